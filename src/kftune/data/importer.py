"""Import recordings into a kftune dataset: ``kftune dataset import`` and
:func:`import_recordings`.

One mapping (a TOML file, or the same as a dict) says how every recording becomes channels:

.. code-block:: toml

    name = "my-car"                 # dataset name (default: the output folder's)
    vehicle = "bmw-320i"            # a preset, or a [vehicle] table of VehicleParams fields
    model = "single-track"          # checked: every channel it needs is mapped
    sample_time = 0.005             # [s] no time column: t = k·sample_time (MDF: the raster)
    min_speed = 1.0                 # [m/s] keep the stretches above it (standstill, reversing out)
    min_duration = 5.0              # [s] drop kept stretches shorter than this
    split_at_gaps = true            # a dropout in time ends a stretch (default: refused)
    segment_length = 30.0           # [s] cut each stretch into equal segments of about this length
    kind = "track-lap"              # the manoeuvres' kind (default "segment" when cut, else
    # kind = { "run3*" = "skidpad" }  #  "recording"); by file name, stem or manoeuvre name
    seed = 0                        # of the generator of the channels' noise (below)

    [source]                        # reader options (each format uses its own)
    format = "csv"                  # the reader, instead of the file's suffix (a .txt export)
    raster = 0.01                   # [s] resample onto a uniform grid (jittered timestamps)
    # raster = { "logger2-*" = 0.01 }   # only the recordings whose file name matches
    delimiter = ";"                 # CSV: default sniffed from the header row
    units_row = true                # CSV: the row after the header holds units
    encoding = "cp1252"             # CSV: the text encoding (default utf-8)
    decimal = ","                   # CSV: decimal comma (12340,5), with ";" or tab between
    struct = "data"                 # MATLAB: the signals are fields of this struct
    suffix = ".dat"                 # a folder of one file per signal: <name>.dat (default .txt)
    # raster = "YawRate"            # MDF: resample onto this signal's timestamps

    [split]                         # one rule: test = [globs], train_every = k, test_fraction = f
    test = ["run3*", "run1-s02"]    # globs of file names, stems or segment names
    # train_every = 3, per = "file" # count segments within each file (default "all")

    [channels]                      # kftune channel = source
    t = "time"                      # a name alone: SI units (or the unit the file declares)
    vx = { column = "Speed", unit = "km/h" }
    ay = { column = "AccY", unit = "g", sign = -1 }           # sign: flip a convention
    delta = { column = "SWA", unit = "deg", hand_wheel = true }   # ÷ steering ratio
    beta_ref = { atan2 = ["Vy", "Vx"], unit = "km/h" }        # atan2(Vy, Vx)
    p_brake = { column = "BrakePress", unit = "bar", scale = 1.0, offset = 0.0 }
    vx_meas = { column = "VxINS", unit = "m/s", noise = 0.05 }  # + white noise, σ in SI
    # computed channels, e.g. for a logger without ay and with four wheel speeds:
    # vx = { expr = "(wheel_fl + wheel_fr + wheel_rl + wheel_rr) / 4", unit = "km/h" }
    # ay = { expr = "vx * omega", unit = "m/s^2" }

A source value becomes ``sign · (scale · raw + offset) · unit factor`` (``scale`` and
``offset`` in the source's unit). ``hand_wheel = true`` divides by ``steering_ratio`` (the
mapping's, else the vehicle's); ``atan2 = [vy, vx]`` gives atan2(vy, vx) of two speed
sources (an ``offset`` there is refused: it would shift the speeds, not the angle).
``noise = σ`` then adds white Gaussian noise of standard deviation σ (in the channel's SI
unit): a measurement simulated from a reference-grade signal, such as a wheel-speed Vx from
an INS velocity. It is drawn from ``numpy.random.default_rng(seed)`` (the mapping's ``seed``,
default 0), one generator for the whole import: recordings in the order given, in each the
channels in the mapping's order (computed ones after the columns). An expression that names
such a channel sees it with its noise.

A source is a file, or a folder of one plain-text file per signal (a column's name is its
file's stem; :func:`~kftune.data.readers.read_column_files`). A mapping is a file, or the
name of one shipped with kftune (:func:`builtin_mapping`): ``revs-250lm``, the race-car
recording of the README (:func:`load_revs`, and :func:`open_dataset` of its folder).

``expr = "..."`` computes a channel (:mod:`kftune.data.expr`: numbers, ``+ - * / **``,
parentheses, abs, sqrt, sin, cos, tan, atan2, mean, clip, gradient/diff over time, lowpass).
A name in an expression is a channel of the mapping where one has that name — its SI values,
after its own unit, scale, offset, sign and hand-wheel ratio, computed first (dependency
order; a cycle is refused, naming it) — else a column of the file, as the file holds it
(raw, in the file's units: its declared unit is not applied); in a channel's own expression
its name is the file's column (``ax = { expr = "lowpass(ax, 10)" }``). ``t`` is the time
[s], ``pi`` is π. The result is in the channel's ``unit`` and converted like a column's
value. Without ``unit``: when every input has one and the same unit of the channel's
quantity (four wheel speeds a header declares in kmph; a channel of the mapping counts as
its SI unit), the result is in that unit; else, when no input is in a unit other than
SI (or none declares one), in SI; else the channel is refused, naming each input's unit
(wheel speeds in km/h and a yaw rate: convert in the expression, give ``unit``). A
division by zero or NaN gives bad samples, reported by row. When channels disagree (ay
against vx·r, the steering against the yaw rate), the message names the computed ones
among them, with the unit each was taken in, and the mapping entry the ratio points at
(``sign = -1``, a ``unit``, ``hand_wheel = true``).
Expressions are computed over the whole recording before it is trimmed and resampled.

``segment_length = L`` cuts a stretch of duration D into k = max(1, round(D / L)) segments
of equal sample counts (D = 169 s, L = 30 s: 6 of 28.2 s). A manoeuvre's ``kind`` (shown
beside its name by figures and ``dataset info``) is the mapping's ``kind``: one string for
all, or a table whose first glob that matches the file name, stem or manoeuvre name gives
it; else ``"segment"`` for a piece cut by ``segment_length`` and ``"recording"`` for one
imported whole (a recording, or a stretch of one).

Quantities (``sample_time``, ``min_speed``, ``min_duration``, ``segment_length``,
a ``raster`` step) are SI numbers or strings with a unit (``"5 km/h"``, ``"5 ms"``).

``[source] raster = <step>`` resamples a recording onto the uniform grid t₀ + k·step over
its span (every channel linearly interpolated; MDF: see :func:`~kftune.data.readers.read_mdf`)
before anything else: for loggers whose timestamps jitter. ``raster = { "<glob>" = <step>,
… }`` resamples only the recordings whose file name or stem a glob matches (the first that
does), for an import that mixes loggers. A step longer than
:data:`~kftune.data.validate.GAP_STEPS` median steps is a gap and is refused, never
bridged. Rows in later messages then count raster samples from the first data row (the
file's rows when the raster step is the recording's own).

Each recording is read (:mod:`kftune.data.readers`), converted, trimmed — with ``min_speed``
only the samples with vx > min_speed are kept (a NaN speed counts as not above it), each
contiguous stretch of at least ``min_duration`` becomes its own manoeuvre or is cut into
segments — and only then validated: a recording's every bad channel is reported at once
(:func:`~kftune.data.validate.channel_problems`), then the remaining checks of
:func:`~kftune.data.validate.validate_channels` run on each stretch. The train/test rule
then applies over all recordings in the order given: ``test = [globs]`` makes every
segment of a recording whose file name (or stem) matches a glob test; ``train_every = k``
makes segment ``i`` (0-based, counted over all recordings) training when ``i % k == 0``
(the default, k = 3: the first manoeuvre and every third after it, ``-s01``, ``-s04``, …,
as names count from 1);
``test_fraction = f`` makes test the segments that start after the first ``1 − f`` of the
total duration (so one uncut recording gives no test segment: cut it with
``segment_length``). ``per = "file"`` beside either counts ``i`` (or measures the
duration) within each recording instead of over all. A ``test`` glob also matches a
segment's name (``<file stem>-sNN``, as the manoeuvres are named). A rule that gives no
test (or no training) manoeuvre, and a test pattern that matches no recording, are
warned about (:class:`~kftune.errors.DataWarning`). With a ``model``, each stretch is
checked as the model checks data before a filter runs (the single-track models refuse
vx ≤ 0: set ``min_speed``).
"""

from __future__ import annotations

import codecs
import dataclasses
import fnmatch
import graphlib
import itertools
import json
import math
import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kftune.data.expr import ExprError, Expression, parse
from kftune.data.io import (
    DEFAULT_DATASET,
    MANIFEST_NAMES,
    _vehicle_from,
    default_dataset,
    file_stem,
    load_dataset,
    save_dataset,
)
from kftune.data.jsonfile import read_toml
from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.data.readers import READER_OPTIONS, Format, Table, format_named, format_of
from kftune.data.textfile import ReadLimits, check_regular_file
from kftune.data.validate import (
    CHANNEL_DIMENSION,
    GAP_STEPS,
    KINEMATIC_RATIO,
    MIN_SAMPLES,
    SI_UNIT,
    STANDARD_GRAVITY,
    STEER_L_EFF,
    UNITS,
    CrossCheckError,
    channel_problems,
    check_channel_name,
    check_increasing,
    kinematic_ratio,
    plausibility_findings,
    sample_time,
    unit_factor,
    validate_channels,
    with_article,
)
from kftune.errors import ConfigError, DataError, DataWarning, excerpt
from kftune.settings import NUMBER, SettingError, check, each, rule, rules, setting, validate
from kftune.vehicle.params import VehicleParams

