"""Hostile recordings given to ``kftune dataset import``: MATLAB v7.3 (HDF5) files whose
variables lead out of the file (links, virtual datasets, external storage), timestamps that
run backwards in every format, decompression bombs and oversized MATLAB variables, sources
that are not regular files, and a disk that fills while the dataset is written. Each case
is run through the command: exit code, a message naming the file and the variable, column,
row or limit, no traceback, no foreign content quoted, nothing written."""

from __future__ import annotations

import errno
import gzip
import io
import os
import struct
import subprocess
import sys
import tempfile
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import DEV_ZERO, run_cli
from kftune.data import load_dataset, textfile
from kftune.data.readers import mat_variables
from kftune.data.textfile import ReadLimits
from kftune.errors import ConfigError, DataError
from test_data_helpers import synthetic_channels

SECRET = "SECRET-content-of-a-foreign-file"
#: A mapping of the channels of :func:`synthetic_channels`, named as they are, in SI.
CHANNELS = {c: c for c in ("t", "vx", "ax", "ay", "r", "delta", "beta_ref")}


def mapping_file(folder: Path, source: dict | None = None, **top: object) -> Path:
    """A mapping TOML of :data:`CHANNELS` (``source``: its ``[source]`` table)."""
    lines = ['vehicle = "bmw-320i"']
    lines += [f"{k} = {v!r}".replace("'", '"') for k, v in top.items()]
    if source:
        lines += ["[source]", *(f'{k} = "{v}"' for k, v in source.items())]
    lines += ["[channels]", *(f'{c} = "{s}"' for c, s in CHANNELS.items())]
    path = folder / "map.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def run_import(folder: Path, source: Path, mapping: Path | None = None) -> tuple:
    """``kftune dataset import SOURCE --mapping MAP -o folder/out``: (result, out)."""
    out = folder / "out"
    res = run_cli("dataset", "import", source, "--mapping", mapping or mapping_file(folder),
                  "-o", out)  # fmt: skip
    return res, out


def assert_refused(res, out: Path, *names: str, code: int = 3) -> None:
    """Exit ``code``, one short message naming each of ``names``, no traceback, no foreign
    content, and no output folder."""
    assert res.returncode == code, res.stderr
    assert "Traceback" not in res.stderr and SECRET not in res.stderr + res.stdout
    assert res.stderr.startswith("kftune: error: ") and len(res.stderr) < 1500, res.stderr
    for name in names:
        assert name in res.stderr, (name, res.stderr)
    assert not out.exists()


# =========================================================================== MATLAB v7.3
MAT73_HEADER = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5"


def savemat73(path: Path, variables: dict[str, np.ndarray], extra=None) -> Path:
    """A MATLAB v7.3 file (512-byte header, then HDF5): each variable a 1×n dataset tagged
    ``MATLAB_class``, in the struct ``rec``; ``extra(h5py, group)`` adds more to it."""
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w", userblock_size=512) as f:
        group = f.create_group("rec")
        group.attrs["MATLAB_class"] = np.bytes_("struct")
        for name, values in variables.items():
            ds = group.create_dataset(name, data=np.asarray(values, dtype=float)[None, :])
            ds.attrs["MATLAB_class"] = np.bytes_("double")
        if extra is not None:
            extra(h5py, group)
    with open(path, "r+b") as fh:
        fh.write(MAT73_HEADER.ljust(116) + b"\0" * 8 + b"\x00\x02IM")
    return path


@pytest.fixture
def foreign(tmp_path: Path) -> dict[str, Path]:
    """Files outside the recording that a link could reach: an HDF5 file and a text file,
    each holding the secret."""
    h5py = pytest.importorskip("h5py")
    h5 = tmp_path / "foreign.h5"
    with h5py.File(h5, "w") as f:
        f["vx"] = np.full((1, 400), 20.0)
        f["vx"].attrs["MATLAB_class"] = np.bytes_("double")
        f.attrs["note"] = SECRET
    text = tmp_path / "foreign.txt"
    text.write_text(SECRET + "\n" * 4000)
    return {"h5": h5, "text": text}


