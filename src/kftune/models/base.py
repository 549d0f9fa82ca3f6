"""The state-space model type: what a filter needs to know about a system, and nothing else.

A model is discrete-time with additive Gaussian noise (Simon, *Optimal State Estimation*,
2006, Ch. 13.1 and 14.2; Särkkä, *Bayesian Filtering and Smoothing*, 2013, Ch. 5.1):

    x_k = f(x_{k−1}, u_{k−1}, p, dt) + w_{k−1},   w ~ N(0, Q)
    z_k = h(x_k, u_k, p) + v_k,                   v ~ N(0, R)

with x the (n,) state, u the (n_u,) input (held over the step, zero-order hold), z the
(m,) measurement and p a float64 parameter vector. f and h are numba-compiled (``@njit``)
functions that write their result into a preallocated output array, so a filter step
allocates nothing:

    f(x: (n,), u: (n_w,), p: (n_p,), dt: float, out: (n,)) -> None
    h(x: (n,), u: (n_w,), p: (n_p,), out: (m,)) -> None

``u`` here is the *prepared* input row. Most models see the raw input row (n_w = n_u). A
model whose f and h share work that depends on the input only (the single-track model's
tan δ, cos δ and axle loads) declares a compiled ``prepare(u_raw: (n_u,), p, out: (n_w,))``;
the filters then compute every sample's prepared row once per run, instead of once per
sigma point. By convention the prepared row starts with the raw inputs.

Optional compiled hooks:

* Jacobians ``F(x, u, p, dt, out: (n, n))`` = ∂f/∂x and ``H(x, u, p, out: (m, n))`` = ∂h/∂x
  (the EKF's linearisation, Simon 2006 Ch. 13.2). When a model gives none, the EKF uses
  central finite differences of f and h (:mod:`kftune.models.jacobians`).
* ``check(x: (n,), z: (m,), u: (n_w,), p, held: (n_held,) bool) -> int``: model-specific
  validity of a posterior estimate (a car's forward speed, a sideslip no car can have). It
  returns 0 when the estimate is valid now, or a stop cause (≥ :data:`FIRST_MODEL_STOP`) that
  ends the run at this step; and it sets ``held[j]`` when condition j is violated. A
  condition violated for ``hold_time`` seconds in a row ends the run with cause
  ``held_causes[j]`` at the step where it started. The counting is the filters' business.

Python-level hooks, run before a filter starts: ``initial_state(z0, r, p) -> (x0, P0)``
(the prior at step 0 from the first measurement), ``pack_params(params) -> (n_p,) array``
(a model's own parameter object, checked) and ``validate_data(u, z)`` (refuse data the model
is not meant for, raising ``ValueError`` that names the argument, row and expectation).
"""

from __future__ import annotations

import inspect
import math
import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from numba.core.dispatcher import Dispatcher
from numpy.typing import ArrayLike

from kftune.errors import KftuneError

__all__ = [
    "FIRST_MODEL_STOP",
    "GENERIC_STOP_REASONS",
    "MAX_STATES",
    "STOP_NONE",
    "STOP_NUMERICAL",
    "DataRefused",
    "StateSpaceModel",
    "prepare_inputs",
]

#: Why a run stopped: generic causes. Models number their own causes from FIRST_MODEL_STOP.
STOP_NONE = 0
STOP_NUMERICAL = 1  # covariance not repairable, or a non-finite state, NIS or estimate
FIRST_MODEL_STOP = 2

#: The most states a model may have. Every state gets a process-noise variance of its own
#: in the search, and kftune's tuners are measured up to about ten dimensions (BENCHMARKS.md);
#: the filter's compile time also grows steeply with n, to minutes at a few hundred states
#: (BENCHMARKS.md, "Moved from module docstrings"). A model beyond it is refused when it is
#: made, by name and count.
MAX_STATES = 100

#: The generic stop causes in words.
GENERIC_STOP_REASONS: dict[int, str] = {
    STOP_NONE: "",
    STOP_NUMERICAL: "a covariance that jitter cannot repair, or an estimate that is no longer "
    "finite",
}


