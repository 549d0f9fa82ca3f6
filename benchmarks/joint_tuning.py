"""Tuning the model's parameters with the noise: how close each optimiser gets to the best
cost at d = 5, 6 and 9, and whether the jointly tuned filter repairs a wrong vehicle on the
test manoeuvres.

A user with a new car guesses its tyres. This benchmark gives the filter a vehicle scaled
from the dataset's own (``--wrong``, default C_af ×0.7, C_ar ×1.4, μ ×0.8: the bundled
data are simulated with the unscaled vehicle) and tunes, on the training manoeuvres with
the paper's cost (Eq. 14–15, ``--normalise`` as ``kftune tune``):

* ``noise-true``:  Q only (d = 3) on the dataset's vehicle — the filter to come near;
* ``noise``:       Q only (d = 3) on the wrong vehicle — what tuning Q alone gives;
* ``d5``:          Q + C_af + C_ar (d = 5) on the wrong vehicle, each stiffness in
  [20000, 400000] N/rad (log10, started at the wrong value);
* ``d6``:          ``d5`` + μ in [0.4, 1.6] (log10);
* ``d9``:          ``d6`` + R's diagonal (``tune_r="diag"``, three factors on R₀).

With ``--wrong`` and no factors the filter gets the recorded vehicle (``noise`` is then
``noise-true``; on a recording such as ``../shared/data/revs-250lm`` this asks whether
joint tuning of parameters its authors identified costs anything).

Methods: any label of ``kftune.optim.METHODS`` (default: TR-BO, Optuna TPE, CMA-ES, random,
GA), and ``trbo-faces``: TR-BO whose design probes the faces of every log10 box (its
``"auto"`` design before a narrow box got DIRECT's thirds), for the side-by-side; and
``trbo-seeded``: TR-BO whose joint search starts (``x0``) from the optimum of a noise-only
TR-BO run at the start model (100 evaluations more; see :func:`run_unit`).

Budgets per configuration (``--budgets`` gives one list for all): d ≤ 6 at 50 and 100,
d = 9 at 75 and 150. A budget-independent method (TR-BO, TPE, CMA-ES, random) runs
once at the largest budget and is read as prefixes; GA runs once per budget.

J* of a configuration: the lowest training cost any run of this invocation found in it
(stated in the output with the run that found it); gap = 100·(J − J*)/J*.

Per configuration, method and budget: median and worst gap over seeds, median test β RMSE
[deg] of the filter at the best point (KPI average over the test manoeuvres, as ``kftune
compare``), median tuned model parameters, whether J never rises with the budget on any
seed. Then the targets of the "tune model parameters" issue:

1. median gap at 100 at d = 5 within 1 %, at 150 at d = 9 within 2 % (TR-BO);
2. TR-BO's median J below every peer's at each budget (d = 5, 6, 9);
3. never worse with more budget (every seed);
4. joint (``d6``, TR-BO at 100) median test β RMSE within 5 % of ``noise-true``'s
   (TR-BO at 100), and how far below ``noise`` (the wrong vehicle, Q only) it is;
5. with ``--wrong`` empty (a recording): ``d5`` at most 1 % above ``noise``.

``--tune-splits N1 …`` measures ``kftune tune`` itself instead (:func:`run_tune_splits`):
its default cost, TR-BO at ``--tune-n``, noise-only on the dataset's vehicle beside the
joint tuning of the first ``--configs`` (d5 or d6) on the wrong vehicle with its first
stage forced to N1 evaluations (0: one unseeded joint search); the held-out β RMSE is
tune's own (``held_out`` of the tuned file, the test split).

Usage::

    .venv/bin/python benchmarks/joint_tuning.py --json-out /tmp/joint.json
    .venv/bin/python benchmarks/joint_tuning.py --configs noise-true noise d6 \\
        --methods trbo --seeds 3 --budgets 100
    .venv/bin/python benchmarks/joint_tuning.py --dataset ../shared/data/revs-250lm \\
        --wrong --configs noise d5 --methods trbo --seeds 3 --budgets 100
    .venv/bin/python benchmarks/joint_tuning.py --configs d6 --tune-splits 25 50 --seeds 3

Prints the tables and, as its last line, one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import itertools
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import kftune
from kftune.data import open_dataset
from kftune.errors import ConfigError, FilterDivergedError, KftuneError
from kftune.experiment import manual_point
from kftune.optim import METHODS, PeerUnavailableError
from kftune.tuning.cost import NORMALISATIONS, CostSpec
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem
from ukf_tuning import (  # benchmarks/ is the script's path
    _CONTEXT,
    LABELS,
    gap_pct,
    is_budget_independent,
    json_safe,
    monotonicity,
    num,
    read_at,
    test_beta_rmse,
    tuning_run,
)

#: The stiffness and friction boxes of the issue (natural units: N/rad, N/rad, -).
STIFFNESS_BOX = (20_000.0, 400_000.0)
MU_BOX = (0.4, 1.6)
#: configuration → (tuned model parameters, R tuning, filter on the dataset's own vehicle).
CONFIGS: dict[str, tuple[dict[str, tuple[float, float]], str, bool]] = {
    "noise-true": ({}, "none", True),
    "noise": ({}, "none", False),
    "d5": ({"C_af": STIFFNESS_BOX, "C_ar": STIFFNESS_BOX}, "none", False),
    "d6": ({"C_af": STIFFNESS_BOX, "C_ar": STIFFNESS_BOX, "mu": MU_BOX}, "none", False),
    "d9": ({"C_af": STIFFNESS_BOX, "C_ar": STIFFNESS_BOX, "mu": MU_BOX}, "diag", False),
}
DEFAULT_WRONG = ("C_af=0.7", "C_ar=1.4", "mu=0.8")
DEFAULT_METHODS = ("trbo", "optuna-tpe", "cma", "random", "ga")
#: TR-BO with the face centres of every log10 box in its design (its "auto" design before
#: narrow log10 boxes got DIRECT's thirds): the side-by-side of that change.
LABELS.setdefault("trbo-faces", ("trbo", {"init_design": "axial"}))
LABELS.setdefault("trbo-seeded", ("trbo", {}))  # its x0 is set per run (run_unit)
#: Evaluations of the noise-only TR-BO run that seeds ``trbo-seeded``.
SEED_BUDGET = 100
PEERS = ("optuna-tpe", "optuna-gp", "cma", "random", "ga")
#: Targets: median gap at (d, budget) [%].
GAP_TARGETS = (("d5", 100, 1.0), ("d9", 150, 2.0))
#: Joint tuning within this factor of the noise-only filter on the true vehicle (test β).
JOINT_VS_TRUE = 1.05
#: On a recording: joint tuning at most this factor of noise-only (test β).
JOINT_VS_NOISE = 1.01

_PROBLEMS: dict[tuple, tuple[Any, TuningProblem]] = {}


def parse_scales(items: Sequence[str]) -> dict[str, float]:
    """``["C_af=0.7", …]`` → {"C_af": 0.7, …} (positive factors)."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            factor = float(value)
        except ValueError:
            factor = math.nan
        if not sep or not name or not math.isfinite(factor) or factor <= 0:
            raise argparse.ArgumentTypeError(
                f"--wrong: expected NAME=FACTOR with a positive factor, got {item!r}"
            )
        out[name] = factor
    return out


