"""Cost (paper Eq. 14–15), NIS cost and KPIs on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kftune.errors import ConfigError
from kftune.tuning.cost import (
    CostSpec,
    dataset_error,
    nis_cost,
    nrmse,
    pooled_error,
    weighted_cost,
)
from kftune.tuning.kpi import average_kpis, sideslip_kpis


def test_nrmse_by_hand():
    # errors (-1, 2, -1, 2): MSE = 10/4 = 2.5, RMSE = 1.58114; max|ref| = 2.
    assert nrmse(np.zeros(4), np.array([1.0, -2.0, 1.0, -2.0])) == pytest.approx(
        math.sqrt(2.5) / 2, rel=1e-15
    )


def test_nrmse_zero_reference_is_refused():
    with pytest.raises(ValueError, match="identically zero"):
        nrmse(np.ones(3), np.zeros(3))


def test_pooled_error_weights_by_sample_count():
    # sqrt((0.1²·100 + 0.2²·300) / 400) = sqrt(13/400)
    assert pooled_error([0.1, 0.2], [100, 300]) == pytest.approx(math.sqrt(13 / 400), rel=1e-15)
    # one manoeuvre: pooling is the identity
    assert pooled_error([0.37], [17]) == pytest.approx(0.37, rel=1e-15)


def test_weighted_cost_paper_weights():
    nr = {"beta": [0.1, 0.2], "r": [0.05, 0.05], "ay": [0.3, 0.1]}
    n = [100, 300]
    j, pooled = weighted_cost(nr, n, CostSpec().weights)
    e_beta = math.sqrt((0.01 * 100 + 0.04 * 300) / 400)
    e_r = 0.05
    e_ay = math.sqrt((0.09 * 100 + 0.01 * 300) / 400)
    assert pooled == pytest.approx({"beta": e_beta, "r": e_r, "ay": e_ay}, rel=1e-14)
    assert j == pytest.approx(5 * e_beta + e_r + e_ay, rel=1e-14)


def test_weighted_cost_ignores_zero_weights_and_needs_weighted_channels():
    j, pooled = weighted_cost({"beta": [0.2]}, [10], {"beta": 2.0, "ay": 0.0})
    assert j == pytest.approx(0.4) and set(pooled) == {"beta"}
    with pytest.raises(ValueError, match="'ay'"):
        weighted_cost({"beta": [0.2]}, [10], {"beta": 1.0, "ay": 1.0})


def test_dataset_error_is_the_rmse_over_all_samples_over_the_largest_reference():
    rng = np.random.default_rng(3)
    refs = [rng.normal(0, 0.02, 50), rng.normal(0, 0.08, 200), rng.normal(0, 0.01, 30)]
    ests = [r + rng.normal(0, 0.004, r.size) for r in refs]
    # reference: every sample of every manoeuvre at once, written out with numpy
    err = np.concatenate([e - r for e, r in zip(ests, refs)])
    expected = np.sqrt(np.mean(err**2)) / np.max(np.abs(np.concatenate(refs)))
    per = [nrmse(e, r) for e, r in zip(ests, refs)]
    scales = [np.max(np.abs(r)) for r in refs]
    n = [r.size for r in refs]
    assert dataset_error(per, scales, n) == pytest.approx(expected, rel=1e-13)
    # the paper's pooling weighs the quiet manoeuvres up: here it is the larger number
    assert pooled_error(per, n) > 1.5 * expected
    j, pooled = weighted_cost({"beta": per}, n, {"beta": 5.0}, {"beta": scales})
    assert pooled["beta"] == pytest.approx(expected, rel=1e-13) and j == pytest.approx(5 * expected)
    with pytest.raises(ValueError, match="positive scale"):
        dataset_error(per, [1.0, 0.0, 1.0], n)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "mse"}, "cost kind"),
        ({"normalise": "channel"}, "cost normalise"),
        ({"kind": "pem", "normalise": "dataset"}, "nrmse cost only"),
        ({"weights": {"yaw rate": 1.0}}, "must be identifiers"),
        ({"weights": {"beta": -1.0}}, "'beta'"),
        ({"weights": {"beta": math.nan}}, "'beta'"),
        ({"weights": {"beta": 0.0}}, "at least one"),
    ],
)
def test_cost_spec_validation(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        CostSpec(**kwargs)


def test_cost_spec_channels_in_canonical_order():
    assert CostSpec(weights={"ay": 1, "beta": 5, "vx": 0}).channels == ("beta", "ay")


def test_nis_cost():
    assert nis_cost([np.full(10, 3.0)], n_z=3) == pytest.approx(0.0, abs=1e-15)
    # mean NIS 6 over two manoeuvres of unequal length: |log(6/3)|
    assert nis_cost([np.full(5, 6.0), np.full(20, 6.0)], n_z=3) == pytest.approx(math.log(2))
    # over-confident and under-confident by the same factor cost the same
    assert nis_cost([np.full(4, 1.5)], 3) == pytest.approx(nis_cost([np.full(4, 6.0)], 3))
    assert nis_cost([np.array([np.nan])], 3) == math.inf


def test_sideslip_kpis_by_hand():
    beta_est = np.radians([1.0, -2.0, 0.5, 3.0])
    ay = np.array([0.0, 5.0, -4.0, 3.0])  # samples 2 and 3 are nonlinear (|ay| >= 4)
    k = sideslip_kpis(beta_est, np.zeros(4), ay)
    assert k["rmse"] == pytest.approx(math.sqrt((1 + 4 + 0.25 + 9) / 4), rel=1e-12)
    assert k["mae"] == pytest.approx(3.0, rel=1e-12)
    assert k["rmse_non"] == pytest.approx(math.sqrt((4 + 0.25) / 2), rel=1e-12)
    assert k["mae_non"] == pytest.approx(2.0, rel=1e-12)
    assert k["n_non"] == 2


def test_kpis_without_nonlinear_samples_and_averaging():
    k1 = sideslip_kpis(np.radians([1.0, 1.0]), np.zeros(2), np.array([1.0, 2.0]))
    assert math.isnan(k1["rmse_non"]) and math.isnan(k1["mae_non"])
    k2 = sideslip_kpis(np.radians([3.0, 1.0]), np.zeros(2), np.array([5.0, 1.0]))
    avg = average_kpis([k1, k2])
    assert avg["rmse"] == pytest.approx((1.0 + math.sqrt(5.0)) / 2)
    assert avg["mae"] == pytest.approx(2.0)
    # NON averaged only over the manoeuvre that has nonlinear samples
    assert avg["rmse_non"] == pytest.approx(3.0) and avg["mae_non"] == pytest.approx(3.0)


def test_kpis_shape_errors():
    with pytest.raises(ValueError, match="equal length"):
        sideslip_kpis(np.zeros(3), np.zeros(4), np.zeros(3))


def test_averages_are_nan_when_any_manoeuvre_diverged():
    ok = sideslip_kpis(np.radians([1.0, 1.0]), np.zeros(2), np.array([5.0, 5.0]))
    diverged = {
        "rmse": math.nan,
        "mae": math.nan,
        "rmse_non": math.nan,
        "mae_non": math.nan,
        "diverged": 1.0,
    }
    avg = average_kpis([ok, diverged])
    assert all(math.isnan(avg[k]) for k in ("rmse", "mae", "rmse_non", "mae_non"))
    assert avg["n_diverged"] == 1 and avg["n_manoeuvres"] == 2
    assert average_kpis([ok])["n_diverged"] == 0


def test_cost_spec_estimate_must_be_known():
    with pytest.raises(ConfigError, match="estimate"):
        CostSpec(estimate="smoothed")


def test_the_report_says_how_the_cost_is_normalised():
    from kftune.experiment import _describe_cost

    assert "paper Eq. 14–15" in _describe_cost(CostSpec())
    assert "over all manoeuvres / the largest |X|" in _describe_cost(CostSpec(normalise="dataset"))


@pytest.mark.parametrize(("kind", "weights", "refused"), [
    ("pem", "{ r = 1.0 }", True),
    ("nis", "{ r = 1.0 }", True),
    ("crps", "{ beta = 1.0 }", False),
    ("nlpd", "{ beta = 1.0 }", False),
])  # fmt: skip
def test_weights_in_a_configuration_are_refused_only_for_the_costs_that_weigh_none(
    small, tmp_path, kind, weights, refused
):
    """[cost] weights with nis or pem: refused naming the file, the section and the costs
    that do take weights (nrmse, nlpd, crps and msp); with a scoring rule: accepted."""
    from conftest import run_cli

    config = tmp_path / "c.toml"
    config.write_text(f'[cost]\nkind = "{kind}"\nweights = {weights}\n')
    res = run_cli("evaluate", str(small), "--manual", "--config", str(config), "--json")
    if refused:
        assert res.returncode == 3, res.stderr
        assert f"the {kind} cost" in res.stderr and "weighs no channels" in res.stderr
        assert "weights apply to the nrmse, nlpd, crps and msp costs" in res.stderr
        assert "[cost] key 'weights'" in res.stderr
        assert str(config) in res.stderr and "Traceback" not in res.stderr
    else:
        assert res.returncode == 0, res.stderr
