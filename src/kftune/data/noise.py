"""Measurement-noise covariance R from the sensor data themselves (paper Sec. V: R comes
from "statistical analysis of the vehicle sensor measurements", it is not optimised).

Method (high-pass residual statistics, as the authors of the revs-250lm recording do for
their KF): a vehicle's motion has almost no power above a quarter of the Nyquist frequency
(12.5 Hz at 100 Hz), sensor noise is close to white. So each measured channel z (the single-track
model's Vx, ay and r by default; any model's measurement channels by name) of each
manoeuvre is high-pass filtered — 4th-order Butterworth at ``cutoff``·Nyquist,
applied forwards and backwards (zero phase, |H|² twice) — and the variance of the output is
divided by the filter's white-noise power gain

    g = (1/π) ∫₀^π |H(e^{jω})|⁴ dω,

which makes it an unbiased estimate of the variance of white noise (any quantisation noise,
LSB²/12, is included, as it should be). Filter transients at both ends are dropped. The
per-manoeuvre sums of squares are pooled over manoeuvres (weighted by their sample
counts). A constant bias is not noise and is not seen (it lies at 0 Hz).

The result is a variance per channel; R = diag(result).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # names only: Dataset.r_default calls this module, so no runtime import
    from kftune.data.manoeuvre import Dataset, Manoeuvre

#: High-pass corner as a fraction of the Nyquist frequency.
CUTOFF = 0.25
#: Butterworth order.
ORDER = 4
#: Samples dropped at each end of a filtered channel (filter transients).
EDGE = 50
#: Smallest variance returned per channel [Vx, ay, r] (SI²): keeps R positive definite for
#: data that are already smooth (e.g. an INS speed), about a 1 mm/s, 1 mm/s², 0.06 °/s noise.
VARIANCE_FLOOR = np.array([1e-6, 1e-6, 1e-6])
#: The same floor for any channel, in its SI unit squared.
CHANNEL_VARIANCE_FLOOR = 1e-6
#: The channels estimated by default: the single-track model's measurements [Vx, ay, r].
DEFAULT_CHANNELS: tuple[str, ...] = ("vx", "ay", "r")


@lru_cache(maxsize=8)
def _highpass(cutoff: float, order: int) -> tuple[np.ndarray, float]:
    from scipy import integrate, signal  # scipy.signal takes ~1 s to import: only when used

    sos = signal.butter(order, cutoff, btype="highpass", output="sos")
    w, h = signal.sosfreqz(sos, worN=1 << 14)
    gain = float(integrate.trapezoid(np.abs(h) ** 4, w) / np.pi)
    return sos, gain


def highpass_noise_variance(
    z: np.ndarray, cutoff: float = CUTOFF, order: int = ORDER, edge: int = EDGE
) -> tuple[float, int]:
    """Sum of squares of the zero-phase high-passed signal, divided by the noise gain,
    and the number of samples it covers.

    Args:
        z: (n,) one channel of one manoeuvre, n > 2·edge + 30.

    Returns:
        ``(sum_sq / g, count)``; their ratio estimates the white-noise variance.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 1 or z.size <= 2 * edge + 30:
        raise ValueError(f"need a 1-D signal of more than {2 * edge + 30} samples, got {z.shape}")
    sos, gain = _highpass(float(cutoff), int(order))
    from scipy import signal

    y = signal.sosfiltfilt(sos, z - z.mean())[edge : z.size - edge]
    return float(np.dot(y, y)) / gain, int(y.size)


def estimate_measurement_noise(
    source: Dataset | Sequence[Manoeuvre] | Manoeuvre,
    cutoff: float = CUTOFF,
    order: int = ORDER,
    channels: Sequence[str] = DEFAULT_CHANNELS,
) -> np.ndarray:
    """Measurement-noise variances of measured channels from high-pass residual statistics.

    Args:
        source: a dataset (all its manoeuvres), a manoeuvre or a sequence of them.
        cutoff: high-pass corner as a fraction of Nyquist (0 < cutoff < 1).
        channels: the channels, by name (default [Vx, ay, r], the single-track model's
            measurements); each channel is estimated on its own, so a channel's variance
            does not depend on which others are asked for.

    Returns:
        (len(channels),) variances, each in its channel's SI unit squared (default
        [Vx [m²/s²], ay [m²/s⁴], r [rad²/s²]]) and at least :data:`CHANNEL_VARIANCE_FLOOR`;
        R = diag of it.

    Raises:
        MissingChannelError: a manoeuvre lacks one of the channels (named).
    """
    if not 0.0 < cutoff < 1.0:
        raise ValueError(f"cutoff must be a fraction of Nyquist in (0, 1), got {cutoff!r}")
    manoeuvres = _manoeuvres(source)
    names = tuple(channels)
    for m in manoeuvres:
        m.require(names, "the measurement-noise estimate")
    sums = np.zeros(len(names))
    count = 0
    for m in manoeuvres:
        n_used = 0
        for j, name in enumerate(names):
            ss, n_used = highpass_noise_variance(m.channel(name), cutoff, order)
            sums[j] += ss
        count += n_used
    return np.maximum(sums / count, CHANNEL_VARIANCE_FLOOR)


def _manoeuvres(source: Any) -> tuple[Manoeuvre, ...]:
    """A dataset, a manoeuvre or a sequence of manoeuvres as a tuple of manoeuvres.

    Recognised by their attributes (a dataset has ``manoeuvres``, a manoeuvre ``channel``
    and ``require``), not by class, so that this module does not import
    :mod:`kftune.data.manoeuvre`, whose ``Dataset.r_default`` calls it.
    """
    if _is_manoeuvre(source):
        return (source,)
    if hasattr(source, "manoeuvres"):
        return tuple(source.manoeuvres)
    out = tuple(source)
    if not out or not all(_is_manoeuvre(m) for m in out):
        raise ValueError("expected a Dataset, a Manoeuvre or a non-empty sequence of Manoeuvre")
    return out


def _is_manoeuvre(obj: Any) -> bool:
    return all(hasattr(obj, name) for name in ("t", "channel", "require"))
