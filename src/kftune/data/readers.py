"""Readers of recordings in the formats loggers write, one registry keyed by file suffix.

A reader takes a file, the names of the source signals wanted and the reader options of a
mapping (``[source]`` in a mapping file, see :mod:`kftune.data.importer`), and returns a
:class:`Table`: the raw values of each signal (float64, not yet converted to SI), the
units the file itself declares, and — for a format that carries its own time axis (MDF) —
the time of each sample.

========== ======================== =========== ==================================================
format     suffixes                 extra       notes
========== ======================== =========== ==================================================
CSV / TSV  .csv .tsv (.gz)          —           header row of names; separator sniffed from the
                                                header (the most frequent of ``, ; TAB |``; TSV:
                                                tab) or ``delimiter``; units from ``name [unit]``
                                                or ``name(unit)`` headers or a units row
                                                (``units_row = true``); a ``#`` before the
                                                first name (``numpy.savetxt``) is dropped;
                                                UTF-8 or ``encoding`` (``"cp1252"``, …);
                                                ``decimal = ","`` for a decimal comma (with
                                                ``;`` or tab); rows are the file's line
                                                numbers
Parquet    .parquet .pq             parquet     numeric columns (nulls become NaN, reported by
                                                validation); rows 1-based
MATLAB     .mat                     (mat73)     v4 through ``scipy.io.loadmat``; v5–v7.2 walked
                                                element by element with SciPy's private
                                                reader (:data:`MAT5_SCIPY_INTERNALS`: a SciPy
                                                without them is named, not the file); v7.3
                                                (HDF5) through h5py (extra ``mat73``); one numeric
                                                vector per signal, at the top level or in the
                                                struct ``struct = "a.b"``; rows 1-based
MDF4       .mf4 .mdf                mdf         through asammdf; signals resampled onto one
                                                raster (:func:`read_mdf`); rows are raster
                                                samples, 1-based
columns    a folder                 —           one file per signal (``<name>.txt``, or the
                                                ``suffix`` given), one value a line, ``#`` and
                                                ``%`` lines comments (the revs-250lm layout,
                                                :func:`read_column_files`); rows are each
                                                file's line numbers
========== ======================== =========== ==================================================

A file's suffix picks its format, a folder is read as column files (:func:`format_of`); a
mapping's ``[source] format`` names
one instead (:func:`format_named`: ``"csv"`` for a ``.txt`` or ``.dat`` logger export).
Only the signals asked for are read. A file is untrusted input: messages quote at most a
short excerpt of it, and the size limits of :class:`~kftune.data.textfile.ReadLimits` hold.
A reader whose optional package is missing says which extra installs it.
"""

from __future__ import annotations

import codecs
import contextlib
import importlib
import math
import os
import zlib
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from kftune.data.textfile import (
    BLOCK_BYTES,
    ENV_MAX_BYTES,
    ENV_MAX_RATIO,
    ENV_MAX_ROWS,
    RATIO_FREE_BYTES,
    NumericRows,
    ReadLimits,
    check_regular_file,
    line_blocks,
    read_values,
)
from kftune.data.validate import UNITS, check_increasing
from kftune.errors import ConfigError, DataError, excerpt


@dataclass
class Table:
    """What a reader returns.

    Attributes:
        columns: source name → (n,) float64 raw values, in the file's units.
        units: source name → unit the file declares (only those it declares).
        time: (n,) time [s] for a format with its own time axis (MDF), else None.
        row_offset: the row number a user sees for sample 0 (a CSV's first data line, 1 for
            1-based indices).
        files: source name → the file that holds it, for a format of one file per signal
            (messages name that file), else empty.
    """

    columns: dict[str, np.ndarray]
    units: dict[str, str] = field(default_factory=dict)
    time: np.ndarray | None = None
    row_offset: int = 1
    files: dict[str, str] = field(default_factory=dict)


Reader = Callable[[Path, Sequence[str], Mapping[str, Any], ReadLimits], Table]


@dataclass(frozen=True)
class Format:
    """One file format: its readers' name, suffixes, function, extra and options."""

    name: str
    suffixes: tuple[str, ...]
    read: Reader
    extra: str | None
    options: tuple[str, ...]
    own_time: bool = False


