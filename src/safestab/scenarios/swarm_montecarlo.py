"""The swarm's Monte Carlo: many perturbed swaps of every compared mode, batched.

Trial ``i`` perturbs the start angles with the seed :func:`trial_seed` ``(seed, i)`` (a
function of ``seed`` and ``i`` only, so a trial's records do not depend on the number of
trials or the chunk size) and sends each robot to the antipode of its perturbed start, as
:meth:`~safestab.scenarios.swarm.SwarmScenario.starts_and_goals` does with that seed: the
scenario ``replace(seed=trial_seed(seed, i))`` runs trial ``i`` alone
(:func:`~safestab.scenarios.swarm.simulate_swarm`, ``safestab run --seed``). Each mode runs
a chunk of trials as one jitted, ``vmap``-ed closed loop whose recorder keeps running
statistics only: the least pair distance at the samples and, exactly, over every hold
interval (:func:`least_distance_over_hold`), the counts below the safety distance, the
arrival time, the final goal error, the mean change to the input and the solver's statuses.
"""

from __future__ import annotations

import dataclasses
import io
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._batching import in_threads
from .._io import with_finite_status
from ..errors import ParameterError
from ..formulas import MultiStatus
from .pipeline import MonteCarloOptions, StudyMonteCarlo, TaskProgress
from .swarm import MODES, UNFILTERED, SwarmScenario, check_mode, current_mode, swarm_closed_loop

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_TRIALS",
    "RECORDS",
    "SWARM_MONTECARLO",
    "SwarmMonteCarlo",
    "least_distance_over_hold",
    "run_swarm_montecarlo",
    "trial_seed",
]

#: Trials of ``safestab mc --scenario swarm`` without ``--trials``, and trials per batch.
DEFAULT_TRIALS, DEFAULT_CHUNK_SIZE = 32, 4
#: The per-trial records, each of shape (trials, modes): name and unit.
RECORDS = {
    "min_distance_at_samples": "m",
    "min_distance": "m",  # exact, over every hold interval (the samples included)
    "samples_below": "samples",
    "holds_below": "hold intervals",
    "arrival_time": "s",  # NaN: never
    "final_max_goal_error": "m",
    "mean_input_change": "m/s",
}
_TASK = "chunks of trials (every mode)"
#: m: a least distance within this of the safety distance is *at* it, to rounding. A filter
#: whose barrier is active holds a pair exactly at the safety distance, and the positions'
#: rounding over a run (about 1e-16 of the arena's size per step, 1e-12 m after a thousand
#: steps) decides on which side of it the recorded distance falls. Such trials count as safe
#: and are reported apart (``at_safety_distance``), so that no count hinges on rounding.
ROUNDING_BAND_M = 1e-9


def trial_seed(seed: int, index: int) -> int:
    """The seed of trial ``index``'s start jitter, a function of ``(seed, index)`` only.

    Parameters
    ----------
    seed : int
        The study's seed, in ``[0, 2**32 - 1]``.
    index : int
        The trial, ``>= 0``.

    Returns
    -------
    int
        In ``[0, 2**32 - 1]``: a swarm scenario's ``seed`` that runs the trial alone.
    """
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def least_distance_over_hold(d0: Any, dv: Any, dt: float) -> Any:
    """The exact least of ``|d0 + s dv|`` over ``s`` in ``[0, dt]``.

    With the inputs held over a step, two single integrators' relative position is
    ``d0 + s dv`` (``d0 = p_i - p_j`` at the sample, ``dv = u_i - u_j``): its distance is
    least at ``s* = clip(-d0.dv / |dv|^2, 0, dt)`` (``s* = 0`` where ``dv = 0``).

    Parameters
    ----------
    d0, dv : arrays of shape (..., 2)
        Relative position (m) and relative velocity (m/s).
    dt : float
        The hold, s.

    Returns
    -------
    array of shape (...)
        The least distance over ``[t_k, t_k + dt]``, m (at most ``|d0|``).
    """
    d0, dv = jnp.asarray(d0), jnp.asarray(dv)
    vv = jnp.sum(dv * dv, -1)
    moving = vv > 0
    s = jnp.where(moving, -jnp.sum(d0 * dv, -1) / jnp.where(moving, vv, 1.0), 0.0)
    s = jnp.clip(s, 0.0, dt)
    return jnp.linalg.norm(d0 + s[..., None] * dv, axis=-1)


