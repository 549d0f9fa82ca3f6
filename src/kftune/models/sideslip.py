"""The paper's sideslip problem as state-space models: the single-track/Dugoff model and
variants with sensor-bias states.

``single-track`` (paper Sec. V, :mod:`kftune.vehicle.single_track`): x = [Vx, Vy, r],
u = [δ, ax], z = [Vx, ay, r]; one RK4 step per sample with the input held, the compiled
scalar functions of :mod:`kftune.vehicle.single_track` unchanged. The input-only
quantities (tan δ, cos δ, axle loads Fz_f, Fz_r) are computed once per sample by
``prepare``: the prepared row is [δ, ax, tan δ, cos δ, Fz_f, Fz_r].

``single-track-ay-bias`` adds a lateral-accelerometer bias b_ay [m/s²] as a random walk
(x = [Vx, Vy, r, b_ay], b_ay,k = b_ay,k−1 + w): the measured ay is the model's ay + b_ay. A
road bank of 3° alone puts g·sin 3° ≈ 0.5 m/s² on a body-fixed accelerometer, and a
consumer-grade MEMS sensor adds a turn-on bias of the same order.

``single-track-biases`` (n = 6) puts a random-walk bias on every measurement:
x = [Vx, Vy, r, b_Vx, b_ay, b_r], z = [Vx + b_Vx, ay + b_ay, r + b_r] (wheel-speed scale
error, accelerometer bias and bank, gyro bias).

Jacobians (all three): analytic, the exact derivative of the RK4 step and of h
(:mod:`kftune.models._single_track_jacobians`), so that the EKF needs no finite differences.

Validity (all three): Vx > 0 and the runaway rules
(:mod:`kftune.models._runaway`): |β⁺| > 60° stops the run at once; |β⁺| > 46°
(:data:`~kftune.vehicle.single_track.MAX_SIDESLIP`) or |Vx⁺ − Vx_measured| > 50 % of the
measured Vx held for 0.5 s stops it where it began. The measured Vx is z[0], which for
``single-track-biases`` includes the wheel-speed bias.

C (all three, for ``kftune export --format c``): the package file
``kftune/models/c/single_track.c``, the twin of every hook here and of the compiled
functions they call; it tells the variants apart by the bias states' index macros in the
model's header (:mod:`kftune.models.c_contract`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numba import njit
from numba.core.dispatcher import Dispatcher
from scipy.ndimage import uniform_filter1d

from kftune.models._runaway import (
    RUNAWAY_BETA,
    RUNAWAY_HOLD,
    RUNAWAY_VX,
    STOP_REASONS,
    STOP_REVERSE,
    STOP_SIDESLIP,
    STOP_SIDESLIP_HELD,
    STOP_SPEED,
    runaway,
)
from kftune.models._single_track_jacobians import single_track_F, single_track_H
from kftune.models.base import DataRefused, ModelKernels, PriorRule, StateSpaceModel
from kftune.models.c_contract import builtin_c_code
from kftune.vehicle.params import PARAM_INDEX, PLAUSIBLE_RANGES, PRESETS, G
from kftune.vehicle.single_track import (
    measure_scalar,
    pack_params,
    rk4_scalar,
    step_context_scalar,
)

__all__ = [
    "AY_BIAS_PRIOR_STD",
    "DEFAULT_VEHICLE",
    "P0_VY_SPEED_FRACTION",
    "RUNAWAY_BETA",
    "RUNAWAY_HOLD",
    "RUNAWAY_VX",
    "SINGLE_TRACK",
    "SINGLE_TRACK_AY_BIAS",
    "SINGLE_TRACK_BIASES",
    "STOP_REASONS",
    "STOP_REVERSE",
    "STOP_SIDESLIP",
    "STOP_SIDESLIP_HELD",
    "STOP_SPEED",
    "check_forward_speed",
    "largest_lateral_acceleration",
    "param_hints",
    "single_track_prior",
]

#: Default prior standard deviation of Vy as a fraction of the first measured Vx [-].
P0_VY_SPEED_FRACTION = 0.05
#: Prior standard deviation of the lateral-accelerometer bias [m/s²] (a 3° bank).
AY_BIAS_PRIOR_STD = 0.5
#: Prior standard deviations of the wheel-speed bias [m/s] and the gyro bias [rad/s].
VX_BIAS_PRIOR_STD = 0.2
R_BIAS_PRIOR_STD = math.radians(0.5)

#: The vehicle whose parameters are the models' defaults.
DEFAULT_VEHICLE = "bmw-320i"

_INPUTS = (("delta", "rad"), ("ax", "m/s^2"))
_MEASUREMENTS = (("vx", "m/s"), ("ay", "m/s^2"), ("r", "rad/s"))
_STATES = (("vx", "m/s"), ("vy", "m/s"), ("r", "rad/s"))
_PARAM_UNITS = {
    "m": "kg",
    "Iz": "kg*m^2",
    "a": "m",
    "b": "m",
    "h": "m",
    "C_af": "N/rad",
    "C_ar": "N/rad",
    "C_x": "N",
    "mu": "-",
}


# --------------------------------------------------------------------------------------
# Compiled model functions
# --------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def prepare(u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """(6,) prepared row [δ, ax, tan δ, cos δ, Fz_f, Fz_r] of an input row u = [δ, ax]."""
    tan_d, cos_d, fzf, fzr = step_context_scalar(u[0], u[1], p)
    out[0] = u[0]
    out[1] = u[1]
    out[2] = tan_d
    out[3] = cos_d
    out[4] = fzf
    out[5] = fzr


@njit(cache=True, error_model="numpy")
def process(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """One RK4 step of x = [Vx, Vy, r] with the prepared input row u."""
    out[0], out[1], out[2] = rk4_scalar(x[0], x[1], x[2], u[2], u[3], u[1], u[4], u[5], p, dt)


@njit(cache=True, error_model="numpy")
def process_biases(x: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float, out: np.ndarray) -> None:
    """One RK4 step of [Vx, Vy, r]; the further states (biases) are random walks, kept.

    (A function of its own: the loop over the biases costs the 3-state model a third of
    its time when the two share one function.)
    """
    out[0], out[1], out[2] = rk4_scalar(x[0], x[1], x[2], u[2], u[3], u[1], u[4], u[5], p, dt)
    for j in range(3, x.shape[0]):
        out[j] = x[j]


@njit(cache=True, error_model="numpy")
def measurement(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """z = [Vx, ay, r] = h(x, u) (:func:`kftune.vehicle.single_track.measure`)."""
    out[0], out[1], out[2] = measure_scalar(x[0], x[1], x[2], u[2], u[3], u[4], u[5], p)


@njit(cache=True, error_model="numpy")
def measurement_ay_bias(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """z = [Vx, ay + b_ay, r] for x = [Vx, Vy, r, b_ay]."""
    measurement(x, u, p, out)
    out[1] += x[3]


@njit(cache=True, error_model="numpy")
def measurement_biases(x: np.ndarray, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """z = [Vx + b_Vx, ay + b_ay, r + b_r] for x = [Vx, Vy, r, b_Vx, b_ay, b_r]."""
    measurement(x, u, p, out)
    out[0] += x[3]
    out[1] += x[4]
    out[2] += x[5]


@njit(cache=True, error_model="numpy")
def check(x: np.ndarray, z: np.ndarray, u: np.ndarray, p: np.ndarray, held: np.ndarray) -> int:
    """The runaway rules (:func:`runaway`) as the model's check: held[0]: |β⁺| >
    MAX_SIDESLIP; held[1]: |Vx⁺ − z_Vx| > RUNAWAY_VX·z_Vx."""
    cause, beyond, off = runaway(x[0], x[1], z[0])
    if cause != 0:
        return cause
    held[0] = beyond
    held[1] = off
    return 0


# --------------------------------------------------------------------------------------
# Python-level hooks
# --------------------------------------------------------------------------------------


def single_track_prior(
    z0: np.ndarray, r: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Prior at step 0: x0 = [z0_Vx, 0, z0_r], P0 = diag(r_Vx, (0.05·z0_Vx)², r_r).

    The measured states as uncertain as their sensors, Vy with a standard deviation of 5 %
    of the speed (a sideslip of about 3°).

    Args:
        z0: (3,) first measurement [Vx m/s, ay m/s², r rad/s]; r: (3,) measurement
        variances; p: vehicle parameters (unused).
    """
    vx0 = float(z0[0])
    x0 = np.array([vx0, 0.0, float(z0[2])])
    P0 = np.diag([float(r[0]), (P0_VY_SPEED_FRACTION * vx0) ** 2, float(r[2])])
    return x0, P0


