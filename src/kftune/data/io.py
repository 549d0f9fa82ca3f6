"""Reading and writing datasets in the kftune format, and the bundled dataset.

**The kftune format** (:func:`load_dataset`, :func:`save_dataset`): a directory with
``manifest.toml`` (or ``manifest.json``, same keys) and one CSV per manoeuvre (optionally
gzip-compressed, ``.csv.gz``); see "Data format" in the README and :class:`Manifest`. A
dataset is validated completely before it is returned (:mod:`kftune.data.validate`), and
every error names the file, the column and the row. Recordings in other layouts (CSV, MATLAB,
MDF, a folder of one file per signal, …) become datasets through one path, a column mapping
(:mod:`kftune.data.importer`).

Input is treated as untrusted: text files are read in blocks within size limits
(:mod:`kftune.data.textfile`, :class:`~kftune.data.textfile.ReadLimits`), so memory follows
the arrays kept; a manifest's file paths must stay inside the dataset folder; names become
file names only through :func:`file_stem`; messages quote at most a short excerpt of a file.
"""

from __future__ import annotations

import contextlib
import gzip
import io
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from kftune.data.jsonfile import read_json, read_toml
from kftune.data.manoeuvre import SPLITS, Dataset, Manoeuvre
from kftune.data.textfile import (
    SEPARATORS,
    NumericRows,
    ReadLimits,
    line_blocks,
)
from kftune.data.validate import (
    CHANNEL_DIMENSION,
    REQUIRED_CHANNELS,
    SI_UNIT,
    SIDESLIP_CHANNELS,
    UNITS,
    check_channel_name,
    sample_time,
    unit_factor,
    validate_channels,
)
from kftune.errors import DataError, excerpt
from kftune.settings import NUMBER, SettingError, each, rule, setting, validate
from kftune.vehicle.params import VehicleParams, preset

#: Identifies a kftune manifest.
FORMAT_TAG = "kftune-dataset"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class ManifestEntry:
    """One ``[[manoeuvres]]`` entry of a manifest: a manoeuvre and its CSV file."""

    name: str = setting(kind=str, required=True)
    kind: str = setting(kind=str, required=True)  # e.g. "j-turn", shown beside the name
    split: str = setting(kind=str, choices=SPLITS, required=True)
    file: str = setting(kind=str, required=True)  # relative to the manifest, inside its folder
    description: str = setting("", kind=str)


@dataclass(frozen=True)
class Manifest:
    """A dataset's manifest (``manifest.toml``); any other key is refused."""

    format: str = setting(kind=str, choices=(FORMAT_TAG,), required=True)
    format_version: int = setting(
        kind=int,
        choices=(FORMAT_VERSION,),
        what=f"{FORMAT_VERSION} (the version this kftune reads)",
        required=True,
    )
    name: str = setting(kind=str, required=True)
    description: str = setting("", kind=str)
    dt: float = setting(kind=NUMBER, low=0, strict=True, high=1, unit="s", required=True)
    #: a preset name or a table of VehicleParams fields (SI); none: data of something other
    #: than a car
    vehicle: str | dict[str, Any] | None = field(
        default=None,
        metadata=rule((str, dict), what="a preset name or a table of VehicleParams fields"),
    )
    #: column → unit; optional for the sideslip channels (SI assumed), required for others
    units: dict[str, str] = field(
        default_factory=dict, metadata=rule(dict, each=each(str, what="a unit string"))
    )
    meta: dict[str, Any] = field(default_factory=dict, metadata=rule(dict))  # provenance
    manoeuvres: list[ManifestEntry] = field(
        default_factory=list, metadata=rule(list, each=each(ManifestEntry), required=True)
    )


#: Manifest file names looked for in a dataset directory, in this order.
MANIFEST_NAMES = ("manifest.toml", "manifest.json")


# =============================================================================== writing
_UNSAFE_IN_FILE_NAME = re.compile(r"[^A-Za-z0-9._-]")


