"""The scoring-rule costs (``--cost nlpd``, ``--cost crps``) against independent references:
scipy's Gaussian log-density, CRPS's integral definition (numerical quadrature, as
``properscoring.crps_quadrature`` computes it) and a Monte Carlo estimate of
E|X − y| − ½E|X − X'|; their propriety (the expected score over y ~ N(0, 1) is lowest for
the forecast N(0, 1)); and the tuning problem's cost against a hand computation from a
filter run's columns, in the serial and the batch kernel."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import integrate, stats

from conftest import run_cli
from kftune.data import default_dataset
from kftune.errors import ConfigError
from kftune.tuning.cost import CostSpec, gaussian_crps, gaussian_nlpd, scoring_rule_cost
from kftune.tuning.problem import TuningProblem
from kftune.tuning.runs import first_scored

#: Two short training manoeuvres of the bundled set and a few points around the manual
#: rule of thumb (Q diag [Vx, Vy, r] in SI²): σ far too small, about right, too large.
MANOEUVRES = ("train-03-j-turn", "train-07-lane-change")
POINTS = np.array([[1e-6, 1e-4, 1e-6], [1e-8, 1e-6, 1e-8], [1e-4, 1e-2, 1e-4], [3e-7, 5e-3, 1e-5]])


@pytest.fixture(scope="module")
def data():
    ds = default_dataset()
    return ds, [ds[name] for name in MANOEUVRES]


# ------------------------------------------------------------------ the scores themselves
def test_nlpd_is_scipys_negative_gaussian_log_density():
    rng = np.random.default_rng(1)
    est, ref = rng.normal(size=50), rng.normal(size=50)
    std = rng.uniform(0.01, 3.0, size=50)
    want = -stats.norm.logpdf(ref, loc=est, scale=std)
    np.testing.assert_allclose(gaussian_nlpd(ref - est, std), want, rtol=1e-12)
    np.testing.assert_allclose(gaussian_nlpd(est - ref, std), want, rtol=1e-12)  # even


@pytest.mark.parametrize(("err", "std"), [(0.0, 1.0), (0.3, 1.0), (-2.5, 0.7), (4.0, 0.5)])
def test_crps_equals_its_integral_definition(err, std):
    """CRPS(F, y) = ∫ (F(x) − 1{x ≥ y})² dx, F the forecast's CDF (Gneiting & Raftery
    2007, Eq. 20), integrated numerically on each side of y."""
    y = err  # forecast N(0, σ²), reference y: error y − 0 = err
    lo, hi = min(y, 0.0) - 12 * std, max(y, 0.0) + 12 * std
    below = integrate.quad(lambda x: stats.norm.cdf(x, scale=std) ** 2, lo, y, epsabs=1e-12)[0]
    above = integrate.quad(lambda x: stats.norm.sf(x, scale=std) ** 2, y, hi, epsabs=1e-12)[0]
    got = gaussian_crps(np.array([err]), np.array([std]))[0]
    assert got == pytest.approx(below + above, rel=1e-7, abs=1e-10)


def test_crps_equals_a_monte_carlo_estimate():
    """E|X − y| − ½E|X − X'| with X, X' ~ N(0, σ²) from 400 000 draws: the standard error
    of the estimate is below 0.002·σ, so 0.01·σ (five standard errors) is the tolerance."""
    rng = np.random.default_rng(7)
    n = 400_000
    for err, std in [(0.0, 1.0), (0.8, 0.5), (-3.0, 2.0)]:
        x, x2 = rng.normal(0.0, std, n), rng.normal(0.0, std, n)
        mc = np.mean(np.abs(x - err)) - 0.5 * np.mean(np.abs(x - x2))
        got = gaussian_crps(np.array([err]), np.array([std]))[0]
        assert got == pytest.approx(mc, abs=0.01 * std)


def test_crps_of_a_sharp_forecast_is_the_absolute_error():
    assert gaussian_crps(np.array([0.4]), np.array([1e-9]))[0] == pytest.approx(0.4, rel=1e-6)


@pytest.mark.parametrize("rule", [gaussian_nlpd, gaussian_crps])
def test_the_scores_are_proper(rule):
    """The expected score over y ~ N(0, 1) (Gauss–Hermite quadrature, exact for these
    smooth integrands to far below the differences checked) of a forecast N(μ, σ²) is
    lowest at μ = 0, σ = 1 on a grid around it: too narrow, too wide or biased is worse."""
    y, w = np.polynomial.hermite_e.hermegauss(80)
    w = w / w.sum()

    def expected(mu: float, sigma: float) -> float:
        return float(np.sum(w * rule(y - mu, np.full_like(y, sigma))))

    sigmas = np.array([0.25, 0.5, 0.8, 0.9, 1.0, 1.1, 1.25, 2.0, 4.0])
    scores = [expected(0.0, s) for s in sigmas]
    assert sigmas[int(np.argmin(scores))] == 1.0
    assert all(s > scores[4] + 1e-4 for i, s in enumerate(scores) if i != 4)
    assert expected(0.2, 1.0) > expected(0.0, 1.0) + 1e-3
    if rule is gaussian_nlpd:  # closed form: E = ½log(2πσ²) + (1 + μ²)/(2σ²)
        assert expected(0.3, 0.8) == pytest.approx(
            0.5 * math.log(2 * math.pi * 0.64) + 1.09 / 1.28, rel=1e-10
        )


def test_scoring_rule_cost_pools_by_samples_and_weighs_channels():
    sums = {"beta": [2.0, 6.0], "vy": [1.0, 3.0]}
    cost, pooled = scoring_rule_cost(sums, [10, 30], {"beta": 2.0, "vy": 0.5})
    assert pooled == pytest.approx({"beta": 0.2, "vy": 0.1})
    assert cost == pytest.approx(2.0 * 0.2 + 0.5 * 0.1)
    scaled, _ = scoring_rule_cost(sums, [10, 30], {"beta": 1.0}, {"beta": [0.05, 0.1]})
    assert scaled == pytest.approx(0.2 / 0.1)  # divided by the largest |X| of the set
    assert scoring_rule_cost({"beta": [math.inf, 1.0]}, [1, 1], {"beta": 1.0})[0] == math.inf


# ------------------------------------------------------------------ in the tuning problem
def beta_and_std_by_hand(res) -> tuple[np.ndarray, np.ndarray]:
    """β = atan2(Vy, Vx) and its delta-method σ written out from the run's columns."""
    vx, vy = res.x[:, 0], res.x[:, 1]
    pvx, pvy = res.P_diag[:, 0], res.P_diag[:, 1]
    d = vx * vx + vy * vy
    return np.arctan2(vy, vx), np.sqrt((vy / d) ** 2 * pvx + (vx / d) ** 2 * pvy)


