"""Best points on a bound of the search box: the report (``Space.on_bounds``) and the
follow-up runs on a widened box (``minimize_widening``), resumable and losing nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kftune.optim import OptimizationInterrupted, Space, minimize, minimize_widening
from kftune.optim.widen import round_storage
from kftune.space import Param
from kftune.tuning.parameterization import NoiseParameterization

#: The revs-250lm optimum, found by three CMA-ES runs of 2,000 evaluations (BENCHMARKS.md).
REVS_Q = (3.77e-6, 6.27e-4, 1.0)
REVS_JSTAR = 0.548688
#: the bundled set's optimum (BENCHMARKS.md), well inside [1e-10, 1].
BUNDLED_Q = (5.22e-8, 1.56e-6, 0.173)


def test_bound_report_fires_on_the_revs_optimum_and_not_on_an_interior_one():
    space = NoiseParameterization().space  # the paper's box: log10 q in [1e-10, 1]
    hits = space.on_bounds(space.to_unit(REVS_Q))
    assert [(h.name, h.side) for h in hits] == [("q_r", "upper")]
    assert hits[0].value == pytest.approx(1.0) and hits[0].bound == 1.0
    assert hits[0].to_dict() == {
        "parameter": "q_r",
        "side": "upper",
        "value": hits[0].value,
        "bound": 1.0,
    }
    assert space.on_bounds(space.to_unit(BUNDLED_Q)) == []


def test_bound_report_uses_one_percent_of_the_range():
    """Closed form: on a 10-decade log10 axis 1 % of the range is 0.1 decade, so 10**-0.095
    is on the upper bound 1 and 10**-0.105 is not; on a linear axis [0, 4], 0.04."""
    space = Space.coerce({"q": (1e-10, 1.0, "log10"), "beta": (0.0, 4.0)})
    on = space.on_bounds(space.to_unit([10**-0.095, 0.039]))
    assert [(h.name, h.side) for h in on] == [("q", "upper"), ("beta", "lower")]
    assert space.on_bounds(space.to_unit([10**-0.105, 0.041])) == []
    assert [h.side for h in space.on_bounds(space.to_unit([10**-9.95, 3.99]))] == [
        "lower",
        "upper",
    ]
    with pytest.raises(ValueError, match=r"one \(d,\) point"):
        space.on_bounds(np.zeros((2, 2)))


def test_revs_optimum_is_a_minimum_against_its_bound(revs_dir):
    """On the real recording the CMA-ES optimum has the cost J* found with it, and moving
    q_r in from the bound raises it: the optimum presses against the bound."""
    from kftune.data import load_revs
    from kftune.tuning.problem import TuningProblem

    ds = load_revs(revs_dir)
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    j = problem(np.array(REVS_Q))
    assert j == pytest.approx(REVS_JSTAR, rel=1e-5)
    assert problem(np.array([*REVS_Q[:2], 0.5])) > j


def test_widened_moves_only_the_hit_sides_of_log_parameters():
    space = Space.coerce({"a": (1e-6, 1e-2, "log10"), "b": (1e-6, 1e-2, "log10"), "c": (0, 1)})
    hits = space.on_bounds(space.to_unit([1e-6, 1e-2, 1.0]))
    assert [(h.name, h.side) for h in hits] == [("a", "lower"), ("b", "upper"), ("c", "upper")]
    wider = space.widened(hits, decades=2.0)
    assert wider.lows == pytest.approx([1e-8, 1e-6, 0.0], rel=1e-12)
    assert wider.highs == pytest.approx([1e-2, 1.0, 1.0], rel=1e-12)
    assert space.widened([h for h in hits if h.name == "c"], 2.0) is space
    with pytest.raises(ValueError, match="decades"):
        space.widened(hits, decades=0.0)


def test_widened_keeps_a_parameter_physical():
    # TR-BO's design reads ``physical`` in the next round, so widening must not drop it
    space = Space([Param("q", 1e-6, 1e-2, "log10"), Param("c", 1e4, 1e5, "log10", physical=True)])
    hits = space.on_bounds(space.to_unit([1e-6, 1e5]))
    wider = space.widened(hits, decades=1.0)
    assert wider is not space
    assert [p.physical for p in wider.params] == [False, True]


#: a minimum outside the initial box: b* = 0.3 lies 1.5 decades above its upper bound 1e-2
SPACE = {"a": (1e-6, 1e-2, "log10"), "b": (1e-6, 1e-2, "log10")}
X_STAR = (1e-3, 0.3)


def bowl(x: np.ndarray) -> float:
    """(log10 a − log10 a*)² + (log10 b − log10 b*)², minimum 0 at X_STAR."""
    return float(sum((math.log10(v) - math.log10(s)) ** 2 for v, s in zip(x, X_STAR)))


#: the default method; no surrogate restarts, to keep the test fast
METHOD, OPTIONS, BUDGET = "tsbo-tsp", {"surrogate_options": {"n_restarts": 0}}, 30


def _plain(fun, space=SPACE):
    return minimize(fun, space, METHOD, budget=BUDGET, seed=0, **OPTIONS)


def _rounds(fun, storage=None, space=SPACE):
    def run(sp, study):
        return minimize(
            fun,
            sp,
            METHOD,
            budget=BUDGET,
            seed=0,
            storage=study,
            resume=study is not None,
            **OPTIONS,
        )

    return minimize_widening(run, space, storage=storage)


def test_widening_reaches_a_minimum_outside_the_initial_box():
    plain = _plain(bowl)
    space = Space.coerce(SPACE)
    assert [h.name for h in space.on_bounds(space.to_unit(plain.x))] == ["b"]
    # in the box no point does better than b on its bound 1e-2, 1.48 decades from b*
    assert plain.fun >= (math.log10(X_STAR[1]) + 2.0) ** 2 - 1e-9
    res = _rounds(bowl)
    assert res.fun < 1e-3 and res.fun < plain.fun
    np.testing.assert_allclose(np.log10(res.x), np.log10(X_STAR), atol=0.05)
    final = Space.from_dict(res.space)
    assert final.highs[1] == pytest.approx(1.0)  # widened once, by two decades
    assert final.on_bounds(final.to_unit(res.x)) == []
    assert res.n_evals == res.budget == 2 * BUDGET
    assert [r.info["widen_round"] for r in res.history] == [0] * BUDGET + [1] * BUDGET
    assert [r.number for r in res.history] == list(range(2 * BUDGET))
    # the first round is kept as it ran: its points, re-expressed in the final box
    assert [r.x for r in res.history[:BUDGET]] == [r.x for r in plain.history]
    np.testing.assert_allclose(
        [r.u for r in res.history], final.to_unit([r.x for r in res.history])
    )


def test_widening_resumes_after_an_interruption_without_repeating_anything(tmp_path):
    db = tmp_path / "study.db"
    calls = []

    def counted(x):
        calls.append(tuple(x))
        if len(calls) == BUDGET + 10:  # in the follow-up round
            raise KeyboardInterrupt
        return bowl(x)

    with pytest.raises(OptimizationInterrupted) as stop:
        _rounds(counted, storage=db)
    partial = stop.value.result
    assert partial.status == "interrupted" and partial.n_evals == BUDGET + 9
    assert db.exists() and round_storage(db, 1).exists()
    n_first = len(calls)
    resumed = _rounds(counted, storage=db)
    # only the rest is evaluated: the interrupted evaluation and those after it
    assert len(calls) - n_first == BUDGET - 9
    full = _rounds(bowl)
    assert resumed.fun == full.fun and [r.x for r in resumed.history] == [r.x for r in full.history]
    again = _rounds(counted, storage=db)  # everything is stored: nothing is evaluated
    assert len(calls) - n_first == BUDGET - 9 and again.fun == full.fun


def test_no_widening_when_the_best_point_is_inside():
    inside = {"a": (1e-6, 1e-2, "log10"), "b": (1e-3, 1.0, "log10")}
    res = _rounds(bowl, space=inside)
    assert res.n_evals == BUDGET and Space.from_dict(res.space) == Space.coerce(inside)
    assert res.fun == _plain(bowl, inside).fun
