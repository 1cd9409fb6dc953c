"""Export a scenario's controller with its C test harness (``safestab export``).

The scenario's side of the export: build the preset's controller (collect, fit, cache), export
it with :mod:`safestab.export`, write and run the harness, and optionally run it on a target.
The export package itself sees only a controller.
"""

from __future__ import annotations

import dataclasses
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..controller_names import EXPORT_CHOICES, export_choice
from ..errors import CompilationError, ParameterError
from ..export.embedded import TARGETS, run_on_target
from ..export.exporter import check_name, check_precision, export_c
from ..export.float_safety import float_check_states, float_refusal, float_safe_controller
from ..export.harness import HARNESS_FLAGS, comparison_scales, write_harness
from ..export.native import find_compiler
from ..learning import FastGP
from .acc import ACCScenario
from .acc_study import collect_study_data, fit_study_gp, study_controllers
from .loading import load as load_any_scenario
from .obstacle import ObstacleScenario
from .obstacle_study import calibrate_beta, fit_obstacle_gp, obstacle_controller

__all__ = [
    "ExportReport",
    "export_scenario",
    "scenario_controller",
]


@dataclasses.dataclass(frozen=True)
class ExportReport:
    """What :func:`export_scenario` wrote and, when checked, what the harness said."""

    files: tuple[Path, ...]
    build_command: str
    harness_output: str | None
    passed: bool | None
    exported: Any = None  #: the ExportedC
    states: Any = None  #: the harness's recorded states, (N, n)
    embedded: Any = None  #: with ``target``, the EmbeddedReport
    #: What the export decided on its own and why (a microcontroller's build in double where
    #: float cannot carry the GP cache)
    notes: tuple[str, ...] = ()


