"""Rough edges a newcomer met in the first hour: what ``tune`` says about a best point on a
bound (a wider box only where the cost still falls towards it), one spelling of every
method's label, and start points written for a cost of Q alone."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import run_cli
from kftune.cli.exit_codes import EXIT_BAD_INPUT, EXIT_OK
from kftune.cli.tune import UNCONVERGED, bound_lines
from kftune.experiment import FLAT_RISE, LABELS, complete_points, edge_probes
from kftune.optim import COMPARE_METHODS
from kftune.space import Param, Space
from kftune.tuning.parameterization import NoiseParameterization

ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------------ bound hints


class AnalyticProblem:
    """What :func:`edge_probes` and :func:`bound_lines` read of a TuningProblem, with a
    cost known in closed form: J = 1 − slope·log10 q − drop·max(0, log10 q) + curve·(10 −
    m), so that one decade below q's upper bound 1 the cost is ``slope`` higher, two
    decades above it 2·(slope + drop) lower, and a tenth of m's box [0, 10] below its upper
    bound ``curve`` higher; ``bowl`` adds bowl·(log10 q)², a minimum near the bound."""

    def __init__(
        self,
        slope: float,
        curve: float = 0.0,
        kind: str = "nrmse",
        drop: float = 0.0,
        bowl: float = 0.0,
    ) -> None:
        self.space = Space((Param("q_a", 1e-10, 1.0, scale="log10"), Param("m", 0.0, 10.0)))
        self.parameterization = SimpleNamespace(model_names=("m",))
        self.cost_spec = SimpleNamespace(kind=kind)
        self.cov_scale = 7.0  # a calibration: the probes must run at 1 and restore it
        self.slope, self.curve, self.drop, self.bowl = slope, curve, drop, bowl
        self.seen_scales: list[float] = []

    def evaluate_batch(self, points: np.ndarray) -> list[SimpleNamespace]:
        self.seen_scales.append(self.cov_scale)
        return [
            SimpleNamespace(
                cost=1.0
                - self.slope * math.log10(q)
                - self.drop * max(0.0, math.log10(q))
                + self.bowl * math.log10(q) ** 2
                + self.curve * (10.0 - m)
            )
            for q, m in points
        ]


def _hits(problem: AnalyticProblem, x: list[float]) -> list[dict]:
    space = problem.space
    return [h.to_dict() for h in space.on_bounds(space.to_unit(np.array(x)))]


def _doc(problem: AnalyticProblem, hits: list[dict], method: str = "trbo") -> dict:
    return {
        "search_space": problem.space.to_dict(),
        "on_bounds": hits,
        "cost_spec": {"kind": problem.cost_spec.kind},
        "method": method,
    }


def test_a_flat_edge_is_said_to_be_flat_with_the_measured_gain_and_no_widening():
    problem = AnalyticProblem(slope=2e-4)  # 0.02 % over the last decade: a plateau
    (hit,) = edge_probes(problem, [1.0, 5.0], _hits(problem, [1.0, 5.0]))
    edge = hit["edge"]
    assert edge["value"] == pytest.approx(0.1, rel=1e-9)  # one decade in
    assert edge["rise"] == pytest.approx(2e-4, rel=1e-6) and edge["flat"]
    beyond = edge["beyond"]  # where --widen-bounds would search: two decades out
    assert beyond["value"] == pytest.approx(100.0) and beyond["rise"] == pytest.approx(-4e-4)
    assert edge["threshold"] == pytest.approx(FLAT_RISE * edge["best_cost"])
    assert problem.seen_scales == [1.0] and problem.cov_scale == 7.0
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "q_a = 1 lies within 1 % of its upper bound 1" in line
    assert "widening the box (--widen-bounds) is unlikely to help (no worthwhile drop" in line
    assert "one decade in, at q_a = 0.1, the cost is 0.02 % higher" in line
    assert "2 decades out, at q_a = 100, 0.04 % lower" in line
    assert "widen the box with" not in line


def test_a_plateau_that_drops_beyond_the_bound_is_no_flat_edge():
    """Flat over the last decade, 2 % lower two decades out (msp on revs-250lm had this
    shape along q_vx): the step out sees it, and the hint suggests widening."""
    problem = AnalyticProblem(slope=1e-5, drop=0.01)
    (hit,) = edge_probes(problem, [1.0, 5.0], _hits(problem, [1.0, 5.0]))
    assert hit["edge"]["rise"] < hit["edge"]["threshold"] and not hit["edge"]["flat"]
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "2 decades out, at q_a = 100, 2 % lower" in line
    assert "widen the box with --widen-bounds" in line and "will not help" not in line


def test_a_cost_no_lower_beyond_the_bound_is_a_flat_edge_whatever_the_last_step():
    """0.96 % higher a decade in, 1.6 % higher two decades out (revs-250lm's r_vx_scale at
    100 had this shape; widening it found nothing, and a newcomer's widened run of this
    shape fitted the training set and predicted the test set worse): the hint gives both
    and says a wider box is unlikely to help; and 260 % higher a decade in is written as a
    whole number, not 2.6e+02."""
    a, b = 0.0176 / 3.0, 0.008 - 2.0 * 0.0176 / 3.0  # J = 1 + a·t² + b·t, t = log10 q
    problem = AnalyticProblem(slope=-b, bowl=a)
    (hit,) = edge_probes(problem, [1.0, 5.0], _hits(problem, [1.0, 5.0]))
    edge = hit["edge"]
    assert edge["rise"] == pytest.approx(0.0096) and edge["beyond"]["rise"] == pytest.approx(0.016)
    assert edge["flat"]
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "0.96 % higher" in line and "2 decades out, at q_a = 100, 1.6 % higher" in line
    assert "is unlikely to help (no worthwhile drop beyond it)" in line
    assert "--widen-bounds)" in line and "widen the box with" not in line
    steep = AnalyticProblem(slope=2.6)
    (hit,) = edge_probes(steep, [1.0, 5.0], _hits(steep, [1.0, 5.0]))
    (line,) = bound_lines(_doc(steep, [hit]), steep, widened=False)
    assert "the cost is 260 % higher" in line


def test_a_model_parameter_on_a_flat_edge_is_probed_a_tenth_of_its_box_in():
    problem = AnalyticProblem(slope=0.05, curve=1e-5)
    hits = _hits(problem, [1e-5, 10.0])  # q_a inside, m on its upper bound 10
    (hit,) = edge_probes(problem, [1e-5, 10.0], hits)
    assert hit["parameter"] == "m" and hit["edge"]["step"] == "a tenth of its box"
    assert hit["edge"]["beyond"] is None  # a model parameter's box is never widened
    assert hit["edge"]["value"] == pytest.approx(9.0)
    assert hit["edge"]["rise"] == pytest.approx(1e-5, rel=1e-6) and hit["edge"]["flat"]
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "m = 10" in line and "a wider box is unlikely to help" in line


def test_a_cost_that_rises_towards_the_bound_is_not_flat_whatever_the_step():
    problem = AnalyticProblem(slope=-0.05)  # the cost is lower one decade in
    (hit,) = edge_probes(problem, [1.0, 5.0], _hits(problem, [1.0, 5.0]))
    assert hit["edge"]["flat"]
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "one decade in, at q_a = 0.1, the cost is 5 % lower" in line
    assert "2 decades out, at q_a = 100, 10 % higher" in line and "unlikely to help" in line
    # the step in is lower than the tuned point: the search had not converged there
    assert line.endswith(UNCONVERGED)


def test_a_log_cost_is_flat_by_an_absolute_rise():
    """msp is Σ log MSE: its value shifts with the units, so its rise is judged absolutely
    (a rise of 1e-3 is a 0.1 % larger product of the MSEs), not as a share of |J*|."""
    problem = AnalyticProblem(slope=3e-4, kind="msp")
    problem_big = AnalyticProblem(slope=5e-3, kind="msp")
    for p, flat in ((problem, True), (problem_big, False)):
        (hit,) = edge_probes(p, [1.0, 5.0], _hits(p, [1.0, 5.0]))
        assert hit["edge"]["threshold"] == FLAT_RISE and hit["edge"]["flat"] is flat
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert f"{100 * math.expm1(5e-3):.2g} % higher" in line


def test_a_widening_whose_filter_diverges_is_said_not_to_help():
    problem = AnalyticProblem(slope=0.0)
    problem.evaluate_batch = lambda pts: (
        [SimpleNamespace(cost=1.0)] + [RuntimeError("diverged") for _ in pts[1:]]
    )
    (hit,) = edge_probes(problem, [1.0, 5.0], _hits(problem, [1.0, 5.0]))
    assert hit["edge"]["cost"] is None and hit["edge"]["flat"]
    assert hit["edge"]["beyond"]["cost"] is None
    (line,) = bound_lines(_doc(problem, [hit]), problem, widened=False)
    assert "the filter diverged" in line


def _tune(*args: str) -> tuple[int, str, str, dict | None]:
    out = Path(args[args.index("-o") + 1])
    res = run_cli("tune", *args)
    doc = json.loads(out.read_text()) if out.exists() else None
    return res.returncode, res.stdout, res.stderr, doc


def _manual(small: Path, tmp_path: Path, q_r: float, box_top: float) -> tuple[str, dict]:
    """``tune -m manual`` of the point (1e-6, 1e-4, q_r) with R factors 1 in a q_r box
    [1e-12, box_top]: its standard output and tuned file."""
    cfg = tmp_path / f"{q_r:g}.toml"
    cfg.write_text(
        f"[parameters]\nq_bounds = {{ q_r = [1e-12, {box_top!r}] }}\n"
        f"[options.manual]\npoints = [[1e-6, 1e-4, {q_r!r}, 1, 1, 1]]\n"
    )
    code, out, err, doc = _tune(str(small), "-m", "manual", "--config", str(cfg), "-o",
                                str(tmp_path / f"{q_r:g}.json"))  # fmt: skip
    assert code == EXIT_OK, err
    return out, doc


def test_tune_measures_the_edge_the_hint_reports(small, tmp_path):
    """A manual point on the upper bound of q_r's box: tune evaluates the cost one decade
    in and two decades out, records and prints them; the recorded costs there are what a
    run that evaluates that very point finds (an independent evaluation of it)."""
    out, doc = _manual(small, tmp_path, 1e-9, 1e-9)
    (hit,) = doc["on_bounds"]
    edge = hit["edge"]
    assert hit["parameter"] == "q_r" and edge["value"] == pytest.approx(1e-10, rel=1e-9)
    assert edge["best_cost"] == pytest.approx(doc["cost"], rel=1e-9)
    (line,) = [x for x in out.splitlines() if x.startswith("best point on a bound")]
    assert "q_r = 1e-09" in line and "upper bound 1e-09" in line and "one decade in" in line
    assert ("unlikely to help" in line) is edge["flat"]
    _, again = _manual(small, tmp_path, 1e-10, 1e-9)
    assert again["cost"] == pytest.approx(edge["cost"], rel=1e-9)
    assert edge["rise"] == pytest.approx(again["cost"] - doc["cost"], rel=1e-6, abs=1e-12)
    # two decades out, where --widen-bounds would search: the same point in a box with room
    assert edge["beyond"]["value"] == pytest.approx(1e-7, rel=1e-9)
    _, out_there = _manual(small, tmp_path, 1e-7, 1e-7)
    assert out_there["cost"] == pytest.approx(edge["beyond"]["cost"], rel=1e-9)


# ------------------------------------------------------------------ method labels


def test_every_method_has_one_label_and_the_readme_table_uses_it():
    readme = (ROOT / "README.md").read_text()
    assert not re.search(r"TSBO - ", readme) and not any(" - " in v for v in LABELS.values())
    # the table of make run's compare: its first column, every method compare runs
    rows = re.findall(r"^\| ([^|]+?) \| \*{0,2}[0-9.]+", readme, flags=re.M)
    table = rows[: len(COMPARE_METHODS)]
    assert table == [LABELS[m] for m in COMPARE_METHODS]


def test_compare_report_uses_the_labels_and_says_what_one_step_in_costs(small, tmp_path):
    """The report's tables name methods by their labels; a best point on a bound (here the
    manual point, put on the top of q_r's box) is listed with the cost one decade in, as
    results.json records it."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "[parameters]\nq_bounds = { q_r = [1e-12, 1e-9] }\n"
        "[options.manual]\npoints = [[1e-6, 1e-4, 1e-9]]\n"
    )
    out = tmp_path / "rep"
    res = run_cli("compare", str(small), "-o", str(out), "-q", "--config", str(cfg),
                  "--methods", "manual", "tsbo-gp", "--budget", "tsbo-gp=4")  # fmt: skip
    assert res.returncode == EXIT_OK, res.stderr
    report = (out / "report.md").read_text()
    assert f"| {LABELS['tsbo-gp']} |" in report and "TSBO - GP" not in report
    manual = json.loads((out / "results.json").read_text())["methods"][0]
    (hit,) = [h for h in manual["extra"]["on_bounds"] if h["parameter"] == "q_r"]
    edge = hit["edge"]
    assert edge["value"] == pytest.approx(1e-10, rel=1e-9) and edge["cost"] is not None
    assert edge["best_cost"] == pytest.approx(manual["best_cost"], rel=1e-9)
    line = next(x for x in report.splitlines() if x.startswith("- Manual: q_r = 1e-09"))
    assert "on its upper bound 1e-09; one decade in, at q_r = 1e-10, the cost is" in line
    assert "2 decades out, at q_r = 1e-07," in line
    assert ("a wider box is unlikely to help" in line) is edge["flat"]