def build(dataset: str | None, wrong: dict[str, float], normalise: str, config: str) -> None:
    """Make ``config``'s problem the current one of ``ukf_tuning``'s helpers (cached)."""
    key = (dataset, tuple(sorted(wrong.items())), normalise, config)
    if key not in _PROBLEMS:
        ds = open_dataset(dataset)
        bounds, tune_r, true_vehicle = CONFIGS[config]
        vehicle = ds.vehicle
        if not true_vehicle and wrong:
            vehicle = vehicle.replace(**{n: f * getattr(vehicle, n) for n, f in wrong.items()})
        start = {n: float(getattr(vehicle, n)) for n in bounds}
        model = {"model_bounds": bounds, "model_start": start} if bounds else {}
        par = NoiseParameterization(tune_r=tune_r, **model)
        cost = CostSpec(normalise=normalise)  # type: ignore[arg-type]
        problem = TuningProblem(ds.train, vehicle, ds.r_default, cost=cost, parameterization=par)
        _PROBLEMS[key] = (ds, problem)
    ds, problem = _PROBLEMS[key]
    _CONTEXT.update(spec=key, dataset=ds, problem=problem)


def run_unit(
    dataset: str | None,
    wrong: dict[str, float],
    normalise: str,
    config: str,
    label: str,
    seed: int,
    budgets: list[int],
) -> dict[str, Any]:
    """Every budget of one (configuration, method, seed), as ``ukf_tuning.run_unit``.

    ``trbo-seeded``: first TR-BO tunes Q alone on the start model (the ``noise``
    configuration, :data:`SEED_BUDGET` evaluations, the same seed); its optimum, with the
    model parameters at their start values and R unscaled, is TR-BO's ``x0`` in the joint
    search — which then ends no worse than noise-only tuning, at twice the evaluations."""
    seeded_from = None
    if label == "trbo-seeded":
        build(dataset, wrong, normalise, "noise")
        noise = tuning_run("trbo", seed, SEED_BUDGET)
        i = int(np.argmin(noise["values"]))
        values = dict(zip(_CONTEXT["problem"].space.names, noise["x"][i], strict=True))
        build(dataset, wrong, normalise, config)
        par = _CONTEXT["problem"].parameterization
        values.update(par.model_start)
        values.update(dict.fromkeys(par.r_names, 1.0))
        x0 = [values[n] for n in _CONTEXT["problem"].space.names]
        LABELS["trbo-seeded"] = ("trbo", {"x0": x0})
        seeded_from = {"J": noise["values"][i], "x0": x0, "evaluations": SEED_BUDGET}
    build(dataset, wrong, normalise, config)
    problem = _CONTEXT["problem"]
    rmse = functools.cache(test_beta_rmse)  # each tuned point scored once

    try:
        independent = is_budget_independent("trbo" if label == "trbo-seeded" else label)
        if independent:
            run = tuning_run(label, seed, max(budgets))
            cells = {b: read_at(run, b, rmse) for b in budgets}
        else:
            cells = {b: read_at(tuning_run(label, seed, b), b, rmse) for b in budgets}
    except PeerUnavailableError as exc:
        return {"config": config, "label": label, "seed": seed, "skipped": str(exc)}
    names = problem.space.names
    for c in cells.values():
        c["params"] = dict(zip(names, c["x"], strict=True))
        del c["trace"]  # the traces of a few hundred units make the JSON heavy
    return json_safe(
        {
            "config": config,
            "label": label,
            "seed": seed,
            "seeded_from": seeded_from,
            "prefix_read": independent,
            "budgets": {str(b): c for b, c in cells.items()},
        }
    )


