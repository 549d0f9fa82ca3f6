"""Typed settings records, checked against the constraints their fields declare.

Each kind of settings file (a run configuration, a dataset manifest, an import mapping) is
a dataclass whose fields declare, with :func:`setting`, what their key takes: the TOML
types (a boolean is never a number), a range, choices, a unit, a converter (a quantity
with a unit → SI), the rule of each element of an array or table, or a nested record (a
table). One function, :func:`validate`, reads those declarations to turn a parsed TOML or
JSON table into the record: an unknown key is refused with the allowed keys listed, a
missing required key is named, and a bad value is reported as ``<key>: expected <what the
rule says>, got <a short excerpt>``, the key by its dotted path (``cost.weights.beta``,
``manoeuvres[2].split``). :func:`merge` layers the sources of one setting (the command
line over a configuration file over a tuned file over the defaults) and says which source
gave each value, so that an error names it.

Generic: nothing here knows datasets or filters; each kind declares its record beside the
code that reads it, and words where an error lies (a file, an option) through
:class:`SettingError`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

from kftune.errors import KftuneError, excerpt

T = TypeVar("T")
#: The TOML types of a number (a boolean, although an ``int`` in Python, is not one).
NUMBER: tuple[type, ...] = (int, float)
_TYPE_NAMES = {
    object: "a value",
    bool: "true or false",
    int: "an integer",
    float: "a number",
    str: "a string",
    list: "an array",
    dict: "a table",
}
#: How a value of the wrong type is named in a message (TOML's and JSON's words).
_GOT_TYPES = {
    bool: "a boolean",
    int: "an integer",
    float: "a float",
    str: "a string",
    list: "an array",
    dict: "a table",
}
#: The value of a key that a source does not give (:func:`merge`); None is a value (a JSON
#: ``null``), refused where a setting needs one.
ABSENT: Any = object()


@dataclasses.dataclass(frozen=True)
class Rule:
    """What one key takes (see :func:`setting`)."""

    kind: tuple[type, ...]
    low: float | None = None
    strict: bool = False  # low excluded
    high: float | None = None
    high_strict: bool = False  # high excluded
    choices: tuple[Any, ...] | None = None
    nonzero: bool = False
    unit: str = ""
    what: str = ""  # how the expected value is described, instead of the type's name
    each: Rule | None = None  # every element of an array, every value of a table
    keys: tuple[str, ...] | None = None  # the keys a table may hold (None: any)
    convert: Callable[[Any], Any] | None = None  # raises ValueError: "expected <what>"
    required: bool = False

    def describe(self) -> str:
        """``"an integer >= 1 and <= 100000"``, ``"a number > 0 and <= 1 [s]"``,
        ``"one of ['train', 'test']"``, ``"a number or '<number> <unit>' whose value in s is
        >= 0.0001 and <= 1"``: what the rule accepts, for messages."""
        bounds = self.bounds()
        if self.what:
            if not bounds:
                return f"{self.what} [{self.unit}]" if self.unit else self.what
            unit = f" in {self.unit}" if self.unit else ""
            return f"{self.what} whose value{unit} is {bounds}"
        if self.choices is not None:
            text = (
                repr(self.choices[0]) if len(self.choices) == 1 else f"one of {list(self.choices)}"
            )
        else:
            kinds = [k for k in self.kind if not (k is int and float in self.kind)]
            text = " or ".join(
                "a table" if dataclasses.is_dataclass(k) else _TYPE_NAMES.get(k, k.__name__)
                for k in kinds
            )
        text += f" {bounds}" if bounds else ""
        return f"{text} [{self.unit}]" if self.unit else text

    def bounds(self) -> str:
        """``">= 1 and <= 100000"``, ``"other than 0"``: the range part of :meth:`describe`
        ("" without one)."""
        parts = []
        if self.low is not None:
            parts.append(f"{'>' if self.strict else '>='} {self.low:g}")
        if self.high is not None:
            parts.append(f"{'<' if self.high_strict else '<='} {self.high:g}")
        text = " and ".join(parts)
        if self.nonzero:
            text += " other than 0" if text else "other than 0"
        return text


