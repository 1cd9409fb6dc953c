"""The command line: checks before work, all-or-none outputs, strict JSON, one-line errors.

The study itself is replaced by a stub here (a real run takes about 15 s; the end-to-end run
is ``tests/test_acc.py::test_cli_smoke``): these tests are about what the CLI does around it.
"""

import json
import os
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.figure import Figure
from typer.testing import CliRunner

import safestab.plotting
from safestab import NumericalError
from safestab.scenarios import acc_study, load_scenario
from safestab.scenarios.acc_study import StudyResult

OUTPUTS = ["acc_stress.pdf", "acc_stress.png", "acc_stress_metrics.json", "acc_stress_run.json"]


def _metrics(min_h):
    return {
        "min_h_m": min_h,
        "time_h_negative_s": 0.0,
        "rms_speed_error_mps": 1.5,
        "region_fraction": {"P1": 1.0},
        "incompatible_steps": 0,
    }


def _result(scenario, metrics=None):
    """A StudyResult with the fields the CLI reads, standing in for a 15 s run."""
    metrics = metrics or {name: _metrics(1.0) for name in acc_study.CONTROLLERS}
    return StudyResult(
        scenario=scenario,
        dataset=[None] * scenario.n_samples,
        gp=SimpleNamespace(components_=(0, 1, 2)),
        calibration=SimpleNamespace(
            per_component=np.array([0.99, 1.0, 1.0]), joint=0.99, rmse=np.array([1e-3, 0, 0])
        ),
        trajectories={},
        metrics=metrics,
        timings={"fit_gp": 0.1},
    )


@pytest.fixture
def study(monkeypatch):
    """Replace the study and its figure by stubs; record the calls."""
    calls = []
    state = {"metrics": None, "error": None}

    def fake_run_study(scenario, **kwargs):
        calls.append(scenario)
        if state["error"] is not None:
            raise state["error"]
        return _result(scenario, state["metrics"])

    def fake_plot(result):
        fig, ax = plt.subplots()
        ax.plot([0, 1], [0, 1])
        return fig

    monkeypatch.setattr(acc_study, "run_study", fake_run_study)
    monkeypatch.setattr(safestab.plotting, "plot_acc_study", fake_plot)
    return SimpleNamespace(calls=calls, state=state)


def _invoke(*args):
    from safestab.cli import app

    return CliRunner().invoke(app, ["acc", "--scenario", "stress", *map(str, args)])


def _one_error_line(res, expected_start):
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(expected_start), lines[0]
    assert "Traceback" not in res.output
    return lines[0]


