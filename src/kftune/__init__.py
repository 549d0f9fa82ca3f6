"""kftune — automatic tuning of Kalman filters.

Data → filter → cost → optimiser → report, one direction:

* :mod:`kftune.vehicle` — single-track model with Dugoff tyres
* :mod:`kftune.filters` — the unscented Kalman filter (compiled kernel + reference path)
* :mod:`kftune.data` — manoeuvres, loading/validation, noise statistics
* :mod:`kftune.sim` — the reference-data generator (CommonRoad plant, drivers, sensors)
* :mod:`kftune.bo` — surrogates (GP, Student-t process) and acquisition functions
* :mod:`kftune.space` — search spaces (box bounds, linear or log10, mapped to [0, 1]^d)
* :mod:`kftune.optim` — TSBO and baselines behind one ask/tell interface; persistent studies
* :mod:`kftune.tuning` — the filter-tuning problem: parameter space, cost, KPIs
* :mod:`kftune.report` — paper-style tables and figures
* :mod:`kftune.experiment`, :mod:`kftune.cli` — the compare experiment, the command line

``tests/test_architecture.py`` holds the layer table and refuses import cycles.
"""

__version__ = "0.1.0"

# Top-level conveniences, imported lazily so that ``import kftune`` stays fast (PEP 562).
_LAZY = {
    "minimize": "kftune.optim.minimize",
    "OptimizeResult": "kftune.optim.result",
    "EvalRecord": "kftune.optim.result",
    "Space": "kftune.space",
    "Param": "kftune.space",
}

__all__ = ["EvalRecord", "OptimizeResult", "Param", "Space", "__version__", "minimize"]


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'kftune' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
