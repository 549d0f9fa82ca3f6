"""Persistent studies and ``minimize``'s run control: exact resume, SIGKILL at random
moments, one process per study, settings checks, Ctrl-C, timeouts, callbacks, JSON."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import HANG_GUARD
from kftune.errors import ConfigError
from kftune.optim import (
    Execution,
    OptimizationInterrupted,
    OptimizeResult,
    StudyError,
    StudyInUseError,
    minimize,
)
from test_optim_contract import _method

HERE = Path(__file__).resolve().parent
WORKER = HERE / "optim_study_worker.py"
sys.path.insert(0, str(HERE))
from optim_study_worker import SPACE, method_options, objective  # noqa: E402

#: The contract runs every method on small budgets: the GA's "no generation" warning
#: is expected there.
pytestmark = pytest.mark.filterwarnings("ignore::kftune.errors.SettingWarning")


def strip_timings(res: OptimizeResult) -> dict:
    """The result as a dict without wall-clock timings (the only legitimate difference)."""
    d = res.to_dict()
    for h in d["history"]:
        h.pop("t_propose")
        h.pop("t_eval")
    return d


def rows(db: Path) -> list[tuple]:
    with sqlite3.connect(db) as conn:
        return conn.execute("SELECT number, state, u FROM trials ORDER BY number").fetchall()


@pytest.mark.parametrize("method", ["ga", "random", "optuna-tpe", "cma", "tsbo-gp"])
def test_stopped_then_resumed_equals_uninterrupted(tmp_path, method):
    method = _method(method)
    budget = 14
    opts = method_options(method)
    ref = minimize(objective, SPACE, method, budget=budget, seed=3, **opts)
    db = tmp_path / "s.db"
    part = minimize(
        objective,
        SPACE,
        method,
        budget=budget,
        seed=3,
        storage=str(db),
        callback=lambda r: r.number == 5,
        **opts,
    )
    assert part.status == "stopped" and part.n_evals == 6
    assert [r[1] for r in rows(db)] == ["complete"] * 6
    calls = []

    def counted(x):
        calls.append(x)
        return objective(x)

    res = minimize(
        counted, SPACE, method, budget=budget, seed=3, storage=str(db), resume=True, **opts
    )
    assert len(calls) == budget - 6  # finished evaluations are not repeated
    assert strip_timings(res) == strip_timings(ref)
    # Resuming a finished study evaluates nothing and returns the same result.
    again = minimize(
        counted, SPACE, method, budget=budget, seed=3, storage=str(db), resume=True, **opts
    )
    assert len(calls) == budget - 6
    assert again.to_dict() == res.to_dict()


def test_interrupt_saves_and_in_flight_point_is_redone(tmp_path):
    db = tmp_path / "s.db"
    ref = minimize(objective, SPACE, "ga", budget=30, seed=1)

    def interrupted(x):
        if len(rows(db)) == 9:
            raise KeyboardInterrupt
        return objective(x)

    with pytest.raises(OptimizationInterrupted) as info:
        minimize(interrupted, SPACE, "ga", budget=30, seed=1, storage=str(db))
    part = info.value.result
    assert isinstance(info.value, KeyboardInterrupt)
    assert part.status == "interrupted" and part.n_evals == 8
    stored = rows(db)
    assert [r[1] for r in stored] == ["complete"] * 8 + ["running"]
    in_flight = json.loads(stored[8][2])
    seen = []
    res = minimize(
        lambda x: seen.append(x.copy()) or objective(x),
        SPACE,
        "ga",
        budget=30,
        seed=1,
        storage=str(db),
        resume=True,
    )
    np.testing.assert_allclose(SpaceU(seen[0]), in_flight, atol=1e-12)
    assert len(seen) == 30 - 8
    assert strip_timings(res) == strip_timings(ref)


def SpaceU(x):
    from kftune.optim import Space

    return Space.coerce(SPACE).to_unit(x)


def test_existing_study_needs_resume_and_same_settings(tmp_path):
    db = str(tmp_path / "s.db")
    minimize(objective, SPACE, "random", budget=4, seed=0, storage=db)
    with pytest.raises(StudyError, match=r"already exists \(4 evaluations.*resume=True"):
        minimize(objective, SPACE, "random", budget=4, seed=0, storage=db)
    cases = [
        ({"method": "ga"}, "method"),
        ({"seed": 1}, "seed"),
        ({"budget": 3}, "budget"),  # a smaller one (a larger one continues the study)
        ({"space": {"a": (-5.0, 10.0), "q": (1e-9, 1.0, "log10")}}, "space"),
    ]
    for change, key in cases:
        kw = {"method": "random", "budget": 4, "seed": 0, "space": SPACE, **change}
        sp = kw.pop("space")
        with pytest.raises(ConfigError, match=rf"created with {key}\b.*this run asks for {key}\b"):
            minimize(objective, sp, storage=db, resume=True, **kw)
    db2 = str(tmp_path / "g.db")
    minimize(objective, SPACE, "ga", budget=20, seed=0, storage=db2)
    # inside the options, the one that differs is named
    with pytest.raises(
        ConfigError,
        match=r"created with options\.crossover_fraction = .*asks for options\.crossover",
    ):
        minimize(
            objective,
            SPACE,
            "ga",
            budget=20,
            seed=0,
            storage=db2,
            resume=True,
            crossover_fraction=0.5,
        )


def test_foreign_file_is_refused(tmp_path):
    bad = tmp_path / "notes.db"
    bad.write_text("not a database at all, just text " * 20)
    with pytest.raises(StudyError, match=r"not a"):
        minimize(objective, SPACE, "random", budget=2, storage=str(bad), resume=True)
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE t (a)")
    with pytest.raises(StudyError, match=r"not a kftune study"):
        minimize(objective, SPACE, "random", budget=2, storage=str(other), resume=True)


@pytest.mark.slow
def test_study_in_use_gives_clear_error_and_lock_dies_with_process(tmp_path):
    db = tmp_path / "s.db"
    log = tmp_path / "log.txt"
    proc = subprocess.Popen(
        [sys.executable, str(WORKER), str(db), str(log), "0", "random", "200", "0.05"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        _wait_for(lambda: db.exists() and log.exists(), proc)
        with pytest.raises(StudyInUseError, match=r"in use by another process"):
            minimize(objective, SPACE, "random", budget=200, seed=5, storage=str(db), resume=True)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # The OS released the lock with the killed process: the study opens and resumes.
    res = minimize(objective, SPACE, "random", budget=200, seed=5, storage=str(db), resume=True)
    assert res.n_evals == 200 and res.status == "completed"


_ORPHAN_SCRIPT = """
import os, sys, time
from kftune.optim import Execution, minimize
def fun(x):
    with open(sys.argv[2], "a") as fh:
        fh.write(f"{os.getpid()}\\n")
    time.sleep(600.0)  # hung: only the timeout (60 s) would end it
    return float(x[0])
