"""Robustness of the single-track UKF (the model's 3×3 loop behind
:class:`kftune.filters.UKF`): divergence is a flag and a step (never an exception or a silent
NaN), covariances are repaired, and bad input is refused before the run with a message
naming the argument, the row and what was expected (hypothesis fuzzing)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import FilterResult, UKFSettings, merwe_weights
from kftune.models import SINGLE_TRACK
from kftune.models._sideslip_ukf import run_kernel
from kftune.models.kernel_io import KernelData, KernelOutputs, SigmaWeights
from kftune.vehicle import preset
from reference_ukf import run_ukf_reference
from single_track import run_ukf, run_ukf_batch

BMW = preset("bmw-320i")
N = 200


@pytest.fixture(scope="module")
def man():
    return demo_manoeuvre(seed=3)


def short(man, n: int = N):
    return man.u[:n].copy(), man.z[:n].copy()


def assert_flagged_not_silent(res, n: int) -> None:
    """Finite rows before the divergence step, NaN rows from it on; all finite otherwise."""
    k = res.diverged_step if res.diverged else n
    assert res.diverged == (res.diverged_step >= 0)
    for arr in (res.x, res.P_diag, res.z_hat, res.innovation, res.nis[:, None]):
        assert np.isfinite(arr[:k]).all()
        assert np.isnan(arr[k:]).all()
    assert (res.P_diag[:k] > 0).all()


# ------------------------------------------------------------------ divergence ------------


def test_overflowing_measurement_is_flagged_at_its_step_in_kernel_and_reference(man):
    u, z = short(man)
    z[150, 0] = 1e90  # finite, positive and below MAX_ABS_INPUT: passes validation; the
    # filter's state then blows up
    runs = [f(u, z, man.dt, man.params, DEFAULT_Q, man.r_var) for f in (run_ukf, run_ukf_reference)]
    for res in runs:
        assert res.diverged
        assert res.diverged_step in (150, 151, 152)
        assert_flagged_not_silent(res, N)
    assert runs[0].diverged_step == runs[1].diverged_step
    np.testing.assert_allclose(runs[0].x[:150], runs[1].x[:150], rtol=1e-9)


def test_state_driven_to_reverse_speed_is_divergence(man):
    u, z = short(man)
    u[100, 1] = -1e4  # an impossible braking input takes the prediction to Vx ≈ −80 m/s
    r = [1e6, 0.01, 1e-5]  # and a Vx sensor the filter hardly trusts keeps it there
    P0 = [0.01, 0.1, 1e-4]
    res = run_ukf(u, z, man.dt, man.params, DEFAULT_Q, r, P0=P0)
    ref = run_ukf_reference(u, z, man.dt, man.params, DEFAULT_Q, r, P0=P0)
    assert (res.diverged_step, ref.diverged_step) == (101, 101)
    assert_flagged_not_silent(res, N)


def test_batch_reports_divergence_per_set(man):
    u, z = short(man)
    u[100, 1] = -1e4
    # set 0 trusts the model's Vx, set 1 the Vx sensor (large q_Vx): only set 0 diverges
    q = [DEFAULT_Q, [10.0, 1e-4, 1e-5]]
    r = [[1e6, 0.01, 1e-5], man.r_var]
    res = run_ukf_batch(u, z, man.dt, man.params, q, r, P0=[0.01, 0.1, 1e-4])
    assert res.diverged.tolist() == [True, False]
    assert res.diverged_step.tolist() == [101, -1]
    assert_flagged_not_silent(res[0], N)
    assert_flagged_not_silent(res[1], N)


def _kernel_run(man, P_init: np.ndarray, n: int = N) -> FilterResult:
    """The compiled 3×3 loop itself, bypassing the UKF's checks (which refuse such a P0)."""
    wm, wc = merwe_weights(3, UKFSettings())
    p = BMW.to_array()
    data = KernelData(
        SINGLE_TRACK.prepared_inputs(man.u[:n], p), man.z[:n], p, man.dt,
        np.array(DEFAULT_Q), man.r_var, man.z[0] * [1, 0, 1], P_init,
        max(1, int(0.5 / man.dt + 0.5)), np.array(SINGLE_TRACK.held_causes, np.int64),
    )  # fmt: skip
    out = KernelOutputs.empty(n, 3, 3)
    div, rep, cause = run_kernel(data, SigmaWeights(wm[0], wc[0], wm[1], math.sqrt(3.0)), out)
    return FilterResult(
        out.x, out.P_diag, out.z_hat, out.innovation, out.nis, div >= 0, div, rep, cause,
        SINGLE_TRACK, "ukf", out.log_det_s,
    )  # fmt: skip


