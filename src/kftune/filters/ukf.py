"""Unscented Kalman filter for vehicle sideslip: the compiled single-track entry points (a
readable numpy reference that the tests compare them with lives in ``tests/reference_ukf.py``).

Model (paper Sec. V, :mod:`kftune.vehicle.single_track`): x = [Vx, Vy, r], u = [δ, ax],
z = [Vx, ay, r]; additive Gaussian process and measurement noise with diagonal
Q = diag(q) and R = diag(r) (variances in SI units: q in (m/s)², (m/s)², (rad/s)² per
step; r in (m/s)², (m/s²)², (rad/s)²).

Time convention (the same in the kernel, the tests' numpy reference and FilterPy run):

* sample k carries u[k] and z[k] (taken at t_k = k·dt);
* step 0 has no prediction: the prior at t_0 is (x0, P0) and is updated with z[0];
* step k ≥ 1 predicts t_{k−1} → t_k through one RK4 step with u[k−1] held over the
  interval (zero-order hold), then updates with z[k], the measurement model using u[k]
  (ay depends on δ and, through the load transfer, on ax at t_k);
* the sigma points of the update are redrawn from the predicted (x̄, P̄) (as FilterPy's
  ``UnscentedKalmanFilter.predict`` does), not reused from the prediction.

Defaults: x0 = [z[0, Vx], 0, z[0, r]] (no lateral velocity at the start) and
P0 = diag(r_Vx, (0.05·z[0, Vx])², r_r): the measured states as uncertain as their sensors,
Vy with a standard deviation of 5 % of the speed (a sideslip of about 3°).

Outputs per step k: the posterior state x⁺_k, diag P⁺_k, the estimated measurements
z_hat_k = h(x⁺_k, u_k) (the tuning cost compares their ay and r columns), the innovation
z_k − ẑ⁻_k (ẑ⁻_k the unscented prediction of the measurement) and its normalised square
NIS_k = (z_k − ẑ⁻_k)ᵀ S_k⁻¹ (z_k − ẑ⁻_k).

Robustness: see :mod:`kftune.filters._kernel` — covariance repair by jitter, and divergence
(numerical, or a runaway to a physically impossible sideslip or speed) reported as
``diverged``/``diverged_step``/``diverged_cause`` with NaN rows from that step on, never an
exception. Bad inputs are refused before the run with a ``ValueError`` naming the argument,
the row and what was expected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from numpy.typing import ArrayLike

import kftune.filters._kernel as _kernel
import kftune.filters._soa_kernel as _soa
from kftune.filters._checks import check_covariance, check_dt, check_state
from kftune.filters._checks import check_noise as _check_noise
from kftune.filters._checks import check_table as _check_table
from kftune.filters.sigma_points import (
    UKFSettings,
    merwe_weights,
)
from kftune.models.base import GENERIC_STOP_REASONS
from kftune.models.sideslip import (
    P0_VY_SPEED_FRACTION,
    STOP_REASONS,
    check_forward_speed,
    single_track_prior,
)
from kftune.vehicle.params import VehicleParams
from kftune.vehicle.single_track import pack_params

__all__ = [
    "DIVERGED_CAUSES",
    "P0_VY_SPEED_FRACTION",
    "UKFBatchResult",
    "UKFResult",
    "default_initial_state",
    "run_ukf",
    "run_ukf_batch",
    "run_ukf_linear",
    "run_ukf_simd",
]

#: What each ``diverged_cause`` code means (``_kernel.STOP_*``), for messages.
DIVERGED_CAUSES: dict[int, str] = {**GENERIC_STOP_REASONS, **STOP_REASONS}

_U_COLS = ("delta", "ax")
_Z_COLS = ("Vx", "ay", "r")
_X_COLS = ("Vx", "Vy", "r")
_Q_UNITS = "[(m/s)², (m/s)², (rad/s)²] for [Vx, Vy, r]"
_R_UNITS = "[(m/s)², (m/s²)², (rad/s)²] for [Vx, ay, r]"


# --------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class UKFResult:
    """One UKF run over a manoeuvre of N samples.

    Attributes:
        x: (N, 3) posterior states [Vx m/s, Vy m/s, r rad/s].
        P_diag: (N, 3) diagonal of the posterior covariance [(m/s)², (m/s)², (rad/s)²].
        z_hat: (N, 3) estimated measurements h(x⁺_k, u_k) [Vx m/s, ay m/s², r rad/s].
        innovation: (N, 3) z_k − ẑ⁻_k (prior measurement prediction), same units as z.
        nis: (N,) normalised innovation squared [-] (χ² with 3 dof when consistent).
        diverged: True when the filter diverged (see ``diverged_step``).
        diverged_step: first step whose outputs are invalid (rows ≥ it are NaN); −1 if none.
            For a runaway held over a time, the step it started.
        n_repairs: number of covariance factorisations that needed jitter.
        diverged_cause: why it diverged, a key of :data:`DIVERGED_CAUSES` (0: it did not).
        log_det_s: (N,) log det S_k of the innovation covariance [log of z's units²]
            (with ``nis``, the Gaussian innovation log-likelihood); None where not computed.
    """

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    diverged: bool
    diverged_step: int
    n_repairs: int = 0
    diverged_cause: int = 0
    log_det_s: np.ndarray | None = None

    @property
    def beta(self) -> np.ndarray:
        """(N,) estimated sideslip angle atan2(Vy, Vx) [rad]."""
        return np.arctan2(self.x[:, 1], self.x[:, 0])

    @property
    def diverged_reason(self) -> str:
        """Why the filter diverged, in words ("" when it did not)."""
        return DIVERGED_CAUSES[self.diverged_cause]


@dataclass(frozen=True, eq=False)
class UKFBatchResult:
    """B UKF runs (one per noise setting) over the same manoeuvre.

    Attributes are those of :class:`UKFResult` with a leading axis B: x, P_diag, z_hat,
    innovation (B, N, 3); nis, log_det_s (B, N); diverged (B,) bool; diverged_step (B,) int
    (−1 if none); n_repairs (B,) int; diverged_cause (B,) int.
    """

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    diverged: np.ndarray
    diverged_step: np.ndarray
    n_repairs: np.ndarray
    diverged_cause: np.ndarray
    log_det_s: np.ndarray | None = None

    @property
    def beta(self) -> np.ndarray:
        """(B, N) estimated sideslip angles [rad]."""
        return np.arctan2(self.x[..., 1], self.x[..., 0])

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, b: int) -> UKFResult:
        """The b-th run as a :class:`UKFResult` (views, no copies)."""
        return UKFResult(
            x=self.x[b],
            P_diag=self.P_diag[b],
            z_hat=self.z_hat[b],
            innovation=self.innovation[b],
            nis=self.nis[b],
            diverged=bool(self.diverged[b]),
            diverged_step=int(self.diverged_step[b]),
            n_repairs=int(self.n_repairs[b]),
            diverged_cause=int(self.diverged_cause[b]),
            log_det_s=None if self.log_det_s is None else self.log_det_s[b],
        )


# --------------------------------------------------------------------------------------
# Input validation (all before the run; messages name argument, row and expectation)
# --------------------------------------------------------------------------------------


def _check_manoeuvre(
    u: ArrayLike, z: ArrayLike, dt: float, *, positive_vx: bool = True
) -> tuple[np.ndarray, np.ndarray, float]:
    u_arr = _check_table("u", u, _U_COLS, "[rad, m/s²]")
    z_arr = _check_table("z", z, _Z_COLS, "[m/s, m/s², rad/s]")
    if u_arr.shape[0] != z_arr.shape[0]:
        raise ValueError(
            f"u and z must have the same number of rows (one per sample); got u with "
            f"{u_arr.shape[0]} rows and z with {z_arr.shape[0]} rows"
        )
    if positive_vx:
        check_forward_speed(z_arr)
    return u_arr, z_arr, check_dt(dt)


def default_initial_state(z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Default prior (x0, P0) at step 0 from the first measurement (module docstring).

    Args:
        z: (N, 3) measurements; r: (3,) measurement variances.

    Returns:
        x0 (3,) = [z[0,0], 0, z[0,2]], P0 (3, 3) = diag(r[0], (0.05·z[0,0])², r[2]).
    """
    return single_track_prior(z[0], r, np.empty(0))


def _check_prior(
    x0: ArrayLike | None,
    P0: ArrayLike | None,
    z: np.ndarray,
    r: np.ndarray,
    *,
    positive_vx: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    dx0, dP0 = default_initial_state(z, r) if positive_vx else (np.zeros(3), np.eye(3))
    if x0 is None:
        x_arr = dx0
    else:
        x_arr = check_state(x0, _X_COLS)
        if positive_vx and not x_arr[0] > 0:
            raise ValueError(f"x0[0] (Vx) must be > 0 m/s, got {float(x_arr[0])}")
    P_arr = dP0 if P0 is None else check_covariance(P0, 3)
    return np.ascontiguousarray(x_arr), np.ascontiguousarray(P_arr)


def _check_run(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    x0: ArrayLike | None,
    P0: ArrayLike | None,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:
    """All checks of one single-track run: (params, u, z, dt, q, r, x0, P0) as arrays."""
    u_arr, z_arr, dt_f = _check_manoeuvre(u, z, dt)
    mp = pack_params(params)
    q_arr = _check_noise("q", q, _Q_UNITS, strictly_positive=False, batch=False)
    r_arr = _check_noise("r", r, _R_UNITS, strictly_positive=True, batch=False)
    x_arr, P_arr = _check_prior(x0, P0, z_arr, r_arr)
    return mp, u_arr, z_arr, dt_f, q_arr, r_arr, x_arr, P_arr


def _weights(settings: UKFSettings) -> tuple[float, float, float, float]:
    if not isinstance(settings, UKFSettings):
        raise ValueError(f"settings must be a UKFSettings, got {type(settings).__name__}")
    wm, wc = merwe_weights(3, settings)
    return float(wm[0]), float(wc[0]), float(wm[1]), math.sqrt(3 + settings.lam(3))


# --------------------------------------------------------------------------------------
# Compiled entry points
# --------------------------------------------------------------------------------------


class _Outputs(NamedTuple):
    """The kernel's per-step output buffers, in its argument order (and UKFResult's):
    x, P_diag, z_hat, innovation (shape + (3,) each) and nis (shape)."""

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray


def _alloc(shape: tuple[int, ...]) -> _Outputs:
    return _Outputs(
        np.empty((*shape, 3)),
        np.empty((*shape, 3)),
        np.empty((*shape, 3)),
        np.empty((*shape, 3)),
        np.empty(shape),
    )


def _run_single(
    model: int,
    mp: np.ndarray,
    u: np.ndarray,
    z: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
    settings: UKFSettings,
) -> UKFResult:
    wm0, wc0, wi, c = _weights(settings)
    out = _alloc((u.shape[0],))
    ldet = np.empty(u.shape[0])
    div, rep, why = _kernel.run_kernel(
        model, mp, u, z, dt, q, r, x0, P0, wm0, wc0, wi, c, *out, ldet
    )
    return UKFResult(
        *out,
        log_det_s=ldet,
        diverged=div >= 0,
        diverged_step=int(div),
        n_repairs=int(rep),
        diverged_cause=int(why),
    )


def run_ukf(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    *,
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
    settings: UKFSettings = UKFSettings(),  # noqa: B008 (frozen, immutable default)
) -> UKFResult:
    """Run the compiled UKF over one manoeuvre.

    Args:
        u: (N, 2) inputs [δ rad, ax m/s²].
        z: (N, 3) measurements [Vx m/s (> 0), ay m/s², r rad/s].
        dt: sample time [s], > 0.
        params: vehicle parameters (or their packed (9,) array).
        q: (3,) process-noise variances, diagonal of Q, ≥ 0 [(m/s)², (m/s)², (rad/s)²].
        r: (3,) measurement-noise variances, diagonal of R, > 0 [(m/s)², (m/s²)², (rad/s)²].
        x0: (3,) prior mean at step 0; default [z[0,0], 0, z[0,2]].
        P0: (3, 3) or (3,) prior covariance at step 0; default diag(r₀, (0.05·Vx₀)², r₂).
        settings: sigma-point parameters.

    Returns:
        :class:`UKFResult`. See the module docstring for the time convention.

    Raises:
        ValueError: bad input (message names the argument, row and what was expected).
    """
    return _run_single(
        _kernel.MODEL_SINGLE_TRACK, *_check_run(u, z, dt, params, q, r, x0, P0), settings
    )


def _check_batch(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    x0: ArrayLike | None,
    P0: ArrayLike | None,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:
    """All checks of a batch of B single-track runs: (params, u, z, dt, q (B, 3),
    r (B, 3), x_init (B, 3), P_init (B, 3, 3)) as arrays."""
    u_arr, z_arr, dt_f = _check_manoeuvre(u, z, dt)
    mp = pack_params(params)
    q_arr = _check_noise("q", q, _Q_UNITS, strictly_positive=False, batch=True)
    n_sets = q_arr.shape[0]
    r_in = np.asarray(r, dtype=np.float64)
    if r_in.ndim == 1:
        r_arr = _check_noise("r", r_in, _R_UNITS, strictly_positive=True, batch=False)
        r_arr = np.ascontiguousarray(np.broadcast_to(r_arr, (n_sets, 3)))
    else:
        r_arr = _check_noise("r", r_in, _R_UNITS, strictly_positive=True, batch=True)
        if r_arr.shape[0] != n_sets:
            raise ValueError(
                f"r must have shape (3,) or (B, 3) with B = {n_sets} (the rows of q), "
                f"got shape {r_arr.shape}"
            )
    # the default P0 uses each run's own r, so priors are per run
    x_init = np.empty((n_sets, 3))
    P_init = np.empty((n_sets, 3, 3))
    for b in range(n_sets):
        if b == 0 or P0 is None:
            xb, pb = _check_prior(x0, P0, z_arr, r_arr[b])
        x_init[b], P_init[b] = xb, pb
    return mp, u_arr, z_arr, dt_f, q_arr, r_arr, x_init, P_init


def _run_batch(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    x0: ArrayLike | None,
    P0: ArrayLike | None,
    settings: UKFSettings,
    *,
    simd: bool,
) -> UKFBatchResult:
    """:func:`run_ukf_batch` (threads over B) or :func:`run_ukf_simd` (vector lanes)."""
    mp, u_arr, z_arr, dt_f, q_arr, r_arr, x_init, P_init = _check_batch(
        u, z, dt, params, q, r, x0, P0
    )
    n_sets = q_arr.shape[0]
    wm0, wc0, wi, c = _weights(settings)
    xs, ps, zh, inn, nis = _alloc((n_sets, u_arr.shape[0]))
    ldet = np.empty((n_sets, u_arr.shape[0]))
    ldet_out: np.ndarray | None = ldet
    div = np.empty(n_sets, dtype=np.int64)
    rep = np.zeros(n_sets, dtype=np.int64)
    why = np.empty(n_sets, dtype=np.int64)
    if n_sets == 1:  # no thread start-up, no padding to 8 lanes, for a single set
        div[0], rep[0], why[0] = _kernel.run_kernel(
            _kernel.MODEL_SINGLE_TRACK, mp, u_arr, z_arr, dt_f, q_arr[0], r_arr[0],
            x_init[0], P_init[0], wm0, wc0, wi, c, xs[0], ps[0], zh[0], inn[0], nis[0],
            ldet[0],
        )  # fmt: skip
    elif simd:  # the vector kernel does not compute log det S (log_det_s is None)
        ldet_out = None
        _soa.ensure_compiled()
        _soa.run_kernel_soa(
            mp, u_arr, z_arr, dt_f, q_arr, r_arr, x_init, P_init, wm0, wc0, wi, c,
            xs, ps, zh, inn, nis, div, rep, why,
        )  # fmt: skip
    else:
        # one set per chunk, handed out dynamically: a thread whose core is busy with another
        # process then does fewer sets instead of holding up a static half of the batch
        previous = numba.set_parallel_chunksize(1)
        try:
            _kernel.run_kernel_batch(
                _kernel.MODEL_SINGLE_TRACK, mp, u_arr, z_arr, dt_f, q_arr, r_arr,
                x_init, P_init, wm0, wc0, wi, c, xs, ps, zh, inn, nis, ldet, div, rep, why,
            )  # fmt: skip
        finally:
            numba.set_parallel_chunksize(previous)
    return UKFBatchResult(xs, ps, zh, inn, nis, div >= 0, div, rep, why, ldet_out)


def run_ukf_batch(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    *,
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
    settings: UKFSettings = UKFSettings(),  # noqa: B008
) -> UKFBatchResult:
    """Run B noise settings over one manoeuvre in one call, in parallel over B.

    Args:
        u, z, dt, params, x0, P0, settings: as :func:`run_ukf` (shared by all runs; the
            default P0 uses each run's own r).
        q: (B, 3) process-noise variances.
        r: (B, 3) or (3,) measurement-noise variances (broadcast to every run).

    Returns:
        :class:`UKFBatchResult`; ``result[b]`` equals ``run_ukf(..., q[b], r[b])``.
    """
    return _run_batch(u, z, dt, params, q, r, x0, P0, settings, simd=False)


def run_ukf_simd(
    u: ArrayLike,
    z: ArrayLike,
    dt: float,
    params: VehicleParams | ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    *,
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
    settings: UKFSettings = UKFSettings(),  # noqa: B008
) -> UKFBatchResult:
    """Run B noise settings over one manoeuvre on one core, the CPU's vector units across B.

    The vectorised batch kernel (:mod:`kftune.filters._soa_kernel`: structure of arrays,
    the sets along the innermost axis). Arguments and result as :func:`run_ukf_batch`;
    ``result[b]`` equals ``run_ukf(..., q[b], r[b])`` bit for bit, a set that diverges
    stops there (NaN rows from its ``diverged_step``) without affecting the others, and
    the kernel never raises. Use it for candidate batches and GA generations; B = 1 runs
    the sequential kernel of :func:`run_ukf` (the same result, without padding to 8 lanes).
    """
    return _run_batch(u, z, dt, params, q, r, x0, P0, settings, simd=True)


def run_ukf_linear(
    u: ArrayLike,
    z: ArrayLike,
    F: ArrayLike,
    G: ArrayLike,
    H: ArrayLike,
    D: ArrayLike,
    q: ArrayLike,
    r: ArrayLike,
    x0: ArrayLike,
    P0: ArrayLike,
    *,
    settings: UKFSettings = UKFSettings(),  # noqa: B008
) -> UKFResult:
    """The compiled UKF on a linear-Gaussian 3-state model (verification against a KF).

    x_k = F·x_{k−1} + G·u_{k−1} + w,  z_k = H·x_k + D·u_k + v, same time convention as
    :func:`run_ukf`. For a linear model the UKF is exactly the Kalman filter.

    Args:
        u: (N, 2); z: (N, 3); F, H: (3, 3); G, D: (3, 2); q, r: (3,); x0: (3,);
        P0: (3, 3) or (3,).
    """
    u_arr = _check_table("u", u, ("u0", "u1"), "")
    z_arr = _check_table("z", z, ("z0", "z1", "z2"), "")
    if u_arr.shape[0] != z_arr.shape[0]:
        raise ValueError(
            f"u and z must have the same number of rows, got {u_arr.shape[0]} and {z_arr.shape[0]}"
        )
    mats = []
    for name, m, shape in (("F", F, (3, 3)), ("G", G, (3, 2)), ("H", H, (3, 3)), ("D", D, (3, 2))):
        arr = np.asarray(m, dtype=np.float64)
        if arr.shape != shape or not np.isfinite(arr).all():
            raise ValueError(f"{name} must be a finite array of shape {shape}, got {arr.shape}")
        mats.append(arr.ravel())
    mp = np.ascontiguousarray(np.concatenate(mats))
    q_arr = _check_noise("q", q, "", strictly_positive=False, batch=False)
    r_arr = _check_noise("r", r, "", strictly_positive=True, batch=False)
    x_arr, P_arr = _check_prior(x0, P0, z_arr, r_arr, positive_vx=False)
    return _run_single(
        _kernel.MODEL_LINEAR, mp, u_arr, z_arr, 1.0, q_arr, r_arr, x_arr, P_arr, settings
    )
