"""Benchmark rows of issue 10: several CBFs, with and without limits inside the problem.

``clf_cbf_multi``'s kernel (the dual active-set solver, jitted) against Clarabel and OSQP (through qpsolvers)
on the same random problems: one CLF with slack weight 10, ``k = 1, 2, 4`` CBFs, ``m = 2``
inputs, limits ``|u_i| <= 2`` or none (so 3 to 9 rows). Latency is the median of single
jitted calls (JAX dispatch included) cycling over 64 problems; the solvers get the same 64
problems with their rows prebuilt, so they are timed on the solve alone (qpsolvers' set-up
included, default tolerances). Throughput is one batched call over ``batch`` problems
(median of 5). The agreement columns give the largest ``|u_solver - u_closed|`` over the
problems that both solved (closed-form status ``SOLVED``, solver found a solution).

``python benchmarks/run.py --only multi`` (or ``python benchmarks/multi.py``) runs them and
writes ``docs/performance_multi.json`` and the block between the ``multi`` markers of
``docs/performance.md``.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import jax
import numpy as np

from _page import machine, median_us, save_results, update_block
from safestab.formulas import MultiStatus
from safestab.formulas.multi import multi_kernel

P = {"kappa": 0.5, "rho": 0.2, "phi": 1.0, "varphi": 0.5}
M = 2
SW = 10.0
BEGIN, END = "<!-- multi:begin -->", "<!-- multi:end -->"
COMMAND = "python benchmarks/run.py --only multi"


def _problems(rng, n, k):
    return (
        rng.standard_normal((n, 1)) * 3,
        rng.standard_normal((n, 1, M)),
        rng.standard_normal((n, k)) * 3,
        rng.standard_normal((n, k, M)),
    )


def _qp_rows(a, b, c, d, limits):
    """Rows of the QP in (u, chi) for qpsolvers (the margins through the public zeta)."""
    import safestab as ss

    A = float(a[0] + P["kappa"] * ss.zeta(a[0], b[0], P["phi"]))
    B = np.asarray(P["rho"] * ss.zeta(c, d, P["varphi"]) - c)
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


def _kernel(limits, batch_shape=()):
    inv = np.asarray(1.0 / np.sqrt(SW))
    lo = np.broadcast_to(-2.0 * np.ones(M), batch_shape + (M,)) if limits else None
    hi = np.broadcast_to(2.0 * np.ones(M), batch_shape + (M,)) if limits else None

    def fn(a, b, c, d):
        res = multi_kernel(
            a, b, c, d, P["kappa"], P["rho"], P["phi"], P["varphi"], inv, lo, hi, None, None
        )
        return res.u, res.status

    return jax.jit(fn)


def run(repeat: int = 300, batch: int = 10_000, seed: int = 0) -> list[dict]:
    """Measure every configuration; returns one row per (k, limits)."""
    import qpsolvers
    from scipy import sparse

    rng = np.random.default_rng(seed)
    rows = []
    empty = jax.jit(lambda a, b, c, d: a)
    floor = [tuple(x[0] for x in _problems(rng, 1, 1)) for _ in range(8)]
    floor_us = median_us(lambda s: jax.block_until_ready(empty(*s)), floor, repeat)
    Pm = sparse.csc_matrix(np.diag([1.0] * M + [SW]))
    q = np.zeros(M + 1)
    for k in (1, 2, 4):
        for limits in (False, True):
            fn = _kernel(limits)
            singles = [tuple(x[0] for x in _problems(rng, 1, k)) for _ in range(64)]
            closed_us = median_us(lambda s: jax.block_until_ready(fn(*s)), singles, repeat)
            closed = [fn(*s) for s in singles]
            big = _problems(rng, batch, k)
            fn_b = _kernel(limits, (batch,))
            jax.block_until_ready(fn_b(*big))
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                jax.block_until_ready(fn_b(*big))
                times.append(time.perf_counter() - t0)
            status_b = np.asarray(fn_b(*big)[1])
            row = {
                "k": k,
                "limits": limits,
                "rows": 1 + k + (2 * M if limits else 0),
                "closed_form_us": closed_us,
                "dispatch_floor_us": floor_us,
                "batched_per_s": batch / float(np.median(times)),
                "batch": batch,
                "solved_fraction": float(np.mean(status_b == MultiStatus.SOLVED)),
            }
            qps = [_qp_rows(*s, limits) for s in singles]
            for solver in ("clarabel", "osqp"):

                def solve(gh, solver=solver):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        return qpsolvers.solve_qp(
                            Pm, q, sparse.csc_matrix(gh[0]), gh[1], solver=solver
                        )

                row[f"{solver}_us"] = median_us(solve, qps, max(50, repeat // 3))
                row[f"{solver}_ratio"] = row[f"{solver}_us"] / closed_us
                diffs = []
                for gh, (u, status) in zip(qps, closed, strict=True):
                    sol = solve(gh)
                    if sol is not None and int(status) == MultiStatus.SOLVED:
                        diffs.append(float(np.max(np.abs(sol[:M] - np.asarray(u)))))
                row[f"{solver}_max_abs_du"] = max(diffs) if diffs else None
                row[f"{solver}_compared"] = len(diffs)
            rows.append(row)
            print(
                f"k={k} limits={limits}: {closed_us:.1f} us, {row['batched_per_s']:.3g}/s, "
                f"clarabel {row['clarabel_us']:.0f} us, osqp {row['osqp_us']:.0f} us",
                flush=True,
            )
    return rows


def markdown(results: dict) -> str:
    """The saved results as the Markdown block of docs/performance.md."""
    mach, rows = results["machine"], results["rows"]
    lines = [
        BEGIN,
        "## Several CBFs, limits inside the problem (`clf_cbf_multi`, issue 10)",
        "",
        "One CLF (slack weight 10), k CBFs, m = 2 inputs, limits |u_i| <= 2 or none; random "
        "problems (seed 0). Ours: one jitted call of the kernel per problem (JAX "
        "dispatch included), median over 64 problems cycled; Clarabel and OSQP through "
        "qpsolvers on the same 64 problems with their rows prebuilt (default tolerances). "
        f"Batched: one call over {rows[0]['batch']:,} problems, median of 5. "
        "*max abs du*: the largest input difference to ours where both solved. "
        f"Rerun with `{COMMAND}`.",
        "",
        f"Measured on {mach['platform']}, {mach['cpus']} CPUs, JAX {mach['jax']} on "
        f"{mach['device']}, load average {mach['load_average_at_start']:.1f} at the start "
        "(a shared machine: times are upper bounds, ratios are from the same run). An empty "
        "jitted call with the same four arguments (the dispatch floor) took "
        f"{rows[0]['dispatch_floor_us']:.1f} us in this run.",
        "",
        "| CBFs k | limits | rows | ours (us) | batched (problems/s) | solved | "
        "Clarabel (us) | OSQP (us) | Clarabel / ours | OSQP / ours | max abs du Clarabel | "
        "max abs du OSQP |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def du(v):
        return "n/a" if v is None else f"{v:.1e}"

    for r in rows:
        lines.append(
            f"| {r['k']} | {'yes' if r['limits'] else 'no'} | {r['rows']} | "
            f"{r['closed_form_us']:.1f} | {r['batched_per_s']:.3g} | "
            f"{100 * r['solved_fraction']:.1f} % | {r['clarabel_us']:.0f} | {r['osqp_us']:.0f} | "
            f"{r['clarabel_ratio']:.1f}x | {r['osqp_ratio']:.1f}x | "
            f"{du(r['clarabel_max_abs_du'])} | {du(r['osqp_max_abs_du'])} |"
        )
    lines += [
        "",
        "*solved*: share of the batched problems with status `SOLVED` (the rest used a named "
        "fallback: `CLF_DROPPED` or `CBF_RELAXED`, where a solver reports infeasibility). "
        "The fallback phases run only where a problem of the batch needs them; the last resort "
        "has k more coordinates (the CBF slacks). The solvers run at their default tolerances, where OSQP, a first-order "
        "method, stops at a much looser accuracy than Clarabel (the two agreement columns).",
        "",
        END,
    ]
    return "\n".join(lines)


def update_markdown(md_path: Path, json_path: Path) -> None:
    """Put the block for the saved results into performance.md (replacing an old one)."""
    update_block(md_path, json_path, markdown, BEGIN, END)


def main(out_dir: Path, repeat: int = 300, batch: int = 10_000) -> None:
    """Run the rows, save them to performance_multi.json and update performance.md."""
    results = {"machine": machine(), "command": COMMAND, "rows": run(repeat, batch)}
    save_results(out_dir, "performance_multi.json", results, markdown, BEGIN, END)


if __name__ == "__main__":
    main(Path(__file__).resolve().parent.parent / "docs")
