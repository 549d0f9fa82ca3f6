"""Elementwise maths for the reference-data generator that rounds the same on every CPU.

NumPy picks some kernels by the CPU it runs on: on AVX-512 machines ``power``, ``arctan2``
and friends run Intel SVML code, elsewhere they call the C library; ``dot``/``convolve`` go
to the BLAS, whose kernels (and summation order) differ by CPU too. Each choice is accurate,
but the last bits differ, and the generator integrates a closed loop (driver + plant), so a
last-bit difference can grow into a visible one. The bundled dataset should be reproducible
(``kftune dataset generate DIR --seed N``), so the generator's own arithmetic
uses only IEEE-exact NumPy operations (+, −, ×, ÷, sqrt, sums) and, for transcendental
functions, Python's :mod:`math`, i.e. the platform's C library, one scalar at a time. (The
CommonRoad plant already uses :mod:`math`.) The arrays are short (one manoeuvre), so the
scalar loops cost milliseconds.

Not covered: SciPy's LSODA calls the BLAS/LAPACK for its Newton iterations (``ddot``,
``daxpy``, ``dgetrf``), and the understeer gradient recorded in the manifest comes from
``np.polyfit`` (LAPACK, rounded to 6 digits there). Those kernels too are chosen by CPU
(OpenBLAS: ``OPENBLAS_CORETYPE`` pins one): on an AVX-512 Xeon a regenerated manoeuvre
differs from the bundle (made on AVX2) by one storage step in up to a few per cent of a
channel's samples. Bit-for-bit identity therefore holds on one machine; across machines
the tests allow one storage step on a small share of the samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np


def _map(fn: Callable[..., float], *arrays: np.ndarray) -> np.ndarray:
    args = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in arrays))
    flat = [a.ravel().tolist() for a in args]
    return np.array(list(map(fn, *flat)), dtype=float).reshape(args[0].shape)


def sin(x: np.ndarray) -> np.ndarray:
    """sin, elementwise, through the C library."""
    return _map(math.sin, x)


def cos(x: np.ndarray) -> np.ndarray:
    """cos, elementwise, through the C library."""
    return _map(math.cos, x)


def arctan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """atan2(y, x), elementwise, through the C library."""
    return _map(math.atan2, y, x)


def moving_average(x: np.ndarray, width: int) -> np.ndarray:
    """Mean over a window of ``width`` samples ending at each index ≥ width − 1: length
    ``len(x) − width + 1`` (NumPy's ``convolve(x, ones(width)/width, "valid")`` without the
    BLAS: each window is summed pairwise by ``np.sum``)."""
    windows = np.lib.stride_tricks.sliding_window_view(np.asarray(x, dtype=float), width)
    return windows.sum(axis=-1) / width
