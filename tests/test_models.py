"""State-space models: the type's checks, the registry, the built-in models against
independent formulas (the numpy single-track model, the CTRV motion in its textbook form,
matrix products), and Jacobians (analytic against central differences)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from numba import njit

from kftune.models import (
    CTRV,
    FD_REL_STEP,
    SINGLE_TRACK,
    SINGLE_TRACK_AY_BIAS,
    SINGLE_TRACK_BIASES,
    StateSpaceModel,
    get_model,
    linear_model,
    linear_params,
    measurement_jacobian,
    model_names,
    process_jacobian,
    register_model,
)
from kftune.models.sideslip import STOP_REVERSE, STOP_SIDESLIP
from kftune.vehicle import measure, preset, step_rk4

BMW = preset("bmw-320i")
VEHICLE_MODELS = (SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES)


def call_f(model, x, u, p, dt):
    """The model's compiled f at one point, raw input u."""
    out = np.empty(model.n_states)
    w = model.prepared_inputs(np.atleast_2d(np.asarray(u, dtype=float)), p)[0]
    model.f(np.asarray(x, dtype=float), w, p, dt, out)
    return out


def call_h(model, x, u, p):
    out = np.empty(model.n_measurements)
    w = model.prepared_inputs(np.atleast_2d(np.asarray(u, dtype=float)), p)[0]
    model.h(np.asarray(x, dtype=float), w, p, out)
    return out


# ------------------------------------------------------------------ registry and type ------


def test_built_in_models_are_registered_under_their_names():
    assert {"single-track", "single-track-ay-bias", "single-track-biases", "ctrv"} <= set(
        model_names()
    )
    for model in (*VEHICLE_MODELS, CTRV):
        assert get_model(model.name) is model
    with pytest.raises(ValueError, match=r"unknown model 'bicycle'.*single-track"):
        get_model("bicycle")


def test_registering_a_second_model_under_a_taken_name_is_refused():
    with pytest.raises(ValueError, match="already registered"):
        register_model(linear_model(np.eye(2), np.eye(2), name="single-track"))
    assert register_model(SINGLE_TRACK) is SINGLE_TRACK  # the same object again: no-op
    with pytest.raises(ValueError, match="needs a StateSpaceModel"):
        register_model("single-track")


@njit
def _f(x, u, p, dt, out):
    out[0] = x[0]


@njit
def _h(x, u, p, out):
    out[0] = x[0]


def _spec(**changes):
    spec = dict(
        name="m",
        state_names=("a",),
        state_units=("m",),
        input_names=(),
        input_units=(),
        measurement_names=("za",),
        measurement_units=("m",),
        f=_f,
        h=_h,
    )
    spec.update(changes)
    return spec


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"f": lambda x, u, p, dt, out: None}, "f must be a numba-compiled function"),
        ({"H": np.eye(1)}, "H must be a numba-compiled function"),
        ({"state_names": ("a", "a"), "state_units": ("m", "m")}, "state names must be unique"),
        ({"state_units": ()}, r"1 state names but 0 units"),
        ({"input_names": ("za",), "input_units": ("m",)}, "both as input and as measurement"),
        ({"param_names": ("k",), "param_defaults": ()}, r"param_defaults must be 1 finite"),
        ({"param_names": ("k",), "param_defaults": (math.nan,)}, "param_defaults"),
        ({"held_causes": (5,)}, "held_causes need a check"),
        ({"stop_reasons": {1: "mine"}}, "stop causes must be >= 2"),
        ({"name": ""}, "non-empty string"),
        ({"measurement_names": (), "measurement_units": ()}, "at least one state and one"),
        (
            {"state_names": tuple(f"s{i}" for i in range(101)), "state_units": ("m",) * 101},
            "has 101 states; kftune takes at most 100",
        ),
    ],
)
def test_model_type_refuses_inconsistent_declarations(changes, match):
    with pytest.raises(ValueError, match=match):
        StateSpaceModel(**_spec(**changes))


