"""Relative output folders work from any working folder: resolved once, where a command starts.

``safestab export --target`` once failed with its default ``--out build``: the embedded build
ran ``arm-none-eabi-size build/cortex-m4/acc.o`` with ``build/cortex-m4`` as the working
folder. The tests elsewhere pass absolute temporary folders, so these run the commands and
the public functions from a temporary working folder with relative paths and the defaults.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import safestab as ss
from safestab._io import ensure_writable_dir
from safestab.export import embedded, write_harness
from safestab.export.harness import comparison_scales
from safestab.scenarios import load_scenario
from safestab.scenarios.export_study import export_scenario


def _export(*args: str):
    from safestab.cli import app

    # the nominal controller: no data collection or GP fit, the build is what is tested
    options = ["--scenario", "paper", "--controller", "nominal", "--cases", "8"]
    return CliRunner().invoke(app, ["export", *options, *args])


def test_ensure_writable_dir_returns_the_folder_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = ensure_writable_dir("a/b", name="--out")
    assert folder == tmp_path / "a" / "b" and folder.is_absolute() and folder.is_dir()


@pytest.mark.parametrize("out", [None, "out", "./deeper/out/"], ids=["default", "rel", "nested"])
def test_export_with_a_relative_out_from_another_folder(tmp_path, monkeypatch, out):
    monkeypatch.chdir(tmp_path)
    res = _export(*([] if out is None else ["--out", out]))
    assert res.exit_code == 0, res.output
    folder = tmp_path / (out or "build")
    assert "0 mismatches" in res.output
    assert {"acc.c", "acc.h", "acc_harness.c", "acc_harness"} <= {p.name for p in folder.iterdir()}


@pytest.mark.parametrize("out", [None, "out"], ids=["default", "rel"])
def test_export_target_with_a_relative_out(tools, tmp_path, monkeypatch, out):
    monkeypatch.chdir(tmp_path)
    res = _export("--target", "cortex-m4", *([] if out is None else ["--out", out]))
    assert res.exit_code == 0, res.output
    assert "0 mismatches / 8" in res.output and "8 / 8" in res.output  # on the core, bit for bit
    assert (tmp_path / (out or "build") / "cortex-m4" / "acc.o").is_file()


def test_export_scenario_keeps_absolute_paths_valid_after_a_chdir(tmp_path, monkeypatch):
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path)
    rep = export_scenario("paper", "rel", controller="nominal", cases=4)
    assert rep.passed
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert all(p.is_absolute() and p.is_file() for p in rep.files)
    assert str(tmp_path / "rel") in rep.build_command


def test_run_on_target_takes_a_relative_folder(tools, tmp_path, monkeypatch):
    # the public functions a Python caller uses, each given the same relative folder
    monkeypatch.chdir(tmp_path)
    sc = load_scenario("paper")
    ctrl = ss.UniversalController(
        sc.system("true"), *sc.certificates(), kappa=0.2, rho=0.1, phi=1e-4, varphi=0.0,
        slack_weight=10.0,
    )  # fmt: skip
    states = np.random.default_rng(0).uniform(sc.x0_low, sc.x0_high, size=(4, 3))
    exported = ss.export_c(ctrl, "acc", "rel", layout="embedded")
    expected = ctrl.step_fn(states)
    harness = write_harness(
        exported, states, expected, "rel", scales=comparison_scales(ctrl, expected, states)
    )
    assert harness == tmp_path / "rel" / "acc_harness.c"
    rep = embedded.run_on_target(Path("rel"), "acc", exported, states, "cortex-m7")
    assert rep.harness_mismatches == 0 and rep.bit_identical_to_host == 4
    rep = embedded.export_for_target(ctrl, "acc", "rel2", states, "cortex-m7")
    assert rep.harness_mismatches == 0 and (tmp_path / "rel2" / "cortex-m7" / "acc.o").is_file()
