"""Paper-style tables (Tables V–VII) as plain rows, rendered to Markdown and CSV.

A table is a header plus rows of cells; numbers stay numbers until rendering, so the same
table feeds the Markdown report, the CSV files and ``--json`` output.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kftune.report.results import ExperimentResults, MethodRun
from kftune.tuning.cost import LOG_COSTS
from kftune.tuning.identify import MEAN_NLL_KINDS
from kftune.tuning.kpi import KPI_NAMES

KPI_LABELS = {
    "rmse": "RMSE [deg]",
    "mae": "MAE (max. abs. error) [deg]",
    "rmse_non": "RMSE_NON [deg]",
    "mae_non": "MAE_NON (max. abs. error) [deg]",
}

#: Channel RMSE metrics compared in Fig. 7, with their labels.
CHANNEL_METRICS = {"rmse_beta": "β", "rmse_r": "yaw rate", "rmse_ay": "ay"}


def scored_channels(results: ExperimentResults) -> dict[str, str] | None:
    """Channel → unit of the channels the results score, for a model reported by its
    channel RMSEs (``meta["scored_channels"]``, :func:`kftune.experiment.scored_channels`);
    None for the paper's sideslip report."""
    channels = results.meta.get("scored_channels")
    return dict(channels) if isinstance(channels, dict) else None


def channel_label(channel: str, unit: str) -> str:
    """``"RMSE v [m/s]"`` (``"RMSE v [-]"`` without a unit)."""
    return f"RMSE {channel} [{unit or '-'}]"


def channel_metrics(results: ExperimentResults) -> dict[str, str]:
    """The channel RMSE metrics of Fig. 7 and the per-manoeuvre table, with their labels:
    :data:`CHANNEL_METRICS` for the sideslip report, else ``rmse_<channel>`` of every
    scored channel."""
    channels = scored_channels(results)
    if channels is None:
        return CHANNEL_METRICS
    return {f"rmse_{c}": c for c in channels}