class _TrialRecorder:
    """Running statistics of one swarm run (no history): the records of :data:`RECORDS`."""

    def __init__(self, sc: SwarmScenario) -> None:
        self.sc = sc
        self.i, self.j = np.triu_indices(sc.n_robots, 1)

    def _at_sample(self, pos, goal):
        dist = jnp.min(jnp.linalg.norm(pos[self.i] - pos[self.j], axis=-1))
        err = jnp.max(jnp.linalg.norm(pos - goal, axis=-1))
        return dist, err

    def init(self, x0, goal):
        inf = jnp.asarray(jnp.inf, jnp.float64)
        zero = jnp.asarray(0, jnp.int64)
        return {
            "min_sample": inf, "min_exact": inf, "samples_below": zero, "holds_below": zero,
            "arrival": jnp.asarray(-1, jnp.int64), "change": jnp.asarray(0.0, jnp.float64),
            "statuses": jnp.zeros(len(MultiStatus), jnp.int64),
        }  # fmt: skip

    def _sample(self, state, k, pos, goal):
        sc = self.sc
        dist, err = self._at_sample(pos, goal)
        arrived = (state["arrival"] < 0) & (err <= sc.goal_tolerance)
        return {
            **state,
            "min_sample": jnp.minimum(state["min_sample"], dist),
            "samples_below": state["samples_below"] + (dist < sc.safety_distance),
            "arrival": jnp.where(arrived, k, state["arrival"]),
        }

    def update(self, state, k, t, pos, out, goal):
        sc = self.sc
        state = self._sample(state, k, pos, goal)
        u = out["u"]
        hold = jnp.min(least_distance_over_hold(pos[self.i] - pos[self.j], u[self.i] - u[self.j],
                                                sc.dt))  # fmt: skip
        nominal = jnp.clip(out["u_nom"], -sc.speed_limit, sc.speed_limit)
        codes = jnp.arange(len(MultiStatus))
        state = {
            **state,
            "min_exact": jnp.minimum(state["min_exact"], hold),
            "holds_below": state["holds_below"] + (hold < sc.safety_distance),
            "change": state["change"] + jnp.sum(jnp.linalg.norm(u - nominal, axis=-1)),
            "statuses": state["statuses"] + jnp.sum(out["status"][:, None] == codes[None, :], 0),
        }
        return state, None

    def finish(self, state, ys, pos_final, out_final, t_final, goal):
        sc = self.sc
        steps = int(round(sc.t_final / sc.dt))
        state = self._sample(state, steps, pos_final, goal)
        _, err = self._at_sample(pos_final, goal)
        arrival = state["arrival"]
        return {
            "min_distance_at_samples": state["min_sample"],
            # the last sample closes the last hold interval: the exact minimum covers it
            "min_distance": jnp.minimum(state["min_exact"], state["min_sample"]),
            "samples_below": state["samples_below"],
            "holds_below": state["holds_below"],
            "arrival_time": jnp.where(arrival >= 0, arrival * sc.dt, jnp.nan),
            "final_max_goal_error": err,
            "mean_input_change": state["change"] / (steps * sc.n_robots),
            "statuses": state["statuses"],
        }


def trial_starts(sc: SwarmScenario, seed: int, indices: Any) -> tuple[np.ndarray, np.ndarray]:
    """Starts and goals of the trials ``indices``, each of shape (B, N, 2), m."""
    pairs = [sc.starts_and_goals(trial_seed(seed, i)) for i in indices]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


@dataclasses.dataclass(frozen=True)
class SwarmMonteCarlo:
    """The swarm's Monte Carlo: per-trial records of every mode, and the settings.

    Attributes
    ----------
    scenario : SwarmScenario
    seed : int
    modes : tuple of str
    chunk_size : int
    records : dict of str to array of shape (trials, modes)
        :data:`RECORDS`, and ``statuses`` of shape (trials, modes, len(MultiStatus)): the
        robot-steps of each solver status (the centralized filter's status counts once per
        robot).
    timings : dict of str to float
        Wall-clock seconds per mode (compilation included) and in total.
    """

    scenario: SwarmScenario
    seed: int
    modes: tuple[str, ...]
    chunk_size: int
    records: dict[str, np.ndarray]
    timings: dict[str, float]

    @property
    def trial_seeds(self) -> np.ndarray:
        """Each trial's :func:`trial_seed`, shape (trials,)."""
        n = self.records["min_distance"].shape[0]
        return np.array([trial_seed(self.seed, i) for i in range(n)], np.int64)


