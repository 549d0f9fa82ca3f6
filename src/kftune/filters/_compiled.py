"""The generic filters' kernels bound to one model, cached on disk across processes.

The text of a module per model (:func:`kftune.models._generated.generated_module`): its
wrappers call the generic kernels (:mod:`kftune.filters._generic_kernel`, whose functions
that take the model's functions are inlined into them) with the model's functions and size
tokens as globals, so that numba caches them and a run passes arrays and numbers only.
"""

from __future__ import annotations

import types

from kftune.models._generated import generated_module
from kftune.models.base import StateSpaceModel

__all__ = ["kernel_module"]

_UKF = """

@numba.njit(error_model="numpy", cache=True)
def ukf_single(u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes, wm0, wc0, wi, c,
               ox, op, oz, oi, on, ol):
    return gk.ukf_run(f, h, check, u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                      n_tok, m_tok, wm0, wc0, wi, c, ox, op, oz, oi, on, ol)


@numba.njit(parallel=True, error_model="numpy", cache=True)
def ukf_batch(u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes, wm0, wc0, wi, c,
              ox, op, oz, oi, on, ol, stop, rep, cause):
    gk.ukf_batch(f, h, check, u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                 n_tok, m_tok, wm0, wc0, wi, c, ox, op, oz, oi, on, ol, stop, rep, cause)
"""

_EKF = """

@numba.njit(error_model="numpy", cache=True)
def ekf_single_{tag}(u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                     ox, op, oz, oi, on, ol):
    return gk.ekf_run(f, h, check, u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                      n_tok, m_tok, {F_way}, {F_jac}, {H_way}, {H_jac}, ox, op, oz, oi, on, ol)


@numba.njit(parallel=True, error_model="numpy", cache=True)
def ekf_batch_{tag}(u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                    ox, op, oz, oi, on, ol, stop, rep, cause):
    gk.ekf_batch(f, h, check, u, z, p, dt, q, r, x_init, P_init, n_hold, held_causes,
                 n_tok, m_tok, {F_way}, {F_jac}, {H_way}, {H_jac},
                 ox, op, oz, oi, on, ol, stop, rep, cause)
"""


def kernel_module(model: StateSpaceModel) -> types.ModuleType:
    """The kernel module of ``model``: ``ukf_single``, ``ukf_batch``,
    ``ekf_single_given``/``ekf_batch_given`` (the model's own Jacobians where it has them)
    and ``ekf_single_fd``/``ekf_batch_fd`` (central differences), with the arguments of
    :func:`~kftune.filters._generic_kernel.ukf_run` and ``ekf_run`` less the model's
    functions, the size tokens and the Jacobian choice (compiled on first call)."""
    code = "\nfrom kftune.filters import _generic_kernel as gk\n" + _UKF
    for tag, own in (("given", True), ("fd", False)):
        use_F = own and model.F is not None
        use_H = own and model.H is not None
        code += _EKF.format(
            tag=tag,
            F_way="gk.given_process_jacobian" if use_F else "gk.numerical_process_jacobian",
            F_jac="F" if use_F else "f",
            H_way="gk.given_measurement_jacobian" if use_H else "gk.numerical_measurement_jacobian",
            H_jac="H" if use_H else "h",
        )
    return generated_module(model, "Filter kernels", code)
