"""Two-Stage Bayesian Optimisation (paper Sec. IV; original algorithm: Torun et al.,
IEEE TVLSI 2018), behind the ask/tell interface.

The algorithm, in the unit cube ``[0, 1]^d`` (log10 parameters are linear there):

* **Start**: evaluate the centre; split the root box into 2^d children (Alg. 1, first lines).
* **Stage 1, fast exploration** (Alg. 1). Candidates are the centres of all current leaves
  of the partition tree whose centre has not been evaluated. Each iteration fits the
  surrogate on all data, scores every candidate with the acquisition function (AF), evaluates
  the best candidate and splits its leaf into 2^d children (every side halved), so the
  leaf list grows by 2^d − 1 per iteration.
* **Acquisition choice**: EI and CBM (paper Eqs. 8–9) alternate, EI first, for the first
  ``max_af`` AF-chosen iterations; afterwards the one with the larger *gain* is used to the
  end of the run (stage 2 included). If stage 1 ends before ``max_af`` iterations (always,
  with ``max_af="switch"``), the choice is made at the switch with the gains gathered so far.
* **Switch** (Eq. 10): a counter n is incremented after every stage-1 evaluation after which
  the incumbent q* moved by less than ``TR_FE = tr_fe·‖q*‖`` (natural units, Euclidean; an
  incumbent that did not move at all always counts, so q* = 0 cannot block the switch) and
  reset otherwise; stage 2 starts once n reaches ``max_fe``. (``tr_fe_units="unit-cube"``:
  ``‖Δu*‖ < tr_fe·√d`` instead.)
* **Stage 2, pure exploitation** (Alg. 2, Eq. 11): the box ``[(1−α)q*, (1+α)q*]`` in natural
  units — additive ``log10(1∓α)`` in log10 coordinates — clipped to the bounds, split into
  3^d boxes; then the same loop, with 3^d splits (the centre child of a split keeps the
  evaluated centre, so 3^d − 1 new candidates per iteration).
* **Surrogate freeze**: after ``max_sm`` evaluations the surrogate's hyperparameters are no
  longer re-optimised (see ``sm_freeze``). Stop after ``max_pe`` = ``budget`` evaluations.

Decisions where the paper is silent (each is tested in ``tests/test_optim_tsbo.py``):

``max_af`` (faithful default 10)
    Table III does not give MAX_AF. 10 AF-chosen iterations give each AF five turns and the
    choice is made before the earliest possible switch (stage 1 lasts at least ``max_fe`` =
    15 AF-chosen iterations), so stage 2 always runs with the chosen AF. ``"switch"``
    (improved mode) alternates through all of stage 1 and chooses at the switch: five turns
    each decide nothing reliable (the first improvements are large and mostly luck: one
    early step can fix the AF for the rest of the run), and alternating keeps EI's
    exploration in stage 1.
*gain*
    The realised improvement of the incumbent credited to the AF that chose the point:
    ``gain_a = Σ max(0, y*_before − y)`` over the evaluations AF ``a`` chose (a failed
    evaluation gains 0). The larger total wins; a tie (e.g. both 0) goes to EI. Realised
    improvements are in the objective's units for both AFs, so they compare directly,
    unlike the AF values themselves (EI is an expectation, CBM a bound).
EI ranking
    Candidates are ranked by ``log EI`` when ``kftune.bo.acquisition`` provides it: the same
    argmax as EI wherever EI is representable, but far-away candidates whose EI underflows
    to 0 stay ordered instead of tying.
Ties
    Candidates whose AF value is within 1e-9 (relative) of the best are tied; the seeded
    RNG picks one (the first iteration, where all 2^d candidates are symmetric, needs this).
TR_FE units (``tr_fe_units``)
    Faithful: ``‖q*_new − q*_old‖ < tr_fe·‖q*_new‖`` in natural units, as the paper writes
    it. On log10 parameters spanning decades the norm is dominated by the largest component
    (UKF: q_r ≈ 0.2 against q_vx, q_vy ≈ 1e-8), so moves of the small ones never count as
    moves and the switch depends on one parameter. ``"unit-cube"`` (improved mode):
    ``‖u*_new − u*_old‖ < tr_fe·√d``, 1 % of the unit cube's diagonal — invariant to units
    and offsets (the cube's origin, unlike q = 0, means nothing, so not ``tr_fe·‖u*‖``).
Minimum resolution (``min_resolution`` = ε)
    Faithful: 0 — only exact repeats (1e-9) are excluded, so pure exploitation (CBM with
    β = 0.01, or stage 2) keeps splitting the incumbent's leaf and spends evaluations on
    points ever closer to it. With ε > 0 no candidate within ε (max-norm, unit cube,
    inclusive) of any asked point is proposed — tree candidates are filtered, fallback
    points too — so the leaves near an evaluated point stop yielding candidates and the AF
    must look elsewhere. Improved: ε = 1e-3, a
    sixth of the paper's stage-2 half-width on the default 10-decade log space (log10(1.15)
    /10 ≈ 0.006) and a twentieth of the improved box floor (0.02), so stage 2 still refines
    three 3^d levels inside its box; on a 10-decade axis 1e-3 is a 2.3 % change of q.
Stage 1 exhausting the budget
    In the faithful mode nothing is reserved: if the switch criterion has not fired when the
    budget is used, the run ends in stage 1 (Alg. 1 has no budget test; Alg. 2 then runs zero
    iterations). ``stage2_reserve`` (improved mode) forces the switch when only that share
    of the budget is left.
Stage-2 box
    Eq. 11 per coordinate, clipped to [0, 1]. On a linear scale with q*_i = 0 the box has zero
    width in that coordinate (all candidates share it) — the original's known weak spot,
    kept in the faithful mode; ``min_box_halfwidth`` (improved mode) widens every side to at
    least that half-width in the unit cube. If clipping moves the box off-centre, q* is no
    longer a box centre and the root centre becomes a candidate like any other.
Stage-2 data
    Faithful: the stage-2 surrogate sees only q* and the stage-2 evaluations, in the box's
    own normalised coordinates (stage 2 is a fresh TSBO on the box started from its evaluated
    centre; the original drops the stage-1 data). Zero-width coordinates map to 0.5.
    ``keep_stage1_data`` (improved mode) fits on every evaluation in global coordinates.
MAX_SM freeze (``sm_freeze``)
    ``"hyperparameters"`` (default): after ``max_sm`` evaluations the hyperparameters are
    frozen but the model is still *conditioned* on new data (``Surrogate.condition``).
    Reason: Alg. 2 says the tSP "is no more retrained", and in GPML (the paper's toolbox)
    training is the hyperparameter optimisation (``minimize`` on the NLML), while every
    prediction call conditions on the data passed to it; the freeze exists to save the
    training cost, and conditioning costs nothing by comparison. ``"full"`` keeps the model
    exactly as last fitted (new points are ignored) for those who read Alg. 2 literally.
    The refit counter is the total number of evaluations n: the model is refitted before a
    proposal iff n ≤ ``max_sm`` (Alg. 2: "if n_iter ≤ MAX_SM, train"), except that the
    first stage-2 proposal always fits, since stage 2 changes the data and coordinates.
Failed evaluations
    Imputed with a pessimistic value for the surrogate: the worst successful value in the
    surrogate's data (in the whole run if that has none; 0 if nothing succeeded yet). The
    imputation is recomputed at every fit, so it follows the data's scale. The failed point
    is never proposed again: its leaf is split like any evaluated leaf and candidates within
    1e-9 (unit cube, max-norm) of any asked point are removed. The incumbent ignores failures.
Huge values
    Finite values beyond ±1e100 (a diverging objective that still returns a number) are
    clipped to ±1e100 for the surrogate, whose variance in the units of y would otherwise
    overflow to inf and turn every AF value into NaN; the record keeps the true value.
All candidates exhausted
    Only possible with degenerate boxes, or when ε has removed every candidate. Then
    ``100·d`` uniform random points over the whole unit cube (from the seeded RNG; with
    ε > 0 those within ε of an asked point are dropped and the draw repeated, up to 100
    times) are scored with the current AF instead, by a surrogate refitted on every
    evaluation in unit-cube coordinates (box coordinates cannot tell points apart along a
    zero-width side); the record's acquisition reads e.g. ``"EI-fallback"``. If no draw
    leaves a point, ``ask`` raises :class:`~kftune.optim.base.ExhaustedError` — each asked
    point excludes a max-norm ball of volume (2ε)^d, so this needs n ≳ (2ε)^−d evaluations
    (500^d at ε = 1e-3).

Modes: ``mode="faithful"`` (default) is the paper as above. ``mode="improved"`` sets
``keep_stage1_data=True``, ``min_box_halfwidth=0.02``, ``stage2_reserve=0.25`` and
``max_af="switch"`` (EI and CBM alternate through the whole of stage 1; the one with the
larger gain is fixed at the switch). ``min_resolution`` (no candidate within ε of an asked
point) and ``tr_fe_units="unit-cube"`` are options, off in both presets. The improved
preset beats the faithful one, paired by seed, on the synthetic suite and on the UKF
problem, also on seeds it was not chosen on; ε and the unit-cube TR_FE did not help and
stay off (BENCHMARKS.md: "Optimisers on known functions", "Tuning the sideslip UKF", and
the ablation in "Moved from module docstrings", "kftune.optim.tsbo").
So it is offered, opt-in; the default stays the paper's algorithm.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kftune.optim.base import (
    ExhaustedError,
    Optimizer,
    Proposal,
    Trial,
    coincides,
)
from kftune.settings import SettingError

#: Relative tolerance for AF ties.
TIE_RTOL = 1e-9
_MODES: dict[str, dict[str, Any]] = {
    "faithful": {
        "keep_stage1_data": False,
        "min_box_halfwidth": 0.0,
        "stage2_reserve": 0.0,
        "min_resolution": 0.0,
        "tr_fe_units": "natural",
        "max_af": 10,
    },
    "improved": {
        "keep_stage1_data": True,
        "min_box_halfwidth": 0.02,
        "stage2_reserve": 0.25,
        "min_resolution": 0.0,
        "tr_fe_units": "natural",
        "max_af": "switch",
    },
}
_AFS = ("EI", "CBM")
_TR_FE_UNITS = ("natural", "unit-cube")
#: Fallback draws of random candidates before giving up (only reachable with a huge
#: ``min_resolution``).
_FALLBACK_TRIES = 100


class PartitionTree:
    """Leaves of a recursive partition of a box in the unit cube.

    Attributes:
        lo, hi: (L, d) corners of every node ever created (unit cube).
        active: (L,) True for current leaves.
        asked: (L,) True where the node's centre has been evaluated (or is pending).
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.lo = np.asarray(lo, dtype=float)[None, :].copy()
        self.hi = np.asarray(hi, dtype=float)[None, :].copy()
        self.active = np.array([True])
        self.asked = np.array([False])

    @property
    def centres(self) -> np.ndarray:
        """(L, d) centres of all nodes."""
        return 0.5 * (self.lo + self.hi)

    def candidates(self) -> np.ndarray:
        """Indices of leaves whose centre has not been evaluated."""
        return np.flatnonzero(self.active & ~self.asked)

    def split(self, i: int, k: int, asked_points: np.ndarray) -> np.ndarray:
        """Split leaf ``i`` into k^d equal children (each side cut into k).

        Args:
            i: node index (must be an active leaf).
            k: 2 (stage 1) or 3 (stage 2).
            asked_points: (n, d) every point asked so far; children whose centre coincides
                with one are marked ``asked``.

        Returns:
            Indices of the new children.
        """
        if not self.active[i]:
            raise ValueError(f"node {i} is not a leaf")
        lo, hi = self.lo[i], self.hi[i]
        d = lo.size
        edges = [lo[j] + (hi[j] - lo[j]) * np.arange(k + 1) / k for j in range(d)]
        combos = np.array(list(itertools.product(range(k), repeat=d)))  # (k^d, d)
        c_lo = np.stack([edges[j][combos[:, j]] for j in range(d)], axis=1)
        c_hi = np.stack([edges[j][combos[:, j] + 1] for j in range(d)], axis=1)
        centres = 0.5 * (c_lo + c_hi)
        start = len(self.active)
        self.lo = np.vstack([self.lo, c_lo])
        self.hi = np.vstack([self.hi, c_hi])
        self.active[i] = False
        self.active = np.concatenate([self.active, np.ones(len(combos), dtype=bool)])
        self.asked = np.concatenate([self.asked, coincides(centres, asked_points)])
        return np.arange(start, start + len(combos))


