"""Linear-Gaussian state-space models (the filters' exact reference case).

    x_k = F·x_{k−1} + G·u_{k−1} + w,   z_k = H·x_k + D·u_k + v

(Simon, *Optimal State Estimation*, 2006, Ch. 5.1). The matrices are the parameter vector,
p = [F (n·n), G (n·n_u), H (m·n), D (m·n_u)] row-major, so that one pair of compiled
functions serves every size (dimensions are read from the arrays f and h are given) and a
model's matrices can be changed per run like any parameters. dt is not used: F and G are
already the discrete-time matrices. For such a model the UKF and the EKF are both exactly
the Kalman filter, which the tests use.

Every linear model carries its C (:attr:`~kftune.models.StateSpaceModel.c_code`, generated
here): the same loops over p with the sizes of ``kftune_model.h``, F and H as given. Its
prior is the fixed (x0, P0) given to :func:`linear_model`; without one the model has no
prior rule, and the C export refuses it for that reason (the exported filter starts from
``kf_model_prior``).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from kftune.models.base import PriorRule, StateSpaceModel

__all__ = ["linear_model", "linear_params"]


@njit(cache=True, error_model="numpy")
def linear_process(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """out = F·x + G·u with F, G read from p."""
    n = x.shape[0]
    nu = u.shape[0]
    g0 = n * n
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += p[i * n + j] * x[j]
        for j in range(nu):
            s += p[g0 + i * nu + j] * u[j]
        out[i] = s


@njit(cache=True, error_model="numpy")
def linear_measurement(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """out = H·x + D·u with H, D read from p."""
    n = x.shape[0]
    nu = u.shape[0]
    m = out.shape[0]
    h0 = n * n + n * nu
    d0 = h0 + m * n
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += p[h0 + i * n + j] * x[j]
        for j in range(nu):
            s += p[d0 + i * nu + j] * u[j]
        out[i] = s


@njit(cache=True, error_model="numpy")
def linear_process_jacobian(
    x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray
) -> None:
    """out = F."""
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = p[i * n + j]


@njit(cache=True, error_model="numpy")
def linear_measurement_jacobian(
    x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray
) -> None:
    """out = H."""
    n = x.shape[0]
    h0 = n * n + n * u.shape[0]
    for i in range(out.shape[0]):
        for j in range(n):
            out[i, j] = p[h0 + i * n + j]


def _matrices(
    F: ArrayLike, G: ArrayLike | None, H: ArrayLike, D: ArrayLike | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    F_arr = np.atleast_2d(np.asarray(F, dtype=np.float64))
    H_arr = np.atleast_2d(np.asarray(H, dtype=np.float64))
    n, m = F_arr.shape[0], H_arr.shape[0]
    G_arr = np.zeros((n, 0)) if G is None else np.asarray(G, dtype=np.float64).reshape(n, -1)
    nu = G_arr.shape[1]
    D_arr = np.zeros((m, nu)) if D is None else np.asarray(D, dtype=np.float64)
    for name, arr, shape in (
        ("F", F_arr, (n, n)),
        ("G", G_arr, (n, nu)),
        ("H", H_arr, (m, n)),
        ("D", D_arr, (m, nu)),
    ):
        if arr.shape != shape or not np.isfinite(arr).all():
            raise ValueError(f"{name} must be a finite array of shape {shape}, got {arr.shape}")
    return F_arr, G_arr, H_arr, D_arr


def linear_params(
    F: ArrayLike, H: ArrayLike, G: ArrayLike | None = None, D: ArrayLike | None = None
) -> np.ndarray:
    """The parameter vector [F, G, H, D] (row-major) of a linear model.

    Args:
        F: (n, n); H: (m, n); G: (n, n_u) or None (no input); D: (m, n_u) or None (zeros).
    """
    return np.concatenate([a.ravel() for a in _matrices(F, G, H, D)])


#: The C of every linear model (sizes from kftune_model.h), the twin of the compiled
#: functions above, loop for loop: p = [F, G, H, D] row-major.
_LINEAR_C = """\
/* a kftune linear model in C99 (kftune/models/linear.py):
 * x' = F x + G u, z = H x + D u, with p = [F, G, H, D] row-major. */
#include "kftune_model.h"

#define LIN_G0 (KF_N * KF_N)
#define LIN_H0 (LIN_G0 + KF_N * KF_NU)
#define LIN_D0 (LIN_H0 + KF_M * KF_N)

void kf_model_f(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    int i, j;
    (void)dt;
    for (i = 0; i < KF_N; ++i) {
        kf_real s = 0;
        for (j = 0; j < KF_N; ++j) {
            s += p[i * KF_N + j] * x[j];
        }
        for (j = 0; j < KF_NU; ++j) {
            s += p[LIN_G0 + i * KF_NU + j] * w[j];
        }
        out[i] = s;
    }
}

void kf_model_h(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    int i, j;
    for (i = 0; i < KF_M; ++i) {
        kf_real s = 0;
        for (j = 0; j < KF_N; ++j) {
            s += p[LIN_H0 + i * KF_N + j] * x[j];
        }
        for (j = 0; j < KF_NU; ++j) {
            s += p[LIN_D0 + i * KF_NU + j] * w[j];
        }
        out[i] = s;
    }
}