def start_point(dataset: str | None, wrong: dict[str, float], normalise: str, config: str) -> dict:
    """Training cost and test β RMSE [deg] of the manual point (the recorded model)."""
    build(dataset, wrong, normalise, config)
    problem = _CONTEXT["problem"]
    x = manual_point(problem.parameterization)
    try:
        j = float(problem(x))
    except FilterDivergedError:
        j = math.inf
    return json_safe({"J": j, "test_rmse_deg": test_beta_rmse(tuple(x)), "x": x.tolist()})


def config_best(units: list[dict], config: str) -> tuple[float, str, int, str] | None:
    """(lowest J, method, seed, budget) over every run of ``config`` (None: none ran)."""
    rows = [u for u in units if u["config"] == config and "skipped" not in u]
    if not rows:
        return None
    return min(
        (num(c["best"]), u["label"], u["seed"], b) for u in rows for b, c in u["budgets"].items()
    )


def summarise(
    units: list[dict], budgets: dict[str, list[int]], reference: Sequence[dict] = ()
) -> dict[str, Any]:
    """Per configuration: J*, and per method and budget the gaps, test β RMSE and tuned
    model parameters over seeds.

    J* is the lowest cost any run of the configuration found — and, for one with model
    parameters, at most the ``noise`` configuration's: its point (Q tuned at the start
    values, R unscaled) lies in the joint space, so a joint run above it has not found what
    noise-only tuning found (``jstar_found_by`` then names ``noise``). ``reference``: units of
    other runs (long ones, ``--reference``) that count for J* only."""
    out: dict[str, Any] = {}
    noise = config_best(units, "noise")
    for config in dict.fromkeys(u["config"] for u in units):
        best = config_best(units, config)
        if best is None:
            continue
        rows = [u for u in units if u["config"] == config and "skipped" not in u]
        found = {"method": best[1], "seed": best[2], "budget": int(best[3])}
        ref = config_best(list(reference), config)
        if ref is not None and ref[0] < best[0]:
            best = ref
            found = {"reference": ref[1], "seed": ref[2], "budget": int(ref[3])}
        if CONFIGS[config][0] and noise is not None and noise[0] < best[0]:
            best = noise
            found = {"config": "noise", "method": noise[1], "seed": noise[2]}
        jstar = best[0]
        s: dict[str, Any] = {"jstar": jstar, "jstar_found_by": found, "methods": {}}
        for label in dict.fromkeys(u["label"] for u in rows):
            mine = sorted((u for u in rows if u["label"] == label), key=lambda u: u["seed"])
            m: dict[str, Any] = {"seeds": [u["seed"] for u in mine]}
            for b in budgets[config]:
                cells = [u["budgets"][str(b)] for u in mine]
                j = [num(c["best"]) for c in cells]
                gaps = [gap_pct(v, jstar) for v in j]
                rmse = [num(c["test_rmse_deg"], math.nan) for c in cells]
                model = {
                    n: float(np.median([c["params"][n] for c in cells])) for n in CONFIGS[config][0]
                }
                m[str(b)] = {
                    "J": j,
                    "median_J": float(np.median(j)),
                    "median_gap_pct": float(np.median(gaps)),
                    "worst_gap_pct": float(np.max(gaps)),
                    "test_rmse_deg": rmse,
                    "median_test_rmse_deg": float(np.median(rmse)),
                    "median_model_params": model,
                    "median_wall_s": float(np.median([c["wall_s"] for c in cells])),
                    "n_failed": int(sum(c["n_failed"] for c in cells)),
                }
            m["monotone"] = monotonicity(mine, budgets[config], jstar)
            s["methods"][label] = m
        out[config] = s
    return out


