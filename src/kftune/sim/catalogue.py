"""The 31 manoeuvres of the default reference set (paper Sec. V-A), as driver programmes.

Training (8): 1 braking in a turn, 1 skidpad, 2 J-turns, 2 slaloms, 2 lane changes.
Test (23): 2 braking in a turn, 2 skidpads, 5 J-turns, 4 slaloms, 4 lane changes, 2 random
steer, 1 track lap, 3 spirals. Speeds, amplitudes and directions vary; where a standard
exists the programme follows it:

* braking in a turn — ISO 7975: steady state on a circle, then constant deceleration with
  the steering wheel held;
* skidpad — ISO 4138 constant-radius method: follow a circle, speed raised slowly to close
  to the limit;
* J-turn — ISO 7401 step steer: straight at constant speed, steering step at a finite
  rate (0.35 rad/s road wheel ≈ 300 °/s at the hand-wheel), held, released;
* slalom — sine steer with frequency V/(2·cone spacing) (cosine-windowed);
* lane change — ISO 3888-1 double lane change, path-following driver;
* random steer — band-limited random steering (0.1–1.2 Hz) at constant speed;
* track lap — a 1.5 km circuit of straights, clothoids and arcs, speed scheduled along
  the path from the curvature;
* spiral — ISO 4138 constant-speed method: slow steering ramp up to the limit.

Steering amplitudes are sized with the steady-state relation δ = L·ay/V² + K·ay for a
target lateral acceleration, with the plant's measured understeer gradient K; the realised
peaks differ (dynamics, saturation), which is the point of a reference set.
"""

from __future__ import annotations

import math

import numpy as np

from kftune.sim import _libm
from kftune.sim.drivers import (
    Path,
    PathFollower,
    PathSpeed,
    Profile,
    RandomSteer,
    SineSteer,
    SpeedLaw,
    SpeedProfile,
    SteerLaw,
    SteerProfile,
    circle_path,
    iso3888_1_path,
)
from kftune.sim.simulate import Brake, Hold, ManoeuvreSpec, Phase, steady_state_delta

#: Wheelbase of the plant (CommonRoad parameter set 2: a + b) [m].
WHEELBASE = 1.1561957064 + 1.4227170936
#: Understeer gradient used to size amplitudes and by the drivers' feed-forward
#: [rad/(m/s²)]; the plant's measured value with the default setup is 0.00368.
K_DRIVER = 0.0037
#: Preview time of the lane-change driver [s] (a tight, test-driver-like line).
LANE_CHANGE_PREVIEW = 0.6
#: Lateral acceleration the track-lap speed profile is planned for [m/s²].
LAP_AY = 7.0
#: Steering-robot rate for steps and releases [rad/s] (road wheel).
STEP_RATE = 0.35


def kmh(v: float) -> float:
    """km/h → m/s."""
    return v / 3.6


def _const_speed(v: float) -> SpeedProfile:
    return SpeedProfile(Profile([0.0], [v]))


def _delta(ay: float, v: float) -> float:
    return steady_state_delta(ay, v, WHEELBASE, K_DRIVER)


def _follower(path: Path, preview: float = 0.7) -> PathFollower:
    return PathFollower(path=path, wheelbase=WHEELBASE, understeer=K_DRIVER, preview=preview)


def _single_phase(
    name: str,
    kind: str,
    split: str,
    v0: float,
    duration: float,
    steer: SteerLaw,
    speed: SpeedLaw,
    description: str,
    **meta: float,
) -> ManoeuvreSpec:
    """A manoeuvre of one driver phase."""
    return ManoeuvreSpec(
        name=name,
        kind=kind,
        split=split,
        v0=v0,
        phases=(Phase(duration, steer, speed),),
        description=description,
        meta=meta,
    )


def j_turn(name: str, split: str, v_kmh: float, ay: float, direction: int) -> ManoeuvreSpec:
    """ISO 7401 step steer: 2 s straight, step to the steady-state angle for ``ay``
    [m/s²], hold 5 s, release, 3 s straight."""
    v = kmh(v_kmh)
    amp = direction * _delta(ay, v)
    ramp = abs(amp) / STEP_RATE
    t1, t2 = 2.0, 2.0 + ramp + 5.0
    steer = SteerProfile(Profile([t1, t1 + ramp, t2, t2 + ramp], [0.0, amp, amp, 0.0]))
    side = "left" if direction > 0 else "right"
    return _single_phase(
        name,
        "j-turn",
        split,
        v,
        round(t2 + ramp + 3.0, 2),
        steer,
        _const_speed(v),
        f"ISO 7401 step steer {side} at {v_kmh:g} km/h, target ay {ay:g} m/s²",
    )


