"""Confidence scaling ``beta_i`` (Lemma 2) and calibration on held-out data."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_scalar_range
from ..errors import DimensionError, ParameterError
from ..robust import joint_probability

__all__ = [
    "information_gain",
    "beta_lemma2",
    "Calibration",
    "calibration",
    "ConfidenceReport",
    "confidence",
]


def information_gain(model: Any) -> np.ndarray:
    """Information gain of the training data per learned component, in nats.

    ``gamma_i = 1/2 log det(I + sigma_i^-2 K_i)``, the mutual information between the noisy
    targets and the latent ``omega_i`` at the training inputs, computed from the fitted
    Cholesky factor as ``sum(log diag L) - Q log sigma`` (with ``sigma^2`` including the
    jitter).

    Parameters
    ----------
    model : GaussianProcessModel
        A fitted model.

    Returns
    -------
    array of shape (k,)

    Notes
    -----
    Lemma 2 (after Srinivas et al.) asks for the *maximum* information gain over any ``Q``
    points, which this data-dependent value bounds from below; a beta built from it is
    therefore the practical estimate used in much of the safe-learning literature, not a
    certified upper bound. Pass your own ``gamma`` to :func:`beta_lemma2` for a bound from
    kernel-specific theory.
    """
    chol = np.asarray(model.chol_)
    q = chol.shape[-1]
    sigma2 = model.noise_**2 + model.jitter * model.amplitude_**2
    logdiag = np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    return logdiag - 0.5 * q * np.log(sigma2)


def beta_lemma2(rkhs_norm: Any, gamma: Any, n_samples: int, delta: float) -> np.ndarray:
    """``beta_i = sqrt(2 ||omega_i||_k^2 + 300 gamma_i ln^3((Q + 1)/delta))``, eq. (15).

    Parameters
    ----------
    rkhs_norm : float or array of shape (k,)
        Upper bound on the RKHS norm of each ``omega_i``, supplied by the user.
    gamma : float or array of shape (k,)
        Information gain per component (for example :func:`information_gain`).
    n_samples : int
        ``Q``.
    delta : float
        In (0, 1).

    Returns
    -------
    array of shape (k,)

    Raises
    ------
    ParameterError
        If ``delta`` is outside (0, 1), a norm or gain is negative, or ``n_samples < 1``.
    """
    check_scalar_range("delta", delta, lower=0.0, strict_lower=True, upper=1.0, strict_upper=True)
    check_scalar_range("rkhs_norm", rkhs_norm, lower=0.0)
    check_scalar_range("gamma", gamma, lower=0.0)
    if int(n_samples) < 1:
        raise ParameterError(f"n_samples must be >= 1, got {n_samples!r}")
    b = np.asarray(rkhs_norm, float)
    g = np.asarray(gamma, float)
    return np.sqrt(2 * b**2 + 300 * g * np.log((n_samples + 1) / delta) ** 3)


@dataclasses.dataclass(frozen=True)
class ConfidenceReport:
    """A beta per component with the probability it is claimed to hold with.

    Attributes
    ----------
    beta : array of shape (n,)
        Confidence scaling per state component (0 for skipped components).
    probability : float
        ``(1 - delta)^k`` for ``k`` learned components, or NaN for a user-chosen beta.
    method : str
        ``"lemma2"`` or ``"user"``.
    """

    beta: np.ndarray
    probability: float
    method: str


def confidence(
    model: Any,
    *,
    beta: Any = None,
    rkhs_norm: Any = None,
    delta: float | None = None,
    gamma: Any = None,
) -> ConfidenceReport:
    """Choose ``beta`` per component: user-given, or by Lemma 2.

    Parameters
    ----------
    model : GaussianProcessModel
        Fitted model.
    beta : float or array, optional
        A chosen scaling (commonly 2 to 3); checked on held-out data with :func:`calibration`.
    rkhs_norm, delta : optional
        For Lemma 2: RKHS-norm bound per learned component and ``delta`` in (0, 1).
    gamma : optional
        Information gain; defaults to :func:`information_gain` of the model.

    Returns
    -------
    ConfidenceReport
    """
    n, comps = model.n_states_, list(model.components_)
    if beta is not None:
        check_scalar_range("beta", beta, lower=0.0)
        b = np.zeros(n)
        b[comps] = np.broadcast_to(np.asarray(beta, float), (len(comps),))
        prob = float("nan") if delta is None else joint_probability(delta, len(comps))
        return ConfidenceReport(beta=b, probability=prob, method="user")
    if rkhs_norm is None or delta is None:
        raise ParameterError("give beta=, or rkhs_norm= and delta= for Lemma 2")
    g = information_gain(model) if gamma is None else gamma
    b = np.zeros(n)
    b[comps] = beta_lemma2(rkhs_norm, g, model.x_train_.shape[0], delta)
    return ConfidenceReport(
        beta=b, probability=joint_probability(delta, len(comps)), method="lemma2"
    )


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Held-out coverage of ``|omega_i - m_i| <= beta_i sigma_i``.

    Attributes
    ----------
    per_component : array of shape (k,)
        Fraction of points inside the band, per learned component.
    joint : float
        Fraction of points inside all bands at once.
    rmse : array of shape (k,)
        Root-mean-square error of the mean, per learned component.
    components : tuple of int
    """

    per_component: np.ndarray
    joint: float
    rmse: np.ndarray
    components: tuple[int, ...]


def calibration(
    model: Any, x: Any, y: Any, beta: Any, *, observation_noise: bool = False
) -> Calibration:
    """Coverage of the confidence bands on held-out data.

    Parameters
    ----------
    model : an uncertainty model with ``mean_std`` (fitted GP or adapter)
    x : array of shape (Q, n)
    y : array of shape (Q, n)
        Held-out values: the true ``omega(x)`` (checks the latent band of Lemma 2), or noisy
        measurements with ``observation_noise=True``.
    beta : float or array of shape (n,)
    observation_noise : bool
        Widen the band to ``beta sqrt(sigma^2 + sigma_epsilon^2)`` using the model's fitted
        ``noise_``, for comparison with noisy targets. Comparing noisy targets with the
        latent band understates coverage once the posterior is sharper than the noise.

    Returns
    -------
    Calibration
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if x.ndim != 2 or y.shape != x.shape:
        raise DimensionError(f"x and y must both have shape (Q, n), got {x.shape} and {y.shape}")
    check_finite("x", x)
    check_finite("y", y)
    mean, std = jax.vmap(model.mean_std)(jnp.asarray(x))
    mean, std = np.asarray(mean), np.asarray(std)
    if observation_noise:
        noise = np.zeros(x.shape[1])
        noise[list(model.components_)] = model.noise_
        std = np.sqrt(std**2 + noise**2)
    comps = tuple(getattr(model, "components_", range(x.shape[1])))
    b = np.broadcast_to(np.asarray(beta, float), (x.shape[1],))
    inside = np.abs(y - mean) <= b * std
    inside = inside[:, list(comps)]
    err = (y - mean)[:, list(comps)]
    return Calibration(
        per_component=inside.mean(0),
        joint=float(inside.all(1).mean()),
        rmse=np.sqrt((err**2).mean(0)),
        components=comps,
    )
