"""How narrow is the UKF cost's optimum? One-at-a-time log10 steps around a point, whole-axis
profiles, and the volume of the 1 % set.

Evaluates the paper's cost on the bundled training set at ``q`` and at ``q`` with one
process-noise entry multiplied by 10^s for each step s (decades), and reports how far each
entry may move before the cost is 1 % above its value at ``q``. The default ``q`` is the
long-run reference of ``benchmarks/ukf_tuning.py`` (best of CMA-ES runs with 2,000
evaluations, seed 0 of 2026-11-22).

Then, with the other two entries at ``q``, the cost along each whole log10 axis of the
search box ([1e-10, 1], half-decade steps), relative to J(q) — this shows the plateaus a
surrogate sees — and a Monte Carlo estimate of the share of the search box (unit cube of
the log10 parameters) where the cost is within 1 % of J(q): ``--mc`` points drawn uniformly
in the cube of half-width 0.1 around ``q`` (which holds the whole 1 % set: checked by the
one-at-a-time steps), scaled by that cube's volume. Its inverse is how many evaluations a
random search needs on average to land in the set once.

Usage: python benchmarks/cost_sensitivity.py [--q QVX QVY QR] [--mc 2000] [--seed 0]
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
    ap.add_argument("--mc", type=int, default=2000, help="Monte Carlo points (default 2000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo draw")
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

    space = problem.space
    grid = np.arange(-10.0, 0.001, 0.5)
    print(f"\nwhole-axis profiles, (J / J(q) - 1) in %, log10 q = {grid[0]:g} … {grid[-1]:g}")
    profiles: dict[str, list[float]] = {}
    for i, name in enumerate(names):
        rel = []
        for g in grid:
            y = q.copy()
            y[i] = 10.0**g
            rel.append(100.0 * (problem(y) / j0 - 1.0))
        profiles[name] = rel
        print(f"{name:5s} " + " ".join(f"{r:6.1f}" for r in rel))
    out["profile_log10_grid"] = grid.tolist()
    out["profile_pct"] = profiles

    half = 0.1
    rng = np.random.default_rng(args.seed)
    u0 = space.to_unit(q)
    u = np.clip(u0 + rng.uniform(-half, half, size=(args.mc, len(names))), 0.0, 1.0)
    inside = np.array([problem(space.from_unit(p)) <= 1.01 * j0 for p in u])
    share = float(inside.mean()) * (2 * half) ** len(names)
    print(
        f"\nshare of the search box within 1 %: {share:.2e} ({int(inside.sum())} of {args.mc} "
        f"points in the cube of half-width {half} around q); random search needs "
        f"≈ {1 / share if share else float('inf'):.0f} evaluations per hit"
    )
    out["share_within_1pct"] = share
    out["mc_points"] = args.mc
    print(json.dumps(out))


if __name__ == "__main__":
    main()
