"""One filter run of a tuning point: which filter runs which model (:class:`FilterSpec`), and
what a run gives — the outputs a cost scores, their σ, where it diverged."""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.data.validate import CHANNEL_DIMENSION, SI_UNIT, UNITS
from kftune.errors import ConfigError, ModelChoiceError
from kftune.filters import FilterBatchResult, FilterResult, ModelFilter, UKFSettings, get_filter
from kftune.models import StateSpaceModel, model_names
from kftune.models.user import is_model_file, load_model
from kftune.tuning.cost import (
    SCORING_RULES,
    CostSpec,
)
from kftune.tuning.hookcheck import check_model_file
from kftune.tuning.parameterization import SIDESLIP_MEASUREMENTS
from kftune.vehicle.params import VehicleParams


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


def model_output(res: FilterResult, name: str) -> np.ndarray:
    """(N,) an output of the run's model (:func:`output_names`) from the posterior states,
    e.g. ``"beta"`` [rad] (the sideslip atan2(Vy, Vx) of the single-track models) or a
    state by name (in its unit)."""
    model = res.model
    if name in model.outputs:
        return res.output(name)
    if name in output_names(model):
        return np.asarray(res.state(name), dtype=float)
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


def output_std(res: FilterResult, name: str) -> np.ndarray:
    """(N,) the standard deviation of :func:`model_output` ``name`` from the posterior
    covariance's diagonal: β [rad] by the delta method (:func:`beta_std`), a state's
    √P_ii in its unit.

    Raises:
        KeyError: an output whose σ the filter does not give (:func:`std_outputs`).
    """
    model = res.model
    if name not in std_outputs(model):
        raise KeyError(
            f"model {model.name!r} gives no standard deviation of {name!r}; it gives one of "
            f"{list(std_outputs(model))}"
        )
    if name == "beta" and "beta" in model.outputs:
        return beta_std(res.x, res.P_diag)
    return np.sqrt(np.asarray(res.P_diag[:, model.state_names.index(name)], dtype=float))


def channel_estimate(
    m: Manoeuvre, res: FilterResult, channel: str, estimate: str = "posterior"
) -> tuple[np.ndarray, np.ndarray]:
    """(estimate, reference) of a cost channel over the whole manoeuvre.

    A measurement of the model (yaw rate [rad/s], ay [m/s²], Vx [m/s] for the single-track
    model) against its measured channel, estimated by h(x⁺_k) (``"posterior"``) or by the
    one-step prediction z_k − innovation_k (``"prior"``); any other channel is a derived
    output of the model (β [rad] from the posterior state, or a state that is not
    measured, :func:`output_names`) against the reference channel ``<channel>_ref`` of the
    data (``beta_ref``); see :class:`~kftune.tuning.cost.CostSpec`.
    """
    names = res.model.measurement_names
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


def where_diverged(m: Manoeuvre, res: FilterResult) -> str:
    """``"manoeuvre 'x' at step k (t = … s): <cause>"`` for a run that diverged on ``m``."""
    return (
        f"manoeuvre {m.name!r} at step {res.diverged_step} "
        f"(t = {m.t[res.diverged_step]:.2f} s): {res.diverged_reason}"
    )


def first_scored(m: Manoeuvre, burn_in: float) -> int:
    """Index of the first sample scored after a burn-in of ``burn_in`` seconds."""
    return int(np.searchsorted(m.t - m.t[0], burn_in - 1e-9 * m.dt))


