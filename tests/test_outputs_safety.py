"""What the commands write and read at their edges: no output replaces an input of the same
command, every write is checked, only kftune's own files are deleted, every JSON a user
hands over is read by one loader that refuses hostile numbers by name, and numeric options
have documented upper limits. Each case asserts the exit code, that the message names the
file or option, that no traceback is printed and that nothing else is written."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import DEV_FULL, DEV_ZERO, run_cli
from kftune.data.jsonfile import MAX_INT_DIGITS, parse_json
from kftune.errors import DataError

LONG = "9" * (MAX_INT_DIGITS + 1)


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


# ------------------------------------------------------------------ JSON with huge numbers
def _tuned(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["evaluate", "--params", "t.json"]


def _estimate(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["estimate", "--params", "t.json", "-o", "est"]


def _export(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["export", "t.json", "-o", "t_c", "-f", "c"]


def _manifest(tmp: Path, text: str) -> list[str]:
    (tmp / "ds").mkdir()
    (tmp / "ds" / "manifest.json").write_text(text)
    return ["dataset", "info", "ds"]


def _results(tmp: Path, text: str) -> list[str]:
    (tmp / "r").mkdir()
    (tmp / "r" / "results.json").write_text(text)
    return ["report", "r", "-o", "rep"]


READERS = {
    "t.json": _tuned,
    "t.json ": _estimate,
    " t.json": _export,
    "manifest.json": _manifest,
    "results.json": _results,
}


@pytest.mark.parametrize("name", list(READERS))
@pytest.mark.parametrize(
    "text",
    [
        '{"format": "kftune-tuned", "q": [LONG]}',
        '{"schema": 1, "burn_in": -LONG}',
        '[[[{"a": {"b": [1, 2, LONG]}}]]]',
    ],
)
def test_an_integer_beyond_the_digit_limit_in_any_json_input_is_refused(tmp_path, name, text):
    """tuned files (evaluate, estimate, export), a dataset's manifest.json (dataset info) and
    results.json (report): exit 3 naming the file and the limit, nothing written."""
    args = READERS[name](tmp_path, text.replace("LONG", LONG))
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert name.strip() in res.stderr and f"more than {MAX_INT_DIGITS:,} digits" in res.stderr
    assert "Traceback" not in res.stderr and LONG not in res.stderr
    assert _files(tmp_path) == before


@pytest.mark.parametrize("name", ["t.json", "t.json ", " t.json", "results.json"])
def test_a_json_input_that_is_a_device_is_refused_before_it_is_read(tmp_path, name):
    """A tuned file or results.json that is /dev/zero (here through a link) was read
    whole: a MemoryError traceback after filling the memory. Exit 3 naming the file."""
    args = READERS[name](tmp_path, "{}")
    json_file = next(tmp_path.rglob(name.strip()))
    json_file.unlink()
    json_file.symlink_to(DEV_ZERO)
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert name.strip() in res.stderr and "not a regular file" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    assert _files(tmp_path) == before


@pytest.mark.parametrize("where", ["config", "mapping"])
def test_a_toml_input_that_is_a_device_is_refused_before_it_is_read(tmp_path, where):
    """A configuration or import mapping that is /dev/zero was read whole (a MemoryError
    traceback); one reader for every JSON and TOML input refuses it naming the file."""
    name = {"config": "run.toml", "mapping": "map.toml"}[where]
    args = {
        "config": ["tune", "--config", name, "-o", "t.json"],
        "mapping": ["dataset", "import", "rec.csv", "--mapping", name, "-o", "o"],
    }[where]
    (tmp_path / "rec.csv").write_text("t,vx\n0,1\n")
    (tmp_path / name).symlink_to(DEV_ZERO)
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert name in res.stderr and "not a regular file" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    assert _files(tmp_path) == before


@pytest.mark.slow
def test_a_tuned_file_that_is_a_fifo_is_refused_not_waited_on(tmp_path):
    """A FIFO with no writer blocked the open for ever. In a subprocess, whose timeout is
    only a hang guard."""
    fifo = tmp_path / "t.json"
    os.mkfifo(fifo)
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "evaluate", "--params", str(fifo)],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 3, res.stderr
    assert str(fifo) in res.stderr and "not a regular file" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    assert _files(tmp_path) == {fifo}


@pytest.mark.parametrize("where", ["config", "manifest", "mapping"])
def test_an_integer_beyond_the_digit_limit_in_a_toml_input_is_refused(tmp_path, where):
    if where == "config":
        (tmp_path / "run.toml").write_text(f"budget = {LONG}\n")
        args, name = ["tune", "--config", "run.toml", "-o", "t.json"], "run.toml"
    elif where == "mapping":
        (tmp_path / "rec.csv").write_text("t,vx\n0,1\n")
        (tmp_path / "map.toml").write_text(f"[source]\nx = {LONG}\n")
        args, name = (
            ["dataset", "import", "rec.csv", "--mapping", "map.toml", "-o", "o"],
            "map.toml",
        )
    else:
        (tmp_path / "ds").mkdir()
        (tmp_path / "ds" / "manifest.toml").write_text(f"name = 'x'\nn = {LONG}\n")
        args, name = ["dataset", "info", "ds"], "manifest.toml"
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3 and name in res.stderr, res.stderr
    assert f"more than {MAX_INT_DIGITS:,} digits" in res.stderr
    assert "Traceback" not in res.stderr and _files(tmp_path) == before


def test_a_deeply_nested_import_mapping_is_refused(tmp_path):
    (tmp_path / "rec.csv").write_text("t,vx\n0,1\n")
    (tmp_path / "map.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    before = _files(tmp_path)
    res = run_cli("dataset", "import", "rec.csv", "--mapping", "map.toml", "-o", "o", cwd=tmp_path)
    assert res.returncode == 3 and "map.toml" in res.stderr and "too deeply" in res.stderr
    assert "Traceback" not in res.stderr and _files(tmp_path) == before


def _containers(inner: st.SearchStrategy) -> st.SearchStrategy:
    """JSON arrays and objects of ``inner`` (a named function: hypothesis cannot read a
    lambda split over lines and warns that it does not recurse)."""
    return st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3)


@settings(max_examples=200, deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
        _containers,
        max_leaves=8,
    ),
    st.integers(min_value=0, max_value=2 * MAX_INT_DIGITS),
)
def test_the_json_loader_reads_any_document_or_refuses_it_by_name(doc, digits):
    """Any JSON document reads back as itself; one holding an integer literal of more than
    MAX_INT_DIGITS digits is a DataError naming the file, never a bare ValueError."""
    import json

    text = json.dumps(doc)
    assert parse_json(text, "f.json") == doc or text.count("NaN")
    big = f"[{text}, {'7' * digits}]" if digits else text
    try:
        parse_json(big, "f.json")
    except DataError as exc:
        assert digits > MAX_INT_DIGITS and "f.json" in str(exc)
    else:
        assert digits <= MAX_INT_DIGITS


# ------------------------------------------------------------------ outputs that are inputs
@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> Path:
    """A folder with a dataset of plain .csv recordings (``ds``) and a filter tuned on it
    (``t.json``, 3 evaluations)."""
    from kftune.data import default_dataset, save_dataset

    root = tmp_path_factory.mktemp("plain")
    names = ("train-03-j-turn", "test-05-j-turn")
    save_dataset(default_dataset().subset(names), root / "ds", compress=False)
    res = run_cli("tune", "ds", "-m", "random", "-n", "3", "-q", "-o", "t.json", cwd=root)
    assert res.returncode == 0, res.stderr
    return root


def _snapshot(folder: Path) -> dict[Path, bytes]:
    """Every file below ``folder`` with its content (links read through)."""
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def work(plain, tmp_path) -> Path:
    """A copy of :func:`plain` to run a command in."""
    import shutil

    shutil.copytree(plain, tmp_path / "w")
    return tmp_path / "w"


def _refused(res, *named: str, code: int = 3) -> None:
    assert res.returncode == code, res.stderr
    assert all(n in res.stderr for n in named), res.stderr
    assert "Traceback" not in res.stderr


def test_estimate_into_the_folder_of_its_plain_csv_dataset_is_refused(work):
    """Each recording is NAME.csv, as each table of estimates would be."""
    before = _snapshot(work)
    res = run_cli("estimate", "ds", "-p", "t.json", "-o", "ds", "--no-plot", cwd=work)
    _refused(res, "--out", "train-03-j-turn.csv", "a file of the dataset ds")
    assert _snapshot(work) == before


@pytest.mark.parametrize(
    ("out", "what"),
    [
        ("s.db", "the study (--storage)"),
        ("s.db-wal", "the study (--storage)"),
        ("s.db-shm", "the study (--storage)"),
        ("s.db-journal", "the study (--storage)"),
        ("s.widen1.db", "the study (--storage)"),
        ("s.widen3.db-wal", "the study (--storage)"),
        ("ds/manifest.toml", "a file of the dataset ds"),
        ("ds/test-05-j-turn.csv", "a file of the dataset ds"),
        ("run.toml", "the configuration (--config)"),
        ("link.json", "the configuration (--config)"),  # a link to it
        ("hard.json", "the configuration (--config)"),  # a hard link to it
    ],
)
def test_tune_refuses_an_output_that_is_one_of_its_inputs(work, out, what):
    """-o onto the study (or a widening round's file or SQLite's side files), a file of the
    dataset, the configuration, also through a symbolic or hard link: exit 3 before any
    work, naming --out and the input; every file as it was, no study started."""
    (work / "run.toml").write_text("seed = 1\n")
    (work / "link.json").symlink_to("run.toml")
    os.link(work / "run.toml", work / "hard.json")
    if out.startswith("s."):  # an existing study: resumed, so it is not refused as taken
        res = run_cli("tune", "ds", "-m", "random", "-n", "2", "-q", "--storage", "s.db",
                      "-o", "first.json", cwd=work)  # fmt: skip
        assert res.returncode == 0, res.stderr
    before = _snapshot(work)
    args = ["tune", "ds", "--config", "run.toml", "-m", "random", "-n", "3", "-q"]
    res = run_cli(*args, "--storage", "s.db", "--resume", "-o", out, cwd=work)
    _refused(res, f"--out {out}", what)
    assert _snapshot(work) == before


def test_tune_refuses_a_study_that_is_its_configuration(work):
    (work / "run.toml").write_text("seed = 1\n")
    before = _snapshot(work)
    res = run_cli("tune", "ds", "--config", "run.toml", "--storage", "run.toml", "-o", "t2.json",
                  cwd=work)  # fmt: skip
    _refused(res, "--storage run.toml", "the configuration (--config)")
    assert _snapshot(work) == before


@pytest.mark.parametrize("out", ["t.json", "./t.json", "lnk.json", "hard.json"])
def test_export_refuses_to_replace_its_tuned_file(work, out):
    (work / "lnk.json").symlink_to("t.json")
    os.link(work / "t.json", work / "hard.json")
    before = _snapshot(work)
    res = run_cli("export", "t.json", "-f", "json", "-o", out, cwd=work)
    _refused(res, f"--out {Path(out)}", "the tuned-parameters file")
    assert _snapshot(work) == before


def test_dataset_show_refuses_a_name_that_is_a_file_of_its_dataset(work):
    (work / "m.png").symlink_to("ds/manifest.toml")
    before = _snapshot(work)
    res = run_cli("dataset", "show", "ds", "-o", "m.png", cwd=work)
    _refused(res, "--out m.png", "a file of the dataset ds")
    assert _snapshot(work) == before


@pytest.mark.slow
def test_export_to_a_closed_standard_output_fails_with_a_message(work):
    """``export -o - >&-``: nothing can be written, and the command says so (exit 2)."""
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "export", "t.json", "-o", "-"],
        preexec_fn=lambda: os.close(1),
        stderr=subprocess.PIPE,
        text=True,
        cwd=work,
        timeout=300,
    )
    _refused(res, "--out -", "standard output is closed", code=2)


MAPPING = """vehicle = "bmw-320i"
[channels]
t = "t"
vx = "vx"
ax = "ax"
ay = "ay"
r = "r"
delta = "delta"
beta_ref = "beta_ref"
"""


@pytest.mark.parametrize("source", ["ds/train-03-j-turn.csv", "ds/map.toml"])
def test_import_force_refuses_to_delete_a_file_it_imports(work, source):
    """``dataset import ds/NAME.csv -o ds --force`` would delete the recording it reads
    (--force replaces the old dataset's files): exit 3 naming it, nothing changed."""
    (work / "ds" / "map.toml").write_text(MAPPING)
    recording = "ds/train-03-j-turn.csv"
    if source.endswith(".toml"):  # the mapping listed as a file of the old dataset
        manifest = work / "ds" / "manifest.toml"
        manifest.write_text(manifest.read_text().replace("test-05-j-turn.csv", "map.toml"))
        recording = "rec.csv"
        (work / recording).write_bytes((work / "ds" / "train-03-j-turn.csv").read_bytes())
    before = _snapshot(work)
    res = run_cli("dataset", "import", recording, "--mapping", "ds/map.toml",
                  "-o", "ds", "--force", cwd=work)  # fmt: skip
    _refused(res, f"--out {source}", "--force would delete it")
    assert _snapshot(work) == before


# ------------------------------------------------------------------ checked writes
def test_dataset_show_says_when_its_figure_cannot_be_written(work):
    """A name that leads to /dev/full: exit 1 naming the file, no "wrote"; the figure is
    kept in a fallback file that the message names."""
    import re

    (work / "full.png").symlink_to(DEV_FULL)
    res = run_cli("dataset", "show", "ds", "-o", "full.png", cwd=work)
    _refused(res, "cannot write --out full.png", "No space left on device", code=1)
    assert "wrote" not in res.stdout
    fallback = Path(re.search(r"written to (\S+) instead", res.stderr).group(1))
    try:
        assert fallback.suffix == ".png" and fallback.read_bytes().startswith(b"\x89PNG")
    finally:
        fallback.unlink()


@pytest.mark.parametrize("out", ["x", "x.pdf", "x.toml"])
def test_dataset_show_refuses_a_name_that_is_not_a_png(work, out):
    """It writes a PNG: a name without .png was written as x.png while it said "wrote x"."""
    before = _snapshot(work)
    res = run_cli("dataset", "show", "ds", "-o", out, cwd=work)
    _refused(res, f"--out {out}", ".png")
    assert _snapshot(work) == before


def test_dataset_show_says_the_name_it_wrote(work):
    res = run_cli("dataset", "show", "ds", "-o", "fig.PNG", cwd=work)
    assert res.returncode == 0 and res.stdout.strip() == "wrote fig.PNG", res.stderr
    assert (work / "fig.PNG").read_bytes().startswith(b"\x89PNG")


def test_a_figure_that_cannot_be_written_raises():
    """matplotlib's own writing ignores a failed write (savefig to the full device succeeds)."""
    import matplotlib.pyplot as plt

    from kftune.report import plots

    fig = plt.figure()
    with pytest.raises(OSError):
        plots.save(fig, DEV_FULL)


# ------------------------------------------------------------------ compare --force
@pytest.fixture(scope="module")
def compared(plain, tmp_path_factory) -> Path:
    """A compare folder (manual and 2 random evaluations) with its studies."""
    import shutil

    root = tmp_path_factory.mktemp("compared")
    shutil.copytree(plain / "ds", root / "ds")
    res = run_cli(*COMPARE, cwd=root)
    assert res.returncode == 0, res.stderr
    return root


COMPARE = ("compare", "ds", "--methods", "manual", "random", "--budget", "random=2", "-q",
           "-o", "out")  # fmt: skip


def _foreign_sqlite(path: Path) -> None:
    import contextlib
    import sqlite3

    with contextlib.closing(sqlite3.connect(path)) as conn:
        conn.execute("CREATE TABLE meta (key TEXT, value TEXT)")
        conn.execute("INSERT INTO meta VALUES ('application', 'something else')")
        conn.commit()


def test_compare_force_deletes_only_the_studies_kftune_made(compared, tmp_path):
    import shutil

    from kftune.optim import is_study

    work = tmp_path / "w"
    shutil.copytree(compared, work)
    studies = work / "out" / "studies"
    assert is_study(studies / "random.db") and is_study(studies / "manual.db")
    (studies / "notes.txt").write_text("mine")
    (studies / "notes.db").write_bytes(b"not even SQLite")
    _foreign_sqlite(studies / "other.db")
    (studies / "other.db-wal").write_text("mine too")
    foreign = {p: p.read_bytes() for p in studies.iterdir() if "other" in p.name or
               "notes" in p.name}  # fmt: skip
    res = run_cli(*COMPARE, "--force", cwd=work)
    assert res.returncode == 0, res.stderr
    assert {p: p.read_bytes() for p in foreign} == foreign  # untouched
    assert is_study(studies / "random.db")  # a new one


def test_a_fifo_among_the_studies_is_not_a_study_and_does_not_block(tmp_path):
    """compare --force asks of every OUT/studies/*.db whether kftune made it: a FIFO there
    blocked the open for ever. In a subprocess, whose timeout is only a hang guard."""
    fifo = tmp_path / "x.db"
    os.mkfifo(fifo)
    res = subprocess.run(
        [sys.executable, "-c", "import sys; from kftune.optim import is_study; "
         "print(is_study(sys.argv[1]))", str(fifo)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0 and res.stdout.strip() == "False", res.stderr


@pytest.mark.parametrize("kind", ["text", "sqlite"])
def test_compare_force_refuses_a_foreign_file_where_a_study_goes(compared, tmp_path, kind):
    """A file named like a method's study that kftune did not make: exit 3 naming it,
    nothing deleted."""
    import shutil

    work = tmp_path / "w"
    shutil.copytree(compared, work)
    studies = work / "out" / "studies"
    (studies / "random.db").unlink()
    if kind == "text":
        (studies / "random.db").write_text("a file of the user's")
    else:
        _foreign_sqlite(studies / "random.db")
    before = _snapshot(work)
    res = run_cli(*COMPARE, "--force", cwd=work)
    _refused(res, str(Path("out", "studies", "random.db")), "not a kftune study")
    assert _snapshot(work) == before


def test_is_study_leaves_no_file_behind(compared, tmp_path):
    import shutil

    from kftune.optim import is_study

    shutil.copy(compared / "out" / "studies" / "manual.db", tmp_path / "s.db")
    _foreign_sqlite(tmp_path / "f.db")
    before = sorted(tmp_path.iterdir())
    assert is_study(tmp_path / "s.db") and not is_study(tmp_path / "f.db")
    assert not is_study(tmp_path / "missing.db") and not is_study(tmp_path)
    assert sorted(tmp_path.iterdir()) == before


# ------------------------------------------------------------------ limits of numbers
@pytest.mark.parametrize(
    ("args", "option"),
    [
        (("tune", "-n", str(10**12)), "--budget/-n"),
        (("tune", "-n", "100001"), "--budget/-n"),
        (("tune", "--batch", str(10**12)), "--batch"),
        (("tune", "--workers", "100000"), "--workers"),
        (("evaluate", "--manual", "--workers", "100000"), "--workers"),
        (("compare", "--budget", f"ga={10**12}"), "--budget"),
    ],
)
def test_numbers_beyond_the_documented_limits_are_usage_errors(tmp_path, args, option):
    """Each command line also holds a later usage error, so that a limit that is lost
    fails this test instead of starting a run that does not end."""
    later = {"tune": ("--resume",), "evaluate": ("--force",), "compare": ("--methods", "ga", "ga")}
    res = run_cli(*args, *later[args[0]], cwd=tmp_path)
    _refused(res, option, "<= ", code=2)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("text", "key"),
    [
        (f"budget = {10**12}", "budget"),
        ("workers = 100000", "workers"),
        (f"batch = {10**12}", "batch"),
        (f"budgets = {{ ga = {10**12} }}", "[budgets]"),
    ],
)
def test_numbers_beyond_the_limits_in_a_configuration_are_refused(tmp_path, text, key):
    (tmp_path / "run.toml").write_text(text + "\n")
    # --resume without --storage: a later error, should the limit be lost (see above)
    res = run_cli("tune", "--config", "run.toml", "--resume", "-o", "t.json", cwd=tmp_path)
    _refused(res, "run.toml", key, "<= ")
    assert [p.name for p in tmp_path.iterdir()] == ["run.toml"]


def test_the_limits_are_in_the_help():
    from kftune.cli._common import MAX_BUDGET, MAX_WORKERS

    text = " ".join(run_cli("tune", "--help").stdout.split())
    assert f"at most {MAX_BUDGET}" in text and f"at most {MAX_WORKERS}" in text


# ------------------------------------------------------------------ closed standard error
@pytest.mark.parametrize("stderr", ["closed", str(DEV_FULL)])
@pytest.mark.slow
def test_tune_with_standard_error_closed_runs_to_the_end(work, stderr):
    """``tune 2>&-`` or ``2>/dev/full``: the progress bar and messages have nowhere to go;
    the run must not fail on them (it exited 1 with no message, leaving an empty study or,
    with a full standard error, none)."""
    import contextlib
    import sqlite3

    if stderr != "closed" and not os.path.exists(stderr):
        pytest.skip(f"no {stderr} on this system")

    def redirect() -> None:
        if stderr == "closed":
            os.close(2)
        else:
            os.dup2(os.open(stderr, os.O_WRONLY), 2)

    res = subprocess.run(
        [sys.executable, "-m", "kftune", "tune", "ds", "-m", "random", "-n", "3",
         "--storage", "s.db", "-o", "t2.json"],
        preexec_fn=redirect,
        stdout=subprocess.PIPE,
        text=True,
        cwd=work,
        timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout
    assert "tuned parameters written to t2.json" in res.stdout
    assert (work / "t2.json").is_file()
    with contextlib.closing(sqlite3.connect(work / "s.db")) as conn:
        assert conn.execute("SELECT COUNT(*) FROM trials").fetchone()[0] == 3


# ------------------------------------------------------------------ C header
def _header_doc(plain: Path) -> dict:
    import json

    from kftune.cli.evaluate import read_tuned
    from kftune.report.export import export_document

    doc = export_document(read_tuned(plain / "t.json"), "t.json")
    return json.loads(json.dumps(doc))


@pytest.mark.parametrize(
    ("key", "names", "pair", "macro"),
    [
        ("states", ["vx", "VX", "r"], ("vx", "VX"), "KFTUNE_STATE_VX"),
        ("measurements", ["vx", "a-y", "a_y"], ("a-y", "a_y"), "KFTUNE_MEASUREMENT_A_Y"),
    ],
)
def test_c_header_refuses_names_that_become_one_macro(plain, key, names, pair, macro):
    from kftune.report.export import to_c_header

    doc = _header_doc(plain)
    doc[key] = names
    with pytest.raises(DataError, match=macro) as info:
        to_c_header(doc, "t.json")
    message = str(info.value)
    assert "t.json" in message and all(repr(n) in message for n in pair)


def _cc() -> str:
    import shutil

    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    return cc


@pytest.mark.parametrize(
    "body",
    [
        "int main(void) { return 0; }",  # uses nothing
        "int main(void) { return KFTUNE_R_DIAG[1] > 0.0 ? 0 : 1; }",  # one array of three
        "static const double q[KFTUNE_N_STATES] = KFTUNE_Q_DIAG_INIT;\n"
        "int main(void) { return q[2] == KFTUNE_Q_DIAG[2] ? 0 : 1; }",
    ],
)
def test_c_header_compiles_without_warnings_however_little_is_used(plain, tmp_path, body):
    """Even with -Wunused-const-variable=2, which warns about unused static const arrays
    defined in headers too."""
    from kftune.report.export import to_c_header

    cc = _cc()
    (tmp_path / "filter.h").write_text(to_c_header(_header_doc(plain), "t.json"))
    (tmp_path / "main.c").write_text(f'#include "filter.h"\n{body}\n')
    res = subprocess.run(
        [cc, "-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror",
         "-Wunused-const-variable=2", "main.c", "-o", "main"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )  # fmt: skip
    if res.returncode != 0 and "unrecognized command-line option" in res.stderr:
        pytest.skip("the compiler has no -Wunused-const-variable=2")
    assert res.returncode == 0, res.stderr
    assert subprocess.run([str(tmp_path / "main")]).returncode == 0


def test_export_of_a_header_whose_names_collide_writes_nothing(work):
    """The CLI's side: exit 3 naming the tuned file and the macro; no header written."""
    import json

    doc = json.loads((work / "t.json").read_text())
    dep = doc["deployment"]
    dep["states"][1]["name"] = "VX"
    next(q for q in dep["Q"] if q["name"] == "vy")["name"] = "VX"
    (work / "tc.json").write_text(json.dumps(doc))
    before = _snapshot(work)
    res = run_cli("export", "tc.json", "-f", "c", "-o", "tc", cwd=work)
    _refused(res, "tc.json", "KFTUNE_STATE_VX", "'vx'", "'VX'")
    assert _snapshot(work) == before
