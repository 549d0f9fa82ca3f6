"""The revs-250lm recording imported by its built-in mapping (the one import path) against
the loader it replaced, kept here as the reference: every manoeuvre, channel, the vehicle,
R and the fingerprints a study records must be what they were, so that studies on
revs-250lm still resume. Skipped when ``../shared/data`` is absent."""

from __future__ import annotations

import functools
import itertools
import math
import re
from pathlib import Path

import numpy as np
import pytest

from kftune.cli import main
from kftune.data import (
    Dataset,
    Manoeuvre,
    import_recordings,
    load_dataset,
    load_revs,
    open_dataset,
)
from kftune.data.importer import builtin_mapping, read_mapping
from kftune.data.validate import sample_time
from kftune.errors import DataError
from kftune.tuning.deploy import dataset_fingerprint
from kftune.tuning.problem import TuningProblem
from kftune.vehicle import preset
from test_data_helpers import synthetic_channels

#: The reference loader's column mapping: kftune channel → (file stem, SI unit), in the
#: order of the channels it gave (``vx_ins`` follows, a copy of vx before the noise).
REFERENCE_MAPPING = {
    "t": "t",
    "delta": "delta",
    "ax": "axCG",
    "ay": "ayCG",
    "r": "yawRate",
    "vx": "vx",
    "beta_ref": "beta_true",
    "vy_ins": "vy",
}


def reference_revs(
    directory: Path,
    *,
    segment_length: float = 30.0,
    train_every: int = 3,
    vx_noise: float = 0.05,
    seed: int = 0,
) -> Dataset:
    """revs-250lm as the former ``kftune.data.io.load_revs`` loaded it: each signal's file
    read with ``numpy.loadtxt`` (every unit is SI already), Vx = INS velocity + white noise
    of σ = ``vx_noise`` from ``default_rng(seed)`` over the whole recording (the INS value
    kept as ``vx_ins``), cut into ``k = round(duration / segment_length)`` segments of
    nearly equal sample counts, segment ``i`` training when ``i % train_every == 0``."""
    channels = {
        c: np.loadtxt(directory / f"{stem}.txt", dtype=np.float64)
        for c, stem in REFERENCE_MAPPING.items()
    }
    channels["vx_ins"] = channels["vx"]
    rng = np.random.default_rng(seed)
    channels["vx"] = channels["vx"] + rng.normal(0.0, vx_noise, channels["vx"].size)
    t = channels["t"]
    k = max(1, round(float(t[-1] - t[0]) / segment_length))
    bounds = np.linspace(0, t.size, k + 1).round().astype(int).tolist()
    manoeuvres = []
    for i, (a, b) in enumerate(itertools.pairwise(bounds)):
        manoeuvres.append(
            Manoeuvre(
                f"revs-250lm-s{i + 1:02d}",
                "segment",
                "train" if i % train_every == 0 else "test",
                t[a:b],
                channels={c: v[a:b] for c, v in channels.items() if c != "t"},
            )
        )
    return Dataset("revs-250lm", preset("revs-250lm"), sample_time(t), tuple(manoeuvres))


@functools.lru_cache(maxsize=1)
def _reference(path: str) -> Dataset:
    return reference_revs(Path(path))


@functools.lru_cache(maxsize=1)
def _loaded(path: str) -> Dataset:
    return load_revs(path)


def assert_same_data(ds: Dataset, ref: Dataset) -> None:
    """The same manoeuvres (names, kinds, splits, in order), channels (names in order,
    every value equal), sample time, vehicle and R."""
    assert ds.names == ref.names
    assert ds.dt == ref.dt
    assert ds.vehicle == ref.vehicle
    assert np.array_equal(ds.r_default, ref.r_default)
    for m, r in zip(ds.manoeuvres, ref.manoeuvres, strict=True):
        assert (m.name, m.kind, m.split) == (r.name, r.kind, r.split)
        assert m.channel_names == r.channel_names
        assert np.array_equal(m.t, r.t)
        for c in r.channel_names:
            assert np.array_equal(m.channel(c), r.channel(c)), (m.name, c)


def test_the_built_in_mapping_loads_what_the_former_loader_did(revs_dir):
    ds, ref = _loaded(str(revs_dir)), _reference(str(revs_dir))
    assert_same_data(ds, ref)
    assert len(ds) == 18 and len(ds.train) == 6
    assert ds.name == "revs-250lm"


def test_the_fingerprints_a_study_records_are_unchanged(revs_dir):
    """A study's objective fingerprint (manoeuvre data, vehicle, R) and a deployment's
    dataset fingerprint: equal, so that studies on revs-250lm resume."""
    ds, ref = _loaded(str(revs_dir)), _reference(str(revs_dir))
    assert dataset_fingerprint(ds) == dataset_fingerprint(ref)
    for split in ("train", "test"):
        ours = TuningProblem(getattr(ds, split), ds.vehicle, ds.r_default).fingerprint()
        theirs = TuningProblem(getattr(ref, split), ref.vehicle, ref.r_default).fingerprint()
        assert ours == theirs