def run_swarm_montecarlo(
    scenario: SwarmScenario,
    *,
    trials: int = DEFAULT_TRIALS,
    seed: int = 0,
    modes: tuple[str, ...] = MODES,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    workers: int | None = None,
    progress: TaskProgress | None = None,
) -> SwarmMonteCarlo:
    """Run ``trials`` perturbed swaps of every mode, ``chunk_size`` trials per compiled batch.

    Parameters
    ----------
    scenario : SwarmScenario
        Its ``seed`` is not used: trial ``i``'s jitter comes from ``trial_seed(seed, i)``.
    trials : int
        ``>= 1``.
    seed : int
        In ``[0, 2**32 - 1]``.
    modes : tuple of str
        Distinct modes of :data:`~safestab.scenarios.swarm.MODES`.
    chunk_size : int
        ``>= 1``; the last chunk is padded to the same shape. Results do not depend on it.
        The default, 4, ran fastest for the 12-robot preset on a 2-core machine: the
        centralized filter's solver loops run until every trial of a batch is done, so a
        larger batch waits on its slowest trial (docs/swarm.md).
    workers : int, optional
        Chunks run at once in threads (XLA releases the GIL), after the first has compiled
        the loop; default 2 where the machine has 2 or more CPUs, else 1. Results do not
        depend on it.
    progress : callable, optional
        ``progress(task, chunks_done, chunks_total)`` after each chunk of each mode.

    Returns
    -------
    SwarmMonteCarlo

    Raises
    ------
    ParameterError
        For a count or seed out of range, or a mode repeated.
    ScenarioError
        For an unknown mode.
    """
    if workers is None:
        workers = 2 if (os.cpu_count() or 1) >= 2 else 1
    for name, value, low in (("trials", trials, 1), ("chunk_size", chunk_size, 1),
                             ("seed", seed, 0), ("workers", workers, 1)):  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise ParameterError(f"{name} must be an integer >= {low}, got {value!r}")
    if seed > 2**32 - 1:
        raise ParameterError(f"seed must be <= 2**32 - 1, got {seed!r}")
    modes = tuple(check_mode(m, "modes") for m in modes)
    if not modes or len(set(modes)) != len(modes):
        raise ParameterError(f"modes must be distinct and at least one, got {modes!r}")
    report = progress or (lambda task, done, total: None)
    size = min(int(chunk_size), int(trials))
    starts = [range(a, min(a + size, trials)) for a in range(0, trials, size)]
    total, done = len(starts) * len(modes), 0
    recorder = _TrialRecorder(scenario)
    columns: list[dict[str, np.ndarray]] = []
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    for mode in modes:
        t0 = time.perf_counter()
        run = jax.jit(jax.vmap(swarm_closed_loop(scenario, mode, recorder)))

        def chunk(idx: range, run: Any = run) -> dict[str, np.ndarray]:
            start, goal = trial_starts(scenario, seed, list(idx))
            pad = size - len(idx)  # the last chunk: the same shape, so no new compilation
            if pad:
                start = np.concatenate([start, np.repeat(start[-1:], pad, 0)])
                goal = np.concatenate([goal, np.repeat(goal[-1:], pad, 0)])
            out = jax.device_get(run(jnp.asarray(start), jnp.asarray(goal)))
            return {k: np.asarray(v)[: len(idx)] for k, v in out.items()}

        def count(_: int) -> None:
            nonlocal done
            done += 1
            report(_TASK, done, total)

        # the first chunk compiles the loop, in this thread; the others share it in threads
        parts = [chunk(starts[0])]
        count(1)
        parts += in_threads(chunk, starts[1:], int(workers), count)
        columns.append({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
        timings[f"{mode}_with_compilation"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    records = {k: np.stack([c[k] for c in columns], 1) for k in columns[0]}
    return SwarmMonteCarlo(scenario, int(seed), modes, size, records, timings)


# -- summary and outputs ------------------------------------------------------------------


def _quantiles(values: np.ndarray) -> dict[str, float]:
    return {str(q): float(np.quantile(values, q)) for q in (0.0, 0.01, 0.1, 0.5)}


def _rate(count: int, n: int) -> dict[str, Any]:
    from ..montecarlo.stats import clopper_pearson

    low, high = clopper_pearson(int(count), int(n))
    return {"count": int(count), "trials": int(n), "rate": count / n, "ci95": [low, high]}


def guarantee(sc: SwarmScenario) -> dict[str, Any]:
    """What the filters guarantee in the sampled-data setting of these runs, and on what."""
    beta_dt = sc.beta * sc.dt
    return {
        "setting": "sampled: the filter runs at t_k = k dt and its input is held over "
        "[t_k, t_k + dt] (zero-order hold, exact for single integrators); no sampled-data "
        "margin",
        "at_samples": "where every solver status of a step is SOLVED, the input meets "
        "2 (p_i - p_j).(u_i - u_j) >= -beta h_ij for every pair at t_k (the decentralized "
        "filter: each robot its half of it)",
        "over_the_hold": "along a hold h_ij(t_k + s) = h_k + s h'(t_k) + s^2 |u_i - u_j|^2 is "
        "convex in s (-h'' <= 0: the margin's M is 0, docs/deployed.md), so "
        "h_ij(t_k + s) >= h_k (1 - beta s): from h_k >= 0 with beta dt <= 1, h_ij >= 0 over "
        "the whole hold and at the next sample"
        + (
            f"; here beta dt = {beta_dt:g}"
            if beta_dt <= 1
            else f"; here beta dt = {beta_dt:g} > 1, so nothing is promised beyond t_k"
        ),
        "beta_dt": beta_dt,
        "measured_by": "min_distance (exact over every hold) and min_distance_at_samples, "
        "against the safety distance; a step whose status is not SOLVED carries no promise "
        "(solver_statuses)",
    }


def metrics_document(result: SwarmMonteCarlo) -> dict[str, Any]:
    """Settings, per-mode rates with 95 % intervals, the guarantee and timings; strict JSON.

    A trial is safe when no pair is closer than the safety distance at any sample or between
    samples (``min_distance``, exact), to rounding (:data:`ROUNDING_BAND_M`); the safe trials
    whose least distance is the safety distance to rounding are counted apart
    (``at_safety_distance``). Non-finite numbers become ``null``; ``status`` is
    ``"ok"`` or ``"non-finite"``.
    """
    sc, rec = result.scenario, result.records
    n = rec["min_distance"].shape[0]
    seeds = result.trial_seeds
    band = ROUNDING_BAND_M
    floor = sc.safety_distance - band
    modes: dict[str, Any] = {}
    for c, mode in enumerate(result.modes):
        least = rec["min_distance"][:, c]
        arrival = rec["arrival_time"][:, c]
        worst = int(np.argmin(least))
        counts = rec["statuses"][:, c].sum(0)
        modes[mode] = {
            "safe": _rate(int(np.sum(least >= floor)), n),
            "at_safety_distance": int(np.sum(np.abs(least - sc.safety_distance) < band)),
            "safe_at_samples": _rate(int(np.sum(rec["min_distance_at_samples"][:, c] >= floor)), n),
            "arrived": _rate(int(np.sum(np.isfinite(arrival))), n),
            "min_distance_quantiles_m": _quantiles(least),
            "min_distance_at_samples_quantiles_m": _quantiles(rec["min_distance_at_samples"][:, c]),
            "arrival_time_quantiles_s": (
                _quantiles(arrival[np.isfinite(arrival)]) if np.isfinite(arrival).any() else None
            ),
            "worst_trial": {
                "index": worst,
                "min_distance_m": float(least[worst]),
                "seed": int(seeds[worst]),
                "reproduce": f"safestab run --scenario {sc.name} --seed {int(seeds[worst])}"
                " (with this scenario's other keys)",
            },
            "mean_input_change_mps": float(np.mean(rec["mean_input_change"][:, c])),
            "solver_statuses": (
                {}
                if mode == UNFILTERED
                else {s.name: int(counts[s]) for s in MultiStatus if counts[s]}
            ),
            "trials_with_unsolved_steps": (
                0 if mode == UNFILTERED else int(np.sum(rec["statuses"][:, c, 1:].sum(-1) > 0))
            ),
        }
    doc = {
        "scenario": sc.name,
        "kind": "swarm",
        "settings": {
            "scenario": dataclasses.asdict(sc),
            "trials": n,
            "seed": result.seed,
            "chunk_size": result.chunk_size,
            "modes": list(result.modes),
            "trial_seed": "numpy SeedSequence([seed, i]).generate_state(1)[0], the scenario "
            "seed that runs trial i alone",
        },
        "summary": {
            "trials": n,
            "safety_distance_m": sc.safety_distance,
            "rounding_band_m": ROUNDING_BAND_M,
            "modes": modes,
            "guarantee": guarantee(sc),
        },
        "timings_s": result.timings,
    }
    return with_finite_status(doc)


def trials_npz_bytes(result: SwarmMonteCarlo) -> bytes:
    """Every record (trials, modes), the statuses, the modes and the trials' seeds, as .npz."""
    buf = io.BytesIO()
    np.savez(
        buf, modes=np.array(result.modes), trial_seed=result.trial_seeds,
        status_names=np.array([s.name for s in MultiStatus]), **result.records,
    )  # fmt: skip
    return buf.getvalue()


def plot_swarm_montecarlo(result: SwarmMonteCarlo) -> Any:
    """ECDFs per mode: least pair distance over the safety distance (exact), and arrival time.

    The left panel's axis is the margin ``min distance - safety distance`` (m; below 0: a
    collision course) on a symmetric log scale, linear within a tenth of the smallest mode's
    median ``|margin|``, so that a filter's margin of micrometres and an unfiltered run's
    near-collision of half a metre show on one axis.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    from ..montecarlo.report import symlog_threshold

    sc, rec = result.scenario, result.records
    n = rec["min_distance"].shape[0]
    margin = rec["min_distance"] - sc.safety_distance  # (trials, modes)
    fig, ax = plt.subplots(1, 2, figsize=(7.5, 3.0), constrained_layout=True)
    y = np.arange(1, n + 1) / n
    for c, mode in enumerate(result.modes):
        ax[0].step(np.sort(margin[:, c]), y, where="post", label=mode)
        arrival = np.sort(rec["arrival_time"][:, c])
        reached = arrival[np.isfinite(arrival)]
        ax[1].step(reached, y[: reached.size], where="post", label=mode)
    ax[0].axvline(0.0, color="k", lw=1, ls="--", label="safety distance")
    lin = symlog_threshold(margin)
    ax[0].set_xscale("symlog", linthresh=lin)
    # 0 and every fourth decade beyond the linear range, on the sides the data reach
    ticks = [0.0]
    for sign in (-1.0, 1.0):
        side = sign * margin[sign * margin > 0]
        if side.size:
            top = int(np.ceil(np.log10(side.max())))
            low = int(np.ceil(np.log10(10 * lin)))
            ticks += [sign * 10.0**e for e in range(top, low - 1, -4)]
    ax[0].set_xticks(sorted(ticks))
    ax[0].tick_params(axis="x", labelsize=7)
    ax[0].set_xlabel("least pair distance - safety distance (m)\n(exact between samples)")
    ax[0].set_ylabel("fraction of trials (ECDF)")
    ax[0].set_title(f"{sc.n_robots} robots, {n} trials", fontsize=9)
    ax[0].legend(fontsize=7)
    ax[1].set_xlabel("time until all robots are at their goals (s)")
    ax[1].set_xlim(0, sc.t_final)
    ax[1].set_ylim(0, 1.02)
    ax[1].set_title("arrival (a curve below 1: trials that never arrive)", fontsize=9)
    return fig


def summary_table(result: SwarmMonteCarlo, document: dict[str, Any]) -> Any:
    """The per-mode summary a person reads after a swarm Monte Carlo, as a rich Table."""
    from rich import box
    from rich.table import Table
    from rich.text import Text

    s = document["summary"]
    table = Table(
        title=Text(
            f"Monte Carlo '{result.scenario.name}': {s['trials']} trials, "
            f"safety distance {s['safety_distance_m']} m"
        ),  # fmt: skip
        caption=Text(
            f"safe: no pair below the safety distance at or between the samples "
            f"(exact, to {ROUNDING_BAND_M:g} m: 'at' counts the safe trials whose least "
            f"distance is the safety distance to that). The guarantee, its setting and "
            "each mode's worst trial: summary.guarantee and "
            "summary.modes.<mode>.worst_trial in the metrics JSON"
        ),  # fmt: skip
        box=box.SIMPLE_HEAD,
        padding=(0, 1),
    )
    table.add_column(Text("mode"), justify="left", no_wrap=True)
    for col in ("safe\n[95% CI]", "least pair\ndistance [m]\nmin / median"):
        table.add_column(Text(col), justify="right", no_wrap=True)
    for col in ("arrived", "solver statuses\nrobot-steps"):
        table.add_column(Text(col), justify="right", overflow="fold")
    for mode, m in s["modes"].items():
        q = m["min_distance_quantiles_m"]
        lo, hi = m["safe"]["ci95"]
        table.add_row(*map(Text, (
            mode,
            f"{m['safe']['count']}/{m['safe']['trials']} (at {m['at_safety_distance']})"
            f"\n[{lo:.3f}, {hi:.3f}]",
            f"{q['0.0']:.4f} / {q['0.5']:.4f}",
            f"{m['arrived']['count']}/{m['arrived']['trials']}",
            ", ".join(f"{k} {v:,}" for k, v in m["solver_statuses"].items()) or "-",
        )))  # fmt: skip
    return table


# -- the plug-in ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Plan:
    scenario: SwarmScenario
    trials: int
    seed: int
    modes: tuple[str, ...]
    chunk_size: int
    workers: int | None


def plan(scenario: SwarmScenario, options: MonteCarloOptions) -> _Plan:
    """Check ``safestab mc``'s options for the swarm, before any work.

    ``--controllers`` names the compared modes; ``--datasets`` (the swarm learns nothing)
    and ``--backend ray`` are refused. The counts, the seed and the backend's name are
    checked before, for every kind (:func:`~safestab.scenarios.kinds.check_mc_options`).

    Raises
    ------
    ParameterError
        Naming the option, what was received and what is expected.
    """
    if options.datasets is not None:
        raise ParameterError(
            f"--datasets does not apply to the swarm (it learns nothing, so it has no data "
            f"sets), got --datasets {options.datasets}; leave it out"
        )
    if options.backend != "local":
        raise ParameterError(
            f"--backend must be 'local' for the swarm (its Monte Carlo runs in this process), "
            f"got {options.backend!r}"
        )
    modes = MODES
    if options.controllers is not None:
        modes = tuple(current_mode(m, "--controllers") for m in options.controllers)
        for i, mode in enumerate(modes):
            if mode not in MODES:
                raise ParameterError(
                    f"--controllers[{i}] must be one of the swarm's modes "
                    f"{', '.join(repr(m) for m in MODES)}, got {mode!r}"
                )
        if not modes or len(set(modes)) != len(modes):
            raise ParameterError(
                f"--controllers must be distinct swarm modes, got {', '.join(modes)!r}"
            )
    trials = DEFAULT_TRIALS if options.trials is None else options.trials
    chunk = DEFAULT_CHUNK_SIZE if options.chunk_size is None else options.chunk_size
    return _Plan(scenario, trials, options.seed, modes, chunk, options.workers)


def _run(checked: _Plan, progress: TaskProgress) -> SwarmMonteCarlo:
    return run_swarm_montecarlo(
        checked.scenario, trials=checked.trials, seed=checked.seed, modes=checked.modes,
        chunk_size=checked.chunk_size, workers=checked.workers, progress=progress,
    )  # fmt: skip


#: The swarm's Monte Carlo (:mod:`safestab.scenarios.pipeline`).
SWARM_MONTECARLO = StudyMonteCarlo(
    tasks=(_TASK,),
    plan=plan,
    run=_run,
    document=metrics_document,
    figure=plot_swarm_montecarlo,
    trials_npz=trials_npz_bytes,
    table=summary_table,
)
