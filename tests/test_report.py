"""Report: results round trip, tables by hand, figures written."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from kftune.errors import DataError
from kftune.report import ExperimentResults, MethodRun, all_tables, write_report
from kftune.report.tables import relative_improvement


def _metrics(scale: float) -> dict:
    return {
        "skidpad-1": {
            "rmse": 0.5 * scale,
            "mae": 1.0 * scale,
            "rmse_non": 0.6 * scale,
            "mae_non": 1.0 * scale,
            "rmse_beta": 0.5 * scale,
            "rmse_r": 0.2 * scale,
            "rmse_ay": 0.3 * scale,
        },
        "slalom-1": {
            "rmse": 0.3 * scale,
            "mae": 0.8 * scale,
            "rmse_non": math.nan,
            "mae_non": math.nan,
            "rmse_beta": 0.3 * scale,
            "rmse_r": 0.1 * scale,
            "rmse_ay": 0.2 * scale,
        },
    }


@pytest.fixture
def results() -> ExperimentResults:
    t = np.linspace(0, 5, 501)
    runs = []
    for key, label, scale, n in (
        ("manual", "Manual", 2.0, 1),
        ("ga", "GA", 1.0, 30),
        ("tsbo-tsp", "TSBO - tSP", 0.8, 12),
    ):
        costs = list(np.linspace(2.0, scale, n))
        if n > 3:
            costs[2] = math.nan  # a failed evaluation
        runs.append(
            MethodRun(
                key=key,
                label=label,
                params={"q_vx": 1e-3 * scale, "q_vy": 1e-5},
                best_cost=scale,
                n_evals=n,
                wall_time_s=0.1 * n,
                history_cost=costs,
                history_time_s=list(0.1 * np.arange(1, n + 1)),
                metrics={"test": _metrics(scale)},
                averages={
                    "train": {
                        "rmse": scale,
                        "mae": 2 * scale,
                        "rmse_non": math.nan,
                        "mae_non": 1.0,
                    },
                    "test": {"rmse": scale, "mae": 2 * scale, "rmse_non": scale, "mae_non": 1.0},
                },
                extra={"stage": [None] * n},
            )
        )
    grid = np.logspace(-6, 0, 20)
    return ExperimentResults(
        meta={
            "dataset": {"name": "synthetic", "n_train": 1, "n_test": 2},
            "manoeuvres": {"skidpad-1": {"kind": "skidpad", "split": "test"}},
        },
        methods=runs,
        cost_slice={
            "parameter": "q_vy",
            "grid": grid.tolist(),
            "cost": (1 + np.log10(grid) ** 2 / 10).tolist(),
            "sample_index": [0, 5, 10],
            "fits": {
                "gp": {"mean": np.ones(20).tolist(), "std": np.full(20, 0.1).tolist()},
                "tsp": {"mean": np.ones(20).tolist(), "std": np.full(20, 0.2).tolist()},
            },
        },
        traces={
            "skidpad-1": {
                "t": t,
                "beta_ref": 0.01 * np.sin(t),
                "beta_ga": 0.011 * np.sin(t),
                "beta_tsbo-tsp": 0.0105 * np.sin(t),
            }
        },
    )


def test_save_load_round_trip(results, tmp_path):
    results.save(tmp_path)
    # strict JSON: no NaN/Infinity tokens
    json.loads(
        (tmp_path / "results.json").read_text(),
        parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"),
    )
    back = ExperimentResults.load(tmp_path)
    assert [m.key for m in back.methods] == ["manual", "ga", "tsbo-tsp"]
    ga = back.method("ga")
    assert (
        math.isnan(ga.history_cost[2])
        and ga.history_cost[:2] == results.method("ga").history_cost[:2]
    )
    assert math.isnan(ga.metrics["test"]["slalom-1"]["rmse_non"])
    assert ga.extra == {"stage": [None] * 30}
    np.testing.assert_array_equal(
        back.traces["skidpad-1"]["beta_ga"], results.traces["skidpad-1"]["beta_ga"]
    )
    assert back.cost_slice["sample_index"] == [0, 5, 10]


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match=r"results\.json"):
        ExperimentResults.load(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        ExperimentResults.load(tmp_path)


def test_best_so_far_skips_failures(results):
    best = results.method("ga").best_so_far()
    assert best[2] == best[1]  # the failed evaluation does not change the running best
    assert np.all(np.diff(best) <= 0)


def test_tables(results):
    tables = all_tables(results)
    cost = tables["cost"]
    assert cost.rows[2][:3] == ("TSBO - tSP", 0.8, 12)
    assert (2, 1) in cost.bold  # lowest cost in bold
    kpi = tables["kpi_test"]
    assert kpi.header == ("KPI", "Manual", "GA", "TSBO - tSP")
    assert kpi.rows[0] == ("RMSE [deg]", 2.0, 1.0, 0.8)
    assert (0, 3) in kpi.bold and (3, 1) in kpi.bold and (3, 2) in kpi.bold  # ties all bold
    md = tables["kpi_train"].to_markdown()
    assert "| RMSE_NON [deg] | – | – | – |" in md
    rel = relative_improvement(results)
    assert rel["skidpad-1"]["rmse_beta"] == pytest.approx(20.0)


@pytest.mark.slow
def test_write_report_writes_everything(results, tmp_path):
    path = write_report(results, tmp_path / "rep")
    text = path.read_text()
    for fig in ("convergence.png", "improvement_test.png", "beta_skidpad-1.png", "cost_slice.png"):
        assert (tmp_path / "rep" / "figures" / fig).stat().st_size > 5000
        assert f"figures/{fig}" in text
    for csv in ("cost", "kpi_train", "kpi_test", "per_manoeuvre", "parameters"):
        assert (tmp_path / "rep" / "tables" / f"{csv}.csv").is_file()
    # rebuilding from the stored results gives identical tables
    results.save(tmp_path / "res")
    path2 = write_report(ExperimentResults.load(tmp_path / "res"), tmp_path / "rep2")
    assert path2.read_text() == text
    for csv in ("cost", "kpi_test", "per_manoeuvre"):
        assert (tmp_path / "rep2" / "tables" / f"{csv}.csv").read_text() == (
            tmp_path / "rep" / "tables" / f"{csv}.csv"
        ).read_text()


def test_figure_names_from_manoeuvre_names_stay_in_the_figures_folder(
    results, tmp_path, monkeypatch
):
    """Trace names come from a dataset's manifest: a name that is a path, or two names that
    reduce to the same file name, still give one figure each inside ``figures/``."""
    from kftune.report import plots

    for name in ("convergence", "beta_trace"):  # the names matter here, not the drawing
        monkeypatch.setattr(plots, name, lambda *args: None)
    monkeypatch.setattr(plots, "save", lambda fig, path: path.write_bytes(b"png"))
    trace = results.traces["skidpad-1"]
    results.traces = {"../../evil": trace, "a/b": trace, "a_b": trace}
    results.methods = [m for m in results.methods if m.key != "ga"]  # no improvement figure
    results.cost_slice = {}
    text = write_report(results, tmp_path / "rep").read_text()
    figures = sorted(p.name for p in (tmp_path / "rep" / "figures").iterdir())
    assert figures == ["beta__.._evil.png", "beta_a_b.png", "beta_a_b_.png", "convergence.png"]
    assert all(f"figures/{f}" in text for f in figures)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]


def test_values_that_print_alike_are_all_bold():
    from kftune.report.tables import Table

    t = Table(
        "t",
        ("KPI", "A", "B", "C"),
        (("x", 0.4541, 0.4539, 0.5),),
        groups=(((0, 1), (0, 2), (0, 3)),),
    )
    assert t.bold == {(0, 2)}  # full precision: one best
    assert (
        t.to_markdown()
        == "| KPI | A | B | C |\n| --- | --- | --- | --- |\n| x | **0.454** | **0.454** | 0.500 |"
    )


@pytest.mark.parametrize(
    "span", [(0.0012, 0.009), (0.025, 0.09), (0.055, 0.09), (0.02, 5.0), (0.01, 300.0)]
)
def test_convergence_time_labels_do_not_overlap(results, span):
    """Under a decade of wall time, the log axis labelled its minor ticks too, and
    "3×10⁻²4×10⁻²6×10⁻²" ran together."""
    from kftune.report import plots

    for m in results.methods:
        m.history_time_s = list(np.geomspace(*span, len(m.history_time_s)))
    fig = plots.convergence(results)
    fig.canvas.draw()
    ax = fig.axes[1]
    boxes = [
        t.get_window_extent()
        for t in (*ax.get_xticklabels(), *ax.get_xticklabels(minor=True))
        if t.get_visible()
        and t.get_text()
        and ax.get_xlim()[0] <= t.get_position()[0] <= ax.get_xlim()[1]
    ]
    assert len(boxes) >= 2  # the axis is labelled
    boxes.sort(key=lambda b: b.x0)
    assert all(a.x1 <= b.x0 for a, b in itertools.pairwise(boxes)), [b.x0 for b in boxes]


def test_parameter_note_names_the_columns_it_has():
    from kftune.report import parameter_note

    note = parameter_note(("q_vx", "q_vy", "q_r", "r_scale", "ukf_alpha"))
    assert "(m/s)² for vx and vy, (rad/s)² for r" in note and "r_scale: " in note
    assert "ukf_alpha, ukf_beta, ukf_kappa" in note and "r_<measurement>" not in note
    note = parameter_note(("q_px", "q_py", "r_z_scale"))  # another model: no sideslip units
    assert "rad/s" not in note and "r_<measurement>_scale" in note
    assert parameter_note(("gain",)) == ""


def test_small_values_keep_three_significant_digits():
    """A tuned variance of 0.00154 printed with three decimals read 0.002 (+30 %)."""
    from kftune.report.tables import Table

    t = Table("t", ("Method", "q_vx", "q_r", "a", "b"), (("TR-BO", 0.00154, 0.0999, 0.9996, 1.0),))
    row = t.to_markdown().splitlines()[-1]
    assert row == "| TR-BO | 0.00154 | 0.0999 | 1.000 | 1.000 |"  # one format from 1 on
    assert float(row.split("|")[2]) == pytest.approx(0.00154, rel=5e-3)


def test_report_names_best_points_on_a_bound(results, tmp_path):
    hit = {"parameter": "q_r", "side": "upper", "value": 0.998, "bound": 1.0}
    results.method("tsbo-tsp").extra["on_bounds"] = [hit]
    results.method("ga").extra["on_bounds"] = []
    results.traces, results.cost_slice = {}, None  # fewer figures: faster
    results.save(tmp_path / "res")  # the report reads it back from results.json
    text = write_report(ExperimentResults.load(tmp_path / "res"), tmp_path / "rep").read_text()
    assert "## Best points on a bound of the search box" in text
    assert "- TSBO - tSP: q_r = 0.998, on its upper bound 1\n" in text
    assert "- GA:" not in text and "- Manual:" not in text
    results.method("tsbo-tsp").extra["on_bounds"] = []
    text = write_report(results, tmp_path / "rep2").read_text()
    assert "No method's best point lies within 1 % of a bound" in text


def test_report_says_the_burn_in_when_there_is_one(results, tmp_path):
    """The burn-in changes every KPI: report.md says it (not only results.json)."""
    results.traces, results.cost_slice = {}, None  # fewer figures: faster
    results.meta["burn_in_s"] = 1.0
    text = write_report(results, tmp_path / "rep").read_text()
    assert "- Burn-in: the first 1 s of every manoeuvre left out" in text
    results.meta["burn_in_s"] = 0.0  # the paper's: nothing to say
    assert "Burn-in" not in write_report(results, tmp_path / "rep2").read_text()


def test_a_method_that_diverged_has_a_consistency_row_saying_so(results, tmp_path):
    """One method consistent on the test split, one whose filter diverged on a test
    manoeuvre (its pooled consistency None), one not recorded: a row each for the first
    two; the diverged row's empty numbers are null in the JSON records, not NaN."""
    from kftune.report.tables import consistency_table
    from kftune.tuning.consistency import as_doc, channel_consistency, nis_consistency

    rng = np.random.default_rng(0)
    e = rng.normal(0.0, 1.0, 2000)
    beta = channel_consistency(e, np.ones(e.size), np.zeros(e.size))
    results.methods[0].consistency = {"test": as_doc({"beta": beta}, nis_consistency(e**2, 1))}
    results.methods[1].consistency = {"test": None}
    table = consistency_table(results, "test")
    assert [row[0] for row in table.rows] == ["Manual", "GA"]
    assert table.rows[0][-1] == "consistent" and table.rows[1][-1] == "diverged"
    assert table.rows[0][2] == pytest.approx(100 * beta.coverage[0])
    json.dumps(table.to_records(), allow_nan=False)
    md = write_report(results, tmp_path).read_text()
    assert "## Consistency of the tuned filters on the test set" in md
    assert not (tmp_path / "figures" / "reliability.png").exists()  # no curves recorded