def test_singular_covariance_is_repaired_and_the_run_goes_on(man):
    # a positive semi-definite (singular) prior: Cholesky fails, the first jitter repairs it
    res = _kernel_run(man, np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1e-4]]))
    assert not res.diverged
    assert res.n_repairs == 1
    assert_flagged_not_silent(res, N)
    ok = run_ukf(man.u[:N], man.z[:N], man.dt, BMW, DEFAULT_Q, man.r_var, P0=[1.0, 1.0, 1e-4])
    assert (
        abs(res.output("beta")[-1] - ok.output("beta")[-1]) < 1e-3
    )  # and it forgets the bad prior like a good one


def test_unrepairable_covariance_is_divergence_at_that_step(man):
    res = _kernel_run(man, np.diag([1.0, -1.0, 1.0]))
    assert (res.diverged, res.diverged_step) == (True, 0)
    assert_flagged_not_silent(res, N)
    res = _kernel_run(man, np.diag([1.0, math.nan, 1.0]))
    assert (res.diverged, res.diverged_step) == (True, 0)


@given(
    log_q=st.lists(st.floats(-12, 4), min_size=3, max_size=3),
    log_r=st.lists(st.floats(-10, 3), min_size=3, max_size=3),
    alpha=st.floats(0.05, 2.0),
    beta=st.floats(0.0, 3.0),
    kappa=st.floats(-2.5, 3.0),
    noise_seed=st.integers(0, 2**16),
    noise_scale=st.floats(0.0, 20.0),
)
@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
def test_any_valid_input_runs_without_exception_or_unflagged_nan(
    man, log_q, log_r, alpha, beta, kappa, noise_seed, noise_scale
):
    u, z = short(man)
    rng = np.random.default_rng(noise_seed)
    z = z + noise_scale * rng.standard_normal(z.shape) * np.array([0.05, 0.3, 0.01])
    z[:, 0] = np.maximum(z[:, 0], 0.1)
    u = u + noise_scale * rng.standard_normal(u.shape) * np.array([0.01, 0.3])
    res = run_ukf(
        u, z, man.dt, man.params, 10.0 ** np.array(log_q), 10.0 ** np.array(log_r),
        settings=UKFSettings(alpha, beta, kappa),
    )  # fmt: skip
    assert_flagged_not_silent(res, N)


# ------------------------------------------------------------------ bad input -------------


def _arrays(draw):
    n = draw(st.integers(2, 40))
    u = np.column_stack([np.full(n, 0.01), np.zeros(n)])
    z = np.column_stack([np.full(n, 15.0), np.zeros(n), np.zeros(n)])
    return n, u, z


@given(data=st.data())
@settings(max_examples=80, deadline=None)
def test_non_finite_values_are_refused_naming_argument_row_and_column(data):
    n, u, z = _arrays(data.draw)
    target = data.draw(st.sampled_from(["u", "z"]))
    arr = u if target == "u" else z
    row = data.draw(st.integers(0, n - 1))
    col = data.draw(st.integers(0, arr.shape[1] - 1))
    arr[row, col] = data.draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    with pytest.raises(ValueError, match=re.escape(f"{target}[{row}, {col}]")):
        run_ukf(u, z, 0.01, BMW, DEFAULT_Q, [0.01] * 3)


@given(data=st.data())
@settings(max_examples=40, deadline=None)
def test_non_positive_speed_is_refused_naming_the_row(data):
    n, u, z = _arrays(data.draw)
    row = data.draw(st.integers(0, n - 1))
    z[row, 0] = data.draw(st.floats(-100.0, 0.0))
    with pytest.raises(ValueError, match=re.escape(f"z[{row}, 0] (Vx)") + ".*must be > 0"):
        run_ukf(u, z, 0.01, BMW, DEFAULT_Q, [0.01] * 3)


@given(data=st.data())
@settings(max_examples=40, deadline=None)
def test_negative_or_non_finite_noise_is_refused_naming_the_entry(data):
    _, u, z = _arrays(data.draw)
    name = data.draw(st.sampled_from(["q", "r"]))
    idx = data.draw(st.integers(0, 2))
    bad = data.draw(st.one_of(st.floats(-1e3, -1e-12), st.just(math.nan), st.just(math.inf)))
    q, r = np.array(DEFAULT_Q), np.full(3, 0.01)
    (q if name == "q" else r)[idx] = bad
    with pytest.raises(ValueError, match=re.escape(f"{name}[{idx}]")):
        run_ukf(u, z, 0.01, BMW, q, r)


