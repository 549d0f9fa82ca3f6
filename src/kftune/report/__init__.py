"""Reports: paper-style tables and figures from stored experiment results.

``write_report(results, directory)`` writes ``report.md``, ``figures/*.png`` and
``tables/*.csv``; it reads nothing but the results, so a report can always be rebuilt.
Results of the paper's sideslip problem get the paper's KPIs and β figures; results of any
other model (``meta["scored_channels"]``) the RMSE of each scored channel, with its unit,
and figures of those channels against their references.
"""

from __future__ import annotations

import json
import math
import re
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from kftune.data.io import file_stem
from kftune.report import plots
from kftune.report.results import ExperimentResults, MethodRun
from kftune.report.tables import (
    Table,
    consistency_split,
    consistency_table,
    cost_table,
    failure_lines,
    kpi_table,
    per_manoeuvre_table,
    relative_improvement,
    scored_channels,
)

__all__ = ["ExperimentResults", "MethodRun", "Table", "all_tables", "write_report"]


def all_tables(results: ExperimentResults) -> dict[str, Table]:
    """The report's tables by file stem."""
    tables = {"cost": cost_table(results)}
    splits = {s for m in results.methods for s in m.averages}
    for split in ("train", "test"):
        if split in splits:
            tables[f"kpi_{split}"] = kpi_table(results, split)
    if (pooled := consistency_split(results)) is not None:
        tables[f"consistency_{pooled}"] = consistency_table(results, pooled)
    tables["per_manoeuvre"] = per_manoeuvre_table(results)
    tables["parameters"] = _parameter_table(results)
    return tables


def _parameter_table(results: ExperimentResults) -> Table:
    names = list(dict.fromkeys(p for m in results.methods for p in m.params))
    rows = tuple(
        (m.label, *(float(m.params.get(p, math.nan)) for p in names)) for m in results.methods
    )
    return Table(title="Tuned parameters", header=("Method", *names), rows=rows)


#: What ``kftune tune`` deploys by default, for the captions of compare's TR-BO figures:
#: compare's TR-BO is a tuner beside the paper's, on their cost, space and budget.
TUNE_DEFAULT = (
    "the filter kftune tune deploys by default is tuned differently: the cost normalised "
    "over the dataset (--normalise dataset), R's diagonal tuned with Q, 100 evaluations"
)


def compare_setting(results: ExperimentResults, key: str) -> str:
    """How ``kftune compare`` ran method ``key``, from the results' ``meta``, in words: its
    cost, what it tuned and its evaluations (``"the paper's cost, Q alone, 40
    evaluations"``), so that a figure of compare's TR-BO is not read as the filter ``kftune
    tune`` deploys (whose cost, space and budget differ: :data:`TUNE_DEFAULT`)."""
    meta = results.meta
    cost = str(meta.get("cost", ""))
    if "paper Eq. 14–15" in cost:
        words = ["the paper's cost"]
    elif "RMSE over all manoeuvres" in cost:
        words = ["the NRMSE cost normalised over the dataset"]
    elif cost:
        words = [f"cost {cost.split(' (')[0]}"]
    else:
        words = []
    names = re.findall(r"(\w+) ∈", str(meta.get("parameters", "")))
    if names:
        others = [n for n in names if not n.startswith(("q_", "r_"))]
        tuned = ["Q"]
        if "r_scale" in names:
            tuned.append("a scale of R")
        elif any(n.startswith("r_") for n in names):
            tuned.append("R's diagonal")
        tuned += others
        words.append("Q alone" if tuned == ["Q"] else ", ".join(tuned) + " tuned")
    budget = (meta.get("budgets") or {}).get(key)
    if budget is None:
        budget = next((m.n_evals for m in results.methods if m.key == key), None)
    if budget is not None:
        words.append(f"{budget} evaluation" + ("" if budget == 1 else "s"))
    return ", ".join(words) or "compare's settings"