def _writable_folder(out: str | Path) -> Path:
    """``out``, created if missing and proved writable, made absolute (once, here).

    The harness is compiled and run, and the embedded build's tools are run, in this folder
    or below it: each subprocess gets an absolute path, whatever its own working folder.
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".safestab-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ParameterError(f"out must be a writable folder, got {str(out)!r}: {exc}") from None
    return out.absolute()


def export_scenario(
    scenario: str | Path,
    out: str | Path,
    *,
    controller: str = "gp",
    name: str | None = None,
    precision: str | None = None,
    cases: int = 256,
    n_samples: int | None = None,
    n_inducing: int = 32,
    seed: int | None = None,
    check: bool = True,
    target: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> ExportReport:
    """Export an ACC or obstacle controller of a scenario to ``out`` with a C test harness.

    Writes ``<name>.c``, ``<name>.h`` and ``<name>_harness.c`` (states drawn uniformly from
    the scenario's learning box ``x0_low .. x0_high``, outputs of the JAX step). With
    ``check``, compiles the harness with :data:`HARNESS_FLAGS` and runs it.

    Parameters
    ----------
    scenario : str or path
        A preset name or a TOML file (see :func:`~safestab.scenarios.load_scenario`).
    out : path
        Output folder, created if needed; a relative path is taken against the current
        working folder when the function is called.
    controller : {"gp", "nominal", "true"} or the controller's name
        The short names of ``"GP-robust"``, ``"mismatched model"`` and ``"true model"``;
        either is taken.
        The GP-robust controller (GP fitted as in the study, exported through a
        :class:`~safestab.learning.FastGP` cache whose band contains the exact GP's), or the
        controller built on the nominal or the true model. For the obstacle scenario, the
        study's relaxed controller without input limits.
    name : str, optional
        Prefix of the C names and files (default ``"acc"`` or ``"obstacle"``).
    precision : {"double", "float"}, optional
        Default: the target's (``"float"`` for ``cortex-m4``, ``"double"`` for
        ``cortex-m7``), else ``"double"``. With a ``target``, float where float cannot carry
        the GP cache (:func:`~safestab.export.float_safety.float_refusal`) becomes double,
        said in the progress and the report's ``notes``; without one it is refused.
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
    target : {"cortex-m4", "cortex-m7"}, optional
        Also cross-compile the step and its harness for this core, run them under QEMU and
        measure size, stack and instructions per step
        (:func:`~safestab.export.embedded.run_on_target`; needs ``arm-none-eabi-gcc`` and
        ``qemu-system-arm``, installed with apt-get where this process may).
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
    say = progress or (lambda msg: None)
    if target is not None and target not in TARGETS:
        raise ParameterError(f"target must be one of {sorted(TARGETS)}, got {target!r}")
    if precision is None:
        precision = TARGETS[target].precision if target is not None else "double"
    controller = export_choice(controller)
    if controller not in EXPORT_CHOICES:  # before the output folder is made
        raise ParameterError(_bad_controller(controller))
    if int(cases) < 1:
        raise ParameterError(f"cases must be >= 1, got {cases!r}")
    # every option checked before the data collection and the GP fit (minutes)
    if name is not None:
        check_name(name)
    check_precision(precision)
    if (
        isinstance(n_inducing, bool)
        or not isinstance(n_inducing, int | np.integer)
        or n_inducing < 1
    ):
        raise ParameterError(f"n_inducing must be an integer >= 1, got {n_inducing!r}")
    out = _writable_folder(out)
    sc = load_any_scenario(scenario)
    seed = sc.seed if seed is None else int(seed)
    ctrl, description, default_name = scenario_controller(
        sc, controller, seed=seed, n_samples=n_samples, n_inducing=n_inducing, progress=say
    )
    name = default_name if name is None else name
    rng = np.random.default_rng(seed)
    states = rng.uniform(sc.x0_low, sc.x0_high, size=(int(cases), len(sc.x0_low)))
    if target is not None and hasattr(ctrl.uncertainty, "unpadded"):
        ctrl = ctrl.replace(uncertainty=ctrl.uncertainty.unpadded())  # fewer operations
    notes: list[str] = []
    if precision == "float" and target is not None:
        # a microcontroller's build picks double where float cannot carry the GP cache (the
        # Cortex-M4F runs it in software: its instruction count says what that costs)
        as_float = states.astype(np.float32).astype(np.float64)
        box = float_check_states(sc.x0_low, sc.x0_high, extra_states=as_float)
        reason = float_refusal(ctrl, box)
        if reason is not None:
            precision = "double"
            notes.append(
                f"{reason}. The build for {target} is in double instead (in software where "
                "the FPU is single precision: its instruction count says what that costs)"
            )
            say(notes[-1])
            description += f" Double, not float: {notes[-1]}."
    if precision == "float":
        # the float step sees float states: record those, so that the comparison is of
        # the step's arithmetic, not of the rounding of its input
        states = states.astype(np.float32).astype(np.float64)
        ctrl, margin = float_safe_controller(ctrl, sc.x0_low, sc.x0_high, extra_states=states)
        description += (
            f" Float variant: GP band widened for float rounding, CBF margin {margin:.3g} "
            "(docs/export.md, 'Float that stays safe')."
        )
    say("translating the controller step to C")
    layout = "host" if target is None else "embedded"
    exported = export_c(
        ctrl, name, out, precision=precision, description=description, layout=layout
    )
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
        return ExportReport(files, build, None, None, exported, states, notes=tuple(notes))
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
    embedded = None
    if target is not None:
        embedded = run_on_target(out, name, exported, states, target, progress=say)
    return ExportReport(
        files,
        build,
        run.stdout + run.stderr,
        run.returncode == 0,
        exported,
        states,
        embedded,
        tuple(notes),
    )


def scenario_controller(
    sc: Any,
    controller: str,
    *,
    seed: int | None = None,
    n_samples: int | None = None,
    n_inducing: int = 32,
    progress: Callable[[str], None] | None = None,
) -> tuple[Any, str, str]:
    """A scenario's controller as :func:`export_scenario` exports it.

    Parameters
    ----------
    sc : ACCScenario or ObstacleScenario
    controller : {"gp", "nominal", "true"} or the controller's name
        The short names of ``"GP-robust"``, ``"mismatched model"`` and ``"true model"``;
        either is taken.
        With ``"gp"``, the data are collected and the GP fitted as in the study (seconds to
        a minute) and the controller uses its :class:`~safestab.learning.FastGP` cache.
    seed, n_samples : optional
        Override the scenario's.
    n_inducing : int
    progress : callable, optional

    Returns
    -------
    (controller, description, default_name)
        The :class:`~safestab.UniversalController`, the header text (model, units) and the
        default C prefix (``"acc"`` or ``"obstacle"``).

    Raises
    ------
    ParameterError
        If ``controller`` is unknown or the scenario is of another kind.
    """
    controller = export_choice(controller)
    if controller not in EXPORT_CHOICES:
        raise ParameterError(_bad_controller(controller))
    seed = sc.seed if seed is None else int(seed)
    say = progress or (lambda msg: None)
    if isinstance(sc, ACCScenario):
        return _acc_controller(sc, controller, seed, n_samples, n_inducing, say)
    if isinstance(sc, ObstacleScenario):
        return _obstacle_controller(sc, controller, seed, n_samples, n_inducing, say)
    raise ParameterError(
        f"export takes an ACC or obstacle scenario, got {type(sc).__name__} "
        f"({sc.name!r}); export a safety filter with safestab.export_c"
    )


def _bad_controller(controller: Any) -> str:
    choices = ", ".join(f"{short!r} ({full!r})" for short, full in EXPORT_CHOICES.items())
    return f"controller must be one of {choices}, by either name, got {controller!r}"


def _acc_controller(sc, controller, seed, n_samples, n_inducing, say):
    uncertainty = None
    if controller == "gp":
        say(f"collecting data and fitting the GP (Q = {n_samples or sc.n_samples})")
        train, _ = collect_study_data(sc, seed=seed, n_samples=n_samples)
        gp = fit_study_gp(sc, train, seed=seed)
        uncertainty = FastGP(gp, n_inducing=n_inducing)  # its band contains the exact one
    ctrl = study_controllers(sc, uncertainty)[EXPORT_CHOICES[controller]]
    units = (
        "wheel force divided by M g (normalised input)"
        if sc.input_units == "normalized"
        else "wheel force in N"
    )
    description = (
        f"Scenario '{sc.name}' (adaptive cruise control, docs/acc.md), controller "
        f"'{EXPORT_CHOICES[controller]}'. State x = (v_f follower speed, m/s; v_l lead speed, m/s; "
        f"D gap, m). Input u: {units}. CLF V = (v_f - v_d)^2 with v_d = {sc.v_d} m/s; CBF "
        f"h = D - tau v_f with tau = {sc.tau} s."
    )
    return ctrl, description, "acc"


def _obstacle_controller(sc, controller, seed, n_samples, n_inducing, say):
    sc = sc.replace(seed=seed, **({} if n_samples is None else {"n_samples": n_samples}))
    uncertainty = None
    beta_note = ""
    if controller == "gp":
        say(f"collecting data and fitting the GP (Q = {sc.n_samples})")
        _, gp, _, gain = fit_obstacle_gp(sc.replace(n_inducing=0))
        uncertainty = FastGP(gp, n_inducing=n_inducing)  # its band contains the exact one
        beta_note = f" GP beta = {sc.gp_beta:g} (learning.gp_beta)."
        gain_note = ""
        if gain is not None:
            # the controller's input matrix is k_nom I + D (learning.input_gain = "learned")
            sc = sc.with_learned_gain(gain)
            gain_note = f" Learned input-gain error D = {gain.matrix.tolist()} (m/s per m/s)."
        if sc.beta_method == "conformal":
            # the beta the study runs with, calibrated for the exported cache itself
            say("calibrating beta on fresh trajectories (learning.beta_method = 'conformal')")
            cal = calibrate_beta(sc, uncertainty)
            sc = sc.replace(gp_beta=cal["beta"])
            beta_note = (
                f" GP beta = {cal['beta']:.6g}, split conformal on {cal['n_trajectories']} fresh "
                f"trajectories for this cache (learning.beta_method = 'conformal'; the file's "
                f"gp_beta is {cal['chosen_beta']:g}): {cal['statement']}"
            )
        beta_note += gain_note
    ctrl = obstacle_controller(sc, EXPORT_CHOICES[controller], uncertainty)
    description = (
        f"Scenario '{sc.name}' (a point robot passing a disc obstacle, docs/obstacle.md), "
        f"controller '{EXPORT_CHOICES[controller]}', relaxed formula, no input limits. State "
        "x = (x1, x2) position, m. Input u: velocity, m/s. CLF V = x^T P x with P = "
        f"diag{tuple(sc.P)} (goal at the origin); CBF h = |x - x_o|^2 - r^2 with x_o = "
        f"({sc.obstacle_x1}, 0) m, r = {sc.radius} m; V and h in m^2.{beta_note}"
    )
    return ctrl, description, "obstacle"
