"""Model parameters tuned together with the noise: the search space, per-point model
parameters in every run path, validation against the model, the covariance scale, and
recovery of known cornering stiffnesses."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import kftune
from conftest import completed_trials as _completed
from conftest import run_cli, run_killed_after
from kftune.data import default_dataset, open_dataset, save_dataset
from kftune.errors import ConfigError
from kftune.experiment import MANUAL_Q, NOISE_STAGE_SHARE, manual_point
from kftune.models import get_model
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem, assess
from kftune.tuning.runs import filter_spec

#: Short manoeuvres of the bundled set near 8–10 m/s² lateral acceleration.
NAMES = ("train-03-j-turn", "train-07-lane-change", "train-08-lane-change")
STIFFNESS = {"C_af": (2e4, 4e5), "C_ar": (2e4, 4e5)}


@pytest.fixture(scope="module")
def ds():
    return default_dataset()


@pytest.fixture(scope="module")
def short(ds):
    return [ds[n] for n in NAMES]


def test_space_names_scales_and_values():
    par = NoiseParameterization(
        tune_r_scale=True,
        model_bounds={"C_af": (2e4, 4e5), "mu": (0.4, 1.6), "h": (0.0, 1.0)},
        model_scales={"mu": "linear"},
    )
    assert par.model_names == ("C_af", "mu", "h")
    assert par.space.names == ("q_vx", "q_vy", "q_r", "r_scale", "C_af", "mu", "h")
    scales = {p.name: p.scale for p in par.space}
    # log10 where the box is positive, unless asked; linear where it reaches 0
    assert (scales["C_af"], scales["mu"], scales["h"]) == ("log10", "linear", "linear")
    x = [1e-6, 1e-4, 1e-6, 2.0, 7e4, 0.9, 0.5]
    assert par.model_values(x) == {"C_af": 7e4, "mu": 0.9, "h": 0.5}
    q, r, _ = par.decode(x, np.ones(3))
    np.testing.assert_array_equal(q, [1e-6, 1e-4, 1e-6])
    np.testing.assert_array_equal(r, [2.0, 2.0, 2.0])
    assert NoiseParameterization().model_values([1e-6, 1e-4, 1e-6]) == {}


def test_manual_point_starts_at_the_recorded_model(ds, short):
    par = NoiseParameterization(model_bounds=STIFFNESS)
    with pytest.raises(ValueError, match="no start value"):
        manual_point(par)
    problem = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)
    x = manual_point(problem.parameterization)
    np.testing.assert_array_equal(x, [*MANUAL_Q, ds.vehicle.C_af, ds.vehicle.C_ar])
    # at the recorded model the joint problem is the noise-only one
    noise_only = TuningProblem(short, ds.vehicle, ds.r_default)
    assert problem(x) == noise_only(np.array(MANUAL_Q))


@pytest.mark.parametrize(
    ("bounds", "scales", "start", "match"),
    [
        ({"C_af": (4e5, 2e4)}, {}, {}, "'C_af'.*low < high"),
        ({"C_af": (2e4, float("inf"))}, {}, {}, "'C_af'.*finite"),
        ({"h": (0.0, 1.0)}, {"h": "log10"}, {}, "'h'.*positive lower bound"),
        ({"mu": (0.4, 1.6)}, {"mu": "log2"}, {}, "'mu'.*'log10' or 'linear'"),
        ({"mu": (0.4, 1.6)}, {"C_af": "linear"}, {}, "'C_af', which is not tuned"),
        ({"mu": (0.4, 0.6)}, {}, {"mu": 1.05}, "'mu'.*1.05 lies outside its box"),
    ],
)
def test_bad_model_boxes_are_refused_naming_the_parameter(bounds, scales, start, match):
    with pytest.raises(ValueError, match=match):
        NoiseParameterization(model_bounds=bounds, model_scales=scales, model_start=start)


@pytest.mark.parametrize(
    ("bounds", "match"),
    [
        ({"C_f": (2e4, 4e5)}, r"'C_f' is not a parameter of model 'single-track'.*'C_af'"),
        ({"track_f": (1.0, 2.0)}, r"'track_f' is not a parameter.*lumps each axle"),
        ({"steering_ratio": (10.0, 20.0)}, r"'steering_ratio'.*hand-wheel"),
        ({"C_af": (2e4, 4e6)}, r"'C_af'.*\[20000, 4e\+06\] N/rad.*\[1000, 2e\+06\] N/rad"),
        ({"mu": (0.4, 2.5)}, r"'mu'.*plausible range \[0.05, 2\]"),
    ],
)
def test_boxes_the_model_cannot_take_are_refused(ds, short, bounds, match):
    par = NoiseParameterization(model_bounds=bounds)
    with pytest.raises(ConfigError, match=match):
        TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)


def test_the_recorded_value_outside_the_box_is_refused(ds, short):
    par = NoiseParameterization(model_bounds={"C_af": (6e4, 4e5)})  # recorded: 55.6 kN/rad
    with pytest.raises(ConfigError, match=r"'C_af'.*recorded value 55600.*widen"):
        TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)


@pytest.mark.parametrize(("model", "filt"), [("single-track", "ukf"), ("single-track", "ekf")])
@pytest.mark.slow
def test_a_point_runs_the_model_it_names_on_every_path(ds, short, model, filt):
    """A joint point's cost equals the noise-only cost on a vehicle that has those values,
    serially, in batches (grouped by model values), per manoeuvre and in worker processes;
    for the EKF through the parameter vector of the generic kernel."""
    par = NoiseParameterization(model_bounds={"C_af": (2e4, 4e5), "mu": (0.4, 1.6)})
    joint = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par, filter=filt)
    q = np.array([1e-5, 1e-3, 1e-5])
    points = np.array([[*q, 4e4, 0.8], [*q, 8e4, 1.2], [*(q * 3), 4e4, 0.8]])
    reference = [
        TuningProblem(short, ds.vehicle.replace(C_af=x[3], mu=x[4]), ds.r_default, filter=filt)(
            x[:3]
        )
        for x in points
    ]
    assert reference[0] != reference[1]  # the model parameters matter
    serial = [joint(x) for x in points]
    np.testing.assert_allclose(serial, reference, rtol=1e-12)
    batch = [e.cost for e in joint.evaluate_batch(points)]
    np.testing.assert_allclose(batch, reference, rtol=1e-12)
    shares = joint.score_manoeuvres(points[1], range(len(short)))
    assert joint._pool_scores(shares).cost == pytest.approx(reference[1], rel=1e-12)
    assert joint.vehicle_at(points[1]).C_af == 8e4
    assert joint.params_at(points[1])[get_model(model).param_names.index("mu")] == 1.2
    if filt == "ukf":
        with TuningProblem(
            short, ds.vehicle, ds.r_default, parameterization=par, workers=2
        ) as pooled:
            assert pooled(points[0]) == pytest.approx(reference[0], rel=1e-12)


@pytest.mark.slow
def test_msp_cost_predicts_with_the_points_vehicle(ds, short):
    from kftune.tuning.cost import CostSpec

    spec = CostSpec(kind="msp", weights={"ay": 1.0, "r": 1.0})
    par = NoiseParameterization(model_bounds={"C_ar": (2e4, 4e5)})
    joint = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par, cost=spec)
    x = np.array([1e-5, 1e-3, 1e-5, 1.2e5])
    ref = TuningProblem(short, ds.vehicle.replace(C_ar=1.2e5), ds.r_default, cost=spec)
    assert joint(x) == pytest.approx(ref(x[:3]), rel=1e-12)


def test_covariance_scale_scales_an_ekfs_covariances_and_keeps_its_estimate(ds, short):
    """c·Q, c·R, c·P0: the Kalman gain is homogeneous of degree 0 in (P, Q, R), so the EKF's
    states stay and every posterior variance is c times as large."""
    m = short[0]
    fs = filter_spec("single-track", "ekf", ds.vehicle)
    q, r = np.array([1e-5, 1e-3, 1e-5]), np.asarray(ds.r_default, float)
    from kftune.filters import UKFSettings

    base = fs.run(m, q, r, UKFSettings())
    scaled = fs.run(m, q, r, UKFSettings(), cov_scale=4.0)
    np.testing.assert_allclose(scaled.x, base.x, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(scaled.P_diag, 4.0 * base.P_diag, rtol=1e-6)
    problem = TuningProblem(short, ds.vehicle, ds.r_default, filter="ekf")
    problem.cov_scale = 4.0
    np.testing.assert_allclose(problem.run(q, m).P_diag, scaled.P_diag, rtol=1e-12)
    with pytest.raises(ValueError, match="cov_scale"):
        fs.run(m, q, r, UKFSettings(), cov_scale=0.0)


def _noise_only_fingerprint(problem: TuningProblem) -> str:
    """The SHA-256 of a study of the paper's pair as it has always been made: the arrays
    t, u, z, beta_ref of every manoeuvre after its name, then the described objective."""
    h = hashlib.sha256()
    for m in problem.manoeuvres:
        h.update(m.name.encode())
        for a in (m.t, m.u, m.z, m.beta_ref):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    par = problem.parameterization
    s = par.default_settings
    described = {
        "vehicle": problem.vehicle.to_dict(),
        "r0": problem.r0.tolist(),
        "cost": {
            "kind": "nrmse",
            "weights": {"beta": 5.0, "r": 1.0, "ay": 1.0},
            "estimate": "posterior",
        },
        "parameterization": {
            "names": ["q_vx", "q_vy", "q_r"],
            "space": par.space.to_dict(),
            "sigma_points": {"alpha": s.alpha, "beta": s.beta, "kappa": s.kappa},
        },
        "burn_in": 0.0,
    }
    h.update(json.dumps(described, sort_keys=True).encode())
    return h.hexdigest()


def test_a_noise_only_study_keeps_its_fingerprint_and_a_joint_one_differs(ds, short):
    noise_only = TuningProblem(short, ds.vehicle, ds.r_default)
    assert noise_only.fingerprint()["sha256"] == _noise_only_fingerprint(noise_only)
    par = NoiseParameterization(model_bounds=STIFFNESS)
    joint = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)
    other_box = TuningProblem(
        short,
        ds.vehicle,
        ds.r_default,
        parameterization=NoiseParameterization(model_bounds={**STIFFNESS, "C_ar": (3e4, 4e5)}),
    )
    prints = {p.fingerprint()["sha256"] for p in (noise_only, joint, other_box)}
    assert len(prints) == 3  # the model box is part of the objective
    assert "model parameters C_af, C_ar tuned" in joint.fingerprint()["summary"]


@pytest.mark.slow
def test_joint_tuning_recovers_known_cornering_stiffnesses(ds, short):
    """The bundled data come from a plant whose single-track stiffnesses are known (the
    bundled vehicle's C_af, C_ar); a filter handed C_af ×0.7 and C_ar ×1.4 finds them again
    with Q. Measured (TR-BO, 100 evaluations, these three manoeuvres, seeds 0–4): within
    7.5 % of the true values (ratios 0.926–1.008); asserted within 10 %."""
    true = ds.vehicle
    wrong = true.replace(C_af=0.7 * true.C_af, C_ar=1.4 * true.C_ar)
    par = NoiseParameterization(model_bounds=STIFFNESS)
    problem = TuningProblem(short, wrong, ds.r_default, parameterization=par)
    res = kftune.minimize(problem, problem.space, "trbo", budget=100, seed=0)
    found = problem.parameterization.model_values(res.x)
    assert found["C_af"] / true.C_af == pytest.approx(1.0, abs=0.10)
    assert found["C_ar"] / true.C_ar == pytest.approx(1.0, abs=0.10)
    # and the tuned filter's sideslip is better than the wrong vehicle's with tuned Q
    start = manual_point(problem.parameterization)
    metrics, _ = assess(problem, res.x, short)
    start_metrics, _ = assess(problem, start, short)
    assert np.mean([v["rmse"] for v in metrics.values()]) < np.mean(
        [v["rmse"] for v in start_metrics.values()]
    )


# --------------------------------------------------------------------- the command line ----


def _tuned(small, tmp_path, *extra: str, budget: str = "20") -> tuple[Path, dict]:
    out = tmp_path / "tuned.json"
    res = run_cli("tune", str(small), "-n", budget, "--quiet", "-o", str(out), *extra)
    assert res.returncode == 0, res.stderr
    return out, json.loads(out.read_text())


def test_tuned_file_records_the_model_parameters_and_every_reader_runs_them(small, tmp_path):
    """The TOML form: the tuned file's model_params, deployment vehicle and parameter list
    hold the tuned values; evaluate's KPIs are assess() at the tuned point; every export
    format writes the tuned values."""
    config = tmp_path / "joint.toml"
    config.write_text(
        "[parameters]\n"
        "tune_model = { C_af = [20000.0, 400000.0], C_ar = [20000.0, 400000.0] }\n"
        'model_scale = { C_ar = "linear" }\n'
    )
    # random search, one stage: its point is not the recorded model (TR-BO's joint search,
    # seeded with the noise-only optimum, may end there on a short budget)
    out, doc = _tuned(small, tmp_path, "--config", str(config), "-m", "random")
    ds = open_dataset(str(small))
    rec = doc["model_params"]
    assert list(rec) == ["C_af", "C_ar"]
    assert rec["C_af"]["start"] == ds.vehicle.C_af and rec["C_ar"]["start"] == ds.vehicle.C_ar
    assert (rec["C_af"]["scale"], rec["C_ar"]["scale"]) == ("log10", "linear")
    assert rec["C_af"]["value"] == doc["params"]["C_af"] != ds.vehicle.C_af
    dep = doc["deployment"]
    assert dep["vehicle"]["C_af"] == rec["C_af"]["value"]
    assert {e["name"]: e["value"] for e in dep["model_params"]}["C_ar"] == rec["C_ar"]["value"]
    # evaluate: the recording's vehicle has the start values, which is no mismatch
    ev = run_cli("evaluate", str(small), "--params", str(out), "--split", "test", "--json")
    assert ev.returncode == 0, ev.stderr
    got = json.loads(ev.stdout)
    assert got["model_params"] == {n: rec[n]["value"] for n in rec}
    par = NoiseParameterization(model_bounds=STIFFNESS, model_scales={"C_ar": "linear"})
    problem = TuningProblem(ds.test, ds.vehicle, doc["r"], parameterization=par)
    problem.cov_scale = got.get("cov_scale", 1.0)  # the calibration evaluate applies
    x = [*doc["q"], rec["C_af"]["value"], rec["C_ar"]["value"]]
    metrics, _ = assess(problem, x, ds.test)
    for name, row in metrics.items():
        assert got["manoeuvres"][name]["rmse"] == pytest.approx(row["rmse"], rel=1e-9)
    # estimate writes the β of the filter at the tuned point
    m = ds.test[0]
    est = run_cli("estimate", str(small), "--params", str(out), "--manoeuvre", m.name,
                  "--no-plot", "-o", str(tmp_path / "est"), "--json")  # fmt: skip
    assert est.returncode == 0, est.stderr
    table = json.loads(est.stdout)["manoeuvres"][m.name]["file"]
    beta = np.genfromtxt(table, delimiter=",", names=True)["beta"]
    np.testing.assert_allclose(beta, problem.run(x, m).output("beta"), rtol=1e-12, atol=1e-15)
    value = rec["C_af"]["value"]
    exported = {}
    for fmt in ("json", "yaml", "c", "matlab"):
        folder = tmp_path / "c"  # c: a folder of C files, its values in kftune_filter.h
        res = run_cli("export", str(out), "-f", fmt, "-o", str(folder) if fmt == "c" else "-")
        assert res.returncode == 0, res.stderr
        exported[fmt] = (folder / "kftune_filter.h").read_text() if fmt == "c" else res.stdout
    assert json.loads(exported["json"])["vehicle_C_af"] == value
    assert json.loads(exported["json"])["tuned_model_param_names"] == ["C_af", "C_ar"]
    assert all("C_af (recorded 55600)" in text for text in exported.values() if text[0] != "{")
    patterns = {
        "yaml": r"vehicle_C_af: (\S+)",
        "c": r"#define KFTUNE_VEHICLE_C_AF (\S+)",
        "matlab": r"kf\.vehicle\.C_af = ([^;]+);",
    }
    for fmt, pattern in patterns.items():
        found = re.search(pattern, exported[fmt])
        assert found and float(found.group(1)) == pytest.approx(value, rel=1e-15), fmt


def test_a_recording_with_another_vehicle_is_still_refused(small, tmp_path):
    """The tuned fields may differ from the recording's; any other field may not."""
    out, _ = _tuned(small, tmp_path, "--tune-model", "C_af=20000:400000", budget="6")
    ds = open_dataset(str(small))
    other = tmp_path / "other"
    save_dataset(dataclasses.replace(ds, vehicle=ds.vehicle.replace(m=1.2 * ds.vehicle.m)), other)
    res = run_cli("evaluate", str(other), "--params", str(out))
    assert res.returncode == 3
    assert "m 1" in res.stderr and "C_af" not in res.stderr.split("differs")[1]


@pytest.mark.parametrize(
    ("args", "code", "says"),
    [
        (["--tune-model", "C_af=20000:4000000"], 2, "--tune-model C_af: .*plausible range"),
        (["--tune-model", "C_f=20000:40000"], 2, "'C_f' is not a parameter.*'C_af'"),
        (["--tune-model", "C_af=2e4"], 2, "NAME=LOW:HIGH"),
        (["--tune-model", "mu=0.4:1.6:log2"], 2, "mu: scale must be log10 or linear"),
        (["--tune-model", "C_af=4e5:2e4"], 2, "--tune-model C_af: .*low < high"),
        (["--tune-model", "C_af=60000:400000"], 3, "'C_af'.*recorded value 55600"),
    ],
)
def test_bad_tune_model_options_are_refused_naming_the_parameter(small, tmp_path, args, code, says):
    res = run_cli("tune", str(small), "-n", "4", "--quiet", "-o", str(tmp_path / "t.json"), *args)
    assert res.returncode == code, res.stderr
    assert re.search(says, res.stderr), res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "t.json").exists()


