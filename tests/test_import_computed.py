"""A recording as a logger writes it, imported without a script: computed channels
(:mod:`kftune.data.expr`) checked against NumPy and SciPy computed here, hostile
expressions refused, logger headers (``# time(s)``, ``name(unit)``, ``kmph``), an offset on
an atan2 channel, missing vehicle keys, the split per file and by segment name, a raster
per recording, and a logger's drive (wheel speeds in km/h, no lateral acceleration)
imported and tuned from the command line."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from conftest import run_cli
from kftune.cli import EXIT_BAD_INPUT
from kftune.data import load_dataset
from kftune.data.expr import LOWPASS_ORDER, MAX_CHARS, ExprError, parse
from kftune.data.importer import import_recordings, read_mapping
from kftune.data.validate import plausibility_findings
from kftune.errors import DataError, DataWarning
from test_data_helpers import synthetic_channels

# most imports here are of one uncut recording, which the default rule cannot split
pytestmark = pytest.mark.filterwarnings("ignore:.*makes none of the:kftune.errors.DataWarning")

DT = 0.01
#: The four wheels' speeds as fractions of the vehicle's: their mean is exactly 1.
WHEELS = {"wheel_fl": 1.012, "wheel_fr": 0.991, "wheel_rl": 1.004, "wheel_rr": 0.993}


def _logger_columns(n: int = 600, seed: int = 0) -> tuple[dict, dict]:
    """(SI channels, the columns as a logger without an ay sensor writes them: time in s, four wheel
    speeds in km/h, ax in m/s², the yaw rate ``omega`` in rad/s, the steering angle in deg;
    no lateral acceleration)."""
    c = synthetic_channels(n=n, dt=DT, seed=seed)
    cols = {"time": c["t"]}
    cols |= {w: c["vx"] * 3.6 * f for w, f in WHEELS.items()}
    cols |= {"ax": c["ax"], "omega": c["r"], "steer": np.degrees(c["delta"])}
    return c, cols


def _savetxt(path: Path, cols: dict, units: dict) -> Path:
    """A CSV as ``numpy.savetxt`` writes it: header ``# time(s),wheel_fl(kmph),…``."""
    header = ",".join(f"{k}({units[k]})" if k in units else k for k in cols)
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=header)
    return path


UNITS = {"time": "s", **dict.fromkeys(WHEELS, "kmph"), "ax": "m/s^2", "omega": "rad/s",
         "steer": "deg"}  # fmt: skip

LOGGER_MAPPING = """
name = "logger-car"
vehicle = "bmw-320i"
model = "single-track"
min_speed = "3 km/h"
segment_length = 2.0

[split]
train_every = 2

[channels]
t = "time"
vx = { expr = "(wheel_fl + wheel_fr + wheel_rl + wheel_rr) / 4", unit = "km/h" }
ay = { expr = "vx * omega", unit = "m/s^2" }
ax = "ax"
r = "omega"
delta = "steer"
"""


def _mapping(**channels: object) -> dict:
    return {"channels": {"t": "time", **channels}}


# ------------------------------------------------------------------------ a logger's drive
def test_a_logger_drive_imports_with_computed_vx_and_ay(tmp_path):
    c, cols = _logger_columns()
    src = _savetxt(tmp_path / "drive.csv", cols, UNITS)
    assert src.read_text().startswith("# time(s),wheel_fl(kmph),")
    (tmp_path / "map.toml").write_text(LOGGER_MAPPING)
    ds = import_recordings([src], tmp_path / "map.toml")
    vx = np.concatenate([m.vx for m in ds.manoeuvres])
    ay = np.concatenate([m.ay for m in ds.manoeuvres])
    r = np.concatenate([m.r for m in ds.manoeuvres])
    kept = slice(0, vx.size)  # min_speed keeps every sample of a drive at 20 m/s
    wheels = sum(cols[w] for w in WHEELS) / 4
    np.testing.assert_allclose(vx, wheels[kept] / 3.6, rtol=1e-12)
    np.testing.assert_allclose(vx, c["vx"][kept], rtol=1e-12)  # the fractions' mean is 1
    np.testing.assert_allclose(ay, c["vx"][kept] * c["r"][kept], rtol=1e-12)
    np.testing.assert_allclose(r, c["r"][kept], rtol=1e-12)
    np.testing.assert_allclose(ds.manoeuvres[0].delta, c["delta"][: ds.manoeuvres[0].n])
    assert [m.split for m in ds.manoeuvres][:3] == ["train", "test", "train"]


