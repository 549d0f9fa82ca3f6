"""``kftune export``: write a tuned filter for deployment.

Reads a tuned-parameters file written by ``kftune tune`` and writes

  c       a folder (-o DIR, default PARAMS_c) holding the filter as C99 that runs and
          reproduces kftune estimate: kftune_filter.h/.c (the UKF or EKF step with the
          tuned Q, R, model parameters, dt, sigma points and covariance scale; the init/step
          API and the filter's conventions in the header's comments; the tuned values also
          as the KFTUNE_* macros), kftune_model.h/.c (the model's C), kftune_demo.c (reads
          a manoeuvre's uncompressed CSV on stdin: gzip -dc FILE.csv.gz | DIR/kftune_demo
          for a dataset's gzipped files; writes the columns of kftune estimate on stdout) and
          a Makefile (make builds kftune_demo with cc -std=c99 -O2 -Wall -Wextra -Werror
          -pedantic; make asan with the sanitizers). Only libm is needed and nothing is
          allocated. --precision float computes in float (for targets without a double
          FPU). The model must carry its C (the built-in models do; a model file's
          StateSpaceModel(c_code=...)): one without is refused, naming the reason.
          --check DATASET builds the demo with the C compiler ($CC, else cc) and compares
          every column with kftune's own estimate on the DATASET's --split (default test):
          the worst relative deviation ||C - kftune|| / ||kftune|| per manoeuvre; for
          float also, per column, the largest deviation in the column's own terms (a state
          or beta in units of its sigma, a sigma relative, an innovation in units of
          sqrt(R), the NIS absolutely) against the stated bounds (0.1 sigma, 10 %, 0.1
          sqrt(R), 0.5). Exit 1 when a double export is off by more than 1e-9, a float
          one is beyond a bound, or either stops elsewhere than kftune's filter
  json    the tuned values as one flat JSON object: model, filter, sample time dt [s], the
          diagonals of Q (variance per step of dt) and R named by state and measurement with
          their units, the sigma-point settings, the model's parameter vector and the
          vehicle, the initial-state rule, and where it came from (method, dataset name and
          SHA-256 fingerprint, kftune versions)
  yaml    the same mapping as YAML (written by kftune itself; no PyYAML needed)
  matlab  a MATLAB/Octave script that builds the struct kf of those numbers (kf.Q, kf.R,
          kf.dt, ...): numbers only, no f, h or filter step (C is the export that runs)

The export applies the tuned file's calibration: a calibrated filter (kftune tune fits a
covariance scale c by default; c = 1 after tune --no-calibration) runs with the tuned Q and
R as written; c (covariance_scale, KF_COV_SCALE) multiplies every covariance it reports:
P (σ by √c) and S (for the NIS and gating). Do not run it with c·Q and c·R: that moves a
UKF's estimate.

Every number is written with the shortest decimal that reads back as the same double.
Files written before 'kftune export' existed lack the sample time and vehicle: tune again.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path
from typing import Any

from kftune.cli._common import add_command, emit_json, split_model_file
from kftune.cli.exit_codes import EXIT_FAILURE, EXIT_OK
from kftune.cli.outputs import (
    Input,
    command_inputs,
    dataset_inputs,
    output_dir,
    output_file,
    refuse_inputs,
    write_output,
)
from kftune.errors import ConfigError, DataWarning, UsageError, excerpt

FORMATS = ("json", "yaml", "c", "matlab")
SUFFIXES = {"json": ".json", "yaml": ".yaml", "matlab": ".m"}
SPLITS = ("train", "test", "all")
#: What a C export folder may hold besides its files, replaced without --force: the
#: programs its Makefile builds.
BUILT = ("kftune_demo", "kftune_demo_asan")


def register(subparsers: Any) -> None:
    """Add ``export``."""
    p = add_command(
        subparsers,
        "export",
        "write a tuned filter as C that runs, or its numbers as JSON, YAML or MATLAB",
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
        help="output file (json, yaml, matlab; default PARAMS with the format's suffix: "
        ".json → PARAMS.filter.json, .yaml, .m; '-' for standard output), or for c the "
        "folder (default PARAMS_c)",
    )
    c = p.add_argument_group("c")
    c.add_argument(
        "--model",
        metavar="FILE.py[:VAR]",
        help="c: the model file the filter was tuned with, when it is one (a built-in "
        "model comes from PARAMS): a model file is Python code that runs with your rights, "
        "so kftune runs it only when you name it here",
    )
    c.add_argument(
        "--precision",
        choices=("double", "float"),
        help="c: the type the filter computes in (default double)",
    )
    c.add_argument(
        "--check",
        metavar="DATASET",
        help="c: build the demo with the C compiler ($CC, else cc) and compare it with "
        "kftune's estimate on this dataset ('default': the bundled one)",
    )
    c.add_argument(
        "--split", choices=SPLITS, help="c --check: the manoeuvres compared (default test)"
    )
    c.add_argument(
        "--force",
        action="store_true",
        help="c: write into a folder that holds other files (they are kept)",
    )
    p.add_argument("--json", action="store_true", help="c: print one JSON object on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``kftune export``."""
    if args.format == "c":
        return _run_c(args)
    for option in ("model", "precision", "check", "split"):
        if getattr(args, option) is not None:
            raise UsageError(f"--{option} is an option of --format c (the C filter)")
    if args.force or args.json:
        raise UsageError(f"--{'force' if args.force else 'json'} is an option of --format c")
    return _run_numbers(args)