def test_options_of_the_former_loader_still_apply(revs_dir):
    """Segment length, train_every, the noise and its seed, as the former loader took them."""
    options = {"segment_length": 60.0, "train_every": 2, "vx_noise": 0.1, "seed": 7}
    assert_same_data(load_revs(revs_dir, **options), reference_revs(revs_dir, **options))
    quiet = load_revs(revs_dir, vx_noise=0.0)
    assert all(np.array_equal(m.vx, m.channel("vx_ins")) for m in quiet.manoeuvres)


def test_open_dataset_of_the_folder_imports_it_by_the_mapping(revs_dir):
    assert_same_data(open_dataset(revs_dir), _reference(str(revs_dir)))


def test_dataset_import_with_the_built_in_mapping_writes_the_same_data(revs_dir, tmp_path):
    """``kftune dataset import DIR --mapping revs-250lm``: the dataset written reads back
    equal to the reference (the CSV keeps every double exactly)."""
    out = tmp_path / "revs"
    code = main(["dataset", "import", str(revs_dir), "--mapping", "revs-250lm", "-o", str(out)])
    assert code == 0
    assert_same_data(load_dataset(out), _reference(str(revs_dir)))


@pytest.mark.parametrize("bad", [{"segment_length": 0.0}, {"vx_noise": -1.0}])
def test_bad_options_are_refused(revs_dir, bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        load_revs(revs_dir, **bad)


# ------------------------------------------------------------- the mapping keys it uses
def _folder(tmp_path: Path, n: int = 600) -> tuple[Path, dict]:
    """A recording as a folder of one file per signal (SI units), and its channels."""
    c = synthetic_channels(n=n, seed=4)
    folder = tmp_path / "rec"
    folder.mkdir()
    for name, values in c.items():
        (folder / f"{name}.txt").write_text("\n".join(repr(float(v)) for v in values) + "\n")
    return folder, c


def test_noise_is_drawn_from_the_seeded_generator(tmp_path):
    """``noise = σ`` adds ``default_rng(seed).normal(0, σ, n)`` to the converted channel
    (here in m/s, so the values read are the file's), and the dataset records it."""
    folder, c = _folder(tmp_path)
    channels = {k: k for k in c} | {"vx": {"column": "vx", "noise": 0.1}, "vx_ins": {
        "column": "vx", "unit": "m/s"}}  # fmt: skip
    ds = import_recordings(
        [folder], {"vehicle": "bmw-320i", "seed": 5, "channels": channels, "segment_length": 3.0}
    )
    vx = np.concatenate([m.vx for m in ds.manoeuvres])
    expected = c["vx"] + np.random.default_rng(5).normal(0.0, 0.1, c["vx"].size)
    np.testing.assert_allclose(vx, expected, rtol=0, atol=1e-12)
    assert np.array_equal(np.concatenate([m.channel("vx_ins") for m in ds.manoeuvres]), c["vx"])
    assert (dict(ds.meta["noise"]), ds.meta["seed"]) == ({"vx": 0.1}, 5)


@pytest.mark.parametrize(
    ("entry", "top", "message"),
    [
        ({"vx": {"column": "vx", "noise": -0.1}}, {}, "key 'channels.vx.noise'"),
        ({"vx": {"column": "vx", "noise": "0.1"}}, {}, "key 'channels.vx.noise'"),
        ({"vx": {"column": "vx", "noise": math.inf}}, {}, "key 'channels.vx.noise'"),
        ({"t": {"column": "t", "noise": 0.01}}, {}, "none for the time t"),
        ({}, {"seed": -1}, "key 'seed': expected an integer >= 0"),
        ({}, {"seed": 1.5}, "key 'seed': expected an integer >= 0"),
    ],
)
def test_bad_noise_or_seed_is_refused_naming_the_key(tmp_path, entry, top, message):
    folder, c = _folder(tmp_path)
    mapping = {"channels": {k: k for k in c} | entry, **top}
    with pytest.raises(DataError, match=re.escape(message)):
        import_recordings([folder], mapping)


def test_built_in_mapping_by_name_and_a_file_of_that_name_first(tmp_path, monkeypatch):
    assert builtin_mapping("revs-250lm") is not None
    assert builtin_mapping("no-such-mapping") is None and builtin_mapping("../io") is None
    assert read_mapping("revs-250lm").vehicle == preset("revs-250lm")
    monkeypatch.chdir(tmp_path)
    Path("revs-250lm").write_text('vehicle = "bmw-320i"\n[channels]\nt = "t"\n')
    assert read_mapping("revs-250lm").vehicle == preset("bmw-320i")  # the user's file
    with pytest.raises(DataError, match=r"no mapping shipped with kftune .*\(revs-250lm"):
        read_mapping("no-such-mapping")
