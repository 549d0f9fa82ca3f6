"""Consistency of a filter's standard deviations: coverage, NEES and NIS with χ² bands.

References independent of kftune: a hand count; the textbook's χ² band (Bar-Shalom, Li &
Kirubarajan 2001, §5.4: 50 runs of a 2-state NEES accept [1.5, 2.6]); the mean of N χ²_k
as a Gamma(N·k/2, 2/N) variable; Monte Carlo of AR(1) errors; a linear-Gaussian model
simulated with known Q and R, filtered by kftune and by FilterPy.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from filterpy.stats import NEES
from scipy.signal import lfilter
from scipy.stats import gamma

from conftest import SMALL_TEST, run_cli
from kftune.filters import EKF
from kftune.models.linear import linear_model
from kftune.tuning.consistency import (
    ChannelConsistency,
    channel_consistency,
    chi2_band,
    covered,
    nis_consistency,
    of_columns,
    pool_runs,
)


# ------------------------------------------------------------------------ the statistics
def test_coverage_and_nees_equal_a_hand_count_on_a_small_example():
    """Errors 0, 0.5, -0.99, 1.5, -2.5 with σ = 1: three inside ±1σ, four inside ±1.96σ;
    a NaN estimate and a σ of 0 are not counted."""
    est = np.array([1.0, 1.5, 0.01, 2.5, -1.5, np.nan, 3.0])
    ref = np.ones(7)
    std = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    got = channel_consistency(est, std, ref)
    assert got.n == 5
    assert got.covered == (3, 4)
    assert got.coverage == pytest.approx((3 / 5, 4 / 5))
    assert got.nees.mean == pytest.approx((0 + 0.25 + 0.99**2 + 2.25 + 6.25) / 5)
    assert covered(est - ref, 2.0 * std, 1.0) == (4, 5)  # |err| ≤ 2: all but -2.5


def test_the_band_is_the_textbooks_and_the_gamma_quantiles():
    """50 runs of a 2-dimensional NEES: [1.5, 2.6] (Bar-Shalom et al. 2001, §5.4); and
    for any N and k the mean of N χ²_k is Gamma(N·k/2, scale 2/N)."""
    lo, hi = chi2_band(50, 2)
    assert (lo, hi) == pytest.approx((1.5, 2.6), abs=0.02)
    for n, k in ((1, 1), (7, 3), (1000, 1), (12.5, 2)):
        want = gamma.ppf([0.025, 0.975], n * k / 2, scale=2 / n)
        assert chi2_band(n, k) == pytest.approx(tuple(want), rel=1e-9)
    assert all(math.isnan(v) for v in chi2_band(0, 1))


@pytest.mark.parametrize("rho", [0.0, 0.9, 0.99])
def test_the_effective_band_accepts_consistent_autocorrelated_errors_95_percent_of_the_time(
    rho,
):
    """Consistent (N(0, 1)) errors that are AR(1), as a Kalman filter's errors are: the
    band of N independent samples rejects far more than 5 % of the runs once ρ is large;
    the band of the effective count rejects about 5 % (binomial bounds over 400 runs)."""
    rng = np.random.default_rng(1)
    runs, n = 400, 2000
    out_n = out_eff = 0
    for _ in range(runs):
        w = rng.normal(0.0, math.sqrt(1 - rho**2), n)
        w[0] = rng.normal()  # e_0 ~ N(0, 1): the sequence is stationary from the start
        e = lfilter([1.0], [1.0, -rho], w)  # e_k = ρ·e_{k−1} + w_k
        nees = channel_consistency(e, np.ones(n), np.zeros(n)).nees
        lo, hi = nees.band
        out_n += not lo <= nees.mean <= hi
        out_eff += not nees.inside
    assert 0.015 <= out_eff / runs <= 0.09  # 5 % ± 3.5 standard errors
    if rho >= 0.9:
        assert out_n / runs > 0.3


def test_pooled_runs_equal_the_runs_concatenated():
    """Pooling two manoeuvres counts their samples together: the coverage and mean NEES of
    the concatenation; the effective counts add (the runs are independent)."""
    rng = np.random.default_rng(2)
    a = [rng.normal(0, 1, 300), np.full(300, 0.8), np.zeros(300)]
    b = [rng.normal(0, 2, 500), np.full(500, 1.1), np.zeros(500)]
    ca, cb = channel_consistency(*a), channel_consistency(*b)
    both = channel_consistency(*(np.r_[x, y] for x, y in zip(a, b)))
    channels, nis = pool_runs([({"x": ca}, None), ({"x": cb, "y": cb}, None)])
    assert nis is None and set(channels) == {"x", "y"}
    assert channels["x"].covered == both.covered and channels["x"].n == 800
    assert channels["x"].nees.mean == pytest.approx(both.nees.mean, rel=1e-12)
    assert channels["x"].nees.n_eff == pytest.approx(ca.nees.n_eff + cb.nees.n_eff)
    assert channels["y"] == cb


def test_columns_with_a_std_and_a_reference_are_measured_from_the_first_scored_sample():
    """Of named columns, each channel with ``<c>_std`` and ``<c>_ref`` (and only those);
    the NIS of m measurements; samples before ``first`` are not counted."""
    n = 10
    cols = {
        "t": np.arange(n),
        "vx": np.ones(n),
        "vx_std": np.full(n, 0.5),
        "vx_ref": np.r_[np.full(4, 100.0), np.ones(n - 4)],
        "vy": np.zeros(n),
        "vy_std": np.ones(n),  # no reference: not measured
        "yaw": np.zeros(n),
        "yaw_ref": np.zeros(n),  # no std: not measured
        "nis": np.r_[np.full(4, 1e6), np.full(n - 4, 2.0)],
    }
    channels, nis = of_columns(cols, 2, first=4)
    assert list(channels) == ["vx"]
    assert channels["vx"].n == 6 and channels["vx"].nees.mean == 0.0
    assert nis.dof == 2 and nis.n == 6 and nis.mean == 2.0 and nis.inside
    assert of_columns({"vx": np.ones(3)}, 1) == ({}, None)


def test_json_form_has_no_nan():
    """Nothing counted: None, not NaN (strict JSON)."""
    empty = channel_consistency(np.full(3, np.nan), np.ones(3), np.zeros(3))
    assert isinstance(empty, ChannelConsistency) and empty.n == 0
    json.dumps(empty.as_dict(), allow_nan=False)
    json.dumps(nis_consistency(np.full(2, np.nan), 3).as_dict(), allow_nan=False)


# ------------------------------------------------------- a filter with known Q and R
F = np.array([[1.0, 0.1], [0.0, 0.95]])
H = np.array([[1.0, 0.0]])
Q = np.array([1e-4, 1e-2])
R = np.array([0.05])


def simulate(seed: int, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """(x (n, 2), z (n, 1)) of x_k = F·x_{k−1} + w, z_k = H·x_k + v, w ~ N(0, diag Q),
    v ~ N(0, R), x_0 ~ N(0, I)."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 2))
    x[0] = rng.normal(0.0, 1.0, 2)
    for k in range(1, n):
        x[k] = F @ x[k - 1] + rng.normal(0.0, np.sqrt(Q))
    return x, x @ H.T + rng.normal(0.0, np.sqrt(R), (n, 1))


