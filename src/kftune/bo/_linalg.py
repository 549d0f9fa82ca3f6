"""Thin, checked wrappers of the LAPACK Cholesky routines used by every surrogate.

The scipy.linalg front-ends re-validate their inputs on every call; inside a likelihood that
L-BFGS-B evaluates hundreds of times per fit that overhead dominates at n ≈ 40, so the
LAPACK routines are called directly here, once, with their ``info`` checked.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from scipy.linalg import lapack

try:  # a dependency of scikit-learn; optional here
    from threadpoolctl import ThreadpoolController
except ImportError:  # pragma: no cover - exercised only without threadpoolctl
    ThreadpoolController = None

_CONTROLLER: Any = None


def single_threaded_blas() -> contextlib.AbstractContextManager[Any]:
    """Context in which BLAS/LAPACK run on one thread (via threadpoolctl when installed).

    At n <= ~100 a multi-threaded BLAS only adds synchronisation: on a shared 2-core
    machine fits ran 3–10x slower with 2 OpenBLAS threads than with 1 (measured). One
    thread also makes the floating-point summation order, hence fits, independent of the
    machine's core count. A no-op when threadpoolctl is not installed.
    """
    global _CONTROLLER
    if ThreadpoolController is None:
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")


#: Jitter ladder, relative to the mean of diag(K): tried in order when Cholesky fails.
JITTER_LADDER: tuple[float, ...] = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)


def cholesky_jitter(K: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Lower Cholesky factor of K + jitter·I with the smallest jitter on the ladder that works.

    Args:
        K: (n, n) symmetric matrix (not modified).

    Returns:
        (L, jitter): L (n, n) lower-triangular with L Lᵀ = K + jitter·I, and the absolute
        jitter added; ``(None, nan)`` when no rung of the ladder gives a positive-definite
        matrix or K is not finite. Never raises.
    """
    L, info = lapack.dpotrf(K, lower=1, clean=1)
    if info == 0:
        return L, 0.0
    if not np.isfinite(K).all():
        return None, float("nan")
    scale = float(np.mean(np.diag(K)))
    if not scale > 0.0:
        scale = 1.0
    eye = np.eye(K.shape[0])
    for rel in JITTER_LADDER[1:]:
        jitter = rel * scale
        L, info = lapack.dpotrf(K + jitter * eye, lower=1, clean=1)
        if info == 0:
            return L, jitter
    return None, float("nan")


def cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve (L Lᵀ) X = B for X; B is (n,) or (n, k)."""
    vec = B.ndim == 1
    X, info = lapack.dpotrs(L, B[:, None] if vec else B, lower=1)
    if info != 0:  # pragma: no cover - only on malformed arguments
        raise ValueError(f"dpotrs failed with info={info}")
    return X[:, 0] if vec else X


def cho_inverse(L: np.ndarray) -> np.ndarray:
    """(L Lᵀ)⁻¹ as a full symmetric (n, n) matrix (LAPACK dpotri, then symmetrised).

    L must have a zero upper triangle (as :func:`cholesky_jitter` returns it), so dpotri's
    lower-triangular result plus its transpose, with the diagonal halved, is the inverse.
    """
    inv, info = lapack.dpotri(L, lower=1)
    if info != 0:  # pragma: no cover - L comes from a successful dpotrf
        raise ValueError(f"dpotri failed with info={info}")
    full = inv + inv.T
    full.flat[:: full.shape[0] + 1] *= 0.5
    return full


def solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve L X = B for lower-triangular L; B is (n,) or (n, k)."""
    vec = B.ndim == 1
    X, info = lapack.dtrtrs(L, B[:, None] if vec else B, lower=1)
    if info != 0:  # pragma: no cover
        raise ValueError(f"dtrtrs failed with info={info}")
    return X[:, 0] if vec else X


def solve_upper_t(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve Lᵀ X = B for lower-triangular L; B is (n,) or (n, k)."""
    vec = B.ndim == 1
    X, info = lapack.dtrtrs(L, B[:, None] if vec else B, lower=1, trans=1)
    if info != 0:  # pragma: no cover
        raise ValueError(f"dtrtrs failed with info={info}")
    return X[:, 0] if vec else X


def log_det_from_cholesky(L: np.ndarray) -> float:
    """log|L Lᵀ| = 2 Σ log L_ii."""
    return 2.0 * float(np.sum(np.log(np.diag(L))))
