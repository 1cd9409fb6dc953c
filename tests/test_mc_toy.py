"""A toy with a known answer: the Monte Carlo machinery against a closed-form probability.

Scalar plant ``x' = u + w`` with a constant random disturbance ``w ~ N(mu, s^2)`` per trial
(per-trial data passed through the scan), nominal model ``x' = u``, CBF ``h = 1 - x`` with rate
``beta``, CLF ``V = (x - 5)^2`` pulling across the boundary. With ``rho = 0`` the relaxed
formula's input is exactly ``u = beta (1 - x)`` here (region P3 of one input, ``u = B / d``),
so with zero-order hold the loop is the linear recursion
``x_{k+1} = x_k + dt (beta (1 - x_k) + w)`` (RK4 is exact for a constant right-hand side):
``h_K = -w/beta + (1 + w/beta) q`` with ``q = (1 - beta dt)^K``, monotone in k, so the run is
safe (``min_k h_k >= 0``) iff ``w <= w* = beta q / (1 - q)``, and
``P(safe) = Phi((w* - mu) / s)``: a hand derivation independent of the code under test.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import safestab as ss
from safestab.montecarlo import clopper_pearson, trial_function

BETA, DT, K = 1.0, 0.01, 100
MU, S = 0.15, 0.1
Q = (1 - BETA * DT) ** K
W_STAR = BETA * Q / (1 - Q)
P_SAFE = float(scipy.stats.norm.cdf((W_STAR - MU) / S))


class _FixedBand:
    """An 'uncertainty model' with mean 0 and std S0: it knows nothing of w."""

    n_states = 1
    S0 = 0.2

    def mean_std(self, x):
        return jnp.zeros(1), jnp.full(1, self.S0)


def _toy(lemma2=False):
    true = ss.ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
    clf = ss.CLF(lambda x: (x[0] - 5.0) ** 2, lam=1.0)
    cbf = ss.CBF(lambda x: 1.0 - x[0], beta=BETA)
    p = dict(kappa=0.0, rho=0.0, phi=0.0, varphi=0.0, slack_weight=10.0)
    band = _FixedBand()  # checked against, not used by the controller (so u = beta h exactly)
    ctrl = ss.UniversalController(true, clf, cbf, **p)
    run = trial_function(
        [ctrl], plant=true, n_steps=K, dt=DT,
        exogenous=lambda t, x, w: jnp.reshape(w, (1,)),
        omega=lambda x, w: jnp.reshape(w, (1,)),
        lemma2=[(band, jnp.ones(1))] if lemma2 else None,
    )  # fmt: skip
    return jax.jit(jax.vmap(run, in_axes=(None, 0)))


def _draw(seed, n):
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(jnp.arange(n))
    return MU + S * jax.vmap(lambda k: jax.random.normal(k))(keys)


def test_each_trial_matches_the_closed_form():
    w = _draw(0, 200)
    rec = _toy()(jnp.zeros(1), w)
    w = np.asarray(w)
    h_final = -w / BETA + (1 + w / BETA) * Q
    expected_min = np.minimum(1.0, h_final)  # h_0 = 1; monotone, so min is h_0 or h_K
    # the recursion in floating point differs from the closed form by rounding only
    np.testing.assert_allclose(np.asarray(rec["min_h"])[:, 0], expected_min, atol=1e-12)


def test_lemma2_event_uses_the_true_omega():
    # the band is |omega - 0| <= 1 * 0.2; omega is the trial's own w, which the model never sees
    w = _draw(1, 200)
    rec = _toy(lemma2=True)(jnp.zeros(1), w)
    inside = np.abs(np.asarray(w)) <= _FixedBand.S0
    viol = np.asarray(rec["lemma2_violations"])[:, 0]
    assert np.array_equal(viol == 0, inside)
    assert np.all(viol[~inside] == K + 1)  # every visited state t_0 .. t_K
    assert 0 < inside.sum() < inside.size  # both outcomes occur, so the test can fail


@pytest.mark.slow
def test_interval_covers_the_known_probability_at_the_stated_rate():
    # R repeated seeds, N trials each. An exact 95 % Clopper-Pearson interval misses the true
    # p with probability <= 0.05, so misses ~ at most Binomial(R, 0.05): with R = 30 we fail
    # at >= 7 misses, P(Binomial(30, 0.05) >= 7) = 1.4e-3, the documented false-alarm rate.
    run = _toy()
    r, n = 30, 300
    misses, pooled = 0, 0
    for seed in range(r):
        rec = run(jnp.zeros(1), _draw(seed + 100, n))
        k = int(np.sum(np.asarray(rec["min_h"])[:, 0] >= 0))
        lo, hi = clopper_pearson(k, n)
        misses += not lo <= P_SAFE <= hi
        pooled += k
    assert scipy.stats.binom.sf(6, r, 0.05) < 2e-3
    assert misses < 7
    # and the pooled estimate: a two-sided exact binomial test at level 1e-3
    assert scipy.stats.binomtest(pooled, r * n, P_SAFE).pvalue > 1e-3


def test_results_do_not_depend_on_the_batch_split():
    run = _toy(lemma2=True)
    w = _draw(5, 12)
    whole = run(jnp.zeros(1), w)
    parts = [run(jnp.zeros(1), w[i : i + 5]) for i in (0, 5, 10)]
    for key, value in whole.items():
        got = np.concatenate([np.asarray(p[key]) for p in parts])
        assert np.array_equal(got, np.asarray(value))
