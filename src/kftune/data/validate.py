"""Validation of manoeuvre channels: every check names the file, column and row at fault.

Channels (SI units once loaded):

========== ======== ==================================================================
name       unit     meaning
========== ======== ==================================================================
t          s        time, strictly increasing, regular sample time
delta      rad      road-wheel steering angle (positive = left, ISO 8855)
ax         m/s²     longitudinal acceleration (IMU, body axes)
ay         m/s²     lateral acceleration (IMU, body axes, positive = left)
r          rad/s    yaw rate (positive = counter-clockwise seen from above)
vx         m/s      longitudinal speed measurement (wheel speeds, INS, …)
beta_ref   rad      reference sideslip at the CG, atan2(vy, vx) (optical sensor / INS)
========== ======== ==================================================================

These are the channels kftune knows (the paper's sideslip problem): when present they are
checked for their unit and plausibility, and the kinematic checks run when the channels
they compare are all present. Only ``t`` is required: which further channels a manoeuvre
needs is the business of the model that runs on it (its inputs and measurements by name,
and ``<output>_ref`` references for costs that score an output; see
:class:`~kftune.models.StateSpaceModel`). Any other channel (a tracking model's ``px``,
true states of a simulation) may ride along; its name must be an identifier.

Data that load can still be implausible in ways that do not make them unusable:
:func:`plausibility_findings` finds samples held at a lower rate, lateral accelerations
beyond what the tyres can give and an ay/(vx·r) that is off but not certainly wrong (a
physical check on real, noisy data warns when it is unsure; it refuses only what is
certain); :class:`~kftune.data.manoeuvre.Dataset` issues them as
:class:`~kftune.errors.DataWarning`.

Row numbers in messages are what the caller's file shows: :func:`validate_channels` adds
``row_offset`` to the 0-based sample index (a CSV with a header passes 2, so the first
data line is reported as row 2; a column-per-file text passes 1, a MATLAB array 1).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from kftune.errors import DataError, excerpt
from kftune.vehicle.params import G
from kftune.vehicle.single_track import MAX_SIDESLIP

#: Channels every manoeuvre must have.
REQUIRED_CHANNELS: tuple[str, ...] = ("t",)
#: The channels of the paper's sideslip problem, in file order: kftune knows their units and
#: plausible ranges (all optional but ``t``).
SIDESLIP_CHANNELS: tuple[str, ...] = ("t", "delta", "ax", "ay", "r", "vx", "beta_ref")
#: The single-track models' measured channels [Vx, ay, r], in their order.
SIDESLIP_MEASURED: tuple[str, ...] = ("vx", "ay", "r")

#: Physical dimension of each known channel.
CHANNEL_DIMENSION: dict[str, str] = {
    "t": "time",
    "delta": "angle",
    "ax": "acceleration",
    "ay": "acceleration",
    "r": "angular rate",
    "vx": "speed",
    "beta_ref": "angle",
}

#: The unit g [m/s²]: standard gravity (ISO 80000-3), what accelerometers report in; the
#: vehicle models' G = 9.81 is a rounded local value.
STANDARD_GRAVITY = 9.80665

#: Accepted unit names → (dimension, factor to SI).
UNITS: dict[str, tuple[str, float]] = {
    "s": ("time", 1.0),
    "ms": ("time", 1e-3),
    "rad": ("angle", 1.0),
    "deg": ("angle", math.pi / 180.0),
    "°": ("angle", math.pi / 180.0),
    "m/s^2": ("acceleration", 1.0),
    "m/s2": ("acceleration", 1.0),
    "m/s²": ("acceleration", 1.0),
    "g": ("acceleration", STANDARD_GRAVITY),
    "rad/s": ("angular rate", 1.0),
    "deg/s": ("angular rate", math.pi / 180.0),
    "°/s": ("angular rate", math.pi / 180.0),
    "m/s": ("speed", 1.0),
    "km/h": ("speed", 1.0 / 3.6),
    "kmph": ("speed", 1.0 / 3.6),  # as loggers write km/h in a header: wheel_fl(kmph)
    "kph": ("speed", 1.0 / 3.6),
    "mph": ("speed", 0.44704),
    "m": ("length", 1.0),
    "mm": ("length", 1e-3),
    "1": ("dimensionless", 1.0),
    "%": ("dimensionless", 0.01),
    "N": ("force", 1.0),
    "kN": ("force", 1e3),
    "Pa": ("pressure", 1.0),
    "kPa": ("pressure", 1e3),
    "MPa": ("pressure", 1e6),
    "bar": ("pressure", 1e5),
    "rad/s^2": ("angular acceleration", 1.0),
    "rad/s2": ("angular acceleration", 1.0),
    "rad/s²": ("angular acceleration", 1.0),
    "deg/s^2": ("angular acceleration", math.pi / 180.0),
    "deg/s2": ("angular acceleration", math.pi / 180.0),
    "deg/s²": ("angular acceleration", math.pi / 180.0),
    "N·m": ("torque", 1.0),
    "Nm": ("torque", 1.0),
}

#: Default SI unit of each dimension (what files of the kftune format declare).
SI_UNIT: dict[str, str] = {
    "time": "s",
    "angle": "rad",
    "acceleration": "m/s^2",
    "angular rate": "rad/s",
    "speed": "m/s",
    "length": "m",
    "dimensionless": "1",
    "force": "N",
    "pressure": "Pa",
    "angular acceleration": "rad/s^2",
    "torque": "N·m",
}

#: Fewest samples a manoeuvre may have (2 s at 100 Hz; the noise estimator of
#: :mod:`kftune.data.noise` needs more than 130).
MIN_SAMPLES = 200
#: Relative tolerance of the sample time (each step within dt·(1 ± tol)).
DT_TOLERANCE = 0.01
#: A step longer than this many median steps is a gap in the recording (a lost sample makes
#: 2), not jitter of the timestamps: it is never resampled across.
GAP_STEPS = 1.5
#: How many float spacings of the largest timestamp a median step is rounded to: each
#: timestamp is off by up to half a spacing, so a step by up to one (its binary noise:
#: 100.01 − 100.0 = 0.010000000000005116 in float64).
TIME_NOISE_SPACINGS = 2

# Plausibility limits in SI units, and what a violation usually means.
_LIMITS: dict[str, tuple[float, float, str]] = {
    "delta": (
        -1.0,
        1.0,
        "a road-wheel angle beyond ±1 rad (57°): degrees, or a hand-wheel "
        "angle without the steering ratio?",
    ),
    "beta_ref": (
        -MAX_SIDESLIP,
        MAX_SIDESLIP,
        f"a sideslip angle beyond ±{MAX_SIDESLIP:g} rad ({math.degrees(MAX_SIDESLIP):.0f}°): "
        "degrees?",
    ),
    "r": (-3.0, 3.0, "a yaw rate beyond ±3 rad/s (172 °/s): deg/s declared as rad/s?"),
    "ax": (-30.0, 30.0, "an acceleration beyond ±30 m/s² (3 g): wrong unit?"),
    "ay": (-30.0, 30.0, "an acceleration beyond ±30 m/s² (3 g): wrong unit?"),
    "vx": (-math.inf, 100.0, "a speed beyond 100 m/s (360 km/h): km/h declared as m/s?"),
}

#: Below this |vx| [m/s] a sideslip angle atan2(vy, vx) is the angle of vy's noise, and at
#: standstill it is undefined: an implausible beta_ref only at such speeds is blamed on the
#: speed (keep the stretches above one), not on its unit.
SLOW_SPEED = 2.0

#: Kinematic check ay ≈ vx·r (steady state; v̇y is small on average). The ratio is fitted
#: through the origin over the cornering samples, chosen by the regressor alone: |vx·r| at
#: least CORNERING [m/s²] (never by |ay|: on a straight, a noisy accelerometer's own noise
#: would choose the samples and bias the fit upwards, to 2.1 on a real recording with
#: σ_ay ≈ 3 m/s²), at least KINEMATIC_MIN_SAMPLES of them. Where ay corners (its moving
#: average over KINEMATIC_SMOOTHING seconds beyond CORNERING on as many samples, which the
#: noise does not reach) but vx·r does not (a yaw rate 57× too small), the samples of the
#: upper half of |vx·r|'s range are used instead, again chosen by the regressor. The fit is
#: a Huber M-estimate (tuning constant KINEMATIC_HUBER: 95 % efficient on Gaussian noise,
#: bounded weight for spikes) with its asymptotic standard error, inflated by
#: (1 + ρ)/(1 − ρ) for the residuals' lag-1 autocorrelation ρ (held samples and the
#: vehicle's dynamics are not independent noise). The fitted ratio must lie in
#: KINEMATIC_RATIO (0.72–1.13 on every bundled and revs-250lm manoeuvre): it is refused
#: only when its whole interval ratio ± KINEMATIC_Z standard errors lies outside (a unit
#: that is certainly wrong: 1/9.81 for ay in g, 57.3 or 1/57.3 for a yaw rate in the wrong
#: one of deg/s and rad/s, 1/3.6 for vx in km/h, −1 for opposite sign conventions), and
#: warned about when only the ratio itself does.
CORNERING = 2.0
KINEMATIC_MIN_SAMPLES = 50
KINEMATIC_RATIO = (0.5, 2.0)
KINEMATIC_SMOOTHING = 1.0
KINEMATIC_HUBER = 1.345
KINEMATIC_Z = 4.0
#: Most samples the fit uses, spread evenly over those chosen (its temporaries stay small
#: whatever the recording's length; the standard error is that of the samples used).
KINEMATIC_MAX_FITTED = 20_000
#: Largest lag-1 autocorrelation of the residuals the standard error allows for (an
#: inflation of the variance by at most 99).
KINEMATIC_MAX_RHO = 0.98
#: Steering check: in the linear range (|ay| ≤ 4 m/s², the paper's threshold) and cornering
#: with |vx·r| ≥ 1 m/s², the yaw rate follows the steering as r = vx·δ/L_eff, with the
#: effective wheelbase L_eff = L + K_us·vx² ≥ L of an understeering car (Gillespie,
#: *Fundamentals of Vehicle Dynamics*, Eq. 6-15). Its least-squares fit over at least
#: STEER_MIN_SAMPLES samples, L_eff = Σ(vx·δ)² / Σ(vx·δ·r), must lie in STEER_L_EFF [m]
#: (2.9–11 m on the bundled manoeuvres, 3.4–6.4 m on revs-250lm); δ in rad declared as deg
#: gives 1/57 of it. The fit, not the median of vx·δ/r: in a J-turn the steering returns
#: to zero while the yaw rate decays, and those samples (ratio ≈ 0) pulled the median of a
#: generated J-turn to 0.14 m with one sensor-noise seed; they carry no weight in the fit.
STEER_AY_LINEAR = 4.0
STEER_CORNERING = 1.0
STEER_MIN_SAMPLES = 10
STEER_L_EFF = (0.5, 50.0)
#: Plausibility warnings: a share of samples repeating the previous one in every IMU channel
#: at once (at most 13 % on revs-250lm, none on the bundled set) that means a recording
#: held at a lower rate; and |vx·r| beyond LATERAL_LIMIT·μ·g in more than LATERAL_SHARE of
#: the samples (transients let it overshoot μ·g by up to 23 % in the bundled lane changes).
HELD_CHANNELS = ("ax", "ay", "r")
HELD_SHARE = 0.25
LATERAL_LIMIT = 1.5
LATERAL_SHARE = 0.01

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class CrossCheckError(DataError):
    """Two or more channels disagree (ay against vx·r, the steering against the yaw rate):
    any of those compared may be the wrong one, so a caller that knows how each was made
    (the importer: a computed channel, the mapping's keys) can say which to suspect and how
    to fix it. The message and location are a :class:`DataError`'s.

    Attributes:
        check: ``"kinematic"`` (the fitted ay/(vx·r), :func:`kinematic_ratio`) or
            ``"steering"`` (the effective wheelbase vx·δ/r). value: that ratio [-] or the
            effective wheelbase [m]. channels: the channels compared.
    """

    def __init__(
        self,
        message: str,
        *,
        check: str,
        value: float,
        channels: tuple[str, ...],
        file: str | None = None,
        column: str | None = None,
        row: int | None = None,
    ) -> None:
        super().__init__(message, file=file, column=column, row=row)
        self.check = check
        self.value = value
        self.channels = channels


def unit_factor(unit: str, dimension: str | None, *, file: str | None, column: str) -> float:
    """Factor that converts ``unit`` to SI, checking it measures ``dimension``.

    Raises:
        DataError: unknown unit, or a unit of another dimension (names file and column).
    """
    try:
        dim, factor = UNITS[unit.strip()]
    except (KeyError, AttributeError):
        raise DataError(
            f"unknown unit {excerpt(unit)}; expected one of {sorted(UNITS)}",
            file=file,
            column=column,
        ) from None
    if dimension is not None and dim != dimension:
        allowed = sorted(u for u, (d, _) in UNITS.items() if d == dimension)
        raise DataError(
            f"unit {excerpt(unit)} is {with_article(dim)} unit, but this channel is "
            f"{with_article(dimension)}; "
            f"expected one of {allowed}",
            file=file,
            column=column,
        )
    return factor


def with_article(noun: str) -> str:
    """``noun`` after its indefinite article, for messages: ``"an angle"``,
    ``"a speed"`` (by its first letter: the dimensions' names need no more)."""
    return f"{'an' if noun[:1].lower() in 'aeiou' else 'a'} {noun}"


def sample_time(t: np.ndarray) -> float:
    """The sample time [s] of a time axis: its median step, with the binary noise of the
    timestamps rounded off (timestamps near 100 s give 0.01 s, not 0.010000000000005116 s).

    The step is rounded to the shortest decimal within :data:`TIME_NOISE_SPACINGS` float
    spacings of the largest timestamp (the resolution the timestamps have there), and to
    no more than 12 significant digits.

    The resolution is that of the timestamps' own type (float32 time from a MATLAB single
    or a Parquet float column is far coarser than float64). Rounding only removes noise:
    when it would move the step by more than that resolution (or the resolution is not
    below the step), the median step is returned as it is.

    Args:
        t: (n,) time [s], n ≥ 2; non-finite values are ignored for the resolution.
    """
    src = np.asarray(t)
    kind = src.dtype.type if np.issubdtype(src.dtype, np.floating) else np.float64
    t = src.astype(np.float64)
    dt = float(np.median(np.diff(t)))
    finite = np.abs(t[np.isfinite(t)])
    if not (math.isfinite(dt) and dt > 0.0 and finite.size):
        return dt
    spacing = float(np.spacing(kind(finite.max())))
    quantum = max(TIME_NOISE_SPACINGS * spacing, dt * 1e-12)
    if quantum >= dt:
        return dt
    for decimals in range(-math.floor(math.log10(dt)), -math.floor(math.log10(quantum)) + 1):
        rounded = round(dt, decimals)  # the shortest decimal within the noise
        if abs(rounded - dt) <= quantum:
            return rounded
    return dt  # not reached: the last rounding is within half the quantum


def check_increasing(
    t: np.ndarray, *, file: str | None, row_offset: int = 0, column: str = "t"
) -> None:
    """Refuse a time axis with a value that is not a finite number or that does not
    increase strictly (naming the first such row: 0-based index + ``row_offset``).

    Raises:
        DataError: naming the file, the column and the row.
    """
    t = np.asarray(t, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise DataError(
            f"value {float(t[bad[0]])} is not a finite number ({bad.size} such values)",
            file=file,
            column=column,
            row=int(bad[0]) + row_offset,
        )
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        k = int(bad[0]) + 1
        what = "duplicated" if steps[bad[0]] == 0.0 else "decreasing"
        raise DataError(
            f"time is {what}: t = {float(t[k]):.10g} s after t = {float(t[k - 1]):.10g} s; time "
            "must be strictly increasing",
            file=file,
            column=column,
            row=k + row_offset,
        )


def check_channel_name(name: str, *, file: str | None) -> None:
    """Channel names must be identifiers (they become CSV headers and attributes)."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise DataError(
            f"channel name {excerpt(name)} is not an identifier (letters, digits, _)",
            file=file,
            column=str(name),
        )


def validate_channels(
    channels: Mapping[str, np.ndarray],
    *,
    file: str | None = None,
    row_offset: int = 0,
    min_samples: int = MIN_SAMPLES,
    dt_tolerance: float = DT_TOLERANCE,
    check_units: bool = True,
    files: Mapping[str, str] | None = None,
    resample_option: str | None = None,
    gap_option: str | None = None,
    speed_option: str | None = None,
) -> float:
    """Check one manoeuvre's channels (already in SI units) before anything uses them.

    Checks, in this order: ``t`` present; channel names; 1-D and equal lengths; at least
    ``min_samples`` samples; every value finite; time strictly increasing (no duplicates);
    regular sample time within ``dt_tolerance``; plausible magnitudes of the known channels
    present (a yaw rate that looks like deg/s, an angle that looks like degrees, km/h as
    m/s); when ay, vx and r are present, the kinematic consistency ay ≈ vx·r in cornering
    (:func:`kinematic_ratio`; refused when certainly wrong), which catches ay in g or r in
    the wrong one of deg/s and rad/s; and when δ is present
    too, the steering consistency r ≈ vx·δ/L_eff, which catches δ in rad declared as deg
    (constants and evidence at :data:`CORNERING` and :data:`STEER_L_EFF`). Which channels a
    model needs, and what it refuses (the single-track models: vx ≤ 0), is checked by the
    model (:attr:`kftune.models.StateSpaceModel.validate_data`) before a filter runs.

    Args:
        channels: name → (n,) array. file: reported in errors. row_offset: added to 0-based
            indices in errors (see module docstring). files: per-channel file names that
            replace ``file`` in errors about that channel (column-per-file layouts).
            resample_option: the option that resamples onto a uniform grid (the
            importer's ``[source] raster``), suggested with the median step when the
            timestamps jitter (steps within :data:`GAP_STEPS` median steps, never a gap).
            gap_option: the option that splits a recording at its gaps (the importer's
            ``split_at_gaps = true``), suggested for a step over :data:`GAP_STEPS` median
            steps.
            speed_option: the option that keeps only the stretches above a speed (the
            importer's ``min_speed``), suggested when beta_ref is implausible only below
            :data:`SLOW_SPEED`.

    Returns:
        The sample time dt [s] (median step, :func:`sample_time`).

    Raises:
        DataError: the first problem found, naming file, column and row.
    """
    for name in REQUIRED_CHANNELS:
        if name not in channels:
            raise DataError(
                "missing the time channel: every manoeuvre needs 't' [s]",
                file=_file_of(name, file, files),
                column=name,
            )
    arrays: dict[str, np.ndarray] = {}
    for name, values in channels.items():
        check_channel_name(name, file=file)
        a = np.asarray(values)
        if a.ndim != 1:
            raise DataError(
                f"expected a 1-D array, got shape {a.shape}",
                file=_file_of(name, file, files),
                column=name,
            )
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise DataError(
                f"expected numbers, got dtype {a.dtype}",
                file=_file_of(name, file, files),
                column=name,
            )
        arrays[name] = a.astype(np.float64, copy=False)
    # equal lengths: blame the first channel whose length differs from the most common one
    sizes = [a.size for a in arrays.values()]
    n = max(set(sizes), key=lambda s: (sizes.count(s), -sizes.index(s)))
    for name, a in arrays.items():
        if a.size != n:
            raise DataError(
                f"has {a.size} samples, the other channels {n}: channels must have equal lengths",
                file=_file_of(name, file, files),
                column=name,
                row=min(a.size, n) + row_offset,
            )
    if n < min_samples:
        raise DataError(
            f"manoeuvre too short: {n} samples, at least {min_samples} needed",
            file=_file_of("t", file, files),
            column="t",
        )
    for name, a in arrays.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise DataError(
                f"value {float(a[bad[0]])} is not a finite number ({bad.size} such values)",
                file=_file_of(name, file, files),
                column=name,
                row=int(bad[0]) + row_offset,
            )
    t = arrays["t"]
    check_increasing(t, file=_file_of("t", file, files), row_offset=row_offset)
    steps = np.diff(t)
    dt = sample_time(t)
    if not 1e-4 <= dt <= 1.0:
        raise DataError(
            f"sample time {dt:.4g} s is outside [1e-4, 1] s: is time in ms?",
            file=_file_of("t", file, files),
            column="t",
        )
    bad = np.flatnonzero(np.abs(steps - dt) > dt_tolerance * dt)
    if bad.size:
        k = int(bad[0]) + 1
        step = float(steps[bad[0]])
        if step > GAP_STEPS * dt:
            fix = "a gap in the recording: split it at the gap"
            if gap_option:
                fix += f" ({gap_option} does)"
        else:
            fix = "jittered timestamps: resample the data onto a uniform grid"
            if resample_option:
                # the mean step: jitter averages out over it (but a gap would not)
                mean = float(np.mean(steps[steps <= GAP_STEPS * dt]))
                fix += f" (set {resample_option} = {mean:.4g}, the mean step)"
        raise DataError(
            f"irregular sample time: step {step:.4g} s from the previous row, the median step "
            f"is {dt:.4g} s (tolerance {dt_tolerance:.0%}); {fix}",
            file=_file_of("t", file, files),
            column="t",
            row=k + row_offset,
        )
    if check_units:
        _check_magnitudes(
            arrays, file=file, row_offset=row_offset, files=files, speed_option=speed_option
        )
    return dt


def channel_problems(
    channels: Mapping[str, np.ndarray],
    *,
    row_offset: int = 0,
    rows_shown: int = 3,
    speed_option: str | None = None,
) -> dict[str, str]:
    """Every channel's own problems at once, where :func:`validate_channels` stops at the
    first: values that are not finite numbers, and values outside the plausible range of a
    known channel. One message per bad channel, saying how many samples are bad and at
    which rows (the first ``rows_shown``; 0-based index + ``row_offset``).

    Returns:
        channel name → what is wrong with it (empty when nothing is).
    """
    problems = {}
    for name, values in channels.items():
        a = np.asarray(values, dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            problems[name] = (
                f"{bad.size} value(s) not a finite number, at row(s) "
                f"{_rows(bad, row_offset, rows_shown)} (first: {float(a[bad[0]])})"
            )
            continue
        if name in _LIMITS:
            lo, hi, _ = _LIMITS[name]
            bad, hint = _implausible(name, a, channels, speed_option)
            if bad.size:
                problems[name] = (
                    f"{bad.size} implausible value(s) at row(s) "
                    f"{_rows(bad, row_offset, rows_shown)} (first: {float(a[bad[0]]):g} in SI "
                    f"units; expected within [{lo:g}, {hi:g}]): {hint}"
                )
    return problems


def _rows(indices: np.ndarray, row_offset: int, shown: int) -> str:
    text = ", ".join(str(int(i) + row_offset) for i in indices[:shown])
    return text + ", …" if indices.size > shown else text


def _file_of(column: str, file: str | None, files: Mapping[str, str] | None) -> str | None:
    return files.get(column, file) if files else file


def _implausible(
    name: str, a: np.ndarray, channels: Mapping[str, np.ndarray], speed_option: str | None
) -> tuple[np.ndarray, str]:
    """The indices of a known channel's values outside its plausible range, and why.

    A sideslip angle beyond its bound only where |vx| < :data:`SLOW_SPEED` (a car standing
    or crawling: atan2(vy, vx) of vy's noise) is blamed on the speed; where it is beyond at
    speed too, those samples are reported, with the hint about degrees."""
    lo, hi, hint = _LIMITS[name]
    bad = np.flatnonzero((a < lo) | (a > hi))
    if name != "beta_ref" or not bad.size or "vx" not in channels:
        return bad, hint
    vx = np.abs(np.asarray(channels["vx"], dtype=np.float64)[bad])
    if np.any(vx >= SLOW_SPEED):
        return bad[vx >= SLOW_SPEED], hint
    fix = f' (set {speed_option}, e.g. {speed_option} = "3 km/h")' if speed_option else ""
    return bad, (
        f"the car stands or crawls at these rows (|vx| below {SLOW_SPEED:g} m/s at each; "
        f"{float(vx[0]):.3g} m/s at the first): a sideslip angle is undefined at standstill, "
        f"not in degrees; keep only the stretches above a speed{fix}"
    )


def _check_magnitudes(
    arrays: Mapping[str, np.ndarray],
    *,
    file: str | None,
    row_offset: int,
    files: Mapping[str, str] | None = None,
    speed_option: str | None = None,
) -> None:
    for name, (lo, hi, _) in _LIMITS.items():
        if name not in arrays:
            continue
        a = arrays[name]
        bad, hint = _implausible(name, a, arrays, speed_option)
        if bad.size:
            raise DataError(
                f"implausible value {a[bad[0]]:g} (expected within [{lo:g}, {hi:g}] in SI "
                f"units): {hint}",
                file=_file_of(name, file, files),
                column=name,
                row=int(bad[0]) + row_offset,
            )
    # Kinematics: the ratio near 1/g means ay in g, near 180/π or π/180 a yaw rate in the
    # wrong one of deg/s and rad/s, near 1/3.6 vx in km/h; negative, opposite conventions.
    fit = kinematic_ratio(arrays)
    if fit is not None and fit.certainly_wrong:
        ay, vxr = arrays["ay"], arrays["vx"] * arrays["r"]
        k = fit.row
        # a sign alone flips the ratio; only a magnitude off by a factor is a unit's doing
        why = []
        if fit.ratio < 0:
            why.append(
                "negative: ay and r use opposite sign conventions; ISO 8855: both positive "
                "to the left"
            )
        if not KINEMATIC_RATIO[0] <= abs(fit.ratio) <= KINEMATIC_RATIO[1]:
            why.append("is ay in g, r in deg/s or rad/s, vx in km/h?")
        raise CrossCheckError(
            f"lateral acceleration and vx·yaw rate disagree: ay/(vx·r) = {fit.ratio:.3g} in "
            f"cornering ({fit.describe()}), expected ≈ 1 ({'; '.join(why)}; at this row "
            f"ay = {ay[k]:.4g}, vx·r = {vxr[k]:.4g})",
            check="kinematic",
            value=fit.ratio,
            channels=("ay", "vx", "r"),
            file=_file_of("ay", file, files),
            column="ay",
            row=k + row_offset,
        )
    if not all(c in arrays for c in ("ay", "vx", "r")):
        return
    ay, vx, r = arrays["ay"], arrays["vx"], arrays["r"]
    vxr = vx * r
    if "delta" not in arrays:
        return
    delta = arrays["delta"]
    steady = (np.abs(vxr) >= STEER_CORNERING) & (np.abs(ay) <= STEER_AY_LINEAR)
    if np.count_nonzero(steady) >= STEER_MIN_SAMPLES:
        vd = vx[steady] * delta[steady]
        cross = float(np.sum(vd * r[steady]))
        l_eff = float(np.sum(vd**2)) / cross if cross else math.inf
        if not STEER_L_EFF[0] <= l_eff <= STEER_L_EFF[1]:
            k = int(np.flatnonzero(steady)[np.argmax(np.abs(vxr[steady]))])
            raise CrossCheckError(
                f"steering angle and yaw rate disagree: in cornering below "
                f"{STEER_AY_LINEAR:g} m/s² the effective wheelbase vx·δ/r is {l_eff:.3g} m "
                f"(least squares), expected {STEER_L_EFF[0]:g} to {STEER_L_EFF[1]:g} m (wheelbase "
                f"plus understeer; 2–15 m for cars): is δ in rad but declared deg (57× too "
                f"small), a hand-wheel angle without the steering ratio, or are δ and r of "
                f"opposite sign conventions (ISO 8855: both positive to the left)? At this row "
                f"δ = {delta[k]:.4g} rad, r = {r[k]:.4g} rad/s, vx = {vx[k]:.4g} m/s",
                check="steering",
                value=l_eff,
                channels=("delta", "vx", "r"),
                file=_file_of("delta", file, files),
                column="delta",
                row=k + row_offset,
            )


@dataclass(frozen=True)
class KinematicRatio:
    """The fitted ay/(vx·r) of a manoeuvre and how sure it is (:func:`kinematic_ratio`).

    Attributes:
        ratio: the robust fit of ay against vx·r through the origin. stderr: its standard
            error (allowing for autocorrelated residuals). samples: how many samples were
            chosen. fitted: how many of them the fit used (all, or
            :data:`KINEMATIC_MAX_FITTED` spread evenly over them). threshold: the |vx·r|
            [m/s²] from which samples were chosen. row: 0-based index
            of the sample with the largest |vx·r| (the one a message quotes).
    """

    ratio: float
    stderr: float
    samples: int
    fitted: int
    threshold: float
    row: int

    @property
    def interval(self) -> tuple[float, float]:
        """ratio ± :data:`KINEMATIC_Z` standard errors."""
        half = KINEMATIC_Z * self.stderr
        return self.ratio - half, self.ratio + half

    @property
    def certainly_wrong(self) -> bool:
        """The whole interval lies outside :data:`KINEMATIC_RATIO`: a wrong unit or sign."""
        lo, hi = self.interval
        return hi < KINEMATIC_RATIO[0] or lo > KINEMATIC_RATIO[1]

    @property
    def doubtful(self) -> bool:
        """The ratio lies outside :data:`KINEMATIC_RATIO` but its interval does not."""
        outside = not KINEMATIC_RATIO[0] <= self.ratio <= KINEMATIC_RATIO[1]
        return outside and not self.certainly_wrong

    def describe(self) -> str:
        """How the ratio was found, for messages."""
        lo, hi = self.interval
        some = f" (an even {self.fitted} of them)" if self.fitted < self.samples else ""
        return (
            f"robust fit over the {self.samples} samples with |vx·r| ≥ {self.threshold:.3g} "
            f"m/s²{some}; {lo:.3g} to {hi:.3g} within {KINEMATIC_Z:g} standard errors"
        )


def kinematic_ratio(channels: Mapping[str, np.ndarray]) -> KinematicRatio | None:
    """Fit ay ≈ k·vx·r in cornering, where there is enough cornering to judge k.

    The samples are chosen by the regressor |vx·r| only, as :data:`CORNERING` explains (a
    choice by |ay| picks a noisy accelerometer's noise on a straight and biases k upwards);
    k is a Huber M-estimate through the origin (``scipy.optimize.least_squares`` with
    ``loss="huber"``, the scale from the residuals' median absolute deviation), robust to
    spikes, and its standard error the M-estimator's asymptotic one, σ²·E[ψ²]/E[ψ′]²/Σx²,
    times (1 + ρ)/(1 − ρ) for the residuals' lag-1 autocorrelation ρ (AR(1) residuals over
    a slowly varying regressor).

    Args:
        channels: SI channels with t, ay, vx and r (equal lengths, finite).

    Returns:
        The fit, or None: a channel missing, fewer than :data:`KINEMATIC_MIN_SAMPLES`
        cornering samples (a straight: nothing to judge), or no yaw rate at all.
    """
    if not all(c in channels for c in ("t", "ay", "vx", "r")):
        return None
    ay = np.asarray(channels["ay"], dtype=np.float64)
    vxr = np.asarray(channels["vx"], dtype=np.float64) * np.asarray(channels["r"], np.float64)
    threshold = CORNERING
    if np.count_nonzero(np.abs(vxr) >= threshold) < KINEMATIC_MIN_SAMPLES:
        from scipy.ndimage import uniform_filter1d

        t = np.asarray(channels["t"], dtype=np.float64)
        dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        window = max(1, round(KINEMATIC_SMOOTHING / dt)) if dt > 0.0 else 1
        smooth = uniform_filter1d(ay, min(window, ay.size))
        if np.count_nonzero(np.abs(smooth) >= CORNERING) < KINEMATIC_MIN_SAMPLES:
            return None  # no cornering in ay either
        threshold = 0.5 * float(np.quantile(np.abs(vxr), 0.99))
    chosen = np.flatnonzero(np.abs(vxr) >= threshold)
    samples = int(chosen.size)
    if samples > KINEMATIC_MAX_FITTED:  # evenly over the recording: bounded memory
        chosen = chosen[np.linspace(0, samples - 1, KINEMATIC_MAX_FITTED).astype(np.intp)]
    x, y = vxr[chosen], ay[chosen]
    sxx = float(x @ x)
    if not (sxx > 0.0 and samples >= KINEMATIC_MIN_SAMPLES):
        return None  # a yaw rate of zero: nothing to fit
    row = int(np.argmax(np.abs(vxr)))

    def result(ratio: float, stderr: float) -> KinematicRatio:
        return KinematicRatio(ratio, stderr, samples, int(x.size), threshold, row)

    k = float(x @ y) / sxx  # least squares: the start
    scale = 1.4826 * float(np.median(np.abs(y - k * x - np.median(y - k * x))))
    if scale == 0.0:  # over half the residuals equal (quantised data)
        scale = float(np.std(y - k * x))
    if scale == 0.0:  # an exact fit
        return result(k, 0.0)
    from scipy.optimize import least_squares

    fit = least_squares(
        lambda p: y - p[0] * x,
        [k],
        jac=lambda p: -x[:, None],
        loss="huber",
        f_scale=KINEMATIC_HUBER * scale,
    )
    k = float(fit.x[0])
    e = y - k * x
    u = e / scale
    inside = float(np.mean(np.abs(u) <= KINEMATIC_HUBER))
    if inside == 0.0:
        return result(k, math.inf)
    psi2 = float(np.mean(np.clip(u, -KINEMATIC_HUBER, KINEMATIC_HUBER) ** 2))
    var = scale**2 * psi2 / inside**2 / sxx
    with np.errstate(invalid="ignore", divide="ignore"):  # constant residuals: nan
        rho = float(np.corrcoef(e[:-1], e[1:])[0, 1]) if e.size > 2 else 0.0
    rho = KINEMATIC_MAX_RHO if not math.isfinite(rho) else min(max(rho, 0.0), KINEMATIC_MAX_RHO)
    var *= (1.0 + rho) / (1.0 - rho)
    return result(k, math.sqrt(var))


def plausibility_findings(channels: Mapping[str, np.ndarray], mu: float | None) -> dict[str, str]:
    """Why channels that passed :func:`validate_channels` may not be what they claim, by
    kind of finding (so that a dataset can report each kind once for all its manoeuvres).

    Args:
        channels: name → (n,) array in SI units; each check runs when its channels are
            present (the held samples: ax, ay and r; the lateral limit: vx and r; the
            kinematic ratio: ay, vx and r).
        mu: the vehicle's friction coefficient [-]; None (no vehicle): no lateral limit.

    Returns:
        kind → message (empty when none): ``"held"``, samples held at a lower rate (the
        share that repeat the previous sample in ax, ay and r at once is at least
        :data:`HELD_SHARE`; the rate from the typical length of a run of repeats);
        ``"lateral"``, |vx·r| beyond :data:`LATERAL_LIMIT`·μ·g in more than
        :data:`LATERAL_SHARE` of the samples (banking, a wrong μ, a wrong unit);
        ``"kinematic"``, an ay/(vx·r) outside :data:`KINEMATIC_RATIO` that is not
        certainly wrong (:func:`kinematic_ratio`; a certainly wrong one is refused).
    """
    found: dict[str, str] = {}
    t = np.asarray(channels["t"], dtype=float)
    held = np.ones(t.size - 1, dtype=bool)
    for name in HELD_CHANNELS:
        if name not in channels:
            held[:] = False
            break
        held &= np.diff(np.asarray(channels[name], dtype=float)) == 0.0
    share = float(np.mean(held)) if held.size else 0.0
    if share >= HELD_SHARE:
        rate = 1.0 / float(np.median(np.diff(t)))
        # runs of repeats: a run of L repeats is L + 1 equal samples
        edges = np.flatnonzero(np.diff(np.concatenate([[0], held.astype(np.int8), [0]])))
        hold = float(np.median(edges[1::2] - edges[0::2])) + 1.0
        found["held"] = (
            f"{share:.0%} of the samples repeat the previous one in {', '.join(HELD_CHANNELS)} "
            f"at once: recorded at about {rate / hold:.3g} Hz and held up to "
            f"{rate:.3g} Hz? The filter takes every sample as a new measurement; resample "
            "the recording at its real rate (kftune dataset import: [source] raster = <step> "
            'in the mapping, or raster = { "<file glob>" = <step> } for some recordings)'
        )
    if mu is not None and "vx" in channels and "r" in channels:
        lateral = np.abs(np.asarray(channels["vx"], dtype=float) * np.asarray(channels["r"]))
        limit = LATERAL_LIMIT * mu * G
        share = float(np.mean(lateral > limit))
        if share > LATERAL_SHARE:
            found["lateral"] = (
                f"|vx·r| exceeds {LATERAL_LIMIT:g}·μ·g = {limit:.3g} m/s² (μ = {mu:g}) in "
                f"{share:.1%} of the samples, up to {float(lateral.max()):.3g} m/s²: more "
                "lateral acceleration than the tyres can give — a banked track, a wrong μ in "
                "the vehicle parameters, or vx or r in a wrong unit?"
            )
    fit = kinematic_ratio(channels)
    if fit is not None and fit.doubtful:
        found["kinematic"] = (
            f"ay/(vx·r) = {fit.ratio:.3g} in cornering ({fit.describe()}), outside the "
            f"expected {KINEMATIC_RATIO[0]:g} to {KINEMATIC_RATIO[1]:g} but not certainly "
            "wrong: the data are kept; check the units and signs of ay, vx and r, the "
            "accelerometer's mounting, or a banked track"
        )
    return found
