"""Tuning costs: the paper's weighted NRMSE (Eq. 14–15) and a variant normalised over the
whole set of manoeuvres, two proper scoring rules of the reference under the filter's
Gaussian (NLPD, CRPS), a NIS consistency cost, and the innovation negative
log-likelihood (the prediction-error method).

The functions here are pure and work on plain arrays, so they can be checked by hand. The
tuning problem (:mod:`kftune.tuning.problem`) extracts the channels from filter runs and
calls them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.special import ndtr

from kftune.errors import ConfigError

#: Channels a cost can weigh: sideslip (against the reference sensor), yaw rate, lateral
#: acceleration and longitudinal speed (against their measurements).
CHANNELS: tuple[str, ...] = ("beta", "r", "ay", "vx")

#: The costs a tuning problem knows: the paper's weighted NRMSE and the two proper scoring
#: rules ``"nlpd"`` and ``"crps"`` (these need a β reference), and three reference-free
#: ones: NIS consistency, the innovation likelihood (``"pem"``) and the multi-step
#: prediction error (``"msp"``).
COST_KINDS: tuple[str, ...] = ("nrmse", "nis", "pem", "msp", "nlpd", "crps")
#: Costs that are logarithms, whose changes are relative changes already.
LOG_COSTS: tuple[str, ...] = ("msp", "nis")

#: The costs that score the reference channels under the filter's Gaussian N(est, σ²)
#: (proper scoring rules: minimised in expectation only by the true predictive
#: distribution, so by an accurate *and* calibrated σ).
SCORING_RULES: tuple[str, ...] = ("nlpd", "crps")

#: How the NRMSE cost normalises a channel's error: ``"manoeuvre"`` — each manoeuvre's RMSE
#: over its own max|X| (paper Eq. 15); ``"dataset"`` — the RMSE pooled over all manoeuvres
#: over the largest |X| among them (see :class:`CostSpec`).
NORMALISATIONS: tuple[str, ...] = ("manoeuvre", "dataset")

#: The multi-step prediction cost's horizon [s] and the spacing of its start samples.
MSP_HORIZON = 0.35
MSP_STRIDE = 5

#: Paper Table III: W1 = 5 (β), W2 = 1 (yaw rate), W3 = 1 (ay).
PAPER_WEIGHTS: Mapping[str, float] = {"beta": 5.0, "r": 1.0, "ay": 1.0}


class _DefaultWeights(dict[str, float]):
    """The weights a :class:`CostSpec` gets when none are given (a plain dict otherwise
    equal to :data:`PAPER_WEIGHTS`), so that a scoring-rule cost can put β alone in their
    place."""


def _paper_weights() -> dict[str, float]:
    return _DefaultWeights(PAPER_WEIGHTS)


@dataclass(frozen=True)
class CostSpec:
    """Which cost to minimise.

    Attributes:
        kind: ``"nrmse"`` — the paper's J = Σ_j W_j·E_j (Eq. 14) over the weighted channels;
            ``"nis"`` — the consistency cost |log(mean NIS / n_z)| of Chen et al. (2018),
            which needs no reference sensor; ``"pem"`` — the filter's innovation negative
            log-likelihood per sample (:func:`innovation_nll`; the prediction-error method,
            maximum likelihood), which needs no reference sensor either; ``"msp"`` — the
            multi-step prediction error (:func:`multistep_cost`): the model run open loop
            for :data:`MSP_HORIZON` from the posterior state, against the measured channels
            among ``weights`` (default r and ay); single-track model only. No
            reference-free cost is reliable yet (README, "Tuning without a reference
            sensor": on revs-250lm msp's optimum is a worse filter than manual tuning).
            ``"nlpd"`` — the mean negative log predictive density of the reference under the
            filter's Gaussian N(est, σ²) (:func:`gaussian_nlpd`), ``"crps"`` — its mean
            continuous ranked probability score (:func:`gaussian_crps`): proper scoring
            rules, minimised only by an estimate that is accurate and whose σ is calibrated;
            see :func:`scoring_rule_cost` for how channels are combined.
        weights: channel → weight W_j ≥ 0 (``"nrmse"``, ``"nlpd"``, ``"crps"``): a
            measurement of the filter's model or one of its outputs (the single-track
            model's: :data:`CHANNELS`); the tuning problem checks them against its model.
            The scoring rules score reference channels only (an output such as β, or a state
            that is not measured, against ``<name>_ref``), and default to β alone
            (``{"beta": 1.0}``): a measured channel's predictive density is the ``pem``
            cost's.
        estimate: which filter output the measured channels (r, ay, vx) are scored with.
            ``"posterior"`` (default; the paper's "estimated states"): h(x⁺_k), after the
            update with z_k. Because that update has already used z_k, a large process noise
            lets the estimate copy the measurement, and the cost then rewards it (the tuned
            yaw-rate error can fall far below the gyro's own noise). ``"prior"``: the
            one-step prediction ẑ⁻_k = z_k − innovation_k, made before z_k is used, which
            cannot copy it. β is a state, never measured by the filter, and is always
            scored from the posterior.
        normalise: ``"nrmse"`` only. ``"manoeuvre"`` (default, the paper's Eq. 15): each
            manoeuvre's RMSE over its own max|X|, pooled by sample count — a manoeuvre with
            little sideslip weighs as much per sample as a limit-handling one, so the cost
            rewards small errors where |β| stays small. ``"dataset"``: the RMSE pooled over
            all scored manoeuvres over the largest |X| among them, i.e. the error in the
            channel's unit, scaled once per channel so that the weights stay comparable.
            On six datasets the filter tuned with ``"dataset"`` had the lower test-set β
            RMSE on five (README, "Which cost").
    """

    kind: Literal["nrmse", "nis", "pem", "msp", "nlpd", "crps"] = "nrmse"
    weights: Mapping[str, float] = field(default_factory=_paper_weights)
    estimate: Literal["posterior", "prior"] = "posterior"
    normalise: Literal["manoeuvre", "dataset"] = "manoeuvre"

    def __post_init__(self) -> None:
        if self.kind not in COST_KINDS:
            raise ConfigError(
                f"cost kind must be one of {', '.join(map(repr, COST_KINDS))}, got {self.kind!r}"
            )
        bad = sorted(c for c in self.weights if not (isinstance(c, str) and c.isidentifier()))
        if bad:
            raise ConfigError(f"cost channel names must be identifiers, got {bad}")
        for name, w in self.weights.items():
            if not (
                isinstance(w, (int, float))
                and not isinstance(w, bool)
                and math.isfinite(w)
                and w >= 0
            ):
                raise ConfigError(
                    f"cost weight for {name!r} must be a finite number >= 0, got {w!r}"
                )
        if self.kind in SCORING_RULES and isinstance(self.weights, _DefaultWeights):
            object.__setattr__(self, "weights", {"beta": 1.0})
        if self.kind in ("nrmse", *SCORING_RULES) and not any(w > 0 for w in self.weights.values()):
            raise ConfigError("at least one cost weight must be > 0")
        if self.estimate not in ("posterior", "prior"):
            raise ConfigError(
                f"cost estimate must be 'posterior' or 'prior', got {self.estimate!r}"
            )
        if self.normalise not in NORMALISATIONS:
            raise ConfigError(
                f"cost normalise must be one of {', '.join(map(repr, NORMALISATIONS))}, "
                f"got {self.normalise!r}"
            )
        if self.normalise != "manoeuvre" and self.kind != "nrmse":
            raise ConfigError(
                f"normalise applies to the nrmse cost only, but the cost is {self.kind!r}"
            )

    @property
    def channels(self) -> tuple[str, ...]:
        """Channels with a positive weight: those of :data:`CHANNELS` in its order, then
        any others sorted."""
        known = [c for c in CHANNELS if self.weights.get(c, 0.0) > 0]
        other = sorted(c for c, w in self.weights.items() if c not in CHANNELS and w > 0)
        return tuple(known + other)


def nrmse(estimate: np.ndarray, reference: np.ndarray) -> float:
    """Normalised RMSE of one channel in one manoeuvre (paper Eq. 15).

    NRMSE = sqrt(mean((X̂ − X)²)) / max|X|.

    Args:
        estimate: (N,) estimated signal.
        reference: (N,) reference (measured) signal, same unit.
    """
    estimate = np.asarray(estimate, dtype=float)
    reference = np.asarray(reference, dtype=float)
    if estimate.shape != reference.shape or estimate.ndim != 1 or estimate.size == 0:
        raise ValueError(
            f"estimate and reference must be non-empty 1-D arrays of equal length, got "
            f"{estimate.shape} and {reference.shape}"
        )
    scale = float(np.max(np.abs(reference)))
    if not scale > 0:
        raise ValueError("cannot normalise: the reference signal is identically zero")
    return float(np.sqrt(np.mean((estimate - reference) ** 2)) / scale)


def pooled_error(nrmse_values: Sequence[float], n_samples: Sequence[int]) -> float:
    """Pool per-manoeuvre NRMSEs by sample count (paper Eq. 14):

    E_j = sqrt( Σ_i NRMSE_{j,i}² · N_i / Σ_i N_i ).

    Args:
        nrmse_values: (M,) NRMSE of one channel in each of M manoeuvres.
        n_samples: (M,) sample counts N_i.
    """
    e = np.asarray(nrmse_values, dtype=float)
    n = np.asarray(n_samples, dtype=float)
    if e.shape != n.shape or e.ndim != 1 or e.size == 0:
        raise ValueError(f"need equal-length non-empty 1-D inputs, got {e.shape} and {n.shape}")
    if np.any(n <= 0):
        raise ValueError("sample counts must be positive")
    return float(np.sqrt(np.sum(e**2 * n) / np.sum(n)))


def dataset_error(
    nrmse_values: Sequence[float], scales: Sequence[float], n_samples: Sequence[int]
) -> float:
    """Pool per-manoeuvre NRMSEs into one error normalised over the whole set:

    E_j = sqrt( Σ_i RMSE_{j,i}² · N_i / Σ_i N_i ) / max_i S_{j,i},

    with RMSE_{j,i} = NRMSE_{j,i}·S_{j,i} and S_{j,i} = max|X_{j,i}| of manoeuvre i: the
    RMSE over all samples of all manoeuvres divided by the largest |X| among them.

    Args:
        nrmse_values: (M,) NRMSE of one channel in each of M manoeuvres (Eq. 15).
        scales: (M,) the max|X| each was normalised by (> 0, the channel's unit).
        n_samples: (M,) sample counts N_i.
    """
    s = np.asarray(scales, dtype=float)
    e = np.asarray(nrmse_values, dtype=float)
    if s.shape != e.shape or not np.all(s > 0):
        raise ValueError(f"need one positive scale per NRMSE value, got {s.shape} for {e.shape}")
    return pooled_error(e * s, n_samples) / float(np.max(s))


def weighted_cost(
    channel_nrmse: Mapping[str, Sequence[float]],
    n_samples: Sequence[int],
    weights: Mapping[str, float],
    scales: Mapping[str, Sequence[float]] | None = None,
) -> tuple[float, dict[str, float]]:
    """The paper's cost J = Σ_j W_j·E_j (Eq. 14).

    Args:
        channel_nrmse: channel → (M,) NRMSE per manoeuvre, for every weighted channel.
        n_samples: (M,) sample counts.
        weights: channel → W_j; channels with weight 0 are ignored.
        scales: channel → (M,) max|X| per manoeuvre: E_j is then normalised over the whole
            set (:func:`dataset_error`) instead of per manoeuvre (:func:`pooled_error`).

    Returns:
        (J, {channel: E_j}).
    """
    pooled: dict[str, float] = {}
    total = 0.0
    for channel, w in weights.items():
        if w == 0:
            continue
        if channel not in channel_nrmse:
            raise ValueError(f"no NRMSE values for weighted channel {channel!r}")
        if scales is None:
            pooled[channel] = pooled_error(channel_nrmse[channel], n_samples)
        else:
            pooled[channel] = dataset_error(channel_nrmse[channel], scales[channel], n_samples)
        total += w * pooled[channel]
    return total, pooled


def _error_and_std(error: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = np.asarray(error, dtype=float)
    sd = np.asarray(std, dtype=float)
    if e.shape != sd.shape:
        raise ValueError(f"error and std must have equal shapes, got {e.shape} and {sd.shape}")
    return e, sd


def gaussian_nlpd(error: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Negative log predictive density of a reference under the Gaussian N(est, σ²), per
    sample:

    NLPD = −log N(ref; est, σ²) = ½·log(2πσ²) + (ref − est)²/(2σ²)   [nats].

    The logarithmic score (Good 1952; Gneiting & Raftery 2007, §3.4): strictly proper, so
    its expectation over ref ~ N(μ, s²) is minimised only by est = μ and σ = s. Not
    scale-free: expressing the channel in another unit (×c) adds log c to every sample.

    Args:
        error: (N,) ref − est (or est − ref), in the channel's unit.
        std: (N,) σ > 0 of the estimate, same unit.

    Returns:
        (N,) the score per sample; inf where σ = 0 and the error is not (and NaN where
        both are 0).
    """
    e, sd = _error_and_std(error, std)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 0.5 * np.log(2.0 * math.pi * sd * sd) + 0.5 * (e / sd) ** 2


def gaussian_crps(error: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Continuous ranked probability score of a reference under the Gaussian N(est, σ²),
    per sample, in closed form (Gneiting & Raftery 2007, Eq. 21):

    CRPS = σ·[z·(2Φ(z) − 1) + 2φ(z) − 1/√π],   z = (ref − est)/σ,

    with Φ, φ the standard normal CDF and density; equal to E|X − ref| − ½·E|X − X'| for
    X, X' ~ N(est, σ²) independent. Strictly proper like the NLPD, in the channel's unit
    (→ |ref − est| as σ → 0), and less severe on a single large error (it grows linearly
    in |z|, the NLPD quadratically).

    Args:
        error: (N,) ref − est (the score is even in it), in the channel's unit.
        std: (N,) σ > 0, same unit.

    Returns:
        (N,) the score per sample [channel unit]; NaN where σ = 0.
    """
    e, sd = _error_and_std(error, std)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = e / sd
        pdf = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
        return sd * (z * (2.0 * ndtr(z) - 1.0) + 2.0 * pdf - 1.0 / math.sqrt(math.pi))


def scoring_rule_cost(
    channel_sums: Mapping[str, Sequence[float]],
    n_samples: Sequence[int],
    weights: Mapping[str, float],
    scales: Mapping[str, Sequence[float]] | None = None,
) -> tuple[float, dict[str, float]]:
    """A scoring rule's cost J = Σ_j W_j·S̄_j, with S̄_j the channel's per-sample score
    (:func:`gaussian_nlpd` or :func:`gaussian_crps`) averaged over all samples of all
    manoeuvres: S̄_j = Σ_i Σ_k s_{j,i,k} / Σ_i N_i, pooled like the NRMSE (Eq. 14).

    How channels of different units are combined: with ``scales`` (the CRPS, which is in
    the channel's unit) S̄_j is divided by the largest |X| of the channel among the
    manoeuvres, as the NRMSE normalised over the whole set, so that the weights compare
    dimensionless numbers; without (the NLPD, in nats) the scores are added as they are —
    a channel's unit shifts its NLPD by a constant (log of the unit), which leaves the
    minimiser unchanged, and the weights trade log-likelihood between channels.

    Args:
        channel_sums: channel → (M,) Σ_k of the per-sample score in each manoeuvre.
        n_samples: (M,) sample counts N_i.
        weights: channel → W_j; channels with weight 0 are ignored.
        scales: channel → (M,) max|X| per manoeuvre, or None (see above).

    Returns:
        (J, {channel: S̄_j (divided by its scale with ``scales``)}); J is inf when a score
        is not finite (a σ of 0, or a run that ran away).
    """
    n = np.asarray(n_samples, dtype=float)
    if n.ndim != 1 or n.size == 0 or np.any(n <= 0):
        raise ValueError(f"need positive sample counts, got {n_samples!r}")
    pooled: dict[str, float] = {}
    total = 0.0
    for channel, w in weights.items():
        if w == 0:
            continue
        if channel not in channel_sums:
            raise ValueError(f"no scores for weighted channel {channel!r}")
        sums = np.asarray(channel_sums[channel], dtype=float)
        if sums.shape != n.shape:
            raise ValueError(f"need one score sum per manoeuvre, got {sums.shape} for {n.shape}")
        value = float(np.sum(sums) / np.sum(n))
        if scales is not None:
            s = np.asarray(scales[channel], dtype=float)
            if s.shape != n.shape or not np.all(s > 0):
                raise ValueError(f"need one positive scale per manoeuvre, got {s.shape}")
            value /= float(np.max(s))
        pooled[channel] = value
        total += w * value
    return (total if math.isfinite(total) else math.inf), pooled


def nis_cost(nis: Sequence[np.ndarray], n_z: int) -> float:
    """Consistency cost from the normalised innovation squared (Chen et al., FUSION 2018).

    For a consistent filter E[NIS] = n_z, so J_NIS = |log(mean NIS / n_z)| is 0 at
    consistency and grows as the filter becomes over- or under-confident. The mean is taken
    over all samples of all manoeuvres.

    Args:
        nis: per manoeuvre, (N_i,) NIS values.
        n_z: measurement dimension.
    """
    values = np.concatenate([np.asarray(v, dtype=float).ravel() for v in nis])
    if values.size == 0:
        raise ValueError("no NIS values")
    mean = float(np.mean(values))
    if not (math.isfinite(mean) and mean > 0):
        return math.inf
    return abs(math.log(mean / n_z))


def innovation_nll(log_det_s: Sequence[np.ndarray], nis: Sequence[np.ndarray], n_z: int) -> float:
    """Innovation negative log-likelihood per sample (the prediction-error method).

    With innovations ν_k ~ N(0, S_k) (the filter's own claim), the negative log-likelihood
    of the measurements is Σ_k ½·[log det S_k + ν_kᵀ S_k⁻¹ ν_k + n_z·log 2π] (Åström 1980;
    Särkkä, *Bayesian Filtering and Smoothing*, 2013, §12.3, the energy function). Here it is
    divided by the number of samples, pooled over all manoeuvres, so the value does not grow
    with the data. Minimising it over Q (and R) is maximum-likelihood tuning: unlike the NIS
    cost, it cannot be satisfied by inflating S (log det S grows) nor by shrinking it (NIS
    grows).

    Args:
        log_det_s: per manoeuvre, (N_i,) log det S_k.
        nis: per manoeuvre, (N_i,) NIS_k = ν_kᵀ S_k⁻¹ ν_k.
        n_z: measurement dimension.

    Returns:
        The mean NLL per sample, or inf when a term is not finite.
    """
    ld = np.concatenate([np.asarray(v, dtype=float).ravel() for v in log_det_s])
    e = np.concatenate([np.asarray(v, dtype=float).ravel() for v in nis])
    if ld.shape != e.shape or ld.size == 0:
        raise ValueError(f"need equal-length non-empty inputs, got {ld.shape} and {e.shape}")
    value = 0.5 * (float(np.mean(ld + e)) + n_z * math.log(2.0 * math.pi))
    return value if math.isfinite(value) else math.inf


def multistep_cost(sq_err: Sequence[Sequence[float] | np.ndarray], counts: Sequence[int]) -> float:
    """Multi-step prediction cost Σ_j log(mean squared h-step prediction error of channel j).

    From every start sample k (every :data:`MSP_STRIDE`-th), the filter's posterior x⁺_k is
    propagated open loop through the process model with the measured inputs for h steps
    (h = :data:`MSP_HORIZON` / dt) and h(x, u) compared with z_{k+h}. A state the filter has
    bent to copy the measurements (a large process noise on an unmeasured state) predicts
    badly once the measurements stop; the logarithm makes channels of any unit comparable.

    Args:
        sq_err: per manoeuvre, (n_channels,) sums of squared prediction errors.
        counts: per manoeuvre, the number of start samples.
    """
    total = np.sum(np.asarray(sq_err, dtype=float), axis=0)
    n = int(np.sum(counts))
    if n <= 0:
        raise ValueError("no start samples for the multi-step prediction")
    with np.errstate(divide="ignore", invalid="ignore"):
        value = float(np.sum(np.log(total / n)))
    return value if math.isfinite(value) else math.inf
