"""The single-track model's vector-lane loop (``UKF().run_batch(SINGLE_TRACK, ...,
lanes=True)``, :mod:`kftune.models._sideslip_lanes`) against its sequential 3×3 loop, set
by set.

Every set's result must equal ``run_ukf``'s for that set (≤ 1e-12 relative; the kernel
does the same operations in the same order, so it is in fact bit for bit), including sets
that diverge at different steps and for different causes, sets whose covariances need
repair, and batches where most sets diverge; a diverged set must not poison the others.
``run_ukf`` itself is checked against FilterPy in test_ukf.py; here the numpy reference
filter is a second, independent check on a short run.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import kftune.models._sideslip_lanes as soa
from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import FilterResult, UKFSettings, merwe_weights
from kftune.models import SINGLE_TRACK
from kftune.models._sideslip_ukf import run_kernel
from kftune.models.kernel_io import KernelData, KernelOutputs, SigmaWeights
from reference_ukf import run_ukf_reference
from single_track import run_ukf, run_ukf_simd

FIELDS = ("x", "P_diag", "z_hat", "innovation", "nis")


@pytest.fixture(scope="module")
def man():
    return demo_manoeuvre(seed=0)


def assert_same(one: FilterResult, ref: FilterResult) -> None:
    """Equal to 1e-12 relative (NaN where the reference has NaN), same divergence."""
    for name in FIELDS:
        np.testing.assert_allclose(
            getattr(one, name), getattr(ref, name), rtol=1e-12, atol=0, equal_nan=True
        )
    assert (one.diverged, one.diverged_step, one.diverged_cause, one.n_repairs) == (
        ref.diverged,
        ref.diverged_step,
        ref.diverged_cause,
        ref.n_repairs,
    )


def check_against_run_ukf(man, q, r, **kw) -> None:
    args = (man.u, man.z, man.dt, man.params)
    batch = run_ukf_simd(*args, q, r, **kw)
    q = np.asarray(q, dtype=float)
    r = np.asarray(r, dtype=float)
    assert len(batch) == q.shape[0]
    # the lanes (B > 1) compute no log det S; B = 1 runs the 3×3 loop, which does
    assert (batch.log_det_s is None) == (q.shape[0] > 1)
    for b in range(q.shape[0]):
        assert_same(batch[b], run_ukf(*args, q[b], r if r.ndim == 1 else r[b], **kw))
    return batch


@pytest.mark.parametrize("n_sets", [2, 3, 4, 5, 8, 13])
def test_each_set_equals_run_ukf(man, n_sets):
    rng = np.random.default_rng(n_sets)
    q = np.array(DEFAULT_Q) * 10.0 ** rng.uniform(-3, 2, size=(n_sets, 3))
    r = man.r_var * 10.0 ** rng.uniform(-1, 1, size=(n_sets, 3))
    check_against_run_ukf(man, q, r)
    check_against_run_ukf(man, q, man.r_var)  # r broadcast to every set


def test_sets_diverging_at_different_steps_do_not_poison_the_others(man):
    good = np.array(DEFAULT_Q)
    q = np.array(
        [
            good,
            [1e-4, 1e9, 1e-5],  # runaway sideslip at the first prediction (step 1)
            good * 3,
            [1e-4, 1e4, 1e-5],  # runaway at step 2
            [1e-4, 1e3, 1e-5],  # held runaway, late (step ~1000)
            good / 7,
            [0.0, 0.0, 0.0],
        ]
    )
    r = np.tile(man.r_var, (len(q), 1))
    r[6] *= 1e-20  # a sensor trusted beyond double precision: numerical failure at step 1
    batch = check_against_run_ukf(man, q, r)
    steps = batch.diverged_step.tolist()
    assert steps[0] == steps[2] == steps[5] == -1
    assert len({s for s in steps if s >= 0}) >= 3  # at least three different steps
    assert len({int(c) for c in batch.diverged_cause if c}) >= 2  # two different causes
    for b in (0, 2, 5):
        assert np.isfinite(batch.x[b]).all()


def test_all_sets_diverging_and_a_lone_survivor(man):
    q = np.array([[1e-4, 1e9, 1e-5]] * 6 + [list(DEFAULT_Q)])
    batch = check_against_run_ukf(man, q, man.r_var)
    assert batch.diverged.tolist() == [True] * 6 + [False]
    check_against_run_ukf(man, q[:6], man.r_var)


def test_sets_retired_across_blocks_of_lanes(man):
    # 21 sets fill three blocks of soa.LANES; retiring a set moves the last active one,
    # from another block, into its lane, so the compaction must move whole rows between blocks
    assert soa.LANES < 21 <= 3 * soa.LANES
    rng = np.random.default_rng(5)
    q = np.array(DEFAULT_Q) * 10.0 ** rng.uniform(-1, 1, size=(21, 3))
    for b, bad in ((0, 1e9), (3, 1e4), (9, 1e3), (10, 1e9), (16, 1e4), (20, 1e9)):
        q[b] = [1e-4, bad, 1e-5]
    batch = check_against_run_ukf(man, q, man.r_var)
    assert set(np.flatnonzero(batch.diverged)) == {0, 3, 9, 10, 16, 20}
    assert len(set(batch.diverged_step[batch.diverged].tolist())) >= 3


def test_single_set_and_sigma_point_settings(man):
    check_against_run_ukf(man, np.array([DEFAULT_Q]), man.r_var)
    st_ = UKFSettings(alpha=0.5, beta=2.0, kappa=1.0)
    check_against_run_ukf(
        man, np.array([DEFAULT_Q, DEFAULT_Q]) * [[1], [10]], man.r_var, settings=st_
    )


def test_against_the_numpy_reference_filter(man):
    n = 300
    q = np.array([DEFAULT_Q, [1e-3, 1e-3, 1e-4], [1e-4, 1e9, 1e-5]])
    batch = run_ukf_simd(man.u[:n], man.z[:n], man.dt, man.params, q, man.r_var)
    for b in range(3):
        ref = run_ukf_reference(man.u[:n], man.z[:n], man.dt, man.params, q[b], man.r_var)
        assert batch.diverged_step[b] == ref.diverged_step
        k = n if ref.diverged_step < 0 else ref.diverged_step
        np.testing.assert_allclose(batch.x[b, :k], ref.x[:k], rtol=1e-9, atol=1e-12)


def _result(out: KernelOutputs, div: int, rep: int, why: int) -> FilterResult:
    return FilterResult(
        out.x, out.P_diag, out.z_hat, out.innovation, out.nis, div >= 0, div, rep, why,
        SINGLE_TRACK, "ukf",
    )  # fmt: skip


def _raw(man, P_init: np.ndarray, n: int = 200):
    """Both loops with priors the UKF would refuse (singular, indefinite, NaN)."""
    wm, wc = merwe_weights(3, UKFSettings())
    w = SigmaWeights(wm[0], wc[0], wm[1], math.sqrt(3.0))
    n_sets = P_init.shape[0]
    p = man.params.to_array()
    data = KernelData(
        SINGLE_TRACK.prepared_inputs(man.u[:n], p), man.z[:n], p, man.dt,
        np.tile(DEFAULT_Q, (n_sets, 1)), np.tile(man.r_var, (n_sets, 1)),
        np.tile(man.z[0] * [1, 0, 1], (n_sets, 1)), P_init, max(1, int(0.5 / man.dt + 0.5)),
        np.array(SINGLE_TRACK.held_causes, np.int64),
    )  # fmt: skip
    outs = KernelOutputs.empty(n, 3, 3, batch=n_sets)
    ints = [np.empty(n_sets, dtype=np.int64) for _ in range(3)]
    ints[1][:] = 0
    soa.ensure_compiled()
    soa.run_kernel_soa(data, w, outs, *ints)
    for b in range(n_sets):
        one_data = data._replace(
            q=data.q[b], r=data.r[b], x_init=data.x_init[b], P_init=data.P_init[b]
        )
        one = KernelOutputs.empty(n, 3, 3)  # (log det S: not compared, the lanes have none)
        div, rep, why = run_kernel(one_data, w, one)
        got = _result(outs.at(b), int(ints[0][b]), int(ints[1][b]), int(ints[2][b]))
        assert_same(got, _result(one, div, rep, why))
    return ints


def test_repairs_and_unrepairable_priors_match_the_sequential_kernel(man):
    singular = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1e-4]])
    good = np.diag([0.01, 0.1, 1e-4])
    P = np.stack([good, singular, np.diag([1.0, -1.0, 1.0]), good, np.diag([1, math.nan, 1])])
    div, rep, _ = _raw(man, P)
    assert rep[1] == 1 and div[1] == -1  # repaired, and the run goes on
    assert div[2] == 0 and div[4] == 0  # unrepairable: divergence at step 0
    assert div[0] == div[3] == -1


@given(
    log_q=st.lists(st.lists(st.floats(-12, 9), min_size=3, max_size=3), min_size=2, max_size=9),
    log_r=st.lists(st.floats(-8, 3), min_size=3, max_size=3),
)
@settings(
    max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
def test_any_batch_equals_run_ukf_set_by_set(man, log_q, log_r):
    n = 400
    q = 10.0 ** np.array(log_q)
    r = 10.0 ** np.array(log_r)
    args = (man.u[:n], man.z[:n], man.dt, man.params)
    batch = run_ukf_simd(*args, q, r)
    for b in range(q.shape[0]):
        assert_same(batch[b], run_ukf(*args, q[b], r))