def file_stem(name: str, limit: int = 100) -> str:
    """A file-name stem for a user-supplied name (manoeuvre, dataset, method) that stays in
    the folder it is joined to: every character but ASCII letters, digits, ``.``, ``_`` and
    ``-`` becomes ``_`` (no ``/``, ``\\``, ``:`` or NUL), leading dots are dropped (no
    ``..``, no hidden file), and it is cut to ``limit`` characters; never empty.
    ``"train-01-j-turn"`` stays as it is, ``"../../tmp/x"`` becomes ``"_.._tmp_x"``.
    """
    return _UNSAFE_IN_FILE_NAME.sub("_", name).lstrip(".")[:limit] or "_"


def _toml_value(value: Any, key: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"cannot write non-finite {key} = {v!r} to a manifest")
        return repr(v)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v, key) for v in value) + "]"
    raise ValueError(
        f"cannot write {key} = {excerpt(value)} ({type(value).__name__}) to a manifest"
    )


def _toml_table(table: Mapping[str, Any], prefix: str, lines: list[str]) -> None:
    subtables = []
    for key, value in table.items():
        if value is None:
            continue
        if isinstance(value, Mapping):
            subtables.append((key, value))
        else:
            lines.append(f"{_toml_key(key)} = {_toml_value(value, key)}")
    for key, value in subtables:
        name = f"{prefix}.{_toml_key(key)}" if prefix else _toml_key(key)
        lines.append("")
        lines.append(f"[{name}]")
        _toml_table(value, name, lines)


def _toml_key(key: str) -> str:
    if key and all(c.isalnum() or c in "_-" for c in key):
        return key
    return json.dumps(key, ensure_ascii=False)


def _format_csv(columns: Mapping[str, np.ndarray]) -> str:
    """CSV text: a header row, then one row per sample; ``repr`` of each float, which
    reads back to the identical double."""
    names = list(columns)
    cols = [[repr(v) for v in np.asarray(columns[n], dtype=np.float64).tolist()] for n in names]
    out = io.StringIO()
    out.write(",".join(names) + "\n")
    for row in zip(*cols):
        out.write(",".join(row))
        out.write("\n")
    return out.getvalue()


def save_dataset(dataset: Dataset, directory: str | Path, compress: bool = True) -> Path:
    """Write ``dataset`` in the kftune format: ``manifest.toml`` and one CSV per manoeuvre.

    Files are byte-for-byte reproducible (gzip without timestamp or file name). Existing
    files of the same names are overwritten; nothing else in ``directory`` is touched. A
    manoeuvre's file is named :func:`file_stem` of its name, so that no name can place it
    outside ``directory``.

    Args:
        compress: write ``<name>.csv.gz`` (gzip) instead of ``<name>.csv``.

    Returns:
        The path of the manifest.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    names = dataset.manoeuvres[0].channel_names
    units: dict[str, str] = {
        c: SI_UNIT[CHANNEL_DIMENSION[c]] if c in CHANNEL_DIMENSION else _extra_unit(dataset, c)
        for c in names
    }
    entries = []
    files: dict[str, str] = {}
    for m in dataset.manoeuvres:
        if set(m.channel_names) != set(names):
            raise ValueError(
                f"manoeuvre {excerpt(m.name)} has channels {list(m.channel_names)}, manoeuvre "
                f"{excerpt(dataset.manoeuvres[0].name)} {list(names)}; the format needs the "
                "same columns in every file"
            )
        file = f"{file_stem(m.name)}.csv.gz" if compress else f"{file_stem(m.name)}.csv"
        if file in files:
            raise ValueError(
                f"manoeuvres {excerpt(files[file])} and {excerpt(m.name)} would both be written "
                f"to {file}; rename one"
            )
        files[file] = m.name
        text = _format_csv({c: m.channel(c) for c in names})
        data = text.encode("utf-8")
        if compress:
            buf = io.BytesIO()
            with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=9) as gz:
                gz.write(data)
            data = buf.getvalue()
        _write_file(directory / file, data)
        entry = {"name": m.name, "kind": m.kind, "split": m.split, "file": file}
        if m.description:
            entry["description"] = m.description
        entries.append(entry)
    lines = [
        '# kftune dataset manifest — see the README, section "Data format".',
        f"format = {_toml_value(FORMAT_TAG, 'format')}",
        f"format_version = {FORMAT_VERSION}",
        f"name = {_toml_value(dataset.name, 'name')}",
    ]
    if dataset.description:
        lines.append(f"description = {_toml_value(dataset.description, 'description')}")
    lines.append(f"dt = {_toml_value(float(dataset.dt), 'dt')}")
    vehicle = None if dataset.vehicle is None else dataset.vehicle.to_dict()
    _toml_table({"vehicle": vehicle, "units": units}, "", lines)
    if dataset.meta:
        _toml_table({"meta": _plain(dataset.meta)}, "", lines)
    for entry in entries:
        lines.append("")
        lines.append("[[manoeuvres]]")
        _toml_table(entry, "", lines)
    manifest = directory / "manifest.toml"
    _write_file(manifest, ("\n".join(lines) + "\n").encode("utf-8"))
    return manifest


def _write_file(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path``; an ``OSError`` (a full disk) names the file, which a
    failed ``write`` alone does not."""
    try:
        path.write_bytes(data)
    except OSError as exc:
        if exc.filename is None:
            exc.filename = str(path)
        raise


