"""Drivers for the reference plant: a speed-hold controller and steering programmes.

Everything here is a pure function of time and of what a driver sees (position, heading,
speeds, yaw rate, road-wheel angle — ISO 8855 signs), so that the closed loop can sit inside
the integrator's right-hand side: the result is smooth enough for LSODA's error control and
exactly reproducible.

The plant's steering input is the road-wheel angle *rate* (CommonRoad MB model, rate
limited to ±0.4 rad/s). Every steering law here produces a target angle δ_ref and its rate
δ̇_ref; :func:`steering_rate` closes a servo loop on δ around them (a steering robot or a
driver's hands, bandwidth :data:`SERVO_GAIN`).
"""

from __future__ import annotations

import bisect
import itertools
import math
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from kftune.sim import _libm

#: Steering servo bandwidth [1/s]: δ̇ = δ̇_ref + SERVO_GAIN·(δ_ref − δ).
SERVO_GAIN = 20.0


@dataclass
class DriverView:
    """What the driver sees at one instant (ISO 8855 signs, SI units).

    ``s_path`` is filled in by a path-following steering law (arc length of the nearest
    path point [m]) so that a speed law can schedule speed along the path.
    """

    t: float
    X: float
    Y: float
    psi: float
    vx: float
    vy: float
    r: float
    delta: float
    s_path: float = math.nan


def steering_rate(delta_ref: float, delta_rate_ref: float, delta: float) -> float:
    """Servo law of the steering actuator: road-wheel angle rate demand [rad/s]."""
    return delta_rate_ref + SERVO_GAIN * (delta_ref - delta)


# --------------------------------------------------------------------------- profiles
class Profile:
    """Piecewise-linear function of one variable, constant outside its knots.

    Args:
        knots: (k,) strictly increasing abscissae. values: (k,) ordinates.
    """

    def __init__(self, knots: Iterable[float], values: Iterable[float]) -> None:
        k = [float(v) for v in knots]
        v = [float(x) for x in values]
        if len(k) != len(v) or len(k) < 1:
            raise ValueError("Profile needs as many values as knots, at least one")
        if any(b <= a for a, b in itertools.pairwise(k)):
            raise ValueError(f"Profile knots must be strictly increasing, got {k}")
        self.knots, self.values = k, v

    def __call__(self, x: float) -> tuple[float, float]:
        """Value and slope at ``x``."""
        k, v = self.knots, self.values
        i = bisect.bisect_right(k, x)
        if i == 0 or i == len(k):
            return (v[0] if i == 0 else v[-1]), 0.0
        slope = (v[i] - v[i - 1]) / (k[i] - k[i - 1])
        return v[i - 1] + slope * (x - k[i - 1]), slope

    @property
    def end(self) -> float:
        """Last knot."""
        return self.knots[-1]


