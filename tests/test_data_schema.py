"""The dataset's channel schema comes from the model: a dataset of a tracking target (no
vehicle, no sideslip channel) is saved, loaded, tuned and evaluated through the command line,
and a sideslip recording without a reference sensor loads and tunes on the NIS cost while
the costs that need the reference say which channel which manoeuvre lacks."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import tomllib

from conftest import bundled_without
from conftest import run_cli as kftune
from kftune.data import Dataset, Manoeuvre, default_dataset, load_dataset, save_dataset
from kftune.errors import ConfigError, DataError, MissingChannelError
from kftune.tuning.cost import CostSpec
from kftune.tuning.problem import TuningProblem
from kftune.tuning.runs import default_r0

if sys.version_info < (3, 11):  # pragma: no cover
    pytest.skip("tomllib", allow_module_level=True)

DT = 0.1  # [s]
N = 300  # samples per manoeuvre (30 s)
POS_NOISE = 0.5  # [m], σ of the position sensor


def ctrv_manoeuvre(name: str, split: str, seed: int) -> Manoeuvre:
    """A target simulated with the CTRV model's own exact step (speed and turn rate wander
    slowly), its position measured with white noise, its true speed and turn rate kept as
    references ``v_ref`` [m/s] and ``omega_ref`` [rad/s]."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    v = 10.0 + 2.0 * np.sin(2 * np.pi * t / 20.0 + seed)
    omega = 0.2 * np.sin(2 * np.pi * t / 15.0 + 2 * seed)
    psi = np.concatenate([[0.0], np.cumsum(omega[:-1] * DT)])
    s = 0.5 * omega * DT
    d = v * DT * np.sinc(s / np.pi)  # numpy's sinc is sin(πx)/(πx)
    px = np.concatenate([[0.0], np.cumsum((d * np.cos(psi + s))[:-1])])
    py = np.concatenate([[0.0], np.cumsum((d * np.sin(psi + s))[:-1])])
    return Manoeuvre(
        name,
        "segment",
        split,
        t,
        px=px + rng.normal(0.0, POS_NOISE, N),
        py=py + rng.normal(0.0, POS_NOISE, N),
        v_ref=v,
        omega_ref=omega,
    )


@pytest.fixture(scope="module")
def track(tmp_path_factory) -> Path:
    """Three simulated CTRV manoeuvres (two training, one test), no vehicle."""
    ms = [
        ctrv_manoeuvre("run-1", "train", 1),
        ctrv_manoeuvre("run-2", "train", 2),
        ctrv_manoeuvre("run-3", "test", 3),
    ]
    ds = Dataset("track", None, DT, ms, units={"px": "m", "py": "m", "v_ref": "m/s"})
    out = tmp_path_factory.mktemp("track")
    save_dataset(ds, out)
    return out


def test_a_dataset_of_any_channels_round_trips(track):
    manifest = tomllib.loads((track / "manifest.toml").read_text())
    assert "vehicle" not in manifest
    assert manifest["units"] == {
        "t": "s",
        "omega_ref": "1",  # no unit declared: dimensionless
        "px": "m",
        "py": "m",
        "v_ref": "m/s",
    }
    ds = load_dataset(track)
    assert ds.vehicle is None and ds.channel_names == ("t", "omega_ref", "px", "py", "v_ref")
    assert ds.units["px"] == "m"
    again = ctrv_manoeuvre("run-1", "train", 1)
    assert ds["run-1"].equals(again)
    # R0 per model: the position sensor's noise from the data's own statistics
    var = ds.noise_variances(["px", "py"])
    np.testing.assert_allclose(np.sqrt(var), POS_NOISE, rtol=0.2)
    lacks = r"needs channel vx, which manoeuvre 'run-1' lacks"
    with pytest.raises(MissingChannelError, match=lacks) as info:
        ds.r_default  # noqa: B018 — the sideslip channels it lacks
    assert (info.value.manoeuvre, info.value.channel) == ("run-1", "vx")
    with pytest.raises(ConfigError, match=r"model 'single-track' needs the vehicle's parameters"):
        TuningProblem(ds.train, None, [1.0, 1.0, 1.0])


