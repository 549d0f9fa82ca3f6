/* The linear-tyre single-track ("bicycle") model of linear_bicycle.py, in C99 for
 * `kftune export --format c`: the same functions, written against kftune_model.h (which
 * kftune writes for the model: kf_real, the sizes KF_N, KF_M, ... and index macros such as
 * KF_P_C_F). Each function here is the twin of the Python one of the same role, and
 * `kftune export --format c --check DATASET` checks them against each other on the data.
 *
 * x = [vx, vy, r] [m/s, m/s, rad/s], u = [delta, ax] [rad, m/s^2], z = [vx, ay, r],
 * p = [m, Iz, a, b, C_f, C_r]. */
#include "kftune_model.h"

/* lateral axle forces F = C * alpha [N] (_forces) */
static void bicycle_forces(const kf_real x[], const kf_real u[], const kf_real p[],
                           kf_real *fyf, kf_real *fyr)
{
    kf_real vx = x[KF_X_VX], vy = x[KF_X_VY], r = x[KF_X_R];
    kf_real alpha_f = u[KF_U_DELTA] - (vy + p[KF_P_A] * r) / vx;
    kf_real alpha_r = -(vy - p[KF_P_B] * r) / vx;
    *fyf = p[KF_P_C_F] * alpha_f;
    *fyr = p[KF_P_C_R] * alpha_r;
}

/* x_k = x_{k-1} + dt * dx/dt (explicit Euler) (f) */
void kf_model_f(const kf_real x[], const kf_real u[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    kf_real fyf, fyr, cd = cos(u[KF_U_DELTA]);
    bicycle_forces(x, u, p, &fyf, &fyr);
    out[0] = x[0] + dt * (u[KF_U_AX] + x[1] * x[2]);
    out[1] = x[1] + dt * ((fyf * cd + fyr) / p[KF_P_M] - x[2] * x[0]);
    out[2] = x[2] + dt * ((p[KF_P_A] * fyf * cd - p[KF_P_B] * fyr) / p[KF_P_IZ]);
}

/* z = [vx, ay, r] with ay the lateral force over the mass (h) */
void kf_model_h(const kf_real x[], const kf_real u[], const kf_real p[], kf_real out[])
{
    kf_real fyf, fyr;
    bicycle_forces(x, u, p, &fyf, &fyr);
    out[0] = x[0];
    out[1] = (fyf * cos(u[KF_U_DELTA]) + fyr) / p[KF_P_M];
    out[2] = x[2];
}

/* start at the first measured speed and yaw rate, vy = 0, variances from R (prior) */
void kf_model_prior(const kf_real z0[], const kf_real r[], const kf_real p[], kf_real x0[],
                    kf_real P0[])
{
    kf_real sd_vy = 0.05 * z0[KF_Z_VX];
    int i;
    (void)p;
    for (i = 0; i < KF_N * KF_N; ++i) {
        P0[i] = 0;
    }
    x0[0] = z0[KF_Z_VX];
    x0[1] = 0;
    x0[2] = z0[KF_Z_R];
    P0[0 * KF_N + 0] = r[KF_Z_VX];
    P0[1 * KF_N + 1] = sd_vy * sd_vy;
    P0[2 * KF_N + 2] = r[KF_Z_R];
}

/* the output beta = atan2(vy, vx) [rad] */
void kf_model_outputs(const kf_real x[], kf_real y[])
{
    y[KF_Y_BETA] = atan2(x[KF_X_VY], x[KF_X_VX]);
}
