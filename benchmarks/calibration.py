"""Does one covariance scale c, fitted on the training manoeuvres after tuning, make the
tuned filter's β σ honest on the test manoeuvres without costing accuracy?

Per dataset (the bundled one, ``../shared/data/revs-250lm`` where it exists, and any
dataset directory given, e.g. a fresh noise draw of ``kftune dataset generate --seed N``)
and seed, TR-BO at ``--budget`` evaluations on the training manoeuvres of the paper's cost
(``--setting paper``, the default) or of the CRPS of β with Q and R's diagonal tuned
(``--setting crps-rdiag``). Then, side by side in one run, the tuned filter on
the test manoeuvres

* uncalibrated (c = 1, what ``kftune tune`` wrote before calibration);
* calibrated by each criterion of :data:`kftune.tuning.calibrate.CRITERIA` (``nees``:
  mean NEES of β = 1, the Gaussian likelihood's maximum; ``coverage95``: ±1.96σ covers
  95 %; ``median``: the median NEES at χ²₁'s; ``reliability``: the reliability curve over
  the levels 0.50–0.99 nearest its diagonal; ``minimax``: the worse of the 68 %/95 %
  misses least; ``crps``: the mean CRPS least), c fitted on the training manoeuvres
  (:func:`kftune.tuning.calibrate.calibrate`): the covariances reported c times larger
  (what kftune does), and with ``--rerun``, tried and not kept (``-rerun``), the UKF rerun
  with c·Q, c·R and c·P0, which moves its estimate;

each scored as ``kftune evaluate --params`` scores it: mean test β RMSE [deg]
(:func:`kftune.tuning.problem.assess`), β coverage of ±1σ and ±1.96σ pooled over the test
samples, mean β NEES, and the count of test manoeuvres whose mean NIS lies in its 95 % χ²
band (:func:`kftune.tuning.deploy.consistency_docs`). And from the fit: c, the shift of the
training β estimate (RMS, and relative to its RMSE), filter runs taken, and whether the
fit says that one scale cannot serve every manoeuvre.

Targets (issue "honest uncertainty", medians over the seeds): test β RMSE within 3 % of the
uncalibrated filter's; ±1σ covering 60–76 %, ±1.96σ 90–98 %; NIS in its band on at least
half of the test manoeuvres. The summary counts, per criterion, the (dataset, level) pairs
whose median test coverage lies inside its target band, and the same over single seeds.

Usage::

    nice -n 10 .venv/bin/python benchmarks/calibration.py
    nice -n 10 .venv/bin/python benchmarks/calibration.py --datasets default /tmp/fresh7 \
        --seeds 3 --budget 100 [--criteria nees median] [--rerun]

Prints a table and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

import kftune
from kftune.data import open_dataset
from kftune.experiment import tune
from kftune.filters import UKF
from kftune.models import SINGLE_TRACK
from kftune.models.sideslip import single_track_prior
from kftune.tuning.calibrate import CRITERIA, RunErrors, calibrate, problem_runs
from kftune.tuning.cost import CostSpec
from kftune.tuning.deploy import consistency_docs
from kftune.tuning.kpi import average_kpis
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem, assess
from kftune.tuning.runs import default_r0, filter_spec

REVS = Path(__file__).resolve().parents[2] / "shared" / "data" / "revs-250lm"
#: What is tuned (``--setting``): cost and NoiseParameterization options.
SETTINGS: dict[str, tuple[CostSpec, dict[str, Any]]] = {
    "paper": (CostSpec(), {}),
    "crps-rdiag": (CostSpec(kind="crps"), {"tune_r": "diag"}),
    # kftune tune's recommended setting: the NRMSE normalised over the dataset, R's diagonal
    "default": (CostSpec(normalise="dataset"), {"tune_r": "diag"}),
}
#: The target bands of the test coverage of ±1σ and ±1.96σ (issue "honest uncertainty").
TARGETS = {"cov68": (0.60, 0.76), "cov95": (0.90, 0.98)}


def variants(criteria: list[str], rerun: bool) -> list[str]:
    """The calibrated variants: each criterion with the covariances scaled after the run
    (kept), and with ``rerun`` also the UKF rerun with c·Q, c·R and c·P0 (tried)."""
    return [*criteria, *(f"{c}-rerun" for c in criteria if rerun)]


def inside(cov: float | None, key: str) -> bool:
    """Whether a test coverage lies in its target band (:data:`TARGETS`)."""
    lo, hi = TARGETS[key]
    return cov is not None and lo <= cov <= hi


class Rerun(TuningProblem):
    """The tuning problem whose calibrated runs, with :attr:`rerun`, rerun the UKF with
    c·Q, c·R and c·P0 (P0 and x0 from the default prior with the unscaled R) instead of
    scaling its covariances afterwards: the variant tried and not kept."""

    rerun = False

    def run(self, x: Any, manoeuvre: Any) -> Any:
        c = self.cov_scale
        if not self.rerun or c == 1.0:
            return super().run(x, manoeuvre)
        q, r, settings = self.decode(x)
        m = manoeuvre
        x0, p0 = single_track_prior(m.z[0], r, np.zeros(0))
        return UKF(settings).run(
            SINGLE_TRACK, m.u, m.z, m.dt, c * q, c * r, params=self.vehicle, x0=x0, P0=c * p0
        )


def _z(runs: list[RunErrors]) -> np.ndarray:
    """|e/σ| of β pooled over the runs (after the burn-in)."""
    return np.abs(np.concatenate([r.normalised()["beta"] for r in runs]))


def _coverage(z: np.ndarray, c: float) -> tuple[float, float]:
    """Shares of |e/σ| inside ±1·√c and ±1.96·√c: the coverages after a scale c."""
    s = math.sqrt(c)
    return float(np.mean(z <= s)), float(np.mean(z <= 1.959963984540054 * s))


def target_range(z: np.ndarray) -> tuple[float, float]:
    """The scales c whose test coverages lie inside both targets (:data:`TARGETS`): from
    the larger of the c that puts ±1σ at 60 % and ±1.96σ at 90 % to the smaller of those
    that put them at 76 % and 98 %. An empty range (lo > hi): no single scale can."""
    (a68, b68), (a95, b95) = TARGETS["cov68"], TARGETS["cov95"]
    z95 = 1.959963984540054
    lo = max(np.quantile(z, a68) ** 2, (np.quantile(z, a95) / z95) ** 2)
    hi = min(np.quantile(z, b68) ** 2, (np.quantile(z, b95) / z95) ** 2)
    return float(lo), float(hi)


def _crps_weighted(runs: list[RunErrors], per_run: list[float]) -> float:
    """c minimising Σ_k w_k CRPS(N(0, c σ_k²); e_k), w_k = ``per_run`` of its run."""
    from scipy.optimize import brentq

    e = np.concatenate([r.err["beta"] for r in runs])
    sd = np.concatenate([r.std["beta"] for r in runs])
    w = np.concatenate([np.full(r.err["beta"].size, v) for r, v in zip(runs, per_run)])
    z = e / sd

    def slope(log_s: float) -> float:
        v = z * math.exp(-log_s)
        return float(
            np.dot(
                w * sd, 2 * np.exp(-0.5 * v * v) / math.sqrt(2 * math.pi) - 1 / math.sqrt(math.pi)
            )
        )

    return math.exp(2 * brentq(slope, -12.0, 12.0))


def _two_parameter(runs: list[RunErrors], ay: list[np.ndarray], kind: str) -> Any:
    """σ' = g(σ) fitted by the mean CRPS on ``runs`` (Nelder–Mead from the one-scale
    fit): ``power`` a·σ^b, ``floor`` √(c σ² + f²), ``ay`` √(c σ² + (k·|ay|/g)²) — a
    model error growing with the lateral acceleration. Returns σ, |ay| → σ'."""
    from scipy.optimize import minimize
    from scipy.stats import norm

    e = np.concatenate([r.err["beta"] for r in runs])
    sd = np.concatenate([r.std["beta"] for r in runs])
    a = np.abs(np.concatenate(ay))
    ref = float(np.median(sd))

    def sigma(p: np.ndarray, s: np.ndarray, acc: np.ndarray) -> np.ndarray:
        if kind == "power":
            return math.exp(p[0]) * ref * (s / ref) ** p[1]
        extra = ref * (acc / 9.81 if kind == "ay" else 1.0)
        return np.sqrt(math.exp(2 * p[0]) * s**2 + (math.exp(p[1]) * extra) ** 2)

    def crps(p: np.ndarray) -> float:
        s = sigma(p, sd, a)
        w = e / s
        return float(
            np.mean(s * (w * (2 * norm.cdf(w) - 1) + 2 * norm.pdf(w) - 1 / math.sqrt(math.pi)))
        )

    c0 = 0.5 * math.log(_crps_weighted(runs, [1.0] * len(runs)))
    starts = [[c0, 1.0]] if kind == "power" else [[c0, v] for v in (-6.0, -2.0, 0.0, 2.0)]
    best = min((minimize(crps, x, method="Nelder-Mead") for x in starts), key=lambda r: r.fun)
    return lambda s, acc: sigma(best.x, s, acc)