def consistency_of_run(x: np.ndarray, z: np.ndarray, scale: float):
    """kftune's Kalman filter (EKF of a linear model) with Q and R times ``scale``,
    started at 0 with P0 = I: (each state's consistency, the NIS)."""
    res = EKF().run(linear_model(F, H), None, z, 1.0, Q * scale, R * scale, x0=[0, 0], P0=[1, 1])
    states = [
        channel_consistency(res.x[:, i], np.sqrt(res.P_diag[:, i]), x[:, i]) for i in range(2)
    ]
    return states, nis_consistency(res.nis, 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_filter_with_the_true_noise_is_consistent(seed):
    """The true Q and R: every state's mean NEES and the mean NIS inside their 95 % bands;
    coverage within 4 standard errors (of the effective count) of 68.27 % and 95 %."""
    x, z = simulate(seed)
    states, nis = consistency_of_run(x, z, 1.0)
    for s in states:
        assert s.nees.inside, (s.nees.mean, s.nees.band_eff)
        for share, p in zip(s.coverage, (0.6827, 0.95)):
            assert abs(share - p) < 4 * math.sqrt(p * (1 - p) / s.nees.n_eff)
    assert nis.dof == 1 and nis.inside, (nis.mean, nis.band)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_filter_with_q_and_r_ten_times_too_small_is_detected(seed):
    """Q and R scaled by 1/10 (the same gain, P ten times too small): the NEES of every
    state and the NIS above their bands, the coverage far below nominal."""
    x, z = simulate(seed)
    states, nis = consistency_of_run(x, z, 0.1)
    for s in states:
        assert s.nees.mean > s.nees.band_eff[1] and not s.nees.inside
        assert s.coverage[0] < 0.5 and s.coverage[1] < 0.8
    assert nis.mean > nis.band[1] and not nis.inside


@pytest.mark.slow
def test_nees_and_nis_equal_filterpys_on_a_scalar_model():
    """A scalar random walk: kftune's filter and statistics give the mean NEES and NIS that
    FilterPy's Kalman filter and its NEES give."""
    rng = np.random.default_rng(3)
    n, q, r = 3000, 0.01, 0.2
    x = np.cumsum(rng.normal(0.0, math.sqrt(q), n))
    z = x + rng.normal(0.0, math.sqrt(r), n)
    res = EKF().run(linear_model([[1.0]], [[1.0]]), None, z[:, None], 1.0, [q], [r], x0=[0], P0=[1])
    ours = channel_consistency(res.x[:, 0], np.sqrt(res.P_diag[:, 0]), x)
    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = np.zeros(1), np.eye(1), np.eye(1), np.eye(1), q, r
    est, cov, nis = [], [], []
    for k in range(n):
        if k:
            kf.predict()
        kf.update(z[k])
        est.append(kf.x.copy())
        cov.append(kf.P.copy())
        nis.append(kf.mahalanobis**2)
    want = np.mean(NEES(x[:, None], np.array(est), np.array(cov)))
    assert ours.nees.mean == pytest.approx(want, rel=1e-9)
    assert nis_consistency(res.nis, 1).mean == pytest.approx(np.mean(nis), rel=1e-9)


def test_the_table_has_a_line_per_channel_the_nis_once_and_marks_means_outside():
    """Two referenced states: a line each, the manoeuvre's NIS on its first; a mean outside
    its band marked ``*``; a diverged manoeuvre says so; every line within 100 columns."""
    from kftune.report.tables import consistency_lines
    from kftune.tuning.consistency import as_doc

    rng = np.random.default_rng(4)
    e = rng.normal(0.0, 1.0, 500)
    good = channel_consistency(e, np.ones(500), np.zeros(500))
    bad = channel_consistency(10 * e, np.ones(500), np.zeros(500))
    run = as_doc({"vx": good, "vy": bad}, nis_consistency(rng.chisquare(2, 500), 2))
    lines = consistency_lines({"a-rather-long-manoeuvre-name": run, "b": None})
    assert "NIS (m=2)" in lines[0]
    vx, vy, diverged = lines[1:4]
    assert vx.split()[:2] == ["a-rather-long-manoeuvre-name", "vx"] and "*" not in vx
    assert vy.split()[0] == "vy" and vy.split()[3].endswith("*") and len(vy.split()) == 6
    assert diverged.split()[:2] == ["b", "–"] and "diverged" in diverged
    assert all(len(line) <= 100 for line in lines)


# ------------------------------------------------------------------ the command line
@pytest.fixture(scope="module")
def tuned_run(small: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """(a tuned file of the small dataset, what tune printed): 3 evaluations, cheap, not a
    good filter."""
    out = tmp_path_factory.mktemp("tuned") / "t.json"
    res = run_cli("tune", small, "-n", "3", "-q", "-o", out)
    assert res.returncode == 0, res.stderr
    return out, res.stdout


@pytest.fixture(scope="module")
def tuned(tuned_run: tuple[Path, str]) -> Path:
    """The tuned file of :func:`tuned_run`."""
    return tuned_run[0]


def check_doc(doc: dict, m: int = 3) -> None:
    """A consistency document (per manoeuvre or pooled) of the sideslip filter: β measured,
    coverages ordered in [0, 1], NEES and NIS bands around 1 and m."""
    beta = doc["channels"]["beta"]
    assert 0 <= beta["cov68"] <= beta["cov95"] <= 1 and beta["n"] > 100
    nees = beta["nees"]
    assert nees["dof"] == 1 and nees["mean"] > 0 and nees["n"] == beta["n"]
    assert nees["band"][0] < 1 < nees["band"][1] and nees["n_eff"] <= nees["n"]
    assert nees["band_eff"][0] <= nees["band"][0] and nees["band_eff"][1] >= nees["band"][1]
    assert nees["inside"] == (nees["band_eff"][0] <= nees["mean"] <= nees["band_eff"][1])
    nis = doc["nis"]
    assert nis["dof"] == m and nis["band"][0] < m < nis["band"][1] and nis["mean"] > 0


def test_evaluate_reports_consistency_per_manoeuvre_and_pooled(small, tuned):
    """--json: each manoeuvre and the split carry "consistency" beside the KPIs (kept);
    the pooled counts are the manoeuvres' summed. The table shows it, m and the bands,
    in 100 columns."""
    res = run_cli("evaluate", small, "--params", tuned, "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    rows = doc["manoeuvres"]
    assert list(rows) == list(SMALL_TEST)
    for row in rows.values():
        assert {"rmse", "mae", "rmse_non", "mae_non", "rmse_beta"} <= set(row)
        check_doc(row["consistency"])
    check_doc(doc["consistency"])
    pooled = doc["consistency"]["channels"]["beta"]
    assert pooled["n"] == sum(r["consistency"]["channels"]["beta"]["n"] for r in rows.values())
    text = run_cli("evaluate", small, "--params", tuned)
    assert text.returncode == 0 and "Traceback" not in text.stderr
    lines = text.stdout.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("consistency"))
    assert "NIS (m=3)" in lines[head] and "cov95%" in lines[head]
    assert [line.split()[0] for line in lines[head + 1 : head + 4]] == [*SMALL_TEST, "test"]
    assert all(len(line) <= 100 for line in lines)


@pytest.mark.slow
def test_estimate_says_what_its_mean_nis_should_be(small, tuned, tmp_path):
    """estimate: per manoeuvre and over all of them, the consistency of β and the NIS with
    m = 3 and its band (JSON and table); "mean_nis" is kept; nothing but its tables and
    figures is written."""
    out = tmp_path / "est"
    res = run_cli("estimate", small, "--params", tuned, "-o", out, "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    for row in doc["manoeuvres"].values():
        assert row["mean_nis"] > 0
        check_doc(row["consistency"])
    assert doc["consistency"] is None  # training and test: pooled within each split only
    assert set(doc["consistency_by_split"]) == {"train", "test"}
    for pooled in doc["consistency_by_split"].values():
        check_doc(pooled)
    text = run_cli("estimate", small, "--params", tuned, "-o", out, "-m", SMALL_TEST[0])
    assert text.returncode == 0 and "Traceback" not in text.stderr
    assert "NIS (m=3)" in text.stdout and "95% band" in text.stdout
    _kpis, checks = (x for x in text.stdout.splitlines() if x.startswith(SMALL_TEST[0] + " "))
    assert checks.split()[1] == "beta"  # the consistency row, after the KPI row
    assert sorted(p.suffix for p in out.iterdir()) == [".csv"] * 4 + [".png"] * 4
    # the table's lines; the closing one names the output folder, whose length is the user's
    assert all(len(line) <= 100 for line in text.stdout.splitlines() if str(out) not in line)


@pytest.mark.parametrize(
    ("error", "scale", "narrow"), [(1.0, 0.001, True), (1.0, 1.0, False), (0.01, 0.01, False)]
)
def test_the_estimate_figure_says_when_its_band_is_too_narrow_to_see(error, scale, narrow):
    """β errors within ±1° and σ of 0.001° (a band of a fraction of a pixel) or of 1°, and
    errors within ±0.01° with σ of 0.01° (a small band, wide on the error's scale): the
    title says how much of the reference the band covers, and that it cannot be seen only
    when, at the scale on the page, it cannot."""
    from kftune.report.plots import estimate_trace, render

    t = np.linspace(0.0, 10.0, 2001)
    ref = np.radians(3.0 * np.sin(t))
    est = ref + np.radians(error * np.sin(3.0 * t))
    fig = estimate_trace(t, est, np.full(t.size, np.radians(scale)), ref, "β")
    title = fig.axes[0].get_title()
    render(fig)
    inside = np.mean(np.abs(error * np.sin(3.0 * t)) <= 2.0 * scale)
    assert f"covers {100 * inside:.0f} % of the reference" in title
    assert ("too narrow to see" in title) == narrow
    if narrow:
        assert "±0.002°" in title  # the band: ±2σ


def test_a_diverged_run_has_no_consistency_and_the_split_none(small):
    """Where the filter diverged, its rows before the divergence would flatter it: no
    consistency for that manoeuvre nor pooled (as the KPI averages); exit 1 as before."""
    res = run_cli("evaluate", small, "--q", "1e9", "1e9", "1e9", "--json")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    doc = json.loads(res.stdout)
    assert doc["consistency"] is None
    assert all(row["consistency"] is None for row in doc["manoeuvres"].values())
    text = run_cli("evaluate", small, "--q", "1e9", "1e9", "1e9")
    assert text.returncode == 1
    assert text.stdout.count("(the filter diverged)") == len(SMALL_TEST) + 1


def test_tune_says_how_well_its_sigma_covers_the_held_out_errors(small, tuned_run, tmp_path):
    """tune's summary: beside the held-out RMSE, the tuned filter's β ±1.96σ coverage and
    mean NEES on the test manoeuvres, and the factor σ is off by; the same numbers as
    evaluate's --json for the tuned file, recorded in its held_out, and as a count by hand
    over estimate's CSV columns β, beta_std and beta_ref after the burn-in."""
    path, stdout = tuned_run
    lines = stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if "held-out errors" in line)
    assert "β RMSE" in lines[at - 1] and "Traceback" not in stdout
    line = lines[at]
    shown = re.search(r"±1\.96σ covers (\d+) % .* mean NEES ([0-9.e+]+) \(1 if consistent\)", line)
    assert shown, line
    tuned = json.loads(path.read_text())
    held = tuned["held_out"]["consistency"]["channels"]["beta"]
    res = run_cli("evaluate", small, "--params", path, "--split", "test", "--json")
    assert res.returncode == 0, res.stderr
    evaluated = json.loads(res.stdout)["consistency"]["channels"]["beta"]
    assert held["n"] == evaluated["n"]
    for key in ("cov68", "cov95"):
        assert held[key] == pytest.approx(evaluated[key], abs=1e-9)
    assert held["nees"]["mean"] == pytest.approx(evaluated["nees"]["mean"], rel=1e-9)
    est = tmp_path / "est"
    res = run_cli("estimate", small, "--params", path, "-o", est, "--no-plot")
    assert res.returncode == 0, res.stderr
    errors = []
    for name in SMALL_TEST:
        cols = np.genfromtxt(est / f"{name}.csv", delimiter=",", names=True)
        kept = cols["t"] - cols["t"][0] >= tuned["burn_in"] - 1e-9
        errors.append(((cols["beta"] - cols["beta_ref"]) / cols["beta_std"])[kept])
    e = np.concatenate(errors)
    cov95, nees = np.mean(np.abs(e) <= 1.959964), np.mean(e**2)
    assert held["n"] == e.size
    assert held["cov95"] == pytest.approx(cov95, abs=1e-9)
    assert held["nees"]["mean"] == pytest.approx(nees, rel=1e-6)
    assert int(shown[1]) == round(100 * cov95)
    assert float(shown[2]) == pytest.approx(nees, rel=5e-3)
    if held["nees"]["inside"]:
        assert line.endswith("σ can be trusted there")
    else:
        factor = math.sqrt(nees) if nees > 1 else 1 / math.sqrt(nees)
        got = re.search(r"σ is about ([0-9.]+)× too (small|large)$", line)
        assert got and float(got[1]) == pytest.approx(factor, rel=0.06)
        assert got[2] == ("small" if nees > 1 else "large")


def test_tunes_consistency_line_says_trusted_too_large_or_nothing():
    """Inside the band: σ can be trusted; a mean NEES of 0.25: σ about 2× too large; no
    consistency recorded (the filter diverged, or an older tuned file): no line."""
    from kftune.cli.tune import held_out_consistency_line
    from kftune.tuning.consistency import as_doc

    rng = np.random.default_rng(5)
    e = rng.normal(0.0, 1.0, 4000)
    for scale, end in ((1.0, "σ can be trusted there"), (0.5, "σ is about 2× too large")):
        beta = channel_consistency(scale * e, np.ones(e.size), np.zeros(e.size))
        line = held_out_consistency_line({"consistency": as_doc({"beta": beta}, None)})
        assert line.endswith(end), line
        assert f"covers {100 * beta.coverage[1]:.0f} % of the held-out errors" in line
    assert held_out_consistency_line({"consistency": None}) is None
    assert held_out_consistency_line({"beta_rmse_deg": 0.1}) is None
