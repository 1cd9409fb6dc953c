"""Wall time of the README's commands, each in a fresh process: the first run with an empty
compilation cache, then a second run that reuses it, against the targets in :data:`TARGETS`.

    python benchmarks/first_run.py            # main job (paper, stress, obstacle) and mc
    python benchmarks/first_run.py --tests    # also the default test run, twice (~30 min)

The main job is also timed with ``SAFESTAB_XLA_FLAGS=off`` (XLA's default fusion emitters,
safestab/_xla_flags.py), a row for comparison without a target (about 90 s more).

Without ``--tests`` the test run's row of the previous results is kept, with its own date.

Each command runs as a new process with ``SAFESTAB_COMPILATION_CACHE`` and
``SAFESTAB_FIT_CACHE`` set to fresh temporary folders: the first run finds them empty (every
program compiled, every GP fitted), the second finds the first run's programs and fits. The
test run fits afresh (``SAFESTAB_FIT_CACHE=off``, as tests/conftest.py sets it). Installation
is excluded (the environment must exist). Writes ``docs/performance_first_run.json`` and its
block in ``docs/performance.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _page import machine, measured, save_results

BEGIN, END = "<!-- first-run:begin -->", "<!-- first-run:end -->"
ROOT = Path(__file__).resolve().parents[1]
SAFESTAB = [sys.executable, "-m", "safestab.cli"]


def main_job_scenarios(script: Path = ROOT / "scripts" / "run-acc.sh") -> list[str]:
    """The scenarios of the main job's first command, read from ``scripts/run-acc.sh``.

    Read, not written here again: a scenario added to the script is timed too.
    """
    import shlex

    for line in script.read_text().splitlines():
        words = shlex.split(line, comments=True)
        if words[:2] == [".venv/bin/safestab", "run"]:
            return [words[i + 1] for i, w in enumerate(words[:-1]) if w == "--scenario"]
    raise RuntimeError(f"no 'safestab run' command in {script}")


#: the main job's scenarios, as scripts/run-acc.sh runs them
MAIN_SCENARIOS = main_job_scenarios()
MAIN = f"main job (scripts/run-acc.sh's first command: {', '.join(MAIN_SCENARIOS)})"
#: the same command with XLA's default fusion emitters (safestab/_xla_flags.py), for comparison
MAIN_XLA = "the same, SAFESTAB_XLA_FLAGS=off (no target: the comparison)"
#: the targets in seconds, per row name: (first run, second run); the test run's is its
#: first run's (pytest time with empty caches), the second's the same bound
TARGETS = {
    MAIN: (45.0, 15.0),
    "safestab mc --scenario stress --trials 10000 --datasets 1": (45.0, 20.0),
    "default test run (bash scripts/run-tests.sh)": (600.0, 600.0),
}


def _commands(out: Path, tests: bool) -> list[tuple[str, list[list[str]]]]:
    """Rows: a name and the commands whose wall times add up to it."""
    main = [*SAFESTAB, "run"]  # as scripts/run-acc.sh runs them: one command (default --jobs)
    for name in MAIN_SCENARIOS:
        main += ["--scenario", name]
    main += ["--out", str(out / "main")]
    rows = [
        (MAIN, [main]),
        (MAIN_XLA, [[*main[:-1], str(out / "main-xla")]]),
        (
            "safestab mc --scenario stress --trials 10000 --datasets 1",
            [
                [
                    *SAFESTAB,
                    "mc",
                    "--scenario",
                    "stress",
                    "--trials",
                    "10000",
                    "--datasets",
                    "1",
                    "--backend",
                    "local",
                    "--out",
                    str(out / "mc"),
                ]
            ],
        ),  # fmt: skip
    ]
    if tests:
        rows.append(
            ("default test run (bash scripts/run-tests.sh)", [["bash", "scripts/run-tests.sh"]])
        )
    return rows


def _timed(cmd: list[str], cache: Path, xla_flags: bool = True) -> float:
    # the GP fit cache beside the compilation cache; the test run fits afresh (conftest.py)
    fits = "off" if cmd[0] == "bash" else str(cache.with_name(cache.name + "-fits"))
    env = dict(os.environ, SAFESTAB_COMPILATION_CACHE=str(cache), SAFESTAB_FIT_CACHE=fits)
    # safestab's own XLA flag, or none (an inherited setting would make both rows alike)
    env.pop("SAFESTAB_XLA_FLAGS", None)
    if "xla_cpu_use_fusion_emitters" in env.get("XLA_FLAGS", ""):
        raise SystemExit("XLA_FLAGS names xla_cpu_use_fusion_emitters: unset it to measure")
    if not xla_flags:
        env["SAFESTAB_XLA_FLAGS"] = "off"
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed with exit code {done.returncode}")
    return seconds


def bench(tests: bool) -> dict:
    results: dict = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        for name, cmds in _commands(Path(tmp), tests):
            cache = Path(tmp) / f"cache-{len(results['rows'])}"  # empty for the first run
            runs = []
            for attempt in ("first", "second"):
                parts = [_timed(cmd, cache, name != MAIN_XLA) for cmd in cmds]
                runs.append(parts)
                print(f"{name}, {attempt} run: {sum(parts):.1f} s {[round(p, 1) for p in parts]}")
            results["rows"].append(
                {"name": name, "first_s": runs[0], "second_s": runs[1],
                 "target_s": TARGETS.get(name), "date": results["date"]}
            )  # fmt: skip
    results["load_average_at_end"] = os.getloadavg()[0]
    return results


def keep_rows(results: dict, previous: Path) -> dict:
    """Add the rows of ``previous`` results that this run did not measure (the test run)."""
    if not previous.exists():
        return results
    old = json.loads(previous.read_text())
    have = {row["name"] for row in results["rows"]}
    for row in old.get("rows", []):
        # marked: it measured the code of an earlier commit (a row renamed since is dropped)
        if row["name"] not in have and row["name"] in TARGETS:
            results["rows"].append({**row, "date": row.get("date", old["date"]), "carried": True})
    return results


def markdown(r: dict) -> str:
    lines = [
        BEGIN,
        "## First run and second run (`python benchmarks/first_run.py --tests`)",
        "",
        f"{measured(r)} and {r['load_average_at_end']:.1f} at the end. Each command is a fresh "
        "process; the first run starts with an empty compilation cache and GP fit cache "
        "(`SAFESTAB_COMPILATION_CACHE` and `SAFESTAB_FIT_CACHE` set to new folders), the "
        "second reuses the first's (the test run fits afresh: `SAFESTAB_FIT_CACHE=off`). "
        "Installation excluded.",
        "",
        "| command | first run (s) | second run (s) | target first / second (s) | met |",
        "|---|---:|---:|---:|---|",
    ]
    for row in r["rows"]:
        first, second = sum(row["first_s"]), sum(row["second_s"])
        t1, t2 = row["target_s"] or (None, None)
        parts = (
            f" ({' + '.join(f'{p:.0f}' for p in row['first_s'])};"
            f" {' + '.join(f'{p:.0f}' for p in row['second_s'])})"
            if len(row["first_s"]) > 1
            else ""
        )
        met = "-" if t1 is None else "yes" if first <= t1 and second <= t2 else "no"
        target = "-" if t1 is None else f"{t1:.0f} / {t2:.0f}"
        when = (
            f" (an earlier run's row, measured {row['date']})"
            if row.get("carried") or row.get("date", r["date"]) != r["date"]
            else ""
        )
        lines.append(
            f"| {row['name']}{parts}{when} | {first:.0f} | {second:.0f} | {target} | {met} |"
        )
    return "\n".join([*lines, "", END])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tests", action="store_true", help="also time the default test run")
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    parser.add_argument("--page", action="store_true",
                        help="measure nothing: rewrite the block from the saved results with "
                        "today's targets")  # fmt: skip
    args = parser.parse_args()
    saved = args.out / "performance_first_run.json"
    if args.page:
        results = json.loads(saved.read_text())
        for row in results["rows"]:
            row["target_s"] = TARGETS.get(row["name"])
    else:
        results = keep_rows(bench(args.tests), saved)
    save_results(args.out, "performance_first_run.json", results, markdown, BEGIN, END)


if __name__ == "__main__":
    main()
