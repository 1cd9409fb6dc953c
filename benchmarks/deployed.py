"""Safe as deployed: a sampled controller with a limited input, checked between the samples.

    python benchmarks/deployed.py [--json FILE]

Two loops, each run at coarse sample rates with the input held (zero-order hold), integrated
in 20 RK4 substeps per hold and checked at every substep (``simulate(..., substeps=20)``):

* ``disc``: a point robot (``x' = u``, ``|u_i| <= 1`` m/s) kept inside the unit disc by a
  ``SafetyFilter`` while its nominal input pulls it out (a concave barrier: the straight hold
  leaves the disc); 64 seeded starts, 5 s.
* ``pass-by``: the same robot passing a disc obstacle of radius 0.25 (a convex barrier with
  a steep rate, ``beta = 50``): a straight hold cuts the disc between two samples outside it.
* ``acc``: the stress preset's follower (true model) under the braking and traction limit
  ``|u| <= 0.3 M g``, the universal controller with safety-first saturation; the lead's
  profile of the preset, 60 s.

* ``mc``: the stress preset's Monte Carlo study at 10 Hz under the same limit, every
  compared controller (the GP ones learn ``omega`` from each of ``--datasets`` fresh data
  sets), ``--trials-per-dataset`` random leads and starts per data set; and the obstacle's at
  2 Hz under its box (the safety filter), its 72 starts per data set.

Each runs without the sampled-data margin and with it (``sample_time``, ``ddh_bound``): the
bound ``M`` from the hand derivation (disc: ``-h'' = 2 |u|^2 <= 4``) or estimated by
``safestab.sampled.ddh_bound`` over the stated box (ACC). docs/deployed.md's table comes from
this file's output (``scripts/reproduce-docs.sh``, step ``deployed``).
"""

from __future__ import annotations

import argparse
import json
import sys

import jax.numpy as jnp
import numpy as np

import safestab as ss
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


def _mc_rows(study: str, sc, spec, M: float, trials: int, datasets: int) -> list[dict]:
    """One Monte Carlo study without and with the margin: a row per controller."""
    from safestab.montecarlo import run_montecarlo

    rows = []
    for margin, bound in (("none", None), ("estimated bound", M)):
        run = run_montecarlo(sc, trials=trials, datasets=datasets,
                             spec=spec.replace(ddh_bound=bound))  # fmt: skip
        rec = run.records
        for c, name in enumerate(run.controllers):
            h, hb = rec["min_h"][:, c], rec["min_h_between"][:, c]
            rows.append({
                "study": study, "controller": name, "margin": margin, "ddh_bound": bound,
                "datasets": datasets, "trials": int(h.size),
                "left_at_samples": int(np.sum(h < 0)),
                "left_between_samples": int(np.sum(hb < 0)),
                "min_h_samples": float(np.min(h)), "min_h_between": float(np.min(hb)),
                "trials_with_unmet_steps": int(np.sum(rec["barrier_unmet_steps"][:, c] > 0)),
                "unmet_steps": int(np.sum(rec["barrier_unmet_steps"][:, c])),
                "median_min_h": float(np.median(h)),
            })  # fmt: skip
    return rows


def mc_rows(datasets: int, trials_per_dataset: int) -> list[dict]:
    """Two Monte Carlo studies at coarse rates, without and with the margin, every compared
    controller over fresh data sets, h checked at 10 substeps a hold: the stress preset at
    10 Hz under |u| <= 0.3 M g (random starts and leads), and the obstacle at 2 Hz under its
    +-1.5 m/s box (the safety filter; its 72 starts per data set)."""
    from safestab.scenarios.obstacle import load_obstacle_scenario

    sc = load_scenario("stress").replace(dt=0.1, input_limit=0.3)
    _, cbf = sc.certificates()
    lim = 0.3 * sc.mass * sc.gravity / sc.input_scale
    spec = sc.montecarlo.replace(substeps=10)
    g = sc.gravity
    # every lead acceleration the trials draw
    a_range = (-spec.lead_decel_max * g, spec.lead_accel_max * g)
    M = _acc_bound(sc.system("true"), cbf, lim, a_range)
    rows = _mc_rows("ACC stress, 10 Hz, input within +-0.3 M g", sc, spec, M,
                    datasets * trials_per_dataset, datasets)  # fmt: skip
    ob = load_obstacle_scenario("obstacle").replace(dt=0.5)
    _, cbf = ob.certificates()
    lim = ob.input_limit
    # the region of the starts and the goal, the box of inputs, the true plant (its current)
    M = float(ddh_bound(ob.system("true"), cbf, [-9.0, -4.0], [3.0, 4.0], u_min=-lim,
                        u_max=lim)[0])  # fmt: skip
    spec = (ob.montecarlo or MonteCarloSpec()).replace(substeps=10, controllers=("true model", "mismatched model",
                                                            "GP-robust"))  # fmt: skip
    starts = len(ob.start_states())
    rows += _mc_rows("obstacle, 2 Hz, inputs within +-1.5 m/s", ob, spec, M, starts * datasets,
                     datasets)  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the rows to this file")
    parser.add_argument("--datasets", type=int, default=10,
                        help="data sets of the Monte Carlo part (0: skip it)")  # fmt: skip
    parser.add_argument("--trials-per-dataset", type=int, default=10)
    args = parser.parse_args(argv)
    rows = disc_rows() + pass_by_rows() + acc_rows()
    for r in rows:
        print(
            f"{r['case']:7s} {r['rate_hz']:5.0f} Hz  margin {r['margin']:16s} "
            f"left: {r['left_at_samples']:3d} at samples, {r['left_between_samples']:3d} between;"
            f"  min h {r['min_h_samples']:+.4f} / {r['min_h_between']:+.4f};"
            f"  not OK {r['steps_not_ok']} of {r['steps']} {r['statuses']}"
        )
    mc = mc_rows(args.datasets, args.trials_per_dataset) if args.datasets else []
    for r in mc:
        print(
            f"mc {r['study'][:8]:8s} {r['controller']:20s} margin {r['margin']:16s} left: {r['left_at_samples']} "
            f"at samples, {r['left_between_samples']} between, of {r['trials']};  min h "
            f"{r['min_h_samples']:+.4f} / {r['min_h_between']:+.4f};  trials with unmet steps "
            f"{r['trials_with_unmet_steps']}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"loops": rows, "montecarlo": mc}, fh, indent=1, allow_nan=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