def tried_variants(
    train: list[RunErrors],
    test: list[RunErrors],
    ay_train: list[np.ndarray],
    ay_test: list[np.ndarray],
) -> dict[str, tuple[float, float]]:
    """Test coverages (±1σ, ±1.96σ) of the calibrations tried and not kept, each fitted on
    the training runs: one scale by the CRPS with every manoeuvre weighted alike
    (``crps-manoeuvres``), one scale by the CRPS of leave-one-manoeuvre-out errors
    (``crps-lomo``: each manoeuvre's errors over the scale fitted on the others, then that
    pooled scale's factor times the full fit's), and the two-parameter σ' of
    :func:`_two_parameter` (``power``, ``floor``, ``ay``)."""
    z_test = _z(test)
    out = {
        "crps-manoeuvres": _coverage(
            z_test, _crps_weighted(train, [1.0 / r.err["beta"].size for r in train])
        )
    }
    full = _crps_weighted(train, [1.0] * len(train))
    held = []
    for k, r in enumerate(train):
        c_k = _crps_weighted(train[:k] + train[k + 1 :], [1.0] * (len(train) - 1))
        held.append(RunErrors(r.name, r.err, {"beta": r.std["beta"] * math.sqrt(c_k)}, r.estimate))
    out["crps-lomo"] = _coverage(z_test, full * _crps_weighted(held, [1.0] * len(held)))
    for kind in ("power", "floor", "ay"):
        g = _two_parameter(train, ay_train, kind)
        z = np.abs(
            np.concatenate(
                [r.err["beta"] / g(r.std["beta"], np.abs(a)) for r, a in zip(test, ay_test)]
            )
        )
        out[kind] = (float(np.mean(z <= 1.0)), float(np.mean(z <= 1.959963984540054)))
    return out