def _in_file(*names: str) -> str:
    """An absolute HDF5 path inside the file being written (from its root group), which a
    soft link names; not a path of the machine."""
    return "/" + "/".join(names)


def _replace_vx(kind: str, foreign: dict[str, Path]):
    def extra(h5py, group) -> None:
        del group["vx"]
        if kind == "external link":
            group["vx"] = h5py.ExternalLink(str(foreign["h5"]), "/vx")
        elif kind == "external link to text":
            group["vx"] = h5py.ExternalLink(str(foreign["text"]), "/vx")
        elif kind == "soft link loop":
            group["vx"] = h5py.SoftLink(_in_file("rec", "speed"))
            group["speed"] = h5py.SoftLink(_in_file("rec", "vx"))
        elif kind == "dangling soft link":
            group["vx"] = h5py.SoftLink(_in_file("nowhere", "vx"))
        elif kind == "soft link through an external link":
            group["elsewhere"] = h5py.ExternalLink(str(foreign["h5"]), "/")
            group["vx"] = h5py.SoftLink(_in_file("rec", "elsewhere", "vx"))
        elif kind == "virtual dataset":
            layout = h5py.VirtualLayout(shape=(1, 400), dtype="f8")
            layout[0, :] = h5py.VirtualSource(str(foreign["h5"]), "vx", shape=(1, 400))[0, :]
            group.create_virtual_dataset("vx", layout)
            group["vx"].attrs["MATLAB_class"] = np.bytes_("double")
        elif kind == "external storage":
            group.create_dataset("vx", shape=(1, 400), dtype="f8",
                                 external=[(str(foreign["text"]), 0, 400 * 8)])  # fmt: skip
            group["vx"].attrs["MATLAB_class"] = np.bytes_("double")

    return extra


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("external link", "external link to another file"),
        ("external link to text", "external link to another file"),
        ("soft link loop", "does not resolve"),
        ("dangling soft link", "which does not exist in the file"),
        ("soft link through an external link", "external link to another file"),
        ("virtual dataset", "virtual dataset"),
        ("external storage", "external storage"),
    ],
)
def test_a_v73_variable_that_leads_out_of_the_file_is_refused(
    tmp_path: Path, foreign: dict[str, Path], kind: str, message: str
):
    src = savemat73(tmp_path / "rec.mat", synthetic_channels(n=400), _replace_vx(kind, foreign))
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, {"struct": "rec"}))
    assert_refused(res, out, str(src), "'vx'", message)


def test_a_v73_struct_behind_an_external_link_is_refused(tmp_path: Path, foreign):
    def extra(h5py, group) -> None:
        group.file["outside"] = h5py.ExternalLink(str(foreign["h5"]), "/")

    src = savemat73(tmp_path / "rec.mat", synthetic_channels(n=400), extra)
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, {"struct": "outside"}))
    assert_refused(res, out, str(src), "'outside'", "external link to another file")
    # a path inside the name would be followed through the link: not a name of the file
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, {"struct": "outside/vx"}))
    assert_refused(res, out, str(src), "struct 'outside/vx' not found")


def test_a_v73_soft_link_inside_the_file_is_read(tmp_path: Path):
    c = synthetic_channels(n=400)

    def extra(h5py, group) -> None:
        group.file["speeds/vx"] = group["vx"][()]
        group.file["speeds/vx"].attrs["MATLAB_class"] = np.bytes_("double")
        del group["vx"]
        group["vx"] = h5py.SoftLink(_in_file("speeds", "vx"))

    src = savemat73(tmp_path / "rec.mat", c, extra)
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, {"struct": "rec"}))
    assert res.returncode == 0, res.stderr
    np.testing.assert_allclose(load_dataset(out).manoeuvres[0].vx, c["vx"], rtol=1e-12)


# =========================================================================== time backwards
def _backwards(n: int = 400, at: int = 250) -> dict[str, np.ndarray]:
    """Channels whose time steps back by 0.5 s at sample ``at`` (0-based): a logger clock
    reset."""
    c = synthetic_channels(n=n)
    c["t"] = c["t"].copy()
    c["t"][at:] -= 0.5
    return c


