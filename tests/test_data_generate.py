"""The generator and the bundled dataset: determinism, seeds, provenance, coverage."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("vehiclemodels")

from kftune.data import default_dataset, save_dataset
from kftune.data.catalogue import default_catalogue
from kftune.data.generate import DEFAULT_SEED, TRUE_CHANNELS, generate_dataset, generate_manoeuvre

SHORT = ("train-03-j-turn", "test-09-j-turn")
MEASURED = ("delta", "ax", "ay", "r", "vx", "beta_ref")


@pytest.fixture(scope="module")
def seeded():
    return generate_dataset(seed=11, names=SHORT)


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
def test_bundled_dataset_is_this_generators_output(name):
    """Regenerating a bundled manoeuvre with the default seed reproduces it bit for bit, on
    whatever CPU the test runs. The lane change, the random steer and the track lap are the
    paths whose arithmetic NumPy would otherwise hand to CPU-specific kernels (``pow``,
    BLAS ``dot``/``convolve``): the set made on an AVX-512 machine differed in their last
    digits from one made on an AVX2 machine, until ``kftune.data._libm``."""
    spec = next(s for s in default_catalogue() if s.name == name)
    assert generate_manoeuvre(spec, DEFAULT_SEED).equals(default_dataset()[name])
    assert default_dataset().meta["generator"]["seed"] == DEFAULT_SEED