@pytest.mark.parametrize(
    ("section", "says"),
    [
        ("tune_model = { mu = [0.4, 2.5] }", r"joint.toml \[parameters\]: .*'mu'.*\[0.05, 2\]"),
        (
            "tune_model = { C_af = 20000.0 }",
            r"\[parameters\] key 'tune_model.C_af': expected \[low, high\]",
        ),
        ('tune_model = { mu = [0.4, 1.6] }\nmodel_scale = { C_af = "linear" }', "model_scale"),
        ('tune_model = { mu = [0.4, 1.6] }\nmodel_scale = { mu = "ln" }', "model_scale.mu"),
    ],
)
def test_bad_tune_model_tables_are_refused_naming_file_and_key(small, tmp_path, section, says):
    config = tmp_path / "joint.toml"
    config.write_text(f"[parameters]\n{section}\n")
    res = run_cli("tune", str(small), "-n", "4", "--quiet", "--config", str(config))
    assert res.returncode == 3, res.stderr
    assert re.search(says, res.stderr), res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("stage", ["noise-only", "joint"])
@pytest.mark.slow
def test_a_joint_study_resumes_exactly_after_sigkill_in_either_stage(small, tmp_path, stage):
    """40 evaluations in two stages (10 + 30 with the share of 1/4, each stage's study file
    beside --storage); killed in the first or in the second, the resumed run keeps every
    finished evaluation and ends as the uninterrupted one."""
    budget = "40"
    n1 = round(40 * NOISE_STAGE_SHARE)
    n_stage = n1 if stage == "noise-only" else 40 - n1
    joint = ["--tune-model", "C_af=20000:400000", "--tune-model", "mu=0.4:1.6:linear"]
    full = run_cli("tune", str(small), "-n", budget, "--quiet", "-o", str(tmp_path / "full.json"),
                   *joint)  # fmt: skip
    assert full.returncode == 0, full.stderr
    db = tmp_path / "study.db"
    first = tmp_path / "study.noise-only.db"
    killed_in = first if stage == "noise-only" else db
    args = ["tune", str(small), "-n", budget, "--quiet", "--storage", str(db), *joint]
    run_killed_after(killed_in, n_stage // 2, *args, "-o", str(tmp_path / "killed.json"))
    assert _completed(killed_in) == n_stage // 2, "the run was not killed mid-way through the stage"
    if stage == "noise-only":
        assert not db.exists(), "the joint study started before the first stage ended"
    else:
        assert _completed(first) == n1
    with sqlite3.connect(killed_in) as conn:
        before = conn.execute("SELECT number, value FROM trials WHERE state='complete'").fetchall()
    if stage == "joint":  # another box is another objective: refused
        other = run_cli(*args[:-1], "mu=0.5:1.6:linear", "--resume", "-o", str(tmp_path / "o.json"))
        assert other.returncode == 3, other.stderr
    res = run_cli(*args, "--resume", "-o", str(tmp_path / "resumed.json"))
    assert res.returncode == 0, res.stderr
    with sqlite3.connect(killed_in) as conn:
        after = dict(conn.execute("SELECT number, value FROM trials WHERE state='complete'"))
    assert len(after) == n_stage and all(after[n] == v for n, v in before)
    assert _completed(first) == n1 and _completed(db) == 40 - n1
    resumed = json.loads((tmp_path / "resumed.json").read_text())
    uninterrupted = json.loads((tmp_path / "full.json").read_text())
    assert resumed["params"] == uninterrupted["params"]
    assert resumed["model_params"] == uninterrupted["model_params"]
    assert resumed["cost"] == uninterrupted["cost"]
    assert resumed["stages"] == {**uninterrupted["stages"], "noise_storage": str(first)}


def test_a_joint_tuning_seeds_its_search_with_the_noise_only_optimum(small, tmp_path):
    """-n 24 with --storage: 6 evaluations of Q alone on the recorded model (a study of its
    own, the noise-only problem's), then 18 of the joint search whose first evaluated point
    is that study's best with the model at its recorded values, at the same cost; the tuned
    file and the held-out line name the noise-only filter, whose held-out β RMSE is the
    recorded-vehicle filter's at that Q."""
    from kftune.optim.study import read_study

    db = tmp_path / "study.db"
    res = run_cli("tune", str(small), "-n", "24", "--storage", str(db), "-o",
                  str(tmp_path / "t.json"), "--tune-model", "C_af=20000:400000",
                  "--cost", "nrmse")  # fmt: skip
    assert res.returncode == 0, res.stderr
    n1 = round(24 * NOISE_STAGE_SHARE)
    assert f"24 evaluations in two stages: {n1} of the noise alone" in res.stderr
    assert f"after 24 evaluations ({n1} + {24 - n1}" in res.stdout
    first = read_study(tmp_path / "study.noise-only.db")
    joint = read_study(db)
    assert len(first.records) == n1 and len(joint.records) == 24 - n1
    assert [p["name"] for p in first.settings["space"]["params"]] == ["q_vx", "q_vy", "q_r"]
    best = min((r for r in first.records if r.ok), key=lambda r: r.value)
    ds = open_dataset(str(small))
    seed = joint.records[0]
    assert seed.params["C_af"] == pytest.approx(ds.vehicle.C_af, rel=1e-12)
    for name in ("q_vx", "q_vy", "q_r"):
        assert seed.params[name] == pytest.approx(best.params[name], rel=1e-9)
    assert seed.value == pytest.approx(best.value, rel=1e-9)
    # the joint design: C_af's two DIRECT thirds on its axis through the seed, the noise held
    assert joint.settings["options"]["design_centre"] == "x0"
    assert joint.settings["options"]["design_params"] == ["C_af"]
    probes = joint.records[1:3]
    thirds = [20000.0 * 20.0 ** (1 / 6), 20000.0 * 20.0 ** (5 / 6)]
    assert [r.params["C_af"] for r in probes] == pytest.approx(thirds, rel=1e-9)
    for r in probes:
        assert [r.params[n] for n in ("q_vx", "q_vy", "q_r")] == pytest.approx(
            [seed.params[n] for n in ("q_vx", "q_vy", "q_r")], rel=1e-9
        )
    doc = json.loads((tmp_path / "t.json").read_text())
    assert doc["cost"] <= best.value
    st = doc["stages"]
    assert (st["total"], st["noise_budget"], st["joint_budget"]) == (24, n1, 24 - n1)
    assert st["noise_only"]["cost"] == pytest.approx(best.value, rel=1e-9)
    held = doc["held_out"]
    recorded = TuningProblem(ds.train, ds.vehicle, doc["r"])
    recorded.cov_scale = held["calibration_factor"]
    q = [best.params[n] for n in ("q_vx", "q_vy", "q_r")]
    metrics, _ = assess(recorded, q, ds.test)
    expected = np.mean([row["rmse"] for row in metrics.values()])
    assert held["noise_only_beta_rmse_deg"] == pytest.approx(expected, rel=1e-9)
    assert (
        "noise-only filter (the noise tuned alone at the recorded model, first stage): β RMSE"
        in res.stdout
    )


@pytest.mark.parametrize(
    ("options", "centre", "params"),
    [('design_centre = "box"', None, None), ('design_params = ["C_af"]', None, ["C_af"])],
)
def test_a_users_design_options_are_the_joint_stages_and_not_the_first_stages(
    small, tmp_path, options, centre, params
):
    """``[options.trbo]`` design options from a configuration file are accepted, reach the
    joint stage alone (the first stage's space has no C_af to name) and replace its default
    design: with ``design_centre = "box"`` the evaluation after the seed is the box's
    centre, C_af = √(20000·400000)."""
    from kftune.optim.study import read_study

    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[options.trbo]\n{options}\n")
    db = tmp_path / "study.db"
    res = run_cli("tune", str(small), "-n", "24", "--storage", str(db), "-o",
                  str(tmp_path / "t.json"), "--tune-model", "C_af=20000:400000",
                  "--cost", "nrmse", "--config", str(cfg))  # fmt: skip
    assert res.returncode == 0, res.stderr
    first, joint = read_study(tmp_path / "study.noise-only.db"), read_study(db)
    assert "design_centre" not in first.settings["options"]
    assert "design_params" not in first.settings["options"]
    assert joint.settings["options"].get("design_centre") == centre  # "box": not recorded
    assert joint.settings["options"].get("design_params") == params
    if "box" in options:
        assert joint.records[1].params["C_af"] == pytest.approx((20000.0 * 400000.0) ** 0.5)


@pytest.mark.parametrize("stage", [1, 2])
def test_ctrl_c_in_either_stage_keeps_the_best_so_far_in_the_joint_space(
    small, tmp_path, monkeypatch, stage
):
    """Ctrl-C after 3 evaluations of stage 1 or 2: exit 130, the partial file holds a
    point of the joint space (stage 1's best with the recorded C_af, or stage 2's best,
    which is no worse than stage 1's), and the message names every study file kept."""
    import kftune.experiment as experiment
    from kftune.optim.study import read_study

    real, calls = experiment.minimize, []

    def interrupted_at(fun: Any, space: Any, method: str, **kw: Any) -> Any:
        calls.append(method)
        if len(calls) != stage:
            return real(fun, space, method, **kw)
        n = []

        def f(x: Any) -> float:
            n.append(1)
            if len(n) > 3:
                raise KeyboardInterrupt
            return fun(x)

        return real(f, space, method, **kw)

    monkeypatch.setattr(experiment, "minimize", interrupted_at)
    db, out = tmp_path / "s.db", tmp_path / "t.json"
    res = run_cli("tune", str(small), "-n", "24", "--cost", "nrmse", "--storage", str(db),
                  "-o", str(out), "--tune-model", "C_af=20000:400000")  # fmt: skip
    assert res.returncode == 130, res.stderr
    partial = json.loads((tmp_path / "t.partial.json").read_text())
    assert list(partial["params"]) == ["q_vx", "q_vy", "q_r", "C_af"]
    first = tmp_path / "s.noise-only.db"
    assert f"is saved in {first}" in res.stderr and "--resume" in res.stderr
    best1 = min(r.value for r in read_study(first).records if r.ok)
    if stage == 1:
        assert not db.exists() and partial["params"]["C_af"] == 55600.0
        assert partial["cost"] == pytest.approx(best1, rel=1e-12)
    else:
        assert f"{first} and {db}" in res.stderr
        assert partial["cost"] <= best1 * (1 + 1e-9)


def test_a_noise_only_tuning_and_other_methods_run_in_one_stage(small, tmp_path):
    """No model parameter, or a method that cannot start from a point: one study, no
    stages record."""
    runs = {"noise": [], "random": ["-m", "random", "--tune-model", "C_af=20000:400000"]}
    for name, extra in runs.items():
        _, doc = _tuned(small, tmp_path, "--storage", str(tmp_path / f"{name}.db"), *extra,
                        budget="8")  # fmt: skip
        assert "stages" not in doc and doc["n_evals"] == 8
        assert not (tmp_path / f"{name}.noise-only.db").exists()


def test_a_config_x0_is_accepted_and_a_bad_one_refused_naming_the_key(small, tmp_path):
    """[options.trbo] x0 is a point of the tuned space: the run checks it (the joint search
    then starts there, in one stage); one outside the box is refused naming x0 and the
    parameter, exit 3."""
    ds = open_dataset(str(small))
    x0 = [1e-6, 1e-4, 1e-6, ds.vehicle.C_af]
    config = tmp_path / "x0.toml"
    config.write_text(f"[options.trbo]\nx0 = {x0!r}\n")
    joint = ["--tune-model", "C_af=20000:400000", "--cost", "nrmse"]  # Q and C_af: 4 numbers
    _, doc = _tuned(small, tmp_path, "--config", str(config), *joint, budget="6")
    assert "stages" not in doc
    bad = tmp_path / "bad.toml"
    bad.write_text(f"[options.trbo]\nx0 = {[*x0[:3], 1e6]!r}\n")
    res = run_cli("tune", str(small), "-n", "6", "--quiet", "--config", str(bad), "-o",
                  str(tmp_path / "b.json"), *joint)  # fmt: skip
    assert res.returncode == 3, res.stderr
    assert "x0" in res.stderr and "C_af" in res.stderr and "Traceback" not in res.stderr


# ------------------------------------------------------------ evidence that it generalises --


def test_held_out_shows_the_tuned_q_on_the_recorded_model(small, tmp_path):
    """With a test split: the tuned file's held-out record has the β RMSE of the tuned Q on
    the recorded model, as a noise-only filter on the recorded vehicle at the tuned Q gives."""
    # random search: one stage, whose point is not the recorded model
    _, doc = _tuned(small, tmp_path, "--tune-model", "C_af=20000:400000", "-m", "random",
                    budget="12")  # fmt: skip
    held = doc["held_out"]
    ds = open_dataset(str(small))
    noise_only = TuningProblem(ds.train, ds.vehicle, doc["r"])
    noise_only.cov_scale = held.get("calibration_factor", 1.0)
    metrics, _ = assess(noise_only, doc["q"], ds.test)
    expected = np.mean([row["rmse"] for row in metrics.values()])
    assert held["recorded_model_beta_rmse_deg"] == pytest.approx(expected, rel=1e-9)
    assert held["beta_rmse_deg"] != held["recorded_model_beta_rmse_deg"]


def test_held_out_line_warns_when_the_joint_filter_is_worse():
    from kftune.cli.tune import held_out_line

    base = {"split": "test", "n_manoeuvres": 4, "manual_beta_rmse_deg": 0.5}
    worse = held_out_line({**base, "beta_rmse_deg": 0.2, "recorded_model_beta_rmse_deg": 0.15})
    assert "tuned Q on the recorded model: β RMSE 0.150°" in worse
    assert "warning: the tuned model parameters make the filter worse" in worse
    better = held_out_line({**base, "beta_rmse_deg": 0.1, "recorded_model_beta_rmse_deg": 0.15})
    assert "warning" not in better
    joint = {**base, "recorded_model_beta_rmse_deg": 0.15, "noise_only_beta_rmse_deg": 0.12}
    noisy = held_out_line({**joint, "beta_rmse_deg": 0.13})
    assert (
        "noise-only filter (the noise tuned alone at the recorded model, first stage): β " in noisy
    )
    assert "warning: the joint filter is 8.3 % worse" in noisy
    assert "keeps the joint filter" in noisy
    assert "noise-only one" not in held_out_line({**joint, "beta_rmse_deg": 0.12})
    manual = held_out_line({**base, "beta_rmse_deg": 0.6, "recorded_model_beta_rmse_deg": 0.7})
    assert "worse there than the manual rule of thumb" in manual
    assert "recorded model" not in held_out_line({**base, "beta_rmse_deg": 0.1})
    # 0.3 % above the recorded model's on a few manoeuvres: shown, no verdict
    close = held_out_line(
        {**base, "beta_rmse_deg": 0.20458, "recorded_model_beta_rmse_deg": 0.20398}
    )
    assert "β RMSE 0.204°" in close and "warning" not in close


def test_leave_one_out_refits_without_the_manoeuvre_it_scores(ds, short):
    """The refit for manoeuvre k sees only the others: replacing k by another manoeuvre
    leaves k's refitted values as they were; the recorded-model error on k is the noise-only
    filter's at the tuned Q."""
    from kftune.tuning.generalise import leave_one_out

    par = NoiseParameterization(model_bounds=STIFFNESS)
    wrong = ds.vehicle.replace(C_af=0.7 * ds.vehicle.C_af)
    x = np.array([1e-8, 1e-6, 1e-6, 0.9 * ds.vehicle.C_af, ds.vehicle.C_ar])
    problem = TuningProblem(short, wrong, ds.r_default, parameterization=par)
    cv = leave_one_out(problem, x)
    assert list(cv["manoeuvres"]) == list(NAMES)
    swapped = [*short[:2], ds["train-04-j-turn"]]
    other = TuningProblem(swapped, wrong, ds.r_default, parameterization=par)
    cv_other = leave_one_out(other, x)
    last = cv["manoeuvres"][NAMES[2]]["refit_values"]
    assert cv_other["manoeuvres"]["train-04-j-turn"]["refit_values"] == last
    assert (
        cv_other["manoeuvres"][NAMES[0]]["refit_values"]
        != cv["manoeuvres"][NAMES[0]]["refit_values"]
    )
    noise_only = TuningProblem(short, wrong, ds.r_default)
    metrics, _ = assess(noise_only, x[:3], short)
    for name, row in cv["manoeuvres"].items():
        assert row["recorded_model"] == pytest.approx(metrics[name]["rmse"], rel=1e-12)
        assert all(2e4 <= v <= 4e5 for v in row["refit_values"].values())
    # the refit moves towards the true front stiffness from the wrong recorded one
    assert cv["mean_refit"] < cv["mean_recorded_model"]


def test_widening_leaves_a_model_parameters_box_alone(ds, short, monkeypatch):
    """--widen-bounds moves the noise's log10 bounds out, never a model parameter's: two
    decades beyond a stiffness box leave every plausible car."""
    import kftune.experiment as experiment
    from kftune.optim import minimize_widening

    space = {"q_vy": (1e-3, 1e-1, "log10"), "C_af": (2e4, 3e4, "log10")}

    def run(sp, storage):  # the best point lies on both upper bounds
        return kftune.minimize(lambda x: 0.0, sp, "manual", points=[[1e-1, 3e4]])

    boxes = {
        p["name"]: (p["low"], p["high"]) for p in minimize_widening(run, space).space["params"]
    }
    assert boxes["C_af"] != (2e4, 3e4) and boxes["q_vy"] != (1e-3, 1e-1)  # unless fixed
    kept = minimize_widening(run, space, fixed=("C_af",)).space["params"]
    boxes = {p["name"]: (p["low"], p["high"]) for p in kept}
    assert boxes["C_af"] == (2e4, 3e4) and boxes["q_vy"] != (1e-3, 1e-1)
    # and tune names the problem's model parameters as fixed
    seen = {}

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return minimize_widening(*args, **kwargs)

    monkeypatch.setattr(experiment, "minimize_widening", spy)
    par = NoiseParameterization(model_bounds={"C_af": (2e4, 1e5)})
    problem = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)
    experiment.tune(problem, "random", budget=2, widen_bounds=True, progress=False)
    assert tuple(seen["fixed"]) == ("C_af",)


