"""What makes a report reproducible: the command line, the package versions and the
machine (``results.json`` keeps them under ``meta``; ``report.md`` lists them)."""

from __future__ import annotations

import os
import platform
import shlex
from collections.abc import Sequence
from importlib import metadata

from kftune import __version__

#: Packages whose versions a report records: the numerical core, the plots, and the peers
#: that some methods use (None where not installed).
PACKAGES = ("numpy", "scipy", "numba", "llvmlite", "matplotlib", "threadpoolctl", "optuna",
            "cma", "torch")  # fmt: skip


def package_versions() -> dict[str, str | None]:
    """``{"python": …, "kftune": …, "numpy": …, …}``; None for a package not installed."""
    out: dict[str, str | None] = {
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "kftune": __version__,
    }
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def machine() -> dict[str, object]:
    """The machine: operating system and architecture, processor, CPU count (those this
    process may use, where the system says)."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable,
    }


def command_line(argv: Sequence[str]) -> str:
    """``kftune compare … `` as a shell would take it back (quoted where needed)."""
    return shlex.join(["kftune", *argv])