# --------------------------------------------------------------------------- paths
class Path:
    """A planar reference path: a polyline resampled at uniform arc length.

    Args:
        X, Y: (k,) vertices [m] in the ISO ground frame (X east/forward, Y north/left).
        spacing: resampling step [m].
        loop_from: for a path that ends where it passed at arc length ``loop_from`` [m]
            (a circle after its lead-in), arc lengths beyond the end wrap around to there;
            otherwise the path continues straight beyond its last vertex.
    """

    def __init__(
        self, X: np.ndarray, Y: np.ndarray, spacing: float = 0.5, loop_from: float | None = None
    ) -> None:
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float)
        seg = np.hypot(np.diff(X), np.diff(Y))
        s = np.concatenate([[0.0], np.cumsum(seg)])
        n = max(math.ceil(s[-1] / spacing), 2)
        self.s = np.linspace(0.0, s[-1], n + 1)
        self.X = np.interp(self.s, s, X)
        self.Y = np.interp(self.s, s, Y)
        self.length = float(self.s[-1])
        if loop_from is not None and not 0.0 <= loop_from < self.length:
            raise ValueError(f"loop_from must be in [0, {self.length:.1f}) m, got {loop_from!r}")
        self.loop_from = loop_from

    # Curvature-defined construction (straights, arcs and clothoids), exact heading.
    @classmethod
    def from_curvature(
        cls,
        segments: Sequence[tuple[float, float, float]],
        X0: float = 0.0,
        Y0: float = 0.0,
        psi0: float = 0.0,
        step: float = 0.25,
        loop_from: float | None = None,
    ) -> Path:
        """Integrate heading and position along segments of linearly varying curvature.

        Args:
            segments: ``(length [m], κ_start [1/m], κ_end [1/m])`` each; κ > 0 turns left.
        """
        X, Y, psi = [X0], [Y0], psi0
        for length, k0, k1 in segments:
            n = max(math.ceil(length / step), 1)
            h = length / n
            for i in range(n):
                # midpoint rule on curvature, exact for the heading of a clothoid
                km = k0 + (k1 - k0) * (i + 0.5) / n
                psi_mid = psi + 0.5 * h * km
                X.append(X[-1] + h * math.cos(psi_mid))
                Y.append(Y[-1] + h * math.sin(psi_mid))
                psi += h * km
        return cls(np.array(X), np.array(Y), loop_from=loop_from)

    def project(self, X: float, Y: float) -> float:
        """Arc length [m] of the path point nearest to (X, Y).

        Coarse-to-fine search (every 16th vertex, then the neighbourhood). Beyond the last
        vertex the path continues straight, so the arc length keeps growing there.
        """
        stride = 16
        d2 = (self.X[::stride] - X) ** 2 + (self.Y[::stride] - Y) ** 2
        centre = int(np.argmin(d2)) * stride
        lo, hi = max(centre - 2 * stride, 0), min(centre + 2 * stride + 1, self.s.size)
        d2 = (self.X[lo:hi] - X) ** 2 + (self.Y[lo:hi] - Y) ** 2
        i = lo + int(np.argmin(d2))
        if i == self.s.size - 1 and self.loop_from is None:
            dx, dy = self.X[-1] - self.X[-2], self.Y[-1] - self.Y[-2]
            ahead = ((X - self.X[-1]) * dx + (Y - self.Y[-1]) * dy) / math.hypot(dx, dy)
            return self.length + max(ahead, 0.0)
        # continuous arc length: project onto the two segments that meet at vertex i
        best_d2, best_s = math.inf, float(self.s[i])
        for j in (i - 1, i):
            if j < 0 or j + 1 >= self.s.size:
                continue
            x0, y0 = float(self.X[j]), float(self.Y[j])
            ex, ey = float(self.X[j + 1]) - x0, float(self.Y[j + 1]) - y0
            u = min(max(((X - x0) * ex + (Y - y0) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
            d2_seg = (x0 + u * ex - X) ** 2 + (y0 + u * ey - Y) ** 2
            if d2_seg < best_d2:
                best_d2 = d2_seg
                best_s = float(self.s[j]) + u * (float(self.s[j + 1]) - float(self.s[j]))
        return best_s

    def point_at(self, s: float) -> tuple[float, float]:
        """Position at arc length ``s`` (wrapped or extrapolated beyond the end)."""
        if s > self.length and self.loop_from is not None:
            s = self.loop_from + (s - self.loop_from) % (self.length - self.loop_from)
        if s <= self.length:
            return float(np.interp(s, self.s, self.X)), float(np.interp(s, self.s, self.Y))
        dx, dy = self.X[-1] - self.X[-2], self.Y[-1] - self.Y[-2]
        norm = math.hypot(dx, dy)
        extra = s - self.length
        return float(self.X[-1] + extra * dx / norm), float(self.Y[-1] + extra * dy / norm)


def circle_path(radius: float, direction: int, lead_in: float = 60.0) -> Path:
    """A straight lead-in along +X, a 15 m clothoid entry and one closed lap of a circle
    (driven round and round: arc lengths beyond the end wrap onto the circle).

    Args:
        radius: [m]. direction: +1 counter-clockwise (left turn), −1 clockwise.
    """
    kappa = direction / radius
    return Path.from_curvature(
        [(lead_in, 0.0, 0.0), (15.0, 0.0, kappa), (2.0 * math.pi * radius, kappa, kappa)],
        loop_from=lead_in + 15.0,
    )


def iso3888_1_path(direction: int = 1, offset: float = 3.5, lead_in: float = 80.0) -> Path:
    """Centre line of the ISO 3888-1 double lane change (severe lane change).

    Sections along X [m] from the start (0, 0): lead-in, 15 entry lane, 30 transition, 25
    side lane at lateral ``offset`` [m] (3.5 m centre-line offset), 25 transition, 15 exit
    lane, run-out. The
    transitions are quintic smoothsteps (zero lateral velocity and acceleration at the ends).
    """
    X = np.arange(0.0, lead_in + 15.0 + 30.0 + 25.0 + 25.0 + 15.0 + 60.0, 0.25)

    def smooth(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, 0.0, 1.0)
        return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)  # no pow: see sim._libm

    x = X - lead_in
    Y = direction * offset * (smooth((x - 15.0) / 30.0) - smooth((x - 70.0) / 25.0))
    return Path(X, Y, spacing=0.25)


# --------------------------------------------------------------------------- steering
class SteerLaw(ABC):
    """A steering programme: target road-wheel angle and its rate (ISO sign)."""

    #: True when the law needs the path-curvature integrator state.
    uses_integrator = False

    @abstractmethod
    def target(self, view: DriverView, integrator: float) -> tuple[float, float, float]:
        """Return ``(δ_ref [rad], δ̇_ref [rad/s], d(integrator)/dt)``."""


@dataclass
class SteerProfile(SteerLaw):
    """Open-loop road-wheel angle δ(t), piecewise linear (steps with a finite rate, ramps,
    holds) — what a steering robot executes."""

    profile: Profile

    def target(self, view: DriverView, integrator: float) -> tuple[float, float, float]:
        value, slope = self.profile(view.t)
        return value, slope, 0.0


@dataclass
class SineSteer(SteerLaw):
    """δ = A·w(t)·sin(2πf(t − t0)) for t in [t0, t0 + cycles/f], zero elsewhere.

    The window w rises and falls as a half cosine over the first and last half cycle, so
    the programme starts and ends with zero angle and rate (slalom, sine steer).
    """

    amplitude: float
    frequency: float
    t0: float
    cycles: float

    def target(self, view: DriverView, integrator: float) -> tuple[float, float, float]:
        tau = view.t - self.t0
        duration = self.cycles / self.frequency
        if tau <= 0.0 or tau >= duration:
            return 0.0, 0.0, 0.0
        half = 0.5 / self.frequency
        w = math.pi * self.frequency * 2.0
        if tau < half:
            win = 0.5 - 0.5 * math.cos(math.pi * tau / half)
            dwin = 0.5 * math.pi / half * math.sin(math.pi * tau / half)
        elif tau > duration - half:
            u = (duration - tau) / half
            win = 0.5 - 0.5 * math.cos(math.pi * u)
            dwin = -0.5 * math.pi / half * math.sin(math.pi * u)
        else:
            win, dwin = 1.0, 0.0
        s, c = math.sin(w * tau), math.cos(w * tau)
        a = self.amplitude
        return a * win * s, a * (dwin * s + win * w * c), 0.0


@dataclass
class RandomSteer(SteerLaw):
    """Band-limited random steering: a sum of sines with random phases and 1/f-shaped
    amplitudes, scaled to a given RMS; the programme is fixed by its own ``seed``."""

    rms: float
    f_low: float
    f_high: float
    t0: float
    t1: float
    seed: int
    n_components: int = 24
    _f: np.ndarray = field(init=False, repr=False)
    _a: np.ndarray = field(init=False, repr=False)
    _ph: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        ratio = self.f_high / self.f_low  # geometric spacing, through math (see sim._libm)
        n = self.n_components
        f = np.array([self.f_low * ratio ** (k / max(n - 1, 1)) for k in range(n)])
        f = f * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, f.size))
        a = 1.0 / np.sqrt(f)
        a *= self.rms / math.sqrt(0.5 * float(np.sum(a * a)))
        self._f, self._a, self._ph = f, a, rng.uniform(0.0, 2.0 * math.pi, f.size)

    def target(self, view: DriverView, integrator: float) -> tuple[float, float, float]:
        t = view.t
        if t <= self.t0 or t >= self.t1:
            return 0.0, 0.0, 0.0
        # 1 s cosine fade-in/out
        ramp = 1.0
        dramp = 0.0
        for edge, sign in ((t - self.t0, 1.0), (self.t1 - t, -1.0)):
            if edge < 1.0:
                ramp = 0.5 - 0.5 * math.cos(math.pi * edge)
                dramp = sign * 0.5 * math.pi * math.sin(math.pi * edge)
        w = 2.0 * math.pi * self._f
        arg = w * (t - self.t0) + self._ph
        value = math.fsum(self._a * _libm.sin(arg))  # no BLAS dot: see sim._libm
        rate = math.fsum(self._a * w * _libm.cos(arg))
        return ramp * value, ramp * rate + dramp * value, 0.0