@dataclass(frozen=True)
class Table:
    """A titled table. ``groups`` are the sets of (row, column) cells that compete (lower
    is better): a method's cost against the others', a KPI across methods."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[object, ...], ...]
    groups: tuple[tuple[tuple[int, int], ...], ...] = ()

    def best_cells(self, digits: int | None = None) -> frozenset[tuple[int, int]]:
        """Cells holding the smallest finite value of their group; with ``digits``, compared
        as :meth:`to_markdown` shows them, so values that print alike are all best."""
        best: set[tuple[int, int]] = set()
        for group in self.groups:
            values = {
                (i, j): v
                for i, j in group
                if isinstance(v := self.rows[i][j], float) and math.isfinite(v)
            }
            if digits is not None:
                values = {c: float(_fmt(v, digits)) for c, v in values.items()}
            if values:
                low = min(values.values())
                best.update(c for c, v in values.items() if v == low)
        return frozenset(best)

    @property
    def bold(self) -> frozenset[tuple[int, int]]:
        """The best cells at full precision."""
        return self.best_cells()

    def to_markdown(self, digits: int = 3) -> str:
        """GitHub-flavoured Markdown, the best value of each group in bold (every value
        that prints as the best)."""
        bold = self.best_cells(digits)
        lines = [
            "| " + " | ".join(self.header) + " |",
            "|" + "|".join(" --- " for _ in self.header) + "|",
        ]
        for i, row in enumerate(self.rows):
            cells = []
            for j, cell in enumerate(row):
                text = _fmt(cell, digits)
                cells.append(f"**{text}**" if (i, j) in bold else text)
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def write_csv(self, path: str | Path) -> None:
        """Write header and rows (full precision) to a CSV file."""
        with open(path, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(self.header)
            for row in self.rows:
                writer.writerow(["" if _isnan(c) else c for c in row])

    def to_records(self) -> list[dict[str, object]]:
        """Rows as dicts keyed by the header (for strict JSON: an empty or unknown number,
        NaN, is None)."""
        return [
            {h: None if _isnan(c) else c for h, c in zip(self.header, row)} for row in self.rows
        ]


def _isnan(x: object) -> bool:
    return isinstance(x, float) and math.isnan(x)


def _fmt(x: object, digits: int) -> str:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return str(x)
    if isinstance(x, int):
        return str(x)
    if math.isnan(x):
        return "–"
    if x != 0 and (abs(x) < 10 ** (-digits) or abs(x) >= 1e6):
        return f"{x:.{digits - 1}e}"
    if x != 0 and abs(float(f"{x:.{digits}g}")) < 1:  # significant: 0.00154, not 0.002
        return f"{x:#.{digits}g}"
    return f"{x:.{digits}f}"


def _row_groups(rows: Sequence[Sequence[object]], first_col: int) -> tuple:
    """One group per row: the cells from ``first_col`` on (a KPI across methods)."""
    return tuple(tuple((i, j) for j in range(first_col, len(row))) for i, row in enumerate(rows))


def n_failed(m: MethodRun) -> int:
    """How many of the method's cost evaluations failed (a NaN in its history: the filter
    diverged or the evaluation raised), the best cost being over the others."""
    return sum(1 for c in m.history_cost if _isnan(float(c)))


def failure_lines(results: ExperimentResults) -> list[str]:
    """One line per method with failed evaluations: how many of how many, and their reasons
    grouped by kind (:func:`~kftune.tuning.runs.failure_kinds`) from the reasons the
    results record (``extra["failures"]``); none when no evaluation failed."""
    from kftune.tuning.runs import failure_kinds

    lines = []
    for m in results.methods:
        if not (failed := n_failed(m)):
            continue
        recorded = [f.get("reason") for f in m.extra.get("failures") or []]
        why = (
            "; ".join(f"{kind} ({count})" for kind, count in failure_kinds(recorded))
            if recorded
            else "no reasons recorded"
        )
        lines.append(f"- **{m.label}**: {failed} of {m.n_evals} evaluations failed: {why}")
    return lines


def cost_table(results: ExperimentResults) -> Table:
    """Paper Table V: best training cost, evaluations (and how many of them failed) and
    tuning time per method."""
    rows = []
    for m in results.methods:
        per_eval = m.wall_time_s / m.n_evals * 1e3 if m.n_evals else math.nan
        rows.append(
            (
                m.label,
                float(m.best_cost),
                int(m.n_evals),
                n_failed(m),
                float(m.wall_time_s),
                per_eval,
            )
        )
    return Table(
        title="Best cost and tuning effort (training set; cf. paper Table V)",
        header=(
            "Method",
            "Best cost J [-]",
            "Evaluations",
            "Failed",
            "Tuning time [s]",
            "Time/eval [ms]",
        ),
        rows=tuple(rows),
        groups=(tuple((i, 1) for i in range(len(rows))),),  # the best cost column
    )


def kpi_table(results: ExperimentResults, split: str) -> Table:
    """Paper Tables VI (``split="train"``) and VII (``"test"``): average β KPIs; for
    another model, the average RMSE of each scored channel in its unit."""
    channels = scored_channels(results)
    labels = (
        KPI_LABELS
        if channels is None
        else {f"rmse_{c}": channel_label(c, u) for c, u in channels.items()}
    )
    rows = tuple(
        (
            label,
            *(float(m.averages.get(split, {}).get(k, math.nan)) for m in results.methods),
        )
        for k, label in labels.items()
    )
    diverged = [int(m.averages.get(split, {}).get("n_diverged", 0)) for m in results.methods]
    if any(diverged):  # the averages are NaN then; say why
        rows = (*rows, ("Diverged manoeuvres", *diverged))
    which = "training" if split == "train" else "test"
    number = "VI" if split == "train" else "VII"
    title = (
        f"Average sideslip KPIs on the {which} set (cf. paper Table {number})"
        if channels is None
        else f"Average RMSE of the scored channels on the {which} set"
    )
    return Table(
        title=title,
        header=("KPI", *(m.label for m in results.methods)),
        rows=rows,
        groups=_row_groups(rows, first_col=1),
    )


def per_manoeuvre_table(results: ExperimentResults) -> Table:
    """Every metric of every method on every manoeuvre (long format, for CSV); ``diverged``
    is 1 where the filter diverged or ran away there (its metrics are then NaN)."""
    sideslip = scored_channels(results) is None
    metrics = (*(KPI_NAMES if sideslip else ()), *channel_metrics(results), "diverged")
    rows = []
    for m in results.methods:
        for split, per in m.metrics.items():
            for name, values in per.items():
                rows.append(
                    (m.key, split, name, *(float(values.get(k, math.nan)) for k in metrics))
                )
    return Table(
        title="Per-manoeuvre metrics",
        header=("method", "split", "manoeuvre", *metrics),
        rows=tuple(rows),
    )


def relative_improvement(
    results: ExperimentResults, baseline: str = "ga", method: str = "tsbo-tsp", split: str = "test"
) -> dict[str, dict[str, float]]:
    """Per-manoeuvre relative improvement of ``method`` over ``baseline`` (paper Fig. 7).

    improvement = 100·(RMSE_baseline − RMSE_method)/RMSE_baseline [%] for the channels of
    :func:`channel_metrics` (for the sideslip report :data:`CHANNEL_METRICS`); positive
    means ``method`` is better.

    Returns:
        manoeuvre → channel metric → improvement [%].
    """
    base = results.method(baseline).metrics.get(split, {})
    new = results.method(method).metrics.get(split, {})
    out: dict[str, dict[str, float]] = {}
    for name in base:
        if name not in new:
            continue
        out[name] = {}
        for metric in channel_metrics(results):
            b, n = base[name].get(metric, math.nan), new[name].get(metric, math.nan)
            out[name][metric] = 100.0 * (b - n) / b if b > 0 else math.nan
    return out


def consistency_lines(runs: Mapping[str, Mapping[str, Any] | None], width: int = 12) -> list[str]:
    """A plain-text table of consistency (:func:`kftune.tuning.consistency.as_doc` per
    row: a manoeuvre, or a pooled set), one line per referenced channel, under 100
    columns: coverage of the ±1σ and ±1.96σ intervals [%], the mean NEES and its 95 % band
    (effective sample count), the mean NIS and its 95 % band; ``*`` marks a mean outside
    its band. A row that is None (the filter diverged there) shows "–"; ``width``: of the
    name column."""
    width = max(width, *(len(n) for n in runs)) if runs else width
    dof = next((r["nis"]["dof"] for r in runs.values() if r and r.get("nis")), None)
    nis_head = f"NIS (m={dof})" if dof is not None else "NIS"
    head = (
        f"{'consistency':{width}s} {'channel':8s} {'cov68%':>6s} {'cov95%':>6s} "
        f"{'NEES':>7s} {'95% band':15s} {nis_head:>9s} {'95% band':15s}"
    ).rstrip()
    lines = [head]
    for name, run in runs.items():
        if run is None:
            lines.append(f"{name:{width}s} {'–':8s} (the filter diverged)")
            continue
        channels = run["channels"] or {"–": None}
        nis = _mean_and_band(run["nis"], "band")
        for i, (channel, ch) in enumerate(channels.items()):
            cov = (_pct(ch["cov68"]), _pct(ch["cov95"])) if ch else ("–", "–")
            nees = _mean_and_band(ch["nees"] if ch else None, "band_eff")
            last = nis if i == 0 else ("", "")
            lines.append(
                f"{name if i == 0 else '':{width}s} {channel:8s} {cov[0]:>6s} {cov[1]:>6s} "
                f"{nees[0]:>7s} {nees[1]:15s} {last[0]:>9s} {last[1]:15s}".rstrip()
            )
    lines.append(
        "consistent: cov68 68.3 %, cov95 95 %, NEES 1, NIS m, each mean in its 95 % band (* "
        "outside);"
    )
    lines.append(
        "NEES per channel (only P's diagonal is kept), its band for the errors' effective "
        "sample count"
    )
    return lines


def _pct(share: float | None) -> str:
    return "–" if share is None else f"{100.0 * share:.1f}"


def _mean_and_band(stat: Mapping[str, Any] | None, band: str) -> tuple[str, str]:
    """(mean with ``*`` when outside ``band``, "[low, high]") of a χ² mean's JSON form."""
    if stat is None or stat["mean"] is None:
        return "–", ""
    lo, hi = stat[band]
    outside = lo is not None and hi is not None and not lo <= stat["mean"] <= hi
    bounds = "" if lo is None or hi is None else f"[{lo:.3g}, {hi:.3g}]"
    return f"{stat['mean']:.3g}" + ("*" if outside else ""), bounds


