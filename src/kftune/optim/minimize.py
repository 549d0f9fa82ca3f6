"""``kftune.minimize``: the thin loop over ask/tell, with failures, timeouts and studies.

Evaluation and failures
    ``fun`` receives a ``(d,)`` array in natural units and returns a float. An exception
    (any ``Exception``), a NaN/inf or non-numeric return value, or — when a ``timeout`` is
    set (:class:`Execution`) — a run longer than ``timeout`` seconds makes the evaluation
    *failed*: it is recorded with its reason, the optimiser is told (TSBO imputes a
    pessimistic value and never proposes the point again) and the run goes on.

Timeouts
    Only when ``timeout`` is given, evaluations run in one persistent worker process
    (``fork`` start method on Linux, ``spawn`` elsewhere — then ``fun`` must be picklable).
    A timed-out worker is killed and a fresh one started for the next evaluation; a worker
    that dies (segfault, ``os._exit``) fails that evaluation likewise. Side effects of
    ``fun`` stay in the worker. Without ``timeout`` ``fun`` runs in this process.

Studies and resume
    With ``storage="study.db"`` every proposal is committed before it is evaluated and every
    result when it arrives (see :mod:`kftune.optim.study`). ``resume=True`` rebuilds the
    optimiser by replaying the stored history through ask/tell with the same seed — each
    replayed proposal must equal the stored one (to 1e-9 in the unit cube) — so no finished
    evaluation is repeated and the final result equals that of an uninterrupted run; the
    proposal that was in flight when the previous process stopped is evaluated again.

Batches and engines
    With ``Execution(batch=q)`` (or an ``engine``, see :mod:`kftune.optim.engine`; then q
    defaults to its number of workers) the loop asks for q points at a time (``ask(q)``),
    stores every proposal of the batch in the study, sends them to the engine, stores each
    result the moment it arrives (in arrival order) and, once the whole batch is back, tells
    the optimiser the results in trial order before it asks for the next batch. The
    proposals therefore depend only on the seed, the settings and q — never on which result
    came back first, how many workers there are or which engine ran them: a run with q = 4
    on a Dask cluster proposes exactly what the same run in this process proposes, and with
    q = 1 exactly what the sequential loop proposes. The price is that a batch waits for its
    slowest point.

    Reproducible resume with pending points: a study of a batched run stores q (resuming
    with another q is refused). On resume the batches are asked again with the same seed;
    each proposal must equal the stored one, a finished result is taken from the study
    (never evaluated again), and only the proposals still ``running`` when the previous
    process stopped are evaluated again. Because tells happen at batch boundaries in trial
    order, the replayed optimiser is in the state the uninterrupted run was in, so the
    resumed run makes the same proposals and — the objective being deterministic — ends
    with the same history as a run that was never interrupted.

Ctrl-C
    ``KeyboardInterrupt`` stops the run after the study is saved and its lock released, and
    is re-raised as :class:`OptimizationInterrupted` (a ``KeyboardInterrupt``) carrying the
    partial :class:`OptimizeResult` in ``.result``. The interrupted evaluation stays
    ``running`` in the study and is redone on resume.
"""

from __future__ import annotations

import inspect
import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kftune.errors import ConfigError
from kftune.optim.base import ExhaustedError, Optimizer
from kftune.optim.engine import Engine, EngineLostError, SerialEngine
from kftune.optim.result import FAILED, EvalRecord, OptimizeResult
from kftune.optim.settings import option_names, settings_from
from kftune.optim.study import Study, StudyError
from kftune.processes import watch_parent
from kftune.settings import Rule, SettingError, check
from kftune.space import Space

#: Tolerance (unit cube, max-norm) for a replayed proposal to count as the stored one.
REPLAY_ATOL = 1e-9

