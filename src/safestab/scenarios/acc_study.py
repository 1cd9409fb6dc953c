"""The ACC study end to end: collect data, fit the GP, simulate three controllers, metrics."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._batching import in_threads
from .._io import with_finite_status
from ..controller_names import (
    GP_ROBUST,
    MISMATCHED_MODEL,
    MODEL_CONTROLLERS,
    STUDY_CONTROLLERS,
    TRUE_MODEL,
    NameMap,
    build_compared,
)
from ..controllers import UniversalController
from ..formulas import Region
from ..learning import (
    Calibration,
    Dataset,
    GaussianProcessModel,
    calibration,
)
from ..montecarlo.plugin import GP_MONTECARLO
from ..simulation import Trajectory, simulate
from .acc import PRESETS, ACCScenario, load_scenario
from .kinds import with_overrides
from .pipeline import (
    MetricsWriter,
    StepProgress,
    Study,
    Summary,
    collect_study_data,
    conformal_calibration,
    fit_study_gp,
)

__all__ = [
    "CONTROLLERS",
    "CONFORMAL_DELTA",
    "STUDY",
    "StudyResult",
    "collect_study_data",
    "fit_study_gp",
    "run_study",
    "study_controllers",
    "study_uncertainty",
    "trajectory_metrics",
]

#: The three controllers of the paper's Fig. 4.
CONTROLLERS = STUDY_CONTROLLERS

#: The closed loops and the conformal check run this many at once, in threads (wall times in
#: ``timings`` then overlap). Results do not depend on it.
STUDY_THREADS = 2

#: Miss probability of the calibrated (split conformal, per-trajectory) beta.
CONFORMAL_DELTA = 0.05
#: Calibration trajectories (>= 1/delta - 1 = 19 needed), one state per second along each
#: (:func:`~safestab.scenarios.pipeline.conformal_calibration`).
_CONFORMAL_TRAJECTORIES = 40


@dataclasses.dataclass
class StudyResult(MetricsWriter):
    """Everything the study produced."""

    scenario: ACCScenario
    dataset: Dataset
    gp: GaussianProcessModel
    calibration: Calibration
    trajectories: dict[str, Trajectory]
    metrics: dict[str, dict[str, Any]]
    timings: dict[str, float]
    conformal: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: The GP-robust controller's uncertainty model: ``gp`` itself, or its FastGP cache
    #: (``learning.n_inducing > 0``), whose band the coverage and conformal figures are about.
    uncertainty: Any = None

    def metrics_document(self) -> dict[str, Any]:
        """The metrics of every controller, the GP calibration and timings, as strict JSON data.

        Non-finite numbers (a diverged run) become ``None`` (JSON ``null``); ``status`` is
        ``"ok"`` or ``"non-finite"``, and ``non_finite`` maps the JSON Pointer of each replaced
        value to what it was (``"nan"``, ``"inf"``, ``"-inf"``).
        """
        doc = {
            "scenario": self.scenario.name,
            "settings": {
                "seed": self.scenario.seed,
                "n_samples": self.scenario.n_samples,
                "t_final_s": self.scenario.t_final,
                "dt_s": self.scenario.dt,
            },
            "controllers": self.metrics,
            "gp": {
                "n_samples": len(self.dataset),
                "components": list(self.gp.components_),
                "held_out_coverage": self.calibration.per_component,
                "held_out_joint_coverage": self.calibration.joint,
                "held_out_rmse": self.calibration.rmse,
                "beta": self.scenario.gp_beta,
                "cache": self._cache_document(),
                "conformal": self.conformal,
            },
            "timings_s": self.timings,
        }
        return with_finite_status(doc)

    def _cache_document(self) -> dict[str, Any] | None:
        """The FastGP cache's size and width against the exact GP, or None for the exact GP."""
        unc = self.uncertainty
        if unc is None or unc is self.gp:
            return None
        return {
            "n_inducing": unc.n_inducing_.tolist(),
            "min_beta": unc.min_beta,
            "std_over_exact_at_training_median": unc.std_over_exact_.tolist(),
            "mean_error_norm": unc.mean_error_norm_.tolist(),
            "warnings": list(unc.width_warnings_),
        }


