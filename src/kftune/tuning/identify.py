"""Whether the data determine each tuned parameter: value against start, bounds, and a profile.

What a system-identification engineer reads after an estimate (Ljung, *System
Identification*, 2nd ed., 1999, Ch. 9.2; Raue et al., "Structural and practical
identifiability analysis of partially observed dynamical models by exploiting the profile
likelihood", Bioinformatics 25(15), 2009): for each parameter its value against the start,
whether it sits on a bound of the box, and how far it can move before the cost notices.

Everything is measured in the *search scale* of the parameter, ``t = log10 x`` on a log10
scale (a change of t by δ is a factor 10^δ) and ``t = x`` on a linear one, along the
parameter's 1-D **profile**: the cost J at points ``t* ± h`` with every other coordinate
held at the best point x* (a *conditional* profile; see below). Steps h are fixed shares
:data:`STEPS` of the box width W (in t), clipped at the bounds, plus the bound itself where
it lies beyond the widest step, so that the profile reaches both ends of the box:
at most ``2·(len(STEPS) + 1)`` = :data:`MAX_EVALS_PER_PARAMETER` evaluations per parameter,
and one at x* shared by all.

* **Curvature** c = ∂²J/∂t² by the second divided difference of three profile points
  t_a < t_b < t_c (for the central pair t* ± h: the central difference
  c = (J(t*+h) + J(t*−h) − 2J(t*))/h²), once per step. Small steps resolve the local shape
  but magnify any roughness of J (an error σ in J gives an error ≈ 2σ/h² in c), wide ones
  see beyond the quadratic region; the reported c is the one whose rise of J is nearest
  the threshold ΔJ below — the scale the confidence range lives on — and every step's
  estimate is kept (``curvature_steps``) so that their agreement can be read.
* **Confidence range** from the curvature: the quadratic J ≈ J* + c·δ²/2 rises by ΔJ at
  δ = √(2·ΔJ/c) (a Wald-type interval; with ΔJ = 1.92 on a negative log-likelihood, the
  95 % interval of a χ²₁ test, Ljung Ch. 9.2).
* **Profile range**: the interval of t around t* where J ≤ J* + ΔJ, from the profile
  itself, out to its farthest point under the threshold on each side (so that one rough
  value cannot shorten it), the crossing interpolated linearly in √(J − J*) — exact for a
  quadratic profile. A side whose profile stays below the threshold up to the bound is
  *open*: the box, not the data, ends the range there.
* **Determined** when the range is closed on both sides (the cost rises by ΔJ before
  either bound) and spans less than :data:`NOT_DETERMINED_SHARE` of the box; otherwise the
  parameter is said plainly to be not determined — only a lower limit, only an upper limit,
  or flat across the box. ΔJ is chosen by the cost's kind (:func:`rise_of`): for a cost
  that is a mean negative log-likelihood per scored sample (``nlpd``, ``pem``: shifted by
  unit-dependent constants, J* may be near 0 or negative, so a share of |J*| means
  nothing) the likelihood-ratio rise ΔJ = χ²₁(0.95)/(2N) ≈ 1.92/N with N the scored
  samples, pooled over the manoeuvres (the profile range is then a 95 % likelihood-ratio
  interval; the samples of a recording are correlated, so N overstates the independent
  information and the interval is if anything too narrow); for any other cost (the NRMSE
  kinds) :data:`REL_RISE` (1 %) of |J*|.

The profile is conditional (the other coordinates held, not re-optimised at each point)
because a re-optimised profile costs a tuning run per point — some hundred evaluations
each. Measured against one (``benchmarks/identifiability.py``, BENCHMARKS.md: three
datasets, C_af, C_ar and μ tuned with Q) the held ranges are several times narrower (the
noise parameters trade off with the model's), while the verdicts agreed on all nine.
Holding the others can only make a valley narrower than the re-optimised profile
(a trade-off with another parameter is not followed), so a parameter found *not
determined* here is not determined, while *determined* could overstate what the data say
when two parameters trade off (the front and rear cornering stiffness through the
understeer gradient). For those, one more point per pair of reported parameters gives
the cross curvatures, and with them the curvature matrix H over the reported parameters:
the **joint range** √(2·ΔJ·(H⁻¹)_ii) with the other reported parameters re-fitted on that
quadratic, and the correlations of the estimates (:func:`_joint`); a parameter whose joint
range spans half its box or more is not determined either. The noise parameters stay held:
a curvature matrix over every coordinate (18 more evaluations at d = 6, tried on the
bundled set's TR-BO point) is no substitute: it was indefinite there (a negative curvature
along q_r, whose box spans ten decades), and the valley a re-fit follows is not quadratic
on the scale of the steps.

Cost: at most ``MAX_EVALS_PER_PARAMETER·k + 1 + k(k−1)/2`` evaluations for k reported
parameters (34 for C_af, C_ar and μ), in two batches.

Physical reasons a model can know (a friction coefficient on data far from the friction
limit) come from the model's optional hook :attr:`~kftune.models.StateSpaceModel.param_hints`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from kftune.space import BOUND_TOL, Space

if TYPE_CHECKING:
    from kftune.tuning.problem import TuningProblem

#: Relative rise of the cost that marks the edge of a parameter's confidence range.
REL_RISE = 0.01
#: Costs that are a mean negative log-likelihood per scored sample: their range ends at
#: the likelihood-ratio rise (:func:`rise_of`), not at a share of |J*|.
MEAN_NLL_KINDS: tuple[str, ...] = ("nlpd", "pem")
#: What a parameter's range is when the search matrix over the tuned parameters has no
#: positive definite quadratic: the one-parameter profile cannot rule out a trade-off.
NOT_JOINT = (
    "not checked jointly: the curvature matrix is not positive definite — parameters may trade off"
)
#: A parameter whose range spans at least this share of its box is not determined.
NOT_DETERMINED_SHARE = 0.5
#: Correlations of at least this size are named with a parameter.
STRONG_CORRELATION = 0.9
#: Profile steps on each side of the best point, as shares of the box width (search scale).
STEPS: tuple[float, ...] = (0.01, 0.03, 0.1, 0.3)
#: Profile evaluations per parameter at most: each step on both sides, and both bounds.
MAX_EVALS_PER_PARAMETER = 2 * (len(STEPS) + 1)
#: What the profile holds fixed, in words (for the tuned file and the printed lines).
METHOD = (
    "1-D profile of the cost in the search scale with the other parameters held at the "
    "best point; curvature by second differences of the profile, and over the tuned "
    "parameters jointly from one more point per pair"
)

#: J over a batch of points: (B, d) natural units → (B,) costs, inf (or NaN) where the
#: evaluation failed (a diverged filter).
CostBatch = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ParameterIdentifiability:
    """What the data say about one tuned parameter (module docstring).

    Attributes:
        name, unit: the parameter and its unit ("" if none).
        scale: ``"log10"`` or ``"linear"``: the search scale t (log10 x or x).
        value: the best value x*; start: the start (recorded) value, or None.
        low, high: the search box, natural units.
        on_bound: ``"lower"``/``"upper"`` when x* lies within 1 % of the box of a bound
            (:data:`kftune.space.BOUND_TOL`, in the search scale), else None.
        cost: J at the best point; delta_j: the rise ΔJ that ends the range.
        curvature: ∂²J/∂t² at the best point [J per decade² on log10, per unit² on
            linear], None where no step saw J rise (flat, or not a minimum).
        curvature_steps: (step h in t, curvature estimate) for every step, widest last.
        half_width: √(2·ΔJ/curvature) [decades or units of x], None without curvature.
        range_low, range_high: the profile range in natural units (J ≤ J* + ΔJ).
        closed_low, closed_high: whether J rose by ΔJ before the bound on that side.
        share: (t(range_high) − t(range_low)) / W, the share of the box the range spans.
        determined: closed on both sides and ``share < NOT_DETERMINED_SHARE``.
        better: (value, J) of a profile point with J below J* by more than ΔJ/10, or
            None: the search had not converged along this parameter.
        profile: (value, J) of every profile point, the best point included, by value;
            J is inf where the evaluation failed.
        reason: a physical reason from the model why the data may not determine it.
        joint_half_width: √(2·ΔJ·(H⁻¹)_ii) [decades or units of x], the half-width with
            the other reported parameters re-fitted on the quadratic J ≈ J* + ½ δᵀHδ
            over them (H their curvature matrix in the search scale); None where H is not
            positive definite or the parameter has no curvature.
        correlations: other reported parameter → the correlation
            (H⁻¹)_ij / √((H⁻¹)_ii·(H⁻¹)_jj) of the two estimates (near ±1: the data
            determine a combination of them, not each).
        joint_note: why the joint check could not be made (:data:`NOT_JOINT`), None
            where it was made or not needed; such a parameter is not determined.
    """

    name: str
    unit: str
    scale: str
    value: float
    start: float | None
    low: float
    high: float
    on_bound: str | None
    cost: float
    delta_j: float
    curvature: float | None
    curvature_steps: tuple[tuple[float, float], ...]
    half_width: float | None
    range_low: float
    range_high: float
    closed_low: bool
    closed_high: bool
    share: float
    determined: bool
    better: tuple[float, float] | None
    profile: tuple[tuple[float, float], ...]
    reason: str | None = None
    joint_half_width: float | None = None
    correlations: Mapping[str, float] = field(default_factory=dict)
    joint_note: str | None = None

    @property
    def ratio(self) -> float | None:
        """x* / start, None without a (non-zero) start."""
        if self.start is None or self.start == 0:
            return None
        return self.value / self.start

    @property
    def limits(self) -> str:
        """Which ends of the range the data set: ``"both"``, ``"lower"``, ``"upper"``,
        ``"none"``."""
        if self.closed_low and self.closed_high:
            return "both"
        return "lower" if self.closed_low else "upper" if self.closed_high else "none"

    def _joint_range(self) -> tuple[float, float]:
        """x* moved by ∓ ``joint_half_width`` in the search scale, clipped to the box."""
        h = self.joint_half_width or 0.0
        log = self.scale == "log10"
        t = _to_t(log, self.value)
        return (
            max(self.low, _from_t(log, t - h)),
            min(self.high, _from_t(log, t + h)),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (strict JSON: no inf or NaN)."""
        ratio = self.ratio
        return {
            "value": self.value,
            "start": self.start,
            "ratio": ratio,
            "change_pct": None if ratio is None else 100.0 * (ratio - 1.0),
            "unit": self.unit,
            "scale": self.scale,
            "low": self.low,
            "high": self.high,
            "on_bound": self.on_bound,
            "determined": self.determined,
            "limits": self.limits,
            "range": [self.range_low, self.range_high],
            "share_of_box": self.share,
            "curvature": self.curvature,
            "half_width": self.half_width,
            "joint_half_width": self.joint_half_width,
            "correlations": dict(self.correlations),
            "curvature_steps": [[h, c] for h, c in self.curvature_steps],
            "better": None if self.better is None else list(self.better),
            "profile": [[v, _finite_or_none(j)] for v, j in self.profile],
            "reason": self.reason,
            "cost": self.cost,
            "delta_j": self.delta_j,
            "joint_note": self.joint_note,
        }

    @classmethod
    def from_dict(cls, name: str, d: Mapping[str, Any]) -> ParameterIdentifiability:
        """Inverse of :meth:`to_dict` (a profile point recorded as null failed: inf).

        Raises:
            ValueError: a key missing or of the wrong kind, naming it.
        """
        try:
            limits = str(d["limits"])
            better = d["better"]
            return cls(
                name=str(name),
                unit=str(d["unit"]),
                scale=str(d["scale"]),
                value=float(d["value"]),
                start=None if d["start"] is None else float(d["start"]),
                low=float(d["low"]),
                high=float(d["high"]),
                on_bound=None if d["on_bound"] is None else str(d["on_bound"]),
                cost=float(d["cost"]),
                delta_j=float(d["delta_j"]),
                curvature=_float_or_none(d["curvature"]),
                curvature_steps=tuple((float(h), float(c)) for h, c in d["curvature_steps"]),
                half_width=_float_or_none(d["half_width"]),
                range_low=float(d["range"][0]),
                range_high=float(d["range"][1]),
                closed_low=limits in ("both", "lower"),
                closed_high=limits in ("both", "upper"),
                share=float(d["share_of_box"]),
                determined=bool(d["determined"]),
                better=None if better is None else (float(better[0]), float(better[1])),
                profile=tuple(
                    (float(v), math.inf if j is None else float(j)) for v, j in d["profile"]
                ),
                reason=None if d["reason"] is None else str(d["reason"]),
                joint_half_width=_float_or_none(d["joint_half_width"]),
                correlations={str(k): float(v) for k, v in dict(d["correlations"]).items()},
                joint_note=None if d.get("joint_note") is None else str(d["joint_note"]),
            )
        except KeyError as exc:
            raise ValueError(f"parameter {name!r}: no {exc.args[0]!r}") from None
        except (TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"parameter {name!r}: malformed record ({exc})") from None

    def describe(self) -> str:
        """One or two lines for ``kftune tune``: value against start, bound, verdict."""
        unit = f" {self.unit}" if self.unit and self.unit != "-" else ""
        text = f"{self.name} = {self.value:.4g}{unit}"
        ratio = self.ratio
        if ratio is not None:
            text += f" (×{ratio:.3g} the start {self.start:.4g}, {100 * (ratio - 1):+.0f} %)"
        if self.on_bound is not None:
            bound = self.low if self.on_bound == "lower" else self.high
            text += f", on its {self.on_bound} bound {bound:g}"
        if self.better is not None:  # not a minimum along it: no range can be read
            v, j = self.better
            text += (
                f": not assessed: the search had not converged along {self.name} (the cost "
                f"is lower at {self.name} = {v:.4g}, by {self.cost - j:.3g}: "
                f"{(self.cost - j) / self.delta_j:.3g}× the rise that ends a range; tune "
                "again with a larger -n, a new --storage, to let it get there)"
            )
            return text + (f"\n      {self.reason}" if self.reason else "")
        lo, hi = self.range_low, self.range_high
        span = f"{lo:.3g} … {hi:.3g}"
        partner = max(self.correlations.items(), key=lambda kv: abs(kv[1]), default=None)
        traded = ""
        if partner is not None and abs(partner[1]) >= STRONG_CORRELATION:
            traded = f"it trades off with {partner[0]} (correlation {partner[1]:+.2f})"
            if self.joint_half_width is not None:
                lo_j, hi_j = self._joint_range()
                traded += f": {lo_j:.3g} … {hi_j:.3g} when {partner[0]} moves too"
        if self.determined:
            text += f": determined, {span}"
            if self.scale == "log10":
                text += f" (×{lo / self.value:.3g} … ×{hi / self.value:.3g})"
            if traded:
                text += f"; {traded}"
        else:
            what = {
                "both": f"{span} with the others held, but "
                + (traded or self.joint_note or "not jointly")
                if self.share < NOT_DETERMINED_SHARE
                else f"the range {span} spans {100 * self.share:.0f} % of the box",
                "lower": f"only a lower limit, ≥ {lo:.3g} ("
                + (
                    "it sits on the upper bound: the optimum may lie beyond"
                    if self.on_bound == "upper"
                    else f"the cost is flat up to the upper bound {self.high:g}"
                )
                + ")",
                "upper": f"only an upper limit, ≤ {hi:.3g} ("
                + (
                    "it sits on the lower bound: the optimum may lie beyond"
                    if self.on_bound == "lower"
                    else f"the cost is flat down to the lower bound {self.low:g}"
                )
                + ")",
                "none": f"the cost is flat across the box [{self.low:g}, {self.high:g}]",
            }[self.limits]
            text += f": NOT determined by these data — {what}"
        if self.reason and not self.determined:
            text += f"\n      {self.reason}"
        return text


