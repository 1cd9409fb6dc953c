"""Rerun the studies behind the docs' result tables and figures, and rewrite them in place.

    bash scripts/reproduce-docs.sh                 # every quick study (about 12 min here)
    bash scripts/reproduce-docs.sh --long          # also the 1,000-data-set Monte Carlo (15 min)
    bash scripts/reproduce-docs.sh --only mc-presets obstacle
    bash scripts/reproduce-docs.sh --check         # then fail if a generated table changed

A generated table sits in a page between ``<!-- generated: NAME -->`` and
``<!-- end generated -->``; this script writes it from the result files of its step, never
by hand. Each step's figures are copied into docs/figures. Timing tables (docs/performance*.md)
are measurements of a time and place and are left alone (``scripts/run-benchmarks.sh``
rewrites them). The script prints what it reran and how long each step took, and the pages
whose tables are still typed by hand.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
SAFESTAB = [sys.executable, "-m", "safestab.cli"]
MC_CONTROLLERS = (
    "true model,mismatched model,GP mean,GP-robust,GP-robust Lemma 2,GP-robust conformal"
)
#: Pages with result tables this script does not write yet (typed from a result file).
BY_HAND = {
    "docs/acc.md": "the ACC study's tables (safestab run --scenario paper / stress)",
    "docs/swarm.md": "the swarm's table (safestab run --scenario swarm)",
}
BLOCK = re.compile(r"(<!-- generated: ([\w.-]+) -->\n)(.*?)(<!-- end generated -->)", re.S)


def blocks(text: str) -> dict[str, str]:
    """The generated blocks of a page, by name."""
    return {m.group(2): m.group(3) for m in BLOCK.finditer(text)}


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with block ``name``'s content replaced by ``body`` (which ends in a newline).

    Raises
    ------
    KeyError
        If the page has no block of that name.
    """
    found = False

    def sub(m: re.Match) -> str:
        nonlocal found
        if m.group(2) != name:
            return m.group(0)
        found = True
        return m.group(1) + body + m.group(4)

    out = BLOCK.sub(sub, text)
    if not found:
        raise KeyError(f"no block '<!-- generated: {name} -->' in the page")
    return out


# -- tables ------------------------------------------------------------------------------


def _table(header: list[str], align: list[str], rows: list[list[str]]) -> str:
    """A Markdown table: ``align`` holds each column's rule (``---`` or ``---:``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def obstacle_table(doc: dict) -> str:
    """The obstacle page's outcome table from a metrics document."""
    rows = []
    for key, run in doc["runs"].items():
        name, limits = key.split(" / ")
        o, stuck = run["outcomes"], run["stuck"]
        both = sum(not s["end_flag_compatible"] and not s["end_verdict_compatible"] for s in stuck)
        rows.append([
            name, "none" if limits == "no limits" else "+-1.5 m/s",
            *(str(o[k]) for k in ("converged", "stuck", "unsafe", "moving")),
            f"{run['min_h_m2']:.3f}", f"{both} / {len(stuck)}" if stuck else "-",
        ])  # fmt: skip
    header = ["controller", "limits", "converged", "stuck", "unsafe", "moving", "min h (m^2)",
              "stuck ends incompatible"]  # fmt: skip
    return _table(header, ["---"] * 2 + ["---:"] * 6, rows)


def obstacle_seed_table(docs: list[dict]) -> str:
    """The GP-robust controller without limits over data seeds."""
    rows = []
    for doc in docs:
        run = doc["runs"]["GP-robust / no limits"]
        o = run["outcomes"]
        rows.append([
            str(doc["settings"]["seed"]), f"{o['converged']} / {o['stuck']} / {o['moving']}",
            f"{run['min_h_m2']:.3f}", f"{run['max_abs_u_mps']:.1f}",
        ])  # fmt: skip
    header = ["data seed", "GP-robust, no limits: converged / stuck / moving", "min h (m^2)",
              "largest input (m/s)"]  # fmt: skip
    return _table(header, ["---:", "---", "---:", "---:"], rows)


def gp_coverage_table(rows: list[dict]) -> str:
    """docs/learning.md's coverage table from benchmarks/gp_coverage.py's --json rows."""
    keys = ("state_coverage_chosen", "state_coverage_conformal", "trajectory_coverage_chosen",
            "trajectory_coverage_conformal")  # fmt: skip
    body = [[str(r["seed"]), f"{r['beta_conformal']:.2f}", *(f"{r[k]:.3f}" for k in keys),
             f"{r['max_score']:.2f}"] for r in rows]  # fmt: skip
    header = ["data seed", "conformal beta", "states in band, beta = 2",
              "states in band, conformal", "trajectories entirely in band, beta = 2",
              "trajectories entirely in band, conformal",
              "max over components of abs(omega - m)/sigma"]  # fmt: skip
    return _table(header, ["---:"] * 7, body)


def mc_table(doc: dict) -> str:
    """A Monte Carlo metrics document's table (safestab.montecarlo.report.markdown_table)."""
    from safestab.montecarlo.report import markdown_table

    return markdown_table(doc)


# -- steps -------------------------------------------------------------------------------


