"""``kftune dataset import`` and :func:`kftune.data.importer.import_recordings`: each reader
on a tiny file written here, unit conversions against closed-form values, derived channels,
standstill trimming, merging with a train/test rule, errors, missing extras, the CLI."""

from __future__ import annotations

import codecs
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from conftest import run_cli
from kftune.cli import EXIT_BAD_INPUT, main
from kftune.data import load_dataset
from kftune.data.importer import import_recordings, read_mapping
from kftune.errors import ConfigError, DataError, DataWarning
from test_data_helpers import synthetic_channels

G = 9.80665  # standard gravity: the unit g

# most imports here are of one uncut recording, which the default rule cannot split
pytestmark = pytest.mark.filterwarnings("ignore:.*makes none of the:kftune.errors.DataWarning")

RATIO = 16.0
KMH = 1 / 3.6
DEG = math.pi / 180


def _recording(n: int = 400, dt: float = 0.01, still: int = 0, seed: int = 0) -> dict:
    """SI channels of a drive with ``still`` samples of standstill first, plus vy."""
    c = synthetic_channels(n=n, dt=dt, seed=seed)
    c["vy"] = c["vx"] * np.tan(c["beta_ref"])
    if still:
        c = {k: np.concatenate([np.zeros(still), v]) for k, v in c.items()}
        c["t"] = np.arange(n + still) * dt
    return c


def _user_units(c: dict) -> dict:
    """The signals as a logger writes them: km/h, g, deg/s, a hand-wheel angle, bar, N."""
    return {
        "time": c["t"],
        "Speed": c["vx"] / KMH,
        "AccX": c["ax"],
        "AccY": c["ay"] / G,
        "YawRate": c["r"] / DEG,
        "SWA": c["delta"] * RATIO / DEG,
        "Vx": c["vx"] / KMH,
        "Vy": c["vy"] / KMH,
        "BrakeP": 2.0 + c["ax"],  # bar
        "Fz": 4000.0 + 10 * c["ay"],  # N
    }


CHANNELS = {
    "vx": {"column": "Speed", "unit": "km/h"},
    "ax": {"column": "AccX", "unit": "m/s^2"},
    "ay": {"column": "AccY", "unit": "g"},
    "r": {"column": "YawRate", "unit": "deg/s"},
    "delta": {"column": "SWA", "unit": "deg", "hand_wheel": True},
    "beta_ref": {"atan2": ["Vy", "Vx"], "unit": "km/h"},
    "p_brake": {"column": "BrakeP", "unit": "bar"},
    "fz": {"column": "Fz", "unit": "N"},
}


def _mapping(**top) -> dict:
    return {"vehicle": "bmw-320i", "steering_ratio": RATIO, "channels": dict(CHANNELS), **top}


def _check(m, user: dict, rows: slice = slice(None)) -> None:
    """A manoeuvre's channels against the closed-form conversions of what was written."""
    u = {k: np.asarray(v)[rows] for k, v in user.items()}
    close = {"rtol": 1e-12, "atol": 1e-12}
    np.testing.assert_allclose(m.vx, u["Speed"] / 3.6, **close)
    np.testing.assert_allclose(m.ay, u["AccY"] * 9.80665, **close)
    np.testing.assert_allclose(m.r, np.radians(u["YawRate"]), **close)
    np.testing.assert_allclose(m.delta, np.radians(u["SWA"]) / RATIO, **close)
    np.testing.assert_allclose(m.beta_ref, np.arctan2(u["Vy"], u["Vx"]), **close)
    np.testing.assert_allclose(m.channel("p_brake"), u["BrakeP"] * 1e5, **close)
    np.testing.assert_allclose(m.channel("fz"), u["Fz"], **close)


def _write_csv(path: Path, user: dict, sep: str = ";", units: dict | None = None) -> Path:
    names = list(user)
    lines = [sep.join(names)]
    if units is not None:
        lines.append(sep.join(units.get(n, "") for n in names))
    lines += [sep.join(v if isinstance(v, str) else repr(float(v)) for v in row)
              for row in zip(*user.values())]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


