"""Calibration of a tuned filter's uncertainty by one covariance scale.

Running a Kalman filter with c·Q, c·R and c·P0 instead of Q, R and P0 scales every
covariance it computes by c and leaves its gain, and so its estimate, unchanged:
P⁻_k = F P_{k−1} Fᵀ + Q, S_k = H P⁻_k Hᵀ + R and K_k = P⁻_k Hᵀ S_k⁻¹ are homogeneous of
degrees 1, 1 and 0 in (P0, Q, R) (Simon, *Optimal State Estimation*, 2006, eq. 5.19), so
by induction P_k(c) = c·P_k(1) and x̂_k(c) = x̂_k(1); an EKF's Jacobians, taken at that
estimate, stay too. A UKF run so would spread its sigma points √c times wider through the
nonlinear model and move its estimate, by a large share of its β RMSE and with a worse
test β RMSE on the tuned single-track UKF (measured in BENCHMARKS.md, "Calibrated
uncertainty"). So the calibrated filter is defined as the tuned filter whose reported
covariances are multiplied by c (P_k·c, S_k·c:
:meth:`kftune.tuning.runs.FilterSpec.run`'s ``cov_scale``) — for a Kalman filter and an
EKF exactly the run with c·Q, c·R and c·P0, for a UKF the same without moving its estimate.

:func:`fit_scale` fits c on runs of the filter (the training manoeuvres after tuning) so that
its stated uncertainty matches its errors, by one of :data:`CRITERIA`:

* ``"nees"``: mean NEES of the calibrated channel = 1 after the burn-in. For fixed errors
  e_k this is also the maximum of the Gaussian likelihood Π N(e_k; 0, c·σ_k²) in c
  (∂/∂c [Σ ln(c σ_k²) + e_k²/(c σ_k²)] = 0 ⇔ c = (1/N) Σ e_k²/σ_k²).
* ``"coverage95"``: the interval ±1.96σ covers 95 % of the errors: c = (q₉₅(|e_k|/σ_k) /
  1.96)², q₉₅ the 95th percentile.
* ``"median"``: the median of (e_k/σ_k)² equals χ²₁'s median (0.455): c = median(z²) /
  0.455, z = e/σ. The mean NEES is pulled up by the few large errors of heavy tails; the
  median is not (a breakdown point of 50 %).
* ``"reliability"``: c minimising the mean absolute difference between the observed share
  of |z| ≤ z_p·√c and the nominal p over the levels p = 0.50, 0.51, …, 0.99
  (:data:`RELIABILITY_LEVELS`, z_p = Φ⁻¹((1 + p)/2)): the reliability curve of the
  interval ±z_p·σ brought to its diagonal as a whole, not at one level.
* ``"minimax"``: c minimising the worse of the misses of the ±1σ and ±1.96σ coverages
  (68.27 % and 95 %), each in units of its binomial standard deviation √(p(1 − p))
  (0.465 and 0.218: a point of coverage at 95 % counts 2.1× one at 68 %, as the
  targets' 90–98 % and 60–76 % half-widths of 4 and 8 points say).
* ``"crps"`` (the default): c minimising the mean continuous ranked probability score of the errors
  under N(0, c·σ_k²) (Gneiting & Raftery 2007, a proper scoring rule; in each channel's
  unit, channels summed), where Σ_k σ_k·(2φ(z_k/s) − 1/√π) = 0 with s = √c (the score's
  derivative in s; it is convex in s, so the root is its minimum).
* ``"nis"`` (chosen when no channel has a reference): mean NIS = m, the number of
  measurements (S_k scales by c, so NIS by 1/c). It calibrates the innovations, not the
  state errors: nothing else can be checked without a reference.

c is found by the fixed point c ← c·ρ(c), ρ the criterion's required factor at c (1 when
met): with the covariances scaled after the run, ρ(c·ρ(1)) = 1 exactly, two runs; a runner
that reran the filter with scaled covariances (the UKF variant measured and not kept)
takes a handful.

Where a single scale cannot work: each manoeuvre has its own factor c_m (the criterion on its
samples alone) and a *bias share* b_m = Σ_c n_c·ē_c² / Σ e_k² of its normalised errors
e_k/σ_k (ē_c their mean over channel c's n_c samples): the part of the squared error that a
constant offset explains, which no scale of a zero-mean σ can describe. When some c_m
differs from the common c by more than :data:`SPREAD_LIMIT` (σ off by more than 2× there:
its ±1.96σ band would hold about 67 % or more than 99.99 % of the errors), the calibration
says so and names those manoeuvres, those with b_m ≥ :data:`BIAS_DOMINATED` as dominated by
bias.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from kftune.errors import KftuneError
from kftune.tuning.consistency import ChannelConsistency, channel_consistency, pool, z_of

if TYPE_CHECKING:
    from kftune.data.manoeuvre import Manoeuvre
    from kftune.tuning.problem import TuningProblem

#: The criteria :func:`fit_scale` fits c by (module docstring).
CRITERIA: tuple[str, ...] = ("nees", "coverage95", "median", "reliability", "minimax", "crps")
#: The criterion ``kftune tune`` uses (chosen by benchmarks/calibration.py, BENCHMARKS.md).
DEFAULT_CRITERION = "crps"
#: A manoeuvre whose own factor differs from the common one by more than this (either way)
#: is one that the common scale cannot make consistent (σ off by more than √4 = 2×).
SPREAD_LIMIT = 4.0
#: Bias share at or above which a manoeuvre's errors are called dominated by bias.
BIAS_DOMINATED = 0.5
#: The mean NIS/m outside which ``tune`` says that the innovations ask for another scale
#: than the one fitted on the state errors (a factor 2 either way: χ² bands of a few
#: thousand samples are far narrower, so this flags only a plain disagreement).
NIS_RANGE: tuple[float, float] = (0.5, 2.0)
#: Fixed-point iterations at most, and the relative change of c that ends them.
MAX_ITERATIONS = 8
TOLERANCE = 1e-3
#: The levels p of the ``"reliability"`` criterion: 0.50, 0.51, …, 0.99.
RELIABILITY_LEVELS: tuple[float, ...] = tuple(round(0.5 + 0.01 * i, 2) for i in range(50))
#: χ²₁'s median, (Φ⁻¹(0.75))² (the ``"median"`` criterion's target).
CHI2_1_MEDIAN = 0.454936423119572
#: The range c is kept in (a filter whose σ is off by more than 1000× is not calibrated
#: by scaling, it is mis-tuned).
FACTOR_RANGE: tuple[float, float] = (1e-6, 1e6)


class CalibrationError(KftuneError, ValueError):
    """The calibration could not be fitted (a diverged run, nothing to fit on)."""


@dataclass(frozen=True)
class RunErrors:
    """What one manoeuvre's run gives the fit, after the burn-in.

    Attributes:
        name: the manoeuvre.
        err: channel → (N,) estimate − reference, in the channel's unit.
        std: channel → (N,) the filter's standard deviation σ of it, same unit.
        estimate: channel → (N,) the estimate (for the shift the scale causes).
        nis: (N,) the NIS terms ν_kᵀ S_k⁻¹ ν_k [-], or None.
        m: the number of measurements (the NIS's dof).
    """

    name: str
    err: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    estimate: dict[str, np.ndarray]
    nis: np.ndarray | None = None
    m: int = 0

    def normalised(self) -> dict[str, np.ndarray]:
        """channel → (n_c,) e_k/σ_k over the samples where both are finite and σ > 0."""
        out = {}
        for c, e in self.err.items():
            s = self.std[c]
            ok = np.isfinite(e) & np.isfinite(s) & (s > 0)
            out[c] = e[ok] / s[ok]
        return out


def required_factor(runs: Sequence[RunErrors], criterion: str) -> float:
    """ρ: the factor by which the covariances of the runs must be multiplied to meet
    ``criterion`` (1 when met), pooled over ``runs``; NaN with nothing to count.

    ``"nees"``: (1/N) Σ (e_k/σ_k)² over every channel; ``"coverage95"``: (q₉₅(|e_k/σ_k|) /
    1.96)²; ``"median"``: median((e_k/σ_k)²) / χ²₁'s median; ``"reliability"``,
    ``"minimax"``, ``"crps"``: the scale that minimises their loss (module docstring);
    ``"nis"``: (1/N) Σ NIS_k / m.
    """
    if criterion == "nis":
        terms = [r.nis[np.isfinite(r.nis)] for r in runs if r.nis is not None]
        n = sum(t.size for t in terms)
        m = max((r.m for r in runs), default=0)
        return float(sum(t.sum() for t in terms) / (n * m)) if n and m else math.nan
    if criterion == "crps":
        return _crps_factor(runs)
    e = _joined([v for r in runs for v in r.normalised().values()])
    if not e.size:
        return math.nan
    if criterion == "nees":
        return float(np.mean(e * e))
    if criterion == "coverage95":
        return float((np.quantile(np.abs(e), 0.95) / z_of(0.95)) ** 2)
    if criterion == "median":
        return float(np.median(e * e) / CHI2_1_MEDIAN)
    if criterion == "reliability":
        return _coverage_fit(np.abs(e), RELIABILITY_LEVELS, "mean")
    if criterion == "minimax":
        return _coverage_fit(np.abs(e), (0.682689492137086, 0.95), "max")
    raise ValueError(f"criterion must be one of {[*CRITERIA, 'nis']}, got {criterion!r}")


def _coverage_fit(a: np.ndarray, levels: Sequence[float], how: str) -> float:
    """The factor c (on the variances) minimising the mean (``how="mean"``) absolute miss
    |share(a ≤ z_p·√c) − p| over ``levels``, or the largest (``"max"``) in units of
    √(p(1 − p)); ``a`` (N,) the |e/σ| [-].

    Each level's miss is least at its own c_p = (q_p(a)/z_p)² and grows away from it, so the
    minimum lies between the smallest and largest c_p: those and 400 log-spaced scales
    between them are scored; then, between the neighbours of the best of them, the loss —
    a step function of c, stepping where z_p·√c passes a sample — at every step's midpoint,
    and the middle of the lowest run taken. Scale-equivariant: a times k gives c times k².
    """
    a = np.sort(a)
    p = np.asarray(levels, dtype=float)
    z = np.array([z_of(v) for v in p])
    own = (np.quantile(a, p) / z) ** 2
    own = own[own > 0]
    if not own.size:
        return math.nan

    def loss(c: np.ndarray) -> np.ndarray:
        shares = np.searchsorted(a, z[None, :] * np.sqrt(c)[:, None], side="right") / a.size
        miss = np.abs(shares - p[None, :])
        return miss.mean(axis=1) if how == "mean" else (miss / np.sqrt(p * (1 - p))).max(axis=1)

    lo, hi = float(own.min()), float(own.max())
    grid = np.unique(np.concatenate([own, np.geomspace(lo, hi, 400) if hi > lo else own]))
    i = int(np.argmin(loss(grid)))
    left, right = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    steps = [(a[(a >= zp * math.sqrt(left)) & (a <= zp * math.sqrt(right))] / zp) ** 2 for zp in z]
    edges = np.unique(np.concatenate([[left, right], *steps]))
    mids = np.concatenate([edges, np.sqrt(edges[:-1] * edges[1:])])
    mids.sort()
    score = loss(mids)
    best = np.flatnonzero(score <= score.min() + 1e-12)
    gaps = np.flatnonzero(np.diff(best) > 1)  # the first run of lowest steps ends there
    last = best[gaps[0]] if gaps.size else best[-1]
    return float(math.sqrt(mids[best[0]] * mids[last]))


def _crps_factor(runs: Sequence[RunErrors]) -> float:
    """The factor c minimising Σ_k CRPS(N(0, c·σ_k²); e_k) over every channel's samples
    (module docstring): the root in s = √c of Σ_k σ_k·(2φ(e_k/(s·σ_k)) − 1/√π), which
    rises from −Σσ/√π (s → 0, unless an error is 0) to Σσ·(2φ(0) − 1/√π) > 0; NaN with
    nothing to count."""
    from scipy.optimize import brentq

    e_all, s_all = [], []
    for r in runs:
        for ch, e in r.err.items():
            s = r.std[ch]
            ok = np.isfinite(e) & np.isfinite(s) & (s > 0)
            e_all.append(e[ok])
            s_all.append(s[ok])
    if not e_all or not sum(v.size for v in e_all):
        return math.nan
    e, sd = np.concatenate(e_all), np.concatenate(s_all)
    z = e / sd
    inv_sqrt_pi = 1.0 / math.sqrt(math.pi)

    def slope(log_s: float) -> float:
        w = z * math.exp(-log_s)
        return float(np.dot(sd, 2.0 * np.exp(-0.5 * w * w) / math.sqrt(2 * math.pi) - inv_sqrt_pi))

    lo, hi = (0.5 * math.log(v) for v in FACTOR_RANGE)
    if slope(lo) >= 0:
        return FACTOR_RANGE[0]
    if slope(hi) <= 0:
        return FACTOR_RANGE[1]
    return float(math.exp(2.0 * brentq(slope, lo, hi, xtol=1e-10, rtol=1e-12)))


def bias_share(run: RunErrors) -> float:
    """b = Σ_c n_c·ē_c² / Σ_k e_k² of the run's normalised errors (module docstring): the
    share of the squared error that a constant offset per channel explains [0–1]; NaN
    without errors."""
    total = biased = 0.0
    for e in run.normalised().values():
        if e.size:
            total += float(np.dot(e, e))
            biased += e.size * float(np.mean(e)) ** 2
    return biased / total if total > 0 else math.nan


@dataclass(frozen=True)
class ManoeuvreFit:
    """One manoeuvre's own factor c_m and bias share b_m at the common scale."""

    name: str
    factor: float
    bias_share: float


@dataclass(frozen=True)
class Calibration:
    """A fitted covariance scale and the evidence for it.

    Attributes:
        factor: c; the filter's covariances are reported c times larger.
        criterion: what c was fitted by (:data:`CRITERIA` or ``"nis"``).
        channels: the channels whose errors it was fitted on (empty for ``"nis"``).
        n_runs: filter runs over the manoeuvres it took (the first at c = 1).
        before, after: the first channel's consistency pooled over the manoeuvres at c = 1
            and at c (None for ``"nis"``).
        nis_before, nis_after: the mean NIS / m at c = 1 and at c (NaN without NIS).
        shift_rms: RMS of the first channel's estimate at c minus at 1, in its unit (NaN
            for ``"nis"``); rmse: the RMSE of its estimate at 1, same unit.
        per_manoeuvre: each manoeuvre's own factor and bias share at c.
        converged: whether the fixed point met :data:`TOLERANCE`.
    """

    factor: float
    criterion: str
    channels: tuple[str, ...]
    n_runs: int
    before: ChannelConsistency | None
    after: ChannelConsistency | None
    nis_before: float
    nis_after: float
    shift_rms: float
    rmse: float
    per_manoeuvre: tuple[ManoeuvreFit, ...] = field(default=())
    converged: bool = True

    @property
    def outliers(self) -> list[ManoeuvreFit]:
        """The manoeuvres whose own factor differs from c by more than SPREAD_LIMIT."""
        return [
            f
            for f in self.per_manoeuvre
            if math.isfinite(f.factor)
            and not 1.0 / SPREAD_LIMIT <= f.factor / self.factor <= SPREAD_LIMIT
        ]

    @property
    def warning(self) -> str | None:
        """Where one scale cannot work, in words (None where it can)."""
        bad = self.outliers
        if not bad:
            return None

        def sigma(f: ManoeuvreFit) -> str:
            k = math.sqrt(f.factor / self.factor)
            return f"σ {k:.2g}× too small there" if k > 1 else f"σ {1 / k:.2g}× too large there"

        biased = [f for f in bad if f.bias_share >= BIAS_DOMINATED]
        other = [f for f in bad if f not in biased]
        parts = []
        if biased:
            parts.append(
                "errors dominated by bias on "
                + ", ".join(
                    f"{f.name!r} (bias {100 * f.bias_share:.0f} % of the squared error, {sigma(f)})"
                    for f in biased
                )
            )
        if other:
            parts.append(
                f"own factor more than {SPREAD_LIMIT:g}× off on "
                + ", ".join(f"{f.name!r} ({sigma(f)})" for f in other)
            )
        seen = []
        if any(f.factor > self.factor for f in bad):
            seen.append(
                "where σ is too small the calibrated ±1.96σ band misses the reference for "
                "long stretches (a slowly varying bias no zero-mean σ describes)"
            )
        if any(f.factor < self.factor for f in bad):
            seen.append("where σ is too large the band is wider than the errors there need")
        return (
            "one scale cannot make every manoeuvre consistent: "
            + "; ".join(parts)
            + ". What you see: "
            + "; ".join(seen)
            + " — the coverage pooled over all manoeuvres is right, on each it is not"
        )

    def as_dict(self, fitted_on: str = "train") -> dict[str, Any]:
        """The ``"calibration"`` record of a tuned file (strict-JSON values)."""

        def stats(ch: ChannelConsistency | None, nis: float) -> dict[str, Any]:
            if ch is None:
                return {"mean_nis_over_m": _num(nis)}
            cov68, cov95 = ch.coverage
            return {
                "coverage68": _num(cov68),
                "coverage95": _num(cov95),
                "mean_nees": _num(ch.nees.mean),
                "mean_nis_over_m": _num(nis),
            }

        channel = self.channels[0] if self.channels else None
        beta = channel == "beta"
        scale = math.degrees(1.0) if beta else 1.0
        return {
            "factor": self.factor,
            "criterion": self.criterion,
            "fitted_on": fitted_on,
            "channel": channel if channel is not None else "nis",
            "channels": list(self.channels),
            "n_runs": self.n_runs,
            "converged": self.converged,
            fitted_on: {
                "before": stats(self.before, self.nis_before),
                "after": stats(self.after, self.nis_after),
            },
            "estimate_shift": None
            if channel is None
            else {
                "channel": channel,
                "rms": _num(self.shift_rms * scale),
                "unit": "deg" if beta else "",
                "relative_to_rmse": _num(self.shift_rms / self.rmse) if self.rmse > 0 else None,
            },
            "per_manoeuvre": [
                {"name": f.name, "factor": _num(f.factor), "bias_share": _num(f.bias_share)}
                for f in self.per_manoeuvre
            ],
            "spread_limit": SPREAD_LIMIT,
            "warning": self.warning,
        }


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def fit_scale(
    run: Callable[[float], Sequence[RunErrors]], criterion: str = DEFAULT_CRITERION
) -> Calibration:
    """Fit one covariance scale c by the fixed point c ← c·ρ(c) (module docstring).

    Args:
        run: c → the runs of the filter with covariances c times larger (for a Kalman
            filter: with c·Q, c·R and c·P0) over the manoeuvres it is
            fitted on (each :class:`RunErrors` with the same channels); raises
            :class:`CalibrationError` when the filter diverges.
        criterion: one of :data:`CRITERIA`; ``"nis"`` is used instead when no run has an
            error to count.

    Raises:
        CalibrationError: nothing to fit on (no reference and no NIS), or a run diverged.
        ValueError: an unknown criterion.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {list(CRITERIA)}, got {criterion!r}")
    first = list(run(1.0))
    channels = tuple(dict.fromkeys(c for r in first for c in r.err))
    if not any(e.size for r in first for e in r.normalised().values()):
        criterion, channels = "nis", ()
    rho = required_factor(first, criterion)
    if not (math.isfinite(rho) and rho > 0):
        raise CalibrationError(
            "nothing to fit the covariance scale on: no reference channel and no NIS"
            if criterion == "nis"
            else f"the {criterion} of the filter's errors is not a positive number"
        )
    lo, hi = FACTOR_RANGE
    c, runs, n_runs, converged = 1.0, first, 1, abs(rho - 1.0) < TOLERANCE
    for _ in range(MAX_ITERATIONS):
        if converged:
            break
        c_new = min(max(c * rho, lo), hi)
        if c_new == c:  # pinned at a limit of FACTOR_RANGE
            break
        c, runs, n_runs = c_new, list(run(c_new)), n_runs + 1
        rho = required_factor(runs, criterion)
        converged = abs(rho - 1.0) < TOLERANCE
    key = channels[0] if channels else None
    return Calibration(
        factor=c,
        criterion=criterion,
        channels=channels,
        n_runs=n_runs,
        before=_pooled(first, key),
        after=_pooled(runs, key),
        nis_before=required_factor(first, "nis"),
        nis_after=required_factor(runs, "nis"),
        shift_rms=_shift(first, runs, key),
        rmse=_rmse(first, key),
        per_manoeuvre=tuple(
            ManoeuvreFit(r.name, c * required_factor([r], criterion), bias_share(r)) for r in runs
        ),
        converged=converged,
    )


def _pooled(runs: Sequence[RunErrors], channel: str | None) -> ChannelConsistency | None:
    """The channel's consistency pooled over the runs (reference = estimate − error)."""
    if channel is None:
        return None
    return pool(
        channel_consistency(r.err[channel], r.std[channel], np.zeros_like(r.err[channel]))
        for r in runs
        if channel in r.err
    )


def _joined(parts: Sequence[np.ndarray]) -> np.ndarray:
    """The (n_i,) parts end to end, (Σ n_i,); (0,) for none."""
    return np.concatenate(parts) if parts else np.zeros(0)


def _shift(a: Sequence[RunErrors], b: Sequence[RunErrors], channel: str | None) -> float:
    """RMS of the channel's estimate in runs ``b`` minus in runs ``a`` (same manoeuvres)."""
    if channel is None:
        return math.nan
    d = _joined(
        [
            rb.estimate[channel] - ra.estimate[channel]
            for ra, rb in zip(a, b)
            if channel in ra.estimate
        ]
    )
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d * d))) if d.size else math.nan