def sigma_verdict(nees: Mapping[str, Any] | None) -> str:
    """Whether σ can be trusted, from a mean NEES's JSON form
    (:meth:`~kftune.tuning.consistency.ChiSquareMean.as_dict`): "consistent" when the mean
    lies in its band (effective sample count) and that count is at least
    :data:`~kftune.tuning.consistency.MIN_EFFECTIVE_TERMS` (fewer: too few to tell), else by
    how much σ is off — the factor √(mean NEES) that would bring the mean to 1; "–" when
    nothing was counted."""
    from kftune.tuning.consistency import MIN_EFFECTIVE_TERMS

    if nees is None or nees.get("mean") is None:
        return "–"
    mean, inside = float(nees["mean"]), nees.get("inside")
    n_eff = nees.get("n_eff")
    if inside and n_eff is not None and n_eff < MIN_EFFECTIVE_TERMS:
        return f"too few independent errors to tell (about {n_eff:.0f})"
    if inside or mean <= 0:
        return "consistent" if inside else "–"
    factor = math.sqrt(mean)
    small = factor >= 1
    factor = factor if small else 1 / factor
    # 1.04, 3.7, 13, 330: no exponent, and never "1×" for a σ that is off by a few per cent
    text = f"{factor:.2f}" if factor < 1.95 else f"{factor:.2g}" if factor < 10 else f"{factor:.0f}"
    return f"σ is about {text}× too {'small' if small else 'large'}"


