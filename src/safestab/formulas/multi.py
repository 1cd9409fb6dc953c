"""Several CLFs and CBFs, input limits inside the problem, and weighted objectives.

The general problem behind the universal formula::

    min  1/2 (u - u_nom)^T H (u - u_nom) + 1/2 sum_j m_j chi_j^2
    s.t. a_j + b_j.u <= -kappa zeta_j + chi_j      (CLF j; chi_j = 0 without slack)
         c_i + d_i.u >= rho Gamma_i                (CBF i)
         u_min <= u <= u_max                       (limits)

is solved exactly by a dual active-set method (:mod:`safestab.formulas._dual_active_set`):
with ``H = L L^T`` and ``w = (L^T u, sqrt(m_j) chi_j)`` the objective is ``1/2 |w - w0|^2``;
the solver adds and drops one row at a time (rank-one factor updates, a fixed iteration
bound), recomputes the point from the final active set, and the answer is called ``SOLVED``
only where its KKT certificate holds at the problem's own scales. Infeasible rows fall back,
by name, to the optimum without the hard CLFs, then to a stated penalised problem (see
:class:`MultiStatus` and docs/theory.md). The cost grows polynomially with the rows; there is
no limit on their number. With one CLF, one CBF, no limits, ``u_nom = 0`` and ``H = I`` this
is the two-constraint formula itself (:func:`clf_cbf` / :func:`clf_cbf_relaxed`), bit for bit.
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._numerics import inv_sqrt, tied
from .._validation import check_finite, check_real, is_concrete
from ..errors import DimensionError, ParameterError
from ._checks import as_float, check_box, check_max_iter, check_output_finite, check_params
from ._dual_active_set import (
    INFEASIBLE,
    ITERATION_LIMIT,
    UNIT_DOUBLE,
    default_max_iter,
    placeholder,
    solve_dual,
)
from ._kernels import margins, satisfied_rtol, scaled_norm, solve_two

__all__ = ["MultiStatus", "MultiResult", "clf_cbf_multi"]


class MultiStatus(IntEnum):
    """How :func:`clf_cbf_multi` solved a point."""

    SOLVED = 0  #: the exact optimum of the whole problem
    #: no input meets every hard CLF together with the CBFs and limits: the CLF rows are
    #: dropped (safety first) and the result is the optimum of the rest
    CLF_DROPPED = 1
    #: the CBFs and the limits are inconsistent: the limits hold, the CLF rows are dropped and
    #: ``u`` is the exact optimum of ``min 1/2 |u - u_nom|_H^2 + W/2 sum_i sigma_i^2 /
    #: |d_i|^2_{H^-1}`` s.t. ``d_i.u >= B_i - sigma_i`` and the limits (``W =
    #: FALLBACK_WEIGHT``)
    CBF_RELAXED = 2
    #: the solver's iteration bound was reached before an answer: ``u`` is its last iterate
    #: (inside the limits), nothing is certified
    ITERATION_LIMIT = 3
    #: the solver stopped, but the KKT certificate of its answer does not hold at the
    #: problem's own scales (rounding beyond the tolerance on a badly conditioned active set):
    #: ``u`` is inside the limits, nothing else is promised
    UNCERTIFIED = 4


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


def _own_scale_ok(res: Any, scale: Any, unit: float = UNIT_DOUBLE) -> Any:
    """A condition ``res <= 0`` holds up to the rounding of its own terms (unit ``unit``)."""
    return res <= satisfied_rtol(unit) * scale


class _Problem(NamedTuple):
    """One problem in the solver's coordinates ``w = (L^T u, sqrt(m_j) chi_j)``."""

    Gw: Any  # (N, D): rows CLFs, CBFs, upper limits, lower limits
    r: Any  # (N,)
    w0: Any  # (D,)
    L: Any  # (m, m) Cholesky factor of H, or None
    A: Any  # (p,) CLF margins
    B: Any  # (k,) CBF margins
    clf_scale: Any  # (p,) |a| + kappa zeta
    cbf_scale: Any  # (k,) |c| + rho Gamma