def require(module: str, extra: str, what: str) -> Any:
    """Import an optional reader's package, or say which extra installs it.

    Raises:
        ConfigError: the package is missing (exit code 3 on the command line).
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ConfigError(
            f"reading {what} needs the optional package {module.split('.')[0]!r}, which is "
            f"not installed: pip install 'kftune[{extra}]'"
        ) from None


def _not_found(what: str, name: str, known: Collection[str], file: str) -> DataError:
    return DataError(
        f"{what} {excerpt(name)} not found; the file has {excerpt(list(known), 300)} (in "
        "file order)",
        file=file,
        column=name,
    )


# ----------------------------------------------------------------------------- text
#: Separators a CSV's header row is sniffed for.
SNIFFED = (",", ";", "\t", "|")


def _split_unit(name: str) -> tuple[str, str | None]:
    """``"speed [km/h]"`` → ``("speed", "km/h")``; ``"wheel_fl(kmph)"`` → ``("wheel_fl",
    "kmph")`` when what the parentheses hold is a unit of
    :data:`~kftune.data.validate.UNITS` (``"p(front)"`` stays a name); a name without
    either has no unit."""
    name = name.strip().strip('"').strip()
    if name.endswith("]") and "[" in name:
        head, _, unit = name[:-1].rpartition("[")
        return head.strip(), unit.strip()
    if name.endswith(")") and "(" in name:
        head, _, unit = name[:-1].rpartition("(")
        if unit.strip() in UNITS and head.strip():
            return head.strip(), unit.strip()
    return name, None


def _units_like(line: str, delimiter: str) -> bool:
    """Whether a CSV row is a row of units, not data: no field is a number, and some field
    (``ms``, ``[km/h]``, ``°/s``) is a unit of :data:`~kftune.data.validate.UNITS`."""
    fields = [f.strip().strip('"').strip().strip("[]()").strip() for f in line.split(delimiter)]

    def number(text: str) -> bool:
        try:
            float(text.replace(",", "."))
        except ValueError:
            return False
        return True

    return not any(number(f) for f in fields if f) and any(f in UNITS for f in fields)


def read_text_table(
    path: Path, names: Sequence[str], options: Mapping[str, Any], limits: ReadLimits
) -> Table:
    """A wide CSV or TSV: a header row of names, optionally a row of units, then one row of
    numbers per sample. Only the columns named are parsed (others may hold text).

    ``options``: ``delimiter`` (default sniffed from the header row among :data:`SNIFFED`;
    with a decimal comma, among the others), ``units_row``, ``encoding``, ``decimal``
    (``"."``, the default, or ``","``: ``12340,5`` as a German export writes it; with ``;``
    or a tab between the fields). A number that cannot be read in the second row, where
    that row holds units and ``units_row`` is not set, is refused with a message that
    suggests ``units_row = true``."""
    file = str(path)
    delimiter = options.get("delimiter")
    decimal = options.get("decimal", ".")
    encoding = options.get("encoding", "utf-8")
    if codecs.lookup(encoding).name == "utf-8":
        fix = (
            'set [source] encoding = "cp1252" in the mapping for a file written by Windows '
            'software ("latin-1" for ISO 8859-1), or re-save the file as UTF-8'
        )
    else:
        fix = f"expected text in the encoding {encoding!r} of [source] encoding: is it another?"
    with contextlib.closing(line_blocks(path, limits, encoding=encoding, fix=fix)) as blocks:
        first_row, lines = next(blocks, (1, []))
        if not lines or not lines[0].strip():
            raise DataError(
                "empty file: expected a header row naming the columns", file=file, row=1
            )
        if delimiter is None:
            if ".tsv" in path.name.lower():
                delimiter = "\t"
            else:
                among = [s for s in SNIFFED if s != decimal]
                delimiter = max(among, key=lambda s: (lines[0].count(s), -among.index(s)))
                if decimal == "," and lines[0].count(delimiter) == 0 and "," in lines[0]:
                    raise DataError(
                        '[source] decimal = "," but the header row separates its names by '
                        "commas: a decimal comma needs another delimiter (';' or a tab)",
                        file=file,
                        row=first_row,
                    )
        # numpy.savetxt writes its header after "# ": the first name is "# time(s)"
        header = [_split_unit(h) for h in lines[0].removeprefix("#").split(delimiter)]
        heads = [h for h, _ in header]
        units = {h: u for h, u in header if u}
        body = 1
        if options.get("units_row"):
            if len(lines) < 2:
                raise DataError("no units row after the header (units_row = true)", file=file)
            row_units = [u.strip().strip('"').strip() for u in lines[1].split(delimiter)]
            if len(row_units) != len(heads):
                raise DataError(
                    f"the units row has {len(row_units)} fields, the header {len(heads)}",
                    file=file,
                    row=first_row + 1,
                )
            units.update({h: u for h, u in zip(heads, row_units) if u})
            body = 2
        usecols = []
        for name in names:
            if name not in heads:
                raise _not_found("column", name, heads, file)
            if heads.count(name) > 1:
                raise DataError("column name appears twice in the header", file=file, column=name)
            usecols.append(heads.index(name))
        rows = NumericRows(file, heads, delimiter, limits=limits, usecols=usecols, decimal=decimal)
        try:
            rows.add(first_row + body, lines[body:])
        except DataError as exc:
            if body != 1 or exc.row != first_row + 1 or not _units_like(lines[1], delimiter):
                raise
            raise DataError(
                f"{exc.message}; this row looks like a row of units "
                f"({excerpt(lines[1].strip(), 80)}): set units_row = true in the mapping's "
                "[source] table",
                file=exc.file,
                column=exc.column,
                row=exc.row,
            ) from None
        for first, more in blocks:
            rows.add(first, more)
    if rows.n == 0:
        raise DataError("no data rows after the header", file=file, row=first_row + body)
    return Table(
        dict(zip(names, rows.columns())),
        {n: units[n] for n in names if n in units},
        row_offset=first_row + body,
    )


# ----------------------------------------------------------------------------- column files
def read_column_files(
    path: Path, names: Sequence[str], options: Mapping[str, Any], limits: ReadLimits
) -> Table:
    """A folder of one plain-text file per signal, all aligned sample by sample: the signal
    ``name`` is the file ``<name><suffix>`` (``suffix`` of ``options``, default ``.txt``; a
    name that ends in it is the file's whole name), one value a line, lines starting with
    ``#`` or ``%`` comments (:func:`~kftune.data.textfile.read_values`). The layout of many
    logger exports, and of the revs-250lm recording. Units: the mapping's, or SI."""
    suffix = options.get("suffix", ".txt")
    files = {n: path / (n if n.endswith(suffix) else n + suffix) for n in names}
    columns = {}
    for name, file in files.items():
        if not file.exists():
            known = sorted(p.name for p in path.glob(f"*{suffix}"))
            raise DataError(
                f"signal {excerpt(name)}: no file {excerpt(file.name)} in the folder; it has "
                f"{excerpt(known, 300)}",
                file=str(path),
                column=name,
            )
        check_regular_file(file)
        columns[name] = read_values(file, limits)
    sizes = [v.size for v in columns.values()]
    n = max(set(sizes), key=lambda k: (sizes.count(k), -sizes.index(k)))  # the most common
    for name, values in columns.items():
        if values.size != n:  # rows as the file's line numbers: where the shorter one ends
            raise DataError(
                f"{values.size} samples, {sizes.count(n)} other file(s) of the folder {n}: "
                "the files of one recording must be aligned sample by sample",
                file=str(files[name]),
                column=name,
                row=min(values.size, n) + 1,
            )
    return Table(columns, row_offset=1, files={k: str(f) for k, f in files.items()})


# ----------------------------------------------------------------------------- Parquet
def read_parquet(
    path: Path, names: Sequence[str], options: Mapping[str, Any], limits: ReadLimits
) -> Table:
    """A Parquet file (pyarrow): one numeric column per signal; a field's ``unit``
    metadata, where present, is its declared unit."""
    pa = require("pyarrow", "parquet", "Parquet files")
    pq = require("pyarrow.parquet", "parquet", "Parquet files")
    file = str(path)
    try:
        meta = pq.ParquetFile(file)
        schema = meta.schema_arrow
        n = meta.metadata.num_rows
    except Exception as exc:  # ArrowInvalid, OSError, …: bad input, without a traceback
        raise DataError(
            f"not a readable Parquet file ({type(exc).__name__}: {excerpt(str(exc), 120)})",
            file=file,
        ) from None
    if n > limits.max_rows:
        raise DataError(
            f"{n:,} rows, more than the limit of {limits.max_rows:,}: raise it with the "
            f"environment variable {ENV_MAX_ROWS} if the file is genuine",
            file=file,
        )
    units = {}
    for name in names:
        if name not in schema.names:
            raise _not_found("column", name, schema.names, file)
        kind = schema.field(name).type
        if not (pa.types.is_integer(kind) or pa.types.is_floating(kind)):
            raise DataError(f"column type {kind}; expected numbers", file=file, column=name)
        unit = (schema.field(name).metadata or {}).get(b"unit")
        if unit:
            units[name] = unit.decode("utf-8", "replace")
    try:
        table = meta.read(columns=list(names))
    except Exception as exc:
        raise DataError(
            f"cannot read the columns ({type(exc).__name__}: {excerpt(str(exc), 120)})", file=file
        ) from None
    columns = {
        name: np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=np.float64).copy()
        for name in names
    }
    return Table(columns, units, row_offset=1)