@dataclass(frozen=True)
class Identifiability:
    """The identifiability of the tuned parameters of one best point.

    Attributes:
        parameters: one record per reported parameter, in search-space order.
        rel_rise: ΔJ / |J*| where the range ends at a relative rise. n_evals: the cost
            evaluations spent. method: what was held.
        abs_rise: ΔJ itself where the range ends at an absolute rise (a mean negative
            log-likelihood: :func:`rise_of`), else None; n_scored: the N of that rise.
    """

    parameters: tuple[ParameterIdentifiability, ...]
    rel_rise: float
    n_evals: int
    method: str = METHOD
    abs_rise: float | None = None
    n_scored: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``identifiability`` of the tuned file and ``--json``)."""
        return {
            "method": self.method,
            "rel_rise": self.rel_rise,
            "not_determined_share": NOT_DETERMINED_SHARE,
            "n_evals": self.n_evals,
            "abs_rise": self.abs_rise,
            "n_scored": self.n_scored,
            "parameters": {p.name: p.to_dict() for p in self.parameters},
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Identifiability:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: a key missing or of the wrong kind, naming it (and the parameter).
        """
        try:
            return cls(
                tuple(
                    ParameterIdentifiability.from_dict(n, p)
                    for n, p in dict(d["parameters"]).items()
                ),
                float(d["rel_rise"]),
                int(d["n_evals"]),
                str(d["method"]),
                _float_or_none(d.get("abs_rise")),
                None if d.get("n_scored") is None else int(d["n_scored"]),
            )
        except KeyError as exc:
            raise ValueError(f"no {exc.args[0]!r}") from None
        except (TypeError, AttributeError) as exc:
            raise ValueError(f"malformed record ({exc})") from None

    def lines(self) -> list[str]:
        """What ``kftune tune`` prints; nothing without parameters."""
        if not self.parameters:
            return []
        rise = (
            f"{100 * self.rel_rise:g} %"
            if self.abs_rise is None
            else f"χ²₁(0.95)/2N = {self.abs_rise:.3g} (a likelihood-ratio 95 % interval, "
            f"N = {self.n_scored} scored samples)"
        )
        out = [
            f"tuned model parameters (range: where the cost rises by less than {rise} with "
            f"the other parameters held, narrower than with them re-fitted; {self.n_evals} "
            "extra evaluations):"
        ]
        out += [f"  {p.describe()}" for p in self.parameters]
        return out


