"""``kftune dataset generate|info|show`` through a subprocess, as a user runs them."""

from __future__ import annotations

import json

import pytest

from conftest import run_cli

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
