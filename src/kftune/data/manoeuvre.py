"""In-memory types: one manoeuvre's signals, and a dataset of manoeuvres with its vehicle.

Both are frozen and validated when built (:func:`kftune.data.validate.validate_channels`),
so a filter or a cost function holding one never sees NaN, unequal lengths or deg/s. The
arrays are read-only float64 copies.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Any

import numpy as np

from kftune.data.noise import estimate_measurement_noise
from kftune.data.validate import REQUIRED_CHANNELS, plausibility_warnings, validate_channels
from kftune.errors import DataError, DataWarning, excerpt
from kftune.vehicle.params import VehicleParams

#: Manoeuvre types of the paper's dataset (Sec. V-A), plus "segment" for a piece of a long
#: recording; other strings are accepted (a user's own manoeuvre types).
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
)
SPLITS: tuple[str, ...] = ("train", "test")


def _frozen(a: Any) -> np.ndarray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Manoeuvre:
    """One manoeuvre, sampled regularly, SI units, ISO 8855 signs.

    Attributes:
        name: unique within its dataset. kind: manoeuvre type (see :data:`KINDS`).
        split: ``"train"`` or ``"test"``.
        t: (n,) time [s]. delta: (n,) road-wheel angle [rad], positive = left.
        ax: (n,) longitudinal acceleration [m/s²]. ay: (n,) lateral acceleration [m/s²],
        positive = left. r: (n,) yaw rate [rad/s], positive = counter-clockwise.
        vx: (n,) measured longitudinal speed [m/s].
        beta_ref: (n,) reference sideslip [rad], atan2(Vy, Vx): positive when the velocity
        vector points to the left of the x axis.
        extra: further (n,) channels by name (e.g. ``vy_true`` [m/s] of a simulation).
        description: free text.
    """

    name: str
    kind: str
    split: str
    t: np.ndarray
    delta: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    r: np.ndarray
    vx: np.ndarray
    beta_ref: np.ndarray
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise DataError(f"manoeuvre name must be a non-empty string, got {excerpt(self.name)}")
        where = f"manoeuvre {excerpt(self.name)}"
        if not isinstance(self.kind, str) or not self.kind.strip():
            raise DataError(f"{where}: kind must be a non-empty string, got {excerpt(self.kind)}")
        if self.split not in SPLITS:
            raise DataError(
                f"{where}: split must be one of {list(SPLITS)}, got {excerpt(self.split)}"
            )
        channels = {name: getattr(self, name) for name in REQUIRED_CHANNELS}
        for name, values in dict(self.extra).items():
            if name in channels:
                raise DataError(
                    f"{where}: extra channel {excerpt(name)} shadows a required channel"
                )
            channels[name] = values
        validate_channels(channels, file=where)
        for name in REQUIRED_CHANNELS:
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        object.__setattr__(
            self, "extra", MappingProxyType({k: _frozen(v) for k, v in dict(self.extra).items()})
        )

    # -- derived -----------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @cached_property
    def dt(self) -> float:
        """Sample time [s] (median step)."""
        return float(np.median(np.diff(self.t)))

    @property
    def duration(self) -> float:
        """t[-1] − t[0] [s]."""
        return float(self.t[-1] - self.t[0])

    @cached_property
    def u(self) -> np.ndarray:
        """(n, 2) filter inputs [δ [rad], ax [m/s²]] (read-only)."""
        return _frozen(np.column_stack([self.delta, self.ax]))

    @cached_property
    def z(self) -> np.ndarray:
        """(n, 3) filter measurements [Vx [m/s], ay [m/s²], r [rad/s]] (read-only)."""
        return _frozen(np.column_stack([self.vx, self.ay, self.r]))

    def channel(self, name: str) -> np.ndarray:
        """A required or extra channel by name."""
        if name in REQUIRED_CHANNELS:
            return getattr(self, name)
        try:
            return self.extra[name]
        except KeyError:
            known = list(REQUIRED_CHANNELS) + sorted(self.extra)
            raise KeyError(
                f"manoeuvre {excerpt(self.name)} has no channel {excerpt(name)}; has {known}"
            ) from None

    @property
    def channel_names(self) -> tuple[str, ...]:
        """Required channels in file order, then the extras (sorted)."""
        return REQUIRED_CHANNELS + tuple(sorted(self.extra))

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
            name=name or self.name,
            kind=kind or self.kind,
            split=split or self.split,
            t=self.t[sl],
            delta=self.delta[sl],
            ax=self.ax[sl],
            ay=self.ay[sl],
            r=self.r[sl],
            vx=self.vx[sl],
            beta_ref=self.beta_ref[sl],
            extra={k: v[sl] for k, v in self.extra.items()},
            description=self.description,
        )

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # the read-only ``extra`` view cannot be pickled; rebuild from plain fields (so a
        # manoeuvre can be sent to worker processes)
        return (
            Manoeuvre,
            (
                self.name,
                self.kind,
                self.split,
                *(getattr(self, c) for c in REQUIRED_CHANNELS),
                dict(self.extra),
                self.description,
            ),
        )

    def equals(self, other: Manoeuvre) -> bool:
        """Exact equality of metadata and every channel (bit for bit)."""
        return (
            (self.name, self.kind, self.split, self.description)
            == (other.name, other.kind, other.split, other.description)
            and set(self.extra) == set(other.extra)
            and all(np.array_equal(self.channel(c), other.channel(c)) for c in self.channel_names)
        )


@dataclass(frozen=True, eq=False)
class Dataset:
    """Manoeuvres of one vehicle at one sample time, split into training and test.

    Built, it warns (:class:`~kftune.errors.DataWarning`, naming the manoeuvre and the share
    of samples) about data that load but look implausible
    (:func:`~kftune.data.validate.plausibility_warnings`).

    Attributes:
        name: a label. vehicle: the single-track model parameters of the car.
        dt: sample time [s] (every manoeuvre's within 1 %).
        manoeuvres: all manoeuvres, training and test, in a fixed order.
        description: free text. meta: provenance (generator seed, sensor model, …).
    """

    name: str
    vehicle: VehicleParams
    dt: float
    manoeuvres: tuple[Manoeuvre, ...]
    description: str = ""
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "manoeuvres", tuple(self.manoeuvres))
        if not isinstance(self.vehicle, VehicleParams):
            raise DataError(f"dataset {excerpt(self.name)}: vehicle must be VehicleParams")
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
                    f"time {m.dt!r} s, the dataset {self.dt!r} s"
                )
        object.__setattr__(self, "meta", MappingProxyType(dict(self.meta)))
        for m in self.manoeuvres:
            for text in plausibility_warnings(
                {c: m.channel(c) for c in REQUIRED_CHANNELS}, self.vehicle.mu
            ):
                warnings.warn(
                    f"dataset {self.name!r}, manoeuvre {m.name!r}: {text}",
                    DataWarning,
                    stacklevel=2,
                )

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
        return Dataset(self.name, self.vehicle, self.dt, picked, self.description, self.meta)

    @cached_property
    def r_default(self) -> np.ndarray:
        """Default measurement-noise variances (3,) [Vx [m²/s²], ay [m²/s⁴], r [rad²/s²]].

        Estimated from the training manoeuvres (all manoeuvres if there are none) by
        :func:`kftune.data.noise.estimate_measurement_noise`; read-only.
        """
        return _frozen(estimate_measurement_noise(self.train or self.manoeuvres))

    def summary(self) -> list[dict[str, Any]]:
        """Per-manoeuvre statistics: name, kind, split, n, duration [s], ay range
        [m/s²], β range [deg], share of |ay| ≥ 4 m/s², speed range [m/s]."""
        rows = []
        for m in self.manoeuvres:
            rows.append(
                {
                    "name": m.name,
                    "kind": m.kind,
                    "split": m.split,
                    "n": m.n,
                    "duration": m.duration,
                    "ay_min": float(m.ay.min()),
                    "ay_max": float(m.ay.max()),
                    "beta_min_deg": float(np.degrees(m.beta_ref.min())),
                    "beta_max_deg": float(np.degrees(m.beta_ref.max())),
                    "share_ay_ge_4": m.share_nonlinear(4.0),
                    "vx_min": float(m.vx.min()),
                    "vx_max": float(m.vx.max()),
                }
            )
        return rows


def _plain(value: Any) -> Any:
    """Mapping views → dicts, recursively (for pickling)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value
