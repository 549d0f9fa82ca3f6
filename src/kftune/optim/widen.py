"""Widening the search box when the best point ends on one of its bounds.

A best point on a bound of the box says the optimum may lie beyond it (revs-250lm: q_r at
the paper's upper bound 1). :func:`minimize_widening` runs an optimiser and, while the best
point found so far lies within 1 % of a bound of a log10 parameter
(:meth:`~kftune.space.Space.on_bounds`), moves that bound outwards by ``decades`` (default
two: [1e-10, 1] becomes [1e-10, 100]) and runs the optimiser again, with the same budget, on
the wider box — a follow-up run — at most ``rounds`` times (default 3). Linear parameters
are reported by ``on_bounds`` but never widened (their bounds are often physical limits).

Nothing finished is lost, and the whole is resumable: every round is an ordinary run with
its own study file (``study.db``, then ``study.widen1.db``, ``study.widen2.db`` …), and the
best point of the finished rounds decides the next box, so a resumed run replays the same
rounds in the same order from their studies.

The result merges the rounds: their evaluations in order (numbered on; each record's
``info["widen_round"]`` says which round, its ``u`` is re-expressed in the final box), the
best over all rounds, the final box as ``space`` and the rounds' budgets summed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from kftune.optim.engine import EngineLostError
from kftune.optim.minimize import OptimizationInterrupted
from kftune.optim.result import EvalRecord, OptimizeResult
from kftune.space import Space

#: Decades a bound of a log10 parameter moves out per widening.
WIDEN_DECADES = 2.0
#: Follow-up runs at most.
WIDEN_ROUNDS = 3


def round_storage(storage: str | os.PathLike[str] | None, k: int) -> Path | None:
    """The study file of round ``k``: ``storage`` itself for round 0, else
    ``<stem>.widen<k><suffix>`` beside it (``None`` without storage)."""
    if storage is None:
        return None
    p = Path(storage)
    return p if k == 0 else p.with_name(f"{p.stem}.widen{k}{p.suffix}")


def minimize_widening(
    run: Callable[[Space, Path | None], OptimizeResult],
    space: Any,
    *,
    storage: str | os.PathLike[str] | None = None,
    rounds: int = WIDEN_ROUNDS,
    decades: float = WIDEN_DECADES,
    fixed: Collection[str] = (),
) -> OptimizeResult:
    """Run, and run again on a widened box while the best point lies on a bound.

    Args:
        run: ``run(space, study_file)`` makes one round (e.g. a :func:`kftune.minimize`
            call with ``storage=study_file`` and ``resume=True``) and returns its result.
        space: the initial search space.
        storage: the first round's study file; the others lie beside it
            (:func:`round_storage`); ``None``: no studies.
        rounds: follow-up runs at most.
        decades: how far a bound moves per widening (log10 parameters).
        fixed: parameters whose box is never widened (a model's physical parameters, whose
            plausible range two decades would leave).

    Returns:
        The merged :class:`OptimizeResult` (see the module docstring).

    Raises:
        OptimizationInterrupted: Ctrl-C in any round; ``.result`` merges what finished.
        EngineLostError: the engine was lost in any round; ``.result`` as for Ctrl-C.
    """
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 0:
        raise ValueError(f"rounds must be a non-negative integer, got {rounds!r}")
    sp = Space.coerce(space)
    results: list[OptimizeResult] = []
    for k in range(rounds + 1):
        if results:
            best = merge(results, sp, results[-1].status)
            if best.x is None or best.status == "stopped":
                break
            hits = [h for h in sp.on_bounds(sp.to_unit(best.x)) if h.name not in fixed]
            wider = sp.widened(hits, decades)
            if wider is sp:
                break
            sp = wider
        try:
            results.append(run(sp, round_storage(storage, k)))
        except OptimizationInterrupted as stop:
            partial = merge([*results, stop.result], sp, "interrupted")
            raise OptimizationInterrupted(partial) from None
        except EngineLostError as lost:
            lost.result = merge([*results, lost.result], sp, "interrupted")
            raise
    return merge(results, sp, results[-1].status)


def merge(results: list[OptimizeResult], space: Space, status: str) -> OptimizeResult:
    """One result from consecutive rounds, expressed in ``space`` (the widest box)."""
    history: list[EvalRecord] = []
    for k, res in enumerate(results):
        for r in res.history:
            history.append(
                dataclasses.replace(
                    r,
                    number=len(history),
                    u=tuple(float(v) for v in space.to_unit(r.x)),
                    info={**r.info, "widen_round": k},
                )
            )
    first = results[0]
    return OptimizeResult.from_history(
        history,
        method=first.method,
        seed=first.seed,
        budget=sum(r.budget for r in results),
        status=status,
        space=space.to_dict(),
        options=first.options,
    )