def write_report(results: ExperimentResults, directory: str | Path) -> Path:
    """Write the Markdown report with its figures and CSV tables.

    Returns:
        Path of ``report.md``.
    """
    out = Path(directory)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    (out / "tables").mkdir(parents=True, exist_ok=True)
    tables = all_tables(results)
    for stem, table in tables.items():
        table.write_csv(out / "tables" / f"{stem}.csv")

    keys = {m.key for m in results.methods}
    channels = scored_channels(results)  # None: the paper's sideslip report
    named = "β, yaw rate and ay" if channels is None else ", ".join(channels)
    figures: list[tuple[str, str, str]] = []  # (file, heading, caption)
    plots.save(plots.convergence(results), out / "figures" / "convergence.png")
    figures.append(
        (
            "convergence.png",
            "Convergence (cf. paper Fig. 6)",
            "Best training cost against cost evaluations and against wall time.",
        )
    )
    # what a user of kftune tune asks first: how much its default tuner gains over the
    # filter tuned by hand, manoeuvre by manoeuvre; then the paper's Fig. 7 (two tuners of
    # the paper against each other), kept for its reproduction
    if {"manual", "trbo"} <= keys and relative_improvement(results, "manual", "trbo"):
        setting = compare_setting(results, "trbo")
        heading = "TR-BO as kftune compare ran it against the manual filter"
        beta = ("rmse_beta",) if channels is None else None  # β alone: see plots.improvement
        plots.save(
            plots.improvement(
                results,
                "manual",
                "trbo",
                # wrapped: a joint comparison's setting is longer than a 6-inch figure
                heading=heading
                + "\n"
                + textwrap.fill(f"({setting}; not kftune tune's default)", 72),
                metrics=beta,
            ),
            out / "figures" / "improvement_trbo_test.png",
        )
        figures.append(
            (
                "improvement_trbo_test.png",
                f"{heading} per manoeuvre",
                "Relative RMSE improvement of the TR-BO-tuned filter over the manual one on "
                "every test manoeuvre: what tuning gains where, "
                + (
                    "for β (against its reference; yaw rate and ay are scored against their "
                    "measurements, which a filter that follows the gyro copies; every "
                    "RMSE is in `tables/per_manoeuvre.csv`). "
                    if channels is None
                    else f"for {named}. "
                )
                + f"TR-BO ran as compare runs it ({setting}), for a comparison with the "
                "paper's tuners on their terms; " + TUNE_DEFAULT + ".",
            )
        )
    if {"ga", "tsbo-tsp"} <= keys and relative_improvement(results):
        heading = "Paper Fig. 7: the paper's tuner TSBO-tSP against its GA baseline"
        plots.save(
            plots.improvement(results, heading=heading),
            out / "figures" / "improvement_test.png",
        )
        figures.append(
            (
                "improvement_test.png",
                "TSBO-tSP against GA per manoeuvre (paper Fig. 7)",
                "The paper's Fig. 7, reproduced: relative RMSE improvement of the "
                "TSBO-tSP-tuned filter over the GA-tuned one on every test manoeuvre, for "
                f"{named}. Neither is kftune tune's default, TR-BO"
                + (" (the figure above)." if "trbo" in keys else "."),
            )
        )
    stems: set[str] = set()
    for name in results.traces:
        prefix = "beta" if channels is None else "channels"
        stem = f"{prefix}_{file_stem(name)}.png"  # names come from a manifest: never a path
        while stem in stems:  # two names reduced to the same stem
            stem = stem.removesuffix(".png") + "_.png"
        stems.add(stem)
        shown = tuple(m.key for m in results.methods)  # every method, none left out
        kind = results.meta.get("manoeuvres", {}).get(name, {}).get("kind", "")
        labels = ", ".join(results.method(k).label for k in shown)
        if channels is not None:
            plots.save(plots.channel_traces(results, name, shown), out / "figures" / stem)
            figures.append(
                (
                    stem,
                    f"Estimated channels, {name}" + (f" ({kind})" if kind else ""),
                    f"{named} estimated by the filters tuned by {labels} against the "
                    "reference `<channel>_ref` (for a measurement, the measured channel), "
                    "and their errors.",
                )
            )
            continue
        plots.save(plots.beta_trace(results, name, shown), out / "figures" / stem)
        figures.append(
            (
                stem,
                f"Sideslip estimate, {name}"
                + (f" ({kind})" if kind else "")
                + " (cf. paper Figs. 8–10)",
                f"β estimated by the filters of {labels} against the reference (top), "
                "and each tuned filter's error in a panel of its own with the manual "
                "filter's in grey behind it.",
            )
        )
    if results.cost_slice:
        plots.save(plots.cost_slice(results), out / "figures" / "cost_slice.png")
        figures.append(
            (
                "cost_slice.png",
                "Surrogate fits of the cost (cf. paper Fig. 2)",
                "A one-dimensional slice of the training cost through the "
                f"{results.cost_slice.get('through', 'best')} optimum, "
                "with GP and Student-t process fits to a few of its points. Where the two "
                "curves coincide they do so by construction: for equal hyperparameters the "
                "tSP's posterior mean is the GP's and only its variance is rescaled "
                "(Shah et al. 2014); the figure prints the largest difference.",
            )
        )

    md = [f"# kftune report — {results.meta.get('dataset', {}).get('name', 'dataset')}", ""]
    md += _meta_lines(results.meta)
    for stem in ("cost", "kpi_train", "kpi_test", "consistency", "parameters"):
        if stem == "consistency":
            md += _consistency_lines(results, tables, out)
        if stem in tables:
            md += [f"## {tables[stem].title}", "", tables[stem].to_markdown(), ""]
            if stem.startswith("kpi_"):
                md += [MAE_NOTE if channels is None else RMSE_NOTE, ""]
            if stem == "cost" and (failed := failure_lines(results)):
                md += [FAILED_NOTE, "", *failed, ""]
            tuned = results.meta.get("model_parameters")
            tuned = tuned if isinstance(tuned, dict) else None
            if stem == "parameters" and (note := parameter_note(tables[stem].header[1:], tuned)):
                md += [note, ""]
    md += _bound_lines(results)
    md += _identifiability_lines(results, out)
    md += _option_lines(results)
    for file, heading, caption in figures:
        md += [f"## {heading}", "", caption, "", f"![{heading}](figures/{file})", ""]
    if not results.traces and channels is None:
        md += ["β figures (cf. paper Figs. 8–10): not available, the stored results have no "
               "β traces (`traces.npz`).", ""]  # fmt: skip
    elif not results.traces:
        md += ["Channel figures: not available, the stored results have no traces "
               "(`traces.npz`).", ""]  # fmt: skip
    md += [
        "Per-manoeuvre metrics of every method: `tables/per_manoeuvre.csv`; "
        "all numbers: `results.json`.",
        "",
    ]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path