def _listing(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# -- checks before any work -------------------------------------------------------------


def test_out_below_a_regular_file_fails_before_any_work(tmp_path, study):
    (tmp_path / "file").write_text("x")
    res = _invoke("--out", tmp_path / "file" / "sub")
    assert res.exit_code == 2
    line = _one_error_line(res, "error: OutputError: --out must be a writable folder")
    assert line.endswith(f"its parent {str(tmp_path / 'file')!r} is not a folder")
    assert study.calls == []  # the study never started


def test_out_that_is_a_regular_file_fails_before_any_work(tmp_path, study):
    (tmp_path / "file").write_text("x")
    res = _invoke("--out", tmp_path / "file")
    assert res.exit_code == 2
    _one_error_line(res, "error: OutputError: --out must be a writable folder")
    assert study.calls == [] and (tmp_path / "file").read_text() == "x"


def test_unwritable_out_fails_before_any_work(tmp_path, study, monkeypatch):
    # Tests run as root, which ignores permission bits: the refusal is simulated at the
    # creation of the probe file, the operation a read-only or foreign folder refuses.
    real_open = os.open

    def fake_open(path, flags, *args, **kwargs):
        if ".safestab-probe-" in os.fspath(path):
            raise OSError(30, "Read-only file system")
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 2
    line = _one_error_line(res, "error: OutputError: --out must be a writable folder")
    assert line.endswith("cannot create a file in it (Read-only file system)")
    assert study.calls == []


def test_nan_scenario_rejected_at_load(tmp_path, study):
    from importlib import resources

    text = resources.files("safestab.scenarios").joinpath("stress.toml").read_text()
    path = tmp_path / "nan.toml"
    path.write_text(text.replace("v_d = 22.0", "v_d = nan"))
    from safestab.cli import app

    res = CliRunner().invoke(app, ["acc", "--scenario", str(path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    _one_error_line(
        res,
        f"error: ScenarioError: {path}: certificates.v_d must be a finite number in [0, 1e9], "
        "got nan",
    )
    assert study.calls == [] and not (tmp_path / "o").exists()  # nothing made, not even --out


@pytest.mark.parametrize(
    "option, match",
    [
        (("--seed", "-1"), "learning.seed must be an integer in [0, 4294967295], got -1"),
        (("--n-samples", "10" + "0" * 11), "learning.n_samples must be an integer in [10, 10000]"),
        (
            ("--t-final", "nan"),
            "simulation.t_final must be a finite number in [1e-9, 1e9], got nan",
        ),
    ],
)
def test_bad_overrides_rejected_before_any_work(tmp_path, study, option, match):
    res = _invoke(*option, "--out", tmp_path / "o")
    assert res.exit_code == 2
    assert match in _one_error_line(res, "error: ScenarioError: scenario 'stress': ")
    assert study.calls == [] and not (tmp_path / "o").exists()


def test_overrides_reach_the_study(tmp_path, study):
    res = _invoke("--seed", 7, "--n-samples", 120, "--t-final", 5, "--out", tmp_path)
    assert res.exit_code == 0, res.output
    (sc,) = study.calls
    assert (sc.seed, sc.n_samples, sc.t_final) == (7, 120, 5.0)


# -- outputs ----------------------------------------------------------------------------


def test_success_writes_the_whole_set(tmp_path, study):
    for name in OUTPUTS:
        (tmp_path / name).write_bytes(b"stale")
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 0, res.output
    files = _listing(tmp_path)
    assert sorted(files) == OUTPUTS  # no temporaries or probes left
    assert files["acc_stress.png"].startswith(b"\x89PNG")
    assert files["acc_stress.pdf"].startswith(b"%PDF")
    assert json.loads(files["acc_stress_metrics.json"])["status"] == "ok"
    assert "wrote " in res.stdout and "acc_stress_metrics.json" in res.stdout


@pytest.mark.parametrize("stale", [True, False])
def test_failed_write_leaves_no_partial_set(tmp_path, study, monkeypatch, stale):
    """The PDF (second file) fails after the PNG was written: nothing new may appear."""
    if stale:
        for name in OUTPUTS:
            (tmp_path / name).write_bytes(b"stale " + name.encode())
    before = _listing(tmp_path)
    real_savefig = Figure.savefig

    def savefig(self, fname, *args, **kwargs):
        if kwargs.get("format") == "pdf":
            raise RuntimeError("disk on fire")
        return real_savefig(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 1
    _one_error_line(res, "error: RuntimeError: disk on fire")
    assert len(study.calls) == 1  # the study ran; only the writing failed
    assert _listing(tmp_path) == before  # stale set intact (or still empty), no temporaries


@pytest.mark.parametrize("stale", [True, False])
def test_failed_rename_rolls_back_the_set(tmp_path, study, monkeypatch, stale):
    """The JSON's rename (the last) fails after PNG and PDF were moved into place."""
    if stale:
        for name in OUTPUTS:
            (tmp_path / name).write_bytes(b"stale " + name.encode())
    before = _listing(tmp_path)
    real_replace = os.replace

    def replace(src, dst):
        if os.fspath(dst).endswith("_metrics.json"):
            raise OSError(5, "Input/output error")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 1
    _one_error_line(res, "error: OutputError: cannot write ")
    assert _listing(tmp_path) == before


def test_each_run_records_itself_and_names_the_other_runs_in_the_folder(
    tmp_path, study, monkeypatch
):
    """Outputs of different runs in one folder can be told apart: each run writes a record
    (command line, scenario, seed, version, time, its files) with its outputs, and the
    command names the other runs' records and the files no record claims."""
    monkeypatch.setattr("sys.argv", ["safestab", "acc", "--scenario", "stress", "--seed", "4"])
    (tmp_path / "acc_old_metrics.json").write_text("{}")  # from a safestab without records
    res = _invoke("--out", tmp_path, "--seed", 4)
    assert res.exit_code == 0, res.output
    record = json.loads((tmp_path / "acc_stress_run.json").read_text())
    assert record["files"] == OUTPUTS
    assert record["scenario"] == "stress" and record["seed"] == 4
    assert record["command"] == "safestab acc --scenario stress --seed 4"
    assert record["safestab"] == safestab.__version__ and record["finished_utc"].endswith("+00:00")
    assert "1 file(s) there come from no recorded run" in " ".join(res.stdout.split())
    # another run's record in the folder is named, with its command and time
    other = {"command": "safestab run --scenario paper", "finished_utc": "2026-01-01T00:00:00",
             "files": ["acc_paper.png", "acc_paper_run.json"]}  # fmt: skip
    (tmp_path / "acc_paper_run.json").write_text(json.dumps(other))
    (tmp_path / "acc_paper.png").write_bytes(b"png")
    res = _invoke("--out", tmp_path, "--seed", 4)
    text = " ".join(res.stdout.split())
    assert "also holds the outputs of 1 other run(s): acc_paper (2026-01-01T00:00:00)" in text
    assert "1 file(s) there come from no recorded run" in text  # still only the old one


def test_warnings_print_one_line_without_internal_paths(tmp_path, study, monkeypatch):
    import warnings

    from safestab.errors import DataWarning

    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # restored after
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 0, res.output
    text = warnings.formatwarning(
        DataWarning("the targets' offset\n   dwarfs their spread"), DataWarning,
        "/somewhere/site-packages/safestab/learning/gp.py", 412,
    )  # fmt: skip
    assert text == "warning: DataWarning: the targets' offset dwarfs their spread\n"


def test_json_has_no_nan_tokens_when_a_metric_is_not_finite(tmp_path, study):
    metrics = {name: _metrics(1.0) for name in acc_study.CONTROLLERS}
    metrics["GP-robust"]["min_h_m"] = float("nan")
    metrics["mismatched model"]["rms_speed_error_mps"] = float("inf")
    study.state["metrics"] = metrics
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 0, res.output
    text = (tmp_path / "acc_stress_metrics.json").read_text()
    assert "NaN" not in text and "Infinity" not in text

    def refuse(token):
        raise AssertionError(f"JSON must not contain {token}")

    doc = json.loads(text, parse_constant=refuse)
    assert doc["status"] == "non-finite"
    assert doc["non_finite"] == {
        "/controllers/GP-robust/min_h_m": "nan",
        "/controllers/mismatched model/rms_speed_error_mps": "inf",
    }
    assert doc["controllers"]["GP-robust"]["min_h_m"] is None
    assert doc["controllers"]["mismatched model"]["rms_speed_error_mps"] is None
    assert doc["controllers"]["true model"]["min_h_m"] == 1.0


# -- error reporting --------------------------------------------------------------------


def test_run_time_error_is_one_line_without_debug(tmp_path, study):
    study.state["error"] = NumericalError("Cholesky failed\n  try more noise")
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 1
    line = _one_error_line(res, "error: NumericalError: ")
    assert line == "error: NumericalError: Cholesky failed try more noise"
    assert list(tmp_path.iterdir()) == []
    # an error's notes (another error met on the way) follow on the same line
    error = NumericalError("Cholesky failed")
    error.add_note("the runs in another thread failed too: ValueError: nan")
    study.state["error"] = error
    line = _one_error_line(_invoke("--out", tmp_path), "error: NumericalError: ")
    assert line == (
        "error: NumericalError: Cholesky failed "
        "[the runs in another thread failed too: ValueError: nan]"
    )


def test_debug_shows_the_traceback(tmp_path, study):
    study.state["error"] = NumericalError("Cholesky failed")
    res = _invoke("--out", tmp_path, "--debug")
    assert res.exit_code == 1
    assert res.stderr.startswith("Traceback (most recent call last):")
    assert "fake_run_study" in res.stderr  # the frame where it was raised
    assert res.stderr.rstrip().endswith("error: NumericalError: Cholesky failed")


def test_debug_shows_the_traceback_of_a_bad_input(tmp_path, study):
    res = _invoke("--seed", "-1", "--out", tmp_path, "--debug")
    assert res.exit_code == 2
    assert "Traceback (most recent call last):" in res.stderr and "check_values" in res.stderr


def test_long_messages_are_cut_on_the_one_line(tmp_path, study):
    study.state["error"] = RuntimeError("x" * 5000)
    res = _invoke("--out", tmp_path)
    line = _one_error_line(res, "error: RuntimeError: xxx")
    assert len(line) < 450 and line.endswith("(cut; --debug shows all)")


def test_real_scenario_objects_are_used(study, tmp_path):
    """The CLI passes the loaded, checked scenario itself (not a re-parsed copy)."""
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 0, res.output
    assert study.calls == [load_scenario("stress")]


def test_summary_table_prints_its_units_as_text(tmp_path, study):
    """The headers' units are plain text, not rich markup ("[m]" is not a style tag)."""
    res = _invoke("--out", tmp_path)
    assert res.exit_code == 0, res.output
    assert "min h [m]" in res.stdout and "ACC study 'stress' (Q = " in res.stdout


def test_run_takes_several_scenarios_in_order_and_checks_all_before_any_work(study, tmp_path):
    """``run --scenario A --scenario B`` runs both studies in the order given, each with its
    own outputs; a bad later scenario is refused before the first one starts."""
    from safestab.cli import app

    out = tmp_path / "o"
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "paper", "--seed", "3", "--out", str(out)],
    )
    assert res.exit_code == 0, res.output
    assert [sc.name for sc in study.calls] == ["stress", "paper"]
    assert all(sc.seed == 3 for sc in study.calls)  # the options apply to each
    for name in ("stress", "paper"):
        assert (out / f"acc_{name}_metrics.json").is_file()

    study.calls.clear()
    bad = tmp_path / "bad"
    res = CliRunner().invoke(
        app, ["run", "--scenario", "stress", "--scenario", "no-such", "--out", str(bad)]
    )
    assert res.exit_code == 2  # bad input
    assert "no-such" in res.stderr
    assert study.calls == [] and not list(bad.glob("*"))


# -- studies of different kinds in several processes (--jobs) ---------------------------


def test_lanes_keep_each_kind_in_one_process_in_order():
    from safestab import cli

    names = ["paper", "obstacle", "stress", "swarm", "stress-ood"]
    kinds = ["acc", "obstacle", "acc", "swarm", "acc"]
    assert cli.plan_lanes(names, kinds, 1) == [names]
    assert cli.plan_lanes(names, kinds, 2) == [
        ["paper", "stress", "swarm", "stress-ood"],
        ["obstacle"],
    ]
    assert cli.plan_lanes(names, kinds, 3) == [["paper", "stress", "stress-ood"], ["obstacle"],
                                           ["swarm"]]  # fmt: skip
    # one process per kind at most
    assert cli.plan_lanes(names, kinds, 8) == cli.plan_lanes(names, kinds, 3)
    assert cli.plan_lanes(["paper", "stress"], ["acc", "acc"], None) == [["paper", "stress"]]


def test_lanes_default_to_one_process_per_cpu():
    from safestab import cli

    names, kinds = ["paper", "obstacle", "swarm"], ["acc", "obstacle", "swarm"]
    assert cli.plan_lanes(names, kinds, None, cpus=1) == [names]
    assert cli.plan_lanes(names, kinds, None, cpus=2) == [["paper", "swarm"], ["obstacle"]]
    assert cli.plan_lanes(names, kinds, 1, cpus=2) == [names]  # --jobs wins


def test_other_processes_get_this_ones_caches_whatever_set_them(tmp_path):
    from safestab import cli

    environ = {"SAFESTAB_COMPILATION_CACHE": "/elsewhere", "PATH": "/bin"}
    env = cli.lane_environment(environ, None, tmp_path / "fits")  # --no-compilation-cache
    assert env["SAFESTAB_COMPILATION_CACHE"] == "off"
    assert env["SAFESTAB_FIT_CACHE"] == str(tmp_path / "fits") and env["PATH"] == "/bin"
    env = cli.lane_environment(environ, tmp_path / "jax", None)  # --no-fit-cache
    assert env["SAFESTAB_COMPILATION_CACHE"] == str(tmp_path / "jax")
    assert env["SAFESTAB_FIT_CACHE"] == "off"
    assert environ == {"SAFESTAB_COMPILATION_CACHE": "/elsewhere", "PATH": "/bin"}


def _fake_lane(monkeypatch, script):
    """Make the other processes run ``python -c script`` (given the real command line)."""
    import sys

    from safestab import cli

    seen, real = [], cli.lane_command

    def command(names, options):
        seen.append(real(names, options))
        return [sys.executable, "-c", script, *seen[-1]]

    monkeypatch.setattr(cli, "lane_command", command)
    return seen


def test_jobs_run_other_kinds_in_another_process_and_print_their_output(
    study, tmp_path, monkeypatch
):
    from safestab.cli import app

    script = (
        "import os, sys; print('other process:', ' '.join(sys.argv[1:]));"
        "print('cache', os.environ['SAFESTAB_COMPILATION_CACHE'], "
        "os.environ['SAFESTAB_FIT_CACHE']); print('a warning', file=sys.stderr)"
    )
    seen = _fake_lane(monkeypatch, script)
    out = tmp_path / "o"
    args = ["run", "--scenario", "stress", "--scenario", "swarm", "--seed", "3",
            "--t-final", "2.5", "--out", str(out), "--jobs", "2"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert [sc.name for sc in study.calls] == ["stress"]  # this process: the ACC kind
    assert (out / "acc_stress_metrics.json").is_file()
    (cmd,) = seen
    assert cmd[1:5] == ["-m", "safestab.cli", "run", "--scenario"] and cmd[5] == "swarm"
    assert cmd[6:] == ["--out", str(out), "--jobs", "1", "--seed", "3", "--t-final", "2.5"]
    assert "running swarm in another process" in res.stdout
    assert "other process: " + " ".join(cmd) in res.stdout
    # the process's caches are passed on (the fit cache is off in the tests)
    from safestab._cache import compilation_cache_dir

    assert f"cache {compilation_cache_dir()} off" in res.stdout
    assert "a warning" in res.stderr
    # --debug and --set go along; a bad --set is refused here, before any process starts
    res = CliRunner().invoke(app, [*args[:-2], "--debug", "--set", "x.y=1", "--jobs", "2"])
    assert res.exit_code == 2 and len(seen) == 1
    res = CliRunner().invoke(app, [*args[:-2], "--debug", "--jobs", "2"])
    assert res.exit_code == 0, res.output
    assert seen[-1][-1] == "--debug"


def test_a_failure_in_another_process_fails_the_command_after_this_ones_studies(
    study, tmp_path, monkeypatch
):
    from safestab.cli import app

    _fake_lane(monkeypatch, "import sys; print('error: StudyError: boom', file=sys.stderr); "
               "sys.exit(1)")  # fmt: skip
    out = tmp_path / "o"
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "swarm", "--jobs", "2", "--out", str(out)],
    )
    assert res.exit_code == 1
    assert "error: StudyError: boom" in res.stderr
    assert (out / "acc_stress_metrics.json").is_file()  # this process's study finished
    # a failure here: the other process still finishes, and its output is printed
    _fake_lane(monkeypatch, "print('the other one finished')")
    study.state["error"] = NumericalError("Cholesky failed")
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "swarm", "--jobs", "2", "--out", str(out)],
    )
    assert res.exit_code == 1
    assert "the other one finished" in res.stdout
    assert "error: NumericalError: Cholesky failed" in res.stderr
    # a process ended by a signal is a failure too, named
    _fake_lane(monkeypatch, "import os, signal; os.kill(os.getpid(), signal.SIGKILL)")
    study.state["error"] = None
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "swarm", "--jobs", "2", "--out", str(out)],
    )
    assert res.exit_code == 1
    assert "the process running swarm ended by signal 9" in res.stderr


