"""The UKF and EKF over any model against independent references: FilterPy's
``UnscentedKalmanFilter`` (Merwe sigma points) and ``ExtendedKalmanFilter`` on every built-in
model with independently written f and h, today's 3×3 kernel on the sideslip model, a
closed-form Kalman filter on linear models; a model written here runs; divergence and bad
input behave as for ``run_ukf``."""

from __future__ import annotations

import dataclasses
import math
import os
import re

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterPyUKF
from numba import njit

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import (
    EKF,
    UKF,
    FilterResult,
    UKFSettings,
    filter_names,
    get_filter,
)
from kftune.filters import _generic_kernel as gk
from kftune.models import (
    CTRV,
    SINGLE_TRACK,
    SINGLE_TRACK_AY_BIAS,
    SINGLE_TRACK_BIASES,
    StateSpaceModel,
    linear_model,
    measurement_jacobian,
    process_jacobian,
)
from kftune.models.kernel_io import KernelData, KernelOutputs
from kftune.models.sideslip import STOP_REVERSE, STOP_SIDESLIP
from kftune.vehicle import measure, step_rk4
from single_track import run_ukf, run_ukf_batch

#: The single-track model without its own loops (ModelKernels): the generic UKF loop on it,
#: to compare with the model's 3×3 loop, which ``run_ukf`` (and SINGLE_TRACK) runs.
GENERIC_SINGLE_TRACK = dataclasses.replace(SINGLE_TRACK, ukf_kernels=None)

OUTPUTS = ("x", "P_diag", "z_hat", "innovation", "nis")


def max_rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max over channels of max_k |a − b| / max_k |b| (channel-scaled relative difference)."""
    a, b = np.atleast_2d(a.T).T, np.atleast_2d(b.T).T
    scale = np.max(np.abs(b), axis=0)
    return float(np.max(np.max(np.abs(a - b), axis=0) / np.where(scale > 0, scale, 1.0)))


# ------------------------------------------------------------------ cases ------------------


class Case:
    """A model, data and noise, and the model's f, h written independently in numpy."""

    def __init__(self, model, u, z, dt, q, r, fx, hx, params=None):
        self.model, self.u, self.z, self.dt, self.q, self.r = model, u, z, dt, q, r
        self.fx, self.hx, self.params = fx, hx, params
        self.p = model.params_vector(params)

    def prior(self):
        return self.model.initial_state(self.z[0], self.r, self.p)


@pytest.fixture(scope="module")
def man():
    return demo_manoeuvre(seed=7)


def vehicle_case(man, model, bias, q_bias, steps=slice(1300, 2000)):
    """The last 7 s of the demo sine steer (deep in the Dugoff saturation), biased sensors."""
    p = man.params.to_array()
    n_b = len(bias)
    at = {0: [], 1: [1], 3: [0, 1, 2]}[n_b]
    z = man.z[steps].copy()
    z[:, at] += bias

    def fx(x, dt, u):
        return np.r_[step_rk4(x[:3], u, p, dt), x[3:]]

    def hx(x, u):
        zz = measure(x[:3], u, p)
        zz[at] += x[3:]
        return zz

    q = np.r_[DEFAULT_Q, q_bias]
    return Case(model, man.u[steps], z, man.dt, q, man.r_var, fx, hx, man.params)


def ctrv_case(n=300, dt=0.1, seed=0):
    """A target driving straight, turning left, then right; noisy positions."""
    rng = np.random.default_rng(seed)
    x = np.array([0.0, 0.0, 12.0, 0.4, 0.0])
    xs = []
    for k in range(n):
        x[4] = 0.0 if k < 80 else (0.25 if k < 180 else -0.3)
        om, v, psi = x[4], x[2], x[3]
        if om == 0.0:
            x[:2] += v * dt * np.array([math.cos(psi), math.sin(psi)])
        else:
            x[0] += v / om * (math.sin(psi + om * dt) - math.sin(psi))
            x[1] += v / om * (math.cos(psi) - math.cos(psi + om * dt))
        x[3] += om * dt
        xs.append(x.copy())
    z = np.array(xs)[:, :2] + rng.normal(0.0, 0.5, (n, 2))

    def fx(x, dt, u):  # the textbook form (the model uses the sinc form)
        px, py, v, psi, om = x
        if abs(om) < 1e-9:
            return np.array([px + v * dt * math.cos(psi), py + v * dt * math.sin(psi), v, psi, om])
        return np.array(
            [
                px + v / om * (math.sin(psi + om * dt) - math.sin(psi)),
                py + v / om * (math.cos(psi) - math.cos(psi + om * dt)),
                v,
                psi + om * dt,
                om,
            ]
        )

    q = np.array([1e-4, 1e-4, 0.05, 1e-4, 2e-3])
    return Case(CTRV, np.zeros((n, 0)), z, dt, q, np.array([0.25, 0.25]), fx, lambda x, u: x[:2])