def stage2_box(
    space: Any, q_star: np.ndarray, alpha: float, min_halfwidth: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The pure-exploitation box of paper Eq. 11 in unit-cube coordinates.

    ``[(1−α)·q*_i, (1+α)·q*_i]`` in natural units (ordered, for negative q*_i); on a log10
    scale this is ``u*_i + [log10(1−α), log10(1+α)] / (log10 hi − log10 lo)``. Each side is
    then widened to at least ``min_halfwidth`` around u*_i and clipped to [0, 1].

    Args:
        space: the :class:`~kftune.space.Space`.
        q_star: (d,) incumbent in natural units.
        alpha: relative half-width α (paper: 0.15), 0 < α < 1.
        min_halfwidth: lower bound on each half-width in the unit cube (0 = paper).

    Returns:
        (lo, hi), each (d,), in the unit cube.
    """
    q = np.asarray(q_star, dtype=float)
    u_star = space.to_unit(q)
    lo = np.empty(space.dim)
    hi = np.empty(space.dim)
    for i, p in enumerate(space.params):
        if p.log:
            lo[i] = u_star[i] + math.log10(1.0 - alpha) / p.width
            hi[i] = u_star[i] + math.log10(1.0 + alpha) / p.width
        else:
            a, b = sorted(((1.0 - alpha) * q[i], (1.0 + alpha) * q[i]))
            lo[i] = (a - p.low) / p.width
            hi[i] = (b - p.low) / p.width
    lo = np.minimum(lo, u_star - min_halfwidth)
    hi = np.maximum(hi, u_star + min_halfwidth)
    return np.clip(lo, 0.0, 1.0), np.clip(hi, 0.0, 1.0)


@dataclass(frozen=True)
class TSBOSettings:
    """Every setting of :class:`TSBO`, checked once (the module docstring gives each
    decision). The paper's values (Table III) are the defaults; ``mode`` presets the options
    whose default is None (the modes are listed in the module docstring), and an option
    given explicitly overrides the preset.

    Surrogate:
        surrogate: ``"tsp"`` (default; Student-t process, ν = 15), ``"gp"``,
            ``"robust-gp"``, or a callable ``factory(seed=int) -> Surrogate``.
        surrogate_options: keyword options for ``kftune.bo.make_surrogate`` (or the
            factory). Default None: none.
        max_sm: MAX_SM, evaluations after which the surrogate is frozen, ≥ 1 (default None:
            ``budget − 2``; paper: 38 of 40).
        sm_freeze: ``"hyperparameters"`` (default) or ``"full"``.

    Stage 1 (fast exploration) and the switch (Eq. 10):
        max_fe: MAX_FE, consecutive small moves of the incumbent that end stage 1, ≥ 1
            (default 15, the paper's).
        max_af: MAX_AF, AF-chosen stage-1 iterations of EI/CBM alternation, ≥ 1, or
            ``"switch"``: alternate through all of stage 1 and choose at the switch
            (default None: the mode's, faithful 10, improved ``"switch"``).
        beta: CBM exploration weight β, ≥ 0 (default 0.01, the paper's).
        tr_fe: TR_FE as a fraction of ‖q*‖ (paper: 0.01, the default), or of the unit
            cube's diagonal √d with ``tr_fe_units="unit-cube"``; ≥ 0.
        tr_fe_units: ``"natural"`` (paper: ‖Δq*‖ < tr_fe·‖q*‖) or ``"unit-cube"``
            (‖Δu*‖ < tr_fe·√d). Default None: the mode's (``"natural"``).
        stage2_reserve: share of the budget reserved for stage 2, in [0, 1) (default None:
            the mode's, faithful 0, improved 0.25).

    Stage 2 (pure exploitation, Eq. 11):
        alpha: the stage-2 box's half-width α, relative in natural units, in (0, 1)
            (default 0.15, the paper's).
        min_box_halfwidth: floor of the stage-2 half-width in the unit cube, in [0, 0.5]
            (default None: the mode's, faithful 0, improved 0.02).
        keep_stage1_data: the stage-2 surrogate also fits the stage-1 data (default None:
            the mode's, faithful False, improved True).

    Both stages:
        mode: ``"faithful"`` (default) or ``"improved"``: the presets above.
        min_resolution: ε (unit cube, max-norm), in [0, 0.25): no point within ε of an
            asked point is proposed (default None: the mode's, 0 = the paper's, which only
            excludes exact repeats).
    """

    surrogate: str | Callable[..., Any] = "tsp"
    surrogate_options: Mapping[str, Any] | None = None
    max_sm: int | None = None
    sm_freeze: str = "hyperparameters"
    max_fe: int = 15
    max_af: int | str | None = None
    beta: float = 0.01
    tr_fe: float = 0.01
    tr_fe_units: str | None = None
    stage2_reserve: float | None = None
    alpha: float = 0.15
    min_box_halfwidth: float | None = None
    keep_stage1_data: bool | None = None
    mode: str = "faithful"
    min_resolution: float | None = None

    def __post_init__(self) -> None:
        """Refuse a setting out of its range (a :class:`~kftune.settings.SettingError`
        naming it); the presets of
        ``mode`` are valid, so checking what is given checks what is used."""
        if self.mode not in _MODES:
            raise SettingError("mode", f"one of {list(_MODES)}", self.mode)
        if self.sm_freeze not in ("hyperparameters", "full"):
            raise SettingError("sm_freeze", "one of ['hyperparameters', 'full']", self.sm_freeze)
        for name, val in (("max_fe", self.max_fe), ("max_af", self.max_af)):
            if name == "max_af" and val in ("switch", None):
                continue
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < 1:
                extra = " or 'switch'" if name == "max_af" else ""
                raise SettingError(
                    name, f"an integer >= 1{extra}", val, wrong_type=not isinstance(val, int)
                )
        max_sm = self.max_sm
        if max_sm is not None and (not isinstance(max_sm, (int, np.integer)) or max_sm < 1):
            raise SettingError(
                "max_sm", "an integer >= 1", max_sm, wrong_type=not isinstance(max_sm, int)
            )
        if not 0.0 < self.alpha < 1.0:
            raise SettingError("alpha", "a number > 0 and < 1", self.alpha)
        for name, number in (("beta", self.beta), ("tr_fe", self.tr_fe)):
            if not number >= 0.0:
                raise SettingError(name, "a number >= 0", number)
        preset = _MODES[self.mode]
        halfwidth = float(self._pick("min_box_halfwidth", preset))
        reserve = float(self._pick("stage2_reserve", preset))
        if not 0.0 <= halfwidth <= 0.5:
            raise SettingError("min_box_halfwidth", "a number >= 0 and <= 0.5", halfwidth)
        if not 0.0 <= reserve < 1.0:
            raise SettingError("stage2_reserve", "a number >= 0 and < 1", reserve)
        resolution = float(self._pick("min_resolution", preset))
        if not 0.0 <= resolution < 0.25:
            raise SettingError("min_resolution", "a number >= 0 and < 0.25 (unit cube)", resolution)
        units = str(self._pick("tr_fe_units", preset))
        if units not in _TR_FE_UNITS:
            raise SettingError("tr_fe_units", f"one of {list(_TR_FE_UNITS)}", units)
        if not isinstance(self.surrogate, str) and not callable(self.surrogate):
            raise SettingError("surrogate", "a name or a factory", self.surrogate)

    def _pick(self, name: str, preset: Mapping[str, Any]) -> Any:
        """The option ``name`` as given, or the preset's value when it is None."""
        value = getattr(self, name)
        return preset[name] if value is None else value

    def with_preset(self) -> TSBOSettings:
        """These settings with every option left to the mode (None) set to its preset, in
        the types :class:`TSBO` uses (``max_sm`` stays: its default needs the budget)."""
        preset = _MODES[self.mode]
        return replace(
            self,
            max_af=self._pick("max_af", preset),
            keep_stage1_data=bool(self._pick("keep_stage1_data", preset)),
            min_box_halfwidth=float(self._pick("min_box_halfwidth", preset)),
            stage2_reserve=float(self._pick("stage2_reserve", preset)),
            min_resolution=float(self._pick("min_resolution", preset)),
            tr_fe_units=str(self._pick("tr_fe_units", preset)),
        )


class TSBO(Optimizer):
    """Two-stage Bayesian optimisation (see the module docstring for every decision).

    Args:
        space: search space.
        settings: the algorithm's settings (:class:`TSBOSettings`; default: the paper's).
            By name, as a configuration's ``[options.tsbo-tsp]`` gives them:
            ``make_optimizer("tsbo-tsp", space, max_fe=10)``.
        budget: total evaluations = MAX_PE (paper: 40).
        seed: drives the surrogate fits, tie-breaks and fallbacks.

    The settings in use, the mode's presets and ``max_sm``'s default filled in, are
    :attr:`settings`.
    """

    method: str = "tsbo"
    default_budget: ClassVar[int] = 40
    #: The record of this optimiser's settings (:func:`kftune.optim.make_optimizer`).
    settings_type: ClassVar[type] = TSBOSettings

    def __init__(
        self,
        space: Any,
        settings: TSBOSettings | None = None,
        *,
        budget: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(space, budget=budget, seed=seed)
        s = TSBOSettings() if settings is None else settings
        if not isinstance(s, TSBOSettings):
            raise TypeError(f"settings must be a TSBOSettings, got {type(s).__name__}")
        s = s.with_preset()
        s = replace(s, max_sm=max(1, self.budget - 2) if s.max_sm is None else s.max_sm)
        self.settings = s
        self.mode = s.mode
        self.keep_stage1_data = bool(s.keep_stage1_data)
        self.min_box_halfwidth = float(s.min_box_halfwidth or 0.0)
        self.stage2_reserve = float(s.stage2_reserve or 0.0)
        self.min_resolution = float(s.min_resolution or 0.0)
        self.tr_fe_units = str(s.tr_fe_units)
        self.max_fe, self.max_sm = int(s.max_fe), int(s.max_sm or 1)
        self.max_af: int | None = None if s.max_af == "switch" else int(s.max_af or 0)
        self.beta, self.alpha, self.tr_fe = float(s.beta), float(s.alpha), float(s.tr_fe)
        self.sm_freeze = s.sm_freeze
        surrogate = s.surrogate
        self.surrogate_name = surrogate if isinstance(surrogate, str) else _qualname(surrogate)
        self.surrogate_options = dict(s.surrogate_options or {})
        self.method = f"tsbo-{self.surrogate_name}" if isinstance(surrogate, str) else "tsbo"
        surrogate_seed = int(self.seed_sequence.spawn(2)[1].generate_state(1)[0])
        if isinstance(surrogate, str):
            from kftune.bo import make_surrogate

            self.surrogate = make_surrogate(
                surrogate, seed=surrogate_seed, **self.surrogate_options
            )
        else:
            self.surrogate = surrogate(seed=surrogate_seed, **self.surrogate_options)

        d = self.space.dim
        self.stage = 1
        self.tree = PartitionTree(np.zeros(d), np.ones(d))
        self._X = np.empty((0, d))  # every asked point (unit cube), told ones first
        self._y: list[float | None] = []
        self.small_moves = 0  # counter n of Eq. 10
        self.af_iterations = 0
        self.gains = {"EI": 0.0, "CBM": 0.0}
        self.chosen_af: str | None = None
        self.switch_at: int | None = None  # number of evaluations when stage 2 began
        self.box: tuple[np.ndarray, np.ndarray] | None = None
        self._stage2_fitted = False
        self._last_fit_n: int | None = None

    # ------------------------------------------------------------------ settings
    def options(self) -> dict[str, Any]:
        return {
            "surrogate": self.surrogate_name,
            "surrogate_options": self.surrogate_options,
            "max_fe": self.max_fe,
            "max_sm": self.max_sm,
            "max_af": "switch" if self.max_af is None else self.max_af,
            "beta": self.beta,
            "alpha": self.alpha,
            "tr_fe": self.tr_fe,
            "mode": self.mode,
            "sm_freeze": self.sm_freeze,
            "keep_stage1_data": self.keep_stage1_data,
            "min_box_halfwidth": self.min_box_halfwidth,
            "stage2_reserve": self.stage2_reserve,
            "min_resolution": self.min_resolution,
            "tr_fe_units": self.tr_fe_units,
        }

    # ------------------------------------------------------------------ data views
    def _incumbent(self) -> tuple[int | None, float | None]:
        """Index and value of the best successful evaluation (first on ties)."""
        return self._incumbent_at(len(self._y))

    def _surrogate_data(
        self, global_view: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Callable]:
        """(X in surrogate coordinates, imputed y, success mask, unit→surrogate map).

        Stage 2 of the faithful mode sees q* and the stage-2 points in box coordinates;
        otherwise (or with ``global_view``) every point in unit-cube coordinates."""
        n = len(self._y)
        idx = np.arange(n)
        to_s: Callable[[np.ndarray], np.ndarray] = lambda u: u  # noqa: E731
        if self.stage == 2 and not self.keep_stage1_data and not global_view:
            assert self.switch_at is not None and self.box is not None
            q_i, _ = self._incumbent_at(self.switch_at)
            idx = np.array([q_i, *range(self.switch_at, n)], dtype=int)
            lo, hi = self.box
            width = hi - lo
            safe = np.where(width > 0, width, 1.0)

            def to_s(u: np.ndarray) -> np.ndarray:
                return np.where(width > 0, (u - lo) / safe, 0.5)

        X = to_s(self._X[idx])
        raw = [self._y[i] for i in idx]
        ok = np.array([v is not None for v in raw])
        if ok.any():
            worst = max(v for v in raw if v is not None)
        else:
            all_ok = [v for v in self._y if v is not None]
            worst = max(all_ok) if all_ok else 0.0
        y = np.array([worst if v is None else v for v in raw], dtype=float)
        from kftune.bo.base import MAX_ABS_Y  # the surrogates refuse more (variance overflow)

        return X, np.clip(y, -MAX_ABS_Y, MAX_ABS_Y), ok, to_s

    def _incumbent_at(self, n: int) -> tuple[int | None, float | None]:
        """Index and value of the best successful evaluation among the first ``n``."""
        best_i, best_v = None, None
        for i, v in enumerate(self._y[:n]):
            if v is not None and (best_v is None or v < best_v):
                best_i, best_v = i, v
        return best_i, best_v

    # ------------------------------------------------------------------ ask
    def _current_af(self) -> str:
        if self.chosen_af is not None:
            return self.chosen_af
        return _AFS[self.af_iterations % 2]

    def _propose(self) -> Proposal:
        n = len(self._y)
        if n == 0:
            return Proposal(
                u=np.full(self.space.dim, 0.5),
                stage=1,
                acquisition="centre",
                info={"leaf": 0},
            )
        leaves = self.tree.candidates()
        pending = self._pending_u()
        if len(pending) and leaves.size:  # batch mode: not a leaf already in flight
            leaves = leaves[~coincides(self.tree.centres[leaves], pending)]
        if self.min_resolution > 0.0 and leaves.size:
            near = coincides(self.tree.centres[leaves], self._X, self.min_resolution)
            leaves = leaves[~near]
        fallback = leaves.size == 0
        X, y, ok, to_s = self._surrogate_data(global_view=fallback)
        refit = fallback or n <= self.max_sm or (self.stage == 2 and not self._stage2_fitted)
        if refit:
            self.surrogate.fit(X, y)
            self._last_fit_n = n
            if self.stage == 2:
                self._stage2_fitted = True
        elif self.sm_freeze == "hyperparameters":
            self.surrogate.condition(X, y)
        model = self.surrogate
        if len(pending):
            # Batch mode, the Kriging believer (Ginsbourger, Le Riche & Carraro, "Kriging is
            # well-suited to parallelize optimization", 2010): the points in flight are
            # believed to return the model's mean, on a copy of the model conditioned on
            # them with its hyperparameters kept (the model itself stays as it was).
            Xp = to_s(pending)
            model = copy.deepcopy(self.surrogate).condition(
                np.vstack([X, Xp]), np.concatenate([y, self.surrogate.predict(Xp).mean])
            )
        af = self._current_af()
        if fallback:
            cand_u = self._fallback_candidates()
            label = f"{af}-fallback"
        else:
            cand_u = self.tree.centres[leaves]
            label = af
        pred = model.predict(to_s(cand_u))
        incumbent = float(np.min(y[ok])) if ok.any() else float(np.min(y))
        scores = self._score(af, pred, incumbent)
        j = self._argmax(scores)
        info: dict[str, Any] = {
            "n_candidates": len(cand_u),
            "af_value": float(scores[j]),
            "refit": bool(refit),
            "frozen": not refit,
            "fit_n": self._last_fit_n,
            "small_moves": self.small_moves,
            "gains": dict(self.gains),
        }
        if not fallback:
            info["leaf"] = int(leaves[j])
        return Proposal(
            u=cand_u[j].copy(),
            stage=self.stage,
            acquisition=label,
            hyperparameters=dict(self.surrogate.hyperparameters),
            info=info,
        )

    def _n_proposable(self) -> int | None:
        """Before any result, only the centre (the model needs data)."""
        return max(1 - self._n_asked, 0) if not self._y else None

    def _fallback_candidates(self) -> np.ndarray:
        """(m, d) uniform random points in the unit cube, farther than ``min_resolution``
        (max-norm) from every asked point; ``100·d`` are drawn, redrawn if none is left."""
        d = self.space.dim
        for _ in range(_FALLBACK_TRIES):
            u = self.rng.random((100 * d, d))
            if self.min_resolution > 0.0:
                asked = np.vstack([self._X, self._pending_u()])
                u = u[~coincides(u, asked, self.min_resolution)]
            if len(u):
                return u
        raise ExhaustedError(
            f"TSBO found no point farther than min_resolution={self.min_resolution} from the "
            f"{len(self._X)} evaluated points in {_FALLBACK_TRIES * 100 * d} random draws"
        )

    def _score(self, af: str, pred: Any, incumbent: float) -> np.ndarray:
        from kftune.bo import acquisition as acq

        if af == "EI":
            log_ei = getattr(acq, "log_expected_improvement", None)
            if log_ei is not None:
                return np.asarray(log_ei(pred, incumbent), dtype=float)
            return np.asarray(acq.expected_improvement(pred, incumbent), dtype=float)
        return np.asarray(acq.confidence_bound(pred, incumbent, beta=self.beta), dtype=float)

    def _argmax(self, scores: np.ndarray) -> int:
        s = np.where(np.isnan(scores), -np.inf, scores)
        top = float(np.max(s))
        if not np.isfinite(top):
            tied = np.flatnonzero(s == top) if top > -np.inf else np.arange(len(s))
        else:
            tied = np.flatnonzero(s >= top - TIE_RTOL * max(abs(top), 1e-300))
        return int(tied[0] if len(tied) == 1 else self.rng.choice(tied))

    # ------------------------------------------------------------------ tell
    def _observe(self, trial: Trial, value: float | None) -> None:
        prev_i, best_before = self._incumbent()
        self._X = np.vstack([self._X, trial.u[None, :]])
        self._y.append(value)
        n = len(self._y)
        leaf = trial.info.get("leaf")
        if trial.acquisition == "centre":
            self.tree.asked[0] = True
            self.tree.split(0, 2, self._X)
        elif leaf is not None:
            self.tree.asked[leaf] = True
            self.tree.split(leaf, 2 if self.stage == 1 else 3, self._X)
        if self.stage == 2:
            return
        # --- acquisition gains (stage 1 alternation)
        af = (trial.acquisition or "").split("-")[0]
        if af in _AFS and self.chosen_af is None:
            if value is not None and best_before is not None:
                self.gains[af] += max(0.0, best_before - value)
            self.af_iterations += 1
            if self.max_af is not None and self.af_iterations >= self.max_af:
                self._choose_af()
        # --- Eq. 10: consecutive small moves of the incumbent
        new_i, _ = self._incumbent()
        if prev_i is not None and new_i is not None:
            self.small_moves = self.small_moves + 1 if self._small_move(prev_i, new_i) else 0
        # --- switch
        reserve = math.floor(self.stage2_reserve * self.budget)
        forced = reserve > 0 and self.budget - n <= reserve
        if new_i is not None and (self.small_moves >= self.max_fe or forced):
            self._start_stage2(n, new_i)

    def _small_move(self, old: int, new: int) -> bool:
        """Eq. 10: did the incumbent move from point ``old`` to point ``new`` by less than
        TR_FE? Natural units: ‖q_new − q_old‖ < tr_fe·‖q_new‖ (paper); unit cube:
        ‖u_new − u_old‖ < tr_fe·√d. Not moving at all always counts."""
        if self.tr_fe_units == "natural":
            a, b = self.space.from_unit(self._X[old]), self.space.from_unit(self._X[new])
            tr = self.tr_fe * float(np.linalg.norm(b))
        else:
            a, b = self._X[old], self._X[new]
            tr = self.tr_fe * math.sqrt(self.space.dim)
        dist = float(np.linalg.norm(b - a))
        return dist < tr or dist == 0.0

    def _choose_af(self) -> None:
        self.chosen_af = "CBM" if self.gains["CBM"] > self.gains["EI"] else "EI"

    def _start_stage2(self, n: int, q_index: int) -> None:
        if self.chosen_af is None:
            self._choose_af()
        self.stage = 2
        self.switch_at = n
        q_star = self.space.from_unit(self._X[q_index])
        lo, hi = stage2_box(self.space, q_star, self.alpha, self.min_box_halfwidth)
        self.box = (lo, hi)
        self.tree = PartitionTree(lo, hi)
        self.tree.asked[0] = bool(coincides(self.tree.centres[:1], self._X)[0])
        self.tree.split(0, 3, self._X)


def _qualname(obj: Any) -> str:
    return getattr(obj, "__qualname__", None) or type(obj).__qualname__
