"""The paper's experiment (Sec. VI): tune on the training set with several methods, evaluate
every tuned filter on the training and test sets, and store what the report needs.

For a model with the sideslip output ``beta`` on data with the reference ``beta_ref`` it is
the paper's experiment (sideslip KPIs, β figures); for any other model or data the KPIs are
the RMSE of each scored channel against its reference (:func:`scored_channels`).

This module only wires the layers together — data → tuning problem → optimiser → results —
the CLI's ``tune`` and ``compare`` call it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from kftune import __version__
from kftune.bo import make_surrogate
from kftune.data.io import file_stem
from kftune.data.manoeuvre import Dataset, Manoeuvre
from kftune.errors import ConfigError, FilterDivergedError, KftuneError, RunFailedError
from kftune.models import StateSpaceModel
from kftune.optim import (
    COMPARE_METHODS,
    DEFAULT_METHOD,
    METHODS,
    Execution,
    OptimizationInterrupted,
    OptimizeResult,
    is_study,
    make_optimizer,
    minimize,
    minimize_widening,
    study_files,
)
from kftune.optim.engine import Engine
from kftune.progress import ProgressBar, announce
from kftune.report.provenance import machine, package_versions
from kftune.report.results import ExperimentResults, MethodRun
from kftune.space import Space
from kftune.tuning.cost import LOG_COSTS, CostSpec
from kftune.tuning.deploy import RELIABILITY_LEVELS, consistency_docs, dataset_fingerprint
from kftune.tuning.kpi import average_kpis
from kftune.tuning.parameterization import Q_NAMES, NoiseParameterization
from kftune.tuning.problem import TuningProblem, assess
from kftune.tuning.runs import (
    channel_estimate,
    check_units,
    default_r0,
    failure_kinds,
    filter_spec,
    model_output,
)

#: The one spelling of each method in tables, legends, progress lines and the README (paper
#: Table V naming, written without spaces around the hyphen as the README's tables have it).
LABELS: dict[str, str] = {
    "manual": "Manual",
    "ga": "GA",
    "tsbo-gp": "TSBO-GP",
    "tsbo-tsp": "TSBO-tSP",
    "tsbo-robust": "TSBO-robust GP",
    "random": "Random",
    "optuna-tpe": "Optuna TPE",
    "optuna-gp": "Optuna GP",
    "cma": "CMA-ES",
    "trbo": "TR-BO",
}


#: "Manual tuning": Q from a rule of thumb, not from a search. The process noise of each
#: state is the squared change per 10 ms step that plausible model errors cause:
#: Vx — ax sensor error ≈ 0.1 m/s² → (1e-3 m/s)²; Vy — lateral-force model error ≈ 1 m/s²
#: (about 10 % of the peak ay) → (1e-2 m/s)²; r — yaw-moment error ≈ 0.1 rad/s² →
#: (1e-3 rad/s)². Q = diag(1e-6, 1e-4, 1e-6).
MANUAL_Q: tuple[float, float, float] = (1e-6, 1e-4, 1e-6)


def manual_point(parameterization: NoiseParameterization) -> np.ndarray:
    """The manual-tuning point in the space of ``parameterization`` (R unscaled, default
    sigma points), clipped into the space's bounds if they exclude it. A state without a
    rule of thumb (any but Vx, Vy, r) gets the geometric centre of its box; a tuned model
    parameter its start value ``model_start`` (the recorded model; a parameterisation
    without one — not yet completed by a :class:`TuningProblem` — is refused)."""
    space = parameterization.space
    missing = [n for n in parameterization.model_names if n not in parameterization.model_start]
    if missing:
        raise ValueError(
            f"model parameters {missing} have no start value: take the parameterisation of "
            "the TuningProblem, which completes them from the recorded model"
        )
    values = {p.name: float(np.sqrt(p.low * p.high)) for p in space if p.name.startswith("q_")}
    values.update(zip(Q_NAMES, MANUAL_Q))
    values.update({n: 1.0 for n in parameterization.r_names})
    s = parameterization.default_settings
    values.update(ukf_alpha=s.alpha, ukf_beta=s.beta, ukf_kappa=s.kappa)
    values.update(parameterization.model_start)
    x = np.array([values[n] for n in space.names])
    return np.clip(x, space.lows, space.highs)


#: Method options that hold points of the tuned space (:func:`complete_points`).
POINT_OPTIONS: Mapping[str, tuple[str, ...]] = {"manual": ("points",), "trbo": ("x0",)}


def complete_points(
    parameterization: NoiseParameterization, value: Any, method: str, key: str
) -> tuple[np.ndarray, str | None]:
    """A method's points (``[options.manual] points``, ``[options.trbo] x0``) as a (k, d)
    array of the tuned space, and a note (None: nothing to say) on what was filled in.

    A point is d numbers in the space's order, or a table ``{q_vx = …, r_ay_scale = …}``
    by name. A point written for a smaller space — Q alone, as for the paper's cost (``kftune
    tune``'s default before it tuned R's diagonal too), or a table without some names —
    keeps what it gives and takes the rest from the untuned filter: R factors 1 (the
    recorded R, which a Q-only cost used), the default sigma points, a model parameter its
    recorded value (:func:`manual_point`'s values); the note names them. The Q entries are
    never filled in: a point without them says nothing about what is tuned.

    Raises:
        ConfigError: not a list of points, a point of another length than d or the number
            of Q entries, a table with an unknown name or without a Q entry, a value that
            is not a number — naming the option, the expected names and the ways out.
    """
    par = parameterization
    names, q_names = par.space.names, par.q_names
    where = f"[options.{method}] {key}"
    rest = names[len(q_names) :]
    ways = (
        f"give all {len(names)} values ({', '.join(names)})"
        + (
            f", the {len(q_names)} of Q alone (the others as the untuned filter has them: "
            "R factors 1)"
            if rest
            else ""
        )
        + f" or a table by name ({{{names[0]} = …, …}})"
        + ("; to tune Q alone, the paper's cost: --cost nrmse" if par.r_names else "")
    )
    if isinstance(value, Mapping) or (
        isinstance(value, list) and value and all(_is_number(v) for v in value)
    ):
        value = [value]  # one point
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{where}: expected a list of points, got {type(value).__name__}; {ways}")
    defaults = dict(zip(names, manual_point(par).tolist()))
    filled: set[str] = set()
    points = []
    for n, point in enumerate(value, 1):
        if isinstance(point, Mapping):
            unknown = sorted(set(point) - set(names))
            if unknown:
                raise ConfigError(
                    f"{where}: point {n} names {unknown}, not tuned in this run; its "
                    f"parameters are {', '.join(names)}"
                )
            given = dict(point)
        elif isinstance(point, list) and len(point) in (len(names), len(q_names)):
            given = dict(zip(names, point))
        else:
            size = len(point) if isinstance(point, list) else type(point).__name__
            raise ConfigError(
                f"{where}: point {n} has {size} values, but this run tunes {len(names)}; {ways}"
            )
        missing_q = [q for q in q_names if q not in given]
        if missing_q:
            raise ConfigError(f"{where}: point {n} gives no {', '.join(missing_q)}; {ways}")
        bad = [k for k, v in given.items() if not _is_number(v)]
        if bad:
            booleans = [k for k in bad if isinstance(given[k], bool)]
            raise ConfigError(
                f"{where}: point {n}: {', '.join(bad)} must be numbers"
                + (f" ({', '.join(booleans)} not true/false)" if booleans else "")
            )
        filled.update(k for k in rest if k not in given)
        points.append([float(given.get(k, defaults[k])) for k in names])
    if not filled:
        return np.array(points), None
    what = [f"{k} = {defaults[k]:g}" for k in names if k in filled]
    why = (
        " (R factor 1: the recorded R, as a cost of Q alone used it)"
        if filled & set(par.r_names)
        else ""
    )
    note = (
        f"{where}: the points leave out {', '.join(k for k in names if k in filled)}; taken "
        f"as {', '.join(what)}{why}; give them in the points to set them"
    )
    return np.array(points), note


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: Share of a joint tuning's budget (model parameters tuned with the noise) spent on its
#: first stage, the noise alone at the recorded model; the second, the joint search, starts
#: from that stage's best (TR-BO's ``x0``) and so ends no worse than it. Measured on the
#: bundled set with a wrong vehicle and on revs-250lm (BENCHMARKS.md, "Tuning model
#: parameters": the budget split of the two stages).
NOISE_STAGE_SHARE = 0.25
#: Methods whose search can start from a given point (their option ``x0``): a joint tuning
#: with one of them runs in two stages (:func:`staging`); the others search the joint box
#: at once.
SEEDABLE_METHODS: tuple[str, ...] = ("trbo",)
#: TR-BO's options that shape its design around a point (:class:`~kftune.optim.trbo.
#: TRBOSettings`): the joint stage's alone (the first stage's space has no model parameter
#: to name). Unless the user gives either, the joint stage's design is centred on the first
#: stage's best and probes the model parameters' axes alone (BENCHMARKS.md, "The joint
#: stage's design").
DESIGN_OPTIONS: tuple[str, ...] = ("design_centre", "design_params")


@dataclass(frozen=True)
class Staging:
    """How a joint tuning splits its budget: ``noise_budget`` evaluations of the noise
    alone at the recorded model (stage 1, its study in ``noise_storage``), then
    ``joint_budget`` of the joint search seeded with stage 1's best; ``total`` = the two.
    ``noise_design``, ``joint_design``: the evaluations each stage spends before its
    search begins, which its budget should exceed: TR-BO's initial design, 2d + 1 points
    over the noise's d parameters; in the joint stage stage 1's best and the design through
    it, two points per model parameter (:data:`DESIGN_OPTIONS`), or the design the user's
    options give (``n_init`` when given), after stage 1's best unless centred on it."""

    total: int
    noise_budget: int
    joint_budget: int
    noise_storage: Path | None
    noise_design: int = 0
    joint_design: int = 0

    def line(self) -> str:
        """What ``tune`` says about the split."""
        return (
            f"{self.total} evaluations in two stages: {self.noise_budget} of the noise alone "
            f"at the recorded model, then {self.joint_budget} of the joint search starting "
            "from its best"
        )

    def warning(self) -> str | None:
        """A sentence when a stage's budget ends within its initial design, with the
        smallest total that gives each stage at least one search step; None when both
        search."""
        if self.noise_budget > self.noise_design and self.joint_budget > self.joint_design:
            return None
        need = self.total
        while True:
            need += 1
            noise = _noise_share(need)
            if noise > self.noise_design and need - noise > self.joint_design:
                break
        return (
            f"{self.noise_budget} evaluations of the noise alone and {self.joint_budget} of "
            f"the joint search end within TR-BO's initial designs ({self.noise_design} and "
            f"{self.joint_design} points: the centre and two per noise parameter, the seed and "
            "two per model parameter): the search "
            f"itself never starts and the result is a design point; give -n {need} or more"
        )


def noise_stage_storage(storage: str | Path | None) -> Path | None:
    """The study file of a joint tuning's first stage: ``<stem>.noise-only<suffix>`` beside
    ``storage`` (None without storage)."""
    if storage is None:
        return None
    p = Path(storage)
    return p.with_name(f"{p.stem}.noise-only{p.suffix}")


def staging(
    problem: TuningProblem,
    method: str,
    budget: int | None,
    *,
    options: Mapping[str, Any] | None = None,
    engine: Engine | None = None,
    storage: str | Path | None = None,
) -> Staging | None:
    """The two stages of a joint tuning (:class:`Staging`), or None where it runs in one:
    no model parameter tuned, a method that cannot start from a point
    (:data:`SEEDABLE_METHODS`), a start point the user gave (option ``x0``), a Dask engine
    (it holds the joint problem), or a budget below 2. ``budget`` None: the method's
    default. The split is :data:`NOISE_STAGE_SHARE`."""
    if (
        not problem.parameterization.model_names
        or method not in SEEDABLE_METHODS
        or "x0" in (options or {})
        or engine is not None
    ):
        return None
    total = budget if budget is not None else make_optimizer(method, problem.space).budget
    if total < 2:
        return None
    noise = _noise_share(total)
    d = problem.space.dim
    d_noise = d - len(problem.parameterization.model_names)
    n_init = (options or {}).get("n_init")

    def design(dim: int) -> int:
        return int(n_init) if isinstance(n_init, int) and n_init > 0 else 2 * dim + 1

    given = options or {}
    own = any(k in given for k in DESIGN_OPTIONS)  # else: the seed-centred model design
    centre = given.get("design_centre", "box") if own else "x0"
    named = given.get("design_params")
    probed = len(named) if isinstance(named, list) else (d if own else d - d_noise)
    joint = design(probed) + (0 if centre == "x0" else 1)  # the seed: the centre, or first
    return Staging(
        total, noise, total - noise, noise_stage_storage(storage), design(d_noise), joint
    )


def _noise_share(total: int) -> int:
    """Stage 1's evaluations of a two-stage tuning of ``total``: :data:`NOISE_STAGE_SHARE`,
    at least one and at most ``total − 1``."""
    return min(total - 1, max(1, round(total * NOISE_STAGE_SHARE)))


def with_dataset(fingerprint: dict[str, Any], dataset: Mapping[str, Any] | None) -> dict[str, Any]:
    """A study's objective: a problem's fingerprint and, where known, the dataset it was
    made on (``"dataset"``: ``{"name": …, "path": …}``, read only to name it;
    :mod:`kftune.optim.study` compares objectives without it)."""
    return fingerprint if dataset is None else {**fingerprint, "dataset": dataset}


def tune(
    problem: TuningProblem,
    method: str = DEFAULT_METHOD,
    *,
    budget: int | None = None,
    seed: int = 0,
    storage: str | Path | None = None,
    resume: bool = False,
    progress: bool | None = None,
    options: Mapping[str, Any] | None = None,
    widen_bounds: bool = False,
    execution: Execution | None = None,
    dataset: Mapping[str, Any] | None = None,
) -> OptimizeResult:
    """Tune the filter of ``problem`` with one method (``kftune tune``).

    ``execution``: how the cost is evaluated (:class:`kftune.optim.Execution`; see
    :func:`kftune.minimize`): a per-evaluation ``timeout`` (only with ``problem.workers``
    = 1: the worker process cannot share its limit with a pool), or an ``engine`` and a
    ``batch`` to evaluate q points at a time, e.g. on a Dask cluster
    (:class:`kftune.optim.dask_engine.DaskEngine`). Default: in this process, one point at
    a time.

    ``method="manual"`` evaluates :func:`manual_point` unless ``options`` give ``points``;
    a user's points (and TR-BO's ``x0``) are read by :func:`complete_points`, which fills in
    what a point of Q alone leaves out and says so on standard error (unless ``progress``
    is False).
    ``progress``: None shows a bar when stderr is a terminal and plain lines otherwise;
    True/False force the bar or nothing (:class:`~kftune.progress.ProgressBar`).

    The study (``storage``) records the problem's :meth:`~TuningProblem.fingerprint`, so
    resuming it on other data, another cost or another model is refused; ``dataset`` (its
    name and where it was read) is recorded beside it, for the refusal to name it, and is
    no part of what must match (a dataset moved elsewhere resumes).

    With model parameters tuned and a method of :data:`SEEDABLE_METHODS` (TR-BO), the
    budget runs in two stages (:func:`staging`): the noise alone at the recorded model
    (:meth:`TuningProblem.noise_only`, its study ``<stem>.noise-only<suffix>`` beside
    ``storage``), then the joint search from that stage's best (TR-BO's ``x0``: evaluated
    first, so the joint result is never worse on the training cost). The result is the
    second stage's; its ``options["x0"]`` holds the first stage's best in the joint space.
    A Ctrl-C in the first stage raises with its best so far lifted into the joint space.

    ``widen_bounds``: while the best point lies on a bound of a log10 parameter, move that
    bound out by two decades and run the method again with the same budget (at most three
    times; :func:`kftune.optim.minimize_widening`; a tuned model parameter's box is never
    widened: it stays within the model's plausible range); the follow-up studies lie beside
    ``storage`` (``study.widen1.db`` …) and resume with it. The result merges the runs.

    Raises:
        ConfigError: an unknown method or method option, a bad budget or seed, or a
            timeout with ``problem.workers`` > 1.
        kftune.optim.OptimizationInterrupted: Ctrl-C (``.result`` holds the partial run).
    """
    if method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; choose one of {list(METHODS)}")
    if widen_bounds and method == "manual":
        raise ConfigError("widening the bounds needs a search; the manual method has none")
    opts = dict(options or {})
    if method == "manual" and "points" not in opts:
        opts["points"] = manual_point(problem.parameterization)[None, :]
    for key in POINT_OPTIONS.get(method, ()):
        if key in opts and not isinstance(opts[key], np.ndarray):  # a user's, from a file
            opts[key], note = complete_points(problem.parameterization, opts[key], method, key)
            announce(note, progress)
    try:  # settle option errors before anything is stored or evaluated
        total = make_optimizer(method, problem.space, budget=budget, seed=seed, **opts).budget
    except ValueError as exc:
        raise ConfigError(f"{method}: {exc}") from None
    ex = Execution() if execution is None else execution  # its own values checked there
    if ex.timeout is not None and problem.workers > 1:
        raise ConfigError(
            "a per-evaluation timeout runs every evaluation in one worker process; combine "
            "it with workers = 1 (the worker cannot share its time limit with a pool)"
        )

    stages = staging(problem, method, budget, options=opts, engine=ex.engine, storage=storage)
    if stages is not None:
        from kftune.tuning.generalise import joint_point

        noise = problem.noise_only()
        try:
            with ProgressBar(
                stages.noise_budget,
                f"{LABELS.get(method, method)}, noise only",
                enabled=progress,
                note=problem.compile_note(),
            ) as bar:
                first = minimize(
                    noise,
                    noise.space,
                    method,
                    budget=stages.noise_budget,
                    seed=seed,
                    storage=None if stages.noise_storage is None else str(stages.noise_storage),
                    resume=resume,
                    callback=bar,
                    objective=with_dataset(noise.fingerprint(), dataset),
                    execution=ex,  # no engine: a Dask engine's tuning runs in one stage
                    **{k: v for k, v in opts.items() if k not in DESIGN_OPTIONS},
                )
        except OptimizationInterrupted as stop:  # its best so far, as a point of the problem
            raise OptimizationInterrupted(_lifted(problem, stop.result)) from None
        finally:
            noise.close()
        if first.x is not None:  # every evaluation failed: the joint search starts cold
            opts["x0"] = [joint_point(problem, first.x).tolist()]
            if not any(k in opts for k in DESIGN_OPTIONS):  # a user's own design stays theirs
                opts["design_centre"] = "x0"
                opts["design_params"] = list(problem.parameterization.model_names)
        budget = total = stages.joint_budget
        # the joint study is created after the first stage's: a resume starts it then
        resume = resume and storage is not None and Path(storage).exists()

    def run(space: Any, study: Path | None) -> OptimizeResult:
        label = LABELS.get(method, method)
        with ProgressBar(total, label, enabled=progress, note=problem.compile_note()) as bar:
            return minimize(
                problem,
                space,
                method,
                budget=budget,
                seed=seed,
                storage=None if study is None else str(study),
                resume=resume,
                callback=bar,
                objective=with_dataset(problem.fingerprint(), dataset),
                execution=ex,
                **opts,
            )

    if widen_bounds:
        return minimize_widening(
            run, problem.space, storage=storage, fixed=problem.parameterization.model_names
        )
    return run(problem.space, None if storage is None else Path(storage))


def _lifted(problem: TuningProblem, result: OptimizeResult) -> OptimizeResult:
    """A first stage's result (noise-only space) with its best point in ``problem``'s joint
    space (the model parameters at their start), for what an interrupted run keeps."""
    from kftune.tuning.generalise import joint_point

    if result.x is None:
        return replace(result, space=problem.space.to_dict())
    x = joint_point(problem, result.x)
    return replace(
        result,
        x=x,
        params=dict(zip(problem.space.names, x.tolist())),
        space=problem.space.to_dict(),
    )


def on_bounds(result: OptimizeResult) -> list[dict[str, Any]]:
    """Where the best point of ``result`` lies on a bound of the space it was searched in
    (within 1 % of the range): ``[{parameter, side, value, bound}, …]``, empty if none."""
    if result.x is None:
        return []
    space = Space.from_dict(result.space)
    return [h.to_dict() for h in space.on_bounds(space.to_unit(result.x))]


#: How little the cost may gain over the last step up to a bound for the bound to be said
#: not to matter (:func:`edge_probes`): a share of |J*| for the costs that scale with the
#: error (nrmse, crps), and an absolute change for a cost that is a logarithm (msp: Σ log
#: MSE; nis: |log(mean NIS/m)|), where 1e-3 is a 0.1 % change of what it takes the log of.
FLAT_RISE = 1e-3


def edge_probes(
    problem: TuningProblem,
    x: Sequence[float] | np.ndarray,
    hits: Sequence[Mapping[str, Any]],
    space: Space | None = None,
) -> list[dict[str, Any]]:
    """Whether the cost still falls towards each bound the best point ``x`` lies on, and
    beyond it: for every hit of :func:`on_bounds` the cost at ``x`` with that parameter one
    step in from its bound — one decade on a log10 parameter (half its box if that is
    narrower), a tenth of its box on a linear one (a model parameter, a sigma-point
    setting) — and, on a log10 parameter that ``--widen-bounds`` would move (not a model
    parameter), :data:`~kftune.optim.widen.WIDEN_DECADES` out, at the bound a widening
    would give; the others held. A 1-D probe: one or two evaluations per hit and one at
    ``x``, in one batch. ``space``: the box that was searched (a widened one; default
    ``problem.space``).

    Widening a box only pays where the cost still falls beyond the bound. A q walked to
    the top of its box for a 0.02 % lower cost sits on a plateau, and the step in says so;
    but a plateau can end in a drop further out (msp on revs-250lm: flat from q_vx = 0.1
    to 10, 2 % lower at 100; BENCHMARKS.md, "Best points on a bound"), which only the
    step out sees. The edge is *flat* — a wider box will not pay — when the step out (where
    a widening would search) is not lower by the threshold, or diverges; where there is no
    step out (a linear or a model parameter, never widened), when the step in rose by less
    than the threshold. The step in is reported either way: a rise there with no drop
    beyond says the optimum lies at the bound or within a decade or two of it, where a
    widening could gain less than that rise. The threshold is :data:`FLAT_RISE`
    (:func:`flat_rise`; for a mean log-likelihood the 95 % likelihood-ratio rise of
    :func:`kftune.tuning.identify.rise_of`: the data cannot tell the points apart).

    Returns:
        each hit with ``"edge"``: ``{"value"`` (the value one step in), ``"step"``
        (``"one decade"`` …), ``"cost"`` (there; None: the filter diverged),
        ``"rise"`` (J − J* there; None where diverged), ``"beyond"`` (None, or
        ``{"value", "decades", "cost", "rise"}`` of the step out: ``rise`` < 0 where the
        cost is lower there), ``"best_cost"`` (J* at ``x``, evaluated with the probes),
        ``"threshold"``, ``"flat"``, ``"cost_kind"``}. J is the cost as tuned (covariance
        scale 1, whatever calibration ``problem.cov_scale`` holds).
    """
    from kftune.optim.widen import WIDEN_DECADES

    if not hits:
        return []
    space = problem.space if space is None else space
    names = space.names
    model_names = set(problem.parameterization.model_names)
    x = np.asarray(x, dtype=float)
    u = space.to_unit(x)
    points, plans = [x], []
    for hit in hits:
        i = names.index(hit["parameter"])
        p = space.params[i]
        if not p.log:
            du, step = 0.1, "a tenth of its box"
        elif p.width >= 2.0:
            du, step = 1.0 / p.width, "one decade"
        else:
            du, step = 0.5, "half its box"
        upper = hit["side"] == "upper"
        ui = u.copy()
        ui[i] = ui[i] - du if upper else ui[i] + du
        k_in, k_out = len(points), None
        points.append(space.from_unit(ui))
        if p.log and p.name not in model_names:  # where --widen-bounds would search
            out = x.copy()
            out[i] = hit["bound"] * 10.0 ** (WIDEN_DECADES if upper else -WIDEN_DECADES)
            k_out = len(points)
            points.append(out)
        plans.append((i, step, k_in, k_out))
    scale, problem.cov_scale = problem.cov_scale, 1.0
    try:
        evaluated = problem.evaluate_batch(np.array(points))
    finally:
        problem.cov_scale = scale
    costs = [float(getattr(e, "cost", math.inf)) for e in evaluated]
    j_best = costs[0]
    threshold = flat_rise(problem, j_best)

    def rise(k: int) -> float | None:
        return costs[k] - j_best if math.isfinite(costs[k]) else None

    probed = []
    for hit, (i, step, k_in, k_out) in zip(hits, plans):
        beyond = None
        r_in = rise(k_in)
        if k_out is not None:
            r_out = rise(k_out)
            beyond = {
                "value": float(points[k_out][i]),
                "decades": WIDEN_DECADES,
                "cost": costs[k_out] if math.isfinite(costs[k_out]) else None,
                "rise": r_out,
            }
        probed.append(
            {
                **hit,
                "edge": {
                    "value": float(points[k_in][i]),
                    "step": step,
                    "cost": costs[k_in] if math.isfinite(costs[k_in]) else None,
                    "rise": r_in,
                    "beyond": beyond,
                    "best_cost": j_best,
                    "threshold": threshold,
                    # a widening's reach is no lower (where it is measured), or else the
                    # last step gained little
                    "flat": (
                        beyond["rise"] is None or beyond["rise"] > -threshold
                        if beyond is not None
                        else r_in is not None and r_in < threshold
                    ),
                    "cost_kind": problem.cost_spec.kind,
                },
            }
        )
    return probed


def flat_rise(problem: TuningProblem, j_best: float) -> float:
    """The rise of the cost below which a step is flat (:func:`edge_probes`):
    :data:`FLAT_RISE`·|J*| for a cost that scales with the error, :data:`FLAT_RISE` for a
    logarithm (:data:`~kftune.tuning.cost.LOG_COSTS`), the 95 % likelihood-ratio rise
    χ²₁(0.95)/(2N) for a mean negative log-likelihood (nlpd, pem; N the scored samples)."""
    from kftune.tuning.identify import MEAN_NLL_KINDS, rise_of
    from kftune.tuning.runs import first_scored

    kind = problem.cost_spec.kind
    if kind in LOG_COSTS:
        return FLAT_RISE
    if kind in MEAN_NLL_KINDS:
        n_scored = sum(m.n - first_scored(m, problem.burn_in) for m in problem.manoeuvres)
        rise = rise_of(kind, max(n_scored, 1))
        if rise is not None:  # always, for these kinds
            return rise
    return FLAT_RISE * (abs(j_best) or 1.0)


def compare_budget(method: str) -> int | None:
    """``compare``'s budget of a method when none is given: the paper's (GA 225 = 15 × 15,
    TSBO 40 = MAX_PE) and 40 for every other search, so that the model-based methods are
    compared on the paper's budget (``kftune tune`` gives TR-BO 100 by default); None for
    manual (its number of points)."""
    return None if method == "manual" else {"ga": 225}.get(method, 40)


@dataclass(frozen=True)
class CompareSettings:
    """Settings of :func:`run_compare`.

    Attributes:
        methods: methods in report order (default: the paper's four and kftune's default
            tuner, :data:`COMPARE_METHODS`).
        seed: drives every method's randomness.
        budgets: method → evaluation budget, overriding :func:`compare_budget` (GA 225 =
            15 × 15, manual its points, every other method 40 = MAX_PE, TR-BO included).
        cost: the cost (default: paper Eq. 14 with W = (5, 1, 1)).
        parameterization: what is tuned (default: the three Q entries, log10 in [1e-10, 1]).
        workers: processes per cost evaluation (1: serial).
        burn_in: [s] start of each manoeuvre left out of cost and KPIs (see
            :class:`~kftune.tuning.problem.TuningProblem`); 0 = the paper.
        slice_parameter: the parameter of the Fig. 2 cost slice (paper: the Vy noise);
            None: ``q_vy`` where the model has it, else the first tuned parameter.
        figure_kinds: manoeuvre kinds whose first test manoeuvre gets a β figure (Figs. 8–10).
        method_options: method → extra optimiser options.
        model, filter: the filter's model (a built-in name or a model file) and ``"ukf"`` /
            ``"ekf"``. A model without the sideslip output ``beta`` (or data without
            ``beta_ref``) is reported by its channel RMSEs (:func:`scored_channels`).
        r0: measurement-noise variances of measurements the dataset has no estimate for.
    """

    methods: tuple[str, ...] = COMPARE_METHODS
    seed: int = 0
    budgets: Mapping[str, int] = field(default_factory=dict)
    cost: CostSpec = field(default_factory=CostSpec)
    parameterization: NoiseParameterization = field(default_factory=NoiseParameterization)
    workers: int = 1
    burn_in: float = 0.0
    slice_parameter: str | None = None
    figure_kinds: tuple[str, ...] = ("skidpad", "slalom", "j-turn")
    method_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    model: str = "single-track"
    filter: str = "ukf"
    r0: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise ConfigError(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
        if not self.methods:
            raise ConfigError("compare needs at least one method")
        if len(set(self.methods)) != len(self.methods):
            raise ConfigError(f"methods listed twice: {list(self.methods)}")
        for m, b in self.budgets.items():
            if not (isinstance(b, int) and b >= 1):
                raise ConfigError(f"budget for {m!r} must be an integer >= 1, got {b!r}")


def figure_manoeuvres(dataset: Dataset, kinds: Sequence[str], sideslip: bool = True) -> list[str]:
    """Test manoeuvres shown in the β figures: per kind, the test manoeuvre with the largest
    reference sideslip (where tuning matters most, cf. paper Figs. 8–10); for a dataset
    without those kinds (e.g. segments of a recording), the test manoeuvre with the largest
    reference sideslip. ``sideslip=False`` (another model's channel figures): per kind the
    first test manoeuvre, else the first test manoeuvre."""
    test = dataset.test or dataset.manoeuvres
    if not sideslip:
        firsts = [next((m.name for m in test if m.kind == k), None) for k in kinds]
        return [n for n in firsts if n is not None] or [test[0].name]

    def peak(m: Manoeuvre) -> float:
        return float(np.max(np.abs(m.beta_ref)))

    picked = [
        max(of_kind, key=peak).name for k in kinds if (of_kind := [m for m in test if m.kind == k])
    ]
    return picked or [max(test, key=peak).name]


def require_success(result: OptimizeResult, method: str) -> tuple[np.ndarray, float]:
    """The best point and cost of ``result`` (a run of ``method``): (d,) natural units, J.
    Raises :class:`~kftune.errors.RunFailedError` if every evaluation failed, with the count
    and the reasons grouped by kind (:func:`~kftune.tuning.runs.failure_kinds`)."""
    if result.x is None or result.fun is None:
        kinds = failure_kinds(r.reason for r in result.history)
        raise RunFailedError(
            f"every evaluation of {method!r} failed ({result.n_failed} of {result.n_evals}): "
            + ("; ".join(f"{kind} ({n})" for kind, n in kinds) or "no evaluation ran")
            + "; leave the method out or widen its search space"
        )
    return result.x, float(result.fun)


def sideslip_report(model: StateSpaceModel, dataset: Dataset) -> bool:
    """Whether ``compare`` reports the paper's sideslip KPIs and β figures: the model has
    the output ``beta`` and the measurements ``r`` and ``ay``, and the data have the
    reference ``beta_ref``.

    Raises:
        MissingChannelError: some manoeuvres have ``beta_ref`` and others do not.
    """
    if "beta" not in model.outputs or not {"r", "ay"} <= set(model.measurement_names):
        return False
    if not any(m.has("beta_ref") for m in dataset.manoeuvres):
        return False
    for m in dataset.manoeuvres:  # before anything is written or run
        m.require(["beta_ref"], "compare (its sideslip KPIs and β figures)", "a reference channel")
    return True


def scored_channels(model: StateSpaceModel, dataset: Dataset, cost: CostSpec) -> dict[str, str]:
    """The channels ``compare`` scores a model without the sideslip report by, with their
    units: the cost's channels (a measurement against the measured channel, any other
    channel against ``<channel>_ref``), or every measurement for a cost without a
    reference (nis, pem, msp). A unit is the model's for a measurement or state, else the
    unit the dataset declares for ``<channel>_ref`` ("" if none)."""
    names = cost.channels if cost.kind in ("nrmse", "nlpd", "crps") else model.measurement_names
    return channel_units(model, dataset, names)


def channel_units(model: StateSpaceModel, dataset: Dataset, names: Sequence[str]) -> dict[str, str]:
    """Channel → unit of scored channels: the model's for a measurement or state, else the
    unit the dataset declares for ``<channel>_ref`` ("" if none)."""
    units = {
        **dict(zip(model.state_names, model.state_units)),
        **dict(zip(model.measurement_names, model.measurement_units)),
    }
    return {c: units.get(c) or dataset.units.get(f"{c}_ref", "") for c in names}


def reference(model: StateSpaceModel, m: Manoeuvre, channel: str) -> np.ndarray:
    """(N,) what ``channel`` is scored against: the measured channel for a measurement of
    ``model``, else the reference ``<channel>_ref``."""
    return m.channel(channel if channel in model.measurement_names else f"{channel}_ref")


def method_run(
    key: str,
    result: OptimizeResult,
    problem: TuningProblem,
    splits: Mapping[str, Sequence[Manoeuvre]],
    channels: Sequence[str] | None = None,
) -> tuple[MethodRun, dict[str, dict[str, np.ndarray]]]:
    """Evaluate a tuning run's best point on each split.

    ``channels``: score these channels (:func:`~kftune.tuning.problem.assess`) instead of
    the sideslip KPIs.

    Each split's consistency (pooled over its manoeuvres, with the points of the
    reliability figure: :func:`~kftune.tuning.deploy.consistency_docs`) goes in
    ``MethodRun.consistency``: of the calibrated filter, as ``kftune tune`` deploys it (its
    covariances c times larger, c fitted on the problem's training manoeuvres:
    :func:`~kftune.tuning.calibrate.calibrate`; the estimate, and so every KPI, is the
    same); the calibration's record in ``extra["calibration"]`` (None where it could not
    be fitted: the filter as tuned then, and why in ``extra["calibration_failed"]``). The
    manual rule of thumb is calibrated alike, with its own c: it is a baseline of accuracy,
    which no calibration moves, and its σ is compared as it would be deployed.

    Returns:
        (the :class:`MethodRun`, manoeuvre → β estimate [rad] ``beta_<key>`` for every
        manoeuvre; with ``channels``, their estimates ``<channel>_<key>`` instead).
    """
    x, best_cost = require_success(result, key)
    # time = what the optimiser and the evaluations took (stored in the study, so a resumed
    # run reports the same as an uninterrupted one; the study's own I/O, a few fsyncs a
    # step, is left out: it depends on the disk, see benchmarks/study_io.py)
    steps = np.array([r.t_propose + r.t_eval for r in result.history])
    metrics: dict[str, dict[str, dict[str, float]]] = {}
    averages: dict[str, dict[str, float]] = {}
    consistency: dict[str, dict[str, Any] | None] = {}
    betas: dict[str, dict[str, np.ndarray]] = {}
    calibration, calibration_failed = _calibration(problem, x)
    scale = problem.cov_scale
    problem.cov_scale = 1.0 if calibration is None else calibration["factor"]
    try:
        for split, manoeuvres in splits.items():
            if not manoeuvres:
                continue
            per, runs = assess(problem, x, manoeuvres, channels)
            metrics[split] = per
            consistency[split] = consistency_docs(problem, manoeuvres, runs, RELIABILITY_LEVELS)[1]
            if channels is None:
                averages[split] = average_kpis(per.values())
            else:
                averages[split] = average_kpis(per.values(), [f"rmse_{c}" for c in channels])
            by_name = {m.name: m for m in manoeuvres}
            for name, res in runs.items():
                if channels is None:
                    betas[name] = {f"beta_{key}": model_output(res, "beta")}
                    continue
                estimate = problem.cost_spec.estimate
                betas[name] = {
                    f"{c}_{key}": channel_estimate(by_name[name], res, c, estimate)[0]
                    for c in channels
                }
    finally:
        problem.cov_scale = scale
    q, r_diag, ukf = problem.decode(x)
    run = MethodRun(
        key=key,
        label=LABELS.get(key, key),
        params=dict(result.params or {}),
        best_cost=best_cost,
        n_evals=result.n_evals,
        wall_time_s=float(steps.sum()),
        history_cost=[math.nan if r.value is None else float(r.value) for r in result.history],
        history_time_s=np.cumsum(steps).tolist(),
        metrics=metrics,
        averages=averages,
        consistency=consistency,
        extra={
            "q": q.tolist(),
            "r": r_diag.tolist(),
            "ukf": {"alpha": ukf.alpha, "beta": ukf.beta, "kappa": ukf.kappa},
            "n_failed": result.n_failed,
            "status": result.status,
            "stage": [r.stage for r in result.history],
            "acquisition": [r.acquisition for r in result.history],
            "failures": [
                {"number": r.number, "reason": r.reason} for r in result.history if not r.ok
            ],
            "failure_kinds": [  # the reasons grouped, as the report's note gives them
                [kind, count]
                for kind, count in failure_kinds(r.reason for r in result.history if not r.ok)
            ],
            "on_bounds": _probed_bounds(problem, result),
            "options": result.options,  # every option, defaults included (e.g. TSBO's mode)
            "calibration": calibration,
            "calibration_failed": calibration_failed,
        },
    )
    return run, betas


def _probed_bounds(problem: TuningProblem, result: OptimizeResult) -> list[dict[str, Any]]:
    """:func:`on_bounds` of ``result``, each hit with the cost one step in from its bound
    and beyond it (:func:`edge_probes`), so that the report can say where a wider box could
    help; the hits alone where the probes could not run (the report then says only where
    the point lies)."""
    hits = on_bounds(result)
    if not hits or result.x is None:
        return hits
    try:
        return edge_probes(problem, result.x, hits, Space.from_dict(result.space))
    except (KftuneError, ValueError):
        return hits


def _calibration(
    problem: TuningProblem, x: np.ndarray | None
) -> tuple[dict[str, Any] | None, str | None]:
    """(the record of the covariance scale fitted on ``problem``'s (training) manoeuvres at
    ``x`` (:meth:`kftune.tuning.calibrate.Calibration.as_dict`), None; or None, why it
    could not be fitted: a diverged run, nothing to fit on)."""
    from kftune.tuning.calibrate import CalibrationError, calibrate

    if x is None:
        return None, "no tuned point"
    try:
        return calibrate(problem, x).as_dict("train"), None
    except (CalibrationError, ValueError) as exc:
        return None, str(exc)


def cost_slice(
    problem: TuningProblem,
    x_best: np.ndarray,
    parameter: str,
    *,
    n_grid: int = 41,
    n_samples: int = 9,
    seed: int = 0,
    through: str = "best",
) -> dict[str, Any]:
    """Paper Fig. 2: the cost along one parameter through ``x_best``, with GP and tSP fits.
    ``through`` names the method whose optimum ``x_best`` is (for the captions).

    The cost is evaluated densely on ``n_grid`` points; both surrogates are fitted on
    ``n_samples`` evenly spaced ones and predicted on the whole grid (the parameter's unit
    coordinate is the surrogate input). Failed evaluations are left out of the fits.
    """
    space = problem.space
    if parameter not in space.names:
        raise ConfigError(f"slice parameter {parameter!r} is not one of {list(space.names)}")
    j = space.names.index(parameter)
    u_best = space.to_unit(x_best)
    u_grid = np.linspace(0.0, 1.0, n_grid)
    grid, cost = [], []
    for u in u_grid:
        uu = u_best.copy()
        uu[j] = u
        x = space.from_unit(uu)
        grid.append(float(x[j]))
        try:
            cost.append(problem(x))
        except Exception:  # a diverged filter on the slice: a gap in the curve
            cost.append(math.nan)
    cost_arr = np.asarray(cost)
    idx = np.unique(np.round(np.linspace(0, n_grid - 1, n_samples)).astype(int))
    idx = idx[np.isfinite(cost_arr[idx])]
    fits = {}
    for name in ("gp", "tsp"):
        model = make_surrogate(name, seed=seed).fit(u_grid[idx, None], cost_arr[idx])
        pred = model.predict(u_grid[:, None])
        fits[name] = {"mean": pred.mean.tolist(), "std": pred.std.tolist()}
    return {
        "parameter": parameter,
        "through": through,
        "log_scale": space.params[j].log,
        "grid": grid,
        "cost": cost_arr.tolist(),
        "sample_index": idx.tolist(),
        "fits": fits,
    }


def run_compare(
    dataset: Dataset,
    out_dir: str | Path,
    settings: CompareSettings | None = None,
    *,
    resume: bool = False,
    force: bool = False,
    progress: bool | None = None,
    command: str | None = None,
) -> ExperimentResults:
    """Run the comparison and store its results in ``out_dir`` (``results.json``,
    ``traces.npz`` and one SQLite study per method under ``studies/``).

    With ``resume=True`` the stored studies are continued: finished evaluations are not
    repeated, and the results equal those of an uninterrupted run. ``force=True`` deletes
    stored studies and starts afresh; without either, existing studies are an error (no
    finished evaluation is thrown away by accident).
    """
    settings = settings or CompareSettings()
    if not dataset.train:
        raise ConfigError(f"dataset {dataset.name!r} has no training manoeuvres")
    fs = filter_spec(settings.model, settings.filter, dataset.vehicle)
    sideslip = sideslip_report(fs.model, dataset)  # before anything is written or run
    check_units(fs.model, dataset)
    out = Path(out_dir)
    studies = out / "studies"
    existing = sorted(studies.glob("*.db"))
    if existing and not resume:
        if not force:
            raise ConfigError(
                f"{studies} already holds studies ({', '.join(p.name for p in existing)}); "
                "continue them with the option --resume, or delete them and start afresh "
                "with the option --force"
            )
        # --force deletes the studies kftune made (by content), no other file
        ours = [p for p in existing if is_study(p)]
        taken = {f"{file_stem(m)}.db" for m in settings.methods}
        clash = [p for p in existing if p not in ours and p.name in taken]
        if clash:
            raise ConfigError(
                f"{clash[0]} is not a kftune study, and --force deletes only the studies "
                f"kftune made; move it elsewhere (a study of that method goes there)"
            )
        for study in ours:
            for p in study_files(study):
                p.unlink(missing_ok=True)
    studies.mkdir(parents=True, exist_ok=True)
    par = settings.parameterization
    if par.states != fs.model.state_names:
        par = replace(par, states=fs.model.state_names, measurements=fs.model.measurement_names)
    problem = TuningProblem(
        dataset.train,
        dataset.vehicle,
        default_r0(fs.model, dataset, settings.r0),
        cost=settings.cost,
        parameterization=par,
        workers=settings.workers,
        burn_in=settings.burn_in,
        model=fs.spec,
        filter=fs.filter,
    )
    channels = None if sideslip else scored_channels(fs.model, dataset, settings.cost)
    splits = {"train": dataset.train, "test": dataset.test}
    shown = figure_manoeuvres(dataset, settings.figure_kinds, sideslip)
    runs: list[MethodRun] = []
    refs = {"beta": "beta_ref"} if channels is None else {c: f"{c}_ref" for c in channels}
    traces: dict[str, dict[str, np.ndarray]] = {
        name: {
            "t": dataset[name].t,
            **{r: reference(fs.model, dataset[name], c) for c, r in refs.items()},
        }
        for name in shown
    }
    with problem:
        # one untimed evaluation first, so no method's timing includes loading the compiled
        # kernel from numba's cache (or compiling it) and starting worker processes
        announce(problem.compile_note(), progress)
        with contextlib.suppress(FilterDivergedError):  # the manual run will record it
            problem(manual_point(problem.parameterization))
        for method in settings.methods:
            storage = studies / f"{file_stem(method)}.db"  # a registry name: unchanged
            budget = settings.budgets.get(method, compare_budget(method))
            options = settings.method_options.get(method)
            # a joint tuning with TR-BO runs in two stages, as tune's (the first one's study
            # beside the method's: studies/trbo.noise-only.db)
            stages = staging(problem, method, budget, options=options, storage=storage)
            first = noise_stage_storage(storage)
            result = tune(
                problem,
                method,
                budget=budget,
                seed=settings.seed,
                storage=storage,
                resume=resume and (storage.exists() or (first is not None and first.exists())),
                progress=progress,
                options=options,
            )
            run, betas = method_run(
                method, result, problem, splits, None if channels is None else list(channels)
            )
            if stages is not None:
                run.extra["stages"] = {
                    "total": stages.total,
                    "noise_budget": stages.noise_budget,
                    "joint_budget": stages.joint_budget,
                }
            if (
                problem.parameterization.model_names
                and method != "manual"
                and result.x is not None  # always: method_run refused a run without one
            ):
                from kftune.tuning.identify import identify_problem

                # whether the data determine the tuned model parameters: the report's
                # identifiability section (a profile of ≤ 10 evaluations each, one per pair)
                run.extra["identifiability"] = identify_problem(problem, result.x).to_dict()
            runs.append(run)
            for name in shown:
                traces[name].update(betas[name])
        best_key = next(
            (m for m in (DEFAULT_METHOD, "tsbo-tsp") if m in settings.methods), runs[-1].key
        )
        best = next(r for r in runs if r.key == best_key)
        x_best = np.array([best.params[n] for n in problem.space.names])
        sliced = settings.slice_parameter
        if sliced is None:
            names = problem.space.names
            sliced = "q_vy" if "q_vy" in names else names[0]
        sl = cost_slice(problem, x_best, sliced, seed=settings.seed, through=best.label)
    meta = {
        "dataset": {
            "name": dataset.name,
            "n_train": len(dataset.train),
            "n_test": len(dataset.test),
            "samples_train": sum(m.n for m in dataset.train),
            "samples_test": sum(m.n for m in dataset.test),
            "vehicle": None if dataset.vehicle is None else dataset.vehicle.name,
        },
        "manoeuvres": {m.name: {"kind": m.kind, "split": m.split} for m in dataset.manoeuvres},
        "filter": f"{problem.filter.upper()} on model {problem.model.name!r}"
        + (f" ({problem.model_spec})" if problem.model_spec != problem.model.name else ""),
        "cost": _describe_cost(settings.cost, None if sideslip else problem.model),
        "parameters": ", ".join(
            f"{p.name} ∈ [{p.low:g}, {p.high:g}] ({p.scale})" for p in problem.space.params
        ),
        "R": "["
        + ", ".join(f"{v:.3g}" for v in problem.r0)
        + f"] ({', '.join(problem.model.measurement_names)} variances)",
        "seed": settings.seed,
        "burn_in_s": settings.burn_in,
        "budgets": {  # a two-stage joint tuning: both stages
            r.key: r.n_evals + r.extra.get("stages", {}).get("noise_budget", 0) for r in runs
        },
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "kftune_version": __version__,
        "command": command,
        "dataset_fingerprint": dataset_fingerprint(dataset),
        "method_options": {r.key: r.extra["options"] for r in runs},
        "packages": package_versions(),
        "machine": machine(),
    }
    if channels is not None:  # absent: the sideslip report (results as before)
        meta["scored_channels"] = channels
    par = problem.parameterization
    if par.model_names:  # absent: a noise-only comparison (results as before)
        units = dict(zip(problem.model.param_names, problem.model.param_units))
        meta["model_parameters"] = {
            n: {"start": par.model_start[n], "unit": units[n]} for n in par.model_names
        }
    results = ExperimentResults(meta=meta, methods=runs, cost_slice=sl, traces=traces)
    results.save(out)
    return results


def _describe_cost(cost: CostSpec, model: StateSpaceModel | None = None) -> str:
    """The cost in words; ``model``: another model than the sideslip report's (its
    measurements named instead of r, ay, vx)."""
    m = 3 if model is None else len(model.measurement_names)
    if cost.kind == "nis":
        return f"NIS consistency |log(mean NIS / {m})| (Chen et al. 2018)"
    if cost.kind == "pem":
        return "innovation negative log-likelihood per sample (prediction-error method)"
    if cost.kind == "msp" and model is not None:
        return "multi-step prediction error of the measured channels"
    if cost.kind == "nlpd":
        terms = " + ".join(f"{w:g}·NLPD_{c}" for c, w in cost.weights.items() if w > 0)
        return f"J = {terms} (mean −log N(ref; est, σ²) per sample, nats)"
    if cost.kind == "crps":
        terms = " + ".join(f"{w:g}·CRPS_{c}" for c, w in cost.weights.items() if w > 0)
        return f"J = {terms} (mean Gaussian CRPS per sample / the largest |X|)"
    terms = " + ".join(f"{w:g}·E_{c}" for c, w in cost.weights.items() if w > 0)
    measured = "r, ay, vx" if model is None else ", ".join(model.measurement_names)
    scored = (
        f"{measured} from the posterior h(x⁺)"
        if cost.estimate == "posterior"
        else f"{measured} from the one-step prediction"
    )
    if cost.normalise == "dataset":
        return f"J = {terms} (Eq. 14, RMSE over all manoeuvres / the largest |X|; {scored})"
    return f"J = {terms} (paper Eq. 14–15, pooled NRMSE; {scored})"
