"""A constant input-gain error learned with the GP: ``y = omega(x) + D u + noise``.

The paper's model error ``omega(x)`` cannot depend on ``u``. When the true input matrix is
``g(x) + D`` for an unknown constant ``D`` (a gain or a mass that is off by some percent),
the targets ``y = xdot - f(x) - g(x) u`` carry ``D u``, and a GP of ``omega(x)`` alone takes
it for noise: with excitation inputs of a few units, that "noise" is many times the sensor's,
the fitted noise grows, and so does every band built from it (docs/obstacle.md measures it).

This module estimates ``D`` as a regression coefficient of the GP (Rasmussen & Williams,
*Gaussian Processes for Machine Learning*, 2006, sec. 2.7, explicit basis functions ``u``
with a vague prior): for each learned component ``i``, with ``K_i`` the fitted kernel matrix
plus noise, ``d_i = (U^T K_i^-1 U)^-1 U^T K_i^-1 (y_i - mu_i)`` (generalised least squares),
whose covariance is ``(U^T K_i^-1 U)^-1``. :func:`fit_input_gain` fits the GP's
hyperparameters on ``y - D u`` and conditions it there; the controller then uses the
corrected input matrix ``g(x) + D`` (:meth:`InputGain.corrected`) with the GP of the rest.

What the band does not contain: the estimate's own error ``(D - D_hat) u``. Its standard
error is reported (``InputGain.std``); on the obstacle preset's data it is 5e-4 to 8e-4 per
unit of input, against a sensor noise of 1e-2 (docs/obstacle.md, "The gain error, and the
axis starts"; docs/learning.md, "A constant input-gain error"). The GP's
mean is conditioned on ``y - D_hat u``, so the error of ``D_hat`` also moves the mean by
``k(x, X) K^-1 U (D - D_hat)``; a conformal beta, calibrated against the true ``omega``,
measures that part.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._validation import is_concrete
from ..errors import DimensionError, NonFiniteError
from ..systems import ControlAffineSystem
from .batched import Hyperparameters, condition
from .gp import GaussianProcessModel

__all__ = ["InputGain", "estimate_input_gain", "fit_input_gain", "with_input_gain"]


@dataclasses.dataclass(frozen=True)
class InputGain:
    """An estimated constant input-matrix error ``D`` (true ``g(x) + D``).

    Attributes
    ----------
    matrix : array of shape (n, m)
        ``D``, in state-derivative units per input unit. Rows of components the GP does not
        learn are 0.
    std : array of shape (n, m)
        Standard errors of ``matrix`` under the GP's model (0 where not learned).
    """

    matrix: np.ndarray
    std: np.ndarray

    def corrected(self, system: ControlAffineSystem) -> ControlAffineSystem:
        """``system`` with input matrix ``g(x) + D`` (:func:`with_input_gain`)."""
        return with_input_gain(system, self.matrix)

    def as_dict(self) -> dict[str, Any]:
        """Strict-JSON data: ``matrix`` and ``std`` as nested lists."""
        return {"matrix": np.asarray(self.matrix).tolist(), "std": np.asarray(self.std).tolist()}


def with_input_gain(system: ControlAffineSystem, matrix: Any) -> ControlAffineSystem:
    """``system`` with input matrix ``g(x) + matrix`` (same drift, same run-time parameters).

    ``matrix`` (n, m) may be a traced array: the Monte Carlo chunks pass each data set's
    estimate as an argument of one compiled loop.

    Raises
    ------
    DimensionError
        If ``matrix`` is not (n, m) for the system.
    """
    n, m = system.n_states, system.n_inputs
    if jnp.shape(matrix) != (n, m):
        raise DimensionError(
            f"the input-gain matrix has shape {jnp.shape(matrix)}, system {system.name!r} needs "
            f"({n}, {m})"
        )
    dj = jnp.asarray(matrix, float)
    if is_concrete(dj) and not bool(jnp.all(jnp.isfinite(dj))):
        raise NonFiniteError(f"the input-gain matrix is not finite: {np.asarray(dj).tolist()}")
    name = f"{system.name} + learned input gain"
    if system.params_spec is None:
        return ControlAffineSystem(system.f, lambda x: system.g(x) + dj, n, name=name)
    return ControlAffineSystem(
        system.f, lambda x, p: system.g(x, p) + dj, n, name=name,
        params=system.params_spec.example,
    )  # fmt: skip


def estimate_input_gain(model: GaussianProcessModel, u: Any) -> InputGain:
    """Generalised least squares of ``model``'s own targets on the inputs ``u``.

    The model's prior mean is held fixed (the studies' GPs have mean zero); with a fitted
    constant mean, ``std`` leaves out the mean's own uncertainty.

    Parameters
    ----------
    model : GaussianProcessModel
        A fitted (or conditioned) exact GP; its factor ``chol_`` is ``K + noise^2 I``.
    u : array of shape (Q, m)
        The inputs of the model's training rows, in the same order.

    Returns
    -------
    InputGain
        ``D`` such that ``model.y_train_ - mean_`` is best explained as ``D u`` plus a draw
        of the GP; rows of unlearned components are 0.

    Raises
    ------
    DimensionError
        If ``u`` is not (Q, m) with the model's Q rows.
    NonFiniteError
        If ``u`` is not finite or ``U^T K^-1 U`` is singular (an input never excited).
    """
    u = np.asarray(u, float)
    q = model.x_train_.shape[0]
    if u.ndim != 2 or u.shape[0] != q:
        raise DimensionError(f"u must have shape (Q, m) = ({q}, m), got shape {u.shape}")
    if not np.all(np.isfinite(u)):
        raise NonFiniteError("u contains non-finite values")
    n, m = model.n_states_, u.shape[1]
    matrix, std = np.zeros((n, m)), np.zeros((n, m))
    for j, comp in enumerate(model.components_):
        chol = np.asarray(model.chol_[j])
        kinv_u = scipy.linalg.cho_solve((chol, True), u)
        a = u.T @ kinv_u
        rhs = kinv_u.T @ (np.asarray(model.y_train_[:, j]) - model.mean_[j])
        try:
            a_chol = scipy.linalg.cho_factor(a, lower=True)
        except np.linalg.LinAlgError as exc:
            raise NonFiniteError(
                f"U^T K^-1 U is singular for component {comp}: some input is never excited "
                "in the data, so its gain cannot be estimated"
            ) from exc
        matrix[comp] = scipy.linalg.cho_solve(a_chol, rhs)
        std[comp] = np.sqrt(np.diag(scipy.linalg.cho_solve(a_chol, np.eye(m))))
    if not (np.all(np.isfinite(matrix)) and np.all(np.isfinite(std))):
        raise NonFiniteError("the input-gain estimate is not finite (U^T K^-1 U is singular)")
    return InputGain(matrix, std)


def fit_input_gain(
    fit: Callable[[np.ndarray, np.ndarray], GaussianProcessModel],
    x: Any,
    u: Any,
    y: Any,
    *,
    seed: int = 0,
) -> tuple[GaussianProcessModel, InputGain]:
    """Fit a GP of ``omega(x)`` and a constant input-gain error ``D`` together.

    Three steps: (1) ``fit(x, y)`` and ``D_0`` from it (its noise holds ``D u``, so ``D_0``
    is consistent but loose); (2) ``fit(x, y - D_0 u)``, hyperparameters of ``omega`` alone,
    and ``D = D_0 + `` the estimate from it; (3) the GP with those hyperparameters conditioned
    on ``y - D u`` (one factorisation, no optimisation).

    Parameters
    ----------
    fit : callable
        ``fit(x, y) -> GaussianProcessModel``, the caller's fit (kernel, subset, seed).
    x : array of shape (Q, n)
    u : array of shape (Q, m)
    y : array of shape (Q, n)
        Targets ``xdot - f(x) - g(x) u``, as :class:`~safestab.learning.Dataset` holds them.
    seed : int
        Seeds the conditioned model's leave-one-out check.

    Returns
    -------
    (model, gain) : (GaussianProcessModel, InputGain)
        ``model`` learns ``omega(x) = y - D u`` (its ``y_train_`` are those targets).
    """
    x, u, y = (np.asarray(a, float) for a in (x, u, y))
    if u.ndim != 2 or u.shape[0] != x.shape[0]:
        raise DimensionError(f"u must have shape (Q, m) with Q = {x.shape[0]}, got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise NonFiniteError("u contains non-finite values")
    first = fit(x, y)
    d0 = estimate_input_gain(first, u).matrix
    second = fit(x, y - u @ d0.T)
    step = estimate_input_gain(second, u)
    gain = InputGain(d0 + step.matrix, step.std)
    model = condition(Hyperparameters.from_model(second), x, y - u @ gain.matrix.T, seed=seed)
    return model, gain
