"""Vehicle parameters of the single-track (bicycle) model with Dugoff axle forces.

All quantities are SI. The parameter object is frozen: a filter or tuning run can hold it
without copying, and two runs with equal parameters are guaranteed to see the same model.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

#: Gravitational acceleration [m/s²].
G = 9.81

#: Plausible range of each numeric field, (low, high, unit), both ends included: wide
#: enough for any road vehicle from a light quadricycle (≈ 400 kg, 1.7 m wheelbase) to a
#: loaded articulated truck (≈ 40 t, Iz ≈ 3·10⁵ kg·m², 4 m from CG to axle), narrow enough
#: to refuse a typing or unit mistake (grams, millimetres, kN/rad) with a clear message.
#: Cornering stiffness per axle: 40–200 kN/rad for cars, up to ≈ 10⁶ N/rad for trucks;
#: μ from ice (≈ 0.05) to racing slicks on a hot track (≈ 2).
PLAUSIBLE_RANGES: dict[str, tuple[float, float, str]] = {
    "m": (100.0, 60_000.0, "kg"),
    "Iz": (10.0, 1.0e6, "kg·m²"),
    "a": (0.1, 10.0, "m"),
    "b": (0.1, 10.0, "m"),
    "h": (0.0, 3.0, "m"),
    "C_af": (1.0e3, 2.0e6, "N/rad"),
    "C_ar": (1.0e3, 2.0e6, "N/rad"),
    "C_x": (1.0e3, 5.0e6, "N"),
    "mu": (0.05, 2.0, "-"),
    "track_f": (0.3, 3.5, "m"),
    "track_r": (0.3, 3.5, "m"),
    "steering_ratio": (1.0, 50.0, "-"),
}


@dataclass(frozen=True)
class VehicleParams:
    """Single-track model parameters (each within :data:`PLAUSIBLE_RANGES`).

    Attributes:
        m: vehicle mass [kg].
        Iz: yaw moment of inertia about the CG [kg·m²].
        a: distance CG → front axle [m] (often written l_f).
        b: distance CG → rear axle [m] (often written l_r).
        h: CG height above ground [m]; drives longitudinal load transfer.
        C_af: front-axle cornering stiffness [N/rad] (both tyres together).
        C_ar: rear-axle cornering stiffness [N/rad] (both tyres together).
        C_x: longitudinal slip stiffness per axle [N] (Dugoff; only matters with wheel slip).
        mu: tyre–road friction coefficient [-].
        track_f: front track width [m] (informational; the single-track model lumps the axle).
        track_r: rear track width [m] (informational).
        steering_ratio: hand-wheel angle / road-wheel angle [-], used to convert recorded
            hand-wheel angles; ``None`` when the data already hold the road-wheel angle.
        name: a label for reports.
    """

    m: float
    Iz: float
    a: float
    b: float
    h: float
    C_af: float
    C_ar: float
    C_x: float = 1.0e5
    mu: float = 1.0
    track_f: float = 1.5
    track_r: float = 1.5
    steering_ratio: float | None = None
    name: str = "vehicle"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"VehicleParams.name must be a string, got {self.name!r}")
        for name, (low, high, unit) in PLAUSIBLE_RANGES.items():
            value = getattr(self, name)
            if name == "steering_ratio" and value is None:
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
            ):
                raise ValueError(f"VehicleParams.{name} must be a finite number, got {value!r}")
            if not low <= value <= high:
                raise ValueError(
                    f"VehicleParams.{name} = {value!r} {unit} is implausible for a road "
                    f"vehicle: expected {low:g} to {high:g} {unit} (SI units)"
                )

    @property
    def L(self) -> float:
        """Wheelbase a + b [m]."""
        return self.a + self.b

    @property
    def understeer_gradient(self) -> float:
        """Linear understeer gradient K_us = m/L·(b/C_af − a/C_ar) [rad/(m/s²)].

        Positive means understeer (Gillespie, *Fundamentals of Vehicle Dynamics*, Eq. 6-15,
        with axle stiffnesses).
        """
        return self.m / self.L * (self.b / self.C_af - self.a / self.C_ar)

    def to_array(self) -> np.ndarray:
        """Pack the model parameters for the compiled kernels.

        Returns:
            (9,) float64 array ``[m, Iz, a, b, h, C_af, C_ar, C_x, mu]`` (indices in
            :data:`PARAM_INDEX`).
        """
        return np.array(
            [self.m, self.Iz, self.a, self.b, self.h, self.C_af, self.C_ar, self.C_x, self.mu],
            dtype=np.float64,
        )

    def replace(self, **changes: Any) -> VehicleParams:
        """Return a copy with some fields changed (validated again)."""
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict, suitable for JSON/TOML manifests."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VehicleParams:
        """Build from a dict, refusing unknown keys with a message that names them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(
                f"unknown vehicle parameter(s) {unknown}; expected some of {sorted(known)}"
            )
        return cls(**data)