def identify(
    cost: CostBatch,
    space: Space,
    x_best: Sequence[float] | np.ndarray,
    names: Sequence[str],
    *,
    start: Mapping[str, float] | None = None,
    units: Mapping[str, str] | None = None,
    reasons: Mapping[str, str] | None = None,
    rel_rise: float = REL_RISE,
    abs_rise: float | None = None,
    n_scored: int | None = None,
) -> Identifiability:
    """Profile the cost along each parameter in ``names`` around ``x_best`` (module
    docstring): at most :data:`MAX_EVALS_PER_PARAMETER` evaluations per parameter and one
    at ``x_best``, all in one call of ``cost``.

    Args:
        cost: J of a (B, d) batch of points of ``space`` (natural units) → (B,), inf or
            NaN where an evaluation failed (counted as a rise of the cost).
        space: the search space; x_best: (d,) the best point, natural units.
        names: the parameters to report (names of ``space``; may be empty).
        start: name → the start value, for the ratio; units: name → unit.
        reasons: name → a physical reason the data may not determine it (printed with a
            parameter found not determined).
        rel_rise: ΔJ / |J*|, the rise that ends a range (> 0).
        abs_rise: ΔJ itself (> 0), in place of ``rel_rise`` (a mean negative
            log-likelihood: :func:`rise_of`); n_scored: its N, recorded with it.

    Raises:
        ValueError: a name not in the space, a point outside it, ``rel_rise`` or
            ``abs_rise`` ≤ 0, or a best point whose cost is not finite.
    """
    x = np.asarray(x_best, dtype=float)
    if x.shape != (space.dim,):
        raise ValueError(f"x_best must have shape ({space.dim},), got {x.shape}")
    unknown = [n for n in names if n not in space.names]
    if unknown:
        raise ValueError(f"parameters {unknown} are not in the search space {list(space.names)}")
    if not space.contains(x):
        raise ValueError("x_best lies outside the search space")
    if not (isinstance(rel_rise, (int, float)) and rel_rise > 0 and math.isfinite(rel_rise)):
        raise ValueError(f"rel_rise must be a positive number, got {rel_rise!r}")
    if abs_rise is not None and not (
        isinstance(abs_rise, (int, float)) and abs_rise > 0 and math.isfinite(abs_rise)
    ):
        raise ValueError(f"abs_rise must be a positive number, got {abs_rise!r}")
    plans = {n: _profile_offsets(space, x, space.names.index(n)) for n in names}
    points = [x]
    for n, offsets in plans.items():
        i = space.names.index(n)
        p = space.params[i]
        t0 = _to_t(p.log, x[i])
        for h in offsets:
            xi = x.copy()
            xi[i] = float(np.clip(_from_t(p.log, t0 + h), p.low, p.high))
            points.append(xi)
    values = np.asarray(cost(np.array(points)), dtype=float).reshape(-1)
    if values.shape != (len(points),):
        raise ValueError(f"cost returned {values.shape[0]} values for {len(points)} points")
    values = np.where(np.isnan(values), np.inf, values)
    j0 = float(values[0])
    if not math.isfinite(j0):
        raise ValueError("the cost at the best point is not finite")
    if abs_rise is not None:
        delta_j = float(abs_rise)
    else:
        delta_j = rel_rise * abs(j0) if j0 != 0 else rel_rise
    records = []
    k = 1
    for n, offsets in plans.items():
        js = values[k : k + len(offsets)]
        k += len(offsets)
        records.append(
            _record(
                space,
                x,
                n,
                offsets,
                js,
                j0,
                delta_j,
                start=(start or {}).get(n),
                unit=(units or {}).get(n, ""),
                reason=(reasons or {}).get(n),
            )
        )
    pairs = _joint(cost, space, x, records, plans, values, delta_j)
    return Identifiability(
        tuple(pairs[0]),
        float(rel_rise),
        len(points) + pairs[1],
        abs_rise=None if abs_rise is None else float(abs_rise),
        n_scored=n_scored if abs_rise is not None else None,
    )


