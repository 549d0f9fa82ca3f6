"""Optimiser settings as records (TR-BO's, TSBO's, how ``minimize`` evaluates): the
records keep the defaults the keyword arguments had, options by name still reach them
through the registry, an unknown name is refused naming it and the names there are, and a
study's record of the options (what a resume compares) is what it was."""

from __future__ import annotations

import inspect
import json
from dataclasses import FrozenInstanceError, asdict, fields

import numpy as np
import pytest

from kftune.errors import ConfigError
from kftune.experiment import tune
from kftune.optim import (
    TSBO,
    Execution,
    TRBOSettings,
    TrustRegionBO,
    TSBOSettings,
    make_optimizer,
    minimize,
)
from kftune.optim.settings import option_names, settings_from
from kftune.settings import SettingError

#: The defaults of ``TrustRegionBO.__init__``'s keyword arguments before they became
#: :class:`TRBOSettings` (written down from that signature, not computed from the record).
OLD_TRBO_DEFAULTS = {
    "surrogate": "gp",
    "surrogate_options": None,
    "n_init": None,
    "init_design": "auto",
    "x0": None,
    "design_centre": "box",  # options added since: their defaults give the old design
    "design_params": None,
    "warp": "log-min",
    "warp_delta": 0.1,
    "length_init": 0.2,
    "length_min": 0.0078125,
    "length_max": 1.0,
    "success_tol": 2,
    "failure_tol": None,
    "global_every": 4,
    "escape": 2,
    "n_candidates": 500,
    "faces": True,
    "refit_every": 5,
    "full_fit_until": 20,
    "probe_after": 5,
    "probe_length_scale": 0.5,
    "restart": "alternate",
    "improvement_rtol": 0.001,
}
#: The same for ``TSBO.__init__``.
OLD_TSBO_DEFAULTS = {
    "surrogate": "tsp",
    "surrogate_options": None,
    "max_fe": 15,
    "max_sm": None,
    "max_af": None,
    "beta": 0.01,
    "alpha": 0.15,
    "tr_fe": 0.01,
    "mode": "faithful",
    "sm_freeze": "hyperparameters",
    "keep_stage1_data": None,
    "min_box_halfwidth": None,
    "stage2_reserve": None,
    "min_resolution": None,
    "tr_fe_units": None,
}
#: What studies stored as the options of these runs before the records (``options()`` of
#: ``make_optimizer(method, SPACE, **kw)``, printed by the code of that time). A resume
#: compares them, so they must not change.
SPACE = {"a": (0.0, 1.0), "b": (1e-6, 1.0, "log10")}
OLD_STUDY_OPTIONS = [
    (
        "trbo",
        {},
        '{"surrogate": "gp", "surrogate_options": {"length_scale_bounds": [0.05, 20.0]}, '
        '"n_init": 5, "init_design": "auto", "warp": "log-min", "warp_delta": 0.1, '
        '"length_init": 0.2, "length_min": 0.0078125, "length_max": 1.0, "success_tol": 2, '
        '"failure_tol": 3, "global_every": 4, "escape": 2, "probe_after": 5, '
        '"probe_length_scale": 0.5, "restart": "alternate", "n_candidates": 500, '
        '"faces": true, "refit_every": 5, "full_fit_until": 20}',
    ),
    (
        "tsbo-tsp",
        {},
        '{"surrogate": "tsp", "surrogate_options": {}, "max_fe": 15, "max_sm": 38, '
        '"max_af": 10, "beta": 0.01, "alpha": 0.15, "tr_fe": 0.01, "mode": "faithful", '
        '"sm_freeze": "hyperparameters", "keep_stage1_data": false, "min_box_halfwidth": 0.0, '
        '"stage2_reserve": 0.0, "min_resolution": 0.0, "tr_fe_units": "natural"}',
    ),
    (
        "tsbo-gp",
        {"mode": "improved", "max_sm": 7},
        '{"surrogate": "gp", "surrogate_options": {}, "max_fe": 15, "max_sm": 7, '
        '"max_af": "switch", "beta": 0.01, "alpha": 0.15, "tr_fe": 0.01, "mode": "improved", '
        '"sm_freeze": "hyperparameters", "keep_stage1_data": true, "min_box_halfwidth": 0.02, '
        '"stage2_reserve": 0.25, "min_resolution": 0.0, "tr_fe_units": "natural"}',
    ),
]


def _defaults(record: type) -> dict:
    return {f.name: getattr(record(), f.name) for f in fields(record)}


@pytest.mark.parametrize(
    ("record", "old"), [(TRBOSettings, OLD_TRBO_DEFAULTS), (TSBOSettings, OLD_TSBO_DEFAULTS)]
)
def test_the_records_defaults_are_the_old_keyword_defaults(record, old):
    assert _defaults(record) == old


def test_minimize_and_tune_keep_their_defaults_and_at_most_twelve_parameters():
    def defaults(fn):
        params = inspect.signature(fn).parameters
        return {k: p.default for k, p in params.items() if p.default is not inspect.Parameter.empty}

    # the evaluation settings moved into Execution, whose defaults are the old ones
    assert asdict(Execution()) == {"timeout": None, "engine": None, "batch": None}
    common = {"method": "trbo", "budget": None, "seed": 0, "storage": None, "resume": False}
    assert defaults(minimize) == {**common, "callback": None, "objective": None, "execution": None}
    assert defaults(tune) == {
        **common,
        "progress": None,
        "options": None,
        "widen_bounds": False,
        "execution": None,
        "dataset": None,
    }
    for fn in (minimize, tune, TrustRegionBO.__init__, TSBO.__init__):
        assert len(inspect.signature(fn).parameters) <= 12 + 1  # (+ self)


