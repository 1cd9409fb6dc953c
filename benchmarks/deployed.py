"""Safe as deployed: a sampled controller with a limited input, checked between the samples.

    python benchmarks/deployed.py [--json FILE] [--datasets K] [--trials-per-dataset N]
                                  [--obstacle-trials-per-dataset N] [--no-loops]

Three loops, each run at coarse sample rates with the input held (zero-order hold), integrated
in 20 RK4 substeps per hold and checked at every substep (``simulate(..., substeps=20)``):

* ``disc``: a point robot (``x' = u``, ``|u_i| <= 1`` m/s) kept inside the unit disc by a
  ``SafetyFilter`` while its nominal input pulls it out (a concave barrier: the straight hold
  leaves the disc); 64 seeded starts, 5 s.
* ``pass-by``: the same robot passing a disc obstacle of radius 0.25 (a convex barrier with
  a steep rate, ``beta = 50``): a straight hold cuts the disc between two samples outside it.
* ``acc``: the stress preset's follower (true model) under the braking and traction limit
  ``|u| <= 0.3 M g``, the universal controller with safety-first saturation; the lead's
  profile of the preset, 60 s.

* ``mc``: two Monte Carlo studies, every compared controller (the GP ones learn ``omega``
  from each of ``--datasets`` fresh data sets), ``h`` checked at 10 substeps a hold:
  the ``stress-limited`` preset (the braking-distance barrier, valid under its limit
  ``|u| <= 0.3 M g``, 10 Hz, ``--trials-per-dataset`` random leads and starts per data set),
  and the obstacle at 2 Hz under its box (the safety filter, ``--obstacle-trials-per-dataset``,
  by default its 72 starts per data set). Each runs without the margin and with it on the
  same trials and data sets (the same seed); per row: trials below ``h = 0`` at and between
  the samples, the safe data sets with their Clopper-Pearson interval, the trials with
  barrier-unmet steps, the share of steps on the limit, and on the margin's rows its price
  against the same controller without it (median paired ``min h`` gain and settle-time
  change, ``MonteCarloSpec.price_metrics``).

Each runs without the sampled-data margin and with it (``sample_time``, ``ddh_bound``): the
bound ``M`` from the hand derivation (disc: ``-h'' = 2 |u|^2 <= 4``), the closed form
``braking_ddh_bound`` (``stress-limited``'s ``montecarlo.ddh_bound``, a proof), or estimated
by ``safestab.sampled.ddh_bound`` over the stated box (the ``acc`` loop, the obstacle).
docs/deployed.md's tables come from this file's output (``scripts/reproduce-docs.sh``, step
``deployed``; with ``--long``, step ``deployed-long``: ``--no-loops --datasets 1000
--obstacle-trials-per-dataset 10``, the Monte Carlo part at 1,000 data sets x 10 trials, whose
measured time docs/deployed.md states beside its table, block ``deployed-mc-long-time``; the
normal step writes its own measurement and projection there, block ``deployed-mc-time``).
"""

from __future__ import annotations

import argparse
import json
import sys

import jax.numpy as jnp
import numpy as np

import safestab as ss
from safestab.montecarlo import clopper_pearson
from safestab.montecarlo.stats import safe_mask
from safestab.sampled import ddh_bound
from safestab.scenarios import MonteCarloSpec, load_scenario

SUBSTEPS = 20


def _row(case: str, rate: float, margin: str, M: float | None, traj: ss.Trajectory) -> dict:
    h = np.asarray(traj.h).reshape(np.shape(traj.h)[0] if np.ndim(traj.h) > 1 else 1, -1)
    hb = np.asarray(traj.h_between).reshape(h.shape)
    status = np.asarray(traj.status).reshape(h.shape[0], -1)
    least_between = np.nanmin(hb, -1)
    return {
        "case": case,
        "rate_hz": rate,
        "margin": margin,
        "ddh_bound": M,
        "runs": int(h.shape[0]),
        "left_at_samples": int(np.sum(np.min(h, -1) < 0)),
        "left_between_samples": int(np.sum(least_between < 0)),
        "min_h_samples": float(np.min(h)),
        "min_h_between": float(np.min(least_between)),
        "steps_not_ok": int(np.sum(status != ss.StepStatus.OK)),
        "steps": int(status.size),
        "statuses": {
            ss.StepStatus(int(v)).name: int(n)
            for v, n in zip(*np.unique(status[status != 0], return_counts=True), strict=True)
        },
    }