#: Under the cost table, before the methods whose evaluations failed.
FAILED_NOTE = (
    "Failed: evaluations whose cost could not be computed (the filter diverged, or the "
    "evaluation raised); the best cost is over the others, and each failure is kept in "
    "the method's study and in `results.json` (`failures`, `failure_kinds`)."
)

#: How to read the consistency table, under it.
CONSISTENCY_NOTE = (
    "Whether the standard deviations σ that each tuned filter states can be trusted (for "
    "gating, or fusing with another estimator): the share of the errors against the "
    "reference inside ±1σ and ±1.96σ (68.3 % and 95 % when σ is right), the mean NEES, "
    "err²/σ² (1 when right; above its band σ is too small, by about √NEES), and the mean "
    "NIS of the m measurements (m when right). Each band holds the mean with 95 % "
    "probability for a consistent filter; the NEES band counts the errors' effective number "
    "of independent samples (successive errors are correlated). A filter tuned for accuracy "
    "alone can be accurate and still state a σ several times too small; "
)
#: The note's end, by what the results record of each filter's calibration.
CALIBRATED_NOTE = (
    "{which} calibrated as kftune tune deploys it: its covariances multiplied by the factor "
    "c fitted on the training manoeuvres, which leaves its estimate, and every accuracy "
    "figure above, unchanged."
)


def calibration_note(results: ExperimentResults) -> str:
    """What the consistency table's filters are, from each run's record: calibrated (a
    factor c), not calibrated and why (``calibration_failed``), or results from before
    the calibration (no record: the filters as tuned)."""
    runs = [m for m in results.methods if m.consistency]
    done = [m for m in runs if isinstance(m.extra.get("calibration"), dict)]
    if not done:
        return "the filters here are shown as tuned: these results record no calibration."
    if len(done) == len(runs):
        return CALIBRATED_NOTE.format(which="each filter here is")
    failed = "; ".join(
        f"{m.label}: {m.extra.get('calibration_failed') or 'no calibration recorded'}"
        for m in runs
        if m not in done
    )
    return (
        CALIBRATED_NOTE.format(which="each filter with a factor c here is")
        + f" Not calibrated (shown as tuned): {failed}."
    )


