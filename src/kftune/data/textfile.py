"""Bounded, streaming reading of numeric text files: the CSV files of the kftune format and
the one-value-per-line signal files of column-per-file recordings.

A file is read in blocks of :data:`BLOCK_BYTES` (decompressed on the fly when its name ends
in ``.gz``); each block's rows are parsed by NumPy and appended to one growing buffer per
column (:class:`array.array`, which grows in place by ``realloc`` with 1/16 spare room and
is handed to NumPy without a copy). Memory therefore follows the arrays that are kept (plus
one block), never the size of the file's text. (Small per-block pieces joined at the end
would do as well on paper, but the C allocator keeps their freed heap: resident memory then
stays a whole copy higher than what Python counts.)

Limits — each stops the read with a :class:`~kftune.errors.DataError` naming the file, the
limit and how to raise it:

* ``max_bytes``: bytes read from one file, counted after decompression (a small gzip bomb
  stops here instead of filling the memory); environment variable ``KFTUNE_MAX_BYTES``,
  default :data:`DEFAULT_MAX_BYTES` (8 GiB);
* ``max_rows``: rows (samples) of one file or signal, which fix the memory the kept arrays
  take (8 bytes per value); ``KFTUNE_MAX_ROWS``, default :data:`DEFAULT_MAX_ROWS`
  (40 million: 100 hours at 100 Hz, and some);
* ``max_ratio``: bytes a gzipped file decompresses to, per byte of the file (beyond the
  first :data:`RATIO_FREE_BYTES`), checked (with ``max_bytes``) in a first pass that
  decompresses the file block by block and keeps nothing: a small file that unpacks to
  millions of rows is refused before a row of it is parsed (numeric CSV text compresses 3
  to 12 times, a logger's export with a hundred columns of zeros 30 times);
  ``KFTUNE_MAX_RATIO``, default :data:`DEFAULT_MAX_RATIO`;
* :data:`MAX_LINE_BYTES`: one line; a binary or sparse file without line breaks is refused
  after its first block;
* :data:`MAX_BLANK_LINES`: empty lines in a row (only allowed at the end of a file).

A source must be a regular file (:func:`check_regular_file`): a device such as
``/dev/zero`` or a FIFO is refused before it is opened, so that reading never blocks or
runs for ever.

Text is UTF-8 unless the caller names another encoding that keeps ASCII as it is (cp1252,
latin-1, …). Line ends LF or CRLF, a UTF-8 byte-order mark, and (in a CSV) a ``;`` or tab separator
named by the header row are handled. Trailing empty lines are ignored; an empty line with
data after it is an error naming its row. Messages quote at most a short excerpt of a file.
"""

from __future__ import annotations

import array
import codecs
import contextlib
import gzip
import io
import os
import re
import stat
import zlib
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kftune.errors import ConfigError, DataError, excerpt

#: Default of ``max_bytes``: the most bytes read from one file, after decompression.
DEFAULT_MAX_BYTES = 8 * 2**30
#: Default of ``max_rows``: the most rows (samples) of one file or signal.
DEFAULT_MAX_ROWS = 40_000_000
#: Default of ``max_ratio``: the most bytes a gzipped file decompresses to per byte of it.
#: A logger's export with many constant columns compresses 30 times (a CSV of 120 columns
#: of zeros, 3 signals and time: 30×); gzip reaches 1,000 on a bomb. The first pass keeps
#: nothing, so a bomb costs only the time to decompress this multiple of its size.
DEFAULT_MAX_RATIO = 100
#: Decompressed bytes that ``max_ratio`` does not count (a small file of constant rows).
RATIO_FREE_BYTES = 8 * 2**20
#: Environment variables that override the defaults (integers, ``4e9`` allowed).
ENV_MAX_BYTES = "KFTUNE_MAX_BYTES"
ENV_MAX_ROWS = "KFTUNE_MAX_ROWS"
ENV_MAX_RATIO = "KFTUNE_MAX_RATIO"
#: Most empty lines in a row (only allowed at the end of a file).
MAX_BLANK_LINES = 1000
#: Longest line accepted [bytes] (a CSV row of the kftune format is about 100 bytes).
MAX_LINE_BYTES = 64 * 2**10
#: Bytes read (and lines parsed) at a time.
BLOCK_BYTES = 2**20

