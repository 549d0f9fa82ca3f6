"""Sensor models: what a production car's sensors and a test car's optical sideslip sensor
would report for the plant's true motion, at 100 Hz.

Magnitudes (σ = standard deviation; biases are constant over one manoeuvre, drawn anew for
each) are those of automotive-grade sensors including vehicle vibration:

* IMU (ESC inertial sensor cluster, body-fixed at the sprung-mass CG):
  ax, ay: σ 0.08 m/s² noise, σ 0.05 m/s² bias, 0.01 m/s² resolution; the accelerometers
  measure specific force in body axes, so a rolled/pitched body adds gravity,
  ay_m = ay·cos φ + g·sin φ, ax_m = ax·cos θ − g·sin θ (ISO 8855: roll φ positive right side
  down, pitch θ positive nose down), and a mounting yaw misalignment (σ 0.3°) mixes a little
  ax into ay. Yaw rate: σ 0.2 °/s noise, σ 0.3 °/s bias, 0.01 °/s resolution.
* Vx from the wheel-speed sensors of the two non-driven front wheels (the plant is rear
  driven): each wheel R_w·ω with σ 0.03 m/s noise and 1/64 km/h resolution, a rolling-radius
  error (σ 0.3 %) common to both, averaged and divided by cos δ. Wheel slip when braking
  and the lateral-velocity term of the steered wheels stay in it, as in a real car.
* Road-wheel angle from the steering-wheel angle sensor: hand-wheel angle = ratio·δ with
  0.1° resolution, σ 0.05° noise and a σ 0.5° centre offset, divided by the nominal
  steering ratio (15).
* Reference sideslip from an optical sensor (Correvit-class) at the CG: β + σ 0.05° noise,
  0.01° resolution.

Every draw comes from the ``numpy.random.Generator`` passed in, in a fixed order, so a seed
fixes the result bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from kftune.sim import _libm
from kftune.sim.plant import PlantOutputs
from kftune.vehicle.params import G

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class SensorModel:
    """Noise, bias and resolution of each sensor (SI units; see module docstring)."""

    accel_noise: float = 0.08
    accel_bias: float = 0.05
    accel_resolution: float = 0.01
    imu_misalignment: float = 0.3 * _DEG
    gyro_noise: float = 0.2 * _DEG
    gyro_bias: float = 0.3 * _DEG
    gyro_resolution: float = 0.01 * _DEG
    wheel_speed_noise: float = 0.03
    wheel_speed_resolution: float = 1.0 / 64.0 / 3.6
    rolling_radius_error: float = 0.003
    steering_ratio: float = 15.0
    handwheel_resolution: float = 0.1 * _DEG
    handwheel_noise: float = 0.05 * _DEG
    handwheel_offset: float = 0.5 * _DEG
    beta_noise: float = 0.05 * _DEG
    beta_resolution: float = 0.01 * _DEG

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"SensorModel.{name} must be finite and >= 0, got {value!r}")
        if self.steering_ratio <= 0.0:
            raise ValueError("SensorModel.steering_ratio must be > 0")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for the manifest's provenance table)."""
        return asdict(self)

    def white_noise_variances(self) -> np.ndarray:
        """(3,) variances of the white part of [Vx, ay, r] (noise + LSB²/12): what a noise
        estimator on these data should find. Vx: the mean of two wheels halves the variance.
        """
        q = self.wheel_speed_resolution
        return np.array(
            [
                0.5 * (self.wheel_speed_noise**2 + q * q / 12.0),
                self.accel_noise**2 + self.accel_resolution**2 / 12.0,
                self.gyro_noise**2 + self.gyro_resolution**2 / 12.0,
            ]
        )


def _quantise(x: np.ndarray, lsb: float) -> np.ndarray:
    return x if lsb <= 0.0 else np.round(x / lsb) * lsb


def measure(
    out: PlantOutputs, wheel_radius: float, model: SensorModel, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Sensor readings for the plant's true motion.

    Args:
        out: the plant outputs at the sample instants (ISO signs), arrays (n,).
        wheel_radius: the plant's effective wheel radius R_w [m].
        model: sensor magnitudes. rng: the only source of randomness.

    Returns:
        ``delta`` [rad], ``ax``, ``ay`` [m/s²], ``r`` [rad/s], ``vx`` [m/s], ``beta_ref``
        [rad], each (n,).
    """
    n = out.vx.size
    # Draw order is part of the format's reproducibility: biases first, then noise.
    b_ax, b_ay = rng.normal(0.0, model.accel_bias, 2)
    b_r = rng.normal(0.0, model.gyro_bias)
    misalign = rng.normal(0.0, model.imu_misalignment)
    radius_scale = 1.0 + rng.normal(0.0, model.rolling_radius_error)
    hw_offset = rng.normal(0.0, model.handwheel_offset)
    e_ax = rng.normal(0.0, model.accel_noise, n)
    e_ay = rng.normal(0.0, model.accel_noise, n)
    e_r = rng.normal(0.0, model.gyro_noise, n)
    e_w = rng.normal(0.0, model.wheel_speed_noise, (2, n))
    e_hw = rng.normal(0.0, model.handwheel_noise, n)
    e_beta = rng.normal(0.0, model.beta_noise, n)

    # specific force in body axes (gravity from pitch and roll), then mounting yaw error
    fx = out.ax * _libm.cos(out.pitch) - G * _libm.sin(out.pitch)
    fy = out.ay * _libm.cos(out.roll) + G * _libm.sin(out.roll)
    cm, sm = math.cos(misalign), math.sin(misalign)
    ax_m = _quantise(cm * fx + sm * fy + b_ax + e_ax, model.accel_resolution)
    ay_m = _quantise(-sm * fx + cm * fy + b_ay + e_ay, model.accel_resolution)
    r_m = _quantise(out.r + b_r + e_r, model.gyro_resolution)

    wheels = out.omega[:, :2].T * (wheel_radius * radius_scale) + e_w  # LF, RF [m/s]
    wheels = _quantise(wheels, model.wheel_speed_resolution)
    handwheel = _quantise(
        model.steering_ratio * out.delta + hw_offset + e_hw, model.handwheel_resolution
    )
    delta_m = handwheel / model.steering_ratio
    vx_m = wheels.mean(axis=0) / _libm.cos(delta_m)

    beta_m = _quantise(out.beta + e_beta, model.beta_resolution)
    return {"delta": delta_m, "ax": ax_m, "ay": ay_m, "r": r_m, "vx": vx_m, "beta_ref": beta_m}