# ------------------------------------------------------------------------------ formats
def test_csv_with_semicolons_and_a_units_row(tmp_path):
    user = _user_units(_recording())
    units = {"time": "s", "Speed": "km/h", "AccX": "m/s^2", "AccY": "g", "YawRate": "deg/s",
             "SWA": "deg", "Vx": "km/h", "Vy": "km/h", "BrakeP": "bar", "Fz": "N"}  # fmt: skip
    src = _write_csv(tmp_path / "run.csv", {"note": ["x"] * user["time"].size, **user}, units=units)
    # units come from the file: the mapping names only the columns (and the derived ones)
    channels = {c: {k: v for k, v in s.items() if k != "unit"} for c, s in CHANNELS.items()}
    channels["beta_ref"]["unit"] = "km/h"
    mapping = _mapping(channels={"t": "time", **channels}, source={"units_row": True})
    import_recordings([src], mapping, tmp_path / "ds")
    ds = load_dataset(tmp_path / "ds")
    (m,) = ds.manoeuvres
    _check(m, user)
    np.testing.assert_array_equal(m.t, user["time"])
    assert ds.units["p_brake"] == "Pa" and ds.units["fz"] == "N"


def test_parquet(tmp_path):
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    user = _user_units(_recording())
    pq.write_table(pa.table({k: pa.array(v) for k, v in user.items()}), tmp_path / "run.parquet")
    ds = import_recordings([tmp_path / "run.parquet"], _mapping(sample_time=0.01))
    _check(ds.manoeuvres[0], user)


def test_mat_v5_without_time_trims_the_standstill(tmp_path):
    c = _recording(n=400, dt=0.005, still=150)
    user = _user_units(c)
    del user["time"]
    scipy.io.savemat(tmp_path / "run.mat", {"data": user})
    ds = import_recordings(
        [tmp_path / "run.mat"],
        _mapping(sample_time=0.005, min_speed="5 km/h", source={"struct": "data"}),
    )
    (m,) = ds.manoeuvres
    assert m.n == 400 and m.t[0] == pytest.approx(150 * 0.005)
    _check(m, user, slice(150, None))


