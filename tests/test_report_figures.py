"""Figures that show what they say: every method that ran is drawn and can be seen (its
colour found among the rendered pixels, its label in the legend), the manual filter is the
β figures' reference, budgets of very different size share the convergence axis, the cost
slice's axis holds its curve and marks where the filter diverged, `dataset show` keeps its
legends off the data, and `evaluate` says what r and ay are scored against."""

from __future__ import annotations

import colorsys
import json
import math

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb

from conftest import run_cli
from kftune.report import ExperimentResults, MethodRun, plots, write_report


def _pixels(fig) -> np.ndarray:
    """The figure rendered by matplotlib's Agg canvas at the report's 130 dpi: (H, W, 3)
    RGB in [0, 1]."""
    fig.set_dpi(130)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3] / 255.0


def _count(pixels: np.ndarray, colour: str, tol: float = 0.06) -> int:
    """How many pixels have ``colour`` (each RGB channel within ``tol``; antialiased edges
    blend, a line's core does not)."""
    return int(np.all(np.abs(pixels - np.array(to_rgb(colour))) <= tol, axis=-1).sum())


def _legend_texts(fig) -> list[str]:
    return [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]


#: A subset of methods without the paper's GA and TSBO-tSP.
RAN = (("manual", "Manual", 1), ("trbo", "TR-BO", 40), ("cma", "CMA-ES", 40),
       ("random", "Random", 225))  # fmt: skip


@pytest.fixture
def ran() -> ExperimentResults:
    t = np.linspace(0.0, 5.0, 501)
    ref = 0.03 * np.sin(2.0 * t)
    beta = {
        "manual": 1.3 * ref,
        "trbo": 0.95 * ref,
        "cma": 0.95 * ref,  # exactly on TR-BO's curve: drawn after it, must not hide it
        "random": 1.1 * ref,
    }
    runs = []
    for i, (key, label, n) in enumerate(RAN):
        costs = np.geomspace(2.0, 0.5 + 0.1 * i, n) if n > 1 else np.array([2.5])
        runs.append(
            MethodRun(
                key=key,
                label=label,
                params={"q_vy": 1e-4},
                best_cost=float(costs[-1]),
                n_evals=n,
                wall_time_s=0.01 * n,
                history_cost=costs.tolist(),
                history_time_s=(0.01 * np.arange(1, n + 1)).tolist(),
                metrics={"test": {"m": {"rmse_beta": 1.0, "rmse_r": 1.0, "rmse_ay": 1.0}}},
            )
        )
    return ExperimentResults(
        meta={"manoeuvres": {"m": {"kind": "slalom", "split": "test"}}},
        methods=runs,
        traces={"m": {"t": t, "beta_ref": ref, **{f"beta_{k}": v for k, v in beta.items()}}},
    )


def test_the_beta_figure_draws_every_method_that_ran_each_visible(ran):
    """With --methods manual trbo cma random only TR-BO was drawn, the manual filter never;
    a method on another's curve (here CMA-ES on TR-BO's) was hidden under it."""
    fig = plots.beta_trace(ran, "m")
    legend = " ".join(_legend_texts(fig))
    pixels = _pixels(fig)
    seen = {key: _count(pixels, plots.COLOURS[key]) for key, _, _ in RAN}
    for key, label, _ in RAN:
        assert label in legend, label
        assert seen[key] > 200, f"{label} cannot be seen"
    # the manual filter is the reference in every tuned method's panel
    panels = fig.axes[1:]
    assert len(panels) == 3
    for ax in panels:
        colours = {to_rgb(line.get_color()) for line in ax.get_lines()}
        assert to_rgb(plots.COLOURS["manual"]) in colours
    # a chosen subset is drawn in the order given, and only that
    fig = plots.beta_trace(ran, "m", ("cma", "trbo"))
    assert len(fig.axes) == 3 and fig.axes[1].get_ylabel() == "CMA-ES"
    # (antialiased edges of other lines blend into a few pixels of any colour)
    assert _count(_pixels(fig), plots.COLOURS["random"]) < seen["random"] / 10
    plots.plt.close("all")


def test_the_report_draws_every_method_in_its_beta_figure(ran, tmp_path):
    write_report(ran, tmp_path)
    md = (tmp_path / "report.md").read_text()
    caption = next(line for line in md.splitlines() if line.startswith("β estimated by"))
    for _, label, _ in RAN:
        assert label in caption


def test_convergence_gives_a_small_budget_its_share_of_the_axis(ran):
    """GA's 225 evaluations squeezed the 40-evaluation curves into the first 15 % of a
    linear axis."""
    fig = plots.convergence(ran)
    fig.canvas.draw()
    ax_n, ax_t = fig.axes
    assert ax_n.get_xscale() == ax_t.get_xscale() == "log"
    low, high = ax_n.get_xlim()
    share = math.log(40 / low) / math.log(high / low)
    assert share > 0.6, share
    # every tuned method has its own marker beside its colour
    markers = [
        line.get_marker() for line in ax_n.get_lines() if not line.get_label().startswith("Manual")
    ]
    assert len(markers) == 3 and len(set(markers)) == 3
    pixels = _pixels(fig)
    for key, label, _ in RAN:
        assert _count(pixels, plots.COLOURS[key]) > 50, label
    plots.plt.close("all")


def test_optuna_tpe_and_cma_es_have_distinct_hues():
    """Magenta beside pink: the two peers read as one in the convergence figure."""
    hue = [colorsys.rgb_to_hsv(*to_rgb(plots.COLOURS[k]))[0] * 360 for k in ("optuna-tpe", "cma")]
    assert min(abs(hue[0] - hue[1]), 360 - abs(hue[0] - hue[1])) > 45


