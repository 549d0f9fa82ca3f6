"""``kftune dataset generate|info|show`` through a subprocess, as a user runs them."""

from __future__ import annotations

import json

import pytest

from conftest import bundled_without, run_cli

kftune = run_cli


def test_info_json_summarises_the_bundled_dataset():
    res = kftune("dataset", "info", "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["name"] == "default" and len(info["manoeuvres"]) == 31
    train, test = info["splits"]["train"], info["splits"]["test"]
    assert (train["manoeuvres"], test["manoeuvres"]) == (8, 23)
    assert max(-test["ay_min"], test["ay_max"]) >= 8.0
    assert 0.0 < train["share_ay_ge_4"] < 1.0
    row = info["manoeuvres"][0]
    assert set(row) >= {
        "name",
        "kind",
        "split",
        "duration",
        "ay_min",
        "ay_max",
        "beta_min_deg",
        "beta_max_deg",
        "share_ay_ge_4",
    }
    assert len(info["r_default"]) == 3


def test_info_table():
    res = kftune("dataset", "info")
    assert res.returncode == 0, res.stderr
    assert "train-01-braking-in-turn" in res.stdout and "|ay| ≥ 4" in res.stdout
    assert "R (high-pass statistics" in res.stdout


def test_show_writes_a_png(tmp_path):
    out = tmp_path / "jturn.png"
    res = kftune("dataset", "show", "default", "-m", "train-04-j-turn", "-o", out)
    assert res.returncode == 0, res.stderr
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    # default file name in the working directory
    res = kftune("dataset", "show", cwd=tmp_path)
    assert res.returncode == 0 and (tmp_path / "train-01-braking-in-turn.png").is_file()


def test_bad_input_exit_codes(tmp_path):
    res = kftune("dataset", "show", "-m", "no-such-manoeuvre", "-o", tmp_path / "x.png")
    assert res.returncode == 3 and "no-such-manoeuvre" in res.stderr and "--manoeuvre" in res.stderr
    res = kftune("dataset", "info", tmp_path)
    assert res.returncode == 3 and str(tmp_path) in res.stderr
    res = kftune("dataset", "generate", tmp_path / "g", "--only", "nope", "--quiet")
    assert res.returncode == 2 and "unknown manoeuvre" in res.stderr


@pytest.mark.slow
def test_generate_is_bit_identical_for_a_seed(tmp_path):
    pytest.importorskip("vehiclemodels")
    runs = {}
    for label, seed in (("a", 5), ("b", 5), ("c", 6)):
        res = kftune(
            "dataset",
            "generate",
            tmp_path / label,
            "--seed",
            seed,
            "--quiet",
            "--only",
            "test-09-j-turn",
        )
        assert res.returncode == 0, res.stderr
        runs[label] = {p.name: p.read_bytes() for p in (tmp_path / label).iterdir()}
    assert runs["a"] == runs["b"]
    assert runs["a"]["test-09-j-turn.csv.gz"] != runs["c"]["test-09-j-turn.csv.gz"]
    res = kftune("dataset", "info", tmp_path / "a", "--json")
    assert json.loads(res.stdout)["manoeuvres"][0]["name"] == "test-09-j-turn"


def test_generate_refuses_a_folder_in_use_and_force_replaces_only_the_dataset(tmp_path):
    pytest.importorskip("vehiclemodels")
    out = tmp_path / "g"
    gen = ("dataset", "generate", out, "--quiet", "--only")
    assert kftune(*gen, "test-09-j-turn").returncode == 0
    (out / "notes.txt").write_text("mine")
    res = kftune(*gen, "test-05-j-turn")
    assert res.returncode == 3 and "not empty" in res.stderr and "--force" in res.stderr
    before = sorted(p.name for p in out.iterdir())
    res = kftune(*gen, "no-such-manoeuvre", "--force")  # fails: the old dataset stays
    assert res.returncode == 2 and sorted(p.name for p in out.iterdir()) == before
    res = kftune(*gen, "test-05-j-turn", "--force")
    assert res.returncode == 0, res.stderr
    # the old manoeuvre's file is gone, the new one is there, the user's file is untouched
    assert sorted(p.name for p in out.iterdir()) == [
        "manifest.toml",
        "notes.txt",
        "test-05-j-turn.csv.gz",
    ]
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "x.txt").write_text("x")
    res = kftune("dataset", "generate", plain, "--quiet", "--only", "test-05-j-turn", "--force")
    assert res.returncode == 3 and "only a kftune dataset" in res.stderr
    assert (plain / "x.txt").exists()


def test_info_without_a_reference_keeps_the_statistics_and_marks_beta(tmp_path):
    import numpy as np

    _, picked = bundled_without(tmp_path, {"beta_ref"}, 300)
    res = kftune("dataset", "info", tmp_path, "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    train = info["splits"]["train"]
    ay = np.concatenate([m.ay for m in picked[:2]])
    assert train["samples"] == ay.size == 600
    assert train["ay_min"] == pytest.approx(ay.min()) and train["ay_max"] == pytest.approx(ay.max())
    assert train["beta_min_deg"] is None and info["manoeuvres"][0]["beta_max_deg"] is None
    assert len(info["r_default"]) == 3
    res = kftune("dataset", "info", tmp_path)
    assert res.returncode == 0, res.stderr
    assert "|ay| ≥ 4" in res.stdout and "R (high-pass statistics" in res.stdout
    assert (
        "train:   2 manoeuvres,    600 samples" in res.stdout and "β – (no beta_ref)" in res.stdout
    )
    row = next(line for line in res.stdout.splitlines() if line.startswith(picked[0].name))
    assert row.split()[-3:-1] == ["–", "–"]


def test_show_labels_each_panel_with_its_unit(tmp_path):
    from kftune.cli.dataset import plot_manoeuvre
    from kftune.data import open_dataset

    bundled_without(tmp_path / "noref", {"beta_ref"}, 300)
    fig = plot_manoeuvre(open_dataset(tmp_path / "noref").manoeuvres[0])
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "δ road wheel [°]",
        "acceleration [m/s²]",
        "yaw rate [°/s]",
        "speed [m/s]",
    ]
    bundled_without(
        tmp_path / "other", {"ax", "beta_ref"}, 300
    )  # not the sideslip set: one panel a channel
    ds = open_dataset(tmp_path / "other")
    labels = [ax.get_ylabel() for ax in plot_manoeuvre(ds.manoeuvres[0], ds.units).axes]
    assert labels[:4] == ["delta [rad]", "ay [m/s^2]", "r [rad/s]", "vx [m/s]"]
    assert "ay_true [m/s^2]" in labels  # an extra channel: the unit its manifest declares
    out = tmp_path / "shown.png"
    res = kftune("dataset", "show", tmp_path / "other", "-o", out)
    assert res.returncode == 0, res.stderr
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_info_of_sideslip_data_without_a_vehicle(tmp_path):
    # sideslip channels need no vehicle (a recording for a model of one's own): info
    # reports the statistics and says there is none instead of failing on it
    from kftune.data import Dataset, default_dataset, save_dataset

    ds = default_dataset()
    save_dataset(Dataset("novehicle", None, ds.dt, [ds.train[0].slice(0, 300)]), tmp_path)
    res = kftune("dataset", "info", tmp_path, "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    assert info["vehicle"] is None and info["splits"]["train"]["samples"] == 300
    res = kftune("dataset", "info", tmp_path)
    assert res.returncode == 0, res.stderr
    assert "dataset 'novehicle': no vehicle," in res.stdout