def rise_of(kind: str, n_scored: int) -> float | None:
    """The absolute rise ΔJ that ends a range for a cost of ``kind`` over ``n_scored``
    samples, or None for the relative :data:`REL_RISE`: a mean negative log-likelihood
    per sample (:data:`MEAN_NLL_KINDS`) rises by χ²₁(0.95)/(2N) at the edge of the 95 %
    likelihood-ratio interval (N·ΔJ = 1.92: twice the log-likelihood ratio is χ²₁),
    whatever constant the units add to J; the NRMSE kinds scale with the error, so a
    share of J* is the invariant rise there."""
    if kind not in MEAN_NLL_KINDS:
        return None
    if n_scored <= 0:
        raise ValueError(f"need a positive number of scored samples, got {n_scored!r}")
    from scipy.stats import chi2

    return float(chi2.ppf(0.95, 1)) / (2.0 * n_scored)


def _joint(
    cost: CostBatch,
    space: Space,
    x: np.ndarray,
    records: Sequence[ParameterIdentifiability],
    plans: Mapping[str, Sequence[float]],
    values: np.ndarray,
    delta_j: float,
) -> tuple[list[ParameterIdentifiability], int]:
    """The curvature matrix H over the reported parameters that have a curvature, and
    from it each one's joint half-width and correlations; (records, evaluations spent).

    H_ii is the profile's curvature; H_ij = (J(x* + s_i e_i + s_j e_j) − J(x* + s_i e_i)
    − J(x* + s_j e_j) + J*)/(s_i·s_j) from one more point per pair, with s_i the offset of
    the profile point nearest the step of the chosen curvature (exact for a quadratic).
    A parameter whose joint range spans at least :data:`NOT_DETERMINED_SHARE` of its box
    is not determined either."""
    curved = [r for r in records if r.curvature is not None]
    if len(curved) < 2:
        return [replace(r, joint_half_width=r.half_width) for r in records], 0
    starts, k = {}, 1
    for n, offsets in plans.items():
        starts[n] = k
        k += len(offsets)
    axis = {}
    for r in curved:
        offs = plans[r.name]
        js = values[starts[r.name] : starts[r.name] + len(offs)]
        step = _chosen_step(r.curvature_steps, delta_j)
        axis[r.name] = _axis_point(offs, js, step)
    index = [space.names.index(r.name) for r in curved]
    pairs = list(itertools.combinations(range(len(curved)), 2))
    points = []
    for a, b in pairs:
        xp = x.copy()
        for c in (a, b):
            p = space.params[index[c]]
            t = _to_t(p.log, x[index[c]]) + axis[curved[c].name][0]
            xp[index[c]] = float(np.clip(_from_t(p.log, t), p.low, p.high))
        points.append(xp)
    js = np.asarray(cost(np.array(points)), dtype=float).reshape(-1)
    j0 = curved[0].cost
    hess: np.ndarray = np.diag([r.curvature for r in curved if r.curvature is not None])
    for (a, b), j in zip(pairs, js):
        (sa, ja), (sb, jb) = axis[curved[a].name], axis[curved[b].name]
        hess[a, b] = hess[b, a] = (j - ja - jb + j0) / (sa * sb) if math.isfinite(j) else math.nan
    try:
        if not np.all(np.isfinite(hess)):
            raise np.linalg.LinAlgError
        np.linalg.cholesky(hess)
        cov = np.linalg.inv(hess)
    except np.linalg.LinAlgError:  # no joint quadratic: a trade-off cannot be ruled out
        unchecked = {r.name for r in curved}
        return [
            replace(r, determined=False, joint_note=NOT_JOINT) if r.name in unchecked else r
            for r in records
        ], len(points)
    sd = np.sqrt(np.diag(cov))
    joint = {}
    for a, r in enumerate(curved):
        half = math.sqrt(2.0 * delta_j * cov[a, a])
        width = space.params[index[a]].width
        joint[r.name] = replace(
            r,
            joint_half_width=half,
            correlations={
                curved[b].name: float(cov[a, b] / (sd[a] * sd[b]))
                for b in range(len(curved))
                if b != a
            },
            determined=r.determined and 2.0 * half / width < NOT_DETERMINED_SHARE,
        )
    return [joint.get(r.name, r) for r in records], len(points)


