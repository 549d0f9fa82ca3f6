"""``kftune estimate``: run a tuned filter on a dataset's recordings and write its estimates.

Reads the filter from a file written by ``kftune tune`` (``--params tuned.json``) — its Q
and R as tuned, not re-estimated from the recordings — and runs it on every manoeuvre of
DATASET: a kftune dataset (its folder or manifest), a directory in the revs-250lm layout,
or 'default'; ``--split train|test|all`` (default all) and ``--manoeuvre`` pick some
(``-m`` takes names or shell patterns: -m 'test-*'). Raw recordings (CSV, Parquet, MAT, MDF4 files)
are imported into a dataset first: kftune dataset import FILE... --mapping MAP -o DIR.

For each manoeuvre it writes, into ``--out`` (default ./estimates), one table (CSV, or
Parquet with ``--format parquet``, which needs pyarrow: pip install 'kftune[parquet]') and
one figure (``--no-plot`` leaves them out):

  NAME.csv   t [s]; the model's states (single-track: vx, vy [m/s], r [rad/s]) and their
             standard deviations <state>_std from the diagonal of the covariance P; beta
             [rad] = atan2(vy, vx) and beta_std [rad] by the delta method from the Vx and Vy
             variances (their covariance is not kept, so it is left out); the innovations
             innovation_<measurement> (z − predicted z, in the measurement's unit); nis [-]
             (normalised innovation squared); and beta_ref [rad] where the recording has a
             reference sideslip — for another model, <name>_ref for each state or output
             the recording has a reference of. SI units throughout.
  NAME.png   β with its ±1.96σ band (95 %), and the reference and the error where there is
             one (for another model: its first state or output with a reference); the
             title says what share of the reference the band covers, and when it is too
             narrow to see; time is the recording's, as in NAME.csv's t (an imported
             recording trimmed of a standstill starts later than 0), as every kftune
             figure over a manoeuvre draws it.

With a reference it prints the sideslip KPIs (RMSE, MAE = maximum absolute error, and both
for |ay| ≥ 4 m/s², in degrees) after the file's burn-in; for another model, the RMSE of
each referenced state or output in its unit. Averages are taken within a split, never
across: a run over training and test manoeuvres prints one average per split (--json:
"averages" by split; "average" only where every manoeuvre run is of one split). And
whether the filter's standard deviations can be trusted (consistency, after the burn-in,
per manoeuvre and over all of them, pooled within a split): for
each channel with a standard deviation and a reference, the share of samples inside its
±1σ and ±1.96σ intervals (68.3 % and 95 % when consistent) and the mean NEES (1), and the
mean NIS of the m measurements (m), each mean with its 95 % χ² band (--json: "consistency";
"mean_nis" stays the mean over all samples).

It refuses (exit 3) recordings whose sample time differs from the tuned one by more than
1 % (Q is a variance per step) or whose vehicle parameters differ from the tuned ones, as
``kftune evaluate --params`` does; --force runs anyway, on the tuned vehicle, and warns.
Without DATASET it runs on the bundled set, and so, as ``evaluate`` does, it refuses (exit 3)
a file tuned on another dataset (the name the file records), naming it; a dataset named
on purpose runs, with a warning that it is not the one tuned on.
Files written before kftune recorded the sample time and vehicle are run with the
recording's vehicle, with a warning. Its standard deviations, NIS and
figure's band carry the file's calibration factor c (covariances c times larger, fitted by
``tune`` so that its σ matches its errors; the estimate is the same); --no-calibration
leaves it out. Exit 1 when the filter diverged on a manoeuvre (its
rows from that step on are empty).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from kftune.cli._common import add_command, emit_json, filter_spec_of, split_model_file
from kftune.cli.evaluate import (
    add_force,
    add_no_calibration,
    check_recordings,
    check_tuned_on,
    read_tuned,
    require_named_model,
)
from kftune.cli.exit_codes import EXIT_FAILURE, EXIT_OK
from kftune.cli.outputs import command_inputs, output_dir, refuse_inputs, write_output, writing
from kftune.errors import ConfigError, UsageError, excerpt

FORMATS = ("csv", "parquet")
SPLITS = ("train", "test", "all")


def register(subparsers: Any) -> None:
    """Add ``estimate``."""
    p = add_command(
        subparsers,
        "estimate",
        "run a tuned filter on a dataset; write estimates, std, innovations, NIS and plots",
        __doc__,
    )
    p.add_argument(
        "dataset",
        nargs="?",
        default=None,
        help="a kftune dataset: its folder or manifest, a directory in the revs-250lm "
        "layout, or 'default' (the bundled set, also when none is named: refused for a file "
        "tuned on another dataset); raw recordings (CSV, ...) are imported first with "
        "'kftune dataset import'",
    )
    p.add_argument(
        "--params", "-p", type=Path, required=True, help="tuned-parameters file ('kftune tune')"
    )
    p.add_argument(
        "--model",
        metavar="FILE.py[:VAR]",
        type=_model_file,
        help="the model file the filter was tuned with, when it is one (a built-in model "
        "comes from PARAMS): a model file is Python code that runs with your rights, so "
        "kftune runs it only when you name it here; its SHA-256 must be the one PARAMS "
        "records (--force runs an edited one)",
    )
    p.add_argument(
        "--manoeuvre",
        "-m",
        action="append",
        metavar="NAME",
        help="only this manoeuvre, or those matching a shell pattern such as 'test-*' "
        "(repeat for more; default: all of --split)",
    )
    p.add_argument(
        "--split",
        choices=SPLITS,
        default="all",
        help="the manoeuvres of this split only (default all; averages are per split)",
    )
    p.add_argument(
        "--out", "-o", type=Path, default=Path("estimates"), help="folder (default ./estimates)"
    )
    p.add_argument(
        "--format",
        choices=FORMATS,
        default="csv",
        help="table format (default csv; parquet needs pyarrow)",
    )
    p.add_argument("--no-plot", action="store_true", help="write no figures")
    add_force(p, "run the filter")
    add_no_calibration(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


def _model_file(text: str) -> str:
    """``--model``: a model file (the filter's model is the tuned file's)."""
    from kftune.models.user import is_model_file

    if not is_model_file(text):
        raise argparse.ArgumentTypeError(
            f"expected the model file the filter was tuned with (FILE.py), got {text!r}; a "
            "built-in model comes from the tuned file"
        )
    return text


def _parquet_writer() -> Any:
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        raise ConfigError(
            "--format parquet needs the package pyarrow, which is not installed "
            "(pip install 'kftune[parquet]'); or use --format csv"
        ) from None
    return pyarrow, pyarrow.parquet


def run(args: argparse.Namespace) -> int:
    """Run ``kftune estimate``."""
    import numpy as np

    from kftune.data import open_dataset
    from kftune.data.io import file_stem
    from kftune.tuning.deploy import TunedFilter, consistency_of, estimate, referenced
    from kftune.tuning.kpi import average_kpis, sideslip_kpis
    from kftune.tuning.runs import check_units, first_scored, where_diverged

    parquet = _parquet_writer() if args.format == "parquet" else None
    output_dir(args.out, "--out")
    doc = read_tuned(args.params)
    recorded = doc.get("model", "single-track")
    if args.model is not None and not split_model_file(str(recorded)):
        raise UsageError(
            f"--model: {args.params} was tuned with the built-in model {excerpt(recorded)}, "
            "which it runs; --model names the model file of a filter tuned with one"
        )
    require_named_model(doc, args.params, args.model)
    tuned = TunedFilter.from_document(doc, str(args.params), calibrated=args.calibrated)
    dataset = open_dataset(args.dataset)
    # without DATASET the bundled set: refused for a filter tuned on another, as evaluate does
    check_tuned_on(tuned.document, dataset.name, args.params, args.dataset, "estimate")
    manoeuvres = pick_manoeuvres(dataset, args.split, args.manoeuvre)
    vehicle, notes = check_recordings(tuned.document, args.params, dataset, manoeuvres, args.force)
    # the model it was tuned with, loaded once before any output (a lost one is named)
    fs = filter_spec_of(args, {}, vehicle, (args.params, tuned.document))
    check_units(fs.model, dataset)
    # its hooks on every manoeuvre, with the tuned filter's sigma points, before any output
    fs.probe(manoeuvres, tuned.r, tuned.q, tuned.settings)
    out: dict[str, Any] = {
        "params": str(args.params),
        "dataset": dataset.name,
        "out": str(args.out),
        "format": args.format,
        "warnings": notes,
        "cov_scale": tuned.cov_scale,
        "manoeuvres": {},
    }
    stems: dict[str, str] = {}  # manoeuvre → the stem of its files
    for m in manoeuvres:
        stem = file_stem(m.name)
        while stem in stems.values():  # two names reduced to the same stem
            stem += "_"
        stems[m.name] = stem
    reads = command_inputs(args, {})  # -o DATASET: a table could replace a recording
    for stem in stems.values():
        for suffix in (".parquet" if parquet else ".csv", ".png"):
            refuse_inputs(args.out / f"{stem}{suffix}", "--out", reads)
    args.out.mkdir(parents=True, exist_ok=True)
    kpis: dict[str, dict[str, float]] = {}  # manoeuvre → its KPIs
    ran: dict[str, Any] = {}  # manoeuvre → (it, its estimates; None where it diverged)
    diverged: list[str] = []
    keep = "nothing else is lost; fix it and run the command again"
    for m in manoeuvres:
        est = estimate(tuned, m, vehicle, probe=False)
        stem = stems[m.name]
        table = args.out / f"{stem}.{'parquet' if parquet else 'csv'}"
        with writing(f"the estimates to {table}", keep):
            if parquet is not None:
                pa, pq = parquet
                pq.write_table(pa.table(est.columns), table)
            else:
                write_output(table, _csv(est.columns), "--out", keep)
        row: dict[str, Any] = {
            "file": str(table),
            "n": m.n,
            "columns": est.units,
            "mean_nis": _num(float(np.nanmean(est.result.nis))) if m.n else None,
        }
        if est.result.diverged:
            row["diverged_at"] = where_diverged(m, est.result)
            diverged.append(row["diverged_at"])
        others = referenced(est)  # a model of one's own: its channels with a reference
        for c in others:  # an output's unit is the one the dataset declares for its reference
            if not est.units.get(c):
                est.units[c] = est.units[f"{c}_ref"] = dataset.units.get(f"{c}_ref", "")
        shown = "beta" if "beta" in est.columns else (others[0] if others else None)
        if not args.no_plot and shown is not None:
            from kftune.report import plots

            figure = args.out / f"{stem}.png"
            fig = plots.estimate_trace(
                m.t,
                est.columns[shown],
                est.columns.get(f"{shown}_std"),
                est.columns.get(f"{shown}_ref"),
                f"Sideslip estimate, {m.name}" if shown == "beta" else f"{shown}, {m.name}",
                label="β" if shown == "beta" else shown,
                unit=est.units.get(shown, ""),
            )
            with writing(f"the figure {figure}", keep):
                plots.save(fig, figure)
            row["figure"] = str(figure)
        if "beta_ref" in est.columns and "beta" in est.columns:
            k0 = first_scored(m, tuned.burn_in)
            if est.result.diverged:
                kpi = {k: math.nan for k in ("rmse", "mae", "rmse_non", "mae_non")}
                kpi["diverged"] = 1.0
            else:
                kpi = sideslip_kpis(
                    est.columns["beta"][k0:], est.columns["beta_ref"][k0:], m.ay[k0:]
                )
            kpis[m.name] = kpi
            row["kpis"] = {k: _num(v) for k, v in kpi.items()}
        elif others:  # the RMSE of each referenced channel, in its unit, after the burn-in
            k0 = first_scored(m, tuned.burn_in)
            row["rmse"] = {
                c: _num(
                    float(
                        np.sqrt(np.mean((est.columns[c][k0:] - est.columns[f"{c}_ref"][k0:]) ** 2))
                    )
                )
                for c in others
            }
            row["units"] = {c: est.units.get(c, "") for c in others}
        ran[m.name] = (m, None if est.result.diverged else est)
        out["manoeuvres"][m.name] = row
    # averages and pooled consistency within a split, never across (held-out evidence
    # mixed with training manoeuvres would read as neither)
    splits = {s: [m for m in manoeuvres if m.split == s] for s in ("train", "test")}
    splits = {s: ms for s, ms in splits.items() if ms}
    out["averages"] = {}
    out["consistency_by_split"] = {}
    for split, ms in splits.items():
        rows = [kpis[m.name] for m in ms if m.name in kpis]
        out["averages"][split] = (
            {k: _num(v) for k, v in average_kpis(rows).items()} if rows else None
        )
        # after the burn-in, as the KPIs; none pooled when it diverged anywhere
        each, out["consistency_by_split"][split] = consistency_of(
            fs.model, tuned.burn_in, {m.name: ran[m.name] for m in ms}
        )
        for name, of_one in each.items():
            out["manoeuvres"][name]["consistency"] = of_one
    one = next(iter(splits)) if len(splits) == 1 else None
    out["average"] = None if one is None else out["averages"][one]
    out["consistency"] = None if one is None else out["consistency_by_split"][one]
    if args.json:
        emit_json(out)
    else:
        _print(out, tuned.burn_in)
    if diverged:
        more = f" (and {len(diverged) - 1} more)" if len(diverged) > 1 else ""
        print(
            f"kftune: failed: the filter diverged on {len(diverged)} of {len(manoeuvres)} "
            f"manoeuvres; first: {diverged[0]}{more}",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    return EXIT_OK


def _csv(columns: dict[str, Any]) -> str:
    """The columns as CSV text: a header row, then one row per sample, ``%.17g`` (every
    float64 exactly); a NaN (after a divergence) as an empty cell."""
    import numpy as np

    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    lines = [",".join(names)]
    for row in data:
        lines.append(",".join("" if math.isnan(v) else f"{v:.17g}" for v in row.tolist()))
    return "\n".join(lines) + "\n"


def _num(v: float) -> float | None:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _print(doc: dict[str, Any], burn_in: float) -> None:
    rows = doc["manoeuvres"]
    width = max(12, *(len(n) for n in rows))
    with_kpis = any("kpis" in r for r in rows.values())
    units: dict[str, str] = next((r["units"] for r in rows.values() if "units" in r), {})
    heads: tuple[str, ...] = ("RMSE°", "MAE°", "RMSE_NON°", "MAE_NON°") if with_kpis else ()
    heads += tuple(f"RMSE {c} {u}".rstrip() for c, u in units.items())
    widths = [max(10, len(h)) for h in heads]
    if heads:  # the accuracy (the NIS is in the consistency table below)
        print(f"{'manoeuvre':{width}s} " + " ".join(f"{h:>{w}s}" for h, w in zip(heads, widths)))
        for name, row in rows.items():
            k = row.get("kpis", {})
            cells = [k.get(c) for c in ("rmse", "mae", "rmse_non", "mae_non")] if with_kpis else []
            cells += [row.get("rmse", {}).get(c) for c in units]
            print(f"{name:{width}s} " + " ".join(_cell(v, w) for v, w in zip(cells, widths)))
    averages = {s: a for s, a in doc["averages"].items() if a is not None}
    for split, avg in averages.items():
        cells = [_cell(avg.get(c)) for c in ("rmse", "mae", "rmse_non", "mae_non")]
        label = "average" if len(doc["averages"]) == 1 else f"average {split}"
        print(f"{label:{width}s} " + " ".join(cells))
    if averages:
        if len(doc["averages"]) > 1:
            print("averages per split, never across training and test manoeuvres")
        print(
            "β KPIs in degrees against the reference"
            + (f", after a burn-in of {burn_in:g} s" if burn_in else "")
            + ";\nMAE = maximum absolute error; _NON: samples with |ay| ≥ 4 m/s²"
        )
    from kftune.report.tables import consistency_lines

    runs = {name: row["consistency"] for name, row in rows.items()}
    if len(rows) > 1:  # pooled sample by sample, within a split
        for split, pooled in doc["consistency_by_split"].items():
            runs["all" if len(doc["consistency_by_split"]) == 1 else split] = pooled
    print("\n".join(consistency_lines(runs, width)))
    if doc["cov_scale"] != 1.0:
        print(
            f"calibrated: covariances × {doc['cov_scale']:.4g} as the tuned file records "
            "(--no-calibration: the filter's own)"
        )
    files = f"{len(rows)} {doc['format']} file{'s' if len(rows) != 1 else ''}"
    figures = sum("figure" in row for row in rows.values())
    if figures:  # -o holds them too: say so, and how many
        files += f" and {figures} PNG figure{'s' if figures != 1 else ''}"
    print(f"estimates written to {doc['out']} ({files})")


def _cell(v: float | None, width: int = 10) -> str:
    return f"{'–':>{width}s}" if v is None else f"{v:{width}.4f}"


def pick_manoeuvres(dataset: Any, split: str, patterns: list[str] | None) -> list[Any]:
    """The manoeuvres of ``split`` (``train``, ``test`` or ``all``) whose names match one
    of ``patterns`` (names or shell patterns, :func:`fnmatch.fnmatchcase`; None: all), in
    dataset order.

    Raises:
        ConfigError: (exit 3) a pattern that matches no manoeuvre of the dataset, or none of
            the split, naming it and what there is; a split the dataset has none of.
    """
    import fnmatch

    names = list(dataset.names)
    in_split = [m for m in dataset.manoeuvres if split == "all" or m.split == split]
    if not in_split:
        raise ConfigError(
            f"--split {split}: dataset {dataset.name!r} has no {split} manoeuvres; use --split all"
        )
    if not patterns:
        return in_split

    def matches(name: str, pattern: str) -> bool:  # a name with [ ] is also itself
        return name == pattern or fnmatch.fnmatchcase(name, pattern)

    for pattern in dict.fromkeys(patterns):
        if not any(matches(n, pattern) for n in names):
            raise ConfigError(
                f"--manoeuvre: no manoeuvre {pattern!r} in dataset {dataset.name!r}; it has {names}"
            )
        if not any(matches(m.name, pattern) for m in in_split):
            raise ConfigError(
                f"--manoeuvre {pattern!r}: no manoeuvre of the {split} split matches it in "
                f"dataset {dataset.name!r}; its {split} manoeuvres are "
                f"{[m.name for m in in_split]}"
            )
    return [m for m in in_split if any(matches(m.name, p) for p in patterns)]
