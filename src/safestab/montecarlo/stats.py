"""Statistics of a Monte Carlo study: exact binomial intervals and per-controller summaries."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.stats

from ..controller_names import GP_ROBUST_CONFORMAL, GP_ROBUST_LEMMA2
from ..controllers import StepStatus
from ..errors import ParameterError
from ..robust import joint_probability
from .runner import MonteCarloRun

__all__ = ["GUARANTEES", "clopper_pearson", "empirical_bernstein", "safe_mask", "summarize"]


def clopper_pearson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) two-sided interval for a binomial proportion.

    Parameters
    ----------
    successes : int
        ``k``, in ``[0, n]``.
    trials : int
        ``n >= 1``.
    confidence : float
        In (0, 1); default 0.95.

    Returns
    -------
    (low, high) : floats
        ``low = B(alpha/2; k, n - k + 1)`` (0 when ``k = 0``) and
        ``high = B(1 - alpha/2; k + 1, n - k)`` (1 when ``k = n``), quantiles of the beta
        distribution, ``alpha = 1 - confidence``. The interval covers the true proportion with
        probability at least ``confidence`` for every proportion (it is conservative).

    Raises
    ------
    ParameterError
        If the counts are not integers with ``0 <= successes <= trials`` and ``trials >= 1``,
        or ``confidence`` is outside (0, 1).
    """
    for name, value in (("successes", successes), ("trials", trials)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ParameterError(f"{name} must be an integer, got {value!r}")
    if trials < 1 or not 0 <= successes <= trials:
        raise ParameterError(
            f"need 0 <= successes <= trials and trials >= 1, got successes={successes} and "
            f"trials={trials}"
        )
    if not isinstance(confidence, float | int) or not 0.0 < confidence < 1.0:
        raise ParameterError(f"confidence must be in (0, 1), got {confidence!r}")
    alpha = 1.0 - float(confidence)
    k, n = int(successes), int(trials)
    low = 0.0 if k == 0 else float(scipy.stats.beta.ppf(alpha / 2, k, n - k + 1))
    high = 1.0 if k == n else float(scipy.stats.beta.ppf(1 - alpha / 2, k + 1, n - k))
    return low, high


def empirical_bernstein(values: Any, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided interval for the mean of independent values in [0, 1] (empirical Bernstein).

    Used for a per-trial rate when trials share data sets: the trials of one data set are not
    independent (they share its GP), so the unit is the data set and ``values`` are the
    per-data-set fractions (their mean is the per-trial probability when every data set has
    as many trials). Maurer and Pontil (2009, Theorem 4), each side at ``alpha / 2``: with
    ``K`` values, sample variance ``V`` (``1 / (K - 1)`` normalisation) and
    ``L = ln(4 / alpha)``, the mean lies within
    ``sqrt(2 V L / K) + 7 L / (3 (K - 1))`` of the sample mean with probability at least
    ``confidence``, whatever the distribution; clipped to [0, 1]. It is conservative: wide
    for few data sets (no interval below 2), close to the normal interval when ``V`` is
    large.

    Raises
    ------
    ParameterError
        If ``values`` has fewer than 2 entries or entries outside [0, 1], or ``confidence``
        is outside (0, 1).
    """
    z = np.asarray(values, float).reshape(-1)
    if z.size < 2 or not np.all((z >= 0) & (z <= 1)):
        raise ParameterError(
            f"values must be at least 2 numbers in [0, 1], got {z.size} values"
            + ("" if z.size < 2 else f" in [{z.min():g}, {z.max():g}]")
        )
    if not isinstance(confidence, float | int) or not 0.0 < confidence < 1.0:
        raise ParameterError(f"confidence must be in (0, 1), got {confidence!r}")
    k = z.size
    log_term = math.log(4.0 / (1.0 - float(confidence)))
    half = math.sqrt(2.0 * float(np.var(z, ddof=1)) * log_term / k) + 7 * log_term / (3 * (k - 1))
    mean = float(np.mean(z))
    return max(0.0, mean - half), min(1.0, mean + half)


def safe_mask(records: dict[str, np.ndarray]) -> np.ndarray:
    """Trials (rows) x controllers where every step gave an input and ``h >= 0`` throughout.

    ``h`` at the samples (``min_h``) and, with substeps, between them (``min_h_between``).

    A trial whose run stopped being finite counts as not safe (its ``min_h`` is NaN). Steps
    whose input could not meet a CBF condition (``barrier_unmet_steps``) are counted apart.
    """
    ok = records["first_bad_status"] == StepStatus.OK
    # between the samples too, where the records have it (min_h with one substep)
    least = records.get("min_h_between", records["min_h"])
    with np.errstate(invalid="ignore"):
        return ok & (records["min_h"] >= 0) & (least >= 0)


#: The controllers whose beta carries a probability guarantee, what it claims and on what
#: it rests (printed beside their rates, plotted against them and documented). Every other
#: controller has none: "GP-robust" uses a hand-chosen beta, "GP mean" beta = 0.
GUARANTEES: dict[str, dict[str, Any]] = {
    GP_ROBUST_LEMMA2: {
        "source": "Lemma 2 with Theorem 3",
        "claim": "(1 - delta)^n over the data set (the measurement noise): the band "
        "|omega_i - m_i| <= beta_i sigma_i holds at every state, so the controller is safe",
        "unit": "data set",
        "assumptions": [
            "||omega_i||_k <= rkhs_norm for every learned component (assumed, not checked: "
            "montecarlo.rkhs_norm)",
            "the measurement noise is independent, zero-mean and sigma-sub-Gaussian with the "
            "GP's noise std",
            "gamma is the information gain of the data set's own inputs, not the maximum "
            "over every input set of that size (so beta can be smaller than Lemma 2's)",
            "the hyperparameters do not depend on the data set (with 'reuse', data set 0's; "
            "data set 0 itself was fitted on its own data)",
            "tested on the trials of a data set only, not on every initial state",
        ],
    },
    GP_ROBUST_CONFORMAL: {
        "source": "split conformal prediction (learning.conformal_beta)",
        "claim": "1 - delta per trial, over the calibration draw and the trial together: "
        "the band holds along the trial's trajectory, so the controller is safe",
        "unit": "trial",
        "assumptions": [
            "the trial's closed-loop trajectory is exchangeable with the calibration "
            "trajectories; here it is not (these are excitation trajectories, so the "
            "closed-loop states come from another distribution)",
            "the claim is marginal over data sets, not conditional on one: it is read on the "
            "per-trial rate with the interval over data sets",
            "one joint band for all learned components (the score is their maximum), so the "
            "claim is 1 - delta, not (1 - delta)^n",
        ],
    },
}


def _rate(k: int, n: int) -> dict[str, Any]:
    low, high = clopper_pearson(k, n)
    return {"count": k, "trials": n, "rate": k / n, "ci95": [low, high]}


def _per_trial(event: np.ndarray, dataset_index: np.ndarray, n_sets: int) -> dict[str, Any]:
    """A per-trial rate with an interval that respects the data sets' clustering.

    One trial per data set: the trials are independent, exact Clopper-Pearson interval. One
    data set: the trials are independent given the data, so the Clopper-Pearson interval is
    for the rate conditional on that data set (``interval`` says so). Otherwise: the
    empirical-Bernstein interval over the per-data-set fractions.
    """
    n, k = event.size, int(event.sum())
    if n_sets == n:
        return {**_rate(k, n), "interval": "Clopper-Pearson (one trial per data set)"}
    if n_sets == 1:
        return {**_rate(k, n), "interval": "Clopper-Pearson, conditional on the one data set"}
    held, trials = _set_counts(event, dataset_index, n_sets)
    fractions = held / trials
    return {
        "count": k, "trials": n, "rate": k / n,
        "ci95": list(empirical_bernstein(fractions)),
        "interval": "empirical Bernstein over the per-data-set fractions",
    }  # fmt: skip


def _per_dataset(event: np.ndarray, dataset_index: np.ndarray, n_sets: int) -> dict[str, Any]:
    """Data sets whose every trial had ``event``, with the exact interval over data sets."""
    held, trials = _set_counts(event, dataset_index, n_sets)
    count = int(np.sum(held == trials))
    low, high = clopper_pearson(count, n_sets)
    return {
        "count": count, "datasets": n_sets, "rate": count / n_sets,
        "ci95": [low, high], "interval": "Clopper-Pearson over data sets",
    }  # fmt: skip


def _set_counts(event: np.ndarray, dataset_index: np.ndarray, n_sets: int) -> Any:
    """Per data set: the trials with ``event`` and all its trials, two arrays of shape (K,).

    One pass over the trials (``bincount``), where a mask per data set cost K passes (10
    million comparisons per rate at K = 1,000 and N = 10,000).
    """
    held = np.bincount(dataset_index, weights=event.astype(float), minlength=n_sets)
    return held, np.bincount(dataset_index, minlength=n_sets).astype(float)


def _guarantee(name: str, entry: dict[str, Any], delta: float, n_comp: int) -> Any:
    """The controller's claimed probability, its assumptions and the rate that tests it."""
    if name not in GUARANTEES:
        return None
    g = GUARANTEES[name]
    per_set = g["unit"] == "data set"
    claimed = joint_probability(delta, n_comp) if per_set else 1.0 - delta
    key = "safe_per_dataset" if per_set else "safe"
    measured = entry[key]
    return {
        **g,
        "claimed_probability": claimed,
        "measured_by": key,
        "consistent": bool(measured["ci95"][1] >= claimed),
        "excess_over_claim": measured["rate"] - claimed,
    }


def summarize(run: MonteCarloRun) -> dict[str, Any]:
    """Per-controller rates: per data set (the theorem's unit) and per trial, with intervals.

    Theorems 2 and 3 bound a probability over the *data*: a data set is the unit, and the
    trials that share a data set are not independent draws of that event. So:

    - ``safe_per_dataset``: data sets whose every trial was safe, with the exact
      Clopper-Pearson interval over the ``K`` data sets (``lemma2_per_dataset`` likewise for
      the band at every visited state);
    - per-trial rates (``safe``, ``cbf_true_every_step``, ``lemma2_every_state``): with
      ``K = N`` the exact interval; with ``K = 1`` the exact interval conditional on that
      data set; otherwise the empirical-Bernstein interval over the per-data-set fractions
      (:func:`empirical_bernstein`); ``interval`` names which;
    - ``guarantee``: only for the controllers of :data:`GUARANTEES` (Lemma 2, conformal):
      the claimed probability, its event, assumptions, the rate that tests it and whether
      that rate's interval reaches the claim; ``None`` for every other controller.

    Returns
    -------
    dict
        ``trials``, ``datasets``, ``trials_per_dataset`` ([fewest, most]), ``h_unit`` and per
        controller the rates above, ``non_finite_trials``, ``min_h`` quantiles (``h_unit``),
        mean time with h < 0, CLF statistics and incompatible steps; GP controllers also
        ``beta_mean_over_datasets`` and ``held_out_coverage_mean``.
    """
    rec = run.records
    n = rec["min_h"].shape[0]
    k_sets = len(run.datasets)
    sets = np.asarray(run.dataset_index)
    counts = np.bincount(sets, minlength=k_sets)
    safe = safe_mask(rec)
    n_comp = len(run.datasets[0].hyper.components)
    out: dict[str, Any] = {
        "trials": n,
        "datasets": k_sets,
        "trials_per_dataset": [int(counts.min()), int(counts.max())],
        "h_unit": run.study.h_unit,
        "controllers": {},
    }
    for c, name in enumerate(run.controllers):
        min_h = rec["min_h"][:, c]
        finite = np.isfinite(min_h)
        cbf_ok = rec["cbf_true_violations"][:, c] == 0
        entry: dict[str, Any] = {
            "safe": _per_trial(safe[:, c], sets, k_sets),
            "safe_per_dataset": _per_dataset(safe[:, c], sets, k_sets),
            "cbf_true_every_step": _per_trial(cbf_ok, sets, k_sets),
            "non_finite_trials": int(np.sum(rec["first_bad_status"][:, c] != StepStatus.OK)),
            "min_h_quantiles": {
                q: float(np.quantile(min_h[finite], float(q))) if finite.any() else math.nan
                for q in ("0.0", "0.001", "0.01", "0.5")
            },
            "mean_time_h_negative_s": float(np.mean(rec["time_h_negative"][:, c])),
            "min_cbf_true_margin": float(np.min(rec["min_cbf_true_margin"][:, c])),
            "mean_clf_true_fraction": float(np.mean(rec["clf_true_fraction"][:, c])),
            "mean_final_V": float(np.mean(rec["final_V"][:, c])),
            "incompatible_steps_total": int(np.sum(rec["incompatible_steps"][:, c])),
        }
        if "min_h_between" in rec:
            between = rec["min_h_between"][:, c]
            entry["left_between_samples_trials"] = int(
                np.sum((between < 0) & ~(min_h < 0) & finite)
            )
        if "barrier_unmet_steps" in rec:  # records written before the count existed lack it
            unmet = rec["barrier_unmet_steps"][:, c]
            entry["barrier_unmet_steps_total"] = int(np.sum(unmet))
            entry["barrier_unmet_trials"] = int(np.sum(unmet > 0))
        l2 = rec["lemma2_violations"][:, c]
        if np.all(l2 >= 0):
            held = l2 == 0
            entry["lemma2_every_state"] = _per_trial(held, sets, k_sets)
            entry["lemma2_per_dataset"] = _per_dataset(held, sets, k_sets)
            entry["beta_mean_over_datasets"] = np.mean(
                [m.betas[name] for m in run.datasets], axis=0
            ).tolist()
            entry["held_out_coverage_mean"] = float(
                np.mean([m.held_out_coverage[name] for m in run.datasets])
            )
        entry["guarantee"] = _guarantee(name, entry, run.spec.delta, n_comp)
        out["controllers"][name] = entry
    return out
