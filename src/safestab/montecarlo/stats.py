"""Statistics of a Monte Carlo study: exact binomial intervals and per-controller summaries."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.stats

from ..controllers import StepStatus
from ..errors import ParameterError
from ..robust import joint_probability
from .runner import MonteCarloRun

__all__ = ["clopper_pearson", "summarize", "safe_mask"]


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


def safe_mask(records: dict[str, np.ndarray]) -> np.ndarray:
    """Trials (rows) x controllers where every step was OK and ``min h >= 0``.

    A trial whose run stopped being finite counts as not safe (its ``min_h`` is NaN).
    """
    ok = records["first_bad_status"] == StepStatus.OK
    with np.errstate(invalid="ignore"):
        return ok & (records["min_h"] >= 0)


def _rate(k: int, n: int) -> dict[str, Any]:
    low, high = clopper_pearson(k, n)
    return {"count": k, "trials": n, "rate": k / n, "ci95": [low, high]}


def summarize(run: MonteCarloRun) -> dict[str, Any]:
    """Per-controller rates with exact 95 % intervals, and per-data-set Lemma-2 frequencies.

    Returns
    -------
    dict
        Per controller: ``safe`` (min h >= 0 and every step OK), ``cbf_true_every_step``,
        ``lemma2_every_state`` (GP controllers; per trial), ``lemma2_per_dataset`` (the
        event over every visited state of every trial of a data set), ``non_finite_trials``,
        ``min_h`` quantiles (``h_unit``), mean time with h < 0, CLF statistics and
        incompatible steps; and ``claimed_probability`` = ``(1 - delta)^n`` for ``n`` learned
        components.
    """
    rec = run.records
    n = rec["min_h"].shape[0]
    safe = safe_mask(rec)
    n_comp = len(run.datasets[0].hyper.components)
    out: dict[str, Any] = {
        "trials": n,
        "datasets": len(run.datasets),
        "claimed_probability": joint_probability(run.spec.delta, n_comp),
        "h_unit": run.study.h_unit,
        "controllers": {},
    }
    for c, name in enumerate(run.controllers):
        min_h = rec["min_h"][:, c]
        finite = np.isfinite(min_h)
        entry: dict[str, Any] = {
            "safe": _rate(int(safe[:, c].sum()), n),
            "cbf_true_every_step": _rate(int(np.sum(rec["cbf_true_violations"][:, c] == 0)), n),
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
        l2 = rec["lemma2_violations"][:, c]
        if np.all(l2 >= 0):
            held = l2 == 0
            per_set = [bool(np.all(held[run.dataset_index == j])) for j in range(len(run.datasets))]
            entry["lemma2_every_state"] = _rate(int(held.sum()), n)
            entry["lemma2_per_dataset"] = _rate(int(sum(per_set)), len(per_set))
            entry["beta_mean_over_datasets"] = np.mean(
                [m.betas[name] for m in run.datasets], axis=0
            ).tolist()
            entry["held_out_coverage_mean"] = float(
                np.mean([m.held_out_coverage[name] for m in run.datasets])
            )
        out["controllers"][name] = entry
    return out