@pytest.mark.parametrize("kind", ["nlpd", "crps"])
def test_the_problems_cost_equals_a_hand_computation_from_the_runs(data, kind):
    ds, ms = data
    burn_in = 0.5
    problem = TuningProblem(ms, ds.vehicle, ds.r_default, cost=CostSpec(kind=kind), burn_in=0.5)
    assert problem.cost_spec.weights == {"beta": 1.0}  # β alone by default
    x = POINTS[3]
    total, n, biggest = 0.0, 0, 0.0
    for m in ms:
        res = problem.run(x, m)
        k0 = first_scored(m, burn_in)
        beta, std = beta_and_std_by_hand(res)
        ref = m.beta_ref[k0:]
        if kind == "nlpd":
            total += float(np.sum(-stats.norm.logpdf(ref, loc=beta[k0:], scale=std[k0:])))
        else:
            z = (ref - beta[k0:]) / std[k0:]
            total += float(
                np.sum(
                    std[k0:]
                    * (
                        z * (2 * stats.norm.cdf(z) - 1)
                        + 2 * stats.norm.pdf(z)
                        - 1 / math.sqrt(math.pi)
                    )
                )
            )
        n += m.n - k0
        biggest = max(biggest, float(np.max(np.abs(ref))))
    want = total / n if kind == "nlpd" else total / n / biggest
    assert problem(x) == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("kind", ["nlpd", "crps"])