def test_a_logger_drive_imports_and_tunes_from_the_command_line(tmp_path):
    _, cols = _logger_columns(n=1200)
    src = _savetxt(tmp_path / "drive.csv", cols, UNITS)
    (tmp_path / "map.toml").write_text(LOGGER_MAPPING.replace("2.0", "4.0"))
    out = tmp_path / "ds"
    imp = run_cli("dataset", "import", src, "--mapping", tmp_path / "map.toml", "-o", out)
    assert imp.returncode == 0, imp.stderr
    ds = load_dataset(out)
    assert {"vx", "ay", "r", "ax", "delta"} <= set(ds.manoeuvres[0].channel_names)
    # no sideslip reference: the NIS cost needs none
    tune = run_cli(
        "tune", out, "-m", "random", "-n", "5", "--cost", "nis", "-o", tmp_path / "t.json"
    )
    assert tune.returncode == 0, tune.stderr
    assert (tmp_path / "t.json").is_file()


# ----------------------------------------------------------------- expressions vs NumPy
T = np.arange(500) * DT
A = np.sin(2 * np.pi * 0.7 * T) + 2.0
B = np.cos(2 * np.pi * 1.3 * T) - 0.2


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("(a + b) / 4 - 2 * a ** 2", (A + B) / 4 - 2 * A**2),
        ("-a + +b", -A + B),
        ("abs(b)", np.abs(B)),
        ("sqrt(a)", np.sqrt(A)),
        ("sin(a) + cos(b) - tan(b)", np.sin(A) + np.cos(B) - np.tan(B)),
        ("atan2(b, a)", np.arctan2(B, A)),
        ("mean(a, b, 3)", (A + B + 3) / 3),
        ("clip(b, -0.5, 0.25)", np.minimum(np.maximum(B, -0.5), 0.25)),
        ("a ** -1 * pi", np.pi / A),
        ("t * 2", 2 * T),
        ("7", np.full(T.size, 7.0)),
    ],
)
def test_expressions_against_numpy(text, expected):
    np.testing.assert_allclose(parse(text).evaluate({"a": A, "b": B}, T), expected, rtol=1e-13)


def test_gradient_is_the_time_derivative():
    """d/dt sin(ωt) = ω cos(ωt): central differences are O(dt²) inside (one-sided at the
    ends), so the error is below ω³dt²/6 ≈ 3e-4 inside."""
    w = 2 * np.pi * 0.7
    t = np.arange(500) * DT
    for name in ("gradient", "diff"):
        got = parse(f"{name}(x)").evaluate({"x": np.sin(w * t)}, t)
        np.testing.assert_allclose(got[1:-1], w * np.cos(w * t[1:-1]), atol=w**3 * DT**2 / 6)


def test_lowpass_is_scipys_butterworth_run_forward_and_backward():
    rng = np.random.default_rng(1)
    x = np.sin(2 * np.pi * 0.5 * T) + 0.3 * rng.standard_normal(T.size)
    b, a = signal.butter(LOWPASS_ORDER, 5.0, fs=1 / DT)
    np.testing.assert_allclose(
        parse("lowpass(x, 5)").evaluate({"x": x}, T), signal.filtfilt(b, a, x), rtol=1e-12
    )
    # and the closed form: a sine far from the ends keeps |H(f)|² = 1 / (1 + (Ω/Ωc)^2N),
    # Ω = tan(π f / fs) (the bilinear transform's warped frequency)
    t = np.arange(4000) * DT
    f, fc = 8.0, 4.0
    y = parse(f"lowpass(x, {fc})").evaluate({"x": np.sin(2 * np.pi * f * t)}, t)
    gain = np.max(np.abs(y[1000:-1000]))
    ratio = math.tan(math.pi * f * DT) / math.tan(math.pi * fc * DT)
    assert gain == pytest.approx(1 / (1 + ratio ** (2 * LOWPASS_ORDER)), rel=0.01)


