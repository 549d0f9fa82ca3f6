"""`make run` installs kftune without extras: the main job must not import any of them.

The main job is `kftune compare` with its default methods, then `report`, and the commands
a first session uses on its result (`demo`, `tune`, `evaluate`, `estimate` to CSV, every
`export` format). They run in a child interpreter where every installed module that is not
in the closure of kftune's core dependencies (read from the installed package's metadata,
so a new extra or a new core dependency needs no edit here) fails to import, as it would
in the environment `make run` builds. The Makefile and pyproject.toml are also checked to
agree: `make test` installs every extra, `make run` none.
"""

from __future__ import annotations

import functools
import json
import re
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).parents[1]

#: Run in the child: find no module of argv[1] (JSON list), run the kftune commands of
#: argv[2] (JSON list of argument lists) and print their exit codes as the last line.
_CHILD = """
import importlib.machinery, json, sys
blocked = frozenset(json.loads(sys.argv[1]))

class _CoreOnly(importlib.machinery.PathFinder):
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name.partition(".")[0] in blocked:
            return None  # as if not installed: import fails, importlib.util.find_spec is None
        return super().find_spec(name, path, target)

sys.meta_path[:] = [_CoreOnly if f is importlib.machinery.PathFinder else f for f in sys.meta_path]
from kftune.cli import main
codes = [main(args) for args in json.loads(sys.argv[2])]
print(json.dumps(codes))
"""


def _core_closure() -> set[str]:
    """Canonical names of kftune and every distribution its core requirements pull in."""
    seen: set[str] = set()
    todo = ["kftune"]
    while todo:
        name = canonicalize_name(todo.pop())
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = distribution(name).requires or []
        except PackageNotFoundError:  # a requirement whose marker excludes this Python
            continue
        for line in requires:
            req = Requirement(line)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(req.name)
    return seen


@functools.cache
def _not_core_modules() -> list[str]:
    """Top-level modules of installed distributions outside the core closure."""
    core = _core_closure()
    return sorted(
        module
        for module, dists in packages_distributions().items()
        if not any(canonicalize_name(d) in core for d in dists)
    )


@pytest.mark.slow
def test_the_blocked_modules_include_the_extras():
    """The check below is only as good as its list: the extras' packages are on it."""
    blocked = set(_not_core_modules())
    for module in ("optuna", "cma", "sklearn", "filterpy", "pytest", "dask", "distributed"):
        if module in packages_distributions():  # installed here by `make test`
            assert module in blocked, module
    assert not {"numpy", "scipy", "numba", "matplotlib", "kftune"} & blocked


@pytest.mark.slow
def test_the_main_job_runs_without_any_extra(small, tmp_path):
    """compare with its default methods (small budgets), report, demo, tune, evaluate,
    estimate and export, run where no extra can be imported; a peer optimiser there is
    refused with exit 3, naming its package, as is every option whose extra is missing."""
    out, tuned = tmp_path / "report", tmp_path / "tuned.json"
    budgets = ["--budget", "ga=4", "--budget", "tsbo-gp=4", "--budget", "tsbo-tsp=4"]
    commands = [
        ["compare", str(small), *budgets, "--budget", "trbo=4", "-q", "-o", str(out)],
        ["report", str(out)],
        ["demo"],
        ["tune", str(small), "-n", "4", "-q", "-o", str(tuned), "--storage", "study.db"],
        ["evaluate", str(small), "--params", str(tuned), "--split", "test"],
        ["estimate", str(small), "--params", str(tuned), "-o", str(tmp_path / "est")],
    ]
    for fmt in ("json", "yaml", "c", "matlab"):
        dest = tmp_path / (f"kf.{fmt}" if fmt != "c" else "kf_c")  # c: a folder
        commands.append(["export", str(tuned), "--format", fmt, "-o", str(dest)])
    # an option whose extra is missing: one exit code (3, as a configuration), the package named
    missing = [
        ["tune", str(small), "-m", "cma", "-n", "2", "-q", "-o", "never.json"],
        ["estimate", str(small), "--params", str(tuned), "--format", "parquet", "-o", "never"],
        ["study", "export", str(tmp_path / "study.db"), "--optuna", "never.db"],
        ["dataset", "generate", "never", "--seed", "1"],
    ]
    commands += missing
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps(_not_core_modules()), json.dumps(commands)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    codes = json.loads(proc.stdout.splitlines()[-1])
    assert codes == [0] * (len(commands) - len(missing)) + [3] * len(missing), (
        codes,
        proc.stderr[-3000:],
    )
    for package in ("'cma'", "pyarrow", "'optuna'", "commonroad-vehicle-models"):
        assert package in proc.stderr, package
    assert "Traceback" not in proc.stderr
    assert not list(tmp_path.glob("never*"))
    assert (out / "report.md").is_file() and (tmp_path / "kf_c" / "kftune_filter.c").is_file()


def _make_variable(name: str) -> str:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    match = re.search(rf"^{name}\s*:=\s*(.+)$", text, flags=re.M)
    assert match, f"Makefile has no {name}"
    return match.group(1).strip()


def test_make_test_installs_every_extra_and_make_run_none():
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "optional-dependencies"
    ]

    def expand(names: set[str]) -> set[str]:
        """The extras named, with those they pull in through kftune[...] requirements."""
        done: set[str] = set()
        while names:
            name = names.pop()
            done.add(name)
            for req in map(Requirement, extras[name]):
                if canonicalize_name(req.name) == "kftune":
                    names |= set(req.extras) - done
        return done

    installed = expand(set(_make_variable("EXTRAS").split(",")))
    assert installed == set(extras), sorted(set(extras) - installed)
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    run_rule = text.split("$(RUN_STAMP): pyproject.toml", 1)[1].split("\n\n", 1)[0]
    assert "pip install --quiet -e .\n" in run_rule + "\n" and "EXTRAS" not in run_rule
    assert re.search(r"^run: \$\(RUN_STAMP\)$", text, flags=re.M)
    assert re.search(r"^test: \$\(TEST_STAMP\)$", text, flags=re.M)
