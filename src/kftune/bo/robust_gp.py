"""GP regression with a Student-t noise likelihood, by the Laplace approximation.

This is the model the paper's GPML configuration actually is ("t-Student likelihood"): a
Gaussian-process prior on the latent cost f and heavy-tailed observation noise

    p(y_i | f_i) = Γ((ν+1)/2) / (Γ(ν/2) √(νπ) σ) · (1 + (y_i − f_i)²/(νσ²))^(−(ν+1)/2),

so that a few wild observations are explained as noise instead of bending f.

**Why Laplace (and not variational Bayes as GPML's ``infVB``).** Both give a Gaussian q(f)
and a deterministic approximate marginal likelihood; Vanhatalo, Jylänki & Vehtari (NeurIPS
2009, "Gaussian process regression with Student-t likelihood") found the Laplace
approximation about as accurate as VB/EP for this likelihood and the cheapest of them. It
has a closed-form gradient (R&W Sec. 5.5.1, generalised below to the non-log-concave case),
so the same seeded multi-start L-BFGS-B as the GP and the tSP fits its hyperparameters, and
it is a deterministic function of θ (Newton always starts at f = 0), which keeps fitting
bit-reproducible.

Non-log-concavity. W = −∇∇ log p(y|f) is negative for residuals r² > νσ², so R&W's
symmetric B = I + W½KW½ does not exist. Everything is written instead with K = L Lᵀ and
A = I + LᵀWL (symmetric, positive definite exactly when K⁻¹ + W is, i.e. at a strict
local maximum of the posterior):

    (K⁻¹ + W)⁻¹ = L A⁻¹ Lᵀ,   (I + KW)⁻¹ = L A⁻¹ L⁻¹,   |I + KW| = |A|,
    (K + W⁻¹)⁻¹ = K⁻¹ − L⁻ᵀ A⁻¹ L⁻¹.

Mode finding: Newton on Ψ(f) = log p(y|f) − ½ fᵀK⁻¹f (R&W Alg. 3.1 in the above form),
with W clipped to max(W, 0) whenever K⁻¹ + W is not positive definite (a positive-definite
modification, so every step is an ascent direction) and step halving until Ψ increases.

Approximate log marginal likelihood (R&W eq. 3.32): log q(y) = −½ f̂ᵀK⁻¹f̂ + log p(y|f̂)
− ½ log|A|. Its gradient (R&W eq. 5.21–5.24, with a = K⁻¹f̂, C = L A⁻¹ Lᵀ):

    kernel θ_j:  ½ aᵀ∂K a − ½ tr((K⁻¹ − L⁻ᵀA⁻¹L⁻¹) ∂K) + s2ᵀ (I + KW)⁻¹ ∂K a,
    likelihood θ: Σ ∂log p_i/∂θ − ½ Σ C_ii ∂W_ii/∂θ + s2ᵀ C ∂(∇ log p)/∂θ,
    s2_i = ∂ log q/∂f̂_i = ½ C_ii ∂³ log p/∂f_i³

(the implicit terms through f̂(θ); checked against finite differences in the tests).
Predictions are of the latent f, Gaussian: mean k*ᵀa, variance k** − vᵀ(I − A⁻¹)v with
v = L⁻¹k* (R&W eq. 3.21 and 3.24 in the above form).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.linalg import lapack
from scipy.special import digamma, gammaln

from kftune.bo._linalg import (
    cho_inverse,
    cho_solve,
    cholesky_jitter,
    solve_lower,
    solve_upper_t,
)
from kftune.bo._model import BoxSurrogate, ThetaSpec, _check_positive_pair, log_box
from kftune.bo.kernels import squared_differences

_MAX_NEWTON = 100


def _student_t_derivatives(
    r: np.ndarray, nu: float, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-observation log p(y|f) and its first three f-derivatives at residuals r = y − f.

    Returns (log p (n,), ∇ log p (n,), W = −∇² log p (n,), ∇³ log p (n,)).
    """
    a = nu * sigma * sigma
    q = a + r * r
    logp = (
        gammaln(0.5 * (nu + 1.0))
        - gammaln(0.5 * nu)
        - 0.5 * math.log(nu * math.pi)
        - math.log(sigma)
        - 0.5 * (nu + 1.0) * np.log1p(r * r / a)
    )
    g = (nu + 1.0) * r / q
    W = (nu + 1.0) * (a - r * r) / (q * q)
    d3 = 2.0 * (nu + 1.0) * r * (r * r - 3.0 * a) / (q * q * q)
    return logp, g, W, d3