minimize(fun, {"a": (0.0, 1.0)}, "random", budget=5, seed=0, storage=sys.argv[1],
         execution=Execution(timeout=60))
"""


@pytest.mark.slow
def test_killed_parent_leaves_no_worker_holding_the_study(tmp_path):
    """SIGKILL of a run with a timeout (evaluations in a worker process) during a hung
    evaluation: the study can be resumed at once (the worker does not hold the lock) and the
    orphaned worker exits within a second or so instead of running on."""
    db, pids = tmp_path / "s.db", tmp_path / "pids.txt"
    proc = subprocess.Popen(
        [sys.executable, "-c", _ORPHAN_SCRIPT, str(db), str(pids)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _wait_for(lambda: pids.exists() and pids.read_text().strip(), proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    worker = int(pids.read_text().split()[0])
    assert worker != proc.pid
    res = minimize(lambda x: float(x[0]), {"a": (0.0, 1.0)}, "random", budget=5, seed=0,
                   storage=str(db), resume=True)  # fmt: skip
    assert res.n_evals == 5
    # a hang guard far below the hung evaluation's 600 s (a loaded machine can stretch the
    # worker's notice of its orphaning to many seconds)
    deadline = time.monotonic() + 120
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(worker), "the orphaned evaluation worker is still running"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped by init) counts as gone
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(") ")[-1].startswith("Z"))


def test_the_lock_follows_the_file_not_the_path(tmp_path):
    """A second path to the same study (here a symlink) meets the same lock."""
    from kftune.optim.study import Study

    db = tmp_path / "s.db"
    (tmp_path / "link.db").symlink_to(db)
    settings = {"method": "random", "seed": 0}
    first = Study.open(db, settings, resume=False)
    try:
        with pytest.raises(StudyInUseError):
            Study.open(tmp_path / "link.db", settings, resume=True)
    finally:
        first.close()
    Study.open(tmp_path / "link.db", settings, resume=True).close()


def test_a_study_dropped_without_close_frees_its_lock(tmp_path):
    import gc

    from kftune.optim.study import Study

    settings = {"method": "random", "seed": 0}
    s = Study.open(tmp_path / "s.db", settings, resume=False)
    del s
    gc.collect()
    Study.open(tmp_path / "s.db", settings, resume=True).close()


def _wait_for(cond, proc, limit=HANG_GUARD, exit_ok=False):
    """Poll ``cond()`` until it holds; ``limit`` [s] is a hang guard only (a loaded machine
    stretches a worker's start-up from a second to a minute)."""
    t0 = time.monotonic()
    while not cond():
        if proc.poll() is not None:
            if exit_ok and proc.returncode == 0:
                return
            raise AssertionError(f"worker exited early: {proc.stderr.read().decode()}")
        if time.monotonic() - t0 > limit:
            raise AssertionError(f"worker did not start within {limit:g} s (a hang guard)")
        time.sleep(0.02)


@pytest.mark.parametrize(("method", "budget"), [("tsbo-tsp", 24), ("ga", 60), ("trbo", 30)])
@pytest.mark.slow
def test_sigkill_at_random_moments_then_resume(tmp_path, method, budget):
    """Kill the study's process with SIGKILL several times at random moments; after the last
    resume the result equals the uninterrupted run's and no finished evaluation was redone."""
    method = _method(method)
    db, log = tmp_path / "s.db", tmp_path / "log.txt"
    ref = minimize(objective, SPACE, method, budget=budget, seed=5, **method_options(method))
    if method.startswith("tsbo"):  # the kills can land in both stages and after the freeze
        stages = [r.stage for r in ref.history]
        assert 2 in stages and stages.index(2) < budget - 5, stages
    rng = np.random.default_rng(2024)
    n_done_before: list[int] = []
    kills = 0
    for run_id in range(12):
        n_done_before.append(len(_complete_u(db)) if db.exists() else 0)
        proc = subprocess.Popen(
            [
                sys.executable,
                str(WORKER),
                str(db),
                str(log),
                str(run_id),
                method,
                str(budget),
                "0.02",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        if kills < 4:
            # Wait for progress (imports take a while), then kill at a random moment.
            n0 = n_done_before[-1]
            _wait_for(lambda n0=n0: db.exists() and len(_complete_u(db)) > n0, proc, exit_ok=True)
            time.sleep(float(rng.uniform(0.0, 0.3)))
            if proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                kills += 1
        proc.wait(timeout=HANG_GUARD)
        if proc.returncode == 0:
            break
        assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
    assert kills >= 3, "the worker finished before it could be killed several times"
    res = OptimizeResult.from_dict(json.loads(Path(str(db) + ".result.json").read_text()))
    assert strip_timings(res) == strip_timings(ref)
    # Run r evaluated exactly the trials n_r, n_r+1, … in order, where n_r trials were
    # complete when it started: nothing finished is redone, the in-flight one is.
    stored_u = {n: u for n, _, u in _complete_u(db)}
    assert sorted(stored_u) == list(range(budget))
    from kftune.optim import Space

    sp = Space.coerce(SPACE)
    logged: dict[int, list] = {}
    for line in log.read_text().splitlines():
        run_id, xs = line.split(" ", 1)
        logged.setdefault(int(run_id), []).append(sp.to_unit(np.array(json.loads(xs))))
    for run_id, us in logged.items():
        n_r = n_done_before[run_id]
        expect = [stored_u[n_r + k] for k in range(len(us))]
        np.testing.assert_allclose(us, expect, atol=1e-12)
    # Progress was really interrupted: several runs each started with a different prefix.
    assert len(set(n_done_before)) >= 3


def _complete_u(db: Path) -> list[tuple]:
    try:
        with sqlite3.connect(db, timeout=5) as conn:
            got = conn.execute("SELECT number, state, u FROM trials WHERE state = 'complete'")
            return [(n, s, json.loads(u)) for n, s, u in got.fetchall()]
    except sqlite3.OperationalError:  # table not created yet
        return []


def _slow(x):
    time.sleep(5.0 if x[0] > 2.5 else 0.0)
    return objective(x)


def _die(x):
    if x[0] > 2.5:
        os._exit(3)
    return objective(x)


@pytest.mark.slow
def test_timeout_and_dying_worker_fail_the_evaluation_only():
    # the limit counts only the evaluation (not a worker start-up), so a fast evaluation on
    # a loaded machine stays far below it
    res = minimize(_slow, SPACE, "random", budget=8, seed=0, execution=Execution(timeout=1.0))
    assert res.n_evals == 8
    for r in res.history:
        if r.x[0] > 2.5:
            assert r.state == "failed" and r.reason == "timeout after 1 s"
        else:
            assert r.state == "complete" and r.value == objective(np.array(r.x))
    assert any(r.state == "failed" for r in res.history)
    res = minimize(_die, SPACE, "random", budget=6, seed=0, execution=Execution(timeout=10))
    assert res.n_evals == 6
    for r in res.history:
        assert (r.state == "failed") == (r.x[0] > 2.5)
        if r.state == "failed":
            assert r.reason == "evaluation process died (exit code 3)"


def test_callback_sees_every_record_and_result_is_strict_json(tmp_path):
    seen = []
    res = minimize(
        lambda x: float("inf") if x[0] > 8 else objective(x),
        SPACE,
        "random",
        budget=10,
        seed=2,
        callback=seen.append,
    )
    assert [r.number for r in seen] == list(range(10))
    assert list(res.history) == seen
    text = res.to_json()
    assert "Infinity" not in text and "NaN" not in text
    back = OptimizeResult.from_dict(json.loads(text))
    assert back.to_dict() == res.to_dict()
    np.testing.assert_array_equal(
        res.best_so_far, np.minimum.accumulate(np.where(np.isnan(res.values), np.inf, res.values))
    )


def test_study_rows_written_before_and_after_each_evaluation(tmp_path):
    db = tmp_path / "s.db"
    states_during = []

    def fun(x):
        states_during.append([r[1] for r in rows(db)])
        return objective(x)

    minimize(fun, SPACE, "random", budget=3, seed=0, storage=str(db))
    # While evaluation k runs, rows 0..k-1 are complete and row k is already stored.
    assert states_during == [
        ["running"],
        ["complete", "running"],
        ["complete", "complete", "running"],
    ]


def test_resume_with_another_objective_is_refused(tmp_path):
    db = tmp_path / "s.db"
    stop_after_3 = lambda rec: rec.number == 2  # noqa: E731
    minimize(
        objective, SPACE, "random", budget=6, seed=0, storage=db, objective={"data": "a"},
        callback=stop_after_3,
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r'objective = \{"data": "a"\}'):
        minimize(
            objective, SPACE, "random", budget=6, seed=0, storage=db, resume=True,
            objective={"data": "b"},
        )  # fmt: skip
    res = minimize(
        objective, SPACE, "random", budget=6, seed=0, storage=db, resume=True,
        objective={"data": "a"},
    )  # fmt: skip
    assert res.n_evals == 6


def _starts_a_process(x):
    # e.g. a tuning problem that runs its manoeuvres in a process pool
    child = multiprocessing.get_context("fork").Process(target=time.sleep, args=(0.0,))
    child.start()
    child.join()
    return objective(x)


def test_timeout_worker_may_start_processes():
    res = minimize(
        _starts_a_process, SPACE, "random", budget=3, seed=0, execution=Execution(timeout=30)
    )
    assert res.n_failed == 0, [r.reason for r in res.history]


def test_resume_refuses_when_the_code_now_proposes_other_points(tmp_path, monkeypatch):
    """The stored settings are equal, but the optimiser's code changed (simulated by a
    shifted proposal from trial 3 on): the replay notices and names the trial, instead of
    mixing the two runs' histories."""
    from kftune.optim.base import Proposal
    from kftune.optim.baselines import RandomSearch

    db = tmp_path / "s.db"
    minimize(objective, SPACE, "random", budget=8, seed=0, storage=db,
             callback=lambda r: r.number == 5)  # fmt: skip
    original = RandomSearch._propose

    def changed(self):
        p = original(self)
        if self.n_evals >= 3:
            return Proposal(u=(p.u + 0.01) % 1.0, acquisition=p.acquisition)
        return p

    monkeypatch.setattr(RandomSearch, "_propose", changed)
    calls = []
    with pytest.raises(StudyError, match=r"replay diverged at trial 3.*different code"):
        minimize(lambda x: calls.append(x) or objective(x), SPACE, "random", budget=8, seed=0,
                 storage=db, resume=True)  # fmt: skip
    assert calls == []  # nothing was evaluated on top of the foreign history
    assert [r[1] for r in rows(db)] == ["complete"] * 6  # and the study is untouched


def test_resume_refuses_an_in_flight_point_the_code_no_longer_proposes(tmp_path):
    """The proposal in flight when a run stopped must be the next one the replay makes."""
    db = tmp_path / "s.db"

    def interrupted(x):
        if len(rows(db)) == 4:
            raise KeyboardInterrupt
        return objective(x)

    with pytest.raises(OptimizationInterrupted):
        minimize(interrupted, SPACE, "random", budget=8, seed=0, storage=str(db))
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE trials SET u = '[0.5, 0.5]' WHERE state = 'running'")
    with pytest.raises(StudyError, match=r"replay diverged at trial 3"):
        minimize(objective, SPACE, "random", budget=8, seed=0, storage=str(db), resume=True)


def test_resume_on_other_data_says_what_differs_in_words(tmp_path):
    """A tuning problem's fingerprint carries a summary: the refusal shows it, not a hash
    in JSON with escapes."""
    db = tmp_path / "s.db"
    a = {"sha256": "aa", "summary": "8 manoeuvres (t-01 … t-08), car A, cost nrmse"}
    minimize(objective, SPACE, "random", budget=2, seed=0, storage=db, objective=a)
    b = {"sha256": "5ca1ab1e", "summary": "6 manoeuvres (s01 … s16), car B, cost nrmse"}
    with pytest.raises(ConfigError) as info:
        minimize(objective, SPACE, "random", budget=2, seed=0, storage=db, resume=True, objective=b)
    msg = str(info.value)
    assert "(t-01 … t-08), car A" in msg and "car B" in msg and "\\u" not in msg
    assert "5ca1ab1e" not in msg  # the summary, not the hash
    with pytest.raises(ConfigError, match=r"the data differ"):
        minimize(
            objective, SPACE, "random", budget=2, seed=0, storage=db, resume=True,
            objective={**a, "sha256": "cc"},
        )  # fmt: skip
