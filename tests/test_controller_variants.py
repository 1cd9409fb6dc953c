"""Issue 10, points 4 and 6: class-K rates, state-dependent weights, single-certificate
controllers."""

import jax.numpy as jnp
import numpy as np
import pytest

from safestab import (
    CBF,
    CLF,
    CBFController,
    ModelError,
    ParameterError,
    RelativeDegreeError,
    SontagController,
    StepStatus,
    UniversalController,
    cbf_universal,
    clf_cbf,
    clf_sontag,
    lie_terms,
)

from .systems_zoo import pendulum_two_inputs

P = {"kappa": 0.3, "rho": 0.2, "phi": 1.0, "varphi": 0.5}


def _states(n=50, seed=0):
    return np.random.default_rng(seed).uniform(-0.8, 0.8, (n, 2))


def test_class_k_rates_enter_the_lie_terms():
    system, clf, cbf = pendulum_two_inputs()

    def alpha(h):
        return 2.0 * h**3

    def gamma(v):
        return 0.5 * jnp.tanh(v)

    clf_k = CLF(clf.V, gamma=gamma)
    cbf_k = CBF(cbf.h, alpha=alpha)
    x = _states()
    base = lie_terms(system, CLF(clf.V, lam=0.0), CBF(cbf.h, beta=0.0), x)
    new = lie_terms(system, clf_k, cbf_k, x)
    V = np.asarray(clf.value(x))
    h = np.asarray(cbf.value(x))
    # a = L_f V + gamma(V), c = L_f h + alpha(h): independent of the rate's implementation
    assert np.allclose(np.asarray(new.a), np.asarray(base.a) + 0.5 * np.tanh(V), rtol=1e-14)
    assert np.allclose(np.asarray(new.c), np.asarray(base.c) + 2.0 * h**3, rtol=1e-14)


@pytest.mark.parametrize(
    "fn, match",
    [
        (lambda h: h + 1.0, r"alpha\(0\) = 0, got alpha\(0\) = 1.0"),
        (lambda h: -h, r"alpha must be strictly increasing"),
        (lambda h: h**2, r"alpha must be strictly increasing"),
    ],
)
def test_class_k_functions_are_checked(fn, match):
    with pytest.raises(ParameterError, match=match):
        CBF(lambda x: x[0], alpha=fn)


def test_rate_and_class_k_are_exclusive():
    with pytest.raises(ParameterError, match=r"exactly one of beta .* and alpha"):
        CBF(lambda x: x[0], beta=1.0, alpha=lambda h: h)
    with pytest.raises(ParameterError, match=r"exactly one of lam .* and gamma"):
        CLF(lambda x: x @ x)


def test_state_dependent_weights_match_the_formula_with_arrays():
    system, clf, cbf = pendulum_two_inputs()

    def phi(x):
        return 0.5 + x[0] ** 2

    def varphi(x):
        return jnp.exp(-x[1])

    ctrl = UniversalController(system, clf, cbf, kappa=0.3, rho=0.2, phi=phi, varphi=varphi)
    x = _states()
    out = ctrl.step(x)
    t = lie_terms(system, clf, cbf, x)
    ref = clf_cbf(*t, kappa=0.3, rho=0.2, phi=0.5 + x[:, 0] ** 2, varphi=np.exp(-x[:, 1]))
    # the same arithmetic, fused differently by XLA inside the controller: last-bit agreement
    # (a wrong weight, e.g. phi evaluated at the wrong state, differs at O(1))
    assert np.allclose(np.asarray(out.u), np.asarray(ref.u), rtol=1e-13, atol=1e-15)


def test_negative_state_dependent_weight_is_a_named_status():
    system, clf, cbf = pendulum_two_inputs()
    ctrl = UniversalController(system, clf, cbf, kappa=0.3, rho=0.2, phi=lambda x: x[0], varphi=0.5)
    out = ctrl.step(np.array([[0.5, 0.0], [-0.5, 0.0]]))
    assert out.status.tolist() == [StepStatus.OK, StepStatus.NEGATIVE_WEIGHT]
    assert np.all(np.isnan(np.asarray(out.u[1]))) and not bool(out.cbf_satisfied[1])
    with pytest.raises(ModelError, match=r"NEGATIVE_WEIGHT .*phi\(x\) \(negative\)"):
        ctrl.step(np.array([-0.5, 0.0]), strict=True)


