"""Calibration of a filter's σ by one covariance scale c (c·Q, c·R, c·P0).

References independent of kftune's calibration: a linear-Gaussian model simulated with known
Q and R (the filter with the true noise is consistent, its mean NEES inside the χ² band of
Bar-Shalom et al. 2001 §5.4), FilterPy's Kalman filter run with the scaled covariances (the
estimate of the Kalman filter does not depend on a common scale of Q, R and P0), hand counts.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from conftest import run_cli
from kftune.filters import EKF
from kftune.models.linear import linear_model
from kftune.tuning.calibrate import (
    CRITERIA,
    RELIABILITY_LEVELS,
    SPREAD_LIMIT,
    TOLERANCE,
    RunErrors,
    bias_share,
    fit_scale,
    required_factor,
)
from kftune.tuning.consistency import channel_consistency, pool
from kftune.tuning.cost import CostSpec

F = np.array([[1.0, 0.1], [0.0, 0.95]])
H = np.array([[1.0, 0.0]])
Q = np.array([1e-4, 1e-2])
R = np.array([0.05])
P0 = np.array([1.0, 1.0])


def simulate(seed: int, n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """(x (n, 2), z (n, 1)) of x_k = F·x_{k−1} + w, z_k = H·x_k + v, w ~ N(0, diag Q),
    v ~ N(0, R), x_0 ~ N(0, diag P0)."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 2))
    x[0] = rng.normal(0.0, np.sqrt(P0))
    for k in range(1, n):
        x[k] = F @ x[k - 1] + rng.normal(0.0, np.sqrt(Q))
    return x, x @ H.T + rng.normal(0.0, np.sqrt(R), (n, 1))


RUNS = [simulate(seed) for seed in range(4)]
MODEL = linear_model(F, H)  # one model object: each new one compiles the filter again


def linear_runs(scale: float):
    """c → kftune's Kalman filter (EKF of the linear model) with c·scale·(Q, R, P0) over
    the simulated runs, both states referenced."""

    def run(c: float) -> list[RunErrors]:
        out = []
        for i, (x, z) in enumerate(RUNS):
            s = c * scale
            res = EKF().run(MODEL, None, z, 1.0, Q * s, R * s, x0=[0, 0], P0=P0 * s)
            names = ("x0", "x1")
            out.append(
                RunErrors(
                    name=f"run{i}",
                    err={c: res.x[:, j] - x[:, j] for j, c in enumerate(names)},
                    std={c: np.sqrt(res.P_diag[:, j]) for j, c in enumerate(names)},
                    estimate={c: res.x[:, j] for j, c in enumerate(names)},
                    nis=res.nis,
                    m=1,
                )
            )
        return out

    return run


def pooled(runs: list[RunErrors]):
    """Both states' consistency pooled over the runs (NEES with its effective band)."""
    return pool(
        channel_consistency(r.err[c], r.std[c], np.zeros_like(r.err[c]))
        for r in runs
        for c in r.err
    )


@pytest.mark.slow
def test_the_filter_with_the_true_noise_is_left_unchanged():
    """The true Q, R and P0: the fitted c lies within the χ² band of the mean NEES around 1
    (c is the mean NEES at c = 1 for a linear filter), so calibrating changes nothing that
    the data could tell; NEES and coverage stay in their bounds."""
    run = linear_runs(1.0)
    nees = pooled(run(1.0)).nees
    lo, hi = nees.band_eff
    assert lo <= nees.mean <= hi  # the reference: a consistent filter
    cal = fit_scale(run, "nees")
    assert lo <= cal.factor <= hi, (cal.factor, (lo, hi))
    assert cal.factor == pytest.approx(nees.mean, rel=TOLERANCE)
    after = pooled(run(cal.factor))
    assert after.nees.mean == pytest.approx(1.0, abs=TOLERANCE)
    for share, p in zip(after.coverage, (0.6827, 0.95)):
        assert abs(share - p) < 4 * math.sqrt(p * (1 - p) / after.nees.n_eff)
    assert cal.warning is None