def test_a_joint_problem_travels_to_another_process_whole(ds, short):
    """What a Dask worker receives (the pickled problem) runs each point's model."""
    import pickle

    par = NoiseParameterization(model_bounds=STIFFNESS)
    problem = TuningProblem(short, ds.vehicle, ds.r_default, parameterization=par)
    x = np.array([1e-5, 1e-3, 1e-5, 4e4, 9e4])
    copy = pickle.loads(pickle.dumps(problem))
    assert copy.score_manoeuvres(x, [1]) == problem.score_manoeuvres(x, [1])
    assert copy(x) == problem(x) != problem(manual_point(problem.parameterization))


def test_models_lists_the_parameters_tune_model_can_search():
    from kftune.vehicle.params import PLAUSIBLE_RANGES

    res = run_cli("models", "--model", "single-track", "--json")
    assert res.returncode == 0, res.stderr
    params = {p["name"]: p for p in json.loads(res.stdout)["models"][0]["parameters"]}
    assert list(params) == ["m", "Iz", "a", "b", "h", "C_af", "C_ar", "C_x", "mu"]
    assert params["C_af"]["range"] == list(PLAUSIBLE_RANGES["C_af"][:2])
    assert params["mu"]["unit"] == "-"
    text = run_cli("models", "--model", "single-track").stdout
    assert "C_af [N/rad] 1000…2e+06" in text