@pytest.mark.parametrize(("method", "kw", "stored"), OLD_STUDY_OPTIONS)
def test_studies_record_the_options_they_recorded_before(method, kw, stored):
    opt = make_optimizer(method, SPACE, **kw)
    assert json.loads(json.dumps(opt.options())) == json.loads(stored)
    assert list(opt.options()) == list(json.loads(stored))  # in the same order too


@pytest.mark.parametrize(("method", "record"), [("trbo", TRBOSettings), ("tsbo-tsp", TSBOSettings)])
def test_an_unknown_option_is_refused_naming_it_and_the_allowed_ones(method, record):
    with pytest.raises(ValueError) as err:
        make_optimizer(method, SPACE, n_inits=3)
    text = str(err.value)
    assert f"method {method!r} has no option(s) ['n_inits']; its options: " in text
    listed = text.split("its options:")[1]
    assert all(repr(name) in listed for name in option_names(record))
    # the same through minimize (**method_options) and settings_from itself
    with pytest.raises(ValueError, match=r"no option\(s\) \['n_inits'\]; its options: \["):
        minimize(lambda x: 0.0, SPACE, method, budget=1, n_inits=3)
    with pytest.raises(ValueError, match=r"'n_inits'.*'surrogate'"):
        settings_from(record, {"n_inits": 3}, method)


def test_an_unknown_tune_option_from_a_configuration_is_a_config_error_naming_it():
    class Problem:  # tune checks the options before it touches the problem's filter
        space = make_optimizer("random", SPACE).space

    with pytest.raises(
        ConfigError, match=r"trbo: method 'trbo' has no option\(s\) \['lenght_init'\]"
    ):
        tune(Problem(), "trbo", options={"lenght_init": 0.3})  # type: ignore[arg-type]


def test_options_by_name_and_the_record_give_the_same_run():
    def proposals(opt):
        out = []
        while not opt.done:
            t = opt.ask()
            out.append(t.u)
            opt.tell(t, float(np.sum((t.u - 0.3) ** 2)))
        return np.array(out)

    by_name = make_optimizer("trbo", SPACE, budget=12, seed=2, n_init=4, global_every=2)
    record = TrustRegionBO(SPACE, TRBOSettings(n_init=4, global_every=2), budget=12, seed=2)
    np.testing.assert_allclose(proposals(by_name), proposals(record), rtol=0, atol=1e-12)
    assert by_name.settings == record.settings and record.settings.n_init == 4
    assert record.settings.failure_tol == 3  # max(3, d) filled in for d = 2


def test_tsbo_settings_fill_the_modes_presets():
    s = TSBO(SPACE, TSBOSettings(surrogate="gp", mode="improved", max_af=4), budget=20).settings
    assert (s.max_af, s.keep_stage1_data, s.min_box_halfwidth, s.stage2_reserve) == (
        4,
        True,
        0.02,
        0.25,
    )
    assert s.max_sm == 18  # budget - 2


def test_records_are_frozen_and_checked_once():
    with pytest.raises(FrozenInstanceError):
        TRBOSettings().n_init = 3  # type: ignore[misc]
    # a SettingError (a KftuneError: the CLI words it with the file and table) naming the key
    with pytest.raises(SettingError, match=r"^key 'warp': expected one of \['none', "):
        TRBOSettings(warp="sqrt")
    with pytest.raises(SettingError, match=r"^key 'n_init': expected an integer >= 1, got 0$"):
        TRBOSettings(n_init=0)
    with pytest.raises(SettingError, match=r"^key 'alpha': expected a number > 0 and < 1, got"):
        TSBOSettings(alpha=1.0)
    with pytest.raises(SettingError, match=r"^key 'stage2_reserve': expected a number >= 0 and"):
        TSBOSettings(stage2_reserve=1.0)
    with pytest.raises(TypeError, match="settings must be a TRBOSettings"):
        TrustRegionBO(SPACE, TSBOSettings())  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"timeout": 0}, "timeout must be a number of seconds"),
        ({"timeout": "5"}, "timeout must be a number of seconds"),
        ({"timeout": 2e6}, "timeout must be a number of seconds"),
        ({"batch": 0}, r"^key 'batch': expected an integer >= 1 and <= 100000, got 0$"),
        ({"batch": True}, "key 'batch': expected an integer >= 1 and <= 100000, got a boolean"),
        # one rule with the configuration's batch (RunConfig): bounded by MAX_BUDGET too
        ({"batch": 100_001}, "key 'batch': expected an integer >= 1 and <= 100000, got 100001"),
        ({"timeout": 5.0, "batch": 2}, "cannot be combined with a batch or an engine"),
    ],
)
def test_execution_refuses_bad_settings(kw, match):
    with pytest.raises(ConfigError, match=match):
        Execution(**kw)


def test_execution_batch_size():
    class Four:
        workers = 4

    assert (Execution().q, Execution().batched) == (1, False)
    assert (Execution(batch=3).q, Execution(engine=Four()).q) == (3, 4)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["timeout", "engine", "batch"])
def test_minimize_points_a_former_keyword_to_execution(name):
    with pytest.raises(ValueError, match=rf"{name}= is a setting .*execution=Execution\({name}="):
        minimize(lambda x: 0.0, SPACE, "random", budget=1, **{name: 1})
