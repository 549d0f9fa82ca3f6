"""TR-BO design runs: gap to J* at 40 and 100 evaluations for one set of TR-BO options.

Runs :class:`kftune.optim.TrustRegionBO` with the given options on the paper's cost of a
dataset's training set, once per seed for the largest budget (TR-BO does not see its
budget, so the first b evaluations are the run at budget b), and prints the median and worst
gap to J* over the seeds, each seed's gaps, and the optimiser's own time per evaluation.
Two option sets run on the same seeds are paired by seed (BENCHMARKS.md, "TR-BO").

Usage::

    .venv/bin/python benchmarks/trbo_design.py                               # the defaults
    .venv/bin/python benchmarks/trbo_design.py --opts '{"faces": false}' --seeds 0-9
    .venv/bin/python benchmarks/trbo_design.py --dataset ../shared/data/revs-250lm \\
        --jstar 0.548688 --opts '{"global_every": 3}'

J* defaults to the bundled set's (0.352017, three CMA-ES runs of 2,000 evaluations; see
``benchmarks/ukf_tuning.py``, which computes and caches it for any dataset). Prints the
table and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from kftune.data import open_dataset
from kftune.errors import FilterDivergedError
from kftune.optim import TRBOSettings, TrustRegionBO
from kftune.tuning.problem import TuningProblem

BUNDLED_JSTAR = 0.352017


def run(problem: TuningProblem, seed: int, budget: int, opts: dict) -> dict:
    """One TR-BO run: best-so-far trace and optimiser time per evaluation."""
    opt = TrustRegionBO(problem.space, TRBOSettings(**opts), budget=budget, seed=seed)
    values, t_eval, t0 = [], 0.0, time.perf_counter()
    while not opt.done:
        trial = opt.ask()
        t1 = time.perf_counter()
        try:
            value = problem(trial.x)
        except FilterDivergedError:
            value = None
        t_eval += time.perf_counter() - t1
        opt.tell(trial, value)
        values.append(np.inf if value is None else value)
    wall = time.perf_counter() - t0
    return {"best": np.minimum.accumulate(values), "overhead_s": (wall - t_eval) / budget}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=None, help="dataset (default: the bundled one)")
    ap.add_argument("--jstar", type=float, default=BUNDLED_JSTAR, help="best known cost J*")
    ap.add_argument("--opts", default="{}", help="TR-BO options as a JSON object")
    ap.add_argument("--seeds", default="0-9", help="seed range FIRST-LAST (default 0-9)")
    ap.add_argument("--budgets", type=int, nargs="+", default=[40, 100])
    args = ap.parse_args()
    first, last = (int(v) for v in args.seeds.split("-"))
    opts = json.loads(args.opts)
    ds = open_dataset(args.dataset)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    budget = max(args.budgets)
    runs = {s: run(problem, s, budget, opts) for s in range(first, last + 1)}
    out: dict = {"benchmark": "trbo_design", "dataset": ds.name, "jstar": args.jstar}
    out["options"] = opts
    for b in args.budgets:
        gaps = [100.0 * (float(r["best"][b - 1]) / args.jstar - 1.0) for r in runs.values()]
        out[f"gap_at_{b}"] = {
            "median": float(np.median(gaps)),
            "worst": max(gaps),
            "per_seed": gaps,
        }
        print(
            f"{ds.name} {opts}: gap at {b}: median {np.median(gaps):.2f} %, worst "
            f"{max(gaps):.2f} %; per seed " + " ".join(f"{g:.2f}" for g in gaps)
        )
    ovh = 1e3 * float(np.median([r["overhead_s"] for r in runs.values()]))
    out["overhead_ms_per_eval"] = ovh
    print(f"optimiser time per evaluation: {ovh:.0f} ms (median over seeds)")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
