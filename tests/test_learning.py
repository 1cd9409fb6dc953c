"""GP posterior against dense NumPy, recovery of known omega, data collection, errors."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import erf

import safestab as ss
from safestab import NonFiniteError, ParameterError
from safestab.errors import DimensionError
from safestab.learning import (
    GaussianProcessModel,
    SklearnGPAdapter,
    beta_lemma2,
    calibration,
    collect_data,
    confidence,
    information_gain,
)
from safestab.scenarios import load_scenario

NOMINAL_COVERAGE_BETA2 = float(erf(2 / np.sqrt(2)))  # 0.9545 for a Gaussian at 2 sigma


def _dense_kernel(kind, amp, ls, x1, x2):
    r2 = np.sum(((x1[:, None, :] - x2[None, :, :]) / ls) ** 2, -1)
    if kind == "se":
        return amp**2 * np.exp(-0.5 * r2)
    r = np.sqrt(5 * r2)
    return amp**2 * (1 + r + 5 * r2 / 3) * np.exp(-r)


@pytest.fixture(scope="module")
def toy_data():
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, size=(60, 2))
    y = np.stack([np.sin(x[:, 0]) * x[:, 1], np.cos(x[:, 1])], 1) + 0.05 * rng.normal(size=(60, 2))
    return x, y


@pytest.mark.parametrize("kind", ["se", "matern52"])
@pytest.mark.parametrize("mean", ["zero", "constant"])
def test_posterior_matches_dense_numpy(toy_data, kind, mean):
    x, y = toy_data
    gp = GaussianProcessModel(kernel=kind, mean=mean).fit(x, y)
    xq = np.random.default_rng(1).uniform(-2.5, 2.5, size=(25, 2))
    m, v = gp.predict(xq)
    for j in range(2):
        amp, ls, nz, mu = gp.amplitude_[j], gp.lengthscale_[j], gp.noise_[j], gp.mean_[j]
        K = _dense_kernel(kind, amp, ls, x, x) + nz**2 * np.eye(len(x))  # noise_ is effective
        ks = _dense_kernel(kind, amp, ls, x, xq)
        mean_np = ks.T @ np.linalg.solve(K, y[:, j] - mu) + mu  # eq. (12)
        var_np = amp**2 - np.sum(ks * np.linalg.solve(K, ks), 0)  # eq. (13)
        # K's condition number is below 1e6 here, so the two solves agree to ~1e-10.
        np.testing.assert_allclose(m[:, j], mean_np, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(v[:, j], np.maximum(var_np, 0), rtol=1e-6, atol=1e-10 * amp**2)


def test_fitted_hyperparameters_maximise_likelihood(toy_data):
    x, y = toy_data
    gp = GaussianProcessModel().fit(x, y, components=[0])
    # perturbing any hyperparameter must not increase the marginal likelihood (local optimum)
    from safestab.learning.gp import _kernel

    def lml(amp, ls, nz):
        K = np.array(_kernel("se", amp, jnp.asarray(ls))(jnp.asarray(x), jnp.asarray(x)))
        K += nz**2 * np.eye(len(x))
        sign, logdet = np.linalg.slogdet(K)
        return (
            -0.5 * y[:, 0] @ np.linalg.solve(K, y[:, 0])
            - 0.5 * logdet
            - 0.5 * len(x) * np.log(2 * np.pi)
        )

    base = lml(gp.amplitude_[0], gp.lengthscale_[0], gp.noise_[0])
    np.testing.assert_allclose(base, gp.log_marginal_likelihood_[0], rtol=1e-6)
    for f in (0.9, 1.1):
        assert lml(gp.amplitude_[0] * f, gp.lengthscale_[0], gp.noise_[0]) <= base + 1e-6
        assert lml(gp.amplitude_[0], gp.lengthscale_[0] * f, gp.noise_[0]) <= base + 1e-6
        assert lml(gp.amplitude_[0], gp.lengthscale_[0], gp.noise_[0] * f) <= base + 1e-6


def test_recover_acc_drag_mismatch():
    sc = load_scenario("stress")
    data = collect_data(
        sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
        u_low=-0.3, u_high=0.3, n_samples=600, rate=10, horizon=10, noise_std=1e-3, seed=1,
    )  # fmt: skip
    train, test = data.split(0.33, seed=0)
    gp = GaussianProcessModel().fit(train.x, train.y, components=[0])
    omega = np.asarray(sc.omega(test.x))
    cal = calibration(gp, test.x, omega, 2.0)
    assert np.mean(np.abs(omega[:, 0])) > 0.3  # the mismatch is about 0.6 m/s^2
    assert cal.rmse[0] < 1e-3  # stated accuracy: 1 mm/s^2, i.e. < 0.2 % of the mismatch
    assert cal.per_component[0] >= NOMINAL_COVERAGE_BETA2
    _, std = gp.predict(test.x)
    assert np.all(np.asarray(std)[:, 1:] == 0)  # skipped components are exact


def test_recover_nonlinear_function_of_two_states():
    nom = ss.ControlAffineSystem(
        lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.array([[0.0], [1.0]]), 2
    )

    def om(x):
        return jnp.array([0.3 * jnp.sin(x[0]) * x[1], 0.5 * jnp.cos(x[0]) - 0.2 * x[1] ** 2])

    data = collect_data(
        nom.with_disturbance(om), nom, x0=([-2, -2], [2, 2]), u_low=-1, u_high=1,
        n_samples=600, rate=10, horizon=5, noise_std=1e-2, seed=2,
    )  # fmt: skip
    train, test = data.split(0.33, seed=0)
    w = np.asarray(jnp.stack([om(x) for x in jnp.asarray(test.x)]))
    for kind in ("se", "matern52"):
        cal = calibration(GaussianProcessModel(kernel=kind).fit(train.x, train.y), test.x, w, 2.0)
        assert np.all(cal.rmse < 0.01)  # stated accuracy: 1e-2 on a function of size ~0.3
        assert np.all(cal.per_component >= NOMINAL_COVERAGE_BETA2)


def test_collect_data_seeded_and_finite_difference_order():
    sc = load_scenario("stress")
    kw = dict(x0=(sc.x0_low, sc.x0_high), u_low=-0.3, u_high=0.3, n_samples=200, horizon=4, seed=3)
    a = collect_data(sc.system("true"), sc.system("nominal"), rate=10, **kw)
    b = collect_data(sc.system("true"), sc.system("nominal"), rate=10, **kw)
    np.testing.assert_array_equal(a.x, b.x)
    errs = []
    for rate in (10.0, 20.0):
        exact = collect_data(sc.system("true"), sc.system("nominal"), rate=rate, **kw)
        fd = collect_data(
            sc.system("true"), sc.system("nominal"), rate=rate, derivative="finite_difference", **kw
        )
        np.testing.assert_array_equal(exact.x, fd.x)
        errs.append(np.sqrt(np.mean((fd.xdot - exact.xdot) ** 2)))
    # forward difference within the hold interval: error ~ xddot / (2 rate), first order
    assert 1.6 < errs[0] / errs[1] < 2.4


def test_save_load_roundtrip(toy_data, tmp_path):
    x, y = toy_data
    gp = GaussianProcessModel(kernel="matern52", mean="constant").fit(x, y, components=[1])
    gp.save(tmp_path / "gp.npz")
    back = GaussianProcessModel.load(tmp_path / "gp.npz")
    xq = np.random.default_rng(2).normal(size=(10, 2))
    for got, want in zip(back.predict(xq), gp.predict(xq), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    assert back.components_ == (1,)


def test_sklearn_adapter_matches_builtin(toy_data):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, Matern

    x, y = toy_data
    for kind in ("se", "matern52"):
        gp = GaussianProcessModel(kernel=kind).fit(x, y)
        regs = {}
        for j in range(2):
            amp, ls = gp.amplitude_[j], gp.lengthscale_[j]
            base = RBF(ls) if kind == "se" else Matern(ls, nu=2.5)
            reg = GaussianProcessRegressor(
                ConstantKernel(amp**2) * base,
                alpha=gp.noise_[j] ** 2,
                optimizer=None,
            )
            regs[j] = reg.fit(x, y[:, j])
        adapter = SklearnGPAdapter(regs, n_states=2)
        system = ss.ControlAffineSystem(lambda s: jnp.array([s[1], -s[0]]), lambda s: jnp.eye(2), 2)
        clf = ss.CLF(lambda s: s @ s, lam=1.0)
        cbf = ss.CBF(lambda s: 4.0 - s @ s, beta=1.0)
        p = dict(kappa=0.3, rho=0.2, phi=1.0, varphi=1.0, gp_beta=2.0)
        c_gp = ss.UniversalController(system, clf, cbf, uncertainty=gp, **p)
        c_sk = ss.UniversalController(system, clf, cbf, uncertainty=adapter, **p)
        xq = np.random.default_rng(4).uniform(-2, 2, size=(30, 2))
        t_gp, t_sk = c_gp.step(xq).terms, c_sk.step(xq).terms
        for a, b in zip(t_gp, t_sk, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
        # and against sklearn's own predict (it includes no noise term for the latent std)
        m_sk, s_sk = regs[0].predict(xq, return_std=True)
        m_ad, s_ad = (np.asarray(v) for v in jax_vmap_mean_std(adapter, xq))
        np.testing.assert_allclose(m_ad[:, 0], m_sk, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(s_ad[:, 0], s_sk, rtol=1e-5, atol=1e-6)


def jax_vmap_mean_std(model, x):
    import jax

    return jax.vmap(model.mean_std)(jnp.asarray(x))


def test_lemma2_beta_and_information_gain(toy_data):
    x, y = toy_data
    gp = GaussianProcessModel().fit(x, y, components=[0])
    amp, ls, nz = gp.amplitude_[0], gp.lengthscale_[0], gp.noise_[0]
    s2 = nz**2
    K = _dense_kernel("se", amp, ls, x, x)
    gamma_np = 0.5 * np.linalg.slogdet(np.eye(len(x)) + K / s2)[1]
    np.testing.assert_allclose(information_gain(gp), [gamma_np], rtol=1e-8)
    b = beta_lemma2(1.5, 2.0, 99, 0.01)
    np.testing.assert_allclose(
        b, np.sqrt(2 * 1.5**2 + 300 * 2.0 * np.log(100 / 0.01) ** 3), rtol=1e-14
    )
    rep = confidence(gp, rkhs_norm=1.0, delta=0.01)
    assert rep.method == "lemma2" and rep.beta[1] == 0.0
    np.testing.assert_allclose(rep.probability, 0.99, rtol=1e-15)  # one learned component
    user = confidence(gp, beta=2.0)
    assert user.beta.tolist() == [2.0, 0.0]
    assert user.probability is None and "no guarantee" in user.statement


# ---- errors -----------------------------------------------------------------------------


def test_learning_errors(toy_data):
    x, y = toy_data
    bad = y.copy()
    bad[3, 1] = np.nan
    with pytest.raises(NonFiniteError, match=r"y must be finite"):
        GaussianProcessModel().fit(x, bad)
    with pytest.raises(DimensionError, match=r"y must have the same shape as x"):
        GaussianProcessModel().fit(x, y[:, :1])
    with pytest.raises(DimensionError, match=r"x must have shape \(Q, n\)"):
        GaussianProcessModel().fit(x[:, 0], y[:, 0])
    with pytest.raises(
        ParameterError, match=r"too few samples to fit 4 hyperparameters per component: got 4"
    ):
        GaussianProcessModel().fit(x[:4], y[:4])
    with pytest.raises(ParameterError, match=r"noise must be >= 0.0, got -0.1"):
        GaussianProcessModel(noise=-0.1)
    with pytest.raises(ParameterError, match=r"kernel must be one of"):
        GaussianProcessModel(kernel="rbf")
    for delta in (0.0, 1.0, 1.5):
        with pytest.raises(ParameterError, match=r"delta must be"):
            beta_lemma2(1.0, 1.0, 10, delta)
    with pytest.raises(ParameterError, match=r"delta must be"):
        ss.joint_probability(-0.1, 3)
    with pytest.raises(RuntimeError, match=r"not fitted yet"):
        GaussianProcessModel().predict(x)
    sc = load_scenario("stress")
    with pytest.raises(ParameterError, match=r"noise_std must be >= 0.0"):
        collect_data(
            sc.system(),
            sc.system("nominal"),
            x0=(sc.x0_low, sc.x0_high),
            u_low=-1,
            u_high=1,
            noise_std=-1.0,
        )
    with pytest.raises(ParameterError, match=r"'controller' excitation needs controller="):
        collect_data(
            sc.system(),
            sc.system("nominal"),
            x0=(sc.x0_low, sc.x0_high),
            u_low=-1,
            u_high=1,
            excitations=("controller",),
        )


def test_controller_excitation_stays_in_range_and_follows_controller():
    sc = load_scenario("stress")
    clf, cbf = sc.certificates()
    ctrl = ss.UniversalController(
        sc.system("nominal"), clf, cbf, kappa=0.2, rho=0.1, phi=1e-4, varphi=0.0, slack_weight=10.0
    )
    kw = dict(
        x0=(sc.x0_low, sc.x0_high),
        u_low=-0.3,
        u_high=0.3,
        n_samples=300,
        horizon=5,
        excitations=("controller",),
    )
    data = collect_data(
        sc.system("true"),
        sc.system("nominal"),
        controller=ctrl.input_fn,
        controller_noise=0.0,
        **kw,
    )
    assert np.all(np.abs(data.u) <= 0.3)  # saturated to the excitation range, as documented
    expected = np.clip(np.asarray(ctrl.input_fn(jnp.asarray(data.x))), -0.3, 0.3)
    np.testing.assert_allclose(data.u, expected, rtol=1e-10, atol=1e-12)
    noisy = collect_data(
        sc.system("true"),
        sc.system("nominal"),
        controller=ctrl.input_fn,
        controller_noise=0.1,
        **kw,
    )
    assert 0.0 < np.std(
        noisy.u - np.clip(np.asarray(ctrl.input_fn(jnp.asarray(noisy.x))), -0.3, 0.3)
    )
