"""The reference-data simulator: an application of the core, not part of the loaders.

It makes the bundled dataset (``kftune dataset generate``): the 31 manoeuvres of
:mod:`kftune.sim.catalogue`, driven by the drivers of :mod:`kftune.sim.drivers`
(:mod:`kftune.sim.simulate` closes the loop) on CommonRoad's multi-body plant
(:mod:`kftune.sim.plant`, needs the ``[simulate]`` extra), measured by the sensor models of
:mod:`kftune.sim.sensors`; :func:`kftune.sim.generate.generate_dataset` puts them together.
It builds :class:`kftune.data.Dataset` objects; nothing in :mod:`kftune.data` imports it.

Typical use::

    from kftune.sim.generate import generate_dataset
    ds = generate_dataset(seed=2024, names=["train-03-j-turn"])  # needs [simulate]

This module imports nothing, so that ``from kftune.sim import _libm`` in its submodules
does not load the plant.
"""
