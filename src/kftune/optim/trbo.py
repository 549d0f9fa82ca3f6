"""Trust-region Bayesian optimisation (method ``"trbo"``): kftune's default tuner.

The paper's TSBO (:mod:`kftune.optim.tsbo`) stays as it is, for the reproduction. On the
recorded costs it gets stuck in the first basin it finds: stage 2's ±15 % box never leaves
it and nothing restarts. TR-BO keeps TSBO's ideas — a surrogate of the whole run, a local
stage, and a global one — but lets them alternate for the whole budget:

* **Design** (``init_design="auto"``): the centre, then two points on each axis through
  it — for a log10 parameter that is a variance the centres of its two faces of the box
  (``"axial"``, the axial points of a face-centred composite design), for any other
  DIRECT's first trisection, the centre ± 1/3 (``"direct"``). A log10 variance spans
  decades (Q's 10, R's factors 4, or whatever box a user gives) and its two ends are
  regimes — a noise too small to matter, a model ignored — where the cost flattens into
  plateaus, and the optima of the tuning problems lie on or next to its bounds; probing
  every face from the start is what reaches them. A linear box carries no such prior, and
  there the face centres can lead into a basin beside a face that is not the global one
  (Hartmann-6). Nor does a narrow log10 box (at most :data:`WIDE_DECADES` decades) of a
  :class:`~kftune.space.Param` marked ``physical`` — a model parameter, the plausible
  range of a physical quantity around its guess (a cornering stiffness in [2e4, 4e5]
  N/rad, 1.3 decades; a friction coefficient in [0.4, 1.6]): its faces are cars nobody
  has, the first basin they lead into is an artefact of the box, and the optimum lies
  inside. Q's and R's boxes keep the faces whatever their width (a user's narrow Q box
  too), so a Q-only or Q-and-R search proposes exactly what it did before and its older
  studies resume.
  A search that continues from a known good point (``x0``, ``design_centre="x0"``)
  centres the design there and probes only the axes it names (``design_params``): the
  second stage of a tuning with model parameters, whose first stage tuned the noise at the
  recorded model, probes each model parameter along its axis through that stage's best
  (7 evaluations at d = 9, the seed included, instead of 20). Centred on the box instead,
  the design's centre put every stiffness at the box's geometric middle (89,443 N/rad for
  [2e4, 4e5], a car nobody gave), which beat the short first stage's point and pulled the
  search into its basin (BENCHMARKS.md, "The joint stage's design").
* **Surrogate**: a GP (Matérn 5/2, ARD, constant mean, fitted noise; ``surrogate="tsp"``
  for the Student-t process) on warped values ``log(y − min y + δ)`` with
  δ = 10 % of (median − min) (``warp="log-min"``, ``warp_delta=0.1``). Cliffs and plateaus
  that span decades become comparable, and differences near the best stay resolved (output
  warping, cf. HEBO); a smaller δ magnifies the incumbent into a spike, which locks the
  search into its basin. Length scales are bounded below by 0.05 of the unit cube
  (:data:`LENGTH_SCALE_BOUNDS`): without the bound the warped costs are fitted with tiny
  length scales, and EI then creeps along slopes in tiny steps.
* **Local steps** (TuRBO, Eriksson et al. 2019): EI maximised inside a trust region around
  the incumbent — a box of side ``L`` stretched by the GP's length scales (each relative
  to their geometric mean, clipped to [1/4, 4]), of side 0.2 at the start
  (``length_init``; TuRBO starts at 0.8: a smaller first region reaches the bottom of the
  design's best basin sooner). Two improvements in a row double ``L`` (at most
  ``length_max``), three failures halve it; an improvement must beat the incumbent by
  ``improvement_rtol`` (1e-3) of its value. When ``L`` falls below ``length_min`` the
  region restarts at ``length_init`` and the next ``escape`` steps go where the model is
  least sure (largest predictive standard deviation over the whole box): EI alone stays in
  a basin that the model believes it knows.
* **Restarts** (``restart="alternate"``): the first collapse re-centres the region on the
  incumbent (one more polish of its basin); the second leaves it — the new region is
  centred on the best escape step and, like TuRBO's restarted regions, measures its local
  steps against its own best (local EI over the centre's value, successes against the
  centre), so it descends into the basin it found rather than chasing the incumbent's
  value; and so on, alternating. A global step that beats the incumbent still re-centres
  the region there; one that only beats the new region's centre does not pull it back
  into the basin it left. Restarting always at the incumbent (``"incumbent"``) re-polishes
  the first basin when the optimum lies in another; always leaving (``"fresh"``) can
  abandon a basin before it is polished, so that more budget buys nothing. Nothing changes
  before the first collapse.
* **Axis probes** (plateaus): after ``probe_after`` (5) model-based results in a row
  without an improvement, the next step moves the incumbent along the coordinate the GP
  finds least relevant — the longest length scale, if it is at least
  ``probe_length_scale`` of the box — into the middle of the widest unsampled gap of that
  coordinate on the incumbent's line (asked points whose other coordinates are within
  :data:`AXIS_SLAB`). A process-noise variance too small to matter leaves the cost flat
  over its whole lower range; there the GP rightly finds the coordinate irrelevant and EI
  never samples the dip beyond the plateau. The probe tests that belief, a bisection at a
  time. A probe that improves nothing doubles the wait for the next one; any improvement
  resets it. A probe takes the place of the step it replaces (a scheduled global step or an
  escape step counts as made) and is a global step for the trust region: one that improves
  re-centres the region afresh.
* **Global steps**: every ``global_every``-th model-based step maximises EI over the whole
  box instead — exploration where the model is unsure, which is how the search leaves a
  basin.
* **Batches** (``ask(q)``): pending points are fantasised at the model's mean (Kriging
  believer, one hyperparameter fit per batch); the trust region is updated once per round
  (TuRBO's batch rule, see :meth:`TrustRegionBO._observe`); the cadence of global steps
  counts proposals; the initial design goes out on its own. With q = 1 every rule is the
  sequential one and the proposals are the sequential loop's.
* **Candidates**: EI is maximised over random candidates (uniform in the region, Gaussian
  around the incumbent) plus copies of some of them with coordinates moved onto the faces
  that the region touches (so optima on faces and corners are reached exactly, not only
  approached), then over a second, finer round of Gaussian perturbations around the five
  best. No point within 1e-9 of an asked one is proposed (so a failed point never is).
* **Cost**: the hyperparameters are fitted with restarts while n ≤ ``full_fit_until`` and
  every ``refit_every``-th step, otherwise warm-started from the last fit.

Nothing depends on the budget, so a run with more budget starts as the shorter one did
(anytime: more budget never ends worse). Failed evaluations are imputed with the worst
value seen, as in TSBO; values beyond ±1e100 are clipped for the surrogate.

The runs that chose each default (paired by seed on the bundled set, revs-250lm, fresh
noise draws of the bundled plant and the synthetic suite) are in BENCHMARKS.md: the
sections "TR-BO …" (the design runs; the warp δ and the trust region's start; axis
probes; alternating restarts and DIRECT's design on a third dataset; the design per
parameter scale), "Tuning model parameters" (the design of physical parameters), and,
gathered per default, "Moved from module docstrings", "kftune.optim.trbo".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from scipy.stats import qmc

from kftune.optim.base import SAME_POINT_ATOL, Optimizer, Proposal, Trial, coincides
from kftune.settings import SettingError

WARPS = ("none", "log", "log-min")
INIT_DESIGNS = ("auto", "axial", "direct", "sobol")
#: Where the initial design is centred (:class:`TRBOSettings` ``design_centre``).
DESIGN_CENTRES = ("box", "x0")
#: Where the design's two points on an axis lie (unit cube): the faces, or DIRECT's thirds.
DESIGN_AXIS_POINTS = {"axial": (0.0, 1.0), "direct": (1.0 / 6.0, 5.0 / 6.0)}
#: ``init_design="auto"`` probes the faces of a log10 parameter whose box spans more than
#: this many decades (a variance), DIRECT's thirds of any other (module docstring).
WIDE_DECADES = 2.0
RESTARTS = ("alternate", "fresh", "incumbent")
#: Axis probes: sampled points count as on the incumbent's line when their other
#: coordinates are within this distance (max-norm, unit cube) of the incumbent's.
AXIS_SLAB = 0.1
#: Axis probes: a coordinate whose widest unsampled gap is narrower than this is skipped.
AXIS_MIN_GAP = 0.02
#: The GP's default length-scale bounds here (unit cube): see the module docstring.
LENGTH_SCALE_BOUNDS = (0.05, 20.0)
#: An improvement must beat the incumbent by this share of its magnitude (TuRBO's 1e-3).
IMPROVEMENT_RTOL = 1e-3


def auto_design(param: Any) -> str:
    """The axis points ``init_design="auto"`` gives a :class:`~kftune.space.Param`:
    ``"direct"`` (DIRECT's thirds) for a linear one and for a physical quantity's narrow
    log10 box (``physical``, at most :data:`WIDE_DECADES` decades: a model parameter's
    plausible range), ``"axial"`` (face centres) for any other log10 one — a variance,
    whatever its box, so that a user's narrow Q box keeps the design it always had."""
    if param.scale != "log10":
        return "direct"
    narrow = math.log10(param.high / param.low) <= WIDE_DECADES
    return "direct" if narrow and getattr(param, "physical", False) else "axial"


def _check_number(name: str, value: Any, ok: Any, expected: str) -> None:
    """Refuse ``value`` unless it is a number (not a bool) for which ``ok(value)`` holds."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and ok(value)):
        raise SettingError(name, expected, value)


@dataclass(frozen=True)
class TRBOSettings:
    """Every setting of :class:`TrustRegionBO`, checked once (see the module docstring for
    the algorithm and why each default, BENCHMARKS.md for the runs). Lengths are in the unit
    cube [0, 1]^d of the search space; counts are evaluations or steps.

    Surrogate:
        surrogate: ``"gp"`` (default), ``"tsp"`` or ``"robust-gp"``.
        surrogate_options: keyword options of the surrogate
            (:func:`kftune.bo.make_surrogate`); ``length_scale_bounds`` defaults to
            :data:`LENGTH_SCALE_BOUNDS`. Default None: none.
        warp: output warping, ``"log-min"`` (default), ``"log"`` (log y when y > 0) or
            ``"none"``.
        warp_delta: δ of ``"log-min"`` as a share of (median − min) of the values, > 0
            (default 0.1).

    Initial design:
        n_init: points of the initial design, ≥ 1 (default None: 2d + 1, the centre and
            two points on each axis; 1 + 2 per parameter named in ``design_params``).
        init_design: ``"auto"`` (default; :func:`auto_design`: ``"axial"`` along log10
            variances, ``"direct"`` along linear and narrow physical parameters; recorded
            as ``"axial"`` or ``"direct"`` when all are alike), ``"axial"`` (centre, face
            centres, then Sobol points), ``"direct"`` (centre, the box's centre ± 1/3
            along each axis — 1/6 and 5/6 of it —, then Sobol points) or ``"sobol"``
            (centre, then scrambled Sobol points over every axis).
        x0: points (natural units; one (d,) or several (k, d), inside the box) evaluated
            first, before the design — a known good point, such as the optimum of Q tuned
            on the recorded model when the model's parameters join the search, so the run
            ends no worse than it (a design point that coincides with one is left out).
            Default None: none.
        design_centre: ``"box"`` (default: the design's centre is the box's) or ``"x0"``
            (its centre is the first point of ``x0``, and its axis points lie on the axes
            through it, each at the position along its own axis that the box-centred
            design gives it: a face or a third of the box): a search that continues from a
            known good point probes around that point, not around the middle of the box.
            Needs ``x0``.
        design_params: the names of the parameters whose axes the design probes (default
            None: every one; ``n_init`` then defaults to 1 + 2 per named parameter). The
            joint stage of a tuning with model parameters names those alone: the first
            stage has already searched the noise from the same point.

    Trust region (TuRBO):
        length_init, length_min, length_max: the region's side at the start and after a
            restart, the side below which it has collapsed, its largest side; need
            0 < length_min ≤ length_init ≤ length_max (defaults 0.2, 2⁻⁷, 1.0).
        success_tol: consecutive successful rounds that double the side, ≥ 1 (default 2).
        failure_tol: failed local evaluations that halve it, ≥ 1 (default None:
            max(3, d)).
        improvement_rtol: a result improves (a success for the trust region, a reset of
            the stall count) when it beats the centre (local) or the incumbent (global) by
            this share of its magnitude, in [0, 1) (default :data:`IMPROVEMENT_RTOL`,
            1e-3).
        restart: after a collapse, ``"alternate"`` (default: re-centre on the incumbent,
            then on the escape steps' best the next time, and so on), ``"fresh"`` (always
            the escape steps' best) or ``"incumbent"`` (always the incumbent).
        escape: global steps (largest predictive standard deviation) after the trust
            region collapsed, ≥ 0 (default 2).

    Global steps and axis probes:
        global_every: every this-many model-based steps is global, ≥ 0 (0: never;
            default 4).
        probe_after: an axis probe after this many model-based results in a row without
            an improvement, ≥ 0 (0: never; default 5); doubled after each probe that
            improves nothing.
        probe_length_scale: only coordinates whose GP length scale (unit cube) is at least
            this are probed, ≥ 0 (default 0.5).

    Maximising the acquisition:
        n_candidates: random candidates per step, ≥ 1 (more cost time, not evaluations;
            default 500).
        faces: add candidates moved onto the faces that the region touches (default True).

    Hyperparameter fits:
        refit_every: a fit with restarts every this-many steps, ≥ 1 (default 5).
        full_fit_until: fits with restarts while there are at most this many results, ≥ 0
            (default 20); otherwise warm-started from the last fit.
    """

    surrogate: str = "gp"
    surrogate_options: Mapping[str, Any] | None = None
    warp: str = "log-min"
    warp_delta: float = 0.1
    n_init: int | None = None
    init_design: str = "auto"
    x0: Any = None
    design_centre: str = "box"
    design_params: Sequence[str] | None = None
    length_init: float = 0.2
    length_min: float = 2.0**-7
    length_max: float = 1.0
    success_tol: int = 2
    failure_tol: int | None = None
    improvement_rtol: float = IMPROVEMENT_RTOL
    restart: str = "alternate"
    escape: int = 2
    global_every: int = 4
    probe_after: int = 5
    probe_length_scale: float = 0.5
    n_candidates: int = 500
    faces: bool = True
    refit_every: int = 5
    full_fit_until: int = 20

    def __post_init__(self) -> None:
        """Refuse a setting out of its range (a :class:`~kftune.settings.SettingError`
        naming it, which a configuration words with its file and table); the checks that need
        the space (``x0``) are :class:`TrustRegionBO`'s."""
        if self.warp not in WARPS:
            raise SettingError("warp", f"one of {list(WARPS)}", self.warp)
        _check_number(
            "warp_delta", self.warp_delta, lambda v: 0.0 < v < math.inf, "a positive number"
        )
        _check_number(
            "probe_length_scale",
            self.probe_length_scale,
            lambda v: 0.0 <= v < math.inf,
            "a number >= 0",
        )
        _check_number(
            "improvement_rtol",
            self.improvement_rtol,
            lambda v: 0.0 <= v < 1.0,
            "a number in [0, 1)",
        )
        if self.restart not in RESTARTS:
            raise SettingError("restart", f"one of {list(RESTARTS)}", self.restart)
        if self.init_design not in INIT_DESIGNS:
            raise SettingError("init_design", f"one of {list(INIT_DESIGNS)}", self.init_design)
        if self.design_centre not in DESIGN_CENTRES:
            raise SettingError(
                "design_centre", f"one of {list(DESIGN_CENTRES)}", self.design_centre
            )
        if self.design_centre == "x0" and self.x0 is None:
            raise SettingError("design_centre", "'box' unless x0 gives the centre", "x0")
        if self.design_params is not None and (
            isinstance(self.design_params, str)
            or not all(isinstance(n, str) for n in self.design_params)
        ):
            raise SettingError("design_params", "a list of parameter names", self.design_params)
        if not 0.0 < self.length_min <= self.length_init <= self.length_max:
            raise SettingError(
                "length_min, length_init, length_max",
                "0 < length_min <= length_init <= length_max",
                (self.length_min, self.length_init, self.length_max),
            )
        positive = ("n_init", "success_tol", "failure_tol", "n_candidates", "refit_every")
        counts = (*positive, "global_every", "escape", "probe_after", "full_fit_until")
        for name in counts:
            val = getattr(self, name)
            low = 1 if name in positive else 0
            if val is None and name in ("n_init", "failure_tol"):  # d-dependent defaults
                continue
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < low:
                raise SettingError(
                    name, f"an integer >= {low}", val, wrong_type=not isinstance(val, int)
                )


class TrustRegionBO(Optimizer):
    """Trust-region Bayesian optimisation over one surrogate of the whole run (see the
    module docstring for the algorithm and why each default, BENCHMARKS.md for the runs).

    Args:
        space, budget, seed: see :class:`~kftune.optim.base.Optimizer`.
        settings: every other setting (:class:`TRBOSettings`; default: its defaults). By
            name, as a configuration's ``[options.trbo]`` gives them:
            ``make_optimizer("trbo", space, n_init=9)``.

    The settings in use, with the space's defaults filled in (``n_init``, ``failure_tol``,
    ``init_design``), are :attr:`settings`.
    """

    method: str = "trbo"
    #: 100, not the paper's 40: at 40 evaluations there is time to polish one basin, and
    #: the design picks which (module docstring, "Restarts"); by 100 the restarts have
    #: reached the second one on most seeds of every dataset measured (BENCHMARKS.md).
    default_budget: ClassVar[int] = 100
    budget_independent: ClassVar[bool] = True
    #: The record of this optimiser's settings (:func:`kftune.optim.make_optimizer`).
    settings_type: ClassVar[type] = TRBOSettings

    def __init__(
        self,
        space: Any,
        settings: TRBOSettings | None = None,
        *,
        budget: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(space, budget=budget, seed=seed)
        s = TRBOSettings() if settings is None else settings
        if not isinstance(s, TRBOSettings):
            raise TypeError(f"settings must be a TRBOSettings, got {type(s).__name__}")
        d = self.space.dim
        init_design = s.init_design
        if init_design == "auto":  # one kind of parameter: say which (and old studies resume)
            kinds = {auto_design(p) for p in self.space.params}
            init_design = kinds.pop() if len(kinds) == 1 else "auto"
        axes = self._design_axes(s.design_params)
        s = replace(
            s,
            n_init=s.n_init if s.n_init is not None else 2 * len(axes) + 1,
            failure_tol=s.failure_tol if s.failure_tol is not None else max(3, d),
            init_design=init_design,
        )
        self.settings = s
        self.n_init, self.success_tol, self.failure_tol = (
            int(s.n_init or 0),
            int(s.success_tol),
            int(s.failure_tol or 0),
        )
        self.global_every, self.escape = int(s.global_every), int(s.escape)
        self.probe_after, self.probe_length_scale = int(s.probe_after), float(s.probe_length_scale)
        self.n_candidates, self.refit_every = int(s.n_candidates), int(s.refit_every)
        self.full_fit_until = int(s.full_fit_until)
        self.init_design, self.warp, self.faces = init_design, s.warp, bool(s.faces)
        self.restart = s.restart
        self.improvement_rtol = float(s.improvement_rtol)
        self.warp_delta = float(s.warp_delta)
        self.length_init, self.length_min, self.length_max = (
            float(s.length_init),
            float(s.length_min),
            float(s.length_max),
        )
        self.surrogate_name = s.surrogate
        self.surrogate_options = {
            "length_scale_bounds": LENGTH_SCALE_BOUNDS,
            **(s.surrogate_options or {}),
        }
        from kftune.bo import make_surrogate

        seeds = self.seed_sequence.spawn(3)
        self.surrogate = make_surrogate(
            s.surrogate, seed=int(seeds[1].generate_state(1)[0]), **self.surrogate_options
        )
        self._n_restarts = self.surrogate.n_restarts
        self.x0 = self._check_x0(s.x0)
        self.design_centre, self._axes = s.design_centre, axes
        self.design_params = None if s.design_params is None else list(s.design_params)
        design = self._initial_design(np.random.default_rng(seeds[2]))
        if self.x0 is not None:
            u0 = np.clip(self.space.to_unit(self.x0), 0.0, 1.0)
            design = np.vstack([u0, design[~coincides(design, u0, SAME_POINT_ATOL)]])
        self._design = design
        self._X = np.empty((0, d))
        self._y: list[float | None] = []
        self.length = self.length_init
        self.n_success = self.n_failure = 0
        self.tr_restarts = 0
        self._stall = 0  # model-based results told since the last improvement
        self._probe_wait = self.probe_after  # stall length that triggers the next probe
        self._iter = 0  # model-based results told so far
        self._n_model = 0  # model-based proposals asked so far (told or pending)
        self._force_global = 0  # escape steps still to hand out
        # Index of the trust region's centre in _X (None: the incumbent). After a collapse
        # that leaves the basin it is None until the first escape step is told.
        self._centre_i: int | None = None
        self._fit_n = -1  # told results at the last hyperparameter fit
        # Batch bookkeeping (TuRBO's batch rule): the trials of one ask() / ask(n) call form
        # a round; the trust region is updated once, when its last trial is told.
        self._round: dict[str, Any] | None = None
        self._round_of: dict[int, dict[str, Any]] = {}

    def _check_x0(self, x0: Any) -> np.ndarray | None:
        """``x0`` as a (k, d) array of points inside the box (natural units), or None.

        Raises:
            ValueError: not numbers of the space's dimension, or outside the box (naming
                the parameter).
        """
        if x0 is None:
            return None
        d = self.space.dim
        try:
            x = np.array(x0, dtype=float, ndmin=2)
        except (TypeError, ValueError):
            raise ValueError(f"x0 must be points of {d} numbers, got {x0!r}") from None
        if x.ndim != 2 or x.shape[1] != d or x.shape[0] == 0 or not np.all(np.isfinite(x)):
            raise ValueError(
                f"x0 must be one point or a list of points of {d} finite numbers "
                f"({', '.join(self.space.names)}), got shape {x.shape}"
            )
        for p, col in zip(self.space.params, x.T, strict=True):
            with np.errstate(divide="ignore", invalid="ignore"):
                u = p.to_unit(col)
            bad = ~np.isfinite(u) | (u < -1e-9) | (u > 1.0 + 1e-9)
            if bad.any():
                raise ValueError(
                    f"x0: {p.name} = {col[bad][0]:g} lies outside its box [{p.low:g}, {p.high:g}]"
                )
        return x

    def _design_axes(self, names: Sequence[str] | None) -> list[int]:
        """The indices of the parameters whose axes the design probes (``design_params``;
        None: all), in the space's order.

        Raises:
            SettingError: a name that is no parameter of the space.
        """
        if names is None:
            return list(range(self.space.dim))
        unknown = [n for n in names if n not in self.space.names]
        if unknown:
            raise SettingError(
                "design_params", f"names of parameters ({', '.join(self.space.names)})", unknown
            )
        return [i for i, n in enumerate(self.space.names) if n in set(names)]

    def _initial_design(self, rng: np.random.Generator) -> np.ndarray:
        """(n_init, d): the centre (the box's, or with ``design_centre="x0"`` the first x0
        point), two points on each probed axis through it (the face centres, ``"axial"``,
        or the box centre ± 1/3, ``"direct"``; per parameter with ``"auto"``), then Sobol
        points."""
        d = self.space.dim
        centre = np.full(d, 0.5)
        if self.design_centre == "x0" and self.x0 is not None:
            centre = np.clip(self.space.to_unit(self.x0[0]), 0.0, 1.0)
        pts = [centre[None, :]]
        if self.init_design != "sobol" and self._axes:
            axes = np.asarray(self._axes)
            at = [
                DESIGN_AXIS_POINTS[
                    self.init_design if self.init_design != "auto" else auto_design(p)
                ]
                for p in (self.space.params[i] for i in axes)
            ]
            axial = np.tile(centre, (2 * axes.size, 1))
            axial[np.arange(2 * axes.size), np.repeat(axes, 2)] = np.ravel(at)
            pts.append(axial)
        n_more = self.n_init - sum(len(p) for p in pts)
        if n_more > 0:  # the first n_more points of 2^m (the same points as random(n_more),
            # without scipy's warning that a count other than 2^m loses balance)
            sobol = qmc.Sobol(d, scramble=True, seed=rng)
            pts.append(sobol.random_base2(math.ceil(math.log2(n_more)))[:n_more])
        return np.vstack(pts)[: self.n_init]

    def options(self) -> dict[str, Any]:
        extra: dict[str, Any] = {}  # left out at its default: studies from before resume
        if self.improvement_rtol != IMPROVEMENT_RTOL:
            extra["improvement_rtol"] = self.improvement_rtol
        if self.x0 is not None:
            extra["x0"] = self.x0.tolist()
        if self.design_centre != "box":
            extra["design_centre"] = self.design_centre
        if self.design_params is not None:
            extra["design_params"] = list(self.design_params)
        return {
            "surrogate": self.surrogate_name,
            "surrogate_options": {
                k: list(v) if isinstance(v, tuple) else v for k, v in self.surrogate_options.items()
            },
            "n_init": self.n_init,
            "init_design": self.init_design,
            "warp": self.warp,
            "warp_delta": self.warp_delta,
            "length_init": self.length_init,
            "length_min": self.length_min,
            "length_max": self.length_max,
            "success_tol": self.success_tol,
            "failure_tol": self.failure_tol,
            "global_every": self.global_every,
            "escape": self.escape,
            "probe_after": self.probe_after,
            "probe_length_scale": self.probe_length_scale,
            "restart": self.restart,
            "n_candidates": self.n_candidates,
            "faces": self.faces,
            "refit_every": self.refit_every,
            "full_fit_until": self.full_fit_until,
            **extra,
        }

    # ------------------------------------------------------------------ data
    def _centre_index(self) -> int | None:
        """Index of the trust region's centre: the incumbent, or after a collapse that left
        its basin the best point of the fresh region (see :meth:`_move_centre`)."""
        if self.restart != "incumbent" and self._centre_i is not None:
            return self._centre_i
        return self._incumbent()[0]

    def _incumbent(self) -> tuple[int | None, float | None]:
        """Index and value of the best successful evaluation (first on ties)."""
        best_i, best_v = None, None
        for i, v in enumerate(self._y):
            if v is not None and (best_v is None or v < best_v):
                best_i, best_v = i, v
        return best_i, best_v

    def _targets(self) -> np.ndarray:
        """(n,) the surrogate's targets: failures imputed with the worst value, clipped to
        ±MAX_ABS_Y, then warped (see the module docstring)."""
        from kftune.bo.base import MAX_ABS_Y

        ok = [v for v in self._y if v is not None]
        worst = max(ok) if ok else 0.0
        y = np.clip(np.array([worst if v is None else v for v in self._y]), -MAX_ABS_Y, MAX_ABS_Y)
        if self.warp == "log" and y.min() > 0:
            return np.log(y)
        if self.warp == "log-min":
            lo = float(y.min())
            delta = max(self.warp_delta * (float(np.median(y)) - lo), 1e-12 * max(1.0, abs(lo)))
            return np.log(y - lo + delta)
        return y

    # ------------------------------------------------------------------ ask
    def _propose(self) -> Proposal:
        n = len(self._y)
        if self._n_asked < len(self._design):  # = n in sequential use
            return Proposal(u=self._design[self._n_asked].copy(), stage=0, acquisition="init")
        y = self._targets()
        if self._fit_n == n:
            # Later points of a batch: no new result since the last fit, so keep its
            # hyperparameters (one model per batch, as the Kriging believer assumes).
            self.surrogate.condition(self._X, y)
        else:
            full = n <= self.full_fit_until or self._iter % self.refit_every == 0
            self.surrogate.n_restarts = self._n_restarts if full else 0
            self.surrogate.fit(self._X, y)
            self._fit_n = n
        pending = self._pending_u()
        if len(pending):
            # Batch mode, the Kriging believer (Ginsbourger, Le Riche & Carraro, "Kriging is
            # well-suited to parallelize optimization", 2010): every point in flight is
            # believed to return the model's mean there; the model is conditioned on those
            # values with its hyperparameters kept, so the next proposal looks elsewhere.
            y = np.concatenate([y, np.asarray(self.surrogate.predict(pending).mean, float)])
            self.surrogate.condition(np.vstack([self._X, pending]), y)
        ci = self._centre_index()
        centre = self._X[ci if ci is not None else int(np.argmin(y[:n]))]
        # Local EI is measured against the centre's value (and the believed values of the
        # points in flight): the incumbent's until the first collapse, so the same as
        # min(y) then; after a fresh restart, the new region's own best.
        local_ref = float(np.min(np.concatenate([y[[ci]] if ci is not None else y[:n], y[n:]])))
        # The cadence counts proposals asked, not results told, so that in a batch every
        # global_every-th point is global (counting tells, a batch of q saw one value of
        # the counter: with q = 4 and global_every = 4 no step was ever global). In
        # sequential use the two counts are equal.
        escaping = self._force_global > 0
        self._force_global = max(0, self._force_global - 1)
        is_global = escaping or (
            self.global_every > 0 and self._n_model % self.global_every == self.global_every - 1
        )
        self._n_model += 1
        self._join_round()
        af = "std" if escaping else "EI"
        probe = self._axis_probe(centre) if 0 < self._probe_wait <= self._stall else None
        if probe is not None:
            self._stall = 0
            return Proposal(
                u=probe,
                stage=2,
                acquisition="axis-probe",
                hyperparameters=dict(self.surrogate.hyperparameters),
                info={"length": self.length, "centre": ci},
            )
        cand = self._global_candidates() if is_global else self._local_candidates(centre)
        cand = self._fresh(cand)
        ref = float(np.min(y)) if is_global else local_ref
        scores = self._score(cand, ref, af)
        fine = self._fresh(self._refine(cand[np.argsort(-scores)[:5]], is_global))
        cand = np.vstack([cand, fine])
        scores = np.concatenate([scores, self._score(fine, ref, af)])
        if not len(cand):  # every candidate was an asked point: only on degenerate spaces
            cand = self._fresh(self.rng.random((self.n_candidates, self.space.dim)))
            scores = self._score(cand, ref, af)
        j = int(np.argmax(scores))
        return Proposal(
            u=cand[j].copy(),
            stage=2 if is_global else 1,
            acquisition=f"{af}-global" if is_global else f"{af}-local",
            hyperparameters=dict(self.surrogate.hyperparameters),
            info={
                "length": self.length,
                "centre": ci,
                "n_candidates": len(cand),
                "af_value": float(scores[j]),
            },
        )

    def ask(self, n: int | None = None) -> Any:
        """As :meth:`Optimizer.ask`; the trials asked in one call form a round for the
        trust-region update (see :meth:`_observe`)."""
        _, best = self._incumbent()
        ci = self._centre_index()
        self._round = {
            "best": best,
            "centre": self._y[ci] if ci is not None else None,
            "left": 0,
            "local": 0,
            "local_ok": False,
            "global_ok": False,
        }
        try:
            return super().ask(n)
        finally:
            self._round = None

    def _join_round(self) -> None:
        """Register the model-based trial being proposed (number ``_n_asked``) with the
        current round."""
        if self._round is not None:
            self._round["left"] += 1
            self._round_of[self._n_asked] = self._round

    def _n_proposable(self) -> int | None:
        """The initial design is handed out on its own, and the model's first proposal waits
        until all of it is told: a batch that mixed the design's last points with model
        points fantasised the design's values at a mean fitted on the first few, and its
        model points went where the rest of the design then showed nothing was (with q = 4
        on the bundled UKF set, the first model point came from 4 results and 3 guesses)."""
        k = len(self._design)
        if self._n_asked < k:
            return k - self._n_asked
        return 0 if any(t.number < k for t in self.pending_trials) else None

    def _fresh(self, cand: np.ndarray) -> np.ndarray:
        """The rows of ``cand`` (m, d) that are not an asked point, told or pending (to 1e-9,
        max-norm)."""
        asked = np.vstack([self._X, self._pending_u()])
        return cand[~coincides(cand, asked, SAME_POINT_ATOL)]

    def _score(self, cand: np.ndarray, ref: float, af: str) -> np.ndarray:
        """(m,) acquisition values of the candidates (larger is better; NaN → −inf):
        ``"EI"`` log expected improvement over ``ref`` (a warped target), ``"std"`` the
        predictive standard deviation (pure exploration, for the escape after a collapse)."""
        from kftune.bo.acquisition import log_expected_improvement

        if not len(cand):
            return np.empty(0)
        pred = self.surrogate.predict(cand)
        if af == "std":
            s = np.asarray(pred.std, dtype=float)
        else:
            s = np.asarray(log_expected_improvement(pred, ref), dtype=float)
        return np.where(np.isnan(s), -np.inf, s)

    def _length_scales(self) -> np.ndarray | None:
        """(d,) the fitted GP's ARD length scales (unit cube), or ``None`` when the
        surrogate has none."""
        ls = np.asarray(self.surrogate.hyperparameters.get("length_scales", []), dtype=float)
        return ls if ls.size == self.space.dim else None

    def _axis_probe(self, centre: np.ndarray) -> np.ndarray | None:
        """(d,) ``centre`` moved along the coordinate the GP finds least relevant (longest
        length scale, at least ``probe_length_scale``) to the middle of the widest unsampled
        gap of that coordinate among the asked points (told or pending) on the incumbent's
        line (the others within :data:`AXIS_SLAB`); the next such coordinate when that gap
        is under :data:`AXIS_MIN_GAP`; ``None`` when no coordinate qualifies. The midpoint
        of a gap is no asked point, so nothing is proposed twice."""
        d = self.space.dim
        ls = self._length_scales()
        if ls is None:  # a surrogate without ARD length scales: no probes
            return None
        asked = np.vstack([self._X, self._pending_u()])
        for k in np.argsort(-ls, kind="stable"):
            if ls[k] < self.probe_length_scale:
                return None
            others = np.arange(d) != k
            dist = np.max(np.abs(asked[:, others] - centre[others]), axis=1, initial=0.0)
            vals = np.unique(np.concatenate([[0.0, 1.0], asked[dist <= AXIS_SLAB, k]]))
            gaps = np.diff(vals)
            j = int(np.argmax(gaps))
            if gaps[j] >= AXIS_MIN_GAP:
                u = centre.copy()
                u[k] = 0.5 * (vals[j] + vals[j + 1])
                return u
        return None

    def _weights(self) -> np.ndarray:
        """(d,) TuRBO's trust-region shape: length scales over their geometric mean."""
        ls = self._length_scales()
        if ls is None or not np.all(ls > 0):
            return np.ones(self.space.dim)
        return np.clip(ls / math.exp(float(np.mean(np.log(ls)))), 0.25, 4.0)

    def _local_candidates(self, centre: np.ndarray) -> np.ndarray:
        """Uniform points in the trust region, Gaussian ones around ``centre`` (d,) and
        copies moved onto the faces of the box that the region touches."""
        d, m = self.space.dim, self.n_candidates
        half = 0.5 * self.length * self._weights()
        lo, hi = np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)
        u = lo + (hi - lo) * self.rng.random((m, d))
        g = np.clip(centre + 0.25 * half * self.rng.standard_normal((m // 2, d)), lo, hi)
        out = [u, g]
        if self.faces:
            out.append(self._snap(np.vstack([u[: m // 4], centre[None, :]]), lo, hi))
        return np.vstack(out)

    def _global_candidates(self) -> np.ndarray:
        """Uniform points in the unit cube and copies moved onto its faces."""
        d, m = self.space.dim, self.n_candidates
        u = self.rng.random((m, d))
        if not self.faces:
            return u
        return np.vstack([u, self._snap(u[: m // 4], np.zeros(d), np.ones(d))])

    def _snap(self, pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Copies of ``pts`` (k, d) with each coordinate whose range [lo, hi] reaches a face
        of the unit cube moved onto that face with probability ½, and the last point with
        all of them moved (the nearest corner or face point of the region)."""
        at_lo, at_hi = lo <= 0.0, hi >= 1.0
        if not (at_lo.any() or at_hi.any()):
            return np.empty((0, self.space.dim))
        p = pts.copy()
        pick = self.rng.random(p.shape) < 0.5
        p[:, at_lo] = np.where(pick[:, at_lo], 0.0, p[:, at_lo])
        p[:, at_hi] = np.where(pick[:, at_hi], 1.0, p[:, at_hi])
        q = pts[-1:].copy()
        q[:, at_lo], q[:, at_hi] = 0.0, 1.0
        return np.vstack([p, q])

    def _refine(self, top: np.ndarray, is_global: bool) -> np.ndarray:
        """Gaussian perturbations around the best candidates ``top`` (k, d): a second,
        finer round (scale 0.05 globally, L/10 locally, shaped like the region)."""
        scale = (0.05 if is_global else 0.1 * self.length) * self._weights()
        m = max(1, self.n_candidates // 10)
        p = top[:, None, :] + scale * self.rng.standard_normal((len(top), m, self.space.dim))
        return np.clip(p.reshape(-1, self.space.dim), 0.0, 1.0)

    # ------------------------------------------------------------------ tell
    def _observe(self, trial: Trial, value: float | None) -> None:
        """Store the result; when it completes its round, update the trust region once for
        the round (TuRBO's batch rule, Eriksson et al. 2019): a round succeeds when any of
        its points beats the incumbent it was asked against (by ``improvement_rtol`` of its
        value), and
        fails otherwise; failures count local evaluations, so a failed round of m local
        points counts m towards ``failure_tol`` (TuRBO's ⌈max(4, d)/q⌉ rounds). Counting
        per told point instead halved the region in a batch of 4 whose first point
        improved and whose other three did not. With one point per round this is the
        sequential rule exactly.

        Local steps and axis probes are measured against the region's centre, global and
        escape steps against the incumbent; the two are the same point until the first
        collapse (and always with ``restart="incumbent"``)."""
        global_ei = (
            trial.stage == 2
            and trial.acquisition is not None
            and trial.acquisition.startswith("EI")
        )
        self._move_centre(len(self._y), value, global_ei)
        self._X = np.vstack([self._X, trial.u[None, :]])
        self._y.append(value)
        if trial.acquisition == "init":
            return
        self._iter += 1
        rnd = self._round_of.pop(trial.number)
        local = trial.stage == 1 or trial.acquisition == "axis-probe"
        before = rnd["centre"] if local else rnd["best"]
        improved = (
            value is not None
            and before is not None
            and value < before - self.improvement_rtol * abs(before)
        )
        self._stall = 0 if improved else self._stall + 1
        if improved:  # axis probes: see the module docstring
            self._probe_wait = self.probe_after
        elif trial.acquisition == "axis-probe":
            self._probe_wait *= 2
        if trial.stage == 2:
            rnd["global_ok"] = rnd["global_ok"] or improved
        else:
            rnd["local"] += 1
            rnd["local_ok"] = rnd["local_ok"] or improved
        rnd["left"] -= 1
        if rnd["left"] == 0:
            self._update_region(rnd)

    def _move_centre(self, i: int, value: float | None, global_ei: bool) -> None:
        """Make result ``i`` the region's centre when it beats the centre — or, for a global
        EI step, the incumbent (a global step that finds only a basin already left does not
        pull the region back there). Until the first collapse the centre is the incumbent,
        as always with ``restart="incumbent"``."""
        if self.restart == "incumbent" or value is None:
            return
        if global_ei:
            _, best = self._incumbent()
            if best is None or value < best:
                self._centre_i = i
        else:
            centre = None if self._centre_i is None else self._y[self._centre_i]
            if centre is None or value < centre:  # a centre is always a completed point
                self._centre_i = i

    def _update_region(self, rnd: dict[str, Any]) -> None:
        """The trust-region update for a completed round (see :meth:`_observe`)."""
        if rnd["global_ok"]:  # a global step improved: re-centre the region afresh
            self._force_global = 0
            self.length = self.length_init
            self.n_success = self.n_failure = 0
            return
        if not rnd["local"]:
            return
        if rnd["local_ok"]:
            self.n_success, self.n_failure = self.n_success + 1, 0
        else:
            self.n_success, self.n_failure = 0, self.n_failure + rnd["local"]
        if self.n_success >= self.success_tol:
            self.length = min(2.0 * self.length, self.length_max)
            self.n_success = 0
        elif self.n_failure >= self.failure_tol:
            self.length /= 2.0
            self.n_failure = 0
            if self.length < self.length_min:  # collapsed: start again, look elsewhere first
                self.tr_restarts += 1
                self.length = self.length_init
                self._force_global = self.escape
                if self.restart != "incumbent":
                    # A fresh region is centred on the escape steps' best; "alternate"
                    # first re-polishes the incumbent's basin, then leaves it, and so on.
                    fresh = self.restart == "fresh" or self.tr_restarts % 2 == 0
                    self._centre_i = None if fresh else self._incumbent()[0]