def slalom(
    name: str, split: str, v_kmh: float, spacing: float, ay: float, cycles: float, direction: int
) -> ManoeuvreSpec:
    """Slalom through cones ``spacing`` m apart: sine steer at V/(2·spacing) Hz."""
    v = kmh(v_kmh)
    freq = v / (2.0 * spacing)
    amp = direction * _delta(ay, v)
    t0 = 2.0
    duration = t0 + cycles / freq + 2.0
    return _single_phase(
        name,
        "slalom",
        split,
        v,
        round(duration, 2),
        SineSteer(amp, freq, t0, cycles),
        _const_speed(v),
        (
            f"slalom at {v_kmh:g} km/h, cones {spacing:g} m apart ({freq:.2f} Hz), "
            f"{cycles:g} cycles, target peak ay {ay:g} m/s²"
        ),
    )


def lane_change(name: str, split: str, v_kmh: float, direction: int) -> ManoeuvreSpec:
    """ISO 3888-1 double lane change at ``v_kmh`` with a path-following driver."""
    v = kmh(v_kmh)
    lead_in = 3.0 * v
    path = iso3888_1_path(direction=direction, lead_in=lead_in)
    duration = (lead_in + 150.0) / v
    side = "left" if direction > 0 else "right"
    return _single_phase(
        name,
        "lane-change",
        split,
        v,
        round(duration, 2),
        _follower(path, LANE_CHANGE_PREVIEW),
        _const_speed(v),
        f"ISO 3888-1 double lane change to the {side} at {v_kmh:g} km/h",
    )


def skidpad(
    name: str, split: str, radius: float, v_start: float, v_end: float, ramp: float, direction: int
) -> ManoeuvreSpec:
    """ISO 4138 constant radius: enter a circle of ``radius`` m at ``v_start`` m/s, raise the
    speed to ``v_end`` m/s over ``ramp`` s, hold 3 s."""
    path = circle_path(radius, direction, lead_in=25.0)
    t_in = 40.0 / v_start + 3.0
    speed = SpeedProfile(Profile([t_in, t_in + ramp], [v_start, v_end]))
    side = "counter-clockwise" if direction > 0 else "clockwise"
    return _single_phase(
        name,
        "skidpad",
        split,
        v_start,
        round(t_in + ramp + 3.0, 2),
        _follower(path),
        speed,
        (
            f"ISO 4138 constant radius R = {radius:g} m {side}, speed {v_start:g} → "
            f"{v_end:g} m/s (ay ≈ {v_start**2 / radius:.1f} → {v_end**2 / radius:.1f} m/s²)"
        ),
        radius=radius,
    )


def braking_in_turn(
    name: str, split: str, radius: float, v_kmh: float, decel: float, direction: int
) -> ManoeuvreSpec:
    """ISO 7975: steady state on a circle of ``radius`` m at ``v_kmh``, then brake at
    ``decel`` m/s² with the steering held, down to 40 % of the speed; hold 2 s."""
    v = kmh(v_kmh)
    path = circle_path(radius, direction, lead_in=30.0)
    t_steady = (45.0 + 0.5 * math.pi * radius) / v + 4.0
    brake_time = 0.6 * v / decel
    side = "left" if direction > 0 else "right"
    return ManoeuvreSpec(
        name=name,
        kind="braking-in-turn",
        split=split,
        v0=v,
        phases=(
            Phase(round(t_steady, 2), _follower(path), _const_speed(v)),
            Phase(round(brake_time + 2.0, 2), Hold(), Brake(decel, 0.4 * v)),
        ),
        description=(
            f"ISO 7975 braking in a {side} turn, R = {radius:g} m at {v_kmh:g} km/h "
            f"(ay ≈ {v * v / radius:.1f} m/s²), deceleration {decel:g} m/s²"
        ),
        meta={"radius": radius},
    )


