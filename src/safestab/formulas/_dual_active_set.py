"""Unchecked kernel: a dual active-set solver for ``min 1/2 |w - w0|^2`` s.t. ``G w <= r``.

The method of Goldfarb and Idnani (1983) for an identity Hessian (the callers whiten the
objective first): start at the unconstrained minimiser ``w0``; repeatedly take the most violated
row (rows normalised to unit length, so violations are distances) and move along the direction
that keeps the active rows tight, dropping an active row when its multiplier reaches zero,
until no row is violated (optimal) or a violated row is a non-negative combination of the
active ones with no multiplier left to drop (infeasible: ``y = (-R^{-1} Q_1^T n_p, 1) >= 0``
is a Farkas certificate). The dual objective increases at every step, so no active set
repeats in exact arithmetic; the loop still has a fixed bound and reports reaching it.

The active rows are kept as ``Q R = N_A`` (``Q`` orthogonal ``D x D``, ``R`` upper
triangular, ``N_A`` the active rows as columns): a row is added by one Householder reflection
on the trailing columns of ``Q`` (``O(D^2)``), dropped by Givens rotations restoring ``R``
(``O(D)`` each). One iteration costs ``O(N D + D^2)``; an active set changes by one row per
iteration, so the work grows polynomially with the rows, not with the number of their subsets.

At the end the point is recomputed from the final active set alone (its orthogonal projection,
then one step of iterative refinement of the active rows), so its accuracy is that of one
backward-stable least-squares solve and does not depend on the path; the multipliers follow
from the same factors. Whether the point is the optimum is then *certified* by the caller
against the problem's own scales (:func:`safestab.formulas.multi`), never assumed.

Only jittable, vmappable operations: ``lax.while_loop``, loops and slices by loop counters,
indices that differ between problems select by masks; beyond a few rows, LAPACK's triangular
solve and QR (one call instead of a loop of small steps).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import ShapedArray
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jax.scipy.linalg import solve_triangular

from .._numerics import tied
from ._kernels import scaled_norm

__all__ = [
    "DualSolution", "solve_dual", "placeholder", "OPTIMAL", "INFEASIBLE", "ITERATION_LIMIT",
    "ADD_RTOL", "UNIT_DOUBLE", "UNIT_FLOAT", "Tolerances", "tolerances", "dual_qp_p",
]  # fmt: skip

OPTIMAL, INFEASIBLE, ITERATION_LIMIT = 0, 1, 2

_EPS = float(np.finfo(float).eps)
#: Unit roundoff of float64, the default precision of the solver's tolerances.
UNIT_DOUBLE = _EPS / 2
#: Unit roundoff of float32: the tolerances of a step exported in float.
UNIT_FLOAT = float(np.finfo(np.float32).eps) / 2
#: A row is taken into the active set only if it is violated by more than this fraction of its
#: own magnitudes ``|r_i| + sum_j |G_ij w_j|`` (rounding of evaluating it is about ``D eps``
#: of that): a row violated only by rounding (a duplicate of an active row, say) is left out.
ADD_RTOL = 64 * _EPS
#: A violated row whose component orthogonal to the active rows is shorter than this (it has
#: unit length) is treated as a combination of them: ``Q^T n`` has an error of a few ``eps``.
DEP_TOL = 1e3 * _EPS
#: Primal tolerance of the certificate, relative to each row's own magnitudes (the same as the
#: controllers' condition flags, :data:`safestab.formulas.SATISFIED_RTOL`).
CERT_RTOL = 1e-13


class Tolerances(NamedTuple):
    """The solver's tolerances for the precision its step is evaluated in (unit ``u``).

    The constants above are float64's (``u = 2^-53``); each is a multiple of ``eps = 2 u``
    (``CERT_RTOL`` about ``450 eps``), and a step exported in float (``u = 2^-24``) takes the
    same multiples of float's ``eps``: its rounding is ``2^29`` times larger, and tolerances
    fixed at float64's would call every float answer uncertified.
    """

    add: float  #: :data:`ADD_RTOL`
    dep: float  #: :data:`DEP_TOL`
    cert: float  #: :data:`CERT_RTOL`
    eps: float  #: ``2 u``, of the dual and stationarity checks


def tolerances(unit: float = UNIT_DOUBLE) -> Tolerances:
    """:class:`Tolerances` for unit roundoff ``unit`` (a Python float: a static setting).

    The dependency test is the exception to "the same multiple": at most ``64 eps`` where
    that is below :data:`DEP_TOL`'s ``1000 eps``. In float, ``1000 eps`` is ``1.2e-4``: the
    last-resort phase's rows (a CBF row with its slack column, weight
    ``1 / sqrt(FALLBACK_WEIGHT)``) lie that close to the span of the active ones at a
    condition number of ``1e4``, and were called dependent (the phase then said
    infeasible); ``Q^T n`` errs by a few ``eps``, which ``64 eps`` still covers.
    """
    scale = float(unit) / UNIT_DOUBLE
    eps = 2.0 * float(unit)
    return Tolerances(ADD_RTOL * scale, min(DEP_TOL * scale, max(DEP_TOL, 64 * eps)),
                      CERT_RTOL * scale, eps)  # fmt: skip


class DualSolution(NamedTuple):
    """What :func:`solve_dual` returns.

    The point ``w`` (D,), multipliers (N,) of the rows as given, the active mask (N,), the
    status (``OPTIMAL``, ``INFEASIBLE``, ``ITERATION_LIMIT``), the iteration count, an estimate
    of the condition number of the final active rows (max/min of ``|diag R|``), and whether the
    KKT certificate of this (whitened, normalised) problem holds: every used row within
    ``CERT_RTOL`` of its own magnitudes and every active row tight to the same tolerance,
    multipliers ``>= -64 eps cond`` times the largest, and stationarity to ``64 eps (iterations
    + D)`` of its terms.
    """

    w: Any
    multipliers: Any
    active: Any
    status: Any
    iterations: Any
    cond: Any
    certified: Any


def placeholder(lead: tuple[int, ...], n_rows: int, dim: int, dtype: Any) -> DualSolution:
    """Zeros of the shapes and dtypes of :func:`solve_dual`'s answer, with leading axes ``lead``.

    Written out instead of ``jax.eval_shape`` of the solver, which would trace it once more.
    """
    z = lambda tail, dt=dtype: jnp.zeros(lead + tail, dt)  # noqa: E731
    i32 = jnp.int32
    return DualSolution(
        z((dim,)), z((n_rows,)), z((n_rows,), bool), z((), i32), z((), i32), z(()), z((), bool)
    )


def default_max_iter(n_rows: int, dim: int) -> int:
    """The iteration bound: every row added and dropped three times, plus slack."""
    return 3 * (n_rows + dim) + 10


def _upper_solve(R, v):
    """``R^{-1} v`` for upper triangular ``R`` (D, D), by back substitution.

    Up to :data:`UNROLL` rows, an unrolled loop: under vmap each step is one dense operation
    over the batch (a batched LAPACK call costs a call per problem). Beyond, LAPACK's
    triangular solve (a rolled loop of ``D`` steps costs ``D`` times the loop overhead).
    """
    dim = v.shape[0]
    if dim > UNROLL:
        return solve_triangular(R, v, lower=False)

    def step(t, x):
        i = dim - 1 - t
        return x.at[i].set((v[i] - R[i] @ x) / R[i, i])

    return _loop(dim, step, jnp.zeros_like(v))


def _upper_t_solve(R, v):
    """``R^{-T} v`` for upper triangular ``R`` (D, D), by forward substitution."""
    dim = v.shape[0]
    if dim > UNROLL:
        return solve_triangular(R, v, lower=False, trans=1)

    def step(i, x):
        return x.at[i].set((v[i] - R[:, i] @ x) / R[i, i])

    return _loop(dim, step, jnp.zeros_like(v))


#: Loops of at most this many steps are unrolled (each step then fuses with its neighbours;
#: a rolled loop of a few steps costs more in loop overhead than in arithmetic).
UNROLL = 8


def _loop(n: int, step, init):
    if n <= UNROLL:
        for i in range(n):
            init = step(i, init)
        return init
    return jax.lax.fori_loop(0, n, step, init)


def solve_dual(
    G: Any,
    r: Any,
    w0: Any,
    use: Any,
    max_iter: Any,
    batched: bool = True,
    unit: float = UNIT_DOUBLE,
    slack: Any = None,
    slack_row: int = 0,
) -> DualSolution:
    """Minimise ``1/2 |w - w0|^2`` subject to ``G_i w <= r_i`` for the rows with ``use_i``.

    One problem (no batch axes; vmap for batches): ``G`` (N, D), ``r`` (N,), ``w0`` (D,),
    ``use`` bool (N,). Rows that are exactly zero are dropped when ``r_i >= 0`` and make the
    problem infeasible otherwise. ``batched`` (static): whether the caller maps this function
    over a batch. Then a row is picked by a mask (a dense operation over the batch); otherwise
    by its index (``O(D)`` instead of ``O(N D)``; under vmap an index becomes a gather).
    ``unit`` (static): the unit roundoff of the precision the step runs in
    (:func:`tolerances`; :data:`UNIT_FLOAT` for a step exported in float).

    ``slack`` (k,), optional: rows ``slack_row + j`` (``slack_row`` static) each get a
    coordinate of their own, appended after ``G``'s, with entry ``slack[j]`` (the last-resort
    phase's slacks): the problem is solved in ``D + k`` coordinates, ``w0`` (D + k,) and the
    answer's point likewise, without the caller building those columns (the solver builds
    them where it runs). ``max_iter <= 0`` means not run: the answer is ``w0`` with status
    ``ITERATION_LIMIT``, no iteration and no active row.
    """
    G = jnp.asarray(G)
    slack = jnp.zeros(0, G.dtype) if slack is None else jnp.asarray(slack, G.dtype)
    G_full = _with_slack_columns(G, slack, slack_row)
    n_rows = G.shape[0]
    if n_rows == 0:  # nothing to satisfy: the unconstrained minimiser
        return DualSolution(
            jnp.asarray(w0, G.dtype), jnp.zeros(0, G.dtype), jnp.zeros(0, bool),
            jnp.int32(OPTIMAL), jnp.int32(0), jnp.asarray(1.0, G.dtype), jnp.asarray(True),
        )  # fmt: skip
    w0 = jnp.asarray(w0, G.dtype)
    # the loop is not differentiated: it runs on the values, and the derivative of its optimum
    # is attached afterwards (:func:`_on_active_set`). The loop is traced once, differentiated
    # or not (a custom derivative of the whole solver traced it twice under differentiation:
    # once as the function, once inside its derivative rule)
    stop = jax.lax.stop_gradient
    sol = DualSolution(
        *dual_qp_p.bind(
            stop(G), stop(r), stop(w0), jnp.asarray(use, bool), jnp.asarray(max_iter, jnp.int32),
            stop(slack), batched=bool(batched), tols=tolerances(unit), slack_row=int(slack_row),
        )
    )  # fmt: skip
    # (the full rows only feed the derivative: without one, XLA and the export drop them)
    w, mult = _on_active_set(G_full, r, w0, sol.w, sol.multipliers, sol.active, sol.status)
    return sol._replace(w=w, multipliers=mult)


def _with_slack_columns(G: Any, slack: Any, slack_row: int) -> Any:
    """``G`` with a column per slack: entry ``slack[j]`` in row ``slack_row + j``."""
    n_rows, k = G.shape[0], slack.shape[0]
    if k == 0:
        return G
    cols = jnp.zeros((n_rows, k), G.dtype).at[slack_row + jnp.arange(k), jnp.arange(k)].set(slack)
    return jnp.concatenate([G, cols], axis=1)


#: The solver's loop as one primitive: ``(G, r, w0, use, max_iter, slack) -> DualSolution``'s
#: fields, each with the leading (batch) axes of ``G``; static ``batched``, ``tols`` and
#: ``slack_row`` (:func:`solve_dual`). Two implementations of the same steps: the JAX one
#: (:func:`_solve_dual`, mapped over the leading axes), which XLA runs on other backends and
#: where no compiler works, and the solver written in C (:mod:`safestab.export._dual_qp`, work
#: arrays sized by the problem), which the C export writes as one call and the CPU runs as
#: one custom call (:func:`_dual_qp_cpu_lowering`).
dual_qp_p = Primitive("safestab_dual_qp")
dual_qp_p.multiple_results = True


def _dual_qp_impl(G, r, w0, use, max_iter, slack, *, batched, tols, slack_row):
    def one(G, r, w0, use, max_iter, slack):
        sol = _solve_dual(
            _with_slack_columns(G, slack, slack_row), r, w0, use, max_iter, batched, tols
        )
        # not run (max_iter <= 0): w0, as the C solver answers without touching the rows
        run = max_iter > 0
        return (
            jnp.where(run, sol.w, w0), jnp.where(run, sol.multipliers, 0.0),
            sol.active & run, jnp.where(run, sol.status, ITERATION_LIMIT).astype(jnp.int32),
            jnp.where(run, sol.iterations, 0).astype(jnp.int32), jnp.where(run, sol.cond, 1.0),
            sol.certified & run,
        )  # fmt: skip

    fn = one
    for _ in range(G.ndim - 2):
        fn = jax.vmap(fn)
    return list(fn(G, r, w0, use, max_iter, slack))


def _dual_qp_abstract(G, r, w0, use, max_iter, slack, *, batched, tols, slack_row):
    *lead, n_rows, _ = G.shape
    lead = tuple(lead)
    dim = w0.shape[-1]
    f, i32 = G.dtype, np.dtype(np.int32)
    return [
        ShapedArray(lead + (dim,), f), ShapedArray(lead + (n_rows,), f),
        ShapedArray(lead + (n_rows,), np.dtype(bool)), ShapedArray(lead, i32),
        ShapedArray(lead, i32), ShapedArray(lead, f), ShapedArray(lead, np.dtype(bool)),
    ]  # fmt: skip


def _dual_qp_batch(args, dims, **params):
    size = next(a.shape[d] for a, d in zip(args, dims, strict=True) if d is not None)
    moved = [
        jnp.broadcast_to(a, (size,) + a.shape) if d is None else jnp.moveaxis(a, d, 0)
        for a, d in zip(args, dims, strict=True)
    ]
    return dual_qp_p.bind(*moved, **params), [0] * 7


def _dual_qp_jvp(primals, tangents, **params):
    # the loop is not differentiated (its inputs are stop_gradient's): zero tangents, the
    # derivative of the optimum comes from _on_active_set
    out = dual_qp_p.bind(*primals, **params)
    return out, [ad.Zero.from_primal_value(o) for o in out]


def _dual_qp_bind(*args, **params):
    return dual_qp_p.bind(*args, **params)


# called on values (eagerly; the C export's folding of known inputs): the primitive, jitted,
# so that it is lowered as inside any jitted function
dual_qp_p.def_impl(jax.jit(_dual_qp_bind, static_argnames=("batched", "tols", "slack_row")))
dual_qp_p.def_abstract_eval(_dual_qp_abstract)
_jax_lowering = mlir.lower_fun(_dual_qp_impl, multiple_results=True)


def _dual_qp_cpu_lowering(ctx, *args, batched, tols, slack_row):
    """On the CPU: one custom call into the solver written in C, where it could be built.

    (:mod:`safestab.export._dual_qp_ffi`: the same function the C export writes, a batch
    looped over in C.) Elsewhere, and where it could not be built, the JAX implementation.
    """
    from ..export._dual_qp_ffi import ensure

    target = ensure() if ctx.avals_in[0].dtype == np.float64 else None
    if target is None:
        return _jax_lowering(ctx, *args, batched=batched, tols=tols, slack_row=slack_row)
    return jax.ffi.ffi_lowering(target)(
        ctx, *args, add=np.float64(tols.add), dep=np.float64(tols.dep),
        cert=np.float64(tols.cert), eps=np.float64(tols.eps), slack_row=np.int64(slack_row),
    )  # fmt: skip


mlir.register_lowering(dual_qp_p, _jax_lowering)
mlir.register_lowering(dual_qp_p, _dual_qp_cpu_lowering, platform="cpu")
batching.primitive_batchers[dual_qp_p] = _dual_qp_batch
ad.primitive_jvps[dual_qp_p] = _dual_qp_jvp


@jax.custom_jvp
def _on_active_set(G, r, w0, w, mult, active, status):
    """The solver's point and multipliers ``(w, mult)``, with their derivative in ``G, r, w0``.

    The value is ``(w, mult)`` as given (the solver's answer for ``G, r, w0``); the derivative
    is :func:`_on_active_set_jvp`'s, on the answer's active set.
    """
    return w, mult


@_on_active_set.defjvp
def _on_active_set_jvp(primals, tangents):
    """Derivative of the optimum on its active set (the loop itself is not differentiated).

    At an optimum with active rows ``G_A`` (linearly independent: the solver adds only rows
    independent of the active ones) and multipliers ``mu``, the KKT system
    ``w = w0 - G^T mu``, ``G_A w = r_A`` is differentiated with the active set held fixed:
    ``dw = g + G_A^+ (e - G_A g)`` and ``dmu_A = -(G_A G_A^T)^{-1} (e - G_A g)`` with
    ``g = dw0 - dG^T mu`` and ``e = dr_A - dG_A w``. Inside an active set's region this is
    the derivative of the optimum; on a boundary between regions it is the one-sided
    derivative of the active set found there. Where the solver did not reach an optimum
    (infeasible rows, iteration bound) the tangents are zero. The pseudo-inverse comes from
    an SVD of the active rows normalised to unit length, keeping exactly as many singular
    values as there are active rows.
    """
    G, r, w0, w, mult, act, status = primals
    dG, dr, dw0 = tangents[:3]
    norms = scaled_norm(G)
    safe = jnp.where(act & (norms > 0), norms, 1.0)
    Gn = jnp.where(act[:, None], G / safe[:, None], 0.0)
    g = dw0 - dG.T @ mult
    en = jnp.where(act, (dr - dG @ w) / safe, 0.0)
    U, S, Vt = jnp.linalg.svd(Gn, full_matrices=False)
    keep = jnp.arange(S.shape[0]) < jnp.sum(act)
    s_inv = jnp.where(keep, 1.0 / jnp.where(keep, S, 1.0), 0.0)
    resid = en - Gn @ g
    coeff = s_inv * (U.T @ resid)
    optimal = status == OPTIMAL
    dw = jnp.where(optimal, g + Vt.T @ coeff, 0.0)
    dmu = jnp.where(optimal & act, -(U @ (s_inv * coeff)) / safe, 0.0)
    return (w, mult), (dw, dmu)


def _solve_dual(G, r, w0, use, max_iter, batched, tols):
    """The solver itself (see :func:`solve_dual`)."""
    n_rows, dim = G.shape
    norms = scaled_norm(G)
    zero = norms == 0
    infeasible0 = jnp.any(use & zero & (r < 0))
    use = use & ~zero
    safe = jnp.where(zero, 1.0, norms)
    Gn = G / safe[:, None]
    rn = r / safe
    absG = jnp.abs(Gn)
    idx = jnp.arange(dim)
    rows_idx = jnp.arange(n_rows)
    # Indices that differ between problems (p, j, q) select by masks, not by gathers and
    # scatters: under vmap a mask is a dense operation, a gather per problem is not.

    def violations(w):
        return Gn @ w - rn, tols.add * (jnp.abs(rn) + absG @ jnp.abs(w))

    def row(M, p):
        if batched:
            return jnp.sum(
                jnp.where((rows_idx == p).reshape((-1,) + (1,) * (M.ndim - 1)), M, 0.0), 0
            )
        return M[p]

    def add(state, p, d, d1, d2, nd2, lam_p, n, rn_p):
        w, Q, R, act, lam, in_set, q, _, _, it, status, A, ra = state
        dq = jnp.sum(jnp.where(idx == q, d, 0.0))
        alpha = -jnp.where(dq < 0, -1.0, 1.0) * jnp.sqrt(nd2)
        v = jnp.where(idx == q, d2 - alpha, d2)
        Q = Q - (2.0 / (v @ v)) * jnp.outer(Q @ v, v)
        col = jnp.where(idx < q, d1, jnp.where(idx == q, alpha, 0.0))
        R = jnp.where(idx[None, :] == q, col[:, None], R)
        act = jnp.where(idx == q, p, act)
        lam = jnp.where(idx == q, lam_p, lam)
        A = jnp.where(idx[:, None] == q, n[None, :], A)  # the active rows, kept in step
        ra = jnp.where(idx == q, rn_p, ra)
        in_set = in_set | (rows_idx == p)
        return (
            w, Q, R, act, lam, in_set, q + 1, jnp.int32(-1), jnp.zeros_like(lam_p), it, status,
            A, ra,
        )  # fmt: skip

    def drop(state, j, p, lam_p):
        w, Q, R, act, lam, in_set, q, _, _, it, status, A, ra = state
        act_j = jnp.sum(jnp.where(idx == j, act, 0))
        in_set = in_set & (rows_idx != act_j)
        moves = (idx >= j) & (idx < q - 1)  # column c takes column c + 1
        R = jnp.where(moves[None, :], jnp.roll(R, -1, axis=1), R)
        R = jnp.where(idx[None, :] == q - 1, 0.0, R)
        act = jnp.where(idx == q - 1, -1, jnp.where(moves, jnp.roll(act, -1), act))
        lam = jnp.where(idx == q - 1, 0.0, jnp.where(moves, jnp.roll(lam, -1), lam))
        A = jnp.where(
            idx[:, None] == q - 1, 0.0, jnp.where(moves[:, None], jnp.roll(A, -1, axis=0), A)
        )
        ra = jnp.where(idx == q - 1, 0.0, jnp.where(moves, jnp.roll(ra, -1), ra))

        def rotate(i, QR):
            # rows i, i + 1 of R (columns of Q), only for j <= i < q - 1; i is the same in
            # every problem of a batch, so the slices stay slices under vmap
            Q, R = QR
            a, b = R[i, i], R[i + 1, i]
            h = jnp.hypot(a, b)
            on = (i >= j) & (i < q - 1) & (h > 0)
            c, s = (
                jnp.where(on, a / jnp.where(h > 0, h, 1.0), 1.0),
                jnp.where(on, b / jnp.where(h > 0, h, 1.0), 0.0),
            )
            ri, ri1 = R[i], R[i + 1]
            R = R.at[i].set(c * ri + s * ri1).at[i + 1].set(-s * ri + c * ri1)
            qi, qi1 = Q[:, i], Q[:, i + 1]
            Q = Q.at[:, i].set(c * qi + s * qi1).at[:, i + 1].set(-s * qi + c * qi1)
            return Q, R

        if dim <= UNROLL:
            Q, R = _loop(dim - 1, rotate, (Q, R))
        else:  # one Householder QR of the Hessenberg matrix: one LAPACK call, not D - 1 steps
            Qh, R = jnp.linalg.qr(R)
            Q = Q @ Qh
            R = jnp.where(
                idx[None, :] >= q - 1, jnp.where(idx[:, None] == idx[None, :], 1.0, 0.0), R
            )
        # padding: identity beyond the active columns
        R = jnp.where((idx[:, None] == q - 1) & (idx[None, :] == q - 1), 1.0, R)
        return (w, Q, R, act, lam, in_set, q - 1, p, lam_p, it, status, A, ra)

    def body(state):
        w, Q, R, act, lam, in_set, q, p, lam_p, it, status, A, ra = state
        viol, tol = violations(w)
        cand = use & ~in_set & (viol > tol)
        p_new = jnp.argmax(jnp.where(cand, viol, -jnp.inf)).astype(jnp.int32)
        pending = p >= 0
        done = ~pending & ~jnp.any(cand)
        p = jnp.where(pending, p, p_new)
        lam_p = jnp.where(pending, lam_p, 0.0)
        n = row(Gn, p)
        viol_p = row(viol, p)
        d = Q.T @ n
        d1 = jnp.where(idx < q, d, 0.0)
        d2 = jnp.where(idx >= q, d, 0.0)
        nd2 = d2 @ d2
        dependent = jnp.sqrt(nd2) <= tols.dep
        dz = jnp.where(dependent, 0.0, -(Q @ d2))
        rvec = _upper_solve(R, d1)
        blocking = (idx < q) & (rvec > 0)
        ratio = jnp.where(blocking, lam / jnp.where(blocking, rvec, 1.0), jnp.inf)
        j = jnp.argmin(ratio).astype(jnp.int32)
        t1 = jnp.maximum(jnp.min(ratio), 0.0)  # a multiplier rounded below zero: a zero step
        t2 = jnp.where(
            dependent, jnp.inf, jnp.maximum(viol_p, 0.0) / jnp.where(dependent, 1.0, nd2)
        )
        t = jnp.minimum(t1, t2)
        # infeasible: the row is a combination of the active ones and no multiplier can give
        # way (a Farkas certificate); a step that overflows is a numerical failure instead
        infeasible = ~done & dependent & ~jnp.any(blocking)
        overflow = ~done & ~infeasible & ~jnp.isfinite(t)
        stop = done | infeasible | overflow
        tt = jnp.where(stop, 0.0, t)
        w = w + tt * dz
        lam = jnp.where(idx < q, jnp.maximum(lam - tt * rvec, 0.0), lam)
        lam_p = jnp.maximum(lam_p, 0.0) + tt
        moved = (w, Q, R, act, lam, in_set, q, p, lam_p, it + 1, status, A, ra)
        full = t2 <= t1
        nxt = jax.lax.cond(
            stop,
            lambda s: s,
            lambda s: jax.lax.cond(
                full,
                lambda s: add(s, p, d, d1, d2, nd2, lam_p, n, row(rn, p)),
                lambda s: drop(s, j, p, lam_p),
                s,
            ),
            moved,
        )
        new_status = jnp.where(done, OPTIMAL, jnp.where(infeasible, INFEASIBLE, ITERATION_LIMIT))
        return nxt[:10] + (jnp.where(stop, new_status, -1).astype(jnp.int32),) + nxt[11:]

    def cond(state):
        it, status = state[9], state[10]
        return (status < 0) & (it < max_iter)

    # the loop's state starts from constants made to depend on the problem's data (``tie``
    # selects them, whatever its value): under vmap the state is then batched from the
    # start, as the loop makes it, and the while loop's batching rule passes over the body
    # once instead of two or three times (each pass costs about as much as tracing it)
    tie = jnp.sum(Gn[0]) + rn[0] + jnp.sum(w0[:1])
    init = tied(
        (
            jnp.asarray(w0, dtype=G.dtype),
            jnp.eye(dim, dtype=G.dtype),
            jnp.eye(dim, dtype=G.dtype),
            jnp.full((dim,), -1, dtype=jnp.int32),
            jnp.zeros(dim, dtype=G.dtype),
            jnp.zeros(n_rows, dtype=bool),
            jnp.int32(0),
            jnp.int32(-1),
            jnp.asarray(0.0, dtype=G.dtype),
            jnp.int32(0),
            jnp.where(infeasible0, INFEASIBLE, -1).astype(jnp.int32),
            jnp.zeros((dim, dim), dtype=G.dtype),
            jnp.zeros(dim, dtype=G.dtype),
        ),
        tie,
    )
    w, Q, R, act, lam, in_set, q, p, lam_p, it, status, A, ra = jax.lax.while_loop(cond, body, init)
    # the bound reached just as the last step finished: the point may still be optimal
    viol, tol = violations(w)
    finished = (status < 0) & (p < 0) & ~jnp.any(use & ~in_set & (viol > tol))
    status = jnp.where(finished, OPTIMAL, jnp.where(status < 0, ITERATION_LIMIT, status))

    # the point from the final active set alone: projection, then one refinement step
    used = idx < q
    # the active rows, kept in step with the factors (no gather whose indices differ
    # between problems, which the C export could not write either)
    rows = jnp.where(used[:, None], A, 0.0)
    rhs = jnp.where(used, ra, 0.0)
    onehot = (act[:, None] == rows_idx[None, :]) & used[:, None]
    Q1 = jnp.where(used[None, :], Q, 0.0)
    y = _upper_t_solve(R, jnp.where(used, rhs - rows @ w0, 0.0))
    w_star = w0 + Q1 @ y
    y2 = _upper_t_solve(R, jnp.where(used, rhs - rows @ w_star, 0.0))
    y = y + y2
    w_star = w_star + Q1 @ y2
    lam_act = -_upper_solve(R, y)
    optimal = status == OPTIMAL
    w = jnp.where(optimal, w_star, w)
    lam_act = jnp.where(optimal, lam_act, lam)
    diag = jnp.abs(jnp.diagonal(R))
    cond_est = jnp.where(
        q > 0,
        jnp.max(jnp.where(used, diag, 0.0)) / jnp.min(jnp.where(used, diag, jnp.inf)),
        1.0,
    )
    # the certificate of this problem
    viol = Gn @ w - rn
    primal_ok = jnp.all(~use | (viol <= tols.cert * (jnp.abs(rn) + absG @ jnp.abs(w))))
    # multipliers: their sign is as accurate as the triangular solve, eps times cond(R);
    # stationarity and the active rows' slackness only carry the factors' drift over the
    # updates, eps times the iterations, with no cond factor (backward stable solves)
    dual_tol = 64 * tols.eps * cond_est
    drift_tol = 64 * tols.eps * (it + dim)
    lam_used = jnp.where(used, lam_act, 0.0)
    lam_max = jnp.max(jnp.abs(lam_used))
    dual_ok = jnp.all(~used | (lam_act >= -dual_tol * lam_max))
    grad = rows.T @ lam_used
    stat = jnp.max(jnp.abs(w - w0 + grad))
    stat_scale = (
        jnp.max(jnp.abs(w)) + jnp.max(jnp.abs(w0)) + jnp.max(jnp.abs(rows.T) @ jnp.abs(lam_used))
    )
    stat_ok = stat <= drift_tol * stat_scale
    slack_rows = rows @ w - rhs
    tight_ok = jnp.all(
        ~used | (jnp.abs(slack_rows) <= tols.cert * (jnp.abs(rhs) + jnp.abs(rows) @ jnp.abs(w)))
    )
    certified = optimal & primal_ok & dual_ok & stat_ok & tight_ok
    lam_act = jnp.maximum(lam_act, 0.0)
    mult = jnp.sum(jnp.where(onehot, lam_act[:, None], 0.0), axis=0) / safe
    return DualSolution(w, mult, in_set, status.astype(jnp.int32), it, cond_est, certified)
