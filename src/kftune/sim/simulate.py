"""Closed-loop simulation of the reference plant: phases of driver laws, LSODA, 100 Hz.

A manoeuvre is a sequence of :class:`Phase` objects, each with a steering law and a speed
law (:mod:`kftune.sim.drivers`). The driver closes its loops inside the right-hand side of
the ODE, so one LSODA run per phase integrates plant and driver together (``rtol`` 1e-6,
steps at most :data:`MAX_STEP`); the states are read at the 100 Hz sample instants from the
solver's own output (no re-stepping). Deterministic: same specification, same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from kftune.sim.drivers import (
    DriverView,
    Profile,
    SpeedLaw,
    SpeedProfile,
    SteerLaw,
    SteerProfile,
    slip_control,
    speed_control,
    steering_rate,
)
from kftune.sim.plant import N_STATES, MultiBodyPlant, PlantOutputs, SimulationError

#: Output sample time [s] (100 Hz, as the sensors).
SAMPLE_TIME = 0.01
#: Largest integrator step [s]: the driver programmes change on this scale.
MAX_STEP = 0.02
#: Right-hand-side evaluations per simulated second beyond which the integrator is deemed
#: stalled (a healthy run needs a few hundred).
MAX_EVALS_PER_SECOND = 20000
RTOL = 1e-6
ATOL = 1e-6


@dataclass(frozen=True)
class Hold:
    """Steering law marker: hold the road-wheel angle reached at the phase start
    (ISO 7975: steering wheel held during braking)."""


@dataclass(frozen=True)
class Brake:
    """Speed law marker: constant deceleration ``decel`` [m/s² > 0] from the speed at the
    phase start down to ``v_end`` [m/s], then hold ``v_end``."""

    decel: float
    v_end: float


@dataclass(frozen=True)
class Phase:
    """One stretch of a manoeuvre: ``duration`` [s] under one steering and one speed law."""

    duration: float
    steer: SteerLaw | Hold
    speed: SpeedLaw | Brake


@dataclass(frozen=True)
class ManoeuvreSpec:
    """A manoeuvre of the reference set, before simulation.

    Attributes:
        name: unique name (also the file stem). kind: manoeuvre type. split: train|test.
        v0: initial speed [m/s] (straight driving). phases: the driver programme.
        description: one line, the standard it follows and its parameters.
    """

    name: str
    kind: str
    split: str
    v0: float
    phases: tuple[Phase, ...]
    description: str = ""
    meta: dict[str, float] = field(default_factory=dict)

    @property
    def duration(self) -> float:
        """Total duration [s]."""
        return float(sum(p.duration for p in self.phases))


@dataclass(frozen=True)
class Truth:
    """The plant's true motion at the sample instants.

    Attributes:
        t: (n,) [s] from 0 at SAMPLE_TIME. out: plant outputs (ISO signs).
        accel_demand: (n,) the speed controller's demand [m/s²].
    """

    t: np.ndarray
    out: PlantOutputs
    accel_demand: np.ndarray


def _view(t: float, x: list[float]) -> DriverView:
    """The driver's view of the state, in ISO signs (the plant keeps SAE)."""
    return DriverView(t=t, X=x[0], Y=-x[1], psi=-x[4], vx=x[3], vy=-x[10], r=-x[5], delta=-x[2])


def _closed_loop(
    plant: MultiBodyPlant, steer: SteerLaw, speed: SpeedLaw, t: float, x: list[float]
) -> tuple[list[float], float]:
    """Right-hand side of plant + driver: 29 plant derivatives, then the derivatives of the
    speed-error integral and of the steering trim; also the acceleration demand [m/s²]."""
    view = _view(t, x)
    d_ref, d_rate_ref, trim_rate = steer.target(view, x[N_STATES + 1])
    v_ref, dv_ref = speed.reference(view)
    plant_x = x[:N_STATES]
    accel = speed_control(v_ref, dv_ref, x[3], x[N_STATES])
    accel = slip_control(accel, plant.wheel_slips(plant_x))
    f = plant.derivatives(plant_x, steering_rate(d_ref, d_rate_ref, view.delta), accel)
    f.append(v_ref - x[3])
    f.append(trim_rate)
    return f, accel


