"""The swarm study: centralized and decentralized filters against the unfiltered swarm.

``run_swarm_study(scenario)`` runs the three closed loops of :mod:`~safestab.scenarios.swarm`
and measures what a reader asks of a safety filter: the least distance between two robots, the
steps below the safety distance, when every robot has arrived, how much the filter changed the
nominal input, and the solver's statuses. It also measures how far a general QP solver at its
default (loose) tolerances, as robot testbeds run it, is from the exact optimum: OSQP and
Clarabel through qpsolvers on states of the centralized run, their input difference to the
exact answer and their barrier violations.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any

import numpy as np

from .._io import with_finite_status
from ..formulas import MultiStatus
from .pipeline import MetricsWriter, StepProgress, Study, Summary, silent
from .swarm import (
    MODES,
    PRESETS,
    UNFILTERED,
    SwarmRun,
    SwarmScenario,
    load_swarm_scenario,
    pair_terms,
    simulate_swarm,
)
from .swarm_montecarlo import SWARM_MONTECARLO

__all__ = ["STUDY", "SwarmStudy", "run_swarm_study", "MODES"]


def _summary(sc: SwarmScenario, run: SwarmRun) -> dict[str, Any]:
    """The run's safety, progress and intervention figures (``solver_statuses``: filters only)."""
    dist = run.min_distance()
    goal = sc.starts_and_goals()[1]
    err = np.max(np.linalg.norm(run.p - goal[None], axis=-1), axis=-1)
    arrived = np.flatnonzero(err <= sc.goal_tolerance)
    # the filter's change against the nominal input inside the limits (what an unfiltered
    # robot would do), so the limits alone do not count as a change
    change = np.linalg.norm(run.u - np.clip(run.u_nom, -sc.speed_limit, sc.speed_limit), axis=-1)
    statuses = {s.name: int(np.sum(run.status == s)) for s in MultiStatus}
    return {
        "min_distance_m": float(dist.min()),
        "steps_below_safety_distance": int(np.sum(dist < sc.safety_distance)),
        "arrival_time_s": float(run.t[arrived[0]]) if arrived.size else None,
        "final_max_goal_error_m": float(err[-1]),
        "mean_input_change_mps": float(change.mean()),
        "max_input_change_mps": float(change.max()),
        "max_abs_input_mps": float(np.abs(run.u).max()),
        "solver_statuses": {k: v for k, v in statuses.items() if v}
        if run.mode != UNFILTERED
        else {},
    }


def loose_solver_gap(sc: SwarmScenario, run: SwarmRun, every: int = 25) -> dict[str, Any]:
    """OSQP and Clarabel at their default tolerances on states of a centralized run.

    Returns, per solver: states compared, the largest ``|u_solver - u_exact|`` (m/s), the
    largest barrier violation of the solver's answer (m^2/s, ``max(0, -(c + d.u))``) and the
    share of states where some barrier is violated; or a note where qpsolvers is missing.
    """
    try:
        import qpsolvers
        from scipy import sparse
    except ImportError:  # the "qp" extra
        return {"note": "qpsolvers not installed (pip install safestab[qp])"}
    n = sc.n_robots
    m = 2 * n
    out: dict[str, Any] = {}
    states = range(0, len(run.u), every)
    for solver in ("osqp", "clarabel"):
        if solver not in qpsolvers.available_solvers:
            out[solver] = {"note": "not installed"}
            continue
        gaps, violations, violated = [], [], 0
        for k in states:
            _, c, d = (np.asarray(v) for v in pair_terms(run.p[k], sc.beta, sc.safety_distance))
            G = sparse.csc_matrix(np.concatenate([-d, np.eye(m), -np.eye(m)]))
            h = np.concatenate([c, np.full(2 * m, sc.speed_limit)])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                x = qpsolvers.solve_qp(
                    sparse.eye(m, format="csc"), -run.u_nom[k].reshape(-1), G, h, solver=solver
                )
            if x is None:
                continue
            gaps.append(float(np.abs(x - run.u[k].reshape(-1)).max()))
            viol = float(np.max(np.maximum(0.0, -(c + d @ x))))
            violations.append(viol)
            violated += viol > 0
        out[solver] = {
            "states": len(gaps),
            "max_input_gap_mps": max(gaps) if gaps else None,
            "median_input_gap_mps": float(np.median(gaps)) if gaps else None,
            "max_barrier_violation_m2ps": max(violations) if violations else None,
            "share_of_states_violating": violated / len(gaps) if gaps else None,
            "tolerances": "qpsolvers defaults",
        }
    return out


