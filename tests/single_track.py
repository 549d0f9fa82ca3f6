"""The paper's filter, the single-track UKF, called as the tests have always called it:
``run_ukf(u, z, dt, vehicle, q, r)``. Thin shorthands over kftune's one UKF
(:class:`kftune.filters.UKF` on :data:`kftune.models.SINGLE_TRACK`, which runs the
model's own 3×3 loop and its vector lanes behind the generic interface), so that a test
says which filter it exercises without repeating the model."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from kftune.filters import UKF, FilterBatchResult, FilterResult, UKFSettings
from kftune.models import SINGLE_TRACK
from kftune.models.sideslip import single_track_prior


def run_ukf(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: Any,
    q: ArrayLike,
    r: ArrayLike,
    *,
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
    settings: UKFSettings = UKFSettings(),  # noqa: B008 (frozen)
) -> FilterResult:
    """One single-track UKF run (u (N, 2) [δ, ax], z (N, 3) [Vx, ay, r], a vehicle or its
    packed (9,) parameters, q and r (3,))."""
    return UKF(settings).run(SINGLE_TRACK, u, z, dt, q, r, params=params, x0=x0, P0=P0)


def run_ukf_batch(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: Any,
    q: ArrayLike,
    r: ArrayLike,
    *,
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
    settings: UKFSettings = UKFSettings(),  # noqa: B008
    lanes: bool = False,
) -> FilterBatchResult:
    """B single-track UKF runs, q (B, 3), r (3,) or (B, 3): in threads, or with ``lanes``
    across the vector lanes of one core."""
    return UKF(settings).run_batch(
        SINGLE_TRACK, u, z, dt, q, r, params=params, x0=x0, P0=P0, lanes=lanes
    )


def run_ukf_simd(*args: Any, **kwargs: Any) -> FilterBatchResult:
    """:func:`run_ukf_batch` in the model's vector lanes."""
    return run_ukf_batch(*args, **kwargs, lanes=True)


def default_initial_state(z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The single-track model's default prior (x0 (3,), P0 (3, 3)) from z (N, 3) and r (3,)."""
    return single_track_prior(np.asarray(z)[0], np.asarray(r), np.empty(0))


def beta(res: FilterResult | FilterBatchResult) -> np.ndarray:
    """(…, N) the estimated sideslip atan2(Vy, Vx) [rad]."""
    return np.arctan2(res.x[..., 1], res.x[..., 0])
