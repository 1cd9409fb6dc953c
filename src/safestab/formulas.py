"""Closed-form universal formulas over the Lie terms ``(a, b, c, d)``.

Every formula here is a pure, jittable function of batched arrays. Nothing here knows about
systems, certificates or Gaussian processes: callers compute

* ``a = L_f V + lambda V`` and ``b = L_g V`` (CLF side), shapes ``(...,)`` and ``(..., m)``,
* ``c = L_f h + beta h`` and ``d = L_g h`` (CBF side), shapes ``(...,)`` and ``(..., m)``,

and pass them in. Batch axes broadcast. See ``docs/theory.md`` for the derivations.

Notation used throughout (the paper's, with the corrections listed in ``docs/theory.md``)::

    zeta  = sqrt(a^2 + phi |b|^4)        Gamma = sqrt(c^2 + varphi |d|^4)
    A     = a + kappa zeta               B     = rho Gamma - c
    CLF condition:  b u <= -A            CBF condition:  d u >= B

The combined formulas solve ``min 1/2 |u|^2`` subject to both conditions (plus a slack ``chi``
on the CLF side with weight ``1/2 slack_weight chi^2`` in the relaxed formula) exactly, through
the active-set cases P1 to P4 of the paper's Theorem 1.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._validation import check_finite, check_same_batch, check_scalar_range, is_concrete
from .errors import DimensionError, ParameterError

__all__ = [
    "Region",
    "CompatibilityCase",
    "FormulaResult",
    "Compatibility",
    "KKTResiduals",
    "DEFAULT_PARALLEL_RTOL",
    "zeta",
    "clf_sontag",
    "cbf_universal",
    "clf_cbf",
    "clf_cbf_relaxed",
    "compatibility",
    "project_box",
    "saturate_safety_first",
    "kkt_residuals",
]

Array = jax.Array

#: Relative tolerance on ``sin^2`` of the angle between ``b`` and ``d`` under which the two
#: vectors count as parallel: ``|b|^2|d|^2 - (b.d)^2 <= DEFAULT_PARALLEL_RTOL |b|^2 |d|^2``.
#: Exactly parallel vectors give about 1e-32 in floating point (the determinant is computed by
#: the Lagrange identity, without cancellation); 1e-12 means an angle below 1e-6 rad, where the
#: two-constraint solution would need an input about 1e6 times larger than either single one.
DEFAULT_PARALLEL_RTOL = 1e-12


class Region(IntEnum):
    """Which case of the combined formula applied at a point (Theorem 1, eq. (8)).

    ``INCOMPATIBLE`` means no input satisfies both conditions (the QP is infeasible); the
    formula then returns the documented safety-first fallback.
    """

    INCOMPATIBLE = 0
    P1 = 1  #: only the CLF condition is active: u = -A / |b|^2 b
    P2 = 2  #: only the CBF condition is active: u = B / |d|^2 d
    P3 = 3  #: both are active: u = -lambda1 b + lambda2 d
    P4 = 4  #: neither is active: u = 0


class CompatibilityCase(IntEnum):
    """Why the CLF and CBF conditions are (positive values) or are not (negative) compatible.

    Lemma 1 of the paper assumes ``b != 0`` and ``d != 0``; the zero cases are added here.
    """

    NOT_PARALLEL = 1  #: Lemma 1 case (i): the two hyperplanes intersect
    PARALLEL_ORDERED = 2  #: b, d point the same way and the half-spaces overlap (v <= 0)
    ANTIPARALLEL = 3  #: b, d point opposite ways: both half-spaces contain a common ray
    B_ZERO = 4  #: b = 0 and A <= 0: the CLF condition holds for every input
    D_ZERO = 5  #: d = 0 and B <= 0: the CBF condition holds for every input
    INCOMPATIBLE_PARALLEL = -1  #: b, d point the same way and the half-spaces are disjoint
    INCOMPATIBLE_B_ZERO = -2  #: b = 0 and A > 0: no input satisfies the CLF condition
    INCOMPATIBLE_D_ZERO = -3  #: d = 0 and B > 0: no input satisfies the CBF condition


@dataclasses.dataclass(frozen=True)
class FormulaResult:
    """Output of :func:`clf_cbf` and :func:`clf_cbf_relaxed`.

    Unpacks as a pair: ``u, region = clf_cbf(...)``.

    Attributes
    ----------
    u : array of shape (..., m)
        The input.
    region : int array of shape (...,)
        A :class:`Region` value per point.
    multipliers : array of shape (..., 2)
        KKT multipliers ``(lambda1, lambda2)`` of the CLF and CBF constraints; at an
        ``INCOMPATIBLE`` point, those of the fallback problem.
    slack : array of shape (...,)
        The CLF slack ``chi`` (zero for :func:`clf_cbf`).
    """

    u: Array
    region: Array
    multipliers: Array
    slack: Array

    def __iter__(self):  # noqa: D105 - allows ``u, region = result``
        return iter((self.u, self.region))


jax.tree_util.register_dataclass(
    FormulaResult, data_fields=["u", "region", "multipliers", "slack"], meta_fields=[]
)


@dataclasses.dataclass(frozen=True)
class Compatibility:
    """Output of :func:`compatibility`.

    Attributes
    ----------
    compatible : bool array of shape (...,)
        Whether some input satisfies both conditions.
    case : int array of shape (...,)
        A :class:`CompatibilityCase` value per point.
    """

    compatible: Array
    case: Array


jax.tree_util.register_dataclass(Compatibility, data_fields=["compatible", "case"], meta_fields=[])


@dataclasses.dataclass(frozen=True)
class KKTResiduals:
    """Residuals of the KKT conditions of a formula's QP, per point (all >= 0).

    Attributes
    ----------
    clf_violation : array of shape (...,)
        ``max(0, b u + A - chi)``.
    cbf_violation : array of shape (...,)
        ``max(0, B - d u)``.
    dual_violation : array of shape (...,)
        ``max(0, -lambda1) + max(0, -lambda2)``.
    complementarity : array of shape (...,)
        ``|lambda1 (b u + A - chi)| + |lambda2 (d u - B)|``.
    stationarity : array of shape (...,)
        ``|u + lambda1 b - lambda2 d| + |slack_weight chi - lambda1|`` (second term relaxed only).
    """

    clf_violation: Array
    cbf_violation: Array
    dual_violation: Array
    complementarity: Array
    stationarity: Array


jax.tree_util.register_dataclass(
    KKTResiduals,
    data_fields=[
        "clf_violation",
        "cbf_violation",
        "dual_violation",
        "complementarity",
        "stationarity",
    ],
    meta_fields=[],
)


# --------------------------------------------------------------------------------------------
# validation


def _check_lie_terms(a: Any, b: Any, c: Any = None, d: Any = None) -> None:
    pairs = [("a", a, "b", b)] + ([("c", c, "d", d)] if c is not None else [])
    for sname, s, vname, v in pairs:
        vshape = np.shape(v)
        if len(vshape) == 0:
            raise DimensionError(f"{vname} must have shape (..., m), got a scalar")
        check_same_batch((sname, vname), (np.shape(s), vshape[:-1]))
        check_finite(sname, s)
        check_finite(vname, v)
    if c is not None and np.shape(b)[-1] != np.shape(d)[-1]:
        raise DimensionError(
            f"b and d must have the same last axis (the input dimension m), "
            f"got b shape {np.shape(b)} and d shape {np.shape(d)}"
        )


def _check_params(**params: Any) -> None:
    for name, value in params.items():
        if name == "slack_weight":
            check_scalar_range(name, value, lower=0.0, strict_lower=True)
        elif name == "parallel_rtol":
            check_scalar_range(name, value, lower=0.0, upper=1.0)
        else:
            check_scalar_range(name, value, lower=0.0)


# --------------------------------------------------------------------------------------------
# shared algebra


def zeta(a: Array, b: Array, phi: Any) -> Array:
    """Return ``sqrt(a^2 + phi |b|^4)``, the CLF margin function (also ``Gamma`` for c, d).

    Computed as ``hypot(a, sqrt(phi) |b|^2)``, which does not overflow for large ``a``.

    Parameters
    ----------
    a : array of shape (...,)
    b : array of shape (..., m)
    phi : float or array broadcastable to (...,), >= 0

    Returns
    -------
    array of shape (...,)
    """
    bb = jnp.sum(b * b, axis=-1)
    return jnp.hypot(a, jnp.sqrt(phi) * bb)


def _gram(b: Array, d: Array) -> tuple[Array, Array, Array, Array]:
    """Return ``|b|^2, b.d, |d|^2`` and ``|b|^2|d|^2 - (b.d)^2`` (by the Lagrange identity)."""
    bb = jnp.sum(b * b, axis=-1)
    dd = jnp.sum(d * d, axis=-1)
    bd = jnp.sum(b * d, axis=-1)
    # sum_{i<j} (b_i d_j - b_j d_i)^2: exact zero for m = 1, no cancellation for parallel b, d
    cross = b[..., :, None] * d[..., None, :] - b[..., None, :] * d[..., :, None]
    det = 0.5 * jnp.sum(cross * cross, axis=(-2, -1))
    return bb, bd, dd, det


def _safe_div(num: Array, den: Array) -> Array:
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _two_halfspace_qp(
    A: Array, B: Array, bb: Array, bd: Array, dd: Array, det: Array, not_parallel: Array
) -> tuple[Array, Array, Array]:
    """Solve ``min 1/2|z|^2 s.t. b.z <= -A, d.z >= B`` in Gram form.

    The minimiser is ``z = -lambda1 b + lambda2 d``. Returns ``(lambda1, lambda2, region)``.
    At an infeasible point the multipliers are those of the safety-first fallback: the CBF-only
    problem when ``d != 0``, else the CLF-only problem.
    """
    v = A * bd + B * bb
    w = A * dd + B * bd
    b_nonzero = bb > 0
    d_nonzero = dd > 0
    p4 = (A <= 0) & (B <= 0)
    p1 = b_nonzero & (A >= 0) & (v <= 0)
    p2 = d_nonzero & (B >= 0) & (w <= 0)
    p3 = not_parallel & (v >= 0) & (w >= 0)
    region = jnp.where(
        p4,
        Region.P4,
        jnp.where(p1, Region.P1, jnp.where(p2, Region.P2, jnp.where(p3, Region.P3, 0))),
    ).astype(jnp.int32)

    fallback_cbf = _safe_div(jnp.maximum(B, 0.0), dd)
    fallback_clf = jnp.where(d_nonzero, 0.0, _safe_div(jnp.maximum(A, 0.0), bb))
    lam1 = jnp.select(
        [region == Region.P1, region == Region.P3, region == Region.INCOMPATIBLE],
        [_safe_div(A, bb), _safe_div(w, det), fallback_clf],
        0.0,
    )
    lam2 = jnp.select(
        [region == Region.P2, region == Region.P3, region == Region.INCOMPATIBLE],
        [_safe_div(B, dd), _safe_div(v, det), fallback_cbf],
        0.0,
    )
    return lam1, lam2, region


def _plus_scaled_hypot(x: Array, p: Array, k: Any) -> Array:
    """Return ``x + k hypot(x, p)`` without cancellation when ``x < 0``.

    Where ``x < 0`` the two terms have opposite signs; the rationalised form
    ``((1 - k^2) x^2 - k^2 p^2) / (x - k hypot(x, p))`` has a denominator without cancellation
    and a numerator whose sign is the answer's. Valid for magnitudes below about 1e150.
    """
    r = jnp.hypot(x, p)
    direct = x + k * r
    den = x - k * r
    safe_den = jnp.where(den < 0, den, -1.0)
    rational = ((1.0 - k) * (1.0 + k) * x * x - k * k * p * p) / safe_den
    return jnp.where((x < 0) & (den < 0), rational, direct)


def _margins(a, b, c, d, kappa, rho, phi, varphi):
    """Return ``A = a + kappa zeta`` and ``B = rho Gamma - c`` (both cancellation-free)."""
    p = jnp.sqrt(phi) * jnp.sum(b * b, axis=-1)
    q = jnp.sqrt(varphi) * jnp.sum(d * d, axis=-1)
    A = _plus_scaled_hypot(a, p, kappa)
    B = _plus_scaled_hypot(-c, q, rho)
    return A, B


# --------------------------------------------------------------------------------------------
# single-certificate formulas


@jax.jit
def _clf_sontag(a, b, kappa, phi):
    A = _plus_scaled_hypot(a, jnp.sqrt(phi) * jnp.sum(b * b, axis=-1), kappa)
    bb = jnp.sum(b * b, axis=-1)
    return -_safe_div(A, bb)[..., None] * b


def clf_sontag(a: Any, b: Any, *, kappa: Any, phi: Any) -> Array:
    """Sontag-type universal formula for a CLF, eq. (3) ``CLF_Sontag_Law``.

    ``u = -(a + kappa zeta) / |b|^2 b`` where ``b != 0`` and ``u = 0`` where ``b = 0``, with
    ``zeta = sqrt(a^2 + phi |b|^4)``.

    Parameters
    ----------
    a : array of shape (...,)
        ``L_f V + lambda V``.
    b : array of shape (..., m)
        ``L_g V``.
    kappa : float or array broadcastable to (...,)
        Convergence-speed parameter, >= 0.
    phi : float or array broadcastable to (...,)
        Weight of ``|b|^4`` in ``zeta``, >= 0.

    Returns
    -------
    u : array of shape (..., m)

    Raises
    ------
    DimensionError
        If ``b`` is a scalar or the batch shapes do not broadcast.
    NonFiniteError
        If an input contains NaN or inf.
    ParameterError
        If ``kappa`` or ``phi`` is negative.

    Notes
    -----
    As printed, the formula makes the CLF condition ``a + b u <= -kappa zeta`` hold with
    equality. For ``kappa >= 1`` the bracket ``a + kappa zeta`` is never negative, and the input
    is the least-norm one; for ``kappa < 1`` and ``a < 0`` the bracket can be negative and the
    formula then *spends* input to reach the boundary, unlike the QP solution (which is 0 there,
    region P4 of :func:`clf_cbf`). Where ``b = 0`` the condition holds only if ``a <= 0``.
    """
    _check_lie_terms(a, b)
    _check_params(kappa=kappa, phi=phi)
    return _clf_sontag(jnp.asarray(a, float), jnp.asarray(b, float), kappa, phi)


@jax.jit
def _cbf_universal(c, d, rho, varphi):
    B = _plus_scaled_hypot(-c, jnp.sqrt(varphi) * jnp.sum(d * d, axis=-1), rho)
    dd = jnp.sum(d * d, axis=-1)
    return _safe_div(B, dd)[..., None] * d


def cbf_universal(c: Any, d: Any, *, rho: Any, varphi: Any) -> Array:
    """Universal formula for a CBF, eq. (6) ``CBF_Universal_Law``.

    ``u = (rho Gamma - c) / |d|^2 d`` where ``d != 0`` and ``u = 0`` where ``d = 0``, with
    ``Gamma = sqrt(c^2 + varphi |d|^4)``.

    Parameters
    ----------
    c : array of shape (...,)
        ``L_f h + beta h``.
    d : array of shape (..., m)
        ``L_g h``.
    rho : float or array broadcastable to (...,)
        Conservatism parameter, >= 0.
    varphi : float or array broadcastable to (...,)
        Weight of ``|d|^4`` in ``Gamma``, >= 0.

    Returns
    -------
    u : array of shape (..., m)

    Raises
    ------
    DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_sontag`.

    Notes
    -----
    The CBF condition ``c + d u >= rho Gamma`` holds with equality where ``d != 0``. Where
    ``d = 0`` it holds only if ``c >= rho Gamma``.
    """
    _check_lie_terms(c, d)
    _check_params(rho=rho, varphi=varphi)
    return _cbf_universal(jnp.asarray(c, float), jnp.asarray(d, float), rho, varphi)


# --------------------------------------------------------------------------------------------
# combined formulas


def _combined(a, b, c, d, kappa, rho, phi, varphi, inv_slack, parallel_rtol):
    """Combined formula; ``inv_slack = 1/slack_weight`` (0 for the hard-constraint formula)."""
    A, B = _margins(a, b, c, d, kappa, rho, phi, varphi)
    bb, bd, dd, det = _gram(b, d)
    # Relaxed problem: substitute s = sqrt(m) chi; the CLF row becomes [b, -1/sqrt(m)], which
    # adds 1/m to |b|^2 and dd/m to the Gram determinant (and leaves b.d unchanged).
    bb_aug = bb + inv_slack
    det_aug = det + inv_slack * dd
    # The parallel tolerance guards against rounding in det for (nearly) parallel b, d. The
    # slack's share inv_slack * dd is exact and positive, so with a slack the two augmented
    # rows are never parallel while d != 0, however large |b| is.
    not_parallel = (det > parallel_rtol * bb * dd) | (inv_slack * dd > 0)
    lam1, lam2, region = _two_halfspace_qp(A, B, bb_aug, bd, dd, det_aug, not_parallel)
    u = -lam1[..., None] * b + lam2[..., None] * d
    slack = lam1 * inv_slack
    return FormulaResult(u=u, region=region, multipliers=jnp.stack([lam1, lam2], -1), slack=slack)


@jax.jit
def _clf_cbf(a, b, c, d, kappa, rho, phi, varphi, parallel_rtol):
    return _combined(a, b, c, d, kappa, rho, phi, varphi, 0.0, parallel_rtol)


@jax.jit
def _clf_cbf_relaxed(a, b, c, d, kappa, rho, phi, varphi, slack_weight, parallel_rtol):
    return _combined(a, b, c, d, kappa, rho, phi, varphi, 1.0 / slack_weight, parallel_rtol)


def _as_float(*xs):
    return tuple(jnp.asarray(x, dtype=float) for x in xs)


def clf_cbf(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
) -> FormulaResult:
    """Combined CLF-CBF universal formula, Theorem 1, eq. (8) ``QP_Control_Law_relaxed``.

    Returns the exact minimiser of ``1/2 |u|^2`` subject to ``a + b u <= -kappa zeta`` and
    ``c + d u >= rho Gamma``, by cases:

    ======  ==============================  ===============================================
    region  condition                       u
    ======  ==============================  ===============================================
    P4      A <= 0 and B <= 0               0
    P1      A >= 0 and v <= 0               -A / |b|^2 b
    P2      B >= 0 and w <= 0               B / |d|^2 d
    P3      v >= 0, w >= 0, b, d not ||     -(w/det) b + (v/det) d
    ======  ==============================  ===============================================

    with ``A = a + kappa zeta``, ``B = rho Gamma - c``, ``v = A b.d + B |b|^2``,
    ``w = A |d|^2 + B b.d`` and ``det = |b|^2 |d|^2 - (b.d)^2``; the first matching row wins.

    Parameters
    ----------
    a, c : arrays of shape (...,)
        ``L_f V + lambda V`` and ``L_f h + beta h``.
    b, d : arrays of shape (..., m)
        ``L_g V`` and ``L_g h``.
    kappa, rho : float or array broadcastable to (...,)
        >= 0.
    phi, varphi : float or array broadcastable to (...,)
        >= 0.
    parallel_rtol : float, optional
        Relative tolerance of the parallel test (see :data:`DEFAULT_PARALLEL_RTOL`).

    Returns
    -------
    FormulaResult
        ``u`` of shape (..., m), ``region`` of shape (...,), multipliers and a zero slack.
        Unpacks as ``u, region``.

    Raises
    ------
    DimensionError
        If ``b`` and ``d`` differ in their last axis or the batch shapes do not broadcast.
    NonFiniteError
        If an input contains NaN or inf.
    ParameterError
        If a parameter is negative.

    Notes
    -----
    Where no input satisfies both conditions (``b`` and ``d`` parallel, pointing the same way,
    with disjoint half-spaces; ``b = 0`` with ``A > 0``; or ``d = 0`` with ``B > 0``) the
    region is ``INCOMPATIBLE`` and ``u`` is the safety-first fallback: the least-norm input
    meeting the CBF condition alone, ``max(B, 0) / |d|^2 d`` (the limit of
    :func:`clf_cbf_relaxed` as the slack becomes free); if ``d = 0`` as well, the least-norm
    input meeting the CLF condition alone. Never NaN for finite input.

    The paper's printed definitions of the P3 weights are garbled; the table above is derived
    from the KKT conditions in ``docs/theory.md``.
    """
    _check_lie_terms(a, b, c, d)
    _check_params(kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=parallel_rtol)
    return _clf_cbf(*_as_float(a, b, c, d), kappa, rho, phi, varphi, parallel_rtol)


def clf_cbf_relaxed(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    slack_weight: Any,
    parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
) -> FormulaResult:
    """Relaxed CLF-CBF formula for the incompatible case, Theorem 3, eq. (22).

    Returns the exact minimiser of ``1/2 |u|^2 + 1/2 slack_weight chi^2`` subject to
    ``a + b u <= -kappa zeta + chi`` and ``c + d u >= rho Gamma``: the table of
    :func:`clf_cbf` with ``|b|^2`` replaced by ``|b|^2 + 1/slack_weight`` and
    ``det = (|b|^2 + 1/slack_weight) |d|^2 - (b.d)^2``. The slack is ``chi = lambda1 /
    slack_weight``.

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi, parallel_rtol
        As for :func:`clf_cbf`.
    slack_weight : float or array broadcastable to (...,)
        Weight ``m`` of the slack, > 0 (the paper's ``m``; larger means closer to the hard
        CLF constraint).

    Returns
    -------
    FormulaResult
        With ``slack`` holding ``chi``. Unpacks as ``u, region``.

    Raises
    ------
    DimensionError, NonFiniteError
        As for :func:`clf_cbf`.
    ParameterError
        If a parameter is negative or ``slack_weight <= 0``.

    Notes
    -----
    Corrections to the printed theorem (derived in ``docs/theory.md``): the right-hand side of
    the multiplier system is ``rho Gamma - c`` (printed ``Gamma - rho c``);
    ``v_bar = A b.d + B (1/m + |b|^2)``; and the objective weight is ``1/2 m chi^2`` (the
    proof writes ``1/m chi^2``, which does not give the printed ``1/m + |b|^2``). The only
    infeasible case left is ``d = 0`` with ``B > 0``, where the CLF-only solution is returned
    with region ``INCOMPATIBLE``.
    """
    _check_lie_terms(a, b, c, d)
    _check_params(
        kappa=kappa,
        rho=rho,
        phi=phi,
        varphi=varphi,
        slack_weight=slack_weight,
        parallel_rtol=parallel_rtol,
    )
    return _clf_cbf_relaxed(
        *_as_float(a, b, c, d), kappa, rho, phi, varphi, slack_weight, parallel_rtol
    )


# --------------------------------------------------------------------------------------------
# compatibility


@jax.jit
def _compatibility(a, b, c, d, kappa, rho, phi, varphi, parallel_rtol):
    A, B = _margins(a, b, c, d, kappa, rho, phi, varphi)
    bb, bd, dd, det = _gram(b, d)
    v = A * bd + B * bb
    C = CompatibilityCase
    parallel = det <= parallel_rtol * bb * dd
    case = jnp.where(
        bb == 0,
        jnp.where(
            A > 0,
            C.INCOMPATIBLE_B_ZERO,
            jnp.where((dd == 0) & (B > 0), C.INCOMPATIBLE_D_ZERO, C.B_ZERO),
        ),
        jnp.where(
            dd == 0,
            jnp.where(B > 0, C.INCOMPATIBLE_D_ZERO, C.D_ZERO),
            jnp.where(
                ~parallel,
                C.NOT_PARALLEL,
                jnp.where(
                    bd < 0,
                    C.ANTIPARALLEL,
                    jnp.where(v <= 0, C.PARALLEL_ORDERED, C.INCOMPATIBLE_PARALLEL),
                ),
            ),
        ),
    ).astype(jnp.int32)
    return Compatibility(compatible=case > 0, case=case)


def compatibility(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    parallel_rtol: float = DEFAULT_PARALLEL_RTOL,
) -> Compatibility:
    """Whether the CLF and CBF conditions can hold together, Lemma 1, eq. (7).

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi, parallel_rtol
        As for :func:`clf_cbf`.

    Returns
    -------
    Compatibility
        ``compatible`` (bool, shape (...,)) and ``case`` (a :class:`CompatibilityCase`).

    Raises
    ------
    DimensionError, NonFiniteError, ParameterError
        As for :func:`clf_cbf`.

    Notes
    -----
    Correction to Lemma 1: when ``b`` and ``d`` point the same way (``d = t b``, ``t > 0``)
    the conditions ``b u <= -A`` and ``b u >= B / t`` are compatible iff ``t A + B <= 0``,
    i.e. ``v = A b.d + B |b|^2 <= 0`` (``v`` and ``w`` then have the same sign). The lemma as
    printed asks for ``v >= 0`` or ``w >= 0``, the opposite inequality, and its absolute value
    in the parallel test also counts anti-parallel vectors, which are always compatible. The
    parallel test uses the relative tolerance ``parallel_rtol``. Lemma 1 assumes ``b, d != 0``;
    the zero cases are decided directly (``b = 0``: compatible iff ``A <= 0``, and so on).
    """
    _check_lie_terms(a, b, c, d)
    _check_params(kappa=kappa, rho=rho, phi=phi, varphi=varphi, parallel_rtol=parallel_rtol)
    return _compatibility(*_as_float(a, b, c, d), kappa, rho, phi, varphi, parallel_rtol)


# --------------------------------------------------------------------------------------------
# input limits


def _check_box(u_min: Any, u_max: Any) -> None:
    check_finite("u_min", u_min)
    check_finite("u_max", u_max)
    if is_concrete(u_min, u_max):
        lo, hi = np.asarray(u_min, float), np.asarray(u_max, float)
        try:
            bad = lo > hi
        except ValueError:
            raise DimensionError(
                f"u_min and u_max must broadcast, got shapes {lo.shape} and {hi.shape}"
            ) from None
        if np.any(bad):
            raise ParameterError(
                f"u_min must be <= u_max elementwise, got u_min={lo.tolist()} "
                f"and u_max={hi.tolist()}"
            )


def project_box(u: Any, u_min: Any, u_max: Any) -> Array:
    """Project an input onto the box ``u_min <= u <= u_max``, eq. (26) ``QP_projection``.

    The QP ``min 1/2|u_proj - u|^2`` over a box separates per component, so its solution is the
    componentwise clip.

    Parameters
    ----------
    u : array of shape (..., m)
    u_min, u_max : arrays broadcastable to (..., m)
        Bounds with ``u_min <= u_max``.

    Returns
    -------
    array of shape (..., m)

    Raises
    ------
    ParameterError
        If ``u_min > u_max`` anywhere.
    NonFiniteError
        If ``u`` or a bound contains NaN or inf.
    """
    check_finite("u", u)
    _check_box(u_min, u_max)
    return jnp.clip(*_as_float(u, u_min, u_max))


@jax.jit
def _saturate_safety_first(u, c, d, rho, varphi, u_min, u_max):
    B = _plus_scaled_hypot(-c, jnp.sqrt(varphi) * jnp.sum(d * d, axis=-1), rho)
    dj = d[..., 0]
    lo = jnp.broadcast_to(u_min, u.shape)[..., 0]
    hi = jnp.broadcast_to(u_max, u.shape)[..., 0]
    bound = _safe_div(B, jnp.abs(dj)) * jnp.sign(dj)  # B / d where d != 0
    new_lo = jnp.where(dj > 0, jnp.maximum(lo, bound), lo)
    new_hi = jnp.where(dj < 0, jnp.minimum(hi, bound), hi)
    feasible = jnp.where(dj == 0, B <= 0, new_lo <= new_hi)
    best_effort = jnp.where(dj > 0, hi, lo)  # the box input that maximises d u
    clipped = jnp.clip(u[..., 0], new_lo, new_hi)
    out = jnp.where(
        feasible | (dj == 0), jnp.where(dj == 0, jnp.clip(u[..., 0], lo, hi), clipped), best_effort
    )
    return out[..., None], feasible


def saturate_safety_first(
    u: Any, c: Any, d: Any, *, rho: Any, varphi: Any, u_min: Any, u_max: Any
) -> tuple[Array, Array]:
    """Saturate a single input so that the CBF condition survives the input limits.

    Projects ``u`` onto the part of ``[u_min, u_max]`` where ``c + d u >= rho Gamma``. When
    that part is empty, returns the box input that comes closest (maximises ``d u``). This goes
    beyond the paper, whose projection (eq. (26)) may give up the CBF condition even when some
    admissible input keeps it.

    Parameters
    ----------
    u : array of shape (..., 1)
        The unconstrained input.
    c : array of shape (...,)
    d : array of shape (..., 1)
    rho, varphi : float or array broadcastable to (...,)
    u_min, u_max : arrays broadcastable to (..., 1)

    Returns
    -------
    u_sat : array of shape (..., 1)
    cbf_feasible : bool array of shape (...,)
        Whether some input in the box satisfies the CBF condition (then ``u_sat`` does).

    Raises
    ------
    DimensionError
        If the input dimension is not 1.
    ParameterError, NonFiniteError
        As for :func:`project_box` and :func:`cbf_universal`.
    """
    if np.shape(u)[-1:] != (1,) or np.shape(d)[-1:] != (1,):
        raise DimensionError(
            "saturate_safety_first needs a single input: u and d must have shape (..., 1), "
            f"got u shape {np.shape(u)} and d shape {np.shape(d)}"
        )
    check_finite("u", u)
    _check_lie_terms(c, d)
    _check_params(rho=rho, varphi=varphi)
    _check_box(u_min, u_max)
    return _saturate_safety_first(*_as_float(u, c, d), rho, varphi, *_as_float(u_min, u_max))


# --------------------------------------------------------------------------------------------
# certificate


def kkt_residuals(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    result: FormulaResult,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    slack_weight: Any = None,
) -> KKTResiduals:
    """KKT residuals of ``result`` for the QP behind :func:`clf_cbf` or the relaxed formula.

    A point where all residuals vanish (to rounding) is certified optimal without any solver:
    the QP is strictly convex, so the KKT conditions are sufficient.

    Parameters
    ----------
    a, b, c, d, kappa, rho, phi, varphi
        As for :func:`clf_cbf`.
    result : FormulaResult
        The output to check.
    slack_weight : float, optional
        Given for the relaxed problem; ``None`` for the hard one.

    Returns
    -------
    KKTResiduals
    """
    a, b, c, d = _as_float(a, b, c, d)
    A, B = _margins(a, b, c, d, kappa, rho, phi, varphi)
    u, lam = result.u, result.multipliers
    lam1, lam2 = lam[..., 0], lam[..., 1]
    chi = result.slack
    g1 = jnp.sum(b * u, -1) + A - chi  # <= 0
    g2 = B - jnp.sum(d * u, -1)  # <= 0
    stat = jnp.linalg.norm(u + lam1[..., None] * b - lam2[..., None] * d, axis=-1)
    if slack_weight is not None:
        stat = stat + jnp.abs(slack_weight * chi - lam1)
    return KKTResiduals(
        clf_violation=jnp.maximum(g1, 0.0),
        cbf_violation=jnp.maximum(g2, 0.0),
        dual_violation=jnp.maximum(-lam1, 0.0) + jnp.maximum(-lam2, 0.0),
        complementarity=jnp.abs(lam1 * g1) + jnp.abs(lam2 * g2),
        stationarity=stat,
    )