@pytest.mark.parametrize(
    ("mean", "said"),
    [(13.9, "σ is about 3.7× too small"), (165.0, "σ is about 13× too small"),
     (110150.0, "σ is about 332× too small"), (0.25, "σ is about 2× too large"),
     (1.08, "σ is about 1.04× too small")],
)  # fmt: skip
def test_the_verdict_says_by_how_much_sigma_is_off(mean, said):
    """√(mean NEES): the factor that would bring the mean NEES to 1; no exponent."""
    from kftune.report.tables import sigma_verdict

    assert sigma_verdict({"mean": mean, "inside": False}) == said
    assert sigma_verdict({"mean": mean, "inside": True}) == "consistent"
    assert sigma_verdict({"mean": None, "inside": None}) == "–"
    # errors that wander slowly: a band so wide that passing it proves nothing
    few = sigma_verdict({"mean": 2.24, "inside": True, "n_eff": 5.0})
    assert few == "too few independent errors to tell (about 5)"
    assert sigma_verdict({"mean": 1.1, "inside": True, "n_eff": 400.0}) == "consistent"


@pytest.mark.slow
def test_the_cost_table_and_report_say_how_many_evaluations_failed_and_why(results, tmp_path):
    ga = results.method("ga")
    ga.history_cost[5] = ga.history_cost[9] = math.nan  # three failed of 30, with index 2
    runaway = "filter diverged: runaway: the estimated sideslip went beyond ±60°"
    ga.extra["failures"] = [
        {"number": 2, "reason": f"FilterDivergedError: {runaway} on manoeuvre 'a' at step 7 "
                                "(t = 0.07 s)"},
        {"number": 5, "reason": f"FilterDivergedError: {runaway} on manoeuvre 'b' at step 90 "
                                "(t = 0.90 s)"},
        {"number": 9, "reason": "non-finite value nan"},
    ]  # fmt: skip
    cost = all_tables(results)["cost"]
    failed = cost.header.index("Failed")
    assert [row[failed] for row in cost.rows] == [0, 3, 1]  # the fixture fails TSBO's third
    assert cost.rows[1][1] == 1.0  # the best cost is the run's, unchanged
    text = write_report(results, tmp_path).read_text()
    assert f"- **GA**: 3 of 30 evaluations failed: {runaway} (2); non-finite value nan (1)" in text
    assert "- **TSBO - tSP**: 1 of 12 evaluations failed: no reasons recorded" in text
    assert "**Manual**" not in text
    csv_rows = (tmp_path / "tables" / "cost.csv").read_text().splitlines()
    assert csv_rows[0].split(",")[3] == "Failed" and csv_rows[2].split(",")[3] == "3"
    del ga.extra["failures"]  # results from before the reasons were recorded
    text = write_report(results, tmp_path / "old").read_text()
    assert "- **GA**: 3 of 30 evaluations failed: no reasons recorded" in text


