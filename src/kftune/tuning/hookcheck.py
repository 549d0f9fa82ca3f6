"""A model file's hooks run first where they can do no harm: in a child process, checked.

A model file's hooks are the user's compiled code, and two of their faults cannot be caught
in the process that tunes:

* an index beyond an array, in some states only: compiled code does not check bounds, so
  the write lands in other memory — silently, or as a glibc abort ("corrupted size"). The
  first-sample probe (:meth:`~kftune.models.StateSpaceModel.probe`) sees it only where
  it happens at the prior mean;
* a loop that never ends: a compiled loop does not see Ctrl-C or SIGTERM, so only SIGKILL
  would stop the command.

So, before a filter relies on them, :func:`check_model_file` runs them in a child process
(spawned: a fresh interpreter, which compiles everything anew): the first-sample probe,
then the filter over each manoeuvre with every compiled function of the model file
recompiled with numba's bounds check (:func:`~kftune.models.user.checked_model`). The
parent waits for it in a way that Ctrl-C and SIGTERM interrupt, and kills it then; a
child that dies (a native crash in a hook) is reported, naming the manoeuvre. The tuned
runs themselves stay unchecked: a checked run is about twice as slow.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from kftune.errors import ConfigError, DataWarning
from kftune.filters import UKFSettings
from kftune.models.base import HOOK_ARGUMENTS
from kftune.processes import sigint_blocked, watch_parent

__all__ = ["HookRun", "check_model_file"]

#: One manoeuvre to check on: (name, u (N, n_u) or None, z (N, m), dt [s]).
HookRun = tuple[str, "np.ndarray | None", np.ndarray, float]

#: [s] after this long without a word from the checking process, a warning says why the
#: command waits (a compile takes seconds; a hook that never returns, for ever).
SLOW_CHECK = 120.0
#: The order in which the hooks are checked one at a time to name the one at fault.
_ORDER = ("prepare", "f", "h", "F", "H", "check")


def check_model_file(
    spec: str,
    filter: str,
    runs: Sequence[HookRun],
    params: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
) -> None:
    """Run the hooks of the model file ``spec`` in a child process: the first-sample probe
    and a bounds-checked run of ``filter`` (``"ukf"``/``"ekf"``) with process-noise
    variances ``q``, measurement-noise variances ``r`` and (a UKF) the sigma-point
    ``settings`` of the filter that will run, over each of ``runs``.

    Raises:
        ValueError: naming the manoeuvre, the hook and what it did (a probe's message, an
            index out of bounds, a crash of the process that ran it).
        KeyboardInterrupt: Ctrl-C or SIGTERM while it runs (the child is killed).
    """
    ctx = multiprocessing.get_context("spawn")
    conn, theirs = ctx.Pipe()
    # the data go through the pipe, not with the start: multiprocessing writes a start's
    # arguments with the child's end of that pipe still open here, so a child that died
    # while starting would leave a large write blocked for ever
    args = (theirs, spec, filter, params, q, r, settings, os.getpid())
    with sigint_blocked():  # a Ctrl-C while the child starts is the parent's alone
        child = ctx.Process(target=_check, args=args, daemon=True)
        child.start()
    theirs.close()
    at = runs[0][0] if runs else "?"
    try:
        try:  # Ctrl-C and SIGTERM interrupt the waits
            conn.send(list(runs))
            slow = False
            while True:
                if not slow and not conn.poll(SLOW_CHECK):
                    slow = True  # say why nothing happens (a hook that never returns?)
                    warnings.warn(
                        f"model {spec}: the process that checks its hooks has run for "
                        f"{SLOW_CHECK:g} s, on manoeuvre {at!r} (a large model compiles for "
                        "minutes); a hook that never returns is stopped by Ctrl-C or SIGTERM",
                        DataWarning,
                        stacklevel=2,
                    )
                kind, payload = conn.recv()
                if kind == "at":
                    at = payload
                elif kind == "error":
                    raise ValueError(f"on manoeuvre {at!r}: {payload}")
                else:
                    return
        except (EOFError, OSError):  # it died (BrokenPipeError: before it read the runs)
            child.join()
            raise ValueError(f"on manoeuvre {at!r}: {_died(child.exitcode)}") from None
    finally:
        conn.close()
        if child.is_alive():
            child.kill()
        child.join()


def _died(code: int | None) -> str:
    """Why the checking process ended without a word, in words."""
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        how = f"was killed by {name}"
    else:
        how = f"ended with exit code {code}"
    return (
        f"the process that ran the model's hooks {how}: a hook that writes beyond an array "
        "(compiled code does not check bounds) or ends the process"
    )


def _check(
    conn: Any,
    spec: str,
    filter: str,
    params: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
    parent_pid: int,
) -> None:  # pragma: no cover - runs in the child process
    """The child: receive the runs, load the model, then for each run the probe and a
    checked filter run; one message per manoeuvre (``("at", name)``), then
    ``("ok", None)`` or ``("error", text)``."""
    watch_parent(parent_pid)  # Ctrl-C is the parent's; a killed parent ends this one
    runs = conn.recv()
    try:
        error = _checked_runs(conn, spec, filter, runs, params, q, r, settings)
        conn.send(("ok", None) if error is None else ("error", error))
    except BaseException as exc:  # the model file's own failure, whatever it is
        conn.send(("error", f"{type(exc).__name__}: {str(exc)[:200]}"))


def _checked_runs(
    conn: Any,
    spec: str,
    filter: str,
    runs: list[HookRun],
    params: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
) -> str | None:  # pragma: no cover - runs in the child process
    """What is wrong with the hooks on ``runs`` (None: nothing)."""
    from kftune.filters.generic import get_filter
    from kftune.models.user import checked_model, load_model

    try:
        model = load_model(spec)
    except ConfigError as exc:
        return str(exc)
    filt = get_filter("ukf", settings=settings) if filter == "ukf" else get_filter("ekf")
    checked = None
    for name, u, z, dt in runs:
        conn.send(("at", name))
        try:
            model.probe(u, z, r, params, dt)
        except ValueError as exc:
            return str(exc)
        if checked is None:
            checked = checked_model(model)
        try:
            filt.run(checked, u, z, dt, q, r, params=params)
        except IndexError:
            return _out_of_bounds(model, filt, u, z, dt, params, q, r)
        except Exception:  # a failed run is the filter's business, not this check's
            continue
    return None


def _out_of_bounds(
    model: Any,
    filt: Any,
    u: np.ndarray | None,
    z: np.ndarray,
    dt: float,
    params: np.ndarray,
    q: np.ndarray,
    r: np.ndarray,
) -> str:  # pragma: no cover - runs in the child process
    """The message for an index out of bounds, naming the hook: the run again with one
    hook checked at a time (a helper function shared by several is blamed on the first)."""
    from kftune.models.user import checked_model

    hook = "a hook"
    for name in _ORDER:
        if getattr(model, name) is None:
            continue
        try:
            filt.run(checked_model(model, (name,)), u, z, dt, q, r, params=params)
        except IndexError:
            hook = f"{name}({', '.join(HOOK_ARGUMENTS[name])})"
            break
        except Exception:  # another failure: not this hook's index
            continue
    return (
        f"{hook} (or a function it calls) indexes beyond an array in a state the filter "
        "reaches on this manoeuvre, not at the first sample (found by a run with bounds "
        "checked); compiled code does not check bounds, so a tuning run would read or "
        "write other memory: index out, x, u and p by the model's sizes"
    )