def trbo_median_rmse(
    summary: dict[str, Any], config: str, budget: int, seeds: list[int], label: str = "trbo"
) -> Any:
    """``label``'s median test β RMSE at ``budget`` over ``seeds`` (None if not run)."""
    m = summary.get(config, {}).get("methods", {}).get(label)
    if m is None or str(budget) not in m:
        return None
    vals = [v for s, v in zip(m["seeds"], m[str(budget)]["test_rmse_deg"]) if s in seeds]
    return float(np.median(vals)) if len(vals) == len(seeds) else None


def targets(summary: dict[str, Any], recorded: bool) -> list[dict[str, Any]]:
    """The issue's targets, each PASS/FAIL/n/a with its figures."""
    out: list[dict[str, Any]] = []

    def add(target: str, ok: bool | None, detail: str) -> None:
        out.append(
            {
                "target": target,
                "result": "n/a" if ok is None else "PASS" if ok else "FAIL",
                "detail": detail,
            }
        )

    for (config, budget, limit), label in itertools.product(GAP_TARGETS, ("trbo", "trbo-seeded")):
        c = summary.get(config, {}).get("methods", {}).get(label, {}).get(str(budget))
        if c is None and label != "trbo":
            continue
        add(
            f"{label} median gap at {budget} ({config}) <= {limit:g} %",
            None if c is None else c["median_gap_pct"] <= limit,
            "not run" if c is None else f"{c['median_gap_pct']:.3f} %",
        )
    for config in ("d5", "d6", "d9"):
        methods = summary.get(config, {}).get("methods", {})
        if "trbo" not in methods:
            continue
        for key in (k for k in methods["trbo"] if k.isdigit()):
            peers = {p: methods[p][key]["median_J"] for p in PEERS if p in methods}
            mine = methods["trbo"][key]["median_J"]
            add(
                f"TR-BO ahead of every peer at {key} ({config}, median J)",
                None if not peers else all(mine < v for v in peers.values()),
                f"{mine:.6f} vs " + ", ".join(f"{p} {v:.6f}" for p, v in peers.items()),
            )
        mono = methods["trbo"]["monotone"]
        add(
            f"TR-BO never worse with more budget ({config})",
            not mono["rising_seeds"],
            f"rising on seeds {mono['rising_seeds']}",
        )
    seeds = [0, 1, 2]
    for label in ("trbo", "trbo-seeded"):
        joint_target(out, summary, recorded, seeds, label)
    return out