# ----------------------------------------------------------------------------- MATLAB
#: MATLAB classes of numeric arrays (the ``MATLAB_class`` attribute of a v7.3 variable).
MATLAB_NUMERIC = frozenset(
    {"double", "single", "logical", *(f"{s}int{b}" for s in ("", "u") for b in (8, 16, 32, 64))}
)


#: The bytes that open HDF5 data, at offset 512 of a MATLAB v7.3 file (after its header).
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def mat_variables(
    path: Path, names: Sequence[str], struct: str | None, limits: ReadLimits
) -> dict[str, np.ndarray]:
    """The named numeric vectors of a MATLAB file (v4–v7.2 through SciPy, v7.3 through
    h5py), from its top level or from the struct at the dotted path ``struct``.

    Returns:
        name → (n,) float64.

    Raises:
        DataError: naming the file and the variable: not found (listing the ones there are),
            not a real numeric vector, more elements than ``limits.max_rows``, an unreadable
            file.
    """
    from scipy.io import matlab

    file = str(path)
    try:
        with open(path, "rb") as fh:
            major, _ = matlab.matfile_version(fh)
            fh.seek(512)
            hdf5 = fh.read(8) == HDF5_SIGNATURE
    except Exception as exc:
        raise DataError(
            f"not a readable MATLAB file ({type(exc).__name__}: {excerpt(str(exc), 120)})",
            file=file,
        ) from None
    if major == 2 and not hdf5:
        raise DataError(
            "not a readable MATLAB file (its header says v7.3, but no HDF5 data follow it)",
            file=file,
        )
    if major == 2:
        values = _mat73_variables(path, names, struct, limits)
    elif major == 0:
        if struct:
            raise DataError(f"struct {excerpt(struct)} not found (a v4 file has none)", file=file)
        values = _mat4_variables(path, names, limits)
    else:
        values = _mat5_variables(path, names, struct, limits)
    out = {}
    for name, value in values.items():
        a = np.asarray(value)
        if np.iscomplexobj(a):
            raise DataError(
                f"variable {excerpt(name)} is complex; expected real numbers",
                file=file,
                column=name,
            )
        if a.ndim == 2 and 1 in a.shape:
            a = a.ravel()
        if a.ndim != 1 or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise DataError(
                f"variable {excerpt(name)} must be a numeric vector, got shape {a.shape} "
                f"dtype {a.dtype}",
                file=file,
                column=name,
            )
        out[name] = a.astype(np.float64, copy=False)
    return out


def _too_many(name: str, size: int, limits: ReadLimits, file: str) -> DataError:
    return DataError(
        f"variable {excerpt(name)} has {size:,} elements, more than the limit of "
        f"{limits.max_rows:,} rows: raise it with the environment variable {ENV_MAX_ROWS} (or "
        "ReadLimits(max_rows=...)) if the file is genuine",
        file=file,
        column=name,
    )


def _unreadable(exc: Exception, file: str) -> DataError:
    # SciPy's reader fails on a damaged or foreign file with any of a dozen exception types
    # (MatReadError, ValueError, zlib.error, IndexError, even UnboundLocalError, found by
    # fuzzing): each is bad input, reported without a traceback
    return DataError(
        f"not a readable MATLAB file ({type(exc).__name__}: {excerpt(str(exc), 120)})",
        file=file,
    )


