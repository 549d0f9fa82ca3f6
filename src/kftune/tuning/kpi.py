"""Key performance indicators of the sideslip estimate (paper Sec. V-D).

All KPIs are in **degrees**. MAE follows the paper: the *maximum* absolute error, not the
mean. The "NON" variants keep only samples where the vehicle is in its nonlinear range,
|ay| ≥ 4 m/s² (measured lateral acceleration).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

#: Lateral-acceleration threshold of the nonlinear-range KPIs [m/s²] (paper Sec. V-D).
AY_NONLINEAR = 4.0

#: KPI names in report order.
KPI_NAMES: tuple[str, ...] = ("rmse", "mae", "rmse_non", "mae_non")


def sideslip_kpis(
    beta_est: np.ndarray,
    beta_ref: np.ndarray,
    ay: np.ndarray,
    *,
    ay_threshold: float = AY_NONLINEAR,
) -> dict[str, float]:
    """Sideslip KPIs of one manoeuvre.

    Args:
        beta_est: (N,) estimated sideslip [rad].
        beta_ref: (N,) reference sideslip [rad].
        ay: (N,) measured lateral acceleration [m/s²], selects the nonlinear samples.
        ay_threshold: |ay| threshold of the NON KPIs [m/s²].

    Returns:
        ``{"rmse", "mae", "rmse_non", "mae_non"}`` in degrees, and ``"n_non"``, the number
        of samples with |ay| ≥ threshold. The NON KPIs are NaN when ``n_non == 0``.
    """
    beta_est = np.asarray(beta_est, dtype=float)
    beta_ref = np.asarray(beta_ref, dtype=float)
    ay = np.asarray(ay, dtype=float)
    if not (beta_est.shape == beta_ref.shape == ay.shape) or beta_est.ndim != 1:
        raise ValueError(
            "beta_est, beta_ref and ay must be 1-D arrays of equal length, got shapes "
            f"{beta_est.shape}, {beta_ref.shape}, {ay.shape}"
        )
    if beta_est.size == 0:
        raise ValueError("cannot compute KPIs of an empty manoeuvre")
    err = np.degrees(beta_est - beta_ref)
    mask = np.abs(ay) >= ay_threshold
    n_non = int(mask.sum())
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mae": float(np.max(np.abs(err))),
        "rmse_non": float(np.sqrt(np.mean(err[mask] ** 2))) if n_non else math.nan,
        "mae_non": float(np.max(np.abs(err[mask]))) if n_non else math.nan,
        "n_non": n_non,
    }


def average_kpis(
    per_manoeuvre: Iterable[Mapping[str, float]], names: Sequence[str] = KPI_NAMES
) -> dict[str, float]:
    """Average KPIs over manoeuvres, as the paper's Tables VI–VII do (plain mean).

    ``names``: the KPIs averaged (default the sideslip KPIs; e.g. ``rmse_<channel>`` for
    the channel RMSEs of another model). A KPI is averaged only over the manoeuvres where
    it is not NaN (a NON KPI over those that have nonlinear samples); it is NaN when none
    has it. If the filter diverged on any manoeuvre (a row with ``diverged`` true),
    every average is NaN — an average over the survivors would flatter the filter — and
    ``n_diverged`` says on how many.

    Returns:
        the KPI averages, ``n_diverged`` and ``n_manoeuvres``.
    """
    rows = list(per_manoeuvre)
    if not rows:
        raise ValueError("no manoeuvres to average")
    n_diverged = sum(1 for r in rows if r.get("diverged", 0))
    out: dict[str, float] = {}
    for name in names:
        values = [r[name] for r in rows if not math.isnan(r.get(name, math.nan))]
        out[name] = float(np.mean(values)) if values and not n_diverged else math.nan
    out["n_diverged"] = n_diverged
    out["n_manoeuvres"] = len(rows)
    return out