def _plain(value: Any) -> Any:
    """Mapping proxies and tuples → dicts and lists (for the TOML writer)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _extra_unit(dataset: Dataset, name: str) -> str:
    """Unit of a channel kftune does not know, for the manifest: the dataset's ``units``,
    else ``meta['units']``, else guessed from the name (kftune's own true-state channels),
    else ``"1"``."""
    if name in dataset.units:
        return str(dataset.units[name])
    declared = dataset.meta.get("units", {}) if isinstance(dataset.meta, Mapping) else {}
    if name in declared:
        return str(declared[name])
    stem = name.split("_")[0]
    guess = {
        "vx": "m/s",
        "vy": "m/s",
        "r": "rad/s",
        "ay": "m/s^2",
        "ax": "m/s^2",
        "beta": "rad",
        "roll": "rad",
        "pitch": "rad",
        "delta": "rad",
    }
    return guess.get(stem, "1")


# =============================================================================== reading
#: Largest manifest read [bytes] (one with a thousand manoeuvres is about 150 kB).
MAX_MANIFEST_BYTES = 16 * 2**20


def _read_manifest(path: Path) -> dict[str, Any]:
    if path.suffix == ".json":
        data = read_json(path, MAX_MANIFEST_BYTES)
    else:
        data = read_toml(path, MAX_MANIFEST_BYTES)
    if not isinstance(data, dict):
        raise DataError("manifest must be a table/object at the top level", file=str(path))
    return data


def _find_manifest(path: Path) -> Path:
    if path.is_dir():
        for name in MANIFEST_NAMES:
            if (path / name).is_file():
                return path / name
        raise DataError(
            f"no {' or '.join(MANIFEST_NAMES)} in this directory (is it a kftune dataset?)",
            file=str(path),
        )
    if not path.exists():
        raise DataError("dataset not found", file=str(path))
    if path.suffix not in (".toml", ".json") or not path.is_file():
        raise DataError(
            "not a kftune dataset (expected a dataset folder or its manifest file, "
            f"{' or '.join(MANIFEST_NAMES)}); a recording is imported first with "
            f"`kftune dataset import {path.name} --mapping MAP -o DIR`",
            file=str(path),
        )
    return path


def _member(manifest: Path, rel: str, index: int) -> Path:
    """The manoeuvre file ``rel`` of a manifest's ``manoeuvres[index]``, which must lie in the
    manifest's folder or below it once ``..`` and symbolic links are resolved: a manifest
    cannot make kftune read (or ``--force`` delete) a file elsewhere.

    Raises:
        DataError: an absolute path, or one that leads out of the dataset folder (the
            message names the entry, not the target's content).
    """
    base = manifest.parent
    target = base / rel
    inside = not Path(rel).is_absolute() and "\0" not in rel
    if inside:
        try:
            inside = target.resolve().is_relative_to(base.resolve())
        except (OSError, RuntimeError):  # a symlink loop
            inside = False
    if not inside:
        raise DataError(
            f"field manoeuvres[{index}].file = {excerpt(rel)} leads outside the dataset folder; "
            "a manoeuvre file must be a relative path inside it (no '..', absolute path or "
            "symbolic link out of it)",
            file=str(manifest),
        )
    return target


def dataset_files(directory: str | Path) -> list[Path]:
    """The files of the kftune dataset in ``directory``: its manifest and the manoeuvre
    files it lists (existing or not), nothing else.

    Raises:
        DataError: no manifest, one that is unreadable or lists no files, or one that lists
            a file outside the dataset folder.
    """
    manifest = _find_manifest(Path(directory))
    data = _read_manifest(manifest)
    entries = data.get("manoeuvres")
    if not isinstance(entries, list) or not all(
        isinstance(e, dict) and isinstance(e.get("file"), str) for e in entries
    ):
        raise DataError("manifest lists no manoeuvre files", file=str(manifest))
    return [manifest, *(_member(manifest, e["file"], i) for i, e in enumerate(entries))]


def load_dataset(path: str | Path | None = None, *, limits: ReadLimits | None = None) -> Dataset:
    """Load a dataset in the kftune format (``None``: the bundled default dataset).

    Args:
        path: a dataset directory, or its manifest file.
        limits: size limits of each manoeuvre file (``None``: the defaults, or the
            environment variables; see :class:`~kftune.data.textfile.ReadLimits`).

    Raises:
        DataError: anything wrong with the manifest or a manoeuvre file; names the file,
            the field or column and the row. Nothing is returned half-loaded.
    """
    if path is None:
        return default_dataset()
    manifest = _find_manifest(Path(path))
    mfile = str(manifest)
    try:
        man = validate(Manifest, _read_manifest(manifest))
    except SettingError as exc:
        raise DataError(exc.text("field"), file=mfile) from None
    vehicle = None if man.vehicle is None else _vehicle_from(man.vehicle, mfile)
    factors: dict[str, float] = {}
    si_units: dict[str, str] = {}  # channels kftune does not know: their SI unit
    for col, unit in man.units.items():
        check_channel_name(col, file=mfile)
        factors[col] = unit_factor(unit, CHANNEL_DIMENSION.get(col), file=mfile, column=col)
        if col not in CHANNEL_DIMENSION:
            si_units[col] = SI_UNIT[UNITS[unit.strip()][0]]
    for col in SIDESLIP_CHANNELS:
        factors.setdefault(col, 1.0)
    if not man.manoeuvres:
        raise DataError("field 'manoeuvres' is empty: a dataset needs at least one", file=mfile)
    manoeuvres = []
    seen: set[str] = set()
    for i, entry in enumerate(man.manoeuvres):
        if entry.name in seen:
            raise DataError(
                f"manoeuvre name {excerpt(entry.name)} appears twice (manoeuvres[{i}])", file=mfile
            )
        seen.add(entry.name)
        csv_path = _member(manifest, entry.file, i)
        if not csv_path.is_file():
            what = "a file that is not a regular file" if csv_path.exists() else "missing file"
            raise DataError(
                f"manoeuvre {excerpt(entry.name)} points at {what} {excerpt(entry.file)}",
                file=mfile,
            )
        channels = read_csv(csv_path, factors, limits)
        validate_channels(channels, file=str(csv_path), row_offset=2)
        step = sample_time(channels["t"])
        if abs(step - man.dt) > 0.01 * man.dt:
            raise DataError(
                f"sample time {step:.4g} s (median step) differs from the manifest's dt = "
                f"{man.dt:.4g} s by more than 1 %",
                file=str(csv_path),
                column="t",
            )
        manoeuvres.append(
            _manoeuvre(
                channels,
                name=entry.name,
                kind=entry.kind,
                split=entry.split,
                description=entry.description,
                file=str(csv_path),
            )
        )
    try:
        return Dataset(
            man.name, vehicle, float(man.dt), tuple(manoeuvres), man.description, man.meta, si_units
        )
    except DataError as exc:
        raise DataError(str(exc), file=mfile) from None


def _vehicle_from(value: Any, file: str) -> VehicleParams:
    if isinstance(value, str):
        try:
            return preset(value)
        except ValueError as exc:
            raise DataError(f"field 'vehicle': {exc}", file=file) from None
    if not isinstance(value, dict):
        raise DataError(
            "field 'vehicle' must be a table of VehicleParams fields or a preset name", file=file
        )
    try:
        return VehicleParams.from_dict(value)
    except (TypeError, ValueError) as exc:
        raise DataError(f"field 'vehicle': {exc}", file=file) from None


def _manoeuvre(
    channels: Mapping[str, np.ndarray],
    *,
    name: str,
    kind: str,
    split: str,
    description: str,
    file: str,
) -> Manoeuvre:
    try:
        return Manoeuvre(
            name,
            kind,
            split,
            channels["t"],
            channels={k: v for k, v in channels.items() if k != "t"},
            description=description,
        )
    except DataError as exc:
        raise DataError(str(exc), file=file) from None


def read_csv(
    path: str | Path, factors: Mapping[str, float], limits: ReadLimits | None = None
) -> dict[str, np.ndarray]:
    """Read one manoeuvre CSV of the kftune format into SI channels.

    The header row names the columns; every column must be declared (``factors`` holds the
    SI conversion factor of each declared column) and ``t`` present.
    Values are plain decimal numbers, separated by commas (or by the ``;`` or tab that
    separates the header's names); the first malformed value is reported by column and row
    (the header is row 1). The file is read in blocks, within ``limits``
    (:class:`~kftune.data.textfile.ReadLimits`; ``None``: the defaults or the environment).
    """
    path = Path(path)
    file = str(path)
    with contextlib.closing(line_blocks(path, limits)) as blocks:
        first_row, lines = next(blocks, (1, []))
        if not lines or not lines[0].strip():
            raise DataError(
                "empty file: expected a header row naming the columns", file=file, row=1
            )
        separator = next((s for s in SEPARATORS if s in lines[0]), ",")
        header = [h.strip() for h in lines[0].split(separator)]
        _check_header(header, factors, file)
        rows = NumericRows(file, header, separator, limits=limits)
        rows.add(first_row + 1, lines[1:])
        for first_row, lines in blocks:
            rows.add(first_row, lines)
    if rows.n == 0:
        raise DataError("no data rows after the header", file=file, row=2)
    columns = dict(zip(header, rows.columns()))
    for h, values in columns.items():
        if factors[h] != 1.0:
            values *= factors[h]
    return columns


def _check_header(header: list[str], factors: Mapping[str, float], file: str) -> None:
    for h in header:
        check_channel_name(h, file=file)
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise DataError(f"duplicated column(s) {excerpt(dup)} in the header", file=file, row=1)
    unknown = [h for h in header if h not in factors]
    if unknown:
        raise DataError(
            "unknown column: not a sideslip channel and not declared in the manifest's "
            f"[units] table (sideslip channels: {list(SIDESLIP_CHANNELS)}; any other column "
            'needs its unit there, e.g. px = "m")',
            file=file,
            column=unknown[0],
            row=1,
        )
    for c in REQUIRED_CHANNELS:
        if c not in header:
            raise DataError(
                f"missing the time column; the header has {excerpt(header, 200)}",
                file=file,
                column=c,
                row=1,
            )


# =========================================================================== bundled
#: Name of the bundled dataset directory inside the package (``kftune/datasets/<name>``).
DEFAULT_DATASET = "default"


def bundled_dataset_path(name: str = DEFAULT_DATASET) -> Path:
    """Directory of a dataset shipped inside the package."""
    return Path(str(resources.files("kftune") / "datasets" / name))


@lru_cache(maxsize=2)
def default_dataset() -> Dataset:
    """The bundled default dataset (generated by ``kftune dataset generate``), cached."""
    path = bundled_dataset_path()
    if not (path / "manifest.toml").is_file():
        raise DataError(
            "the bundled default dataset is missing from this installation; regenerate it "
            "with `kftune dataset generate src/kftune/datasets/default`",
            file=str(path),
        )
    return load_dataset(path)
