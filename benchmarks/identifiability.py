"""How far the identifiability that ``kftune tune`` reports can be trusted: its ranges of
the tuned model parameters against the system-identification reference, a profile with
every other parameter re-optimised at each point.

``kftune.tuning.identify`` profiles the cost along each tuned model parameter with the
other coordinates *held* at the tuned point (at most 10 evaluations per parameter, one more
per pair for the joint curvature over the model parameters). A profile that re-optimises
the others at each point (Raue et al. 2009: the profile likelihood) is the reference, at
some hundred evaluations per point. Holding can only narrow a valley, so the held range is
never wider than the re-optimised one; this measures how much narrower it is, and whether
the verdict (determined or not) agrees.

Per dataset: the joint tuning (TR-BO, ``--budget`` evaluations, seed 0) of Q with C_af,
C_ar ∈ [2e4, 4e5] N/rad and μ ∈ [0.4, 1.6] (log10), then per model parameter:

* ``held``: identify's profile range (J ≤ J* + 1 %), and its evaluations;
* ``joint``: identify's quadratic range with the other model parameters re-fitted;
* ``re-opt``: the same profile points (±0.01, 0.03, 0.1, 0.3 of the box in log10), each
  with every other coordinate (Q and the other model parameters) re-optimised by
  Nelder–Mead in the unit cube from the tuned point (``--reopt-evals`` per point), the
  range read off as identify reads it (√-interpolated crossing of J* + 1 %);
* the ratio of the widths (in decades) re-opt / held, and the verdicts.

Datasets: ``default`` (the bundled set), ``../shared/data/revs-250lm`` where present, and
``gentle``: two 20-s runs simulated on the single-track model itself with the bundled
vehicle at |ay| ≤ 3 m/s² (29 % of μ·g; tests/test_identify.py's), where μ cannot be
determined and the stiffnesses can.

Usage (from the repository root; about 4 minutes on 2 vCPU):

    nice -n 10 .venv/bin/python benchmarks/identifiability.py

The last line is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize as scipy_minimize

from kftune import minimize
from kftune.data import Manoeuvre, default_dataset, open_dataset
from kftune.models import get_model
from kftune.sim.single_track import SENSOR_STD, gentle_slalom
from kftune.tuning.identify import (
    NOT_DETERMINED_SHARE,
    REL_RISE,
    STEPS,
    _side_end,
    identify_problem,
)
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem
from kftune.tuning.runs import default_r0
from kftune.vehicle.params import VehicleParams

BOUNDS = {"C_af": (2e4, 4e5), "C_ar": (2e4, 4e5), "mu": (0.4, 1.6)}
REVS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "revs-250lm"


def gentle_runs(vehicle: VehicleParams) -> list[Manoeuvre]:
    """Two 20-s slalom-like runs on the single-track model, |ay| ≤ 3 m/s², noisy sensors."""
    return [gentle_slalom(f"gentle-{seed}", vehicle, seed, ay_peak=3.0) for seed in range(2)]


def problem_of(name: str) -> TuningProblem:
    par = NoiseParameterization(model_bounds=BOUNDS)
    if name == "gentle":
        vehicle = default_dataset().vehicle
        return TuningProblem(
            gentle_runs(vehicle), vehicle, np.square(SENSOR_STD), parameterization=par
        )
    ds = open_dataset(name)
    r0 = default_r0(get_model("single-track"), ds)
    return TuningProblem(ds.train, ds.vehicle, r0, parameterization=par)


def reoptimised_range(
    problem: TuningProblem, x: np.ndarray, name: str, j0: float, evals: int
) -> tuple[float, float, bool, bool, int]:
    """(low, high, closed low, closed high, evaluations) of the profile with every other
    coordinate re-optimised (Nelder–Mead in the unit cube from x, ``evals`` per point)."""
    space = problem.space
    i = space.names.index(name)
    u_best = space.to_unit(x)
    free = [k for k in range(space.dim) if k != i]
    spent = 0

    def cost_at(u_i: float) -> float:
        nonlocal spent

        def f(v: np.ndarray) -> float:
            nonlocal spent
            u = u_best.copy()
            u[free] = np.clip(v, 0.0, 1.0)
            u[i] = u_i
            spent += 1
            try:
                return problem(space.from_unit(u))
            except Exception:  # a diverged filter: worse than any finite cost
                return math.inf

        start = u_best[free]
        simplex = np.vstack([start, start + 0.05 * np.eye(len(free))])
        res = scipy_minimize(
            f, start, method="Nelder-Mead",
            options={"maxfev": evals, "initial_simplex": np.clip(simplex, 0, 1)},
        )  # fmt: skip
        return float(res.fun)

    p = space.params[i]
    ends = []
    for sign in (-1.0, 1.0):
        side = []
        for s in STEPS:
            u_i = u_best[i] + sign * s
            if not 0.0 <= u_i <= 1.0:
                break
            side.append((s * p.width, cost_at(u_i)))
        d, closed = _side_end(side, j0, REL_RISE * j0, j0 * (1 + REL_RISE))
        ends.append((d if closed else (side[-1][0] if side else 0.0), closed))
    t0 = math.log10(x[i])
    (d_lo, c_lo), (d_hi, c_hi) = ends
    return 10 ** (t0 - d_lo), 10 ** (t0 + d_hi), c_lo, c_hi, spent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=100, help="TR-BO evaluations (default 100)")
    ap.add_argument("--reopt-evals", type=int, default=60, help="per re-optimised point")
    ap.add_argument("--datasets", nargs="*", default=None)
    args = ap.parse_args()
    names = args.datasets or ["default", *([str(REVS)] if REVS.is_dir() else []), "gentle"]
    out: dict[str, dict] = {}
    for name in names:
        problem = problem_of(name)
        result = minimize(problem, problem.space, method="trbo", budget=args.budget, seed=0)
        t = time.perf_counter()
        ident = identify_problem(problem, result.x)
        t_ident = time.perf_counter() - t
        label = Path(name).name
        print(f"\n{label}: J* = {result.fun:.5g} after {result.n_evals} TR-BO evaluations; "
              f"identify: {ident.n_evals} evaluations, {t_ident:.2f} s")  # fmt: skip
        print(f"  {'param':5s} {'value':>9s} {'held range':>21s} {'joint range':>21s} "
              f"{'re-opt range':>21s} {'ratio':>6s}  held/re-opt verdict  evals")  # fmt: skip
        rows = {}
        for rec in ident.parameters:
            t = time.perf_counter()
            lo, hi, c_lo, c_hi, spent = reoptimised_range(
                problem, result.x, rec.name, rec.cost, args.reopt_evals
            )
            t_re = time.perf_counter() - t
            width = math.log10(rec.high / rec.low)
            share = math.log10(hi / lo) / width
            re_det = c_lo and c_hi and share < NOT_DETERMINED_SHARE
            held_w = math.log10(rec.range_high / rec.range_low)
            ratio = math.log10(hi / lo) / held_w if held_w > 0 else math.inf
            jlo, jhi = rec._joint_range() if rec.joint_half_width is not None else (None, None)
            rows[rec.name] = {
                "value": rec.value, "held": [rec.range_low, rec.range_high],
                "joint": None if jlo is None else [jlo, jhi], "reopt": [lo, hi],
                "reopt_closed": [c_lo, c_hi], "ratio_reopt_to_held": ratio,
                "held_determined": rec.determined, "reopt_determined": bool(re_det),
                "reopt_evals": spent, "reopt_s": t_re,
            }  # fmt: skip
            joint = "—" if jlo is None else f"{jlo:.3g} … {jhi:.3g}"
            opened = "" if (c_lo and c_hi) else " (open)"
            held = f"{rec.range_low:>9.3g} … {rec.range_high:<9.3g}"
            reopt = f"{lo:>9.3g} … {hi:<9.3g}"
            verdicts = f"{rec.determined!s:>5s}/{bool(re_det)!s:<5s}{opened:7s}"
            print(f"  {rec.name:5s} {rec.value:9.4g} {held} {joint:>21s} {reopt} "
                  f"{ratio:6.2f}  {verdicts} {spent}")  # fmt: skip
        out[label] = {"j_best": result.fun, "identify_evals": ident.n_evals,
                      "identify_s": t_ident, "parameters": rows}  # fmt: skip
    agree = [r["held_determined"] == r["reopt_determined"] for d in out.values()
             for r in d["parameters"].values()]  # fmt: skip
    ratios = [r["ratio_reopt_to_held"] for d in out.values() for r in d["parameters"].values()
              if math.isfinite(r["ratio_reopt_to_held"])]  # fmt: skip
    print(f"\nverdicts agree on {sum(agree)} of {len(agree)}; re-opt/held width ratio: median "
          f"{np.median(ratios):.2f}, max {np.max(ratios):.2f}")  # fmt: skip
    print(json.dumps({"datasets": out, "agree": sum(agree), "n": len(agree),
                      "ratio_median": float(np.median(ratios)),
                      "ratio_max": float(np.max(ratios))}))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