def _mat4_variables(path: Path, names: Sequence[str], limits: ReadLimits) -> dict[str, Any]:
    """MATLAB v4 (no structs): the named variables through ``scipy.io.loadmat``, each
    sized from its header (``whosmat``) before anything is loaded."""
    from scipy import io as sio

    file = str(path)
    try:
        sizes = {name: math.prod(shape) for name, shape, _ in sio.whosmat(file)}
        for name in names:
            if name not in sizes:
                raise _not_found("variable", name, sizes, file)
            if sizes[name] > limits.max_rows:
                raise _too_many(name, sizes[name], limits, file)
        data = sio.loadmat(file, variable_names=list(names))
        return {name: data[name] for name in names}
    except DataError:
        raise
    except Exception as exc:
        raise _unreadable(exc, file) from None


#: Most bytes SciPy's reader may read of one compressed element: its headers (MATLAB names
#: are at most 63 characters) and the field names of the structs on the way (64 bytes a
#: field); the numbers of mapped variables are read by kftune, sized from their headers.
MAT5_MAX_HEADER_BYTES = 16 * 2**20


class _Inflated:
    """One compressed element of a MAT file as a stream SciPy's reader can read: inflated
    in blocks of at most :data:`~kftune.data.textfile.BLOCK_BYTES` as they are asked for
    (SciPy's own stream inflates each 256 kB of input whole: a field of zeros skipped took
    its full size in memory), counting the bytes inflated in ``budget`` (``[bytes left]``,
    shared by the file's elements: ``limits.max_bytes``)."""

    def __init__(self, fh: Any, nbytes: int, budget: list[int], limit: int, file: str) -> None:
        self._fh, self._left, self._budget = fh, nbytes, budget
        self._limit, self._file = limit, file
        self._z = zlib.decompressobj()
        self._pos = 0
        self._header_bytes = 0

    def _chunk(self, want: int) -> bytes:
        """Up to ``want`` inflated bytes; ``b""`` at the end of the element."""
        while True:
            data = self._z.unconsumed_tail
            if not data:
                data = self._fh.read(min(self._left, 2**16)) if self._left > 0 else b""
                self._left -= len(data)
                if not data:
                    return b""
            out = self._z.decompress(data, want)
            if out:
                self._pos += len(out)
                self._budget[0] -= len(out)
                if self._budget[0] < 0:
                    raise DataError(
                        f"more than {self._limit:,} bytes after decompression; reading stopped "
                        f"at this limit: raise it with the environment variable {ENV_MAX_BYTES} "
                        "(or ReadLimits(max_bytes=...)) if the file is genuine",
                        file=self._file,
                    )
                return out
            if self._z.eof:
                return b""

    def read(self, n: int) -> bytes:
        """SciPy's reads (headers, a struct's field names): at most
        :data:`MAT5_MAX_HEADER_BYTES` in all from one element, as a damaged or hostile size
        would have SciPy fill a buffer of up to ``limits.max_bytes`` with it."""
        self._header_bytes += n
        if self._header_bytes > MAT5_MAX_HEADER_BYTES:
            raise DataError(
                f"not a readable MATLAB file (a variable's headers or field names take more "
                f"than {MAT5_MAX_HEADER_BYTES:,} bytes)",
                file=self._file,
            )
        return self.read_data(n)

    def read_data(self, n: int) -> bytes:
        """kftune's own read of a mapped variable's numbers (sized from its header)."""
        parts = []
        while n > 0:
            data = self._chunk(min(n, BLOCK_BYTES))
            if not data:
                break
            parts.append(data)
            n -= len(data)
        return b"".join(parts)

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = 0) -> int:
        target = offset if whence == 0 else self._pos + offset
        if target < self._pos:
            raise OSError("cannot seek backwards in a compressed element")
        while self._pos < target and self._chunk(min(target - self._pos, BLOCK_BYTES)):
            pass
        return self._pos


#: What the MATLAB v5 walker uses of SciPy's private MAT-file modules
#: (``scipy.io.matlab._mio5``, ``_mio5_params``, ``_mio5_utils``: SciPy has no public API
#: that reads one element at a time), as ``module.attribute``; checked before a file is
#: read, so that a SciPy whose internals differ is named as the cause, not the file.
MAT5_SCIPY_INTERNALS = (
    "_mio5.MatFile5Reader.initialize_read",
    "_mio5.MatFile5Reader.read_file_header",
    "_mio5.MatFile5Reader.end_of_stream",
    "_mio5_utils.VarReader5.set_stream",
    "_mio5_utils.VarReader5.read_full_tag",
    "_mio5_utils.VarReader5.read_header",
    "_mio5_utils.VarReader5.shape_from_header",
    "_mio5_utils.VarReader5.read_fieldnames",
    "_mio5_params.mxSTRUCT_CLASS",
    "_mio5_params.miMATRIX",
    "_mio5_params.miCOMPRESSED",
    "_mio5_params.mclass_info",
)
#: The attributes of a ``MatFile5Reader`` after ``initialize_read`` that the walker uses.
MAT5_SCIPY_READER = ("_file_reader", "_matrix_reader", "byte_order")


