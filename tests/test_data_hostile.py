"""Hostile and malformed input: manifests that point outside the dataset, names that would
write outside the working folder, files that would fill the memory, and messages that would
quote a whole file. Each case is checked through the API and, where a user meets it, through
the ``kftune`` command in a subprocess (exit code, message naming the file / column / row /
option, no traceback, nothing written or deleted outside)."""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import run_cli
from kftune.cli import main
from kftune.data import (
    SIDESLIP_CHANNELS,
    Dataset,
    import_recordings,
    load_dataset,
    save_dataset,
    textfile,
)
from kftune.data.io import file_stem, read_csv
from kftune.data.readers import read_text_table
from kftune.data.textfile import ReadLimits, read_values
from kftune.errors import ConfigError, DataError, DataWarning
from kftune.optim import METHODS
from kftune.vehicle import preset
from test_data_helpers import synthetic_channels, synthetic_dataset, synthetic_manoeuvre

SECRET = "SECRET-first-line-of-a-foreign-file"
SI = dict.fromkeys(SIDESLIP_CHANNELS, 1.0)


def kftune(*args: object, cwd: Path | None = None, env: dict | None = None):
    """``kftune ARGS``: in this process, or a real one when ``env`` sets its environment."""
    if env is None:
        return run_cli(*map(str, args), cwd=cwd)
    return subprocess.run(
        [sys.executable, "-m", "kftune", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={**os.environ, **(env or {})},
        timeout=300,
    )


def assert_clean_failure(res: subprocess.CompletedProcess, code: int, *names: str) -> None:
    """Exit ``code``, one ``kftune: error`` line naming each of ``names``, no traceback,
    no foreign content, a short message."""
    assert res.returncode == code, res.stderr
    assert "Traceback" not in res.stderr and SECRET not in res.stderr + res.stdout
    assert res.stderr.startswith("kftune: error: ") and len(res.stderr) < 1500, res.stderr
    for name in names:
        assert name in res.stderr, (name, res.stderr)


def csv_text(n: int = 400, sep: str = ",", newline: str = "\n") -> str:
    c = synthetic_channels(n=n)
    rows = [sep.join(SIDESLIP_CHANNELS)]
    rows += [sep.join(repr(float(c[k][i])) for k in SIDESLIP_CHANNELS) for i in range(n)]
    return newline.join(rows) + newline


@pytest.fixture
def dataset_dir(tmp_path: Path) -> Path:
    """A valid one-manoeuvre dataset (plain CSV) in ``tmp_path/ds``; a foreign file with a
    secret first line beside it in ``tmp_path/foreign.csv``."""
    save_dataset(synthetic_dataset(1, 0), tmp_path / "ds", compress=False)
    (tmp_path / "foreign.csv").write_text(f"{SECRET}\n1,2,3\n")
    return tmp_path / "ds"


def point_manifest_at(ds: Path, target: str) -> Path:
    manifest = ds / "manifest.toml"
    text = manifest.read_text().replace('file = "tr0.csv"', f"file = {target!r}".replace("'", '"'))
    manifest.write_text(text)
    return manifest


# =========================================================================== traversal
@pytest.mark.parametrize("target", ["../foreign.csv", "ABS", "sub/../../foreign.csv", "LINK"])
def test_manifest_paths_out_of_the_dataset_are_refused_without_quoting_them(
    dataset_dir: Path, target: str
):
    foreign = dataset_dir.parent / "foreign.csv"
    if target == "ABS":
        target = str(foreign)
    elif target == "LINK":
        (dataset_dir / "link.csv").symlink_to(foreign)
        target = "link.csv"
    manifest = point_manifest_at(dataset_dir, target)
    with pytest.raises(DataError) as info:
        load_dataset(dataset_dir)
    assert info.value.file == str(manifest)
    assert "manoeuvres[0].file" in str(info.value) and "outside the dataset folder" in str(
        info.value
    )
    assert SECRET not in str(info.value)


#: The file-system root; system files are named from it (no literal absolute paths here).
ROOT = Path(os.sep)


def test_system_files_named_in_a_manifest_are_refused_by_the_command(dataset_dir: Path):
    system_files = (ROOT / "etc" / "passwd", ROOT / "proc" / "self" / "environ")
    for target in (*map(str, system_files), "../../../../../../etc/shadow"):
        manifest = point_manifest_at(dataset_dir, target)
        res = kftune("dataset", "info", dataset_dir)
        assert_clean_failure(res, 3, str(manifest), "manoeuvres[0].file", "outside")
        assert "root:" not in res.stderr  # /etc/passwd's first line
        save_dataset(synthetic_dataset(1, 0), dataset_dir, compress=False)  # reset


def test_links_inside_the_dataset_still_load(dataset_dir: Path):
    (dataset_dir / "data").mkdir()
    (dataset_dir / "tr0.csv").rename(dataset_dir / "data" / "tr0.csv")
    (dataset_dir / "alias.csv").symlink_to(dataset_dir / "data" / "tr0.csv")
    point_manifest_at(dataset_dir, "alias.csv")
    assert load_dataset(dataset_dir).manoeuvres[0].equals(synthetic_dataset(1, 0).manoeuvres[0])


def test_force_never_deletes_a_file_outside_the_dataset(dataset_dir: Path):
    victim = dataset_dir.parent / "foreign.csv"
    point_manifest_at(dataset_dir, "../foreign.csv")
    before = sorted(p.name for p in dataset_dir.iterdir())
    res = kftune("dataset", "generate", dataset_dir, "--force", "--quiet", "--only", "x")
    assert_clean_failure(res, 3, "--force", "outside the dataset folder")
    assert victim.read_text().startswith(SECRET)  # nothing lost
    assert sorted(p.name for p in dataset_dir.iterdir()) == before


# =========================================================================== names → paths
@settings(max_examples=50, deadline=None)  # hypothesis's 200 ms per example: load stretches it
@given(st.text(max_size=300))
def test_file_stem_never_leaves_the_folder(name: str):
    stem = file_stem(name)
    assert 0 < len(stem) <= 100 and not stem.startswith(".")
    assert set(stem) <= set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")
    folder = ROOT / "srv" / "out"
    assert (folder / f"{stem}.png").resolve().parent == folder


def test_registered_names_are_file_names_already():
    """Studies are stored as ``<method>.db``, manoeuvres as ``<name>.csv.gz``: the names
    kftune ships keep their spelling."""
    for name in (*METHODS, "train-01-braking-in-turn", "revs-250lm-s01"):
        assert file_stem(name) == name


def test_hostile_manoeuvre_names_stay_inside_every_output_folder(tmp_path: Path, monkeypatch):
    outside = tmp_path / "outside"
    names = ["../../evil", str(outside / "abs"), "a/b", ".hidden"]
    ms = [synthetic_manoeuvre(n, seed=i) for i, n in enumerate(names)]
    ds = synthetic_dataset(1, 0)
    ds = type(ds)(ds.name, ds.vehicle, ds.dt, tuple(ms), ds.description, ds.meta)
    save_dataset(ds, tmp_path / "ds")
    written = sorted(p.name for p in (tmp_path / "ds").iterdir())
    stems = ["_.._evil", file_stem(names[1]), "a_b", "hidden"]
    assert written == sorted([*(f"{s}.csv.gz" for s in stems), "manifest.toml"])
    back = load_dataset(tmp_path / "ds")
    assert back.names == tuple(names)  # the names themselves are kept
    # `dataset show` names its default file after the manoeuvre: in the working folder only
    work = tmp_path / "work"
    work.mkdir()
    res = kftune("dataset", "show", tmp_path / "ds", "-m", names[0], cwd=work)
    assert res.returncode == 0, res.stderr
    monkeypatch.chdir(work)
    assert main(["dataset", "show", str(tmp_path / "ds"), "-m", names[1]]) == 0
    assert sorted(p.name for p in work.iterdir()) == sorted(
        f"{file_stem(n)}.png" for n in names[:2]
    )
    assert not outside.exists() and not (tmp_path.parent / "evil.png").exists()
    twins = (synthetic_manoeuvre("a/b"), synthetic_manoeuvre("a_b", seed=1))
    with pytest.raises(ValueError, match=r"would both be written to a_b\.csv\.gz"):
        save_dataset(type(ds)("d", ds.vehicle, ds.dt, twins), tmp_path / "twins")


# =========================================================================== memory
def gzip_bomb(path: Path, mib: int, line: bytes) -> None:
    block = line * (2**20 // len(line))
    with gzip.open(path, "wb", compresslevel=9) as fh:
        fh.write(b",".join(c.encode() for c in SIDESLIP_CHANNELS) + b"\n")
        for _ in range(mib):
            fh.write(block)


def test_gzip_bomb_stops_at_the_byte_limit_with_little_memory(tmp_path: Path):
    f = tmp_path / "bomb.csv.gz"
    gzip_bomb(f, 64, b"0,0,0,0,0,0,0\n")  # 64 MiB of rows in 64 kB
    assert f.stat().st_size < 2**20
    tracemalloc.start()
    try:
        with pytest.raises(DataError, match="more than 4,194,304 bytes") as info:
            read_csv(f, SI, ReadLimits(max_bytes=4 * 2**20))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert info.value.file == str(f) and textfile.ENV_MAX_BYTES in str(info.value)
    # 4 MiB of rows parse into 17 MB of arrays before the limit stops the read (the whole
    # bomb would give 268 MB); the rest is one block of text and its lines
    assert peak < 40 * 2**20
    with pytest.raises(DataError, match="more than 1,000 rows") as info:  # the ratio allowing
        read_csv(f, SI, ReadLimits(max_rows=1000, max_ratio=10**6))
    assert info.value.row == 1002 and textfile.ENV_MAX_ROWS in str(info.value)


@pytest.mark.slow
def test_the_limits_come_from_the_environment_in_the_command(dataset_dir: Path):
    res = kftune("dataset", "info", dataset_dir, env={"KFTUNE_MAX_ROWS": "300"})
    assert_clean_failure(res, 3, str(dataset_dir / "tr0.csv"), "row 302", "KFTUNE_MAX_ROWS")
    res = kftune("dataset", "info", dataset_dir, env={"KFTUNE_MAX_BYTES": "1e4"})
    assert_clean_failure(res, 3, str(dataset_dir / "tr0.csv"), "10,000 bytes")
    res = kftune("dataset", "info", dataset_dir, env={"KFTUNE_MAX_ROWS": "lots"})
    assert_clean_failure(res, 3, "KFTUNE_MAX_ROWS", "whole number")


def test_limits_from_the_environment(monkeypatch, dataset_dir: Path):
    monkeypatch.setenv("KFTUNE_MAX_ROWS", "4e2")  # the manoeuvre's 400 rows: just within
    monkeypatch.setenv("KFTUNE_MAX_BYTES", " 123456 ")
    assert ReadLimits.from_env() == ReadLimits(max_bytes=123456, max_rows=400)
    assert load_dataset(dataset_dir).manoeuvres[0].n == 400
    monkeypatch.delenv("KFTUNE_MAX_BYTES")
    for bad in ("0", "-5", "2.5", "inf", "1e30"):
        monkeypatch.setenv("KFTUNE_MAX_ROWS", bad)
        with pytest.raises(ConfigError, match="KFTUNE_MAX_ROWS must be a whole number"):
            ReadLimits.from_env()
    with pytest.raises(ConfigError, match="max_rows"):
        ReadLimits(max_rows=0)


def test_files_without_line_breaks_stop_after_one_block(tmp_path: Path):
    sparse = tmp_path / "sparse.csv"
    with open(sparse, "wb") as fh:
        try:
            fh.truncate(50 * 2**30)  # 50 GB of holes
        except OSError:
            pytest.skip("no sparse files here")
    bomb = tmp_path / "nul.csv.gz"
    gzip_bomb(bomb, 32, b"\0" * 64)  # a header row, then 32 MiB without a line break
    tracemalloc.start()
    try:
        for f in (sparse, bomb):  # (the bomb within the ratio, which would refuse it first)
            with pytest.raises(DataError, match="line longer than 65,536 bytes") as info:
                read_csv(f, SI, ReadLimits(max_ratio=10**6))
            assert info.value.file == str(f)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20


def test_loading_takes_memory_in_proportion_to_the_arrays_kept(tmp_path: Path):
    """Peak traced memory of loading a 150,000-row manoeuvre (7 channels, 8.4 MB kept) is
    at most 3× the arrays kept (the reader's blocks, one copy into the frozen Manoeuvre,
    validation temporaries); benchmarks/data_memory.py measures it at 1 M and 36 M rows."""
    n = 150_000
    c = synthetic_channels(n=n)
    folder = tmp_path / "long"
    short = synthetic_manoeuvre("long", extra=False)
    save_dataset(Dataset("long", preset("bmw-320i"), 0.01, (short,)), folder, compress=False)
    with open(folder / "long.csv", "w") as fh:
        fh.write(",".join(SIDESLIP_CHANNELS) + "\n")
        columns = np.column_stack([c[k] for k in SIDESLIP_CHANNELS])
        np.savetxt(fh, columns, fmt="%.6f", delimiter=",")
    tracemalloc.start()
    try:
        ds = load_dataset(folder)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    kept = sum(ds.manoeuvres[0].channel(k).nbytes for k in ds.manoeuvres[0].channel_names)
    assert kept == n * 7 * 8
    assert peak <= 3 * kept, f"peak {peak / 2**20:.1f} MiB for {kept / 2**20:.1f} MiB kept"


# =========================================================================== messages
def test_a_five_megabyte_line_gives_a_short_message(tmp_path: Path):
    f = tmp_path / "one-line.csv"
    f.write_text("t," + "x" * (5 * 2**20) + "\n")
    with pytest.raises(DataError, match="line longer than") as info:
        read_csv(f, SI)
    assert info.value.row == 1 and len(str(info.value)) < 300
    f.write_text("t,delta," + "y-" * 25_000 + "\n1,2,3\n")  # long, but within one line's limit
    with pytest.raises(DataError, match="is not an identifier") as info:
        read_csv(f, SI)
    assert len(str(info.value)) < 400 and "50,000 characters" in str(info.value)
    f.write_text(csv_text().replace("\n0.01,", "\n" + "9" * 50_000 + "z,", 1))
    with pytest.raises(DataError, match="cannot read") as info:
        read_csv(f, SI)
    assert (info.value.column, info.value.row) == ("t", 3) and len(str(info.value)) < 400


def test_the_command_quotes_no_five_megabyte_line(dataset_dir: Path):
    (dataset_dir / "tr0.csv").write_text(f"t,{SECRET}" + "x" * (5 * 2**20) + "\n1\n")
    res = kftune("dataset", "info", dataset_dir)
    assert_clean_failure(res, 3, str(dataset_dir / "tr0.csv"), "row 1", "line longer than")


@pytest.mark.parametrize(
    ("variant", "make"),
    [
        ("BOM", lambda: "\ufeff" + csv_text()),
        ("CRLF", lambda: csv_text(newline="\r\n")),
        ("BOM+CRLF+semicolon", lambda: "\ufeff" + csv_text(sep=";", newline="\r\n")),
        ("tab", lambda: csv_text(sep="\t")),
        ("trailing blank lines", lambda: csv_text() + "\n\n  \n"),
    ],
)
def test_common_export_variants_load_as_the_plain_file(tmp_path: Path, variant: str, make):
    plain = tmp_path / "plain.csv"
    plain.write_text(csv_text())
    f = tmp_path / "variant.csv.gz"
    with gzip.open(f, "wb") as fh:
        fh.write(make().encode("utf-8"))
    got, want = read_csv(f, SI), read_csv(plain, SI)
    assert list(got) == list(want)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k])


