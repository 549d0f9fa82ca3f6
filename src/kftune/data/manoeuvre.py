"""In-memory types: one manoeuvre's signals, and a dataset of manoeuvres with its vehicle.

Both are frozen and validated when built (:func:`kftune.data.validate.validate_channels`),
so a filter or a cost function holding one never sees NaN, unequal lengths or deg/s. The
arrays are read-only float64 copies.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Any

import numpy as np

from kftune.data.noise import estimate_measurement_noise
from kftune.data.validate import (
    SIDESLIP_CHANNELS,
    SIDESLIP_MEASURED,
    plausibility_findings,
    sample_time,
    validate_channels,
)
from kftune.errors import DataError, DataWarning, MissingChannelError, excerpt
from kftune.vehicle.params import VehicleParams

#: Manoeuvre types of the paper's dataset (Sec. V-A), plus what an import gives without
#: the mapping's ``kind``: "segment" for a piece cut from a recording, "recording" for one
#: imported whole; other strings are accepted (a user's own manoeuvre types).
KINDS: tuple[str, ...] = (
    "braking-in-turn",
    "skidpad",
    "j-turn",
    "slalom",
    "lane-change",
    "random-steer",
    "track-lap",
    "spiral",
    "segment",
    "recording",
)
SPLITS: tuple[str, ...] = ("train", "test")


def _frozen(a: Any) -> np.ndarray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def _known(name: str, doc: str) -> property:
    """A read-only attribute for a known channel, with a clear error when it is absent."""

    def get(self: Manoeuvre) -> np.ndarray:
        return self.channel(name)

    return property(get, doc=doc)


def _restore(
    name: str,
    kind: str,
    split: str,
    t: np.ndarray,
    channels: dict[str, np.ndarray],
    description: str,
) -> Manoeuvre:
    """Rebuild a pickled manoeuvre."""
    return Manoeuvre(name, kind, split, t, channels=channels, description=description)


class Manoeuvre:
    """One manoeuvre, sampled regularly: time and any named channels, SI units, ISO 8855 signs.

    Only ``t`` is required; which channels a manoeuvre needs depends on the model that runs
    on it (its inputs and measurements by name, ``<output>_ref`` for a cost or KPI that
    scores a derived output; see :class:`~kftune.models.StateSpaceModel`). The channels of
    the paper's sideslip problem (:data:`~kftune.data.validate.SIDESLIP_CHANNELS`) are
    attributes; reading one the manoeuvre lacks raises
    :class:`~kftune.errors.MissingChannelError` naming the manoeuvre and the channel.

    Built as ``Manoeuvre(name, kind, split, t, delta=…, vx=…, px=…, description=…)``:
    every further keyword is a channel, as is every entry of ``channels`` (and of ``extra``,
    the former name for channels beyond the sideslip ones). Validated on construction
    (:func:`~kftune.data.validate.validate_channels`); the arrays are read-only float64
    copies; the object is immutable.

    Attributes:
        name: unique within its dataset. kind: manoeuvre type (see :data:`KINDS`).
        split: ``"train"`` or ``"test"``. t: (n,) time [s]. description: free text.
        delta: (n,) road-wheel angle [rad], positive = left.
        ax: (n,) longitudinal acceleration [m/s²]. ay: (n,) lateral acceleration [m/s²],
        positive = left. r: (n,) yaw rate [rad/s], positive = counter-clockwise.
        vx: (n,) measured longitudinal speed [m/s].
        beta_ref: (n,) reference sideslip [rad], atan2(Vy, Vx): positive when the velocity
        vector points to the left of the x axis.
        channels: every channel but ``t``, by name (read-only mapping).
        extra: the channels that are not sideslip channels (e.g. ``vy_true`` [m/s]).
    """

    name: str
    kind: str
    split: str
    t: np.ndarray
    description: str
    # every channel but t, in channel_names' order; set once in __init__
    _channels: Mapping[str, np.ndarray]

    def __init__(
        self,
        name: str,
        kind: str,
        split: str,
        t: Any,
        *,
        channels: Mapping[str, Any] | None = None,
        extra: Mapping[str, Any] | None = None,
        description: str = "",
        **named: Any,
    ) -> None:
        if not isinstance(name, str) or not name.strip():
            raise DataError(f"manoeuvre name must be a non-empty string, got {excerpt(name)}")
        where = f"manoeuvre {excerpt(name)}"
        if not isinstance(kind, str) or not kind.strip():
            raise DataError(f"{where}: kind must be a non-empty string, got {excerpt(kind)}")
        if split not in SPLITS:
            raise DataError(f"{where}: split must be one of {list(SPLITS)}, got {excerpt(split)}")
        given: dict[str, Any] = {}
        for source in (named, dict(channels or {}), dict(extra or {})):
            for key, values in source.items():
                if key in given or key == "t":
                    raise DataError(f"{where}: channel {excerpt(key)} is given twice")
                given[key] = values
        validate_channels({"t": t, **given}, file=where)
        known = [c for c in SIDESLIP_CHANNELS if c in given]
        order = known + sorted(c for c in given if c not in SIDESLIP_CHANNELS)
        d = self.__dict__
        d["name"], d["kind"], d["split"], d["description"] = name, kind, split, description
        d["t"] = _frozen(t)
        d["_channels"] = MappingProxyType({c: _frozen(given[c]) for c in order})

    def __setattr__(self, key: str, value: Any) -> None:
        raise AttributeError(f"Manoeuvre is immutable (cannot set {key!r})")

    def __delattr__(self, key: str) -> None:
        raise AttributeError(f"Manoeuvre is immutable (cannot delete {key!r})")

    def __repr__(self) -> str:
        return (
            f"Manoeuvre({self.name!r}, {self.kind!r}, {self.split!r}, n={self.n}, "
            f"channels={list(self.channel_names)})"
        )

    delta = _known("delta", "(n,) road-wheel angle [rad], positive = left.")
    ax = _known("ax", "(n,) longitudinal acceleration [m/s²].")
    ay = _known("ay", "(n,) lateral acceleration [m/s²], positive = left.")
    r = _known("r", "(n,) yaw rate [rad/s], positive = counter-clockwise.")
    vx = _known("vx", "(n,) measured longitudinal speed [m/s].")
    beta_ref = _known("beta_ref", "(n,) reference sideslip atan2(Vy, Vx) [rad].")

    # -- channels ----------------------------------------------------------------------
    @property
    def channels(self) -> Mapping[str, np.ndarray]:
        """Every channel but ``t`` (read-only): the sideslip ones present in file order,
        then the others sorted."""
        return self._channels

    @property
    def extra(self) -> Mapping[str, np.ndarray]:
        """The channels that are not sideslip channels (read-only), sorted."""
        return MappingProxyType(
            {k: v for k, v in self._channels.items() if k not in SIDESLIP_CHANNELS}
        )

    @property
    def channel_names(self) -> tuple[str, ...]:
        """``t``, then the sideslip channels present in file order, then the others sorted."""
        return ("t", *self._channels)

    def has(self, name: str) -> bool:
        """Whether the manoeuvre has a channel ``name``."""
        return name == "t" or name in self._channels

    def channel(self, name: str) -> np.ndarray:
        """A channel by name.

        Raises:
            MissingChannelError: no such channel (names the manoeuvre and what it has).
        """
        if name == "t":
            return self.t
        try:
            return self._channels[name]
        except KeyError:
            raise MissingChannelError(
                f"manoeuvre {excerpt(self.name)} has no channel {excerpt(name)}; it has "
                f"{excerpt(list(self.channel_names), 300)}",
                manoeuvre=self.name,
                channel=name,
            ) from None

    def require(self, names: Iterable[str], purpose: str, what: str = "channel") -> None:
        """Raise unless every channel of ``names`` is present.

        Args:
            purpose: who needs them, e.g. ``"the sideslip KPIs"``. what: what they are to
                it, e.g. ``"a reference channel"``.

        Raises:
            MissingChannelError: "<purpose> needs <what> beta_ref, which manoeuvre 'x'
                lacks (it has […])", for the first missing one.
        """
        for c in names:
            if not self.has(c):
                raise MissingChannelError(
                    f"{purpose} needs {what} {c}, which manoeuvre {excerpt(self.name)} lacks "
                    f"(it has {excerpt(list(self.channel_names), 300)})",
                    manoeuvre=self.name,
                    channel=c,
                )

    # -- derived -----------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @cached_property
    def dt(self) -> float:
        """Sample time [s] (median step, without the timestamps' binary noise:
        :func:`~kftune.data.validate.sample_time`)."""
        return sample_time(self.t)

    @property
    def duration(self) -> float:
        """t[-1] − t[0] [s]."""
        return float(self.t[-1] - self.t[0])

    @cached_property
    def u(self) -> np.ndarray:
        """(n, 2) single-track filter inputs [δ [rad], ax [m/s²]] (read-only)."""
        return _frozen(np.column_stack([self.delta, self.ax]))

    @cached_property
    def z(self) -> np.ndarray:
        """(n, 3) single-track filter measurements [Vx [m/s], ay [m/s²], r [rad/s]]
        (read-only)."""
        return _frozen(np.column_stack([self.vx, self.ay, self.r]))

    def share_nonlinear(self, threshold: float = 4.0) -> float:
        """Share of samples with |ay| ≥ ``threshold`` [m/s²] (paper's "NON" samples)."""
        return float(np.mean(np.abs(self.ay) >= threshold))

    def slice(
        self,
        start: int,
        stop: int,
        name: str | None = None,
        split: str | None = None,
        kind: str | None = None,
    ) -> Manoeuvre:
        """Samples ``start:stop`` as a new manoeuvre (time is kept, not shifted)."""
        sl = slice(start, stop)
        return Manoeuvre(
            name or self.name,
            kind or self.kind,
            split or self.split,
            self.t[sl],
            channels={k: v[sl] for k, v in self._channels.items()},
            description=self.description,
        )

    def replace(self, **changes: Any) -> Manoeuvre:
        """A copy with some fields or channels replaced (``name``, ``kind``, ``split``,
        ``description``, ``t``, or a channel by name, new or existing); validated again."""
        meta = {
            k: changes.pop(k) for k in ("name", "kind", "split", "t", "description") if k in changes
        }
        return Manoeuvre(
            meta.get("name", self.name),
            meta.get("kind", self.kind),
            meta.get("split", self.split),
            meta.get("t", self.t),
            channels={**self._channels, **changes.pop("channels", {}), **changes},
            description=meta.get("description", self.description),
        )

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # the read-only channel view cannot be pickled; rebuild from plain fields (so a
        # manoeuvre can be sent to worker processes)
        return (
            _restore,
            (self.name, self.kind, self.split, self.t, dict(self._channels), self.description),
        )

    def equals(self, other: Manoeuvre) -> bool:
        """Exact equality of metadata and every channel (bit for bit)."""
        return (
            (self.name, self.kind, self.split, self.description)
            == (other.name, other.kind, other.split, other.description)
            and self.channel_names == other.channel_names
            and all(np.array_equal(self.channel(c), other.channel(c)) for c in self.channel_names)
        )


@dataclass(frozen=True, eq=False)
class Dataset:
    """Manoeuvres of one system (a vehicle, or any other) at one sample time, split into
    training and test.

    Built, it warns (:class:`~kftune.errors.DataWarning`, naming the manoeuvre and the share
    of samples) about data that load but look implausible
    (:func:`~kftune.data.validate.plausibility_findings`): once per kind of finding, naming
    the first manoeuvre with it and the others (a recording cut into segments is one
    finding, not one per segment).

    Attributes:
        name: a label. vehicle: the single-track model parameters of the car, or None for
            data of something else (the single-track models refuse to run without one).
        dt: sample time [s] (every manoeuvre's within 1 %).
        manoeuvres: all manoeuvres, training and test, in a fixed order.
        description: free text. meta: provenance (generator seed, sensor model, …).
        units: SI unit of channels kftune does not know (name → unit, e.g. ``px = "m"``),
            written to the manifest by :func:`~kftune.data.io.save_dataset`.
    """

    name: str
    vehicle: VehicleParams | None
    dt: float
    manoeuvres: tuple[Manoeuvre, ...]
    description: str = ""
    meta: Mapping[str, Any] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "manoeuvres", tuple(self.manoeuvres))
        if self.vehicle is not None and not isinstance(self.vehicle, VehicleParams):
            raise DataError(f"dataset {excerpt(self.name)}: vehicle must be VehicleParams or None")
        if not self.manoeuvres:
            raise DataError(f"dataset {excerpt(self.name)} has no manoeuvres")
        if not (isinstance(self.dt, (int, float)) and 0.0 < self.dt <= 1.0):
            raise DataError(
                f"dataset {excerpt(self.name)}: dt must be in (0, 1] s, got {self.dt!r}"
            )
        seen: set[str] = set()
        for m in self.manoeuvres:
            if not isinstance(m, Manoeuvre):
                raise DataError(f"dataset {excerpt(self.name)}: {excerpt(m)} is not a Manoeuvre")
            if m.name in seen:
                raise DataError(
                    f"dataset {excerpt(self.name)}: manoeuvre name {excerpt(m.name)} is duplicated"
                )
            seen.add(m.name)
            if abs(m.dt - self.dt) > 0.01 * self.dt:
                raise DataError(
                    f"dataset {excerpt(self.name)}: manoeuvre {excerpt(m.name)} has sample "
                    f"time {m.dt:.4g} s, the dataset {self.dt:.4g} s"
                )
        object.__setattr__(self, "meta", MappingProxyType(dict(self.meta)))
        object.__setattr__(self, "units", MappingProxyType(dict(self.units)))
        object.__setattr__(self, "_noise", {})
        mu = None if self.vehicle is None else self.vehicle.mu
        found: dict[str, list[tuple[str, str]]] = {}  # kind → [(manoeuvre, message)]
        for m in self.manoeuvres:
            for kind, text in plausibility_findings({"t": m.t, **m.channels}, mu).items():
                found.setdefault(kind, []).append((m.name, text))
        for hits in found.values():  # each kind once: a recording cut in 24 segments
            (name, text), more = hits[0], len(hits) - 1  # is one finding, not 24
            where = f"manoeuvre {name!r}"
            if more:
                others = excerpt([n for n, _ in hits[1:]], 200)
                where += f" (and {more} more with the same finding: {others})"
            warnings.warn(f"dataset {self.name!r}, {where}: {text}", DataWarning, stacklevel=2)

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # the read-only ``meta`` view cannot be pickled; rebuild from plain fields
        return (
            Dataset,
            (
                self.name,
                self.vehicle,
                self.dt,
                self.manoeuvres,
                self.description,
                _plain(self.meta),
                dict(self.units),
            ),
        )

    @property
    def train(self) -> tuple[Manoeuvre, ...]:
        """Training manoeuvres, in dataset order."""
        return tuple(m for m in self.manoeuvres if m.split == "train")

    @property
    def test(self) -> tuple[Manoeuvre, ...]:
        """Test manoeuvres, in dataset order."""
        return tuple(m for m in self.manoeuvres if m.split == "test")

    @property
    def names(self) -> tuple[str, ...]:
        """Manoeuvre names, in dataset order."""
        return tuple(m.name for m in self.manoeuvres)

    def __getitem__(self, name: str) -> Manoeuvre:
        for m in self.manoeuvres:
            if m.name == name:
                return m
        raise KeyError(
            f"dataset {excerpt(self.name)} has no manoeuvre {excerpt(name)}; "
            f"has {excerpt(list(self.names), 400)}"
        )

    def __len__(self) -> int:
        return len(self.manoeuvres)

    def subset(self, names: Iterable[str]) -> Dataset:
        """A dataset with only the named manoeuvres (in the order given).

        Raises:
            KeyError: a name that is not in the dataset (the message lists the known ones).
        """
        picked = tuple(self[n] for n in names)
        return Dataset(
            self.name, self.vehicle, self.dt, picked, self.description, self.meta, self.units
        )

    @property
    def channel_names(self) -> tuple[str, ...]:
        """The channels every manoeuvre has, in the first manoeuvre's order."""
        first = self.manoeuvres[0].channel_names
        return tuple(c for c in first if all(m.has(c) for m in self.manoeuvres[1:]))

    def noise_variances(self, channels: Sequence[str]) -> np.ndarray:
        """Measurement-noise variances of measured channels, by name, in their SI unit
        squared: a model's R₀ (e.g. ``ds.noise_variances(model.measurement_names)``).

        Estimated from the training manoeuvres (all manoeuvres if there are none) by
        :func:`kftune.data.noise.estimate_measurement_noise`, each channel on its own (so
        a channel's value is the same whichever others are asked for), and cached; a
        read-only array.

        Raises:
            MissingChannelError: a manoeuvre lacks one of the channels (named).
        """
        names = tuple(channels)
        # set in __post_init__, not a field (no part of a dataset's equality or repr)
        cache: dict[tuple[str, ...], np.ndarray] = self._noise  # type: ignore[attr-defined]
        if names not in cache:
            cache[names] = _frozen(
                estimate_measurement_noise(self.train or self.manoeuvres, channels=names)
            )
        return cache[names]

    @property
    def r_default(self) -> np.ndarray:
        """Default measurement-noise variances of the single-track model's measurements,
        (3,) [Vx [m²/s²], ay [m²/s⁴], r [rad²/s²]] (:meth:`noise_variances`).

        Raises:
            MissingChannelError: a manoeuvre lacks vx, ay or r (named).
        """
        return self.noise_variances(SIDESLIP_MEASURED)

    def summary(self) -> list[dict[str, Any]]:
        """Per-manoeuvre statistics: name, kind, split, n, duration [s], ay range
        [m/s²], β range [deg], share of |ay| ≥ 4 m/s², speed range [m/s]; a statistic
        whose channel the manoeuvre lacks is None."""
        rows = []
        for m in self.manoeuvres:
            ay = m.channel("ay") if m.has("ay") else None
            beta = np.degrees(m.channel("beta_ref")) if m.has("beta_ref") else None
            vx = m.channel("vx") if m.has("vx") else None
            rows.append(
                {
                    "name": m.name,
                    "kind": m.kind,
                    "split": m.split,
                    "n": m.n,
                    "duration": m.duration,
                    "ay_min": None if ay is None else float(ay.min()),
                    "ay_max": None if ay is None else float(ay.max()),
                    "beta_min_deg": None if beta is None else float(beta.min()),
                    "beta_max_deg": None if beta is None else float(beta.max()),
                    "share_ay_ge_4": None if ay is None else m.share_nonlinear(4.0),
                    "vx_min": None if vx is None else float(vx.min()),
                    "vx_max": None if vx is None else float(vx.max()),
                }
            )
        return rows


def _plain(value: Any) -> Any:
    """Mapping views → dicts, recursively (for pickling)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value