def _savemat73(path: Path, variables: dict, struct: str) -> None:
    """A file in MATLAB's v7.3 layout: a 512-byte header, then HDF5 with each variable
    stored transposed (an n×1 MATLAB vector is a 1×n dataset) and tagged MATLAB_class."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w", userblock_size=512) as f:
        group = f.create_group(struct)
        group.attrs["MATLAB_class"] = np.bytes_("struct")
        for name, values in variables.items():
            ds = group.create_dataset(name, data=np.asarray(values, dtype=float)[None, :])
            ds.attrs["MATLAB_class"] = np.bytes_("double")
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5"
    with open(path, "r+b") as fh:
        fh.write(header.ljust(116) + b"\0" * 8 + b"\x00\x02IM")


def test_mat_v73(tmp_path):
    user = _user_units(_recording())
    _savemat73(tmp_path / "run.mat", user, "rec")
    mapping = _mapping(channels={"t": "time", **CHANNELS}, source={"struct": "rec"})
    _check(import_recordings([tmp_path / "run.mat"], mapping).manoeuvres[0], user)


def test_mdf_two_rasters_resampled_onto_the_finest(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t_fast = np.arange(0.0, 4.0, 0.01)  # 100 Hz
    t_slow = np.arange(0.02, 4.2, 0.02)  # 50 Hz, starts later, ends later
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(72 + np.sin(t_fast), t_fast, name="Speed", unit="km/h")])
    mdf.append([asammdf.Signal(10 * np.cos(t_slow), t_slow, name="YawRate", unit="deg/s")])
    mdf.save(tmp_path / "run.mf4", overwrite=True)
    mdf.close()
    mapping = {"channels": {"vx": "Speed", "r": "YawRate"}}  # units from the file
    (m,) = import_recordings([tmp_path / "run.mf4"], mapping).manoeuvres
    grid = t_fast[(t_fast >= 0.02 - 1e-12) & (t_fast <= t_fast[-1])]  # the span both cover
    np.testing.assert_allclose(m.t, grid)
    np.testing.assert_allclose(m.vx, (72 + np.sin(grid)) / 3.6, rtol=1e-12)
    expected = np.radians(np.interp(grid, t_slow, 10 * np.cos(t_slow)))  # linear
    np.testing.assert_allclose(m.r, expected, rtol=1e-12)


# ------------------------------------------------------------------------------ merging
def _three_mat_files(tmp_path: Path) -> list[Path]:
    paths = []
    for i in range(3):
        user = _user_units(_recording(n=400, dt=0.005, still=100, seed=i))
        del user["time"]
        paths.append(tmp_path / f"file{i + 1}.mat")
        scipy.io.savemat(paths[-1], user)
    return paths


def test_three_recordings_merged_with_a_test_rule(tmp_path):
    mapping = _mapping(sample_time=0.005, min_speed=1.0, split={"test": ["file3*"]})
    ds = import_recordings(_three_mat_files(tmp_path), mapping, name="three")
    assert ds.names == ("file1", "file2", "file3")
    assert [m.split for m in ds.manoeuvres] == ["train", "train", "test"]
    assert all(m.n == 400 for m in ds.manoeuvres)  # standstill trimmed in each
    assert ds.dt == pytest.approx(0.005)
    frac = import_recordings(
        _three_mat_files(tmp_path), {**mapping, "split": {"test_fraction": 0.4}}
    )
    assert [m.split for m in frac.manoeuvres] == ["train", "train", "test"]


def test_reversing_and_a_stop_cut_a_recording_into_stretches(tmp_path):
    user = _user_units(_recording(n=1200, dt=0.01))
    user["Speed"][500:540] = -5.0  # reversing in the middle: two stretches
    user["Speed"][1150:] = 0.0  # a stop at the end
    scipy.io.savemat(tmp_path / "drive.mat", user)
    mapping = _mapping(channels={"t": "time", **CHANNELS}, min_speed=0.5, segment_length=2.5)
    ds = import_recordings([tmp_path / "drive.mat"], mapping)
    spans = [(m.t[0], m.t[-1]) for m in ds.manoeuvres]
    assert spans[0][0] == 0.0 and max(e for _, e in spans) == pytest.approx(11.49)
    assert not any(s <= 5.2 and e >= 5.0 for s, e in spans)  # the reversing is gone
    assert len(ds) == 4 and ds.names[0] == "drive-s01"


# ------------------------------------------------------------------------------ errors
def test_every_bad_channel_is_reported_with_file_column_and_rows(tmp_path):
    user = _user_units(_recording())
    user["YawRate"][[7, 9]] = np.nan
    user["SWA"][20:30] = 5000.0  # a hand-wheel angle of 312° after the ratio: implausible
    src = _write_csv(tmp_path / "bad.csv", user, sep="\t")
    with pytest.raises(DataError) as info:
        import_recordings([src], _mapping(channels={"t": "time", **CHANNELS}))
    text = str(info.value)
    assert str(src) in text and "2 bad channel(s)" in text
    assert "r (source 'YawRate')" in text and "row(s) 9, 11" in text  # file lines
    assert "delta (source 'SWA')" in text and "row(s) 22, 23, 24, …" in text


def test_a_missing_column_and_a_bad_value_name_file_column_and_row(tmp_path):
    user = _user_units(_recording())
    src = _write_csv(tmp_path / "run.csv", user, sep=",")
    with pytest.raises(DataError, match=r"column 'Speeed'.*not found.*'Speed'"):
        import_recordings([src], {"channels": {"t": "time", "vx": "Speeed"}})
    src.write_text(src.read_text().replace(repr(float(user["Speed"][4])), "fast", 1))
    with pytest.raises(DataError, match=r"run\.csv, column 'Speed', row 6: cannot read 'fast'"):
        import_recordings([src], {"channels": {"t": "time", "vx": "Speed"}})


def test_mapping_errors_name_the_key(tmp_path):
    src = _write_csv(tmp_path / "run.csv", _user_units(_recording()))
    for mapping, match in [
        ({"channels": {"vx": "Speed"}}, "no time: map t"),
        ({"channels": {"t": "time", "vx": {"column": "Speed", "unit": "bar"}}}, "pressure unit"),
        ({"channels": {"t": "time"}, "split": {"test": "x"}}, "split.test"),
        ({"channels": {"t": "time"}, "smaple_time": 1}, "'smaple_time': unknown"),
        ({"channels": {"t": "time", "ay": "AccY"}, "model": "single-track"}, "needs the chan"),
    ]:
        with pytest.raises(DataError, match=match):
            import_recordings([src], mapping)


@pytest.mark.parametrize(
    ("module", "suffix", "extra"),
    [("pyarrow", ".parquet", "parquet"), ("h5py", ".mat", "mat73"), ("asammdf", ".mf4", "mdf")],
)
def test_a_missing_reader_names_its_extra(tmp_path, monkeypatch, module, suffix, extra):
    src = tmp_path / f"run{suffix}"
    if suffix == ".mat":
        _savemat73(src, {"time": np.arange(300) * 0.01}, "rec")  # a v7.3 file needs h5py
    else:
        src.write_bytes(b"\0" * 64)
    for name in (module, f"{module}.parquet"):
        monkeypatch.setitem(sys.modules, name, None)  # import fails as if not installed
    with pytest.raises(ConfigError, match=rf"pip install 'kftune\[{extra}\]'"):
        import_recordings([src], {"channels": {"t": "time"}})


def test_cli_exit_code_for_bad_input(tmp_path, capsys):
    src = _write_csv(tmp_path / "run.csv", _user_units(_recording()))
    (tmp_path / "map.toml").write_text('[channels]\nt = "time"\nvx = "nope"\n')
    code = main(["dataset", "import", str(src), "--mapping", str(tmp_path / "map.toml"),
                 "-o", str(tmp_path / "ds")])  # fmt: skip
    assert code == EXIT_BAD_INPUT
    assert "column 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "ds" / "manifest.toml").exists()


def test_an_imported_dataset_folder_has_the_permissions_of_a_new_folder(tmp_path, capsys):
    """The dataset is written into a private temporary folder and renamed into place: the
    folder others read must get what ``mkdir`` gives (0o777 less the umask), not 0o700."""
    src = _write_csv(tmp_path / "run.csv", _user_units(_recording()))
    (tmp_path / "map.toml").write_text(
        '[channels]\nt = "time"\nvx = { column = "Speed", unit = "km/h" }\n'
    )
    (tmp_path / "plain").mkdir()
    code = main(["dataset", "import", str(src), "--mapping", str(tmp_path / "map.toml"),
                 "-o", str(tmp_path / "ds")])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert "Traceback" not in capsys.readouterr().err
    mode = (tmp_path / "ds").stat().st_mode & 0o777
    assert mode == (tmp_path / "plain").stat().st_mode & 0o777
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "map.toml", "plain", "run.csv"]


MAPPING_TOML = """
name = "cli-car"
vehicle = "bmw-320i"
model = "single-track"
sample_time = 0.005
min_speed = "3 km/h"
steering_ratio = 16.0