def trajectory_metrics(
    traj: Trajectory, scenario: ACCScenario, reference: Trajectory | None = None
) -> dict[str, Any]:
    """Summary statistics of one closed-loop run.

    Returns min h (m), time with h < 0 (s), RMS speed error to ``v_d`` (m/s), fraction of
    steps per formula region, steps where the conditions were incompatible or the applied
    input broke the CBF condition, the step status (``"ok"`` or the first step that was not OK,
    :meth:`~safestab.simulation.Trajectory.failure_summary`), and, given a ``reference`` run,
    the largest gap in ``h``
    (m) and the RMS gap in ``v_f`` (m/s) between the two.
    """
    h = np.asarray(traj.h)
    x = np.asarray(traj.x)
    region = np.asarray(traj.region)
    dt = scenario.dt
    out: dict[str, Any] = {
        "min_h_m": float(h.min()),
        "time_h_negative_s": float(np.sum(h[:-1] < 0) * dt),
        "rms_speed_error_mps": float(np.sqrt(np.mean((x[:, 0] - scenario.v_d) ** 2))),
        "region_fraction": {r.name: float(np.mean(region == r)) for r in Region},
        "incompatible_steps": int(np.sum(~np.asarray(traj.compatible))),
        "cbf_violations_after_limits": int(np.sum(~np.asarray(traj.cbf_satisfied))),
        "status": traj.failure_summary(),
        "max_abs_u_over_Mg": float(
            np.max(np.abs(np.asarray(traj.u)))
            * scenario.input_scale
            / (scenario.mass * scenario.gravity)
        ),
    }
    if reference is not None:
        out["max_abs_h_gap_to_true_m"] = float(np.max(np.abs(h - np.asarray(reference.h))))
        out["rms_vf_gap_to_true_mps"] = float(
            np.sqrt(np.mean((x[:, 0] - np.asarray(reference.x)[:, 0]) ** 2))
        )
    return out


def study_controllers(
    scenario: ACCScenario, uncertainty: Any = None
) -> NameMap[UniversalController]:
    """The controllers of Fig. 4 with the scenario's parameters and input limits.

    Parameters
    ----------
    scenario : ACCScenario
    uncertainty : UncertaintyModel, optional
        A fitted GP (or its :class:`~safestab.learning.FastGP` cache) for the GP-robust
        controller, used with ``scenario.gp_beta``; without it only the two model-based
        controllers are returned.

    Returns
    -------
    NameMap
        ``{"true model": ..., "mismatched model": ..., "GP-robust": ...}``, a dict that also
        finds the GP-robust controller by its old name ``"GP-corrected"`` (with a
        DeprecationWarning).
    """
    # the controllers' models: with the braking barrier, with the worst lead (docs/acc.md)
    true_sys = scenario.controller_system(scenario.system("true"))
    nominal = scenario.controller_system(scenario.system("nominal"))
    clf, cbf = scenario.certificates()
    common = scenario.trial_study().controller_options()  # those of the Monte Carlo trials
    models = {"true": true_sys, "nominal": nominal, "learned": nominal}

    def build(model: Any, **options: Any) -> UniversalController:
        return UniversalController(model, clf, cbf, **options)

    names = STUDY_CONTROLLERS if uncertainty is not None else MODEL_CONTROLLERS
    return NameMap({
        name: build_compared(name, build, models, uncertainty=uncertainty,
                             gp_beta=scenario.gp_beta, **common)
        for name in names
    })  # fmt: skip