def _prior_with_biases(stds: tuple[float, ...]) -> PriorRule:
    def prior(z0: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x0, P0 = single_track_prior(z0, r, p)
        n = 3 + len(stds)
        x = np.zeros(n)
        P = np.zeros((n, n))
        x[:3] = x0
        P[:3, :3] = P0
        P[3:, 3:] = np.diag(np.square(stds))
        return x, P

    prior.__doc__ = f"The single-track prior, and zero biases with standard deviations {stds}."
    return prior


def check_forward_speed(z: np.ndarray) -> None:
    """Refuse measurements with Vx ≤ 0 (the slip-angle model is for forward driving).

    Args:
        z: (N, 3) measurements [Vx, ay, r]; checked: z[:, 0] > 0.

    Raises:
        DataRefused: naming the first row with Vx ≤ 0.
    """
    bad = z[:, 0] <= 0
    if bad.any():
        row = int(np.argmax(bad))
        why = (
            "the measured longitudinal speed must be > 0 (the single-track slip-angle model "
            "is for forward driving: cut standstill and reversing out of the manoeuvre)"
        )
        reason = f"Vx = {float(z[row, 0]):.4g} m/s; {why}"
        raise DataRefused(
            f"z[{row}, 0] (Vx) = {float(z[row, 0])} m/s; {why}",
            array="z",
            row=row,
            column=0,
            reason=reason,
        )


def _validate(u: np.ndarray, z: np.ndarray) -> None:
    check_forward_speed(z)


#: A friction coefficient is not determined by data whose largest |ay| stays below this
#: share of μ·g. The Dugoff axle force is C_α·tan α, free of μ, while |F_y| ≤ μ·F_z/2
#: (λ ≥ 1, :mod:`kftune.vehicle.tyre`), which in steady cornering is |ay| ≤ μ·g/2; from
#: there to μ·g the force bends towards its limit μ·F_z.
FRICTION_HINT_SHARE = 0.7
#: The cornering stiffnesses are barely excited when the largest |ay| stays below this
#: [m/s²] (about 0.1 g): the lateral forces, and so C_α·α, are then of the order of the
#: accelerometer's noise and bank.
LATERAL_HINT_AY = 1.0
#: [s] the centred moving average |ay| is taken over, so that the accelerometer's noise
#: does not set the largest value.
HINT_SMOOTHING = 0.2


def largest_lateral_acceleration(runs: Sequence[tuple[float, Mapping[str, np.ndarray]]]) -> float:
    """The largest |ay| [m/s²] of the runs' measured ay, each smoothed by a centred moving
    average over :data:`HINT_SMOOTHING`; NaN without an ay channel."""
    peaks = [
        float(np.max(np.abs(uniform_filter1d(np.asarray(ch["ay"], float), size, mode="nearest"))))
        for dt, ch in runs
        if "ay" in ch and len(ch["ay"]) and (size := max(1, round(HINT_SMOOTHING / dt)))
    ]
    return max(peaks) if peaks else math.nan


def _friction_hint(ay: float, p: np.ndarray) -> str | None:
    share = ay / (float(p[PARAM_INDEX["mu"]]) * G)
    if share >= FRICTION_HINT_SHARE:
        return None
    return (
        f"μ is not determined by these manoeuvres: the largest |ay| is {100 * share:.0f} % of "
        "μ·g, no sample near the friction limit (the Dugoff tyre force depends on μ only "
        "beyond 50 %)"
    )


def _stiffness_hint(name: str) -> Callable[[float, np.ndarray], str | None]:
    axle = "front" if name == "C_af" else "rear"

    def hint(ay: float, p: np.ndarray) -> str | None:
        if ay >= LATERAL_HINT_AY:
            return None
        return (
            f"too little lateral excitation for the {axle} cornering stiffness {name}: the "
            f"largest |ay| is {ay:.2g} m/s² (under {LATERAL_HINT_AY:g} m/s²)"
        )

    return hint


#: What kftune knows of the single-track parameters' excitation: parameter → (largest
#: |ay| [m/s²], tuned parameters p) → a reason the data may not determine it, or None.
_PARAM_HINTS: dict[str, Callable[[float, np.ndarray], str | None]] = {
    "mu": _friction_hint,
    "C_af": _stiffness_hint("C_af"),
    "C_ar": _stiffness_hint("C_ar"),
}


def param_hints(
    runs: Sequence[tuple[float, Mapping[str, np.ndarray]]], p: np.ndarray
) -> dict[str, str]:
    """The single-track models' :attr:`~kftune.models.StateSpaceModel.param_hints`: from
    the largest lateral acceleration of the training runs (:func:`largest_lateral_acceleration`)
    and the tuned parameters p (9,), a reason for each parameter of :data:`_PARAM_HINTS`
    the data leave unexcited."""
    ay = largest_lateral_acceleration(runs)
    if not math.isfinite(ay):
        return {}
    found = {name: hint(ay, p) for name, hint in _PARAM_HINTS.items()}
    return {name: text for name, text in found.items() if text is not None}


@functools.cache
def single_track_kernels() -> ModelKernels:
    """The single-track model's own UKF loops, which the generic UKF runs for it: the
    hand-written 3×3 loop (:mod:`kftune.models._sideslip_ukf`; about 1.2–1.9× faster than
    the generic loop, BENCHMARKS.md "Filters over any model") for one run and threads,
    and the vector-lane loop (:mod:`kftune.models._sideslip_lanes`) for batches. Imported
    on first use (they compile, or load from numba's cache, when first called)."""
    from kftune.models._sideslip_lanes import ensure_compiled, run_kernel_soa
    from kftune.models._sideslip_ukf import run_kernel, run_kernel_batch

    def lanes(*args: Any) -> None:
        ensure_compiled()  # with vectorisation on (see there)
        run_kernel_soa(*args)

    return ModelKernels(run_kernel, run_kernel_batch, lanes, (process, measurement, check))


def sideslip_angle(x: np.ndarray) -> np.ndarray:
    """(N,) the sideslip angle atan2(Vy, Vx) [rad] of posterior states x (N, n ≥ 2)."""
    return np.arctan2(x[:, 1], x[:, 0])


def _model(
    name: str,
    states: tuple[tuple[str, str], ...],
    f: Dispatcher,
    h: Dispatcher,
    prior: PriorRule,
    description: str,
    kernels: Callable[[], ModelKernels] | None = None,
) -> StateSpaceModel:
    return StateSpaceModel(
        name=name,
        state_names=tuple(s for s, _ in states),
        state_units=tuple(u for _, u in states),
        input_names=tuple(s for s, _ in _INPUTS),
        input_units=tuple(u for _, u in _INPUTS),
        measurement_names=tuple(s for s, _ in _MEASUREMENTS),
        measurement_units=tuple(u for _, u in _MEASUREMENTS),
        f=f,
        h=h,
        param_names=tuple(PARAM_INDEX),
        param_units=tuple(_PARAM_UNITS[k] for k in PARAM_INDEX),
        param_defaults=tuple(PRESETS[DEFAULT_VEHICLE].to_array()),
        initial_state=prior,
        prepare=prepare,
        prepared_size=6,
        check=check,
        held_causes=(STOP_SIDESLIP_HELD, STOP_SPEED),
        hold_time=RUNAWAY_HOLD,
        stop_reasons=STOP_REASONS,
        F=single_track_F,
        H=single_track_H,
        pack_params=pack_params,
        validate_data=_validate,
        description=description,
        outputs={"beta": sideslip_angle},
        needs_vehicle=True,
        param_ranges={k: PLAUSIBLE_RANGES[k][:2] for k in PARAM_INDEX},
        param_hints=param_hints,
        c_code=builtin_c_code("single_track"),
        ukf_kernels=kernels,
    )


#: The paper's model (3 states, 3 measurements).
SINGLE_TRACK = _model(
    "single-track",
    _STATES,
    process,
    measurement,
    single_track_prior,
    "single-track vehicle with Dugoff axle forces, states [Vx, Vy, r] (the paper's model)",
    single_track_kernels,
)

#: The single-track model with a lateral-accelerometer bias state (4 states).
SINGLE_TRACK_AY_BIAS = _model(
    "single-track-ay-bias",
    (*_STATES, ("b_ay", "m/s^2")),
    process_biases,
    measurement_ay_bias,
    _prior_with_biases((AY_BIAS_PRIOR_STD,)),
    "single-track/Dugoff with a random-walk lateral-accelerometer bias b_ay",
)

#: The single-track model with a bias state on every measurement (6 states).
SINGLE_TRACK_BIASES = _model(
    "single-track-biases",
    (*_STATES, ("b_vx", "m/s"), ("b_ay", "m/s^2"), ("b_r", "rad/s")),
    process_biases,
    measurement_biases,
    _prior_with_biases((VX_BIAS_PRIOR_STD, AY_BIAS_PRIOR_STD, R_BIAS_PRIOR_STD)),
    "single-track/Dugoff with random-walk biases on the Vx, ay and r sensors",
)
