"""Dugoff tyre model: lateral force from slip angle, vertical load and friction.

Dugoff, Fancher & Segel, "An analysis of tire traction properties and their influence on
vehicle dynamic performance", SAE 700377 (1970); in the form of Rajamani, *Vehicle Dynamics
and Control*, 2nd ed., Ch. 13 (tyre models), with the braking-slip sign convention of DESIGN.md §3:

    λ    = μ·Fz·(1 − κ) / (2·√((C_x·κ)² + (C_α·tan α)²))                 (Dugoff λ)
    f(λ) = (2 − λ)·λ  for λ < 1,   1  for λ ≥ 1
    F_y  = C_α·tan α / (1 − κ) · f(λ)

Two exact rewritings make the formula safe everywhere (D := √((C_x·κ)² + (C_α·tan α)²)):

* saturated branch (λ < 1): F_y = C_α·tan α·μ·Fz·(1 − λ/2) / D — no division by (1 − κ),
  bounded as tan α → ±∞ (|F_y| → μ·Fz·C_α|tan α|/D ≤ μ·Fz);
* with κ = 0 (no wheel speeds, as in the sideslip filter) D = C_α|tan α| and this is
  F_y = sign(tan α)·μ·Fz·(1 − λ/2), λ = μ·Fz / (2·C_α|tan α|).

The two branches meet with equal value and slope at λ = 1 (F_y is C¹ in tan α). A load
Fz ≤ 0 (a lifted axle) carries no force.

Used per *axle* in the single-track model: Fz and C_α are the axle's (both tyres). Because
λ is invariant to scaling Fz, C_α and C_x together, the axle force is exactly twice the
force of one tyre carrying half the load — the lumping neglects lateral load transfer only.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

__all__ = ["dugoff_lateral_force"]


def _check_finite(name: str, value: np.ndarray) -> None:
    if not np.all(np.isfinite(value)):
        bad = np.argwhere(~np.isfinite(np.atleast_1d(value)))[0]
        raise ValueError(
            f"dugoff_lateral_force: {name} must be finite, got "
            f"{float(np.atleast_1d(value)[tuple(bad)])} at index {tuple(int(i) for i in bad)}"
        )


def dugoff_lateral_force(
    alpha: ArrayLike,
    Fz: ArrayLike,
    C_alpha: ArrayLike,
    mu: ArrayLike,
    kappa: ArrayLike = 0.0,
    C_x: ArrayLike = 1.0e5,
) -> np.ndarray:
    """Dugoff lateral tyre (or axle) force, vectorised with numpy broadcasting.

    Args:
        alpha: slip angle [rad], any shape.
        Fz: vertical load [N]; values ≤ 0 (lifted wheel) give zero force.
        C_alpha: cornering stiffness [N/rad], > 0.
        mu: tyre–road friction coefficient [-], > 0.
        kappa: longitudinal slip ratio [-], braking convention (κ > 0 braking, κ = 1 a
            locked wheel), ≤ 1. Default 0: free rolling.
        C_x: longitudinal slip stiffness [N], > 0 (only matters for κ ≠ 0).

    Returns:
        F_y [N], the broadcast shape of the inputs, with the sign of tan α. Equals
        C_α·tan α in the linear region (λ ≥ 1) and never exceeds μ·Fz in magnitude.

    Raises:
        ValueError: non-finite input, C_alpha/mu/C_x ≤ 0, or kappa > 1.
    """
    alpha, Fz, C_alpha, mu, kappa, C_x = (
        np.asarray(v, dtype=np.float64) for v in (alpha, Fz, C_alpha, mu, kappa, C_x)
    )
    for name, value in (
        ("alpha", alpha),
        ("Fz", Fz),
        ("C_alpha", C_alpha),
        ("mu", mu),
        ("kappa", kappa),
        ("C_x", C_x),
    ):
        _check_finite(name, value)
    for name, value in (("C_alpha", C_alpha), ("mu", mu), ("C_x", C_x)):
        if np.any(value <= 0):
            raise ValueError(f"dugoff_lateral_force: {name} must be > 0, got {value!r}")
    if np.any(kappa > 1):
        raise ValueError(
            f"dugoff_lateral_force: kappa (braking slip ratio) must be <= 1, got {kappa!r}"
        )
    return _dugoff_unchecked(alpha, Fz, C_alpha, mu, kappa, C_x)


def _dugoff_unchecked(
    alpha: np.ndarray,
    Fz: np.ndarray,
    C_alpha: np.ndarray | float,
    mu: np.ndarray | float,
    kappa: np.ndarray | float = 0.0,
    C_x: np.ndarray | float = 1.0e5,
) -> np.ndarray:
    """:func:`dugoff_lateral_force` without input checks (for callers that checked)."""
    tan_a = np.tan(alpha)
    load = np.maximum(Fz, 0.0)
    D = np.hypot(C_x * kappa, C_alpha * tan_a)
    cap = mu * load * (1.0 - kappa)  # = 2·λ·D
    linear = cap >= 2.0 * D  # λ ≥ 1 (also D = 0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # unselected branch
        lam = cap / (2.0 * D)
        saturated = C_alpha * tan_a * mu * load * (1.0 - 0.5 * lam) / D
        lin = C_alpha * tan_a / (1.0 - kappa)
    return np.where(linear, lin, saturated)


@njit(cache=True, error_model="numpy")
def dugoff_fy_scalar(tan_alpha: float, Fz: float, C_alpha: float, mu: float) -> float:
    """Compiled scalar Dugoff force with κ = 0 (the filter's case) [N].

    Takes tan α rather than α so that callers can form it without trigonometry (see
    :mod:`kftune.vehicle.single_track`). tan α = ±inf is allowed and gives ±μ·Fz.
    """
    if not Fz > 0.0:
        return 0.0 if Fz <= 0.0 else Fz  # Fz ≤ 0: no force; NaN propagates
    s = C_alpha * abs(tan_alpha)
    half_cap = 0.5 * mu * Fz  # λ·s
    if s <= half_cap:  # λ ≥ 1: linear region
        return C_alpha * tan_alpha
    # λ = half_cap / s < 1:  F_y = sign(tan α)·μ·Fz·(1 − λ/2)
    return math.copysign(mu * Fz * (1.0 - 0.5 * half_cap / s), tan_alpha)


@njit(cache=True, error_model="numpy")
def dugoff_fy_scalar_kappa(
    tan_alpha: float, kappa: float, Fz: float, C_alpha: float, C_x: float, mu: float
) -> float:
    """Compiled scalar Dugoff force with longitudinal slip κ ≤ 1 [N] (see module doc)."""
    if not Fz > 0.0:
        return 0.0 if Fz <= 0.0 else Fz
    if math.isinf(tan_alpha):  # α = ±π/2: C_α·tan α / D → ±1, λ → 0
        return math.copysign(mu * Fz, tan_alpha)
    D = math.hypot(C_x * kappa, C_alpha * tan_alpha)
    cap = mu * Fz * (1.0 - kappa)
    if cap >= 2.0 * D:
        return C_alpha * tan_alpha / (1.0 - kappa)
    lam = cap / (2.0 * D)
    return C_alpha * tan_alpha * mu * Fz * (1.0 - 0.5 * lam) / D
