"""The innovation-likelihood cost (``--cost pem``) against independent references: a direct
numpy computation from FilterPy's UKF, and maximum-likelihood recovery of a known process
noise on a linear-Gaussian system (the classic property of ML tuning)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterPyUKF
from scipy.optimize import minimize_scalar

from kftune.data import default_dataset
from kftune.filters import get_filter
from kftune.models.linear import linear_model
from kftune.tuning.cost import CostSpec, innovation_nll
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem
from kftune.vehicle import measure, step_rk4
from single_track import default_initial_state

Q = np.array([1e-5, 1e-4, 1e-5])


def filterpy_nll(m, vehicle, q, r, n: int, settings) -> float:
    """Mean Gaussian innovation NLL of FilterPy's UKF (same f, h, prior, time convention)."""
    p = vehicle.to_array()
    points = MerweScaledSigmaPoints(
        3, alpha=settings.alpha, beta=settings.beta, kappa=settings.kappa
    )
    ukf = FilterPyUKF(
        dim_x=3, dim_z=3, dt=m.dt, points=points,
        fx=lambda x, dt, u: step_rk4(x, u, p, dt), hx=lambda x, u: measure(x, u, p),
    )  # fmt: skip
    ukf.x, ukf.P = (a.copy() for a in default_initial_state(m.z, r))
    ukf.Q, ukf.R = np.diag(q), np.diag(r)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
    total = 0.0
    for k in range(n):
        if k > 0:
            ukf.predict(u=m.u[k - 1])
        ukf.update(m.z[k], u=m.u[k])
        y, S = ukf.y, ukf.S
        total += 0.5 * (
            np.linalg.slogdet(S)[1] + y @ np.linalg.solve(S, y) + 3 * math.log(2 * math.pi)
        )
    return total / n


@pytest.mark.slow
def test_pem_cost_equals_filterpy_innovation_likelihood():
    ds = default_dataset()
    m = min(ds.train, key=lambda m: m.n)
    settings = NoiseParameterization().default_settings
    problem = TuningProblem([m], ds.vehicle, ds.r_default, cost=CostSpec(kind="pem"))
    got = problem(Q)
    ref = filterpy_nll(m, ds.vehicle, Q, ds.r_default, m.n, settings)
    assert got == pytest.approx(ref, rel=1e-9, abs=1e-9)
    # the NIS cost of the same problem is unchanged by the new output
    nis = TuningProblem([m], ds.vehicle, ds.r_default, cost=CostSpec(kind="nis"))
    assert math.isfinite(nis(Q))


def test_pem_diverged_filter_is_a_failed_evaluation():
    from kftune.errors import FilterDivergedError

    ds = default_dataset()
    problem = TuningProblem(ds.train[:1], ds.vehicle, ds.r_default, cost=CostSpec(kind="pem"))
    with pytest.raises(FilterDivergedError):
        problem.evaluate([1e9, 1e9, 1e9])


def _simulate(q_true: float, r_true: float, a: float, n: int, seed: int):
    rng = np.random.default_rng(seed)
    x = np.zeros(3)
    z = np.empty((n, 3))
    for k in range(n):
        if k:
            x = a * x + rng.normal(0.0, math.sqrt(q_true), 3)
        z[k] = x + rng.normal(0.0, math.sqrt(r_true), 3)
    return z


@pytest.mark.slow
def test_minimising_the_likelihood_recovers_the_true_process_noise():
    """Monte Carlo: AR(1) states seen in white noise; the ML estimate of a scalar q (Q = q·I,
    R known) lands near the true q."""
    q_true, r_true, a, n = 0.04, 0.25, 0.95, 6000
    F, H = a * np.eye(3), np.eye(3)
    model = linear_model(F, H)
    r = np.full(3, r_true)
    estimates = []
    for seed in range(3):
        z = _simulate(q_true, r_true, a, n, seed)

        def nll(log_q: float, z: np.ndarray = z) -> float:
            res = get_filter("ukf").run(
                model, None, z, 1.0, np.full(3, 10**log_q), r, x0=np.zeros(3), P0=np.eye(3)
            )
            return innovation_nll([res.log_det_s], [res.nis], 3)

        best = minimize_scalar(nll, bounds=(-4, 0), method="bounded", options={"xatol": 1e-4})
        estimates.append(10**best.x)
    assert np.median(estimates) == pytest.approx(q_true, rel=0.15)
    assert all(abs(math.log(e / q_true)) < math.log(1.5) for e in estimates)


