"""GP-robust Lie terms (Lemma 3) and probabilistic compatibility (Lemma 4, eq. (20)).

Pure functions of arrays: they take the nominal Lie terms, the certificate gradients and a
mean and standard deviation of the unknown dynamics ``omega(x)``, from any uncertainty model.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import check_scalar_range, is_concrete
from .certificates import LieTerms
from .errors import DimensionError, ParameterError
from .formulas import DEFAULT_PARALLEL_RTOL
from .formulas._kernels import compatibility_case, parallel

__all__ = [
    "UncertaintyModel",
    "RobustMargins",
    "robust_margins",
    "robust_lie_terms",
    "ProbabilisticCompatibility",
    "probabilistic_compatibility",
    "joint_probability",
    "check_beta",
    "check_uncertainty_model",
]


@runtime_checkable
class UncertaintyModel(Protocol):
    """What the robust controllers need from a model of ``omega(x)``.

    ``mean_std`` must be a JAX-traceable function of one state of shape (n,) returning the
    posterior mean and standard deviation of ``omega``, each of shape (n,). Components known to
    be exact return mean 0 and standard deviation 0.
    """

    @property
    def n_states(self) -> int:
        """State dimension ``n``."""
        ...

    def mean_std(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and standard deviation of ``omega(x)`` at one state, each of shape (n,)."""
        ...


class RobustMargins(NamedTuple):
    """``Delta_V`` and ``Delta_h`` of Lemma 3, each of shape (...,)."""

    delta_V: jax.Array
    delta_h: jax.Array


def check_uncertainty_model(uncertainty: Any, n: int) -> None:
    """Check that ``uncertainty.mean_std`` maps a state (n,) to a mean and a std of shape (n,).

    Raises
    ------
    TypeError
        If there is no ``mean_std``.
    DimensionError
        If ``n_states`` or the traced output shapes do not match ``n``.
    """
    if not hasattr(uncertainty, "mean_std"):
        raise TypeError("uncertainty must provide mean_std(x) -> (mean, std)")
    if getattr(uncertainty, "n_states", n) != n:
        raise DimensionError(
            f"uncertainty.n_states must equal system.n_states = {n}, got {uncertainty.n_states}"
        )
    probe = jax.ShapeDtypeStruct((n,), jnp.float64)
    out = jax.eval_shape(uncertainty.mean_std, probe)
    shapes = [getattr(o, "shape", None) for o in out] if isinstance(out, tuple) else None
    if shapes is None or len(shapes) != 2 or any(sh != (n,) for sh in shapes):
        got = shapes if shapes is not None else type(out).__name__
        raise DimensionError(
            f"uncertainty.mean_std(x) must return (mean, std), each of shape ({n},), got {got}"
        )


def check_beta(beta: Any, n_states: int) -> jax.Array:
    """Return ``beta`` broadcast to shape (n,), after checking it is finite and >= 0.

    Raises
    ------
    ParameterError
        If some entry is negative.
    DimensionError
        If ``beta`` is neither a scalar nor of shape (n,).
    """
    check_scalar_range("beta", beta, lower=0.0)
    arr = np.asarray(beta, dtype=float) if is_concrete(beta) else beta
    if np.ndim(arr) not in (0, 1) or (np.ndim(arr) == 1 and np.shape(arr)[0] != n_states):
        raise DimensionError(
            f"beta must be a scalar or have shape ({n_states},), got shape {np.shape(arr)}"
        )
    return jnp.broadcast_to(jnp.asarray(arr, dtype=float), (n_states,))