@dataclass
class PathFollower(SteerLaw):
    """Pure-pursuit driver with understeer feed-forward and a slow curvature trim.

    The look-ahead point lies ``preview`` seconds ahead along the path (at least
    ``min_lookahead`` m); its position in axes aligned with the *velocity* (course angle
    ψ + β, so that sideslip does not bias the aim) gives the pure-pursuit curvature
    κ = 2·d_y/ℓ² (Coulter 1992). The road-wheel target is δ = (L + K·V²)·κ + δ_I, where the
    driver's understeer knowledge K [rad·s²/m²… i.e. rad/(m/s²)] turns curvature into angle
    (Gillespie Eq. 6-15) and δ_I integrates the error between demanded and driven curvature
    r/V (the trim a driver applies on a constant-radius circle), rate ``trim_gain`` [1/s].
    """

    path: Path
    wheelbase: float
    understeer: float = 0.0034
    preview: float = 0.7
    min_lookahead: float = 8.0
    trim_gain: float = 0.6

    uses_integrator = True

    def target(self, view: DriverView, integrator: float) -> tuple[float, float, float]:
        speed = math.hypot(view.vx, view.vy)
        s_near = self.path.project(view.X, view.Y)
        view.s_path = s_near
        lookahead = max(self.min_lookahead, self.preview * speed)
        px, py = self.path.point_at(s_near + lookahead)
        course = view.psi + math.atan2(view.vy, view.vx)
        dx, dy = px - view.X, py - view.Y
        ly = -math.sin(course) * dx + math.cos(course) * dy
        kappa = 2.0 * ly / (dx * dx + dy * dy)
        gain = self.wheelbase + self.understeer * speed * speed
        delta = gain * kappa + integrator
        trim_rate = self.trim_gain * gain * (kappa - view.r / max(speed, 1.0))
        return delta, 0.0, trim_rate


