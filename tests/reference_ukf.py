"""The readable numpy UKF the tests compare kftune's compiled single-track loops with
(the model's 3×3 loop that :class:`kftune.filters.UKF` runs on
:data:`kftune.models.SINGLE_TRACK`, its threads and vector lanes): the same algorithm
written plainly, one sigma point matrix at a time, with the model's numpy functions
(:func:`kftune.vehicle.step_rk4`, :func:`kftune.vehicle.measure`) and the same covariance
repair and stop rules. It shares no code with the compiled loops but the input checks and
the model's constants (prior rule, jitter and runaway bounds). Slow; a reference, not a
product, so it lives with the tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from kftune.errors import FilterDivergedError
from kftune.filters import FilterResult
from kftune.filters._checks import (
    check_covariance,
    check_dt,
    check_noise,
    check_state,
    check_table,
)
from kftune.filters.sigma_points import UKFSettings, merwe_weights, unscented_transform
from kftune.models import SINGLE_TRACK, sideslip
from kftune.models.base import STOP_NONE, STOP_NUMERICAL
from kftune.models.kernel_io import JITTER_MAX, JITTER_START
from kftune.models.sideslip import single_track_prior
from kftune.vehicle import VehicleParams, measure, step_rk4
from kftune.vehicle.single_track import MAX_SIDESLIP, pack_params


def _cholesky_repaired(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Symmetrise P and factorise it, adding escalating jitter when needed.

    Returns (L, P_used, repaired); raises FilterDivergedError when no jitter up to
    ``JITTER_MAX``·max(diag) helps. Same policy as the 3×3 loop's ``chol3_repair``.
    """
    P = 0.5 * (P + P.T)
    if not np.isfinite(P).all():
        raise FilterDivergedError("covariance is not finite")
    try:
        return np.linalg.cholesky(P), P, False
    except np.linalg.LinAlgError:
        pass
    scale = float(np.max(np.diag(P)))
    jitter = JITTER_START * scale
    while scale > 0 and 0.0 < jitter <= JITTER_MAX * scale * 1.0000001:
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
    (the time convention of :mod:`kftune.filters.generic`). ``x``/``P`` hold the current estimate.
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


def _checked(
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
    """The run's arguments as arrays (p (9,), u (N, 2), z (N, 3), dt, q, r, x0 (3,),
    P0 (3, 3)), refused as kftune refuses them; the prior defaults to the model's rule."""
    u_arr = check_table("u", u, SINGLE_TRACK.input_names, "")
    z_arr = check_table("z", z, SINGLE_TRACK.measurement_names, "")
    if u_arr.shape[0] != z_arr.shape[0]:
        raise ValueError(f"u and z must have the same number of rows: {len(u_arr)}, {len(z_arr)}")
    dt_f = check_dt(dt)
    p = pack_params(params)
    q_arr = check_noise("q", q, "", strictly_positive=False, batch=False)
    r_arr = check_noise("r", r, "", strictly_positive=True, batch=False)
    x_def, P_def = single_track_prior(z_arr[0], r_arr, p)
    x_arr = x_def if x0 is None else check_state(x0, SINGLE_TRACK.state_names)
    P_arr = P_def if P0 is None else check_covariance(P0, 3)
    return p, u_arr, z_arr, dt_f, q_arr, r_arr, x_arr, P_arr


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
) -> FilterResult:
    """The single-track UKF (``UKF().run(SINGLE_TRACK, ...)``) through
    :class:`UnscentedKalmanFilter` and the numpy model (slow): u (N, 2) [δ, ax], z (N, 3)
    [Vx, ay, r], a vehicle or its packed (9,) parameters, q and r (3,)."""
    p, u_arr, z_arr, dt_f, q_arr, r_arr, x_arr, P_arr = _checked(u, z, dt, params, q, r, x0, P0)
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
    x, P_diag, z_hat, innovation = (np.full((n, 3), np.nan) for _ in range(4))
    nis, ldet = np.full(n, np.nan), np.full(n, np.nan)
    n_hold = max(1, int(sideslip.RUNAWAY_HOLD / dt_f + 0.5))  # steps a runaway must last
    held_beta = held_vx = 0  # consecutive steps beyond the held-runaway bounds

    def result(step: int, cause: int) -> FilterResult:
        if step >= 0:
            for a in (x, P_diag, z_hat, innovation, nis, ldet):
                a[step:] = np.nan
        return FilterResult(
            x, P_diag, z_hat, innovation, nis, step >= 0, step, ukf.n_repairs, cause,
            SINGLE_TRACK, "ukf", ldet,
        )  # fmt: skip

    for k in range(n):
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                if k > 0:
                    ukf.predict(u_arr[k - 1])
                ukf.update(z_arr[k], u_arr[k])
                zk = measure(ukf.x, u_arr[k], p)
        except (FilterDivergedError, ValueError):  # ValueError: the model met a non-finite state
            return result(k, STOP_NUMERICAL)
        if not (np.isfinite(ukf.x).all() and math.isfinite(ukf.nis)):
            return result(k, STOP_NUMERICAL)
        if not ukf.x[0] > 0:
            return result(k, sideslip.STOP_REVERSE)
        beta = abs(math.atan2(ukf.x[1], ukf.x[0]))
        if beta > sideslip.RUNAWAY_BETA:
            return result(k, sideslip.STOP_SIDESLIP)
        held_beta = held_beta + 1 if beta > MAX_SIDESLIP else 0
        off = abs(ukf.x[0] - z_arr[k, 0]) > sideslip.RUNAWAY_VX * z_arr[k, 0]
        held_vx = held_vx + 1 if off else 0
        if held_beta >= n_hold:
            return result(k + 1 - n_hold, sideslip.STOP_SIDESLIP_HELD)
        if held_vx >= n_hold:
            return result(k + 1 - n_hold, sideslip.STOP_SPEED)
        x[k] = ukf.x
        P_diag[k] = np.diag(ukf.P)
        z_hat[k] = zk
        innovation[k] = ukf.y
        nis[k] = ukf.nis
        ldet[k] = ukf.log_det_s
    return result(-1, STOP_NONE)
