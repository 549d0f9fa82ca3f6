"""A model's own compiled loops (``StateSpaceModel.ukf_kernels``, :class:`ModelKernels`) run
behind the one UKF's interface: the filter calls the model's loop where the model supplies
one (single runs, threads, vector lanes on request), the generic loop otherwise, and the
EKF never. The single-track model's own loops give the generic loop's results (its 3×3
loop to 1e-12, the lanes the 3×3 loop's to 1e-12 too); against FilterPy and the numpy
reference they are tested in tests/test_ukf.py and tests/test_filters_generic.py."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from numba import njit

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import EKF, UKF
from kftune.models import SINGLE_TRACK, ModelKernels, StateSpaceModel
from kftune.models.sideslip import measurement, single_track_kernels

OUTPUTS = ("x", "P_diag", "z_hat", "innovation", "nis")


@pytest.fixture(scope="module")
def man():
    m = demo_manoeuvre(0)
    return m.u[:800], m.z[:800], m.dt, m.params.to_array(), m.r_var


def spied(calls: list[str]) -> StateSpaceModel:
    """The single-track model whose own loops record each call before they run."""
    own = single_track_kernels()

    def spy(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(*args: Any) -> Any:
            calls.append(name)
            return fn(*args)

        return wrapped

    assert own.lanes is not None
    kernels = ModelKernels(
        spy("single", own.single), spy("batch", own.batch), spy("lanes", own.lanes),
        own.implements,
    )  # fmt: skip
    return dataclasses.replace(SINGLE_TRACK, ukf_kernels=lambda: kernels)


@njit(cache=True)
def half_ay(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """The single-track measurement with half the lateral acceleration."""
    measurement(x, u, p, out)
    out[1] *= 0.5


def test_the_ukf_runs_the_models_own_loop_and_the_ekf_does_not(man):
    u, z, dt, p, r = man
    calls: list[str] = []
    model = spied(calls)
    q = np.array([DEFAULT_Q] * 3) * [[1.0], [10.0], [0.1]]
    UKF().run(model, u, z, dt, DEFAULT_Q, r, params=p)
    assert calls == ["single"]
    UKF().run_batch(model, u, z, dt, q, r, params=p)
    assert calls[1:] == ["batch"]
    lanes = UKF().run_batch(model, u, z, dt, q, r, params=p, lanes=True)
    assert calls[2:] == ["lanes"] and lanes.log_det_s is None
    UKF().run_batch(model, u, z, dt, q[:1], r, params=p, lanes=True)  # one set: no lanes
    assert calls[3:] == ["single"]
    EKF().run(model, u, z, dt, DEFAULT_Q, r, params=p)
    EKF().run_batch(model, u, z, dt, q, r, params=p, lanes=True)
    assert len(calls) == 4


def test_a_model_without_its_own_loops_runs_the_generic_one_and_both_agree(man):
    """The 3×3 loop against the generic loop on the same model (to 1e-12 of each
    channel's scale), lanes against threads to 1e-12 relative (the same operations in the same
    order; a tolerance, not bit equality, across CPUs), including a set that diverges."""
    u, z, dt, p, r = man
    generic = dataclasses.replace(SINGLE_TRACK, ukf_kernels=None)
    q = np.array([DEFAULT_Q] * 4) * [[1.0], [30.0], [0.03], [1.0]]
    q[3] = 1e9  # runs away at once
    own = UKF().run_batch(SINGLE_TRACK, u, z, dt, q, r, params=p)
    lanes = UKF().run_batch(SINGLE_TRACK, u, z, dt, q, r, params=p, lanes=True)
    ref = UKF().run_batch(generic, u, z, dt, q, r, params=p)
    np.testing.assert_array_equal(own.diverged_step, ref.diverged_step)
    np.testing.assert_array_equal(own.diverged_cause, ref.diverged_cause)
    assert own.diverged[3] and not own.diverged[:3].any()
    for name in (*OUTPUTS, "log_det_s"):
        a, b = getattr(own, name)[:3], getattr(ref, name)[:3]
        scale = np.max(np.abs(b), axis=1, keepdims=True)
        assert np.all(np.abs(a - b) <= 1e-12 * np.where(scale > 0, scale, 1.0)), name
    for name in OUTPUTS:  # (the lanes compute no log det S)
        np.testing.assert_allclose(
            getattr(lanes, name), getattr(own, name), rtol=1e-12, atol=0, equal_nan=True
        )
    np.testing.assert_array_equal(lanes.diverged_step, own.diverged_step)


def test_the_lanes_compile_once_for_the_data_the_filter_hands_them():
    """A read-only z or an F-ordered r would make numba compile a second version of the
    lanes outside ``ensure_compiled``'s raised inlining threshold: unvectorised, 3–4×
    slower. In a fresh process, after a filter run on a dataset's manoeuvre, the lanes
    loop has one compiled signature."""
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from kftune.data import open_dataset\n"
        "from kftune.filters import UKF\n"
        "from kftune.models import SINGLE_TRACK\n"
        "from kftune.models._sideslip_lanes import run_kernel_soa\n"
        "ds = open_dataset('default'); m = ds.train[0]\n"
        "m.z.flags.writeable = False\n"
        "UKF().run_batch(SINGLE_TRACK, m.u, m.z, m.dt, np.full((3, 3), 1e-4), ds.r_default,\n"
        "                params=ds.vehicle, lanes=True)\n"
        "print(len(run_kernel_soa.signatures))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-1] == "1", out.stdout + out.stderr


def test_a_copy_of_the_model_with_other_hooks_runs_the_generic_loop(man):
    """The model's own loops implement its f, h and check: a copy with another h (a
    user's variant of the single-track model) must not run the 3×3 physics."""
    u, z, dt, p, r = man
    calls: list[str] = []
    variant = dataclasses.replace(spied(calls), name="half-ay", h=half_ay)
    res = UKF().run(variant, u, z, dt, DEFAULT_Q, r, params=p)
    assert calls == []
    generic = UKF().run(
        dataclasses.replace(variant, ukf_kernels=None), u, z, dt, DEFAULT_Q, r, params=p
    )
    np.testing.assert_array_equal(res.x, generic.x)
    own = UKF().run(SINGLE_TRACK, u, z, dt, DEFAULT_Q, r, params=p)
    assert not np.allclose(res.x, own.x)  # the 3×3 physics would have given own.x
    assert calls == []
