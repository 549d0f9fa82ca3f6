"""A tuned filter as a deployment needs it, and running it on recordings.

``kftune tune`` writes, under the key ``"deployment"`` of the tuned-parameters file,
everything needed to rebuild the filter elsewhere (:func:`deployment_record`): the model
and filter, the sample time dt [s] (Q is a variance *per step* of dt), the vehicle and
model parameters, Q and R (diagonals, named by state and measurement, with units), the
sigma-point settings, the rule that sets the initial state and covariance, and the
fingerprint of the dataset it was tuned on (:func:`dataset_fingerprint`).
:class:`TunedFilter` reads that back (files written before it existed load with ``dt``,
``vehicle`` and ``dataset`` unknown; :func:`tuned_for` checks the record), :func:`mismatches`
says how recordings differ from what it was tuned for, and :func:`estimate` runs it on a
manoeuvre.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np

from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.errors import DataError, excerpt
from kftune.filters import FilterResult, UKFSettings
from kftune.models import StateSpaceModel, get_model, model_names
from kftune.models.user import model_file_sha256
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem
from kftune.tuning.runs import beta_std, filter_spec, first_scored, model_output
from kftune.vehicle.params import VehicleParams

if TYPE_CHECKING:  # imported where used: consistency imports this module's neighbours
    from kftune.tuning.consistency import ChannelConsistency, ChiSquareMean

#: Relative difference of sample times beyond which a recording is not the tuned one's.
DT_TOLERANCE = 0.01


def dataset_fingerprint(dataset: Dataset) -> dict[str, Any]:
    """What identifies a dataset's data: its name, size, and a SHA-256 over every
    manoeuvre's name, split, kind and channels (names and float64 values, in order)."""
    h = hashlib.sha256()
    for m in dataset.manoeuvres:
        h.update(f"{m.name}\0{m.split}\0{m.kind}\0".encode())
        h.update(np.ascontiguousarray(m.t, dtype=np.float64).tobytes())
        for name in m.channel_names:
            h.update(name.encode() + b"\0")
            h.update(np.ascontiguousarray(m.channel(name), dtype=np.float64).tobytes())
    return {
        "name": dataset.name,
        "n_manoeuvres": len(dataset.manoeuvres),
        "n_samples": int(sum(m.n for m in dataset.manoeuvres)),
        "sha256": h.hexdigest(),
    }


def _squared(unit: str) -> str:
    """``"m/s"`` → ``"(m/s)^2"``, ``"rad"`` → ``"rad^2"``, ``""`` → ``""``."""
    if not unit or unit == "-":
        return unit
    return f"({unit})^2" if any(c in unit for c in "/*^ ") else f"{unit}^2"


def _initial_rule(model: StateSpaceModel) -> str:
    """How x0 and P0 are set: the first line of the model's prior rule's docstring, or,
    for a rule without one, its name and where it is defined."""
    rule = model.initial_state
    if rule is None:
        return "none: the caller gives x0 and P0"
    doc = (getattr(rule, "__doc__", None) or "").strip()
    if doc:
        return doc.splitlines()[0].strip()
    name = getattr(rule, "__qualname__", type(rule).__name__)
    return (
        f"the model's initial_state rule {name}(z0, r, p) (model {model.name!r}; undocumented): "
        "x0 and P0 from the first measurement z0 and the measurement variances r"
    )