# --------------------------------------------------------------------------- speed
class SpeedLaw(ABC):
    """Speed reference for the PI speed-hold controller."""

    @abstractmethod
    def reference(self, view: DriverView) -> tuple[float, float]:
        """Return ``(v_ref [m/s], dv_ref/dt [m/s²])`` (the latter is feed-forward)."""


@dataclass
class SpeedProfile(SpeedLaw):
    """Speed as a piecewise-linear function of time."""

    profile: Profile

    def reference(self, view: DriverView) -> tuple[float, float]:
        return self.profile(view.t)


@dataclass
class PathSpeed(SpeedLaw):
    """Speed as a piecewise-linear function of the arc length along the followed path
    (needs a :class:`PathFollower` steering law in the same phase)."""

    profile: Profile

    def reference(self, view: DriverView) -> tuple[float, float]:
        v, dv_ds = self.profile(view.s_path)
        return v, dv_ds * math.hypot(view.vx, view.vy)


#: PI speed-hold gains: a = dv_ref/dt + KP·(v_ref − vx) + KI·∫(v_ref − vx) dt.
SPEED_KP = 1.5
SPEED_KI = 0.4


def speed_control(v_ref: float, dv_ref: float, vx: float, integral: float) -> float:
    """Acceleration demand of the speed-hold PI controller [m/s²].

    The plant slows down with zero demand (rolling of the Pacejka tyres, cornering drag), so
    the integral term carries the steady-state demand.
    """
    return dv_ref + SPEED_KP * (v_ref - vx) + SPEED_KI * integral


#: Wheel-slip limits of the ABS / traction control [-]: full demand below SLIP_ONSET,
#: none at SLIP_LIMIT, linear in between.
SLIP_ONSET = 0.08
SLIP_LIMIT = 0.15


def slip_control(accel: float, slips: Sequence[float]) -> float:
    """ABS and traction control as a continuous select-low limiter [m/s²].

    The plant turns one acceleration demand into brake torques on all wheels (split
    ``T_sb``) or engine torque on the rear; without a limiter a hard brake in a turn locks a
    wheel (the plant clips ω at 0 and becomes very stiff). The demand is scaled down when
    the largest braking slip (or, when driving, the largest drive slip) exceeds SLIP_ONSET.
    """
    worst = max(slips) if accel < 0.0 else -min(slips)
    factor = min(max((SLIP_LIMIT - worst) / (SLIP_LIMIT - SLIP_ONSET), 0.0), 1.0)
    return accel * factor
