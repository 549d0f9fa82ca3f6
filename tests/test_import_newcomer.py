"""What a newcomer tripped over importing a logger's recordings, each checked against values
computed here from the SI channels the recording was made of: a computed channel without
``unit`` (its inputs' shared unit, or refused, or named as a suspect when a check between
channels fails), decimal commas (``[source] decimal``), messages that name the mapping's
fix (``units_row = true``, ``sign = -1``, ``hand_wheel = true``), ``estimate`` without a
dataset for a file tuned on another, and the demo's R printed as numbers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import tomllib

from conftest import run_cli
from kftune.cli import EXIT_BAD_INPUT
from kftune.data import load_dataset
from kftune.data.importer import import_recordings
from kftune.errors import DataError
from kftune.vehicle.params import preset
from test_data_helpers import synthetic_channels

# most imports here are of one uncut recording, which the default rule cannot split
pytestmark = pytest.mark.filterwarnings("ignore:.*makes none of the:kftune.errors.DataWarning")

G = 9.80665  # standard gravity [m/s²]: what a logger's "g" means
#: The four wheels' speeds as fractions of the vehicle's: their mean is exactly 1.
WHEELS = {"wheel_fl": 1.012, "wheel_fr": 0.991, "wheel_rl": 1.004, "wheel_rr": 0.993}
#: The German logger's names of the same wheels, in the same order.
GERMAN_WHEELS = ("VL", "VR", "HL", "HR")
WHEEL_MEAN = "(wheel_fl + wheel_fr + wheel_rl + wheel_rr) / 4"


def _logger_csv(
    path: Path, c: dict, *, units: bool = True, ay_sign: float = 1.0, steer_ratio: float = 1.0
) -> Path:
    """A CSV as numpy.savetxt writes it: ``# time(s),wheel_fl(kmph),…`` (or names alone,
    ``units=False``); ay in g times ``ay_sign``, r in deg/s, the steering angle in deg
    times ``steer_ratio`` (a hand-wheel angle), beta in deg."""
    cols = {("time", "s"): c["t"]}
    cols |= {(w, "kmph"): c["vx"] * 3.6 * f for w, f in WHEELS.items()}
    cols |= {
        ("acc_x", "g"): c["ax"] / G,
        ("acc_y", "g"): ay_sign * c["ay"] / G,
        ("yaw_rate", "deg/s"): np.degrees(c["r"]),
        ("steer", "deg"): np.degrees(c["delta"]) * steer_ratio,
        ("slip_angle", "deg"): np.degrees(c["beta_ref"]),
    }
    header = ",".join(f"{n}({u})" if units else n for n, u in cols)
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=header)
    return path


def _mapping(**channels: object) -> dict:
    """The logger's mapping (no vehicle, no model: only the channels' own checks), with
    ``channels`` replacing entries of [channels]."""
    table: dict[str, object] = {
        "t": "time",
        "vx": {"expr": WHEEL_MEAN},
        "ax": "acc_x",
        "ay": "acc_y",
        "r": "yaw_rate",
        "delta": "steer",
        "beta_ref": "slip_angle",
    }
    return {"name": "newcomer", "channels": table | channels}


def _german_csv(path: Path, c: dict, *, steer_ratio: float = 15.0) -> Path:
    """A German logger's export: ``;`` between fields, decimal commas, cp1252 (``°/s``),
    CRLF, a units row under the header; time in ms, the hand-wheel angle in degrees."""
    cols = {
        ("Zeit", "ms"): c["t"] * 1000.0,
        **{(f"Rad_{w}", "km/h"): c["vx"] * 3.6 * f for w, f in zip(GERMAN_WHEELS, WHEELS.values())},
        ("AccX", "g"): c["ax"] / G,
        ("AccY", "g"): c["ay"] / G,
        ("Gierrate", "°/s"): np.degrees(c["r"]),
        ("LRW", "°"): np.degrees(c["delta"]) * steer_ratio,
        ("Schwimmwinkel", "°"): np.degrees(c["beta_ref"]),
    }  # fmt: skip
    lines = [";".join(n for n, _ in cols), ";".join(u for _, u in cols)]
    for row in np.column_stack(list(cols.values())):
        lines.append(";".join(f"{v:.6f}".replace(".", ",") for v in row))
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("cp1252"))
    return path


GERMAN_MAPPING = """
name = "german"
vehicle = "bmw-320i"
model = "single-track"

