"""``kftune compare``: the paper's experiment from one command.

Tunes the UKF on the training manoeuvres with manual tuning, a genetic algorithm, TSBO with
a GP and TSBO with a Student-t process (or the methods you name), evaluates every tuned
filter on the training and test manoeuvres, and writes a report directory: ``report.md``,
``figures/*.png``, ``tables/*.csv``, ``results.json`` and one SQLite study per method under
``studies/`` (``--resume`` continues them after an interruption).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from kftune.cli import EXIT_OK
from kftune.cli._common import (
    add_command,
    add_common,
    cost_spec,
    emit_json,
    load_config,
    parameterization,
    pick,
)
from kftune.errors import ConfigError
from kftune.optim import METHODS


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
        help="methods in report order (default: the paper's four: manual ga tsbo-gp "
        f"tsbo-tsp); any of {', '.join(METHODS)}",
    )
    p.add_argument(
        "--budget",
        action="append",
        metavar="METHOD=N",
        help="evaluation budget of a method, e.g. --budget ga=225 --budget tsbo-tsp=40 "
        "(defaults: TSBO 40, GA 225, manual 1, others 40)",
    )
    p.add_argument(
        "--resume", action="store_true", help="continue the studies stored in --out/studies"
    )
    p.set_defaults(func=run)


def _budgets(items: list[str] | None) -> dict[str, int]:
    out: dict[str, int] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or name not in METHODS or not value.strip().isdigit():
            raise ConfigError(
                f"--budget: expected METHOD=N with METHOD one of {list(METHODS)}, got {item!r}"
            )
        out[name] = int(value)
    return out


def run(args: argparse.Namespace) -> int:
    """Run ``kftune compare``."""
    from kftune.data import open_dataset
    from kftune.experiment import CompareSettings, run_compare
    from kftune.report import all_tables, write_report

    config = load_config(args.config)
    dataset = open_dataset(pick(args, config, "dataset", None))
    methods = args.methods or config.get("methods")
    settings = CompareSettings(
        **({"methods": tuple(methods)} if methods else {}),
        seed=pick(args, config, "seed", 0),
        budgets=_budgets(args.budget),
        cost=cost_spec(args, config),
        parameterization=parameterization(args, config),
        workers=pick(args, config, "workers", 1),
        method_options=config.get("options", {}),
    )
    results = run_compare(
        dataset,
        args.out,
        settings,
        resume=args.resume,
        progress=False if (args.quiet or args.json) else None,
    )
    report = write_report(results, args.out)
    tables = all_tables(results)
    if args.json:
        emit_json(
            {
                "report": str(report),
                "results": str(args.out / "results.json"),
                "tables": {k: t.to_records() for k, t in tables.items() if k != "per_manoeuvre"},
            }
        )
    else:
        for key in ("cost", "kpi_train", "kpi_test"):
            if key in tables:
                print(f"\n{tables[key].title}\n\n{tables[key].to_markdown()}")
        print(f"\nreport written to {report}")
    return EXIT_OK
