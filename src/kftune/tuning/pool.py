"""The worker processes that score manoeuvres in parallel for a tuning problem
(:class:`~kftune.tuning.problem.TuningProblem`; the manoeuvres are sent once, when the pool
starts), and the balanced split of the work."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kftune.data.manoeuvre import Manoeuvre
from kftune.filters import UKFSettings
from kftune.processes import watch_parent
from kftune.tuning.cost import (
    CostSpec,
)
from kftune.tuning.runs import filter_spec
from kftune.tuning.scoring import ManoeuvreScore, score_manoeuvre
from kftune.vehicle.params import VehicleParams

# Worker-process state: the manoeuvres are sent once, when the pool starts.
_WORKER: dict[str, Any] = {}


def init_worker(
    manoeuvres: tuple[Manoeuvre, ...],
    vehicle: VehicleParams | None,
    model: str,
    filter: str,
    parent_pid: int,
) -> None:  # pragma: no cover - runs in the pool's workers
    watch_parent(parent_pid)  # exit with a killed parent; Ctrl-C stops the parent only
    _WORKER["manoeuvres"] = manoeuvres
    fs = filter_spec(model, filter, vehicle)  # a model file is loaded again here
    _WORKER["filter"] = fs
    # compile / load the kernel now, so no evaluation's timing includes it
    m = manoeuvres[0]
    n, k = fs.model.n_states, fs.model.n_measurements
    fs.run(m, np.full(n, 1e-4), np.full(k, 1e-2), UKFSettings())


def score_chunk(
    indices: list[int],
    q: np.ndarray,
    r: np.ndarray,
    settings: UKFSettings,
    spec: CostSpec,
    burn_in: float,
    params: np.ndarray | None,
    cov_scale: float,
) -> list[ManoeuvreScore]:
    ms, fs = _WORKER["manoeuvres"], _WORKER["filter"]
    return [
        score_manoeuvre(ms[i], fs, q, r, settings, spec, burn_in, params, cov_scale)
        for i in indices
    ]


def balanced_chunks(sizes: Sequence[int], k: int) -> list[list[int]]:
    """Split indices into k groups of similar total size (longest-first greedy)."""
    groups: list[list[int]] = [[] for _ in range(k)]
    loads = [0] * k
    for i in sorted(range(len(sizes)), key=lambda i: -sizes[i]):
        j = loads.index(min(loads))
        groups[j].append(i)
        loads[j] += sizes[i]
    return [sorted(g) for g in groups if g]
