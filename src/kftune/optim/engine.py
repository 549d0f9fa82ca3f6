"""Evaluation engines: who evaluates a batch of points for :func:`kftune.minimize`.

An engine takes the points of one batch (``ask(q)``) and yields each point's outcome as it
finishes, in whatever order they finish::

    for i, (value, reason, t_eval) in engine.run(points):
        ...   # point i: its value (None when it failed), why it failed, [s] it took

* :class:`SerialEngine` — in this process, one point after another (a tuning problem's
  batch goes through its vectorised batch kernel, :meth:`TuningProblem.evaluate_batch`);
  no dependency, the reference the distributed engine is compared against.
* :class:`kftune.optim.dask_engine.DaskEngine` — on a Dask cluster (local processes or a
  scheduler address), behind the ``dask`` extra.

Outcomes equal those of the sequential loop for the same point bit for bit: the objective
is the same deterministic function, a failure (an exception, a non-number) becomes a
reason string exactly as :func:`kftune.minimize` writes it.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from kftune.errors import RunFailedError

#: What an engine reports for one point: (value or None, failure reason or None, t_eval [s]).
Outcome = tuple[Any, str | None, float]


class EngineLostError(RunFailedError):
    """The engine can evaluate no more (a Dask scheduler went away): a run-time failure,
    exit code 1. Every evaluation finished before is stored; :func:`kftune.minimize` sets
    ``.result`` to the partial run (as for Ctrl-C), so that a caller can say what was kept.
    """

    result: Any = None


class Engine(ABC):
    """Evaluates batches of points; :attr:`workers` says how many run at once."""

    #: How many evaluations the engine runs at the same time (the default batch size).
    workers: int = 1

    @abstractmethod
    def run(self, points: Sequence[np.ndarray]) -> Iterator[tuple[int, Outcome]]:
        """Evaluate ``points``; yield ``(index, outcome)`` for each as it finishes."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release what the engine holds (workers, a cluster connection)."""

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def evaluate_point(fun: Callable[[np.ndarray], float], x: np.ndarray) -> Outcome:
    """Call ``fun(x)`` and turn an exception or a non-number into a failure reason (as the
    sequential loop does)."""
    t0 = time.perf_counter()
    try:
        value = fun(np.array(x))
    except Exception as exc:
        return None, describe(exc), time.perf_counter() - t0
    t = time.perf_counter() - t0
    try:
        return float(value), None, t
    except (TypeError, ValueError):
        return None, f"objective returned a non-number: {value!r}", t


def describe(exc: BaseException) -> str:
    """``"TypeName: message"`` of an exception (the reason a failed evaluation records)."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class SerialEngine(Engine):
    """Evaluates in this process. A :class:`~kftune.tuning.problem.TuningProblem` (anything
    with ``evaluate_batch``) gets its batch in one call of its vectorised kernel, which
    equals evaluating the points one by one bit for bit."""

    workers = 1

    def __init__(self, fun: Callable[[np.ndarray], float]) -> None:
        self.fun = fun

    def run(self, points: Sequence[np.ndarray]) -> Iterator[tuple[int, Outcome]]:
        batch = getattr(self.fun, "evaluate_batch", None)
        if batch is not None and len(points) > 1:
            t0 = time.perf_counter()
            try:
                results = batch(np.array(points))
            except Exception:  # e.g. a channel that cannot be scored: point by point
                results = None
            if results is not None:
                t = (time.perf_counter() - t0) / len(points)
                for i, res in enumerate(results):
                    if isinstance(res, BaseException):
                        yield i, (None, describe(res), t)
                    else:
                        yield i, (float(res.cost), None, t)
                return
        for i, x in enumerate(points):
            yield i, evaluate_point(self.fun, x)
