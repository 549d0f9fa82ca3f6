"""The single-track models' runaway rule, written once: the scalar compiled function every
loop that runs these models calls (the generic filters through the model's ``check``, the
model's own 3×3 and vector-lane loops directly), its bounds and its stop causes.

A filter can stay finite and positive-definite while its estimate leaves physics behind —
with a large Vy process noise the sideslip random-walks to ±90° and the cost merely grows.
These estimates are divergence too, at the step where they start:

* |β⁺| > 60° (``RUNAWAY_BETA``) at any step: the car would move more sideways than
  forwards (|Vy| > 1.7·Vx), which no cornering car does and the model (slip angles of a
  rolling tyre) does not describe;
* |β⁺| > 46° (:data:`~kftune.vehicle.single_track.MAX_SIDESLIP`, the bound the loader puts
  on a reference sideslip) held for 0.5 s (``RUNAWAY_HOLD``): a sustained spin;
* |Vx⁺ − Vx_measured| > 50 % of the measured Vx (``RUNAWAY_VX``) held for 0.5 s: a
  speed sensor (wheel speeds, GNSS/INS) errs by the wheel slip at most, |κ| ≲ 0.2 outside
  lock-up and spin; holding it for 0.5 s keeps a single glitch of the measurement from
  counting.

Why not the NIS: filters with Q near 1e-10 are overconfident (NIS above 1000 held for
seconds) yet estimate β within 1°, and runaway filters with a huge Vy noise have NIS below
25, because their innovation covariance is as inflated as their estimate.
"""

from __future__ import annotations

import math

from numba import njit

from kftune.models.base import FIRST_MODEL_STOP
from kftune.vehicle.single_track import MAX_SIDESLIP

__all__ = [
    "RUNAWAY_BETA",
    "RUNAWAY_HOLD",
    "RUNAWAY_VX",
    "STOP_REASONS",
    "STOP_REVERSE",
    "STOP_SIDESLIP",
    "STOP_SIDESLIP_HELD",
    "STOP_SPEED",
    "runaway",
]

#: Stop causes of the single-track models.
STOP_REVERSE = FIRST_MODEL_STOP  # estimated Vx ≤ 0
STOP_SIDESLIP = FIRST_MODEL_STOP + 1  # |β⁺| > RUNAWAY_BETA
STOP_SIDESLIP_HELD = FIRST_MODEL_STOP + 2  # |β⁺| > MAX_SIDESLIP for RUNAWAY_HOLD
STOP_SPEED = FIRST_MODEL_STOP + 3  # |Vx⁺ − Vx measured| > RUNAWAY_VX·Vx measured, held

#: Runaway bounds (module docstring).
RUNAWAY_BETA = math.radians(60.0)  # [rad]
RUNAWAY_VX = 0.5  # [-] relative to the measured Vx
RUNAWAY_HOLD = 0.5  # [s]

STOP_REASONS: dict[int, str] = {
    STOP_REVERSE: "the estimated Vx fell to 0 m/s or below",
    STOP_SIDESLIP: "runaway: the estimated sideslip went beyond "
    f"±{math.degrees(RUNAWAY_BETA):.0f}°",
    STOP_SIDESLIP_HELD: "runaway: the estimated sideslip stayed beyond "
    f"±{math.degrees(MAX_SIDESLIP):.0f}° for {RUNAWAY_HOLD:g} s",
    STOP_SPEED: "runaway: the estimated Vx stayed more than "
    f"{RUNAWAY_VX:.0%} away from the measured Vx for {RUNAWAY_HOLD:g} s",
}

_TAN_RUNAWAY_BETA = math.tan(RUNAWAY_BETA)
_TAN_MAX_SIDESLIP = math.tan(MAX_SIDESLIP)


@njit(cache=True, error_model="numpy", inline="always")
def runaway(vx: float, vy: float, vx_measured: float) -> tuple[int, bool, bool]:
    """The single-track runaway rules (module docstring) on a posterior estimate, the one
    place they are written: every loop that runs the model calls this (the generic
    filters through the model's :func:`kftune.models.sideslip.check`, its own 3×3 loop and
    vector lanes directly).
    |Vy| > tan(bound)·Vx instead of atan2.

    Args:
        vx, vy: [m/s] the posterior Vx⁺ and Vy⁺. vx_measured: [m/s] the measured Vx.

    Returns:
        (cause, beyond_sideslip, off_speed): cause STOP_REVERSE (Vx⁺ ≤ 0) or STOP_SIDESLIP
        (|β⁺| > RUNAWAY_BETA) to stop now, else 0; and whether the held conditions hold at
        this step: |β⁺| > MAX_SIDESLIP, |Vx⁺ − Vx measured| > RUNAWAY_VX·Vx measured (their
        counting over RUNAWAY_HOLD is the kernel's).
    """
    if not vx > 0.0:
        return STOP_REVERSE, False, False
    if abs(vy) > _TAN_RUNAWAY_BETA * vx:
        return STOP_SIDESLIP, False, False
    beyond = abs(vy) > _TAN_MAX_SIDESLIP * vx
    off = abs(vx - vx_measured) > RUNAWAY_VX * vx_measured
    return 0, beyond, off