@pytest.mark.parametrize("dt", [0.0, -0.01, math.nan, math.inf, "x"])
def test_bad_sample_time_is_refused(dt):
    u, z = np.zeros((5, 2)), np.tile([10.0, 0.0, 0.0], (5, 1))
    with pytest.raises(ValueError, match="dt must be"):
        run_ukf(u, z, dt, BMW, DEFAULT_Q, [0.01] * 3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"u": np.zeros((5, 3))}, r"u must have shape \(N, 2\).*got shape \(5, 3\)"),
        ({"z": np.zeros(5)}, r"z must have shape \(N, 3\)"),
        ({"u": np.zeros((0, 2)), "z": np.zeros((0, 3))}, r"N >= 1"),
        ({"z": np.tile([10.0, 0.0, 0.0], (4, 1))}, r"same number of rows.*5 rows.*4 rows"),
        ({"q": [1e-3, 1e-3]}, r"q must have shape \(3,\)"),
        ({"r": [0.01, 0.0, 0.01]}, r"r\[1\] = 0.0.*must be > 0"),
        ({"x0": [10.0, 0.0]}, r"x0 must have shape \(3,\)"),
        (
            {"x0": [-1.0, 0.0, 0.0]},
            r"x0 = \[-1.0, 0.0, 0.0\] is not a valid state.*Vx fell to 0 m/s or below",
        ),
        ({"P0": np.diag([1.0, -1.0, 1.0])}, r"P0 must be positive definite"),
        ({"P0": [[1.0, 0.5, 0], [0.0, 1.0, 0], [0, 0, 1.0]]}, r"P0 must be symmetric"),
        ({"params": np.ones(5)}, r"params must be a VehicleParams or a packed array"),
        ({"settings": "fast"}, r"settings must be a UKFSettings"),
    ],
)
def test_wrong_shapes_and_values_are_refused(kwargs, match):
    args = {
        "u": np.zeros((5, 2)),
        "z": np.tile([10.0, 0.0, 0.0], (5, 1)),
        "dt": 0.01,
        "params": BMW,
        "q": DEFAULT_Q,
        "r": [0.01] * 3,
    } | kwargs
    with pytest.raises(ValueError, match=match):
        run_ukf(**args)


def test_batch_refuses_bad_shapes():
    u, z = np.zeros((5, 2)), np.tile([10.0, 0.0, 0.0], (5, 1))
    with pytest.raises(ValueError, match=r"q must have shape \(B, 3\)"):
        run_ukf_batch(u, z, 0.01, BMW, DEFAULT_Q, [0.01] * 3)
    with pytest.raises(ValueError, match=r"r must have shape \(3,\) or \(B, 3\) with B = 2"):
        run_ukf_batch(u, z, 0.01, BMW, [DEFAULT_Q] * 2, [[0.01] * 3] * 3)
    with pytest.raises(ValueError, match=re.escape("q[1, 2]")):
        run_ukf_batch(u, z, 0.01, BMW, [DEFAULT_Q, [1e-3, 1e-3, -1.0]], [0.01] * 3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"alpha": 0.0}, "alpha must be > 0"),
        ({"beta": math.nan}, "beta must be a finite number"),
        ({"kappa": -3.0}, "kappa must be > -3"),
    ],
)
def test_bad_sigma_point_settings_are_refused(kwargs, match):
    u, z = np.zeros((5, 2)), np.tile([10.0, 0.0, 0.0], (5, 1))
    with pytest.raises(ValueError, match=match):
        run_ukf(u, z, 0.01, BMW, DEFAULT_Q, [0.01] * 3, settings=UKFSettings(**kwargs))


@pytest.mark.parametrize("row", [0, 150])
@pytest.mark.parametrize(("arg", "col"), [("z", 0), ("z", 2), ("u", 1)])
def test_values_whose_squares_overflow_are_refused(man, row, col, arg):
    """Beyond ±1e100 a covariance (a square) overflows: refused before the run, naming the
    entry, whether in the first row (the default prior is built from it) or later."""
    u, z = short(man)
    (z if arg == "z" else u)[row, col] = 1e160
    for f in (run_ukf, run_ukf_reference):
        with pytest.raises(ValueError, match=rf"{arg}\[{row}, {col}\] .*1e\+160.*overflow"):
            f(u, z, man.dt, man.params, DEFAULT_Q, man.r_var)
    with pytest.raises(ValueError, match="overflow"):
        run_ukf_batch(u, z, man.dt, man.params, [DEFAULT_Q], man.r_var)