def _slice(cost: np.ndarray) -> ExperimentResults:
    grid = np.logspace(-6, 0, cost.size)
    fit = {"mean": np.nan_to_num(cost, nan=5.0).tolist(), "std": np.full(cost.size, 2.0).tolist()}
    return ExperimentResults(
        meta={},
        methods=[],
        cost_slice={
            "parameter": "q_vy",
            "grid": grid.tolist(),
            "cost": cost.tolist(),
            "sample_index": [0, 10, 20],
            "fits": {"gp": fit, "tsp": fit},
        },
    )


def test_the_cost_slice_holds_its_curve_marks_divergence_and_stays_above_zero():
    """The dense curve was clipped at the top, ended without a mark where the filter
    diverged, and the axis ran below 0 for a cost that cannot be negative."""
    cost = 0.05 + np.linspace(0.0, 1.0, 40) ** 4 * 5.0
    cost[-4:] = math.nan  # the filter diverged on the last grid points
    fig = plots.cost_slice(_slice(cost))
    ax = fig.axes[0]
    low, high = ax.get_ylim()
    assert low >= 0.0 and high > np.nanmax(cost)
    crosses = [line for line in ax.get_lines() if line.get_marker() == "x"]
    assert len(crosses) == 1
    grid = np.logspace(-6, 0, 40)
    np.testing.assert_allclose(crosses[0].get_xdata(), grid[-4:])
    assert all(low < y < high for y in crosses[0].get_ydata())  # inside the axes: seen
    assert any("diverged" in text for text in _legend_texts(fig))
    # a cost that may be negative (a log density) keeps its negative values in view
    fig = plots.cost_slice(_slice(np.linspace(-3.0, 1.0, 40)))
    assert fig.axes[0].get_ylim()[0] < -3.0
    plots.plt.close("all")


def test_dataset_show_keeps_its_legends_off_the_data_and_labels_the_4_ms2_lines(small):
    from kftune.cli.dataset import plot_manoeuvre
    from kftune.data import open_dataset

    fig = plot_manoeuvre(open_dataset(small).manoeuvres[0])
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legends = [ax for ax in fig.axes if ax.get_legend()]
    assert legends
    for ax in legends:
        box, inside = ax.get_legend().get_window_extent(renderer), ax.get_window_extent(renderer)
        assert box.x0 >= inside.x1, "the legend lies on the axes"
    acceleration = fig.axes[1]
    labelled = [
        line for line in acceleration.get_lines()
        if "4 m/s²" in line.get_label() and set(line.get_ydata()) == {4.0}
    ]  # fmt: skip
    assert labelled and any("4 m/s²" in t for t in _legend_texts(fig))
    plots.plt.close("all")


def test_evaluate_says_r_and_ay_are_scored_against_the_measurement(small):
    res = run_cli("evaluate", str(small), "--manual", "--split", "test", "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    for row in doc["manoeuvres"].values():
        assert row["rmse_r_vs_measured_degps"] == row["rmse_r"] > 0
        assert row["rmse_ay_vs_measured_mps2"] == row["rmse_ay"] > 0
    table = run_cli("evaluate", str(small), "--manual", "--split", "test")
    assert "r vs meas °/s" in table.stdout and "ay vs meas m/s²" in table.stdout
    assert "vs meas: RMSE against the measured channel" in table.stdout


def test_the_estimates_band_is_not_hidden_by_the_filters_start():
    """σ from P0 at the start (5° decaying in 0.1 s to 0.1°) set the axis, and the band of
    the remaining 20 s was a flat line at the bottom, too narrow to see."""
    t = np.arange(0.0, 20.0, 0.01)
    rng = np.random.default_rng(0)
    ref = np.radians(2.0 * np.sin(t))
    est = ref + np.radians(rng.normal(0.0, 0.1, t.size))
    std = np.radians(0.1 + 5.0 * np.exp(-t / 0.1))
    fig = plots.estimate_trace(t, est, std, ref, "β")
    title = fig.axes[0].get_title()
    assert "too narrow to see" not in title and "covers" in title
    low, high = fig.axes[1].get_ylim()  # the error panel
    assert high - low < 1.5 and high > 0.2 and low < -0.2  # [deg]: the later ±0.2° band
    plots.plt.close("all")


def test_a_models_channel_figure_shows_every_method_and_the_manual_one_dashed():
    """For a model reported by its channels: a filter on another's curve (GA exactly on
    TR-BO's here) was hidden under it."""
    t = np.linspace(0.0, 10.0, 1001)
    runs, trace = [], {"t": t, "v_ref": 10.0 + np.sin(t)}
    for key, label, err in (("manual", "Manual", 0.5), ("ga", "GA", 0.1), ("trbo", "TR-BO", 0.1)):
        runs.append(
            MethodRun(key=key, label=label, params={}, best_cost=1.0, n_evals=1,
                      wall_time_s=1.0, history_cost=[1.0], history_time_s=[1.0])
        )  # fmt: skip
        trace[f"v_{key}"] = trace["v_ref"] + err * np.sin(3.0 * t)
    results = ExperimentResults(
        meta={"scored_channels": {"v": "m/s"}}, methods=runs, traces={"run": trace}
    )
    fig = plots.channel_traces(results, "run", ("manual", "ga", "trbo"))
    pixels = _pixels(fig)
    for key, label, _ in (("manual", "Manual", 0), ("ga", "GA", 0), ("trbo", "TR-BO", 0)):
        assert label in _legend_texts(fig)
        assert _count(pixels, plots.COLOURS[key]) > 100, f"{label} cannot be seen"
    manual = next(line for line in fig.axes[0].get_lines() if line.get_label() == "Manual")
    assert manual.get_linestyle() == "--"
    plots.plt.close("all")