def spiral(
    name: str, split: str, v_kmh: float, ay_end: float, duration: float, direction: int
) -> ManoeuvreSpec:
    """ISO 4138 constant speed: steering ramped slowly from 0 to the steady-state angle of
    ``ay_end`` (beyond the limit when ay_end is), then released."""
    v = kmh(v_kmh)
    amp = direction * _delta(ay_end, v)
    t1, t2 = 2.0, duration - 3.0
    steer = SteerProfile(Profile([t1, t2, t2 + 1.5], [0.0, amp, 0.0]))
    side = "left" if direction > 0 else "right"
    return _single_phase(
        name,
        "spiral",
        split,
        v,
        duration,
        steer,
        _const_speed(v),
        f"ISO 4138 constant-speed ramp steer {side} at {v_kmh:g} km/h up to "
        f"the angle for ay {ay_end:g} m/s²",
    )


def random_steer(
    name: str, split: str, v_kmh: float, ay_rms: float, duration: float, seed: int
) -> ManoeuvreSpec:
    """Band-limited random steering (0.1–1.2 Hz) at constant speed; RMS angle sized for
    ``ay_rms``; the programme is fixed by ``seed`` (not by the sensor seed)."""
    v = kmh(v_kmh)
    steer = RandomSteer(_delta(ay_rms, v), 0.1, 1.2, 1.0, duration - 1.0, seed)
    return _single_phase(
        name,
        "random-steer",
        split,
        v,
        duration,
        steer,
        _const_speed(v),
        f"random steer at {v_kmh:g} km/h, 0.1–1.2 Hz, RMS sized for ay {ay_rms:g} m/s²",
    )


def track_path() -> Path:
    """A closed circuit of straights, clothoids and arcs, driven counter-clockwise from the
    start of its main straight (about 1.8 km; one lap of heading, 2π).

    The corners are fixed; the lengths of the main straight and of the straight after the
    first corner are solved so that the lap closes on its start point.
    """

    def corner(radius: float, angle_deg: float, clothoid: float = 20.0) -> list:
        k = math.copysign(1.0 / radius, angle_deg)
        arc = abs(math.radians(angle_deg)) * radius - clothoid  # clothoids add half each
        return [(clothoid, 0.0, k), (max(arc, 1.0), k, k), (clothoid, k, 0.0)]

    def layout(main: float, back: float) -> list[tuple[float, float, float]]:
        return [
            (main, 0.0, 0.0),
            *corner(45.0, 120.0),
            (back, 0.0, 0.0),
            *corner(70.0, 60.0),
            (60.0, 0.0, 0.0),
            *corner(35.0, -50.0, 15.0),
            *corner(35.0, 50.0, 15.0),
            (90.0, 0.0, 0.0),
            *corner(110.0, 90.0),
            (110.0, 0.0, 0.0),
            *corner(30.0, 90.0, 15.0),
            (1.0, 0.0, 0.0),
        ]

    # End point is affine in the two free straight lengths (headings 0 and 120 degrees).
    base = Path.from_curvature(layout(1.0, 1.0))
    u_main = np.array([1.0, 0.0])
    u_back = np.array([math.cos(math.radians(120.0)), math.sin(math.radians(120.0))])
    gap = -np.array([base.X[-1], base.Y[-1]])
    # 2×2 solve by Cramer's rule (no LAPACK: see sim._libm)
    det = u_main[0] * u_back[1] - u_back[0] * u_main[1]
    main = (gap[0] * u_back[1] - u_back[0] * gap[1]) / det
    back = (u_main[0] * gap[1] - gap[0] * u_main[1]) / det
    return Path.from_curvature(layout(1.0 + float(main), 1.0 + float(back)))


