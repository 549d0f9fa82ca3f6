"""TuningProblem.evaluate_batch: the vectorised batch kernel on the fast path, a loop
otherwise; every point's result equals evaluate()'s exactly, and a diverged point returns
its error without losing the others."""

from __future__ import annotations

import numpy as np
import pytest

from kftune.data import default_dataset
from kftune.errors import FilterDivergedError
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem


@pytest.fixture(scope="module")
def ds():
    return default_dataset()


def assert_batch_equals_sequential(problem: TuningProblem, X) -> list:
    batch = problem.evaluate_batch(X)
    assert len(batch) == len(X)
    for x, got in zip(X, batch):
        try:
            want = problem.evaluate(x)
        except FilterDivergedError as exc:
            assert isinstance(got, FilterDivergedError)
            assert str(got) == str(exc)
            continue
        assert got.cost == want.cost  # bit for bit
        assert got.pooled == want.pooled and got.mean_nis == want.mean_nis
        assert got.scores == want.scores
    return batch


def test_batch_equals_sequential_with_diverged_points(ds):
    wide = NoiseParameterization(q_bounds=(1e-10, 1e4))
    problem = TuningProblem(ds.train[:3], ds.vehicle, ds.r_default, parameterization=wide)
    rng = np.random.default_rng(0)
    X = list(10.0 ** rng.uniform(-8, -1, size=(5, 3)))
    X.insert(2, np.array([1e-10, 1e4, 1e-10]))  # runs away on the first manoeuvre
    batch = assert_batch_equals_sequential(problem, X)
    assert isinstance(batch[2], FilterDivergedError)
    assert sum(isinstance(b, FilterDivergedError) for b in batch) == 1


def test_points_with_different_sigma_point_settings_and_r_scale(ds):
    par = NoiseParameterization(tune_r_scale=True, tune_sigma_points=True)
    problem = TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, parameterization=par)
    rng = np.random.default_rng(1)
    X = list(problem.space.from_unit(rng.uniform(size=(4, problem.space.dim))))
    X.append(X[0].copy())
    X[-1][:3] = [1e-5, 1e-6, 1e-4]  # same settings as X[0], other Q: one kernel call
    assert_batch_equals_sequential(problem, X)


def test_fallback_loop_for_the_nis_cost_and_a_single_point(ds):
    from kftune.tuning.cost import CostSpec

    problem = TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, cost=CostSpec(kind="nis"))
    assert_batch_equals_sequential(problem, [[1e-4, 1e-6, 1e-3], [1e-5, 1e-5, 1e-5]])
    assert_batch_equals_sequential(problem, [[1e-4, 1e-6, 1e-3]])


def test_the_dataset_normalised_cost_through_the_batch_kernel(ds):
    from kftune.tuning.cost import CostSpec

    spec = CostSpec(normalise="dataset")
    problem = TuningProblem(ds.train[:3], ds.vehicle, ds.r_default, cost=spec)
    X = list(10.0 ** np.random.default_rng(2).uniform(-8, -1, (3, 3)))
    batch = assert_batch_equals_sequential(problem, X)
    paper = TuningProblem(ds.train[:3], ds.vehicle, ds.r_default)  # Eq. 15: other numbers
    assert all(b.cost != pytest.approx(paper.evaluate(x).cost, rel=1e-3) for b, x in zip(batch, X))
