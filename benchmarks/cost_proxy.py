"""Is the tuning cost a good proxy for the filter? The training cost J against the test-set β
RMSE of the same filter, at points drawn around the cost's best known point J*.

Issue 11 asks that the better cost give the better filter. This draws ``--points`` points
uniformly in the cube of half-width ``--halfwidth`` (unit-cube units of the search box; 0.1
is one decade of the paper's [1e-10, 1] box per parameter, clipped to the box) around the
point of J* (``benchmarks/ukf_tuning.py``'s long CMA-ES runs, read from its cache or computed
the same way), evaluates the training cost J and the test-set β RMSE [deg] of the filter
tuned there (the KPI average over the test manoeuvres, as ``kftune compare`` reports it), and
reports per band of the gap to J* the median and lowest β RMSE, the rank correlation of J
and β RMSE among the points within 1, 3 and 10 % of J*, and how many points within 1 % have
a lower β RMSE than the filter at J*. A negative or zero correlation near J* means that no
optimiser of this cost can promise a better filter by getting closer to J*.

Usage::

    .venv/bin/python benchmarks/cost_proxy.py [--dataset DIR] [--normalise dataset]
        [--points 600] [--halfwidth 0.1] [--seed 0] [--jobs 2] [--plot FILE.png]

Prints the table and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from kftune.errors import KftuneError
from kftune.tuning.cost import NORMALISATIONS
from ukf_tuning import (  # benchmarks/ is the script's path
    _CONTEXT,
    _init,
    _problem,
    default_jstar_cache,
    json_safe,
    long_run_jstar,
    test_beta_rmse,
)

#: Bands of the gap to J* [%]: (low, high].
BANDS = ((0.0, 0.3), (0.3, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, math.inf))
#: Gap limits [%] for the rank correlations.
NEAR = (1.0, 3.0, 10.0)


def _evaluate(x: list[float]) -> tuple[float, float]:
    """(training cost J, test β RMSE [deg]) of the filter tuned at ``x``."""
    return float(_problem()(np.asarray(x))), test_beta_rmse(x)


def draw(u_star: np.ndarray, halfwidth: float, n: int, seed: int) -> np.ndarray:
    """``n`` points uniform in the cube of half-width ``halfwidth`` around ``u_star``, clipped
    to the unit cube; shape (n, d)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.clip(u_star - halfwidth, 0, 1), np.clip(u_star + halfwidth, 0, 1)
    return lo + rng.random((n, u_star.size)) * (hi - lo)


def analyse(j: np.ndarray, beta: np.ndarray, jstar: float, beta_star: float) -> dict[str, Any]:
    """Bands, rank correlations and the share of near points with a better filter."""
    ok = np.isfinite(j) & np.isfinite(beta)
    gap = 100.0 * (j - jstar) / jstar
    bands = []
    for lo, hi in BANDS:
        m = ok & (gap > lo) & (gap <= hi) if lo > 0 else ok & (gap <= hi)
        bands.append(
            {
                "gap_pct": [lo, hi],
                "n": int(m.sum()),
                "beta_median": float(np.median(beta[m])) if m.any() else None,
                "beta_min": float(np.min(beta[m])) if m.any() else None,
            }
        )
    corr = {}
    for lim in NEAR:
        m = ok & (gap <= lim)
        rho = spearmanr(j[m], beta[m]).statistic if m.sum() >= 5 else math.nan
        corr[str(lim)] = {"n": int(m.sum()), "spearman": None if math.isnan(rho) else float(rho)}
    near = ok & (gap <= 1.0)
    return {
        "bands": bands,
        "spearman_within_pct": corr,
        "within_1pct": int(near.sum()),
        "beta_min_within_1pct": float(np.min(beta[near])) if near.any() else None,
        "within_1pct_better_beta": int((near & (beta < beta_star)).sum()),
        "failed": int((~ok).sum()),
    }


