"""Figures and messages that misled a newcomer who followed the README: the log cost axis
of the convergence figures labels enough values that every line can be read (the manual
filter's 1.52 and the first cost 1.28 lay above the last label, 1), `study plot`'s legend
counts evaluations rather than showing a bare number, the report draws TR-BO against the
manual filter beside the paper's Fig. 7 (which says what it is), the estimate's band is the
tables' ±1.96σ, and a resume on another dataset says to name the study's dataset instead
of suggesting --cost nrmse."""

from __future__ import annotations

import itertools
import json
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import SMALL_TEST, SMALL_TRAIN, run_cli
from kftune.errors import ObjectiveMismatchError
from kftune.report import ExperimentResults, MethodRun, plots, write_report


def _labels(axis: Any) -> dict[float, str]:
    """The labelled ticks of ``axis`` inside its limits (the figure drawn): value → text."""
    axis.figure.canvas.draw()
    low, high = sorted(axis.get_view_interval())
    return {
        float(tick.get_loc()): tick.label1.get_text()
        for tick in axis.get_major_ticks() + axis.get_minor_ticks()
        if tick.label1.get_visible() and tick.label1.get_text() and low <= tick.get_loc() <= high
    }


def _readable(value: float, labelled: list[float]) -> bool:
    """Whether ``value`` lies between two labelled ticks at most 30 % apart (read by eye to
    a few per cent), or within 5 % of one."""
    below = [v for v in labelled if v <= value]
    above = [v for v in labelled if v >= value]
    near = any(abs(v / value - 1) <= 0.05 for v in labelled)
    return near or bool(below and above and min(above) / max(below) <= 1.3)


def _no_overlap(axis: Any) -> None:
    """No two of ``axis``'s tick labels overlap on the page."""
    renderer = axis.figure.canvas.get_renderer()
    ticks = axis.get_major_ticks() + axis.get_minor_ticks()
    shown = [t.label1 for t in ticks if t.label1.get_visible() and t.label1.get_text()]
    boxes = sorted((label.get_window_extent(renderer) for label in shown), key=lambda b: b.y0)
    for a, b in itertools.pairwise(boxes):
        assert a.y1 <= b.y0 + 0.5, "two y tick labels overlap"


def _run(key: str, label: str, costs: np.ndarray, rmse: dict[str, float]) -> MethodRun:
    return MethodRun(
        key=key,
        label=label,
        params={"q_vy": 1e-4},
        best_cost=float(costs.min()),
        n_evals=costs.size,
        wall_time_s=0.01 * costs.size,
        history_cost=costs.tolist(),
        history_time_s=(0.01 * np.arange(1, costs.size + 1)).tolist(),
        metrics={"test": {m: dict(rmse) for m in ("m1", "m2")}},
    )


#: RMSEs on the test manoeuvres: TR-BO's β a third of the manual filter's; its yaw rate
#: against the gyro it copies near 0, its ay against the measurement larger.
RMSE = {
    "manual": {"rmse_beta": 0.47, "rmse_r": 0.10, "rmse_ay": 0.05},
    "trbo": {"rmse_beta": 0.155, "rmse_r": 0.0002, "rmse_ay": 0.35},
    "ga": {"rmse_beta": 0.148, "rmse_r": 0.05, "rmse_ay": 0.30},
    "tsbo-tsp": {"rmse_beta": 0.150, "rmse_r": 0.05, "rmse_ay": 0.29},
}


def _results(keys: tuple[str, ...]) -> ExperimentResults:
    """The README's default run in small: the manual filter at J = 1.52, tuners from 1.28
    down to about 0.36."""
    labels = {"manual": "Manual", "trbo": "TR-BO", "ga": "GA", "tsbo-tsp": "TSBO-tSP"}
    runs = []
    for i, key in enumerate(keys):
        costs = np.array([1.521]) if key == "manual" else np.geomspace(1.28, 0.355 + 0.01 * i, 40)
        runs.append(_run(key, labels[key], costs, RMSE[key]))
    split = {"split": "test", "kind": "slalom"}
    return ExperimentResults(meta={"manoeuvres": {"m1": split, "m2": split}}, methods=runs)


def test_the_convergence_axis_labels_the_manual_line_and_the_first_cost():
    fig = plots.convergence(_results(("manual", "ga", "tsbo-tsp", "trbo")))
    ax = fig.axes[0]
    labels = _labels(ax.yaxis)
    assert any(v > 1.0 for v in labels), f"no label above 1: {labels}"
    for value in (1.521, 1.28, 0.36):  # the manual line, the first cost, the end
        assert _readable(value, list(labels)), (value, labels)
    for v, text in labels.items():  # plain numbers, each its tick's value
        assert float(text) == pytest.approx(v, rel=1e-6)
    _no_overlap(ax.yaxis)
    legend = [t.get_text() for t in ax.get_legend().texts]
    assert "Manual (J = 1.521)" in legend
    plots.plt.close("all")


