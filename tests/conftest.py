"""Shared test fixtures.

The real recording lives outside the repository, in ``../shared/data`` next to the checkout
(override with the environment variable ``KFTUNE_SHARED_DATA``). Tests that need it use the
``shared_data`` fixture and skip cleanly when it is absent.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import signal
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config: pytest.Config) -> None:
    """The filter kernels the suite compiles are cached in a folder of its own
    (:mod:`kftune.filters._compiled`), shared with the kftune processes the tests start and
    removed at the end, not in the user's cache (a KFTUNE_CACHE_DIR given is kept)."""
    if "KFTUNE_CACHE_DIR" not in os.environ:
        folder = tempfile.mkdtemp(prefix="kftune-test-kernels-")
        os.environ["KFTUNE_CACHE_DIR"] = folder
        config.add_cleanup(lambda: shutil.rmtree(folder, ignore_errors=True))


def shared_data_dir() -> Path:
    """Where ``../shared/data`` is expected (it may not exist)."""
    env = os.environ.get("KFTUNE_SHARED_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"shared data folder not present ({path.name} beside the repository)")
    return path


@pytest.fixture
def revs_dir(shared_data: Path) -> Path:
    """The real race-car recording; skips when absent."""
    path = shared_data / "revs-250lm"
    if not (path / "t.txt").is_file():
        pytest.skip("revs-250lm recording not present")
    return path


#: A small dataset for command-line tests: two training and two test manoeuvres.
SMALL_TRAIN = ("train-03-j-turn", "train-07-lane-change")
SMALL_TEST = ("test-05-j-turn", "test-14-lane-change")


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """Two training and two test manoeuvres of the bundled set, as a dataset directory."""
    from kftune.data import default_dataset, save_dataset

    out = tmp_path_factory.mktemp("small")
    save_dataset(default_dataset().subset(SMALL_TRAIN + SMALL_TEST), out)
    return out


def default_sigint() -> None:
    """``preexec_fn`` for a child that the test interrupts with SIGINT: a shell that starts
    the suite in the background without job control makes it ignore SIGINT, and children
    inherit that (Python then installs no KeyboardInterrupt handler); restore the default."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@dataclass(frozen=True)
class Ran:
    """What a command returned: as :class:`subprocess.CompletedProcess`'s fields."""

    returncode: int
    stdout: str
    stderr: str


def run_cli(*args: str, cwd: Path | None = None) -> Ran:
    """``kftune ARGS`` in this process (``kftune.cli.main``), capturing its output.

    A subprocess would re-import kftune and reload every compiled kernel for each command
    (seconds each); tests of process behaviour (signals, closed streams, SIGKILL and
    resume) start real processes instead.
    """
    from kftune.cli import main

    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    handler = signal.getsignal(signal.SIGINT)
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(a) for a in args])
            except SystemExit as exc:  # argparse: --help (0) and usage errors (2)
                code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    finally:
        os.chdir(here)
        signal.signal(signal.SIGINT, handler)
    return Ran(int(code), out.getvalue(), err.getvalue())


#: The device that refuses every write with ENOSPC, and the one that reads endless zeros
#: (Linux, FreeBSD): named once, as devices, not as paths of a machine.
DEV_FULL = Path("/dev", "full")
DEV_ZERO = Path("/dev", "zero")

#: [s] how long a test waits for evidence (a study's first results, a process's exit) before
#: it gives up: a guard against a hang, never a measure of speed. A shared machine under load
#: (load average 10–19 on 2 cores) stretches a command of 5 s beyond a minute.
HANG_GUARD = 600.0


def bundled_without(out: Path, dropped: set[str], n: int, name: str = "mine") -> tuple:
    """Two training and one test manoeuvre of the bundled set, their first ``n`` samples,
    written to ``out`` as a dataset without the channels ``dropped`` (e.g. ``beta_ref``: a
    recording without a reference sensor). Returns (the bundled set, the picked slices)."""
    from kftune.data import Dataset, Manoeuvre, default_dataset, save_dataset

    ds = default_dataset()
    picked = [ds.train[0].slice(0, n), ds.train[3].slice(0, n), ds.test[9].slice(0, n)]
    ms = [
        Manoeuvre(
            m.name,
            m.kind,
            m.split,
            m.t,
            channels={k: v for k, v in m.channels.items() if k not in dropped},
        )
        for m in picked
    ]
    save_dataset(Dataset(name, ds.vehicle, ds.dt, ms), out)
    return ds, picked


def completed_trials(db: Path) -> int:
    """The finished evaluations in the study ``db`` (SQLite, read-only: a running tune may
    hold it), 0 while it does not exist or cannot be read yet."""
    import sqlite3

    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1) as conn:
            return conn.execute("SELECT COUNT(*) FROM trials WHERE state='complete'").fetchone()[0]
    except sqlite3.Error:
        return 0


#: Runs ``kftune ARGS`` with a hook that SIGKILLs the process itself right after the study
#: DB has stored its n-th finished evaluation: a kill at a known point, whatever the load
#: (a parent polling the DB could see the run, or a short stage, finish first).
_KILL_AFTER = """
import os, signal, sqlite3, sys
from pathlib import Path
from kftune.cli import main
from kftune.optim.study import Study
db, n = Path(sys.argv[1]).resolve(), int(sys.argv[2])
write = Study.write_result
def write_then_die(self, record):
    write(self, record)
    if Path(self.path).resolve() == db:
        with sqlite3.connect(db) as conn:
            done = conn.execute("SELECT COUNT(*) FROM trials WHERE state='complete'").fetchone()[0]
        if done >= n:
            os.kill(os.getpid(), signal.SIGKILL)
Study.write_result = write_then_die
sys.exit(main(sys.argv[3:]))
"""


def run_killed_after(db: Path, n: int, *args: str) -> None:
    """Run ``kftune ARGS`` in a process of its own, SIGKILLed by itself right after the
    study ``db`` stores its n-th finished evaluation (:data:`_KILL_AFTER`); fails if it
    ended any other way."""
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", _KILL_AFTER, str(db), str(n), *map(str, args)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        timeout=HANG_GUARD,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode(errors="replace")[-2000:]


def wait_until(
    ready, proc=None, what: str = "the condition", limit: float = HANG_GUARD, every: float = 0.05
) -> None:
    """Poll ``ready()`` every ``every`` seconds until it holds. Fails naming ``what`` when
    the process ``proc`` ends first, or when ``limit`` seconds pass (a hang guard, see
    :data:`HANG_GUARD`)."""
    import time

    deadline = time.monotonic() + limit
    while not ready():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"waiting for {what}: the process ended (exit {proc.returncode})")
        if time.monotonic() > deadline:
            raise AssertionError(f"waiting for {what}: not seen within {limit:g} s (a hang guard)")
        time.sleep(every)
