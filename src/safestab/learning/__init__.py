"""Learning the unknown dynamics ``omega(x)``: data, GPs, their batched forms, confidence bounds."""

from .batched import (
    BatchedUncertainty,
    ExactPosterior,
    Hyperparameters,
    InducingCache,
    condition,
    inducing_cache,
)
from .bounds import (
    Calibration,
    ConfidenceReport,
    beta_lemma2,
    calibration,
    confidence,
    conformal_beta,
    information_gain,
)
from .data import Dataset, collect_data
from .fast import FastGP
from .gp import GaussianProcessModel
from .input_gain import InputGain, estimate_input_gain, fit_input_gain
from .sklearn_adapter import SklearnGPAdapter
from .sparse import SparseGP

__all__ = [
    "BatchedUncertainty",
    "Calibration",
    "ConfidenceReport",
    "Dataset",
    "ExactPosterior",
    "FastGP",
    "GaussianProcessModel",
    "Hyperparameters",
    "InputGain",
    "InducingCache",
    "SklearnGPAdapter",
    "SparseGP",
    "beta_lemma2",
    "calibration",
    "collect_data",
    "condition",
    "confidence",
    "conformal_beta",
    "estimate_input_gain",
    "fit_input_gain",
    "inducing_cache",
    "information_gain",
]
