"""The arithmetic of ``benchmarks/ukf_tuning.py`` — gaps, evaluations to 1 %, the
monotonicity check and a candidate's target verdicts — on made-up runs with known answers."""

from __future__ import annotations

import math
import sys

import pytest

from conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
ukf_tuning = pytest.importorskip("ukf_tuning")

BUDGETS = [40, 100, 225]


def unit(label: str, seed: int, j: dict[int, float], rmse: float = 0.2) -> dict:
    """A (method, seed) unit whose best cost at budget b is j[b], reached at evaluation b/2."""
    cells = {}
    for b, v in j.items():
        trace = [10.0] * (b // 2 - 1) + [v] * (b - b // 2 + 1)
        cells[str(b)] = {
            "best": v,
            "trace": trace,
            "test_rmse_deg": rmse,
            "wall_s": 1.0,
            "overhead_ms_per_eval": 1.0,
            "n_failed": 0,
        }
    return {"label": label, "seed": seed, "prefix_read": False, "budgets": cells}


def test_gap_and_evaluations_to_one_percent():
    assert ukf_tuning.gap_pct(1.01, 1.0) == pytest.approx(1.0)
    assert ukf_tuning.evals_to_reach([5.0, 3.0, 1.01, 1.0], 1.01) == 3
    assert ukf_tuning.evals_to_reach([5.0, 3.0], 1.01) == math.inf
    safe = ukf_tuning.json_safe({"a": [math.inf, 1.0], "b": math.nan})
    assert safe == {"a": [None, 1.0], "b": None} and ukf_tuning.num(None) == math.inf


def test_monotonicity_per_seed():
    rows = [
        unit("m", 0, {40: 1.05, 100: 1.02, 225: 1.01}),  # falls: fine
        unit("m", 1, {40: 1.05, 100: 1.05, 225: 1.0}),  # stalls 1.05 → 1.05: not strict
        unit("m", 2, {40: 1.0005, 100: 1.0005, 225: 1.0005}),  # within 0.1 %: may stall
        unit("m", 3, {40: 1.02, 100: 1.03, 225: 1.0}),  # rises
    ]
    m = ukf_tuning.monotonicity(rows, BUDGETS, jstar=1.0)
    assert m["rising_seeds"] == [3]
    assert m["not_strictly_better_seeds"] == [1, 3]


def test_candidate_targets():
    """J* = 1. The candidate 'new': medians 1.005 at 40 (PASS ≤ 1 %), 1.003 at 100 (FAIL >
    0.2 %), worst at 40 1.02 (PASS ≤ 3 %); ahead of every peer at 40, not of cma at 100;
    ≤ GA at 225; monotone and strict; test RMSE 0.2 vs GA's 0.19 (FAIL)."""
    units = {
        "new": [
            unit("new", 0, {40: 1.005, 100: 1.003, 225: 1.0}),
            unit("new", 1, {40: 1.004, 100: 1.002, 225: 1.0}),
            unit("new", 2, {40: 1.02, 100: 1.01, 225: 1.0}),
        ],
        "cma": [unit("cma", s, {40: 1.01, 100: 1.001, 225: 1.0}) for s in range(3)],
        "random": [unit("random", s, {40: 1.1, 100: 1.05, 225: 1.02}) for s in range(3)],
        "ga": [unit("ga", s, {40: 1.2, 100: 1.1, 225: 1.006}, rmse=0.19) for s in range(3)],
    }
    summary = ukf_tuning.summarise(units, BUDGETS, jstar=1.0)
    assert summary["new"]["40"]["median_gap_pct"] == pytest.approx(0.5)
    assert summary["new"]["40"]["worst_gap_pct"] == pytest.approx(2.0)
    assert summary["new"]["40"]["median_evals_to_1pct"] == 20  # reached at b/2 on 2 of 3
    assert summary["new"]["40"]["reached_1pct"] == 2
    verdicts = [c["result"] for c in ukf_tuning.candidate_checks("new", summary, BUDGETS)]
    assert verdicts == ["PASS", "FAIL", "PASS", "PASS", "FAIL", "PASS", "PASS", "FAIL"]
    # a peer is not compared with itself; without GA its targets are not applicable
    checks = ukf_tuning.candidate_checks("cma", summary, [40, 100])
    ahead = [c for c in checks if c["target"].startswith("ahead")]
    assert all("cma 1." not in c["detail"] for c in ahead)
    assert [c["result"] for c in checks][-3:] == ["n/a", "PASS", "n/a"]