def _record_started_lanes(monkeypatch):
    """The other processes started (their ``Lane``), in order; 5 s to stop instead of 10."""
    from safestab import cli

    started, real_start = [], cli.start_lane

    def start(names, options):
        started.append(real_start(names, options))
        return started[-1]

    monkeypatch.setattr(cli, "start_lane", start)
    monkeypatch.setattr(cli.Lane, "STOP_SECONDS", 5.0)
    return started


def test_a_process_that_cannot_start_stops_those_already_started(study, tmp_path, monkeypatch):
    import sys

    from safestab import cli
    from safestab.cli import app

    def command(names, options):
        if names == ["swarm"]:
            return [sys.executable, "-c", "import time; time.sleep(60)"]
        return [str(tmp_path / "no-such-program")]  # the second process cannot start

    monkeypatch.setattr(cli, "lane_command", command)
    started = _record_started_lanes(monkeypatch)
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "swarm", "--scenario", "obstacle",
         "--jobs", "3", "--out", str(tmp_path / "o")],
    )  # fmt: skip
    assert isinstance(res.exception, FileNotFoundError)
    assert study.calls == []  # no study started here
    # the first process was started, then stopped and waited for (not left running)
    (lane,) = started
    assert lane.process.returncode is not None and lane.stdout.closed


