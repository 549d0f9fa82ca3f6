"""The generic filters' kernels bound to one model, cached on disk across processes.

The text of a module per model (:func:`kftune.models._generated.generated_module`): its
wrappers call the generic kernels (:mod:`kftune.filters._generic_kernel`, whose functions
that take the model's functions are inlined into them) with the model's functions and size
tokens as globals, so that numba caches them and a run passes records of arrays and numbers
only (:mod:`kftune.models.kernel_io`).
"""

from __future__ import annotations

import types

from kftune.models._generated import generated_module
from kftune.models.base import StateSpaceModel

__all__ = ["kernel_module"]

_UKF = """

@numba.njit(error_model="numpy", cache=True)
def ukf_single(data, w, out):
    return gk.ukf_run(f, h, check, data, w, out, n_tok, m_tok)


@numba.njit(parallel=True, error_model="numpy", cache=True)
def ukf_batch(data, w, out, stop, rep, cause):
    gk.ukf_batch(ukf_single, data, w, out, stop, rep, cause)
"""

_EKF = """

@numba.njit(error_model="numpy", cache=True)
def ekf_single_{tag}(data, out):
    return gk.ekf_run(f, h, check, data, out, n_tok, m_tok, {F_way}, {F_jac}, {H_way}, {H_jac})


@numba.njit(parallel=True, error_model="numpy", cache=True)
def ekf_batch_{tag}(data, out, stop, rep, cause):
    gk.ekf_batch(ekf_single_{tag}, data, out, stop, rep, cause)
"""


def kernel_module(model: StateSpaceModel) -> types.ModuleType:
    """The kernel module of ``model``: ``ukf_single``, ``ukf_batch``,
    ``ekf_single_given``/``ekf_batch_given`` (the model's own Jacobians where it has them)
    and ``ekf_single_fd``/``ekf_batch_fd`` (central differences), compiled on first call.

    Their arguments are records (:mod:`kftune.models.kernel_io`): ``ukf_single(data, w,
    out) -> (stop_step, n_repairs, cause)`` with ``data`` a
    :class:`~kftune.models.kernel_io.KernelData`, ``w`` the
    :class:`~kftune.models.kernel_io.SigmaWeights` and ``out`` the
    :class:`~kftune.models.kernel_io.KernelOutputs` it fills; ``ukf_batch(data, w, out,
    stop, rep, cause)`` the same for B settings (data's q, r, x_init, P_init and every
    buffer with a leading axis B; stop, rep, cause (B,) int64 it fills); the EKF's
    ``ekf_single_<tag>(data, out)`` and ``ekf_batch_<tag>(data, out, stop, rep, cause)``
    likewise, without weights."""
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