def _ay(problem: TuningProblem, manoeuvres: list[Any]) -> list[np.ndarray]:
    """Each manoeuvre's measured ay [m/s²] over the samples the calibration counts."""
    from kftune.tuning.runs import first_scored

    i = list(problem.model.measurement_names).index("ay")
    return [m.z[first_scored(m, problem.burn_in) :, i] for m in manoeuvres]


def calibrated(problem: Any, x: Any, test: Any, criterion: str) -> dict[str, Any]:
    """The test scores of the filter at ``x`` calibrated by ``criterion`` on the problem's
    training manoeuvres (:func:`scored` with its c), with c, the fit's cost in filter runs
    and seconds, the training estimate's shift and coverage after, and the fit's warning;
    the problem's covariance scale is 1 again afterwards."""
    t0 = time.perf_counter()
    cal = calibrate(problem, x, criterion=criterion)
    t_cal = time.perf_counter() - t0
    problem.cov_scale = cal.factor
    try:
        got = scored(problem, x, test)
    finally:
        problem.cov_scale = 1.0
    rec = cal.as_dict()
    got.update(
        factor=cal.factor,
        n_runs=cal.n_runs,
        calibrate_s=t_cal,
        train_shift_deg=rec["estimate_shift"]["rms"],
        train_shift_rel=rec["estimate_shift"]["relative_to_rmse"],
        train_cov68=rec["train"]["after"]["coverage68"],
        train_cov95=rec["train"]["after"]["coverage95"],
        warning=cal.warning,
        per_manoeuvre=rec["per_manoeuvre"],
    )
    return got