def test_sigterm_stops_the_other_processes_before_this_one_exits(study, tmp_path, monkeypatch):
    """A job scheduler's (or ``kill``'s) SIGTERM: the other processes are stopped and waited
    for, and the command exits 143, instead of ending at once and leaving them running."""
    import os
    import signal
    import sys
    import time

    from safestab import cli
    from safestab.cli import app

    def terminated_during_the_study(scenario, **kwargs):
        # without the handler the signal would end pytest itself: fail this test instead
        assert signal.getsignal(signal.SIGTERM) is not before, "no SIGTERM handler"
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)  # the handler raises here
        raise AssertionError("SIGTERM did not stop the study")

    monkeypatch.setattr(
        cli, "lane_command", lambda names, options: [sys.executable, "-c", "import time; "
                                                     "time.sleep(60)"]
    )  # fmt: skip
    started = _record_started_lanes(monkeypatch)
    monkeypatch.setattr(acc_study, "run_study", terminated_during_the_study)
    before = signal.getsignal(signal.SIGTERM)
    t0 = time.perf_counter()
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", "swarm", "--jobs", "2", "--out",
         str(tmp_path / "o")],
    )  # fmt: skip
    assert res.exit_code == 128 + signal.SIGTERM, res.output
    assert time.perf_counter() - t0 < 20
    (lane,) = started
    assert lane.process.returncode is not None and lane.stdout.closed
    assert signal.getsignal(signal.SIGTERM) is before  # the handler is this command's only


