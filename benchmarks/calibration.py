"""Does one covariance scale c, fitted on the training manoeuvres after tuning, make the
tuned filter's β σ honest on the test manoeuvres without costing accuracy?

Per dataset (the bundled one, ``../shared/data/revs-250lm`` where it exists, and any
dataset directory given, e.g. a fresh noise draw of ``kftune dataset generate --seed N``)
and seed, ``kftune tune``'s default setting: TR-BO at ``--budget`` evaluations of the
paper's cost on the training manoeuvres. Then, side by side in one run, the tuned filter on
the test manoeuvres

* uncalibrated (c = 1, what ``kftune tune`` wrote before calibration);
* calibrated by each criterion of :data:`kftune.tuning.calibrate.CRITERIA` (``nees``:
  mean NEES of β = 1, the Gaussian likelihood's maximum; ``coverage95``: ±1.96σ covers
  95 %), c fitted on the training manoeuvres (:func:`kftune.tuning.calibrate.calibrate`):
  the covariances reported c times larger (what kftune does), and, tried and not kept
  (``-rerun``), the UKF rerun with c·Q, c·R and c·P0, which moves its estimate;

each scored as ``kftune evaluate --params`` scores it: mean test β RMSE [deg]
(:func:`kftune.tuning.problem.assess`), β coverage of ±1σ and ±1.96σ pooled over the test
samples, mean β NEES, and the count of test manoeuvres whose mean NIS lies in its 95 % χ²
band (:func:`kftune.tuning.deploy.consistency_docs`). And from the fit: c, the shift of the
training β estimate (RMS, and relative to its RMSE), filter runs taken, and whether the
fit says that one scale cannot serve every manoeuvre.

Targets (issue "honest uncertainty", medians over the seeds): test β RMSE within 3 % of the
uncalibrated filter's; ±1σ covering 60–76 %, ±1.96σ 90–98 %; NIS in its band on at least
half of the test manoeuvres.

Usage::

    nice -n 10 .venv/bin/python benchmarks/calibration.py
    nice -n 10 .venv/bin/python benchmarks/calibration.py --datasets default /tmp/fresh7 \
        --seeds 3 --budget 100

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
from kftune.filters import run_ukf
from kftune.models.sideslip import single_track_prior
from kftune.tuning.calibrate import CRITERIA, calibrate
from kftune.tuning.deploy import consistency_docs
from kftune.tuning.kpi import average_kpis
from kftune.tuning.problem import TuningProblem, assess, default_r0, filter_spec

#: The calibrated variants: each criterion with the covariances scaled after the run (kept),
#: and with the UKF rerun with c·Q, c·R and c·P0 (tried).
VARIANTS = (*CRITERIA, *(f"{c}-rerun" for c in CRITERIA))
REVS = Path(__file__).resolve().parents[2] / "shared" / "data" / "revs-250lm"


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
        return run_ukf(
            m.u, m.z, m.dt, self.vehicle, c * q, c * r, x0=x0, P0=c * p0, settings=settings
        )


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


def run_dataset(name: str, seeds: int, budget: int) -> dict[str, Any]:
    """Every seed's tuned, and calibrated, filter on one dataset."""
    ds = open_dataset(name)
    fs = filter_spec("single-track", "ukf", ds.vehicle)
    test = [m for m in ds.test if m.has("beta_ref")]
    rows = []
    for seed in range(seeds):
        problem = Rerun(ds.train, ds.vehicle, default_r0(fs.model, ds))
        t0 = time.perf_counter()
        result = tune(problem, "trbo", budget=budget, seed=seed, progress=False)
        t_tune = time.perf_counter() - t0
        row: dict[str, Any] = {"seed": seed, "tune_s": t_tune, "cost": result.fun}
        row["uncalibrated"] = scored(problem, result.x, test)
        for crit in CRITERIA:
            t0 = time.perf_counter()
            cal = calibrate(problem, result.x, criterion=crit)
            t_cal = time.perf_counter() - t0
            problem.cov_scale = cal.factor
            got = scored(problem, result.x, test)
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
            row[crit] = got
            problem.rerun = True  # tried: the UKF rerun with c·Q, c·R and c·P0
            t0 = time.perf_counter()
            cal = calibrate(problem, result.x, criterion=crit)
            t_cal = time.perf_counter() - t0
            problem.cov_scale = cal.factor
            got = scored(problem, result.x, test)
            problem.cov_scale, problem.rerun = 1.0, False
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
            row[f"{crit}-rerun"] = got
        rows.append(row)
        u = row["uncalibrated"]
        print(
            f"{ds.name} seed {seed}: J {result.fun:.5f}; uncalibrated β RMSE {u['rmse']:.4f}°, "
            f"cov68 {u['cov68']:.3f} cov95 {u['cov95']:.3f} NEES {u['nees']:.3g}, NIS in band "
            f"{u['nis_inside']}/{u['n_test']}",
            flush=True,
        )
        for crit in VARIANTS:
            g = row[crit]
            print(
                f"  {crit:10s}: c {g['factor']:.4g} ({g['n_runs']} runs, "
                f"{g['calibrate_s']:.2f} s); β RMSE {g['rmse']:.4f}° "
                f"(×{g['rmse'] / u['rmse']:.4f}), cov68 {g['cov68']:.3f} cov95 "
                f"{g['cov95']:.3f} NEES {g['nees']:.3g}, NIS in band "
                f"{g['nis_inside']}/{g['n_test']}; train shift {g['train_shift_deg']:.3g}° "
                f"({100 * g['train_shift_rel']:.2g} % of RMSE)"
                + ("; WARNS" if g["warning"] else ""),
                flush=True,
            )
    return {"dataset": Path(name).name, "n_test": len(test), "seeds": rows}


def medians(result: dict[str, Any]) -> dict[str, Any]:
    """Medians over seeds of each variant's figures, and the RMSE ratio to uncalibrated."""
    out: dict[str, Any] = {}
    rows = result["seeds"]
    for variant in ("uncalibrated", *VARIANTS):
        v = [r[variant] for r in rows]
        med = {
            k: statistics.median(x[k] for x in v)
            for k in ("rmse", "cov68", "cov95", "nees", "nis_inside")
        }
        if variant != "uncalibrated":
            med["rmse_ratio"] = statistics.median(
                x["rmse"] / r["uncalibrated"]["rmse"] for x, r in zip(v, rows)
            )
            for k in ("factor", "train_shift_deg", "train_shift_rel"):
                med[k] = statistics.median(x[k] for x in v)
            med["warned"] = sum(1 for x in v if x["warning"])
        out[variant] = med
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", help="datasets (default: bundled, revs-250lm)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--budget", type=int, default=100)
    args = ap.parse_args()
    names = args.datasets or ["default", *([str(REVS)] if REVS.is_dir() else [])]
    t0 = time.perf_counter()
    results = [run_dataset(n, args.seeds, args.budget) for n in names]
    print()
    print(
        "dataset | variant | c | test β RMSE [°] | ratio | cov68 | cov95 | NEES | NIS in band "
        "| train shift [°] (% RMSE) | warned"
    )
    summary = []
    for res in results:
        med = medians(res)
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
    print(
        json.dumps(
            {
                "benchmark": "calibration",
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
