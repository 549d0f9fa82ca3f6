"""Inputs that used to load silently: a corpus of malformed files written here and run
through the ``kftune`` command. Each wrong unit, absurd vehicle, boolean or digit-separated
number exits 3 with a message naming the file, the column or field and the row, and no
traceback; data that load but cannot be what they claim (samples held at a lower rate,
|vx·r| far beyond μ·g) load with a ``kftune: warning:`` naming the manoeuvre and the share;
parameters tuned on another dataset are not scored on the bundled one by default."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.cli import main
from kftune.data import Dataset, Manoeuvre, save_dataset, validate_channels
from kftune.data.validate import HELD_SHARE, STEER_L_EFF, plausibility_findings
from kftune.errors import DataError, DataWarning
from kftune.optim import make_optimizer
from kftune.tuning.cost import CostSpec
from kftune.tuning.problem import TuningProblem
from kftune.vehicle import preset
from test_data_helpers import synthetic_channels, synthetic_dataset

DEG = math.pi / 180.0


def kftune(*args: str) -> subprocess.CompletedProcess:
    """The command in its own process (what a user sees, tracebacks included)."""
    return subprocess.run(
        [sys.executable, "-m", "kftune", *args], capture_output=True, text=True, timeout=300
    )


@pytest.fixture
def cli(capsys):
    """The command in this process (fast): ``cli(*args)`` → (exit code, stdout, stderr). An
    exception that ``main`` let through would fail the test: no traceback can hide."""

    def run(*args: str) -> subprocess.CompletedProcess:
        try:
            code = main(list(args))
        except SystemExit as stop:  # argparse's usage errors
            code = int(stop.code)
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out, err)

    return run


def clean_failure(res: subprocess.CompletedProcess, code: int) -> str:
    """The exit code is ``code`` and stderr is one kftune message, no traceback."""
    assert res.returncode == code, res.stderr
    assert "Traceback" not in res.stderr + res.stdout
    assert res.stderr.startswith("kftune: error:" if code == 3 else "usage:"), res.stderr
    return res.stderr


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A valid one-training, one-test synthetic dataset (uncompressed CSV) to corrupt."""
    d = tmp_path_factory.mktemp("good")
    save_dataset(synthetic_dataset(1, 1), d, compress=False)
    return d


def corrupt(good: Path, tmp_path: Path, manifest=None, csv=None) -> Path:
    """A copy of ``good`` with the manifest and/or tr0.csv text passed through a function."""
    out = tmp_path / "bad"
    out.mkdir()
    for f in good.iterdir():
        text = f.read_text()
        if f.name == "manifest.toml" and manifest:
            text = manifest(text)
        if f.name == "tr0.csv" and csv:
            text = csv(text)
        (out / f.name).write_text(text)
    return out


# ------------------------------------------------------------------ units that load silently


@pytest.mark.parametrize(
    ("unit", "column", "says"),
    [  # rad/s declared deg/s: r 57× too small; rad declared deg: δ 57× too small
        ('r = "deg/s"', "ay", r"ay/\(vx·r\) = 5\d\.\d in cornering"),
        ('delta = "deg"', "delta", r"effective wheelbase vx·δ/r is 0\.0\d+ m \(least squares\)"),
    ],
)
def test_a_unit_declared_wrong_is_refused_naming_file_column_and_row(
    cli, good, tmp_path, unit, column, says
):
    key = unit.split(" ")[0]
    bad = corrupt(good, tmp_path, manifest=lambda t: re.sub(rf'\n{key} = "[^"]*"', f"\n{unit}", t))
    err = clean_failure(cli("dataset", "info", str(bad)), 3)
    assert f"file {bad / 'tr0.csv'}, column {column!r}, row " in err
    assert re.search(says, err), err


def test_the_kinematic_check_no_longer_skips_a_yaw_rate_57_times_too_small():
    """|vx·r| stays below 2 m/s² everywhere once r is 57× too small, which used to switch
    the ay ≈ vx·r check off; the cornering seen in ay keeps it on."""
    c = synthetic_channels()
    c["r"] = c["r"] * DEG
    assert np.abs(c["vx"] * c["r"]).max() < 2.0
    with pytest.raises(DataError, match=r"ay/\(vx·r\) = 57\.\d"):
        validate_channels(c, file="rec.csv")


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), speed=st.floats(8.0, 40.0), wheelbase=st.floats(2.0, 12.0))
def test_steering_in_rad_declared_deg_is_caught_for_any_plausible_car(seed, speed, wheelbase):
    """Kinematically consistent weaving at any speed and effective wheelbase loads; the
    same steering angle shrunk by π/180 is refused, whatever the car."""
    c = synthetic_channels(seed=seed)
    scale = speed / 20.0
    c["vx"], c["ay"] = c["vx"] * scale, c["ay"] * scale
    c["delta"] = c["r"] * wheelbase / c["vx"] + 1e-4 * np.sin(np.arange(c["t"].size))
    validate_channels(c, file="rec.csv")
    c["delta"] = c["delta"] * DEG
    with pytest.raises(DataError, match="steering angle and yaw rate disagree") as info:
        validate_channels(c, file="rec.csv")
    assert info.value.column == "delta" and info.value.row is not None
    assert STEER_L_EFF[0] > wheelbase * DEG * 1.5  # the bound is not met by a hair