[source]
encoding = "cp1252"
units_row = true
decimal = ","

[split]
test = ["*2"]

[channels]
t = "Zeit"
vx = { expr = "mean(Rad_VL, Rad_VR, Rad_HL, Rad_HR)" }
ax = "AccX"
ay = "AccY"
r = "Gierrate"
delta = { column = "LRW", hand_wheel = true }
beta_ref = "Schwimmwinkel"
"""


def _german_case(tmp_path: Path, old: str, new: str) -> tuple[Path, Path]:
    """A short German recording and :data:`GERMAN_MAPPING` with ``old`` replaced by ``new``."""
    csv = _german_csv(tmp_path / "fahrt1.csv", synthetic_channels(n=300))
    mapping = tmp_path / "m.toml"
    mapping.write_text(GERMAN_MAPPING.replace(old, new))
    return csv, mapping


def _import_error(csv: Path, mapping: dict | Path) -> str:
    with pytest.raises(DataError) as info:
        import_recordings([csv], mapping)
    return str(info.value)


# ------------------------------------------------------------------ computed channel units
def test_a_computed_channel_without_unit_takes_the_unit_its_inputs_share(tmp_path):
    """Four wheel speeds declared kmph: their mean is in km/h, converted to m/s (it was
    taken as m/s, 3.6 times too high)."""
    c = synthetic_channels(n=600)
    ds = import_recordings([_logger_csv(tmp_path / "run1.csv", c)], _mapping())
    (m,) = ds.manoeuvres
    np.testing.assert_allclose(m.vx, c["vx"], rtol=1e-9)
    np.testing.assert_allclose(m.ay, c["ay"], rtol=1e-9, atol=1e-12)


def test_a_computed_channel_over_inputs_in_different_units_is_refused_naming_them(tmp_path):
    """A wheel speed in kmph times a yaw rate in deg/s has no unit to guess."""
    c = synthetic_channels(n=600)
    csv = _logger_csv(tmp_path / "run1.csv", c)
    err = _import_error(csv, _mapping(ay={"expr": "wheel_fl * yaw_rate"}))
    assert err.startswith("file <mapping>: ay (expression 'wheel_fl * yaw_rate'): no unit")
    assert "wheel_fl [kmph], yaw_rate [deg/s]; in run1.csv" in err
    assert 'ay = { expr = "wheel_fl * yaw_rate", unit = "<unit>" }' in err
    assert 'give unit = "m/s^2"' in err


def test_si_inputs_give_an_si_result_without_unit(tmp_path):
    """vx (a channel of the mapping, m/s) times a yaw rate in rad/s: m/s², as before."""
    c = synthetic_channels(n=600)
    csv = tmp_path / "run1.csv"
    np.savetxt(
        csv,
        np.column_stack([c["t"], c["vx"] * 3.6, c["r"]]),
        delimiter=",",
        header="time(s),speed(km/h),omega(rad/s)",
    )
    mapping = {"channels": {"t": "time", "vx": "speed", "r": "omega", "ay": {"expr": "vx * omega"}}}
    (m,) = import_recordings([csv], mapping).manoeuvres
    np.testing.assert_allclose(m.ay, c["vx"] * c["r"], rtol=1e-9, atol=1e-12)


def test_a_computed_channel_taken_as_si_is_named_as_the_suspect_of_the_ratio(tmp_path):
    """Wheel speeds in km/h under names without units: the mean is taken as m/s, and the
    error the kinematic check raises on ay names vx, its expression, the unit it was taken
    in and the entry that fixes it."""
    c = synthetic_channels(n=600)
    err = _import_error(_logger_csv(tmp_path / "run1.csv", c, units=False), _mapping(
        ax={"column": "acc_x", "unit": "g"},
        ay={"column": "acc_y", "unit": "g"},
        r={"column": "yaw_rate", "unit": "deg/s"},
        delta={"column": "steer", "unit": "deg"},
        beta_ref={"column": "slip_angle", "unit": "deg"},
    ))  # fmt: skip
    ratio = float(re.search(r"ay/\(vx·r\) = ([-0-9.e]+)", err).group(1))
    assert ratio == pytest.approx(1 / 3.6, rel=0.05)
    assert (
        f"suspect the computed channel vx (expression '{WHEEL_MEAN}'), its result taken in m/s"
        in err
    )
    assert f'if vx in km/h: vx = {{ expr = "{WHEEL_MEAN}", unit = "km/h" }}' in err


# ------------------------------------------------------------------ decimal commas
def test_a_german_csv_with_decimal_commas_imports(tmp_path):
    """``;``, decimal commas, cp1252, a units row, time in ms, a hand-wheel angle: every
    channel equals the SI one it was written from (to the 6 decimals written)."""
    c = synthetic_channels(n=800)
    files = [_german_csv(tmp_path / f"fahrt{i}.csv", c) for i in (1, 2)]
    mapping = tmp_path / "german.toml"
    mapping.write_text(GERMAN_MAPPING)
    ran = run_cli("dataset", "import", *files, "--mapping", mapping, "-o", tmp_path / "de")
    assert ran.returncode == 0, ran.stderr
    ds = load_dataset(tmp_path / "de")
    m = ds["fahrt1"]
    np.testing.assert_allclose(m.t, c["t"], atol=1e-8)
    np.testing.assert_allclose(m.vx, c["vx"], atol=1e-6)
    np.testing.assert_allclose(m.ay, c["ay"], atol=1e-5)
    np.testing.assert_allclose(m.r, c["r"], atol=1e-7)
    np.testing.assert_allclose(m.delta, c["delta"], atol=1e-7)
    assert [x.split for x in ds.manoeuvres] == ["train", "test"]


def test_decimal_comma_with_a_comma_delimiter_is_refused_naming_both(tmp_path):
    csv, mapping = _german_case(tmp_path, 'decimal = ","', 'decimal = ","\ndelimiter = ","')
    err = _import_error(csv, mapping)
    assert f"file {mapping}: key 'source.decimal'" in err
    assert 'decimal = "," with source.delimiter = ","' in err


def test_decimal_commas_without_the_option_name_it(tmp_path):
    csv, mapping = _german_case(tmp_path, 'decimal = ","', "")
    err = _import_error(csv, mapping)
    assert err.startswith(f"file {csv}, column 'Zeit', row 3: cannot read '0,000000' as a number")
    assert 'set decimal = "," in the mapping\'s [source] table' in err


# ------------------------------------------------------------------ the mapping's fix
def test_a_forgotten_units_row_suggests_units_row(tmp_path):
    csv, mapping = _german_case(tmp_path, "units_row = true", "")
    ran = run_cli("dataset", "import", csv, "--mapping", mapping, "-o", tmp_path / "de")
    assert ran.returncode == EXIT_BAD_INPUT and "Traceback" not in ran.stderr
    assert ran.stderr.startswith(
        f"kftune: error: file {csv}, column 'Zeit', row 2: cannot read 'ms' as a number; this "
        "row looks like a row of units ('ms;km/h;"
    )
    assert "set units_row = true in the mapping's [source] table" in ran.stderr


def test_data_that_fail_in_row_2_without_units_get_no_units_row_hint(tmp_path):
    csv = tmp_path / "run1.csv"
    csv.write_text("time,vx\n0.0,oops\n")
    err = _import_error(csv, {"channels": {"t": "time", "vx": "vx"}})
    assert "cannot read 'oops'" in err and "units_row" not in err


def test_ay_of_the_other_sign_names_sign_minus_one_on_ay(tmp_path):
    c = synthetic_channels(n=600)
    csv = _logger_csv(tmp_path / "run1.csv", c, ay_sign=-1.0)
    err = _import_error(csv, _mapping())
    assert "column 'ay'" in err
    assert float(re.search(r"ay/\(vx·r\) = ([-0-9.e]+)", err).group(1)) == pytest.approx(
        -1, abs=0.05
    )
    assert (
        "if ay is positive to the right, flip it in the mapping's [channels] table (<mapping>): "
        'ay = { column = "acc_y", sign = -1 }' in err
    )


def test_a_hand_wheel_angle_beyond_a_road_wheels_names_hand_wheel_and_the_ratio(tmp_path):
    """Steering ratio 25: beyond ±1 rad, so the channel's own check; no ratio anywhere, so
    the message says where to give one."""
    c = synthetic_channels(n=600)
    csv = _logger_csv(tmp_path / "run1.csv", c, steer_ratio=25.0)
    err = _import_error(csv, _mapping())
    assert "delta (source 'steer'): " in err and "implausible value(s)" in err
    assert (
        "if it is the hand-wheel angle, set hand_wheel = true in the mapping's [channels] "
        'table (<mapping>): delta = { column = "steer", hand_wheel = true } (and give '
        "steering_ratio = <hand-wheel angle / road-wheel angle, e.g. 15.8> at the top of the "
        "mapping)" in err
    )


def test_a_hand_wheel_angle_within_a_road_wheels_names_hand_wheel_from_the_wheelbase(tmp_path):
    """Steering ratio 18 keeps the angle within ±1 rad but makes the effective wheelbase
    about 18 × 3.3 m; the vehicle's ratio is the one hand_wheel divides by."""
    c = synthetic_channels(n=600)
    csv = _logger_csv(tmp_path / "run1.csv", c, steer_ratio=18.0)
    err = _import_error(csv, _mapping() | {"vehicle": "bmw-320i"})
    assert "column 'delta'" in err and "steering angle and yaw rate disagree" in err
    ratio = preset("bmw-320i").steering_ratio
    assert (
        'delta = { column = "steer", hand_wheel = true } (it divides by the vehicle\'s '
        f"steering_ratio = {ratio:g})" in err
    )