[split]
test = ["file3*"]

[channels]
vx = { column = "Speed", unit = "km/h" }
ax = { column = "AccX", unit = "m/s^2" }
ay = { column = "AccY", unit = "g" }
r = { column = "YawRate", unit = "deg/s" }
delta = { column = "SWA", unit = "deg", hand_wheel = true }
beta_ref = { atan2 = ["Vy", "Vx"], unit = "km/h" }
"""


@pytest.mark.slow
def test_cli_import_then_tune(tmp_path):
    files = _three_mat_files(tmp_path)
    (tmp_path / "map.toml").write_text(MAPPING_TOML)
    out = tmp_path / "ds"
    imp = run_cli(
        "dataset", "import", *map(str, files), "--mapping", str(tmp_path / "map.toml"),
        "-o", str(out),
    )  # fmt: skip
    assert imp.returncode == 0, imp.stderr
    assert "3 manoeuvres" in imp.stdout and "1 test" in imp.stdout
    tune = run_cli(
        "tune", str(out), "-m", "random", "--budget", "3", "-o", str(tmp_path / "t.json")
    )
    assert tune.returncode == 0, tune.stderr
    assert (tmp_path / "t.json").is_file()


def test_the_readme_mapping_example_is_valid():
    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    block = readme.split("# my-car.toml\n", 1)[1].split("```", 1)[0]
    m = read_mapping(tomllib.loads(block))
    assert m.split == ("test", ["run3*"]) and m.min_speed == pytest.approx(3 / 3.6)
    assert m.channels["delta"].hand_wheel and m.channels["beta_ref"].sources == ("Vy", "Vx")


# ------------------------------------------------------------------------------ review fixes
def _drive_csv(tmp_path: Path, name: str = "run.csv", **kw) -> tuple[Path, dict]:
    user = _user_units(_recording(**kw))
    return _write_csv(tmp_path / name, user, sep=","), user


TIMED = {"t": "time", **CHANNELS}


@pytest.mark.parametrize(
    ("vehicle", "where"),
    [("revs-250lm", "vehicle 'revs-250lm'"), ({"m": 1093.3, "Iz": 1791.6, "a": 1.156,
     "b": 1.423, "h": 0.575, "C_af": 55600.0, "C_ar": 68220.0, "mu": 1.05},
     "the [vehicle] table")],
)  # fmt: skip
def test_a_hand_wheel_channel_with_a_vehicle_without_a_ratio_names_the_key(
    tmp_path, vehicle, where
):
    src, _ = _drive_csv(tmp_path)
    mapping = {"vehicle": vehicle, "channels": TIMED}  # no steering_ratio anywhere
    with pytest.raises(DataError) as info:
        import_recordings([src], mapping)
    text = str(info.value)
    assert "key 'channels.delta.hand_wheel'" in text and f"{where} has no steering_ratio" in text
    assert "give steering_ratio = " in text


def test_the_model_refuses_standstill_at_import_naming_the_file_row(tmp_path):
    user = _user_units(_recording(n=600))
    user["Speed"][300] = 0.0  # one sample at standstill: the single-track model refuses it
    src = _write_csv(tmp_path / "stop.csv", user, sep=",")
    with pytest.raises(DataError) as info:
        import_recordings([src], _mapping(channels=TIMED, model="single-track"))
    e = info.value
    # the header is row 1: sample 300 is on line 302 of the file
    assert (e.file, e.column, e.row) == (str(src), "vx", 302)
    assert "model 'single-track' refuses" in str(e) and "min_speed" in str(e)
    ds = import_recordings([src], _mapping(channels=TIMED, model="single-track", min_speed=1.0))
    assert [m.n for m in ds.manoeuvres] == [300, 299]  # cut at the stop


def test_the_sample_time_of_late_timestamps_has_no_binary_noise(tmp_path):
    user = _user_units(_recording())
    user["time"] = 100.0 + np.arange(user["time"].size) * 0.01  # 100.01 − 100.0 ≠ 0.01 in binary
    src = _write_csv(tmp_path / "late.csv", user, sep=",")
    ds = import_recordings([src], _mapping(channels=TIMED), tmp_path / "ds")
    assert ds.dt == 0.01 and ds.manoeuvres[0].dt == 0.01
    assert "\ndt = 0.01\n" in (tmp_path / "ds" / "manifest.toml").read_text()


def test_a_cp1252_file_needs_its_encoding(tmp_path):
    user = _user_units(_recording())
    names = ["time", "Speed", "YawRate", "SWA", "AccY"]
    lines = [",".join(names), "s,km/h,°/s,°,g"]  # the units row: 0xb0 in cp1252
    lines += [",".join(repr(float(user[n][k])) for n in names) for k in range(user["time"].size)]
    src = tmp_path / "win.csv"
    src.write_bytes("\r\n".join(lines).encode("cp1252"))
    channels = {"t": "time", "vx": "Speed", "r": "YawRate", "ay": "AccY",
                "delta": {"column": "SWA", "hand_wheel": True}}  # fmt: skip
    mapping = _mapping(channels=channels, source={"units_row": True})
    with pytest.raises(DataError, match=r'row 2: not UTF-8.*encoding = "cp1252"') as info:
        import_recordings([src], mapping)
    assert info.value.file == str(src)
    mapping["source"]["encoding"] = "cp1252"
    (m,) = import_recordings([src], mapping).manoeuvres
    np.testing.assert_allclose(m.r, user["YawRate"] * math.pi / 180, rtol=1e-12)
    np.testing.assert_allclose(m.delta, user["SWA"] * math.pi / 180 / RATIO, rtol=1e-12)


@pytest.mark.parametrize(
    ("encoding", "message"),
    [("nope", "unknown text encoding 'nope'"), ("base64", "unknown text encoding"),
     ("utf-16", "'utf-16' does not write ASCII as ASCII"), (1252, "expected a codec name"),
     ("undefined", "unknown text encoding 'undefined'")],
)  # fmt: skip
def test_a_bad_encoding_names_the_key(encoding, message):
    with pytest.raises(DataError, match=rf"key 'source\.encoding': {message}"):
        read_mapping({"channels": {"t": "time"}, "source": {"encoding": encoding}})


def test_excel_utf8_csv_reads_with_any_encoding_named(tmp_path):
    """Excel's "CSV UTF-8" starts with a byte-order mark: its name (utf-8-sig) is a valid
    encoding, and the mark is honoured whatever encoding the mapping names (cp1252 read it
    into the first column's name)."""
    src, user = _drive_csv(tmp_path)
    bom = tmp_path / "excel.csv"
    bom.write_bytes(codecs.BOM_UTF8 + src.read_bytes())
    for encoding in ("utf-8-sig", "cp1252", "latin-1"):
        mapping = _mapping(channels=TIMED, source={"encoding": encoding})
        (m,) = import_recordings([bom], mapping).manoeuvres
        _check(m, user)


def test_a_txt_export_is_read_as_the_format_the_mapping_names(tmp_path):
    src, user = _drive_csv(tmp_path, "logger.txt")
    with pytest.raises(DataError, match=r'unknown file type.*\[source\] format = "csv"'):
        import_recordings([src], _mapping(channels=TIMED))
    (m,) = import_recordings([src], _mapping(channels=TIMED, source={"format": "CSV"})).manoeuvres
    _check(m, user)
    with pytest.raises(DataError, match=r"key 'source\.format': unknown format 'xls'.*'csv'"):
        read_mapping({"channels": {"t": "time"}, "source": {"format": "xls"}})
    # "tsv" means tab, as the suffix does: header names with commas stay whole
    user = {"time, s" if k == "time" else k: v for k, v in user.items()}
    tab = _write_csv(tmp_path / "logger2.txt", user, sep="\t")
    mapping = _mapping(channels={**TIMED, "t": "time, s"}, source={"format": "tsv"})
    (m,) = import_recordings([tab], mapping).manoeuvres
    _check(m, {**user, "time": user["time, s"]})
    assert read_mapping({"channels": {"t": "t"}, "source": {"format": "TSV"}}).options == {
        "delimiter": "\t"
    }  # not sniffed: a header with more commas than tabs is still split at the tabs


def test_a_raster_step_without_a_space_is_a_quantity():
    with pytest.raises(DataError, match=r"key 'source\.raster': expected a number or '<number>"):
        read_mapping({"channels": {"t": "time"}, "source": {"raster": "10ms"}})
    assert read_mapping({"channels": {"t": "time"}, "source": {"raster": "10 ms"}}).raster_step == (
        pytest.approx(0.01)
    )


def _jittered(tmp_path: Path, n: int = 600) -> tuple[Path, dict]:
    """A CSV logged at 10 ms whose timestamps jitter by up to ±0.4 ms, with a brake
    pressure linear in time (so that linear interpolation reproduces it exactly)."""
    user = _user_units(_recording(n=n))
    user["time"] = user["time"] + np.random.default_rng(1).uniform(-4e-4, 4e-4, n)
    user["BrakeP"] = 2.0 + 0.1 * user["time"]
    return _write_csv(tmp_path / "jitter.csv", user, sep=","), user


def test_jittered_timestamps_suggest_and_take_a_raster(tmp_path):
    src, user = _jittered(tmp_path)
    with pytest.raises(DataError, match=r"irregular sample time.*\[source\] raster = 0\.01\b"):
        import_recordings([src], _mapping(channels=TIMED))
    (m,) = import_recordings([src], _mapping(channels=TIMED, source={"raster": "10 ms"})).manoeuvres
    t0, t_end = user["time"][0], user["time"][-1]
    assert m.n >= user["time"].size - 1 and m.t[-1] <= t_end
    np.testing.assert_allclose(m.t, t0 + np.arange(m.n) * 0.01, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.channel("p_brake"), (2.0 + 0.1 * m.t) * 1e5, rtol=1e-12)


def test_a_raster_never_bridges_a_gap(tmp_path):
    user = _user_units(_recording(n=600))
    kept = np.r_[0:300, 340:600]  # 0.4 s lost after sample 299
    src = _write_csv(tmp_path / "gap.csv", {k: v[kept] for k, v in user.items()}, sep=",")
    with pytest.raises(DataError, match=r"a gap in the recording: step 0\.4\d* s") as info:
        import_recordings([src], _mapping(channels=TIMED, source={"raster": 0.01}))
    assert (info.value.column, info.value.row) == ("t", 302)  # line of the sample after it
    with pytest.raises(DataError, match=r"irregular.*split it at the gap \(split_at_gaps = true"):
        import_recordings([src], _mapping(channels=TIMED))


def test_split_at_gaps_keeps_each_side_of_a_dropout(tmp_path):
    """A logger dropout refused by default (above) is cut out with split_at_gaps: each side
    is a manoeuvre with the file's samples, also when resampled onto a raster; a piece too
    short to be a manoeuvre is dropped, and none long enough is an error."""
    user = _user_units(_recording(n=700))
    kept = np.r_[0:300, 340:600, 650:700]  # gaps after samples 299 and 599; 50 at the end
    src = _write_csv(tmp_path / "gap.csv", {k: v[kept] for k, v in user.items()}, sep=",")
    ds = import_recordings([src], _mapping(channels=TIMED, split_at_gaps=True))
    assert [m.n for m in ds.manoeuvres] == [300, 260]
    np.testing.assert_array_equal(ds.manoeuvres[1].t, user["time"][340:600])
    np.testing.assert_allclose(ds.manoeuvres[1].r, user["YawRate"][340:600] * math.pi / 180)
    assert ds.meta["kept_s"] == [pytest.approx(2.99 + 2.59)]
    jitter = user["time"] + np.random.default_rng(2).uniform(-4e-4, 4e-4, user["time"].size)
    src = _write_csv(
        tmp_path / "jg.csv", {k: v[kept] for k, v in {**user, "time": jitter}.items()}, sep=","
    )
    mapping = _mapping(channels=TIMED, split_at_gaps=True, source={"raster": 0.01})
    ds = import_recordings([src], mapping)
    for m, (a, b) in zip(ds.manoeuvres, [(0, 299), (340, 599)], strict=True):
        # the 10 ms grid from each side's first timestamp to within one step of its last
        assert m.t[0] == jitter[a] and m.t[-1] <= jitter[b] < m.t[-1] + 0.01
        np.testing.assert_allclose(np.diff(m.t), 0.01, rtol=0, atol=1e-12)
    with pytest.raises(DataError, match=r"no stretch of at least 200 samples and 4 s between"):
        import_recordings([src], _mapping(channels=TIMED, split_at_gaps=True, min_duration=4.0))
    with pytest.raises(DataError, match=r"key 'split_at_gaps': expected true or false"):
        read_mapping({"channels": {"t": "time"}, "split_at_gaps": "yes"})


def test_errors_in_resampled_data_say_their_rows_are_raster_samples(tmp_path):
    src, user = _jittered(tmp_path)
    lines = src.read_text().splitlines()
    cells = lines[101].split(",")  # line 102: sample 100
    cells[list(user).index("AccY")] = "nan"
    lines[101] = ",".join(cells)
    src.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"resampled: a row counts 0\.01 s raster samples"):
        import_recordings([src], _mapping(channels=TIMED, source={"raster": 0.01}))
    with pytest.raises(DataError, match=r"row\(s\) 102\b") as info:  # not resampled: the line
        import_recordings([src], _mapping(channels=TIMED))
    assert "(resampled:" not in str(info.value)


