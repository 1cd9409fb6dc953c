"""Confidence scaling ``beta``: Lemma 2, split conformal calibration, held-out checks.

Three ways to choose ``beta``, with what each probability means:

- Lemma 2 (:func:`confidence` with ``rkhs_norm=``, ``delta=``): ``|omega_i - m_i| <= beta_i
  sigma_i`` at *every* state with probability ``(1 - delta)^k`` over the noise, if the RKHS-norm
  bound and the information gain are right (the gain used here is an estimate).
- Split conformal (:func:`conformal_beta`): a new state (or a new trajectory) drawn from the
  calibration distribution is inside the band with probability at least ``1 - delta`` over the
  calibration draw and the new draw; nothing assumed about the GP.
- Hand-chosen (:func:`confidence` with ``beta=``): no guarantee; check with :func:`calibration`.
"""

from __future__ import annotations

import dataclasses
import functools
import weakref
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_scalar_range
from .._values import model_is_data
from ..errors import DimensionError, NumericalError, ParameterError
from ..robust import joint_probability
from ._predict import Predictor

__all__ = [
    "information_gain",
    "beta_lemma2",
    "Calibration",
    "calibration",
    "ConfidenceReport",
    "confidence",
    "conformal_beta",
    "mean_std_batch",
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
    sigma2 = model.noise_**2  # effective noise: the jitter is included
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
    """A beta per component with the probability it holds with, and what that means.

    Attributes
    ----------
    beta : array of shape (n,)
        Confidence scaling per state component (0 for skipped components).
    probability : float or None
        ``(1 - delta)^k`` for Lemma 2 with ``k`` learned components; ``1 - delta`` for the
        conformal beta; None for a hand-chosen beta (no guarantee).
    method : str
        ``"lemma2"``, ``"conformal"`` or ``"user"``.
    statement : str
        What ``probability`` is the probability of, in words.
    n_calibration : int or None
        Calibration units (states or trajectories) behind a conformal beta.
    """

    beta: np.ndarray
    probability: float | None
    method: str
    statement: str = ""
    n_calibration: int | None = None


def confidence(
    model: Any,
    *,
    beta: Any = None,
    rkhs_norm: Any = None,
    delta: float | None = None,
    gamma: Any = None,
) -> ConfidenceReport:
    """Choose ``beta`` per component: hand-chosen (no guarantee), or by Lemma 2.

    Parameters
    ----------
    model : GaussianProcessModel
        Fitted model.
    beta : float or array, optional
        A chosen scaling (commonly 2 to 3). It carries no probability: check it with
        :func:`calibration`, or calibrate one with :func:`conformal_beta`.
    rkhs_norm, delta : optional
        For Lemma 2: RKHS-norm bound per learned component and ``delta`` in (0, 1).
    gamma : optional
        Information gain; defaults to :func:`information_gain` of the model.

    Returns
    -------
    ConfidenceReport

    Raises
    ------
    ParameterError
        If ``delta`` is given with a hand-chosen ``beta`` (a probability would not follow from
        it), or neither ``beta`` nor ``rkhs_norm`` and ``delta`` are given.
    """
    n, comps = model.n_states_, list(model.components_)
    if beta is not None:
        if delta is not None:
            raise ParameterError(
                f"delta={delta!r} gives no probability for a hand-chosen beta={beta!r}: the "
                "probability of Lemma 2 holds only for its own beta (pass rkhs_norm= and "
                "delta= without beta=), and conformal_beta(model, x, y, delta) calibrates a "
                "beta for 1 - delta"
            )
        check_scalar_range("beta", beta, lower=0.0)
        b = np.zeros(n)
        b[comps] = np.broadcast_to(np.asarray(beta, float), (len(comps),))
        return ConfidenceReport(
            beta=b,
            probability=None,
            method="user",
            statement="no guarantee: a hand-chosen beta; check its coverage on held-out data",
        )
    if rkhs_norm is None or delta is None:
        raise ParameterError("give beta=, or rkhs_norm= and delta= for Lemma 2")
    g = information_gain(model) if gamma is None else gamma
    b = np.zeros(n)
    b[comps] = beta_lemma2(rkhs_norm, g, model.x_train_.shape[0], delta)
    return ConfidenceReport(
        beta=b,
        probability=joint_probability(delta, len(comps)),
        method="lemma2",
        statement=(
            f"Lemma 2: with probability (1 - delta)^{len(comps)} over the noise, "
            "|omega_i(x) - m_i(x)| <= beta_i sigma_i(x) for every state x and component, "
            "provided ||omega_i||_k <= rkhs_norm and gamma bounds the information gain"
        ),
    )


def mean_std_batch(model: Any, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std at states (N, n), each (N, n).

    A GP class of this package answers ``predict(x, return_std=True)`` (compiled once per
    shape); any other :class:`~safestab.robust.UncertaintyModel` has its ``mean_std`` mapped
    with ``jax.vmap`` and compiled (once per model and shape: run op by op, the first call of
    each shape compiled every operation on its own, 2.3 s for the paper preset's cache
    against 0.3 s).
    """
    if isinstance(model, Predictor):
        return model.predict(x, return_std=True)
    mean, std = _batched(model)(jnp.asarray(x))
    return np.asarray(mean), np.asarray(std)


def _batched(model: Any) -> Any:
    """The batched ``mean_std`` of ``model``: one module-level jitted function.

    A model that is data (a fitted GP or cache registered as a pytree) is its argument, so
    every model of the same kind and shapes runs one compiled program; another model is its
    static argument (by identity, as ``jax.jit`` keys it), and one that cannot be hashed is
    compiled for this call only.
    """
    if model_is_data(model):
        return lambda x: _mean_std_of(model, x)
    try:
        key = _Referent(model)
    except TypeError:  # not weakly referable: compiled for this call
        return jax.jit(jax.vmap(model.mean_std))
    return lambda x: _mean_std_static(key, x)


class _Referent:
    """A static argument naming a model by identity without keeping it alive.

    Equal only while the model lives, so a program compiled for a model is reused for it
    and never for a later model at the same address; the model is freed when its owner
    drops it (the compiled program keeps only the arrays it read as constants).
    """

    __slots__ = ("ref", "key")

    def __init__(self, model: Any) -> None:
        self.ref, self.key = weakref.ref(model), id(model)

    def __hash__(self) -> int:
        return self.key

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Referent) and self.ref() is not None and self.ref() is other.ref()


@jax.jit
def _mean_std_of(model: Any, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    return jax.vmap(model.mean_std)(x)


@functools.partial(jax.jit, static_argnames=("key",))
def _mean_std_static(key: _Referent, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    return jax.vmap(key.ref().mean_std)(x)


def _scores(model: Any, x: np.ndarray, y: np.ndarray, observation_noise: bool) -> np.ndarray:
    """``max_i |y_i - m_i| / s_i`` over learned components, per row; shape (N,)."""
    mean, std = mean_std_batch(model, x)
    comps = list(getattr(model, "components_", range(x.shape[1])))
    if observation_noise:
        noise = np.zeros(x.shape[1])
        noise[comps] = model.noise_
        std = np.sqrt(std**2 + noise**2)
    err = np.abs(y - mean)[:, comps]
    sd = std[:, comps]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(err == 0, 0.0, err / sd)  # err > 0 with sd = 0: inf, never covered
    return ratio.max(1)


def conformal_beta(
    model: Any,
    x: Any,
    y: Any,
    delta: float,
    *,
    groups: Any = None,
    observation_noise: bool = False,
) -> ConfidenceReport:
    """Calibrated ``beta`` by split conformal prediction on data not used for fitting.

    The score of a calibration unit is ``max_i |y_i - m_i(x)| / sigma_i(x)`` over the learned
    components (and over the unit's rows when ``groups`` is given). With ``N`` units, ``beta``
    is the ``ceil((N + 1)(1 - delta))``-th smallest score, applied to every learned component.

    Parameters
    ----------
    model : an uncertainty model with ``mean_std`` (fitted GP, cache or adapter)
    x : array of shape (N_rows, n)
        Calibration states, from trajectories not used to fit ``model``.
    y : array of shape (N_rows, n)
        The true ``omega(x)`` (the guarantee is then about ``omega``, the band of Lemma 2),
        or noisy measurements with ``observation_noise=True`` (the guarantee is then about a
        new noisy measurement and the band ``beta sqrt(sigma^2 + noise_^2)``).
    delta : float
        In (0, 1): the allowed miss probability.
    groups : array of shape (N_rows,), optional
        A unit label per row (for example the trajectory index). The score of a unit is its
        largest row score and the guarantee covers *every* row of a new unit at once.
    observation_noise : bool
        Calibrate the band for noisy measurements, as above.

    Returns
    -------
    ConfidenceReport
        ``method="conformal"``, ``probability = 1 - delta`` and ``n_calibration = N``.

    Raises
    ------
    DimensionError
        If ``x``, ``y`` or ``groups`` have the wrong shapes.
    NonFiniteError
        If ``x`` or ``y`` contains NaN or inf.
    ParameterError
        If ``delta`` is outside (0, 1) or ``N < 1/delta - 1`` (no finite quantile).
    NumericalError
        If the quantile score is infinite (``sigma = 0`` where the error is not 0).

    Notes
    -----
    Guarantee (Vovk et al.; Lei et al., 2018, Theorem 2.2): if the ``N`` calibration units and
    a new unit are exchangeable (for example independent draws of states, or of whole
    trajectories, from one distribution) and independent of the data the model was fitted on,
    then ``P(new unit inside the band) >= 1 - delta``; with almost surely distinct scores it is
    also ``<= 1 - delta + 1/(N + 1)``. The probability is over the calibration draw and the new
    unit together. States along one trajectory are not exchangeable with each other: calibrate
    per state only with states drawn independently (one per trajectory, say), or pass
    ``groups`` for the per-trajectory guarantee. Closed-loop states under a new controller come
    from another distribution, which the guarantee does not cover.
    """
    check_scalar_range("delta", delta, lower=0.0, strict_lower=True, upper=1.0, strict_upper=True)
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if x.ndim != 2 or y.shape != x.shape:
        raise DimensionError(f"x and y must both have shape (N, n), got {x.shape} and {y.shape}")
    check_finite("x", x)
    check_finite("y", y)
    scores = _scores(model, x, y, observation_noise)
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (x.shape[0],):
            raise DimensionError(
                f"groups must have shape ({x.shape[0]},), one label per row, got {groups.shape}"
            )
        labels, inverse = np.unique(groups, return_inverse=True)
        unit = np.full(len(labels), -np.inf)
        np.maximum.at(unit, inverse, scores)
        scores = unit
    n_units = scores.shape[0]
    rank = int(np.ceil((n_units + 1) * (1.0 - delta)))
    if rank > n_units:
        need = int(np.ceil(1.0 / delta - 1.0 - 1e-12))
        raise ParameterError(
            f"delta={delta!r} needs at least {need} calibration units (ceil((N + 1)(1 - delta)) "
            f"<= N), got N = {n_units}; use more calibration "
            f"{'groups' if groups is not None else 'rows'} or a larger delta"
        )
    beta = float(np.sort(scores)[rank - 1])
    if not np.isfinite(beta):
        raise NumericalError(
            "the conformal quantile is infinite: the model reports sigma = 0 where the error "
            "is not 0 at too many calibration units; a skipped component is not exact, or the "
            "model is degenerate"
        )
    n = x.shape[1]
    comps = list(getattr(model, "components_", range(n)))
    b = np.zeros(n)
    b[comps] = beta
    unit_word = "trajectory (every row of it)" if groups is not None else "state"
    target = "a new noisy measurement" if observation_noise else "omega"
    return ConfidenceReport(
        beta=b,
        probability=1.0 - delta,
        method="conformal",
        statement=(
            f"split conformal: a new {unit_word} from the calibration distribution has {target} "
            f"inside the band at every learned component with probability >= 1 - delta = "
            f"{1.0 - delta:g} (over calibration and new draw; N = {n_units} units)"
        ),
        n_calibration=n_units,
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
        Widen the band to ``beta sqrt(sigma^2 + sigma_epsilon^2)`` using the model's
        ``noise_`` (the effective noise, jitter included), for comparison with noisy
        targets. Comparing noisy targets with the latent band understates coverage once the
        posterior is sharper than the noise.

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
    mean, std = mean_std_batch(model, x)
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
