"""Kalman filters: the UKF and the EKF over any state-space model, one interface and one
result type. What is special about a model comes from the model: a model may supply its
own compiled loops (the single-track model's 3×3 loop and vector lanes), which the UKF
runs behind the same interface (:class:`~kftune.models.ModelKernels`)."""

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

__all__ = [
    "EKF",
    "UKF",
    "FilterBatchResult",
    "FilterResult",
    "ModelFilter",
    "UKFSettings",
    "filter_names",
    "get_filter",
    "merwe_weights",
    "sigma_points",
    "unscented_transform",
]
