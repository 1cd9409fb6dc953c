"""Export an ACC scenario's controller with its C test harness (``safestab export``)."""

from __future__ import annotations

import dataclasses
import subprocess
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import CompilationError, ParameterError
from .exporter import check_name, check_precision, export_c
from .harness import comparison_scales, write_harness
from .native import find_compiler

__all__ = ["HARNESS_FLAGS", "ExportReport", "export_scenario"]

#: Flags the harness (and the exported code) must compile with, warning-free.
HARNESS_FLAGS = (
    "-std=c99",
    "-Wall",
    "-Wextra",
    "-Werror",
    "-pedantic",
    "-O2",
    "-ffp-contract=off",
)

CONTROLLERS = {"gp": "GP-corrected", "nominal": "mismatched model", "true": "true model"}


@dataclasses.dataclass(frozen=True)
class ExportReport:
    """What :func:`export_scenario` wrote and, when checked, what the harness said."""

    files: tuple[Path, ...]
    build_command: str
    harness_output: str | None
    passed: bool | None


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".safestab-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ParameterError(f"out must be a writable folder, got {str(out)!r}: {exc}") from None


def export_scenario(
    scenario: str | Path,
    out: str | Path,
    *,
    controller: str = "gp",
    name: str = "acc",
    precision: str = "double",
    cases: int = 256,
    n_samples: int | None = None,
    n_inducing: int = 32,
    seed: int | None = None,
    check: bool = True,
    progress: Callable[[str], None] | None = None,
) -> ExportReport:
    """Export an ACC controller of a scenario to ``out`` with a C test harness.

    Writes ``<name>.c``, ``<name>.h`` and ``<name>_harness.c`` (states drawn uniformly from
    the scenario's learning box ``x0_low .. x0_high``, outputs of the JAX step). With
    ``check``, compiles the harness with :data:`HARNESS_FLAGS` and runs it.

    Parameters
    ----------
    scenario : str or path
        A preset name or a TOML file (see :func:`~safestab.scenarios.load_scenario`).
    out : path
        Output folder, created if needed.
    controller : {"gp", "nominal", "true"}
        The GP-corrected controller (GP fitted as in the study, exported through a
        :class:`~safestab.learning.FastGP` cache calibrated on held-out data), or the
        controller built on the nominal or the true model.
    name : str
        Prefix of the C names and files.
    precision : {"double", "float"}
    cases : int
        Number of recorded states, >= 1.
    n_samples : int, optional
        Overrides the scenario's ``Q``.
    n_inducing : int
        Inducing points per GP component of the cache.
    seed : int, optional
        Overrides the scenario's seed.
    check : bool
        Compile and run the harness.
    progress : callable, optional
        Called with a message at each stage.

    Returns
    -------
    ExportReport

    Raises
    ------
    ScenarioError
        If the scenario cannot be loaded.
    ParameterError
        If an option is invalid or ``out`` is not writable.
    UnsupportedPrimitiveError
        If the controller cannot be translated.
    CompilationError
        With ``check``, if no compiler is found or the harness does not compile.
    """
    from ..learning import FastGP
    from ..scenarios import load_scenario
    from ..scenarios.acc_study import collect_study_data, fit_study_gp, study_controllers

    say = progress or (lambda msg: None)
    if controller not in CONTROLLERS:
        raise ParameterError(f"controller must be one of {sorted(CONTROLLERS)}, got {controller!r}")
    if int(cases) < 1:
        raise ParameterError(f"cases must be >= 1, got {cases!r}")
    # every option checked before the data collection and the GP fit (minutes)
    check_name(name)
    check_precision(precision)
    if (
        isinstance(n_inducing, bool)
        or not isinstance(n_inducing, int | np.integer)
        or n_inducing < 1
    ):
        raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
    out = Path(out)
    _check_writable(out)
    sc = load_scenario(scenario)
    seed = sc.seed if seed is None else int(seed)
    uncertainty = None
    if controller == "gp":
        say(f"collecting data and fitting the GP (Q = {n_samples or sc.n_samples})")
        train, _ = collect_study_data(sc, seed=seed, n_samples=n_samples)
        gp = fit_study_gp(sc, train, seed=seed)
        uncertainty = FastGP(gp, n_inducing=n_inducing)  # its band contains the exact one
    ctrl = study_controllers(sc, uncertainty)[CONTROLLERS[controller]]
    units = (
        "wheel force divided by M g (normalised input)"
        if sc.input_units == "normalized"
        else "wheel force in N"
    )
    description = (
        f"Scenario '{sc.name}' (adaptive cruise control, docs/acc.md), controller "
        f"'{CONTROLLERS[controller]}'. State x = (v_f follower speed, m/s; v_l lead speed, m/s; "
        f"D gap, m). Input u: {units}. CLF V = (v_f - v_d)^2 with v_d = {sc.v_d} m/s; CBF "
        f"h = D - tau v_f with tau = {sc.tau} s."
    )
    say("translating the controller step to C")
    exported = export_c(ctrl, name, out, precision=precision, description=description)
    rng = np.random.default_rng(seed)
    states = rng.uniform(sc.x0_low, sc.x0_high, size=(int(cases), len(sc.x0_low)))
    expected = ctrl.step_fn(states)
    harness = write_harness(
        exported, states, expected, out, scales=comparison_scales(ctrl, expected, states)
    )
    files = (out / f"{name}.c", out / f"{name}.h", harness)
    build = (
        f"cd {out} && cc {' '.join(HARNESS_FLAGS)} {name}.c {name}_harness.c -lm "
        f"-o {name}_harness && ./{name}_harness"
    )
    if not check:
        return ExportReport(files, build, None, None)
    say("compiling and running the harness")
    cc = find_compiler()
    exe = out / f"{name}_harness"
    cmd = [cc, *HARNESS_FLAGS, f"{name}.c", f"{name}_harness.c", "-lm", "-o", exe.name]
    proc = subprocess.run(cmd, cwd=out, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise CompilationError(
            f"the harness did not compile with {' '.join(HARNESS_FLAGS)}:\n"
            + (proc.stderr or proc.stdout)[-4000:]
        )
    run = subprocess.run([str(exe.resolve())], cwd=out, capture_output=True, text=True)
    return ExportReport(files, build, run.stdout + run.stderr, run.returncode == 0)
