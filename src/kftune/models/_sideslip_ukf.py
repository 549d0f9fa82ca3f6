"""The single-track model's own UKF loop: three states and three measurements (numba).

The maths is that of the generic UKF (:mod:`kftune.filters._generic_kernel`), written out
for n = 3 with scalars so that the step loop allocates nothing:

* covariances are kept as their six upper-triangle entries (symmetric by construction —
  the "symmetrise" part of the covariance repair is structural);
* Cholesky factors are closed-form 3×3 (L = [[l00,0,0],[l10,l11,0],[l20,l21,l22]]);
* the update avoids forming S⁻¹ and K: with S = L_S·L_Sᵀ, A = L_S⁻¹ (closed-form
  triangular inverse), W = A·P_xzᵀ and v = A·y,
      x⁺ = x̄ + Wᵀ·v            (= x̄ + P_xz·S⁻¹·y = x̄ + K·y)
      P⁺ = P̄ − Wᵀ·W            (= P̄ − P_xz·S⁻¹·P_xzᵀ = P̄ − K·S·Kᵀ)
      NIS = vᵀ·v               (= yᵀ·S⁻¹·y)
      log det S = 2·Σ log diag(L_S)  (with NIS, the innovation log-likelihood)
  (the UKF measurement update of Simon, *Optimal State Estimation*, 2006, Ch. 14, and
  Särkkä, *Bayesian Filtering and Smoothing*, 2013, Ch. 5, rearranged.)

Covariance repair: every covariance the filter factorises (P⁺ after each update, the
predicted P̄ before the sigma points are redrawn, the innovation covariance S) goes through
:func:`chol3_repair`. If the Cholesky factorisation fails, a jitter of 10⁻¹²·max(diag),
growing tenfold per try up to 10⁻⁶·max(diag), is added to the diagonal (and kept). If that
fails too, or the state, the covariance, the NIS or the estimated measurement stops being
finite, or (single-track model) the estimated Vx is not > 0, the run has diverged: the
kernel returns that step and a cause (``STOP_*``), and fills the remaining output rows with
NaN. It never raises.

Runaway: the single-track model's rule (:func:`kftune.models._runaway.runaway`, the one
place it is written), counted over ``n_hold`` steps as the generic filters count the
model's held conditions. On the bundled data and revs-250lm no manual or tuned filter
comes near its bounds (|β⁺| ≤ 10°, Vx⁺ within 10 % of the measurement), while
Q = diag(1e9, 1e9, 1e9) trips the 60° bound at the first prediction.

This is the loop the single-track model supplies for itself
(:func:`kftune.models.sideslip.single_track_kernels`): the generic UKF
(:class:`kftune.filters.UKF`) runs it behind its own interface for that model, and its
results equal the generic loop's (tests/test_model_kernels.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from kftune.models._runaway import STOP_SIDESLIP_HELD, STOP_SPEED, runaway
from kftune.models.base import STOP_NONE, STOP_NUMERICAL
from kftune.models.kernel_io import (
    JITTER_MAX,
    JITTER_START,
    KernelData,
    KernelOutputs,
    SigmaWeights,
)
from kftune.vehicle.single_track import (
    measure_scalar,
    rk4_scalar,
)

# Why a run stopped (the third value :func:`run_kernel` returns), STOP_*: the generic causes
# (kftune.models.base) and the single-track model's (kftune.models._runaway), imported above.

_NAN = math.nan


@njit(cache=True, error_model="numpy")
def chol3(
    p00: float, p01: float, p02: float, p11: float, p12: float, p22: float
) -> tuple[bool, float, float, float, float, float, float]:
    """Closed-form Cholesky of a symmetric 3×3 matrix from its upper triangle.

    Returns:
        (ok, l00, l10, l11, l20, l21, l22); ok is False when a pivot is not > 0 (or NaN).
    """
    if not (p00 > 0.0 and p00 < math.inf):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    l00 = math.sqrt(p00)
    l10 = p01 / l00
    l20 = p02 / l00
    d1 = p11 - l10 * l10
    if not (d1 > 0.0 and d1 < math.inf):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    l11 = math.sqrt(d1)
    l21 = (p12 - l20 * l10) / l11
    d2 = p22 - l20 * l20 - l21 * l21
    if not (d2 > 0.0 and d2 < math.inf):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return True, l00, l10, l11, l20, l21, math.sqrt(d2)


@njit(cache=True, error_model="numpy")
def chol3_repair(
    p00: float, p01: float, p02: float, p11: float, p12: float, p22: float
) -> tuple[int, float, float, float, float, float, float, float]:
    """Cholesky with jitter escalation.

    Returns:
        (status, l00, l10, l11, l20, l21, l22, jitter): status 0 = factorised as is,
        1 = factorised after adding ``jitter`` to the diagonal, 2 = failed (not repairable).
    """
    ok, l00, l10, l11, l20, l21, l22 = chol3(p00, p01, p02, p11, p12, p22)
    if ok:
        return 0, l00, l10, l11, l20, l21, l22, 0.0
    scale = max(p00, p11, p22)
    finite = (
        math.isfinite(p00)
        and math.isfinite(p01)
        and math.isfinite(p02)
        and math.isfinite(p11)
        and math.isfinite(p12)
        and math.isfinite(p22)
    )
    if finite and scale > 0.0:
        jitter = JITTER_START * scale
        # (0 < jitter: a subnormal scale underflows the jitter to 0, which never grows)
        while 0.0 < jitter <= JITTER_MAX * scale * 1.0000001:
            ok, l00, l10, l11, l20, l21, l22 = chol3(
                p00 + jitter, p01, p02, p11 + jitter, p12, p22 + jitter
            )
            if ok:
                return 1, l00, l10, l11, l20, l21, l22, jitter
            jitter *= 10.0
    return 2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy")
def _fill_nan(
    k0: int,
    out_x: np.ndarray,
    out_p: np.ndarray,
    out_zhat: np.ndarray,
    out_innov: np.ndarray,
    out_nis: np.ndarray,
    out_ldet: np.ndarray,
) -> None:
    for k in range(k0, out_x.shape[0]):
        for j in range(3):
            out_x[k, j] = _NAN
            out_p[k, j] = _NAN
            out_zhat[k, j] = _NAN
            out_innov[k, j] = _NAN
        out_nis[k] = _NAN
        out_ldet[k] = _NAN


@njit(cache=True, error_model="numpy")
def run_kernel(data: KernelData, w: SigmaWeights, out: KernelOutputs) -> tuple[int, int, int]:
    """Run the UKF over a whole manoeuvre (inputs already validated by the filter).

    Time convention (:mod:`kftune.filters.generic`): step 0 updates the prior
    (x_init, P_init) with z[0]; step k ≥ 1 predicts from k−1 to k with u[k−1] held, then
    updates with z[k] using h(·, u[k]).

    Args:
        data: the run (:class:`~kftune.models.kernel_io.KernelData`): u (N, 6) the
            single-track model's prepared rows [δ rad, ax m/s², tan δ, cos δ, Fz_f N,
            Fz_r N] (:func:`kftune.models.sideslip.prepare`), z (N, 3) [Vx, ay, r], p the
            packed (9,) vehicle array, q and r (3,), x_init (3,), P_init (3, 3), n_hold
            the steps a runaway must be held.
        w: the sigma-point weights. out: (N, 3) and (N,) output buffers.

    Returns:
        (diverged_step, n_repairs, cause): diverged_step = −1 and cause = STOP_NONE when
        the run completed; otherwise the first invalid step and a ``STOP_*`` code.
    """
    u, z, mp, dt, q, r = data.u, data.z, data.p, data.dt, data.q, data.r
    x_init, P_init, n_hold = data.x_init, data.P_init, data.n_hold
    wm0, wc0, wi, c = w.wm0, w.wc0, w.wi, w.c
    out_x, out_p, out_zhat, out_innov = out.x, out.P_diag, out.z_hat, out.innovation
    out_nis, out_ldet = out.nis, out.log_det_s
    n_steps = u.shape[0]
    sx = np.empty((7, 3))  # sigma points (state)
    sz = np.empty((7, 3))  # sigma points (measurement)
    n_rep = 0
    held_beta = 0  # consecutive steps with |β⁺| > MAX_SIDESLIP
    held_vx = 0  # consecutive steps with Vx⁺ off the measurement by > RUNAWAY_VX

    x0 = x_init[0]
    x1 = x_init[1]
    x2 = x_init[2]
    p00 = P_init[0, 0]
    p01 = 0.5 * (P_init[0, 1] + P_init[1, 0])
    p02 = 0.5 * (P_init[0, 2] + P_init[2, 0])
    p11 = P_init[1, 1]
    p12 = 0.5 * (P_init[1, 2] + P_init[2, 1])
    p22 = P_init[2, 2]
    # Prior at step 0 is (x_init, P_init): factorise it for the first sigma points.
    st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(p00, p01, p02, p11, p12, p22)
    if st == 2:
        _fill_nan(0, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
        return 0, n_rep, STOP_NUMERICAL
    if st == 1:
        n_rep += 1
        p00 += jit
        p11 += jit
        p22 += jit

    for k in range(n_steps):
        if k > 0:
            # ---- predict k−1 → k with u[k−1] (sigma points of the posterior at k−1) ----
            e0, e1, e2, e3 = u[k - 1, 2], u[k - 1, 3], u[k - 1, 4], u[k - 1, 5]
            ax = u[k - 1, 1]
            a0 = c * l00
            a1 = c * l10
            a2 = c * l20
            b1 = c * l11
            b2 = c * l21
            d2 = c * l22
            # columns of c·L: (a0, a1, a2), (0, b1, b2), (0, 0, d2)
            sx[0, 0], sx[0, 1], sx[0, 2] = rk4_scalar(x0, x1, x2, e0, e1, ax, e2, e3, mp, dt)
            sx[1, 0], sx[1, 1], sx[1, 2] = rk4_scalar(
                x0 + a0, x1 + a1, x2 + a2, e0, e1, ax, e2, e3, mp, dt
            )
            sx[2, 0], sx[2, 1], sx[2, 2] = rk4_scalar(
                x0, x1 + b1, x2 + b2, e0, e1, ax, e2, e3, mp, dt
            )
            sx[3, 0], sx[3, 1], sx[3, 2] = rk4_scalar(x0, x1, x2 + d2, e0, e1, ax, e2, e3, mp, dt)
            sx[4, 0], sx[4, 1], sx[4, 2] = rk4_scalar(
                x0 - a0, x1 - a1, x2 - a2, e0, e1, ax, e2, e3, mp, dt
            )
            sx[5, 0], sx[5, 1], sx[5, 2] = rk4_scalar(
                x0, x1 - b1, x2 - b2, e0, e1, ax, e2, e3, mp, dt
            )
            sx[6, 0], sx[6, 1], sx[6, 2] = rk4_scalar(x0, x1, x2 - d2, e0, e1, ax, e2, e3, mp, dt)
            # unscented transform: x̄ = Σ W^m χ_i,  P̄ = Σ W^c (χ_i − x̄)(χ_i − x̄)ᵀ + Q
            x0 = wm0 * sx[0, 0]
            x1 = wm0 * sx[0, 1]
            x2 = wm0 * sx[0, 2]
            for i in range(1, 7):
                x0 += wi * sx[i, 0]
                x1 += wi * sx[i, 1]
                x2 += wi * sx[i, 2]
            d0 = sx[0, 0] - x0
            d1 = sx[0, 1] - x1
            dd2 = sx[0, 2] - x2
            p00 = wc0 * d0 * d0
            p01 = wc0 * d0 * d1
            p02 = wc0 * d0 * dd2
            p11 = wc0 * d1 * d1
            p12 = wc0 * d1 * dd2
            p22 = wc0 * dd2 * dd2
            for i in range(1, 7):
                d0 = sx[i, 0] - x0
                d1 = sx[i, 1] - x1
                dd2 = sx[i, 2] - x2
                p00 += wi * d0 * d0
                p01 += wi * d0 * d1
                p02 += wi * d0 * dd2
                p11 += wi * d1 * d1
                p12 += wi * d1 * dd2
                p22 += wi * dd2 * dd2
            p00 += q[0]
            p11 += q[1]
            p22 += q[2]
            st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(p00, p01, p02, p11, p12, p22)
            if st == 2:
                _fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
                return k, n_rep, STOP_NUMERICAL
            if st == 1:
                n_rep += 1
                p00 += jit
                p11 += jit
                p22 += jit

        # ---- update with z[k], h(·, u[k]); sigma points redrawn from (x̄, P̄) ----
        e0, e1, e2, e3 = u[k, 2], u[k, 3], u[k, 4], u[k, 5]
        a0 = c * l00
        a1 = c * l10
        a2 = c * l20
        b1 = c * l11
        b2 = c * l21
        d2 = c * l22
        sx[0, 0], sx[0, 1], sx[0, 2] = 0.0, 0.0, 0.0  # deviations χ_i − x̄
        sx[1, 0], sx[1, 1], sx[1, 2] = a0, a1, a2
        sx[2, 0], sx[2, 1], sx[2, 2] = 0.0, b1, b2
        sx[3, 0], sx[3, 1], sx[3, 2] = 0.0, 0.0, d2
        for i in range(1, 4):
            sx[i + 3, 0] = -sx[i, 0]
            sx[i + 3, 1] = -sx[i, 1]
            sx[i + 3, 2] = -sx[i, 2]
        for i in range(7):
            sz[i, 0], sz[i, 1], sz[i, 2] = measure_scalar(
                x0 + sx[i, 0], x1 + sx[i, 1], x2 + sx[i, 2], e0, e1, e2, e3, mp
            )
        z0 = wm0 * sz[0, 0]
        z1 = wm0 * sz[0, 1]
        z2 = wm0 * sz[0, 2]
        for i in range(1, 7):
            z0 += wi * sz[i, 0]
            z1 += wi * sz[i, 1]
            z2 += wi * sz[i, 2]
        # S = Σ W^c dz dzᵀ + R;  P_xz = Σ W^c dx dzᵀ (dx_0 = 0)
        f0 = sz[0, 0] - z0
        f1 = sz[0, 1] - z1
        f2 = sz[0, 2] - z2
        s00 = wc0 * f0 * f0
        s01 = wc0 * f0 * f1
        s02 = wc0 * f0 * f2
        s11 = wc0 * f1 * f1
        s12 = wc0 * f1 * f2
        s22 = wc0 * f2 * f2
        c00 = c01 = c02 = c10 = c11 = c12 = c20 = c21 = c22 = 0.0
        for i in range(1, 7):
            f0 = sz[i, 0] - z0
            f1 = sz[i, 1] - z1
            f2 = sz[i, 2] - z2
            s00 += wi * f0 * f0
            s01 += wi * f0 * f1
            s02 += wi * f0 * f2
            s11 += wi * f1 * f1
            s12 += wi * f1 * f2
            s22 += wi * f2 * f2
            g0 = wi * sx[i, 0]
            g1 = wi * sx[i, 1]
            g2 = wi * sx[i, 2]
            c00 += g0 * f0
            c01 += g0 * f1
            c02 += g0 * f2
            c10 += g1 * f0
            c11 += g1 * f1
            c12 += g1 * f2
            c20 += g2 * f0
            c21 += g2 * f1
            c22 += g2 * f2
        s00 += r[0]
        s11 += r[1]
        s22 += r[2]
        st, m00, m10, m11, m20, m21, m22, jit = chol3_repair(s00, s01, s02, s11, s12, s22)
        if st == 2:
            _fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
            return k, n_rep, STOP_NUMERICAL
        if st == 1:
            n_rep += 1
        # A = L_S⁻¹ (lower triangular)
        i00 = 1.0 / m00
        i11 = 1.0 / m11
        i22 = 1.0 / m22
        i10 = -m10 * i00 * i11
        i21 = -m21 * i11 * i22
        i20 = -(m20 * i00 + m21 * i10) * i22
        # W = A·P_xzᵀ: W[i][j] = Σ_m A[i][m]·P_xz[j][m]
        w00 = i00 * c00
        w01 = i00 * c10
        w02 = i00 * c20
        w10 = i10 * c00 + i11 * c01
        w11 = i10 * c10 + i11 * c11
        w12 = i10 * c20 + i11 * c21
        w20 = i20 * c00 + i21 * c01 + i22 * c02
        w21 = i20 * c10 + i21 * c11 + i22 * c12
        w22 = i20 * c20 + i21 * c21 + i22 * c22
        y0 = z[k, 0] - z0
        y1 = z[k, 1] - z1
        y2 = z[k, 2] - z2
        v0 = i00 * y0
        v1 = i10 * y0 + i11 * y1
        v2 = i20 * y0 + i21 * y1 + i22 * y2
        x0 += w00 * v0 + w10 * v1 + w20 * v2
        x1 += w01 * v0 + w11 * v1 + w21 * v2
        x2 += w02 * v0 + w12 * v1 + w22 * v2
        p00 -= w00 * w00 + w10 * w10 + w20 * w20
        p01 -= w00 * w01 + w10 * w11 + w20 * w21
        p02 -= w00 * w02 + w10 * w12 + w20 * w22
        p11 -= w01 * w01 + w11 * w11 + w21 * w21
        p12 -= w01 * w02 + w11 * w12 + w21 * w22
        p22 -= w02 * w02 + w12 * w12 + w22 * w22
        # factorise P⁺ now: it is repaired (or the run declared diverged) before it is
        # stored, and the factor is reused by the next prediction.
        st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(p00, p01, p02, p11, p12, p22)
        nis = v0 * v0 + v1 * v1 + v2 * v2
        h0, h1, h2 = measure_scalar(x0, x1, x2, e0, e1, e2, e3, mp)
        if (
            st == 2
            or not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2))
            or not (math.isfinite(nis) and math.isfinite(h1))
        ):
            _fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
            return k, n_rep, STOP_NUMERICAL
        cause, beyond, off = runaway(x0, x1, z[k, 0])
        if cause != 0:
            _fill_nan(k, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
            return k, n_rep, cause
        held_beta = held_beta + 1 if beyond else 0
        held_vx = held_vx + 1 if off else 0
        if held_beta >= n_hold or held_vx >= n_hold:
            k0 = k + 1 - n_hold  # the runaway started there
            _fill_nan(k0, out_x, out_p, out_zhat, out_innov, out_nis, out_ldet)
            return k0, n_rep, STOP_SIDESLIP_HELD if held_beta >= n_hold else STOP_SPEED
        if st == 1:
            n_rep += 1
            p00 += jit
            p11 += jit
            p22 += jit
        out_x[k, 0] = x0
        out_x[k, 1] = x1
        out_x[k, 2] = x2
        out_p[k, 0] = p00
        out_p[k, 1] = p11
        out_p[k, 2] = p22
        out_innov[k, 0] = y0
        out_innov[k, 1] = y1
        out_innov[k, 2] = y2
        out_nis[k] = nis
        out_ldet[k] = 2.0 * (math.log(m00) + math.log(m11) + math.log(m22))
        out_zhat[k, 0] = h0
        out_zhat[k, 1] = h1
        out_zhat[k, 2] = h2
    return -1, n_rep, STOP_NONE


@njit(cache=True, parallel=True, error_model="numpy")
def run_kernel_batch(
    data: KernelData,
    w: SigmaWeights,
    out: KernelOutputs,
    out_div: np.ndarray,
    out_rep: np.ndarray,
    out_cause: np.ndarray,
) -> None:
    """:func:`run_kernel` for B noise settings in parallel (numba prange over B).

    data's q, r, x_init (B, 3) and P_init (B, 3, 3) and every buffer of ``out`` carry a
    leading B axis; out_div, out_rep, out_cause: (B,) int64.
    """
    for b in prange(data.q.shape[0]):
        one = KernelData(
            data.u, data.z, data.p, data.dt, data.q[b], data.r[b], data.x_init[b],
            data.P_init[b], data.n_hold, data.held_causes,
        )  # fmt: skip
        buffers = KernelOutputs(
            out.x[b], out.P_diag[b], out.z_hat[b], out.innovation[b], out.nis[b],
            out.log_det_s[b],
        )  # fmt: skip
        d, nr, why = run_kernel(one, w, buffers)
        out_div[b] = d
        out_rep[b] = nr
        out_cause[b] = why
