"""Reference-data generator: the 31 manoeuvres of :mod:`kftune.sim.catalogue`, simulated on
CommonRoad's multi-body plant (:mod:`kftune.sim.plant`), measured by the sensor models of
:mod:`kftune.sim.sensors`. Needs the extra ``[simulate]`` (commonroad-vehicle-models).

``generate_dataset(seed)`` is deterministic on one machine: the plant and drivers do not
depend on the seed at all (LSODA on the same programme gives the same numbers; on another
CPU its BLAS kernels may round differently, so a few stored values can differ by one
storage step, see :mod:`kftune.sim._libm`), the sensor noise of each
manoeuvre comes from ``numpy.random.default_rng([seed, crc32(name)])`` — so a manoeuvre's
noise does not change when others are added or left out — and every channel is rounded to
a fixed number of decimals before it is stored, so that the files are short and a written
and re-read dataset is bit-identical to the generated one.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterable
from importlib import metadata

import numpy as np

from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.sim.catalogue import default_catalogue
from kftune.sim.plant import MultiBodyPlant, PlantSetup
from kftune.sim.sensors import SensorModel, measure
from kftune.sim.simulate import SAMPLE_TIME, ManoeuvreSpec, ramp_steer_understeer, simulate
from kftune.vehicle.params import preset

#: Seed of the bundled default dataset.
DEFAULT_SEED = 2024

#: Decimals each stored channel is rounded to (below every sensor's resolution).
STORAGE_DECIMALS: dict[str, int] = {
    "t": 2,
    "delta": 7,
    "ax": 2,
    "ay": 2,
    "r": 6,
    "vx": 4,
    "beta_ref": 6,
    "vx_true": 4,
    "vy_true": 5,
    "r_true": 6,
    "ay_true": 3,
    "beta_true": 6,
    "roll_true": 5,
}

#: What the extra channels of a generated manoeuvre hold (SI units, ISO signs).
TRUE_CHANNELS: dict[str, str] = {
    "vx_true": "true longitudinal velocity of the sprung-mass CG [m/s]",
    "vy_true": "true lateral velocity of the sprung-mass CG [m/s]",
    "r_true": "true yaw rate [rad/s]",
    "ay_true": "true lateral acceleration v̇y + r·vx, road-plane axes [m/s²]",
    "beta_true": "true sideslip atan2(vy, vx) [rad]",
    "roll_true": "body roll angle, positive right side down [rad]",
}


def manoeuvre_rng(seed: int, name: str) -> np.random.Generator:
    """The sensor-noise generator of one manoeuvre: depends on the seed and its name only."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode("utf-8"))])


def generate_manoeuvre(
    spec: ManoeuvreSpec,
    seed: int,
    plant: MultiBodyPlant | None = None,
    sensors: SensorModel | None = None,
) -> Manoeuvre:
    """Simulate one manoeuvre and measure it.

    Returns:
        A :class:`~kftune.data.manoeuvre.Manoeuvre` with the sensor channels and the true
        channels of :data:`TRUE_CHANNELS` as extras, rounded per :data:`STORAGE_DECIMALS`.
    """
    plant = plant if plant is not None else MultiBodyPlant()
    sensors = sensors if sensors is not None else SensorModel()
    truth = simulate(spec, plant)
    measured = measure(truth.out, float(plant.p.R_w), sensors, manoeuvre_rng(seed, spec.name))
    o = truth.out
    channels = {
        "t": truth.t,
        **measured,
        "vx_true": o.vx,
        "vy_true": o.vy,
        "r_true": o.r,
        "ay_true": o.ay,
        "beta_true": o.beta,
        "roll_true": o.roll,
    }
    c = {k: np.round(v, STORAGE_DECIMALS[k]) for k, v in channels.items()}
    return Manoeuvre(
        name=spec.name,
        kind=spec.kind,
        split=spec.split,
        t=c["t"],
        delta=c["delta"],
        ax=c["ax"],
        ay=c["ay"],
        r=c["r"],
        vx=c["vx"],
        beta_ref=c["beta_ref"],
        extra={k: c[k] for k in TRUE_CHANNELS},
        description=spec.description,
    )


def generate_dataset(
    seed: int = DEFAULT_SEED,
    names: Iterable[str] | None = None,
    sensors: SensorModel | None = None,
    setup: PlantSetup | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> Dataset:
    """Generate the reference dataset (all 31 manoeuvres, or the ``names`` given).

    Args:
        seed: drives all sensor noise. names: a subset of the catalogue, in catalogue
            order. sensors: sensor magnitudes. setup: plant changes (tyres, roll bars).
        progress: called as ``progress(name, i, total)`` before each manoeuvre.

    Returns:
        A :class:`~kftune.data.manoeuvre.Dataset` with the ``bmw-320i`` vehicle preset (the
        single-track parameters an engineer identifies on this plant) and provenance in
        ``meta``.
    """
    sensors = sensors if sensors is not None else SensorModel()
    plant = MultiBodyPlant(setup)
    catalogue = default_catalogue()
    if names is not None:
        wanted = list(names)
        known = {s.name for s in catalogue}
        unknown = [n for n in wanted if n not in known]
        if unknown:
            raise ValueError(f"unknown manoeuvre(s) {unknown}; known: {sorted(known)}")
        catalogue = tuple(s for s in catalogue if s.name in set(wanted))
    manoeuvres = []
    for i, spec in enumerate(catalogue):
        if progress is not None:
            progress(spec.name, i, len(catalogue))
        manoeuvres.append(generate_manoeuvre(spec, seed, plant, sensors))
    k_us, _ = ramp_steer_understeer(plant)
    try:
        cr_version = metadata.version("commonroad-vehicle-models")
    except metadata.PackageNotFoundError:  # pragma: no cover
        cr_version = "unknown"
    from kftune import __version__

    meta = {
        "generator": {
            "seed": int(seed),
            "kftune_version": __version__,
            "plant": "commonroad-vehicle-models vehicle_dynamics_mb, parameter set 2 (BMW 320i)",
            "commonroad_vehicle_models_version": cr_version,
            "integrator": "scipy solve_ivp LSODA, rtol 1e-6, atol 1e-6, max step 0.02 s",
            "understeer_gradient_rad_per_mps2": round(k_us, 6),
            "understeer_gradient_deg_per_g": round(float(np.degrees(k_us) * 9.81), 3),
        },
        "plant_setup": {
            k: v if isinstance(v, bool) else float(v) for k, v in vars(plant.setup).items()
        },
        "sensor_model": sensors.to_dict(),
        "true_channels": dict(TRUE_CHANNELS),
    }
    return Dataset(
        name="default" if names is None else "default-subset",
        vehicle=preset("bmw-320i"),
        dt=SAMPLE_TIME,
        manoeuvres=tuple(manoeuvres),
        description=(
            "Reference manoeuvres simulated on CommonRoad's multi-body model (BMW 320i, "
            "per-axle tyres, anti-roll bars) with automotive sensor models; 8 training and "
            "23 test manoeuvres following paper Sec. V-A."
        ),
        meta=meta,
    )