def scored(problem: TuningProblem, x: np.ndarray, test: list[Any]) -> dict[str, Any]:
    """The filter at ``x`` with ``problem.cov_scale`` on the test manoeuvres: mean β RMSE
    [deg], pooled coverage and NEES of β, and the NIS-in-band count."""
    metrics, runs = assess(problem, x, test)
    each, pooled = consistency_docs(problem, test, runs)
    avg = average_kpis(metrics.values())
    beta = (pooled or {}).get("channels", {}).get("beta") or {}
    nis_in = sum(1 for d in each.values() if d is not None and d["nis"]["inside"])
    return {
        "rmse": float(avg["rmse"]),
        "cov68": beta.get("cov68"),
        "cov95": beta.get("cov95"),
        "nees": (beta.get("nees") or {}).get("mean"),
        "nis_inside": nis_in,
        "n_test": len(test),
        "nis_mean": [None if d is None else d["nis"]["mean"] for d in each.values()],
    }


def run_dataset(
    name: str,
    seeds: int,
    budget: int,
    criteria: list[str],
    rerun: bool,
    setting: str = "paper",
    tried: bool = False,
    resplit: bool = False,
) -> dict[str, Any]:
    """Every seed's tuned, and calibrated, filter on one dataset; with ``resplit`` each seed
    draws its own split (as many training manoeuvres as the dataset's, drawn at random
    among those with a β reference by the seed; the others are the test manoeuvres)."""
    ds = open_dataset(name)
    fs = filter_spec("single-track", "ukf", ds.vehicle)
    train, test = list(ds.train), [m for m in ds.test if m.has("beta_ref")]
    pool = [m for m in ds.manoeuvres if m.has("beta_ref")]
    rows = []
    for seed in range(seeds):
        if resplit:
            drawn = set(np.random.default_rng(seed).choice(len(pool), len(ds.train), replace=False))
            train = [m for i, m in enumerate(pool) if i in drawn]
            test = [m for i, m in enumerate(pool) if i not in drawn]
        cost, options = SETTINGS[setting]
        problem = Rerun(
            train,
            ds.vehicle,
            default_r0(fs.model, ds),
            cost=cost,
            parameterization=NoiseParameterization(**options),
        )
        t0 = time.perf_counter()
        result = tune(problem, "trbo", budget=budget, seed=seed, progress=False)
        t_tune = time.perf_counter() - t0
        row: dict[str, Any] = {"seed": seed, "tune_s": t_tune, "cost": result.fun}
        row["uncalibrated"] = scored(problem, result.x, test)
        train_runs = problem_runs(problem, result.x, problem.manoeuvres)(1.0)
        test_runs = problem_runs(problem, result.x, test)(1.0)
        row["target_range"] = target_range(_z(test_runs))
        for part, runs_, ms in (
            ("train", train_runs, problem.manoeuvres),
            ("test", test_runs, test),
        ):
            e = np.concatenate([r.err["beta"] for r in runs_])
            row[f"{part}_err_rms_deg"] = float(np.degrees(np.sqrt(np.mean(e * e))))
            row[f"{part}_mean_abs_ay"] = float(np.mean(np.abs(np.concatenate(_ay(problem, ms)))))
        for crit in criteria:
            row[crit] = calibrated(problem, result.x, test, crit)
            if rerun:  # tried: the UKF rerun with c·Q, c·R and c·P0
                problem.rerun = True
                row[f"{crit}-rerun"] = calibrated(problem, result.x, test, crit)
                problem.rerun = False
        if tried:
            row["tried"] = tried_variants(
                train_runs, test_runs, _ay(problem, problem.manoeuvres), _ay(problem, test)
            )
        rows.append(row)
        u = row["uncalibrated"]
        print(
            f"{ds.name} seed {seed}: J {result.fun:.5f}; uncalibrated β RMSE {u['rmse']:.4f}°, "
            f"cov68 {u['cov68']:.3f} cov95 {u['cov95']:.3f} NEES {u['nees']:.3g}, NIS in band "
            f"{u['nis_inside']}/{u['n_test']}",
            flush=True,
        )
        for crit in variants(criteria, rerun):
            g = row[crit]
            print(
                f"  {crit:11s}: c {g['factor']:.4g} ({g['n_runs']} runs, "
                f"{g['calibrate_s']:.2f} s); β RMSE {g['rmse']:.4f}° "
                f"(×{g['rmse'] / u['rmse']:.4f}), cov68 {g['cov68']:.3f} cov95 "
                f"{g['cov95']:.3f} NEES {g['nees']:.3g}, NIS in band "
                f"{g['nis_inside']}/{g['n_test']}; train shift {g['train_shift_deg']:.3g}° "
                f"({100 * g['train_shift_rel']:.2g} % of RMSE); train cov68 "
                f"{g['train_cov68']:.3f} cov95 {g['train_cov95']:.3f}"
                + ("; WARNS" if g["warning"] else ""),
                flush=True,
            )
        lo, hi = row["target_range"]
        print(
            f"  β error RMS train {row['train_err_rms_deg']:.3f}° test "
            f"{row['test_err_rms_deg']:.3f}°; mean |ay| train {row['train_mean_abs_ay']:.2f} "
            f"test {row['test_mean_abs_ay']:.2f} m/s²",
            flush=True,
        )
        print(
            f"  scales meeting both test targets: c in [{lo:.4g}, {hi:.4g}]"
            + (" (none: no single scale can)" if lo > hi else ""),
            flush=True,
        )
        for name_, (c68, c95) in row.get("tried", {}).items():
            print(f"  tried {name_:15s}: cov68 {c68:.3f} cov95 {c95:.3f}", flush=True)
    return {"dataset": Path(name).name, "n_test": len(test), "seeds": rows}


