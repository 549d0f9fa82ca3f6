"""The reference plant: CommonRoad's multi-body model, wrapped (never rewritten).

The plant is ``vehiclemodels.vehicle_dynamics_mb`` of the PyPI package
``commonroad-vehicle-models`` (Althoff & Würsching, "CommonRoad: Vehicle Models", 2020,
Sec. 6: 29 states, sprung and unsprung masses with roll and pitch, Pacejka combined-slip
tyres) with vehicle parameter set 2 (BMW 320i). It is independent of kftune's own
single-track model on purpose: tuning against data from it is the same problem as tuning on
a real car — model mismatch, load transfer, roll, nonlinear tyres.

This module runs CommonRoad's own function object unchanged and only wraps it:

* **Per-axle tyres.** The package uses one tyre parameter set for all four wheels, and its
  lateral stiffness is proportional to load (``K_y = p_ky1·F_z``), so the axle cornering
  stiffnesses are in exactly the ratio of the axle loads and the car is neutral-steer
  (measured: −0.05 deg/g). Real passenger cars understeer. The wrapper runs the original
  code with a tyre module whose ``formula_lateral`` uses a front and a rear parameter set
  (:class:`PlantSetup`); everything else of the tyre model is CommonRoad's. The same setup
  replaces the (negative) auxiliary roll stiffnesses by anti-roll bars, see there.
* **Signs.** The MB model is written in the SAE J670 frame (x forward, y right, z down;
  a positive yaw rate turns right; its "left" wheels are at y = −T/2). kftune uses ISO 8855
  (y left, z up): lateral quantities flip sign at this boundary (δ, vy, r, ay, yaw angle,
  Y position), roll keeps its sign (both: positive = right side down) and pitch flips
  (ISO: positive = nose down; SAE: nose up). :meth:`MultiBodyPlant.outputs` returns ISO.
* **Guards.** Its longitudinal slip ``1 − R_w·ω/u_w`` divides by the wheel's ground speed
  ``u_w``, which the model clips to 0 when negative; the wrapper refuses states in which
  any wheel's ground speed is below :data:`MIN_WHEEL_SPEED` with a
  :class:`SimulationError` naming the wheel, instead of a bare ``ZeroDivisionError``. It
  also passes a copy of the state: the model writes into its argument ("negative wheel
  spin forbidden"), which would corrupt the integrator's own state vector.
"""

from __future__ import annotations

import math
import types
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from kftune.errors import ConfigError, KftuneError
from kftune.sim import _libm

#: Smallest wheel ground speed [m/s] the wrapper lets the model see (its slip divides by it).
MIN_WHEEL_SPEED = 0.5

#: Index of each of the model's 29 states (CommonRoad MB documentation, Sec. 6, SAE signs).
STATE = {
    "x": 0,
    "y": 1,
    "delta": 2,
    "vx": 3,
    "psi": 4,
    "r": 5,
    "roll": 6,
    "roll_rate": 7,
    "pitch": 8,
    "pitch_rate": 9,
    "vy": 10,
    "z": 11,
    "vz": 12,
    "omega_lf": 23,
    "omega_rf": 24,
    "omega_lr": 25,
    "omega_rr": 26,
}
N_STATES = 29


class SimulationError(KftuneError):
    """The plant left the region where it is defined (or the integrator failed)."""


