"""The obstacle's axis starts, exactly on the axis and 1 mm off it: how fragile the deadlock is.

    python benchmarks/obstacle_axis.py --json results/obstacle_axis.json

The four starts behind the obstacle, ``(-8, 0)`` to ``(-5, 0)`` m, stay on the x1 axis by
symmetry and get stuck there (docs/obstacle.md). This runs them, and the same starts moved
``offset`` = 1 mm off the axis (``x2 = +1e-3`` m), for three controllers, with and without the
input limits kept by the projection (eq. (26)) and by the safety filter
(``controller.limit_method``), relaxed formula (these starts lie outside every certified
sublevel set):

- the true model;
- the GP-robust controller with ``learning.input_gain = "nominal"``;
- the GP-robust controller with ``learning.input_gain = "learned"`` (the preset).

Per row: the outcomes, min h, max |u|. ``scripts/reproduce_docs.py`` (step ``obstacle``)
writes the table into docs/obstacle.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

OFFSET_M = 1e-3


def rows() -> list[dict]:
    import numpy as np

    from safestab.scenarios import load
    from safestab.scenarios.obstacle_study import (
        OUTCOMES,
        calibrate_beta,
        classify_outcomes,
        fit_obstacle_gp,
        obstacle_controller,
    )
    from safestab.simulation import simulate

    base = load("obstacle")
    axis = np.array([[-8.0, 0.0], [-7.0, 0.0], [-6.0, 0.0], [-5.0, 0.0]])
    setups = [("true model", "-", base, None)]
    for gain in ("nominal", "learned"):
        sc = base.replace(input_gain=gain)
        _, _, unc, found = fit_obstacle_gp(sc)
        sc = sc.with_learned_gain(found)
        if sc.beta_method == "conformal":
            sc = sc.replace(gp_beta=calibrate_beta(sc, unc)["beta"])
        setups.append(("GP-robust", gain, sc, unc))
    out = []
    for name, gain, sc, unc in setups:
        for offset in (0.0, OFFSET_M):
            x0 = axis + np.array([0.0, offset])
            for method in (None, "projection", "filter"):
                limits = method is not None
                run_sc = sc if method is None else sc.replace(limit_method=method)
                ctrl = obstacle_controller(run_sc, name, unc, limits=limits)
                tr = simulate(ctrl, x0, t_final=sc.t_final, dt=sc.dt, plant=sc.system("true"))
                x, u, h = (np.asarray(a) for a in (tr.x, tr.u, tr.h))
                h = h.reshape(h.shape[:2])  # a safety filter's: one CBF
                outcome = classify_outcomes(x, h, sc.dt, sc.ball_radius, sc.rest_speed)
                out.append({
                    "controller": name, "input_gain": gain, "offset_m": offset,
                    "limits": "input limits" if limits else "no limits",
                    "limit_method": method or "-",
                    "outcomes": {k: int(np.sum(outcome == k)) for k in OUTCOMES},
                    "min_h_m2": float(np.min(h)), "max_abs_u_mps": float(np.max(np.abs(u))),
                    "gp_beta": float(sc.gp_beta),
                })  # fmt: skip
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, required=True, help="result file (strict JSON)")
    args = parser.parse_args()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    found = rows()
    tmp = args.json.with_name(args.json.name + ".tmp")
    tmp.write_text(json.dumps(found, indent=1, allow_nan=False) + "\n")
    tmp.replace(args.json)
    for r in found:
        o = r["outcomes"]
        print(
            f"{r['controller']:>10} {r['input_gain']:>8} offset {r['offset_m']:g} m "
            f"{r['limits']:>12} {r['limit_method']:>10}: {o['converged']}/{o['stuck']}/{o['moving']}/{o['unsafe']} "
            f"min h {r['min_h_m2']:.3f}  max |u| {r['max_abs_u_mps']:.2f}"
        )


if __name__ == "__main__":
    main()
