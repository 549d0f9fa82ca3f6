"""The layers import in one direction: data → filter → cost → optimiser → report.

Every ``import`` in a layer's source files (including imports inside functions, which run
lazily) is read with :mod:`ast` and the kftune packages it names are compared with what the
layer may depend on. The surrogates (``bo``) and the optimisers (``optim``) must know
nothing about vehicles or filters (issues 4 and 5).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import kftune

SRC = Path(kftune.__file__).parent
#: layer → kftune top-level modules it may import (itself and ``errors`` always allowed).
ALLOWED: dict[str, set[str]] = {
    "space": set(),
    "processes": set(),
    "bo": set(),
    "vehicle": set(),
    "models": {"vehicle"},
    "filters": {"vehicle", "models"},
    "data": {"vehicle", "progress"},
    "optim": {"space", "bo", "processes"},
    "tuning": {"vehicle", "filters", "data", "space", "processes"},
    "report": {"vehicle", "filters", "data", "space", "tuning"},
}


def _is_module(name: str) -> bool:
    return (SRC / name).is_dir() or (SRC / f"{name}.py").exists()


def kftune_imports(path: Path) -> set[str]:
    """Top-level kftune modules that the file imports, e.g. ``{"vehicle", "errors"}``."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            mods = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            mods = [node.module]
            if node.module == "kftune":  # from kftune import vehicle
                mods += [f"kftune.{a.name}" for a in node.names if _is_module(a.name)]
        else:
            continue
        names |= {m.split(".")[1] for m in mods if m.startswith("kftune.")}
    return names


def test_the_check_sees_lazy_imports(tmp_path: Path) -> None:
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from kftune.vehicle import VehicleParams\n    import kftune.bo\n")
    assert kftune_imports(f) == {"vehicle", "bo"}


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layer_imports_only_what_lies_below_it(layer: str) -> None:
    files = (
        [SRC / f"{layer}.py"]
        if (SRC / f"{layer}.py").exists()
        else sorted((SRC / layer).rglob("*.py"))
    )
    assert files
    for f in files:
        extra = kftune_imports(f) - ALLOWED[layer] - {layer, "errors"}
        assert not extra, f"{f.relative_to(SRC)} imports kftune.{sorted(extra)}"
