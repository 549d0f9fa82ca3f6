"""Student-t process regression (Shah, Wilson & Ghahramani, AISTATS 2014; paper Eq. 3, 6–7).

y ~ MVT_n(ν, m·1, K): a multivariate Student-t whose *covariance* is K, i.e. whose shape
matrix is (ν−2)/ν·K (Shah et al. 2014, Def. 2). Its log density (ibid., eq. 4/Lemma 3) is

    log p(y) = log Γ((ν+n)/2) − log Γ(ν/2) − n/2·log((ν−2)π) − ½ log|K|
               − (ν+n)/2 · log(1 + β/(ν−2)),      β = (y − m)ᵀ K⁻¹ (y − m),

evaluated with ``gammaln`` and ``log1p`` (no overflow for large ν or n). Conditioning on n
observations (ibid., Lemma 3 / paper Eq. 6–7) gives a Student-t predictive with

    location  m + k*ᵀ K⁻¹ (y − m)          (the GP posterior mean),
    covariance (ν + β − 2)/(ν + n − 2) · (k** − k*ᵀ K⁻¹ k*),
    dof        ν + n.

Noise is part of the kernel (K + σ_n² I), as in Shah et al. (their Sec. 3: independent
t noise would not give an analytic marginal).

Gradient: with α = K⁻¹(y − m), ∂β/∂θ = −αᵀ(∂K/∂θ)α, hence

    ∂ log p/∂θ_j = ½ tr((w ααᵀ − K⁻¹) ∂K/∂θ_j),   w = (ν + n)/(ν − 2 + β),

the GP gradient (R&W eq. 5.9) with ααᵀ re-weighted by w; w → 1 as ν → ∞. For ν:

    ∂ log p/∂ν = ½ψ((ν+n)/2) − ½ψ(ν/2) − n/(2(ν−2)) − ½ log(1 + β/(ν−2))
                 + (ν+n)β / (2(ν−2)(ν−2+β)).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.special import digamma, gammaln

from kftune.bo._model import ThetaSpec, _check_positive_pair, log_box
from kftune.bo.gp import ExactSurrogate


class StudentTProcess(ExactSurrogate):
    """Student-t process with a constant mean and a Matérn 5/2 (or SE) ARD kernel.

    Extra keyword-only args (besides :class:`~kftune.bo.gp.ExactSurrogate`'s):
        dof: prior degrees of freedom ν > 2 (paper Table III: 15). Used as is, or as the
            first start when ``fit_dof``.
        fit_dof: also fit ν by maximum likelihood, as ``log(ν − 2)`` within ``dof_bounds``.
        dof_bounds: (low, high) for a fitted ν, low > 2.

    Predictions are Student-t with ``dof = ν + n``; ``Predictive.variance`` is the
    predictive variance (paper Eq. 7), not the squared t scale.
    """

    model_name = "tsp"

    def __init__(
        self,
        *,
        dof: float = 15.0,
        fit_dof: bool = False,
        dof_bounds: tuple[float, float] = (2.5, 1000.0),
        **options: Any,
    ) -> None:
        super().__init__(**options)
        dof = float(dof)
        if not (dof > 2.0):
            raise ValueError(f"dof must be > 2 (finite variance), got {dof}")
        self.dof = dof
        self.fit_dof = bool(fit_dof)
        lo, hi = _check_positive_pair("dof_bounds", dof_bounds)
        if not lo > 2.0:
            raise ValueError(f"dof_bounds low must be > 2, got {dof_bounds!r}")
        if self.fit_dof and not lo <= dof <= hi:
            raise ValueError(f"dof {dof} must lie inside dof_bounds {dof_bounds!r}")
        self.dof_bounds = (lo, hi)
        self._n = 0

    def _theta_spec(self, d: int) -> ThetaSpec:
        names, bounds, init, default = self._base_spec(d)
        if self.fit_dof:
            lo, hi = self.dof_bounds
            b, i, dflt = log_box((lo - 2.0, hi - 2.0), (1.0, 50.0), self.dof - 2.0)
            names.append("log_dof_minus_2")
            bounds.append(b)
            init.append(i)
            default.append(dflt)
        return ThetaSpec(tuple(names), np.array(bounds), np.array(default), np.array(init))

    def _nu(self, theta: np.ndarray) -> float:
        if self.fit_dof:
            return 2.0 + math.exp(theta[-1])
        return self.dof

    def _log_likelihood_terms(
        self, theta: np.ndarray, n: int, beta: float, log_det: float
    ) -> tuple[float, float, float]:
        nu = self._nu(theta)
        nu2 = nu - 2.0
        # Shah et al. 2014: MVT log density with covariance K (shape (ν−2)/ν K).
        ll = (
            gammaln(0.5 * (nu + n))
            - gammaln(0.5 * nu)
            - 0.5 * n * math.log(nu2 * math.pi)
            - 0.5 * log_det
            - 0.5 * (nu + n) * math.log1p(beta / nu2)
        )
        w = (nu + n) / (nu2 + beta)
        g_nu = 0.0
        if self.fit_dof:
            dll_dnu = (
                0.5 * digamma(0.5 * (nu + n))
                - 0.5 * digamma(0.5 * nu)
                - 0.5 * n / nu2
                - 0.5 * math.log1p(beta / nu2)
                + 0.5 * (nu + n) * beta / (nu2 * (nu2 + beta))
            )
            g_nu = nu2 * dll_dnu  # θ = log(ν − 2): dν/dθ = ν − 2
        return float(ll), w, float(g_nu)

    def _condition_standardised(self, theta: np.ndarray, mean_s: float | None) -> bool:
        ok = super()._condition_standardised(theta, mean_s)
        self._n = 0 if self._ys is None else int(self._ys.shape[0])
        return ok

    def _variance_factor(self) -> float:
        # Paper Eq. 7 / Shah et al. 2014 Lemma 3: (ν + β_n − 2)/(ν + n − 2).
        assert self._theta is not None
        nu = self._nu(self._theta)
        return (nu + self._beta - 2.0) / (nu + self._n - 2.0)

    def _predictive_dof(self) -> float:
        assert self._theta is not None
        return self._nu(self._theta) + self._n

    def _natural_hyperparameters(self) -> dict[str, Any]:
        out = super()._natural_hyperparameters()
        assert self._theta is not None
        out["dof"] = float(self._nu(self._theta))
        out["dof_fitted"] = self.fit_dof
        return out
