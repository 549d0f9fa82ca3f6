/* kftune model "ctrv" in C99: constant turn rate and velocity, position measurements.
 * The twin of kftune/models/tracking.py, hook for hook (see its docstring for the
 * equations): x = [px, py, v, psi, omega] [m, m, m/s, rad, rad/s], no input,
 * z = [px, py] [m], no parameters. Written against kftune_model.h. */
#include "kftune_model.h"

/* Below this |s| the sinc derivative uses its Taylor series (tracking._SERIES_BELOW). */
#define CTRV_SERIES_BELOW 0.1

/* Prior standard deviations of v [m/s], psi [rad], omega [rad/s] (tracking.CTRV_PRIOR_STD). */
#define CTRV_PRIOR_STD_V 20.0
#define CTRV_PRIOR_STD_PSI 3.141592653589793
#define CTRV_PRIOR_STD_OMEGA 0.5

/* sin(s)/s, 1 at s = 0 */
static kf_real ctrv_sinc(kf_real s)
{
    return s == 0 ? (kf_real)1 : sin(s) / s;
}

/* d sinc/ds = (s cos s - sin s)/s^2, by its Taylor series for |s| < 0.1 */
static kf_real ctrv_dsinc(kf_real s)
{
    if (fabs(s) < CTRV_SERIES_BELOW) {
        kf_real s2 = s * s;
        return s * (-1.0 / 3.0 + s2 * (1.0 / 30.0 + s2 * (-1.0 / 840.0 + s2 / 45360.0)));
    }
    return (s * cos(s) - sin(s)) / (s * s);
}

void kf_model_prior(const kf_real z0[], const kf_real r[], const kf_real p[], kf_real x0[],
                    kf_real P0[])
{
    int i;
    (void)p;
    for (i = 0; i < KF_N * KF_N; ++i) {
        P0[i] = 0;
    }
    x0[0] = z0[0];
    x0[1] = z0[1];
    x0[2] = 0;
    x0[3] = 0;
    x0[4] = 0;
    P0[0 * KF_N + 0] = r[0];
    P0[1 * KF_N + 1] = r[1];
    P0[2 * KF_N + 2] = CTRV_PRIOR_STD_V * CTRV_PRIOR_STD_V;
    P0[3 * KF_N + 3] = CTRV_PRIOR_STD_PSI * CTRV_PRIOR_STD_PSI;
    P0[4 * KF_N + 4] = CTRV_PRIOR_STD_OMEGA * CTRV_PRIOR_STD_OMEGA;
}

/* the exact CTRV step of length dt */
void kf_model_f(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    kf_real v = x[2], psi = x[3], om = x[4];
    kf_real s = 0.5 * om * dt;
    kf_real a = psi + s;
    kf_real d = v * dt * ctrv_sinc(s);
    (void)w;
    (void)p;
    out[0] = x[0] + d * cos(a);
    out[1] = x[1] + d * sin(a);
    out[2] = v;
    out[3] = psi + om * dt;
    out[4] = om;
}

void kf_model_h(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    (void)w;
    (void)p;
    out[0] = x[0];
    out[1] = x[1];
}

/* the model has no outputs */
void kf_model_outputs(const kf_real x[], kf_real y[])
{
    (void)x;
    (void)y;
}

/* (5, 5) df/dx of kf_model_f */
void kf_model_F(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    kf_real v = x[2], om = x[4];
    kf_real s = 0.5 * om * dt;
    kf_real a = x[3] + s;
    kf_real c = cos(a), sn = sin(a);
    kf_real sc = ctrv_sinc(s), ds = ctrv_dsinc(s);
    int i;
    (void)w;
    (void)p;
    for (i = 0; i < KF_N * KF_N; ++i) {
        out[i] = 0;
    }
    for (i = 0; i < KF_N; ++i) {
        out[i * KF_N + i] = 1;
    }
    out[0 * KF_N + 2] = dt * sc * c;
    out[0 * KF_N + 3] = -v * dt * sc * sn;
    out[0 * KF_N + 4] = 0.5 * v * dt * dt * (ds * c - sc * sn);
    out[1 * KF_N + 2] = dt * sc * sn;
    out[1 * KF_N + 3] = v * dt * sc * c;
    out[1 * KF_N + 4] = 0.5 * v * dt * dt * (ds * sn + sc * c);
    out[3 * KF_N + 4] = dt;
}

/* (2, 5) dh/dx = [I2 0] */
void kf_model_H(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    int i;
    (void)x;
    (void)w;
    (void)p;
    for (i = 0; i < KF_M * KF_N; ++i) {
        out[i] = 0;
    }
    out[0 * KF_N + 0] = 1;
    out[1 * KF_N + 1] = 1;
}