#: CSV field separators recognised in a header row, in the order they are looked for.
SEPARATORS: dict[str, str] = {",": "comma", ";": "semicolon", "\t": "tab"}


@dataclass(frozen=True)
class ReadLimits:
    """How much one file may hold before reading stops (see the module docstring).

    Attributes:
        max_bytes: bytes read from one file, after decompression.
        max_rows: rows (samples) of one file or signal.
        max_ratio: bytes a gzipped file decompresses to, per byte of the file.
    """

    max_bytes: int = DEFAULT_MAX_BYTES
    max_rows: int = DEFAULT_MAX_ROWS
    max_ratio: int = DEFAULT_MAX_RATIO

    def __post_init__(self) -> None:
        for name in ("max_bytes", "max_rows", "max_ratio"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"ReadLimits.{name} must be an integer >= 1, got {value!r}")

    @classmethod
    def from_env(cls) -> ReadLimits:
        """The defaults, overridden by ``KFTUNE_MAX_BYTES`` / ``KFTUNE_MAX_ROWS`` /
        ``KFTUNE_MAX_RATIO`` when set.

        Raises:
            ConfigError: a variable that is not a whole number >= 1 (names it).
        """
        return cls(
            max_bytes=_env_int(ENV_MAX_BYTES, DEFAULT_MAX_BYTES),
            max_rows=_env_int(ENV_MAX_ROWS, DEFAULT_MAX_ROWS),
            max_ratio=_env_int(ENV_MAX_RATIO, DEFAULT_MAX_RATIO),
        )


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 1 and value < 2**63 and value == int(value)):
        raise ConfigError(
            f"environment variable {name} must be a whole number >= 1, got {excerpt(text)}"
        )
    return int(value)


def _limits(limits: ReadLimits | None) -> ReadLimits:
    return ReadLimits.from_env() if limits is None else limits


# ----------------------------------------------------------------------------- lines
def check_regular_file(path: str | Path) -> int:
    """Refuse a source that is not a regular file, before opening it (a FIFO would block
    the open, ``/dev/zero`` would never end).

    Returns:
        The file's size in bytes.

    Raises:
        DataError: naming the file: not found, a folder, a device, FIFO or socket.
    """
    file = str(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise DataError("file not found", file=file) from None
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or type(exc).__name__}", file=file) from None
    if stat.S_ISDIR(info.st_mode):
        raise DataError("is a folder; expected a file", file=file)
    if not stat.S_ISREG(info.st_mode):
        raise DataError(
            "not a regular file (a device, FIFO or socket); expected a file on disk", file=file
        )
    return info.st_size


def _open(path: Path) -> io.BufferedIOBase:
    if path.name.endswith(".gz"):
        return gzip.open(path, "rb")  # decompresses at most what each read asks for
    return open(path, "rb")


#: What a text file that is not UTF-8 is told to do, by default.
RESAVE_AS_UTF8 = "expected a text file in UTF-8 (re-save it as UTF-8)"


def _decode(data: bytes, file: str, row: int, encoding: str, fix: str) -> str:
    """Text with LF line ends (a CR before each LF dropped)."""
    if row == 1 and data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise DataError("UTF-16 text; expected UTF-8 (save it as UTF-8)", file=file, row=1)
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as exc:
        what = "UTF-8" if codecs.lookup(encoding).name == "utf-8" else encoding
        raise DataError(
            f"not {what} text (byte 0x{data[exc.start]:02x}): {fix}",
            file=file,
            row=row + data.count(b"\n", 0, exc.start),
        ) from None
    if "\x00" in text:
        raise DataError(
            "holds NUL bytes: a binary file, not text",
            file=file,
            row=row + text.count("\n", 0, text.index("\x00")),
        )
    if "\r" in text:
        text = text.replace("\r\n", "\n").removesuffix("\r")
    return text


