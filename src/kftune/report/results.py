"""The stored results of a tuning experiment: what ``compare`` writes and ``report`` reads.

A results directory holds ``results.json`` (everything but long signals) and
``traces.npz`` (β time series for the figures). The report is a pure function of these two
files, so ``kftune report`` rebuilds identical tables without re-running anything.
"""

from __future__ import annotations

import json
import math
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kftune.data.jsonfile import read_json
from kftune.errors import DataError

RESULTS_FILE = "results.json"
TRACES_FILE = "traces.npz"
SCHEMA_VERSION = 1


@dataclass
class MethodRun:
    """One tuning method's run and the evaluation of its tuned filter.

    Attributes:
        key: method identifier (``"tsbo-tsp"``, ``"ga"``, ...).
        label: name for tables and legends (``"TSBO-tSP"``).
        params: tuned parameters in natural units (e.g. ``{"q_vx": 1e-3, ...}``).
        best_cost: best training cost J found [-].
        n_evals: number of cost evaluations (failed ones included).
        wall_time_s: time of the tuning run [s]: the optimiser's proposals plus the cost
            evaluations (not the progress bar or the study's I/O, a few fsyncs a step:
            ``benchmarks/study_io.py``).
        history_cost: (n_evals,) cost of each evaluation in order (NaN where it failed).
        history_time_s: (n_evals,) that time accumulated up to each evaluation [s].
        metrics: split → manoeuvre name → metric → value. Metrics: the β KPIs
            ``rmse, mae, rmse_non, mae_non`` [deg] and channel RMSEs ``rmse_beta`` [deg],
            ``rmse_r`` [deg/s], ``rmse_ay`` [m/s²]; for a model reported by its channels
            (``meta["scored_channels"]``, channel → unit), ``rmse_<channel>`` of each in its
            unit. And ``diverged`` (0/1).
        averages: split → KPI → value averaged over the split's manoeuvres.
        consistency: split → whether the tuned filter's standard deviations can be
            trusted there, pooled over the split's manoeuvres
            (:func:`kftune.tuning.consistency.as_doc`, plus ``"reliability"``: observed
            coverage at nominal levels; :func:`kftune.tuning.deploy.consistency_docs`), None
            where the filter diverged on a manoeuvre; empty in results written before it
            was recorded.
        extra: free-form, JSON-serialisable (stage per evaluation, failures, ...).
    """

    key: str
    label: str
    params: dict[str, float]
    best_cost: float
    n_evals: int
    wall_time_s: float
    history_cost: list[float]
    history_time_s: list[float]
    metrics: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    averages: dict[str, dict[str, float]] = field(default_factory=dict)
    consistency: dict[str, dict[str, Any] | None] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def best_so_far(self) -> np.ndarray:
        """(n_evals,) running minimum of the cost, ignoring failed evaluations (NaN
        until the first success)."""
        costs = np.asarray(self.history_cost, dtype=float)
        filled = np.where(np.isfinite(costs), costs, np.inf)
        best = np.minimum.accumulate(filled) if filled.size else filled
        return np.where(np.isfinite(best), best, np.nan)


