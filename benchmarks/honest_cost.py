"""Which cost tunes a filter that is accurate *and* whose β σ can be trusted?

Per dataset (the bundled one, ``../shared/data/revs-250lm``, fresh noise draws from
``kftune dataset generate``, or any dataset directory ``kftune`` opens) it tunes the UKF on
the training manoeuvres with each cost, TR-BO at ``--budget`` evaluations with the default
settings otherwise (Q only, as ``kftune tune``), for every seed, and measures the tuned
filter on the test manoeuvres:

* ``nrmse``: the paper's weighted NRMSE (the default); ``nrmse-dataset``: the same with
  ``--normalise dataset``;
* ``nlpd``, ``crps``: the proper scoring rules of β_ref under the filter's Gaussian
  N(β̂, σ_β²) (``--cost nlpd`` / ``--cost crps``, β alone); ``nlpd-rscale``,
  ``crps-rscale``: the same with one scale factor of R tuned too (``--tune-r-scale``);
  and, with ``--configs``, ``nrmse-rscale``, ``crps-rscale-wide`` (R's scale in
  [1e-2, 1e4]), ``crps-rdiag``, ``nrmse-rdiag`` and ``nrmse-dataset-rdiag`` (R's diagonal
  tuned);
* ``nis``, ``pem``, ``msp``: the reference-free costs (no target: what they achieve);
* ``manual``: the rule of thumb Q = diag(1e-6, 1e-4, 1e-6), untuned, for scale.

Measured on the test manoeuvres after the burn-in, with the code ``evaluate`` reports
through (:func:`kftune.tuning.problem.assess` for the β RMSE,
:func:`kftune.tuning.deploy.consistency_docs` for the rest): β RMSE [deg], the shares of
samples inside β ± 1σ and ± 1.96σ (68 % / 95 % when calibrated), the mean β NEES with its
95 % χ² band for the effective number of independent errors (1 when calibrated), the mean
NIS (3 when consistent) and the share of test manoeuvres whose mean NIS lies in its band.
Each also after the covariance calibration ``tune`` now applies
(:func:`kftune.tuning.calibrate.calibrate`: one factor c on Q, R, P0 fitted on the training
manoeuvres), marked ``cal``. Medians over the seeds, and ratios against ``nrmse``.

Usage::

    nice -n 10 .venv/bin/python benchmarks/honest_cost.py --datasets bundled \\
        ../shared/data/revs-250lm gen8 --seeds 3 --budget 100

Prints a table per dataset and, as its last line, one JSON object with the figures.
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

import kftune
from kftune.data import open_dataset
from kftune.errors import FilterDivergedError
from kftune.experiment import manual_point, tune
from kftune.tuning.calibrate import CalibrationError, calibrate
from kftune.tuning.cost import CostSpec
from kftune.tuning.deploy import consistency_docs
from kftune.tuning.kpi import average_kpis
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem, assess

#: Tuned parameters beyond ``kftune tune``'s default (Q only): one scale of R
#: (``--tune-r-scale``), in its default box [1e-2, 1e2] or a wider one, or R's diagonal.
RSCALE = {"tune_r": "scale"}
RSCALE_WIDE = {"tune_r": "scale", "r_scale_bounds": (1e-2, 1e4)}
RDIAG = {"tune_r": "diag"}
#: configuration → (its cost, the parameterisation's options).
CONFIGS: dict[str, tuple[CostSpec, dict[str, Any]]] = {
    "manual": (CostSpec(), {}),
    "nrmse": (CostSpec(), {}),
    "nrmse-dataset": (CostSpec(normalise="dataset"), {}),
    "nlpd": (CostSpec(kind="nlpd"), {}),
    "crps": (CostSpec(kind="crps"), {}),
    "nlpd-rscale": (CostSpec(kind="nlpd"), RSCALE),
    "crps-rscale": (CostSpec(kind="crps"), RSCALE),
    "nis": (CostSpec(kind="nis"), {}),
    "pem": (CostSpec(kind="pem"), {}),
    "msp": (CostSpec(kind="msp"), {}),
    # tried beside the above (BENCHMARKS.md, "An honest cost")
    "nrmse-rscale": (CostSpec(), RSCALE),
    "crps-rscale-wide": (CostSpec(kind="crps"), RSCALE_WIDE),
    "crps-rdiag": (CostSpec(kind="crps"), RDIAG),
    "nrmse-rdiag": (CostSpec(), RDIAG),
    # the control of the recommended-setting run: the dataset normalisation with R's
    # diagonal, so that the CRPS's gain is split into the cost's and R tuning's
    "nrmse-dataset-rdiag": (CostSpec(normalise="dataset"), RDIAG),
}
#: What a run without ``--configs`` tunes.
DEFAULT_CONFIGS = list(CONFIGS)[:10]
#: The figures a run measures on the test manoeuvres (medians are taken of each).
FIGURES = ("rmse", "cov68", "cov95", "nees", "nis", "nis_m", "nis_ok")


def measure(problem: TuningProblem, x: np.ndarray, manoeuvres: Any) -> dict[str, float]:
    """β RMSE [deg], coverage of ±1σ and ±1.96σ [share], mean β NEES and its band, mean
    NIS, mean NIS per measurement (NIS/m, 1 when consistent) and the share of manoeuvres
    whose NIS is inside its band, on ``manoeuvres``."""
    per_manoeuvre, results = assess(problem, x, manoeuvres)
    each, pooled = consistency_docs(problem, manoeuvres, results)
    out: dict[str, Any] = {"rmse": average_kpis(per_manoeuvre.values())["rmse"]}
    if pooled is None:  # diverged on a test manoeuvre
        return {**out, **{k: math.nan for k in FIGURES[1:]}, "nees_band": None}
    beta = pooled["channels"]["beta"]
    nis_ok = [d["nis"]["inside"] for d in each.values() if d is not None]
    return {
        **out,
        "cov68": beta["cov68"],
        "cov95": beta["cov95"],
        "nees": beta["nees"]["mean"],
        "nees_band": beta["nees"]["band_eff"],
        "nis": pooled["nis"]["mean"],
        "nis_m": pooled["nis"]["mean"] / problem.model.n_measurements,
        "nis_ok": sum(bool(v) for v in nis_ok) / len(nis_ok),
    }


def r_at_bound(par: NoiseParameterization, params: dict[str, float]) -> list[int]:
    """[k, n]: how many of the n tuned R factors (``r_scale`` or ``r_<measurement>_scale``,
    [-]) end within 1 % of a bound of ``par.r_scale_bounds`` — a tuned R the box, not the
    data, decides. [0, 0] where R is not tuned."""
    lo, hi = par.r_scale_bounds
    k = sum(not lo * 1.01 < params[n] < hi / 1.01 for n in par.r_names)
    return [k, len(par.r_names)]


def run_config(
    ds: Any,
    name: str,
    budget: int,
    seed: int,
    criterion: str | None = None,
    point: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Tune (or take the manual point, or ``point``: parameter name → value, an earlier
    run's) with one cost and measure the filter on the test set, as tuned and after the
    calibration by ``criterion`` (None: ``tune``'s default)."""
    cost, options = CONFIGS[name]
    par = NoiseParameterization(**options)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default, cost=cost, parameterization=par)
    t0 = time.perf_counter()
    if point is not None:
        x, fun = np.array([point[n] for n in problem.space.names]), math.nan
    elif name == "manual":
        x, fun = manual_point(problem.parameterization), math.nan
    else:
        res = tune(problem, "trbo", budget=budget, seed=seed, progress=False)
        x, fun = np.asarray(res.x, dtype=float), float(res.fun)
    wall = time.perf_counter() - t0
    params = dict(zip(problem.space.names, x.tolist()))
    row: dict[str, Any] = {
        "config": name,
        "seed": seed,
        "params": params,
        "cost": fun,
        "wall_s": wall,
        "r_at_bound": r_at_bound(problem.parameterization, params),
        **measure(problem, x, ds.test),
    }
    try:
        how = {} if criterion is None else {"criterion": criterion}
        cal = calibrate(problem, x, **how)
        problem.cov_scale = cal.factor
        row["cal_factor"] = cal.factor
        row.update({f"cal_{k}": v for k, v in measure(problem, x, ds.test).items()})
    except (CalibrationError, FilterDivergedError) as exc:
        row["cal_factor"] = math.nan
        row["cal_error"] = str(exc)
        row.update({f"cal_{k}": math.nan for k in FIGURES})
    return row


