"""Identifiability of tuned parameters against closed forms: a quadratic cost of known
Hessian, a flat direction, an optimum on a bound, a noisy flat direction, failed points."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from kftune.sim.single_track import SENSOR_STD, gentle_slalom
from kftune.space import Param, Space
from kftune.tuning.identify import (
    MAX_EVALS_PER_PARAMETER,
    NOT_DETERMINED_SHARE,
    REL_RISE,
    identify,
)

#: log10 over 6 decades, linear over 10 units, log10 over 2 decades.
SPACE = Space(
    (
        Param("k", 1e-3, 1e3, "log10"),
        Param("b", -5.0, 5.0, "linear"),
        Param("c", 1.0, 100.0, "log10"),
    )
)
X_BEST = np.array([0.1, 1.0, 10.0])
J_BEST = 2.0


def search_t(x: np.ndarray) -> np.ndarray:
    """(B, 3) natural units → the search scale t (log10 k, b, log10 c)."""
    x = np.atleast_2d(x)
    return np.column_stack([np.log10(x[:, 0]), x[:, 1], np.log10(x[:, 2])])


def quadratic(hessian: np.ndarray, t_best: np.ndarray | None = None):
    """J(t) = J* + ½ (t − t*)ᵀ H (t − t*) over batches of natural-unit points."""
    centre = search_t(X_BEST)[0] if t_best is None else t_best

    def cost(points: np.ndarray) -> np.ndarray:
        d = search_t(points) - centre
        return J_BEST + 0.5 * np.einsum("bi,ij,bj->b", d, hessian, d)

    return cost


#: A symmetric positive definite Hessian with strong off-diagonal terms.
HESSIAN = np.array([[80.0, 30.0, -10.0], [30.0, 40.0, 5.0], [-10.0, 5.0, 500.0]])


def test_quadratic_curvature_and_range_are_the_closed_form():
    """With the other coordinates held, the curvature along t_i is H_ii and the cost rises
    by ΔJ = 1 % of J* at δ = √(2·ΔJ/H_ii), from the curvature and from the profile."""
    assert np.all(np.linalg.eigvalsh(HESSIAN) > 0)
    calls = []

    def cost(points: np.ndarray) -> np.ndarray:
        calls.append(len(points))
        return quadratic(HESSIAN)(points)

    out = identify(cost, SPACE, X_BEST, ["k", "b", "c"], start={"k": 0.05, "b": 2.0, "c": 10.0})
    # the profiles in one batch, then one point per pair for the cross curvatures
    assert len(calls) == 2 and calls[1] == 3 and sum(calls) == out.n_evals
    assert out.n_evals <= 1 + 3 * MAX_EVALS_PER_PARAMETER + 3
    delta_j = REL_RISE * J_BEST
    cov = np.linalg.inv(HESSIAN)
    for i, rec in enumerate(out.parameters):
        # with the other two re-fitted: the marginal of the quadratic
        assert rec.joint_half_width == pytest.approx(math.sqrt(2 * delta_j * cov[i, i]), rel=1e-6)
        for j, other in enumerate(SPACE.names):
            if j != i:
                rho = cov[i, j] / math.sqrt(cov[i, i] * cov[j, j])
                assert rec.correlations[other] == pytest.approx(rho, rel=1e-6)
        assert rec.delta_j == pytest.approx(delta_j)
        assert rec.curvature == pytest.approx(HESSIAN[i, i], rel=1e-6)
        for _, c in rec.curvature_steps:  # every step agrees on a quadratic
            assert c == pytest.approx(HESSIAN[i, i], rel=1e-6)
        half = math.sqrt(2 * delta_j / HESSIAN[i, i])
        assert rec.half_width == pytest.approx(half, rel=1e-6)
        t = search_t(X_BEST)[0][i]
        lo, hi = (t - half, t + half)
        if rec.scale == "log10":
            lo, hi = 10**lo, 10**hi
        assert rec.range_low == pytest.approx(lo, rel=1e-6)
        assert rec.range_high == pytest.approx(hi, rel=1e-6)
        assert rec.determined and rec.limits == "both" and rec.on_bound is None
        assert rec.better is None
        assert rec.share == pytest.approx(2 * half / SPACE.params[i].width, rel=1e-6)
    k, b, _ = out.parameters
    assert k.ratio == pytest.approx(2.0) and b.ratio == pytest.approx(0.5)
    assert k.to_dict()["change_pct"] == pytest.approx(100.0)
    json.dumps(out.to_dict(), allow_nan=False)  # strict JSON
    assert "determined" in k.describe() and "×2 the start" in k.describe()


def test_a_direction_the_cost_ignores_is_not_determined():
    hessian = HESSIAN.copy()
    hessian[2, :] = hessian[:, 2] = 0.0  # c does not enter J
    out = identify(quadratic(hessian), SPACE, X_BEST, ["k", "c"], reasons={"c": "c is idle"})
    k, c = out.parameters
    assert k.determined
    assert not c.determined and c.limits == "none" and c.curvature is None
    assert c.share == pytest.approx(1.0)
    assert (c.range_low, c.range_high) == (1.0, 100.0)
    text = c.describe()
    assert "NOT determined" in text and "flat across the box" in text and "c is idle" in text
    assert "c is idle" not in k.describe()


def test_a_wide_valley_is_not_determined_even_when_closed():
    """A range closed on both sides that spans most of the box says the data do not
    determine the parameter: the box, not the data, is almost all that limits it."""
    hessian = np.diag([80.0, 40.0, 0.0])
    width = SPACE.params[2].width
    # the cost rises by ΔJ at ±0.35 of the box: closed, but over 70 % of it
    hessian[2, 2] = 2 * REL_RISE * J_BEST / (0.35 * width) ** 2
    (c,) = identify(quadratic(hessian), SPACE, X_BEST, ["c"]).parameters  # c at its centre
    assert c.limits == "both" and c.share == pytest.approx(0.7, rel=1e-6)
    assert c.share >= NOT_DETERMINED_SHARE and not c.determined
    assert "spans 70 % of the box" in c.describe()


def test_an_optimum_beyond_a_bound_is_on_it_with_only_a_lower_limit():
    """The best point sits on the upper bound (the valley's centre lies beyond it): on
    its bound, the cost rises below it and not above, so only a lower limit."""
    beyond = np.array([-1.0, 1.0, 2.3])  # log10 c = 2.3 > log10 100
    x = np.array([0.1, 1.0, 100.0])
    (c,) = identify(quadratic(np.diag([80.0, 40.0, 50.0]), beyond), SPACE, x, ["c"]).parameters
    assert c.on_bound == "upper"
    assert c.limits == "lower" and not c.determined
    assert c.range_high == 100.0 and c.range_low < 100.0
    text = c.describe()
    assert "on its upper bound 100" in text and "only a lower limit" in text
    assert "the optimum may lie beyond" in text and "flat" not in text
    # within 1 % of the box (in the search scale) of the lower bound counts as on it
    x_near = np.array([10 ** (-3 + 0.009 * 6), 1.0, 10.0])
    (k,) = identify(quadratic(HESSIAN), SPACE, x_near, ["k"]).parameters
    assert k.on_bound == "lower"
    x_off = np.array([10 ** (-3 + 0.02 * 6), 1.0, 10.0])
    (k,) = identify(quadratic(HESSIAN), SPACE, x_off, ["k"]).parameters
    assert k.on_bound is None


def test_a_one_sided_valley_gives_only_a_lower_limit():
    """A cost that rises below a threshold and is flat above it (a friction coefficient
    on data that never reach the friction limit): only a lower limit, not determined."""
    t_knee = 1.0  # log10 c

    def cost(points: np.ndarray) -> np.ndarray:
        below = np.maximum(t_knee - search_t(points)[:, 2], 0.0)
        return J_BEST + 50.0 * below**2

    x = np.array([0.1, 1.0, 10**1.3])
    (c,) = identify(cost, SPACE, x, ["c"]).parameters
    assert c.limits == "lower" and not c.determined
    # J*(1 + 1 %) is reached at t = 1 − 0.02; the profile brackets it between its points
    # at t* − 0.1·W and t* − 0.3·W (t = 1.1 and 0.7): the end lies in that bracket
    assert 0.7 <= math.log10(c.range_low) <= 1.1
    assert c.range_high == 100.0
    assert "the cost is flat up to the upper bound 100" in c.describe()


@pytest.mark.parametrize("seed", range(10))
def test_noise_does_not_make_a_flat_direction_look_determined(seed):
    """Cost noise of 0.3 % of J (σ, Gaussian, independent per point: under a third of the
    1 % rise that ends a range): the flat direction stays not determined, and the
    determined one keeps its range within 25 % of the closed form."""
    rng = np.random.default_rng(seed)
    hessian = np.diag([80.0, 40.0, 0.0])
    clean = quadratic(hessian)

    def cost(points: np.ndarray) -> np.ndarray:
        return clean(points) * (1.0 + 0.003 * rng.standard_normal(len(points)))

    k, c = identify(cost, SPACE, X_BEST, ["k", "c"]).parameters
    assert not c.determined and c.share > NOT_DETERMINED_SHARE
    assert k.determined
    half = math.sqrt(2 * REL_RISE * J_BEST / 80.0)
    width = math.log10(k.range_high) - math.log10(k.range_low)
    assert width == pytest.approx(2 * half, rel=0.25)


def test_failed_points_count_as_a_rise_and_a_lower_cost_is_reported():
    """A diverged filter (inf, or NaN) ends the range; a profile point below J* says the
    search had not converged along that parameter."""

    def cost(points: np.ndarray) -> np.ndarray:
        t = search_t(points)
        j = J_BEST - 0.5 * (t[:, 1] - 1.0) + 0.0 * t[:, 0]  # falls along b, flat along k
        j = np.where(t[:, 0] > -0.5, np.inf, j)  # k above 10^-0.5 diverges
        return np.where(t[:, 0] < -2.5, np.nan, j)  # and below 10^-2.5

    k, b = identify(cost, SPACE, X_BEST, ["k", "b"]).parameters
    # each end at the first failed point beyond the last good one (the wider range)
    failed_above = min(v for v, j in k.profile if j == math.inf and v > k.value)
    failed_below = max(v for v, j in k.profile if j == math.inf and v < k.value)
    assert failed_above > 10**-0.5 and failed_below < 10**-2.5
    assert k.limits == "both" and k.determined
    assert (k.range_low, k.range_high) == (failed_below, failed_above)
    assert b.better is not None and b.better[0] > 1.0 and b.better[1] < J_BEST
    assert "had not converged" in b.describe()
    doc = json.dumps(k.to_dict(), allow_nan=False)
    assert "null" in doc  # the failed points, in strict JSON


def test_refuses_unknown_names_points_outside_and_a_bad_rise():
    cost = quadratic(HESSIAN)
    with pytest.raises(ValueError, match=r"\['mu'\] are not in the search space"):
        identify(cost, SPACE, X_BEST, ["mu"])
    with pytest.raises(ValueError, match="outside the search space"):
        identify(cost, SPACE, np.array([1e4, 1.0, 10.0]), ["k"])
    with pytest.raises(ValueError, match="rel_rise"):
        identify(cost, SPACE, X_BEST, ["k"], rel_rise=0.0)
    with pytest.raises(ValueError, match="best point is not finite"):
        identify(lambda p: np.full(len(p), np.inf), SPACE, X_BEST, ["k"])
    assert identify(cost, SPACE, X_BEST, []).lines() == []


def test_an_isolated_rough_value_does_not_close_a_flat_range():
    """A flat cost with one value 2 % too high on each side of the best point, next to it
    (a rough evaluation): the range runs out to the farthest point under the threshold, so
    the parameter is still not determined."""
    width = SPACE.params[2].width
    rough = {round(1.0 - 0.03 * width, 9), round(1.0 + 0.03 * width, 9)}  # log10 c

    def cost(points: np.ndarray) -> np.ndarray:
        t = np.round(search_t(points)[:, 2], 9)
        return np.where(np.isin(t, list(rough)), 1.02 * J_BEST, J_BEST)

    (c,) = identify(cost, SPACE, X_BEST, ["c"]).parameters
    assert sum(j > J_BEST for _, j in c.profile) == 2  # both rough values were evaluated
    assert c.limits == "none" and not c.determined


# ------------------------------------------------------- a real tuning problem, joint tuning


@pytest.mark.slow
def test_joint_tuning_far_from_the_friction_limit_determines_the_stiffnesses_not_mu():
    """Data simulated on the bundled vehicle with |ay| ≤ 3 m/s² (29 % of μ·g), a recorded
    vehicle whose stiffnesses are off (×0.8, ×1.25), Q, C_af, C_ar and μ tuned together
    (TR-BO, 150 evaluations): the stiffnesses come out determined and within 5 % of the
    truth, μ not determined, with the model's reason (no sample near the friction limit)."""
    from kftune import minimize
    from kftune.data import default_dataset
    from kftune.tuning.identify import identify_problem
    from kftune.tuning.parameterization import NoiseParameterization
    from kftune.tuning.problem import TuningProblem

    truth = default_dataset().vehicle
    runs = [gentle_slalom(f"gentle-{k}", truth, k, ay_peak=3.0) for k in range(2)]
    recorded = truth.replace(C_af=0.8 * truth.C_af, C_ar=1.25 * truth.C_ar)
    par = NoiseParameterization(
        model_bounds={"C_af": (2e4, 4e5), "C_ar": (2e4, 4e5), "mu": (0.4, 1.6)}
    )
    r0 = np.square(SENSOR_STD)
    problem = TuningProblem(runs, recorded, r0, parameterization=par)
    result = minimize(problem, problem.space, method="trbo", budget=150, seed=0)
    problem.cov_scale = 3.0  # a calibration fitted after the search: not the tuned cost
    out = identify_problem(problem, result.x)
    assert problem.cov_scale == 3.0
    assert out.parameters[0].cost == pytest.approx(result.fun, rel=1e-9)
    assert out.n_evals <= 1 + 3 * MAX_EVALS_PER_PARAMETER + 3  # and one per pair
    rec = {p.name: p for p in out.parameters}
    assert list(rec) == ["C_af", "C_ar", "mu"]
    for name in ("C_af", "C_ar"):
        assert rec[name].determined, rec[name].describe()
        assert rec[name].value == pytest.approx(getattr(truth, name), rel=0.05)
        assert rec[name].start == getattr(recorded, name)
        assert rec[name].reason is None
    mu = rec["mu"]
    assert not mu.determined and mu.limits in ("lower", "none"), mu.describe()
    assert mu.reason is not None and "% of μ·g, no sample near the friction limit" in mu.reason
    lines = "\n".join(out.lines())
    verdict = "not assessed" if mu.better is not None else "NOT determined"
    assert "mu = " in lines and verdict in lines and "friction limit" in lines
    json.dumps(out.to_dict(), allow_nan=False)


def test_the_single_track_models_name_mu_far_from_the_friction_limit_and_idle_stiffnesses():
    """The hints come from the largest |ay| after a 0.2-s moving average: a plateau of
    3 m/s² is 29 % of μ·g at μ = 1.05 (g = 9.81); one noisy sample of 9 m/s² does not
    count; under 1 m/s² the stiffnesses are named too; near the limit nothing is said."""
    from kftune.models import get_model
    from kftune.vehicle.params import PARAM_INDEX

    hints = get_model("single-track").param_hints
    p = np.zeros(len(PARAM_INDEX))
    p[PARAM_INDEX["mu"]] = 1.05
    ay = np.zeros(1000)
    ay[300:500] = 3.0
    ay[700] = 9.0  # a spike, averaged over 21 samples: 0.43 m/s²
    said = hints([(0.01, {"ay": ay, "r": np.zeros(1000)})], p)
    assert set(said) == {"mu"}
    assert f"{100 * 3.0 / (1.05 * 9.81):.0f} % of μ·g" in said["mu"]
    gentle = hints([(0.01, {"ay": 0.5 * np.sin(np.linspace(0, 20, 1000))})], p)
    assert set(gentle) == {"mu", "C_af", "C_ar"} and "0.5 m/s²" in gentle["C_af"]
    ay[300:500] = 0.8 * 1.05 * 9.81
    assert hints([(0.01, {"ay": ay})], p) == {}
    assert hints([(0.01, {"r": ay})], p) == {}  # no ay channel: nothing known


def test_two_parameters_that_trade_off_are_not_determined_each():
    """A valley along a combination of k and c: each alone is pinned (the profile with the
    other held rises at ±1 % of its box), but with the other re-fitted k moves over more
    than its whole box (correlation 0.99989); the closed forms √(2ΔJ/H_kk) and
    √(2ΔJ·(H⁻¹)_kk) both hold, and k is reported not determined, naming c."""
    delta_j = REL_RISE * J_BEST
    a = 2 * delta_j / 0.06**2  # k alone: ±0.06 decades (1 % of 6)
    b = 2 * delta_j / 0.02**2  # c alone: ±0.02 decades (1 % of 2)
    rho = math.sqrt(1 - 1 / (400 * a))  # (H⁻¹)_kk = 400: k jointly ±4 decades
    hessian = np.diag([a, 0.0, b])
    hessian[0, 2] = hessian[2, 0] = -rho * math.sqrt(a * b)
    k, c = identify(quadratic(hessian), SPACE, X_BEST, ["k", "c"]).parameters
    cov = np.linalg.inv(hessian[np.ix_([0, 2], [0, 2])])
    assert cov[0, 0] == pytest.approx(400.0)
    assert k.half_width == pytest.approx(0.06, rel=1e-6) and k.limits == "both"
    assert k.joint_half_width == pytest.approx(4.0, rel=1e-4)
    assert k.correlations["c"] == pytest.approx(rho, rel=1e-6)
    assert not k.determined and not c.determined
    assert "it trades off with c (correlation +1.00)" in k.describe()


def test_tune_ends_with_the_identifiability_of_the_tuned_model_parameters(small, tmp_path):
    """kftune tune with a tuned stiffness prints its verdict after the held-out lines and
    records it (identifiability) in the tuned file and --json, against the file's own
    value and start; a noise-only tuning prints and records none."""
    from conftest import run_cli

    out = tmp_path / "tuned.json"
    joint = ("--tune-model", "C_af=20000:400000")
    res = run_cli("tune", str(small), "-n", "12", "-o", str(out), *joint)
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    ident = doc["identifiability"]
    rec = ident["parameters"]["C_af"]
    assert list(ident["parameters"]) == ["C_af"]
    assert ident["n_evals"] <= 1 + MAX_EVALS_PER_PARAMETER
    assert rec["value"] == doc["params"]["C_af"] == doc["model_params"]["C_af"]["value"]
    assert rec["start"] == doc["model_params"]["C_af"]["start"]
    assert (rec["low"], rec["high"]) == (20000.0, 400000.0)
    lines = res.stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("tuned model parameters"))
    assert lines[at + 1].startswith("  C_af = ")
    assert at < next(i for i, line in enumerate(lines) if line.startswith("tuned parameters"))
    assert "profiling the cost around the tuned point for C_af" in res.stderr
    as_json = run_cli(
        "tune", str(small), "-n", "12", "--json", "-o", str(tmp_path / "j.json"), *joint
    )
    assert json.loads(as_json.stdout)["identifiability"] == ident  # the same run again
    assert "profiling" not in as_json.stderr
    noise = run_cli("tune", str(small), "-n", "4", "-o", str(tmp_path / "noise.json"))
    assert "identifiability" not in json.loads((tmp_path / "noise.json").read_text())
    assert "tuned model parameters" not in noise.stdout and "profiling" not in noise.stderr


