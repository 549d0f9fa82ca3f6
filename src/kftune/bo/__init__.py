"""Surrogate models and acquisition functions for Bayesian optimisation (paper Sec. III).

Everything here works in a box (default [0, 1]^d) and knows nothing about vehicles, filters
or data files. A surrogate is fitted on (X (n, d), y (n,)) and returns a
:class:`~kftune.bo.base.Predictive`; the functions of :mod:`kftune.bo.acquisition` read only
that and the incumbent::

    from kftune.bo import make_surrogate
    from kftune.bo.acquisition import expected_improvement

    model = make_surrogate("tsp", seed=0).fit(X, y)   # Student-t process, ν = 15
    ei = expected_improvement(model.predict(candidates), best=y.min())
"""

from __future__ import annotations

import inspect
from typing import Any

from kftune.bo._model import BoxSurrogate
from kftune.bo.base import Predictive, Surrogate
from kftune.bo.gp import GaussianProcess
from kftune.bo.kernels import Kernel, Matern52, SquaredExponential, make_kernel
from kftune.bo.robust_gp import RobustGaussianProcess
from kftune.bo.student_t import StudentTProcess

#: Surrogate names accepted by :func:`make_surrogate`.
SURROGATES: dict[str, type[BoxSurrogate]] = {
    "tsp": StudentTProcess,
    "gp": GaussianProcess,
    "robust-gp": RobustGaussianProcess,
}


def _accepted_options(cls: type) -> set[str]:
    names: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        for p in inspect.signature(init).parameters.values():
            if p.kind is p.KEYWORD_ONLY:
                names.add(p.name)
    return names


def make_surrogate(name: str, *, seed: int | None = None, **options: Any) -> BoxSurrogate:
    """Build a surrogate by name.

    Args:
        name: ``"tsp"`` (:class:`StudentTProcess`, ν = 15 unless ``dof=``; ``fit_dof=True``
            fits ν > 2), ``"gp"`` (:class:`GaussianProcess`, exact), or ``"robust-gp"``
            (:class:`RobustGaussianProcess`: GP with Student-t noise, Laplace approximation).
        seed: seeds the restarts of the hyperparameter fit (reproducible fits).
        **options: keyword options of that class (e.g. ``bounds``, ``kernel``, ``noise``,
            ``n_restarts``); see the class docstrings.

    Raises:
        ValueError: unknown name (the message lists the valid ones) or unknown option.
    """
    try:
        cls = SURROGATES[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown surrogate {name!r}; valid names: {', '.join(SURROGATES)}"
        ) from None
    accepted = _accepted_options(cls)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ValueError(
            f"unknown option(s) {unknown} for surrogate {name!r}; valid options: "
            f"{', '.join(sorted(accepted - {'seed'}))}"
        )
    return cls(seed=seed, **options)


__all__ = [
    "SURROGATES",
    "GaussianProcess",
    "Kernel",
    "Matern52",
    "Predictive",
    "RobustGaussianProcess",
    "SquaredExponential",
    "StudentTProcess",
    "Surrogate",
    "make_kernel",
    "make_surrogate",
]