def _run(cmd: list[str]) -> None:
    print("  $ " + shlex.join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def _load(path: Path) -> dict:
    return json.loads(path.read_text())


def step_obstacle(out: Path) -> dict[str, tuple[str, str]]:
    """The obstacle preset (main job): its outcome table and both figures."""
    folder = out / "obstacle"
    _run([*SAFESTAB, "run", "--scenario", "obstacle", "--out", str(folder)])
    for src, dst in (("obstacle_obstacle.png", "obstacle.png"),
                     ("obstacle_obstacle_maps.png", "obstacle_maps.png")):  # fmt: skip
        shutil.copyfile(folder / src, DOCS / "figures" / dst)
    doc = _load(folder / "obstacle_obstacle_metrics.json")
    return {"obstacle-outcomes": ("docs/obstacle.md", obstacle_table(doc))}


def step_obstacle_seeds(out: Path) -> dict[str, tuple[str, str]]:
    """The obstacle preset at data seeds 0 to 4: the GP-robust rows' spread."""
    docs = []
    for seed in range(5):
        folder = out / f"obstacle-seed{seed}"
        _run([*SAFESTAB, "run", "--scenario", "obstacle", "--seed", str(seed), "--out",
              str(folder)])  # fmt: skip
        docs.append(_load(folder / "obstacle_obstacle_metrics.json"))
    return {"obstacle-seeds": ("docs/obstacle.md", obstacle_seed_table(docs))}


def step_mc_presets(out: Path) -> dict[str, tuple[str, str]]:
    """The three 200-trial, 2-data-set Monte Carlo runs: tables and figures."""
    tables = {}
    folder = out / "mc"
    for preset in ("stress", "paper", "stress-ood"):
        _run([*SAFESTAB, "mc", "--scenario", preset, "--trials", "200", "--datasets", "2",
              "--out", str(folder), "--seed", "0"])  # fmt: skip
        shutil.copyfile(folder / f"mc_{preset}.png", DOCS / "figures" / f"mc_{preset}.png")
        doc = _load(folder / f"mc_{preset}_metrics.json")
        tables[f"mc-{preset}"] = ("docs/montecarlo.md", mc_table(doc))
    return tables


def step_mc_datasets(out: Path) -> dict[str, tuple[str, str]]:
    """The 1,000-data-set stress study (--long): table, figure, summary JSON."""
    folder = out / "datasets"
    _run([*SAFESTAB, "mc", "--scenario", "stress", "--trials", "10000", "--datasets", "1000",
          "--controllers", MC_CONTROLLERS, "--out", str(folder)])  # fmt: skip
    shutil.copyfile(folder / "mc_stress.png", DOCS / "figures" / "mc_stress_datasets.png")
    doc = _load(folder / "mc_stress_metrics.json")
    (DOCS / "montecarlo_datasets.json").write_text(datasets_summary(folder))
    return {"mc-datasets": ("docs/montecarlo.md", mc_table(doc))}


def datasets_summary(folder: Path) -> str:
    """docs/montecarlo_datasets.json: the study's command, settings, summary and timings.

    The per-data-set list (1,000 entries) stays in the result file.
    """
    doc = _load(folder / "mc_stress_metrics.json")
    record = _load(folder / "mc_stress_run.json")
    summary = {k: doc[k] for k in ("scenario", "status", "settings", "summary", "timings_s")}
    summary["datasets_with_cache_warnings"] = [d["index"] for d in doc["datasets"]
                                               if d["cache_warnings"]]  # fmt: skip
    summary["run"] = record
    return json.dumps(summary, indent=1, allow_nan=False) + "\n"


def step_gp_coverage(out: Path) -> dict[str, tuple[str, str]]:
    """benchmarks/gp_coverage.py over ten data seeds: docs/learning.md's table."""
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "gp_coverage.json"
    seeds = [str(s) for s in range(10)]
    _run([sys.executable, "benchmarks/gp_coverage.py", "--seeds", *seeds, "--json", str(rows)])
    return {"gp-coverage": ("docs/learning.md", gp_coverage_table(_load(rows)))}


STEPS: dict[str, Callable[[Path], dict[str, tuple[str, str]]]] = {
    "obstacle": step_obstacle,
    "obstacle-seeds": step_obstacle_seeds,
    "mc-presets": step_mc_presets,
    "gp-coverage": step_gp_coverage,
    "mc-datasets": step_mc_datasets,
}
LONG = {"mc-datasets"}
#: The generated blocks each step writes (tests/test_docs_tools.py checks that every block
#: in docs/ is written by a step).
PRODUCES = {
    "obstacle": ["obstacle-outcomes"],
    "obstacle-seeds": ["obstacle-seeds"],
    "mc-presets": ["mc-stress", "mc-paper", "mc-stress-ood"],
    "gp-coverage": ["gp-coverage"],
    "mc-datasets": ["mc-datasets"],
}


def main(argv: list[str] | None = None) -> int:
    """Run the steps, rewrite the blocks; with ``--check``, 1 if a block's text changed."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=sorted(STEPS), help="run these steps")
    parser.add_argument("--long", action="store_true", help="include " + ", ".join(LONG))
    parser.add_argument("--check", action="store_true", help="exit 1 if a table changed")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "docs",
                        help="folder for the runs' result files")  # fmt: skip
    args = parser.parse_args(argv)
    names = args.only or [n for n in STEPS if args.long or n not in LONG]
    changed = []
    total = time.perf_counter()
    for name in names:
        print(f"[{name}]", flush=True)
        t0 = time.perf_counter()
        written = STEPS[name](args.out)
        assert sorted(written) == sorted(PRODUCES[name]), (name, sorted(written))
        for block, (page, table) in written.items():
            body = "\n" + table + "\n"  # blank lines: Markdown renders the table apart
            path = ROOT / page
            text = path.read_text()
            if blocks(text).get(block) != body:
                changed.append(f"{page}: {block}")
            path.write_text(replace_block(text, block, body))
        print(f"[{name}] {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"reran {', '.join(names)} in {time.perf_counter() - total:.0f} s")
    print("tables still typed by hand from result files: " +
          "; ".join(f"{p} ({what})" for p, what in BY_HAND.items()))  # fmt: skip
    if changed:
        print("changed: " + ", ".join(changed))
        return 1 if args.check else 0
    print("no generated table changed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
