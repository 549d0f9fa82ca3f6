"""Validation: every check fails with a DataError naming file, column and row; fuzzed
loaders either load or raise DataError (never another exception, never silent NaN)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kftune.data import (
    Manoeuvre,
    import_recordings,
    load_dataset,
    save_dataset,
    validate_channels,
)
from kftune.data.validate import _LIMITS, SIDESLIP_CHANNELS, sample_time
from kftune.errors import DataError
from test_data_helpers import synthetic_channels, synthetic_dataset


def _fails(channels, **kw) -> DataError:
    with pytest.raises(DataError) as info:
        validate_channels(channels, file="rec.csv", **kw)
    return info.value


def test_valid_channels_pass_and_return_dt():
    assert validate_channels(synthetic_channels(), file="rec.csv") == pytest.approx(0.01)


def test_missing_time_channel():
    c = synthetic_channels()
    del c["t"]
    e = _fails(c)
    assert e.column == "t" and e.file == "rec.csv"
    assert "missing the time channel" in str(e)


@pytest.mark.parametrize("missing", SIDESLIP_CHANNELS[1:])
def test_sideslip_channels_are_optional(missing):
    """Only t is required: which channels a manoeuvre needs is the model's business."""
    c = synthetic_channels()
    del c[missing]
    assert validate_channels(c, file="rec.csv") == pytest.approx(0.01)
    m = Manoeuvre("x", "slalom", "train", **c)
    assert not m.has(missing) and missing not in m.channel_names
    with pytest.raises(DataError, match=f"manoeuvre 'x' has no channel '{missing}'"):
        getattr(m, missing)


def test_a_manoeuvre_of_any_channels():
    t = np.arange(300) * 0.1
    m = Manoeuvre("track", "segment", "test", t, px=np.cos(t), py=np.sin(t))
    assert m.channel_names == ("t", "px", "py") and m.extra.keys() == {"px", "py"}
    with pytest.raises(DataError, match="needs a reference channel v_ref, which manoeuvre"):
        m.require(["px", "v_ref"], "the cost", "a reference channel")
    with pytest.raises(DataError, match="given twice"):
        Manoeuvre("x", "segment", "test", t, px=t, channels={"px": t})


def test_unequal_lengths_name_column_and_row():
    c = synthetic_channels(n=300)
    c["ay"] = c["ay"][:250]
    e = _fails(c, row_offset=2)
    assert e.column == "ay" and e.row == 252
    assert "equal lengths" in str(e)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("column", ["t", "r", "beta_ref", "vx"])
def test_non_finite_values(bad, column):
    c = synthetic_channels()
    c[column] = c[column].copy()
    c[column][123] = bad
    e = _fails(c, row_offset=2)
    assert (e.column, e.row) == (column, 125)
    assert "not a finite number" in str(e)


def test_duplicated_and_decreasing_time():
    c = synthetic_channels()
    c["t"][57] = c["t"][56]
    e = _fails(c)
    assert (e.column, e.row) == ("t", 57) and "duplicated" in str(e)
    c = synthetic_channels()
    c["t"][80] = c["t"][78]
    e = _fails(c, row_offset=1)
    assert (e.column, e.row) == ("t", 81) and "decreasing" in str(e)


def test_irregular_sample_time():
    c = synthetic_channels()
    c["t"][200:] += 0.005  # a half-sample gap
    e = _fails(c, row_offset=2)
    assert (e.column, e.row) == ("t", 202)
    assert "irregular sample time" in str(e)


def test_time_in_messages_has_four_significant_digits():
    c = synthetic_channels(n=400, t0=100.0)  # late timestamps: binary noise in every step
    c["t"][200:] += 0.5  # a gap of half a second
    e = _fails(c, row_offset=2)
    assert (e.column, e.row) == ("t", 202)
    assert "step 0.51 s from the previous row, the median step is 0.01 s" in str(e)
    assert "a gap in the recording: split it at the gap" in str(e)


def test_jittered_timestamps_are_told_how_to_resample():
    c = synthetic_channels(n=400)
    c["t"] = c["t"] + np.random.default_rng(3).uniform(-4e-4, 4e-4, 400)
    e = _fails(c, resample_option="[source] raster")
    assert "jittered timestamps" in str(e) and "(set [source] raster = 0.01, the mean step)" in str(
        e
    )


