"""What a second newcomer misread after following the README: the report's TR-BO figure
says it is compare's TR-BO (the paper's cost, Q alone, 40 evaluations), not the filter
``kftune tune`` deploys; ``study plot`` on the joint stage of a two-stage tuning says that
evaluation 0 is the first stage's best and names that stage's study; the parameter
figure's tick labels have one font size on log axes too; every figure over a manoeuvre
draws the recording's time and says so; an imported manoeuvre's kind is "recording" when
it was not cut (or what the mapping's ``kind`` says), and ``train_every`` makes the first
segment, ``-s01``, training; a sign error is not blamed on a computed channel's unit; unit
messages have the right article; a tune without any sideslip reference says what the
held-out check needs."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from kftune.cli.study import _figures
from kftune.data import Dataset, Manoeuvre
from kftune.data.importer import import_recordings
from kftune.data.validate import unit_factor
from kftune.errors import DataError, DataWarning
from kftune.report import ExperimentResults, MethodRun, compare_setting, plots, write_report
from test_data_helpers import synthetic_channels

# an uncut recording has one manoeuvre, which the default split cannot make test
pytestmark = pytest.mark.filterwarnings("ignore:.*makes none of the:kftune.errors.DataWarning")

PAPER_COST = "J = 5·E_beta + 1·E_r + 1·E_ay (paper Eq. 14–15, pooled NRMSE; r, ay, vx from h(x⁺))"
Q_BOX = "q_vx ∈ [1e-10, 1] (log10), q_vy ∈ [1e-10, 1] (log10), q_r ∈ [1e-10, 1] (log10)"


def _run(key: str, label: str, beta_rmse: float, n: int) -> MethodRun:
    rmse = {"rmse_beta": beta_rmse, "rmse_r": 0.1, "rmse_ay": 0.1}
    return MethodRun(
        key=key,
        label=label,
        params={"q_vy": 1e-4},
        best_cost=0.4,
        n_evals=n,
        wall_time_s=0.01 * n,
        history_cost=list(np.linspace(1.0, 0.4, n)),
        history_time_s=list(0.01 * np.arange(1, n + 1)),
        metrics={"test": {m: dict(rmse) for m in ("m1", "m2")}},
    )


def _results(**meta: Any) -> ExperimentResults:
    """compare's results of the manual filter and TR-BO on two test manoeuvres."""
    split = {"split": "test", "kind": "recording"}
    return ExperimentResults(
        meta={"manoeuvres": {"m1": split, "m2": split}, **meta},
        methods=[_run("manual", "Manual", 0.47, 1), _run("trbo", "TR-BO", 0.155, 40)],
    )


# ------------------------------------------------------------------ the report's TR-BO
def test_compare_setting_says_cost_space_and_budget():
    paper = _results(cost=PAPER_COST, parameters=Q_BOX, budgets={"manual": 1, "trbo": 40})
    assert compare_setting(paper, "trbo") == "the paper's cost, Q alone, 40 evaluations"
    joint = _results(
        cost="J = 5·E_beta (Eq. 14, RMSE over all manoeuvres / the largest |X|; …)",
        parameters=Q_BOX + ", r_vx_scale ∈ [0.01, 100] (log10), r_ay_scale ∈ [0.01, 100] "
        "(log10), C_af ∈ [2e+04, 4e+05] (log10)",
        budgets={"trbo": 12},
    )
    assert compare_setting(joint, "trbo") == (
        "the NRMSE cost normalised over the dataset, Q, R's diagonal, C_af tuned, 12 evaluations"
    )
    scale = _results(parameters=Q_BOX + ", r_scale ∈ [0.01, 100] (log10)")  # no budgets: runs'
    assert compare_setting(scale, "trbo") == "Q, a scale of R tuned, 40 evaluations"