def linear_system(seed=0, n=4, nu=2, m=3, steps=300):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    F = 0.97 * A / np.max(np.abs(np.linalg.eigvals(A)))  # stable
    G, H, D = rng.normal(size=(n, nu)) * 0.1, rng.normal(size=(m, n)), rng.normal(size=(m, nu))
    q, r = 10.0 ** rng.uniform(-4, -2, n), 10.0 ** rng.uniform(-2, -1, m)
    u = rng.normal(size=(steps, nu))
    x = np.zeros((steps, n))
    x[0] = rng.normal(size=n)
    for k in range(1, steps):
        x[k] = F @ x[k - 1] + G @ u[k - 1] + rng.normal(size=n) * np.sqrt(q)
    z = x @ H.T + u @ D.T + rng.normal(size=(steps, m)) * np.sqrt(r)
    return F, G, H, D, q, r, u, z


def linear_case():
    F, G, H, D, q, r, u, z = linear_system()
    model = linear_model(F, H, G, D)
    case = Case(model, u, z, 1.0, q, r, lambda x, dt, u: F @ x + G @ u, lambda x, u: H @ x + D @ u)
    x0, P0 = np.array([0.5, -0.2, 0.1, 0.0]), np.diag([2.0, 1.0, 0.5, 1.0])
    case.prior = lambda: (x0, P0)
    return case


#: Every built-in model compiles its own kernels (numba specialises on f and h; 3–6 s per
#: model and filter on a 2-core machine, more under load). The suite runs three models that
#: between them cover a vehicle, a tracking and a linear model; KFTUNE_ALL_MODELS=1 adds the
#: two bias variants.
ALL_MODELS = os.environ.get("KFTUNE_ALL_MODELS") == "1"
_EXTRA = pytest.mark.skipif(
    not ALL_MODELS, reason="compiles two more models' kernels: set KFTUNE_ALL_MODELS=1"
)
CASES = (
    "single-track",
    "single-track (generic loop)",
    "ctrv",
    "linear",
    pytest.param("single-track-ay-bias", marks=_EXTRA),
    pytest.param("single-track-biases", marks=_EXTRA),
)


@pytest.fixture(scope="module")
def cases(man):
    return {
        "single-track": vehicle_case(man, SINGLE_TRACK, [], []),
        "single-track (generic loop)": vehicle_case(man, GENERIC_SINGLE_TRACK, [], []),
        "single-track-ay-bias": vehicle_case(man, SINGLE_TRACK_AY_BIAS, [0.3], [1e-6]),
        "single-track-biases": vehicle_case(
            man, SINGLE_TRACK_BIASES, [0.1, 0.3, 0.005], [1e-7, 1e-6, 1e-9]
        ),
        "ctrv": ctrv_case(),
        "linear": linear_case(),
    }


def run(filt, case, **kw) -> FilterResult:
    x0, P0 = case.prior()
    u = None if case.model.n_inputs == 0 else case.u
    return filt.run(
        case.model, u, case.z, case.dt, case.q, case.r, params=case.params, x0=x0, P0=P0, **kw
    )


# ------------------------------------------------------------------ FilterPy references ----


