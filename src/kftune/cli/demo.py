"""``kftune demo``: the UKF on a built-in simulated manoeuvre, with sideslip KPIs.

A one-second look at the filter without any data: a sine-steer with growing amplitude
and a braking pulse is simulated with the single-track/Dugoff model (the plant, integrated
with 10 RK4 sub-steps, its cornering stiffnesses off by ``--stiffness-error`` from the
filter's, because a filter's model is never exact), seeded sensor noise is added, and the
compiled UKF estimates the sideslip angle. Prints RMSE, MAE (maximum absolute error) and both
restricted to |ay| ≥ 4 m/s², in degrees (paper Sec. V-D).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass

import numpy as np

from kftune.filters import UKF, FilterResult
from kftune.models import SINGLE_TRACK
from kftune.tuning.kpi import sideslip_kpis
from kftune.vehicle import VehicleParams, measure, preset, simulate

#: Sensor noise standard deviations of the demo (SI): δ, ax (inputs); Vx, ay, r (outputs).
#: Road-wheel angle 0.03° (≈ 0.5° at the hand wheel), accelerometers 0.1 m/s², wheel-speed
#: based Vx 0.05 m/s, gyro 0.2 °/s — typical of series-production ESC sensors.
SENSOR_STD = {
    "delta": math.radians(0.03),
    "ax": 0.1,
    "Vx": 0.05,
    "ay": 0.1,
    "r": math.radians(0.2),
}

#: Final road-wheel amplitude of the demo's growing sine steer [deg].
MAX_STEER_DEG = 7.0

#: Default process-noise variances of the demo [(m/s)², (m/s)², (rad/s)²] per 10 ms step:
#: a hand-set (untuned) choice of the kind the tuner replaces.
DEFAULT_Q = (1e-4, 1e-4, 1e-5)


@dataclass(frozen=True, eq=False)
class DemoManoeuvre:
    """A simulated manoeuvre.

    Attributes:
        dt: sample time [s].
        u: (N, 2) measured inputs [δ rad, ax m/s²] (with sensor noise).
        z: (N, 3) measurements [Vx m/s, ay m/s², r rad/s] (with sensor noise).
        x_true: (N, 3) plant states [Vx, Vy, r].
        ay_true: (N,) plant lateral acceleration [m/s²].
        params: the filter's vehicle parameters (the plant's differ by the stiffness error).
        r_var: (3,) variances of the measurement noise added to z (the filter's R).
    """

    dt: float
    u: np.ndarray
    z: np.ndarray
    x_true: np.ndarray
    ay_true: np.ndarray
    params: VehicleParams
    r_var: np.ndarray

    @property
    def beta_true(self) -> np.ndarray:
        """(N,) plant sideslip atan2(Vy, Vx) [rad]."""
        return np.arctan2(self.x_true[:, 1], self.x_true[:, 0])


def demo_inputs(duration: float = 20.0, dt: float = 0.01) -> np.ndarray:
    """Noise-free inputs of the demo manoeuvre: (N, 2) [δ rad, ax m/s²].

    A 0.5 Hz sine steer whose road-wheel amplitude grows linearly from 0.5° to
    ``MAX_STEER_DEG`` (with the BMW preset at 22 m/s this reaches |ay| ≈ 8 m/s², about 80 %
    of μ·g, and a sideslip of about 5°, deep in the Dugoff saturation), and a 2 s braking pulse of
    −3 m/s² followed by +1.5 m/s² to recover speed.
    """
    t = np.arange(round(duration / dt)) * dt
    amp = np.radians(0.5 + (MAX_STEER_DEG - 0.5) * t / duration)
    delta = amp * np.sin(2.0 * np.pi * 0.5 * t)
    ax = np.where((t >= 0.4 * duration) & (t < 0.4 * duration + 2.0), -3.0, 0.0)
    ax = ax + np.where((t >= 0.4 * duration + 2.0) & (t < 0.4 * duration + 6.0), 1.5, 0.0)
    return np.column_stack([delta, ax])


def demo_manoeuvre(
    seed: int = 0,
    *,
    params: VehicleParams | None = None,
    speed: float = 22.0,
    duration: float = 20.0,
    dt: float = 0.01,
    stiffness_error: float = 0.1,
) -> DemoManoeuvre:
    """Simulate the demo manoeuvre with seeded sensor noise.

    Args:
        seed: drives all the noise.
        params: the filter's vehicle parameters (default: the ``bmw-320i`` preset).
        speed: initial speed [m/s].
        duration, dt: length and sample time [s].
        stiffness_error: the plant's axle cornering stiffnesses are (1 − error) times the
            filter's [-], in [0, 1).
    """
    if not 0.0 <= stiffness_error < 1.0:
        raise ValueError(f"stiffness_error must be in [0, 1), got {stiffness_error!r}")
    params = preset("bmw-320i") if params is None else params
    plant = params.replace(
        C_af=params.C_af * (1.0 - stiffness_error), C_ar=params.C_ar * (1.0 - stiffness_error)
    )
    rng = np.random.default_rng(seed)
    u_true = demo_inputs(duration, dt)
    x_true = simulate([speed, 0.0, 0.0], u_true, plant, dt, substeps=10)
    z_true = measure(x_true, u_true, plant)
    n = u_true.shape[0]
    u_std = np.array([SENSOR_STD["delta"], SENSOR_STD["ax"]])
    z_std = np.array([SENSOR_STD["Vx"], SENSOR_STD["ay"], SENSOR_STD["r"]])
    u = u_true + rng.standard_normal((n, 2)) * u_std
    z = z_true + rng.standard_normal((n, 3)) * z_std
    return DemoManoeuvre(
        dt=dt, u=u, z=z, x_true=x_true, ay_true=z_true[:, 1], params=params, r_var=z_std**2
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo",
        help="run the UKF on a built-in simulated manoeuvre and print sideslip KPIs",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the sensor noise (default 0)")
    p.add_argument(
        "--q",
        type=float,
        nargs=3,
        metavar=("Q_VX", "Q_VY", "Q_R"),
        default=list(DEFAULT_Q),
        help="process-noise variances per step [(m/s)^2 (m/s)^2 (rad/s)^2] "
        f"(default {' '.join(map(str, DEFAULT_Q))})",
    )
    p.add_argument(
        "--stiffness-error",
        type=float,
        default=0.1,
        help="plant cornering stiffness = (1 - this) x the filter's (default 0.1)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, filter, print KPIs; exit code 1 if the filter diverged."""
    from kftune.cli.exit_codes import EXIT_FAILURE, EXIT_OK, EXIT_USAGE

    try:
        man = demo_manoeuvre(args.seed, stiffness_error=args.stiffness_error)
        res: FilterResult = UKF().run(
            SINGLE_TRACK, man.u, man.z, man.dt, args.q, man.r_var, params=man.params
        )
    except ValueError as exc:
        print(f"kftune demo: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    out: dict[str, object] = {
        "manoeuvre": f"sine steer 0.5 Hz, 0.5°→{MAX_STEER_DEG:g}° road-wheel, braking pulse; "
        "BMW 320i preset",
        "samples": int(man.u.shape[0]),
        "dt_s": man.dt,
        "seed": args.seed,
        "q": list(map(float, args.q)),
        "r": man.r_var.tolist(),
        "stiffness_error": args.stiffness_error,
        "max_abs_ay_m_s2": float(np.max(np.abs(man.ay_true))),
        "max_abs_beta_deg": float(np.degrees(np.max(np.abs(man.beta_true)))),
        "diverged": res.diverged,
        "diverged_step": res.diverged_step,
        "diverged_reason": res.diverged_reason,
    }
    if not res.diverged:
        kpis = sideslip_kpis(res.output("beta"), man.beta_true, man.z[:, 1])
        out["kpis_deg"] = {k: kpis[k] for k in ("rmse", "mae", "rmse_non", "mae_non")}
        out["n_non"] = kpis["n_non"]
    if args.json:
        print(json.dumps(out))
    else:
        print(f"kftune demo — {out['manoeuvre']}")
        print(
            f"  {out['samples']} samples at {man.dt * 1000:.0f} ms, max |ay| "
            f"{out['max_abs_ay_m_s2']:.1f} m/s², max |β| {out['max_abs_beta_deg']:.2f}°, "
            f"plant stiffness error {args.stiffness_error:.0%}, seed {args.seed}"
        )
        r_text = ", ".join(f"{v:.3g}" for v in man.r_var)  # numbers, not quoted strings
        print(f"  UKF q = {out['q']}, r = [{r_text}]")
        if res.diverged:
            print(f"  the filter DIVERGED at step {res.diverged_step}: {res.diverged_reason}")
        else:
            k = out["kpis_deg"]
            assert isinstance(k, dict)
            print(f"  sideslip KPIs [deg] (NON: |ay| >= 4 m/s², {out['n_non']} samples):")
            print(f"    RMSE     {k['rmse']:.4f}    MAE     {k['mae']:.4f}")
            print(f"    RMSE_NON {k['rmse_non']:.4f}    MAE_NON {k['mae_non']:.4f}")
            print("    (MAE: maximum absolute error)")
    return EXIT_FAILURE if res.diverged else EXIT_OK
