"""The settings records: one validator reads the constraints each record declares, and the
three kinds of settings file (dataset manifest, import mapping, run configuration) refuse a
bad value through their public entry points with a message that names the file, the key
and what was expected.

Each constraint kind (type, range, choices, an element's rule, required, unknown key) is
checked once per kind of file; the expected messages are written out here, not derived from
the declarations they test.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from kftune.cli import main
from kftune.cli._common import cost_spec, model_choice, pick
from kftune.data import import_recordings, load_dataset, save_dataset
from kftune.data.importer import open_dataset
from kftune.errors import ConfigError, DataError, UsageError
from kftune.settings import NUMBER, Layer, SettingError, each, merge, rule, setting, validate
from test_data_helpers import synthetic_channels, synthetic_dataset


# ----------------------------------------------------------------- the generic validator
@dataclass(frozen=True)
class Inner:
    """A nested table."""

    x: float = setting(1.0, kind=NUMBER, low=0, strict=True, high=1, high_strict=True)


@dataclass(frozen=True)
class Record:
    """A record with one key of each constraint kind."""

    n: int = setting(3, kind=int, low=1, high=10)
    mode: str = setting("a", kind=str, choices=("a", "b"))
    flag: bool = setting(False, kind=bool)
    sign: float = setting(1.0, kind=NUMBER, choices=(1, -1))
    scale: float = setting(1.0, kind=NUMBER, nonzero=True)
    name: str = setting(kind=str, required=True)
    inner: Inner = field(default_factory=Inner, metadata=rule(Inner))
    table: dict[str, int] = field(
        default_factory=dict, metadata=rule(dict, keys=("p", "q"), each=each(int, low=0))
    )
    items: list[Inner] = field(default_factory=list, metadata=rule(list, each=each(Inner)))


def test_a_valid_table_becomes_the_record_with_defaults_for_the_absent_keys():
    r = validate(Record, {"name": "x", "inner": {"x": 0.5}, "items": [{}, {"x": 0.25}]})
    assert r == Record(name="x", inner=Inner(0.5), items=[Inner(1.0), Inner(0.25)])
    assert r.n == 3 and r.table == {} and Record(name="y").table is not r.table


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"n": "3"}, "key 'n': expected an integer >= 1 and <= 10, got a string ('3')"),
        ({"n": True}, "key 'n': expected an integer >= 1 and <= 10, got a boolean (true)"),
        ({"n": 11}, "key 'n': expected an integer >= 1 and <= 10, got 11"),
        ({"n": 10.0}, "key 'n': expected an integer >= 1 and <= 10, got a float (10.0)"),
        ({"table": {"r": 1, "p": 0, "s": 2}}, "keys 'table.r', 'table.s': unknown; expected"),
        ({"mode": "c"}, "key 'mode': expected one of ['a', 'b'], got 'c'"),
        ({"flag": 1}, "key 'flag': expected true or false, got an integer (1)"),
        ({"sign": 2}, "key 'sign': expected one of [1, -1], got 2"),
        ({"scale": 0.0}, "key 'scale': expected a number other than 0, got 0.0"),
        ({"scale": float("nan")}, "key 'scale': expected a number other than 0, got nan"),
        ({"inner": {"x": 1.0}}, "key 'inner.x': expected a number > 0 and < 1, got 1.0"),
        ({"inner": 3}, "key 'inner': expected a table, got an integer (3)"),
        ({"table": {"p": -1}}, "key 'table.p': expected an integer >= 0, got -1"),
        ({"table": {"r": 1}}, "key 'table.r': unknown; expected some of ['p', 'q']"),
        ({"items": [{}, {"y": 1}]}, "key 'items[1].y': unknown; expected some of ['x']"),
        ({"extra": 1}, "key 'extra': unknown; expected some of ['n', 'mode', 'flag', 'sign',"),
    ],
)
def test_each_constraint_kind_is_refused_naming_the_key_and_what_was_expected(data, message):
    with pytest.raises(SettingError) as info:
        validate(Record, {"name": "x", **data})
    assert message in str(info.value)


def test_a_missing_required_key_and_a_long_value_are_named_shortly():
    with pytest.raises(SettingError, match=r"^key 'name' is missing$"):
        validate(Record, {})
    with pytest.raises(SettingError) as info:
        validate(Record, {"name": "x", "mode": "z" * 10_000})
    assert len(str(info.value)) < 200 and "(10,000 characters)" in str(info.value)


# ------------------------------------------------------------------- dataset manifest
@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    save_dataset(synthetic_dataset(), tmp_path, compress=False)
    return tmp_path


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [  # type, range, choices, an element's rule, required, unknown key
        ('name = "', "name = 5\n#", "field 'name': expected a string, got an integer (5)"),
        ("dt = 0.01", "dt = 2.0", "field 'dt': expected a number > 0 and <= 1 [s], got 2.0"),
        ('split = "test"', 'split = "dev"', "field 'manoeuvres[2].split': expected one of"),
        ('r = "rad/s"', "r = 3", "field 'units.r': expected a unit string, got an integer (3)"),
        ('format = "kftune-dataset"\n', "", "field 'format' is missing"),
        ("dt = 0.01", "dt = 0.01\nsample_rate = 100", "field 'sample_rate': unknown; expected"),
        (  # every unknown field is named, not the first alone
            "dt = 0.01",
            "dt = 0.01\nsample_rate = 100\nrate = 1",
            "fields 'sample_rate', 'rate': unknown; expected",
        ),
    ],
)
def test_a_manifest_constraint_violation_names_the_manifest_and_field(dataset, old, new, message):
    manifest = dataset / "manifest.toml"
    text = manifest.read_text()
    assert old in text
    manifest.write_text(text.replace(old, new, 1))
    for load in (load_dataset, open_dataset):
        with pytest.raises(DataError) as info:
            load(dataset)
        assert info.value.file == str(manifest) and message in str(info.value), info.value
    if "unknown" in message:
        assert "'dt', 'vehicle', 'units', 'meta', 'manoeuvres']" in str(info.value)


# ---------------------------------------------------------------------- import mapping
@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """A recording as a folder of one file per signal (SI units)."""
    folder = tmp_path / "rec"
    folder.mkdir()
    for name, values in synthetic_channels(n=600, seed=2).items():
        np.savetxt(folder / f"{name}.txt", values)
    return folder


CHANNELS = "[channels]\n" + "".join(f'{c} = "{c}"\n' for c in synthetic_channels(n=2))


@pytest.mark.parametrize(
    ("top", "channels", "message"),
    [  # type, range, a quantity's unit, choices, an element's rule, nested table, required
        ("seed = 1.5", "", "key 'seed': expected an integer >= 0, got a float (1.5)"),
        ("steering_ratio = 0", "", "key 'steering_ratio': expected a number > 0, got 0"),
        (
            'min_speed = "5 furlongs"',
            "",
            "key 'min_speed': expected a number or '<number> <unit>' whose value in m/s is >= 0, "
            "got '5 furl",
        ),
        (  # the range reads with the value, not after the unit alternative
            'sample_time = "2 s"',
            "",
            "key 'sample_time': expected a number or '<number> <unit>' whose value in s is "
            ">= 0.0001 and <= 1, got '2 s'",
        ),
        ("", "ay = { column = 'ay', sign = 2 }", "key 'channels.ay.sign': expected one of [1, -1]"),
        (
            "",
            "ay = { column = 'ay', scale = 0 }",
            "key 'channels.ay.scale': expected a number other",
        ),
        ("", "ay = 3", "key 'channels.ay': expected a column name or a table, got an integer (3)"),
        (
            "[split]\ntrain_every = 0",
            "",
            "key 'split.train_every': expected an integer >= 1, got 0",
        ),
        ("[split]\nper = 'run'", "", "key 'split.per': expected one of ['all', 'file'], got 'run'"),
        ("", "vx = { column = 'vx', nosie = 0.1 }", "key 'channels.vx.nosie': unknown; expected"),
        ("smaple_time = 0.01", "", "key 'smaple_time': unknown; expected some of ['name', 'd"),
    ],
)
def test_a_mapping_constraint_violation_names_the_mapping_and_key(
    tmp_path, recording, top, channels, message
):
    mapping = tmp_path / "map.toml"
    table = CHANNELS.replace('ay = "ay"\n', "") if channels.startswith("ay") else CHANNELS
    table = table.replace('vx = "vx"\n', "") if channels.startswith("vx") else table
    split = top.startswith("[")
    body = f"{'' if split else top}\n{table}{channels}\n{top if split else ''}\n"
    mapping.write_text('vehicle = "bmw-320i"\n' + body)
    with pytest.raises(DataError) as info:
        import_recordings([recording], mapping)
    assert info.value.file == str(mapping) and message in str(info.value), info.value


def test_a_mapping_without_channels_says_the_key_is_missing(tmp_path, recording):
    mapping = tmp_path / "map.toml"
    mapping.write_text('vehicle = "bmw-320i"\n')
    with pytest.raises(DataError, match=r"map\.toml: key 'channels' is missing$"):
        import_recordings([recording], mapping)


# ------------------------------------------------------------ run configuration, merge
def test_the_merge_takes_each_key_from_the_first_layer_that_gives_it():
    """Command line over configuration file over tuned file over defaults, key by key."""
    cli = Layer({"a": 1}, lambda k: f"--{k}", "command line")  # a key absent: not given
    file = Layer({"b": 2}, lambda k: f"file, key {k!r}", "file")
    tuned = Layer({"b": 30, "c": 3}, lambda k: "the tuned file", "tuned")
    default = Layer({"a": 40, "b": 40, "c": 40, "d": 4}, lambda k: f"the default {k}", "default")
    rule_ = each(int, low=0)
    chosen = merge(dict.fromkeys("abcd", rule_), [cli, file, tuned, default])
    assert {k: (v, layer.name) for k, (v, layer) in chosen.items()} == {
        "a": (1, "command line"),
        "b": (2, "file"),
        "c": (3, "tuned"),
        "d": (4, "default"),
    }
    assert "e" not in merge({"e": rule_}, [cli, default])


def test_a_null_in_a_layer_is_refused_naming_it_not_taken_for_absent():
    """A JSON ``null`` (None) is a value no setting takes: it must not fall back to the
    next layer (a tuned file's ``"filter": null`` would silently become the default)."""
    tuned = Layer({"filter": None}, lambda k: f"tuned.json, key {k!r}", "tuned")
    default = Layer({"filter": "ukf"}, lambda k: "the default", "default")
    with pytest.raises(SettingError) as info:
        merge({"filter": each(object)}, [tuned, default])
    assert str(info.value) == "tuned.json, key 'filter': expected a value, got null"


@pytest.mark.parametrize(
    ("layer", "message"),
    [
        (Layer({"n": -1}, lambda k: f"--{k}"), "--n: expected an integer >= 0, got -1"),
        (
            Layer({"n": "x"}, lambda k: f"configuration file cfg.toml, key {k!r}"),
            "configuration file cfg.toml, key 'n': expected an integer >= 0, got a string ('x')",
        ),
    ],
)
def test_a_bad_value_in_the_merge_names_its_source(layer, message):
    fallback = Layer({"n": 1}, lambda k: "the default")
    with pytest.raises(SettingError) as info:
        merge({"n": each(int, low=0)}, [layer, fallback])
    assert str(info.value) == message


def _args(**given):
    """The options of ``kftune evaluate`` that set the cost, as argparse gives them."""
    names = ("cost", "weights", "estimate", "normalise", "model", "filter", "workers")
    return argparse.Namespace(command="evaluate", **{**dict.fromkeys(names), **given})


@pytest.mark.parametrize(
    ("args", "section", "tuned", "estimate"),
    [
        ({"estimate": "prior"}, {"estimate": "posterior"}, {"estimate": "posterior"}, "prior"),
        ({}, {"estimate": "prior"}, {"estimate": "posterior"}, "prior"),
        ({}, {}, {"estimate": "prior"}, "prior"),
        ({}, {}, {}, "posterior"),  # CostSpec's default
    ],
)
def test_the_cost_comes_from_command_line_then_file_then_tuned_file_then_default(
    args, section, tuned, estimate
):
    config = {"cost": section, "_file": "cfg.toml"}
    assert cost_spec(_args(**args), config, tuned).estimate == estimate


def test_a_cost_setting_that_does_not_apply_names_where_it_was_given(tmp_path):
    with pytest.raises(UsageError, match=r"^--weights: the nis cost \(--cost nis\) weighs no"):
        cost_spec(_args(cost="nis", weights={"beta": 1.0}), {})
    config = {"cost": {"weights": {"beta": 1.0}}, "_file": "cfg.toml"}
    with pytest.raises(ConfigError) as info:
        cost_spec(_args(), config, {"kind": "nis", "weights": {}})
    assert not isinstance(info.value, UsageError)
    assert str(info.value).startswith(
        "configuration file cfg.toml, [cost] key 'weights': the nis cost (the cost the "
        "parameters were tuned with) weighs no channels"
    )
    assert pick(_args(workers=3), {"workers": 2}, "workers", 1) == 3
    assert pick(_args(), {"workers": 2}, "workers", 1) == 2
    assert pick(_args(), {}, "workers", 5) == 5
    assert pick(_args(), {}, "workers") == 1 and pick(_args(), {}, "dataset") is None  # DEFAULTS


@pytest.mark.parametrize(
    ("text", "message"),
    [  # type, range, choices, an element's rule, a table's keys, nested table, unknown key
        ('seed = "x"', "key 'seed': expected an integer >= 0, got a string ('x')"),
        ("workers = 0", "key 'workers': expected an integer >= 1 and <= "),
        ('filter = "pf"', "key 'filter': expected one of ['ukf', 'ekf'], got 'pf'"),
        ('methods = ["ga", "gd"]', "key 'methods[1]': expected one of ['trbo', "),
        ("budgets = { gd = 3 }", "[budgets] key 'gd': unknown; expected some of ['trbo', "),
        ("[cost]\nweights = { beta = -1.0 }", "[cost] key 'weights.beta': expected a number >= 0"),
        ("[ukf]\ngamma = 1.0", "[ukf] key 'gamma': unknown; expected some of ['alpha', 'beta',"),
        ("budjet = 40", "key 'budjet': unknown; expected some of ['dataset', 'method', 'm"),
        ("budjet = 40\nsede = 1", "key 'budjet' (and 'sede'): unknown; expected some of"),
        ("budget = 10.0", "key 'budget': expected an integer >= 1 and <= 100000, got a float"),
        ("budget = true", "key 'budget': expected an integer >= 1 and <= 100000, got a boolean"),
        ("batch = 100001", "key 'batch': expected an integer >= 1 and <= 100000, got 100001"),
        ("r0 = { ay = -1 }", "[r0] key 'ay': expected a number > 0, got -1"),
        ("[ukf]\nalpha = 0", "[ukf] key 'alpha': expected a number > 0, got 0"),
        ("[ukf]\nbeta = -1", "[ukf] key 'beta': expected a number >= 0, got -1"),
        ('[options.tsbo-gp]\nmode = "fast"', "[options.tsbo-gp] key 'mode': expected one of ["),
        ("[options.trbo]\nn_init = 0", "[options.trbo] key 'n_init': expected an integer >= 1"),
    ],
)
def test_a_configuration_constraint_violation_names_the_file_and_key(
    tmp_path, capsys, text, message
):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text + "\n")
    assert main(["evaluate", "--manual", "--config", str(cfg)]) == 3
    err = capsys.readouterr().err
    assert f"configuration file {cfg}, {message}" in err and "Traceback" not in err, err


