"""Runaway estimates are divergence: a sideslip or speed estimate that no car can have stops
the run with a step and a cause, in the kernel and the numpy reference alike; the tuning
problem counts it as a failed evaluation; ``kftune evaluate`` exits 1 and names the
manoeuvres; no manual or tuned filter of the bundled set or revs-250lm is flagged."""

from __future__ import annotations

import math
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.data import default_dataset, load_revs
from kftune.errors import FilterDivergedError
from kftune.filters import UKFSettings
from kftune.models import sideslip
from kftune.report import ExperimentResults, MethodRun
from kftune.report.tables import kpi_table, per_manoeuvre_table
from kftune.tuning.kpi import average_kpis
from kftune.tuning.problem import TuningProblem, assess
from kftune.vehicle import preset
from kftune.vehicle.single_track import MAX_SIDESLIP
from reference_ukf import run_ukf_reference
from single_track import beta, run_ukf, run_ukf_batch
from test_ukf import filterpy_run

BMW = preset("bmw-320i")
DT = 0.01
N = 200
#: Measurements the filter is told to ignore (R huge): it then simulates its own model.
R_IGNORE = np.full(3, 1e8)

# the filters of the README runs (seed 0): manual and the best point of each method
TUNED = {
    "default": [
        [1e-06, 1e-04, 1e-06],
        [1.3389e-08, 5.2202e-09, 0.18727],
        [8.6238e-09, 7.0762e-09, 0.20157],
        [8.7905e-06, 5.8833e-09, 0.20157],
    ],
    "revs": [
        [1e-06, 1e-04, 1e-06],
        [6.4366e-07, 4.4181e-04, 0.25146],
        [1.7783e-09, 1.7783e-04, 0.056234],
        [4.2169e-10, 9.9999e-06, 0.23714],
    ],
}


def both(u, z, q, r, **kw):
    """The compiled kernel and the numpy reference on the same input."""
    return [f(u, z, DT, BMW, q, r, **kw) for f in (run_ukf, run_ukf_reference)]


