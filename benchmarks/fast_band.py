"""The fast cache's width against the exact GP, in every preset.

    python benchmarks/fast_band.py --json results/fast_band.json

For each preset, the GP its study fits (the ACC presets: ``safestab run``'s data and fit; the
obstacle: its study's ``fit_obstacle_gp``) and the ``FastGP`` cache its controllers use (the
ACC presets' Monte Carlo ``n_inducing``, the obstacle's ``learning.n_inducing``), per learned
component: the inducing inputs the pivoted Cholesky kept, the cache's std over the exact std at
every training input (median and max) and at the held-out states (median), ``E`` (the
mean-error constant), whether the band contains the exact band at those states (beta = 1) and
the ``InducingPointsWarning`` count. ``scripts/reproduce_docs.py`` (step ``fast-band``) writes
the table into docs/learning.md.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

PRESETS = ("paper", "stress", "stress-ood", "obstacle")


def rows_for(preset: str) -> list[dict]:
    import numpy as np

    from safestab.learning import FastGP
    from safestab.scenarios import load
    from safestab.scenarios.obstacle_study import fit_obstacle_gp
    from safestab.scenarios.pipeline import collect_study_data, fit_study_gp

    sc = load(preset)
    if preset == "obstacle":
        test, gp, _, _ = fit_obstacle_gp(sc.replace(n_inducing=0))
        n_inducing = sc.n_inducing
    else:
        train, test = collect_study_data(sc, seed=sc.seed, n_samples=sc.n_samples)
        gp = fit_study_gp(sc, train)
        n_inducing = (sc.montecarlo or sc.trial_study().spec).n_inducing
    t0 = time.perf_counter()
    fast = FastGP(gp, n_inducing, warn=False)
    build_s = time.perf_counter() - t0
    comps = list(gp.components_)
    out = []
    for name, x in (("training", gp.x_train_), ("held-out", test.x)):
        _, s_fa = fast.predict(x, return_std=True)
        _, s_ex = gp.predict(x, return_std=True)
        ratio = s_fa[:, comps] / s_ex[:, comps]
        cover = fast.coverage_of_exact_band(x, 1.0)
        out.append((name, ratio, cover))
    rows = []
    for j, comp in enumerate(comps):
        (_, r_tr, c_tr), (_, r_ho, c_ho) = out
        rows.append({
            "preset": preset, "component": int(comp), "q": int(gp.x_train_.shape[0]),
            "n_inducing_cap": int(n_inducing), "n_inducing": int(fast.n_inducing_[j]),
            "ratio_training_median": float(np.median(r_tr[:, j])),
            "ratio_training_max": float(np.max(r_tr[:, j])),
            "ratio_held_out_median": float(np.median(r_ho[:, j])),
            "coverage_training": float(c_tr[j]), "coverage_held_out": float(c_ho[j]),
            "mean_error_norm": float(fast.mean_error_norm_[j]),
            "warnings": len(fast.width_warnings_), "build_s": build_s,
        })  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, required=True, help="result file (strict JSON)")
    parser.add_argument("--presets", nargs="+", choices=PRESETS, default=list(PRESETS))
    args = parser.parse_args()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for preset in args.presets:
        print(f"{preset}: fitting the study's GP and building its cache", flush=True)
        rows += rows_for(preset)
    tmp = args.json.with_name(args.json.name + ".tmp")
    tmp.write_text(json.dumps(rows, indent=1, allow_nan=False) + "\n")
    tmp.replace(args.json)
    for r in rows:
        print(
            f"{r['preset']:>10} c{r['component']}: M {r['n_inducing']:>3}  training "
            f"{r['ratio_training_median']:.3f} / {r['ratio_training_max']:.3f}  held-out "
            f"{r['ratio_held_out_median']:.3f}  E {r['mean_error_norm']:.3g}  "
            f"warnings {r['warnings']}"
        )


if __name__ == "__main__":
    main()
