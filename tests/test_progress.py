"""What a run says while it runs and when it ends: plain progress lines where stderr is not
a terminal (a log file, nohup, CI), the note that the first evaluation compiles the filter,
the failed evaluations' reasons grouped by kind, and what ``kftune --help`` says kftune is."""

from __future__ import annotations

import contextlib
import io
import json

from conftest import run_cli
from kftune.data import default_dataset, save_dataset
from kftune.optim.result import EvalRecord
from kftune.progress import ProgressBar
from kftune.tuning.runs import failure_kinds

DIVERGED = (
    "FilterDivergedError: filter diverged on manoeuvre {name!r} at step {k} (t = {t:.2f} s): "
    "runaway: the estimated sideslip went beyond ±60°"
)


def record(number: int, value: float | None, reason: str | None = None) -> EvalRecord:
    return EvalRecord(
        number=number,
        x=(0.0,),
        u=(0.0,),
        params={"q": 0.0},
        value=value,
        state="complete" if reason is None else "failed",
        reason=reason,
    )


def test_plain_lines_off_a_terminal_every_tenth_of_the_budget():
    """Off a terminal: a line after the first evaluation, then every 10 % of the budget
    (the time gate set to 0 here), and the last; no carriage return; the note first."""
    err = io.StringIO()
    note = "compiling the filter"
    with contextlib.redirect_stderr(err), ProgressBar(20, "trbo", note=note, interval=0) as bar:
        for i in range(20):
            bar(record(i, 1.0 / (i + 1)) if i % 5 else record(i, None, "timeout after 5 s"))
    lines = err.getvalue().splitlines()
    assert "\r" not in err.getvalue()
    assert lines[0] == "compiling the filter"
    done = [int(line.split(": ")[1].split("/")[0]) for line in lines[1:]]
    assert done == [1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 20]
    assert all(line.startswith("trbo: ") and "/20 evaluations" in line for line in lines[1:])
    assert "best cost 0.05, 4 failed, elapsed " in lines[-1]
    assert "ETA" in lines[2] and "ETA" not in lines[-1]  # nothing left at the end


def test_plain_lines_wait_for_the_interval_as_well():
    """The time gate: with an interval no run reaches, only the first and the last line."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), ProgressBar(50, "ga", interval=1e9) as bar:
        for i in range(50):
            bar(record(i, 2.0))
    lines = err.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "ga: 1/50 evaluations",
        "ga: 50/50 evaluations",
    ]


def test_quiet_prints_nothing_not_even_the_note():
    err = io.StringIO()
    with contextlib.redirect_stderr(err), ProgressBar(3, "x", enabled=False, note="n") as bar:
        for i in range(3):
            bar(record(i, 1.0))
    assert err.getvalue() == ""


def test_failure_kinds_leave_out_where_and_the_exception_name():
    reasons = [
        DIVERGED.format(name="a", k=12, t=0.12),
        "non-finite value nan",
        DIVERGED.format(name="b'c", k=3, t=0.03),  # repr with double quotes
        DIVERGED.format(name="a", k=400, t=4.0),
        None,
    ]
    assert failure_kinds(reasons) == [
        ("filter diverged: runaway: the estimated sideslip went beyond ±60°", 3),
        ("non-finite value nan", 1),
        ("no reason recorded", 1),
    ]


def test_tune_off_a_terminal_shows_progress_compile_note_and_why_evaluations_failed(tmp_path):
    """``tune`` with stderr captured (not a terminal): plain progress lines without a
    carriage return, the compile note before them, and at the end the failed evaluations'
    reasons grouped by kind with counts (two manual points run away, one does not)."""
    ds = default_dataset().subset(("train-01-braking-in-turn", "test-05-j-turn"))
    save_dataset(ds, tmp_path / "d")
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[parameters]\nq_bounds = [1e-10, 1.1e8]\n"
        "[options.manual]\npoints = [[1e8, 1e8, 1e8], [1e-6, 1e-5, 1e-3], [1e8, 1e8, 1e8]]\n"
    )
    out = tmp_path / "t.json"
    # the paper's cost and Q alone: the points are Q's
    res = run_cli(
        "tune",
        str(tmp_path / "d"),
        "-m",
        "manual",
        "--cost",
        "nrmse",
        "--config",
        str(cfg),
        "-o",
        str(out),
    )
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "\r" not in res.stderr
    err = res.stderr.splitlines()
    note = next(i for i, line in enumerate(err) if line.startswith("compiling the filter"))
    assert "model 'single-track' (ukf)" in err[note]
    progress = [line for line in err if line.startswith("Manual: ")]
    assert progress[0].startswith("Manual: 1/3 evaluations")
    assert progress[-1].startswith("Manual: 3/3 evaluations, best cost ")
    assert err.index(progress[0]) > note
    said = res.stdout.splitlines()
    at = said.index("2 of 3 evaluations failed:")
    assert said[at + 1] == "  filter diverged: runaway: the estimated sideslip went beyond ±60° (2)"
    assert json.loads(out.read_text())["n_failed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml", "d", "t.json"]


def test_top_level_help_says_what_kftune_is_today():
    text = " ".join(run_cli("--help").stdout.split())
    assert "tunes Kalman filters" in text and "UKF or EKF" in text
    assert "The default tuner is TR-BO" in text
    assert "Student-t process (TSBO) is one method among" in text
    assert "kftune compare reproduces the paper" in text


def test_compare_says_once_that_it_compiles_and_shows_each_methods_progress(tmp_path):
    """``compare`` compiles the filter in an untimed evaluation before its methods: the note
    comes once, before them; each method then has its plain progress lines."""
    ds = default_dataset().subset(("train-01-braking-in-turn", "test-05-j-turn"))
    save_dataset(ds, tmp_path / "d")
    res = run_cli("compare", str(tmp_path / "d"), "--methods", "manual", "random",
                  "--budget", "random=2", "--out", str(tmp_path / "r"))  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "\r" not in res.stderr
    err = res.stderr.splitlines()
    notes = [i for i, line in enumerate(err) if line.startswith("compiling the filter")]
    assert len(notes) == 1
    manual = [i for i, line in enumerate(err) if line.startswith("Manual: 1/1 evaluations")]
    random = [i for i, line in enumerate(err) if line.startswith("Random: 2/2 evaluations")]
    assert notes[0] < manual[0] < random[0]


def test_the_time_left_leaves_out_the_first_evaluation(monkeypatch):
    """The first evaluation compiles the filter (100 s on a clock set by the test), the
    others take 1 s each: the time left is 1 s per evaluation left, not 100 s."""
    clock = iter([0.0, *(100.0 + k for k in range(10))])
    monkeypatch.setattr("kftune.progress.time.monotonic", lambda: next(clock))
    err = io.StringIO()
    with contextlib.redirect_stderr(err), ProgressBar(10, "x", interval=0) as bar:
        for i in range(10):
            bar(record(i, 1.0))
    lines = err.getvalue().splitlines()
    assert (
        lines[0] == "x: 1/10 evaluations, best cost 1, elapsed 01:40, ETA after the next evaluation"
    )
    assert lines[1] == "x: 2/10 evaluations, best cost 1, elapsed 01:41, ETA 00:08"
