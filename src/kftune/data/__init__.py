"""Manoeuvre data: the in-memory types, loading and validation, and noise statistics.

Typical use::

    from kftune.data import default_dataset, estimate_measurement_noise
    ds = default_dataset()                 # the bundled 31 manoeuvres (8 train, 23 test)
    m = ds.train[0]                        # a Manoeuvre: m.t, m.channel("vx"), m.beta_ref, …
    R = ds.r_default                       # (3,) variances [Vx, ay, r] from sensor statistics
    R = ds.noise_variances(["vx", "r"])    # any measured channels, by name

Everything here needs only numpy and scipy. The generator of the bundled data is a package
of its own, :mod:`kftune.sim` (it needs the ``[simulate]`` extra).
"""

from __future__ import annotations

from kftune.data.importer import import_recordings, load_revs, open_dataset
from kftune.data.io import bundled_dataset_path, default_dataset, load_dataset, save_dataset
from kftune.data.manoeuvre import KINDS, SPLITS, Dataset, Manoeuvre
from kftune.data.noise import estimate_measurement_noise
from kftune.data.textfile import ReadLimits
from kftune.data.validate import (
    REQUIRED_CHANNELS,
    SIDESLIP_CHANNELS,
    UNITS,
    validate_channels,
)

__all__ = [
    "KINDS",
    "REQUIRED_CHANNELS",
    "SIDESLIP_CHANNELS",
    "SPLITS",
    "UNITS",
    "Dataset",
    "Manoeuvre",
    "ReadLimits",
    "bundled_dataset_path",
    "default_dataset",
    "estimate_measurement_noise",
    "import_recordings",
    "load_dataset",
    "load_revs",
    "open_dataset",
    "save_dataset",
    "validate_channels",
]
