/* kftune models "single-track", "single-track-ay-bias" and "single-track-biases" in C99:
 * the single-track vehicle with Dugoff axle forces, one RK4 step per sample.
 *
 * The twin of kftune/models/sideslip.py and the compiled scalar functions it calls
 * (kftune/vehicle/single_track.py, kftune/vehicle/tyre.py,
 * kftune/models/_single_track_jacobians.py), function for function and in the same order
 * of operations, so that each hook agrees with Python to rounding; the equations are in
 * those modules' docstrings.
 *
 * x = [Vx, Vy, r (, bias states)] [m/s, m/s, rad/s], raw input u = [delta, ax]
 * [rad, m/s^2], prepared row w = [delta, ax, tan delta, cos delta, Fz_f, Fz_r],
 * z = [Vx, ay, r] [m/s, m/s^2, rad/s], p = [m, Iz, a, b, h, C_af, C_ar, C_x, mu] (SI).
 *
 * The variant is read from kftune_model.h: a bias state's index macro (KF_X_B_VX,
 * KF_X_B_AY, KF_X_B_R) is defined only in the models that have it, and each bias is a
 * random walk added to its measurement. */
#include "kftune_model.h"

/* Gravitational acceleration [m/s^2] (kftune.vehicle.params.G). */
#define ST_G 9.81

/* Stop causes (kftune.models.sideslip; FIRST_MODEL_STOP = 2). */
#define ST_STOP_REVERSE 2       /* estimated Vx <= 0 */
#define ST_STOP_SIDESLIP 3      /* |beta| > 60 deg: at once */
#define ST_STOP_SIDESLIP_HELD 4 /* |beta| > MAX_SIDESLIP = 0.8 rad, held (held[0]) */
#define ST_STOP_SPEED 5         /* |Vx - z_Vx| > 50 % of z_Vx, held (held[1]) */

/* Runaway bounds: tan(RUNAWAY_BETA = 60 deg) and tan(MAX_SIDESLIP = 0.8 rad) as the
 * Python computes them (sideslip._TAN_RUNAWAY_BETA, _TAN_MAX_SIDESLIP), and RUNAWAY_VX. */
#define ST_TAN_RUNAWAY_BETA 1.7320508075688767
#define ST_TAN_MAX_SIDESLIP 1.0296385570503641
#define ST_RUNAWAY_VX 0.5

/* Prior: Vy's standard deviation as a fraction of the first measured Vx
 * (P0_VY_SPEED_FRACTION) and the bias states' standard deviations (VX_BIAS_PRIOR_STD [m/s],
 * AY_BIAS_PRIOR_STD [m/s^2], R_BIAS_PRIOR_STD = radians(0.5) [rad/s]). */
#define ST_P0_VY_SPEED_FRACTION 0.05
#define ST_VX_BIAS_PRIOR_STD 0.2
#define ST_AY_BIAS_PRIOR_STD 0.5
#define ST_R_BIAS_PRIOR_STD 0.008726646259971648

/* ------------------------------------------------------------------ the vehicle -- */

/* Dugoff axle force with kappa = 0 from tan(alpha) [N] (tyre.dugoff_fy_scalar). */
static kf_real st_dugoff(kf_real tan_alpha, kf_real Fz, kf_real C_alpha, kf_real mu)
{
    kf_real s, half_cap;
    if (!(Fz > 0)) {
        return Fz <= 0 ? (kf_real)0 : Fz; /* no load: no force; NaN propagates */
    }
    s = C_alpha * fabs(tan_alpha);
    half_cap = 0.5 * mu * Fz;
    if (s <= half_cap) { /* lambda >= 1: linear region */
        return C_alpha * tan_alpha;
    }
    return copysign(mu * Fz * (1.0 - 0.5 * half_cap / s), tan_alpha);
}

/* tan(alpha) = num/den; den = 0: +-inf, 0/0: fallback (single_track._tan_ratio). */
static kf_real st_tan_ratio(kf_real num, kf_real den, kf_real fallback)
{
    if (den != 0) {
        return num / den;
    }
    if (num != 0) {
        return copysign((kf_real)INFINITY, num);
    }
    return fallback;
}

/* Axle lateral forces (F_yf, F_yr) [N] (single_track.lateral_forces_scalar). */
static void st_lateral_forces(kf_real vx, kf_real vy, kf_real r, const kf_real w[],
                              const kf_real p[], kf_real *Fyf, kf_real *Fyr)
{
    kf_real tan_d = w[2];
    kf_real yf = vy + p[KF_P_A] * r;
    kf_real tan_af = st_tan_ratio(vx * tan_d - yf, vx + yf * tan_d, tan_d);
    kf_real tan_ar = st_tan_ratio(p[KF_P_B] * r - vy, vx, 0);
    *Fyf = st_dugoff(tan_af, w[4], p[KF_P_C_AF], p[KF_P_MU]);
    *Fyr = st_dugoff(tan_ar, w[5], p[KF_P_C_AR], p[KF_P_MU]);
}

