"""Analytic Jacobians of the single-track/Dugoff model (the EKF's linearisation).

Continuous model g(x) = ẋ for x = [Vx, Vy, r] (:mod:`kftune.vehicle.single_track`), with
the prepared input quantities t = tan δ, cos δ, ax, Fz_f, Fz_r held over the step:

    tan α_f = N/D,  N = Vx·t − y_f,  D = Vx + y_f·t,  y_f = Vy + a·r     (exact ratio form)
    tan α_r = (b·r − Vy)/Vx
    g = [ax + r·Vy,  (F_yf·cos δ + F_yr)/m − r·Vx,  (a·F_yf·cos δ − b·F_yr)/I_z]

Its Jacobian G = ∂g/∂x follows by the chain rule through the Dugoff slope
dF_y/d(tan α) (:func:`dugoff_slope`) and

    ∂(N/D)/∂x_j = (∂N/∂x_j·D − N·∂D/∂x_j)/D²,   ∂(N, D)/∂(Vx, Vy, r) = (t, 1), (−1, t), (−a, a·t).

One RK4 step x' = x + dt/6·(k1 + 2k2 + 2k3 + k4) has the Jacobian (differentiating each
stage k_i = g(x_i) with x_2 = x + dt/2·k1, x_3 = x + dt/2·k2, x_4 = x + dt·k3):

    J1 = G(x1),  J2 = G(x2)·(I + dt/2·J1),  J3 = G(x3)·(I + dt/2·J2),  J4 = G(x4)·(I + dt·J3)
    F = I + dt/6·(J1 + 2·J2 + 2·J3 + J4)

— the exact derivative of the discrete model the filter uses, not of the continuous one.
The measurement ay = (F_yf·cos δ + F_yr)/m has the row ∂ay/∂x = G[1] + [r, 0, Vx].

Where tan α is infinite (D = 0 or Vx = 0) the force is saturated and its derivative is 0.
3×3 matrices are 9-tuples (row-major), so that nothing is allocated.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from kftune.vehicle.single_track import derivatives_scalar

Mat3 = tuple[float, float, float, float, float, float, float, float, float]


@njit(cache=True, error_model="numpy")
def dugoff_slope(tan_alpha: float, Fz: float, C_alpha: float, mu: float) -> float:
    """dF_y/d(tan α) of :func:`~kftune.vehicle.tyre.dugoff_fy_scalar` [N].

    With s = C_α·|tan α|: C_α in the linear region (s ≤ μ·Fz/2); in the saturated one
    F_y = sign(tan α)·μ·Fz·(1 − μ·Fz/(4·s)), whose slope μ·Fz·(μ·Fz/2)·C_α/(2·s²) equals C_α
    where the two meet; 0 without load or at tan α = ±inf.
    """
    if not Fz > 0.0:
        return 0.0 if Fz <= 0.0 else Fz
    s = C_alpha * abs(tan_alpha)
    half_cap = 0.5 * mu * Fz
    if s <= half_cap:
        return C_alpha
    if s == math.inf:
        return 0.0
    return 0.5 * mu * Fz * half_cap * C_alpha / (s * s)


@njit(cache=True, error_model="numpy")
def _tan_ratio_gradient(
    num: float, den: float, dnum: tuple[float, float, float], dden: tuple[float, float, float]
) -> tuple[float, float, float, float]:
    """(tan α, ∂/∂Vx, ∂/∂Vy, ∂/∂r) of tan α = num/den; the gradient is 0 where den = 0."""
    if den == 0.0:
        return math.copysign(math.inf, num), 0.0, 0.0, 0.0
    inv2 = 1.0 / (den * den)
    return (
        num / den,
        (dnum[0] * den - num * dden[0]) * inv2,
        (dnum[1] * den - num * dden[1]) * inv2,
        (dnum[2] * den - num * dden[2]) * inv2,
    )


@njit(cache=True, error_model="numpy")
def _force_gradients(
    vx: float, vy: float, r: float, u: np.ndarray, p: np.ndarray
) -> tuple[float, float, float, float, float, float]:
    """(∂(F_yf·cos δ)/∂x, ∂F_yr/∂x), each over (Vx, Vy, r); u is the prepared row."""
    a, b = p[2], p[3]
    t, cos_d, fzf, fzr = u[2], u[3], u[4], u[5]
    yf = vy + a * r
    taf, f0, f1, f2 = _tan_ratio_gradient(vx * t - yf, vx + yf * t, (t, -1.0, -a), (1.0, t, a * t))
    tar, r0, r1, r2 = _tan_ratio_gradient(b * r - vy, vx, (0.0, -1.0, b), (1.0, 0.0, 0.0))
    kf = dugoff_slope(taf, fzf, p[5], p[8]) * cos_d
    kr = dugoff_slope(tar, fzr, p[6], p[8])
    return kf * f0, kf * f1, kf * f2, kr * r0, kr * r1, kr * r2


@njit(cache=True, error_model="numpy")
def _continuous_jacobian(vx: float, vy: float, r: float, u: np.ndarray, p: np.ndarray) -> Mat3:
    """G = ∂g/∂x at (Vx, Vy, r) (module docstring)."""
    m, iz, a, b = p[0], p[1], p[2], p[3]
    f0, f1, f2, r0, r1, r2 = _force_gradients(vx, vy, r, u, p)
    return (
        0.0,
        r,
        vy,
        (f0 + r0) / m - r,
        (f1 + r1) / m,
        (f2 + r2) / m - vx,
        (a * f0 - b * r0) / iz,
        (a * f1 - b * r1) / iz,
        (a * f2 - b * r2) / iz,
    )


@njit(cache=True, error_model="numpy")
def _chain(g: Mat3, h: float, j: Mat3) -> Mat3:
    """G·(I + h·J) for 3×3 matrices as 9-tuples."""
    g00, g01, g02, g10, g11, g12, g20, g21, g22 = g
    j00, j01, j02, j10, j11, j12, j20, j21, j22 = j
    return (
        g00 + h * (g00 * j00 + g01 * j10 + g02 * j20),
        g01 + h * (g00 * j01 + g01 * j11 + g02 * j21),
        g02 + h * (g00 * j02 + g01 * j12 + g02 * j22),
        g10 + h * (g10 * j00 + g11 * j10 + g12 * j20),
        g11 + h * (g10 * j01 + g11 * j11 + g12 * j21),
        g12 + h * (g10 * j02 + g11 * j12 + g12 * j22),
        g20 + h * (g20 * j00 + g21 * j10 + g22 * j20),
        g21 + h * (g20 * j01 + g21 * j11 + g22 * j21),
        g22 + h * (g20 * j02 + g21 * j12 + g22 * j22),
    )


@njit(cache=True, error_model="numpy")
def rk4_jacobian(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """out[:3, :3] = ∂x'/∂x of one RK4 step of [Vx, Vy, r] (module docstring)."""
    t, cos_d, ax, fzf, fzr = u[2], u[3], u[1], u[4], u[5]
    h2 = 0.5 * dt
    vx, vy, r = x[0], x[1], x[2]
    a1, b1, c1 = derivatives_scalar(vx, vy, r, t, cos_d, ax, fzf, fzr, p)
    J1 = _continuous_jacobian(vx, vy, r, u, p)
    x2, y2, r2 = vx + h2 * a1, vy + h2 * b1, r + h2 * c1
    a2, b2, c2 = derivatives_scalar(x2, y2, r2, t, cos_d, ax, fzf, fzr, p)
    J2 = _chain(_continuous_jacobian(x2, y2, r2, u, p), h2, J1)
    x3, y3, r3 = vx + h2 * a2, vy + h2 * b2, r + h2 * c2
    a3, b3, c3 = derivatives_scalar(x3, y3, r3, t, cos_d, ax, fzf, fzr, p)
    J3 = _chain(_continuous_jacobian(x3, y3, r3, u, p), h2, J2)
    J4 = _chain(_continuous_jacobian(vx + dt * a3, vy + dt * b3, r + dt * c3, u, p), dt, J3)
    s = dt / 6.0
    for i in range(3):
        for j in range(3):
            k = 3 * i + j
            out[i, j] = (1.0 if i == j else 0.0) + s * (J1[k] + 2.0 * J2[k] + 2.0 * J3[k] + J4[k])