def identify_problem(
    problem: TuningProblem,
    x_best: Sequence[float] | np.ndarray,
    names: Sequence[str] | None = None,
    *,
    rel_rise: float = REL_RISE,
) -> Identifiability:
    """:func:`identify` on a tuning problem: the tuned model parameters by default
    (``problem.parameterization.model_names``, their start values ``model_start`` and the
    model's units), J from :meth:`TuningProblem.evaluate_batch` (a diverged filter counts
    as a rise of the cost), and the model's physical reasons
    (:attr:`~kftune.models.StateSpaceModel.param_hints`) on the training manoeuvres at
    the best point's model parameters. J is the cost as tuned: with the covariance scale
    1, whatever calibration ``problem.cov_scale`` holds (restored afterwards). The rise
    that ends a range follows the cost's kind (:func:`rise_of`, N the samples scored after
    the burn-in over all manoeuvres)."""
    from kftune.tuning.runs import first_scored

    par = problem.parameterization
    names = par.model_names if names is None else tuple(names)
    if not names:
        return Identifiability((), float(rel_rise), 0)
    model = problem.model
    units = dict(zip(model.param_names, model.param_units))
    reasons = _hints(problem, x_best, names)
    n_scored = sum(m.n - first_scored(m, problem.burn_in) for m in problem.manoeuvres)
    abs_rise = rise_of(problem.cost_spec.kind, n_scored)

    def cost(points: np.ndarray) -> np.ndarray:
        out = problem.evaluate_batch(points)
        return np.array([getattr(e, "cost", math.inf) for e in out], dtype=float)

    scale, problem.cov_scale = problem.cov_scale, 1.0
    try:
        return identify(
            cost,
            problem.space,
            x_best,
            names,
            start=par.model_start,
            units=units,
            reasons=reasons,
            rel_rise=rel_rise,
            abs_rise=abs_rise,
            n_scored=n_scored,
        )
    finally:
        problem.cov_scale = scale