def test_sample_time_drops_the_binary_noise_of_late_timestamps():
    assert (100.0 + 0.01) - 100.0 != 0.01  # the noise
    assert sample_time(100.0 + np.arange(500) * 0.01) == 0.01
    assert sample_time(1e5 + np.arange(500) * 0.001) == 0.001  # 28 hours into a recording
    assert sample_time(np.arange(500) * 0.005) == 0.005
    assert sample_time(np.arange(500) / 3) == pytest.approx(1 / 3, rel=1e-12, abs=0)
    t = 100.0 + np.arange(300) * 0.01
    assert Manoeuvre("late", "segment", "train", t, vx=np.full(300, 10.0)).dt == 0.01


@pytest.mark.parametrize("t0", [0.0, 100.0, 1000.0])
@pytest.mark.parametrize("dt", [0.01, 0.0125, 0.002])
def test_sample_time_of_float32_timestamps(t0, dt):
    """Single-precision time (a MATLAB single, a Parquet float column) is 6e-5 s coarse at
    1000 s: its median step is rounded within that resolution, never beyond it."""
    t = (t0 + np.arange(2000) * dt).astype(np.float32)
    assert np.median(np.diff(t.astype(np.float64))) != dt or t0 == 0.0  # the noise
    assert sample_time(t) == dt


def test_sample_time_never_rounds_beyond_the_noise():
    """A step that is not a short decimal stays as measured (to 12 digits)."""
    assert sample_time(10.0 + np.arange(500) * 0.0123456789) == pytest.approx(0.0123456789, 1e-12)
    t = (1000.0 + np.arange(500) * 0.0123456789).astype(np.float32)  # 6e-5 s resolution
    assert abs(sample_time(t) - 0.0123456789) <= 2 * np.spacing(np.float32(1010.0))


def test_small_timing_jitter_is_accepted():
    c = synthetic_channels()
    c["t"] = np.round(c["t"] + 149.99, 5)  # a logger's printed time (revs-like)
    validate_channels(c)


@pytest.mark.parametrize(
    ("column", "scale", "hint"),
    [
        ("r", 180.0 / math.pi, "deg/s"),
        ("delta", 15.0 * 180.0 / math.pi, "degrees"),
        ("beta_ref", 180.0 / math.pi * 30.0, "degrees"),
        ("vx", 3.6 * 1.5, "km/h"),
        ("ay", 40.0, "wrong unit"),
    ],
)
def test_implausible_units(column, scale, hint):
    c = synthetic_channels()
    c[column] = c[column] * scale
    e = _fails(c, row_offset=2)
    lo, hi, _ = _LIMITS[column]
    first = int(np.flatnonzero((c[column] < lo) | (c[column] > hi))[0])
    assert (e.file, e.column, e.row) == ("rec.csv", column, first + 2)
    assert hint in str(e)


def test_ay_in_g_is_caught_by_kinematics():
    """Lateral acceleration in g stays within every magnitude limit; ay ≈ vx·r exposes it."""
    c = synthetic_channels()
    c["ay"] = c["ay"] / 9.81
    e = _fails(c, row_offset=2)
    peak = int(np.argmax(np.abs(c["vx"] * c["r"])))  # the row the message quotes
    assert (e.file, e.column, e.row) == ("rec.csv", "ay", peak + 2)
    assert "ay/(vx·r)" in str(e)


def test_opposite_sign_convention_is_caught():
    """SAE-signed ay (positive right) with an ISO yaw rate: the ratio is −1."""
    c = synthetic_channels()
    c["ay"] = -c["ay"]
    e = _fails(c)
    assert (e.file, e.column, e.row) == ("rec.csv", "ay", int(np.argmax(np.abs(c["vx"] * c["r"]))))
    assert "opposite sign conventions" in str(e) and "ay/(vx·r) = -1" in str(e)


def test_too_short():
    e = _fails(synthetic_channels(n=40))
    assert e.column == "t" and "too short" in str(e)
    validate_channels(synthetic_channels(n=40), min_samples=10)


@pytest.mark.parametrize("speed", [0.0, -1.0])
def test_standstill_or_reversing_loads(speed):
    """vx > 0 is the single-track model's assumption, not the data's: the data load, and the
    single-track filter refuses them (tests/test_tuning_problem.py)."""
    c = synthetic_channels()
    c["vx"] = c["vx"].copy()
    c["vx"][77] = speed
    assert validate_channels(c, file="rec.csv", row_offset=2) == pytest.approx(0.01)


def test_minimum_length_leaves_room_for_the_noise_estimate():
    """A manoeuvre just long enough to load is long enough for the R estimate."""
    from kftune.data import estimate_measurement_noise
    from kftune.data.validate import MIN_SAMPLES

    c = synthetic_channels(n=MIN_SAMPLES)
    m = Manoeuvre("short", "j-turn", "train", **c)
    assert np.all(estimate_measurement_noise([m]) > 0)
    with pytest.raises(DataError, match="too short"):
        validate_channels(synthetic_channels(n=MIN_SAMPLES - 1), file="rec.csv")