def robust_margins(
    grad_V: jax.Array,
    grad_h: jax.Array,
    mean: jax.Array,
    std: jax.Array,
    beta: jax.Array,
    clf_layer: Any = 0.0,
) -> RobustMargins:
    """``Delta_V`` and ``Delta_h`` of Lemma 3 with the per-component bound.

    ``Delta_V = dV/dx . m(x) + sum_i |dV/dx_i| beta_i sigma_i(x)`` and
    ``Delta_h = dh/dx . m(x) - sum_i |dh/dx_i| beta_i sigma_i(x)``.

    With ``clf_layer = eps > 0`` the CLF's robust term is smoothed at the goal (a boundary
    layer): ``sum_i |dV/dx_i| beta_i sigma_i`` is multiplied by
    ``s(|dV/dx|) = |dV/dx| / sqrt(|dV/dx|^2 + eps^2)`` (see Notes). ``Delta_h``, the safety
    margin, is never changed.

    Parameters
    ----------
    grad_V, grad_h, mean, std : arrays of shape (..., n)
    beta : array broadcastable to (..., n)
    clf_layer : float, optional
        ``eps >= 0`` in the units of ``dV/dx`` (default 0: Lemma 3's term, unchanged).

    Returns
    -------
    RobustMargins

    Notes
    -----
    The paper writes ``beta ||dV/dx|| sigma(x)``, a norm times a vector. If each component
    satisfies ``|omega_i - m_i| <= beta_i sigma_i`` (Lemma 2), then
    ``|dV/dx . (omega - m)| <= sum_i |dV/dx_i| beta_i sigma_i``, which is what is used here; it
    is the tightest bound that follows from the per-component intervals (it is attained at a
    corner of the box).

    **The boundary layer (not in the paper).** Lemma 3's CLF term grows like ``|dV/dx|``, i.e.
    like ``|x|`` at a quadratic CLF's minimum, while the required decrease ``lambda V`` (the
    CLF's linear rate) grows like ``|x|^2``: wherever ``sigma(0) > 0`` the robust CLF
    condition asks for an input of size about ``(1 + kappa) beta sigma(0)`` that does not
    vanish at the goal and points along ``-dV/dx``, a direction that flips as the state
    crosses the goal. A sampled loop then chatters around the goal (docs/obstacle.md measures
    it). With ``eps > 0`` the term becomes quadratic in ``|dV/dx|`` below ``eps`` and the
    input goes to zero continuously. What is given up is exact: ``|g| (1 - s(|g|))`` is at
    most ``0.31 eps`` for every ``g`` (at ``|g| = 0.79 eps``), so the smoothed term is below
    Lemma 3's by at most ``(eps / 2) |beta sigma(x)|`` (Euclidean norm, by Cauchy-Schwarz).
    Where the smoothed CLF condition holds (the compatible formula enforces it; the relaxed
    formula and input limits do not), with Lemma 2's probability the true
    ``dV/dt <= -lambda V + (eps / 2) |beta sigma(x)|``: every sublevel set ``{V <= c}`` with
    ``c >= eps M_c / (2 lambda)``, ``M_c`` the largest ``|beta sigma|`` on it, is invariant,
    and from inside it ``V(t) <= exp(-lambda t) V(0) + eps M_c / (2 lambda)`` (practical
    instead of asymptotic stability). ``eps = 0`` gives Lemma 3's term bit for bit.

    Raises
    ------
    ParameterError, NonFiniteError, DimensionError
        If a concrete ``clf_layer`` is negative, not finite or not a scalar.
    """
    if is_concrete(clf_layer):
        if np.ndim(clf_layer) != 0:
            raise DimensionError(f"clf_layer must be a scalar, got shape {np.shape(clf_layer)}")
        check_scalar_range("clf_layer", clf_layer, lower=0.0)
    spread = beta * std
    weight = jnp.abs(grad_V)
    layer = jnp.asarray(clf_layer, dtype=float)
    if not (is_concrete(clf_layer) and float(np.asarray(clf_layer)) == 0.0):
        # a traced eps = 0 keeps Lemma 3's term (the where below); the smoothing is then
        # computed with eps = 1 only so that its derivatives stay finite
        eps = jnp.where(layer > 0, layer, 1.0)
        # s = |g| / sqrt(|g|^2 + eps^2), |g| computed scaled by its largest entry: neither a
        # huge nor a tiny gradient overflows or underflows, and no 0/0 at the goal (values
        # and derivatives)
        top = jnp.max(weight, -1, keepdims=True)
        positive = top > 0
        # the norm does not depend on the scale: no derivative through it (whose square
        # underflows for tiny gradients)
        scale = jax.lax.stop_gradient(jnp.where(positive, top, 1.0))
        ratio2 = jnp.sum((grad_V / scale) ** 2, -1, keepdims=True)
        norm = scale * jnp.sqrt(jnp.where(positive, ratio2, 1.0))
        shrink = jnp.where(positive, _layer_shrink(norm, eps), 0.0)
        weight = jnp.where(layer > 0, weight * shrink, weight)
    delta_V = jnp.sum(grad_V * mean, -1) + jnp.sum(weight * spread, -1)
    delta_h = jnp.sum(grad_h * mean, -1) - jnp.sum(jnp.abs(grad_h) * spread, -1)
    return RobustMargins(delta_V, delta_h)


