"""Calibrated sensor model: fits of how often segmentation labels are right (isotonic, logistic, smoothed rates)."""
from .fit import (
    isotonic_fit,
    logistic_fit,
    logistic_predict,
    reliability_weight,
    smoothed_rates,
    smoothing_prior,
)

__all__ = [
    "isotonic_fit",
    "logistic_fit",
    "logistic_predict",
    "reliability_weight",
    "smoothed_rates",
    "smoothing_prior",
]
