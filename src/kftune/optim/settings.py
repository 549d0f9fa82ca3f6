"""Optimiser settings as records: the one place where keyword options become a record.

An optimiser with many settings (TR-BO, TSBO) takes them as one frozen dataclass, checked
once in its ``__post_init__`` (cf. BoTorch's ``OptimizeAcqfInputs``), rather than as a
long list of keyword arguments. Options that arrive as a mapping — a configuration's
``[options.<method>]`` table, ``kftune.minimize(..., max_fe=10)`` — are turned into that
record here, so an unknown name is refused with the names the method has.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, is_dataclass
from typing import Any, TypeVar

from kftune.errors import ConfigError

S = TypeVar("S")


def option_names(record_type: type[Any]) -> list[str]:
    """The option names a settings record takes, in its declared order."""
    if not is_dataclass(record_type):
        raise TypeError(f"{record_type.__name__} is not a settings record (a dataclass)")
    return [f.name for f in fields(record_type)]


def settings_from(record_type: type[S], options: Mapping[str, Any], method: str) -> S:
    """A ``record_type`` built from keyword ``options`` of method ``method``.

    Raises:
        ConfigError: a name the record does not have (the message names it and lists the
            method's options).
        SettingError: a value the record's checks refuse, naming its key.
    """
    allowed = option_names(record_type)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(f"method {method!r} has no option(s) {unknown}; its options: {allowed}")
    return record_type(**options)
