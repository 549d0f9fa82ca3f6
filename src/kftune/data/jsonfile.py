"""One reader of the JSON and TOML files users hand to kftune (tuned files, manifests,
results, configurations, import mappings).

:func:`json.loads` and :func:`tomllib.loads` fail on hostile input in ways that are not
their decode errors: an integer of more than 4,300 digits is a ``ValueError`` from
Python's int-conversion limit (which exists because converting one costs quadratic time),
deep nesting a ``RecursionError``. Every reader goes through :func:`parse_json` or
:func:`parse_toml`, which turn each of those into a :class:`~kftune.errors.DataError`
naming the file, so none of them becomes a traceback; a file is read by
:func:`read_text`: a regular file only (a device such as ``/dev/zero`` never ends, a FIFO
blocks the open), and at most a size.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from kftune.data.textfile import check_regular_file
from kftune.errors import DataError, KftuneError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Most digits of an integer in a JSON file: Python's own default limit of int() on a
#: string (``sys.get_int_max_str_digits``), fixed here so that a raised process-wide limit
#: does not raise it. No number kftune writes comes near it.
MAX_INT_DIGITS = 4300
#: Largest JSON or TOML file read [bytes]: a tuned file is a few kB, a ``results.json`` of
#: ``compare`` with every evaluation's history a few MB; the text and the objects parsed
#: from it take several times the file's size in memory.
MAX_INPUT_BYTES = 256 * 2**20


class _LongInteger(KftuneError, ValueError):
    """An integer literal with more digits than :data:`MAX_INT_DIGITS`."""


def _parse_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise _LongInteger(digits)
    return int(text)


def parse_json(text: str, file: str) -> Any:
    """The JSON document ``text`` read from ``file`` (named in errors).

    Raises:
        DataError: naming ``file``: not JSON, an integer of more than
            :data:`MAX_INT_DIGITS` digits, or nesting deeper than Python's recursion limit.
    """
    try:
        return json.loads(text, parse_int=_parse_int)
    except _LongInteger as exc:
        raise DataError(
            f"not valid JSON: an integer with more than {MAX_INT_DIGITS:,} digits "
            f"({exc.args[0]:,})",
            file=file,
        ) from None
    except json.JSONDecodeError as exc:
        raise DataError(f"not valid JSON: {exc}", file=file) from None
    except RecursionError:
        raise DataError("not valid JSON: arrays or objects nest too deeply", file=file) from None
    except ValueError as exc:  # anything else json refuses (a number it cannot convert)
        raise DataError(f"not valid JSON: {exc}", file=file) from None


def parse_toml(text: str, file: str) -> dict[str, Any]:
    """The TOML document ``text`` read from ``file`` (named in errors).

    Raises:
        DataError: naming ``file``: not TOML, an integer of more than
            :data:`MAX_INT_DIGITS` digits, or nesting deeper than Python's recursion limit.
    """
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"not valid TOML: {exc}", file=file) from None
    except RecursionError:
        raise DataError("nests arrays or tables too deeply", file=file) from None
    except ValueError:  # an integer beyond Python's int-conversion limit
        raise DataError(
            f"not valid TOML: an integer with more than {MAX_INT_DIGITS:,} digits", file=file
        ) from None


def read_json(path: str | Path, max_bytes: int = MAX_INPUT_BYTES) -> Any:
    """The JSON document in the file ``path`` (:func:`read_text`, :func:`parse_json`)."""
    return parse_json(read_text(path, max_bytes), str(path))


def read_toml(path: str | Path, max_bytes: int = MAX_INPUT_BYTES) -> dict[str, Any]:
    """The TOML document in the file ``path`` (:func:`read_text`, :func:`parse_toml`)."""
    return parse_toml(read_text(path, max_bytes), str(path))


def read_text(path: str | Path, max_bytes: int = MAX_INPUT_BYTES) -> str:
    """The UTF-8 text of the file ``path``.

    Args:
        max_bytes: refuse a larger file without reading more of it.

    Raises:
        DataError: naming ``path``: missing, not a regular file (a folder, a device such as
            ``/dev/zero`` or a FIFO: refused before it is opened, as it would never end or
            block), unreadable, larger than ``max_bytes``, or not UTF-8.
    """
    p = Path(path)
    size = check_regular_file(p)
    try:
        with open(p, "rb") as fh:  # read(n) allocates n bytes first: no more than the file
            raw = fh.read(min(size, max_bytes) + 1)
    except OSError as exc:
        raise DataError(f"cannot be read ({exc.strerror or exc})", file=str(p)) from None
    if len(raw) > max_bytes:
        raise DataError(f"larger than {max_bytes:,} bytes", file=str(p))
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", file=str(p)) from None
    return text
