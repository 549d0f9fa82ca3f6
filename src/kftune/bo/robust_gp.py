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
symmetric B = I + W½KW½ does not exist. As GPML's ``infLaplace`` does in that case,
everything is written with the non-symmetric I + KW and its LU factors (partial pivoting),
which never needs K⁻¹ (K is often nearly singular for smooth kernels):

    (K⁻¹ + W)⁻¹ = (I + KW)⁻¹ K,   (K + W⁻¹)⁻¹ = W (I + KW)⁻¹,   |B| = |I + KW|.

Whether K⁻¹ + W is positive definite (a strict local maximum) is tested by a Cholesky of
I + LᵀWL with K = L Lᵀ.

Mode finding: Newton on Ψ(f) = log p(y|f) − ½ fᵀK⁻¹f (R&W Alg. 3.1):
f_new = (I + KW)⁻¹ K b, a_new = K⁻¹f_new = b − W f_new with b = W f + ∇log p, W clipped to
max(W, 0) whenever K⁻¹ + W is not positive definite (a positive-definite modification, so
every step is an ascent direction), and step halving until Ψ increases.

Approximate log marginal likelihood (R&W eq. 3.32): log q(y) = −½ f̂ᵀK⁻¹f̂ + log p(y|f̂)
− ½ log|B|. Its gradient (R&W eq. 5.21–5.24, with a = K⁻¹f̂, C = (K⁻¹ + W)⁻¹):

    kernel θ_j:  ½ aᵀ∂K a − ½ tr((K + W⁻¹)⁻¹ ∂K) + s2ᵀ (I + KW)⁻¹ ∂K a,
    likelihood θ: Σ ∂log p_i/∂θ − ½ Σ C_ii ∂W_ii/∂θ + s2ᵀ C ∂(∇ log p)/∂θ,
    s2_i = ∂ log q/∂f̂_i = ½ C_ii ∂³ log p/∂f_i³

(the implicit terms through f̂(θ); R&W print eq. 5.23 with the opposite sign, GPML's code
has this one; checked against finite differences in the tests). Predictions are of the
latent f, Gaussian: mean k*ᵀa, variance k** − k*ᵀ W (I + KW)⁻¹ k* (R&W eq. 3.21, 3.24).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.linalg import lapack
from scipy.special import digamma, poch

from kftune.bo._linalg import cho_solve, cholesky_jitter
from kftune.bo._model import BoxSurrogate, ThetaSpec, _check_positive_pair, log_box
from kftune.bo.kernels import squared_differences

_MAX_NEWTON = 200  # small noise scales need ~60 (clipped-W steps are first-order)
_MAX_HALVINGS = 30
#: Relative Newton step in f below which Ψ's rounding error exceeds the step's gain.
_EXACT_STEP = 1e-8