def disc_rows() -> list[dict]:
    """The point robot in the unit disc at 20, 10 and 5 Hz."""
    plane = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    disc = ss.CBF(lambda x: 1.0 - x @ x, beta=5.0)
    goal = jnp.array([2.0, 0.5])
    filt = ss.SafetyFilter(plane, disc, u_nom=lambda x: 2.0 * (goal - x), u_min=-1.0, u_max=1.0)
    x0 = np.random.default_rng(0).uniform(-0.7, 0.7, size=(64, 2))
    M = 4.0  # -h'' = 2 |u|^2 <= 2 (1^2 + 1^2): the hand bound over the limits
    rows = []
    for rate in (20.0, 10.0, 5.0):
        dt = 1.0 / rate
        for margin, ctrl in (
            ("none", filt),
            ("hand bound", filt.replace(sample_time=dt, ddh_bound=M)),
        ):
            traj = ss.simulate(ctrl, x0, t_final=5.0, dt=dt, substeps=SUBSTEPS)
            rows.append(_row("disc", rate, margin, None if margin == "none" else M, traj))
    return rows


def pass_by_rows() -> list[dict]:
    """A point robot passing a disc obstacle at 10 and 5 Hz: the dips between the samples."""
    plane = ss.ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2)
    obstacle = ss.CBF(lambda x: x @ x - 0.25**2, beta=50.0)  # keep out: convex along a line
    filt = ss.SafetyFilter(plane, obstacle, u_nom=lambda x: jnp.array([1.0, 0.0]),
                           u_min=-1.0, u_max=1.0)  # fmt: skip
    ys = np.random.default_rng(1).uniform(-0.35, 0.35, size=64)
    x0 = np.stack([np.full(64, -1.0), ys], -1)
    rows = []
    for rate in (10.0, 5.0):
        dt = 1.0 / rate
        # h'' = 2 |u|^2 >= 0 along a held input: M = 0, the rate's cap at 1 / T alone
        for margin, ctrl in (
            ("none", filt),
            ("hand bound", filt.replace(sample_time=dt, ddh_bound=0.0)),
        ):
            traj = ss.simulate(ctrl, x0, t_final=3.0, dt=dt, substeps=SUBSTEPS)
            rows.append(_row("pass-by", rate, margin, None if margin == "none" else 0.0, traj))
    return rows


def _acc_bound(system: ss.ControlAffineSystem, cbf: ss.CBF, lim: float, a_range) -> float:
    """``ddh_bound`` of the ACC's barrier over speeds 0 to 35 m/s, gaps 0 to 150 m, inputs
    within ``+-lim`` and lead accelerations in ``a_range`` (m/s^2)."""
    lo, hi = [0.0, 0.0, 0.0], [35.0, 35.0, 150.0]
    lead = ([0.0, a_range[0], 0.0], [0.0, a_range[1], 0.0])
    return float(ddh_bound(system, cbf, lo, hi, u_min=-lim, u_max=lim, disturbance=lead)[0])


def acc_rows() -> list[dict]:
    """The stress preset's true-model follower under |u| <= 0.3 M g at 10 and 5 Hz."""
    sc = load_scenario("stress")
    system = sc.system("true")
    clf, cbf = sc.certificates()
    lim = 0.3 * sc.mass * sc.gravity / sc.input_scale
    ctrl = ss.UniversalController(
        system, clf, cbf, kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi,
        slack_weight=sc.slack_weight, u_min=-lim, u_max=lim, saturation="safety_first",
    )  # fmt: skip
    profile = np.asarray(sc.lead_profile, dtype=float)
    a_range = (min(0.0, profile[:, 1].min()), max(0.0, profile[:, 1].max()))
    M = _acc_bound(system, cbf, lim, a_range)
    rows = []
    for rate in (10.0, 5.0):
        dt = 1.0 / rate
        for margin, c in (
            ("none", ctrl),
            ("estimated bound", ctrl.replace(sample_time=dt, ddh_bound=M)),
        ):
            traj = ss.simulate(c, np.asarray(sc.x0), t_final=sc.t_final, dt=dt,
                               exogenous=sc.exogenous, substeps=SUBSTEPS)  # fmt: skip
            rows.append(_row("acc", rate, margin, None if margin == "none" else M, traj))
    return rows


