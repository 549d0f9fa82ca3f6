"""Vehicle model: parameters, Dugoff tyre, single-track process and measurement models."""

from kftune.vehicle.params import PARAM_INDEX, PRESETS, G, VehicleParams, preset
from kftune.vehicle.single_track import (
    axle_loads,
    derivatives,
    lateral_forces,
    measure,
    pack_params,
    simulate,
    slip_angles,
    step_rk4,
)
from kftune.vehicle.tyre import dugoff_lateral_force

__all__ = [
    "PARAM_INDEX",
    "PRESETS",
    "G",
    "VehicleParams",
    "axle_loads",
    "derivatives",
    "dugoff_lateral_force",
    "lateral_forces",
    "measure",
    "pack_params",
    "preset",
    "simulate",
    "slip_angles",
    "step_rk4",
]