def _row_changed(row: int, edit) -> str:
    """csv_text() with line ``row`` (1 = header) edited."""
    lines = csv_text().split("\n")
    lines[row - 1] = edit(lines[row - 1])
    return "\n".join(lines)


@pytest.mark.parametrize(
    ("content", "message", "row", "column"),
    [
        (csv_text(sep=";").replace(".", ","), "decimal comma", 2, "t"),
        (
            _row_changed(7, lambda x: x.replace(",", ";", 2)),
            "has 5 fields, the header has 7",
            7,
            None,
        ),
        (
            _row_changed(9, lambda x: x.replace(",", ",,", 1)),
            "has 8 fields, the header has 7",
            9,
            None,
        ),
        (_row_changed(5, lambda x: "2_2.5" + x[x.index(",") :]), "cannot read '2_2.5'", 5, "t"),
        (_row_changed(6, lambda x: x[: x.rindex(",") + 1] + "１２"), "cannot read", 6, "beta_ref"),
        ("t\rdelta\r1\r2\r", "lone CR", 1, None),
        (csv_text().replace("\n", "\n\n", 5), "empty line inside the data", 2, None),
        (_row_changed(40, lambda x: ""), "empty line inside the data", 40, None),
        ("", "empty file", 1, None),
        (csv_text().split("\n")[0] + "\n", "no data rows", 2, None),
        (_row_changed(1, lambda x: x.replace("ay", "AY")), "unknown column", 1, "AY"),
    ],
)
def test_malformed_text_is_named(tmp_path: Path, content: str, message: str, row, column):
    f = tmp_path / "bad.csv"
    f.write_bytes(content.encode("utf-8"))
    with pytest.raises(DataError, match=message) as info:
        read_csv(f, SI)
    assert (info.value.file, info.value.row, info.value.column) == (str(f), row, column)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (csv_text().encode("utf-16"), "UTF-16"),
        (csv_text().encode() + b"\xff\xfe\x00", "not UTF-8"),
        (b"t,delta\x00,ax\n", "NUL bytes"),
        (b"\x1f\x8b\x08\x00not really gzip", "not UTF-8"),
    ],
)
def test_binary_content_is_named(tmp_path: Path, content: bytes, message: str):
    f = tmp_path / "bad.csv"
    f.write_bytes(content)
    with pytest.raises(DataError, match=message) as info:
        read_csv(f, SI)
    assert info.value.file == str(f)
    g = tmp_path / "bad.csv.gz"
    g.write_bytes(content[:40])
    with pytest.raises(DataError, match="not a valid gzip file"):
        read_csv(g, SI)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    block=st.integers(16, 4096),
    bad_row=st.integers(0, 299),
    bad_col=st.integers(0, 6),
    junk=st.sampled_from(["x", "", "1.2.3", "--", "nan!", "0x10", "2_2.5", "１２", "1e"]),
    corrupt=st.booleans(),
)
def test_block_boundaries_never_move_a_row(
    tmp_path, monkeypatch, block, bad_row, bad_col, junk, corrupt
):
    """Read in blocks of any size, a file gives the same numbers as NumPy reading it whole,
    and a bad value is reported at its own row and column."""
    monkeypatch.setattr(textfile, "BLOCK_BYTES", block)
    monkeypatch.setattr(textfile, "MAX_LINE_BYTES", 4096 + 200)
    lines = csv_text(300).splitlines()
    if corrupt:
        fields = lines[bad_row + 1].split(",")
        fields[bad_col] = junk
        lines[bad_row + 1] = ",".join(fields)
    f = tmp_path / "x.csv"
    f.write_text("\n".join(lines) + "\n")
    if corrupt:
        with pytest.raises(DataError, match="cannot read") as info:
            read_csv(f, SI)
        assert (info.value.row, info.value.column) == (bad_row + 2, SIDESLIP_CHANNELS[bad_col])
    else:
        whole = np.loadtxt(f, delimiter=",", skiprows=1)
        got = read_csv(f, SI)
        np.testing.assert_array_equal(np.column_stack([got[k] for k in SIDESLIP_CHANNELS]), whole)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.binary(max_size=3000))