def rule(kind: type | tuple[type, ...], **constraints: Any) -> dict[str, Rule]:
    """A field's metadata: its key takes ``kind`` (a type, a tuple of types, or a record
    type for a table) under the :class:`Rule` ``constraints`` (``low``, ``high``,
    ``choices``, ``unit``, ``each``, ``required``, …). For a field whose default is a list
    or dict: ``field(default_factory=dict, metadata=rule(dict, ...))``."""
    return {"rule": Rule(kind if isinstance(kind, tuple) else (kind,), **constraints)}


def setting(default: Any = None, *, kind: type | tuple[type, ...], **constraints: Any) -> Any:
    """A dataclass field of :func:`rule` ``(kind, **constraints)`` whose value is
    ``default`` (immutable) when its key is absent."""
    return dataclasses.field(default=default, metadata=rule(kind, **constraints))


def each(kind: type | tuple[type, ...], **rule: Any) -> Rule:
    """The rule of every element of an array or value of a table (``setting(each=...)``)."""
    return Rule(kind if isinstance(kind, tuple) else (kind,), **rule)


class SettingError(KftuneError, ValueError):
    """A key that is unknown, missing or holds a bad value; ``str()`` is the whole message.
    ``where``: where the key lies, when a caller words it (``"--budget"``, a file and a
    table); else the key's dotted path is named. ``unknown``: every unknown key of the
    table (``key`` is the first), all of them named. ``wrong_type``: the value's type is
    what is wrong (a boolean or a float where an integer belongs), so the message names
    it."""

    def __init__(
        self,
        key: str,
        expected: str = "",
        value: Any = None,
        *,
        allowed: Sequence[str] | None = None,
        missing: bool = False,
        unknown: Sequence[str] = (),
        wrong_type: bool = False,
    ) -> None:
        self.key, self.expected, self.value = key, expected, value
        self.allowed, self.missing = allowed, missing
        self.unknown = list(unknown) or [key]
        self.wrong_type = wrong_type
        self.where: str | None = None
        super().__init__(key)

    def text(self, noun: str = "key") -> str:
        """The message, the key called a ``noun`` (a manifest's "field")."""
        if self.allowed is not None:
            if len(self.unknown) > 1 and self.where is None:
                names = ", ".join(excerpt(k) for k in self.unknown)
                return f"{noun}s {names}: unknown; expected some of {list(self.allowed)}"
            where = self.where or f"{noun} {excerpt(self.key)}"
            if len(self.unknown) > 1:  # the caller named the first: name the others too
                others = ", ".join(excerpt(k.rpartition(".")[2]) for k in self.unknown[1:])
                where += f" (and {others})"
            return f"{where}: unknown; expected some of {list(self.allowed)}"
        where = self.where or f"{noun} {excerpt(self.key)}"
        if self.missing:
            return f"{where} is missing"
        return f"{where}: expected {self.expected}, got {self.got()}"

    def got(self) -> str:
        """The value as a message shows it: ``null`` for None (a JSON null), ``a boolean
        (true)``, ``a float (10.0)`` where the type is wrong, else an excerpt."""
        if self.value is None:
            return "null"
        if isinstance(self.value, bool):
            return f"a boolean ({str(self.value).lower()})"
        name = _GOT_TYPES.get(type(self.value))
        if self.wrong_type and name is not None:
            return f"{name} ({excerpt(self.value)})"
        return excerpt(self.value)

    def __str__(self) -> str:
        return self.text()


def check(rule: Rule, value: Any, key: str) -> Any:
    """``value`` of ``key`` checked against ``rule``: converted, and with nested tables as
    their records.

    Raises:
        SettingError: naming ``key`` (or the element's key below it).
    """
    bad = SettingError(key, rule.describe(), value)
    record = next((k for k in rule.kind if dataclasses.is_dataclass(k)), None)
    if record is not None and isinstance(value, dict):
        return validate(record, value, key)
    boolean = isinstance(value, bool) and not any(k in (bool, object) for k in rule.kind)
    # True is an int, but not a number; None (a JSON null) is no setting's value
    if boolean or value is None or not isinstance(value, rule.kind):
        raise SettingError(key, rule.describe(), value, wrong_type=True)
    if rule.convert is not None:
        try:
            value = rule.convert(value)
        except ValueError:
            raise bad from None
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    low, high = rule.low, rule.high
    if number and not (
        math.isfinite(value)
        and (low is None or (value > low if rule.strict else value >= low))
        and (high is None or (value < high if rule.high_strict else value <= high))
        and not (rule.nonzero and value == 0)
    ):
        raise bad
    if rule.choices is not None and value not in rule.choices:
        raise bad
    if isinstance(value, dict):
        if rule.keys is not None:
            unknown = [f"{key}.{k}" for k in value if k not in rule.keys]
            if unknown:
                raise SettingError(unknown[0], allowed=rule.keys, unknown=unknown)
        if rule.each is not None:
            return {k: check(rule.each, v, f"{key}.{k}") for k, v in value.items()}
    if isinstance(value, list) and rule.each is not None:
        return [check(rule.each, v, f"{key}[{i}]") for i, v in enumerate(value)]
    return value


def rules(cls: type) -> dict[str, Rule]:
    """The declared rule of each key of the record type ``cls``, in field order."""
    return {f.name: f.metadata["rule"] for f in dataclasses.fields(cls) if "rule" in f.metadata}


def validate(cls: type[T], data: Any, path: str = "", **extra: Any) -> T:
    """The record ``cls`` of the table ``data``: every key checked against its field's
    rule (:func:`check`), absent ones at their defaults; ``extra``: fields that are not
    keys (where the record came from). ``path``: the table's own key, for messages.

    Raises:
        SettingError: an unknown key (the allowed ones listed), a missing required one, a
            bad value; naming its dotted path.
    """
    declared = rules(cls)
    if not isinstance(data, dict):
        raise SettingError(path, "a table", data)
    prefix = f"{path}." if path else ""
    unknown = [f"{prefix}{key}" for key in data if key not in declared]
    if unknown:
        raise SettingError(unknown[0], allowed=list(declared), unknown=unknown)
    values = {}
    for key, rule in declared.items():
        if key in data:
            values[key] = check(rule, data[key], prefix + key)
        elif rule.required:
            raise SettingError(prefix + key, missing=True)
    return cls(**values, **extra)


def given(record: Any) -> dict[str, Any]:
    """The keys of a record that differ from their defaults (nested records as tables):
    what a file set, as the table it came from."""
    out = {}
    for f in dataclasses.fields(record):
        value = getattr(record, f.name)
        if "rule" not in f.metadata:
            continue
        if dataclasses.is_dataclass(value):
            value = given(value)
            if value:
                out[f.name] = value
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if value != default:
            out[f.name] = value
    return out


@dataclasses.dataclass(frozen=True)
class Layer:
    """One source of settings: ``values`` by key (a key it does not hold: not given; None,
    a JSON null, is refused where a setting needs a value); ``where`` says where a
    key's value lies (``"--budget"``, ``"configuration file run.toml, [cost] kind"``);
    ``name``: what the source is (``"command line"``), for a caller to choose its error."""

    values: Mapping[str, Any]
    where: Callable[[str], str]
    name: str = ""


def merge(
    rules_by_key: Mapping[str, Rule], layers: Sequence[Layer]
) -> dict[str, tuple[Any, Layer]]:
    """Each key's value from the first layer that gives it (``layers`` in precedence order,
    e.g. command line, configuration file, tuned file, defaults), checked against its rule,
    with the layer it came from: key → (value, layer). A key no layer gives is left out;
    a layer that gives None (a JSON ``null``) gives a bad value, not none (a ``"filter":
    null`` would otherwise fall back to the default unsaid).

    Raises:
        SettingError: a bad value, its ``where`` naming the layer and key that gave it.
    """
    out: dict[str, tuple[Any, Layer]] = {}
    for key, rule in rules_by_key.items():
        for layer in layers:
            value = layer.values.get(key, ABSENT)
            if value is ABSENT:
                continue
            try:
                out[key] = (check(rule, value, key), layer)
            except SettingError as exc:
                exc.where = layer.where(exc.key)
                raise
            break
    return out