def deployment_record(problem: TuningProblem, x: Any, dataset: Dataset) -> dict[str, Any]:
    """The ``"deployment"`` part of a tuned-parameters file for the point ``x`` of
    ``problem`` tuned on ``dataset`` (strict-JSON values)."""
    q, r, settings = problem.decode(x)
    model = problem.model
    vehicle = problem.vehicle_at(x)  # the tuned model parameters: what runs
    file_sha = model_file_sha256(problem.model_spec)
    return {
        "model": problem.model_spec,
        **({"model_sha256": file_sha} if file_sha else {}),
        "filter": problem.filter,
        "dt": float(dataset.dt),
        "vehicle": None if vehicle is None else vehicle.to_dict(),
        "model_params": [
            {"name": n, "unit": u, "value": float(v)}
            for n, u, v in zip(model.param_names, model.param_units, problem.params_at(x).tolist())
        ],
        "states": [{"name": n, "unit": u} for n, u in zip(model.state_names, model.state_units)],
        "inputs": [{"name": n, "unit": u} for n, u in zip(model.input_names, model.input_units)],
        "measurements": [
            {"name": n, "unit": u} for n, u in zip(model.measurement_names, model.measurement_units)
        ],
        "Q": [
            {"name": n, "variance": float(v), "unit": _squared(u)}
            for n, u, v in zip(model.state_names, model.state_units, q.tolist())
        ],
        "R": [
            {"name": n, "variance": float(v), "unit": _squared(u)}
            for n, u, v in zip(model.measurement_names, model.measurement_units, r.tolist())
        ],
        "sigma_points": None
        if problem.filter != "ukf"
        else {
            "alpha": settings.alpha,
            "beta": settings.beta,
            "kappa": settings.kappa,
            "convention": "scaled sigma points (Van der Merwe; FilterPy MerweScaledSigmaPoints)",
        },
        "initial_state": _initial_rule(model),
        "dataset": dataset_fingerprint(dataset),
    }


def model_params_record(problem: TuningProblem, x: Any) -> dict[str, dict[str, Any]]:
    """The ``"model_params"`` of a tuned-parameters file: for each tuned model parameter,
    name → ``{"value", "start", "low", "high", "scale", "unit"}`` (the tuned value, the
    recorded one it started from, its box and scale); empty when none was tuned."""
    par = problem.parameterization
    values = par.model_values(x)
    units = dict(zip(problem.model.param_names, problem.model.param_units))
    return {
        n: {
            "value": values[n],
            "start": par.model_start[n],
            "low": par.model_bounds[n][0],
            "high": par.model_bounds[n][1],
            "scale": par.model_scales[n],
            "unit": units[n],
        }
        for n in par.model_names
    }


def tuned_model_params(
    doc: Mapping[str, Any], source: str, param_names: Sequence[str] | None = None
) -> dict[str, float]:
    """The tuned model parameters of a tuned-parameters file, name → value (``model_params``;
    empty for a file without it: noise only, or an older kftune). The one check of the key:
    every reader of tuned files goes through it (:func:`kftune.cli.evaluate.read_tuned`).
    ``param_names``: the model's parameters (each name must be one of them); by default
    those of the file's ``model`` where it is a registered one (a model file's are known
    only once it is loaded).

    Raises:
        DataError: naming ``source`` and the key, when ``model_params`` is not an object of
            ``{value, start, low, high, scale}`` objects with finite numbers, low ≤ start,
            value ≤ high, scale log10 or linear, a box the search could not have had
            (low ≥ high, a log10 scale over low ≤ 0: :class:`NoiseParameterization`'s
            rules), or a name not among ``param_names``.
    """
    record = doc.get("model_params", {})
    if not isinstance(record, Mapping):
        raise DataError(
            f"'model_params' must be an object (name -> its record), got {record!r:.60}",
            file=source,
        )
    model = doc.get("model", "single-track")
    if param_names is None and isinstance(model, str) and model in model_names():
        param_names = get_model(model).param_names
    out: dict[str, float] = {}
    for name, entry in record.items():
        where = f"'model_params.{name}'"
        nums: dict[str, Any] = (
            {k: entry.get(k) for k in ("value", "start", "low", "high")}
            if isinstance(entry, Mapping)
            else {}
        )
        if not nums or not all(finite_number(v) for v in nums.values()):
            raise DataError(
                f"{where} must be an object with finite numbers value, start, low and high, "
                f"got {entry!r:.80}",
                file=source,
            )
        if not (
            nums["low"] <= nums["start"] <= nums["high"]
            and nums["low"] <= nums["value"] <= nums["high"]
        ):
            raise DataError(
                f"{where}: value {nums['value']!r} and start {nums['start']!r} must lie in "
                f"[low, high] = [{nums['low']!r}, {nums['high']!r}]",
                file=source,
            )
        if entry.get("scale", "log10") not in ("log10", "linear"):
            raise DataError(f"{where}: scale must be log10 or linear", file=source)
        if param_names is not None and name not in param_names:
            raise DataError(
                f"{where}: the model has no parameter {excerpt(name, 40)}; its parameters: "
                f"{', '.join(param_names)}",
                file=source,
            )
        out[str(name)] = float(nums["value"])
    try:  # each box as the search took it: the one rule of bounds and scales
        _parameterization_of(record)
    except ValueError as exc:
        raise DataError(f"'model_params': {exc}", file=source) from None
    return out


