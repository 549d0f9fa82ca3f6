"""The settings records: one validator reads the constraints each record declares, and the
three kinds of settings file (dataset manifest, import mapping, run configuration) refuse a
bad value through their public entry points with a message that names the file, the key
and what was expected.

Each constraint kind (type, range, choices, an element's rule, required, unknown key) is
checked once per kind of file; the expected messages are written out here, not derived from
the declarations they test.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from kftune.data import import_recordings, load_dataset, save_dataset
from kftune.data.importer import open_dataset
from kftune.errors import DataError
from kftune.settings import NUMBER, SettingError, each, rule, setting, validate
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
        ({"n": "3"}, "key 'n': expected an integer >= 1 and <= 10, got '3'"),
        ({"n": True}, "key 'n': expected an integer >= 1 and <= 10, got True"),
        ({"n": 11}, "key 'n': expected an integer >= 1 and <= 10, got 11"),
        ({"mode": "c"}, "key 'mode': expected one of ['a', 'b'], got 'c'"),
        ({"flag": 1}, "key 'flag': expected true or false, got 1"),
        ({"sign": 2}, "key 'sign': expected one of [1, -1], got 2"),
        ({"scale": 0.0}, "key 'scale': expected a number other than 0, got 0.0"),
        ({"scale": float("nan")}, "key 'scale': expected a number other than 0, got nan"),
        ({"inner": {"x": 1.0}}, "key 'inner.x': expected a number > 0 and < 1, got 1.0"),
        ({"inner": 3}, "key 'inner': expected a table, got 3"),
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
        ('name = "', "name = 5\n#", "field 'name': expected a string, got 5"),
        ("dt = 0.01", "dt = 2.0", "field 'dt': expected a number > 0 and <= 1 [s], got 2.0"),
        ('split = "test"', 'split = "dev"', "field 'manoeuvres[2].split': expected one of"),
        ('r = "rad/s"', "r = 3", "field 'units.r': expected a unit string, got 3"),
        ('format = "kftune-dataset"\n', "", "field 'format' is missing"),
        ("dt = 0.01", "dt = 0.01\nsample_rate = 100", "field 'sample_rate': unknown; expected"),
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
        ("seed = 1.5", "", "key 'seed': expected an integer >= 0, got 1.5"),
        ("steering_ratio = 0", "", "key 'steering_ratio': expected a number > 0, got 0"),
        (
            'min_speed = "5 furlongs"',
            "",
            "key 'min_speed': expected a number or '<number> <unit>' >= 0 [m/s], got '5 furl",
        ),
        ('sample_time = "2 s"', "", "key 'sample_time': expected a number or '<number> <un"),
        ("", "ay = { column = 'ay', sign = 2 }", "key 'channels.ay.sign': expected one of [1, -1]"),
        (
            "",
            "ay = { column = 'ay', scale = 0 }",
            "key 'channels.ay.scale': expected a number other",
        ),
        ("", "ay = 3", "key 'channels.ay': expected a column name or a table, got 3"),
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
