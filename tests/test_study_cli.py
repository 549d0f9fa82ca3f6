"""Looking at one study: ``kftune study show/plot/export``, a larger budget on resume, and
``report`` pointing a study or a tuned file to the right command.

The references are independent of the readers under test: the study's rows read with
plain SQL, numpy's running minimum, Optuna's own ``load_study``, and a straight run of the
larger budget.
"""

from __future__ import annotations

import json
import sqlite3
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from kftune.errors import ConfigError
from kftune.optim import minimize

SPACE = {"a": (0.0, 1.0), "b": (1e-4, 10.0, "log10")}


def bowl(x: np.ndarray) -> float:
    """(2,) point → cost; fails (raises) where a > 0.85, as a diverged filter does."""
    if x[0] > 0.85:
        raise FloatingPointError("filter diverged: runaway: the estimate went beyond 60°")
    return float((x[0] - 0.3) ** 2 + (np.log10(x[1]) + 1.0) ** 2)


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    """A random-search study of 30 evaluations with some failures."""
    db = tmp_path_factory.mktemp("study") / "s.db"
    res = minimize(bowl, SPACE, "random", budget=30, seed=3, storage=db)
    assert 0 < res.n_failed < 30
    return db


def sql_rows(db: Path) -> list[tuple]:
    """(number, state, value, reason) of every row, read with plain SQL."""
    with sqlite3.connect(db) as conn:
        return conn.execute(
            "SELECT number, state, value, reason FROM trials ORDER BY number"
        ).fetchall()


