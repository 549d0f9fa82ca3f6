"""kftune's modules import in one direction, and no two of them import each other.

The import graph is read from the source with :mod:`ast`, module by module, and contains:

* ``import a.b`` → ``a.b``; ``from a import b`` → ``a`` (the statement reads ``a``'s
  namespace, so it runs ``a``'s ``__init__``) and ``a.b`` where that is a module; relative
  imports resolved the same way;
* imports inside functions (they run lazily, but they run);
* ``importlib.import_module("kftune.x")``-style names: a string constant that is exactly a
  kftune module name, or an f-string that starts with ``"kftune.…"`` (→ every module under
  that prefix);
* ``from kftune import minimize``: the names that ``kftune/__init__.py`` resolves lazily
  (its ``_LAZY`` table, PEP 562) count as an import of their target module by the module
  that names them — the root package itself imports nothing.

Not edges: a package's ``__init__`` that Python runs before a submodule (every submodule
would otherwise "import" its package), and imports under ``if TYPE_CHECKING:`` for the
cycle check (they never run); the layer check counts them (a layer should not even name an
upper layer's types).

Two checks on that graph: every top-level module or package (a *layer*) imports only the
layers :data:`ALLOWED` lists, and the graph of modules has no cycle. :data:`ALLOWED` must
list every top-level module of kftune, so a new package cannot escape the check.
"""

from __future__ import annotations

import ast
import itertools
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import pytest

import kftune

SRC = Path(kftune.__file__).parent
ROOT = "__init__"  # the layer name of kftune/__init__.py itself
#: Layers every layer may import: the exception types, and the root package (only
#: ``__version__``; its lazy names count as imports of their targets).
ALWAYS: frozenset[str] = frozenset({"errors", ROOT})

#: layer → the kftune layers it may import (itself and :data:`ALWAYS` always allowed).
#: Bottom to top: the generic pieces, which know nothing of cars or filters; the vehicle
#: physics of the sideslip problem; the models (the generic model type, and the sideslip
#: model built on the vehicle physics); filters over any model; data, and the simulator that
#: makes the bundled data; the tuning problem; the application on top.
#:
#: A row is a top-level module, or a part of one (``"models.sideslip"``): a module follows
#: the row of its longest dotted prefix. Imports within one top-level module are always
#: allowed (the cycle check polices those); the sets name top-level modules, or a module
#: within one (``"vehicle.params"``: that module and its submodules only).
ALLOWED: dict[str, set[str]] = {
    ROOT: set(),
    "errors": set(),
    # generic pieces
    "space": set(),
    "processes": set(),
    "bo": set(),  # surrogates and acquisitions
    "optim": {"space", "bo", "processes", "settings"},  # optimisers: nothing of vehicles or filters
    "progress": {"optim"},
    "settings": set(),  # typed settings records and their one validator
    # the sideslip problem's physics, the models, the filters
    "vehicle": set(),  # single-track model, Dugoff tyres, parameters and presets
    "models": set(),  # the state-space model type, its registry, generic built-in models
    "models.sideslip": {"vehicle"},  # the paper's problem as a model: only it knows cars
    "models._single_track_jacobians": {"vehicle"},  # its analytic Jacobians
    "models._runaway": {"vehicle"},  # its runaway rule, written once
    "models._sideslip_ukf": {"vehicle"},  # its own 3×3 UKF loop (ModelKernels)
    "models._sideslip_lanes": {"vehicle"},  # and its vector lanes
    "filters": {"models"},  # filters over any model: no vehicle
    # data and the simulator
    "data": {"models", "vehicle", "settings"},
    "sim": {"models", "vehicle", "data"},
    # the tuning problem
    # (the vehicle's parameter record, which datasets carry, but none of its physics)
    "tuning": {"models", "vehicle.params", "filters", "data", "space", "processes"},
    # application: tables and figures, the experiment, the command line
    "report": {"models", "vehicle", "filters", "data", "space", "processes", "tuning"},
    "experiment": {
        *("models", "vehicle", "filters", "data", "tuning", "report"),
        *("space", "processes", "bo", "optim", "progress"),
    },
    "cli": {
        *("models", "vehicle", "filters", "data", "sim", "tuning", "report", "experiment"),
        *("space", "processes", "bo", "optim", "progress", "settings"),
    },
    "__main__": {"cli"},
}