/* dx/dt of [Vx, Vy, r] (single_track.derivatives_scalar). */
static void st_derivatives(kf_real vx, kf_real vy, kf_real r, const kf_real w[],
                           const kf_real p[], kf_real d[3])
{
    kf_real Fyf, Fyr, Fyf_c;
    st_lateral_forces(vx, vy, r, w, p, &Fyf, &Fyr);
    Fyf_c = Fyf * w[3];
    d[0] = w[1] + r * vy;
    d[1] = (Fyf_c + Fyr) / p[KF_P_M] - r * vx;
    d[2] = (p[KF_P_A] * Fyf_c - p[KF_P_B] * Fyr) / p[KF_P_IZ];
}

/* ------------------------------------------------------------ the Jacobians -- */

/* dF_y/d(tan alpha) [N] (_single_track_jacobians.dugoff_slope). */
static kf_real st_dugoff_slope(kf_real tan_alpha, kf_real Fz, kf_real C_alpha, kf_real mu)
{
    kf_real s, half_cap;
    if (!(Fz > 0)) {
        return Fz <= 0 ? (kf_real)0 : Fz;
    }
    s = C_alpha * fabs(tan_alpha);
    half_cap = 0.5 * mu * Fz;
    if (s <= half_cap) {
        return C_alpha;
    }
    if (s == (kf_real)INFINITY) {
        return 0;
    }
    return 0.5 * mu * Fz * half_cap * C_alpha / (s * s);
}

/* (tan alpha, d/dVx, d/dVy, d/dr) of num/den; gradient 0 where den = 0
 * (_single_track_jacobians._tan_ratio_gradient). */
static void st_tan_ratio_gradient(kf_real num, kf_real den, const kf_real dnum[3],
                                  const kf_real dden[3], kf_real g[4])
{
    kf_real inv2;
    int j;
    if (den == 0) {
        g[0] = copysign((kf_real)INFINITY, num);
        g[1] = g[2] = g[3] = 0;
        return;
    }
    inv2 = 1.0 / (den * den);
    g[0] = num / den;
    for (j = 0; j < 3; ++j) {
        g[1 + j] = (dnum[j] * den - num * dden[j]) * inv2;
    }
}

/* (d(F_yf cos delta)/dx, dF_yr/dx), each over (Vx, Vy, r), into g[0..5]
 * (_single_track_jacobians._force_gradients). */
static void st_force_gradients(kf_real vx, kf_real vy, kf_real r, const kf_real w[],
                               const kf_real p[], kf_real g[6])
{
    kf_real a = p[KF_P_A], b = p[KF_P_B];
    kf_real t = w[2];
    kf_real yf = vy + a * r;
    kf_real front[4], rear[4], kf, kr;
    const kf_real dnum_f[3] = {t, -1.0, -a}, dden_f[3] = {1.0, t, a * t};
    const kf_real dnum_r[3] = {0.0, -1.0, b}, dden_r[3] = {1.0, 0.0, 0.0};
    int j;
    st_tan_ratio_gradient(vx * t - yf, vx + yf * t, dnum_f, dden_f, front);
    st_tan_ratio_gradient(b * r - vy, vx, dnum_r, dden_r, rear);
    kf = st_dugoff_slope(front[0], w[4], p[KF_P_C_AF], p[KF_P_MU]) * w[3];
    kr = st_dugoff_slope(rear[0], w[5], p[KF_P_C_AR], p[KF_P_MU]);
    for (j = 0; j < 3; ++j) {
        g[j] = kf * front[1 + j];
        g[3 + j] = kr * rear[1 + j];
    }
}

/* G = d(dx/dt)/dx at (Vx, Vy, r), 3x3 row-major
 * (_single_track_jacobians._continuous_jacobian). */
static void st_continuous_jacobian(kf_real vx, kf_real vy, kf_real r, const kf_real w[],
                                   const kf_real p[], kf_real G[9])
{
    kf_real m = p[KF_P_M], iz = p[KF_P_IZ], a = p[KF_P_A], b = p[KF_P_B];
    kf_real g[6];
    st_force_gradients(vx, vy, r, w, p, g);
    G[0] = 0;
    G[1] = r;
    G[2] = vy;
    G[3] = (g[0] + g[3]) / m - r;
    G[4] = (g[1] + g[4]) / m;
    G[5] = (g[2] + g[5]) / m - vx;
    G[6] = (a * g[0] - b * g[3]) / iz;
    G[7] = (a * g[1] - b * g[4]) / iz;
    G[8] = (a * g[2] - b * g[5]) / iz;
}

