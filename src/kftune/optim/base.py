"""The ask/tell core every optimiser shares (cf. Optuna's ``Study.ask``/``Study.tell``).

An optimiser proposes points in the unit cube; :class:`Optimizer` maps them to natural
units, hands them out as :class:`Trial` objects, validates what comes back, turns failures
(an exception, NaN/inf, a timeout) into ``failed`` records, and keeps the history.
:func:`kftune.minimize` is a thin loop on top::

    opt = make_optimizer("tsbo-tsp", space, seed=0)
    while not opt.done:
        trial = opt.ask()
        opt.tell(trial, fun(trial.x))          # or opt.tell(trial, state="failed", reason=…)

``ask()`` hands out one trial and refuses while one is pending (the sequential loop).
``ask(n)`` hands out a batch of up to n trials and may be called with trials pending; every
pending trial is known to the optimiser (``_pending``), so its next proposals neither
repeat nor ignore them, and ``tell`` takes results by trial number in any order::

    trials = opt.ask(4)                       # 4 distinct points, none asked before
    for trial in as_completed(trials):        # any order
        opt.tell(trial.number, fun(trial.x))

Fewer than n come back only when the budget ends or the optimiser must hear back first
(a GA or CMA-ES at the end of a generation: ``_n_proposable``). With n = 1 and tells in
ask order every optimiser proposes exactly what ``ask()`` would.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, overload

import numpy as np
from scipy.spatial import cKDTree

from kftune.errors import KftuneError
from kftune.optim.result import COMPLETE, FAILED, EvalRecord, best_record, jsonable
from kftune.space import Space

#: Distance (unit cube, max-norm) under which two points count as the same point.
SAME_POINT_ATOL = 1e-9


def coincides(points: np.ndarray, others: np.ndarray, atol: float = SAME_POINT_ATOL) -> np.ndarray:
    """(m,) True where a row of ``points`` (m, d) lies within ``atol`` (max-norm, inclusive;
    default :data:`SAME_POINT_ATOL`) of a row of ``others`` (n, d).

    A k-d tree over ``others`` answers each row with its nearest neighbour in the max-norm
    (the distances are the same |a − b| maxima a dense comparison computes, so the result
    is exact), in O(m log n) instead of the O(m·n·d) of a dense comparison."""
    if len(others) == 0 or len(points) == 0:
        return np.zeros(len(points), dtype=bool)
    dist, _ = cKDTree(others).query(points, k=1, p=np.inf)
    return np.asarray(dist <= atol)


@dataclass(frozen=True)
class Proposal:
    """What an optimiser's ``_propose`` returns.

    Attributes:
        u: (d,) point in the unit cube.
        x: optional (d,) point in natural units; when given it is evaluated as is (e.g. fixed
            manual points, which must not suffer a log10 round trip) and ``u`` is ignored.
        stage, acquisition, hyperparameters, info: bookkeeping copied into the record
            (see :class:`~kftune.optim.result.EvalRecord`).
    """

    u: np.ndarray
    x: np.ndarray | None = None
    stage: int | None = None
    acquisition: str | None = None
    hyperparameters: dict[str, Any] | None = None
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Trial:
    """A point handed out by :meth:`Optimizer.ask`, waiting for its value.

    Attributes:
        number: 0-based position in the run.
        x: (d,) point in natural units — pass this to the objective.
        u: (d,) the same point in the unit cube.
        params: ``{name: value}`` of ``x``.
        stage, acquisition, hyperparameters, info: how it was chosen.
        t_propose: [s] time ``ask`` took.
    """

    number: int
    x: np.ndarray
    u: np.ndarray
    params: dict[str, float]
    stage: int | None
    acquisition: str | None
    hyperparameters: dict[str, Any] | None
    info: dict[str, Any]
    t_propose: float


class ExhaustedError(KftuneError, RuntimeError):
    """``ask`` was called on an optimiser that has nothing left to propose."""


class Optimizer(ABC):
    """Base class of every optimiser: ask/tell bookkeeping on top of ``_propose``/``_observe``.

    Subclasses implement :meth:`_propose` (next point in the unit cube) and :meth:`_observe`
    (learn from a result; ``value is None`` means the evaluation failed) and may override
    :meth:`_exhausted`. They must draw all randomness from ``self.rng`` (or from seeds
    spawned from ``self.seed_sequence``) so that one seed reproduces a run.

    Args:
        space: the search space (anything :meth:`Space.coerce` accepts).
        budget: maximum number of evaluations (failed ones count); ``None`` → the method's
            default (``default_budget``).
        seed: drives all randomness.
    """

    #: Registry name (``kftune.minimize(method=...)``); an instance may name its variant
    #: (TSBO: ``tsbo-<surrogate>``), so not a ClassVar.
    method: str = "base"
    #: Budget used when ``budget=None``.
    default_budget: ClassVar[int] = 40
    #: True when the proposals never depend on ``budget`` (for every option): a run with
    #: budget b then equals the first b evaluations of a run with a larger budget, so a
    #: benchmark may run once and read shorter budgets as prefixes. False (the safe
    #: default) where the budget shapes the run (TSBO: MAX_SM and the stage-2 reserve; GA:
    #: the number of generations and with it the mutation schedule).
    budget_independent: ClassVar[bool] = False

    def __init__(self, space: Any, *, budget: int | None = None, seed: int = 0) -> None:
        self.space = Space.coerce(space)
        if budget is None:
            budget = self.default_budget
        if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 1:
            raise ValueError(f"budget must be a positive integer, got {budget!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.budget = int(budget)
        self.seed = int(seed)
        self.seed_sequence = np.random.SeedSequence(self.seed)
        self.rng = np.random.default_rng(self.seed_sequence.spawn(1)[0])
        self._history: list[EvalRecord] = []
        self._pending: dict[int, Trial] = {}  # asked, not told; by trial number
        self._n_asked = 0

    # ------------------------------------------------------------------ subclass hooks
    @abstractmethod
    def _propose(self) -> Proposal:
        """The next point to evaluate (only called when not :attr:`done`)."""

    @abstractmethod
    def _observe(self, trial: Trial, value: float | None) -> None:
        """Learn from the result of ``trial``; ``value is None`` ⇔ the evaluation failed."""

    def _exhausted(self) -> bool:
        """True when the optimiser has nothing left to propose (budget aside)."""
        return False

    def _n_proposable(self) -> int | None:
        """How many more points :meth:`_propose` can give before it must hear back (None:
        no limit). Only consulted by ``ask(n)``; e.g. the rest of a GA generation."""
        return None

    def options(self) -> dict[str, Any]:
        """The settings that define this optimiser's behaviour (stored with a study and
        compared on resume); subclasses extend it."""
        return {}

    # ------------------------------------------------------------------ public API
    @property
    def done(self) -> bool:
        """True once the budget is used or the optimiser is exhausted."""
        return self._n_asked >= self.budget or self._exhausted()

    @property
    def history(self) -> tuple[EvalRecord, ...]:
        """Every told evaluation, in order."""
        return tuple(self._history)

    @property
    def n_evals(self) -> int:
        """Number of told evaluations."""
        return len(self._history)

    @property
    def best(self) -> EvalRecord | None:
        """The best completed evaluation so far (None before the first success)."""
        return best_record(self._history)

    @property
    def pending(self) -> Trial | None:
        """The oldest trial handed out by :meth:`ask` and not told yet (None: none)."""
        return self._pending[min(self._pending)] if self._pending else None

    @property
    def pending_trials(self) -> tuple[Trial, ...]:
        """Every trial asked and not told yet, by number."""
        return tuple(self._pending[k] for k in sorted(self._pending))

    @overload
    def ask(self, n: None = None) -> Trial: ...

    @overload
    def ask(self, n: int) -> list[Trial]: ...

    def ask(self, n: int | None = None) -> Trial | list[Trial]:
        """Propose the next point (``ask()``), or a batch of up to n points (``ask(n)``).

        ``ask()`` returns one :class:`Trial` and refuses while a trial is pending.
        ``ask(n)`` returns a list of up to n trials, distinct and none at an asked point,
        also while trials are pending (see the module docstring); fewer than n only when
        the budget ends or the optimiser must hear back first (``_n_proposable``).

        Raises:
            RuntimeError: ``ask()`` while a trial is still pending (tell it first).
            ExhaustedError: the budget is used or nothing is left to propose.
            ValueError: n is not a positive integer.
        """
        if n is None:
            waiting = self.pending
            if waiting is not None:
                raise RuntimeError(
                    f"trial {waiting.number} is still pending: tell its result before "
                    "asking for another point (or ask for a batch with ask(n))"
                )
            self._check_not_done()
            return self._ask_one()
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"n must be a positive integer, got {n!r}")
        self._check_not_done()
        cap = self._n_proposable()
        if cap is not None and cap < 1:
            raise RuntimeError(
                f"{self.method} must hear back first: tell the pending trials "
                f"{[t.number for t in self.pending_trials]} before asking again"
            )
        limit = int(n) if cap is None else min(int(n), cap)
        trials: list[Trial] = []
        while len(trials) < limit and not self.done:
            trials.append(self._ask_one())
        return trials

    def _pending_u(self) -> np.ndarray:
        """(p, d) the pending trials' points in the unit cube (p = 0 in sequential use)."""
        return np.array([t.u for t in self.pending_trials]).reshape(-1, self.space.dim)

    def _check_not_done(self) -> None:
        if self.done:
            raise ExhaustedError(
                f"{self.method}: nothing left to propose "
                f"({self._n_asked} of budget {self.budget} asked)"
            )

    def _ask_one(self) -> Trial:
        """Propose one point and register it as pending."""
        t0 = time.perf_counter()
        prop = self._propose()
        t_propose = time.perf_counter() - t0
        if prop.x is not None:
            x = np.array(prop.x, dtype=float).reshape(self.space.dim)
            u = np.clip(self.space.to_unit(x), 0.0, 1.0)
        else:
            u = np.asarray(prop.u, dtype=float).reshape(self.space.dim)
            if not np.all(np.isfinite(u)):
                raise RuntimeError(f"{self.method} proposed a non-finite point {u}")
            u = np.clip(u, 0.0, 1.0)
            x = self.space.from_unit(u)
        u.setflags(write=False)
        x.setflags(write=False)
        trial = Trial(
            number=self._n_asked,
            x=x,
            u=u,
            params=self.space.as_dict(x),
            stage=prop.stage,
            acquisition=prop.acquisition,
            hyperparameters=jsonable(prop.hyperparameters),
            info=jsonable(dict(prop.info)),
            t_propose=t_propose,
        )
        self._pending[trial.number] = trial
        self._n_asked += 1
        return trial

    def tell(
        self,
        trial: Trial | int | Any,
        value: float | None = None,
        *,
        state: str | None = None,
        reason: str | None = None,
        t_eval: float = 0.0,
    ) -> EvalRecord:
        """Report the result of a pending trial (pending trials may be told in any order).

        Args:
            trial: the :class:`Trial`, its number, or its point ``x`` in natural units.
            value: the objective value. ``None``, NaN or ±inf make the evaluation failed.
            state: ``"complete"`` (default when a value is given) or ``"failed"``.
            reason: why it failed (kept in the record).
            t_eval: [s] how long the evaluation took (kept in the record).

        Returns:
            The :class:`EvalRecord` appended to :attr:`history`.
        """
        if state not in (None, COMPLETE, FAILED):
            raise ValueError(f"state must be {COMPLETE!r} or {FAILED!r}, got {state!r}")
        pending = self._resolve(trial)
        rec = self.record(pending, value, state=state, reason=reason, t_eval=t_eval)
        self._observe(pending, rec.value)
        self._history.append(rec)
        return rec

    def record(
        self,
        trial: Trial,
        value: float | None = None,
        *,
        state: str | None = None,
        reason: str | None = None,
        t_eval: float = 0.0,
    ) -> EvalRecord:
        """The :class:`EvalRecord` that :meth:`tell` would append for this result, without
        telling it (a parallel loop stores a result when it arrives and tells the optimiser
        later, in trial order). Same arguments as :meth:`tell`."""
        if state not in (None, COMPLETE, FAILED):
            raise ValueError(f"state must be {COMPLETE!r} or {FAILED!r}, got {state!r}")
        val: float | None = None
        if state == FAILED:
            reason = reason or "failed"
        elif value is None:
            state, reason = FAILED, reason or "no value reported"
        else:
            try:
                val = float(value)
            except (TypeError, ValueError):
                state, reason = FAILED, f"objective returned a non-number: {value!r}"
            else:
                if math.isfinite(val):
                    state, reason = COMPLETE, None
                else:
                    state, reason, val = FAILED, f"non-finite value {val}", None
        return EvalRecord(
            number=trial.number,
            x=tuple(float(v) for v in trial.x),
            u=tuple(float(v) for v in trial.u),
            params=dict(trial.params),
            value=val,
            state=state,
            reason=reason,
            stage=trial.stage,
            acquisition=trial.acquisition,
            hyperparameters=trial.hyperparameters,
            t_propose=float(trial.t_propose),
            t_eval=float(t_eval),
            info=trial.info,
        )

    def _resolve(self, trial: Trial | int | Any) -> Trial:
        """Find the pending trial meant by ``trial`` and take it off the pending list
        (before ``_observe``, which then sees only the trials still in flight)."""
        if not self._pending:
            raise RuntimeError("no trial is pending: call ask() before tell()")
        found: Trial | None = None
        if isinstance(trial, Trial):
            found = self._pending.get(trial.number)
        elif isinstance(trial, (int, np.integer)) and not isinstance(trial, bool):
            found = self._pending.get(int(trial))
        else:
            xa = np.asarray(trial, dtype=float)
            for p in self.pending_trials:
                if xa.shape == p.x.shape and bool(np.allclose(xa, p.x, rtol=1e-12, atol=0.0)):
                    found = p
                    break
        if found is None:
            numbers = [p.number for p in self.pending_trials]
            raise ValueError(
                f"tell() got {trial!r}, which is not the pending trial (pending: {numbers}; "
                f"x = {self.pending_trials[0].x.tolist()})"
            )
        del self._pending[found.number]
        return found
