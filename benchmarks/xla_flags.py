"""Compilation and run time of the filter's solver with and without the XLA flag safestab sets
at import (``--xla_cpu_use_fusion_emitters=false``, safestab/_xla_flags.py).

    python benchmarks/xla_flags.py      # about 2 minutes on 2 CPUs

Each setting runs in a fresh process with the compilation cache off: safestab's default, and
``SAFESTAB_XLA_FLAGS=off`` (XLA's own default emitters). The processes alternate, twice each.
For each problem shape: lowering plus compilation of ``multi_kernel`` (jit), the best of 5
runs, and a hash of every output (the same hash: the same bits). Writes
``docs/performance_xla_flags.json`` and its block in ``docs/performance.md``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _page import machine, measured, save_results

BEGIN, END = "<!-- xla-flags:begin -->", "<!-- xla-flags:end -->"
ROOT = Path(__file__).resolve().parents[1]
#: (name, batch or 0 for one problem, CLFs p, CBFs k, inputs m, soft CLFs)
SHAPES = [
    ("one problem, 1 CLF, 1 CBF, m = 2, limits", 0, 1, 1, 2, False),
    ("one problem, 1 soft CLF, 4 CBFs, m = 2, limits", 0, 1, 4, 2, True),
    ("72 problems, 1 CLF, 1 CBF, m = 2, limits", 72, 1, 1, 2, False),
    ("10,000 problems, 1 CLF, 4 CBFs, m = 2, limits", 10_000, 1, 4, 2, False),
    ("10,000 problems, 8 CBFs, m = 2, limits", 10_000, 0, 8, 2, False),
]
SETTINGS = {
    "safestab's default (the flag set)": {},
    "SAFESTAB_XLA_FLAGS=off": {"SAFESTAB_XLA_FLAGS": "off"},
}
ROUNDS = 2


def _case(batch, p, k, m, slack, seed=0):
    import numpy as np

    rng = np.random.default_rng(seed)
    sh = (batch,) if batch else ()
    return (
        rng.normal(size=sh + (p,)), rng.normal(size=sh + (p, m)), rng.normal(size=sh + (k,)),
        rng.normal(size=sh + (k, m)), 1.0, 1.0, 0.0, 0.0, np.ones(p) if slack else None,
        -np.ones(m), np.ones(m), rng.normal(size=sh + (m,)), None,
    )  # fmt: skip


def child() -> dict:
    """One process: every shape's compile and run time, and its outputs' hash."""
    import jax
    import numpy as np

    import safestab  # noqa: F401  (the import sets the flag, or not)
    from safestab.formulas.multi import multi_kernel

    out = {"XLA_FLAGS": os.environ.get("XLA_FLAGS", ""), "shapes": []}
    for name, *shape in SHAPES:
        args = _case(*shape)
        t0 = time.perf_counter()
        compiled = jax.jit(multi_kernel).lower(*args).compile()
        compile_s = time.perf_counter() - t0
        res = jax.block_until_ready(compiled(*args))
        runs = []
        for _ in range(5):
            t0 = time.perf_counter()
            res = jax.block_until_ready(compiled(*args))
            runs.append(time.perf_counter() - t0)
        leaves = jax.tree_util.tree_leaves(res)
        digest = hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in leaves)).hexdigest()
        out["shapes"].append({"name": name, "compile_s": compile_s, "run_s": min(runs),
                              "sha256": digest[:16]})  # fmt: skip
    return out


def bench() -> dict:
    results: dict = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "runs": {}}
    for _ in range(ROUNDS):
        for setting, extra in SETTINGS.items():
            env = {
                k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "SAFESTAB_XLA_FLAGS")
            }
            env.update(extra, SAFESTAB_COMPILATION_CACHE="off")
            done = subprocess.run(
                [sys.executable, __file__, "--child"], env=env, capture_output=True, text=True,
                check=True, cwd=ROOT,
            )  # fmt: skip
            run = json.loads(done.stdout.strip().splitlines()[-1])
            if ("--xla_cpu_use_fusion_emitters=false" in run["XLA_FLAGS"]) != (not extra):
                raise SystemExit(f"{setting}: XLA_FLAGS={run['XLA_FLAGS']!r} (this jaxlib?)")
            results["runs"].setdefault(setting, []).append(run)
            total = sum(s["compile_s"] for s in run["shapes"])
            print(f"{setting}: compilation {total:.1f} s (XLA_FLAGS={run['XLA_FLAGS']!r})")
    results["load_average_at_end"] = os.getloadavg()[0]
    return results


def markdown(r: dict) -> str:
    names = list(r["runs"])
    ours, off = (r["runs"][n] for n in names)

    def best(runs, i, key):
        return min(run["shapes"][i][key] for run in runs)

    lines = [
        BEGIN,
        "## XLA's fusion emitters (`python benchmarks/xla_flags.py`)",
        "",
        f"{measured(r)} and {r['load_average_at_end']:.1f} at the end. The filter's solver "
        "(`multi_kernel`, random problems, seed 0) compiled and run in fresh processes with "
        f"the compilation cache off, alternating, {len(ours)} processes per setting; the best "
        "of them. *ours*: safestab's default, which adds `--xla_cpu_use_fusion_emitters=false` "
        "to `XLA_FLAGS` at import (`safestab/_xla_flags.py`); *XLA's*: "
        "`SAFESTAB_XLA_FLAGS=off`, XLA's newer fusion emitters. *same bits*: every output "
        "identical in every process.",
        "",
        "| problem | compile, ours (s) | compile, XLA's (s) | ratio | run, ours (ms) "
        "| run, XLA's (ms) | same bits |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for i, shape in enumerate(ours[0]["shapes"]):
        c1, c2 = best(ours, i, "compile_s"), best(off, i, "compile_s")
        r1, r2 = best(ours, i, "run_s") * 1e3, best(off, i, "run_s") * 1e3
        same = len({run["shapes"][i]["sha256"] for run in ours + off}) == 1
        lines.append(f"| {shape['name']} | {c1:.2f} | {c2:.2f} | {c2 / c1:.1f}x | {r1:.3g} "
                     f"| {r2:.3g} | {'yes' if same else 'no'} |")  # fmt: skip
    return "\n".join([*lines, "", END])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child()))
        return
    save_results(args.out, "performance_xla_flags.json", bench(), markdown, BEGIN, END)


if __name__ == "__main__":
    main()
