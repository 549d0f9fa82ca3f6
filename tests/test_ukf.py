"""The single-track model's compiled UKF loop (what :class:`kftune.filters.UKF` runs on
:data:`kftune.models.SINGLE_TRACK`) against independent references: FilterPy's UKF on the
nonlinear single-track model, the numpy reference filter (itself checked against a linear
Kalman filter), closed-form unscented-transform moments and Cholesky factors, and the χ²
statistics of the NIS on a consistent simulation. The generic UKF on linear models is
checked against the Kalman filter in test_filters_generic.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterPyUKF

from kftune.cli.demo import DEFAULT_Q, demo_inputs, demo_manoeuvre
from kftune.filters import UKFSettings, merwe_weights, sigma_points, unscented_transform
from kftune.models._sideslip_ukf import chol3, chol3_repair
from kftune.vehicle import lateral_forces, measure, preset, simulate, slip_angles, step_rk4
from reference_ukf import UnscentedKalmanFilter, run_ukf_reference
from single_track import beta as beta_of
from single_track import default_initial_state, run_ukf, run_ukf_batch

BMW = preset("bmw-320i")


def max_rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max over channels of max_k |a − b| / max_k |b| (channel-scaled relative difference)."""
    return float(np.max(np.max(np.abs(a - b), axis=0) / np.max(np.abs(b), axis=0)))


def filterpy_run(man, q, settings: UKFSettings, n: int | None = None) -> np.ndarray:
    """FilterPy's UKF with the same f, h, Q, R, prior and time convention as run_ukf."""
    n = man.u.shape[0] if n is None else n
    p = man.params.to_array()
    points = MerweScaledSigmaPoints(
        3, alpha=settings.alpha, beta=settings.beta, kappa=settings.kappa
    )
    ukf = FilterPyUKF(
        dim_x=3,
        dim_z=3,
        dt=man.dt,
        fx=lambda x, dt, u: step_rk4(x, u, p, dt),
        hx=lambda x, u: measure(x, u, p),
        points=points,
    )
    x0, P0 = default_initial_state(man.z, man.r_var)
    ukf.x, ukf.P = x0.copy(), P0.copy()
    ukf.Q, ukf.R = np.diag(q), np.diag(man.r_var)
    # step 0: update the prior (x0, P0) with z[0] — no prediction, so give FilterPy the
    # sigma points its predict() would otherwise have left for update()
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
    xs = np.empty((n, 3))
    for k in range(n):
        if k > 0:
            ukf.predict(u=man.u[k - 1])  # u[k−1] held over t_{k−1} → t_k
        ukf.update(man.z[k], u=man.u[k])  # h(·, u[k])
        xs[k] = ukf.x
    return xs


@pytest.fixture(scope="module")
def manoeuvre():
    return demo_manoeuvre(seed=7)


def test_manoeuvre_exercises_the_dugoff_saturation(manoeuvre):
    assert manoeuvre.u.shape == (2000, 2)
    x, u, p = manoeuvre.x_true, manoeuvre.u, manoeuvre.params
    forces, slips = lateral_forces(x, u, p), slip_angles(x, u, p)
    deficit = np.zeros(len(x))
    for F, alpha, C in zip(forces, slips, (p.C_af, p.C_ar)):
        linear = C * np.tan(alpha)
        deficit = np.maximum(deficit, np.abs(F - linear) / np.maximum(np.abs(linear), 1.0))
    assert np.mean(deficit > 0.01) > 0.2  # a fifth of the run is beyond the linear tyre
    assert deficit.max() > 0.3
    assert np.abs(manoeuvre.z[:, 1]).max() > 7.0


@pytest.mark.slow
def test_kernel_equals_filterpy_on_nonlinear_manoeuvre(manoeuvre):
    settings = UKFSettings()
    res = run_ukf(
        manoeuvre.u, manoeuvre.z, manoeuvre.dt, manoeuvre.params, DEFAULT_Q, manoeuvre.r_var
    )
    ref = filterpy_run(manoeuvre, DEFAULT_Q, settings)
    assert not res.diverged and res.n_repairs == 0
    assert max_rel_diff(res.x, ref) <= 1e-9
    # element by element too, where the reference is not near zero
    big = np.abs(ref) > 1e-3 * np.max(np.abs(ref), axis=0)
    assert np.max(np.abs(res.x - ref)[big] / np.abs(ref)[big]) <= 1e-9


