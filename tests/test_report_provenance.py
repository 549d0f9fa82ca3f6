"""Reproducible reports: results.json and report.md record the command line, every method
option, the package versions, the dataset's fingerprint and the machine; each method keeps
one colour, distinct from every other's, in every figure; MAE is explained."""

from __future__ import annotations

import colorsys
import contextlib
import csv
import io
import itertools
import json
import platform
import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_hex, to_rgb

from conftest import SMALL_TEST, SMALL_TRAIN, run_cli
from kftune.cli import build_parser, main
from kftune.data import default_dataset, load_dataset, save_dataset
from kftune.optim import METHODS
from kftune.report import ExperimentResults, MethodRun, plots
from kftune.report.tables import KPI_LABELS
from kftune.tuning.deploy import dataset_fingerprint


def _lab(colour: str) -> np.ndarray:
    """CIELAB (D65) of an sRGB colour."""
    c = np.array(to_rgb(colour))
    c = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = m @ c / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def test_every_method_has_its_own_colour():
    keys = [*METHODS, "reference", "estimate"]
    assert set(METHODS) <= set(plots.COLOURS)
    colours = [plots.COLOURS[k].lower() for k in keys]
    assert len(set(colours)) == len(colours)
    for a, b in itertools.combinations(keys, 2):
        delta = np.linalg.norm(_lab(plots.COLOURS[a]) - _lab(plots.COLOURS[b]))
        assert delta >= 20, f"{a} and {b} look alike (ΔE {delta:.1f})"
    # the pair that looked alike: TSBO-GP's blue and Optuna TPE's former cyan
    hue = [
        colorsys.rgb_to_hsv(*to_rgb(plots.COLOURS[k]))[0] * 360 for k in ("tsbo-gp", "optuna-tpe")
    ]
    assert min(abs(hue[0] - hue[1]), 360 - abs(hue[0] - hue[1])) > 60


@pytest.fixture
def every_method() -> ExperimentResults:
    t = np.linspace(0.0, 2.0, 50)
    runs = [
        MethodRun(
            key=key,
            label=key,
            params={"q_vy": 1e-4},
            best_cost=1.0 / (i + 1),
            n_evals=1 if key == "manual" else 5,
            wall_time_s=1.0,
            history_cost=[1.0] if key == "manual" else list(np.linspace(2, 1 / (i + 1), 5)),
            history_time_s=[1.0] if key == "manual" else [0.2, 0.4, 0.6, 0.8, 1.0],
            metrics={"test": {"m": {"rmse_beta": 1.0, "rmse_r": 1.0, "rmse_ay": 1.0 + i}}},
        )
        for i, key in enumerate(METHODS)
    ]
    trace = {"t": t, "beta_ref": np.sin(t), **{f"beta_{k}": np.sin(t) for k in METHODS}}
    return ExperimentResults(meta={}, methods=runs, traces={"m": trace})


def _line_colours(fig) -> dict[str, str]:
    return {
        line.get_label(): to_hex(line.get_color())
        for ax in fig.axes
        for line in ax.get_lines()
        if not line.get_label().startswith("_")
    }


def test_figures_draw_each_method_in_its_colour(every_method):
    for fig in (
        plots.convergence(every_method),
        plots.beta_trace(every_method, "m", tuple(METHODS)),
    ):
        drawn = _line_colours(fig)
        for key in METHODS:  # the manual line's label also gives its cost: "manual (J = …)"
            (colour,) = [c for label, c in drawn.items() if label.split(" (J = ")[0] == key]
            assert colour == plots.COLOURS[key], key
        plots.plt.close(fig)
    # Fig. 7's bars are channels, not methods: no method's colour on them
    fig = plots.improvement(every_method, "ga", "tsbo-tsp")
    bars = {to_hex(p.get_facecolor()) for p in fig.axes[0].patches}
    plots.plt.close(fig)
    assert bars and not bars & {c.lower() for c in plots.COLOURS.values()}


