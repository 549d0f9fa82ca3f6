"""The kftune command: help, errors and exit codes, --json, an end-to-end compare on a small
subset, report rebuilding, and --resume after a SIGKILL. Commands run in this process
(``run_cli``) unless the test is about the process itself (the entry point, signals, a
closed pipe, SIGKILL), which runs ``python -m kftune``."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shlex
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import (
    DEV_FULL,
    HANG_GUARD,
    SMALL_TEST,
    SMALL_TRAIN,
    default_sigint,
    run_cli,
    run_killed_after,
    wait_until,
)
from conftest import completed_trials as _completed
from kftune.cli import SUBCOMMANDS, main
from kftune.data import default_dataset, save_dataset

kftune = run_cli


def kftune_process(
    *args: str, cwd: Path | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "kftune", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
    )


def test_estimate_help_says_it_needs_a_kftune_dataset():
    text = " ".join(kftune("estimate", "--help").stdout.split())
    assert "a kftune dataset: its folder or manifest" in text
    assert "kftune dataset import FILE... --mapping MAP -o DIR" in text


def test_help_of_every_command():
    top = kftune_process("--help")  # the entry point, as a user runs it
    assert top.returncode == 0
    for name in SUBCOMMANDS:
        assert name in top.stdout
        sub = kftune(name, "--help")
        assert sub.returncode == 0, sub.stderr
        assert sub.stdout.startswith(f"usage: kftune {name}")


@pytest.mark.parametrize(
    "args",
    [
        ("tune", "--budget", "many"),
        ("compare", "--methods", "simulated-annealing"),
        ("evaluate",),  # needs --params, --q or --manual
        ("frobnicate",),
    ],
)
def test_bad_options_exit_2(args):
    res = kftune(*args)
    assert res.returncode == 2
    assert "usage:" in res.stderr


@pytest.mark.parametrize(
    ("args", "command", "said"),
    [
        (("tune", "my-car", "--budjet", "12"), "tune", "unrecognized arguments: --budjet 12"),
        (
            ("tune", "-n", "0"),
            "tune",
            "argument --budget/-n: expected an integer >= 1 and <= 100000, got '0'",
        ),
        (("evaluate",), "evaluate", "one of the arguments --params/-p --q --manual is required"),
        (("dataset", "info", "--bogus"), "dataset info", "unrecognized arguments: --bogus"),
    ],
)
def test_a_subcommands_error_names_the_subcommand_in_two_lines(args, command, said):
    """A mistyped option of ``tune`` is tune's error (argparse leaves it to the top-level
    parser, which printed ``usage: kftune [-h] …``), and a bad value gives a short usage,
    not every option of the command."""
    res = kftune(*args)
    assert res.returncode == 2
    assert res.stderr.splitlines() == [
        f"usage: kftune {command} [options] [dataset]",
        f"kftune {command}: error: {said} (see kftune {command} --help)",
    ], res.stderr


def test_the_short_usage_shows_the_required_options():
    """``dataset import`` without -o: the usage line names what is required."""
    res = kftune("dataset", "import", "a.csv", "--mapping", "m.toml")
    assert res.returncode == 2
    usage = res.stderr.splitlines()[0]
    assert usage.startswith("usage: kftune dataset import [options] ")
    assert "--mapping MAPPING" in usage and "--out OUT" in usage and "SOURCE" in usage


def test_weights_errors_name_the_option_once():
    res = kftune("tune", "--weights", "beta=five")
    assert res.returncode == 2
    assert "argument --weights: expected CHANNEL=NUMBER items" in res.stderr, res.stderr


def test_compare_budget_wants_a_method():
    """tune's --budget takes N, compare's METHOD=N: a bare N says how to write it."""
    res = kftune("compare", "--budget", "12")
    assert res.returncode == 2
    assert "expected METHOD=N" in res.stderr and "e.g. --budget trbo=12" in res.stderr
    help_text = kftune("compare", "--help").stdout
    assert "e.g. --budget trbo=12" in " ".join(help_text.split())


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (("--cost", "pem", "--normalise", "dataset"), "--normalise"),
        (("--cost", "nis", "--weights", "beta=1"), "--weights"),
    ],
)
def test_an_option_the_chosen_cost_does_not_use_is_refused(tmp_path, args, option):
    res = kftune("tune", *args, "--quiet", "-o", str(tmp_path / "t.json"))
    assert res.returncode == 2 and option in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "t.json").exists()


def test_bad_files_exit_3_and_name_the_file(tmp_path):
    missing = tmp_path / "no-such-dataset"
    res = kftune("tune", str(missing), "--quiet", cwd=tmp_path)
    assert res.returncode == 3
    assert "no-such-dataset" in res.stderr
    cfg = tmp_path / "bad.toml"
    cfg.write_text("budjet = 40\n")
    res = kftune("tune", "--config", str(cfg), "--quiet", cwd=tmp_path)
    assert res.returncode == 3
    assert "bad.toml" in res.stderr and "'budjet'" in res.stderr
    cfg.write_text("budget = 40\n[cost]\nweights = { yaw = 1.0 }\n")
    res = kftune("tune", "--config", str(cfg), "--quiet", cwd=tmp_path)
    assert res.returncode == 3 and "unknown cost channel" in res.stderr
    assert "bad.toml, [cost] key 'weights'" in res.stderr
    bad_params = tmp_path / "tuned.json"
    bad_params.write_text('{"q": [1, 2]}')
    res = kftune("evaluate", "--params", str(bad_params))
    assert res.returncode == 3 and "tuned.json" in res.stderr
    res = kftune("report", str(tmp_path))
    assert res.returncode == 3 and "results.json" in res.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("compare", "--budget", "ga=lots"),
        ("compare", "--budget", "ga=0"),
        ("tune", "--weights", "beta=five"),
        ("tune", "--seed", "-1"),
        ("tune", "--timeout", "-5"),
        ("tune", "--budget", "0"),
        ("tune", "--workers", "0"),
        ("tune", "--burn-in", "-1"),
        ("tune", "--normalise", "channel"),
        ("evaluate", "--q", "-1", "1", "1"),
        ("evaluate", "--q", "nan", "1", "1"),
        ("compare", "--resume", "--force"),
    ],
)
def test_bad_option_values_exit_2_and_name_the_option(args):
    res = kftune(*args, "--json")
    assert res.returncode == 2, res.stderr
    assert "usage:" in res.stderr and "Traceback" not in res.stderr
    option = next(a for a in args if a.startswith("--") and a != "--json")
    assert option in res.stderr


@pytest.mark.slow
def test_the_readme_configuration_serves_every_command(tmp_path):
    """The README's configuration block (the TOML block with a [cost] table), as it is, for
    tune, evaluate and compare: another command's keys (budgets for compare) are left out,
    not refused."""
    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    toml_blocks = [b.split("```", 1)[0] for b in readme.split("```toml\n")[1:]]
    (block,) = [b for b in toml_blocks if re.search(r"^\[cost\]", b, re.M)]
    assert "budgets" in block and "[cost]" in block
    cfg = tmp_path / "run.toml"
    cfg.write_text(block)
    from kftune.cli._common import load_config

    assert "budgets" not in load_config(cfg, "tune") and "budgets" in load_config(cfg, "compare")
    assert "seed" not in load_config(cfg, "evaluate") and load_config(cfg, "tune")["seed"] == 0
    res = kftune("tune", "--config", str(cfg), "-n", "2", "-q", "-o", str(tmp_path / "t.json"))
    assert res.returncode == 0, res.stderr
    res = kftune("evaluate", "--config", str(cfg), "--params", str(tmp_path / "t.json"))
    assert res.returncode == 0, res.stderr
    res = kftune(
        "compare", "--config", str(cfg), "--methods", "manual", "-q", "-o", str(tmp_path / "c")
    )
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["evaluate", "--q", "1", "2"], "--q"),
        (["evaluate", "--manual", "--weights", "bta=5"], "--weights"),
        (["tune", "--weights", "bta=5,r=1", "-n", "2"], "--weights"),
        (["tune", "--timeout", "5", "--batch", "2", "-n", "2"], "--batch"),
        (["tune", "-m", "manual", "--widen-bounds"], "--widen-bounds"),
        (["tune", "--resume", "-n", "2"], "--storage"),
        (["tune", "--model", "unicycle", "-n", "2"], "--model"),
        (["compare", "--methods", "manual", "manual"], "--methods"),
    ],
)
def test_values_and_contradictions_that_argparse_cannot_see_exit_2(tmp_path, args, named):
    """Options well-formed for argparse but wrong for the run (a channel the model has not,
    options that exclude each other) are still usage errors, naming the option."""
    res = kftune(*args, "-q" if args[0] != "evaluate" else "--json", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert named in res.stderr and "Traceback" not in res.stderr
    assert not any(tmp_path.iterdir())  # refused before anything was written


@pytest.mark.parametrize(
    ("command", "text", "expected"),
    [
        ("tune", "q_bounds = [1e-3, 1]", "'q_bounds': unknown"),  # belongs in [parameters]
        ("tune", "seed = -2", "key 'seed': expected an integer >= 0, got -2"),
        ("compare", "[budgets]\nga = 0", "[budgets] key 'ga': expected an integer >= 1"),
        ("tune", "[budgets]\nga = 0", "'ga': expected an int"),  # another command's: still checked
        ("evaluate", "[options.ga]\npopulation_size = 0", "population_size"),
        ("tune", "[options.tsbo-tsp]\nmax_fee = 3", "max_fee"),
        ("tune", "[parameters]\nq_bounds = ['a', 1]", "key 'q_bounds': expected [low, high]"),
        ("tune", "[parameters]\nq_bounds = [1, 1e-3]", "below"),
        ("tune", "[cost]\nkind = 'mse'", "[cost] key 'kind': expected one of ['nrmse'"),
        ("tune", "[cost]\nweights = { beta = -1.0 }", "beta"),
        ("tune", "[cost]\nnormalise = 'run'", "[cost] key 'normalise': expected one of"),
        ("tune", "[cost]\nkind = 'pem'\nnormalise = 'dataset'", "nrmse cost only"),
        ("compare", "[options.tsbo-gp]\nmode = 'fast'", "mode"),
        ("compare", "[ukf]\nalpha = -1.0", "alpha"),
    ],
)
def test_bad_configuration_exits_3_and_names_file_and_key(tmp_path, command, text, expected):
    cfg = tmp_path / "run.toml"
    cfg.write_text(text + "\n")
    extra = ("--manual",) if command == "evaluate" else ("--quiet", "--out", str(tmp_path / "o"))
    res = kftune(command, "--config", str(cfg), *extra)
    assert res.returncode == 3, res.stderr
    assert "Traceback" not in res.stderr and expected in res.stderr
    assert str(cfg) in res.stderr, res.stderr


def test_timeout_with_worker_pool_is_refused(small, tmp_path):
    res = kftune(
        "tune",
        str(small),
        "--timeout",
        "5",
        "--workers",
        "2",
        "--quiet",
        "-o",
        str(tmp_path / "t.json"),
    )
    assert res.returncode == 3 and "workers = 1" in res.stderr


def test_evaluate_averages_every_column_and_explains_a_non_kpi_of_no_samples(tmp_path, capsys):
    import numpy as np

    from kftune.data import Dataset

    ds = default_dataset()
    calm = ds["test-14-lane-change"].slice(0, 300)
    assert np.abs(calm.ay).max() < 4.0  # no sample where the _NON KPIs are taken
    save_dataset(Dataset("calm", ds.vehicle, ds.dt, [ds["test-05-j-turn"], calm]), tmp_path)
    assert main(["evaluate", str(tmp_path), "--manual", "--split", "test", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = doc["manoeuvres"]
    assert rows[calm.name]["rmse_non"] is None and rows[calm.name]["n_non"] == 0
    for key in ("rmse_r_vs_measured_degps", "rmse_ay_vs_measured_mps2", "rmse", "rmse_non"):
        values = [row[key] for row in rows.values() if row[key] is not None]
        assert doc["average"][key] == pytest.approx(np.mean(values), rel=1e-12)
    assert main(["evaluate", str(tmp_path), "--manual", "--split", "test"]) == 0
    lines = capsys.readouterr().out.splitlines()
    average = next(line for line in lines if line.startswith("average")).split()
    assert len(average) == 1 + 6 and "–" not in average  # the r and ay columns too
    assert float(average[5]) == pytest.approx(doc["average"]["rmse_r_vs_measured_degps"], abs=1e-4)
    assert any(
        line.startswith("_NON –: no sample with |ay| >= 4 m/s² in 1 of 2") and calm.name in line
        for line in lines
    )


def test_tune_then_evaluate_json(small, tmp_path):
    out = tmp_path / "tuned.json"
    # the paper's cost and Q alone (tune's own default: test_tune_default.py)
    res = kftune("tune", str(small), "-n", "6", "--cost", "nrmse", "--json", "-o", str(out))
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["method"] == "trbo" and doc["n_evals"] == 6  # the default method
    assert set(doc["params"]) == {"q_vx", "q_vy", "q_r"}
    assert json.loads(out.read_text())["cost"] == doc["cost"]
    ev = kftune(
        "evaluate", str(small), "--params", str(out), "--split", "train", "--json",
        "--no-calibration",
    )  # fmt: skip
    assert ev.returncode == 0, ev.stderr
    evd = json.loads(ev.stdout)
    # the tuned cost on the training split is what tune reported, of the filter as tuned
    assert evd["cost"] == pytest.approx(doc["cost"], rel=1e-12) and evd["cov_scale"] == 1.0
    assert set(evd["manoeuvres"]) == set(SMALL_TRAIN)
    assert {"rmse", "mae", "rmse_non", "mae_non"} <= set(evd["average"])
    manual = kftune("evaluate", str(small), "--manual", "--json")
    assert manual.returncode == 0 and json.loads(manual.stdout)["q"] == [1e-6, 1e-4, 1e-6]
    # tune's held-out evidence is what evaluate finds on the test split, tuned (and
    # calibrated, as it is deployed) and manual
    held = doc["held_out"]
    assert held["calibration_factor"] == doc["calibration"]["factor"] != 1.0
    assert held["n_manoeuvres"] == len(SMALL_TEST)
    for args, key in (
        (("--params", str(out)), "beta_rmse_deg"),
        (("--manual",), "manual_beta_rmse_deg"),
    ):
        test = kftune("evaluate", str(small), *args, "--split", "test", "--json")
        assert json.loads(test.stdout)["average"]["rmse"] == pytest.approx(held[key], rel=1e-12)
    text = kftune("tune", str(small), "-n", "6", "-o", str(tmp_path / "again.json"))
    assert f"on the {len(SMALL_TEST)} held-out test manoeuvres: β RMSE" in text.stdout


def test_no_held_out_evidence_without_test_manoeuvres(tmp_path):
    only_train = tmp_path / "train-only"
    save_dataset(default_dataset().subset(SMALL_TRAIN), only_train)
    res = kftune("tune", str(only_train), "-n", "3", "--json", "-o", str(tmp_path / "t.json"))
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["held_out"] is None


def test_a_dataset_normalised_cost_is_recorded_and_evaluated_the_same_way(small, tmp_path):
    out = tmp_path / "tuned.json"
    res = kftune(
        "tune", str(small), "-n", "4", "--normalise", "dataset", "--json", "-o", str(out),
        "--no-calibration",  # the cost of the filter as tuned
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert json.loads(out.read_text())["cost_spec"]["normalise"] == "dataset"
    ev = kftune("evaluate", str(small), "--params", str(out), "--split", "train", "--json")
    evd = json.loads(ev.stdout)
    assert evd["cost_normalise"] == "dataset"
    assert evd["cost"] == pytest.approx(doc["cost"], rel=1e-12)
    # the same point under the paper's Eq. 15 is another number
    paper = kftune(
        "evaluate",
        str(small),
        "--params",
        str(out),
        "--split",
        "train",
        "--json",
        "--normalise",
        "manoeuvre",
    )
    assert json.loads(paper.stdout)["cost_normalise"] == "manoeuvre"
    assert json.loads(paper.stdout)["cost"] != pytest.approx(doc["cost"], rel=1e-3)


@pytest.mark.slow
def test_tune_gives_trbo_100_evaluations_and_compare_the_papers_40(small, tmp_path):
    res = kftune("tune", str(small), "--json", "--quiet", "-o", str(tmp_path / "t.json"))
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["n_evals"] == 100
    rep = kftune(
        "compare", str(small), "--methods", "manual", "trbo", "--json", "--quiet",
        "--out", str(tmp_path / "rep"),
    )  # fmt: skip
    assert rep.returncode == 0, rep.stderr
    cost = {row["Method"]: row for row in json.loads(rep.stdout)["tables"]["cost"]}
    assert cost["TR-BO"]["Evaluations"] == 40 and cost["Manual"]["Evaluations"] == 1


@pytest.mark.slow
def test_compare_writes_report_and_report_rebuilds_it(small, tmp_path):
    out = tmp_path / "rep"
    res = kftune(
        "compare", str(small), "--out", str(out), "--json",
        "--budget", "ga=8", "--budget", "tsbo-gp=6", "--budget", "tsbo-tsp=6",
        "--budget", "trbo=6",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    cost = {row["Method"]: row for row in doc["tables"]["cost"]}
    assert set(cost) == {"Manual", "GA", "TSBO-GP", "TSBO-tSP", "TR-BO"}
    assert cost["GA"]["Evaluations"] == 8 and cost["TSBO-tSP"]["Evaluations"] == 6
    assert cost["TR-BO"]["Evaluations"] == 6
    # results.json records, per method, where its best point lies on a bound (within 1 % of
    # the range; closed form on the default log10 box [1e-10, 1])
    for run in json.loads((out / "results.json").read_text())["methods"]:
        u = {n: (math.log10(v) + 10.0) / 10.0 for n, v in run["params"].items()}
        expected = [(n, "lower" if u[n] <= 0.01 else "upper") for n in u if abs(u[n] - 0.5) >= 0.49]
        assert [(h["parameter"], h["side"]) for h in run["extra"]["on_bounds"]] == expected
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert "convergence.png" in figures and "cost_slice.png" in figures
    # the cost slice goes through the default tuner's optimum, and the caption says so
    saved = json.loads((out / "results.json").read_text())
    assert saved["cost_slice"]["through"] == "TR-BO"
    report = (out / "report.md").read_text()
    assert "through the TR-BO optimum" in report
    # every method that ran, the manual filter too (the paper's three were hard-coded)
    assert (
        "β estimated by the filters of Manual, GA, TSBO-GP, TSBO-tSP, TR-BO "
        "against the reference" in report
    )
    assert "improvement_test.png" in figures and "beta_test-05-j-turn.png" in figures
    # the studies are not thrown away by accident; resuming finished studies evaluates
    # nothing new and reproduces the tables
    again = kftune("compare", str(small), "--out", str(out), "--quiet")
    assert again.returncode == 3 and "resume" in again.stderr
    resumed = kftune(
        "compare", str(small), "--out", str(out), "--json", "--resume",
        "--budget", "ga=8", "--budget", "tsbo-gp=6", "--budget", "tsbo-tsp=6",
        "--budget", "trbo=6",
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    assert json.loads(resumed.stdout)["tables"]["cost"] == doc["tables"]["cost"]
    # rebuild elsewhere from the stored results only: identical report and tables
    again = kftune("report", str(out), "--out", str(tmp_path / "again"))
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "again" / "report.md").read_text() == (out / "report.md").read_text()
    for csv in (out / "tables").glob("*.csv"):
        assert (tmp_path / "again" / "tables" / csv.name).read_text() == csv.read_text()


@pytest.mark.slow
def test_tune_resume_after_sigkill_equals_uninterrupted_run(small, tmp_path):
    budget = "24"
    full = kftune("tune", str(small), "-n", budget, "--quiet", "-o", str(tmp_path / "full.json"))
    assert full.returncode == 0, full.stderr
    db = tmp_path / "study.db"
    killed = ("tune", small, "-n", budget, "--quiet", "--storage", db)
    run_killed_after(db, 8, *killed, "-o", tmp_path / "killed.json")
    assert _completed(db) == 8, "the run was not killed after its 8th evaluation"
    with sqlite3.connect(db) as conn:
        before = conn.execute("SELECT number, value FROM trials WHERE state='complete'").fetchall()
    # without --resume an existing study is refused
    refused = kftune("tune", str(small), "--storage", str(db), "--quiet")
    assert refused.returncode == 3 and "--resume" in refused.stderr
    res = kftune(
        "tune",
        str(small),
        "-n",
        budget,
        "--quiet",
        "--storage",
        str(db),
        "--resume",
        "-o",
        str(tmp_path / "resumed.json"),
    )
    assert res.returncode == 0, res.stderr
    with sqlite3.connect(db) as conn:
        after = dict(conn.execute("SELECT number, value FROM trials WHERE state='complete'"))
    assert len(after) == 24
    assert all(after[n] == v for n, v in before)  # nothing finished was lost or redone
    resumed = json.loads((tmp_path / "resumed.json").read_text())
    uninterrupted = json.loads((tmp_path / "full.json").read_text())
    assert resumed["params"] == uninterrupted["params"]
    assert resumed["cost"] == uninterrupted["cost"]


def _cpu_seconds(pid: int, since: float) -> float:
    """CPU time [s] the process ``pid`` has used: how far it got, also on a loaded machine
    (Linux /proc; elsewhere the wall time since ``since``)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return time.monotonic() - since
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _interrupt_tune(
    args: list[str], ready, sig: int = signal.SIGINT
) -> subprocess.CompletedProcess:
    """Run ``kftune tune ARGS`` and send ``sig`` once ``ready(process)`` holds."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "kftune", "tune", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint,
    )  # fmt: skip
    try:
        wait_until(lambda: ready(proc), proc, "the moment to interrupt tune")
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=HANG_GUARD)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.slow
def test_ctrl_c_keeps_the_best_so_far_and_says_how_to_resume(small, tmp_path):
    db = tmp_path / "s.db"
    res = _interrupt_tune(
        [str(small), "-m", "ga", "-n", "5000", "--quiet", "--storage", str(db),
         "-o", str(tmp_path / "t.json")],
        ready=lambda proc: _completed(db) >= 20,
    )  # fmt: skip
    assert res.returncode == 130, res.stderr
    assert "--resume" in res.stderr and str(db) in res.stderr
    partial = json.loads((tmp_path / "t.partial.json").read_text())
    assert partial["status"] == "interrupted" and partial["n_evals"] >= 20
    assert _completed(db) >= partial["n_evals"]  # every finished evaluation is in the study
    start = time.monotonic()
    res = _interrupt_tune(
        [str(small), "-m", "ga", "-n", "5000", "--quiet", "-o", str(tmp_path / "u.json")],
        ready=lambda proc: _cpu_seconds(proc.pid, start) > 6,  # started up, evaluating
    )  # fmt: skip
    assert res.returncode == 130
    assert "nothing else was saved" in res.stderr and "saved in" not in res.stderr


def _children(pid: int) -> set[int]:
    """The child processes of ``pid`` (Linux /proc; empty elsewhere)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        with contextlib.suppress(OSError):
            out |= {int(c) for c in task.read_text().split()}
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


