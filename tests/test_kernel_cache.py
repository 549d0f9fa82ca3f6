"""The generic filters' kernels are compiled once per model and loaded from a cache on disk
by later processes (:mod:`kftune.models._generated`): a second process hits the cache and
gives the same numbers, an edited model file is a new kernel (never a stale one), and a
cache folder that cannot be used costs only the cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from kftune.models import StateSpaceModel, _generated

#: Every test here compiles kernels in child processes: outside the fast inner loop.
pytestmark = pytest.mark.slow

MODEL = """
import numpy as np
from numba import njit
from kftune.models import StateSpaceModel

GAIN = {gain}


@njit
def f(x, u, p, dt, out):
    out[0] = x[0] + dt * x[1]
    out[1] = GAIN * x[1] + dt * u[0]


@njit
def h(x, u, p, out):
    out[0] = x[0]


def prior(z0, r, p):
    return np.array([z0[0], 0.0]), np.diag([r[0], 1.0])


MODEL = StateSpaceModel(
    name="cache-probe", state_names=("pos", "vel"), state_units=("m", "m/s"),
    input_names=("acc",), input_units=("m/s^2",), measurement_names=("pos",),
    measurement_units=("m",), f=f, h=h, initial_state=prior,
)
"""

RUN = """
import json, sys
import numpy as np
from kftune.filters import get_filter
from kftune.filters._compiled import kernel_module
from kftune.models.user import load_model