def test_a_cutoff_at_nyquist_is_refused_naming_the_channel_and_frequency(tmp_path):
    _, cols = _logger_columns()
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    # in its own expression, a channel's name is the file's column of that name
    mapping = _mapping(ax={"expr": "lowpass(ax, 50)", "unit": "m/s^2"})
    with pytest.raises(DataError, match=r"ax \(expression 'lowpass.*50 Hz.*Nyquist.*50 Hz"):
        import_recordings([src], mapping)
    mapping = _mapping(ax={"expr": "lowpass(ax, 10)", "unit": "m/s^2"})
    (m,) = import_recordings([src], mapping).manoeuvres
    b, a = signal.butter(LOWPASS_ORDER, 10.0, fs=1 / DT)
    np.testing.assert_allclose(m.ax, signal.filtfilt(b, a, cols["ax"]), rtol=1e-12)


def test_a_division_by_zero_is_a_bad_sample_named_by_row(tmp_path):
    _, cols = _logger_columns()
    cols["count"] = np.ones(cols["time"].size)
    cols["count"][37] = 0.0
    src = _savetxt(tmp_path / "run.csv", cols, {})
    mapping = _mapping(ratio={"expr": "1 / count", "unit": "1"})
    # the header is row 1: sample 37 is row 39
    with pytest.raises(DataError, match=r"ratio \(expression '1 / count'\): 1 value.*row\(s\) 39"):
        import_recordings([src], mapping)


def test_computed_channels_are_computed_in_dependency_order(tmp_path):
    _, cols = _logger_columns()
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    # ay names vx before vx is defined; vx's expression names a column
    mapping = _mapping(
        ay={"expr": "vx * r", "unit": "m/s^2"},
        vx={"expr": "mean(wheel_fl, wheel_fr, wheel_rl, wheel_rr)", "unit": "km/h"},
        r="omega",
    )
    (m,) = import_recordings([src], mapping).manoeuvres
    np.testing.assert_allclose(m.ay, m.vx * m.r, rtol=1e-12)


def test_a_cycle_is_refused_naming_it():
    mapping = _mapping(
        ay={"expr": "vx * omega", "unit": "m/s^2"},
        vx={"expr": "ay / omega", "unit": "m/s"},
    )
    with pytest.raises(DataError, match=r"cycle: (ay -> vx -> ay|vx -> ay -> vx)"):
        read_mapping(mapping)


def test_a_typo_names_the_column_and_lists_the_files_columns_in_file_order(tmp_path):
    _, cols = _logger_columns()
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    mapping = _mapping(ay={"expr": "vx * omgea", "unit": "m/s^2"}, vx="wheel_fl")
    with pytest.raises(DataError) as info:
        import_recordings([src], mapping)
    text = str(info.value)
    assert "ay (expression 'vx * omgea') names 'omgea'" in text
    listed = "['time', 'wheel_fl', 'wheel_fr', 'wheel_rl', 'wheel_rr', 'ax', 'omega', 'steer']"
    assert listed in text and "file order" in text


def test_a_missing_column_lists_the_columns_in_file_order(tmp_path):
    _, cols = _logger_columns()
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    with pytest.raises(DataError, match=r"'Speed' not found; the file has \['time', 'wheel_fl'"):
        import_recordings([src], _mapping(vx="Speed"))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("__import__('os')", "unknown function '__import__'"),
        ("omega.real", r"attribute access"),
        ("(lambda: 1)()", "unknown function"),
        ("lambda: 1", "a lambda"),
        ("[w for w in omega]", "a comprehension"),
        ("10**10**10", r"exponent of \*\* .*must be a number between -64 and 64"),
        ("omega ** 1000", r"exponent of \*\*"),
        ("x" * (MAX_CHARS + 1), f"at most {MAX_CHARS:,}"),
        ("(" * 300 + "omega" + ")" * 300, "too many nested parentheses"),
        ("abs(" * 60 + "omega" + ")" * 60, "nested more than 40 deep"),
        ("-" * 900 + "omega", "nested more than"),
        ("omega[0]", r"indexing"),
        ("'omega'", "is not a number"),
        ("omega if omega else 1", "if/else"),
        ("abs(x=omega)", "positional arguments only"),
        ("vx * * omega", r"syntax error at character 6"),
        ("1e999", "too large"),
        ("atan2(omega)", r"takes 2 argument"),
    ],
)
def test_hostile_or_wrong_expressions_are_refused_naming_the_channel(tmp_path, text, message):
    _, cols = _logger_columns(n=300)
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    (tmp_path / "map.toml").write_text(
        f'[channels]\nt = "time"\nay = {{ expr = {_toml_string(text)}, unit = "m/s^2" }}\n'
    )
    out = tmp_path / "ds"
    res = run_cli("dataset", "import", src, "--mapping", tmp_path / "map.toml", "-o", out)
    assert res.returncode == EXIT_BAD_INPUT
    assert "key 'channels.ay.expr'" in res.stderr
    assert len(re.findall(message, res.stderr)) == 1, res.stderr
    assert "Traceback" not in res.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.toml", "run.csv"]


