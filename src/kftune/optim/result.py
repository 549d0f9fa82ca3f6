"""What an optimisation run leaves behind: one :class:`EvalRecord` per evaluation and the
:class:`OptimizeResult` (cf. scikit-optimize: a named object with x, fun and the history,
never a bare tuple)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: States of an evaluation. ``running`` exists only in a study (proposal written, result not
#: yet arrived); records handed to callers are always ``complete`` or ``failed``.
COMPLETE = "complete"
FAILED = "failed"
RUNNING = "running"


@dataclass(frozen=True)
class EvalRecord:
    """One evaluation of the objective.

    Attributes:
        number: 0-based position in the run.
        x: (d,) point in natural units, as a tuple.
        u: (d,) the same point in the unit cube.
        params: ``{name: value}`` in natural units.
        value: objective value, ``None`` when the evaluation failed.
        state: ``"complete"`` or ``"failed"``.
        reason: why it failed (exception text, "non-finite value nan", "timeout after 5 s").
        stage: which stage of the optimiser proposed it (TSBO: 1 fast exploration, 2 pure
            exploitation; GA: the generation; ``None`` where the notion does not exist).
        acquisition: the rule that chose it (TSBO: ``"centre"``, ``"EI"``, ``"CBM"``,
            ``"EI-fallback"``…; GA: ``"initial"``, ``"crossover"``, ``"mutation"``…).
        hyperparameters: surrogate hyperparameters used to choose it (natural units), or None.
        t_propose: [s] wall time the optimiser spent proposing it (``ask``).
        t_eval: [s] wall time the evaluation took.
        info: extra method-specific details (JSON-serialisable).
    """

    number: int
    x: tuple[float, ...]
    u: tuple[float, ...]
    params: dict[str, float]
    value: float | None
    state: str
    reason: str | None = None
    stage: int | None = None
    acquisition: str | None = None
    hyperparameters: dict[str, Any] | None = None
    t_propose: float = 0.0
    t_eval: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True for a completed evaluation with a finite value."""
        return self.state == COMPLETE and self.value is not None

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (strict JSON: no NaN/inf)."""
        return {
            "number": self.number,
            "x": list(self.x),
            "u": list(self.u),
            "params": dict(self.params),
            "value": self.value,
            "state": self.state,
            "reason": self.reason,
            "stage": self.stage,
            "acquisition": self.acquisition,
            "hyperparameters": jsonable(self.hyperparameters),
            "t_propose": self.t_propose,
            "t_eval": self.t_eval,
            "info": jsonable(self.info),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EvalRecord:
        """Inverse of :meth:`to_dict`."""
        return cls(
            number=int(d["number"]),
            x=tuple(float(v) for v in d["x"]),
            u=tuple(float(v) for v in d["u"]),
            params={str(k): float(v) for k, v in d["params"].items()},
            value=None if d["value"] is None else float(d["value"]),
            state=str(d["state"]),
            reason=d.get("reason"),
            stage=d.get("stage"),
            acquisition=d.get("acquisition"),
            hyperparameters=d.get("hyperparameters"),
            t_propose=float(d.get("t_propose", 0.0)),
            t_eval=float(d.get("t_eval", 0.0)),
            info=dict(d.get("info") or {}),
        )


@dataclass(frozen=True)
class OptimizeResult:
    """The outcome of :func:`kftune.minimize`.

    Attributes:
        x: (d,) best point found in natural units (``None`` if every evaluation failed).
        fun: objective value at ``x`` (``None`` if every evaluation failed).
        params: ``{name: value}`` of ``x``.
        n_evals: number of evaluations made (failed ones included).
        n_failed: how many of them failed.
        method: optimiser name (e.g. ``"tsbo-tsp"``).
        seed: the seed that drove all randomness.
        budget: the evaluation budget the run was given.
        status: ``"completed"`` (budget used), ``"exhausted"`` (optimiser had nothing left to
            propose), ``"stopped"`` (the callback asked to stop) or ``"interrupted"``.
        space: the search space as a dict (see :meth:`Space.to_dict`).
        options: the method options the run used.
        history: every evaluation, in order.
        best_number: ``number`` of the best record (``None`` if none succeeded).
    """

    x: np.ndarray | None
    fun: float | None
    params: dict[str, float] | None
    n_evals: int
    n_failed: int
    method: str
    seed: int
    budget: int
    status: str
    space: dict[str, Any]
    options: dict[str, Any]
    history: tuple[EvalRecord, ...]
    best_number: int | None

    @classmethod
    def from_history(
        cls,
        history: list[EvalRecord] | tuple[EvalRecord, ...],
        *,
        method: str,
        seed: int,
        budget: int,
        status: str,
        space: dict[str, Any],
        options: dict[str, Any],
    ) -> OptimizeResult:
        """Build a result, picking the best completed record (first one on ties)."""
        best = best_record(history)
        return cls(
            x=None if best is None else np.array(best.x),
            fun=None if best is None else best.value,
            params=None if best is None else dict(best.params),
            n_evals=len(history),
            n_failed=sum(1 for r in history if r.state == FAILED),
            method=method,
            seed=seed,
            budget=budget,
            status=status,
            space=space,
            options=options,
            history=tuple(history),
            best_number=None if best is None else best.number,
        )

    @property
    def values(self) -> np.ndarray:
        """(n_evals,) objective values, NaN where an evaluation failed."""
        return np.array([np.nan if r.value is None else r.value for r in self.history])

    @property
    def best_so_far(self) -> np.ndarray:
        """(n_evals,) running minimum of the completed values (inf before the first success)."""
        v = np.where(np.isnan(self.values), np.inf, self.values)
        return np.minimum.accumulate(v) if v.size else v

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (strict JSON)."""
        return {
            "x": None if self.x is None else [float(v) for v in self.x],
            "fun": self.fun,
            "params": self.params,
            "n_evals": self.n_evals,
            "n_failed": self.n_failed,
            "method": self.method,
            "seed": self.seed,
            "budget": self.budget,
            "status": self.status,
            "space": self.space,
            "options": jsonable(self.options),
            "best_number": self.best_number,
            "history": [r.to_dict() for r in self.history],
        }

    def to_json(self, **kwargs: Any) -> str:
        """:meth:`to_dict` as a JSON string (``allow_nan=False``: strict JSON)."""
        return json.dumps(self.to_dict(), allow_nan=False, **kwargs)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> OptimizeResult:
        """Inverse of :meth:`to_dict`."""
        return cls(
            x=None if d["x"] is None else np.array(d["x"], dtype=float),
            fun=d["fun"],
            params=d["params"],
            n_evals=int(d["n_evals"]),
            n_failed=int(d["n_failed"]),
            method=str(d["method"]),
            seed=int(d["seed"]),
            budget=int(d["budget"]),
            status=str(d["status"]),
            space=d["space"],
            options=d["options"],
            history=tuple(EvalRecord.from_dict(r) for r in d["history"]),
            best_number=d["best_number"],
        )

    def __repr__(self) -> str:
        return (
            f"OptimizeResult(method={self.method!r}, fun={self.fun!r}, params={self.params!r}, "
            f"n_evals={self.n_evals}, n_failed={self.n_failed}, status={self.status!r})"
        )


def best_record(history: list[EvalRecord] | tuple[EvalRecord, ...]) -> EvalRecord | None:
    """The completed record with the smallest value (the earliest one on ties)."""
    best: EvalRecord | None = None
    best_value = math.inf
    for r in history:
        if r.ok and r.value is not None and (best is None or r.value < best_value):
            best, best_value = r, r.value
    return best


def jsonable(obj: Any) -> Any:
    """Recursively turn numpy scalars/arrays into plain Python for strict JSON; a non-finite
    float becomes the string ``"inf"``, ``"-inf"`` or ``"nan"`` (e.g. a GP's dof = inf)."""
    if obj is None or isinstance(obj, (str, bool, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, np.ndarray):
        return [jsonable(v) for v in obj.tolist()]
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return str(obj)
