"""Loading and writing: round trips, manifest errors, unit conversion, column-per-file and
MATLAB recordings, segmentation."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from kftune.data import (
    SIDESLIP_CHANNELS,
    Dataset,
    import_recordings,
    load_dataset,
    open_dataset,
    save_dataset,
)
from kftune.data.io import read_csv
from kftune.data.validate import STANDARD_GRAVITY
from kftune.errors import DataError, DataWarning
from test_data_helpers import synthetic_channels, synthetic_dataset, synthetic_manoeuvre

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _same(a: Dataset, b: Dataset) -> None:
    assert (a.name, a.description, a.dt, a.vehicle) == (b.name, b.description, b.dt, b.vehicle)
    assert a.names == b.names
    for x, y in zip(a.manoeuvres, b.manoeuvres):
        assert x.equals(y), x.name


def test_a_raw_recording_is_pointed_to_the_importer(tmp_path):
    """A user's CSV given where a dataset goes: say what it is not and how to import it."""
    rec = tmp_path / "drive4.csv"
    rec.write_text("time_s,vx_kmh\n0,50\n")
    with pytest.raises(
        DataError, match=r"not a kftune dataset .*kftune dataset import drive4\.csv"
    ):
        load_dataset(rec)


@pytest.mark.parametrize("compress", [True, False])
def test_round_trip_is_bit_exact(tmp_path, compress):
    ds = synthetic_dataset()
    manifest = save_dataset(ds, tmp_path, compress=compress)
    back = load_dataset(tmp_path)
    _same(ds, back)
    assert dict(back.meta) == {"origin": "tests", "units": {"vy_true": "m/s"}}
    assert load_dataset(manifest).names == ds.names  # the manifest file itself works too
    # writing what was read gives the same bytes
    again = tmp_path / "again"
    save_dataset(back, again, compress=compress)
    for f in tmp_path.iterdir():
        if f.is_file():
            assert (again / f.name).read_bytes() == f.read_bytes(), f.name


def test_round_trip_of_the_bundled_dataset(tmp_path):
    ds = open_dataset(None)
    sub = ds.subset(["train-03-j-turn", "test-21-spiral"])
    save_dataset(sub, tmp_path)
    _same(sub, load_dataset(tmp_path))


def test_json_manifest(tmp_path):
    save_dataset(synthetic_dataset(), tmp_path)
    data = tomllib.loads((tmp_path / "manifest.toml").read_text())
    (tmp_path / "manifest.toml").unlink()
    (tmp_path / "manifest.json").write_text(json.dumps(data))
    _same(synthetic_dataset(), load_dataset(tmp_path))


def _edit_manifest(path: Path, edit) -> Path:
    text = (path / "manifest.toml").read_text()
    (path / "manifest.toml").write_text(edit(text))
    return path / "manifest.toml"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: s.replace('file = "tr1.csv"', 'file = "nope.csv"'), "missing file 'nope.csv'"),
        (lambda s: s.replace('format = "kftune-dataset"', 'format = "other"'), "format"),
        (
            lambda s: s.replace("format_version = 1", "format_version = 7"),
            "expected 1 (the version",
        ),
        (lambda s: s.replace('split = "test"', 'split = "validation"', 1), "split"),
        (lambda s: s.replace('name = "tr1"', 'name = "tr0"'), "appears twice"),
        (lambda s: s.replace("dt = 0.01", "dt = -1.0"), "dt"),
        (lambda s: s.replace("m = 1093", "m = -1093"), "vehicle"),
        (lambda s: s.replace("[units]", "colour = 3\n[units]"), "unknown vehicle parameter"),
        (lambda s: "extra_key = 1\n" + s, "field 'extra_key': unknown; expected some of"),
        (lambda s: s.replace('r = "rad/s"', 'r = "furlong/s"'), "unknown unit"),
        (lambda s: s.replace('r = "rad/s"', 'r = "m/s"'), "angular rate"),
        (lambda s: s.replace('vy_true = "m/s"\n', ""), "unknown column"),
        (lambda s: s.replace('kind = "slalom"\n', "", 1), "kind"),
        (lambda s: s.replace("[[manoeuvres]]", '[[manoeuvres]]\nweather = "dry"', 1), "weather"),
        (lambda s: s + "\n[[[", "not valid TOML"),
    ],
)
def test_manifest_errors_name_the_manifest_and_field(tmp_path, edit, message):
    save_dataset(synthetic_dataset(), tmp_path, compress=False)
    manifest = _edit_manifest(tmp_path, edit)
    with pytest.raises(DataError) as info:
        load_dataset(tmp_path)
    assert message in str(info.value)
    assert info.value.file in (str(manifest), str(tmp_path / "tr0.csv"), str(tmp_path / "tr1.csv"))


