"""Dugoff tyre model: linear region, saturation, symmetry, and the textbook formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.vehicle.tyre import dugoff_fy_scalar, dugoff_fy_scalar_kappa, dugoff_lateral_force

C, FZ, MU = 60_000.0, 4_000.0, 1.0


def textbook_dugoff(alpha: float, Fz: float, C_a: float, mu: float, kappa: float, C_x: float):
    """Dugoff as printed (Rajamani 2nd ed. Ch. 13, braking-slip sign), scalar, literal."""
    den = 2 * math.sqrt((C_x * kappa) ** 2 + (C_a * math.tan(alpha)) ** 2)
    if den == 0.0:
        return None  # undefined as printed (λ = ∞); the limit is the linear tyre, F_y = 0
    lam = mu * Fz * (1 - kappa) / den
    f = (2 - lam) * lam if lam < 1 else 1.0
    return C_a * math.tan(alpha) / (1 - kappa) * f


def test_linear_region_is_c_tan_alpha():
    # λ ≥ 1 ⇔ C·|tan α| ≤ μ·Fz/2
    alpha_max = math.atan(MU * FZ / (2 * C))
    alpha = np.linspace(-alpha_max, alpha_max, 201)
    np.testing.assert_allclose(
        dugoff_lateral_force(alpha, FZ, C, MU), C * np.tan(alpha), rtol=1e-14, atol=1e-9
    )
    # just beyond the linear region the force is below the linear tyre's
    beyond = alpha_max * 1.2
    assert dugoff_lateral_force(beyond, FZ, C, MU) < C * math.tan(beyond)


def test_saturates_at_mu_fz_and_is_bounded_and_monotonic():
    alpha = np.linspace(-math.pi / 2 + 1e-9, math.pi / 2 - 1e-9, 20001)
    fy = dugoff_lateral_force(alpha, FZ, C, MU)
    assert np.all(np.abs(fy) <= MU * FZ * (1 + 1e-12))
    assert np.all(np.diff(fy) >= 0)  # non-decreasing in α on (−π/2, π/2)
    # limit: λ → 0 as tan α → ∞ gives |F_y| → μ·Fz
    assert fy[-1] == pytest.approx(MU * FZ, rel=1e-9)
    assert fy[0] == pytest.approx(-MU * FZ, rel=1e-9)
    # a large slip angle is close to the limit (λ = μFz/(2C tan α), F = μFz(1 − λ/2))
    a = math.radians(60)
    lam = MU * FZ / (2 * C * math.tan(a))
    assert dugoff_lateral_force(a, FZ, C, MU) == pytest.approx(MU * FZ * (1 - lam / 2), rel=1e-14)


@given(
    alpha=st.floats(-1.5, 1.5),
    Fz=st.floats(100.0, 20_000.0),
    C_a=st.floats(1e3, 3e5),
    mu=st.floats(0.1, 2.0),
    kappa=st.floats(-0.5, 0.95),
)
@settings(max_examples=200, deadline=None)
def test_symmetric_in_alpha_and_matches_textbook(alpha, Fz, C_a, mu, kappa):
    fy = float(dugoff_lateral_force(alpha, Fz, C_a, mu, kappa, 1.2e5))
    assert float(dugoff_lateral_force(-alpha, Fz, C_a, mu, kappa, 1.2e5)) == -fy
    ref = textbook_dugoff(alpha, Fz, C_a, mu, kappa, 1.2e5)
    if ref is None:
        assert fy == pytest.approx(
            C_a * math.tan(alpha), abs=1e-9
        )  # the limit for the textbook form
    else:
        assert fy == pytest.approx(ref, rel=1e-12, abs=1e-9)
    # the compiled scalar versions are the same function
    assert dugoff_fy_scalar_kappa(math.tan(alpha), kappa, Fz, C_a, 1.2e5, mu) == pytest.approx(
        fy, rel=1e-12, abs=1e-9
    )
    if kappa == 0.0:
        assert dugoff_fy_scalar(math.tan(alpha), Fz, C_a, mu) == pytest.approx(
            fy, rel=1e-12, abs=1e-9
        )


def test_continuous_with_continuous_slope_at_lambda_one():
    t1 = MU * FZ / (2 * C)  # tan α at λ = 1
    eps = 1e-7
    lo, hi = t1 * (1 - eps), t1 * (1 + eps)
    f_lo = dugoff_fy_scalar(lo, FZ, C, MU)
    f_hi = dugoff_fy_scalar(hi, FZ, C, MU)
    assert f_hi - f_lo == pytest.approx(C * (hi - lo), rel=1e-6)  # slope C on both sides


def test_axle_lumping_is_exact_for_two_equal_tyres():
    alpha = np.linspace(-0.5, 0.5, 101)
    np.testing.assert_allclose(
        dugoff_lateral_force(alpha, 2 * FZ, 2 * C, MU),
        2 * dugoff_lateral_force(alpha, FZ, C, MU),
        rtol=1e-14,
        atol=1e-9,
    )


def test_unloaded_wheel_carries_no_force_and_broadcasting():
    assert dugoff_lateral_force(0.1, 0.0, C, MU) == 0.0
    assert dugoff_lateral_force(0.1, -50.0, C, MU) == 0.0
    assert dugoff_fy_scalar(0.1, -50.0, C, MU) == 0.0
    assert dugoff_lateral_force(0.0, FZ, C, MU) == 0.0
    out = dugoff_lateral_force(np.zeros((4, 1)), np.array([1e3, 2e3, 3e3]), C, MU)
    assert out.shape == (4, 3)
    assert dugoff_fy_scalar(math.inf, FZ, C, MU) == MU * FZ
    assert dugoff_fy_scalar_kappa(-math.inf, 0.3, FZ, C, 1e5, MU) == -MU * FZ


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"alpha": np.array([0.1, np.nan])}, r"alpha must be finite.*index \(1,\)"),
        ({"Fz": np.inf}, "Fz must be finite"),
        ({"C_alpha": 0.0}, "C_alpha must be > 0"),
        ({"mu": -1.0}, "mu must be > 0"),
        ({"kappa": 1.5}, "kappa"),
    ],
)
def test_bad_input_is_refused(kwargs, match):
    args = {"alpha": 0.1, "Fz": FZ, "C_alpha": C, "mu": MU} | kwargs
    with pytest.raises(ValueError, match=match):
        dugoff_lateral_force(**args)