def _run_numbers(args: argparse.Namespace) -> int:
    """JSON, YAML or MATLAB: one file of the tuned values."""
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
    text = render(doc, args.format, source)
    if str(out) == "-":
        print(text, end="")
    else:
        write_output(out, text, "--out")
        print(f"{args.format} export of {args.params} written to {out}")
    return EXIT_OK


def _c_folder(args: argparse.Namespace) -> Path:
    """The C export's folder (-o), refused where it is a file's name or holds other files
    (without --force), before anything is written."""
    from kftune.report.c_export import C_FILES

    out = args.out
    if out is None:
        out = args.params.with_name(args.params.stem + "_c")
    if str(out) == "-" or out.suffix in (".h", ".c") or (out.exists() and not out.is_dir()):
        raise UsageError(
            f"--out {out}: --format c writes a folder of C files ({', '.join(C_FILES)}), the "
            "filter that runs, no longer one header of numbers (its KFTUNE_* macros are in "
            "kftune_filter.h there): give --out a folder name"
        )
    inputs: list[Input] = command_inputs(args, {})
    if args.check is not None:
        inputs += dataset_inputs(args.check)
    for name in C_FILES:
        refuse_inputs(out / name, "--out", inputs)
        if (out / name).exists() or (out / name).is_symlink():
            output_file(out / name, "--out", inputs)
    if out.is_dir() and not args.force:
        others = sorted(p.name for p in out.iterdir() if p.name not in (*C_FILES, *BUILT))
        if others:
            shown = ", ".join(excerpt(n, 40) for n in others[:3])
            raise ConfigError(
                f"--out {out}: the folder holds other files than a C export's ({shown}"
                + (f" and {len(others) - 3} more" if len(others) > 3 else "")
                + "); choose a new or empty folder, or pass --force to write the export's "
                "files beside them"
            )
    return output_dir(out, "--out", inputs)  # a folder that exists or can be made


def _run_c(args: argparse.Namespace) -> int:
    """The C filter: refuse what cannot be exported, write the folder, then --check."""
    from kftune.cli.evaluate import read_tuned, require_named_model
    from kftune.models.c_contract import export_refusal
    from kftune.models.user import load_model
    from kftune.report.c_export import c_files, find_compiler
    from kftune.report.export import export_document
    from kftune.tuning.deploy import model_file_changed

    precision = args.precision or "double"
    if args.split is not None and args.check is None:
        raise UsageError("--split chooses the manoeuvres of --check DATASET; give --check")
    if args.model is not None and split_model_file(args.model) is None:
        raise UsageError(
            f"--model: expected the model file the filter was tuned with (FILE.py), got "
            f"{excerpt(args.model)}; a built-in model comes from the tuned file"
        )
    cc = None
    if args.check is not None:
        cc = find_compiler()
        if cc is None:
            raise ConfigError(
                "--check needs a C compiler, and none was found (the CC environment "
                "variable, or cc, gcc or clang on the PATH): install one or set CC, or "
                "export without --check"
            )
    out = _c_folder(args)
    tuned = read_tuned(args.params)
    recorded = tuned.get("model", "single-track")
    if args.model is not None and split_model_file(str(recorded)) is None:
        raise UsageError(
            f"--model: {args.params} was tuned with the built-in model {excerpt(recorded)}, "
            "which it runs; --model names the model file of a filter tuned with one"
        )
    require_named_model(tuned, args.params, args.model)
    changed = model_file_changed(tuned)
    if changed:
        warnings.warn(
            f"{args.params}: {changed}; the export is of the model file as it is now",
            DataWarning,
            stacklevel=2,
        )
    doc = export_document(tuned, str(args.params))
    model = load_model(str(tuned.get("model", "single-track")))
    why = export_refusal(model)
    if why is not None:
        raise ConfigError(f"{args.params}: no C export: {why}")
    try:
        files = c_files(doc, model, precision=precision, source=args.params.name)
    except ValueError as exc:  # names that are no C macros, a record that does not fit
        raise ConfigError(f"{args.params}: no C export: {exc}") from None
    check = None
    if args.check is not None:
        check = _prepare_check(args, tuned)  # the dataset is read before anything is written
    out.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        write_output(out / name, text, "--out")
    report: dict[str, Any] = {
        "params": str(args.params),
        "out": str(out),
        "files": list(files),
        "model": model.name,
        "filter": doc["filter"],
        "precision": precision,
    }
    if not args.json:
        print(
            f"C export of {args.params} ({doc['filter'].upper()}, model {model.name!r}, "
            f"{precision}) written to {out}: {', '.join(files)}\n"
            f"build its demo: make -C {out}; run it on a manoeuvre (a dataset's files are "
            f"gzipped): gzip -dc manoeuvre.csv.gz | {out}/kftune_demo > estimates.csv"
        )
    code = EXIT_OK
    if check is not None:
        assert cc is not None
        report["check"], code = _check(args, check, out, doc, model, cc, precision)
    if args.json:
        emit_json(report)
    return code