@dataclass
class ExperimentResults:
    """Everything a report needs.

    Attributes:
        meta: dataset, vehicle, configuration, versions, date; ``scored_channels``
            (channel → unit) for a model reported by its channel RMSEs instead of the
            sideslip KPIs (absent for the paper's sideslip report).
        methods: the runs, in report order (manual first, the proposed method last).
        cost_slice: optional one-dimensional slice of the cost with surrogate fits (Fig. 2):
            keys ``parameter``, ``grid`` (natural units), ``cost``, ``sample_index`` and per
            surrogate ``{"mean": [...], "std": [...]}`` under ``fits``.
        traces: manoeuvre name → signal name → (N,) array; signals ``t`` [s],
            ``beta_ref`` [rad] and ``beta_<method key>`` [rad]; with ``scored_channels``,
            ``<channel>_ref`` (the reference, or the measured channel for a measurement)
            and ``<channel>_<method key>`` for each scored channel, in its unit.
    """

    meta: dict[str, Any]
    methods: list[MethodRun]
    cost_slice: dict[str, Any] | None = None
    traces: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def method(self, key: str) -> MethodRun:
        """The run of a method, by key."""
        for m in self.methods:
            if m.key == key:
                return m
        raise KeyError(f"no method {key!r} in results; have {[m.key for m in self.methods]}")

    def save(self, directory: str | Path) -> Path:
        """Write ``results.json`` and ``traces.npz`` into ``directory`` (created)."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        doc = {
            "schema": SCHEMA_VERSION,
            "meta": self.meta,
            "methods": [asdict(m) for m in self.methods],
            "cost_slice": self.cost_slice,
        }
        (out / RESULTS_FILE).write_text(json.dumps(_jsonable(doc), indent=1) + "\n")
        flat: dict[str, Any] = {  # Any: savez's **arrays could otherwise name allow_pickle
            f"{man}::{sig}": np.asarray(arr)
            for man, sigs in self.traces.items()
            for sig, arr in sigs.items()
        }
        np.savez_compressed(out / TRACES_FILE, **flat)
        return out

    @classmethod
    def load(cls, directory: str | Path) -> ExperimentResults:
        """Read a results directory written by :meth:`save`.

        Raises:
            DataError: ``results.json`` is missing, unreadable or not what :meth:`save`
                writes (the message names the file and the part at fault), or
                ``traces.npz`` is damaged.
        """
        src = Path(directory)
        path = src / RESULTS_FILE
        if not path.exists():  # a device or FIFO there is refused by read_json, by name
            raise DataError(
                f"no {RESULTS_FILE} here; expected a results directory written by 'kftune compare'",
                file=str(src),
            )
        doc = read_json(path)
        if not isinstance(doc, dict):
            raise DataError(
                f"expected a JSON object written by 'kftune compare', got a {type(doc).__name__}",
                file=str(path),
            )
        if doc.get("schema") != SCHEMA_VERSION:
            raise DataError(
                f"results schema {doc.get('schema')!r} is not the supported {SCHEMA_VERSION}",
                file=str(path),
            )
        if not isinstance(doc.get("meta"), dict) or not isinstance(doc.get("methods"), list):
            raise DataError("expected an object 'meta' and a list 'methods'", file=str(path))
        methods = []
        for i, m in enumerate(doc["methods"]):
            try:
                methods.append(_method_from_json(m))
            except (TypeError, ValueError, AttributeError):
                raise DataError(
                    f"methods[{i}] is not a method run written by 'kftune compare'",
                    file=str(path),
                ) from None
        cost_slice = doc.get("cost_slice")
        if cost_slice is not None and not isinstance(cost_slice, dict):
            raise DataError("'cost_slice' must be an object or null", file=str(path))
        return cls(
            meta=doc["meta"],
            methods=methods,
            cost_slice=_numbers(cost_slice) if cost_slice else None,
            traces=_load_traces(src / TRACES_FILE),
        )


def _load_traces(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """The β traces of ``traces.npz`` (none if the file is absent).

    Raises:
        DataError: the file is damaged (truncated, not a NumPy archive, or holding keys
            other than ``<manoeuvre>::<signal>``).
    """
    traces: dict[str, dict[str, np.ndarray]] = {}
    if not path.is_file():
        return traces
    try:
        with np.load(path) as npz:
            for key in npz.files:
                man, sep, sig = key.partition("::")
                if not sep:
                    raise ValueError(f"key {key!r} is not <manoeuvre>::<signal>")
                traces.setdefault(man, {})[sig] = npz[key]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DataError(
            f"not a traces archive written by 'kftune compare' ({type(exc).__name__}); delete "
            "it to build the report without the β figures",
            file=str(path),
        ) from None
    return traces


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays and non-finite floats for strict JSON (NaN → null,
    ±inf → "inf"/"-inf")."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        if math.isnan(f):
            return None
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return f
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _numbers(obj: Any) -> Any:
    """Inverse of :func:`_jsonable` inside numeric containers: null → NaN, "inf" → inf."""
    if isinstance(obj, dict):
        return {k: _numbers(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_numbers(v) for v in obj]
    if obj is None:
        return math.nan
    if obj == "inf":
        return math.inf
    if obj == "-inf":
        return -math.inf
    return obj


_NUMERIC_FIELDS = (
    "params",
    "best_cost",
    "wall_time_s",
    "history_cost",
    "history_time_s",
    "metrics",
    "averages",
)


def _method_from_json(doc: dict[str, Any]) -> MethodRun:
    """A :class:`MethodRun` from its JSON form (numeric fields restored, ``extra`` as is).

    Raises:
        TypeError, ValueError, AttributeError: ``doc`` is not what :meth:`save` writes.
    """
    run = MethodRun(**{k: _numbers(v) if k in _NUMERIC_FIELDS else v for k, v in doc.items()})
    number = (int, float)
    fields_ok = (
        isinstance(run.key, str)
        and isinstance(run.label, str)
        and isinstance(run.n_evals, int)
        and isinstance(run.best_cost, number)
        and isinstance(run.wall_time_s, number)
        and isinstance(run.params, dict)
        and all(isinstance(v, number) for v in run.params.values())
        and all(
            isinstance(h, list) and all(isinstance(v, number) for v in h)
            for h in (run.history_cost, run.history_time_s)
        )
        and all(isinstance(d, dict) for d in (run.metrics, run.averages, run.extra))
        and isinstance(run.consistency, dict)
        and all(d is None or _consistency_ok(d) for d in run.consistency.values())
    )
    if not fields_ok:
        raise ValueError("a field has the wrong type")
    return run


def _consistency_ok(doc: Any) -> bool:
    """Whether ``doc`` has the shape of a pooled consistency that the report reads
    (:func:`kftune.tuning.consistency.as_doc`, optionally with ``"reliability"``)."""
    number = (int, float, type(None))

    def mean_ok(d: Any, band: str) -> bool:
        return (
            isinstance(d, dict)
            and isinstance(d.get("mean"), number)
            and isinstance(d.get(band), list)
            and len(d[band]) == 2
            and all(isinstance(v, number) for v in d[band])
        )

    if not isinstance(doc, dict) or not isinstance(doc.get("channels"), dict):
        return False
    channels_ok = all(
        isinstance(ch, dict)
        and all(isinstance(ch.get(k), number) for k in ("cov68", "cov95"))
        and mean_ok(ch.get("nees"), "band_eff")
        for ch in doc["channels"].values()
    )
    nis = doc.get("nis")
    rel = doc.get("reliability")
    rel_ok = rel is None or (
        isinstance(rel, dict)
        and isinstance(rel.get("levels"), list)
        and all(isinstance(v, (int, float)) for v in rel["levels"])
        and isinstance(rel.get("coverage"), dict)
        and all(
            isinstance(c, list)
            and len(c) == len(rel["levels"])
            and all(isinstance(v, number) for v in c)
            for c in rel["coverage"].values()
        )
    )
    nis_ok = nis is None or (mean_ok(nis, "band") and isinstance(nis.get("dof"), int))
    return channels_ok and nis_ok and rel_ok