def shift_table(results: list[dict[str, Any]], criteria: list[str]) -> dict[str, Any]:
    """Per dataset and criterion, median over seeds of the training and the test coverages
    after the fit, and of the fitted c relative to the target range's ends (c/lo ≥ 1 and
    c/hi ≤ 1 when inside; a seed whose range is empty, lo > hi, counts in both medians);
    printed, and returned for the JSON."""
    out: dict[str, Any] = {}
    print("\ndataset | criterion | train cov68 / cov95 | test cov68 / cov95 | c / lo | c / hi")
    for res in results:
        for crit in criteria:
            rows = res["seeds"]
            med = {
                k: statistics.median(r[crit][k] for r in rows)
                for k in ("train_cov68", "train_cov95", "cov68", "cov95")
            }
            med["c_over_lo"] = statistics.median(
                r[crit]["factor"] / r["target_range"][0] for r in rows
            )
            med["c_over_hi"] = statistics.median(
                r[crit]["factor"] / r["target_range"][1] for r in rows
            )
            out.setdefault(res["dataset"], {})[crit] = med
            print(
                f"{res['dataset']} | {crit} | {100 * med['train_cov68']:.1f} / "
                f"{100 * med['train_cov95']:.1f} | "
                f"{100 * med['cov68']:.1f} / {100 * med['cov95']:.1f} | {med['c_over_lo']:.3g} | "
                f"{med['c_over_hi']:.3g}"
            )
        tried = [r["tried"] for r in res["seeds"] if "tried" in r]
        for name in tried[0] if tried else ():
            c68 = statistics.median(t[name][0] for t in tried)
            c95 = statistics.median(t[name][1] for t in tried)
            out[res["dataset"]][f"tried:{name}"] = {"cov68": c68, "cov95": c95}
            print(
                f"{res['dataset']} | tried {name} | – | {100 * c68:.1f} / {100 * c95:.1f} | – | –"
            )
    return out