def _lap_speed_profile(
    path: Path, v_max: float, ay_max: float, a_acc: float, a_brake: float
) -> Profile:
    """Speed along the path: curvature-limited, then accel/brake-limited passes, then
    smoothed."""
    s = path.s
    dx, dy = np.gradient(path.X, s), np.gradient(path.Y, s)
    ddx, ddy = np.gradient(dx, s), np.gradient(dy, s)
    kappa = np.abs(dx * ddy - dy * ddx)
    kappa = _libm.moving_average(np.pad(kappa, 10), 21)  # = convolve(…, "same"), no BLAS
    v = np.minimum(v_max, np.sqrt(ay_max / np.maximum(kappa, 1e-9)))
    for i in range(1, s.size):  # acceleration limit, forwards
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2.0 * a_acc * (s[i] - s[i - 1])))
    for i in range(s.size - 2, -1, -1):  # braking limit, backwards
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * a_brake * (s[i + 1] - s[i])))
    # a driver blends throttle and brake over ~1 s: smooth over 30 m (no ax steps)
    width = 61
    v = _libm.moving_average(np.pad(v, width // 2, mode="edge"), width)
    knots = s[::10]
    return Profile(knots, v[::10])


def track_lap(name: str, split: str) -> ManoeuvreSpec:
    """One lap of :func:`track_path` with a curvature-scheduled speed (ay ≤ LAP_AY)."""
    path = track_path()
    profile = _lap_speed_profile(path, v_max=kmh(130.0), ay_max=LAP_AY, a_acc=2.5, a_brake=6.0)
    v0 = profile.values[0]
    # duration from the profile (distance / speed), a little short of the path end
    s = np.asarray(profile.knots)
    v = np.asarray(profile.values)
    duration = float(np.sum(np.diff(s) / (0.5 * (v[1:] + v[:-1])))) - 3.0
    return _single_phase(
        name,
        "track-lap",
        split,
        v0,
        round(duration, 1),
        _follower(path),
        PathSpeed(profile),
        f"track lap, {path.length:.0f} m circuit, speed scheduled for ay ≤ {LAP_AY:g} m/s²",
    )


def default_catalogue() -> tuple[ManoeuvreSpec, ...]:
    """The 31 manoeuvres (8 training, 23 test) of the bundled reference set."""
    L, R = 1, -1
    train = (
        braking_in_turn("train-01-braking-in-turn", "train", 80.0, 80.0, 5.0, L),
        skidpad("train-02-skidpad", "train", 40.0, 8.0, 18.6, 40.0, L),
        j_turn("train-03-j-turn", "train", 80.0, 5.0, L),
        j_turn("train-04-j-turn", "train", 100.0, 7.5, R),
        slalom("train-05-slalom", "train", 60.0, 18.0, 5.0, 10.0, L),
        slalom("train-06-slalom", "train", 90.0, 36.0, 7.0, 7.0, R),
        lane_change("train-07-lane-change", "train", 72.0, L),
        lane_change("train-08-lane-change", "train", 80.0, R),
    )
    test = (
        braking_in_turn("test-01-braking-in-turn", "test", 100.0, 85.0, 3.0, R),
        braking_in_turn("test-02-braking-in-turn", "test", 60.0, 72.0, 5.5, L),
        skidpad("test-03-skidpad", "test", 60.0, 10.0, 23.0, 40.0, R),
        skidpad("test-04-skidpad", "test", 30.0, 7.0, 16.0, 35.0, L),
        j_turn("test-05-j-turn", "test", 60.0, 4.0, L),
        j_turn("test-06-j-turn", "test", 70.0, 6.0, R),
        j_turn("test-07-j-turn", "test", 90.0, 8.0, L),
        j_turn("test-08-j-turn", "test", 110.0, 5.5, R),
        j_turn("test-09-j-turn", "test", 120.0, 3.5, L),
        slalom("test-10-slalom", "test", 50.0, 18.0, 4.0, 8.0, R),
        slalom("test-11-slalom", "test", 70.0, 24.0, 6.0, 6.0, L),
        slalom("test-12-slalom", "test", 80.0, 30.0, 7.5, 6.0, R),
        slalom("test-13-slalom", "test", 100.0, 36.0, 5.0, 5.0, L),
        lane_change("test-14-lane-change", "test", 65.0, L),
        lane_change("test-15-lane-change", "test", 75.0, R),
        lane_change("test-16-lane-change", "test", 85.0, L),
        lane_change("test-17-lane-change", "test", 90.0, R),
        random_steer("test-18-random-steer", "test", 70.0, 3.5, 30.0, seed=18),
        random_steer("test-19-random-steer", "test", 90.0, 4.5, 30.0, seed=19),
        track_lap("test-20-track-lap", "test"),
        spiral("test-21-spiral", "test", 50.0, 9.5, 30.0, L),
        spiral("test-22-spiral", "test", 70.0, 9.5, 30.0, R),
        spiral("test-23-spiral", "test", 90.0, 9.0, 30.0, L),
    )
    return train + test