def test_an_option_is_checked_by_the_rule_of_its_configuration_key(capsys):
    for argv, message in [
        (["tune", "--budget", "0"], "expected an integer >= 1 and <= 100000, got '0'"),
        (["evaluate", "--burn-in", "-1"], "expected a number >= 0 [s], got '-1'"),
    ]:
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("given", "config", "tuned", "expected"),
    [
        ({"model": "cv"}, {"model": "ct"}, {"model": "ca"}, ("cv", "ekf")),
        ({}, {"model": "ct"}, {"model": "ca"}, ("ct", "ekf")),
        ({}, {}, {"model": "ca"}, ("ca", "ekf")),
        ({}, {}, {}, ("single-track", "ekf")),
    ],
)
def test_the_model_comes_from_command_line_then_file_then_tuned_file_then_default(
    given, config, tuned, expected
):
    """The filter comes from the tuned file here, the model from the first that names one."""
    args = _args(**given)
    assert model_choice(args, config, {**tuned, "filter": "ekf"}) == expected


def test_a_model_that_does_not_load_names_where_it_was_chosen(capsys, tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('model = "unicycle"\n')
    assert main(["evaluate", "--manual", "--config", str(cfg)]) == 3
    assert f"configuration file {cfg}, key 'model': " in capsys.readouterr().err
    assert main(["evaluate", "--manual", "--config", str(cfg), "--model", "unicycle2"]) == 2
    assert "--model: " in capsys.readouterr().err


# ------------------------------------------------------- the model, the filter, the data
@pytest.fixture
def no_vehicle(tmp_path: Path) -> Path:
    """The synthetic dataset saved without its vehicle (as data of something else are)."""
    import dataclasses

    folder = tmp_path / "novehicle"
    save_dataset(dataclasses.replace(synthetic_dataset(), vehicle=None), folder, compress=False)
    return folder


@pytest.mark.parametrize(
    ("argv", "config"),
    [
        (["--filter", "ekf"], ""),  # the filter is fine: the data lack the vehicle
        ([], 'filter = "ekf"\n'),
        ([], ""),
    ],
)
def test_a_vehicle_model_on_data_without_a_vehicle_blames_the_dataset_not_a_setting(
    no_vehicle, tmp_path, capsys, argv, config
):
    cfg = tmp_path / "d.toml"
    cfg.write_text("seed = 1\n" + config)
    code = main(["tune", str(no_vehicle), "--config", str(cfg), "-n", "1", *argv])
    err = capsys.readouterr().err
    assert code == 3 and "Traceback" not in err, err
    assert "model 'single-track' needs the vehicle's parameters" in err
    assert "dataset 'synthetic': model 'single-track' needs" in err
    assert "--filter" not in err and "key 'filter'" not in err and "d.toml" not in err, err


def test_an_unknown_filter_or_model_is_still_blamed_on_where_it_was_given(tmp_path, capsys):
    cfg = tmp_path / "m.toml"
    cfg.write_text('model = "no-such-model"\n')
    assert main(["evaluate", "--manual", "--config", str(cfg)]) == 3
    err = capsys.readouterr().err
    assert f"configuration file {cfg}, key 'model': " in err and "no-such-model" in err, err
    with pytest.raises(SystemExit) as info:  # argparse refuses an unknown --filter itself
        main(["evaluate", "--manual", "--filter", "pf"])
    assert info.value.code == 2


def test_a_vehicle_that_lacks_the_models_parameters_is_refused_not_replaced_by_a_preset():
    """The model's parameters come from the dataset's vehicle; one it cannot read them from
    is an error naming the model, not a silent fall back to the BMW preset."""
    from kftune.errors import ModelChoiceError
    from kftune.tuning.runs import filter_spec

    class Partial:  # a vehicle record without the tyre stiffnesses
        m = 1500.0

    with pytest.raises(ModelChoiceError) as info:
        filter_spec("single-track", "ukf", Partial())
    text = str(info.value)
    assert info.value.key is None and isinstance(info.value, ConfigError)
    assert text.startswith("model 'single-track' cannot read its parameters from the dataset's")


# ------------------------------------------- settings merged from every source, and nulls
def test_compare_budgets_merge_method_by_method_and_a_bad_one_names_its_source():
    from kftune.cli._common import budgets

    config = {"budgets": {"ga": 5, "trbo": 9}, "_file": "c.toml"}
    assert budgets([("ga", 7)], config) == {"ga": 7, "trbo": 9}
    assert budgets(None, {}) == {}
    with pytest.raises(SettingError) as info:
        budgets(None, {"budgets": {"ga": 0}, "_file": "c.toml"})
    assert str(info.value) == (
        "configuration file c.toml, [budgets] key 'ga': expected an integer >= 1 and <= 100000, "
        "got 0"
    )


def test_a_tuned_files_burn_in_is_merged_below_the_configuration_and_checked():
    from kftune.cli._common import pick_tuned

    tuned = (Path("t.json"), {"burn_in": 2.0})
    assert pick_tuned(_args(burn_in=None), {}, "burn_in", tuned) == 2.0
    assert pick_tuned(_args(burn_in=None), {"burn_in": 1.0}, "burn_in", tuned) == 1.0
    assert pick_tuned(_args(burn_in=0.5), {"burn_in": 1.0}, "burn_in", tuned) == 0.5
    assert pick_tuned(_args(burn_in=None), {}, "burn_in", None) == 0.0  # the default
    for bad, got in [(None, "null"), (-1.0, "-1.0"), ("2 s", "a string ('2 s')")]:
        with pytest.raises(SettingError) as info:
            pick_tuned(_args(burn_in=None), {}, "burn_in", (Path("t.json"), {"burn_in": bad}))
        assert str(info.value) == (
            f"tuned file t.json, key 'burn_in': expected a number >= 0 [s], got {got}"
        )


def test_a_null_filter_in_a_tuned_file_is_refused_naming_the_file_not_the_default(tmp_path):
    """A JSON ``"filter": null`` used to read as "not given": the default UKF ran, unsaid."""
    from kftune.cli._common import filter_spec_of

    tuned = (tmp_path / "t.json", {"model": "ctrv", "filter": None})
    with pytest.raises(ConfigError) as info:
        filter_spec_of(_args(), {}, None, tuned)
    assert str(info.value) == (
        f"{tmp_path / 't.json'}: the filter it was tuned with: expected a value, got null"
    )
    fs = filter_spec_of(_args(), {}, None, (tmp_path / "t.json", {"model": "ctrv"}))
    assert fs.filter == "ukf"  # absent: the default


def test_compare_methods_and_r0_come_through_the_merge():
    config = {"methods": ["ga"], "r0": {"ay": 0.5}, "_file": "c.toml"}
    assert pick(_args(methods=None), config, "methods", None) == ["ga"]
    assert pick(_args(methods=["trbo"]), config, "methods", None) == ["trbo"]
    assert pick(_args(), config, "r0", {}) == {"ay": 0.5} and pick(_args(), {}, "r0", {}) == {}


def test_a_bad_tune_model_box_shows_an_example(tmp_path, capsys):
    cfg = tmp_path / "b.toml"
    cfg.write_text("[parameters]\ntune_model = { cf = [1] }\n")
    assert main(["evaluate", "--manual", "--config", str(cfg)]) == 3
    assert (
        f"configuration file {cfg}, [parameters] key 'tune_model.cf': expected [low, high] in "
        "the parameter's unit, e.g. C_af = [20000.0, 400000.0], got [1]"
    ) in capsys.readouterr().err


def test_a_null_in_a_tuned_files_cost_names_the_file_and_key():
    with pytest.raises(SettingError) as info:
        cost_spec(_args(), {}, {"kind": "nrmse", "estimate": None}, tuned_file="t.json")
    assert str(info.value) == (
        "the cost the parameters were tuned with (t.json, key 'cost_spec.estimate'): "
        "expected a value, got null"
    )
