"""A two-stage joint tuning says when its budget ends inside TR-BO's initial designs: a
newcomer's -n 30 with two stiffnesses gave 8 evaluations of the noise alone (6 noise
parameters: a design of 13) and 22 joint ones, and the result was a design point, with
nothing said."""

from __future__ import annotations

import pytest

from kftune.data import default_dataset
from kftune.experiment import staging
from kftune.tuning.parameterization import NoiseParameterization
from kftune.tuning.problem import TuningProblem


@pytest.fixture(scope="module")
def joint() -> TuningProblem:
    ds = default_dataset()
    par = NoiseParameterization(
        tune_r="diag", model_bounds={"C_af": (2e4, 4e5), "C_ar": (2e4, 4e5)}
    )
    return TuningProblem(ds.train[:2], ds.vehicle, ds.r_default, parameterization=par)


def test_a_budget_inside_the_designs_is_said_with_the_smallest_that_searches(joint):
    stages = staging(joint, "trbo", 30)
    assert stages is not None
    assert (stages.noise_budget, stages.joint_budget) == (8, 22)
    # 2d + 1 over the 6 noise parameters; the joint design: 1 + 2 per model parameter
    assert (stages.noise_design, stages.joint_design) == (13, 5)
    text = stages.warning()
    assert text is not None and "8 evaluations" in text and "22" in text
    need = int(text.rsplit("-n ", 1)[1].split()[0])
    enough, short = staging(joint, "trbo", need), staging(joint, "trbo", need - 1)
    assert enough is not None and short is not None
    assert enough.warning() is None and short.warning() is not None
    assert enough.noise_budget > 13 and enough.joint_budget > 5  # each stage searches


def test_the_default_budget_and_a_given_design_size(joint):
    stages = staging(joint, "trbo", None)  # TR-BO's default, 100
    assert stages is not None and stages.warning() is None
    small = staging(joint, "trbo", 30, options={"n_init": 4})
    assert small is not None and small.warning() is None
    assert (small.noise_design, small.joint_design) == (4, 4)


@pytest.mark.parametrize(
    ("options", "joint_design"),
    [
        ({"design_centre": "box"}, 1 + 17),  # the seed, then the box's design over d = 8
        ({"design_params": ["C_af"]}, 1 + 3),  # the seed, then the box's centre and C_af's two
        ({"design_centre": "x0", "design_params": ["q_vx", "C_af"]}, 5),  # the seed is the centre
    ],
)
def test_a_users_design_options_are_counted_as_they_design(joint, options, joint_design):
    stages = staging(joint, "trbo", 100, options=options)
    assert stages is not None and stages.joint_design == joint_design
