"""GP-robust Lie terms (Lemma 3) and probabilistic compatibility (Lemma 4, eq. (20))."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
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


def test_clf_layer_zero_is_lemma_3_bit_for_bit_and_leaves_the_cbf_margin_alone():
    rng = np.random.default_rng(7)
    gV, gh, mean = (jnp.asarray(rng.normal(size=(50, 3))) for _ in range(3))
    std = jnp.asarray(rng.uniform(0.0, 1.0, size=(50, 3)))
    plain = robust_margins(gV, gh, mean, std, 2.0)
    zero = robust_margins(gV, gh, mean, std, 2.0, 0.0)
    layered = robust_margins(gV, gh, mean, std, 2.0, 0.3)
    np.testing.assert_array_equal(np.asarray(zero.delta_V), np.asarray(plain.delta_V))
    np.testing.assert_array_equal(np.asarray(layered.delta_h), np.asarray(plain.delta_h))
    # a traced zero takes the other branch of the code: Lemma 3's term up to the rounding of
    # a differently compiled sum (a few units in the last place of its terms' magnitude)
    traced = jax.jit(lambda e: robust_margins(gV, gh, mean, std, 2.0, e).delta_V)(0.0)
    for bad, error in ((-0.1, ss.ParameterError), (np.nan, ss.NonFiniteError)):
        with pytest.raises(error, match="clf_layer"):
            robust_margins(gV, gh, mean, std, 2.0, bad)
    with pytest.raises(ss.DimensionError, match=r"clf_layer must be a scalar, got shape \(2,\)"):
        robust_margins(gV, gh, mean, std, 2.0, [0.1, 0.2])
    size = np.sum(np.abs(gV * mean) + np.abs(gV) * 2.0 * std, 1)
    assert np.all(np.abs(np.asarray(traced) - np.asarray(plain.delta_V)) <= 8e-16 * size)


def test_clf_layer_gives_up_at_most_half_eps_times_the_band_norm():
    # The documented bound: 0 <= Lemma 3's term - the smoothed one <= (eps / 2) |beta sigma|,
    # checked on gradients from 1e-6 to 1e3 times eps; and the smoothed term is quadratic in
    # |dV/dx| near the goal (within 1 % of |g|^2 / eps times its direction's sum).
    rng = np.random.default_rng(8)
    eps, beta = 0.2, np.array([1.5, 3.0, 0.5])
    direction = rng.normal(size=(400, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    scale = eps * 10.0 ** rng.uniform(-6, 3, size=(400, 1))
    gV = direction * scale
    std = rng.uniform(0.0, 2.0, size=(400, 3))
    zero = np.zeros((400, 3))
    full = np.sum(np.abs(gV) * beta * std, 1)
    smooth = np.asarray(robust_margins(gV, gV, zero, std, beta, eps).delta_V)
    gap = full - smooth
    bound = eps / 2 * np.linalg.norm(beta * std, axis=1)
    assert np.all(gap >= -1e-15 * full) and np.all(gap <= bound * (1 + 1e-12))
    near = scale[:, 0] < 1e-3 * eps
    quadratic = scale[near, 0] / eps * full[near]
    np.testing.assert_allclose(smooth[near], quadratic, rtol=1e-2)
    # derivatives finite from 1e-300 to 1e300 (tiny and huge gradients, tiny and huge eps)
    # and equal to central differences at ordinary magnitudes
    for e in (1e-300, 0.2, 1e300):
        for size in (1e-300, 1e-160, 1e-3, 1.0, 1e300):
            x = size * jnp.array([1.0, 0.5, -1.0])
            d = jax.grad(
                lambda x, e: robust_margins(x, x, jnp.zeros(3), jnp.ones(3), beta, e).delta_V,
                argnums=(0, 1),
            )(x, e)
            assert np.all(np.isfinite(np.asarray(d[0]))) and np.isfinite(float(d[1]))

    def smooth_term(x, e):
        return float(robust_margins(x, x, jnp.zeros(3), jnp.ones(3), beta, e).delta_V)

    x0, h = jnp.array([0.1, 0.05, -0.1]), 1e-7
    grad_x = jax.grad(lambda x: robust_margins(x, x, 0 * x, 0 * x + 1, beta, eps).delta_V)(x0)
    fd = (smooth_term(x0.at[0].add(h), eps) - smooth_term(x0.at[0].add(-h), eps)) / (2 * h)
    assert float(grad_x[0]) == pytest.approx(fd, rel=1e-6)
    # at the goal itself: finite, no robust term, and a finite derivative
    at_goal = robust_margins(jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), jnp.ones(3), beta, eps)
    assert float(at_goal.delta_V) == 0.0
    grad = jax.grad(
        lambda x: robust_margins(2 * x, 2 * x, jnp.zeros(3), jnp.ones(3), beta, eps).delta_V
    )(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(grad)))


def _integrator_with_unknown_drift(layer, *, dt=0.02, t_final=10.0):
    # x' = u + w with a constant drift w that neither the nominal model nor the uncertainty
    # model's mean (0) has; its std, 0.2 per component, covers w at beta = 2, so the GP-robust
    # CLF term is beta sigma |dV/dx| with V = |x|^2; the barrier is far away. (A nonzero mean
    # at the goal is another cause of chattering: the goal is then no equilibrium of the
    # corrected model; docs/obstacle.md.)
    w = jnp.array([0.05, -0.03])
    nominal = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    plant = ss.ControlAffineSystem(lambda x: w, lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    cbf = ss.CBF(lambda x: 400.0 - x @ x, beta=1.0)  # a disc of radius 20 m about the goal

    class Band:
        n_states = 2

        def mean_std(self, x):
            return jnp.zeros(2), jnp.full(2, 0.2)

    extra = {} if layer is None else {"robust_clf_layer": layer}
    ctrl = ss.UniversalController(
        nominal, clf, cbf, kappa=0.1, rho=0.1, phi=0.01, varphi=0.01,
        uncertainty=Band(), gp_beta=2.0, **extra,
    )  # fmt: skip
    tr = ss.simulate(ctrl, jnp.array([1.0, 0.5]), t_final=t_final, dt=dt, plant=plant)
    u, x = np.asarray(tr.u), np.asarray(tr.x)
    late = slice(len(u) // 2, None)  # after the transient
    variation = np.sum(np.linalg.norm(np.diff(u[late], axis=0), axis=1)) / (t_final / 2)
    return variation, np.max(np.sum(x[late] ** 2, 1))


def test_clf_layer_removes_the_chattering_at_the_goal_and_keeps_the_stated_bound():
    # Lemma 3's term: an input of about 2 beta sigma that flips across the goal; the sampled
    # loop chatters. With the documented rule eps >= 4 |beta sigma| lambda_max(P) dt the input
    # vanishes continuously; V stays below eps max|beta sigma| / (2 lambda).
    dt, beta_sigma = 0.02, 2.0 * 0.2 * np.sqrt(2)
    eps = 4 * beta_sigma * 1.0 * dt * 1.5
    tv_plain, v_plain = _integrator_with_unknown_drift(None, dt=dt)
    tv_layer, v_layer = _integrator_with_unknown_drift(eps, dt=dt)
    assert tv_plain > 1.0  # m/s^2: chattering of about 2 beta sigma every step or so
    assert tv_layer < 1e-2 * tv_plain
    assert v_layer <= eps * beta_sigma / (2 * 1.0)
    # the guarantee given up (a neighbourhood instead of the point) costs nothing here: the
    # chattering loop keeps further from the goal than the smoothed one
    assert v_layer < v_plain


def test_robust_clf_layer_is_checked_and_tunable():
    system, clf, cbf = unicycle_obstacle()
    base = dict(kappa=0.1, rho=0.1, phi=0.01, varphi=0.01)

    class Band:
        n_states = 3

        def mean_std(self, x):
            return jnp.zeros(3), jnp.full(3, 0.1)

    with pytest.raises(ss.ParameterError, match="robust_clf_layer.*needs uncertainty"):
        ss.UniversalController(system, clf, cbf, robust_clf_layer=0.1, **base)
    with pytest.raises(ss.ParameterError, match="robust_clf_layer must be a finite number >= 0"):
        ss.UniversalController(system, clf, cbf, uncertainty=Band(), robust_clf_layer=-1.0, **base)
    ctrl = ss.UniversalController(system, clf, cbf, uncertainty=Band(), **base)
    layered = ss.UniversalController(
        system, clf, cbf, uncertainty=Band(), robust_clf_layer=0.5, **base
    )
    assert "robust_clf_layer" in layered.tunables() and "robust_clf_layer" not in ctrl.tunables()
    x = jnp.array([0.3, -0.2, 0.1])
    zero = layered.replace(robust_clf_layer=0.0)
    np.testing.assert_array_equal(np.asarray(zero.step(x).u), np.asarray(ctrl.step(x).u))
    # the layer lowers a~ by at most the documented amount, computed here by hand from the
    # CLF's gradient, and leaves c~ alone
    t0, t1 = ctrl.terms_point(x), layered.terms_point(x)
    g = np.asarray(clf.gradient(x))
    n = np.linalg.norm(g)
    by_hand = (1 - n / np.sqrt(n * n + 0.25)) * np.sum(np.abs(g) * 2.0 * 0.1)
    assert float(t0.a) - float(t1.a) == pytest.approx(by_hand, rel=1e-12)
    assert by_hand <= 0.5 / 2 * np.linalg.norm(np.full(3, 2.0 * 0.1))
    assert float(t1.c) == float(t0.c)


def test_safety_filter_robust_clf_layer_matches_the_margin_by_hand():
    # One hard CLF row and an inactive barrier, u_nom = 0: the filter's input is the least-norm
    # one on the CLF row, u = -a~ b / |b|^2, so -b.u is the row's a~, checked against a~
    # written by hand (V = |x|^2, f = 0, g = I) with and without the layer.
    robot = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: x @ x, lam=1.0)
    far = ss.CBF(lambda x: 100.0 - x @ x, beta=1.0)
    m, sd = np.array([0.02, -0.01]), np.array([0.1, 0.2])

    class Band:
        n_states = 2

        def mean_std(self, x):
            return jnp.asarray(m), jnp.asarray(sd)

    common = dict(clfs=clf, uncertainty=Band(), gp_beta=2.0)
    x = np.array([0.3, 0.2])
    g = 2 * x
    n = np.linalg.norm(g)
    robust = np.sum(np.abs(g) * 2.0 * sd)
    for layer, shrink in ((None, 1.0), (0.5, n / np.sqrt(n * n + 0.25))):
        extra = {} if layer is None else {"robust_clf_layer": layer}
        filt = ss.SafetyFilter(robot, far, **common, **extra)
        out = filt.step(jnp.asarray(x))
        a_tilde = x @ x + g @ m + shrink * robust
        assert -float(g @ np.asarray(out.u)) == pytest.approx(a_tilde, rel=1e-12)
        assert bool(np.all(np.asarray(out.cbf_satisfied)))
    assert "robust_clf_layer" in filt.tunables()
    zero = filt.replace(robust_clf_layer=0.0)
    plain = ss.SafetyFilter(robot, far, **common)
    np.testing.assert_array_equal(np.asarray(zero.step(x).u), np.asarray(plain.step(x).u))
    with pytest.raises(ss.ParameterError, match="robust_clf_layer.*needs uncertainty"):
        ss.SafetyFilter(robot, far, clfs=clf, robust_clf_layer=0.5)
    with pytest.raises(ss.DimensionError, match="robust_clf_layer must be a scalar"):
        ss.SafetyFilter(robot, far, robust_clf_layer=[0.1, 0.2], **common)
