"""Several CLFs and CBFs, input limits inside the problem, and weighted objectives (issue 10).

The general problem behind the universal formula::

    min  1/2 (u - u_nom)^T H (u - u_nom) + 1/2 sum_j m_j chi_j^2
    s.t. a_j + b_j.u <= -kappa zeta_j + chi_j      (CLF j; chi_j = 0 without slack)
         c_i + d_i.u >= rho Gamma_i                (CBF i)
         u_min <= u <= u_max                       (limits)

is solved exactly without an iterative solver: the change of variables
``v = L^T (u - u_nom)`` (``H = L L^T``) makes the objective ``1/2 |(v, s)|^2`` with
``s_j = sqrt(m_j) chi_j``, and every active set of at most ``dim`` rows is solved in closed form
(a small orthogonal solve each, all subsets at once) and the unique KKT point kept
(:mod:`safestab.formulas._active_set`). With one CLF, one CBF, no limits, ``u_nom = 0`` and
``H = I`` this is the two-constraint formula itself (:func:`clf_cbf` /
:func:`clf_cbf_relaxed`), bit for bit.

Size: the number of subsets grows like ``C(rows, dim)``; up to ``k + 2m <= 10`` rows (the
benchmarks measure it) the whole solve stays a few thousand fused arithmetic operations.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_finite, check_real
from ..errors import DimensionError, ParameterError
from ._active_set import active_sets, solve_rows
from ._checks import as_float, check_box, check_output_finite, check_params
from ._kernels import margins, solve_two

__all__ = ["MultiStatus", "MultiResult", "clf_cbf_multi", "MAX_ROWS"]

#: The most constraint rows (CLFs + CBFs + 2 per limited input) :func:`clf_cbf_multi` accepts.
MAX_ROWS = 12


class MultiStatus(IntEnum):
    """How :func:`clf_cbf_multi` solved a point."""

    SOLVED = 0  #: the exact optimum of the whole problem
    #: no input meets every hard CLF together with the CBFs and limits: the CLF rows are
    #: dropped (safety first) and the result is the optimum of the rest
    CLF_DROPPED = 1
    #: the CBFs and the limits are inconsistent: the limits hold and the CBF rows carry
    #: slacks of weight ``FALLBACK_WEIGHT`` (in units of the normalised rows), so the squared
    #: violations are as small as the limits allow
    CBF_RELAXED = 2


#: Weight of the CBF slacks of the last-resort problem (rows normalised to unit length).
FALLBACK_WEIGHT = 1e8


@dataclasses.dataclass(frozen=True)
class MultiResult:
    """Output of :func:`clf_cbf_multi`.

    Attributes
    ----------
    u : array of shape (..., m)
    status : int array of shape (...,)
        A :class:`MultiStatus`.
    active : bool array of shape (..., p + k + 2m_lim)
        Which rows are active, in the order CLFs, CBFs, then ``u <= u_max``, ``u >= u_min``
        per limited input.
    multipliers : array of shape (..., p + k + 2m_lim)
        KKT multipliers of those rows (>= 0).
    slack : array of shape (..., p)
        The CLF slacks ``chi_j`` (zero without slack weights).
    """

    u: jax.Array
    status: jax.Array
    active: jax.Array
    multipliers: jax.Array
    slack: jax.Array


jax.tree_util.register_dataclass(
    MultiResult, data_fields=["u", "status", "active", "multipliers", "slack"], meta_fields=[]
)


def _whiten(H: Any, g: Any) -> Any:
    """``L^{-1} g`` for rows ``g`` (..., N, m), ``H = L L^T``."""
    L = jnp.linalg.cholesky(H)
    return jnp.swapaxes(
        jax.scipy.linalg.solve_triangular(L, jnp.swapaxes(g, -1, -2), lower=True), -1, -2
    )


def _unwhiten(H: Any, v: Any) -> Any:
    """``L^{-T} v`` for ``v`` (..., m)."""
    L = jnp.linalg.cholesky(H)
    return jax.scipy.linalg.solve_triangular(jnp.swapaxes(L, -1, -2), v[..., None], lower=False)[
        ..., 0
    ]


def multi_kernel(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, lo, hi, u_nom, H):
    """Unchecked kernel of :func:`clf_cbf_multi` (``lo``/``hi``/``u_nom``/``H`` may be None)."""
    p, k, m = b.shape[-2], d.shape[-2], b.shape[-1]
    # margins per row: A_j for the CLFs, B_i for the CBFs
    A = margins(a, b, a, b, kappa, 0.0, phi, 0.0).A
    B = margins(c, d, c, d, 0.0, rho, 0.0, varphi).B
    if u_nom is not None:
        A = A + jnp.einsum("...jm,...m->...j", b, u_nom)
        B = B - jnp.einsum("...im,...m->...i", d, u_nom)
    rows = [b, -d]
    rhs = [-A, -B]
    exclusive: list[tuple[int, int]] = []
    if lo is not None:
        eye = jnp.broadcast_to(jnp.eye(m), b.shape[:-2] + (m, m))
        base = jnp.zeros(b.shape[:-2] + (m,)) if u_nom is None else u_nom
        rows += [eye, -eye]
        rhs += [hi - base, -(lo - base)]
        exclusive = [(p + k + i, p + k + m + i) for i in range(m)]
    G = jnp.concatenate(rows, axis=-2)
    r = jnp.concatenate(rhs, axis=-1)
    if H is not None:
        G = _whiten(H, G)
    n_slack = p if inv_sqrt_slack is not None else 0
    if n_slack:
        s = jnp.broadcast_to(jnp.asarray(inv_sqrt_slack, dtype=float), b.shape[:-2] + (p,))
        slack_cols = jnp.zeros(G.shape[:-1] + (p,))
        slack_cols = slack_cols.at[..., jnp.arange(p), jnp.arange(p)].set(-s)
        G = jnp.concatenate([G, slack_cols], axis=-1)
    n_rows, dim = G.shape[-2], G.shape[-1]
    sets = active_sets(n_rows, dim, tuple(exclusive))
    full = solve_rows(G, r, sets)
    # safety first: without the CLF rows (only differs from the full problem for hard CLFs)
    no_clf = jnp.concatenate([jnp.zeros_like(G[..., :p, :]), G[..., p:, :]], axis=-2)
    no_clf_r = jnp.concatenate([jnp.zeros_like(r[..., :p]), r[..., p:]], axis=-1)
    safe = solve_rows(no_clf, no_clf_r, sets)
    # last resort: slacks on the CBF rows (normalised), limits kept
    norms = jnp.linalg.norm(G[..., p : p + k, :], axis=-1)
    w = jnp.where(norms > 0, norms, 1.0) / np.sqrt(FALLBACK_WEIGHT)
    relax_cols = jnp.zeros(G.shape[:-1] + (k,)).at[..., p + jnp.arange(k), jnp.arange(k)].set(-w)
    relaxed_G = jnp.concatenate([no_clf, relax_cols], axis=-1)
    relaxed = solve_rows(relaxed_G, no_clf_r, active_sets(n_rows, dim + k, tuple(exclusive)))
    status = jnp.where(
        full.found,
        MultiStatus.SOLVED,
        jnp.where(safe.found, MultiStatus.CLF_DROPPED, MultiStatus.CBF_RELAXED),
    ).astype(jnp.int32)
    z = jnp.where(
        full.found[..., None],
        full.z,
        jnp.where(safe.found[..., None], safe.z, relaxed.z[..., :dim]),
    )
    mult = jnp.where(
        full.found[..., None],
        full.multipliers,
        jnp.where(safe.found[..., None], safe.multipliers, relaxed.multipliers),
    )
    active = jnp.where(
        full.found[..., None],
        full.active,
        jnp.where(safe.found[..., None], safe.active, relaxed.active),
    )
    v = z[..., :m]
    u = v if H is None else _unwhiten(H, v)
    if u_nom is not None:
        u = u + u_nom
    slack = z[..., m:dim] * s if n_slack else jnp.zeros(b.shape[:-2] + (p,))
    return MultiResult(u=u, status=status, active=active, multipliers=mult, slack=slack)


def _single_pair(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, u_nom, H):
    """One CLF and one CBF without limits: the two-constraint kernel.

    The objective's change of variables is applied first (none for ``u_nom = None``,
    ``H = None``: then the result is the two-constraint formula bit for bit).
    """
    a1, b1, c1, d1 = a[..., 0], b[..., 0, :], c[..., 0], d[..., 0, :]
    mg = margins(a1, b1, c1, d1, kappa, rho, phi, varphi)
    A, B = mg.A, mg.B
    if u_nom is not None:
        A = A + jnp.sum(b1 * u_nom, -1)
        B = B - jnp.sum(d1 * u_nom, -1)
    nb, nd = mg.nb, mg.nd
    if H is not None:
        b1 = _whiten(H, b1[..., None, :])[..., 0, :]
        d1 = _whiten(H, d1[..., None, :])[..., 0, :]
        nb, nd = jnp.linalg.norm(b1, axis=-1), jnp.linalg.norm(d1, axis=-1)
    if inv_sqrt_slack is None:
        sol = solve_two(A, B, b1, d1, nb, nd, parallel_rtol=1e-12)
    else:
        sol = solve_two(A, B, b1, d1, nb, nd, inv_sqrt_slack=inv_sqrt_slack)
    u = sol.u if H is None else _unwhiten(H, sol.u)
    if u_nom is not None:
        u = u + u_nom
    dropped = jnp.where(nd > 0, MultiStatus.CLF_DROPPED, MultiStatus.CBF_RELAXED)
    status = jnp.where(sol.region == 0, dropped, MultiStatus.SOLVED).astype(jnp.int32)
    active = jnp.stack([sol.multipliers[..., 0] > 0, sol.multipliers[..., 1] > 0], axis=-1)
    return MultiResult(
        u=u, status=status, active=active, multipliers=sol.multipliers, slack=sol.slack[..., None]
    )


def _check_rows(name_s: str, s: Any, name_v: str, v: Any) -> tuple[tuple[int, ...], int, int]:
    check_real(name_s, s)
    check_real(name_v, v)
    vs, ss = np.shape(v), np.shape(s)
    if len(vs) < 2:
        raise DimensionError(f"{name_v} must have shape (..., rows, m), got shape {vs}")
    if ss != vs[:-1]:
        raise DimensionError(
            f"{name_s} must have shape {vs[:-1]} (the batch and rows of {name_v}), got shape {ss}"
        )
    check_finite(name_s, s)
    check_finite(name_v, v)
    return tuple(vs[:-2]), vs[-2], vs[-1]


def clf_cbf_multi(
    a: Any,
    b: Any,
    c: Any,
    d: Any,
    *,
    kappa: Any,
    rho: Any,
    phi: Any,
    varphi: Any,
    slack_weight: Any = None,
    u_min: Any = None,
    u_max: Any = None,
    u_nom: Any = None,
    H: Any = None,
) -> MultiResult:
    """Exact optimum with several CLFs and CBFs, input limits and a weighted objective.

    Solves the problem in the module docstring in closed form (active sets, no iterative
    solver).

    Parameters
    ----------
    a : array of shape (..., p)
        ``L_f V_j + lambda V_j`` of ``p >= 0`` CLFs.
    b : array of shape (..., p, m)
        ``L_g V_j``.
    c : array of shape (..., k)
        ``L_f h_i + beta h_i`` of ``k >= 0`` CBFs.
    d : array of shape (..., k, m)
        ``L_g h_i``.
    kappa, rho, phi, varphi : float
        As for :func:`clf_cbf` (shared by all rows), >= 0.
    slack_weight : float or array of shape (p,), optional
        Slack weights of the CLFs (Theorem 3's ``m``); hard CLFs when omitted.
    u_min, u_max : float or array of shape (m,), optional
        Input limits, both or neither, inside the problem (not a projection afterwards).
    u_nom : array of shape (..., m), optional
        Nominal input: the objective is ``1/2 |u - u_nom|_H^2`` (a safety filter).
    H : array of shape (m, m) or (..., m, m), optional
        Positive definite weight of the objective (identity when omitted).

    Returns
    -------
    MultiResult

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError, NumericalError
        As for :func:`clf_cbf`; also if there are more than :data:`MAX_ROWS` rows, ``H`` is not
        symmetric positive definite, or only one limit is given.

    Notes
    -----
    Where the rows are inconsistent the result is a documented fallback, never NaN: first the
    CLF rows are dropped (``status = CLF_DROPPED``: the CBFs and limits hold), and if the CBFs
    and limits are themselves inconsistent, the limits hold and the CBF violations are
    minimised with slacks of large weight (``status = CBF_RELAXED``). With one CLF, one CBF and
    no limits, ``u`` is bit for bit :func:`clf_cbf` (or :func:`clf_cbf_relaxed`) when
    ``u_nom`` and ``H`` are omitted; the two fallbacks then coincide with that formula's
    ``INCOMPATIBLE`` fallback.
    """
    batch_a, p, m = _check_rows("a", a, "b", b)
    batch_c, k, m2 = _check_rows("c", c, "d", d)
    if m != m2:
        raise DimensionError(f"b and d must have the same last axis m, got {m} and {m2}")
    if batch_a != batch_c:
        raise DimensionError(
            f"a, b and c, d must have the same batch shape, got {batch_a} and {batch_c}"
        )
    batch = batch_a
    check_params(batch, kappa=kappa, rho=rho, phi=phi, varphi=varphi)
    inv_sqrt = None
    if slack_weight is not None:
        check_params(slack_weight=slack_weight)
        sw = np.asarray(slack_weight, dtype=float)
        if sw.ndim not in (0, 1) or (sw.ndim == 1 and sw.shape != (p,)):
            raise DimensionError(
                f"slack_weight must be a scalar or have shape ({p},), got {sw.shape}"
            )
        inv_sqrt = 1.0 / np.sqrt(sw)
    if (u_min is None) != (u_max is None):
        raise ParameterError("give both u_min and u_max, or neither")
    lo = hi = None
    if u_min is not None:
        check_box(u_min, u_max, batch + (m,))
        lo = jnp.broadcast_to(jnp.asarray(u_min, float), batch + (m,))
        hi = jnp.broadcast_to(jnp.asarray(u_max, float), batch + (m,))
    n_rows = p + k + (2 * m if lo is not None else 0)
    if n_rows > MAX_ROWS:
        raise ParameterError(
            f"clf_cbf_multi handles at most {MAX_ROWS} rows (CLFs + CBFs + 2 per limited input), "
            f"got {n_rows}"
        )
    if u_nom is not None:
        check_real("u_nom", u_nom)
        check_finite("u_nom", u_nom)
        if tuple(np.shape(u_nom)) not in ((m,), batch + (m,)):
            raise DimensionError(
                f"u_nom must have shape ({m},) or {batch + (m,)}, got {np.shape(u_nom)}"
            )
        u_nom = jnp.broadcast_to(jnp.asarray(u_nom, float), batch + (m,))
    if H is not None:
        check_real("H", H)
        check_finite("H", H)
        Hn = np.asarray(H, dtype=float)
        if Hn.shape[-2:] != (m, m) or Hn.shape[:-2] not in ((), batch):
            raise DimensionError(
                f"H must have shape ({m}, {m}) or {batch + (m, m)}, got {Hn.shape}"
            )
        if not np.allclose(Hn, np.swapaxes(Hn, -1, -2), rtol=1e-12, atol=0.0):
            raise ParameterError("H must be symmetric")
        if np.any(np.linalg.eigvalsh(Hn) <= 0):
            raise ParameterError("H must be positive definite (all eigenvalues > 0)")
        H = jnp.broadcast_to(jnp.asarray(Hn), batch + (m, m))
    a, b, c, d = as_float(a, b, c, d)
    if p == 1 and k == 1 and lo is None:
        res = _single_jit(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt, u_nom, H)
    else:
        res = _multi_jit(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt, lo, hi, u_nom, H)
    check_output_finite("clf_cbf_multi", u=res.u, slack=res.slack, multipliers=res.multipliers)
    return res


_multi_jit = jax.jit(multi_kernel)


@jax.jit
def _single_jit(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, u_nom, H):
    return _single_pair(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, u_nom, H)
