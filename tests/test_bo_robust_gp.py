"""GP with Student-t likelihood (Laplace): gradients, mode, Gaussian limit, robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import optimize, stats
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel as C
from sklearn.gaussian_process.kernels import Matern

from kftune.bo import GaussianProcess, RobustGaussianProcess, StudentTProcess
from test_bo_gp import fd_gradient

LS = np.array([0.35, 0.6])
SF2 = 1.4


def outlier_data(n: int = 25, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, 2))
    y = np.sin(3 * X[:, 0]) + X[:, 1] ** 2 + 0.03 * rng.standard_normal(n)
    y[[2, 9]] += [4.0, -3.0]  # two gross outliers
    return X, y


def robust_standardise(y: np.ndarray) -> np.ndarray:
    med = np.median(y)
    return (y - med) / (1.4826 * np.median(np.abs(y - med)))


def neg_psi(f: np.ndarray, K: np.ndarray, ys: np.ndarray, nu: float, sigma: float) -> float:
    """−[log p(y|f) − ½ fᵀK⁻¹f] with scipy's Student-t density."""
    return -(stats.t.logpdf(ys, nu, loc=f, scale=sigma).sum() - 0.5 * f @ np.linalg.solve(K, f))


@pytest.mark.parametrize("fit_dof", [False, True])
def test_laplace_gradient_matches_finite_differences_with_negative_W(fit_dof):
    X, y = outlier_data()
    model = RobustGaussianProcess(fit_likelihood_dof=fit_dof, seed=0).fit(X, y)
    extra = [math.log(3.0)] if fit_dof else []
    theta = np.r_[np.log(LS), math.log(SF2), math.log(0.08), extra]
    _, g = model.log_marginal_likelihood(theta, eval_gradient=True)
    fd = fd_gradient(model.log_marginal_likelihood, theta)
    np.testing.assert_allclose(g, fd, rtol=2e-6, atol=1e-8)
    # the test exercises the non-log-concave case: residuals with r² > νσ² (W < 0)
    model.fit(X, y, theta=theta)
    ys = robust_standardise(y)
    f_hat = (model.predict(X).mean - np.median(y)) / (1.4826 * np.median(np.abs(y - np.median(y))))
    nu = 3.0 if fit_dof else 4.0
    assert np.sum((ys - f_hat) ** 2 > nu * 0.08**2) >= 2


def test_laplace_mode_matches_a_generic_optimiser():
    X, y = outlier_data(15, seed=3)
    theta = np.r_[np.log(LS), math.log(SF2), math.log(0.1)]
    model = RobustGaussianProcess().fit(X, y, theta=theta)
    ys = robust_standardise(y)
    K = (C(SF2) * Matern(LS, nu=2.5))(X)
    res = optimize.minimize(
        neg_psi, np.zeros(15), args=(K, ys, 4.0, 0.1), method="BFGS", options={"gtol": 1e-10}
    )
    center = np.median(y)
    scale = 1.4826 * np.median(np.abs(y - center))
    f_hat = (model.predict(X).mean - center) / scale
    np.testing.assert_allclose(f_hat, res.x, atol=1e-6)
    assert model.laplace_converged


