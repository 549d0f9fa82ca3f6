"""Faults and hostile input around runs: a study that cannot be written or is copied after a
SIGKILL, outputs that fail, killed parents and Ctrl-C with worker pools, a lock that a
deleted file cannot defeat, and a corpus of malformed files. Every case asserts the exit
code, that the message names the file, row or option, that no traceback is printed, and
that nothing finished is lost."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import HANG_GUARD, default_sigint, wait_until
from kftune.cli import main
from kftune.errors import DataError, RunFailedError
from kftune.optim import StudyError, StudyInUseError, minimize
from test_cli import _completed, kftune, kftune_process
from test_optim_study import (
    WORKER,
    _alive,
    _complete_u,
    _wait_for,
    strip_timings,
)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from optim_study_worker import SPACE, objective  # noqa: E402

LINUX = sys.platform.startswith("linux")


def run_main(capsys, *args: str) -> tuple[int, str]:
    """Run the CLI in this process: (exit code, stderr). An exception escaping ``main``
    (what a user would see as a traceback) fails the test."""
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def _children(pid: int) -> list[int]:
    """PIDs whose parent is ``pid`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    found.append(int(entry.name))
    return found


def _immutable(path: Path) -> bool:
    """Make ``path`` immutable with ``chattr +i`` (stops root too); False if impossible."""
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode == 0


@pytest.fixture
def immutable_dir(tmp_path):
    """A folder in which nobody, root included, can create a file."""
    d = tmp_path / "frozen"
    d.mkdir()
    if not _immutable(d):
        pytest.skip("chattr +i is not available here")
    yield d
    subprocess.run(["chattr", "-i", str(d)], check=True)


# ------------------------------------------------------------------ the study file
@pytest.mark.slow
def test_a_copy_of_the_study_file_alone_keeps_every_finished_evaluation(tmp_path):
    """SIGKILL at a random moment, then copy only ``s.db`` (not ``s.db-wal``): the copy
    holds every evaluation the killed run finished — all but the last when the kill fell
    between that result's commit and the end of its checkpoint (seen once in a loaded
    run) — and resumes to the uninterrupted result."""
    db, log, budget = tmp_path / "s.db", tmp_path / "log.txt", 40
    proc = subprocess.Popen(
        [sys.executable, str(WORKER), str(db), str(log), "0", "random", str(budget), "0.03"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _wait_for(lambda: len(_complete_u(db)) >= 4, proc)
    # stop reading (a reader may hold back a checkpoint), let a few evaluations pass, kill
    time.sleep(float(np.random.default_rng().uniform(0.2, 0.4)))
    proc.kill()
    proc.wait()
    copy = tmp_path / "copy" / "s.db"
    copy.parent.mkdir()
    shutil.copyfile(db, copy)  # before anything opens the original and replays its WAL
    query = "SELECT number, state, value, record FROM trials WHERE state != 'running'"
    with contextlib.closing(sqlite3.connect(copy)) as conn:
        in_copy = conn.execute(query + " ORDER BY number").fetchall()
    with contextlib.closing(sqlite3.connect(db)) as conn:
        in_original = conn.execute(query + " ORDER BY number").fetchall()
    # at least the 4 seen (a loaded machine may starve the run through the short sleep)
    assert len(in_original) >= 4 and len(in_original) < budget, "not killed mid-run"
    assert in_copy in (in_original, in_original[:-1])
    res = minimize(objective, SPACE, "random", budget=budget, seed=5, storage=copy, resume=True)
    ref = minimize(objective, SPACE, "random", budget=budget, seed=5)
    assert strip_timings(res) == strip_timings(ref)


@pytest.mark.slow
def test_deleting_files_beside_a_study_cannot_let_a_second_run_in(tmp_path):
    """The lock is on the study itself: delete whatever lies beside it apart from SQLite's
    own files (a lock file, say) and a second run is still refused at once."""
    db, log = tmp_path / "s.db", tmp_path / "log.txt"
    proc = subprocess.Popen(
        [sys.executable, str(WORKER), str(db), str(log), "0", "random", "60", "0.05"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        _wait_for(lambda: len(_complete_u(db)) >= 2, proc)
        for p in tmp_path.iterdir():
            if p.name.startswith("s.db") and p.name not in ("s.db", "s.db-wal", "s.db-shm"):
                p.unlink()
        with pytest.raises(StudyInUseError, match=r"in use by another process"):
            minimize(objective, SPACE, "random", budget=60, seed=5, storage=db, resume=True)
    finally:
        proc.kill()
        proc.wait()
    res = minimize(objective, SPACE, "random", budget=60, seed=5, storage=db, resume=True)
    assert res.n_evals == 60 and res.status == "completed"


def _limit_file_size(limit: int):
    def set_limit() -> None:  # runs in the child; Python ignores SIGXFSZ, so writes fail
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return set_limit


@pytest.mark.slow
def test_a_study_that_cannot_grow_fails_cleanly_keeps_everything_and_resumes(small, tmp_path):
    """A file-size limit (as a full disk) stops the study mid-run: exit 1, a message naming
    the study, what it keeps and how to resume; no traceback; resuming without the limit
    keeps every stored evaluation and finishes."""
    db = tmp_path / "s.db"
    args = ["tune", str(small), "-m", "random", "-n", "80", "-q", "--storage", str(db),
            "-o", str(tmp_path / "t.json")]  # fmt: skip
    res = subprocess.run(
        [sys.executable, "-m", "kftune", *args],
        preexec_fn=_limit_file_size(40_000),  # above the 32 KiB of s.db-shm
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr and str(db) in res.stderr and "--resume" in res.stderr
    assert "resume=True" not in res.stderr  # the command's option, not the library's argument
    with contextlib.closing(sqlite3.connect(db)) as conn:
        kept = conn.execute("SELECT number, value FROM trials WHERE state = 'complete'").fetchall()
    said = re.search(r"keeps the (\d+) evaluations finished so far", res.stderr)
    assert said and int(said.group(1)) == len(kept), res.stderr
    assert 3 <= len(kept) < 80
    resumed = kftune(*args, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    with contextlib.closing(sqlite3.connect(db)) as conn:
        after = dict(conn.execute("SELECT number, value FROM trials WHERE state = 'complete'"))
    assert len(after) == 80 and all(after[n] == v for n, v in kept)


#: Linux's process file system: a folder that takes no new file, even for root.
PROC = Path(os.sep, "proc")


@pytest.mark.skipif(not (PROC / "self").is_dir(), reason="needs /proc")
def test_a_study_or_output_where_no_file_can_be_made_is_refused_before_any_work(tmp_path, capsys):
    """As root, permission bits stop nothing: /proc is a folder that takes no new file,
    whatever os.access says; refused with exit 3 naming the option."""
    for option, path in [("--storage", PROC / "kftune-study.db"), ("--out", PROC / "t.json")]:
        code, err = run_main(
            capsys, "tune", "-q", "-n", "1000", "-o", tmp_path / "t.json", option, path
        )
        assert code == 3 and option in err and "no file can be created" in err, err


def test_a_read_only_folder_is_refused_before_any_work(immutable_dir, tmp_path, capsys):
    for option in ("--storage", "--out"):
        other = ("-o", tmp_path / "t.json") if option == "--storage" else ()
        code, err = run_main(
            capsys, "tune", "-q", "-n", "1000", *other, option, immutable_dir / "f"
        )
        assert code == 3 and option in err and str(immutable_dir) in err, err
    code, err = run_main(capsys, "compare", "-q", "--out", immutable_dir / "report")
    assert code == 3 and "--out" in err


# ------------------------------------------------------------------ outputs
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.slow
def test_an_output_that_is_a_pipe_or_a_dangling_link_is_refused_at_once(tmp_path):
    """Checked before the work: a FIFO (writing it would block forever) and a link into a
    missing folder give exit 3 naming --out, within seconds."""
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    dangling = tmp_path / "link.json"
    dangling.symlink_to(tmp_path / "gone" / "t.json")
    for out, expected in [(fifo, "not a regular file"), (dangling, "does not exist")]:
        res = kftune_process("tune", "-q", "-n", "1000", "-o", str(out), timeout=HANG_GUARD)
        assert res.returncode == 3, res.stderr
        assert "--out" in res.stderr and expected in res.stderr and "Traceback" not in res.stderr


def test_an_immutable_output_file_is_refused_at_once(tmp_path, capsys):
    """``tune -o`` naming a file that cannot be replaced, and a report folder whose
    results.json cannot be: exit 3 naming --out, before any work."""
    out = tmp_path / "t.json"
    out.write_text("{}")
    report = tmp_path / "report"
    report.mkdir()
    (report / "results.json").write_text("{}")
    try:
        if not (_immutable(out) and _immutable(report / "results.json")):
            pytest.skip("chattr +i is not available here")
        code, err = run_main(capsys, "tune", "-q", "-n", "1000", "-o", out)
        assert code == 3 and "--out" in err and "cannot be written" in err
        code, err = run_main(capsys, "compare", "-q", "--out", report)
        assert code == 3 and "results.json" in err and "cannot be written" in err
    finally:
        if shutil.which("chattr"):
            subprocess.run(["chattr", "-i", str(out), str(report / "results.json")], check=False)


def test_an_output_that_fails_at_the_end_is_kept_in_a_fallback_file(tmp_path):
    """The folder vanishes between the check and the write: the text goes to a fallback
    file that the error names; nothing is left half-written."""
    from kftune.cli.outputs import output_file, write_output

    out = tmp_path / "gone" / "t.json"
    out.parent.mkdir()
    output_file(out, "--out")
    out.parent.rmdir()
    text = json.dumps({"format": "kftune-tuned-1", "cost": 0.5})
    with pytest.raises(RunFailedError, match=r"cannot write --out .*t\.json") as info:
        write_output(out, text, "--out", "every evaluation is saved in the study s.db")
    message = str(info.value)
    assert "every evaluation is saved in the study s.db" in message
    fallback = Path(re.search(r"it was written to (\S+) instead", message).group(1))
    try:
        assert fallback.read_text() == text
    finally:
        fallback.unlink()


@pytest.mark.slow
def test_tune_whose_output_cannot_be_written_at_the_end_prints_the_result(small, tmp_path):
    """A file-size limit below the tuned file's size and no study: exit 1, no traceback,
    and the tuned parameters are in the message, since no file could hold them."""
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "tune", str(small), "-m", "random", "-n", "2", "-q",
         "-o", str(tmp_path / "t.json")],
        preexec_fn=_limit_file_size(300),
        env={**os.environ, "TMPDIR": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=300,
    )  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr and "cannot write --out" in res.stderr
    doc = json.loads(res.stderr.split("here it is:\n", 1)[1])
    assert doc["format"] == "kftune-tuned-1" and doc["n_evals"] == 2
    assert not (tmp_path / "t.json").exists()
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_a_report_that_cannot_be_written_keeps_the_studies_and_resume_writes_it(
    small, tmp_path, capsys, monkeypatch
):
    """compare whose report cannot be written (a full disk, simulated where the report is
    written): exit 1 naming the report folder, the studies and --resume; resuming writes
    the report from the stored evaluations, evaluating nothing again."""
    import errno

    import kftune.report

    out = tmp_path / "rep"
    args = ["compare", small, "--methods", "manual", "-q", "--out", out]
    real_write_report = kftune.report.write_report

    def disk_full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(kftune.report, "write_report", disk_full)
    code, err = run_main(capsys, *args)
    assert code == 1 and "cannot write the report" in err and "No space left" in err
    assert str(out / "studies") in err and "--resume" in err
    study = out / "studies" / "manual.db"
    with contextlib.closing(sqlite3.connect(study)) as conn:
        before = conn.execute("SELECT number, value FROM trials ORDER BY number").fetchall()
    assert len(before) == 1
    monkeypatch.setattr(kftune.report, "write_report", real_write_report)
    code, err = run_main(capsys, *args, "--resume")
    assert code == 0, err
    assert (out / "report.md").is_file()
    with contextlib.closing(sqlite3.connect(study)) as conn:
        after = conn.execute("SELECT number, value FROM trials ORDER BY number").fetchall()
    assert after == before


@pytest.mark.slow
def test_closed_standard_output(tmp_path):
    """``kftune tune --json >&-``: exit 2 at once, naming --json; without --json the run
    goes on and writes its file."""

    def close_stdout() -> None:
        os.close(1)

    res = subprocess.run(
        [sys.executable, "-m", "kftune", "tune", "--json", "-q", "-o", str(tmp_path / "t.json")],
        preexec_fn=close_stdout,
        stderr=subprocess.PIPE,
        text=True,
        timeout=HANG_GUARD,
    )
    assert (
        res.returncode == 2
        and "--json" in res.stderr
        and "standard output is closed" in (res.stderr)
    )
    assert "Traceback" not in res.stderr
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "evaluate", "--manual", "--split", "train"],
        preexec_fn=close_stdout,
        stderr=subprocess.PIPE,
        text=True,
        timeout=HANG_GUARD,
    )
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr


# ------------------------------------------------------------------ worker processes
@pytest.mark.skipif(not LINUX, reason="reads the process tree from /proc")
@pytest.mark.slow
def test_killing_the_parent_of_a_workers_run_takes_its_workers_along(small, tmp_path):
    """SIGKILL of ``kftune tune --workers 2``: its two pool workers (and the resource
    tracker) exit within seconds instead of living on."""
    db = tmp_path / "s.db"
    proc = subprocess.Popen(
        [sys.executable, "-m", "kftune", "tune", str(small), "-m", "ga", "-n", "5000", "-q",
         "--workers", "2", "--storage", str(db), "-o", str(tmp_path / "t.json")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    wait_until(lambda: _completed(db) >= 2, proc, "2 finished evaluations in the study")
    kids = _children(proc.pid)
    proc.kill()
    proc.wait()
    assert len(kids) >= 2, "the pool's workers were not running"
    deadline = time.monotonic() + 120  # a hang guard: load stretches the workers' notice
    while any(_alive(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [k for k in kids if _alive(k)]
    for k in left:
        os.kill(k, signal.SIGKILL)
    assert not left, "pool workers outlived their killed parent"


def _ctrl_c(args: list[str], ready) -> subprocess.CompletedProcess:
    """Start ``kftune ARGS`` in its own process group, wait for ``ready()``, then send
    SIGINT to the whole group, as a terminal's Ctrl-C does."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "kftune", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=default_sigint,
    )
    try:
        wait_until(ready, proc, "the moment to interrupt it")
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=HANG_GUARD)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.slow
def test_ctrl_c_with_workers_prints_no_worker_traceback(small, tmp_path):
    db = tmp_path / "s.db"
    res = _ctrl_c(
        ["tune", str(small), "-m", "ga", "-n", "5000", "-q", "--workers", "2",
         "--storage", str(db), "-o", str(tmp_path / "t.json")],
        ready=lambda: _completed(db) >= 3,
    )  # fmt: skip
    assert res.returncode == 130, res.stderr
    assert "Traceback" not in res.stderr and "KeyboardInterrupt" not in res.stderr, res.stderr
    assert "--resume" in res.stderr and str(db) in res.stderr


@pytest.mark.slow
def test_ctrl_c_in_compare_says_how_to_resume(small, tmp_path):
    out = tmp_path / "rep"
    db = out / "studies" / "ga.db"
    res = _ctrl_c(
        ["compare", str(small), "--methods", "ga", "--budget", "ga=5000", "-q", "--out", str(out)],
        ready=lambda: _completed(db) >= 3,
    )
    assert res.returncode == 130, res.stderr
    assert "Traceback" not in res.stderr
    assert "during ga after" in res.stderr and "--resume" in res.stderr
    assert str(out / "studies") in res.stderr
    stopped_at = int(re.search(r"after (\d+) evaluations", res.stderr).group(1))
    assert _completed(db) >= stopped_at >= 3  # every finished evaluation is in the study


# ------------------------------------------------------------------ malformed input
DEEP_TOML = "a = " + "[" * 100_000 + "]" * 100_000 + "\n"
DEEP_JSON = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("timeout = inf", "key 'timeout': expected a number > 0 and <= 1e+06 [s]"),
        ("timeout = nan", "key 'timeout': expected a number"),
        ("timeout = 1e7", "key 'timeout': expected a number > 0 and <= 1e+06 [s]"),
        ("burn_in = inf", "key 'burn_in': expected a number >= 0 [s]"),
        (DEEP_TOML, "nests arrays or tables too deeply"),
    ],
)
def test_bad_numbers_and_deep_nesting_in_a_configuration(tmp_path, capsys, text, expected):
    cfg = tmp_path / "run.toml"
    cfg.write_text(text + "\n")
    code, err = run_main(capsys, "tune", "--config", cfg, "-q", "-o", tmp_path / "t.json")
    assert code == 3 and expected in err and str(cfg) in err, err


@pytest.mark.parametrize("value", ["1e300", "inf", "2e6"])
def test_a_timeout_beyond_the_limit_is_a_usage_error(capsys, value):
    with pytest.raises(SystemExit) as info:
        main(["tune", "--timeout", value])
    assert info.value.code == 2 and "--timeout" in capsys.readouterr().err


def test_the_nis_cost_refuses_weights(tmp_path, capsys):
    code, err = run_main(capsys, "evaluate", "--manual", "--cost", "nis", "--weights", "beta=1")
    assert code == 2 and "--weights" in err and "nis" in err
    cfg = tmp_path / "c.toml"
    cfg.write_text("[cost]\nweights = { beta = 2.0 }\n")
    code, err = run_main(capsys, "evaluate", "--manual", "--cost", "nis", "--config", cfg)
    assert code == 3 and str(cfg) in err and "[cost]" in err and "weights" in err


@pytest.fixture(scope="module")
def tuned_doc(tmp_path_factory) -> dict:
    """A real tuned-parameters file's content (3 evaluations on the bundled set)."""
    out = tmp_path_factory.mktemp("tuned") / "t.json"
    assert main(["tune", "-m", "random", "-n", "3", "-q", "-o", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"burn_in": "abc"}, "'burn_in'"),
        ({"burn_in": -1.0}, "'burn_in'"),
        ({"burn_in": math.inf}, "'burn_in'"),
        ({"burn_in": True}, "'burn_in'"),
        ({"params": {"r_scale": 0.0}}, "'params.r_scale'"),
        ({"params": {"r_scale": -2.0}}, "'params.r_scale'"),
        ({"params": {"r_scale": math.nan}}, "'params.r_scale'"),
        ({"params": {"r_scale": True}}, "'params.r_scale'"),
        ({"params": {"r_scale": "x"}}, "'params.r_scale'"),
        ({"params": {"r_scale": 10**400}}, "'params.r_scale'"),  # no float holds it
        ({"burn_in": 10**400}, "'burn_in'"),
    ],
)
def test_a_tuned_file_with_bad_values_is_refused(tuned_doc, tmp_path, capsys, change, key):
    doc = {**tuned_doc, **change}
    if "params" in change:
        doc["params"] = {**tuned_doc["params"], **change["params"]}
    f = tmp_path / "bad-tuned.json"
    f.write_text(json.dumps(doc))  # NaN/inf as JSON's NaN/Infinity, as a user might
    code, err = run_main(capsys, "evaluate", "--params", f, "--split", "train")
    assert code == 3 and str(f) in err and key in err, err


def test_a_deeply_nested_tuned_file_or_manifest_is_refused(tmp_path, capsys):
    f = tmp_path / "deep.json"
    f.write_text(DEEP_JSON)
    code, err = run_main(capsys, "evaluate", "--params", f)
    assert code == 3 and str(f) in err and "too deeply" in err
    for name, text in [("manifest.json", DEEP_JSON), ("manifest.toml", DEEP_TOML)]:
        ds = tmp_path / name.replace(".", "-")
        ds.mkdir()
        (ds / name).write_text(text)
        code, err = run_main(capsys, "dataset", "info", ds)
        assert code == 3 and name in err and "too deeply" in err, err


@pytest.fixture(scope="module")
def results_dir(tmp_path_factory) -> Path:
    """A real compare results directory (manual and 3 random evaluations on 2 manoeuvres)."""
    from kftune.data import default_dataset
    from kftune.experiment import CompareSettings, run_compare

    ds = default_dataset().subset(("train-03-j-turn", "test-05-j-turn"))
    out = tmp_path_factory.mktemp("results")
    run_compare(
        ds, out, CompareSettings(methods=("manual", "random"), budgets={"random": 3}),
        progress=False,
    )  # fmt: skip
    return out


@pytest.mark.parametrize(
    ("results", "expected"),
    [
        ([], "got a list"),
        ({}, "schema"),
        ({"schema": 1, "meta": {}}, "'methods'"),
        ({"schema": 1, "meta": {}, "methods": [1]}, "methods[0]"),
        ({"schema": 1, "meta": {}, "methods": [{"key": "ga"}]}, "methods[0]"),
        ("deep", "too deeply"),
    ],
)
def test_a_malformed_results_file_is_refused(results_dir, tmp_path, capsys, results, expected):
    d = tmp_path / "r"
    d.mkdir()
    text = DEEP_JSON if results == "deep" else json.dumps(results)
    (d / "results.json").write_text(text)
    code, err = run_main(capsys, "report", d)
    assert code == 3 and "results.json" in err and expected in err, err


@pytest.mark.parametrize("damage", ["truncated", "foreign key", "text"])
def test_a_damaged_traces_file_is_refused(results_dir, tmp_path, capsys, damage):
    d = tmp_path / "r"
    shutil.copytree(results_dir, d)
    traces = d / "traces.npz"
    if damage == "truncated":
        traces.write_bytes(traces.read_bytes()[:300])
    elif damage == "foreign key":
        np.savez(traces, nokey=np.zeros(3))
    else:
        traces.write_text("not an archive")
    code, err = run_main(capsys, "report", d, "--out", tmp_path / "out")
    assert code == 3 and "traces.npz" in err, err
    assert not (tmp_path / "out" / "report.md").exists()


@pytest.fixture(scope="module")
def study_command(small, tmp_path_factory) -> tuple[Path, list[str]]:
    """A study written by ``kftune tune`` (4 evaluations) and the command that resumes it."""
    d = tmp_path_factory.mktemp("study")
    db = d / "s.db"
    args = ["tune", str(small), "-m", "random", "-n", "4", "-q", "-o", str(d / "t.json"),
            "--storage", str(db)]  # fmt: skip
    assert main(args) == 0
    return db, [*args, "--resume"]


@pytest.mark.parametrize(
    ("sql", "trial"),
    [
        ("UPDATE trials SET record = '{bad' WHERE number = 1", "trial 1"),
        ("UPDATE trials SET record = '{\"number\": 2}' WHERE number = 2", "trial 2"),
        ("UPDATE trials SET record = '[1, 2]' WHERE number = 0", "trial 0"),
        ("UPDATE trials SET record = NULL WHERE number = 3", "trial 3"),
        ("UPDATE trials SET state = 'running', u = '[' WHERE number = 3", "trial 3"),
        ("UPDATE trials SET state = 'sleeping' WHERE number = 2", "trial 2"),
        ("UPDATE meta SET value = '{bad' WHERE key = 'settings'", "settings"),
    ],
)
def test_a_damaged_study_row_is_refused_naming_it(study_command, tmp_path, capsys, sql, trial):
    original, args = study_command
    db = tmp_path / "s.db"
    shutil.copyfile(original, db)
    with contextlib.closing(sqlite3.connect(db)) as conn, conn:
        conn.execute(sql)
    args = [str(db) if a == str(original) else a for a in args]
    code, err = run_main(capsys, *args)
    assert code == 3 and str(db) in err and trial in err, err
    assert "{bad" not in err  # the row's content is not quoted


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)
# Documents shaped like the real files, with values replaced at random.
TUNED_KEYS = st.sampled_from(["format", "q", "ukf", "params", "burn_in", "cost_spec"])
RESULT_KEYS = st.sampled_from(["schema", "meta", "methods", "cost_slice"])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(changes=st.dictionaries(TUNED_KEYS, JSON_VALUES, max_size=3), data=st.data())
@pytest.mark.slow
def test_any_tuned_document_is_read_or_refused_with_a_data_error(
    tuned_doc, tmp_path_factory, changes, data
):
    """Whatever a tuned file holds, reading it gives a usable document or a DataError
    naming the file — never another exception."""
    from kftune.cli.evaluate import read_tuned

    doc = {**tuned_doc, **changes}
    if data.draw(st.booleans()):
        doc["params"] = {**tuned_doc["params"], "r_scale": data.draw(JSON_VALUES)}
    path = tmp_path_factory.mktemp("hyp") / "tuned.json"
    path.write_text(json.dumps(doc))
    try:
        read_tuned(path)
    except DataError as exc:
        assert str(path) in str(exc)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    changes=st.dictionaries(RESULT_KEYS, JSON_VALUES, max_size=3),
    method_changes=st.dictionaries(st.sampled_from(["best_cost", "params", "n_evals",
                                                    "history_cost", "key", "extra"]),
                                   JSON_VALUES, max_size=2),
)  # fmt: skip
def test_any_results_document_is_read_or_refused_with_a_data_error(
    results_dir, tmp_path_factory, changes, method_changes
):
    from kftune.report import ExperimentResults

    doc = json.loads((results_dir / "results.json").read_text())
    doc["methods"][0].update(method_changes)
    doc.update(changes)
    d = tmp_path_factory.mktemp("hyp")
    (d / "results.json").write_text(json.dumps(doc))
    try:
        ExperimentResults.load(d)
    except DataError as exc:
        assert "results.json" in str(exc)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(record=st.one_of(st.text(max_size=30), JSON_VALUES.map(json.dumps)))
@pytest.mark.slow
def test_any_damaged_record_is_refused_with_a_study_error(tmp_path_factory, record):
    db = tmp_path_factory.mktemp("hyp") / "s.db"
    minimize(objective, SPACE, "random", budget=2, seed=0, storage=db)
    with contextlib.closing(sqlite3.connect(db)) as conn, conn:
        conn.execute("UPDATE trials SET record = ? WHERE number = 1", (record,))
    with pytest.raises(StudyError, match=r"trial 1 \(complete\) is damaged"):
        minimize(objective, SPACE, "random", budget=2, seed=0, storage=db, resume=True)


def test_ctrl_c_after_a_commit_counts_that_evaluation(tmp_path, monkeypatch):
    """Ctrl-C that lands after a result is committed (during the checkpoint that follows):
    the partial result holds exactly what the study holds."""
    from kftune.optim.study import Study

    db = tmp_path / "s.db"
    write_result = Study.write_result

    def interrupted_after_commit(self, record):
        write_result(self, record)
        if record.number == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(Study, "write_result", interrupted_after_commit)
    with pytest.raises(KeyboardInterrupt) as info:
        minimize(objective, SPACE, "random", budget=10, seed=0, storage=db)
    with contextlib.closing(sqlite3.connect(db)) as conn:
        stored = conn.execute("SELECT COUNT(*) FROM trials WHERE state = 'complete'").fetchone()
    assert info.value.result.n_evals == stored[0] == 4


@pytest.mark.skipif(not LINUX, reason="SQLite's lock bytes of its unix file locking")
def test_a_refused_second_open_in_the_same_process_keeps_sqlites_locks(tmp_path):
    """The study lock sits on the database file, where SQLite keeps POSIX locks that any
    close of a descriptor of the file in this process would drop. A refused second open
    must not open (and close) one: the first connection's shared lock on SQLite's lock
    bytes (offset 2^30 + 2, 510 bytes) must stay, or another process could take the file
    away under it."""
    from kftune.optim.study import Study

    db = tmp_path / "s.db"
    probe = (
        "import fcntl, sys\n"
        "with open(sys.argv[1], 'r+b') as f:\n"
        "    fcntl.lockf(f, fcntl.LOCK_EX | fcntl.LOCK_NB, 510, 0x40000002)\n"
    )

    def exclusive_lock_possible() -> bool:
        res = subprocess.run([sys.executable, "-c", probe, str(db)], capture_output=True)
        return res.returncode == 0

    with Study.open(db, {"method": "random"}, resume=False) as first:
        first.write_proposal(0, [0.5])
        assert not exclusive_lock_possible()  # SQLite's shared lock is there
        with pytest.raises(StudyInUseError):
            Study.open(db, {"method": "random"}, resume=True)
        assert not exclusive_lock_possible()
