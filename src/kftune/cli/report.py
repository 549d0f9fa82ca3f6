"""``kftune report``: rebuild a report from stored results, without re-running anything.

Reads ``results.json`` and ``traces.npz`` from a directory written by ``kftune compare`` and
writes ``report.md``, ``figures/`` and ``tables/`` (into the same directory unless ``--out``
names another). Results written before the consistency of the tuned filters was measured
still rebuild their report, which says it is not recorded.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from kftune.cli._common import add_command, emit_json
from kftune.cli.exit_codes import EXIT_OK
from kftune.cli.outputs import output_dir, writing


def register(subparsers: Any) -> None:
    """Add ``report``."""
    p = add_command(
        subparsers, "report", "rebuild the report from stored results (no re-running)", __doc__
    )
    p.add_argument(
        "results",
        type=Path,
        help="directory holding results.json (for one tune run's study: kftune study show)",
    )
    p.add_argument("--out", "-o", type=Path, help="write the report here (default: RESULTS)")
    p.add_argument("--json", action="store_true", help="print the tables as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``kftune report``."""
    from kftune.report import ExperimentResults, all_tables, write_report
    from kftune.report.results import TRACES_FILE
    from kftune.report.tables import scored_channels

    if args.results.is_file():
        from kftune.cli.study import not_a_study_hint
        from kftune.errors import ConfigError
        from kftune.optim.study import is_study

        if is_study(args.results):
            raise ConfigError(
                f"{args.results} is a study (tune --storage): report rebuilds a compare "
                f"run's folder; look at the study with kftune study show {args.results} "
                f"(kftune study plot {args.results} -o DIR for its figures)"
            )
        hint = not_a_study_hint(args.results)
        if hint is not None:
            raise ConfigError(f"{hint}; report rebuilds a compare run's folder")
    results = ExperimentResults.load(args.results)
    if not results.traces:
        which = (
            "β figures (paper Figs. 8–10)"
            if scored_channels(results) is None
            else "figures of the estimated channels"
        )
        print(
            f"kftune: warning: no {TRACES_FILE} beside results.json in {args.results}: the "
            f"{which} are left out",
            file=sys.stderr,
        )
    out = output_dir(args.out or args.results, "--out")
    with writing(f"the report to {out}", f"the results in {args.results} are unchanged"):
        path = write_report(results, out)
    if args.json:
        tables = all_tables(results)
        emit_json({"report": str(path), "tables": {k: t.to_records() for k, t in tables.items()}})
    else:
        print(f"report written to {path}")
    return EXIT_OK