def plot(path: Path, title: str, j: np.ndarray, beta: np.ndarray, jstar: float, bs: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = np.isfinite(j) & np.isfinite(beta)
    gap = np.maximum(100.0 * (j[ok] - jstar) / jstar, 1e-4)
    fig, ax = plt.subplots(figsize=(6.4, 4.2), layout="constrained")
    ax.scatter(gap, beta[ok], s=8, alpha=0.5, label="drawn points")
    ax.scatter([1e-4], [bs], marker="*", s=160, color="C3", label="J* (gap shown at 1e-4 %)")
    ax.axhline(bs, color="C3", lw=0.8, ls="--")
    ax.axvline(1.0, color="0.5", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("gap of the training cost to J* [%]")
    ax.set_ylabel("test-set β RMSE [deg]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default=None, help="dataset directory (default: bundled)")
    ap.add_argument("--normalise", choices=NORMALISATIONS, default="manoeuvre")
    ap.add_argument("--points", type=int, default=600, help="points drawn (default 600)")
    ap.add_argument("--halfwidth", type=float, default=0.1, help="unit-cube half-width (0.1)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the draw (default 0)")
    ap.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    ap.add_argument("--jstar-cache", type=Path, default=None, help="ukf_tuning's J* cache")
    ap.add_argument("--jstar-runs", type=int, default=3)
    ap.add_argument("--jstar-evals", type=int, default=2000)
    ap.add_argument("--plot", type=Path, default=None, help="write the scatter plot here")
    args = ap.parse_args(argv)
    if args.points < 5 or not 0 < args.halfwidth <= 1 or args.jobs < 1:
        ap.error("--points must be >= 5, --halfwidth in (0, 1], --jobs >= 1")
    spec = (None if args.dataset in (None, "default") else str(args.dataset), args.normalise)
    try:
        _init(spec)
    except KftuneError as exc:
        print(f"cost_proxy: error: {exc}", file=sys.stderr)
        return 3
    problem, ds = _problem(), _CONTEXT["dataset"]
    if not ds.test:
        print(f"cost_proxy: error: dataset {ds.name!r} has no test manoeuvres", file=sys.stderr)
        return 3
    cache = args.jstar_cache or default_jstar_cache()
    key = f"{problem.fingerprint()['sha256']}|cma|{args.jstar_runs}x{args.jstar_evals}"
    executor = None
    if args.jobs > 1:
        executor = ProcessPoolExecutor(
            args.jobs, mp_context=get_context("spawn"), initializer=_init, initargs=(spec,)
        )

    def pool_map(fn: Any, arg_list: list[tuple]) -> list[Any]:
        if executor is None:
            return [fn(*a) for a in arg_list]
        return list(executor.map(fn, *zip(*arg_list, strict=True), chunksize=8))

    try:
        ref = long_run_jstar(spec, key, cache, args.jstar_runs, args.jstar_evals, pool_map)
        x_star = np.asarray(ref["x"], dtype=float)
        jstar, beta_star = _evaluate(list(x_star))
        u = draw(problem.space.to_unit(x_star), args.halfwidth, args.points, args.seed)
        xs = [list(problem.space.from_unit(ui)) for ui in u]
        res = np.asarray(pool_map(_evaluate, [(x,) for x in xs]), dtype=float)
    finally:
        if executor is not None:
            executor.shutdown(cancel_futures=True)
    j, beta = res[:, 0], res[:, 1]
    jstar = min(jstar, float(np.nanmin(j)))
    out = analyse(j, beta, jstar, beta_star)
    print(
        f"{ds.name} ({args.normalise}): J* = {jstar:.6f} at q = "
        f"({', '.join(f'{v:.3g}' for v in x_star)}); test β RMSE there {beta_star:.4f}°; "
        f"{args.points} points within ±{args.halfwidth} of it (seed {args.seed})"
    )
    print(f"{'gap to J* [%]':>16s} {'n':>5s} {'β median':>9s} {'β lowest':>9s}")
    for b in out["bands"]:
        lo, hi = b["gap_pct"]
        med = "" if b["beta_median"] is None else f"{b['beta_median']:.4f}"
        low = "" if b["beta_min"] is None else f"{b['beta_min']:.4f}"
        print(f"{f'({lo:g}, {hi:g}]':>16s} {b['n']:5d} {med:>9s} {low:>9s}")
    for lim, c in out["spearman_within_pct"].items():
        rho = "n/a" if c["spearman"] is None else f"{c['spearman']:+.2f}"
        print(f"rank correlation of J and β RMSE within {lim} % of J*: {rho} (n = {c['n']})")
    print(
        f"within 1 % of J*: {out['within_1pct_better_beta']} of {out['within_1pct']} points "
        f"have a lower test β RMSE than the filter at J*"
    )
    if args.plot:
        plot(args.plot, f"{ds.name}, {args.normalise}", j, beta, jstar, beta_star)
        print(f"plot: {args.plot}")
    summary = {
        "dataset": ds.name,
        "normalise": args.normalise,
        "jstar": jstar,
        "x_star": x_star.tolist(),
        "beta_at_jstar": beta_star,
        "points": args.points,
        "halfwidth": args.halfwidth,
        "seed": args.seed,
        **out,
    }
    print(json.dumps(json_safe(summary), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