def test_a_raster_coarser_than_the_recording_warns(tmp_path):
    src, _ = _jittered(tmp_path, n=3000)
    with pytest.warns(DataWarning, match=r"raster = 0\.05 s is coarser .* anti-alias"):
        (m,) = import_recordings(
            [src], _mapping(channels=TIMED, source={"raster": 0.05})
        ).manoeuvres
    assert m.dt == 0.05


def test_a_raster_applies_to_the_kept_stretches_only(tmp_path):
    """A logger that pauses while parked: min_speed cuts the pause out, so a raster must
    not refuse the gap there (it was checked on the whole recording, before trimming)."""
    user = _user_units(_recording(n=1200))
    user["Speed"][550:650] = 0.0  # parked
    kept = np.r_[0:580, 620:1200]  # the logger paused while parked
    user["time"] = user["time"] + np.random.default_rng(0).uniform(-3e-4, 3e-4, 1200)
    src = _write_csv(tmp_path / "park.csv", {k: v[kept] for k, v in user.items()}, sep=",")
    mapping = _mapping(channels=TIMED, min_speed="3 km/h", source={"raster": 0.01})
    ds = import_recordings([src], mapping)
    assert len(ds.manoeuvres) == 2
    assert ds.manoeuvres[0].t[0] == user["time"][0]
    assert ds.manoeuvres[1].t[0] == user["time"][650]  # the first sample moving again