def test_another_process_computes_what_this_one_does(study, tmp_path):
    """A real second process (a small swarm) writes the metrics that a run here writes."""
    from importlib.resources import files

    from safestab.cli import app

    text = (files("safestab.scenarios") / "swarm.toml").read_text()
    for old, new in (('name = "swarm"', 'name = "small"'), ("n_robots = 12", "n_robots = 4"),
                     ("arena_radius = 4.0", "arena_radius = 2.0"),
                     ("t_final = 16.0", "t_final = 0.5")):  # fmt: skip
        assert old in text
        text = text.replace(old, new)
    small = tmp_path / "small.toml"
    small.write_text(text)
    here, there = tmp_path / "here", tmp_path / "there"
    res = CliRunner().invoke(app, ["run", "--scenario", str(small), "--out", str(here)])
    assert res.exit_code == 0, res.output
    # the ACC study (a stub) here, the swarm in a real second process
    res = CliRunner().invoke(
        app,
        ["run", "--scenario", "stress", "--scenario", str(small), "--jobs", "2", "--out",
         str(there)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "running " + str(small) + " in another process" in res.stdout
    assert "swarm 'small' (4 robots, 6 pair barriers)" in res.stdout  # the other's summary

    def metrics(folder):
        doc = json.loads((folder / "swarm_small_metrics.json").read_text())
        doc.pop("timings_s", None)
        return doc

    assert metrics(there) == metrics(here)
    record = json.loads((there / "swarm_small_run.json").read_text())
    assert record["command"].endswith(f"--scenario {small} --out {there} --jobs 1")
