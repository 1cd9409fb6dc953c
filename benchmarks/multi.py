"""Benchmark rows of issue 10: several CBFs, with and without limits inside the problem.

``clf_cbf_multi`` (closed form, jitted) against Clarabel and OSQP (through qpsolvers) on the
same random problems: one CLF with slack weight 10, ``k = 1, 2, 4`` CBFs, ``m = 2`` inputs,
limits ``|u_i| <= 2`` or none. Latency is the median of single calls; throughput is one
batched call over 10,000 problems. ``python benchmarks/multi.py`` prints the table; ``run.py``
includes it in docs/performance.md.
"""

from __future__ import annotations

import time
import warnings

import jax
import numpy as np

from safestab.formulas.multi import multi_kernel

P = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}
M = 2
SW = 10.0


def _problems(rng, n, k):
    return (
        rng.standard_normal((n, 1)) * 3,
        rng.standard_normal((n, 1, M)),
        rng.standard_normal((n, k)) * 3,
        rng.standard_normal((n, k, M)),
    )


def _qp_rows(a, b, c, d, limits):
    """Rows of the QP in (u, chi) for qpsolvers (margins as in the closed form)."""
    from safestab.formulas._kernels import margins

    A = float(margins(a, b, a, b, P["kappa"], 0.0, P["phi"], 0.0).A[0])
    B = np.asarray(margins(c, d, c, d, 0.0, P["rho"], 0.0, P["varphi"]).B)
    G = [np.append(b[0], -1.0)]
    h = [-A]
    for i in range(d.shape[0]):
        G.append(np.append(-d[i], 0.0))
        h.append(-B[i])
    if limits:
        for t in range(M):
            e = np.zeros(M + 1)
            e[t] = 1.0
            G += [e, -e]
            h += [2.0, 2.0]
    return np.asarray(G), np.asarray(h)


def _median_us(fn, args, repeat):
    for x in args[:3]:
        fn(x)
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        fn(args[i % len(args)])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def run(repeat: int = 300, batch: int = 10_000, seed: int = 0) -> list[dict]:
    """Measure every configuration; returns one row per (k, limits)."""
    import qpsolvers
    from scipy import sparse

    rng = np.random.default_rng(seed)
    rows = []
    for k in (1, 2, 4):
        for limits in (False, True):
            lo = -2.0 * np.ones(M) if limits else None
            hi = 2.0 * np.ones(M) if limits else None
            inv = np.asarray(1.0 / np.sqrt(SW))
            fn = jax.jit(
                lambda a, b, c, d, lo=lo, hi=hi: multi_kernel(
                    a, b, c, d, P["kappa"], P["rho"], P["phi"], P["varphi"], inv, lo, hi, None, None
                ).u
            )
            singles = [tuple(x[0] for x in _problems(rng, 1, k)) for _ in range(64)]
            closed_us = _median_us(lambda s: jax.block_until_ready(fn(*s)), singles, repeat)
            big = _problems(rng, batch, k)
            if limits:
                lo_b, hi_b = np.broadcast_to(lo, (batch, M)), np.broadcast_to(hi, (batch, M))
                fn_b = jax.jit(
                    lambda a, b, c, d: multi_kernel(
                        a, b, c, d, P["kappa"], P["rho"], P["phi"], P["varphi"], inv, lo_b, hi_b, None, None
                    ).u
                )
            else:
                fn_b = jax.jit(
                    lambda a, b, c, d: multi_kernel(
                        a, b, c, d, P["kappa"], P["rho"], P["phi"], P["varphi"], inv, None, None, None, None
                    ).u
                )
            jax.block_until_ready(fn_b(*big))
            t0 = time.perf_counter()
            jax.block_until_ready(fn_b(*big))
            throughput = batch / (time.perf_counter() - t0)
            row = {"k": k, "limits": limits, "closed_form_us": closed_us, "batched_per_s": throughput}
            for solver in ("clarabel", "osqp"):
                qps = [_qp_rows(*s, limits) for s in singles]
                Pm = sparse.csc_matrix(np.diag([1.0] * M + [SW]))
                q = np.zeros(M + 1)

                def solve(gh, solver=solver, Pm=Pm, q=q):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        return qpsolvers.solve_qp(Pm, q, sparse.csc_matrix(gh[0]), gh[1], solver=solver)

                row[f"{solver}_us"] = _median_us(solve, qps, max(50, repeat // 3))
                row[f"{solver}_ratio"] = row[f"{solver}_us"] / closed_us
            rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = [
        "| CBFs k | limits in problem | closed form (us) | batched (problems/s) | Clarabel (us) | OSQP (us) | Clarabel / closed | OSQP / closed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['k']} | {'yes' if r['limits'] else 'no'} | {r['closed_form_us']:.1f} | "
            f"{r['batched_per_s']:.3g} | {r['clarabel_us']:.1f} | {r['osqp_us']:.1f} | "
            f"{r['clarabel_ratio']:.1f}x | {r['osqp_ratio']:.1f}x |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown(run()))