def filterpy_ukf(case, settings: UKFSettings):
    """FilterPy's UKF with the time convention of run_ukf (see tests/test_ukf.py)."""
    n, m = case.model.n_states, case.model.n_measurements
    points = MerweScaledSigmaPoints(
        n, alpha=settings.alpha, beta=settings.beta, kappa=settings.kappa
    )
    ukf = FilterPyUKF(dim_x=n, dim_z=m, dt=case.dt, fx=case.fx, hx=case.hx, points=points)
    ukf.x, ukf.P = (a.copy() for a in case.prior())
    ukf.Q, ukf.R = np.diag(case.q), np.diag(case.r)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)  # step 0: update the prior, no predict
    return _drive(case, ukf, lambda k: ukf.predict(u=case.u[k - 1]), lambda k: ukf.update(
        case.z[k], u=case.u[k]))  # fmt: skip


class ModelEKF(ExtendedKalmanFilter):
    """FilterPy's EKF with a nonlinear f (its predict is linear, F·x + B·u, by default)."""

    def __init__(self, case):
        super().__init__(dim_x=case.model.n_states, dim_z=case.model.n_measurements)
        self.case = case

    def predict_x(self, u=0):
        self.x = self.case.fx(self.x, self.case.dt, u)


def filterpy_ekf(case, numerical=False):
    """FilterPy's EKF given the model's Jacobian functions (its own, or central differences)."""
    model, p = case.model, case.p
    ekf = ModelEKF(case)
    ekf.x, ekf.P = (a.copy() for a in case.prior())
    ekf.Q, ekf.R = np.diag(case.q), np.diag(case.r)

    def predict(k):
        ekf.F = process_jacobian(model, ekf.x, case.u[k - 1], case.dt, p, numerical=numerical)
        ekf.predict(u=case.u[k - 1])

    def update(k):
        ekf.update(
            case.z[k],
            HJacobian=lambda x: measurement_jacobian(model, x, case.u[k], p, numerical=numerical),
            Hx=lambda x: case.hx(x, case.u[k]),
        )

    return _drive(case, ekf, predict, update)


def _drive(case, flt, predict, update):
    steps = case.z.shape[0]
    out = {
        "x": np.empty((steps, case.model.n_states)),
        "P_diag": np.empty((steps, case.model.n_states)),
        "innovation": np.empty((steps, case.model.n_measurements)),
        "nis": np.empty(steps),
    }
    for k in range(steps):
        if k > 0:
            predict(k)
        update(k)
        out["x"][k], out["P_diag"][k], out["innovation"][k] = flt.x, np.diag(flt.P), flt.y
        out["nis"][k] = flt.y @ np.linalg.solve(flt.S, flt.y)
    return out


def assert_equal_to(res, ref, tol):
    assert not res.diverged and res.n_repairs == 0
    for name, value in ref.items():
        assert max_rel_diff(getattr(res, name), value) <= tol, name


@pytest.mark.parametrize("name", CASES)
@pytest.mark.slow
def test_ukf_equals_filterpy_on_every_built_in_model(cases, name):
    case = cases[name]
    res = run(UKF(), case)
    assert_equal_to(res, filterpy_ukf(case, UKFSettings()), 1e-9)
    # z_hat is h(posterior, u_k)
    z_hat = np.array([case.hx(x, uk) for x, uk in zip(res.x, case.u)])
    assert max_rel_diff(res.z_hat, z_hat) <= 1e-12


@pytest.mark.parametrize("name", ["ctrv", pytest.param("single-track-ay-bias", marks=_EXTRA)])
@pytest.mark.parametrize("settings", [UKFSettings(0.5, 2.0, 1.0), UKFSettings(0.3, 0.0, 2.0)])
def test_ukf_equals_filterpy_for_other_sigma_point_settings(cases, name, settings):
    # (not α ≪ 1: weights of order 1/α² amplify rounding past 1e-9 in either implementation;
    # tests/test_ukf.py covers α = 0.01 on the 3-state model, to which this UKF is identical)
    case = cases[name]
    assert_equal_to(run(UKF(settings), case), filterpy_ukf(case, settings), 1e-9)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.slow
def test_ekf_equals_filterpy_given_the_same_jacobians(cases, name):
    case = cases[name]
    assert_equal_to(run(EKF(), case), filterpy_ekf(case), 1e-9)


