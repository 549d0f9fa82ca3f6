"""The black-box tuning problem: a parameter vector → UKF runs over manoeuvres → a cost.

    x (natural units) ──NoiseParameterization──▶ (Q diag, R diag, sigma-point settings)
                       ──run_ukf per manoeuvre──▶ estimates
                       ──cost (paper Eq. 14–15, NIS or innovation likelihood)──▶ J

The optimiser sees only ``problem(x) -> J`` and ``problem.space``; a diverged filter (also one
that ran away to an impossible sideslip or speed, see :mod:`kftune.filters._kernel`) raises
:class:`FilterDivergedError`, which :func:`kftune.minimize` records as a failed evaluation.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import multiprocessing
import os
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.data.validate import CHANNEL_DIMENSION, SI_UNIT, UNITS
from kftune.errors import ConfigError, DataError, FilterDivergedError
from kftune.filters import UKFResult, UKFSettings, run_ukf, run_ukf_simd
from kftune.filters.generic import FilterResult, ModelFilter, get_filter
from kftune.models import DataRefused, StateSpaceModel, model_names
from kftune.models.user import is_model_file, load_model, model_file_sha256
from kftune.processes import sigint_blocked, watch_parent
from kftune.space import Param, Space
from kftune.tuning.cost import (
    MSP_HORIZON,
    MSP_STRIDE,
    SCORING_RULES,
    CostSpec,
    gaussian_crps,
    gaussian_nlpd,
    innovation_nll,
    multistep_cost,
    nis_cost,
    nrmse,
    scoring_rule_cost,
    weighted_cost,
)
from kftune.tuning.hookcheck import check_model_file
from kftune.tuning.kpi import sideslip_kpis
from kftune.vehicle.params import VehicleParams

#: Paper Sec. VI: every process-noise parameter searched in [1e-10, 1] (log10 scale here).
Q_BOUNDS = (1e-10, 1.0)
#: The single-track model's states and measurements (the paper's filter).
SIDESLIP_STATES = ("vx", "vy", "r")
SIDESLIP_MEASUREMENTS = ("vx", "ay", "r")
Q_NAMES = tuple(f"q_{s}" for s in SIDESLIP_STATES)
#: How R is tuned: not at all (paper), one factor on R₀, or one factor per measurement.
R_MODES = ("none", "scale", "diag")

Bounds = tuple[float, float]


@dataclass(frozen=True)
class NoiseParameterization:
    """What the optimiser tunes, and how its vector maps onto the filter.

    Always the diagonal of Q, one parameter ``q_<state>`` per state of the model (default:
    the single-track model's ``q_vx, q_vy, q_r`` [(m/s)², (m/s)², (rad/s)²]), on a log10
    scale over ``q_bounds`` (paper: [1e-10, 1]) — one box for all, or a box per name
    (``{"q_vy": (1e-8, 1e-2)}``; names not given keep :data:`Q_BOUNDS`). Optionally (the
    paper's future work), R as factors on the measurement-noise variances R₀ from sensor
    statistics, log10 over ``r_scale_bounds``:

    * ``tune_r="scale"`` (or ``tune_r_scale=True``): one ``r_scale`` [-], R = r_scale·R₀.
      Only the ratio of Q to R shapes the gain, so this matters mostly for the NIS cost
      and for filters whose R₀ is poorly known;
    * ``tune_r="diag"``: one factor ``r_<measurement>_scale`` [-] per measurement,
      R = diag(f)·R₀.

    And ``tune_sigma_points``: ``ukf_alpha`` (log10), ``ukf_beta`` and ``ukf_kappa``
    (linear), the sigma-point parameters (FilterPy's ``MerweScaledSigmaPoints`` convention;
    κ > −2 keeps n + κ ≥ 1).

    And the model's own parameters (``param_names`` of the model; for the single-track
    models the vehicle's fields, e.g. ``C_af`` [N/rad]): ``model_bounds`` name → (low, high)
    in the parameter's unit adds one parameter of that name per entry, after the others,
    on the scale ``model_scales[name]`` — default log10 where low > 0 (stiffness, mass and
    friction are scale quantities whose uncertainty is relative: ×0.7 and ×1.4 are equally
    likely guesses), else linear. ``model_start`` name → the recorded value, the start and
    manual point (:func:`kftune.experiment.manual_point`); :class:`TuningProblem` fills
    the names it lacks from the model's recorded parameters. Whether a name is a parameter
    of the model and its box plausible is checked against the model
    (:func:`check_model_params`).
    """

    q_bounds: Bounds | Mapping[str, Bounds] = Q_BOUNDS
    tune_r_scale: bool = False
    r_scale_bounds: tuple[float, float] = (1e-2, 1e2)
    tune_sigma_points: bool = False
    alpha_bounds: tuple[float, float] = (1e-2, 2.0)
    beta_bounds: tuple[float, float] = (0.0, 4.0)
    kappa_bounds: tuple[float, float] = (-2.0, 3.0)
    default_settings: UKFSettings = field(default_factory=UKFSettings)
    states: tuple[str, ...] = SIDESLIP_STATES
    measurements: tuple[str, ...] = SIDESLIP_MEASUREMENTS
    tune_r: str = "none"
    model_bounds: Mapping[str, Bounds] = field(default_factory=dict)
    model_scales: Mapping[str, str] = field(default_factory=dict)
    model_start: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "states", tuple(self.states))
        object.__setattr__(self, "measurements", tuple(self.measurements))
        self._check_model_fields()
        if self.tune_r not in R_MODES:
            raise ValueError(f"tune_r must be one of {list(R_MODES)}, got {self.tune_r!r}")
        if self.tune_r_scale and self.tune_r == "diag":
            raise ValueError('tune_r_scale and tune_r="diag" exclude each other')
        if self.tune_r_scale:
            object.__setattr__(self, "tune_r", "scale")
        if isinstance(self.q_bounds, Mapping):
            unknown = sorted(set(self.q_bounds) - set(self.q_names))
            if unknown:
                raise ValueError(
                    f"q_bounds names {unknown} are not parameters of this model; "
                    f"expected some of {list(self.q_names)}"
                )

    def _check_model_fields(self) -> None:
        """Normalise ``model_bounds``/``model_scales``/``model_start`` to plain dicts of
        floats and refuse what no model could take (each message names the parameter)."""
        bounds: dict[str, Bounds] = {}
        for name, box in dict(self.model_bounds).items():
            try:
                low, high = (float(v) for v in box)
            except (TypeError, ValueError):
                raise ValueError(
                    f"model parameter {name!r}: bounds must be (low, high), got {box!r}"
                ) from None
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(
                    f"model parameter {name!r}: bounds must be finite with low < high, "
                    f"got ({low:g}, {high:g})"
                )
            bounds[str(name)] = (low, high)
        scales: dict[str, str] = {}
        for name, scale in dict(self.model_scales).items():
            if name not in bounds:
                raise ValueError(
                    f"a scale is given for model parameter {name!r}, which is not tuned; "
                    f"tuned: {list(bounds)}"
                )
            if scale not in ("log10", "linear"):
                raise ValueError(
                    f"model parameter {name!r}: scale must be 'log10' or 'linear', got {scale!r}"
                )
            scales[name] = scale
        for name, (low, _) in bounds.items():
            scales.setdefault(name, "log10" if low > 0 else "linear")
            if scales[name] == "log10" and low <= 0:
                raise ValueError(
                    f"model parameter {name!r}: a log10 scale needs a positive lower bound, "
                    f"got {low:g} (give the scale 'linear')"
                )
        start: dict[str, float] = {}
        for name, value in dict(self.model_start).items():
            if name not in bounds:
                raise ValueError(
                    f"a start value is given for model parameter {name!r}, which is not "
                    f"tuned; tuned: {list(bounds)}"
                )
            v = float(value)
            low, high = bounds[name]
            if not low <= v <= high:
                # refused, not clipped: the start is the recorded model, the manual point
                # and the baseline of the held-out comparison; a clipped one is a model
                # nobody recorded
                raise ValueError(
                    f"model parameter {name!r}: its recorded value {v:g} lies outside its "
                    f"box [{low:g}, {high:g}]; widen the box to include it"
                )
            start[name] = v
        object.__setattr__(self, "model_bounds", bounds)
        object.__setattr__(self, "model_scales", {n: scales[n] for n in bounds})
        object.__setattr__(self, "model_start", start)

    @property
    def model_names(self) -> tuple[str, ...]:
        """The tuned model parameters, in the order of ``model_bounds`` (as in the space)."""
        return tuple(self.model_bounds)

    def model_values(self, x: Sequence[float] | np.ndarray) -> dict[str, float]:
        """The model parameters of a point of :attr:`space` (natural units), name → value."""
        if not self.model_bounds:
            return {}
        names = self.space.names
        x = np.asarray(x, dtype=float)
        if x.shape != (len(names),):
            raise ValueError(f"expected a point with {len(names)} values {names}, got {x.shape}")
        return {n: float(x[names.index(n)]) for n in self.model_names}

    def with_start(self, recorded: Mapping[str, float]) -> NoiseParameterization:
        """This parameterisation with ``model_start`` completed from ``recorded`` (name →
        the model's recorded value) for the tuned names it lacks (itself when none)."""
        missing = {n: float(recorded[n]) for n in self.model_names if n not in self.model_start}
        if not missing:
            return self
        return replace(self, model_start={**self.model_start, **missing})

    @property
    def q_names(self) -> tuple[str, ...]:
        """``q_<state>`` for every state, in state order."""
        return tuple(f"q_{s}" for s in self.states)

    @property
    def r_names(self) -> tuple[str, ...]:
        """The R parameters: none, ``("r_scale",)`` or ``r_<measurement>_scale`` each."""
        if self.tune_r == "scale":
            return ("r_scale",)
        if self.tune_r == "diag":
            return tuple(f"r_{m}_scale" for m in self.measurements)
        return ()

    def q_box(self, name: str) -> Bounds:
        """The (low, high) box of a Q parameter."""
        if isinstance(self.q_bounds, Mapping):
            low, high = self.q_bounds.get(name, Q_BOUNDS)
            return (low, high)
        return self.q_bounds

    @property
    def space(self) -> Space:
        """The search space (validates the bounds)."""
        params = [Param(name, *self.q_box(name), scale="log10") for name in self.q_names]
        params += [Param(name, *self.r_scale_bounds, scale="log10") for name in self.r_names]
        if self.tune_sigma_points:
            params += [
                Param("ukf_alpha", *self.alpha_bounds, scale="log10"),
                Param("ukf_beta", *self.beta_bounds),
                Param("ukf_kappa", *self.kappa_bounds),
            ]
        params += [
            Param(name, *self.model_bounds[name], scale=self.model_scales[name], physical=True)
            for name in self.model_names
        ]
        return Space(tuple(params))

    def decode(
        self, x: Sequence[float] | np.ndarray, r0: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, UKFSettings]:
        """Map a point of :attr:`space` (natural units) to (q (n,), r (m,), settings)."""
        names = self.space.names
        x = np.asarray(x, dtype=float)
        if x.shape != (len(names),):
            raise ValueError(f"expected a point with {len(names)} values {names}, got {x.shape}")
        values = dict(zip(names, x.tolist()))
        q = np.array([values[n] for n in self.q_names])
        r = np.asarray(r0, dtype=float) * values.get("r_scale", 1.0)
        if self.tune_r == "diag":
            r = r * np.array([values[n] for n in self.r_names])
        settings = self.default_settings
        if self.tune_sigma_points:
            settings = UKFSettings(values["ukf_alpha"], values["ukf_beta"], values["ukf_kappa"])
        return q, r, settings

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable description (for reports and study metadata)."""
        out: dict[str, Any] = {
            "names": list(self.space.names),
            "space": self.space.to_dict(),
            "sigma_points": None
            if self.tune_sigma_points
            else {
                "alpha": self.default_settings.alpha,
                "beta": self.default_settings.beta,
                "kappa": self.default_settings.kappa,
            },
        }
        if self.states != SIDESLIP_STATES or self.measurements != SIDESLIP_MEASUREMENTS:
            out["states"], out["measurements"] = list(self.states), list(self.measurements)
        if self.model_bounds:  # absent without: a noise-only study keeps its fingerprint
            out["model"] = {
                n: {
                    "low": self.model_bounds[n][0],
                    "high": self.model_bounds[n][1],
                    "scale": self.model_scales[n],
                    "start": self.model_start.get(n),
                }
                for n in self.model_names
            }
        return out


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


#: A filter run's output: the paper's 3×3 kernel or the generic filters.
RunResult = UKFResult | FilterResult


def output_names(model: StateSpaceModel) -> tuple[str, ...]:
    """What a cost or KPI can score against a reference channel ``<name>_ref``: the model's
    derived outputs (the single-track models' ``beta``), then its states that are not also
    measurements (the single-track ``vy``, the CTRV model's ``v``, ``psi``, ``omega``)."""
    states = [s for s in model.state_names if s not in model.measurement_names]
    return (*model.outputs, *(s for s in states if s not in model.outputs))


def check_units(model: StateSpaceModel, dataset: Dataset) -> None:
    """Refuse a model whose inputs or measurements are in other units than the dataset's
    channels of the same names (SI, as kftune holds every channel; a model that says km
    would read metres as kilometres).

    Raises:
        ConfigError: naming the model, the channel and both units.
    """
    for kind, names, units in (
        ("input", model.input_names, model.input_units),
        ("measurement", model.measurement_names, model.measurement_units),
    ):
        for name, unit in zip(names, units):
            dim = CHANNEL_DIMENSION.get(name)
            data = SI_UNIT[dim] if dim is not None else dataset.units.get(name)
            if data is None or unit.strip() == data:
                continue
            ours, theirs = UNITS.get(unit.strip()), UNITS.get(data)
            if ours is not None and theirs is not None and ours == theirs:
                continue  # two spellings of one unit
            raise ConfigError(
                f"model {model.name!r}: {kind} {name!r} is in {unit!r}, but the dataset "
                f"{dataset.name!r} holds it in {data!r} (SI): give the model's units as the "
                "data's"
            )


def check_cost_channels(spec: CostSpec, model: StateSpaceModel) -> None:
    """Refuse an NRMSE cost that weighs a channel ``model`` cannot score, and a scoring-rule
    cost (nlpd, crps) that weighs a channel other than an output with a standard deviation
    (:func:`std_outputs`).

    Raises:
        ConfigError: naming the channel, the model's measurements and its outputs.
    """
    if spec.kind in SCORING_RULES:
        scored = std_outputs(model)
        for c in spec.channels:
            if c not in scored:
                what = "a measurement" if c in model.measurement_names else "not an output"
                raise ConfigError(
                    f"cost channel {c!r} ({what} of model {model.name!r}): the {spec.kind} "
                    "cost scores a reference channel <output>_ref under the filter's "
                    f"Gaussian, for an output with a standard deviation: {list(scored)} (a "
                    "measured channel's predictive density is the pem cost's)"
                )
        return
    if spec.kind != "nrmse":
        return
    outputs = output_names(model)
    for c in spec.channels:
        if c not in model.measurement_names and c not in outputs:
            raise ConfigError(
                f"unknown cost channel {c!r}: neither a measurement of model {model.name!r} "
                f"{list(model.measurement_names)} nor one of its outputs {list(outputs)} "
                "(scored against a reference channel <output>_ref)"
            )


#: Vehicle fields that are no parameters of the single-track models, and why.
_NOT_IN_MODEL = {
    "track_f": "the single-track model lumps each axle",
    "track_r": "the single-track model lumps each axle",
    "steering_ratio": "it only converts recorded hand-wheel angles when data are imported",
}


def check_model_params(par: NoiseParameterization, model: StateSpaceModel) -> None:
    """Refuse tuned model parameters ``model`` cannot take: a name that is not one of its
    ``param_names``, or a box beyond the model's plausible range of the parameter
    (``param_ranges``; the single-track models: the vehicle's ``PLAUSIBLE_RANGES``).

    Raises:
        ConfigError: naming the parameter and the model's parameters or the range.
    """
    for name, (low, high) in par.model_bounds.items():
        if name not in model.param_names:
            why = f" ({_NOT_IN_MODEL[name]})" if name in _NOT_IN_MODEL else ""
            raise ConfigError(
                f"tune_model: {name!r} is not a parameter of model {model.name!r}{why}; it "
                f"has {list(model.param_names)}"
            )
        if name in model.param_ranges:
            lo, hi = model.param_ranges[name]
            unit = model.param_units[model.param_names.index(name)]
            if low < lo or high > hi:
                raise ConfigError(
                    f"tune_model: the box of {name!r}, [{low:g}, {high:g}] {unit}, reaches "
                    f"beyond its plausible range [{lo:g}, {hi:g}] {unit} (model "
                    f"{model.name!r}); give a box within it"
                )


def model_output(res: RunResult, name: str) -> np.ndarray:
    """(N,) an output of the run's model (:func:`output_names`) from the posterior states,
    e.g. ``"beta"`` [rad] (the sideslip atan2(Vy, Vx) of the single-track models) or a
    state by name (in its unit)."""
    from kftune.models import SINGLE_TRACK

    model = SINGLE_TRACK if isinstance(res, UKFResult) else res.model
    if isinstance(res, UKFResult) and name == "beta":
        return res.beta
    if name in model.outputs:
        return np.asarray(model.outputs[name](res.x), dtype=float)
    if name in output_names(model):
        return np.asarray(res.x[:, model.state_names.index(name)], dtype=float)
    raise KeyError(
        f"model {model.name!r} has no output {name!r}; it has {list(output_names(model))}"
    )


def beta_std(x: np.ndarray, p_diag: np.ndarray) -> np.ndarray:
    """(N,) standard deviation [rad] of β = atan2(Vy, Vx) by the delta method.

    Linearises β about the estimate: ∂β/∂Vx = −Vy/(Vx² + Vy²), ∂β/∂Vy = Vx/(Vx² + Vy²), so
    var β ≈ (Vy²·var Vx + Vx²·var Vy)/(Vx² + Vy²)². Only the diagonal of P is kept by the
    filter's output, so the Vx–Vy covariance is left out (it is small when Vx is measured).

    Args:
        x: (N, ≥2) states with Vx in column 0 and Vy in column 1 [m/s]; p_diag: (N, ≥2) their
            variances [(m/s)²].
    """
    vx, vy = x[:, 0], x[:, 1]
    s = vx**2 + vy**2
    return np.sqrt(vy**2 * p_diag[:, 0] + vx**2 * p_diag[:, 1]) / s


def std_outputs(model: StateSpaceModel) -> tuple[str, ...]:
    """The outputs of ``model`` (:func:`output_names`) whose standard deviation the filter
    gives (:func:`output_std`): β of a model whose first states are Vx, Vy, and every
    state that is not measured."""
    beta = "beta" in model.outputs and model.state_names[:2] == ("vx", "vy")
    return tuple(c for c in output_names(model) if (c == "beta" and beta) or c in model.state_names)


def output_std(res: RunResult, name: str) -> np.ndarray:
    """(N,) the standard deviation of :func:`model_output` ``name`` from the posterior
    covariance's diagonal: β [rad] by the delta method (:func:`beta_std`), a state's
    √P_ii in its unit.

    Raises:
        KeyError: an output whose σ the filter does not give (:func:`std_outputs`).
    """
    from kftune.models import SINGLE_TRACK

    model = SINGLE_TRACK if isinstance(res, UKFResult) else res.model
    if name not in std_outputs(model):
        raise KeyError(
            f"model {model.name!r} gives no standard deviation of {name!r}; it gives one of "
            f"{list(std_outputs(model))}"
        )
    if name == "beta" and "beta" in model.outputs:
        return beta_std(res.x, res.P_diag)
    return np.sqrt(np.asarray(res.P_diag[:, model.state_names.index(name)], dtype=float))


def channel_estimate(
    m: Manoeuvre, res: RunResult, channel: str, estimate: str = "posterior"
) -> tuple[np.ndarray, np.ndarray]:
    """(estimate, reference) of a cost channel over the whole manoeuvre.

    A measurement of the model (yaw rate [rad/s], ay [m/s²], Vx [m/s] for the single-track
    model) against its measured channel, estimated by h(x⁺_k) (``"posterior"``) or by the
    one-step prediction z_k − innovation_k (``"prior"``); any other channel is a derived
    output of the model (β [rad] from the posterior state, or a state that is not
    measured, :func:`output_names`) against the reference channel ``<channel>_ref`` of the
    data (``beta_ref``); see :class:`~kftune.tuning.cost.CostSpec`.
    """
    names = SIDESLIP_MEASUREMENTS if isinstance(res, UKFResult) else res.model.measurement_names
    if channel not in names:
        return model_output(res, channel), m.channel(f"{channel}_ref")
    column = names.index(channel)
    measured = m.channel(channel)
    if estimate == "prior":
        return measured - res.innovation[:, column], measured
    return res.z_hat[:, column], measured


#: Where a filter diverged, as :func:`where_diverged` says it: not part of a failure's kind.
_WHERE_DIVERGED = re.compile(r" on manoeuvre (?:'[^']*'|\"[^\"]*\") at step \d+ \(t = [^)]*\)")
#: The exception's class name in front of a failed evaluation's reason.
_EXCEPTION_NAME = re.compile(r"^[A-Za-z_]\w*(?:Error|Exception): ")


def failure_kinds(reasons: Iterable[str | None]) -> list[tuple[str, int]]:
    """Failed evaluations' reasons grouped by kind, most frequent first, as
    ``[(kind, count), …]``: a reason without the exception's class name and without where
    the filter diverged (manoeuvre, step, time), so that the divergences of one cause are
    one kind (``"filter diverged: runaway: the estimated sideslip went beyond ±60°"``).
    A missing reason counts as ``"no reason recorded"``."""
    kinds = Counter(
        _WHERE_DIVERGED.sub("", _EXCEPTION_NAME.sub("", r)) if r else "no reason recorded"
        for r in reasons
    )
    return kinds.most_common()


def where_diverged(m: Manoeuvre, res: RunResult) -> str:
    """``"manoeuvre 'x' at step k (t = … s): <cause>"`` for a run that diverged on ``m``."""
    return (
        f"manoeuvre {m.name!r} at step {res.diverged_step} "
        f"(t = {m.t[res.diverged_step]:.2f} s): {res.diverged_reason}"
    )


def first_scored(m: Manoeuvre, burn_in: float) -> int:
    """Index of the first sample scored after a burn-in of ``burn_in`` seconds."""
    return int(np.searchsorted(m.t - m.t[0], burn_in - 1e-9 * m.dt))


def scaled_covariances(res: RunResult, c: float) -> RunResult:
    """A run's result with its covariances c times larger and its estimate as it is: P_diag·c,
    NIS/c (S·c), log det S + m·ln c — the run with c·Q, c·R and c·P0 of a Kalman filter or
    EKF (:meth:`FilterSpec.run`'s ``cov_scale``)."""
    log_det = res.log_det_s
    m = res.innovation.shape[1]
    return replace(
        res,
        P_diag=res.P_diag * c,
        nis=res.nis / c,
        log_det_s=None if log_det is None else log_det + m * math.log(c),
    )


@dataclass(frozen=True)
class FilterSpec:
    """Which filter runs which model: the paper's pair (single-track UKF) runs on the
    hand-written 3×3 kernel, every other pair on the generic kernels.

    Attributes:
        model: the state-space model. spec: how to load it again (a registered name or a
            model file, for worker processes and tuned files).
        filter: ``"ukf"`` or ``"ekf"``. params: (n_p,) the model's parameters.
    """

    model: StateSpaceModel
    spec: str
    filter: str
    params: np.ndarray

    @property
    def fast(self) -> bool:
        """Whether the 3×3 kernel runs it (the paper's model and filter)."""
        from kftune.models import SINGLE_TRACK

        return self.model is SINGLE_TRACK and self.filter == "ukf"

    def inputs(self, m: Manoeuvre) -> tuple[np.ndarray | None, np.ndarray]:
        """(u (N, n_u) or None, z (N, m)) of a manoeuvre, by the model's channel names."""
        if self.fast:
            return m.u, m.z
        names = self.model.input_names
        u = np.column_stack([m.channel(c) for c in names]) if names else None
        return u, np.column_stack([m.channel(c) for c in self.model.measurement_names])

    def probe(
        self,
        manoeuvres: Sequence[Manoeuvre],
        r: np.ndarray,
        q: np.ndarray | None = None,
        settings: UKFSettings | None = None,
    ) -> None:
        """Run the model's hooks before a filter relies on them, with measurement variances
        ``r``: once on the first sample of each manoeuvre
        (:meth:`~kftune.models.StateSpaceModel.probe`). A model file's hooks run in a
        child process instead, where a hook that never returns can be stopped (Ctrl-C,
        SIGTERM), and then through the filter with bounds checked (process-noise
        variances ``q``, default 1e-4 each; the UKF's sigma-point ``settings``, default
        :class:`~kftune.filters.UKFSettings`, so that the check visits the states the
        filter it protects visits):
        :func:`~kftune.tuning.hookcheck.check_model_file`. kftune's own models are not
        probed in a child (nor the paper's kernel at all).

        Raises:
            ConfigError: naming the model (its file), the manoeuvre and the hook.
        """
        if self.fast or not manoeuvres:
            return
        if is_model_file(self.spec):
            runs = [(m.name, *self.inputs(m), m.dt) for m in manoeuvres]
            qs = np.full(self.model.n_states, 1e-4) if q is None else np.asarray(q, float)
            try:
                check_model_file(
                    self.spec,
                    self.filter,
                    runs,
                    self.params,
                    qs,
                    np.asarray(r),
                    settings or UKFSettings(),
                )
            except ValueError as exc:
                raise ConfigError(f"model {self.spec}, {exc}") from None
            return
        for m in manoeuvres:
            u, z = self.inputs(m)
            try:
                self.model.probe(u, z, r, self.params, m.dt)
            except ValueError as exc:
                raise ConfigError(f"model {self.spec}, on manoeuvre {m.name!r}: {exc}") from None

    def run(
        self,
        m: Manoeuvre,
        vehicle: VehicleParams | None,
        q: np.ndarray,
        r: np.ndarray,
        settings: UKFSettings,
        *,
        params: np.ndarray | None = None,
        cov_scale: float = 1.0,
    ) -> RunResult:
        """The filter's run over one manoeuvre.

        Args:
            m: the manoeuvre. vehicle: the vehicle of the paper's kernel (single-track UKF).
            q: (n,) and r: (m,) the noise variances. settings: the UKF's sigma points.
            params: (n_p,) the model's parameter vector for this run (None: :attr:`params`,
                or for the paper's kernel ``vehicle``).
            cov_scale: c > 0: the calibration (:mod:`kftune.tuning.calibrate`): the filter
                runs with Q, R and its default prior as given, and reports every covariance
                c times larger (P_diag·c, NIS/c, log det S + m·ln c). For a Kalman filter and
                an EKF this is exactly the run with c·Q, c·R and c·P0 (the gain is
                homogeneous of degree 0 in (P, Q, R), so the estimate, and with it the
                EKF's Jacobians, stay); a UKF run so would spread its sigma points √c times
                wider and move its estimate (by how much: BENCHMARKS.md, "Calibrated
                uncertainty"), so the UKF keeps the tuned filter's.
        """
        c = float(cov_scale)
        if not (math.isfinite(c) and c > 0):
            raise ValueError(f"cov_scale must be a positive finite number, got {cov_scale!r}")
        res: RunResult
        if self.fast:
            p = vehicle if params is None else params
            if p is None:  # filter_spec gives the paper's kernel a vehicle
                raise ValueError("the single-track kernel needs a vehicle or its parameters")
            res = run_ukf(m.u, m.z, m.dt, p, q, r, settings=settings)
        else:
            u, z = self.inputs(m)
            p = self.params if params is None else np.asarray(params, dtype=float)
            res = self.filter_object(settings).run(self.model, u, z, m.dt, q, r, params=p)
        return res if c == 1.0 else scaled_covariances(res, c)

    def filter_object(self, settings: UKFSettings) -> ModelFilter:
        """The generic filter (the UKF with these sigma-point settings)."""
        return get_filter("ukf", settings=settings) if self.filter == "ukf" else get_filter("ekf")


def filter_spec(
    model: str | StateSpaceModel, filter: str, vehicle: VehicleParams | None
) -> FilterSpec:
    """A :class:`FilterSpec` from a model name, model file or model, and a filter name; a
    vehicle model's parameters come from ``vehicle``, another model's are its defaults.

    Raises:
        ConfigError: unknown model or filter, a model file that cannot be loaded, or a
            model that needs a vehicle (the single-track models) without one.
    """
    mod = load_model(model)
    if filter not in ("ukf", "ekf"):
        raise ConfigError(f"filter must be 'ukf' or 'ekf', got {filter!r}")
    if mod.needs_vehicle and vehicle is None:
        raise ConfigError(
            f"model {mod.name!r} needs the vehicle's parameters, but the dataset has no vehicle "
            "(a manifest's 'vehicle' table or preset name); for data of something else choose "
            f"a model that fits them (--model; built-in: {', '.join(model_names())})"
        )
    spec = model if isinstance(model, str) else mod.name
    if vehicle is not None and mod.pack_params is not None:
        try:
            params = mod.pack_params(vehicle)
        except (TypeError, ValueError, AttributeError):
            params = np.asarray(mod.param_defaults, dtype=float)
    else:
        params = np.asarray(mod.param_defaults, dtype=float)
    return FilterSpec(mod, spec, filter, np.asarray(params, dtype=float))


def default_r0(
    model: StateSpaceModel,
    r_default: Dataset | Mapping[str, float] | Sequence[float] | np.ndarray,
    overrides: Mapping[str, float] | None = None,
) -> np.ndarray:
    """(m,) the measurement-noise variances R₀ of a model's measurements: ``overrides``
    (name → variance, e.g. from a configuration's ``r0``) first, then the estimate from
    the data: a dataset's :meth:`~kftune.data.Dataset.noise_variances` of the model's
    measurement channels (of those not overridden), a mapping name → variance, or an
    array of the single-track channels [Vx, ay, r] (``Dataset.r_default``).

    Raises:
        ConfigError: a measurement with neither, or an override that is not a measurement
            or not a positive finite number.
        MissingChannelError: a dataset whose manoeuvres lack a measurement channel.
    """
    given = dict(overrides or {})
    extra = sorted(set(given) - set(model.measurement_names))
    if extra:
        raise ConfigError(
            f"r0 names {extra} are not measurements of model {model.name!r} "
            f"{list(model.measurement_names)}"
        )
    if isinstance(r_default, Dataset):
        wanted = [c for c in model.measurement_names if c not in given]
        for m in r_default.train or r_default.manoeuvres:
            m.require(wanted, f"model {model.name!r}", "measurement channel")
        known = dict(zip(wanted, r_default.noise_variances(wanted).tolist()))
    elif isinstance(r_default, Mapping):
        known = {str(k): float(v) for k, v in r_default.items()}
    else:
        known = dict(zip(SIDESLIP_MEASUREMENTS, np.asarray(r_default, dtype=float).tolist()))
    out = []
    for name in model.measurement_names:
        v = given.get(name, known.get(name))
        if v is None:
            raise ConfigError(
                f"no measurement-noise variance for {name!r} of model {model.name!r}: give it "
                f"in the configuration, e.g. r0 = {{ {name} = 0.01 }} (in its unit squared)"
            )
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < v < math.inf):
            raise ConfigError(f"r0 for {name!r} must be a positive finite number, got {v!r}")
        out.append(float(v))
    return np.array(out)


def _score(
    m: Manoeuvre,
    vehicle: VehicleParams | None,
    fs: FilterSpec,
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
    spec: CostSpec,
    burn_in: float,
    params: np.ndarray | None = None,
    cov_scale: float = 1.0,
) -> ManoeuvreScore:
    """One manoeuvre's score of one point: ``vehicle`` and ``params`` are the point's model
    (:meth:`TuningProblem.vehicle_at`, :meth:`TuningProblem.params_at`)."""
    res = fs.run(m, vehicle, q, r, settings, params=params, cov_scale=cov_scale)
    return _score_result(m, res, spec, burn_in, fs, _run_params(fs, vehicle, params))


def _run_params(
    fs: FilterSpec, vehicle: VehicleParams | None, params: np.ndarray | None
) -> np.ndarray:
    """(n_p,) the model's parameter vector a run of ``fs`` used (:meth:`FilterSpec.run`)."""
    if params is not None:
        return np.asarray(params, dtype=float)
    if fs.fast and vehicle is not None:
        return fs.model.params_vector(vehicle)
    return fs.params


def _log_det_s_sum(res: RunResult, k0: int) -> float:
    """Σ log det S from step k0 on (the pem cost's); the vector kernel does not compute it."""
    if res.log_det_s is None:
        raise ValueError("the pem cost needs log det S, which this run did not compute")
    return float(np.sum(res.log_det_s[k0:]))


def _score_result(
    m: Manoeuvre,
    res: RunResult,
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
        msp_sq, msp_n = _multistep_errors(m, res, fs, params, spec, k0)
    return ManoeuvreScore(
        name=m.name,
        n=m.n - k0,
        nrmse=scores,
        scale=scales,
        nis_sum=float(np.sum(res.nis[k0:])),
        log_det_s_sum=_log_det_s_sum(res, k0) if spec.kind == "pem" else 0.0,
        msp_sq=msp_sq,
        msp_n=msp_n,
        score_sum=score_sum,
    )


def _msp_channels(spec: CostSpec, model: StateSpaceModel) -> list[int]:
    """Indices into ``model``'s measurements of the multi-step cost's channels."""
    names = model.measurement_names
    return [names.index(c) for c in spec.channels if c in names]


def _multistep_errors(
    m: Manoeuvre, res: RunResult, fs: FilterSpec, params: np.ndarray, spec: CostSpec, k0: int
) -> tuple[tuple[float, ...], int]:
    """Sums of squared h-step open-loop prediction errors from x⁺_k through the model's own
    f and h (:meth:`~kftune.models.StateSpaceModel.predict_open_loop`), any model."""
    model = fs.model
    h = max(1, round(MSP_HORIZON / m.dt))
    ks = np.arange(k0, m.n - h, MSP_STRIDE)
    chans = _msp_channels(spec, model)
    if ks.size == 0:
        return tuple(0.0 for _ in chans), 0
    u, z = fs.inputs(m)
    w = model.prepared_inputs(np.zeros((m.n, 0)) if u is None else u, params)
    zh = model.predict_open_loop(res.x[ks], w, params, m.dt, ks, h)
    with np.errstate(all="ignore"):
        err = zh[:, chans] - z[ks + h][:, chans]
        sq = np.sum(err * err, axis=0)
    return tuple(float(v) for v in sq), int(ks.size)


# Worker-process state: the manoeuvres are sent once, when the pool starts.
_WORKER: dict[str, Any] = {}


def _init_worker(
    manoeuvres: tuple[Manoeuvre, ...],
    vehicle: VehicleParams | None,
    model: str,
    filter: str,
    parent_pid: int,
) -> None:  # pragma: no cover - runs in the pool's workers
    watch_parent(parent_pid)  # exit with a killed parent; Ctrl-C stops the parent only
    _WORKER["manoeuvres"] = manoeuvres
    _WORKER["vehicle"] = vehicle
    fs = filter_spec(model, filter, vehicle)  # a model file is loaded again here
    _WORKER["filter"] = fs
    # compile / load the kernel now, so no evaluation's timing includes it
    m = manoeuvres[0]
    n, k = fs.model.n_states, fs.model.n_measurements
    fs.run(m, vehicle, np.full(n, 1e-4), np.full(k, 1e-2), UKFSettings())


def _score_chunk(
    indices: list[int],
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
    spec: CostSpec,
    burn_in: float,
    vehicle: VehicleParams | None,
    params: np.ndarray | None,
    cov_scale: float,
) -> list[ManoeuvreScore]:
    ms, fs = _WORKER["manoeuvres"], _WORKER["filter"]
    return [
        _score(ms[i], vehicle, fs, q, r, settings, spec, burn_in, params, cov_scale)
        for i in indices
    ]


class TuningProblem:
    """Cost of a UKF tuning over a set of manoeuvres.

    Args:
        manoeuvres: the manoeuvres the cost is pooled over (the training set).
        vehicle: model parameters of a vehicle model's filter; None for a model that is not
            a vehicle's (the single-track models refuse to run without one).
        r0: (m,) measurement-noise variances of the model's measurements (single-track:
            [Vx, ay, r]; from sensor statistics, :func:`default_r0`; paper: R is not
            optimised).
        cost: which cost (default: the paper's weighted NRMSE, W = (5, 1, 1)).
        parameterization: what is tuned (default: the three Q entries).
        workers: processes that run the manoeuvres in parallel; 1 (default) runs them in
            this process. Use as a context manager (or call :meth:`close`) when > 1.
        model: the state-space model the filter runs: a registered name (default
            ``"single-track"``, the paper's), a model file (``"my_model.py"``, see
            :mod:`kftune.models.user`) or a :class:`~kftune.models.StateSpaceModel`. Its
            inputs and measurements are read from the manoeuvres' channels of the same
            names; a vehicle model takes its parameters from ``vehicle``.
        filter: ``"ukf"`` (default) or ``"ekf"``.
        burn_in: [s] initial part of every manoeuvre left out of the cost (and of
            :func:`assess`'s KPIs), while the filter converges from its default prior; 0
            (default, the paper) scores every sample. Useful for segments cut out of a
            longer recording, which start mid-manoeuvre with the filter's Vy = 0.

    Raises:
        DataError: a manoeuvre the filter cannot run: it lacks a channel the model or the
            cost needs (:class:`~kftune.errors.MissingChannelError`, e.g. ``beta_ref`` for
            the paper's cost), the model refuses its data (the single-track models: Vx ≤ 0),
            or it has fewer than 2 samples after the burn-in; the message names the
            manoeuvre, and the channel and sample where there is one.
        ConfigError: a model that needs a vehicle without one, an unknown cost channel, a
            model whose hooks fail on the first sample (:meth:`StateSpaceModel.probe`).

    ``problem(x)`` returns J for a point of ``problem.space`` (natural units).
    """

    def __init__(
        self,
        manoeuvres: Sequence[Manoeuvre],
        vehicle: VehicleParams | None,
        r0: Sequence[float] | np.ndarray,
        *,
        cost: CostSpec | None = None,
        parameterization: NoiseParameterization | None = None,
        workers: int = 1,
        burn_in: float = 0.0,
        model: str | StateSpaceModel = "single-track",
        filter: str = "ukf",
    ) -> None:
        self.manoeuvres = tuple(manoeuvres)
        self._fs = filter_spec(model, filter, vehicle)
        mod = self._fs.model
        if not self.manoeuvres:
            raise ConfigError("the tuning problem needs at least one manoeuvre")
        if not (
            isinstance(burn_in, (int, float))
            and not isinstance(burn_in, bool)
            and math.isfinite(burn_in)
            and burn_in >= 0
        ):
            raise ConfigError(f"burn_in must be a number of seconds >= 0, got {burn_in!r}")
        self.burn_in = float(burn_in)
        self.cost_spec = cost or CostSpec()
        check_cost_channels(self.cost_spec, mod)
        if self.cost_spec.kind == "msp" and not _msp_channels(self.cost_spec, mod):
            raise ConfigError(
                "the multi-step prediction cost (msp) needs a positive weight on a measured "
                f"channel of model {mod.name!r} ({', '.join(mod.measurement_names)})"
            )
        for m in self.manoeuvres:
            self._check_channels(m)
            if m.n - first_scored(m, self.burn_in) < 2:
                raise ConfigError(
                    f"manoeuvre {m.name!r} ({m.duration:.2f} s) is shorter than the burn-in "
                    f"of {self.burn_in:g} s"
                )
        self.vehicle = vehicle
        self.r0 = np.asarray(r0, dtype=float)
        k = mod.n_measurements
        if self.r0.shape != (k,) or not np.all(np.isfinite(self.r0)) or np.any(self.r0 <= 0):
            raise ConfigError(
                f"r0 must be {k} positive finite variances {list(mod.measurement_names)}, "
                f"got {r0!r}"
            )
        self.parameterization = parameterization or NoiseParameterization(
            states=mod.state_names, measurements=mod.measurement_names
        )
        par = self.parameterization
        if par.states != mod.state_names or par.measurements != mod.measurement_names:
            raise ConfigError(
                f"the tuned parameters are for states {list(par.states)} and measurements "
                f"{list(par.measurements)}, but model {mod.name!r} has "
                f"{list(mod.state_names)} and {list(mod.measurement_names)}"
            )
        check_model_params(par, mod)
        recorded = dict(zip(mod.param_names, self._fs.params.tolist()))
        try:
            self.parameterization = par = par.with_start(recorded)
        except ValueError as exc:
            raise ConfigError(f"tune_model: {exc}") from None
        self._model_index = [mod.param_names.index(n) for n in par.model_names]
        #: c of :meth:`FilterSpec.run`: the runs use c·Q, c·R and c·P0 (1: as tuned).
        self.cov_scale = 1.0
        # before a budget is spent on the model; with the sigma points the tuning starts from
        self._fs.probe(self.manoeuvres, self.r0, settings=par.default_settings)
        if not (isinstance(workers, int) and workers >= 1):
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = min(workers, len(self.manoeuvres))
        self._pool: ProcessPoolExecutor | None = None
        self._chunks = _balanced_chunks([m.n for m in self.manoeuvres], self.workers)
        self._evaluated = False  # see compile_note

    @property
    def space(self) -> Space:
        """The search space of the optimiser."""
        return self.parameterization.space

    @property
    def model(self) -> StateSpaceModel:
        """The model the filter runs."""
        return self._fs.model

    @property
    def filter(self) -> str:
        """``"ukf"`` or ``"ekf"``."""
        return self._fs.filter

    @property
    def model_spec(self) -> str:
        """How the model was named (a registered name or a model file)."""
        return self._fs.spec

    def _outputs(self) -> tuple[str, ...]:
        return output_names(self._fs.model)

    def _check_channels(self, m: Manoeuvre) -> None:
        """Refuse a manoeuvre without the channels the model and the cost need, or data the
        model refuses (naming the manoeuvre, and the channel and row where it can)."""
        mod = self._fs.model
        who = f"model {mod.name!r}"
        m.require(mod.input_names, who, "input channel")
        m.require(mod.measurement_names, who, "measurement channel")
        if self.cost_spec.kind == "nrmse":
            refs = [f"{c}_ref" for c in self.cost_spec.channels if c not in mod.measurement_names]
            m.require(
                refs,
                "the nrmse cost (without a reference sensor, tune with --cost msp, the "
                "multi-step prediction of the measurements — README 'Tuning without a "
                "reference sensor' —, or weigh only measured channels: "
                f"--weights {','.join(f'{c}=1' for c in mod.measurement_names)})",
                "a reference channel",
            )
        elif self.cost_spec.kind in SCORING_RULES:
            m.require(
                [f"{c}_ref" for c in self.cost_spec.channels],
                f"the {self.cost_spec.kind} cost (it scores the reference under the filter's "
                "Gaussian; without a reference sensor use the nis, pem or msp cost)",
                "a reference channel",
            )
        if mod.validate_data is not None:
            u, z = self._fs.inputs(m)
            try:
                mod.validate_data(np.zeros((m.n, 0)) if u is None else u, z)
            except DataRefused as exc:
                raise DataError(
                    f"manoeuvre {m.name!r}, channel {exc.channel(mod)!r}, sample {exc.row} "
                    f"(t = {float(m.t[exc.row]):.4g} s): {who} refuses these data: {exc.reason}"
                ) from None
            except ValueError as exc:
                raise DataError(f"manoeuvre {m.name!r}: {who} refuses these data: {exc}") from None

    def decode(self, x: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray, UKFSettings]:
        """(q, r, settings) of a point."""
        return self.parameterization.decode(x, self.r0)

    def vehicle_at(self, x: Sequence[float] | np.ndarray) -> VehicleParams | None:
        """The vehicle of a point: the recorded one with the point's tuned model parameters
        (None for a model without a vehicle; unchanged for a model whose parameters do not
        come from the vehicle, which runs :meth:`params_at`).

        Raises:
            ValueError: a value the vehicle refuses (outside its plausible range).
        """
        values = self.parameterization.model_values(x)
        if self.vehicle is None or not values or not self._fs.model.needs_vehicle:
            return self.vehicle  # a model not of the vehicle: its parameters by params_at
        return self.vehicle.replace(**values)

    def params_at(self, x: Sequence[float] | np.ndarray) -> np.ndarray:
        """(n_p,) the model's parameter vector at a point: the recorded one with the point's
        tuned model parameters in their places (``param_names``)."""
        p = self._fs.params.copy()
        values = self.parameterization.model_values(x)
        for i, name in zip(self._model_index, self.parameterization.model_names):
            p[i] = values[name]
        return p

    def _point(
        self, x: Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, UKFSettings, VehicleParams | None, np.ndarray | None]:
        """(q, r, settings, vehicle, params) of a point; params None when no model
        parameter is tuned (the filter runs the recorded model)."""
        q, r, settings = self.decode(x)
        if not self.parameterization.model_names:
            return q, r, settings, self.vehicle, None
        return q, r, settings, self.vehicle_at(x), self.params_at(x)

    def __call__(self, x: Sequence[float] | np.ndarray) -> float:
        return self.evaluate(x).cost

    def compile_note(self) -> str | None:
        """What to say before the first evaluation: that it compiles the filter for the
        model, which takes seconds (a large model, minutes) that look like a hang and are
        not the time an evaluation takes; None once this problem has evaluated a point."""
        if self._evaluated:
            return None
        what = f"compiling the filter for model {self.model.name!r} ({self.filter})"
        if self._fs.fast:  # numba keeps the paper's kernel on disk
            return f"{what}, or loading it from an earlier run's cache…"
        return f"{what} (at the first evaluation of each run; it cannot be cached)…"

    def evaluate(self, x: Sequence[float] | np.ndarray) -> Evaluation:
        """Run the filter on every manoeuvre and compute the cost.

        Raises:
            FilterDivergedError: the filter diverged on a manoeuvre.
        """
        q, r, settings, vehicle, params = self._point(x)
        spec, c = self.cost_spec, self.cov_scale
        self._evaluated = True  # the filter compiles now, also for a point that diverges
        if self.workers == 1:
            scores = [
                _score(m, vehicle, self._fs, q, r, settings, spec, self.burn_in, params, c)
                for m in self.manoeuvres
            ]
        else:
            pool = self._get_pool()
            with sigint_blocked():  # workers started by a submit inherit it (see there)
                futures = [
                    pool.submit(
                        _score_chunk, chunk, q, r, settings, spec, self.burn_in, vehicle, params, c
                    )
                    for chunk in self._chunks
                ]
            by_index: dict[int, ManoeuvreScore] = {}
            for chunk, fut in zip(self._chunks, futures):
                by_index.update(zip(chunk, fut.result()))
            scores = [by_index[i] for i in range(len(self.manoeuvres))]
        return self._pool_scores(scores)

    def score_manoeuvres(
        self, x: Sequence[float] | np.ndarray, indices: Sequence[int]
    ) -> list[ManoeuvreScore]:
        """The scores of a point on the manoeuvres ``indices`` (a share of :meth:`evaluate`
        for a distributed engine; pooled by :meth:`_pool_scores` in manoeuvre order, they
        give :meth:`evaluate`'s cost bit for bit)."""
        q, r, settings, vehicle, params = self._point(x)
        fs, spec, c = self._fs, self.cost_spec, self.cov_scale
        return [
            _score(self.manoeuvres[i], vehicle, fs, q, r, settings, spec, self.burn_in, params, c)
            for i in indices
        ]

    def manoeuvre_chunks(self, k: int) -> list[list[int]]:
        """The manoeuvre indices in at most k groups of similar total length."""
        return _balanced_chunks([m.n for m in self.manoeuvres], max(1, k))

    def _pool_scores(self, scores: Sequence[ManoeuvreScore]) -> Evaluation:
        """The cost J (paper Eq. 14–15, a scoring rule's, or a reference-free one) from
        every manoeuvre's score."""
        spec = self.cost_spec
        channels = spec.channels if spec.kind == "nrmse" else ()
        n_total = sum(s.n for s in scores)
        mean_nis = sum(s.nis_sum for s in scores) / n_total
        if spec.kind == "nis":
            cost = nis_cost([np.array([mean_nis])], n_z=self._fs.model.n_measurements)
            pooled: dict[str, float] = {}
        elif spec.kind == "msp":
            cost = multistep_cost([s.msp_sq for s in scores], [s.msp_n for s in scores])
            pooled = {}
        elif spec.kind == "pem":
            cost = innovation_nll(
                [np.array([sum(s.log_det_s_sum for s in scores) / n_total])],
                [np.array([mean_nis])],
                n_z=self._fs.model.n_measurements,
            )
            pooled = {}
        elif spec.kind in SCORING_RULES:
            cost, pooled = scoring_rule_cost(
                {c: [s.score_sum[c] for s in scores] for c in spec.channels},
                [s.n for s in scores],
                spec.weights,
                {c: [s.scale[c] for s in scores] for c in spec.channels}
                if spec.kind == "crps"
                else None,
            )
        else:
            cost, pooled = weighted_cost(
                {c: [s.nrmse[c] for s in scores] for c in channels},
                [s.n for s in scores],
                spec.weights,
                {c: [s.scale[c] for s in scores] for c in channels}
                if spec.normalise == "dataset"
                else None,
            )
        return Evaluation(cost=cost, pooled=pooled, mean_nis=mean_nis, scores=tuple(scores))

    def evaluate_batch(
        self, X: Sequence[Sequence[float]] | np.ndarray
    ) -> list[Evaluation | FilterDivergedError]:
        """Evaluate B points; a point whose filter diverged gets its error, not a raise.

        On the paper's pair (single-track UKF) in this process (``workers == 1``) every
        manoeuvre runs all points that share sigma-point settings and tuned model parameters
        in one call of the vectorised batch kernel (:func:`~kftune.filters.run_ukf_simd`,
        the sets across the CPU's vector lanes, one vehicle for all); otherwise the points
        are evaluated one after another (a point whose model parameters no other point
        shares is a group of one, which runs the sequential kernel). Either way each result
        equals :meth:`evaluate`'s for that point exactly.

        Args:
            X: (B, d) points of ``self.space`` (natural units).

        Returns:
            B entries in the order of X: an :class:`Evaluation`, or the
            :class:`FilterDivergedError` that :meth:`evaluate` would have raised.

        Raises:
            DataError: a channel that cannot be scored (as :meth:`evaluate`).
        """
        points = [np.asarray(x, dtype=float) for x in X]
        # the vector kernel computes neither log det S (pem) nor predictions (msp)
        vector = self.cost_spec.kind in ("nrmse", "nis", *SCORING_RULES) and self.cov_scale == 1.0
        if not (vector and self._fs.fast and self.workers == 1 and len(points) > 1):
            out: list[Evaluation | FilterDivergedError] = []
            for x in points:
                try:
                    out.append(self.evaluate(x))
                except FilterDivergedError as exc:
                    out.append(exc)
            return out
        decoded = [self.decode(x) for x in points]
        self._evaluated = True
        par = self.parameterization
        groups: dict[tuple[UKFSettings, tuple[float, ...]], list[int]] = {}
        for i, (x, (_, _, settings)) in enumerate(zip(points, decoded)):
            key = (settings, tuple(par.model_values(x).values()))
            groups.setdefault(key, []).append(i)
        # results[i][j]: point i's score on manoeuvre j, or its error (first manoeuvre first)
        results: list[list[ManoeuvreScore | FilterDivergedError]] = [[] for _ in points]
        for (settings, _), idx in groups.items():
            q = np.array([decoded[i][0] for i in idx])
            r = np.array([decoded[i][1] for i in idx])
            vehicle = self.vehicle_at(points[idx[0]])
            if vehicle is None:  # fast (the paper's kernel) comes with a vehicle
                raise ValueError("the single-track kernel needs a vehicle")
            for m in self.manoeuvres:
                batch = run_ukf_simd(m.u, m.z, m.dt, vehicle, q, r, settings=settings)
                for b, i in enumerate(idx):
                    try:
                        results[i].append(
                            _score_result(
                                m,
                                batch[b],
                                self.cost_spec,
                                self.burn_in,
                                self._fs,
                                _run_params(self._fs, vehicle, None),
                            )
                        )
                    except FilterDivergedError as exc:
                        results[i].append(exc)
        out = []
        for per_m in results:
            err = next((e for e in per_m if isinstance(e, FilterDivergedError)), None)
            scores = [s for s in per_m if isinstance(s, ManoeuvreScore)]  # all, without err
            out.append(err if err is not None else self._pool_scores(scores))
        return out

    def fingerprint(self) -> dict[str, Any]:
        """What makes two problems the same objective, for a study to check on resume: a
        readable summary and a SHA-256 over the manoeuvre data, vehicle, R, cost,
        parameterisation and burn-in."""
        h = hashlib.sha256()
        for m in self.manoeuvres:
            h.update(m.name.encode())
            for a in self._fingerprinted(m):
                h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        spec = self.cost_spec
        described = {
            "vehicle": None if self.vehicle is None else self.vehicle.to_dict(),
            "r0": self.r0.tolist(),
            "cost": {"kind": spec.kind, "weights": dict(spec.weights), "estimate": spec.estimate},
            "parameterization": self.parameterization.to_dict(),
            "burn_in": self.burn_in,
        }
        if self.cov_scale != 1.0:  # a run as tuned keeps earlier fingerprints
            described["cov_scale"] = self.cov_scale
        if spec.normalise != "manoeuvre":  # the paper's Eq. 15 keeps earlier fingerprints
            described["cost"]["normalise"] = spec.normalise
        file_sha = model_file_sha256(self._fs.spec)
        if not self._fs.fast:  # the paper's pair keeps the fingerprints of earlier studies
            described["model"] = {"name": self._fs.model.name, "filter": self._fs.filter}
            if file_sha is not None:  # an edited model file is another objective
                described["model"]["file_sha256"] = file_sha
        h.update(json.dumps(described, sort_keys=True).encode())
        names = [m.name for m in self.manoeuvres]
        return {
            "summary": f"{len(names)} manoeuvres ({names[0]} … {names[-1]}), "
            f"{self.vehicle.name if self.vehicle is not None else 'no vehicle'}, "
            f"cost {spec.kind}"
            + (f" ({spec.normalise}-normalised)" if spec.normalise != "manoeuvre" else "")
            + (
                f", model parameters {', '.join(self.parameterization.model_names)} tuned"
                if self.parameterization.model_names
                else ""
            )
            + (f", model file sha256 {file_sha[:12]}" if file_sha else ""),
            "sha256": h.hexdigest(),
        }

    def _fingerprinted(self, m: Manoeuvre) -> list[np.ndarray]:
        """The arrays of ``m`` a fingerprint covers: for a model over the single-track
        channels with a reference sideslip, t, u, z and beta_ref, as studies have always
        been fingerprinted; otherwise t, then every channel the objective reads (the
        model's inputs and measurements, the cost's references), each after its name."""
        mod = self._fs.model
        if (
            mod.input_names == ("delta", "ax")
            and mod.measurement_names == SIDESLIP_MEASUREMENTS
            and m.has("beta_ref")
        ):
            return [m.t, m.u, m.z, m.beta_ref]
        names = [*mod.input_names, *mod.measurement_names]
        if self.cost_spec.kind in ("nrmse", *SCORING_RULES):
            names += [f"{c}_ref" for c in self.cost_spec.channels if c not in names]
        out = [m.t]
        for c in names:
            out += [np.frombuffer(c.encode(), dtype=np.uint8), m.channel(c)]
        return out

    def run(self, x: Sequence[float] | np.ndarray, manoeuvre: Manoeuvre) -> RunResult:
        """The filter's full output on one manoeuvre for a point (its model parameters,
        with :attr:`cov_scale`)."""
        q, r, settings, vehicle, params = self._point(x)
        return self._fs.run(
            manoeuvre, vehicle, q, r, settings, params=params, cov_scale=self.cov_scale
        )

    def noise_only(self) -> TuningProblem:
        """This problem with no model parameter tuned: the same manoeuvres, recorded model,
        R, cost and burn-in, the noise (and sigma-point) parameters alone — the first stage
        of a joint tuning, and what ``kftune tune`` without ``--tune-model`` would tune (the
        same fingerprint). Shares nothing mutable: close it after use when ``workers`` > 1
        (it starts its own pool)."""
        other = copy.copy(self)
        other.parameterization = replace(
            self.parameterization, model_bounds={}, model_scales={}, model_start={}
        )
        other._model_index = []
        other._pool = None
        other.cov_scale = 1.0
        return other

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # spawn, not fork: numba's threading layer is not fork-safe once it has run
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker,
                initargs=(
                    self.manoeuvres,
                    self.vehicle,
                    self._fs.spec,
                    self._fs.filter,
                    os.getpid(),
                ),
            )
        return self._pool

    def close(self) -> None:
        """Stop the worker processes (no-op when serial)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def __enter__(self) -> TuningProblem:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_pool"] = None  # a pool does not travel; a copy in another process is serial
        state["workers"] = 1
        fs = state.pop("_fs")  # compiled model functions do not pickle: load them again
        state["_fs_spec"] = (fs.spec, fs.filter)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        spec, filt = state.pop("_fs_spec")
        self.__dict__.update(state)
        self._fs = filter_spec(spec, filt, self.vehicle)


def assess(
    problem: TuningProblem,
    x: Sequence[float] | np.ndarray,
    manoeuvres: Sequence[Manoeuvre],
    channels: Sequence[str] | None = None,
) -> tuple[dict[str, dict[str, float]], dict[str, RunResult]]:
    """KPIs and channel errors of a tuned filter on manoeuvres (for tables and figures).

    Scored like the problem's cost: after its burn-in, with its measured-channel estimate
    (posterior or prior). A diverged manoeuvre gets NaN metrics and ``diverged = 1``.

    Returns:
        (metrics, results): manoeuvre name → metrics, and name → the filter's result.
        For a model with the sideslip output ``beta`` (the single-track models): ``rmse,
        mae, rmse_non, mae_non, n_non`` [deg] (sideslip KPIs, :mod:`kftune.tuning.kpi`)
        and ``rmse_beta`` [deg], NaN on a manoeuvre without the reference ``beta_ref``
        (:func:`missing_references` says which); ``rmse_r`` [deg/s], ``rmse_ay``
        [m/s²]. For any other model: ``rmse_<measurement>`` for each measurement, and
        ``rmse_<output>`` for each output whose reference ``<output>_ref`` the manoeuvre
        has (in the channel's unit). With ``channels`` (measurements or outputs of the
        model), for any model: only ``rmse_<channel>`` for each of them, in the channel's
        unit (:func:`channel_estimate`; a missing reference is an error). And
        ``diverged`` (0/1).
    """
    metrics: dict[str, dict[str, float]] = {}
    results: dict[str, RunResult] = {}
    estimate = problem.cost_spec.estimate
    model = problem.model
    sideslip = (
        channels is None
        and "beta" in problem._outputs()
        and {"r", "ay"} <= set(model.measurement_names)
    )
    for m in manoeuvres:
        res = problem.run(x, m)
        results[m.name] = res
        k0 = first_scored(m, problem.burn_in)
        row: dict[str, float] = {}
        if sideslip:
            if m.has("beta_ref") and not res.diverged:
                beta = model_output(res, "beta")
                row.update(sideslip_kpis(beta[k0:], m.beta_ref[k0:], m.ay[k0:]))
            else:
                row.update({k: math.nan for k in ("rmse", "mae", "rmse_non", "mae_non")})
            row["rmse_beta"] = row["rmse"]
            scored: dict[str, Any] = {"r": np.degrees, "ay": float}  # r in deg/s
        elif channels is not None:
            scored = dict.fromkeys(channels, float)
        else:
            scored = dict.fromkeys(model.measurement_names, float)
            refs = [c for c in problem._outputs() if m.has(f"{c}_ref")]
            scored.update(dict.fromkeys(refs, float))
        for c, unit in scored.items():
            if res.diverged:
                row[f"rmse_{c}"] = math.nan
                continue
            est, ref = channel_estimate(m, res, c, estimate)
            row[f"rmse_{c}"] = float(unit(np.sqrt(np.mean((est[k0:] - ref[k0:]) ** 2))))
        row["diverged"] = float(res.diverged)
        metrics[m.name] = row
    return metrics, results


def missing_references(
    problem: TuningProblem, manoeuvres: Sequence[Manoeuvre]
) -> dict[str, list[str]]:
    """Reference channel → the manoeuvres that lack it, for the KPIs :func:`assess` gives
    (the sideslip KPIs' ``beta_ref``); empty when every reference is there."""
    out: dict[str, list[str]] = {}
    if "beta" in problem._outputs():
        lacking = [m.name for m in manoeuvres if not m.has("beta_ref")]
        if lacking:
            out["beta_ref"] = lacking
    return out


def _balanced_chunks(sizes: Sequence[int], k: int) -> list[list[int]]:
    """Split indices into k groups of similar total size (longest-first greedy)."""
    groups: list[list[int]] = [[] for _ in range(k)]
    loads = [0] * k
    for i in sorted(range(len(sizes)), key=lambda i: -sizes[i]):
        j = loads.index(min(loads))
        groups[j].append(i)
        loads[j] += sizes[i]
    return [sorted(g) for g in groups if g]