if TYPE_CHECKING:
    from kftune.models import StateSpaceModel

#: The kind of a manoeuvre cut from a recording by ``segment_length``, and of one imported
#: whole (a recording, or a stretch of one that ``min_speed`` or a gap delimits), unless
#: the mapping's ``kind`` names one; figures and ``dataset info`` show it beside the name.
CUT_KIND = "segment"
WHOLE_KIND = "recording"
#: The rules of ``[split]``, one of which a mapping gives (:class:`SplitTable`).
SPLIT_RULES = ("test", "train_every", "test_fraction")
#: What ``[split] per`` takes: the segments counted over all recordings, or within each file.
SPLIT_PER = ("all", "file")
DEFAULT_TRAIN_EVERY = 3
#: What ``[source] raster`` is called in messages that suggest it.
RASTER_OPTION = "[source] raster"
#: What ``split_at_gaps`` is called in messages that suggest it.
GAP_OPTION = "split_at_gaps = true"
#: What keeps the stretches above a speed, in messages that suggest it.
SPEED_OPTION = "min_speed"
#: Text that every ASCII-compatible encoding writes as ASCII (a CSV's separators, numbers).
_ASCII_PROBE = "time,1.5;-2e+3\t|[m/s]\n"
_QUANTITY = "a number or '<number> <unit>'"


def _quantity(dimension: str) -> Callable[[Any], float]:
    """A converter of a quantity (an SI number, or ``"5 km/h"``) to SI: a setting's
    ``convert`` (a ValueError: not a quantity of ``dimension``)."""

    def convert(value: Any) -> float:
        if isinstance(value, str):
            number, _, unit = value.strip().partition(" ")
            factor = unit_factor(unit or SI_UNIT[dimension], dimension, file=None, column="")
            return float(number) * factor
        return float(value)

    return convert


def _pair(value: list[Any]) -> list[Any]:
    """``atan2 = [vy, vx]``: two names."""
    if len(value) != 2:
        raise ValueError("not two names")
    return value


def _kinds(value: str | dict[str, Any]) -> dict[str, Any]:
    """``kind``: one manoeuvre kind for all, or a table glob → kind; as glob → kind (each
    kind then checked by the rule of a table's values)."""
    if not (value.strip() if isinstance(value, str) else value):
        raise ValueError("no kind")
    return {"*": value} if isinstance(value, str) else value


def _nonblank(value: str) -> str:
    """A string with more than white space."""
    if not value.strip():
        raise ValueError("blank")
    return value


def _time(**constraints: Any) -> Any:
    """A quantity of time [s] (``"5 ms"``, ``0.005``)."""
    return setting(
        kind=(*NUMBER, str), convert=_quantity("time"), unit="s", what=_QUANTITY, **constraints
    )


@dataclass(frozen=True)
class ChannelTable:
    """One ``[channels]`` entry given as a table (a name alone is ``{ column = name }``)."""

    column: str | None = setting(kind=str)
    atan2: list[str] | None = field(
        default=None, metadata=rule(list, convert=_pair, each=each(str), what="[vy, vx], two names")
    )
    expr: str | None = setting(kind=str)
    unit: str | None = setting(kind=str)
    scale: float = setting(1.0, kind=NUMBER, nonzero=True)  # in the source's unit
    offset: float = setting(0.0, kind=NUMBER)  # in the source's unit
    sign: float = setting(1.0, kind=NUMBER, choices=(1, -1))
    hand_wheel: bool = setting(False, kind=bool)  # ÷ the steering ratio
    noise: float = setting(
        0.0, kind=NUMBER, low=0, what="a standard deviation", unit="the channel's SI unit"
    )


@dataclass(frozen=True)
class SplitTable:
    """``[split]``: one rule (checked by :func:`_split_rule`) and how segments are counted."""

    test: list[str] | None = field(
        default=None, metadata=rule(list, each=each(str, what="a file-name glob"))
    )
    train_every: int | None = setting(kind=int, low=1)
    test_fraction: float | None = setting(kind=NUMBER, low=0, strict=True, high=1, high_strict=True)
    per: str = setting("all", kind=str, choices=SPLIT_PER)


@dataclass(frozen=True)
class MappingFile:
    """An import mapping as written (see the module docstring); quantities in SI."""

    name: str | None = setting(kind=str)  # the dataset's (default: the output folder's)
    description: str = setting("", kind=str)
    vehicle: str | dict[str, Any] | None = field(
        default=None,
        metadata=rule((str, dict), what="a preset name or a table of VehicleParams fields"),
    )
    model: str | None = setting(kind=str)  # its channels must be mapped
    sample_time: float | None = _time(low=1e-4, high=1)  # no time column: t = k·sample_time
    min_speed: float | None = setting(
        kind=(*NUMBER, str), convert=_quantity("speed"), low=0, unit="m/s", what=_QUANTITY
    )
    min_duration: float | None = _time(low=0)  # drop kept stretches shorter than it
    split_at_gaps: bool = setting(False, kind=bool)  # a gap ends a stretch, not refused
    segment_length: float | None = _time(low=0, strict=True)  # cut stretches into segments
    kind: dict[str, str] = field(
        default_factory=dict,
        metadata=rule(
            (str, dict),
            convert=_kinds,
            each=each(str, convert=_nonblank, what="a non-empty string (a manoeuvre kind)"),
            what='a manoeuvre kind ("skidpad") or a table { "<file or manoeuvre glob>" = '
            '"<kind>" }',
        ),
    )
    steering_ratio: float | None = setting(kind=NUMBER, low=0, strict=True)  # hand-wheel/road
    source: dict[str, Any] = field(
        default_factory=dict,
        metadata=rule(dict, keys=READER_OPTIONS, what="a table of reader options"),
    )
    split: SplitTable | None = field(default=None, metadata=rule(SplitTable))
    channels: dict[str, str | ChannelTable] = field(
        default_factory=dict,
        metadata=rule(
            dict, each=each((str, ChannelTable), what="a column name or a table"), required=True
        ),
    )
    seed: int = setting(0, kind=int, low=0)  # of the generator of the channels' noise


@dataclass(frozen=True)
class ChannelSpec:
    """How one kftune channel is made from the sources (see the module docstring)."""

    channel: str
    sources: tuple[str, ...]  # one column, (vy, vx) for atan2, the names of an expression
    unit: str | None
    scale: float = 1.0
    offset: float = 0.0
    sign: float = 1.0
    hand_wheel: bool = False
    expression: Expression | None = None  # a computed channel
    noise: float = 0.0  # σ of the white noise added [the channel's SI unit]

    @property
    def label(self) -> str:
        """``vx (source 'Speed')`` or ``ay (expression 'vx * omega')``, for messages."""
        if self.expression is not None:
            return f"{self.channel} (expression {excerpt(self.expression.text)})"
        return f"{self.channel} (source {', '.join(repr(s) for s in self.sources)})"


@dataclass(frozen=True)
class Mapping_:
    """A parsed mapping (see the module docstring)."""

    file: str
    channels: dict[str, ChannelSpec]
    options: dict[str, Any]
    name: str | None
    description: str
    vehicle: VehicleParams | None
    model: str | None
    sample_time: float | None
    min_speed: float | None
    min_duration: float
    segment_length: float | None
    steering_ratio: float | None
    split: tuple[str, Any]
    split_per: str = "all"  # [split] per: count train_every / test_fraction per "file"
    split_at_gaps: bool = False  # a gap in time ends a stretch instead of being refused
    format: Format | None = None  # [source] format: the reader, instead of the suffix
    raster_step: float | None = None  # [s] [source] raster as a step: resample onto it
    raster_by_file: tuple[tuple[str, float], ...] = ()  # [source] raster per file glob
    given: Mapping[str, Any] = field(default_factory=dict)  # quantities as written
    state_space: StateSpaceModel | None = None  # the model named by ``model``
    seed: int = 0  # of the generator of the channels' noise
    kind_by_name: tuple[tuple[str, str], ...] = ()  # kind: (glob, kind), the first match's

    def raster_for(self, path: Path) -> float | None:
        """The raster step [s] a recording is resampled onto: that of the first glob of
        ``[source] raster = { "<glob>" = <step> }`` that matches its file name or stem,
        else the one ``raster`` step, else None (not resampled)."""
        for glob, step in self.raster_by_file:
            stem = file_stem(path.name.split(".")[0])
            if fnmatch.fnmatch(path.name, glob) or fnmatch.fnmatch(stem, glob):
                return step
        return self.raster_step

    def kind_for(self, path: Path, stem: str, name: str, cut: bool) -> str:
        """A manoeuvre's kind: that of the first glob of the mapping's ``kind`` that
        matches its recording's file name or stem, or its own name (``run1-s02``); else
        :data:`CUT_KIND` for a piece cut by ``segment_length``, :data:`WHOLE_KIND` for a
        recording (or a stretch of one) imported whole."""
        for glob, kind in self.kind_by_name:
            if any(fnmatch.fnmatch(n, glob) for n in (path.name, stem, name)):
                return kind
        return CUT_KIND if cut else WHOLE_KIND

    def echo(self, key: str, si_value: float, dimension: str) -> str:
        """A quantity for messages: in the unit the mapping wrote ``key`` in, then in SI
        (``"3 km/h (0.8333 m/s)"``), or in SI alone when the mapping gave a number."""
        si = f"{si_value:.4g} {SI_UNIT[dimension]}"
        given = self.given.get(key)
        unit = given.strip().partition(" ")[2].strip() if isinstance(given, str) else ""
        if not unit or unit == SI_UNIT[dimension]:
            return si
        return f"{si_value / UNITS[unit][1]:.4g} {unit} ({si})"