@pytest.mark.parametrize(
    ("alpha", "beta", "kappa"), [(0.5, 2.0, 0.0), (1e-2, 2.0, 1.0), (1.3, 0.0, 2.0)]
)
def test_kernel_equals_filterpy_for_other_sigma_point_settings(manoeuvre, alpha, beta, kappa):
    settings = UKFSettings(alpha, beta, kappa)
    n = 400
    q = np.array([1e-3, 1e-3, 1e-4])
    res = run_ukf(
        manoeuvre.u[:n], manoeuvre.z[:n], manoeuvre.dt, manoeuvre.params, q, manoeuvre.r_var,
        settings=settings,
    )  # fmt: skip
    ref = filterpy_run(manoeuvre, q, settings, n)
    assert max_rel_diff(res.x, ref) <= 1e-9


def test_kernel_equals_reference_path_in_every_output(manoeuvre):
    args = (manoeuvre.u, manoeuvre.z, manoeuvre.dt, manoeuvre.params, DEFAULT_Q, manoeuvre.r_var)
    res, ref = run_ukf(*args), run_ukf_reference(*args)
    for name in ("x", "P_diag", "z_hat", "innovation"):
        assert max_rel_diff(getattr(res, name), getattr(ref, name)) <= 1e-9, name
    assert max_rel_diff(res.nis[:, None], ref.nis[:, None]) <= 1e-9
    assert max_rel_diff(res.log_det_s[:, None], ref.log_det_s[:, None]) <= 1e-9
    np.testing.assert_allclose(res.output("beta"), np.arctan2(res.x[:, 1], res.x[:, 0]))
    # z_hat is h(posterior, u_k), the estimated measurement the tuning cost uses
    np.testing.assert_allclose(res.z_hat, measure(res.x, manoeuvre.u, BMW), rtol=1e-12, atol=1e-12)


def test_nis_is_chi2_with_3_dof_when_model_and_noise_are_right():
    # plant = the filter's model, exact inputs, Gaussian measurement noise of variance r
    u = demo_inputs()
    x = simulate([22.0, 0.0, 0.0], u, BMW, 0.01)
    r = np.array([0.05, 0.1, math.radians(0.2)]) ** 2
    z = measure(x, u, BMW) + np.random.default_rng(11).standard_normal(x.shape) * np.sqrt(r)
    res = run_ukf(u, z, 0.01, BMW, [1e-12] * 3, r, x0=x[0], P0=[r[0], 1e-4, r[2]])
    # E[NIS] = 3, Var = 6 per step; 2000 steps → standard error ≈ 0.055
    assert res.nis.mean() == pytest.approx(3.0, abs=0.2)
    beta_true = np.arctan2(x[:, 1], x[:, 0])
    assert np.degrees(np.sqrt(np.mean((res.output("beta") - beta_true) ** 2))) < 0.01


def test_batch_equals_single_runs(manoeuvre):
    rng = np.random.default_rng(2)
    q = 10.0 ** rng.uniform(-8, -2, size=(5, 3))
    r = manoeuvre.r_var * 10.0 ** rng.uniform(-1, 1, size=(5, 3))
    args = (manoeuvre.u, manoeuvre.z, manoeuvre.dt, manoeuvre.params)
    for r_arg in (manoeuvre.r_var, r):
        batch = run_ukf_batch(*args, q, r_arg)
        assert (
            len(batch) == 5 and batch.x.shape == (5, 2000, 3) and beta_of(batch).shape == (5, 2000)
        )
        for b in range(5):
            single = run_ukf(*args, q[b], r_arg if r_arg.ndim == 1 else r_arg[b])
            one = batch[b]
            for name in ("x", "P_diag", "z_hat", "innovation", "nis"):
                np.testing.assert_array_equal(getattr(one, name), getattr(single, name))
            assert one.diverged == single.diverged and one.diverged_step == single.diverged_step
    one_set = run_ukf_batch(*args, q[:1], r[0])  # B = 1 takes the sequential path
    np.testing.assert_array_equal(one_set.x[0], run_ukf(*args, q[0], r[0]).x)


# ------------------------------------------------------------------ linear model ----------