def _setup(
    a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, lo, hi, u_nom, H, margin=None
) -> _Problem:
    p, m = b.shape
    mg_v = margins(a, b, a, b, kappa, 0.0, phi, 0.0)
    mg_c = margins(c, d, c, d, 0.0, rho, 0.0, varphi)
    if margin is not None:  # c + d.u >= rho Gamma + margin
        mg_c = mg_c._replace(B=mg_c.B + margin)
    eye = jnp.eye(m)
    G = jnp.concatenate([b, -d] + ([eye, -eye] if lo is not None else []), axis=0)
    r = jnp.concatenate([-mg_v.A, -mg_c.B] + ([hi, -lo] if lo is not None else []), axis=0)
    L = None
    if H is None:
        Gw, w0 = G, (jnp.zeros(m) if u_nom is None else u_nom)
    else:
        L = jnp.linalg.cholesky(H)
        Gw = jax.scipy.linalg.solve_triangular(L, G.T, lower=True).T  # G L^{-T}
        w0 = jnp.zeros(m) if u_nom is None else L.T @ u_nom
    if inv_sqrt_slack is not None:
        cols = jnp.zeros((G.shape[0], p)).at[jnp.arange(p), jnp.arange(p)].set(-inv_sqrt_slack)
        Gw = jnp.concatenate([Gw, cols], axis=1)
        w0 = jnp.concatenate([w0, jnp.zeros(p)])
    return _Problem(
        Gw, r, w0, L, mg_v.A, mg_c.B,
        jnp.abs(a) + kappa * mg_v.zeta, jnp.abs(c) + rho * mg_c.Gamma,
    )  # fmt: skip


def _input(pr: _Problem, w: Any, m: int, lo: Any, hi: Any) -> Any:
    """``u = L^{-T} w_u``, inside the limits (rounding only: certified points are inside)."""
    v = w[:m]
    u = v if pr.L is None else jax.scipy.linalg.solve_triangular(pr.L.T, v, lower=False)
    return u if lo is None else jnp.clip(u, lo, hi)


def _conditions_hold(pr: _Problem, b, d, u, chi, with_clf: bool, unit: float) -> Any:
    """Every CBF (and CLF) condition at ``u`` within the rounding of its own terms."""
    bu, du = b * u, d * u
    cbf_res, cbf_scale = pr.B - jnp.sum(du, -1), pr.cbf_scale + jnp.sum(jnp.abs(du), -1)
    ok = jnp.all(_own_scale_ok(cbf_res, cbf_scale, unit))
    if with_clf:
        clf_res = pr.A + jnp.sum(bu, -1) - chi
        clf_scale = pr.clf_scale + jnp.sum(jnp.abs(bu), -1) + jnp.abs(chi)
        ok = ok & jnp.all(_own_scale_ok(clf_res, clf_scale, unit))
    return ok


def _phase_full(pr: _Problem, b, d, inv_sqrt_slack, lo, hi, max_iter, unit, batched=True):
    """Phase 1: the whole problem. Returns (solution, u, chi, certified)."""
    use = jnp.ones(pr.r.shape[0], bool)
    sol = solve_dual(pr.Gw, pr.r, pr.w0, use, max_iter, batched, unit)
    return (sol, *_full_outputs(pr, b, d, sol, inv_sqrt_slack, lo, hi, unit))


def _full_outputs(pr: _Problem, b, d, sol, inv_sqrt_slack, lo, hi, unit):
    """Phase 1's ``(u, chi, certified)`` from its solution."""
    p, m = b.shape
    u = _input(pr, sol.w, m, lo, hi)
    chi = sol.w[m:] * inv_sqrt_slack if inv_sqrt_slack is not None else jnp.zeros(p)
    return u, chi, sol.certified & _conditions_hold(pr, b, d, u, chi, True, unit)


