"""The price of robustness against the amount of data: a Monte Carlo study per data size.

For each data size ``Q`` the scenario's Monte Carlo study runs ``K`` independent data sets of
``Q`` rows with a few trials each (:func:`~safestab.montecarlo.run_montecarlo`), and every
controller is scored on two things:

- **safety**, on the theorem's unit: the data sets in which every trial was safe, with the
  exact Clopper-Pearson interval over the ``K`` data sets (``safe_per_dataset`` of
  :func:`~safestab.montecarlo.stats.summarize`);
- **price**, paired with the true-model controller on the same trials (same initial state,
  same lead or current): ``min h - min h_true`` (the margin kept beyond what the true model
  needs), ``settle_time - settle_time_true`` (the time to converge, ``V`` down to 1 % of its
  initial value for good, beyond the true model's), ``final V - final V_true`` (how much
  further from the goal the run ends) and ``clf_true_fraction_true - clf_true_fraction``
  (the share of steps on which the CLF decrease was given up, beyond the true model's);
  and, unpaired, ``mean_input_gap``: the mean over the run of ``max_j |u_j - u_true,j(x)|``,
  the controller's input against the true-model controller's input *at the same state*
  (``MonteCarloSpec.price_metrics``).

The pairing removes the spread of the trials themselves: a controller that behaves like the
true-model one scores 0 on every trial, whatever the initial state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .._io import with_finite_status
from ..controller_names import GP_CONTROLLERS, TRUE_MODEL
from ..errors import ParameterError
from ..scenarios import MonteCarloSpec
from .report import study_settings
from .runner import MonteCarloRun, run_montecarlo
from .stats import summarize

__all__ = ["PRICE_CONTROLLERS", "REFERENCE", "plot_price", "price_point", "price_study"]

#: The controller every price is measured against.
REFERENCE = TRUE_MODEL
#: The controllers of the study: the reference and the four GP controllers.
PRICE_CONTROLLERS = (REFERENCE, *GP_CONTROLLERS)
#: Quantiles of the paired differences over trials.
QUANTILES = ("0.1", "0.5", "0.9")


def _quantiles(values: np.ndarray) -> dict[str, float]:
    finite = values[np.isfinite(values)]
    return {q: float(np.quantile(finite, float(q))) if finite.size else math.nan
            for q in QUANTILES}  # fmt: skip


def price_point(run: MonteCarloRun, reference: str = REFERENCE) -> dict[str, Any]:
    """Safety per data set and the paired price of every controller of one Monte Carlo run.

    Parameters
    ----------
    run : MonteCarloRun
        Must include ``reference`` among its controllers.
    reference : str
        The controller the prices are measured against (default the true model).

    Returns
    -------
    dict
        Per controller: ``safe_per_dataset`` (count, rate and exact interval over data sets),
        ``safe`` (per trial, with the interval of :func:`summarize`), the quantiles
        :data:`QUANTILES` over trials of ``min_h_excess`` (``min h - min h_ref``, in the
        study's ``h_unit``) and ``final_V_excess``, the mean ``clf_fraction_deficit``, for GP
        controllers ``beta_mean``, where the run measured them (``price_metrics``) the
        quantiles of ``settle_time_excess`` (s) and ``mean_input_gap`` (input units), and
        how often the limit bound and the barrier went unmet (``limit_step_fraction``,
        ``limit_trials``, ``barrier_unmet_trials``, ``barrier_unmet_steps``).

    Raises
    ------
    ParameterError
        If ``reference`` is not one of the run's controllers.
    """
    if reference not in run.controllers:
        raise ParameterError(
            f"reference must be one of the run's controllers {list(run.controllers)}, "
            f"got {reference!r}"
        )
    summary = summarize(run)
    rec = run.records
    r = run.controllers.index(reference)
    out: dict[str, Any] = {}
    for c, name in enumerate(run.controllers):
        s = summary["controllers"][name]
        entry = {
            "safe_per_dataset": s["safe_per_dataset"],
            "safe": s["safe"],
            "min_h_excess": _quantiles(rec["min_h"][:, c] - rec["min_h"][:, r]),
            "final_V_excess": _quantiles(rec["final_V"][:, c] - rec["final_V"][:, r]),
            "clf_fraction_deficit": float(
                np.mean(rec["clf_true_fraction"][:, r] - rec["clf_true_fraction"][:, c])
            ),
        }
        if np.all(rec["settle_time"][:, c] >= 0):  # measured (price_metrics)
            entry["settle_time_excess"] = _quantiles(
                rec["settle_time"][:, c] - rec["settle_time"][:, r]
            )
            entry["mean_input_gap"] = _quantiles(rec["mean_input_gap"][:, c])
        if "beta_mean_over_datasets" in s:
            entry["beta_mean"] = s["beta_mean_over_datasets"]
        entry |= _limit_counts(rec, c, run.study.n_steps)
        out[name] = entry
    return out


def _limit_counts(rec: dict[str, np.ndarray], c: int, n_steps: int) -> dict[str, Any]:
    """How often the input limit bound and the barrier went unmet, for controller ``c``.

    ``limit_step_fraction``: the share of all steps whose input was on a limit;
    ``limit_trials``: trials with any such step; ``barrier_unmet_trials`` and
    ``barrier_unmet_steps``: trials with, and the count of, steps whose status said the
    barrier's condition was not met (``CBF_INFEASIBLE`` and the other named statuses).
    Records without the counts (older runs) give none of these keys.
    """
    out: dict[str, Any] = {}
    if "limit_steps" in rec:
        steps = rec["limit_steps"][:, c]
        out["limit_step_fraction"] = float(np.sum(steps) / (steps.size * n_steps))
        out["limit_trials"] = int(np.sum(steps > 0))
    if "barrier_unmet_steps" in rec:
        unmet = rec["barrier_unmet_steps"][:, c]
        out["barrier_unmet_trials"] = int(np.sum(unmet > 0))
        out["barrier_unmet_steps"] = int(np.sum(unmet))
    return out


def _check_sizes(q_values: Sequence[int]) -> list[int]:
    qs = list(q_values)
    if not qs or any(isinstance(q, bool) or not isinstance(q, int | np.integer) for q in qs):
        raise ParameterError(f"q_values must be a non-empty list of integers, got {q_values!r}")
    if any(b <= a for a, b in zip(qs, qs[1:], strict=False)):
        raise ParameterError(f"q_values must increase, got {qs}")
    return [int(q) for q in qs]


def price_study(
    scenario: Any,
    q_values: Sequence[int],
    *,
    datasets: int,
    trials_per_dataset: int,
    seed: int = 0,
    controllers: Sequence[str] = PRICE_CONTROLLERS,
    progress: Callable[[int, int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the scenario's Monte Carlo study at each data size and score the controllers.

    Parameters
    ----------
    scenario : ACCScenario, ObstacleScenario or any scenario with ``replace(n_samples=...)``
        and ``trial_study``; its ``[montecarlo]`` table gives the trial distributions, the
        GP (``gp``, ``n_inducing``, ``hyperparameters``), ``delta`` and ``rkhs_norm``.
    q_values : sequence of int
        The data sizes ``Q``, increasing (each checked by the scenario like ``--n-samples``).
    datasets, trials_per_dataset : int
        ``K`` data sets per size, and trials per data set (``N = K * trials_per_dataset``).
    seed : int
        The Monte Carlo seed, the same at every size (data set ``j`` and trial ``i`` draw
        from ``(seed, j)`` and ``(seed, i)``: the trials are the same at every size).
    controllers : sequence of str
        Must include :data:`REFERENCE`.
    progress : callable, optional
        ``progress(size_index, sizes, q)`` before each size.

    Returns
    -------
    dict
        Strict JSON data: ``scenario``, ``settings``, ``h_unit`` and ``points``, one per
        size: ``n_samples``, ``timings_s`` and the :func:`price_point` of each controller.

    Raises
    ------
    ParameterError
        For bad sizes, counts or controllers (before any data set is drawn).
    ScenarioError
        If the scenario refuses a size.
    """
    qs = _check_sizes(q_values)
    for name, value in (("datasets", datasets), ("trials_per_dataset", trials_per_dataset)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ParameterError(f"{name} must be an integer >= 1, got {value!r}")
    if REFERENCE not in controllers:
        raise ParameterError(
            f"controllers must include {REFERENCE!r}, the reference of every price, "
            f"got {list(controllers)}"
        )
    scenarios = [scenario.replace(n_samples=q) for q in qs]  # every size checked first
    base = getattr(scenario, "montecarlo", None) or MonteCarloSpec()  # as run_montecarlo
    spec = base.replace(controllers=tuple(controllers), price_metrics=True)
    points = []
    for i, (q, sc) in enumerate(zip(qs, scenarios, strict=True)):
        if progress is not None:
            progress(i, len(qs), q)
        run = run_montecarlo(
            sc, trials=datasets * trials_per_dataset, datasets=datasets, seed=seed,
            spec=spec,
        )  # fmt: skip
        points.append({"n_samples": q, "timings_s": run.timings,
                       "controllers": price_point(run)})  # fmt: skip
    # the same at every size (qs is not empty) but n_samples, each point's
    recorded = study_settings(run.study)
    recorded["gp_settings"].pop("n_samples", None)
    doc = {
        "scenario": scenario.name,
        "settings": {
            "q_values": qs,
            "datasets": datasets,
            "trials_per_dataset": trials_per_dataset,
            "seed": seed,
            "controllers": list(controllers),
            "reference": REFERENCE,
            "gp": spec.gp,
            "n_inducing": spec.n_inducing,
            "hyperparameters": spec.hyperparameters,
            "delta": spec.delta,
            "rkhs_norm": spec.rkhs_norm,
            **recorded,
        },  # fmt: skip
        "h_unit": run.study.h_unit,
        "points": points,
    }
    return with_finite_status(doc)


def plot_price(doc: dict[str, Any]) -> Any:
    """The study's figure: safety per data set and the price in min h, against ``Q``.

    Left: the share of data sets whose every trial was safe, with its exact 95 % interval,
    per controller. Right: the paired ``min h - min h_true`` over trials (median, and the
    10 % to 90 % band), on a symmetric log axis.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullLocator

    qs = np.array([p["n_samples"] for p in doc["points"]], float)
    names = [n for n in doc["settings"]["controllers"] if n != doc["settings"]["reference"]]
    fig, (ax_s, ax_p) = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for k, name in enumerate(names):
        colour = f"C{k}"
        entries = [p["controllers"][name] for p in doc["points"]]
        rate = np.array([e["safe_per_dataset"]["rate"] for e in entries], float)
        lo = np.array([e["safe_per_dataset"]["ci95"][0] for e in entries], float)
        hi = np.array([e["safe_per_dataset"]["ci95"][1] for e in entries], float)
        shift = qs * (1 + 0.03 * (k - (len(names) - 1) / 2))  # apart, on a log axis
        ax_s.errorbar(shift, rate, yerr=[rate - lo, hi - rate], marker="o", ms=4, capsize=2,
                      color=colour, label=name)  # fmt: skip
        excess = [e["min_h_excess"] for e in entries]
        med = np.array([x["0.5"] for x in excess], float)
        ax_p.plot(qs, med, marker="o", ms=4, color=colour, label=name)
        ax_p.fill_between(qs, [x["0.1"] for x in excess], [x["0.9"] for x in excess],
                          color=colour, alpha=0.15, lw=0)  # fmt: skip
    unit = doc["h_unit"]
    k_sets = doc["settings"]["datasets"]
    ax_s.set(ylim=(-0.03, 1.03), ylabel=f"share of the {k_sets} data sets (95 % CI)",
             title=f"{doc['scenario']}: data sets with every trial safe")  # fmt: skip
    ax_p.set_yscale("symlog", linthresh=1e-3)
    ax_p.axhline(0.0, color="k", lw=0.8)
    ax_p.set(ylabel=f"min h - min h of the true model ({unit})",
             title=f"{doc['scenario']}: margin paid (median, 10-90 % of trials)")  # fmt: skip
    for ax in (ax_s, ax_p):
        ax.set_xscale("log")
        ax.set_xticks(qs, [f"{int(q)}" for q in qs])
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_xlabel("data size Q (rows)")
    ax_s.legend(fontsize=7, loc="lower right")
    return fig