def test_a_raster_naming_a_signal_is_for_mdf_files(tmp_path):
    src, _ = _drive_csv(tmp_path)
    with pytest.raises(DataError, match=r"key 'source\.raster': 'Speed' names a signal"):
        import_recordings([src], _mapping(channels=TIMED, source={"raster": "Speed"}))


def test_a_numeric_raster_resamples_an_mdf_file(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t = np.arange(0.0, 4.0, 0.01)
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(72 + t, t, name="Speed", unit="km/h")])
    mdf.save(tmp_path / "run.mf4", overwrite=True)
    mdf.close()
    mapping = {"channels": {"vx": "Speed"}, "source": {"raster": 0.02}}
    (m,) = import_recordings([tmp_path / "run.mf4"], mapping).manoeuvres
    np.testing.assert_allclose(m.t, np.arange(200) * 0.02, atol=1e-12)
    np.testing.assert_allclose(m.vx, (72 + m.t) / 3.6, rtol=1e-12)


def test_split_rules_without_a_test_manoeuvre_warn(tmp_path):
    src, _ = _drive_csv(tmp_path, "drive4.csv", n=1000)
    with pytest.warns(DataWarning, match=r"'split\.test_fraction'.*none of the 1 manoeuvre test"):
        import_recordings([src], _mapping(channels=TIMED, split={"test_fraction": 0.3}))
    with pytest.warns(DataWarning) as record:
        ds = import_recordings([src], _mapping(channels=TIMED, split={"test": ["drive9*"]}))
    texts = [str(w.message) for w in record]
    assert any(
        "pattern 'drive9*' matches none of the recordings ['drive4.csv']" in x for x in texts
    )
    assert any(x.endswith("for a test split, name a recording in split.test") for x in texts)
    assert not ds.test
    # the advice fits the rule: segments do not help train_every = 1, nor a test pattern
    with pytest.warns(DataWarning, match=r"for a test split, use train_every = 2 or more$"):
        import_recordings(
            [src], _mapping(channels=TIMED, split={"train_every": 1}, segment_length=2.5)
        )
    with pytest.warns(DataWarning, match=r"raise test_fraction or cut .* shorter segment_length$"):
        import_recordings(
            [src], _mapping(channels=TIMED, split={"test_fraction": 0.05}, segment_length=2.5)
        )
    # cut into segments, the same rule gives a test split, without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        ds = import_recordings(
            [src], _mapping(channels=TIMED, split={"test_fraction": 0.3}, segment_length=2.5)
        )
    assert [m.split for m in ds.manoeuvres] == ["train", "train", "train", "test"]