def _parameterization_of(
    record: Mapping[str, Any], settings: UKFSettings | None = None, model: Any = None
) -> NoiseParameterization:
    """The search's parameterisation from a ``model_params`` record (R's diagonal tuned: a
    tuned file records R whole); ``model`` names the states and measurements."""
    extra: dict[str, Any] = {}
    if model is not None:
        extra = {"states": model.state_names, "measurements": model.measurement_names}
    return NoiseParameterization(
        tune_r="diag",
        default_settings=settings or UKFSettings(),
        model_bounds={n: (e["low"], e["high"]) for n, e in record.items()},
        model_scales={n: e["scale"] for n, e in record.items() if "scale" in e},
        model_start={n: e["start"] for n, e in record.items()},
        **extra,
    )


def parameterization_of(
    doc: Mapping[str, Any], source: str, model: StateSpaceModel, settings: UKFSettings
) -> NoiseParameterization:
    """The parameterisation a tuned-parameters file was searched in, for ``model``: Q's and
    R's diagonals and the tuned model parameters with their recorded boxes, scales (absent:
    :class:`NoiseParameterization`'s rule, log10 for a positive box) and start values. Its
    point is ``[*q, *r_factors, *model_params values]``.

    Raises:
        DataError: naming ``source`` and the key, for a damaged ``model_params``
            (:func:`tuned_model_params`, the names checked against ``model``).
    """
    tuned_model_params(doc, source, model.param_names)
    return _parameterization_of(doc.get("model_params") or {}, settings, model)


@dataclass(frozen=True)
class TunedFilter:
    """A tuned filter read from a tuned-parameters file.

    Attributes:
        model, filter: the model spec (a registered name or a model file) and ``"ukf"`` /
            ``"ekf"``.
        q, r: (n,), (m,) the diagonals of Q (per step of ``dt``) and R, in the squared
            units of the states and measurements.
        settings: the UKF's sigma-point settings.
        dt: [s] the sample time it was tuned at (None: an old file that does not say).
        vehicle: the vehicle it was tuned for (None: an old file that does not say).
        dataset: the fingerprint of the dataset it was tuned on (None: not recorded).
        burn_in: [s] left out of the KPIs at each manoeuvre's start.
        source: the file it came from (for messages).
        document: the whole file.
        cov_scale: the calibration factor c its runs apply (covariances reported c times
            larger, :func:`calibration_factor`), 1 for an uncalibrated one.
        model_params: name → the tuned value of each model parameter tuned with the noise
            (:func:`tuned_model_params`; ``vehicle`` already holds them).
    """

    model: str
    filter: str
    q: np.ndarray
    r: np.ndarray
    settings: UKFSettings
    dt: float | None
    vehicle: VehicleParams | None
    dataset: Mapping[str, Any] | None
    burn_in: float
    source: str
    document: Mapping[str, Any]
    cov_scale: float = 1.0
    model_params: Mapping[str, float] = field(default_factory=dict)

    def params_of(self, model: StateSpaceModel, recorded: np.ndarray) -> np.ndarray:
        """(n_p,) the parameter vector the tuned filter runs: ``recorded`` (the model's
        parameters of the recordings or defaults) with the tuned values in their places.

        Raises:
            DataError: naming the file and the key, for a tuned name ``model`` lacks.
        """
        tuned_model_params(self.document, self.source, model.param_names)
        p = np.array(recorded, dtype=float)
        for name, value in self.model_params.items():
            p[model.param_names.index(name)] = value
        return p

    @classmethod
    def from_document(
        cls, doc: Mapping[str, Any], source: str, *, calibrated: bool = True
    ) -> TunedFilter:
        """From a tuned-parameters file already read and checked by
        :func:`kftune.cli.evaluate.read_tuned` (``q``, ``ukf``, ``params`` are valid);
        ``calibrated``: apply the file's calibration factor (False: the filter as tuned).

        Raises:
            DataError: naming ``source``, when ``r`` is missing or not one positive number
                per measurement, or the ``deployment`` part is damaged
                (:func:`tuned_for`).
        """
        r = doc.get("r")
        if not (
            isinstance(r, list)
            and r
            and all(finite_number(v) and v > 0 for v in r)
            and len(r) == len(doc.get("measurements", r))
        ):
            raise DataError(
                f"'r' must be one positive variance per measurement, got {r!r:.80}", file=source
            )
        dt, vehicle = tuned_for(doc, source)
        return cls(
            model=str(doc.get("model", "single-track")),
            filter=str(doc.get("filter", "ukf")),
            q=np.array(doc["q"], dtype=float),
            r=np.array(r, dtype=float),
            settings=UKFSettings(**doc["ukf"]),
            dt=dt,
            vehicle=vehicle,
            dataset=(doc.get("deployment") or {}).get("dataset"),
            burn_in=float(doc.get("burn_in", 0.0)),
            source=source,
            document=doc,
            cov_scale=calibration_factor(doc, source) if calibrated else 1.0,
            model_params=tuned_model_params(doc, source),
        )