def consistency_split(results: ExperimentResults) -> str | None:
    """The split the report's consistency table and reliability figure show: the test
    manoeuvres, the training ones when there are none; None when no method's results record
    consistency (results written before it was measured)."""
    splits = {s for m in results.methods for s in m.consistency}
    return next((s for s in ("test", "train") if s in splits), None)


def consistency_table(results: ExperimentResults, split: str) -> Table:
    """Whether each method's tuned filter has standard deviations that can be trusted on
    ``split``, pooled sample by sample over its manoeuvres: per referenced channel, the
    coverage of the ±1σ and ±1.96σ intervals [%], the mean NEES and its 95 % band (for the
    errors' effective sample count), the mean NIS against m and its band, the calibration
    factor c its covariances carry (fitted on the training manoeuvres, its estimate
    unchanged; – where none was fitted, or in results written before) and a verdict
    (:func:`sigma_verdict`). A method whose filter diverged on a manoeuvre of the split has
    one row saying so."""
    dof = next(
        (
            d["nis"]["dof"]
            for m in results.methods
            if (d := m.consistency.get(split)) and d.get("nis")
        ),
        None,
    )
    m_text = "m" if dof is None else f"m = {dof}"
    header = (
        "Method",
        "Channel",
        "±1σ coverage [%] (68.3)",
        "±1.96σ coverage [%] (95)",
        "Mean NEES (1)",
        "NEES 95 % band",
        f"Mean NIS ({m_text})",
        "NIS 95 % band",
        "Covariances × c (calibration)",
        "σ",
    )
    rows: list[tuple[object, ...]] = []
    for m in results.methods:
        if split not in m.consistency:
            continue
        doc = m.consistency[split]
        cal = m.extra.get("calibration")
        factor = cal.get("factor") if isinstance(cal, dict) else None
        factor = float(factor) if isinstance(factor, (int, float)) else math.nan
        if doc is None:
            rows.append((m.label, "–", *(math.nan,) * 3, "", math.nan, "", factor, "diverged"))
            continue
        nis = doc.get("nis") or {}
        for i, (channel, ch) in enumerate(doc["channels"].items()):
            nees = ch["nees"]
            rows.append(
                (
                    m.label,
                    channel,
                    _share(ch["cov68"]),
                    _share(ch["cov95"]),
                    _float(nees["mean"]),
                    _band(nees["band_eff"]),
                    _float(nis.get("mean")) if i == 0 else math.nan,
                    _band(nis.get("band")) if i == 0 else "",
                    factor if i == 0 else math.nan,
                    sigma_verdict(nees),
                )
            )
    which = "test" if split == "test" else "training"
    return Table(
        title=f"Consistency of the tuned filters on the {which} set (pooled over its manoeuvres)",
        header=header,
        rows=tuple(rows),
    )


