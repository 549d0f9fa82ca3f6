"""The MATLAB-style GA: its operators against their definitions, and the generation layout
of the paper's settings (Table IV)."""

from __future__ import annotations

from decimal import ROUND_HALF_UP, Decimal

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.optim.ga import (
    GeneticAlgorithm,
    matlab_round,
    rank_scaling,
    reflect_unit,
    stochastic_uniform_selection,
)


def test_rank_scaling_is_inverse_sqrt_rank():
    scores = np.array([3.0, 1.0, np.inf, 2.0])
    e = rank_scaling(scores, n_parents=25)
    raw = np.array([1 / np.sqrt(3), 1.0, 1 / np.sqrt(4), 1 / np.sqrt(2)])
    np.testing.assert_allclose(e, 25 * raw / raw.sum())


def test_stochastic_uniform_selection_floor_ceil_and_mean():
    rng = np.random.default_rng(1)
    e = rank_scaling(rng.random(15), 25)
    counts_sum = np.zeros(15)
    n_rep = 4000
    for _ in range(n_rep):
        idx = stochastic_uniform_selection(e, 25, rng)
        assert idx.shape == (25,)
        c = np.bincount(idx, minlength=15)
        # Each individual is chosen floor(e_i) or ceil(e_i) times (equal-step wheel).
        assert np.all(c >= np.floor(e) - 1e-9) and np.all(c <= np.ceil(e) + 1e-9)
        counts_sum += c
    # Unbiased: the average count equals the expectation (Monte Carlo, ±0.05).
    np.testing.assert_allclose(counts_sum / n_rep, e, atol=0.05)


def test_reflect_unit():
    got = reflect_unit(np.array([-0.2, 1.3, 2.5, 0.4, -3.1]))
    np.testing.assert_allclose(got, [0.2, 0.7, 0.5, 0.4, 0.9])


def test_paper_settings_generation_layout():
    ga = GeneticAlgorithm({"a": (0, 1), "b": (0, 1), "c": (0, 1)}, seed=3)
    assert (ga.budget, ga.population_size, ga.generations) == (225, 15, 15)
    assert (ga.n_elite, ga.n_xover, ga.n_mut) == (1, 11, 3)
    prev_pop = None
    by_gen: dict[int, list] = {}
    while not ga.done:
        t = ga.ask()
        by_gen.setdefault(t.stage, []).append(t)
        ga.tell(t, float(np.sum((t.u - 0.3) ** 2)))
    assert ga.n_evals == 225
    assert [len(by_gen[g]) for g in range(16)] == [15] + [14] * 15
    assert [t.acquisition for t in by_gen[0]] == ["initial"] * 15
    for g in range(1, 16):
        origins = [t.acquisition.removesuffix("+mutation") for t in by_gen[g]]
        assert origins == ["crossover"] * 11 + ["mutation"] * 3
    # Crossover children take every gene from some individual of the previous generation
    # (scattered crossover copies genes, it never blends them) — except the copies of a
    # known point, which are mutated and say so.
    hist = ga.history
    copies = 0
    for g in range(1, 16):
        prev_pop = _population(hist, by_gen, g - 1)
        for t in by_gen[g][:11]:
            if t.acquisition == "crossover+mutation":
                copies += 1
                continue
            for j in range(3):
                assert np.any(np.isclose(prev_pop[:, j], t.u[j], rtol=0, atol=0))
    # All genes from one parent: 2/2^3 of the crossovers, plus identical parents.
    assert 0.15 < copies / (15 * 11) < 0.6


def _population(hist, by_gen, g):
    """Points of generation g including its elite (the best of all before it)."""
    pts = [t.u for t in by_gen[g]]
    if g > 0:
        n_before = 15 + 14 * (g - 1)
        best = min(hist[:n_before], key=lambda r: r.value)
        pts.append(np.array(best.u))
    return np.array(pts)


