"""The tuning problem: parameter mapping, cost assembly, parallel = serial, divergence."""

from __future__ import annotations

import math

import numpy as np
import pytest

import kftune
from kftune.data import default_dataset
from kftune.errors import ConfigError, DataError, FilterDivergedError
from kftune.experiment import MANUAL_Q, manual_point
from kftune.filters import UKFSettings
from kftune.models import get_model
from kftune.tuning.cost import CostSpec
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.pool import balanced_chunks
from kftune.tuning.problem import TuningProblem, assess
from kftune.tuning.runs import channel_estimate, default_r0
from single_track import run_ukf


@pytest.fixture(scope="module")
def ds():
    return default_dataset()


def test_default_space_is_the_papers(ds):
    space = NoiseParameterization().space
    assert space.names == ("q_vx", "q_vy", "q_r")
    assert all(p.low == 1e-10 and p.high == 1.0 and p.scale == "log10" for p in space)


def test_decode_optional_parameters():
    par = NoiseParameterization(tune_r_scale=True, tune_sigma_points=True)
    assert par.space.names == (
        "q_vx",
        "q_vy",
        "q_r",
        "r_scale",
        "ukf_alpha",
        "ukf_beta",
        "ukf_kappa",
    )
    q, r, s = par.decode([1e-3, 2e-3, 3e-3, 10.0, 0.5, 2.0, 1.0], np.array([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(q, [1e-3, 2e-3, 3e-3])
    np.testing.assert_array_equal(r, [10.0, 20.0, 30.0])
    assert s == UKFSettings(0.5, 2.0, 1.0)
    with pytest.raises(ValueError, match="7 values"):
        par.decode([1e-3, 1e-3, 1e-3], np.ones(3))


def test_any_model_size_with_per_parameter_boxes_and_a_tuned_r_diagonal():
    """Q named after the model's states (any n), R's diagonal as factors on R₀ named after
    its measurements, one log10 box per parameter."""
    par = NoiseParameterization(
        states=("px", "py", "v", "psi", "omega"),
        measurements=("px", "py"),
        q_bounds={"q_omega": (1e-6, 1e-1)},
        tune_r="diag",
        r_scale_bounds=(0.1, 10.0),
    )
    space = par.space
    assert space.names == ("q_px", "q_py", "q_v", "q_psi", "q_omega", "r_px_scale", "r_py_scale")
    assert [(p.low, p.high, p.scale) for p in space][3:] == [
        (1e-10, 1.0, "log10"),
        (1e-6, 1e-1, "log10"),
        (0.1, 10.0, "log10"),
        (0.1, 10.0, "log10"),
    ]
    q, r, _ = par.decode([1e-5, 2e-5, 3e-5, 4e-5, 5e-3, 0.5, 4.0], np.array([2.0, 3.0]))
    np.testing.assert_array_equal(q, [1e-5, 2e-5, 3e-5, 4e-5, 5e-3])
    np.testing.assert_array_equal(r, [1.0, 12.0])
    assert par.to_dict()["states"] == ["px", "py", "v", "psi", "omega"]
    assert "states" not in NoiseParameterization().to_dict()  # old study fingerprints hold
    with pytest.raises(ValueError, match=r"q_bounds names \['q_vz'\] are not parameters"):
        NoiseParameterization(q_bounds={"q_vz": (1e-6, 1.0)})
    with pytest.raises(ValueError, match="tune_r must be one of"):
        NoiseParameterization(tune_r="full")


def test_cost_matches_paper_formula_computed_directly(ds):
    """J assembled by the problem = Eq. 14–15 written out here from raw filter runs."""
    train = ds.train[:3]
    q = np.array([1e-4, 1e-6, 1e-3])
    problem = TuningProblem(train, ds.vehicle, ds.r_default)
    nr = {"beta": [], "r": [], "ay": []}
    err = {c: [] for c in nr}  # (error, reference) per manoeuvre
    n = []
    for m in train:
        res = run_ukf(m.u, m.z, m.dt, ds.vehicle, q, ds.r_default)
        est = {
            "beta": np.arctan2(res.x[:, 1], res.x[:, 0]),
            "r": res.z_hat[:, 2],
            "ay": res.z_hat[:, 1],
        }
        ref = {"beta": m.beta_ref, "r": m.r, "ay": m.ay}
        for c in nr:
            nr[c].append(np.sqrt(np.mean((est[c] - ref[c]) ** 2)) / np.max(np.abs(ref[c])))
            err[c].append((est[c] - ref[c], ref[c]))
        n.append(m.n)
    n = np.array(n)
    e = {c: np.sqrt(np.sum(np.array(v) ** 2 * n) / n.sum()) for c, v in nr.items()}
    expected = 5 * e["beta"] + e["r"] + e["ay"]
    ev = problem.evaluate(q)
    assert ev.cost == pytest.approx(expected, rel=1e-12)
    assert ev.pooled == pytest.approx(e, rel=1e-12)
    # normalised over the whole set: the RMSE over every sample over the largest |X|
    e_ds = {
        c: np.sqrt(np.mean(np.concatenate([a for a, _ in v]) ** 2))
        / np.max(np.abs(np.concatenate([b for _, b in v])))
        for c, v in err.items()
    }
    by_set = TuningProblem(train, ds.vehicle, ds.r_default, cost=CostSpec(normalise="dataset"))
    ev_ds = by_set.evaluate(q)
    assert ev_ds.pooled == pytest.approx(e_ds, rel=1e-12)
    assert ev_ds.cost == pytest.approx(5 * e_ds["beta"] + e_ds["r"] + e_ds["ay"], rel=1e-12)
    nis = np.concatenate([run_ukf(m.u, m.z, m.dt, ds.vehicle, q, ds.r_default).nis for m in train])
    assert ev.mean_nis == pytest.approx(nis.mean(), rel=1e-12)
    nis_problem = TuningProblem(train, ds.vehicle, ds.r_default, cost=CostSpec(kind="nis"))
    assert nis_problem(q) == pytest.approx(abs(math.log(nis.mean() / 3)), rel=1e-12)


@pytest.mark.slow
def test_parallel_workers_give_the_serial_cost(ds):
    q = [1e-5, 1e-7, 1e-2]
    serial = TuningProblem(ds.train, ds.vehicle, ds.r_default).evaluate(q)
    with TuningProblem(ds.train, ds.vehicle, ds.r_default, workers=2) as par:
        parallel = par.evaluate(q)
        assert par.evaluate(q).cost == parallel.cost  # the pool is reused
    assert parallel.cost == serial.cost
    assert [s.name for s in parallel.scores] == [m.name for m in ds.train]


def test_balanced_chunks_cover_everything_once():
    chunks = balanced_chunks([5, 1, 1, 1, 1, 1], 2)
    assert sorted(i for c in chunks for i in c) == list(range(6))
    assert {0} in [set(c) for c in chunks]  # the long one alone, the short ones together


def test_divergence_is_a_failed_evaluation_not_a_crash(ds):
    """A filter that runs away for some parameters (a Vy process noise of 1e2 or more lets
    the sideslip estimate leave ±60°) makes those evaluations fail; the tuning run carries
    on and finds working ones."""
    wide = NoiseParameterization(q_bounds=(1e-10, 1e4))
    problem = TuningProblem(ds.train[:1], ds.vehicle, ds.r_default, parameterization=wide)
    with pytest.raises(FilterDivergedError, match="diverged on manoeuvre 'train-01"):
        problem([1e-10, 1e4, 1e-10])
    res = kftune.minimize(problem, problem.space, method="random", budget=12, seed=1)
    assert res.n_evals == 12
    assert 0 < res.n_failed < 12
    failed = [r for r in res.history if not r.ok]
    assert all("diverged" in r.reason for r in failed)
    assert res.fun is not None and math.isfinite(res.fun)


def test_bad_problem_settings(ds):
    with pytest.raises(ConfigError, match="at least one manoeuvre"):
        TuningProblem([], ds.vehicle, ds.r_default)
    with pytest.raises(ConfigError, match="r0"):
        TuningProblem(ds.train, ds.vehicle, [1.0, -1.0, 1.0])
    with pytest.raises(ConfigError, match="workers"):
        TuningProblem(ds.train, ds.vehicle, ds.r_default, workers=0)


def test_manual_point_and_assess(ds):
    par = NoiseParameterization(tune_r_scale=True)
    x = manual_point(par)
    np.testing.assert_array_equal(x, [*MANUAL_Q, 1.0])
    problem = TuningProblem(ds.test[:2], ds.vehicle, ds.r_default, parameterization=par)
    metrics, results = assess(problem, x, ds.test[:2])
    m = ds.test[0]
    err = np.degrees(results[m.name].output("beta") - m.beta_ref)
    assert metrics[m.name]["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert metrics[m.name]["mae"] == pytest.approx(np.max(np.abs(err)))
    ay_err = results[m.name].z_hat[:, 1] - m.ay
    assert metrics[m.name]["rmse_ay"] == pytest.approx(np.sqrt(np.mean(ay_err**2)))


def test_burn_in_leaves_the_first_seconds_out_of_cost_and_kpis(ds):
    m = ds.train[2]
    q = np.array([1e-4, 1e-6, 1e-3])
    problem = TuningProblem([m], ds.vehicle, ds.r_default, burn_in=1.0)
    res = run_ukf(m.u, m.z, m.dt, ds.vehicle, q, ds.r_default)
    k0 = round(1.0 / m.dt)  # the sample at t0 + 1 s is the first one scored
    assert m.t[k0] - m.t[0] == pytest.approx(1.0)
    beta = np.arctan2(res.x[k0:, 1], res.x[k0:, 0])
    e_beta = np.sqrt(np.mean((beta - m.beta_ref[k0:]) ** 2)) / np.max(np.abs(m.beta_ref[k0:]))
    e_r = np.sqrt(np.mean((res.z_hat[k0:, 2] - m.r[k0:]) ** 2)) / np.max(np.abs(m.r[k0:]))
    e_ay = np.sqrt(np.mean((res.z_hat[k0:, 1] - m.ay[k0:]) ** 2)) / np.max(np.abs(m.ay[k0:]))
    assert problem(q) == pytest.approx(5 * e_beta + e_r + e_ay, rel=1e-12)
    metrics, _ = assess(problem, q, [m])
    err = np.degrees(beta - m.beta_ref[k0:])
    assert metrics[m.name]["mae"] == pytest.approx(np.max(np.abs(err)), rel=1e-12)
    with pytest.raises(ConfigError, match="shorter than the burn-in"):
        TuningProblem([m], ds.vehicle, ds.r_default, burn_in=1e3)


def test_prior_estimate_cannot_copy_the_measurement(ds):
    """With a huge yaw-rate process noise the posterior yaw rate follows the gyro, so its
    error against the gyro falls far below the gyro's own noise (0.2 deg/s in the bundled
    set); the one-step prediction cannot, its error stays at least at the noise level."""
    m = ds.train[4]
    q = np.array([1e-6, 1e-6, 1.0])
    post = TuningProblem([m], ds.vehicle, ds.r_default)
    prior = TuningProblem([m], ds.vehicle, ds.r_default, cost=CostSpec(estimate="prior"))
    mp, _ = assess(post, q, [m])
    mq, results = assess(prior, q, [m])
    assert mp[m.name]["rmse_r"] < 0.05  # deg/s, copying
    assert mq[m.name]["rmse_r"] > 0.18  # deg/s, about the gyro noise
    res = results[m.name]
    est, _ = channel_estimate(m, res, "r", "prior")
    np.testing.assert_allclose(est, m.r - res.innovation[:, 2], rtol=0, atol=0)


@pytest.mark.parametrize("model", ["single-track", "single-track-ay-bias"])
def test_non_positive_speed_is_refused_naming_manoeuvre_and_row(ds, model):
    m = ds.train[2]
    vx = m.vx.copy()
    vx[17] = 0.0
    # vx > 0 is the single-track models' assumption: the data load, the models refuse them
    stopped = m.replace(vx=vx)
    r0 = default_r0(get_model(model), ds)
    t17 = f"{m.t[17]:.4g}"
    where = rf"^manoeuvre 'train-03-j-turn', channel 'vx', sample 17 \(t = {t17} s\): model '"
    with pytest.raises(DataError, match=where + model + r"' refuses these data: Vx = 0 m/s;"):
        TuningProblem([stopped], ds.vehicle, r0, model=model)


def test_fingerprint_tells_objectives_apart(ds):
    a = TuningProblem(ds.train[:2], ds.vehicle, ds.r_default).fingerprint()
    assert a == TuningProblem(ds.train[:2], ds.vehicle, ds.r_default).fingerprint()
    others = [
        TuningProblem(ds.train[1:3], ds.vehicle, ds.r_default),
        TuningProblem(ds.train[:2], ds.vehicle.replace(mu=0.9), ds.r_default),
        TuningProblem(ds.train[:2], ds.vehicle, ds.r_default * 2),
        TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, cost=CostSpec(kind="nis")),
        TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, burn_in=0.5),
        TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, cost=CostSpec(normalise="dataset")),
    ]
    assert len({a["sha256"], *(p.fingerprint()["sha256"] for p in others)}) == 7


def test_a_problem_over_another_model_names_its_parameters_and_checks_its_channels(ds):
    """The tuned parameters follow the model; cost channels and R₀ are checked against it
    before anything runs (no filter is compiled here)."""
    from kftune.models import get_model
    from kftune.tuning.runs import default_r0

    bias = get_model("single-track-ay-bias")
    r0 = default_r0(bias, ds.r_default)
    np.testing.assert_array_equal(r0, ds.r_default)  # same measurements: the dataset's R₀
    problem = TuningProblem(ds.train[:1], ds.vehicle, r0, model="single-track-ay-bias")
    assert problem.space.names == ("q_vx", "q_vy", "q_r", "q_b_ay")
    assert problem.model is bias and problem.filter == "ukf"
    assert (
        problem.fingerprint()["sha256"]
        != TuningProblem(ds.train[:1], ds.vehicle, ds.r_default).fingerprint()["sha256"]
    )
    with pytest.raises(ConfigError, match=r"unknown cost channel 'vz'"):
        TuningProblem(ds.train[:1], ds.vehicle, r0, model=bias, cost=CostSpec(weights={"vz": 1.0}))
    # a state that is not measured is an output, scored against its reference <state>_ref
    with pytest.raises(DataError, match=r"needs a reference channel vy_ref, which manoeuvre"):
        TuningProblem(ds.train[:1], ds.vehicle, r0, model=bias, cost=CostSpec(weights={"vy": 1.0}))
    with pytest.raises(ConfigError, match=r"for states \['vx', 'vy', 'r'\]"):
        TuningProblem(
            ds.train[:1], ds.vehicle, r0, model=bias, parameterization=NoiseParameterization()
        )
    ctrv = get_model("ctrv")
    with pytest.raises(ConfigError, match=r"no measurement-noise variance for 'px'.*r0 ="):
        default_r0(ctrv, ds.r_default)
    np.testing.assert_array_equal(default_r0(ctrv, ds.r_default, {"px": 1.0, "py": 2.0}), [1, 2])
    with pytest.raises(ConfigError, match=r"r0 names \['vz'\] are not measurements"):
        default_r0(bias, ds.r_default, {"vz": 1.0})
    with pytest.raises(DataError, match=r"model 'ctrv' needs measurement channel px, which"):
        TuningProblem(ds.train[:1], ds.vehicle, [1.0, 1.0], model=ctrv, cost=CostSpec(kind="nis"))
