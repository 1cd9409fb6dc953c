"""The Q-independent GP cache against the exact GP, and the fused controller step."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.learning import FastGP, GaussianProcessModel, collect_data
from safestab.scenarios import load_scenario


@pytest.fixture(scope="module")
def acc_gp():
    sc = load_scenario("stress")
    data = collect_data(
        sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
        u_low=-0.3, u_high=0.3, n_samples=1400, rate=10, horizon=20, noise_std=1e-3, seed=0,
    )  # fmt: skip
    train, test = data._take(np.arange(800)), data._take(np.arange(800, 1400))
    return sc, GaussianProcessModel().fit(train.x, train.y, hyper_subset=300), test


def test_fast_cache_against_exact(acc_gp):
    sc, gp, test = acc_gp
    fast = FastGP(gp, n_inducing=32)
    widening = fast.calibrate(test.x[:300], 2.0)
    assert np.all(widening >= 1.0) and np.all(widening < 10.0)
    held = test.x[300:]
    m_ex, v_ex = gp.predict(held)
    m_fa, s_fa = jax.vmap(fast.mean_std)(jnp.asarray(held))
    s_ex = np.sqrt(np.asarray(v_ex))
    # documented tolerance: mean within 0.5 exact posterior std plus 1e-5 m/s^2 (pivoting stops
    # once the residual prior variance is 1e-12 of the signal variance)
    assert np.all(np.abs(np.asarray(m_fa - m_ex))[:, 0] <= 0.5 * s_ex[:, 0] + 1e-5)
    # the widened band contains the exact band at every held-out state (not only those used to
    # calibrate it): std never below the exact one by more than the mean offset allows
    np.testing.assert_array_equal(fast.coverage_of_exact_band(held, 2.0), 1.0)
    assert np.all(2.0 * np.asarray(s_fa)[:, 0] >= 2.0 * s_ex[:, 0] - 1e-12)


def test_fast_cache_exact_at_small_q():
    # With every training input an inducing point, the projection is the exact posterior, up
    # to the jitter on Kzz; a wiggly target keeps the lengthscale short and Kzz well
    # conditioned (with a near-singular Kzz the jittered inverse is not Kzz^-1 K = I).
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(30, 2))
    y = np.stack([np.sin(6 * x[:, 0]) * np.cos(5 * x[:, 1]), np.cos(7 * x[:, 1])], 1)
    y = y + 0.01 * rng.normal(size=(30, 2))
    gp = GaussianProcessModel(kernel="matern52").fit(x, y)
    fast = FastGP(gp, n_inducing=30, pivot_tol=0.0)
    assert fast.n_inducing_.tolist() == [30, 30]
    xq = rng.uniform(-1, 1, size=(20, 2))
    m_ex, v_ex = gp.predict(xq)
    m_fa, s_fa = jax.vmap(fast.mean_std)(jnp.asarray(xq))
    # tolerance: jitter (1e-10) times cond(Kzz) (about 1e4 here) times a safety factor of 10
    np.testing.assert_allclose(m_fa, m_ex, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.asarray(s_fa) ** 2, v_ex, rtol=1e-5, atol=1e-7)


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