def test_parameter_vectors_are_checked_by_name():
    model = linear_model(np.eye(2), np.eye(1, 2))
    assert model.n_params == 4 + 2
    np.testing.assert_array_equal(model.params_vector(None), [1, 0, 0, 1, 1, 0])
    with pytest.raises(ValueError, match=r"shape \(6,\) \[F\[0,0\]"):
        model.params_vector(np.ones(5))
    with pytest.raises(ValueError, match=re.escape("params[3] (F[1,1]) must be finite")):
        model.params_vector([1, 0, 0, math.inf, 1, 0])
    # the single-track models take a VehicleParams (or its packed array), checked as today
    np.testing.assert_array_equal(SINGLE_TRACK.params_vector(BMW), BMW.to_array())
    with pytest.raises(ValueError, match=r"params\[0\] \(m\) must be > 0"):
        SINGLE_TRACK.params_vector(np.r_[-1.0, BMW.to_array()[1:]])


def test_stop_reasons_name_generic_and_model_causes():
    assert SINGLE_TRACK.stop_reason(0) == ""
    assert "jitter" in CTRV.stop_reason(1)
    assert SINGLE_TRACK.stop_reason(STOP_SIDESLIP).startswith("runaway")
    assert "cause 9" in CTRV.stop_reason(9)


# ------------------------------------------------------------------ vehicle models ---------


@pytest.fixture(scope="module")
def vehicle_points():
    rng = np.random.default_rng(3)
    xs = np.column_stack(
        [rng.uniform(3, 40, 30), rng.uniform(-3, 3, 30), rng.uniform(-0.8, 0.8, 30)]
    )
    us = np.column_stack([rng.uniform(-0.15, 0.15, 30), rng.uniform(-8, 4, 30)])
    return xs, us