def _consistency_lines(
    results: ExperimentResults, tables: dict[str, Table], out: Path
) -> list[str]:
    """The consistency table with its note, and its reliability figure (written to
    ``out/figures``); for results that do not record consistency, a line saying so."""
    split = consistency_split(results)
    if split is None:
        return [
            "Consistency of the tuned filters (whether their standard deviations can be "
            "trusted): not recorded in these results, written by a kftune that did not "
            "measure it; run `kftune compare` again to have it.",
            "",
        ]
    table = tables[f"consistency_{split}"]
    note = CONSISTENCY_NOTE + calibration_note(results)
    md = [f"## {table.title}", "", table.to_markdown(), "", note, ""]
    if not any((d := m.consistency.get(split)) and d.get("reliability") for m in results.methods):
        return md
    plots.save(plots.reliability(results, split), out / "figures" / "reliability.png")
    heading = "Reliability of the stated uncertainty"
    return [
        *md,
        f"## {heading}",
        "",
        "Observed share of the errors inside ±z·σ (y) against the share the filter claims "
        "(x, the nominal coverage of ±z·σ), pooled over the "
        + ("test" if split == "test" else "training")
        + " manoeuvres. On the diagonal σ is right; below it σ is too small (the intervals "
        "hold fewer errors than they claim), above it too large.",
        "",
        f"![{heading}](figures/reliability.png)",
        "",
    ]


def _bound_lines(results: ExperimentResults) -> list[str]:
    """Which methods' best points lie on a bound of the search box (``extra["on_bounds"]``,
    written by ``kftune compare``), with what the cost gained over the last step up to the
    bound where it was measured (``"edge"``, :func:`kftune.experiment.edge_probes`): where
    it is flat a wider box is unlikely to help, and the list says so; nothing for results that
    do not record bounds."""
    from kftune.report.tables import edge_text

    runs = [m for m in results.methods if "on_bounds" in m.extra]
    if not runs:
        return []
    hits = [(m.label, h) for m in runs for h in m.extra["on_bounds"]]
    md = ["## Best points on a bound of the search box", ""]
    if not hits:
        return [*md, "No method's best point lies within 1 % of a bound of the search box.", ""]
    md += [
        "These tuned parameters lie within 1 % of the range of a bound. Where the cost still "
        "falls beyond the bound the optimum may lie there (widen the box: `kftune tune "
        "--widen-bounds`, or `[parameters] q_bounds`); where a widening would search and "
        "the cost is not 0.1 % lower two decades out, or (where none would) it rose by less "
        "than 0.1 % over the last step in, a wider box is unlikely to help:",
        "",
    ]
    for label, h in hits:
        name = h["parameter"]
        line = f"- {label}: {name} = {h['value']:.4g}, on its {h['side']} bound {h['bound']:g}"
        edge = h.get("edge")
        if edge is not None:
            line += f"; {edge_text(name, edge)}"
            if edge["flat"]:
                line += (
                    ": no worthwhile drop beyond, a wider box is unlikely to help"
                    if edge.get("beyond")
                    else ": flat there, a wider box is unlikely to help"
                )
        md.append(line)
    return [*md, ""]


def _identifiability_lines(results: ExperimentResults, out: Path) -> list[str]:
    """Whether the training data determine each tuned model parameter, per method
    (``extra["identifiability"]``, written by ``kftune compare`` when model parameters are
    tuned; :mod:`kftune.tuning.identify`), with the figure of the cost's profiles (written
    to ``out/figures``); nothing for results without tuned model parameters. A damaged
    record is said to be so, naming the method."""
    from kftune.tuning.identify import Identifiability

    runs = [m for m in results.methods if (m.extra.get("identifiability") or {}).get("parameters")]
    if not runs:
        return []
    md = ["## Identifiability of the tuned model parameters", ""]
    shown = []
    for m in runs:
        try:
            lines = Identifiability.from_dict(m.extra["identifiability"]).lines()
        except ValueError as exc:
            md += [f"- {m.label}: the record is damaged ({exc}); not shown", ""]
            continue
        shown.append(m)
        md += [f"{m.label}: {lines[0]}", "", *(f"- {line.strip()}" for line in lines[1:]), ""]
    if shown:
        figure = plots.identifiability(results, [m.key for m in shown])
        plots.save(figure, out / "figures" / "identifiability.png")
        md += [
            "The training cost's rise around each tuned point along one model parameter, "
            "the others held, across the parameter's box; dashed: the recorded start value.",
            "",
            "![Identifiability](figures/identifiability.png)",
            "",
        ]
    return md


#: What the KPI names mean, under every KPI table.
MAE_NOTE = (
    "RMSE: root-mean-square error; MAE: the *maximum* absolute error (the paper's "
    "definition, not the mean); _NON: only the samples with |ay| ≥ 4 m/s²."
)