@pytest.mark.parametrize("criterion", CRITERIA)
def test_q_and_r_ten_times_too_large_are_detected_and_recalibrated(criterion):
    """Q, R and P0 × 10: the NEES far below its band before; c ≈ 0.1 (exactly the true
    filter's required factor / 10, P scaling exactly with c); after it the NEES (or the 95 %
    coverage) is at its target, the ±1σ and ±1.96σ coverages within 3 points of nominal
    for every criterion (the errors are Gaussian), and the estimate has not moved."""
    true_rho = required_factor(linear_runs(1.0)(1.0), criterion)
    cal = fit_scale(linear_runs(10.0), criterion)
    assert cal.before.nees.mean < cal.before.nees.band_eff[0]
    assert cal.before.coverage[1] > 0.999
    assert cal.factor == pytest.approx(true_rho / 10, rel=1e-6)
    assert 0.08 < cal.factor < 0.12
    assert cal.n_runs == 2  # one fixed-point step is exact for a linear filter
    after = pooled(linear_runs(10.0)(cal.factor))  # both states, as fitted
    if criterion == "nees":
        lo, hi = after.nees.band_eff
        assert lo <= after.nees.mean <= hi
    elif criterion == "coverage95":
        assert after.coverage[1] == pytest.approx(0.95, abs=1e-3)
    assert after.coverage[0] == pytest.approx(0.6827, abs=0.03)
    assert after.coverage[1] == pytest.approx(0.95, abs=0.03)
    assert cal.shift_rms < 1e-9 * cal.rmse


