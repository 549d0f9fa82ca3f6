"""The single-track model's vector-lane UKF loop: B noise settings over one manoeuvre, SIMD
across the sets.

The maths is that of :func:`kftune.models._sideslip_ukf.run_kernel` (the 3×3 single-track UKF
with closed-form Cholesky and covariance repair) with the same floating-point operations
in the same order for every set, so each set's result equals ``run_kernel``'s bit for bit
(the tests ask ≤ 1e-12 relative; no fast-math, so the compiler may not reorder).

What differs is the arrangement (structure of arrays): the per-set state lives in one flat
array of blocks of ``LANES`` = 8 sets; a block holds one row per scalar (x̄, the six
entries of P and of its Cholesky factor L, …), and a row holds the 8 sets ("lanes")
contiguously. Each time step is a few loops over the blocks whose innermost loop runs over
the 8 lanes of a block, so that the compiler's loop vectoriser puts 4 sets into one AVX2
register (8 into one AVX-512 register):

1. predict (k ≥ 1): 7 sigma points from (x⁺, L⁺), one RK4 step each, the unscented
   transform x̄ = Σ Wᵐ χ_i, P̄ = Σ Wᶜ (χ_i − x̄)(χ_i − x̄)ᵀ + Q, and the plain Cholesky of P̄
   (:func:`~kftune.models._sideslip_ukf.chol3`) with a per-lane success flag;
2. the lanes whose P̄ did not factorise go through
   :func:`~kftune.models._sideslip_ukf.chol3_repair` one by one (jitter escalation; rare);
3. update: the sigma points redrawn from (x̄, L̄), h at each, S, P_xz, chol(S), the
   update x⁺ = x̄ + Wᵀv, P⁺ = P̄ − WᵀW (W = L_S⁻¹P_xzᵀ, v = L_S⁻¹y; see ``_sideslip_ukf``) and
   chol(P⁺), with success flags;
4. per lane (scalar, cheap): a lane whose S or P⁺ did not factorise redoes its update with
   the repairing factorisation; then the divergence and runaway checks of ``run_kernel``
   and the output rows.

The vector loops contain no calls the compiler cannot inline and no loop-carried
dependence; branches (the Dugoff saturation, the Cholesky pivots) become selects. The
rows of a block are the compile-time constant ``LANES`` elements apart, so LLVM proves
that they do not overlap and needs no run-time overlap checks (with rows of a run-time
stride it guarded every loop with checks of its ~50 rows and gained only ~1.4–2× at
B = 8). The inner loop's trip count is the block view's length over ``NROWS`` — equal to
``LANES`` but not known to LLVM at compile time: with a constant trip count LLVM unrolls
the 8 iterations fully, and numba leaves the SLP vectoriser off, so nothing is vectorised.

A set that diverges is retired: its lane is swapped with the last active one (compaction),
so the loops keep running over active sets only and a diverged set's NaN or inf can reach
no other set (lanes never mix; the swap moves whole columns). Its output rows from the
diverged step on are NaN, as in ``run_kernel``. The kernel never raises.

The single-track model supplies it for batches
(:func:`kftune.models.sideslip.single_track_kernels`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from kftune.models._runaway import STOP_SIDESLIP_HELD, STOP_SPEED, runaway
from kftune.models._sideslip_ukf import chol3, chol3_repair
from kftune.models.base import STOP_NONE, STOP_NUMERICAL
from kftune.models.kernel_io import KernelData, KernelOutputs, SigmaWeights
from kftune.vehicle.single_track import (
    measure_scalar,
    rk4_scalar,
)

#: Lanes per block: the vector loops run over blocks of this many sets (8 doubles: two
#: AVX2 registers or one AVX-512 register); rows a constant LANES apart need no run-time
#: overlap checks, and a multiple of the vector width leaves no scalar remainder.
LANES = 8

#: Small fixed-size groups of scalars passed between the compiled helpers as tuples (numba
#: keeps them in registers): a 3-vector, the upper triangle of a symmetric 3×3 matrix
#: (00, 01, 02, 11, 12, 22) or its Cholesky factor's lower one (00, 10, 11, 20, 21, 22), a
#: full 3×3 matrix by rows, and a step's input-only quantities (tan δ, cos δ, Fz_f, Fz_r).
Vec3 = tuple[float, float, float]
Sym3 = tuple[float, float, float, float, float, float]
Mat3 = tuple[float, float, float, float, float, float, float, float, float]
Context = tuple[float, float, float, float]


def _rows(first: int, count: int) -> tuple[int, ...]:
    """Offsets of ``count`` consecutive rows from row ``first`` within a block."""
    return tuple((first + i) * LANES for i in range(count))


# Rows of a block: row r of lane l of block b is s[b·BLOCK + r·LANES + l]; the names below
# are the offsets r·LANES. Posterior (after the update of step k): state, covariance, factor.
X0, X1, X2 = _rows(0, 3)
P00, P01, P02, P11, P12, P22 = _rows(3, 6)
L00, L10, L11, L20, L21, L22 = _rows(9, 6)
# Predicted (after the prediction to step k): state, covariance, factor.
XB0, XB1, XB2 = _rows(15, 3)
PB00, PB01, PB02, PB11, PB12, PB22 = _rows(18, 6)
LB00, LB10, LB11, LB20, LB21, LB22 = _rows(24, 6)
# Noise diagonals.
Q0, Q1, Q2, R0, R1, R2 = _rows(30, 6)
# Update by-products: innovation, NIS, h(x⁺, u), and the success flags (1.0 = factorised).
Y0, Y1, Y2, NIS, H0, H1, H2, OK_P, OK_S, OK_PB = _rows(36, 10)
NROWS = 46
BLOCK = NROWS * LANES

_NAN = math.nan


@njit(cache=True, error_model="numpy")
def _centre_and_spread(
    s: np.ndarray, j: int, x_row: int, l_row: int, c: float
) -> tuple[float, float, float, float, float, float, float, float, float]:
    """Lane j's state x (rows from ``x_row``: X0 or XB0) and the columns of c·L (rows from
    ``l_row``: L00 or LB00, in the order L00, L10, L11, L20, L21, L22): the sigma points
    are x and x ± those columns. Returns (x0, x1, x2, c·L00, c·L10, c·L20, c·L11, c·L21,
    c·L22)."""
    return (
        s[x_row + j],
        s[x_row + LANES + j],
        s[x_row + 2 * LANES + j],
        c * s[l_row + j],
        c * s[l_row + LANES + j],
        c * s[l_row + 3 * LANES + j],
        c * s[l_row + 2 * LANES + j],
        c * s[l_row + 4 * LANES + j],
        c * s[l_row + 5 * LANES + j],
    )


@njit(cache=True, error_model="numpy")
def _predict_lanes(
    lanes: np.ndarray,
    n_blocks: int,
    mp: np.ndarray,
    dt: float,
    ctx: Context,
    ax: float,
    w: SigmaWeights,
) -> None:
    """Step 1 for the lanes of blocks [0, n_blocks): (x⁺, L⁺) → (x̄, P̄, chol P̄, ok).

    Simon 2006, Eq. 14.59–14.60. ``lanes``: the flat lane array (see the module docstring).
    ctx: (tan δ, cos δ, Fz_f, Fz_r) of u[k−1]; ax: u[k−1, 1] [m/s²].
    """
    e0, e1, e2, e3 = ctx
    wm0, wc0, wi, c = w
    for blk in range(n_blocks):
        s = lanes[blk * BLOCK : (blk + 1) * BLOCK]
        for j in range(s.size // NROWS):  # LANES, but unknown to LLVM: it must not unroll
            x0, x1, x2, a0, a1, a2, b1, b2, d2 = _centre_and_spread(s, j, X0, L00, c)
            # the seven propagated sigma points, in run_kernel's order
            f00, f01, f02 = rk4_scalar(x0, x1, x2, e0, e1, ax, e2, e3, mp, dt)
            f10, f11, f12 = rk4_scalar(x0 + a0, x1 + a1, x2 + a2, e0, e1, ax, e2, e3, mp, dt)
            f20, f21, f22 = rk4_scalar(x0, x1 + b1, x2 + b2, e0, e1, ax, e2, e3, mp, dt)
            f30, f31, f32 = rk4_scalar(x0, x1, x2 + d2, e0, e1, ax, e2, e3, mp, dt)
            f40, f41, f42 = rk4_scalar(x0 - a0, x1 - a1, x2 - a2, e0, e1, ax, e2, e3, mp, dt)
            f50, f51, f52 = rk4_scalar(x0, x1 - b1, x2 - b2, e0, e1, ax, e2, e3, mp, dt)
            f60, f61, f62 = rk4_scalar(x0, x1, x2 - d2, e0, e1, ax, e2, e3, mp, dt)
            # x̄ = W0ᵐ χ0 + Σ_{i≥1} Wᵢ χi, summed in run_kernel's order
            m0, m1, m2 = _mean7(
                wm0, wi, (f00, f01, f02), (f10, f11, f12), (f20, f21, f22), (f30, f31, f32),
                (f40, f41, f42), (f50, f51, f52), (f60, f61, f62),
            )  # fmt: skip
            # P̄ = W0ᶜ d0 d0ᵀ + Σ Wᵢ dᵢ dᵢᵀ + Q
            d0 = f00 - m0
            d1 = f01 - m1
            dd = f02 - m2
            p00, p01, p02, p11, p12, p22 = _outer(wc0, d0, d1, dd)
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f10 - m0, f11 - m1, f12 - m2
            )
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f20 - m0, f21 - m1, f22 - m2
            )
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f30 - m0, f31 - m1, f32 - m2
            )
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f40 - m0, f41 - m1, f42 - m2
            )
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f50 - m0, f51 - m1, f52 - m2
            )
            p00, p01, p02, p11, p12, p22 = _acc_outer(
                p00, p01, p02, p11, p12, p22, wi, f60 - m0, f61 - m1, f62 - m2
            )
            p00 += s[Q0 + j]
            p11 += s[Q1 + j]
            p22 += s[Q2 + j]
            ok, l00, l10, l11, l20, l21, l22 = chol3(p00, p01, p02, p11, p12, p22)
            s[XB0 + j] = m0
            s[XB1 + j] = m1
            s[XB2 + j] = m2
            s[PB00 + j] = p00
            s[PB01 + j] = p01
            s[PB02 + j] = p02
            s[PB11 + j] = p11
            s[PB12 + j] = p12
            s[PB22 + j] = p22
            s[LB00 + j] = l00
            s[LB10 + j] = l10
            s[LB11 + j] = l11
            s[LB20 + j] = l20
            s[LB21 + j] = l21
            s[LB22 + j] = l22
            s[OK_PB + j] = 1.0 if ok else 0.0


@njit(cache=True, error_model="numpy")
def _mean7(
    wm0: float, wi: float, a: Vec3, b: Vec3, c: Vec3, d: Vec3, e: Vec3, f: Vec3, g: Vec3
) -> tuple[float, float, float]:
    """W0ᵐ·a + Wᵢ·(b + c + … + g) of seven 3-vectors, summed in run_kernel's order (the
    unscented mean of the sigma points a, …, g; Simon 2006, Eq. 14.59 and 14.61)."""
    m0 = wm0 * a[0]
    m1 = wm0 * a[1]
    m2 = wm0 * a[2]
    for v0, v1, v2 in (b, c, d, e, f, g):
        m0 += wi * v0
        m1 += wi * v1
        m2 += wi * v2
    return m0, m1, m2


@njit(cache=True, error_model="numpy")
def _outer(
    w: float, d0: float, d1: float, d2: float
) -> tuple[float, float, float, float, float, float]:
    """The upper triangle of w·d·dᵀ, as run_kernel starts its covariance sums."""
    return w * d0 * d0, w * d0 * d1, w * d0 * d2, w * d1 * d1, w * d1 * d2, w * d2 * d2


@njit(cache=True, error_model="numpy")
def _acc_outer(
    p00: float,
    p01: float,
    p02: float,
    p11: float,
    p12: float,
    p22: float,
    w: float,
    d0: float,
    d1: float,
    d2: float,
) -> tuple[float, float, float, float, float, float]:
    """P += w·d·dᵀ on the upper triangle, as run_kernel accumulates it."""
    return (
        p00 + w * d0 * d0,
        p01 + w * d0 * d1,
        p02 + w * d0 * d2,
        p11 + w * d1 * d1,
        p12 + w * d1 * d2,
        p22 + w * d2 * d2,
    )


@njit(cache=True, error_model="numpy")
def _innovation_stats(
    s: np.ndarray, j: int, mp: np.ndarray, ctx: Context, w: SigmaWeights
) -> tuple[Vec3, Sym3, Mat3]:
    """Sigma points of (x̄, L̄) through h: (ẑ⁻, S − R, P_xz) of lane j, run_kernel's order.

    Returns:
        (ẑ⁻ (z0, z1, z2), S − R (s00, s01, s02, s11, s12, s22), P_xz (c00, c01, c02, c10,
        c11, c12, c20, c21, c22)) with S = Σ Wᶜ (Zᵢ − ẑ)(Zᵢ − ẑ)ᵀ (R not yet added) and
        P_xz[i][m] = c_im = Σ Wᶜ (χᵢ − x̄)(Zᵢ − ẑ)ᵀ (Simon 2006, Eq. 14.61–14.63).
    """
    e0, e1, e2, e3 = ctx
    wm0, wc0, wi, c = w
    x0, x1, x2, a0, a1, a2, b1, b2, d2 = _centre_and_spread(s, j, XB0, LB00, c)
    g00, g01, g02 = measure_scalar(x0, x1, x2, e0, e1, e2, e3, mp)
    g10, g11, g12 = measure_scalar(x0 + a0, x1 + a1, x2 + a2, e0, e1, e2, e3, mp)
    g20, g21, g22 = measure_scalar(x0 + 0.0, x1 + b1, x2 + b2, e0, e1, e2, e3, mp)
    g30, g31, g32 = measure_scalar(x0 + 0.0, x1 + 0.0, x2 + d2, e0, e1, e2, e3, mp)
    g40, g41, g42 = measure_scalar(x0 + -a0, x1 + -a1, x2 + -a2, e0, e1, e2, e3, mp)
    g50, g51, g52 = measure_scalar(x0 + -0.0, x1 + -b1, x2 + -b2, e0, e1, e2, e3, mp)
    g60, g61, g62 = measure_scalar(x0 + -0.0, x1 + -0.0, x2 + -d2, e0, e1, e2, e3, mp)
    z0, z1, z2 = _mean7(
        wm0, wi, (g00, g01, g02), (g10, g11, g12), (g20, g21, g22), (g30, g31, g32),
        (g40, g41, g42), (g50, g51, g52), (g60, g61, g62),
    )  # fmt: skip
    f0 = g00 - z0
    f1 = g01 - z1
    f2 = g02 - z2
    sz = _outer(wc0, f0, f1, f2)
    # P_xz: the deviations χᵢ − x̄ are the columns of ±c·L̄ (zero for i = 0)
    cxz = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    sz, cxz = _acc_cross(sz, cxz, wi, (a0, a1, a2), (g10 - z0, g11 - z1, g12 - z2))
    sz, cxz = _acc_cross(sz, cxz, wi, (0.0, b1, b2), (g20 - z0, g21 - z1, g22 - z2))
    sz, cxz = _acc_cross(sz, cxz, wi, (0.0, 0.0, d2), (g30 - z0, g31 - z1, g32 - z2))
    sz, cxz = _acc_cross(sz, cxz, wi, (-a0, -a1, -a2), (g40 - z0, g41 - z1, g42 - z2))
    sz, cxz = _acc_cross(sz, cxz, wi, (-0.0, -b1, -b2), (g50 - z0, g51 - z1, g52 - z2))
    sz, cxz = _acc_cross(sz, cxz, wi, (-0.0, -0.0, -d2), (g60 - z0, g61 - z1, g62 - z2))
    return (z0, z1, z2), sz, cxz


@njit(cache=True, error_model="numpy")
def _acc_cross(sz: Sym3, cxz: Mat3, w: float, dx: Vec3, f: Vec3) -> tuple[Sym3, Mat3]:
    """S += w·f·fᵀ (upper triangle) and P_xz += (w·dx)·fᵀ, as run_kernel accumulates."""
    s00, s01, s02, s11, s12, s22 = sz
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = cxz
    f0, f1, f2 = f
    g0 = w * dx[0]
    g1 = w * dx[1]
    g2 = w * dx[2]
    return (
        s00 + w * f0 * f0, s01 + w * f0 * f1, s02 + w * f0 * f2,
        s11 + w * f1 * f1, s12 + w * f1 * f2, s22 + w * f2 * f2,
    ), (
        c00 + g0 * f0, c01 + g0 * f1, c02 + g0 * f2,
        c10 + g1 * f0, c11 + g1 * f1, c12 + g1 * f2,
        c20 + g2 * f0, c21 + g2 * f1, c22 + g2 * f2,
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def _apply_update(
    s: np.ndarray, j: int, zk: Vec3, zb: Vec3, ls: Sym3, cxz: Mat3
) -> tuple[Vec3, Sym3, Vec3, float]:
    """x⁺ = x̄ + Wᵀv, P⁺ = P̄ − WᵀW with W = L_S⁻¹P_xzᵀ, v = L_S⁻¹y (``_kernel`` docstring).

    zk: the measurement z_k; zb: its prediction ẑ⁻; ls: L_S (m00, m10, m11, m20, m21, m22);
    cxz: P_xz (c00, …, c22).

    Returns:
        (x⁺, P⁺ (00, 01, 02, 11, 12, 22), y, NIS).
    """
    m00, m10, m11, m20, m21, m22 = ls
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = cxz
    i00 = 1.0 / m00
    i11 = 1.0 / m11
    i22 = 1.0 / m22
    i10 = -m10 * i00 * i11
    i21 = -m21 * i11 * i22
    i20 = -(m20 * i00 + m21 * i10) * i22
    w00 = i00 * c00
    w01 = i00 * c10
    w02 = i00 * c20
    w10 = i10 * c00 + i11 * c01
    w11 = i10 * c10 + i11 * c11
    w12 = i10 * c20 + i11 * c21
    w20 = i20 * c00 + i21 * c01 + i22 * c02
    w21 = i20 * c10 + i21 * c11 + i22 * c12
    w22 = i20 * c20 + i21 * c21 + i22 * c22
    y0 = zk[0] - zb[0]
    y1 = zk[1] - zb[1]
    y2 = zk[2] - zb[2]
    v0 = i00 * y0
    v1 = i10 * y0 + i11 * y1
    v2 = i20 * y0 + i21 * y1 + i22 * y2
    x0 = s[XB0 + j] + (w00 * v0 + w10 * v1 + w20 * v2)
    x1 = s[XB1 + j] + (w01 * v0 + w11 * v1 + w21 * v2)
    x2 = s[XB2 + j] + (w02 * v0 + w12 * v1 + w22 * v2)
    p00 = s[PB00 + j] - (w00 * w00 + w10 * w10 + w20 * w20)
    p01 = s[PB01 + j] - (w00 * w01 + w10 * w11 + w20 * w21)
    p02 = s[PB02 + j] - (w00 * w02 + w10 * w12 + w20 * w22)
    p11 = s[PB11 + j] - (w01 * w01 + w11 * w11 + w21 * w21)
    p12 = s[PB12 + j] - (w01 * w02 + w11 * w12 + w21 * w22)
    p22 = s[PB22 + j] - (w02 * w02 + w12 * w12 + w22 * w22)
    nis = v0 * v0 + v1 * v1 + v2 * v2
    return (x0, x1, x2), (p00, p01, p02, p11, p12, p22), (y0, y1, y2), nis


@njit(cache=True, error_model="numpy")
def _store_update(
    s: np.ndarray,
    j: int,
    mp: np.ndarray,
    ctx: Context,
    update: tuple[Vec3, Sym3, Vec3, float],
    ok_s: bool,
) -> None:
    """Store x⁺, P⁺, its plain Cholesky, y, NIS (``update``, :func:`_apply_update`'s),
    h(x⁺, u) and the flags of lane j."""
    (x0, x1, x2), (p00, p01, p02, p11, p12, p22), (y0, y1, y2), nis = update
    e0, e1, e2, e3 = ctx
    ok, l00, l10, l11, l20, l21, l22 = chol3(p00, p01, p02, p11, p12, p22)
    h0, h1, h2 = measure_scalar(x0, x1, x2, e0, e1, e2, e3, mp)
    s[X0 + j] = x0
    s[X1 + j] = x1
    s[X2 + j] = x2
    s[P00 + j] = p00
    s[P01 + j] = p01
    s[P02 + j] = p02
    s[P11 + j] = p11
    s[P12 + j] = p12
    s[P22 + j] = p22
    s[L00 + j] = l00
    s[L10 + j] = l10
    s[L11 + j] = l11
    s[L20 + j] = l20
    s[L21 + j] = l21
    s[L22 + j] = l22
    s[Y0 + j] = y0
    s[Y1 + j] = y1
    s[Y2 + j] = y2
    s[NIS + j] = nis
    s[H0 + j] = h0
    s[H1 + j] = h1
    s[H2 + j] = h2
    s[OK_P + j] = 1.0 if ok else 0.0
    s[OK_S + j] = 1.0 if ok_s else 0.0


@njit(cache=True, error_model="numpy")
def _update_lanes(
    lanes: np.ndarray, n_blocks: int, mp: np.ndarray, zk: Vec3, ctx: Context, w: SigmaWeights
) -> None:
    """Step 3 for the lanes of blocks [0, n_blocks), with the plain Cholesky of S (a failure
    is flagged)."""
    for blk in range(n_blocks):
        s = lanes[blk * BLOCK : (blk + 1) * BLOCK]
        for j in range(s.size // NROWS):  # LANES, but unknown to LLVM: it must not unroll
            zb, (s00, s01, s02, s11, s12, s22), cxz = _innovation_stats(s, j, mp, ctx, w)
            ok_s, m00, m10, m11, m20, m21, m22 = chol3(
                s00 + s[R0 + j], s01, s02, s11 + s[R1 + j], s12, s22 + s[R2 + j]
            )
            update = _apply_update(s, j, zk, zb, (m00, m10, m11, m20, m21, m22), cxz)
            _store_update(s, j, mp, ctx, update, ok_s)


@njit(cache=True, error_model="numpy")
def _update_lane_repaired(
    s: np.ndarray, j: int, mp: np.ndarray, zk: Vec3, ctx: Context, w: SigmaWeights
) -> tuple[int, int]:
    """Step 3 for one lane with the repairing Cholesky of S.

    Returns:
        (status, repairs): status 2 when S cannot be repaired (the lane diverged), else 0;
        repairs 1 when S needed jitter.
    """
    zb, (s00, s01, s02, s11, s12, s22), cxz = _innovation_stats(s, j, mp, ctx, w)
    st, m00, m10, m11, m20, m21, m22, _ = chol3_repair(
        s00 + s[R0 + j], s01, s02, s11 + s[R1 + j], s12, s22 + s[R2 + j]
    )
    if st == 2:
        return 2, 0
    update = _apply_update(s, j, zk, zb, (m00, m10, m11, m20, m21, m22), cxz)
    _store_update(s, j, mp, ctx, update, True)
    return 0, st


@njit(cache=True, error_model="numpy")
def _flat(j: int) -> int:
    """Index of lane j's first row in the flat lane array."""
    return (j // LANES) * BLOCK + j % LANES


@njit(cache=True, error_model="numpy")
def _retire(
    s: np.ndarray,
    ints: np.ndarray,
    j: int,
    n_active: int,
    step: int,
    cause: int,
    out_div: np.ndarray,
    out_rep: np.ndarray,
    out_cause: np.ndarray,
) -> int:
    """Record lane j's set as diverged at ``step`` and move the last active lane into j.

    ints: (4, BP) int64 rows [set id, repairs, held β, held Vx]. Returns the new count.
    """
    b = ints[0, j]
    out_div[b] = step
    out_rep[b] = ints[1, j]
    out_cause[b] = cause
    last = n_active - 1
    if j != last:
        fj = _flat(j)
        fl = _flat(last)
        for row in range(0, BLOCK, LANES):
            s[row + fj] = s[row + fl]
        for row in range(4):
            ints[row, j] = ints[row, last]
    return last


@njit(cache=True, error_model="numpy")
def run_kernel_soa(
    data: KernelData,
    w: SigmaWeights,
    out: KernelOutputs,
    out_div: np.ndarray,
    out_rep: np.ndarray,
    out_cause: np.ndarray,
) -> None:
    """The single-track UKF for B noise settings over one manoeuvre, SIMD across the sets.

    Arguments and outputs are those of :func:`kftune.models._sideslip_ukf.run_kernel_batch`:
    data's q, r, x_init (B, 3) and P_init (B, 3, 3); out's x, P_diag, z_hat, innovation
    (B, N, 3) and nis (B, N) — its log_det_s is not written (the lanes do not compute log
    det S); out_div, out_rep, out_cause (B,) int64. Set b's outputs equal ``run_kernel``'s
    for (q[b], r[b], x_init[b], P_init[b]) bit for bit.
    """
    mp, u, z, dt, q, r = data.p, data.u, data.z, data.dt, data.q, data.r
    x_init, P_init, n_hold = data.x_init, data.P_init, data.n_hold
    out_x, out_p, out_zhat, out_innov, out_nis = (
        out.x,
        out.P_diag,
        out.z_hat,
        out.innovation,
        out.nis,
    )
    n_sets = q.shape[0]
    n_steps = u.shape[0]
    n_blocks = (n_sets + LANES - 1) // LANES
    bp = n_blocks * LANES
    s = np.zeros(n_blocks * BLOCK)
    ints = np.zeros((4, bp), dtype=np.int64)  # set id, repairs, held β, held Vx
    n_active = 0
    for b in range(n_sets):
        out_div[b] = -1
        out_cause[b] = STOP_NONE
        p00 = P_init[b, 0, 0]
        p01 = 0.5 * (P_init[b, 0, 1] + P_init[b, 1, 0])
        p02 = 0.5 * (P_init[b, 0, 2] + P_init[b, 2, 0])
        p11 = P_init[b, 1, 1]
        p12 = 0.5 * (P_init[b, 1, 2] + P_init[b, 2, 1])
        p22 = P_init[b, 2, 2]
        st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(p00, p01, p02, p11, p12, p22)
        if st == 2:
            out_div[b] = 0
            out_rep[b] = 0
            out_cause[b] = STOP_NUMERICAL
            continue
        j = n_active
        f = _flat(j)
        n_active += 1
        ints[0, j] = b
        ints[1, j] = 1 if st == 1 else 0
        # step 0 has no prediction: the "predicted" rows hold the prior
        s[XB0 + f] = x_init[b, 0]
        s[XB1 + f] = x_init[b, 1]
        s[XB2 + f] = x_init[b, 2]
        s[PB00 + f] = p00 + jit
        s[PB01 + f] = p01
        s[PB02 + f] = p02
        s[PB11 + f] = p11 + jit
        s[PB12 + f] = p12
        s[PB22 + f] = p22 + jit
        s[LB00 + f] = l00
        s[LB10 + f] = l10
        s[LB11 + f] = l11
        s[LB20 + f] = l20
        s[LB21 + f] = l21
        s[LB22 + f] = l22
        s[Q0 + f] = q[b, 0]
        s[Q1 + f] = q[b, 1]
        s[Q2 + f] = q[b, 2]
        s[R0 + f] = r[b, 0]
        s[R1 + f] = r[b, 1]
        s[R2 + f] = r[b, 2]
    # padding lanes: a copy of lane 0, never read back
    for j in range(n_active, bp):
        f = _flat(j)
        for row in range(0, BLOCK, LANES):
            s[row + f] = s[row]

    for k in range(n_steps):
        if n_active == 0:
            break
        n_vec_blocks = (n_active + LANES - 1) // LANES
        if k > 0:
            ctx = (u[k - 1, 2], u[k - 1, 3], u[k - 1, 4], u[k - 1, 5])  # prepared row
            _predict_lanes(s, n_vec_blocks, mp, dt, ctx, u[k - 1, 1], w)
            j = 0
            while j < n_active:
                f = _flat(j)
                if s[OK_PB + f] == 0.0:
                    st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(
                        s[PB00 + f], s[PB01 + f], s[PB02 + f], s[PB11 + f], s[PB12 + f], s[PB22 + f]
                    )
                    if st == 2:
                        n_active = _retire(
                            s, ints, j, n_active, k, STOP_NUMERICAL, out_div, out_rep, out_cause
                        )
                        continue  # lane j now holds another set: look at it again
                    ints[1, j] += 1
                    s[PB00 + f] += jit
                    s[PB11 + f] += jit
                    s[PB22 + f] += jit
                    s[LB00 + f] = l00
                    s[LB10 + f] = l10
                    s[LB11 + f] = l11
                    s[LB20 + f] = l20
                    s[LB21 + f] = l21
                    s[LB22 + f] = l22
                j += 1
            n_vec_blocks = (n_active + LANES - 1) // LANES
        ctx = (u[k, 2], u[k, 3], u[k, 4], u[k, 5])
        zk = (z[k, 0], z[k, 1], z[k, 2])
        _update_lanes(s, n_vec_blocks, mp, zk, ctx, w)
        j = 0
        while j < n_active:
            f = _flat(j)
            if s[OK_S + f] == 0.0:
                st, rep = _update_lane_repaired(s, f, mp, zk, ctx, w)
                if st == 2:
                    n_active = _retire(
                        s, ints, j, n_active, k, STOP_NUMERICAL, out_div, out_rep, out_cause
                    )
                    continue
                ints[1, j] += rep
            # P⁺: factorised in the vector loop, or repaired here (run_kernel's order of checks)
            st = 0
            jit = 0.0
            if s[OK_P + f] == 0.0:
                st, l00, l10, l11, l20, l21, l22, jit = chol3_repair(
                    s[P00 + f], s[P01 + f], s[P02 + f], s[P11 + f], s[P12 + f], s[P22 + f]
                )
            x0 = s[X0 + f]
            x1 = s[X1 + f]
            x2 = s[X2 + f]
            if (
                st == 2
                or not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2))
                or not (math.isfinite(s[NIS + f]) and math.isfinite(s[H1 + f]))
            ):
                n_active = _retire(
                    s, ints, j, n_active, k, STOP_NUMERICAL, out_div, out_rep, out_cause
                )
                continue
            cause, beyond, off = runaway(x0, x1, zk[0])
            if cause != 0:
                n_active = _retire(s, ints, j, n_active, k, cause, out_div, out_rep, out_cause)
                continue
            ints[2, j] = ints[2, j] + 1 if beyond else 0
            ints[3, j] = ints[3, j] + 1 if off else 0
            if ints[2, j] >= n_hold or ints[3, j] >= n_hold:
                why = STOP_SIDESLIP_HELD if ints[2, j] >= n_hold else STOP_SPEED
                n_active = _retire(
                    s, ints, j, n_active, k + 1 - n_hold, why, out_div, out_rep, out_cause
                )
                continue
            if st == 1:
                ints[1, j] += 1
                s[P00 + f] += jit
                s[P11 + f] += jit
                s[P22 + f] += jit
                s[L00 + f] = l00
                s[L10 + f] = l10
                s[L11 + f] = l11
                s[L20 + f] = l20
                s[L21 + f] = l21
                s[L22 + f] = l22
            b = ints[0, j]
            out_x[b, k, 0] = x0
            out_x[b, k, 1] = x1
            out_x[b, k, 2] = x2
            out_p[b, k, 0] = s[P00 + f]
            out_p[b, k, 1] = s[P11 + f]
            out_p[b, k, 2] = s[P22 + f]
            out_innov[b, k, 0] = s[Y0 + f]
            out_innov[b, k, 1] = s[Y1 + f]
            out_innov[b, k, 2] = s[Y2 + f]
            out_nis[b, k] = s[NIS + f]
            out_zhat[b, k, 0] = s[H0 + f]
            out_zhat[b, k, 1] = s[H1 + f]
            out_zhat[b, k, 2] = s[H2 + f]
            j += 1
    for j in range(n_active):
        out_rep[ints[0, j]] = ints[1, j]
    # NaN rows from each diverged set's step on, as run_kernel's _fill_nan
    for b in range(n_sets):
        if out_div[b] >= 0:
            for k in range(out_div[b], n_steps):
                for col in range(3):
                    out_x[b, k, col] = _NAN
                    out_p[b, k, col] = _NAN
                    out_zhat[b, k, col] = _NAN
                    out_innov[b, k, col] = _NAN
                out_nis[b, k] = _NAN


