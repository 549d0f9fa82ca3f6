"""The generator and the bundled dataset: determinism, seeds, provenance, coverage."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("vehiclemodels")

from kftune.data import default_dataset, save_dataset
from kftune.sim.catalogue import default_catalogue
from kftune.sim.generate import DEFAULT_SEED, TRUE_CHANNELS, generate_dataset, generate_manoeuvre
from test_data_helpers import storage_step_differences

SHORT = ("train-03-j-turn", "test-09-j-turn")
MEASURED = ("delta", "ax", "ay", "r", "vx", "beta_ref")


@pytest.fixture(scope="module")
def seeded():
    return generate_dataset(seed=11, names=SHORT)


@pytest.mark.slow
def test_same_seed_same_bytes(seeded, tmp_path):
    again = generate_dataset(seed=11, names=SHORT)
    for a, b in zip(seeded.manoeuvres, again.manoeuvres):
        assert a.equals(b)
    save_dataset(seeded, tmp_path / "a")
    save_dataset(again, tmp_path / "b")
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert files == ["manifest.toml", *sorted(f"{n}.csv.gz" for n in SHORT)]
    for name in files:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_other_seed_other_noise_same_plant(seeded):
    other = generate_dataset(seed=12, names=SHORT)
    for a, b in zip(seeded.manoeuvres, other.manoeuvres):
        for c in MEASURED:
            assert not np.array_equal(a.channel(c), b.channel(c)), c
        for c in TRUE_CHANNELS:  # the plant and drivers do not depend on the seed
            assert np.array_equal(a.extra[c], b.extra[c]), c
        np.testing.assert_array_equal(a.t, b.t)


def test_a_manoeuvres_noise_does_not_depend_on_the_others(seeded):
    alone = generate_dataset(seed=11, names=[SHORT[1]])
    assert alone.manoeuvres[0].equals(seeded[SHORT[1]])


@pytest.mark.parametrize(
    "name", ["train-04-j-turn", "train-07-lane-change", "test-18-random-steer", "test-20-track-lap"]
)
@pytest.mark.slow
def test_bundled_dataset_is_this_generators_output(name):
    """Regenerating a bundled manoeuvre with the default seed reproduces it to within what
    floating point allows across CPUs: at most one step of each channel, on a small share of
    the samples (:func:`storage_step_differences`; a step is the storage step, one sensor
    step for a measured channel, 3e-4 of the range for a true one). Bit-for-bit identity
    holds on one machine (``test_same_seed_same_bytes``), not across machines: the
    generator's own arithmetic avoids CPU-specific kernels (``kftune.sim._libm``), but
    SciPy's LSODA calls the BLAS, whose kernels OpenBLAS picks by CPU. On an AVX-512 Xeon
    the true channels of these manoeuvres differ from the bundle (made on an AVX2 machine)
    by up to 7e-5 of their range, and a measured channel rounds to the neighbouring sensor
    step on up to 6 % of its samples (δ by 0.1°/15, r by 0.01°/s)."""
    spec = next(s for s in default_catalogue() if s.name == name)
    problems = storage_step_differences(
        generate_manoeuvre(spec, DEFAULT_SEED), default_dataset()[name]
    )
    assert not problems, "\n".join(problems)
    assert default_dataset().meta["generator"]["seed"] == DEFAULT_SEED


def test_a_j_turn_with_another_noise_seed_passes_the_steering_check():
    """With seed 7 this J-turn was refused: the median of vx·δ/r over its steering release
    (δ back at zero, yaw rate still decaying) was 0.14 m; the least-squares effective
    wheelbase gives those samples no weight (``kftune.data.validate``)."""
    ds = generate_dataset(seed=7, names=["test-08-j-turn"])
    assert ds["test-08-j-turn"].t.size > 0
