"""Single-track (bicycle) model with Dugoff axle forces: process and measurement models.

State x = [Vx, Vy, r]: longitudinal and lateral velocity of the CG in the body frame [m/s]
and yaw rate [rad/s]. Input u = [δ, ax]: road-wheel steering angle [rad] and measured
(accelerometer) longitudinal acceleration [m/s²]. Measurement z = [Vx, ay, r] with ay the
accelerometer's lateral acceleration [m/s²]. Paper Sec. V; DESIGN.md §3.

Equations (body frame, planar, no aerodynamic or rolling-resistance terms — they are inside
the measured ax):

* slip angles (Rajamani, *Vehicle Dynamics and Control*, 2nd ed., Ch. 2, without
  the small-angle approximation)
      α_f = δ − atan2(Vy + a·r, Vx),    α_r = −atan2(Vy − b·r, Vx)
* axle loads with longitudinal load transfer (Gillespie, *Fundamentals of Vehicle
  Dynamics*, Ch. 2, with the accelerometer's ax)
      Fz_f = m·(g·b − ax·h)/L,          Fz_r = m·(g·a + ax·h)/L
* axle lateral forces by Dugoff with κ = 0 (:mod:`kftune.vehicle.tyre`)
* Newton–Euler in the rotating body frame (Rajamani Ch. 2); an accelerometer
  reads a = V̇ + ω × V, so with the measured ax
      V̇x = ax + r·Vy
      V̇y = (F_yf·cos δ + F_yr)/m − r·Vx
      ṙ  = (a·F_yf·cos δ − b·F_yr)/I_z
      ay = (F_yf·cos δ + F_yr)/m
  The front longitudinal force's lateral component F_xf·sin δ is neglected (the drive and
  brake split is unknown; it is second order in δ for the yaw moment).

Discretisation: one classical RK4 step per sample with the input held over the step
(zero-order hold). The lateral dynamics are stiff at low speed (eigenvalues of the order
of −(C_af + C_ar)/(m·Vx) and −(a²·C_af + b²·C_ar)/(I_z·Vx)), and RK4's stability limit
(|λ·dt| < 2.8 on the real axis) is crossed at about Vx = 1 m/s for the BMW preset at
100 Hz (checked by simulation). Below that the Dugoff saturation keeps the states bounded,
but the discrete model chatters; the sideslip filter is meant for driving speeds.

The slip-angle formula uses atan2, defined for every (Vx, Vy) — sigma points with Vx ≤ 0
stay finite — but the model is physical only for forward driving, Vx > 0.

Two implementations: readable vectorised numpy functions (:func:`derivatives`,
:func:`step_rk4`, :func:`measure`, …) that follow the equations literally, and compiled
scalar ones (``*_scalar``) for the filter kernels. The compiled ones never form α: Dugoff
needs only tan α, and tan is π-periodic, so for every (Vx, Vy) with t_δ = tan δ

    tan α_f = tan(δ − atan2(y_f, Vx)) = (Vx·t_δ − y_f) / (Vx + y_f·t_δ),   y_f = Vy + a·r
    tan α_r = −(Vy − b·r) / Vx

exactly — the same function, without atan2 or tan in the inner loop.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from kftune.vehicle.params import PARAM_INDEX, G, VehicleParams
from kftune.vehicle.tyre import _dugoff_unchecked, dugoff_fy_scalar

__all__ = [
    "MAX_SIDESLIP",
    "axle_loads",
    "derivatives",
    "lateral_forces",
    "measure",
    "pack_params",
    "simulate",
    "slip_angles",
    "step_rk4",
]

#: Largest sideslip magnitude the single-track model is meant for [rad] (0.8 rad ≈ 46°).
#: Beyond it a car is spinning rather than cornering (production cars stay below ≈ 10° in
#: normal driving, drifting below ≈ 45°); the data loader refuses a reference sideslip
#: beyond it, and the filter calls an estimate held beyond it a runaway.
MAX_SIDESLIP = 0.8

_POSITIVE = ("m", "Iz", "a", "b", "C_af", "C_ar", "C_x")
_POS_IDX = np.array([PARAM_INDEX[n] for n in _POSITIVE])


def pack_params(p: VehicleParams | ArrayLike) -> np.ndarray:
    """The (9,) float64 parameter array of the compiled kernels, checked.

    Args:
        p: a :class:`VehicleParams`, or its packed array ``[m, Iz, a, b, h, C_af, C_ar,
            C_x, mu]`` (SI units; see :meth:`VehicleParams.to_array`).

    Raises:
        ValueError: wrong shape, non-finite or out-of-range entries (naming the entry).
    """
    if isinstance(p, VehicleParams):
        return p.to_array()
    arr = np.array(p, dtype=np.float64)
    if (
        arr.shape == (len(PARAM_INDEX),)
        and np.all(arr[_POS_IDX] > 0)
        and np.all(np.isfinite(arr))
        and arr[4] >= 0
        and 0.0 < arr[8] <= 2.0
    ):
        return arr
    if arr.shape != (len(PARAM_INDEX),):
        raise ValueError(
            f"params must be a VehicleParams or a packed array of shape ({len(PARAM_INDEX)},) "
            f"[{', '.join(PARAM_INDEX)}], got shape {arr.shape}"
        )
    for name, i in PARAM_INDEX.items():
        v = arr[i]
        if not math.isfinite(v):
            raise ValueError(f"params[{i}] ({name}) must be finite, got {float(v)}")
        if name in _POSITIVE and v <= 0:
            raise ValueError(f"params[{i}] ({name}) must be > 0 (SI units), got {float(v)}")
    if arr[PARAM_INDEX["h"]] < 0:
        raise ValueError(f"params[4] (h) must be >= 0 m, got {float(arr[4])}")
    if not 0.0 < arr[PARAM_INDEX["mu"]] <= 2.0:
        raise ValueError(f"params[8] (mu) must be in (0, 2], got {float(arr[8])}")
    return arr


def _as_xu(x: ArrayLike, u: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if x.shape[-1:] != (3,):
        raise ValueError(f"x must have last dimension 3 ([Vx, Vy, r]), got shape {x.shape}")
    if u.shape[-1:] != (2,):
        raise ValueError(f"u must have last dimension 2 ([delta, ax]), got shape {u.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("x (state [Vx, Vy, r]) contains NaN or inf")
    if not np.all(np.isfinite(u)):
        raise ValueError("u (input [delta, ax]) contains NaN or inf")
    return x, u


def axle_loads(ax: ArrayLike, p: VehicleParams | ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Front and rear axle loads with longitudinal load transfer [N].

    Args:
        ax: longitudinal acceleration [m/s²], any shape.
        p: vehicle parameters.

    Returns:
        (Fz_f, Fz_r), each of ax's shape: m·(g·b − ax·h)/L and m·(g·a + ax·h)/L.
    """
    return _axle_loads(np.asarray(ax, dtype=np.float64), pack_params(p))


