"""``kftune study``: look at one study (the SQLite file of ``tune --storage``).

``study show STUDY`` prints its settings, every evaluation (number, parameters, cost,
best so far, state, why it failed), the best point and the failed ones grouped by reason;
``--json`` prints the same as one JSON object. ``study plot STUDY -o DIR`` draws the cost
against evaluations with the best so far (convergence.png) and each parameter against
evaluations (parameters.png); of the joint stage of a two-stage joint tuning, they say that
its evaluation 0 is the best point of the first, noise-only stage and name that stage's
study (``<stem>.noise-only.db``), which ``study plot`` draws in turn. ``study export STUDY
--optuna FILE.db`` writes the study into Optuna's storage, so that ``optuna-dashboard
sqlite:///FILE.db`` shows its history, slices and parameter importances (needs the
``peers`` extra).

The study is only read, never written: a study that a ``tune`` run holds open can be
looked at while it runs.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from kftune.cli._common import emit_json
from kftune.cli.exit_codes import EXIT_OK
from kftune.cli.outputs import output_dir, output_file, same_file, write_output
from kftune.errors import ConfigError

#: Figures ``study plot`` writes into its folder.
PLOT_FILES = ("convergence.png", "parameters.png")


def register(subparsers: Any) -> None:
    """Add ``study`` and its verbs."""
    parser = subparsers.add_parser(
        "study",
        help="show, plot or export one study (tune --storage's file)",
        description=(__doc__ or "").replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    verbs = parser.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True

    show = verbs.add_parser("show", help="print the evaluations, the best one and the failures")
    show.add_argument("study", type=Path, help="study file (tune --storage)")
    show.add_argument("--json", action="store_true", help="print one JSON object instead")
    show.set_defaults(func=run_show)

    plot = verbs.add_parser("plot", help="draw the convergence and the parameters over time")
    plot.add_argument("study", type=Path, help="study file (tune --storage)")
    plot.add_argument(
        "--out", "-o", type=Path, required=True, help="folder for convergence.png, parameters.png"
    )
    plot.set_defaults(func=run_plot)

    export = verbs.add_parser(
        "export", help="write the study into Optuna's storage (for optuna-dashboard)"
    )
    export.add_argument("study", type=Path, help="study file (tune --storage)")
    export.add_argument(
        "--optuna",
        type=Path,
        required=True,
        metavar="FILE.db",
        help="new SQLite file of Optuna's storage (refused if it exists); then "
        "optuna-dashboard sqlite:///FILE.db",
    )
    export.add_argument(
        "--name", help="the Optuna study's name (default: the study file's name without .db)"
    )
    export.set_defaults(func=run_export)


# ---------------------------------------------------------------------- reading
def summarise(stored: Any) -> dict[str, Any]:
    """A stored study as JSON-ready data.

    Args:
        stored: a :class:`kftune.optim.study.StoredStudy`.

    Returns:
        ``study``, ``method``, ``seed``, ``budget``, ``objective`` (its summary or None),
        ``parameters`` (name, low, high, scale), counts (``finished``, ``complete``,
        ``failed``, ``running``), ``best`` (number, cost, params; None if nothing
        succeeded), ``trials`` (number, state, cost, best_so_far, params, reason) in order
        and ``failures`` (reason kind, count, trial numbers), most frequent first;
        ``first_stage``: the study of a two-stage joint tuning's first, noise-only stage
        where it lies beside this one (``<stem>.noise-only<suffix>``), else None.
    """
    from kftune.experiment import noise_stage_storage
    from kftune.tuning.runs import failure_kinds

    settings = stored.settings
    records = stored.records
    best_so_far: list[float | None] = []
    best = None
    for rec in records:
        if rec.ok and (best is None or rec.value < best.value):
            best = rec
        best_so_far.append(None if best is None else best.value)
    kinds = failure_kinds(r.reason for r in records if not r.ok)
    by_kind: dict[str, list[int]] = {k: [] for k, _ in kinds}
    for rec in records:
        if not rec.ok:
            by_kind[failure_kinds([rec.reason])[0][0]].append(rec.number)
    objective = settings.get("objective")
    first = noise_stage_storage(stored.path)
    first_stage = str(first) if first is not None and first.is_file() else None
    return {
        "study": str(stored.path),
        "method": settings.get("method"),
        "seed": settings.get("seed"),
        "budget": settings.get("budget"),
        "objective": objective.get("summary") if isinstance(objective, dict) else None,
        "parameters": list((settings.get("space") or {}).get("params", [])),
        "finished": len(records),
        "complete": sum(r.ok for r in records),
        "failed": sum(not r.ok for r in records),
        "running": list(stored.running),
        "best": None
        if best is None
        else {"number": best.number, "cost": best.value, "params": dict(best.params)},
        "trials": [
            {
                "number": r.number,
                "state": r.state,
                "cost": r.value,
                "best_so_far": b,
                "params": dict(r.params),
                "reason": r.reason,
            }
            for r, b in zip(records, best_so_far)
        ],
        "failures": [{"reason": k, "count": n, "trials": by_kind[k]} for k, n in kinds],
        "first_stage": first_stage,
    }


def cost_label(objective: str | None) -> str:
    """The cost axis's label: which cost the study minimised, from its objective's summary
    (``"…, cost nrmse (dataset-normalised), …"`` → ``"cost J: nrmse, dataset-normalised"``;
    the paper's per-manoeuvre normalisation is the one the summary leaves unsaid); plain
    ``"cost J"`` for a study that records no objective."""
    import re

    found = re.search(r"(?:^|, )cost (\w+)(?: \((\w+)-normalised\))?", objective or "")
    if found is None:
        return "cost J"
    kind, normalise = found.groups()
    if normalise is None and kind == "nrmse":
        normalise = "manoeuvre"
    return f"cost J: {kind}" + (f", {normalise}-normalised" if normalise else "")


def not_a_study_hint(path: Path) -> str | None:
    """What to run instead where ``path`` is a file kftune wrote that is not a study: a
    tuned file (``tune -o``) holds the tuned point, not the evaluations. None otherwise.
    Reads at most the first 4 KiB, and only of a regular file."""
    import os
    import stat

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return None
    if b'"format": "kftune-tuned-' in head or b'"format":"kftune-tuned-' in head:
        return (
            f"{path} is a tuned file (tune -o): it holds the tuned point, not the evaluations; "
            f"see it with kftune evaluate --params {path} --split test, and the evaluations "
            "with kftune study show on the file tune wrote with --storage"
        )
    return None


def _read(path: Path) -> Any:
    from kftune.optim.study import StudyError, read_study

    try:
        return read_study(path)
    except StudyError:
        hint = not_a_study_hint(path)
        if hint is not None:
            raise ConfigError(hint) from None
        raise


def _num(v: float | None) -> str:
    return "—" if v is None else f"{v:.6g}"


def render_text(s: dict[str, Any]) -> str:
    """``study show``'s text: settings, the trial table (a failure's reason by its kind; the
    full reason is in ``--json``), the best point, the failures grouped by kind."""
    from kftune.tuning.runs import failure_kinds

    names = [p["name"] for p in s["parameters"]]
    lines = [
        f"study {s['study']}: method {s['method']}, seed {s['seed']}, budget {s['budget']}",
    ]
    if s["objective"]:
        lines.append(f"objective: {s['objective']}")
    box = ", ".join(
        f"{p['name']} in [{p['low']:g}, {p['high']:g}]"
        + (" log10" if p["scale"] == "log10" else "")
        for p in s["parameters"]
    )
    lines.append(f"parameters: {box}")
    if s.get("first_stage"):
        lines.append(
            f"first stage (noise only) of this joint tuning: {s['first_stage']} "
            "(kftune study show it)"
        )
    running = f", {len(s['running'])} running or cut off" if s["running"] else ""
    lines.append(
        f"{s['finished']} evaluations finished of {s['budget']}: {s['complete']} complete, "
        f"{s['failed']} failed{running}"
    )
    lines.append("")
    header = ["#", *names, "cost", "best so far", "state", "reason"]
    rows = [
        [
            str(t["number"]),
            *(_num(t["params"].get(n)) for n in names),
            _num(t["cost"]),
            _num(t["best_so_far"]),
            t["state"],
            failure_kinds([t["reason"]])[0][0] if t["state"] != "complete" else "",
        ]
        for t in s["trials"]
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header) - 1)]
    for r in [header, *rows]:
        lines.append(
            "  ".join(
                c.rjust(w) if i < len(header) - 2 else c.ljust(w)
                for i, (c, w) in enumerate(zip(r, widths))
            )
            + ("  " + r[-1] if r[-1] else "")
        )
    lines.append("")
    if s["best"] is None:
        lines.append("best: none (no evaluation completed)")
    else:
        b = s["best"]
        point = ", ".join(f"{n} = {b['params'][n]:.6g}" for n in names)
        lines.append(f"best: #{b['number']} cost {b['cost']:.6g} at {point}")
    for f in s["failures"]:
        shown = ", ".join(map(str, f["trials"][:10])) + (", …" if len(f["trials"]) > 10 else "")
        lines.append(f"failed: {f['count']} of {s['finished']}: {f['reason']} (#{shown})")
    return "\n".join(lines)


def run_show(args: argparse.Namespace) -> int:
    """Run ``kftune study show``."""
    s = summarise(_read(args.study))
    if args.json:
        emit_json(s)
    else:
        print(render_text(s))
    return EXIT_OK


# ---------------------------------------------------------------------- figures
def _figures(s: dict[str, Any]) -> dict[str, Any]:
    """The two figures of ``study plot`` (matplotlib Figures by file name)."""
    import matplotlib.pyplot as plt

    from kftune.report.plots import label_log_axis  # (it sets the Agg backend)

    trials = s["trials"]
    n = np.array([t["number"] for t in trials], dtype=float)
    ok = np.array([t["cost"] is not None for t in trials], dtype=bool)
    cost = np.array([np.nan if t["cost"] is None else t["cost"] for t in trials], dtype=float)
    best = np.array(
        [np.nan if t["best_so_far"] is None else t["best_so_far"] for t in trials], dtype=float
    )
    finite = cost[ok]
    log_y = finite.size > 0 and bool(np.all(finite > 0)) and finite.max() / finite.min() > 30

    # the axis ends above the first best and most costs, so that a few far-off points do
    # not squeeze the best so far into a flat line at the bottom; those are marked on top
    top = None
    if finite.size and not log_y:
        low = float(finite.min())
        high = max(float(best[np.isfinite(best)][0]), float(np.quantile(finite, 0.9)))
        top = high + 0.08 * (high - low) if high > low else None
    above = ok & (cost > top) if top is not None else np.zeros_like(ok)
    fig, ax = plt.subplots(figsize=(8.0, 4.0))
    shown = ok & ~above
    ax.plot(n[shown], cost[shown], "o", ms=3.5, color="0.55", label="cost of each evaluation")
    ax.step(n, best, where="post", color="C0", lw=2.0, label="best so far")
    if s["best"] is not None:
        ax.plot(
            [s["best"]["number"]],
            [s["best"]["cost"]],
            "*",
            ms=12,
            color="C3",
            label=f"best: #{s['best']['number']}, {s['best']['cost']:.4g}",
        )
    if log_y:
        ax.set_yscale("log")
    if top is not None:
        ax.set_ylim(top=top)
    if above.any():
        ax.plot(
            n[above],
            np.full(above.sum(), ax.get_ylim()[1]),
            "^",
            color="0.55",
            ms=6,
            clip_on=False,
            label=f"{_evaluations(int(above.sum()))} above the axis (cost > {top:.4g}), "
            "drawn at the top",
        )
    if (~ok).any():
        top = ax.get_ylim()[1]
        ax.plot(
            n[~ok],
            np.full((~ok).sum(), top),
            "x",
            color="C3",
            ms=6,
            clip_on=False,
            label=f"{_evaluations(int((~ok).sum()))} failed, drawn at the top",
        )
        ax.set_ylim(top=top)
    if log_y:  # its limits final: enough labels to read the best and the first costs
        y_low, y_high = ax.get_ylim()
        label_log_axis(ax.yaxis, y_low, y_high, vertical=True)
    ax.set_xlabel("evaluation")
    ax.set_ylabel(cost_label(s.get("objective")))
    stage = _first_stage_note(s)
    ax.set_title(
        f"{Path(s['study']).name}: {s['method']}, seed {s['seed']}"
        + (f"\n{stage}" if stage else ""),
        fontsize=10,
        pad=10,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    conv = fig

    params = s["parameters"]
    cols = min(3, max(1, len(params)))
    rows = math.ceil(len(params) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), squeeze=False)
    for k, p in enumerate(params):
        a = axes[k // cols][k % cols]
        v = np.array([t["params"].get(p["name"], np.nan) for t in trials], dtype=float)
        a.plot(n[ok], v[ok], "o", ms=3, color="C0", clip_on=False)  # points on a bound too
        if (~ok).any():
            a.plot(n[~ok], v[~ok], "x", ms=4, color="C3", clip_on=False)
        if s["best"] is not None:
            a.axhline(s["best"]["params"][p["name"]], color="C3", lw=1, ls="--")
        a.set_ylim(p["low"], p["high"])  # first: a parameter tried at one value only would
        if p["scale"] == "log10":  # give the log scale identical limits (a warning)
            a.set_yscale("log")
        a.set_title(p["name"], fontsize=9, pad=7)  # clear of the points on the upper bound
        a.set_xlabel("evaluation", fontsize=8)
        a.tick_params(which="both", labelsize=7)  # a log axis labels minor ticks too
        a.grid(alpha=0.3)
    for k in range(len(params), rows * cols):
        axes[k // cols][k % cols].set_visible(False)
    fig.suptitle(
        "parameters over the evaluations (x: failed; dashed: the best point; y: the search box)"
        + (f"\n{stage}" if stage else ""),
        fontsize=9,
    )
    fig.tight_layout()
    return {"convergence.png": conv, "parameters.png": fig}


def _first_stage_note(s: dict[str, Any]) -> str:
    """For the joint stage of a two-stage joint tuning (its first, noise-only stage's study
    ``s["first_stage"]`` lies beside it), what a reader of its figures must know: they draw
    this stage alone, and its evaluation 0 is the first stage's best point; ``""`` for
    any other study."""
    first = s.get("first_stage")
    if not first:
        return ""
    return (
        "the joint stage of a two-stage tuning: evaluation 0 is the best point of\n"
        f"its first, noise-only stage, drawn by kftune study plot {Path(first).name}"
    )


def _evaluations(n: int) -> str:
    """A count of evaluations in words: "1 evaluation", "3 evaluations" (a legend's
    "cost above the axis (3)" read as a threshold of 3)."""
    return f"{n} evaluation" + ("" if n == 1 else "s")


def run_plot(args: argparse.Namespace) -> int:
    """Run ``kftune study plot``."""
    from kftune.report.plots import render

    s = summarise(_read(args.study))
    out = output_dir(args.out, "--out")
    for name in PLOT_FILES:
        if same_file(out / name, args.study):
            raise ConfigError(
                f"--out {out}: {name} there is the study this command reads; choose another folder"
            )
        if (out / name).exists():
            output_file(out / name, "--out")
    out.mkdir(parents=True, exist_ok=True)
    for name, fig in _figures(s).items():
        write_output(out / name, render(fig), "--out", f"the study {args.study} is unchanged")
    print(f"figures written to {out}: {', '.join(PLOT_FILES)}")
    return EXIT_OK


# ---------------------------------------------------------------------- Optuna
def export_optuna(stored: Any, path: Path, name: str) -> int:
    """Write a stored study into a new Optuna SQLite storage; returns the trials written.

    Each finished evaluation becomes one trial in trial order: a complete one with its cost
    as the value (direction minimise), a failed one as ``FAIL`` with its point; running
    ones are left out. Distributions are ``FloatDistribution(low, high, log=…)`` with
    ``log`` for a log10 parameter; a value is clipped into its box (a log10 point can lie
    a rounding error outside it, which Optuna refuses). The kftune trial number, state,
    reason, stage and acquisition are user attributes (``kftune_*``). The file is written
    beside its target and renamed onto it when done, so a failure leaves no half export.

    Raises:
        ConfigError: Optuna is not installed (exit 3, as every missing optional package).
    """
    import contextlib
    import os
    import tempfile

    try:
        import optuna
    except ImportError:
        raise ConfigError(
            "study export --optuna needs the package 'optuna', which is not installed "
            "(pip install 'kftune[peers]' or pip install optuna)"
        ) from None
    from optuna.distributions import FloatDistribution
    from optuna.trial import TrialState, create_trial

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    params = stored.settings.get("space", {}).get("params", [])
    dists: dict[str, FloatDistribution] = {
        p["name"]: FloatDistribution(p["low"], p["high"], log=p["scale"] == "log10") for p in params
    }
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        storage = optuna.storages.RDBStorage(f"sqlite:///{tmp}")
        study = optuna.create_study(storage=storage, study_name=name, direction="minimize")
        study.set_user_attr("kftune_method", stored.settings.get("method"))
        study.set_user_attr("kftune_seed", stored.settings.get("seed"))
        study.set_user_attr("kftune_budget", stored.settings.get("budget"))
        for rec in stored.records:
            point = {n: min(max(float(rec.params[n]), d.low), d.high) for n, d in dists.items()}
            attrs = {
                "kftune_number": rec.number,
                "kftune_state": rec.state,
                "kftune_reason": rec.reason,
                "kftune_stage": rec.stage,
                "kftune_acquisition": rec.acquisition,
            }
            study.add_trial(
                create_trial(
                    state=TrialState.COMPLETE if rec.ok else TrialState.FAIL,
                    value=rec.value if rec.ok else None,
                    params=point,
                    distributions={**dists},  # as dict[str, BaseDistribution], optuna's hint
                    user_attrs=attrs,
                )
            )
        storage.engine.dispose()
        umask = os.umask(0o022)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # as a plain write would make it (mkstemp's is 0600)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return len(stored.records)


def run_export(args: argparse.Namespace) -> int:
    """Run ``kftune study export``."""
    stored = _read(args.study)
    path: Path = args.optuna
    if same_file(path, args.study):
        raise ConfigError(f"--optuna {path}: is the study this command reads; choose another name")
    if path.exists() or path.is_symlink():
        raise ConfigError(
            f"--optuna {path}: the file exists; an export writes a new Optuna storage "
            "(delete it first or choose another name)"
        )
    output_file(path, "--optuna")
    name = args.name or args.study.stem
    n = export_optuna(stored, path, name)
    left = f" ({len(stored.running)} running left out)" if stored.running else ""
    print(
        f"{n} trials of {args.study} written to {path} as Optuna study {name!r}{left}; "
        f"look at it with: optuna-dashboard sqlite:///{path}"
    )
    return EXIT_OK
