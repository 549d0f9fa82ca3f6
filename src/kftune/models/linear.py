"""Linear-Gaussian state-space models (the filters' exact reference case).

    x_k = F·x_{k−1} + G·u_{k−1} + w,   z_k = H·x_k + D·u_k + v

(Simon, *Optimal State Estimation*, 2006, Ch. 5.1). The matrices are the parameter vector,
p = [F (n·n), G (n·n_u), H (m·n), D (m·n_u)] row-major, so that one pair of compiled
functions serves every size (dimensions are read from the arrays f and h are given) and a
model's matrices can be changed per run like any parameters. dt is not used: F and G are
already the discrete-time matrices. For such a model the UKF and the EKF are both exactly
the Kalman filter, which the tests use.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from kftune.models.base import StateSpaceModel

__all__ = ["linear_model", "linear_params"]


@njit(cache=True, error_model="numpy")
def linear_process(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """out = F·x + G·u with F, G read from p."""
    n = x.shape[0]
    nu = u.shape[0]
    g0 = n * n
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += p[i * n + j] * x[j]
        for j in range(nu):
            s += p[g0 + i * nu + j] * u[j]
        out[i] = s


@njit(cache=True, error_model="numpy")
def linear_measurement(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """out = H·x + D·u with H, D read from p."""
    n = x.shape[0]
    nu = u.shape[0]
    m = out.shape[0]
    h0 = n * n + n * nu
    d0 = h0 + m * n
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += p[h0 + i * n + j] * x[j]
        for j in range(nu):
            s += p[d0 + i * nu + j] * u[j]
        out[i] = s


@njit(cache=True, error_model="numpy")
def linear_process_jacobian(
    x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray
) -> None:
    """out = F."""
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = p[i * n + j]


@njit(cache=True, error_model="numpy")
def linear_measurement_jacobian(
    x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray
) -> None:
    """out = H."""
    n = x.shape[0]
    h0 = n * n + n * u.shape[0]
    for i in range(out.shape[0]):
        for j in range(n):
            out[i, j] = p[h0 + i * n + j]


def _matrices(
    F: ArrayLike, G: ArrayLike | None, H: ArrayLike, D: ArrayLike | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    F_arr = np.atleast_2d(np.asarray(F, dtype=np.float64))
    H_arr = np.atleast_2d(np.asarray(H, dtype=np.float64))
    n, m = F_arr.shape[0], H_arr.shape[0]
    G_arr = np.zeros((n, 0)) if G is None else np.asarray(G, dtype=np.float64).reshape(n, -1)
    nu = G_arr.shape[1]
    D_arr = np.zeros((m, nu)) if D is None else np.asarray(D, dtype=np.float64)
    for name, arr, shape in (
        ("F", F_arr, (n, n)),
        ("G", G_arr, (n, nu)),
        ("H", H_arr, (m, n)),
        ("D", D_arr, (m, nu)),
    ):
        if arr.shape != shape or not np.isfinite(arr).all():
            raise ValueError(f"{name} must be a finite array of shape {shape}, got {arr.shape}")
    return F_arr, G_arr, H_arr, D_arr


def linear_params(
    F: ArrayLike, H: ArrayLike, G: ArrayLike | None = None, D: ArrayLike | None = None
) -> np.ndarray:
    """The parameter vector [F, G, H, D] (row-major) of a linear model.

    Args:
        F: (n, n); H: (m, n); G: (n, n_u) or None (no input); D: (m, n_u) or None (zeros).
    """
    return np.concatenate([a.ravel() for a in _matrices(F, G, H, D)])


def linear_model(
    F: ArrayLike,
    H: ArrayLike,
    G: ArrayLike | None = None,
    D: ArrayLike | None = None,
    *,
    name: str = "linear",
) -> StateSpaceModel:
    """A linear model whose default parameters are the given matrices.

    States, inputs and measurements are named x0…, u0…, z0… (no units). Other matrices of
    the same sizes can be given per run as ``params=linear_params(F2, H2, G2, D2)``.

    Args:
        F: (n, n) transition; H: (m, n) measurement matrix; G: (n, n_u) input matrix or None;
        D: (m, n_u) feedthrough or None; name: the model's name.
    """
    F_arr, G_arr, H_arr, D_arr = _matrices(F, G, H, D)
    n, nu, m = F_arr.shape[0], G_arr.shape[1], H_arr.shape[0]
    pnames = tuple(
        f"{mat}[{i},{j}]"
        for mat, (rows, cols) in (("F", (n, n)), ("G", (n, nu)), ("H", (m, n)), ("D", (m, nu)))
        for i in range(rows)
        for j in range(cols)
    )
    return StateSpaceModel(
        name=name,
        state_names=tuple(f"x{i}" for i in range(n)),
        state_units=("",) * n,
        input_names=tuple(f"u{i}" for i in range(nu)),
        input_units=("",) * nu,
        measurement_names=tuple(f"z{i}" for i in range(m)),
        measurement_units=("",) * m,
        f=linear_process,
        h=linear_measurement,
        param_names=pnames,
        param_defaults=tuple(linear_params(F_arr, H_arr, G_arr, D_arr)),
        F=linear_process_jacobian,
        H=linear_measurement_jacobian,
        description=f"linear-Gaussian model, {n} states, {nu} inputs, {m} measurements",
    )