def joint_target(
    out: list[dict[str, Any]],
    summary: dict[str, Any],
    recorded: bool,
    seeds: list[int],
    label: str,
) -> None:
    """The held-out targets of joint tuning with ``label`` (appended to ``out``)."""

    def add(target: str, ok: bool | None, detail: str) -> None:
        verdict = "n/a" if ok is None else "PASS" if ok else "FAIL"
        out.append({"target": f"{label}: {target}", "result": verdict, "detail": detail})

    joint = trbo_median_rmse(summary, "d5" if recorded else "d6", 100, seeds, label)
    if joint is None and label != "trbo":
        return
    if recorded:
        noise = trbo_median_rmse(summary, "noise", 100, seeds)
        add(
            "joint (C_af, C_ar; TR-BO 100, seeds 0-2) test beta RMSE <= 1.01 x noise-only",
            None if joint is None or noise is None else joint <= JOINT_VS_NOISE * noise,
            "not run"
            if joint is None or noise is None
            else f"{joint:.4f} vs {noise:.4f} deg ({100 * (joint / noise - 1):+.1f} %)",
        )
    else:
        true = trbo_median_rmse(summary, "noise-true", 100, seeds)
        wrong = trbo_median_rmse(summary, "noise", 100, seeds)
        add(
            "joint (Q + C_af + C_ar + mu; TR-BO 100, seeds 0-2) test beta RMSE <= 1.05 x "
            "noise-only on the true vehicle",
            None if joint is None or true is None else joint <= JOINT_VS_TRUE * true,
            "not run"
            if joint is None or true is None
            else f"{joint:.4f} vs {true:.4f} deg ({100 * (joint / true - 1):+.1f} %); "
            + ("" if wrong is None else f"noise-only on the wrong vehicle {wrong:.4f} deg"),
        )


def print_tables(summary: dict[str, Any], starts: dict[str, Any]) -> None:
    for config, s in summary.items():
        names = list(CONFIGS[config][0])
        st = starts.get(config, {})
        print(
            f"\n{config} (d = {len(s.get('dim_names', [])) or '?'}): J* = {s['jstar']:.6f} "
            f"(found by {' '.join(f'{k} {v}' for k, v in s['jstar_found_by'].items())}); "
            f"start point J = {num(st.get('J')):.6f}, "
            f"test β RMSE {num(st.get('test_rmse_deg'), math.nan):.4f}°\n"
        )
        head = "| method | budget | gap median [%] | worst [%] | test β RMSE median [°] |"
        head += "".join(f" {n} median |" for n in names) + " J never rises |"
        print(head)
        print("|" + " --- |" * (6 + len(names)))
        for label, m in s["methods"].items():
            for key in (k for k in m if k.isdigit()):
                c = m[key]
                mono = m["monotone"]
                print(
                    f"| {label} | {key} | {c['median_gap_pct']:.3f} | {c['worst_gap_pct']:.3f} | "
                    f"{c['median_test_rmse_deg']:.4f} |"
                    + "".join(f" {c['median_model_params'][n]:.4g} |" for n in names)
                    + f" {mono['n'] - len(mono['rising_seeds'])}/{mono['n']} |"
                )


def read_units(path: Path) -> dict[str, Any]:
    """A ``--json-out`` file of this script (units, starts, budgets, seeds).

    Raises:
        ConfigError: it is not one, naming the file.
    """
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(data, dict) or data.get("benchmark") != "joint_tuning" or "units" not in data:
        raise ConfigError(f"{path}: not a --json-out file of joint_tuning.py (no units)")
    return data