/* out = G (I + h J), 3x3 row-major (_single_track_jacobians._chain). */
static void st_chain(const kf_real G[9], kf_real h, const kf_real J[9], kf_real out[9])
{
    int i, k;
    for (i = 0; i < 3; ++i) {
        for (k = 0; k < 3; ++k) {
            out[3 * i + k] = G[3 * i + k] + h * (G[3 * i] * J[k] + G[3 * i + 1] * J[3 + k] +
                                                 G[3 * i + 2] * J[6 + k]);
        }
    }
}

/* ------------------------------------------------------------ the contract -- */

void kf_model_prepare(const kf_real u_raw[], const kf_real p[], kf_real w[])
{
    kf_real m = p[KF_P_M], a = p[KF_P_A], b = p[KF_P_B], h = p[KF_P_H];
    kf_real L = a + b;
    kf_real delta = u_raw[KF_U_DELTA], ax = u_raw[KF_U_AX];
    w[0] = delta;
    w[1] = ax;
    w[2] = tan(delta);
    w[3] = cos(delta);
    w[4] = m * (ST_G * b - ax * h) / L;
    w[5] = m * (ST_G * a + ax * h) / L;
}

/* one RK4 step of [Vx, Vy, r] with w held; the bias states are kept */
void kf_model_f(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    kf_real vx = x[0], vy = x[1], r = x[2];
    kf_real h2 = 0.5 * dt, s = dt / 6.0;
    kf_real k1[3], k2[3], k3[3], k4[3];
    int j;
    st_derivatives(vx, vy, r, w, p, k1);
    st_derivatives(vx + h2 * k1[0], vy + h2 * k1[1], r + h2 * k1[2], w, p, k2);
    st_derivatives(vx + h2 * k2[0], vy + h2 * k2[1], r + h2 * k2[2], w, p, k3);
    st_derivatives(vx + dt * k3[0], vy + dt * k3[1], r + dt * k3[2], w, p, k4);
    for (j = 0; j < 3; ++j) {
        out[j] = x[j] + s * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j]);
    }
    for (j = 3; j < KF_N; ++j) {
        out[j] = x[j];
    }
}

/* z = [Vx, ay, r], ay = (F_yf cos delta + F_yr)/m, each plus its bias state if any */
void kf_model_h(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    kf_real Fyf, Fyr;
    st_lateral_forces(x[0], x[1], x[2], w, p, &Fyf, &Fyr);
    out[0] = x[0];
    out[1] = (Fyf * w[3] + Fyr) / p[KF_P_M];
    out[2] = x[2];
#ifdef KF_X_B_VX
    out[KF_Z_VX] += x[KF_X_B_VX];
#endif
#ifdef KF_X_B_AY
    out[KF_Z_AY] += x[KF_X_B_AY];
#endif
#ifdef KF_X_B_R
    out[KF_Z_R] += x[KF_X_B_R];
#endif
}

/* F = d x'/dx: the exact derivative of the RK4 step (_single_track_jacobians.rk4_jacobian),
 * identity on the bias states. Stage i+1 is at x + h_i k_i (h = dt/2, dt/2, dt) and has
 * J_{i+1} = G(x_{i+1}) (I + h_i J_i); F = I + dt/6 (J1 + 2 J2 + 2 J3 + J4). */
void kf_model_F(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    const kf_real h[3] = {0.5 * dt, 0.5 * dt, dt}, weight[3] = {2.0, 2.0, 1.0};
    kf_real s = dt / 6.0;
    kf_real k[3], xs[3], G[9], J[9], Jn[9], sum[9];
    int i, j;
    st_derivatives(x[0], x[1], x[2], w, p, k);
    st_continuous_jacobian(x[0], x[1], x[2], w, p, J);
    for (j = 0; j < 9; ++j) {
        sum[j] = J[j];
    }
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            xs[j] = x[j] + h[i] * k[j];
        }
        if (i < 2) { /* the last stage's derivative is not needed */
            st_derivatives(xs[0], xs[1], xs[2], w, p, k);
        }
        st_continuous_jacobian(xs[0], xs[1], xs[2], w, p, G);
        st_chain(G, h[i], J, Jn);
        for (j = 0; j < 9; ++j) {
            J[j] = Jn[j];
            sum[j] += weight[i] * Jn[j]; /* 1.0 * Jn is Jn exactly */
        }
    }
    for (i = 0; i < KF_N * KF_N; ++i) {
        out[i] = 0;
    }
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            out[i * KF_N + j] = (kf_real)(i == j ? 1 : 0) + s * sum[3 * i + j];
        }
    }
    for (j = 3; j < KF_N; ++j) {
        out[j * KF_N + j] = 1;
    }
}

