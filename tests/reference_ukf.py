"""The readable numpy UKF the tests compare kftune's compiled single-track kernels with
(the 3×3 kernel of :func:`kftune.filters.run_ukf`, its batch and SIMD lanes): the same
algorithm written plainly, one sigma point matrix at a time, with the model's numpy
functions (:func:`kftune.vehicle.step_rk4`, :func:`kftune.vehicle.measure`) and the same
covariance repair and stop rules. Slow; a reference, not a product, so it lives with the
tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from kftune.errors import FilterDivergedError
from kftune.filters import _kernel
from kftune.filters.sigma_points import UKFSettings, merwe_weights, unscented_transform
from kftune.filters.ukf import UKFResult, _alloc, _check_run
from kftune.models import sideslip
from kftune.models.base import STOP_NUMERICAL
from kftune.vehicle import VehicleParams, measure, step_rk4
from kftune.vehicle.single_track import MAX_SIDESLIP


def _cholesky_repaired(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Symmetrise P and factorise it, adding escalating jitter when needed.

    Returns (L, P_used, repaired); raises FilterDivergedError when no jitter up to
    ``JITTER_MAX``·max(diag) helps. Same policy as the kernel's ``chol3_repair``.
    """
    P = 0.5 * (P + P.T)
    if not np.isfinite(P).all():
        raise FilterDivergedError("covariance is not finite")
    try:
        return np.linalg.cholesky(P), P, False
    except np.linalg.LinAlgError:
        pass
    scale = float(np.max(np.diag(P)))
    jitter = _kernel.JITTER_START * scale
    while scale > 0 and 0.0 < jitter <= _kernel.JITTER_MAX * scale * 1.0000001:
        Pj = P + jitter * np.eye(P.shape[0])
        try:
            return np.linalg.cholesky(Pj), Pj, True
        except np.linalg.LinAlgError:
            jitter *= 10.0
    raise FilterDivergedError("covariance is not positive definite and jitter does not repair it")