def _write(fmt: str, path: Path, c: dict[str, np.ndarray]) -> Path:
    if fmt == "csv":
        rows = [",".join(c)] + [",".join(repr(float(v)) for v in row) for row in zip(*c.values())]
        path.write_text("\n".join(rows) + "\n")
    elif fmt == "parquet":
        pa = pytest.importorskip("pyarrow")
        pq = pytest.importorskip("pyarrow.parquet")
        pq.write_table(pa.table({k: pa.array(v) for k, v in c.items()}), path)
    elif fmt == "mat":
        scipy.io.savemat(path, c)
    else:
        savemat73(path, c)
    return path


@pytest.mark.parametrize(
    ("fmt", "name", "source", "row"),
    [
        ("csv", "rec.csv", None, 252),  # the header is row 1: sample 250 is line 252
        ("parquet", "rec.parquet", None, 251),
        ("mat", "rec.mat", None, 251),
        ("mat73", "rec.mat", {"struct": "rec"}, 251),
    ],
)
def test_time_running_backwards_is_refused_in_every_format(tmp_path, fmt, name, source, row):
    src = _write(fmt, tmp_path / name, _backwards())
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, source, min_speed=1.0))
    assert_refused(res, out, str(src), "column 't'", f"row {row}", "decreasing")


def write_mdf(tmp_path: Path, signals: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    """An MDF4 file of ``name → (samples, timestamps)``, each signal in a group of its own
    (asammdf resamples signals appended together onto the first one's timestamps), and the
    mapping ``map.toml`` of :data:`CHANNELS` but t onto the signals ``S_<channel>``."""
    asammdf = pytest.importorskip("asammdf")
    mdf = asammdf.MDF(version="4.10")
    for name, (samples, stamps) in signals.items():
        mdf.append([asammdf.Signal(samples, stamps, name=name)])
    mdf.save(tmp_path / "rec.mf4", overwrite=True)
    mdf.close()
    lines = ['vehicle = "bmw-320i"', "[channels]"]
    lines += [f'{k} = "S_{k}"' for k in CHANNELS if k != "t"]
    (tmp_path / "map.toml").write_text("\n".join(lines) + "\n")
    return tmp_path / "rec.mf4"


def test_an_mdf_signal_whose_timestamps_run_backwards_is_refused(tmp_path: Path):
    c = synthetic_channels(n=400)
    back = _backwards()["t"]  # r's clock steps back
    src = write_mdf(
        tmp_path,
        {f"S_{k}": (c[k], back if k == "r" else c["t"]) for k in CHANNELS if k != "t"},
    )
    res, out = run_import(tmp_path, src, tmp_path / "map.toml")
    assert_refused(res, out, str(src), "'S_r'", "row 251", "decreasing")


def test_an_mdf_signal_beyond_the_row_limit_is_refused_before_it_is_loaded(tmp_path, monkeypatch):
    c = synthetic_channels(n=400)
    signals = {f"S_{k}": (c[k], c["t"]) for k in CHANNELS if k != "t"}
    long = np.arange(2 * 10**6) * 1e-3  # 2 M samples, 16 MB each of time and values
    signals["S_vx"] = (np.full(long.size, 20.0), long)
    src = write_mdf(tmp_path, signals)
    monkeypatch.setenv("KFTUNE_MAX_ROWS", "5e5")
    res, out, peak = _peak_of_import(tmp_path, src, mapping=tmp_path / "map.toml")
    assert_refused(res, out, str(src), "'S_vx'", "2,000,000 samples", "KFTUNE_MAX_ROWS")
    assert peak < 8 * 2**20, f"peak {peak / 2**20:.1f} MiB"


def test_an_mdf_signal_of_large_records_in_a_small_file_is_refused_before_it_is_loaded(
    tmp_path,
):
    """'S_vx' of 100 kB arrays (40 MB of records) in a compressed file of tens of kB:
    asammdf reads a channel group's records whole (1 MB arrays took 640 MB from a 500 kB
    file); sized from the group's header, it is refused first."""
    asammdf = pytest.importorskip("asammdf")
    c = synthetic_channels(n=400)
    write_mdf(tmp_path, {f"S_{k}": (c[k], c["t"]) for k in CHANNELS if k != "t"})  # map.toml
    mdf = asammdf.MDF(version="4.10")
    for k in CHANNELS:
        if k != "t":
            big = np.zeros((400, 100_000), np.uint8) if k == "vx" else c[k]
            mdf.append([asammdf.Signal(big, c["t"], name=f"S_{k}")])
    src = tmp_path / "big.mf4"
    mdf.save(src, overwrite=True, compression=2)
    mdf.close()
    assert src.stat().st_size < 2**20
    res, out, peak = _peak_of_import(tmp_path, src, mapping=tmp_path / "map.toml")
    assert_refused(res, out, str(src), "'S_vx'", "400 records of 100,008 bytes", "KFTUNE_MAX_RATIO")
    assert peak < 16 * 2**20, f"peak {peak / 2**20:.1f} MiB"


def test_time_running_backwards_where_min_speed_drops_the_rows_is_still_refused(tmp_path):
    c = _backwards(at=120)
    c["vx"][100:150] = 0.0  # standing still where the clock steps back
    src = _write("csv", tmp_path / "rec.csv", c)
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, min_speed=1.0))
    assert_refused(res, out, str(src), "column 't'", "row 122", "decreasing")


