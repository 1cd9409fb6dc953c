"""Random filter problems at wide scales and their 50-digit reference answers.

Shared by the solver's property tests (``test_dual_active_set.py``) and the benchmark's
accuracy column. A case is a dict of plain floats: Lie terms ``a`` (p,), ``b`` (p, m), ``c``
(k,), ``d`` (k, m), the four parameters, and optionally ``sw`` (slack weight), ``lo``/``hi``,
``u_nom``, ``H``. Geometries: generic rows, near-parallel and antiparallel rows, duplicated
rows, rows scaled from 1e-6 to 1e6, and deliberately inconsistent barriers.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np

from . import mpref

GEOMETRIES = ("generic", "scaled", "nearpar", "antipar", "duplicate", "conflict")
FALLBACK_WEIGHT = 1e8  # safestab.formulas.multi.FALLBACK_WEIGHT, restated as the spec


#: Shapes drawn from (p CLFs, k CBFs, m inputs, slack weight or None, limits, weighted H):
#: a fixed list, so that a test compiles the solver a dozen times, not once per case.
SIGNATURES = (
    (0, 1, 1, None, True, False),
    (0, 2, 1, None, True, False),
    (0, 3, 2, None, True, True),
    (0, 4, 3, None, True, False),
    (1, 1, 2, None, True, True),
    (1, 2, 2, None, True, False),
    (1, 3, 3, 10.0, False, False),
    (1, 4, 2, 1e4, True, False),
    (2, 2, 1, None, False, False),
    (2, 3, 3, None, False, True),
    (2, 4, 3, 1e-2, True, True),
    (2, 4, 2, None, True, True),
)


def random_case(rng: np.random.Generator, geometry: str, signature: tuple) -> dict:
    p, k, m, sw, limits, weighted = signature
    scale = 10.0 ** rng.uniform(-6, 6) if geometry == "scaled" else 1.0
    b = rng.standard_normal((p, m)) * scale
    d = rng.standard_normal((k, m)) * (
        10.0 ** rng.uniform(-6, 6, (k, 1)) if geometry == "scaled" else 1
    )
    a = rng.standard_normal(p) * 3 * scale
    c = (rng.standard_normal(k) * 3 + 2) * (
        np.linalg.norm(d, axis=1) if geometry == "scaled" else 1
    )
    if k >= 2 and geometry in ("nearpar", "antipar", "duplicate", "conflict"):
        sign = -1.0 if geometry in ("antipar", "conflict") else 1.0
        exact = geometry in ("duplicate", "conflict")  # a power of two: the rows stay exact
        s = 2.0 ** int(rng.integers(-10, 11)) if exact else 10.0 ** rng.uniform(-3, 3)
        eps = 0.0 if exact else 10.0 ** rng.uniform(-12, -4)
        d[1] = sign * d[0] * s + eps * rng.standard_normal(m)
        if geometry == "duplicate":
            c[1] = c[0] * s
        if geometry == "conflict":  # d0.u >= -c0 and d0.u <= -c0 - gap: inconsistent
            c[1] = -c[0] * s - 10.0 ** rng.uniform(-8, 0) * s
    if p >= 1 and m >= 1 and geometry == "nearpar" and k >= 1:
        b[0] = -d[0] * 10.0 ** rng.uniform(-2, 2) + 1e-7 * rng.standard_normal(m)
    case = {
        "a": a.tolist(), "b": b.tolist(), "c": c.tolist(), "d": d.tolist(), "m": m,
        "kappa": float(rng.uniform(0, 1)), "rho": float(rng.uniform(0, 1)),
        "phi": float(rng.uniform(0, 2)), "varphi": float(rng.uniform(0, 2)),
        "geometry": geometry,
    }  # fmt: skip
    if geometry == "conflict":
        case["rho"] = 0.0
    if sw is not None:
        case["sw"] = sw
    if limits:
        half = 10.0 ** rng.uniform(-1, 3)
        centre = rng.standard_normal(m) * half * 0.5
        case["lo"], case["hi"] = (centre - half).tolist(), (centre + half).tolist()
    far = rng.uniform() < 0.6
    case["u_nom"] = (rng.standard_normal(m) * 10.0 ** rng.uniform(-3, 6) * far).tolist()
    if weighted:
        X = rng.standard_normal((m, m))
        Qo, _ = np.linalg.qr(X)
        ev = 10.0 ** rng.uniform(-3, 3, m)
        H = Qo @ np.diag(ev) @ Qo.T
        case["H"] = ((H + H.T) / 2).tolist()
    return case


def kwargs(case: dict) -> dict:
    kw = {k: case[k] for k in ("kappa", "rho", "phi", "varphi")}
    if "sw" in case:
        kw["slack_weight"] = case["sw"]
    if "lo" in case:
        kw["u_min"], kw["u_max"] = np.array(case["lo"]), np.array(case["hi"])
    if "u_nom" in case:
        kw["u_nom"] = np.array(case["u_nom"])
    if "H" in case:
        kw["H"] = np.array(case["H"])
    return kw


def arrays(case: dict) -> tuple:
    m = case["m"]
    return (
        np.array(case["a"], float).reshape(-1),
        np.array(case["b"], float).reshape(-1, m),
        np.array(case["c"], float).reshape(-1),
        np.array(case["d"], float).reshape(-1, m),
    )


def _problem(case: dict, phase: str):
    """Rows ``G z <= r``, ``Q``, ``z0`` in mp numbers for a phase: "full", "no_clf", "relaxed"."""
    a, b, c, d = arrays(case)
    p, m, k = len(a), case["m"], len(c)
    A = [
        mpref.margins(a[j], b[j], 0.0, b[j], case["kappa"], 0.0, case["phi"], 0.0)[0]
        for j in range(p)
    ]
    B = [
        mpref.margins(0.0, d[i], c[i], d[i], 0.0, case["rho"], 0.0, case["varphi"])[1]
        for i in range(k)
    ]
    H = np.array(case["H"]) if "H" in case else np.eye(m)
    mp0 = mp.mpf(0)
    soft = "sw" in case and phase == "full"
    extra = p if soft else (k if phase == "relaxed" else 0)
    dim = m + extra
    G, r = [], []
    if phase == "full":
        for j in range(p):
            row = [mp.mpf(float(x)) for x in b[j]] + [mp0] * extra
            if soft:
                row[m + j] = mp.mpf(-1)
            G.append(row)
            r.append(-A[j])
    Hm = mp.matrix([[mp.mpf(float(x)) for x in row] for row in H])
    Hi = mp.inverse(Hm)
    for i in range(k):
        row = [-mp.mpf(float(x)) for x in d[i]] + [mp0] * extra
        if phase == "relaxed":
            row[m + i] = mp.mpf(-1)
        G.append(row)
        r.append(-B[i])
    if "lo" in case:
        for sign, bound in ((1, case["hi"]), (-1, case["lo"])):
            for t in range(m):
                row = [mp0] * dim
                row[t] = mp.mpf(sign)
                G.append(row)
                r.append(sign * mp.mpf(bound[t]))
    Q = mp.zeros(dim, dim)
    for i in range(m):
        for j in range(m):
            Q[i, j] = Hm[i, j]
    if soft:
        for j in range(p):
            Q[m + j, m + j] = mp.mpf(case["sw"])
    if phase == "relaxed":
        # the stated penalised problem: weight W / |d_i|^2_{H^-1} on the CBF violation sigma_i
        for i in range(k):
            dv = mp.matrix([mp.mpf(float(x)) for x in d[i]])
            norm2 = (dv.T * Hi * dv)[0]
            Q[m + i, m + i] = mp.mpf(FALLBACK_WEIGHT) / norm2 if norm2 > 0 else mp.mpf(1)
    z0 = [mp.mpf(x) for x in case.get("u_nom", [0.0] * m)] + [mp0] * extra
    Ql = [[Q[i, j] for j in range(dim)] for i in range(dim)]
    return G, r, Ql, z0


def reference(case: dict, hint=None):
    """``(status_name, u, z, active_set, cond)``: SOLVED, CLF_DROPPED or CBF_RELAXED.

    ``hint``: an active set to try first (indices over the rows CLFs, CBFs, upper, lower
    limits), mapped to each phase's rows; it only orders the search.
    """
    p = len(case["a"])
    later = None if hint is None else [i - p for i in hint if i >= p]
    with mp.workdps(60):
        G, r, Q, z0 = _problem(case, "full")
        found = mpref.solve_qp(Q, z0, G, r, hint=hint)
        if found is not None:
            return "SOLVED", found[0][: case["m"]], *found[:1], *found[2:]
        if len(case["a"]) and "sw" not in case:
            G, r, Q, z0 = _problem(case, "no_clf")
            found = mpref.solve_qp(Q, z0, G, r, hint=later)
            if found is not None:
                return "CLF_DROPPED", found[0][: case["m"]], *found[:1], *found[2:]
        G, r, Q, z0 = _problem(case, "relaxed")
        found = mpref.solve_qp(Q, z0, G, r, hint=later)
        assert found is not None, "the relaxed problem is always feasible"
        return "CBF_RELAXED", found[0][: case["m"]], *found[:1], *found[2:]


def violations(case: dict, u, chi=None) -> dict:
    """Exact violation of each condition over its own magnitudes (> 0: violated)."""
    a, b, c, d = arrays(case)
    out = {}
    with mp.workdps(60):
        um = [mp.mpf(float(x)) for x in u]
        for j in range(len(a)):
            A, _, zeta, _ = mpref.margins(
                a[j], b[j], 0.0, b[j], case["kappa"], 0.0, case["phi"], 0.0
            )
            bu = [mp.mpf(float(x)) * y for x, y in zip(b[j], um, strict=True)]
            ch = mp.mpf(float(chi[j])) if chi is not None else mp.mpf(0)
            res = A + mp.fsum(bu) - ch
            sc = (
                abs(mp.mpf(float(a[j])))
                + case["kappa"] * zeta
                + mp.fsum(abs(t) for t in bu)
                + abs(ch)
            )
            out[("clf", j)] = float(res / sc) if sc > 0 else float(res)
        for i in range(len(c)):
            _, B, _, Gamma = mpref.margins(
                0.0, d[i], c[i], d[i], 0.0, case["rho"], 0.0, case["varphi"]
            )
            du = [mp.mpf(float(x)) * y for x, y in zip(d[i], um, strict=True)]
            res = B - mp.fsum(du)
            sc = abs(mp.mpf(float(c[i]))) + case["rho"] * Gamma + mp.fsum(abs(t) for t in du)
            out[("cbf", i)] = float(res / sc) if sc > 0 else float(res)
        if "lo" in case:
            for t in range(case["m"]):
                out[("hi", t)] = float(um[t] - mp.mpf(case["hi"][t]))
                out[("lo", t)] = float(mp.mpf(case["lo"][t]) - um[t])
    return out


def solve_cases(cases: list[dict], solver) -> list[tuple]:
    """``(u, status, slack, active)`` per case from ``solver`` (``clf_cbf_multi``), batched."""
    groups: dict[tuple, list[int]] = {}
    for i, case in enumerate(cases):
        key = (
            len(case["a"]), len(case["c"]), case["m"], case.get("sw"), "lo" in case,
            "u_nom" in case, "H" in case,
        )  # fmt: skip
        groups.setdefault(key, []).append(i)
    out: list[tuple] = [None] * len(cases)  # type: ignore[list-item]
    for key, idx in groups.items():
        sub = [cases[i] for i in idx]
        stack = lambda f: np.stack([f(c) for c in sub])  # noqa: E731
        a, b, c, d = (stack(lambda cs, t=t: arrays(cs)[t]) for t in range(4))
        kw = {
            name: stack(lambda cs, n=name: np.asarray(cs[n]))
            for name in ("kappa", "rho", "phi", "varphi")
        }
        if key[3] is not None:
            kw["slack_weight"] = key[3]
        if key[4]:
            kw["u_min"], kw["u_max"] = (
                stack(lambda cs: np.array(cs["lo"])),
                stack(lambda cs: np.array(cs["hi"])),
            )
        if key[5]:
            kw["u_nom"] = stack(lambda cs: np.array(cs["u_nom"]))
        if key[6]:
            kw["H"] = stack(lambda cs: np.array(cs["H"]))
        res = solver(a, b, c, d, **kw)
        for t, i in enumerate(idx):
            active = tuple(int(j) for j in np.flatnonzero(np.asarray(res.active[t])))
            out[i] = (np.asarray(res.u[t]), int(res.status[t]), np.asarray(res.slack[t]), active)
    return out


def judge(case: dict, u, status: str, slack, active=None, rtol_sat: float = 1e-13) -> dict:
    """Compare one answer with the reference: a dict of findings (empty lists: all good)."""
    ref_status, u_ref, z_ref, _, cond = reference(case, hint=active)
    chi = slack if "sw" in case else None
    v = violations(case, u, chi)
    out = {"ref": ref_status, "status": status}
    out["limits_broken"] = any(val > 0 for key, val in v.items() if key[0] in ("hi", "lo"))
    u_ref_f = np.array([float(x) for x in u_ref])
    scale = max(np.max(np.abs(u_ref_f)), 1e-300)
    out["rel_error"] = float(np.max(np.abs(np.asarray(u) - u_ref_f)) / scale)
    # the error that the data's rounding alone allows: eps * cond * the magnitudes that enter
    mags = [np.max(np.abs(u_ref_f)), np.max(np.abs(case["u_nom"]))]
    if "lo" in case:
        mags.append(np.max(np.abs(case["lo"] + case["hi"])))
    # the slacks are part of the solution: its size in the objective's metric counts too
    # (a tiny u beside a large weighted slack is accurate relative to the whole solution)
    phase = {"SOLVED": "full", "CLF_DROPPED": "no_clf", "CBF_RELAXED": "relaxed"}[ref_status]
    with mp.workdps(60):
        _, _, Q, _ = _problem(case, phase)
        m = case["m"]
        mags += [float(mp.sqrt(Q[i][i]) * abs(z_ref[i])) for i in range(m, len(z_ref))]
    out["cond"] = cond
    out["error_over_eps_cond"] = (
        float(np.max(np.abs(np.asarray(u) - u_ref_f)) / (np.finfo(float).eps * cond * max(mags)))
        if max(mags) > 0 and np.isfinite(cond)
        else 0.0
    )
    if status == "SOLVED":
        out["violated"] = [
            key for key, val in v.items() if key[0] in ("clf", "cbf") and val > rtol_sat
        ]
    elif status == "CLF_DROPPED":
        out["violated"] = [key for key, val in v.items() if key[0] == "cbf" and val > rtol_sat]
    else:
        out["violated"] = []
    return out
