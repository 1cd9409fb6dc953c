"""Every error path of the core gives a clear message naming the argument."""

import jax.numpy as jnp
import numpy as np
import pytest

from safestab import (
    CBF,
    CLF,
    ControlAffineSystem,
    DimensionError,
    NonFiniteError,
    ParameterError,
    UniversalController,
    clf_cbf,
    clf_cbf_relaxed,
    clf_sontag,
    compatibility,
    project_box,
    saturate_safety_first,
)

from .systems_zoo import pendulum_two_inputs

P = {"kappa": 0.1, "rho": 0.1, "phi": 1.0, "varphi": 1.0}


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"kappa": -1.0}, r"kappa must be >= 0.0, got -1.0"),
        ({"rho": -0.5}, r"rho must be >= 0.0, got -0.5"),
        ({"phi": -1e-3}, r"phi must be >= 0.0, got -0.001"),
        ({"varphi": -2.0}, r"varphi must be >= 0.0"),
    ],
)
def test_negative_parameters(bad, match):
    with pytest.raises(ParameterError, match=match):
        clf_cbf(1.0, [1.0], 1.0, [1.0], **{**P, **bad})


@pytest.mark.parametrize("weight", [0.0, -1.0])
def test_slack_weight_must_be_positive(weight):
    with pytest.raises(ParameterError, match=rf"slack_weight must be > 0.0, got {weight}"):
        clf_cbf_relaxed(1.0, [1.0], 1.0, [1.0], slack_weight=weight, **P)


@pytest.mark.parametrize("name", ["kappa", "rho", "phi", "varphi"])
def test_non_finite_parameters(name):
    with pytest.raises(NonFiniteError, match=rf"{name} must be finite, got nan"):
        clf_cbf(1.0, [1.0], 1.0, [1.0], **{**P, name: float("nan")})


@pytest.mark.parametrize("pos, name", [(0, "a"), (1, "b"), (2, "c"), (3, "d")])
def test_non_finite_lie_terms(pos, name):
    args = [1.0, [1.0, 2.0], 1.0, [0.5, 1.0]]
    args[pos] = np.inf if pos in (0, 2) else [1.0, np.inf]
    with pytest.raises(NonFiniteError, match=rf"{name} must be finite"):
        clf_cbf(*args, **P)


def test_shape_errors_in_formulas():
    with pytest.raises(DimensionError, match=r"b and d must have the same last axis"):
        clf_cbf(1.0, [1.0, 2.0], 1.0, [1.0], **P)
    with pytest.raises(DimensionError, match=r"b must have shape \(\.\.\., m\), got a scalar"):
        clf_sontag(1.0, 2.0, kappa=1.0, phi=1.0)
    with pytest.raises(DimensionError, match=r"batch shapes do not broadcast: a \(3,\), b \(2,\)"):
        compatibility(np.ones(3), np.ones((2, 2)), np.ones(2), np.ones((2, 2)), **P)


def test_box_errors():
    with pytest.raises(ParameterError, match=r"u_min must be <= u_max elementwise"):
        project_box([0.0], [1.0], [-1.0])
    with pytest.raises(NonFiniteError, match=r"u must be finite"):
        project_box([np.nan], [-1.0], [1.0])
    with pytest.raises(DimensionError, match=r"needs a single input"):
        saturate_safety_first([0.0, 0.0], 1.0, [1.0, 1.0], rho=0.1, varphi=1.0, u_min=-1, u_max=1)


def test_system_shape_errors():
    with pytest.raises(
        DimensionError, match=r"f must return shape \(n_states,\) = \(2,\), got shape \(3,\)"
    ):
        ControlAffineSystem(lambda x: jnp.zeros(3), lambda x: jnp.zeros((2, 1)), 2)
    with pytest.raises(
        DimensionError,
        match=r"g must return shape \(n_states, n_inputs\) = \(2, m\), got shape \(2,\)",
    ):
        ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.zeros(2), 2)
    with pytest.raises(DimensionError, match=r"n_states must be a positive integer, got 0"):
        ControlAffineSystem(lambda x: x, lambda x: x[:, None], 0)


def test_state_errors():
    system, clf, cbf = pendulum_two_inputs()
    ctrl = UniversalController(system, clf, cbf, **P)
    with pytest.raises(DimensionError, match=r"x must have shape \(\.\.\., 2\), got shape \(3,\)"):
        ctrl(np.zeros(3))
    with pytest.raises(
        NonFiniteError, match=r"x must be finite, got an array of shape \(2,\) containing nan"
    ):
        ctrl(np.array([0.0, np.nan]))
    with pytest.raises(NonFiniteError, match=r"x must be finite"):
        ctrl(np.array([[0.0, 1.0], [np.inf, 0.0]]))


def test_certificate_errors():
    system, clf, cbf = pendulum_two_inputs()
    with pytest.raises(ParameterError, match=r"lam must be >= 0.0, got -1.0"):
        CLF(lambda x: x @ x, lam=-1.0)
    with pytest.raises(ParameterError, match=r"beta must be >= 0.0, got -0.1"):
        CBF(lambda x: x[0], beta=-0.1)
    vector_V = CLF(lambda x: x, lam=1.0)
    with pytest.raises(DimensionError, match=r"V must return a scalar, got shape \(2,\)"):
        UniversalController(system, vector_V, cbf, **P)
    bad_grad = CBF(lambda x: x[0], beta=1.0, grad=lambda x: jnp.zeros(3))
    with pytest.raises(DimensionError, match=r"grad of h must return shape \(2,\), got \(3,\)"):
        UniversalController(system, clf, bad_grad, **P)


def test_controller_parameter_errors():
    system, clf, cbf = pendulum_two_inputs()
    with pytest.raises(ParameterError, match=r"kappa must be >= 0.0, got -1.0"):
        UniversalController(system, clf, cbf, **{**P, "kappa": -1.0})
    with pytest.raises(ParameterError, match=r"slack_weight must be > 0.0, got 0.0"):
        UniversalController(system, clf, cbf, slack_weight=0.0, **P)
    with pytest.raises(ParameterError, match=r"u_min must be <= u_max"):
        UniversalController(system, clf, cbf, u_min=[1.0, 0.0], u_max=[0.0, 0.0], **P)
    with pytest.raises(NonFiniteError, match=r"u_max must be a number, or \+inf where"):
        UniversalController(system, clf, cbf, u_min=[1.0, 0.0], u_max=[-np.inf, 1.0], **P)
    with pytest.raises(
        DimensionError, match=r"safety_first' needs a single-input system, got n_inputs=2"
    ):
        UniversalController(system, clf, cbf, saturation="safety_first", u_min=-1, u_max=1, **P)
    with pytest.raises(
        ParameterError, match=r"saturation must be 'project' or 'safety_first', got 'clip'"
    ):
        UniversalController(system, clf, cbf, saturation="clip", **P)