@pytest.mark.slow
def test_ekf_with_central_differences_equals_filterpy_given_them_too(cases):
    case = cases["ctrv"]
    res = run(EKF(numerical_jacobians=True), case)
    assert_equal_to(res, filterpy_ekf(case, numerical=True), 1e-9)
    # and finite differences barely change the analytic EKF's estimate
    assert max_rel_diff(res.x, run(EKF(), case).x) <= 1e-6


# ------------------------------------------------------------------ today's 3×3 kernel -----


@pytest.mark.slow
def test_generic_ukf_reproduces_run_ukf_on_the_sideslip_model(man):
    args = (man.u, man.z, man.dt)
    ref = run_ukf(*args, man.params, DEFAULT_Q, man.r_var)
    res = UKF().run(GENERIC_SINGLE_TRACK, *args, DEFAULT_Q, man.r_var, params=man.params)
    for name in OUTPUTS:
        assert max_rel_diff(getattr(res, name), getattr(ref, name)) <= 1e-12, name
    assert (res.diverged, res.n_repairs) == (ref.diverged, ref.n_repairs)


@pytest.mark.parametrize(
    ("q", "r", "P0", "cause"),
    [
        ([1e9, 1e9, 1e9], None, None, STOP_SIDESLIP),  # runaway beyond 60° at once
        (DEFAULT_Q, [1e6, 0.01, 1e-5], [0.01, 0.1, 1e-4], STOP_REVERSE),  # Vx driven < 0
    ],
)
def test_generic_ukf_diverges_where_and_why_run_ukf_does(man, q, r, P0, cause):
    u, z = man.u[:300].copy(), man.z[:300].copy()
    u[100, 1] = -1e4  # an impossible braking input
    r = man.r_var if r is None else r
    ref = run_ukf(u, z, man.dt, man.params, q, r, P0=P0)
    res = UKF().run(GENERIC_SINGLE_TRACK, u, z, man.dt, q, r, params=man.params, P0=P0)
    assert ref.diverged and ref.diverged_cause == cause
    assert (res.diverged_step, res.diverged_cause) == (ref.diverged_step, ref.diverged_cause)
    assert res.diverged_reason == ref.diverged_reason
    k = ref.diverged_step
    for name in OUTPUTS:
        a, b = getattr(res, name), getattr(ref, name)
        assert np.isnan(a[k:]).all() and np.isnan(b[k:]).all()
        if k > 0:
            assert max_rel_diff(a[:k], b[:k]) <= 1e-12, name


def test_held_runaways_stop_where_they_began_as_in_run_ukf(man):
    """Vx measured far from the model's speed for 0.5 s: STOP_SPEED at the start of it."""
    u, z = man.u[:400], man.z[:400].copy()
    z[200:, 0] *= 3.0  # a wheel-speed sensor gone wrong: the filter trusts the model
    r = [1e2, 0.01, 1e-5]
    ref = run_ukf(u, z, man.dt, man.params, DEFAULT_Q, r)
    res = UKF().run(GENERIC_SINGLE_TRACK, u, z, man.dt, DEFAULT_Q, r, params=man.params)
    assert ref.diverged and ref.diverged_cause == 5
    assert (res.diverged_step, res.diverged_cause) == (ref.diverged_step, ref.diverged_cause)
    assert res.diverged_step == 200


@pytest.mark.slow
def test_batches_equal_single_runs_and_run_ukf_batch(man):
    rng = np.random.default_rng(2)
    q = np.array(DEFAULT_Q) * 10.0 ** rng.uniform(-2, 2, size=(5, 3))
    q[3] = 1e9  # one setting runs away
    r = man.r_var * 10.0 ** rng.uniform(-1, 1, size=(5, 3))
    u, z = man.u[:600], man.z[:600]
    ref = run_ukf_batch(u, z, man.dt, man.params, q, r)
    for filt in (UKF(), EKF()):
        batch = filt.run_batch(GENERIC_SINGLE_TRACK, u, z, man.dt, q, r, params=man.params)
        assert len(batch) == 5 and batch.x.shape == (5, 600, 3)
        for b in range(5):
            one = filt.run(GENERIC_SINGLE_TRACK, u, z, man.dt, q[b], r[b], params=man.params)
            for name in OUTPUTS:
                np.testing.assert_array_equal(getattr(batch[b], name), getattr(one, name))
            assert (batch[b].diverged_step, batch[b].diverged_cause) == (
                one.diverged_step,
                one.diverged_cause,
            )
        if filt.name == "ukf":
            for name in OUTPUTS:
                assert (
                    max_rel_diff(
                        getattr(batch, name)[~ref.diverged], getattr(ref, name)[~ref.diverged]
                    )
                    <= 1e-12
                )
            np.testing.assert_array_equal(batch.diverged_step, ref.diverged_step)
    single_set = UKF().run_batch(SINGLE_TRACK, u, z, man.dt, q[:1], r[0], params=man.params)
    np.testing.assert_array_equal(single_set.x[0], UKF().run(
        SINGLE_TRACK, u, z, man.dt, q[0], r[0], params=man.params).x)  # fmt: skip


