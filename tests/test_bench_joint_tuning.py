"""The arithmetic of ``benchmarks/joint_tuning.py`` (J* of a joint configuration, the
vehicle-scaling option, the held-out target) and of ``benchmarks/reference_free.py``'s rank
analysis near the optimum, on made-up runs with known answers."""

from __future__ import annotations

import argparse
import json
import math
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import spearmanr

from conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
joint_tuning = pytest.importorskip("joint_tuning")
reference_free = pytest.importorskip("reference_free")


def unit(config: str, label: str, seed: int, j: float, rmse: float, params: dict) -> dict:
    """A (configuration, method, seed) unit with best cost ``j`` at budget 100."""
    cell = {"best": j, "test_rmse_deg": rmse, "wall_s": 1.0, "n_failed": 0, "params": params}
    return {"config": config, "label": label, "seed": seed, "budgets": {"100": cell}}


MODEL = {"C_af": 5e4, "C_ar": 8e4, "mu": 1.2}


def test_a_joint_configurations_jstar_is_at_most_the_noise_only_optimum():
    """The noise-only optimum lies in the joint space: a joint run above it has a positive
    gap to it, and J* names where it came from; a long reference run that is lower wins."""
    units = [unit("noise", "trbo", s, 0.50, 0.27, {}) for s in range(3)]
    units += [unit("d5", "trbo", s, 0.55 + 0.01 * s, 0.29, MODEL) for s in range(3)]
    budgets = {"noise": [100], "d5": [100]}
    s = joint_tuning.summarise(units, budgets)
    assert s["d5"]["jstar"] == 0.50 and s["d5"]["jstar_found_by"]["config"] == "noise"
    assert s["d5"]["methods"]["trbo"]["100"]["median_gap_pct"] == pytest.approx(12.0)
    ref = [unit("d5", "cma", 1000, 0.40, 0.3, MODEL)]
    s = joint_tuning.summarise(units, budgets, ref)
    assert s["d5"]["jstar"] == 0.40 and s["d5"]["jstar_found_by"]["reference"] == "cma"
    assert s["noise"]["jstar"] == 0.50  # a configuration without model parameters: its own


def test_the_heldout_target_compares_the_medians_over_seeds_0_to_2():
    """Joint within 5 % of noise-only on the true vehicle: 0.104 vs 0.100 passes (+4 %),
    0.106 fails (+6 %); seed 3 is not part of the median."""
    for joint, verdict in ((0.104, "PASS"), (0.106, "FAIL")):
        units = [unit("noise-true", "trbo", s, 0.35, 0.100, {}) for s in range(4)]
        units += [unit("noise", "trbo", s, 1.4, 0.86, {}) for s in range(4)]
        units += [unit("d6", "trbo", s, 0.3, joint, MODEL) for s in range(3)]
        units.append(unit("d6", "trbo", 3, 0.3, 9.0, MODEL))
        budgets = {key: [100] for key in ("noise-true", "noise", "d6")}
        checks = joint_tuning.targets(joint_tuning.summarise(units, budgets), recorded=False)
        held = [c for c in checks if "true vehicle" in c["target"]]
        assert [c["result"] for c in held] == [verdict], held


@pytest.mark.parametrize("bad", ["C_af", "C_af=", "C_af=-1", "=0.7", "mu=nan"])
def test_a_vehicle_scaling_that_is_not_name_equals_positive_factor_is_refused(bad):
    with pytest.raises(argparse.ArgumentTypeError, match="NAME=FACTOR"):
        joint_tuning.parse_scales([bad])
    assert joint_tuning.parse_scales(["C_af=0.7", "mu=0.8"]) == {"C_af": 0.7, "mu": 0.8}


def test_rank_near_optimum_takes_the_distinct_lowest_costs_and_spearmans_rho(monkeypatch):
    """The ``top`` distinct points of lowest cost (a repeated point once, failed ones never),
    each scored on the test set; ρ is scipy's Spearman of the two."""
    rng = np.random.default_rng(0)
    costs = rng.permutation(np.arange(1.0, 11.0))
    records = [SimpleNamespace(ok=True, value=float(v), x=(float(v),)) for v in costs]
    records.append(SimpleNamespace(ok=True, value=1.0, x=(1.0,)))  # the best point again
    records.append(SimpleNamespace(ok=False, value=None, x=(0.5,)))
    beta = {float(v): float(rng.random()) for v in costs}
    monkeypatch.setattr(reference_free, "test_beta_rmse", lambda _p, x, _m: beta[float(x[0])])
    out = reference_free.rank_near_optimum(None, records, None, top=6)
    assert out["J"] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    want = spearmanr(out["J"], [beta[v] for v in out["J"]]).statistic
    assert out["spearman"] == pytest.approx(want)
    assert out["gap_last_pct"] == pytest.approx(500.0)
    assert out["beta_min_deg"] == min(beta[v] for v in out["J"])
    monkeypatch.setattr(reference_free, "test_beta_rmse", lambda _p, x, _m: 0.2)
    assert reference_free.rank_near_optimum(None, records, None, top=6)["spearman"] is None
    pooled = reference_free.pooled_rank([out, {**out, "spearman": None}])
    assert pooled["rank_pooled_n"] == 12 and not math.isnan(pooled["rank_pooled_spearman"])


def test_tune_splits_forces_the_first_stage_and_zero_runs_one_unseeded_search(small, tmp_path):
    """``--tune-splits``' runs are ``kftune tune`` with the first stage forced: N1 = 5 of
    -n 12 gives stages of 5 and 7 (staging's own split of 12 is 3 + 9), 0 one joint search
    without stages, None staging's split; ``experiment.staging`` is restored after each."""
    import kftune.experiment as ex

    original = ex.staging
    model = ["--tune-model", "C_af=20000:400000"]
    runs = {
        n1: joint_tuning.tune_cli_split(str(small), 12, n1, 0, model, tmp_path / f"{n1}.json")
        for n1 in (5, 0, None)
    }
    assert ex.staging is original
    stages = {n1: json.loads((tmp_path / f"{n1}.json").read_text()).get("stages") for n1 in runs}
    assert (stages[5]["noise_budget"], stages[5]["joint_budget"]) == (5, 7)
    assert stages[0] is None and runs[0]["stage1_J"] is None
    assert stages[None]["noise_budget"] == runs[None]["noise_budget"] != 5
    assert runs[5]["stage1_J"] == pytest.approx(stages[5]["noise_only"]["cost"])
    for r in runs.values():
        assert r["beta_deg"] > 0 and set(r["model"]) == {"C_af"}
