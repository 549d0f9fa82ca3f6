"""The real recording (revs-250lm), a folder of one file per signal, imported by its
built-in mapping; skipped when ``../shared/data`` is absent."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from kftune.data import import_recordings, load_revs, open_dataset
from kftune.data.importer import builtin_mapping
from kftune.data.jsonfile import read_toml
from kftune.errors import DataError, DataWarning
from kftune.vehicle import preset


@functools.lru_cache(maxsize=1)
def _load(path: str):
    return load_revs(path)


@pytest.fixture
def revs(revs_dir):
    return revs_dir, _load(str(revs_dir))


def test_loads_with_its_vehicle_and_segments(revs):
    _, ds = revs
    assert ds.vehicle == preset("revs-250lm")
    assert ds.dt == pytest.approx(0.01)
    assert len(ds) == 18
    assert ds.names[0] == "revs-250lm-s01" and ds.names[-1] == "revs-250lm-s18"
    assert [m.name for m in ds.train] == [f"revs-250lm-s{i:02d}" for i in (1, 4, 7, 10, 13, 16)]
    assert len(ds.test) == 12
    assert sum(m.n for m in ds.manoeuvres) == 55_001
    assert ds.manoeuvres[0].t[0] == pytest.approx(149.99)
    assert all(m.kind == "segment" for m in ds.manoeuvres)


def test_reference_and_measurements(revs):
    _, ds = revs
    for m in ds.manoeuvres:
        # the reference is the INS sideslip = atan2(vy, vx) (README: to 5e-9)
        np.testing.assert_allclose(
            m.beta_ref, np.arctan2(m.extra["vy_ins"], m.extra["vx_ins"]), atol=1e-8
        )
    vx_err = np.concatenate([m.vx - m.extra["vx_ins"] for m in ds.manoeuvres])
    assert np.std(vx_err) == pytest.approx(0.05, rel=0.05)  # documented Vx measurement noise
    ay = np.concatenate([m.ay for m in ds.manoeuvres])
    assert np.mean(np.abs(ay) >= 4.0) == pytest.approx(0.56, abs=0.02)  # README: 56 %
    assert np.all(np.isfinite(ds.r_default)) and np.all(ds.r_default > 0)
    assert np.sqrt(ds.r_default[0]) == pytest.approx(0.05, rel=0.1)


def _revs_mapping(**channels: dict) -> dict:
    """The built-in revs-250lm mapping as a dict, with ``channels`` replaced, uncut."""
    data = read_toml(builtin_mapping("revs-250lm"))
    data.pop("segment_length")
    return data | {"channels": data["channels"] | channels}


def test_filtered_yaw_rate_trap_is_caught(revs_dir):
    """yawRateFilt.txt is in deg/s; declared as rad/s it is refused, naming the file."""
    bad = _revs_mapping(r={"column": "yawRateFilt", "unit": "rad/s"})
    with pytest.raises(DataError) as info:
        import_recordings([revs_dir], bad)
    assert info.value.file.endswith("yawRateFilt.txt") and info.value.column == "r"
    assert "deg/s" in str(info.value)
    with pytest.warns(DataWarning, match="none of the 1 manoeuvre test"):  # uncut
        good = import_recordings(
            [revs_dir], _revs_mapping(r={"column": "yawRateFilt", "unit": "deg/s"})
        )
    raw = _load(str(revs_dir))
    # filtered and raw yaw rate agree once the unit is right
    r_raw = np.concatenate([m.r for m in raw.manoeuvres])
    assert np.corrcoef(good.manoeuvres[0].r, r_raw)[0, 1] > 0.99


def test_open_dataset_detects_the_layout(revs):
    revs_dir, ds = revs
    assert open_dataset(revs_dir).names == ds.names
    assert load_revs(revs_dir, vx_noise=0.0).manoeuvres[0].vx.tolist() == (
        ds.manoeuvres[0].extra["vx_ins"].tolist()
    )
