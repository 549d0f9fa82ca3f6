"""Target tracking: the constant-turn-rate-and-velocity model with position measurements.

Nothing here knows about cars or the filters' vehicle origins: a target moves in the plane
with speed v and heading ψ, turning at the constant rate ω, and a sensor measures its
position (radar or GNSS after conversion to a local Cartesian frame). This is the CTRV model
of Schubert, Richter & Wanielik, "Comparison and evaluation of advanced motion models for
vehicle tracking", FUSION 2008, and the polar coordinated-turn model of Bar-Shalom, Li &
Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, Sec. 11.7.

State x = [px, py, v, ψ, ω] [m, m, m/s, rad, rad/s], no input, measurement z = [px, py] [m].
The exact discretisation over dt = T of the noise-free motion is

    px' = px + (v/ω)·(sin(ψ + ωT) − sin ψ),   py' = py + (v/ω)·(cos ψ − cos(ψ + ωT)),
    v' = v,  ψ' = ψ + ωT,  ω' = ω,

written here with the product-to-sum identities as

    px' = px + v·T·sinc(ωT/2)·cos(ψ + ωT/2),  py' = py + v·T·sinc(ωT/2)·sin(ψ + ωT/2),

sinc(s) = sin(s)/s, which has no 0/0 at ω = 0 (straight motion) and no cancellation near it.
Process noise is additive on all five states (random-walk v, ψ and ω).

The analytic Jacobians F = ∂f/∂x and H = ∂h/∂x are given (and checked against finite
differences in the tests). The model has no parameters. Its C twin, hook for hook, is the
package file ``kftune/models/c/ctrv.c``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from kftune.models.base import StateSpaceModel
from kftune.models.c_contract import builtin_c_code

__all__ = ["CTRV", "CTRV_PRIOR_STD"]

#: Prior standard deviations of [v, ψ, ω] at step 0 (position from the first measurement):
#: speed unknown up to a fast road vehicle, heading unknown, turn rate up to a tight turn.
CTRV_PRIOR_STD = (20.0, math.pi, 0.5)

#: Below this |s| the sinc derivative uses its Taylor series (no cancellation).
_SERIES_BELOW = 0.1


@njit(cache=True, error_model="numpy")
def _sinc(s: float) -> float:
    """sin(s)/s, 1 at s = 0."""
    return 1.0 if s == 0.0 else math.sin(s) / s


@njit(cache=True, error_model="numpy")
def _dsinc(s: float) -> float:
    """d sinc/ds = (s·cos s − sin s)/s², by its Taylor series for |s| < 0.1."""
    if abs(s) < _SERIES_BELOW:
        s2 = s * s
        return s * (-1.0 / 3.0 + s2 * (1.0 / 30.0 + s2 * (-1.0 / 840.0 + s2 / 45360.0)))
    return (s * math.cos(s) - math.sin(s)) / (s * s)


@njit(cache=True, error_model="numpy")
def ctrv_process(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """Exact CTRV step of length dt (module docstring)."""
    v = x[2]
    psi = x[3]
    om = x[4]
    s = 0.5 * om * dt
    a = psi + s
    d = v * dt * _sinc(s)
    out[0] = x[0] + d * math.cos(a)
    out[1] = x[1] + d * math.sin(a)
    out[2] = v
    out[3] = psi + om * dt
    out[4] = om


@njit(cache=True, error_model="numpy")
def ctrv_process_jacobian(
    x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray
) -> None:
    """(5, 5) ∂f/∂x of :func:`ctrv_process`."""
    v = x[2]
    om = x[4]
    s = 0.5 * om * dt
    a = x[3] + s
    c = math.cos(a)
    sn = math.sin(a)
    sc = _sinc(s)
    ds = _dsinc(s)
    out[:, :] = 0.0
    for j in range(5):
        out[j, j] = 1.0
    out[0, 2] = dt * sc * c
    out[0, 3] = -v * dt * sc * sn
    out[0, 4] = 0.5 * v * dt * dt * (ds * c - sc * sn)
    out[1, 2] = dt * sc * sn
    out[1, 3] = v * dt * sc * c
    out[1, 4] = 0.5 * v * dt * dt * (ds * sn + sc * c)
    out[3, 4] = dt


@njit(cache=True, error_model="numpy")
def position(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """z = [px, py]."""
    out[0] = x[0]
    out[1] = x[1]


@njit(cache=True, error_model="numpy")
def position_jacobian(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """(2, 5) ∂h/∂x = [I₂ 0]."""
    out[:, :] = 0.0
    out[0, 0] = 1.0
    out[1, 1] = 1.0


def ctrv_prior(z0: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x0 = [z0_px, z0_py, 0, 0, 0], P0 = diag(r_px, r_py, 20², π², 0.5²) (CTRV_PRIOR_STD)."""
    x0 = np.array([float(z0[0]), float(z0[1]), 0.0, 0.0, 0.0])
    P0 = np.diag([float(r[0]), float(r[1]), *np.square(CTRV_PRIOR_STD)])
    return x0, P0


#: Constant turn rate and velocity, position measurements (5 states, 2 measurements).
CTRV = StateSpaceModel(
    name="ctrv",
    state_names=("px", "py", "v", "psi", "omega"),
    state_units=("m", "m", "m/s", "rad", "rad/s"),
    input_names=(),
    input_units=(),
    measurement_names=("px", "py"),
    measurement_units=("m", "m"),
    f=ctrv_process,
    h=position,
    initial_state=ctrv_prior,
    F=ctrv_process_jacobian,
    H=position_jacobian,
    description="target tracking: constant turn rate and velocity, position measurements",
    c_code=builtin_c_code("ctrv"),
)
