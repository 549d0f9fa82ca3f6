"""Kalman filters: UKF and EKF over any state-space model (one interface, one result type),
the hand-written 3×3 single-track UKF (``run_ukf``, the fast path) and its SIMD lanes."""

from kftune.filters.generic import (
    EKF,
    UKF,
    FilterBatchResult,
    FilterResult,
    ModelFilter,
    filter_names,
    get_filter,
)
from kftune.filters.sigma_points import (
    UKFSettings,
    merwe_weights,
    sigma_points,
    unscented_transform,
)
from kftune.filters.ukf import (
    UKFBatchResult,
    UKFResult,
    default_initial_state,
    run_ukf,
    run_ukf_batch,
    run_ukf_linear,
    run_ukf_simd,
)

__all__ = [
    "EKF",
    "UKF",
    "FilterBatchResult",
    "FilterResult",
    "ModelFilter",
    "UKFBatchResult",
    "UKFResult",
    "UKFSettings",
    "default_initial_state",
    "filter_names",
    "get_filter",
    "merwe_weights",
    "run_ukf",
    "run_ukf_batch",
    "run_ukf_linear",
    "run_ukf_simd",
    "sigma_points",
    "unscented_transform",
]
