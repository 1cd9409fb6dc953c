"""The Q-independent GP cache against the exact GP, and the fused controller step."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.errors import DimensionError, InducingPointsWarning, ParameterError
from safestab.learning import FastGP, GaussianProcessModel, collect_data
from safestab.scenarios import load_scenario


@pytest.fixture(scope="module")
def acc_gp():
    sc = load_scenario("stress")
    data = collect_data(
        sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
        u_low=-0.3, u_high=0.3, n_samples=1400, rate=10, horizon=20, noise_std=1e-3, seed=0,
    )  # fmt: skip
    train, test = data.take(np.arange(800)), data.take(np.arange(800, 1400))
    gp = GaussianProcessModel(n_restarts=0).fit(train.x, train.y, hyper_subset=300)
    return sc, gp, test


def _check_bound(gp, fast, x, label):
    m_ex, v_ex = (np.asarray(a) for a in gp.predict(x))
    m_fa, s_fa = fast.predict(x)
    m_one, s_one = jax.vmap(fast.mean_std)(jnp.asarray(x[:5]))  # the controller's path
    # same formulas, fused differently by XLA: rounding of M-term sums (1e-9 relative on the
    # mean); the std goes through r^2 = amp^2 - |a|^2, whose cancellation (up to the cache's
    # allowance 2 (M + 2) u amp^2 ~ 1e-13) moves a std of 1e-3 by up to 1e-5 relative
    # (the weights w are large and cancel in k . w: 1e-7 relative on the mean)
    np.testing.assert_allclose(m_one, m_fa[:5], rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(s_one, s_fa[:5], rtol=1e-5, atol=1e-12)
    merr = fast.mean_error_bound(x)
    comps = list(gp.components_)
    amp2 = gp.amplitude_**2
    q = gp.x_train_.shape[0]
    # rounding of the exact predictor's own amp^2 - |L^-1 k|^2: about Q u amp^2 (u = 1.1e-16),
    # with a factor 4 of slack; the cache adds its own allowance for its side
    tol_var = 4 * q * 1.1e-16 * amp2
    s_ex2 = v_ex[:, comps]
    assert np.all(s_fa[:, comps] ** 2 >= s_ex2 - tol_var), label  # variance bound
    gap = np.abs(m_fa - m_ex)[:, comps]
    # mean bound |m~ - m| <= E r(x), up to the exact mean's rounding (Q u sum |alpha_i k_i|)
    tol_mean = 4 * q * 1.1e-16 * np.abs(gp.alpha_).sum(1) * gp.amplitude_**2 + 1e-14
    assert np.all(gap <= merr + tol_mean), label
    for beta in (1.0, 2.0, 3.0):  # every beta >= min_beta = 1: the cache's band contains the exact
        lo = m_fa[:, comps] - beta * s_fa[:, comps]
        hi = m_fa[:, comps] + beta * s_fa[:, comps]
        s_ex = np.sqrt(s_ex2)
        slack = beta * np.sqrt(tol_var) + tol_mean
        assert np.all(lo <= m_ex[:, comps] - beta * s_ex + slack), label
        assert np.all(hi >= m_ex[:, comps] + beta * s_ex - slack), label


@pytest.mark.parametrize("kind", ["se", "matern52"])
def test_cache_band_contains_exact_band_everywhere(acc_gp, kind):
    sc, gp_se, test = acc_gp
    gp = gp_se
    if kind == "matern52":
        data = collect_data(
            sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
            u_low=-0.3, u_high=0.3, n_samples=400, rate=10, horizon=20, noise_std=1e-3, seed=5,
        )  # fmt: skip
        gp = GaussianProcessModel(kernel="matern52", n_restarts=0).fit(
            data.x, data.y, hyper_subset=200
        )
    lo, hi = np.asarray(sc.x0_low), np.asarray(sc.x0_high)
    rng = np.random.default_rng(0)
    # ten times the data's box around its centre, and the data's own distribution
    far = (lo + hi) / 2 + 10 * (hi - lo) / 2 * rng.uniform(-1, 1, size=(500, 3))
    near = test.x[:200]
    for m in (4, 16, 64):  # the range 4 to 64; the default 32 is tested below
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", InducingPointsWarning)  # small M is flagged
            fast = FastGP(gp, n_inducing=m)
        _check_bound(gp, fast, far, f"{kind} M={m} far")
        _check_bound(gp, fast, near, f"{kind} M={m} near")
        np.testing.assert_array_equal(fast.coverage_of_exact_band(far, 2.0), 1.0)


def test_too_few_inducing_points_warn_and_bad_arguments(acc_gp):
    _, gp, test = acc_gp
    with pytest.warns(InducingPointsWarning, match=r"n_inducing=4: for component 0, at \d+%"):
        small = FastGP(gp, n_inducing=4)
    assert small.inflation_at_training_[0] > 0.01
    fast = FastGP(gp, n_inducing=32)  # no warning at the default
    assert np.all(fast.inflation_at_training_ <= 0.01)
    # the price of the guarantee at the default M, in distribution: the cache's std is a
    # modest multiple of the exact one (measured 1.0 to 1.9 on this data; 3 is the bound here)
    _, v_ex = gp.predict(test.x)
    _, s_fa = fast.predict(test.x)
    assert np.median(np.asarray(s_fa) / np.sqrt(np.asarray(v_ex))) < 3.0
    with pytest.raises(ParameterError, match=r"n_inducing must be an integer >= 1, got 0"):
        FastGP(gp, n_inducing=0)
    with pytest.raises(ParameterError, match=r"min_beta must be > 0.0, got 0.0"):
        FastGP(gp, min_beta=0.0)
    with pytest.raises(DimensionError, match=r"x must have shape \(N, 3\)"):
        fast.mean_error_bound(test.x[:, :2])


def test_fast_cache_exact_at_small_q():
    # With every training input an inducing point, the projection is the exact posterior, up
    # to the jitter on Kzz; a wiggly target keeps the lengthscale short and Kzz well
    # conditioned (with a near-singular Kzz the jittered inverse is not Kzz^-1 K = I).
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(30, 2))
    y = np.stack([np.sin(6 * x[:, 0]) * np.cos(5 * x[:, 1]), np.cos(7 * x[:, 1])], 1)
    y = y + 0.01 * rng.normal(size=(30, 2))
    gp = GaussianProcessModel(kernel="matern52").fit(x, y)
    fast = FastGP(gp, n_inducing=30, pivot_tol=0.0, noise_tol=0.0)
    assert fast.n_inducing_.tolist() == [30, 30]
    xq = rng.uniform(-1, 1, size=(20, 2))
    m_ex, v_ex = gp.predict(xq)
    m_fa, s_fa = jax.vmap(fast.mean_std)(jnp.asarray(xq))
    # tolerance: jitter (1e-10) times cond(Kzz) (about 1e4 here) times a safety factor of 10
    np.testing.assert_allclose(m_fa, m_ex, rtol=1e-5, atol=1e-7)
    # the std is an upper bound: with the jitter, Kj = Kzz + eps I leaves r(x_i)^2 ~ eps =
    # 1e-10 amp^2 at the inducing inputs themselves, which the bound's cross and mean-error
    # terms carry (times sum |alpha_i| ~ 1e3 here): an excess of order 1e-3 relative; 1 %
    s_ex = np.sqrt(np.asarray(v_ex))
    assert np.all(np.asarray(s_fa) >= s_ex - 1e-12)
    assert np.all(np.asarray(s_fa) <= 1.01 * s_ex + 1e-6)


def test_noise_tol_stops_below_the_noise_and_keeps_the_band():
    # component 0 carries a signal far above the noise, component 1 pure noise: the GP gives
    # the latter an amplitude near the noise, whose residual the data cannot resolve
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, size=(300, 2))
    y = np.stack([np.sin(3 * x[:, 0]) + x[:, 1] ** 2, np.zeros(300)], 1)
    y = y + 0.01 * rng.normal(size=(300, 2))
    gp = GaussianProcessModel(kernel="se").fit(x, y)
    full = FastGP(gp, n_inducing=24, noise_tol=0.0)
    fast = FastGP(gp, n_inducing=24, noise_tol=0.1)
    assert fast.n_inducing_[1] < full.n_inducing_[1]
    xs = (gp.x_train_ - gp.x_offset_) / gp.x_scale_
    for j, amp in enumerate(gp.amplitude_):
        m = int(fast.n_inducing_[j])
        z = (fast.inducing_[j, :m] - gp.x_offset_) / gp.x_scale_
        ls = np.asarray(gp.lengthscale_std_[j])

        def k(a, b, amp=amp, ls=ls):  # the SE kernel in standardised units (independent)
            d = ((a[:, None, :] - b[None, :, :]) / ls) ** 2
            return amp**2 * np.exp(-0.5 * d.sum(-1))

        # residual prior variance at the training inputs, by a dense computation
        kxz = k(xs, z)
        resid = amp**2 - np.sum(kxz * np.linalg.solve(k(z, z), kxz.T).T, 1)
        stopped_early = m < min(24, len(xs)) and resid.max() > 1e-10 * amp**2
        if stopped_early:  # stopped by the noise: the residual is below (0.1 noise)^2 ...
            assert resid.max() <= (0.1 * gp.noise_[j]) ** 2 * (1 + 1e-6)
            # ... and one inducing input fewer would not have been (greedy choice)
            kxz1 = kxz[:, : m - 1]
            r1 = amp**2 - np.sum(kxz1 * np.linalg.solve(k(z[: m - 1], z[: m - 1]), kxz1.T).T, 1)
            assert m == 1 or r1.max() > (0.1 * gp.noise_[j]) ** 2
    assert fast.n_inducing_[1] < 24
    # the band still contains the exact band, near the data and far from it
    xq = rng.uniform(-2, 2, size=(400, 2))
    assert np.all(fast.coverage_of_exact_band(xq, 1.0) == 1.0)
    with pytest.raises(ParameterError, match="noise_tol"):
        FastGP(gp, noise_tol=-1.0)


def test_fused_step_equals_unfused(acc_gp):
    sc, gp, test = acc_gp
    fast = FastGP(gp, n_inducing=32)
    nominal = sc.system("nominal")
    clf, cbf = sc.certificates()
    p = dict(kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi)
    ctrl = ss.UniversalController(
        nominal, clf, cbf, slack_weight=sc.slack_weight, u_min=[-0.3], u_max=[0.3],
        uncertainty=fast, gp_beta=2.0, **p,
    )  # fmt: skip
    xs = test.x[:50]
    fused = np.asarray(ctrl.input_fn(jnp.asarray(xs)))
    # the same pipeline, one public function at a time
    terms = ss.lie_terms(nominal, clf, cbf, xs)
    mean, std = jax.vmap(fast.mean_std)(jnp.asarray(xs))
    robust = ss.robust_lie_terms(terms, clf.gradient(xs), cbf.gradient(xs), mean, std, 2.0)
    res = ss.clf_cbf_relaxed(*robust, slack_weight=sc.slack_weight, **p)
    unfused = np.asarray(ss.project_box(res.u, [-0.3], [0.3]))
    np.testing.assert_allclose(fused, unfused, rtol=1e-12, atol=1e-14)
    for i in range(0, 50, 10):  # single state through the same compiled function family
        np.testing.assert_allclose(
            ctrl.input_fn(jnp.asarray(xs[i])), unfused[i], rtol=1e-12, atol=1e-14
        )
