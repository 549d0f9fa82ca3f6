"""What one manoeuvre contributes to a cost: its filter run scored by the cost's kind
(:class:`ManoeuvreScore`), and the pooled :class:`Evaluation`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kftune.data.manoeuvre import Manoeuvre
from kftune.errors import DataError, FilterDivergedError
from kftune.filters import FilterResult, UKFSettings
from kftune.models import StateSpaceModel
from kftune.tuning.cost import (
    MSP_HORIZON,
    MSP_STRIDE,
    SCORING_RULES,
    CostSpec,
    gaussian_crps,
    gaussian_nlpd,
    nrmse,
)
from kftune.tuning.runs import (
    FilterSpec,
    channel_estimate,
    first_scored,
    output_std,
    where_diverged,
)


@dataclass(frozen=True)
class ManoeuvreScore:
    """What one manoeuvre contributes to the cost.

    Attributes:
        name: manoeuvre name. n: its number of samples.
        nrmse: channel → NRMSE (paper Eq. 15) for the weighted channels.
        scale: channel → the max|X| that NRMSE was normalised by (the channel's unit; for
            the cost normalised over the whole set, ``CostSpec.normalise="dataset"``).
        nis_sum: Σ_k NIS_k over the manoeuvre (for the NIS cost).
        log_det_s_sum: Σ_k log det S_k (with ``nis_sum``, the innovation likelihood).
        msp_sq, msp_n: per cost channel the sum of squared multi-step prediction errors,
            and the number of start samples (the ``msp`` cost).
        score_sum: channel → Σ_k of the per-sample scoring rule (the ``nlpd`` cost: NLPD
            [nats]; ``crps``: CRPS [channel unit]) of the reference under the filter's
            Gaussian, for the weighted channels (with ``scale`` their max|X|).
    """

    name: str
    n: int
    nrmse: dict[str, float]
    nis_sum: float
    scale: dict[str, float] = field(default_factory=dict)
    log_det_s_sum: float = 0.0
    msp_sq: tuple[float, ...] = ()
    msp_n: int = 0
    score_sum: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Evaluation:
    """One cost evaluation in detail.

    Attributes:
        cost: J.
        pooled: channel → pooled error E_j (paper Eq. 14); empty for the NIS cost.
        mean_nis: mean NIS over all samples [-] (3 for a consistent filter).
        scores: per-manoeuvre contributions.
    """

    cost: float
    pooled: dict[str, float]
    mean_nis: float
    scores: tuple[ManoeuvreScore, ...]


def score_manoeuvre(
    m: Manoeuvre,
    fs: FilterSpec,
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
    spec: CostSpec,
    burn_in: float,
    params: np.ndarray | None = None,
    cov_scale: float = 1.0,
) -> ManoeuvreScore:
    """One manoeuvre's score of one point: ``params`` (n_p,) are the point's model
    parameters (:meth:`TuningProblem.params_at`; None: the recorded model's)."""
    res = fs.run(m, q, r, settings, params=params, cov_scale=cov_scale)
    return score_result(m, res, spec, burn_in, fs, fs.params_or(params))


def log_det_s_sum(res: FilterResult, k0: int) -> float:
    """Σ log det S from step k0 on (the pem cost's); the vector kernel does not compute it."""
    if res.log_det_s is None:
        raise ValueError("the pem cost needs log det S, which this run did not compute")
    return float(np.sum(res.log_det_s[k0:]))


def score_result(
    m: Manoeuvre,
    res: FilterResult,
    spec: CostSpec,
    burn_in: float,
    fs: FilterSpec,
    params: np.ndarray,
) -> ManoeuvreScore:
    """One manoeuvre's contribution from the filter's run over it (``fs`` and ``params``
    (n_p,): the run's model, for the multi-step predictions of the msp cost)."""
    if res.diverged:
        raise FilterDivergedError(f"filter diverged on {where_diverged(m, res)}")
    k0 = first_scored(m, burn_in)
    channels = spec.channels if spec.kind == "nrmse" else ()
    scores, scales = {}, {}
    for c in channels:
        est, ref = channel_estimate(m, res, c, spec.estimate)
        try:
            scores[c] = nrmse(est[k0:], ref[k0:])
        except ValueError as exc:  # e.g. a reference that is zero throughout
            raise DataError(f"manoeuvre {m.name!r}: cannot score channel {c!r}: {exc}") from None
        scales[c] = float(np.max(np.abs(ref[k0:])))
    score_sum: dict[str, float] = {}
    if spec.kind in SCORING_RULES:
        rule = gaussian_nlpd if spec.kind == "nlpd" else gaussian_crps
        for c in spec.channels:
            est, ref = channel_estimate(m, res, c)
            scales[c] = float(np.max(np.abs(ref[k0:])))
            if spec.kind == "crps" and not scales[c] > 0:
                raise DataError(
                    f"manoeuvre {m.name!r}: cannot score channel {c!r} by the crps cost: the "
                    "reference is identically zero (the cost is divided by its largest |X|)"
                )
            score_sum[c] = float(np.sum(rule(ref[k0:] - est[k0:], output_std(res, c)[k0:])))
    msp_sq: tuple[float, ...] = ()
    msp_n = 0
    if spec.kind == "msp":
        msp_sq, msp_n = multistep_errors(m, res, fs, params, spec, k0)
    return ManoeuvreScore(
        name=m.name,
        n=m.n - k0,
        nrmse=scores,
        scale=scales,
        nis_sum=float(np.sum(res.nis[k0:])),
        log_det_s_sum=log_det_s_sum(res, k0) if spec.kind == "pem" else 0.0,
        msp_sq=msp_sq,
        msp_n=msp_n,
        score_sum=score_sum,
    )


def msp_channels(spec: CostSpec, model: StateSpaceModel) -> list[int]:
    """Indices into ``model``'s measurements of the multi-step cost's channels."""
    names = model.measurement_names
    return [names.index(c) for c in spec.channels if c in names]


def multistep_errors(
    m: Manoeuvre, res: FilterResult, fs: FilterSpec, params: np.ndarray, spec: CostSpec, k0: int
) -> tuple[tuple[float, ...], int]:
    """Sums of squared h-step open-loop prediction errors from x⁺_k through the model's own
    f and h (:meth:`~kftune.models.StateSpaceModel.predict_open_loop`), any model."""
    model = fs.model
    h = max(1, round(MSP_HORIZON / m.dt))
    ks = np.arange(k0, m.n - h, MSP_STRIDE)
    chans = msp_channels(spec, model)
    if ks.size == 0:
        return tuple(0.0 for _ in chans), 0
    u, z = fs.inputs(m)
    w = model.prepared_inputs(np.zeros((m.n, 0)) if u is None else u, params)
    zh = model.predict_open_loop(res.x[ks], w, params, m.dt, ks, h)
    with np.errstate(all="ignore"):
        err = zh[:, chans] - z[ks + h][:, chans]
        sq = np.sum(err * err, axis=0)
    return tuple(float(v) for v in sq), int(ks.size)
