"""Shared builders for the data tests (no tests here).

``synthetic_channels`` makes kinematically consistent signals (ay = vx·r, small β) so that
they pass every validation check; tests then break exactly one thing.
"""

from __future__ import annotations

import numpy as np

from kftune.data import Dataset, Manoeuvre
from kftune.vehicle import preset


def synthetic_channels(n: int = 400, dt: float = 0.01, seed: int = 0, t0: float = 0.0) -> dict:
    """Channels (SI) of a plausible weaving drive at 20 m/s, with a little noise."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * dt
    vx = 20.0 + 0.5 * np.sin(0.3 * t)
    r = 0.3 * np.sin(1.5 * t)
    return {
        "t": t,
        "delta": 0.05 * np.sin(1.5 * t + 0.1),
        "ax": 0.15 * np.cos(0.3 * t) + 0.05 * rng.standard_normal(n),
        "ay": vx * r + 0.05 * rng.standard_normal(n),
        "r": r + 0.002 * rng.standard_normal(n),
        "vx": vx + 0.02 * rng.standard_normal(n),
        "beta_ref": -0.02 * np.sin(1.5 * t - 0.2),
    }


def synthetic_manoeuvre(
    name: str = "m", split: str = "train", seed: int = 0, n: int = 400, extra: bool = True
) -> Manoeuvre:
    c = synthetic_channels(n=n, seed=seed)
    extras = {"vy_true": 20.0 * c["beta_ref"]} if extra else {}
    return Manoeuvre(
        name=name, kind="slalom", split=split, **c, extra=extras, description=f"synthetic {name}"
    )


def synthetic_dataset(n_train: int = 2, n_test: int = 2) -> Dataset:
    ms = [synthetic_manoeuvre(f"tr{i}", "train", seed=i) for i in range(n_train)]
    ms += [synthetic_manoeuvre(f"te{i}", "test", seed=100 + i) for i in range(n_test)]
    return Dataset(
        "synthetic",
        preset("bmw-320i"),
        0.01,
        tuple(ms),
        "synthetic data",
        {"origin": "tests", "units": {"vy_true": "m/s"}},
    )
