"""Which cost tunes the better filter: does a cost that needs no sideslip sensor tune a
filter whose test β RMSE beats the manual rule of thumb and comes within 1.5× of the
NRMSE-tuned filter's (issue 13, item 5)? And which normalisation of the NRMSE gives the
filter with the lower test β RMSE (issue 11: the cost is a proxy)?

Per dataset (the bundled one, ``../shared/data/revs-250lm``, or any dataset directory
``kftune`` opens) it tunes the UKF on the training manoeuvres with each configuration and
scores the tuned filter on the test manoeuvres with the KPI code ``kftune compare`` uses
(:func:`kftune.tuning.problem.assess`, :func:`kftune.tuning.kpi.average_kpis`):

* ``manual``: the rule of thumb Q = diag(1e-6, 1e-4, 1e-6) (no tuning);
* ``nrmse``: the paper's cost (needs the β reference) — the target to come near;
* ``nrmse-dataset``: the same channels and weights, each channel's RMSE over all training
  manoeuvres over its largest |X| (``--normalise dataset``) instead of each manoeuvre's
  RMSE over its own max|X| (Eq. 15);
* ``nrmse-prior``: the paper's cost with yaw rate and ay scored by the one-step prediction
  (``--estimate prior``), which cannot copy the measurement;
* ``nis``: |log(mean NIS / 3)| (Chen et al. 2018), Q only — the old reference-free cost;
* ``pem-q``, ``pem-rscale``, ``pem-rdiag``: the innovation negative log-likelihood
  (``--cost pem``) with Q only, Q and one R scale, Q and R's diagonal;
* ``msp``: the multi-step (0.35 s) open-loop prediction error of r and ay (``--cost msp``),
  Q only.

Each tuned configuration runs with ``--method`` (default ``trbo``) at ``--budget``
evaluations for every seed. Reported per configuration: the median over seeds of the test
β RMSE [deg] (and its range), the paper's cost J (Eq. 14–15, training manoeuvres) at the
tuned point, and the filter's sideslip calibration on the test set — the
mean β NEES (error² / σ², 1 for a calibrated filter) and the share of samples with the
error inside ±2σ (95 % for a calibrated Gaussian filter), with σ² of β = atan2(Vy, Vx)
linearised from P's diagonal (the Vx–Vy covariance, which the filter does not output, is
left out; at |β| of a few degrees Vy's variance dominates).

Then the checks of issue 13: for each reference-free configuration, median test β RMSE
below the manual one, and at most 1.5× the NRMSE-tuned one.

With ``--rank-top N`` it also asks whether the training cost still ranks the test error near
the optimum each run reached: the ``N`` distinct points of lowest training cost J that the
run evaluated (its tuned point first) are each scored on the test manoeuvres, and the
Spearman rank correlation ρ(J, test β RMSE) is reported per run (median over seeds), over
the ``N`` points of every seed pooled, the gap of the ``N``-th point's J to the run's best,
and the lowest test β RMSE among the ``N`` points (what a perfect proxy would have chosen).
ρ near +1: the lower cost is the better filter there; near 0 or negative: the cost no longer
tells the filters apart, and more evaluations buy no better filter.

Usage::

    .venv/bin/python benchmarks/reference_free.py
    .venv/bin/python benchmarks/reference_free.py --dataset ../shared/data/revs-250lm
    .venv/bin/python benchmarks/reference_free.py --seeds 3 --budget 40 --configs manual pem-q
    .venv/bin/python benchmarks/reference_free.py --configs nrmse nrmse-dataset --budget 100
    .venv/bin/python benchmarks/reference_free.py --configs nrmse nrmse-dataset --budget 100 \
        --rank-top 20

Prints a table and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import platform
import statistics
import time
from typing import Any

import numpy as np
from scipy.stats import spearmanr

import kftune
from kftune.data import open_dataset
from kftune.errors import FilterDivergedError
from kftune.experiment import manual_point
from kftune.optim import minimize
from kftune.tuning.cost import CostSpec
from kftune.tuning.kpi import average_kpis
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem, assess

#: configuration → (cost, R tuning).
CONFIGS: dict[str, tuple[CostSpec, str]] = {
    "manual": (CostSpec(), "none"),
    "nrmse": (CostSpec(), "none"),
    "nrmse-dataset": (CostSpec(normalise="dataset"), "none"),
    "nrmse-prior": (CostSpec(estimate="prior"), "none"),
    "nis": (CostSpec(kind="nis"), "none"),
    "pem-q": (CostSpec(kind="pem"), "none"),
    "pem-rscale": (CostSpec(kind="pem"), "scale"),
    "pem-rdiag": (CostSpec(kind="pem"), "diag"),
    "msp": (CostSpec(kind="msp"), "none"),
}
REFERENCE_FREE = ("nis", "pem-q", "pem-rscale", "pem-rdiag", "msp")
#: issue 13: within this factor of the NRMSE-tuned filter's test β RMSE.
WITHIN = 1.5


def beta_calibration(problem: TuningProblem, x: np.ndarray, manoeuvres: Any) -> dict[str, float]:
    """Mean β NEES and ±2σ coverage of the filter at x over the manoeuvres (see above)."""
    nees, inside, n = 0.0, 0, 0
    for m in manoeuvres:
        res = problem.run(x, m)
        if res.diverged:
            return {"nees": math.nan, "coverage_2sigma": math.nan}
        vx, vy = res.x[:, 0], res.x[:, 1]
        d = vx * vx + vy * vy
        var = (vx * vx * res.P_diag[:, 1] + vy * vy * res.P_diag[:, 0]) / (d * d)
        err = np.arctan2(vy, vx) - m.beta_ref
        nees += float(np.sum(err * err / var))
        inside += int(np.sum(np.abs(err) <= 2.0 * np.sqrt(var)))
        n += m.n
    return {"nees": nees / n, "coverage_2sigma": inside / n}


def test_beta_rmse(problem: TuningProblem, x: np.ndarray, manoeuvres: Any) -> float:
    """Mean over ``manoeuvres`` of the β RMSE [deg] of the filter at ``x`` (NaN: diverged)."""
    per_manoeuvre, _ = assess(problem, x, manoeuvres)
    return float(average_kpis(per_manoeuvre.values())["rmse"])


def rank_near_optimum(
    problem: TuningProblem, history: Any, manoeuvres: Any, top: int
) -> dict[str, Any]:
    """The ``top`` distinct points of lowest training cost in ``history`` (EvalRecords),
    each with its test β RMSE [deg], and Spearman's ρ between the two (None below 5 points
    or where either is constant)."""
    seen: set[tuple[float, ...]] = set()
    best: list[tuple[float, tuple[float, ...]]] = []
    for rec in sorted((r for r in history if r.ok), key=lambda r: r.value):
        if rec.x not in seen:
            seen.add(rec.x)
            best.append((float(rec.value), rec.x))
        if len(best) == top:
            break
    j = np.array([v for v, _ in best])
    beta = np.array([test_beta_rmse(problem, np.asarray(x), manoeuvres) for _, x in best])
    ok = np.isfinite(beta)
    rho = math.nan
    if ok.sum() >= 5 and np.ptp(j[ok]) > 0 and np.ptp(beta[ok]) > 0:
        rho = float(spearmanr(j[ok], beta[ok]).statistic)
    return {
        "J": j.tolist(),
        "beta_rmse_deg": beta.tolist(),
        "spearman": None if math.isnan(rho) else rho,
        "gap_last_pct": float(100.0 * (j[-1] - j[0]) / j[0]) if j.size else None,
        "beta_min_deg": float(np.nanmin(beta)) if ok.any() else None,
    }


def run_config(
    ds: Any, name: str, method: str, budget: int, seed: int, rank_top: int = 0
) -> dict[str, Any]:
    cost, tune_r = CONFIGS[name]
    par = NoiseParameterization(tune_r=tune_r)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default, cost=cost, parameterization=par)
    paper = TuningProblem(ds.train, ds.vehicle, ds.r_default, parameterization=par)
    t0 = time.perf_counter()
    history: list[Any] = []
    if name == "manual":
        x, fun, n_eval = manual_point(par), math.nan, 1
    else:
        res = minimize(problem, problem.space, method, budget=budget, seed=seed)
        x, fun, n_eval = np.asarray(res.x, dtype=float), float(res.fun), len(res.history)
        history = res.history
    wall = time.perf_counter() - t0
    per_manoeuvre, _ = assess(problem, x, ds.test)
    kpis = average_kpis(per_manoeuvre.values())
    rank = None
    if rank_top > 0 and history:
        rank = rank_near_optimum(problem, history, ds.test, rank_top)
    try:
        paper_cost = float(paper(x))
    except FilterDivergedError:
        paper_cost = math.inf
    return {
        "config": name,
        "seed": seed,
        "params": dict(zip(problem.space.names, x.tolist())),
        "cost": fun,
        "paper_cost": paper_cost,
        "evaluations": n_eval,
        "wall_s": wall,
        "beta_rmse_deg": kpis["rmse"],
        "beta_mae_deg": kpis["mae"],
        **beta_calibration(problem, x, ds.test),
        "rank": rank,
    }


def _fmt_rho(rho: float | None) -> str:
    return "n/a" if rho is None else f"{rho:+.2f}"


def pooled_rank(ranked: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary over seeds of :func:`rank_near_optimum`'s records: median per-run ρ, ρ of
    the points of every run pooled, median gap of the last point, lowest test β."""
    j = np.concatenate([r["J"] for r in ranked])
    beta = np.concatenate([r["beta_rmse_deg"] for r in ranked])
    ok = np.isfinite(beta)
    rhos = [r["spearman"] for r in ranked if r["spearman"] is not None]
    pooled = float(spearmanr(j[ok], beta[ok]).statistic) if ok.sum() >= 5 else math.nan
    return {
        "rank_median_spearman": statistics.median(rhos) if rhos else None,
        "rank_pooled_spearman": None if math.isnan(pooled) else pooled,
        "rank_pooled_n": int(ok.sum()),
        "rank_median_gap_last_pct": statistics.median(r["gap_last_pct"] for r in ranked),
        "rank_min_beta_deg": float(np.nanmin(beta)),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=None, help="dataset directory (default: bundled)")
    ap.add_argument("--method", default="trbo")
    ap.add_argument("--budget", type=int, default=40)
    ap.add_argument("--seeds", type=int, default=3, help="number of seeds (default 3)")
    ap.add_argument(
        "--seed-offset", type=int, default=0, help="first seed (default 0; fresh seeds: 3)"
    )
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument(
        "--rank-top",
        type=int,
        default=0,
        metavar="N",
        help="also score the N lowest-cost points of each run on the test set (default 0)",
    )
    args = ap.parse_args(argv)
    if args.rank_top < 0:
        ap.error("--rank-top must be >= 0")

    ds = open_dataset(args.dataset)
    runs: list[dict[str, Any]] = []
    for name in args.configs:
        seeds = range(args.seed_offset, args.seed_offset + (1 if name == "manual" else args.seeds))
        for seed in seeds:
            r = run_config(ds, name, args.method, args.budget, seed, args.rank_top)
            runs.append(r)
            rank = r["rank"]
            print(
                f"{name:<11} seed {seed}: test β RMSE {r['beta_rmse_deg']:.4f}°  "
                f"NEES {r['nees']:.3g}  ±2σ {100 * r['coverage_2sigma']:.1f} %  "
                f"J {r['cost']:.4g}  paper J {r['paper_cost']:.6g}  {r['wall_s']:.1f} s  "
                + " ".join(f"{k}={v:.3g}" for k, v in r["params"].items())
                + (
                    ""
                    if rank is None
                    else f"  top {len(rank['J'])}: ρ(J, β) {_fmt_rho(rank['spearman'])}, "
                    f"J within {rank['gap_last_pct']:.2f} %, lowest β {rank['beta_min_deg']:.4f}°"
                ),
                flush=True,
            )
    summary: dict[str, dict[str, float]] = {}
    for name in args.configs:
        rs = [r for r in runs if r["config"] == name]
        rmse = [r["beta_rmse_deg"] for r in rs]
        summary[name] = {
            "median_beta_rmse_deg": statistics.median(rmse),
            "median_paper_cost": statistics.median(r["paper_cost"] for r in rs),
            "min_beta_rmse_deg": min(rmse),
            "max_beta_rmse_deg": max(rmse),
            "median_nees": statistics.median(r["nees"] for r in rs),
            "median_coverage_2sigma": statistics.median(r["coverage_2sigma"] for r in rs),
        }
        ranked = [r["rank"] for r in rs if r["rank"] is not None]
        if ranked:
            summary[name].update(pooled_rank(ranked))
    print()
    print("| Config | median test β RMSE [°] | range [°] | paper J | β NEES | ±2σ coverage |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, s in summary.items():
        print(
            f"| {name} | {s['median_beta_rmse_deg']:.4f} | {s['min_beta_rmse_deg']:.4f}–"
            f"{s['max_beta_rmse_deg']:.4f} | {s['median_paper_cost']:.6g} | "
            f"{s['median_nees']:.3g} | "
            f"{100 * s['median_coverage_2sigma']:.1f} % |"
        )
    if any("rank_pooled_spearman" in s for s in summary.values()):
        print()
        print(
            f"| Config | ρ(J, test β) per run, median | pooled over seeds (n) | gap of the "
            f"{args.rank_top}-th point [%] | lowest test β among them [°] |"
        )
        print("| --- | --- | --- | --- | --- |")
        for name, s in summary.items():
            if "rank_pooled_spearman" in s:
                print(
                    f"| {name} | {_fmt_rho(s['rank_median_spearman'])} | "
                    f"{_fmt_rho(s['rank_pooled_spearman'])} ({s['rank_pooled_n']}) | "
                    f"{s['rank_median_gap_last_pct']:.2f} | {s['rank_min_beta_deg']:.4f} |"
                )
    checks: dict[str, dict[str, bool | None]] = {}
    man = summary.get("manual", {}).get("median_beta_rmse_deg")
    ref = summary.get("nrmse", {}).get("median_beta_rmse_deg")
    for name in REFERENCE_FREE:
        if name not in summary:
            continue
        v = summary[name]["median_beta_rmse_deg"]
        checks[name] = {
            "beats_manual": None if man is None else v < man,
            "within_1.5x_nrmse": None if ref is None else v <= WITHIN * ref,
        }
        verdict = ", ".join(
            f"{k}: {'n/a' if ok is None else 'PASS' if ok else 'FAIL'}"
            for k, ok in checks[name].items()
        )
        print(f"{name}: {verdict}")
    out = {
        "benchmark": "reference_free",
        "date": dt.date.today().isoformat(),
        "kftune_version": kftune.__version__,
        "machine": f"{platform.machine()}, Python {platform.python_version()}",
        "dataset": args.dataset or "bundled",
        "method": args.method,
        "budget": args.budget,
        "seeds": list(range(args.seed_offset, args.seed_offset + args.seeds)),
        "summary": summary,
        "checks": checks,
        "runs": runs,
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