def test_the_reports_trbo_figure_says_it_is_compares_setting(tmp_path, monkeypatch):
    headings: list[str] = []
    improvement = plots.improvement

    def spy(*args: Any, **kwargs: Any) -> Any:
        if args[1:] == ("manual", "trbo"):
            headings.append(kwargs["heading"])
        return improvement(*args, **kwargs)

    monkeypatch.setattr(plots, "improvement", spy)
    results = _results(cost=PAPER_COST, parameters=Q_BOX, budgets={"manual": 1, "trbo": 40})
    md = write_report(results, tmp_path).read_text()
    (heading,) = headings
    assert "kftune tune's default)" not in heading.splitlines()[0]
    assert heading.splitlines() == [
        "TR-BO as kftune compare ran it against the manual filter",
        "(the paper's cost, Q alone, 40 evaluations; not kftune tune's default)",
    ]
    assert "TR-BO ran as compare runs it (the paper's cost, Q alone, 40 evaluations)" in md
    assert "R's diagonal tuned with Q, 100 evaluations" in md
    plots.plt.close("all")


# ------------------------------------------------------------------ study plot
def _summary(first_stage: str | None) -> dict[str, Any]:
    """``study show --json``'s summary of a joint study: Q and a cornering stiffness."""
    params = [
        {"name": "q_r", "low": 1e-10, "high": 1.0, "scale": "log10"},
        {"name": "C_af", "low": 2e4, "high": 4e5, "scale": "log10"},
    ]
    costs = [0.2, 0.58, 0.57, 0.21, 0.19, 0.2, 0.185]
    trials, best = [], None
    for i, c in enumerate(costs):
        best = c if best is None else min(best, c)
        point = {"q_r": 10.0 ** -(i % 5), "C_af": 5e4 + 1e4 * i}
        trials.append({"number": i, "cost": c, "best_so_far": best, "params": point})
    return {
        "study": str(Path("somewhere", "s.db").absolute()),
        "method": "trbo",
        "seed": 0,
        "objective": "8 manoeuvres (a … b), car, cost nrmse (dataset-normalised)",
        "trials": trials,
        "best": {"number": 6, "cost": 0.185, "params": trials[6]["params"]},
        "parameters": params,
        "first_stage": first_stage,
    }


def test_study_plot_of_a_joint_stage_names_the_first_stage():
    figs = _figures(_summary(str(Path("somewhere", "s.noise-only.db").absolute())))
    title = figs["convergence.png"].axes[0].get_title()
    assert "evaluation 0 is the best point of" in title
    assert "noise-only stage" in title and "s.noise-only.db" in title
    assert "somewhere" not in title  # the file's name: it lies beside the study
    assert "s.noise-only.db" in figs["parameters.png"]._suptitle.get_text()
    alone = _figures(_summary(None))
    assert "noise-only" not in alone["convergence.png"].axes[0].get_title()
    assert "noise-only" not in alone["parameters.png"]._suptitle.get_text()
    plots.plt.close("all")


def test_the_parameter_figure_has_one_tick_font_size():
    """C_af's box spans under two decades, so its log axis labels minor ticks
    (2×10⁴, 3×10⁴, …): they were drawn larger than every other panel's labels."""
    fig = _figures(_summary(None))["parameters.png"]
    fig.canvas.draw()
    sizes = {
        tick.label1.get_fontsize()
        for ax in fig.axes
        for axis in (ax.xaxis, ax.yaxis)
        for tick in axis.get_major_ticks() + axis.get_minor_ticks()
        if tick.label1.get_visible() and tick.label1.get_text()
    }
    minor = [
        t
        for t in fig.axes[1].yaxis.get_minor_ticks()
        if t.label1.get_visible() and t.label1.get_text()
    ]
    assert minor, "C_af's axis labels no minor tick: the check would check nothing"
    assert len(sizes) == 1, sizes
    plots.plt.close("all")


