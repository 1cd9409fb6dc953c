"""The fast cache's width on the Monte Carlo's own data sets, against the exact GP.

    python benchmarks/mc_band_width.py --presets stress obstacle --datasets 20 --json out.json

Each data set is drawn and fitted as ``safestab mc`` draws and fits it
(``montecarlo.trials.dataset_draw``; data set 0's hyperparameters fitted, the others
conditioned on them where the preset reuses them), and cached as the Monte Carlo caches it
(``FastGP(gp, n_inducing)``). Per data set and learned component: the inducing inputs kept, the
cache's std over the exact std at the training inputs (median, and the same at 400 states
drawn in the box ten times the data's, centred on it), the fraction of those states where the
cache's band contains the exact band (beta = 1) and whether an ``InducingPointsWarning``
names the component.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def rows_for(
    preset: str, indices: list[int], seed: int | None, cap: int | None = None
) -> list[dict]:
    import numpy as np

    from safestab.learning import FastGP, GaussianProcessModel
    from safestab.learning.batched import condition, one_blas_thread
    from safestab.learning.fast import STD_RATIO_WARN
    from safestab.montecarlo.trials import dataset_draw
    from safestab.scenarios import load

    study = load(preset).trial_study()
    spec, settings = study.spec, study.gp_settings()
    seed = int(getattr(load(preset), "seed", 0) if seed is None else seed)
    q = settings["n_samples"]
    cap = int(spec.n_inducing if cap is None else cap)
    if settings.get("input_gain", "nominal") == "learned":
        from safestab.learning import fit_input_gain
    rows, hyper = [], None
    for index in sorted({0, *indices}):  # data set 0 gives the reused hyperparameters
        data_seed = int(np.random.SeedSequence([seed, index]).generate_state(1)[0])
        data = dataset_draw(study, seed, index)
        x, y, u = data.x[:q], data.y[:q], data.u[:q]
        t0 = time.perf_counter()
        with one_blas_thread():
            if hyper is None or spec.hyperparameters != "reuse":

                def fit(x, y):
                    gp = GaussianProcessModel(kernel=settings["kernel"])
                    sub = min(settings["hyper_subset"], q)
                    return gp.fit(x, y, hyper_subset=sub, seed=data_seed)

                if settings.get("input_gain", "nominal") == "learned":
                    gp, _ = fit_input_gain(fit, x, u, y, seed=data_seed)
                else:
                    gp = fit(x, y)
                from safestab.learning.batched import Hyperparameters

                hyper = Hyperparameters.from_model(gp)
            else:
                gp = condition(hyper, x, y, seed=data_seed)
                if settings.get("input_gain", "nominal") == "learned":
                    from safestab.learning import estimate_input_gain

                    gain = estimate_input_gain(gp, u).matrix
                    gp = condition(hyper, x, y - u @ gain.T, seed=data_seed)
            fit_s = time.perf_counter() - t0
            fast = FastGP(gp, cap, warn=False)
        lo, hi = gp.x_train_.min(0), gp.x_train_.max(0)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        rng = np.random.default_rng(index)
        far = centre + 10 * half * rng.uniform(-1, 1, size=(400, len(lo)))
        comps = list(gp.components_)
        ratios = {}
        for name, pts in (("training", gp.x_train_), ("far", far)):
            _, s_fa = fast.predict(pts, return_std=True)
            _, s_ex = gp.predict(pts, return_std=True)
            ratios[name] = s_fa[:, comps] / np.maximum(s_ex[:, comps], 1e-150)
        cover = fast.coverage_of_exact_band(np.concatenate([gp.x_train_[:400], far]), 1.0)
        for j, comp in enumerate(comps):
            named = any(f"component {comp}," in w for w in fast.width_warnings_)
            rows.append({
                "preset": preset, "seed": seed, "dataset": index, "component": int(comp),
                "n_inducing": int(fast.n_inducing_[j]), "cap": cap,
                "ratio_training_median": float(np.median(ratios["training"][:, j])),
                "ratio_far_median": float(np.median(ratios["far"][:, j])),
                "contains_exact": float(cover[j]), "warned": bool(named),
                "std_ratio_warn": STD_RATIO_WARN,
                "fit_s": round(fit_s, 2),
            })  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["stress", "obstacle"])
    ap.add_argument("--datasets", type=int, default=20)
    ap.add_argument("--only", type=int, nargs="*", help="only these data set indices")
    ap.add_argument("--seed", type=int, default=None, help="Monte Carlo seed (the preset's)")
    ap.add_argument("--cap", type=int, default=None, help="n_inducing (the preset's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    for preset in args.presets:
        indices = list(range(args.datasets)) if args.only is None else args.only
        for row in rows_for(preset, indices, args.seed, args.cap):
            rows.append(row)
            print(
                f"{row['preset']:9s} set {row['dataset']:2d} comp {row['component']} "
                f"M {row['n_inducing']:3d}/{row['cap']} train {row['ratio_training_median']:7.3f} "
                f"far {row['ratio_far_median']:7.3f} contains {row['contains_exact']:.3f} "
                f"warned {row['warned']} fit {row['fit_s']} s",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