def test_any_bytes_give_data_or_a_short_data_error(tmp_path, data: bytes):
    f = tmp_path / "fuzz.csv"
    f.write_bytes(b"t,delta,ax,ay,r,vx,beta_ref\n" + data)
    try:
        read_csv(f, SI)
    except DataError as exc:
        assert exc.file == str(f) and len(str(exc)) < 600
    g = tmp_path / "fuzz.txt"
    g.write_bytes(data)
    try:
        read_values(g)
    except DataError as exc:
        assert exc.file == str(g) and len(str(exc)) < 600


# =========================================================================== MATLAB
MAPPING = {"vehicle": "bmw-320i", "channels": {c: c for c in SIDESLIP_CHANNELS}}  # SI


@pytest.mark.parametrize(
    "content", [b"", b"hello, I am text\n" * 20, b"MATLAB 5.0 MAT-file" + b"\0" * 200]
)
def test_mat_import_of_text_or_empty_files_raises_data_error(tmp_path: Path, content: bytes):
    f = tmp_path / "rec.mat"
    f.write_bytes(content)
    with pytest.raises(DataError, match="not a readable MATLAB file") as info:
        import_recordings([f], MAPPING)
    assert info.value.file == str(f)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=12),
    cut=st.integers(0, 10**6),
    compress=st.booleans(),
)
def test_damaged_mat_files_raise_data_error(tmp_path, flips, cut, compress):
    f = tmp_path / "rec.mat"
    scipy.io.savemat(f, synthetic_channels(n=300), do_compression=compress)
    data = bytearray(f.read_bytes())
    for pos, value in flips:
        data[pos % len(data)] = value
    f.write_bytes(bytes(data[: max(1, cut % (len(data) + 1))]))
    try:
        import_recordings([f], MAPPING)
    except DataError as exc:
        assert exc.file == str(f) and len(str(exc)) < 600