# ------------------------------------------------------------------ linear models ----------


def kalman_filter(F, G, H, D, q, r, u, z, x0, P0):
    """The Kalman filter in closed form (Simon 2006, eqs. 5.19), numpy, no FilterPy."""
    x, P = x0.copy(), P0.copy()
    out = {k: [] for k in ("x", "P_diag", "innovation", "nis")}
    for k in range(len(z)):
        if k > 0:
            x = F @ x + G @ u[k - 1]
            P = F @ P @ F.T + np.diag(q)
        y = z[k] - H @ x - D @ u[k]
        S = H @ P @ H.T + np.diag(r)
        K = np.linalg.solve(S, H @ P).T  # P·Hᵀ·S⁻¹ (S symmetric)
        x = x + K @ y
        P = (np.eye(len(x)) - K @ H) @ P
        for name, value in zip(out, (x, np.diag(P), y, y @ np.linalg.solve(S, y))):
            out[name].append(value)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize(
    ("filt", "sizes"),
    [
        (UKF(), (4, 2, 3)),
        (UKF(UKFSettings(0.3, 0.0, 2.0)), (4, 2, 3)),
        (UKF(UKFSettings(1e-3, 2.0, 0.0)), (2, 1, 1)),
        (UKF(), (7, 0, 5)),
        (EKF(), (4, 2, 3)),
        (EKF(numerical_jacobians=True), (4, 2, 3)),
        (EKF(), (7, 0, 5)),
    ],
)
@pytest.mark.slow
def test_ukf_and_ekf_equal_a_linear_kalman_filter_on_linear_models(filt, sizes):
    n, nu, m = sizes
    F, G, H, D, q, r, u, z = linear_system(seed=n, n=n, nu=nu, m=m)
    x0, P0 = np.linspace(-1, 1, n), np.diag(np.linspace(0.5, 2, n))
    model = linear_model(F, H, G, D)
    res = filt.run(model, u if nu else None, z, 1.0, q, r, x0=x0, P0=P0)
    ref = kalman_filter(F, G, H, D, q, r, u, z, x0, P0)
    tol = 1e-6 if getattr(filt, "numerical_jacobians", False) else 1e-9
    assert_equal_to(res, ref, tol)


# ------------------------------------------------------------------ a user's own model -----


@njit
def pendulum_f(x, u, p, dt, out):
    """A damped pendulum driven by a torque u[0], one explicit midpoint step."""
    g_l, damping = p[0], p[1]
    a0 = -g_l * math.sin(x[0]) - damping * x[1] + u[0]
    xm0, xm1 = x[0] + 0.5 * dt * x[1], x[1] + 0.5 * dt * a0
    out[0] = x[0] + dt * xm1
    out[1] = x[1] + dt * (-g_l * math.sin(xm0) - damping * xm1 + u[0])


@njit
def pendulum_h(x, u, p, out):
    """The bob's horizontal position (length 1) — a nonlinear measurement."""
    out[0] = math.sin(x[0])


@njit
def pendulum_check(x, z, u, p, held):
    """Held: the estimated angle beyond ±π/2 (our user's pendulum never gets there)."""
    held[0] = abs(x[0]) > 0.5 * math.pi
    return 9 if abs(x[1]) > 100.0 else 0