def coasting(vx: float, n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """No steering, no acceleration; measurements Vx = vx, ay = r = 0."""
    return np.zeros((n, 2)), np.column_stack([np.full(n, vx), np.zeros(n), np.zeros(n)])


def assert_stopped(res, step: int, cause: int) -> None:
    assert (res.diverged, res.diverged_step, res.diverged_cause) == (True, step, cause)
    assert np.isfinite(res.x[:step]).all() and np.isnan(res.x[step:]).all()
    assert np.isnan(res.nis[step:]).all()
    assert "runaway" in res.diverged_reason


def test_huge_process_noise_runs_away_beyond_60_degrees():
    """Q = 1e9 lets Vy jump anywhere: |β| passes 60° almost at once."""
    man = demo_manoeuvre(seed=3)
    q = [1e9, 1e9, 1e9]
    runs = both(man.u[:N], man.z[:N], q, man.r_var)
    for res in runs:
        assert res.diverged and res.diverged_cause == sideslip.STOP_SIDESLIP
        k = res.diverged_step
        assert k < 20
        assert np.all(np.abs(beta(res)[:k]) <= math.radians(60.0))
    assert runs[0].diverged_step == runs[1].diverged_step
    # FilterPy on the same model, which has no such check, crosses 60° at that very step
    k = runs[0].diverged_step
    x = filterpy_run(man, q, UKFSettings(), n=k + 1)
    beta_deg = np.degrees(np.abs(np.arctan2(x[:, 1], x[:, 0])))
    assert beta_deg[k] > 60.0 and np.all(beta_deg[:k] <= 60.0)
    np.testing.assert_allclose(runs[0].x[:k], x[:k], rtol=1e-6, atol=1e-6)


def test_sideslip_held_beyond_46_degrees_for_half_a_second_is_a_runaway_from_its_start():
    """A filter that ignores its measurements simulates its model: started at β = 55° and
    50 m/s the car slides, |β| falling through 46° after ≈ 1.5 s (checked by simulation)."""
    u, z = coasting(50.0)
    x0 = [50.0, 50.0 * math.tan(math.radians(55.0)), 0.0]
    for res in both(u, z, [0.0] * 3, R_IGNORE, x0=x0, P0=[1e-6] * 3):
        assert_stopped(res, 0, sideslip.STOP_SIDESLIP_HELD)


def test_sideslip_beyond_46_degrees_for_less_than_half_a_second_is_not_flagged():
    """Started at 52° and 30 m/s with a yaw rate of 0.5 rad/s the car straightens out:
    |β| is below 46° after ≈ 0.2 s (simulation), and the run completes."""
    u, z = coasting(30.0)
    x0 = [30.0, 30.0 * math.tan(math.radians(52.0)), 0.5]
    for res in both(u, z, [0.0] * 3, R_IGNORE, x0=x0, P0=[1e-6] * 3):
        assert not res.diverged and res.diverged_cause == 0 and res.diverged_reason == ""
        beyond = np.abs(beta(res)) > MAX_SIDESLIP
        assert 5 < beyond.sum() < round(sideslip.RUNAWAY_HOLD / DT)  # 50 steps


def test_estimated_speed_off_the_measurement_for_half_a_second_is_a_runaway():
    """A filter that trusts its Vx model (q_Vx = 0, r_Vx huge) and is started at twice the
    measured speed keeps it: flagged from step 0 once it has lasted 0.5 s."""
    u, z = coasting(20.0)
    kw = {"x0": [40.0, 0.0, 0.0], "P0": [1e-6, 1e-2, 1e-6]}
    for res in both(u, z, [0.0, 1e-4, 1e-6], [1e8, 0.01, 1e-5], **kw):
        assert_stopped(res, 0, sideslip.STOP_SPEED)


@pytest.mark.parametrize(("glitch", "flagged"), [(45, False), (55, True)])
def test_a_speed_glitch_counts_only_when_it_lasts_half_a_second(glitch, flagged):
    """The Vx sensor reads 40 % of the speed for ``glitch`` samples; a filter that trusts
    its model does not follow, so it is > 50 % off the measurement all that time."""
    u, z = coasting(20.0)
    z[100 : 100 + glitch, 0] = 8.0
    for res in both(u, z, [0.0, 1e-4, 1e-6], [1e4, 0.01, 1e-5]):
        if flagged:
            assert_stopped(res, 100, sideslip.STOP_SPEED)
        else:
            assert not res.diverged


def test_batch_reports_the_cause_per_set():
    man = demo_manoeuvre(seed=3)
    res = run_ukf_batch(man.u[:N], man.z[:N], man.dt, BMW, [DEFAULT_Q, [1e9] * 3], man.r_var)
    assert res.diverged.tolist() == [False, True]
    assert res.diverged_cause.tolist() == [0, sideslip.STOP_SIDESLIP]
    assert "60°" in res[1].diverged_reason


def test_a_runaway_is_a_failed_evaluation_naming_manoeuvre_step_and_cause():
    ds = default_dataset()
    problem = TuningProblem(ds.train[:1], ds.vehicle, ds.r_default)
    with pytest.raises(FilterDivergedError) as info:
        problem([1e9, 1e9, 1e9])
    msg = str(info.value)
    assert "diverged on manoeuvre 'train-01-braking-in-turn' at step" in msg
    assert "runaway: the estimated sideslip went beyond ±60°" in msg


def _max_abs_beta_deg(manoeuvres, vehicle, r, q) -> float:
    worst = 0.0
    for m in manoeuvres:
        res = run_ukf(m.u, m.z, m.dt, vehicle, q, r)
        assert not res.diverged, (m.name, q, res.diverged_reason)
        worst = max(worst, float(np.degrees(np.abs(beta(res)).max())))
    return worst


@pytest.mark.parametrize("q", TUNED["default"])
def test_no_manual_or_tuned_filter_of_the_bundled_set_is_flagged(q):
    ds = default_dataset()
    assert _max_abs_beta_deg(ds.manoeuvres, ds.vehicle, ds.r_default, q) < 20.0


def test_no_manual_or_tuned_filter_of_revs_is_flagged(revs_dir):
    ds = load_revs(revs_dir)
    for q in TUNED["revs"]:
        assert _max_abs_beta_deg(ds.manoeuvres, ds.vehicle, ds.r_default, q) < 20.0


@pytest.mark.slow
def test_evaluate_exits_1_naming_the_runaway_manoeuvres_and_still_prints_kpis():
    res = subprocess.run(
        [sys.executable, "-m", "kftune", "evaluate", "--q", "1e9", "1e9", "1e9"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr + res.stdout
    assert "the filter diverged on 23 of 23 manoeuvres" in res.stderr
    assert "first: manoeuvre 'test-01-braking-in-turn' at step" in res.stderr
    assert "runaway: the estimated sideslip went beyond ±60°" in res.stderr
    assert res.stdout.startswith("manoeuvre") and "average" in res.stdout
    assert res.stdout.count("runaway:") == 23


def test_a_tuning_run_whose_every_evaluation_runs_away_keeps_them_all(tmp_path, capsys):
    """Every evaluation fails (Q pinned near 1e8): ``tune`` exits 1 naming the cause, and
    the study holds each failed evaluation with its reason — nothing finished is lost."""
    from kftune.cli import main

    cfg = tmp_path / "c.toml"
    cfg.write_text("[parameters]\nq_bounds = [1e8, 1.1e8]\n")
    db = tmp_path / "s.db"
    args = ["tune", "-m", "random", "-n", "3", "--storage", str(db), "--config", str(cfg)]
    assert main([*args, "--quiet", "-o", str(tmp_path / "t.json")]) == 1
    err = capsys.readouterr().err
    assert "every evaluation of 'random' failed (3 of 3)" in err and "runaway" in err
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT state, reason FROM trials ORDER BY number").fetchall()
    assert len(rows) == 3
    assert all(
        state == "failed" and "runaway: the estimated sideslip" in why for state, why in rows
    )


def test_a_runaway_shows_in_the_kpis_and_the_tables():
    """assess flags each runaway manoeuvre; the averages refuse to average over survivors;
    the KPI table counts the diverged manoeuvres and the per-manoeuvre table marks them."""
    ds = default_dataset()
    problem = TuningProblem(ds.train[:1], ds.vehicle, ds.r_default)
    tested = (*ds.test[:2], ds.train[0])
    per, _ = assess(problem, [1e9, 1e9, 1e9], tested[:2])
    good, _ = assess(problem, TUNED["default"][1], tested[2:])
    per.update(good)
    avg = average_kpis(per.values())
    assert avg["n_diverged"] == 2 and math.isnan(avg["rmse"])
    run = MethodRun(
        key="ga", label="GA", params={}, best_cost=1.0, n_evals=1, wall_time_s=0.1,
        history_cost=[1.0], history_time_s=[0.1], metrics={"test": per},
        averages={"test": avg}, extra={},
    )  # fmt: skip
    results = ExperimentResults(meta={}, methods=[run])
    assert kpi_table(results, "test").rows[-1] == ("Diverged manoeuvres", 2)
    table = per_manoeuvre_table(results)
    column = table.header.index("diverged")
    assert [row[column] for row in table.rows] == [1.0, 1.0, 0.0]
