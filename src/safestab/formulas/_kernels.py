"""Unchecked, jittable kernels shared by the public formulas, the controllers and robust.py.

Nothing here validates its arguments: the public functions in this package check them and
then call these kernels; the controllers call them inside their fused, jitted step. Every
kernel works on batched arrays (leading axes broadcast).

The two-constraint solve (:func:`solve_two`) is the heart of the package. It works on the
*row-normalised* problem

    min 1/2 |z|^2   s.t.   p.z <= -A/|p|,   q.z >= B/|q|,   p = (b, -s)/|(b, -s)|, q = (d, 0)/|d|

with ``z = (u, sqrt(slack_weight) chi)`` and ``s = 1/sqrt(slack_weight)`` (``s = 0`` for the
hard problem). Scaling a constraint row does not move its half-space, so the minimiser is
that of the original problem, while every Gram quantity is now of order one (no overflow for
|b| = 1e200). When both constraints are active (region P3) the minimiser is written in an
orthogonal basis of span(p, q),

    z = (B'/|q|^2) q - y p_perp,   p_perp = p - (p.q/|q|^2) q,   y = w' / (|q|^2 |p_perp|^2),

where the part of ``b`` orthogonal to ``d`` is built from the cross terms
``C_ij = b_i d_j - b_j d_i`` (never from the difference ``b - (b.d/|d|^2) d``), and
``|p_perp|^2 |q|^2 = sum_{i<j} C_ij^2 + s^2 |q|^2`` (Lagrange's identity, no cancellation).
See docs/theory.md, "The stable two-constraint solve", for the error bound.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .results import CompatibilityCase, Region

__all__ = [
    "DEFAULT_PARALLEL_RTOL",
    "SATISFIED_RTOL",
    "satisfied_rtol",
    "Margins",
    "ANTIPARALLEL_DET",
    "scaled_norm",
    "plus_scaled_hypot",
    "safe_hypot",
    "margin",
    "margins",
    "TwoConstraintSolution",
    "solve_two",
    "compatibility_case",
    "parallel",
    "sontag",
    "cbf_only",
    "condition_flags",
    "saturate_single",
    "kkt",
]

#: Relative tolerance on ``sin^2`` of the angle between ``b`` and ``d`` under which two rows
#: pointing the same way count as parallel in the hard problem:
#: ``|b|^2|d|^2 - (b.d)^2 <= DEFAULT_PARALLEL_RTOL |b|^2 |d|^2``. The left side is computed by
#: Lagrange's identity (no cancellation); 1e-12 means an angle below 1e-6 rad, where meeting
#: both conditions would need an input about 1e6 times larger than either single one. Such a
#: point is reported compatible iff ``v <= 0``, with the P1/P2/P4 input (exact there).
DEFAULT_PARALLEL_RTOL = 1e-12

#: Relative tolerance of the ``clf_satisfied`` / ``cbf_satisfied`` flags, measured against the
#: magnitudes of the condition itself (see :func:`condition_flags`): about 450 float64 epsilons,
#: a few hundred times the rounding of evaluating the condition and of the formulas' own error
#: (docs/theory.md), and nowhere near any error that matters.
SATISFIED_RTOL = 1e-13
_UNIT_DOUBLE = float(np.finfo(float).eps) / 2


def satisfied_rtol(unit: float) -> float:
    """:data:`SATISFIED_RTOL` for a step evaluated with unit roundoff ``unit``.

    The same multiple of its rounding; the units are powers of two, so float64's is exactly
    :data:`SATISFIED_RTOL`.
    """
    return SATISFIED_RTOL * (float(unit) / _UNIT_DOUBLE)


#: Below this value of ``sin^2`` of the angle between ``-b`` and ``d`` (about 1e-12 rad), two
#: anti-parallel rows are treated as exactly anti-parallel: the tighter of the two conditions is
#: then the active one. Above it the exact P3 solution is used; its rounding error grows like
#: ``eps / angle``, which at this angle (2e-4 relative, the problem's own conditioning) is still
#: far below the error of ignoring the angle (about ``angle^2`` of the CBF condition and
#: ``angle`` of ``u``), and the division by ``sin^2`` cannot overflow.
ANTIPARALLEL_DET = 1e-24


def _by_region(region: Any, values: dict[Any, Any]) -> Any:
    """``values[region]`` elementwise, 0 for regions not listed.

    Nested ``where`` rather than ``jnp.select``: ``select`` picks its case with an ``argmax``
    over the stacked conditions, a reduction into which XLA fuses the whole computation of
    ``region`` once per case (measured: a fifth of the Monte Carlo loop's time); the C export
    got a loop over the cases. The regions are exclusive, so the value is the same.
    """
    out = jnp.zeros_like(next(iter(values.values())))
    for reg, val in values.items():
        out = jnp.where(region == reg, val, out)
    return out


def _safe(x: Any) -> Any:
    """``x`` where it is nonzero, else 1 (for divisions selected away afterwards)."""
    return jnp.where(x != 0, x, 1.0)


def wedge(x: Any, y: Any) -> Any:
    """The exactly antisymmetric matrix ``C_ij = x_i y_j - x_j y_i`` over the last axis.

    Only the entries above the diagonal are computed; the rest is their negated transpose.
    XLA may contract ``x_i y_j - x_j y_i`` into a fused multiply-add, which rounds ``C_ij`` and
    ``C_ji`` differently; exact antisymmetry is what makes ``y . (C y) = 0`` to rounding, i.e.
    the part of ``x`` orthogonal to ``y`` really orthogonal to ``y``.
    """
    m = x.shape[-1]
    upper = jnp.asarray(np.triu(np.ones((m, m)), k=1))
    t = (x[..., :, None] * y[..., None, :] - x[..., None, :] * y[..., :, None]) * upper
    return t - jnp.swapaxes(t, -1, -2)


@jax.custom_jvp
def scaled_norm(v: Any) -> Any:
    """Euclidean norm over the last axis without overflow or underflow (scaled by max |v_i|).

    Its derivative is ``(v/|v|).dv``, and 0 at ``v = 0`` (where the norm has a kink: 0 is
    the smallest of its one-sided derivatives' sub-gradients), never NaN.
    """
    mx = jnp.max(jnp.abs(v), axis=-1)
    return mx * jnp.sqrt(jnp.sum(jnp.square(v / _safe(mx)[..., None]), axis=-1))


@scaled_norm.defjvp
def _scaled_norm_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    n = scaled_norm(v)
    return n, jnp.where(n > 0, jnp.sum(v / _safe(n)[..., None] * dv, axis=-1), 0.0)


@jax.custom_jvp
def safe_hypot(x: Any, y: Any) -> Any:
    """``jnp.hypot(x, y)`` whose derivative at ``(0, 0)`` is 0 instead of NaN."""
    return jnp.hypot(x, y)


@safe_hypot.defjvp
def _safe_hypot_jvp(primals, tangents):
    (x, y), (dx, dy) = primals, tangents
    r = jnp.hypot(x, y)
    rs = _safe(r)
    return r, jnp.where(r > 0, (x / rs) * dx + (y / rs) * dy, 0.0)


def plus_scaled_hypot(x: Any, p: Any, k: Any) -> Any:
    """Return ``x + k hypot(x, p)`` without cancellation and without spurious overflow.

    Where ``x < 0`` and ``0 < k <= 2`` the two terms can cancel; with ``r = hypot(x, p)``,
    ``x^ = x/r``, ``p^ = p/r`` the rationalised form
    ``r ((1 - k)(1 + k) x^2 - k^2 p^2) / (x^ - k)`` has a denominator of one sign and a
    numerator whose sign is the answer's, with every intermediate bounded by ``r``. For
    ``k > 2`` the direct sum has no cancellation (``k r - |x| >= r``), and ``k^2`` is never
    formed, so a large ``k`` cannot overflow an intermediate. For ``k = 0`` the result is ``x``
    exactly (also when ``p`` is infinite).
    """
    r = jnp.hypot(x, p)
    direct = x + k * r
    rs = _safe(r)
    xh, ph = x / rs, p / rs
    den = xh - k
    num = (1.0 - k) * (1.0 + k) * xh * xh - k * k * ph * ph
    rational = r * num / jnp.where(den < 0, den, -1.0)
    use_rational = (x < 0) & (k > 0) & (k <= 2.0)
    return jnp.where(k == 0, x, jnp.where(use_rational, rational, direct))


class Margins(NamedTuple):
    """``A = a + kappa zeta``, ``B = rho Gamma - c``, and ``zeta``, ``Gamma``, ``|b|``, ``|d|``."""

    A: Any
    B: Any
    zeta: Any
    Gamma: Any
    nb: Any
    nd: Any


@jax.custom_jvp
def margin(x: Any, n: Any, w: Any, k: Any) -> tuple[Any, Any]:
    """``(x + k r, r)`` with ``r = sqrt(x^2 + w n^4)``.

    ``(A, zeta)`` from ``(a, |b|, phi, kappa)``, ``(B, Gamma)`` from ``(-c, |d|, varphi,
    rho)``. The value is cancellation-free (``w n^4`` is formed as the square ``(w^(1/4) n)^2`` and
    the sum by :func:`plus_scaled_hypot`). The derivative is that of ``r^2 = x^2 + w n^4``,
    ``dr = (x dx + n^4 dw / 2 + 2 w n^3 dn) / r``, written with ``x/r`` and ``p/r`` (``p =
    sqrt(w) n^2``) so that it is finite at ``w = 0`` where ``r > 0`` (the chain rule through
    ``w^(1/4)`` would give NaN there). Where ``r = 0`` (``x = 0`` and ``w n^4 = 0``, a kink
    of ``r = |x|``) ``dr`` is taken as 0, the midpoint of its one-sided derivatives in ``x``.
    """
    p = jnp.square(jnp.sqrt(jnp.sqrt(w)) * n)  # sqrt(w) n^2
    return plus_scaled_hypot(x, p, k), jnp.hypot(x, p)


@margin.defjvp
def _margin_jvp(primals, tangents):
    x, n, w, k = primals
    dx, dn, dw, dk = tangents
    A, r = margin(x, n, w, k)
    rs = _safe(r)
    on = r > 0
    xr = x / rs
    nr = n / rs  # n^4 / (2 r) = (n^2 / r) n^2 / 2, and 2 w n^3 / r = 2 (p / r) sqrt(w) n
    sw = jnp.sqrt(w)
    dr = jnp.where(
        on, xr * dx + 0.5 * (n * nr) * (n * n) * dw + 2.0 * (sw * n * nr) * sw * n * dn, 0.0
    )
    return (A, r), (dx + dk * r + k * dr, dr)


def margins(a: Any, b: Any, c: Any, d: Any, kappa: Any, rho: Any, phi: Any, varphi: Any) -> Margins:
    """The CLF and CBF margins, cancellation-free (``phi |b|^4`` is formed as a square).

    The parameters may be numbers, arrays or (from a public function's caller) lists.
    """
    kappa, rho, phi, varphi = (jnp.asarray(v, float) for v in (kappa, rho, phi, varphi))
    nb = scaled_norm(b)
    nd = scaled_norm(d)
    shape = jnp.broadcast_shapes(jnp.shape(a), jnp.shape(nb), jnp.shape(kappa), jnp.shape(phi))
    bc = lambda v, sh: jnp.broadcast_to(jnp.asarray(v, float), sh)  # noqa: E731
    A, zeta = margin(*(bc(v, shape) for v in (a, nb, phi, kappa)))
    shape = jnp.broadcast_shapes(jnp.shape(c), jnp.shape(nd), jnp.shape(rho), jnp.shape(varphi))
    B, Gamma = margin(*(bc(v, shape) for v in (-jnp.asarray(c, float), nd, varphi, rho)))
    return Margins(A, B, zeta, Gamma, nb, nd)


class TwoConstraintSolution(NamedTuple):
    """What :func:`solve_two` returns, batched over (...)."""

    u: Any  #: (..., m)
    region: Any  #: int32 (...,), a Region
    case: Any  #: int32 (...,), a CompatibilityCase of the hard problem (only when hard)
    multipliers: Any  #: (..., 2): lambda1 (CLF), lambda2 (CBF) in the original scaling
    slack: Any  #: (...,): chi (0 for the hard problem)


def solve_two(
    A: Any,
    B: Any,
    b: Any,
    d: Any,
    nb: Any,
    nd: Any,
    *,
    inv_sqrt_slack: Any = None,
    parallel_rtol: Any = 0.0,
) -> TwoConstraintSolution:
    """Exact minimiser of ``1/2|u|^2 (+ 1/2 m chi^2)`` s.t. ``b.u <= -A (+ chi)``, ``d.u >= B``.

    ``inv_sqrt_slack = 1/sqrt(slack_weight)`` for the relaxed problem; ``None`` for the hard
    one, which alone has the parallel (``parallel_rtol``) and zero-vector cases.
    ``nb = |b|`` and ``nd = |d|`` come from :func:`margins`. This one decision procedure
    serves :func:`~safestab.formulas.clf_cbf`, :func:`~safestab.formulas.clf_cbf_relaxed`,
    :func:`~safestab.formulas.compatibility` and the controllers, so that they cannot
    disagree.
    """
    hard = inv_sqrt_slack is None
    s = jnp.asarray(0.0 if hard else inv_sqrt_slack, dtype=float)
    np_ = safe_hypot(nb, s)  # |(b, -s)|
    p_nz = np_ > 0
    d_nz = nd > 0
    bh = b / _safe(np_)[..., None]
    dh = d / _safe(nd)[..., None]
    sh = s / _safe(np_)
    Ah = A / _safe(np_)
    Bh = B / _safe(nd)

    pq = jnp.sum(bh * dh, axis=-1)
    qq = jnp.sum(dh * dh, axis=-1)
    pp = jnp.sum(bh * bh, axis=-1) + sh * sh
    cross = wedge(bh, dh)
    det_u = 0.5 * jnp.sum(cross * cross, axis=(-2, -1))  # |b^|^2|d^|^2 - (b^.d^)^2, >= 0
    b_perp = jnp.sum(cross * dh[..., None, :], axis=-1)  # |d^|^2 times the part of b^ _|_ d
    v = Ah * pq + Bh * pp
    w = Ah * qq + Bh * pq
    den = det_u + sh * sh * qq  # |q|^2 |p_perp|^2

    p4 = (A <= 0) & (B <= 0)
    p1_ok = (A >= 0) & (v <= 0)
    p2_ok = (B >= 0) & (w <= 0)
    R, K = Region, CompatibilityCase
    if hard:
        anti = pq < 0
        parallel = det_u <= parallel_rtol * (pp * qq)
        same_parallel = parallel & ~anti
        exact_anti = anti & (det_u <= ANTIPARALLEL_DET * (pp * qq))
        # both nonzero: P4, then the (anti)parallel special cases, then P1, P2, P3
        anti_region = jnp.where(Ah >= Bh, R.P1, R.P2)
        same_region = jnp.where(v <= 0, jnp.where(A >= 0, R.P1, R.P2), R.INCOMPATIBLE)
        regular = jnp.where(p1_ok, R.P1, jnp.where(p2_ok, R.P2, R.P3))
        both = jnp.where(
            p4,
            R.P4,
            jnp.where(exact_anti, anti_region, jnp.where(same_parallel, same_region, regular)),
        )
        both_case = jnp.where(
            anti & parallel,
            K.ANTIPARALLEL,
            jnp.where(
                same_parallel,
                jnp.where(v <= 0, K.PARALLEL_ORDERED, K.INCOMPATIBLE_PARALLEL),
                K.NOT_PARALLEL,
            ),
        )
        # b = 0: the CLF condition reads 0 <= -A
        b0_region = jnp.where(
            A > 0, R.INCOMPATIBLE, jnp.where(B <= 0, R.P4, jnp.where(d_nz, R.P2, R.INCOMPATIBLE))
        )
        b0_case = jnp.where(
            A > 0,
            K.INCOMPATIBLE_B_ZERO,
            jnp.where(~d_nz & (B > 0), K.INCOMPATIBLE_D_ZERO, K.B_ZERO),
        )
        # d = 0 (b != 0): the CBF condition reads 0 >= B
        d0_region = jnp.where(B > 0, R.INCOMPATIBLE, jnp.where(A <= 0, R.P4, R.P1))
        d0_case = jnp.where(B > 0, K.INCOMPATIBLE_D_ZERO, K.D_ZERO)
        region = jnp.where(~p_nz, b0_region, jnp.where(~d_nz, d0_region, both))
        case = jnp.where(~p_nz, b0_case, jnp.where(~d_nz, d0_case, both_case))
    else:
        # with a slack the rows (b, -s) and (d, 0) are never parallel while d != 0
        regular = jnp.where(p4, R.P4, jnp.where(p1_ok, R.P1, jnp.where(p2_ok, R.P2, R.P3)))
        d0_region = jnp.where(B > 0, R.INCOMPATIBLE, jnp.where(A <= 0, R.P4, R.P1))
        region = jnp.where(d_nz, regular, d0_region)
        case = jnp.zeros_like(region)
    region = region.astype(jnp.int32)
    case = case.astype(jnp.int32)

    # multipliers of the normalised rows; the fallback at an INCOMPATIBLE point is the
    # CBF-only problem when d != 0, else the CLF-only problem (safety first)
    mu1_p3 = w / _safe(den)
    fallback_mu1 = jnp.where(d_nz, 0.0, jnp.maximum(Ah, 0.0) / _safe(pp))
    fallback_mu2 = jnp.maximum(Bh, 0.0) / _safe(qq)
    mu1 = _by_region(region, {R.P1: Ah / _safe(pp), R.P3: mu1_p3, R.INCOMPATIBLE: fallback_mu1})
    mu1 = jnp.where(p_nz, mu1, 0.0)
    # P3: z = (B'/|q|^2) q - y p_perp; elsewhere z = -mu1 p + mu2 q with one of them zero
    coef_d = _by_region(
        region, {R.P2: Bh / _safe(qq), R.P3: Bh / _safe(qq), R.INCOMPATIBLE: fallback_mu2}
    )
    coef_d = jnp.where(d_nz, coef_d, 0.0)
    in_p3 = region == R.P3
    u = (
        coef_d[..., None] * dh
        - jnp.where(in_p3, mu1 / _safe(qq), 0.0)[..., None] * b_perp
        - jnp.where(in_p3, 0.0, mu1)[..., None] * bh
    )
    mu2 = jnp.where(in_p3, (Bh + mu1 * pq) / _safe(qq), coef_d)
    lam1 = mu1 / _safe(np_)
    lam2 = mu2 / _safe(nd)
    slack = mu1 * sh * s  # chi = z_s / sqrt(m) = (mu1 s^) s
    return TwoConstraintSolution(u, region, case, jnp.stack([lam1, lam2], axis=-1), slack)


def compatibility_case(
    a: Any, b: Any, c: Any, d: Any, kappa: Any, rho: Any, phi: Any, varphi: Any, parallel_rtol: Any
) -> Any:
    """The :class:`CompatibilityCase` of the hard problem (int32, shape (...,)).

    It comes from :func:`solve_two`, so it agrees with the combined formula's region.
    """
    mg = margins(a, b, c, d, kappa, rho, phi, varphi)
    return solve_two(mg.A, mg.B, b, d, mg.nb, mg.nd, parallel_rtol=parallel_rtol).case


def parallel(b: Any, d: Any, parallel_rtol: Any) -> Any:
    """Whether nonzero ``b`` and ``d`` are parallel or anti-parallel within ``parallel_rtol``."""
    nb, nd = scaled_norm(b), scaled_norm(d)
    bh = b / _safe(nb)[..., None]
    dh = d / _safe(nd)[..., None]
    cross = wedge(bh, dh)
    det_u = 0.5 * jnp.sum(cross * cross, axis=(-2, -1))
    scale = jnp.sum(bh * bh, axis=-1) * jnp.sum(dh * dh, axis=-1)
    return (nb > 0) & (nd > 0) & (det_u <= parallel_rtol * scale)


def sontag(A: Any, b: Any, nb: Any) -> Any:
    """Eq. (3): ``-A b / |b|^2`` (0 where ``b = 0``), written as ``-(A/|b|) (b/|b|)``."""
    nbs = _safe(nb)
    return jnp.where(nb > 0, -(A / nbs), 0.0)[..., None] * (b / nbs[..., None])


def cbf_only(B: Any, d: Any, nd: Any) -> Any:
    """Eq. (6): ``B d / |d|^2`` (0 where ``d = 0``), written as ``(B/|d|) (d/|d|)``."""
    nds = _safe(nd)
    return jnp.where(nd > 0, B / nds, 0.0)[..., None] * (d / nds[..., None])


def condition_flags(
    a: Any, b: Any, c: Any, d: Any, u: Any, mg: Margins, kappa: Any, rho: Any, rtol: Any
) -> tuple[Any, Any]:
    """Whether ``u`` meets the CLF and the CBF condition, judged against their own magnitudes.

    ``clf_satisfied``: ``a + b.u + kappa zeta <= rtol (|a| + kappa zeta + sum_i |b_i u_i|)``;
    ``cbf_satisfied``: ``c + d.u - rho Gamma >= -rtol (|c| + rho Gamma + sum_i |d_i u_i|)``.
    The right-hand sides bound the rounding of evaluating each condition, so a flag never
    excuses more than that. NaN anywhere gives False.
    """
    bu = b * u
    du = d * u
    clf_res = jnp.sum(bu, axis=-1) + mg.A
    cbf_res = jnp.sum(du, axis=-1) - mg.B
    clf_scale = jnp.abs(a) + kappa * mg.zeta + jnp.sum(jnp.abs(bu), axis=-1)
    cbf_scale = jnp.abs(c) + rho * mg.Gamma + jnp.sum(jnp.abs(du), axis=-1)
    return clf_res <= rtol * clf_scale, cbf_res >= -rtol * cbf_scale


def saturate_single(u: Any, B: Any, d: Any, u_min: Any, u_max: Any) -> tuple[Any, Any]:
    """Safety-first saturation of one input (shape (..., 1)); see ``saturate_safety_first``."""
    dj = d[..., 0]
    lo = jnp.broadcast_to(u_min, u.shape)[..., 0]
    hi = jnp.broadcast_to(u_max, u.shape)[..., 0]
    bound = B / _safe(dj)  # the CBF condition reads u >= bound (d > 0) or u <= bound (d < 0)
    new_lo = jnp.where(dj > 0, jnp.maximum(lo, bound), lo)
    new_hi = jnp.where(dj < 0, jnp.minimum(hi, bound), hi)
    # a bound that overflows (|B / d| beyond float64) asks for an input no box holds
    feasible = jnp.where(dj == 0, B <= 0, (new_lo <= new_hi) & jnp.isfinite(bound))
    best_effort = jnp.where(dj > 0, hi, lo)  # the box input that maximises d u
    # an unbounded side (one-sided limits): the input clipped to the box instead of inf
    best_effort = jnp.where(jnp.isfinite(best_effort), best_effort, jnp.clip(u[..., 0], lo, hi))
    clipped = jnp.clip(u[..., 0], new_lo, new_hi)
    out = jnp.where(dj == 0, jnp.clip(u[..., 0], lo, hi), jnp.where(feasible, clipped, best_effort))
    return out[..., None], feasible


def kkt(
    b: Any, d: Any, A: Any, B: Any, u: Any, lam: Any, chi: Any, slack_weight: Any
) -> tuple[Any, Any, Any, Any, Any]:
    """KKT residuals (clf, cbf, dual, complementarity, stationarity) of a formula's output."""
    lam1, lam2 = lam[..., 0], lam[..., 1]
    g1 = jnp.sum(b * u, -1) + A - chi  # <= 0
    g2 = B - jnp.sum(d * u, -1)  # <= 0
    stat = scaled_norm(u + lam1[..., None] * b - lam2[..., None] * d)
    if slack_weight is not None:
        stat = stat + jnp.abs(slack_weight * chi - lam1)
    return (
        jnp.maximum(g1, 0.0),
        jnp.maximum(g2, 0.0),
        jnp.maximum(-lam1, 0.0) + jnp.maximum(-lam2, 0.0),
        jnp.abs(lam1 * g1) + jnp.abs(lam2 * g2),
        stat,
    )