# ------------------------------------------------------------------ start points


PAR = NoiseParameterization(tune_r="diag", measurements=("vx", "ay", "r"))


def test_a_q_only_point_takes_the_recorded_r_and_says_so():
    pts, note = complete_points(PAR, [[1e-6, 1e-4, 1e-6]], "manual", "points")
    assert pts.shape == (1, 6) and pts[0, 3:].tolist() == [1.0, 1.0, 1.0]
    assert pts[0, :3].tolist() == [1e-6, 1e-4, 1e-6]
    assert "r_vx_scale = 1" in note and "recorded R" in note
    # by name, one point alone, R given: nothing to say
    pts, note = complete_points(
        PAR, {"q_vx": 1e-6, "q_vy": 1e-4, "q_r": 1e-6, "r_ay_scale": 2.0}, "trbo", "x0"
    )
    assert pts[0].tolist() == [1e-6, 1e-4, 1e-6, 1.0, 2.0, 1.0] and "r_vx_scale" in note
    full, note = complete_points(PAR, [1e-6, 1e-4, 1e-6, 3.0, 2.0, 1.0], "trbo", "x0")
    assert full.shape == (1, 6) and note is None


@pytest.mark.parametrize(
    ("points", "said"),
    [
        ("[[1e-6, 1e-4]]", "point 1 has 2 values, but this run tunes 6"),
        ("[{q_vx = 1e-6, q_vy = 1e-4}]", "point 1 gives no q_r"),
        ("[{q_vx = 1e-6, q_vy = 1e-4, q_r = 1e-6, q_z = 1}]", "names ['q_z'], not tuned"),
        ("[[1e-6, 1e-4, 'a']]", "q_r must be numbers"),
        ("3", "expected a list of points, got int"),
    ],
)
def test_a_point_that_does_not_fit_is_refused_naming_the_ways_out(small, tmp_path, points, said):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[options.manual]\npoints = {points}\n")
    code, _, err, doc = _tune(str(small), "-m", "manual", "--config", str(cfg), "-o",
                              str(tmp_path / "t.json"))  # fmt: skip
    assert code == EXIT_BAD_INPUT and doc is None
    assert "[options.manual] points" in err and said in err and "Traceback" not in err
    if "gives no" in said or "values" in said:
        assert "q_vx, q_vy, q_r, r_vx_scale, r_ay_scale, r_r_scale" in err
        assert "--cost nrmse" in err


