"""Unscented Kalman filter: compiled kernel, batch entry point and a numpy reference path."""

from kftune.filters.sigma_points import (
    UKFSettings,
    merwe_weights,
    sigma_points,
    unscented_transform,
)
from kftune.filters.ukf import (
    FilterDiverged,
    UKFBatchResult,
    UKFResult,
    UnscentedKalmanFilter,
    default_initial_state,
    run_ukf,
    run_ukf_batch,
    run_ukf_linear,
    run_ukf_reference,
)

__all__ = [
    "FilterDiverged",
    "UKFBatchResult",
    "UKFResult",
    "UKFSettings",
    "UnscentedKalmanFilter",
    "default_initial_state",
    "merwe_weights",
    "run_ukf",
    "run_ukf_batch",
    "run_ukf_linear",
    "run_ukf_reference",
    "sigma_points",
    "unscented_transform",
]
