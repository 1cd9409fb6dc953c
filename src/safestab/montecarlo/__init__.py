"""Monte Carlo verification of the probabilistic safety guarantee (issue 13).

``run_montecarlo`` runs ``N`` closed loops of every compared controller over ``K`` fitted GPs,
batched (``lax.scan`` inside ``vmap``, in chunks) on one machine or as Ray tasks on a cluster;
``summarize`` gives the safety rates with exact Clopper-Pearson intervals. See
docs/montecarlo.md.
"""

from ..scenarios import MonteCarloSpec
from .acc_trials import (
    CONFORMAL_MIN_TRAJECTORIES,
    DataSetModel,
    calibration_draw,
    draw_trials,
    fit_dataset,
    lead_acceleration,
    run_chunk,
)
from .loop import RECORD_FIELDS, trial_function
from .report import metrics_document, plot_montecarlo, trials_npz_bytes
from .runner import BACKENDS, MonteCarloRun, plan_chunks, run_montecarlo, start_ray
from .stats import clopper_pearson, safe_mask, summarize

__all__ = [
    "BACKENDS",
    "CONFORMAL_MIN_TRAJECTORIES",
    "RECORD_FIELDS",
    "DataSetModel",
    "MonteCarloRun",
    "MonteCarloSpec",
    "calibration_draw",
    "clopper_pearson",
    "draw_trials",
    "fit_dataset",
    "lead_acceleration",
    "metrics_document",
    "plan_chunks",
    "plot_montecarlo",
    "run_chunk",
    "run_montecarlo",
    "safe_mask",
    "start_ray",
    "summarize",
    "trial_function",
    "trials_npz_bytes",
]