def test_manual_with_a_q_only_point_runs_the_recorded_r(small, tmp_path):
    """The older default's point (Q alone) under tune's default cost: it runs with R factors
    1, says so, and costs what the same point with R factors 1 written out costs."""
    cfg = tmp_path / "q.toml"
    cfg.write_text("[options.manual]\npoints = [[1e-6, 1e-4, 1e-6]]\n")
    code, _, err, doc = _tune(str(small), "-m", "manual", "--config", str(cfg), "-o",
                              str(tmp_path / "q.json"))  # fmt: skip
    assert code == EXIT_OK, err
    assert "leave out r_vx_scale, r_ay_scale, r_r_scale" in err and "recorded R" in err
    assert [doc["params"][k] for k in ("r_vx_scale", "r_ay_scale", "r_r_scale")] == [1, 1, 1]
    full = tmp_path / "full.toml"
    full.write_text("[options.manual]\npoints = [[1e-6, 1e-4, 1e-6, 1.0, 1.0, 1.0]]\n")
    code, _, err, ref = _tune(str(small), "-m", "manual", "--config", str(full), "-o",
                              str(tmp_path / "full.json"))  # fmt: skip
    assert code == EXIT_OK and "leave out" not in err
    assert doc["cost"] == pytest.approx(ref["cost"], rel=1e-12)