class _RightHandSide:
    """``f(t, y)`` for solve_ivp, with an evaluation budget that turns a stalled integrator
    (steps shrinking without end) into a clear error instead of a hang."""

    def __init__(self, plant: MultiBodyPlant, steer: SteerLaw, speed: SpeedLaw, budget: float):
        self.plant, self.steer, self.speed, self.budget = plant, steer, speed, budget

    def __call__(self, t: float, y: np.ndarray) -> list[float]:
        self.budget -= 1
        if self.budget < 0:
            raise SimulationError(f"integrator stalled near t = {t:.3f} s")
        return _closed_loop(self.plant, self.steer, self.speed, t, y.tolist())[0]


def _bind_phase(phase: Phase, t0: float, x: list[float]) -> tuple[SteerLaw, SpeedLaw]:
    """Turn the phase's markers into laws, using the state at the phase start."""
    steer = phase.steer
    if isinstance(steer, Hold):
        steer = SteerProfile(Profile([t0], [-x[2]]))
    speed = phase.speed
    if isinstance(speed, Brake):
        v0 = x[3]
        v_end = min(speed.v_end, v0)
        t_stop = t0 + max((v0 - v_end) / speed.decel, 1e-3)
        speed = SpeedProfile(Profile([t0, t_stop], [v0, v_end]))
    return steer, speed


def simulate(
    spec: ManoeuvreSpec, plant: MultiBodyPlant | None = None, stop_ay: float | None = None
) -> Truth:
    """Integrate plant and driver through all phases and sample at 100 Hz.

    Args:
        spec: the manoeuvre. plant: the plant (a default one when None).
        stop_ay: if given, end the simulation early when the steady-state lateral
            acceleration V·|r| first reaches this value [m/s²] (used by ramp tests).

    Returns:
        :class:`Truth` with n = round(duration / SAMPLE_TIME) + 1 samples.

    Raises:
        SimulationError: the car left the plant's domain (see
            :class:`~kftune.sim.plant.MultiBodyPlant`) or the integrator failed; the
            message names the manoeuvre and the time.
    """
    plant = plant if plant is not None else MultiBodyPlant()
    dt = SAMPLE_TIME
    y = np.concatenate([plant.initial_state(spec.v0), [0.0, 0.0]])
    t_start = 0.0
    chunks: list[np.ndarray] = []
    times: list[np.ndarray] = []
    laws: list[tuple[SteerLaw, SpeedLaw, int]] = []
    k0 = 0
    n_phases = len(spec.phases)
    for i, phase in enumerate(spec.phases):
        k1 = round((t_start + phase.duration) / dt)
        t_end = k1 * dt
        steer, speed = _bind_phase(phase, t_start, y[:N_STATES].tolist())

        rhs = _RightHandSide(plant, steer, speed, MAX_EVALS_PER_SECOND * max(phase.duration, 1.0))
        last = i == n_phases - 1
        t_eval = np.arange(k0, k1 + 1) * dt
        events = None
        if stop_ay is not None:

            def events(t: float, yy: np.ndarray) -> float:
                return math.hypot(yy[3], yy[10]) * abs(yy[5]) - stop_ay

            events.terminal = True  # type: ignore[attr-defined]  # read by solve_ivp
        try:
            sol = solve_ivp(
                rhs,
                (t_start, t_end),
                y,
                method="LSODA",
                t_eval=t_eval,
                rtol=RTOL,
                atol=ATOL,
                max_step=MAX_STEP,
                events=events,
            )
        except SimulationError as exc:
            raise SimulationError(f"manoeuvre {spec.name!r}, phase {i + 1}: {exc}") from None
        stopped = sol.status == 1
        if sol.status not in (0, 1):
            raise SimulationError(
                f"manoeuvre {spec.name!r}, phase {i + 1}: LSODA failed at "
                f"t = {sol.t[-1] if sol.t.size else t_start:.3f} s: {sol.message}"
            )
        keep = slice(None) if (last or stopped) else slice(0, -1)
        chunks.append(sol.y[:, keep])
        times.append(sol.t[keep])
        laws.append((steer, speed, sol.t[keep].size))
        if stopped:
            break
        y = sol.y[:, -1].copy()
        t_start, k0 = t_end, k1
    Y = np.concatenate(chunks, axis=1).T
    t = np.concatenate(times)
    # Derivatives and controller demand at the samples, from the same laws.
    xdot = np.empty((t.size, N_STATES))
    accel = np.empty(t.size)
    j = 0
    for steer, speed, count in laws:
        for k in range(j, j + count):
            f, accel[k] = _closed_loop(plant, steer, speed, float(t[k]), Y[k].tolist())
            xdot[k] = f[:N_STATES]
        j += count
    if not np.all(np.isfinite(Y)):
        raise SimulationError(f"manoeuvre {spec.name!r}: non-finite plant state")
    loads = plant.tyre_loads(Y[:, :N_STATES])
    if loads.min() < 0.0:
        k, w = (int(i) for i in np.unravel_index(int(np.argmin(loads)), loads.shape))
        wheel = ("front-left", "front-right", "rear-left", "rear-right")[w]
        raise SimulationError(
            f"manoeuvre {spec.name!r}: the {wheel} wheel lifts off at t = {t[k]:.2f} s "
            f"(load {loads[k, w]:.0f} N); the MB model has no tyre contact condition, so the "
            "data would be unphysical: make the manoeuvre less severe"
        )
    out = plant.outputs(Y[:, :N_STATES], xdot)
    return Truth(t=t - t[0], out=out, accel_demand=accel)


