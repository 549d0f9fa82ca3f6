"""Paper-style figures (Figs. 2, 6, 7, 8–10), drawn with matplotlib's Agg backend; for a
model reported by its channel RMSEs, :func:`channel_traces` stands in for Figs. 8–10.

Every function takes stored :class:`~kftune.report.results.ExperimentResults` and returns a
matplotlib ``Figure``; :func:`save` writes it as PNG and closes it.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

from kftune.report.results import ExperimentResults
from kftune.report.tables import channel_metrics, relative_improvement, scored_channels

#: The one registry of colours: every method keeps its colour in every figure (and no
#: figure uses a method's colour for anything else). Distinct hues, at least ΔE 20 apart
#: in CIELAB (tests/test_report.py checks both); "reference" and "estimate" are the
#: sideslip reference and ``kftune estimate``'s estimate.
COLOURS = {
    "manual": "#7f7f7f",  # grey
    "ga": "#d62728",  # red
    "tsbo-gp": "#1f77b4",  # blue
    "tsbo-tsp": "#2ca02c",  # green
    "tsbo-robust": "#9467bd",  # purple
    "random": "#8c564b",  # brown
    "trbo": "#ff7f0e",  # orange
    "optuna-tpe": "#ff00ff",  # magenta (was cyan, too close to TSBO-GP's blue)
    "optuna-gp": "#bcbd22",  # olive
    "cma": "#00008b",  # navy (was pink, beside Optuna TPE's magenta)
    "reference": "#000000",
    "estimate": "#1b9e77",  # teal
}

#: Fills of the per-channel bars of Fig. 7: greys and hatches, no method's colour.
CHANNEL_STYLES = (("#404040", ""), ("#909090", "//"), ("#d0d0d0", ".."))


def _colour(key: str) -> str | None:
    return COLOURS.get(key)


def render(fig: Figure, dpi: int = 130, tight: bool = True) -> bytes:
    """A figure as PNG bytes; the figure is released. Rendered in memory, so that the
    file is written by a write that reports its errors: matplotlib's own file writing
    ignores a failed one (``savefig`` to the full device succeeds)."""
    buf = io.BytesIO()
    try:
        # bbox_inches=None: savefig's default (rcParams["savefig.bbox"])
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    finally:
        plt.close(fig)
    return buf.getvalue()


def save(fig: Figure, path: str | Path, dpi: int = 130) -> Path:
    """Write a figure as PNG and release it (``OSError`` if the write fails, e.g. a full
    disk)."""
    path = Path(path)
    path.write_bytes(render(fig, dpi))
    return path


def convergence(results: ExperimentResults) -> Figure:
    """Fig. 6: best cost so far against evaluations (left) and against wall time (right),
    both on log axes: budgets of very different size (a GA's 225 evaluations beside a
    Bayesian optimiser's 40) each get their share of the width. Every method in its
    colour and with its own marker (:data:`MARKERS`, report order), so that two curves
    that run together, or two similar colours, stay apart; a fixed point (the manual
    filter) is a dotted line with its cost in the legend. The log cost axis labels enough
    values (:func:`label_log_axis`) that every line, the reference too, can be read."""
    fig, (ax_n, ax_t) = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for i, m in enumerate(results.methods):
        best = m.best_so_far()
        if m.n_evals <= 1:  # a fixed point (manual tuning): a reference line, its value
            for ax in (ax_n, ax_t):  # in the legend (it may lie between two labels)
                label = f"{m.label} (J = {m.best_cost:.4g})"
                ax.axhline(m.best_cost, color=_colour(m.key), ls=":", label=label)
            continue
        n = np.arange(1, best.size + 1)
        style = {
            "color": _colour(m.key),
            "marker": MARKERS[i % len(MARKERS)],
            "ms": 5,
            "mfc": "none",
            "markevery": 0.12,  # spaced on the page, not by index: log axes
            "drawstyle": "steps-post",
            "label": m.label,
        }
        ax_n.plot(n, best, **style)
        ax_t.plot(m.history_time_s, best, **style)
    ax_n.set_xlabel("cost evaluations")
    ax_t.set_xlabel("tuning wall time [s]")
    for ax in (ax_n, ax_t):
        ax.set_xscale("log")
        label_log_axis(ax.xaxis, *ax.get_xlim())
    ax_n.set_ylabel("best cost J [-]")
    for ax in (ax_n, ax_t):
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    low, high = ax_n.get_ylim()
    label_log_axis(ax_n.yaxis, low, high, vertical=True)  # 0.4, not 4×10⁻¹
    ax_n.legend(fontsize=8)
    fig.suptitle("Convergence of the tuning methods (training set)")
    return fig


def label_log_axis(axis: Any, low: float, high: float, vertical: bool = False) -> None:
    """Label a log axis with plain numbers (0.002, not 2×10⁻³), as many as fit.

    An x axis: the decades over two decades and more, also the 2s and 5s over one, also the
    3s under one, every tick under 0.3 of a decade (matplotlib labelled every minor tick of
    a span under a decade in scientific notation, and the labels ran together).

    A y axis (``vertical``), whose labels stack: the roundest values first (1, then 2 and 5,
    then the other digits, then 1.5 and 2.5, then 1.2, 1.4, …), each where it is at least
    :data:`LOG_LABEL_GAP` points from every label already placed (:func:`_log_ticks`). A span
    of under a decade between 0.33 and 1.6 got labels up to 1 only, as matplotlib has no
    tick between 1 and 2, and a line at 1.52 could not be read; it now gets 1.2 and 1.5.
    Call it once the axis's limits and the figure's size are final."""
    if vertical:
        ticks = _log_ticks(axis, low, high)
        if len(ticks) >= 2:
            axis.set_major_locator(FixedLocator(ticks))
            axis.set_major_formatter(FuncFormatter(lambda value, _pos: f"{value:g}"))
            axis.set_minor_formatter(NullFormatter())
            return
    decades = math.log10(high / low) if 0 < low < high else 2.0
    shown = (
        set(range(1, 10)) if decades < (1.0 if vertical else 0.3)
        else {1, 2, 3, 5} if decades < 1
        else {1, 2, 5} if decades < 2
        else {1}
    )  # fmt: skip

    def label(value: float, _pos: int) -> str:
        mantissa = round(value / 10 ** math.floor(math.log10(value) + 1e-9), 6)
        return f"{value:g}" if mantissa in shown else ""

    axis.set_major_formatter(FuncFormatter(label))
    axis.set_minor_formatter(FuncFormatter(label))


#: The least distance between two labels of a log y axis [points, 1/72 in]: a 10-point
#: label and a gap.
LOG_LABEL_GAP = 16.0

#: Mantissas of a log axis's labels, roundest first (:func:`_log_ticks` places them in
#: this order).
LOG_MANTISSAS = (
    (1.0,),
    (2.0, 5.0),
    (3.0, 4.0, 6.0, 7.0, 8.0, 9.0),
    (1.5, 2.5),
    (1.2, 1.4, 1.6, 1.8, 3.5, 4.5),
    (1.1, 1.3, 1.7, 1.9, 2.2, 2.4, 2.6, 2.8, 3.2, 3.4, 3.6, 3.8, 4.2, 4.4, 4.6, 4.8,
     5.5, 6.5, 7.5, 8.5, 9.5),
)  # fmt: skip


def _log_ticks(axis: Any, low: float, high: float) -> list[float]:
    """The labelled values of a log y axis from ``low`` to ``high`` (its limits), sorted:
    the mantissas of :data:`LOG_MANTISSAS` in their order, each value kept where it lies at
    least :data:`LOG_LABEL_GAP` points on the page from every value kept before (the axis's
    height in points over its decades gives points per decade). [] for limits that are not
    positive."""
    if not 0 < low < high:
        return []
    ax = axis.axes
    height = ax.get_position().height * ax.figure.get_figheight() * 72.0  # points
    span = math.log10(high / low)
    gap = LOG_LABEL_GAP / height * span  # [decades]
    kept: list[float] = []  # log10 of the values kept
    decades = range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)
    for level in LOG_MANTISSAS:
        for k in decades:
            for mantissa in level:
                value = mantissa * 10.0**k
                if not low <= value <= high:
                    continue
                where = math.log10(value)
                if all(abs(where - other) >= gap for other in kept):
                    kept.append(where)
    return sorted(float(f"{10.0**w:.6g}") for w in kept)


def improvement(
    results: ExperimentResults,
    baseline: str = "ga",
    method: str = "tsbo-tsp",
    split: str = "test",
    manoeuvres: list[str] | None = None,
    heading: str = "",
    metrics: Sequence[str] | None = None,
) -> Figure:
    """Fig. 7: per-manoeuvre relative RMSE improvement of ``method`` over ``baseline`` (for
    β, yaw rate and ay; for another model, for each scored channel). The paper's figure is
    TSBO-tSP over GA (the defaults); the report also draws TR-BO over the manual filter
    (TR-BO as compare runs it, on the paper's cost and space: not the filter ``kftune
    tune`` deploys). ``heading``: the title's first line, saying which of the
    two a reader sees (the title's line below names the pair and the split). ``metrics``:
    the channel metrics drawn (default: all; the β figure of TR-BO over the manual filter
    draws β alone: yaw rate and ay are scored against their measurements, which a filter
    that follows the gyro copies, so their bars measure the fit to the sensors rather than
    accuracy, and dwarf β's)."""
    rel = relative_improvement(results, baseline, method, split)
    names = [n for n in (manoeuvres or list(rel)) if n in rel]
    x = np.arange(len(names))
    drawn = {k: v for k, v in channel_metrics(results).items() if metrics is None or k in metrics}
    width = 0.8 / len(drawn)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(names) + 2), 3.8))
    for i, (metric, label) in enumerate(drawn.items()):
        values = [rel[n][metric] for n in names]
        colour, hatch = CHANNEL_STYLES[i % len(CHANNEL_STYLES)]
        ax.bar(
            x + (i - (len(drawn) - 1) / 2) * width,
            values,
            width,
            color=colour,
            hatch=hatch,
            edgecolor="black",
            lw=0.4,
            label=f"RMSE {label}",
        )
    ax.axhline(0.0, color="black", lw=0.8)
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("relative improvement [%]")
    b, m = results.method(baseline).label, results.method(method).label
    title = f"{m} vs {b}, {split} set (positive: {m} better)"
    ax.set_title(f"{heading}\n{title}" if heading else title, fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return fig


#: The time axis of every figure over a manoeuvre (compare's β and channel figures,
#: estimate's, dataset show's): the recording's own time, as its file and the manoeuvre's
#: description ("t = 2.00 … 30.20 s") give it — an imported recording trimmed of a
#: standstill starts later than 0 — so that a moment on a figure is found in the file.
TIME_LABEL = "time in the recording [s]"

#: Dash patterns of the tuned methods' β curves, in the order drawn: tuned filters often
#: coincide, and a dash lets the one beneath show through.
LINESTYLES = ("-", (0, (5, 2)), (0, (1, 1.5)), (0, (6, 2, 1, 2)), (0, (3, 3)))


def _rmse(error: np.ndarray) -> float:
    """Root mean square of the finite samples of ``error`` (NaN when there are none)."""
    finite = error[np.isfinite(error)]
    return float(np.sqrt(np.mean(finite**2))) if finite.size else math.nan


def beta_trace(
    results: ExperimentResults,
    manoeuvre: str,
    methods: Sequence[str] | None = None,
) -> Figure:
    """Figs. 8–10: the sideslip β [deg] of every method's filter against the reference in
    one manoeuvre (top), and each tuned method's error [deg] in a panel of its own with the
    manual filter's error behind it in grey (below; one panel per method, a common y
    axis), so that no filter hides another and each is read against the manual baseline
    that every table compares with. ``methods``: the keys to draw, in this order (default:
    every method of ``results`` with a trace here); "manual" is drawn as the reference
    filter, grey and dashed, never in a panel of its own."""
    tr = results.traces[manoeuvre]
    t = tr["t"]
    ref = np.degrees(tr["beta_ref"])
    keys = [m.key for m in results.methods] if methods is None else list(methods)
    keys = [k for k in keys if f"beta_{k}" in tr]
    tuned = [k for k in keys if k != "manual"]
    manual = np.degrees(tr["beta_manual"]) if "manual" in keys else None
    rows = max(1, len(tuned))
    fig, axes = plt.subplots(
        1 + rows,
        1,
        figsize=(8, 3.0 + 0.95 * rows),
        sharex=True,
        gridspec_kw={"height_ratios": [3.0] + [1.0] * rows},
        squeeze=False,
        layout="constrained",  # the gap for the panels' caption only above the first
    )
    ax, panels = axes[0, 0], axes[1:, 0]
    ax.plot(t, ref, color=COLOURS["reference"], lw=1.6, label="reference")
    if manual is not None:
        label = f"{results.method('manual').label}, RMSE {_rmse(manual - ref):.3f}°"
        ax.plot(t, manual, color=COLOURS["manual"], lw=1.1, ls="--", label=label)
    for i, key in enumerate(tuned):
        est = np.degrees(tr[f"beta_{key}"])
        label = f"{results.method(key).label}, RMSE {_rmse(est - ref):.3f}°"
        ax.plot(t, est, color=_colour(key), lw=1.1, ls=LINESTYLES[i % len(LINESTYLES)],
                label=label)  # fmt: skip
        e = panels[i]
        if manual is not None:
            e.plot(t, manual - ref, color=COLOURS["manual"], lw=0.8, alpha=0.7,
                   label=results.method("manual").label)  # fmt: skip
        e.plot(t, est - ref, color=_colour(key), lw=0.8, label=results.method(key).label)
        e.axhline(0.0, color="black", lw=0.5)
        # the panel's name as its y label, in the method's colour: inside, it lay on data
        name = results.method(key).label.replace(" (", "\n(")
        e.set_ylabel(name, fontsize=8, color=_colour(key))
    if not tuned and manual is not None:
        panels[0].plot(t, manual - ref, color=COLOURS["manual"], lw=0.8)
    for e in panels[1:]:
        e.sharey(panels[0])
    kind = results.meta.get("manoeuvres", {}).get(manoeuvre, {}).get("kind", "")
    fig.suptitle(f"Sideslip angle, {manoeuvre}" + (f" ({kind})" if kind else ""))
    ax.set_ylabel("β [deg]")
    # above the axes: inside, the legend covered the curves of a long manoeuvre
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=3, frameon=False)
    behind = f"; grey: {results.method('manual').label}" if manual is not None else ""
    panels[0].set_title(f"error: estimate − reference [deg]{behind}", fontsize=8, loc="left")
    panels[-1].set_xlabel(TIME_LABEL)
    for a in axes[:, 0]:
        a.grid(True, alpha=0.3)
    return fig