def tune_cli_split(
    data: str,
    n: int,
    noise_budget: int | None,
    seed: int,
    model_args: Sequence[str],
    out: Path,
) -> dict[str, Any]:
    """One ``kftune tune DATA -n n --seed seed --no-calibration`` run in this process under
    tune's default cost, its two-stage split forced to ``noise_budget`` evaluations of the
    noise alone (None: the split ``experiment.staging`` chooses; 0: one unseeded joint
    search; without ``model_args`` a noise-only tuning). Its held-out β RMSE [deg] (test
    split), training J, the first stage's J and held-out β RMSE."""
    import contextlib
    import io

    import kftune.experiment as ex
    from kftune.cli import main as kftune_main

    original = ex.staging

    def forced(*a: Any, **kw: Any) -> Any:
        st = original(*a, **kw)
        if st is None or noise_budget is None:
            return st
        if noise_budget == 0:
            return None
        return ex.Staging(st.total, noise_budget, st.total - noise_budget, st.noise_storage)

    ex.staging = forced
    t0 = time.perf_counter()
    try:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            rc = kftune_main(
                ["tune", data, "-n", str(n), "--seed", str(seed), "--quiet",
                 "--no-calibration", "-o", str(out), *model_args]
            )  # fmt: skip
    finally:
        ex.staging = original
    if rc != 0:
        raise KftuneError(f"kftune tune {data} exited {rc}: {buf.getvalue()[-400:]}")
    doc = json.loads(out.read_text())
    st = doc.get("stages") or {}
    return {
        "seed": seed,
        "beta_deg": doc["held_out"]["beta_rmse_deg"],
        "J": doc["cost"],
        "noise_budget": st.get("noise_budget"),
        "stage1_J": (st.get("noise_only") or {}).get("cost"),
        "stage1_beta_deg": doc["held_out"].get("noise_only_beta_rmse_deg"),
        "model": {k: v["value"] for k, v in (doc.get("model_params") or {}).items()},
        "cost_spec": doc["cost_spec"],
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def run_tune_splits(
    dataset: str | None,
    wrong: dict[str, float],
    config: str,
    splits: Sequence[int],
    n: int,
    seeds: Sequence[int],
    swap: bool = False,
) -> dict[str, Any]:
    """``kftune tune`` as a user runs it (tune's default cost, TR-BO at ``n``): noise-only
    on the dataset's own vehicle, and the joint tuning of ``config``'s model parameters on
    the ``wrong`` vehicle (a copy of the dataset saved with it) with the first stage forced
    to each of ``splits`` (0: unseeded), every seed; with ``swap`` on a copy whose training
    and test manoeuvres trade places. Prints each run; returns the rows and per split the
    median held-out β RMSE [deg] and its ratio to noise-only's."""
    import dataclasses
    import statistics
    import tempfile

    from kftune.data.io import bundled_dataset_path, save_dataset

    bounds = CONFIGS[config][0]
    if not bounds or CONFIGS[config][1] != "none":
        raise ConfigError(
            f"--tune-splits needs a joint configuration without R (d5, d6), got {config}"
        )
    model_args = [
        a for name, (lo, hi) in bounds.items() for a in ("--tune-model", f"{name}={lo:g}:{hi:g}")
    ]
    true_path = dataset or str(bundled_dataset_path())
    rows: dict[str, list[dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory(prefix="joint_splits_") as tmp:
        if swap:
            ds = open_dataset(true_path)
            traded = [
                m.replace(split="test" if m.split == "train" else "train") for m in ds.manoeuvres
            ]
            save_dataset(dataclasses.replace(ds, manoeuvres=tuple(traded)), Path(tmp) / "swapped")
            true_path = str(Path(tmp) / "swapped")
        joint_path = true_path
        if wrong:
            ds = open_dataset(true_path)
            vehicle = ds.vehicle.replace(
                **{k: f * getattr(ds.vehicle, k) for k, f in wrong.items()}
            )
            save_dataset(dataclasses.replace(ds, vehicle=vehicle), Path(tmp) / "wrong")
            joint_path = str(Path(tmp) / "wrong")
        labels = ["noise-only", *(f"{s} + {n - s}" if s else "unseeded" for s in splits)]
        for seed in seeds:
            for label, split in zip(labels, [None, *splits], strict=True):
                out = Path(tmp) / f"{seed}-{label.replace(' ', '')}.json"
                if label == "noise-only":
                    row = tune_cli_split(true_path, n, None, seed, [], out)
                else:
                    row = tune_cli_split(joint_path, n, split, seed, model_args, out)
                rows.setdefault(label, []).append(row)
                first = ""
                if row["stage1_J"] is not None:
                    b1 = num(row["stage1_beta_deg"], math.nan)
                    first = f" (first stage J {row['stage1_J']:.5f}, β {b1:.4f}°)"
                print(
                    f"  {label:10s} seed {seed}: β {row['beta_deg']:.4f}° J {row['J']:.5f}"
                    + first
                    + "".join(f" {k}={v:.4g}" for k, v in row["model"].items())
                    + f" ({row['wall_s']:.0f} s)",
                    flush=True,
                )  # fmt: skip
    ref = statistics.median(r["beta_deg"] for r in rows["noise-only"])
    summary = {}
    print(f"\nmedian held-out β RMSE [deg] over seeds {list(seeds)} (worst), median J:")
    for label, rs in rows.items():
        med = statistics.median(r["beta_deg"] for r in rs)
        summary[label] = {
            "beta_median_deg": med,
            "beta_worst_deg": max(r["beta_deg"] for r in rs),
            "ratio_to_noise_only": med / ref,
            "J_median": statistics.median(r["J"] for r in rs),
        }
        s = summary[label]
        print(
            f"  {label:10s} {med:.4f} ({s['beta_worst_deg']:.4f}) "
            f"{100 * (med / ref - 1):+.1f} %  J {s['J_median']:.5f}"
        )
    return {"rows": rows, "summary": summary, "cost_spec": rows["noise-only"][0]["cost_spec"]}


def default_budgets(config: str) -> list[int]:
    """d = 9: 75 and 150; otherwise 50 and 100."""
    return [75, 150] if CONFIGS[config][1] == "diag" else [50, 100]


def main(argv: list[str] | None = None) -> int:
    global SEED_BUDGET
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=None, help="dataset directory (default: bundled)")
    ap.add_argument(
        "--wrong",
        nargs="*",
        default=list(DEFAULT_WRONG),
        metavar="NAME=FACTOR",
        help="the filter's vehicle: these fields scaled (default C_af=0.7 C_ar=1.4 mu=0.8; "
        "none: the recorded vehicle)",
    )
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument(
        "--methods",
        nargs="+",
        default=list(DEFAULT_METHODS),
        choices=[*METHODS, "trbo-faces", "trbo-seeded"],
    )
    ap.add_argument(
        "--seed-budget",
        type=int,
        default=SEED_BUDGET,
        help=f"evaluations of trbo-seeded's noise-only run (default {SEED_BUDGET}); with "
        "--budgets n - N it is tune's two-stage split of n",
    )
    ap.add_argument(
        "--tune-splits",
        type=int,
        nargs="+",
        default=None,
        metavar="N1",
        help="instead of the optimisers: run kftune tune (its default cost, TR-BO at "
        "--tune-n) noise-only on the dataset's vehicle and joint (--configs' first, d5 or d6) "
        "on the wrong one with the first stage forced to N1 evaluations (0: unseeded)",
    )
    ap.add_argument("--tune-n", type=int, default=100, help="-n of --tune-splits (default 100)")
    ap.add_argument(
        "--swap-split",
        action="store_true",
        help="with --tune-splits: tune on the dataset's test manoeuvres and hold out its "
        "training ones (does the held-out verdict depend on which manoeuvres are held out?)",
    )
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds (default 5)")
    ap.add_argument("--seed-offset", type=int, default=0, help="first seed (default 0)")
    ap.add_argument("--budgets", type=int, nargs="+", default=None, help="for every config")
    ap.add_argument("--normalise", choices=NORMALISATIONS, default="manoeuvre")
    ap.add_argument("--json-out", type=Path, default=None, help="also write the units here")
    ap.add_argument(
        "--reference",
        type=Path,
        nargs="+",
        default=[],
        help="--json-out files of other runs (e.g. long CMA-ES runs) whose units count for J*",
    )
    ap.add_argument(
        "--from",
        dest="from_json",
        type=Path,
        default=None,
        help="summarise the units of this --json-out file instead of running",
    )
    args = ap.parse_args(argv)
    try:
        wrong = parse_scales(args.wrong)
    except argparse.ArgumentTypeError as exc:
        ap.error(str(exc))
    if args.seeds < 1 or args.seed_offset < 0 or args.seed_budget < 1:
        ap.error("--seeds and --seed-budget must be >= 1 and --seed-offset >= 0")
    SEED_BUDGET = args.seed_budget
    if args.budgets is not None and any(b < 1 for b in args.budgets):
        ap.error(f"--budgets must be positive integers, got {args.budgets}")
    budgets = {
        c: sorted(set(args.budgets)) if args.budgets else default_budgets(c) for c in args.configs
    }
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    t0 = time.perf_counter()
    if args.tune_splits is not None:
        if any(not 0 <= k < args.tune_n for k in args.tune_splits):
            ap.error(f"--tune-splits must lie in [0, --tune-n), got {args.tune_splits}")
        try:
            result = run_tune_splits(
                args.dataset,
                wrong,
                args.configs[0],
                args.tune_splits,
                args.tune_n,
                seeds,
                swap=args.swap_split,
            )
        except KftuneError as exc:
            print(f"joint_tuning: error: {exc}", file=sys.stderr)
            return 3
        print(
            json.dumps(
                json_safe(
                    {
                        "benchmark": "joint_tuning --tune-splits",
                        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
                        "machine": f"{platform.machine()} {os.cpu_count()} cpu, "
                        f"{platform.python_version()}",
                        "kftune_version": kftune.__version__,
                        "wall_s": round(time.perf_counter() - t0, 1),
                        "dataset": args.dataset or "bundled",
                        "wrong": wrong,
                        "config": args.configs[0],
                        "n": args.tune_n,
                        "seeds": seeds,
                        "swap_split": args.swap_split,
                        **result,
                    }
                ),
                allow_nan=False,
            )
        )
        return 0
    starts: dict[str, Any] = {}
    units: list[dict[str, Any]] = []
    try:
        reference = [u for path in args.reference for u in read_units(path)["units"]]
        if args.from_json is not None:
            stored = read_units(args.from_json)
            units, starts = stored["units"], stored["starts"]
            budgets = {c: b for c, b in stored["budgets"].items() if c in args.configs}
            units = [u for u in units if u["config"] in budgets]
            seeds = stored["seeds"]
            args.dataset = None if stored["dataset"] == "bundled" else stored["dataset"]
            wrong, args.normalise = stored["wrong"], stored["normalise"]
    except KftuneError as exc:
        print(f"joint_tuning: error: {exc}", file=sys.stderr)
        return 3
    try:
        for config in args.configs if args.from_json is None else ():
            starts[config] = start_point(args.dataset, wrong, args.normalise, config)
            print(
                f"{config}: d = {_CONTEXT['problem'].space.dim}, "
                f"{' '.join(_CONTEXT['problem'].space.names)}; start J "
                f"{num(starts[config]['J']):.6f}, test β RMSE "
                f"{num(starts[config]['test_rmse_deg'], math.nan):.4f}°",
                flush=True,
            )
            for label in args.methods:
                if config.startswith("noise") and label != "trbo":
                    continue  # the noise-only baselines are TR-BO's (the targets' reference)
                for seed in seeds:
                    u = run_unit(
                        args.dataset, wrong, args.normalise, config, label, seed, budgets[config]
                    )
                    units.append(u)
                    if "skipped" in u:
                        print(f"  {config} {label} seed {seed}: skipped ({u['skipped']})")
                        continue
                    print(
                        f"  {config:10s} {label:10s} seed {seed}: "
                        + "  ".join(
                            f"J {num(c['best']):.6f} β {num(c['test_rmse_deg'], math.nan):.4f}°"
                            f" @{b} ({c['wall_s']:.0f} s) "
                            + " ".join(f"{n}={c['params'][n]:.4g}" for n in CONFIGS[config][0])
                            for b, c in u["budgets"].items()
                        ),
                        flush=True,
                    )
    except KftuneError as exc:
        print(f"joint_tuning: error: {exc}", file=sys.stderr)
        return 3
    summary = summarise(units, budgets, reference)
    for config, s in summary.items():
        build(args.dataset, wrong, args.normalise, config)
        s["dim_names"] = list(_CONTEXT["problem"].space.names)
    print_tables(summary, starts)
    checks = targets(summary, recorded=not wrong)
    print("\ntargets:")
    for c in checks:
        print(f"  {c['result']:4s}  {c['target']}: {c['detail']}")
    out = {
        "benchmark": "joint_tuning",
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "machine": f"{platform.machine()} {os.cpu_count()} cpu, {platform.python_version()}",
        "kftune_version": kftune.__version__,
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "wall_s": round(time.perf_counter() - t0, 1),
        "dataset": args.dataset or "bundled",
        "wrong": wrong,
        "normalise": args.normalise,
        "seeds": seeds,
        "seed_budget": SEED_BUDGET,
        "budgets": budgets,
        "starts": starts,
        "summary": summary,
        "targets": checks,
    }
    if args.json_out is not None:
        args.json_out.write_text(
            json.dumps(json_safe({**out, "units": units}), allow_nan=False) + "\n"
        )
    print(json.dumps(json_safe(out), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
