"""R from high-pass residual statistics, against known noise (Monte Carlo) and against the
generator's sensor model."""

from __future__ import annotations

import numpy as np
import pytest

from kftune.data import Manoeuvre, estimate_measurement_noise, open_dataset
from kftune.data.noise import highpass_noise_variance
from test_data_helpers import synthetic_channels


def test_white_noise_variance_is_recovered_under_a_vehicle_like_signal():
    """Smooth manoeuvre content (below 3 Hz) + white noise: the estimate is unbiased
    (mean over 40 draws within 2 % of σ², each draw within 10 %)."""
    t = np.arange(3000) * 0.01
    smooth = 4.0 * np.sin(0.7 * t) + 2.0 * np.sin(2 * np.pi * 2.5 * t + 1.0) + 0.3 * t
    rng = np.random.default_rng(1)
    sigma = 0.08
    est = []
    for _ in range(40):
        ss, n = highpass_noise_variance(smooth + sigma * rng.standard_normal(t.size))
        est.append(ss / n)
    est = np.array(est)
    assert np.mean(est) == pytest.approx(sigma**2, rel=0.02)
    assert np.all(np.abs(est / sigma**2 - 1.0) < 0.10)


def test_quantisation_noise_is_included():
    t = np.arange(20_000) * 0.01
    rng = np.random.default_rng(2)
    lsb, sigma = 0.05, 0.02
    z = np.round((3.0 * np.sin(0.4 * t) + sigma * rng.standard_normal(t.size)) / lsb) * lsb
    ss, n = highpass_noise_variance(z)
    assert ss / n == pytest.approx(sigma**2 + lsb**2 / 12.0, rel=0.06)


def test_per_channel_and_pooled_over_manoeuvres():
    rng = np.random.default_rng(3)
    ms = []
    for i, n in enumerate((1500, 4000)):
        c = synthetic_channels(n=n, seed=i)
        c["vx"] = 20.0 + 0.5 * np.sin(0.3 * c["t"]) + 0.03 * rng.standard_normal(n)
        c["ay"] = 20.0 * 0.3 * np.sin(1.5 * c["t"]) + 0.1 * rng.standard_normal(n)
        c["r"] = 0.3 * np.sin(1.5 * c["t"]) + 0.004 * rng.standard_normal(n)
        ms.append(Manoeuvre(name=f"m{i}", kind="slalom", split="train", **c))
    r = estimate_measurement_noise(ms)
    np.testing.assert_allclose(r, [0.03**2, 0.1**2, 0.004**2], rtol=0.1)
    with pytest.raises(ValueError, match="cutoff"):
        estimate_measurement_noise(ms, cutoff=1.5)
    with pytest.raises(ValueError):
        estimate_measurement_noise([])


def test_a_dataset_a_manoeuvre_or_a_sequence_of_them_is_accepted():
    """The estimator tells its inputs apart by their attributes (it does not import the
    classes, whose ``Dataset.r_default`` calls it)."""
    ds = open_dataset(None)
    pooled = estimate_measurement_noise(ds)
    np.testing.assert_array_equal(pooled, estimate_measurement_noise(list(ds.manoeuvres)))
    one = ds.manoeuvres[0]
    np.testing.assert_array_equal(
        estimate_measurement_noise(one), estimate_measurement_noise([one])
    )
    with pytest.raises(ValueError, match="sequence of Manoeuvre"):
        estimate_measurement_noise([one, "not a manoeuvre"])


def test_bundled_dataset_r_matches_the_sensor_model():
    """On the generated data the estimate finds the sensor model's white noise (noise +
    resolution; the biases are constant and invisible to it). Needs no CommonRoad."""
    from kftune.sim.sensors import SensorModel

    ds = open_dataset(None)
    np.testing.assert_allclose(ds.r_default, SensorModel().white_noise_variances(), rtol=0.1)
    np.testing.assert_array_equal(ds.r_default, estimate_measurement_noise(ds.train))
