"""``kftune export``: write a tuned filter for deployment.

Reads a tuned-parameters file written by ``kftune tune`` and writes what embedded code
needs — model, filter, sample time dt [s], the diagonals of Q (variance per step of dt) and
R named by state and measurement with their units, the sigma-point settings, the model's
parameter vector and the vehicle, the initial-state rule, and where it came from (method,
dataset name and SHA-256 fingerprint, kftune versions) — as

  json    one flat JSON object
  yaml    the same mapping as YAML (written by kftune itself; no PyYAML needed)
  c       a C header of macros only: scalars, arrays as C99 compound literals
          (KFTUNE_Q_DIAG[i], KFTUNE_R_DIAG, KFTUNE_MODEL_PARAMS) and their initialisers
          (static const double q[] = KFTUNE_Q_DIAG_INIT;), index macros per state and
          measurement, units in comments, an include guard named after --out; names
          that differ only in case or punctuation are refused (they would be one macro)
  matlab  a MATLAB/Octave script that builds the struct kf (kf.Q, kf.R, kf.dt, ...)

The export applies the tuned file's calibration: a calibrated filter (kftune tune fits a
covariance scale c by default; c = 1 after tune --no-calibration) runs with the tuned Q and
R as written; c (covariance_scale, KFTUNE_COVARIANCE_SCALE) multiplies every
covariance it reports: P (σ by √c) and S (for the NIS and gating). Do not run it with c·Q
and c·R: that moves a UKF's estimate.

Every number is written with the shortest decimal that reads back as the same double.
Files written before 'kftune export' existed lack the sample time and vehicle: tune again.
"""

from __future__ import annotations

import argparse
import re
import sys
import warnings
from pathlib import Path
from typing import Any

from kftune.cli._common import add_command, command_inputs, output_file, write_output
from kftune.cli.exit_codes import EXIT_OK
from kftune.errors import DataWarning, UsageError

FORMATS = ("json", "yaml", "c", "matlab")
SUFFIXES = {"json": ".json", "yaml": ".yaml", "c": ".h", "matlab": ".m"}


def register(subparsers: Any) -> None:
    """Add ``export``."""
    p = add_command(
        subparsers,
        "export",
        "write a tuned filter as JSON, YAML, a C header or a MATLAB script",
        __doc__,
    )
    p.add_argument("params", type=Path, help="tuned-parameters file ('kftune tune')")
    p.add_argument(
        "--format", "-f", choices=FORMATS, default="json", help="what to write (default json)"
    )
    p.add_argument(
        "--out",
        "-o",
        type=Path,
        help="output file (default: PARAMS with the format's suffix: .json → "
        "PARAMS.filter.json, .yaml, .h, .m); '-' for standard output",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``kftune export``."""
    from kftune.cli.evaluate import read_tuned
    from kftune.report.export import export_document, render
    from kftune.tuning.deploy import model_file_changed

    out = args.out
    if out is None:
        suffix = SUFFIXES[args.format]
        stem = args.params.stem + (".filter" if suffix == ".json" else "")
        out = args.params.with_name(stem + suffix)
    if str(out) != "-":
        output_file(out, "--out", command_inputs(args, {}))
    elif sys.stdout is None:  # closed before Python started (kftune export … >&-)
        raise UsageError("--out -: standard output is closed; name a file with --out")
    source = args.params.name
    tuned = read_tuned(args.params)
    changed = model_file_changed(tuned)
    if changed:  # the deployed model code is the file's, as it is now
        warnings.warn(
            f"{args.params}: {changed}; the export is of the tuned values",
            DataWarning,
            stacklevel=2,
        )
    doc = export_document(tuned, str(args.params))
    guard = re.sub(r"[^0-9A-Za-z]+", "_", "x" if str(out) == "-" else out.name).upper()
    text = render(doc, args.format, source, guard=f"KFTUNE_{guard.strip('_')}")
    if str(out) == "-":
        print(text, end="")
    else:
        write_output(out, text, "--out")
        print(f"{args.format} export of {args.params} written to {out}")
    return EXIT_OK
