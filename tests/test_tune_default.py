"""``kftune tune``'s recommended setting: the NRMSE normalised over the dataset with R's
diagonal tuned where the user says nothing of the cost or R, the paper's cost (Eq. 15) with
Q alone as soon as a cost option is given, and ``compare`` / ``evaluate`` untouched (the
paper's reproduction)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import run_cli
from kftune.cli import build_parser
from kftune.cli._common import cost_spec, load_config, parameterization


def _resolved(argv: list[str], config: str = "", tmp_path: Path | None = None) -> tuple:
    """(cost kind, normalisation, R mode) that ``argv``'s command would tune with."""
    cfg = None
    if config:
        assert tmp_path is not None
        cfg = tmp_path / "c.toml"
        cfg.write_text(config)
        argv = [*argv, "--config", str(cfg)]
    args = build_parser().parse_args(argv)
    conf = load_config(cfg, args.command)
    spec = cost_spec(args, conf)
    par = parameterization(args, conf)
    return spec.kind, spec.normalise, par.tune_r


@pytest.mark.parametrize(
    ("argv", "config", "expected"),
    [
        (["tune"], "", ("nrmse", "dataset", "diag")),
        (["tune", "--tune-r-scale"], "", ("nrmse", "dataset", "scale")),
        (["tune"], "[parameters]\ntune_r = 'none'\n", ("nrmse", "dataset", "none")),
        (["tune"], "[parameters]\ntune_r_scale = false\n", ("nrmse", "dataset", "none")),
        # any cost setting: the user's cost, the NRMSE where no kind is given, Q alone
        (["tune", "--cost", "nrmse"], "", ("nrmse", "manoeuvre", "none")),
        (["tune", "--cost", "crps"], "", ("crps", "manoeuvre", "none")),
        (["tune", "--normalise", "dataset"], "", ("nrmse", "dataset", "none")),
        (["tune", "--weights", "beta=1"], "", ("nrmse", "manoeuvre", "none")),
        (["tune", "--estimate", "prior"], "", ("nrmse", "manoeuvre", "none")),
        (["tune"], "[cost]\nkind = 'nrmse'\n", ("nrmse", "manoeuvre", "none")),
        (["tune"], "[cost]\nnormalise = 'dataset'\n", ("nrmse", "dataset", "none")),
        # the paper's reproduction and the manual scoring keep the paper's cost
        (["compare"], "", ("nrmse", "manoeuvre", "none")),
        (["evaluate", "--manual"], "", ("nrmse", "manoeuvre", "none")),
    ],
)
def test_tune_defaults_to_the_recommended_setting_only_where_nothing_is_said(
    argv: list[str], config: str, expected: tuple, tmp_path: Path
) -> None:
    assert _resolved(argv, config, tmp_path) == expected


def test_tune_writes_the_recommended_setting_and_an_old_study_names_how_to_resume(
    small: Path, tmp_path: Path
) -> None:
    """The tuned file records the dataset normalisation and R's three factors (evaluate then
    scores what it says); a study made with the paper's cost is refused by the default run
    with the option that resumes it, and resumes with it."""
    out = tmp_path / "t.json"
    res = run_cli("tune", str(small), "-n", "3", "-q", "-o", str(out))
    assert res.returncode == 0, res.stderr
    doc = json.loads(out.read_text())
    assert doc["cost_spec"]["kind"] == "nrmse" and doc["cost_spec"]["normalise"] == "dataset"
    assert set(doc["params"]) == {"q_vx", "q_vy", "q_r", "r_vx_scale", "r_ay_scale", "r_r_scale"}
    ev = run_cli(
        "evaluate",
        str(small),
        "--params",
        str(out),
        "--split",
        "train",
        "--no-calibration",
        "--json",
    )
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["cost"] == pytest.approx(doc["cost"], rel=1e-9)

    db = tmp_path / "s.db"
    old = run_cli(
        "tune", str(small), "-n", "2", "-q", "--cost", "nrmse", "--storage", str(db),
        "-o", str(tmp_path / "old.json"),
    )  # fmt: skip
    assert old.returncode == 0, old.stderr
    refused = run_cli("tune", str(small), "-n", "3", "-q", "--storage", str(db), "--resume")
    assert refused.returncode == 3
    assert "cost nrmse;" in refused.stderr and "resumes with --cost nrmse" in refused.stderr
    again = run_cli(
        "tune",
        str(small),
        "-n",
        "3",
        "-q",
        "--cost",
        "nrmse",
        "--storage",
        str(db),
        "--resume",
        "-o",
        str(tmp_path / "again.json"),
    )
    assert again.returncode == 0, again.stderr
