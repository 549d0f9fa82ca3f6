"""The records a compiled filter loop takes and fills: the contract between the filters
(:mod:`kftune.filters`) and the loops that run them — the generic kernels, and the fast
loops a model may supply for itself (:attr:`~kftune.models.StateSpaceModel.ukf_kernels`).

They live beside the model type so that a model can supply a loop without importing the
filters (the layers import downwards only, ``tests/test_architecture.py``). All three are
plain :class:`~typing.NamedTuple` s of arrays and numbers, which numba passes to and
between compiled functions as structs, so one record replaces the ten data arguments, the
four sigma-point weights and the six output buffers that travelled one by one.

Shapes: N steps, n states, m measurements, n_w prepared inputs, n_p parameters; with B
noise settings (a batch) q, r, x_init, P_init and every output carry a leading axis B.
Every array is float64 (held causes int64), C-ordered and writable: the filters hand the
loops one array type, so that each loop is compiled once.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["JITTER_MAX", "JITTER_START", "KernelData", "KernelOutputs", "SigmaWeights"]

#: The covariance repair every loop applies (and the C export): a covariance whose Cholesky
#: factorisation fails gets a jitter of JITTER_START·max(diag) on its diagonal, ten times
#: more per try, up to JITTER_MAX·max(diag) (and kept); beyond that the run has diverged.
JITTER_START = 1e-12
JITTER_MAX = 1e-6


class KernelData(NamedTuple):
    """One run's checked data, in the model's units.

    Attributes:
        u: (N, n_w) prepared inputs (:meth:`~kftune.models.StateSpaceModel.prepared_inputs`;
            a model without inputs has n_w = 0).
        z: (N, m) measurements. p: (n_p,) the model's parameters. dt: sample time [s].
        q: (n,) or (B, n) diagonal of Q per step. r: (m,) or (B, m) diagonal of R.
        x_init: (n,) or (B, n) prior mean at step 0; P_init: (n, n) or (B, n, n) its
            covariance.
        n_hold: steps a held stop condition must last (≥ 1).
        held_causes: (n_held,) int64 the causes that must be held
            (:attr:`~kftune.models.StateSpaceModel.held_causes`).
    """

    u: np.ndarray
    z: np.ndarray
    p: np.ndarray
    dt: float
    q: np.ndarray
    r: np.ndarray
    x_init: np.ndarray
    P_init: np.ndarray
    n_hold: int
    held_causes: np.ndarray


class SigmaWeights(NamedTuple):
    """The Merwe scaled sigma points' weights (Wan & van der Merwe 2000, Eq. 15):
    W_0^m = λ/(n + λ), W_0^c = W_0^m + 1 − α² + β, W_i = 1/(2(n + λ)) for i ≥ 1, and the
    spread c = √(n + λ) of the points x ± c·(√P)_i."""

    wm0: float
    wc0: float
    wi: float
    c: float


class KernelOutputs(NamedTuple):
    """The buffers a loop fills per step k (rows from a stop on are NaN).

    Attributes:
        x: (N, n) posterior state x⁺_k. P_diag: (N, n) diagonal of P⁺_k.
        z_hat: (N, m) h(x⁺_k, u_k). innovation: (N, m) z_k − ẑ⁻_k.
        nis: (N,) normalised innovation squared. log_det_s: (N,) log det S_k.
    """

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    log_det_s: np.ndarray

    @staticmethod
    def empty(n_steps: int, n: int, m: int, batch: int | None = None) -> KernelOutputs:
        """Uninitialised buffers for N = ``n_steps`` steps (with a leading axis of
        ``batch`` settings where given)."""
        lead = () if batch is None else (batch,)
        return KernelOutputs(
            np.empty((*lead, n_steps, n)),
            np.empty((*lead, n_steps, n)),
            np.empty((*lead, n_steps, m)),
            np.empty((*lead, n_steps, m)),
            np.empty((*lead, n_steps)),
            np.empty((*lead, n_steps)),
        )

    def at(self, b: int) -> KernelOutputs:
        """Setting b's buffers of a batch (views)."""
        return KernelOutputs(*(a[b] for a in self))