def test_elite_is_kept_so_generation_best_never_worsens():
    ga = GeneticAlgorithm({"a": (0, 1), "b": (0, 1)}, seed=0)
    vals = []
    while not ga.done:
        t = ga.ask()
        if t.acquisition != "initial" and t.info["index"] == ga.n_elite:
            # A new generation started: its elite carries the best score seen so far.
            assert ga._scores[0] == min(vals)
        v = float(np.sum((t.u - 0.7) ** 2))
        ga.tell(t, v)
        vals.append(v)
    assert ga._scores.min() == min(vals)
    assert min(vals) < 1e-2


def test_failures_rank_last_and_run_goes_on():
    ga = GeneticAlgorithm({"a": (0, 1)}, seed=0, budget=60)
    while not ga.done:
        t = ga.ask()
        ga.tell(t, None if t.u[0] > 0.8 else float(t.u[0]))
    assert ga.n_evals == 60
    assert ga.best.value < 0.05
    assert any(r.state == "failed" for r in ga.history)


def test_bad_options():
    with pytest.raises(ValueError, match=r"crossover_fraction"):
        GeneticAlgorithm({"a": (0, 1)}, crossover_fraction=1.5)
    with pytest.raises(ValueError, match=r"elite_count"):
        GeneticAlgorithm({"a": (0, 1)}, elite_count=1.5)
    with pytest.raises(ValueError, match=r"population_size"):
        GeneticAlgorithm({"a": (0, 1)}, population_size=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_point_is_evaluated_twice_and_failed_points_are_not_reproposed(seed):
    """Scattered crossover copies a parent a quarter of the time in 3-d; those copies are
    mutated into new points, so all 225 evaluations are distinct."""
    from kftune.optim import minimize

    space = {"a": (-5.0, 10.0), "q": (1e-10, 1.0, "log10"), "c": (0.0, 1.0)}

    def f(x):
        if x[0] > 6.0:
            raise RuntimeError("unstable region")
        return float((x[0] - 1) ** 2 / 10 + (np.log10(x[1]) + 4) ** 2 + (x[2] - 0.3) ** 2)

    res = minimize(f, space, "ga", seed=seed)
    u = np.array([r.u for r in res.history])
    assert len(u) == 225 and res.n_failed > 0
    gaps = np.max(np.abs(u[:, None, :] - u[None, :, :]), axis=2)
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() > 1e-9


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.floats(min_value=0.0, max_value=1e6, allow_nan=False),
        st.integers(0, 10_000).map(lambda k: k + 0.5),  # exact halves
        st.integers(0, 10_000).map(lambda k: np.nextafter(k + 0.5, 0.0)),  # just below
    )
)
def test_matlab_round_takes_halves_away_from_zero(x):
    """Against decimal's ROUND_HALF_UP on the exact binary value (MATLAB's ``round``)."""
    expected = int(Decimal(float(x)).quantize(Decimal(1), rounding=ROUND_HALF_UP))
    assert matlab_round(float(x)) == expected


@pytest.mark.parametrize(
    ("population", "fraction", "n_xover"),
    [(14, 0.5, 7), (6, 0.5, 3), (16, 0.3, 5), (16, 0.7, 11), (15, 0.8, 11)],
)
def test_crossover_children_are_rounded_as_matlab_does(population, fraction, n_xover):
    """MATLAB ``stepGA``: round(0.5 · 13) = 7 crossover children for a population of 14
    with one elite; Python's round would give 6."""
    ga = GeneticAlgorithm({"a": (0, 1)}, population_size=population, crossover_fraction=fraction)
    assert ga.n_elite == 1
    assert (ga.n_xover, ga.n_mut) == (n_xover, population - 1 - n_xover)


def test_a_budget_that_breeds_no_generation_warns():
    """A GA of 10 evaluations is 10 random points: compare called it "GA" in every table."""
    from kftune.errors import SettingWarning
    from kftune.optim import make_optimizer

    with pytest.warns(SettingWarning, match=r"no generation is bred: this GA is a random"):
        make_optimizer("ga", {"x": (0.0, 1.0)}, budget=10)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingWarning)
        make_optimizer("ga", {"x": (0.0, 1.0)}, budget=16)  # one (partial) generation
