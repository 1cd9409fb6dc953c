"""A safety filter around a policy on highway-env (safestab.gym), counted over seeded episodes.

    python benchmarks/gym_highway.py [--episodes 20] [--json FILE] [--figure FILE]

The ego car of highway-env's ``highway-v0`` (two lanes, 15 other cars driven by the
intelligent driver model, 30 s) takes continuous longitudinal actions (acceleration, +-5
m/s^2, at 5 Hz); its policy is "full throttle". The filter keeps a time headway to the car in
front, ``h = gap - tau v - d0 >= 0`` (``tau`` 1 s, ``d0`` 4 m), on the model ``gap' = v_l -
v``, ``v' = u``, with the acceleration limits inside its problem, and, in the third variant,
the sampled-data margin of the 5 Hz hold (``-h'' = a - a_l <= 5 + 6`` m/s^2: the ego's limit
and the other cars' largest acceleration, 6 m/s^2). Episodes end at a crash or at 30 s.
docs/tutorials/safe-rl.md's table and figure come from this script (``scripts/
reproduce-docs.sh``, step ``safe-rl``).
"""

from __future__ import annotations

import argparse
import json
import sys

import gymnasium as gym
import highway_env  # noqa: F401  (registers the environments)
import jax.numpy as jnp
import numpy as np

import safestab as ss
from safestab.gym import SafetyWrapper

CONFIG = {
    "action": {"type": "ContinuousAction", "longitudinal": True, "lateral": False},
    "lanes_count": 2,
    "vehicles_count": 15,
    "duration": 30,
    "policy_frequency": 5,
    "simulation_frequency": 15,
}
TAU, D0, ACC = 1.0, 4.0, 5.0  # s, m, m/s^2


def state(env, obs) -> np.ndarray:
    """``(gap m, v m/s, v_l m/s)`` from the simulator: the car ahead in the ego's lane."""
    ego = env.unwrapped.vehicle
    front, _ = env.unwrapped.road.neighbour_vehicles(ego, ego.lane_index)
    if front is None:  # nobody ahead: a free road
        return np.array([100.0, ego.speed, ego.speed])
    gap = front.position[0] - ego.position[0] - 0.5 * (front.LENGTH + ego.LENGTH)
    return np.array([gap, ego.speed, front.speed])


def filters() -> dict[str, ss.SafetyFilter | None]:
    """The three variants: no filter, the filter, the filter with the sampled-data margin."""
    car = ss.ControlAffineSystem(
        lambda x: jnp.array([x[2] - x[1], 0.0, 0.0]),
        lambda x: jnp.array([[0.0], [1.0], [0.0]]),
        3,
    )
    headway = ss.CBF(lambda x: x[0] - TAU * x[1] - D0, beta=1.0)
    filt = ss.SafetyFilter(car, headway, u_min=-ACC, u_max=ACC)
    return {
        "none": None,
        "filter": filt,
        "filter with the sampled-data margin": filt.replace(sample_time=0.2, ddh_bound=ACC + 6.0),
    }


def episode(filt: ss.SafetyFilter | None, seed: int) -> dict:
    """One seeded episode of full throttle; ``h`` from the state, filtered or not."""
    env = gym.make("highway-v0", config=CONFIG)
    if filt is not None:
        env = SafetyWrapper(env, filt, state=state)
    env.reset(seed=seed)
    hs, interventions, statuses, crashed = [], [], {}, False
    for _ in range(200):
        x = state(env, None)
        hs.append(float(x[0] - TAU * x[1] - D0))
        _, _, terminated, truncated, info = env.step(np.array([1.0], np.float32))
        if "safestab" in info:
            interventions.append(info["safestab"]["intervention"])
            name = info["safestab"]["status"]
            statuses[name] = statuses.get(name, 0) + 1
        if info.get("crashed"):
            crashed = True
            break
        if terminated or truncated:
            break
    env.close()
    return {"h": hs, "crashed": crashed, "interventions": interventions, "statuses": statuses}


def run(episodes: int) -> tuple[list[dict], dict]:
    """The rows (one per variant) and the first episode's h per variant, for the figure."""
    rows, first = [], {}
    for name, filt in filters().items():
        eps = [episode(filt, seed) for seed in range(episodes)]
        statuses: dict[str, int] = {}
        for e in eps:
            for k, v in e["statuses"].items():
                statuses[k] = statuses.get(k, 0) + v
        inter = [v for e in eps for v in e["interventions"]]
        rows.append({
            "variant": name, "episodes": episodes,
            "crashes": int(sum(e["crashed"] for e in eps)),
            "steps": int(sum(len(e["h"]) for e in eps)),
            "mean_intervention": float(np.mean(inter)) if inter else 0.0,
            "steps_changed": int(sum(v > 1e-6 for v in inter)),
            "statuses": statuses,
        })  # fmt: skip
        first[name] = eps[0]["h"]
    return rows, first


def figure(first: dict, path: str) -> None:
    """h over the first seeded episode, one line per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.2), layout="constrained")
    for name, hs in first.items():
        ax.plot(np.arange(len(hs)) * 0.2, hs, label=name)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("h = gap - tau v - d0 (m)")
    ax.set_title("highway-env, full throttle, episode seed 0")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--json", help="write the rows to this file")
    parser.add_argument("--figure", help="write the first episode's h to this PNG")
    args = parser.parse_args(argv)
    rows, first = run(args.episodes)
    for r in rows:
        print(
            f"{r['variant']:40s} crashes {r['crashes']:2d} of {r['episodes']}, "
            f"mean intervention {r['mean_intervention']:.3f}, statuses {r['statuses']}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1, allow_nan=False)
    if args.figure:
        figure(first, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
