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
    "InducingCache",
    "SklearnGPAdapter",
    "SparseGP",
    "beta_lemma2",
    "calibration",
    "collect_data",
    "condition",
    "confidence",
    "conformal_beta",
    "inducing_cache",
    "information_gain",
]
