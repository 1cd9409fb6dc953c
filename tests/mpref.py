"""A high-precision (mpmath) active-set reference for the two-constraint QPs.

Independent of the library's algebra: it enumerates the four active sets of

    min 1/2 |z|^2   s.t.   p.z <= -A,   q.z >= B

in 80-digit arithmetic (z = (u, sqrt(m) chi), p = (b, -1/sqrt(m)), q = (d, 0) for the relaxed
problem; p = b, q = d for the hard one) and returns the one whose KKT conditions hold exactly.
The hard problem's parallel tolerance is part of its specification (``parallel_rtol``): a
same-direction pair within it is compatible iff ``v <= 0``, and is otherwise reported
incompatible with the safety-first fallback, as documented in safestab.formulas.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np

DPS = 80


def _mp(x):
    """Exact conversion of a float (or an mp number, kept as it is)."""
    return x if isinstance(x, mp.mpf) else mp.mpf(float(x))


def _seq(v):
    return list(v) if isinstance(v, list) else list(np.atleast_1d(np.asarray(v, float)))


def _dot(x, y):
    return mp.fsum(xi * yi for xi, yi in zip(x, y, strict=True))


def margins(a, b, c, d, kappa, rho, phi, varphi):
    """Exact A = a + kappa zeta, B = rho Gamma - c, zeta, Gamma (mp numbers)."""
    with mp.workdps(DPS):
        a, c = _mp(a), _mp(c)
        b = [_mp(x) for x in _seq(b)]
        d = [_mp(x) for x in _seq(d)]
        bb, dd = _dot(b, b), _dot(d, d)
        zeta = mp.sqrt(a * a + _mp(phi) * bb * bb)
        gamma = mp.sqrt(c * c + _mp(varphi) * dd * dd)
        return a + _mp(kappa) * zeta, _mp(rho) * gamma - c, zeta, gamma


def solve(a, b, c, d, *, kappa, rho, phi, varphi, slack_weight=None, parallel_rtol=1e-12):
    """Return (u as mp list, chi, region, ratio) for the formula's QP; region as in Region.

    ``ratio`` is ``det / (|p|^2 |q|^2)`` of the rows (to skip cases on the tolerance's edge).
    """
    with mp.workdps(DPS):
        A, B, _, _ = margins(a, b, c, d, kappa, rho, phi, varphi)
        bu = [_mp(x) for x in _seq(b)]
        du = [_mp(x) for x in _seq(d)]
        m = len(bu)
        if slack_weight is None:
            p, q = bu, du
        else:
            s = 1 / mp.sqrt(_mp(slack_weight))
            p, q = bu + [-s], du + [mp.mpf(0)]
        pp, qq, pq = _dot(p, p), _dot(q, q), _dot(p, q)
        det = pp * qq - pq * pq
        ratio = det / (pp * qq) if pp > 0 and qq > 0 else mp.mpf(1)
        zero = [mp.mpf(0)] * len(p)

        tiny = mp.mpf(10) ** (20 - DPS)  # 80-digit rounding of the active rows, with room

        norm_p, norm_q = mp.sqrt(pp), mp.sqrt(qq)

        def feasible(z, mag):
            # z was assembled from terms of size mag (|mu1||p| + |mu2||q|): its 80-digit
            # rounding is relative to those, not to z itself
            scale = abs(A) + abs(B) + mag * (norm_p + norm_q)
            return _dot(p, z) + A <= tiny * scale and _dot(q, z) - B >= -tiny * scale

        candidates = []
        candidates.append((4, zero, mp.mpf(0), mp.mpf(0)))
        if pp > 0 and A >= 0:
            candidates.append((1, [-A / pp * x for x in p], A / pp, abs(A) / norm_p))
        if qq > 0 and B >= 0:
            candidates.append((2, [B / qq * x for x in q], mp.mpf(0), abs(B) / norm_q))
        if det > 0:
            mu1 = (A * qq + B * pq) / det
            mu2 = (A * pq + B * pp) / det
            if mu1 >= 0 and mu2 >= 0:
                z3 = [-mu1 * x + mu2 * y for x, y in zip(p, q, strict=True)]
                candidates.append((3, z3, mu1, mu1 * norm_p + mu2 * norm_q))
        region, z, mu1 = 0, None, mp.mpf(0)
        for reg, cand, mu, mag in candidates:
            if feasible(cand, mag):
                region, z, mu1 = reg, cand, mu
                break
        same_parallel = slack_weight is None and pq > 0 and det <= parallel_rtol * pp * qq
        if same_parallel and A * pq + B * pp > 0:
            region, z = 0, None  # the documented tolerance decision
        if z is None:  # safety-first fallback
            if qq > 0:
                z = [max(B, 0) / qq * y for y in q]
                mu1 = mp.mpf(0)
            elif pp > 0:
                mu1 = max(A, 0) / pp
                z = [-mu1 * x for x in p]
            else:
                z = zero
        u = z[:m]
        chi = mu1 / _mp(slack_weight) if slack_weight is not None else mp.mpf(0)
        return u, chi, region, ratio


def rel_error(u_float, u_ref):
    """|u - u_ref| / |u_ref| in high precision (absolute when u_ref = 0)."""
    with mp.workdps(DPS):
        diff = mp.sqrt(mp.fsum((_mp(x) - y) ** 2 for x, y in zip(u_float, u_ref, strict=True)))
        nref = mp.sqrt(mp.fsum(y * y for y in u_ref))
        return float(diff / nref) if nref > 0 else float(diff)


def condition_estimate(
    a, b, c, d, params, slack_weight=None, parallel_rtol=1e-12, samples=6, seed=0
):
    """Relative condition number of u, estimated by random relative perturbations of size 1e-30.

    Every scalar of the problem (a, b, c, d, the parameters and the slack weight) is perturbed
    by ``(1 + 1e-30 r)`` with independent signs ``r``; the estimate is the largest
    ``|du| / (1e-30 |u|)`` over ``samples`` draws (at least 1).
    """
    rng = np.random.default_rng(seed)
    eps = mp.mpf("1e-30")
    with mp.workdps(DPS):
        u0, _, _, _ = solve(
            a, b, c, d, slack_weight=slack_weight, parallel_rtol=parallel_rtol, **params
        )
        n0 = mp.sqrt(mp.fsum(x * x for x in u0))
        best = mp.mpf(1)
        b = np.atleast_1d(np.asarray(b, float))
        d = np.atleast_1d(np.asarray(d, float))
        for _ in range(samples):

            def pert(x):
                return _mp(x) * (1 + eps * int(rng.choice([-1, 1])))

            args = dict(
                a=pert(a),
                b=[pert(x) for x in b],
                c=pert(c),
                d=[pert(x) for x in d],
            )
            par = {k: pert(v) for k, v in params.items()}
            sw = None if slack_weight is None else pert(slack_weight)
            u1, _, _, _ = solve(**args, slack_weight=sw, parallel_rtol=parallel_rtol, **par)
            du = mp.sqrt(mp.fsum((x - y) ** 2 for x, y in zip(u1, u0, strict=True)))
            if n0 > 0:
                best = max(best, du / (eps * n0))
        return float(best)


def cbf_residual(c, d, u, rho, varphi):
    """Exact ``c + d.u - rho Gamma`` and the scale ``|c| + rho Gamma + sum |d_i u_i|``."""
    with mp.workdps(DPS):
        du = [_mp(x) * _mp(y) for x, y in zip(np.atleast_1d(d), np.atleast_1d(u), strict=True)]
        dd = mp.fsum(_mp(x) ** 2 for x in np.atleast_1d(d))
        gamma = mp.sqrt(_mp(c) ** 2 + _mp(varphi) * dd * dd)
        res = _mp(c) + mp.fsum(du) - _mp(rho) * gamma
        scale = abs(_mp(c)) + _mp(rho) * gamma + mp.fsum(abs(x) for x in du)
        return float(res), float(scale)


def clf_residual(a, b, u, kappa, phi):
    """Exact ``a + b.u + kappa zeta`` and the scale ``|a| + kappa zeta + sum |b_i u_i|``."""
    with mp.workdps(DPS):
        bu = [_mp(x) * _mp(y) for x, y in zip(np.atleast_1d(b), np.atleast_1d(u), strict=True)]
        bb = mp.fsum(_mp(x) ** 2 for x in np.atleast_1d(b))
        zeta = mp.sqrt(_mp(a) ** 2 + _mp(phi) * bb * bb)
        res = _mp(a) + mp.fsum(bu) + _mp(kappa) * zeta
        scale = abs(_mp(a)) + _mp(kappa) * zeta + mp.fsum(abs(x) for x in bu)
        return float(res), float(scale)


def solve_rows(G, r):
    """Exact minimiser of 1/2|z|^2 s.t. G z <= r (rows as lists of floats or mp numbers).

    Enumerates every subset of at most D linearly independent rows in 80 digits and keeps the
    KKT point (multipliers >= 0, every row satisfied). Returns (z, found).
    """
    import itertools

    with mp.workdps(DPS):
        G = [[_mp(x) for x in row] for row in G]
        r = [_mp(x) for x in r]
        n, dim = len(G), len(G[0])
        tiny = mp.mpf(10) ** (20 - DPS)
        for size in range(min(n, dim) + 1):
            for S in itertools.combinations(range(n), size):
                if size == 0:
                    z = [mp.mpf(0)] * dim
                    lam = []
                else:
                    M = mp.matrix([[_dot(G[i], G[j]) for j in S] for i in S])
                    if abs(mp.det(M)) <= mp.mpf(10) ** (-60) * max(
                        mp.mpf(1), mp.fsum(abs(M[i, i]) for i in range(size)) ** size
                    ):
                        continue
                    mu = mp.lu_solve(M, mp.matrix([r[i] for i in S]))
                    lam = [-mu[i] for i in range(size)]
                    z = [mp.fsum(mu[t] * G[S[t]][col] for t in range(size)) for col in range(dim)]
                mag = mp.fsum(abs(x) for x in z) + mp.fsum(abs(x) for x in r)
                if any(x < -tiny * (1 + max((abs(y) for y in lam), default=0)) for x in lam):
                    continue
                if all(
                    _dot(G[i], z) - r[i] <= tiny * (mag * (1 + mp.fsum(abs(x) for x in G[i])))
                    for i in range(n)
                ):
                    return z, True
        return [mp.mpf(0)] * dim, False


def proves_inconsistent(G, r, dps=60) -> bool:
    """Whether the rows ``G z <= r`` are proven inconsistent by a Farkas certificate.

    A ``y >= 0`` with ``G'y = 0`` and ``r'y < 0`` proves that no ``z`` satisfies the rows
    (``0 = y'G z <= y'r < 0``). A float64 linear program only proposes ``y``; the proof is
    checked in the working precision, with ``r'y`` negative beyond ``tiny`` times its own
    terms, in one of two ways:

    * the rows that bound one coordinate (``z_j <= hi``, ``-z_j <= -lo``: the input limits)
      cancel ``G'y`` of the other rows exactly (their multipliers are its entries), so the
      proposed multipliers of the other rows need not be exact: this is the statement that
      ``min`` over the box of ``(y'G) z`` exceeds ``y'r``;
    * otherwise ``y`` is solved on the rows the program used (at most ``dim + 1``) and
      ``G'y`` must vanish beyond ``tiny`` times its terms (a feasible point could then only
      lie beyond about ``1 / tiny`` times the data's scale).

    False when neither proves it (the caller then enumerates every active set, as it did
    without this test): a float64 proposal can miss on rows inconsistent by less than its
    rounding. ``G``, ``r``: floats or mp numbers, exact.
    """
    with mp.workdps(dps):
        Gm = [[_mp(x) for x in row] for row in G]
        rm = [_mp(x) for x in r]
        return _certified(Gm, rm, mp.mpf(10) ** (25 - dps))


def _certified(Gm, rm, tiny) -> bool:
    """:func:`proves_inconsistent` on mp rows, in the caller's precision."""
    from scipy.optimize import linprog

    n, dim = len(Gm), len(Gm[0]) if Gm else 0
    if n == 0 or dim == 0:
        return False
    Gf = np.array([[float(x) for x in row] for row in Gm])
    rf = np.array([float(x) for x in rm])
    norm = np.maximum(np.abs(Gf).sum(1), np.abs(rf))
    keep = np.flatnonzero(norm > 0)  # a zero row with r = 0 holds everywhere
    Gn, rn = Gf[keep] / norm[keep, None], rf[keep] / norm[keep]
    A_eq = np.vstack([Gn.T, np.ones((1, len(keep)))])
    b_eq = np.concatenate([np.zeros(dim), [1.0]])
    lp = linprog(rn, A_eq=A_eq, b_eq=b_eq, bounds=(0, None), method="highs")
    if lp.status != 0 or not lp.fun < 0:
        return False

    def negative(terms):
        return mp.fsum(terms) < -tiny * mp.fsum(abs(x) for x in terms)

    # 1. the limit rows cancel what the other rows leave of G'y
    bound = {}  # (coordinate, +1 or -1) -> a row that is exactly that unit vector
    for i in range(n):
        nz = [j for j in range(dim) if Gm[i][j] != 0]
        if len(nz) == 1 and abs(Gm[i][nz[0]]) == 1:
            bound.setdefault((nz[0], int(mp.sign(Gm[i][nz[0]]))), i)
    box = set(bound.values())
    y = {int(i): mp.mpf(float(v / norm[i])) for i, v in zip(keep, lp.x, strict=True) if v > 0}
    y = {i: v for i, v in y.items() if i not in box}
    c = [mp.fsum(Gm[i][j] * v for i, v in y.items()) for j in range(dim)]
    terms = [rm[i] * v for i, v in y.items()]
    for j in range(dim):
        if c[j] != 0:
            row = bound.get((j, -int(mp.sign(c[j]))))
            if row is None:
                break
            terms.append(rm[row] * abs(c[j]))
    else:
        if y and negative(terms):
            return True

    # 2. y solved on the program's rows: G_S' y = 0 and sum_i norm_i y_i = 1
    support = keep[lp.x > 1e-9 * np.max(lp.x)]
    if len(support) > dim + 1:
        return False
    M = mp.matrix(dim + 1, len(support))
    for t, i in enumerate(support):
        for j in range(dim):
            M[j, t] = Gm[i][j]
        M[dim, t] = mp.mpf(float(norm[i]))
    try:
        ys = mp.qr_solve(M, mp.matrix([0] * dim + [1]))[0]
    except ZeroDivisionError:  # dependent rows on the support: no unique y to check
        return False
    ymax = max(abs(ys[t]) for t in range(len(support)))
    if any(ys[t] <= tiny * ymax for t in range(len(support))):
        return False
    for j in range(dim):
        col = [Gm[i][j] * ys[t] for t, i in enumerate(support)]
        if abs(mp.fsum(col)) > tiny * mp.fsum(abs(x) for x in col):
            return False
    return negative([rm[i] * ys[t] for t, i in enumerate(support)])


def solve_qp(Q, z0, G, r, hint=None, dps=60, certificate=True):
    """Exact minimiser of ``1/2 (z - z0)' Q (z - z0)`` s.t. ``G z <= r`` (Q positive definite).

    Every argument is exact (floats converted exactly, or mp numbers). The active set ``hint``
    (row indices) is tried first; otherwise every subset of at most ``dim`` rows is tried in
    ``dps`` digits, candidates ordered by a float64 score so that the optimum is found early.
    Returns ``(z, lam, S, cond)`` with the multipliers of the rows in ``S`` and the condition
    number of the active rows (see ``_condition``), or None if no subset is
    a KKT point (the rows are inconsistent: proven by a Farkas certificate where one is
    found, see :func:`proves_inconsistent`, otherwise by trying every subset;
    ``certificate=False`` always tries every subset). The KKT point of a strictly convex QP is
    unique, so the result does not depend on the order in which subsets are tried.
    """
    import itertools

    with mp.workdps(dps):
        n, dim = len(G), len(z0)
        Qm = mp.matrix([[_mp(x) for x in row] for row in Q])
        Qi = mp.inverse(Qm)
        z0m = mp.matrix([_mp(x) for x in z0])
        Gm = [[_mp(x) for x in row] for row in G]
        rm = [_mp(x) for x in r]
        tiny = mp.mpf(10) ** (25 - dps)

        # the Gram matrix of every row in the Q^-1 metric and the unconstrained residuals, once
        GT = mp.matrix([[Gm[i][j] for i in range(n)] for j in range(dim)]) if n and dim else None
        QiGT = Qi * GT if GT is not None else None
        P = GT.T * QiGT if GT is not None else None
        res0 = [mp.fsum(Gm[i][j] * z0m[j] for j in range(dim)) - rm[i] for i in range(n)]

        def attempt(S):
            if S and not dim:  # rows without columns: zero norms
                return None
            if S:
                k = len(S)
                M = mp.matrix([[P[i, j] for j in S] for i in S])
                nr2 = [M[i, i] for i in range(k)]
                if any(x == 0 for x in nr2):
                    return None
                # one LU factorisation gives the normalised determinant
                # det(M) / prod M_ii (the Gram matrix of the unit rows) and the multipliers
                try:
                    LU, piv = mp.mp.LU_decomp(M)
                except ZeroDivisionError:  # dependent rows: a smaller subset gives the point
                    return None
                det = mp.fprod(LU[i, i] for i in range(k)) / mp.fprod(nr2)
                if abs(det) < mp.mpf(10) ** (20 - 2 * dps):
                    return None
                lam = mp.mp.U_solve(LU, mp.mp.L_solve(LU, mp.matrix([res0[i] for i in S]), piv))
                z = z0m - mp.matrix(
                    [mp.fsum(QiGT[j, i] * lam[t] for t, i in enumerate(S)) for j in range(dim)]
                )
                lmax = max(abs(t) for t in lam)
                if any(t < -tiny * lmax for t in lam):
                    return None
                lam = [lam[i] for i in range(k)]
            else:
                z, lam = z0m, []
            for i in range(n):
                gz = mp.fsum(Gm[i][j] * z[j] for j in range(dim))
                scale = abs(rm[i]) + mp.fsum(abs(Gm[i][j] * z[j]) for j in range(dim))
                if gz - rm[i] > tiny * scale:
                    return None
            return [z[j] for j in range(dim)], lam, tuple(S), _condition(S)

        def _condition(S):
            """kappa(normalised Gram of the active rows in the Q^-1 metric) * kappa(Q)^(1/2)."""
            kq = mp.sqrt(mp.norm(Qm, 2) * mp.norm(Qi, 2)) if dim else mp.mpf(1)
            if not S:
                return float(kq)
            GS = mp.matrix([Gm[i] for i in S])
            M = GS * Qi * GS.T
            nr = [mp.sqrt(M[i, i]) for i in range(len(S))]
            Mn = mp.matrix(len(S), len(S))
            for i in range(len(S)):
                for j in range(len(S)):
                    Mn[i, j] = M[i, j] / (nr[i] * nr[j])
            ev = mp.eigsy(Mn)[0]
            lo = min(abs(ev[i]) for i in range(len(S)))
            hi = max(abs(ev[i]) for i in range(len(S)))
            return float(hi / lo * kq) if lo > 0 else float("inf")

        if hint is not None:
            found = attempt(tuple(hint))
            if found is not None:
                return found
        if certificate and proves_inconsistent(Gm, rm, dps):  # no KKT point: none to look for
            return None
        Gf = np.array([[float(x) for x in row] for row in Gm]).reshape(n, dim)
        rf = np.array([float(x) for x in rm])
        Qf = np.array([[float(Qm[i, j]) for j in range(dim)] for i in range(dim)])
        Qif = np.linalg.inv(Qf)
        z0f = np.array([float(x) for x in z0m])

        def score(S):
            if S:
                GS = Gf[list(S)]
                lam = np.linalg.lstsq(GS @ Qif @ GS.T, GS @ z0f - rf[list(S)], rcond=None)[0]
                z = z0f - Qif @ GS.T @ lam
                dual = np.max(np.maximum(-lam, 0)) / (np.max(np.abs(lam)) + 1e-300)
            else:
                z, dual = z0f, 0.0
            sc = np.abs(rf) + np.abs(Gf) @ np.abs(z) + 1e-300
            v = (np.max(np.maximum(Gf @ z - rf, 0) / sc) if n else 0.0) + dual
            return v if np.isfinite(v) else np.inf

        subsets = [S for s in range(min(n, dim) + 1) for S in itertools.combinations(range(n), s)]
        with np.errstate(all="ignore"):
            subsets.sort(key=lambda S: (score(S), len(S)))
        for S in subsets:
            found = attempt(S)
            if found is not None:
                return found
        return None
