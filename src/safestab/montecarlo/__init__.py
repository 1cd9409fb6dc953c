"""Monte Carlo verification of the probabilistic safety guarantee.

``run_montecarlo`` runs ``N`` closed loops of every compared controller over ``K`` fitted GPs,
batched (``lax.scan`` inside ``vmap``, in chunks) on one machine or as Ray tasks on a cluster;
``summarize`` gives the safety rates with exact Clopper-Pearson intervals. See
docs/montecarlo.md.
"""

from ..scenarios import MonteCarloSpec
from .loop import RECORD_FIELDS, StatisticsRecorder, trial_function
from .report import metrics_document, plot_montecarlo, trials_npz_bytes
from .runner import BACKENDS, MonteCarloRun, run_montecarlo, start_ray
from .stats import clopper_pearson, summarize

# The study's plumbing (data sets, trial draws, chunks) stays in its modules:
# montecarlo.trials, montecarlo.runner, montecarlo.stats; the protocol a scenario
# provides is montecarlo.protocol.TrialStudy.
__all__ = [
    "BACKENDS",
    "RECORD_FIELDS",
    "MonteCarloRun",
    "MonteCarloSpec",
    "StatisticsRecorder",
    "clopper_pearson",
    "metrics_document",
    "plot_montecarlo",
    "run_montecarlo",
    "start_ray",
    "summarize",
    "trial_function",
    "trials_npz_bytes",
]