def test_not_a_dataset(tmp_path):
    with pytest.raises(DataError, match="no manifest"):
        load_dataset(tmp_path)
    with pytest.raises(DataError, match="not found"):
        load_dataset(tmp_path / "absent")
    with pytest.raises(DataError, match="revs-250lm layout"):
        open_dataset(tmp_path)


def test_csv_column_errors(tmp_path):
    m = synthetic_manoeuvre()
    lines = ["t,delta,ax,ay,r,vx,beta_ref"] + [
        ",".join(repr(float(m.channel(c)[i])) for c in SIDESLIP_CHANNELS) for i in range(m.n)
    ]
    f = tmp_path / "x.csv"
    si = dict.fromkeys(SIDESLIP_CHANNELS, 1.0)
    f.write_text("\n".join(lines).replace("beta_ref", "beta", 1))
    with pytest.raises(DataError) as info:
        read_csv(f, si)
    assert info.value.column == "beta" and info.value.row == 1
    f.write_text("\n".join(lines).replace(",beta_ref", "", 1))
    with pytest.raises(DataError) as info:
        read_csv(f, si)
    assert info.value.row == 2 and "the header has 6" in str(info.value)  # rows disagree
    f.write_text("\n".join(lines).replace("t,", "time,", 1))
    with pytest.raises(DataError, match="missing the time column") as info:
        read_csv(f, {**si, "time": 1.0})
    assert (info.value.column, info.value.row) == ("t", 1)
    f.write_text("t,t,delta,ax,ay,r,vx,beta_ref\n")
    with pytest.raises(DataError, match="duplicated column"):
        read_csv(f, si)
    f.write_text("t,delta,ax,ay,r,vx,beta_ref\n")
    with pytest.raises(DataError, match="no data rows"):
        read_csv(f, si)
    f.write_text("\n".join([*lines[:50], "", *lines[50:]]))
    with pytest.raises(DataError, match="empty line") as info:
        read_csv(f, si)
    assert info.value.row == 51


def test_manifest_units_convert_to_si(tmp_path):
    """A dataset whose files are in deg, deg/s, km/h and g loads in SI."""
    ds = synthetic_dataset(1, 1)
    save_dataset(ds, tmp_path, compress=False)
    scale = {
        "delta": 180 / math.pi,
        "r": 180 / math.pi,
        "vx": 3.6,
        "ay": 1 / STANDARD_GRAVITY,
        "beta_ref": 180 / math.pi,
    }
    for m in ds.manoeuvres:
        cols = {c: m.channel(c) * scale.get(c, 1.0) for c in m.channel_names}
        text = (
            ",".join(cols)
            + "\n"
            + "\n".join(",".join(repr(float(v[i])) for v in cols.values()) for i in range(m.n))
        )
        (tmp_path / f"{m.name}.csv").write_text(text)
    _edit_manifest(
        tmp_path,
        lambda s: (
            s.replace('delta = "rad"', 'delta = "deg"')
            .replace('r = "rad/s"', 'r = "deg/s"')
            .replace('vx = "m/s"', 'vx = "km/h"')
            .replace('ay = "m/s^2"', 'ay = "g"')
            .replace('beta_ref = "rad"', 'beta_ref = "deg"')
        ),
    )
    back = load_dataset(tmp_path)
    for a, b in zip(ds.manoeuvres, back.manoeuvres):
        for c in ("delta", "r", "vx", "ay", "beta_ref"):
            np.testing.assert_allclose(b.channel(c), a.channel(c), rtol=1e-12, atol=1e-14)


# ----------------------------------------------------------------- mapped recordings
# (the importer, kftune's one path for recordings; its own tests: test_data_import.py)
def _recording(n: int = 3000) -> dict:
    c = synthetic_channels(n=n, seed=3, t0=12.5)
    return c


#: kftune channel → (source name, unit) of a user's recording.
USER_MAPPING = {
    "t": ("time_s", "s"),
    "delta": ("SteerAngle", "deg"),
    "ax": ("AccX", "g"),
    "ay": ("AccY", "g"),
    "r": ("YawRate", "deg/s"),
    "vx": ("Speed", "km/h"),
    "beta_ref": ("Beta", "deg"),
    "vy_true": ("Vy", "m/s"),
}
USER_SCALE = {
    "time_s": 1.0,
    "SteerAngle": 180 / math.pi,
    "AccX": 1 / STANDARD_GRAVITY,
    "AccY": 1 / STANDARD_GRAVITY,
    "YawRate": 180 / math.pi,
    "Speed": 3.6,
    "Beta": 180 / math.pi,
    "Vy": 1.0,
}