@dataclasses.dataclass(frozen=True)
class SwarmStudy(MetricsWriter):
    """The three runs, their summaries, the loose-solver gap and the wall times."""

    scenario: SwarmScenario
    runs: dict[str, SwarmRun]
    loose_solvers: dict[str, Any]
    timings: dict[str, float]

    def metrics_document(self) -> dict[str, Any]:
        """Settings, per-mode summaries, the loose-solver gap and timings, as strict JSON data.

        Non-finite numbers become ``None`` (JSON ``null``), listed under ``non_finite`` with
        ``status = "non-finite"``; otherwise ``status = "ok"``.
        """
        sc = self.scenario
        doc = {
            "scenario": sc.name,
            "kind": "swarm",
            "settings": dataclasses.asdict(sc),
            "pairs": sc.n_robots * (sc.n_robots - 1) // 2,
            "runs": {mode: _summary(sc, run) for mode, run in self.runs.items()},
            "loose_solvers_on_centralized_states": self.loose_solvers,
            "timings_s": self.timings,
        }
        return with_finite_status(doc)


def run_swarm_study(scenario: SwarmScenario, *, progress: StepProgress | None = None) -> SwarmStudy:
    """Run the centralized, decentralized and unfiltered swarms, and the loose-solver check.

    Parameters
    ----------
    scenario : SwarmScenario
    progress : callable, optional
        Called as ``progress(message, fraction_done)``.

    Returns
    -------
    SwarmStudy
    """
    report = progress or silent
    runs, timings = {}, {}
    for i, mode in enumerate(MODES):
        report(f"closed loop: {mode}", i / (len(MODES) + 1))
        t0 = time.perf_counter()
        runs[mode] = simulate_swarm(scenario, mode)
        timings[f"{mode}_closed_loop_with_compilation"] = time.perf_counter() - t0
    report("general QP solvers at default tolerances", len(MODES) / (len(MODES) + 1))
    t0 = time.perf_counter()
    loose = loose_solver_gap(scenario, runs["centralized"])
    timings["loose_solvers"] = time.perf_counter() - t0
    report("done", 1.0)
    return SwarmStudy(scenario, runs, loose, timings)


def summary(result: SwarmStudy, document: dict[str, Any]) -> Summary:
    """The per-filter table and the loose solvers' lines a person reads after a swarm run.

    Parameters
    ----------
    result : SwarmStudy
    document : dict
        Its metrics document.

    Returns
    -------
    Summary
    """
    sc = result.scenario
    rows = []
    for mode, m in document["runs"].items():
        arrived = m["arrival_time_s"]
        rows.append(
            (
                mode,
                f"{m['min_distance_m']:.4f}",
                str(m["steps_below_safety_distance"]),
                "never" if arrived is None else f"{arrived:.2f}",
                f"{m['mean_input_change_mps']:.3f}",
                ", ".join(f"{k} {v}" for k, v in m["solver_statuses"].items()),
            )
        )
    lines = [
        f"{solver} at default tolerances on {gap['states']} centralized states: input "
        f"off by up to {gap['max_input_gap_mps']:.2e} m/s, a barrier violated in "
        f"{100 * gap['share_of_states_violating']:.0f} % of them (by up to "
        f"{gap['max_barrier_violation_m2ps']:.2e} m^2/s)"
        for solver, gap in document["loose_solvers_on_centralized_states"].items()
        if isinstance(gap, dict) and gap.get("states")
    ]
    return Summary(
        title=f"swarm '{sc.name}' ({sc.n_robots} robots, {document['pairs']} pair barriers)",
        columns=(
            "filter",
            "min distance [m]",
            "steps < safety",
            "all arrived [s]",
            "mean change [m/s]",
            "statuses",
        ),  # fmt: skip
        rows=rows,
        lines=lines,
    )


def _figures(result: SwarmStudy) -> dict[str, Any]:
    from ..plotting import plot_swarm

    return {"": plot_swarm(result)}


#: The swarm study's place in the pipeline (:mod:`safestab.scenarios.pipeline`).
STUDY = Study(
    kind="swarm",
    scenario_type=SwarmScenario,
    presets=PRESETS,
    load=load_swarm_scenario,
    run=lambda scenario, progress: run_swarm_study(scenario, progress=progress),
    figures=_figures,
    summary=summary,
    table_width=115,
    montecarlo=SWARM_MONTECARLO,
)