def _toml_string(text: str) -> str:
    """A TOML basic string holding ``text`` (which has no backslash or control character)."""
    return '"' + text.replace('"', '\\"') + '"'


def test_parse_refuses_what_is_not_a_string():
    with pytest.raises(ExprError, match="expected the expression as a string"):
        parse(3.0)  # type: ignore[arg-type]


# ------------------------------------------------------------------------- logger headers
def test_logger_headers_give_names_and_units(tmp_path):
    """``# `` before the first name is dropped, ``name(unit)`` declares the unit (kmph and
    kph are km/h), and a parenthesis that holds no unit stays part of the name."""
    n = 300
    v = np.linspace(10.0, 20.0, n)
    cols = {"time(s)": np.arange(n) * DT, "speed(kph)": v * 3.6, "p(front)": v}
    path = tmp_path / "run.csv"
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols))
    mapping = {"channels": {"t": "time", "vx": "speed", "p": {"column": "p(front)", "unit": "1"}}}
    (m,) = import_recordings([path], mapping).manoeuvres
    np.testing.assert_allclose(m.vx, v, rtol=1e-12)
    np.testing.assert_allclose(m.channel("p"), v, rtol=1e-12)


# --------------------------------------------------------------------------- atan2 offset
def test_an_offset_on_an_atan2_channel_is_refused_with_the_expression_that_does_it():
    mapping = _mapping(beta_ref={"atan2": ["Vy", "Vx"], "unit": "km/h", "offset": 0.01})
    with pytest.raises(DataError, match=r"channels.beta_ref.offset.*expr = \"atan2\(Vy, Vx\)"):
        read_mapping(mapping)


def test_an_angle_offset_by_expression_shifts_the_angle(tmp_path):
    c, cols = _logger_columns()
    cols |= {"Vx": c["vx"] * 3.6, "Vy": c["vx"] * np.tan(c["beta_ref"]) * 3.6}
    src = _savetxt(tmp_path / "run.csv", cols, {})
    mapping = _mapping(beta_ref={"expr": "atan2(Vy, Vx) + 0.5 * pi / 180", "unit": "rad"})
    (m,) = import_recordings([src], mapping).manoeuvres
    np.testing.assert_allclose(m.beta_ref, c["beta_ref"] + math.radians(0.5), atol=1e-12)


# ------------------------------------------------------------------------ missing vehicle
def test_missing_vehicle_keys_are_named_with_what_they_do():
    vehicle = {"m": 1500.0, "Iz": 2500.0, "a": 1.2, "b": 1.5, "C_af": 9e4}
    mapping = {"vehicle": vehicle, "model": "single-track", **_mapping(vx="Speed")}
    with pytest.raises(DataError) as info:
        read_mapping(mapping)
    text = str(info.value)
    assert "key 'vehicle': the [vehicle] table lacks h, C_ar" in text
    assert "model 'single-track' uses every one of them" in text
    assert "h = CG height [m]: only the longitudinal load transfer from ax" in text
    assert "C_ar = rear cornering stiffness" in text and "always" in text
    assert "__init__" not in text and "positional argument" not in text