def pendulum_model(name="pendulum", **kw):
    return StateSpaceModel(
        name=name,
        state_names=("theta", "omega"),
        state_units=("rad", "rad/s"),
        input_names=("torque",),
        input_units=("1/s^2",),
        measurement_names=("x_bob",),
        measurement_units=("m",),
        f=pendulum_f,
        h=pendulum_h,
        param_names=("g_over_l", "damping"),
        param_units=("1/s^2", "1/s"),
        param_defaults=(9.81, 0.3),
        initial_state=lambda z0, r, p: (
            np.array([math.asin(z0[0]), 0.0]),
            np.diag([r[0], 1.0]),
        ),
        **kw,
    )


@pytest.fixture(scope="module")
def pendulum():
    dt, n = 0.01, 1500
    rng = np.random.default_rng(5)
    u = np.column_stack([0.5 * np.sin(np.arange(n) * dt)])
    x = np.zeros((n, 2))
    x[0] = [0.6, 0.0]
    p = np.array([9.81, 0.3])
    for k in range(1, n):
        pendulum_f(x[k - 1], u[k - 1], p, dt, x[k])
    z = np.sin(x[:, :1]) + rng.normal(0, 0.01, (n, 1))
    return u, z, x, dt


@pytest.mark.parametrize("filt", [UKF(), EKF()], ids=["ukf", "ekf"])
@pytest.mark.slow
def test_a_users_own_model_runs_through_both_filters(pendulum, filt):
    u, z, x_true, dt = pendulum
    model = pendulum_model()
    res = filt.run(model, u, z, dt, [1e-8, 1e-6], [1e-4])
    assert not res.diverged and res.x.shape == (len(z), 2)
    assert np.sqrt(np.mean((res.state("theta")[100:] - x_true[100:, 0]) ** 2)) < 0.01
    assert np.sqrt(np.mean((res.state("omega")[100:] - x_true[100:, 1]) ** 2)) < 0.05
    assert 0.5 < np.mean(res.nis) < 2.0  # χ² with 1 dof: mean 1


@pytest.mark.slow
def test_a_users_check_and_held_cause_stop_the_run_where_the_condition_began(pendulum):
    u, z, _, dt = pendulum
    model = pendulum_model(
        name="pendulum-checked",
        check=pendulum_check,
        held_causes=(7,),
        hold_time=0.1,
        stop_reasons={7: "the pendulum went over the top", 9: "spinning"},
    )
    z = z.copy()
    z[600:] = 1.0  # the bob "measured" at its horizontal extreme: the angle is pulled to π/2+
    for filt in (UKF(), EKF()):
        res = filt.run(model, u, z, dt, [1e-4, 1e-2], [1e-4], x0=[0.6, 0.0], P0=[1e-4, 1e-2])
        assert res.diverged and res.diverged_cause == 7
        assert res.diverged_reason == "the pendulum went over the top"
        k = res.diverged_step
        # the run held |θ| > π/2 for 10 steps from k on: the last valid estimate is before k
        assert k > 600 and np.isnan(res.x[k:]).all() and np.isfinite(res.x[:k]).all()
        assert abs(res.x[k - 1, 0]) <= 0.5 * math.pi


# ------------------------------------------------------------------ robustness -------------


def assert_flagged_not_silent(res, n: int) -> None:
    """Finite rows before the divergence step, NaN rows from it on; all finite otherwise."""
    k = res.diverged_step if res.diverged else n
    assert res.diverged == (res.diverged_step >= 0)
    for name in OUTPUTS:
        arr = np.atleast_2d(getattr(res, name).T).T
        assert np.isfinite(arr[:k]).all() and np.isnan(arr[k:]).all(), name
    assert (res.P_diag[:k] > 0).all()


