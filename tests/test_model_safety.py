"""A model file is Python code that runs with the user's rights: kftune runs one only when
the user names it (``--model``, or a configuration passed on the command line), never
because a tuned file or a dataset mapping names it — a tuned file is what users send each
other. The model files here write a marker when imported, so a test sees whether they ran."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from conftest import run_cli as kftune
from kftune.cli import EXIT_BAD_INPUT, EXIT_OK

#: A "model" that records being imported (and then defines no model).
MARKING = "from pathlib import Path\nPath(__file__).with_name('MARKER').write_text('ran')\n"


@pytest.fixture(scope="module")
def tuned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tuned-parameters file of the built-in model (the manual rule of thumb)."""
    path = tmp_path_factory.mktemp("tuned") / "tuned.json"
    assert kftune("tune", "-m", "manual", "-o", str(path), "-q").returncode == 0
    return path


def naming(tuned: Path, folder: Path, spec: str, sha256: str | None = None) -> Path:
    """A copy of ``tuned`` in ``folder`` that says it was tuned with the model ``spec``
    (and records ``sha256`` for it)."""
    doc = json.loads(tuned.read_text())
    doc["model"] = doc["deployment"]["model"] = spec
    if sha256 is not None:
        doc["deployment"]["model_sha256"] = sha256
    out = folder / "tuned.json"
    out.write_text(json.dumps(doc))
    return out


@pytest.mark.parametrize("where", ["beside", "parent", "absolute", "with a name"])
def test_a_tuned_file_never_runs_the_model_file_it_names(tuned, tmp_path, where):
    (tmp_path / "sent").mkdir()
    model = (tmp_path if where in ("parent", "absolute") else tmp_path / "sent") / "evil.py"
    model.write_text(MARKING)
    spec = {"beside": "evil.py", "parent": "../evil.py", "absolute": str(model)}.get(
        where, "evil.py:MODEL"
    )
    params = naming(tuned, tmp_path / "sent", spec)
    out = tmp_path / "estimates"
    for cmd in (["evaluate", "--params", params], ["estimate", "--params", params, "-o", out]):
        res = kftune(*cmd)
        assert res.returncode == EXIT_BAD_INPUT, res.stderr
        assert str(params) in res.stderr and "--model" in res.stderr, res.stderr
        assert "Python code" in res.stderr and "Traceback" not in res.stderr
        assert not (model.parent / "MARKER").exists(), f"{cmd[0]} ran {spec}"
        assert not out.exists()
    # export deploys the tuned values: it never runs the model either
    res = kftune("export", str(params), "-o", str(tmp_path / "kf.h"), "-f", "c")
    assert res.returncode == EXIT_OK, res.stderr
    assert not (model.parent / "MARKER").exists()


def test_a_model_file_the_user_names_runs(tuned, tmp_path):
    model = tmp_path / "mine.py"
    model.write_text(MARKING)
    params = naming(tuned, tmp_path, "mine.py")
    for cmd in (["evaluate"], ["estimate", "-o", tmp_path / "est"]):
        res = kftune(*cmd, "--params", params, "--model", model)
        assert "defines 0 StateSpaceModel objects" in res.stderr, res.stderr  # it ran
        assert res.returncode == EXIT_BAD_INPUT and (tmp_path / "MARKER").read_text() == "ran"
        (tmp_path / "MARKER").unlink()
    config = tmp_path / "run.toml"  # a configuration the user passes names it too
    config.write_text('model = "mine.py"\n')
    res = kftune("evaluate", "--params", params, "--config", config)
    assert res.returncode == EXIT_BAD_INPUT and (tmp_path / "MARKER").exists(), res.stderr


def test_a_named_model_file_is_not_run_unless_it_is_the_tuned_one(tuned, tmp_path):
    """The tuned file's SHA-256 of its model file is checked before the file the user
    names runs: another file (or an edited one) is refused, --force runs it."""
    model = tmp_path / "mine.py"
    model.write_text(MARKING)
    other = hashlib.sha256(b"the file it was tuned with").hexdigest()
    params = naming(tuned, tmp_path, "mine.py", sha256=other)
    for cmd in (["evaluate"], ["estimate", "-o", tmp_path / "est"]):
        res = kftune(*cmd, "--params", params, "--model", model)
        assert res.returncode == EXIT_BAD_INPUT, res.stderr
        assert "has changed since the filter was tuned" in res.stderr and "--force" in res.stderr
        assert not (tmp_path / "MARKER").exists() and "Traceback" not in res.stderr
    res = kftune("evaluate", "--params", params, "--model", model, "--force")
    assert res.returncode == EXIT_BAD_INPUT and (tmp_path / "MARKER").exists(), res.stderr


def test_estimate_takes_only_a_model_file(tuned, tmp_path):
    """estimate runs the tuned filter: its --model names the tuned model's file, a
    built-in model comes from the tuned file."""
    res = kftune("estimate", "--params", tuned, "--model", "ctrv", "-o", tmp_path / "e")
    assert res.returncode == 2 and "--model" in res.stderr and "FILE.py" in res.stderr
    assert not (tmp_path / "e").exists()


def test_a_dataset_mapping_names_built_in_models_only(tmp_path):
    from kftune.data.importer import read_mapping
    from kftune.errors import DataError

    (tmp_path / "evil.py").write_text(MARKING)
    with pytest.raises(DataError, match="key 'model'"):
        read_mapping({"channels": {"t": "time"}, "model": str(tmp_path / "evil.py")})
    assert not (tmp_path / "MARKER").exists()


@pytest.mark.parametrize(("signal_name", "code"), [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_real_interrupt_while_a_model_file_loads_is_still_an_interrupt(
    tmp_path, signal_name, code
):
    """Only a KeyboardInterrupt that the file raises itself is its failure: a Ctrl-C (or a
    SIGTERM) that arrives while it loads ends the command as an interrupt."""
    model = tmp_path / "slow.py"
    model.write_text(
        f"import os, signal\nos.kill(os.getpid(), signal.{signal_name})\n"
        "for _ in range(10**8):\n    pass\n"
    )
    res = kftune("tune", "--model", model, "-n", "2", "-o", tmp_path / "t.json")
    assert res.returncode == code, res.stderr
    assert "interrupted" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "t.json").exists()