def medians(result: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """Medians over seeds of each variant's figures, the RMSE ratio to uncalibrated, and
    how many seeds' test coverages of ±1σ and ±1.96σ lie inside their targets."""
    out: dict[str, Any] = {}
    rows = result["seeds"]
    for variant in ("uncalibrated", *names):
        v = [r[variant] for r in rows]
        med = {
            k: statistics.median(x[k] for x in v)
            for k in ("rmse", "cov68", "cov95", "nees", "nis_inside")
        }
        if variant != "uncalibrated":
            med["rmse_ratio"] = statistics.median(
                x["rmse"] / r["uncalibrated"]["rmse"] for x, r in zip(v, rows)
            )
            for k in ("factor", "train_shift_deg", "train_shift_rel", "train_cov68", "train_cov95"):
                med[k] = statistics.median(x[k] for x in v)
            med["warned"] = sum(1 for x in v if x["warning"])
        for key in TARGETS:
            med[f"{key}_seeds_inside"] = sum(1 for x in v if inside(x[key], key))
        out[variant] = med
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", help="datasets (default: bundled, revs-250lm)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument(
        "--criteria", nargs="+", choices=CRITERIA, default=list(CRITERIA), help="c fitted by"
    )
    ap.add_argument(
        "--setting",
        choices=list(SETTINGS),
        default="paper",
        help="what is tuned: the paper's NRMSE of β with Q (default), the CRPS of β with "
        "Q and R's diagonal, or kftune tune's default (the NRMSE normalised over the dataset "
        "with R's diagonal)",
    )
    ap.add_argument(
        "--rerun", action="store_true", help="also the UKF rerun with c·Q, c·R, c·P0 (tried)"
    )
    ap.add_argument(
        "--resplit",
        action="store_true",
        help="each seed draws its own training and test manoeuvres (as many training ones as "
        "the dataset's split): the coverage on manoeuvres not seen, whatever the split",
    )
    ap.add_argument(
        "--tried",
        action="store_true",
        help="also the calibrations tried and not kept (manoeuvre-weighted and leave-one-"
        "manoeuvre-out CRPS scales, σ power law, σ floor, an ay-proportional model error)",
    )
    args = ap.parse_args()
    names = args.datasets or ["default", *([str(REVS)] if REVS.is_dir() else [])]
    shown = variants(args.criteria, args.rerun)
    t0 = time.perf_counter()
    results = [
        run_dataset(
            n,
            args.seeds,
            args.budget,
            args.criteria,
            args.rerun,
            args.setting,
            args.tried,
            args.resplit,
        )
        for n in names
    ]
    shifts = shift_table(results, args.criteria)
    print()
    print(
        "dataset | variant | c | test β RMSE [°] | ratio | cov68 | cov95 | NEES | NIS in band "
        "| train shift [°] (% RMSE) | warned"
    )
    summary = []
    for res in results:
        med = medians(res, shown)
        summary.append({"dataset": res["dataset"], "n_test": res["n_test"], "median": med})
        for variant, m in med.items():
            print(
                f"{res['dataset']} | {variant} | {m.get('factor', 1.0):.4g} | {m['rmse']:.4f} | "
                f"{m.get('rmse_ratio', 1.0):.4f} | {m['cov68']:.3f} | {m['cov95']:.3f} | "
                f"{m['nees']:.3g} | {m['nis_inside']}/{res['n_test']} | "
                + (
                    f"{m['train_shift_deg']:.3g} ({100 * m['train_shift_rel']:.2g} %) | "
                    f"{m['warned']}/{args.seeds}"
                    if "factor" in m
                    else "– | –"
                )
            )
    print()
    print(
        "variant | (dataset, level) pairs inside the targets, medians over seeds | "
        "(dataset, level, seed) inside | median RMSE ratio, worst dataset"
    )
    pairs: dict[str, Any] = {}
    for variant in ("uncalibrated", *shown):
        meds = [s["median"][variant] for s in summary]
        n_med = sum(1 for m in meds for key in TARGETS if inside(m[key], key))
        n_seed = sum(m[f"{key}_seeds_inside"] for m in meds for key in TARGETS)
        worst = max(m.get("rmse_ratio", 1.0) for m in meds)
        pairs[variant] = {
            "median_inside": n_med,
            "of": len(TARGETS) * len(meds),
            "seeds_inside": n_seed,
            "seeds_of": len(TARGETS) * len(meds) * args.seeds,
            "worst_rmse_ratio": worst,
        }
        print(
            f"{variant} | {n_med}/{len(TARGETS) * len(meds)} | "
            f"{n_seed}/{len(TARGETS) * len(meds) * args.seeds} | {worst:.4f}"
        )
    print(
        json.dumps(
            {
                "benchmark": "calibration",
                "criteria": args.criteria,
                "setting": args.setting,
                "resplit": args.resplit,
                "targets": TARGETS,
                "inside_targets": pairs,
                "train_test_shift": shifts,
                "seeds": args.seeds,
                "budget": args.budget,
                "python": platform.python_version(),
                "numpy": np.__version__,
                "kftune": kftune.__version__,
                "wall_s": time.perf_counter() - t0,
                "summary": summary,
                "runs": results,
            },
            allow_nan=False,
            default=lambda v: None if isinstance(v, float) and not math.isfinite(v) else v,
        )
    )


if __name__ == "__main__":
    main()