#: [s] the longest per-evaluation timeout (11.6 days): waiting on a worker takes a timeout
#: below 2^31 ms, and a longer one is no limit at all (leave the timeout out instead).
MAX_TIMEOUT = 1e6
#: Most cost evaluations a run may be given (a budget, a batch): far beyond any tuning that
#: ends — the Bayesian methods' step grows as n³ — while a typing slip (``-n 1000000000000``)
#: would run until killed.
MAX_BUDGET = 100_000
#: The rule of a batch's size (``Execution.batch``, a configuration's ``batch``, ``tune
#: --batch``): points per ``ask(q)``, one rule wherever it is given.
BATCH_RULE = Rule((int,), low=1, high=MAX_BUDGET)


def _registry() -> dict[str, tuple[type[Optimizer], dict[str, Any]]]:
    from kftune.optim.baselines import ManualPoints, RandomSearch
    from kftune.optim.ga import GeneticAlgorithm
    from kftune.optim.peers import CMAES, OptunaGP, OptunaTPE
    from kftune.optim.trbo import TrustRegionBO
    from kftune.optim.tsbo import TSBO

    return {
        "trbo": (TrustRegionBO, {}),
        "tsbo-tsp": (TSBO, {"surrogate": "tsp"}),
        "tsbo-gp": (TSBO, {"surrogate": "gp"}),
        "tsbo-robust": (TSBO, {"surrogate": "robust-gp"}),
        "ga": (GeneticAlgorithm, {}),
        "random": (RandomSearch, {}),
        "manual": (ManualPoints, {}),
        "optuna-tpe": (OptunaTPE, {}),
        "optuna-gp": (OptunaGP, {}),
        "cma": (CMAES, {}),
    }


METHODS: tuple[str, ...] = (
    "trbo",
    "tsbo-tsp",
    "tsbo-gp",
    "tsbo-robust",
    "ga",
    "random",
    "manual",
    "optuna-tpe",
    "optuna-gp",
    "cma",
)
#: What ``kftune.minimize`` and ``kftune tune`` use when no method is named.
DEFAULT_METHOD = "trbo"
#: The paper's comparison (Tables V–VII), in report order.
PAPER_METHODS: tuple[str, ...] = ("manual", "ga", "tsbo-gp", "tsbo-tsp")
#: What ``kftune compare`` runs by default: the paper's four and the default tuner beside them.
COMPARE_METHODS: tuple[str, ...] = (*PAPER_METHODS, DEFAULT_METHOD)


def make_optimizer(
    method: str, space: Any, *, budget: int | None = None, seed: int = 0, **options: Any
) -> Optimizer:
    """Construct an optimiser by name (see :data:`METHODS`), its options by name.

    This is where keyword options (a configuration's ``[options.<method>]`` table, the
    ``**method_options`` of :func:`minimize`) meet the optimisers: a method whose class
    declares a settings record (``settings_type``: TR-BO's
    :class:`~kftune.optim.trbo.TRBOSettings`, TSBO's :class:`~kftune.optim.tsbo.TSBOSettings`)
    gets one built from them (:func:`~kftune.optim.settings.settings_from`); any other
    takes them as keyword arguments.

    Raises:
        ValueError: unknown method or an option the method does not have (naming it and
            listing the method's options), or an option's value out of its range.
        kftune.optim.peers.PeerUnavailableError: a peer's package is missing.
    """
    reg = _registry()
    if method not in reg:
        raise ValueError(f"unknown method {method!r}; choose one of {list(METHODS)}")
    cls, defaults = reg[method]
    record = getattr(cls, "settings_type", None)
    if record is not None:
        allowed = option_names(record)
    else:
        params = inspect.signature(cls.__init__).parameters
        allowed = [n for n in params if n not in ("self", "space", "budget", "seed")]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(f"method {method!r} has no option(s) {unknown}; its options: {allowed}")
    clash = sorted(set(options) & set(defaults))
    if clash:
        raise ValueError(f"method {method!r} fixes {clash}; use another method name instead")
    sp = Space.coerce(space)
    if record is not None:
        settings = settings_from(record, {**defaults, **options}, method)
        with_record: Any = cls  # its __init__ takes the record after the space
        return with_record(sp, settings, budget=budget, seed=seed)
    return cls(sp, budget=budget, seed=seed, **defaults, **options)


class OptimizationInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`minimize`; ``.result`` holds what finished (already saved)."""

    def __init__(self, result: OptimizeResult) -> None:
        super().__init__(f"optimisation interrupted after {result.n_evals} evaluations")
        self.result = result


@dataclass(frozen=True)
class Execution:
    """How :func:`minimize` (and :func:`kftune.experiment.tune`) evaluate the objective,
    checked once: one point at a time in this process (the default), in a worker process
    with a time limit, or in batches on an engine (module docstring, "Timeouts" and
    "Batches and engines").

    Attributes:
        timeout: [s] per-evaluation time limit, in (0, :data:`MAX_TIMEOUT`]; runs ``fun``
            in a worker process, one point at a time (not with ``engine`` or ``batch``).
            Default None: no limit, ``fun`` runs in this process.
        engine: who evaluates (see :mod:`kftune.optim.engine`; e.g. a
            :class:`~kftune.optim.dask_engine.DaskEngine`); implies a batched run. Default
            None: this process.
        batch: evaluations per batch (``ask(q)``), ≥ 1. Default None: the engine's number
            of workers, or the sequential loop without an engine.

    Raises:
        kftune.errors.ConfigError: (a ValueError) a value out of range, or a timeout with
            a batch or an engine.
    """

    timeout: float | None = None
    engine: Engine | None = None
    batch: int | None = None

    def __post_init__(self) -> None:
        timeout, batch = self.timeout, self.batch
        if timeout is not None and not (
            isinstance(timeout, (int, float))
            and not isinstance(timeout, bool)
            and 0 < timeout <= MAX_TIMEOUT
        ):
            raise ConfigError(
                f"timeout must be a number of seconds in (0, {MAX_TIMEOUT:g}] or None, "
                f"got {timeout!r}"
            )
        if batch is not None:
            try:
                check(BATCH_RULE, batch, "batch")
            except SettingError as exc:
                raise ConfigError(str(exc)) from None
        if timeout is not None and self.batched:
            raise ConfigError(
                "a per-evaluation timeout runs every evaluation in one local worker process; it "
                "cannot be combined with a batch or an engine (a Dask scheduler)"
            )

    @property
    def batched(self) -> bool:
        """Whether the points go out in batches (``ask(q)``): with an engine or a batch."""
        return self.engine is not None or self.batch is not None

    @property
    def q(self) -> int:
        """Points per batch: ``batch``, else the engine's workers, else 1."""
        if self.batch is not None:
            return self.batch
        return max(1, int(self.engine.workers)) if self.engine is not None else 1


#: :func:`minimize`'s former keywords that are :class:`Execution`'s settings now.
_EXECUTION_KEYS = ("timeout", "engine", "batch")


