"""Vehicle model: parameters, Dugoff tyre, single-track process and measurement models.

The parameter record (:mod:`kftune.vehicle.params`) is imported with the package; the
physics (:mod:`kftune.vehicle.single_track`, :mod:`kftune.vehicle.tyre`, numba code) only
when one of its names is first used (PEP 562), so that a layer that may use the parameter
record but not the physics (``kftune.tuning``, tests/test_architecture.py) does not load it
by importing the record.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from kftune.vehicle.params import PARAM_INDEX, PRESETS, G, VehicleParams, preset

if TYPE_CHECKING:
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

#: The physics' names, by the module that defines them (imported on first use).
_LAZY = {
    **dict.fromkeys(
        (
            "axle_loads",
            "derivatives",
            "lateral_forces",
            "measure",
            "pack_params",
            "simulate",
            "slip_angles",
            "step_rk4",
        ),
        "kftune.vehicle.single_track",
    ),
    "dugoff_lateral_force": "kftune.vehicle.tyre",
}

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


def __getattr__(name: str) -> object:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'kftune.vehicle' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
