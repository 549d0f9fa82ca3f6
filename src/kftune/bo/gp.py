"""Exact Gaussian-process regression (Rasmussen & Williams 2006, Alg. 2.1 and eq. 5.8–5.9).

:class:`ExactSurrogate` holds what the GP and the Student-t process share — a stationary ARD
kernel, an optional fitted Gaussian noise variance, a constant mean (profiled by generalised
least squares or fixed at zero), and the Cholesky-based posterior — and leaves to subclasses
only the marginal likelihood and the scaling of the posterior variance.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kftune.bo._linalg import (
    cho_inverse,
    cho_solve,
    cholesky_jitter,
    log_det_from_cholesky,
    solve_lower,
)
from kftune.bo._model import BoxSurrogate, ThetaSpec, _check_positive_pair, log_box
from kftune.bo.kernels import squared_differences

LOG_2PI = math.log(2.0 * math.pi)
MEANS = ("constant", "zero")


class ExactSurrogate(BoxSurrogate):
    """Base of :class:`GaussianProcess` and :class:`StudentTProcess` (exact inference).

    Extra keyword-only args (besides :class:`~kftune.bo._model.BoxSurrogate`'s):
        noise: ``None`` (default) fits a Gaussian noise variance σ_n²; a number fixes it.
            In standardised output units, i.e. as a fraction of var(y) — the meaning of
            scikit-learn's ``alpha`` with ``normalize_y=True``.
        noise_bounds: (low, high) for a fitted σ_n² (standardised units).
        mean: ``"constant"`` (default): a constant prior mean, set to its maximum-likelihood
            value for the current kernel by generalised least squares,
            m̂ = 1ᵀK⁻¹y / 1ᵀK⁻¹1 (exact profiling: the likelihood gradient needs no extra
            term, by the envelope theorem); ``"zero"``: zero in standardised units, i.e. the
            sample mean of y (what scikit-learn's ``normalize_y=True`` does).
    """

    def __init__(
        self,
        *,
        noise: float | None = None,
        noise_bounds: tuple[float, float] = (1e-8, 1.0),
        mean: str = "constant",
        **options: Any,
    ) -> None:
        super().__init__(**options)
        if noise is not None:
            noise = float(noise)
            if not (noise >= 0.0 and math.isfinite(noise)):
                raise ValueError(
                    f"noise must be None (fitted) or a finite number >= 0, got {noise}"
                )
        self.noise = noise
        self.noise_bounds = _check_positive_pair("noise_bounds", noise_bounds)
        if mean not in MEANS:
            raise ValueError(f"mean must be one of {MEANS}, got {mean!r}")
        self.mean = mean
        self._L: np.ndarray | None = None
        self._y1: np.ndarray | None = None  # [y, 1], the right-hand sides of the GLS mean
        self._alpha: np.ndarray | None = None
        self._beta: float = 0.0

    def _set_data(self, X: np.ndarray, y: np.ndarray) -> None:
        super()._set_data(X, y)
        self._y1 = None

    # ------------------------------------------------------------------ hyperparameters
    def _base_spec(
        self, d: int
    ) -> tuple[list[str], list[list[float]], list[list[float]], list[float]]:
        names = [f"log_length_scale[{i}]" for i in range(d)] + ["log_signal_variance"]
        b_l, i_l, d_l = log_box(self.length_scale_bounds, (0.05, 2.0), 0.5)
        b_s, i_s, d_s = log_box(self.signal_variance_bounds, (0.2, 5.0), 1.0)
        bounds = [b_l] * d + [b_s]
        init = [i_l] * d + [i_s]
        default = [d_l] * d + [d_s]
        if self.noise is None:
            b_n, i_n, d_n = log_box(self.noise_bounds, (1e-6, 1e-1), 1e-4)
            names.append("log_noise_variance")
            bounds.append(b_n)
            init.append(i_n)
            default.append(d_n)
        return names, bounds, init, default

    def _theta_spec(self, d: int) -> ThetaSpec:
        names, bounds, init, default = self._base_spec(d)
        return ThetaSpec(tuple(names), np.array(bounds), np.array(default), np.array(init))

    def _noise_variance(self, theta: np.ndarray) -> float:
        d = self._d or 0
        return math.exp(theta[d + 1]) if self.noise is None else float(self.noise)

    # ------------------------------------------------------------------ likelihood
    def _factorise(
        self, theta: np.ndarray, *, gradient: bool
    ) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None, float, float]:
        """Cholesky of K + σ_n²I (+ jitter if needed). Returns (L, (K, G) for the gradient
        or None, noise, jitter); see :meth:`Kernel.contract_gradient`."""
        d = self._d or 0
        assert self._S is not None
        if gradient:
            K, G = self.kernel.gram_for_gradient(theta[: d + 1], self._S)
            parts: tuple[np.ndarray, np.ndarray] | None = (K.copy(), G)
        else:
            K, _ = self.kernel.from_squared_differences(theta[: d + 1], self._S)
            parts = None
        noise = self._noise_variance(theta)
        K.flat[:: K.shape[0] + 1] += noise
        L, jitter = cholesky_jitter(K)
        return L, parts, noise, jitter

    def _residual_solve(
        self, L: np.ndarray, mean_s: float | None
    ) -> tuple[float, np.ndarray, float]:
        """Constant mean m, α = K⁻¹(y − m) and β = (y − m)ᵀK⁻¹(y − m)."""
        y = self._ys
        assert y is not None
        if mean_s is None and self.mean == "constant":
            # GLS estimate m̂ = 1ᵀK⁻¹y / 1ᵀK⁻¹1 (R&W eq. 2.42 with h(x) = 1).
            if self._y1 is None or self._y1.shape[0] != y.shape[0]:
                self._y1 = np.column_stack([y, np.ones_like(y)])
            sol = cho_solve(L, self._y1)
            m = float(sol[:, 0].sum() / sol[:, 1].sum())
            alpha = sol[:, 0] - m * sol[:, 1]
        else:
            m = 0.0 if mean_s is None else float(mean_s)
            alpha = cho_solve(L, y - m)
        return m, alpha, float((y - m) @ alpha)

    def _log_likelihood_terms(
        self, theta: np.ndarray, n: int, beta: float, log_det: float
    ) -> tuple[float, float, float]:
        """(log likelihood, weight w of ααᵀ in the gradient, ∂ll/∂(extra theta) or 0)."""
        # R&W eq. 2.30 / 5.8: log p(y) = −½ yᵀK⁻¹y − ½ log|K| − n/2 log 2π.
        return -0.5 * beta - 0.5 * log_det - 0.5 * n * LOG_2PI, 1.0, 0.0

    def _nll_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        d = self._d or 0
        L, parts, noise, _ = self._factorise(theta, gradient=True)
        if L is None or parts is None:
            return math.inf, np.zeros_like(theta)
        n = L.shape[0]
        _, alpha, beta = self._residual_solve(L, None)
        ll, w, g_extra = self._log_likelihood_terms(theta, n, beta, log_det_from_cholesky(L))
        # R&W eq. 5.9: ∂ll/∂θ_j = ½ tr((w ααᵀ − K⁻¹) ∂K/∂θ_j), w = 1 for the GP; the tSP
        # differs only by w (see student_t.py).
        Wm = w * np.outer(alpha, alpha) - cho_inverse(L)
        grad = np.empty_like(theta)
        assert self._S is not None
        grad[: d + 1] = 0.5 * self.kernel.contract_gradient(theta, self._S, *parts, Wm)
        k = d + 1
        if self.noise is None:
            grad[k] = 0.5 * noise * float(np.trace(Wm))  # ∂K/∂log σ_n² = σ_n² I
            k += 1
        if k < theta.shape[0]:
            grad[k] = g_extra
        return -ll, -grad

    # ------------------------------------------------------------------ posterior
    def _condition_standardised(self, theta: np.ndarray, mean_s: float | None) -> bool:
        L, _, _, jitter = self._factorise(theta, gradient=False)
        if L is None:
            return False
        m, alpha, beta = self._residual_solve(L, mean_s)
        self._L, self._alpha, self._beta = L, alpha, beta
        self._mean_s, self._jitter = m, jitter
        return True

    def _variance_factor(self) -> float:
        """Multiplier of the Gaussian posterior variance (1 for the GP)."""
        return 1.0

    def _predictive_dof(self) -> float:
        return math.inf

    def _predict_standardised(self, Xn: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        assert self._Xn is not None and self._L is not None and self._theta is not None
        d = self._d or 0
        theta_k = self._theta[: d + 1]
        Ks, _ = self.kernel.from_squared_differences(theta_k, squared_differences(self._Xn, Xn))
        # R&W Alg. 2.1 lines 4–6: mean = m + K*ᵀα, var = k(x,x) − vᵀv, v = L⁻¹K*.
        mean = self._mean_s + Ks.T @ self._alpha
        v = solve_lower(self._L, Ks)
        var = math.exp(theta_k[d]) - np.einsum("ij,ij->j", v, v)
        np.maximum(var, 0.0, out=var)
        return mean, var * self._variance_factor(), self._predictive_dof()

    def _natural_hyperparameters(self) -> dict[str, Any]:
        assert self._theta is not None
        return {"noise_variance": float(self._noise_variance(self._theta) * self._y_scale**2)}


class GaussianProcess(ExactSurrogate):
    """Exact GP regression with a constant mean and a Matérn 5/2 (or SE) ARD kernel.

    Hyperparameters (log space): ARD length scales, signal variance, and the noise variance
    unless fixed; fitted by maximising the log marginal likelihood (R&W eq. 5.8) with
    analytic gradients (eq. 5.9). Predictions are of the latent function (noise-free) and
    Gaussian (``dof = inf``).

    See :class:`ExactSurrogate` and :class:`~kftune.bo._model.BoxSurrogate` for the options.
    """

    model_name = "gp"