@pytest.mark.parametrize("low, high", [(0.33, 1.6), (1.2, 1.6), (0.01, 50.0), (3e-4, 2e3)])
def test_a_log_y_axis_labels_values_that_fit(low, high):
    """Over under a decade and over many: at least three labels, none overlapping, and
    every value between the limits readable."""
    _, ax = plots.plt.subplots(figsize=(5, 3.8))
    ax.plot([0, 1], [low, high])
    ax.set_yscale("log")
    ax.set_ylim(low, high)
    plots.label_log_axis(ax.yaxis, low, high, vertical=True)
    labels = _labels(ax.yaxis)
    assert len(labels) >= 3, labels
    _no_overlap(ax.yaxis)
    if high / low < 10:  # under a decade: any value can be read between two labels
        for value in np.geomspace(low * 1.05, high / 1.05, 9):
            assert _readable(float(value), list(labels)), (value, labels)
    plots.plt.close("all")


def _summary(costs: list[float | None]) -> dict[str, Any]:
    """``kftune study show --json``'s summary of a study of ``costs`` (None: failed)."""
    trials, best, best_t = [], None, None
    for i, c in enumerate(costs):
        if c is not None and (best is None or c < best):
            best, best_t = c, i
        trials.append({"number": i, "cost": c, "best_so_far": best, "params": {"q_r": 0.1}})
    return {
        "study": "study.db",
        "method": "trbo",
        "seed": 0,
        "objective": "8 manoeuvres (a … b), car, cost nrmse (dataset-normalised)",
        "trials": trials,
        "best": {"number": best_t, "cost": best, "params": {"q_r": 0.1}},
        "parameters": [{"name": "q_r", "low": 1e-10, "high": 1.0, "scale": "log10"}],
    }


def test_study_plot_counts_the_evaluations_above_its_axis():
    """ "cost above the axis (3)" read as a threshold of 3."""
    from kftune.cli.study import _figures

    costs: list[float | None] = [0.63, 0.47, 1.95, 0.25, 0.41, 0.21, 1.01, 0.8, 0.2, 0.21]
    costs += [0.2] * 10 + [None]
    figs = _figures(_summary(costs))
    ax = figs["convergence.png"].axes[0]
    legend = [t.get_text() for t in ax.get_legend().texts]
    above = next(t for t in legend if "above the axis" in t)
    top = ax.get_ylim()[1]
    assert above.startswith("2 evaluations above the axis (cost > ")
    assert float(above.split("cost > ")[1].split(")")[0]) == pytest.approx(top, rel=1e-3)
    assert "1 evaluation failed, drawn at the top" in legend
    plots.plt.close("all")


def test_study_plot_labels_its_log_axis():
    """Costs over three decades are drawn on a log axis, whose labels reach the first
    cost."""
    from kftune.cli.study import _figures

    costs: list[float | None] = [40.0, 12.0, 3.0, 1.4, 0.5, 0.3, 0.2, 0.19, 0.19, 0.18]
    ax = _figures(_summary(costs))["convergence.png"].axes[0]
    assert ax.get_yscale() == "log"
    labels = _labels(ax.yaxis)
    for value in (40.0, 1.4, 0.19):
        assert _readable(value, list(labels)) or len(labels) >= 4, (value, labels)
    assert max(labels) >= 10.0
    _no_overlap(ax.yaxis)
    plots.plt.close("all")


@pytest.mark.slow
def test_the_report_draws_trbo_against_the_manual_filter_and_names_the_papers_figure(
    tmp_path, monkeypatch
):
    drawn: list[tuple[tuple[Any, ...], dict[str, Any]]] = []
    improvement = plots.improvement

    def spy(*args: Any, **kwargs: Any) -> Any:
        drawn.append((args[1:], kwargs))
        return improvement(*args, **kwargs)

    monkeypatch.setattr(plots, "improvement", spy)
    write_report(_results(("manual", "ga", "tsbo-tsp", "trbo")), tmp_path / "all")
    # TR-BO's figure: β alone (r and ay are scored against the sensors its filter copies)
    assert [kw.get("metrics") for args, kw in drawn if args == ("manual", "trbo")] == [
        ("rmse_beta",)
    ]
    assert [kw.get("metrics") for args, kw in drawn if not args] == [None]  # the paper's
    md = (tmp_path / "all" / "report.md").read_text()
    assert (tmp_path / "all" / "figures" / "improvement_trbo_test.png").is_file()
    assert (tmp_path / "all" / "figures" / "improvement_test.png").is_file()
    assert "(paper Fig. 7)" in md and "Neither is kftune tune's default" in md
    assert md.index("improvement_trbo_test.png") < md.index("improvement_test.png")
    # without GA: TR-BO's figure stays, the paper's is not drawn
    write_report(_results(("manual", "trbo")), tmp_path / "trbo")
    figures = tmp_path / "trbo" / "figures"
    assert (figures / "improvement_trbo_test.png").is_file()
    assert not (figures / "improvement_test.png").exists()