def _student_t_derivatives(
    r: np.ndarray, nu: float, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-observation log p(y|f) and its first three f-derivatives at residuals r = y − f.

    Returns (log p (n,), ∇ log p (n,), W = −∇² log p (n,), ∇³ log p (n,)).
    """
    a = nu * sigma * sigma
    q = a + r * r
    logp = (
        math.log(poch(0.5 * nu, 0.5))  # log Γ((ν+1)/2) − log Γ(ν/2), exact for large ν
        - 0.5 * math.log(nu * math.pi)
        - math.log(sigma)
        - 0.5 * (nu + 1.0) * np.log1p(r * r / a)
    )
    # Written as products of bounded ratios (r/q, (a − r²)/q, 1/q) so that huge residuals
    # give the correct limits (→ 0) instead of overflowing in q² or q³ — for |r| < 1e154,
    # where r² itself is finite (TSBO clips its outputs to ±1e100; the standardisation
    # then keeps r far below that).
    rq, inv_q = r / q, 1.0 / q
    g = (nu + 1.0) * rq
    W = (nu + 1.0) * ((a - r * r) * inv_q) * inv_q
    d3 = 2.0 * (nu + 1.0) * rq * ((r * r - 3.0 * a) * inv_q) * inv_q
    return logp, g, W, d3


def _student_t_param_derivatives(
    r: np.ndarray, nu: float, sigma: float, *, with_nu: bool
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """∂/∂θ of (log p, ∇ log p, W) per observation, for θ = log σ (and θ = log ν)."""
    a = nu * sigma * sigma
    r2 = r * r
    q = a + r2
    rq, inv_q, d = r / q, 1.0 / q, (a - r2) / q  # bounded ratios, as above
    out = [
        (
            -1.0 + (nu + 1.0) * r2 * inv_q,  # ∂ log p/∂ log σ
            -2.0 * (nu + 1.0) * rq * a * inv_q,  # ∂ g/∂ log σ
            2.0 * a * (nu + 1.0) * ((3.0 * r2 - a) * inv_q) * inv_q * inv_q,  # ∂ W/∂ log σ
        )
    ]
    if with_nu:
        s2 = sigma * sigma
        dlogp = (
            0.5 * digamma(0.5 * (nu + 1.0))
            - 0.5 * digamma(0.5 * nu)
            - 0.5 / nu
            - 0.5 * np.log1p(r2 / a)
            + 0.5 * (nu + 1.0) * r2 * inv_q / nu
        )
        dg = rq - (nu + 1.0) * rq * s2 * inv_q
        dW = d * inv_q + (nu + 1.0) * s2 * inv_q * inv_q - 2.0 * (nu + 1.0) * d * s2 * inv_q * inv_q
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
        self._lu: tuple[np.ndarray, np.ndarray] | None = None
        self._W: np.ndarray | None = None
        self._a: np.ndarray | None = None
        self._last_a: np.ndarray | None = None  # warm start of the mode search
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
        L, jitter = cholesky_jitter(K)  # only to test K⁻¹ + W for definiteness
        if L is None:
            return -math.inf, None, None
        if jitter:
            K = K + jitter * np.eye(n)
        nu, sigma = self._lik_params(theta)
        eye = np.eye(n)

        def psi_of(a: np.ndarray, f: np.ndarray) -> float:
            logp, _, _, _ = _student_t_derivatives(y - f, nu, sigma)
            return float(logp.sum() - 0.5 * a @ f)

        # Start from the best (by Ψ) of: the prior mean; the Gaussian-likelihood posterior
        # mean with the Student-t's variance (a far better start when σ is small, where the
        # heavy-tailed Ψ is very flat far from the data); the previous evaluation's mode
        # (GPML's infLaplace keeps it too: L-BFGS-B moves θ a little at a time). The last one
        # is reset at every fit/condition, so a fit stays a deterministic function of its
        # data, start and seed.
        starts = [np.zeros(n)]
        s2 = sigma * sigma * (nu / (nu - 2.0) if nu > 2.0 else 3.0)
        Lg, _ = cholesky_jitter(K + s2 * eye)
        if Lg is not None:
            starts.append(cho_solve(Lg, y))
        if self._last_a is not None and self._last_a.shape == (n,):
            starts.append(self._last_a)
        psi = -math.inf
        for a0 in starts:
            f0 = K @ a0
            psi0 = psi_of(a0, f0)
            if psi0 > psi:
                a, f, psi = a0.copy(), f0, psi0
        if not math.isfinite(psi):
            return -math.inf, None, None
        converged = False
        stalls = 0
        prev_step_f = math.inf
        for _ in range(_MAX_NEWTON):
            _, g, W, _ = _student_t_derivatives(y - f, nu, sigma)
            if W.min() < 0.0 and not _is_posterior_definite(L, W, eye):
                W = np.maximum(W, 0.0)  # positive-definite modification: an ascent direction
            lu = _lu(eye + K * W)
            if lu is None:
                return -math.inf, None, None
            b = W * f + g
            # Newton: f_new = (K⁻¹ + W)⁻¹ b = (I + KW)⁻¹ K b and a_new = K⁻¹ f_new = b − W f_new
            # (no solve with the possibly ill-conditioned K).
            f_new = _lu_solve(lu, K @ b)
            df = f_new - f
            da = (b - W * f_new) - a
            # Converged when the Newton step in f (to first order the distance to the mode)
            # is at rounding level, or when 3 steps in a row that are already small have
            # neither increased Ψ nor shrunk: the rounding floor of f̂ grows with cond(I + KW).
            step_f = float(np.max(np.abs(df))) / (1.0 + float(np.max(np.abs(f))))
            tol = 1e-13 * (1.0 + abs(psi))
            if step_f <= _EXACT_STEP:
                # A step this small changes Ψ by less than Ψ's rounding error, so Ψ cannot
                # judge it: take it whole. (Comparing would halve it at random and stop the
                # search short of the mode, making log q depend on the start to ~1e-9.)
                a_try, f_try = a + da, f + df
                psi_try = psi_of(a_try, f_try)
            else:
                # Step halving until Ψ increases; near the mode the gain is below Ψ's
                # rounding error, so a step that loses no more than that is accepted too.
                step = 1.0
                for _halving in range(_MAX_HALVINGS):
                    a_try = a + step * da
                    f_try = f + step * df
                    psi_try = psi_of(a_try, f_try)
                    if psi_try >= psi - tol:
                        break
                    step *= 0.5
                else:
                    converged = step_f <= 1e-6
                    break  # no ascent along the Newton direction
            # a stall: no gain beyond Ψ's rounding and steps no longer shrinking fast
            stalling = psi_try - psi <= tol and step_f > 0.1 * prev_step_f
            stalls = stalls + 1 if stalling else 0
            prev_step_f = step_f
            a, f, psi = a_try, f_try, psi_try
            if step_f <= 1e-10 or (stalls >= 3 and step_f <= 1e-6):
                converged = True
                break
        self._laplace_converged = converged
        self._last_a = a.copy()
        r = y - f
        logp, g, W, d3 = _student_t_derivatives(r, nu, sigma)
        defined = W.min() >= 0.0 or _is_posterior_definite(L, W, eye)
        if not defined:  # not a strict local maximum: the approximation is undefined
            self._laplace_converged = False
            if gradient:
                return -math.inf, None, None
            # Conditioning only (a fit that ended here): predict with the positive-definite
            # modification rather than fail; the likelihood itself stays −inf.
            W = np.maximum(W, 0.0)
        lu = _lu(eye + K * W)
        if lu is None:
            return -math.inf, None, None
        cache = {"lu": lu, "W": W, "a": a, "jitter": jitter}
        if not defined:
            return -math.inf, None, cache
        # log|B| = log|I + KW| from the LU factors (positive at a strict maximum).
        log_det_B = float(np.sum(np.log(np.abs(np.diag(lu[0])))))
        log_q = float(logp.sum() - 0.5 * a @ f - 0.5 * log_det_B)
        if not gradient:
            return log_q, None, cache
        assert dK is not None
        Q = _lu_solve(lu, eye)  # (I + KW)⁻¹
        C = Q @ K  # (K⁻¹ + W)⁻¹
        C = 0.5 * (C + C.T)
        R = W[:, None] * Q  # (K + W⁻¹)⁻¹ = W (I + KW)⁻¹
        R = 0.5 * (R + R.T)
        diagC = np.diag(C)
        s2 = 0.5 * diagC * d3  # ∂ log q / ∂ f̂
        m = Q.T @ s2  # (I + KW)⁻ᵀ s2
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

    def _set_data(self, X: np.ndarray, y: np.ndarray) -> None:
        super()._set_data(X, y)
        self._last_a = None  # new data: the mode search starts afresh

    def _condition_standardised(self, theta: np.ndarray, mean_s: float | None) -> bool:
        _, _, cache = self._laplace(theta, gradient=False)
        if cache is None:
            return False
        self._lu, self._W, self._a = cache["lu"], cache["W"], cache["a"]
        self._jitter = cache["jitter"]
        self._mean_s = 0.0
        return True

    def _predict_standardised(self, Xn: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        assert self._Xn is not None and self._theta is not None and self._lu is not None
        assert self._W is not None and self._a is not None
        d = self._d or 0
        theta_k = self._theta[: d + 1]
        Ks, _ = self.kernel.from_squared_differences(theta_k, squared_differences(self._Xn, Xn))
        mean = Ks.T @ self._a  # R&W eq. 3.21: k*ᵀ ∇log p(y|f̂) = k*ᵀ K⁻¹ f̂
        # R&W eq. 3.24: k** − k*ᵀ (K + W⁻¹)⁻¹ k*, with (K + W⁻¹)⁻¹ = W (I + KW)⁻¹
        QKs = _lu_solve(self._lu, Ks)
        var = math.exp(theta_k[d]) - np.einsum("ij,ij->j", Ks, self._W[:, None] * QKs)
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
        }

    @property
    def laplace_converged(self) -> bool:
        """Whether the last Newton search for the posterior mode converged (diagnostic)."""
        return bool(self._laplace_converged)


def _is_posterior_definite(L: np.ndarray, W: np.ndarray, eye: np.ndarray) -> bool:
    """Whether K⁻¹ + diag(W) is positive definite, i.e. I + Lᵀ diag(W) L is (K = L Lᵀ)."""
    _, info = lapack.dpotrf(eye + (L.T * W) @ L, lower=1, clean=0)
    return info == 0


def _lu(A: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """LU factors (LAPACK dgetrf, partial pivoting) of A, or None when A is singular."""
    lu, piv, info = lapack.dgetrf(A)
    return (lu, piv) if info == 0 else None


def _lu_solve(lu: tuple[np.ndarray, np.ndarray], B: np.ndarray) -> np.ndarray:
    """Solve A X = B from :func:`_lu` factors; B is (n,) or (n, k)."""
    vec = B.ndim == 1
    X, info = lapack.dgetrs(lu[0], lu[1], B[:, None] if vec else B)
    if info != 0:  # pragma: no cover - only on malformed arguments
        raise ValueError(f"dgetrs failed with info={info}")
    return X[:, 0] if vec else X
