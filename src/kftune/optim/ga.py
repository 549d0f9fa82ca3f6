"""The genetic algorithm of the paper's comparison (Table IV), with MATLAB ``ga`` semantics.

Why not pymoo: pymoo's mating always applies crossover *and then* mutation to every
offspring and its survival is (μ + λ) truncation (``pymoo/core/mating.py``,
``FitnessSurvival``), so it cannot express MATLAB's "crossover fraction" — the share of the
non-elite children made by crossover *alone*, the rest by mutation *alone* — nor MATLAB's
generational replacement with elites. Hence this small GA, which follows MATLAB's
``stepGA`` generation by generation:

1. Generation 0: ``population_size`` uniform random points (``gacreationuniform``).
2. Each later generation of N individuals:
   * elites: the ``elite_count`` best individuals survive unchanged and are *not*
     re-evaluated (MATLAB reuses their scores);
   * ``n_xover = round(crossover_fraction · (N − elite_count))`` children (MATLAB's
     ``round``, halves away from zero: :func:`matlab_round`) by scattered crossover
     (``crossoverscattered``: each gene from one of two parents with p = ½);
   * ``n_mut = N − elite_count − n_xover`` children by Gaussian mutation;
   * parents: ``2·n_xover + n_mut`` of them, by rank fitness scaling (``fitscalingrank``:
     expectation ∝ 1/√rank) and stochastic-uniform selection (``selectionstochunif``: one
     random offset, equal steps along the expectation wheel), then shuffled (as ``stepGA``).

Paper settings (Table IV): N = 15, 15 generations, crossover fraction 0.8, "elite count
0.75". MATLAB's EliteCount is an integer; 0.75 is read as **one** elite (it rounds to 1, and
MATLAB's default ``ceil(0.05·N)`` is also 1 for N = 15). So each generation has 1 elite,
11 crossover and 3 mutation children, and the run costs 15 + 15·14 = 225 evaluations
(which is also 15·15, the figure usually quoted).

Documented differences from MATLAB: mutation is ``mutationgaussian``'s schedule (σ_k =
scale·(1 − shrink·k/G) of the range at generation k of G) floored at ``min_sigma`` (1 % of
the range) so that last-generation mutants are never clones of evaluated points, and
children are folded back into the bounds by reflection; and a child that copies a point
already evaluated, or an earlier child of its generation, is mutated (with the generation's
σ) until it is new. Scattered crossover copies a parent whenever all genes come from one
side, 2/2^d of the time — a quarter of the crossover children for d = 3 — and MATLAB
evaluates those copies again; here no evaluation is spent on a known point and a failed
point is never proposed again. (MATLAB uses
``mutationadaptfeasible`` on bounded problems; its direction generator is not documented
well enough to reproduce.) All operators act in the unit cube, i.e. on log10 for log-scaled
parameters. Failed evaluations score +inf, so they rank last.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, ClassVar

import numpy as np

from kftune.errors import SettingWarning
from kftune.optim.base import SAME_POINT_ATOL, Optimizer, Proposal, Trial


class GeneticAlgorithm(Optimizer):
    """MATLAB-style GA (see the module docstring).

    Args:
        space, seed: as for every optimiser.
        budget: evaluations; default 225 = N + G·(N − elites) with the paper's settings.
        population_size: N (paper: 15).
        generations: G bred generations after the initial one; default from the budget,
            ``ceil((budget − N)/(N − elites))`` (15 for the paper).
        crossover_fraction: share of the non-elite children made by crossover (paper: 0.8).
        elite_count: elites per generation; a float in (0, 1) (the paper's 0.75) is rounded
            to the nearest integer but at least 1.
        mutation_scale, mutation_shrink: MATLAB ``mutationgaussian`` arguments (1, 1).
        min_sigma: floor of the mutation standard deviation in the unit cube.
    """

    method: str = "ga"
    default_budget: ClassVar[int] = 225

    def __init__(
        self,
        space: Any,
        *,
        budget: int | None = None,
        seed: int = 0,
        population_size: int = 15,
        generations: int | None = None,
        crossover_fraction: float = 0.8,
        elite_count: float = 0.75,
        mutation_scale: float = 1.0,
        mutation_shrink: float = 1.0,
        min_sigma: float = 0.01,
    ) -> None:
        super().__init__(space, budget=budget, seed=seed)
        if not isinstance(population_size, (int, np.integer)) or population_size < 2:
            raise ValueError(f"population_size must be an integer >= 2, got {population_size!r}")
        n_elite = max(1, matlab_round(elite_count)) if 0 < elite_count < 1 else int(elite_count)
        if n_elite != elite_count and not 0 < elite_count < 1:
            raise ValueError(f"elite_count must be an integer or in (0, 1), got {elite_count!r}")
        if not 0 <= n_elite < population_size:
            raise ValueError(
                f"elite_count must be below population_size={population_size}, got {elite_count}"
            )
        if not 0.0 <= crossover_fraction <= 1.0:
            raise ValueError(f"crossover_fraction must be in [0, 1], got {crossover_fraction!r}")
        if mutation_scale <= 0 or not 0 <= mutation_shrink <= 1 or min_sigma < 0:
            raise ValueError(
                "mutation_scale must be > 0, mutation_shrink in [0, 1] and min_sigma >= 0; got "
                f"{mutation_scale!r}, {mutation_shrink!r}, {min_sigma!r}"
            )
        self.population_size = int(population_size)
        self.n_elite = n_elite
        n_kids = self.population_size - n_elite
        self.n_xover = matlab_round(crossover_fraction * n_kids)
        self.n_mut = n_kids - self.n_xover
        if generations is None:
            generations = max(0, math.ceil((self.budget - self.population_size) / n_kids))
        if not isinstance(generations, (int, np.integer)) or generations < 0:
            raise ValueError(f"generations must be a non-negative integer, got {generations!r}")
        self.generations = int(generations)
        if self.generations == 0:
            warnings.warn(
                f"GA: with a budget of {self.budget} evaluations and a population of "
                f"{self.population_size}, no generation is bred: this GA is a random search "
                "(the paper's: 225 evaluations, 15 generations)",
                SettingWarning,
                stacklevel=2,
            )
        self.crossover_fraction = float(crossover_fraction)
        self.mutation_scale = float(mutation_scale)
        self.mutation_shrink = float(mutation_shrink)
        self.min_sigma = float(min_sigma)
        self._elite_count_option = elite_count
        # Current generation: points (N, d) and their scores (+inf until told / if failed).
        self._generation = 0
        self._pop = self.rng.random((self.population_size, self.space.dim))
        self._scores = np.full(self.population_size, np.inf)
        self._origin = ["initial"] * self.population_size
        self._next = 0  # index into _pop of the next individual to hand out
        self._told = 0  # individuals of the current generation told so far

    def options(self) -> dict[str, Any]:
        return {
            "population_size": self.population_size,
            "generations": self.generations,
            "crossover_fraction": self.crossover_fraction,
            "elite_count": self._elite_count_option,
            "mutation_scale": self.mutation_scale,
            "mutation_shrink": self.mutation_shrink,
            "min_sigma": self.min_sigma,
        }

    def _exhausted(self) -> bool:
        return self._generation > self.generations or (
            self._generation == self.generations and self._told >= self.population_size
        )

    def _n_proposable(self) -> int | None:
        """The rest of the generation; a whole one once the last is told (ask(n))."""
        if self._next < self.population_size:
            return self.population_size - self._next
        return self.population_size - self.n_elite if self._told >= self.population_size else 0

    def _propose(self) -> Proposal:
        if self._next >= self.population_size:
            self._breed()
            self._told = self._next  # the elites keep their scores
        i = self._next
        self._next += 1
        return Proposal(
            u=self._pop[i].copy(),
            stage=self._generation,
            acquisition=self._origin[i],
            info={"generation": self._generation, "index": i},
        )

    def _observe(self, trial: Trial, value: float | None) -> None:
        # by the individual's index, so a generation's results may come in any order
        self._scores[int(trial.info["index"])] = np.inf if value is None else value
        self._told += 1

    # ------------------------------------------------------------------ MATLAB stepGA
    def _breed(self) -> None:
        """Replace the population by the next generation (elites first, their scores kept)."""
        self._generation += 1
        rng, d = self.rng, self.space.dim
        n_parents = 2 * self.n_xover + self.n_mut
        expectation = rank_scaling(self._scores, n_parents)
        parents = stochastic_uniform_selection(expectation, n_parents, rng)
        parents = parents[rng.permutation(n_parents)]
        order = np.argsort(self._scores, kind="stable")
        elites = order[: self.n_elite]
        new_pop = [self._pop[elites]]
        new_scores = [self._scores[elites]]
        # Scattered crossover: gene j from the first parent where rand > 0.5.
        p1 = self._pop[parents[0 : 2 * self.n_xover : 2]]
        p2 = self._pop[parents[1 : 2 * self.n_xover : 2]]
        mask = rng.random((self.n_xover, d)) > 0.5
        new_pop.append(np.where(mask, p1, p2))
        # Gaussian mutation with MATLAB's shrinking schedule, floored, reflected into [0, 1].
        sigma = self.mutation_scale * (
            1.0 - self.mutation_shrink * self._generation / max(self.generations, 1)
        )
        sigma = max(sigma, self.min_sigma)
        pm = self._pop[parents[2 * self.n_xover :]]
        new_pop.append(reflect_unit(pm + sigma * rng.standard_normal(pm.shape)))
        new_scores.append(np.full(self.population_size - self.n_elite, np.inf))
        self._pop = np.vstack(new_pop)
        self._scores = np.concatenate(new_scores)
        self._origin = (
            ["elite"] * self.n_elite + ["crossover"] * self.n_xover + ["mutation"] * self.n_mut
        )
        self._next = self.n_elite  # elites are not re-evaluated
        self._mutate_copies(sigma)

    def _mutate_copies(self, sigma: float) -> None:
        """Mutate every child that repeats an evaluated point or an earlier child; its
        origin then reads e.g. ``"crossover+mutation"``."""
        known = [np.asarray(r.u) for r in self._history]
        for i in range(self.n_elite, self.population_size):
            earlier = np.asarray([*known, *self._pop[self.n_elite : i]])
            while np.min(np.max(np.abs(earlier - self._pop[i]), axis=1)) <= SAME_POINT_ATOL:
                self._pop[i] = reflect_unit(
                    self._pop[i] + sigma * self.rng.standard_normal(self.space.dim)
                )
                if not self._origin[i].endswith("+mutation"):
                    self._origin[i] += "+mutation"


def matlab_round(x: float) -> int:
    """MATLAB's ``round`` of a non-negative number: halves away from zero (2.5 → 3), where
    Python's ``round`` takes halves to even (2.5 → 2). Exact for every float: ``x − ⌊x⌋`` is
    computed without rounding error, so no ``x + 0.5`` carries a value just below a half
    over it."""
    if not x >= 0:
        raise ValueError(f"expected a number >= 0, got {x!r}")
    whole = math.floor(x)
    return int(whole) + (x - whole >= 0.5)


def rank_scaling(scores: np.ndarray, n_parents: int) -> np.ndarray:
    """MATLAB ``fitscalingrank``: expectation ∝ 1/√rank (rank 1 = lowest score), summing to
    ``n_parents``. Ties are ranked in index order (stable sort, as MATLAB's ``sort``).

    Args:
        scores: (N,) objective values (+inf allowed).
        n_parents: number of parents to be selected.

    Returns:
        (N,) expected number of times each individual is selected.
    """
    order = np.argsort(scores, kind="stable")
    expectation = np.empty(len(scores))
    expectation[order] = 1.0 / np.sqrt(np.arange(1, len(scores) + 1))
    return n_parents * expectation / expectation.sum()


def stochastic_uniform_selection(
    expectation: np.ndarray, n_parents: int, rng: np.random.Generator
) -> np.ndarray:
    """MATLAB ``selectionstochunif``: walk the cumulative expectation with equal steps from a
    single random offset, so individual i is picked ⌊e_i⌋ or ⌈e_i⌉ times.

    Returns:
        (n_parents,) indices into the population.
    """
    wheel = np.cumsum(expectation) / n_parents
    wheel[-1] = 1.0  # guard round-off so every position finds a slot
    step = 1.0 / n_parents
    positions = rng.random() * step + step * np.arange(n_parents)
    return np.searchsorted(wheel, positions, side="right")


def reflect_unit(u: np.ndarray) -> np.ndarray:
    """Fold points back into [0, 1] by mirror reflection at the bounds (any distance)."""
    v = np.mod(u, 2.0)
    return np.where(v > 1.0, 2.0 - v, v)
