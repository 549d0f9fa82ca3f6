"""Your own model, from a Python file: ``--model my_car.py`` or ``model = "my_car.py"``.

A model file is plain Python that builds a :class:`~kftune.models.StateSpaceModel` from
``@njit`` functions f and h (see the README's worked example). :func:`load_model` runs it
and takes the model it defines:

* ``"my_car.py"`` — the file's one module-level StateSpaceModel (or the one it registers);
* ``"my_car.py:FAST"`` — the module-level variable ``FAST`` when it defines several;
* ``"single-track"`` — a registered model, by name (:func:`~kftune.models.model_names`).

A file is run once per process and path (numba compiles its functions then); the model is
registered under its name, so results, tuned files and studies can name it. Worker
processes (``--workers``) load the same file again from the spec string.

A model file is Python code that runs with the user's rights: the command line runs one
only when the user names it (``--model``, or a configuration passed on the command line),
never because a tuned file names it (:func:`kftune.cli.evaluate.require_named_model`).
Loading one catches whatever it raises, also SystemExit and a KeyboardInterrupt of its
own (a real Ctrl-C while it loads stays an interrupt). Its hooks are then checked in a
child process, with bounds checked (:func:`checked_model`,
:mod:`kftune.tuning.hookcheck`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.util
import os
import signal
import stat
import sys
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

from numba import njit
from numba.core.dispatcher import Dispatcher

from kftune.errors import ConfigError
from kftune.models.base import HOOK_ARGUMENTS, StateSpaceModel
from kftune.models.registry import get_model, model_names, register_model

__all__ = ["checked_model", "is_model_file", "load_model", "model_file_sha256"]

_LOADED: dict[tuple[str, str], StateSpaceModel] = {}
#: The start of the module name a model file is run under (one per path).
_MODULE_PREFIX = "kftune_user_model_"


def is_model_file(spec: str) -> bool:
    """Whether ``spec`` names a Python file (``x.py`` or ``x.py:NAME``), not a model name."""
    return model_file_parts(spec) is not None


def model_file_parts(spec: str) -> tuple[str, str] | None:
    """(file, NAME or "") of a model-file spec ``x.py[:NAME]`` (a spec that ends in ``.py``
    is all file); None for a model name."""
    if spec.endswith(".py"):
        return spec, ""
    head, sep, attr = spec.partition(".py:")
    return (head + ".py", attr) if sep else None


#: [bytes] the largest model file kftune hashes (a Python source of a model is kilobytes).
MAX_MODEL_FILE_BYTES = 64 * 2**20


def model_file_sha256(spec: str) -> str | None:
    """The SHA-256 of the file a model-file spec names (hex), so that a tuned file and a
    study can tell an edited model from the one they were made with; None for a model
    name, or a file that cannot be read, is not a regular file or is larger than
    :data:`MAX_MODEL_FILE_BYTES`."""
    parts = model_file_parts(spec) if isinstance(spec, str) else None
    if parts is None:
        return None
    # Opened without blocking and checked on the open file: a tuned file from elsewhere may
    # name a FIFO (reading it would wait for ever) or a device such as /dev/zero (endless).
    try:
        fd = os.open(Path(parts[0]).expanduser(), os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as file:
        try:
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_MODEL_FILE_BYTES:
                return None
            digest = hashlib.sha256()
            for block in iter(lambda: file.read(2**20), b""):
                digest.update(block)
            return digest.hexdigest()
        except OSError:
            return None


def load_model(spec: str | StateSpaceModel) -> StateSpaceModel:
    """The model a spec names (module docstring).

    Raises:
        ConfigError: no such file or model; the file fails to run, defines no model or
            several without a ``:NAME``; the name does not hold a model. The message names
            the file and what was expected, never the file's text.
    """
    if isinstance(spec, StateSpaceModel):
        return spec
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"model must be a model name or a Python file, got {spec!r}")
    parts = model_file_parts(spec)
    if parts is None:
        try:
            return get_model(spec)
        except ValueError:
            raise ConfigError(
                f"unknown model {spec!r}; built-in models: {', '.join(model_names())}; or "
                "give a Python file that defines one (e.g. --model my_model.py)"
            ) from None
    file, attr = parts
    path = Path(file).expanduser().resolve()
    key = (str(path), attr)
    if key in _LOADED:
        return _LOADED[key]
    if not path.is_file():
        raise ConfigError(f"model file {file} does not exist (or is not a file)")
    module = _run(path, file)
    found = {k: v for k, v in vars(module).items() if isinstance(v, StateSpaceModel)}
    if attr:
        if attr not in found:
            raise ConfigError(
                f"model file {file} has no StateSpaceModel named {attr!r}; it defines "
                f"{sorted(found) or 'none'}"
            )
        model = found[attr]
    else:
        distinct = {id(m): m for m in found.values()}
        if len(distinct) != 1:
            raise ConfigError(
                f"model file {file} defines {len(distinct)} StateSpaceModel objects "
                f"({sorted(found) or 'none'}); it must define exactly one, or name it: "
                f"{file}:NAME"
            )
        model = next(iter(distinct.values()))
    try:
        register_model(model, replace=True)
    except ValueError as exc:  # pragma: no cover - a StateSpaceModel always registers
        raise ConfigError(f"model file {file}: {exc}") from None
    _LOADED[key] = model
    return model


def checked_model(model: StateSpaceModel, hooks: Iterable[str] = HOOK_ARGUMENTS) -> StateSpaceModel:
    """A copy of ``model`` whose compiled ``hooks`` check every index (numba's
    ``boundscheck``): an index beyond an array raises IndexError instead of reading or
    writing other memory. The compiled functions that the hooks' own module defines (the
    helpers they call by name) are recompiled with the check too, by rebinding them in
    that module: only for a process that runs the model to check it (a child process),
    as the module's other users get the checked helpers as well. Nothing is cached."""
    done: dict[int, Dispatcher] = {}

    def checked(fn: Dispatcher) -> Dispatcher:
        if id(fn) not in done:
            options = {k: v for k, v in fn.targetoptions.items() if k not in ("nopython", "cache")}
            done[id(fn)] = njit(**{**options, "boundscheck": True})(fn.py_func)
        return done[id(fn)]

    for fn in (getattr(model, hook) for hook in HOOK_ARGUMENTS):
        module = sys.modules.get(getattr(getattr(fn, "py_func", None), "__module__", ""))
        if module is None or not module.__name__.startswith(_MODULE_PREFIX):
            continue  # only a model file's own functions (kftune's are its own business)
        for name, value in list(vars(module).items()):
            if isinstance(value, Dispatcher) and value.py_func.__module__ == module.__name__:
                setattr(module, name, checked(value))
    changed: dict[str, Any] = {
        h: checked(getattr(model, h)) for h in hooks if getattr(model, h) is not None
    }
    return dataclasses.replace(model, **changed)