def test_the_record_reads_back_from_its_json_form_and_a_damaged_one_is_named():
    """from_dict inverts to_dict through strict JSON (a failed profile point included),
    giving the same lines; a missing key is named with its parameter."""
    from kftune.tuning.identify import Identifiability

    def cost(points: np.ndarray) -> np.ndarray:
        j = quadratic(HESSIAN)(points)
        return np.where(search_t(points)[:, 0] > 1.0, np.inf, j)  # k above 10 diverges

    out = identify(cost, SPACE, X_BEST, ["k", "b", "c"], start={"k": 0.2}, reasons={"c": "idle"})
    doc = json.loads(json.dumps(out.to_dict(), allow_nan=False))
    back = Identifiability.from_dict(doc)
    assert back.to_dict() == out.to_dict() and back.lines() == out.lines()
    assert any(j == math.inf for _, j in back.parameters[0].profile)
    del doc["parameters"]["b"]["profile"]
    with pytest.raises(ValueError, match="parameter 'b': no 'profile'"):
        Identifiability.from_dict(doc)
    with pytest.raises(ValueError, match="no 'parameters'"):
        Identifiability.from_dict({})


@pytest.mark.slow
def test_compare_reports_the_identifiability_of_each_tuned_method_with_its_figure(small, tmp_path):
    """compare with a tuned model parameter records each tuned method's identifiability
    (not the manual point's), and the report shows its lines and the profile figure;
    kftune report rebuilds the same section from results.json, and names a damaged
    record instead of failing."""
    from conftest import run_cli

    out = tmp_path / "report"
    res = run_cli(
        "compare", str(small), "--methods", "manual", "trbo", "--budget", "trbo=20",
        "--tune-model", "C_af=20000:400000", "-o", str(out), "--quiet",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads((out / "results.json").read_text())
    by_key = {m["key"]: m for m in doc["methods"]}
    assert "identifiability" not in by_key["manual"]["extra"]
    rec = by_key["trbo"]["extra"]["identifiability"]["parameters"]["C_af"]
    assert rec["value"] == by_key["trbo"]["params"]["C_af"] and rec["start"] == 55600.0
    report = (out / "report.md").read_text()
    section = report[report.index("## Identifiability") :].split("\n## ")[0]
    assert "- C_af = " in section and "figures/identifiability.png" in section
    assert (out / "figures" / "identifiability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    again = tmp_path / "again"
    assert run_cli("report", str(out), "-o", str(again)).returncode == 0
    assert section in (again / "report.md").read_text()
    del by_key["trbo"]["extra"]["identifiability"]["parameters"]["C_af"]["profile"]
    (out / "results.json").write_text(json.dumps(doc))
    damaged = run_cli("report", str(out), "-o", str(tmp_path / "damaged"))
    assert damaged.returncode == 0, damaged.stderr
    text = (tmp_path / "damaged" / "report.md").read_text()
    assert "TR-BO: the record is damaged (parameter 'C_af': no 'profile')" in text
    assert "figures/identifiability.png" not in text


def test_a_negative_cost_takes_its_rise_relative_to_its_magnitude():
    """A cost that can be negative (an innovation log-likelihood): ΔJ is 1 % of |J*|, and
    the range is √(2·ΔJ/H_ii) as for a positive one."""
    offset = -5.0 - J_BEST  # J* = −5

    def cost(points: np.ndarray) -> np.ndarray:
        return quadratic(HESSIAN)(points) + offset

    (k,) = identify(cost, SPACE, X_BEST, ["k"]).parameters
    assert k.cost == pytest.approx(-5.0) and k.delta_j == pytest.approx(0.05)
    half = math.sqrt(2 * 0.05 / HESSIAN[0, 0])
    assert math.log10(k.range_high / k.value) == pytest.approx(half, rel=1e-6)
    from kftune.tuning.identify import rise_pct

    assert rise_pct(-4.95, -5.0) == pytest.approx(1.0)  # a rise, in % of |J*|
    assert rise_pct(2.02, 2.0) == pytest.approx(1.0) and rise_pct(0.5, 0.0) == 50.0


@pytest.mark.parametrize("shift", [0.0, 1e3, -1e3])
def test_a_mean_log_likelihood_ends_its_range_at_the_likelihood_ratio_rise(shift):
    """For a mean negative log-likelihood over N samples the range ends where N·ΔJ is
    χ²₁(0.95)/2 (scipy's quantile), whatever constant the units add to J: the half-width
    along k is √(2ΔJ/H_kk) for J* = 2, 1002 and −998 alike; the NRMSE kinds keep the
    relative rise (no absolute one)."""
    from scipy.stats import chi2

    from kftune.tuning.identify import rise_of

    n = 4000
    delta_j = rise_of("nlpd", n)
    assert delta_j == pytest.approx(chi2.ppf(0.95, df=1) / 2 / n, rel=1e-12)
    assert rise_of("pem", n) == delta_j
    assert rise_of("nrmse", n) is None and rise_of("crps", n) is None

    def cost(points: np.ndarray) -> np.ndarray:
        return quadratic(HESSIAN)(points) + shift

    out = identify(cost, SPACE, X_BEST, ["k"], abs_rise=delta_j, n_scored=n)
    (k,) = out.parameters
    assert k.delta_j == delta_j and out.abs_rise == delta_j and out.n_scored == n
    half = math.sqrt(2 * delta_j / HESSIAN[0, 0])
    assert math.log10(k.range_high / k.value) == pytest.approx(half, rel=1e-6)
    assert "N = 4000 scored samples" in out.lines()[0]
    back = type(out).from_dict(json.loads(json.dumps(out.to_dict(), allow_nan=False)))
    assert back.abs_rise == delta_j and back.n_scored == n


def test_an_indefinite_curvature_matrix_leaves_no_parameter_determined():
    """Each profile alone is a narrow valley (positive H_kk, H_cc), but the cross term
    makes H indefinite (a saddle): the joint check cannot be made, so neither parameter
    is called determined, and the text says why."""
    a, b = 200.0, 2000.0
    hessian = np.diag([a, 0.0, b])
    hessian[0, 2] = hessian[2, 0] = 2.0 * math.sqrt(a * b)  # correlation 2: a saddle
    assert np.linalg.eigvalsh(hessian[np.ix_([0, 2], [0, 2])]).min() < 0
    k, c = identify(quadratic(hessian), SPACE, X_BEST, ["k", "c"]).parameters
    for rec in (k, c):
        assert rec.limits == "both" and rec.share < NOT_DETERMINED_SHARE
        assert not rec.determined and rec.joint_half_width is None
        assert "not checked jointly: the curvature matrix is not positive definite" in (
            rec.describe()
        )


def test_a_profile_point_below_the_tuned_one_leaves_the_parameter_not_assessed():
    """A narrow valley along b whose bottom lies 0.08 beside the tuned point: the profile
    closes on both sides within 1 % of the box, but the cost is lower at a profile point,
    so no range and no verdict are given: "not assessed", naming the lower point."""
    t_best = search_t(X_BEST)[0] + np.array([0.0, 0.08, 0.0])
    (b,) = identify(quadratic(HESSIAN, t_best), SPACE, X_BEST, ["b"]).parameters
    assert b.limits == "both" and b.share < NOT_DETERMINED_SHARE
    assert b.better is not None and b.better[1] < b.cost
    text = b.describe()
    assert not b.determined
    assert "not assessed: the search had not converged along b (the cost is lower at b =" in text
    assert "determined" not in text and " … " not in text
    # the drop in the units of the rise (a share of J* means nothing for a log-likelihood)
    assert f"by {b.cost - b.better[1]:.3g}: " in text and "× the rise that ends a range" in text
    assert "%" not in text


def test_a_model_files_hints_cannot_fail_tune_nor_flood_its_text():
    """param_hints is a model file's code: an exception becomes one line naming its type,
    a long text is cut, names that are not tuned (or not names) are ignored."""
    from types import SimpleNamespace

    from kftune.tuning.identify import HINT_CHARS, _hints

    def model(hook):
        return SimpleNamespace(param_hints=hook, input_names=(), measurement_names=())

    def problem(hook):
        return SimpleNamespace(model=model(hook), manoeuvres=[], params_at=lambda x: x)

    def raises(runs, params):
        raise ZeroDivisionError("secret /home/user/model.py line 3")

    said = _hints(problem(raises), np.zeros(1), ["C_af"])
    assert said == {"C_af": "hint failed: ZeroDivisionError"}
    long = _hints(
        problem(lambda runs, p: {"C_af": "x" * 5000, "mu": "not tuned", 3: "odd"}),
        np.zeros(1),
        ["C_af"],
    )
    assert list(long) == ["C_af"] and len(long["C_af"]) < HINT_CHARS + 40
    assert _hints(problem(lambda runs, p: {"C_af": "short"}), np.zeros(1), ["C_af"]) == {
        "C_af": "short"
    }


def test_the_reports_range_line_sits_at_the_recorded_rise():
    """The figure's dotted line: a relative record's rise in %, an absolute one (a mean
    log-likelihood) as its share of |J*| (0.01 over J* = −2: 0.5 %)."""
    from kftune.report.plots import _range_rise_pct

    assert _range_rise_pct({"rel_rise": 0.01, "parameters": {"k": {"cost": 2.0}}}) == 1.0
    rec = {"rel_rise": 0.01, "abs_rise": 0.01, "parameters": {"k": {"cost": -2.0}}}
    assert _range_rise_pct(rec) == pytest.approx(0.5)