def _phase_relaxed(pr: _Problem, b, d, lo, hi, run, max_iter, unit, batched=True):
    """Phase 3: limits kept, CBF rows relaxed by slacks, CLF rows dropped.

    The slack of CBF ``i`` enters its normalised whitened row with weight
    :data:`FALLBACK_WEIGHT`: in the original variables, the exact optimum of
    ``min 1/2 |u - u_nom|_H^2 + W/2 sum_i sigma_i^2 / |d_i|^2_{H^-1}`` s.t.
    ``d_i.u >= B_i - sigma_i`` and the limits.
    """
    p, m = b.shape
    k = d.shape[0]
    n_rows = pr.r.shape[0]
    Gu = pr.Gw[:, :m]
    nrm = scaled_norm(Gu[p : p + k])
    slack = -jnp.where(nrm > 0, nrm, 1.0) / np.sqrt(FALLBACK_WEIGHT)  # row p + i's column
    w03 = jnp.concatenate([pr.w0[:m], jnp.zeros(k)])
    use = jnp.arange(n_rows) >= p
    sol = solve_dual(
        Gu, pr.r, w03, use, jnp.where(run, max_iter, 0), batched, unit, slack=slack, slack_row=p
    )
    return sol, _input(pr, sol.w, m, lo, hi), sol.certified


def _phases_full_and_no_clf(pr, b, d, lo, hi, max_iter, unit):
    """Phases 1 and 2 (hard CLFs) with one instance of the solver, in a loop of one or two.

    Both phases solve problems of the same shapes (phase 2 leaves the CLF rows out by
    ``use``): one instance of the solver in a loop compiles once instead of twice (the
    solver is most of a filter's program and of its compilation time). The second pass runs
    only if some problem of the batch needs it, and only for those (the others' solver stops
    at once); each pass computes exactly what the phase computed on its own.
    Returns ``(full, u1, chi1, ok1, safe, u2, ok2)`` over the flattened batch.
    """
    flat, (p, m) = b.shape[0], b.shape[-2:]
    n_rows = pr.r.shape[-1]
    batched = flat != 1
    rows = jnp.arange(n_rows)

    def solve(pr, use, run):
        return solve_dual(pr.Gw, pr.r, pr.w0, use, jnp.where(run, max_iter, 0), batched, unit)

    solve_all = _map(solve, flat)

    def solve_pass(phase, carry):
        first, second = carry
        use = jnp.broadcast_to((rows >= p) | (phase == 0), (flat, n_rows))
        run = (phase == 0) | (first.status == INFEASIBLE)
        sol = solve_all(pr, use, run)
        tree_where = lambda keep, old: jax.tree_util.tree_map(  # noqa: E731
            lambda x, y: jnp.where(keep, y, x), old, sol
        )
        return tree_where(phase == 0, first), tree_where(phase == 1, second)

    def body(phase, carry):
        # the second pass only if some problem needs it (a batch-level cond, as before)
        needed = (phase == 0) | jnp.any(carry[0].status == INFEASIBLE)
        return jax.lax.cond(needed, solve_pass, lambda _, carry: carry, phase, carry)

    # placeholders of the answers' shapes (never read: pass 1 replaces the first, and the
    # second is replaced by the first where pass 2 did not run), made to depend on the data:
    # inside a user's vmap they are then batched like the answers, and the loop's batching
    # rule passes over the solver once instead of twice
    tie = sum(jnp.sum(leaf[:1]) for leaf in jax.tree_util.tree_leaves(pr))
    zeros = tied(placeholder((flat,), n_rows, pr.w0.shape[-1], pr.w0.dtype), tie)
    # a loop of a fixed count: reverse-mode differentiable (a while loop is not)
    full, safe = jax.lax.fori_loop(0, 2, body, (zeros, zeros))
    ran2 = jnp.any(full.status == INFEASIBLE)

    def finish(pr, b, d, lo, hi, full, safe):
        u1, chi1, ok1 = _full_outputs(pr, b, d, full, None, lo, hi, unit)
        u2 = _input(pr, safe.w, m, lo, hi)
        ok2 = safe.certified & _conditions_hold(pr, b, d, u2, jnp.zeros(p), False, unit)
        return u1, chi1, ok1, u2, ok2

    u1, chi1, ok1, u2, ok2 = _map(finish, flat)(pr, b, d, lo, hi, full, safe)
    # as the separate phases: without a second pass, its results are phase 1's
    safe = jax.tree_util.tree_map(lambda x, y: jnp.where(ran2, x, y), safe, full)
    u2 = jnp.where(ran2, u2, u1)
    ok2 = jnp.where(ran2, ok2, False)
    return full, u1, chi1, ok1, safe, u2, ok2


