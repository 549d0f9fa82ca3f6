"""Acquisition functions for minimisation, vectorised over candidates.

Each function reads only a :class:`~kftune.bo.base.Predictive` and the incumbent ``best``
(the smallest observed value), so every surrogate works with every acquisition function.
Except :func:`lower_confidence_bound`, larger values are better.

Notation. σ = ``pred.std`` is always the predictive standard deviation (√variance); s =
``pred.scale`` the scale of the location-scale family: s = σ for a Gaussian and
s = σ·√((ν−2)/ν) for a Student-t with ν = ``pred.dof`` (the *predictive* dof, ν + n for
the tSP). Where a standardised distribution appears (EI, PI, log-EI), z = (best − μ)/s uses
the scale — the t cdf and pdf are those of (Y − μ)/s. The confidence bounds use σ, as the
paper's Eq. 9 does with σ̂ from its Eq. 7 (a variance). For a Gaussian the two coincide.

Student-t expected improvement (derivation). Let Y = μ + s·T with T ~ t_ν (ν > 1), pdf
t_ν, cdf T_ν, and I = max(best − Y, 0). With z = (best − μ)/s,

    E[I] = ∫_{−∞}^{z} (best − μ − s u) t_ν(u) du = (best − μ) T_ν(z) − s ∫_{−∞}^{z} u t_ν(u) du,

and since d/du [(ν + u²) t_ν(u)/(ν − 1)] = −u t_ν(u) (differentiate (1 + u²/ν)^{−(ν−1)/2}),

    EI = (best − μ) T_ν(z) + s · (ν + z²)/(ν − 1) · t_ν(z) = s · h_ν(z),
    h_ν(z) = z T_ν(z) + (ν + z²)/(ν − 1) · t_ν(z).

This is the t-EI of Tracey & Wolpert (2018, "Upgrading from Gaussian processes to Student's-T
processes", AIAA SciTech, eq. for EI) and paper Eq. 8 *when* its σ̂ is the t scale s (not the
standard deviation of Eq. 7) and its ν is the predictive dof. As ν → ∞ it tends to the
Gaussian EI s·(zΦ(z) + φ(z)) (Jones, Schonlau & Welch 1998, eq. 15). Check: z = 0, ν = 2,
s = 1 gives 2·t_2(0) = 2·(1/(2√2)) = 1/√2.

Numerical stability (both families). h(z) for z ≪ 0 is a difference of nearly equal terms
that underflows; for z < −2 it is computed without subtraction:

* Gaussian: h(z) = φ(z)·q/(w + q), w = −z, with q = 1/(w + 2/(w + 3/(w + …))), from
  Laplace's continued fraction of the Mills ratio R(w) = 1/(w + q) (A&S 26.2.14), since
  1 − wR(w) = q/(w + q).
* Student-t: with x = ν/(ν + z²) and the regularised incomplete beta
  T_ν(z) = ½ I_x(ν/2, ½) = ½ x^{ν/2}(1−x)^{½} F / ((ν/2) B(ν/2, ½)), where F is the
  continued fraction of I_x (A&S 26.5.8, evaluated by modified Lentz), one gets
  h_ν(z) = A·(1 − ρ), A = (ν + z²) t_ν(z)/(ν − 1), ρ = (1 − x)(ν − 1)F/ν, with
  0 < ρ < (ν−1)/ν: at most a factor ν of cancellation, all in log space.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr, poch, stdtr

from kftune.bo.base import Predictive

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_Z_SWITCH = -2.0  # below this, h(z) comes from the continued fractions
_GAUSS_CF_TERMS = 100  # Laplace CF depth: < 1e-14 relative error for w >= 2
_LENTZ_MAXIT = 10_000
_TINY = 1e-300


# ---------------------------------------------------------------------- validation
def _check_best(best: float) -> float:
    try:
        b = float(best)
    except (TypeError, ValueError):
        raise ValueError(f"best must be a real number, got {best!r}") from None
    if not math.isfinite(b):
        raise ValueError(f"best (the incumbent value) must be finite, got {b}")
    return b


def _check_beta(beta: float) -> float:
    b = float(beta)
    if not (b >= 0.0 and math.isfinite(b)):
        raise ValueError(f"beta must be a finite number >= 0, got {beta}")
    return b


def _check_ei_dof(pred: Predictive) -> float:
    nu = pred.dof
    if not nu > 1.0:
        raise ValueError(f"expected improvement needs predictive dof > 1 (finite mean), got {nu}")
    return nu


def _standardise(pred: Predictive, best: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(improvement best − μ, scale s, z = (best − μ)/s with 0 where s = 0)."""
    diff = best - pred.mean
    s = pred.scale
    pos = s > 0
    z = np.zeros_like(diff)
    np.divide(diff, s, out=z, where=pos)
    return diff, s, z