# =========================================================================== bombs
HEADER = ",".join(CHANNELS).encode() + b"\n"


def gzip_file(path: Path, body: bytes, repeat: int) -> Path:
    """``HEADER`` then ``body`` ``repeat`` times, gzipped."""
    with gzip.open(path, "wb", compresslevel=9) as fh:
        fh.write(HEADER)
        for _ in range(repeat):
            fh.write(body)
    return path


def test_a_gzip_file_that_unpacks_to_many_times_its_size_stops_early(tmp_path, monkeypatch):
    """64 MiB of rows in 160 kB are refused by a first pass that keeps nothing: parsing up
    to the limit (8 MiB and 100 times the file) would have made 50 MB of arrays first."""
    row = b"0.01,20,0,0,0,0,0\n"
    src = gzip_file(tmp_path / "rec.csv.gz", row * 2**16, 56)
    size = src.stat().st_size
    assert size < 2**18
    res, out, peak = _peak_of_import(tmp_path, src)
    ratio = textfile.DEFAULT_MAX_RATIO
    assert_refused(res, out, str(src), f"{ratio} times its {size:,} bytes", "KFTUNE_MAX_RATIO")
    assert peak < 8 * 2**20, f"peak {peak / 2**20:.1f} MiB"
    monkeypatch.setattr(textfile, "RATIO_FREE_BYTES", 2**20)  # a smaller file is enough
    src = gzip_file(tmp_path / "rec.csv.gz", row * 2**16, 8)  # 9.4 MB of rows in 20 kB
    assert_refused(*run_import(tmp_path, src), str(src), "KFTUNE_MAX_RATIO")
    monkeypatch.setenv("KFTUNE_MAX_RATIO", "2000")  # a genuine file of constant rows
    res, out = run_import(tmp_path, src)
    assert_refused(res, out, str(src), "time is duplicated")  # read to the end, then checked
    with pytest.raises(ConfigError, match="KFTUNE_MAX_RATIO must be a whole number"):
        monkeypatch.setenv("KFTUNE_MAX_RATIO", "0")
        ReadLimits.from_env()