def slip_angles(
    x: ArrayLike, u: ArrayLike, p: VehicleParams | ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Front and rear axle slip angles (α_f, α_r) [rad].

    Args:
        x: (..., 3) state; u: (..., 2) input (broadcasting); p: parameters.
    """
    arr = pack_params(p)
    return _slip_angles(*_as_xu(x, u), arr)


def lateral_forces(
    x: ArrayLike, u: ArrayLike, p: VehicleParams | ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Axle lateral forces (F_yf, F_yr) [N] from Dugoff with κ = 0, in each wheel's frame."""
    arr = pack_params(p)
    return _lateral_forces(*_as_xu(x, u), arr)


def derivatives(x: ArrayLike, u: ArrayLike, p: VehicleParams | ArrayLike) -> np.ndarray:
    """Continuous-time process model ẋ = f(x, u).

    Args:
        x: (..., 3) state [Vx, Vy, r] [m/s, m/s, rad/s].
        u: (..., 2) input [δ, ax] [rad, m/s²]; broadcasts against x's leading axes.
        p: vehicle parameters.

    Returns:
        (..., 3) [V̇x, V̇y, ṙ] [m/s², m/s², rad/s²].
    """
    arr = pack_params(p)
    return _derivatives(*_as_xu(x, u), arr)


def step_rk4(x: ArrayLike, u: ArrayLike, p: VehicleParams | ArrayLike, dt: float) -> np.ndarray:
    """One classical Runge–Kutta step of length dt with u held constant.

    Args:
        x: (..., 3) state at t_k.
        u: (..., 2) input over [t_k, t_k + dt).
        p: vehicle parameters.
        dt: step [s], > 0.

    Returns:
        (..., 3) state at t_k + dt.
    """
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite sample time > 0 s, got {dt!r}")
    arr = pack_params(p)
    x, u = _as_xu(x, u)
    k1 = _derivatives(x, u, arr)
    k2 = _derivatives(x + 0.5 * dt * k1, u, arr)
    k3 = _derivatives(x + 0.5 * dt * k2, u, arr)
    k4 = _derivatives(x + dt * k3, u, arr)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def measure(x: ArrayLike, u: ArrayLike, p: VehicleParams | ArrayLike) -> np.ndarray:
    """Measurement model z = h(x, u) = [Vx, ay, r].

    Args:
        x: (..., 3) state; u: (..., 2) input at the same sample; p: parameters.

    Returns:
        (..., 3) [Vx, ay, r] [m/s, m/s², rad/s], ay = (F_yf·cos δ + F_yr)/m.
    """
    arr = pack_params(p)
    x, u = _as_xu(x, u)
    Fyf, Fyr = _lateral_forces(x, u, arr)
    ay = (Fyf * np.cos(u[..., 0]) + Fyr) / arr[0]
    return np.stack(np.broadcast_arrays(x[..., 0], ay, x[..., 2]), axis=-1)


# Unchecked numpy implementations (arguments already validated by the public functions).


def _axle_loads(ax: np.ndarray, arr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m, a, b, h = arr[0], arr[2], arr[3], arr[4]
    L = a + b
    return m * (G * b - ax * h) / L, m * (G * a + ax * h) / L


def _slip_angles(x: np.ndarray, u: np.ndarray, arr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = arr[2], arr[3]
    vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
    return u[..., 0] - np.arctan2(vy + a * r, vx), -np.arctan2(vy - b * r, vx)


def _lateral_forces(x: np.ndarray, u: np.ndarray, arr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    alpha_f, alpha_r = _slip_angles(x, u, arr)
    Fz_f, Fz_r = _axle_loads(u[..., 1], arr)
    return (
        _dugoff_unchecked(alpha_f, Fz_f, arr[5], arr[8]),
        _dugoff_unchecked(alpha_r, Fz_r, arr[6], arr[8]),
    )


def _derivatives(x: np.ndarray, u: np.ndarray, arr: np.ndarray) -> np.ndarray:
    m, Iz, a, b = arr[0], arr[1], arr[2], arr[3]
    Fyf, Fyr = _lateral_forces(x, u, arr)
    cos_d = np.cos(u[..., 0])
    vx, vy, r = x[..., 0], x[..., 1], x[..., 2]
    dvx = u[..., 1] + r * vy  # V̇x = ax + r·Vy
    dvy = (Fyf * cos_d + Fyr) / m - r * vx  # V̇y = ΣFy/m − r·Vx
    dr = (a * Fyf * cos_d - b * Fyr) / Iz  # ṙ = ΣMz/Iz
    return np.stack(np.broadcast_arrays(dvx, dvy, dr), axis=-1)


def simulate(
    x0: ArrayLike,
    u: ArrayLike,
    p: VehicleParams | ArrayLike,
    dt: float,
    *,
    substeps: int = 1,
) -> np.ndarray:
    """Simulate the model over an input sequence (a plant for tests and the demo).

    Args:
        x0: (3,) initial state.
        u: (N, 2) inputs; u[k] is held over [t_k, t_{k+1}).
        p: vehicle parameters.
        dt: sample time [s].
        substeps: RK4 steps per sample (a finer plant than the filter's discretisation).

    Returns:
        (N, 3) states with x[0] = x0 and x[k] the state at t_k (compiled; the same RK4
        as :func:`step_rk4` applied ``substeps`` times per sample).
    """
    arr = pack_params(p)
    u = np.ascontiguousarray(u, dtype=np.float64)
    x0 = np.asarray(x0, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 2 or u.shape[0] < 1:
        raise ValueError(f"u must have shape (N, 2) with N >= 1, got {u.shape}")
    if x0.shape != (3,):
        raise ValueError(f"x0 must have shape (3,) [Vx, Vy, r], got {x0.shape}")
    _as_xu(x0, u)  # finiteness
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite sample time > 0 s, got {dt!r}")
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    x = np.empty((u.shape[0], 3))
    _simulate_kernel(x0, u, arr, float(dt), int(substeps), x)
    return x


# --------------------------------------------------------------------------------------
# Compiled scalar internals (the filter kernels inline these). p is the packed (9,) array.
# --------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def step_context_scalar(
    delta: float, ax: float, p: np.ndarray
) -> tuple[float, float, float, float]:
    """Quantities that depend on the input only: (tan δ, cos δ, Fz_f, Fz_r)."""
    m, a, b, h = p[0], p[2], p[3], p[4]
    L = a + b
    return math.tan(delta), math.cos(delta), m * (G * b - ax * h) / L, m * (G * a + ax * h) / L


@njit(cache=True, error_model="numpy")
def _tan_ratio(num: float, den: float, fallback: float) -> float:
    # tan α = num/den; den = 0 means α = ±π/2 (tan = ±inf, Dugoff saturates); 0/0 happens
    # only at Vx = y = 0, where atan2(0, 0) = 0 and tan α = fallback.
    if den != 0.0:
        return num / den
    if num != 0.0:
        return math.copysign(math.inf, num)
    return fallback


@njit(cache=True, error_model="numpy")
def lateral_forces_scalar(
    vx: float, vy: float, r: float, tan_d: float, Fz_f: float, Fz_r: float, p: np.ndarray
) -> tuple[float, float]:
    """(F_yf, F_yr) [N]; tan α via the exact ratio form (module docstring)."""
    a, b = p[2], p[3]
    yf = vy + a * r
    tan_af = _tan_ratio(vx * tan_d - yf, vx + yf * tan_d, tan_d)
    tan_ar = _tan_ratio(b * r - vy, vx, 0.0)
    return dugoff_fy_scalar(tan_af, Fz_f, p[5], p[8]), dugoff_fy_scalar(tan_ar, Fz_r, p[6], p[8])


@njit(cache=True, error_model="numpy")
def derivatives_scalar(
    vx: float,
    vy: float,
    r: float,
    tan_d: float,
    cos_d: float,
    ax: float,
    Fz_f: float,
    Fz_r: float,
    p: np.ndarray,
) -> tuple[float, float, float]:
    """ẋ = f(x, u) for one state (see :func:`derivatives`)."""
    Fyf, Fyr = lateral_forces_scalar(vx, vy, r, tan_d, Fz_f, Fz_r, p)
    Fyf_c = Fyf * cos_d
    return ax + r * vy, (Fyf_c + Fyr) / p[0] - r * vx, (p[2] * Fyf_c - p[3] * Fyr) / p[1]


@njit(cache=True, error_model="numpy")
def rk4_scalar(
    vx: float,
    vy: float,
    r: float,
    tan_d: float,
    cos_d: float,
    ax: float,
    Fz_f: float,
    Fz_r: float,
    p: np.ndarray,
    dt: float,
) -> tuple[float, float, float]:
    """One RK4 step for one state (see :func:`step_rk4`)."""
    h2 = 0.5 * dt
    a1, b1, c1 = derivatives_scalar(vx, vy, r, tan_d, cos_d, ax, Fz_f, Fz_r, p)
    a2, b2, c2 = derivatives_scalar(
        vx + h2 * a1, vy + h2 * b1, r + h2 * c1, tan_d, cos_d, ax, Fz_f, Fz_r, p
    )
    a3, b3, c3 = derivatives_scalar(
        vx + h2 * a2, vy + h2 * b2, r + h2 * c2, tan_d, cos_d, ax, Fz_f, Fz_r, p
    )
    a4, b4, c4 = derivatives_scalar(
        vx + dt * a3, vy + dt * b3, r + dt * c3, tan_d, cos_d, ax, Fz_f, Fz_r, p
    )
    s = dt / 6.0
    return (
        vx + s * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
        vy + s * (b1 + 2.0 * b2 + 2.0 * b3 + b4),
        r + s * (c1 + 2.0 * c2 + 2.0 * c3 + c4),
    )


@njit(cache=True, error_model="numpy")
def measure_scalar(
    vx: float,
    vy: float,
    r: float,
    tan_d: float,
    cos_d: float,
    Fz_f: float,
    Fz_r: float,
    p: np.ndarray,
) -> tuple[float, float, float]:
    """z = h(x, u) = (Vx, ay, r) for one state (see :func:`measure`)."""
    Fyf, Fyr = lateral_forces_scalar(vx, vy, r, tan_d, Fz_f, Fz_r, p)
    return vx, (Fyf * cos_d + Fyr) / p[0], r


@njit(cache=True, error_model="numpy")
def _simulate_kernel(
    x0: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, substeps: int, out: np.ndarray
) -> None:
    """Compiled loop of :func:`simulate` (the same RK4 as :func:`step_rk4`)."""
    vx, vy, r = x0[0], x0[1], x0[2]
    out[0, 0], out[0, 1], out[0, 2] = vx, vy, r
    h = dt / substeps
    for k in range(1, u.shape[0]):
        tan_d, cos_d, fzf, fzr = step_context_scalar(u[k - 1, 0], u[k - 1, 1], p)
        for _ in range(substeps):
            vx, vy, r = rk4_scalar(vx, vy, r, tan_d, cos_d, u[k - 1, 1], fzf, fzr, p, h)
        out[k, 0], out[k, 1], out[k, 2] = vx, vy, r
