"""The one contract between surrogates and acquisition functions.

A surrogate is fitted on observations and returns a :class:`Predictive`; an acquisition
function reads only a :class:`Predictive` (and the incumbent). That is the whole coupling
(cf. BoTorch: a model returns a posterior, an acquisition function reads mean/variance),
so any surrogate works with any acquisition function.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Largest |y| a surrogate accepts (every kftune surrogate refuses more, naming the row):
#: its variances are squares in the units of y and must stay finite in float64. TSBO clips
#: the values it passes to this.
MAX_ABS_Y = 1e100


@dataclass(frozen=True)
class Predictive:
    """Marginal predictive distribution at m query points, in the units of the observations.

    Attributes:
        mean: (m,) predictive mean (location).
        variance: (m,) predictive variance (not the squared t scale), >= 0; ``inf`` where
            it does not exist (a Student-t with dof <= 2, built by :meth:`from_scale`).
        dof: degrees of freedom of the predictive Student-t; ``math.inf`` for a Gaussian.
            For a Student-t with dof ν' > 2 the scale is ``sqrt(variance·(ν'−2)/ν')``.
        t_scale: (m,) the Student-t scale when given explicitly (only needed for dof <= 2,
            where the variance is infinite and cannot carry the scale); ``None`` otherwise.

    Notation used throughout :mod:`kftune.bo`: σ (``std``) is always the standard
    deviation √variance; s (``scale``) is the scale of the location-scale family, equal to
    σ for a Gaussian and to σ·√((ν'−2)/ν') for a Student-t.
    """

    mean: np.ndarray
    variance: np.ndarray
    dof: float = math.inf
    t_scale: np.ndarray | None = None

    def __post_init__(self) -> None:
        try:
            mean, variance = np.broadcast_arrays(
                np.asarray(self.mean, dtype=float), np.asarray(self.variance, dtype=float)
            )
        except ValueError:
            raise ValueError(
                f"Predictive: mean shape {np.shape(self.mean)} and variance shape "
                f"{np.shape(self.variance)} do not broadcast"
            ) from None
        if not (self.dof > 0):  # also rejects NaN
            raise ValueError(f"Predictive: dof must be > 0 (math.inf for Gaussian), got {self.dof}")
        object.__setattr__(self, "mean", np.array(mean))  # copies: broadcasts are read-only
        object.__setattr__(self, "variance", np.array(variance))
        object.__setattr__(self, "dof", float(self.dof))
        if self.t_scale is not None:
            t_scale = np.asarray(self.t_scale, dtype=float)
            if t_scale.shape != mean.shape:
                raise ValueError(
                    f"Predictive: t_scale shape {t_scale.shape} differs from mean {mean.shape}"
                )
            object.__setattr__(self, "t_scale", t_scale)

    @classmethod
    def from_scale(cls, mean: np.ndarray, scale: np.ndarray, dof: float) -> Predictive:
        """Predictive from a location and a *scale* (not a standard deviation).

        For dof ν > 2 the variance is scale²·ν/(ν−2); for ν <= 2 it is infinite and the
        scale is kept in ``t_scale``. For ``dof = inf`` the scale is the standard deviation.
        """
        mean = np.asarray(mean, dtype=float)
        scale = np.broadcast_to(np.asarray(scale, dtype=float), mean.shape).copy()
        if math.isinf(dof):
            return cls(mean, scale**2, dof)
        if dof > 2.0:
            return cls(mean, scale**2 * dof / (dof - 2.0), dof, scale)
        return cls(mean, np.full(mean.shape, math.inf), dof, scale)

    @property
    def std(self) -> np.ndarray:
        """(m,) predictive standard deviation σ = √variance (``inf`` for dof <= 2)."""
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def scale(self) -> np.ndarray:
        """(m,) scale of the predictive: the t scale √(var·(ν−2)/ν), or σ for a Gaussian."""
        if self.t_scale is not None:
            return self.t_scale
        if math.isinf(self.dof):
            return self.std
        if self.dof <= 2.0:
            raise ValueError(
                f"Predictive: dof {self.dof} <= 2 has no finite variance; build it with "
                "Predictive.from_scale to carry the scale"
            )
        return np.sqrt(np.maximum(self.variance, 0.0) * (self.dof - 2.0) / self.dof)


class Surrogate(ABC):
    """A probabilistic regression model of a black-box function on a box domain.

    Inputs X are (n, d) points; outputs y are (n,). Implementations normalise inputs to
    [0, 1]^d (using ``bounds``) and standardise outputs internally, but always report
    predictions in the units of y.
    """

    @abstractmethod
    def fit(self, X: np.ndarray, y: np.ndarray) -> Surrogate:
        """Fit hyperparameters and condition on (X, y); returns self. Never raises on
        degenerate data (n = 1, duplicated points, constant y)."""

    @abstractmethod
    def condition(self, X: np.ndarray, y: np.ndarray) -> Surrogate:
        """Condition on (X, y) keeping the current hyperparameters (no refit); returns self."""

    @abstractmethod
    def predict(self, X: np.ndarray) -> Predictive:
        """Marginal predictive at (m, d) points."""

    @property
    @abstractmethod
    def hyperparameters(self) -> dict[str, Any]:
        """Current hyperparameters in natural units (JSON-serialisable)."""