def run_study(
    scenario: ACCScenario,
    *,
    seed: int | None = None,
    progress: StepProgress | None = None,
    n_samples: int | None = None,
    t_final: float | None = None,
) -> StudyResult:
    """Run the study of Fig. 4 for a scenario.

    Parameters
    ----------
    scenario : ACCScenario
    seed : int, optional
        Overrides the scenario's seed (data collection and the GP subset).
    progress : callable, optional
        Called as ``progress(message, fraction_done)``.
    n_samples, t_final : optional
        Override ``Q`` and the horizon (for quick runs). Overrides are checked like the file
        (:meth:`ACCScenario.replace`) and recorded in the result's ``scenario``. The GP's
        hyperparameters come from ``min(hyper_subset, n_samples)`` rows.

    Returns
    -------
    StudyResult

    Raises
    ------
    ScenarioError
        If an override is invalid; raised before any data collection.
    """
    import time

    report = progress or (lambda msg, frac: None)
    # checked like the file (ScenarioError), before any work
    scenario = with_overrides(scenario, seed=seed, n_samples=n_samples, t_final=t_final)
    seed, q, horizon = scenario.seed, scenario.n_samples, scenario.t_final
    true_sys = scenario.system("true")
    timings: dict[str, float] = {}

    # built first, so that the formulas' own parameter checks also run before any work
    study_controllers(scenario)

    report("collecting data", 0.0)
    t0 = time.perf_counter()
    train, test = collect_study_data(scenario, seed=seed, n_samples=q)
    timings["collect_data"] = time.perf_counter() - t0

    report(f"fitting the GP (Q = {q}, n = {true_sys.n_states})", 0.2)
    t0 = time.perf_counter()
    gp = fit_study_gp(scenario, train, seed=seed)
    timings["fit_gp"] = time.perf_counter() - t0
    if scenario.n_inducing:
        report(f"building the FastGP cache (at most {scenario.n_inducing} inducing inputs)", 0.35)
    t0 = time.perf_counter()
    unc = study_uncertainty(scenario, gp)
    if unc is not gp:
        timings["fast_cache"] = time.perf_counter() - t0
    # Lemma 2's band is about omega itself, which the simulator knows: check it there, for
    # the band the controller uses.
    calib = calibration(unc, test.x, np.asarray(scenario.omega(test.x)), scenario.gp_beta)

    controllers = study_controllers(scenario, unc)

    # the two model-based controllers stand on one parametric model: one program, other data
    family = scenario.controller_system(scenario.model_family())
    model_of = {TRUE_MODEL: "true", MISMATCHED_MODEL: "nominal"}

    def simulated(name: str) -> tuple[Trajectory, float]:
        t0 = time.perf_counter()
        ctrl, p = controllers[name], None
        if name in model_of:
            ctrl, p = ctrl.replace(system=family), scenario.model_params(model_of[name])
        traj = simulate(
            ctrl, np.asarray(scenario.x0), t_final=horizon, dt=scenario.dt,
            plant=true_sys, exogenous=scenario.exogenous, params=p,
        )  # fmt: skip
        traj.h.block_until_ready()  # JAX dispatches asynchronously: time the finished run
        return traj, time.perf_counter() - t0

    def job(name: str) -> Any:
        if name == "conformal":
            return _conformal_check(scenario, unc, seed, test)
        if name == "models":  # the mismatched model after the true one: it reuses the program
            return [simulated(n) for n in model_of]
        return simulated(name)

    # the GP-robust loop (memory-bound, most of the run) on one core; the conformal check
    # and the two model-based loops (one after the other) beside it on the other (JAX
    # releases the GIL)
    jobs = [GP_ROBUST, "conformal", "models"]
    report("simulating the controllers beside the conformal check, two at a time", 0.4)
    done = in_threads(
        job, jobs, STUDY_THREADS,
        lambda count: report(f"{count} of {len(jobs)} done", 0.4 + 0.6 * count / len(jobs)),
    )  # fmt: skip
    out = dict(zip(jobs, done, strict=True))
    out.update(zip(model_of, out.pop("models"), strict=True))
    conformal = out.pop("conformal")
    timings["conformal_beta"] = conformal.pop("seconds")
    trajectories: NameMap[Trajectory] = NameMap()
    for name in controllers:  # the order of CONTROLLERS
        trajectories[name], timings[f"simulate {name}"] = out[name]
    ref = trajectories[TRUE_MODEL]
    metrics = NameMap(
        (name, trajectory_metrics(tr, scenario, None if name == TRUE_MODEL else ref))
        for name, tr in trajectories.items()
    )
    # both betas on the GP-robust run's own states (another distribution: no guarantee)
    closed = np.asarray(trajectories[GP_ROBUST].x)[:: max(1, int(round(1.0 / scenario.dt)))]
    omega_cl = np.asarray(scenario.omega(closed))
    for key, beta in (("chosen", scenario.gp_beta), ("conformal", conformal["beta"])):
        cov = calibration(unc, closed, omega_cl, beta).per_component
        conformal[f"closed_loop_coverage_{key}_beta"] = cov.tolist()
    report("done", 1.0)
    return StudyResult(scenario, train, gp, calib, trajectories, metrics, timings, conformal, unc)


