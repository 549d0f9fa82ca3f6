"""The reference plant and its drivers: physics sanity against closed-form vehicle dynamics.

References used (independent of the code under test): steady cornering kinematics r = V/R;
the linear single-track steady state (Gillespie, *Fundamentals of Vehicle Dynamics*,
Eqs. 6-15 and 6-21: δ = L/R + K_us·ay, β = b/R − m·a·V²/(L·C_ar·R)); the accelerometer's
specific force in a rolled body; CommonRoad's own unwrapped function.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("vehiclemodels")

from vehiclemodels.parameters_vehicle2 import parameters_vehicle2
from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb

from kftune.sim.catalogue import K_DRIVER, WHEELBASE, j_turn
from kftune.sim.drivers import (
    PathFollower,
    Profile,
    SpeedLaw,
    SpeedProfile,
    SteerProfile,
    circle_path,
)
from kftune.sim.plant import (
    COMMONROAD_SETUP,
    MultiBodyPlant,
    PlantSetup,
    SimulationError,
)
from kftune.sim.sensors import SensorModel, measure
from kftune.sim.simulate import (
    ManoeuvreSpec,
    Phase,
    ramp_steer_understeer,
    simulate,
)
from kftune.vehicle import G, preset

RADIUS = 40.0
SPEED = 12.0


@pytest.fixture(scope="module")
def plant() -> MultiBodyPlant:
    return MultiBodyPlant()


@pytest.fixture(scope="module")
def circle(plant):
    """25 s on a 40 m circle to the left at a constant 12 m/s (ay ≈ 3.6 m/s²)."""
    follower = PathFollower(circle_path(RADIUS, +1, lead_in=20.0), WHEELBASE, K_DRIVER)
    spec = ManoeuvreSpec(
        "circle",
        "skidpad",
        "test",
        SPEED,
        (Phase(25.0, follower, SpeedProfile(Profile([0.0], [SPEED]))),),
    )
    truth = simulate(spec, plant)
    return truth, truth.t >= 20.0


def test_skidpad_steady_state_yaw_rate_is_speed_over_radius(circle):
    truth, ss = circle
    o = truth.out
    v = np.hypot(o.vx, o.vy)[ss]
    # kinematics of steady circular motion: r = V/R (R the nominal circle radius)
    assert np.mean(o.r[ss]) == pytest.approx(np.mean(v) / RADIUS, rel=0.01)
    # and the driven path is that circle (least-squares circle fit of the positions)
    X, Y = o.X[ss], o.Y[ss]
    A = np.column_stack([2 * X, 2 * Y, np.ones_like(X)])
    c = np.linalg.lstsq(A, X**2 + Y**2, rcond=None)[0]
    assert math.sqrt(c[2] + c[0] ** 2 + c[1] ** 2) == pytest.approx(RADIUS, rel=0.01)
    # centripetal acceleration V²/R, and the speed controller holds the set speed
    assert np.mean(o.ay[ss]) == pytest.approx(np.mean(v) ** 2 / RADIUS, rel=0.01)
    assert np.all(np.abs(o.vx[ss] - SPEED) < 0.05)


def test_skidpad_matches_linear_single_track_steady_state(circle):
    """In the linear range the plant agrees with the single-track steady state computed
    from the bmw-320i preset (whose stiffnesses were identified on this plant)."""
    truth, ss = circle
    o, p = truth.out, preset("bmw-320i")
    v = float(np.mean(np.hypot(o.vx, o.vy)[ss]))
    ay = v * v / RADIUS
    beta_lin = p.b / RADIUS - p.m * p.a * v * v / (p.L * p.C_ar * RADIUS)
    delta_lin = p.L / RADIUS + p.understeer_gradient * ay
    assert math.degrees(np.mean(o.beta[ss])) == pytest.approx(math.degrees(beta_lin), abs=0.1)
    assert math.degrees(np.mean(o.delta[ss])) == pytest.approx(math.degrees(delta_lin), abs=0.2)


def test_iso_signs_in_a_left_turn(circle):
    """ISO 8855 at the plant's boundary: a left turn has δ, r, ay > 0; at 12 m/s on 40 m the
    CG velocity points left of the x axis (β > 0, kinematic b/R dominates); the body rolls
    outwards (right side down, roll > 0), so a body-fixed accelerometer reads more than ay."""
    truth, ss = circle
    o = truth.out
    for name in ("delta", "r", "ay", "roll"):
        assert np.all(getattr(o, name)[ss] > 0), name
    assert np.all(o.beta[ss] > 0)
    quiet = SensorModel(**{k: 0.0 for k in SensorModel().to_dict() if k != "steering_ratio"})
    m = measure(o, 0.344, quiet, np.random.default_rng(0))
    expected = o.ay * np.cos(o.roll) + G * np.sin(o.roll)
    np.testing.assert_allclose(m["ay"], expected, atol=1e-12)
    assert np.all(m["ay"][ss] > o.ay[ss])
    np.testing.assert_allclose(m["beta_ref"], o.beta, atol=1e-12)
    np.testing.assert_allclose(m["r"], o.r, atol=1e-12)
    np.testing.assert_allclose(m["delta"], o.delta, atol=1e-12)


def test_j_turns_left_and_right_mirror_each_other(plant):
    """High-speed J-turns: left → r, ay > 0 and β < 0 (the rear slips outwards); the right
    turn is the mirror image (up to the tyres' slip-induced side forces, r_vy*)."""
    left = simulate(j_turn("l", "test", 90.0, 6.0, +1), plant).out
    right = simulate(j_turn("r", "test", 90.0, 6.0, -1), plant).out
    hold = slice(400, 700)
    assert np.all(left.r[hold] > 0) and np.all(left.ay[hold] > 0)
    assert np.all(left.beta[hold] < 0)
    for name in ("r", "ay", "beta", "delta", "vy"):
        a, b = getattr(left, name), getattr(right, name)
        assert np.max(np.abs(a + b)) < 0.04 * np.max(np.abs(a)), name
    np.testing.assert_allclose(left.vx, right.vx, rtol=1e-3)


def test_understeer_gradient_commonroad_neutral_adjusted_realistic():
    """The package's tyres are neutral steer (the known trap); the per-axle setup gives a
    passenger-car understeer gradient, close to the linear theory of the preset's axle
    stiffnesses, K_us = m/L·(b/C_af − a/C_ar)."""
    k_cr, _ = ramp_steer_understeer(MultiBodyPlant(COMMONROAD_SETUP))
    k_us, _ = ramp_steer_understeer(MultiBodyPlant())
    assert abs(math.degrees(k_cr) * G) < 0.2  # deg/g
    assert 1.0 < math.degrees(k_us) * G < 3.0
    assert k_us == pytest.approx(preset("bmw-320i").understeer_gradient, rel=0.05)


def test_preset_stiffness_is_the_plants_at_static_load(plant):
    c_f, c_r = plant.axle_cornering_stiffness()
    p = preset("bmw-320i")
    assert p.C_af == pytest.approx(c_f, rel=1e-3)
    assert p.C_ar == pytest.approx(c_r, rel=1e-3)
    assert p.mu == pytest.approx(plant.p.tire.p_dy1, rel=0.01)


def test_wrapper_is_commonroads_function_when_setup_is_the_packages():
    """With the package's own tyre and roll numbers the wrapper returns exactly what
    CommonRoad's vehicle_dynamics_mb returns (steering rate sign converted ISO → SAE)."""
    wrapped = MultiBodyPlant(COMMONROAD_SETUP)
    p = parameters_vehicle2()
    x = list(wrapped.initial_state(20.0, delta=0.02))
    x[5], x[10] = 0.1, 0.3  # some yaw rate and lateral velocity
    assert wrapped.derivatives(list(x), 0.05, 0.7) == vehicle_dynamics_mb(list(x), [-0.05, 0.7], p)


def test_per_axle_tyres_change_only_the_lateral_stiffness(plant):
    """Front p_ky1 changes the front slip-stiffness only: doubling it changes the yaw
    acceleration but not the wheel-spin derivatives of a free-rolling straight state."""
    x = list(plant.initial_state(20.0, delta=0.02))
    softer = MultiBodyPlant(PlantSetup(front_p_ky1=-5.5))
    f0, f1 = plant.derivatives(list(x), 0.0, 0.0), softer.derivatives(list(x), 0.0, 0.0)
    assert f1[5] != f0[5]  # yaw acceleration responds to the front cornering force
    assert abs(f1[5]) < abs(f0[5])
    assert f1[23:27] == f0[23:27]  # wheel spin (ω̇ of the four wheels): longitudinal only
    # Straight ahead there is no slip angle: the lateral stiffness changes nothing at all.
    x = list(plant.initial_state(20.0, delta=0.0))
    assert softer.derivatives(list(x), 0.0, 0.0) == plant.derivatives(list(x), 0.0, 0.0)


def test_wheel_speed_guard_replaces_division_by_zero(plant):
    """CommonRoad's slip 1 − R·ω/u_w divides by a wheel's ground speed (clipped to 0 when
    negative): the raw model raises ZeroDivisionError, the wrapper a clear error."""
    x = plant.initial_state(20.0).tolist()
    x[3] = 0.3  # slow, and yawing fast: the inner rear wheel's ground speed is negative
    x[5] = 1.0
    with pytest.raises(ZeroDivisionError):
        vehicle_dynamics_mb(list(x), [0.0, 0.0], parameters_vehicle2())
    with pytest.raises(SimulationError, match="wheel ground speed"):
        plant.derivatives(list(x), 0.0, 0.0)


def test_derivatives_do_not_modify_the_state(plant):
    """The MB model writes into its argument ("negative wheel spin forbidden"); the wrapper
    must hand it a copy so the integrator's state stays intact."""
    x = list(plant.initial_state(20.0))
    x[25] = -1.0  # a negative wheel speed, which the model would clip in place
    before = list(x)
    plant.derivatives(x, 0.0, 0.0)
    assert x == before


class _NoThrottle(SpeedLaw):
    """A 'speed law' that always agrees with the current speed: zero acceleration demand."""

    def reference(self, view):
        return view.vx, 0.0


def test_speed_controller_needed_and_holds_speed(plant):
    """With zero acceleration demand the plant slows down in a turn (cornering drag of the
    tyres); the speed-hold controller keeps the set speed through the same turn."""
    steer = SteerProfile(Profile([1.0, 1.2], [0.0, 0.03]))
    coast = ManoeuvreSpec("coast", "j-turn", "test", 25.0, (Phase(8.0, steer, _NoThrottle()),))
    held = ManoeuvreSpec(
        "held", "j-turn", "test", 25.0, (Phase(8.0, steer, SpeedProfile(Profile([0.0], [25.0]))),)
    )
    v_coast = simulate(coast, plant).out.vx
    v_held = simulate(held, plant).out.vx
    assert v_coast[-1] < 25.0 - 0.5
    assert np.all(np.abs(v_held - 25.0) < 0.2)


def test_integration_is_deterministic(plant):
    spec = j_turn("det", "test", 60.0, 4.0, -1)
    a, b = simulate(spec, plant), simulate(spec, MultiBodyPlant())
    for name in a.out._fields:
        assert np.array_equal(getattr(a.out, name), getattr(b.out, name)), name


def test_steering_servo_tracks_the_programme(plant):
    """The plant's input is steering *rate*: the servo loop makes the road-wheel angle
    follow the programme (after the rate-limited step) within a fraction of a degree."""
    steer = SteerProfile(Profile([1.0, 1.2, 3.0, 3.2], [0.0, 0.05, 0.05, 0.0]))
    spec = ManoeuvreSpec(
        "servo", "j-turn", "test", 20.0, (Phase(5.0, steer, SpeedProfile(Profile([0.0], [20.0]))),)
    )
    o = simulate(spec, plant).out
    target = np.array([steer.profile(t)[0] for t in np.arange(o.delta.size) * 0.01])
    assert np.max(np.abs(o.delta - target)) < math.radians(0.5)
    assert np.max(np.abs(o.delta[150:290] - 0.05)) < math.radians(0.05)


def test_tyre_loads_at_rest_and_wheel_lift_guard(plant):
    """Static tyre loads are the axle loads of init_mb split evenly; a manoeuvre that lifts
    a wheel (the MB tyre spring would pull on the road) is refused, naming the wheel."""
    loads = plant.tyre_loads(plant.initial_state(20.0))[0]
    front, rear = plant.static_axle_loads()
    np.testing.assert_allclose(loads, [front / 2, front / 2, rear / 2, rear / 2], rtol=1e-9)
    all_front_bar = MultiBodyPlant(PlantSetup(K_tsf=-150e3, K_tsr=0.0))
    with pytest.raises(SimulationError, match="front-left wheel lifts off"):
        simulate(j_turn("lift", "test", 60.0, 8.0, +1), all_front_bar)