def channel_traces(
    results: ExperimentResults,
    manoeuvre: str,
    methods: tuple[str, ...] = ("ga", "tsbo-tsp", "trbo"),
) -> Figure:
    """For a model reported by its channel RMSEs (the counterpart of Figs. 8–10): each
    scored channel estimated by ``methods`` against its reference in one manoeuvre (left)
    and the error (right), one row per channel, in the channel's unit."""
    channels = scored_channels(results) or {}
    tr = results.traces[manoeuvre]
    t = tr["t"]
    rows = max(1, len(channels))
    fig, axes = plt.subplots(rows, 2, figsize=(11, 0.4 + 2.3 * rows), sharex=True, squeeze=False)
    for (ax, ax_e), (c, unit) in zip(axes, channels.items()):
        unit = f" [{unit}]" if unit else ""
        if f"{c}_ref" not in tr:
            continue
        ref = np.asarray(tr[f"{c}_ref"], dtype=float)
        ax.plot(t, ref, color=COLOURS["reference"], lw=1.4, label="reference")
        tuned = 0
        for key in methods:
            if f"{c}_{key}" not in tr:
                continue
            est = np.asarray(tr[f"{c}_{key}"], dtype=float)
            label = results.method(key).label
            # the manual filter dashed grey as in the β figure; the tuned ones each with
            # its dash, so that one on another's curve still shows
            ls = "--" if key == "manual" else LINESTYLES[tuned % len(LINESTYLES)]
            tuned += key != "manual"
            ax.plot(t, est, color=_colour(key), lw=1.0, ls=ls, label=label)
            ax_e.plot(t, est - ref, color=_colour(key), lw=0.9, ls=ls, label=label)
        ax.set_ylabel(f"{c}{unit}")
        ax_e.axhline(0.0, color="black", lw=0.6)
        ax_e.set_ylabel(f"error {c}{unit}")
        for a in (ax, ax_e):
            a.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[0, 0].set_title("estimate and reference")
    axes[0, 1].set_title("estimate − reference")
    for a in axes[-1]:
        a.set_xlabel(TIME_LABEL)
    kind = results.meta.get("manoeuvres", {}).get(manoeuvre, {}).get("kind", "")
    fig.suptitle(f"Scored channels, {manoeuvre}" + (f" ({kind})" if kind else ""))
    fig.tight_layout()
    return fig