@pytest.mark.parametrize("filt", [UKF(), EKF()], ids=["ukf", "ekf"])
@pytest.mark.slow
def test_overflow_is_divergence_at_its_step_never_an_exception(cases, filt):
    case = cases["single-track"]
    z = case.z.copy()
    z[150, 0] = 1e90  # finite, positive, below the input bound: the state blows up
    res = filt.run(case.model, case.u, z, case.dt, case.q, case.r, params=case.params)
    assert res.diverged and 150 <= res.diverged_step <= 152
    assert_flagged_not_silent(res, len(z))
    # a model without a validity check: an unobserved state growing 1000-fold per step has
    # a variance growing 10⁶-fold, beyond float64 (1.8e308) at step 52
    model = linear_model(np.diag([1e3, 0.5]), [[0.0, 1.0]])
    z = np.random.default_rng(1).normal(size=(100, 1))
    res = filt.run(model, None, z, 1.0, [0.0, 0.1], [1.0], x0=[1.0, 0.0], P0=[1.0, 1.0])
    assert (res.diverged, res.diverged_cause) == (True, 1) and 51 <= res.diverged_step <= 53
    assert "jitter" in res.diverged_reason
    assert_flagged_not_silent(res, len(z))


@pytest.mark.parametrize("run_kernel", ["ukf", "ekf"])
@pytest.mark.slow
def test_unrepairable_prior_is_divergence_at_step_0_and_singular_is_repaired(cases, run_kernel):
    case = cases["ctrv"]
    model, steps = case.model, 50
    x0, P0 = case.prior()

    def kernel(P_init):
        outs = KernelOutputs.empty(steps, 5, 2)
        data = KernelData(
            case.u[:steps], case.z[:steps], case.p, case.dt, case.q, case.r, x0, P_init, 1,
            np.zeros(0, dtype=np.int64),
        )  # fmt: skip
        tokens = ((0.0,) * 5, (0.0,) * 2)
        if run_kernel == "ukf":
            (w,) = UKF()._options(model)
            stop, rep, cause = gk.ukf_run(model.f, model.h, None, data, w, outs, *tokens)
        else:
            ways = (gk.given_process_jacobian, model.F, gk.given_measurement_jacobian, model.H)
            stop, rep, cause = gk.ekf_run(model.f, model.h, None, data, outs, *tokens, *ways)
        return stop, rep, cause, outs

    for bad in (np.diag([1.0, 1.0, -1.0, 1.0, 1.0]), np.diag([1.0, math.nan, 1.0, 1.0, 1.0])):
        stop, _, cause, outs = kernel(bad)
        assert (stop, cause) == (0, 1) and all(np.isnan(a).all() for a in outs)
    singular = P0.copy()
    singular[0, 1] = singular[1, 0] = math.sqrt(P0[0, 0] * P0[1, 1])  # rank-deficient
    stop, rep, cause, outs = kernel(singular)
    assert (stop, cause) == (-1, 0) and rep >= 1 and np.isfinite(outs[0]).all()