# ---------------------------------------------------------------------- Gaussian h(z)
def _gauss_log_pdf(z: np.ndarray) -> np.ndarray:
    return -0.5 * z * z - _LOG_SQRT_2PI


def _gauss_tail_ratio(w: np.ndarray) -> np.ndarray:
    """q/(w + q) = 1 − wR(w) = h(−w)/φ(w) for w >= 2, by the Laplace continued fraction."""
    t = np.zeros_like(w)
    for k in range(_GAUSS_CF_TERMS, 1, -1):
        t = k / (w + t)
    q = 1.0 / (w + t)
    return q / (w + q)


def _gauss_log_h(z: np.ndarray) -> np.ndarray:
    """log(φ(z) + zΦ(z)), accurate for every finite z."""
    out = np.empty_like(z)
    hi = z >= _Z_SWITCH
    zh = z[hi]
    out[hi] = np.log(np.exp(_gauss_log_pdf(zh)) + zh * ndtr(zh))
    lo = ~hi
    w = -z[lo]
    with np.errstate(over="ignore"):
        out[lo] = _gauss_log_pdf(w) + np.log(_gauss_tail_ratio(w))
    return out


# ---------------------------------------------------------------------- Student-t h(z)
def _t_log_pdf(z: np.ndarray, nu: float) -> np.ndarray:
    """log t_ν(z); Γ((ν+1)/2)/Γ(ν/2) via ``poch`` (no cancellation of large gammaln)."""
    return (
        math.log(poch(0.5 * nu, 0.5))
        - 0.5 * math.log(nu * math.pi)
        - 0.5 * (nu + 1.0) * _log1p_z2_over_nu(z, nu)
    )


def _log1p_z2_over_nu(z: np.ndarray, nu: float) -> np.ndarray:
    """log(1 + z²/ν) without overflowing z² for huge |z|."""
    az = np.abs(z)
    big = az > 1e100
    out = np.empty_like(az)
    out[~big] = np.log1p(az[~big] ** 2 / nu)
    out[big] = 2.0 * np.log(az[big]) - math.log(nu)
    return out


