"""Input checks of the filters, before any run: each refusal is a ``ValueError`` naming the
argument, the row or entry, and what was expected. For any state and measurement size."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

#: Largest |value| accepted in u and z: covariances are squares of such values and must stay
#: finite in float64 (no physical signal of a car comes anywhere near it).
MAX_ABS_INPUT = 1e100


def first_bad(mask: np.ndarray) -> tuple[int, ...]:
    """Index of the first True entry of ``mask``."""
    return tuple(int(i) for i in np.argwhere(mask)[0])


def check_table(
    name: str, value: ArrayLike | None, cols: tuple[str, ...], units: str
) -> np.ndarray:
    """A finite (N, len(cols)) float64 table with N ≥ 1 and no entry beyond MAX_ABS_INPUT
    (None is refused: a model with inputs needs its table)."""
    if value is None:
        raise ValueError(
            f"{name} must have shape (N, {len(cols)}) with N >= 1, columns "
            f"[{', '.join(cols)}] {units}; got None"
        )
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{name} must be a numeric array of shape (N, {len(cols)}): {exc}"
        ) from None
    if arr.ndim != 2 or arr.shape[1] != len(cols) or arr.shape[0] < 1:
        raise ValueError(
            f"{name} must have shape (N, {len(cols)}) with N >= 1, columns "
            f"[{', '.join(cols)}] {units}; got shape {arr.shape}"
        )
    finite = np.isfinite(arr)
    if not finite.all():
        row, col = first_bad(~finite)
        raise ValueError(
            f"{name}[{row}, {col}] ({cols[col]}) is {float(arr[row, col])}; all {name} values "
            "must be finite"
        )
    huge = np.abs(arr) > MAX_ABS_INPUT
    if huge.any():
        row, col = first_bad(huge)
        raise ValueError(
            f"{name}[{row}, {col}] ({cols[col]}) is {float(arr[row, col])}: beyond "
            f"±{MAX_ABS_INPUT:g}, where covariances (squares) overflow; check the units"
        )
    return np.ascontiguousarray(arr)


def check_dt(dt: float) -> float:
    """A finite sample time > 0 [s] as a float."""
    try:
        dt_f = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a number (sample time in s), got {dt!r}") from None
    if not (math.isfinite(dt_f) and dt_f > 0):
        raise ValueError(f"dt must be a finite sample time > 0 s, got {dt!r}")
    return dt_f


def check_noise(
    name: str,
    value: ArrayLike,
    units: str,
    *,
    strictly_positive: bool,
    batch: bool,
    dim: int = 3,
) -> np.ndarray:
    """Noise variances: (dim,), or (B, dim) with ``batch``; finite, ≥ 0 (> 0 if strictly)."""
    arr = np.asarray(value, dtype=np.float64)
    want = f"(B, {dim})" if batch else f"({dim},)"
    ok_shape = (
        (arr.ndim == 2 and arr.shape[1] == dim and arr.shape[0] >= 1)
        if batch
        else (arr.shape == (dim,))
    )
    if not ok_shape:
        raise ValueError(
            f"{name} must have shape {want}: the diagonal of the covariance, variances "
            f"{units}; got shape {arr.shape}"
        )
    finite = np.isfinite(arr)
    if not finite.all():
        idx = first_bad(~finite)
        raise ValueError(f"{name}{list(idx)} is {float(arr[idx])}; variances must be finite")
    bad = arr <= 0 if strictly_positive else arr < 0
    if bad.any():
        idx = first_bad(bad)
        need = "> 0" if strictly_positive else ">= 0"
        raise ValueError(f"{name}{list(idx)} = {float(arr[idx])}; variances {units} must be {need}")
    return np.ascontiguousarray(arr)


def check_state(x0: ArrayLike, names: tuple[str, ...]) -> np.ndarray:
    """A finite (n,) prior mean, n = len(names)."""
    x_arr = np.asarray(x0, dtype=np.float64)
    if x_arr.shape != (len(names),):
        raise ValueError(
            f"x0 must have shape ({len(names)},) [{', '.join(names)}], got shape {x_arr.shape}"
        )
    if not np.isfinite(x_arr).all():
        raise ValueError(f"x0 must be finite, got {x_arr.tolist()}")
    return np.ascontiguousarray(x_arr)


def check_covariance(P0: ArrayLike, n: int) -> np.ndarray:
    """A finite, symmetric, positive-definite (n, n) prior covariance (an (n,) is its diagonal)."""
    P_arr = np.asarray(P0, dtype=np.float64)
    if P_arr.shape == (n,):
        P_arr = np.diag(P_arr)
    if P_arr.shape != (n, n):
        raise ValueError(
            f"P0 must be a ({n}, {n}) covariance or a ({n},) diagonal, got shape {P_arr.shape}"
        )
    if not np.isfinite(P_arr).all():
        raise ValueError("P0 must be finite")
    if not np.allclose(P_arr, P_arr.T, rtol=1e-10, atol=0.0):
        raise ValueError("P0 must be symmetric")
    try:
        np.linalg.cholesky(P_arr)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"P0 must be positive definite, got eigenvalues {np.linalg.eigvalsh(P_arr)}"
        ) from None
    return np.ascontiguousarray(P_arr)
