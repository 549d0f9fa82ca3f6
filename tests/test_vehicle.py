"""Single-track model: steady-state cornering against the closed-form linear bicycle model,
RK4 against scipy's adaptive integrator, and the compiled scalar internals against numpy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve

from kftune.vehicle import (
    derivatives,
    measure,
    pack_params,
    preset,
    simulate,
    slip_angles,
    step_rk4,
)
from kftune.vehicle.params import PLAUSIBLE_RANGES
from kftune.vehicle.single_track import (
    derivatives_scalar,
    measure_scalar,
    rk4_scalar,
    step_context_scalar,
)

BMW = preset("bmw-320i")


def steady_state(p, vx: float, delta: float) -> tuple[float, float]:
    """(Vy, r) with ẋ = 0 at constant speed: the accelerometer then reads ax = −r·Vy."""

    def eqs(v):
        vy, r, ax = v
        return derivatives([vx, vy, r], [delta, ax], p)

    vy, r, ax = fsolve(eqs, [0.0, vx * delta / p.L, 0.0], xtol=1e-12)
    assert abs(ax + r * vy) < 1e-12
    return vy, r


@pytest.mark.parametrize("name", ["bmw-320i", "revs-250lm"])
@pytest.mark.parametrize("speed", [8.0, 20.0, 35.0])
def test_steady_state_yaw_rate_matches_understeer_gradient(name, speed):
    p = preset(name)
    delta = math.radians(0.1)
    vy, r = steady_state(p, speed, delta)
    # linear bicycle model (Gillespie Ch. 6; Rajamani Ch. 3): r = V·δ / (L + K_us·V²)
    r_lin = speed * delta / (p.L + p.understeer_gradient * speed**2)
    assert r == pytest.approx(r_lin, rel=2e-5)
    # rear-axle slip balance of the linear model: Vy = b·r − a·m·V²·r / (L·C_ar)
    vy_lin = p.b * r_lin - p.a * p.m * speed**2 * r_lin / (p.L * p.C_ar)
    assert vy == pytest.approx(vy_lin, rel=2e-5)


def test_steady_state_error_is_a_small_angle_effect():
    # the nonlinear model departs from the closed form only at second order in δ
    p, speed = BMW, 20.0
    errs = []
    for delta in (math.radians(0.4), math.radians(0.2), math.radians(0.1)):
        _, r = steady_state(p, speed, delta)
        r_lin = speed * delta / (p.L + p.understeer_gradient * speed**2)
        errs.append(abs(r / r_lin - 1))
    assert errs[0] > errs[1] > errs[2]
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.1)  # O(δ²)


def test_neutral_steer_and_time_domain_convergence():
    # b/C_af = a/C_ar ⇒ K_us = 0 ⇒ r = V·δ/L; reach it by integrating with speed hold
    p = BMW.replace(C_ar=BMW.C_af * BMW.a / BMW.b)
    assert p.understeer_gradient == pytest.approx(0.0, abs=1e-15)
    speed, delta, dt = 15.0, math.radians(0.1), 0.01
    x = np.array([speed, 0.0, 0.0])
    for _ in range(800):
        x = step_rk4(x, [delta, -x[2] * x[1]], p, dt)  # ax = −r·Vy keeps Vx constant
    assert x[0] == pytest.approx(speed, rel=1e-6)
    assert x[2] == pytest.approx(speed * delta / p.L, rel=2e-4)


def test_rk4_step_matches_scipy_reference_and_is_fourth_order():
    u = np.array([math.radians(4.0), -2.0])  # saturating front axle, braking
    x0 = np.array([20.0, -0.4, 0.35])
    ref = solve_ivp(
        lambda t, x: derivatives(x, u, BMW), (0, 0.02), x0, rtol=1e-13, atol=1e-13, method="DOP853"
    )
    exact = ref.y[:, -1]
    err_1 = np.max(np.abs(step_rk4(x0, u, BMW, 0.02) - exact))
    x_half = step_rk4(step_rk4(x0, u, BMW, 0.01), u, BMW, 0.01)
    err_2 = np.max(np.abs(x_half - exact))
    assert err_1 < 1e-7
    assert err_1 / err_2 > 12  # local error O(dt⁵): halving dt gives ≈ 16× on two steps


def test_measured_ay_is_vdot_y_plus_r_vx():
    rng = np.random.default_rng(3)
    x = np.column_stack([rng.uniform(5, 40, 50), rng.normal(0, 1, 50), rng.normal(0, 0.5, 50)])
    u = np.column_stack([rng.normal(0, 0.05, 50), rng.normal(0, 3, 50)])
    xd = derivatives(x, u, BMW)
    z = measure(x, u, BMW)
    np.testing.assert_allclose(z[:, 1], xd[:, 1] + x[:, 2] * x[:, 0], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(z[:, [0, 2]], x[:, [0, 2]])
    # V̇x = ax + r·Vy (kinematics of a body-fixed accelerometer)
    np.testing.assert_allclose(xd[:, 0], u[:, 1] + x[:, 2] * x[:, 1], rtol=1e-14)


def test_slip_angles_reduce_to_atan_for_forward_speed():
    x = np.array([[20.0, 0.5, 0.3], [10.0, -1.0, -0.2]])
    af, ar = slip_angles(x, [0.05, 0.0], BMW)
    np.testing.assert_allclose(af, 0.05 - np.arctan((x[:, 1] + BMW.a * x[:, 2]) / x[:, 0]))
    np.testing.assert_allclose(ar, -np.arctan((x[:, 1] - BMW.b * x[:, 2]) / x[:, 0]))


def test_compiled_scalars_equal_numpy_model_everywhere():
    # including Vx ≤ 0 (sigma points may go there): the compiled tan-ratio form is exact
    rng = np.random.default_rng(0)
    n = 400
    x = np.column_stack([rng.uniform(-10, 50, n), rng.normal(0, 3, n), rng.normal(0, 1, n)])
    x[:5, 0] = 0.0
    u = np.column_stack([rng.normal(0, 0.2, n), rng.normal(0, 4, n)])
    arr = BMW.to_array()
    f_np, x1_np, z_np = derivatives(x, u, arr), step_rk4(x, u, arr, 0.01), measure(x, u, arr)
    for i in range(n):
        tan_d, cos_d, fzf, fzr = step_context_scalar(u[i, 0], u[i, 1], arr)
        f = derivatives_scalar(*x[i], tan_d, cos_d, u[i, 1], fzf, fzr, arr)
        x1 = rk4_scalar(*x[i], tan_d, cos_d, u[i, 1], fzf, fzr, arr, 0.01)
        z = measure_scalar(*x[i], tan_d, cos_d, fzf, fzr, arr)
        np.testing.assert_allclose(f, f_np[i], rtol=1e-11, atol=1e-10)
        np.testing.assert_allclose(x1, x1_np[i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(z, z_np[i], rtol=1e-11, atol=1e-10)


def test_simulate_is_repeated_rk4_and_straight_driving_stays_straight():
    u = np.column_stack([np.linspace(0, 0.05, 30), np.full(30, 1.0)])
    xs = simulate([15.0, 0.0, 0.0], u, BMW, 0.01, substeps=2)
    x = np.array([15.0, 0.0, 0.0])
    for k in range(1, 30):
        x = step_rk4(step_rk4(x, u[k - 1], BMW, 0.005), u[k - 1], BMW, 0.005)
        np.testing.assert_allclose(xs[k], x, rtol=1e-13, atol=1e-13)
    straight = simulate([15.0, 0.0, 0.0], np.tile([0.0, 2.0], (101, 1)), BMW, 0.01)
    np.testing.assert_allclose(straight[:, 1:], 0.0, atol=0.0)
    assert straight[-1, 0] == pytest.approx(17.0, rel=1e-12)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.arange(8.0), r"shape \(9,\)"),
        (np.r_[BMW.to_array()[:1] * -1, BMW.to_array()[1:]], r"params\[0\] \(m\) must be > 0"),
        (np.r_[BMW.to_array()[:8], 3.0], r"params\[8\] \(mu\)"),
        (
            np.r_[BMW.to_array()[:4], np.nan, BMW.to_array()[5:]],
            r"params\[4\] \(h\) must be finite",
        ),
    ],
)
def test_pack_params_refuses_bad_arrays(bad, match):
    with pytest.raises(ValueError, match=match):
        pack_params(bad)


def test_model_refuses_bad_state_and_dt():
    with pytest.raises(ValueError, match=r"x .*NaN"):
        derivatives([np.nan, 0, 0], [0, 0], BMW)
    with pytest.raises(ValueError, match="last dimension 2"):
        measure([10, 0, 0], [0, 0, 0], BMW)
    with pytest.raises(ValueError, match="dt must be"):
        step_rk4([10, 0, 0], [0, 0], BMW, 0.0)
    with pytest.raises(ValueError, match="substeps"):
        simulate([10, 0, 0], np.zeros((3, 2)), BMW, 0.01, substeps=0)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("m", -1093.0, r"VehicleParams\.m = -1093\.0 kg is implausible.*100 to 60000 kg"),
        ("m", 1e-300, r"VehicleParams\.m = 1e-300 kg is implausible"),
        ("Iz", 0.0, r"VehicleParams\.Iz = 0\.0 kg·m² is implausible.*10 to 1e\+06"),
        ("a", -1.0, r"VehicleParams\.a = -1\.0 m is implausible.*0\.1 to 10 m"),
        ("b", 1e6, r"VehicleParams\.b = 1000000\.0 m is implausible"),
        ("C_ar", 0.0, r"VehicleParams\.C_ar = 0\.0 N/rad is implausible"),
        ("C_af", 55.6, r"VehicleParams\.C_af = 55\.6 N/rad .*1000 to 2e\+06 N/rad"),
        ("h", -0.1, r"VehicleParams\.h = -0\.1 m is implausible.*0 to 3 m"),
        ("mu", 0.0, r"VehicleParams\.mu = 0\.0 - is implausible.*0\.05 to 2"),
        ("mu", 2.5, r"VehicleParams\.mu = 2\.5 - is implausible"),
        ("m", float("nan"), r"VehicleParams\.m must be a finite number"),
        ("b", "1.5", r"VehicleParams\.b must be a finite number"),
        ("Iz", True, r"VehicleParams\.Iz must be a finite number"),
        ("steering_ratio", "x", r"VehicleParams\.steering_ratio must be a finite number"),
        ("steering_ratio", -16.0, r"VehicleParams\.steering_ratio = -16\.0 - is implausible"),
        ("track_r", 1365.0, r"VehicleParams\.track_r = 1365\.0 m is implausible"),
        ("name", 3, r"VehicleParams\.name must be a string"),
    ],
)
def test_bad_parameters_are_refused_naming_the_field(field, value, match):
    with pytest.raises(ValueError, match=match):
        preset("bmw-320i").replace(**{field: value})


def test_every_range_bound_is_accepted_and_just_beyond_it_refused():
    """The plausible ranges are closed intervals, and each field is checked against its own."""
    for name, (low, high, _) in PLAUSIBLE_RANGES.items():
        for ok in (low, high):
            assert getattr(preset("bmw-320i").replace(**{name: ok}), name) == ok
        for bad in (low - 1e-9 * max(1.0, abs(low)) - 1e-12, high * (1 + 1e-9)):
            with pytest.raises(ValueError, match=rf"VehicleParams\.{name} = "):
                preset("bmw-320i").replace(**{name: bad})


def test_presets_are_valid_and_frozen():
    import dataclasses

    for name in ("bmw-320i", "revs-250lm"):
        p = preset(name)
        assert p.replace() == p
        with pytest.raises(dataclasses.FrozenInstanceError):
            p.m = 1.0  # type: ignore[misc]