def tuned_for(doc: Mapping[str, Any], source: str) -> tuple[float | None, VehicleParams | None]:
    """(dt [s], vehicle) that a tuned-parameters file records under ``deployment`` — what
    the filter was tuned for — each None where the file does not say (an older file, or a
    model without a vehicle). The one check of these keys: every reader of tuned files
    (``evaluate``, ``estimate``, ``export``) goes through it.

    A record that is there must be whole: ``dt`` a number, ``dataset`` an object, and
    ``vehicle`` null only for a registered model that needs none (a model file's needs
    are not known here).

    Raises:
        DataError: naming ``source`` and the key, when ``deployment`` is not an object,
            ``deployment.dt`` is not a positive finite number, ``deployment.dataset`` is
            not an object, or ``deployment.vehicle`` is not a vehicle (unknown keys,
            implausible values; null for a model that needs one).
    """
    dep = doc.get("deployment")
    if dep is None:
        return None, None
    if not isinstance(dep, Mapping):
        raise DataError("'deployment' must be an object", file=source)
    dt = dep.get("dt")
    if "dt" in dep and not (finite_number(dt) and dt > 0):
        raise DataError(
            f"'deployment.dt' must be a positive number [s], got {dt!r:.40}", file=source
        )
    if "dataset" in dep and not isinstance(dep["dataset"], Mapping):
        raise DataError(
            f"'deployment.dataset' must be an object (the dataset's fingerprint), got "
            f"{dep['dataset']!r:.40}",
            file=source,
        )
    vehicle = dep.get("vehicle")
    model = doc.get("model", "single-track")
    if (
        "vehicle" in dep
        and vehicle is None
        and model in model_names()
        and get_model(model).needs_vehicle
    ):
        raise DataError(
            f"'deployment.vehicle' is null, but model {model!r} needs a vehicle", file=source
        )
    if vehicle is not None:
        if not isinstance(vehicle, Mapping):
            raise DataError(
                f"'deployment.vehicle' must be an object of vehicle parameters, got "
                f"{vehicle!r:.40}",
                file=source,
            )
        try:
            vehicle = VehicleParams.from_dict(dict(vehicle))
        except (TypeError, ValueError) as exc:
            raise DataError(f"'deployment.vehicle': {exc}", file=source) from None
    return None if dt is None else float(dt), vehicle


#: How a calibrated filter is deployed, in the record itself (``deployment.calibration``).
CALIBRATION_CONVENTION = (
    "the filter runs with Q, R and the initial-state rule as recorded (the tuned values); "
    "every covariance it reports is multiplied by factor: P (its standard deviations by "
    "sqrt(factor)) and the innovation covariance S (for the NIS and gating). For a Kalman "
    "filter or an EKF this equals running with factor*Q, factor*R and factor*P0; a UKF run "
    "so would spread its sigma points and move its estimate, so do not"
)


def calibration_record(factor: float) -> dict[str, Any]:
    """The ``"calibration"`` of a deployment record: the factor c that the reported
    covariances are multiplied by, and :data:`CALIBRATION_CONVENTION` saying so (Q and R,
    beside it, stay the tuned values: what runs)."""
    return {
        "factor": float(factor),
        "applies_to": "reported covariances: P and S",
        "convention": CALIBRATION_CONVENTION,
    }


