"""Batched and distributed evaluation on a real Dask LocalCluster (2 worker processes).

The cluster starts once for the module (it takes seconds on a loaded machine); every test
connects its engine to it by address, which is also how ``kftune tune --scheduler`` works.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import cloudpickle  # noqa: E402  (a dependency of distributed)

from kftune.data import default_dataset  # noqa: E402
from kftune.errors import ConfigError  # noqa: E402
from kftune.experiment import tune  # noqa: E402
from kftune.optim import minimize  # noqa: E402
from kftune.optim.dask_engine import DaskEngine  # noqa: E402
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


def _slow(x):
    time.sleep(0.4)
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
            problem, problem.space, "trbo", budget=4, batch=2, engine=engine, n_init=2
        )
        _same(on_dask, minimize(problem, problem.space, "trbo", budget=4, batch=2, n_init=2))
        one_by_one = minimize(problem, problem.space, "trbo", budget=3, batch=1, engine=engine)
        _same(one_by_one, minimize(problem, problem.space, "trbo", budget=3))


def test_a_worker_killed_mid_evaluation_loses_nothing(cluster):
    space = [(0.0, 1.0), (0.0, 1.0)]
    killed: list[int] = []
    with DaskEngine(_slow, scheduler=cluster.scheduler_address) as engine:
        pids = engine.worker_pids()

        def killer():  # SIGKILL the first worker seen running an evaluation
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not killed:
                busy = [a for a, keys in engine.client.processing().items() if keys]
                if busy and busy[0] in pids:
                    time.sleep(0.1)  # well inside the 0.4 s evaluation
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(pids[busy[0]])
                time.sleep(0.01)

        thread = threading.Thread(target=killer, daemon=True)
        thread.start()
        result = minimize(_slow, space, "random", budget=4, batch=2, engine=engine)
        thread.join()
    assert killed, "no worker was seen evaluating"
    assert result.n_failed == 0 and result.n_evals == 4
    _same(result, minimize(_slow, space, "random", budget=4, batch=2))


def test_a_run_killed_during_a_batch_resumes_exactly(cluster, problem, tmp_path):
    db = tmp_path / "study.db"
    config = tmp_path / "tune.toml"  # a short initial design: the batches after it are the
    config.write_text("[options.trbo]\nn_init = 2\n")  # model's (Kriging believer)
    cmd = [sys.executable, "-m", "kftune", "tune", "--scheduler", cluster.scheduler_address]
    cmd += ["--batch", "2", "-n", "6", "--storage", str(db), "-o", str(tmp_path / "t.json")]
    cmd += ["--config", str(config)]
    proc = subprocess.Popen([*cmd, "-q"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    states: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
                    states = [s for (s,) in conn.execute("SELECT state FROM trials")]
            except sqlite3.Error:
                states = []
            if states.count(COMPLETE) >= 2 and "running" in states:
                proc.send_signal(signal.SIGKILL)  # with a batch in flight
                break
            time.sleep(0.005)
    finally:
        if proc.poll() is None:
            proc.wait(timeout=60)
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
            engine=engine,
            batch=2,
            progress=False,
            options={"n_init": 2},
        )
    reference = tune(problem, budget=6, batch=2, progress=False, options={"n_init": 2})
    _same(resumed, reference)
    for n, v in before.items():  # finished results were kept, not evaluated again
        assert resumed.history[n].value == v


def test_unreachable_scheduler_and_missing_extra_are_bad_input(monkeypatch, problem):
    with pytest.raises(ConfigError, match="cannot reach the Dask scheduler at"):
        DaskEngine(problem, scheduler="tcp://127.0.0.1:9", connect_timeout=0.5)
    from kftune.cli import main

    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["tune", "--scheduler", "local", "-n", "2", "-q", "-o", os.devnull]) == 3


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
        t0 = time.perf_counter()
        with pytest.raises(ConfigError, match=r"cannot reach .* is it a Dask scheduler\?"):
            DaskEngine(problem, scheduler=f"tcp://127.0.0.1:{port}", connect_timeout=1.0)
        assert time.perf_counter() - t0 < 10


def test_ctrl_c_on_a_local_cluster_prints_no_worker_tracebacks(tmp_path):
    """A terminal's Ctrl-C reaches the whole process group: each local worker printed a
    KeyboardInterrupt traceback (71 lines on stderr). The workers now ignore SIGINT; the
    command says what was kept, in three lines, and exits 130."""
    db = tmp_path / "study.db"
    cmd = [sys.executable, "-m", "kftune", "tune", "--scheduler", "local", "--workers", "2"]
    cmd += ["-n", "100", "--storage", str(db), "-o", str(tmp_path / "t.json")]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True, text=True
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
                    done = conn.execute("SELECT count(*) FROM trials WHERE state = ?", (COMPLETE,))
                    if done.fetchone()[0] >= 3:
                        os.killpg(proc.pid, signal.SIGINT)  # as a terminal does
                        break
            except sqlite3.Error:
                pass
            time.sleep(0.05)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "ERROR" not in err, err[-2000:]
    assert "continue with the same command plus --resume" in err


@pytest.mark.parametrize("address", ["foo", "tcp:/127.0.0.1", "tcp://127.0.0.1:99999", ""])
def test_a_malformed_scheduler_address_is_refused_before_connecting(problem, address):
    """distributed raised its own ValueError for these (a traceback, exit 1); port 99999
    waited out the connect timeout."""
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"not a scheduler address; expected tcp://HOST:PORT"):
        DaskEngine(problem, scheduler=address, connect_timeout=30)
    assert time.perf_counter() - t0 < 5


def test_a_point_that_kills_every_worker_is_recorded_failed(cluster):
    points = [[0.2, 0.2], [0.9, 0.1], [0.3, 0.4]]
    space = [(0.0, 1.0), (0.0, 1.0)]
    with DaskEngine(_dies_above_half, scheduler=cluster.scheduler_address, retries=0) as e:
        result = minimize(_dies_above_half, space, "manual", points=points, batch=3, engine=e)
    assert [r.state for r in result.history] == [COMPLETE, FAILED, COMPLETE]
    assert "KilledWorker" in result.history[1].reason
    assert result.history[0].value == pytest.approx(0.08)