def minimize(
    fun: Callable[[np.ndarray], float],
    space: Any,
    method: str = DEFAULT_METHOD,
    *,
    budget: int | None = None,
    seed: int = 0,
    storage: str | os.PathLike[str] | None = None,
    resume: bool = False,
    callback: Callable[[EvalRecord], bool | None] | None = None,
    objective: dict[str, Any] | None = None,
    execution: Execution | None = None,
    **method_options: Any,
) -> OptimizeResult:
    """Minimise a black-box function over a box.

    Args:
        fun: objective; ``fun(x) -> float`` with ``x`` a ``(d,)`` array in natural units.
        space: a :class:`Space`, ``{"name": (low, high[, "log10"])}`` or a sequence of
            ``(low, high[, scale])``.
        method: one of :data:`METHODS` (default :data:`DEFAULT_METHOD`, ``"trbo"``;
            the paper's ``"tsbo-tsp"``, ``"tsbo-gp"``, ``"tsbo-robust"``, ``"ga"``,
            ``"random"``, ``"manual"``, ``"optuna-tpe"``, ``"optuna-gp"``, ``"cma"``).
        budget: evaluations (failed ones count); ``None`` → the method's default (TR-BO
            100, TSBO 40 = MAX_PE, GA 225, manual: its number of points, others 40).
        seed: drives all randomness; same seed, same run.
        storage: path of a SQLite study file, or ``None`` for no persistence.
        resume: continue the study in ``storage`` (see the module docstring).
        callback: called with every finished :class:`EvalRecord`, in order — on resume the
            replayed ones first — e.g. to drive a progress bar; returning ``True`` after a new
            evaluation stops the run (status ``"stopped"``; ignored for replayed records).
        objective: JSON-serialisable description of ``fun`` (e.g. the dataset, cost and
            model of a tuning problem) stored in the study; resuming with a different one is
            refused, so a study never mixes values of two objectives.
        execution: how ``fun`` is evaluated (:class:`Execution`: a per-evaluation
            timeout, or an engine and the batch size); default: in this process, one point
            at a time.
        **method_options: passed to the optimiser (e.g. ``max_fe=10`` for TSBO,
            ``population_size=20`` for GA, ``points=[...]`` for manual).

    Returns:
        :class:`OptimizeResult` with the best point, its value and the full history.

    Raises:
        OptimizationInterrupted: on Ctrl-C, after saving (``.result`` has the partial run).
        kftune.optim.engine.EngineLostError: the engine can evaluate no more (``.result``
            as for Ctrl-C).
        kftune.optim.study.StudyInUseError: the study is open in another process.
        kftune.optim.study.StudyError, kftune.errors.ConfigError: unusable study / settings.
        ValueError: bad arguments.
    """
    if not callable(fun):
        raise ValueError(f"fun must be callable, got {type(fun).__name__}")
    moved = [k for k in _EXECUTION_KEYS if k in method_options]
    if moved:
        raise ValueError(
            f"{moved[0]}= is a setting of how the objective is evaluated: pass "
            f"execution=Execution({moved[0]}=...) (kftune.optim.Execution)"
        )
    if resume and storage is None:
        raise ValueError("resume=True needs storage= (the study file to resume)")
    ex = Execution() if execution is None else execution
    sp = Space.coerce(space)
    opt = make_optimizer(method, sp, budget=budget, seed=seed, **method_options)
    settings: dict[str, Any] = {
        "method": method,
        "seed": opt.seed,
        "budget": opt.budget,
        "space": sp.to_dict(),
        "options": opt.options(),
        "objective": objective,
    }
    q = ex.q
    if ex.batched:
        settings["batch"] = q  # the proposals depend on q: a resume must use the same
    study = (
        Study.open(storage, settings, resume=resume, extendable=opt.budget_independent)
        if storage is not None
        else None
    )
    batch_engine: Engine | None = None
    if ex.batched:
        batch_engine = ex.engine if ex.engine is not None else SerialEngine(fun)
    evaluator = _Evaluator(fun, ex.timeout)
    history: list[EvalRecord] = []
    status = "completed"

    def result(st: str) -> OptimizeResult:
        return OptimizeResult.from_history(
            history,
            method=method,
            seed=opt.seed,
            budget=opt.budget,
            status=st,
            space=sp.to_dict(),
            options=settings["options"],
        )

    try:
        if batch_engine is not None:
            status = _run_batched(opt, batch_engine, q, study, history, callback)
            history.sort(key=lambda r: r.number)
            if status == "completed" and opt.n_evals < opt.budget:
                status = "exhausted"
            return result(status)
        in_flight: list[float] | None = None
        if study is not None:
            stored, in_flight = study.records()
            for rec in stored:
                trial = opt.ask()
                _check_replay(study, rec.number, trial.u, rec.u)
                opt.tell(trial, rec.value, state=rec.state, reason=rec.reason, t_eval=rec.t_eval)
                history.append(rec)
                if callback is not None:
                    callback(rec)
        while not opt.done:
            try:
                trial = opt.ask()
            except ExhaustedError:  # nothing left to propose (e.g. a degenerate space)
                break
            if in_flight is not None:
                _check_replay(study, trial.number, trial.u, in_flight)
                in_flight = None
            if study is not None:
                study.write_proposal(trial.number, [float(v) for v in trial.u])
            value, reason, t_eval = evaluator(trial.x)
            rec = opt.tell(
                trial,
                value,
                state=FAILED if reason is not None else None,
                reason=reason,
                t_eval=t_eval,
            )
            _save(study, rec, history)
            if callback is not None and callback(rec) is True:
                status = "stopped"
                break
        if status == "completed" and opt.n_evals < opt.budget:
            status = "exhausted"
    except KeyboardInterrupt:
        # ``finally`` below closes the study (releasing its lock) before this propagates.
        raise OptimizationInterrupted(result("interrupted")) from None
    except EngineLostError as lost:
        lost.result = result("interrupted")
        raise
    finally:
        evaluator.close()
        if study is not None:
            study.close()
    return result(status)


