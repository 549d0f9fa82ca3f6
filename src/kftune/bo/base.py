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


@dataclass(frozen=True)
class Predictive:
    """Marginal predictive distribution at m query points, in the units of the observations.

    Attributes:
        mean: (m,) predictive mean (location).
        variance: (m,) predictive variance (not the squared t scale), >= 0.
        dof: degrees of freedom of the predictive Student-t; ``math.inf`` for a Gaussian.
            For a Student-t with dof ν' > 2 the scale is ``sqrt(variance·(ν'−2)/ν')``.
    """

    mean: np.ndarray
    variance: np.ndarray
    dof: float = math.inf

    @property
    def std(self) -> np.ndarray:
        """(m,) predictive standard deviation."""
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def scale(self) -> np.ndarray:
        """(m,) scale of the predictive: the t scale √(var·(ν−2)/ν), or σ for a Gaussian."""
        if math.isinf(self.dof):
            return self.std
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