def _prepare_check(args: argparse.Namespace, tuned_doc: dict[str, Any]) -> tuple[Any, ...]:
    """(tuned filter, dataset, manoeuvres, vehicle) of --check, refused (exit 3) where the
    recordings are sampled at another rate than the filter was tuned at (the demo refuses
    those, as kftune estimate does)."""
    from kftune.cli.evaluate import pick_split
    from kftune.data import open_dataset
    from kftune.tuning.deploy import TunedFilter, mismatches, tuned_for

    tuned = TunedFilter.from_document(tuned_doc, str(args.params))
    dataset = open_dataset(args.check)
    _, manoeuvres = pick_split(args.split, dataset)
    dt, vehicle = tuned_for(tuned_doc, str(args.params))
    bad = mismatches(dt, None, dataset, manoeuvres)
    if bad:
        raise ConfigError(
            f"--check {args.check}: {bad[0]}; the exported demo refuses such a recording, as "
            "kftune estimate does"
        )
    if vehicle is None and dataset.vehicle is None and tuned.model in _vehicle_models():
        raise ConfigError(f"--check {args.check}: the dataset names no vehicle")
    return tuned, dataset, manoeuvres, vehicle or dataset.vehicle


def _vehicle_models() -> list[str]:
    from kftune.models import get_model, model_names

    return [n for n in model_names() if get_model(n).needs_vehicle]