def _rmse(runs: Sequence[RunErrors], channel: str | None) -> float:
    """RMSE of the channel's estimate over the runs, in its unit."""
    if channel is None:
        return math.nan
    e = _joined([r.err[channel] for r in runs if channel in r.err])
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e * e))) if e.size else math.nan


# -- the tuning problem's filter ------------------------------------------------------------


def problem_runs(
    problem: TuningProblem, x: Sequence[float] | np.ndarray, manoeuvres: Sequence[Manoeuvre]
) -> Callable[[float], list[RunErrors]]:
    """c → the runs of ``problem``'s filter at point ``x`` with its covariances scaled by c
    (``problem.cov_scale``) over ``manoeuvres``, after its burn-in: the channels β (where
    the model outputs it and the manoeuvre has ``beta_ref``), else each estimated channel
    with a reference ``<name>_ref``, else none (the NIS only).

    Raises:
        CalibrationError: naming the manoeuvre, when the filter diverges on it.
    """
    from kftune.tuning.deploy import estimates_of, referenced
    from kftune.tuning.runs import first_scored

    def run(c: float) -> list[RunErrors]:
        scaled = copy.copy(problem)
        scaled.cov_scale = c
        out = []
        for m in manoeuvres:
            res = scaled.run(x, m)
            if res.diverged:
                raise CalibrationError(
                    f"the filter diverged on manoeuvre {m.name!r} ({res.diverged_reason})"
                    if c == 1.0
                    else f"the filter diverged on manoeuvre {m.name!r} with its covariances "
                    f"scaled by {c:.3g} ({res.diverged_reason})"
                )
            est = estimates_of(problem.model, res, m)
            cols = est.columns
            k0 = first_scored(m, problem.burn_in)
            names = (
                ["beta"]
                if {"beta", "beta_std", "beta_ref"} <= set(cols)
                else [c for c in referenced(est) if f"{c}_std" in cols]
            )
            out.append(
                RunErrors(
                    name=m.name,
                    err={c: (cols[c] - cols[f"{c}_ref"])[k0:] for c in names},
                    std={c: cols[f"{c}_std"][k0:] for c in names},
                    estimate={c: cols[c][k0:] for c in names},
                    nis=cols["nis"][k0:],
                    m=problem.model.n_measurements,
                )
            )
        return out

    return run