@pytest.mark.slow
def test_sigterm_is_handled_as_ctrl_c_with_exit_143(small, tmp_path):
    """Batch schedulers stop a job with SIGTERM: the best point so far and the resume hint
    as for Ctrl-C, no traceback, exit 143, and the pool's workers go too."""
    db = tmp_path / "s.db"
    workers: set[int] = set()

    def ready(proc) -> bool:
        workers.update(_children(proc.pid))
        return _completed(db) >= 10

    res = _interrupt_tune(
        [str(small), "-m", "ga", "-n", "5000", "--quiet", "--storage", str(db),
         "--workers", "2", "-o", str(tmp_path / "t.json")],
        ready=ready,
        sig=signal.SIGTERM,
    )  # fmt: skip
    assert res.returncode == 143, res.stderr
    assert "--resume" in res.stderr and "Traceback" not in res.stderr
    partial = json.loads((tmp_path / "t.partial.json").read_text())
    assert partial["status"] == "interrupted" and _completed(db) >= partial["n_evals"] >= 10
    if Path("/proc").is_dir():
        assert workers, "the pool's workers were not seen"
        deadline = time.monotonic() + 120  # a hang guard: load stretches their exit
        while any(map(_alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(map(_alive, workers))


@pytest.mark.slow
def test_a_reader_that_closes_early_gets_no_traceback():
    """``kftune dataset info | true``: exit 141 as for SIGPIPE, nothing on stderr."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "kftune", "dataset", "info"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader goes away before anything is written
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=HANG_GUARD) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err


@pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")
@pytest.mark.parametrize("json_flag", [[], ["--json"]])
@pytest.mark.slow
def test_a_full_standard_output_is_a_message_not_a_traceback(json_flag):
    """``kftune evaluate --manual > /dev/full``: exit 1 and one line saying what failed."""
    with DEV_FULL.open("w") as full:
        proc = subprocess.run(
            [sys.executable, "-m", "kftune", "evaluate", "--manual", *json_flag],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=300,
        )
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert "cannot write standard output" in proc.stderr, proc.stderr


def test_unwritable_outputs_are_refused_before_any_work(tmp_path):
    """Output paths are checked first: exit 3 naming the option, no traceback, and no
    tuning run spent before a crash at the end."""
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    cases = [
        (["tune", "-q", "--storage", str(tmp_path / "missing" / "s.db")], "--storage"),
        (["tune", "-q", "-n", "1000", "-o", str(tmp_path / "missing" / "t.json")], "--out"),
        (["compare", "-q", "--out", str(a_file)], "--out"),
        (["compare", "-q", "--out", str(a_file / "sub")], "--out"),
        (["dataset", "show", "-o", str(tmp_path)], "--out"),
    ]
    for args, option in cases:
        start = time.process_time()  # CPU time (this process runs the command): no work
        proc = kftune(*args)  # spent, however loaded the machine (wall time stretches)
        assert proc.returncode == 3, (args, proc.stderr)
        assert "Traceback" not in proc.stderr and option in proc.stderr, proc.stderr
        assert time.process_time() - start < 30, args


def test_the_readme_documents_the_exit_code_of_an_unwritable_output():
    """An output path that cannot be written is refused before any work with exit 3 (see
    the test above); the README's table said exit 1 for it."""
    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    codes = " ".join(readme.split("Exit codes:", 1)[1].split("130 interrupted", 1)[0].split())
    three = codes.split("; 3 ", 1)[1]
    assert "output or study path that cannot be written" in three
    assert "refused before any work starts" in three


def test_output_checks(tmp_path):
    from kftune.cli.outputs import output_dir, output_file
    from kftune.errors import ConfigError

    f = tmp_path / "f"
    f.write_text("x")
    assert output_file(tmp_path / "new.json", "--out") == tmp_path / "new.json"
    assert output_dir(tmp_path / "a" / "b", "--out") == tmp_path / "a" / "b"
    for call, path, expected in [
        (output_file, tmp_path, "is a folder"),
        (output_file, tmp_path / "no" / "x.json", "does not exist"),
        (output_file, f / "x.json", f"{f} is a file, not a folder"),
        (output_file, f / "sub" / "x.json", f"{f} is a file, not a folder"),
        (output_dir, f, "is a file"),
        (output_dir, f / "a" / "b", "lies below the file"),
    ]:
        with pytest.raises(ConfigError, match=expected):
            call(path, "--out")


def test_a_filter_that_diverges_everywhere_fails_cleanly(tmp_path):
    """Every evaluation runs away (Q pinned near 1e8: the sideslip estimate leaves ±60° at
    once): ``tune`` and ``compare`` exit 1 with a message naming the cause — no traceback,
    also not from the untimed warm-up evaluation of ``compare``."""
    ds = default_dataset().subset(("train-01-braking-in-turn", "test-05-j-turn"))
    save_dataset(ds, tmp_path / "d")
    cfg = tmp_path / "c.toml"
    cfg.write_text("[parameters]\nq_bounds = [1e8, 1.1e8]\n")
    common = ("--config", str(cfg), "--quiet")
    res = kftune("tune", str(tmp_path / "d"), "-n", "3", "-o", str(tmp_path / "t.json"), *common)
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    assert "every evaluation of 'trbo' failed (3 of 3)" in res.stderr  # the default method
    assert "diverged" in res.stderr
    res = kftune("compare", str(tmp_path / "d"), "--methods", "manual", "random",
                 "--budget", "random=3", "--out", str(tmp_path / "r"), *common)  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr and "every evaluation of 'manual' failed" in res.stderr


def test_manual_points_in_a_config_are_accepted(small, tmp_path):
    cfg = tmp_path / "m.toml"
    cfg.write_text("[options.manual]\npoints = [[1e-6, 1e-5, 1e-3]]\n")
    # the paper's cost, Q alone: the points are Q's
    res = kftune("tune", str(small), "-m", "manual", "--config", str(cfg), "--quiet", "--json",
                 "--cost", "nrmse", "-o", str(tmp_path / "t.json"))  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["q"] == [1e-6, 1e-5, 1e-3]


def test_tune_reports_a_best_point_on_a_bound(small, tmp_path, capsys):
    """The manual point (1e-6, 1e-4, 1e-6) clipped into q ∈ [1e-10, 1e-7] lies on the upper
    bound of every parameter: tune says so, and the file and --json record it. (In-process,
    like the widening test below: each subprocess start costs seconds.)"""
    cfg = tmp_path / "narrow.toml"
    cfg.write_text("[parameters]\nq_bounds = [1e-10, 1e-7]\n")
    out = tmp_path / "tuned.json"
    args = ["tune", str(small), "--config", str(cfg), "-m", "manual", "--quiet", "-o", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    for name in ("q_vx", "q_vy", "q_r"):
        assert f"best point on a bound: {name} = 1e-07 lies within 1 % of its upper" in text
    assert main([*args, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [(h["parameter"], h["side"], h["bound"]) for h in doc["on_bounds"]] == [
        (n, "upper", 1e-7) for n in ("q_vx", "q_vy", "q_r")
    ]
    assert json.loads(out.read_text())["on_bounds"] == doc["on_bounds"]
    assert main([*args, "--widen-bounds"]) == 2  # both on the command line: usage
    assert "manual" in capsys.readouterr().err
    cfg.write_text("widen_bounds = true\n[parameters]\nq_bounds = [1e-10, 1e-7]\n")
    assert main(args) == 3  # one of them from the configuration
    assert "manual" in capsys.readouterr().err


def test_tune_widen_bounds_runs_on_a_wider_box_and_resumes(small, tmp_path, capsys):
    """In q ∈ [1e-10, 1e-9], far below the optimum, TSBO's best point (seed 0, 8
    evaluations) ends on bounds; widen_bounds widens them and tunes again in a follow-up
    study beside --storage, which --resume replays without evaluating anything."""
    cfg = tmp_path / "narrow.toml"
    cfg.write_text("widen_bounds = true\n[parameters]\nq_bounds = [1e-10, 1e-9]\n")
    db = tmp_path / "study.db"
    args = ["tune", str(small), "--config", str(cfg), "-m", "tsbo-tsp", "-n", "8"]
    args += ["--storage", str(db), "--cost", "nrmse"]  # the paper's cost, Q alone
    assert main([*args, "--json", "-o", str(tmp_path / "t.json")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["n_evals"] > 8 and (tmp_path / "study.widen1.db").exists()
    highs = [p["high"] for p in doc["search_space"]["params"]]
    lows = [p["low"] for p in doc["search_space"]["params"]]
    assert max(highs) == pytest.approx(1e-7) or min(lows) == pytest.approx(1e-12)
    assert main([*args, "--quiet"]) == 3
    assert "--resume" in capsys.readouterr().err
    assert main([*args, "--resume", "--json", "-o", str(tmp_path / "r.json")]) == 0
    back = json.loads(capsys.readouterr().out)
    assert (back["cost"], back["params"], back["n_evals"]) == (
        doc["cost"],
        doc["params"],
        doc["n_evals"],
    )


def test_the_held_out_line_says_when_the_tuned_filter_is_the_worse_one():
    from kftune.cli.tune import held_out_line

    better = {"n_manoeuvres": 3, "beta_rmse_deg": 0.15, "manual_beta_rmse_deg": 0.47}
    assert "worse" not in held_out_line(better) and "β RMSE 0.150°" in held_out_line(better)
    for tuned in (0.5, None):  # worse than the rule of thumb, or diverged
        line = held_out_line({**better, "beta_rmse_deg": tuned})
        assert "the tuned filter is the worse one there" in line
    assert "diverged" in held_out_line({**better, "beta_rmse_deg": None})
    both = held_out_line({**better, "beta_rmse_deg": None, "manual_beta_rmse_deg": None})
    assert "worse" not in both


@pytest.mark.parametrize(
    ("error", "said"),
    [
        (ValueError("cannot compute KPIs of an empty manoeuvre"), "the test manoeuvres could not"),
        (KeyboardInterrupt(), "skipped (interrupted); the tuned parameters are saved"),
    ],
)
def test_the_tuned_file_is_kept_when_the_held_out_evidence_fails(
    small, tmp_path, monkeypatch, error, said
):
    import kftune.tuning.problem as problem_module

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(problem_module, "assess", fail)
    out = tmp_path / "t.json"
    res = kftune("tune", str(small), "-n", "3", "--quiet", "-o", str(out))
    assert res.returncode == 0, res.stderr
    assert f"no held-out evidence: {said}" in res.stdout
    doc = json.loads(out.read_text())
    assert doc["held_out"] is None and len(doc["q"]) == 3


def test_evaluate_changes_only_the_part_of_the_tuned_cost_it_is_told(small, tmp_path):
    out = tmp_path / "beta-only.json"
    res = kftune("tune", str(small), "-n", "3", "--weights", "beta=1,r=0,ay=0", "-o", str(out))
    assert res.returncode == 0, res.stderr

    def cost(*extra: str) -> float:
        ev = kftune(
            "evaluate", str(small), "--params", str(out), "--split", "train", "--json", *extra
        )
        assert ev.returncode == 0, ev.stderr
        return json.loads(ev.stdout)["cost"]

    carried = cost("--normalise", "dataset")  # the tuned file's weights stay
    assert carried == cost("--normalise", "dataset", "--weights", "beta=1,r=0,ay=0")
    assert carried != pytest.approx(cost("--normalise", "dataset", "--weights", "beta=5,r=1,ay=1"))
    assert carried != pytest.approx(cost())  # the file's own normalisation: Eq. 15


def test_normalise_is_refused_for_a_file_tuned_with_another_cost(small, tmp_path):
    out = tmp_path / "pem.json"
    assert kftune("tune", str(small), "-n", "3", "--cost", "pem", "-o", str(out)).returncode == 0
    res = kftune("evaluate", str(small), "--params", str(out), "--normalise", "dataset")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "--normalise: the pem cost (the cost the parameters were tuned with)" in res.stderr


def closing_hint(dataset: Path, out: Path) -> tuple[str, list[str]]:
    """Tune briefly on ``dataset`` into ``out``: tune's last line, and the command in it."""
    res = kftune("tune", str(dataset), "-n", "2", "-q", "-o", str(out))
    assert res.returncode == 0, res.stderr
    hint = res.stdout.strip().splitlines()[-1]
    return hint, shlex.split(hint.split(": ", 1)[1])


def test_tune_ends_with_a_command_that_runs(small, tmp_path):
    """The closing hint is a whole command (dataset, tuned file, split), and it works."""
    out = tmp_path / "a b.json"
    hint, argv = closing_hint(small, out)
    assert hint.startswith("KPIs per test manoeuvre: kftune evaluate ")
    assert argv[2] == str(small) and str(out) in argv
    ev = kftune(*argv[1:])
    assert ev.returncode == 0, ev.stderr
    assert "test split" in ev.stdout
    # every column with its unit, and what the yaw rate and ay are scored against
    assert "r vs meas °/s ay vs meas m/s²" in ev.stdout


def test_without_test_manoeuvres_tune_and_evaluate_use_the_training_ones(tmp_path):
    """tune's closing hint named --split test, which failed there; evaluate's default split
    (test) falls back to all manoeuvres with a warning; an explicit --split test says what
    to use instead."""
    only_train = tmp_path / "train-only"
    save_dataset(default_dataset().subset(SMALL_TRAIN), only_train)
    out = tmp_path / "t.json"
    hint, argv = closing_hint(only_train, out)
    assert hint.startswith("KPIs per training manoeuvre (the dataset has no test manoeuvres): ")
    assert argv[-2:] == ["--split", "train"]
    ev = kftune(*argv[1:])
    assert ev.returncode == 0, ev.stderr
    ev = kftune("evaluate", str(only_train), "--params", str(out), "--json")
    assert ev.returncode == 0, ev.stderr
    assert "kftune: warning: dataset" in ev.stderr and "no test manoeuvres" in ev.stderr
    doc = json.loads(ev.stdout)
    assert doc["split"] == "all" and set(doc["manoeuvres"]) == set(SMALL_TRAIN)
    ev = kftune("evaluate", str(only_train), "--params", str(out), "--split", "test")
    assert ev.returncode == 3 and "use --split all" in ev.stderr, ev.stderr
    assert "Traceback" not in ev.stderr


def test_a_finished_run_removes_the_partial_file_of_an_interrupted_one(small, tmp_path):
    out = tmp_path / "t.json"
    (tmp_path / "t.partial.json").write_text("{}")  # left by an earlier Ctrl-C
    (tmp_path / "other.partial.json").write_text("{}")
    res = kftune("tune", str(small), "-n", "2", "-q", "-o", str(out))
    assert res.returncode == 0, res.stderr
    assert out.is_file() and not (tmp_path / "t.partial.json").exists()
    assert (tmp_path / "other.partial.json").exists()


def test_resume_of_a_study_that_does_not_exist_is_refused(small, tmp_path):
    """A misspelt --storage with --resume would silently start afresh."""
    res = kftune("tune", str(small), "-n", "2", "--storage", str(tmp_path / "nos.db"), "--resume")
    assert res.returncode == 3 and "nos.db" in res.stderr and "does not exist" in res.stderr
    assert not (tmp_path / "nos.db").exists()
    res = kftune(
        "compare", str(small), "--methods", "manual", "--resume", "-o", str(tmp_path / "r")
    )
    assert res.returncode == 3 and "holds no study" in res.stderr
    assert not (tmp_path / "r" / "report.md").exists()


def test_ctrl_c_before_the_first_evaluation_says_so(small, tmp_path, monkeypatch):
    """Interrupted while loading: no count of zero evaluations (a resumed study holds more);
    the hint says whether there is a study to resume."""
    import kftune.data as data_module

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    db = tmp_path / "s.db"
    monkeypatch.setattr(data_module, "open_dataset", interrupted)
    res = kftune("tune", str(small), "-n", "2", "--storage", str(db))
    assert res.returncode == 130
    assert "kftune: interrupted" in res.stderr and "after 0" not in res.stderr
    assert "no study was started" in res.stderr and "--resume" not in res.stderr


def test_a_dataset_without_training_manoeuvres_says_so(tmp_path):
    from kftune.data import default_dataset, save_dataset

    save_dataset(default_dataset().subset(["test-05-j-turn"]), tmp_path / "only-test")
    res = kftune("tune", str(tmp_path / "only-test"), "-n", "2", "-q", "-o", str(tmp_path / "t"))
    assert res.returncode == 3, res.stderr
    assert "has no training manoeuvres" in res.stderr and "1 are all test" in res.stderr


def test_config_method_names_the_file_and_a_budget_for_no_method_is_refused(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text('method = "bogus"\n')
    res = kftune("tune", "--config", str(cfg), "-n", "2", "-q")
    assert res.returncode == 3 and str(cfg) in res.stderr and "'bogus'" in res.stderr
    cfg.write_text('methods = ["manual", "gaa"]\n')
    res = kftune("compare", "--config", str(cfg), "-q", "-o", str(tmp_path / "r"))
    assert res.returncode == 3 and str(cfg) in res.stderr and "gaa" in res.stderr
    res = kftune("compare", "--methods", "manual", "--budget", "ga=5", "-o", str(tmp_path / "r"))
    assert res.returncode == 2 and "--budget ga" in res.stderr and "not among" in res.stderr
    assert not (tmp_path / "r").exists()


def test_evaluate_runs_the_tuned_files_r_as_estimate_and_export_do(small, tmp_path):
    """R set by the configuration at tuning time (r0) is part of the tuned filter:
    evaluate --params, without that configuration, scores the same cost, and an R edited in
    the file (both copies) changes what it scores."""
    cfg = tmp_path / "r0.toml"
    cfg.write_text("r0 = { vx = 1.0 }\n")
    out = tmp_path / "t.json"
    res = kftune(
        "tune", str(small), "--config", str(cfg), "-n", "3", "-q", "-o", str(out),
        "--no-calibration",  # the cost of the filter as tuned
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert doc["r"][0] == 1.0 and doc["calibration"] is None
    ev = kftune("evaluate", str(small), "--params", str(out), "--split", "train", "--json")
    assert ev.returncode == 0, ev.stderr
    got = json.loads(ev.stdout)
    assert got["r"] == pytest.approx(doc["r"], rel=1e-12)
    assert got["cost"] == pytest.approx(doc["cost"], rel=1e-9)
    doc["r"] = [v * 100 for v in doc["r"]]
    for e in doc["deployment"]["R"]:
        e["variance"] *= 100
    out.write_text(json.dumps(doc))
    ev = kftune("evaluate", str(small), "--params", str(out), "--split", "train", "--json")
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["r"] == pytest.approx(doc["r"], rel=1e-12)
    assert json.loads(ev.stdout)["cost"] != pytest.approx(got["cost"], rel=1e-3)


def test_evaluate_refuses_a_damaged_r_in_the_tuned_file(small, tmp_path):
    """A tuned file's R that is no positive variance per measurement is named, not replaced
    by the data's R."""
    out = tmp_path / "t.json"
    assert kftune("tune", str(small), "-m", "manual", "-q", "-o", str(out)).returncode == 0
    doc = json.loads(out.read_text())
    doc["r"][1] = -1.0
    out.write_text(json.dumps(doc))
    res = kftune("evaluate", str(small), "--params", str(out))  # disagrees with the record
    assert res.returncode == 3 and str(out) in res.stderr and "'r'" in res.stderr, res.stderr
    doc.pop("deployment")  # an older file: no record to disagree with
    out.write_text(json.dumps(doc))
    res = kftune("evaluate", str(small), "--params", str(out))
    assert res.returncode == 3 and str(out) in res.stderr, res.stderr
    assert "'r' must be one positive variance per measurement" in res.stderr