def test_bad_names_and_shapes():
    c = synthetic_channels()
    c["bad name"] = c["t"]
    assert "identifier" in str(_fails(c))
    c = synthetic_channels()
    c["r"] = np.column_stack([c["r"], c["r"]])
    e = _fails(c)
    assert e.column == "r" and "1-D" in str(e)


def test_manoeuvre_validates_on_construction():
    c = synthetic_channels()
    c["r"] = np.degrees(c["r"])
    with pytest.raises(DataError, match="deg/s"):
        Manoeuvre(name="x", kind="slalom", split="train", **c)
    with pytest.raises(DataError, match="split"):
        Manoeuvre(name="x", kind="slalom", split="validation", **synthetic_channels())
    m = Manoeuvre(name="x", kind="slalom", split="train", **synthetic_channels())
    with pytest.raises(ValueError):
        m.ay[0] = 1.0  # read-only arrays
    assert m.u.shape == (400, 2) and m.z.shape == (400, 3)
    np.testing.assert_array_equal(m.z[:, 0], m.vx)


# ----------------------------------------------------------------------------- fuzzing
@pytest.fixture(scope="module")
def csv_dataset(tmp_path_factory) -> Path:
    """A small valid dataset on disk (uncompressed CSV), to be corrupted by the fuzzers."""
    d = tmp_path_factory.mktemp("fuzz")
    save_dataset(synthetic_dataset(1, 1), d, compress=False)
    return d


CORRUPTIONS = ["nan", "inf", "abc", "", "1e999", "drop", "add"]


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    row=st.integers(min_value=2, max_value=401),
    col=st.integers(min_value=0, max_value=7),
    kind=st.sampled_from(CORRUPTIONS),
)
def test_fuzz_csv_corruption_is_reported_at_its_row(csv_dataset, tmp_path_factory, row, col, kind):
    """One corrupted field of a manoeuvre CSV: load_dataset raises a DataError naming that
    file and row (and the column, where the value is unreadable)."""
    work = tmp_path_factory.mktemp("case")
    for f in csv_dataset.iterdir():
        (work / f.name).write_bytes(f.read_bytes())
    target = work / "tr0.csv"
    lines = target.read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[row - 1].split(",")
    if kind == "drop":
        del fields[col]
    elif kind == "add":
        fields.insert(col, "0.5")
    else:
        fields[col] = kind
    lines[row - 1] = ",".join(fields)
    target.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as info:
        load_dataset(work)
    e = info.value
    assert e.file == str(target)
    assert e.row == row
    if kind in ("abc", ""):
        assert e.column == header[col]
    if kind in ("nan", "inf", "1e999"):
        assert e.column == header[col] and "finite" in str(e)


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(text=st.text(alphabet=st.sampled_from(list("0123456789.,-eE\nnaif t_x")), max_size=400))
def test_fuzz_csv_garbage_never_crashes(csv_dataset, tmp_path_factory, text):
    work = tmp_path_factory.mktemp("garbage")
    for f in csv_dataset.iterdir():
        (work / f.name).write_bytes(f.read_bytes())
    (work / "te0.csv").write_text(text)
    try:
        ds = load_dataset(work)
    except DataError as e:
        assert e.file is not None
    else:  # pragma: no cover - only if the text happens to be a valid manoeuvre
        assert all(np.all(np.isfinite(m.z)) for m in ds.manoeuvres)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    channel=st.sampled_from(list(SIDESLIP_CHANNELS)),
    line=st.integers(min_value=1, max_value=400),
    kind=st.sampled_from(["nan", "x1", "", "truncate"]),
)
def test_fuzz_column_files(tmp_path_factory, channel, line, kind):
    """Column-per-file: a bad value or a short file is reported in that file, at that line."""
    d = tmp_path_factory.mktemp("cols")
    c = synthetic_channels()
    for name, values in c.items():
        (d / f"{name}.txt").write_text("\n".join(repr(float(v)) for v in values) + "\n")
    path = d / f"{channel}.txt"
    lines = path.read_text().splitlines()
    if kind == "truncate":
        lines = lines[: line - 1] if line > 1 else lines[:-1]
    else:
        lines[line - 1] = kind
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as info:
        import_recordings([d], {"channels": {k: k for k in SIDESLIP_CHANNELS}})
    e = info.value
    if kind == "truncate":
        assert "samples" in str(e) or "too short" in str(e)
    else:
        assert e.file == str(path)
        assert e.row == line or f"at row(s) {line} " in str(e)  # NaN: with every bad channel