def calibration_factor(doc: Mapping[str, Any], source: str) -> float:
    """The calibration factor c a tuned-parameters file records (``calibration.factor``,
    the same as ``deployment.calibration.factor``), 1.0 when it records none (null, or a
    file of an older kftune). The one check of these keys: every reader of tuned files goes
    through it (:func:`kftune.cli.evaluate.read_tuned`).

    Raises:
        DataError: naming ``source`` and the key, when ``calibration`` is not null or an
            object whose ``factor`` is a positive finite number, or the deployment record's
            factor disagrees with it.
    """
    cal = doc.get("calibration")
    dep = doc.get("deployment")
    dep_cal = dep.get("calibration") if isinstance(dep, Mapping) else None
    if cal is None:
        if dep_cal is not None:
            raise DataError(
                "'deployment.calibration' is set but 'calibration' is null: edited in one "
                "place only? make both null (uncalibrated) or tune again",
                file=source,
            )
        return 1.0
    factor = cal.get("factor") if isinstance(cal, Mapping) else None
    if not (finite_number(factor) and factor > 0):
        raise DataError(
            f"'calibration' must be null or an object whose 'factor' is a positive number, "
            f"got {cal!r:.60}",
            file=source,
        )
    if not isinstance(dep, Mapping) or "Q" not in dep:
        return float(factor)
    if not isinstance(dep_cal, Mapping):
        raise DataError(
            "'calibration' is set but 'deployment.calibration' is not an object: edited in "
            "one place only? make both null (uncalibrated) or tune again",
            file=source,
        )
    got = dep_cal.get("factor")
    if not (finite_number(got) and math.isclose(got, factor, rel_tol=1e-9)):
        raise DataError(
            f"'calibration.factor' ({factor!r}) and 'deployment.calibration.factor' "
            f"({got!r:.40}) disagree: edited in one place only? make them equal or tune again",
            file=source,
        )
    return float(factor)


def unrecorded(doc: Mapping[str, Any]) -> list[str]:
    """What a deployment needs that a tuned-parameters file (an older one) does not record:
    some of ``dt``, ``vehicle``, ``dataset``."""
    dep = doc.get("deployment") or {}
    # (an explicit null vehicle is a model without one, not an old file: tuned_for)
    return [k for k in ("dt", "vehicle", "dataset") if k not in dep]


def mismatches(
    dt: float | None,
    vehicle: VehicleParams | None,
    dataset: Dataset,
    manoeuvres: Sequence[Manoeuvre],
    tuned: Sequence[str] = (),
) -> list[str]:
    """How recordings differ from what a filter was tuned for (``dt``, ``vehicle`` from
    :func:`tuned_for`; None: not recorded, not checked): a sample time off by more than
    :data:`DT_TOLERANCE` (each manoeuvre named), other vehicle parameters than those
    ``tuned`` with the noise (which are expected to differ from the recorded ones)."""
    out = []
    if dt is not None:
        for m in manoeuvres:
            if abs(m.dt - dt) > DT_TOLERANCE * dt:
                out.append(
                    f"manoeuvre {m.name!r} is sampled every {m.dt:.6g} s, the filter was "
                    f"tuned at dt = {dt:.6g} s (Q is a variance per step)"
                )
    if vehicle is not None and dataset.vehicle is None:
        out.append(
            f"the filter was tuned for vehicle {vehicle.name!r}; the recording names no vehicle"
        )
    elif vehicle is not None and dataset.vehicle is not None:
        differ = [
            d for d in vehicle_differences(vehicle, dataset.vehicle) if d.split()[0] not in tuned
        ]
        if differ:
            out.append(
                f"the recording's vehicle {dataset.vehicle.name!r} differs from the tuned "
                f"one {vehicle.name!r} in {', '.join(differ[:3])}"
                + (f" and {len(differ) - 3} more parameters" if len(differ) > 3 else "")
            )
    return out


def model_file_changed(doc: Mapping[str, Any]) -> str | None:
    """How the model file of a tuned-parameters file differs from the one it was tuned with
    (the SHA-256 ``deployment.model_sha256`` records), in words; None when it is the same,
    or when either is unknown (a built-in model, an older file, an unreadable one)."""
    recorded = (doc.get("deployment") or {}).get("model_sha256")
    now = model_file_sha256(doc.get("model", ""))
    if not isinstance(recorded, str) or now is None or now == recorded:
        return None
    return (
        f"the model file {doc['model']} has changed since the filter was tuned (sha256 "
        f"{recorded[:12]}… then, {now[:12]}… now)"
    )


