"""Vehicle model: parameters, Dugoff tyre, single-track process and measurement models."""

from kftune.vehicle.params import G, PARAM_INDEX, PRESETS, VehicleParams, preset

__all__ = ["G", "PARAM_INDEX", "PRESETS", "VehicleParams", "preset"]
