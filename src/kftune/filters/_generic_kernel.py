"""Compiled UKF and EKF kernels for any state-space model (numba).

Both filters share the time convention of :mod:`kftune.filters.generic` (step 0 updates the
prior with z[0]; step k ≥ 1 predicts with u[k−1] held, then updates with z[k] and
h(·, u[k])), the covariance repair, the stop causes and the NaN fill of the single-track model's
own 3×3 loop (:mod:`kftune.models._sideslip_ukf`), and the measurement update, written with
the Cholesky factor of the innovation covariance S = L_S·L_Sᵀ instead of S⁻¹ (Simon,
*Optimal State Estimation*, 2006, eqs. 13.48 and 14.80; Särkkä, *Bayesian Filtering and
Smoothing*, 2013, Algs. 5.4 and 5.14, rearranged): with A = L_S⁻¹, W = A·P_xzᵀ and v = A·y,

    x⁺ = x̄ + Wᵀ·v,   P⁺ = P̄ − Wᵀ·W,   NIS = vᵀ·v.

They differ in the moments they hand to that update:

* UKF (Merwe scaled sigma points, Simon 2006 Sec. 14.3; Särkkä 2013 Alg. 5.14): sigma points
  of (x⁺, P⁺) through f give x̄, P̄ = Σ W^c·(χ − x̄)(χ − x̄)ᵀ + Q; points redrawn from (x̄, P̄)
  through h give ẑ, S = Σ W^c·(ζ − ẑ)(ζ − ẑ)ᵀ + R and P_xz = Σ W^c·(χ − x̄)(ζ − ẑ)ᵀ.
* EKF (Simon 2006 Sec. 13.2; Särkkä 2013 Alg. 5.4): x̄ = f(x⁺), P̄ = F·P⁺·Fᵀ + Q with F the
  Jacobian at x⁺; ẑ = h(x̄), P_xz = P̄·Hᵀ, S = H·P_xz + R with H the Jacobian at x̄. Jacobians are
  the model's own or central finite differences (:mod:`kftune.models.jacobians`).

The arithmetic of the UKF follows that 3×3 loop operation by operation (the same Cholesky,
sums in the same order, the same triangular inverse), so that for the single-track model the
two give the same numbers. Covariances are kept as full symmetric arrays: every routine
computes the upper triangle and mirrors it, and reads only that.

Covariance repair: P⁺ after each update, the UKF's predicted P̄ (before its sigma points are
drawn), the prior and S go through :func:`chol_repair`: jitter from 10⁻¹²·max(diag), ten
times more per try, up to 10⁻⁶·max(diag), added to the diagonal (and kept in P). If that
fails, or the state, the NIS or the estimated measurement is not finite, the run stops with
``STOP_NUMERICAL``; a model's ``check`` can stop it with its own causes (immediately, or for
a condition held ``n_hold`` steps, at the step it began). Rows from the stop step on are NaN.
The kernels never raise.

How it is compiled. The model's functions are first-class arguments of the kernels
(:func:`ukf_run`, :func:`ekf_run`): numba compiles the kernels once per model, calling
the model's f and h directly. Every kernel that takes a function is inlined
(``inline="always"``) into the wrappers of a module generated per model
(:mod:`kftune.filters._compiled`), which name the model's functions as globals: numba can
cache those wrappers on disk, as it cannot cache a function that receives a function
value. The linear algebra lives in a few helpers without function arguments, which are
cached, with their own small helpers inlined into them
(``inline="always"``: a call costs about 30 ns, a tenth of a filter step's arithmetic at
n = 3). The sizes are compile-time constants: kernels and helpers take the state and
measurement sizes as tuples of n and m zeros (``n_token``, ``m_token``), whose lengths are
part of their numba types, so that LLVM unrolls the small loops and resolves every index
(for n = 3 the UKF is 1.6 times faster than with run-time sizes).

Arguments travel as records, numba-compiled as structs: a run's data, the sigma-point
weights and the output buffers as :mod:`kftune.models.kernel_io`'s
:class:`~kftune.models.kernel_io.KernelData`, :class:`~kftune.models.kernel_io.SigmaWeights`
and :class:`~kftune.models.kernel_io.KernelOutputs` (the interface a model's own loops
share), the work arrays as :class:`Work` (with :class:`UpdateWork` and :class:`Hold`); the
kernels read the records into locals once, before the steps (:class:`Work`). A batch calls
the model's compiled single run per setting (:func:`ukf_batch`) rather than inlining it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numba.core.dispatcher import Dispatcher

from kftune.models.base import STOP_NONE, STOP_NUMERICAL
from kftune.models.jacobians import fd_measurement_jacobian, fd_process_jacobian
from kftune.models.kernel_io import (
    JITTER_MAX,
    JITTER_START,
    KernelData,
    KernelOutputs,
    SigmaWeights,
)

_NAN = math.nan

Token = tuple[float, ...]

#: The unscented transform's weights (W^m_0, W^c_0, W_i) as the helpers take them: a plain
#: tuple, not the whole :class:`~kftune.models.kernel_io.SigmaWeights` record, with which
#: numba's code for the n = 3 UKF runs measurably slower (BENCHMARKS.md, "Records instead of
#: argument lists").
MomentWeights = tuple[float, float, float]

#: A measurement update's outcome: (status of S, NIS, log det S, status of P⁺, P⁺'s jitter),
#: the statuses as :func:`chol_repair`'s.
UpdateStatus = tuple[int, float, float, int, float]


class UpdateWork(NamedTuple):
    """The measurement update's work arrays (n states, m measurements).

    Attributes:
        zb: (m,) ẑ, the predicted measurement. S: (m, m) innovation covariance (with R).
        Pxz: (n, m) cross covariance P_xz. Ls: (m, m) L_S, S's lower Cholesky factor, and
        A: (m, m) L_S⁻¹, both allocated zeroed (their upper triangles stay 0).
        W: (m, n) A·P_xzᵀ. y: (m,) innovation z_k − ẑ. v: (m,) A·y.
    """

    zb: np.ndarray
    S: np.ndarray
    Pxz: np.ndarray
    Ls: np.ndarray
    A: np.ndarray
    W: np.ndarray
    y: np.ndarray
    v: np.ndarray


class Hold(NamedTuple):
    """The held stop conditions of a run (:attr:`~kftune.models.StateSpaceModel.held_causes`).

    Attributes:
        held: (n_held,) bool, which conditions the model's check found at this step (it
            writes them). held_for: (n_held,) int64, the steps each has lasted (from 0).
        n_hold: the steps a condition must last to stop the run (≥ 1).
        causes: (n_held,) int64 their causes.
    """

    held: np.ndarray
    held_for: np.ndarray
    n_hold: int
    causes: np.ndarray


class Work(NamedTuple):
    """A run's work arrays (:func:`workspace`), both filters' (each uses its own).

    Attributes:
        x: (n,) the state. P: (n, n) its covariance. L: (n, n) P's lower Cholesky factor.
        X, D, Y: (2n+1, n) the UKF's sigma points, their deviations and the points through
            f. Z: (2n+1, m) the points through h. zh: (m,) h(x⁺_k, u_k).
        T: (n, n) the EKF's F·P. Fm: (n, n) F. Hm: (m, n) H. xw, fp, fm: (n,) and hp, hm:
            (m,) f(x̄) and the finite differences' work.
        upd: the measurement update's arrays. hold: the held conditions' state.

    The kernels read the fields into locals once, before the steps: a record handed to an
    inlined function costs numba a reference count per array and call.
    """

    x: np.ndarray
    P: np.ndarray
    L: np.ndarray
    X: np.ndarray
    D: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    zh: np.ndarray
    T: np.ndarray
    Fm: np.ndarray
    Hm: np.ndarray
    xw: np.ndarray
    fp: np.ndarray
    fm: np.ndarray
    hp: np.ndarray
    hm: np.ndarray
    upd: UpdateWork
    hold: Hold


# --------------------------------------------------------------------------------------
# Linear algebra on small work arrays (cached; sizes from the tokens)
# --------------------------------------------------------------------------------------


@njit(cache=True, inline="always", error_model="numpy")
def chol(P: np.ndarray, L: np.ndarray, jitter: float, n_token: Token) -> bool:
    """Lower Cholesky factor L of P + jitter·I from P's upper triangle (as ``chol3``).

    L[i, i] = √(P[i, i] + jitter − Σ_{k<i} L[i, k]²),
    L[i, j] = (P[j, i] − Σ_{k<j} L[i, k]·L[j, k]) / L[j, j]   (j < i).

    Returns:
        False when a pivot is not > 0 and finite (L is then incomplete).
    """
    n = len(n_token)
    for i in range(n):
        for j in range(i + 1):
            if i == j:
                s = P[i, i] + jitter
                for k in range(j):
                    s -= L[i, k] * L[i, k]
                if not (s > 0.0 and s < math.inf):
                    return False
                L[i, i] = math.sqrt(s)
            else:
                s = P[j, i]
                for k in range(j):
                    s -= L[i, k] * L[j, k]
                L[i, j] = s / L[j, j]
    return True


@njit(cache=True, inline="always", error_model="numpy")
def chol_repair(P: np.ndarray, L: np.ndarray, n_token: Token) -> tuple[int, float]:
    """Cholesky with jitter escalation (as ``chol3_repair``).

    Returns:
        (status, jitter): 0 = factorised as is, 1 = factorised after adding ``jitter`` to
        the diagonal, 2 = not repairable (non-finite, or no jitter up to the maximum helps).
    """
    n = len(n_token)
    jitter = 0.0
    limit = 0.0
    status = 0
    while True:  # one call site of chol: a shorter compile
        if chol(P, L, jitter, n_token):
            return status, jitter
        if status == 0:
            status = 1
            scale = P[0, 0]
            finite = True
            for i in range(n):
                if P[i, i] > scale:
                    scale = P[i, i]
                for j in range(i, n):
                    if not math.isfinite(P[i, j]):
                        finite = False
            jitter = JITTER_START * scale
            limit = JITTER_MAX * scale * 1.0000001
            # (jitter > 0 also ends the escalation where a subnormal scale underflows it)
            if not (finite and jitter > 0.0):
                return 2, 0.0
        else:
            jitter *= 10.0
        if not jitter <= limit:
            return 2, 0.0


@njit(cache=True, error_model="numpy")
def prior(
    x_init: np.ndarray,
    P_init: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    n_token: Token,
) -> int:
    """x = x_init; P = P_init symmetrised ((P + Pᵀ)/2 off the diagonal, as the 3×3 kernel),
    factorised into L and repaired. Returns the status of :func:`chol_repair`."""
    n = len(n_token)
    for i in range(n):
        x[i] = x_init[i]
        P[i, i] = P_init[i, i]
        for j in range(i + 1, n):
            P[i, j] = 0.5 * (P_init[i, j] + P_init[j, i])
            P[j, i] = P[i, j]
    st, jit = chol_repair(P, L, n_token)
    if st == 1:
        for i in range(n):
            P[i, i] += jit
    return st


@njit(cache=True, error_model="numpy")
def sigma_points(
    x: np.ndarray,
    L: np.ndarray,
    c: float,
    X: np.ndarray,
    D: np.ndarray,
    update: bool,
    n_token: Token,
) -> None:
    """Merwe sigma points of (x, L·Lᵀ): X_0 = x, X_i = x ± c·L[:, i] (Simon 2006 eq. 14.57).

    D: (2n+1, n) the deviations 0, ±c·L[:, i], zeros above the diagonal of c·L. X: (2n+1, n)
    the points, x + D for the update, and x itself where D is 0 for the prediction (the two
    differ only for a state −0.0, and follow the 3×3 kernel's two ways).
    """
    n = len(n_token)
    for j in range(n):
        X[0, j] = x[j] + 0.0 if update else x[j]
        D[0, j] = 0.0
    for i in range(n):
        for j in range(n):
            d = c * L[j, i] if j >= i else 0.0
            D[1 + i, j] = d
            D[1 + n + i, j] = -d
            if update:
                X[1 + i, j] = x[j] + d
                X[1 + n + i, j] = x[j] + -d
            else:
                X[1 + i, j] = x[j] + d if j >= i else x[j]
                X[1 + n + i, j] = x[j] - d if j >= i else x[j]


@njit(cache=True, inline="always", error_model="numpy")
def unscented_moments(
    Y: np.ndarray,
    mean: np.ndarray,
    cov: np.ndarray,
    noise: np.ndarray,
    wts: MomentWeights,
    n_token: Token,
    k_token: Token,
) -> None:
    """mean = Σ W^m_i·Y_i; Y_i −= mean in place; cov = Σ W^c_i·d_i·d_iᵀ + diag(noise).

    Y: (2n+1, k) transformed sigma points (n = len(n_token), k = len(k_token)); mean: (k,);
    cov: (k, k) symmetric; noise: (k,) variances; wts: the weights W^m_0, W^c_0, W_i
    (Simon 2006 eqs. 14.59–14.60, 14.63–14.64).
    """
    wm0, wc0, wi = wts
    ns = 2 * len(n_token) + 1
    k = len(k_token)
    for j in range(k):
        s = wm0 * Y[0, j]
        for i in range(1, ns):
            s += wi * Y[i, j]
        mean[j] = s
    for i in range(ns):
        for j in range(k):
            Y[i, j] -= mean[j]
    for a in range(k):
        for b in range(a, k):
            s = wc0 * Y[0, a] * Y[0, b]
            for i in range(1, ns):
                s += wi * Y[i, a] * Y[i, b]
            cov[a, b] = s
        cov[a, a] += noise[a]
        for b in range(a + 1, k):
            cov[b, a] = cov[a, b]


@njit(cache=True, inline="always", error_model="numpy")
def cross_covariance(
    D: np.ndarray, dZ: np.ndarray, Pxz: np.ndarray, wi: float, n_token: Token, m_token: Token
) -> None:
    """P_xz = Σ_{i≥1} W_i·D_i·dZ_iᵀ (D_0 = 0; Simon 2006 eq. 14.65)."""
    n = len(n_token)
    for a in range(n):
        for b in range(len(m_token)):
            s = 0.0
            for i in range(1, 2 * n + 1):
                s += wi * D[i, a] * dZ[i, b]
            Pxz[a, b] = s


@njit(cache=True, error_model="numpy")
def linearised_prediction(
    Fm: np.ndarray, P: np.ndarray, T: np.ndarray, q: np.ndarray, n_token: Token
) -> None:
    """P = F·P·Fᵀ + diag(q) in place (Simon 2006 eq. 13.47); T: (n, n) work."""
    n = len(n_token)
    for a in range(n):
        for b in range(n):
            s = 0.0
            for i in range(n):
                s += Fm[a, i] * P[i, b]
            T[a, b] = s
    for a in range(n):
        for b in range(a, n):
            s = 0.0
            for i in range(n):
                s += T[a, i] * Fm[b, i]
            P[a, b] = s + q[a] if a == b else s
            P[b, a] = P[a, b]


@njit(cache=True, inline="always", error_model="numpy")
def linearised_moments(
    P: np.ndarray,
    Hm: np.ndarray,
    Pxz: np.ndarray,
    S: np.ndarray,
    r: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> None:
    """P_xz = P·Hᵀ, S = H·P_xz + diag(r) (Simon 2006 eq. 13.48)."""
    n, m = len(n_token), len(m_token)
    for a in range(n):
        for b in range(m):
            s = 0.0
            for i in range(n):
                s += P[a, i] * Hm[b, i]
            Pxz[a, b] = s
    for a in range(m):
        for b in range(a, m):
            s = 0.0
            for i in range(n):
                s += Hm[a, i] * Pxz[i, b]
            S[a, b] = s + r[a] if a == b else s
            S[b, a] = S[a, b]


@njit(cache=True, inline="always", error_model="numpy")
def kalman_update(
    x: np.ndarray, P: np.ndarray, zk: np.ndarray, wu: UpdateWork, n_token: Token, m_token: Token
) -> tuple[int, float, float]:
    """Kalman update of (x, P) in place from ẑ, S (with R) and P_xz in ``wu`` and z_k.

    Returns:
        (status of S's factorisation as :func:`chol_repair`, NIS, log det S = 2·Σ log
        diag(L_S), with the NIS the innovation likelihood); on status 2 (x, P) are
        untouched.
    """
    n, m = len(n_token), len(m_token)
    zb, S, Pxz, Ls, A, W, y, v = wu.zb, wu.S, wu.Pxz, wu.Ls, wu.A, wu.W, wu.y, wu.v
    st, _ = chol_repair(S, Ls, m_token)
    if st == 2:
        return st, _NAN, _NAN
    ldet = 0.0
    for i in range(m):
        ldet += 2.0 * math.log(Ls[i, i])
    # A = L_S⁻¹ by forward substitution: A[i, i] = 1/L[i, i],
    # A[i, j] = −(Σ_{j≤k<i} L[i, k]·A[k, j])·A[i, i]
    for i in range(m):
        A[i, i] = 1.0 / Ls[i, i]
    for i in range(1, m):
        for j in range(i):
            s = Ls[i, j] * A[j, j]
            for k in range(j + 1, i):
                s += Ls[i, k] * A[k, j]
            A[i, j] = -s * A[i, i]
    # W = A·P_xzᵀ,  v = A·y
    for i in range(m):
        for j in range(n):
            s = A[i, 0] * Pxz[j, 0]
            for k in range(1, i + 1):
                s += A[i, k] * Pxz[j, k]
            W[i, j] = s
    for i in range(m):
        y[i] = zk[i] - zb[i]
    nis = 0.0
    for i in range(m):
        s = A[i, 0] * y[0]
        for k in range(1, i + 1):
            s += A[i, k] * y[k]
        v[i] = s
        nis = s * s if i == 0 else nis + s * s
    # x⁺ = x̄ + Wᵀ·v,  P⁺ = P̄ − Wᵀ·W
    for j in range(n):
        s = W[0, j] * v[0]
        for i in range(1, m):
            s += W[i, j] * v[i]
        x[j] += s
    for a in range(n):
        for b in range(a, n):
            s = W[0, a] * W[0, b]
            for i in range(1, m):
                s += W[i, a] * W[i, b]
            P[a, b] -= s
            P[b, a] = P[a, b]
    return st, nis, ldet


@njit(cache=True, error_model="numpy")
def predicted_moments(
    Y: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    q: np.ndarray,
    wts: MomentWeights,
    n_token: Token,
) -> int:
    """The UKF's prediction from the points through f, Y: x̄, P̄ = UT(Y) + Q, factorised
    into L and repaired (jitter kept in P̄). Returns the status of :func:`chol_repair`."""
    unscented_moments(Y, x, P, q, wts, n_token, n_token)
    st, jit = chol_repair(P, L, n_token)
    if st == 1:
        for j in range(len(n_token)):
            P[j, j] += jit
    return st


@njit(cache=True, error_model="numpy")
def unscented_update(
    Z: np.ndarray,
    D: np.ndarray,
    zk: np.ndarray,
    r: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    wu: UpdateWork,
    wts: MomentWeights,
    n_token: Token,
    m_token: Token,
) -> UpdateStatus:
    """The UKF's update from the points through h, Z, and their state deviations D: ẑ, S,
    P_xz (into ``wu``), then :func:`kalman_update` and the factorisation of P⁺ into L.

    Returns:
        :data:`UpdateStatus`; P⁺ is not factorised (status 2) when S is not.
    """
    unscented_moments(Z, wu.zb, wu.S, r, wts, n_token, m_token)
    cross_covariance(D, Z, wu.Pxz, wts[2], n_token, m_token)
    st_s, nis, ldet = kalman_update(x, P, zk, wu, n_token, m_token)
    if st_s == 2:
        return st_s, nis, ldet, 2, 0.0
    st, jit = chol_repair(P, L, n_token)
    return st_s, nis, ldet, st, jit


@njit(cache=True, error_model="numpy")
def linearised_update(
    Hm: np.ndarray,
    zk: np.ndarray,
    r: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    wu: UpdateWork,
    n_token: Token,
    m_token: Token,
) -> UpdateStatus:
    """The EKF's update with H and ẑ = h(x̄) (already in ``wu.zb``):
    :func:`linearised_moments`, then as :func:`unscented_update`."""
    linearised_moments(P, Hm, wu.Pxz, wu.S, r, n_token, m_token)
    st_s, nis, ldet = kalman_update(x, P, zk, wu, n_token, m_token)
    if st_s == 2:
        return st_s, nis, ldet, 2, 0.0
    st, jit = chol_repair(P, L, n_token)
    return st_s, nis, ldet, st, jit


@njit(cache=True, inline="always", error_model="numpy")
def all_finite(x: np.ndarray, zh: np.ndarray, nis: float, n_token: Token, m_token: Token) -> bool:
    """x⁺, h(x⁺) and the NIS are finite."""
    ok = math.isfinite(nis)
    for j in range(len(n_token)):
        ok = ok and math.isfinite(x[j])
    for j in range(len(m_token)):
        ok = ok and math.isfinite(zh[j])
    return ok


@njit(cache=True, error_model="numpy")
def fill_nan(k0: int, out: KernelOutputs) -> None:
    """Rows k0… of every output are NaN."""
    ox, op, oz, oi, on, ol = out.x, out.P_diag, out.z_hat, out.innovation, out.nis, out.log_det_s
    for k in range(k0, ox.shape[0]):
        ox[k, :] = _NAN
        op[k, :] = _NAN
        oz[k, :] = _NAN
        oi[k, :] = _NAN
        on[k] = _NAN
        ol[k] = _NAN


@njit(cache=True, error_model="numpy")
def workspace(n_token: Token, m_token: Token, held_causes: np.ndarray, n_hold: int) -> Work:
    """The work arrays of a run (:class:`Work`), allocated here (cached) rather than in the
    kernels (whose every allocation would cost each process a compilation)."""
    n, m = len(n_token), len(m_token)
    ns = 2 * n + 1
    n_held = held_causes.shape[0]
    upd = UpdateWork(
        np.empty(m), np.empty((m, m)), np.empty((n, m)), np.zeros((m, m)), np.zeros((m, m)),
        np.empty((m, n)), np.empty(m), np.empty(m),
    )  # fmt: skip
    hold = Hold(
        np.zeros(n_held, dtype=np.bool_), np.zeros(n_held, dtype=np.int64), n_hold, held_causes
    )
    return Work(
        np.empty(n), np.empty((n, n)), np.empty((n, n)),
        np.empty((ns, n)), np.empty((ns, n)), np.empty((ns, n)), np.empty((ns, m)), np.empty(m),
        np.empty((n, n)), np.empty((n, n)), np.empty((m, n)),
        np.empty(n), np.empty(n), np.empty(n), np.empty(m), np.empty(m), upd, hold,
    )  # fmt: skip


@njit(cache=True, inline="always", error_model="numpy")
def conclude_step(
    k: int,
    status: UpdateStatus,
    cause: int,
    x: np.ndarray,
    P: np.ndarray,
    zh: np.ndarray,
    y: np.ndarray,
    hold: Hold,
    out: KernelOutputs,
    n_token: Token,
    m_token: Token,
) -> tuple[int, int, int]:
    """End step k of either filter: stop with ``cause`` (:func:`step_cause`), or count the
    held conditions, then store x⁺, diag P⁺ (repaired by its jitter when its status is 1),
    ẑ = h(x⁺) (zh), the innovation y, the NIS and log det S.

    Returns:
        (stop_step, cause, repairs): stop_step = −1 to go on, else the rows from stop_step
        (for a held condition the step where it began) are NaN; ``repairs`` counts the
        jittered factorisations of this step that count (as in the 3×3 kernel: P⁺'s only
        when the step is stored).
    """
    st_s, nis, ldet, st, jit = status
    if cause != STOP_NONE:
        fill_nan(k, out)
        return k, cause, 0 if st_s == 2 else st_s
    held, count, n_hold = hold.held, hold.held_for, hold.n_hold
    for j in range(count.shape[0]):
        count[j] = count[j] + 1 if held[j] else 0
    for j in range(count.shape[0]):
        if count[j] >= n_hold:
            k0 = k + 1 - n_hold
            fill_nan(k0, out)
            return k0, hold.causes[j], st_s
    n, m = len(n_token), len(m_token)
    if st == 1:
        for j in range(n):
            P[j, j] += jit
    for j in range(n):  # out's fields read at each use, not into locals: fewer refcounts
        out.x[k, j] = x[j]
        out.P_diag[k, j] = P[j, j]
    for j in range(m):
        out.innovation[k, j] = y[j]
        out.z_hat[k, j] = zh[j]
    out.nis[k] = nis
    out.log_det_s[k] = ldet
    return -1, STOP_NONE, st_s + st


# --------------------------------------------------------------------------------------
# The kernels (compiled once per model)
# --------------------------------------------------------------------------------------


@njit(error_model="numpy", inline="always")
def step_cause(
    h: Dispatcher,
    check: Dispatcher | None,
    status: UpdateStatus,
    x: np.ndarray,
    zh: np.ndarray,
    uk: np.ndarray,
    zk: np.ndarray,
    p: np.ndarray,
    held: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> int:
    """h(x⁺_k, u_k) into zh, and why the run stops at step k after its update:
    STOP_NUMERICAL where S or P⁺ was not factorised (statuses in ``status``) or x⁺, h(x⁺)
    or the NIS is not finite, else the model's check's cause (which also fills ``held``);
    STOP_NONE to go on."""
    st_s, nis, _, st, _ = status
    if st_s == 2:
        return STOP_NUMERICAL
    h(x, uk, p, zh)
    if st == 2 or not all_finite(x, zh, nis, n_token, m_token):
        return STOP_NUMERICAL
    return STOP_NONE if check is None else check(x, zk, uk, p, held)


@njit(error_model="numpy", inline="always")
def ukf_run(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    data: KernelData,
    w: SigmaWeights,
    out: KernelOutputs,
    n_token: Token,
    m_token: Token,
) -> tuple[int, int, int]:
    """Run the UKF over a whole manoeuvre (inputs already validated).

    Args:
        f, h, check: the model's compiled functions (:mod:`kftune.models.base`); check may
            be None (no model-specific validity).
        data: the run's data (:class:`~kftune.models.kernel_io.KernelData`, one setting:
            q (n,), r (m,), x_init (n,), P_init (n, n)).
        w: the sigma-point weights (:class:`~kftune.models.kernel_io.SigmaWeights`).
        out: (N, …) buffers the run fills (:class:`~kftune.models.kernel_io.KernelOutputs`).
        n_token, m_token: tuples of n and m zeros (module docstring).

    Returns:
        (stop_step, n_repairs, cause): stop_step = −1 and cause = STOP_NONE when the run
        completed; otherwise the first invalid step and its cause.
    """
    u, z, p, dt, q, r = data.u, data.z, data.p, data.dt, data.q, data.r
    n = len(n_token)
    ns = 2 * n + 1
    wk = workspace(n_token, m_token, data.held_causes, data.n_hold)
    x, P, L, X, D, Y, Z = wk.x, wk.P, wk.L, wk.X, wk.D, wk.Y, wk.Z
    zh, upd, hold = wk.zh, wk.upd, wk.hold
    y, held = upd.y, hold.held
    wts, c = (w.wm0, w.wc0, w.wi), w.c

    # the prior at step 0 is (x_init, P_init): factorised for the first sigma points
    st = prior(data.x_init, data.P_init, x, P, L, n_token)
    if st == 2:
        fill_nan(0, out)
        return 0, 0, STOP_NUMERICAL
    n_rep = st
    for k in range(u.shape[0]):
        if k > 0:
            # ---- predict k−1 → k with u[k−1]: x̄ = Σ W^m χ_i, P̄ = Σ W^c dχ dχᵀ + Q ----
            sigma_points(x, L, c, X, D, False, n_token)
            uk = u[k - 1]
            for i in range(ns):
                f(X[i], uk, p, dt, Y[i])
            st = predicted_moments(Y, x, P, L, q, wts, n_token)
            if st == 2:
                fill_nan(k, out)
                return k, n_rep, STOP_NUMERICAL
            n_rep += st
        # ---- update with z[k], h(·, u[k]); sigma points redrawn from (x̄, P̄); P⁺ is
        # factorised at once: repaired (or the run stopped) before it is stored, and the
        # factor is the next prediction's ----
        sigma_points(x, L, c, X, D, True, n_token)
        uk = u[k]
        for i in range(ns):
            h(X[i], uk, p, Z[i])
        status = unscented_update(Z, D, z[k], r, x, P, L, upd, wts, n_token, m_token)
        cause = step_cause(h, check, status, x, zh, uk, z[k], p, held, n_token, m_token)
        stop, cause, rep = conclude_step(k, status, cause, x, P, zh, y, hold, out, n_token, m_token)
        n_rep += rep
        if stop >= 0:
            return stop, n_rep, cause
    return -1, n_rep, STOP_NONE


@njit(error_model="numpy", inline="always")
def ekf_run(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    data: KernelData,
    out: KernelOutputs,
    n_token: Token,
    m_token: Token,
    F_way: Dispatcher,
    F_jac: Dispatcher,
    H_way: Dispatcher,
    H_jac: Dispatcher,
) -> tuple[int, int, int]:
    """Run the EKF over a whole manoeuvre (inputs already validated).

    Args are those of :func:`ukf_run` without the sigma-point weights, and:
        F_way, F_jac: :func:`given_process_jacobian` and the model's F, or
            :func:`numerical_process_jacobian` and anything (central differences of f);
        H_way, H_jac: the same for H. (Passing the way as a function, rather than a flag,
            makes numba compile only the way a run takes.)
    """
    u, z, p, dt, q, r = data.u, data.z, data.p, data.dt, data.q, data.r
    n = len(n_token)
    wk = workspace(n_token, m_token, data.held_causes, data.n_hold)
    x, P, L, T, Fm, Hm = wk.x, wk.P, wk.L, wk.T, wk.Fm, wk.Hm
    xw, fp, fm, hp, hm = wk.xw, wk.fp, wk.fm, wk.hp, wk.hm
    zh, upd, hold = wk.zh, wk.upd, wk.hold
    zb, y, held = upd.zb, upd.y, hold.held

    st = prior(data.x_init, data.P_init, x, P, L, n_token)
    if st == 2:
        fill_nan(0, out)
        return 0, 0, STOP_NUMERICAL
    n_rep = st
    for k in range(u.shape[0]):
        if k > 0:
            # ---- predict: F at x⁺_{k−1}; x̄ = f(x⁺, u[k−1]); P̄ = F·P·Fᵀ + Q ----
            uk = u[k - 1]
            F_way(F_jac, f, x, uk, p, dt, Fm, xw, fp, fm)
            f(x, uk, p, dt, xw)
            for j in range(n):
                x[j] = xw[j]
            linearised_prediction(Fm, P, T, q, n_token)
        # ---- update: H at x̄; ẑ = h(x̄, u[k]); P_xz = P̄·Hᵀ; S = H·P_xz + R ----
        uk = u[k]
        H_way(H_jac, h, x, uk, p, Hm, xw, hp, hm)
        h(x, uk, p, zb)
        status = linearised_update(Hm, z[k], r, x, P, L, upd, n_token, m_token)
        cause = step_cause(h, check, status, x, zh, uk, z[k], p, held, n_token, m_token)
        stop, cause, rep = conclude_step(k, status, cause, x, P, zh, y, hold, out, n_token, m_token)
        n_rep += rep
        if stop >= 0:
            return stop, n_rep, cause
    return -1, n_rep, STOP_NONE


# --------------------------------------------------------------------------------------
# Batches over noise settings (numba prange over B)
# --------------------------------------------------------------------------------------


@njit(cache=True, inline="always", error_model="numpy")
def setting(data: KernelData, b: int) -> KernelData:
    """Setting b's data of a batch's (q, r, x_init, P_init with a leading axis B; views)."""
    return KernelData(
        data.u, data.z, data.p, data.dt, data.q[b], data.r[b], data.x_init[b], data.P_init[b],
        data.n_hold, data.held_causes,
    )  # fmt: skip


@njit(cache=True, inline="always", error_model="numpy")
def outputs_at(out: KernelOutputs, b: int) -> KernelOutputs:
    """Setting b's buffers of a batch's (views; as :meth:`KernelOutputs.at`)."""
    return KernelOutputs(
        out.x[b], out.P_diag[b], out.z_hat[b], out.innovation[b], out.nis[b], out.log_det_s[b]
    )


@njit(parallel=True, error_model="numpy", inline="always")
def ukf_batch(
    single: Dispatcher,
    data: KernelData,
    w: SigmaWeights,
    out: KernelOutputs,
    stop: np.ndarray,
    rep: np.ndarray,
    cause: np.ndarray,
) -> None:
    """``single`` (a model's compiled :func:`ukf_run`, ``(data, w, out) -> (stop_step,
    n_repairs, cause)``) for B noise settings: data's q (B, n), r (B, m), x_init (B, n) and
    P_init (B, n, n) and every buffer of ``out`` carry a leading axis B; stop, rep and cause
    (B,) int64 get each run's results.

    ``single`` is called, not inlined: numba's parallel loop does not see that a record's
    array aliases the batch's buffers, and drops the writes of an inlined run into them as
    dead code (numba 0.68).
    """
    for b in prange(data.q.shape[0]):
        stop[b], rep[b], cause[b] = single(setting(data, b), w, outputs_at(out, b))


@njit(parallel=True, error_model="numpy", inline="always")
def ekf_batch(
    single: Dispatcher,
    data: KernelData,
    out: KernelOutputs,
    stop: np.ndarray,
    rep: np.ndarray,
    cause: np.ndarray,
) -> None:
    """``single`` (a model's compiled :func:`ekf_run`, ``(data, out)``) for B noise settings
    (shapes as :func:`ukf_batch`)."""
    for b in prange(data.q.shape[0]):
        stop[b], rep[b], cause[b] = single(setting(data, b), outputs_at(out, b))


# --------------------------------------------------------------------------------------
# The EKF's two ways to a Jacobian
# --------------------------------------------------------------------------------------


@njit(error_model="numpy", inline="always")
def given_process_jacobian(
    F: Dispatcher,
    f: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    dt: float,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = F(x, u, p, dt), the model's own Jacobian (f and the work arrays unused)."""
    F(x, u, p, dt, out)


@njit(error_model="numpy", inline="always")
def numerical_process_jacobian(
    F: Dispatcher,
    f: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    dt: float,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = ∂f/∂x by central differences (F unused; :mod:`kftune.models.jacobians`)."""
    fd_process_jacobian(f, x, u, p, dt, out, xw, gp, gm)


@njit(error_model="numpy", inline="always")
def given_measurement_jacobian(
    H: Dispatcher,
    h: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = H(x, u, p), the model's own Jacobian."""
    H(x, u, p, out)


@njit(error_model="numpy", inline="always")
def numerical_measurement_jacobian(
    H: Dispatcher,
    h: Dispatcher,
    x: np.ndarray,
    u: np.ndarray,
    p: np.ndarray,
    out: np.ndarray,
    xw: np.ndarray,
    gp: np.ndarray,
    gm: np.ndarray,
) -> None:
    """out = ∂h/∂x by central differences (H unused)."""
    fd_measurement_jacobian(h, x, u, p, out, xw, gp, gm)