def steady_state_delta(ay: float, speed: float, wheelbase: float, understeer: float) -> float:
    """Road-wheel angle for steady cornering at ``ay`` [m/s²] and ``speed`` [m/s]:
    δ = L/R + K_us·ay with R = V²/ay (Gillespie Eq. 6-15) [rad]."""
    return wheelbase * ay / (speed * speed) + understeer * ay


def ramp_steer_understeer(
    plant: MultiBodyPlant | None = None,
    speed: float = 25.0,
    rate: float = 0.001,
    ay_range: tuple[float, float] = (0.5, 3.0),
) -> tuple[float, Truth]:
    """Understeer gradient of the plant from a constant-speed ramp steer (ISO 4138,
    constant-speed method).

    At constant speed V the road-wheel angle is ramped slowly (``rate`` [rad/s]); in steady
    state δ = L/R + K_us·ay with 1/R = r/V and ay = V·r (Gillespie Eq. 6-15), so K_us is the
    slope of δ − L·r/V over ay, fitted on ``ay_range`` [m/s²] (the linear range).

    Returns:
        ``(K_us [rad/(m/s²)], truth)``; K_us > 0 is understeer (deg/g = K_us·g·180/π).
    """
    plant = plant if plant is not None else MultiBodyPlant()
    t_ramp = 0.08 / rate
    spec = ManoeuvreSpec(
        name="ramp-steer",
        kind="spiral",
        split="test",
        v0=speed,
        phases=(
            Phase(
                2.0 + t_ramp,
                SteerProfile(Profile([2.0, 2.0 + t_ramp], [0.0, 0.08])),
                SpeedProfile(Profile([0.0], [speed])),
            ),
        ),
    )
    # stop well before the limit: only the linear range is needed, and a neutral or
    # oversteering plant would spin at the end of the ramp
    truth = simulate(spec, plant, stop_ay=ay_range[1] + 1.0)
    o = truth.out
    v = np.hypot(o.vx, o.vy)
    ay_ss = v * o.r
    sel = (ay_ss >= ay_range[0]) & (ay_ss <= ay_range[1])
    if np.count_nonzero(sel) < 50:
        raise SimulationError("ramp steer did not cover the requested ay range")
    k_us = float(np.polyfit(ay_ss[sel], o.delta[sel] - plant.wheelbase * o.r[sel] / v[sel], 1)[0])
    return k_us, truth


__all__ = [
    "MAX_STEP",
    "SAMPLE_TIME",
    "Brake",
    "Hold",
    "ManoeuvreSpec",
    "Phase",
    "Truth",
    "ramp_steer_understeer",
    "simulate",
    "steady_state_delta",
]