@pytest.mark.slow
def test_a_tracking_model_is_tuned_and_evaluated_on_its_own_dataset_through_the_cli(
    track, tmp_path
):
    out = tmp_path / "tuned.json"
    res = kftune(
        "tune",
        str(track),
        "--model",
        "ctrv",
        "--weights",
        "v=1,omega=1",
        "-m",
        "random",
        "--budget",
        "6",
        "--json",
        "-o",
        str(out),
    )
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["model"] == "ctrv" and doc["states"] == ["px", "py", "v", "psi", "omega"]
    assert doc["n_evals"] == 6 and math.isfinite(doc["cost"])
    ev = kftune("evaluate", str(track), "--params", str(out), "--split", "train", "--json")
    assert ev.returncode == 0, ev.stderr
    got = json.loads(ev.stdout)
    assert got["cost"] == pytest.approx(doc["cost"], rel=1e-12)
    assert set(got["average"]) >= {"rmse_px", "rmse_py", "rmse_v", "rmse_omega"}
    assert got["average"]["rmse_v"] < 5.0  # [m/s]: the speed is estimated, not guessed
    table = kftune("evaluate", str(track), "--params", str(out))
    assert table.returncode == 0, table.stderr
    assert "RMSE v" in table.stdout and "run-3" in table.stdout
    # with units; a measurement scored against the measured channel says so
    assert "RMSE px vs meas m" in table.stdout and "RMSE v m/s" in table.stdout
    assert "RMSE v vs meas" not in table.stdout  # v is scored against v_ref
    assert got["average"]["rmse_px_vs_measured"] == got["average"]["rmse_px"]
    assert got["units"] == {"px": "m", "py": "m", "v": "m/s", "omega": "rad/s"}
    # the tuned tracking filter runs on the recordings and exports (no vehicle anywhere)
    est = kftune("estimate", str(track), "--params", str(out), "-o", str(tmp_path / "est"))
    assert est.returncode == 0, est.stderr
    rows = (tmp_path / "est" / "run-3.csv").read_text().splitlines()
    header = rows[0].split(",")
    assert {"t", "px", "v_std", "innovation_py", "nis", "v_ref"} <= set(header)
    assert len(rows) - 1 == load_dataset(track)["run-3"].n
    # its references: the RMSE of each, in its unit, and a figure (none were written)
    assert (tmp_path / "est" / "run-3.png").stat().st_size > 5000
    assert "RMSE v m/s" in est.stdout
    js = kftune("estimate", str(track), "--params", str(out), "-o", str(tmp_path / "e2"),
                "--json", "--no-plot")  # fmt: skip
    row = json.loads(js.stdout)["manoeuvres"]["run-3"]
    table = np.genfromtxt(tmp_path / "est" / "run-3.csv", delimiter=",", names=True)
    assert row["rmse"]["v"] == pytest.approx(np.sqrt(np.mean((table["v"] - table["v_ref"]) ** 2)))
    assert row["units"]["v"] == "m/s"
    c_dir = tmp_path / "kf_c"
    exp = kftune("export", str(out), "--format", "c", "-o", str(c_dir))
    assert exp.returncode == 0, exp.stderr
    assert "omega" in (c_dir / "kftune_filter.h").read_text()
    # a reference the data lack, and the paper's model on data that are not a car's
    res = kftune("tune", str(track), "--model", "ctrv", "--weights", "psi=1", "-n", "2")
    assert res.returncode == 3 and "Traceback" not in res.stderr
    assert "needs a reference channel psi_ref, which manoeuvre 'run-1' lacks" in res.stderr
    res = kftune("tune", str(track), "-n", "2")
    assert res.returncode == 3 and "Traceback" not in res.stderr
    assert "needs the vehicle's parameters" in res.stderr


