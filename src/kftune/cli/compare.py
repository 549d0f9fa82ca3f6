"""``kftune compare``: the paper's experiment from one command.

Tunes the UKF on the training manoeuvres with manual tuning, a genetic algorithm, TSBO with
a GP and TSBO with a Student-t process (the paper's four) and, beside them, kftune's default
tuner TR-BO (or the methods you name), evaluates every tuned filter on the training and test
manoeuvres, and writes a report directory: ``report.md``,
``figures/*.png``, ``tables/*.csv``, ``results.json`` and one SQLite study per method under
``studies/`` (``--resume`` continues them after an interruption).

The KPIs are the paper's, in degrees: RMSE, MAE — the maximum absolute error, not the
mean — and both over the samples with |ay| ≥ 4 m/s² (_NON). For a model without the
sideslip output beta (--model ctrv, a model file) or data without beta_ref, they are the
RMSE of each scored channel against its reference <channel>_ref (the cost's channels; every
measurement, against the measured channel, for the nis, pem and msp costs), in the
channel's unit, and the figures show those channels over time. And whether each tuned
filter's standard deviations can be trusted, pooled over the test manoeuvres: for β (each
channel with a reference) the share of errors inside ±1σ and ±1.96σ (68.3 % and 95 % when
consistent), the mean NEES (1) and NIS (m) with their 95 % bands (tables/consistency_test.csv),
and a reliability figure of observed against nominal coverage. Each filter, the manual one
too, is shown calibrated as kftune tune deploys it: its covariances times the factor c
fitted on the training manoeuvres (its estimate, and every KPI, unchanged); there is no
--no-calibration here (tune, evaluate and estimate have it). results.json and report.md
record the command line, every option of every method (defaults included), the package
versions, the dataset's SHA-256 fingerprint and the machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from kftune.cli._common import (
    MAX_BUDGET,
    add_command,
    add_common,
    budgets,
    burn_in,
    cost_spec,
    emit_json,
    filter_spec_of,
    load_config,
    model_choice,
    parameterization,
    pick,
)
from kftune.cli.exit_codes import EXIT_INTERRUPTED, EXIT_OK
from kftune.cli.outputs import command_inputs, output_dir, writing
from kftune.errors import ConfigError, UsageError, excerpt
from kftune.optim import COMPARE_METHODS, DEFAULT_METHOD, METHODS


def register(subparsers: Any) -> None:
    """Add ``compare``."""
    p = add_command(
        subparsers,
        "compare",
        "the paper's experiment: tune with several methods, evaluate, write a report",
        __doc__,
    )
    add_common(p)
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        default=Path("report"),
        help="report directory (default ./report)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        choices=METHODS,
        metavar="METHOD",
        help=f"methods in report order (default: {' '.join(COMPARE_METHODS)} — the paper's "
        f"four and kftune's default tuner); any of {', '.join(METHODS)}",
    )
    p.add_argument(
        "--budget",
        action="append",
        type=_budget,
        metavar="METHOD=N",
        help="evaluation budget of one method, e.g. --budget trbo=12; repeat it for more: "
        "--budget ga=225 --budget tsbo-tsp=40 (defaults: TSBO 40, GA 225, manual 1, "
        "others 40)",
    )
    again = p.add_mutually_exclusive_group()
    again.add_argument(
        "--resume", action="store_true", help="continue the studies stored in --out/studies"
    )
    again.add_argument(
        "--force",
        action="store_true",
        help="delete the studies stored in --out/studies and start afresh (only files of "
        "studies kftune made; a foreign file named like a study is refused)",
    )
    p.set_defaults(func=run)


def _budget(item: str) -> tuple[str, int]:
    """argparse type of ``--budget METHOD=N`` (errors exit with code 2; a bare N, as
    ``tune --budget`` takes, is refused too: the methods' defaults differ)."""

    def count(text: str) -> int:
        text = text.strip()
        return int(text) if text.isascii() and text.isdigit() else 0

    name, sep, value = item.partition("=")
    if not sep or name not in METHODS or not 1 <= count(value) <= MAX_BUDGET:
        n = count(value or item)
        n = n if 1 <= n <= MAX_BUDGET else 12
        example = f"{name if name in METHODS else DEFAULT_METHOD}={n}"
        raise argparse.ArgumentTypeError(
            f"expected METHOD=N, a budget per method, e.g. --budget {example} (repeat it for "
            f"more), with 1 <= N <= {MAX_BUDGET} and METHOD one of {', '.join(METHODS)}; got "
            f"{excerpt(item)}"
        )
    return name, count(value)


def run(args: argparse.Namespace) -> int:
    """Run ``kftune compare``."""
    from kftune.data import open_dataset
    from kftune.experiment import CompareSettings, run_compare
    from kftune.report import all_tables, write_report
    from kftune.report.provenance import command_line

    config = load_config(args.config, "compare")
    if args.methods and len(set(args.methods)) != len(args.methods):
        raise UsageError(f"--methods: a method listed twice: {args.methods}")
    output_dir(args.out, "--out", command_inputs(args, config))
    dataset = open_dataset(pick(args, config, "dataset", None))
    fs = filter_spec_of(args, config, dataset.vehicle, dataset=dataset.name)  # stops here, named
    methods = pick(args, config, "methods", None)
    idle = [m for m, _ in args.budget or [] if m not in (methods or COMPARE_METHODS)]
    if idle:
        raise UsageError(
            f"--budget {idle[0]}=…: {idle[0]} is not among the methods run "
            f"({' '.join(methods or COMPARE_METHODS)}); add it with --methods or drop the budget"
        )
    chosen: dict[str, Any] = {"methods": tuple(methods)} if methods else {}
    settings = CompareSettings(
        **chosen,
        seed=pick(args, config, "seed"),
        budgets=budgets(args.budget, config),
        cost=cost_spec(args, config),
        parameterization=parameterization(args, config, fs.model),  # its tune_model names
        workers=pick(args, config, "workers"),
        burn_in=burn_in(args, config),
        method_options=config.get("options", {}),
        model=model_choice(args, config)[0],
        filter=model_choice(args, config)[1],
        r0=pick(args, config, "r0", {}),
    )
    studies = args.out / "studies"
    if args.resume and not any(studies.glob("*.db")):
        raise ConfigError(
            f"--resume: {studies} holds no study to continue (a misspelt --out would start "
            "afresh); leave out --resume to start there"
        )
    keep = (
        f"every finished evaluation is saved in {studies}; once that is fixed, the same "
        "command plus --resume writes the report without tuning again"
    )
    try:
        with writing(f"the report to {args.out}", keep):
            results = run_compare(
                dataset,
                args.out,
                settings,
                resume=args.resume,
                force=args.force,
                progress=False if (args.quiet or args.json) else None,
                command=command_line(getattr(args, "argv", [])),
            )
            report = write_report(results, args.out)
    except KeyboardInterrupt as stop:
        partial = getattr(stop, "result", None)  # an OptimizationInterrupted's partial run
        during = f" during {partial.method} after {partial.n_evals} evaluations" if partial else ""
        if not any(studies.glob("*.db")):
            hint = "no study was started yet; run the same command again"
        else:
            hint = (
                f"every finished evaluation is saved in {studies}; continue with the same "
                "command" + ("" if args.resume else " plus --resume")
            )
        print(f"kftune: interrupted{during}; {hint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    tables = all_tables(results)
    if args.json:
        emit_json(
            {
                "report": str(report),
                "results": str(args.out / "results.json"),
                "tables": {k: t.to_records() for k, t in tables.items()},
            }
        )
    else:
        consistency = [k for k in tables if k.startswith("consistency_")]
        for key in ("cost", "kpi_train", "kpi_test", *consistency):
            if key in tables:
                print(f"\n{tables[key].title}\n\n{tables[key].to_markdown()}")
        print(f"\nreport written to {report}")
    for m in results.methods:  # the KPI tables say it too; not a failure of the experiment
        for split, avg in m.averages.items():
            if avg.get("n_diverged", 0):
                print(
                    f"kftune: warning: the filter tuned by {m.key} diverged or ran away on "
                    f"{int(avg['n_diverged'])} of {int(avg['n_manoeuvres'])} {split} "
                    "manoeuvres; its average KPIs there are undefined (per-manoeuvre table: "
                    "column 'diverged')",
                    file=sys.stderr,
                )
    return EXIT_OK