def _incomplete_beta_cf(a: float, b: float, x: np.ndarray) -> np.ndarray:
    """Continued fraction F of I_x(a, b) = x^a (1−x)^b F / (a B(a, b)) (A&S 26.5.8),
    by the modified Lentz method, vectorised over x. Converges fast for x < (a+1)/(a+b+2)."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = np.ones_like(x)
    d = 1.0 - qab * x / qap
    d = 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)
    h = d.copy()
    for m in range(1, _LENTZ_MAXIT):
        m2 = 2 * m
        for aa in (
            m * (b - m) * x / ((qam + m2) * (a + m2)),
            -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)),
        ):
            d = 1.0 + aa * d
            d = 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)
            c = 1.0 + aa / c
            c = np.where(np.abs(c) < _TINY, _TINY, c)
            delta = d * c
            h = h * delta
        if np.all(np.abs(delta - 1.0) <= 1e-15):
            break
    return h


def _t_log_h(z: np.ndarray, nu: float) -> np.ndarray:
    """log h_ν(z) = log(z T_ν(z) + (ν + z²) t_ν(z)/(ν − 1)), accurate for every finite z."""
    out = np.empty_like(z)
    hi = z >= _Z_SWITCH
    zh = z[hi]
    out[hi] = np.log(zh * stdtr(nu, zh) + (nu + zh * zh) / (nu - 1.0) * np.exp(_t_log_pdf(zh, nu)))
    lo = ~hi
    if np.any(lo):
        zl = z[lo]
        l1p = _log1p_z2_over_nu(zl, nu)  # log((ν + z²)/ν)
        x = np.exp(-l1p)  # ν/(ν + z²)
        one_minus_x = -np.expm1(-l1p)  # z²/(ν + z²), no cancellation
        F = _incomplete_beta_cf(0.5 * nu, 0.5, x)
        rho = one_minus_x * (nu - 1.0) / nu * F
        log_A = math.log(nu) + l1p - math.log(nu - 1.0) + _t_log_pdf(zl, nu)
        out[lo] = log_A + np.log1p(-rho)
    return out


def _log_h(z: np.ndarray, nu: float) -> np.ndarray:
    return _gauss_log_h(z) if math.isinf(nu) else _t_log_h(z, nu)


# ---------------------------------------------------------------------- public API
def expected_improvement(pred: Predictive, best: float) -> np.ndarray:
    """Expected improvement E[max(best − Y, 0)] (minimisation), (m,).

    Gaussian (``pred.dof`` = inf): s·(zΦ(z) + φ(z)) (Jones et al. 1998, eq. 15).
    Student-t (dof ν > 1): s·(z T_ν(z) + (ν + z²)/(ν − 1)·t_ν(z)) with the t *scale*
    s = √(var·(ν−2)/ν) (module docstring; Tracey & Wolpert 2018; paper Eq. 8 read with
    σ̂ = s). z = (best − μ)/s. Where s = 0: max(best − μ, 0).
    """
    best = _check_best(best)
    nu = _check_ei_dof(pred)
    diff, s, z = _standardise(pred, best)
    pos = s > 0
    out = np.maximum(diff, 0.0)
    if np.any(pos):
        out[pos] = s[pos] * np.exp(_log_h(z[pos], nu))
    return out


def log_expected_improvement(pred: Predictive, best: float) -> np.ndarray:
    """log of :func:`expected_improvement`, (m,), accurate (no underflow to −inf, no
    cancellation) for every finite z, for both the Gaussian and the Student-t predictive
    (module docstring). −inf only where s = 0 and μ >= best.
    """
    best = _check_best(best)
    nu = _check_ei_dof(pred)
    diff, s, z = _standardise(pred, best)
    pos = s > 0
    out = np.full(diff.shape, -math.inf)
    with np.errstate(divide="ignore"):
        out[~pos] = np.log(np.maximum(diff[~pos], 0.0))
    if np.any(pos):
        out[pos] = np.log(s[pos]) + _log_h(z[pos], nu)
    return out


def probability_of_improvement(pred: Predictive, best: float) -> np.ndarray:
    """P(Y < best), (m,): Φ(z) (Gaussian) or T_ν(z) (Student-t), z = (best − μ)/s.
    Where s = 0: 1 if μ < best else 0."""
    best = _check_best(best)
    diff, s, z = _standardise(pred, best)
    pos = s > 0
    out = (diff > 0).astype(float)
    if np.any(pos):
        nu = pred.dof
        out[pos] = ndtr(z[pos]) if math.isinf(nu) else stdtr(nu, z[pos])
    return out


def confidence_bound(pred: Predictive, best: float, beta: float = 0.01) -> np.ndarray:
    """Paper Eq. 9 (CBM): √β·σ + (best − μ), (m,); larger is better. σ = ``pred.std``
    (the standard deviation, as the paper's σ̂ from Eq. 7). Equals best − LCB."""
    best = _check_best(best)
    beta = _check_beta(beta)
    return math.sqrt(beta) * pred.std + (best - pred.mean)


def lower_confidence_bound(pred: Predictive, beta: float = 0.01) -> np.ndarray:
    """μ − √β·σ, (m,); *smaller* is better (minimise it). σ = ``pred.std``."""
    beta = _check_beta(beta)
    return pred.mean - math.sqrt(beta) * pred.std