def _mapping(channels: dict = USER_MAPPING, vehicle: str = "revs-250lm", **top) -> dict:
    """An import mapping (as a dict) of ``channels``: channel → (source, unit)."""
    return {
        "vehicle": vehicle,
        **top,
        "channels": {c: {"column": s, "unit": u} for c, (s, u) in channels.items()},
    }


def _user_signals(c: dict) -> dict:
    src = {
        "time_s": c["t"],
        "SteerAngle": c["delta"],
        "AccX": c["ax"],
        "AccY": c["ay"],
        "YawRate": c["r"],
        "Speed": c["vx"],
        "Beta": c["beta_ref"],
        "Vy": 20 * c["beta_ref"],
    }
    return {k: v * USER_SCALE[k] for k, v in src.items()}


def test_column_files_with_mapping_and_segments(tmp_path):
    c = _recording()
    folder = tmp_path / "run"
    folder.mkdir()
    for name, values in _user_signals(c).items():
        (folder / f"{name}.txt").write_text(
            "% exported by a logger\n" + "\n".join(f"{v:.12e}" for v in values) + "\n"
        )
    ds = import_recordings([folder], _mapping(segment_length=5.0))
    assert ds.names == ("run-s01", "run-s02", "run-s03", "run-s04", "run-s05", "run-s06")
    assert [m.split for m in ds.manoeuvres] == ["train", "test", "test", "train", "test", "test"]
    assert sum(m.n for m in ds.manoeuvres) == c["t"].size
    whole = np.concatenate([m.r for m in ds.manoeuvres])
    np.testing.assert_allclose(whole, c["r"], rtol=1e-11)
    np.testing.assert_allclose(np.concatenate([m.vx for m in ds.manoeuvres]), c["vx"], rtol=1e-11)
    assert ds.manoeuvres[0].t[0] == pytest.approx(12.5)
    assert "vy_true" in ds.manoeuvres[0].extra


def test_column_files_errors_name_the_file(tmp_path):
    c = _recording(500)
    sig = _user_signals(c)
    for name, values in sig.items():
        (tmp_path / f"{name}.txt").write_text("\n".join(repr(float(v)) for v in values))
    # yaw rate declared rad/s although the file holds deg/s
    bad = dict(USER_MAPPING, r=("YawRate", "rad/s"))
    with pytest.raises(DataError) as info:
        import_recordings([tmp_path], _mapping(bad))
    assert info.value.file == str(tmp_path / "YawRate.txt") and info.value.column == "r"
    with pytest.raises(DataError, match="map t to the time column"):
        import_recordings([tmp_path], _mapping({k: v for k, v in USER_MAPPING.items() if k != "t"}))
    with pytest.raises(DataError, match=r"no file 'AccelX\.txt' in the folder") as info:
        import_recordings([tmp_path], _mapping(dict(USER_MAPPING, ax=("AccelX", "g"))))
    assert info.value.file == str(tmp_path)
    with pytest.raises(DataError, match="angle"):
        import_recordings([tmp_path], _mapping(dict(USER_MAPPING, delta=("SteerAngle", "km/h"))))
    (tmp_path / "Speed.txt").write_text("\n".join(repr(float(v)) for v in sig["Speed"][:-3]))
    with pytest.raises(DataError, match="aligned sample by sample") as info:
        import_recordings([tmp_path], _mapping())
    assert info.value.file == str(tmp_path / "Speed.txt") and info.value.row == 498


@pytest.mark.parametrize("struct", [None, "log.signals"])
def test_mat_recording(tmp_path, struct):
    c = _recording(1200)
    sig = {k: v.reshape(-1, 1) for k, v in _user_signals(c).items()}  # MATLAB column vectors
    f = tmp_path / "run.mat"
    scipy.io.savemat(f, sig if struct is None else {"log": {"signals": sig}})
    source = {} if struct is None else {"source": {"struct": struct}}
    with pytest.warns(DataWarning, match="makes none of the 1 manoeuvre test"):  # uncut
        ds = import_recordings([f], _mapping(vehicle="bmw-320i", **source))
    assert len(ds) == 1 and ds.manoeuvres[0].name == "run"
    m = ds.manoeuvres[0]
    np.testing.assert_allclose(m.ay, c["ay"], rtol=1e-12)
    np.testing.assert_allclose(m.delta, c["delta"], rtol=1e-12)
    with pytest.raises(DataError, match="not found"):
        import_recordings([f], _mapping(dict(USER_MAPPING, ax=("ACC", "g")), **source))