def test_a_logger_export_with_many_constant_columns_loads(tmp_path, monkeypatch):
    """300 unmapped columns of zeros beside the channels: a genuine file that compresses
    over 20 times (the first default refused it), well within the ratio limit."""
    c = synthetic_channels(n=4000)
    zeros = ",0" * 300
    values = zip(*(c[k] for k in CHANNELS))
    rows = [",".join(f"{float(v):.5g}" for v in row) + zeros for row in values]
    header = ",".join(CHANNELS) + "".join(f",status{i}" for i in range(300)) + "\n"
    body = (header + "\n".join(rows) + "\n").encode()
    src = tmp_path / "rec.csv.gz"
    src.write_bytes(gzip.compress(body, 9))
    assert len(body) / src.stat().st_size > 20
    monkeypatch.setattr(textfile, "RATIO_FREE_BYTES", 0)  # the ratio alone, on a small file
    res, out = run_import(tmp_path, src)
    assert res.returncode == 0, res.stderr
    np.testing.assert_allclose(load_dataset(out).manoeuvres[0].vx, c["vx"], rtol=1e-4)


def test_a_compressed_recording_loads_within_the_ratio(tmp_path):
    c = synthetic_channels(n=400)
    rows = [",".join(repr(float(v)) for v in row) for row in zip(*(c[k] for k in CHANNELS))]
    src = gzip_file(tmp_path / "rec.csv.gz", ("\n".join(rows) + "\n").encode(), 1)
    res, out = run_import(tmp_path, src)
    assert res.returncode == 0, res.stderr
    np.testing.assert_allclose(load_dataset(out).manoeuvres[0].ay, c["ay"], rtol=1e-12)


@pytest.mark.parametrize("compress", [False, True])
def test_blank_lines_stop_after_a_thousand(tmp_path, monkeypatch, compress: bool):
    c = synthetic_channels(n=400)
    rows = [",".join(repr(float(v)) for v in row) for row in zip(*(c[k] for k in CHANNELS))]
    text = ("\n".join(rows) + "\n").encode()
    if compress:  # 200 MiB of line feeds in 200 kB: the ratio refuses it first, else this
        monkeypatch.setenv("KFTUNE_MAX_RATIO", "1e6")
        src = gzip_file(tmp_path / "rec.csv.gz", text, 1)
        with gzip.open(src, "ab", compresslevel=9) as fh:
            for _ in range(200):
                fh.write(b"\n" * 2**20)
    else:
        src = tmp_path / "rec.csv"
        src.write_bytes(HEADER + text + b"\r\n" * 5000)
    res, out = run_import(tmp_path, src)
    assert_refused(res, out, str(src), "row 402", "more than 1,000 empty lines in a row")
    src.write_bytes(HEADER + text + b"\n" * 10)  # a few at the end are fine
    src = src.rename(tmp_path / "rec.csv")
    res, out = run_import(tmp_path, src)
    assert res.returncode == 0, res.stderr


# =========================================================================== not a file
@pytest.mark.slow
def test_a_device_or_a_fifo_is_not_a_regular_file(tmp_path: Path):
    """Refused before it is opened: a FIFO with no writer would block the open for ever
    (so it runs in a subprocess, whose timeout only guards against that hang)."""
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    zero = tmp_path / "zero.csv"
    zero.symlink_to(DEV_ZERO)
    mapping = mapping_file(tmp_path)
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "dataset", "import", str(fifo), "--mapping",
         str(mapping), "-o", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert_refused(res, tmp_path / "out", str(fifo), "not a regular file")
    for src, what in ((zero, "not a regular file"), (tmp_path, "no file 't.txt' in the folder")):
        res, out = run_import(tmp_path, src, mapping)  # a folder: one file per signal
        assert_refused(res, out, str(src), what)
    folder = tmp_path / "cols"  # a signal's file in a folder of column files: also refused
    folder.mkdir()
    os.mkfifo(folder / "t.txt")
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "dataset", "import", str(folder), "--mapping",
         str(mapping), "-o", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert_refused(res, tmp_path / "out", str(folder / "t.txt"), "not a regular file")


# =========================================================================== disk full
def _two_recordings(tmp_path: Path) -> list[Path]:
    paths = []
    for i in range(2):
        c = synthetic_channels(n=400, seed=i)
        paths.append(_write("csv", tmp_path / f"rec{i}.csv", c))
    return paths


