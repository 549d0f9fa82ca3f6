"""``kftune dataset``: generate the reference set, summarise a dataset, plot a manoeuvre.

    kftune dataset generate OUT [--seed N] [--only NAME ...]
    kftune dataset info [DATASET] [--json]
    kftune dataset show [DATASET] [--manoeuvre NAME] [--out FILE.png]
    kftune dataset import SOURCE... --mapping MAP.toml --out DIR [--name NAME] [--force]

DATASET is a kftune dataset directory (or its manifest), a directory in the revs-250lm
layout, or omitted / ``default`` for the bundled set.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kftune.errors import ConfigError, KftuneError

if TYPE_CHECKING:  # kftune.data loads scipy: only when a verb runs, not for --help
    from kftune.data import Dataset, Manoeuvre


def register(subparsers: Any) -> None:
    """Add ``dataset`` and its verbs."""
    parser = subparsers.add_parser(
        "dataset",
        help="generate, summarise or plot manoeuvre data",
        description="Generate the reference dataset, summarise a dataset, plot a manoeuvre.",
    )
    verbs = parser.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True

    gen = verbs.add_parser(
        "generate",
        help="simulate the 31 reference manoeuvres and write them (needs [simulate])",
        description="Simulate the reference manoeuvres on CommonRoad's multi-body model, "
        "measure them with the sensor models and write a dataset in the kftune format. "
        "The same seed gives the same bytes on the same machine.",
    )
    gen.add_argument("out", type=Path, help="output directory (created if needed)")
    gen.add_argument(
        "--seed", type=int, default=None, help="sensor-noise seed (default: the bundled set's)"
    )
    gen.add_argument("--only", nargs="+", metavar="NAME", help="generate only these manoeuvres")
    gen.add_argument(
        "--force",
        action="store_true",
        help="replace the kftune dataset already in OUT (its manifest and the files it lists)",
    )
    gen.add_argument("--quiet", action="store_true", help="no progress output")
    gen.set_defaults(func=run_generate)

    info = verbs.add_parser("info", help="summarise a dataset")
    info.add_argument("dataset", nargs="?", default=None, help="dataset (default: bundled)")
    info.add_argument("--json", action="store_true", help="print one JSON object instead")
    info.set_defaults(func=run_info)

    show = verbs.add_parser("show", help="plot one manoeuvre's signals to a PNG")
    show.add_argument("dataset", nargs="?", default=None, help="dataset (default: bundled)")
    show.add_argument(
        "--manoeuvre", "-m", default=None, help="manoeuvre name (default: the first one)"
    )
    show.add_argument(
        "--out",
        "-o",
        type=Path,
        default=None,
        help="PNG file (default: <manoeuvre>.png in the working folder, the name reduced to "
        "letters, digits, '.', '_' and '-')",
    )
    show.set_defaults(func=run_show)

    imp = verbs.add_parser(
        "import",
        help="turn recordings (CSV/TSV, Parquet, MATLAB, MDF4) into a dataset",
        description="Read recordings through one column mapping (a TOML file: which source "
        "signal is which channel, its unit, a sample time, channels computed from the "
        'columns (expr = "(wheel_fl + wheel_fr) / 2"), standstill trimming, the train/test '
        "rule, the vehicle; see the README, 'Importing your recordings'), merge them into "
        "one dataset and write it in the kftune format. "
        "Formats by suffix: CSV/TSV (.csv .tsv), Parquet (.parquet, extra [parquet]), "
        "MATLAB (.mat; v7.3 needs extra [mat73]), MDF4 (.mf4 .mdf, extra [mdf]); a folder "
        "is a recording of one text file per signal (<name>.txt). --mapping takes a TOML "
        "file or the name of a mapping kftune ships (revs-250lm: "
        "kftune dataset import path/to/revs-250lm --mapping revs-250lm -o revs/).",
    )
    imp.add_argument(
        "sources",
        nargs="+",
        type=Path,
        metavar="SOURCE",
        help="recording files, or folders of one file per signal",
    )
    imp.add_argument(
        "--mapping",
        required=True,
        type=Path,
        help="column mapping: a TOML file, or a built-in mapping's name (revs-250lm)",
    )
    imp.add_argument("--out", "-o", required=True, type=Path, help="output dataset folder")
    imp.add_argument("--name", default=None, help="dataset name (default: the mapping's, or OUT's)")
    imp.add_argument(
        "--force",
        action="store_true",
        help="replace the kftune dataset already in OUT (its manifest and the files it lists)",
    )
    imp.set_defaults(func=run_import)


# ------------------------------------------------------------------------------ generate
def run_generate(args: argparse.Namespace) -> int:
    """Simulate and write the reference dataset."""
    from kftune.cli.outputs import output_dir
    from kftune.data import save_dataset
    from kftune.sim.generate import DEFAULT_SEED, generate_dataset
    from kftune.sim.plant import SimulationError

    output_dir(args.out, "OUT")
    old_files = _files_to_replace(args.out, args.force)  # checked before the simulation

    seed = DEFAULT_SEED if args.seed is None else args.seed
    start = time.perf_counter()

    def progress(name: str, i: int, total: int) -> None:
        if not args.quiet:
            print(
                f"[{time.perf_counter() - start:6.1f} s] {i + 1}/{total} {name}",
                file=sys.stderr,
                flush=True,
            )

    try:
        dataset = generate_dataset(seed=seed, names=args.only, progress=progress)
    except SimulationError as exc:
        print(f"kftune: simulation failed: {exc}", file=sys.stderr)
        return 1
    except ConfigError:
        raise  # a missing optional package: exit 3, as every command says it
    except ValueError as exc:
        print(f"kftune: error: {exc}", file=sys.stderr)
        return 2
    _remove(old_files, args.out)  # only now that the new dataset exists
    manifest = save_dataset(dataset, args.out)
    elapsed = time.perf_counter() - start
    print(
        f"wrote {len(dataset)} manoeuvres ({sum(m.n for m in dataset.manoeuvres)} samples, "
        f"seed {seed}) to {manifest.parent} in {elapsed:.1f} s"
    )
    return 0


def _files_to_replace(out: Path, force: bool) -> list[Path]:
    """The files of the kftune dataset in ``out`` that ``--force`` replaces (none for a new
    or empty folder). Refuses a non-empty folder without ``force``, and with it a folder
    that holds no kftune dataset or whose manifest lists files outside it
    (:func:`kftune.data.io.dataset_files` refuses those)."""
    if not out.is_dir() or not any(out.iterdir()):
        return []
    if not force:
        raise ConfigError(
            f"OUT {out}: the folder is not empty; choose a new or empty folder, or pass "
            "--force to replace the kftune dataset in it"
        )
    from kftune.data.io import dataset_files

    try:
        files = dataset_files(out)
    except KftuneError as exc:
        raise ConfigError(f"OUT {out}: --force replaces only a kftune dataset: {exc}") from None
    folders = [f for f in files if f.is_dir()]
    if folders:
        raise ConfigError(f"OUT {out}: its manifest lists a folder as a file: {folders[0]}")
    return files


def _remove(files: list[Path], out: Path) -> None:
    """Delete the old dataset's files, the manifest last (so an interrupted removal leaves
    a dataset that ``--force`` can still recognise)."""
    for f in [*files[1:], *files[:1]]:  # dataset_files lists the manifest first
        try:
            f.unlink(missing_ok=True)
        except OSError as exc:
            raise ConfigError(f"OUT {out}: cannot remove the old file {f}: {exc}") from None


def _save_in_place(dataset: Dataset, out: Path, old_files: list[Path]) -> Path:
    """Write ``dataset`` into a temporary folder beside ``out``, then move it into place: a
    new ``out`` by one rename, else file by file with the manifest renamed over the old
    one last, and only then the old dataset's other files deleted. A failed write (a full
    disk) leaves ``out`` as it was and removes the temporary folder, so the import can
    simply be run again.

    Returns:
        The manifest's path in ``out``.

    Raises:
        RunFailedError: (exit 1) naming the file of ``out`` that could not be written and
            why.
    """
    import os
    import shutil
    import tempfile

    from kftune.data import save_dataset
    from kftune.errors import RunFailedError

    tmp: Path | None = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp"))
        umask = os.umask(0o022)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; renamed, it is ``out``
        manifest = save_dataset(dataset, tmp)
        if not out.exists():
            os.rename(tmp, out)
            tmp = None
        else:  # an empty folder, or the dataset --force replaces
            new = sorted(p for p in tmp.iterdir() if p != manifest)
            for f in [*new, manifest]:
                os.replace(f, out / f.name)
            kept = {f.name for f in new} | {manifest.name}
            _remove([f for f in old_files if f.name not in kept or f.parent != out], out)
    except OSError as exc:
        name = Path(exc.filename).name if exc.filename else ""
        what = out / name if tmp is not None and Path(exc.filename or "").parent == tmp else None
        raise RunFailedError(
            f"--out {out}: cannot write {what or exc.filename or 'the dataset'} "
            f"({exc.strerror or exc}); {out} was left as it was: free some space (or fix "
            "the cause) and run the import again"
        ) from None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return out / manifest.name


# ------------------------------------------------------------------------------ import
def run_import(args: argparse.Namespace) -> int:
    """Import recordings into a dataset folder."""
    from kftune.cli.outputs import output_dir, refuse_inputs
    from kftune.data.importer import import_recordings

    output_dir(args.out, "--out")
    old_files = _files_to_replace(args.out, args.force)  # checked before reading anything
    reads = [(s, "a recording it imports") for s in args.sources]
    why = "--force would delete it: import from a copy outside the folder"
    for f in old_files:  # --force: a file of the old dataset that is imported again
        refuse_inputs(f, "--out", [*reads, (args.mapping, "the mapping (--mapping)")], why)
    dataset = import_recordings(args.sources, args.mapping, name=args.name or None)
    manifest = _save_in_place(dataset, args.out, old_files)
    meta = dataset.meta
    for file, kept, total in zip(meta["imported_from"], meta["kept_s"], meta["recorded_s"]):
        print(f"{file}: kept {kept:.1f} s of {total:.1f} s")
    print(
        f"wrote {len(dataset)} manoeuvre{'' if len(dataset) == 1 else 's'} "
        f"({len(dataset.train)} train, {len(dataset.test)} "
        f"test; dt = {dataset.dt:g} s; channels {', '.join(dataset.channel_names)}) to "
        f"{manifest.parent}"
    )
    return 0


# ------------------------------------------------------------------------------ info
def dataset_info(dataset: Dataset) -> dict[str, Any]:
    """The summary ``kftune dataset info`` prints, as plain data: the sideslip statistics
    for data with the sideslip model's inputs and measurements (β's range None where no
    manoeuvre of the split has a ``beta_ref``, as in a recording without a reference
    sensor), the channels and their units for any other."""
    from kftune.data.validate import SIDESLIP_CHANNELS

    if not set(SIDESLIP_CHANNELS) - {"beta_ref"} <= set(dataset.channel_names):
        return _generic_info(dataset)
    rows = dataset.summary()
    splits = {}
    for split in ("train", "test"):
        ms = [m for m in dataset.manoeuvres if m.split == split]
        if not ms:
            continue
        ay = np.concatenate([m.ay for m in ms])
        refs = [m.channel("beta_ref") for m in ms if m.has("beta_ref")]
        beta = np.degrees(np.concatenate(refs)) if refs else None
        splits[split] = {
            "manoeuvres": len(ms),
            "samples": int(ay.size),
            "duration_s": float(sum(m.duration for m in ms)),
            "ay_min": float(ay.min()),
            "ay_max": float(ay.max()),
            "beta_min_deg": None if beta is None else float(beta.min()),
            "beta_max_deg": None if beta is None else float(beta.max()),
            "share_ay_ge_4": float(np.mean(np.abs(ay) >= 4.0)),
        }
    r = dataset.r_default
    return {
        "name": dataset.name,
        "vehicle": None if dataset.vehicle is None else dataset.vehicle.name,
        "dt": dataset.dt,
        "splits": splits,
        "r_default": [float(v) for v in r],
        "r_default_std": {
            "vx_mps": float(np.sqrt(r[0])),
            "ay_mps2": float(np.sqrt(r[1])),
            "r_degps": float(np.degrees(np.sqrt(r[2]))),
        },
        "manoeuvres": rows,
    }


def _generic_info(dataset: Dataset) -> dict[str, Any]:
    """:func:`dataset_info` of data without the sideslip channels."""
    names = [c for c in dataset.channel_names if c != "t"]
    return {
        "name": dataset.name,
        "vehicle": None if dataset.vehicle is None else dataset.vehicle.name,
        "dt": dataset.dt,
        "channels": names,
        "units": {c: channel_unit(dataset.units, c) for c in names},
        "splits": {
            split: {"manoeuvres": len(ms), "samples": sum(m.n for m in ms)}
            for split, ms in (("train", dataset.train), ("test", dataset.test))
            if ms
        },
        "manoeuvres": [
            {"name": m.name, "kind": m.kind, "split": m.split, "n": m.n, "duration": m.duration}
            for m in dataset.manoeuvres
        ],
    }


def run_info(args: argparse.Namespace) -> int:
    """Print a dataset summary."""
    from kftune.data import open_dataset

    dataset = open_dataset(args.dataset)
    info = dataset_info(dataset)
    if args.json:
        print(json.dumps(info))
        return 0
    if "channels" in info:
        vehicle = "no vehicle" if info["vehicle"] is None else f"vehicle {info['vehicle']!r}"
        print(
            f"dataset {info['name']!r}: {vehicle}, dt = {info['dt']:g} s, "
            f"{len(dataset)} manoeuvres; channels t, "
            + ", ".join(f"{c} [{u}]" if u else c for c, u in info["units"].items())
        )
        for row in info["manoeuvres"]:
            print(f"{row['name']:34s} {row['kind']:16s} {row['split']:5s} {row['duration']:7.1f} s")
        return 0
    vehicle = "no vehicle" if info["vehicle"] is None else f"vehicle {info['vehicle']!r}"
    print(f"dataset {info['name']!r}: {vehicle}, dt = {info['dt']:g} s, {len(dataset)} manoeuvres")
    header = (
        f"{'manoeuvre':34s} {'kind':16s} {'split':5s} {'dur[s]':>7s} {'n':>6s} "
        f"{'ay min':>7s} {'ay max':>7s} {'β min°':>7s} {'β max°':>7s} {'|ay|≥4':>7s}"
    )
    print(header)
    print("-" * len(header))
    for row in info["manoeuvres"]:
        print(
            f"{row['name']:34s} {row['kind']:16s} {row['split']:5s} {row['duration']:7.1f} "
            f"{row['n']:6d} {row['ay_min']:7.2f} {row['ay_max']:7.2f} "
            f"{_deg(row['beta_min_deg'], 7)} {_deg(row['beta_max_deg'], 7)} "
            f"{100 * row['share_ay_ge_4']:6.1f}%"
        )
    print("-" * len(header))
    for split, s in info["splits"].items():
        print(
            f"{split:5s}: {s['manoeuvres']:3d} manoeuvres, {s['samples']:6d} samples "
            f"({s['duration_s']:.0f} s), ay {s['ay_min']:.2f} … {s['ay_max']:.2f} m/s², "
            + (
                "β – (no beta_ref), "
                if s["beta_min_deg"] is None
                else f"β {s['beta_min_deg']:.2f} … {s['beta_max_deg']:.2f}°, "
            )
            + f"|ay| ≥ 4 m/s² in {100 * s['share_ay_ge_4']:.1f} %"
        )
    sd = info["r_default_std"]
    print(
        f"R (high-pass statistics, σ): Vx {sd['vx_mps']:.4f} m/s, ay {sd['ay_mps2']:.4f} m/s², "
        f"r {sd['r_degps']:.4f} °/s"
    )
    return 0


def _deg(value: float | None, width: int) -> str:
    """An angle [deg] for ``dataset info``'s table, "–" where the manoeuvre has no β."""
    return f"{'–':>{width}s}" if value is None else f"{value:{width}.2f}"