def test_show_json_holds_every_trial_the_running_best_and_failures_by_reason(study):
    res = run_cli("study", "show", study, "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    rows = sql_rows(study)
    assert [(t["number"], t["state"], t["cost"]) for t in doc["trials"]] == [
        (n, s, v) for n, s, v, _ in rows
    ]
    values = np.array([np.inf if v is None else v for _, _, v, _ in rows])
    assert [t["best_so_far"] for t in doc["trials"]] == pytest.approx(
        np.minimum.accumulate(values).tolist()
    )
    k = int(np.argmin(values))
    assert doc["best"]["number"] == k and doc["best"]["cost"] == values[k]
    failed = [n for n, s, _, _ in rows if s == "failed"]
    assert doc["failed"] == len(failed) and doc["complete"] == len(rows) - len(failed)
    assert doc["failures"] == [
        {
            "reason": "filter diverged: runaway: the estimate went beyond 60°",
            "count": len(failed),
            "trials": failed,
        }
    ]
    for t in doc["trials"]:  # the failed ones are those with a > 0.85
        assert (t["params"]["a"] > 0.85) == (t["state"] == "failed")
    assert doc["method"] == "random" and doc["budget"] == 30
    assert [p["scale"] for p in doc["parameters"]] == ["linear", "log10"]


def test_show_text_has_a_row_per_trial_the_best_and_the_grouped_failures(study):
    res = run_cli("study", "show", study)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    rows = sql_rows(study)
    head = next(i for i, ln in enumerate(lines) if ln.split()[:1] == ["#"])
    table = lines[head + 1 : lines.index("", head)]
    assert [int(ln.split()[0]) for ln in table] == [n for n, *_ in rows]
    n_failed = sum(s == "failed" for _, s, _, _ in rows)
    assert f"failed: {n_failed} of 30: filter diverged" in res.stdout
    assert "FloatingPointError" not in res.stdout  # the kind, not the exception's class
    assert any(ln.startswith("best: #") for ln in lines)


def test_a_study_held_open_by_a_run_can_be_shown(study, tmp_path):
    from kftune.optim.study import Study, read_study

    with Study.open(study, read_study(study).settings, resume=True):
        res = run_cli("study", "show", study, "--json")
    assert res.returncode == 0, res.stderr
    assert len(json.loads(res.stdout)["trials"]) == 30


def test_plot_draws_the_running_best_and_each_parameter_in_its_box(study, tmp_path):
    from kftune.cli.study import _figures, summarise
    from kftune.optim.study import read_study

    res = run_cli("study", "plot", study, "-o", tmp_path / "f")
    assert res.returncode == 0, res.stderr
    for name in ("convergence.png", "parameters.png"):
        assert (tmp_path / "f" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    s = summarise(read_study(study))
    figs = _figures(s)
    ax = figs["convergence.png"].axes[0]
    best = next(ln for ln in ax.get_lines() if ln.get_label() == "best so far")
    assert best.get_ydata() == pytest.approx([t["best_so_far"] for t in s["trials"]])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(lbl.endswith(" failed, drawn at the top") for lbl in labels)
    # every complete evaluation is drawn: inside the axis, or marked on top of it
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    inside = lines["cost of each evaluation"].get_ydata()
    top = [ln for lbl, ln in lines.items() if lbl.startswith("cost above the axis")]
    n_top = len(top[0].get_xdata()) if top else 0
    assert len(inside) + n_top == sum(t["state"] == "complete" for t in s["trials"])
    assert max(inside) <= ax.get_ylim()[1]
    pa, pb = figs["parameters.png"].axes[:2]
    assert pa.get_ylim() == pytest.approx((0.0, 1.0)) and pa.get_yscale() == "linear"
    assert pb.get_ylim() == pytest.approx((1e-4, 10.0)) and pb.get_yscale() == "log"


@pytest.mark.slow
def test_export_loads_in_optuna_with_the_same_trials(study, tmp_path):
    optuna = pytest.importorskip("optuna")
    out = tmp_path / "o.db"
    res = run_cli("study", "export", study, "--optuna", out)
    assert res.returncode == 0, res.stderr
    assert f"optuna-dashboard sqlite:///{out}" in res.stdout
    loaded = optuna.load_study(study_name="s", storage=f"sqlite:///{out}")
    rows = sql_rows(study)
    assert len(loaded.trials) == len(rows)
    with sqlite3.connect(study) as conn:
        records = [
            json.loads(r) for (r,) in conn.execute("SELECT record FROM trials ORDER BY number")
        ]
    for trial, (number, state, value, reason), rec in zip(loaded.trials, rows, records):
        assert trial.user_attrs["kftune_number"] == number
        if state == "complete":
            assert trial.state == optuna.trial.TrialState.COMPLETE and trial.value == value
        else:
            assert trial.state == optuna.trial.TrialState.FAIL and trial.value is None
            assert trial.user_attrs["kftune_reason"] == reason
        assert trial.params == pytest.approx(rec["params"], rel=1e-12)
        assert not trial.distributions["a"].log and trial.distributions["b"].log
    assert loaded.best_trial.value == min(v for _, _, v, _ in rows if v is not None)
    again = run_cli("study", "export", study, "--optuna", out)
    assert again.returncode == 3 and "exists" in again.stderr
    assert optuna.load_study(study_name="s", storage=f"sqlite:///{out}").trials  # intact


def test_export_without_optuna_is_a_clear_configuration_error(study, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna → ImportError
    res = run_cli("study", "export", study, "--optuna", tmp_path / "o.db")
    assert res.returncode == 3
    assert "needs the package 'optuna'" in res.stderr and "Traceback" not in res.stderr
    assert not list(tmp_path.iterdir())  # no half export left


def test_not_a_study_is_named_and_report_points_to_study_show(study, tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("SECRET-CONTENT\n")
    res = run_cli("study", "show", text)
    assert res.returncode == 3 and "is not a kftune study" in res.stderr
    assert "SECRET-CONTENT" not in res.stderr
    missing = run_cli("study", "show", tmp_path / "nope.db")
    assert missing.returncode == 3 and "nope.db" in missing.stderr
    rep = run_cli("report", study)
    assert rep.returncode == 3 and f"kftune study show {study}" in rep.stderr
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"format": "kftune-tuned-1"}))
    for args in (("study", "show", tuned), ("report", tuned)):
        res = run_cli(*args)
        assert res.returncode == 3 and "is a tuned file" in res.stderr, args


# ---------------------------------------------------------------------- a larger budget
@pytest.mark.parametrize("method", ["trbo", "random", "optuna-tpe", "cma"])
def test_a_larger_budget_continues_a_finished_study_as_a_straight_run(method, tmp_path):
    """For a method whose proposals do not depend on the budget, 12 then resumed to 20 is
    the straight run of 20: the first 12 are replayed (the replay check), the rest continue
    exactly as they would have."""
    if method.startswith("optuna"):
        pytest.importorskip("optuna")
    if method == "cma":
        pytest.importorskip("cma")
    db = tmp_path / "s.db"
    first = minimize(bowl, SPACE, method, budget=12, seed=1, storage=db)
    more = minimize(bowl, SPACE, method, budget=20, seed=1, storage=db, resume=True)
    straight = minimize(bowl, SPACE, method, budget=20, seed=1)
    assert [r.u for r in more.history[:12]] == [r.u for r in first.history]
    assert [r.u for r in more.history] == [r.u for r in straight.history]
    assert more.n_evals == 20 and more.budget == 20
    from kftune.optim.study import read_study

    assert read_study(db).settings["budget"] == 20  # shown as the study's budget now


@pytest.mark.filterwarnings("ignore::kftune.errors.SettingWarning")  # GA's tiny budget
@pytest.mark.parametrize("method", ["tsbo-tsp", "ga"])
def test_a_larger_budget_is_refused_where_the_method_plans_by_it(method, tmp_path):
    db = tmp_path / "s.db"
    minimize(bowl, SPACE, method, budget=6, seed=1, storage=db)
    before = sql_rows(db)
    with pytest.raises(ConfigError, match="plans its run by the budget") as err:
        minimize(bowl, SPACE, method, budget=10, seed=1, storage=db, resume=True)
    assert "budget 6" in str(err.value) and "budget 10" in str(err.value)
    assert sql_rows(db) == before  # nothing changed
    with pytest.raises(ConfigError, match="budget"):  # a smaller one: refused as ever
        minimize(bowl, SPACE, method, budget=4, seed=1, storage=db, resume=True)


def test_tune_resume_with_a_larger_n_continues_the_study(small, tmp_path):
    db, out = tmp_path / "s.db", tmp_path / "t.json"
    common = ("tune", small, "-m", "random", "--storage", db, "-o", out, "--no-calibration")
    assert run_cli(*common, "-n", "4").returncode == 0
    first = sql_rows(db)
    res = run_cli(*common, "-n", "7", "--resume")
    assert res.returncode == 0, res.stderr
    rows = sql_rows(db)
    assert len(rows) == 7 and rows[:4] == first
    shown = json.loads(run_cli("study", "show", db, "--json").stdout)
    assert shown["budget"] == 7 and shown["finished"] == 7


# ---------------------------------------------------------------------- estimate by split
SPLITS = ("train", "test")


@pytest.fixture(scope="module")
def tuned(small, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tuned") / "t.json"
    res = run_cli("tune", small, "-m", "manual", "-o", out, "--no-calibration")
    assert res.returncode == 0, res.stderr
    return out


def estimate_json(small: Path, tuned: Path, out: Path, *args: str) -> dict:
    res = run_cli("estimate", small, "--params", tuned, "-o", out, "--no-plot", "--json", *args)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def test_estimate_never_averages_across_splits(small, tuned, tmp_path):
    from conftest import SMALL_TEST, SMALL_TRAIN

    doc = estimate_json(small, tuned, tmp_path / "all")
    assert doc["average"] is None and doc["consistency"] is None
    for split, names in (("train", SMALL_TRAIN), ("test", SMALL_TEST)):
        rmse = [doc["manoeuvres"][n]["kpis"]["rmse"] for n in names]
        assert doc["averages"][split]["rmse"] == pytest.approx(np.mean(rmse), rel=1e-12)
        assert doc["averages"][split]["n_manoeuvres"] == len(names)
    text = run_cli("estimate", small, "--params", tuned, "-o", tmp_path / "t", "--no-plot")
    firsts = [ln.split()[:2] for ln in text.stdout.splitlines()]
    assert ["average", "train"] in firsts and ["average", "test"] in firsts
    assert not any(f[:1] == ["average"] and len(f) > 1 and f[1] not in SPLITS for f in firsts)
    # the test split: by --split, by a pattern, and as evaluate scores it
    by_split = estimate_json(small, tuned, tmp_path / "s", "--split", "test")
    by_glob = estimate_json(small, tuned, tmp_path / "g", "-m", "test-*")
    assert list(by_split["manoeuvres"]) == list(by_glob["manoeuvres"]) == list(SMALL_TEST)
    assert by_split["average"] == by_glob["average"] == by_split["averages"]["test"]
    assert list(by_split["averages"]) == ["test"]
    ev = run_cli("evaluate", small, "--params", tuned, "--split", "test", "--json")
    assert ev.returncode == 0, ev.stderr
    held = json.loads(ev.stdout)["average"]["rmse"]
    assert by_split["average"]["rmse"] == pytest.approx(held, rel=1e-9)
    assert by_split["average"]["rmse"] != pytest.approx(doc["averages"]["train"]["rmse"])


def test_estimate_patterns_are_checked_against_the_split(small, tuned, tmp_path):
    res = run_cli(
        "estimate", small, "--params", tuned, "-o", tmp_path, "--split", "train", "-m", "test-*"
    )
    assert res.returncode == 3 and "no manoeuvre of the train split matches" in res.stderr
    res = run_cli("estimate", small, "--params", tuned, "-o", tmp_path, "-m", "zz*")
    assert res.returncode == 3 and "--manoeuvre: no manoeuvre 'zz*'" in res.stderr
    assert not list(tmp_path.iterdir())  # refused before any output
    res = run_cli("estimate", small, "--params", tuned, "-o", tmp_path, "--split", "held")
    assert res.returncode == 2


def test_a_far_off_cost_is_marked_on_top_not_squeezing_the_best_so_far():
    from kftune.cli.study import _figures

    costs = [1.0, 0.5, 9.0, 0.45, 0.44, 0.43, 0.43, 0.42, 0.42, 0.41, 0.41, 0.4]
    best = np.minimum.accumulate(costs).tolist()
    s = {
        "study": "s.db",
        "method": "random",
        "seed": 0,
        "parameters": [{"name": "a", "low": 0.0, "high": 1.0, "scale": "linear"}],
        "best": {"number": 11, "cost": 0.4, "params": {"a": 0.5}},
        "trials": [
            {"number": i, "state": "complete", "cost": c, "best_so_far": b, "params": {"a": 0.5}}
            for i, (c, b) in enumerate(zip(costs, best))
        ],
    }
    ax = _figures(s)["convergence.png"].axes[0]
    assert ax.get_ylim()[1] < 2.0  # the axis ends near the first best, not at 9
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    top = next(ln for label, ln in lines.items() if label.startswith("1 evaluation above the axis"))
    assert list(top.get_xdata()) == [2]


def test_a_running_trial_is_counted_and_left_out_of_the_export(study, tmp_path):
    import shutil

    from kftune.optim.study import Study, read_study

    db = tmp_path / "cut.db"
    shutil.copy(study, db)
    with Study.open(db, read_study(db).settings, resume=True) as open_study:
        open_study.write_proposal(30, [0.5, 0.5])  # in flight when its process was killed
    doc = json.loads(run_cli("study", "show", db, "--json").stdout)
    assert doc["running"] == [30] and doc["finished"] == 30
    assert "1 running or cut off" in run_cli("study", "show", db).stdout
    pytest.importorskip("optuna")
    res = run_cli("study", "export", db, "--optuna", tmp_path / "o.db")
    assert res.returncode == 0 and "30 trials" in res.stdout and "1 running left out" in res.stdout


def test_a_two_stage_joint_tuning_refuses_another_budget_before_touching_a_study(small, tmp_path):
    db, out = tmp_path / "j.db", tmp_path / "j.json"
    common = ("tune", small, "--tune-model", "mu=0.8:1.6", "--cost", "nrmse", "--storage", db)
    first = run_cli(*common, "-n", "8", "-o", out, "--no-calibration")
    assert first.returncode == 0, first.stderr
    noise = tmp_path / "j.noise-only.db"
    before = (sql_rows(noise), sql_rows(db))
    res = run_cli(*common, "-n", "16", "-o", out, "--no-calibration", "--resume")
    assert res.returncode == 3 and "cannot be continued with another budget" in res.stderr
    assert (sql_rows(noise), sql_rows(db)) == before
    from kftune.optim.study import read_study

    assert read_study(noise).settings["budget"] == 2  # a quarter of 8, as planned


@pytest.mark.filterwarnings("default::kftune.errors.SettingWarning")  # said, not raised
@pytest.mark.filterwarnings("error::UserWarning")  # a parameter tried at one value only
def test_show_names_a_joint_tunings_first_stage_and_plot_names_the_cost(small, tmp_path):
    from kftune.cli.study import _figures, summarise
    from kftune.optim.study import read_study

    db = tmp_path / "j.db"
    tuned = run_cli("tune", small, "--tune-model", "mu=0.8:1.6", "--storage", db, "-n", "8",
                    "-o", tmp_path / "j.json", "--no-calibration")  # fmt: skip
    assert tuned.returncode == 0, tuned.stderr
    assert "initial designs" in tuned.stderr  # -n 8 leaves both stages inside their designs
    noise = tmp_path / "j.noise-only.db"
    assert noise.is_file()
    shown = run_cli("study", "show", db)
    assert shown.returncode == 0, shown.stderr
    assert f"first stage (noise only) of this joint tuning: {noise}" in shown.stdout
    first = run_cli("study", "show", noise)
    assert first.returncode == 0 and "first stage" not in first.stdout
    record = json.loads((tmp_path / "j.json").read_text())["cost_spec"]
    kind, normalise = record["kind"], record["normalise"]  # what tune minimised, as it says
    for path in (db, noise):
        ax = _figures(summarise(read_study(path)))["convergence.png"].axes[0]
        assert ax.get_ylabel() == f"cost J: {kind}, {normalise}-normalised"
    # the paper's cost, per manoeuvre, which the objective's summary leaves unsaid
    paper = tmp_path / "p.db"
    res = run_cli("tune", small, "--cost", "nrmse", "--storage", paper, "-n", "2", "-m", "random",
                  "-o", tmp_path / "p.json", "--no-calibration")  # fmt: skip
    assert res.returncode == 0, res.stderr
    ax = _figures(summarise(read_study(paper)))["convergence.png"].axes[0]
    assert ax.get_ylabel() == "cost J: nrmse, manoeuvre-normalised"
    assert run_cli("study", "show", paper).stdout.count("first stage") == 0


def test_plot_of_a_study_without_an_objective_says_only_cost(study):
    from kftune.cli.study import _figures, summarise
    from kftune.optim.study import read_study

    s = summarise(read_study(study))
    assert s["objective"] is None and s["first_stage"] is None
    assert _figures(s)["convergence.png"].axes[0].get_ylabel() == "cost J"