@pytest.mark.slow
def test_compare_tunes_model_parameters_with_every_method_and_reports_them(small, tmp_path):
    out = tmp_path / "cmp"
    res = run_cli("compare", str(small), "--methods", "manual", "random", "ga", "--budget",
                  "random=4", "--budget", "ga=8", "--tune-model", "C_af=20000:400000",
                  "-o", str(out), "--quiet")  # fmt: skip
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["meta"]["model_parameters"]["C_af"] == {"start": 55600.0, "unit": "N/rad"}
    params = {m["key"]: m["params"] for m in results["methods"]}
    assert params["manual"]["C_af"] == 55600.0
    assert all(2e4 <= p["C_af"] <= 4e5 for p in params.values())
    report = (out / "report.md").read_text()
    assert "| Method | q_vx | q_vy | q_r | C_af |" in report
    assert "C_af [N/rad]: model parameters tuned with the noise" in report
    # a noise-only comparison's results are as before
    from kftune.report import parameter_note

    assert "model parameters" not in parameter_note(("q_vx", "q_vy", "q_r", "gain"))


@pytest.mark.slow
def test_compare_stages_trbo_as_tune_does(small, tmp_path):
    """compare --tune-model with TR-BO: the same two stages (the first one's study beside
    the method's), its first joint evaluation the noise-only optimum, and the budget
    recorded as the total asked for."""
    from kftune.optim.study import read_study

    out = tmp_path / "cmp"
    res = run_cli("compare", str(small), "--methods", "trbo", "--budget", "trbo=16",
                  "--tune-model", "C_af=20000:400000", "-o", str(out), "--quiet")  # fmt: skip
    assert res.returncode == 0, res.stderr
    n1 = round(16 * NOISE_STAGE_SHARE)
    first = read_study(out / "studies" / "trbo.noise-only.db")
    joint = read_study(out / "studies" / "trbo.db")
    assert (len(first.records), len(joint.records)) == (n1, 16 - n1)
    best = min((r for r in first.records if r.ok), key=lambda r: r.value)
    assert joint.records[0].value == pytest.approx(best.value, rel=1e-9)
    results = json.loads((out / "results.json").read_text())
    assert results["meta"]["budgets"]["trbo"] == 16
    (run,) = results["methods"]
    assert run["extra"]["stages"] == {"total": 16, "noise_budget": n1, "joint_budget": 16 - n1}


