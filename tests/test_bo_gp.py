"""Exact GP and Student-t process against scikit-learn, scipy and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, Matern
from sklearn.gaussian_process.kernels import ConstantKernel as C

from kftune.bo import GaussianProcess, StudentTProcess
from kftune.bo.kernels import Matern52, SquaredExponential, make_kernel


def data(n: int = 25, d: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, d))
    y = np.sin(3 * X[:, 0]) + X[:, 1] ** 2 - 0.5 * X[:, -1] + 0.05 * rng.standard_normal(n)
    return X, 10.0 + 3.0 * y  # offset and scale so that standardisation matters


def fd_gradient(fun, theta: np.ndarray, h: float = 1e-5) -> np.ndarray:
    g = np.empty_like(theta)
    for j in range(theta.size):
        e = np.zeros_like(theta)
        e[j] = h
        g[j] = (fun(theta + e) - fun(theta - e)) / (2 * h)
    return g


LS = np.array([0.3, 0.55, 0.9])
SF2 = 1.7
NOISE = 1e-4


def sk_kernel(kind: str):
    base = Matern(LS, nu=2.5) if kind == "matern52" else RBF(LS)
    return C(SF2) * base


# ---------------------------------------------------------------- kernels
@pytest.mark.parametrize("kind", ["matern52", "se"])
def test_kernel_matrix_and_gradient_match_sklearn(kind):
    X, _ = data(12)
    kern = make_kernel(kind)
    theta = np.r_[np.log(LS), math.log(SF2)]
    K, dK = kern.matrix_and_gradient(theta, X)
    K_sk, dK_sk = sk_kernel(kind)(X, eval_gradient=True)  # sklearn: [log σ², log ℓ...]
    np.testing.assert_allclose(K, K_sk, rtol=1e-13)
    np.testing.assert_allclose(dK[-1], dK_sk[..., 0], rtol=1e-12, atol=1e-15)
    for i in range(3):
        np.testing.assert_allclose(dK[i], dK_sk[..., i + 1], rtol=1e-10, atol=1e-14)
    Xs = np.random.default_rng(1).random((7, 3))
    np.testing.assert_allclose(kern.matrix(theta, X, Xs), sk_kernel(kind)(X, Xs), rtol=1e-13)


def test_kernel_gradient_matches_finite_differences_at_coincident_points():
    X = np.array([[0.2, 0.4], [0.2, 0.4], [0.9, 0.1]])  # r = 0 off the diagonal too
    for kern in (Matern52(), SquaredExponential()):
        theta = np.array([-1.0, 0.3, 0.2])
        _, dK = kern.matrix_and_gradient(theta, X)
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-6
            fd = (kern.matrix(theta + e, X, X) - kern.matrix(theta - e, X, X)) / 2e-6
            np.testing.assert_allclose(dK[j], fd, rtol=1e-7, atol=1e-10)


def test_unknown_kernel_names_the_valid_ones():
    with pytest.raises(ValueError, match="matern52"):
        make_kernel("matern32")


# ---------------------------------------------------------------- GP vs scikit-learn
@pytest.mark.parametrize("kind", ["matern52", "se"])
def test_gp_equals_sklearn_with_fixed_hyperparameters(kind):
    X, y = data()
    # sklearn's normalize_y: y ← (y − mean)/std (population std); alpha is then added to
    # the diagonal in those standardised units. Our GP with mean="zero" and a fixed noise
    # is the same model.
    gp = GaussianProcess(kernel=kind, noise=NOISE, mean="zero")
    gp.fit(X, y, theta=np.r_[np.log(LS), math.log(SF2)])
    sk = GaussianProcessRegressor(
        sk_kernel(kind), alpha=NOISE, normalize_y=True, optimizer=None
    ).fit(X, y)
    Xs = np.random.default_rng(3).random((40, 3))
    pred = gp.predict(Xs)
    mean, cov = sk.predict(Xs, return_cov=True)
    np.testing.assert_allclose(pred.mean, mean, rtol=1e-8)
    np.testing.assert_allclose(pred.variance, np.diag(cov), rtol=1e-8)
    assert math.isinf(pred.dof)
    theta_sk = np.r_[math.log(SF2), np.log(LS)]
    ll_sk, g_sk = sk.log_marginal_likelihood(theta_sk, eval_gradient=True)
    ll, g = gp.log_marginal_likelihood(eval_gradient=True)
    np.testing.assert_allclose(ll, ll_sk, rtol=1e-8)
    np.testing.assert_allclose(g, np.r_[g_sk[1:], g_sk[0]], rtol=1e-7, atol=1e-9)


def test_gp_fitted_likelihood_is_at_least_sklearns_optimum():
    # Same model, both optimised: our optimum must be as good as scikit-learn's (which
    # uses the same likelihood), within optimiser tolerance.
    X, y = data(30)
    kernel = C(1.0, (1e-2, 1e2)) * Matern(np.ones(3), (5e-3, 20.0), nu=2.5)
    sk = GaussianProcessRegressor(
        kernel, alpha=NOISE, normalize_y=True, n_restarts_optimizer=4, random_state=0
    ).fit(X, y)
    gp = GaussianProcess(noise=NOISE, mean="zero", seed=0, n_restarts=4).fit(X, y)
    assert gp.log_marginal_likelihood() >= sk.log_marginal_likelihood_value_ - 1e-4


@pytest.mark.parametrize("mean", ["constant", "zero"])
@pytest.mark.parametrize("kind", ["matern52", "se"])
def test_gp_likelihood_gradient_matches_finite_differences(mean, kind):
    X, y = data(20, d=2)
    gp = GaussianProcess(kernel=kind, mean=mean, seed=1).fit(X, y)
    theta = np.array([-1.2, -0.4, 0.3, math.log(1e-2)])
    _, g = gp.log_marginal_likelihood(theta, eval_gradient=True)
    np.testing.assert_allclose(g, fd_gradient(gp.log_marginal_likelihood, theta), rtol=1e-6)


def test_constant_mean_is_the_gls_estimate():
    X, y = data(15)
    theta = np.r_[np.log(LS), math.log(SF2)]
    gp = GaussianProcess(noise=NOISE).fit(X, y, theta=theta)
    K = sk_kernel("matern52")(X) + NOISE * np.eye(15)
    ys = (y - y.mean()) / y.std()
    one = np.ones(15)
    m_gls = one @ np.linalg.solve(K, ys) / (one @ np.linalg.solve(K, one))
    np.testing.assert_allclose(gp.hyperparameters["mean"], y.mean() + y.std() * m_gls, rtol=1e-12)

    # and it maximises the likelihood over constant means
    def ll_at(m: float) -> float:
        return stats.multivariate_normal(np.full(15, m), K).logpdf(ys)

    assert ll_at(m_gls) > max(ll_at(m_gls - 1e-3), ll_at(m_gls + 1e-3))


def test_failed_cholesky_gives_minus_inf_not_an_exception():
    X, y = data(10)
    gp = GaussianProcess(noise=0.0, mean="zero").fit(X, y)
    nan_theta = np.array([np.nan, 0.0, 0.0, 0.0])
    assert gp.log_marginal_likelihood(nan_theta) == -math.inf
    # duplicated points, no noise: singular K, rescued by the jitter ladder
    Xd = np.vstack([X, X[:3]])
    yd = np.r_[y, y[:3] + 0.5]
    gp.fit(Xd, yd)
    assert gp.hyperparameters["jitter"] > 0.0
    assert np.all(np.isfinite(gp.predict(X).mean))


# ---------------------------------------------------------------- Student-t process
@pytest.mark.parametrize("nu", [2.5, 5.0, 15.0, 80.0])
def test_tsp_likelihood_equals_scipy_multivariate_t(nu):
    X, y = data(18)
    theta = np.r_[np.log(LS), math.log(SF2)]
    tsp = StudentTProcess(dof=nu, noise=NOISE, mean="zero").fit(X, y, theta=theta)
    K = sk_kernel("matern52")(X) + NOISE * np.eye(18)
    ys = (y - y.mean()) / y.std()
    ref = stats.multivariate_t(loc=np.zeros(18), shape=(nu - 2) / nu * K, df=nu).logpdf(ys)
    np.testing.assert_allclose(tsp.log_marginal_likelihood(), ref, rtol=1e-10)
    # with the constant mean: the MVT centred at the profiled mean
    tsp_c = StudentTProcess(dof=nu, noise=NOISE).fit(X, y, theta=theta)
    m = (tsp_c.hyperparameters["mean"] - y.mean()) / y.std()
    ref_c = stats.multivariate_t(loc=np.full(18, m), shape=(nu - 2) / nu * K, df=nu).logpdf(ys)
    np.testing.assert_allclose(tsp_c.log_marginal_likelihood(), ref_c, rtol=1e-10)


def test_tsp_predictive_is_the_conditional_of_the_joint_multivariate_t():
    # Independent of Shah et al.'s closed form: the conditional density of f* given y is
    # p(y, f*)/p(y), both from scipy's multivariate t with covariance K (shape (ν−2)/ν K).
    X, y = data(12)
    nu = 6.0
    theta = np.r_[np.log(LS), math.log(SF2)]
    tsp = StudentTProcess(dof=nu, noise=NOISE, mean="zero").fit(X, y, theta=theta)
    x_star = np.array([[0.4, 0.6, 0.2]])
    pred = tsp.predict(x_star)
    assert pred.dof == nu + 12
    ys = (y - y.mean()) / y.std()
    Xa = np.vstack([X, x_star])
    Kj = sk_kernel("matern52")(Xa) + NOISE * np.diag(np.r_[np.ones(12), 0.0])
    joint = stats.multivariate_t(np.zeros(13), (nu - 2) / nu * Kj, df=nu)
    marg = stats.multivariate_t(np.zeros(12), (nu - 2) / nu * Kj[:12, :12], df=nu)
    for f_std in (-1.0, 0.3, 2.5):  # standardised units
        log_cond = joint.logpdf(np.r_[ys, f_std]) - marg.logpdf(ys)
        f = y.mean() + y.std() * f_std
        ours = stats.t.logpdf(f, pred.dof, pred.mean[0], pred.scale[0]) + math.log(y.std())
        np.testing.assert_allclose(ours, log_cond, rtol=1e-9)


@pytest.mark.parametrize("fit_dof", [False, True])
@pytest.mark.parametrize("mean", ["constant", "zero"])
def test_tsp_likelihood_gradient_matches_finite_differences(fit_dof, mean):
    X, y = data(20, d=2)
    tsp = StudentTProcess(fit_dof=fit_dof, mean=mean, seed=2).fit(X, y)
    theta = np.array([-1.2, -0.4, 0.3, math.log(1e-2)] + ([math.log(4.0)] if fit_dof else []))
    _, g = tsp.log_marginal_likelihood(theta, eval_gradient=True)
    np.testing.assert_allclose(g, fd_gradient(tsp.log_marginal_likelihood, theta), rtol=1e-6)


def test_tsp_tends_to_gp_as_dof_grows():
    X, y = data(20)
    theta = np.r_[np.log(LS), math.log(SF2)]
    Xs = np.random.default_rng(5).random((30, 3))
    gp = GaussianProcess(noise=NOISE).fit(X, y, theta=theta)
    p_gp = gp.predict(Xs)
    gaps = []
    for nu in (1e3, 1e5, 1e7):
        tsp = StudentTProcess(dof=nu, noise=NOISE).fit(X, y, theta=theta)
        p = tsp.predict(Xs)
        np.testing.assert_allclose(p.mean, p_gp.mean, rtol=1e-12)  # same mean for any ν
        gaps.append(np.max(np.abs(p.variance / p_gp.variance - 1)))
        assert abs(tsp.log_marginal_likelihood() - gp.log_marginal_likelihood()) < 1e3 / nu
    assert gaps[2] < 1e-5 and gaps[1] < gaps[0] / 50 and gaps[2] < gaps[1] / 50


def test_tsp_variance_scaling_and_dof():
    # Paper Eq. 7: var_tSP = (ν + β − 2)/(ν + n − 2) · var_GP with β = (y−m)ᵀK⁻¹(y−m).
    X, y = data(16)
    theta = np.r_[np.log(LS), math.log(SF2)]
    Xs = np.random.default_rng(6).random((5, 3))
    gp = GaussianProcess(noise=NOISE, mean="zero").fit(X, y, theta=theta)
    tsp = StudentTProcess(dof=15.0, noise=NOISE, mean="zero").fit(X, y, theta=theta)
    K = sk_kernel("matern52")(X) + NOISE * np.eye(16)
    ys = (y - y.mean()) / y.std()
    beta = ys @ np.linalg.solve(K, ys)
    np.testing.assert_allclose(
        tsp.predict(Xs).variance,
        (15 + beta - 2) / (15 + 16 - 2) * gp.predict(Xs).variance,
        rtol=1e-10,
    )
    assert tsp.predict(Xs).dof == 31.0


def test_fitted_dof_stays_in_bounds_and_is_reported():
    X, y = data(25)
    tsp = StudentTProcess(fit_dof=True, dof_bounds=(3.0, 200.0), dof=10.0, seed=0).fit(X, y)
    hp = tsp.hyperparameters
    assert hp["dof_fitted"] and 3.0 <= hp["dof"] <= 200.0
    assert tsp.predict(X[:2]).dof == pytest.approx(hp["dof"] + 25)
    with pytest.raises(ValueError, match="dof"):
        StudentTProcess(dof=2.0)
