"""Batched and distributed evaluation on a real Dask LocalCluster (2 worker processes).

The cluster starts once for the module (it takes seconds on a loaded machine); every test
connects its engine to it by address, which is also how ``kftune tune --scheduler`` works.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shlex
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import threading
import time
import types
from collections.abc import Iterator

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import cloudpickle  # noqa: E402  (a dependency of distributed)

from conftest import HANG_GUARD, default_sigint, wait_until  # noqa: E402
from kftune.data import default_dataset  # noqa: E402
from kftune.errors import ConfigError  # noqa: E402
from kftune.experiment import tune  # noqa: E402
from kftune.optim import Execution, minimize  # noqa: E402
from kftune.optim.dask_engine import DaskEngine, SchedulerLostError  # noqa: E402
from kftune.optim.result import COMPLETE, FAILED  # noqa: E402
from kftune.tuning.problem import TuningProblem  # noqa: E402

# The objectives below live in this test module, which the workers cannot import: send them
# by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def cluster():
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        lc = distributed.LocalCluster(
            n_workers=2,
            processes=True,
            threads_per_worker=1,
            dashboard_address=None,
            silence_logs=50,
        )
    yield lc
    lc.close()


@pytest.fixture(scope="module")
def problem():
    ds = default_dataset()
    return TuningProblem(ds.train, ds.vehicle, ds.r_default)


def _held(go, x):
    """An objective that waits until the file ``go`` exists (HANG_GUARD at most): an
    evaluation is in flight for as long as the test needs it to be, however loaded the
    machine."""
    deadline = time.monotonic() + HANG_GUARD
    while not os.path.exists(go) and time.monotonic() < deadline:
        time.sleep(0.01)
    return float(np.sum((np.asarray(x) - 0.3) ** 2))


def _dies_above_half(x):
    if x[0] > 0.5:
        os._exit(1)
    return float(np.sum(np.asarray(x) ** 2))


def _same(a, b):
    assert [r.number for r in a.history] == [r.number for r in b.history]
    assert [r.u for r in a.history] == [r.u for r in b.history]
    assert [r.value for r in a.history] == [r.value for r in b.history]
    assert [r.state for r in a.history] == [r.state for r in b.history]


@pytest.mark.slow
def test_results_equal_the_sequential_run_bit_for_bit(cluster, problem):
    rng = np.random.default_rng(7)
    X = [problem.space.from_unit(rng.random(problem.space.dim)) for _ in range(3)]
    expected = [problem.evaluate(x).cost for x in X]
    with DaskEngine(problem, scheduler=cluster.scheduler_address) as engine:
        assert engine.workers == 2
        by_point = dict(engine.run(X))  # 3 points >= 2 workers: one task per point
        assert [by_point[i][0] for i in range(3)] == expected
        [(_, one)] = list(engine.run(X[:1]))  # 1 point < 2 workers: split by manoeuvre
        assert one[0] == expected[0] and one[1] is None
        # a whole run: q = 2 on the cluster proposes and scores exactly what q = 2 in
        # process does, and q = 1 exactly what the sequential loop does
        on_dask = minimize(
            problem,
            problem.space,
            "trbo",
            budget=4,
            execution=Execution(batch=2, engine=engine),
            n_init=2,
        )
        _same(
            on_dask,
            minimize(
                problem, problem.space, "trbo", budget=4, execution=Execution(batch=2), n_init=2
            ),
        )
        one_by_one = minimize(
            problem, problem.space, "trbo", budget=3, execution=Execution(batch=1, engine=engine)
        )
        _same(one_by_one, minimize(problem, problem.space, "trbo", budget=3))


@pytest.mark.slow
def test_a_worker_killed_mid_evaluation_loses_nothing(cluster, tmp_path):
    """SIGKILL of a worker holding an evaluation: it is sent again and the run ends as the
    sequential one does. The evaluations wait for the kill (they used to sleep 0.4 s, and a
    loaded machine could let the whole run pass before the killer saw a busy worker)."""
    space = [(0.0, 1.0), (0.0, 1.0)]
    go = tmp_path / "go"
    fun = functools.partial(_held, str(go))
    killed: list[int] = []
    errors: list[BaseException] = []
    with DaskEngine(fun, scheduler=cluster.scheduler_address) as engine:
        pids = engine.worker_pids()

        def busy() -> list[str]:
            return [a for a, keys in engine.client.processing().items() if keys and a in pids]

        def killer() -> None:  # SIGKILL the first worker seen holding an evaluation
            try:
                wait_until(lambda: busy(), what="a worker holding an evaluation")
                pid = pids[busy()[0]]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            except BaseException as exc:
                errors.append(exc)
            finally:
                go.touch()  # the evaluations go on, the re-sent one included

        thread = threading.Thread(target=killer, daemon=True)
        thread.start()
        result = minimize(
            fun, space, "random", budget=4, execution=Execution(batch=2, engine=engine)
        )
        thread.join(HANG_GUARD)
    assert not errors and killed, errors
    assert result.n_failed == 0 and result.n_evals == 4
    _same(result, minimize(fun, space, "random", budget=4, execution=Execution(batch=2)))


@pytest.mark.slow
def test_a_run_killed_during_a_batch_resumes_exactly(cluster, problem, tmp_path):
    db = tmp_path / "study.db"
    config = tmp_path / "tune.toml"  # a short initial design: the batches after it are the
    config.write_text("[options.trbo]\nn_init = 2\n")  # model's (Kriging believer)
    cmd = [sys.executable, "-m", "kftune", "tune", "--scheduler", cluster.scheduler_address]
    cmd += ["--batch", "2", "-n", "6", "--storage", str(db), "-o", str(tmp_path / "t.json")]
    cmd += ["--config", str(config), "--cost", "nrmse"]  # the problem's: the paper's, Q alone
    proc = subprocess.Popen([*cmd, "-q"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    states: list[str] = []

    def batch_in_flight() -> bool:
        try:
            with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as conn:
                states[:] = [s for (s,) in conn.execute("SELECT state FROM trials")]
        except sqlite3.Error:
            states.clear()
        return states.count(COMPLETE) >= 2 and "running" in states

    try:
        wait_until(batch_in_flight, proc, "a batch in flight after 2 results", every=0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    assert "running" in states and len(states) < 6
    with sqlite3.connect(db) as conn:
        before = {
            n: v
            for n, s, v in conn.execute("SELECT number, state, value FROM trials")
            if s in (COMPLETE, FAILED)
        }
    with DaskEngine(problem, scheduler=cluster.scheduler_address) as engine:
        resumed = tune(
            problem,
            budget=6,
            storage=db,
            resume=True,
            execution=Execution(engine=engine, batch=2),
            progress=False,
            options={"n_init": 2},
        )
    reference = tune(
        problem,
        budget=6,
        execution=Execution(batch=2),
        progress=False,
        options={"n_init": 2},
    )
    _same(resumed, reference)
    for n, v in before.items():  # finished results were kept, not evaluated again
        assert resumed.history[n].value == v


def test_unreachable_scheduler_and_missing_extra_are_bad_input(monkeypatch, problem):
    with pytest.raises(ConfigError, match="cannot reach the Dask scheduler at"):
        DaskEngine(problem, scheduler="tcp://127.0.0.1:9", connect_timeout=0.5)
    from kftune.cli import main

    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["tune", "--scheduler", "local", "-n", "2", "-q", "-o", os.devnull]) == 3


@pytest.mark.slow
def test_an_address_that_is_not_a_dask_scheduler_is_given_up(problem, monkeypatch):
    """A service that accepts the connection and never answers in Dask's protocol (an HTTP
    server on the port) made tune wait for ever: distributed's timeout does not cover the
    handshake."""
    import socket

    from kftune.optim import dask_engine

    monkeypatch.setattr(dask_engine, "HANDSHAKE_GRACE", 1.0)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        outcome = _in_thread(
            lambda: DaskEngine(problem, scheduler=f"tcp://127.0.0.1:{port}", connect_timeout=1.0)
        )
    with pytest.raises(ConfigError, match=r"cannot reach .* is it a Dask scheduler\?"):
        outcome()


def _in_thread(call):
    """Run ``call()`` in a thread; returns a function that returns its result or raises its
    exception. Fails when it has not returned within :data:`HANG_GUARD` seconds."""
    box: dict = {}

    def run() -> None:
        try:
            box["result"] = call()
        except BaseException as exc:
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(HANG_GUARD)
    assert not thread.is_alive(), f"still waiting after {HANG_GUARD:g} s (a hang guard)"

    def outcome():
        if "error" in box:
            raise box["error"]
        return box["result"]

    return outcome


def _finished(db) -> int:
    """How many evaluations the study ``db`` holds finished (0 while it does not exist)."""
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as conn:
            query = "SELECT count(*) FROM trials WHERE state IN (?, ?)"
            return conn.execute(query, (COMPLETE, FAILED)).fetchone()[0]
    except sqlite3.Error:
        return 0


@pytest.mark.slow
def test_ctrl_c_on_a_local_cluster_prints_no_worker_tracebacks(tmp_path):
    """A terminal's Ctrl-C reaches the whole process group: each local worker printed a
    KeyboardInterrupt traceback (71 lines on stderr). The workers now ignore SIGINT; the
    command says what was kept, in three lines, and exits 130.

    Synchronised on the study's results only: on a loaded machine starting the cluster
    alone takes a minute (the test gave up after 120 s and then waited 60 s for a run of
    100 evaluations to end), and distributed's log lines of a slow shutdown went to stderr.
    """
    db = tmp_path / "study.db"
    cmd = [sys.executable, "-m", "kftune", "tune", "--scheduler", "local", "--workers", "2"]
    cmd += ["-n", "100", "--storage", str(db), "-o", str(tmp_path / "t.json")]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
        text=True,
        preexec_fn=default_sigint,
    )
    try:
        wait_until(lambda: _finished(db) >= 3, proc, "3 finished evaluations in the study")
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal does
        _, err = proc.communicate(timeout=HANG_GUARD)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "ERROR" not in err, err[-2000:]
    assert "continue with the same command plus --resume" in err


@contextlib.contextmanager
def _listener(answer: bytes) -> Iterator[str]:
    """A service on 127.0.0.1 that answers ``answer`` to each connection and closes it (at
    most 20); yields its tcp:// address."""
    server = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve() -> None:
        for _ in range(20):
            conn, _ = server.accept()
            with conn:
                if stop.is_set():
                    return
                with contextlib.suppress(OSError):
                    conn.sendall(answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    host, port = server.getsockname()[:2]
    try:
        yield f"tcp://{host}:{port}"
    finally:
        stop.set()
        with contextlib.suppress(OSError):  # wakes the accept (the thread may have ended)
            socket.create_connection((host, port), timeout=HANG_GUARD).close()
        thread.join(HANG_GUARD)
        server.close()


#: What a service that is not a Dask scheduler answers: distributed reads the first 8 bytes
#: as the length to allocate.
JUNK_ANSWERS = {
    "0xff bytes (16 EiB)": b"\xff" * 16,
    "3 EiB": struct.pack("Q", 3 << 60) + b"\0" * 8,
    "an HTTP answer": b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n",
    "a handshake-sized message of 2**40 frames": struct.pack("QQ", 24, 1 << 40) + b"\0" * 16,
}


@pytest.mark.parametrize("answer", list(JUNK_ANSWERS.values()), ids=list(JUNK_ANSWERS))
def test_a_service_answering_junk_is_refused_before_distributed_reads_it(
    tmp_path, monkeypatch, answer
):
    """Junk on the --scheduler port was a traceback ending in an attempt to allocate 3 EiB:
    distributed's client trusts the length prefix of its framing. kftune reads the first
    message itself, with a bound, and refuses it before distributed connects (exit 3, the
    address named), writing nothing."""
    from conftest import run_cli

    def never(*args, **kwargs):
        raise AssertionError("distributed was given the address")

    monkeypatch.setattr(distributed, "Client", never)
    with _listener(answer) as address:
        out = tmp_path / "out"
        out.mkdir()
        res = run_cli(
            "tune", "--scheduler", address, "-n", "2", "-q",
            "--storage", str(out / "s.db"), "-o", str(out / "t.json"),
        )  # fmt: skip
    assert res.returncode == 3, res.stderr
    assert f"{address!r}" in res.stderr and "does not answer in Dask's protocol" in res.stderr
    assert "Traceback" not in res.stderr
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("answer", [b"\xff" * 16, struct.pack("Q", 3 << 60) + b"\0" * 8])
def test_junk_that_reaches_distributed_is_refused_too(problem, monkeypatch, answer):
    """A service that answered kftune's own read as a scheduler and distributed's with junk:
    distributed's failure to allocate what it announced (ValueError, MemoryError) is the
    same refusal, not a traceback. The half-made client is collected at once: left to a
    later collection on distributed's event-loop thread, its clean-up blocked the next
    client's start."""
    import gc

    from kftune.optim import dask_engine

    monkeypatch.setattr(dask_engine, "_preflight", lambda scheduler, timeout: None)
    gc.collect()  # what earlier tests left
    refused = pytest.raises(ConfigError, match=r"does not answer in Dask's protocol")
    with _listener(answer) as address, refused as err:
        DaskEngine(problem, scheduler=address, connect_timeout=60)  # a hang guard only
    assert address in str(err.value)
    assert not [c for c in gc.get_objects() if isinstance(c, distributed.Client)]


@pytest.mark.slow
def test_a_killed_scheduler_keeps_what_finished_and_says_how_to_resume(tmp_path):
    """SIGKILL of the scheduler mid-run: the command said "failed: Timed out trying to
    connect" after 30 lines of distributed's tracebacks. Now: exit 1, the address named,
    how many finished evaluations the study keeps, the best point so far saved, and the
    exact command that resumes the run."""
    scheduler_file = tmp_path / "scheduler.json"

    def address() -> str | None:
        try:
            return json.loads(scheduler_file.read_text())["address"]
        except (OSError, ValueError, KeyError):
            return None

    dask = [sys.executable, "-m", "dask"]
    scheduler = subprocess.Popen(
        [*dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
         "--scheduler-file", str(scheduler_file)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    worker = tune = None
    try:
        wait_until(lambda: address() is not None, scheduler, "the scheduler's address")
        addr = address()
        worker = subprocess.Popen(
            [*dask, "worker", addr, "--nthreads", "1", "--no-nanny", "--no-dashboard"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        with distributed.Client(addr, timeout=HANG_GUARD) as client:
            client.wait_for_workers(1, timeout=HANG_GUARD)  # tune waits only 10 s for one
        db, out = tmp_path / "s.db", tmp_path / "t.json"
        args = ["tune", "--scheduler", addr, "-n", "100", "-q", "--storage", str(db)]
        args += ["-o", str(out)]
        tune = subprocess.Popen(
            [sys.executable, "-m", "kftune", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        wait_until(lambda: _finished(db) >= 1, tune, "a finished evaluation in the study")
        scheduler.kill()
        scheduler.wait()
        kept = _finished(db)
        _, err = tune.communicate(timeout=HANG_GUARD)
    finally:
        for proc in (tune, worker, scheduler):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    assert tune.returncode == 1, err
    assert "Traceback" not in err and "ERROR" not in err, err
    assert f"lost the Dask scheduler at {addr!r} during the run" in err
    n = _finished(db)
    assert n >= kept >= 1 and f"every finished evaluation ({n}) is saved in {db}" in err
    assert shlex.join(["kftune", *args, "--resume"]) in err
    assert json.loads((tmp_path / "t.partial.json").read_text())["n_evals"] == n
    written = {p.name for p in tmp_path.iterdir()} - {"scheduler.json", "t.partial.json"}
    assert all(name.startswith("s.db") for name in written), written  # the study's files


@pytest.mark.parametrize(
    ("error", "lost"),
    [
        # gather's stream closes under a future that finished, before the client marks
        # itself disconnected: the scheduler is gone (seen once in the test above)
        (distributed.comm.CommClosedError("in <TCP (closed) ConnectionPool.gather>: closed"), True),
        (ValueError("a bug of the objective's"), False),  # connected: not a lost scheduler
    ],
)
def test_a_closed_connection_is_a_lost_scheduler_while_the_client_still_runs(error, lost):
    engine = DaskEngine.__new__(DaskEngine)  # no cluster: only run()'s reading of errors
    engine.client = types.SimpleNamespace(status="running")
    engine.scheduler = "tcp://127.0.0.1:8786"

    def fails(points):
        raise error
        yield

    engine._run = fails
    expected = SchedulerLostError if lost else type(error)
    with pytest.raises(expected) as caught:
        list(engine.run([np.zeros(3)]))
    assert ("lost the Dask scheduler at 'tcp://127.0.0.1:8786'" in str(caught.value)) == lost


@pytest.mark.parametrize("address", ["foo", "tcp:/127.0.0.1", "tcp://127.0.0.1:99999", ""])
def test_a_malformed_scheduler_address_is_refused_before_connecting(problem, address, monkeypatch):
    """distributed raised its own ValueError for these (a traceback, exit 1); port 99999
    waited out the connect timeout."""

    def no_connection(*args, **kwargs):
        raise AssertionError("a connection was tried")

    monkeypatch.setattr(socket, "create_connection", no_connection)
    monkeypatch.setattr(distributed, "Client", no_connection)
    with pytest.raises(ConfigError, match=r"not a scheduler address; expected tcp://HOST:PORT"):
        DaskEngine(problem, scheduler=address, connect_timeout=30)


@pytest.mark.slow
def test_a_point_that_kills_every_worker_is_recorded_failed(cluster):
    points = [[0.2, 0.2], [0.9, 0.1], [0.3, 0.4]]
    space = [(0.0, 1.0), (0.0, 1.0)]
    with DaskEngine(_dies_above_half, scheduler=cluster.scheduler_address, retries=0) as e:
        result = minimize(
            _dies_above_half,
            space,
            "manual",
            points=points,
            execution=Execution(batch=3, engine=e),
        )
    assert [r.state for r in result.history] == [COMPLETE, FAILED, COMPLETE]
    assert "KilledWorker" in result.history[1].reason
    assert result.history[0].value == pytest.approx(0.08)
