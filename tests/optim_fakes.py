"""Small stand-ins for the optimiser tests: a fixed-hyperparameter GP surrogate that counts
its fits, and test objectives. Kept out of ``kftune`` on purpose."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kftune.bo.base import Predictive, Surrogate


class CountingGP(Surrogate):
    """Zero-mean GP on standardised y with a squared-exponential kernel of fixed length
    scale; ``fit`` "learns" one hyperparameter (the output scale) so a freeze is visible.

    Attributes:
        n_fit, n_condition: how often each was called.
        fit_sizes, condition_sizes: the number of points passed each time.
        fit_inputs, fit_outputs: the (X, y) of every fit.
    """

    def __init__(self, seed: int | None = None, lengthscale: float = 0.2) -> None:
        self.seed = seed
        self.lengthscale = lengthscale
        self.n_fit = 0
        self.n_condition = 0
        self.fit_sizes: list[int] = []
        self.condition_sizes: list[int] = []
        self.fit_inputs: list[np.ndarray] = []
        self.fit_outputs: list[np.ndarray] = []
        self._scale = 1.0

    def _k(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        d2 = ((A[:, None, :] - B[None, :, :]) ** 2).sum(-1)
        return np.exp(-0.5 * d2 / self.lengthscale**2)

    def _set(self, X: np.ndarray, y: np.ndarray) -> None:
        self.X = np.asarray(X, float)
        y = np.asarray(y, float)
        self.mu = float(y.mean())
        self.sd = self._scale
        z = (y - self.mu) / self.sd
        K = self._k(self.X, self.X) + 1e-8 * np.eye(len(self.X))
        self.L = np.linalg.cholesky(K)
        self.alpha = np.linalg.solve(self.L.T, np.linalg.solve(self.L, z))

    def fit(self, X: np.ndarray, y: np.ndarray) -> CountingGP:
        self.n_fit += 1
        self.fit_sizes.append(len(X))
        self.fit_inputs.append(np.array(X, float))
        self.fit_outputs.append(np.array(y, float))
        s = float(np.std(y))
        self._scale = s if s > 0 else 1.0
        self._set(X, y)
        return self

    def condition(self, X: np.ndarray, y: np.ndarray) -> CountingGP:
        self.n_condition += 1
        self.condition_sizes.append(len(X))
        self._set(X, y)
        return self

    def predict(self, X: np.ndarray) -> Predictive:
        Ks = self._k(np.asarray(X, float), self.X)
        mean = self.mu + self.sd * Ks @ self.alpha
        v = np.linalg.solve(self.L, Ks.T)
        var = np.maximum(1.0 - (v**2).sum(0), 1e-12) * self.sd**2
        return Predictive(mean=mean, variance=var, dof=math.inf)

    @property
    def hyperparameters(self) -> dict[str, Any]:
        return {"output_scale": self._scale, "lengthscale": self.lengthscale}


def branin(x: np.ndarray) -> float:
    """Branin-Hoo on [-5, 10] × [0, 15]; minimum 0.397887 at three points."""
    x1, x2 = float(x[0]), float(x[1])
    b, c = 5.1 / (4 * math.pi**2), 5 / math.pi
    return (x2 - b * x1**2 + c * x1 - 6) ** 2 + 10 * (1 - 1 / (8 * math.pi)) * math.cos(x1) + 10


BRANIN_SPACE = {"x1": (-5.0, 10.0), "x2": (0.0, 15.0)}
