"""A model's hooks are run once on the first sample before a filter relies on them
(:meth:`StateSpaceModel.probe`): a hook that fails, writes the wrong size or a non-finite
value is named before any budget is spent, instead of after every evaluation failed."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from kftune.data import default_dataset
from kftune.errors import ConfigError
from kftune.models import StateSpaceModel
from kftune.tuning.cost import CostSpec
from kftune.tuning.problem import TuningProblem


@njit
def f_cv(x, u, p, dt, out):
    out[0] = x[0] + dt * x[1]
    out[1] = x[1]


@njit
def h_cv(x, u, p, out):
    out[0] = x[0]


@njit
def f_raises(x, u, p, dt, out):
    raise ValueError("boom")


@njit
def f_nan(x, u, p, dt, out):
    out[0] = x[0]
    out[1] = np.nan


@njit
def h_beyond(x, u, p, out):  # out has one entry: out[1] is someone else's memory
    out[0] = x[0]
    out[1] = x[1]


@njit
def h_unwritten(x, u, p, out):
    pass


def prior(z0, r, p):
    return np.array([z0[0], 0.0]), np.diag([r[0], 4.0])


def prior_short(z0, r, p):
    return np.array([z0[0]]), np.eye(2)


def cv(name: str = "cv1d", **hooks) -> StateSpaceModel:
    spec = {"f": f_cv, "h": h_cv, "initial_state": prior, **hooks}
    return StateSpaceModel(
        name=name, state_names=("pos", "vel"), state_units=("m", "m/s"), input_names=(),
        input_units=(), measurement_names=("pos",), measurement_units=("m",), **spec,
    )  # fmt: skip


Z = np.array([[1.5], [1.6]])


def probe(model: StateSpaceModel) -> None:
    model.probe(None, Z, np.array([0.01]), np.empty(0), 0.1)


def test_a_sound_model_passes():
    probe(cv(outputs={"speed": lambda x: np.abs(x[:, 1])}))


@pytest.mark.parametrize(
    ("hooks", "said"),
    [
        ({"f": f_raises}, r"f\(x, u, p, dt, out\) failed on the first sample: ValueError: boom"),
        ({"f": f_nan}, r"f\(x, u, p, dt, out\) wrote a non-finite value to out\[1\] \(vel\)"),
        ({"h": h_beyond}, r"h\(x, u, p, out\) wrote beyond the end of out \(shape \(1,\)\)"),
        ({"h": h_unwritten}, r"h\(x, u, p, out\) left unwritten out\[0\] \(pos\)"),
        ({"initial_state": prior_short}, r"returned x0 of shape \(1,\); expected \(2,\)"),
        ({"outputs": {"speed": lambda x: np.hypot(x)}}, r"output 'speed'\(x\) failed"),
        ({"outputs": {"speed": lambda x: x[:, :2]}}, r"output 'speed'\(x\) returned shape"),
    ],
)
def test_a_broken_hook_is_named(hooks, said):
    with pytest.raises(ValueError, match=said):
        probe(cv(**hooks))


def test_a_hook_with_the_wrong_arguments_is_refused_when_the_model_is_made():
    @njit
    def f_no_dt(x, u, p, out):
        out[0] = x[0]

    with pytest.raises(ValueError, match=r"f must take 5 arguments f\(x, u, p, dt, out\), it"):
        cv(f=f_no_dt)


@njit
def f_vx(x, u, p, dt, out):
    raise ValueError("boom")


@njit
def h_vx(x, u, p, out):
    out[0] = x[0]


def test_the_tuning_problem_probes_before_the_first_evaluation():
    model = StateSpaceModel(
        name="vx-only", state_names=("vx",), state_units=("m/s",), input_names=(),
        input_units=(), measurement_names=("vx",), measurement_units=("m/s",), f=f_vx, h=h_vx,
        initial_state=lambda z0, r, p: (np.array([z0[0]]), np.diag(r)),
    )  # fmt: skip
    ds = default_dataset()
    with pytest.raises(ConfigError, match=r"^model vx-only, on manoeuvre '.*': f\(x, u, p"):
        TuningProblem(ds.train[:1], None, [0.01], model=model, cost=CostSpec(weights={"vx": 1}))


def test_an_undocumented_prior_rule_is_not_exported_as_none():
    """The export said "none: the caller gives x0 and P0" for a model whose prior rule has
    no docstring, though the filter ran it."""
    from kftune.tuning.deploy import _initial_rule

    assert prior.__doc__ is None
    text = _initial_rule(cv())
    assert "prior(z0, r, p)" in text and "none" not in text
    assert _initial_rule(cv(initial_state=None)) == "none: the caller gives x0 and P0"


def test_estimate_probes_the_model_too(monkeypatch):
    """``kftune estimate`` runs a tuned file's filter without a tuning problem: it probes
    the model as well."""
    from kftune.data.manoeuvre import Manoeuvre
    from kftune.filters import UKFSettings
    from kftune.models import registry
    from kftune.tuning.deploy import TunedFilter, estimate

    monkeypatch.setitem(registry._MODELS, "cv1d-raises", cv(f=f_raises, name="cv1d-raises"))
    t = np.arange(300) * 0.01
    m = Manoeuvre("track", "segment", "test", t, extra={"pos": np.sin(t)})
    tuned = TunedFilter(
        model="cv1d-raises", filter="ukf", q=np.full(2, 1e-3), r=np.array([0.01]),
        settings=UKFSettings(), dt=0.01, vehicle=None, dataset=None, burn_in=0.0,
        source="t.json", document={},
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r"^model cv1d-raises, on manoeuvre 'track': f\(x"):
        estimate(tuned, m, None)


def test_measurement_units_must_be_the_datas():
    """A model that says km for a channel the dataset holds in metres was tuned silently on
    numbers 1000 times off its own description."""
    from types import SimpleNamespace

    from kftune.tuning.runs import check_units

    data = SimpleNamespace(name="track", units={"pos": "m"})
    check_units(cv(), data)  # the same unit
    km = StateSpaceModel(
        name="cv-km", state_names=("pos", "vel"), state_units=("km", "km/s"), input_names=(),
        input_units=(), measurement_names=("pos",), measurement_units=("km",), f=f_cv, h=h_cv,
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r"measurement 'pos' is in 'km', but the dataset 'track'"):
        check_units(km, data)
    check_units(km, SimpleNamespace(name="other", units={}))  # a unit the data do not say


@njit
def f_hold(x, u, p, dt, out):
    out[0] = x[0]


@njit
def F_unwritten(x, u, p, dt, out):  # a Jacobian that forgets its only entry
    pass


def test_the_probe_runs_the_hooks_the_filter_calls():
    """The EKF calls the Jacobians, the UKF never: a broken F is named before an EKF runs
    and left alone before a UKF (probing it would compile it for nothing)."""
    model = StateSpaceModel(
        name="vx-bad-F", state_names=("vx",), state_units=("m/s",), input_names=(),
        input_units=(), measurement_names=("vx",), measurement_units=("m/s",), f=f_hold,
        h=h_vx, F=F_unwritten, initial_state=lambda z0, r, p: (np.array([z0[0]]), np.diag(r)),
    )  # fmt: skip
    z, r = np.array([[20.0], [20.1]]), np.array([0.01])
    with pytest.raises(ValueError, match=r"F\(x, u, p, dt, out\) left unwritten out\[0\]"):
        model.probe(None, z, r, np.empty(0), 0.1)
    model.probe(None, z, r, np.empty(0), 0.1, jacobians=False)
    m = default_dataset().train[0]
    spec = {"cost": CostSpec(kind="nis"), "model": model}
    with pytest.raises(ConfigError, match=r"F\(x, u, p, dt, out\)"):
        TuningProblem([m], None, r, filter="ekf", **spec)
    TuningProblem([m], None, r, filter="ukf", **spec)