def scaled_covariances(res: FilterResult, c: float) -> FilterResult:
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
    """Which filter runs which model (the generic filters; a model that supplies its own
    loops, as the single-track model does, has them run behind the same interface).

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
    def paper_pair(self) -> bool:
        """Whether this is the paper's model and filter (single-track UKF), whose study
        fingerprints name neither (they keep the fingerprints of studies made before
        other models existed). The one place the tuning asks which model it runs: which
        loop runs a model is the filter's business (:class:`~kftune.models.ModelKernels`)."""
        from kftune.models import SINGLE_TRACK

        return self.model is SINGLE_TRACK and self.filter == "ukf"

    def inputs(self, m: Manoeuvre) -> tuple[np.ndarray | None, np.ndarray]:
        """(u (N, n_u) or None, z (N, m)) of a manoeuvre, by the model's channel names."""
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
        :func:`~kftune.tuning.hookcheck.check_model_file`. Only the hooks the filter calls
        are probed: the UKF's probe leaves the Jacobians alone (compiling the single-track
        model's for a UKF that never calls them took 2 s of a first ``make run``).

        Raises:
            ConfigError: naming the model (its file), the manoeuvre and the hook.
        """
        if not manoeuvres:
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
                self.model.probe(u, z, r, self.params, m.dt, jacobians=self.filter == "ekf")
            except ValueError as exc:
                raise ConfigError(f"model {self.spec}, on manoeuvre {m.name!r}: {exc}") from None

    def run(
        self,
        m: Manoeuvre,
        q: np.ndarray,
        r: np.ndarray,
        settings: UKFSettings,
        *,
        params: np.ndarray | None = None,
        cov_scale: float = 1.0,
    ) -> FilterResult:
        """The filter's run over one manoeuvre.

        Args:
            m: the manoeuvre. q: (n,) and r: (m,) the noise variances. settings: the UKF's
                sigma points.
            params: (n_p,) the model's parameter vector for this run (None: :attr:`params`).
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
        u, z = self.inputs(m)
        res = self.filter_object(settings).run(
            self.model, u, z, m.dt, q, r, params=self.params_or(params)
        )
        return res if c == 1.0 else scaled_covariances(res, c)

    def params_or(self, params: np.ndarray | None) -> np.ndarray:
        """(n_p,) a run's parameter vector: ``params``, or None: :attr:`params`."""
        return self.params if params is None else np.asarray(params, dtype=float)

    @property
    def has_lanes(self) -> bool:
        """Whether the model supplies vector lanes for this filter
        (:class:`~kftune.models.base.ModelKernels`, the single-track UKF's), which
        :meth:`run_lanes` runs B noise settings in at once."""
        own = self.model.own_ukf_kernels()
        return self.filter == "ukf" and own is not None and own.lanes is not None

    def run_lanes(
        self,
        m: Manoeuvre,
        q: np.ndarray,
        r: np.ndarray,
        settings: UKFSettings,
        *,
        params: np.ndarray | None = None,
    ) -> FilterBatchResult:
        """B runs over one manoeuvre, q (B, n) and r (B, m), in the model's vector lanes
        where it has them (:attr:`has_lanes`; else the batch in threads); ``result[b]``
        equals :meth:`run` with (q[b], r[b]). No log det S where the lanes ran."""
        u, z = self.inputs(m)
        return self.filter_object(settings).run_batch(
            self.model, u, z, m.dt, q, r, params=self.params_or(params), lanes=True
        )

    def filter_object(self, settings: UKFSettings) -> ModelFilter:
        """The generic filter (the UKF with these sigma-point settings)."""
        return get_filter("ukf", settings=settings) if self.filter == "ukf" else get_filter("ekf")


def filter_spec(
    model: str | StateSpaceModel, filter: str, vehicle: VehicleParams | None
) -> FilterSpec:
    """A :class:`FilterSpec` from a model name, model file or model, and a filter name; a
    vehicle model's parameters come from ``vehicle``, another model's are its defaults.

    Raises:
        ModelChoiceError: (a ConfigError) unknown model (``key`` "model") or filter
            (``key`` "filter"), a model file that cannot be loaded ("model"), or a model
            that needs a vehicle (the single-track models) without one or whose parameters
            the vehicle lacks (``key`` None: the data, not a setting, lack them).
    """
    try:
        mod = load_model(model)
    except ModelChoiceError:
        raise
    except ConfigError as exc:
        raise ModelChoiceError(str(exc), "model") from None
    if filter not in ("ukf", "ekf"):
        raise ModelChoiceError(f"filter must be 'ukf' or 'ekf', got {filter!r}", "filter")
    if mod.needs_vehicle and vehicle is None:
        raise ModelChoiceError(
            f"model {mod.name!r} needs the vehicle's parameters, but the dataset has no vehicle "
            "(a manifest's 'vehicle' table or preset name); for data of something else choose "
            f"a model that fits them (--model; built-in: {', '.join(model_names())})",
            None,
        )
    spec = model if isinstance(model, str) else mod.name
    if vehicle is not None and mod.pack_params is not None:
        try:
            params = mod.pack_params(vehicle)
        except (TypeError, ValueError, AttributeError) as exc:  # not another vehicle's preset
            raise ModelChoiceError(
                f"model {mod.name!r} cannot read its parameters from the dataset's vehicle: {exc}",
                None,
            ) from None
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
