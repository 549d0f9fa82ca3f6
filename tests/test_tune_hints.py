"""What ``kftune tune`` suggests after a search: ``--normalise dataset`` only where it is
accepted and not already given, ``--widen-bounds`` only where the best point lies on a bound
that it would move (a log10 parameter's)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from kftune.cli.tune import bound_lines, held_out_line
from kftune.space import Param, Space

WORSE = {"n_manoeuvres": 3, "beta_rmse_deg": 0.5, "manual_beta_rmse_deg": 0.47}


@pytest.mark.parametrize(
    ("cost", "suggests_normalise", "suggests_nrmse"),
    [
        ({"kind": "nrmse", "normalise": "manoeuvre"}, True, False),
        ({"kind": "nrmse", "normalise": "dataset"}, False, False),  # given already
        ({"kind": "nis", "normalise": "manoeuvre"}, False, True),  # refused with nis
        ({"kind": "pem", "normalise": "manoeuvre"}, False, True),
    ],
)
def test_the_normalise_hint_only_where_it_is_accepted_and_new(
    cost, suggests_normalise, suggests_nrmse
):
    line = held_out_line(WORSE, cost)
    assert "the tuned filter is the worse one there" in line
    assert ("--normalise dataset" in line) is suggests_normalise
    assert ("try --cost nrmse" in line) is suggests_nrmse
    better = held_out_line({**WORSE, "beta_rmse_deg": 0.1}, cost)
    assert "--normalise" not in better and "--cost" not in better


def _doc(space: Space, x: list[float]) -> dict:
    u = space.to_unit(np.array(x))
    return {"search_space": space.to_dict(), "on_bounds": [h.to_dict() for h in space.on_bounds(u)]}


SPACE = Space((Param("q_vy", 1e-10, 1.0, scale="log10"), Param("ukf_alpha", 1e-3, 1.0)))
#: What bound_lines reads of a TuningProblem: its space, and which parameters are the model's.
PROBLEM = SimpleNamespace(space=SPACE, parameterization=SimpleNamespace(model_names=()))


def test_widening_is_suggested_only_for_a_log10_parameter_on_its_bound():
    problem = PROBLEM
    (line,) = bound_lines(_doc(SPACE, [1.05e-10, 0.5]), problem, widened=False)
    assert "q_vy" in line and "lower bound" in line and "--widen-bounds)" in line
    (line,) = bound_lines(_doc(SPACE, [1e-5, 0.999]), problem, widened=False)
    assert "ukf_alpha" in line and "widens log10 parameters only" in line
    assert "(widen the box with --widen-bounds)" not in line


def test_nothing_is_said_about_the_box_when_the_best_point_is_far_inside_it():
    problem = PROBLEM
    assert bound_lines(_doc(SPACE, [1e-5, 0.5]), problem, widened=False) == []
    # 2 % of the range in from a bound (log10: 0.2 decades) is not on it
    assert bound_lines(_doc(SPACE, [10**-9.8, 0.5]), problem, widened=False) == []
