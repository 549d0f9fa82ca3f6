"""Whether model parameters tuned with the noise generalise beyond the training manoeuvres.

More parameters can fit a few training manoeuvres better and new ones worse. The evidence
compares three filters on data the model parameters were not fitted on:

* the joint filter: the tuned point x (Q, R, … and the model parameters);
* "tuned Q on the recorded model": x with every model parameter back at its start value
  (the recorded one), i.e. the tuned noise on the model the user was handed;
* where it applies, the manual rule of thumb (:func:`kftune.experiment.manual_point`).

With a test split the comparison is on its manoeuvres (:func:`recorded_model_point` gives
the second filter). Without one, :func:`leave_one_out` cross-validates the model parameters
over the training manoeuvres: for each manoeuvre k it refits only the model parameters on
the others (Q, R and the sigma points held at their tuned values, a bounded Nelder–Mead
search from the tuned values, a few evaluations per parameter) and scores the refit on k.
Q was fitted on all manoeuvres, k included, in both filters alike, so the comparison
isolates what the model parameters add; it is not an unbiased estimate of the joint
filter's test error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.optimize import minimize

from kftune.errors import FilterDivergedError
from kftune.tuning.kpi import sideslip_kpis
from kftune.tuning.problem import TuningProblem
from kftune.tuning.runs import first_scored, model_output

#: Evaluations of a leave-one-out refit per tuned model parameter (plus a base of 10).
REFIT_EVALS_PER_PARAM = 10


def recorded_model_point(problem: TuningProblem, x: Sequence[float] | np.ndarray) -> np.ndarray:
    """(d,) the point x with every tuned model parameter at its start (recorded) value."""
    par = problem.parameterization
    out = np.array(x, dtype=float)
    names = par.space.names
    for n in par.model_names:
        out[names.index(n)] = par.model_start[n]
    return out


def joint_point(problem: TuningProblem, x_noise: Sequence[float] | np.ndarray) -> np.ndarray:
    """(d,) the point of ``problem``'s joint space that is the point ``x_noise`` of its
    :meth:`~TuningProblem.noise_only` space (the noise parameters, natural units) with every
    tuned model parameter at its start (recorded) value: the same filter, so the same cost.

    Raises:
        ValueError: ``x_noise`` is not a point of the noise-only space.
    """
    par = problem.parameterization
    noise_names = [n for n in par.space.names if n not in par.model_names]
    x_noise = np.asarray(x_noise, dtype=float)
    if x_noise.shape != (len(noise_names),):
        raise ValueError(
            f"expected a point of {len(noise_names)} noise parameters {noise_names}, got shape "
            f"{x_noise.shape}"
        )
    values = {**dict(zip(noise_names, x_noise.tolist())), **par.model_start}
    return np.array([values[n] for n in par.space.names], dtype=float)


def beta_rmse_deg(problem: TuningProblem, x: np.ndarray, m: Any) -> float | None:
    """β RMSE [deg] of the filter at x on manoeuvre m after the burn-in (None: it
    diverged, or m has no sideslip reference)."""
    if not m.has("beta_ref"):
        return None
    res = problem.run(x, m)
    if res.diverged:
        return None
    k0 = first_scored(m, problem.burn_in)
    return sideslip_kpis(model_output(res, "beta")[k0:], m.beta_ref[k0:], m.ay[k0:])["rmse"]


def leave_one_out(problem: TuningProblem, x: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Cross-validation of the tuned model parameters over the training manoeuvres (module
    docstring): for each manoeuvre k, the model parameters refitted on the others (the
    problem's cost over them, :meth:`TuningProblem.score_manoeuvres`, uncalibrated as it
    was tuned) and the β RMSE [deg] on k of the refitted filter, the joint filter (fitted
    on all) and the tuned Q on the recorded model (these three with the problem's
    ``cov_scale``, as deployed).

    Returns:
        ``{"kind", "refit", "manoeuvres": {name: {"refit", "joint", "recorded_model",
        "refit_values"}}, "mean_refit", "mean_joint", "mean_recorded_model"}`` (β RMSE
        [deg], None where a filter diverged or the manoeuvre has no reference; means over
        the manoeuvres where all three are numbers, None without any).

    Raises:
        ValueError: fewer than two training manoeuvres, or no tuned model parameter.
    """
    par = problem.parameterization
    if not par.model_names:
        raise ValueError("no model parameter was tuned: nothing to cross-validate")
    n = len(problem.manoeuvres)
    if n < 2:
        raise ValueError("a leave-one-out needs at least two training manoeuvres")
    x = np.asarray(x, dtype=float)
    space = par.space
    idx = [space.names.index(m) for m in par.model_names]
    u0 = space.to_unit(x)[idx]
    start = recorded_model_point(problem, x)

    def point(u: np.ndarray) -> np.ndarray:
        full = space.to_unit(x)
        full[idx] = np.clip(u, 0.0, 1.0)
        return space.from_unit(full)

    rows: dict[str, dict[str, Any]] = {}
    for k, m in enumerate(problem.manoeuvres):
        others = [i for i in range(n) if i != k]

        def cost(u: np.ndarray, others: list[int] = others) -> float:
            scale, problem.cov_scale = problem.cov_scale, 1.0  # the cost as tuned
            try:
                scores = problem.score_manoeuvres(point(u), others)
                value = problem._pool_scores(scores).cost
            except FilterDivergedError:
                return math.inf
            finally:
                problem.cov_scale = scale
            return value if math.isfinite(value) else math.inf

        d = len(idx)
        fit = minimize(
            cost,
            u0,
            method="Nelder-Mead",
            bounds=[(0.0, 1.0)] * d,
            options={"maxfev": 10 + REFIT_EVALS_PER_PARAM * d, "xatol": 1e-3, "fatol": 1e-6},
        )
        refit = point(fit.x if math.isfinite(fit.fun) else u0)
        rows[m.name] = {
            "refit": beta_rmse_deg(problem, refit, m),
            "joint": beta_rmse_deg(problem, x, m),
            "recorded_model": beta_rmse_deg(problem, start, m),
            "refit_values": par.model_values(refit),
        }
    full = [r for r in rows.values() if None not in (r["refit"], r["joint"], r["recorded_model"])]

    def mean(key: str) -> float | None:
        return float(np.mean([r[key] for r in full])) if full else None

    return {
        "kind": "leave-one-out over the training manoeuvres",
        "refit": "model parameters only, Q/R/sigma points held at the tuned values (fitted "
        "on all manoeuvres)",
        "manoeuvres": rows,
        "mean_refit": mean("refit"),
        "mean_joint": mean("joint"),
        "mean_recorded_model": mean("recorded_model"),
    }