class DataRefused(KftuneError, ValueError):
    """What a model's ``validate_data`` raises for data it is not meant for, saying where:
    the array (``"u"`` or ``"z"``), the row (0-based sample) and the column (index into the
    model's input or measurement names), so that the caller can name the manoeuvre's
    channel and row. ``reason`` is the message without the array position, for those
    callers (default: the message).
    """

    def __init__(
        self, message: str, *, array: str, row: int, column: int, reason: str | None = None
    ) -> None:
        super().__init__(message)
        self.array = array
        self.row = row
        self.column = column
        self.reason = message if reason is None else reason

    def channel(self, model: StateSpaceModel) -> str:
        """The name of the refused channel among ``model``'s inputs or measurements."""
        names = model.input_names if self.array == "u" else model.measurement_names
        return names[self.column]


PriorRule = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
#: ``(runs: [(dt, {channel: (N,) array})], p: (n_p,)) -> {parameter: sentence}``.


class ModelKernels(NamedTuple):
    """Compiled UKF loops a model supplies for itself, run by the generic UKF
    (:class:`kftune.filters.UKF`) behind its own interface instead of its generic loops:
    what is special about a model comes from the model. Each takes the records of
    :mod:`kftune.models.kernel_io` and must give the generic loop's result for the model
    (a test of the model's, against the generic UKF and FilterPy).

    Attributes:
        single: ``single(data, w, out) -> (stop_step, n_repairs, cause)``, one run.
        batch: ``batch(data, w, out, stop, rep, cause)``, B runs in parallel threads
            (data's q, r, x_init, P_init and the buffers with a leading axis B; stop, rep,
            cause (B,) int64).
        lanes: as ``batch`` on one core, the B runs across its vector lanes, or None;
            it may leave ``out.log_det_s`` unwritten (the result then has none: three logs
            per set and step made the single-track lanes 11–14 % slower, BENCHMARKS.md).
        implements: the model's hooks (f, h, check) the loops are written for: a model
            whose hooks are others (a copy of the model with another h, say) runs the
            generic loops (:meth:`StateSpaceModel.own_ukf_kernels`).
    """

    single: Callable[..., tuple[int, int, int]]
    batch: Callable[..., None]
    lanes: Callable[..., None] | None
    implements: tuple[Dispatcher | None, ...]


ParamHints = Callable[
    [Sequence[tuple[float, Mapping[str, np.ndarray]]], np.ndarray], Mapping[str, str]
]

#: The arguments of each compiled hook, in order (module docstring).
HOOK_ARGUMENTS: dict[str, tuple[str, ...]] = {
    "f": ("x", "u", "p", "dt", "out"),
    "h": ("x", "u", "p", "out"),
    "prepare": ("u_raw", "p", "out"),
    "check": ("x", "z", "u", "p", "held"),
    "F": ("x", "u", "p", "dt", "out"),
    "H": ("x", "u", "p", "out"),
}
#: What :meth:`StateSpaceModel.probe` fills an output buffer with, to see what a hook left
#: unwritten or wrote beyond its end.
_UNWRITTEN = -1.2345678901234567e300


def _names(model: str, what: str, names: tuple[str, ...], units: tuple[str, ...]) -> None:
    if not all(isinstance(s, str) and s for s in names):
        raise ValueError(f"model {model!r}: {what} names must be non-empty strings: {names}")
    if len(set(names)) != len(names):
        raise ValueError(f"model {model!r}: {what} names must be unique: {names}")
    if len(units) != len(names):
        raise ValueError(
            f"model {model!r}: {len(names)} {what} names but {len(units)} units ({units})"
        )


@dataclass(frozen=True, eq=False)
class StateSpaceModel:
    """A discrete-time state-space model with additive noise (module docstring).

    Attributes:
        name: registry key, e.g. ``"single-track"``.
        state_names, state_units: (n,) names and SI units of the states.
        input_names, input_units: (n_u,) of the raw inputs (both may be empty).
        measurement_names, measurement_units: (m,) of the measurements.
        f: compiled process model ``f(x, u, p, dt, out)``.
        h: compiled measurement model ``h(x, u, p, out)``.
        param_names, param_units: (n_p,) of the parameter vector p (may be empty).
        param_defaults: (n_p,) default p.
        initial_state: ``(z0 (m,), r (m,), p (n_p,)) -> (x0 (n,), P0 (n, n))``, the prior at
            step 0 from the first measurement and the measurement variances; None: callers
            must give x0 and P0.
        prepare: compiled ``prepare(u_raw, p, out)`` of the input-only quantities, or None.
        prepared_size: n_w, the length of a prepared row (ignored without ``prepare``).
        check: compiled validity check (module docstring), or None (numerical checks only).
        held_causes: stop cause of each held condition ``check`` reports.
        hold_time: how long [s] a held condition must last to stop the run.
        stop_reasons: the model's stop causes (≥ FIRST_MODEL_STOP) in words.
        F, H: compiled Jacobians ``F(x, u, p, dt, out)``, ``H(x, u, p, out)``, or None
            (finite differences).
        pack_params: the model's parameter object (e.g. a VehicleParams) → checked (n_p,)
            array; None: any finite (n_p,) array.
        validate_data: ``(u (N, n_u), z (N, m)) -> None``, raises ValueError (best a
            :class:`DataRefused`, which says where) for data the model is not meant for;
            None: no model-specific checks.
        needs_vehicle: the parameters p come from the dataset's vehicle (VehicleParams,
            through ``pack_params``): a dataset without one is refused.
        description: one line for listings.
        outputs: derived quantities a cost can score against a reference channel
            ``<name>_ref`` of the data: name → ``g(x (N, n)) -> (N,)`` over the posterior
            states (the single-track models' ``beta`` = atan2(Vy, Vx) [rad]).
        param_ranges: name → (low, high), the plausible range of a parameter in its unit
            (both ends included): a tuning box for it beyond the range is refused. A
            parameter without one may take any finite value.
        param_hints: physical reasons the data may not determine a tuned parameter,
            ``(runs, p) -> {name: sentence}`` over the training data — ``runs`` a sequence
            of (dt [s], {channel: (N,) array}) of the model's input and measurement
            channels, ``p`` (n_p,) the tuned parameters — naming only the parameters the
            data leave unexcited (a friction coefficient on data far from the friction
            limit); None: no such knowledge. Said with a parameter the tuning's profile
            finds not determined (:mod:`kftune.tuning.identify`).
        c_code: the model in C99 for ``kftune export --format c`` — the source text of
            ``kf_f``, ``kf_h`` and the other hooks the model has, written against the
            contract of :mod:`kftune.models.c_contract` — or None: the model cannot be
            exported as a running filter (the export says so and writes nothing).
        ukf_kernels: loads the model's own compiled UKF loops (:class:`ModelKernels`) on
            first use, or None: the UKF runs its generic loops for the model (the EKF
            always does).
    """

    name: str
    state_names: tuple[str, ...]
    state_units: tuple[str, ...]
    input_names: tuple[str, ...]
    input_units: tuple[str, ...]
    measurement_names: tuple[str, ...]
    measurement_units: tuple[str, ...]
    f: Dispatcher
    h: Dispatcher
    param_names: tuple[str, ...] = ()
    param_units: tuple[str, ...] = ()
    param_defaults: tuple[float, ...] = ()
    initial_state: PriorRule | None = None
    prepare: Dispatcher | None = None
    prepared_size: int = 0
    check: Dispatcher | None = None
    held_causes: tuple[int, ...] = ()
    hold_time: float = 0.0
    stop_reasons: Mapping[int, str] = field(default_factory=dict)
    F: Dispatcher | None = None
    H: Dispatcher | None = None
    pack_params: Callable[[Any], np.ndarray] | None = None
    validate_data: Callable[[np.ndarray, np.ndarray], None] | None = None
    description: str = ""
    outputs: Mapping[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)
    needs_vehicle: bool = False
    param_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    param_hints: ParamHints | None = None
    c_code: str | None = None
    ukf_kernels: Callable[[], ModelKernels] | None = None

    def own_ukf_kernels(self) -> ModelKernels | None:
        """The model's own UKF loops (:attr:`ukf_kernels`), where they implement this
        model's f, h and check; None: the generic loops run it."""
        if self.ukf_kernels is None:
            return None
        own = self.ukf_kernels()
        return own if own.implements == (self.f, self.h, self.check) else None

    def __post_init__(self) -> None:
        name = self.name
        if not isinstance(name, str) or not name or name != name.strip():
            raise ValueError(f"model name must be a non-empty string, got {name!r}")
        for attr in ("state", "input", "measurement", "param"):
            names = tuple(getattr(self, f"{attr}_names"))
            units = tuple(getattr(self, f"{attr}_units"))
            if attr == "param" and not units:
                units = ("",) * len(names)
            object.__setattr__(self, f"{attr}_names", names)
            object.__setattr__(self, f"{attr}_units", units)
            _names(name, attr, names, units)
        if not self.state_names or not self.measurement_names:
            raise ValueError(f"model {name!r} needs at least one state and one measurement")
        if len(self.state_names) > MAX_STATES:
            raise ValueError(
                f"model {name!r} has {len(self.state_names)} states; kftune takes at most "
                f"{MAX_STATES} (one process-noise variance per state is searched, and the "
                "filter's compile time grows steeply with the state count)"
            )
        both = set(self.input_names) & set(self.measurement_names)
        if both:
            raise ValueError(
                f"model {name!r}: {sorted(both)} named both as input and as measurement "
                "(each is a data channel and needs its own name)"
            )
        defaults = tuple(float(v) for v in self.param_defaults)
        if len(defaults) != len(self.param_names) or not all(map(math.isfinite, defaults)):
            raise ValueError(
                f"model {name!r}: param_defaults must be {len(self.param_names)} finite numbers "
                f"({self.param_names}), got {self.param_defaults}"
            )
        object.__setattr__(self, "param_defaults", defaults)
        ranges: dict[str, tuple[float, float]] = {}
        for key, rng in dict(self.param_ranges).items():
            if key not in self.param_names:
                raise ValueError(
                    f"model {name!r}: param_ranges names {key!r}, which is not one of its "
                    f"parameters {list(self.param_names)}"
                )
            try:
                low, high = (float(v) for v in rng)
            except (TypeError, ValueError):
                raise ValueError(
                    f"model {name!r}: param_ranges[{key!r}] must be (low, high), got {rng!r}"
                ) from None
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise ValueError(
                    f"model {name!r}: param_ranges[{key!r}] must be finite with low <= high, "
                    f"got {rng!r}"
                )
            ranges[key] = (low, high)
        object.__setattr__(self, "param_ranges", types.MappingProxyType(ranges))
        if self.param_hints is not None and not callable(self.param_hints):
            raise ValueError(
                f"model {name!r}: param_hints must be a function (runs, p) -> {{name: reason}}, "
                f"got {type(self.param_hints).__name__}"
            )
        for hook, args in HOOK_ARGUMENTS.items():
            fn = getattr(self, hook)
            if (fn is not None or hook in ("f", "h")) and not isinstance(fn, Dispatcher):
                raise ValueError(
                    f"model {name!r}: {hook} must be a numba-compiled function (@njit), "
                    f"got {type(fn).__name__}"
                )
            if fn is not None and _arity(fn) not in (None, len(args)):
                raise ValueError(
                    f"model {name!r}: {hook} must take {len(args)} arguments "
                    f"{hook}({', '.join(args)}), it takes {_arity(fn)}"
                )
        if self.c_code is not None and not (isinstance(self.c_code, str) and self.c_code.strip()):
            raise ValueError(f"model {name!r}: c_code must be C source text or None")
        if self.prepare is not None and not (
            isinstance(self.prepared_size, int) and self.prepared_size >= 0
        ):
            raise ValueError(f"model {name!r}: prepared_size must be an integer >= 0")
        held = tuple(int(c) for c in self.held_causes)
        object.__setattr__(self, "held_causes", held)
        outputs = dict(self.outputs)
        for key, fn in outputs.items():
            if not (isinstance(key, str) and key.isidentifier() and callable(fn)):
                raise ValueError(
                    f"model {name!r}: outputs must map identifiers to functions of the states, "
                    f"got {key!r}: {type(fn).__name__}"
                )
            if key in self.measurement_names:
                raise ValueError(f"model {name!r}: output {key!r} is also a measurement name")
        object.__setattr__(self, "outputs", types.MappingProxyType(outputs))
        reasons = types.MappingProxyType(dict(self.stop_reasons))
        object.__setattr__(self, "stop_reasons", reasons)
        for code in (*held, *reasons):
            if code < FIRST_MODEL_STOP:
                raise ValueError(
                    f"model {name!r}: stop causes must be >= {FIRST_MODEL_STOP} "
                    f"(0 and 1 are the filters' own), got {code}"
                )
        if held and (self.check is None or not self.hold_time > 0):
            raise ValueError(f"model {name!r}: held_causes need a check and a hold_time > 0")

    # ---------------------------------------------------------------- sizes and names ----

    @property
    def n_states(self) -> int:
        """n, the state dimension."""
        return len(self.state_names)

    @property
    def n_inputs(self) -> int:
        """n_u, the raw input dimension."""
        return len(self.input_names)

    @property
    def n_measurements(self) -> int:
        """m, the measurement dimension."""
        return len(self.measurement_names)

    @property
    def n_params(self) -> int:
        """n_p, the length of the parameter vector."""
        return len(self.param_names)

    def stop_reason(self, cause: int) -> str:
        """A stop cause in words ("" for STOP_NONE)."""
        if cause in GENERIC_STOP_REASONS:
            return GENERIC_STOP_REASONS[cause]
        return self.stop_reasons.get(cause, f"stop cause {cause} of model {self.name!r}")

    # ---------------------------------------------------------------- parameters and data --

    def default_params(self) -> np.ndarray:
        """(n_p,) float64 copy of the default parameter vector."""
        return np.array(self.param_defaults, dtype=np.float64)

    def params_vector(self, params: Any = None) -> np.ndarray:
        """The checked (n_p,) float64 parameter vector of ``params`` (None: the defaults).

        Raises:
            ValueError: wrong shape or non-finite entries (naming the entry).
        """
        if params is None:
            return self.default_params()
        if self.pack_params is not None:
            return np.ascontiguousarray(self.pack_params(params), dtype=np.float64)
        try:
            arr = np.array(params, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"params of model {self.name!r} must be numeric: {exc}") from None
        if arr.shape != (self.n_params,):
            raise ValueError(
                f"params of model {self.name!r} must have shape ({self.n_params},) "
                f"[{', '.join(self.param_names)}], got shape {arr.shape}"
            )
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"params[{i}] ({self.param_names[i]}) must be finite, got {arr[i]}")
        return arr

    def probe(
        self,
        u: np.ndarray | None,
        z: np.ndarray,
        r: np.ndarray,
        p: np.ndarray,
        dt: float,
        *,
        jacobians: bool = True,
    ) -> None:
        """Run every hook once on the first sample of some data, before a filter relies on
        them: the prior rule (from z[0] and r), ``prepare``, ``f``, ``h``, the Jacobians
        and the outputs, each on the prior mean. A hook that raises, returns or writes the
        wrong size (leaves an entry of ``out`` unwritten, or writes beyond its end) or a
        non-finite value is named. Without a prior rule the state is zero and only sizes
        are checked.

        Args:
            u: (N, n_u) raw inputs or None; z: (N, m) measurements; r: (m,) measurement
                variances; p: (n_p,) parameters; dt: [s] the sample time.
            jacobians: probe F and H too (False for a filter that never calls them, the
                UKF: probing compiles them, seconds for the single-track model's).

        Raises:
            ValueError: naming the hook, what it did and what was expected.
        """
        n, m = self.n_states, self.n_measurements
        u0 = np.zeros((1, self.n_inputs)) if u is None else np.ascontiguousarray(u[:1], float)
        z0 = np.ascontiguousarray(z[0], dtype=np.float64)
        p = np.ascontiguousarray(p, dtype=np.float64)
        rule = self.initial_state
        finite = rule is not None
        if rule is not None:
            prior = _call("initial_state(z0, r, p)", rule, z0, np.asarray(r), p)
            if not (isinstance(prior, tuple) and len(prior) == 2):
                raise ValueError("initial_state(z0, r, p) must return (x0, P0)")
            x0 = np.asarray(prior[0], dtype=np.float64)
            P0 = np.asarray(prior[1], dtype=np.float64)
            for what, arr, shape in (("x0", x0, (n,)), ("P0", P0, (n, n))):
                if arr.shape != shape:
                    raise ValueError(
                        f"initial_state(z0, r, p) returned {what} of shape {arr.shape}; "
                        f"expected {shape} (states {', '.join(self.state_names)})"
                    )
                if not np.all(np.isfinite(arr)):
                    raise ValueError(f"initial_state(z0, r, p) returned a non-finite {what}")
        else:
            x0 = np.zeros(n)
        w0 = u0[0]
        if self.prepare is not None:
            w0 = _filled("prepare(u_raw, p, out)", self.prepare, (u0[0], p), self.prepared_size,
                         None, finite)  # fmt: skip
        _filled("f(x, u, p, dt, out)", self.f, (x0, w0, p, float(dt)), n, self.state_names, finite)
        _filled("h(x, u, p, out)", self.h, (x0, w0, p), m, self.measurement_names, finite)
        if self.F is not None and jacobians:
            _filled("F(x, u, p, dt, out)", self.F, (x0, w0, p, float(dt)), (n, n), None, finite)
        if self.H is not None and jacobians:
            _filled("H(x, u, p, out)", self.H, (x0, w0, p), (m, n), None, finite)
        for key, g in self.outputs.items():
            value = np.asarray(_call(f"output {key!r}(x)", g, x0[None, :]), dtype=np.float64)
            if value.shape != (1,):
                raise ValueError(
                    f"output {key!r}(x) returned shape {value.shape} for x of shape (1, {n}); "
                    "expected (1,): one value per row of states"
                )
            if finite and not np.isfinite(value[0]):
                raise ValueError(f"output {key!r}(x) is not finite at the prior mean x0")

    def predict_open_loop(
        self,
        x0: np.ndarray,
        w: np.ndarray,
        p: np.ndarray,
        dt: float,
        starts: np.ndarray,
        horizon: int,
    ) -> np.ndarray:
        """Measurement predictions h steps ahead without measurements: from each start state
        x0[i] at sample starts[i], ``horizon`` steps of f with the inputs held over each step,
        then h with the input at the end (x_{k+j+1} = f(x_{k+j}, w_{k+j}), ẑ = h(x_{k+h},
        w_{k+h}); the model's own equations, module docstring). A state that leaves the
        model's domain gives non-finite predictions, not an error.

        Args:
            x0: (K, n) start states. w: (N, n_w) prepared input rows
                (:meth:`prepared_inputs`; (N, 0) for a model without inputs). p: (n_p,)
                parameters. dt: [s] the sample time. starts: (K,) start samples with
                starts + horizon < N. horizon: h ≥ 1 steps.

        Returns:
            (K, m) predicted measurements ẑ_{starts+h}.
        """
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        w = np.ascontiguousarray(w, dtype=np.float64)
        starts = np.ascontiguousarray(starts, dtype=np.int64)
        out = np.empty((starts.shape[0], self.n_measurements))
        from kftune.models._generated import generated_module  # it imports this module

        run = generated_module(self, "Open-loop predictions", _OPEN_LOOP).open_loop
        run(x0, w, np.asarray(p, np.float64), float(dt), starts, int(horizon), out)
        return out

    def prepared_inputs(self, u: ArrayLike, p: np.ndarray) -> np.ndarray:
        """(N, n_w) prepared input rows of (N, n_u) raw inputs ``u`` (u itself without prepare)."""
        u_arr = np.ascontiguousarray(u, dtype=np.float64)
        if self.prepare is None:
            return u_arr
        from kftune.models._generated import generated_module  # it imports this module

        out = np.empty((u_arr.shape[0], self.prepared_size))
        generated_module(self, "Prepared inputs", _PREPARE_ROWS).prepare_rows(u_arr, p, out)
        return out