def line_blocks(
    path: str | Path,
    limits: ReadLimits | None = None,
    *,
    encoding: str = "utf-8",
    fix: str = RESAVE_AS_UTF8,
) -> Generator[tuple[int, list[str]], None, None]:
    """The lines of a text file, in blocks: ``(number of the block's first line, lines)``.

    Lines are numbered from 1 and come without their line end (LF or CRLF); a UTF-8
    byte-order mark at the start is dropped.

    Args:
        path: the file (gzipped when its name ends in ``.gz``). limits: size limits.
        encoding: the text encoding, a codec Python knows that encodes ASCII as ASCII
            (UTF-8, cp1252, latin-1, …: blocks are cut at the byte of a line feed).
        fix: what the message of a file that is not in ``encoding`` tells the user to do.

    Raises:
        DataError: unreadable or not in ``encoding``, a line longer than
            :data:`MAX_LINE_BYTES`, line breaks that are a lone CR, or more than
            ``limits.max_bytes`` bytes.
    """
    path = Path(path)
    file = str(path)
    lim = _limits(limits)
    size = check_regular_file(path)
    gz = path.name.endswith(".gz")
    total = 0
    row = 1
    carry = b""
    first = True
    try:
        if gz:  # a first pass that keeps nothing: a bomb is refused before any parsing
            with _open(path) as fh:
                unpacked = 0
                while chunk := fh.read(BLOCK_BYTES):
                    unpacked += len(chunk)
                    _check_size(unpacked, lim, size, file)
        with _open(path) as fh:
            while True:
                chunk = fh.read(BLOCK_BYTES)
                if not chunk:
                    break
                total += len(chunk)
                _check_size(total, lim, size if gz else None, file)
                data = carry + chunk
                if first and data.startswith(codecs.BOM_UTF8):
                    encoding = "utf-8"  # the file says it is UTF-8, whatever was assumed
                cut = data.rfind(b"\n")
                if cut < 0:
                    carry = data
                    _check_line_length(carry, file, row)
                    continue
                carry = data[cut + 1 :]
                _check_line_length(carry, file, row + data.count(b"\n", 0, cut + 1))
                text = _decode(data[:cut], file, row, encoding, fix)
                if first:
                    text = _start(text, file)
                    first = False
                lines = text.split("\n")
                yield row, lines
                row += len(lines)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise DataError(f"not a valid gzip file: {excerpt(str(exc), 120)}", file=file) from None
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or type(exc).__name__}", file=file) from None
    if carry:
        text = _decode(carry, file, row, encoding, fix)
        if first:
            text = _start(text, file)
        yield row, [text]


def _check_size(total: int, lim: ReadLimits, packed: int | None, file: str) -> None:
    """Refuse a file once ``total`` bytes of it were read (after decompression) beyond
    ``lim.max_bytes``, or beyond ``lim.max_ratio`` times its size ``packed`` (a gzipped
    file; plus :data:`RATIO_FREE_BYTES`)."""
    if total > lim.max_bytes:
        raise DataError(
            f"more than {lim.max_bytes:,} bytes (after decompression); reading stopped at this "
            f"limit: raise it with the environment variable {ENV_MAX_BYTES} (or "
            "ReadLimits(max_bytes=...)) if the file is genuine",
            file=file,
        )
    if packed is not None and total > RATIO_FREE_BYTES + lim.max_ratio * packed:
        raise DataError(
            f"decompresses to more than {lim.max_ratio} times its {packed:,} bytes (reading "
            f"stopped after {total:,} bytes: a decompression bomb?): raise the limit with the "
            f"environment variable {ENV_MAX_RATIO} (or ReadLimits(max_ratio=...)) if the file "
            "is genuine",
            file=file,
        )


