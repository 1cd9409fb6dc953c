"""GP-robust Lie terms (Lemma 3) and probabilistic compatibility (Lemma 4, eq. (20))."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import erf

import safestab as ss
from safestab import LieTerms, probabilistic_compatibility, robust_lie_terms, robust_margins

from .systems_zoo import unicycle_obstacle


def test_zero_sigma_equals_mean_corrected_system():
    # With sigma = 0 the robust terms are the Lie terms of the model f + m(x): computed here
    # by a different path (autodiff on the corrected system).
    system, clf, cbf = unicycle_obstacle()

    def mean_fn(x):
        return jnp.array([0.2 * jnp.sin(x[1]), -0.1 * x[0], 0.05])

    xs = np.random.default_rng(0).normal(size=(20, 3))
    nominal = ss.lie_terms(system, clf, cbf, xs)
    m = jax.vmap(mean_fn)(jnp.asarray(xs))
    robust = robust_lie_terms(
        nominal, clf.gradient(xs), cbf.gradient(xs), m, jnp.zeros_like(m), 2.0
    )
    corrected = ss.lie_terms(system.with_disturbance(mean_fn), clf, cbf, xs)
    for a, b in zip(robust, corrected, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def test_robust_margins_bound_posterior_samples_at_stated_rate():
    rng = np.random.default_rng(1)
    n, k, beta = 3, 20000, 2.0
    gV, gh = rng.normal(size=n), rng.normal(size=n)
    mean, std = rng.normal(size=n), rng.uniform(0.1, 1.0, size=n)
    dV, dh = robust_margins(
        jnp.asarray(gV), jnp.asarray(gh), jnp.asarray(mean), jnp.asarray(std), beta
    )
    omega = mean + std * rng.normal(size=(k, n))  # samples of the independent posteriors
    clf_ok = omega @ gV <= float(dV)
    cbf_ok = omega @ gh >= float(dh)
    stated = erf(beta / np.sqrt(2)) ** n  # probability all components lie in their bands
    # the bound holds at least whenever every component is inside its band; 4 binomial
    # standard deviations of slack for the Monte Carlo estimate
    slack = 4 * np.sqrt(stated * (1 - stated) / k)
    assert clf_ok.mean() >= stated - slack
    assert cbf_ok.mean() >= stated - slack
    inside = np.all(np.abs(omega - mean) <= beta * std, 1)
    assert np.all(clf_ok[inside]) and np.all(cbf_ok[inside])  # Lemma 3 deterministically


def _terms(a, b, c, d):
    return LieTerms(jnp.asarray(a), jnp.asarray(b), jnp.asarray(c), jnp.asarray(d))


def test_probabilistic_compatibility_branches():
    p = dict(kappa=0.0, rho=0.0, phi=0.0, varphi=0.0)
    M = ss.RobustMargins
    # non-parallel: compatible before and after, whatever the margins
    r = probabilistic_compatibility(
        _terms(1.0, [1.0, 0.0], -1.0, [0.0, 1.0]), M(jnp.asarray(5.0), jnp.asarray(-5.0)), **p
    )
    assert bool(r.nominal_compatible) and bool(r.updated) and not bool(r.parallel)
    # parallel, same direction: u <= -a~ and u >= -c~. a = -2, c = 1 -> u <= 2, u >= -1: OK.
    t = _terms(-2.0, [1.0], 1.0, [1.0])
    r = probabilistic_compatibility(t, M(jnp.asarray(0.5), jnp.asarray(-0.5)), **p)
    assert (
        bool(r.parallel) and bool(r.nominal_compatible) and bool(r.updated)
    )  # u <= 1.5, u >= -0.5
    # eq. (18): Delta_V d.b - Delta_h |b|^2 = 0.5 + 0.5 >= 0; eq. (19) likewise
    assert bool(r.clf_condition) and bool(r.cbf_condition) and bool(r.lemma4)
    # larger margins make the robust conditions incompatible: u <= -1 and u >= 2.5
    r = probabilistic_compatibility(t, M(jnp.asarray(3.0), jnp.asarray(-3.5)), **p)
    assert bool(r.nominal_compatible) and not bool(r.updated)
    # ... although Lemma 4's printed conditions (18), (19) hold: the lemma's sign is off
    assert bool(r.lemma4)
    # anti-parallel: always compatible
    r = probabilistic_compatibility(
        _terms(5.0, [1.0], 5.0, [-1.0]), M(jnp.asarray(9.0), jnp.asarray(-9.0)), **p
    )
    assert bool(r.updated) and bool(r.parallel)
    # negative (18): Delta_V d.b - Delta_h |b|^2 < 0
    r = probabilistic_compatibility(t, M(jnp.asarray(-1.0), jnp.asarray(0.5)), **p)
    assert not bool(r.clf_condition) and not bool(r.cbf_condition) and not bool(r.lemma4)
    r = probabilistic_compatibility(
        t, M(jnp.asarray(0.0), jnp.asarray(0.0)), delta=0.01, n_components=3, **p
    )
    np.testing.assert_allclose(r.probability, 0.99**3, rtol=1e-15)
