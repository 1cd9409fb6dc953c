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
    sontag_ref = clf_sontag(t.a, t.b, kappa=P["kappa"], phi=P["phi"])
    cbf_ref = cbf_universal(t.c, t.d, rho=P["rho"], varphi=P["varphi"])
    assert np.allclose(np.asarray(sontag.u), np.asarray(sontag_ref), rtol=1e-13, atol=1e-15)
    assert np.allclose(np.asarray(cbf_ctrl.u), np.asarray(cbf_ref), rtol=1e-13, atol=1e-15)
    assert not np.allclose(np.asarray(sontag.u), np.asarray(cbf_ref))  # they differ here
    # the flags report on both conditions: Sontag's input meets the CLF condition by design
    assert np.all(np.asarray(sontag.clf_satisfied)) and np.all(np.asarray(cbf_ctrl.cbf_satisfied))
    with pytest.raises(ParameterError, match=r"slack_weight applies to the combined formula"):
        SontagController(system, clf, cbf, slack_weight=1.0, **P)