def test_mat_variables_beyond_the_row_limit_are_refused_before_loading(tmp_path: Path):
    f = tmp_path / "rec.mat"
    scipy.io.savemat(f, synthetic_channels(n=500))
    with pytest.warns(DataWarning, match="makes none of the 1 manoeuvre test"):  # uncut
        assert len(import_recordings([f], MAPPING).manoeuvres[0].t) == 500
    with pytest.raises(DataError, match="has 500 elements, more than the limit of 400") as info:
        import_recordings([f], MAPPING, limits=ReadLimits(max_rows=400))
    assert textfile.ENV_MAX_ROWS in str(info.value)


# =========================================================================== import
IMPORT_CHANNELS = "\n".join(
    ["[channels]", 't = "t"', 'vx = "vx"', 'ay = "ay"', 'r = "r"', "delta = "
     '{ column = "delta", hand_wheel = true }']
)  # fmt: skip


@pytest.mark.parametrize(
    ("name", "content", "mapping", "named"),
    [
        # a catalogue vehicle without a steering ratio, for a hand-wheel channel
        ("rec.csv", csv_text().encode(), 'vehicle = "revs-250lm"\n',
         ["map.toml", "channels.delta.hand_wheel", "steering_ratio"]),
        # Windows-1252 text read as UTF-8: says how to name its encoding
        ("rec.csv", csv_text().replace("\n", ",°\n", 1).replace("\n", ",1\n").encode("cp1252"),
         'steering_ratio = 15.0\n', ["rec.csv", "row 1", '[source] encoding = "cp1252"']),
        # … and bytes that are not cp1252 either (0x81 is undefined in it)
        ("rec.csv", b"\x81" + csv_text().encode(),
         'steering_ratio = 15.0\n[source]\nencoding = "cp1252"\n', ["rec.csv", "row 1", "cp1252"]),
        # a typo under [source]
        ("rec.csv", csv_text().encode(), 'steering_ratio = 15.0\n[source]\ndelimeter = ","\n',
         ["map.toml", "'source.delimeter'"]),
        # a suffix no reader takes
        ("rec.dat", csv_text().encode(), "steering_ratio = 15.0\n",
         ["rec.dat", '[source] format = "csv"']),
    ],
)  # fmt: skip
def test_import_refuses_cleanly(tmp_path: Path, name, content, mapping, named):
    (tmp_path / name).write_bytes(content)
    (tmp_path / "map.toml").write_text(mapping + IMPORT_CHANNELS + "\n", encoding="utf-8")
    res = kftune("dataset", "import", tmp_path / name, "--mapping", tmp_path / "map.toml",
                 "-o", tmp_path / "out")  # fmt: skip
    assert_clean_failure(res, 3, *named)
    assert not (tmp_path / "out").exists()


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=2000), encoding=st.sampled_from(["cp1252", "latin-1", "utf-8"]))
def test_any_bytes_in_any_encoding_give_data_or_a_short_data_error(tmp_path, data, encoding):
    f = tmp_path / "fuzz.csv"
    f.write_bytes(b"t;vx\n" + data)
    try:
        read_text_table(f, ["t", "vx"], {"encoding": encoding}, ReadLimits())
    except DataError as exc:
        assert exc.file == str(f) and len(str(exc)) < 600
