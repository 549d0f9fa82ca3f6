"""Compiled UKF and EKF kernels for any state-space model (numba).

Both filters share the time convention of :func:`kftune.filters.ukf.run_ukf` (step 0 updates
the prior with z[0]; step k ≥ 1 predicts with u[k−1] held, then updates with z[k] and
h(·, u[k])), the covariance repair, the stop causes and the NaN fill of
:mod:`kftune.filters._kernel`, and the measurement update, written with the Cholesky factor
of the innovation covariance S = L_S·L_Sᵀ instead of S⁻¹ (Simon, *Optimal State Estimation*,
2006, eqs. 13.48 and 14.80; Särkkä, *Bayesian Filtering and Smoothing*, 2013, Algs. 5.4 and
5.14, rearranged): with A = L_S⁻¹, W = A·P_xzᵀ and v = A·y,

    x⁺ = x̄ + Wᵀ·v,   P⁺ = P̄ − Wᵀ·W,   NIS = vᵀ·v.

They differ in the moments they hand to that update:

* UKF (Merwe scaled sigma points, Simon 2006 Sec. 14.3; Särkkä 2013 Alg. 5.14): sigma points
  of (x⁺, P⁺) through f give x̄, P̄ = Σ W^c·(χ − x̄)(χ − x̄)ᵀ + Q; points redrawn from (x̄, P̄)
  through h give ẑ, S = Σ W^c·(ζ − ẑ)(ζ − ẑ)ᵀ + R and P_xz = Σ W^c·(χ − x̄)(ζ − ẑ)ᵀ.
* EKF (Simon 2006 Sec. 13.2; Särkkä 2013 Alg. 5.4): x̄ = f(x⁺), P̄ = F·P⁺·Fᵀ + Q with F the
  Jacobian at x⁺; ẑ = h(x̄), P_xz = P̄·Hᵀ, S = H·P_xz + R with H the Jacobian at x̄. Jacobians are
  the model's own or central finite differences (:mod:`kftune.models.jacobians`).

The arithmetic of the UKF follows the 3×3 kernel operation by operation (the same Cholesky,
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
(:func:`ukf_run`, :func:`ekf_run` and their batches): numba compiles the kernels once per
model, calling the model's f and h directly. Every kernel that takes a function is inlined
(``inline="always"``) into the wrappers of a module generated per model
(:mod:`kftune.filters._compiled`), which name the model's functions as globals: numba can
cache those wrappers on disk, as it cannot cache a function that receives a function
value. The linear algebra lives in a few helpers without
function arguments, which are cached, with their own small helpers inlined into them
(``inline="always"``: a call costs about 30 ns, a tenth of a filter step's arithmetic at
n = 3). The sizes are compile-time constants: kernels and helpers take the state and
measurement sizes as tuples of n and m zeros (``n_token``, ``m_token``), whose lengths are
part of their numba types, so that LLVM unrolls the small loops and resolves every index
(for n = 3 the UKF is 1.6 times faster than with run-time sizes).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.core.dispatcher import Dispatcher

from kftune.filters._kernel import JITTER_MAX, JITTER_START
from kftune.models.base import STOP_NONE, STOP_NUMERICAL
from kftune.models.jacobians import fd_measurement_jacobian, fd_process_jacobian

_NAN = math.nan

Token = tuple[float, ...]


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
    wm0: float,
    wc0: float,
    wi: float,
    n_token: Token,
    k_token: Token,
) -> None:
    """mean = Σ W^m_i·Y_i; Y_i −= mean in place; cov = Σ W^c_i·d_i·d_iᵀ + diag(noise).

    Y: (2n+1, k) transformed sigma points (n = len(n_token), k = len(k_token)); mean: (k,);
    cov: (k, k) symmetric; noise: (k,) variances (Simon 2006 eqs. 14.59–14.60, 14.63–14.64).
    """
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
    x: np.ndarray,
    P: np.ndarray,
    zb: np.ndarray,
    S: np.ndarray,
    Pxz: np.ndarray,
    zk: np.ndarray,
    Ls: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    y: np.ndarray,
    v: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> tuple[int, float]:
    """Kalman update of (x, P) in place from ẑ (zb), S (with R), P_xz and z_k.

    Returns:
        (status of S's factorisation as :func:`chol_repair`, NIS); on status 2 (x, P) are
        untouched.
    """
    n, m = len(n_token), len(m_token)
    st, _ = chol_repair(S, Ls, m_token)
    if st == 2:
        return st, _NAN
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
    return st, nis


@njit(cache=True, error_model="numpy")
def predicted_moments(
    Y: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    q: np.ndarray,
    wm0: float,
    wc0: float,
    wi: float,
    n_token: Token,
) -> int:
    """The UKF's prediction from the points through f, Y: x̄, P̄ = UT(Y) + Q, factorised
    into L and repaired (jitter kept in P̄). Returns the status of :func:`chol_repair`."""
    unscented_moments(Y, x, P, q, wm0, wc0, wi, n_token, n_token)
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
    zb: np.ndarray,
    S: np.ndarray,
    Pxz: np.ndarray,
    Ls: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    y: np.ndarray,
    v: np.ndarray,
    wm0: float,
    wc0: float,
    wi: float,
    n_token: Token,
    m_token: Token,
) -> tuple[int, float, int, float]:
    """The UKF's update from the points through h, Z, and their state deviations D: ẑ, S,
    P_xz, then :func:`kalman_update` and the factorisation of P⁺ into L.

    Returns:
        (status of S, NIS, status of P⁺, its jitter), statuses as :func:`chol_repair`; P⁺ is
        not factorised (status 2) when S is not.
    """
    unscented_moments(Z, zb, S, r, wm0, wc0, wi, n_token, m_token)
    cross_covariance(D, Z, Pxz, wi, n_token, m_token)
    st_s, nis = kalman_update(x, P, zb, S, Pxz, zk, Ls, A, W, y, v, n_token, m_token)
    if st_s == 2:
        return st_s, nis, 2, 0.0
    st, jit = chol_repair(P, L, n_token)
    return st_s, nis, st, jit


@njit(cache=True, error_model="numpy")
def linearised_update(
    Hm: np.ndarray,
    zk: np.ndarray,
    r: np.ndarray,
    x: np.ndarray,
    P: np.ndarray,
    L: np.ndarray,
    zb: np.ndarray,
    S: np.ndarray,
    Pxz: np.ndarray,
    Ls: np.ndarray,
    A: np.ndarray,
    W: np.ndarray,
    y: np.ndarray,
    v: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> tuple[int, float, int, float]:
    """The EKF's update with H and ẑ = h(x̄) (zb): :func:`linearised_moments`, then as
    :func:`unscented_update`."""
    linearised_moments(P, Hm, Pxz, S, r, n_token, m_token)
    st_s, nis = kalman_update(x, P, zb, S, Pxz, zk, Ls, A, W, y, v, n_token, m_token)
    if st_s == 2:
        return st_s, nis, 2, 0.0
    st, jit = chol_repair(P, L, n_token)
    return st_s, nis, st, jit


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
def fill_nan(
    k0: int,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
) -> None:
    """Rows k0… of every output are NaN."""
    for k in range(k0, out_x.shape[0]):
        out_x[k, :] = _NAN
        out_p[k, :] = _NAN
        out_zhat[k, :] = _NAN
        out_innov[k, :] = _NAN
        out_nis[k] = _NAN
        out_ldet[k] = _NAN


@njit(cache=True, inline="always", error_model="numpy")
def commit(
    k: int,
    st: int,
    jit: float,
    x: np.ndarray,
    P: np.ndarray,
    y: np.ndarray,
    zh: np.ndarray,
    nis: float,
    ldet: float,
    held: np.ndarray,
    count: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> tuple[int, int]:
    """Count the held conditions of step k, then store its outputs (P⁺ repaired by ``jit``
    when ``st`` = 1).

    Returns:
        (stop_step, cause): (−1, STOP_NONE) to go on; otherwise the rows from stop_step (the
        step where the held condition began) are NaN.
    """
    for j in range(count.shape[0]):
        count[j] = count[j] + 1 if held[j] else 0
    for j in range(count.shape[0]):
        if count[j] >= n_hold:
            k0 = k + 1 - n_hold
            fill_nan(k0, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
            return k0, held_causes[j]
    n, m = len(n_token), len(m_token)
    if st == 1:
        for j in range(n):
            P[j, j] += jit
    for j in range(n):
        out_x[k, j] = x[j]
        out_p[k, j] = P[j, j]
    for j in range(m):
        out_innov[k, j] = y[j]
        out_zhat[k, j] = zh[j]
    out_nis[k] = nis
    out_ldet[k] = ldet
    return -1, STOP_NONE


@njit(cache=True, error_model="numpy")
def workspace(n_token: Token, m_token: Token, n_held: int) -> tuple[np.ndarray, ...]:
    """The work arrays of a run, allocated here (cached) rather than in the kernels (whose
    every allocation would cost each process a compilation).

    Returns:
        x (n,), P, L (n, n), X, D, Y (2n+1, n), Z (2n+1, m), zb (m,), S (m, m), P_xz (n, m),
        L_S, A (m, m) zeroed, W (m, n), y, v, zh (m,), T, F (n, n), H (m, n), xw, fp, fm (n,),
        hp, hm (m,), held (n_held,) bool and count (n_held,) int64, both zeroed.
    """
    n, m = len(n_token), len(m_token)
    ns = 2 * n + 1
    return (
        np.empty(n), np.empty((n, n)), np.empty((n, n)),
        np.empty((ns, n)), np.empty((ns, n)), np.empty((ns, n)), np.empty((ns, m)),
        np.empty(m), np.empty((m, m)), np.empty((n, m)), np.zeros((m, m)), np.zeros((m, m)),
        np.empty((m, n)), np.empty(m), np.empty(m), np.empty(m),
        np.empty((n, n)), np.empty((n, n)), np.empty((m, n)),
        np.empty(n), np.empty(n), np.empty(n), np.empty(m), np.empty(m),
        np.zeros(n_held, dtype=np.bool_), np.zeros(n_held, dtype=np.int64),
    )  # fmt: skip


# --------------------------------------------------------------------------------------
# The kernels (compiled once per model)
# --------------------------------------------------------------------------------------


@njit(error_model="numpy", inline="always")
def conclude_step(
    k: int,
    h: Dispatcher,
    check: Dispatcher | None,
    st_s: int,
    nis: float,
    Ls: np.ndarray,
    st: int,
    jit: float,
    x: np.ndarray,
    P: np.ndarray,
    y: np.ndarray,
    zh: np.ndarray,
    uk: np.ndarray,
    z: np.ndarray,
    p: np.ndarray,
    held: np.ndarray,
    count: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
    n_token: Token,
    m_token: Token,
) -> tuple[int, int, int]:
    """End step k of either filter after its update: the numerical checks (S and P⁺
    factorised with statuses st_s and st, finite x⁺, h(x⁺) and NIS), the model's check,
    the held conditions, then the outputs (:func:`commit`).

    Returns:
        (stop_step, cause, repairs): stop_step = −1 to go on; ``repairs`` counts the
        jittered factorisations of this step that count (as in the 3×3 kernel: P⁺'s only
        when the step is stored).
    """
    if st_s == 2:
        fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
        return k, STOP_NUMERICAL, 0
    h(x, uk, p, zh)
    if st == 2 or not all_finite(x, zh, nis, n_token, m_token):
        fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
        return k, STOP_NUMERICAL, st_s
    cause = STOP_NONE if check is None else check(x, z[k], uk, p, held)
    if cause != STOP_NONE:
        fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
        return k, cause, st_s
    ldet = 0.0  # log det S = 2·Σ log diag(L_S), with the NIS the innovation likelihood
    for i in range(len(m_token)):
        ldet += 2.0 * math.log(Ls[i, i])
    stop, cause = commit(
        k, st, jit, x, P, y, zh, nis, ldet, held, count, n_hold, held_causes,
        out_x, out_p, out_zhat, out_innov, out_nis, out_ldet, n_token, m_token,
    )  # fmt: skip
    if stop >= 0:
        return stop, cause, st_s
    return -1, STOP_NONE, st_s + st


@njit(error_model="numpy", inline="always")
def ukf_run(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    u: np.ndarray,
    z: np.ndarray,
    p: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    x_init: np.ndarray,
    P_init: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    n_token: Token,
    m_token: Token,
    wm0: float,
    wc0: float,
    wi: float,
    c: float,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
) -> tuple[int, int, int]:
    """Run the UKF over a whole manoeuvre (inputs already validated).

    Args:
        f, h, check: the model's compiled functions (:mod:`kftune.models.base`); check may
            be None (no model-specific validity).
        u: (N, n_w) prepared inputs; z: (N, m) measurements; p: (n_p,) parameters;
        dt: sample time [s].
        q: (n,) diagonal of Q; r: (m,) diagonal of R.
        x_init: (n,) prior mean at step 0; P_init: (n, n) prior covariance at step 0.
        n_hold: steps a held condition must last; held_causes: (n_held,) their causes.
        n_token, m_token: tuples of n and m zeros (module docstring).
        wm0, wc0, wi: sigma-point weights W_0^m, W_0^c, W_i; c: √(n + λ).
        out_x, out_p: (N, n) posterior state and diag P⁺; out_zhat, out_innov: (N, m)
            h(x⁺_k, u_k) and z_k − ẑ_k; out_nis, out_ldet: (N,) NIS and log det S.

    Returns:
        (stop_step, n_repairs, cause): stop_step = −1 and cause = STOP_NONE when the run
        completed; otherwise the first invalid step and its cause.
    """
    n = len(n_token)
    ns = 2 * n + 1
    (x, P, L, X, D, Y, Z, zb, S, Pxz, Ls, A, W, y, v, zh, _, _, _, _, _, _, _, _, held,
     count) = workspace(n_token, m_token, held_causes.shape[0])  # fmt: skip

    # the prior at step 0 is (x_init, P_init): factorised for the first sigma points
    st = prior(x_init, P_init, x, P, L, n_token)
    if st == 2:
        fill_nan(0, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
        return 0, 0, STOP_NUMERICAL
    n_rep = st
    for k in range(u.shape[0]):
        if k > 0:
            # ---- predict k−1 → k with u[k−1]: x̄ = Σ W^m χ_i, P̄ = Σ W^c dχ dχᵀ + Q ----
            sigma_points(x, L, c, X, D, False, n_token)
            uk = u[k - 1]
            for i in range(ns):
                f(X[i], uk, p, dt, Y[i])
            st = predicted_moments(Y, x, P, L, q, wm0, wc0, wi, n_token)
            if st == 2:
                fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
                return k, n_rep, STOP_NUMERICAL
            n_rep += st
        # ---- update with z[k], h(·, u[k]); sigma points redrawn from (x̄, P̄); P⁺ is
        # factorised at once: repaired (or the run stopped) before it is stored, and the
        # factor is the next prediction's ----
        sigma_points(x, L, c, X, D, True, n_token)
        uk = u[k]
        for i in range(ns):
            h(X[i], uk, p, Z[i])
        st_s, nis, st, jit = unscented_update(
            Z, D, z[k], r, x, P, L, zb, S, Pxz, Ls, A, W, y, v, wm0, wc0, wi, n_token, m_token
        )
        stop, cause, rep = conclude_step(
            k, h, check, st_s, nis, Ls, st, jit, x, P, y, zh, uk, z, p, held, count, n_hold,
            held_causes, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet, n_token, m_token,
        )  # fmt: skip
        n_rep += rep
        if stop >= 0:
            return stop, n_rep, cause
    return -1, n_rep, STOP_NONE


@njit(error_model="numpy", inline="always")
def ekf_run(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    u: np.ndarray,
    z: np.ndarray,
    p: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    x_init: np.ndarray,
    P_init: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    n_token: Token,
    m_token: Token,
    F_way: Dispatcher,
    F_jac: Dispatcher,
    H_way: Dispatcher,
    H_jac: Dispatcher,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
) -> tuple[int, int, int]:
    """Run the EKF over a whole manoeuvre (inputs already validated).

    Args are those of :func:`ukf_run` without the sigma-point weights, and:
        F_way, F_jac: :func:`given_process_jacobian` and the model's F, or
            :func:`numerical_process_jacobian` and anything (central differences of f);
        H_way, H_jac: the same for H. (Passing the way as a function, rather than a flag,
            makes numba compile only the way a run takes.)
    """
    n = len(n_token)
    (x, P, L, _, _, _, _, zb, S, Pxz, Ls, A, W, y, v, zh, T, Fm, Hm, xw, fp, fm, hp, hm, held,
     count) = workspace(n_token, m_token, held_causes.shape[0])  # fmt: skip

    st = prior(x_init, P_init, x, P, L, n_token)
    if st == 2:
        fill_nan(0, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
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
        st_s, nis, st, jit = linearised_update(
            Hm, z[k], r, x, P, L, zb, S, Pxz, Ls, A, W, y, v, n_token, m_token
        )
        stop, cause, rep = conclude_step(
            k, h, check, st_s, nis, Ls, st, jit, x, P, y, zh, uk, z, p, held, count, n_hold,
            held_causes, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet, n_token, m_token,
        )  # fmt: skip
        n_rep += rep
        if stop >= 0:
            return stop, n_rep, cause
    return -1, n_rep, STOP_NONE


# --------------------------------------------------------------------------------------
# Batches over noise settings (numba prange over B)
# --------------------------------------------------------------------------------------


@njit(parallel=True, error_model="numpy", inline="always")
def ukf_batch(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    u: np.ndarray,
    z: np.ndarray,
    p: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    x_init: np.ndarray,
    P_init: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    n_token: Token,
    m_token: Token,
    wm0: float,
    wc0: float,
    wi: float,
    c: float,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
    out_stop: np.ndarray,
    out_rep: np.ndarray,
    out_cause: np.ndarray,
) -> None:
    """:func:`ukf_run` for B noise settings: q (B, n), r (B, m), x_init (B, n), P_init
    (B, n, n); outputs with a leading B axis; out_stop, out_rep, out_cause (B,) int64."""
    for b in prange(q.shape[0]):
        out_stop[b], out_rep[b], out_cause[b] = ukf_run(
            f, h, check, u, z, p, dt, q[b], r[b], x_init[b], P_init[b], n_hold, held_causes,
            n_token, m_token, wm0, wc0, wi, c,
            out_x[b], out_p[b], out_zhat[b], out_innov[b], out_nis[b], out_ldet[b],
        )  # fmt: skip


@njit(parallel=True, error_model="numpy", inline="always")
def ekf_batch(
    f: Dispatcher,
    h: Dispatcher,
    check: Dispatcher | None,
    u: np.ndarray,
    z: np.ndarray,
    p: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    x_init: np.ndarray,
    P_init: np.ndarray,
    n_hold: int,
    held_causes: np.ndarray,
    n_token: Token,
    m_token: Token,
    F_way: Dispatcher,
    F_jac: Dispatcher,
    H_way: Dispatcher,
    H_jac: Dispatcher,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
    out_stop: np.ndarray,
    out_rep: np.ndarray,
    out_cause: np.ndarray,
) -> None:
    """:func:`ekf_run` for B noise settings (shapes as :func:`ukf_batch`)."""
    for b in prange(q.shape[0]):
        out_stop[b], out_rep[b], out_cause[b] = ekf_run(
            f, h, check, u, z, p, dt, q[b], r[b], x_init[b], P_init[b], n_hold, held_causes,
            n_token, m_token, F_way, F_jac, H_way, H_jac,
            out_x[b], out_p[b], out_zhat[b], out_innov[b], out_nis[b], out_ldet[b],
        )  # fmt: skip


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
