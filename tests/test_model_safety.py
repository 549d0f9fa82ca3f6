"""A model file is Python code that runs with the user's rights: kftune runs one only when
the user names it (``--model``, or a configuration passed on the command line), never
because a tuned file or a dataset mapping names it — a tuned file is what users send each
other. The model files here write a marker when imported, so a test sees whether they ran."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import default_sigint
from conftest import run_cli as kftune
from kftune.cli import EXIT_BAD_INPUT, EXIT_OK

#: [s] how long a test waits for a command before it counts as hung (load can stretch any
#: wait; only a hang should reach this).
HANG_GUARD = 300
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
    # export writes the tuned values without running the model; its C filter needs the
    # model's C, so it asks for --model as the others do
    res = kftune("export", str(params), "-o", str(tmp_path / "kf.json"))
    assert res.returncode == EXIT_OK, res.stderr
    res = kftune("export", str(params), "-o", str(tmp_path / "kf_c"), "-f", "c")
    assert res.returncode == EXIT_BAD_INPUT, res.stderr
    assert "--model" in res.stderr and "Python code" in res.stderr
    assert not (model.parent / "MARKER").exists() and not (tmp_path / "kf_c").exists()


@pytest.mark.parametrize("kind", ["fifo", "device"])
@pytest.mark.slow
def test_a_model_file_named_by_a_tuned_file_is_hashed_only_if_it_is_a_regular_file(
    tuned, tmp_path, kind
):
    """export compares the recorded SHA-256 with the file's: a tuned file from elsewhere
    naming a FIFO made it wait for ever, one naming /dev/zero read without end."""
    from conftest import DEV_ZERO
    from kftune.models.user import model_file_sha256

    model = tmp_path / "evil.py"
    if kind == "fifo":
        os.mkfifo(model)
    else:
        model.symlink_to(DEV_ZERO)
    assert model_file_sha256(str(model)) is None
    params = naming(tuned, tmp_path, "evil.py", sha256="0" * 64)
    export = [sys.executable, "-m", "kftune", "export", str(params), "-f", "yaml"]
    res = subprocess.run(
        [*export, "-o", str(tmp_path / "kf.yaml")], capture_output=True, text=True,
        timeout=HANG_GUARD, cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == EXIT_OK and "Traceback" not in res.stderr, res.stderr


def test_a_model_files_hash_is_sha256_of_its_bytes(tmp_path):
    from kftune.models.user import model_file_sha256

    model = tmp_path / "m.py"
    model.write_bytes(bytes(range(256)) * 5000)  # over one read block
    want = hashlib.sha256(model.read_bytes()).hexdigest()
    assert model_file_sha256(f"{model}:MODEL") == want == model_file_sha256(str(model))
    assert model_file_sha256("single-track") is None


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


def test_estimate_takes_only_the_model_file_of_a_filter_tuned_with_one(tuned, tmp_path):
    """estimate runs the tuned filter: its --model names the tuned model's file; a
    built-in model comes from the tuned file, and is not replaced by a file."""
    res = kftune("estimate", "--params", tuned, "--model", "ctrv", "-o", tmp_path / "e")
    assert res.returncode == 2 and "--model" in res.stderr and "FILE.py" in res.stderr
    (tmp_path / "mine.py").write_text(MARKING)
    res = kftune("estimate", "--params", tuned, "--model", tmp_path / "mine.py", "-o",
                 tmp_path / "e")  # fmt: skip
    assert res.returncode == 2 and "built-in model 'single-track'" in res.stderr, res.stderr
    assert not (tmp_path / "e").exists() and not (tmp_path / "MARKER").exists()


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
    # a shell that starts the suite in the background makes it ignore SIGINT, and Python
    # then installs no handler: give this process the one an interactive start gives it
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        res = kftune("tune", "--model", model, "-n", "2", "-o", tmp_path / "t.json")
    finally:
        signal.signal(signal.SIGINT, before)
    assert res.returncode == code, res.stderr
    assert "interrupted" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "t.json").exists()


EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "linear_bicycle.py"
#: The example's last line of f, to which a fault is added in some states only.
LAST_OF_F = "    out[2] = x[2] + dt * ((p[2] * fyf * cd - p[3] * fyr) / p[1])\n"


def faulty(folder: Path, fault: str, marker: bool = False) -> Path:
    """The README's example model with ``fault`` at the end of f (indented), and, with
    ``marker``, a line per process that imports it (its pid) in ``folder/imported``."""
    text = EXAMPLE.read_text()
    assert LAST_OF_F in text
    added = "".join(f"    {line}\n" for line in fault.split("\n"))
    text = text.replace(LAST_OF_F, LAST_OF_F + added)
    if marker:
        text += (
            "\nimport os\nwith open(os.path.join(os.path.dirname(__file__), 'imported'), 'a') "
            "as _f:\n    _f.write(f'{os.getpid()}\\n')\n"
        )
    path = folder / "faulty.py"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_a_hook_that_writes_out_of_bounds_in_some_states_is_named(small, tmp_path):
    """f writes beyond out only once the yaw rate exceeds 0.2 rad/s, not at the prior mean
    where the first-sample probe looks: compiled code does not check bounds, so a tuning
    run corrupted memory silently or aborted (glibc). A bounds-checked run of the filter
    over each manoeuvre, in a child process, names the hook, the file and the manoeuvre."""
    model = faulty(tmp_path, "if abs(x[2]) > 0.2:\n    out[3 + int(abs(x[2]) * 1000)] = 0.0")
    out = tmp_path / "t.json"
    res = kftune("tune", small, "--model", model, "-n", "2", "-o", out)
    assert res.returncode == EXIT_BAD_INPUT, res.stderr
    assert f"model {model}, on manoeuvre 'train-03-j-turn': f(x, u, p, dt, out)" in res.stderr
    assert "indexes beyond an array" in res.stderr and "Traceback" not in res.stderr
    assert not out.exists()


#: A random walk whose f writes beyond ``out`` only where |s| > 5: a unit prior around
#: z = 0 reaches it only through sigma points spread by √(n + λ) = √(1 + κ) beyond 5.
WIDE_SIGMA_MODEL = """import numpy as np
from numba import njit
from kftune.models import StateSpaceModel