def test_segments_too_short_name_the_key(tmp_path):
    src, _ = _drive_csv(tmp_path, n=1000)
    with pytest.raises(DataError, match=r"key 'segment_length': .*into 10 segments of 100 samp"):
        import_recordings([src], _mapping(channels=TIMED, segment_length=1.0))


def test_a_typo_under_source_is_named():
    with pytest.raises(DataError, match=r"key 'source\.delimeter': unknown; expected .*delimiter"):
        read_mapping({"channels": {"t": "time"}, "source": {"delimeter": ","}})


def test_min_speed_is_echoed_in_the_unit_it_was_given_in(tmp_path):
    user = _user_units(_recording())
    user["Speed"][:] = 2.0  # km/h: below min_speed everywhere
    src = _write_csv(tmp_path / "parked.csv", user, sep=",")
    with pytest.raises(DataError, match=r"min_speed = 3 km/h \(0\.8333 m/s\).*top speed 2 km/h"):
        import_recordings([src], _mapping(channels=TIMED, min_speed="3 km/h"))
    user["Speed"][:] = _user_units(_recording())["Speed"]
    _write_csv(src, user, sep=",")
    ds = import_recordings([src], _mapping(channels=TIMED, min_speed="3 km/h"), tmp_path / "ds")
    assert ds.meta["min_speed"] == pytest.approx(3 / 3.6)  # SI, whatever unit was written
