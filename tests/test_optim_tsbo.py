"""TSBO specifics: partition-tree bookkeeping, the Eq. 10 switch, the Eq. 11 stage-2 box,
EI/CBM alternation and gain, the MAX_SM freeze, failures, exhaustion — each decision of the
module docstring. Most runs use a counting fixed-hyperparameter GP (tests/optim_fakes.py)
so the bookkeeping is visible and fast; the acquisition functions are kftune.bo's."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.optim import ExhaustedError, Space, minimize
from kftune.optim.tsbo import TSBO, PartitionTree, TSBOSettings, stage2_box
from optim_fakes import BRANIN_SPACE, CountingGP, branin


def tsbo(space, *, budget=None, seed=0, **settings) -> TSBO:
    """A TSBO with ``settings`` (:class:`TSBOSettings`) by name."""
    return TSBO(space, TSBOSettings(**settings), budget=budget, seed=seed)


def run(space, fun, **kw) -> TSBO:
    kw.setdefault("surrogate", CountingGP)
    opt = tsbo(space, **kw)
    while not opt.done:
        t = opt.ask()
        opt.tell(t, fun(t.x))
    return opt


def eq10_counter(history, space, tr_fe=0.01, units="natural"):
    """Independent Eq. 10: counter after each evaluation (incumbent moves), in natural
    units (threshold tr_fe·‖q*‖) or in the unit cube (threshold tr_fe·√d)."""
    out, n, best = [], 0, None
    for r in history:
        prev = best
        if r.ok and (best is None or r.value < best.value):
            best = r
        if prev is not None and best is not None:
            if units == "natural":
                d = np.linalg.norm(np.array(best.x) - np.array(prev.x))
                tr = tr_fe * np.linalg.norm(best.x)
            else:
                d = np.linalg.norm(np.array(best.u) - np.array(prev.u))
                tr = tr_fe * math.sqrt(len(best.u))
            n = n + 1 if (d < tr or d == 0) else 0
        out.append(n)
    return out


def min_pair_distance(history) -> float:
    """Smallest max-norm distance (unit cube) between two evaluated points."""
    U = np.array([r.u for r in history])
    D = np.abs(U[:, None, :] - U[None, :, :]).max(-1)
    return float(D[np.triu_indices(len(U), 1)].min())


# ----------------------------------------------------------------------------- tree
@pytest.mark.parametrize(("d", "k"), [(1, 2), (2, 2), (3, 2), (2, 3), (3, 3)])
def test_split_tiles_the_parent(d, k):
    rng = np.random.default_rng(d * 10 + k)
    lo = rng.random(d) * 0.3
    hi = lo + 0.2 + rng.random(d) * 0.5
    tree = PartitionTree(lo, hi)
    kids = tree.split(0, k, np.empty((0, d)))
    assert len(kids) == k**d and not tree.active[0] and tree.active[kids].all()
    vol = np.prod(tree.hi[kids] - tree.lo[kids], axis=1)
    np.testing.assert_allclose(vol.sum(), np.prod(hi - lo))
    np.testing.assert_allclose(vol, np.prod(hi - lo) / k**d)
    # Every point of the parent lies in exactly one child (closed-open boxes).
    pts = lo + (hi - lo) * rng.random((500, d))
    inside = np.all((pts[:, None, :] >= tree.lo[kids]) & (pts[:, None, :] < tree.hi[kids]), 2)
    assert (inside.sum(1) == 1).all()
    centres = tree.centres[kids]
    if k == 3:  # the middle child keeps the parent's centre
        assert np.any(np.all(np.isclose(centres, 0.5 * (lo + hi)), axis=1))
    else:  # 2^d split: children centres are the quarter points
        expect = [lo + (hi - lo) * np.array(c) for c in itertools.product([0.25, 0.75], repeat=d)]
        np.testing.assert_allclose(np.sort(centres, 0), np.sort(np.array(expect), 0))


def test_stage1_tree_grows_by_2d_minus_1_and_leaves_tile_the_cube():
    sp = {"a": (0.0, 1.0), "b": (0.0, 1.0), "c": (0.0, 1.0)}
    opt = tsbo(sp, surrogate=CountingGP, budget=12, max_fe=100, seed=1)
    first = opt.ask()
    np.testing.assert_array_equal(first.u, [0.5, 0.5, 0.5])
    assert (first.stage, first.acquisition, first.hyperparameters) == (1, "centre", None)
    opt.tell(first, 1.0)
    for i in range(1, 12):
        t = opt.ask()
        # candidates = unevaluated leaf centres: 2^d after the centre, +2^d − 1 per step
        assert t.info["n_candidates"] == 8 + 7 * (i - 1)
        leaf = t.info["leaf"]
        np.testing.assert_allclose(t.u, opt.tree.centres[leaf])
        assert opt.tree.active[leaf] and not opt.tree.asked[leaf]
        opt.tell(t, float(np.sum((t.u - 0.3) ** 2)))
        assert not opt.tree.active[leaf]
    act = opt.tree.active
    np.testing.assert_allclose(np.prod(opt.tree.hi[act] - opt.tree.lo[act], 1).sum(), 1.0)
    # every evaluated point is the centre of a node whose centre is marked asked
    for r in opt.history:
        hit = np.all(np.isclose(opt.tree.centres, r.u), 1)
        assert hit.any() and opt.tree.asked[hit].all()


# ----------------------------------------------------------------------------- switch
def test_switch_after_max_fe_small_moves_and_flat_objective_ties_go_to_ei():
    opt = run({"a": (1.0, 2.0), "b": (1.0, 2.0)}, lambda x: 5.0, budget=14, max_fe=5, seed=0)
    stages = [r.stage for r in opt.history]
    # centre (n stays 0), then 5 AF iterations with an incumbent that never moves → switch
    assert stages == [1] * 6 + [2] * 8
    assert opt.switch_at == 6
    # linear scale: the Eq. 11 box is centred on q*, whose child is not a candidate
    assert opt.history[6].info["n_candidates"] == 3**2 - 1
    # Alternation EI, CBM, … until the switch; equal (zero) gains → EI thereafter.
    assert [r.acquisition for r in opt.history[1:6]] == ["EI", "CBM", "EI", "CBM", "EI"]
    assert opt.chosen_af == "EI" and opt.gains == {"EI": 0.0, "CBM": 0.0}
    assert {r.acquisition for r in opt.history[6:]} == {"EI"}


@pytest.mark.parametrize("seed", [0, 1])
def test_switch_follows_eq10_on_branin(seed):
    opt = run(BRANIN_SPACE, branin, budget=40, max_fe=4, max_af=4, seed=seed)
    counter = eq10_counter(opt.history, opt.space)
    first2 = next(i for i, r in enumerate(opt.history) if r.stage == 2)
    # stage 2 starts right after the first evaluation that brought the counter to MAX_FE
    assert counter[first2 - 1] == 4 and max(counter[: first2 - 1]) < 4
    assert all(r.stage == 1 for r in opt.history[:first2])
    assert all(r.stage == 2 for r in opt.history[first2:])


def test_faithful_stage1_may_use_the_whole_budget_and_reserve_forces_stage2():
    # An objective that improves at every evaluation keeps the counter at 0.
    count = itertools.count()
    opt = run({"a": (1.0, 2.0), "b": (1.0, 2.0)}, lambda x: -next(count) * 10.0, budget=20)
    assert {r.stage for r in opt.history} == {1}  # never switched, budget used
    count = itertools.count()
    opt = run(
        {"a": (1.0, 2.0), "b": (1.0, 2.0)},
        lambda x: -next(count) * 10.0,
        budget=20,
        stage2_reserve=0.25,
    )
    assert [r.stage for r in opt.history] == [1] * 15 + [2] * 5


def test_tr_fe_in_the_unit_cube_on_a_hand_made_history():
    # The paper's TR_FE = 0.01·‖q*‖ in natural units is dominated by the largest component:
    # on the UKF space (q_r ≈ 0.2 ≫ q_vx, q_vy) moves of the small ones never count.
    sp = Space.coerce({k: (1e-10, 1.0, "log10") for k in ("vx", "vy", "r")})
    base = [1e-8, 1e-8, 0.2]
    cases = {  # q*_new: (small in natural units, small in the unit cube)
        # ‖Δq‖ = 1e-6 < 0.002 ; Δu = 2 decades / 10 = 0.2 > 0.01·√3
        "vx two decades": ([1e-6, 1e-8, 0.2], True, False),
        # ‖Δq‖ = 0.05 > 0.0025 ; Δu = log10(1.25)/10 = 0.0097 < 0.0173
        "r +25 %": ([1e-8, 1e-8, 0.25], False, True),
        # ‖Δq‖ = 0.064 > 0.0026 ; Δu = log10(1.32)/10 = 0.0121 < 0.01·√3 (not 0.01·‖u*‖)
        "r +32 %": ([1e-8, 1e-8, 0.264], False, True),
        # ‖Δq‖ = 4e-4 < 0.002 ; Δu = log10(1.002)/10 = 8.7e-5
        "r +0.2 %": ([1e-8, 1e-8, 0.2004], True, True),
        # ‖Δq‖ = 0.3 > 0.005 ; Δu = log10(2.5)/10 = 0.040 > 0.0173
        "r x2.5": ([1e-8, 1e-8, 0.5], False, False),
        "no move": (base, True, True),
    }
    for name, (q_new, small_natural, small_unit) in cases.items():
        for units, expect in (("natural", small_natural), ("unit-cube", small_unit)):
            opt = tsbo(sp, surrogate=CountingGP, tr_fe_units=units)
            opt._X = np.array([sp.to_unit(np.array(base)), sp.to_unit(np.array(q_new))])
            assert opt._small_move(0, 1) is expect, (name, units)


def test_unit_cube_tr_fe_drives_the_switch():
    sp = {"a": (1e-6, 1.0, "log10"), "b": (1e-6, 1.0, "log10")}
    f = lambda x: (math.log10(x[0]) + 3.3) ** 2 + (math.log10(x[1]) + 0.4) ** 2  # noqa: E731
    opt = run(sp, f, budget=30, max_fe=4, tr_fe_units="unit-cube", seed=0)
    unit = eq10_counter(opt.history, opt.space, units="unit")
    natural = eq10_counter(opt.history, opt.space)
    k = opt.switch_at
    assert k is not None and unit[k - 1] == 4 and max(unit[: k - 1]) < 4
    assert natural[k - 1] < 4  # the paper's rule would not have switched here
    assert all(r.stage == 1 for r in opt.history[:k]) and opt.history[k].stage == 2


# ----------------------------------------------------------------------------- box
def test_stage2_box_eq11_by_hand():
    sp = Space.coerce(
        {
            "q": (1e-10, 1.0, "log10"),
            "a": (0.0, 10.0),
            "n": (-5.0, 5.0),
            "e": (0.0, 10.0),
            "z": (-1.0, 1.0),
        }
    )
    q = np.array([1e-4, 2.0, -2.0, 9.5, 0.0])
    lo, hi = stage2_box(sp, q, 0.15)
    expect_lo = [(math.log10(0.85e-4) + 10) / 10, 0.17, (-2.3 + 5) / 10, 0.8075, 0.5]
    expect_hi = [(math.log10(1.15e-4) + 10) / 10, 0.23, (-1.7 + 5) / 10, 1.0, 0.5]
    np.testing.assert_allclose(lo, expect_lo, atol=1e-12)
    np.testing.assert_allclose(hi, expect_hi, atol=1e-12)
    # the multiplicative box on a log10 scale is additive log10(1 ± α) / decades
    assert hi[0] - sp.to_unit(q)[0] == pytest.approx(math.log10(1.15) / 10)
    lo2, hi2 = stage2_box(sp, q, 0.15, min_halfwidth=0.05)
    np.testing.assert_allclose(lo2, [sp.to_unit(q)[0] - 0.05, 0.15, 0.25, 0.8075, 0.45])
    np.testing.assert_allclose(hi2, [sp.to_unit(q)[0] + 0.05, 0.25, 0.35, 1.0, 0.55])


def test_stage2_points_stay_in_the_box_and_candidates_grow_by_3d_minus_1():
    sp = {"a": (1.0, 10.0), "q": (1e-6, 1.0, "log10")}
    opt = run(sp, lambda x: (x[0] - 3.3) ** 2 + np.log10(x[1] / 1e-3) ** 2, budget=30, max_fe=3)
    s2 = [r for r in opt.history if r.stage == 2]
    assert s2, "stage 2 never started"
    lo, hi = opt.box
    q_star = opt.history[opt.switch_at - 1]  # incumbent at the switch …
    best1 = min((r for r in opt.history[: opt.switch_at] if r.ok), key=lambda r: r.value)
    lo_e, hi_e = stage2_box(opt.space, np.array(best1.x), 0.15)
    np.testing.assert_allclose(lo, lo_e)
    np.testing.assert_allclose(hi, hi_e)
    assert q_star.stage == 1
    for r in s2:
        assert np.all(np.array(r.u) >= lo - 1e-12) and np.all(np.array(r.u) <= hi + 1e-12)
    # Eq. 11 is asymmetric on a log10 scale (log10 0.85 ≠ −log10 1.15), so q* is not the
    # box centre: all 3^d children are candidates at first, then 3^d − 1 more per split.
    assert not np.allclose(0.5 * (lo + hi), best1.u)
    assert [r.info["n_candidates"] for r in s2[:4]] == [9, 16, 23, 30]


def test_stage2_faithful_fits_box_data_improved_fits_everything():
    sp = {"a": (1.0, 10.0), "b": (1.0, 10.0)}
    f = lambda x: (x[0] - 3.3) ** 2 + (x[1] - 6.1) ** 2  # noqa: E731
    opt = run(sp, f, budget=24, max_fe=3, seed=2)
    k = opt.switch_at
    X = opt.surrogate.fit_inputs[-1]
    # faithful: q* plus the stage-2 points, in box coordinates (q* unclipped → 0.5); the
    # last fit saw MAX_SM = 22 evaluations
    assert opt.max_sm == 22 and len(X) == 1 + (22 - k)
    np.testing.assert_allclose(X[0], [0.5, 0.5])
    assert np.all((X >= -1e-12) & (X <= 1 + 1e-12))
    opt2 = run(sp, f, budget=24, max_fe=3, seed=2, keep_stage1_data=True)
    assert len(opt2.surrogate.fit_inputs[-1]) == 22


# ----------------------------------------------------------------------------- AF and gain
def test_gain_is_realised_improvement_per_af():
    opt = run(BRANIN_SPACE, branin, budget=20, max_fe=100, max_af=6, seed=3)
    gains = {"EI": 0.0, "CBM": 0.0}
    best = opt.history[0].value
    for r in opt.history[1:7]:
        gains[r.acquisition] += max(0.0, best - r.value)
        best = min(best, r.value)
    assert [r.acquisition for r in opt.history[1:7]] == ["EI", "CBM"] * 3
    assert opt.gains == pytest.approx(gains)
    winner = "CBM" if gains["CBM"] > gains["EI"] else "EI"
    assert opt.chosen_af == winner
    assert {r.acquisition for r in opt.history[7:]} == {winner}


def test_max_af_switch_alternates_through_stage1_and_chooses_at_the_switch():
    opt = run(BRANIN_SPACE, branin, budget=30, max_fe=4, max_af="switch", seed=3)
    k = opt.switch_at
    assert k is not None and k > 12  # alternation went on past the faithful MAX_AF = 10
    s1 = opt.history[1:k]
    assert [r.acquisition for r in s1] == (["EI", "CBM"] * k)[: len(s1)]
    gains, best = {"EI": 0.0, "CBM": 0.0}, opt.history[0].value
    for r in s1:
        gains[r.acquisition] += max(0.0, best - r.value)
        best = min(best, r.value)
    assert opt.gains == pytest.approx(gains)
    winner = "CBM" if gains["CBM"] > gains["EI"] else "EI"
    assert opt.chosen_af == winner and {r.acquisition for r in opt.history[k:]} == {winner}


def test_first_choice_is_a_random_tie_break_among_symmetric_candidates():
    firsts = set()
    for seed in range(8):
        opt = tsbo({"a": (0.0, 1.0), "b": (0.0, 1.0)}, surrogate=CountingGP, seed=seed)
        opt.tell(opt.ask(), 1.0)
        firsts.add(tuple(opt.ask().u))
    assert firsts <= {(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)}
    assert len(firsts) > 1


# ----------------------------------------------------------------------------- MAX_SM
@pytest.mark.parametrize("freeze", ["hyperparameters", "full"])
def test_max_sm_freeze(freeze):
    opt = run(BRANIN_SPACE, branin, budget=14, max_sm=9, max_fe=100, seed=0, sm_freeze=freeze)
    gp = opt.surrogate
    # refit before proposal k+1 iff k ≤ MAX_SM evaluations are known (Alg. 2)
    assert gp.fit_sizes == list(range(1, 10))
    if freeze == "hyperparameters":
        assert gp.condition_sizes == [10, 11, 12, 13]
    else:
        assert gp.condition_sizes == []
    refit = [r.info["refit"] for r in opt.history[1:]]
    assert refit == [True] * 9 + [False] * 4
    hp_last_fit = opt.history[9].hyperparameters
    for r in opt.history[10:]:
        assert r.hyperparameters == hp_last_fit  # frozen
    assert [r.info["fit_n"] for r in opt.history[10:]] == [9] * 4


def test_first_stage2_proposal_refits_even_after_max_sm():
    opt = run({"a": (1.0, 2.0), "b": (1.0, 2.0)}, lambda x: 5.0, budget=12, max_fe=6, max_sm=3)
    s2 = [r for r in opt.history if r.stage == 2]
    assert s2[0].info["refit"] and not any(r.info["refit"] for r in s2[1:])


# ----------------------------------------------------------------------------- failures
def test_failures_imputed_pessimistically_and_never_reproposed():
    def f(x):
        if x[0] > 6.0:
            raise RuntimeError("diverged")
        return branin(x)

    opt = tsbo(BRANIN_SPACE, surrogate=CountingGP, budget=25, seed=4, max_fe=100)
    while not opt.done:
        t = opt.ask()
        try:
            opt.tell(t, f(t.x))
        except RuntimeError as exc:
            opt.tell(t, state="failed", reason=str(exc))
    failed = [r for r in opt.history if r.state == "failed"]
    assert failed and all(r.x[0] > 6.0 for r in failed)
    U = np.array([r.u for r in opt.history])
    dist = np.abs(U[:, None] - U[None]).max(-1) + np.eye(len(U))
    assert dist.min() > 1e-9  # no point proposed twice
    # In the last fit, each failed point carries the worst successful value
    X, y = opt.surrogate.fit_inputs[-1], opt.surrogate.fit_outputs[-1]
    ok_vals = [r.value for r in opt.history[: len(y)] if r.ok]
    for r in failed:
        i = r.number
        if i < len(y):
            np.testing.assert_allclose(X[i], r.u)
            assert y[i] == max(ok_vals)
    assert opt.best.value == min(ok_vals + [r.value for r in opt.history[len(y) :] if r.ok])


def test_all_failed_start_does_not_crash():
    opt = run({"a": (0.0, 1.0), "b": (0.0, 1.0)}, lambda x: math.nan, budget=6, seed=0)
    assert [r.state for r in opt.history] == ["failed"] * 6
    assert opt.best is None and opt.stage == 1


# ----------------------------------------------------------------------------- exhaustion
def test_degenerate_box_falls_back_to_random_candidates():
    # minimum exactly at the natural-units origin = the centre → Eq. 11 box has zero width
    sp = {"a": (-1.0, 1.0), "b": (-1.0, 1.0)}
    opt = run(sp, lambda x: float(np.sum(x**2)), budget=12, max_fe=3, seed=0)
    s2 = [r for r in opt.history if r.stage == 2]
    lo, hi = opt.box
    np.testing.assert_allclose(hi - lo, 0.0)
    assert s2 and {r.acquisition for r in s2} <= {"EI-fallback", "CBM-fallback"}
    assert s2[0].info["n_candidates"] == 200
    # fallback candidates are scored by a model of every evaluation, in unit coordinates
    assert all(r.info["refit"] for r in s2)
    np.testing.assert_allclose(opt.surrogate.fit_inputs[-1], [r.u for r in opt.history[:-1]])
    U = np.array([r.u for r in opt.history])
    assert len({tuple(u) for u in U}) == len(U)
    # the improved mode's half-width floor removes the degeneracy
    opt2 = run(sp, lambda x: float(np.sum(x**2)), budget=12, max_fe=3, min_box_halfwidth=0.02)
    assert not any("fallback" in (r.acquisition or "") for r in opt2.history)


# ----------------------------------------------------------------------------- resolution
@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    d=st.sampled_from([2, 3]),
    eps=st.sampled_from([1e-3, 0.01, 0.03]),
    max_fe=st.integers(2, 6),
    box=st.sampled_from([0.0, 0.02]),
    keep=st.booleans(),
    data=st.data(),
)
def test_min_resolution_never_proposes_within_eps_of_an_asked_point(
    seed, d, eps, max_fe, box, keep, data
):
    c = np.array(data.draw(st.lists(st.floats(0.0, 1.0), min_size=d, max_size=d)))
    sp = {f"x{i}": (0.0, 1.0) for i in range(d)}
    opt = run(
        sp,
        lambda x: float(np.sum((x - c) ** 2)),
        budget=25,
        seed=seed,
        max_fe=max_fe,
        min_resolution=eps,
        min_box_halfwidth=box,
        keep_stage1_data=keep,
    )
    assert len(opt.history) == 25
    assert min_pair_distance(opt.history) > eps


def test_without_min_resolution_the_same_runs_come_closer():
    # The check above has teeth: the paper's rule only excludes exact repeats, and pure
    # exploitation near a minimum refines below 0.03 (seed 5: two points 2e-9 apart).
    sp = {f"x{i}": (0.0, 1.0) for i in range(3)}
    for seed in range(6):
        c = np.random.default_rng(seed).random(3)
        f = lambda x, c=c: float(np.sum((x - c) ** 2))  # noqa: E731
        faithful = run(sp, f, budget=40, seed=seed, max_fe=5)
        assert min_pair_distance(faithful.history) < 0.03
        spaced = run(sp, f, budget=40, seed=seed, max_fe=5, min_resolution=0.03)
        assert min_pair_distance(spaced.history) > 0.03
        if seed == 5:
            assert min_pair_distance(faithful.history) < 1e-8


def test_min_resolution_exhaustion_falls_back_then_stops_clearly():
    # d = 1, ε = 0.2: the tree offers 0.5, 0.25, 0.75 (finer centres are within 0.2 of
    # those); random fallback points then fit only in [0, 0.05) and (0.95, 1], one each.
    opt = tsbo({"a": (0.0, 1.0)}, surrogate=CountingGP, budget=10, max_fe=100, min_resolution=0.2)
    with pytest.raises(ExhaustedError, match=r"min_resolution=0\.2 "):
        while not opt.done:
            t = opt.ask()
            opt.tell(t, (t.u[0] - 0.3) ** 2)
    u = [r.u[0] for r in opt.history]
    assert sorted(u[:3]) == [0.25, 0.5, 0.75]
    assert len(u) == 5 and all("fallback" in r.acquisition for r in opt.history[3:])
    assert sorted(v < 0.05 for v in u[3:]) == [False, True]
    assert min_pair_distance(opt.history) > 0.2


def test_records_carry_stage_acquisition_and_hyperparameters():
    res = minimize(
        branin,
        BRANIN_SPACE,
        "tsbo-tsp",
        budget=10,
        seed=0,
        max_fe=4,
        surrogate_options={"n_restarts": 0},
    )
    assert res.history[0].acquisition == "centre" and res.history[0].hyperparameters is None
    for r in res.history[1:]:
        assert r.stage in (1, 2) and r.acquisition in ("EI", "CBM")
        hp = r.hyperparameters
        assert hp["model"] == "tsp" and hp["dof"] == 15.0 and len(hp["length_scales"]) == 2
    assert res.to_json()  # strict JSON


def test_bad_options():
    with pytest.raises(ValueError, match="key 'mode': expected one of"):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, mode="fast")
    with pytest.raises(ValueError, match="key 'alpha': expected a number > 0 and < 1"):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, alpha=1.5)
    with pytest.raises(ValueError, match="sm_freeze"):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, sm_freeze="some")
    with pytest.raises(ValueError, match="unknown surrogate"):
        tsbo(BRANIN_SPACE, surrogate="svm")
    with pytest.raises(
        ValueError, match=r"key 'min_resolution': expected a number >= 0 and < 0\.25"
    ):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, min_resolution=0.3)
    with pytest.raises(ValueError, match="key 'tr_fe_units': expected one of"):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, tr_fe_units="natural-log")
    with pytest.raises(
        ValueError,
        match=r"key 'max_af': expected an integer >= 1 or 'switch', got a string \('always'\)",
    ):
        tsbo(BRANIN_SPACE, surrogate=CountingGP, max_af="always")


def test_modes_are_presets_of_six_options():
    names = (
        "keep_stage1_data",
        "min_box_halfwidth",
        "stage2_reserve",
        "min_resolution",
        "tr_fe_units",
        "max_af",
    )
    f = tsbo(BRANIN_SPACE, surrogate=CountingGP).options()
    assert [f[k] for k in names] == [False, 0.0, 0.0, 0.0, "natural", 10]
    i = tsbo(BRANIN_SPACE, surrogate=CountingGP, mode="improved").options()
    assert [i[k] for k in names] == [True, 0.02, 0.25, 0.0, "natural", "switch"]
    o = tsbo(
        BRANIN_SPACE, surrogate=CountingGP, mode="improved", stage2_reserve=0.0, max_af=4
    ).options()
    assert [o[k] for k in names] == [True, 0.02, 0.0, 0.0, "natural", 4]
    assert o["mode"] == "improved"


def test_defaults_are_the_papers_table_iii():
    """ν = 15, MAX_FE = 15, MAX_PE = 40, MAX_SM = 38, β = 0.01, α = 0.15, TR_FE = 0.01."""
    from kftune.bo import make_surrogate

    t = tsbo(BRANIN_SPACE)
    o = t.options()
    assert t.budget == 40 and o["surrogate"] == "tsp" and o["mode"] == "faithful"
    assert (o["max_fe"], o["max_sm"], o["beta"], o["alpha"], o["tr_fe"]) == (
        15,
        38,
        0.01,
        0.15,
        0.01,
    )
    tsp = make_surrogate("tsp")
    assert tsp.dof == 15.0 and not tsp.fit_dof


@pytest.mark.parametrize("method", ["tsbo-tsp", "tsbo-gp", "tsbo-robust"])
def test_huge_finite_values_do_not_break_the_surrogate(method):
    """A diverging objective that still returns a number (1e300): the surrogate sees it
    clipped (its variance would overflow), every AF value stays finite, no numerical
    warning, and the search still finds the minimum."""
    import warnings

    from kftune.optim import minimize

    def f(x):
        return 1e300 if x[0] > 0.7 else (x[0] - 0.3) ** 2 + (x[1] - 0.6) ** 2

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = minimize(f, {"a": (0.0, 1.0), "b": (0.0, 1.0)}, method, budget=25)
    assert any(r.value == 1e300 for r in res.history)
    assert all(np.isfinite(r.info["af_value"]) for r in res.history[1:])
    assert res.fun < 0.02  # as good as with a plain large value (10) there: 0.0028–0.017