def _student_t_param_derivatives(
    r: np.ndarray, nu: float, sigma: float, *, with_nu: bool
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """∂/∂θ of (log p, ∇ log p, W) per observation, for θ = log σ (and θ = log ν)."""
    a = nu * sigma * sigma
    r2 = r * r
    q = a + r2
    out = [
        (
            -1.0 + (nu + 1.0) * r2 / q,  # ∂ log p/∂ log σ
            -2.0 * (nu + 1.0) * r * a / (q * q),  # ∂ g/∂ log σ
            2.0 * a * (nu + 1.0) * (3.0 * r2 - a) / (q * q * q),  # ∂ W/∂ log σ
        )
    ]
    if with_nu:
        s2 = sigma * sigma
        dlogp = (
            0.5 * digamma(0.5 * (nu + 1.0))
            - 0.5 * digamma(0.5 * nu)
            - 0.5 / nu
            - 0.5 * np.log1p(r2 / a)
            + 0.5 * (nu + 1.0) * r2 / (nu * q)
        )
        dg = r / q - (nu + 1.0) * r * s2 / (q * q)
        dW = (
            (a - r2) / (q * q)
            + (nu + 1.0) * s2 / (q * q)
            - 2.0 * (nu + 1.0) * (a - r2) * s2 / (q * q * q)
        )
        out.append((nu * dlogp, nu * dg, nu * dW))  # θ = log ν: d/dθ = ν d/dν
    return out


class RobustGaussianProcess(BoxSurrogate):
    """GP prior + Student-t observation noise, Laplace approximation (see module docstring).

    Extra keyword-only args (besides :class:`~kftune.bo._model.BoxSurrogate`'s):
        likelihood_dof: ν of the Student-t noise (default 4, the usual robust choice of
            Vanhatalo et al. 2009 and Gelman et al.; heavier tails for smaller ν).
        fit_likelihood_dof: also fit ν (as log ν within ``likelihood_dof_bounds``). Off by
            default: ν and σ trade off against each other and the fit gets multimodal.
        likelihood_dof_bounds: (low, high) for a fitted ν.
        noise_scale_bounds: (low, high) for the Student-t scale σ, in standardised output
            units.

    Outputs are standardised robustly (median and 1.4826·MAD, so that the outliers this
    model exists for do not set the scale); the prior mean is the median of y.
    """

    model_name = "robust-gp"

    def __init__(
        self,
        *,
        likelihood_dof: float = 4.0,
        fit_likelihood_dof: bool = False,
        likelihood_dof_bounds: tuple[float, float] = (1.0, 100.0),
        noise_scale_bounds: tuple[float, float] = (1e-3, 10.0),
        **options: Any,
    ) -> None:
        super().__init__(**options)
        nu = float(likelihood_dof)
        if not (nu > 0.0 and math.isfinite(nu)):
            raise ValueError(f"likelihood_dof must be a finite number > 0, got {likelihood_dof}")
        self.likelihood_dof = nu
        self.fit_likelihood_dof = bool(fit_likelihood_dof)
        self.likelihood_dof_bounds = _check_positive_pair(
            "likelihood_dof_bounds", likelihood_dof_bounds
        )
        lo, hi = self.likelihood_dof_bounds
        if self.fit_likelihood_dof and not lo <= nu <= hi:
            raise ValueError(
                f"likelihood_dof {nu} must lie inside likelihood_dof_bounds "
                f"{likelihood_dof_bounds!r}"
            )
        self.noise_scale_bounds = _check_positive_pair("noise_scale_bounds", noise_scale_bounds)
        self._L: np.ndarray | None = None
        self._LA: np.ndarray | None = None
        self._a: np.ndarray | None = None
        self._laplace_converged = True

    # ------------------------------------------------------------------ hyperparameters
    def _theta_spec(self, d: int) -> ThetaSpec:
        names = [f"log_length_scale[{i}]" for i in range(d)] + [
            "log_signal_variance",
            "log_noise_scale",
        ]
        b_l, i_l, d_l = log_box(self.length_scale_bounds, (0.05, 2.0), 0.5)
        b_s, i_s, d_s = log_box(self.signal_variance_bounds, (0.2, 5.0), 1.0)
        b_n, i_n, d_n = log_box(self.noise_scale_bounds, (1e-2, 0.5), 0.1)
        bounds = [b_l] * d + [b_s, b_n]
        init = [i_l] * d + [i_s, i_n]
        default = [d_l] * d + [d_s, d_n]
        if self.fit_likelihood_dof:
            b, i, dflt = log_box(self.likelihood_dof_bounds, (2.0, 20.0), self.likelihood_dof)
            names.append("log_likelihood_dof")
            bounds.append(b)
            init.append(i)
            default.append(dflt)
        return ThetaSpec(tuple(names), np.array(bounds), np.array(default), np.array(init))

    def _standardisation(self, y: np.ndarray) -> tuple[float, float]:
        center = float(np.median(y))
        scale = 1.4826 * float(np.median(np.abs(y - center)))  # MAD → σ for a Gaussian
        if not scale > 1e-12 * max(1.0, abs(center)):
            scale = float(np.std(y))
        if not scale > 1e-12 * max(1.0, abs(center)):
            scale = 1.0
        return center, scale

    def _lik_params(self, theta: np.ndarray) -> tuple[float, float]:
        d = self._d or 0
        sigma = math.exp(theta[d + 1])
        nu = math.exp(theta[d + 2]) if self.fit_likelihood_dof else self.likelihood_dof
        return nu, sigma

    # ------------------------------------------------------------------ Laplace
    def _laplace(
        self, theta: np.ndarray, *, gradient: bool
    ) -> tuple[float, np.ndarray | None, dict[str, Any] | None]:
        """Mode, approximate log marginal likelihood and (optionally) its gradient.

        Returns (log q, grad or None, cache for prediction or None on failure)."""
        d = self._d or 0
        assert self._S is not None and self._ys is not None
        y = self._ys
        n = y.shape[0]
        K, dK = self.kernel.from_squared_differences(theta[: d + 1], self._S, gradient=gradient)
        L, jitter = cholesky_jitter(K)
        if L is None:
            return -math.inf, None, None
        if jitter:
            K = K + jitter * np.eye(n)
        nu, sigma = self._lik_params(theta)
        eye = np.eye(n)

        def psi_of(a: np.ndarray, f: np.ndarray) -> float:
            logp, _, _, _ = _student_t_derivatives(y - f, nu, sigma)
            return float(logp.sum() - 0.5 * a @ f)

        a = np.zeros(n)
        f = np.zeros(n)
        psi = psi_of(a, f)
        converged = False
        for _ in range(_MAX_NEWTON):
            _, g, W, _ = _student_t_derivatives(y - f, nu, sigma)
            # Converged when ∇Ψ = ∇log p − K⁻¹f = g − a vanishes (relative to g): the
            # implicit gradient terms assume an exact mode, so Ψ's own stall is not enough.
            if float(np.max(np.abs(g - a))) <= 1e-11 * (1.0 + float(np.max(np.abs(g)))):
                converged = True
                break
            LA = _chol_A(L, W, eye)
            if LA is None:  # K⁻¹ + W indefinite: positive-definite modification of W
                W = np.maximum(W, 0.0)
                LA = _chol_A(L, W, eye)
                if LA is None:
                    return -math.inf, None, None
            b = W * f + g
            # a_new = K⁻¹ (K⁻¹ + W)⁻¹ b = L⁻ᵀ A⁻¹ Lᵀ b
            da = solve_upper_t(L, cho_solve(LA, L.T @ b)) - a
            # Step halving until Ψ increases; near the mode the gain is below Ψ's rounding
            # error, so a step that loses no more than that is accepted too.
            tol = 1e-13 * (1.0 + abs(psi))
            step = 1.0
            while True:
                a_try = a + step * da
                f_try = K @ a_try
                psi_try = psi_of(a_try, f_try)
                if psi_try >= psi - tol:
                    break
                step *= 0.5
                if step < 1e-10:
                    break
            if not psi_try >= psi - tol:
                break  # no ascent along the Newton direction: give up (flagged below)
            a, f, psi = a_try, f_try, psi_try
        self._laplace_converged = converged
        r = y - f
        logp, g, W, d3 = _student_t_derivatives(r, nu, sigma)
        LA = _chol_A(L, W, eye)
        if LA is None:  # not a strict local maximum: the approximation is undefined
            return -math.inf, None, None
        log_q = float(logp.sum() - 0.5 * a @ f - np.sum(np.log(np.diag(LA))))
        cache = {"L": L, "LA": LA, "a": a, "jitter": jitter}
        if not gradient:
            return log_q, None, cache
        assert dK is not None
        Ainv = cho_inverse(LA)
        Linv = solve_lower(L, eye)
        LAinvLt = L @ Ainv  # L A⁻¹
        C = LAinvLt @ L.T  # (K⁻¹ + W)⁻¹
        diagC = np.diag(C)
        s2 = 0.5 * diagC * d3  # ∂ log q / ∂ f̂
        m = solve_upper_t(L, Ainv @ (L.T @ s2))  # (I + KW)⁻ᵀ s2 = L⁻ᵀ A⁻¹ Lᵀ s2
        R = Linv.T @ (eye - Ainv) @ Linv  # (K + W⁻¹)⁻¹
        M = 0.5 * np.outer(a, a) - 0.5 * R + 0.5 * (np.outer(m, a) + np.outer(a, m))
        grad = np.empty_like(theta)
        grad[: d + 1] = dK.reshape(d + 1, -1) @ M.ravel()
        Cs2 = C @ s2
        for k, (dlogp, dg, dW) in enumerate(
            _student_t_param_derivatives(r, nu, sigma, with_nu=self.fit_likelihood_dof)
        ):
            grad[d + 1 + k] = dlogp.sum() - 0.5 * diagC @ dW + Cs2 @ dg
        return log_q, grad, cache

    def _nll_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        log_q, grad, _ = self._laplace(theta, gradient=True)
        if grad is None or not math.isfinite(log_q):
            return math.inf, np.zeros_like(theta)
        return -log_q, -grad

    def _condition_standardised(self, theta: np.ndarray, mean_s: float | None) -> bool:
        _, _, cache = self._laplace(theta, gradient=False)
        if cache is None:
            return False
        self._L, self._LA, self._a = cache["L"], cache["LA"], cache["a"]
        self._jitter = cache["jitter"]
        self._mean_s = 0.0
        return True

    def _predict_standardised(self, Xn: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        assert self._Xn is not None and self._theta is not None and self._L is not None
        assert self._LA is not None and self._a is not None
        d = self._d or 0
        theta_k = self._theta[: d + 1]
        Ks, _ = self.kernel.from_squared_differences(theta_k, squared_differences(self._Xn, Xn))
        mean = Ks.T @ self._a  # R&W eq. 3.21: k*ᵀ ∇log p(y|f̂) = k*ᵀ K⁻¹ f̂
        v = solve_lower(self._L, Ks)
        u = solve_lower(self._LA, v)
        # R&W eq. 3.24: k** − k*ᵀ(K + W⁻¹)⁻¹k* = k** − vᵀv + vᵀA⁻¹v
        var = math.exp(theta_k[d]) - np.einsum("ij,ij->j", v, v) + np.einsum("ij,ij->j", u, u)
        np.maximum(var, 0.0, out=var)
        return mean, var, math.inf

    def _natural_hyperparameters(self) -> dict[str, Any]:
        assert self._theta is not None
        nu, sigma = self._lik_params(self._theta)
        return {
            "noise_scale": float(sigma * self._y_scale),
            "likelihood_dof": float(nu),
            "likelihood_dof_fitted": self.fit_likelihood_dof,
            "inference": "laplace",
            "laplace_converged": bool(self._laplace_converged),
        }


def _chol_A(L: np.ndarray, W: np.ndarray, eye: np.ndarray) -> np.ndarray | None:
    """Lower Cholesky factor of A = I + Lᵀ diag(W) L, or None when A is not positive
    definite (K⁻¹ + W indefinite)."""
    A = eye + (L.T * W) @ L
    LA, info = lapack.dpotrf(A, lower=1, clean=1)
    return LA if info == 0 else None
