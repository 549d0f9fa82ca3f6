"""What the commands write and read at their edges: no output replaces an input of the same
command, every write is checked, only kftune's own files are deleted, every JSON a user
hands over is read by one loader that refuses hostile numbers by name, and numeric options
have documented upper limits. Each case asserts the exit code, that the message names the
file or option, that no traceback is printed and that nothing else is written."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import run_cli
from kftune.data.jsonfile import MAX_INT_DIGITS, parse_json
from kftune.errors import DataError

LONG = "9" * (MAX_INT_DIGITS + 1)


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


# ------------------------------------------------------------------ JSON with huge numbers
def _tuned(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["evaluate", "--params", "t.json"]


def _estimate(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["estimate", "--params", "t.json", "-o", "est"]


def _export(tmp: Path, text: str) -> list[str]:
    (tmp / "t.json").write_text(text)
    return ["export", "t.json", "-o", "t.h", "-f", "c"]


def _manifest(tmp: Path, text: str) -> list[str]:
    (tmp / "ds").mkdir()
    (tmp / "ds" / "manifest.json").write_text(text)
    return ["dataset", "info", "ds"]


def _results(tmp: Path, text: str) -> list[str]:
    (tmp / "r").mkdir()
    (tmp / "r" / "results.json").write_text(text)
    return ["report", "r", "-o", "rep"]


READERS = {
    "t.json": _tuned,
    "t.json ": _estimate,
    " t.json": _export,
    "manifest.json": _manifest,
    "results.json": _results,
}


@pytest.mark.parametrize("name", list(READERS))
@pytest.mark.parametrize(
    "text",
    [
        '{"format": "kftune-tuned", "q": [LONG]}',
        '{"schema": 1, "burn_in": -LONG}',
        '[[[{"a": {"b": [1, 2, LONG]}}]]]',
    ],
)
def test_an_integer_beyond_the_digit_limit_in_any_json_input_is_refused(tmp_path, name, text):
    """tuned files (evaluate, estimate, export), a dataset's manifest.json (dataset info) and
    results.json (report): exit 3 naming the file and the limit, nothing written."""
    args = READERS[name](tmp_path, text.replace("LONG", LONG))
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert name.strip() in res.stderr and f"more than {MAX_INT_DIGITS:,} digits" in res.stderr
    assert "Traceback" not in res.stderr and LONG not in res.stderr
    assert _files(tmp_path) == before


@pytest.mark.parametrize("where", ["config", "manifest"])
def test_an_integer_beyond_the_digit_limit_in_a_toml_input_is_refused(tmp_path, where):
    if where == "config":
        (tmp_path / "run.toml").write_text(f"budget = {LONG}\n")
        args, name = ["tune", "--config", "run.toml", "-o", "t.json"], "run.toml"
    else:
        (tmp_path / "ds").mkdir()
        (tmp_path / "ds" / "manifest.toml").write_text(f"name = 'x'\nn = {LONG}\n")
        args, name = ["dataset", "info", "ds"], "manifest.toml"
    before = _files(tmp_path)
    res = run_cli(*args, cwd=tmp_path)
    assert res.returncode == 3 and name in res.stderr, res.stderr
    assert f"more than {MAX_INT_DIGITS:,} digits" in res.stderr
    assert "Traceback" not in res.stderr and _files(tmp_path) == before


@settings(max_examples=200, deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
        lambda inner: (
            st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3)
        ),
        max_leaves=8,
    ),
    st.integers(min_value=0, max_value=2 * MAX_INT_DIGITS),
)
def test_the_json_loader_reads_any_document_or_refuses_it_by_name(doc, digits):
    """Any JSON document reads back as itself; one holding an integer literal of more than
    MAX_INT_DIGITS digits is a DataError naming the file, never a bare ValueError."""
    import json

    text = json.dumps(doc)
    assert parse_json(text, "f.json") == doc or text.count("NaN")
    big = f"[{text}, {'7' * digits}]" if digits else text
    try:
        parse_json(big, "f.json")
    except DataError as exc:
        assert digits > MAX_INT_DIGITS and "f.json" in str(exc)
    else:
        assert digits <= MAX_INT_DIGITS