# LLVM option set while this module's kernel compiles, and set back to LLVM's value at
# numba's optimisation level 3 afterwards: the inlining threshold (250 at -O3); the RK4
# step and the measurement model must be inlined into the lane loops, or the loops hold
# calls and cannot be vectorised.
_LLVM_OPTIONS = (("-inline-threshold", 100_000, 250),)
_ready = False


def ensure_compiled() -> None:
    """Compile (or load from numba's cache) :func:`run_kernel_soa` with vectorisation on.

    LLVM's inlining threshold (an option global to the process) is raised only while this
    kernel compiles and set back to numba's value afterwards, so that no other function is
    compiled differently.
    """
    global _ready
    if _ready:
        return
    import llvmlite.binding as llvm

    for name, value, _ in _LLVM_OPTIONS:
        llvm.set_option("", f"{name}={value}")
    try:
        mp = np.array([1500.0, 2500.0, 1.2, 1.4, 0.5, 8e4, 9e4, 1e5, 1.0])
        q = np.full((1, 3), 1e-4)
        data = KernelData(
            np.zeros((2, 6)), np.tile([20.0, 0.0, 0.0], (2, 1)), mp, 0.01, q, q,
            np.array([[20.0, 0.0, 0.0]]), np.eye(3)[None], 50, np.array([0, 0], np.int64),
        )  # fmt: skip
        div, rep, why = (np.empty(1, dtype=np.int64) for _ in range(3))
        run_kernel_soa(
            data, SigmaWeights(0.5, 0.5, 0.1, 1.0), KernelOutputs.empty(2, 3, 3, 1), div, rep, why
        )
    finally:
        for name, _, default in _LLVM_OPTIONS:
            llvm.set_option("", f"{name}={default}")
    _ready = True