def _run(path: Path, shown: str) -> object:
    """Import the file as a module of its own (a name unique to its path)."""
    name = _MODULE_PREFIX + hashlib.sha256(str(path).encode()).hexdigest()[:16]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ConfigError(f"model file {shown} cannot be loaded as Python")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # numba and pickle look functions up by module
    try:
        with _signals_seen() as seen:
            spec.loader.exec_module(module)
    except BaseException as exc:  # any failure of the user's code is reported
        del sys.modules[name]
        if isinstance(exc, KeyboardInterrupt) and seen:
            raise  # a real Ctrl-C or SIGTERM while loading: the user's interrupt
        where = f" (line {exc.lineno})" if isinstance(exc, SyntaxError) else ""
        tb = exc.__traceback__
        while tb is not None:
            if Path(tb.tb_frame.f_code.co_filename) == path:
                where = f" (line {tb.tb_lineno})"
            tb = tb.tb_next
        if not isinstance(exc, Exception):  # SystemExit, KeyboardInterrupt, GeneratorExit
            raise ConfigError(
                f"model file {shown} raised {type(exc).__name__} while loading{where}: a "
                "model file must define its model, not end or interrupt the program"
            ) from None
        text = exc.msg if isinstance(exc, SyntaxError) else str(exc)  # not the source line
        raise ConfigError(
            f"model file {shown} failed to run{where}: {type(exc).__name__}: {text[:200]}"
        ) from None
    return module


@contextlib.contextmanager
def _signals_seen() -> Iterator[list[int]]:
    """Note SIGINT and SIGTERM arriving while the body runs (each then handled as before),
    so that a KeyboardInterrupt that a model file raises itself is told from the user's
    Ctrl-C (or a SIGTERM that the command line turns into one). Outside the main thread,
    where no signal handler runs, nothing is noted."""
    seen: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield seen
        return
    previous: dict[int, Any] = {}

    def note(signum: int, frame: FrameType | None) -> None:
        seen.append(signum)
        before = previous[signum]
        if callable(before):
            before(signum, frame)
        elif before == signal.SIG_DFL:  # what it would have done: end the process
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)

    for signum in (signal.SIGINT, signal.SIGTERM):
        before = signal.getsignal(signum)
        if before is not None and before != signal.SIG_IGN:  # None: set outside Python
            previous[signum] = before
            signal.signal(signum, note)
    try:
        yield seen
    finally:
        for held, before in previous.items():
            signal.signal(held, before)