# ------------------------------------------------------------------ time axes
def test_every_figure_over_a_manoeuvre_draws_the_recordings_time():
    """A recording trimmed of 2 s of standstill: dataset show, estimate and compare's β
    figure all start at t = 2 s and label the axis the same way."""
    from kftune.cli.dataset import plot_manoeuvre

    c = synthetic_channels(n=500, t0=2.0)
    m = Manoeuvre("run1", "recording", "test", c["t"], **{k: v for k, v in c.items() if k != "t"})
    shown = plot_manoeuvre(m)
    beta = np.asarray(c["beta_ref"])
    est = plots.estimate_trace(c["t"], beta, np.full(beta.size, 0.01), beta, "β")
    tr = {"t": c["t"], "beta_ref": beta, "beta_manual": beta + 0.01, "beta_trbo": beta}
    results = _results()
    results.traces["m1"] = tr
    compared = plots.beta_trace(results, "m1")
    for fig in (shown, est, compared):
        xlabels = [a.get_xlabel() for a in fig.axes if a.get_xlabel()]
        assert xlabels == [plots.TIME_LABEL], xlabels
        first = min(float(line.get_xdata()[0]) for a in fig.axes for line in a.get_lines()
                    if len(line.get_xdata()) > 10)  # fmt: skip
        assert first == pytest.approx(2.0)
    plots.plt.close("all")


# ------------------------------------------------------------------ import: kind, split
@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """A recording of 100 s as a folder of one file per signal, SI units."""
    c = synthetic_channels(n=10_000)
    folder = tmp_path / "run1"
    folder.mkdir()
    for name, values in c.items():
        np.savetxt(folder / f"{name}.txt", values)
    return folder


MAPPING = {"vehicle": "bmw-320i", "channels": {k: k for k in synthetic_channels(n=2)}}


def test_an_uncut_recording_is_of_kind_recording_a_cut_one_of_segment(recording):
    (whole,) = import_recordings([recording], MAPPING).manoeuvres
    assert (whole.name, whole.kind) == ("run1", "recording")
    cut = import_recordings([recording], MAPPING | {"segment_length": 30.0})
    # 100 s / 30 s rounds to 3 equal segments of about 33 s
    assert [(m.name, m.kind) for m in cut.manoeuvres] == [
        (f"run1-s0{i}", "segment") for i in (1, 2, 3)
    ]
    assert [m.duration for m in cut.manoeuvres] == pytest.approx([33.33] * 3, abs=0.02)


def test_the_mappings_kind_names_the_kind(recording):
    one = import_recordings([recording], MAPPING | {"kind": "track-lap"})
    assert one.manoeuvres[0].kind == "track-lap"
    by_name = MAPPING | {
        "segment_length": 20.0,
        "kind": {"run1-s0[12]": "skidpad", "run1-s02": "never: the first match wins"},
    }
    kinds = [m.kind for m in import_recordings([recording], by_name).manoeuvres]
    assert kinds == ["skidpad", "skidpad", "segment", "segment", "segment"]


def test_a_kind_glob_that_matches_nothing_warns_and_a_bad_kind_is_refused(recording):
    with pytest.warns(DataWarning, match=r"key 'kind.run9\*': pattern 'run9\*' matches none"):
        import_recordings([recording], MAPPING | {"kind": {"run9*": "slalom"}})
    for kind, key in ((3, "'kind'"), ({"run1": ""}, "'kind.run1'"), ("", "'kind'")):
        with pytest.raises(DataError, match=f"key {key}: expected"):
            import_recordings([recording], MAPPING | {"kind": kind})


def test_train_every_makes_the_first_segment_training(recording):
    """The rule counts from 0, names from 1: with k = 3, s01, s04, s07 and s10 train."""
    ds = import_recordings([recording], MAPPING | {"segment_length": 10.0})
    train = [m.name for m in ds.manoeuvres if m.split == "train"]
    assert train == ["run1-s01", "run1-s04", "run1-s07", "run1-s10"]


# ------------------------------------------------------------------ messages
WHEEL_MEAN = "(wheel_fl + wheel_fr + wheel_rl + wheel_rr) / 4"


def _logger(path: Path, ay_sign: float, vx_factor: float) -> Path:
    """A logger's CSV: four wheel speeds (m/s times ``vx_factor``), ay times ``ay_sign``,
    every column in SI units."""
    c = synthetic_channels(n=1500)
    cols = {"time": c["t"], **{w: c["vx"] * vx_factor for w in WHEEL_MEAN[1:-5].split(" + ")}}
    cols |= {"acc_y": ay_sign * c["ay"], "yaw_rate": c["r"], "ax": c["ax"]}
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",",
               header=",".join(cols))  # fmt: skip
    return path


