"""A user's own model, written in a Python file, tuned and evaluated end to end through the
command line (the README's worked example, copied to a temporary file)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from conftest import run_cli as kftune

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "linear_bicycle.py"


def test_a_model_file_is_tuned_and_evaluated_through_the_cli(small, tmp_path):
    model = tmp_path / "my_model.py"
    shutil.copyfile(EXAMPLE, model)
    out = tmp_path / "tuned.json"
    res = kftune("tune", str(small), "--model", str(model), "-n", "6", "--json", "-o", str(out))
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["model"] == str(model) and doc["filter"] == "ukf"
    assert doc["states"] == ["vx", "vy", "r"] and set(doc["params"]) == {"q_vx", "q_vy", "q_r"}
    assert doc["n_evals"] == 6 and doc["cost"] > 0
    # evaluate takes the model from the tuned file and scores the same cost
    ev = kftune("evaluate", str(small), "--params", str(out), "--split", "train", "--json")
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["cost"] == pytest.approx(doc["cost"], rel=1e-12)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("import numpy as np\nx = (\n", "failed to run (line 2): SyntaxError"),
        ("raise RuntimeError('no licence')\n", "failed to run (line 1): RuntimeError: no licence"),
        ("X = 1\n", "defines 0 StateSpaceModel objects"),
    ],
)
def test_a_broken_model_file_is_a_clear_error(tmp_path, text, expected):
    model = tmp_path / "broken.py"
    model.write_text(text)
    res = kftune("tune", "--model", str(model), "-n", "2")
    assert res.returncode == 3, res.stderr
    assert expected in res.stderr and str(model) in res.stderr
    assert "Traceback" not in res.stderr


def test_unknown_model_and_filter_are_refused(tmp_path):
    res = kftune("tune", "--model", "unicycle", "-n", "2")
    assert res.returncode == 3 and "unknown model 'unicycle'" in res.stderr
    assert "single-track" in res.stderr  # the built-in models are listed
    res = kftune("tune", "--model", str(tmp_path / "missing.py"), "-n", "2")
    assert res.returncode == 3 and "does not exist" in res.stderr
    res = kftune("tune", "--filter", "pf", "-n", "2")
    assert res.returncode == 2 and "--filter" in res.stderr