def _median(rows: list[dict[str, Any]], key: str) -> float:
    values = [r[key] for r in rows if r.get(key) is not None and math.isfinite(r[key])]
    return statistics.median(values) if values else math.nan


def summarise(runs: list[dict[str, Any]], configs: list[str]) -> dict[str, dict[str, Any]]:
    """Per configuration: the median over seeds of every figure (before and after the
    calibration), the β RMSE's range, and the ratios of the medians to nrmse's."""
    summary: dict[str, dict[str, Any]] = {}
    for name in configs:
        rows = [r for r in runs if r["config"] == name]
        s: dict[str, Any] = {k: _median(rows, k) for k in FIGURES}
        s.update({f"cal_{k}": _median(rows, f"cal_{k}") for k in FIGURES})
        s["cal_factor"] = _median(rows, "cal_factor")
        s["rmse_range"] = [min(r["rmse"] for r in rows), max(r["rmse"] for r in rows)]
        s["nees_band"] = rows[0].get("nees_band")
        s["r_at_bound"] = [sum(r["r_at_bound"][i] for r in rows) for i in (0, 1)]
        summary[name] = s
    ref = summary.get("nrmse")
    for s in summary.values():
        for k in ("rmse", "nees", "cal_rmse"):
            s[f"{k}_ratio"] = s[k] / ref[k] if ref and ref[k] else math.nan
    return summary


