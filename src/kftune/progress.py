"""Progress of a run, fed by :func:`kftune.minimize`'s callback.

On a terminal, a tqdm bar on stderr: evaluations done out of the budget, the optimiser's
stage and acquisition rule, the best cost so far and the time per evaluation. Off a
terminal (a log file, nohup, CI), where a bar's carriage returns would garble the log,
plain lines instead, one every :data:`PLAIN_FRACTION` of the budget or every
:data:`PLAIN_INTERVAL` seconds, whichever is rarer, plus the first and the last: done/total,
best cost, failures, elapsed time and an estimate of the time left. The estimate leaves out
the first evaluation, which includes compiling the filter. ``--json`` and ``--quiet`` turn
both off, so stdout and logs stay clean.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, TextIO

from tqdm.auto import tqdm

from kftune.optim.result import EvalRecord

#: Off a terminal, a line at most every this share of the budget …
PLAIN_FRACTION = 0.1
#: … and at most every this many seconds [s] (whichever is rarer).
PLAIN_INTERVAL = 30.0


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def announce(note: str | None, enabled: bool | None = None) -> None:
    """Print ``note`` (e.g. that the next evaluation compiles the filter) on stderr, on a
    terminal or not, unless progress is off (``enabled`` False) or there is no note."""
    if note and enabled is not False:
        print(note, file=sys.stderr, flush=True)


class ProgressBar:
    """Callable for ``minimize(..., callback=ProgressBar(...))``; use as a context manager.

    Args:
        total: the evaluation budget.
        desc: label in front of the bar or line (e.g. the method).
        enabled: False forces all progress off; True forces the bar; None: a bar when
            stderr is a terminal, plain lines otherwise.
        note: printed once before the first evaluation (e.g. that it compiles the filter),
            unless ``enabled`` is False.
        interval: [s] the least time between two plain lines (default
            :data:`PLAIN_INTERVAL`).
    """

    def __init__(
        self,
        total: int,
        desc: str,
        enabled: bool | None = None,
        note: str | None = None,
        interval: float = PLAIN_INTERVAL,
    ) -> None:
        self.best = math.inf
        self.failed = 0
        self.total = total
        self.desc = desc
        self._stream: TextIO = sys.stderr
        terminal = _is_terminal(self._stream)
        self._plain = enabled is None and not terminal
        self._interval = interval
        self._step = max(1, math.ceil(PLAIN_FRACTION * total))
        self._done = 0
        self._shown = 0  # evaluations done at the last plain line
        self._t_start = time.monotonic()
        self._t_shown = self._t_start
        self._t_first: float | None = None  # when the first evaluation finished
        announce(note, enabled)
        self._bar = tqdm(
            total=total,
            desc=desc,
            unit="eval",
            disable=not (enabled is True or (enabled is None and terminal)),
            dynamic_ncols=True,
            leave=True,
            file=self._stream,
        )

    def __call__(self, rec: EvalRecord) -> None:
        if rec.ok and rec.value is not None:
            self.best = min(self.best, rec.value)
        else:
            self.failed += 1
        self._done += 1
        if self._plain:
            now = time.monotonic()
            if self._t_first is None:
                self._t_first = now
                self._line(now)
            elif self._done - self._shown >= self._step and now - self._t_shown >= self._interval:
                self._line(now)
            return
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

    def _line(self, now: float) -> None:
        """One plain progress line: done/total, best, failures, elapsed and time left."""
        self._shown, self._t_shown = self._done, now
        best = "none yet" if math.isinf(self.best) else f"{self.best:.5g}"
        parts = [
            f"{self.desc}: {self._done}/{self.total} evaluations",
            f"best cost {best}",
            *([f"{self.failed} failed"] if self.failed else []),
            f"elapsed {tqdm.format_interval(now - self._t_start)}",
        ]
        left = self.total - self._done
        if left > 0:
            after_first = self._done - 1  # the first includes the compile: not a rate
            if self._t_first is not None and after_first > 0:
                eta = (now - self._t_first) / after_first * left
                parts.append(f"ETA {tqdm.format_interval(eta)}")
            else:
                parts.append("ETA after the next evaluation")
        print(", ".join(parts), file=self._stream, flush=True)

    def close(self) -> None:
        """Finish the bar, or print the last plain line if not shown yet."""
        if self._plain and self._done > self._shown:
            self._line(time.monotonic())
        self._bar.close()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
