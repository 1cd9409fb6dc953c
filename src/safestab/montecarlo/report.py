"""Outputs of a Monte Carlo study: the figure, the metrics document and the per-trial file."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from .._io import with_finite_status
from .runner import MonteCarloRun
from .stats import summarize

__all__ = [
    "markdown_table", "metrics_document", "plot_montecarlo", "study_settings", "trials_npz_bytes",
]  # fmt: skip


def study_settings(study: Any) -> dict[str, Any]:
    """What a study's documents record of its learning and its controllers.

    ``gp_settings``: the study's ``gp_settings()`` (``n_samples``, ``kernel``,
    ``hyper_subset``, ``gp_beta``, ``input_gain``); ``controller_settings``: its
    ``controller_settings()`` (the gains, the input limits and how they are kept,
    ``limit_method``), or None for a study without that optional member. As the study
    returns them (a copy): the documents' :func:`~safestab._io.with_finite_status` makes them
    JSON data.
    """
    describe = getattr(study, "controller_settings", None)
    return {
        "gp_settings": dict(study.gp_settings()),
        "controller_settings": None if describe is None else describe(),
    }


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
            **study_settings(study),
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
                # FastGP's std over the exact std at the training inputs (median), per
                # learned component; None for the exact posterior
                "std_over_exact": (
                    None if m.std_over_exact is None else np.asarray(m.std_over_exact).tolist()
                ),
                # the learned input-matrix error D (gp_settings input_gain = "learned")
                "input_gain": None if m.input_gain is None else np.asarray(m.input_gain).tolist(),
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


def _symlog_ticks(min_h: np.ndarray, lin: float) -> list[float]:
    """0 and every other power of ten beyond ``10 lin`` within the data, for a symlog axis.

    Labels nearer than that to 0 (inside the linear range) overlap the label of 0, and a
    tick at every decade crowds the axis when min h spans ten decades or more.
    """
    h = np.asarray(min_h, float)
    h = h[np.isfinite(h)]
    ticks = [0.0]
    for sign in (-1.0, 1.0):
        side = h[sign * h > 0] * sign
        if side.size == 0:
            continue
        lo = int(np.ceil(np.log10(10 * lin)))
        hi = int(np.ceil(np.log10(side.max())))
        exps = list(range(hi, lo - 1, -2)) if hi >= lo else []
        ticks += [sign * 10.0**e for e in exps]
    return sorted(ticks)


def plot_montecarlo(run: MonteCarloRun, ax: Any = None) -> Any:
    """Min-h ECDF per controller (h = 0 marked) and the rates with their 95 % intervals.

    The right panel: per controller the safe rate per data set (the theorem's unit), per
    trial and the Lemma-2 band per data set; a claimed probability is drawn only over the bar
    that tests it, for the controllers of :data:`~safestab.montecarlo.stats.GUARANTEES`.

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
    ax[0].set_xticks(_symlog_ticks(run.records["min_h"], lin))
    unit = run.study.h_unit
    ax[0].set_xlabel(f"min over the run of h ({unit}; linear within +-{lin:.1g}, log beyond)")
    ax[0].set_ylabel("fraction of trials (ECDF)")
    ax[0].set_title(f"{run.study.name}: {counted(summary['trials'], 'trial')}, "
                    f"{counted(summary['datasets'], 'data set')}")  # fmt: skip
    ax[0].legend(fontsize=8)
    kinds = (("safe_per_dataset", "safe, per data set (all its trials)"),
             ("safe", "safe, per trial"),
             ("lemma2_per_dataset", "Lemma-2 band, per data set"))  # fmt: skip
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
    # a claim only where a controller's beta carries one, over the bar that tests it
    claimed_label = "claimed probability (only where the beta carries one)"
    for c, name in enumerate(names):
        g = summary["controllers"][name]["guarantee"]
        if g is None:
            continue
        j = 0 if g["measured_by"] == "safe_per_dataset" else 1
        x = c + (j - 1) * width
        ax[1].hlines(g["claimed_probability"], x - width / 2, x + width / 2, color="k", lw=2,
                     label=claimed_label)  # fmt: skip
        claimed_label = None
    ax[1].set_xticks(range(len(names)), names, rotation=20, fontsize=8)
    ax[1].set_ylim(0, 1.05)
    ax[1].set_ylabel("rate with 95 % interval")
    # below the axes, so no bar (a rate near 0) is hidden behind it
    ax[1].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2)
    return fig


def markdown_table(doc: dict[str, Any]) -> str:
    """A metrics document's per-controller rates as a Markdown table (docs/montecarlo.md).

    One row per controller: safe per data set and per trial, the CBF condition on the true
    dynamics at every step (per trial), the Lemma-2 band per data set, the claimed
    probability (only where the controller's beta carries one, with its unit), min h (the
    smallest and the 1 % quantile, in the document's unit) and the mean beta. Each rate is
    ``rate [low, high]`` with its 95 % interval; a per-trial interval is over data sets when
    several data sets share the trials (``summary.controllers.<name>.safe.interval``).
    """
    summary = doc["summary"]
    unit = summary.get("h_unit", "")

    def rate(entry: Any) -> str:
        if entry is None:
            return "-"
        lo, hi = entry["ci95"]
        return f"{entry['rate']:.3f} [{lo:.3f}, {hi:.3f}]"

    def count(entry: Any) -> str:
        if entry is None:
            return "-"
        lo, hi = entry["ci95"]
        return f"{entry['count']}/{entry['datasets']} [{lo:.3f}, {hi:.3f}]"

    lines = [
        "| controller | safe, per data set | safe, per trial | CBF cond. (true) every step, "
        f"per trial | Lemma-2 band, per data set | claimed | min h: min / 1 % quantile ({unit})"
        " | mean beta |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, e in summary["controllers"].items():
        g = e.get("guarantee")
        claim = "-" if g is None else f"{g['claimed_probability']:.4f} (per {g['unit']})"
        q = e["min_h_quantiles"]
        low = "-" if q["0.0"] is None else f"{q['0.0']:.4f}"
        one = "-" if q["0.01"] is None else f"{q['0.01']:.4f}"
        beta = e.get("beta_mean_over_datasets")
        beta_text = "-" if beta is None else ", ".join(f"{b:.3g}" for b in beta)
        lines.append(
            f"| {name} | {count(e['safe_per_dataset'])} | {rate(e['safe'])} "
            f"| {rate(e['cbf_true_every_step'])} | {count(e.get('lemma2_per_dataset'))} "
            f"| {claim} | {low} / {one} | {beta_text} |"
        )
    return "\n".join(lines) + "\n"


def counted(n: int, noun: str) -> str:
    """``"1 data set"``, ``"2 data sets"``: a count with its noun in the right number."""
    return f"{n} {noun}" + ("" if n == 1 else "s")
