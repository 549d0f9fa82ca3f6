"""Stationary ARD covariance functions with analytic gradients in log space.

A kernel here is a stateless description (frozen dataclass); its hyperparameters travel
separately as a log-space vector ``theta = [log ℓ_1, …, log ℓ_d, log σ_f²]`` so that the
likelihood optimiser works on an unconstrained-ish box and the gradient is w.r.t. exactly the
variables it moves.

Both kernels are functions of the ARD-scaled distance (Rasmussen & Williams 2006, eq. 5.2)

    r² = Σ_i (x_i − x'_i)² / ℓ_i²,

and the per-dimension terms D_i = (x_i − x'_i)²/ℓ_i² are all the gradients need, so the
training-set squared differences are computed once per data set (:func:`squared_differences`)
and rescaled for every θ.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

SQRT5 = math.sqrt(5.0)


def squared_differences(X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
    """Per-dimension squared differences.

    Args:
        X1: (n1, d) points.
        X2: (n2, d) points.

    Returns:
        (d, n1, n2) array S with S[i, a, b] = (X1[a, i] − X2[b, i])².
    """
    # Contiguous (d, n) copies first: broadcasting the strided transposes directly is ~10×
    # slower for a few hundred candidates (same values either way).
    diff = np.ascontiguousarray(X1.T)[:, :, None] - np.ascontiguousarray(X2.T)[:, None, :]
    diff *= diff
    return diff


class Kernel(ABC):
    """A stationary ARD kernel k(x, x') = σ_f² · κ(r) with log-space hyperparameters.

    ``theta`` layout: ``[log ℓ_1, …, log ℓ_d, log σ_f²]`` (length d + 1).
    """

    name: str = "kernel"

    @staticmethod
    def n_params(d: int) -> int:
        """Number of hyperparameters for inputs of dimension d (d length scales + σ_f²)."""
        return d + 1

    @abstractmethod
    def _profile(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit-amplitude kernel κ(r) and −2·dκ/d(r²) as functions of r² (same shape)."""

    def from_squared_differences(
        self, theta: np.ndarray, S: np.ndarray, *, gradient: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Kernel matrix (and its gradient) from precomputed squared differences.

        Args:
            theta: (d+1,) log hyperparameters.
            S: (d, n1, n2) from :func:`squared_differences`.
            gradient: also return the derivatives w.r.t. theta.

        Returns:
            K: (n1, n2); dK: (d+1, n1, n2) with dK[j] = ∂K/∂theta[j], or None.
        """
        d = S.shape[0]
        inv_l2 = np.exp(-2.0 * theta[:d])
        sf2 = math.exp(theta[d])
        # r² = Σ_i D_i with D_i = (x_i − x'_i)²/ℓ_i² (one gemv over the (d, n1·n2) stack)
        r2 = (inv_l2 @ S.reshape(d, -1)).reshape(S.shape[1:])
        kappa, neg2dk = self._profile(r2)
        K = sf2 * kappa
        if not gradient:
            return K, None
        dK = np.empty((d + 1, *r2.shape))
        # ∂r²/∂log ℓ_i = −2 D_i, so ∂K/∂log ℓ_i = σ_f² (dκ/dr²)(−2 D_i) = σ_f² (−2dκ/dr²) D_i.
        np.multiply(S, inv_l2[:, None, None], out=dK[:d])
        dK[:d] *= sf2 * neg2dk
        dK[d] = K  # ∂K/∂log σ_f² = K
        return K, dK

    def gram_for_gradient(self, theta: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kernel matrix K (n1, n2) and the factor G = −2σ_f²·dκ/dr² (n1, n2) that
        :meth:`contract_gradient` needs, from squared differences S (d, n1, n2)."""
        d = S.shape[0]
        inv_l2 = np.exp(-2.0 * theta[:d])
        r2 = (inv_l2 @ S.reshape(d, -1)).reshape(S.shape[1:])
        kappa, neg2dk = self._profile(r2)
        sf2 = math.exp(theta[d])
        return sf2 * kappa, sf2 * neg2dk

    @staticmethod
    def contract_gradient(
        theta: np.ndarray, S: np.ndarray, K: np.ndarray, G: np.ndarray, M: np.ndarray
    ) -> np.ndarray:
        """(d+1,) vector Σ_ab M_ab ∂K_ab/∂theta_j, without forming ∂K (d+1, n, n).

        With ∂K/∂log ℓ_i = G ⊙ S_i/ℓ_i² and ∂K/∂log σ_f² = K (see
        :meth:`from_squared_differences`); K and G from :meth:`gram_for_gradient`.
        """
        d = S.shape[0]
        out = np.empty(d + 1)
        out[:d] = np.exp(-2.0 * theta[:d]) * (S.reshape(d, -1) @ (M * G).ravel())
        out[d] = float(np.vdot(M, K))
        return out

    def matrix(self, theta: np.ndarray, X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
        """(n1, n2) cross-covariance matrix between X1 (n1, d) and X2 (n2, d)."""
        K, _ = self.from_squared_differences(theta, squared_differences(X1, X2))
        return K

    def matrix_and_gradient(
        self, theta: np.ndarray, X: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gram matrix K (n, n) of X (n, d) and dK (d+1, n, n) = ∂K/∂theta."""
        K, dK = self.from_squared_differences(theta, squared_differences(X, X), gradient=True)
        assert dK is not None
        return K, dK

    @staticmethod
    def diag(theta: np.ndarray, n: int) -> np.ndarray:
        """(n,) prior variances k(x, x) = σ_f² (stationary kernel)."""
        return np.full(n, math.exp(theta[-1]))


@dataclass(frozen=True)
class Matern52(Kernel):
    """Matérn ν = 5/2 with ARD length scales (R&W eq. 4.17; paper Eq. 4 with ARD):

    k(r) = σ_f² (1 + √5 r + 5r²/3) exp(−√5 r).
    """

    name: str = "matern52"

    def _profile(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.sqrt(r2)
        e = np.exp(-SQRT5 * r)
        kappa = (1.0 + SQRT5 * r + (5.0 / 3.0) * r2) * e
        # dκ/dr = −(5/3) r (1 + √5 r) e^{−√5 r}; dκ/dr² = dκ/dr / (2r) = −(5/6)(1 + √5 r) e.
        # Finite at r = 0, so the gradient needs no division by r.
        neg2dk = (5.0 / 3.0) * (1.0 + SQRT5 * r) * e
        return kappa, neg2dk


@dataclass(frozen=True)
class SquaredExponential(Kernel):
    """Squared exponential with ARD length scales (R&W eq. 4.9): k(r) = σ_f² exp(−r²/2)."""

    name: str = "se"

    def _profile(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kappa = np.exp(-0.5 * r2)
        return kappa, kappa  # −2 dκ/dr² = κ


KERNELS: dict[str, type[Kernel]] = {
    "matern52": Matern52,
    "se": SquaredExponential,
    "rbf": SquaredExponential,
    "squared-exponential": SquaredExponential,
}


def make_kernel(name: str) -> Kernel:
    """Kernel by name: ``"matern52"`` or ``"se"`` (aliases ``"rbf"``, ``"squared-exponential"``)."""
    try:
        return KERNELS[name]()
    except KeyError:
        raise ValueError(f"unknown kernel {name!r}; expected one of {sorted(KERNELS)}") from None
