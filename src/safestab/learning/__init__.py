"""Learning the unknown dynamics ``omega(x)``: data, kernels, GPs, their batched forms, bounds."""

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
from .kernels import Matern52, SquaredExponential, StationaryKernel
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
    "Matern52",
    "SklearnGPAdapter",
    "SparseGP",
    "SquaredExponential",
    "StationaryKernel",
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
