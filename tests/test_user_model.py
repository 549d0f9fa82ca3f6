"""A user's own model, written in a Python file, tuned and evaluated end to end through the
command line (the README's worked example, copied to a temporary file)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli as kftune

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "linear_bicycle.py"


@pytest.mark.slow
def test_a_model_file_is_tuned_and_evaluated_through_the_cli(small, tmp_path):
    model = tmp_path / "my_model.py"
    shutil.copyfile(EXAMPLE, model)
    out = tmp_path / "tuned.json"
    # the paper's cost, Q alone: the test is about the model file
    args = ("--model", str(model), "--cost", "nrmse", "-n", "6", "--json")
    res = kftune("tune", str(small), *args, "-o", str(out))
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    # recorded relative to the tuned file's folder, where it lies
    assert doc["model"] == doc["deployment"]["model"] == "my_model.py"
    assert doc["filter"] == "ukf"
    assert doc["states"] == ["vx", "vy", "r"] and set(doc["params"]) == {"q_vx", "q_vy", "q_r"}
    assert doc["n_evals"] == 6 and doc["cost"] > 0
    # evaluate runs the model file the user names (checked against the tuned file's record)
    # and scores the same cost
    ev = kftune("evaluate", str(small), "--params", str(out), "--model", str(model), "--split",
                "train", "--json")  # fmt: skip
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["cost"] == pytest.approx(doc["cost"], rel=1e-12)


@pytest.mark.slow
def test_an_edited_model_file_is_not_taken_for_the_tuned_one(small, tmp_path):
    """The tuned file and the study record the model file's SHA-256: after an edit,
    evaluate refuses (--force runs it with a warning), export warns, and a study does not
    resume on it (it silently scored another model, and resumed an old cost)."""
    model = tmp_path / "m.py"
    shutil.copyfile(EXAMPLE, model)
    out, study = tmp_path / "t.json", tmp_path / "s.db"
    res = kftune("tune", str(small), "--model", str(model), "-n", "3", "-q", "-o", str(out),
                 "--storage", str(study))  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert len(doc["deployment"]["model_sha256"]) == 64
    named = ("--model", str(model))
    ev = kftune("evaluate", str(small), "--params", str(out), *named, "--split", "train")
    assert ev.returncode == 0 and "model file" not in ev.stderr, ev.stderr
    model.write_text(model.read_text() + "\n# an edit\n")
    ev = kftune("evaluate", str(small), "--params", str(out), *named, "--split", "train")
    assert ev.returncode == 3, ev.stderr
    assert "has changed since the filter was tuned" in ev.stderr and "--force" in ev.stderr
    ev = kftune("evaluate", str(small), "--params", str(out), *named, "--split", "train",
                "--force")  # fmt: skip
    assert ev.returncode == 0 and "has changed since the filter was tuned" in ev.stderr
    ex = kftune("export", str(out), "-o", "-")
    assert ex.returncode == 0 and "has changed since the filter was tuned" in ex.stderr
    res = kftune("tune", str(small), "--model", str(model), "-n", "3", "-q", "-o", str(out),
                 "--storage", str(study), "--resume")  # fmt: skip
    assert res.returncode == 3 and "model file sha256" in res.stderr, res.stderr


@pytest.mark.slow
def test_the_tuned_file_says_where_its_model_file_lies_from_any_working_directory(small, tmp_path):
    """A tuned file records its model file relative to itself when it lies beside it (the
    folder can move), otherwise absolute; run elsewhere, ``evaluate`` and ``estimate``
    refuse to run it unnamed and tell where it lies, and run it once named."""
    (tmp_path / "models").mkdir()
    (tmp_path / "out").mkdir()
    shutil.copyfile(EXAMPLE, tmp_path / "models" / "m.py")
    res = kftune(
        "tune", str(small), "--model", "models/m.py", "-n", "4", "-q", "-o", "out/t.json",
        cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "--model models/m.py" in res.stdout  # the closing hint names it
    doc = json.loads((tmp_path / "out" / "t.json").read_text())
    assert Path(doc["model"]) == (tmp_path / "models" / "m.py").resolve()
    ev = kftune("evaluate", str(small), "--params", "t.json", "--json", cwd=tmp_path / "out")
    assert ev.returncode == 3 and f"--model {doc['model']}" in ev.stderr, ev.stderr
    ev = kftune("evaluate", str(small), "--params", "t.json", "--model", "../models/m.py",
                "--json", cwd=tmp_path / "out")  # fmt: skip
    assert ev.returncode == 0, ev.stderr
    # beside the tuned file: relative, and the pair moves together
    shutil.copyfile(EXAMPLE, tmp_path / "out" / "m2.py")
    res = kftune(
        "tune", str(small), "--model", "m2.py", "-n", "4", "-q", "-o", "t2.json",
        cwd=tmp_path / "out",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert json.loads((tmp_path / "out" / "t2.json").read_text())["model"] == "m2.py"
    moved = shutil.copytree(tmp_path / "out", tmp_path / "moved")
    est = kftune("estimate", str(small), "--params", str(moved / "t2.json"), "-o",
                 str(tmp_path / "est"), "-m", "test-05-j-turn")  # fmt: skip
    assert est.returncode == 3 and f"--model {moved / 'm2.py'}" in est.stderr, est.stderr
    est = kftune("estimate", str(small), "--params", str(moved / "t2.json"), "-o",
                 str(tmp_path / "est"), "-m", "test-05-j-turn", "--model",
                 str(moved / "m2.py"))  # fmt: skip
    assert est.returncode == 0, est.stderr
    lost = shutil.copytree(tmp_path / "out", tmp_path / "lost")  # (loaded models are cached)
    (lost / "m2.py").unlink()
    for extra in ([], ["estimate", "-o", str(tmp_path / "e")]):
        cmd, *out = extra or ["evaluate"]
        res = kftune(cmd, str(small), "--params", str(lost / "t2.json"), *out, "--model",
                     str(lost / "m2.py"))  # fmt: skip
        assert res.returncode == 3, res.stderr
        assert "--model" in res.stderr and "does not exist" in res.stderr


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("import numpy as np\nx = (\n", "failed to run (line 2): SyntaxError"),
        ("raise RuntimeError('no licence')\n", "failed to run (line 1): RuntimeError: no licence"),
        ("X = 1\n", "defines 0 StateSpaceModel objects"),
        # the module's own exit or interrupt is its failure, not a finished run (exit 0)
        # or the user's Ctrl-C (130)
        ("import sys\nsys.exit(0)\n", "raised SystemExit while loading (line 2)"),
        ("raise KeyboardInterrupt\n", "raised KeyboardInterrupt while loading (line 1)"),
        ("def g():\n    yield\nraise GeneratorExit\n", "raised GeneratorExit while loading"),
    ],
)
def test_a_broken_model_file_is_a_clear_error(tmp_path, text, expected):
    model = tmp_path / "broken.py"
    model.write_text(text)
    res = kftune("tune", "--model", str(model), "-n", "2")
    assert res.returncode == 3, res.stderr
    assert expected in res.stderr and str(model) in res.stderr
    assert "Traceback" not in res.stderr


def test_a_model_file_with_more_states_than_kftune_takes_is_refused_before_compiling(tmp_path):
    model = tmp_path / "huge.py"
    model.write_text(
        "import numpy as np\nfrom numba import njit\nfrom kftune.models import StateSpaceModel\n"
        "N = 1000\n"
        "@njit\ndef f(x, u, p, dt, out):\n    out[:] = x\n"
        "@njit\ndef h(x, u, p, out):\n    out[0] = x[0]\n"
        "MODEL = StateSpaceModel(name='huge', state_names=tuple(f's{i}' for i in range(N)),\n"
        "    state_units=('m',) * N, input_names=(), input_units=(),\n"
        "    measurement_names=('z',), measurement_units=('m',), f=f, h=h)\n"
    )
    res = kftune("tune", "--model", str(model), "-n", "2")
    assert res.returncode == 3, res.stderr
    assert "has 1000 states; kftune takes at most 100" in res.stderr and str(model) in res.stderr
    assert "Traceback" not in res.stderr


def test_unknown_model_and_filter_are_refused(tmp_path):
    res = kftune("tune", "--model", "unicycle", "-n", "2")  # a name: the command line is wrong
    assert res.returncode == 2 and "--model: unknown model 'unicycle'" in res.stderr
    assert "single-track" in res.stderr  # the built-in models are listed
    res = kftune("tune", "--model", str(tmp_path / "missing.py"), "-n", "2")
    assert res.returncode == 3 and "does not exist" in res.stderr
    res = kftune("tune", "--filter", "pf", "-n", "2")
    assert res.returncode == 2 and "--filter" in res.stderr


@pytest.mark.slow
def test_a_model_files_parameters_are_tuned_and_evaluated(small, tmp_path):
    """A model of one's own (no vehicle, no declared ranges): its parameter joins the
    search from its default, the tuned file records it, and evaluate runs it (the training
    cost again, which the model's default would not give)."""
    model = tmp_path / "my_model.py"
    shutil.copyfile(EXAMPLE, model)
    out = tmp_path / "tuned.json"
    res = kftune("tune", str(small), "--model", str(model), "--tune-model", "C_f=2e4:4e5",
                  "-n", "10", "-q", "--no-calibration", "-o", str(out))  # fmt: skip
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    from kftune.models.user import load_model

    defaults = dict(zip(load_model(str(model)).param_names, load_model(str(model)).param_defaults))
    assert doc["model_params"]["C_f"]["start"] == defaults["C_f"]
    tuned = doc["model_params"]["C_f"]["value"]
    assert {e["name"]: e["value"] for e in doc["deployment"]["model_params"]}["C_f"] == tuned
    ev = kftune("evaluate", str(small), "--params", str(out), "--model", str(model),
                 "--split", "train", "--json")  # fmt: skip
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["cost"] == pytest.approx(doc["cost"], rel=1e-12)
    # estimate runs the tuned C_f too: its states are the filter's at the tuned point
    from kftune.data import open_dataset
    from kftune.tuning.parameterization import NoiseParameterization
    from kftune.tuning.problem import TuningProblem

    est = kftune("estimate", str(small), "--params", str(out), "--model", str(model),
                 "--no-plot", "-o", str(tmp_path / "est"), "--json")  # fmt: skip
    assert est.returncode == 0, est.stderr
    ds = open_dataset(str(small))
    m = ds.train[0]
    table = json.loads(est.stdout)["manoeuvres"][m.name]["file"]
    vy = np.genfromtxt(table, delimiter=",", names=True)["vy"]
    par = NoiseParameterization(model_bounds={"C_f": (2e4, 4e5)})
    problem = TuningProblem(ds.train, ds.vehicle, doc["r"], parameterization=par, model=str(model))
    run = problem.run([*doc["q"], tuned], m)
    np.testing.assert_allclose(vy, run.x[:, 1], rtol=1e-12, atol=1e-15)