# ------------------------------------------------------------------------------ mapping
def builtin_mapping(name: str) -> Path | None:
    """The file of the mapping shipped with kftune under ``name`` (``"revs-250lm"``: the
    race-car recording, see the README), or None when there is none."""
    path = _BUILTIN_MAPPINGS / f"{name}.toml"
    return path if _BUILTIN_NAME.fullmatch(name) and path.is_file() else None


_BUILTIN_MAPPINGS = Path(str(resources.files("kftune") / "data" / "mappings"))
_BUILTIN_NAME = re.compile(r"[a-z0-9][a-z0-9-]*")


def read_mapping(mapping: str | Path | Mapping[str, Any]) -> Mapping_:
    """Parse and check a mapping (a TOML file, the name of a built-in mapping where no file
    of that name exists (:func:`builtin_mapping`), or a dict); errors name the file and
    key."""
    if isinstance(mapping, Mapping):
        file, data = "<mapping>", dict(mapping)
    else:
        if not Path(mapping).exists():
            builtin = builtin_mapping(str(mapping))
            if builtin is None:
                names = sorted(f.stem for f in _BUILTIN_MAPPINGS.glob("*.toml"))
                raise DataError(
                    "mapping not found: no such file, and no mapping shipped with kftune of "
                    f"that name ({', '.join(names)})",
                    file=str(mapping),
                )
            mapping = builtin
        file = str(mapping)
        data = read_toml(mapping)

    def bad(key: str, what: str) -> DataError:
        return DataError(f"key {key!r}: {what}", file=file)

    try:
        mf = validate(MappingFile, data)
    except SettingError as exc:
        raise DataError(str(exc), file=file) from None
    options = dict(mf.source)
    delimiter = options.get("delimiter")
    if delimiter is not None and (not isinstance(delimiter, str) or len(delimiter) != 1):
        raise bad("source.delimiter", f"expected one character, got {excerpt(delimiter)}")
    if "encoding" in options:
        _check_encoding(options["encoding"], bad)
    decimal = options.get("decimal", ".")
    if decimal not in (".", ","):
        raise bad("source.decimal", f'expected "." or ",", got {excerpt(decimal)}')
    if decimal == "," and delimiter == ",":
        raise bad(
            "source.decimal",
            'decimal = "," with source.delimiter = ",": a comma cannot both separate the '
            'fields and mark the decimals; a file with decimal commas separates them by ";" '
            'or a tab (delimiter = ";")',
        )
    fmt = None
    if "format" in options:
        if not isinstance(options["format"], str):
            raise bad("source.format", f"expected a format name, got {excerpt(options['format'])}")
        try:
            name = options.pop("format")
            fmt = format_named(name)
        except ConfigError as exc:
            raise bad("source.format", str(exc)) from None
        if name.strip().lower() == "tsv":
            options.setdefault("delimiter", "\t")  # what the .tsv suffix means
    raster = options.get("raster")
    raster_step = None
    raster_by_file: list[tuple[str, float]] = []

    def raster_quantity(key: str, value: Any) -> float:
        try:  # a step as sample_time takes
            return float(check(rules(MappingFile)["sample_time"], value, key))
        except SettingError as exc:
            raise DataError(str(exc), file=file) from None

    if isinstance(raster, str) and not _starts_with_number(raster):
        pass  # an MDF signal's name
    elif isinstance(raster, dict):  # per recording: file-name glob → step
        options.pop("raster")
        if not raster:
            raise bad("source.raster", 'expected a step, or a table { "<file glob>" = <step> }')
        for glob, value in raster.items():
            raster_by_file.append((glob, raster_quantity(f"source.raster.{glob}", value)))
    elif raster is not None:
        raster_step = raster_quantity("source.raster", options.pop("raster"))

    if isinstance(mf.vehicle, dict):
        _check_vehicle_table(mf.vehicle, mf.model, file)
    vehicle = None if mf.vehicle is None else _vehicle_from(mf.vehicle, file)
    if raster is not None and mf.sample_time is not None:
        raise bad(
            "source.raster",
            "give raster or sample_time, not both (sample_time: no time column, or an MDF "
            "file's raster step)",
        )
    channels = _channel_specs(mf.channels, file)
    needs_ratio = [c for c, s in channels.items() if s.hand_wheel]
    if needs_ratio and mf.steering_ratio is None:
        key = f"channels.{needs_ratio[0]}.hand_wheel"
        if vehicle is None:
            raise bad(key, "needs steering_ratio (or a vehicle, whose steering_ratio is used)")
        if vehicle.steering_ratio is None:
            named = isinstance(mf.vehicle, str)
            raise bad(
                key,
                f"{f'vehicle {mf.vehicle!r}' if named else 'the [vehicle] table'} has no "
                "steering_ratio to divide the hand-wheel angle by: give steering_ratio = "
                "<hand-wheel angle / road-wheel angle, e.g. 15.8> at the top of the mapping"
                + ("" if named else " or in the [vehicle] table"),
            )
    model = mf.model
    state_space = None if model is None else _check_model(model, channels, vehicle, file)
    return Mapping_(
        file=file,
        channels=channels,
        options=options,
        name=mf.name,
        description=mf.description,
        vehicle=vehicle,
        model=model,
        sample_time=mf.sample_time,
        min_speed=mf.min_speed,
        min_duration=mf.min_duration or 0.0,
        segment_length=mf.segment_length,
        steering_ratio=mf.steering_ratio,
        split=_split_rule(mf.split, file),
        split_per=_split_per(mf.split, file),
        split_at_gaps=mf.split_at_gaps,
        format=fmt,
        raster_step=raster_step,
        raster_by_file=tuple(raster_by_file),
        given={k: data[k] for k in ("min_speed", "min_duration", "split") if k in data},
        state_space=state_space,
        seed=mf.seed,
        kind_by_name=tuple(mf.kind.items()),
    )


#: What each required ``[vehicle]`` key is in the single-track models, for the message that
#: names the missing ones.
VEHICLE_ROLES = {
    "m": "mass [kg]: every force balance",
    "Iz": "yaw inertia [kg m²]: the yaw dynamics",
    "a": "CG to front axle [m]: the slip angles and axle loads",
    "b": "CG to rear axle [m]: the slip angles and axle loads",
    "h": "CG height [m]: only the longitudinal load transfer from ax (where |ax| stays "
    "small, a typical 0.5 m changes little)",
    "C_af": "front cornering stiffness [N/rad]: the front lateral force, always",
    "C_ar": "rear cornering stiffness [N/rad]: the rear lateral force, always",
}