def test_tune_model_names_are_checked_against_the_chosen_model():
    """The command line's --tune-model is checked against the model the command runs (a
    model file's own parameter names), not the single-track model's."""
    import argparse

    from kftune.cli._common import parameterization
    from kftune.errors import UsageError
    from kftune.models.user import load_model

    example = Path(__file__).resolve().parents[1] / "examples" / "linear_bicycle.py"
    args = argparse.Namespace(tune_model=[("C_f", 2e4, 4e5, None)])
    par = parameterization(args, {}, load_model(str(example)))
    assert par.model_names == ("C_f",)
    with pytest.raises(UsageError, match=r"--tune-model C_f: .*'C_f' is not a parameter"):
        parameterization(args, {}, get_model("single-track"))


def test_tune_model_twice_is_refused_and_a_box_alone_keeps_the_configured_scale():
    """--tune-model C_af twice: refused naming it (the second silently won); a box without
    a scale on the command line keeps the configuration's model_scale for that name
    (linear here), one with a scale takes it."""
    import argparse

    from kftune.cli._common import parameterization
    from kftune.errors import UsageError

    model = get_model("single-track")
    twice = argparse.Namespace(tune_model=[("C_af", 2e4, 4e5, None), ("C_af", 3e4, 4e5, None)])
    with pytest.raises(UsageError, match="--tune-model C_af is given twice"):
        parameterization(twice, {}, model)
    config = {"parameters": {"tune_model": {"C_af": [2e4, 4e5]}, "model_scale": {"C_af": "linear"}}}
    box = argparse.Namespace(tune_model=[("C_af", 3e4, 3e5, None)])
    par = parameterization(box, config, model)
    assert par.model_bounds["C_af"] == (3e4, 3e5) and par.model_scales["C_af"] == "linear"
    scaled = argparse.Namespace(tune_model=[("C_af", 3e4, 3e5, "log10")])
    assert parameterization(scaled, config, model).model_scales["C_af"] == "log10"


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda d: d.update(model_params=[1]), "'model_params' must be an object"),
        (lambda d: d["model_params"]["C_af"].update(value="big"), "'model_params.C_af' must be"),
        (lambda d: d["model_params"]["C_af"].update(value=1e6), r"'model_params.C_af': value"),
        (lambda d: d["model_params"]["C_af"].update(scale="ln"), "scale must be log10 or"),
        (lambda d: d["model_params"]["C_af"].update(low=-1.0), "needs a positive lower bound"),
        (
            lambda d: d["model_params"]["C_af"].update(low=1e6, high=1e6, value=1e6, start=1e6),
            "'model_params'.*low < high",
        ),
        (
            lambda d: d["model_params"].update(C_zz=d["model_params"].pop("C_af")),
            "'model_params.C_zz': the model has no parameter 'C_zz'",
        ),
        (  # a tuned value off the recording's: named before the vehicle mismatch it makes
            lambda d: (
                d["deployment"]["vehicle"].update(C_af=6e4),
                d["model_params"]["C_af"].update(value=6e4),
                d["model_params"].update(C_zz=d["model_params"].pop("C_af")),
            ),
            "'model_params.C_zz': the model has no parameter 'C_zz'",
        ),
    ],
)
def test_a_damaged_model_params_record_is_refused_naming_file_and_key(small, tmp_path, edit, says):
    out, doc = _tuned(small, tmp_path, "--tune-model", "C_af=20000:400000", budget="4")
    edit(doc)
    out.write_text(json.dumps(doc))
    estimated = str(tmp_path / "estimates")
    for command, after in (
        (["evaluate", str(small), "--params"], []),
        (["estimate", str(small), "--params"], ["-o", estimated]),
        (["export"], ["-o", "-"]),
    ):
        res = run_cli(*command, str(out), *after)
        assert res.returncode == 3, res.stderr
        assert re.search(says, res.stderr) and str(out) in res.stderr, res.stderr
        assert "Traceback" not in res.stderr
