"""Learning the unknown dynamics ``omega(x)``: data, GPs, confidence bounds."""

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

__all__ = [
    "Calibration",
    "ConfidenceReport",
    "Dataset",
    "FastGP",
    "GaussianProcessModel",
    "SklearnGPAdapter",
    "beta_lemma2",
    "calibration",
    "collect_data",
    "confidence",
    "conformal_beta",
    "information_gain",
]