def test_mat_errors(tmp_path):
    c = _recording(400)
    sig = _user_signals(c)
    sig["AccY"] = np.vstack([sig["AccY"], sig["AccY"]])  # a matrix, not a vector
    f = tmp_path / "bad.mat"
    scipy.io.savemat(f, sig)
    with pytest.raises(DataError, match="numeric vector") as info:
        import_recordings([f], _mapping())
    assert info.value.column == "AccY"
    sig = _user_signals(c)
    sig["YawRate"] = sig["YawRate"].copy()
    sig["YawRate"][99] = np.nan
    scipy.io.savemat(f, sig)
    with pytest.raises(DataError, match=r"r \(source 'YawRate'\): 1 value\(s\) not a finite "
                       r"number, at row\(s\) 100 "):  # fmt: skip
        import_recordings([f], _mapping())  # 1-based, as MATLAB
    (tmp_path / "junk.mat").write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(DataError, match="MATLAB"):
        import_recordings([tmp_path / "junk.mat"], _mapping())
    with pytest.raises(DataError, match="struct"):
        import_recordings([tmp_path / "bad.mat"], _mapping(source={"struct": "nothere"}))
    sig = _user_signals(c)
    sig["Speed"] = sig["Speed"] + 1j  # a complex variable is refused, not silently cut
    scipy.io.savemat(f, sig)
    with pytest.raises(DataError, match="complex") as info:
        import_recordings([f], _mapping())
    assert (info.value.file, info.value.column) == (str(f), "Speed")


def test_segmentation_is_deterministic_and_documented(tmp_path):
    c = synthetic_channels(n=10_000)
    for name, values in c.items():
        (tmp_path / f"{name}.txt").write_text("\n".join(repr(float(v)) for v in values))
    mapping = {"vehicle": "bmw-320i", "channels": {k: k for k in c}}  # SI: no unit
    ds = import_recordings([tmp_path], mapping | {"segment_length": 10.0}, labels=["rec"])
    assert len(ds) == 10
    assert [i for i, m in enumerate(ds.manoeuvres) if m.split == "train"] == [0, 3, 6, 9]
    assert all(m.kind == "segment" for m in ds.manoeuvres)
    with pytest.warns(DataWarning, match="makes none of the 1 manoeuvre test"):
        one = import_recordings([tmp_path], mapping, labels=["rec"])
    assert one.names == ("rec",) and one.manoeuvres[0].split == "train"
    with pytest.raises(DataError, match=r"segment_length = 1.5 s .* \(segment_length >= 2 s"):
        import_recordings([tmp_path], mapping | {"segment_length": 1.5}, labels=["rec"])


def test_manifest_dt_that_disagrees_with_a_file_names_the_file(tmp_path):
    save_dataset(synthetic_dataset(1, 1), tmp_path)
    manifest = tmp_path / "manifest.toml"
    manifest.write_text(manifest.read_text().replace("dt = 0.01", "dt = 0.02"))
    with pytest.raises(DataError, match="differs from the manifest's dt") as info:
        load_dataset(tmp_path)
    assert info.value.file.endswith(".csv.gz") and info.value.column == "t"


def test_dataset_api():
    ds = synthetic_dataset(2, 3)
    assert [m.name for m in ds.train] == ["tr0", "tr1"]
    assert [m.name for m in ds.test] == ["te0", "te1", "te2"]
    sub = ds.subset(["te2", "tr0"])
    assert sub.names == ("te2", "tr0") and sub.vehicle == ds.vehicle
    with pytest.raises(KeyError, match="has no manoeuvre"):
        ds.subset(["nope"])
    with pytest.raises(DataError, match="duplicated"):
        Dataset("d", ds.vehicle, 0.01, (ds.manoeuvres[0], ds.manoeuvres[0]))
    with pytest.raises(DataError, match="sample time"):
        Dataset("d", ds.vehicle, 0.02, ds.manoeuvres)
    assert ds.r_default.shape == (3,) and np.all(ds.r_default > 0)


def test_pickle_round_trip():
    """Manoeuvres and datasets travel to worker processes."""
    import pickle

    ds = synthetic_dataset()
    back = pickle.loads(pickle.dumps(ds))
    _same(ds, back)
    assert dict(back.meta) == dict(ds.meta)
    m = pickle.loads(pickle.dumps(ds.manoeuvres[0]))
    assert m.equals(ds.manoeuvres[0]) and not m.ay.flags.writeable
