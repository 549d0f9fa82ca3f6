"""The ``kftune`` command: one subcommand per verb, ``main() -> int``.

Each subcommand lives in its own module with ``register(subparsers)``, which adds its parser
and sets ``func`` to a callable ``(args) -> int``. This module only wires them together and
maps errors to exit codes.

The exit codes (0 success, 1 failure, 2 usage, 3 bad input, 130 interrupted, 141 broken
pipe, 143 terminated) are listed in :mod:`kftune.cli.exit_codes`; this module re-exports
them.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn, TextIO

from kftune import __version__
from kftune.cli.exit_codes import (
    EXIT_BAD_INPUT,
    EXIT_BROKEN_PIPE,
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    EXIT_USAGE,
)
from kftune.errors import DataWarning, KftuneError, RunFailedError, UsageError

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_BROKEN_PIPE",
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_TERMINATED",
    "EXIT_USAGE",
    "SUBCOMMANDS",
    "build_parser",
    "main",
]

#: Subcommand modules, in the order ``--help`` lists them.
SUBCOMMANDS: tuple[str, ...] = (
    "compare",
    "tune",
    "evaluate",
    "estimate",
    "export",
    "report",
    "study",
    "dataset",
    "models",
    "demo",
)


class CommandParser(argparse.ArgumentParser):
    """The parser of a subcommand (and of its own subcommands, ``dataset info``).

    Two changes to argparse's behaviour, which is otherwise kept: an error prints a
    one-line usage (the command, ``[options]``, its required options and its positional
    arguments, not every option: that is ``--help``'s job) and the error, ending in where
    help is (exit 2 as ever); an argument the command does not know is its own error, not
    the top-level parser's (argparse leaves those to the top level, which then shows
    ``usage: kftune [-h] …`` and not the command that was mistyped).
    """

    def parse_known_args(  # type: ignore[override]  # typeshed's overloads; the plain form
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        parsed, extra = super().parse_known_args(args, namespace)
        if extra:  # only the subcommand's parser reads what follows the subcommand
            self.error(f"unrecognized arguments: {' '.join(extra)}")
        return parsed, extra

    def error(self, message: str) -> NoReturn:
        shown = [a for a in self._actions if a.required or not a.option_strings]
        formatter = self._get_formatter()
        formatter.add_usage(None, shown, [], prefix="")
        usage = formatter.format_help().strip().removeprefix(self.prog).strip()
        self.exit(
            EXIT_USAGE,
            f"usage: {self.prog} [options] {usage}".rstrip()
            + f"\n{self.prog}: error: {message} (see {self.prog} --help)\n",
        )


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (exposed for tests and documentation)."""
    parser = argparse.ArgumentParser(
        prog="kftune",
        description="kftune tunes Kalman filters: it searches the noise covariances of a "
        "UKF or EKF running a built-in model (the paper's single-track sideslip model, and "
        "others: kftune models) or a model file of your own, against a dataset's "
        "manoeuvres. The default tuner is TR-BO (trust-region Bayesian optimisation); the "
        "paper's two-stage Bayesian optimisation with a Student-t process (TSBO) is one "
        "method among GA, TSBO-GP, manual tuning and more (kftune tune --method), and "
        "kftune compare reproduces the paper's experiment.",
    )
    parser.add_argument("--version", action="version", version=f"kftune {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    sub.required = True
    for name in SUBCOMMANDS:
        importlib.import_module(f"kftune.cli.{name}").register(sub)
    return parser


def _plain_warnings(fallback: Callable[..., None]) -> Callable[..., None]:
    """A ``warnings.showwarning`` that prints kftune's own warnings as ``kftune: warning: …``
    (no source file and line, which look like a traceback) and hands others to
    ``fallback``."""

    def show(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        if issubclass(category, DataWarning):
            print(f"kftune: warning: {message}", file=sys.stderr)
        else:
            fallback(message, category, filename, lineno, file, line)

    return show


def _occupy_closed_std_streams() -> None:
    """Open the null device on standard descriptors 0–2 that were closed at start
    (``kftune … >&-``): otherwise the next file opened (a study, an output) would get the
    number 1 or 2, and whatever a worker process prints would land in it. A closed
    standard error (``2>&-``, where Python sets ``sys.stderr`` to None) becomes the null
    device too, so that the progress bar and messages are dropped instead of failing the
    run; a closed standard output stays None (``--json`` and ``export -o -`` refuse it)."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            os.open(os.devnull, os.O_RDWR)  # the lowest free number: this one
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - for the whole process
    if not isinstance(sys.stderr, _Diagnostics):
        sys.stderr = _Diagnostics(sys.stderr)


class _Diagnostics:
    """Standard error that drops what it cannot write (``2>/dev/full``, a log on a full
    disk): a progress line or warning that fails must not end the run that it reports on,
    nor be blamed on standard output; there is nowhere left to say it anyway."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError:
            return len(text)

    def flush(self) -> None:
        with contextlib.suppress(OSError):
            self._stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    _occupy_closed_std_streams()
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # recorded by reports
    with warnings.catch_warnings(), _sigterm_as_interrupt() as terminated:
        warnings.showwarning = _plain_warnings(warnings.showwarning)
        code = _run(args)
    return EXIT_TERMINATED if terminated and code == EXIT_INTERRUPTED else code


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[list[bool]]:
    """SIGTERM (``timeout``, a batch scheduler's stop) ends a command as Ctrl-C does — the
    best point so far saved, how to resume said — and the exit code is then 143. Yields a
    list that holds ``True`` once SIGTERM arrived. A second SIGTERM (during the clean-up)
    terminates at once; a process forked from this one (``--timeout``'s worker) keeps the
    default action; the previous handler is restored on the way out."""
    received: list[bool] = []
    pid = os.getpid()

    def handler(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the next one is not caught
        if os.getpid() != pid:  # a forked process: terminate as by default
            os.kill(os.getpid(), signal.SIGTERM)
            return
        received.append(True)
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield received
        return
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)


#: errno values of a write that failed (a full disk or quota, /dev/full, an I/O error).
_WRITE_ERRNOS = frozenset(
    getattr(errno, name) for name in ("ENOSPC", "EDQUOT", "EFBIG", "EIO") if hasattr(errno, name)
)


def _run(args: argparse.Namespace) -> int:
    if getattr(args, "json", False) and sys.stdout is None:  # closed before Python started
        print(f"kftune {args.command}: error: --json: standard output is closed", file=sys.stderr)
        return EXIT_USAGE
    try:
        code = int(args.func(args))
        if sys.stdout is not None:
            sys.stdout.flush()  # a closed pipe surfaces here, not at interpreter exit
        return code
    except KeyboardInterrupt:
        print("kftune: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except UsageError as exc:
        print(f"kftune {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except RunFailedError as exc:
        print(f"kftune: failed: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except KftuneError as exc:
        print(f"kftune: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:
        # The reader went away (| head): no traceback, and keep Python from failing again
        # when it flushes stdout at exit (Python docs, "Note on SIGPIPE").
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:
        # Files the commands write say so themselves (RunFailedError, naming the file and
        # what is kept); what is left is standard output (> /dev/full, a full disk) or an
        # error the commands did not foresee: a message, not a traceback.
        if exc.filename is None and exc.errno in _WRITE_ERRNOS:
            # the files kftune writes are named by their own errors: this is stdout
            what = f"cannot write standard output: {exc.strerror}"
            # drop what is still buffered, or Python fails the same way at exit
            with contextlib.suppress(OSError, ValueError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        else:
            what = f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc)
        print(f"kftune {args.command}: failed: {what}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