def _disk_full_after(monkeypatch, files: int) -> None:
    """Make every write of a file into a folder after the first ``files`` fail as a full
    disk does (``OSError(ENOSPC)`` from ``write``, which names no file)."""
    written = []
    real = Path.write_bytes

    def write_bytes(self: Path, data: bytes) -> int:
        if len(written) >= files:
            real(self, data[: len(data) // 2])  # a partial file, as a full disk leaves
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written.append(self)
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", write_bytes)


def test_a_full_disk_while_importing_leaves_nothing_and_a_rerun_works(tmp_path, monkeypatch):
    sources = _two_recordings(tmp_path)
    args = ("dataset", "import", *sources, "--mapping", mapping_file(tmp_path), "-o")
    out = tmp_path / "out"
    before = set(tmp_path.iterdir())
    _disk_full_after(monkeypatch, 1)
    res = run_cli(*args, out)
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr and "standard output" not in res.stderr
    assert str(out / "rec1.csv.gz") in res.stderr and "No space left on device" in res.stderr
    assert set(tmp_path.iterdir()) == before  # no partial dataset, no temporary folder
    monkeypatch.undo()
    res = run_cli(*args, out)
    assert res.returncode == 0, res.stderr
    assert [m.name for m in load_dataset(out).manoeuvres] == ["rec0", "rec1"]


def test_a_full_disk_while_replacing_a_dataset_keeps_the_old_one(tmp_path, monkeypatch):
    sources = _two_recordings(tmp_path)
    mapping = mapping_file(tmp_path)
    out = tmp_path / "out"
    assert run_cli("dataset", "import", sources[0], "--mapping", mapping, "-o", out).returncode == 0
    (out / "notes.txt").write_text("mine")
    old = {p.name: p.read_bytes() for p in out.iterdir()}
    _disk_full_after(monkeypatch, 0)
    res = run_cli("dataset", "import", *sources, "--mapping", mapping, "-o", out, "--force")
    assert res.returncode == 1 and "No space left on device" in res.stderr, res.stderr
    assert {p.name: p.read_bytes() for p in out.iterdir()} == old
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
    monkeypatch.undo()
    res = run_cli("dataset", "import", *sources, "--mapping", mapping, "-o", out, "--force")
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in out.iterdir()) == [
        "manifest.toml", "notes.txt", "rec0.csv.gz", "rec1.csv.gz"
    ]  # fmt: skip


# =========================================================================== MATLAB sizes
def _peak_of_import(
    tmp_path: Path, src: Path, source: dict | None = None, mapping: Path | None = None
) -> tuple:
    """Import ``src`` in this process under tracemalloc: (result, out, peak bytes)."""
    mapping = mapping or mapping_file(tmp_path, source)
    run_cli("dataset", "import", "--help")  # the modules the command imports, not counted
    tracemalloc.start()
    try:
        res, out = run_import(tmp_path, src, mapping)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return res, out, peak


def test_an_unmapped_struct_field_is_never_loaded(tmp_path: Path):
    """A 64 MB field of zeros beside the mapped ones (a file of 70 kB) is skipped in 1 MiB
    blocks: loadmat loaded the whole struct to reach the fields asked for."""
    c = synthetic_channels(n=400)
    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, {"rec": {**c, "unused": np.zeros((8, 10**6))}}, do_compression=True)
    assert src.stat().st_size < 2**20
    res, out, peak = _peak_of_import(tmp_path, src, {"struct": "rec"})
    assert res.returncode == 0, res.stderr
    assert peak < 16 * 2**20, f"peak {peak / 2**20:.1f} MiB"
    np.testing.assert_allclose(load_dataset(out).manoeuvres[0].vx, c["vx"], rtol=1e-12)


@pytest.mark.parametrize("struct", [None, "rec"])
def test_a_mapped_matlab_variable_beyond_the_row_limit_is_refused_from_its_header(
    tmp_path: Path, monkeypatch, struct: str | None
):
    c = synthetic_channels(n=400)
    c["vx"] = np.full(4 * 10**6, 20.0)  # 32 MB of one value, beyond a limit of 1 M rows
    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, {"rec": c} if struct else c, do_compression=True)
    monkeypatch.setenv("KFTUNE_MAX_ROWS", "1e6")
    res, out, peak = _peak_of_import(tmp_path, src, {"struct": struct} if struct else None)
    assert_refused(res, out, str(src), "'vx'", "4,000,000 elements", "KFTUNE_MAX_ROWS")
    assert peak < 16 * 2**20, f"peak {peak / 2**20:.1f} MiB"