def cost_slice(results: ExperimentResults) -> Figure:
    """Fig. 2: a one-dimensional slice of the cost with the GP and tSP fits (±2 std).

    The y axis holds the whole dense curve (the fits' bands may leave it) and, for a cost
    that is nowhere negative, starts at 0 or above; a grid point whose filter diverged (no
    cost, NaN in ``cost_slice["cost"]``) is a cross along the top, so that the curve's end
    there is not read as the edge of the box."""
    sl = results.cost_slice
    if not sl:
        raise ValueError("these results hold no cost slice")
    grid = np.asarray(sl["grid"], dtype=float)
    cost = np.asarray(sl["cost"], dtype=float)
    idx = np.asarray(sl["sample_index"], dtype=int)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(grid, cost, color="black", lw=1.0, label="cost J (dense evaluation)")
    ax.plot(grid[idx], cost[idx], "ko", ms=5, label="surrogate training points")
    styles = {"gp": ("tsbo-gp", "GP"), "tsp": ("tsbo-tsp", "tSP")}
    fits = sl.get("fits", {})
    # The tSP filled, the GP drawn on top dashed: where the two agree both stay visible.
    for name in sorted(fits, key=lambda n: n != "tsp"):
        key, label = styles.get(name, (name, name))
        mean = np.asarray(fits[name]["mean"], dtype=float)
        std = np.asarray(fits[name]["std"], dtype=float)
        colour = _colour(key)
        if name == "tsp":
            ax.plot(grid, mean, color=colour, lw=2.0, label=f"{label} mean")
            ax.fill_between(
                grid,
                mean - 2 * std,
                mean + 2 * std,
                color=colour,
                alpha=0.18,
                label=f"{label} ±2 std",
            )
        else:
            ax.plot(grid, mean, color=colour, lw=1.4, ls="--", label=f"{label} mean")
            for k, edge in enumerate((mean - 2 * std, mean + 2 * std)):
                ax.plot(
                    grid,
                    edge,
                    color=colour,
                    lw=0.9,
                    ls=":",
                    label=f"{label} ±2 std" if k == 0 else None,
                )
    if {"gp", "tsp"} <= set(fits):
        gp, tsp = fits["gp"], fits["tsp"]
        dmean = np.max(np.abs(np.subtract(tsp["mean"], gp["mean"])))
        ratio = np.divide(tsp["std"], gp["std"])
        ax.text(  # above the axes: inside, it lay on the curve's low plateau
            0.5,
            1.01,
            f"max |mean tSP − mean GP| = {dmean:.2g}; std tSP/GP in "
            f"[{np.min(ratio):.2f}, {np.max(ratio):.2f}]",
            transform=ax.transAxes,
            ha="center",
            va="bottom",
            fontsize=8,
        )
    if sl.get("log_scale", True):
        ax.set_xscale("log")
    finite = np.isfinite(cost)
    if finite.any():
        lo, hi = float(np.min(cost[finite])), float(np.max(cost[finite]))
        pad = 0.25 * (hi - lo) if hi > lo else 0.25 * max(abs(hi), 1.0)
        bottom = lo - pad if lo < 0 else max(0.0, lo - pad)  # a cost >= 0: no axis below 0
        ax.set_ylim(bottom, hi + pad)
        if not finite.all():  # on the page whatever the axis: at 90 % of its height
            y = bottom + 0.9 * (hi + pad - bottom)
            ax.plot(grid[~finite], np.full(int((~finite).sum()), y), "x", color="black",
                    ms=6, label="filter diverged (no cost)")  # fmt: skip
    through = sl.get("through", "best")
    ax.set_xlabel(f"{sl['parameter']} (other parameters at the {through} optimum)")
    ax.set_ylabel("cost J [-]")
    ax.set_title("GP and Student-t process fits of a slice of the cost", pad=16)
    ax.legend(fontsize=8, loc="best")
    ax.grid(True, which="both", alpha=0.3)
    return fig