#: The most characters of a model's hint that are kept (a model file's text).
HINT_CHARS = 200


def _hints(
    problem: TuningProblem, x_best: Sequence[float] | np.ndarray, names: Sequence[str]
) -> dict[str, str]:
    """The model's physical reasons (:attr:`~kftune.models.StateSpaceModel.param_hints`)
    for the tuned ``names``, on the training manoeuvres at the best point. The hook may
    come from a user's model file: an exception is reported as one line naming its type
    (no traceback), texts are cut to :data:`HINT_CHARS`, names not tuned are ignored."""
    from kftune.errors import excerpt

    model = problem.model
    if model.param_hints is None:
        return {}
    channels = (*model.input_names, *model.measurement_names)
    runs = [(m.dt, {c: m.channel(c) for c in channels if m.has(c)}) for m in problem.manoeuvres]
    try:
        said = model.param_hints(runs, np.asarray(problem.params_at(x_best), dtype=float))
        items = list(dict(said).items())
    except Exception as exc:  # a model file's code: its failure is no failure of tune
        return {n: f"hint failed: {type(exc).__name__}" for n in names}
    return {
        k: v if isinstance(v, str) and len(v) <= HINT_CHARS else excerpt(v, HINT_CHARS)
        for k, v in items
        if isinstance(k, str) and k in names
    }


