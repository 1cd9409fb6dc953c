"""The deployed Monte Carlo study (benchmarks/deployed.py) and its tables in docs/deployed.md."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from safestab.controllers import StepStatus

ROOT = Path(__file__).resolve().parents[1]


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


deployed = _load(ROOT / "benchmarks" / "deployed.py")
reproduce_docs = _load(ROOT / "scripts" / "reproduce_docs.py")


def _records(min_h, min_h_between=None, settle=None, unmet=None, limit=None, bad=None):
    """Records of 4 trials x 2 controllers, the fields the study reads."""
    min_h = np.asarray(min_h, float)
    shape = min_h.shape
    zeros = np.zeros(shape, int)
    return {
        "min_h": min_h,
        "min_h_between": min_h if min_h_between is None else np.asarray(min_h_between, float),
        "settle_time": np.full(shape, -1.0) if settle is None else np.asarray(settle, float),
        "barrier_unmet_steps": zeros if unmet is None else np.asarray(unmet),
        "limit_steps": zeros if limit is None else np.asarray(limit),
        "first_bad_status": zeros if bad is None else np.asarray(bad),
    }


def _run(records):
    # 4 trials over 2 data sets (trial i in data set i mod 2), 10 steps each
    return SimpleNamespace(
        records=records, controllers=("true model", "GP-robust"),
        dataset_index=np.arange(4) % 2, study=SimpleNamespace(n_steps=10),
    )  # fmt: skip


def test_study_rows_count_safety_per_data_set_and_pair_the_margin_price():
    plain = _records(
        [[1.0, 0.5], [2.0, -0.1], [1.5, 0.2], [1.0, 0.3]],
        # controller 0, trial 2: safe at the samples, below 0 between them (data set 0)
        min_h_between=[[1.0, 0.5], [2.0, -0.1], [-0.01, 0.2], [1.0, 0.3]],
        settle=[[10.0, 12.0], [10.0, 12.0], [10.0, 12.0], [10.0, 12.0]],
        unmet=[[0, 3], [0, 0], [0, 1], [0, 0]],
        limit=[[0, 5], [0, 1], [0, 0], [0, 0]],
    )
    margin = _records(
        [[1.5, 1.0], [2.5, 0.4], [2.0, 0.7], [1.5, 0.8]],
        settle=[[11.0, 12.0], [11.0, 13.0], [11.0, 14.0], [11.0, 15.0]],
        # controller 1, trial 3: no input at some step (data set 1)
        bad=[[0, 0], [0, 0], [0, 0], [0, int(StepStatus.NONFINITE_STATE)]],
    )
    rows = deployed.study_rows("s", {"none": _run(plain), "bound": _run(margin)}, 2.5)
    assert [(r["controller"], r["margin"]) for r in rows] == [
        ("true model", "none"), ("GP-robust", "none"),
        ("true model", "bound"), ("GP-robust", "bound"),
    ]  # fmt: skip
    true_plain, gp_plain, true_margin, gp_margin = rows
    assert true_plain["left_at_samples"] == 0 and true_plain["left_between_samples"] == 1
    assert true_plain["safe_per_dataset"]["count"] == 1  # data set 0 lost between the samples
    assert gp_plain["safe_per_dataset"]["count"] == 1  # set 1 lost (trial 1), set 0 safe
    assert gp_plain["left_at_samples"] == 1 and gp_plain["min_h_samples"] == -0.1
    assert gp_plain["trials_with_unmet_steps"] == 2 and gp_plain["unmet_steps"] == 4
    assert gp_plain["limit_step_fraction"] == pytest.approx(6 / 40)
    assert gp_plain["ddh_bound"] is None and gp_plain["price"] is None
    assert true_margin["safe_per_dataset"]["count"] == 2
    assert true_margin["safe_per_dataset"]["ci95"][1] == 1.0
    assert gp_margin["safe_per_dataset"]["count"] == 1  # data set 1 had a step with no input
    assert gp_margin["ddh_bound"] == 2.5
    # paired with the same controller and trials without the margin
    assert true_margin["price"] == {"median_min_h_gain": 0.5, "median_settle_time_change": 1.0}
    assert gp_margin["price"]["median_min_h_gain"] == pytest.approx(0.5)
    assert gp_margin["price"]["median_settle_time_change"] == pytest.approx(1.5)
    json.dumps(rows, allow_nan=False)  # strict JSON


def test_margin_price_without_settle_times_says_not_measured():
    plain = _records([[1.0, 0.5], [2.0, 0.1], [1.0, 0.3], [1.0, 0.3]])
    margin = _records([[1.2, 0.5], [2.4, 0.1], [1.1, 0.3], [1.3, 0.3]])
    price = deployed.margin_price(plain, margin, 0)
    assert price == {"median_min_h_gain": pytest.approx(0.25), "median_settle_time_change": None}
    assert reproduce_docs.price_cells(price) == ["+0.2500", "not measured"]


def _doc():
    row = {
        "study": "ACC stress-limited", "controller": "GP-robust", "margin": "none",
        "ddh_bound": None, "datasets": 10, "trials": 100, "left_at_samples": 3,
        "left_between_samples": 4, "min_h_samples": -0.0225, "min_h_between": -0.0231,
        "median_min_h": 0.00015,
        "safe_per_dataset": {"count": 7, "datasets": 10, "ci95": [0.3475, 0.9333]},
        "trials_with_unmet_steps": 2, "unmet_steps": 17, "limit_step_fraction": 0.01234,
        "price": None,
    }  # fmt: skip
    with_margin = row | {
        "margin": "closed-form bound", "ddh_bound": 5.886, "left_at_samples": 0,
        "left_between_samples": 0, "min_h_samples": 0.566, "min_h_between": 0.566,
        "safe_per_dataset": {"count": 10, "datasets": 10, "ci95": [0.6915, 1.0]},
        "price": {"median_min_h_gain": 0.5876, "median_settle_time_change": 0.0},
    }  # fmt: skip
    return {
        "montecarlo": [row, with_margin],
        "montecarlo_settings": {
            "datasets": 10,
            "trials_per_dataset": {"ACC stress-limited, 10 Hz": 10, "obstacle, 2 Hz": 72},
        },
        "montecarlo_timings_s": {
            "ACC stress-limited, 10 Hz": {"none": {"total": 100.0}, "bound": {"total": 120.0}},
            "obstacle, 2 Hz": {"none": {"total": 30.0}, "bound": {"total": 50.0}},
        },
    }


def test_deployed_mc_table_rows():
    lines = reproduce_docs.deployed_mc_table(_doc()["montecarlo"]).splitlines()
    assert len(lines) == 4
    assert lines[0].count("|") == 15 and lines[1].count("|") == 15
    assert lines[2] == (
        "| ACC stress-limited | GP-robust | none | 3 / 100 | 4 / 100 | -0.0225 | -0.0231 "
        "| +1.5e-04 | 7/10 | [0.35, 0.93] | 2 (17 steps) | 0.0123 | - | - |"
    )
    assert lines[3] == (
        "| ACC stress-limited | GP-robust | closed-form bound (M = 5.89) | 0 / 100 | 0 / 100 "
        "| +0.5660 | +0.5660 | +1.5e-04 | 10/10 | [0.69, 1.00] | 2 (17 steps) | 0.0123 "
        "| +0.5876 | +0.00 |"
    )


def test_deployed_mc_timing_states_the_time_per_data_set_and_the_projection():
    line = reproduce_docs.deployed_mc_timing(_doc())
    # 300 s over 10 data sets: 30 s each, 30,000 s (8.3 h) for 1,000
    assert "10 data sets (ACC stress-limited: 10 trials each; obstacle: 72 trials each)" in line
    assert "in 300 s: 30.0 s per data set" in line
    assert "about 8.3 h" in line


def test_check_reports_a_measured_time_but_fails_on_a_table(tmp_path, monkeypatch, capsys):
    page = tmp_path / "page.md"
    written = {"t": "old\n", "t-time": "12 s\n"}
    monkeypatch.setattr(reproduce_docs, "ROOT", tmp_path)
    monkeypatch.setattr(reproduce_docs, "STEPS", {"fake": lambda out: {
        name: ("page.md", body) for name, body in written.items()}})  # fmt: skip
    monkeypatch.setattr(reproduce_docs, "PRODUCES", {"fake": ["t", "t-time"]})
    monkeypatch.setattr(reproduce_docs, "MEASURED_TIMES", {"t-time"})
    # a block's body is the table between blank lines (as main writes it)
    page.write_text(
        "<!-- generated: t -->\n\nold\n\n<!-- end generated -->\n"
        "<!-- generated: t-time -->\n\nold\n\n<!-- end generated -->\n"
    )
    before = page.read_text()
    assert reproduce_docs.main(["--check", "--out", str(tmp_path / "out")]) == 0
    assert "measured times that differ: page.md: t-time" in capsys.readouterr().out
    assert page.read_text() == before  # --check writes nothing
    written["t"] = "new\n"
    assert reproduce_docs.main(["--check", "--out", str(tmp_path / "out")]) == 1
    # without --check the time is written like a table
    assert reproduce_docs.main(["--out", str(tmp_path / "out")]) == 0
    assert reproduce_docs.blocks(page.read_text()) == {"t": "\nnew\n\n", "t-time": "\n12 s\n\n"}


def test_the_long_step_runs_the_same_study_at_1000_data_sets():
    assert "deployed-long" in reproduce_docs.LONG
    assert reproduce_docs.PRODUCES["deployed-long"] == ["deployed-mc-long", "deployed-mc-long-time"]
    assert {"deployed-mc-time", "deployed-mc-long-time"} <= reproduce_docs.MEASURED_TIMES
    args = deployed.parse_args(reproduce_docs.DEPLOYED_LONG_ARGS)
    assert args.datasets == 1000 and args.trials_per_dataset == 10 and args.no_loops
    normal = deployed.parse_args([])
    assert normal.datasets == 10 and normal.trials_per_dataset == 10 and not normal.no_loops
    # the unit for both studies: 1,000 data sets x 10 trials (the normal step runs
    # the obstacle's 72 starts per data set)
    assert args.obstacle_trials_per_dataset == 10 and normal.obstacle_trials_per_dataset is None


@pytest.mark.parametrize("argv", [["--datasets", "-1"], ["--trials-per-dataset", "0"],
                                  ["--obstacle-trials-per-dataset", "0"],
                                  ["--no-loops", "--datasets", "0"]])  # fmt: skip
def test_deployed_refuses_bad_counts(argv, capsys):
    with pytest.raises(SystemExit):
        deployed.parse_args(argv)
    err = capsys.readouterr().err
    assert "must be" in err or "nothing to run" in err


def test_the_long_block_is_generated_or_says_how_to_generate_it():
    page = (ROOT / "docs" / "deployed.md").read_text()
    body = reproduce_docs.blocks(page)["deployed-mc-long"]
    if body.lstrip().startswith("|"):  # generated: the 1,000 data sets of every row
        assert all("/1000 |" in line for line in body.splitlines()[2:] if line.startswith("| "))
    else:
        assert reproduce_docs.LONG_PLACEHOLDER in body
        assert "bash scripts/reproduce-docs.sh --long" in body
        time = reproduce_docs.blocks(page)["deployed-mc-long-time"]
        assert reproduce_docs.LONG_PLACEHOLDER in time  # no time for a study not run
