"""``kftune evaluate``: sideslip KPIs and the cost of given filter parameters on a dataset.

The parameters come from a file written by ``kftune tune`` (``--params tuned.json``), from
the command line (``--q QVX QVY QR``), or are the manual-tuning rule of thumb
(``--manual``). With ``--params`` the filter is the file's, Q and R as tuned (what
``kftune estimate`` runs and ``kftune export`` deploys); otherwise R is the evaluated
dataset's own, from its sensor statistics. Parameters tuned on another dataset than the one
scored are refused when no dataset is named (the bundled one would be scored by default)
and scored with a warning when one is. As ``kftune estimate`` does, it refuses (exit 3)
manoeuvres whose sample time differs from the one the file was tuned at by more than 1 %
(Q is a variance per step) or a vehicle other than the tuned one; --force scores them
anyway, with a warning, on the tuned vehicle. A tuned file's filter runs with its
calibration factor c (its covariances reported c times larger, fitted by ``tune`` so that
its σ matches its errors, its estimate unchanged; --json: "cov_scale"); --no-calibration
runs it as tuned.

--split picks the manoeuvres: test (the default), train or all. Without --split, a dataset
that has no test manoeuvres is scored on all of them, with a warning that these are the
training ones (not held-out evidence); an explicit --split test is then refused.

The sideslip KPIs, in degrees: RMSE, MAE — the maximum absolute error, as in the paper,
not the mean — and both again over the samples with |ay| ≥ 4 m/s² (RMSE_NON, MAE_NON).
The filter's yaw rate and ay (for another model: each measurement) are scored against the
measured channel, noise included — no reference: a filter that copies the sensor scores
best there. Their columns say "vs meas" and their --json keys name it with the unit:
"rmse_r_vs_measured_degps" [deg/s], "rmse_ay_vs_measured_mps2" [m/s²] (another model:
"rmse_<measurement>_vs_measured", in the unit "units" gives). The former keys "rmse_r" and
"rmse_ay" (another model: "rmse_<measurement>") still hold the same numbers for one
release.

And whether the filter's standard deviations can be trusted (consistency, per manoeuvre and
pooled over the split): for each channel with a standard deviation and a reference (β, a
state with <state>_ref), the share of samples inside its ±1σ and ±1.96σ intervals (68.3 %
and 95 % when consistent) and the mean NEES (1 when consistent), and the mean NIS of the m
measurements (m), each mean with its 95 % χ² band; --json: "consistency".

Exit code 1 (after the KPI table, which shows "–" there) when the filter diverged or ran
away on any manoeuvre; the message names each, with the step and the cause.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kftune.cli._common import (
    NON_NEGATIVE_FLOAT,
    add_command,
    add_common,
    cost_spec,
    emit_json,
    filter_spec_of,
    load_config,
    model_file_from,
    parameterization,
    pick,
    pick_tuned,
    split_model_file,
)
from kftune.cli.exit_codes import EXIT_FAILURE, EXIT_OK
from kftune.cli.tune import TUNED_FORMAT
from kftune.errors import (
    ConfigError,
    DataError,
    DataWarning,
    MissingChannelError,
    UsageError,
    excerpt,
)
from kftune.tuning.kpi import KPI_NAMES

if TYPE_CHECKING:
    import numpy as np

    from kftune.data import Dataset, Manoeuvre
    from kftune.tuning.problem import TuningProblem
    from kftune.vehicle.params import VehicleParams


def register(subparsers: Any) -> None:
    """Add ``evaluate``."""
    p = add_command(
        subparsers,
        "evaluate",
        "KPIs and cost of given filter parameters on a dataset split",
        __doc__,
    )
    add_common(p, tuning=False)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--params", "-p", type=Path, help="tuned-parameters file from 'kftune tune'")
    src.add_argument(
        "--q",
        nargs="+",
        type=NON_NEGATIVE_FLOAT,
        metavar="Q",
        help="process-noise variances, one per state of the model (single-track: Vx, Vy, r "
        "[(m/s)², (m/s)², (rad/s)²])",
    )
    src.add_argument("--manual", action="store_true", help="the manual-tuning rule of thumb")
    p.add_argument(
        "--split",
        choices=("train", "test", "all"),
        help="which manoeuvres (default test; all when the dataset has no test manoeuvres)",
    )
    add_force(p, "score the --params file's filter")
    add_no_calibration(p)
    p.set_defaults(func=run)


def add_force(parser: argparse.ArgumentParser, what: str) -> None:
    """``--force`` of the commands that run a tuned file's filter (``evaluate``,
    ``estimate``; see :func:`check_recordings`); ``what`` it does, for the help."""
    parser.add_argument(
        "--force",
        action="store_true",
        help=f"{what} even when the recordings' sample time or vehicle differ from the tuned "
        "ones (warns; the tuned vehicle is used)",
    )


def add_no_calibration(parser: argparse.ArgumentParser) -> None:
    """``--no-calibration`` of the commands that run a tuned file's filter (``evaluate``,
    ``estimate``): by default they apply the file's calibration factor c (covariances
    reported c times larger, :mod:`kftune.tuning.calibrate`), as ``export`` deploys it."""
    parser.add_argument(
        "--no-calibration",
        dest="calibrated",
        action="store_false",
        help="run the --params file's filter without its calibration factor c (by default "
        "its covariances P and S are reported c times larger, which makes its σ match its "
        "errors; the estimate is the same)",
    )


#: Relative tolerance between the top-level Q and R and the deployment record's: written
#: from the same floats, so anything beyond rounding by an editor or a tool is an edit.
AGREE_RTOL = 1e-9


def _check_deployment(doc: dict[str, Any], path: Path) -> None:
    """``q``/``r`` (what ``evaluate`` and ``estimate`` run) and ``deployment.Q``/``R`` (what
    ``export`` writes) must be the same filter: a file edited in one place only would
    deploy another filter than the one evaluated."""
    dep = doc.get("deployment")
    if not isinstance(dep, dict):
        return
    for key, top in (("Q", "q"), ("R", "r")):
        values, entries = doc.get(top), dep.get(key)
        if entries is None or not (isinstance(values, list) and all(map(_finite, values))):
            continue  # no record (an old file), or an 'r' that TunedFilter refuses itself
        try:
            names = [str(e["name"]) for e in entries]
            recorded = [float(e["variance"]) for e in entries]
        except (TypeError, KeyError, ValueError):
            raise DataError(
                f"'deployment.{key}' must be a list of {{name, variance, unit}} objects",
                file=str(path),
            ) from None
        if len(recorded) != len(values):
            raise DataError(
                f"'{top}' holds {len(values)} values, 'deployment.{key}' {len(recorded)}",
                file=str(path),
            )
        for name, a, b in zip(names, values, recorded):
            if not math.isclose(a, b, rel_tol=AGREE_RTOL):
                raise DataError(
                    f"'{top}' and 'deployment.{key}' disagree for {name!r} ({a!r} against "
                    f"{b!r}): edited in one place only? evaluate and estimate run '{top}', "
                    "export writes the deployment record; make them equal or tune again",
                    file=str(path),
                )


def _locate_model(doc: dict[str, Any], path: Path) -> None:
    """The model file the tuned file ``path`` records (``model``) by a relative path is
    looked for from the tuned file's folder (:func:`~kftune.cli._common.model_file_for`),
    and, for files written before that, from the working directory."""
    spec = doc.get("model")
    if not isinstance(spec, str):
        return
    recorded = split_model_file(spec)
    if recorded is None:  # a built-in model (the deployment record keeps what was written)
        return
    there = model_file_from(spec, path.parent)
    if Path(there.removesuffix(recorded[1])).expanduser().is_file() or not recorded[0].is_file():
        doc["model"] = there


def require_named_model(doc: dict[str, Any], path: Path, named: str | None) -> None:
    """Run a tuned file's model file only when the user names it: a model file is Python
    code that runs with the user's rights, and a tuned file is what users send each other,
    so the file it records is never imported on its word. ``named`` is the model the user
    gave (``--model``, or the ``model`` of a configuration passed on the command line);
    it takes the recorded one's place in ``doc``, so that its SHA-256 is checked against
    the one recorded (:func:`check_recordings`). A built-in model needs no naming.

    Raises:
        ConfigError: (exit 3) naming ``path`` and the model file, when the tuned file
            records a model file and the user named none.
    """
    if named is not None:
        doc["model"] = named
        return
    spec = doc.get("model")
    if isinstance(spec, str) and split_model_file(spec) is not None:
        raise ConfigError(
            f"{path}: the filter was tuned with the model file {excerpt(spec, 200)}; a model "
            "file is Python code that runs with your rights, and kftune does not run one "
            "because a tuned file names it: if you trust that file, pass it with --model "
            f"{shlex.quote(spec)}"
        )


def read_tuned(path: Path) -> dict[str, Any]:
    """Read and check a tuned-parameters file: the one place where ``evaluate``,
    ``estimate`` and ``export`` check it (a bad key is named, with what was expected).

    Raises:
        DataError: (exit 3) naming ``path`` and the key.
    """
    from kftune.data.jsonfile import read_json

    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != TUNED_FORMAT:
        raise DataError(
            f'not a tuned-parameters file (expected "format": "{TUNED_FORMAT}", written '
            "by 'kftune tune')",
            file=str(path),
        )
    for key in ("q", "ukf", "params"):
        if key not in doc:
            raise DataError(f"missing key {key!r}", file=str(path))
    q = doc["q"]
    if not (isinstance(q, list) and q and all(_finite(v) and v >= 0 for v in q)):
        raise DataError(
            "'q' must be a list of numbers >= 0, one per state (not true/false or strings), "
            f"got {q!r:.80}",
            file=str(path),
        )
    from kftune.filters import UKFSettings
    from kftune.tuning.cost import CostSpec

    try:  # the settings must make a filter and a cost, or the file is not usable
        UKFSettings(**doc["ukf"]).check_dim(len(q))
        CostSpec(**doc.get("cost_spec", {}))
    except (TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise DataError(f"unusable filter or cost settings: {exc}", file=str(path)) from None
    if not isinstance(doc["params"], dict):
        raise DataError("'params' must be an object of parameter values", file=str(path))
    from kftune.tuning.deploy import calibration_factor, tuned_for, tuned_model_params

    tuned_for(doc, str(path))  # the record's sample time and vehicle
    tuned_model_params(doc, str(path))  # model parameters tuned with the noise
    _check_deployment(doc, path)
    calibration_factor(doc, str(path))  # the calibration, in both places alike
    _locate_model(doc, path)
    for key, value, strict in (
        ("burn_in", doc.get("burn_in", 0.0), False),  # [s], >= 0
        ("params.r_scale", doc["params"].get("r_scale", 1.0), True),  # [-], > 0
    ):
        if not _finite(value) or (value <= 0 if strict else value < 0):
            raise DataError(
                f"{key!r} must be a finite number {'>' if strict else '>='} 0, got {value!r:.40}",
                file=str(path),
            )
    return doc


def _finite(value: Any) -> bool:
    """:func:`kftune.tuning.deploy.finite_number` (imported when a file is read: it loads
    the filter layer)."""
    from kftune.tuning.deploy import finite_number

    return finite_number(value)


def check_tuned_on(
    tuned: Mapping[str, Any],
    dataset: str,
    path: Path,
    named: str | None,
    command: str = "evaluate",
) -> None:
    """Parameters tuned on another dataset: refused when no dataset was named (the bundled
    one would be used by default: a run on the wrong data that looks like a result), a
    warning when one was named on purpose. ``command`` (``evaluate``, ``estimate``) is the
    one the message suggests."""
    tuned_on = tuned.get("dataset")
    if not isinstance(tuned_on, str) or tuned_on == dataset:
        return
    verb = "score them on" if command == "evaluate" else "run them on"
    if named is None:
        raise ConfigError(
            f"{path}: the parameters were tuned on dataset {tuned_on!r}, but no dataset was "
            f"given and the bundled one is {dataset!r}; name the dataset to {verb} "
            f"(kftune {command} DATASET --params {path}; 'default' for the bundled one)"
        )
    done = "scored on" if command == "evaluate" else "run on"
    warnings.warn(
        f"{path}: parameters tuned on dataset {tuned_on!r} are {done} dataset {dataset!r}",
        DataWarning,
        stacklevel=2,
    )


def check_recordings(
    doc: Mapping[str, Any],
    path: Path,
    dataset: Dataset,
    manoeuvres: Sequence[Manoeuvre],
    force: bool,
) -> tuple[VehicleParams | None, list[str]]:
    """Refuse recordings that the filter of the tuned file ``doc`` (read from ``path`` by
    :func:`read_tuned`) was not tuned for: another sample time or vehicle
    (:func:`~kftune.tuning.deploy.mismatches`), unless ``force``; each warning is issued
    as a :class:`~kftune.errors.DataWarning`.

    Returns:
        (the vehicle to run the filter with: the tuned one, else the recording's; the
        warnings, in words).

    Raises:
        ConfigError: (exit 3) naming ``path`` and the first difference, and --force.
    """
    from kftune.tuning.deploy import (
        mismatches,
        model_file_changed,
        tuned_for,
        tuned_model_params,
        unrecorded,
    )

    dt, vehicle = tuned_for(doc, str(path))
    notes = []
    missing = unrecorded(doc)
    if missing:
        notes.append(
            f"{path} does not record {', '.join(missing)} (written before kftune "
            "recorded deployments): the sample time and vehicle cannot be checked"
            + (
                f", the recording's vehicle {dataset.vehicle.name!r} is used"
                if vehicle is None and dataset.vehicle is not None
                else ""
            )
        )
    changed = model_file_changed(doc)
    tuned = list(tuned_model_params(doc, str(path)))  # expected to differ from the recording
    bad = ([changed] if changed else []) + mismatches(dt, vehicle, dataset, manoeuvres, tuned)
    if bad and not force:
        raise ConfigError(
            f"{path}: the filter was not tuned for these recordings: {bad[0]}"
            + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else "")
            + "; tune it on recordings like these, or pass --force to run it anyway"
        )
    for b in bad:
        notes.append(f"--force: {b}; the results may be poor")
    for note in notes:
        warnings.warn(note, DataWarning, stacklevel=2)
    return vehicle or dataset.vehicle, notes


def pick_split(split: str | None, dataset: Dataset) -> tuple[str, tuple[Manoeuvre, ...]]:
    """(split, its manoeuvres) of ``--split`` (None: test, or all with a warning when the
    dataset has no test manoeuvres).

    Raises:
        ConfigError: (exit 3) a split the dataset has no manoeuvres in, naming those it has.
    """
    if split is None:
        split = "test"
        if not dataset.test:
            split = "all"
            warnings.warn(
                f"dataset {dataset.name!r} has no test manoeuvres: scoring all "
                f"{len(dataset.manoeuvres)} (--split all), which are training ones, so the "
                "KPIs are no held-out evidence",
                DataWarning,
                stacklevel=2,
            )
    chosen = {"train": dataset.train, "test": dataset.test, "all": dataset.manoeuvres}[split]
    if not chosen:
        other = "train" if split == "test" else "test"
        raise ConfigError(
            f"--split {split}: dataset {dataset.name!r} has no {split} manoeuvres (its "
            f"{len(dataset.manoeuvres)} are all {other} manoeuvres); use --split all or "
            f"--split {other}"
        )
    return split, chosen


def run(args: argparse.Namespace) -> int:
    """Run ``kftune evaluate``."""
    import numpy as np

    from kftune.data import open_dataset
    from kftune.experiment import channel_units, manual_point
    from kftune.filters import UKFSettings
    from kftune.tuning.cost import CostSpec
    from kftune.tuning.deploy import (
        TunedFilter,
        calibration_factor,
        consistency_docs,
        parameterization_of,
        tuned_model_params,
    )
    from kftune.tuning.kpi import average_kpis
    from kftune.tuning.parameterization import NoiseParameterization
    from kftune.tuning.problem import TuningProblem, assess, missing_references
    from kftune.tuning.runs import check_units, default_r0, where_diverged

    if args.force and args.params is None:
        raise UsageError("--force applies to a tuned file's filter (--params) only")
    if not args.calibrated and args.params is None:
        raise UsageError("--no-calibration applies to a tuned file's filter (--params) only")
    config = load_config(args.config, "evaluate")
    tuned = read_tuned(args.params) if args.params is not None else None
    if tuned is not None:
        require_named_model(tuned, args.params, pick(args, config, "model", None))
    named = pick(args, config, "dataset", None)
    dataset = open_dataset(named)
    if tuned is not None:
        check_tuned_on(tuned, dataset.name, args.params, named)
    split, manoeuvres = pick_split(args.split, dataset)
    vehicle = dataset.vehicle
    if tuned is not None:  # the filter as tuned: for these recordings, on its vehicle
        vehicle, _ = check_recordings(tuned, args.params, dataset, manoeuvres, args.force)
    # unless told otherwise, the model the parameters were tuned for
    was = None if tuned is None else (args.params, tuned)
    fs = filter_spec_of(args, config, vehicle, was, dataset=dataset.name)
    check_units(fs.model, dataset)
    model = fs.model
    # unless told otherwise, score the way the parameters were tuned: what the command line
    # and the configuration give replaces that part of the tuned file's cost
    spec = cost_spec(
        args,
        config,
        None if tuned is None else tuned.get("cost_spec", {}),
        model=model,
        tuned_file=args.params,
    )
    # the burn-in the file was scored with, unless the command line or configuration says
    scored_after = float(pick_tuned(args, config, "burn_in", was))
    if tuned is not None:
        params = tuned["params"]
        r_scale = float(params.get("r_scale", 1.0))
        ukf = UKFSettings(**tuned["ukf"])
        if len(tuned["q"]) != model.n_states:
            raise ConfigError(
                f"{args.params} holds {len(tuned['q'])} Q values but model {model.name!r} "
                f"has {model.n_states} states {list(model.state_names)}"
            )
        if "r" in tuned:  # the filter as tuned, the one estimate runs and export deploys
            r0: Any = TunedFilter.from_document(tuned, str(args.params)).r  # checks 'r'
            if len(r0) != model.n_measurements:
                raise ConfigError(
                    f"{args.params} holds {len(r0)} R values but model {model.name!r} has "
                    f"{model.n_measurements} measurements {list(model.measurement_names)}"
                )
            factors = [1.0] * model.n_measurements
        else:  # a file from before R was recorded: the data's R times the tuned scales
            r0 = default_r0(model, dataset, pick(args, config, "r0", None))
            factors = [
                r_scale * float(params.get(f"r_{m}_scale", 1.0)) for m in model.measurement_names
            ]
        # the model parameters as tuned (a vehicle model's are in its vehicle already)
        par = parameterization_of(tuned, str(args.params), model, ukf)
        values = tuned_model_params(tuned, str(args.params))
        x = np.array([*tuned["q"], *factors, *(values[n] for n in par.model_names)])
    else:
        par = parameterization(args, config, model)
        par = NoiseParameterization(
            default_settings=par.default_settings,
            states=model.state_names,
            measurements=model.measurement_names,
        )
        if args.q and len(args.q) != model.n_states:
            raise UsageError(
                f"--q takes {model.n_states} values for model {model.name!r} "
                f"{list(par.q_names)}, got {len(args.q)}"
            )
        x = np.array(args.q) if args.q else manual_point(par)
        r0 = default_r0(model, dataset, pick(args, config, "r0", None))

    def problem_for(cost: CostSpec) -> TuningProblem:
        return TuningProblem(
            manoeuvres,
            vehicle,
            r0,
            cost=cost,
            parameterization=par,
            workers=pick(args, config, "workers"),
            burn_in=scored_after,
            model=fs.spec,
            filter=fs.filter,
        )

    unscored = None  # why the cost J cannot be given: its reference channel is missing
    try:
        problem = problem_for(spec)
    except MissingChannelError as exc:
        if not exc.channel.endswith("_ref"):
            raise
        # the filter still runs and its KPIs against the measurements are still worth
        # having: the cost is left out ('–'), not the evaluation
        unscored = str(exc)
        problem = problem_for(CostSpec(kind="nis", estimate=spec.estimate))
    # the cost as tune minimised it (covariance scale 1): nis, pem, nlpd and crps move with
    # the scale, so the calibrated filter's value is reported apart, never as the cost
    scale = (
        calibration_factor(tuned, str(args.params))
        if tuned is not None and args.calibrated
        else 1.0
    )
    with problem:
        cost = None if unscored else _cost_or_none(problem, x)
        problem.cov_scale = scale  # the filter as deployed: its σ, for the consistency
        cost_calibrated = cost if scale == 1.0 or unscored else _cost_or_none(problem, x)
        metrics, results = assess(problem, x, manoeuvres)
    missing = missing_references(problem, manoeuvres)
    consistency, pooled = consistency_docs(problem, manoeuvres, results)
    sideslip = all("rmse" in row for row in metrics.values())
    avg = (
        average_kpis(metrics.values(), (*KPI_NAMES, *MEASURED_KEYS))
        if sideslip
        else _averages(metrics.values())
    )
    measured = MEASURED_KEYS if sideslip else measured_keys(problem.model.measurement_names)
    for row in (*metrics.values(), avg):
        row.update({new: row[old] for old, new in measured.items() if old in row})
    where = {
        name: where_diverged(dataset[name], res) for name, res in results.items() if res.diverged
    }
    reason = f"the filter diverged on {len(where)} of {len(results)} manoeuvres" if where else None
    q, r, ukf = problem.decode(x)
    doc = {
        "dataset": dataset.name,
        "split": split,
        "q": q.tolist(),
        "r": r.tolist(),
        "ukf": {"alpha": ukf.alpha, "beta": ukf.beta, "kappa": ukf.kappa},
        "model_params": problem.parameterization.model_values(x),
        "cov_scale": problem.cov_scale,
        "cost": cost,
        "cost_calibrated": cost_calibrated,
        "cost_unscored": unscored,
        "cost_kind": spec.kind,
        "cost_estimate": spec.estimate,
        "cost_normalise": spec.normalise,
        "burn_in": scored_after,
        "diverged": reason,
        "missing_references": missing,
        "average": {k: _num(v) for k, v in avg.items()},
        **(
            {}
            if sideslip
            else {
                "units": channel_units(
                    problem.model,
                    dataset,
                    [k[5:] for k in avg if k.startswith("rmse_") and k not in measured.values()],
                )
            }
        ),
        "manoeuvres": {
            name: {
                "kind": dataset[name].kind,
                **{k: _num(v) for k, v in row.items()},
                **({"diverged_at": where[name]} if name in where else {}),
                "consistency": consistency[name],
            }
            for name, row in metrics.items()
        },
        "consistency": pooled,
    }
    if args.json:
        emit_json(doc)
    else:
        _print_table(doc)
    if reason is None:
        return EXIT_OK
    first = next(iter(where.values()))
    more = f" (and {len(where) - 1} more)" if len(where) > 1 else ""
    print(f"kftune: failed: {reason}; first: {first}{more}", file=sys.stderr)
    return EXIT_FAILURE


#: The sideslip report's measured-channel errors: the former --json key → the key that
#: says what the error is taken against and in which unit (both written for one release).
MEASURED_KEYS = {"rmse_r": "rmse_r_vs_measured_degps", "rmse_ay": "rmse_ay_vs_measured_mps2"}


def measured_keys(measurements: Sequence[str]) -> dict[str, str]:
    """For a model other than the sideslip report's: ``rmse_<m>`` → ``rmse_<m>_vs_measured``
    for each of its ``measurements`` (the error of h(x) against the measured, noisy channel,
    in the channel's unit)."""
    return {f"rmse_{m}": f"rmse_{m}_vs_measured" for m in measurements}


def _cost_or_none(problem: TuningProblem, x: np.ndarray) -> float | None:
    """The problem's cost at ``x`` with its current covariance scale; None where the filter
    diverges (the cost is then undefined)."""
    from kftune.errors import FilterDivergedError

    try:
        return problem.evaluate(x).cost
    except FilterDivergedError:
        return None


def _num(v: float) -> float | None:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _averages(rows: Any) -> dict[str, float]:
    """Plain means of each ``rmse_*`` metric over the manoeuvres that have it (NaN for all
    when the filter diverged on any, as :func:`~kftune.tuning.kpi.average_kpis`)."""
    import numpy as np

    rows = list(rows)
    n_diverged = sum(1 for r in rows if r.get("diverged", 0))
    keys = [k for k in dict.fromkeys(k for r in rows for k in r) if k.startswith("rmse_")]
    out: dict[str, float] = {}
    for k in keys:
        values = [r[k] for r in rows if k in r and not math.isnan(r[k])]
        out[k] = float(np.mean(values)) if values and not n_diverged else math.nan
    out["n_diverged"] = n_diverged
    out["n_manoeuvres"] = len(rows)
    return out


def _print_table(doc: dict[str, Any]) -> None:
    rows = doc["manoeuvres"]
    if all("rmse" in row for row in rows.values()):
        cols: tuple[str, ...] = (*KPI_NAMES, *MEASURED_KEYS.values())
        heads: tuple[str, ...] = (
            "RMSE°",
            "MAE°",
            "RMSE_NON°",
            "MAE_NON°",
            "r vs meas °/s",  # RMSE, as the footnote says: the table fits 100 columns
            "ay vs meas m/s²",
        )
    else:  # another model: the RMSE of each measurement and referenced output
        means = doc["average"]
        cols = tuple(
            k for k in means
            if k.startswith("rmse_") and not k.endswith("_vs_measured")
            and f"{k}_vs_measured" not in means
        )  # fmt: skip
        units = doc.get("units", {})
        heads = tuple(f"RMSE {k[5:]} {units.get(k[5:], '')}".rstrip() for k in cols)
        cols += tuple(k for k in means if k.endswith("_vs_measured"))
        heads += tuple(
            f"RMSE {k[5:-12]} vs meas {units.get(k[5:-12], '')}".rstrip()
            for k in cols[len(heads) :]
        )
    widths = [max(10, len(h)) for h in heads]
    width = max(12, *(len(n) for n in rows))
    print(f"{'manoeuvre':{width}s} " + " ".join(f"{h:>{w}s}" for h, w in zip(heads, widths)))
    for name, row in rows.items():
        cells = " ".join(_cell(row.get(c), w) for c, w in zip(cols, widths))
        print(f"{name:{width}s} {cells}")
    average = (_cell(doc["average"].get(c), w) for c, w in zip(cols, widths))
    print(f"{'average':{width}s} " + " ".join(average))
    if "rmse_non" in cols:
        print("MAE: maximum absolute error; _NON: samples with |ay| >= 4 m/s²")
        calm = [n for n, row in rows.items() if row.get("n_non") == 0]
        if calm:  # a NON KPI of no samples is undefined, not zero
            print(
                f"_NON –: no sample with |ay| >= 4 m/s² in {len(calm)} of {len(rows)} "
                f"manoeuvres (first: {calm[0]!r}); "
                + ("averaged over the rest" if len(calm) < len(rows) else "no average")
            )
    if any(c in MEASURED_KEYS.values() or c.endswith("_vs_measured") for c in cols):
        print("vs meas: RMSE against the measured channel, sensor noise included (no reference)")
    for ref, lacking in doc["missing_references"].items():
        print(
            f"sideslip KPIs (–): they need a reference channel {ref}, which "
            f"{len(lacking)} of {len(rows)} manoeuvres lack (first: {lacking[0]!r})"
        )
    if doc.get("cost_unscored"):
        print(f"cost J ({doc['cost_kind']}): – ({doc['cost_unscored']})")
    if doc["cost"] is not None:
        split, cost = doc["split"], doc["cost"]
        print(f"cost J ({doc['cost_kind']}) on the {split} split, as tuned: {cost:.5g}")
    calibrated = doc.get("cost_calibrated")
    if doc["cov_scale"] != 1.0 and calibrated is not None and calibrated != doc["cost"]:
        print(f"cost J of the calibrated filter (covariances × c): {calibrated:.5g}")
    if doc["cov_scale"] != 1.0:
        print(
            f"calibrated: covariances × {doc['cov_scale']:.4g} as the tuned file records "
            "(--no-calibration: the filter's own)"
        )
    from kftune.report.tables import consistency_lines

    runs = {name: row["consistency"] for name, row in rows.items()}
    runs[f"{doc['split']} split"] = doc["consistency"]  # pooled sample by sample
    print("\n".join(consistency_lines(runs, width)))
    if doc["diverged"] is not None:
        print(f"{doc['diverged']}:")
        for row in doc["manoeuvres"].values():
            if "diverged_at" in row:
                print(f"  {row['diverged_at']}")


def _cell(v: float | None, width: int = 10) -> str:
    return f"{'–':>{width}s}" if v is None else f"{v:{width}.4f}"