def _share(v: float | None) -> float:
    return math.nan if v is None else 100.0 * float(v)


def _float(v: float | None) -> float:
    return math.nan if v is None else float(v)


def _band(band: Sequence[float | None] | None) -> str:
    """ "[low, high]" of a band's JSON form; "" when it is not known."""
    if not band or any(v is None for v in band):
        return ""
    return f"[{band[0]:.3g}, {band[1]:.3g}]"


def rise_text(edge: Mapping[str, Any], rise: float | None = None) -> str:
    """How much higher (or lower) the cost is at a probe of
    :func:`kftune.experiment.edge_probes` than at the best point (``rise``: J − J*; default
    the step in, ``edge["rise"]``), in the
    cost's own terms: a share of |J*| for a cost that scales with the error, for a
    logarithm (msp, nis) the share by which what it is the log of changes (e^|ΔJ| − 1), a
    mean log-likelihood's change per sample beside the change the data can tell apart."""
    rise = edge["rise"] if rise is None else rise
    kind = edge.get("cost_kind", "nrmse")
    way = "higher" if rise >= 0 else "lower"
    if kind in MEAN_NLL_KINDS:
        return f"{abs(rise):.2g} per sample {way} (the data tell {edge['threshold']:.2g} apart)"
    if kind in LOG_COSTS:
        share = math.expm1(abs(rise))
    else:
        share = abs(rise) / (abs(edge["best_cost"]) or 1.0)
    pct = 100.0 * share
    return f"{pct:.2g} % {way}" if pct < 100.0 else f"{pct:,.0f} % {way}"


def edge_text(name: str, edge: Mapping[str, Any]) -> str:
    """What the probes of :func:`kftune.experiment.edge_probes` found, for a hint: ``"one
    decade in, at q_vx = 0.1, the cost is 0.96 % higher, and 2 decades out, at q_vx = 100,
    1.6 % higher"``."""
    said = f"{edge['step']} in, at {name} = {edge['value']:.4g}, " + (
        "the filter diverged" if edge["rise"] is None else f"the cost is {rise_text(edge)}"
    )
    beyond = edge.get("beyond")
    if beyond is None:
        return said
    said += f", and {beyond['decades']:g} decades out, at {name} = {beyond['value']:.4g}, " + (
        "the filter diverged" if beyond["rise"] is None else rise_text(edge, beyond["rise"])
    )
    return said