@pytest.mark.slow
def test_multistep_cost_prefers_the_filter_with_the_better_sideslip():
    """On the simulated set, the reference-free msp cost ranks the NRMSE-tuned filter (small
    Vy noise, yaw rate following the gyro) above the manual one, as the β errors do; the
    one-step likelihood does not (why msp is the cost to use; BENCHMARKS.md)."""
    ds = default_dataset()
    train = sorted(ds.train, key=lambda m: m.n)[:3]
    manual, tuned = np.array([1e-6, 1e-4, 1e-6]), np.array([3.5e-8, 6.8e-7, 0.13])
    msp = TuningProblem(train, ds.vehicle, ds.r_default, cost=CostSpec(kind="msp"))
    beta = TuningProblem(train, ds.vehicle, ds.r_default, cost=CostSpec(weights={"beta": 1}))
    assert beta(tuned) < 0.7 * beta(manual)
    assert msp(tuned) < msp(manual)


@pytest.mark.parametrize("filt", ["ukf", "ekf"])
def test_multistep_cost_equals_an_independent_open_loop_prediction(filt):
    """The msp cost of any filter predicts through the model's own f and h: for the
    single-track model it equals h-step RK4 predictions of the vehicle's physics
    (:func:`kftune.vehicle.step_rk4`, :func:`measure`), computed here from the filter's
    posterior states, to rounding."""
    from kftune.tuning.cost import MSP_HORIZON, MSP_STRIDE, multistep_cost

    ds = default_dataset()
    train = sorted(ds.train, key=lambda m: m.n)[:2]
    spec = CostSpec(kind="msp", weights={"ay": 1.0, "r": 1.0})
    problem = TuningProblem(train, ds.vehicle, ds.r_default, cost=spec, filter=filt)
    x = Q
    sq, counts = [], []
    for m in train:
        post = problem.run(x, m).x
        h = max(1, round(MSP_HORIZON / m.dt))
        ks = np.arange(0, m.n - h, MSP_STRIDE)
        xs = post[ks]
        for j in range(h):
            xs = step_rk4(xs, m.u[ks + j], ds.vehicle, m.dt)
        err = (measure(xs, m.u[ks + h], ds.vehicle) - m.z[ks + h])[:, [2, 1]]
        sq.append(np.sum(err**2, axis=0))
        counts.append(ks.size)
    assert problem(x) == pytest.approx(multistep_cost(sq, counts), rel=1e-10)


def test_open_loop_prediction_of_a_linear_model_is_its_closed_form():
    """h steps of x ← F x + G u, then z = H x + D u: F^h x0 + Σ_j F^(h−1−j) G u_(k+j)."""
    rng = np.random.default_rng(3)
    F = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    G, H, D = rng.standard_normal((3, 2)), rng.standard_normal((2, 3)), rng.standard_normal((2, 2))
    model = linear_model(F, H, G, D)
    u = rng.standard_normal((40, 2))
    x0 = rng.standard_normal((4, 3))
    starts, h = np.array([0, 5, 17, 30]), 7
    got = model.predict_open_loop(x0, u, model.default_params(), 0.1, starts, h)
    for i, k in enumerate(starts):
        x = np.linalg.matrix_power(F, h) @ x0[i]
        x += sum(np.linalg.matrix_power(F, h - 1 - j) @ G @ u[k + j] for j in range(h))
        np.testing.assert_allclose(got[i], H @ x + D @ u[k + h], rtol=1e-12, atol=1e-12)
