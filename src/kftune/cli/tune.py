"""``kftune tune``: tune a filter's process noise on a dataset's training manoeuvres.

The filter is the paper's single-track UKF unless ``--model`` (a built-in model or a Python
file defining your own) and ``--filter ekf`` say otherwise; Q's diagonal is tuned, one
``q_<state>`` per state of the model. Without any cost option (``--cost``, ``--weights``,
``--normalise``, ``--estimate``) or ``[cost]`` key, tune tunes kftune's recommended
setting: the NRMSE normalised over the dataset, with R's diagonal tuned too (one
``r_<measurement>_scale`` each; README 'Which cost'); ``--cost nrmse`` is the paper's
cost with Q alone.

Writes the tuned parameters to a JSON file (``--out``, default ``tuned.json``) that
``kftune evaluate --params`` reads. With ``--storage study.db`` every evaluation is saved as
it happens; ``--resume`` continues a study that was interrupted or killed, without
re-evaluating anything finished.

The cost is a proxy: at the end ``tune`` runs the tuned filter and the manual rule of thumb
on the dataset's test manoeuvres, which the tuning never saw, and prints and records
(``held_out``) their mean β RMSE, and whether the tuned filter's β standard deviation can be
trusted there: its ±1.96σ coverage and mean NEES (``held_out.consistency``, as ``kftune
evaluate`` reports them).

With tuned model parameters (``--tune-model``) ``tune`` then says for each whether the
training manoeuvres determine it: its value against the recorded start, whether it sits on
a bound, and the range over which the cost rises by less than 1 % around the tuned point,
with the others held and with the other model parameters re-fitted — a parameter whose
range reaches a bound or spans half its box is said to be not determined, with a physical
reason where the model knows one (μ on data far from the friction limit). At most 10
evaluations per parameter and one per pair; recorded as ``identifiability``
(:mod:`kftune.tuning.identify`).

With model parameters tuned by TR-BO (the default method) the budget ``-n`` runs in two
stages: a quarter of it tunes the noise alone at the recorded model, the rest searches the
joint box from that optimum (TR-BO's ``x0``), so the joint filter never ends at a higher
training cost than the noise-only one; the held-out line then also shows the noise-only
filter's β RMSE and warns where the joint one is worse (the joint filter is kept). The
first stage's study lies beside ``--storage`` (``study.noise-only.db``); ``--resume``
continues either stage. Other methods, ``--scheduler`` and an ``[options.trbo] x0`` of
your own search the joint box in one stage.

When the best point lies on a bound of the search box (within 1 % of a parameter's range),
tune says which parameter and which bound, and the file records it (``on_bounds``): the
optimum may lie beyond. Unless the cost is flat there: tune runs the filter with that
parameter one step in (a decade, or a tenth of a linear box) and, where ``--widen-bounds``
would move the bound, two decades beyond it (:func:`kftune.experiment.edge_probes`),
records both (``on_bounds[].edge``) and, where the cost is not 0.1 % lower two decades
out (or, where no widening would search, rose less than 0.1 % over the step in), says a
wider box is unlikely to help instead of suggesting one. ``--widen-bounds`` (config
``widen_bounds = true``) then moves that bound out by two decades and runs the method
again on the wider box with the same budget, at most three times; the follow-up studies
lie beside ``--storage`` (``study.widen1.db`` …) and ``--resume`` continues them too. The
best point of all runs is kept.

Parallel and distributed evaluation: ``--batch Q`` asks the method for Q points at a time
(``--workers`` keeps its meaning: processes that share the manoeuvres of one evaluation).
``--scheduler tcp://HOST:8786`` evaluates on a running Dask cluster, ``--scheduler local``
on a local one of ``--workers`` processes (both need the ``dask`` extra); Q then defaults to
the cluster's number of worker threads. The dataset is sent to every worker once; a batch
is split across its points, and across manoeuvres when it has fewer points than workers.
Every proposal is saved before it is sent and every result as it arrives; the proposals
depend only on the seed and Q, so ``--resume`` re-runs only what was in flight and the run
ends as an uninterrupted one would. A worker that dies is replaced and its evaluation sent
again (twice at most), then recorded as failed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import shlex
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kftune import __version__
from kftune.cli._common import (
    BATCH,
    BUDGET,
    CALIBRATIONS,
    MAX_BUDGET,
    RECOMMENDED_NORMALISE,
    RECOMMENDED_TUNE_R,
    TIMEOUT_SECONDS,
    add_command,
    add_common,
    burn_in,
    cost_spec,
    emit_json,
    filter_spec_of,
    load_config,
    model_file_for,
    parameterization,
    pick,
    recommended,
    split_model_file,
)
from kftune.cli.exit_codes import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK
from kftune.cli.outputs import command_inputs, output_file, write_output
from kftune.errors import (
    ConfigError,
    ObjectiveMismatchError,
    RunFailedError,
    SettingWarning,
    UsageError,
)
from kftune.optim import DEFAULT_METHOD, METHODS
from kftune.optim.widen import WIDEN_ROUNDS, round_storage
from kftune.tuning.calibrate import DEFAULT_CRITERION

if TYPE_CHECKING:
    from kftune.data import Dataset
    from kftune.experiment import Staging
    from kftune.optim import OptimizeResult
    from kftune.tuning.calibrate import Calibration
    from kftune.tuning.identify import Identifiability
    from kftune.tuning.problem import TuningProblem

TUNED_FORMAT = "kftune-tuned-1"
#: A held-out β RMSE is called worse than another's in a warning only above this factor:
#: a 0.3 % gap on six test manoeuvres (a newcomer's joint tuning, C_af moved 1 %) is no
#: verdict on the parameters, and the test error of one tuning moves by a few per cent
#: between seeds (BENCHMARKS.md, "Tuning model parameters"). Smaller gaps are shown, not
#: warned about.
WORSE_RMSE = 1.02
#: How a warning inside the held-out evidence starts a line (as the CLI's own warnings do).
WARN = "\nkftune: warning: "


def register(subparsers: Any) -> None:
    """Add ``tune``."""
    p = add_command(
        subparsers, "tune", "tune a filter's process noise on the training manoeuvres", __doc__
    )
    add_common(p)
    p.add_argument(
        "--method",
        "-m",
        choices=METHODS,
        help=f"optimiser (default {DEFAULT_METHOD}: trust-region Bayesian optimisation; the "
        "paper's method is tsbo-tsp)",
    )
    p.add_argument(
        "--budget",
        "-n",
        type=BUDGET,
        help="cost evaluations (default: the method's own — TR-BO 100, TSBO 40, GA 225, others "
        "40; an anytime method such as TR-BO never ends at a higher cost with more; at most "
        f"{MAX_BUDGET}, beyond any run that ends)",
    )
    p.add_argument("--storage", type=Path, help="SQLite study file saving every evaluation")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the study in --storage where it stopped, with the settings it was "
        "created with (the same method, seed and data); a larger -n continues a finished "
        "study of trbo, random, optuna-tpe, optuna-gp or cma (its stored evaluations are "
        "proposed again as they were, then the run goes on); tsbo and ga plan their run by "
        "the budget and are refused, and so is a two-stage joint tuning (--tune-model), "
        "whose joint search starts from the first stage's best",
    )
    p.add_argument(
        "--timeout",
        type=TIMEOUT_SECONDS,
        help="per-evaluation time limit [s], at most 1e6; a slower evaluation fails and the "
        "run goes on (not with --batch or --scheduler)",
    )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT|local",
        help="evaluate on the Dask cluster of this scheduler, or 'local' to start one of "
        "--workers processes (needs the 'dask' extra)",
    )
    p.add_argument(
        "--batch",
        type=BATCH,
        help="points evaluated at a time (default: the Dask cluster's workers; 1 without "
        "--scheduler)",
    )
    p.add_argument(
        "--widen-bounds",
        action="store_true",
        default=None,
        help="when the best point lies on a bound of a log10 parameter, widen that bound by "
        "two decades and tune again with the same budget (at most 3 times, so up to 4× the "
        "budget in all: 400 evaluations with TR-BO's default)",
    )
    p.add_argument(
        "--no-calibration",
        dest="calibrate",
        action="store_false",
        help="do not fit the covariance scale c after the search (by default the filter's "
        "covariances are reported c times larger, c fitted so that its β σ matches its errors "
        "on the training manoeuvres, its estimate unchanged; the file records c, and "
        'evaluate, estimate and export apply it); config calibration = "none"',
    )
    p.add_argument(
        "--calibration",
        choices=CALIBRATIONS,
        metavar="CRITERION",
        help=f"what c is fitted by: {DEFAULT_CRITERION} (default: the mean CRPS of the β "
        "errors least, which held the test errors best across datasets), nees (mean NEES 1), "
        "coverage95, median (median NEES at χ²₁'s), reliability (coverage over 50-99 %% "
        "nearest nominal), minimax (the worse 68 %%/95 %% miss least), or none (= "
        "--no-calibration); config calibration = CRITERION",
    )
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        default=Path("tuned.json"),
        help="where to write the tuned parameters (default tuned.json)",
    )
    p.set_defaults(func=run)


def _check_staged_budget(stages: Any) -> None:
    """Refuse to resume a two-stage joint tuning with another budget, before either study
    is touched: the split between the stages follows the budget, and the joint search
    starts from the first stage's best, so the first stage run longer would move that
    start and the stored joint evaluations could not be proposed again.

    Raises:
        ConfigError: the first stage's study was planned for another number of evaluations.
    """
    from kftune.optim.study import read_study

    first = stages.noise_storage
    if first is None or not first.exists():
        return
    stored = read_study(first).settings.get("budget")
    if stored != stages.noise_budget:
        raise ConfigError(
            f"--resume: this joint tuning runs in two stages and its first stage ({first}) "
            f"was planned for {stored} evaluations of the noise alone, but -n "
            f"{stages.total} gives it {stages.noise_budget}; the joint search starts from "
            "the first stage's best, so a two-stage tuning cannot be continued with another "
            "budget: resume it with the -n it was started with, or start a new study"
        )


def run(args: argparse.Namespace) -> int:
    """Run ``kftune tune``."""
    config = load_config(args.config, "tune")
    if args.resume and args.storage is None:
        raise UsageError("--resume needs --storage (the study file to continue)")
    # contradictions between options on the command line are usage errors (exit 2); the
    # same between the configuration and the command line are refused by tune() (exit 3)
    if args.timeout is not None and (args.batch is not None or args.scheduler is not None):
        raise UsageError(
            f"--timeout cannot be combined with {'--batch' if args.batch else '--scheduler'}: "
            "a per-evaluation timeout runs every evaluation in one local worker process"
        )
    if args.widen_bounds and args.method == "manual":
        raise UsageError("--widen-bounds needs a search; -m manual evaluates one point")
    output_file(args.out, "--out", command_inputs(args, config))
    if args.storage is not None:
        output_file(args.storage, "--storage", command_inputs(args, config, study=False))
    widen = bool(pick(args, config, "widen_bounds"))
    if not args.calibrate and args.calibration not in (None, "none"):
        raise UsageError(f"--no-calibration contradicts --calibration {args.calibration}")
    criterion = "none" if not args.calibrate else pick(args, config, "calibration", None)
    criterion = criterion or DEFAULT_CRITERION
    from kftune.experiment import noise_stage_storage

    first_stage = noise_stage_storage(args.storage)  # a joint tuning's first stage
    if (
        args.resume
        and args.storage is not None
        and not args.storage.exists()
        and not (first_stage is not None and first_stage.exists())
    ):
        raise ConfigError(
            f"--resume: study file {args.storage} does not exist (a misspelt name would "
            "start afresh); leave out --resume to start a new study there"
        )
    if args.storage is not None and not args.resume:
        studies = [round_storage(args.storage, k) for k in range(WIDEN_ROUNDS + 1 if widen else 1)]
        for study in [*studies, first_stage]:
            if study is not None and study.exists():
                raise ConfigError(
                    f"study file {study} already exists; pass --resume to continue it, or "
                    "choose another --storage"
                )
    result = problem = dataset = None
    try:  # from here on a Ctrl-C says what was kept, also before the first evaluation
        from kftune.data import open_dataset
        from kftune.experiment import require_success, staging, tune
        from kftune.optim import Execution, OptimizationInterrupted
        from kftune.optim.engine import EngineLostError
        from kftune.tuning.problem import TuningProblem
        from kftune.tuning.runs import check_units, default_r0

        dataset = open_dataset(pick(args, config, "dataset", None))
        if not dataset.train:
            raise ConfigError(
                f"dataset {dataset.name!r} has no training manoeuvres to tune on (its "
                f"{len(dataset.test)} are all test manoeuvres; see kftune dataset info)"
            )
        method = pick(args, config, "method", DEFAULT_METHOD)  # both checked already
        fs = filter_spec_of(args, config, dataset.vehicle, dataset=dataset.name)
        check_units(fs.model, dataset)
        scheduler = pick(args, config, "scheduler", None)
        workers = pick(args, config, "workers")
        problem = TuningProblem(
            dataset.train,
            dataset.vehicle,
            default_r0(fs.model, dataset, pick(args, config, "r0", None)),
            cost=cost_spec(args, config, model=fs.model),
            parameterization=parameterization(args, config, fs.model),
            workers=1 if scheduler is not None else workers,  # the cluster's processes
            burn_in=burn_in(args, config),
            model=fs.spec,
            filter=fs.filter,
        )
        with problem, _engine(problem, scheduler, workers) as engine:
            budget = pick(args, config, "budget", None)
            options = config.get("options", {}).get(method)
            stages = staging(
                problem, method, budget, options=options, engine=engine, storage=args.storage
            )
            if args.resume and stages is not None:
                _check_staged_budget(stages)
            if stages is not None and not (args.quiet or args.json):
                print(stages.line(), file=sys.stderr, flush=True)
            short = None if stages is None else stages.warning()
            if short is not None:
                warnings.warn(short, SettingWarning, stacklevel=1)
            try:
                result = tune(
                    problem,
                    method,
                    budget=budget,
                    seed=pick(args, config, "seed"),
                    storage=args.storage,
                    resume=args.resume,
                    progress=False if (args.quiet or args.json) else None,
                    options=options,
                    widen_bounds=widen,
                    execution=Execution(
                        timeout=pick(args, config, "timeout", None),
                        engine=engine,
                        batch=pick(args, config, "batch", None),
                    ),
                    dataset=dataset_record(dataset.name, pick(args, config, "dataset", None)),
                )
            except OptimizationInterrupted as stop:
                _interrupted(args, stop.result, problem, dataset)
                return EXIT_INTERRUPTED
            except EngineLostError as lost:  # the Dask scheduler went away
                _interrupted(args, lost.result, problem, dataset, failure=str(lost))
                return EXIT_FAILURE
            except ObjectiveMismatchError as exc:
                hint = mismatch_hint(exc, dataset.name, args.storage, recommended(args, config))
                if not hint:
                    raise
                raise ObjectiveMismatchError(f"{exc}{hint}", exc.stored, exc.current) from None
    except KeyboardInterrupt:  # loading, starting or stopping workers: keep what there is
        _interrupted(args, result, problem, dataset)
        return EXIT_INTERRUPTED
    require_success(result, method)
    doc = tuned_document(result, problem, dataset, args.out)
    noise_x = None
    if stages is not None and result.options.get("x0"):  # the first stage's best
        noise_x = result.options["x0"][0]
        doc["stages"] = stages_record(stages, result, noise_x, problem)
    # The result first: nothing after this line can lose it.
    write_output(args.out, json.dumps(doc, indent=1, allow_nan=False) + "\n", "--out", _kept(args))
    # an interrupted run's best-so-far (see _interrupted) is superseded now
    with contextlib.suppress(OSError):
        _partial(args.out).unlink(missing_ok=True)
    if doc["on_bounds"]:  # before calibration: the probes measure the cost as tuned
        doc["on_bounds"] = probe_edges(problem, result, doc["on_bounds"], args.quiet or args.json)
        write_output(args.out, json.dumps(doc, indent=1, allow_nan=False) + "\n", "--out")
    cal, no_calibration = (
        calibrate(problem, result.x, criterion) if criterion != "none" else (None, None)
    )
    if cal is not None:
        from kftune.tuning.deploy import calibration_record

        doc["calibration"] = cal.as_dict("train")
        doc["deployment"]["calibration"] = calibration_record(cal.factor)
        problem.cov_scale = cal.factor  # the held-out evidence is the calibrated filter's
    doc["held_out"], no_evidence = held_out(
        problem, result.x, dataset, noise_only=noise_x, first_box=first_box_best(result)
    )
    if doc["held_out"] is not None or cal is not None:
        write_output(args.out, json.dumps(doc, indent=1, allow_nan=False) + "\n", "--out")
    ident, no_ident = identifiability(problem, result.x, quiet=args.quiet or args.json)
    if ident is not None:
        doc["identifiability"] = ident.to_dict()
        write_output(args.out, json.dumps(doc, indent=1, allow_nan=False) + "\n", "--out")
    if args.json:
        emit_json({**doc, "file": str(args.out)})
    else:
        evals = f"{result.n_evals} evaluations ({result.n_failed} failed)"
        if "stages" in doc:  # the failures are the joint search's; its first is stage 1's best
            st = doc["stages"]
            evals = (
                f"{st['noise_budget'] + result.n_evals} evaluations ({st['noise_budget']} + "
                f"{result.n_evals}, {result.n_failed} of the joint search failed)"
            )
        print(
            f"{method}: best cost {result.fun:.5g} after {evals} on {len(dataset.train)} "
            f"training manoeuvres of {dataset.name!r}"
        )
        if problem.model_spec != "single-track" or problem.filter != "ukf":
            print(f"  model {problem.model.name!r}, filter {problem.filter}")
        if "stages" in doc:
            print(stages_line(doc["stages"]))
        for name, value in (result.params or {}).items():
            print(f"  {name:10s} = {value:.4e}")
        for line in failure_lines(result):
            print(line)
        for line in bound_lines(doc, problem, widen):
            print(line)
        if cal is not None:
            from kftune.tuning.calibrate import summary_line

            print(summary_line(cal))
        elif no_calibration:
            print(f"σ not calibrated: {no_calibration}")
        if doc["held_out"] is not None:
            print(held_out_line(doc["held_out"], doc["cost_spec"]))
            if (pooled := held_out_consistency_line(doc["held_out"])) is not None:
                print(pooled)
        elif no_evidence:
            print(f"no held-out evidence: {no_evidence}")
        for line in ident.lines() if ident is not None else []:
            print(line)
        if no_ident:
            print(f"identifiability of the tuned model parameters not measured: {no_ident}")
        print(f"tuned parameters written to {args.out}")
        dataset_arg = pick(args, config, "dataset", None)
        # no test manoeuvres: the training ones, and the hint says they are
        split, what = ("test", "test") if dataset.test else ("train", "training")
        spec = problem.model_spec  # never run on a tuned file's word: named in the hint
        model_named = ["--model", spec] if split_model_file(spec) else []
        print(
            f"KPIs per {what} manoeuvre"
            + ("" if dataset.test else " (the dataset has no test manoeuvres)")
            + ": "
            + shlex.join(
                [
                    "kftune",
                    "evaluate",
                    *([] if dataset_arg in (None, "default") else [str(dataset_arg)]),
                    "--params",
                    str(args.out),
                    *model_named,  # a model file runs only when named
                    "--split",
                    split,
                ]
            )
        )
    return EXIT_OK


@contextlib.contextmanager
def _engine(problem: TuningProblem, scheduler: str | None, workers: int) -> Iterator[Any]:
    """The Dask engine of ``--scheduler`` (None without), closed on the way out."""
    if scheduler is None:
        yield None
        return
    from kftune.optim.dask_engine import DaskEngine

    engine = DaskEngine(problem, scheduler=scheduler, workers=workers)
    try:
        yield engine
    finally:
        engine.close()


def dataset_record(name: str, spec: Any) -> dict[str, Any]:
    """What a study records of the dataset it is made on, to name it when a resume on
    other data is refused: its name and the absolute path it was read from (None for the
    bundled set, ``spec`` None or "default")."""
    bundled = spec is None or str(spec) == "default"
    return {"name": name, "path": None if bundled else str(Path(spec).resolve())}


def mismatch_hint(
    exc: ObjectiveMismatchError, dataset: str, storage: Any, default_cost: bool
) -> str:
    """What to do about a study made for another objective, to append to its message: where
    the data differ, that the study was made on other data (its manoeuvres, from the
    study's objective), and to name that dataset (by its recorded name and path where the
    study recorded them, :func:`dataset_record`); where the cost differs and this run tunes
    tune's default cost (``default_cost``) while the study has the paper's, the option that
    resumes it. "" when neither applies (or the summaries are not known).

    A summary reads "8 manoeuvres (a … b), VEHICLE, cost KIND …" (the data before
    ", cost ", the cost and model after it, :meth:`TuningProblem.fingerprint`); equal
    summaries of two objectives mean data of the same names with other samples."""
    if exc.stored is None or exc.current is None:
        return ""
    old_data, _, old_cost = exc.stored.partition(", cost ")
    new_data, _, new_cost = exc.current.partition(", cost ")
    hint = ""
    if old_data != new_data or exc.stored == exc.current:
        changed = (
            " (the same manoeuvre names, other samples: the dataset changed since)"
            if exc.stored == exc.current
            else ""
        )
        made, named, where = exc.dataset, "", "DATASET"  # a study before datasets were named
        if made is not None:
            path = made.get("path")
            named = f" {made.get('name')!r}" + (f" ({path})" if path else "")
            where = path or "default"
        hint += (
            f". The study was made on other data than this run's dataset {dataset!r}: on the "
            f"dataset{named} of {old_data}{changed}; to resume it, name the dataset it was "
            f"made on: kftune tune {shlex.quote(where)} --storage {shlex.quote(str(storage))} "
            "--resume"
        )
    paper_cost = old_cost.startswith("nrmse") and "dataset-normalised" not in old_cost
    if default_cost and old_cost != new_cost and paper_cost:
        hint += (
            f". This run tunes kftune tune's default, the NRMSE {RECOMMENDED_NORMALISE}-"
            f"normalised with R's diagonal (tune_r = {RECOMMENDED_TUNE_R!r}); a study "
            "started with the paper's cost and Q alone (tune's default before) resumes with "
            "--cost nrmse"
        )
    return hint


def failure_lines(result: OptimizeResult) -> list[str]:
    """Why evaluations failed, grouped by kind with counts (the reasons are otherwise in
    the study file only): ``"3 of 40 evaluations failed:"`` and one line per kind, most
    frequent first; nothing when none failed."""
    from kftune.tuning.runs import failure_kinds

    reasons = [r.reason for r in result.history if not r.ok]
    if not reasons:
        return []
    return [f"{len(reasons)} of {len(result.history)} evaluations failed:"] + [
        f"  {kind} ({n})" for kind, n in failure_kinds(reasons)
    ]


def bound_lines(doc: dict[str, Any], problem: TuningProblem, widened: bool) -> list[str]:
    """What ``tune`` says about the search box: bounds it widened, and parameters whose
    best value lies on a bound — with the cost one step in from that bound and, where a
    widening would search, beyond it, where they were measured (``hit["edge"]``,
    :func:`probe_edges`): where the cost is flat there a wider box will not help, and the
    line says so instead of suggesting one."""
    from kftune.report.tables import edge_text

    lines = []
    initial = {p.name: p for p in problem.space.params}
    for p in doc["search_space"]["params"]:
        was = initial[p["name"]]
        if (p["low"], p["high"]) != (was.low, was.high):
            lines.append(
                f"search box widened: {p['name']} in [{was.low:g}, {was.high:g}] -> "
                f"[{p['low']:g}, {p['high']:g}]"
            )
    for hit in doc["on_bounds"]:
        name = hit["parameter"]
        log = initial[name].log if name in initial else False
        model = name in problem.parameterization.model_names  # never widened
        where = (
            f"best point on a bound: {name} = {hit['value']:.4g} lies within 1 % of its "
            f"{hit['side']} bound {hit['bound']:g}"
        )
        edge = hit.get("edge")
        if edge is not None and edge["flat"] and edge.get("beyond") is not None:
            searched = log and not model and doc.get("method") != "manual"
            box = "widening the box (--widen-bounds)" if searched else "a wider box"
            lines.append(
                f"{where}, but {box} is unlikely to help (no worthwhile drop beyond "
                f"it): {edge_text(name, edge)}"
            )
            continue
        if edge is not None and edge["flat"]:  # only the step in: a parameter never widened
            lines.append(
                f"{where}, but the cost is flat there: {edge_text(name, edge)}, so a wider "
                "box is unlikely to help"
            )
            continue
        notes = [] if edge is None else [edge_text(name, edge)]
        if not widened and doc.get("method") == "manual":  # no search to widen
            notes.append("a search (another -m) in a wider box could go there")
        elif not widened:
            notes.append(
                "widen the box with --widen-bounds"
                if log and not model
                else "--widen-bounds widens log10 parameters only: give this one a wider "
                "box in the configuration, where the physics allows"
            )
        said = f"{where}; the optimum may lie beyond it" + (
            f" ({'; '.join(notes)})" if notes else ""
        )
        lines.append(said)
    hints = [line for line in lines if line.startswith("best point on a bound:")]
    for line, hit in zip(hints, doc["on_bounds"]):  # one hint per hit, in order
        edge = hit.get("edge") or {}
        rise, threshold = edge.get("rise"), edge.get("threshold")
        if rise is not None and threshold is not None and rise < -threshold:
            # the step in from the bound is lower than the tuned point
            lines[lines.index(line)] = line + UNCONVERGED
    return lines


#: Said after a bound hint whose step in from the bound found a lower cost than the tuned
#: point (by more than the flatness threshold).
UNCONVERGED = (
    " — the step in is lower than the tuned point, so the search had not converged here: "
    "tune again with a larger -n (a new --storage)"
)


def probe_edges(
    problem: TuningProblem, result: OptimizeResult, hits: list[dict[str, Any]], quiet: bool
) -> list[dict[str, Any]]:
    """``hits`` (the best point's bounds, ``on_bounds``) each with the cost one step in
    from its bound and, on a parameter a widening would move, two decades beyond it
    (:func:`kftune.experiment.edge_probes`: one or two filter runs over the training
    manoeuvres per hit and one at the best point), so that the hint can say whether a wider
    box could help; ``hits`` unchanged where the probe could not run (interrupted, or the
    data refused): the hint then says only where the point lies. Unless ``quiet``, says on
    standard error what it runs."""
    from kftune.errors import KftuneError
    from kftune.experiment import edge_probes
    from kftune.space import Space

    if not quiet:
        names = ", ".join(h["parameter"] for h in hits)
        print(
            f"probing the cost in from and beyond the bound of {names} (at most "
            f"{2 * len(hits) + 1} evaluations)…",
            file=sys.stderr,
            flush=True,
        )
    if result.x is None:
        return hits
    try:
        return edge_probes(problem, result.x, hits, Space.from_dict(result.space))
    except KeyboardInterrupt:
        return hits
    except (KftuneError, ValueError):
        return hits


def calibrate(
    problem: TuningProblem, x: Any, criterion: str = DEFAULT_CRITERION
) -> tuple[Calibration | None, str | None]:
    """The covariance scale c fitted by ``criterion`` on the training manoeuvres at the
    tuned point (:func:`kftune.tuning.calibrate.calibrate`, a few filter runs), or (None,
    why not): the filter diverged when scaled, or was interrupted (the tuned file is written
    before)."""
    from kftune.errors import KftuneError
    from kftune.tuning.calibrate import CalibrationError
    from kftune.tuning.calibrate import calibrate as fit

    try:
        return fit(problem, x, criterion=criterion), None
    except KeyboardInterrupt:
        return None, "skipped (interrupted); the tuned parameters are saved uncalibrated"
    except (CalibrationError, KftuneError, ValueError) as exc:
        return None, f"{exc}; the tuned file records the filter uncalibrated"


def stages_record(
    stages: Staging, result: OptimizeResult, noise_x: Any, problem: TuningProblem
) -> dict[str, Any]:
    """The tuned file's ``stages``: how a joint tuning split its budget, and the first
    stage's best — the noise-only filter (its point in the joint space, the model at its
    recorded values; its cost is the joint search's first evaluation)."""
    first = result.history[0] if result.history else None
    return {
        "total": stages.total,
        "noise_budget": stages.noise_budget,
        "joint_budget": stages.joint_budget,
        "noise_storage": None if stages.noise_storage is None else str(stages.noise_storage),
        "noise_only": {
            "cost": first.value if first is not None else None,
            "params": dict(zip(problem.space.names, [float(v) for v in noise_x])),
        },
    }


def stages_line(rec: dict[str, Any]) -> str:
    """What ``tune`` says about a joint tuning's two stages (its ``stages`` record)."""
    cost = rec["noise_only"]["cost"]
    return (
        f"  in two stages: {rec['noise_budget']} evaluations of the noise alone at the "
        "recorded model (best cost "
        + ("failed" if cost is None else f"{cost:.5g}")
        + f"), then {rec['joint_budget']} of the joint search starting from it"
    )


def first_box_best(result: OptimizeResult) -> tuple[float, ...] | None:
    """The best point of a ``--widen-bounds`` run's first round (the box as given), when a
    later round's, in a widened box, is the tuned one; None otherwise."""
    first = [
        r
        for r in result.history
        if r.value is not None and r.info.get("widen_round", 0) == 0 and math.isfinite(r.value)
    ]
    if not first or not any(r.info.get("widen_round", 0) > 0 for r in result.history):
        return None
    best = min(first, key=lambda r: r.value if r.value is not None else math.inf)
    return None if result.fun is None or best.value == result.fun else best.x


def held_out(
    problem: TuningProblem,
    x: Any,
    dataset: Dataset,
    noise_only: Any = None,
    first_box: Any = None,
) -> tuple[dict[str, Any] | None, str | None]:
    """The evidence that the lower training cost is the better filter: the tuned filter and
    the manual rule of thumb (:func:`kftune.experiment.manual_point`) on the dataset's test
    manoeuvres, which the tuning never saw — mean β RMSE [deg] over those with a sideslip
    reference (None where a filter diverged), and the tuned filter's consistency pooled
    over them (with the problem's ``cov_scale``, the calibration) (``consistency``:
    :func:`kftune.tuning.deploy.consistency_docs`, None where it diverged). The manual rule
    is a baseline of accuracy here: its β RMSE, which no calibration moves, so its own c is
    not fitted (``kftune compare`` shows its σ calibrated with its own c, as every filter's).
    Two filter runs over the test split, in this process. With model
    parameters tuned, also the tuned Q on the recorded model
    (``recorded_model_beta_rmse_deg``, :func:`kftune.tuning.generalise.recorded_model_point`),
    and without a test split a leave-one-out over the training manoeuvres instead
    (``split: "train"``, ``cross_validation``: :func:`kftune.tuning.generalise.leave_one_out`).
    ``noise_only``: the first stage's best of a two-stage joint tuning (a point of the
    joint space, the model at its recorded values), scored alike
    (``noise_only_beta_rmse_deg``, calibrated with the same c). ``first_box``: after
    ``--widen-bounds``, the best point in the box as given (:func:`first_box_best`), scored
    alike (``first_box_beta_rmse_deg``): a wider box fits the training manoeuvres better and
    may predict the others worse (a yaw-rate noise beyond 1 (rad/s)² per step, a speed
    sensor's R ten thousand times its estimate).

    Returns:
        (evidence, why not): evidence None without test manoeuvres or sideslip output (no
        reason given: ``kftune evaluate --split test`` scores the measured channels), or
        with the reason when they could not be scored (the tuned file is written before).
    """
    from kftune.errors import KftuneError
    from kftune.experiment import manual_point
    from kftune.tuning.deploy import consistency_docs
    from kftune.tuning.generalise import leave_one_out, recorded_model_point
    from kftune.tuning.kpi import average_kpis
    from kftune.tuning.problem import assess
    from kftune.tuning.runs import first_scored, output_names

    joint = bool(problem.parameterization.model_names)
    if "beta" not in output_names(problem.model):
        return None, None
    if not dataset.test:
        if not joint or len(problem.manoeuvres) < 2:
            return None, None
        try:
            cv = leave_one_out(problem, x)
        except KeyboardInterrupt:
            return None, "skipped (interrupted); the tuned parameters are saved"
        except (KftuneError, ValueError) as exc:
            return None, f"the cross-validation could not be run ({exc})"
        return {"split": "train", "cross_validation": cv}, None
    test = [
        m for m in dataset.test if m.has("beta_ref") and m.n - first_scored(m, problem.burn_in) >= 2
    ]
    if not any(m.has("beta_ref") for m in dataset.test):
        return None, (
            "the held-out β check needs a sideslip reference, a beta_ref channel, which "
            "none of the test manoeuvres has; kftune evaluate --split test (below) scores "
            "the tuned filter on their measured channels"
        )
    if not test:
        return None, "no test manoeuvre has a sideslip reference longer than the burn-in"
    rmse: dict[str, float | None] = {}
    consistency = None
    scale = problem.cov_scale
    points = [("tuned", x), ("manual", manual_point(problem.parameterization))]
    if joint:  # the tuned noise on the model the user was handed (calibrated alike)
        points.append(("recorded_model", recorded_model_point(problem, x)))
    if noise_only is not None:  # the noise tuned alone at that model (calibrated alike)
        points.append(("noise_only", noise_only))
    if first_box is not None:  # the best before the box was widened (calibrated alike)
        points.append(("first_box", first_box))
    try:
        for key, point in points:
            problem.cov_scale = 1.0 if key == "manual" else scale
            metrics, runs = assess(problem, point, test)
            if key == "tuned":  # pooled over the test manoeuvres, None if it diverged
                consistency = consistency_docs(problem, test, runs)[1]
            if not all("rmse" in row for row in metrics.values()):
                return None, None  # a model without the sideslip KPIs' channels
            avg = average_kpis(metrics.values())
            rmse[key] = None if math.isnan(avg["rmse"]) else avg["rmse"]
    except KeyboardInterrupt:
        return None, "skipped (interrupted); the tuned parameters are saved"
    except (KftuneError, ValueError) as exc:
        return None, f"the test manoeuvres could not be scored ({exc})"
    finally:
        problem.cov_scale = scale
    return {
        "split": "test",
        "n_manoeuvres": len(test),
        "n_left_out": len(dataset.test) - len(test),
        "beta_rmse_deg": rmse["tuned"],
        "manual_beta_rmse_deg": rmse["manual"],
        **({"recorded_model_beta_rmse_deg": rmse["recorded_model"]} if joint else {}),
        **({"noise_only_beta_rmse_deg": rmse["noise_only"]} if noise_only is not None else {}),
        **({"first_box_beta_rmse_deg": rmse["first_box"]} if first_box is not None else {}),
        "consistency": consistency,
        "calibration_factor": scale,
    }, None


def held_out_line(h: dict[str, Any], cost: dict[str, Any] | None = None) -> str:
    """What ``tune`` says about the held-out test manoeuvres; where the tuned filter is the
    worse one, a hint that fits the cost it was tuned on (``cost``: the tuned file's
    ``cost_spec``; None: no hint about the cost): ``--normalise dataset`` only for the
    NRMSE normalised per manoeuvre (it is refused for other costs, and is no news when it
    was given)."""

    def deg(v: float | None) -> str:
        return "diverged" if v is None else f"{v:.3f}°"

    if h.get("split") == "train":
        return cross_validation_line(h["cross_validation"])
    tuned, manual = h["beta_rmse_deg"], h["manual_beta_rmse_deg"]
    first = h.get("first_box_beta_rmse_deg", "absent")
    if first != "absent":  # --widen-bounds moved the best point out of the given box
        line = held_out_line({k: v for k, v in h.items() if k != "first_box_beta_rmse_deg"}, cost)
        line += f"\n  best in the box as given (before --widen-bounds): β RMSE {deg(first)}"
        if first is not None and (tuned is None or tuned > first * WORSE_RMSE):
            worse = "diverged" if tuned is None else f"{100 * (tuned / first - 1):.1f} % worse"
            line += (
                f"{WARN}the widened box's filter is {worse} on the held-out manoeuvres "
                "than the best in the box as given: the wider box fitted the training "
                "manoeuvres, not the car. To deploy the first box's filter, run the same "
                "tune without --widen-bounds, with --storage STUDY --resume (its first study "
                "is complete: it ends at once)"
            )
        return line
    recorded = h.get("recorded_model_beta_rmse_deg", "absent")
    if recorded != "absent":  # model parameters tuned with the noise
        joint_keys = ("recorded_model_beta_rmse_deg", "noise_only_beta_rmse_deg")
        line = held_out_line({k: v for k, v in h.items() if k not in joint_keys}, cost)
        noise = h.get("noise_only_beta_rmse_deg", "absent")
        if noise != "absent":  # the first stage of a two-stage joint tuning
            line += (
                "\n  noise-only filter (the noise tuned alone at the recorded model, first "
                f"stage): β RMSE {deg(noise)}"
            )
        line += f"\n  tuned Q on the recorded model: β RMSE {deg(recorded)}"
        if noise not in ("absent", None) and (tuned is None or tuned > noise * WORSE_RMSE):
            worse = "diverged" if tuned is None else f"{100 * (tuned / noise - 1):.1f} % worse"
            line += (
                f"{WARN}the joint filter is {worse} on the held-out manoeuvres than the "
                "noise-only one; the tuned file keeps the joint filter (choosing by these "
                "data would leave no held-out evidence): tune without --tune-model to deploy "
                "the noise alone, or tune on more varied manoeuvres"
            )
        if recorded is not None and (tuned is None or tuned > recorded * WORSE_RMSE):
            line += (
                f"{WARN}the tuned model parameters make the filter worse on the held-out "
                "manoeuvres than the recorded ones with the same Q: they fit the training "
                "manoeuvres, not the car (tune fewer, or on more varied manoeuvres)"
            )
        if manual is not None and (tuned is None or tuned > manual):
            line += f"{WARN}the joint filter is worse there than the manual rule of thumb"
        return line
    behind = manual is not None and (tuned is None or tuned > manual)
    left_out = h.get("n_left_out", 0)
    return (
        f"on the {h['n_manoeuvres']} held-out test manoeuvres"
        + (f" with a sideslip reference ({left_out} without)" if left_out else "")
        + f": β RMSE {deg(tuned)} (manual rule of thumb {deg(manual)})"
        + (
            "; the tuned filter is the worse one there — the search stopped early (a larger "
            "-n), or the cost is a poor proxy on these data" + _cost_hint(cost)
            if behind
            else ""
        )
    )


def cross_validation_line(cv: dict[str, Any]) -> str:
    """What ``tune`` says about the leave-one-out of the tuned model parameters (no test
    split): mean β RMSE of the refitted, joint and recorded-model filters, and a warning
    where refitting without a manoeuvre predicts it worse than the recorded model."""

    def deg(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}°"

    n = len(cv["manoeuvres"])
    line = (
        f"leave-one-out over the {n} training manoeuvres (no test split): β RMSE of each left "
        f"out with the model parameters refitted on the others {deg(cv['mean_refit'])}, with "
        f"the tuned Q on the recorded model {deg(cv['mean_recorded_model'])} (the joint "
        f"filter, fitted on all of them: {deg(cv['mean_joint'])}, in-sample)"
    )
    refit, recorded = cv["mean_refit"], cv["mean_recorded_model"]
    if refit is not None and recorded is not None and refit > recorded:
        line += (
            f"{WARN}model parameters fitted without a manoeuvre predict it worse than the "
            "recorded ones: they fit the training manoeuvres, not the car"
        )
    return line


def _cost_hint(cost: dict[str, Any] | None) -> str:
    """What to try when the tuned cost was a poor proxy for β (see :func:`held_out_line`)."""
    if cost is None:
        return ""
    kind = cost.get("kind")
    if kind == "nrmse":
        return " (try --normalise dataset)" if cost.get("normalise") != "dataset" else ""
    if kind in ("nis", "pem", "msp"):
        return f" (the {kind} cost scores the innovations, not β: try --cost nrmse)"
    return ""


def held_out_consistency_line(h: dict[str, Any]) -> str | None:
    """Whether the tuned filter's β σ can be trusted on the held-out test manoeuvres: its
    ±1.96σ coverage and mean NEES pooled over them (``h["consistency"]``, as ``kftune
    evaluate`` measures it), with what a consistent filter gives; None when not measured
    (the filter diverged there, or a tuned file of an older kftune)."""
    from kftune.report.tables import sigma_verdict

    beta = ((h.get("consistency") or {}).get("channels") or {}).get("beta")
    if not beta or beta["cov95"] is None or beta["nees"]["mean"] is None:
        return None
    nees = beta["nees"]
    verdict = sigma_verdict(nees)
    return (
        f"  β ±1.96σ covers {100 * beta['cov95']:.0f} % of the held-out errors (95 % if "
        f"consistent), mean NEES {nees['mean']:.3g} (1 if consistent); "
        + ("σ can be trusted there" if verdict == "consistent" else verdict)
    )


def identifiability(
    problem: TuningProblem, x: Any, *, quiet: bool = False
) -> tuple[Identifiability | None, str | None]:
    """Whether the training manoeuvres determine each tuned model parameter: its value
    against the start, whether it sits on a bound, and the cost's profile around the tuned
    point (:func:`kftune.tuning.identify.identify_problem`; at most 10 filter runs over the
    training manoeuvres per parameter and one per pair of them, in this process), or
    (None, why not); (None, None) when no model parameter was tuned. Unless ``quiet``, says
    on standard error what it runs (it takes as long as that many evaluations)."""
    from kftune.errors import KftuneError
    from kftune.tuning.identify import MAX_EVALS_PER_PARAMETER, identify_problem

    names = problem.parameterization.model_names
    if not names:
        return None, None
    k = len(names)
    if not quiet:
        print(
            f"profiling the cost around the tuned point for {', '.join(names)} (at most "
            f"{MAX_EVALS_PER_PARAMETER * k + 1 + k * (k - 1) // 2} evaluations)…",
            file=sys.stderr,
            flush=True,
        )
    try:
        return identify_problem(problem, x), None
    except KeyboardInterrupt:
        return None, "skipped (interrupted); the tuned parameters are saved"
    except (KftuneError, ValueError) as exc:
        return None, f"{exc}; the tuned parameters are saved"


def _interrupted(
    args: argparse.Namespace,
    result: OptimizeResult | None = None,
    problem: TuningProblem | None = None,
    dataset: Dataset | None = None,
    failure: str | None = None,
) -> None:
    """Ctrl-C, or a run that cannot go on (``failure`` says why: a lost Dask scheduler):
    say what was kept, save the best point so far, and how to go on."""
    if failure is not None:
        lines = [f"kftune: failed: {failure}"]
    elif result is None:
        lines = ["kftune: interrupted"]  # how many ran is the study's to say
    else:
        lines = [f"kftune: interrupted after {result.n_evals} evaluations"]
    if result is not None and result.x is not None and problem is not None and dataset is not None:
        partial = _partial(args.out)
        doc = tuned_document(result, problem, dataset, partial)
        try:
            write_output(partial, json.dumps(doc, indent=1, allow_nan=False) + "\n", "--out")
            lines.append(f"best cost so far {result.fun:.5g}, its parameters written to {partial}")
        except RunFailedError as exc:
            lines.append(f"best cost so far {result.fun:.5g}; {exc}")
    from kftune.experiment import noise_stage_storage

    # a two-stage joint tuning keeps its first stage beside --storage
    first = noise_stage_storage(args.storage)
    saved = [p for p in (first, args.storage) if p is not None and p.exists()]
    if args.storage is not None and not saved:
        lines.append(f"no study was started in {args.storage}; run the same command again")
    elif args.storage is not None:
        again = ["kftune", *getattr(args, "argv", ["tune"]), *([] if args.resume else ["--resume"])]
        lines.append(
            "every finished evaluation"
            + ("" if result is None or len(saved) > 1 else f" ({result.n_evals})")
            + f" is saved in {' and '.join(map(str, saved))}; continue with the same command"
            + ("" if args.resume else " plus --resume")
            + f": {shlex.join(again)}"
        )
    else:
        lines.append("nothing else was saved (run with --storage FILE to be able to resume)")
    print("\n".join(lines), file=sys.stderr)


def _partial(out: Path) -> Path:
    """Where an interrupted run leaves its best point so far (``tuned.partial.json``)."""
    return out.with_name(out.stem + ".partial" + out.suffix)


def _kept(args: argparse.Namespace) -> str:
    """What keeps a run's evaluations besides the tuned file, for error messages."""
    if args.storage is None:
        return ""
    return f"every evaluation is saved in the study {args.storage}"


def tuned_document(
    result: OptimizeResult, problem: TuningProblem, dataset: Dataset, out: Path
) -> dict[str, Any]:
    """The tuned-parameters file written to ``out``: what was found, and how, in strict
    JSON; ``deployment`` holds everything needed to run the filter elsewhere (``kftune
    export``, see :func:`kftune.tuning.deploy.deployment_record`). A model file is recorded
    so that it is found from the file's folder (:func:`~kftune.cli._common.model_file_for`)."""
    from kftune.experiment import on_bounds, require_success
    from kftune.tuning.deploy import deployment_record, model_params_record

    x, _ = require_success(result, result.method)
    q, r, ukf = problem.decode(x)
    model = model_file_for(problem.model_spec, out)
    return {
        "format": TUNED_FORMAT,
        "kftune_version": __version__,
        "dataset": dataset.name,
        "method": result.method,
        "seed": result.seed,
        "cost": result.fun,
        "held_out": None,  # filled in by tune after the file is first written
        "cost_spec": {
            "kind": problem.cost_spec.kind,
            "weights": dict(problem.cost_spec.weights),
            "estimate": problem.cost_spec.estimate,
            "normalise": problem.cost_spec.normalise,
        },
        "burn_in": problem.burn_in,
        "model": model,
        "filter": problem.filter,
        "states": list(problem.model.state_names),
        "measurements": list(problem.model.measurement_names),
        "n_evals": result.n_evals,
        "n_failed": result.n_failed,
        "status": result.status,
        "params": result.params,
        # the model parameters tuned with the noise: value, recorded start, box, scale
        "model_params": model_params_record(problem, result.x),
        "search_space": result.space,
        "on_bounds": on_bounds(result),
        "q": q.tolist(),
        "r": r.tolist(),
        "ukf": {"alpha": ukf.alpha, "beta": ukf.beta, "kappa": ukf.kappa},
        "calibration": None,  # filled in by tune after the file is first written
        "deployment": {
            **deployment_record(problem, result.x, dataset),
            "model": model,
            "calibration": None,
        },
    }
