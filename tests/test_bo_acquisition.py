"""Acquisition functions against closed-form values, scipy quadrature and Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from kftune.bo.acquisition import (
    confidence_bound,
    expected_improvement,
    log_expected_improvement,
    lower_confidence_bound,
    probability_of_improvement,
)
from kftune.bo.base import Predictive


def t_pred(z: np.ndarray, nu: float, scale: float = 1.0) -> Predictive:
    """Predictive with best = 0 at standardised improvement z, i.e. mean = −z·scale."""
    z = np.asarray(z, dtype=float)
    return Predictive.from_scale(-z * scale, np.full(z.shape, scale), nu)


# ---------------------------------------------------------------- closed-form values
def test_gaussian_ei_and_pi_closed_form():
    # (best − μ)/σ = −0.5 with σ = 1: EI = σ(zΦ(z) + φ(z)) = 0.1977966, PI = Φ(−0.5).
    pred = Predictive(np.array([0.5, 10.5]), np.array([1.0, 1.0]))
    ei = expected_improvement(pred, best=0.0)
    np.testing.assert_allclose(ei[0], 0.1977966, atol=5e-8)
    np.testing.assert_allclose(probability_of_improvement(pred, 0.0)[0], 0.308538, atol=5e-7)
    # Translation invariance: the same z with best = 10.
    np.testing.assert_allclose(expected_improvement(pred, 10.0)[1], ei[0], rtol=1e-13)
    # Scale: EI(σ = 2, z = −0.5) = 2 · 0.1977966
    pred2 = Predictive(np.array([1.0]), np.array([4.0]))
    np.testing.assert_allclose(expected_improvement(pred2, 0.0), 2 * 0.1977966, atol=1e-7)


def test_t_ei_at_z0_nu2_unit_scale_is_inverse_sqrt2():
    # With ν = 2 the variance is infinite: "unit scale" can only be the t scale s = 1.
    pred = Predictive.from_scale(np.array([0.0]), 1.0, 2.0)
    assert np.isinf(pred.variance[0]) and pred.scale[0] == 1.0
    np.testing.assert_allclose(expected_improvement(pred, 0.0), 1 / math.sqrt(2), rtol=1e-14)
    # Independent: E[max(−T, 0)] for T ~ t_2 by quadrature of the density.
    ref, _ = integrate.quad(lambda u: -u * stats.t.pdf(u, 2), -np.inf, 0.0)
    np.testing.assert_allclose(1 / math.sqrt(2), ref, rtol=1e-8)


def test_t_ei_uses_scale_not_std():
    # ν = 5, variance 1: scale s = √(3/5). The right EI integrates the t with that scale;
    # the common bug (std used as scale) gives a visibly different number.
    nu, var, mu = 5.0, 1.0, 0.3
    pred = Predictive(np.array([mu]), np.array([var]), nu)
    s = math.sqrt(var * (nu - 2) / nu)
    dist = stats.t(nu, loc=mu, scale=s)
    assert math.isclose(dist.var(), var, rel_tol=1e-12)  # the Predictive's variance
    ref = dist.expect(lambda y: np.maximum(0.0 - y, 0.0), lb=-np.inf, ub=0.0, epsrel=1e-12)
    got = expected_improvement(pred, 0.0)[0]
    np.testing.assert_allclose(got, ref, rtol=1e-9)
    wrong = stats.t(nu, loc=mu, scale=math.sqrt(var)).expect(
        lambda y: np.maximum(-y, 0.0), lb=-np.inf, ub=0.0
    )
    assert abs(wrong - got) / got > 0.1


@pytest.mark.parametrize("nu", [math.inf, 2.5, 4.0, 17.0, 55.0])
@pytest.mark.parametrize("z", [-1.5, -0.5, 0.0, 0.8])
def test_ei_matches_monte_carlo(nu, z):
    rng = np.random.default_rng(12345)
    mu, s, best = 1.3, 0.7, 1.3 + 0.7 * z
    pred = Predictive.from_scale(np.array([mu]), s, nu)
    n = 2_000_000
    draws = mu + s * (rng.standard_normal(n) if math.isinf(nu) else rng.standard_t(nu, n))
    mc = np.maximum(best - draws, 0.0).mean()
    got = expected_improvement(pred, best)[0]
    assert abs(got - mc) <= 0.01 * got, (got, mc)
    # PI too (absolute 1 % of probability: MC standard error is ~3.5e-4 here)
    assert abs(probability_of_improvement(pred, best)[0] - np.mean(draws < best)) < 0.01


@pytest.mark.parametrize("nu", [3.0, 16.0, 115.0])
def test_pi_is_t_cdf_of_scaled_z(nu):
    pred = Predictive(np.array([0.2, -1.0, 3.0]), np.array([0.5, 2.0, 0.1]), nu)
    s = np.sqrt(pred.variance * (nu - 2) / nu)
    ref = stats.t.cdf(0.1, nu, loc=pred.mean, scale=s)
    np.testing.assert_allclose(probability_of_improvement(pred, 0.1), ref, rtol=1e-12)


def test_t_ei_tends_to_gaussian_ei():
    # The t-EI converges to the Gaussian EI at rate O(1/ν) (slower far in the tail).
    z = np.linspace(-6, 3, 19)
    g = expected_improvement(t_pred(z, math.inf), 0.0)
    err = {
        nu: np.max(np.abs(expected_improvement(t_pred(z, nu), 0.0) / g - 1))
        for nu in (1e4, 1e6, 1e8)
    }
    assert err[1e6] < err[1e4] / 50 and err[1e8] < err[1e6] / 50
    assert err[1e8] < 1e-5


@settings(max_examples=60, deadline=None)
@given(
    z=st.floats(-40.0, 40.0),
    nu=st.one_of(st.just(math.inf), st.floats(1.2, 1e4)),
    scale=st.floats(1e-3, 1e3),
)
def test_ei_put_call_parity_and_jensen_bound(z, nu, scale):
    # For a symmetric predictive, E[max(b − Y, 0)] − E[max(Y − b, 0)] = b − μ, and the second
    # term is the EI of the mirrored problem: s·h(z) − s·h(−z) = s·z. Exercises the tail
    # branch on one side and the direct formula on the other. Jensen: EI >= max(b − μ, 0).
    ei = expected_improvement(t_pred(np.array([z, -z]), nu, scale), 0.0)
    assert ei[0] - ei[1] == pytest.approx(scale * z, rel=1e-9, abs=1e-12 * scale)
    assert ei[0] >= max(scale * z, 0.0) * (1 - 1e-12)
    assert np.isfinite(log_expected_improvement(t_pred(np.array([z]), nu, scale), 0.0)[0])


# ---------------------------------------------------------------- log-EI
def _ref_log_h(z: float, nu: float) -> float:
    """log E[max(z − T, 0)] for z < 0 by quadrature, rescaled so nothing underflows:
    h(z) = w² ∫_1^∞ (v − 1) p(wv) dv with w = −z, and p(wv)/p(w) integrated."""
    w = -z
    logpdf = stats.norm.logpdf if math.isinf(nu) else (lambda u: stats.t.logpdf(u, nu))
    lw = logpdf(w)
    integral, _ = integrate.quad(
        lambda v: (v - 1) * np.exp(logpdf(w * v) - lw), 1, np.inf, epsabs=0, epsrel=1e-12
    )
    return 2 * math.log(w) + lw + math.log(integral)


@pytest.mark.parametrize("nu", [math.inf, 3.0, 17.0, 116.0, 1000.0])
def test_log_ei_matches_quadrature_deep_in_the_tail(nu):
    zs = np.array([-2.5, -5.0, -20.0, -60.0, -300.0] if not math.isinf(nu) else [-2.5, -5, -20])
    got = log_expected_improvement(t_pred(zs, nu, scale=0.3), 0.0) - math.log(0.3)
    ref = np.array([_ref_log_h(z, nu) for z in zs])
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    assert np.all(np.isfinite(got))


def test_gaussian_log_ei_far_tail_matches_asymptotic_series():
    # h(z) = φ(z)/z² (1 − 3/z² + 15/z⁴ − 105/z⁶ + …) (A&S 7.1.23 integrated twice).
    z = np.array([-50.0, -1e3, -1e6, -1e9])
    series = 1 - 3 / z**2 + 15 / z**4 - 105 / z**6
    ref = -0.5 * z**2 - 0.5 * math.log(2 * math.pi) - 2 * np.log(-z) + np.log(series)
    got = log_expected_improvement(t_pred(z, math.inf), 0.0)
    np.testing.assert_allclose(got, ref, rtol=1e-13)
    # plain EI underflows there; log-EI does not
    assert expected_improvement(t_pred(z, math.inf), 0.0)[0] == 0.0


@pytest.mark.parametrize("nu", [math.inf, 2.5, 15.0, 55.0, 1e4])
def test_log_ei_equals_log_of_ei_where_ei_is_representable(nu):
    z = np.concatenate([np.linspace(-12, 5, 69), [-2 - 1e-9, -2 + 1e-9]])
    pred = t_pred(z, nu, scale=2.0)
    np.testing.assert_allclose(
        log_expected_improvement(pred, 0.0), np.log(expected_improvement(pred, 0.0)), rtol=1e-12
    )
    # and EI is continuous and increasing in z across the branch switch at z = −2
    ei = expected_improvement(pred, 0.0)
    order = np.argsort(z)
    assert np.all(np.diff(ei[order]) > 0)


def test_log_ei_independent_check_against_direct_formula_for_moderate_z():
    # Where no cancellation happens the textbook formula is accurate: compare the tail
    # machinery with it through scipy's t distribution.
    nu, z = 7.0, np.array([-2.1, -3.0, -4.5])
    direct = z * stats.t.cdf(z, nu) + (nu + z**2) / (nu - 1) * stats.t.pdf(z, nu)
    got = np.exp(log_expected_improvement(t_pred(z, nu), 0.0))
    np.testing.assert_allclose(got, direct, rtol=1e-12)


# ---------------------------------------------------------------- confidence bounds
def test_confidence_bound_is_paper_eq9_with_std():
    pred = Predictive(np.array([1.0, 2.0]), np.array([4.0, 0.25]), 20.0)
    cbm = confidence_bound(pred, best=1.5, beta=0.01)
    np.testing.assert_allclose(cbm, [0.1 * 2.0 + 0.5, 0.1 * 0.5 - 0.5], rtol=1e-15)
    lcb = lower_confidence_bound(pred, beta=0.04)
    np.testing.assert_allclose(lcb, [1.0 - 0.2 * 2.0, 2.0 - 0.2 * 0.5], rtol=1e-15)
    np.testing.assert_allclose(
        confidence_bound(pred, 1.5, beta=0.04), 1.5 - lower_confidence_bound(pred, 0.04)
    )


# ---------------------------------------------------------------- edge cases and errors
def test_zero_variance_candidates():
    pred = Predictive(np.array([0.0, 2.0, 1.0]), np.array([0.0, 0.0, 0.0]), 30.0)
    np.testing.assert_array_equal(expected_improvement(pred, 1.0), [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(probability_of_improvement(pred, 1.0), [1.0, 0.0, 0.0])
    log_ei = log_expected_improvement(pred, 1.0)
    assert log_ei[0] == 0.0 and np.all(np.isneginf(log_ei[1:]))


def test_vectorised_shapes():
    rng = np.random.default_rng(0)
    pred = Predictive(rng.standard_normal(1000), rng.random(1000) + 0.01, 45.0)
    for f in (expected_improvement, log_expected_improvement, probability_of_improvement):
        out = f(pred, 0.1)
        assert out.shape == (1000,) and np.all(np.isfinite(out))
    assert confidence_bound(pred, 0.1).shape == (1000,)


def test_bad_arguments_raise_clear_errors():
    pred = Predictive(np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="best"):
        expected_improvement(pred, float("nan"))
    with pytest.raises(ValueError, match="beta"):
        confidence_bound(pred, 0.0, beta=-1.0)
    cauchy = Predictive.from_scale(np.zeros(2), 1.0, 1.0)
    with pytest.raises(ValueError, match="dof > 1"):
        expected_improvement(cauchy, 0.0)
    with pytest.raises(ValueError, match="dof"):
        Predictive(np.zeros(2), np.ones(2), 0.0)
    with pytest.raises(ValueError, match="from_scale"):
        _ = Predictive(np.zeros(2), np.ones(2), 2.0).scale