def _check_line_length(pending: bytes, file: str, row: int) -> None:
    if len(pending) > MAX_LINE_BYTES:
        raise DataError(
            f"line longer than {MAX_LINE_BYTES:,} bytes without a line break: expected a text "
            "file with one row per line (is it binary, or empty space?)",
            file=file,
            row=row,
        )


def _start(text: str, file: str) -> str:
    """The first block's text without a byte-order mark; refuses lone-CR line breaks."""
    text = text.removeprefix("\ufeff")
    if "\r" in text.split("\n", 1)[0]:
        raise DataError(
            "lines end in a lone CR (classic Mac OS line breaks); expected LF or CRLF",
            file=file,
            row=1,
        )
    return text


# ----------------------------------------------------------------------------- numbers
#: A plain decimal number (what NumPy's parser reads; ``float`` alone would also take
#: ``"2_2.5"`` as 22.5 and non-ASCII digits). Unambiguous, so a failed match is linear in
#: the length: ``\d+\.?\d*`` could split a run of digits at every position, and a 50,000-digit
#: field with a bad last character took 85 s to refuse.
_NUMBER = re.compile(
    r"[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|nan|inf(?:inity)?)", re.ASCII | re.I
)


class NumericRows:
    """Rows of numbers fed in blocks, appended to one growing float64 buffer per column.

    Args:
        file: reported in errors. names: column names, for errors (their number fixes the
            number of fields of a row). separator: field separator (``None``: one value a
            line). comments: prefixes of lines to skip. limits: ``max_rows``.
        decimal: the decimal mark, ``"."`` or ``","`` (a German export: ``12340,5``; the
            separator must then be another character), set by an import mapping's
            ``[source] decimal``; ``None``: ``"."``, where no option can change it (a
            number with a comma is then refused without naming the option).
    """

    def __init__(
        self,
        file: str,
        names: list[str],
        separator: str | None,
        comments: tuple[str, ...] = (),
        limits: ReadLimits | None = None,
        usecols: Sequence[int] | None = None,
        decimal: str | None = None,
    ) -> None:
        if decimal == "," and separator == ",":
            raise ValueError("a decimal comma needs a separator other than the comma")
        self.file = file
        self.decimal = decimal
        self.names = names
        self.separator = separator
        self.comments = comments
        self.limits = _limits(limits)
        self.usecols = list(range(len(names))) if usecols is None else list(usecols)
        self.n = 0
        self._columns = [array.array("d") for _ in self.usecols]
        self._blank_row: int | None = None  # an empty line, an error if data follow it

    def add(self, first_row: int, lines: list[str]) -> None:
        """Parse one block of lines (``first_row``: the file row of ``lines[0]``)."""
        rows: Sequence[int] = range(first_row, first_row + len(lines))
        if self.comments:
            kept = [(r, x) for r, x in zip(rows, lines) if not x.lstrip().startswith(self.comments)]
            rows, lines = [r for r, _ in kept], [x for _, x in kept]
        blank = [k for k, x in enumerate(lines) if not x.strip()]
        if self._blank_row is not None and len(blank) < len(lines):
            raise DataError("empty line inside the data", file=self.file, row=self._blank_row)
        if blank:
            if blank[-1] - blank[0] + 1 != len(blank) or blank[-1] != len(lines) - 1:
                raise DataError("empty line inside the data", file=self.file, row=rows[blank[0]])
            if self._blank_row is None:
                self._blank_row = rows[blank[0]]
            if rows[blank[-1]] - self._blank_row >= MAX_BLANK_LINES:
                raise DataError(
                    f"more than {MAX_BLANK_LINES:,} empty lines in a row; reading stopped: "
                    "expected rows of data, or the end of the file",
                    file=self.file,
                    row=self._blank_row,
                )
            lines, rows = lines[: blank[0]], rows[: blank[0]]
        if not lines:
            return
        if self.n + len(lines) > self.limits.max_rows:
            raise DataError(
                f"more than {self.limits.max_rows:,} rows; reading stopped at this limit: raise "
                f"it with the environment variable {ENV_MAX_ROWS} (or "
                "ReadLimits(max_rows=...)) if the file is genuine",
                file=self.file,
                row=rows[self.limits.max_rows - self.n],
            )
        by_column = np.ascontiguousarray(self._parse(lines, rows).T)
        for column, values in zip(self._columns, by_column):
            column.frombytes(memoryview(values).cast("B"))
        self.n += len(lines)

    def _parse(self, lines: list[str], rows: Sequence[int]) -> np.ndarray:
        every = self.usecols == list(range(len(self.names)))
        # with a decimal comma, every comma is one (the separator is another character)
        text = [x.replace(",", ".") for x in lines] if self.decimal == "," else lines
        try:
            with np.errstate(all="ignore"):
                values = np.loadtxt(
                    text,
                    delimiter=self.separator,
                    dtype=np.float64,
                    ndmin=2,
                    comments=None,
                    usecols=None if every else self.usecols,
                )
            if values.shape == (len(lines), len(self.usecols)) and (
                every
                or all(line.count(self.separator or "\n") == len(self.names) - 1 for line in lines)
            ):
                return values
        except ValueError:
            pass
        return self._parse_slowly(lines, rows)

    def _parse_slowly(self, lines: list[str], rows: Sequence[int]) -> np.ndarray:
        """Row by row, to name the first bad row and field (NumPy's parser stops at it
        without saying where)."""
        width = len(self.names)
        out = np.empty((len(lines), len(self.usecols)))
        for i, (row, line) in enumerate(zip(rows, lines)):
            fields = [line] if self.separator is None else line.split(self.separator)
            if len(fields) != width:
                raise DataError(
                    f"has {len(fields)} fields, the header has {width} (fields separated by "
                    f"{SEPARATORS.get(self.separator or ',', repr(self.separator))}s)",
                    file=self.file,
                    row=row,
                )
            for k, j in enumerate(self.usecols):
                text = fields[j]
                try:
                    number = text.replace(",", ".") if self.decimal == "," else text
                    if not _NUMBER.fullmatch(number.strip()):
                        raise ValueError(text)
                    out[i, k] = float(number)
                except ValueError:
                    hint = ""
                    if self.decimal == "," and "." in text:
                        hint = (
                            ' (with [source] decimal = "," a point is no decimal mark: a '
                            "thousands separator?)"
                        )
                    elif self.separator != "," and "," in text:
                        hint = (
                            " (a decimal comma? numbers need a decimal point)"
                            if self.decimal is None
                            else ' (a decimal comma? set decimal = "," in the mapping\'s '
                            "[source] table)"
                        )
                    what = "one number" if width == 1 else "a number"
                    raise DataError(
                        f"cannot read {excerpt(text.strip())} as {what}{hint}",
                        file=self.file,
                        column=self.names[j] if self.separator is not None else None,
                        row=row,
                    ) from None
        return out

    def columns(self) -> list[np.ndarray]:
        """The columns, (n,) float64 each, writable views of the buffers (no copy); no rows
        can be added afterwards."""
        return [np.frombuffer(column, dtype=np.float64) for column in self._columns]


def read_values(path: str | Path, limits: ReadLimits | None = None) -> np.ndarray:
    """One number per line; lines starting with ``#`` or ``%`` are comments.

    Returns:
        (n,) float64 array.

    Raises:
        DataError: naming the file and the row (the file's line number).
    """
    rows = NumericRows(str(path), [Path(path).stem], None, comments=("#", "%"), limits=limits)
    with contextlib.closing(line_blocks(path, limits)) as blocks:
        for first, lines in blocks:
            rows.add(first, lines)
    return rows.columns()[0]