def test_a_steering_release_with_the_yaw_rate_still_decaying_is_accepted():
    """A J-turn: the driver lets the wheel go back to zero while the yaw rate decays.
    Those samples (δ ≈ 0, |vx·r| ≥ 1 m/s²) have vx·δ/r ≈ 0; with 60 % of the cornering
    samples in such a release the median of vx·δ/r is ~0 (and was refused), the
    least-squares effective wheelbase stays the car's."""
    c = synthetic_channels(n=1000)
    n = c["t"].size
    wheelbase = 3.0
    c["delta"] = c["r"] * wheelbase / c["vx"]
    tail = np.arange(n) >= 400  # released: no steering, the yaw rate decays slowly
    c["delta"][tail] = 1e-5
    c["r"][tail] = 0.2 * np.exp(-(c["t"][tail] - c["t"][400]) / 20.0)
    c["ay"][tail] = c["vx"][tail] * c["r"][tail]
    steady = np.abs(c["vx"] * c["r"]) >= 1.0
    ratio = c["vx"][steady] * c["delta"][steady] / c["r"][steady]
    assert np.median(ratio) < STEER_L_EFF[0]  # the median would have refused it
    validate_channels(c, file="rec.csv")


def test_steering_of_the_opposite_sign_convention_is_refused():
    c = synthetic_channels()
    c["delta"] = -c["delta"]
    with pytest.raises(DataError, match="opposite sign conventions"):
        validate_channels(c, file="rec.csv")


def test_digit_separators_in_a_csv_are_refused_naming_column_and_row(cli, good, tmp_path):
    def one_value(text: str) -> str:
        lines = text.splitlines()
        fields = lines[9].split(",")
        fields[5] = "2_0.25"  # vx: float() would read 20.25
        lines[9] = ",".join(fields)
        return "\n".join(lines) + "\n"

    bad = corrupt(good, tmp_path, csv=one_value)
    err = clean_failure(cli("dataset", "info", str(bad)), 3)
    assert f"file {bad / 'tr0.csv'}, column 'vx', row 10: cannot read '2_0.25'" in err


# ------------------------------------------------------------------ absurd vehicles


@pytest.mark.parametrize(
    ("field", "value", "says"),
    [("m", "1e-300", "VehicleParams.m = 1e-300 kg"), ("b", "1e6", "VehicleParams.b = 1000000.0 m")],
)
def test_an_absurd_vehicle_in_a_manifest_is_refused_naming_field_and_range(
    cli, good, tmp_path, field, value, says
):
    bad = corrupt(
        good, tmp_path, manifest=lambda t: re.sub(rf"\n{field} = .*", f"\n{field} = {value}", t)
    )
    err = clean_failure(cli("dataset", "info", str(bad)), 3)
    assert f"file {bad / 'manifest.toml'}" in err and "field 'vehicle'" in err
    assert says in err and "implausible for a road vehicle: expected" in err


# ------------------------------------------------------------------ booleans and separators


@pytest.mark.parametrize(
    "args",
    [
        ("evaluate", "--q", "2_2.5", "1", "1"),
        ("evaluate", "--q", "1e-3", "١", "1"),
        ("tune", "--budget", "1_0"),
        ("tune", "--weights", "beta=5_0"),
    ],
)
def test_digit_separators_on_the_command_line_exit_2_naming_the_option(cli, args):
    err = clean_failure(cli(*args), 2)
    bad = next(a for a in args if "_" in a or not a.isascii())
    assert bad in err and f"{args[1]}" in err


def tuned_file(path: Path, **changes) -> Path:
    doc = {
        "format": "kftune-tuned-1",
        "dataset": "default",
        "cost_spec": {"kind": "nrmse", "weights": {"beta": 5.0, "r": 1.0, "ay": 1.0}},
        "burn_in": 0.0,
        "params": {"q_vx": 1e-6, "q_vy": 1e-4, "q_r": 1e-6},
        "q": [1e-6, 1e-4, 1e-6],
        "ukf": {"alpha": 1.0, "beta": 2.0, "kappa": 0.0},
    } | changes
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"q": [True, 1, 1]}, "'q' must be a list of numbers >= 0, one per state (not true/false"),
        ({"q": ["1e-6", 1, 1]}, "'q' must be a list of numbers >= 0"),
        ({"burn_in": True}, "'burn_in' must be a finite number >= 0, got True"),
        ({"params": {"r_scale": False}}, "'params.r_scale' must be a finite number > 0, got False"),
    ],
)
def test_booleans_in_a_tuned_file_are_refused_naming_it(cli, tmp_path, change, says):
    path = tuned_file(tmp_path / "tuned.json", **change)
    err = clean_failure(cli("evaluate", "--params", str(path)), 3)
    assert f"file {path}: {says}" in err