def _scipy_mat5(file: str) -> tuple[Any, Any]:
    """SciPy's private modules ``_mio5`` and ``_mio5_params``, checked to hold every name
    of :data:`MAT5_SCIPY_INTERNALS`.

    Raises:
        DataError: naming the file, the SciPy version and what it lacks (exit 3), when this
            SciPy's internals are not the ones the walker was written against.
    """
    missing = []
    try:
        from scipy.io.matlab import _mio5, _mio5_params, _mio5_utils
    except ImportError:
        missing.append("the module scipy.io.matlab._mio5, _mio5_params or _mio5_utils")
    else:
        modules = {"_mio5": _mio5, "_mio5_params": _mio5_params, "_mio5_utils": _mio5_utils}
        for dotted in MAT5_SCIPY_INTERNALS:
            module, *attrs = dotted.split(".")
            obj: Any = modules[module]
            for attr in attrs:
                obj = getattr(obj, attr, None)
            if obj is None:
                missing.append(f"scipy.io.matlab.{dotted}")
    if missing:
        raise _lacks_scipy_internals(missing, file)
    return _mio5, _mio5_params


def _lacks_scipy_internals(missing: Sequence[str], file: str) -> DataError:
    """The error for a SciPy without the ``missing`` internals: the file is not at fault."""
    import scipy

    return DataError(
        f"cannot read a MATLAB v5-v7.2 file with SciPy {scipy.__version__}: kftune reads it "
        "one variable at a time through SciPy's private MAT-file modules, and this SciPy "
        f"lacks {', '.join(missing[:3])}; install a SciPy version kftune is tested with, or "
        "save the recording as MATLAB v7.3 (save -v7.3) or CSV",
        file=file,
    )


def _mat5_variables(
    path: Path, names: Sequence[str], struct: str | None, limits: ReadLimits
) -> dict[str, Any]:
    """MATLAB v5 to v7.2, walked element by element with SciPy's own reader: only the named
    vectors (at the top level, or fields of the struct at the dotted path ``struct``) are
    read, each checked from its header (class, number of elements) before its data are
    loaded; every other variable and field is skipped unread (a compressed one is
    decompressed in blocks and dropped). Memory therefore follows the arrays kept, whatever
    else the file holds — ``loadmat`` would load a whole struct to reach one field."""
    file = str(path)
    _mio5, _mio5_params = _scipy_mat5(file)
    parts = struct.split(".") if struct else []
    out: dict[str, Any] = {}
    known: list[str] = []  # the names where the variables are looked for
    reached = not parts  # the struct was found (the top level: no struct asked for)
    budget = [limits.max_bytes]  # bytes inflated from compressed elements, at most

    def element(
        reader: Any, stream: Any, header: Any, name: str, rest: list[str], end: int
    ) -> None:
        """Read what is wanted of the element ``name`` (a variable or a field, ending at
        ``end`` in ``stream``) whose header was read: the struct ``rest[0]`` of the path
        (its fields, recursively), or a named vector when ``rest`` is empty."""
        nonlocal reached, known
        if rest:
            if header.mclass != _mio5_params.mxSTRUCT_CLASS:
                raise DataError(f"{excerpt(struct)} is not a struct", file=file)
            shape = reader.shape_from_header(header)
            if math.prod(shape) != 1:
                raise DataError(
                    f"{excerpt(struct)} is a struct array of shape {shape}; expected one struct",
                    file=file,
                )
            fields = list(reader.read_fieldnames())
            if len(rest) == 1:
                reached, known = True, fields
            for field in fields:
                mdtype, nbytes = reader.read_full_tag()
                start = stream.tell()
                if mdtype != _mio5_params.miMATRIX:
                    raise DataError(
                        f"not a readable MATLAB file (field {excerpt(field)} of "
                        f"{excerpt(struct)} is not a matrix element)",
                        file=file,
                    )
                if nbytes and (field == rest[1] if len(rest) > 1 else field in names):
                    sub = reader.read_header(False)
                    element(reader, stream, sub, field, rest[1:], start + nbytes)
                stream.seek(start + nbytes)
            return
        if name in names:
            shape = reader.shape_from_header(header)
            out[name] = _mat5_numeric(stream, order, header.mclass, shape, end, name, limits, file)

    try:
        with open(path, "rb") as fh:
            top = _mio5.MatFile5Reader(fh)
            top.initialize_read()
            lacks = [a for a in MAT5_SCIPY_READER if getattr(top, a, None) is None]
            if lacks:
                raise _lacks_scipy_internals([f"MatFile5Reader().{a}" for a in lacks], file)
            top.read_file_header()
            reader = top._matrix_reader
            order = top.byte_order
            while not top.end_of_stream():
                mdtype, nbytes = top._file_reader.read_full_tag()
                end = fh.tell() + nbytes
                stream: Any = fh
                if mdtype == _mio5_params.miCOMPRESSED:
                    stream = _Inflated(fh, nbytes, budget, limits.max_bytes, file)
                reader.set_stream(stream)
                if stream is not fh:
                    mdtype, nbytes = reader.read_full_tag()
                if mdtype != _mio5_params.miMATRIX:
                    raise ValueError(f"expected a matrix element, got type {mdtype}")
                inner_end = stream.tell() + nbytes
                header = reader.read_header(False)
                name = header.name.decode("latin1")
                if not parts:
                    known.append(name)
                if (name == parts[0]) if parts else (name in names):
                    element(reader, stream, header, name, parts, inner_end)
                fh.seek(end)
    except DataError:
        raise
    except Exception as exc:
        raise _unreadable(exc, file) from None
    if not reached:
        raise DataError(f"struct {excerpt(struct)} not found", file=file)
    for name in names:
        if name not in out:
            raise _not_found("variable", name, known, file)
    return out


#: MAT-file data types of numbers (miINT8 … miUINT64, by the format's codes) → NumPy type.
MAT5_NUMBERS = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    9: "f8",
    12: "i8",
    13: "u8",
}