@jax.custom_jvp
def _layer_shrink(norm: jax.Array, eps: jax.Array) -> jax.Array:
    """``s = |g| / sqrt(|g|^2 + eps^2)`` for ``|g| >= 0``, ``eps > 0`` (scaled by hypot)."""
    return norm / jnp.hypot(norm, eps)


@_layer_shrink.defjvp
def _layer_shrink_jvp(primals, tangents):
    # ds/d|g| = eps^2 / h^3 and ds/d eps = -|g| eps / h^3 (h = hypot), written as ratios
    # that stay finite for any magnitudes (no squares that overflow or underflow)
    norm, eps = primals
    d_norm, d_eps = tangents
    h = jnp.hypot(norm, eps)
    s, c = norm / h, eps / h
    return s, (c * c * d_norm - s * c * d_eps) / h


def robust_lie_terms(
    terms: LieTerms,
    grad_V: jax.Array,
    grad_h: jax.Array,
    mean: jax.Array,
    std: jax.Array,
    beta: jax.Array,
    clf_layer: Any = 0.0,
) -> LieTerms:
    """Return ``(a~, b, c~, d)`` with ``a~ = a + Delta_V`` and ``c~ = c + Delta_h``, eq. (17).

    Parameters
    ----------
    terms : LieTerms
        Nominal terms.
    grad_V, grad_h, mean, std : arrays of shape (..., n)
    beta : array broadcastable to (..., n)
    clf_layer : float, optional
        The CLF term's boundary layer ``eps`` (:func:`robust_margins`); default 0.

    Returns
    -------
    LieTerms
        With ``sigma = 0`` these are the mean-corrected terms; ``b`` and ``d`` are unchanged
        because ``omega`` does not depend on ``u``.
    """
    m = robust_margins(grad_V, grad_h, mean, std, beta, clf_layer)
    return LieTerms(terms.a + m.delta_V, terms.b, terms.c + m.delta_h, terms.d)


class ProbabilisticCompatibility(NamedTuple):
    """Output of :func:`probabilistic_compatibility`, each of shape (...,).

    Attributes
    ----------
    nominal_compatible : bool array
        Compatibility for the nominal model, Lemma 1 (corrected).
    parallel : bool array
        Whether ``b`` and ``d`` are parallel (relative tolerance), either direction.
    clf_condition : bool array
        Eq. (18): ``Delta_V d.b - Delta_h |b|^2 >= 0``.
    cbf_condition : bool array
        Eq. (19): ``Delta_V |d|^2 - Delta_h b.d >= 0``.
    lemma4 : bool array
        Lemma 4's sufficient condition: nominal compatibility and eqs. (18), (19).
    updated : bool array
        Eq. (20), corrected: compatibility of the robust conditions (17) themselves.
    probability : float
        The probability ``(1 - delta)^n`` with which ``updated`` implies compatibility for the
        true system (from the confidence level of ``beta``), or NaN when not given.
    """

    nominal_compatible: jax.Array
    parallel: jax.Array
    clf_condition: jax.Array
    cbf_condition: jax.Array
    lemma4: jax.Array
    updated: jax.Array
    probability: float


