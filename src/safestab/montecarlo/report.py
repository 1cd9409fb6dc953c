"""Outputs of a Monte Carlo study: the figure, the metrics document and the per-trial file."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from .._io import with_finite_status
from .runner import MonteCarloRun
from .stats import summarize

__all__ = ["metrics_document", "plot_montecarlo", "trials_npz_bytes"]


def metrics_document(run: MonteCarloRun) -> dict[str, Any]:
    """Settings, per-controller statistics, data sets and timings, as strict JSON data.

    Non-finite numbers become ``null``; ``status`` is ``"ok"`` or ``"non-finite"`` and
    ``non_finite`` maps the JSON Pointer of each replaced value to what it was.
    """
    spec, study = run.spec, run.study
    doc = {
        "scenario": study.name,
        "settings": {
            "seed": run.seed,
            "trials": int(run.records["min_h"].shape[0]),
            "datasets": len(run.datasets),
            "backend": run.backend,
            "chunk_size": spec.chunk_size,
            "gp": spec.gp,
            "hyperparameters": spec.hyperparameters,
            "delta": spec.delta,
            "rkhs_norm": spec.rkhs_norm,
            "initial_distribution": spec.initial_distribution,
            "lead_kind": spec.lead_kind,
            "h_unit": run.study.h_unit,
            "t_final_s": study.t_final,
            "dt_s": study.dt,
            "n_samples": study.gp_settings()["n_samples"],
        },
        "summary": summarize(run),
        "datasets": [
            {
                "index": m.index,
                "amplitude": m.hyper.amplitude.tolist(),
                "lengthscale": m.hyper.lengthscale.tolist(),
                "noise": m.hyper.noise.tolist(),
                "information_gain": m.information_gain.tolist(),
                "betas": {k: np.asarray(v).tolist() for k, v in m.betas.items()},
                "held_out_coverage": m.held_out_coverage,
                "cache_warnings": list(m.cache_warnings),
            }
            for m in run.datasets
        ],
        "timings_s": run.timings,
    }
    return with_finite_status(doc)


def trials_npz_bytes(run: MonteCarloRun) -> bytes:
    """The per-trial records (N, C), the data-set index (N,) and the controller names, as .npz."""
    buf = io.BytesIO()
    arrays: dict[str, Any] = {
        "controllers": np.array(run.controllers),
        "dataset_index": run.dataset_index,
        **run.records,
    }
    np.savez(buf, **arrays)
    return buf.getvalue()


def symlog_threshold(min_h: np.ndarray) -> float:
    """The linear range of the ECDF's symmetric log axis (the unit of h).

    The smallest controller's median ``|min h|`` over ten: 1e-9 at least, and 1 when every
    value is zero or not finite. ``min_h`` has shape (N, C), trials by controllers.
    """
    medians = []
    for col in np.asarray(min_h, float).reshape(len(min_h), -1).T:
        mag = np.abs(col[np.isfinite(col)])
        if mag.size and np.median(mag) > 0:
            medians.append(float(np.median(mag)))
    return max(min(medians) / 10, 1e-9) if medians else 1.0


def plot_montecarlo(run: MonteCarloRun, ax: Any = None) -> Any:
    """Min-h ECDF per controller (h = 0 marked) and the rates with exact 95 % intervals.

    Parameters
    ----------
    run : MonteCarloRun
    ax : pair of matplotlib axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    else:
        fig = ax[0].figure
    summary = summarize(run)
    names = run.controllers
    for c, name in enumerate(names):
        h = np.sort(run.records["min_h"][:, c])
        h = h[np.isfinite(h)]
        if h.size:
            ax[0].step(h, np.arange(1, h.size + 1) / run.records["min_h"].shape[0],
                       where="post", label=name)  # fmt: skip
    ax[0].axvline(0.0, color="k", lw=1, ls="--", label="h = 0")
    # min h spans decades (the ACC's Lemma-2 controller keeps tens of metres, the others
    # millimetres or less): a symmetric log axis, linear within the smallest controller's typical
    # distance from 0, so the curves near h = 0 are told apart and signs stay visible
    lin = symlog_threshold(run.records["min_h"])
    ax[0].set_xscale("symlog", linthresh=lin)
    unit = run.study.h_unit
    ax[0].set_xlabel(f"min over the run of h ({unit}; linear within +-{lin:.1g}, log beyond)")
    ax[0].set_ylabel("fraction of trials (ECDF)")
    ax[0].set_title(f"{run.study.name}: {summary['trials']} trials, "
                    f"{summary['datasets']} data sets")  # fmt: skip
    ax[0].legend(fontsize=8)
    kinds = (("safe", "safe (min h >= 0)"), ("cbf_true_every_step", "CBF cond. (true) every step"),
             ("lemma2_every_state", "Lemma-2 event every state"))  # fmt: skip
    width = 0.8 / len(kinds)
    for j, (key, label) in enumerate(kinds):
        xs, ys, lo, hi = [], [], [], []
        for c, name in enumerate(names):
            entry = summary["controllers"][name].get(key)
            if entry is None:
                continue
            xs.append(c + (j - 1) * width)
            ys.append(entry["rate"])
            lo.append(entry["rate"] - entry["ci95"][0])
            hi.append(entry["ci95"][1] - entry["rate"])
        ax[1].bar(xs, ys, width, yerr=[lo, hi], capsize=3, label=label)
    ax[1].axhline(summary["claimed_probability"], color="k", lw=1, ls=":",
                  label="(1 - delta)^n claimed")  # fmt: skip
    ax[1].set_xticks(range(len(names)), names, rotation=20, fontsize=8)
    ax[1].set_ylim(0, 1.05)
    ax[1].set_ylabel("rate with exact 95 % interval")
    ax[1].legend(fontsize=8, loc="lower left")
    return fig