#: Problems of a batch solved together by the last-resort phase, at most. Its coordinates
#: include a slack per CBF, so its rows and factors take ``(rows + m + k)(m + k)`` numbers per
#: problem: the problems that need it are gathered into chunks of at most this many, and of
#: at most ``RELAXED_CHUNK_NUMBERS`` such numbers together, which bounds its memory whatever
#: the batch.
RELAXED_CHUNK = 256
RELAXED_CHUNK_NUMBERS = 2**22


def _map(fn, flat: int):
    """``jax.vmap(fn)`` over ``flat`` problems; for one problem, ``fn`` itself.

    One problem is the common case of a control step: without ``vmap``, the solver's
    ``lax.cond`` steps (add a row or drop one) stay branches and only one of them runs
    (under ``vmap`` both run and one is selected), and the C export writes them as ``if``.
    """
    if flat != 1:
        return jax.vmap(fn)
    tree_map = jax.tree_util.tree_map

    def one(*args):
        out = fn(*tree_map(lambda v: v[0], args))
        return tree_map(lambda v: v[None], out)

    return one


def _relaxed_in_chunks(pr, b, d, lo, hi, need, max_iter, out, unit):
    """Phase 3 for the problems with ``need``, in chunks; ``out`` holds the other answers."""
    flat, (k, m) = need.shape[0], d.shape[-2:]
    if flat == 1:  # one problem: no gathering (and no index that depends on the data)
        sol, u, ok = _map(
            lambda pr, b, d, lo, hi, run: _phase_relaxed(
                pr, b, d, lo, hi, run, max_iter, unit, False
            ),
            1,
        )(pr, b, d, lo, hi, need)
        return sol._replace(w=sol.w[:, :m]), u, ok
    per_problem = (pr.r.shape[-1] + m + k) * (m + k)
    size = max(1, min(flat, RELAXED_CHUNK, RELAXED_CHUNK_NUMBERS // per_problem))
    order = jnp.argsort(~need, stable=True)  # the problems that need it first
    count = jnp.sum(need)
    take = lambda tree, lanes: jax.tree_util.tree_map(  # noqa: E731
        lambda x: None if x is None else x[lanes], tree, is_leaf=lambda x: x is None
    )

    def chunk(i, acc):
        start = jnp.minimum(i * size, flat - size)
        lanes = jax.lax.dynamic_slice(order, (start,), (size,))
        run = start + jnp.arange(size) < count
        sol, u, ok = jax.vmap(
            lambda pr, b, d, lo, hi, run: _phase_relaxed(pr, b, d, lo, hi, run, max_iter, unit)
        )(take(pr, lanes), b[lanes], d[lanes], take(lo, lanes), take(hi, lanes), run)
        new = (sol._replace(w=sol.w[:, :m]), u, ok)

        def put(old, val):
            keep = run.reshape(run.shape + (1,) * (val.ndim - 1))
            return old.at[lanes].set(jnp.where(keep, val, old[lanes]))

        return jax.tree_util.tree_map(put, acc, new)

    # a loop of a fixed count (reverse-mode differentiable), each chunk run only if needed
    n_chunks = (count + size - 1) // size
    return jax.lax.fori_loop(
        0,
        -(-flat // size),
        lambda i, acc: jax.lax.cond(i < n_chunks, chunk, lambda _, acc: acc, i, acc),
        out,
    )


#: The iteration count is an int32: a larger bound is the same bound as this one.
_INT32_MAX = int(np.iinfo(np.int32).max)


def _default_bound(p: int, m: int, k: int, limits: bool, soft: bool) -> int:
    """The default iteration bound of ``p`` CLF, ``k`` CBF rows over ``m`` inputs."""
    n_rows = p + k + (2 * m if limits else 0)
    dim = m + (p if soft else 0)
    return default_max_iter(n_rows, dim + k)


def multi_kernel(
    a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, lo, hi, u_nom, H, max_iter=None,
    unit=UNIT_DOUBLE, cbf_margin=None,
):  # fmt: skip
    """Unchecked kernel of :func:`clf_cbf_multi` (``lo``/``hi``/``u_nom``/``H`` may be None).

    ``unit`` (static): the unit roundoff the step runs in, which scales the solver's
    tolerances and the certificate's (:func:`~safestab.formulas._dual_active_set.tolerances`).
    ``cbf_margin``: every CBF condition tightened to ``c + d.u >= rho Gamma + cbf_margin``.

    Batched over the leading axes of ``b``; the parameters broadcast against that batch. The
    fallback phases run only where some problem of the batch needs them (a batch-level
    ``lax.cond``: inside a user's ``vmap`` both branches run, with the same results).
    """
    batch, (p, m), k = b.shape[:-2], b.shape[-2:], d.shape[-2]
    if max_iter is None:
        max_iter = _default_bound(p, m, k, lo is not None, inv_sqrt_slack is not None)
    flat = int(np.prod(batch, dtype=int))

    def bc(v, tail):
        if v is None:
            return None
        return jnp.broadcast_to(jnp.asarray(v, float), batch + tail).reshape((flat,) + tail)

    a, b, c, d = bc(a, (p,)), bc(b, (p, m)), bc(c, (k,)), bc(d, (k, m))
    params = [bc(v, ()) for v in (kappa, rho, phi, varphi)]
    sw, lo, hi = bc(inv_sqrt_slack, (p,)), bc(lo, (m,)), bc(hi, (m,))
    pr = _map(_setup, flat)(
        a, b, c, d, *params, sw, lo, hi, bc(u_nom, (m,)), bc(H, (m, m)), bc(cbf_margin, ())
    )
    # phase 2 drops hard CLFs: known before any data (no CLF, or soft ones, leave none to drop)
    hard_clfs = p > 0 and inv_sqrt_slack is None
    if hard_clfs:
        full, u1, chi1, ok1, safe, u2, ok2 = _phases_full_and_no_clf(
            pr, b, d, lo, hi, max_iter, unit
        )
        infeasible = full.status == INFEASIBLE
        need2 = infeasible
    else:
        full, u1, chi1, ok1 = _map(
            lambda pr, b, d, sw, lo, hi: _phase_full(
                pr, b, d, sw, lo, hi, max_iter, unit, flat != 1
            ),
            flat,
        )(pr, b, d, sw, lo, hi)
        infeasible = full.status == INFEASIBLE
        # phase 2 can never run: it is not traced nor compiled (it was a third of a soft-CLF
        # filter's program, and of its compilation time)
        need2 = jnp.zeros(flat, bool)
        safe, u2, ok2 = full, u1, jnp.zeros(flat, bool)
    need3 = infeasible & ~(need2 & (safe.status != INFEASIBLE))

    skipped3 = (full._replace(w=full.w[:, :m]), u1, jnp.zeros(flat, bool))
    relaxed, u3, ok3 = jax.lax.cond(
        jnp.any(need3),
        lambda _: _relaxed_in_chunks(pr, b, d, lo, hi, need3, max_iter, skipped3, unit),
        lambda _: skipped3,
        None,
    )

    S = MultiStatus
    col = lambda v: v[:, None]  # noqa: E731
    pick = lambda x1, x2, x3: jnp.where(  # noqa: E731
        col(need3) if x1.ndim > 1 else need3,
        x3,
        jnp.where(col(need2) if x1.ndim > 1 else need2, x2, x1),
    )
    u = pick(u1, u2, u3)
    certified = pick(ok1, ok2, ok3)
    limit_hit = pick(
        full.status == ITERATION_LIMIT, safe.status == ITERATION_LIMIT,
        relaxed.status == ITERATION_LIMIT,
    )  # fmt: skip
    base = pick(
        jnp.full(flat, S.SOLVED), jnp.full(flat, S.CLF_DROPPED), jnp.full(flat, S.CBF_RELAXED)
    )
    status = jnp.where(limit_hit, S.ITERATION_LIMIT, jnp.where(certified, base, S.UNCERTIFIED))
    mult = pick(full.multipliers, safe.multipliers, relaxed.multipliers)
    active = pick(full.active, safe.active, relaxed.active)
    slack = (
        jnp.where(col(need2 | need3), 0.0, chi1)
        if inv_sqrt_slack is not None
        else jnp.zeros((flat, p))
    )
    shape = lambda v: v.reshape(batch + v.shape[1:])  # noqa: E731
    return MultiResult(
        u=shape(u), status=shape(status.astype(jnp.int32)), active=shape(active),
        multipliers=shape(mult), slack=shape(slack),
    )  # fmt: skip


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
    max_iter: int | None = None,
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
    max_iter : int, optional
        Iteration bound of the active-set solver per phase (default ``3 (rows + dim) + 10``,
        ``dim`` the inputs, CLF slacks and, for the last-resort phase, CBF slacks); where it
        is reached the status is ``ITERATION_LIMIT``. Unused where the closed form applies
        (one CLF, one CBF, no limits). An argument of the compiled solver: another bound
        does not compile it again.

    Returns
    -------
    MultiResult

    Raises
    ------
    InputTypeError, DimensionError, NonFiniteError, ParameterError, NumericalError
        As for :func:`clf_cbf`; also if ``H`` is not symmetric positive definite, only one
        limit is given, or ``max_iter`` is not a positive integer.

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
    inv_s = None  # 1 / sqrt(slack_weight)
    if slack_weight is not None:
        check_params(slack_weight=slack_weight)
        sw_shape = tuple(np.shape(slack_weight))
        if len(sw_shape) not in (0, 1) or (len(sw_shape) == 1 and sw_shape != (p,)):
            raise DimensionError(
                f"slack_weight must be a scalar or have shape ({p},), got {sw_shape}"
            )
        inv_s = inv_sqrt(slack_weight) if p > 0 else None  # no CLF row carries a slack
    if (u_min is None) != (u_max is None):  # one-sided: the other side unbounded
        u_min = -np.inf if u_min is None else u_min
        u_max = np.inf if u_max is None else u_max
    lo = hi = None
    if u_min is not None:
        check_box(u_min, u_max, batch + (m,))
        lo = jnp.broadcast_to(jnp.asarray(u_min, float), batch + (m,))
        hi = jnp.broadcast_to(jnp.asarray(u_max, float), batch + (m,))
    max_iter = check_max_iter(max_iter)
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
        h_shape = tuple(np.shape(H))
        if h_shape[-2:] != (m, m) or h_shape[:-2] not in ((), batch):
            raise DimensionError(f"H must have shape ({m}, {m}) or {batch + (m, m)}, got {h_shape}")
        if is_concrete(H):  # traced, its values are unknown: a non-PD H gives NaN (see docs)
            Hn = np.asarray(H, dtype=float)
            if not np.allclose(Hn, np.swapaxes(Hn, -1, -2), rtol=1e-12, atol=0.0):
                raise ParameterError("H must be symmetric")
            if np.any(np.linalg.eigvalsh(Hn) <= 0):
                raise ParameterError("H must be positive definite (all eigenvalues > 0)")
        H = jnp.broadcast_to(jnp.asarray(H, float), batch + (m, m))
    a, b, c, d = as_float(a, b, c, d)
    if max_iter is None:
        max_iter = _default_bound(p, m, k, lo is not None, inv_s is not None)
    if p == 1 and k == 1 and lo is None:
        res = _single_jit(a, b, c, d, kappa, rho, phi, varphi, inv_s, u_nom, H)
    else:
        res = _multi_jit(
            a, b, c, d, kappa, rho, phi, varphi, inv_s, lo, hi, u_nom, H,
            max_iter=jnp.int32(min(max_iter, _INT32_MAX)),
        )  # fmt: skip
    check_output_finite("clf_cbf_multi", u=res.u, slack=res.slack, multipliers=res.multipliers)
    return res


# the bound is an argument, not a static value: it is only compared with the iteration count,
# so every bound runs one program (a static bound compiled the whole solver once per value)
_multi_jit = jax.jit(multi_kernel)


@jax.jit
def _single_jit(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, u_nom, H):
    return _single_pair(a, b, c, d, kappa, rho, phi, varphi, inv_sqrt_slack, u_nom, H)
