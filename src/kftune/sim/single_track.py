"""Runs simulated on the single-track model itself: data whose model, parameters and noise
are known exactly, for checks of what tuning recovers (identifiability of the tyre
parameters, benchmarks/identifiability.py and the tests), unlike the bundled set's
multi-body plant (:mod:`kftune.sim.plant`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kftune.data import Manoeuvre
from kftune.vehicle.params import VehicleParams
from kftune.vehicle.single_track import measure, simulate

#: Sensor noise standard deviations of :func:`gentle_slalom`: vx [m/s], ay [m/s²], r [rad/s].
SENSOR_STD: tuple[float, float, float] = (0.05, 0.1, 0.002)


def gentle_slalom(
    name: str,
    vehicle: VehicleParams,
    seed: int,
    ay_peak: float,
    sensor_std: Sequence[float] = SENSOR_STD,
) -> Manoeuvre:
    """A 20-s slalom-like run at 20 m/s (dt 0.01 s, 2,000 samples) simulated on the
    single-track model with ``vehicle``, steered by two sines (0.3 Hz, and 0.8 Hz phased by
    ``seed``) scaled so that the largest |ay| is ``ay_peak`` [m/s²] (linear in the steer
    far from the friction limit), with Gaussian sensor noise of ``sensor_std`` (vx, ay, r;
    drawn with ``seed``) and the true sideslip as its reference ``beta_ref`` [rad].

    A ``"train"`` manoeuvre of kind ``"slalom"``; ax is 0 throughout."""
    dt, n, vx = 0.01, 2000, 20.0
    t = np.arange(n) * dt
    shape = np.sin(2 * np.pi * 0.3 * t) + 0.5 * np.sin(2 * np.pi * 0.8 * t + seed)
    u = np.column_stack([shape, np.zeros(n)])
    x0 = np.array([vx, 0.0, 0.0])
    ay_unit = np.max(np.abs(measure(simulate(x0, u * 0.01, vehicle, dt), u * 0.01, vehicle)[:, 1]))
    u[:, 0] *= 0.01 * ay_peak / ay_unit  # linear regime: |ay| scales with the steer
    x = simulate(x0, u, vehicle, dt)
    z = measure(x, u, vehicle)
    rng = np.random.default_rng(seed)
    z = z + rng.standard_normal(z.shape) * np.asarray(sensor_std, dtype=float)
    return Manoeuvre(
        name,
        "slalom",
        "train",
        t,
        delta=u[:, 0],
        ax=u[:, 1],
        vx=z[:, 0],
        ay=z[:, 1],
        r=z[:, 2],
        beta_ref=np.arctan2(x[:, 1], x[:, 0]),
    )