def _safe_per_dataset(rec: dict, dataset_index: np.ndarray, n_sets: int, c: int) -> dict:
    """Data sets whose every trial of controller ``c`` was safe (every step gave an input,
    ``h >= 0`` at the samples and between them), with the exact interval over data sets."""
    safe = safe_mask(rec)[:, c]
    held = np.bincount(dataset_index, weights=safe.astype(float), minlength=n_sets)
    count = int(np.sum(held == np.bincount(dataset_index, minlength=n_sets)))
    low, high = clopper_pearson(count, n_sets)
    return {"count": count, "datasets": n_sets, "ci95": [low, high]}


def margin_price(without: dict, with_margin: dict, c: int) -> dict:
    """The margin's price for controller ``c``, paired trial by trial (the same trials run
    without and with the margin): medians over trials of ``min h`` (with minus without,
    the headway the margin keeps, in the study's unit of ``h``) and of ``settle_time`` (s);
    the latter None where the run did not measure it (``price_metrics``)."""
    gain = with_margin["min_h"][:, c] - without["min_h"][:, c]
    settle = with_margin["settle_time"][:, c] - without["settle_time"][:, c]
    measured = np.all(with_margin["settle_time"][:, c] >= 0) and np.all(
        without["settle_time"][:, c] >= 0
    )
    finite = np.isfinite(gain)
    return {
        "median_min_h_gain": float(np.median(gain[finite])) if finite.any() else None,
        "median_settle_time_change": float(np.median(settle)) if measured else None,
    }


def study_rows(study: str, runs: dict, M: float) -> list[dict]:
    """A row per controller and margin from two runs of one Monte Carlo study on the same
    trials, ``runs = {"none": run, label: run}`` (``run.records``, ``run.controllers``,
    ``run.dataset_index``, ``run.study.n_steps``); the margin's rows carry its price
    against the same controller in the run without it."""
    rows = []
    plain = runs["none"].records
    for margin, run in runs.items():
        rec, sets = run.records, np.asarray(run.dataset_index)
        n_sets = int(sets.max()) + 1
        for c, name in enumerate(run.controllers):
            h, hb = rec["min_h"][:, c], rec["min_h_between"][:, c]
            limit = rec["limit_steps"][:, c]
            row = {
                "study": study, "controller": name, "margin": margin,
                "ddh_bound": None if margin == "none" else M,
                "datasets": n_sets, "trials": int(h.size),
                "left_at_samples": int(np.sum(h < 0)),
                "left_between_samples": int(np.sum(hb < 0)),
                "min_h_samples": float(np.nanmin(h)), "min_h_between": float(np.nanmin(hb)),
                "median_min_h": float(np.nanmedian(h)),
                "safe_per_dataset": _safe_per_dataset(rec, sets, n_sets, c),
                "trials_with_unmet_steps": int(np.sum(rec["barrier_unmet_steps"][:, c] > 0)),
                "unmet_steps": int(np.sum(rec["barrier_unmet_steps"][:, c])),
                "limit_step_fraction": float(np.sum(limit) / (limit.size * run.study.n_steps)),
                "price": None if margin == "none" else margin_price(plain, rec, c),
            }  # fmt: skip
            rows.append(row)
    return rows


def _run_pair(sc, spec, M: float, bound: str, trials: int, datasets: int) -> tuple[dict, dict]:
    """One Monte Carlo study without and with the margin (the same seed: the same trials and
    data sets); ``({margin: run}, {margin: timings})``."""
    from safestab.montecarlo import run_montecarlo

    runs = {}
    for margin, value in (("none", None), (bound, M)):
        runs[margin] = run_montecarlo(sc, trials=trials, datasets=datasets,
                                      spec=spec.replace(ddh_bound=value, price_metrics=True))  # fmt: skip
    return runs, {m: r.timings for m, r in runs.items()}


#: The Monte Carlo studies' titles (the table's first column).
ACC_STUDY = "ACC stress-limited, 10 Hz"
OBSTACLE_STUDY = "obstacle, 2 Hz"