def test_compare_and_report_a_tracking_model_by_its_channel_rmses(track, tmp_path):
    """``compare`` on a model without the sideslip output: the KPIs are the RMSE of each
    cost channel against its reference, named with units; ``report`` rebuilds it."""
    out = tmp_path / "rep"
    res = kftune(
        "compare", str(track), "--model", "ctrv", "--weights", "v=1,omega=1",
        "--methods", "manual", "random", "trbo", "--budget", "random=3", "--budget", "trbo=3",
        "--json", "-o", str(out),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads((out / "results.json").read_text())
    assert doc["meta"]["scored_channels"] == {"omega": "rad/s", "v": "m/s"}
    assert "Eq. 14–15" in doc["meta"]["cost"] and "px, py from the posterior" in doc["meta"]["cost"]
    ds = load_dataset(track)
    for run in doc["methods"]:
        for split, names in (("train", ["run-1", "run-2"]), ("test", ["run-3"])):
            assert set(run["metrics"][split]) == set(names)
            assert set(run["averages"][split]) == {
                "rmse_omega", "rmse_v", "n_diverged", "n_manoeuvres"
            }  # fmt: skip
            assert all(math.isfinite(run["averages"][split][k]) for k in ("rmse_omega", "rmse_v"))
    # the test KPI is the RMSE of the stored estimate against the reference (no burn-in)
    traces = np.load(out / "traces.npz")
    v = traces["run-3::v_trbo"]
    np.testing.assert_array_equal(traces["run-3::v_ref"], ds["run-3"].channel("v_ref"))
    rmse = float(np.sqrt(np.mean((v - ds["run-3"].channel("v_ref")) ** 2)))
    trbo = next(r for r in doc["methods"] if r["key"] == "trbo")
    assert trbo["metrics"]["test"]["run-3"]["rmse_v"] == pytest.approx(rmse, rel=1e-12)
    tables = json.loads(res.stdout)["tables"]
    assert [row["KPI"] for row in tables["kpi_test"]] == ["RMSE omega [rad/s]", "RMSE v [m/s]"]
    md = (out / "report.md").read_text()
    assert "## Average RMSE of the scored channels on the test set" in md
    assert "| RMSE v [m/s] |" in md and "| RMSE omega [rad/s] |" in md
    assert "sideslip" not in md.lower() and "β" not in md
    figures = {p.name for p in (out / "figures").glob("*.png")}
    assert figures == {
        "convergence.png", "cost_slice.png", "channels_run-3.png", "reliability.png",
        "improvement_trbo_test.png",  # TR-BO against the manual filter, on the model's channels
    }  # fmt: skip
    assert "(figures/channels_run-3.png)" in md
    assert "filters tuned by Manual, Random, TR-BO against" in md  # none left out
    header = (out / "tables" / "per_manoeuvre.csv").read_text().splitlines()[0]
    assert header == "method,split,manoeuvre,rmse_omega,rmse_v,diverged"
    again = kftune("report", str(out), "--out", str(tmp_path / "again"))
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "again" / "report.md").read_text() == md
    for csv in (out / "tables").glob("*.csv"):
        assert (tmp_path / "again" / "tables" / csv.name).read_text() == csv.read_text()
    assert {p.name for p in (tmp_path / "again" / "figures").glob("*.png")} == figures


@pytest.fixture(scope="module")
def no_reference(tmp_path_factory) -> Path:
    """Two training and one test manoeuvre of the bundled set without ``beta_ref``."""
    out = tmp_path_factory.mktemp("no-beta-ref")
    bundled_without(out, {"beta_ref"}, 400, "no-ref")
    return out