def test_a_matlab_file_that_inflates_beyond_the_byte_limit_stops(tmp_path, monkeypatch):
    c = synthetic_channels(n=400)
    src = tmp_path / "rec.mat"
    # a field is inflated to be skipped (a variable at the top level is skipped unread)
    scipy.io.savemat(src, {"rec": {"unused": np.zeros((8, 10**6)), **c}}, do_compression=True)
    monkeypatch.setenv("KFTUNE_MAX_BYTES", "2e7")
    res, out = run_import(tmp_path, src, mapping_file(tmp_path, {"struct": "rec"}))
    assert_refused(res, out, str(src), "20,000,000 bytes", "KFTUNE_MAX_BYTES")


def test_a_compressed_matlab_recording_takes_little_more_memory_than_its_arrays(tmp_path):
    """Each variable is read, checked and converted before the next (loadmat read them
    all, and a float64 copy of each followed: twice the arrays kept)."""
    c = synthetic_channels(n=200_000)
    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, c, do_compression=True)
    tracemalloc.start()
    try:
        values = mat_variables(src, list(c), None, ReadLimits())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    kept = sum(v.nbytes for v in values.values())
    assert kept == 200_000 * len(c) * 8
    assert peak < 1.5 * kept, f"peak {peak / 2**20:.1f} MiB for {kept / 2**20:.1f} MiB kept"


def test_a_damaged_data_type_in_a_matlab_file_is_refused_not_a_crash(tmp_path: Path):
    """SciPy's reader indexes a table by a data element's type unchecked: a damaged type
    byte crashed the process (SIGSEGV or SIGBUS). In a subprocess, so that a crash is a
    failure of this test only."""
    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, synthetic_channels(n=400), do_compression=False)
    data = bytearray(src.read_bytes())
    tag = data.index(struct.pack("<II", 9, 400 * 8))  # the first variable's doubles
    data[tag + 1] = 0xE0  # miDOUBLE (9) becomes type 0xE009
    src.write_bytes(bytes(data))
    out = tmp_path / "out"
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "dataset", "import", str(src), "--mapping",
         str(mapping_file(tmp_path)), "-o", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert_refused(res, out, str(src), "not a readable MATLAB file", "type 57353")


def test_a_v73_variable_of_long_strings_is_refused_before_it_is_loaded(tmp_path):
    """'vx' tagged double but stored as 200 strings of 1 MB, compressed to a few kB: its
    dtype is checked before it is read (loaded first, it took 200 MB before the refusal)."""
    c = synthetic_channels(n=400)

    def strings(h5py, group) -> None:
        ds = group.create_dataset("vx", shape=(1, 200), dtype="S1000000", chunks=(1, 4),
                                  compression="gzip")  # fmt: skip
        ds.attrs["MATLAB_class"] = np.bytes_("double")

    src = savemat73(tmp_path / "rec.mat", {k: v for k, v in c.items() if k != "vx"}, strings)
    assert src.stat().st_size < 2**17
    res, out, peak = _peak_of_import(tmp_path, src, {"struct": "rec"})
    assert_refused(res, out, str(src), "'vx'", "not as numbers")
    assert peak < 16 * 2**20, f"peak {peak / 2**20:.1f} MiB"


