"""Scaled sigma points and the unscented transform (readable numpy reference).

Van der Merwe's scaled sigma points (van der Merwe, *Sigma-Point Kalman Filters for
Probabilistic Inference in Dynamic State-Space Models*, PhD thesis, 2004, Ch. 3;
Wan & van der Merwe, "The unscented Kalman filter for nonlinear estimation", 2000), in the
conventions of FilterPy's ``MerweScaledSigmaPoints``:

    λ        = α²·(n + κ) − n
    χ_0      = x,   χ_i = x + [√((n+λ)·P)]_i,   χ_{n+i} = x − [√((n+λ)·P)]_i,  i = 1…n
    W_0^m    = λ/(n+λ),   W_0^c = λ/(n+λ) + 1 − α² + β,   W_i^m = W_i^c = 1/(2(n+λ))

with [√A]_i the i-th column of the lower Cholesky factor of A (= row i of FilterPy's upper
factor). The compiled loops (:mod:`kftune.filters._generic_kernel`, and the single-track
model's own :mod:`kftune.models._sideslip_ukf`) implement the same maths; the latter
written out for n = 3.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

__all__ = ["UKFSettings", "merwe_weights", "sigma_points", "unscented_transform"]


@dataclass(frozen=True)
class UKFSettings:
    """Sigma-point parameters of the UKF (FilterPy ``MerweScaledSigmaPoints`` convention).

    Attributes:
        alpha: spread of the sigma points [-], > 0. Default 1.0.
        beta: prior-distribution term of W_0^c [-]; 2 is optimal for a Gaussian prior
            (van der Merwe 2004, Ch. 3). Default 2.0.
        kappa: secondary scaling [-], n + κ > 0. Default 0.0.

    Why these defaults for the 3-state sideslip model: κ = 3 − n = 0 makes n + κ = 3, which
    matches the fourth moment (kurtosis) of a Gaussian along each axis (Julier & Uhlmann,
    "Unscented filtering and nonlinear estimation", Proc. IEEE 92(3), 2004;
    FilterPy's suggestion too). With α = 1 this gives λ = 0: the points sit at x ± √3·σ,
    W_0^m = 0, W_i = 1/6 and W_0^c = 2 — every covariance weight is non-negative, so the
    predicted covariance is a sum of positive semi-definite terms plus Q and cannot lose
    definiteness in the transform itself. The often-quoted α = 1e-3 instead gives
    W_0^m ≈ −10⁶ and points 1.7e-3·σ from the mean: a near-linearisation that cancels
    digits and samples the model only next to the mean, where the points at ±√3·σ reach
    into the Dugoff saturation when the state is near it.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        for name in ("alpha", "beta", "kappa"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise ValueError(f"UKFSettings.{name} must be a finite number, got {v!r}")
        if self.alpha <= 0:
            raise ValueError(f"UKFSettings.alpha must be > 0, got {self.alpha!r}")

    def check_dim(self, n: int) -> None:
        """Raise ValueError unless n + κ > 0 (i.e. n + λ > 0) for state dimension n."""
        if not n + self.kappa > 0:
            raise ValueError(
                f"UKFSettings.kappa must be > -{n} for a {n}-state filter (n + kappa > 0), "
                f"got {self.kappa!r}"
            )

    def lam(self, n: int) -> float:
        """λ = α²(n + κ) − n."""
        return self.alpha**2 * (n + self.kappa) - n


def merwe_weights(n: int, settings: UKFSettings) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance weights (W^m, W^c), each (2n+1,)."""
    settings.check_dim(n)
    lam = settings.lam(n)
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + 1.0 - settings.alpha**2 + settings.beta
    return wm, wc


def sigma_points(x: np.ndarray, P: np.ndarray, settings: UKFSettings) -> np.ndarray:
    """Scaled sigma points.

    Args:
        x: (n,) mean.
        P: (n, n) symmetric positive-definite covariance.
        settings: sigma-point parameters.

    Returns:
        (2n+1, n) points χ_0 = x, χ_{1..n} = x + columns of chol((n+λ)P),
        χ_{n+1..2n} = x − the same columns.

    Raises:
        numpy.linalg.LinAlgError: P is not positive definite.
    """
    n = x.shape[0]
    settings.check_dim(n)
    L = np.linalg.cholesky((n + settings.lam(n)) * P)
    return np.vstack([x, x + L.T, x - L.T])


def unscented_transform(
    sigmas: np.ndarray, wm: np.ndarray, wc: np.ndarray, noise_cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and covariance of transformed sigma points (+ additive noise).

    Args:
        sigmas: (2n+1, m) transformed points.
        wm, wc: (2n+1,) weights.
        noise_cov: (m, m) additive noise covariance, or None.

    Returns:
        mean (m,) = Σ W^m_i·Y_i and covariance (m, m) = Σ W^c_i·(Y_i − ȳ)(Y_i − ȳ)ᵀ + noise.
    """
    mean = wm @ sigmas
    d = sigmas - mean
    cov = (d * wc[:, None]).T @ d
    if noise_cov is not None:
        cov = cov + noise_cov
    return mean, cov