# ------------------------------------------------------------------ estimate, demo, meta
@pytest.fixture(scope="module")
def german(tmp_path_factory) -> tuple[Path, Path]:
    """The German recordings imported as dataset 'german', and a filter tuned on it (one
    manual evaluation)."""
    tmp = tmp_path_factory.mktemp("german")
    c = synthetic_channels(n=800)
    files = [_german_csv(tmp / f"fahrt{i}.csv", c) for i in (1, 2)]
    (tmp / "german.toml").write_text(GERMAN_MAPPING)
    ran = run_cli("dataset", "import", *files, "--mapping", tmp / "german.toml", "-o", tmp / "de")
    assert ran.returncode == 0, ran.stderr
    ran = run_cli("tune", tmp / "de", "-m", "manual", "-q", "-o", tmp / "tuned.json")
    assert ran.returncode == 0, ran.stderr
    return tmp / "de", tmp / "tuned.json"


def test_estimate_without_a_dataset_refuses_a_file_tuned_on_another(german, tmp_path):
    dataset, tuned = german
    ran = run_cli("estimate", "--params", tuned, "-o", tmp_path / "e", "--no-plot")
    assert ran.returncode == EXIT_BAD_INPUT
    assert ran.stderr == (
        f"kftune: error: {tuned}: the parameters were tuned on dataset 'german', but no "
        "dataset was given and the bundled one is 'default'; name the dataset to run them on "
        f"(kftune estimate DATASET --params {tuned}; 'default' for the bundled one)\n"
    )
    assert not (tmp_path / "e").exists()
    ran = run_cli("estimate", dataset, "--params", tuned, "-o", tmp_path / "e", "--no-plot")
    assert ran.returncode == 0, ran.stderr
    assert sorted(p.name for p in (tmp_path / "e").iterdir()) == ["fahrt1.csv", "fahrt2.csv"]


def test_the_import_provenance_is_the_manifests_meta_table(german):
    """What the README says the [meta] table of manifest.toml records."""
    dataset, _ = german
    meta = tomllib.loads((dataset / "manifest.toml").read_text())["meta"]
    assert meta["imported_from"] == ["fahrt1.csv", "fahrt2.csv"]
    assert meta["mapping"] == "german.toml"
    assert len(meta["kept_s"]) == len(meta["recorded_s"]) == 2
    assert meta["split"] == "test = ['*2']" and meta["model"] == "single-track"


def test_the_demo_prints_r_as_numbers():
    ran = run_cli("demo")
    line = next(x for x in ran.stdout.splitlines() if "UKF q = " in x)
    shown = line.split("r = ", 1)[1]
    assert "'" not in shown
    r = json.loads(shown)  # a list of numbers, as JSON reads it
    doc = json.loads(run_cli("demo", "--json").stdout)
    assert r == pytest.approx(doc["r"], rel=5e-3)
