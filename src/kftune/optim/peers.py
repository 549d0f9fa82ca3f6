"""Adapters to optimisers people already use, for honest comparisons in ``benchmarks/``.

* ``optuna-tpe`` — Optuna's TPESampler with its defaults (seeded);
* ``optuna-gp`` — Optuna's GPSampler (seeded); it needs PyTorch, and constructing the
  adapter without PyTorch raises :class:`PeerUnavailableError` (an ``ImportError``) at once
  rather than failing after the start-up trials;
* ``cma`` — CMA-ES from the ``cma`` package, started at the centre of the unit cube with
  σ0 = 0.25, box-constrained to [0, 1]^d, restarted from a random point (same σ0) whenever
  it meets one of its own termination criteria before the budget is used.

All three see the unit cube, so log10 parameters are searched log-uniformly (equivalent to
Optuna's ``log=True``). Failed evaluations are reported to Optuna as ``TrialState.FAIL``
(its samplers then ignore them) and to CMA-ES as a pessimistic value (worst value seen + 1 +
|worst|; 1e10 before any success), because CMA-ES must rank every member of a generation.

``cma`` draws from NumPy's *global* random state; the adapter keeps its own copy of that
state and swaps it in only around ``cma`` calls, so the objective's own use of
``np.random`` cannot change the search (needed for exact resume).
"""

from __future__ import annotations

import importlib.util
from typing import Any, ClassVar

import numpy as np

from kftune.errors import KftuneError
from kftune.optim.base import Optimizer, Proposal, Trial


class PeerUnavailableError(KftuneError, ImportError):
    """A peer optimiser's package (or its PyTorch dependency) is not installed."""


def _require(module: str, method: str, hint: str) -> None:
    if importlib.util.find_spec(module) is None:
        raise PeerUnavailableError(
            f"method {method!r} needs the package {module!r}, which is not installed ({hint})"
        )


class _OptunaAdapter(Optimizer):
    """Common part of the Optuna adapters: an in-memory Optuna study driven by ask/tell.

    Optuna's samplers never see the number of trials, so the proposals do not depend on
    the budget."""

    budget_independent: ClassVar[bool] = True

    def __init__(self, space: Any, *, budget: int | None = None, seed: int = 0) -> None:
        super().__init__(space, budget=budget, seed=seed)
        _require("optuna", self.method, "pip install optuna")
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        self._optuna = optuna
        # Optuna seeds must fit in 32 bits; derive one from our seed sequence.
        sampler_seed = int(self.seed_sequence.generate_state(1)[0])
        self._study = optuna.create_study(
            direction="minimize", sampler=self._make_sampler(sampler_seed)
        )
        self._dists: dict[str, optuna.distributions.BaseDistribution] = {
            f"u{i}": optuna.distributions.FloatDistribution(0.0, 1.0) for i in range(self.space.dim)
        }
        self._otrials: dict[int, Any] = {}  # our trial number → Optuna's trial

    def _make_sampler(self, seed: int) -> Any:
        raise NotImplementedError

    def _propose(self) -> Proposal:
        # Optuna keeps asked-but-not-told trials as RUNNING, so a batch is its own
        otrial = self._study.ask(self._dists)
        self._otrials[self._n_asked] = otrial  # the number the base class gives this trial
        u = np.array([otrial.params[f"u{i}"] for i in range(self.space.dim)])
        return Proposal(u=u, acquisition=self.method)

    def _observe(self, trial: Trial, value: float | None) -> None:
        otrial = self._otrials.pop(trial.number)
        if value is None:
            self._study.tell(otrial, state=self._optuna.trial.TrialState.FAIL)
        else:
            self._study.tell(otrial, value)


class OptunaTPE(_OptunaAdapter):
    """Optuna's Tree-structured Parzen Estimator with default settings."""

    method: str = "optuna-tpe"

    def _make_sampler(self, seed: int) -> Any:
        return self._optuna.samplers.TPESampler(seed=seed)