def test_compare_records_its_failed_evaluations_grouped_by_kind(small, tmp_path):
    """A method's run as compare records it (:func:`kftune.experiment.method_run`), with two
    evaluations that diverged on different manoeuvres: results.json counts them and groups
    their reasons into one kind, the report gives it under the cost table."""
    from dataclasses import replace

    from kftune.data import open_dataset
    from kftune.experiment import method_run, tune
    from kftune.tuning.problem import TuningProblem

    ds = open_dataset(small)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    result = tune(problem, "manual", progress=False)
    cause = "filter diverged: runaway: the estimated sideslip went beyond ±60°"
    failed = tuple(
        replace(
            result.history[0],
            number=n,
            value=None,
            state="failed",
            reason=f"FilterDivergedError: {cause} on manoeuvre {name!r} at step {n} (t = 0.0{n} s)",
        )
        for n, name in ((1, ds.train[0].name), (2, ds.train[1].name))
    )
    result = replace(result, history=(*result.history, *failed), n_evals=3, n_failed=2)
    run, _ = method_run("manual", result, problem, {"test": ds.test[:1]})
    assert run.best_cost == result.fun and run.extra["n_failed"] == 2
    ExperimentResults(meta={}, methods=[run]).save(tmp_path / "res")
    doc = json.loads((tmp_path / "res" / "results.json").read_text())
    assert doc["methods"][0]["extra"]["failure_kinds"] == [[cause, 2]]
    text = write_report(ExperimentResults.load(tmp_path / "res"), tmp_path / "rep").read_text()
    assert f"- **Manual**: 2 of 3 evaluations failed: {cause} (2)" in text
