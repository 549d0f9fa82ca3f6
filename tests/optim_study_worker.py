"""Helper for the study tests: runs one resumable study in its own process.

Usage: ``python optim_study_worker.py DB LOG RUN_ID METHOD BUDGET SLEEP``

Each finished evaluation appends ``RUN_ID <json x>`` to LOG (flushed) just before the value
is returned, so the test can see which process evaluated which point. At the end the result
(JSON) is written to ``DB.result.json``.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from kftune.optim import minimize

SPACE = {"a": (-5.0, 10.0), "q": (1e-10, 1.0, "log10")}


def objective(x: np.ndarray) -> float:
    """Branin-like in (a, log10 q), cheap and deterministic."""
    x1, x2 = float(x[0]), (float(np.log10(x[1])) + 10.0) * 1.5
    b, c = 5.1 / (4 * np.pi**2), 5 / np.pi
    return (x2 - b * x1**2 + c * x1 - 6) ** 2 + 10 * (1 - 1 / (8 * np.pi)) * np.cos(x1) + 10


def method_options(method: str) -> dict:
    """Options shared by the worker and the test's reference run. TSBO: no fit restarts,
    to keep the test quick (the resume logic does not depend on them), and MAX_FE = 4,
    MAX_SM = 10 so that short runs go through the switch, stage 2 and the frozen surrogate."""
    if method.startswith("tsbo"):
        return {"surrogate_options": {"n_restarts": 0}, "max_fe": 4, "max_sm": 10}
    return {}


def main() -> int:
    db, log, run_id, method, budget, sleep = sys.argv[1:7]

    def fun(x: np.ndarray) -> float:
        time.sleep(float(sleep))
        v = objective(x)
        with open(log, "a") as fh:
            fh.write(f"{run_id} {json.dumps([float(t) for t in x])}\n")
            fh.flush()
            os.fsync(fh.fileno())
        return v

    res = minimize(
        fun,
        SPACE,
        method,
        budget=int(budget),
        seed=5,
        storage=db,
        resume=True,
        **method_options(method),
    )
    with open(db + ".result.json", "w") as fh:
        fh.write(res.to_json())
    return 0


if __name__ == "__main__":
    sys.exit(main())
