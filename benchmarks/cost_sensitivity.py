"""How narrow is the UKF cost's optimum? One-at-a-time log10 steps around a point.

Evaluates the paper's cost on the bundled training set at ``q`` and at ``q`` with one
process-noise entry multiplied by 10^s for each step s (decades), and reports how far each
entry may move before the cost is 1 % above its value at ``q``. The default ``q`` is the
long-run reference of ``benchmarks/ukf_tuning.py`` (best of CMA-ES runs with 2,000
evaluations, seed 0 of 2026-11-22).

Usage: python benchmarks/cost_sensitivity.py [--q QVX QVY QR]
Last line: one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from kftune.data import default_dataset
from kftune.tuning.problem import TuningProblem

STEPS = (-2.0, -1.0, -0.5, -0.3, -0.2, -0.1, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)  # decades


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--q", type=float, nargs=3, default=[5.2232655e-08, 1.5591458e-06, 0.17260204])
    args = ap.parse_args()
    ds = default_dataset()
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    names = [p.name for p in problem.space.params]
    q = np.array(args.q)
    j0 = problem(q)
    print(f"J(q) = {j0:.5f} at q = {q.tolist()}; steps in decades: {list(STEPS)}")
    out: dict[str, object] = {"q": q.tolist(), "J": j0, "steps": list(STEPS)}
    for i, name in enumerate(names):
        costs = []
        for s in STEPS:
            y = q.copy()
            y[i] *= 10.0**s
            costs.append(problem(y))
        within = [s for s, c in zip(STEPS, costs, strict=True) if c <= 1.01 * j0]
        lo, hi = (min(within), max(within)) if within else (0.0, 0.0)
        print(
            f"{name:5s} " + " ".join(f"{c:.4f}" for c in costs) + f"   within 1 %: {lo:+} … {hi:+}"
        )
        out[name] = {"J": costs, "within_1pct_decades": [lo, hi]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