/* H = dh/dx: rows Vx, ay (through the Dugoff slope), r, and 1 for each bias state */
void kf_model_H(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    kf_real g[6], m = p[KF_P_M];
    int i;
    for (i = 0; i < KF_M * KF_N; ++i) {
        out[i] = 0;
    }
    st_force_gradients(x[0], x[1], x[2], w, p, g);
    out[0 * KF_N + 0] = 1;
    out[1 * KF_N + 0] = (g[0] + g[3]) / m;
    out[1 * KF_N + 1] = (g[1] + g[4]) / m;
    out[1 * KF_N + 2] = (g[2] + g[5]) / m;
    out[2 * KF_N + 2] = 1;
#ifdef KF_X_B_VX
    out[KF_Z_VX * KF_N + KF_X_B_VX] = 1;
#endif
#ifdef KF_X_B_AY
    out[KF_Z_AY * KF_N + KF_X_B_AY] = 1;
#endif
#ifdef KF_X_B_R
    out[KF_Z_R * KF_N + KF_X_B_R] = 1;
#endif
}

/* Vx > 0 and the runaway rules (sideslip.check): |Vy| > tan(bound) Vx, no atan2.
 * held[0]: |beta| > MAX_SIDESLIP; held[1]: |Vx - z_Vx| > RUNAWAY_VX z_Vx. */
int kf_model_check(const kf_real x[], const kf_real z[], const kf_real w[], const kf_real p[],
                   int held[])
{
    kf_real vx = x[0], vy = x[1];
    (void)w;
    (void)p;
    if (!(vx > 0)) {
        return ST_STOP_REVERSE;
    }
    if (fabs(vy) > ST_TAN_RUNAWAY_BETA * vx) {
        return ST_STOP_SIDESLIP;
    }
    held[0] = fabs(vy) > ST_TAN_MAX_SIDESLIP * vx;
    held[1] = fabs(vx - z[0]) > ST_RUNAWAY_VX * z[0];
    return 0;
}

/* x0 = [z0_Vx, 0, z0_r, 0...], P0 = diag(r_Vx, (0.05 z0_Vx)^2, r_r, bias variances)
 * (sideslip.single_track_prior and _prior_with_biases) */
void kf_model_prior(const kf_real z0[], const kf_real r[], const kf_real p[], kf_real x0[],
                    kf_real P0[])
{
    kf_real vx0 = z0[0];
    kf_real sd_vy = ST_P0_VY_SPEED_FRACTION * vx0;
    int i;
    (void)p;
    for (i = 0; i < KF_N; ++i) {
        x0[i] = 0;
    }
    for (i = 0; i < KF_N * KF_N; ++i) {
        P0[i] = 0;
    }
    x0[0] = vx0;
    x0[2] = z0[2];
    P0[0 * KF_N + 0] = r[0];
    P0[1 * KF_N + 1] = sd_vy * sd_vy;
    P0[2 * KF_N + 2] = r[2];
#ifdef KF_X_B_VX
    P0[KF_X_B_VX * KF_N + KF_X_B_VX] = ST_VX_BIAS_PRIOR_STD * ST_VX_BIAS_PRIOR_STD;
#endif
#ifdef KF_X_B_AY
    P0[KF_X_B_AY * KF_N + KF_X_B_AY] = ST_AY_BIAS_PRIOR_STD * ST_AY_BIAS_PRIOR_STD;
#endif
#ifdef KF_X_B_R
    P0[KF_X_B_R * KF_N + KF_X_B_R] = ST_R_BIAS_PRIOR_STD * ST_R_BIAS_PRIOR_STD;
#endif
}

/* the outputs the model names, each where the header puts it: the sideslip angle
 * beta = atan2(Vy, Vx) [rad] (sideslip.sideslip_angle), and any state given as an output */
void kf_model_outputs(const kf_real x[], kf_real y[])
{
    (void)x;
    (void)y;
#ifdef KF_Y_BETA
    y[KF_Y_BETA] = atan2(x[1], x[0]);
#endif
#ifdef KF_Y_VY
    y[KF_Y_VY] = x[1];
#endif
#if defined(KF_Y_B_VX) && defined(KF_X_B_VX)
    y[KF_Y_B_VX] = x[KF_X_B_VX];
#endif
#if defined(KF_Y_B_AY) && defined(KF_X_B_AY)
    y[KF_Y_B_AY] = x[KF_X_B_AY];
#endif
#if defined(KF_Y_B_R) && defined(KF_X_B_R)
    y[KF_Y_B_R] = x[KF_X_B_R];
#endif
}
