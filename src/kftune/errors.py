"""Exception types shared by every layer; the CLI maps them to exit codes."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

#: Most characters of a file's (or a user's) text that a message quotes: :func:`excerpt`.
EXCERPT_CHARS = 60
#: Most characters of a :class:`DataError` message; longer ones are cut (a last resort:
#: each message quotes file content through :func:`excerpt` already).
MAX_MESSAGE_CHARS = 2000


def excerpt(value: object, limit: int = EXCERPT_CHARS) -> str:
    """``repr(value)`` cut to about ``limit`` characters, for quoting a file's or a user's
    text in an error message: a long one ends in ``…`` and says how long it was."""
    if isinstance(value, (str, bytes)) and len(value) > limit:
        return f"{value[:limit]!r}… ({len(value):,} characters)"
    text = repr(value)
    if len(text) > limit:
        return f"{text[:limit]}… ({len(text):,} characters)"
    return text


class KftuneError(Exception):
    """Base class of errors kftune raises on purpose (bad input, bad options)."""


class DataError(KftuneError, ValueError):
    """Input data are unusable. The message names the file, column and row at fault
    (where they exist) and what was expected."""

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        column: str | None = None,
        row: int | None = None,
    ) -> None:
        where = []
        if file is not None:
            where.append(f"file {file}")
        if column is not None:
            where.append(f"column {excerpt(column)}")
        if row is not None:
            where.append(f"row {row}")
        if len(message) > MAX_MESSAGE_CHARS:
            message = message[:MAX_MESSAGE_CHARS] + "… (message cut)"
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.message = message  # without the location, to re-raise with another one
        self.file = file
        self.column = column
        self.row = row


class MissingChannelError(DataError, KeyError):
    """A manoeuvre lacks a channel that a model, a cost, a KPI or a plot needs (e.g. the
    reference ``beta_ref`` of the sideslip KPIs). A :class:`DataError` (the CLI's bad-input
    exit code) and a ``KeyError`` (a lookup by name that failed).

    Attributes:
        manoeuvre: the manoeuvre's name. channel: the channel it lacks.
    """

    def __init__(self, message: str, *, manoeuvre: str, channel: str) -> None:
        super().__init__(message)
        self.manoeuvre = manoeuvre
        self.channel = channel

    def __str__(self) -> str:  # KeyError's own would quote the message
        return str(self.args[0]) if self.args else ""


class RunFailedError(KftuneError):
    """A run produced no result although its input was valid (e.g. every evaluation of a
    tuning run failed); the CLI exits with 1, not with the bad-input code."""


class FilterDivergedError(RunFailedError, RuntimeError):
    """A filter's covariance could not be repaired or its estimate left the model's domain
    (a failed evaluation while tuning; a failed run elsewhere): the input was valid, the
    filter was not, so the CLI exits with 1."""


class ConfigError(KftuneError, ValueError):
    """An option or configuration value is invalid; the message names it."""


class ModelChoiceError(ConfigError):
    """A model and filter that cannot run. ``key``: the setting at fault — ``"model"`` (no
    such model, a model file that does not load), ``"filter"`` (no such filter) — so that a
    caller names where that setting came from (an option, a configuration key); None where
    no setting is wrong but the pair of model and data (a vehicle model on a dataset without
    a vehicle, or whose vehicle lacks a parameter the model reads): the message then says
    what the data lack, and no option or key is blamed."""

    def __init__(self, message: str, key: str | None) -> None:
        super().__init__(message)
        self.key = key


class ObjectiveMismatchError(ConfigError):
    """A stored study was created for another objective (data, cost, model) than the run
    that resumes it; a caller that chose the objective's defaults can say how to match.
    ``stored`` and ``current``: the two objectives' readable summaries (a tuning problem's
    ``fingerprint()["summary"]``), for a caller to tell which part differs; ``dataset``:
    the dataset the study was made on, as it recorded it (``{"name": …, "path": …}``, the
    path None for the bundled set); None when not known."""

    def __init__(
        self,
        message: str,
        stored: str | None = None,
        current: str | None = None,
        dataset: Mapping[str, Any] | None = None,
    ):
        super().__init__(message)
        self.stored = stored
        self.current = current
        self.dataset = dataset


class DataWarning(UserWarning):
    """Input data load but look implausible (e.g. samples held at a lower rate); the
    message names the dataset and manoeuvre and says how much of it is affected. The CLI
    prints it as ``kftune: warning: …``."""


class SettingWarning(DataWarning):
    """A setting that runs but does not do what its name says (a GA whose budget breeds no
    generation: random search); printed by the CLI as a :class:`DataWarning`."""


class UsageError(ConfigError):
    """Command-line options that contradict each other; the CLI exits with 2 (usage), as
    for options argparse refuses. The message names the options."""
