"""After ``--widen-bounds``, the held-out evidence compares the widened box's filter with the
best of the box as given: a newcomer's widened run fitted the training manoeuvres better
(0.185 → 0.164) and the test manoeuvres 38 % worse, and nothing said so."""

from __future__ import annotations

import numpy as np
import pytest

from kftune.cli.tune import first_box_best, held_out, held_out_line
from kftune.data import default_dataset
from kftune.optim import minimize
from kftune.optim.widen import minimize_widening
from kftune.space import Space
from kftune.tuning.problem import TuningProblem


def _bowl(x: np.ndarray) -> float:
    """Lowest at 1e-14 and 1e-3: beyond the box's lower bound 1e-10 for the first."""
    return float((np.log10(x[0]) + 14.0) ** 2 + (np.log10(x[1]) + 3.0) ** 2)


def test_the_first_rounds_best_is_the_best_of_a_run_in_the_box_as_given():
    space = Space.coerce({"a": (1e-10, 1.0, "log10"), "b": (1e-10, 1.0, "log10")})

    def run(sp, storage):
        return minimize(_bowl, sp, "trbo", budget=30, seed=3)

    widened = minimize_widening(run, space)
    alone = minimize(_bowl, space, "trbo", budget=30, seed=3)
    assert widened.fun < alone.fun  # the wider box found a lower cost
    assert first_box_best(widened) == pytest.approx(tuple(alone.x), rel=1e-12)
    assert first_box_best(alone) is None  # nothing widened: nothing to compare


def test_the_held_out_line_warns_when_the_wider_box_predicts_worse():
    h = {
        "split": "test",
        "n_manoeuvres": 23,
        "n_left_out": 0,
        "beta_rmse_deg": 0.202,
        "manual_beta_rmse_deg": 0.471,
        "first_box_beta_rmse_deg": 0.146,
    }
    line = held_out_line(h)
    assert "best in the box as given (before --widen-bounds): β RMSE 0.146°" in line
    assert "38.4 % worse" in line and "without --widen-bounds" in line
    assert "warning" not in held_out_line({**h, "first_box_beta_rmse_deg": 0.25})


def test_held_out_scores_the_first_boxs_best_as_the_tuned_point():
    """The first box's β RMSE is the tuned filter's at that point (the same runs)."""
    ds = default_dataset()
    problem = TuningProblem(sorted(ds.train, key=lambda m: m.n)[:2], ds.vehicle, ds.r_default)
    a, b = np.array([1e-5, 1e-3, 1e-5]), np.array([3.5e-8, 6.8e-7, 0.13])
    both, _ = held_out(problem, a, ds, first_box=b)
    alone, _ = held_out(problem, b, ds)
    assert both is not None and alone is not None
    assert both["first_box_beta_rmse_deg"] == pytest.approx(alone["beta_rmse_deg"], rel=1e-12)
    assert both["beta_rmse_deg"] != pytest.approx(alone["beta_rmse_deg"], rel=1e-3)