# ----------------------------------------------------------------------------- the split
def _two_files(tmp_path: Path) -> list[Path]:
    """Two recordings of 4 segments of 2 s each and one of 2 segments."""
    files = []
    for name, n in (("a", 800), ("b", 800), ("c", 400)):
        _, cols = _logger_columns(n=n, seed=len(files))
        files.append(_savetxt(tmp_path / f"{name}.csv", cols, UNITS))
    return files


SPLIT_CHANNELS = {"vx": {"expr": "mean(wheel_fl, wheel_fr, wheel_rl, wheel_rr)", "unit": "km/h"}}


def test_train_every_counts_within_each_file_with_per_file(tmp_path):
    files = _two_files(tmp_path)
    common = {"segment_length": 2.0, **_mapping(**SPLIT_CHANNELS)}
    across = import_recordings(files, {**common, "split": {"train_every": 3}})
    per = import_recordings(files, {**common, "split": {"train_every": 3, "per": "file"}})
    names = [m.name for m in per.manoeuvres]
    assert names == [f"{f}-s{i:02d}" for f, k in (("a", 4), ("b", 4), ("c", 2))
                     for i in range(1, k + 1)]  # fmt: skip
    # i % 3 == 0 is train: i over all 10 segments, or within each file
    train_across = [i % 3 == 0 for i in range(10)]
    train_per = [k % 3 == 0 for n in (4, 4, 2) for k in range(n)]
    assert [m.split == "train" for m in across.manoeuvres] == train_across
    assert [m.split == "train" for m in per.manoeuvres] == train_per
    assert per.meta["split"] == "train_every = 3, per = 'file'"


def test_test_fraction_per_file_takes_the_end_of_each_file(tmp_path):
    files = _two_files(tmp_path)
    ds = import_recordings(
        files,
        {"segment_length": 2.0, "split": {"test_fraction": 0.55, "per": "file"},
         **_mapping(**SPLIT_CHANNELS)},
    )  # fmt: skip
    # test: the segments that start after the first 45 % of their file's time
    tests = [m.name for m in ds.manoeuvres if m.split == "test"]
    assert tests == ["a-s03", "a-s04", "b-s03", "b-s04", "c-s02"]


def test_split_test_names_segments(tmp_path):
    files = _two_files(tmp_path)
    ds = import_recordings(
        files,
        {"segment_length": 2.0, "split": {"test": ["a-s02", "b-s0[34]"]},
         **_mapping(**SPLIT_CHANNELS)},
    )  # fmt: skip
    assert [m.name for m in ds.manoeuvres if m.split == "test"] == ["a-s02", "b-s03", "b-s04"]


def test_per_file_is_refused_with_test_globs():
    with pytest.raises(DataError, match=r"split.per.*train_every and test_fraction"):
        read_mapping({"split": {"test": ["a*"], "per": "file"}, **_mapping(vx="v")})
    with pytest.raises(DataError, match=r"split.per.*expected one of \['all', 'file'\]"):
        read_mapping({"split": {"train_every": 2, "per": "files"}, **_mapping(vx="v")})


# --------------------------------------------------------------------- raster per source
def test_a_raster_per_recording_resamples_only_the_ones_it_names(tmp_path):
    _, cols = _logger_columns(n=600)
    a = _savetxt(tmp_path / "steady.csv", cols, UNITS)
    jittered = dict(cols)
    rng = np.random.default_rng(3)
    jittered["time"] = cols["time"] + rng.uniform(-0.002, 0.002, cols["time"].size)
    b = _savetxt(tmp_path / "jitter.csv", jittered, UNITS)
    mapping = {"source": {"raster": {"jitter*": 0.01}}, **_mapping(**SPLIT_CHANNELS)}
    ds = import_recordings([a, b], mapping)
    steady, resampled = ds.manoeuvres
    np.testing.assert_array_equal(steady.t, cols["time"])  # not resampled
    grid = jittered["time"][0] + np.arange(resampled.n) * 0.01
    np.testing.assert_allclose(resampled.t, grid, rtol=0, atol=1e-9)
    wheels = sum(jittered[w] for w in WHEELS) / 4 / 3.6
    np.testing.assert_allclose(resampled.vx, np.interp(grid, jittered["time"], wheels))