def test_kernel_cholesky_matches_the_3x3_one_and_repairs_alike():
    from kftune.models._sideslip_ukf import chol3, chol3_repair

    rng = np.random.default_rng(9)
    L = np.empty((3, 3))
    for _ in range(50):
        B = rng.normal(size=(3, 3))
        P = B @ B.T + 1e-3 * np.eye(3)
        assert gk.chol_repair(P, L, (0.0,) * 3) == (0, 0.0)
        _, l00, l10, l11, l20, l21, l22 = chol3(
            P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 2]
        )
        np.testing.assert_array_equal(np.tril(L), [[l00, 0, 0], [l10, l11, 0], [l20, l21, l22]])
    for P in (
        np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # singular: 1st jitter
        np.diag([1.0, 1.0, -1e-13]),
        np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # indefinite
        np.diag([1.0, math.nan, 1.0]),
        -np.eye(3),
    ):
        ref = chol3_repair(P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 2])
        assert gk.chol_repair(P, L, (0.0,) * 3) == (ref[0], ref[-1])
    # a subnormal scale underflows the first jitter to 0: both escalations end (not repairable)
    assert gk.chol_repair(np.diag([1e-320, 1e-320, -1e-320]), L, (0.0,) * 3) == (2, 0.0)
    assert chol3_repair(1e-320, 0.0, 0.0, 1e-320, 0.0, -1e-320)[0] == 2


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"z": "nan"}, re.escape("z[3, 1] (ay) is nan")),
        ({"u": "nan"}, re.escape("u[3, 1] (ax) is nan")),
        ({"z": (10, 2)}, r"z must have shape \(N, 3\) with N >= 1, columns \[vx, ay, r\]"),
        ({"u": (9, 2)}, "same number of rows"),
        ({"q": [1.0, 1.0]}, r"q must have shape \(3,\).*\(m/s\)²"),
        ({"q": [1.0, -1.0, 1.0]}, re.escape("q[1] = -1.0") + ".*must be >= 0"),
        ({"r": [1.0, 0.0, 1.0]}, re.escape("r[1] = 0.0") + ".*must be > 0"),
        ({"q": [1.0, math.inf, 1.0]}, re.escape("q[1] is inf")),
        ({"dt": 0.0}, "dt must be a finite sample time > 0"),
        ({"x0": [1.0, 2.0]}, r"x0 must have shape \(3,\) \[vx, vy, r\]"),
        ({"x0": [-1.0, 0.0, 0.0]}, r"x0 = .* is not a valid state of model 'single-track'.*Vx"),
        ({"P0": np.diag([1.0, -1.0, 1.0])}, "P0 must be positive definite"),
        ({"P0": [[1.0, 2.0, 0], [0, 1.0, 0], [0, 0, 1.0]]}, "P0 must be symmetric"),
        ({"params": np.ones(4)}, r"params must be a VehicleParams or a packed array"),
        ({"z_vx": -1.0}, re.escape("z[3, 0] (Vx) = -1.0 m/s") + ".*must be > 0"),
        ({"model": "bicycle"}, "unknown model 'bicycle'"),
    ],
)
@pytest.mark.parametrize("filt", [UKF(), EKF()], ids=["ukf", "ekf"])
def test_bad_input_is_refused_before_the_run_naming_the_argument(man, filt, kwargs, match):
    args = {
        "model": "single-track",
        "u": man.u[:10].copy(),
        "z": man.z[:10].copy(),
        "dt": man.dt,
        "q": DEFAULT_Q,
        "r": man.r_var,
    }
    for key, value in kwargs.items():
        if isinstance(value, str) and value == "nan":
            args[key][3, 1] = math.nan
        elif key == "z_vx":
            args["z"][3, 0] = value
        elif isinstance(value, tuple):
            args[key] = np.ones(value)
        else:
            args[key] = value
    extra = {k: args.pop(k) for k in ("x0", "P0", "params") if k in args}
    with pytest.raises(ValueError, match=match):
        filt.run(**args, **extra)


def test_bad_batch_shapes_and_names_are_refused(man):
    u, z = man.u[:10], man.z[:10]
    with pytest.raises(ValueError, match=r"q must have shape \(B, 3\)"):
        UKF().run_batch(SINGLE_TRACK, u, z, man.dt, DEFAULT_Q, man.r_var)
    with pytest.raises(ValueError, match=r"r must have shape \(3,\) or \(B, 3\) with B = 2"):
        UKF().run_batch(SINGLE_TRACK, u, z, man.dt, [DEFAULT_Q] * 2, [man.r_var] * 3)
    with pytest.raises(ValueError, match="u must have shape"):  # a model with inputs needs u
        UKF().run(SINGLE_TRACK, None, z, man.dt, DEFAULT_Q, man.r_var)
    with pytest.raises(ValueError, match="no initial-state rule: give x0 and P0"):
        UKF().run(linear_model(np.eye(2), np.eye(2)), None, np.ones((5, 2)), 1.0, [1, 1], [1, 1])
    with pytest.raises(ValueError, match="settings must be a UKFSettings"):
        UKF(settings=(1.0, 2.0, 0.0))
    assert filter_names() == ["ekf", "ukf"]
    assert get_filter("ukf", settings=UKFSettings(0.5)) == UKF(UKFSettings(0.5))
    with pytest.raises(ValueError, match="unknown filter 'pf'"):
        get_filter("pf")
    with pytest.raises(ValueError, match="filter 'ekf'"):
        get_filter("ekf", alpha=1.0)
    with pytest.raises(ValueError, match="no state 'beta'"):
        UKF().run(SINGLE_TRACK, u, z, man.dt, DEFAULT_Q, man.r_var).state("beta")