def test_the_calibrated_filter_equals_filterpys_kalman_filter():
    """kftune's filter with c·10·(Q, R, P0) and FilterPy's KalmanFilter with the same
    covariances agree in estimate and covariance; the estimate equals the uncalibrated
    (×10) filter's, and the covariance is c times it."""
    cal = fit_scale(linear_runs(10.0), "nees")
    s = 10.0 * cal.factor
    z = RUNS[0][1]
    ours = EKF().run(MODEL, None, z, 1.0, Q * s, R * s, x0=[0, 0], P0=P0 * s)
    raw = EKF().run(MODEL, None, z, 1.0, Q * 10, R * 10, x0=[0, 0], P0=P0 * 10)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.H = np.zeros(2), np.diag(P0 * s), F, H
    kf.Q, kf.R = np.diag(Q * s), np.diag(R * s)
    est, var = [], []
    for k in range(len(z)):
        if k:
            kf.predict()
        kf.update(z[k])
        est.append(kf.x.copy())
        var.append(np.diag(kf.P).copy())
    np.testing.assert_allclose(ours.x, np.array(est), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ours.P_diag, np.array(var), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(ours.x, raw.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ours.P_diag, cal.factor * raw.P_diag, rtol=1e-9)


def test_without_a_reference_it_fits_the_nis_to_m():
    """No channel with a reference: c makes the mean NIS equal m (S scales by c)."""
    full = linear_runs(10.0)

    def run(c: float) -> list[RunErrors]:
        return [RunErrors(r.name, {}, {}, {}, r.nis, r.m) for r in full(c)]

    cal = fit_scale(run, "nees")
    assert cal.criterion == "nis" and cal.channels == ()
    assert cal.nis_after == pytest.approx(1.0, abs=1e-3)
    assert cal.nis_before == pytest.approx(cal.factor, rel=1e-6)  # ρ(1) = NIS/m at c = 1
    assert 0.05 < cal.factor < 0.2


# ------------------------------------------------------------------------- hand counts
def one(name: str, e: list[float], s: float = 1.0) -> RunErrors:
    arr = np.asarray(e, dtype=float)
    return RunErrors(name, {"a": arr}, {"a": np.full(arr.size, s)}, {"a": arr})


def test_required_factor_and_bias_share_equal_hand_counts():
    """Errors 2, 0 (σ = 1): mean NEES (4 + 0)/2 = 2; bias share 2·1²/4 = 0.5. Alternating
    ±1: no bias; constant 1: all bias. The 95 % criterion: the 95th percentile of |e|/σ
    over 0…19 (numpy's linear interpolation: 18.05) over 1.96, squared."""
    assert required_factor([one("m", [2.0, 0.0])], "nees") == pytest.approx(2.0)
    assert bias_share(one("m", [2.0, 0.0])) == pytest.approx(0.5)
    assert bias_share(one("m", [1.0, -1.0, 1.0, -1.0])) == pytest.approx(0.0)
    assert bias_share(one("m", [1.0, 1.0, 1.0])) == pytest.approx(1.0)
    got = required_factor([one("m", list(range(20)))], "coverage95")
    assert got == pytest.approx((18.05 / 1.959963984540054) ** 2)
    # a σ of 0 and a NaN error are not counted
    r = RunErrors("m", {"a": np.array([2.0, np.nan, 5.0])}, {"a": np.array([1.0, 1.0, 0.0])}, {})
    assert required_factor([r], "nees") == pytest.approx(4.0)


def test_a_manoeuvre_dominated_by_bias_is_named():
    """Nine manoeuvres of unit white errors and one with an offset of 3σ (own factor 10,
    bias share 9/10; the common one about 1.9): the common factor cannot serve it; the
    warning names it as dominated by bias and says what the user sees, and none is named
    when all are alike."""
    rng = np.random.default_rng(0)
    errs = {f"m{i}": rng.normal(0.0, 1.0, 2000) for i in range(9)}
    errs["offset"] = rng.normal(0.0, 1.0, 2000) + 3.0

    def runs(errors: dict[str, np.ndarray]):
        def run(c: float) -> list[RunErrors]:
            return [
                RunErrors(n, {"a": e}, {"a": np.full(e.size, math.sqrt(c))}, {"a": e})
                for n, e in errors.items()
            ]

        return run

    cal = fit_scale(runs(errs), "nees")
    own = {f.name: f for f in cal.per_manoeuvre}
    assert own["offset"].bias_share == pytest.approx(9 / 10, abs=0.02)
    assert own["offset"].factor / cal.factor > SPREAD_LIMIT
    assert [f.name for f in cal.outliers] == ["offset"]
    assert cal.warning.startswith(
        "one scale cannot make every manoeuvre consistent: errors dominated by bias on 'offset'"
    )
    assert "What you see" in cal.warning
    assert cal.as_dict()["warning"] == cal.warning
    del errs["offset"]
    assert fit_scale(runs(errs), "nees").warning is None
    assert fit_scale(runs(errs)).warning is None


@pytest.mark.slow
def test_scaling_after_the_run_is_the_run_with_scaled_q_r_and_p0_of_a_linear_filter():
    """What kftune applies (covariances c times larger after the run, the estimate kept) is,
    for a Kalman filter, the run with c·Q, c·R and c·P0: kftune's EKF and UKF of the linear
    model and FilterPy's KalmanFilter run so give the same states, c·P and NIS/c."""
    from kftune.filters import UKF
    from kftune.tuning.runs import scaled_covariances

    c = 0.37
    z = RUNS[1][1][:500]
    for filt in (EKF(), UKF()):
        base = filt.run(MODEL, None, z, 1.0, Q, R, x0=[0, 0], P0=P0)
        rerun = filt.run(MODEL, None, z, 1.0, c * Q, c * R, x0=[0, 0], P0=c * P0)
        got = scaled_covariances(base, c)
        np.testing.assert_allclose(got.x, rerun.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got.P_diag, rerun.P_diag, rtol=1e-9)
        np.testing.assert_allclose(got.nis, rerun.nis, rtol=1e-9)
        np.testing.assert_allclose(got.log_det_s, rerun.log_det_s, rtol=1e-9, atol=1e-12)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.H = np.zeros(2), np.diag(c * P0), F, H
    kf.Q, kf.R = np.diag(c * Q), np.diag(c * R)
    var = []
    for k in range(len(z)):
        if k:
            kf.predict()
        kf.update(z[k])
        var.append(np.diag(kf.P).copy())
    np.testing.assert_allclose(got.P_diag, np.array(var), rtol=1e-9)


# --------------------------------------------------- criteria against independent references
def with_glitches(runs: list[RunErrors], share: float, size: float, seed: int) -> list[RunErrors]:
    """The runs with ``share`` of each channel's errors replaced by gross ones of ``size``·σ
    times a Student-t (3 dof) draw (a reference sensor's glitches, heavy-tailed)."""
    rng = np.random.default_rng(seed)
    out = []
    for r in runs:
        err = {}
        for c, e in r.err.items():
            e = e.copy()
            hit = rng.random(e.size) < share
            e[hit] = size * r.std[c][hit] * rng.standard_t(3, int(hit.sum()))
            err[c] = e
        out.append(RunErrors(r.name, err, r.std, r.estimate, r.nis, r.m))
    return out


def test_the_median_criterion_recovers_the_scale_through_heavy_tailed_glitches():
    """The linear filter with Q, R and P0 four times too small (its own errors Gaussian, the
    true factor c₀ = 4·ρ of the true filter) and 3 % of its errors replaced by Student-t
    glitches of 30σ: the median of the NEES still gives c₀ within 10 %, the mean NEES
    (the Gaussian likelihood's optimum) overshoots it more than tenfold, and the CRPS and
    the reliability curve land between them, far closer to c₀ than the mean NEES."""
    c0 = 4.0 * required_factor(linear_runs(1.0)(1.0), "nees")
    runs = linear_runs(0.25)
    got = {
        crit: fit_scale(lambda c: with_glitches(runs(c), 0.03, 30.0, 1), crit).factor
        for crit in ("median", "nees", "crps", "reliability")
    }
    miss = {k: abs(math.log(v / c0)) for k, v in got.items()}
    assert miss["median"] < math.log(1.1), got
    assert got["nees"] > 10 * c0, got
    assert miss["crps"] < miss["nees"] / 2 and miss["reliability"] < miss["nees"] / 4, got


def crps_gaussian(e: np.ndarray, s: np.ndarray) -> np.ndarray:
    """CRPS of N(0, s²) at e, the closed form of Gneiting & Raftery (2007) eq. 21."""
    from scipy.stats import norm

    w = e / s
    return s * (w * (2 * norm.cdf(w) - 1) + 2 * norm.pdf(w) - 1 / math.sqrt(math.pi))


def test_the_crps_criterion_minimises_the_mean_crps_as_scipy_finds_it():
    """Two channels of unequal σ (log-normal, two units) and Student-t errors: the factor of
    the ``crps`` criterion equals the minimum of Σ CRPS(N(0, c·σ²); e) that scipy's
    bounded scalar minimiser finds on log c (the closed form itself checked against its
    integral definition ∫ (F(x) − 1{x ≥ e})² dx on one sample)."""
    from scipy.integrate import quad
    from scipy.optimize import minimize_scalar
    from scipy.stats import norm

    def integral(e: float, s: float) -> float:
        lo = quad(lambda x: norm.cdf(x, scale=s) ** 2, -np.inf, e)[0]
        return lo + quad(lambda x: norm.sf(x, scale=s) ** 2, e, np.inf)[0]

    assert crps_gaussian(np.array([0.7]), np.array([0.3]))[0] == pytest.approx(
        integral(0.7, 0.3), rel=1e-7
    )
    rng = np.random.default_rng(3)
    runs = []
    for i in range(3):
        sa, sb = np.exp(rng.normal(0, 0.5, 700)), 0.01 * np.exp(rng.normal(0, 0.5, 700))
        ea, eb = 2.0 * sa * rng.standard_t(4, 700), 0.5 * sb * rng.standard_t(4, 700)
        runs.append(RunErrors(f"m{i}", {"a": ea, "b": eb}, {"a": sa, "b": sb}, {}))
    e = np.concatenate([r.err[c] for r in runs for c in ("a", "b")])
    s = np.concatenate([r.std[c] for r in runs for c in ("a", "b")])
    best = minimize_scalar(
        lambda lc: crps_gaussian(e, math.exp(0.5 * lc) * s).sum(),
        bounds=(math.log(1e-3), math.log(1e3)),
        method="bounded",
        options={"xatol": 1e-9},
    )
    assert required_factor(runs, "crps") == pytest.approx(math.exp(best.x), rel=1e-4)


@pytest.mark.parametrize("criterion", ["reliability", "minimax"])
def test_the_coverage_criteria_are_the_least_loss_of_a_brute_force_scan(criterion):
    """Student-t errors (σ = 1): the factor each coverage criterion gives has a loss (the
    mean absolute miss of the observed share inside ±z_p·√c over p = 0.50…0.99, or the
    worse of the 68.27 %/95 % misses over √(p(1 − p))) no larger than the least over
    4,001 log-spaced factors, each counted here by hand; on Gaussian errors of variance 9
    both give c = 9 within 5 %."""
    from scipy.stats import norm

    rng = np.random.default_rng(5)
    e = rng.standard_t(3, 2000)
    levels = np.array(RELIABILITY_LEVELS if criterion == "reliability" else (0.6826895, 0.95))
    z = norm.ppf(0.5 * (1 + levels))

    def loss(c: float) -> float:
        share = np.mean(np.abs(e)[None, :] <= z[:, None] * math.sqrt(c), axis=1)
        if criterion == "reliability":
            return float(np.mean(np.abs(share - levels)))
        return float(np.max(np.abs(share - levels) / np.sqrt(levels * (1 - levels))))

    got = required_factor([one("m", list(e))], criterion)
    scan = min(loss(c) for c in np.geomspace(0.2, 5.0, 4001))
    assert loss(got) <= scan + 1e-12
    g = 3.0 * rng.normal(0.0, 1.0, 20000)
    assert required_factor([one("m", list(g))], criterion) == pytest.approx(9.0, rel=0.05)


# ------------------------------------------------------------------ tune, evaluate, files
@pytest.fixture(scope="module")
def tuned(small, tmp_path_factory) -> Path:
    """A tuned file of the small dataset (3 evaluations), calibrated by tune."""
    out = tmp_path_factory.mktemp("cal") / "t.json"
    res = run_cli("tune", small, "-n", "3", "-o", out)
    assert res.returncode == 0, res.stderr
    assert "calibrated σ: covariances × " in res.stdout
    assert "the estimate is unchanged" in res.stdout
    return out


def test_tune_records_the_factor_and_evaluate_applies_it_without_moving_the_estimate(small, tuned):
    """The file's calibration (top level and deployment, the same factor); evaluate --params
    with it and --no-calibration: the same β RMSE to the last digit, the NEES c times
    smaller; the training NEES of the record is 1 after calibration."""
    doc = json.loads(tuned.read_text())
    cal, dep = doc["calibration"], doc["deployment"]["calibration"]
    c = cal["factor"]
    assert dep["factor"] == c and c > 1 and cal["fitted_on"] == "train"
    assert cal["channel"] == "beta" and cal["criterion"] == "crps"
    assert cal["estimate_shift"]["rms"] == 0.0
    assert doc["held_out"]["calibration_factor"] == c
    runs = {}
    for flag in ((), ("--no-calibration",)):
        res = run_cli("evaluate", small, "--params", tuned, "--split", "test", "--json", *flag)
        assert res.returncode == 0, res.stderr
        runs[flag] = json.loads(res.stdout)
    on, off = runs[()], runs[("--no-calibration",)]
    assert on["cov_scale"] == c and off["cov_scale"] == 1.0
    assert on["average"]["rmse"] == off["average"]["rmse"]
    nees_on = on["consistency"]["channels"]["beta"]["nees"]["mean"]
    nees_off = off["consistency"]["channels"]["beta"]["nees"]["mean"]
    assert nees_on == pytest.approx(nees_off / c, rel=1e-9)
    assert on["consistency"] == doc["held_out"]["consistency"]


def test_evaluate_reports_the_cost_as_tuned_and_the_calibrated_one_apart(small, tmp_path):
    """A likelihood cost (nlpd) moves with the covariance scale: evaluate on the training
    split reports the cost tune minimised (its recorded J*, scale 1) whether or not the
    calibration is applied, and the calibrated filter's value under its own key, different
    from it where c ≠ 1."""
    out = tmp_path / "nlpd.json"
    res = run_cli("tune", small, "-n", "3", "--cost", "nlpd", "-o", out)
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    c = doc["calibration"]["factor"]
    assert not math.isclose(c, 1.0, rel_tol=1e-3)
    runs = {}
    for flag in ((), ("--no-calibration",)):
        res = run_cli("evaluate", small, "--params", out, "--split", "train", "--json", *flag)
        assert res.returncode == 0, res.stderr
        runs[flag] = json.loads(res.stdout)
    on, off = runs[()], runs[("--no-calibration",)]
    assert on["cost"] == pytest.approx(doc["cost"], rel=1e-9)
    assert off["cost"] == pytest.approx(doc["cost"], rel=1e-9)
    assert off["cost_calibrated"] == off["cost"]
    assert not math.isclose(on["cost_calibrated"], on["cost"], rel_tol=1e-6)


def test_the_criterion_is_chosen_on_the_command_line_or_in_the_configuration(small, tmp_path):
    """--calibration nees records the criterion and meets it (training mean NEES 1);
    calibration = "none" in a configuration tunes without calibrating, as --no-calibration;
    an unknown criterion in a file is refused naming the file and the key (exit 3), on the
    command line by argparse (exit 2), and --no-calibration with a criterion as a
    contradiction (exit 2) — each before anything runs."""
    out = tmp_path / "nees.json"
    res = run_cli("tune", small, "-n", "2", "--calibration", "nees", "-o", out)
    assert res.returncode == 0, res.stderr
    cal = json.loads(out.read_text())["calibration"]
    assert cal["criterion"] == "nees" and "(nees on β" in res.stdout
    assert cal["train"]["after"]["mean_nees"] == pytest.approx(1.0, abs=TOLERANCE)
    cfg = tmp_path / "run.toml"
    cfg.write_text('calibration = "none"\n')
    out = tmp_path / "none.json"
    res = run_cli("tune", small, "-n", "2", "--config", cfg, "-o", out)
    assert res.returncode == 0, res.stderr
    assert json.loads(out.read_text())["calibration"] is None
    assert "calibrated σ" not in res.stdout
    cfg.write_text('calibration = "mean"\n')
    for cmd in ("tune", "evaluate"):  # one file serves every command: checked by all
        out = ("-o", tmp_path / "no.json") if cmd == "tune" else ("--manual",)
        res = run_cli(cmd, small, "--config", cfg, *out)
        assert res.returncode == 3, res.stderr
        assert str(cfg) in res.stderr and "key 'calibration': expected one of" in res.stderr
        assert "Traceback" not in res.stderr
    res = run_cli("tune", small, "--calibration", "mean", "-o", tmp_path / "no.json")
    assert res.returncode == 2 and "--calibration" in res.stderr
    res = run_cli(
        "tune", small, "--no-calibration", "--calibration", "nees", "-o", tmp_path / "no.json"
    )
    assert res.returncode == 2 and "contradicts" in res.stderr
    assert not (tmp_path / "no.json").exists()


@pytest.mark.parametrize(
    ("edit", "named"),
    [
        (lambda d: d["calibration"].update(factor=-1.0), "'calibration'"),
        (lambda d: d["deployment"]["calibration"].update(factor=3.0), "disagree"),
        (lambda d: d.update(calibration=None), "'deployment.calibration' is set"),
        (lambda d: d["deployment"].update(calibration=None), "edited in one place only"),
    ],
)
def test_a_damaged_calibration_is_refused_naming_the_file_and_key(
    small, tuned, tmp_path, edit, named
):
    doc = json.loads(tuned.read_text())
    edit(doc)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    for cmd in (("evaluate", small, "--params", bad), ("export", bad, "-o", "-")):
        res = run_cli(*cmd)
        assert res.returncode == 3, res.stdout + res.stderr
        assert str(bad) in res.stderr and named in res.stderr and "Traceback" not in res.stderr


def test_the_scale_round_trips_through_every_export_format(tuned, tmp_path):
    """json, yaml, C (kftune_filter.h), MATLAB: Q and R as tuned (what runs) and the factor,
    each read back as the same double."""
    doc = json.loads(tuned.read_text())
    c = doc["calibration"]["factor"]
    texts = {}
    for fmt, suffix in (("json", ".json"), ("yaml", ".yaml"), ("c", "_c"), ("matlab", ".m")):
        out = tmp_path / f"f{suffix}"
        assert run_cli("export", tuned, "-f", fmt, "-o", out).returncode == 0
        texts[fmt] = (out / "kftune_filter.h" if fmt == "c" else out).read_text()
    exported = json.loads(texts["json"])
    assert exported["covariance_scale"] == c and exported["q_diag"] == doc["q"]
    got = re.search(r"^covariance_scale: (\S+)$", texts["yaml"], re.M)
    assert got and float(got[1]) == c
    got = re.search(r"#define KFTUNE_COVARIANCE_SCALE (\S+)", texts["c"])
    assert got and float(got[1]) == c
    got = re.search(r"^kf\.covariance_scale = (\S+);", texts["matlab"], re.M)
    assert got and float(got[1]) == c


def test_compare_shows_the_calibrated_consistency_and_the_same_kpis(small):
    """A method's run as compare records it: the KPIs are the uncalibrated filter's to the
    last digit, the consistency is the calibrated one's (NEES c times smaller), and the
    consistency table carries c."""
    from kftune.data import open_dataset
    from kftune.experiment import method_run, tune
    from kftune.report.results import ExperimentResults
    from kftune.report.tables import consistency_table
    from kftune.tuning.deploy import consistency_docs
    from kftune.tuning.problem import TuningProblem, assess

    ds = open_dataset(small)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    result = tune(problem, "manual", progress=False)
    run, _ = method_run("manual", result, problem, {"test": ds.test})
    c = run.extra["calibration"]["factor"]
    assert c > 1 and problem.cov_scale == 1.0  # restored
    metrics, runs = assess(problem, result.x, ds.test)
    assert run.metrics["test"] == metrics
    nees = consistency_docs(problem, ds.test, runs)[1]["channels"]["beta"]["nees"]["mean"]
    got = run.consistency["test"]["channels"]["beta"]["nees"]["mean"]
    assert got == pytest.approx(nees / c, rel=1e-9)
    table = consistency_table(ExperimentResults(meta={}, methods=[run]), "test")
    assert table.header[-2] == "Covariances × c (calibration)" and table.rows[0][-2] == c


@pytest.mark.slow
def test_a_model_without_beta_is_fitted_on_its_referenced_states_else_on_the_nis():
    """The CTRV tracker (no β): c is fitted on the states with a reference (v_ref,
    omega_ref), pooled, to a mean NEES of 1 (or the least CRPS); without any reference on
    the NIS (mean NIS = m after it), and the record says so."""
    from kftune.data.manoeuvre import Manoeuvre
    from kftune.experiment import manual_point
    from kftune.tuning.calibrate import calibrate, problem_runs
    from kftune.tuning.problem import TuningProblem
    from test_data_schema import ctrv_manoeuvre

    ms = [ctrv_manoeuvre(f"run-{i}", "train", i) for i in (1, 2)]
    problem = TuningProblem(ms, None, [0.25, 0.25], model="ctrv", cost=CostSpec(kind="nis"))
    x = manual_point(problem.parameterization)
    for criterion in ("nees", "crps"):
        cal = calibrate(problem, x, criterion=criterion)
        assert set(cal.channels) == {"v", "omega"} and cal.criterion == criterion
        got = required_factor(problem_runs(problem, x, ms)(cal.factor), criterion)
        assert got == pytest.approx(1.0, abs=TOLERANCE)
    bare = [
        Manoeuvre(m.name, m.kind, m.split, m.t, px=m.channel("px"), py=m.channel("py")) for m in ms
    ]
    cal = calibrate(problem, x, bare)
    assert cal.criterion == "nis" and cal.as_dict()["channel"] == "nis"
    assert cal.nis_after == pytest.approx(1.0, abs=TOLERANCE)


def test_a_filter_that_diverges_is_not_calibrated_and_says_where(small):
    """Q of 1e9 everywhere: the filter diverges; calibrate names the manoeuvre and why."""
    from kftune.data import open_dataset
    from kftune.tuning.calibrate import CalibrationError, calibrate
    from kftune.tuning.problem import TuningProblem

    ds = open_dataset(small)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    with pytest.raises(CalibrationError, match=f"diverged on manoeuvre '{ds.train[0].name}' \\("):
        calibrate(problem, np.array([1e9, 1e9, 1e9]))


def test_compare_records_why_a_filter_was_not_calibrated_and_the_report_says_so(small):
    """A diverging point: the record is None and the reason names the manoeuvre; the
    report's note says which filters are calibrated, names one that is not with its
    reason, and says results without any record show the filters as tuned."""
    from types import SimpleNamespace

    from kftune.data import open_dataset
    from kftune.experiment import _calibration
    from kftune.report import calibration_note
    from kftune.tuning.problem import TuningProblem

    ds = open_dataset(small)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    record, why = _calibration(problem, np.array([1e9, 1e9, 1e9]))
    assert record is None and f"diverged on manoeuvre '{ds.train[0].name}'" in why

    def run(label: str, **extra: object) -> SimpleNamespace:
        return SimpleNamespace(label=label, consistency={"test": {}}, extra=extra)

    ok = run("TR-BO", calibration={"factor": 2.0})
    bad = run("Manual", calibration=None, calibration_failed=why)
    assert calibration_note(SimpleNamespace(methods=[ok])).startswith("each filter here is")
    mixed = calibration_note(SimpleNamespace(methods=[ok, bad]))
    assert "each filter with a factor c here is calibrated" in mixed
    assert f"Not calibrated (shown as tuned): Manual: {why}" in mixed
    old = calibration_note(SimpleNamespace(methods=[run("TR-BO"), run("Manual")]))
    assert "shown as tuned: these results record no calibration" in old
    assert "calibrated as kftune tune deploys it" not in old


def test_compare_and_export_say_in_their_help_what_they_do_with_the_calibration():
    """compare --help: each filter shown calibrated, --no-calibration is another command's;
    export --help: the export applies the tuned file's calibration."""
    helps = {}
    for command in ("compare", "export"):
        res = run_cli(command, "--help")
        assert res.returncode == 0, res.stderr
        helps[command] = " ".join(res.stdout.split())
    assert "Each filter, the manual one too, is shown calibrated" in helps["compare"]
    assert "there is no --no-calibration here (tune, evaluate and estimate" in helps["compare"]
    assert "The export applies the tuned file's calibration" in helps["export"]