def _error(csv: Path) -> str:
    channels = {"t": "time", "vx": {"expr": WHEEL_MEAN}, "ay": "acc_y", "r": "yaw_rate"}
    with pytest.raises(DataError) as info:
        import_recordings([csv], {"channels": channels | {"ax": "ax"}})
    return str(info.value)


def test_a_negative_ratio_blames_a_sign_not_a_computed_channels_unit(tmp_path):
    err = _error(_logger(tmp_path / "flipped.csv", ay_sign=-1.0, vx_factor=1.0))
    assert "ay/(vx·r) = -1" in err and "opposite sign conventions" in err
    assert 'ay = { column = "acc_y", sign = -1 }' in err
    assert "suspect" not in err and "is ay in g" not in err
    # a ratio off by a unit's factor (wheel speeds in km/h taken as m/s): vx is a suspect
    err = _error(_logger(tmp_path / "kmh.csv", ay_sign=1.0, vx_factor=3.6))
    assert "suspect the computed channel vx" in err and "is ay in g" in err
    assert "opposite sign conventions" not in err


def test_a_unit_of_another_dimension_is_named_with_its_article():
    with pytest.raises(DataError) as info:
        unit_factor("g", "angle", file=None, column="delta")
    assert "is an acceleration unit, but this channel is an angle" in str(info.value)
    with pytest.raises(DataError) as info:
        unit_factor("deg", "speed", file=None, column="vx")
    assert "is an angle unit, but this channel is a speed" in str(info.value)


def test_without_any_sideslip_reference_the_held_out_check_says_what_it_needs():
    from kftune.cli.tune import held_out
    from kftune.models import get_model

    c = synthetic_channels(n=300)
    measured = {k: v for k, v in c.items() if k not in ("t", "beta_ref")}
    ms = tuple(Manoeuvre(f"m{i}", "recording", s, c["t"], **measured)
               for i, s in enumerate(("train", "test")))  # fmt: skip
    dataset = Dataset("no-ref", None, 0.01, ms, "", {})
    problem = SimpleNamespace(
        parameterization=SimpleNamespace(model_names=()), model=get_model("single-track")
    )
    evidence, why = held_out(problem, None, dataset)  # type: ignore[arg-type]
    assert evidence is None and why is not None
    assert "needs a sideslip reference, a beta_ref channel" in why
    assert "kftune evaluate --split test" in why and "burn-in" not in why


@pytest.mark.parametrize(("ratio", "suspected"), [(-0.8, False), (0.3, True), (-3.0, True)])
def test_a_doubtful_ratio_names_the_computed_channel_only_where_a_unit_could_explain_it(
    tmp_path, monkeypatch, ratio, suspected
):
    """The warning about an ay/(vx·r) outside 0.5–2 that is not certainly wrong (noisy
    data: faked here, as real data noisy enough trip other checks first): a ratio of the
    expected size but negative is a sign, no unit's doing."""
    import kftune.data.importer as importer

    doubt = f"ay/(vx·r) = {ratio} in cornering, outside the expected 0.5 to 2"
    monkeypatch.setattr(importer, "plausibility_findings", lambda *a: {"kinematic": doubt})
    monkeypatch.setattr(importer, "kinematic_ratio", lambda *a: SimpleNamespace(ratio=ratio))
    csv = _logger(tmp_path / "run1.csv", ay_sign=1.0, vx_factor=1.0)
    channels = {"t": "time", "vx": {"expr": WHEEL_MEAN}, "ay": "acc_y", "r": "yaw_rate"}
    with pytest.warns(DataWarning, match="outside the expected") as caught:
        import_recordings([csv], {"channels": channels | {"ax": "ax"}})
    (said,) = [str(w.message) for w in caught if "outside the expected" in str(w.message)]
    assert ("suspect the computed channel vx" in said) == suspected, said
