"""The price of robustness against the amount of data (safestab.montecarlo.price).

    python benchmarks/price_of_robustness.py --scenario stress --out results/price
    python benchmarks/price_of_robustness.py --scenario obstacle --out results/price \\
        --q 25 50 100 250 500 1000 2000 --datasets 20 --trials-per-dataset 4

For each data size ``Q`` the scenario's Monte Carlo study (its ``[montecarlo]`` table) runs
``--datasets`` independent data sets with ``--trials-per-dataset`` trials each, and every GP
controller is scored against the true-model controller on the same trials: the data sets in
which every trial was safe (exact interval over data sets) and the margin it paid
(``min h - min h_true``). Writes ``price_<scenario>.json`` (strict JSON) and
``price_<scenario>.png`` to ``--out``, atomically, and prints a table. docs/price.md is
written from the JSON by ``bash scripts/reproduce-docs.sh --only price``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

from safestab._io import ensure_writable_dir, figure_writer, json_writer, write_all  # noqa: E402
from safestab.montecarlo.price import plot_price, price_study  # noqa: E402
from safestab.scenarios.loading import load  # noqa: E402

Q_VALUES = (25, 50, 100, 250, 500, 1000, 2000, 4000)


def table(doc: dict) -> str:
    """One row per size and GP controller: safe data sets and the median margin paid."""
    names = [n for n in doc["settings"]["controllers"] if n != doc["settings"]["reference"]]
    unit = doc["h_unit"]
    lines = [f"{'Q':>6}  {'controller':<20} {'safe data sets':>15}  {'95 % CI':>15}  "
             f"{'median min h excess (' + unit + ')':>28}"]  # fmt: skip
    for point in doc["points"]:
        for name in names:
            e = point["controllers"][name]
            s = e["safe_per_dataset"]
            lo, hi = s["ci95"]
            lines.append(f"{point['n_samples']:>6}  {name:<20} {s['count']:>7}/{s['datasets']:<7}"
                         f"  [{lo:.3f}, {hi:.3f}]  {e['min_h_excess']['0.5']:>28.4g}")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the study for one scenario and write its JSON and figure."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="stress", help="a preset with [montecarlo]")
    parser.add_argument("--q", type=int, nargs="+", default=list(Q_VALUES), help="data sizes")
    parser.add_argument("--datasets", type=int, default=30)
    parser.add_argument("--trials-per-dataset", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("results/price"))
    args = parser.parse_args(argv)
    out = ensure_writable_dir(args.out, "--out")  # before any work
    scenario = load(args.scenario)
    t0 = time.perf_counter()

    def progress(i: int, n: int, q: int) -> None:
        print(f"[{i + 1}/{n}] Q = {q} ({time.perf_counter() - t0:.0f} s)", flush=True)

    doc = price_study(
        scenario, args.q, datasets=args.datasets, trials_per_dataset=args.trials_per_dataset,
        seed=args.seed, progress=progress,
    )  # fmt: skip
    doc["command"] = "python benchmarks/price_of_robustness.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    doc["wall_s"] = time.perf_counter() - t0
    name = f"price_{scenario.name}"
    written = write_all({
        out / f"{name}.json": json_writer(doc),
        out / f"{name}.png": figure_writer(plot_price(doc), out / f"{name}.png", dpi=150,
                                               metadata={"Software": None}),
    })  # fmt: skip
    print(table(doc))
    print(f"{doc['wall_s']:.0f} s; wrote " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