def _check(
    args: argparse.Namespace,
    check: tuple[Any, ...],
    out: Path,
    doc: dict[str, Any],
    model: Any,
    cc: list[str],
    precision: str,
) -> tuple[dict[str, Any], int]:
    """Build the demo of ``out`` (and, for float, of the double export) into a temporary
    folder, run it and kftune on every manoeuvre and print the deviations."""
    import tempfile

    from kftune.report.c_export import (
        FLOAT_MEASURES,
        TOLERANCE,
        build_demo,
        c_files,
        check_manoeuvre,
        demo_columns,
        float_summary,
    )

    tuned, dataset, manoeuvres, vehicle = check
    quiet = args.json
    r_diag = dict(zip(model.measurement_names, doc["r_diag"]))
    rows = []
    with tempfile.TemporaryDirectory(prefix="kftune-c-check-") as tmp:
        work = Path(tmp)
        if not quiet:
            print(f"compiling the demo with {' '.join(cc)} …", file=sys.stderr, flush=True)
        try:
            exe = build_demo(out, work, cc)
            double_exe = None
            if precision == "float":
                ref = work / "double"
                ref.mkdir()
                for name, text in c_files(doc, model, source=args.params.name).items():
                    (ref / name).write_text(text)
                double_exe = build_demo(ref, work, cc, name="kftune_demo_double")
        except RuntimeError as exc:
            from kftune.errors import RunFailedError

            raise RunFailedError(f"--check: {exc}") from None
        width = max(12, *(len(m.name) for m in manoeuvres))
        vs = "  vs double" if double_exe is not None else ""
        if not quiet:
            print(
                f"check on dataset {dataset.name!r}, {len(manoeuvres)} manoeuvres: the largest "
                "relative deviation ||C - kftune|| / ||kftune|| of a column"
            )
            print(f"{'manoeuvre':{width}s}  deviation  {'column':16s}  stop (step, cause){vs}")
        for m in manoeuvres:
            row = check_manoeuvre(exe, tuned, m, vehicle, double_exe, r_diag)
            rows.append(row)
            if not quiet:
                stop = "-" if row.stop is None else f"{row.stop[0]}, {row.stop[1]}"
                if row.stop != row.kftune_stop:
                    stop += f" (kftune: {row.kftune_stop or 'none'})"
                extra = "" if row.vs_double is None else f"  {row.vs_double:9.2e}"
                column = row.column if row.deviation > 0 else "-"  # every column the same
                line = f"{row.manoeuvre:{width}s}  {row.deviation:9.2e}  {column:16s}  "
                print((line + f"{stop:18s}{extra}").rstrip(), flush=True)
    worst = max(r.deviation for r in rows)
    worst_double = max((r.vs_double for r in rows if r.vs_double is not None), default=None)
    same_stops = all(r.stop == r.kftune_stop for r in rows)
    summary = {}
    if precision == "float":
        summary = float_summary(rows, demo_columns(model))
    beyond = [name for name, col in summary.items() if not col.within]
    passed = worst <= TOLERANCE if precision == "double" else same_stops and not beyond
    doc_check = {
        "dataset": dataset.name,
        "compiler": " ".join(cc),
        "tolerance": TOLERANCE if precision == "double" else None,
        "worst": _num(worst),
        "worst_vs_double": _num(worst_double),
        "passed": passed,
        "manoeuvres": {
            r.manoeuvre: {
                "deviation": _num(r.deviation),
                "column": r.column,
                "stop": list(r.stop) if r.stop else None,
                "kftune_stop": list(r.kftune_stop) if r.kftune_stop else None,
                **({"vs_double": _num(r.vs_double)} if r.vs_double is not None else {}),
            }
            for r in rows
        },
    }
    if precision == "float":
        doc_check["float"] = {
            "measures": FLOAT_MEASURES,
            "columns": {
                name: {
                    "kind": col.kind,
                    "max": _num(col.largest),
                    "p99": _num(col.p99),
                    "bound": col.bound,
                    "within": col.within,
                }
                for name, col in summary.items()
            },
            "beyond": beyond,
        }
    if not quiet:
        if precision == "double":
            verdict = (
                "the C filter reproduces kftune estimate"
                if passed
                else "the C filter does NOT reproduce kftune estimate"
            )
            print(f"worst {worst:.2e} (limit {TOLERANCE:g}): {verdict}")
        else:
            _print_float(summary, worst, worst_double, same_stops)
    if not passed:
        print(
            "kftune: failed: the exported filter's check found deviations beyond its limit",
            file=sys.stderr,
        )
    return doc_check, EXIT_OK if passed else EXIT_FAILURE


#: How the float check's table names each kind's measure (FLOAT_MEASURES in short).
_UNITS = {
    "state": "sigma",
    "std": "of sigma",
    "innovation": "sqrt(R)",
    "nis": "",
    "other": "of rms",
}


def _print_float(
    summary: dict[str, Any], worst: float, worst_double: float | None, stops: bool
) -> None:
    """The float check's table: each column's largest deviation from kftune's double filter
    and its 99th percentile in its own terms, against the stated bound, and the verdict."""
    print(
        "float against kftune's double filter, over every sample: a state or beta in units "
        "of its own sigma, a sigma relative, an innovation in units of sqrt(R), the NIS "
        "absolutely"
    )
    print(f"{'column':16s}  {'largest':>9s}  {'p99':>9s}  {'bound':>7s}  {'unit':8s}  verdict")
    for name, col in summary.items():
        verdict = "within" if col.within else f"BEYOND ({col.largest / col.bound:.3g} x the bound)"
        print(
            f"{name:16s}  {col.largest:9.2e}  {col.p99:9.2e}  {col.bound:7.2g}  "
            f"{_UNITS[col.kind]:8s}  {verdict}"
        )
    beyond = [name for name, col in summary.items() if not col.within]
    norms = (
        f"(largest relative deviation of a column's norm: {worst:.2e} against kftune, "
        f"{worst_double:.2e} against the double C filter)"
    )
    if not beyond and stops:
        print(f"float: every column within the stated bounds {norms}")
        return
    if beyond:
        print(
            f"float: BEYOND the stated bound in {', '.join(beyond)} {norms}: this filter "
            "loses too much in float. A UKF whose sigma of a state is a tiny fraction of its "
            "value (Vx known to 1e-5 of itself) cannot place its sigma points finely enough "
            "in float's 24 bits: export it in double, or its EKF (kftune tune --filter ekf), "
            "which held every bound on the data measured (BENCHMARKS.md)"
        )
    if not stops:
        print("float: it stops elsewhere than kftune on some manoeuvres")


def _num(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else v