def test_single_track_model_is_the_vehicle_packages_model(vehicle_points):
    """f and h equal the readable numpy functions (RK4, Dugoff) of kftune.vehicle."""
    p = BMW.to_array()
    for x, u in zip(*vehicle_points):
        np.testing.assert_allclose(
            call_f(SINGLE_TRACK, x, u, p, 0.01), step_rk4(x, u, p, 0.01), rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(
            call_h(SINGLE_TRACK, x, u, p), measure(x, u, p), rtol=1e-13, atol=1e-12
        )


def test_bias_states_are_random_walks_added_to_their_measurements(vehicle_points):
    p = BMW.to_array()
    for x, u in zip(*vehicle_points):
        b = np.array([0.2, -0.4, 0.01])
        x4, x6 = np.r_[x, b[1]], np.r_[x, b]
        np.testing.assert_array_equal(
            call_f(SINGLE_TRACK_AY_BIAS, x4, u, p, 0.01),
            np.r_[call_f(SINGLE_TRACK, x, u, p, 0.01), b[1]],
        )
        np.testing.assert_array_equal(
            call_f(SINGLE_TRACK_BIASES, x6, u, p, 0.01),
            np.r_[call_f(SINGLE_TRACK, x, u, p, 0.01), b],
        )
        z = call_h(SINGLE_TRACK, x, u, p)
        z_ay = z + np.array([0, b[1], 0])
        np.testing.assert_allclose(call_h(SINGLE_TRACK_AY_BIAS, x4, u, p), z_ay)
        np.testing.assert_allclose(call_h(SINGLE_TRACK_BIASES, x6, u, p), z + b)


def test_vehicle_priors_come_from_the_first_measurement():
    z0, r = np.array([20.0, 1.0, 0.1]), np.array([0.01, 0.04, 1e-4])
    x0, P0 = SINGLE_TRACK.initial_state(z0, r, BMW.to_array())
    np.testing.assert_array_equal(x0, [20.0, 0.0, 0.1])
    np.testing.assert_array_equal(np.diag(P0), [0.01, 1.0, 1e-4])
    x0, P0 = SINGLE_TRACK_BIASES.initial_state(z0, r, BMW.to_array())
    assert x0.shape == (6,) and P0.shape == (6, 6)
    np.testing.assert_array_equal(x0[3:], 0.0)
    assert np.all(np.diag(P0) > 0) and np.count_nonzero(P0 - np.diag(np.diag(P0))) == 0


def test_vehicle_check_holds_the_runaway_rules():
    p, z = BMW.to_array(), np.array([20.0, 0.0, 0.0])
    held = np.zeros(2, dtype=np.bool_)
    check = SINGLE_TRACK.check
    assert check(np.array([20.0, 1.0, 0.0]), z, np.zeros(6), p, held) == 0
    assert not held.any()
    assert check(np.array([-1.0, 0.0, 0.0]), z, np.zeros(6), p, held) == STOP_REVERSE
    assert check(np.array([10.0, 18.0, 0.0]), z, np.zeros(6), p, held) == STOP_SIDESLIP  # 61°
    assert check(np.array([10.0, 12.0, 0.0]), z, np.zeros(6), p, held) == 0  # 50°: held only
    assert held.tolist() == [True, False]
    assert check(np.array([9.0, 0.0, 0.0]), z, np.zeros(6), p, held) == 0  # Vx 55 % off
    assert held.tolist() == [False, True]


# ------------------------------------------------------------------ CTRV -------------------


def ctrv_textbook(x, dt):
    """CTRV step in its textbook form (Schubert et al. 2008), ω ≠ 0."""
    px, py, v, psi, om = x
    return np.array(
        [
            px + v / om * (math.sin(psi + om * dt) - math.sin(psi)),
            py + v / om * (math.cos(psi) - math.cos(psi + om * dt)),
            v,
            psi + om * dt,
            om,
        ]
    )


def test_ctrv_step_equals_the_textbook_form_and_goes_straight_at_zero_turn_rate():
    rng = np.random.default_rng(0)
    for _ in range(50):
        x = np.array([*rng.normal(0, 100, 2), rng.uniform(0, 40), rng.uniform(-4, 4), 0.0])
        x[4] = rng.choice([-1, 1]) * 10.0 ** rng.uniform(-2, 0.5)
        np.testing.assert_allclose(
            call_f(CTRV, x, [], np.empty(0), 0.1), ctrv_textbook(x, 0.1), rtol=1e-12, atol=1e-10
        )
    x = np.array([1.0, 2.0, 10.0, 0.3, 0.0])
    np.testing.assert_allclose(
        call_f(CTRV, x, [], np.empty(0), 0.5),
        [1 + 5 * math.cos(0.3), 2 + 5 * math.sin(0.3), 10, 0.3, 0],
        rtol=1e-15,
    )
    # a full circle returns to its start: v = 2π m/s at ω = 1 rad/s over 2π s
    x = np.array([0.0, 0.0, 2 * math.pi, 0.0, 1.0])
    for _ in range(100):
        x = call_f(CTRV, x, [], np.empty(0), 2 * math.pi / 100)
    np.testing.assert_allclose(x[:2], 0.0, atol=1e-12)


@pytest.mark.parametrize("omega", [0.0, 1e-9, -3e-5, 0.02, 0.19, 0.21, -1.3])
def test_ctrv_analytic_jacobians_agree_with_central_differences(omega):
    rng = np.random.default_rng(int(abs(omega) * 1e9) % 1000)
    for dt in (0.05, 1.0):
        x = np.array([*rng.normal(0, 50, 2), rng.uniform(1, 30), rng.uniform(-3, 3), omega])
        F = process_jacobian(CTRV, x, None, dt)
        F_fd = process_jacobian(CTRV, x, None, dt, numerical=True)
        np.testing.assert_allclose(F, F_fd, rtol=1e-7, atol=1e-7 * np.abs(F).max())
        H = measurement_jacobian(CTRV, x, None)
        np.testing.assert_allclose(H, measurement_jacobian(CTRV, x, None, numerical=True))
        np.testing.assert_array_equal(H, np.eye(2, 5))


def test_central_differences_use_the_documented_step_and_err_by_rounding_only_on_linear_maps():
    assert np.finfo(float).eps ** (1 / 3) == pytest.approx(FD_REL_STEP)
    A = np.array([[1.0, 2.0], [-0.5, 3.0]])
    model = linear_model(A, np.eye(2))
    for x in (np.array([0.3, -2e-3]), np.array([1e3, -2e-3])):
        J = process_jacobian(model, x, None, 1.0, numerical=True)
        # no truncation error on a linear map; rounding ≈ ε·|f|/h for the step h of x_j
        f_scale = np.abs(A @ x).max()
        np.testing.assert_allclose(J, A, rtol=0, atol=4 * 2.2e-16 * f_scale / FD_REL_STEP)


# ------------------------------------------------------------------ linear models ----------


def test_linear_model_is_its_matrices():
    rng = np.random.default_rng(4)
    F, G, H, D = (
        rng.normal(size=(4, 4)),
        rng.normal(size=(4, 2)),
        rng.normal(size=(3, 4)),
        (rng.normal(size=(3, 2))),
    )
    model = linear_model(F, H, G, D)
    assert (model.n_states, model.n_inputs, model.n_measurements) == (4, 2, 3)
    x, u = rng.normal(size=4), rng.normal(size=2)
    p = model.default_params()
    np.testing.assert_allclose(call_f(model, x, u, p, 0.1), F @ x + G @ u, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(call_h(model, x, u, p), H @ x + D @ u, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(process_jacobian(model, x, u, 0.1), F)
    np.testing.assert_array_equal(measurement_jacobian(model, x, u), H)
    # other matrices of the same sizes, per run
    p2 = linear_params(2 * F, H, G, D)
    np.testing.assert_allclose(
        call_f(model, x, u, p2, 0.1), 2 * F @ x + G @ u, rtol=1e-13, atol=1e-14
    )
    with pytest.raises(ValueError, match=r"G must be a finite array of shape \(4, 2\)"):
        linear_params(F, H, np.full((4, 2), np.nan), D)


@pytest.mark.parametrize("model", VEHICLE_MODELS, ids=lambda m: m.name)
@pytest.mark.slow
def test_single_track_analytic_jacobians_agree_with_central_differences(model, vehicle_points):
    """At random states, many deep in the Dugoff saturation, and at a lifted rear axle."""
    p = BMW.to_array()
    rng = np.random.default_rng(1)
    points = list(zip(*vehicle_points))
    points.append((np.array([20.0, 0.5, 0.3]), np.array([0.05, -30.0])))  # Fz_r ≤ 0
    for x3, u in points:
        x = np.r_[x3, rng.normal(0, 0.1, model.n_states - 3)]
        for dt in (0.01, 0.05):
            F = process_jacobian(model, x, u, dt, p)
            F_fd = process_jacobian(model, x, u, dt, p, numerical=True)
            np.testing.assert_allclose(F, F_fd, rtol=1e-6, atol=1e-8 * np.abs(F).max())
        H = measurement_jacobian(model, x, u, p)
        H_fd = measurement_jacobian(model, x, u, p, numerical=True)
        np.testing.assert_allclose(H, H_fd, rtol=1e-6, atol=1e-7 * np.abs(H).max())


def test_dugoff_slope_is_the_derivative_of_the_force_and_continuous_at_the_knee():
    from kftune.models._single_track_jacobians import dugoff_slope
    from kftune.vehicle.tyre import dugoff_fy_scalar

    C, mu, Fz = 8e4, 1.0, 8e3
    knee = 0.5 * mu * Fz / C
    for t in (-2.0, -0.3, -knee * 1.001, 0.0, 0.5 * knee, knee * 0.999, knee * 1.001, 0.2, 5.0):
        step = 1e-7 * max(abs(t), knee)
        fd = (dugoff_fy_scalar(t + step, Fz, C, mu) - dugoff_fy_scalar(t - step, Fz, C, mu)) / (
            2 * step
        )
        assert dugoff_slope(t, Fz, C, mu) == pytest.approx(fd, rel=1e-5)
    assert dugoff_slope(knee, Fz, C, mu) == C
    assert dugoff_slope(math.inf, Fz, C, mu) == 0.0
    assert dugoff_slope(0.1, -5.0, C, mu) == 0.0
