"""UKF-tuning benchmark: how fast each optimiser tunes the sideslip UKF on the bundled data.

Problem: the paper's cost (Eq. 14–15, W = (5, 1, 1)) of the UKF over the bundled training
set (8 manoeuvres), three process-noise parameters on log10 scales in [1e-10, 1].

Methods (same problem, same seeds): TSBO-tSP and TSBO-GP (budget 40 = MAX_PE; also
TSBO with the robust GP, and the opt-in ``mode="improved"`` of TSBO-tSP/GP as
``tsbo-tsp-improved``/``tsbo-gp-improved``), GA (paper Table IV: 15 × 15 = 225), random
search, Optuna TPE, Optuna's GP sampler and CMA-ES (budget 100 each; Optuna GP needs
PyTorch and is skipped without it). The ablation labels of ``benchmarks/optimizers.py``
(``tsbo-tsp-improved-prev``, ``tsbo-tsp-prev+res`` …) can be asked for with ``--methods``.
Each (variant, base) pair of ``optimizers.PAIRS`` that both ran is compared seed by seed
(best cost at 40 evaluations; sign test).

Reference: the best cost any run ever found, including a long CMA-ES run (2,000
evaluations per reference seed) — the "long-run reference". Reported per method:

* best cost after 10, 20, 40, 100 and 225 evaluations (median and quartiles over seeds;
  a run is read at b evaluations as the prefix of its history);
* evaluations needed to come within 1 % of the reference (median over seeds; a run that
  never gets there counts as ∞), and the share of seeds that get there;
* wall time per evaluation: the cost itself and the optimiser's own overhead (medians).

Also measured: one cost evaluation on the bundled training set (median of 30 calls).

Usage::

    .venv/bin/python benchmarks/ukf_tuning.py                    # full: 10 seeds
    .venv/bin/python benchmarks/ukf_tuning.py --seeds 2 --methods tsbo-tsp ga --ref-evals 300
    .venv/bin/python benchmarks/ukf_tuning.py --methods tsbo-tsp tsbo-tsp-improved \\
        --seed-offset 10 --ref-seeds 0                      # paired TSBO variants only

Prints tables and, as its last line, one JSON object with all figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import time
from typing import Any

import numpy as np

import kftune
from kftune.data import default_dataset
from kftune.optim import PeerUnavailableError, minimize
from kftune.tuning.problem import TuningProblem
from optimizers import DEFAULT_METHODS, PAIRS, sign_test_p
from optimizers import METHODS as SYNTHETIC_METHODS  # benchmarks/ is the script's path

BUDGETS = {
    "tsbo-tsp": 40,
    "tsbo-gp": 40,
    "tsbo-robust": 40,
    "ga": 225,
    "random": 100,
    "optuna-tpe": 100,
    "optuna-gp": 100,
    "cma": 100,
}
#: label → (kftune method, options): the peers as themselves, TSBO variants as in
#: benchmarks/optimizers.py (budget 40 like their base).
METHODS: dict[str, tuple[str, dict[str, Any]]] = {m: (m, {}) for m in BUDGETS}
for _label, (_method, _options, _) in SYNTHETIC_METHODS.items():
    if _label.startswith("tsbo-") and _label not in METHODS:
        METHODS[_label] = (_method, dict(_options))
        BUDGETS[_label] = 40
CHECKPOINTS = (10, 20, 40, 100, 225)
TOL = 0.01


def run_method(problem: TuningProblem, label: str, seed: int, budget: int) -> dict[str, Any]:
    """One run: its cost history and timings."""
    method, options = METHODS[label]
    t0 = time.perf_counter()
    res = minimize(problem, problem.space, method, budget=budget, seed=seed, **options)
    wall = time.perf_counter() - t0
    values = [math.inf if r.value is None else float(r.value) for r in res.history]
    t_eval = float(sum(r.t_eval for r in res.history))
    return {
        "values": values,
        "best": float(np.min(values)),
        "x": None if res.x is None else [float(v) for v in res.x],
        "n_evals": res.n_evals,
        "n_failed": res.n_failed,
        "eval_s_per_eval": t_eval / max(res.n_evals, 1),
        "overhead_s_per_eval": (wall - t_eval) / max(res.n_evals, 1),
    }


def evals_to_reach(values: list[float], target: float) -> float:
    """1-based number of evaluations until the running best is ≤ target (∞ if never)."""
    best = np.minimum.accumulate(np.asarray(values))
    hit = np.nonzero(best <= target)[0]
    return float(hit[0] + 1) if hit.size else math.inf


def quartiles(x: list[float]) -> tuple[float, float, float]:
    a = np.asarray(x, dtype=float)
    return tuple(float(v) for v in np.percentile(a, [25, 50, 75]))  # type: ignore[return-value]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds per method (default 10)")
    ap.add_argument("--seed-offset", type=int, default=0, help="first seed (default 0)")
    ap.add_argument("--methods", nargs="+", default=DEFAULT_METHODS, choices=list(METHODS))
    ap.add_argument(
        "--ref-evals", type=int, default=2000, help="CMA-ES evaluations per reference run"
    )
    ap.add_argument("--ref-seeds", type=int, default=3, help="reference CMA-ES runs")
    ap.add_argument("--out", help="also write the JSON object to this file")
    args = ap.parse_args()

    ds = default_dataset()
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    x_manual = np.array([1e-6, 1e-4, 1e-6])
    problem(x_manual)  # load the compiled kernel before timing
    times = []
    for _ in range(30):
        t0 = time.perf_counter()
        problem(x_manual)
        times.append(time.perf_counter() - t0)
    cost_eval_ms = 1e3 * float(np.median(times))
    n_samples = sum(m.n for m in ds.train)
    print(
        f"one cost evaluation: {cost_eval_ms:.1f} ms median over 30 "
        f"({len(ds.train)} manoeuvres, {n_samples} samples)"
    )

    runs: dict[str, list[dict[str, Any]]] = {}
    skipped: dict[str, str] = {}
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    for method in args.methods:
        runs[method] = []
        for seed in seeds:
            try:
                runs[method].append(run_method(problem, method, seed, BUDGETS[method]))
            except PeerUnavailableError as exc:
                skipped[method] = str(exc)
                break
            r = runs[method][-1]
            print(f"  {method:22s} seed {seed}: best {r['best']:.5f} in {r['n_evals']} evals")
        if method in skipped:
            del runs[method]
            print(f"  {method}: skipped ({skipped[method]})")

    ref_runs = []
    for seed in range(args.ref_seeds):
        r = run_method(problem, "cma", 1000 + seed, args.ref_evals)
        ref_runs.append(r)
        print(f"  reference cma seed {1000 + seed}: best {r['best']:.6f} in {args.ref_evals}")
    reference = min([r["best"] for r in ref_runs] + [r["best"] for rs in runs.values() for r in rs])
    target = reference * (1 + TOL)
    print(f"reference (best cost ever found): {reference:.6f}; 1 % target {target:.6f}")

    summary: dict[str, Any] = {}
    width = max([14, *(len(m) + 1 for m in runs)])
    header = f"{'method':{width}s}" + "".join(f"  best@{b:<4d}          " for b in CHECKPOINTS)
    print("\nbest cost, median [quartiles] over seeds")
    print(header + "  evals to 1 %   reached   cost ms/eval  overhead ms/eval")
    for method, rs in runs.items():
        row: dict[str, Any] = {"budget": BUDGETS[method], "seeds": len(rs)}
        cells = []
        for b in CHECKPOINTS:
            if b > BUDGETS[method]:
                cells.append(f"  {'–':20s}")
                continue
            best_b = [float(np.min(r["values"][:b])) for r in rs]
            q1, med, q3 = quartiles(best_b)
            row[f"best_at_{b}"] = {"q1": q1, "median": med, "q3": q3}
            cells.append(f"  {med:.4f} [{q1:.3f},{q3:.3f}]")
        reach = [evals_to_reach(r["values"], target) for r in rs]
        med_reach = float(np.median(reach))
        row["evals_to_1pct_median"] = med_reach if math.isfinite(med_reach) else None
        row["evals_to_1pct"] = [v if math.isfinite(v) else None for v in reach]
        row["share_reached"] = float(np.mean(np.isfinite(reach)))
        row["cost_ms_per_eval"] = 1e3 * float(np.median([r["eval_s_per_eval"] for r in rs]))
        row["overhead_ms_per_eval"] = 1e3 * float(np.median([r["overhead_s_per_eval"] for r in rs]))
        row["n_failed_total"] = int(sum(r["n_failed"] for r in rs))
        row["best_x"] = [r["x"] for r in rs]  # per seed, at the end of the run
        summary[method] = row
        reach_txt = f"{med_reach:.0f}" if math.isfinite(med_reach) else "never"
        print(
            f"{method:{width}s}"
            + "".join(cells)
            + f"  {reach_txt:>11s}   {row['share_reached']:5.0%}"
            f"   {row['cost_ms_per_eval']:10.1f}  {row['overhead_ms_per_eval']:14.1f}"
        )

    # TSBO variants seed by seed, and paired comparisons
    tsbo = [m for m in runs if m.startswith("tsbo-")]
    if tsbo:
        print(f"\nbest cost at 40 evaluations per seed ({', '.join(map(str, seeds))})")
        for m in tsbo:
            vals = " ".join(f"{float(np.min(r['values'][:40])):.4f}" for r in runs[m])
            print(f"  {m:{width}s} {vals}")
        names = problem.space.names
        print(f"its best point, log10 ({', '.join(names)}), per seed")
        for m in tsbo:
            pts = " ".join(
                "(" + ", ".join(f"{math.log10(v):.1f}" for v in r["x"]) + ")" for r in runs[m]
            )
            print(f"  {m:{width}s} {pts}")
    paired: dict[str, Any] = {}
    for variant, base in PAIRS:
        if variant not in runs or base not in runs:
            continue
        v40 = [float(np.min(r["values"][:40])) for r in runs[variant]]
        b40 = [float(np.min(r["values"][:40])) for r in runs[base]]
        lower = sum(v < b for v, b in zip(v40, b40))
        higher = sum(v > b for v, b in zip(v40, b40))
        paired[f"{variant} vs {base}"] = {
            "lower": lower,
            "higher": higher,
            "equal": len(v40) - lower - higher,
            "sign_test_p": sign_test_p(lower, higher),
            "median_diff_at_40": float(np.median(np.subtract(v40, b40))),
        }
        c = paired[f"{variant} vs {base}"]
        print(
            f"paired per seed, {variant} vs {base}: best@40 lower in {lower}, higher in "
            f"{higher} of {len(v40)} (sign test p = {c['sign_test_p']:.2g}); median "
            f"difference {c['median_diff_at_40']:+.4f}"
        )

    # who leads at 40 evaluations
    at40 = {m: s["best_at_40"]["median"] for m, s in summary.items() if "best_at_40" in s}
    if at40:
        leader = min(at40, key=at40.get)
        print(f"\nlowest median best cost at 40 evaluations: {leader} ({at40[leader]:.5f})")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    out = {
        "benchmark": "ukf_tuning",
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.machine()} {os.cpu_count()} cpu, {platform.python_version()}",
        "kftune_version": kftune.__version__,
        "load_average_1min": load,
        "seeds": seeds,
        "cost_eval_ms": cost_eval_ms,
        "train_samples": n_samples,
        "reference_cost": reference,
        "reference_runs": [{"best": r["best"], "x": r["x"]} for r in ref_runs],
        "target_1pct": target,
        "methods": summary,
        "paired": paired,
        "skipped": skipped,
    }
    line = json.dumps(out, allow_nan=False)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(line + "\n")
    print(line)


if __name__ == "__main__":
    main()