@njit
def f(x, u, p, dt, out):
    if abs(x[0]) > 5.0:
        out[3 + int(abs(x[0]))] = 0.0
    out[0] = x[0]

@njit
def h(x, u, p, out):
    out[0] = x[0]

def prior(z0, r, p):
    return np.array([z0[0]]), np.diag([1.0])

MODEL = StateSpaceModel(name="walk", state_names=("s",), state_units=("m",), input_names=(),
    input_units=(), measurement_names=("z",), measurement_units=("m",), f=f, h=h,
    initial_state=prior)
"""


@pytest.mark.slow
def test_the_hook_check_runs_the_sigma_points_of_the_filter_it_protects(tmp_path):
    """evaluate and estimate run the tuned α, β, κ: a check with the default sigma points
    never visits the states a wider spread reaches (κ = 100: √101 ≈ 10 prior σ out)."""
    from kftune.filters import UKFSettings
    from kftune.tuning.hookcheck import check_model_file

    model = tmp_path / "walk.py"
    model.write_text(WIDE_SIGMA_MODEL)
    runs = [("walk-1", None, np.zeros((50, 1)), 0.01)]
    q, r = np.array([1e-4]), np.array([1.0])
    check_model_file(str(model), "ukf", runs, np.zeros(0), q, r, UKFSettings())  # no error
    with pytest.raises(ValueError, match=r"on manoeuvre 'walk-1': f\(x, u, p, dt, out\)"):
        check_model_file(str(model), "ukf", runs, np.zeros(0), q, r, UKFSettings(kappa=100.0))


@pytest.mark.slow
def test_a_hook_that_crashes_its_process_is_named(small, tmp_path):
    model = faulty(tmp_path, "out[10**9] = 1.0")  # far beyond: a segmentation fault
    res = kftune("tune", small, "--model", model, "-n", "2", "-o", tmp_path / "t.json")
    assert res.returncode == EXIT_BAD_INPUT, res.stderr
    assert f"model {model}, on manoeuvre 'train-03-j-turn'" in res.stderr
    assert "killed by SIGSEGV" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
@pytest.mark.slow
def test_a_hook_that_never_returns_is_stopped_by_a_signal(small, tmp_path, signum, code):
    """f loops for ever once the yaw rate exceeds 0.2 rad/s: a compiled loop does not see
    signals, so a probe in the command's own process could only be SIGKILLed. The hooks
    run first in a child process, which the command kills when it is told to stop."""
    faulty(tmp_path, "if abs(x[2]) > 0.2:\n    while True:\n        out[0] += 1.0", marker=True)
    proc = subprocess.Popen(
        [sys.executable, "-m", "kftune", "tune", str(small), "--model", "faulty.py", "-n", "2",
         "-o", "t.json"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=default_sigint,
    )  # fmt: skip
    imported = tmp_path / "imported"
    try:
        # the command loaded the model, then the child that runs its hooks did: wait for
        # both lines (a hang guard, not a timing assumption)
        for _ in range(HANG_GUARD * 10):
            if imported.exists() and len(imported.read_text().split()) >= 2:
                break
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.1)
        else:
            pytest.fail("the hooks were not run in a child process")
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=HANG_GUARD)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == code, err
    assert "Traceback" not in err and not (tmp_path / "t.json").exists()
    child = int(imported.read_text().split()[1])
    with pytest.raises(ProcessLookupError):  # killed with the command, not left looping
        os.kill(child, 0)


@pytest.mark.slow
def test_a_long_hook_check_says_why_the_command_waits(small, tmp_path, monkeypatch):
    """A check that takes long (a hook that never returns, or a large model's compile)
    warns that Ctrl-C or SIGTERM stops it, instead of waiting without a word."""
    from kftune.data import open_dataset
    from kftune.errors import DataWarning
    from kftune.tuning import hookcheck
    from kftune.tuning.runs import filter_spec

    monkeypatch.setattr(hookcheck, "SLOW_CHECK", 0.0)  # every check is a long one
    model = tmp_path / "mine.py"
    model.write_text(EXAMPLE.read_text())
    dataset = open_dataset(str(small))
    fs = filter_spec(str(model), "ukf", dataset.vehicle)
    with pytest.warns(DataWarning, match=r"Ctrl-C or SIGTERM") as seen:
        fs.probe(dataset.train[:1], dataset.r_default)
    assert str(model) in str(seen[0].message) and "train-03-j-turn" in str(seen[0].message)