def calibrate(
    problem: TuningProblem,
    x: Sequence[float] | np.ndarray,
    manoeuvres: Sequence[Manoeuvre] | None = None,
    criterion: str = DEFAULT_CRITERION,
) -> Calibration:
    """The covariance scale of ``problem``'s filter at ``x`` fitted on ``manoeuvres``
    (default: the problem's own, the training ones): :func:`fit_scale` of
    :func:`problem_runs`."""
    return fit_scale(problem_runs(problem, x, manoeuvres or problem.manoeuvres), criterion)


def summary_line(cal: Calibration) -> str:
    """What ``tune`` prints: the factor, the training coverage before → after, the shift of
    the estimate, and the warning where one scale cannot work."""
    what = cal.channels[0] if cal.channels else "the innovations"
    shown = {"beta": "β"}.get(what, what)
    head = f"calibrated σ: covariances × {cal.factor:.3g} ({cal.criterion} on {shown}, training"
    if cal.before is not None and cal.after is not None:
        (a68, a95), (b68, b95) = cal.before.coverage, cal.after.coverage
        head += (
            f": ±1σ covers {100 * a68:.0f} → {100 * b68:.0f} %, ±1.96σ {100 * a95:.0f} → "
            f"{100 * b95:.0f} %, mean NEES {cal.before.nees.mean:.3g} → "
            f"{cal.after.nees.mean:.3g})"
        )
        unit = "°" if what == "beta" else ""
        scale = math.degrees(1.0) if what == "beta" else 1.0
        rel = cal.shift_rms / cal.rmse if cal.rmse > 0 else math.nan
        head += (
            "; the estimate is unchanged"
            if cal.shift_rms == 0.0
            else f"; the estimate moves by {cal.shift_rms * scale:.2g}{unit} RMS "
            f"({100 * rel:.2g} % of its RMSE)"
        )
        lo, hi = NIS_RANGE
        if math.isfinite(cal.nis_after) and not lo <= cal.nis_after <= hi:
            head += (
                f"\n  the innovations ask for another scale: mean NIS/m {cal.nis_before:.3g} → "
                f"{cal.nis_after:.3g} (1 if consistent) — the {shown} errors are not the noise "
                "that Q and R describe (model error); gate measurements on the NIS with care"
            )
    else:
        head += (
            f": no reference, fitted on the NIS — mean NIS/m {cal.nis_before:.3g} → "
            f"{cal.nis_after:.3g}; the state errors are unchecked)"
        )
    return head + ("" if cal.warning is None else f"\n  {cal.warning}")