def test_gaussian_likelihood_limit_equals_exact_gp():
    # As ν → ∞ the Student-t likelihood becomes Gaussian with variance σ², for which the
    # Laplace approximation is exact: compare with scikit-learn's GP on the same
    # (robustly standardised) data.
    X, y = outlier_data(20, seed=1)
    sigma = 0.3
    model = RobustGaussianProcess(likelihood_dof=1e14)
    model.fit(X, y, theta=np.r_[np.log(LS), math.log(SF2), math.log(sigma)])
    ys = robust_standardise(y)
    sk = GaussianProcessRegressor(C(SF2) * Matern(LS, nu=2.5), alpha=sigma**2, optimizer=None).fit(
        X, ys
    )
    Xs = np.random.default_rng(2).random((25, 2))
    pred = model.predict(Xs)
    center = np.median(y)
    scale = 1.4826 * np.median(np.abs(y - center))
    mean, std = sk.predict(Xs, return_std=True)
    np.testing.assert_allclose((pred.mean - center) / scale, mean, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(pred.std / scale, std, rtol=1e-6)
    np.testing.assert_allclose(model.log_marginal_likelihood(), sk.log_marginal_likelihood_value_)


# ---------------------------------------------------------------- robustness property
FUNCTIONS = {
    "sine": lambda X: np.sin(2 * np.pi * X[:, 0]) + 0.5 * np.cos(np.pi * X[:, 1]),
    "valley": lambda X: (X[:, 1] - 0.5 * X[:, 0] ** 2) ** 2 + 0.3 * np.cos(3 * X[:, 0]),
    "bowl": lambda X: ((X - 0.4) ** 2).sum(axis=1),
    "rosenbrock": lambda X: (1 - X[:, 0]) ** 2 + 2 * (X[:, 1] - X[:, 0] ** 2) ** 2,
}
CASES = [(name, seed) for name in FUNCTIONS for seed in (0, 1)]


def held_out_errors(name: str, seed: int) -> dict[str, float]:
    """Held-out RMSE / range of f for each surrogate, 30 points with 3 planted outliers of
    2–5 times the range of f."""
    f = FUNCTIONS[name]
    rng = np.random.default_rng(seed)
    X = rng.random((30, 2))
    y = f(X)
    span = float(y.max() - y.min())
    idx = rng.choice(30, 3, replace=False)
    y_obs = y.copy()
    y_obs[idx] += rng.choice([-1.0, 1.0], 3) * span * rng.uniform(2, 5, 3)
    Xt = rng.random((400, 2))
    errs = {}
    for label, model in (
        ("gp", GaussianProcess(seed=seed)),
        ("tsp", StudentTProcess(seed=seed)),
        ("robust-gp", RobustGaussianProcess(seed=seed)),
    ):
        pred = model.fit(X, y_obs).predict(Xt)
        errs[label] = float(np.sqrt(np.mean((pred.mean - f(Xt)) ** 2)) / span)
    return errs


@pytest.fixture(scope="module")
def robustness_table() -> dict[tuple[str, int], dict[str, float]]:
    return {case: held_out_errors(*case) for case in CASES}


@pytest.mark.parametrize("case", CASES, ids=[f"{n}-{s}" for n, s in CASES])
def test_robust_gp_mean_errs_less_than_gp_under_outliers(case, robustness_table):
    e = robustness_table[case]
    assert e["robust-gp"] < 0.5 * e["gp"], e
    assert e["robust-gp"] < 0.1, e  # and is accurate in absolute terms


@pytest.mark.xfail(
    strict=True,
    reason=(
        "Measured, not assumed: for fixed hyperparameters the exact tSP's posterior mean is "
        "the GP's (Shah et al. 2014: linear in y; see the next test), so only its fitted "
        "hyperparameters differ. Fitted with nu = 15 they are close to the GP's on half the "
        "cases (error ratio tSP/GP 0.85-1.0) and far on the others, where the multivariate-t "
        "likelihood, which penalises a large beta_n only logarithmically, picks near-zero "
        "noise and interpolates the outliers (ratio 1.25-1.93). Only the robust GP "
        "(Student-t noise) is robust in the mean."
    ),
)
def test_tsp_mean_errs_clearly_less_than_gp_under_outliers(robustness_table):
    assert all(e["tsp"] < 0.9 * e["gp"] for e in robustness_table.values())


def test_tsp_mean_is_the_gps_at_equal_hyperparameters():
    """The structural reason behind the xfail above: with the same kernel, noise and
    constant mean, the tSP's posterior mean is the GP's whatever the outliers; only the
    variance differs, by the factor (ν + βₙ − 2)/(ν + n − 2) (Shah et al. 2014, Eq. 8)."""
    X, y = outlier_data()
    gp = GaussianProcess(seed=0).fit(X, y)
    Xt = np.random.default_rng(1).random((50, 2))
    tsp = StudentTProcess(seed=0)
    tsp.fit(X, y, theta=np.r_[gp._theta])  # the GP's standardised hyperparameters
    a, b = gp.predict(Xt), tsp.predict(Xt)
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-9, atol=1e-12)
    ratio = b.variance / a.variance  # one factor for every point, > 1 with outliers
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)
    assert ratio[0] > 1.0
    assert b.dof == 15.0 + len(y) and math.isinf(a.dof)
