"""``kftune demo``: the UKF on a built-in simulated manoeuvre — its KPIs against the filter
run here, its seed, its text output and a bad option."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from kftune.cli import main
from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from single_track import run_ukf


def test_demo_json_reports_the_kpis_of_the_filter_run(capsys):
    assert main(["demo", "--json", "--seed", "4"]) == 0
    out = json.loads(capsys.readouterr().out)
    man = demo_manoeuvre(4)
    res = run_ukf(man.u, man.z, man.dt, man.params, DEFAULT_Q, man.r_var)
    err = np.degrees(res.output("beta") - man.beta_true)
    non = np.abs(man.z[:, 1]) >= 4.0
    assert out["kpis_deg"]["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
    assert out["kpis_deg"]["mae"] == pytest.approx(np.max(np.abs(err)), rel=1e-12)
    assert out["kpis_deg"]["rmse_non"] == pytest.approx(np.sqrt(np.mean(err[non] ** 2)), rel=1e-12)
    assert out["kpis_deg"]["mae_non"] == pytest.approx(np.max(np.abs(err[non])), rel=1e-12)
    assert out["n_non"] == int(non.sum()) > 100
    # the estimate is useful: well below the sideslip it estimates
    assert out["kpis_deg"]["rmse"] < 0.2 * out["max_abs_beta_deg"]


def test_demo_is_seeded_and_noise_matters():
    a, b, c = demo_manoeuvre(1), demo_manoeuvre(1), demo_manoeuvre(2)
    np.testing.assert_array_equal(a.z, b.z)
    assert not np.array_equal(a.z, c.z)
    np.testing.assert_array_equal(a.x_true, c.x_true)


CLI = "import sys; from kftune.cli import main; sys.exit(main(sys.argv[1:]))"


@pytest.mark.slow
def test_demo_command_line_text_and_bad_option():
    run = subprocess.run(
        [sys.executable, "-c", CLI, "demo"], capture_output=True, text=True, check=False
    )
    assert run.returncode == 0, run.stderr
    assert "RMSE_NON" in run.stdout and "MAE" in run.stdout
    bad = subprocess.run(
        [sys.executable, "-c", CLI, "demo", "--q", "1", "1", "-1"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 2
    assert "q[2]" in bad.stderr