# ---------------------------------------------------------------------------- helpers


def _to_t(log: bool, v: float) -> float:
    return math.log10(v) if log else float(v)


def _from_t(log: bool, t: float) -> float:
    return 10.0**t if log else float(t)


def rise_pct(j: float, j_best: float) -> float:
    """100·(J − J*)/|J*| [%]: the rise of the cost over its best value, also for a cost
    that can be negative (a log-likelihood); relative to 1 where J* = 0."""
    return 100.0 * (j - j_best) / (abs(j_best) or 1.0)


def _float_or_none(v: Any) -> float | None:
    return None if v is None else float(v)


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _profile_offsets(space: Space, x: np.ndarray, i: int) -> list[float]:
    """Offsets in t of the profile of parameter i: ±h·W for h in :data:`STEPS`, clipped at
    the bounds, and the bound itself where it lies beyond the widest step; points closer
    than half the smallest step to x* or to each other are left out. Left side first
    (outwards), then the right side (outwards)."""
    p = space.params[i]
    lo, hi = p._t_bounds
    t0 = _to_t(p.log, x[i])
    width = hi - lo
    gap = 0.5 * STEPS[0] * width
    out: list[float] = []
    for sign, room in ((-1.0, t0 - lo), (1.0, hi - t0)):
        side: list[float] = []
        for h in (*(s * width for s in STEPS), room):
            d = min(h, room)
            if d >= gap and all(abs(d - e) >= gap for e in side):
                side.append(d)
        out += [sign * d for d in sorted(side)]
    return out


def _record(
    space: Space,
    x: np.ndarray,
    name: str,
    offsets: Sequence[float],
    js: np.ndarray,
    j0: float,
    delta_j: float,
    *,
    start: float | None,
    unit: str,
    reason: str | None,
) -> ParameterIdentifiability:
    """One parameter's record from its profile (offsets in t and their costs)."""
    i = space.names.index(name)
    p = space.params[i]
    log = p.log
    lo, hi = p._t_bounds
    width = hi - lo
    t0 = _to_t(log, x[i])
    left = [(-h, float(j)) for h, j in zip(offsets, js) if h < 0]  # outwards
    right = [(h, float(j)) for h, j in zip(offsets, js) if h > 0]
    threshold = j0 + delta_j
    # the range on each side: out to its farthest point under the threshold
    ends: list[tuple[float, bool]] = []
    for side, room in ((left, t0 - lo), (right, hi - t0)):
        d, closed = _side_end(side, j0, delta_j, threshold)
        ends.append((d if closed else room, closed))  # open: flat up to the bound
    (d_lo, closed_lo), (d_hi, closed_hi) = ends
    share = (d_lo + d_hi) / width
    steps = _curvatures(left, right, j0)
    curvature = _chosen_curvature(steps, delta_j)
    hits = space.on_bounds(space.to_unit(x), BOUND_TOL)
    on_bound = next((h.side for h in hits if h.name == name), None)
    along = [float(np.clip(_from_t(log, t0 + h), p.low, p.high)) for h in offsets]
    profile = sorted([(float(x[i]), j0), *zip(along, (float(j) for j in js))])
    finite = [(v, j) for v, j in profile if math.isfinite(j)]
    vmin, jmin = min(finite, key=lambda vj: vj[1])
    better = (vmin, jmin) if jmin < j0 - 0.1 * delta_j else None
    return ParameterIdentifiability(
        name=name,
        unit=unit,
        scale=p.scale,
        value=float(x[i]),
        start=None if start is None else float(start),
        low=p.low,
        high=p.high,
        on_bound=on_bound,
        cost=j0,
        delta_j=delta_j,
        curvature=curvature,
        curvature_steps=tuple(steps),
        half_width=None if curvature is None else math.sqrt(2.0 * delta_j / curvature),
        range_low=float(np.clip(_from_t(log, t0 - d_lo), p.low, p.high)),
        range_high=float(np.clip(_from_t(log, t0 + d_hi), p.low, p.high)),
        closed_low=closed_lo,
        closed_high=closed_hi,
        share=float(min(share, 1.0)),
        # a lower profile point: x* is no minimum along it, so no range can be read
        determined=closed_lo and closed_hi and share < NOT_DETERMINED_SHARE and better is None,
        better=better,
        profile=tuple(profile),
        reason=reason,
    )


