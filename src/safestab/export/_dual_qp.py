"""The filter's QP solver as written C: the second implementation of :data:`dual_qp_p`.

:func:`safestab.formulas._dual_active_set.solve_dual` binds one primitive,
:data:`~safestab.formulas._dual_active_set.dual_qp_p`, for the solver's loop. The C export
writes it as a call of the function below instead of translating the JAX implementation's
operations one by one, and the CPU runs it as one XLA custom call into the same function
(:mod:`safestab.export._dual_qp_ffi`). The steps, the order of the rows and the tolerances
are the JAX implementation's (the dual active-set method of Goldfarb and Idnani; see that
module); what differs is how they are laid out:

* the work arrays are sized by the problem, ``2 D^2 + N D + 9 D + 4 N`` reals and
  ``D + 2 N`` ints for ``N`` rows in ``D`` coordinates, reused by every iteration (the
  translated loop held a copy of its whole state, ``3 D^2 + ...``, and the temporaries of
  each of its operations);
* a row leaving the active set restores the triangular factor by Givens rotations of the
  columns it moved, ``O(D q)``; the JAX implementation does the same up to 8 coordinates and
  a Householder QR beyond (one LAPACK call costs less than a loop in XLA, while in C the
  rotations cost less);
* the active rows are read from the normalised rows by their indices, not kept as a copy;
* loops run over the active set's size ``q``, not over ``D``.

The answers agree with XLA's to rounding (``tests/test_export_filter.py``); where rounding
decides (a row violated by exactly its tolerance), the C and the JAX step may take different
steps, each certified against the problem's own scales as before.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["c_work_sizes", "int_work_size", "source", "work_size"]

#: The work arrays' sizes as terms ``(coefficient, sizes multiplied)`` of ``n`` rows and ``dim``
#: coordinates: one definition for the exporter's static arrays (:func:`work_size`) and C
#: expressions of ``n`` and ``dim`` (:func:`c_work_sizes`: the CPU kernel's allocations).
_WORK_REALS = ((2, ("dim", "dim")), (1, ("n", "dim")), (9, ("dim",)), (4, ("n",)))
_WORK_INTS = ((1, ("dim",)), (2, ("n",)))


def _size(terms: tuple, n_rows: int, dim: int) -> int:
    sizes = {"n": n_rows, "dim": dim}
    return sum(c * math.prod(sizes[s] for s in names) for c, names in terms)


def _c_size(terms: tuple) -> str:
    return " + ".join(" * ".join((str(c), *names)) for c, names in terms)


def work_size(n_rows: int, dim: int) -> int:
    """Reals of the solver's work array for ``n_rows`` rows in ``dim`` coordinates."""
    return _size(_WORK_REALS, n_rows, dim)


def int_work_size(n_rows: int, dim: int) -> int:
    """Ints of the solver's index work array."""
    return _size(_WORK_INTS, n_rows, dim)


def c_work_sizes() -> tuple[str, str]:
    """The work arrays' sizes (reals, ints) as C expressions of ``n`` and ``dim``."""
    return _c_size(_WORK_REALS), _c_size(_WORK_INTS)