class OptunaGP(_OptunaAdapter):
    """Optuna's Gaussian-process sampler (needs PyTorch)."""

    method: str = "optuna-gp"

    def __init__(self, space: Any, *, budget: int | None = None, seed: int = 0) -> None:
        _require("torch", self.method, "Optuna's GPSampler needs PyTorch: pip install torch")
        super().__init__(space, budget=budget, seed=seed)

    def _make_sampler(self, seed: int) -> Any:
        return self._optuna.samplers.GPSampler(seed=seed)


class CMAES(Optimizer):
    """CMA-ES (``cma`` package) in the unit cube; see the module docstring.

    Args:
        sigma0: initial step size in the unit cube.
        popsize: population size; ``None`` → cma's default 4 + ⌊3 ln d⌋.
    """

    method: str = "cma"
    #: ``cma`` is never told the budget (no ``maxfevals``); its own termination criteria
    #: and the restarts do not depend on it.
    budget_independent: ClassVar[bool] = True

    def __init__(
        self,
        space: Any,
        *,
        budget: int | None = None,
        seed: int = 0,
        sigma0: float = 0.25,
        popsize: int | None = None,
    ) -> None:
        super().__init__(space, budget=budget, seed=seed)
        _require("cma", self.method, "pip install cma")
        if not sigma0 > 0:
            raise ValueError(f"sigma0 must be positive, got {sigma0!r}")
        self.sigma0 = float(sigma0)
        self.popsize = popsize
        self._np_state = np.random.RandomState(
            int(self.seed_sequence.generate_state(1)[0])
        ).get_state()
        self._restarts = 0
        self._es = self._new_es(np.full(self.space.dim, 0.5))
        self._asked: list[np.ndarray] = []  # the current generation
        self._batch: list[np.ndarray] = []  # its points not handed out yet
        self._values: dict[int, float | None] = {}  # index in the generation → value
        self._worst = -np.inf

    def options(self) -> dict[str, Any]:
        return {"sigma0": self.sigma0, "popsize": self.popsize}

    def _with_own_np_state(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        # cma uses NumPy's legacy global RNG; swapping states is the point here.
        saved = np.random.get_state()  # noqa: NPY002
        np.random.set_state(self._np_state)  # noqa: NPY002
        try:
            return fn(*args, **kwargs)
        finally:
            self._np_state = np.random.get_state()  # noqa: NPY002
            np.random.set_state(saved)  # noqa: NPY002

    def _new_es(self, x0: np.ndarray) -> Any:
        import cma

        # cma treats seed 0/None as "use the clock"; derive a positive one.
        cma_seed = 1 + int(self.rng.integers(2**31 - 2))
        opts: dict[str, Any] = {"bounds": [0.0, 1.0], "seed": cma_seed, "verbose": -9}
        if self.popsize is not None:
            opts["popsize"] = int(self.popsize)
        return self._with_own_np_state(cma.CMAEvolutionStrategy, list(x0), self.sigma0, opts)

    def _n_proposable(self) -> int | None:
        """The rest of the generation; a new one only once the last is told (ask(n))."""
        if self._batch:
            return len(self._batch)
        return self._es.popsize if len(self._values) == len(self._asked) else 0

    def _propose(self) -> Proposal:
        if not self._batch:
            if self._with_own_np_state(self._es.stop):
                self._restarts += 1
                self._es = self._new_es(self.rng.random(self.space.dim))
            asked = self._with_own_np_state(self._es.ask)
            self._asked = [np.asarray(s, dtype=float) for s in asked]
            self._batch = list(self._asked)
            self._values = {}
        index = len(self._asked) - len(self._batch)
        u = self._batch.pop(0)
        return Proposal(
            u=np.clip(u, 0.0, 1.0),
            stage=self._restarts,
            acquisition="cma",
            info={"generation": int(self._es.countiter), "index": index},
        )

    def _observe(self, trial: Trial, value: float | None) -> None:
        if value is not None:
            self._worst = max(self._worst, value)
        self._values[int(trial.info["index"])] = value  # a generation told in any order
        if not self._batch and len(self._values) == len(self._asked):
            fallback = self._worst + 1.0 + abs(self._worst) if np.isfinite(self._worst) else 1e10
            told = [self._values[i] for i in range(len(self._asked))]
            f = [fallback if v is None else v for v in told]
            self._with_own_np_state(self._es.tell, self._asked, f)