@pytest.mark.slow
def test_a_sideslip_recording_without_a_reference_loads_and_tunes_on_nis(no_reference, tmp_path):
    ds = load_dataset(no_reference)
    assert not any(m.has("beta_ref") for m in ds.manoeuvres)
    np.testing.assert_array_equal(ds.r_default, ds.noise_variances(["vx", "ay", "r"]))
    with pytest.raises(DataError, match="needs a reference channel beta_ref, which manoeuvre"):
        TuningProblem(ds.train, ds.vehicle, default_r0_of(ds))
    TuningProblem(ds.train, ds.vehicle, default_r0_of(ds), cost=CostSpec(kind="nis"))
    out = tmp_path / "tuned.json"
    res = kftune(
        "tune", str(no_reference), "--cost", "nis", "-m", "random", "-n", "3", "-o", str(out)
    )
    assert res.returncode == 0, res.stderr
    ev = kftune("evaluate", str(no_reference), "--params", str(out), "--split", "all")
    assert ev.returncode == 0, ev.stderr
    assert "they need a reference channel beta_ref, which 3 of 3 manoeuvres lack" in ev.stdout
    est = kftune("estimate", str(no_reference), "--params", str(out), "-o", str(tmp_path / "e"))
    assert est.returncode == 0, est.stderr
    header = (tmp_path / "e" / f"{ds.test[0].name}.csv").read_text().splitlines()[0].split(",")
    assert "beta_std" in header and "beta_ref" not in header
    res = kftune("tune", str(no_reference), "--cost", "nrmse", "-n", "2")
    assert res.returncode == 3 and "Traceback" not in res.stderr
    assert "the nrmse cost (without a reference sensor" in res.stderr
    assert "tune with --cost msp" in res.stderr and "--weights" in res.stderr  # the ways out
    assert (
        "needs a reference channel beta_ref, which manoeuvre "
        f"{ds.train[0].name!r} lacks" in res.stderr
    )
    # the manual filter under the default cost, which needs beta_ref: its KPIs against the
    # measurements, the cost J left out with the reason, not a refusal
    man = kftune("evaluate", str(no_reference), "--manual", "--split", "all", "--json")
    assert man.returncode == 0, man.stderr
    doc = json.loads(man.stdout)
    assert doc["cost"] is None and "beta_ref" in doc["cost_unscored"]
    assert all(row["rmse_r_vs_measured_degps"] > 0 for row in doc["manoeuvres"].values())
    text = kftune("evaluate", str(no_reference), "--manual", "--split", "all")
    assert text.returncode == 0 and "cost J (nrmse): – (" in text.stdout
    # without beta_ref, compare reports the RMSE of every measurement (a reference-free cost)
    rep = tmp_path / "rep"
    res = kftune("compare", str(no_reference), "--cost", "nis", "--methods", "manual", "random",
                 "--budget", "random=2", "-q", "-o", str(rep))  # fmt: skip
    assert res.returncode == 0, res.stderr
    meta = json.loads((rep / "results.json").read_text())["meta"]
    assert meta["scored_channels"] == {"vx": "m/s", "ay": "m/s^2", "r": "rad/s"}
    assert "| RMSE r [rad/s] |" in (rep / "report.md").read_text()
    res = kftune("dataset", "show", str(no_reference), "-o", str(tmp_path / "m.png"))
    assert res.returncode == 0, res.stderr  # the channels it has


def default_r0_of(ds: Dataset) -> np.ndarray:
    from kftune.models import SINGLE_TRACK

    return default_r0(SINGLE_TRACK, ds)


def test_the_sideslip_report_needs_beta_ref_on_every_manoeuvre_or_none():
    from kftune.experiment import sideslip_report
    from kftune.models import CTRV, SINGLE_TRACK

    ds = default_dataset()
    a, b = ds.train[0].slice(0, 400), ds.test[0].slice(0, 400)
    bare = Manoeuvre(
        b.name,
        b.kind,
        b.split,
        b.t,
        channels={k: v for k, v in b.channels.items() if k != "beta_ref"},
    )
    assert sideslip_report(SINGLE_TRACK, Dataset("full", ds.vehicle, ds.dt, [a, b]))
    assert not sideslip_report(CTRV, Dataset("full", ds.vehicle, ds.dt, [a, b]))
    mixed = Dataset("mixed", ds.vehicle, ds.dt, [a, bare])
    with pytest.raises(MissingChannelError, match="needs a reference channel beta_ref"):
        sideslip_report(SINGLE_TRACK, mixed)
    none = Dataset("none", ds.vehicle, ds.dt, [bare])
    assert not sideslip_report(SINGLE_TRACK, none)  # scored by its measurements instead
