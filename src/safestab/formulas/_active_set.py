"""Unchecked kernel: the exact minimiser of ``1/2 |z|^2`` under a few linear rows, by active sets.

For ``G z <= r`` with ``N`` rows in ``D`` dimensions, every subset ``S`` of at most ``D`` rows
(with at most one row of each *exclusive* pair, the two sides of an input limit) is tried at
once (a static list, vectorised): its equality-constrained minimiser
``z_S = G_S^T (G_S G_S^T)^{-1} r_S`` and multipliers are computed by Gram-Schmidt (twice, so
the basis is orthonormal to working precision) and triangular solves — elementwise operations
only, so the kernel fuses, jits, vmaps and exports to C. The KKT point (multipliers >= 0, every
row satisfied) is unique because the objective is strictly convex; the first valid subset in
order of size is returned. Rows are normalised to unit length first (a row's scaling does not
move its half-space), and a subset whose rows are dependent within ``rank_tol`` (``sin`` of the
angle between a row and the span of the others) is skipped: a smaller subset then gives the
same point.
"""

from __future__ import annotations

import itertools
from functools import lru_cache
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ._kernels import scaled_norm

__all__ = ["ActiveSetSolution", "active_sets", "solve_rows", "RANK_TOL", "FEAS_RTOL"]

#: A subset is used only if each of its rows is at least this far (sine of the angle) from the
#: span of the earlier ones: the general solver's counterpart of the two-constraint parallel
#: tolerance (``sin^2 <= 1e-12``).
RANK_TOL = 1e-6
#: Relative tolerance of the primal and dual checks that select the KKT subset.
FEAS_RTOL = 1e-10


class ActiveSetSolution(NamedTuple):
    """The minimiser ``z`` (..., D), its multipliers (..., N), the active mask and a flag."""

    z: Any
    multipliers: Any
    active: Any
    found: Any


@lru_cache(maxsize=64)
def active_sets(n_rows: int, dim: int, exclusive: tuple[tuple[int, int], ...] = ()) -> np.ndarray:
    """The candidate subsets, ordered by size, as row indices padded with -1: (n_sets, s_max)."""
    s_max = min(n_rows, dim)
    sets = []
    for size in range(s_max + 1):
        for combo in itertools.combinations(range(n_rows), size):
            chosen = set(combo)
            if any(i in chosen and j in chosen for i, j in exclusive):
                continue
            sets.append(list(combo) + [-1] * (s_max - size))
    return np.asarray(sets, dtype=np.int32).reshape(len(sets), s_max)


def solve_rows(G: Any, r: Any, sets: np.ndarray) -> ActiveSetSolution:
    """Minimise ``1/2 |z|^2`` subject to ``G z <= r``; ``G`` (..., N, D), ``r`` (..., N).

    Rows of ``G`` that are exactly zero are never made active (their condition ``0 <= r``
    either holds or makes the problem infeasible). ``found`` is False where no subset is a KKT
    point (the rows are inconsistent); ``z`` is then zero.
    """
    n_rows, dim = G.shape[-2], G.shape[-1]
    norms = scaled_norm(G)
    safe = jnp.where(norms > 0, norms, 1.0)
    Gn = G / safe[..., None]
    rn = r / safe
    s_max = sets.shape[1]
    idx = np.where(sets >= 0, sets, 0)
    used = sets >= 0  # (n_sets, s_max), static
    # rows of every subset: (..., n_sets, s_max, D), padding rows zero
    rows = jnp.where(used[..., None], jnp.take(Gn, idx, axis=-2), 0.0)
    rhs = jnp.where(used, jnp.take(rn, idx, axis=-1), 0.0)
    nonzero = jnp.where(used, jnp.take(norms, idx, axis=-1) > 0, True)

    # Gram-Schmidt, twice, on the rows in order: rows_i = sum_{j<=i} R[j, i] q_j
    qs: list[Any] = []
    R: list[list[Any]] = [[None] * s_max for _ in range(s_max)]
    ok = jnp.all(nonzero, axis=-1)
    for i in range(s_max):
        v = rows[..., i, :]
        coef = [jnp.zeros(v.shape[:-1]) for _ in range(i)]
        for _ in range(2):
            for j in range(i):
                proj = jnp.sum(v * qs[j], axis=-1)
                coef[j] = coef[j] + proj
                v = v - proj[..., None] * qs[j]
        nrm = scaled_norm(v)
        pad = ~used[:, i]
        indep = nrm > RANK_TOL
        ok = ok & (pad | indep)
        qs.append(
            jnp.where((pad | ~indep)[..., None], 0.0, v / jnp.where(indep, nrm, 1.0)[..., None])
        )
        for j in range(i):
            R[j][i] = jnp.where(pad, 0.0, coef[j])
        R[i][i] = jnp.where(pad | ~indep, 1.0, nrm)
    # R^T y = rhs (forward), z = sum_i y_i q_i, R lam' = y (backward), multipliers = -lam'
    y: list[Any] = []
    for i in range(s_max):
        acc = rhs[..., i]
        for j in range(i):
            acc = acc - R[j][i] * y[j]
        y.append(acc / R[i][i])
    z = sum((y[i][..., None] * qs[i] for i in range(s_max)), jnp.zeros(rows.shape[:-2] + (dim,)))
    lam: list[Any] = [None] * s_max  # filled backwards
    for i in reversed(range(s_max)):
        acc = y[i]
        for j in range(i + 1, s_max):
            acc = acc - R[i][j] * lam[j]
        lam[i] = acc / R[i][i]
    mult_s = -jnp.stack(lam, axis=-1) if s_max else jnp.zeros(rows.shape[:-2] + (0,))

    # KKT check of every subset: dual feasibility and every row's primal feasibility
    Gz = jnp.einsum("...nd,...sd->...sn", Gn, z)  # (..., n_sets, N)
    scale = jnp.abs(rn)[..., None, :] + jnp.einsum("...nd,...sd->...sn", jnp.abs(Gn), jnp.abs(z))
    primal = jnp.all(Gz - rn[..., None, :] <= FEAS_RTOL * scale, axis=-1)
    dual_scale = jnp.max(jnp.abs(mult_s), axis=-1, keepdims=True) if s_max else 0.0
    dual = jnp.all(jnp.where(used, mult_s >= -FEAS_RTOL * dual_scale, True), axis=-1)
    valid = ok & primal & dual
    first = jnp.argmax(valid, axis=-1)
    found = jnp.any(valid, axis=-1)
    take = lambda a: jnp.take_along_axis(a, first[..., None, None], axis=-2)[..., 0, :]  # noqa: E731
    z_best = jnp.where(found[..., None], take(z), 0.0)
    mult_best = take(mult_s) if s_max else jnp.zeros(z_best.shape[:-1] + (0,))
    # scatter the subset's multipliers to the rows (divided by the row norms: original scale)
    chosen = jnp.take(jnp.asarray(idx), first, axis=0)  # (..., s_max)
    chosen_used = jnp.take(jnp.asarray(used), first, axis=0)
    onehot = (chosen[..., :, None] == jnp.arange(n_rows)) & chosen_used[..., :, None]
    mult_rows = jnp.sum(jnp.where(onehot, mult_best[..., :, None], 0.0), axis=-2) / safe
    mult_rows = jnp.where(found[..., None], mult_rows, 0.0)
    active = jnp.any(onehot, axis=-2) & found[..., None]
    return ActiveSetSolution(z_best, mult_rows, active, found)
