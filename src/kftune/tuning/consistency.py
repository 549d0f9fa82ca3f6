"""Consistency of a filter: whether its standard deviations describe its errors.

A Kalman filter reports an estimate x̂_k and its covariance P_k. It is *consistent* when
its errors are zero-mean with that covariance (Bar-Shalom, Li & Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, 2001, §5.4). This module measures it from
one run, with arrays in and statistics out (nothing of cars or files):

* **coverage** of the central Gaussian interval of probability p: the share of samples
  with |x̂_k − x_k| ≤ z_p·σ_k, z_p = Φ⁻¹((1 + p)/2) (1.0 for 68.27 %, 1.96 for 95 %).
  A consistent filter covers p of the samples.
* **mean NEES** of a scalar channel (normalised estimation error squared, §5.4):
  ε̄ = (1/N) Σ_k (x̂_k − x_k)²/σ_k²; 1 when consistent, above 1 when σ is too small.
* **mean NIS** of the measurements (normalised innovation squared, §5.4):
  ν̄ = (1/N) Σ_k ν_kᵀ S_k⁻¹ ν_k; m (the number of measurements) when consistent.

Each mean comes with its two-sided 95 % acceptance band: if the N terms were independent
χ²_k variables, N·mean would be χ²_{N·k}, so the band is χ²⁻¹([0.025, 0.975]; N·k)/N
(§5.4). The innovations of a consistent filter are white, so that band holds for the NIS
as it is. The estimation errors are not: even a consistent filter's
error at one sample is largely the error at the previous one (a slowly varying state
sampled fast), so N samples carry the evidence of far fewer, and the N-sample NEES band
is too narrow — a consistent filter would fall outside it. The NEES is therefore also
given an *effective* sample count from the lag-1 autocorrelation ρ of the normalised errors
e_k = (x̂_k − x_k)/σ_k: for a Gaussian AR(1) sequence (which the error of a steady-state
scalar Kalman filter is, e_{k+1} = (1 − KH)F·e_k + noise), e_k² has autocorrelation
ρ^{2|j|}, so the variance of their mean is that of N·(1 − ρ²)/(1 + ρ²) independent ones
(Isserlis' theorem gives the e_k²'s autocorrelation; the count is Bayley & Hammersley's
1946 effective number of observations). The verdict on the NEES uses that band
(``band_eff``); the N-sample one is given too. Consistent AR(1) errors of 4000 samples at
ρ = 0.9 fall outside the N-sample band in about half of the runs, outside the effective
one in 5 %. ρ is estimated under the consistency hypothesis (zero-mean errors:
Σ e_k e_{k+1} / Σ e_k², uncentred), over the counted samples in order. A lag-1 model
understates the memory of errors that wander slowly (biases held for seconds), so the
effective band is, if anything, still optimistic about how much the data can tell.

The filters keep only the diagonal of P, so the NEES is per channel (dof 1); a joint NEES
over several referenced states would need the cross-covariances, which are not kept.

Samples counted: those where the estimate, the reference and σ are finite and σ > 0
(a diverged run's NaN rows, a reference's gaps); ``n`` says how many.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike

#: Nominal probabilities of the intervals whose coverage is measured: ±1σ and ±1.96σ.
COVERAGE_LEVELS: tuple[float, float] = (0.6827, 0.95)
#: Probability of the χ² acceptance bands (two-sided).
BAND_PROBABILITY = 0.95
#: Below this many effective independent terms a mean NEES inside its band is no evidence
#: of consistency: errors that wander slowly (n_eff ≈ 5 of 4,000 samples at ρ = 0.999) widen
#: the band until a σ 1.5× too small passes it.
MIN_EFFECTIVE_TERMS = 30.0


def z_of(probability: float) -> float:
    """z of the central Gaussian interval ±z·σ of the given probability, Φ⁻¹((1 + p)/2)."""
    from scipy.stats import norm

    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {probability!r}")
    return float(norm.ppf(0.5 * (1.0 + probability)))


def chi2_band(n: float, dof: int, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """Two-sided acceptance band of the mean of ``n`` independent χ²_dof variables:
    χ²⁻¹([(1 − p)/2, (1 + p)/2]; n·dof)/n (Bar-Shalom et al. 2001, §5.4). ``n``
    may be fractional (an effective count); (NaN, NaN) when n ≤ 0."""
    from scipy.stats import chi2

    if not n > 0:
        return math.nan, math.nan
    tail = 0.5 * (1.0 - probability)
    lo, hi = chi2.ppf([tail, 1.0 - tail], n * dof) / n
    return float(lo), float(hi)


def effective_count(n: int, rho: float) -> float:
    """The number of independent samples whose mean of squares varies as much as that of
    ``n`` samples of a Gaussian AR(1) sequence with lag-1 autocorrelation ``rho``:
    n·(1 − ρ²)/(1 + ρ²) (module docstring); n when ρ is NaN (fewer than 2 samples)."""
    if math.isnan(rho):
        return float(n)
    r2 = min(rho * rho, 1.0)
    return float(n) * (1.0 - r2) / (1.0 + r2)


def lag1_autocorrelation(e: ArrayLike) -> float:
    """Uncentred lag-1 autocorrelation Σ e_k e_{k+1} / Σ e_k² of a (N,) sequence [-]; NaN
    with fewer than 2 samples or all zero."""
    e = np.asarray(e, dtype=float)
    if e.size < 2:
        return math.nan
    denom = float(np.dot(e, e))
    return float(np.dot(e[:-1], e[1:]) / denom) if denom > 0 else math.nan


@dataclass(frozen=True)
class ChiSquareMean:
    """The mean of N terms that are χ²_dof when the filter is consistent (NEES, NIS).

    Attributes:
        total: Σ of the terms; n: N, the terms counted; dof: their degrees of freedom (1
            for a scalar NEES, m for the NIS of m measurements); n_eff: the effective number
            of independent terms (n for the NIS; for the NEES from the errors' lag-1
            autocorrelation, module docstring).
    """

    total: float
    n: int
    dof: int
    n_eff: float

    @property
    def mean(self) -> float:
        """The mean [-]; dof when consistent; NaN when nothing was counted."""
        return self.total / self.n if self.n else math.nan

    @property
    def band(self) -> tuple[float, float]:
        """95 % band of the mean for N independent terms."""
        return chi2_band(self.n, self.dof)

    @property
    def band_eff(self) -> tuple[float, float]:
        """95 % band of the mean for ``n_eff`` independent terms (the verdict's)."""
        return chi2_band(self.n_eff, self.dof)

    @property
    def inside(self) -> bool | None:
        """Whether the mean lies in ``band_eff``; None when nothing was counted."""
        if not self.n:
            return None
        lo, hi = self.band_eff
        return lo <= self.mean <= hi

    def __add__(self, other: ChiSquareMean) -> ChiSquareMean:
        """Pooled over two independent runs (manoeuvres): sums and counts add."""
        if self.dof != other.dof:
            raise ValueError(f"cannot pool χ² terms of {self.dof} and {other.dof} dof")
        return ChiSquareMean(
            self.total + other.total, self.n + other.n, self.dof, self.n_eff + other.n_eff
        )

    def as_dict(self) -> dict[str, object]:
        """``{mean, dof, n, band, n_eff, band_eff, inside}`` (bands as [low, high]; None
        for a value that is not finite, as strict JSON wants)."""
        return {
            "mean": _num(self.mean),
            "dof": self.dof,
            "n": self.n,
            "band": [_num(v) for v in self.band],
            "n_eff": _num(self.n_eff),
            "band_eff": [_num(v) for v in self.band_eff],
            "inside": self.inside,
        }


@dataclass(frozen=True)
class ChannelConsistency:
    """Consistency of one scalar channel with a reference (one run, or pooled).

    Attributes:
        n: samples counted; covered: for each of :data:`COVERAGE_LEVELS`, the samples with
            |err| ≤ z·σ; nees: the NEES terms err²/σ² (dof 1) with their effective count.
    """

    n: int
    covered: tuple[int, int]
    nees: ChiSquareMean

    @property
    def coverage(self) -> tuple[float, float]:
        """Observed coverage of the 68.27 % and 95 % intervals [share 0–1]; NaN when
        nothing was counted."""
        inner, outer = self.covered
        return (inner / self.n, outer / self.n) if self.n else (math.nan, math.nan)

    def __add__(self, other: ChannelConsistency) -> ChannelConsistency:
        """Pooled over two independent runs: counts add."""
        return ChannelConsistency(
            self.n + other.n,
            (self.covered[0] + other.covered[0], self.covered[1] + other.covered[1]),
            self.nees + other.nees,
        )

    def as_dict(self) -> dict[str, object]:
        """``{n, cov68, cov95, nees: {…}}``, coverages as shares 0–1 (None when nothing
        was counted)."""
        cov68, cov95 = self.coverage
        return {
            "n": self.n,
            "cov68": _num(cov68),
            "cov95": _num(cov95),
            "nees": self.nees.as_dict(),
        }


def _num(v: float) -> float | None:
    """``v``, or None when it is not finite."""
    return v if math.isfinite(v) else None


#: The statistics that pool by addition.
Pooled = TypeVar("Pooled", ChannelConsistency, ChiSquareMean)


def _counted(*arrays: ArrayLike) -> tuple[np.ndarray, ...]:
    """The arrays as float (N,) vectors of equal length."""
    out = tuple(np.asarray(a, dtype=float) for a in arrays)
    if any(a.ndim != 1 or a.shape != out[0].shape for a in out):
        raise ValueError(
            "expected 1-D arrays of equal length, got shapes "
            + ", ".join(str(a.shape) for a in out)
        )
    return out


def covered(err: ArrayLike, std: ArrayLike, z: float) -> tuple[int, int]:
    """(samples with |err| ≤ z·σ, samples counted) of errors ``err`` and standard
    deviations ``std``, both (N,) in the same unit; counted: both finite and σ > 0."""
    err, std = _counted(err, std)
    ok = np.isfinite(err) & np.isfinite(std) & (std > 0)
    return int(np.count_nonzero(np.abs(err[ok]) <= z * std[ok])), int(ok.sum())


def channel_consistency(
    estimate: ArrayLike, std: ArrayLike, reference: ArrayLike
) -> ChannelConsistency:
    """Coverage and mean NEES of one scalar channel over one run.

    Args:
        estimate: (N,) the filter's estimate; std: (N,) its standard deviation σ_k (the
            square root of the covariance's diagonal entry); reference: (N,) the true value.
            All three in the same unit (the statistics are unit-free).

    Returns:
        the counts of |err| ≤ z·σ for :data:`COVERAGE_LEVELS` and the NEES terms
        err²/σ² (one run: the lag-1 autocorrelation of err/σ gives their effective count).
    """
    est, sd, ref = _counted(estimate, std, reference)
    ok = np.isfinite(est) & np.isfinite(sd) & np.isfinite(ref) & (sd > 0)
    e = (est[ok] - ref[ok]) / sd[ok]  # normalised error, N(0, 1) when consistent
    n = int(e.size)
    inner, outer = (covered(e, np.ones_like(e), z_of(p))[0] for p in COVERAGE_LEVELS)
    nees = ChiSquareMean(
        float(np.dot(e, e)), n, 1, effective_count(n, lag1_autocorrelation(e)) if n else 0.0
    )
    return ChannelConsistency(n, (inner, outer), nees)


def nis_consistency(nis: ArrayLike, m: int) -> ChiSquareMean:
    """Mean NIS of one run against m, with its band.

    Args:
        nis: (N,) ν_kᵀ S_k⁻¹ ν_k of each step [-] (NaN rows, after a divergence, are not
            counted). m: the number of measurements (each term's dof).

    The innovations of a consistent filter are white, so the N-sample band is the test
    (``n_eff`` = N).
    """
    (values,) = _counted(nis)
    values = values[np.isfinite(values)]
    return ChiSquareMean(float(values.sum()), int(values.size), int(m), float(values.size))


def pool(runs: Iterable[Pooled]) -> Pooled | None:
    """A statistic (:class:`ChannelConsistency` or :class:`ChiSquareMean`) over several
    independent runs (manoeuvres) pooled sample by sample; None when there are none."""
    total: Pooled | None = None
    for r in runs:
        total = r if total is None else total + r
    return total


def of_columns(
    columns: Mapping[str, ArrayLike], n_measurements: int, first: int = 0
) -> tuple[dict[str, ChannelConsistency], ChiSquareMean | None]:
    """Consistency of one run given as named (N,) columns, from sample ``first`` on (after
    a burn-in).

    Args:
        columns: the columns of :class:`~kftune.tuning.deploy.Estimates`: each channel
            ``c`` with a standard deviation ``c_std`` and a reference ``c_ref`` (β with
            ``beta_std`` and ``beta_ref``, a state with ``<state>_ref``) is measured;
            ``nis``, when present, is the NIS of the ``n_measurements`` measurements.

    Returns:
        (channel → its consistency, in column order; the NIS, or None without ``nis``).
    """
    channels = {
        c: channel_consistency(
            np.asarray(columns[c])[first:],
            np.asarray(columns[f"{c}_std"])[first:],
            np.asarray(columns[f"{c}_ref"])[first:],
        )
        for c in columns
        if f"{c}_std" in columns and f"{c}_ref" in columns
    }
    nis = columns.get("nis")
    return channels, None if nis is None else nis_consistency(
        np.asarray(nis)[first:], n_measurements
    )


def as_doc(
    channels: Mapping[str, ChannelConsistency], nis: ChiSquareMean | None
) -> dict[str, object]:
    """The JSON form of one run's (or a pooled) consistency: ``{"channels": {c:
    ChannelConsistency.as_dict()}, "nis": ChiSquareMean.as_dict() or None}``."""
    return {
        "channels": {c: v.as_dict() for c, v in channels.items()},
        "nis": None if nis is None else nis.as_dict(),
    }


def pool_runs(
    runs: Iterable[tuple[Mapping[str, ChannelConsistency], ChiSquareMean | None]],
) -> tuple[dict[str, ChannelConsistency], ChiSquareMean | None]:
    """The consistency of several runs (manoeuvres, as :func:`of_columns` gives each)
    pooled: each channel over the runs that have it, and the NIS."""
    runs = list(runs)
    names = dict.fromkeys(c for channels, _ in runs for c in channels)
    channels: dict[str, ChannelConsistency] = {}
    for c in names:
        pooled = pool(ch[c] for ch, _ in runs if c in ch)
        if pooled is not None:  # always: every name comes from a run
            channels[c] = pooled
    return channels, pool(nis for _, nis in runs if nis is not None)