def _read_exactly(stream: Any, n: int, file: str) -> bytes:
    data = stream.read_data(n) if isinstance(stream, _Inflated) else stream.read(n)
    if len(data) != n:
        raise DataError("not a readable MATLAB file (it ends inside a variable)", file=file)
    return data


def _mat5_numeric(
    stream: Any,
    order: Literal["<", ">"],  # scipy's byte_order of the file
    mclass: int,
    shape: tuple[int, ...],
    end: int,
    name: str,
    limits: ReadLimits,
    file: str,
) -> np.ndarray:
    """The numbers of the element ``name`` (class ``mclass``, ``shape``), whose header was
    read and whose data element follows in ``stream``, up to ``end``: checked from the
    header (a numeric class, at most ``limits.max_rows`` elements) before anything is
    loaded, then read here (SciPy's reader indexes a table by the data element's type
    unchecked: a damaged type crashed the process).

    Raises:
        DataError: naming the file and the variable: not numbers, too many, complex (an
            imaginary part follows the real one), or a data element that does not fit.
    """
    from scipy.io.matlab import _mio5_params

    cls = _mio5_params.mclass_info.get(mclass, "unknown")
    if cls not in MATLAB_NUMERIC:
        raise DataError(
            f"variable {excerpt(name)} is a MATLAB {cls}; expected a real numeric vector",
            file=file,
            column=name,
        )
    size = math.prod(shape)
    if size > limits.max_rows:
        raise _too_many(name, size, limits, file)
    tag = _read_exactly(stream, 8, file)
    mdtype, nbytes = np.frombuffer(tag, dtype=f"{order}u4").tolist()
    small = mdtype >> 16  # a small data element: its size, then its type, in 4 bytes
    if small:
        mdtype, nbytes = mdtype & 0xFFFF, small
    dtype = np.dtype(MAT5_NUMBERS.get(mdtype, "V")).newbyteorder(order)
    if dtype.kind == "V" or nbytes != size * dtype.itemsize or (small and nbytes > 4):
        raise DataError(
            f"not a readable MATLAB file (variable {excerpt(name)}: {nbytes} bytes of data "
            f"type {mdtype} for {size:,} elements)",
            file=file,
            column=name,
        )
    if small:
        data = tag[4 : 4 + nbytes]
    else:
        data = _read_exactly(stream, nbytes, file)
        stream.read(-nbytes % 8)  # padding to 8 bytes
    if stream.tell() < end:  # an imaginary part follows the real one
        raise DataError(
            f"variable {excerpt(name)} is complex; expected real numbers", file=file, column=name
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape, order="F")


def _mat73_variables(
    path: Path, names: Sequence[str], struct: str | None, limits: ReadLimits
) -> dict[str, Any]:
    """MATLAB v7.3: an HDF5 file (after a 512-byte header) with one dataset per variable,
    stored transposed (a MATLAB n×1 vector is a 1×n dataset) and tagged with its class in
    the attribute ``MATLAB_class``; a struct is a group."""
    h5py = require("h5py", "mat73", "MATLAB v7.3 (HDF5) files")
    file = str(path)
    try:
        fh = h5py.File(file, "r")
    except Exception as exc:
        raise DataError(
            f"not a readable MATLAB file (v7.3, HDF5: {type(exc).__name__}: "
            f"{excerpt(str(exc), 120)})",
            file=file,
        ) from None
    with fh:
        container = fh
        for part in struct.split(".") if struct else ():
            found = (
                _h5_member(fh, container, part, struct or "", file)
                if isinstance(container, h5py.Group)
                else None
            )
            if found is None:
                raise DataError(
                    f"struct {excerpt(struct)} not found (no field {excerpt(part)})", file=file
                )
            container = found
        if not isinstance(container, h5py.Group):
            raise DataError(f"{excerpt(struct)} is not a struct", file=file)
        known = [k for k in container if not k.startswith("#")]
        out = {}
        for name in names:
            if name not in known:
                raise _not_found("variable", name, known, file)
            item = _h5_member(fh, container, name, name, file)
            if isinstance(item, h5py.Dataset) and (item.is_virtual or item.external):
                kind = "virtual dataset" if item.is_virtual else "dataset with external storage"
                raise DataError(
                    f"variable {excerpt(name)} is an HDF5 {kind}: its data lie in "
                    "other files; kftune reads only data stored in the file itself (MATLAB "
                    "never writes these)",
                    file=file,
                    column=name,
                )
            cls = (
                item.attrs.get("MATLAB_class", b"double")
                if isinstance(item, h5py.Dataset)
                else b"struct"
            )
            cls = cls.decode("ascii", "replace") if isinstance(cls, bytes) else str(cls)
            if cls not in MATLAB_NUMERIC or item.dtype.names:  # compound: complex
                what = "complex" if cls in MATLAB_NUMERIC else f"a MATLAB {cls}"
                raise DataError(
                    f"variable {excerpt(name)} is {excerpt(what)}; expected a real numeric vector",
                    file=file,
                    column=name,
                )
            if item.dtype.kind not in "biuf":  # checked before loading: 1 MB strings …
                raise DataError(
                    f"variable {excerpt(name)} is stored as {excerpt(str(item.dtype), 40)}, "
                    "not as numbers; expected a real numeric vector",
                    file=file,
                    column=name,
                )
            if item.size > limits.max_rows:
                raise _too_many(name, int(item.size), limits, file)
            out[name] = item[()]
    return out


#: Most soft links followed to find one object of a v7.3 file (a chain longer than this
#: is taken for a loop).
MAX_SOFT_LINKS = 16


