"""Controllers without a CLF (the CBF formula, eq. (6)) or without a CBF (Sontag's, eq. (3)).

Checked against the formulas written out by hand in NumPy at random states.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss

DRIFT = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
DISC = ss.CBF(lambda x: 1.0 - x @ x, beta=2.0)
GOAL = ss.CLF(lambda x: (x - 2.0) @ (x - 2.0), lam=1.0)
KW = dict(kappa=0.1, rho=0.3, phi=0.5, varphi=0.5)


def _states():
    x = np.random.default_rng(0).uniform(-1.2, 1.2, size=(200, 2))
    return np.vstack([x, [[0.0, 0.0]]])  # the disc's centre: d = -2 x = 0 there


def test_the_cbf_formula_without_a_clf_is_eq_6_by_hand():
    x = _states()
    ctrl = ss.UniversalController(DRIFT, None, DISC, formula="cbf", **KW)
    out = ctrl.step(x)
    # by hand: c = L_f h + beta h, d = L_g h, u = (rho Gamma - c) / |d|^2 d (0 where d = 0)
    f = np.stack([x[:, 1], -x[:, 0]], -1)
    grad = -2.0 * x
    c = np.sum(grad * f, -1) + 2.0 * (1.0 - np.sum(x * x, -1))
    d = grad
    dd = np.sum(d * d, -1)
    gamma = np.sqrt(c**2 + KW["varphi"] * dd**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        want = np.where(dd[:, None] > 0, ((KW["rho"] * gamma - c) / dd)[:, None] * d, 0.0)
    np.testing.assert_allclose(np.asarray(out.u), want, rtol=1e-12, atol=1e-14)
    assert np.all(np.asarray(out.clf_satisfied))  # no CLF condition: met by every input
    assert ctrl.clfs == () and ctrl.cbfs == (DISC,)
    terms = ss.lie_terms(DRIFT, None, DISC, x)
    assert np.all(np.asarray(terms.a) == 0) and np.all(np.asarray(terms.b) == 0)
    np.testing.assert_allclose(np.asarray(terms.c), c, rtol=1e-13, atol=1e-14)
    # a trajectory records V as NaN (no CLF) and h as usual; the export computes the same
    traj = ss.simulate(ctrl, x[0], t_final=0.5, dt=0.1)
    assert np.all(np.isnan(np.asarray(traj.V))) and np.all(np.isfinite(np.asarray(traj.h)))
    native = ss.NativeController(ctrl)
    np.testing.assert_allclose(native.step(x).u, np.asarray(out.u), rtol=0, atol=1e-13)


def test_sontag_without_a_cbf_is_eq_3_by_hand():
    x = _states()
    out = ss.UniversalController(DRIFT, GOAL, None, formula="sontag", **KW).step(x)
    f = np.stack([x[:, 1], -x[:, 0]], -1)
    grad = 2.0 * (x - 2.0)
    a = np.sum(grad * f, -1) + np.sum((x - 2.0) ** 2, -1)
    b = grad
    bb = np.sum(b * b, -1)
    zeta = np.sqrt(a**2 + KW["phi"] * bb**2)
    want = -((a + KW["kappa"] * zeta) / bb)[:, None] * b
    np.testing.assert_allclose(np.asarray(out.u), want, rtol=1e-12, atol=1e-14)
    assert np.all(np.asarray(out.status) == ss.StepStatus.OK)


def test_a_missing_certificate_is_named():
    with pytest.raises(ss.InputTypeError, match=r"without a CLF, use formula='cbf'"):
        ss.UniversalController(DRIFT, None, DISC, **KW)
    with pytest.raises(
        ss.InputTypeError, match=r"cbf must be a CBF \(or None with formula='sontag'"
    ):
        ss.UniversalController(DRIFT, GOAL, None, formula="cbf", **KW)
    with pytest.raises(TypeError, match="clf must be a CLF or None, got str"):
        ss.lie_terms(DRIFT, "V", DISC, np.zeros(2))
