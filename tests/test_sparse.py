"""SparseGP (inducing points, DTC posterior) against the exact GP and by its rules."""

import jax
import numpy as np
import pytest

from safestab.errors import DimensionError, NonFiniteError, ParameterError
from safestab.learning import GaussianProcessModel, InducingCache, SparseGP, conformal_beta


def _data(q, seed=0, noise=0.05):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, size=(q, 2))
    omega = np.stack([np.sin(x[:, 0]) * np.cos(x[:, 1]), 0.5 * x[:, 0] * x[:, 1]], 1)
    return x, omega + noise * rng.standard_normal(omega.shape), omega


def test_with_every_training_input_inducing_it_is_the_exact_gp():
    x, y, _ = _data(120)
    # all rows for the hyperparameters, no stopping rule: the pivoted Cholesky takes rows
    # until the prior is resolved to rounding at every training input (114 and 39 of them;
    # it used to reach 120 by choosing rows again), and DTC is exact
    sp = SparseGP(120, hyper_subset=120, pivot_tol=0.0, noise_tol=0.0).fit(x, y, seed=3)
    exact = GaussianProcessModel().fit(x, y, hyper_subset=120, seed=3)
    np.testing.assert_allclose(sp.model.amplitude_, exact.amplitude_, rtol=1e-12)
    for j, m in enumerate(sp.n_inducing_):
        assert len(np.unique(sp.inducing_[j, :m], axis=0)) == m  # distinct rows
    xt = np.random.default_rng(1).uniform(-3, 3, size=(200, 2))
    m_s, s_s = sp.predict(xt, return_std=True)
    m_e, s_e = exact.predict(xt, return_std=True)
    # equal in real arithmetic; in float64 the DTC path solves with K_ZZ (all 120 inputs, no
    # noise on the diagonal), whose condition number amplifies rounding: 1e-5 relative here
    np.testing.assert_allclose(m_s, m_e, atol=1e-4 * np.abs(m_e).max())
    np.testing.assert_allclose(s_s, s_e, rtol=1e-2, atol=1e-4 * s_e.max())
    # the jittable single-state form agrees with the batched one (the std to the rounding of
    # amp^2 - |a|^2, whose terms are about amp^2)
    m1, s1 = jax.jit(sp.mean_std)(xt[7])
    scale = float(np.max(sp.model.amplitude_)) ** 2
    np.testing.assert_allclose(np.asarray(m1), m_s[7], rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(s1) ** 2, s_s[7] ** 2, atol=1e-11 * scale)
    # and the Monte Carlo's batched form of the same arrays
    mb, sb = (np.asarray(a) for a in InducingCache.from_fastgp(sp).mean_std_batch(xt))
    np.testing.assert_allclose(mb, m_s, rtol=1e-9, atol=1e-12 * scale)
    np.testing.assert_allclose(sb**2, s_s**2, atol=1e-11 * scale)


def _dtc_by_hand(sp, x, y, xt):
    """The DTC posterior written out from the fit's hyperparameters and inducing inputs, in
    40-digit arithmetic on the same float64 kernel values (its normal equations square
    cond(K_ZZ): in float64 they lose several digits here): ``mean = mu + k_tZ S K_ZX (y - mu)``,
    ``var = k_tt - k_tZ K_ZZ^-1 k_Zt + s^2 k_tZ S k_Zt``, ``S = (s^2 K_ZZ + K_ZX K_XZ)^-1``.
    """
    import mpmath as mp

    from safestab.learning._posterior import kernel_matrix

    mp.mp.dps = 40
    g = sp.model
    xs, ts = ((a - g.x_offset_) / g.x_scale_ for a in (x, xt))
    means, stds = [], []
    for j, comp in enumerate(g.components_):
        amp, ls, s2 = g.amplitude_[j], g.lengthscale_std_[j], mp.mpf(g.noise_[j]) ** 2
        z = sp.arrays()["z"][j, : sp.n_inducing_[j]]  # standardised, as the fit used them

        def k(a, b, amp=amp, ls=ls):
            return mp.matrix(np.asarray(kernel_matrix(amp, ls, a, b, kind=g.kernel)).tolist())

        kzz, kzx, ktz = k(z, z), k(z, xs), k(ts, z)
        s_inv = mp.inverse(s2 * kzz + kzx * kzx.T)
        r = mp.matrix((y[:, comp] - g.mean_[j]).tolist())
        mean = ktz * (s_inv * (kzx * r))
        a = ktz * mp.inverse(kzz)
        b = ktz * s_inv
        var = [
            mp.mpf(amp) ** 2
            - sum(a[i, c] * ktz[i, c] for c in range(ktz.cols))
            + s2 * sum(b[i, c] * ktz[i, c] for c in range(ktz.cols))
            for i in range(ktz.rows)
        ]
        means.append([float(g.mean_[j] + mean[i]) for i in range(ktz.rows)])
        stds.append([float(mp.sqrt(v)) for v in var])
    return np.array(means).T, np.array(stds).T