#: The half-width of :func:`estimate_trace`'s band in σ: the 95 % interval of a Gaussian,
#: as in the consistency tables (``cov95``), so that the figure and the tables agree.
BAND_Z = 1.96

#: The band's legend entry.
BAND_LABEL = "±1.96σ (95 %)"


def estimate_trace(
    t: np.ndarray,
    beta: np.ndarray,
    beta_std: np.ndarray | None,
    beta_ref: np.ndarray | None,
    title: str,
    label: str = "β",
    unit: str = "rad",
) -> Figure:
    """``kftune estimate``: an estimate (by default the sideslip β) with its ±1.96σ band
    (:data:`BAND_Z`: the 95 % interval that every consistency table counts) and,
    when there is one, the reference and the error; radians are shown in degrees, other
    units as they are. The title gives the share of the reference the band covers, and its
    median half-width when it is too narrow to see (:func:`_band_note`)."""
    rows = 2 if beta_ref is not None else 1
    fig, axes = plt.subplots(
        rows,
        1,
        figsize=(8, 4.8 if rows == 2 else 3.4),
        sharex=True,
        squeeze=False,
        gridspec_kw={"height_ratios": [2, 1][:rows]},
    )
    ax = axes[0, 0]
    show = np.degrees if unit == "rad" else np.asarray
    shown_unit = "deg" if unit == "rad" else unit or "-"
    est = show(beta)
    colour = COLOURS["estimate"]
    if beta_std is not None:
        band = BAND_Z * show(beta_std)
        ax.fill_between(t, est - band, est + band, color=colour, alpha=0.25, lw=0,
                        label=BAND_LABEL)  # fmt: skip
    ax.plot(t, est, color=colour, lw=1.0, label="estimate")
    if beta_ref is not None:
        ref = show(beta_ref)
        ax.plot(t, ref, color=COLOURS["reference"], lw=1.0, label="reference")
        ax_e = axes[1, 0]
        ax_e.axhline(0.0, color="black", lw=0.6)
        if beta_std is not None:
            ax_e.fill_between(t, -band, band, color=colour, alpha=0.25, lw=0, label=BAND_LABEL)
        ax_e.plot(t, est - ref, color=colour, lw=0.9, label="estimate − reference")
        ax_e.set_ylabel(f"error [{shown_unit}]")
        if beta_std is not None:
            _fit_band(ax_e, [est - ref], np.zeros_like(est), band)
        # above the panel (the x tick labels of the one above are hidden): inside, it
        # covered the error
        ax_e.legend(fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2,
                    frameon=False, borderaxespad=0.1)  # fmt: skip
    if beta_std is not None:
        _fit_band(ax, [est] if beta_ref is None else [est, show(beta_ref)], est, band)
    if beta_std is not None:  # judged on the error's scale where it is shown
        error = None if beta_ref is None else est - show(beta_ref)
        title += _band_note(axes[-1, 0], band, error, shown_unit)
    ax.set_ylabel(f"{label} [{shown_unit}]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel(TIME_LABEL)
    for a in axes[:, 0]:
        a.grid(True, alpha=0.3)
    return fig


def _fit_band(ax: Any, lines: Sequence[np.ndarray], centre: np.ndarray, half: np.ndarray) -> None:
    """Set ``ax``'s y limits to hold every sample of ``lines`` (each (N,)) and the ±``half``
    (N,) band about ``centre`` (N,) from the first sample where the band is at most three
    times its median half-width: the filter's start, where σ comes from P0 and is many
    times its later value, set the axis, and the band and the error over the rest of the
    manoeuvre were a flat line (the start's band runs off the axes instead)."""
    values = np.concatenate([np.ravel(v) for v in lines])
    values = values[np.isfinite(values)]
    finite = np.isfinite(half)
    if finite.any():
        settled = np.flatnonzero(finite & (half <= 3.0 * np.median(half[finite])))
        k0 = int(settled[0]) if settled.size else 0
        low_b, high_b = (centre - half)[k0:], (centre + half)[k0:]
        values = np.concatenate([values, low_b[np.isfinite(low_b)], high_b[np.isfinite(high_b)]])
    if values.size and values.max() > values.min():
        pad = 0.05 * (values.max() - values.min())
        ax.set_ylim(values.min() - pad, values.max() + pad)


#: The narrowest ±1.96σ band that can be seen [points, 1/72 in]: about 3.6 pixels at the
#: 130 dpi of :func:`save`.
VISIBLE_BAND = 2.0


def _band_note(ax: Any, half: np.ndarray, error: np.ndarray | None, unit: str) -> str:
    """A title's second line on a ±1.96σ band of half-width ``half`` (N,) drawn on ``ax`` (its
    limits final): the share of the samples whose ``error`` (N,) it covers, and its median
    half-width where the band, at the axis's scale on the page, is narrower than
    :data:`VISIBLE_BAND` — a band that cannot be seen says so rather than pass for one that
    covers the error. ``half`` and ``error`` in ``unit`` ("deg" is written °); "" when there
    is nothing to say."""
    from kftune.tuning.consistency import covered

    notes = []
    finite = half[np.isfinite(half)]
    if finite.size:
        median = float(np.median(finite))
        low, high = ax.get_ylim()
        page = ax.get_position().height * ax.figure.get_figheight() * 72.0  # points
        if 2.0 * median / (high - low) * page < VISIBLE_BAND:
            shown = f"{median:.2g}°" if unit == "deg" else f"{median:.2g} {unit}"
            notes.append(f"±{shown}, too narrow to see")
    if error is not None:
        inside, n = covered(error, half, 1.0)
        if n:
            notes.append(f"covers {100.0 * inside / n:.0f} % of the reference")
    return f"\n±1.96σ band: {'; '.join(notes)}" if notes else ""


#: Markers of the methods' curves in the reliability figure, in report order.
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">")