def _check_vehicle_table(table: Mapping[str, Any], model: Any, file: str) -> None:
    """Refuse a ``[vehicle]`` table that lacks a required key, naming the missing keys in
    the mapping's terms and what each does in the model (instead of Python's message
    about ``VehicleParams.__init__``)."""
    required = [
        f.name
        for f in dataclasses.fields(VehicleParams)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    missing = [k for k in required if k not in table]
    if not missing:
        return
    uses = "the single-track models use every one of them"
    if isinstance(model, str):
        try:
            from kftune.models import get_model

            needs = get_model(model).needs_vehicle
        except (KeyError, ValueError, TypeError):
            needs = True  # the model key's own check names the problem
        uses = (
            f"model {model!r} uses every one of them"
            if needs
            else f"model {model!r} uses no vehicle: leave the [vehicle] table out"
        )
    raise DataError(
        f"key 'vehicle': the [vehicle] table lacks {', '.join(missing)} (it needs "
        f"{', '.join(required)}; {uses}): "
        + "; ".join(f"{k} = {VEHICLE_ROLES.get(k, 'required')}" for k in missing),
        file=file,
    )


def _starts_with_number(text: str) -> bool:
    """Whether a string starts like a number (``"10 ms"``, ``"10ms"``: a quantity, checked
    as one; ``"YawRate"``: a signal's name)."""
    return re.match(r"\s*[-+]?\.?\d", text) is not None


def _check_encoding(name: Any, bad: Callable[[str, str], DataError]) -> None:
    """Refuse an ``encoding`` Python does not know, or one that does not write ASCII as
    ASCII (UTF-16: its lines cannot be cut at the line-feed byte)."""
    if not isinstance(name, str):
        raise bad("source.encoding", f"expected a codec name such as 'cp1252', got {excerpt(name)}")
    try:
        codecs.lookup(name)  # a BOM is no byte of the text ("utf-8-sig": Excel's UTF-8 CSV)
        same = _ASCII_PROBE.encode(name).removeprefix(codecs.BOM_UTF8) == _ASCII_PROBE.encode()
    except (LookupError, UnicodeError):  # no such codec, or none for text ("undefined")
        raise bad(
            "source.encoding",
            f"unknown text encoding {excerpt(name)}; expected a codec name Python knows, such "
            "as 'utf-8', 'cp1252' or 'latin-1'",
        ) from None
    if not same:
        raise bad(
            "source.encoding",
            f"{excerpt(name)} does not write ASCII as ASCII (UTF-16 or -32?): re-save the file "
            "as UTF-8, or name an encoding such as 'cp1252' or 'latin-1'",
        )


def _channel_specs(table: Mapping[str, str | ChannelTable], file: str) -> dict[str, ChannelSpec]:
    """The ``[channels]`` entries (each checked against :class:`ChannelTable` already) as
    specs, with the checks that relate an entry's keys to each other."""
    if not table:
        raise DataError(
            "key 'channels': expected a table of kftune channel = source column", file=file
        )
    out = {}
    for channel, given in table.items():
        check_channel_name(channel, file=file)
        key = f"channels.{channel}"
        spec = ChannelTable(column=given) if isinstance(given, str) else given
        if sum(v is not None for v in (spec.column, spec.atan2, spec.expr)) != 1:
            raise DataError(
                f'key {key!r}: give one of column, atan2 = [vy, vx] or expr = "..."', file=file
            )
        expression = None
        if spec.atan2 is not None:
            sources = spec.atan2
            if spec.offset:
                raise DataError(
                    f"key '{key}.offset': an offset would shift both speeds before the angle, "
                    "not the angle; for an angle offset compute the channel: "
                    f'{channel} = {{ expr = "atan2({sources[0]}, {sources[1]}) + 0.01", '
                    'unit = "rad" }',
                    file=file,
                )
        elif spec.expr is not None:
            if channel == "t":
                raise DataError(
                    f"key '{key}.expr': the time t must be a column (or sample_time): "
                    "expressions are computed against it",
                    file=file,
                )
            try:
                expression = parse(spec.expr)
            except ExprError as exc:
                raise DataError(f"key '{key}.expr': {exc}", file=file) from None
            sources = list(expression.names)
        else:
            sources = [spec.column or ""]
        if not all(sources):
            raise DataError(f"key {key!r}: a source name must be a non-empty string", file=file)
        dim = "speed" if spec.atan2 is not None else CHANNEL_DIMENSION.get(channel)
        if spec.unit is not None:
            unit_factor(spec.unit, dim, file=file, column=channel)
        if spec.noise and channel == "t":
            raise DataError(
                f"key '{key}.noise': expected none for the time t (noise is added to "
                f"measurements), got {excerpt(spec.noise)}",
                file=file,
            )
        out[channel] = ChannelSpec(
            channel,
            tuple(sources),
            spec.unit,
            scale=float(spec.scale),
            offset=float(spec.offset),
            sign=float(spec.sign),
            hand_wheel=spec.hand_wheel,
            expression=expression,
            noise=float(spec.noise),
        )
    _computing_order(out, file)
    return out


def _computing_order(channels: Mapping[str, ChannelSpec], file: str) -> list[str]:
    """The computed channels in an order in which each comes after the channels of the
    mapping its expression names (dependency order; :class:`graphlib.TopologicalSorter`).
    A channel's own name in its expression is the file's column of that name
    (``ax = { expr = "lowpass(ax, 10)" }``), not a reference to itself.

    Raises:
        DataError: channels that refer to each other in a cycle (naming it).
    """
    graph = {
        c: [s for s in spec.sources if s in channels and s != c]
        for c, spec in channels.items()
        if spec.expression is not None
    }
    try:
        return [c for c in graphlib.TopologicalSorter(graph).static_order() if c in graph]
    except graphlib.CycleError as exc:
        cycle = exc.args[1][::-1]  # graphlib lists it against the edges
        raise DataError(
            f"key 'channels': computed channels refer to each other in a cycle: "
            f"{' -> '.join(cycle)} (an expression's name is a channel of the mapping where "
            "one has that name, else a column of the file)",
            file=file,
        ) from None


def _split_per(table: SplitTable | None, file: str) -> str:
    """``[split] per``: ``"all"`` (the default) or ``"file"``."""
    if table is None:
        return "all"
    if table.per == "file" and table.test is not None:
        raise DataError(
            "key 'split.per': per = \"file\" applies to train_every and test_fraction; test = "
            "[globs] names recordings or segments itself",
            file=file,
        )
    return table.per


def _split_rule(table: SplitTable | None, file: str) -> tuple[str, Any]:
    """The one rule of ``[split]`` (each checked against :class:`SplitTable` already) as
    (rule, value); none: every :data:`DEFAULT_TRAIN_EVERY`-th manoeuvre trains."""
    given = [(r, getattr(table, r)) for r in SPLIT_RULES if getattr(table, r, None) is not None]
    if not given:
        return ("train_every", DEFAULT_TRAIN_EVERY)
    if len(given) > 1:
        raise DataError(
            f"key 'split': expected one of {list(SPLIT_RULES)} (and optionally per = "
            f"{' or '.join(repr(p) for p in SPLIT_PER)})",
            file=file,
        )
    return given[0]


def _check_model(
    name: Any, channels: Mapping[str, ChannelSpec], vehicle: VehicleParams | None, file: str
) -> StateSpaceModel:
    """The model ``name``, checked: the mapping gives every channel it needs (and a
    vehicle when it needs one)."""
    from kftune.models import get_model

    try:
        model = get_model(name)
    except (KeyError, ValueError, TypeError) as exc:
        raise DataError(f"key 'model': {exc}", file=file) from None
    needed = (*model.input_names, *model.measurement_names)
    missing = [c for c in needed if c not in channels]
    if missing:
        raise DataError(
            f"key 'channels': model {name!r} needs the channel(s) {missing}, which the "
            "mapping does not give",
            file=file,
        )
    if model.needs_vehicle and vehicle is None:
        raise DataError(f"key 'vehicle': model {name!r} needs a vehicle", file=file)
    return model


# ------------------------------------------------------------------------------ import
@dataclass(frozen=True)
class _Recording:
    """One recording, converted and trimmed: its stretches of samples."""

    file: Path
    label: str
    stretches: list[dict[str, np.ndarray]]
    starts: list[int]  # row of each stretch's first sample in the file
    kept_s: float
    total_s: float
    units: dict[str, str]  # SI unit of each channel kftune does not know
    files: dict[str, str]  # channel → the file of its own that holds it (column files)


def _columns_of(m: Mapping_, spec: ChannelSpec) -> list[str]:
    """The file's columns a channel reads: its source(s), or the names of its expression
    that are no channel of the mapping."""
    if spec.expression is None:
        return list(spec.sources)
    return [s for s in spec.sources if s not in m.channels or s == spec.channel]


def _convert(
    m: Mapping_, path: Path, table: Table, rng: np.random.Generator
) -> tuple[dict[str, np.ndarray], dict[str, str], dict[str, tuple[str, str]]]:
    """The table's columns as SI channels, with time (see the module docstring), then the
    computed channels in dependency order; the SI unit of each channel kftune does not
    know; and the unit each channel was read in with how it was chosen (``("kmph", "the
    unit its inputs share")``), for the messages that suggest a fix."""
    file = str(path)
    lengths = {s: v.size for s, v in table.columns.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(
            f"signals of unequal lengths {excerpt(lengths, 300)}; one recording's signals "
            "must be sampled together",
            file=file,
        )
    if lengths:
        n = next(iter(lengths.values()))
    elif table.time is not None:
        n = table.time.size
    else:
        raise DataError(
            "key 'channels': the mapping names no column of the file (an expression of "
            "numbers alone has no samples)",
            file=m.file,
        )
    out: dict[str, np.ndarray] = {}
    si_units: dict[str, str] = {}
    taken: dict[str, tuple[str, str]] = {}  # channel → (unit read in, how it was chosen)
    for channel, spec in m.channels.items():
        if channel == "t" and table.time is not None:
            raise DataError(
                "an MDF file brings its own time axis (the raster): leave t out of the mapping",
                file=file,
                column="t",
            )
        if spec.expression is not None:
            continue  # computed once the time and the channels it names are known
        dim = "speed" if len(spec.sources) == 2 else CHANNEL_DIMENSION.get(channel)
        values = []
        for source in spec.sources:
            unit = spec.unit or table.units.get(source)
            if unit is None:
                if dim is None:
                    raise DataError(
                        f"{spec.label}: no unit in the mapping and none in the file; add "
                        f'unit = "..." to channels.{channel}',
                        file=m.file,
                    )
                unit = SI_UNIT[dim]
            try:
                factor = unit_factor(unit, dim, file=file, column=source)
            except DataError as exc:
                raise DataError(
                    f"{exc.message} (the file declares it; set unit in channels.{channel} of "
                    "the mapping to override)",
                    file=file,
                    column=source,
                ) from None
            values.append((table.columns[source] * spec.scale + spec.offset) * factor)
            si_units[channel] = SI_UNIT[UNITS[unit.strip()][0]]
            how = "as given" if spec.unit else "the file's" if source in table.units else "SI"
            taken[channel] = (unit.strip(), how)
        if len(values) == 2:
            value = np.arctan2(values[0], values[1])
            si_units[channel] = "rad"
        else:
            value = values[0]
        out[channel] = _finish(m, spec, value, rng)
    if table.time is not None:
        out["t"] = table.time
    elif "t" in out:
        if m.sample_time is not None:
            raise DataError(
                "key 'sample_time': the mapping maps t to a column too; give one", file=m.file
            )
    elif m.sample_time is not None:
        out["t"] = np.arange(n) * m.sample_time
    else:
        raise DataError(
            "no time: map t to the time column, or give sample_time (a constant step)",
            file=m.file,
            column="t",
        )
    for channel in _computing_order(m.channels, m.file):
        spec = m.channels[channel]
        assert spec.expression is not None
        dim = CHANNEL_DIMENSION.get(channel)
        unit, how = _expression_unit(m, spec, table.units, si_units, path)
        names = {
            s: out[s] if s in m.channels and s != channel else table.columns[s]
            for s in spec.sources
        }
        try:
            value = spec.expression.evaluate(names, out["t"])
        except ExprError as exc:
            raise DataError(
                f"{spec.label}: {exc}",
                file=file,
                row=None if exc.index is None else exc.index + table.row_offset,
            ) from None
        factor = unit_factor(unit, dim, file=m.file, column=channel)
        out[channel] = _finish(m, spec, (value * spec.scale + spec.offset) * factor, rng)
        si_units[channel] = SI_UNIT[UNITS[unit.strip()][0]]
        taken[channel] = (unit.strip(), how)
    extra = {c: u for c, u in si_units.items() if c not in CHANNEL_DIMENSION}
    return {"t": out.pop("t"), **out}, extra, taken


def _expression_unit(
    m: Mapping_,
    spec: ChannelSpec,
    file_units: Mapping[str, str],
    si_units: Mapping[str, str],
    path: Path,
) -> tuple[str, str]:
    """The unit of a computed channel's result, and how it was chosen (for messages).

    The mapping's ``unit`` when given. Else the unit its inputs share when every input has
    one and the same unit of the channel's quantity (four wheel speeds declared ``kmph``
    give ``kmph``, converted like a column's value); a channel of the mapping counts as
    its SI unit, a column as the unit its file declares. Else, when no input is in a unit
    other than an SI one, the channel's SI unit (SI in, SI out: ``vx * omega`` in m/s²).
    Anything else would be a guess that silently scales the channel (wheel speeds in km/h
    and a yaw rate, a column in deg/s): refused.

    Raises:
        DataError: no unit can be chosen, naming the mapping's key and each input's unit.
    """
    channel = spec.channel
    dim = CHANNEL_DIMENSION.get(channel)
    if spec.unit is not None:
        return spec.unit, "as given"
    inputs: dict[str, str | None] = {}
    for source in spec.sources:
        if source in m.channels and source != channel:  # a channel: SI, converted already
            known = CHANNEL_DIMENSION.get(source)
            inputs[source] = SI_UNIT[known] if known else si_units.get(source)
        else:
            inputs[source] = file_units.get(source)
    units = {u.strip() for u in inputs.values() if u is not None}
    if len(units) == 1 and None not in inputs.values():
        (shared,) = units
        if shared in UNITS and (dim is None or UNITS[shared][0] == dim):
            return shared, "the unit its inputs share"
    non_si = [u for u in units if u not in UNITS or UNITS[u][1] != 1.0]
    if not non_si and dim is not None:
        why = "its inputs are in SI units" if units else "its inputs declare no unit"
        return SI_UNIT[dim], f"SI: no unit given and {why}"
    listed = ", ".join(f"{s} [{u or 'no unit'}]" for s, u in inputs.items()) or "none"
    quantity = (
        f"{with_article(dim)} (SI unit {SI_UNIT[dim]})" if dim else "a channel kftune does not know"
    )
    raise DataError(
        f"{spec.label}: no unit in the mapping for the expression's result, and its inputs "
        f"({listed}; in {path.name}) do not all share one unit of this channel, "
        f"{quantity}: give the unit of the result in the mapping's [channels] table, "
        f"{_entry(m, channel, unit='<unit>')}"
        + (
            f"; with inputs in different units, convert them to SI in the expression (km/h: "
            f'/ 3.6, deg/s: * pi / 180) and give unit = "{SI_UNIT[dim]}"'
            if dim
            else ""
        ),
        file=m.file,
    )


def _finish(
    m: Mapping_, spec: ChannelSpec, value: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """A converted channel with its hand-wheel ratio and sign applied, and its ``noise``
    added (drawn from ``rng``)."""
    if spec.hand_wheel:
        ratio = m.steering_ratio or (m.vehicle and m.vehicle.steering_ratio)
        assert ratio, "read_mapping checks that a hand_wheel channel has a ratio"
        value = value / ratio
    value = spec.sign * value
    if spec.noise:
        value = value + rng.normal(0.0, spec.noise, value.size)
    return value


def _stretches(
    m: Mapping_, path: Path, channels: dict[str, np.ndarray]
) -> tuple[list[int], list[int]]:
    """Start and end indices of the stretches kept by ``min_speed`` and ``min_duration``."""
    t = channels["t"]
    n = t.size
    if m.min_speed is None:
        return [0], [n]
    if "vx" not in channels:
        raise DataError("key 'min_speed': trimming needs the channel vx", file=m.file)
    keep = np.zeros(n + 2, dtype=np.int8)
    with np.errstate(invalid="ignore"):
        keep[1:-1] = channels["vx"] > m.min_speed
    edges = np.diff(keep)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    finite = t[np.isfinite(t)]
    dt = float(np.median(np.diff(finite))) if finite.size > 1 else 0.0
    shortest = max(m.min_duration, (MIN_SAMPLES - 1) * dt)
    kept = [(a, b) for a, b in zip(starts, ends) if (b - a - 1) * dt >= shortest]
    return [int(a) for a, _ in kept], [int(b) for _, b in kept]


def _pieces(
    m: Mapping_, channels: dict[str, np.ndarray], file: str, row_offset: int
) -> list[tuple[int, dict[str, np.ndarray]]]:
    """The recording cut at its gaps in time when ``split_at_gaps`` (a step longer than
    :data:`~kftune.data.validate.GAP_STEPS` median steps: a logger dropout), else whole:
    ``(index of the piece's first sample, its channels)``. Pieces too short to be a
    manoeuvre (``min_duration``, :data:`MIN_SAMPLES` samples) are dropped; a recording cut
    in no piece long enough gives none."""
    t = channels["t"]
    if not m.split_at_gaps or t.size < 2:
        return [(0, channels)]
    check_increasing(t, file=file, row_offset=row_offset)
    steps = np.diff(t)
    dt = float(np.median(steps))
    cuts = [0, *(np.flatnonzero(steps > GAP_STEPS * dt) + 1).tolist(), t.size]
    if len(cuts) == 2:
        return [(0, channels)]
    shortest = max(m.min_duration, (MIN_SAMPLES - 1) * dt)
    return [
        (a, {c: v[a:b] for c, v in channels.items()})
        for a, b in itertools.pairwise(cuts)
        if t[b - 1] - t[a] >= shortest
    ]


def _resample(
    channels: dict[str, np.ndarray], step: float, file: str, row_offset: int
) -> dict[str, np.ndarray]:
    """The channels on the uniform grid t₀ + k·step [s] over the recording's span, each
    linearly interpolated (``[source] raster``). Time must increase strictly and have no
    gap: a step longer than :data:`~kftune.data.validate.GAP_STEPS` median steps is refused
    (naming its row), never bridged."""
    t = channels["t"]
    check_increasing(t, file=file, row_offset=row_offset)
    if t.size < 2:
        return channels  # too short: validation says so
    steps = np.diff(t)
    median = float(np.median(steps))
    gaps = np.flatnonzero(steps > GAP_STEPS * median)
    if gaps.size:
        k = int(gaps[0])
        raise DataError(
            f"a gap in the recording: step {steps[k]:.4g} s from the previous row, the median "
            f"step is {median:.4g} s; {RASTER_OPTION} resamples jittered timestamps but never "
            f"across a gap: split the recording at the gap ({GAP_OPTION} does)",
            file=file,
            column="t",
            row=k + 1 + row_offset,
        )
    if step > GAP_STEPS * median:
        warnings.warn(
            f"file {file}: [source] raster = {step:.4g} s is coarser than the recording's "
            f"step {median:.4g} s: resampled by linear interpolation, without an anti-alias "
            "filter (a raster is meant for jittered timestamps)",
            DataWarning,
            stacklevel=2,
        )
    grid = t[0] + np.arange(math.floor((t[-1] - t[0]) / step * (1 + 1e-12)) + 1) * step
    return {c: grid if c == "t" else np.interp(grid, t, v) for c, v in channels.items()}


def _check_model_data(m: Mapping_, part: Mapping[str, np.ndarray], file: str, row: int) -> None:
    """Refuse a stretch that the mapping's model refuses (its ``validate_data``, as run
    before a filter), naming the file, the channel and the row (``row``: the stretch's
    first)."""
    from kftune.models.base import DataRefused

    model = m.state_space
    if model is None or model.validate_data is None:
        return
    u = np.column_stack([part[c] for c in model.input_names] or [np.empty((part["t"].size, 0))])
    z = np.column_stack([part[c] for c in model.measurement_names])
    who = f"model {m.model!r}"
    try:
        model.validate_data(u, z)
    except DataRefused as exc:
        channel = exc.channel(model)
        hint = ""
        if channel == "vx" and m.min_speed is None:
            hint = (
                '; set min_speed (e.g. min_speed = "3 km/h") in the mapping to keep only the '
                "stretches with vx above it"
            )
        raise DataError(
            f"{who} refuses these data: {exc.reason}{hint}",
            file=file,
            column=channel,
            row=exc.row + row,
        ) from None
    except ValueError as exc:
        raise DataError(f"{who} refuses these data: {exc}", file=file) from None


def _check_stretches(
    m: Mapping_,
    file: str,
    starts: list[int],
    stretches: list[dict[str, np.ndarray]],
    offset: int,
    taken: Mapping[str, tuple[str, str]],
    files: Mapping[str, str],
) -> None:
    """Validate every kept stretch (all bad channels at once, then each stretch and the
    model's own check), naming rows as ``start + offset + index``; warn about a stretch
    whose ay/(vx·r) is off but not certainly wrong (the whole recording is judged before
    it is cut into segments, and each segment again when it becomes a manoeuvre). Where a
    message can name a fix in the mapping (a unit, ``sign = -1``, ``hand_wheel = true``)
    or a computed channel to suspect, it does (``taken``: each channel's unit as read). A
    channel read from a file of its own (``files``) is located in that file."""
    problems: dict[str, str] = {}
    for a, part in zip(starts, stretches):
        found = channel_problems(part, row_offset=a + offset, speed_option=SPEED_OPTION)
        for channel, text in found.items():
            if channel in m.channels and "implausible value" in text:
                text += _channel_fixes(m, channel, taken)
            problems.setdefault(channel, text)
    if problems:
        label_of = {c: s.label for c, s in m.channels.items()}
        label_of.setdefault("t", "t (sample_time)")
        only = next(iter(problems)) if len(problems) == 1 and files else None
        raise DataError(
            f"{len(problems)} bad channel(s): "
            + "; ".join(f"{label_of[c]}: {text}" for c, text in problems.items()),
            file=files.get(only, file) if only else file,
            column=only,
        )
    for a, part in zip(starts, stretches):
        row = a + offset
        try:
            validate_channels(
                part,
                file=file,
                row_offset=row,
                resample_option=RASTER_OPTION,
                gap_option=GAP_OPTION,
                speed_option=SPEED_OPTION,
                files=files,
            )
        except CrossCheckError as exc:
            raise DataError(
                exc.message + _cross_check_fixes(m, exc, taken),
                file=exc.file,
                column=exc.column,
                row=exc.row,
            ) from None
        _check_model_data(m, part, file, row)
        doubt = plausibility_findings(part, None).get("kinematic")
        if doubt:
            where = f"file {file}, rows {row}–{row + part['t'].size - 1}"
            fit = kinematic_ratio(part)
            if fit is None or _unit_could_explain("kinematic", fit.ratio):
                doubt += _suspects(m, ("ay", "vx", "r"), taken)
            warnings.warn(f"{where}: {doubt}", DataWarning, stacklevel=2)


#: Fits of ay/(vx·r) that mean one channel in a wrong unit: (ratio, channel, the unit it
#: is then in, what that is). ay in g read as m/s² gives 1/g; vx in km/h read as m/s 1/3.6;
#: r in deg/s read as rad/s π/180; and the inverse of each for the inverse mistake.
_RATIO_FIXES: tuple[tuple[float, str, str, str], ...] = (
    (1 / STANDARD_GRAVITY, "ay", "g", "ay in g"),
    (STANDARD_GRAVITY, "ay", "m/s^2", "ay in m/s² (not g)"),
    (1 / 3.6, "vx", "km/h", "vx in km/h"),
    (3.6, "vx", "m/s", "vx in m/s (not km/h)"),
    (math.pi / 180, "r", "deg/s", "r in deg/s"),
    (180 / math.pi, "r", "rad/s", "r in rad/s (not deg/s)"),
)
#: How far (a factor) a fitted ratio may lie from one of :data:`_RATIO_FIXES` to suggest it.
_RATIO_NEAR = 1.25


def _entry(m: Mapping_, channel: str, **changes: Any) -> str:
    """A channel's entry of the mapping's ``[channels]`` table as it reads with ``changes``
    (``ay = { column = "acc_y_right", sign = -1 }``), for messages that say what to write."""
    spec = m.channels[channel]
    fields: dict[str, Any] = {}
    if spec.expression is not None:
        fields["expr"] = spec.expression.text
    elif len(spec.sources) == 2:
        fields["atan2"] = list(spec.sources)
    else:
        fields["column"] = spec.sources[0]
    defaults: dict[str, Any] = {
        "unit": None,
        "scale": 1.0,
        "offset": 0.0,
        "sign": 1.0,
        "hand_wheel": False,
    }
    fields |= {k: getattr(spec, k) for k in defaults} | changes

    def toml(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v, ensure_ascii=False)
        if isinstance(v, list):
            return "[" + ", ".join(toml(x) for x in v) + "]"
        return f"{v:g}"

    shown = [
        f"{k} = {toml(v)}"
        for k, v in fields.items()
        if k in changes or k not in defaults or v != defaults[k]
    ]
    return f"{channel} = {{ {', '.join(shown)} }}"


def _ratio_text(m: Mapping_) -> str:
    """Which steering ratio ``hand_wheel = true`` divides by, or where to give one."""
    if m.steering_ratio is not None:
        return f"it divides by the mapping's steering_ratio = {m.steering_ratio:g}"
    if m.vehicle is not None and m.vehicle.steering_ratio is not None:
        return f"it divides by the vehicle's steering_ratio = {m.vehicle.steering_ratio:g}"
    return (
        "and give steering_ratio = <hand-wheel angle / road-wheel angle, e.g. 15.8> at the "
        "top of the mapping"
    )


def _suspects(m: Mapping_, channels: Sequence[str], taken: Mapping[str, tuple[str, str]]) -> str:
    """``"; suspect the computed channel vx (expression '…'), its result taken in kmph
    (…)"`` for the computed channels among ``channels``, else ``""``: a computed channel
    is the likeliest wrong one (its unit is the mapping's or a rule's, not the file's)."""
    texts = [
        f"{m.channels[c].label}, its result taken in {taken[c][0]} ({taken[c][1]}; if it is "
        f"in another unit, give it as unit in channels.{c} of the mapping)"
        for c in channels
        if c in m.channels and m.channels[c].expression is not None and c in taken
    ]
    if not texts:
        return ""
    return f"; suspect the computed channel{'s' if len(texts) > 1 else ''} " + "; ".join(texts)


def _channel_fixes(m: Mapping_, channel: str, taken: Mapping[str, tuple[str, str]]) -> str:
    """The mapping fixes for a channel with implausible values (a unit, a hand-wheel angle),
    in the mapping's words, and the unit a computed one was taken in."""
    spec = m.channels[channel]
    unit = taken.get(channel, ("", ""))[0]
    where = f"in the mapping's [channels] table ({m.file})"
    fixes = []
    if channel == "delta":
        if not spec.hand_wheel:
            fixes.append(
                f"if it is the hand-wheel angle, set hand_wheel = true {where}: "
                f"{_entry(m, channel, hand_wheel=True)} ({_ratio_text(m)})"
            )
        if unit == "rad":
            fixes.append(f"if it is in degrees: {_entry(m, channel, unit='deg')}")
    wrong = {"vx": ("m/s", "km/h"), "r": ("rad/s", "deg/s"), "beta_ref": ("rad", "deg")}
    if channel in wrong and unit == wrong[channel][0]:
        fixes.append(
            f"if it is in {wrong[channel][1]}: {_entry(m, channel, unit=wrong[channel][1])} {where}"
        )
    text = "; " + "; ".join(fixes) if fixes else ""
    return text + _suspects(m, (channel,), taken)


def _cross_check_fixes(
    m: Mapping_, exc: CrossCheckError, taken: Mapping[str, tuple[str, str]]
) -> str:
    """What to change in the mapping when channels disagree (:class:`CrossCheckError`):
    the sign or unit that the fitted ratio points at, a hand-wheel angle, and the
    computed channels among those compared."""
    where = f"in the mapping's [channels] table ({m.file})"
    fixes = []
    value = exc.value
    if exc.check == "kinematic" and "ay" in m.channels:
        if value < 0:
            fixes.append(
                f"if ay is positive to the right, flip it {where}: "
                f"{_entry(m, 'ay', sign=-m.channels['ay'].sign)} (or flip r the same way if "
                "it is the yaw rate that is positive clockwise)"
            )
        for ratio, channel, unit, what in _RATIO_FIXES:
            if channel in m.channels and abs(math.log(abs(value) / ratio)) < math.log(_RATIO_NEAR):
                fixes.append(f"if {what}: {_entry(m, channel, unit=unit)} {where}")
    if exc.check == "steering" and "delta" in m.channels:
        spec = m.channels["delta"]
        if value < 0:
            fixes.append(
                f"if δ is positive to the right, flip it {where}: "
                f"{_entry(m, 'delta', sign=-spec.sign)}"
            )
        elif value > STEER_L_EFF[1] and not spec.hand_wheel:
            fixes.append(
                f"if delta is the hand-wheel angle, set hand_wheel = true {where}: "
                f"{_entry(m, 'delta', hand_wheel=True)} ({_ratio_text(m)})"
            )
        elif 0 < value < STEER_L_EFF[0] and taken.get("delta", ("",))[0] in ("deg", "°"):
            fixes.append(f"if δ is in rad: {_entry(m, 'delta', unit='rad')} {where}")
    text = "; " + "; ".join(fixes) if fixes else ""
    if not _unit_could_explain(exc.check, value):  # a sign: no unit is to blame
        return text
    return text + _suspects(m, exc.channels, taken)


def _unit_could_explain(check: str, value: float) -> bool:
    """Whether a failed check between channels (``check`` of :class:`CrossCheckError`:
    ``"kinematic"``, ay/(vx·r) = ``value``; ``"steering"``, the effective wheelbase
    ``value`` [m]) could come from a channel in a wrong unit: its magnitude lies outside
    the expected range (:data:`~kftune.data.validate.KINEMATIC_RATIO`,
    :data:`~kftune.data.validate.STEER_L_EFF`). A value of the expected size but negative
    is a sign convention, which no unit explains."""
    low, high = KINEMATIC_RATIO if check == "kinematic" else STEER_L_EFF
    return not low <= abs(value) <= high


def _read(
    m: Mapping_, path: Path, label: str, limits: ReadLimits, rng: np.random.Generator
) -> _Recording:
    if not path.is_dir():  # a folder is read as column files, each of them checked
        check_regular_file(path)  # before any reader opens it: a FIFO would block the open
    fmt = m.format or format_of(path)
    file = str(path)
    names = list(dict.fromkeys(s for spec in m.channels.values() for s in _columns_of(m, spec)))
    options = {k: v for k, v in m.options.items() if k in fmt.options}
    if isinstance(m.options.get("raster"), str) and "raster" not in fmt.options:
        raise DataError(
            f"key 'source.raster': {excerpt(m.options['raster'])} names a signal, whose "
            f"timestamps only an MDF file has; for a {fmt.name} file give a step [s] to "
            "resample onto (raster = 0.01)",
            file=m.file,
        )
    raster_step = m.raster_for(path)
    step = m.sample_time or raster_step
    if fmt.own_time and step is not None:
        options["sample_time"] = step
    try:
        table = fmt.read(path, names, options, limits)
    except DataError as exc:
        users = [
            s
            for s in m.channels.values()
            if s.expression is not None and exc.column in _columns_of(m, s)
        ]
        if not users or "not found" not in exc.message:
            raise
        raise DataError(
            f"{users[0].label} names {exc.column!r}, which is neither a channel of the mapping "
            f"nor a column of the file: {exc.message}",
            file=exc.file,
            column=exc.column,
        ) from None
    channels, units, taken = _convert(m, path, table, rng)
    files = {  # a channel read from a file of its own (column files): errors name that file
        c: table.files[s.sources[0]]
        for c, s in m.channels.items()
        if s.expression is None and len(s.sources) == 1 and s.sources[0] in table.files
    }
    try:  # every reader's time, once, over the whole recording (rows min_speed drops too)
        check_increasing(channels["t"], file=files.get("t", file), row_offset=table.row_offset)
    except DataError as exc:
        spec = m.channels.get("t")
        raise DataError(
            f"{spec.label if spec else 't'}: {exc.message}",
            file=exc.file,
            column="t",
            row=exc.row,
        ) from None
    starts, stretches = [], []
    for first, piece in _pieces(m, channels, file, table.row_offset):
        for a, b in zip(*_stretches(m, path, piece)):  # resampled after trimming: a gap
            part = {c: v[a:b] for c, v in piece.items()}  # where vx is too low is cut out
            if raster_step is not None and not fmt.own_time:
                part = _resample(part, raster_step, file, first + a + table.row_offset)
            starts.append(first + a)
            stretches.append(part)
    t = channels["t"]
    if not starts and m.min_speed is None:  # split_at_gaps left no piece long enough
        longer = f" and {m.min_duration:g} s" if m.min_duration else ""
        raise DataError(
            f"no stretch of at least {MIN_SAMPLES} samples{longer} between the gaps in time "
            f"({t.size} samples; {GAP_OPTION} cuts at every step over {GAP_STEPS:g} median "
            "steps)",
            file=file,
            column="t",
        )
    if not starts:
        longer = f" and {m.min_duration:g} s" if m.min_duration else ""
        top = float(np.nanmax(channels["vx"], initial=-np.inf))
        raise DataError(
            f"no stretch of at least {MIN_SAMPLES} samples{longer} with vx above min_speed = "
            f"{m.echo('min_speed', m.min_speed or 0.0, 'speed')} ({t.size} samples, "
            + (
                f"top speed {m.echo('min_speed', top, 'speed')})"
                if math.isfinite(top)
                else "no vx sample is a number)"
            ),
            file=file,
            column="vx",
        )
    try:
        _check_stretches(m, file, starts, stretches, table.row_offset, taken, files)
    except DataError as exc:
        if raster_step is None or fmt.own_time:
            raise
        raise DataError(  # rows of resampled data are raster samples, not lines
            f"{exc.message} (resampled: a row counts {raster_step:g} s raster samples from "
            "the first row of its stretch)",
            file=exc.file,
            column=exc.column,
            row=exc.row,
        ) from None
    total = float(t[-1] - t[0]) if t.size > 1 else 0.0
    kept = sum(float(p["t"][-1] - p["t"][0]) for p in stretches)
    rows = [a + table.row_offset for a in starts]
    return _Recording(path, label, stretches, rows, kept, total, units, files)


def segment_bounds(t: np.ndarray, segment_length: float | None, name: str) -> list[int]:
    """Sample indices that cut a recording of times ``t`` into
    ``k = max(1, round(duration / segment_length))`` segments of (nearly) equal sample counts:
    ``[0, …, n]`` (``segment_length=None``: ``[0, n]``, one segment).

    Raises:
        ValueError: ``segment_length`` not > 0, or segments shorter than
            :data:`~kftune.data.validate.MIN_SAMPLES` (the message names ``name``).
    """
    n = t.size
    if segment_length is None:
        return [0, n]
    if not segment_length > 0:
        raise ValueError(f"segment_length must be > 0 s, got {segment_length!r}")
    k = max(1, round(float(t[-1] - t[0]) / segment_length))
    bounds = np.linspace(0, n, k + 1).round().astype(int).tolist()
    shortest = min(b - a for a, b in itertools.pairwise(bounds))
    if shortest < MIN_SAMPLES:
        dt = float(np.median(np.diff(t)))
        raise ValueError(
            f"segment_length = {segment_length!r} s cuts {name!r} into {k} segments of "
            f"{shortest} samples; a manoeuvre needs at least {MIN_SAMPLES} "
            f"(segment_length >= {MIN_SAMPLES * dt:g} s at dt = {dt:g} s)"
        )
    return bounds


def segment_manoeuvre(
    label: str,
    split: str,
    seg: Mapping[str, np.ndarray],
    description: str,
    *,
    file: str | None,
    row: int,
    note: str = "",
    files: Mapping[str, str] | None = None,
    kind: str = CUT_KIND,
) -> Manoeuvre:
    """A segment of a recording as a manoeuvre of ``kind`` (default ``"segment"``,
    :data:`CUT_KIND`). Its own checks (the
    kinematic ones judge the segment alone) name the recording's ``file`` (for a channel
    with a file of its own, ``files[channel]``) and a row of it (``row``: the segment's
    first sample's), with the segment's name and ``note`` — not the manoeuvre as the file
    and an index inside the segment as the row.

    Raises:
        DataError: a check refuses the segment (located in ``file`` when given).
    """
    try:
        return Manoeuvre(
            label,
            kind,
            split,
            seg["t"],
            channels={c: v for c, v in seg.items() if c != "t"},
            description=description,
        )
    except DataError as exc:
        if file is None:
            raise
        raise DataError(
            f"{exc.message} (segment {label!r}{note})",
            file=(files or {}).get(exc.column or "", file),
            column=exc.column,
            row=None if exc.row is None else row + exc.row,
        ) from None


def import_recordings(
    sources: Sequence[str | Path],
    mapping: str | Path | Mapping[str, Any] | Mapping_,
    out: str | Path | None = None,
    *,
    name: str | None = None,
    labels: Sequence[str] | None = None,
    limits: ReadLimits | None = None,
) -> Dataset:
    """Read recordings through one mapping and merge them into one dataset.

    Args:
        sources: recording files, in any format of :data:`kftune.data.readers.FORMATS`
            (their suffix picks the reader; a folder holds one file per signal).
        mapping: a mapping TOML file, the name of a built-in one (:func:`builtin_mapping`),
            its content as a dict (see the module docstring), or one parsed already.
        out: write the dataset there (:func:`~kftune.data.io.save_dataset`) when given.
        name: dataset name (default: the mapping's ``name``, else ``out``'s folder name,
            else ``"imported"``).
        labels: each recording's name, which its manoeuvres are named after (default: its
            file name up to the first dot, reduced by :func:`~kftune.data.io.file_stem`).
        limits: size limits of each file (``None``: the defaults or the environment).

    Returns:
        The dataset: per recording, each kept stretch (or its segments) a manoeuvre named
        ``<file stem>`` or ``<file stem>-sNN``, of the mapping's ``kind`` where it names
        one, else ``"segment"`` when cut by ``segment_length`` and ``"recording"`` when not.

    Raises:
        DataError: naming the file (recording or mapping), the column or key, the row.
        ConfigError: a reader's optional package is missing (names the extra).
    """
    if not sources:
        raise ConfigError("no recordings to import")
    m = mapping if isinstance(mapping, Mapping_) else read_mapping(mapping)
    lim = ReadLimits.from_env() if limits is None else limits
    if labels is None:
        labels = [file_stem(Path(s).name.split(".")[0]) for s in sources]
    for a, b in itertools.combinations(range(len(labels)), 2):
        if labels[a] == labels[b]:
            raise ConfigError(
                f"recordings {sources[a]} and {sources[b]} would both be named {labels[a]!r}; "
                "rename one"
            )
    for glob, _ in m.raster_by_file:
        if not any(fnmatch.fnmatch(Path(s).name, glob) or fnmatch.fnmatch(lab, glob)
                   for s, lab in zip(sources, labels)):  # fmt: skip
            warnings.warn(
                f"mapping {m.file}, key 'source.raster': pattern {excerpt(glob)} matches none "
                f"of the recordings {excerpt([Path(s).name for s in sources], 200)}",
                DataWarning,
                stacklevel=2,
            )
    rng = np.random.default_rng(m.seed)  # one generator: the recordings' noise in order
    recordings = [_read(m, Path(s), lab, lim, rng) for s, lab in zip(sources, labels)]
    steps = [sample_time(r.stretches[0]["t"]) for r in recordings]
    for r, step in zip(recordings, steps):
        if abs(step - steps[0]) > 0.01 * steps[0]:
            raise DataError(
                f"sample time {step:.4g} s, while {recordings[0].file.name} has {steps[0]:.4g} "
                f"s: one dataset has one sample time (resample with {RASTER_OPTION} = "
                f"{steps[0]:.4g}, or this recording alone with {RASTER_OPTION} = "
                f'{{ "{r.label}*" = {steps[0]:.4g} }})',
                file=str(r.file),
            )
    pieces = []  # (recording, label, channels, description)
    first_rows = []  # the row of each piece's first sample in its file
    kinds = []  # each piece's kind (Mapping_.kind_for)
    for r in recordings:
        parts = []
        for row, part in zip(r.starts, r.stretches):
            try:
                bounds = segment_bounds(part["t"], m.segment_length, r.label)
            except ValueError as exc:  # segments too short
                raise DataError(f"key 'segment_length': {exc}", file=m.file) from None
            parts += [
                ({c: v[a:b] for c, v in part.items()}, row + a, len(bounds) > 2)
                for a, b in itertools.pairwise(bounds)
            ]
        width = max(2, len(str(len(parts))))
        for i, (seg, row, cut) in enumerate(parts):
            label = r.label if len(parts) == 1 else f"{r.label}-s{i + 1:0{width}d}"
            where = f"{r.file.name}, rows {row}–{row + seg['t'].size - 1}"
            pieces.append((r, label, seg, f"{where}, t = {seg['t'][0]:.2f} … {seg['t'][-1]:.2f} s"))
            first_rows.append(row)
            kinds.append(m.kind_for(r.file, r.label, label, cut))
    for glob, _ in m.kind_by_name:
        if glob != "*" and not any(_matches(r, glob, label) for (r, label, _, _) in pieces):
            warnings.warn(
                f"mapping {m.file}, key 'kind.{glob}': pattern {excerpt(glob)} matches none "
                f"of the recordings {excerpt([r.file.name for r in recordings], 200)} and none "
                f"of their manoeuvres {excerpt([label for _, label, _, _ in pieces], 200)}",
                DataWarning,
                stacklevel=2,
            )
    splits = _splits(m, pieces)
    for text in _split_warnings(m, recordings, splits, [label for _, label, _, _ in pieces]):
        warnings.warn(text, DataWarning, stacklevel=2)
    manoeuvres = [
        _segment(m, r, label, split, seg, desc, row, kind)
        for (r, label, seg, desc), split, row, kind in zip(pieces, splits, first_rows, kinds)
    ]
    units = {c: u for r in recordings for c, u in r.units.items()}
    dataset_name = name or m.name or (Path(out).name if out is not None else "imported")
    meta: dict[str, Any] = {
        "imported_from": [r.file.name for r in recordings],
        "mapping": Path(m.file).name,
        "kept_s": [round(r.kept_s, 3) for r in recordings],
        "recorded_s": [round(r.total_s, 3) for r in recordings],
        "split": f"{m.split[0]} = {m.split[1]!r}"
        + (f", per = {m.split_per!r}" if m.split_per != "all" else ""),
    }
    if m.model is not None:
        meta["model"] = m.model
    if m.min_speed is not None:
        meta["min_speed"] = m.min_speed  # [m/s]
    noise = {c: s.noise for c, s in m.channels.items() if s.noise}
    if noise:
        meta["noise"] = noise  # [SI unit of each channel]
        meta["seed"] = m.seed
    dataset = Dataset(
        dataset_name,
        m.vehicle,
        float(np.median(steps)),
        tuple(manoeuvres),
        m.description or f"imported from {len(recordings)} recording(s)",
        meta,
        units,
    )
    if out is not None:
        save_dataset(dataset, out)
    return dataset


def _segment(
    m: Mapping_,
    r: _Recording,
    label: str,
    split: str,
    seg: dict[str, np.ndarray],
    desc: str,
    row: int,
    kind: str,
) -> Manoeuvre:
    """A segment of a recording as a manoeuvre of ``kind`` (:func:`segment_manoeuvre`:
    its errors name the recording's file and row, ``row`` the segment's first)."""
    note = ""
    step = m.raster_for(r.file)
    if step is not None and not (m.format or format_of(r.file)).own_time:
        note = (
            f"; resampled: a row counts {step:g} s raster samples from the first row of its stretch"
        )
    return segment_manoeuvre(
        label, split, seg, desc, file=str(r.file), row=row, note=note, files=r.files, kind=kind
    )


def _matches(r: _Recording, glob: str, segment: str | None = None) -> bool:
    """Whether a ``[split] test`` glob matches a recording's file name or its stem, or
    (given) the name of one of its segments (``run1-s02``)."""
    names = (r.file.name, r.label, *(() if segment is None else (segment,)))
    return any(fnmatch.fnmatch(n, glob) for n in names)


def _splits(m: Mapping_, pieces: list[tuple[Any, str, dict[str, np.ndarray], str]]) -> list[str]:
    """Each piece's split by the mapping's rule; with ``per = "file"`` the rule counts
    (``train_every``) or measures time (``test_fraction``) within each recording."""
    rule, value = m.split
    if rule == "test":
        return [
            "test" if any(_matches(r, g, label) for g in value) else "train"
            for r, label, _, _ in pieces
        ]
    groups: dict[int, list[int]] = {}
    for i, (r, _, _, _) in enumerate(pieces):
        groups.setdefault(id(r) if m.split_per == "file" else 0, []).append(i)
    out = [""] * len(pieces)
    for members in groups.values():
        if rule == "train_every":
            for k, i in enumerate(members):
                out[i] = "train" if k % value == 0 else "test"
            continue
        durations = np.array([float(np.ptp(pieces[i][2]["t"])) for i in members])
        before = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
        for i, b in zip(members, before):
            out[i] = "test" if b >= (1 - value) * durations.sum() else "train"
    return out


def _split_warnings(
    m: Mapping_, recordings: list[_Recording], splits: list[str], labels: list[str]
) -> list[str]:
    """What is suspicious about the split: a test pattern that matches no recording, and a
    split without test (or training) manoeuvres, each naming the mapping's key."""
    rule, value = m.split
    where = f"mapping {m.file}, key 'split.{rule}'"
    out = [
        f"{where}: pattern {excerpt(g)} matches none of the recordings "
        f"{excerpt([r.file.name for r in recordings], 200)} (by file name or stem) and none "
        f"of their segments {excerpt(labels, 200)}"
        for g in (value if rule == "test" else ())
        if not any(_matches(r, g) for r in recordings)
        and not any(fnmatch.fnmatch(label, g) for label in labels)
    ]
    given = f"{rule} = {excerpt(value, 100)}" + ("" if "split" in m.given else " (the default)")
    n = f"{len(splits)} manoeuvre{'s' if len(splits) > 1 else ''}"
    if "test" not in splits:
        cut = (
            "cut the recordings into more segments with a shorter segment_length"
            if m.segment_length is not None
            else "cut the recordings into segments with segment_length (e.g. "
            "segment_length = 30.0, in s)"
        )
        if rule == "test":  # by recording: segments do not help
            why, fix = "no recording matches a pattern", "name a recording in split.test"
        elif rule == "train_every":
            why = f"manoeuvre i is test when i % {value} != 0" + (
                " (i counted within each file)" if m.split_per == "file" else ""
            )
            fix = "use train_every = 2 or more" if value == 1 else cut
        else:
            why = f"test are the manoeuvres that start in the last {value:.0%} of the total time"
            fix = f"raise test_fraction or {cut}"
        out.append(f"{where}: {given} makes none of the {n} test ({why}); for a test split, {fix}")
    if "train" not in splits:
        out.append(
            f"{where}: {given} makes none of the {n} training: every recording matches a test "
            "pattern"
        )
    return out


# ------------------------------------------------------------------------------ revs-250lm
#: The built-in mapping of the revs-250lm race-car recording (its traps are in the file).
REVS_MAPPING = "revs-250lm"
#: Files whose presence marks a folder as the revs-250lm layout.
REVS_MARKERS = ("t.txt", "ayCG.txt", "yawRate.txt", "beta_true.txt", "vx.txt")


def load_revs(
    directory: str | Path,
    *,
    segment_length: float | None = None,
    train_every: int | None = None,
    vx_noise: float | None = None,
    seed: int | None = None,
    limits: ReadLimits | None = None,
) -> Dataset:
    """The revs-250lm race-car recording (a folder of one file per signal), imported by its
    built-in mapping (``data/mappings/revs-250lm.toml``, which holds every default): its
    vehicle (preset ``"revs-250lm"``), cut into segments of ``segment_length`` (30 s: 18
    segments ``revs-250lm-s01`` … ``-s18``), every ``train_every``-th (3rd) from the first
    training.

    The recording has no wheel speeds: the Vx measurement is the INS velocity plus white
    noise of σ = ``vx_noise`` (0.05 m/s; drawn from ``numpy.random.default_rng(seed)``, seed
    0; 0 keeps the INS value); the INS velocities stay as the extras ``vx_ins`` and
    ``vy_ins``. ``None`` keeps the mapping's value.

    Raises:
        ValueError: ``segment_length`` not > 0, ``train_every`` < 1 or ``vx_noise`` < 0.
        DataError: a file of the folder is missing or unusable.
    """
    m = read_mapping(_BUILTIN_MAPPINGS / f"{REVS_MAPPING}.toml")
    changes: dict[str, Any] = {}  # checked as the mapping's keys are (a SettingError)
    if segment_length is not None:
        changes["segment_length"] = check(
            rules(MappingFile)["segment_length"], segment_length, "segment_length"
        )
    if train_every is not None:
        rule_ = rules(SplitTable)["train_every"]
        changes["split"] = ("train_every", check(rule_, train_every, "train_every"))
    if vx_noise is not None:
        noise = check(rules(ChannelTable)["noise"], vx_noise, "vx_noise")
        vx = dataclasses.replace(m.channels["vx"], noise=float(noise))
        changes["channels"] = m.channels | {"vx": vx}
    if seed is not None:
        changes["seed"] = seed
    m = dataclasses.replace(m, **changes)
    return import_recordings([directory], m, labels=[REVS_MAPPING], limits=limits)


def open_dataset(spec: str | Path | None) -> Dataset:
    """Open a dataset named on a command line.

    ``None`` or ``"default"``: the bundled dataset; a folder or file with a kftune manifest:
    :func:`~kftune.data.io.load_dataset`; a folder in the revs-250lm layout: imported by its
    built-in mapping (:func:`load_revs`).
    """
    if spec is None or str(spec) == DEFAULT_DATASET:
        return default_dataset()
    path = Path(spec)
    if path.is_dir() and not any((path / n).is_file() for n in MANIFEST_NAMES):
        if all((path / f).is_file() for f in REVS_MARKERS):
            return load_revs(path)
        raise DataError(
            f"neither a kftune dataset ({' / '.join(MANIFEST_NAMES)}) nor the revs-250lm "
            f"layout ({', '.join(REVS_MARKERS)}); a recording is imported first with "
            "`kftune dataset import`",
            file=str(path),
        )
    return load_dataset(path)