@dataclass(frozen=True)
class PlantSetup:
    """What the wrapper changes in CommonRoad's parameter set 2: tyres per axle, roll bars.

    ``*_p_ky1`` are CommonRoad's cornering stiffness per unit load, ``K_y = p_ky1·F_z``
    [N/rad per N], negative in its sign convention; the package's single value is −21.92
    (both axles: neutral steer, and stiff: 64 kN/rad per tyre at static load). The defaults
    lower both to effective axle values that also stand in for the steering and suspension
    compliance the MB model lacks, the front more than the rear (−9.5 and −14: 28 and
    34 kN/rad per tyre at static load); with them the plant's understeer gradient, measured by
    :func:`kftune.sim.simulate.ramp_steer_understeer` (constant-speed ramp steer, ISO
    4138), is 3.68e-3 rad/(m/s²) = 2.07 deg/g, typical of a passenger car. Peak friction,
    curvature and the combined-slip functions stay CommonRoad's.

    ``K_tsf``/``K_tsr`` [N·m/rad] replace the model's auxiliary torsion roll stiffnesses per
    axle (anti-roll bars), in the model's own convention: *negative adds roll stiffness*
    (the parameter set has −6.9 and −2.6 kN·m/rad, "normally negative"). With those the body
    rolls about 9 deg/g, twice what a saloon with proper anti-roll bars does, and the
    roll-induced gravity error of a body-fixed accelerometer would be ~16 % of ay. The
    defaults (stiffer bars, slightly front-biased) give 4.9 deg/g, measured on the ramp
    steer of :func:`kftune.sim.simulate.ramp_steer_understeer`. A stronger front bias lifts
    the inside front wheel near 1 g (the MB tyre spring then pulls on the road, see
    :meth:`MultiBodyPlant.tyre_loads`).

    ``zero_lateral_offsets`` sets the lateral shifts ``p_hy1`` and ``p_vy1`` to 0. CommonRoad
    applies them as ``sign(γ)·(p_hy1 + p_hy3·|γ|)`` and ``sign(γ)·F_z·(p_vy1 + p_vy3·|γ|)``
    (Pacejka's MF has no sign(γ) there): a side force of 3.7 % of the wheel load that switches
    sign when the camber γ crosses 0. Near γ = 0 that discontinuity makes the right-hand side
    non-smooth and settles the car into a pull (0.3 °/s yaw rate with the wheel straight at
    90 km/h). Without the constant parts, the camber terms p_hy3·γ and p_vy3·γ·F_z remain —
    continuous and mirror-symmetric.
    """

    front_p_ky1: float = -9.5
    rear_p_ky1: float = -14.0
    K_tsf: float = -35.0e3
    K_tsr: float = -25.0e3
    zero_lateral_offsets: bool = True

    def __post_init__(self) -> None:
        for name in ("front_p_ky1", "rear_p_ky1"):
            value = getattr(self, name)
            if not (math.isfinite(value) and -60.0 < value < 0.0):
                raise ValueError(
                    f"PlantSetup.{name} must be in (−60, 0) (CommonRoad's sign convention), "
                    f"got {value!r}"
                )
        for name in ("K_tsf", "K_tsr"):
            value = getattr(self, name)
            if not (math.isfinite(value) and -2.0e5 < value <= 0.0):
                raise ValueError(
                    f"PlantSetup.{name} must be in (−2e5, 0] N·m/rad (negative = stiffer), "
                    f"got {value!r}"
                )


#: CommonRoad's own tyres and roll stiffness (neutral steer, ~9 deg/g roll), for comparison.
COMMONROAD_SETUP = PlantSetup(-21.92, -21.92, -6914.881688272133, -2643.6009520155308, False)


class _PerAxleTyreModule:
    """Stands in for ``vehiclemodels.utils.tire_model`` inside the MB model's globals.

    The MB model evaluates ``formula_lateral`` exactly four times per call, in the fixed
    order LF, RF, LR, RR; the first two calls get the front parameters, the last two the
    rear. :meth:`MultiBodyPlant.derivatives` resets the counter before each call and checks
    afterwards that it saw four calls, so a change of the package cannot go unnoticed.
    """

    def __init__(self, tire_module: types.ModuleType, front: Any, rear: Any) -> None:
        self._tm = tire_module
        self.front = front
        self.rear = rear
        self.calls = 0
        self.formula_longitudinal = tire_module.formula_longitudinal
        self.formula_longitudinal_comb = tire_module.formula_longitudinal_comb
        self.formula_lateral_comb = tire_module.formula_lateral_comb

    def formula_lateral(self, alpha: float, gamma: float, F_z: float, _p: Any) -> list[float]:
        params = self.front if self.calls < 2 else self.rear
        self.calls += 1
        return self._tm.formula_lateral(alpha, gamma, F_z, params)


class PlantOutputs(NamedTuple):
    """Plant quantities at given instants, ISO 8855 signs, SI units; arrays (n,).

    ``ax``/``ay`` are the accelerations of the sprung mass's CG in the body's road-plane
    axes (v̇x − r·vy, v̇y + r·vx); ``roll``/``pitch`` are the sprung mass's angles (positive
    = right side down / nose down); ``omega`` is (n, 4) wheel speeds [rad/s] in the order
    LF, RF, LR, RR; ``X``, ``Y``, ``psi`` the position [m] and yaw angle [rad].
    """

    delta: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    r: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    omega: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    psi: np.ndarray

    @property
    def beta(self) -> np.ndarray:
        """Sideslip at the CG, atan2(vy, vx) [rad], positive = velocity left of the x axis."""
        return _libm.arctan2(self.vy, self.vx)