def test_the_batch_kernel_gives_the_serial_cost_exactly(data, kind):
    ds, ms = data
    problem = TuningProblem(ms, ds.vehicle, ds.r_default, cost=CostSpec(kind=kind))
    serial = [problem.evaluate(x) for x in POINTS]
    batch = problem.evaluate_batch(POINTS)
    for a, b in zip(serial, batch):
        assert b.cost == a.cost and b.pooled == a.pooled
        assert [s.score_sum for s in b.scores] == [s.score_sum for s in a.scores]


def test_the_nlpd_prefers_the_filter_whose_sigma_is_nearer_its_errors(data):
    """Of two filters, the NRMSE prefers the more accurate one whose β σ is far too small
    (mean NEES over 100), the NLPD the one whose σ is nearer its errors (NEES about 10
    times smaller), at a larger error."""
    ds, ms = data
    sharp, wide = np.array([1e-6, 1e-6, 1e-6]), np.array([1e-4, 1e-2, 1e-4])
    nrmse = TuningProblem(ms, ds.vehicle, ds.r_default)
    nlpd = TuningProblem(ms, ds.vehicle, ds.r_default, cost=CostSpec(kind="nlpd"))
    nees = []
    for x in (sharp, wide):
        err2, var = [], []
        for m in ms:
            beta, std = beta_and_std_by_hand(nlpd.run(x, m))
            err2.append((beta - m.beta_ref) ** 2)
            var.append(std**2)
        nees.append(float(np.mean(np.concatenate(err2) / np.concatenate(var))))
    assert nees[0] > 100 and nees[0] > 5 * nees[1]
    assert nrmse(sharp) < nrmse(wide)
    assert nlpd(wide) < nlpd(sharp)


def test_a_scoring_rule_refuses_a_measured_channel_and_needs_the_reference(data):
    ds, ms = data
    with pytest.raises(ConfigError, match=r"'r' \(a measurement.*pem cost"):
        TuningProblem(
            ms, ds.vehicle, ds.r_default, cost=CostSpec(kind="nlpd", weights={"beta": 1, "r": 1})
        )
    with pytest.raises(ConfigError, match=r"'yaw' \(not an output"):
        TuningProblem(ms, ds.vehicle, ds.r_default, cost=CostSpec(kind="crps", weights={"yaw": 1}))
    assert CostSpec(kind="nlpd", weights={"beta": 5.0, "vy": 1.0}).weights == {
        "beta": 5.0,
        "vy": 1.0,
    }
    with pytest.raises(ConfigError, match="normalise applies to the nrmse cost only"):
        CostSpec(kind="crps", normalise="dataset")


def test_tune_and_evaluate_take_the_scoring_rules(small, tmp_path):
    out = tmp_path / "tuned.json"
    res = run_cli("tune", str(small), "--cost", "nlpd", "-n", "4", "--json", "-o", str(out))
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert doc["cost_spec"]["kind"] == "nlpd" and doc["cost_spec"]["weights"] == {"beta": 1.0}
    ev = run_cli("evaluate", str(small), "--params", str(out), "--split", "train", "--json")
    assert ev.returncode == 0, ev.stderr
    evd = json.loads(ev.stdout)  # the calibrated filter's NLPD: another number than tune's
    assert evd["cost_kind"] == "nlpd" and math.isfinite(evd["cost"])
    bad = run_cli("tune", str(small), "--cost", "crps", "--weights", "beta=1,ay=1", "-n", "4")
    assert bad.returncode == 2 and "--weights" in bad.stderr and "'ay'" in bad.stderr
    assert "Traceback" not in bad.stderr