def _h5_member(root: Any, group: Any, name: str, label: str, file: str, hops: int = 0) -> Any:
    """The object ``name`` of an HDF5 group, or None if there is none — without ever leaving
    the file: an external link is refused, a soft link is followed by its path inside the
    file (each step checked the same way) and refused when it does not resolve or loops.

    Raises:
        DataError: naming the file and ``label`` (the variable or struct asked for).
    """
    import h5py

    if "/" in name or name in ("", "."):  # a path: its steps are links too, unchecked
        return None
    link = group.get(name, getlink=True)
    if link is None:
        return None
    if isinstance(link, h5py.ExternalLink):
        raise DataError(
            f"{excerpt(label)} is an HDF5 external link to another file; kftune reads only "
            "data stored in the file itself (MATLAB never writes links)",
            file=file,
            column=label,
        )
    if not isinstance(link, h5py.SoftLink):
        return group[name]  # a hard link: an object of this file
    if hops >= MAX_SOFT_LINKS:
        raise DataError(
            f"{excerpt(label)} is an HDF5 soft link that does not resolve (more than "
            f"{MAX_SOFT_LINKS} links in a row: a loop?)",
            file=file,
            column=label,
        )
    target: Any = root if link.path.startswith("/") else group
    for part in [p for p in link.path.split("/") if p not in ("", ".")]:
        found = (
            _h5_member(root, target, part, label, file, hops + 1)
            if isinstance(target, h5py.Group)
            else None
        )
        if found is None:
            raise DataError(
                f"{excerpt(label)} is an HDF5 soft link to {excerpt(link.path)}, which does not "
                "exist in the file",
                file=file,
                column=label,
            )
        target = found
    return target


def read_mat(
    path: Path, names: Sequence[str], options: Mapping[str, Any], limits: ReadLimits
) -> Table:
    """A MATLAB file: :func:`mat_variables`."""
    return Table(mat_variables(path, names, options.get("struct"), limits), row_offset=1)


# ----------------------------------------------------------------------------- MDF
def _check_mdf_records(mdf: Any, name: str, limits: ReadLimits, file: str) -> None:
    """Refuse the signal ``name`` when loading it would read more bytes of records than
    ``limits.max_bytes``, or (a compressed file) than ``limits.max_ratio`` times the file's
    size beyond :data:`~kftune.data.textfile.RATIO_FREE_BYTES`: asammdf reads its channel
    group's records whole (``cycles_nr`` records of ``samples_byte_nr`` bytes, from the
    group's header), and a signal of 1 MB arrays took 640 MB from a file of 500 kB."""
    packed = os.path.getsize(file)
    for g, _ in mdf.channels_db[name]:
        cg = mdf.groups[g].channel_group
        record = cg.samples_byte_nr + getattr(cg, "invalidation_bytes_nr", 0)
        total = cg.cycles_nr * record
        if total > min(limits.max_bytes, RATIO_FREE_BYTES + limits.max_ratio * packed):
            raise DataError(
                f"signal's channel group holds {cg.cycles_nr:,} records of {record:,} bytes "
                f"({total:,} bytes), more than {limits.max_bytes:,} bytes or "
                f"{limits.max_ratio} times the file's {packed:,}: raise the limits with the "
                f"environment variables {ENV_MAX_BYTES} and {ENV_MAX_RATIO} if the file is "
                "genuine",
                file=file,
                column=name,
            )