@njit(cache=True, error_model="numpy")
def ay_gradient(x: np.ndarray, u: np.ndarray, p: np.ndarray) -> tuple[float, float, float]:
    """∂ay/∂(Vx, Vy, r) of ay = (F_yf·cos δ + F_yr)/m."""
    f0, f1, f2, r0, r1, r2 = _force_gradients(x[0], x[1], x[2], u, p)
    m = p[0]
    return (f0 + r0) / m, (f1 + r1) / m, (f2 + r2) / m


@njit(cache=True, error_model="numpy")
def single_track_F(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """F of the single-track model and of its bias variants (biases: identity block)."""
    out[:, :] = 0.0
    rk4_jacobian(x, u, p, dt, out)
    for j in range(3, x.shape[0]):
        out[j, j] = 1.0


@njit(cache=True, error_model="numpy")
def single_track_H(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """H of z = [Vx, ay, r] (+ the bias states, each added to its measurement)."""
    out[:, :] = 0.0
    out[0, 0] = 1.0
    out[1, 0], out[1, 1], out[1, 2] = ay_gradient(x, u, p)
    out[2, 2] = 1.0
    n_b = x.shape[0] - 3
    if n_b == 1:  # ay bias
        out[1, 3] = 1.0
    elif n_b == 3:  # Vx, ay, r biases
        for i in range(3):
            out[i, 3 + i] = 1.0
