"""A user model for kftune: the linear-tyre single-track ("bicycle") model.

Tune it on the bundled data with

    kftune tune --model examples/linear_bicycle.py -n 40

States x = [vx, vy, r] [m/s, m/s, rad/s], inputs u = [delta, ax] [rad, m/s^2],
measurements z = [vx, ay, r] [m/s, m/s^2, rad/s]: the channel names of a kftune dataset, so
the filter reads them from the data by name. Lateral tyre forces are linear in the slip
angles (F = C * alpha), integrated with one explicit Euler step per sample. The output
"beta" (the sideslip angle) lets the paper's cost score it against the data's beta_ref.

The same model in C99 is linear_bicycle.c beside this file (c_code below), so that
``kftune export --format c`` can write a running filter for it; check the two against
each other on the data with

    kftune export lin.json --format c -o lin_c --model examples/linear_bicycle.py --check default
"""

from pathlib import Path

import numpy as np
from numba import njit

from kftune.models import StateSpaceModel

#: The same model in C99, for `kftune export --format c`. A copy of this file without the
#: .c beside it still runs and tunes; only the C export then refuses it (no C code).
C_SOURCE = Path(__file__).with_name("linear_bicycle.c")

# m [kg], Iz [kg m^2], a, b [m] (CoG to front/rear axle), C_f, C_r [N/rad]: a BMW 320i
PARAMS = (1093.3, 1791.6, 1.156, 1.423, 55600.0, 68220.0)


@njit
def _forces(x: np.ndarray, u: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    vx, vy, r = x[0], x[1], x[2]
    alpha_f = u[0] - (vy + p[2] * r) / vx
    alpha_r = -(vy - p[3] * r) / vx
    return p[4] * alpha_f, p[5] * alpha_r


@njit
def f(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """x_k = x_{k-1} + dt * dx/dt (explicit Euler), written into out."""
    fyf, fyr = _forces(x, u, p)
    cd = np.cos(u[0])
    out[0] = x[0] + dt * (u[1] + x[1] * x[2])
    out[1] = x[1] + dt * ((fyf * cd + fyr) / p[0] - x[2] * x[0])
    out[2] = x[2] + dt * ((p[2] * fyf * cd - p[3] * fyr) / p[1])


@njit
def h(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """z = [vx, ay, r] with ay the lateral force over the mass."""
    fyf, fyr = _forces(x, u, p)
    out[0] = x[0]
    out[1] = (fyf * np.cos(u[0]) + fyr) / p[0]
    out[2] = x[2]


def prior(z0: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start at the first measured speed and yaw rate, vy = 0, variances from R."""
    x0 = np.array([z0[0], 0.0, z0[2]])
    return x0, np.diag([r[0], (0.05 * z0[0]) ** 2, r[2]])


MODEL = StateSpaceModel(
    name="linear-bicycle",
    state_names=("vx", "vy", "r"),
    state_units=("m/s", "m/s", "rad/s"),
    input_names=("delta", "ax"),
    input_units=("rad", "m/s^2"),
    measurement_names=("vx", "ay", "r"),
    measurement_units=("m/s", "m/s^2", "rad/s"),
    f=f,
    h=h,
    param_names=("m", "Iz", "a", "b", "C_f", "C_r"),
    param_units=("kg", "kg*m^2", "m", "m", "N/rad", "N/rad"),
    param_defaults=PARAMS,
    initial_state=prior,
    outputs={"beta": lambda x: np.arctan2(x[:, 1], x[:, 0])},
    description="single-track model with linear tyres, explicit Euler",
    c_code=C_SOURCE.read_text() if C_SOURCE.is_file() else None,
)