#: Index of each parameter in :meth:`VehicleParams.to_array`.
PARAM_INDEX = {"m": 0, "Iz": 1, "a": 2, "b": 3, "h": 4, "C_af": 5, "C_ar": 6, "C_x": 7, "mu": 8}


def _revs_250lm() -> VehicleParams:
    # ../shared/data/revs-250lm/README.md: the parameters of the authors' own KF
    # (Leanza, Reina & Blanco-Claraco 2021). μ and h are not given reliably there; μ = 1.2
    # sits in the 1.0–1.3 range it quotes for a race car, h = 0.35 m is an assumption for a
    # low race car (it only enters through longitudinal load transfer).
    m = 982.0
    return VehicleParams(
        m=m,
        Iz=m / 12.0 * (1.7**2 + 4.09**2),
        a=1.33,
        b=1.07,
        h=0.35,
        C_af=70.0e3,
        C_ar=120.0e3,
        mu=1.2,
        track_f=1.35,
        track_r=1.35,
        steering_ratio=None,
        name="revs-250lm race car",
    )


def _bmw_320i() -> VehicleParams:
    # CommonRoad vehicle parameter set 2 (BMW 320i; Althoff & Würsching, "CommonRoad:
    # Vehicle Models", 2020): m, I_z, a, b, h_cg, T_f, T_r as given there. The tyre numbers
    # are what an engineer identifies on the reference dataset's plant (kftune.sim.plant,
    # default PlantSetup), i.e. the single-track model of the car the default data come from:
    # - C_af, C_ar: slope of the plant's Pacejka tyres at zero slip and static load. Its
    #   K_y = |p_ky1|·F_z per tyre, so per axle C = |p_ky1|·F_z,axle with the static axle
    #   loads of init_mb, F_z,f = m_s·g·b/L + m_uf·g = 5852.1 N, F_z,r = 4873.1 N, and the
    #   per-axle p_ky1 = −9.5 (front), −14 (rear): C_af = 55.60 kN/rad, C_ar = 68.22 kN/rad
    #   (MultiBodyPlant.axle_cornering_stiffness()). Linear understeer gradient from these,
    #   m/L·(b/C_af − a/C_ar) = 3.66e-3 rad/(m/s²); measured on the plant by a
    #   constant-speed ramp steer (ISO 4138): 3.68e-3 rad/(m/s²) = 2.07 deg/g.
    # - mu: the lateral peak friction p_dy1 = 1.0489 of the plant tyres (zero camber).
    # - C_x: longitudinal slip stiffness p_kx1·F_z = 22.303·F_z at the mean static axle
    #   load (5362.6 N); only used when wheel slip is measured.
    return VehicleParams(
        m=1093.2952334674046,
        Iz=1791.5995300122856,
        a=1.1561957064,
        b=1.4227170936,
        h=0.5748689544,
        C_af=55.60e3,
        C_ar=68.22e3,
        C_x=119.6e3,
        mu=1.05,
        track_f=1.38684,
        track_r=1.36398,
        steering_ratio=15.0,
        name="BMW 320i (CommonRoad parameter set 2)",
    )


#: Named presets; ``PRESETS[name]()`` is not needed — they are built once.
PRESETS: dict[str, VehicleParams] = {
    "revs-250lm": _revs_250lm(),
    "bmw-320i": _bmw_320i(),
}


def preset(name: str) -> VehicleParams:
    """Return a named preset, with a clear error listing the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown vehicle preset {name!r}; known presets: {sorted(PRESETS)}"
        ) from None