class UnscentedKalmanFilter:
    """Readable UKF with additive noise (numpy; generic model).

    Args:
        fx: process model ``fx(X, u) -> X'`` for sigma points X of shape (m, n).
        hx: measurement model ``hx(X, u) -> Z`` of shape (m, dim_z).
        Q: (n, n) process-noise covariance; R: (dim_z, dim_z) measurement-noise covariance.
        x0: (n,) prior mean; P0: (n, n) prior covariance.
        settings: sigma-point parameters.

    Usage: ``update(z0, u0)`` first, then ``predict(u_{k−1}); update(z_k, u_k)`` per step
    (the time convention of :func:`run_ukf`). ``x``/``P`` hold the current estimate.
    """

    def __init__(
        self,
        fx: Callable[[np.ndarray, np.ndarray], np.ndarray],
        hx: Callable[[np.ndarray, np.ndarray], np.ndarray],
        Q: np.ndarray,
        R: np.ndarray,
        x0: np.ndarray,
        P0: np.ndarray,
        settings: UKFSettings = UKFSettings(),  # noqa: B008
    ) -> None:
        self.fx, self.hx = fx, hx
        self.Q, self.R = np.asarray(Q, dtype=float), np.asarray(R, dtype=float)
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        self.settings = settings
        self.wm, self.wc = merwe_weights(self.x.shape[0], settings)
        self.n_repairs = 0
        self.y = np.zeros(self.R.shape[0])  # innovation of the last update
        self.S = self.R.copy()  # innovation covariance of the last update
        self.nis = math.nan
        self.log_det_s = math.nan

    def _points(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        L, P_used, repaired = _cholesky_repaired(P)
        self.n_repairs += int(repaired)
        n = self.x.shape[0]
        c = math.sqrt(n + self.settings.lam(n))
        return np.vstack([self.x, self.x + c * L.T, self.x - c * L.T]), P_used

    def predict(self, u: np.ndarray) -> None:
        """x̄, P̄ = UT(f(χ(x, P), u)) + Q  (van der Merwe 2004, Ch. 3, time update)."""
        sigmas, _ = self._points(self.P)
        self.x, self.P = unscented_transform(self.fx(sigmas, u), self.wm, self.wc, self.Q)

    def update(self, z: np.ndarray, u: np.ndarray) -> None:
        """Measurement update with sigma points redrawn from (x̄, P̄) (ibid., meas. update)."""
        sigmas, self.P = self._points(self.P)
        zs = self.hx(sigmas, u)
        z_pred, S = unscented_transform(zs, self.wm, self.wc, self.R)
        Pxz = ((sigmas - self.x) * self.wc[:, None]).T @ (zs - z_pred)
        Ls, _, repaired = _cholesky_repaired(S)
        self.n_repairs += int(repaired)
        S_inv = np.linalg.inv(Ls @ Ls.T)  # S, jittered if it had to be
        K = Pxz @ S_inv
        self.y = z - z_pred
        self.S = S
        self.nis = float(self.y @ S_inv @ self.y)
        self.log_det_s = 2.0 * float(np.sum(np.log(np.diag(Ls))))
        self.x = self.x + K @ self.y
        self.P = self.P - K @ S @ K.T
        _, self.P, repaired = _cholesky_repaired(self.P)
        self.n_repairs += int(repaired)


def run_ukf_reference(
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
) -> UKFResult:
    """:func:`run_ukf` through :class:`UnscentedKalmanFilter` and the numpy model (slow)."""
    p, u_arr, z_arr, dt_f, q_arr, r_arr, x_arr, P_arr = _check_run(u, z, dt, params, q, r, x0, P0)
    ukf = UnscentedKalmanFilter(
        fx=lambda X, uk: step_rk4(X, uk, p, dt_f),
        hx=lambda X, uk: measure(X, uk, p),
        Q=np.diag(q_arr),
        R=np.diag(r_arr),
        x0=x_arr,
        P0=P_arr,
        settings=settings,
    )
    n = u_arr.shape[0]
    out = _alloc((n,))
    for a in out:
        a.fill(np.nan)
    ldet = np.full(n, np.nan)
    n_hold = _kernel.hold_steps(dt_f)
    held_beta = held_vx = 0  # consecutive steps beyond the held-runaway bounds

    def stopped(k: int, cause: int) -> UKFResult:
        for a in (*out, ldet):
            a[k:] = np.nan
        return UKFResult(*out, True, k, ukf.n_repairs, cause, log_det_s=ldet)

    for k in range(n):
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                if k > 0:
                    ukf.predict(u_arr[k - 1])
                ukf.update(z_arr[k], u_arr[k])
                z_hat = measure(ukf.x, u_arr[k], p)
        except (FilterDivergedError, ValueError):  # ValueError: the model met a non-finite state
            return stopped(k, STOP_NUMERICAL)
        if not (np.isfinite(ukf.x).all() and math.isfinite(ukf.nis)):
            return stopped(k, STOP_NUMERICAL)
        if not ukf.x[0] > 0:
            return stopped(k, sideslip.STOP_REVERSE)
        beta = abs(math.atan2(ukf.x[1], ukf.x[0]))
        if beta > sideslip.RUNAWAY_BETA:
            return stopped(k, sideslip.STOP_SIDESLIP)
        held_beta = held_beta + 1 if beta > MAX_SIDESLIP else 0
        off = abs(ukf.x[0] - z_arr[k, 0]) > sideslip.RUNAWAY_VX * z_arr[k, 0]
        held_vx = held_vx + 1 if off else 0
        if held_beta >= n_hold:
            return stopped(k + 1 - n_hold, sideslip.STOP_SIDESLIP_HELD)
        if held_vx >= n_hold:
            return stopped(k + 1 - n_hold, sideslip.STOP_SPEED)
        out.x[k] = ukf.x
        out.P_diag[k] = np.diag(ukf.P)
        out.z_hat[k] = z_hat
        out.innovation[k] = ukf.y
        out.nis[k] = ukf.nis
        ldet[k] = ukf.log_det_s
    return UKFResult(
        *out, diverged=False, diverged_step=-1, n_repairs=ukf.n_repairs, log_det_s=ldet
    )