def read_mdf(
    path: Path, names: Sequence[str], options: Mapping[str, Any], limits: ReadLimits
) -> Table:
    """An MDF file (asammdf), its signals resampled onto one raster.

    The raster: ``sample_time`` (a step in seconds; the raster starts at the latest first
    timestamp of the signals), else ``raster = "<signal>"`` (that signal's own timestamps),
    else the timestamps of the mapped signal with the finest raster (smallest median step).
    Only the span that every signal covers is kept: raster points before the latest first
    sample or after the earliest last sample of any signal are dropped — nothing is
    extrapolated or held at the ends. Signals of a floating-point type are interpolated
    linearly between their two neighbouring samples; integer and boolean signals (states,
    counters) hold their previous sample. A signal's declared unit (``Signal.unit``) is
    taken when the mapping gives none.
    """
    asammdf = require("asammdf", "mdf", "MDF files")
    file = str(path)
    try:
        mdf = asammdf.MDF(file)
    except Exception as exc:
        raise DataError(
            f"not a readable MDF file ({type(exc).__name__}: {excerpt(str(exc), 120)})",
            file=file,
        ) from None
    raster = options.get("raster")
    step = options.get("sample_time")
    wanted = list(dict.fromkeys([*names, *([raster] if isinstance(raster, str) else [])]))
    signals: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    units: dict[str, str] = {}
    try:
        known = list(mdf.channels_db)
        for name in wanted:
            if name not in mdf.channels_db:
                raise _not_found("signal", name, known, file)
            try:
                # the samples its group's header records, checked before any is loaded
                cycles = max(
                    mdf.groups[g].channel_group.cycles_nr for g, _ in mdf.channels_db[name]
                )
                if cycles > limits.max_rows:
                    raise DataError(
                        f"signal has {cycles:,} samples, more than the limit of "
                        f"{limits.max_rows:,} rows: raise it with the environment variable "
                        f"{ENV_MAX_ROWS} (or ReadLimits(max_rows=...)) if the file is genuine",
                        file=file,
                        column=name,
                    )
                _check_mdf_records(mdf, name, limits, file)
                sig = mdf.get(name)
            except DataError:
                raise
            except Exception as exc:  # several channels of this name, a damaged block
                raise DataError(
                    f"cannot read the signal ({type(exc).__name__}: {excerpt(str(exc), 160)})",
                    file=file,
                    column=name,
                ) from None
            samples, stamps = np.asarray(sig.samples), np.asarray(sig.timestamps, dtype=float)
            if samples.ndim != 1 or not (
                np.issubdtype(samples.dtype, np.number) or samples.dtype == bool
            ):
                raise DataError(
                    f"signal of shape {samples.shape} dtype {samples.dtype}; expected numbers",
                    file=file,
                    column=name,
                )
            if samples.size < 2 or samples.size > limits.max_rows:
                raise DataError(
                    f"signal has {samples.size:,} samples; expected 2 to {limits.max_rows:,}",
                    file=file,
                    column=name,
                )
            try:
                check_increasing(stamps, file=file, column=name, row_offset=1)
            except DataError as exc:  # the shared check, its row a sample of this signal
                raise DataError(
                    f"the signal's own timestamps (row: its sample, from 1): {exc.message}",
                    file=file,
                    column=name,
                    row=exc.row,
                ) from None
            signals[name] = (samples, stamps)
            if getattr(sig, "unit", ""):
                units[name] = str(sig.unit)
    finally:
        mdf.close()
    start = max(s[1][0] for s in signals.values())
    end = min(s[1][-1] for s in signals.values())
    if not start < end:
        raise DataError(
            f"the signals {excerpt(list(signals), 200)} share no time span (latest start "
            f"{start:g} s, earliest end {end:g} s)",
            file=file,
        )
    if step is not None:
        grid = start + np.arange(math.floor((end - start) / step * (1 + 1e-12)) + 1) * step
    else:
        if raster is None:
            raster = min(names, key=lambda n: float(np.median(np.diff(signals[n][1]))))
        stamps = signals[raster][1]
        grid = stamps[(stamps >= start) & (stamps <= end)]
    columns = {}
    for name in names:
        samples, stamps = signals[name]
        if np.issubdtype(samples.dtype, np.floating):
            columns[name] = np.interp(grid, stamps, samples)
        else:
            hold = np.searchsorted(stamps, grid, side="right") - 1
            columns[name] = samples[np.clip(hold, 0, samples.size - 1)].astype(np.float64)
    return Table(columns, {n: units[n] for n in names if n in units}, time=grid, row_offset=1)


# ----------------------------------------------------------------------------- registry
#: Every format read, in the order listed to users. The one place suffixes are named.
FORMATS: tuple[Format, ...] = (
    Format("CSV/TSV", (".csv", ".tsv", ".csv.gz", ".tsv.gz"), read_text_table, None,
           ("delimiter", "units_row", "encoding", "decimal")),
    Format("Parquet", (".parquet", ".pq"), read_parquet, "parquet", ()),
    Format("MATLAB", (".mat",), read_mat, "mat73", ("struct",)),
    Format("MDF4", (".mf4", ".mdf"), read_mdf, "mdf", ("raster",), own_time=True),
    Format("columns", (), read_column_files, None, ("suffix",)),
)  # fmt: skip
#: The format of a folder: one file per signal.
COLUMN_FILES = FORMATS[-1]

#: ``[source]`` options of every format, applied by the importer: ``format`` (a name of
#: :func:`format_named`, instead of the suffix) and ``raster`` (a step [s] to resample onto;
#: an MDF file's ``raster`` may also name a signal, see :func:`read_mdf`).
COMMON_OPTIONS: tuple[str, ...] = ("format", "raster")
#: Reader options a mapping's ``[source]`` table may hold (each format uses its own).
READER_OPTIONS: tuple[str, ...] = tuple(
    dict.fromkeys([*COMMON_OPTIONS, *(o for f in FORMATS for o in f.options)])
)


def suffix_text(fmt: Format) -> str:
    """A format's suffixes for messages (``.csv .tsv``), or what it reads instead."""
    return " ".join(fmt.suffixes) or "a folder of one file per signal"


def format_names(fmt: Format) -> tuple[str, ...]:
    """The names :func:`format_named` takes for a format, lower case: each part of its name
    (``CSV/TSV``: ``csv``, ``tsv``) and its simple suffixes without the dot (``mat``)."""
    names = [*fmt.name.lower().split("/"), *(s[1:] for s in fmt.suffixes if s.count(".") == 1)]
    return tuple(dict.fromkeys(names))


def format_named(name: str) -> Format:
    """The format of a name of :func:`format_names` (case-insensitive).

    Raises:
        ConfigError: a name of no format (the message lists the names).
    """
    for fmt in FORMATS:
        if name.strip().lower() in format_names(fmt):
            return fmt
    raise ConfigError(
        f"unknown format {excerpt(name)}; expected one of "
        f"{[n for f in FORMATS for n in format_names(f)]}"
    )


def format_of(path: str | Path) -> Format:
    """The format of a file, by its suffix (case-insensitive; the longest match wins); of
    a folder, :data:`COLUMN_FILES`.

    Raises:
        DataError: a suffix no reader takes (the message lists the ones read, and how a
            mapping names the format of a file of another suffix).
    """
    if Path(path).is_dir():
        return COLUMN_FILES
    name = Path(path).name.lower()
    matches = [(len(s), f) for f in FORMATS for s in f.suffixes if name.endswith(s)]
    if not matches:
        known = ", ".join(f"{f.name} ({suffix_text(f)})" for f in FORMATS)
        raise DataError(
            f"unknown file type; kftune reads {known}: for another suffix (a .txt or .dat "
            'export), name the format in the mapping, e.g. [source] format = "csv"',
            file=str(path),
        )
    return max(matches, key=lambda m: m[0])[1]