model = load_model(sys.argv[1])
rng = np.random.default_rng(0)
u = rng.standard_normal((200, 1))
z = np.cumsum(rng.standard_normal((200, 1)), axis=0)
res = get_filter(sys.argv[2]).run(model, u, z, 0.01, np.array([1e-4, 1e-2]), np.array([0.1]))
module = kernel_module(model)
fn = module.ukf_single if sys.argv[2] == "ukf" else module.ekf_single_given
print(json.dumps({
    "hits": sum(fn.stats.cache_hits.values()),
    "misses": sum(fn.stats.cache_misses.values()),
    "module": module.__name__,
    "x": res.x[-1].tolist(),
}))
"""


def _run(model_file: Path, filt: str, cache: str) -> dict:
    env = {**os.environ, "KFTUNE_CACHE_DIR": cache}
    done = subprocess.run(
        [sys.executable, "-c", RUN, str(model_file), filt],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("filt", ["ukf", "ekf"])
def test_a_second_process_loads_the_kernel_and_an_edited_model_is_a_new_one(tmp_path, filt):
    model_file = tmp_path / "probe_model.py"
    model_file.write_text(MODEL.format(gain=1.0))
    cache = tmp_path / "cache"
    first = _run(model_file, filt, str(cache))
    second = _run(model_file, filt, str(cache))
    assert (first["hits"], first["misses"]) == (0, 1)
    assert (second["hits"], second["misses"]) == (1, 0)
    assert second["module"] == first["module"]
    np.testing.assert_allclose(second["x"], first["x"], rtol=1e-15)
    assert list((cache / "kernels").glob("kftune_kernels_*.py"))

    model_file.write_text(MODEL.format(gain=0.5))  # the same file, other dynamics
    edited = _run(model_file, filt, str(cache))
    assert edited["module"] != first["module"]
    assert (edited["hits"], edited["misses"]) == (0, 1)
    assert not np.allclose(edited["x"], first["x"], rtol=1e-6)


def test_a_cache_folder_that_cannot_be_made_costs_only_the_cache(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    model_file = tmp_path / "probe_model.py"
    model_file.write_text(MODEL.format(gain=1.0))
    for cache in (str(blocker / "below"), ""):  # cannot be created; or no cache asked for
        out = _run(model_file, "ukf", cache)
        assert (out["hits"], out["misses"]) == (0, 1)
        assert np.all(np.isfinite(out["x"]))
    assert blocker.read_text() == "not a folder"


def test_the_key_covers_closure_constants_and_refuses_what_it_cannot_see():
    def model_with(gain: object) -> StateSpaceModel:
        @njit
        def f(x, u, p, dt, out):
            out[0] = gain * x[0]

        @njit
        def h(x, u, p, out):
            out[0] = x[0]

        return StateSpaceModel(
            name="closure", state_names=("a",), state_units=("",), input_names=(),
            input_units=(), measurement_names=("a",), measurement_units=("",), f=f, h=h,
        )  # fmt: skip

    one, other = model_with(1.0), model_with(2.0)
    assert _generated._key(one, "code") is not None
    assert _generated._key(one, "code") == _generated._key(model_with(1.0), "code")
    assert _generated._key(one, "code") != _generated._key(other, "code")
    assert _generated._key(model_with(njit(lambda v: v)), "code") is None  # a function's behaviour
    assert _generated._key(one, "code") != _generated._key(one, "other code")


def test_the_cache_keeps_the_newest_modules_and_their_code(tmp_path, monkeypatch):
    monkeypatch.setattr(_generated, "MAX_MODULES", 2)
    (tmp_path / "__pycache__").mkdir()
    for age, name in enumerate(["kftune_kernels_c", "kftune_kernels_b", "kftune_kernels_a"]):
        module = tmp_path / f"{name}.py"
        module.write_text("")
        code = tmp_path / "__pycache__" / f"{name}.ukf_single-12.py311.nbi"
        code.write_text("")
        os.utime(module, (1e9 - age, 1e9 - age))  # c newest, a oldest
    (tmp_path / "other.py").write_text("")
    _generated._prune(tmp_path)
    assert sorted(p.name for p in tmp_path.glob("*.py")) == [
        "kftune_kernels_b.py", "kftune_kernels_c.py", "other.py",
    ]  # fmt: skip
    assert sorted(p.name.split(".")[0] for p in (tmp_path / "__pycache__").iterdir()) == [
        "kftune_kernels_b", "kftune_kernels_c",
    ]  # fmt: skip


def test_a_bounds_checked_copy_of_a_model_is_other_code(tmp_path):
    """The child process that checks a model file's hooks (tuning.hookcheck) runs them
    recompiled with numba's bounds check: it must never load the unchecked kernels from
    the cache (the check would be silently gone), nor leave checked ones for the tuning."""
    from kftune.models.user import checked_model, load_model

    model_file = tmp_path / "probe_model.py"
    model_file.write_text(MODEL.format(gain=1.0))
    model = load_model(str(model_file))
    checked = checked_model(model)
    assert checked.f.targetoptions.get("boundscheck") is True
    assert _generated._key(model, "code") != _generated._key(checked, "code")


def test_the_cache_runs_only_code_kftune_wrote_in_a_folder_only_its_user_writes(tmp_path):
    """The cache holds code kftune imports: a module planted under the name kftune would
    use is never run (kftune's own text is compiled elsewhere instead), and a cache folder
    that other users can write is not used at all."""
    model_file = tmp_path / "probe_model.py"
    model_file.write_text(MODEL.format(gain=1.0))
    cache = tmp_path / "cache"
    first = _run(model_file, "ukf", str(cache))
    planted = cache / "kernels" / f"{first['module']}.py"
    marker = tmp_path / "RAN"
    planted.write_text(f"open({str(marker)!r}, 'w').close()\n")
    again = _run(model_file, "ukf", str(cache))
    assert not marker.exists()
    np.testing.assert_allclose(again["x"], first["x"], rtol=1e-12)
    assert planted.read_text().startswith("open(")  # left as it was, not imported

    shared = tmp_path / "shared"
    (shared / "kernels").mkdir(parents=True)
    (shared / "kernels").chmod(0o777)
    out = _run(model_file, "ukf", str(shared))
    np.testing.assert_allclose(out["x"], first["x"], rtol=1e-12)
    assert not list((shared / "kernels").iterdir())
