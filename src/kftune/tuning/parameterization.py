"""What a tuning searches: the noise (and model) parameters and how a point maps onto the
filter (Q diagonal, R factors, sigma-point settings, model parameters)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from kftune.errors import ConfigError
from kftune.filters import UKFSettings
from kftune.models import StateSpaceModel
from kftune.space import Param, Space

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


#: Vehicle fields that are no parameters of the single-track models, and why.
NOT_IN_MODEL = {
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
            why = f" ({NOT_IN_MODEL[name]})" if name in NOT_IN_MODEL else ""
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
