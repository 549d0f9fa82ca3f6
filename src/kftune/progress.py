"""A tqdm progress bar fed by :func:`kftune.minimize`'s callback.

Shows evaluations done out of the budget, the optimiser's stage and acquisition rule, the
best cost so far and the time per evaluation. Writes to stderr and switches itself off
when stderr is not a terminal (tqdm's ``disable=None``), so logs and ``--json`` output stay
clean.
"""

from __future__ import annotations

import math
from typing import Any

from tqdm.auto import tqdm

from kftune.optim.result import EvalRecord


class ProgressBar:
    """Callable for ``minimize(..., callback=ProgressBar(...))``; use as a context manager.

    Args:
        total: the evaluation budget.
        desc: label in front of the bar (e.g. the method).
        enabled: False forces the bar off; None lets tqdm decide (on when a terminal).
    """

    def __init__(self, total: int, desc: str, enabled: bool | None = None) -> None:
        self.best = math.inf
        self.failed = 0
        self._bar = tqdm(
            total=total,
            desc=desc,
            unit="eval",
            disable=None if enabled is None else not enabled,
            dynamic_ncols=True,
            leave=True,
        )

    def __call__(self, rec: EvalRecord) -> None:
        if rec.ok and rec.value is not None:
            self.best = min(self.best, rec.value)
        else:
            self.failed += 1
        post: dict[str, Any] = {}
        if rec.stage is not None:
            post["stage"] = rec.stage
        if rec.acquisition:
            post["af"] = rec.acquisition
        post["best"] = f"{self.best:.4g}"
        post["ms/eval"] = f"{1e3 * (rec.t_eval + rec.t_propose):.0f}"
        if self.failed:
            post["failed"] = self.failed
        self._bar.set_postfix(post, refresh=False)
        self._bar.update(1)

    def close(self) -> None:
        """Finish the bar."""
        self._bar.close()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