def test_booleans_are_not_numbers_for_weights_burn_in_and_manual_points():
    with pytest.raises(ValueError, match="cost weight for 'beta'"):
        CostSpec(weights={"beta": True})
    ds = synthetic_dataset(1, 0)
    with pytest.raises(ValueError, match="burn_in"):
        TuningProblem(ds.train, ds.vehicle, [1e-3] * 3, burn_in=True)
    with pytest.raises(ValueError, match="not true/false"):
        make_optimizer("manual", {"q": (1e-10, 1.0, "log10")}, points=[[True]])


def test_manual_points_with_a_boolean_in_a_config_exit_3(cli, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[options.manual]\npoints = [[true, 1e-3, 1e-3]]\n")
    err = clean_failure(cli("tune", "-m", "manual", "--config", str(cfg), "--quiet"), 3)
    assert "not true/false" in err


# ------------------------------------------------------------------ the wrong dataset


def test_parameters_tuned_elsewhere_are_not_scored_on_the_bundled_set_by_default(cli, tmp_path):
    path = tuned_file(tmp_path / "tuned.json", dataset="revs-250lm")
    err = clean_failure(cli("evaluate", "--params", str(path)), 3)
    assert f"{path}: the parameters were tuned on dataset 'revs-250lm'" in err
    assert "the bundled one is 'default'" in err
    named = cli("evaluate", "default", "--params", str(path), "--split", "train")
    assert named.returncode == 0, named.stderr
    assert named.stderr.startswith(
        f"kftune: warning: {path}: parameters tuned on dataset 'revs-250lm' are scored on "
        "dataset 'default'"
    )
    same = cli("evaluate", "--params", str(tuned_file(path)), "--split", "train")
    # (the only warning: this minimal file records no sample time and vehicle to check)
    assert same.returncode == 0 and "tuned on dataset" not in same.stderr, same.stderr
    assert same.stderr.count("kftune: warning:") == 1 and "does not record dt" in same.stderr


# ------------------------------------------------------------------ data that cannot be so


def held(channels: dict, factor: int) -> dict:
    """Every channel but time sampled at 1/factor of the rate and held (zero-order)."""
    out = dict(channels)
    idx = (np.arange(channels["t"].size) // factor) * factor
    for name in channels:
        if name != "t":
            out[name] = channels[name][idx]
    return out


@settings(max_examples=25, deadline=None)
@given(factor=st.integers(2, 10), seed=st.integers(0, 1000))
def test_samples_held_at_a_lower_rate_are_reported_with_share_and_rate(factor, seed):
    c = held(synthetic_channels(n=600, seed=seed), factor)
    validate_channels(c)  # they load
    (message,) = plausibility_findings(c, mu=1.0).values()
    share = 1.0 - 1.0 / factor
    assert share >= HELD_SHARE
    assert f"{share:.0%} of the samples repeat the previous one in ax, ay, r" in message
    rate = float(re.search(r"recorded at about ([0-9.]+) Hz", message).group(1))
    assert rate == pytest.approx(100.0 / factor, rel=0.02)


def test_unheld_data_give_no_warning():
    assert plausibility_findings(synthetic_channels(n=600), mu=1.0) == {}


def test_lateral_acceleration_beyond_the_tyres_names_the_share():
    """The synthetic drive reaches |vx·r| = 6.6 m/s²: with μ = 0.3, 1.5·μ·g = 4.41 m/s²."""
    c = synthetic_channels(n=600)
    lateral = np.abs(c["vx"] * c["r"])
    (message,) = plausibility_findings(c, mu=0.3).values()
    share = float(np.mean(lateral > 1.5 * 0.3 * 9.81))
    assert f"1.5·μ·g = 4.41 m/s² (μ = 0.3) in {share:.1%} of the samples" in message
    assert plausibility_findings(c, mu=1.0) == {}


def test_a_dataset_warns_once_per_finding_naming_dataset_and_manoeuvre():
    c = held(synthetic_channels(n=600), 5)
    m = Manoeuvre("held-5", "slalom", "train", **c)
    with pytest.warns(DataWarning) as record:
        Dataset("d", preset("bmw-320i"), 0.01, (m,))
    assert len(record) == 1
    assert str(record[0].message).startswith("dataset 'd', manoeuvre 'held-5': 80% of the")


@pytest.mark.slow
def test_the_command_line_prints_data_warnings_plainly_and_goes_on(good, tmp_path):
    low_mu = corrupt(good, tmp_path, manifest=lambda t: re.sub(r"\nmu = .*", "\nmu = 0.3", t))
    res = kftune("dataset", "info", str(low_mu))
    assert res.returncode == 0, res.stderr
    (line,) = res.stderr.splitlines()  # one for the finding, no source line, no traceback
    assert line.startswith(
        "kftune: warning: dataset 'synthetic', manoeuvre 'tr0' (and 1 more with the same "
        "finding: ['te0']): "
    )
    assert "|vx·r| exceeds 1.5·μ·g = 4.41 m/s² (μ = 0.3)" in line
