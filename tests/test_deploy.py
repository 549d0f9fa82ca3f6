"""A tuned filter deployed: the record in tuned.json, ``kftune estimate`` (states, standard
deviations, innovations, NIS, KPIs, refusals) and ``kftune export`` (JSON, YAML, the C export's
macros compiled with the system compiler, a MATLAB script), each checked against
independent computations (the C filter that runs: test_export_c.py)."""

from __future__ import annotations

import csv
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from kftune.cli import main
from kftune.data import default_dataset
from kftune.filters import UKFSettings
from kftune.tuning.deploy import (
    TunedFilter,
    beta_std,
    dataset_fingerprint,
    estimate,
    reference,
)
from kftune.tuning.kpi import sideslip_kpis
from single_track import run_ukf

MANOEUVRE = "test-12-slalom"


@pytest.fixture(scope="module")
def tuned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tuned-parameters file (the manual rule of thumb, written by ``kftune tune``)."""
    path = tmp_path_factory.mktemp("tuned") / "tuned.json"
    assert main(["tune", "-m", "manual", "-o", str(path), "-q"]) == 0
    return path


def edited(tuned: Path, tmp_path: Path, change) -> Path:
    doc = json.loads(tuned.read_text())
    change(doc)
    out = tmp_path / "edited.json"
    out.write_text(json.dumps(doc))
    return out


# -- the record -----------------------------------------------------------------------------


def test_tuned_file_records_what_a_deployment_needs(tuned):
    doc = json.loads(tuned.read_text())
    dep = doc["deployment"]
    ds = default_dataset()
    assert dep["dt"] == ds.dt
    assert dep["vehicle"] == ds.vehicle.to_dict()
    assert dep["dataset"] == dataset_fingerprint(ds)
    assert [e["name"] for e in dep["Q"]] == doc["states"] == ["vx", "vy", "r"]
    assert [e["variance"] for e in dep["Q"]] == doc["q"]
    assert [e["variance"] for e in dep["R"]] == doc["r"]
    assert [e["unit"] for e in dep["Q"]] == ["(m/s)^2", "(m/s)^2", "(rad/s)^2"]
    assert [e["unit"] for e in dep["R"]] == ["(m/s)^2", "(m/s^2)^2", "(rad/s)^2"]
    assert dep["sigma_points"]["alpha"] == doc["ukf"]["alpha"]
    assert "x0 = [z0_Vx, 0, z0_r]" in dep["initial_state"]
    assert [e["name"] for e in dep["model_params"]][:3] == ["m", "Iz", "a"]


def test_dataset_fingerprint_changes_with_one_sample():
    ds = default_dataset()
    sub = ds.subset(ds.names[:2])
    m = sub.manoeuvres[0]
    vx = m.vx.copy()
    vx[5] += 1e-9
    changed = type(sub)(sub.name, sub.vehicle, sub.dt, (_replace(m, vx=vx), sub.manoeuvres[1]))
    a, b = dataset_fingerprint(sub), dataset_fingerprint(changed)
    assert a["sha256"] != b["sha256"]
    assert dataset_fingerprint(ds.subset(ds.names[:2]))["sha256"] == a["sha256"]


def _replace(m, **changes):
    return m.replace(**changes)


# -- estimate (library) --------------------------------------------------------------------


def test_beta_std_matches_a_monte_carlo_of_the_gaussian_posterior():
    rng = np.random.default_rng(0)
    x = np.array([[20.0, 1.0, 0.0], [8.0, -0.9, 0.1], [30.0, 0.0, 0.0]])
    p = np.array([[0.04, 0.01, 1e-4], [0.01, 0.0225, 1e-4], [0.09, 0.0025, 1e-4]])
    n = 400_000
    for k in range(len(x)):
        vx = x[k, 0] + np.sqrt(p[k, 0]) * rng.standard_normal(n)
        vy = x[k, 1] + np.sqrt(p[k, 1]) * rng.standard_normal(n)
        mc = np.std(np.arctan2(vy, vx))
        # linearisation error is second order in std/speed (< 1 % here), MC error ~0.2 %
        assert beta_std(x[k : k + 1], p[k : k + 1])[0] == pytest.approx(mc, rel=0.01)


def test_estimate_equals_run_ukf_for_the_same_parameters(tuned):
    from kftune.cli.evaluate import read_tuned

    tf = TunedFilter.from_document(read_tuned(tuned), str(tuned), calibrated=False)
    ds = default_dataset()
    m = ds[MANOEUVRE]
    est = estimate(tf, m, ds.vehicle)
    ref = run_ukf(m.u, m.z, m.dt, ds.vehicle, tf.q, tf.r, settings=UKFSettings())
    c = est.columns
    np.testing.assert_array_equal(np.column_stack([c["vx"], c["vy"], c["r"]]), ref.x)
    np.testing.assert_array_equal(c["vy_std"], np.sqrt(ref.P_diag[:, 1]))
    np.testing.assert_array_equal(c["beta"], ref.output("beta"))
    np.testing.assert_array_equal(c["nis"], ref.nis)
    np.testing.assert_array_equal(c["innovation_ay"], ref.innovation[:, 1])
    np.testing.assert_array_equal(c["beta_ref"], m.beta_ref)
    assert est.units["beta_std"] == "rad" and est.units["innovation_ay"] == "m/s^2"


def test_the_calibrated_estimate_is_the_tuned_one_with_covariances_c_times_larger(tuned):
    """The tuned file's calibration factor c applied: run_ukf's estimate with the tuned q and
    r, its variances times c (σ and β's σ times √c) and its NIS over c."""
    from kftune.cli.evaluate import read_tuned

    doc = read_tuned(tuned)
    tf = TunedFilter.from_document(doc, str(tuned))
    c = doc["calibration"]["factor"]
    assert tf.cov_scale == c and c != 1.0
    ds = default_dataset()
    m = ds[MANOEUVRE]
    cols = estimate(tf, m, ds.vehicle).columns
    ref = run_ukf(m.u, m.z, m.dt, ds.vehicle, tf.q, tf.r, settings=UKFSettings())
    np.testing.assert_array_equal(np.column_stack([cols["vx"], cols["vy"], cols["r"]]), ref.x)
    np.testing.assert_allclose(cols["vy_std"], np.sqrt(c * ref.P_diag[:, 1]), rtol=1e-12)
    np.testing.assert_allclose(
        cols["beta_std"], np.sqrt(c) * beta_std(ref.x, ref.P_diag), rtol=1e-12
    )
    np.testing.assert_allclose(cols["nis"], ref.nis / c, rtol=1e-12)


class _NoReference:
    """A recording without a reference sideslip sensor (the manoeuvre, minus beta_ref)."""

    def __init__(self, m):
        self._m = m

    def __getattr__(self, name):
        if name == "beta_ref":
            raise AttributeError(name)
        return getattr(self._m, name)

    def channel(self, name):
        if name == "beta_ref":
            raise KeyError(name)
        return self._m.channel(name)


def test_estimate_without_a_reference_writes_no_reference(tuned):
    from kftune.cli.evaluate import read_tuned

    tf = TunedFilter.from_document(read_tuned(tuned), str(tuned))
    ds = default_dataset()
    bare = _NoReference(ds[MANOEUVRE])
    assert reference(bare) is None
    est = estimate(tf, bare, ds.vehicle)
    assert "beta_ref" not in est.columns
    assert np.all(np.isfinite(est.columns["beta_std"]))


# -- estimate (command) --------------------------------------------------------------------


def test_estimate_command_writes_tables_figures_and_kpis(tuned, tmp_path, capsys):
    out = tmp_path / "est"
    code = main(["estimate", "--params", str(tuned), "-m", MANOEUVRE, "-o", str(out), "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    row = doc["manoeuvres"][MANOEUVRE]
    assert (out / f"{MANOEUVRE}.png").stat().st_size > 10_000
    with open(out / f"{MANOEUVRE}.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    header, data = rows[0], np.array(rows[1:], dtype=float)
    assert header[:4] == ["t", "vx", "vy", "r"]
    assert {"vx_std", "beta", "beta_std", "innovation_vx", "nis", "beta_ref"} <= set(header)
    ds = default_dataset()
    m = ds[MANOEUVRE]
    # the file holds every double exactly (%.17g), so the KPIs recompute from it exactly
    col = {h: data[:, i] for i, h in enumerate(header)}
    np.testing.assert_array_equal(col["t"], m.t)
    kpis = sideslip_kpis(col["beta"], col["beta_ref"], m.ay)
    for k in ("rmse", "mae", "rmse_non", "mae_non"):
        assert row["kpis"][k] == pytest.approx(kpis[k], rel=1e-12)
    assert doc["average"]["rmse"] == pytest.approx(kpis["rmse"], rel=1e-12)
    assert row["columns"]["beta_std"] == "rad"
    assert doc["warnings"] == []


def test_estimate_says_how_many_tables_and_figures_it_wrote(tuned, tmp_path, capsys):
    names = ["test-12-slalom", "test-09-j-turn"]
    for plot, out in ((True, tmp_path / "with"), (False, tmp_path / "without")):
        args = ["estimate", "--params", str(tuned), "-o", str(out)]
        args += [a for name in names for a in ("-m", name)] + ([] if plot else ["--no-plot"])
        assert main(args) == 0
        last = capsys.readouterr().out.strip().splitlines()[-1]
        tables, figures = len(list(out.glob("*.csv"))), len(list(out.glob("*.png")))
        assert (tables, figures) == (2, 2 if plot else 0)
        said = "2 csv files and 2 PNG figures" if plot else "2 csv files"
        assert last == f"estimates written to {out} ({said})"


def _runs(command: str, params: Path, tmp_path: Path, small: Path) -> list[str]:
    """The command line that runs ``params``'s filter: ``estimate`` on one manoeuvre of the
    bundled set, ``evaluate`` on the small dataset's test split."""
    if command == "estimate":
        return ["estimate", "--params", str(params), "-m", MANOEUVRE, "-o", str(tmp_path / "e")]
    return ["evaluate", str(small), "--params", str(params), "--json"]


@pytest.mark.parametrize("command", ["estimate", "evaluate"])
def test_another_sample_time_is_refused_unless_forced(tuned, tmp_path, capsys, small, command):
    """evaluate --params scores the filter estimate runs: the same check, the same --force
    (evaluate used to score a filter tuned at 100 Hz on 50 Hz data without a word)."""
    params = edited(tuned, tmp_path, lambda d: d["deployment"].update(dt=0.0102))
    args = _runs(command, params, tmp_path, small)
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "0.0102" in err and "--force" in err and str(params) in err
    assert (MANOEUVRE if command == "estimate" else "test-05-j-turn") in err
    assert "Traceback" not in err
    assert main([*args, "--force", *(["--no-plot"] if command == "estimate" else [])]) == 0
    err = capsys.readouterr().err
    assert "kftune: warning: --force" in err and "sampled every 0.01 s" in err


@pytest.mark.parametrize("command", ["estimate", "evaluate"])
def test_another_vehicle_is_refused_unless_forced(tuned, tmp_path, capsys, small, command):
    params = edited(tuned, tmp_path, lambda d: d["deployment"]["vehicle"].update(m=1500.0))
    args = _runs(command, params, tmp_path, small)
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "vehicle" in err and "m 1500.0 vs 1093.29" in err and "--force" in err
    assert main([*args, "--force", *(["--no-plot"] if command == "estimate" else [])]) == 0
    assert "kftune: warning: --force" in capsys.readouterr().err


def test_evaluate_force_scores_the_filter_estimate_runs(tuned, tmp_path, capsys, small):
    """Forced onto another vehicle, evaluate scores the tuned filter — on the tuned vehicle,
    as estimate runs and export deploys it — not a filter rebuilt on the data's vehicle."""
    params = edited(tuned, tmp_path, lambda d: d["deployment"]["vehicle"].update(m=1500.0))
    ev = ["evaluate", str(small), "--params", str(params), "--json", "--force"]
    assert main(ev) == 0
    scored = json.loads(capsys.readouterr().out)
    out = tmp_path / "e"
    est = ["estimate", str(small), "--params", str(params), "-o", str(out), "--no-plot"]
    for name in scored["manoeuvres"]:
        est += ["-m", name]
    assert main([*est, "--json", "--force"]) == 0
    ran = json.loads(capsys.readouterr().out)
    assert scored["average"]["rmse"] == pytest.approx(ran["average"]["rmse"], rel=1e-12)
    assert main(["evaluate", str(small), "--params", str(tuned), "--json"]) == 0
    own = json.loads(capsys.readouterr().out)  # the tuned vehicle is another filter
    assert own["average"]["rmse"] != pytest.approx(scored["average"]["rmse"], rel=1e-6)


def test_force_without_a_tuned_file_is_a_usage_error(capsys):
    assert main(["evaluate", "--manual", "--force"]) == 2
    assert "--force" in capsys.readouterr().err


def test_estimate_reads_a_file_from_before_the_deployment_record(tuned, tmp_path, capsys):
    params = edited(tuned, tmp_path, lambda d: d.pop("deployment"))
    out = tmp_path / "e"
    code = main(["estimate", "--params", str(params), "-m", MANOEUVRE, "-o", str(out), "--no-plot"])
    assert code == 0
    assert "does not record dt, vehicle, dataset" in capsys.readouterr().err
    assert (out / f"{MANOEUVRE}.csv").is_file()


def test_estimate_names_an_unknown_manoeuvre(tuned, tmp_path, capsys):
    code = main(["estimate", "--params", str(tuned), "-m", "no-such", "-o", str(tmp_path)])
    assert code == 3
    assert "--manoeuvre: no manoeuvre 'no-such'" in capsys.readouterr().err


def test_estimate_parquet_names_the_missing_package(tuned, tmp_path, capsys):
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        args = ["estimate", "--params", str(tuned), "-m", MANOEUVRE, "-o", str(tmp_path)]
        code = main([*args, "--format", "parquet"])
        assert code == 2
        assert "pyarrow" in capsys.readouterr().err
        return
    import pyarrow.parquet as pq

    out = tmp_path / "e"
    args = ["estimate", "--params", str(tuned), "-m", MANOEUVRE, "-o", str(out)]
    code = main([*args, "--format", "parquet", "--no-plot"])
    assert code == 0
    table = pq.read_table(out / f"{MANOEUVRE}.parquet")
    assert "beta_std" in table.column_names


# -- export ---------------------------------------------------------------------------------


def export(tuned: Path, tmp_path: Path, fmt: str, suffix: str) -> Path:
    out = tmp_path / f"filter{suffix}"
    assert main(["export", str(tuned), "--format", fmt, "-o", str(out)]) == 0
    return out


def numbers(doc: dict) -> dict[str, float]:
    """Every number of a flat export document, lists flattened to ``key[i]``."""
    out = {}
    for key, value in doc.items():
        for i, v in enumerate(value if isinstance(value, list) else [value]):
            if isinstance(v, float):
                out[f"{key}[{i}]" if isinstance(value, list) else key] = v
    return out


def test_json_export_holds_the_tuned_values(tuned, tmp_path):
    doc = json.loads(export(tuned, tmp_path, "json", ".json").read_text())
    src = json.loads(tuned.read_text())
    assert doc["q_diag"] == src["q"] and doc["r_diag"] == src["r"]  # what runs
    assert doc["covariance_scale"] == src["calibration"]["factor"] != 1.0
    assert doc["dt"] == src["deployment"]["dt"]
    assert doc["vehicle_m"] == src["deployment"]["vehicle"]["m"]
    assert doc["states"] == ["vx", "vy", "r"] and doc["q_units"][2] == "(rad/s)^2"
    assert doc["ukf_alpha"] == src["ukf"]["alpha"]
    assert doc["dataset_sha256"] == src["deployment"]["dataset"]["sha256"]


def test_yaml_export_reads_back_as_the_json_export(tuned, tmp_path):
    yaml = pytest.importorskip("yaml")
    doc = json.loads(export(tuned, tmp_path, "json", ".json").read_text())
    text = export(tuned, tmp_path, "yaml", ".yaml").read_text()
    assert yaml.safe_load(text) == doc  # PyYAML reads YAML 1.1: floats need "1.0e-06"
    assert text.startswith("# kftune filter: UKF on model 'single-track'")


def test_c_header_compiles_and_its_values_round_trip(tuned, tmp_path):
    """The numbers-only macros of the C export's kftune_filter.h (the filter that runs
    beside them: test_export_c.py)."""
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    doc = json.loads(export(tuned, tmp_path, "json", ".json").read_text())
    folder = export(tuned, tmp_path, "c", "_c")
    text = (folder / "kftune_filter.h").read_text()
    assert "#ifndef KFTUNE_FILTER_H" in text
    assert text.rstrip().endswith("#endif /* KFTUNE_FILTER_H */")
    assert "sha256 " + doc["dataset_sha256"] in text
    prints = ['printf("dt %.17g\\n", KFTUNE_DT);']
    prints.append('printf("covariance_scale %.17g\\n", KFTUNE_COVARIANCE_SCALE);')
    for name, n in (("Q_DIAG", 3), ("R_DIAG", 3), ("MODEL_PARAMS", 9)):
        prints += [f'printf("{name} {i} %.17g\\n", KFTUNE_{name}[{i}]);' for i in range(n)]
    for key in ("alpha", "beta", "kappa"):
        prints.append(f'printf("ukf_{key} %.17g\\n", KFTUNE_UKF_{key.upper()});')
    prints.append('printf("vehicle_m %.17g\\n", KFTUNE_VEHICLE_M);')
    prints.append('printf("n %d %d\\n", KFTUNE_N_STATES, KFTUNE_STATE_VY);')
    program = tmp_path / "main.c"
    program.write_text(
        '#include <stdio.h>\n#include "kftune_filter.h"\n#include "kftune_filter.h" /* guard */\n'
        "int main(void) {\n" + "\n".join(prints) + "\nreturn 0;\n}\n"
    )
    exe = tmp_path / "main"
    flags = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror", "-I", str(folder)]
    subprocess.run(
        [cc, *flags, str(program), "-o", str(exe), "-lm"],
        check=True,
        capture_output=True,
        cwd=tmp_path,
    )
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split("\n")
    got = {" ".join(line.split()[:-1]): line.split()[-1] for line in out if line}
    assert float(got["dt"]) == doc["dt"]
    for name, key in (("Q_DIAG", "q_diag"), ("R_DIAG", "r_diag"), ("MODEL_PARAMS", "model_params")):
        for i, v in enumerate(doc[key]):
            assert float(got[f"{name} {i}"]) == v  # exactly: %.17g of the same double
    for key in ("alpha", "beta", "kappa"):
        assert float(got[f"ukf_{key}"]) == doc[f"ukf_{key}"]
    assert float(got["vehicle_m"]) == doc["vehicle_m"]
    assert float(got["covariance_scale"]) == doc["covariance_scale"]
    assert got["n 3"] == "1"


def test_c_header_of_a_model_without_parameters_compiles(tuned, tmp_path):
    """A model with no parameter vector (a kinematic model of one's own) wrote
    ``KFTUNE_MODEL_PARAMS[0] = {}``, which ISO C refuses (zero-size array, empty braces)."""
    from kftune.report.export import to_c_header

    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    doc = json.loads(export(tuned, tmp_path, "json", ".json").read_text())
    doc.update(model_params=[], model_param_names=[], model_param_units=[])
    (tmp_path / "filter.h").write_text(to_c_header(doc, "tuned.json"))
    program = tmp_path / "main.c"
    program.write_text('#include "filter.h"\nint main(void) { return KFTUNE_N_MODEL_PARAMS; }\n')
    res = subprocess.run(
        [cc, "-std=c99", "-pedantic-errors", "-Wall", "-Werror", str(program), "-o", "main"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert subprocess.run([str(tmp_path / "main")]).returncode == 0


def parse_matlab(text: str) -> dict[str, object]:
    """A parser of the statements the MATLAB export writes: ``kf.a.b = VALUE;`` with
    VALUE a number, a quoted string, [] or a column vector, or a cell array of strings."""
    out: dict[str, object] = {}
    number = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
    for line in text.splitlines():
        if not line or line.startswith("%") or line in ("kf = struct();",):
            continue
        m = re.fullmatch(r"kf\.([\w.]+) = (.*?);(?: % .*)?", line)
        assert m, f"unexpected line {line!r}"
        key, value = m.groups()
        if re.fullmatch(number, value):
            out[key] = float(value)
        elif value.startswith("'"):
            out[key] = value[1:-1].replace("''", "'")
        elif value == "[]":
            out[key] = None
        elif value.startswith("["):
            items = value[1:-1].split("; ")
            assert all(re.fullmatch(number, v) for v in items), value
            out[key] = [float(v) for v in items]
        elif value.startswith("{"):
            out[key] = re.findall(r"'((?:[^']|'')*)'", value)
        else:
            out[key] = ("expr", value)
    return out


def test_matlab_export_parses_to_the_json_values(tuned, tmp_path):
    doc = json.loads(export(tuned, tmp_path, "json", ".json").read_text())
    script = export(tuned, tmp_path, "matlab", ".m")
    got = parse_matlab(script.read_text())
    assert got["dt"] == doc["dt"]
    assert got["q_diag"] == doc["q_diag"] and got["r_diag"] == doc["r_diag"]
    assert got["covariance_scale"] == doc["covariance_scale"]
    assert got["model_params"] == doc["model_params"]
    assert got["states"] == doc["states"] and got["q_units"] == doc["q_units"]
    assert got["vehicle.m"] == doc["vehicle_m"] and got["vehicle.name"] == doc["vehicle_name"]
    assert got["Q"] == ("expr", "diag(kf.q_diag)")
    assert got["tuned_method"] == "manual"
    octave = shutil.which("octave")
    if octave is not None:  # not on the development machine; checked where it exists
        res = subprocess.run(
            [octave, "--no-gui", "--eval", f"run('{script}'); printf('%.17g\\n', kf.Q(2, 2))"],
            capture_output=True,
            text=True,
            check=True,
        )
        assert float(res.stdout.split()[-1]) == doc["q_diag"][1]


def test_export_of_a_file_before_the_record_says_to_tune_again(tuned, tmp_path, capsys):
    params = edited(tuned, tmp_path, lambda d: d.pop("deployment"))
    assert main(["export", str(params), "-f", "c", "-o", str(tmp_path / "x")]) == 3
    err = capsys.readouterr().err
    assert str(params) in err and "tune again" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_export_names_a_damaged_record(tuned, tmp_path, capsys):
    params = edited(tuned, tmp_path, lambda d: d["deployment"].pop("Q"))
    assert main(["export", str(params), "-o", "-"]) == 3
    assert "'deployment' record is damaged" in capsys.readouterr().err


def test_export_to_stdout_and_default_name(tuned, tmp_path, capsys):
    copy_ = tmp_path / "t.json"
    copy_.write_text(tuned.read_text())
    assert main(["export", str(copy_), "-f", "matlab"]) == 0
    assert (tmp_path / "t.m").is_file()
    capsys.readouterr()
    assert main(["export", str(copy_), "-f", "yaml", "-o", "-"]) == 0
    assert "q_diag: [1.0e-06, 0.0001, 1.0e-06]" in capsys.readouterr().out


def reader_argv(command: str, params: Path, tmp_path: Path) -> list[str]:
    """The arguments of ``command`` (export, estimate, evaluate) reading the tuned file
    ``params``, with outputs under ``tmp_path`` (the folder x, est)."""
    return {
        "export": ["export", str(params), "-o", str(tmp_path / "x"), "-f", "c"],
        "estimate": ["estimate", "--params", str(params), "-o", str(tmp_path / "est")],
        "evaluate": ["evaluate", "--params", str(params)],
    }[command]


@pytest.mark.parametrize(
    ("change", "where"),
    [
        (lambda d: d["q"].__setitem__(1, 1e9), ("'q'", "'vy'")),
        (lambda d: d["deployment"]["Q"][2].__setitem__("variance", 1e9), ("'q'", "'r'")),
        (lambda d: d["deployment"]["R"][0].__setitem__("variance", 2.0), ("'r'", "'vx'")),
        (lambda d: d["deployment"]["Q"].pop(), ("holds 3 values",)),
    ],
)
@pytest.mark.parametrize("command", ["export", "estimate", "evaluate"])
def test_q_and_r_edited_in_one_place_only_are_refused_by_every_reader(
    tuned, tmp_path, capsys, change, where, command
):
    """evaluate and estimate run the top-level q and r, export writes the deployment
    record: a file whose two copies disagree would deploy another filter than was scored."""
    params = edited(tuned, tmp_path, change)
    assert main(reader_argv(command, params, tmp_path)) == 3
    err = capsys.readouterr().err
    assert str(params) in err and "Traceback" not in err
    assert all(w in err for w in where), err
    assert not (tmp_path / "x").exists() and not (tmp_path / "est").exists()


def test_q_rewritten_with_rounding_only_is_accepted(tuned, tmp_path, capsys):
    """Both copies written out with 15 significant digits (an editor or a tool that
    re-prints the numbers) still agree."""

    def reprint(d):
        d["q"] = [float(f"{v:.15g}") for v in d["q"]]

    params = edited(tuned, tmp_path, reprint)
    assert main(["export", str(params), "-o", "-"]) == 0


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda d: d["deployment"].update(dt=-5), "'deployment.dt' must be a positive number"),
        (lambda d: d["deployment"].update(dt="0.01"), "'deployment.dt' must be a positive"),
        (lambda d: d["deployment"].update(dt=10**400), "'deployment.dt' must be a positive"),
        (lambda d: d["deployment"]["vehicle"].update(m=-1000), "'deployment.vehicle'"),
        (lambda d: d["deployment"].update(vehicle="bmw"), "'deployment.vehicle' must be an"),
        (lambda d: d["deployment"].update(dt=None), "'deployment.dt' must be a positive"),
        (lambda d: d["deployment"].update(dataset=5), "'deployment.dataset' must be an obj"),
        (lambda d: d["deployment"].update(vehicle=None), "'deployment.vehicle' is null, but"),
    ],
)
@pytest.mark.parametrize("command", ["export", "estimate", "evaluate"])
def test_a_bad_deployment_record_is_refused_the_same_way_by_every_reader(
    tuned, tmp_path, capsys, change, says, command
):
    """The tuned file is checked where it is read, once for all three commands: export
    used to write ``#define KFTUNE_DT -5.0`` and a vehicle mass of -1000 kg that estimate
    refuses."""
    params = edited(tuned, tmp_path, change)
    assert main(reader_argv(command, params, tmp_path)) == 3
    err = capsys.readouterr().err
    assert f"file {params}: {says}" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists() and not (tmp_path / "est").exists()
    if says == "'deployment.vehicle'":
        assert "VehicleParams.m = -1000" in err