def table(summary: dict[str, dict[str, Any]]) -> list[str]:
    """The summary as a Markdown table (percentages for coverage)."""

    def pct(v: float) -> str:
        return "–" if not math.isfinite(v) else f"{100 * v:.0f} %"

    lines = [
        "| cost | β RMSE [°] (×nrmse) | ±1σ | ±1.96σ | β NEES (×nrmse) | NIS | NIS in band "
        "| cal c | cal β RMSE [°] | cal ±1σ | cal ±1.96σ | cal NEES | cal NIS/m "
        "| β RMSE range over seeds [°] | R at a bound |",
        "| --- " * 16 + "|",
    ]
    for name, s in summary.items():
        lines.append(
            f"| {name} | {s['rmse']:.4f} ({s['rmse_ratio']:.3f}) | {pct(s['cov68'])} | "
            f"{pct(s['cov95'])} | {s['nees']:.3g} ({s['nees_ratio']:.3g}) | {s['nis']:.3g} | "
            f"{pct(s['nis_ok'])} | {s['cal_factor']:.3g} | {s['cal_rmse']:.4f} | "
            f"{pct(s['cal_cov68'])} | {pct(s['cal_cov95'])} | {s['cal_nees']:.3g} | "
            f"{s['cal_nis_m']:.3g} | {s['rmse_range'][0]:.4f}–{s['rmse_range'][1]:.4f} | "
            f"{s['r_at_bound'][0]}/{s['r_at_bound'][1]} |"
        )
    return lines


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--datasets", nargs="+", default=["bundled"], help="dataset directories, or 'bundled'"
    )
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--seeds", type=int, default=3, help="seeds 0 … N−1 (default 3)")
    ap.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS, choices=list(CONFIGS))
    ap.add_argument(
        "--criterion", help="the calibration's criterion (default: tune's; kftune tune --help)"
    )
    ap.add_argument(
        "--points",
        metavar="OUT",
        help="take the tuned points from an earlier run's output (its last line) instead of "
        "tuning: the calibration and the figures again, e.g. with another --criterion",
    )
    args = ap.parse_args(argv)
    stored: dict[tuple[str, str, int], dict[str, float]] = {}
    if args.points:
        with open(args.points, encoding="utf-8") as f:
            earlier = json.loads(f.read().strip().splitlines()[-1])
        for ds_name, d in earlier["datasets"].items():
            for r in d["runs"]:
                stored[(ds_name, r["config"], r["seed"])] = r["params"]

    results: dict[str, Any] = {}
    for name in args.datasets:
        ds = open_dataset(None if name == "bundled" else name)
        runs: list[dict[str, Any]] = []
        for config in args.configs:
            for seed in range(1 if config == "manual" else args.seeds):
                point = stored.get((name, config, seed))
                if args.points and point is None:
                    continue
                r = run_config(ds, config, args.budget, seed, args.criterion, point)
                runs.append(r)
                print(
                    f"{name} {config:<13} seed {seed}: β RMSE {r['rmse']:.4f}°  "
                    f"±1σ {100 * r['cov68']:.0f} %  ±1.96σ {100 * r['cov95']:.0f} %  "
                    f"NEES {r['nees']:.3g}  NIS {r['nis']:.3g}  | cal c {r['cal_factor']:.3g} "
                    f"RMSE {r['cal_rmse']:.4f}° ±1.96σ {100 * r['cal_cov95']:.0f} % "
                    f"NEES {r['cal_nees']:.3g}  ({r['wall_s']:.1f} s)  "
                    + " ".join(f"{k}={v:.3g}" for k, v in r["params"].items()),
                    flush=True,
                )
        summary = summarise(runs, args.configs)
        print(f"\n{name}: test manoeuvres, medians over {args.seeds} seeds")
        print("\n".join(table(summary)), "\n", flush=True)
        results[name] = {"summary": summary, "runs": runs}
    out = {
        "benchmark": "honest_cost",
        "date": dt.date.today().isoformat(),
        "kftune_version": kftune.__version__,
        "machine": f"{platform.machine()}, Python {platform.python_version()}",
        "method": "trbo",
        "budget": args.budget,
        "seeds": list(range(args.seeds)),
        "datasets": results,
    }
    print(json.dumps(out, default=lambda v: None))
    return out


if __name__ == "__main__":
    main()