def test_a_raster_glob_that_matches_no_recording_warns(tmp_path):
    _, cols = _logger_columns(n=300)
    a = _savetxt(tmp_path / "run.csv", cols, UNITS)
    mapping = {"source": {"raster": {"other*": 0.01}}, **_mapping(**SPLIT_CHANNELS)}
    with pytest.warns(DataWarning, match=r"source.raster.*'other\*' matches none"):
        import_recordings([a], mapping)


def test_the_held_samples_warning_names_the_raster_option():
    c = synthetic_channels(n=400)
    for k in ("ax", "ay", "r"):
        c[k] = np.repeat(c[k][::4], 4)  # recorded at 25 Hz, held up to 100 Hz
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = plausibility_findings(c, None)["held"]
    assert "[source] raster = <step>" in found and '{ "<file glob>" = <step> }' in found


def test_the_readme_computed_channels_example_imports_a_logger_drive(tmp_path):
    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    section = readme.split("**Computed channels**", 1)[1]
    block = section.split("```toml\n", 1)[1].split("```", 1)[0]
    c, cols = _logger_columns()
    src = _savetxt(tmp_path / "drive.csv", cols, UNITS)
    (tmp_path / "map.toml").write_text(block)
    (m,) = import_recordings([src], tmp_path / "map.toml").manoeuvres
    np.testing.assert_allclose(m.ay, c["vx"] * c["r"], rtol=1e-12)


def test_a_channel_named_in_an_expression_is_in_si_units_a_column_raw(tmp_path):
    """A column whose name is no identifier is mapped to a channel and named by it: then
    it is that channel's SI value (m/s), where a column is the file's raw km/h."""
    _, cols = _logger_columns()
    cols["wheel fl"] = cols.pop("wheel_fl")
    src = _savetxt(tmp_path / "run.csv", cols, {})
    mapping = _mapping(
        wfl={"column": "wheel fl", "unit": "km/h"},
        vx={"expr": "wfl", "unit": "m/s"},
        v_fr={"expr": "wheel_fr", "unit": "km/h"},
    )
    (m,) = import_recordings([src], mapping).manoeuvres
    np.testing.assert_allclose(m.vx, cols["wheel fl"] / 3.6, rtol=1e-12)
    np.testing.assert_allclose(m.channel("v_fr"), cols["wheel_fr"] / 3.6, rtol=1e-12)


def test_a_lowpass_of_a_signal_with_a_bad_sample_names_its_row(tmp_path):
    """A filter would spread one NaN over the whole recording: refused at its row."""
    _, cols = _logger_columns()
    cols["ax"][120] = np.nan
    src = _savetxt(tmp_path / "run.csv", cols, UNITS)
    mapping = _mapping(ax={"expr": "lowpass(ax, 10)", "unit": "m/s^2"})
    with pytest.raises(DataError, match=r"row 122: ax \(expression .*1 sample\(s\) that are not"):
        import_recordings([src], mapping)


def test_mean_takes_at_most_sixteen_arguments_and_never_stacks_them():
    """mean(…) of 16 channels is their mean (numpy's); of 17 it is refused with the limit;
    its memory is a running sum: the peak (tracemalloc, which numpy reports to) stays a
    few arrays for 16 arguments of 10^6 samples, where stacking them took 16."""
    import tracemalloc

    from kftune.data.expr import MAX_MEAN_ARGS

    sixteen = ", ".join(["a", "b"] * (MAX_MEAN_ARGS // 2))
    np.testing.assert_allclose(
        parse(f"mean({sixteen})").evaluate({"a": A, "b": B}, T), (A + B) / 2, rtol=1e-13
    )
    with pytest.raises(
        ExprError, match=r"mean\(\) at character 1 takes 1 to 16 argument\(s\).*got 17"
    ):
        parse(f"mean({sixteen}, a)")
    n = 10**6
    big, t = np.linspace(0.0, 1.0, n), np.arange(n) * 0.01
    expression = parse(f"mean({', '.join(['a'] * MAX_MEAN_ARGS)})")
    tracemalloc.start()
    try:
        expression.evaluate({"a": big}, t)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5 * big.nbytes, peak / big.nbytes