def _side_end(
    side: Sequence[tuple[float, float]], j0: float, delta_j: float, threshold: float
) -> tuple[float, bool]:
    """(distance in t from t* to the range's end on one side, closed): the farthest point
    under the threshold, and the crossing beyond it interpolated linearly in √(J − J*)
    (exact for a quadratic profile); closed False when no point beyond it rose."""
    under = [k for k, (_, j) in enumerate(side) if j <= threshold]
    k = under[-1] if under else -1
    if k == len(side) - 1:
        return (side[-1][0] if side else 0.0), False
    d_in, j_in = side[k] if k >= 0 else (0.0, j0)
    d_out, j_out = side[k + 1]
    if not math.isfinite(j_out):
        return d_out, True  # failed: somewhere before it, taken at it (the wider range)
    s_in = math.sqrt(max(j_in - j0, 0.0))
    s_out = math.sqrt(j_out - j0)
    s_thr = math.sqrt(delta_j)
    return d_in + (s_thr - s_in) / (s_out - s_in) * (d_out - d_in), True


def _curvatures(
    left: Sequence[tuple[float, float]], right: Sequence[tuple[float, float]], j0: float
) -> list[tuple[float, float]]:
    """(step, ∂²J/∂t²) by the second divided difference of three profile points, for each
    step: the pair t* − h, t*, t* + h' where both sides have one (h' = h unless clipped),
    and the points t*, t* + h_k, t* + h_{k+1} on the one side where the other has none.
    Steps with a failed evaluation are left out."""
    out = []
    if left and right:
        for (a, ja), (b, jb) in zip(left, right):
            if math.isfinite(ja) and math.isfinite(jb):
                out.append((0.5 * (a + b), _second_difference((-a, ja), (0.0, j0), (b, jb))))
    else:
        side = left or right
        for (a, ja), (b, jb) in itertools.pairwise(side):
            if math.isfinite(ja) and math.isfinite(jb):
                out.append((b, _second_difference((0.0, j0), (a, ja), (b, jb))))
    return out


def _second_difference(
    p0: tuple[float, float], p1: tuple[float, float], p2: tuple[float, float]
) -> float:
    """2·f[t0, t1, t2] for t0 < t1 < t2: the second derivative of the parabola through the
    three points (for t1 − t0 = t2 − t1 = h, (f0 − 2f1 + f2)/h²)."""
    (t0, f0), (t1, f1), (t2, f2) = p0, p1, p2
    return 2.0 * ((f2 - f1) / (t2 - t1) - (f1 - f0) / (t1 - t0)) / (t2 - t0)


def _chosen_step(steps: Sequence[tuple[float, float]], delta_j: float) -> float | None:
    """The step whose rise c·h²/2 is nearest ΔJ (in ratio), among the positive curvature
    estimates; None without one."""
    positive = [(h, c) for h, c in steps if c > 0]
    if not positive:
        return None
    return min(positive, key=lambda hc: abs(math.log(0.5 * hc[1] * hc[0] ** 2 / delta_j)))[0]


def _chosen_curvature(steps: Sequence[tuple[float, float]], delta_j: float) -> float | None:
    """The curvature estimate at :func:`_chosen_step`; None without one."""
    step = _chosen_step(steps, delta_j)
    return None if step is None else dict(steps)[step]


def _axis_point(
    offsets: Sequence[float], js: np.ndarray, step: float | None
) -> tuple[float, float]:
    """(offset in t, J) of the finite profile point nearest ``step`` away from x* (the
    upper side first on a tie)."""
    finite = [(h, float(j)) for h, j in zip(offsets, js) if math.isfinite(j)]
    return min(finite, key=lambda hj: (abs(abs(hj[0]) - (step or 0.0)), -hj[0]))