# ------------------------------------------------------------------------------ show
def channel_unit(units: Mapping[str, str], name: str) -> str:
    """The SI unit of channel ``name``: the dataset's declared ``units`` for a channel kftune
    does not know, the SI unit of its dimension for one it knows (``delta`` → rad), else ""."""
    from kftune.data.validate import CHANNEL_DIMENSION, SI_UNIT

    if name in units:
        return str(units[name])
    return SI_UNIT[CHANNEL_DIMENSION[name]] if name in CHANNEL_DIMENSION else ""


def plot_manoeuvre(m: Manoeuvre, units: Mapping[str, str] | None = None) -> Any:
    """A figure of the manoeuvre's signals against time (see :func:`kftune.report.plots.render`):
    the sideslip channels in degrees and SI units (β's panel only where the manoeuvre has a
    ``beta_ref``), any other data one panel per channel labelled with its unit from ``units``
    (the dataset's, name → SI unit) or kftune's own for a channel it knows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kftune.data.validate import SIDESLIP_CHANNELS
    from kftune.report.plots import TIME_LABEL

    t = m.t  # the recording's time, as compare's and estimate's figures draw it
    if not all(m.has(c) for c in SIDESLIP_CHANNELS if c != "beta_ref"):  # every channel
        names = [c for c in m.channel_names if c != "t"]
        fig, axs = plt.subplots(len(names), 1, figsize=(9, 2 * len(names)), sharex=True)
        for ax, c in zip(np.atleast_1d(axs), names):
            ax.plot(t, m.channel(c), lw=0.7)
            unit = channel_unit(units or {}, c)
            ax.set_ylabel(f"{c} [{unit}]" if unit else c)
            ax.grid(True, lw=0.3)
        np.atleast_1d(axs)[-1].set_xlabel(TIME_LABEL)
        fig.suptitle(f"{m.name} ({m.kind}, {m.split})\n{m.description}", fontsize=9)
        fig.tight_layout()
        return fig
    has_beta = m.has("beta_ref")
    fig, axes = plt.subplots(5 if has_beta else 4, 1, figsize=(9, 10 if has_beta else 8),
                             sharex=True)  # fmt: skip
    axes[0].plot(t, np.degrees(m.delta), lw=0.8)
    axes[0].set_ylabel("δ road wheel [°]")
    axes[1].plot(t, m.ay, lw=0.6, label="ay")
    axes[1].plot(t, m.ax, lw=0.6, label="ax")
    for sign in (1.0, -1.0):  # where the _NON KPIs start (|ay| >= 4 m/s²)
        axes[1].axhline(sign * 4.0, color="grey", lw=0.8, ls=":",
                        label="|ay| = 4 m/s²\n(KPIs _NON above)" if sign > 0 else None)  # fmt: skip
    axes[1].set_ylabel("acceleration [m/s²]")
    axes[2].plot(t, np.degrees(m.r), lw=0.6)
    axes[2].set_ylabel("yaw rate [°/s]")
    axes[3].plot(t, m.vx, lw=0.8, label="vx measured")
    if "vx_true" in m.extra:
        axes[3].plot(t, m.extra["vx_true"], lw=0.8, ls="--", label="vx true")
    axes[3].set_ylabel("speed [m/s]")
    if has_beta:
        axes[4].plot(t, np.degrees(m.beta_ref), lw=0.6, label="β reference")
        if "beta_true" in m.extra:
            axes[4].plot(t, np.degrees(m.extra["beta_true"]), lw=0.8, ls="--", label="β true")
        axes[4].set_ylabel("sideslip β [°]")
    axes[-1].set_xlabel(TIME_LABEL)
    for ax in axes:
        ax.grid(True, lw=0.3)
        if len(ax.get_legend_handles_labels()[0]) > 1 or ax is axes[1]:
            # beside the axes: inside, it covered the signals of a long manoeuvre
            ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8,
                      borderaxespad=0)  # fmt: skip
    fig.suptitle(f"{m.name} ({m.kind}, {m.split})\n{m.description}", fontsize=9)
    fig.tight_layout()
    return fig


def run_show(args: argparse.Namespace) -> int:
    """Plot one manoeuvre."""
    from kftune.data import open_dataset

    dataset = open_dataset(args.dataset)
    if args.manoeuvre is None:
        m = dataset.manoeuvres[0]
    else:
        try:
            m = dataset[args.manoeuvre]
        except KeyError as exc:  # a name the data do not hold: bad input (3), not usage
            raise ConfigError(f"--manoeuvre: {exc.args[0]}") from None
    from kftune.cli.outputs import command_inputs, output_file, write_output
    from kftune.data.io import file_stem

    default = Path(f"{file_stem(m.name)}.png")  # the name comes from a manifest: no path
    out = args.out if args.out is not None else default
    if out.suffix.lower() != ".png":  # a PNG whatever the name says: no name that hides it
        raise ConfigError(f"--out {out}: expected a file name ending in .png")
    output_file(out, "--out", command_inputs(args, {}))
    from kftune.report.plots import render

    write_output(out, render(plot_manoeuvre(m, dataset.units), dpi=110, tight=False), "--out")
    print(f"wrote {out}")
    return 0
