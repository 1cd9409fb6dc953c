"""The exact GP in a closed loop: the cost of one step's posterior, by triangular solve.

    python benchmarks/gp_step.py

The ACC ``paper`` preset's GP (3 components, Q = 2,000; fitted as ``safestab run`` fits
it) evaluated at one state per step inside a ``lax.scan`` of 400 steps, the model's arrays
arguments of the compiled loop (as :func:`~safestab.simulate` passes them): the mean and std
with the factor as row panels of 64 to 500 rows (``_posterior.solve_panels``; the package
uses ``PANEL_ROWS``), with XLA's solve of the whole factor (the package before), and a
product with the whole factor (what an explicit inverse would cost; not used: it loses the
solve's backward stability). Then the preset's whole GP-robust closed loop (80 s at
100 Hz) through :func:`~safestab.simulate`, a first call (tracing and compiling, no
persistent cache) and a second. Writes ``docs/performance_gp_step.json`` and its block in
``docs/performance.md``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

BEGIN, END = "<!-- gp-step:begin -->", "<!-- gp-step:end -->"
ROOT = Path(__file__).resolve().parents[1]
STEPS = 400


def _per_step_ms(fn, model, x0, repeat: int = 5) -> float:
    """Median ms per step of ``fn(model, x)`` in a scan of STEPS steps (compiled once)."""
    import jax
    import numpy as np

    def loop(m, x):
        def body(c, _):
            return c + 1e-12 * fn(m, c), None

        return jax.lax.scan(body, x, None, length=STEPS)[0]

    f = jax.jit(loop)
    f(model, x0).block_until_ready()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f(model, x0).block_until_ready()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) / STEPS * 1e3)


def bench() -> dict:
    os.environ["SAFESTAB_COMPILATION_CACHE"] = "0"  # compile times without a persistent cache
    import jax.numpy as jnp
    import numpy as np

    from _page import machine
    from safestab.learning._posterior import PANEL_ROWS, exact_point, panels
    from safestab.scenarios.acc_study import collect_study_data, fit_study_gp, study_controllers
    from safestab.scenarios.loading import load
    from safestab.simulation import simulate

    sc = load("paper")
    train, _ = collect_study_data(sc)
    gp = fit_study_gp(sc, train)
    x0 = jnp.asarray(sc.x0)
    kind, n = gp.kernel, gp.n_states_

    post = dict(gp.posterior_)
    rows = {}
    for r in (64, 128, 256, 500):
        pan = panels(gp.chol_, r)
        rows[f"panels of {r} rows"] = _per_step_ms(
            lambda m, x: exact_point(m, x, kind, n)[1], {**post, "panels": pan}, x0
        )
        print(f"panels of {r} rows", rows[f"panels of {r} rows"])
    rows["whole factor, XLA triangular solve"] = _per_step_ms(
        lambda m, x: exact_point(m, x, kind, n)[1], post, x0
    )
    rows["whole factor, matrix-vector product"] = _per_step_ms(
        lambda m, x: jnp.sum(jnp.einsum("cij,cj->ci", m["chol"], m["alpha"] + 1e-12 * x[0]), 1),
        post,
        x0,
    )
    print(rows)
    ctrl = study_controllers(sc, gp)["GP-robust"]
    loop = []
    for _ in range(2):
        t0 = time.perf_counter()
        traj = simulate(
            ctrl, np.asarray(sc.x0), t_final=sc.t_final, dt=sc.dt, plant=sc.system("true"),
            exogenous=sc.exogenous,
        )  # fmt: skip
        traj.h.block_until_ready()
        loop.append(time.perf_counter() - t0)
    print("closed loop", loop)
    return {
        "machine": machine(), "date": time.strftime("%Y-%m-%d"), "q": len(train),
        "components": len(gp.components_), "steps": STEPS, "panel_rows": PANEL_ROWS,
        "per_step_ms": rows, "closed_loop_s": loop, "closed_loop_steps": len(traj.t) - 1,
    }  # fmt: skip


def markdown(r: dict) -> str:
    from _page import measured

    per = r["per_step_ms"]
    base = per["whole factor, XLA triangular solve"]
    lines = [
        BEGIN,
        "## The exact GP in a closed loop (`python benchmarks/gp_step.py`)",
        "",
        f"{measured(r)}. The ACC `paper` preset's GP ({r['components']} components, "
        f"Q = {r['q']:,}): its mean and std at one state per step of a compiled loop "
        f"({r['steps']} steps), the model's arrays arguments of the loop. The package solves "
        f"with the factor as row panels of {r['panel_rows']} rows (a blocked forward "
        "substitution, backward stable as the unblocked one); the product with the whole "
        "factor is the cost of an explicit inverse, which the package does not use.",
        "",
        "| posterior std by | ms per step | vs XLA's solve |",
        "|---|---:|---:|",
    ]
    for name, ms in per.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / base:.2f}x |")
    first, second = r["closed_loop_s"]
    lines += [
        "",
        f"The preset's GP-robust closed loop ({r['closed_loop_steps']:,} steps, "
        f"`simulate`): {first:.1f} s on the first call (tracing and compiling, no persistent "
        f"cache), {second:.1f} s on the second.",
        "",
        END,
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args()
    from _page import save_results

    save_results(args.out, "performance_gp_step.json", bench(), markdown, BEGIN, END)


if __name__ == "__main__":
    main()