def joint_probability(delta: float, n_components: int) -> float:
    """Return ``(1 - delta)^n``, the probability of Lemma 2's joint bound.

    Raises
    ------
    ParameterError
        If ``delta`` is outside (0, 1) or ``n_components < 1``.
    """
    check_scalar_range("delta", delta, lower=0.0, strict_lower=True, upper=1.0, strict_upper=True)
    if int(n_components) < 1:
        raise ParameterError(f"n_components must be >= 1, got {n_components!r}")
    return float((1.0 - delta) ** int(n_components))


def probabilistic_compatibility(
    terms: LieTerms,
    margins: RobustMargins,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    delta: float | None = None,
    n_components: int | None = None,
    parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
) -> ProbabilisticCompatibility:
    """Where the GP-robust CLF and CBF conditions are compatible (Lemma 4, eqs. (18)-(20)).

    Parameters
    ----------
    terms : LieTerms
        Nominal terms ``(a, b, c, d)``, batched over (...).
    margins : RobustMargins
        ``Delta_V``, ``Delta_h`` at the same states.
    kappa, rho, phi, varphi : float
        Formula parameters.
    delta : float, optional
        Per-component confidence parameter of ``beta`` (in (0, 1)); with ``n_components``
        gives the reported probability ``(1 - delta)^n``.
    n_components : int, optional
        Number of learned components ``n``.
    parallel_rtol : float
        Tolerance of the parallel test.

    Returns
    -------
    ProbabilisticCompatibility

    Notes
    -----
    ``updated`` evaluates the compatibility of ``a~ + b u <= -kappa zeta~`` and
    ``c~ + d u >= rho Gamma~`` exactly, with the corrected parallel condition of
    :func:`safestab.formulas.compatibility` (``v~ <= 0`` when ``b``, ``d`` point the same way;
    the paper prints ``>= 0``). Lemma 4's conditions (18), (19) are reported as printed; with
    the sign correction, Lemma 4's implication holds for anti-parallel and non-parallel
    ``b, d`` (always compatible) but not in general for same-direction parallel ones, which is
    why ``updated`` is the verdict to use. The margins ``zeta``, ``Gamma`` use the robust
    ``a~``, ``c~`` (as Theorem 2 replaces ``a``, ``c`` everywhere).
    """
    prob = float("nan")
    if delta is not None:
        if n_components is None:
            raise ParameterError("n_components is required with delta")
        prob = joint_probability(delta, n_components)
    # one compiled program per shape (called eagerly, its operations one by one compiled
    # about 70 small programs on a first call: seconds on a grid of states)
    verdicts = _probabilistic_jit(*terms, *margins, kappa, rho, phi, varphi, parallel_rtol)
    return ProbabilisticCompatibility(*verdicts, probability=prob)


@jax.jit
def _probabilistic_jit(a, b, c, d, dV, dh, kappa, rho, phi, varphi, parallel_rtol):
    """The verdicts of :func:`probabilistic_compatibility`, in its field order."""
    bb = jnp.sum(b * b, -1)
    dd = jnp.sum(d * d, -1)
    bd = jnp.sum(b * d, -1)
    nominal = compatibility_case(a, b, c, d, kappa, rho, phi, varphi, parallel_rtol) > 0
    robust = compatibility_case(a + dV, b, c + dh, d, kappa, rho, phi, varphi, parallel_rtol) > 0
    clf_cond = dV * bd - dh * bb >= 0
    cbf_cond = dV * dd - dh * bd >= 0
    return (
        nominal, parallel(b, d, parallel_rtol), clf_cond, cbf_cond,
        nominal & clf_cond & cbf_cond, robust,
    )  # fmt: skip