def test_a_compressed_matlab_variable_whose_name_claims_megabytes_is_refused(tmp_path):
    """An unmapped variable whose name element claims 32 MiB (of one letter, 32 kB
    compressed): SciPy fills a buffer of the claimed size while reading the header, so a
    500 kB file made the import take 1.2 GB (and up to KFTUNE_MAX_BYTES). Refused."""
    buf = io.BytesIO()
    scipy.io.savemat(buf, synthetic_channels(n=400), do_compression=True)
    good = buf.getvalue()
    size = 32 * 2**20
    body = struct.pack("<IIII", 6, 8, 6, 0) + struct.pack("<IIii", 5, 8, 1, 1)  # double, 1×1
    body += struct.pack("<II", 1, size) + b"a" * size  # the name
    body += struct.pack("<IId", 9, 8, 1.0)
    packed = zlib.compress(struct.pack("<II", 14, len(body)) + body, 9)
    src = tmp_path / "rec.mat"
    src.write_bytes(good[:128] + struct.pack("<II", 15, len(packed)) + packed + good[128:])
    res, out = run_import(tmp_path, src)
    assert_refused(res, out, str(src), "not a readable MATLAB file", "headers or field names")


@settings(max_examples=40, deadline=None)
@given(
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=12),
    cut=st.integers(0, 10**6),
    compress=st.booleans(),
)
def test_damaged_matlab_structs_give_data_or_a_short_data_error(flips, cut, compress):
    """Any damage to a file of a struct (skipped fields, nested ones, the mapped ones)
    gives the data or a DataError naming the file: never another exception or a crash."""
    buf = io.BytesIO()
    c = synthetic_channels(n=50)
    scipy.io.savemat(buf, {"log": {"note": "x", "rec": c, "more": np.ones((3, 40))}},
                     do_compression=compress)  # fmt: skip
    data = bytearray(buf.getvalue())
    for pos, value in flips:
        data[pos % len(data)] = value
    with tempfile.TemporaryDirectory() as folder:
        f = Path(folder) / "rec.mat"
        f.write_bytes(bytes(data[: max(1, cut % (len(data) + 1))]))
        try:
            values = mat_variables(f, list(c), "log.rec", ReadLimits(max_bytes=2**24))
            assert all(v.shape == (50,) for v in values.values())
        except DataError as exc:
            assert exc.file == str(f) and len(str(exc)) < 600


def _scipy_without(monkeypatch, what: str) -> str:
    """Take ``what`` out of SciPy's private MAT-file internals, as another SciPy version
    might have them; the name the message should give."""
    import scipy.io.matlab
    from scipy.io.matlab import _mio5

    if what == "module":
        monkeypatch.delattr(scipy.io.matlab, "_mio5_params")
        monkeypatch.setitem(sys.modules, "scipy.io.matlab._mio5_params", None)
        return "_mio5_params"
    if what == "method":
        monkeypatch.delattr(_mio5.MatFile5Reader, "read_file_header")
        return "MatFile5Reader.read_file_header"
    monkeypatch.setattr(_mio5.MatFile5Reader, "initialize_read", lambda self: None)
    return "MatFile5Reader()._file_reader"


@pytest.mark.parametrize("what", ["module", "method", "reader attribute"])
def test_a_scipy_without_the_matlab_internals_kftune_uses_is_named(tmp_path, monkeypatch, what):
    """The v5 walker uses SciPy's private modules: a SciPy whose internals differ is named
    as the cause (its version, what it lacks), exit 3, not a traceback or a damaged file."""
    import scipy

    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, synthetic_channels(n=400))
    lacking = _scipy_without(monkeypatch, what)
    res, out = run_import(tmp_path, src)
    assert_refused(res, out, str(src), f"SciPy {scipy.__version__}", lacking, "v7.3")
    assert "not a readable MATLAB file" not in res.stderr


def test_a_matlab_v4_file_is_read_by_name_and_sized_first(tmp_path: Path, monkeypatch):
    c = synthetic_channels(n=400)
    src = tmp_path / "rec.mat"
    scipy.io.savemat(src, {**c, "unused": np.zeros(10)}, format="4")
    res, out = run_import(tmp_path, src)
    assert res.returncode == 0, res.stderr
    np.testing.assert_allclose(load_dataset(out).manoeuvres[0].ay, c["ay"], rtol=1e-12)
    monkeypatch.setenv("KFTUNE_MAX_ROWS", "300")
    (tmp_path / "again").mkdir()
    res, out = run_import(tmp_path / "again", src)
    assert_refused(res, out, str(src), "400 elements", "KFTUNE_MAX_ROWS")