def parameter_note(names: Sequence[str], model: Mapping[str, Any] | None = None) -> str:
    """What the parameter table's columns are, for the kinds of parameter it holds (the
    names of :class:`~kftune.tuning.problem.TuningProblem`'s space; ``model``: the tuned
    model parameters, name → ``{"start", "unit"}``, the results' ``model_parameters``);
    "" for none known."""
    model = model or {}
    parts = []
    if any(n.startswith("q_") for n in names):
        units = "(m/s)² for vx and vy, (rad/s)² for r" if {"q_vx", "q_r"} <= set(names) else ""
        parts.append(
            "q_<state>: the process-noise variance of that state per filter step (a diagonal "
            "entry of Q, in the state's SI unit squared" + (f": {units}" if units else "") + ")"
        )
    if "r_scale" in names:
        parts.append("r_scale: the factor on every measurement variance (R = r_scale · R₀)")
    if any(n.startswith("r_") and n.endswith("_scale") and n != "r_scale" for n in names):
        parts.append("r_<measurement>_scale: the factor on that measurement's variance in R₀")
    if any(n.startswith("ukf_") for n in names):
        parts.append("ukf_alpha, ukf_beta, ukf_kappa: the sigma-point parameters (dimensionless)")
    tuned = [n for n in names if n in model]
    if tuned:
        parts.append(
            ", ".join(
                f"{n} [{model[n].get('unit', '')}]" if isinstance(model[n], Mapping) else n
                for n in tuned
            )
            + ": model parameters tuned with the noise (the manual row: their recorded "
            "values, where the search started)"
        )
    return "; ".join(parts) + "." if parts else ""


#: What the KPIs of a model without the sideslip report mean, under every KPI table.
RMSE_NOTE = (
    "RMSE: root-mean-square error of each scored channel (the cost's channels, or every "
    "measurement for a cost without a reference) against its reference `<channel>_ref`, "
    "or against the measured channel for a measurement, averaged over the manoeuvres. "
    "Against a measurement, a lower RMSE is not a more accurate filter: one that follows "
    "the measurement noise scores lowest there; only a reference says how accurate it is."
)


def _option_lines(results: ExperimentResults) -> list[str]:
    """Every method's options, defaults included (``extra["options"]``; results written
    before they were recorded have none)."""
    runs = [m for m in results.methods if "options" in m.extra]
    if not runs:
        return []
    md = ["## Method options", "", "Every option of every method, defaults included:", ""]
    for m in runs:
        opts = m.extra["options"] or {}
        text = ", ".join(f"{k} = {_value(v)}" for k, v in opts.items()) or "none"
        md.append(f"- {m.label} (`{m.key}`): {text}")
    return [*md, ""]


def _value(value: object) -> str:
    return json.dumps(value, separators=(", ", ": "))


def _meta_lines(meta: dict) -> list[str]:
    lines = []
    ds = meta.get("dataset", {})
    if ds:
        lines.append(
            f"- Dataset: **{ds.get('name', '?')}** — {ds.get('n_train', '?')} training and "
            f"{ds.get('n_test', '?')} test manoeuvres"
            + (f", vehicle: {ds['vehicle']}" if ds.get("vehicle") is not None else "")
        )
    for key, label in (
        ("filter", "Filter"),
        ("cost", "Cost"),
        ("parameters", "Tuned parameters"),
        ("R", "Measurement noise R (from sensor statistics)"),
        ("seed", "Seed"),
        ("created", "Created"),
        ("kftune_version", "kftune version"),
    ):
        if key in meta:
            lines.append(f"- {label}: {meta[key]}")
        if key == "cost" and meta.get("burn_in_s"):  # 0 (the paper) goes unsaid
            lines.append(
                f"- Burn-in: the first {meta['burn_in_s']:g} s of every manoeuvre left out of "
                "the cost and the KPIs"
            )
    if meta.get("command"):
        lines.append(f"- Command: `{meta['command']}`")
    fp = meta.get("dataset_fingerprint")
    if isinstance(fp, dict):
        lines.append(
            f"- Dataset fingerprint: SHA-256 `{fp.get('sha256')}` ({fp.get('n_manoeuvres')} "
            f"manoeuvres, {fp.get('n_samples')} samples)"
        )
    packages = meta.get("packages")
    if isinstance(packages, dict):
        lines.append(
            "- Packages: " + ", ".join(f"{k} {v}" for k, v in packages.items() if v is not None)
        )
    mach = meta.get("machine")
    if isinstance(mach, dict):
        lines.append(
            f"- Machine: {mach.get('platform')}, {mach.get('processor') or mach.get('machine')}"
            f", {mach.get('cpu_count')} CPUs ({mach.get('cpus_usable')} usable by this process)"
        )
    elif mach:
        lines.append(f"- Machine: {mach}")
    return [*lines, ""]