def finite_number(value: Any) -> TypeGuard[float]:
    """A JSON number (not a boolean) that is finite as a float (a huge integer is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def vehicle_differences(a: VehicleParams, b: VehicleParams, rtol: float = 1e-9) -> list[str]:
    """``["m: 1500 vs 1600", …]``: the parameters (not the name) in which two vehicles differ."""
    da, db = a.to_dict(), b.to_dict()
    out = []
    for key in da:
        if key == "name":
            continue
        va, vb = da[key], db[key]
        if va is None or vb is None:
            same = va is vb
        else:
            same = math.isclose(va, vb, rel_tol=rtol, abs_tol=0.0)
        if not same:
            out.append(f"{key} {va!r} vs {vb!r}")
    return out


@dataclass(frozen=True)
class Estimates:
    """One manoeuvre's estimates as named columns of equal length N (SI units).

    Attributes:
        columns: name → (N,) values: ``t`` [s]; each state and its standard deviation
            ``<state>_std`` from the diagonal of P; each model output (``beta`` [rad]) and,
            for β, ``beta_std`` (delta method, :func:`beta_std`); ``innovation_<measurement>``
            (z − ẑ⁻); ``nis`` [-]; and ``beta_ref`` when the recording has a reference.
        units: name → unit.
        result: the filter's run.
    """

    columns: dict[str, np.ndarray]
    units: dict[str, str]
    result: FilterResult


def reference(m: Manoeuvre, channel: str = "beta_ref") -> np.ndarray | None:
    """(N,) a reference channel of ``m``, or None when the recording has none (or it holds
    no finite value)."""
    try:
        ref = m.channel(channel)
    except (KeyError, AttributeError):
        return None
    if ref is None:
        return None
    ref = np.asarray(ref, dtype=float)
    return ref if ref.shape == (m.n,) and np.isfinite(ref).any() else None


def estimate(
    tuned: TunedFilter, m: Manoeuvre, vehicle: VehicleParams | None, *, probe: bool = True
) -> Estimates:
    """Run ``tuned`` (its Q and R, not re-estimated, with its calibration factor
    ``cov_scale``) over ``m`` with ``vehicle``'s parameters (None: a model without one), at
    the manoeuvre's own sample
    time; ``probe``: run the model's hooks
    first (:meth:`~kftune.tuning.runs.FilterSpec.probe`; False: the caller did, on
    every manoeuvre at once)."""
    fs = filter_spec(tuned.model, tuned.filter, vehicle)
    model = fs.model
    params = tuned.params_of(model, fs.params)  # a vehicle model's: already in vehicle
    if probe:
        fs.probe([m], tuned.r, tuned.q, tuned.settings)
    res = fs.run(m, tuned.q, tuned.r, tuned.settings, params=params, cov_scale=tuned.cov_scale)
    return estimates_of(model, res, m)


def estimates_of(model: StateSpaceModel, res: FilterResult, m: Manoeuvre) -> Estimates:
    """The named columns of a run ``res`` of a filter of ``model`` over ``m``
    (:class:`Estimates`): what ``estimate`` writes and ``evaluate`` measures."""
    cols: dict[str, np.ndarray] = {"t": m.t}
    units: dict[str, str] = {"t": "s"}
    for i, (name, unit) in enumerate(zip(model.state_names, model.state_units)):
        cols[name] = res.x[:, i]
        units[name] = unit
    for i, (name, unit) in enumerate(zip(model.state_names, model.state_units)):
        cols[f"{name}_std"] = np.sqrt(res.P_diag[:, i])
        units[f"{name}_std"] = unit
    if "beta" in model.outputs:
        cols["beta"] = model_output(res, "beta")
        units["beta"] = "rad"
        if model.state_names[:2] == ("vx", "vy"):
            cols["beta_std"] = beta_std(res.x, res.P_diag)
            units["beta_std"] = "rad"
    for name in model.outputs:
        if name not in cols:
            cols[name] = model_output(res, name)
            units[name] = ""
    for i, (name, unit) in enumerate(zip(model.measurement_names, model.measurement_units)):
        cols[f"innovation_{name}"] = res.innovation[:, i]
        units[f"innovation_{name}"] = unit
    cols["nis"] = res.nis
    units["nis"] = "-"
    ref = reference(m)
    if ref is not None:
        cols["beta_ref"] = ref
        units["beta_ref"] = "rad"
    for name in (*model.state_names, *model.outputs):  # the references a model's user has
        if name != "beta" and f"{name}_ref" not in cols:
            other = reference(m, f"{name}_ref")
            if other is not None:
                cols[f"{name}_ref"] = other
                units[f"{name}_ref"] = units.get(name, "")
    return Estimates(columns=cols, units=units, result=res)


#: Nominal probabilities of the intervals ±z·σ whose observed coverage a reliability
#: figure plots (nominal against observed), pooled over manoeuvres.
RELIABILITY_LEVELS: tuple[float, ...] = (
    0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.6827, 0.7, 0.8, 0.9, 0.95, 0.99
)  # fmt: skip


def consistency_docs(
    problem: TuningProblem,
    manoeuvres: Sequence[Manoeuvre],
    results: Mapping[str, FilterResult],
    levels: Sequence[float] = (),
) -> tuple[dict[str, dict[str, Any] | None], dict[str, Any] | None]:
    """Whether the filter's standard deviations can be trusted on ``manoeuvres``, from its
    runs ``results`` (name → run), after the problem's burn-in.

    Returns:
        (manoeuvre name → its consistency (:func:`kftune.tuning.consistency.as_doc`;
        None where the filter diverged); the same pooled sample by sample over all of them,
        None when it diverged on any, as the KPI averages). With ``levels`` (nominal
        probabilities p), the pooled document also holds ``"reliability": {"levels": [p…],
        "coverage": {channel: [observed share of |err| ≤ z_p·σ for each p]}}``, the points
        of a reliability figure.
    """
    model = problem.model
    runs = {
        m.name: (m, None if results[m.name].diverged else estimates_of(model, results[m.name], m))
        for m in manoeuvres
    }
    return consistency_of(model, problem.burn_in, runs, levels)


def consistency_of(
    model: StateSpaceModel,
    burn_in: float,
    estimates: Mapping[str, tuple[Manoeuvre, Estimates | None]],
    levels: Sequence[float] = (),
) -> tuple[dict[str, dict[str, Any] | None], dict[str, Any] | None]:
    """:func:`consistency_docs` from the estimates of ``model`` (name → (manoeuvre, its
    :class:`Estimates`, None where the filter diverged)), after ``burn_in`` [s]: what
    ``evaluate``, ``compare``, ``tune`` and ``estimate`` report, counted in one place."""
    from kftune.tuning.consistency import as_doc, covered, of_columns, pool_runs, z_of

    runs: dict[str, tuple[dict[str, ChannelConsistency], ChiSquareMean | None]] = {}
    curves: dict[str, list[tuple[int, int]]] = {}  # channel → (covered, counted) per level
    zs = [z_of(p) for p in levels]
    for name, (m, est) in estimates.items():
        if est is None:
            continue
        columns = est.columns
        first = first_scored(m, burn_in)
        runs[name] = of_columns(columns, model.n_measurements, first)
        for c in runs[m.name][0]:  # the channels measured: with a std and a reference
            err = (columns[c] - columns[f"{c}_ref"])[first:]
            counts = [covered(err, columns[f"{c}_std"][first:], z) for z in zs]
            was = curves.get(c, [(0, 0)] * len(zs))
            curves[c] = [(a + k, b + n) for (a, b), (k, n) in zip(was, counts)]
    each = {name: as_doc(*runs[name]) if name in runs else None for name in estimates}
    if len(runs) != len(estimates):
        return each, None
    pooled = as_doc(*pool_runs(runs.values()))
    if levels:
        pooled["reliability"] = {
            "levels": list(levels),
            "coverage": {c: [k / n if n else None for k, n in cs] for c, cs in curves.items()},
        }
    return each, pooled


def referenced(est: Estimates) -> list[str]:
    """The estimated channels (states and outputs other than β) with a reference column
    ``<name>_ref`` in ``est``, in column order."""
    return [c for c in est.columns if c != "beta" and f"{c}_ref" in est.columns]
