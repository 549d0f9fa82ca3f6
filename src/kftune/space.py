"""Search spaces: named box bounds, each on a linear or a log10 scale, mapped to [0, 1]^d.

Shared by the tuning problems (which define a space) and the optimisers (which search it);
it depends on numpy only.

Every optimiser in :mod:`kftune.optim` works in the unit cube ``u ∈ [0, 1]^d`` (cf. Optuna's
``_gp/search_space.py``: every parameter mapped to [0, 1], log scale when asked); the
objective always receives points in natural units. For a parameter with bounds ``[lo, hi]``

* linear scale: ``u = (x − lo) / (hi − lo)``;
* log10 scale:  ``u = (log10 x − log10 lo) / (log10 hi − log10 lo)``, so a multiplicative
  change ``x·c`` in natural units is the additive change ``log10(c) / (log10 hi − log10 lo)``
  in ``u``. The UKF process-noise parameters use log10 over ``[1e-10, 1]`` (paper Sec. VI).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

SCALES = ("linear", "log10")
#: A coordinate within this share of its range (in the unit cube) of a bound is "on" it.
BOUND_TOL = 0.01


@dataclass(frozen=True)
class Param:
    """One search dimension.

    Attributes:
        name: identifier (non-empty, unique within a :class:`Space`).
        low: lower bound in natural units (finite; > 0 on a log10 scale).
        high: upper bound in natural units (finite, > low).
        scale: ``"linear"`` or ``"log10"``.
        physical: a physical quantity's plausible range around a guess (a model's
            parameter: a stiffness, a friction coefficient), not a variance; a hint to
            optimisers (TR-BO's design), left out of comparisons and of :meth:`to_dict`
            so that a space's record and fingerprint do not change with it.
    """

    name: str
    low: float
    high: float
    scale: str = "linear"
    physical: bool = field(default=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"parameter name must be a non-empty string, got {self.name!r}")
        for attr in ("low", "high"):
            value = getattr(self, attr)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(
                    f"parameter {self.name!r}: {attr} must be a number, got {value!r}"
                ) from None
            if not math.isfinite(value):
                raise ValueError(f"parameter {self.name!r}: {attr} must be finite, got {value}")
            object.__setattr__(self, attr, value)
        if self.scale not in SCALES:
            raise ValueError(
                f"parameter {self.name!r}: scale must be one of {SCALES}, got {self.scale!r}"
            )
        if not self.low < self.high:
            raise ValueError(
                f"parameter {self.name!r}: lower bound {self.low} must be below "
                f"upper bound {self.high}"
            )
        if self.scale == "log10" and self.low <= 0.0:
            raise ValueError(
                f"parameter {self.name!r}: a log10 scale needs positive bounds, "
                f"got [{self.low}, {self.high}]"
            )

    @property
    def log(self) -> bool:
        """True on a log10 scale."""
        return self.scale == "log10"

    @property
    def _t_bounds(self) -> tuple[float, float]:
        """Bounds in the transformed coordinate (log10 x or x)."""
        if self.log:
            return math.log10(self.low), math.log10(self.high)
        return self.low, self.high

    @property
    def width(self) -> float:
        """Width of the box in the transformed coordinate (decades on a log10 scale)."""
        lo, hi = self._t_bounds
        return hi - lo

    def to_unit(self, value: Any) -> np.ndarray:
        """Natural units → ``u`` (no clipping; values outside the bounds map outside [0, 1])."""
        v = np.asarray(value, dtype=float)
        lo, hi = self._t_bounds
        t = np.log10(v) if self.log else v
        return (t - lo) / (hi - lo)

    def from_unit(self, u: Any) -> np.ndarray:
        """``u`` → natural units, clipped to ``[low, high]`` (guards 10**x round-off)."""
        uu = np.asarray(u, dtype=float)
        lo, hi = self._t_bounds
        t = lo + uu * (hi - lo)
        v = np.power(10.0, t) if self.log else t
        return np.clip(v, self.low, self.high)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return {"name": self.name, "low": self.low, "high": self.high, "scale": self.scale}


@dataclass(frozen=True)
class BoundHit:
    """A coordinate of a point that lies on (within :data:`BOUND_TOL` of) a bound.

    Attributes:
        name: the parameter.
        side: ``"lower"`` or ``"upper"``.
        value: the coordinate in natural units.
        bound: the bound it is next to, in natural units.
    """

    name: str
    side: str
    value: float
    bound: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return {"parameter": self.name, "side": self.side, "value": self.value, "bound": self.bound}

    def describe(self) -> str:
        """``"q_r = 0.998 is on its upper bound 1"``."""
        return f"{self.name} = {self.value:.4g} is on its {self.side} bound {self.bound:g}"


@dataclass(frozen=True)
class Space:
    """An ordered box of named parameters; points are ``(d,)`` arrays in natural units.

    Build one from :class:`Param` objects, or with :meth:`coerce` from
    ``{"name": (low, high)}`` / ``{"name": (low, high, "log10")}`` or a sequence of
    ``(low, high)`` pairs (names ``x0, x1, …``).
    """

    params: tuple[Param, ...]

    def __post_init__(self) -> None:
        params = tuple(self.params)
        if not params:
            raise ValueError("a search space needs at least one parameter")
        for p in params:
            if not isinstance(p, Param):
                raise ValueError(f"search space entries must be Param, got {type(p).__name__}")
        names = [p.name for p in params]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate parameter names in search space: {dup}")
        object.__setattr__(self, "params", params)

    # ---------------------------------------------------------------- construction
    @classmethod
    def coerce(cls, obj: Any) -> Space:
        """A :class:`Space` from a Space, a mapping name → (low, high[, scale]), or a sequence
        of (low, high[, scale]) tuples or :class:`Param`."""
        if isinstance(obj, Space):
            return obj
        if isinstance(obj, Mapping):
            return cls(tuple(_param_from(name, spec) for name, spec in obj.items()))
        if isinstance(obj, Sequence) and not isinstance(obj, (str, bytes)):
            return cls(
                tuple(
                    spec if isinstance(spec, Param) else _param_from(f"x{i}", spec)
                    for i, spec in enumerate(obj)
                )
            )
        raise ValueError(
            "space must be a Space, a mapping name -> (low, high[, scale]) or a sequence of "
            f"(low, high[, scale]); got {type(obj).__name__}"
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Space:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(tuple(Param(**p) for p in data["params"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed search-space description: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (used by studies to check a resume uses the same space)."""
        return {"params": [p.to_dict() for p in self.params]}

    # ---------------------------------------------------------------- accessors
    def __len__(self) -> int:
        return len(self.params)

    def __iter__(self) -> Iterator[Param]:
        return iter(self.params)

    @property
    def dim(self) -> int:
        """Number of parameters d."""
        return len(self.params)

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names, in order."""
        return tuple(p.name for p in self.params)

    @property
    def lows(self) -> np.ndarray:
        """(d,) lower bounds in natural units."""
        return np.array([p.low for p in self.params])

    @property
    def highs(self) -> np.ndarray:
        """(d,) upper bounds in natural units."""
        return np.array([p.high for p in self.params])

    # ---------------------------------------------------------------- mapping
    def to_unit(self, x: Any) -> np.ndarray:
        """Natural units (d,) or (n, d) → unit cube, same shape."""
        xa = self._check_shape(x, "x")
        return np.stack([p.to_unit(xa[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def from_unit(self, u: Any) -> np.ndarray:
        """Unit cube (d,) or (n, d) → natural units, same shape, clipped to the bounds."""
        ua = self._check_shape(u, "u")
        return np.stack([p.from_unit(ua[..., i]) for i, p in enumerate(self.params)], axis=-1)

    def centre(self) -> np.ndarray:
        """(d,) centre of the unit cube mapped to natural units (geometric mean on log10)."""
        return self.from_unit(np.full(self.dim, 0.5))

    def as_dict(self, x: Any) -> dict[str, float]:
        """A (d,) natural-units point as ``{name: value}``."""
        xa = self._check_shape(x, "x")
        if xa.ndim != 1:
            raise ValueError(f"as_dict expects one (d,) point, got shape {xa.shape}")
        return {p.name: float(v) for p, v in zip(self.params, xa)}

    def contains(self, x: Any) -> bool:
        """True if every coordinate of the (d,) natural-units point lies within its bounds."""
        xa = self._check_shape(x, "x")
        return bool(np.all((xa >= self.lows) & (xa <= self.highs)))

    def on_bounds(self, u: Any, tol: float = BOUND_TOL) -> list[BoundHit]:
        """The coordinates of a ``(d,)`` unit-cube point that lie within ``tol`` of a face
        of the cube (``u_i ≤ tol`` or ``u_i ≥ 1 − tol``), in parameter order — where the
        best point of a search sits against the box, so the optimum may lie beyond it."""
        ua = self._check_shape(u, "u")
        if ua.ndim != 1:
            raise ValueError(f"on_bounds expects one (d,) point, got shape {ua.shape}")
        x = self.from_unit(ua)
        hits = []
        for p, ui, xi in zip(self.params, ua, x):
            if ui <= tol:
                hits.append(BoundHit(p.name, "lower", float(xi), p.low))
            elif ui >= 1.0 - tol:
                hits.append(BoundHit(p.name, "upper", float(xi), p.high))
        return hits

    def widened(self, hits: Sequence[BoundHit], decades: float) -> Space:
        """This space with the bounds named in ``hits`` moved outwards by ``decades``
        decades, on log10 parameters only (a linear parameter has no scale-free extension,
        and its bounds are often physical limits: it keeps its bounds). Returns ``self``
        when nothing changes."""
        if not decades > 0:
            raise ValueError(f"decades must be positive, got {decades!r}")
        factor = 10.0**decades
        bounds = {p.name: [p.low, p.high] for p in self.params}
        for h in hits:
            if not self.params[self.names.index(h.name)].log:
                continue
            if h.side == "lower":
                bounds[h.name][0] /= factor
            else:
                bounds[h.name][1] *= factor
        # replace() keeps every other field: a physical parameter stays physical in the
        # wider box (TR-BO's design reads it in the next round).
        params = tuple(
            replace(p, low=bounds[p.name][0], high=bounds[p.name][1]) for p in self.params
        )
        return self if params == self.params else Space(params)

    def _check_shape(self, a: Any, what: str) -> np.ndarray:
        arr = np.asarray(a, dtype=float)
        if arr.ndim not in (1, 2) or arr.shape[-1] != self.dim:
            raise ValueError(
                f"{what} must have shape ({self.dim},) or (n, {self.dim}) for parameters "
                f"{list(self.names)}, got {arr.shape}"
            )
        return arr


def _param_from(name: str, spec: Any) -> Param:
    """A :class:`Param` from ``(low, high)`` or ``(low, high, scale)``."""
    if isinstance(spec, Param):
        return spec
    if isinstance(spec, Mapping):
        return Param(name=name, **spec)
    try:
        items = tuple(spec)
    except TypeError:
        raise ValueError(
            f"parameter {name!r}: expected (low, high) or (low, high, scale), got {spec!r}"
        ) from None
    if len(items) not in (2, 3):
        raise ValueError(
            f"parameter {name!r}: expected (low, high) or (low, high, scale), got {spec!r}"
        )
    return Param(name, *items)