_TEMPLATE = r"""
/* The dual active-set solver of safestab.formulas._dual_active_set (Goldfarb-Idnani with an
   identity Hessian): min 1/2 |w - w0|^2 s.t. G_i w <= r_i for the rows with use_i. G (the
   n x dim rows stored by columns: element (i, j) at G[j * n + i]) and r are normalised in
   place; w holds w0 on entry and the point on return.
   work: 2 dim^2 + 9 dim + 3 n reals, iwork: dim + 2 n ints. status 0 optimal, 1 infeasible,
   2 iteration bound; certified: the KKT certificate of the normalised problem holds.
   NAME below (one problem as solve_dual states it) is the entry the callers use. */
static REAL NAME_max(REAL a, REAL b) { return a != a ? a : (b != b ? b : (a > b ? a : b)); }
static REAL NAME_min(REAL a, REAL b) { return a != a ? a : (b != b ? b : (a < b ? a : b)); }
/* s = G w for every row, G stored by columns (dim x n): the inner loop runs over the rows
   (vectorised), each row's sum in the order of its coordinates */
static void NAME_rows(int n, int dim, const REAL *G, const REAL *w, REAL *s)
{
    for (int i = 0; i < n; ++i) s[i] = ZERO;
    for (int j = 0; j < dim; ++j) {
        const REAL wj = w[j];
        for (int i = 0; i < n; ++i) s[i] += G[j * n + i] * wj;
    }
}
/* |G_i| |w|, the magnitude a row's value is tested against: needed only where the row is
   violated (every tolerance is >= 0), so computed for those rows alone */
static REAL NAME_size(int n, int dim, const REAL *G, const REAL *w, int i)
{
    REAL t = ZERO;
    for (int j = 0; j < dim; ++j) t += FABS(G[j * n + i]) * FABS(w[j]);
    return t;
}
static void NAME_core(int n, int dim, REAL *G, REAL *r, REAL *w, const int *use_in, int max_iter,
                 REAL add_tol, REAL dep_tol, REAL cert_tol, REAL eps, REAL *work, int *iwork,
                 REAL *mult, int *active, int *status_out, int *iters_out, REAL *cond_out,
                 int *certified_out)
{
    REAL *Q = work, *R = Q + dim * dim, *w0 = R + dim * dim, *lam = w0 + dim, *d = lam + dim;
    REAL *dz = d + dim, *v = dz + dim, *rvec = v + dim, *y = rvec + dim, *y2 = y + dim;
    REAL *tmp = y2 + dim, *safe = tmp + dim, *viol = safe + n, *tolv = viol + n;
    int *act = iwork, *use = act + dim, *in_set = use + n;
    int infeasible0 = 0;
    /* each row's scaled norm (max |G_ij| times the norm of the row over it), as the JAX one */
    for (int i = 0; i < n; ++i) viol[i] = ZERO;
    for (int j = 0; j < dim; ++j)
        for (int i = 0; i < n; ++i) {
            const REAL a = FABS(G[j * n + i]);
            if (viol[i] == viol[i] && !(a <= viol[i])) viol[i] = a;
        }
    for (int i = 0; i < n; ++i) {
        safe[i] = viol[i] != ZERO ? viol[i] : ONE;
        tolv[i] = ZERO;
    }
    for (int j = 0; j < dim; ++j)
        for (int i = 0; i < n; ++i) tolv[i] += (G[j * n + i] / safe[i]) * (G[j * n + i] / safe[i]);
    for (int i = 0; i < n; ++i) {
        const REAL norm = viol[i] * SQRT(tolv[i]);
        use[i] = use_in[i] && !(norm == ZERO);
        if (use_in[i] && norm == ZERO && r[i] < ZERO) infeasible0 = 1;
        safe[i] = norm == ZERO ? ONE : norm;
        r[i] = r[i] / safe[i];
        in_set[i] = 0;
    }
    for (int j = 0; j < dim; ++j)
        for (int i = 0; i < n; ++i) G[j * n + i] = G[j * n + i] / safe[i];
    for (int i = 0; i < dim; ++i) {
        w0[i] = w[i];
        lam[i] = ZERO;
        act[i] = -1;
        for (int j = 0; j < dim; ++j) Q[i * dim + j] = R[i * dim + j] = i == j ? ONE : ZERO;
    }
    int q = 0, p = -1, it = 0, status = infeasible0 ? 1 : -1;
    REAL lam_p = ZERO;
    while (status < 0 && it < max_iter) {
        int any_cand = 0, p_new = 0;
        REAL best = -INFINITY;
        NAME_rows(n, dim, G, w, viol);
        for (int i = 0; i < n; ++i) {
            viol[i] = viol[i] - r[i];
            if (use[i] && !in_set[i] && viol[i] > ZERO
                && viol[i] > add_tol * (FABS(r[i]) + NAME_size(n, dim, G, w, i))) {
                any_cand = 1;
                if (viol[i] > best) { best = viol[i]; p_new = i; }
            }
        }
        const int pending = p >= 0, done = !pending && !any_cand;
        if (!pending) { p = p_new; lam_p = ZERO; }
        const REAL viol_p = viol[p];
        REAL nd2 = ZERO;
        for (int c = 0; c < dim; ++c) d[c] = ZERO;
        for (int i = 0; i < dim; ++i) {  /* d = Q^T n, n = row p */
            const REAL ni = G[i * n + p];
            for (int c = 0; c < dim; ++c) d[c] += Q[i * dim + c] * ni;
        }
        for (int c = q; c < dim; ++c) nd2 += d[c] * d[c];
        const int dependent = SQRT(nd2) <= dep_tol;
        for (int i = 0; i < dim; ++i) {
            REAL s = ZERO;
            for (int c = q; c < dim; ++c) s += Q[i * dim + c] * d[c];
            dz[i] = dependent ? ZERO : -s;
        }
        for (int c = q - 1; c >= 0; --c) {  /* rvec = R^-1 d, on the active block */
            REAL s = d[c];
            for (int k = c + 1; k < q; ++k) s -= R[c * dim + k] * rvec[k];
            rvec[c] = s / R[c * dim + c];
        }
        int any_blocking = 0, j = 0;
        REAL ratio_min = INFINITY;
        for (int c = 0; c < q; ++c) {
            if (rvec[c] > ZERO) {
                const REAL ratio = lam[c] / rvec[c];
                any_blocking = 1;
                if (ratio < ratio_min || ratio != ratio) {
                    if (ratio_min == ratio_min) { ratio_min = ratio; j = c; }
                }
            }
        }
        const REAL t1 = NAME_max(ratio_min, ZERO);
        const REAL t2 = dependent ? INFINITY : NAME_max(viol_p, ZERO) / nd2;
        const REAL t = NAME_min(t1, t2);
        const int infeasible = !done && dependent && !any_blocking;
        const int overflow = !done && !infeasible && !isfinite(t);
        const int stop = done || infeasible || overflow;
        const REAL tt = stop ? ZERO : t;
        for (int i = 0; i < dim; ++i) w[i] = w[i] + tt * dz[i];
        for (int c = 0; c < q; ++c) lam[c] = NAME_max(lam[c] - tt * rvec[c], ZERO);
        lam_p = NAME_max(lam_p, ZERO) + tt;
        it += 1;
        if (stop) {
            status = done ? 0 : (infeasible ? 1 : 2);
        } else if (t2 <= t1) {  /* add row p: one Householder reflection of Q's columns q.. */
            const REAL alpha = -(d[q] < ZERO ? -ONE : ONE) * SQRT(nd2);
            REAL vv = ZERO;
            for (int c = q; c < dim; ++c) {
                v[c] = c == q ? d[c] - alpha : d[c];
                vv += v[c] * v[c];
            }
            const REAL coef = TWO / vv;
            for (int i = 0; i < dim; ++i) {
                REAL s = ZERO;
                for (int c = q; c < dim; ++c) s += Q[i * dim + c] * v[c];
                for (int c = q; c < dim; ++c) Q[i * dim + c] = Q[i * dim + c] - coef * (s * v[c]);
            }
            for (int i = 0; i < dim; ++i) R[i * dim + q] = i < q ? d[i] : (i == q ? alpha : ZERO);
            act[q] = p;
            lam[q] = lam_p;
            in_set[p] = 1;
            q += 1;
            p = -1;
            lam_p = ZERO;
        } else {  /* drop active column j; Givens rotations restore R */
            in_set[act[j]] = 0;
            for (int c = j; c < q - 1; ++c) {
                for (int i = 0; i < dim; ++i) R[i * dim + c] = R[i * dim + c + 1];
                act[c] = act[c + 1];
                lam[c] = lam[c + 1];
            }
            for (int i = 0; i < dim; ++i) R[i * dim + q - 1] = ZERO;
            act[q - 1] = -1;
            lam[q - 1] = ZERO;
            for (int i = j; i < q - 1; ++i) {
                const REAL a = R[i * dim + i], b = R[(i + 1) * dim + i];
                const REAL h = HYPOT(a, b);
                if (h > ZERO) {
                    const REAL cs = a / h, sn = b / h;
                    for (int k = 0; k < dim; ++k) {
                        const REAL ri = R[i * dim + k], ri1 = R[(i + 1) * dim + k];
                        R[i * dim + k] = cs * ri + sn * ri1;
                        R[(i + 1) * dim + k] = -sn * ri + cs * ri1;
                    }
                    for (int k = 0; k < dim; ++k) {
                        const REAL qi = Q[k * dim + i], qi1 = Q[k * dim + i + 1];
                        Q[k * dim + i] = cs * qi + sn * qi1;
                        Q[k * dim + i + 1] = -sn * qi + cs * qi1;
                    }
                }
            }
            R[(q - 1) * dim + q - 1] = ONE;
            q -= 1;
        }
    }
    if (status < 0) {  /* the bound reached just as the last step finished: maybe optimal */
        int any_cand = 0;
        NAME_rows(n, dim, G, w, viol);
        for (int i = 0; i < n; ++i)
            if (use[i] && !in_set[i] && viol[i] - r[i] > ZERO
                && viol[i] - r[i] > add_tol * (FABS(r[i]) + NAME_size(n, dim, G, w, i)))
                any_cand = 1;
        status = p < 0 && !any_cand ? 0 : 2;
    }
    /* the point from the final active set alone: projection, then one refinement step */
    for (int pass = 0; pass < 2; ++pass) {
        const REAL *base = pass == 0 ? w0 : y2;  /* y2 holds w* in pass 1 */
        for (int c = 0; c < q; ++c) {
            REAL s = ZERO;
            for (int k = 0; k < dim; ++k) s += G[k * n + act[c]] * base[k];
            tmp[c] = r[act[c]] - s;
        }
        for (int c = 0; c < q; ++c) {  /* solve R^T x = tmp (forward) into v */
            REAL s = tmp[c];
            for (int k = 0; k < c; ++k) s -= R[k * dim + c] * v[k];
            v[c] = s / R[c * dim + c];
        }
        if (pass == 0) {
            for (int c = 0; c < q; ++c) y[c] = v[c];
            for (int i = 0; i < dim; ++i) {
                REAL s = ZERO;
                for (int c = 0; c < q; ++c) s += Q[i * dim + c] * v[c];
                y2[i] = w0[i] + s;
            }
        } else {
            for (int c = 0; c < q; ++c) y[c] = y[c] + v[c];
            for (int i = 0; i < dim; ++i) {
                REAL s = ZERO;
                for (int c = 0; c < q; ++c) s += Q[i * dim + c] * v[c];
                y2[i] = y2[i] + s;
            }
        }
    }
    const int optimal = status == 0;
    for (int c = q - 1; c >= 0; --c) {  /* multipliers: -R^-1 y (into rvec) */
        REAL s = y[c];
        for (int k = c + 1; k < q; ++k) s -= R[c * dim + k] * rvec[k];
        rvec[c] = s / R[c * dim + c];
    }
    for (int c = 0; c < q; ++c) rvec[c] = optimal ? -rvec[c] : lam[c];
    if (optimal) for (int i = 0; i < dim; ++i) w[i] = y2[i];
    REAL cond = ONE;
    if (q > 0) {
        REAL hi = ZERO, lo = INFINITY;
        for (int c = 0; c < q; ++c) {
            hi = NAME_max(hi, FABS(R[c * dim + c]));
            lo = NAME_min(lo, FABS(R[c * dim + c]));
        }
        cond = hi / lo;
    }
    /* the certificate of this problem */
    int ok = optimal;
    NAME_rows(n, dim, G, w, viol);
    for (int i = 0; i < n; ++i) {
        const REAL e = viol[i] - r[i];
        if (use[i] && !(e <= ZERO)
            && !(e <= cert_tol * (FABS(r[i]) + NAME_size(n, dim, G, w, i))))
            ok = 0;
    }
    const REAL dual_tol = SIXTYFOUR * eps * cond, drift_tol = SIXTYFOUR * eps * (REAL)(it + dim);
    REAL lam_max = ZERO;
    for (int c = 0; c < q; ++c) lam_max = NAME_max(lam_max, FABS(rvec[c]));
    for (int c = 0; c < q; ++c) if (!(rvec[c] >= -dual_tol * lam_max)) ok = 0;
    REAL stat = ZERO, wmax = ZERO, w0max = ZERO, gmax = ZERO;
    for (int i = 0; i < dim; ++i) {
        REAL s = ZERO, a = ZERO;
        for (int c = 0; c < q; ++c) {
            const REAL gc = G[i * n + act[c]];
            s += gc * rvec[c];
            a += FABS(gc) * FABS(rvec[c]);
        }
        stat = NAME_max(stat, FABS(w[i] - w0[i] + s));
        wmax = NAME_max(wmax, FABS(w[i]));
        w0max = NAME_max(w0max, FABS(w0[i]));
        gmax = NAME_max(gmax, a);
    }
    if (!(stat <= drift_tol * (wmax + w0max + gmax))) ok = 0;
    for (int c = 0; c < q; ++c) {  /* the active rows are tight (viol: G w at this w) */
        const int i = act[c];
        const REAL t = NAME_size(n, dim, G, w, i);
        if (!(FABS(viol[i] - r[i]) <= cert_tol * (FABS(r[i]) + t))) ok = 0;
    }
    for (int i = 0; i < n; ++i) {
        mult[i] = ZERO;
        active[i] = in_set[i];
    }
    for (int c = 0; c < q; ++c) mult[act[c]] = NAME_max(rvec[c], ZERO) / safe[act[c]];
    *status_out = status;
    *iters_out = it;
    *cond_out = cond;
    *certified_out = ok;
}
/* One problem as safestab.formulas._dual_active_set.solve_dual states it: the rows G (n x
   cols, row-major) and a column per slack (dim - cols of them: slack[j] in row
   slack_row + j), r, w0 (dim), use; max_iter <= 0 means not run (w = w0, no active row,
   status 2, not certified). The point into w (dim), the rows' multipliers and active flags
   into mult and active (n). work: WORK_REALS reals, iwork: WORK_INTS ints. */
static void NAME(int n, int cols, int dim, const REAL *G, const REAL *r, const REAL *w0,
                 const int *use, int max_iter, const REAL *slack, int slack_row, REAL add_tol,
                 REAL dep_tol, REAL cert_tol, REAL eps, REAL *work, int *iwork, REAL *w,
                 REAL *mult, int *active, int *status, int *iters, REAL *cond, int *certified)
{
    REAL *gt = work, *rw = gt + n * dim;
    for (int j = 0; j < dim; ++j) w[j] = w0[j];
    if (max_iter <= 0) {
        for (int i = 0; i < n; ++i) { mult[i] = ZERO; active[i] = 0; }
        *status = 2; *iters = 0; *cond = ONE; *certified = 0;
        return;
    }
    for (int i = 0; i < n; ++i) {  /* the rows by columns, the solver's layout */
        for (int j = 0; j < cols; ++j) gt[j * n + i] = G[i * cols + j];
        rw[i] = r[i];
    }
    for (int i = cols * n; i < dim * n; ++i) gt[i] = ZERO;
    for (int j = 0; j < dim - cols; ++j) gt[(cols + j) * n + slack_row + j] = slack[j];
    NAME_core(n, dim, gt, rw, w, use, max_iter, add_tol, dep_tol, cert_tol, eps, rw + n, iwork,
              mult, active, status, iters, cond, certified);
}
"""


def source(name: str, ct: str, flt: bool, e: Any) -> str:
    """The solver's C function ``name`` for the real type ``ct`` (an emitter helper)."""
    f = "f" if ct == "float" else ""
    lit = (lambda x: f"{x}.0f") if f else (lambda x: f"{x}.0")
    text = _TEMPLATE.replace("WORK_REALS", _c_size(_WORK_REALS))
    text = text.replace("WORK_INTS", _c_size(_WORK_INTS))
    for key, val in (
        ("NAME", name), ("REAL", ct), ("ZERO", lit(0)), ("ONE", lit(1)), ("TWO", lit(2)),
        ("SIXTYFOUR", lit(64)),
        ("FABS", "fabs" + f), ("SQRT", "sqrt" + f), ("HYPOT", "hypot" + f),
    ):  # fmt: skip
        text = text.replace(key, val)
    return text.strip("\n")