def reliability(results: ExperimentResults, split: str) -> Figure:
    """Reliability of each method's stated uncertainty on ``split``: the observed coverage
    of the intervals ±z_p·σ (y) against their nominal probability p (x), pooled over the
    split's manoeuvres (``MethodRun.consistency[split]["reliability"]``), one panel per
    referenced channel. A consistent filter lies on the diagonal; below it σ is too small
    (the intervals hold fewer errors than they claim), above it too large."""
    curves = {
        m.key: doc["reliability"]
        for m in results.methods
        if (doc := m.consistency.get(split)) and doc.get("reliability")
    }
    channels = list(dict.fromkeys(c for r in curves.values() for c in r["coverage"]))
    n = max(1, len(channels))
    fig, axes = plt.subplots(1, n, figsize=(5.4 * n, 5.0), squeeze=False)
    for ax, channel in zip(axes[0], channels or ["–"]):
        ax.plot([0, 100], [0, 100], color=COLOURS["reference"], ls="--", lw=1, label="consistent")
        for p in (68.27, 95.0):  # the table's two intervals: ±1σ and ±1.96σ
            ax.axvline(p, color="#c0c0c0", lw=0.8, zorder=0)
        for i, m in enumerate(results.methods):
            r = curves.get(m.key)
            if r is None or channel not in r["coverage"]:
                continue
            obs = np.array([np.nan if v is None else 100 * v for v in r["coverage"][channel]])
            # tuned filters often coincide: each later one drawn thinner with another
            # marker, so that the ones beneath still show
            ax.plot(
                100 * np.asarray(r["levels"]), obs, marker=MARKERS[i % len(MARKERS)],
                ms=max(3.0, 8.0 - 1.2 * i), lw=max(1.0, 3.0 - 0.5 * i), mfc="none",
                color=_colour(m.key), label=m.label,
            )  # fmt: skip
        for x, y, text in ((58, 52, "below: σ too small"), (42, 48, "above: σ too large")):
            ax.text(x, y, text, rotation=45, rotation_mode="anchor", ha="center",
                    va="top" if y < x else "bottom", fontsize=8, color="#505050")  # fmt: skip
        for p in (68.27, 95.0):
            ax.text(p, 101, f"{p:.3g}", ha="center", va="bottom", fontsize=7, color="#808080")
        ax.set_xlim(0, 100)
        ax.set_ylim(0, 100)
        ax.set_aspect("equal")
        ax.set_xlabel("nominal coverage of ±z·σ [%]")
        ax.set_ylabel(f"observed coverage of the {channel} errors [%]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    which = "test" if split == "test" else "training"
    fig.suptitle(f"Reliability of the stated uncertainty, {which} manoeuvres pooled", fontsize=10)
    fig.tight_layout()
    return fig


def _range_rise_pct(record: dict[str, Any]) -> float:
    """The rise that ends a range in an identifiability record, in % of |J*|: its relative
    rise, or its absolute one (a mean negative log-likelihood) over its first |J*|."""
    from kftune.tuning.identify import rise_pct

    first = next(iter(record["parameters"].values()))
    if record.get("abs_rise") is not None and first["cost"] != 0:
        return rise_pct(first["cost"] + float(record["abs_rise"]), first["cost"])
    return 100 * float(record.get("rel_rise", 0.01))


def identifiability(results: ExperimentResults, keys: Sequence[str] | None = None) -> Figure:
    """The cost's 1-D profile around each method's tuned point, one panel per tuned model
    parameter (``MethodRun.extra["identifiability"]``, :mod:`kftune.tuning.identify`): the
    rise of the training cost over its best value [%] (y, linear within ±1 %, logarithmic
    beyond) against the parameter (x, on its search scale, across its box), with the other
    parameters held; each tuned value a filled dot, the recorded start value dashed, the 1 %
    rise that ends a parameter's range dotted. A profile point whose filter diverged is
    drawn at the top as a cross. ``keys``: only these methods (default: every one with a
    record)."""
    from kftune.tuning.identify import rise_pct

    runs = [
        (i, m, m.extra["identifiability"])
        for i, m in enumerate(results.methods)
        if (m.extra.get("identifiability") or {}).get("parameters")
        and (keys is None or m.key in keys)
    ]
    names = list(dict.fromkeys(n for _, _, d in runs for n in d["parameters"]))
    rel = _range_rise_pct(runs[0][2]) if runs else 1.0
    fig, axes = plt.subplots(1, max(1, len(names)), figsize=(3.6 * max(1, len(names)), 3.7),
                             squeeze=False)  # fmt: skip
    for ax, name in zip(axes[0], names):
        recs = [(i, m, d["parameters"][name]) for i, m, d in runs if name in d["parameters"]]
        rises = {
            m.key: [(v, None if j is None else rise_pct(j, r["cost"])) for v, j in r["profile"]]
            for _, m, r in recs
        }
        top = max([1.0, *(y for p in rises.values() for _, y in p if y is not None)])
        for i, m, r in recs:
            good = [(v, y) for v, y in rises[m.key] if y is not None]
            ax.plot([v for v, _ in good], [y for _, y in good], marker=MARKERS[i % len(MARKERS)],
                    ms=4, lw=1.2, mfc="none", color=_colour(m.key), label=m.label)  # fmt: skip
            ax.plot([r["value"]], [0.0], marker="o", ms=6, color=_colour(m.key))
            failed = [v for v, y in rises[m.key] if y is None]
            if failed:  # (an empty line off the clip would stretch the tight layout)
                ax.plot(failed, [top] * len(failed), "x", color=_colour(m.key), ms=6, clip_on=False)
        first = recs[0][2]
        ax.axhline(rel, color="#808080", ls=":", lw=1.0, label=f"+{rel:g} % (range)")
        if first.get("start") is not None:
            ax.axvline(first["start"], color=COLOURS["reference"], ls="--", lw=1.0, label="start")
        if first["scale"] == "log10":
            ax.set_xscale("log")
            label_log_axis(ax.xaxis, first["low"], first["high"])
        ax.set_xlim(first["low"], first["high"])
        ax.set_yscale("symlog", linthresh=rel)
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
        bottom = min([-rel, *(y for p in rises.values() for _, y in p if y is not None)])
        ax.set_ylim(1.5 * bottom, 2 * top)
        unit = first.get("unit", "")
        ax.set_xlabel(name + (f" [{unit}]" if unit and unit != "-" else "") + ", across its box")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("rise of the training cost [%]")
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:  # below the panels: inside, it hides the profile near the optimum
        fig.legend(handles, labels, loc="lower center", ncol=len(handles), fontsize=8)
    fig.suptitle("Do the data determine each tuned model parameter? (others held)", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig
