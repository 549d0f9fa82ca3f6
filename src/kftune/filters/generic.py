"""UKF and EKF over any state-space model, behind one interface and one result type.

    >>> from kftune.filters import UKF, EKF
    >>> res = UKF().run("single-track", u, z, dt, q, r)        # or EKF().run(...)
    >>> res.x, res.P_diag, res.nis, res.diverged_step

A filter is a small frozen object (its options: the UKF's sigma-point settings); the model
(:class:`kftune.models.StateSpaceModel`, or a registered name) and the data are arguments of
``run`` (one noise setting) and ``run_batch`` (B settings in parallel over a numba
``prange``). Both return :class:`FilterResult` / :class:`FilterBatchResult` whatever the
filter, as dynamax's EKF and UKF return one posterior type.

Time convention (every loop's, the C export's too): sample k carries u[k] and z[k];
step 0 updates the prior (x0, P0) with z[0]; step k ≥ 1 predicts from k−1 to k with u[k−1]
held, then updates with z[k] through h(·, u[k]). Q = diag(q) and R = diag(r) are the
variances of the additive process noise per step and of the measurement noise, in the
squared units of the model's states and measurements. The default prior is the model's
``initial_state`` rule applied to z[0] and r.

Robustness: bad input is refused before the run with a ``ValueError`` naming the argument,
the row and what was expected; a run that diverges (a covariance that jitter cannot repair,
a non-finite estimate, or a model's own validity check) returns ``diverged`` with the step
and cause and NaN rows from that step on, never an exception
(:mod:`kftune.filters._generic_kernel`).

First use of a filter on a model compiles its kernel for that model (a few seconds per
model and filter); later processes load it from a cache on disk
(:mod:`kftune.filters._compiled`).
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numba
import numpy as np
from numpy.typing import ArrayLike

from kftune.filters._checks import check_covariance, check_dt, check_noise, check_state, check_table
from kftune.filters._compiled import kernel_module
from kftune.filters.sigma_points import UKFSettings, merwe_weights
from kftune.models.base import STOP_NONE, StateSpaceModel
from kftune.models.kernel_io import KernelData, KernelOutputs, SigmaWeights
from kftune.models.registry import resolve_model

__all__ = [
    "EKF",
    "UKF",
    "FilterBatchResult",
    "FilterResult",
    "ModelFilter",
    "filter_names",
    "get_filter",
]


# --------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FilterResult:
    """One filter run over a manoeuvre of N samples (n states, m measurements).

    Attributes:
        x: (N, n) posterior states, in the model's state units.
        P_diag: (N, n) diagonal of the posterior covariance (squared state units).
        z_hat: (N, m) estimated measurements h(x⁺_k, u_k).
        innovation: (N, m) z_k − ẑ_k (ẑ_k the filter's prediction of the measurement).
        nis: (N,) normalised innovation squared yᵀS⁻¹y [-] (χ² with m dof when consistent).
        diverged: True when the run stopped early (see ``diverged_step``).
        diverged_step: first step whose outputs are invalid (rows ≥ it are NaN); −1 if none.
            For a condition held over a time, the step it began.
        n_repairs: covariance factorisations that needed jitter.
        diverged_cause: why it stopped (0: it did not), a code of the model's
            :meth:`~kftune.models.StateSpaceModel.stop_reason`.
        model: the model filtered.
        filter: the filter's name ("ukf", "ekf").
        log_det_s: (N,) log det S_k of the innovation covariance (with ``nis``, the
            Gaussian innovation log-likelihood).
    """

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    diverged: bool
    diverged_step: int
    n_repairs: int
    diverged_cause: int
    model: StateSpaceModel = field(repr=False)
    filter: str = ""
    log_det_s: np.ndarray | None = None

    @property
    def diverged_reason(self) -> str:
        """Why the run stopped, in words ("" when it did not)."""
        return self.model.stop_reason(self.diverged_cause)

    def state(self, name: str) -> np.ndarray:
        """(N,) posterior estimate of the state called ``name``."""
        return self.x[:, _index(self.model.state_names, name, "state")]

    def output(self, name: str) -> np.ndarray:
        """(N,) a derived output of the model from the posterior states (its
        :attr:`~kftune.models.StateSpaceModel.outputs`, e.g. the single-track models'
        sideslip ``"beta"`` [rad])."""
        if name not in self.model.outputs:
            raise ValueError(f"no output {name!r}; the model's are {list(self.model.outputs)}")
        return np.asarray(self.model.outputs[name](self.x), dtype=float)


@dataclass(frozen=True, eq=False)
class FilterBatchResult:
    """B runs (one per noise setting) over the same manoeuvre.

    Attributes are those of :class:`FilterResult` with a leading axis B: x, P_diag (B, N, n);
    z_hat, innovation (B, N, m); nis, log_det_s (B, N); diverged (B,) bool; diverged_step,
    n_repairs, diverged_cause (B,) int.
    """

    x: np.ndarray
    P_diag: np.ndarray
    z_hat: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    diverged: np.ndarray
    diverged_step: np.ndarray
    n_repairs: np.ndarray
    diverged_cause: np.ndarray
    model: StateSpaceModel = field(repr=False)
    filter: str = ""
    log_det_s: np.ndarray | None = None

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, b: int) -> FilterResult:
        """The b-th run as a :class:`FilterResult` (views, no copies)."""
        return FilterResult(
            x=self.x[b],
            P_diag=self.P_diag[b],
            z_hat=self.z_hat[b],
            innovation=self.innovation[b],
            nis=self.nis[b],
            diverged=bool(self.diverged[b]),
            diverged_step=int(self.diverged_step[b]),
            n_repairs=int(self.n_repairs[b]),
            diverged_cause=int(self.diverged_cause[b]),
            model=self.model,
            filter=self.filter,
            log_det_s=None if self.log_det_s is None else self.log_det_s[b],
        )


def _index(names: tuple[str, ...], name: str, what: str) -> int:
    try:
        return names.index(name)
    except ValueError:
        raise ValueError(f"no {what} {name!r}; the model's are {list(names)}") from None


# --------------------------------------------------------------------------------------
# Checked arguments of a run
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Run:
    """Everything a kernel needs, checked: prepared inputs, z, p, dt, q, r, priors."""

    model: StateSpaceModel
    u: np.ndarray  # (N, n_w) prepared inputs
    z: np.ndarray  # (N, m)
    p: np.ndarray  # (n_p,)
    dt: float
    q: np.ndarray  # (B, n)
    r: np.ndarray  # (B, m)
    x_init: np.ndarray  # (B, n)
    P_init: np.ndarray  # (B, n, n)
    n_hold: int
    held_causes: np.ndarray  # (n_held,) int64

    def outputs(self) -> KernelOutputs:
        """The B runs' output buffers, (B, N, …)."""
        n, m = self.model.n_states, self.model.n_measurements
        return KernelOutputs.empty(self.z.shape[0], n, m, batch=self.q.shape[0])

    def head(self, b: int | None) -> KernelData:
        """The data of a bound kernel for setting b (None: all B, for the batch)."""
        sl = slice(None) if b is None else b
        return KernelData(
            self.u, self.z, self.p, self.dt, self.q[sl], self.r[sl], self.x_init[sl],
            self.P_init[sl], self.n_hold, self.held_causes,
        )  # fmt: skip


@functools.lru_cache(maxsize=64)
def _unit_texts(model: StateSpaceModel) -> tuple[str, str, str, str]:
    """How the messages name the units of u, z, q and r, e.g. "[m/s, rad] for [Vx, r]"."""
    return (
        _units(model.input_names, model.input_units, square=False),
        _units(model.measurement_names, model.measurement_units, square=False),
        _units(model.state_names, model.state_units, square=True),
        _units(model.measurement_names, model.measurement_units, square=True),
    )


def _units(names: tuple[str, ...], units: tuple[str, ...], square: bool) -> str:
    fmt = "({})²" if square else "{}"
    return "[" + ", ".join(fmt.format(u or "-") for u in units) + "] for [" + ", ".join(names) + "]"


def _check_run(
    model: StateSpaceModel | str,
    u: ArrayLike | None,
    z: ArrayLike,
    dt: float,
    q: ArrayLike,
    r: ArrayLike,
    params: Any,
    x0: ArrayLike | None,
    P0: ArrayLike | None,
    *,
    batch: bool,
) -> _Run:
    """All checks of a run, before any loop runs."""
    model = resolve_model(model)
    n, m = model.n_states, model.n_measurements
    u_units, z_units, q_units, r_units = _unit_texts(model)
    no_u = u is None and model.n_inputs == 0
    u_arr = None if no_u else check_table("u", u, model.input_names, u_units)
    z_arr = check_table("z", z, model.measurement_names, z_units)
    if u_arr is None:
        u_arr = np.zeros((z_arr.shape[0], 0))
    if u_arr.shape[0] != z_arr.shape[0]:
        raise ValueError(
            f"u and z must have the same number of rows (one per sample); got u with "
            f"{u_arr.shape[0]} rows and z with {z_arr.shape[0]} rows"
        )
    if model.validate_data is not None:
        model.validate_data(u_arr, z_arr)
    dt_f = check_dt(dt)
    p = model.params_vector(params)
    q_arr = check_noise("q", q, q_units, strictly_positive=False, batch=batch, dim=n)
    q_arr = q_arr if batch else q_arr[None, :]
    n_sets = q_arr.shape[0]
    r_in = np.asarray(r, dtype=np.float64)
    if r_in.ndim <= 1 or not batch:
        r_arr = check_noise("r", r_in, r_units, strictly_positive=True, batch=False, dim=m)
        r_arr = np.broadcast_to(r_arr, (n_sets, m))
    else:
        r_arr = check_noise("r", r_in, r_units, strictly_positive=True, batch=True, dim=m)
        if r_arr.shape[0] != n_sets:
            raise ValueError(
                f"r must have shape ({m},) or (B, {m}) with B = {n_sets} (the rows of q), "
                f"got shape {r_arr.shape}"
            )
    w = model.prepared_inputs(u_arr, p)
    x_init = np.empty((n_sets, n))
    P_init = np.empty((n_sets, n, n))
    given_x = None if x0 is None else check_state(x0, model.state_names)
    given_P = None if P0 is None else check_covariance(P0, n)
    if given_x is not None:
        _check_valid_state(model, given_x, z_arr[0], w[0], p)
    for b in range(n_sets):  # the default prior uses each run's own r
        if given_x is None or given_P is None:
            if model.initial_state is None:
                raise ValueError(f"model {model.name!r} has no initial-state rule: give x0 and P0")
            dx, dP = model.initial_state(z_arr[0], r_arr[b], p)
        x_init[b] = dx if given_x is None else given_x
        P_init[b] = dP if given_P is None else given_P
    n_hold = max(1, int(model.hold_time / dt_f + 0.5)) if model.held_causes else 1

    def kernel_array(a: np.ndarray) -> np.ndarray:
        # C-ordered and writable, the one array type every loop is compiled for (a
        # read-only z or a broadcast r would compile another version: for the model's own
        # vector lanes, an unvectorised one); copies only what is not so already
        return np.require(a, dtype=np.float64, requirements=("C", "W"))

    return _Run(
        model, kernel_array(w), kernel_array(z_arr), kernel_array(p), dt_f,
        kernel_array(q_arr), kernel_array(r_arr), x_init, P_init, n_hold,
        np.array(model.held_causes, dtype=np.int64),
    )  # fmt: skip


def _check_valid_state(
    model: StateSpaceModel, x0: np.ndarray, z0: np.ndarray, w0: np.ndarray, p: np.ndarray
) -> None:
    """Refuse a given prior mean that the model's own check calls invalid."""
    if model.check is None:
        return
    cause = model.check(x0, z0, w0, p, np.zeros(len(model.held_causes), dtype=np.bool_))
    if cause != STOP_NONE:
        raise ValueError(
            f"x0 = {x0.tolist()} is not a valid state of model {model.name!r}: "
            f"{model.stop_reason(cause)}"
        )


# --------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------


class ModelFilter(ABC):
    """A Kalman-type filter over any :class:`~kftune.models.StateSpaceModel`."""

    #: The filter's registry name.
    name: ClassVar[str]

    @abstractmethod
    def _options(self, model: StateSpaceModel) -> tuple[Any, ...]:
        """The kernel arguments between the data and the outputs: the UKF's
        (:class:`~kftune.models.kernel_io.SigmaWeights`,), the EKF's ()."""

    @abstractmethod
    def _bound(self, model: StateSpaceModel) -> tuple[Any, Any]:
        """(single-run, batch) kernels bound to the model's functions."""

    def run(
        self,
        model: StateSpaceModel | str,
        u: ArrayLike | None,
        z: ArrayLike,
        dt: float,
        q: ArrayLike,
        r: ArrayLike,
        *,
        params: Any = None,
        x0: ArrayLike | None = None,
        P0: ArrayLike | None = None,
    ) -> FilterResult:
        """Filter one manoeuvre.

        Args:
            model: the model, or a registered model's name.
            u: (N, n_u) inputs in the model's input units (None for a model without inputs).
            z: (N, m) measurements in the model's measurement units.
            dt: sample time [s], > 0.
            q: (n,) process-noise variances per step, ≥ 0 (diagonal of Q).
            r: (m,) measurement-noise variances, > 0 (diagonal of R).
            params: the model's parameters (its own object, or the (n_p,) vector); None:
                the model's defaults.
            x0: (n,) prior mean at step 0; None: the model's initial-state rule.
            P0: (n, n) or (n,) prior covariance at step 0; None: the model's rule.

        Returns:
            :class:`FilterResult`.

        Raises:
            ValueError: bad input (naming the argument, row and what was expected).
        """
        run = _check_run(model, u, z, dt, q, r, params, x0, P0, batch=False)
        outs = run.outputs().at(0)
        single, _ = self._bound(run.model)
        stop, rep, cause = single(run.head(0), *self._options(run.model), outs)
        return FilterResult(
            outs.x, outs.P_diag, outs.z_hat, outs.innovation, outs.nis, stop >= 0, int(stop),
            int(rep), int(cause), run.model, self.name, outs.log_det_s,
        )  # fmt: skip

    def run_batch(
        self,
        model: StateSpaceModel | str,
        u: ArrayLike | None,
        z: ArrayLike,
        dt: float,
        q: ArrayLike,
        r: ArrayLike,
        *,
        params: Any = None,
        x0: ArrayLike | None = None,
        P0: ArrayLike | None = None,
        lanes: bool = False,
    ) -> FilterBatchResult:
        """Filter one manoeuvre with B noise settings, in parallel over B.

        Args:
            model, u, z, dt, params, x0, P0: as :meth:`run` (shared by all runs; the default
                P0 uses each run's own r).
            q: (B, n) process-noise variances.
            r: (m,) or (B, m) measurement-noise variances.
            lanes: run the B settings across one core's vector lanes where the model
                supplies such a loop for this filter (:class:`~kftune.models.ModelKernels`,
                the single-track UKF's: 3–4× the throughput of one core's sequential runs,
                BENCHMARKS.md "Vectorised batch kernel"), without log det S
                (``log_det_s`` None); else, and by default, in parallel threads.

        Returns:
            :class:`FilterBatchResult`; ``result[b]`` equals ``run(..., q[b], r[b])``.
        """
        run = _check_run(model, u, z, dt, q, r, params, x0, P0, batch=True)
        outs = run.outputs()
        n_sets = run.q.shape[0]
        stop = np.empty(n_sets, dtype=np.int64)
        rep = np.empty(n_sets, dtype=np.int64)
        cause = np.empty(n_sets, dtype=np.int64)
        single, batch = self._bound(run.model)
        vector = self._lanes(run.model) if lanes and n_sets > 1 else None
        opts = self._options(run.model)
        if vector is not None:  # one core, the sets across its vector lanes
            vector(run.head(None), *opts, outs, stop, rep, cause)
        elif n_sets == 1:  # no thread start-up for a single set
            stop[0], rep[0], cause[0] = single(run.head(0), *opts, outs.at(0))
        else:
            # one set per chunk, handed out dynamically: a thread whose core is busy with
            # another process then does fewer sets instead of holding up a static half
            previous = numba.set_parallel_chunksize(1)
            try:
                batch(run.head(None), *opts, outs, stop, rep, cause)
            finally:
                numba.set_parallel_chunksize(previous)
        return FilterBatchResult(
            outs.x, outs.P_diag, outs.z_hat, outs.innovation, outs.nis, stop >= 0, stop, rep,
            cause, run.model, self.name, None if vector is not None else outs.log_det_s,
        )  # fmt: skip

    def _lanes(self, model: StateSpaceModel) -> Any | None:
        """The model's vector-lane loop for this filter, or None (the default: none)."""
        return None


@dataclass(frozen=True)
class UKF(ModelFilter):
    """Unscented Kalman filter with Merwe scaled sigma points (additive noise).

    Attributes:
        settings: sigma-point parameters α, β, κ (:class:`UKFSettings`).
    """

    settings: UKFSettings = field(default_factory=UKFSettings)
    name: ClassVar[str] = "ukf"

    def __post_init__(self) -> None:
        if not isinstance(self.settings, UKFSettings):
            raise ValueError(f"settings must be a UKFSettings, got {type(self.settings).__name__}")

    def _options(self, model: StateSpaceModel) -> tuple[Any, ...]:
        n = model.n_states
        wm, wc = merwe_weights(n, self.settings)
        c = math.sqrt(n + self.settings.lam(n))
        return (SigmaWeights(float(wm[0]), float(wc[0]), float(wm[1]), c),)

    def _bound(self, model: StateSpaceModel) -> tuple[Any, Any]:
        own = model.own_ukf_kernels()
        if own is not None:  # the model's own loops (ModelKernels)
            return own.single, own.batch
        return _bound_ukf(model)

    def _lanes(self, model: StateSpaceModel) -> Any | None:
        own = model.own_ukf_kernels()
        return None if own is None else own.lanes


@dataclass(frozen=True)
class EKF(ModelFilter):
    """Extended Kalman filter: the model's Jacobians, or central finite differences.

    Attributes:
        numerical_jacobians: use finite differences even where the model gives Jacobians.
    """

    numerical_jacobians: bool = False
    name: ClassVar[str] = "ekf"

    def _options(self, model: StateSpaceModel) -> tuple[Any, ...]:
        return ()

    def _bound(self, model: StateSpaceModel) -> tuple[Any, Any]:
        return _bound_ekf(model, self.numerical_jacobians)


# --------------------------------------------------------------------------------------
# Kernels bound to a model's functions
# --------------------------------------------------------------------------------------

# The kernels take the model's functions as arguments. Passing a compiled function from
# Python costs numba some 10 µs of typing per argument and call, and a kernel that receives
# one cannot be cached on disk; the generated module of each model (filters._compiled)
# holds the functions (and the size tokens) as constants instead, so that a run passes
# arrays and numbers only, and a second process loads its kernels from the cache.


def _bound_ukf(model: StateSpaceModel) -> tuple[Any, Any]:
    module = kernel_module(model)
    return module.ukf_single, module.ukf_batch


def _bound_ekf(model: StateSpaceModel, numerical: bool) -> tuple[Any, Any]:
    module = kernel_module(model)
    tag = "fd" if numerical else "given"
    return getattr(module, f"ekf_single_{tag}"), getattr(module, f"ekf_batch_{tag}")


_FILTERS: dict[str, type[ModelFilter]] = {"ukf": UKF, "ekf": EKF}


def filter_names() -> list[str]:
    """Names of the filters, for a configuration file or the command line."""
    return sorted(_FILTERS)


def get_filter(name: str, **options: Any) -> ModelFilter:
    """The filter called ``name`` with its options (e.g. ``settings=UKFSettings(...)``).

    Raises:
        ValueError: unknown name or option.
    """
    if name not in _FILTERS:
        raise ValueError(f"unknown filter {name!r}; filters: {', '.join(filter_names())}")
    try:
        return _FILTERS[name](**options)
    except TypeError as exc:
        raise ValueError(f"filter {name!r}: {exc}") from None
