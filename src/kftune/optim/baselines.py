"""The simplest baselines: uniform random search and fixed ("manual") points."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from kftune.optim.base import Optimizer, Proposal, Trial


class RandomSearch(Optimizer):
    """Independent uniform samples in the unit cube (log-uniform on log10 parameters).

    Failures need no special handling: the next point never depends on past values, and a
    repeat of a failed point has probability zero.
    """

    method: str = "random"
    default_budget: ClassVar[int] = 40
    budget_independent: ClassVar[bool] = True

    def _propose(self) -> Proposal:
        return Proposal(u=self.rng.random(self.space.dim), acquisition="uniform")

    def _observe(self, trial: Trial, value: float | None) -> None:
        pass


class ManualPoints(Optimizer):
    """Evaluates fixed points given in natural units — the paper's "manual tuning" row.

    Args:
        points: (k, d) or (d,) points in natural units, each inside the space; default: the
            centre of the unit cube (the geometric centre on log10 parameters).
        budget: defaults to the number of points; a larger budget does not add evaluations
            (the optimiser is exhausted after the last point).
    """

    method: str = "manual"
    default_budget: ClassVar[int] = 1
    budget_independent: ClassVar[bool] = True

    def __init__(
        self,
        space: Any,
        *,
        points: Any = None,
        budget: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(space, budget=budget, seed=seed)
        if points is None:
            pts = self.space.centre()[None, :]
        else:
            if any(isinstance(v, (bool, np.bool_)) for v in np.ravel(np.asarray(points, object))):
                raise ValueError(f"points must be numbers, not true/false; got {points!r}")
            pts = np.atleast_2d(np.asarray(points, dtype=float))
        if pts.ndim != 2 or pts.shape[1] != self.space.dim or pts.shape[0] == 0:
            raise ValueError(
                f"points must have shape (k, {self.space.dim}) in natural units for parameters "
                f"{list(self.space.names)}, got {np.shape(points)}"
            )
        for i, p in enumerate(pts):
            if not np.all(np.isfinite(p)) or not self.space.contains(p):
                raise ValueError(
                    f"manual point {i} = {p.tolist()} lies outside the search space "
                    f"(bounds {self.space.lows.tolist()} .. {self.space.highs.tolist()})"
                )
        self.points = pts
        if budget is None:
            self.budget = len(pts)

    def options(self) -> dict[str, Any]:
        return {"points": self.points.tolist()}

    def _exhausted(self) -> bool:
        return self._n_asked >= len(self.points)

    def _propose(self) -> Proposal:
        x = self.points[self._n_asked]
        return Proposal(u=self.space.to_unit(x), x=x, acquisition="fixed")

    def _observe(self, trial: Trial, value: float | None) -> None:
        pass