def mc_rows(
    datasets: int, trials_per_dataset: int, obstacle_trials_per_dataset: int | None = None
) -> dict:
    """Two Monte Carlo studies at coarse rates, without and with the margin, every compared
    controller over fresh data sets, h checked at 10 substeps a hold: the stress-limited
    preset (the braking-distance barrier, valid under its limit |u| <= 0.3 M g, at 10 Hz,
    random starts and leads; its margin ``montecarlo.ddh_bound`` is the closed-form
    ``braking_ddh_bound``), and the obstacle at 2 Hz under its +-1.5 m/s box (the safety
    filter; by default its 72 starts per data set; the bound estimated on the true plant).

    Returns ``{"rows": [...], "settings": ..., "timings_s": ...}``.
    """
    from safestab.scenarios.obstacle import load_obstacle_scenario

    sc = load_scenario("stress-limited")
    spec = sc.montecarlo
    M = float(spec.ddh_bound)
    acc_runs, acc_t = _run_pair(sc, spec, M, "closed-form bound", datasets * trials_per_dataset,
                                datasets)  # fmt: skip
    rows = study_rows(ACC_STUDY, acc_runs, M)
    ob = load_obstacle_scenario("obstacle").replace(dt=0.5)
    _, cbf = ob.certificates()
    lim = ob.input_limit
    # the region of the starts and the goal, the box of inputs, the true plant (its current)
    M = float(ddh_bound(ob.system("true"), cbf, [-9.0, -4.0], [3.0, 4.0], u_min=-lim,
                        u_max=lim)[0])  # fmt: skip
    spec = (ob.montecarlo or MonteCarloSpec()).replace(
        substeps=10, controllers=("true model", "mismatched model", "GP-robust")
    )
    per_set = obstacle_trials_per_dataset or len(ob.start_states())
    ob_runs, ob_t = _run_pair(ob, spec, M, "estimated bound", per_set * datasets, datasets)
    rows += study_rows(OBSTACLE_STUDY, ob_runs, M)
    settings = {
        "datasets": datasets,
        "trials_per_dataset": {ACC_STUDY: trials_per_dataset, OBSTACLE_STUDY: per_set},
    }
    return {"rows": rows, "settings": settings,
            "timings_s": {ACC_STUDY: acc_t, OBSTACLE_STUDY: ob_t}}  # fmt: skip


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; refuses negative counts."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the rows to this file")
    parser.add_argument("--datasets", type=int, default=10,
                        help="data sets of the Monte Carlo part (0: skip it)")  # fmt: skip
    parser.add_argument("--trials-per-dataset", type=int, default=10,
                        help="the ACC study's trials per data set")  # fmt: skip
    parser.add_argument("--obstacle-trials-per-dataset", type=int, default=None,
                        help="the obstacle study's (default: its 72 starts)")  # fmt: skip
    parser.add_argument("--no-loops", action="store_true",
                        help="the Monte Carlo part only (not the disc, pass-by, acc loops)")  # fmt: skip
    args = parser.parse_args(argv)
    for name in ("datasets", "trials_per_dataset", "obstacle_trials_per_dataset"):
        value = getattr(args, name)
        if value is not None and (value < 0 or (value == 0 and name != "datasets")):
            parser.error(
                f"--{name.replace('_', '-')} must be {'>= 0' if name == 'datasets' else '>= 1'}, got {value}"
            )
    if args.no_loops and not args.datasets:
        parser.error("--no-loops with --datasets 0 leaves nothing to run")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows = [] if args.no_loops else disc_rows() + pass_by_rows() + acc_rows()
    for r in rows:
        print(
            f"{r['case']:7s} {r['rate_hz']:5.0f} Hz  margin {r['margin']:16s} "
            f"left: {r['left_at_samples']:3d} at samples, {r['left_between_samples']:3d} between;"
            f"  min h {r['min_h_samples']:+.4f} / {r['min_h_between']:+.4f};"
            f"  not OK {r['steps_not_ok']} of {r['steps']} {r['statuses']}"
        )
    mc = {"rows": [], "settings": None, "timings_s": None}
    if args.datasets:
        mc = mc_rows(args.datasets, args.trials_per_dataset, args.obstacle_trials_per_dataset)
    for r in mc["rows"]:
        safe = r["safe_per_dataset"]
        print(
            f"mc {r['study'][:8]:8s} {r['controller']:18s} margin {r['margin']:17s} left: "
            f"{r['left_at_samples']} at samples, {r['left_between_samples']} between, of "
            f"{r['trials']};  min h {r['min_h_samples']:+.4f} / {r['min_h_between']:+.4f};  "
            f"safe data sets {safe['count']}/{safe['datasets']};  trials with unmet steps "
            f"{r['trials_with_unmet_steps']};  on the limit {r['limit_step_fraction']:.3g}"
        )
    if mc["timings_s"]:
        print("timings (s):", json.dumps(mc["timings_s"]))
    if args.json:
        doc = {"loops": rows, "montecarlo": mc["rows"], "montecarlo_settings": mc["settings"],
               "montecarlo_timings_s": mc["timings_s"]}  # fmt: skip
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=1, allow_nan=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