def _arity(fn: Dispatcher) -> int | None:
    """How many arguments a compiled function takes (None: not known)."""
    try:
        return len(inspect.signature(fn.py_func).parameters)
    except (AttributeError, TypeError, ValueError):
        return None


def _call(what: str, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``; any failure as a ValueError naming ``what`` (first line only)."""
    try:
        return fn(*args)
    except Exception as exc:  # the user's code: any failure is reported
        lines = str(exc).strip().splitlines()
        first = lines[0][:200] if lines else ""
        raise ValueError(
            f"{what} failed on the first sample: {type(exc).__name__}: {first}"
        ) from None


def _filled(
    what: str,
    fn: Callable[..., Any],
    args: tuple[Any, ...],
    shape: int | tuple[int, int],
    names: tuple[str, ...] | None,
    finite: bool,
) -> np.ndarray:
    """Call a hook that writes ``out`` of ``shape`` and check what it wrote: every entry,
    nothing beyond the end (the buffer continues past ``out``: compiled code does not
    check bounds), and finite values when ``finite``."""
    size = int(np.prod(shape))
    buf = np.full(size + 8, _UNWRITTEN)
    out = buf[:size].reshape(shape)
    _call(what, fn, *args, out)
    if np.any(buf[size:] != _UNWRITTEN):
        raise ValueError(
            f"{what} wrote beyond the end of out (shape {out.shape}): index it by the "
            "model's "
            + ("names" if names else "sizes")
            + (f" ({', '.join(names)})" if names else "")
        )
    flat = buf[:size]
    for kind, bad in (("left unwritten", flat == _UNWRITTEN), ("wrote a non-finite value to",
                      ~np.isfinite(flat) if finite else np.zeros(size, bool))):  # fmt: skip
        if bad.any():
            i = int(np.argmax(bad))
            at = f"out[{i}]" + (f" ({names[i]})" if names else "")
            raise ValueError(f"{what} {kind} {at} at the prior mean x0")
    return out


#: The loop of a model's ``prepare`` over input rows (:func:`prepare_inputs`), in the
#: model's generated module (:mod:`kftune.models._generated`), cached across processes.
_PREPARE_ROWS = """
from kftune.models.base import prepare_inputs


@numba.njit(error_model="numpy", cache=True)
def prepare_rows(u, p, out):
    prepare_inputs(prepare, u, p, out)
"""


#: :meth:`StateSpaceModel.predict_open_loop`'s loop, in the model's generated module.
_OPEN_LOOP = """
import numpy as np


@numba.njit(error_model="numpy", cache=True)
def open_loop(x0, w, p, dt, starts, horizon, out):
    x = np.empty(x0.shape[1])
    nxt = np.empty(x0.shape[1])
    for i in range(starts.shape[0]):
        x[:] = x0[i]
        k = starts[i]
        for j in range(horizon):
            f(x, w[k + j], p, dt, nxt)
            x[:] = nxt
        h(x, w[k + horizon], p, out[i])
"""


@njit(error_model="numpy", inline="always")
def prepare_inputs(prepare: Dispatcher, u: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """out[k] = prepare(u[k], p) for every row: (N, n_u) → (N, n_w)."""
    for k in range(u.shape[0]):
        prepare(u[k], p, out[k])
