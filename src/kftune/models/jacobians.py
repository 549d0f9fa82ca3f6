"""Jacobians of a model's f and h: the model's own, or central finite differences.

The EKF linearises f at the posterior and h at the prediction (Simon, *Optimal State
Estimation*, 2006, Ch. 13.2, eqs. 13.46–13.47):

    F_{k−1} = ∂f/∂x (x⁺_{k−1}, u_{k−1}),     H_k = ∂h/∂x (x̄_k, u_k).

A model without analytic Jacobians gets them by central differences, column by column:

    ∂g/∂x_j ≈ (g(x + h_j·e_j) − g(x − h_j·e_j)) / (2·h_j),   h_j = ε^{1/3}·max(|x_j|, 1)

with ε the float64 machine epsilon (h_j ≈ 6·10⁻⁶ for |x_j| ≤ 1). The cube root balances the
truncation error O(h²·g‴) against the rounding error O(ε·|g|/h) (Nocedal & Wright,
*Numerical Optimization*, 2nd ed., 2006, Sec. 8.1), for about 10 correct digits on a smooth
model whose states are of order one in their SI units or larger. The step actually taken is
the representable (x_j + h_j) − (x_j − h_j), so the division uses the exact spacing.
A model with states much smaller than one in their units (10⁻⁶ rad, say) should give its
own Jacobians or be scaled.

The compiled functions write into preallocated arrays (the EKF's work arrays); the Python
wrappers :func:`process_jacobian` and :func:`measurement_jacobian` allocate and are meant
for tests and for giving another filter library the same Jacobians.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core.dispatcher import Dispatcher
from numpy.typing import ArrayLike

from kftune.models.base import StateSpaceModel

__all__ = [
    "FD_REL_STEP",
    "fd_measurement_jacobian",
    "fd_process_jacobian",
    "measurement_jacobian",
    "process_jacobian",
]

#: Relative central-difference step ε^{1/3} (module docstring).
FD_REL_STEP = float(np.finfo(np.float64).eps ** (1.0 / 3.0))


@njit(error_model="numpy", inline="always")
def fd_process_jacobian(
    f: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    dt: float,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = ∂f/∂x at (x, u) by central differences (module docstring).

    Args:
        f: the model's compiled process function.
        x: (n,) state; u: (n_w,) prepared input; p: parameters; dt: step [s].
        out: (n, n) result; xw, gp, gm: (n,) work arrays.
    """
    for j in range(x.shape[0]):
        xw[j] = x[j]
    for j in range(x.shape[0]):
        step = FD_REL_STEP * max(abs(x[j]), 1.0)
        hi = x[j] + step
        lo = x[j] - step
        xw[j] = hi
        f(xw, u, p, dt, gp)
        xw[j] = lo
        f(xw, u, p, dt, gm)
        xw[j] = x[j]
        inv = 1.0 / (hi - lo)
        for i in range(out.shape[0]):
            out[i, j] = (gp[i] - gm[i]) * inv


@njit(error_model="numpy", inline="always")
def fd_measurement_jacobian(
    h: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = ∂h/∂x at (x, u) by central differences; out: (m, n), xw: (n,), gp, gm: (m,)."""
    for j in range(x.shape[0]):
        xw[j] = x[j]
    for j in range(x.shape[0]):
        step = FD_REL_STEP * max(abs(x[j]), 1.0)
        hi = x[j] + step
        lo = x[j] - step
        xw[j] = hi
        h(xw, u, p, gp)
        xw[j] = lo
        h(xw, u, p, gm)
        xw[j] = x[j]
        inv = 1.0 / (hi - lo)
        for i in range(out.shape[0]):
            out[i, j] = (gp[i] - gm[i]) * inv


def _point(
    model: StateSpaceModel, x: ArrayLike, u: ArrayLike | None, params: object
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = model.params_vector(params)
    x_arr = np.ascontiguousarray(x, dtype=np.float64)
    if x_arr.shape != (model.n_states,):
        raise ValueError(f"x must have shape ({model.n_states},), got {x_arr.shape}")
    u_arr = np.zeros(model.n_inputs) if u is None else np.asarray(u, dtype=np.float64)
    if u_arr.shape != (model.n_inputs,):
        raise ValueError(f"u must have shape ({model.n_inputs},), got {u_arr.shape}")
    return x_arr, model.prepared_inputs(u_arr[None, :], p)[0], p


def process_jacobian(
    model: StateSpaceModel,
    x: ArrayLike,
    u: ArrayLike | None,
    dt: float,
    params: object = None,
    *,
    numerical: bool = False,
) -> np.ndarray:
    """(n, n) ∂f/∂x at (x, u): the model's F, or finite differences (always if ``numerical``).

    Args:
        model: the model; x: (n,) state; u: (n_u,) raw input (None for a model without
        inputs); dt: step [s]; params: the model's parameters (None: defaults).
    """
    x_arr, w, p = _point(model, x, u, params)
    n = model.n_states
    out = np.empty((n, n))
    if model.F is not None and not numerical:
        model.F(x_arr, w, p, float(dt), out)
    else:
        fd_process_jacobian(model.f, x_arr, w, p, float(dt), out, *np.empty((3, n)))
    return out


def measurement_jacobian(
    model: StateSpaceModel,
    x: ArrayLike,
    u: ArrayLike | None,
    params: object = None,
    *,
    numerical: bool = False,
) -> np.ndarray:
    """(m, n) ∂h/∂x at (x, u): the model's H, or finite differences (always if ``numerical``)."""
    x_arr, w, p = _point(model, x, u, params)
    out = np.empty((model.n_measurements, model.n_states))
    if model.H is not None and not numerical:
        model.H(x_arr, w, p, out)
    else:
        m = model.n_measurements
        fd_measurement_jacobian(
            model.h, x_arr, w, p, out, np.empty(model.n_states), np.empty(m), np.empty(m)
        )
    return out