def _save(study: Study | None, rec: EvalRecord, history: list[EvalRecord]) -> None:
    """Store a finished evaluation in the study (committed on return) and the history."""
    if study is not None:
        try:
            study.write_result(rec)
        except KeyboardInterrupt:
            # Ctrl-C after the commit (e.g. during the checkpoint): the record is saved,
            # so it belongs to the partial result, which matches the study
            if study.is_finished(rec.number):
                history.append(rec)
            raise
    history.append(rec)


def _run_batched(
    opt: Optimizer,
    engine: Engine,
    q: int,
    study: Study | None,
    history: list[EvalRecord],
    callback: Callable[[EvalRecord], bool | None] | None,
) -> str:
    """The batched loop (module docstring, "Batches and engines"); fills ``history`` in
    arrival order and returns the status."""
    stored, running = study.rows() if study is not None else ([], {})
    known = {rec.number: rec for rec in stored}
    stored_u: dict[int, Any] = {rec.number: rec.u for rec in stored}
    stored_u.update(running)
    stop = False
    while not opt.done and not stop:
        try:
            trials = opt.ask(q)
        except ExhaustedError:
            break
        if not trials:
            break
        for t in trials:  # every proposal is committed before any point is sent
            if t.number in stored_u:
                _check_replay(study, t.number, t.u, stored_u[t.number])
            elif study is not None:
                study.write_proposal(t.number, [float(v) for v in t.u])
        results: dict[int, EvalRecord] = {}
        for t in trials:
            if t.number in known:  # finished before the previous process stopped
                results[t.number] = known[t.number]
                history.append(known[t.number])
                if callback is not None:
                    callback(known[t.number])
        todo = [t for t in trials if t.number not in known]
        if todo:
            for i, (value, reason, t_eval) in engine.run([t.x for t in todo]):
                t = todo[i]
                rec = opt.record(
                    t,
                    value,
                    state=FAILED if reason is not None else None,
                    reason=reason,
                    t_eval=t_eval,
                )
                _save(study, rec, history)
                results[t.number] = rec
                if callback is not None and callback(rec) is True:
                    stop = True  # the rest of the batch is still collected and stored
        for t in trials:  # tells in trial order: the next batch does not depend on timing
            r = results[t.number]
            opt.tell(t, r.value, state=r.state, reason=r.reason, t_eval=r.t_eval)
    return "stopped" if stop else "completed"