def test_trbos_improvement_draws_beta_alone_and_the_papers_says_what_it_is():
    results = _results(("manual", "ga", "tsbo-tsp", "trbo"))
    fig = plots.improvement(results, "manual", "trbo", heading="TR-BO", metrics=("rmse_beta",))
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_legend().texts] == ["RMSE β"]
    heights = [p.get_height() for p in ax.patches]
    assert heights == pytest.approx([100 * (0.47 - 0.155) / 0.47] * 2)
    assert ax.get_title().startswith("TR-BO\nTR-BO vs Manual")
    fig = plots.improvement(results, heading="Paper Fig. 7: x")
    ax = fig.axes[0]
    assert len([t.get_text() for t in ax.get_legend().texts]) == 3
    assert ax.get_title().startswith("Paper Fig. 7: x\nTSBO-tSP vs GA")
    plots.plt.close("all")


def test_the_estimates_band_is_the_tables_196_sigma():
    t = np.arange(0.0, 10.0, 0.01)
    ref = np.radians(2.0 * np.sin(t))
    est = ref + np.radians(0.05 * np.cos(7.0 * t))
    std = np.full(t.size, np.radians(0.1))
    fig = plots.estimate_trace(t, est, std, ref, "β")
    ax = fig.axes[0]
    band = ax.collections[0]
    assert band.get_label() == "±1.96σ (95 %)"
    top = band.get_paths()[0].vertices[:, 1].max()
    assert top == pytest.approx(np.degrees(est).max() + 1.96 * 0.1, abs=1e-3)
    legend = [t.get_text() for a in fig.axes if a.get_legend() for t in a.get_legend().texts]
    assert "±1.96σ (95 %)" in legend and not any("±2σ" in x for x in legend)
    assert "±1.96σ band" in ax.get_title() and "±2σ" not in ax.get_title()
    plots.plt.close("all")


def test_the_mismatch_hint_names_the_data_or_the_cost_not_both_blindly():
    from kftune.cli.tune import mismatch_hint

    def hint(stored: str, current: str, default_cost: bool = True) -> str:
        exc = ObjectiveMismatchError("refused", stored, current)
        return mismatch_hint(exc, "default", "s2.db", default_cost)

    mine = "8 manoeuvres (log_001 … log_008), car, cost nrmse (dataset-normalised)"
    bundled = "8 manoeuvres (train-01 … train-08), car, cost nrmse (dataset-normalised)"
    other_data = hint(mine, bundled)
    assert "(log_001 … log_008)" in other_data and "name the dataset it was made on" in other_data
    assert "--storage s2.db --resume" in other_data and "--cost nrmse" not in other_data
    paper_cost = "8 manoeuvres (a … b), car, cost nrmse"
    default = "8 manoeuvres (a … b), car, cost nrmse (dataset-normalised)"
    paper = hint(paper_cost, default)
    assert "resumes with --cost nrmse" in paper and "other data" not in paper
    assert hint(paper_cost, default, default_cost=False) == ""
    same = hint(mine, mine)  # the same summaries: the same names, other samples
    assert "other samples" in same and "--cost nrmse" not in same


def test_tune_resumed_on_another_dataset_says_to_name_the_studys(
    small: Path, tmp_path: Path
) -> None:
    from kftune.data import default_dataset, save_dataset

    other = tmp_path / "other"
    names = ("train-01-braking-in-turn", "train-02-skidpad", *SMALL_TEST)
    save_dataset(default_dataset().subset(names), other)
    db = tmp_path / "s2.db"
    made = run_cli("tune", str(small), "-n", "2", "-q", "--storage", str(db), "-o",
                   str(tmp_path / "t.json"))  # fmt: skip
    assert made.returncode == 0, made.stderr
    refused = run_cli("tune", str(other), "-n", "2", "-q", "--storage", str(db), "--resume",
                      "-o", str(tmp_path / "u.json"))  # fmt: skip
    assert refused.returncode == 3, refused.stderr
    err = refused.stderr
    assert f"({SMALL_TRAIN[0]} … {SMALL_TRAIN[-1]})" in err
    assert f"kftune tune {small.resolve()} --storage {db} --resume" in err
    assert "--cost nrmse" not in err and "Traceback" not in err
    # the dataset is recorded to name it, not to match it: the same data moved elsewhere
    # resume, and so does a study made before datasets were recorded
    moved = tmp_path / "moved"
    shutil.copytree(small, moved)
    again = run_cli("tune", str(moved), "-n", "3", "-q", "--storage", str(db), "--resume",
                    "-o", str(tmp_path / "v.json"))  # fmt: skip
    assert again.returncode == 0, again.stderr
    with sqlite3.connect(db) as conn:
        (text,) = conn.execute("SELECT value FROM meta WHERE key = 'settings'").fetchone()
        settings = json.loads(text)
        assert settings["objective"].pop("dataset")["path"] == str(moved.resolve())  # the last
        conn.execute("UPDATE meta SET value = ? WHERE key = 'settings'", (json.dumps(settings),))
    old = run_cli("tune", str(small), "-n", "3", "-q", "--storage", str(db), "--resume",
                  "-o", str(tmp_path / "w.json"))  # fmt: skip
    assert old.returncode == 0, old.stderr