# ---------------------------------------------------------------------------- the graph
def module_files(src: Path = SRC) -> dict[str, Path]:
    """Every module of the package at ``src``, by dotted name (``kftune.data.io``)."""
    out = {}
    for path in sorted(src.rglob("*.py")):
        parts = list(path.relative_to(src.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def layer_of(module: str) -> str:
    """The top-level module a dotted name belongs to: ``kftune.data.io`` → ``data``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT


def row_of(module: str, allowed: Mapping[str, set[str]]) -> str:
    """The row of ``allowed`` that governs ``module``: its longest dotted prefix below the
    root that has a row (``kftune.models.sideslip.x`` → ``models.sideslip`` if that row
    exists, else ``models``)."""
    parts = module.split(".")[1:]
    for n in range(len(parts), 1, -1):
        if ".".join(parts[:n]) in allowed:
            return ".".join(parts[:n])
    return layer_of(module)


def top_level_modules(src: Path = SRC) -> set[str]:
    """Layers present in the source tree (packages and single-file modules)."""
    return {layer_of(m) for m in module_files(src)}


def _lazy_names(root_init: Path) -> dict[str, str]:
    """The root package's ``_LAZY`` table: attribute name → module that defines it."""
    for node in ast.parse(root_init.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "_LAZY" for t in node.targets
        ):
            return dict(ast.literal_eval(node.value))
    return {}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _nodes(tree: ast.AST, typing_imports: bool) -> Iterator[ast.AST]:
    """All nodes, less the bodies of ``if TYPE_CHECKING:`` unless ``typing_imports``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        if not typing_imports and isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        stack.extend(ast.iter_child_nodes(node))


def imports_of(
    module: str, path: Path, modules: Mapping[str, Path], typing_imports: bool = True
) -> set[str]:
    """The kftune modules that ``module`` (source at ``path``) imports; see the module
    docstring for what counts."""
    package = module.split(".")[0]
    lazy = _lazy_names(modules[package]) if package in modules else {}
    is_package = path.name == "__init__.py"

    def resolve(name: str) -> str:
        """The longest prefix of ``name`` that is a module below the root (a name that
        matches none, e.g. a module that does not exist, stays as it is)."""
        prefix = name
        while "." in prefix and prefix not in modules:
            prefix = prefix.rpartition(".")[0]
        return prefix if prefix in modules and (prefix != package or name == package) else name

    out: set[str] = set()
    for node in _nodes(ast.parse(path.read_text(encoding="utf-8")), typing_imports):
        if isinstance(node, ast.Import):
            out |= {resolve(a.name) for a in node.names if a.name.split(".")[0] == package}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module if is_package else module.rpartition(".")[0]
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            if source.split(".")[0] != package:
                continue
            out.add(resolve(source))
            for alias in node.names:
                if f"{source}.{alias.name}" in modules:
                    out.add(f"{source}.{alias.name}")
                elif source == package and alias.name in lazy:
                    out.add(resolve(lazy[alias.name]))
        elif module != package and isinstance(node, ast.Constant):
            if isinstance(node.value, str) and node.value in modules and node.value != package:
                out.add(node.value)
        elif isinstance(node, ast.JoinedStr) and node.values:
            head = node.values[0]
            if isinstance(head, ast.Constant) and str(head.value).startswith(f"{package}."):
                out |= {m for m in modules if m.startswith(str(head.value))}
    out.discard(module)
    return out


def import_graph(src: Path = SRC, typing_imports: bool = False) -> dict[str, set[str]]:
    """Module → the modules it imports, for every module of the package at ``src``."""
    modules = module_files(src)
    return {m: imports_of(m, p, modules, typing_imports) for m, p in modules.items()}


def find_cycle(graph: Mapping[str, Iterable[str]]) -> list[str] | None:
    """One cycle of ``graph`` as ``[a, b, …, a]``, or None if it is acyclic (iterative
    depth-first search, nodes and edges in sorted order, so the answer is stable)."""
    done: set[str] = set()
    for start in sorted(graph):
        if start in done:
            continue
        path, on_path = [start], {start}
        stack = [iter(sorted(graph.get(start, ())))]
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                stack.pop()
                done.add(path[-1])
                on_path.discard(path.pop())
            elif nxt in on_path:
                return [*path[path.index(nxt) :], nxt]
            elif nxt not in done:
                path.append(nxt)
                on_path.add(nxt)
                stack.append(iter(sorted(graph.get(nxt, ()))))
    return None


def layer_violations(
    graph: Mapping[str, Iterable[str]], allowed: Mapping[str, set[str]]
) -> list[str]:
    """``"kftune.a.b imports kftune.c.d (layer c)"`` for every import that crosses into a
    layer that the importer's row may not use (or that has no row in ``allowed``)."""
    out = []
    for module in sorted(graph):
        ok = allowed.get(row_of(module, allowed), set()) | ALWAYS | {layer_of(module)}
        for target in sorted(graph[module]):
            parts = target.split(".")[1:]
            if layer_of(target) not in ok and not any(
                ".".join(parts[:n]) in ok for n in range(2, len(parts) + 1)
            ):
                out.append(f"{module} imports {target} (layer {layer_of(target)})")
    return out


def uncovered_layers(src: Path, allowed: Mapping[str, set[str]]) -> set[str]:
    """Top-level modules of the package at ``src`` that ``allowed`` has no row for."""
    return top_level_modules(src) - set(allowed)


# ------------------------------------------------------------------------- kftune itself
def test_every_top_level_module_has_a_row_in_the_table() -> None:
    missing = uncovered_layers(SRC, ALLOWED)
    assert not missing, f"add a row to ALLOWED for kftune.{sorted(missing)}"
    for row, deps in ALLOWED.items():
        assert row.split(".")[0] in ALLOWED, f"row {row} is part of no top-level row"
        tops = {d.split(".")[0] for d in deps}
        assert tops <= set(ALLOWED), f"{row} may import unknown layers {tops - set(ALLOWED)}"
        parts = {f"kftune.{d}" for d in deps if "." in d}
        assert parts <= set(module_files()), f"{row}: no such modules {parts}"


def test_the_layers_go_one_way() -> None:
    """The table itself is acyclic: a layer cannot sit both above and below another (a
    part's row counts for its top-level module)."""
    layers: dict[str, set[str]] = {}
    for row, deps in ALLOWED.items():
        top = row.split(".")[0]
        layers.setdefault(top, set()).update({d.split(".")[0] for d in deps} - {top})
    cycle = find_cycle(layers)
    assert cycle is None, f"ALLOWED has a cycle: {' -> '.join(cycle)}"


def test_each_layer_imports_only_what_lies_below_it() -> None:
    violations = layer_violations(import_graph(SRC, typing_imports=True), ALLOWED)
    assert not violations, "\n".join(violations)


def test_no_module_imports_itself_through_others() -> None:
    graph = import_graph(SRC)
    assert set(graph) >= {"kftune.cli", "kftune.experiment", "kftune.progress", "kftune.sim"}
    cycle = find_cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


def test_the_vehicle_parameter_record_comes_without_the_physics() -> None:
    """``tuning`` may import the vehicle's parameter record (``vehicle.params``) but not its
    physics: importing the record (which runs the package's ``__init__``) must not load
    the single-track model or the tyres. In a fresh process, as a layer would."""
    import subprocess
    import sys

    code = (
        "import sys, kftune.vehicle.params\n"
        "print(sorted(m for m in sys.modules if m.startswith('kftune.vehicle.')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['kftune.vehicle.params']", out.stdout + out.stderr


def test_the_graph_sees_kftunes_own_hard_cases() -> None:
    """Lazy imports in functions, importlib with an f-string, and the root's lazy names."""
    graph = import_graph(SRC)
    # cli/__init__: importlib.import_module(f"kftune.cli.{name}") in build_parser
    assert {"kftune.cli.tune", "kftune.cli.dataset"} <= graph["kftune.cli"]
    # cli/dataset: the generator is imported inside run_generate
    assert "kftune.sim.generate" in graph["kftune.cli.dataset"]
    # data/manoeuvre -> data/noise, and noise's TYPE_CHECKING import is not an edge
    assert "kftune.data.noise" in graph["kftune.data.manoeuvre"]
    assert "kftune.data.manoeuvre" not in graph["kftune.data.noise"]
    assert "kftune.data.manoeuvre" in import_graph(SRC, typing_imports=True)["kftune.data.noise"]
    assert graph["kftune"] == set()  # the root imports nothing at import time
    # the single-track model imports its own loops inside a function, by name
    assert "kftune.models._sideslip_ukf" in graph["kftune.models.sideslip"]
    assert "kftune.models" not in graph["kftune.models._sideslip_ukf"]


# ------------------------------------------------------------- the checks catch breakage
def _tree(root: Path, files: dict[str, str]) -> Path:
    """A package ``kftune`` under ``root`` with the given files (relative path → source);
    packages get an empty ``__init__.py``. Returns the package directory."""
    src = root / "kftune"
    for rel, text in {"__init__.py": "", **files}.items():
        path = src / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        for parent in path.relative_to(src).parents:
            init = src / parent / "__init__.py"
            if not init.exists():
                init.write_text("")
        path.write_text(text)
    return src


def test_an_injected_cycle_is_found_with_its_path(tmp_path: Path) -> None:
    """package → a → b at import time, b → c inside a function, c → the package
    (``from kftune.data import a`` runs the package, which imports a)."""
    src = _tree(
        tmp_path,
        {
            "data/__init__.py": "from kftune.data.a import A\n",
            "data/a.py": "from kftune.data.b import B\nA = 1\n",
            "data/b.py": "def f():\n    import kftune.data.c as c\nB = 2\n",
            "data/c.py": "from kftune.data import a\n",
        },
    )
    graph = import_graph(src)
    cycle = find_cycle(graph)
    assert cycle == [f"kftune.data{m}" for m in ("", ".a", ".b", ".c", "")]
    for here, there in itertools.pairwise(cycle):
        assert there in graph[here]
    # the same tree without c's import is acyclic
    (src / "data" / "c.py").write_text("X = 0\n")
    assert find_cycle(import_graph(src)) is None


def test_a_cycle_through_importlib_or_relative_imports_is_found(tmp_path: Path) -> None:
    src = _tree(
        tmp_path,
        {
            "cli/__init__.py": "import importlib\n"
            "def build(name):\n    return importlib.import_module(f'kftune.cli.{name}')\n",
            "cli/tune.py": "from . import EXIT_OK\n",
        },
    )
    assert find_cycle(import_graph(src)) == ["kftune.cli", "kftune.cli.tune", "kftune.cli"]


def test_type_checking_imports_make_no_cycle_but_count_for_layers(tmp_path: Path) -> None:
    src = _tree(
        tmp_path,
        {
            "data/a.py": "from kftune.data.b import f\n",
            "data/b.py": "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n    from kftune.data.a import A\n    from kftune.optim import O\n",
        },
    )
    assert find_cycle(import_graph(src)) is None
    assert find_cycle(import_graph(src, typing_imports=True)) is not None
    assert layer_violations(import_graph(src), ALLOWED) == []
    assert layer_violations(import_graph(src, typing_imports=True), ALLOWED) == [
        "kftune.data.b imports kftune.optim (layer optim)"
    ]


def test_an_injected_upward_import_is_refused(tmp_path: Path) -> None:
    """The vehicle model reaching up into the optimisers, lazily, and the optimisers
    reaching into the filters through the root package's lazy names: both refused."""
    src = _tree(
        tmp_path,
        {
            "__init__.py": "_LAZY = {'UKF': 'kftune.filters.generic'}\n",
            "vehicle/tyre.py": "def f():\n    import kftune.optim.tsbo as t\n    return t\n",
            "optim/tsbo.py": "from kftune import UKF\n",
            "filters/generic.py": "from kftune.models import base\n",
            "models/base.py": "from kftune.errors import KftuneError\n",
            "errors.py": "class KftuneError(Exception): ...\n",
        },
    )
    assert layer_violations(import_graph(src, typing_imports=True), ALLOWED) == [
        "kftune.optim.tsbo imports kftune.filters.generic (layer filters)",
        "kftune.vehicle.tyre imports kftune.optim.tsbo (layer optim)",
    ]


def test_only_the_sideslip_model_may_know_the_vehicle(tmp_path: Path) -> None:
    """A part's row (``models.sideslip``) widens its top-level row for it alone."""
    src = _tree(
        tmp_path,
        {
            "models/__init__.py": "from kftune.models.sideslip import SINGLE_TRACK\n",
            "models/base.py": "from kftune.vehicle.params import G\n",
            "models/sideslip.py": "from kftune.models import base\n"
            "from kftune.vehicle.single_track import f\n",
            "models/linear.py": "from kftune.models.base import StateSpaceModel\n",
            "vehicle/params.py": "",
            "vehicle/single_track.py": "",
        },
    )
    assert row_of("kftune.models.sideslip", ALLOWED) == "models.sideslip"
    assert row_of("kftune.models.sideslip.tyres", ALLOWED) == "models.sideslip"
    assert row_of("kftune.models.base", ALLOWED) == "models"
    assert layer_violations(import_graph(src, typing_imports=True), ALLOWED) == [
        "kftune.models.base imports kftune.vehicle.params (layer vehicle)"
    ]


def test_a_new_package_must_be_added_to_the_table(tmp_path: Path) -> None:
    src = _tree(tmp_path, {"errors.py": "", "plugins/x.py": "", "vehicle/params.py": ""})
    assert uncovered_layers(src, ALLOWED) == {"plugins"}
    assert layer_violations({"kftune.plugins.x": {"kftune.errors"}}, ALLOWED) == []
    assert layer_violations({"kftune.plugins.x": {"kftune.vehicle"}}, ALLOWED) == [
        "kftune.plugins.x imports kftune.vehicle (layer vehicle)"
    ]


@pytest.mark.parametrize(
    ("graph", "expected"),
    [
        ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
        ({"a": {"b", "c"}, "b": {"c"}, "c": set(), "d": {"d"}}, ["d", "d"]),
        ({"x": {"y"}, "y": {"z"}, "z": {"y"}}, ["y", "z", "y"]),
    ],
)
def test_find_cycle_on_small_graphs(graph: dict[str, set[str]], expected: list[str] | None) -> None:
    assert find_cycle(graph) == expected


def test_every_exception_kftune_defines_is_a_kftune_error() -> None:
    """One root for kftune's own exceptions, so that a caller (and the CLI's exit codes)
    can tell them from a bug: every exception class defined in a kftune module derives from
    :class:`~kftune.errors.KftuneError` (warnings excepted: they are not raised to stop; and
    interrupts, which derive from KeyboardInterrupt so that no ``except Exception`` swallows
    Ctrl-C)."""
    import importlib
    import inspect
    import pkgutil

    import kftune
    from kftune.errors import KftuneError

    own: list[type] = []
    for info in pkgutil.walk_packages(kftune.__path__, "kftune."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for _, obj in inspect.getmembers(module, inspect.isclass):
            if obj.__module__ == info.name and issubclass(obj, Exception):
                own.append(obj)
    assert len(own) >= 10  # the walk found kftune's exceptions, not nothing
    strays = [
        f"{c.__module__}.{c.__qualname__}" for c in own if not issubclass(c, (KftuneError, Warning))
    ]
    assert strays == []