void kf_model_F(const kf_real x[], const kf_real w[], const kf_real p[], kf_real dt,
                kf_real out[])
{
    int i;
    (void)x;
    (void)w;
    (void)dt;
    for (i = 0; i < KF_N * KF_N; ++i) {
        out[i] = p[i];
    }
}

void kf_model_H(const kf_real x[], const kf_real w[], const kf_real p[], kf_real out[])
{
    int i;
    (void)x;
    (void)w;
    for (i = 0; i < KF_M * KF_N; ++i) {
        out[i] = p[LIN_H0 + i];
    }
}

/* a linear model has no outputs */
void kf_model_outputs(const kf_real x[], kf_real y[])
{
    (void)x;
    (void)y;
}
"""

#: The C prior of a linear model with a fixed (x0, P0); the two arrays are filled in.
_LINEAR_PRIOR_C = """
/* the fixed prior given to linear_model: x0 (KF_N), P0 (KF_N*KF_N row-major) */
static const kf_real lin_x0[KF_N] = {{{x0}}};
static const kf_real lin_P0[KF_N * KF_N] = {{{P0}}};

void kf_model_prior(const kf_real z0[], const kf_real r[], const kf_real p[], kf_real x0[],
                    kf_real P0[])
{{
    int i;
    (void)z0;
    (void)r;
    (void)p;
    for (i = 0; i < KF_N; ++i) {{
        x0[i] = lin_x0[i];
    }}
    for (i = 0; i < KF_N * KF_N; ++i) {{
        P0[i] = lin_P0[i];
    }}
}}
"""


def _c_numbers(values: np.ndarray) -> str:
    """C literals of float64 values that read back to the same doubles."""
    return ", ".join(repr(float(v)) for v in values.ravel())


def _fixed_prior(x0: ArrayLike, P0: ArrayLike, n: int) -> tuple[PriorRule, str]:
    """The prior rule returning (x0, P0) whatever the first measurement, and its C."""
    x = np.array(x0, dtype=np.float64).reshape(-1)
    P = np.array(P0, dtype=np.float64)
    if P.ndim == 1:
        P = np.diag(P)
    if x.shape != (n,) or not np.isfinite(x).all():
        raise ValueError(f"x0 must be {n} finite numbers (the prior mean), got {x0!r}")
    if P.shape != (n, n) or not np.isfinite(P).all() or not np.array_equal(P, P.T):
        raise ValueError(
            f"P0 must be a finite symmetric ({n}, {n}) covariance or its ({n},) diagonal, "
            f"got shape {P.shape}"
        )

    def prior(z0: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fixed prior (x0, P0) given to linear_model."""
        return x.copy(), P.copy()

    return prior, _LINEAR_PRIOR_C.format(x0=_c_numbers(x), P0=_c_numbers(P))


def linear_model(
    F: ArrayLike,
    H: ArrayLike,
    G: ArrayLike | None = None,
    D: ArrayLike | None = None,
    *,
    name: str = "linear",
    x0: ArrayLike | None = None,
    P0: ArrayLike | None = None,
) -> StateSpaceModel:
    """A linear model whose default parameters are the given matrices.

    States, inputs and measurements are named x0…, u0…, z0… (no units). Other matrices of
    the same sizes can be given per run as ``params=linear_params(F2, H2, G2, D2)``.

    Args:
        F: (n, n) transition; H: (m, n) measurement matrix; G: (n, n_u) input matrix or None;
        D: (m, n_u) feedthrough or None; name: the model's name.
        x0, P0: a fixed prior, (n,) mean and (n, n) covariance (or its (n,) diagonal), the
            model's prior rule whatever the first measurement — both or neither. Without
            them callers give x0 and P0 per run, and the model cannot be exported as C.
    """
    F_arr, G_arr, H_arr, D_arr = _matrices(F, G, H, D)
    n, nu, m = F_arr.shape[0], G_arr.shape[1], H_arr.shape[0]
    if (x0 is None) != (P0 is None):
        raise ValueError("linear_model needs both x0 and P0 for a fixed prior, or neither")
    prior, prior_c = (None, "") if x0 is None or P0 is None else _fixed_prior(x0, P0, n)
    pnames = tuple(
        f"{mat}[{i},{j}]"
        for mat, (rows, cols) in (("F", (n, n)), ("G", (n, nu)), ("H", (m, n)), ("D", (m, nu)))
        for i in range(rows)
        for j in range(cols)
    )
    return StateSpaceModel(
        name=name,
        state_names=tuple(f"x{i}" for i in range(n)),
        state_units=("",) * n,
        input_names=tuple(f"u{i}" for i in range(nu)),
        input_units=("",) * nu,
        measurement_names=tuple(f"z{i}" for i in range(m)),
        measurement_units=("",) * m,
        f=linear_process,
        h=linear_measurement,
        param_names=pnames,
        param_defaults=tuple(linear_params(F_arr, H_arr, G_arr, D_arr)),
        F=linear_process_jacobian,
        H=linear_measurement_jacobian,
        initial_state=prior,
        c_code=_LINEAR_C + prior_c,
        description=f"linear-Gaussian model, {n} states, {nu} inputs, {m} measurements",
    )