def study_uncertainty(scenario: ACCScenario, gp: GaussianProcessModel) -> Any:
    """The GP-robust controller's uncertainty model: ``gp`` or its FastGP cache.

    ``learning.n_inducing = 0``: the exact GP, ``O(Q^2)`` per step. ``M > 0``: FastGP with at
    most ``M`` inducing inputs per component, ``O(M^2)`` per step, whose band contains the
    exact band for every ``beta >= min_beta = max(1, gp_beta)`` (docs/learning.md): the
    controller is then at least as cautious as the exact GP's, and within the cache's width of
    it (``gp.cache`` in the metrics). Its warnings are recorded, not raised (the study's loops
    run in threads).
    """
    if scenario.n_inducing == 0:
        return gp
    from ..learning import FastGP

    return FastGP(gp, scenario.n_inducing, min_beta=max(1.0, scenario.gp_beta), warn=False)


def _conformal_check(scenario, gp, seed, test) -> dict[str, Any]:
    """Per-trajectory split conformal beta on fresh trajectories, and both betas' coverage."""
    import time

    t0 = time.perf_counter()
    # an independent stream: trajectories not used to fit
    out = conformal_calibration(
        scenario, gp, n_trajectories=_CONFORMAL_TRAJECTORIES,
        seed=(seed + 2**31) % 2**32, delta=CONFORMAL_DELTA,
    )  # fmt: skip
    beta_c = out["beta"]
    omega_test = np.asarray(scenario.omega(test.x))
    return {
        **out,
        "held_out_coverage_chosen_beta": calibration(
            gp, test.x, omega_test, scenario.gp_beta
        ).per_component.tolist(),
        "held_out_coverage_conformal_beta": calibration(
            gp, test.x, omega_test, beta_c
        ).per_component.tolist(),
        "seconds": time.perf_counter() - t0,
    }


def summary(result: StudyResult, document: dict[str, Any]) -> Summary:
    """The table and calibration line a person reads after an ACC run.

    Parameters
    ----------
    result : StudyResult
    document : dict
        Its metrics document.

    Returns
    -------
    Summary
    """
    sc = result.scenario
    rows = [
        (
            name,
            f"{m['min_h_m']:.3f}",
            f"{m['time_h_negative_s']:.2f}",
            f"{m['rms_speed_error_mps']:.3f}",
            f"{m.get('max_abs_h_gap_to_true_m', 0.0):.4f}",
            str(m["incompatible_steps"]),
        )
        for name, m in result.metrics.items()
    ]
    cal = result.calibration
    unc = result.uncertainty
    band = (
        ""
        if unc is None or unc is result.gp
        else (f" (FastGP band, inducing inputs {unc.n_inducing_.tolist()})")
    )
    line = (
        f"GP held-out coverage{band} at beta = {sc.gp_beta}: per component "
        f"{[round(float(c), 3) for c in cal.per_component]}, joint {cal.joint:.3f}; "
        f"RMSE {[float(f'{r:.2e}') for r in cal.rmse]} m/s^2"
    )
    return Summary(
        title=f"ACC study '{sc.name}' (Q = {len(result.dataset)})",
        columns=(
            "controller",
            "min h [m]",
            "h<0 [s]",
            "rms v_f-v_d",
            "max|h-h_true|",
            "incompat.",
        ),  # fmt: skip
        rows=rows,
        lines=[line],
    )


def _figures(result: StudyResult) -> dict[str, Any]:
    from ..plotting import plot_acc_study

    return {"": plot_acc_study(result)}


#: The ACC study's place in the pipeline (:mod:`safestab.scenarios.pipeline`).
STUDY = Study(
    kind="acc",
    scenario_type=ACCScenario,
    presets=PRESETS,
    load=load_scenario,
    run=lambda scenario, progress: run_study(scenario, progress=progress),
    figures=_figures,
    summary=summary,
    montecarlo=GP_MONTECARLO,
)