def linear_system(seed: int = 0, n: int = 300):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    F = 0.97 * A / np.max(np.abs(np.linalg.eigvals(A)))  # stable
    G = rng.normal(size=(3, 2)) * 0.1
    H = rng.normal(size=(3, 3))
    D = rng.normal(size=(3, 2)) * 0.2
    q = np.array([1e-3, 4e-3, 2e-4])
    r = np.array([0.05, 0.02, 0.1])
    u = rng.normal(size=(n, 2))
    x = np.zeros((n, 3))
    x[0] = rng.normal(size=3)
    for k in range(1, n):
        x[k] = F @ x[k - 1] + G @ u[k - 1] + rng.normal(size=3) * np.sqrt(q)
    z = x @ H.T + u @ D.T + rng.normal(size=(n, 3)) * np.sqrt(r)
    return F, G, H, D, q, r, u, z


def test_reference_class_equals_linear_kalman_filter():
    F, G, H, D, q, r, u, z = linear_system(seed=1, n=100)
    ukf = UnscentedKalmanFilter(
        fx=lambda X, uk: X @ F.T + G @ uk,
        hx=lambda X, uk: X @ H.T + D @ uk,
        Q=np.diag(q),
        R=np.diag(r),
        x0=np.zeros(3),
        P0=np.eye(3),
    )
    kf = KalmanFilter(dim_x=3, dim_z=3, dim_u=2)
    kf.F, kf.B, kf.H, kf.Q, kf.R, kf.x, kf.P = (
        F,
        G,
        H,
        np.diag(q),
        np.diag(r),
        np.zeros(3),
        np.eye(3),
    )
    for k in range(len(u)):
        if k > 0:
            ukf.predict(u[k - 1])
            kf.predict(u=u[k - 1])
        ukf.update(z[k], u[k])
        kf.update(z[k] - D @ u[k])
        np.testing.assert_allclose(ukf.x, kf.x, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(ukf.P, kf.P, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("settings", [UKFSettings(), UKFSettings(0.1, 2.0, 1.0)])
def test_unscented_transform_is_exact_for_linear_maps_and_quadratic_means(settings):
    rng = np.random.default_rng(5)
    x = rng.normal(size=3)
    B = rng.normal(size=(3, 3))
    P = B @ B.T + 0.1 * np.eye(3)
    A, c = rng.normal(size=(4, 3)), rng.normal(size=4)
    wm, wc = merwe_weights(3, settings)
    assert wm.sum() == pytest.approx(1.0)
    sig = sigma_points(x, P, settings)
    mean, cov = unscented_transform(sig @ A.T + c, wm, wc)
    np.testing.assert_allclose(mean, A @ x + c, rtol=1e-12)
    np.testing.assert_allclose(cov, A @ P @ A.T, rtol=1e-10, atol=1e-12)
    # E[xᵀMx] = x̄ᵀMx̄ + tr(MP) — the UT mean is exact to second order
    M = rng.normal(size=(3, 3))
    quad = np.einsum("ij,jk,ik->i", sig, M, sig)[:, None]
    q_mean, _ = unscented_transform(quad, wm, wc)
    assert q_mean[0] == pytest.approx(x @ M @ x + np.trace(M @ P), rel=1e-10)


def test_closed_form_cholesky_and_repair():
    rng = np.random.default_rng(9)
    for _ in range(50):
        B = rng.normal(size=(3, 3))
        P = B @ B.T + 1e-3 * np.eye(3)
        ok, l00, l10, l11, l20, l21, l22 = chol3(
            P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 2]
        )
        L = np.array([[l00, 0, 0], [l10, l11, 0], [l20, l21, l22]])
        assert ok
        np.testing.assert_allclose(L, np.linalg.cholesky(P), rtol=1e-10, atol=1e-12)
    # singular (positive semi-definite): repaired by the first jitter, 1e-12·max(diag)
    st, *_, jitter = chol3_repair(1.0, 1.0, 0.0, 1.0, 0.0, 1.0)
    assert (st, jitter) == (1, 1e-12)
    st, *_ = chol3_repair(1.0, 0.0, 0.0, 1.0, 0.0, 1.0 - 1e-13 - 1.0)  # p22 ≈ −1e-13
    assert st == 1
    # clearly indefinite or non-finite: not repairable
    assert chol3_repair(1.0, 2.0, 0.0, 1.0, 0.0, 1.0)[0] == 2
    assert chol3_repair(1.0, 0.0, 0.0, math.nan, 0.0, 1.0)[0] == 2
    assert chol3_repair(-1.0, 0.0, 0.0, -1.0, 0.0, -1.0)[0] == 2