class MultiBodyPlant:
    """CommonRoad's MB model (parameter set 2) with per-axle tyres, ISO signs and guards.

    Attributes:
        p: the CommonRoad parameter object (roll stiffnesses from ``setup``; its ``tire`` is
            the package's own set, the per-axle changes live in the tyre wrapper).
        setup: the per-axle tyre and roll-stiffness changes in use.
    """

    def __init__(self, setup: PlantSetup | None = None) -> None:
        try:
            import vehiclemodels.utils.tire_model as tire_model
            import vehiclemodels.vehicle_dynamics_mb as mb_module
            from vehiclemodels.init_mb import init_mb
            from vehiclemodels.parameters_vehicle2 import parameters_vehicle2
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ConfigError(
                "the reference-data generator needs the optional dependency "
                "commonroad-vehicle-models: pip install 'kftune[simulate]'"
            ) from exc
        self.setup = setup if setup is not None else PlantSetup()
        self.p = replace(
            parameters_vehicle2(),
            K_tsf=self.setup.K_tsf,
            K_tsr=self.setup.K_tsr,
        )
        self._init_mb = init_mb
        offsets = {"p_hy1": 0.0, "p_vy1": 0.0} if self.setup.zero_lateral_offsets else {}
        self._tyre_module = _PerAxleTyreModule(
            tire_model,
            replace(self.p.tire, p_ky1=self.setup.front_p_ky1, **offsets),
            replace(self.p.tire, p_ky1=self.setup.rear_p_ky1, **offsets),
        )
        # CommonRoad's own code object, run with a globals dict in which ``tireModel`` is
        # the per-axle module; the package itself is left untouched.
        original = mb_module.vehicle_dynamics_mb
        namespace = dict(mb_module.__dict__)
        namespace["tireModel"] = self._tyre_module
        self._mb = types.FunctionType(
            original.__code__, namespace, original.__name__, original.__defaults__
        )

    # -- geometry and loads ------------------------------------------------------------
    @property
    def wheelbase(self) -> float:
        """a + b [m]."""
        return float(self.p.a + self.p.b)

    def static_axle_loads(self) -> tuple[float, float]:
        """Static vertical load on the front and rear axle [N] (as ``init_mb`` sets it)."""
        p, g = self.p, 9.81
        front = p.m_s * g * p.b / (p.a + p.b) + p.m_uf * g
        rear = p.m_s * g * p.a / (p.a + p.b) + p.m_ur * g
        return float(front), float(rear)

    def axle_cornering_stiffness(self) -> tuple[float, float]:
        """Linear cornering stiffness of each axle at static load [N/rad] (both tyres).

        The Pacejka slope at zero slip is B·C·D = K_y = |p_ky1|·F_z per tyre (CommonRoad's
        simplification K_y0 = p_ky1·F_z), so the axle value is |p_ky1|·F_z,axle.
        """
        front, rear = self.static_axle_loads()
        return abs(self.setup.front_p_ky1) * front, abs(self.setup.rear_p_ky1) * rear

    # -- states ------------------------------------------------------------------------
    def initial_state(self, speed: float, delta: float = 0.0) -> np.ndarray:
        """Equilibrium-like initial state for straight driving at ``speed`` [m/s].

        Returns:
            (29,) state (CommonRoad's ``init_mb``: static tyre deflections, wheels rolling).
        """
        if not speed > 2.0:
            raise ValueError(f"initial speed must be > 2 m/s, got {speed!r}")
        return np.asarray(self._init_mb([0.0, 0.0, -delta, speed, 0.0, 0.0, 0.0], self.p))

    def wheel_ground_speeds(self, x: list[float]) -> tuple[float, float, float, float]:
        """Longitudinal ground speed of each wheel centre [m/s] (LF, RF, LR, RR).

        The same expressions the MB model uses before dividing by them.
        """
        p = self.p
        cd, sd = math.cos(x[2]), math.sin(x[2])
        lat_f = (x[10] + p.a * x[5]) * sd
        return (
            (x[3] + 0.5 * p.T_f * x[5]) * cd + lat_f,
            (x[3] - 0.5 * p.T_f * x[5]) * cd + lat_f,
            x[3] + 0.5 * p.T_r * x[5],
            x[3] - 0.5 * p.T_r * x[5],
        )

    def tyre_loads(self, x: np.ndarray) -> np.ndarray:
        """Vertical tyre loads [N] (n, 4) in the order LF, RF, LR, RR for states (n, 29).

        The MB model's tyre is a linear spring (``K_zt``) without a contact condition: a
        negative value means the wheel has lifted and the model would pull on the road.
        """
        x = np.atleast_2d(x)
        p = self.p
        out = np.empty((x.shape[0], 4))
        for j, (z, phi, track) in enumerate(((16, 13, p.T_f), (21, 18, p.T_r))):
            base = x[:, z] + p.R_w * (_libm.cos(x[:, phi]) - 1.0)
            half = 0.5 * track * _libm.sin(x[:, phi])
            out[:, 2 * j] = (base - half) * p.K_zt
            out[:, 2 * j + 1] = (base + half) * p.K_zt
        return out

    def wheel_slips(self, x: list[float]) -> tuple[float, float, float, float]:
        """Longitudinal slip 1 − R_w·ω/u_w of each wheel (LF, RF, LR, RR) [-], as the MB
        model defines it (positive when braking); requires ground speeds > 0."""
        R = self.p.R_w
        u = self.wheel_ground_speeds(x)
        return tuple(1.0 - R * x[23 + i] / u[i] for i in range(4))

    def derivatives(self, x: list[float], steer_rate: float, accel: float) -> list[float]:
        """Time derivative of the 29 states.

        Args:
            x: (29,) state (SAE signs, as the model keeps it); not modified.
            steer_rate: road-wheel steering rate [rad/s], **ISO sign** (positive = left);
                the model limits it to ±``p.steering.v_max``.
            accel: longitudinal acceleration demand [m/s²]; the model turns it into
                engine (rear) or brake (split ``T_sb``) torque and limits it.

        Raises:
            SimulationError: a wheel's ground speed is below :data:`MIN_WHEEL_SPEED`.
        """
        x = [float(v) for v in x]  # Python floats: numpy scalars would turn 1/0 into inf
        speeds = self.wheel_ground_speeds(x)
        for wheel, slowest in zip(("front-left", "front-right", "rear-left", "rear-right"), speeds):
            if slowest >= MIN_WHEEL_SPEED:  # written so that NaN fails too
                continue
            raise SimulationError(
                f"{wheel} wheel ground speed {slowest:.3g} m/s is below {MIN_WHEEL_SPEED} m/s "
                f"(vx = {x[3]:.3g} m/s, yaw rate = {-x[5]:.3g} rad/s): the MB model's "
                "longitudinal slip divides by it; keep the manoeuvre's speed up (did the car "
                "spin?)"
            )
        tm = self._tyre_module
        tm.calls = 0
        f = self._mb(x, [-float(steer_rate), float(accel)], self.p)
        if tm.calls != 4:  # pragma: no cover - only if the package changes
            raise SimulationError(
                f"CommonRoad's MB model called formula_lateral {tm.calls} times, expected 4 "
                "(LF, RF, LR, RR); the per-axle tyre wrapper does not fit this version"
            )
        return f

    def outputs(self, x: np.ndarray, xdot: np.ndarray) -> PlantOutputs:
        """ISO-signed plant quantities from states and their derivatives.

        Args:
            x: (n, 29) states. xdot: (n, 29) their time derivatives.
        """
        x = np.atleast_2d(x)
        xdot = np.atleast_2d(xdot)
        vx, vy_sae, r_sae = x[:, 3], x[:, 10], x[:, 5]
        ax = xdot[:, 3] - r_sae * vy_sae  # v̇x − r·vy (the product has the same sign in SAE)
        ay_sae = xdot[:, 10] + r_sae * vx  # v̇y + r·vx, SAE sign
        return PlantOutputs(
            delta=-x[:, 2],
            vx=vx.copy(),
            vy=-vy_sae,
            r=-r_sae,
            ax=ax,
            ay=-ay_sae,
            roll=x[:, 6].copy(),
            pitch=-x[:, 8],
            omega=x[:, 23:27].copy(),
            X=x[:, 0].copy(),
            Y=-x[:, 1],
            psi=-x[:, 4],
        )
