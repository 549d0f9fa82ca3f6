"""Optimiser overhead per evaluation at n ≈ 100 observations, d = 3.

What one ``ask`` + ``tell`` costs once the optimiser holds about 100 evaluations — the
surrogate fit (with its periodic multi-start refits), the candidate scoring and the
bookkeeping — measured on Hartmann-3 (the objective's own time is excluded). Methods run
interleaved, seed by seed, so that a busy machine slows them alike; the figure per method
is the median and the mean over evaluations ``--from``..``--to`` (1-based) of all seeds.
The mean includes the periodic refits, so it is the cost a long run pays per evaluation.

Usage::

    .venv/bin/python benchmarks/optimizer_overhead.py                # trbo, tsbo-tsp, tsbo-gp
    .venv/bin/python benchmarks/optimizer_overhead.py --methods trbo --seeds 5

Prints a line per method and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from kftune.optim import make_optimizer

_A = np.array([[3.0, 10, 30], [0.1, 10, 35], [3.0, 10, 30], [0.1, 10, 35]])
_P = 1e-4 * np.array(
    [[3689, 1170, 2673], [4699, 4387, 7470], [1091, 8732, 5547], [381, 5743, 8828]]
)
_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])


def hartmann3(x: np.ndarray) -> float:
    """Hartmann-3 on [0, 1]^3 (f* = −3.86278)."""
    return float(-np.sum(_ALPHA * np.exp(-np.sum(_A * (x - _P) ** 2, axis=1))))


def step_times(method: str, seed: int, n_evals: int) -> np.ndarray:
    """(n_evals,) seconds of ask + tell of each evaluation of one run."""
    opt = make_optimizer(method, [(0.0, 1.0)] * 3, budget=n_evals, seed=seed)
    out = np.empty(n_evals)
    for i in range(n_evals):
        t0 = time.perf_counter()
        trial = opt.ask()
        t1 = time.perf_counter()
        value = hartmann3(np.asarray(trial.x))
        t2 = time.perf_counter()
        opt.tell(trial, value)
        out[i] = (t1 - t0) + (time.perf_counter() - t2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", nargs="+", default=["trbo", "tsbo-tsp", "tsbo-gp"])
    ap.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    ap.add_argument("--from", dest="first", type=int, default=91, help="first evaluation (91)")
    ap.add_argument("--to", dest="last", type=int, default=110, help="last evaluation (110)")
    args = ap.parse_args()
    times: dict[str, list[np.ndarray]] = {m: [] for m in args.methods}
    for seed in range(args.seeds):
        for m in args.methods:
            times[m].append(step_times(m, seed, args.last)[args.first - 1 : args.last])
    figures = {}
    for m, runs in times.items():
        t = 1e3 * np.concatenate(runs)
        figures[m] = {
            "median_ms": round(float(np.median(t)), 2),
            "mean_ms": round(float(t.mean()), 2),
        }
        print(
            f"{m:10s} ask+tell at evaluations {args.first}-{args.last}: "
            f"median {figures[m]['median_ms']:.1f} ms, mean {figures[m]['mean_ms']:.1f} ms"
        )
    print(
        json.dumps(
            {
                "benchmark": "optimizer_overhead",
                "d": 3,
                "evaluations": [args.first, args.last],
                "seeds": args.seeds,
                "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
                "load_avg_1min": round(os.getloadavg()[0], 2),
                "overhead": figures,
            }
        )
    )


if __name__ == "__main__":
    main()