def _check_replay(study: Any, number: int, proposed: np.ndarray, stored: Any) -> None:
    s = np.asarray(stored, dtype=float)
    if s.shape != proposed.shape or not np.allclose(proposed, s, rtol=0.0, atol=REPLAY_ATOL):
        raise StudyError(
            f"study {study.path}: replay diverged at trial {number}: the optimiser now proposes "
            f"u = {proposed.tolist()} where the study stored u = {s.tolist()}; the study was "
            "made with different code or settings, or the objective was not deterministic"
        )


# ---------------------------------------------------------------------- evaluation
#: [s] how long a fresh evaluation worker may take to start (fork: milliseconds; spawn on
#: other systems: an interpreter start and the objective's imports).
_WORKER_START_LIMIT = 120.0


class _Evaluator:
    """Calls ``fun`` in-process, or in a worker process when a timeout is set."""

    def __init__(self, fun: Callable[[np.ndarray], float], timeout: float | None) -> None:
        self.fun = fun
        self.timeout = timeout
        self._proc: Any = None
        self._conn: Any = None

    def __call__(self, x: np.ndarray) -> tuple[Any, str | None, float]:
        if self.timeout is None:
            t0 = time.perf_counter()
            try:
                value = self.fun(np.array(x))
            except Exception as exc:
                return None, _describe(exc), time.perf_counter() - t0
            return value, None, time.perf_counter() - t0
        if self._proc is None or not self._proc.is_alive():
            self._start()  # not timed: the limit is on the evaluation, not on a start-up
        t0 = time.perf_counter()
        return (*self._call_worker(np.array(x)), time.perf_counter() - t0)

    def _call_worker(self, x: np.ndarray) -> tuple[Any, str | None]:
        self._conn.send(x)
        if not self._conn.poll(self.timeout):
            self._kill()
            return None, f"timeout after {self.timeout:g} s"
        try:
            kind, payload = self._conn.recv()
        except (EOFError, OSError):
            self._proc.join(5)
            code = self._proc.exitcode
            self._kill()
            return None, f"evaluation process died (exit code {code})"
        return (payload, None) if kind == "ok" else (None, payload)

    def _start(self) -> None:
        methods = multiprocessing.get_all_start_methods()
        ctx: multiprocessing.context.ForkContext | multiprocessing.context.SpawnContext
        if sys.platform.startswith("linux") and "fork" in methods:
            ctx = multiprocessing.get_context("fork")
        else:
            ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        # Not a daemon: the objective may start processes of its own (a tuning problem's
        # worker pool). close() kills the worker; if this process dies first (SIGKILL), the
        # worker sees that it was orphaned and exits (a forked child holds a copy of the
        # parent's end of the pipe, so it would never see the pipe close).
        self._proc = ctx.Process(
            target=_worker_loop, args=(self.fun, child, os.getpid()), daemon=False
        )
        self._proc.start()
        child.close()
        self._conn = parent
        if not parent.poll(_WORKER_START_LIMIT) or parent.recv() != ("ready", None):
            self._kill()
            raise RuntimeError(
                f"the evaluation worker process did not start within {_WORKER_START_LIMIT} s"
            )

    def _kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.join(5)
            self._proc = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def close(self) -> None:
        self._kill()


def _worker_loop(
    fun: Callable[[np.ndarray], float], conn: Any, parent_pid: int
) -> None:  # pragma: no cover - runs in the child process
    """Body of the evaluation worker: evaluate what arrives on ``conn`` until the pipe
    closes or the parent process ``parent_pid`` is gone (also in the middle of an
    evaluation: a hung one is what a timeout exists for, and nobody is left to read it)."""
    watch_parent(parent_pid)
    conn.send(("ready", None))
    while True:
        try:
            x = conn.recv()
        except (EOFError, OSError):
            return
        try:
            value = fun(x)
            try:
                msg: tuple[str, Any] = ("ok", float(value))
            except (TypeError, ValueError):
                msg = ("error", f"objective returned a non-number: {value!r}")
        except Exception as exc:
            msg = ("error", _describe(exc))
        conn.send(msg)


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