def test_dtc_posterior_against_the_formula_written_out_and_chunks_do_not_matter():
    x, y, _ = _data(200, seed=4)
    sp = SparseGP(16, hyper_subset=150, pivot_tol=1e-6).fit(x, y, seed=1)
    assert np.all(sp.n_inducing_ <= 16)
    xt = np.random.default_rng(5).uniform(-2.5, 2.5, size=(20, 2))
    m_s, s_s = sp.predict(xt, return_std=True)
    m_h, s_h = _dtc_by_hand(sp, x, y, xt)
    np.testing.assert_allclose(m_s, m_h, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(s_s, s_h, rtol=1e-4, atol=1e-6)
    # conditioning by row blocks of 7 (the last one short) gives the same posterior
    sp7 = SparseGP(16, hyper_subset=150, pivot_tol=1e-6, chunk=7).fit(x, y, seed=1)
    m7, s7 = sp7.predict(xt, return_std=True)
    np.testing.assert_allclose(m7, m_s, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s7, s_s, rtol=1e-9, atol=1e-12)


def test_fewer_inducing_inputs_stay_close_and_a_conformal_beta_covers():
    x, y, _ = _data(3000, seed=1)
    sp = SparseGP(64, hyper_subset=400).fit(x, y, seed=0)
    assert sp.n_samples_ == 3000 and np.all(sp.n_inducing_ <= 64)
    exact = GaussianProcessModel().fit(x, y, hyper_subset=400, seed=0)
    xt, _, omega_t = _data(500, seed=2)
    m_s, s_s = sp.predict(xt, return_std=True)
    m_e = exact.predict(xt, return_std=False)
    # same hyperparameters (the same 400 rows are not guaranteed): compare the fits' errors
    err_s = np.sqrt(np.mean((m_s - omega_t) ** 2, 0))
    err_e = np.sqrt(np.mean((m_e - omega_t) ** 2, 0))
    assert np.all(err_s <= 2 * err_e + 1e-3), (err_s, err_e)
    # split conformal on fresh points, checked on more fresh points
    xc, _, omega_c = _data(400, seed=3)
    beta = conformal_beta(sp, xc, omega_c, 0.05).beta
    inside = np.all(np.abs(omega_t - m_s) <= beta * s_s, 1)
    assert inside.mean() >= 0.9


def test_bad_input_is_refused_with_its_name():
    with pytest.raises(ParameterError, match="n_inducing must be an integer >= 1"):
        SparseGP(0)
    with pytest.raises(ParameterError, match="kernel must be one of 'se', 'matern52' .*'rbf'"):
        SparseGP(kernel="rbf")
    with pytest.raises(ParameterError, match="hyper_subset must be an integer >= 2"):
        SparseGP(hyper_subset=1)
    for use in (
        lambda sp: sp.predict(np.zeros((1, 2))),
        lambda sp: sp.mean_std(np.zeros(2)),
        lambda sp: sp.arrays(),
        lambda sp: sp.for_precision("float"),
        lambda sp: sp.unpadded(),
        lambda sp: sp.rounding_scales(np.zeros((1, 2))),
    ):
        with pytest.raises(RuntimeError, match="not fitted"):
            use(SparseGP())
    x, y, _ = _data(50)
    with pytest.raises(DimensionError, match=r"x and y must have the same shape"):
        SparseGP().fit(x, y[:, :1])
    y[3, 1] = np.nan
    with pytest.raises(NonFiniteError, match="y"):
        SparseGP().fit(x, y)
    with pytest.raises(ParameterError, match="seed"):
        SparseGP().fit(x, np.nan_to_num(y), seed=-1)


def test_a_large_offset_is_fitted_with_the_constant_mean_the_warning_advises():
    import inspect
    import re
    import warnings

    from safestab.errors import ConvergenceWarning, DataWarning

    x, y, _ = _data(120)
    y = y + 1e6  # an offset 1e7 times the variation: the zero-mean fit warns
    with pytest.warns(DataWarning, match="use mean='constant'") as record:
        # the zero-mean model misfits the offset; its optimiser may stop early as well
        warnings.simplefilter("ignore", ConvergenceWarning)
        SparseGP(120, hyper_subset=120, pivot_tol=0.0, noise_tol=0.0).fit(x, y, seed=3)
    # every argument the fit's warnings and errors advise is one SparseGP takes
    advised = {a for w in record for a in re.findall(r"\b(\w+)=", str(w.message))}
    advised |= {"noise", "jitter", "max_iter"}  # ConvergenceWarning's and NumericalError's
    assert advised <= set(inspect.signature(SparseGP).parameters), advised
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # the advice taken: no offset warning
        sp = SparseGP(120, mean="constant", hyper_subset=120, pivot_tol=0.0, noise_tol=0.0).fit(
            x, y, seed=3
        )
    exact = GaussianProcessModel(mean="constant").fit(x, y, hyper_subset=120, seed=3)
    np.testing.assert_allclose(sp.model.mean_, exact.mean_, rtol=1e-12)
    assert abs(float(sp.model.mean_[0]) - 1e6) < 1.0  # the offset is the fitted mean
    xt = np.random.default_rng(1).uniform(-3, 3, size=(50, 2))
    m_s, s_s = sp.predict(xt, return_std=True)
    m_e, s_e = exact.predict(xt, return_std=True)
    # with every input inducing, DTC is the exact posterior (as above; the variation, not
    # the offset, sets the scale of the rounding)
    np.testing.assert_allclose(m_s - 1e6, m_e - 1e6, atol=1e-4 * np.abs(m_e - 1e6).max())
    np.testing.assert_allclose(s_s, s_e, rtol=1e-2, atol=1e-4 * s_e.max())
    with pytest.raises(ParameterError, match="mean must be 'zero' or 'constant', got 'linear'"):
        SparseGP(mean="linear")
    with pytest.raises(ParameterError, match="noise must be >= 0"):
        SparseGP(noise=-1.0)


def test_all_rows_at_one_state_are_refused_by_name():
    _, y, _ = _data(300)
    x = np.tile([[0.3, -0.2]], (300, 1))
    with pytest.raises(ParameterError, match=r"x has all 300 rows at one state \[ 0.3 -0.2\]"):
        SparseGP().fit(x, y)