def test_mae_is_explained_in_tables_and_help():
    assert "max. abs. error" in KPI_LABELS["mae"] and "max. abs. error" in KPI_LABELS["mae_non"]
    helps = build_parser()._subparsers._group_actions[0].choices
    for command in ("evaluate", "compare", "estimate"):
        text = " ".join(helps[command].format_help().split())
        assert "maximum absolute error" in text, command
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    assert len(re.findall(r"maximum\*? absolute error", readme)) >= 2


@pytest.fixture(scope="module")
def compared(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small compare run (manual and TSBO-tSP in improved mode) on four manoeuvres."""
    root = tmp_path_factory.mktemp("compare")
    save_dataset(default_dataset().subset(SMALL_TRAIN + SMALL_TEST), root / "data")
    config = root / "run.toml"
    config.write_text('[options.tsbo-tsp]\nmode = "improved"\n')
    out = root / "report"
    args = ["compare", str(root / "data"), "--methods", "manual", "tsbo-tsp", "--budget",
            "tsbo-tsp=4", "--config", str(config), "-o", str(out), "-q"]  # fmt: skip
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(args) == 0
    (root / "stdout.txt").write_text(printed.getvalue())  # what compare printed
    return out


def test_results_json_records_how_it_was_made(compared):
    meta = json.loads((compared / "results.json").read_text())["meta"]
    assert meta["command"].startswith("kftune compare ")
    assert "--budget tsbo-tsp=4" in meta["command"] and "run.toml" in meta["command"]
    assert meta["method_options"]["tsbo-tsp"]["mode"] == "improved"
    assert meta["method_options"]["tsbo-tsp"]["max_fe"] == 15  # defaults too
    assert "points" in meta["method_options"]["manual"]
    packages = meta["packages"]
    for name in ("python", "kftune", "numpy", "scipy", "numba", "matplotlib"):
        assert isinstance(packages[name], str), name
    assert packages["numpy"] == np.__version__
    machine = meta["machine"]
    assert machine["cpu_count"] >= 1 and machine["machine"] == platform.machine()
    dataset = load_dataset(compared.parent / "data")
    assert meta["dataset_fingerprint"] == dataset_fingerprint(dataset)
    run = json.loads((compared / "results.json").read_text())["methods"][1]
    assert run["extra"]["options"]["mode"] == "improved"


@pytest.mark.slow
def test_report_md_shows_it_and_rebuilds_the_same(compared, tmp_path):
    md = (compared / "report.md").read_text()
    meta = json.loads((compared / "results.json").read_text())["meta"]
    assert f"- Command: `{meta['command']}`" in md
    assert meta["dataset_fingerprint"]["sha256"] in md
    assert f"numpy {np.__version__}" in md and "CPUs" in md
    assert 'mode = "improved"' in md.split("## Method options")[1]
    assert "MAE: the *maximum* absolute error" in md
    assert main(["report", str(compared), "-o", str(tmp_path / "again")]) == 0
    assert (tmp_path / "again" / "report.md").read_text() == md


def test_the_report_says_whether_each_methods_sigma_can_be_trusted(compared):
    """Per method, pooled over the test manoeuvres: β's coverage of ±1σ and ±1.96σ, the mean
    NEES and NIS with their bands and a verdict, in results.json, report.md and
    tables/consistency_test.csv; the reliability figure's points at 68.27 % and 95 % (counted
    apart from the table's) are the table's coverages, and rise with the nominal level."""
    doc = json.loads((compared / "results.json").read_text())
    with open(compared / "tables" / "consistency_test.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["Method"] for r in rows] == ["Manual", "TSBO-tSP"]
    for run, row in zip(doc["methods"], rows):
        assert set(run["consistency"]) == {"train", "test"}
        test = run["consistency"]["test"]
        beta, nees = test["channels"]["beta"], test["channels"]["beta"]["nees"]
        assert beta["n"] == doc["meta"]["dataset"]["samples_test"]  # no burn-in: every one
        assert 0 < beta["cov68"] <= beta["cov95"] <= 1
        assert float(row["±1σ coverage [%] (68.3)"]) == pytest.approx(100 * beta["cov68"])
        assert float(row["±1.96σ coverage [%] (95)"]) == pytest.approx(100 * beta["cov95"])
        assert float(row["Mean NEES (1)"]) == pytest.approx(nees["mean"])
        assert nees["band_eff"][0] < 1 < nees["band_eff"][1]
        assert test["nis"]["dof"] == 3 and float(row["Mean NIS (m = 3)"]) > 0
        if nees["inside"]:
            assert row["σ"] == "consistent"
        else:
            side = "small" if nees["mean"] > 1 else "large"
            assert row["σ"].startswith("σ is about ") and row["σ"].endswith(f"too {side}")
        levels, cov = test["reliability"]["levels"], test["reliability"]["coverage"]["beta"]
        assert levels == sorted(levels) and levels[0] > 0 and levels[-1] < 1
        assert cov == sorted(cov) and len(cov) == len(levels)
        assert cov[levels.index(0.6827)] == pytest.approx(beta["cov68"])
        assert cov[levels.index(0.95)] == pytest.approx(beta["cov95"])
    md = (compared / "report.md").read_text()
    assert "## Consistency of the tuned filters on the test set" in md
    assert "| Method | Channel | ±1σ coverage [%] (68.3) |" in md
    assert "![Reliability of the stated uncertainty](figures/reliability.png)" in md
    printed = (compared.parent / "stdout.txt").read_text()  # compare prints the table too
    assert "Consistency of the tuned filters on the test set" in printed
    assert printed.count("| beta |") == 2
    assert (compared / "figures" / "reliability.png").read_bytes()[:4] == b"\x89PNG"


def test_results_without_consistency_still_rebuild_their_report(compared, tmp_path):
    """A results.json written before consistency was measured (no "consistency" key): the
    report is rebuilt, says consistency is not recorded, and has every other table."""
    old = tmp_path / "old"
    old.mkdir()
    doc = json.loads((compared / "results.json").read_text())
    for run in doc["methods"]:
        del run["consistency"]
    (old / "results.json").write_text(json.dumps(doc))
    (old / "traces.npz").write_bytes((compared / "traces.npz").read_bytes())
    res = run_cli("report", old, "-o", tmp_path / "rep")
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Consistency of the tuned filters (whether their standard deviations can be " in md
    assert "not recorded in these results" in md and "reliability.png" not in md
    assert not (tmp_path / "rep" / "figures" / "reliability.png").exists()
    tables = sorted(p.name for p in (tmp_path / "rep" / "tables").iterdir())
    assert tables == sorted(
        p.name for p in (compared / "tables").iterdir() if p.name != "consistency_test.csv"
    )
    assert (tmp_path / "rep" / "tables" / "kpi_test.csv").read_text() == (
        compared / "tables" / "kpi_test.csv"
    ).read_text()


@pytest.mark.parametrize(
    "broken",
    [
        {"test": {"channels": {"beta": {"cov68": "most"}}}},
        {"test": {"channels": {}, "nis": {"mean": 3.0, "band": [2.9]}}},
        {"test": {"channels": {}, "reliability": {"levels": [0.5], "coverage": {"beta": []}}}},
        {"test": ["not", "an", "object"]},
    ],
)
def test_a_damaged_consistency_in_results_json_is_refused_by_name(compared, tmp_path, broken):
    """A hand-edited or damaged "consistency": exit 3 naming results.json and the method,
    no traceback, and no report written."""
    doc = json.loads((compared / "results.json").read_text())
    doc["methods"][1]["consistency"] = broken
    (tmp_path / "results.json").write_text(json.dumps(doc))
    res = run_cli("report", tmp_path, "-o", tmp_path / "rep")
    assert res.returncode == 3 and "Traceback" not in res.stderr
    assert "results.json" in res.stderr and "methods[1]" in res.stderr
    assert not (tmp_path / "rep").exists()