def test_single_certificate_controllers_are_the_paper_formulas():
    system, clf, cbf = pendulum_two_inputs()
    x = _states()
    t = lie_terms(system, clf, cbf, x)
    sontag = SontagController(system, clf, cbf, **P).step(x)
    cbf_ctrl = CBFController(system, clf, cbf, **P).step(x)
    # same kernels, fused differently inside the controller: agreement to the last bits
    sontag_ref = clf_sontag(t.a, t.b, kappa=P["kappa"], phi=P["phi"]).u
    cbf_ref = cbf_universal(t.c, t.d, rho=P["rho"], varphi=P["varphi"]).u
    assert np.allclose(np.asarray(sontag.u), np.asarray(sontag_ref), rtol=1e-13, atol=1e-15)
    assert np.allclose(np.asarray(cbf_ctrl.u), np.asarray(cbf_ref), rtol=1e-13, atol=1e-15)
    assert not np.allclose(np.asarray(sontag.u), np.asarray(cbf_ref))  # they differ here
    # the flags report on both conditions: Sontag's input meets the CLF condition by design
    assert np.all(np.asarray(sontag.clf_satisfied)) and np.all(np.asarray(cbf_ctrl.cbf_satisfied))
    with pytest.raises(ParameterError, match=r"slack_weight applies to the combined formula"):
        SontagController(system, clf, cbf, slack_weight=1.0, **P)


def _double_integrator():
    from safestab import ControlAffineSystem

    return ControlAffineSystem(
        lambda x: jnp.array([x[1], 0.0]), lambda x: jnp.array([[0.0], [1.0]]), 2, name="di"
    )


def test_high_order_cbf_keeps_a_position_limit_where_degree_one_cannot():
    """Double integrator (position p, speed v, input = acceleration), position limit p <= 1,
    and a CLF that pulls towards p = 3 beyond it."""
    from safestab import Region, high_order_cbf, simulate

    system = _double_integrator()
    clf = CLF(lambda x: (x[0] - 3.0) ** 2 + (x[0] - 3.0 + x[1]) ** 2, lam=1.0)

    def h(x):
        return 1.0 - x[0]

    kw = {"kappa": 0.0, "rho": 0.0, "phi": 0.0, "varphi": 0.0, "slack_weight": 10.0}
    x0 = np.array([0.0, 0.0])
    # degree one: d = L_g h = 0, so the barrier cannot act (the CLF would drive p past 1):
    # refused where the controller is built, with a pointer to high_order_cbf
    with pytest.raises(RelativeDegreeError, match=r"cbf: L_g h is zero at every probe.*high_order"):
        UniversalController(system, clf, CBF(h, beta=1.0), **kw)
    # Sontag's CLF formula does not enforce the barrier: it is not refused, and it crosses
    t_plain = simulate(UniversalController(system, clf, CBF(h, beta=1.0), formula="sontag",
                                           **{**kw, "slack_weight": None}), x0, t_final=8.0,
                       dt=0.01)  # fmt: skip
    assert float(np.min(np.asarray(t_plain.h))) < -0.5
    # degree two: psi1 = -v + 2 (1 - p); the closed loop keeps h >= 0 throughout
    hocbf = high_order_cbf(system, h, alpha1=2.0, beta=2.0)
    ctrl = UniversalController(system, clf, hocbf, **kw)
    traj = simulate(ctrl, x0, t_final=8.0, dt=0.01)
    p = np.asarray(traj.x)[:, 0]
    assert traj.ok and np.min(1.0 - p) >= -1e-6  # RK4 with dt = 0.01: O(dt^4) drift at most
    assert p[-1] > 0.9  # it still goes as far as the limit allows
    assert np.any(np.asarray(traj.region) == Region.P3) or np.any(
        np.asarray(traj.region) == Region.P2
    )


def test_high_order_cbf_rejects_relative_degree_one():
    from safestab import high_order_cbf

    system = _double_integrator()
    with pytest.raises(ParameterError, match=r"h does not have relative degree 2: L_g h = \[1.0\]"):
        high_order_cbf(system, lambda x: x[1], alpha1=1.0, beta=1.0)


def test_high_order_cbf_reports_where_degree_two_fails_at_run_time():
    from safestab import ControlAffineSystem, high_order_cbf

    # g acts on the position only where p > 5: degree 2 holds at the probes, not there
    system = ControlAffineSystem(
        lambda x: jnp.array([x[1], 0.0]),
        lambda x: jnp.array([[jnp.where(x[0] > 5.0, 1.0, 0.0)], [1.0]]),
        2,
    )
    clf = CLF(lambda x: x @ x, lam=1.0)
    hocbf = high_order_cbf(
        system, lambda x: 10.0 - x[0], alpha1=1.0, beta=1.0, probe=np.zeros((1, 2))
    )
    ctrl = UniversalController(system, clf, hocbf, **P)
    out = ctrl.step(np.array([[0.0, 0.0], [6.0, 0.0]]))
    assert out.status.tolist() == [StepStatus.OK, StepStatus.RELATIVE_DEGREE]
    with pytest.raises(ModelError, match=r"relative degree 2 does not hold"):
        ctrl.step(np.array([6.0, 0.0]), strict=True)
