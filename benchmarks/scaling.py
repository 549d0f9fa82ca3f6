"""Scaling: wall time per evaluation against local Dask workers, and batch size q for TR-BO.

Part 1 — a synthetic large dataset: the bundled manoeuvres (train and test, 31) repeated to
the paper's 216 (``--large``: also to 2160). One cost evaluation is timed in this process
and on a local Dask cluster of 1 and 2 worker processes, as a single point (split across
manoeuvres) and as a batch of as many points as workers (split across points); parallel
efficiency E = T(1 worker) / (2 · T(2 workers)).

Part 2 — TR-BO (the default tuner) on the bundled training set with batch sizes
q = 1, 2, 4, 8 (in process: a batch goes through the vectorised batch kernel): evaluations,
batches (rounds) and wall time until the best cost is within 1 % of J* = 0.352017 (the best
known cost of the bundled set), median over seeds.

    PYTHONPATH=src python benchmarks/scaling.py [--large] [--seeds 3] [--budget 60]

Prints the figures and, as its last line, one JSON object.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from kftune.data import default_dataset
from kftune.optim import minimize
from kftune.tuning.problem import TuningProblem

J_STAR = 0.352017


def _problem(n: int) -> TuningProblem:
    ds = default_dataset()
    pool = list(ds.train) + list(ds.test)
    ms = [pool[i % len(pool)] for i in range(n)]
    return TuningProblem(ms, ds.vehicle, ds.r_default)


def _timed(f, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return min(times)


def per_evaluation(n: int, repeats: int) -> dict:
    from kftune.optim.dask_engine import DaskEngine

    p = _problem(n)
    rng = np.random.default_rng(0)
    X = [p.space.from_unit(0.3 + 0.4 * rng.random(p.space.dim)) for _ in range(2)]
    p.evaluate(X[0])  # compile / load the kernel
    out = {"manoeuvres": n, "samples": sum(m.n for m in p.manoeuvres)}
    out["in_process_s"] = _timed(lambda: p.evaluate(X[0]), repeats)
    for w in (1, 2):
        with DaskEngine(p, workers=w) as e:
            list(e.run(X[:w]))  # warm: every worker loads the kernel
            t_one = _timed(lambda e=e: list(e.run(X[:1])), repeats)
            t_batch = _timed(lambda e=e, w=w: list(e.run(X[:w])), repeats) / w
        out[f"dask{w}_one_point_s"] = t_one
        out[f"dask{w}_batch_per_eval_s"] = t_batch
    out["efficiency_one_point"] = out["dask1_one_point_s"] / (2 * out["dask2_one_point_s"])
    out["efficiency_batch"] = out["dask1_batch_per_eval_s"] / (2 * out["dask2_batch_per_eval_s"])
    return out


def batch_sizes(seeds: int, budget: int) -> dict:
    ds = default_dataset()
    p = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    p.evaluate_batch([p.space.from_unit(np.full(3, 0.5))] * 2)  # compile the batch kernel
    out = {}
    for q in (1, 2, 4, 8):
        runs = []
        for seed in range(seeds):
            hit: dict = {}
            t0 = time.perf_counter()

            def cb(rec, hit=hit, t0=t0):
                if rec.value is not None and rec.value <= 1.01 * J_STAR and not hit:
                    hit["evals"] = rec.number + 1
                    hit["s"] = time.perf_counter() - t0
                return bool(hit)

            minimize(p, p.space, "trbo", budget=budget, seed=seed, batch=q, callback=cb)
            evals = hit.get("evals")
            runs.append(
                {
                    "seed": seed,
                    "evals": evals,
                    "rounds": None if evals is None else -(-evals // q),
                    "s": hit.get("s"),
                }
            )
        reached = [r for r in runs if r["evals"] is not None]
        out[q] = {
            "runs": runs,
            "reached": len(reached),
            "median_evals": statistics.median(r["evals"] for r in reached) if reached else None,
            "median_rounds": statistics.median(r["rounds"] for r in reached) if reached else None,
            "median_s": statistics.median(r["s"] for r in reached) if reached else None,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--large", action="store_true", help="also the 2160-manoeuvre dataset")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-workers", action="store_true")
    ap.add_argument("--skip-batch", action="store_true")
    a = ap.parse_args()
    result: dict = {"j_star": J_STAR}
    if not a.skip_workers:
        result["per_evaluation"] = []
        for n in (216, 2160) if a.large else (216,):
            r = per_evaluation(n, a.repeats)
            result["per_evaluation"].append(r)
            print(
                f"{n} manoeuvres ({r['samples']} samples): in process {r['in_process_s']:.2f} s; "
                f"one point on 1/2 workers {r['dask1_one_point_s']:.2f}/"
                f"{r['dask2_one_point_s']:.2f} s (E = {r['efficiency_one_point']:.0%}); "
                f"a batch, per evaluation, {r['dask1_batch_per_eval_s']:.2f}/"
                f"{r['dask2_batch_per_eval_s']:.2f} s (E = {r['efficiency_batch']:.0%})",
                flush=True,
            )
    if not a.skip_batch:
        bs = batch_sizes(a.seeds, a.budget)
        result["batch"] = bs
        for q, r in bs.items():
            print(
                f"trbo q = {q}: within 1 % of J* in {r['reached']}/{a.seeds} seeds; median "
                f"{r['median_evals']} evaluations, {r['median_rounds']} rounds, "
                f"{r['median_s'] if r['median_s'] is None else round(r['median_s'], 1)} s",
                flush=True,
            )
        q1, q4 = bs[1]["median_evals"], bs[4]["median_evals"]
        result["q4_over_q1_evals"] = None if not (q1 and q4) else q4 / q1
    print(json.dumps(result))


if __name__ == "__main__":
    main()
