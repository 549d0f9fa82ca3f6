"""Helpers for the processes kftune starts (the evaluation worker of a timed run, the pool
that runs a cost evaluation's manoeuvres in parallel): Ctrl-C is the parent's business, and
a worker whose parent is gone exits instead of living on.

Why a worker would live on: a pool worker waits on a queue whose write end it holds itself
(``multiprocessing`` pickles both ends into a spawned child), so the parent's death never
reaches it as an end of file; it must notice by itself.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator

#: [s] how often a worker checks that its parent is still alive.
ORPHAN_POLL = 0.5


def _exit_when_orphaned(parent_pid: int) -> None:  # pragma: no cover - runs in workers
    """End the process as soon as the parent ``parent_pid`` is gone (its parent changes
    when it is re-parented), also in the middle of a task: nobody is left to read it."""
    while os.getppid() == parent_pid:
        time.sleep(ORPHAN_POLL)
    os._exit(0)


def watch_parent(parent_pid: int) -> None:  # pragma: no cover - runs in workers
    """In a worker: ignore Ctrl-C (the parent stops the run and the workers) and start a
    daemon thread that ends the process when the parent ``parent_pid`` is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), daemon=True).start()


@contextlib.contextmanager
def sigint_blocked() -> Iterator[None]:
    """Block SIGINT in the calling thread while the body runs. Processes started inside
    inherit the blocked signal through ``fork`` and ``exec``, so a Ctrl-C that arrives
    while a spawned worker is still importing (before :func:`watch_parent` runs) cannot
    print its ``KeyboardInterrupt`` traceback; this process gets the signal when the body
    ends. No-op where signal masks do not exist (Windows)."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - Windows
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
