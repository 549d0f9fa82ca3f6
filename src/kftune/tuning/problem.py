"""The black-box tuning problem: a parameter vector → UKF runs over manoeuvres → a cost.

    x (natural units) ──NoiseParameterization──▶ (Q diag, R diag, sigma-point settings)
                       ──the filter per manoeuvre──▶ estimates
                       ──cost (paper Eq. 14–15, NIS or innovation likelihood)──▶ J

The optimiser sees only ``problem(x) -> J`` and ``problem.space``; a diverged filter (also one
that ran away to an impossible sideslip or speed, see :mod:`kftune.models._runaway`) raises
:class:`FilterDivergedError`, which :func:`kftune.minimize` records as a failed evaluation.

The parts it composes, one module each: what is searched and how a point maps onto the
filter (:mod:`kftune.tuning.parameterization`), one filter run and what it gives
(:mod:`kftune.tuning.runs`), what a run contributes to the cost
(:mod:`kftune.tuning.scoring`) and the worker processes that score manoeuvres in parallel
(:mod:`kftune.tuning.pool`).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import multiprocessing
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from kftune.data.manoeuvre import Manoeuvre
from kftune.errors import ConfigError, DataError, FilterDivergedError
from kftune.filters import FilterResult, UKFSettings
from kftune.models import DataRefused, StateSpaceModel
from kftune.models.user import model_file_sha256
from kftune.processes import sigint_blocked
from kftune.space import Space
from kftune.tuning.cost import (
    SCORING_RULES,
    CostSpec,
    innovation_nll,
    multistep_cost,
    nis_cost,
    scoring_rule_cost,
    weighted_cost,
)
from kftune.tuning.kpi import sideslip_kpis
from kftune.tuning.parameterization import (
    SIDESLIP_MEASUREMENTS,
    NoiseParameterization,
    check_model_params,
)
from kftune.tuning.pool import balanced_chunks, init_worker, score_chunk
from kftune.tuning.runs import (
    channel_estimate,
    check_cost_channels,
    filter_spec,
    first_scored,
    model_output,
    output_names,
)
from kftune.tuning.scoring import (
    Evaluation,
    ManoeuvreScore,
    msp_channels,
    score_manoeuvre,
    score_result,
)
from kftune.vehicle.params import VehicleParams


class TuningProblem:
    """Cost of a UKF tuning over a set of manoeuvres.

    Args:
        manoeuvres: the manoeuvres the cost is pooled over (the training set).
        vehicle: model parameters of a vehicle model's filter; None for a model that is not
            a vehicle's (the single-track models refuse to run without one).
        r0: (m,) measurement-noise variances of the model's measurements (single-track:
            [Vx, ay, r]; from sensor statistics, :func:`default_r0`; paper: R is not
            optimised).
        cost: which cost (default: the paper's weighted NRMSE, W = (5, 1, 1)).
        parameterization: what is tuned (default: the three Q entries).
        workers: processes that run the manoeuvres in parallel; 1 (default) runs them in
            this process. Use as a context manager (or call :meth:`close`) when > 1.
        model: the state-space model the filter runs: a registered name (default
            ``"single-track"``, the paper's), a model file (``"my_model.py"``, see
            :mod:`kftune.models.user`) or a :class:`~kftune.models.StateSpaceModel`. Its
            inputs and measurements are read from the manoeuvres' channels of the same
            names; a vehicle model takes its parameters from ``vehicle``.
        filter: ``"ukf"`` (default) or ``"ekf"``.
        burn_in: [s] initial part of every manoeuvre left out of the cost (and of
            :func:`assess`'s KPIs), while the filter converges from its default prior; 0
            (default, the paper) scores every sample. Useful for segments cut out of a
            longer recording, which start mid-manoeuvre with the filter's Vy = 0.

    Raises:
        DataError: a manoeuvre the filter cannot run: it lacks a channel the model or the
            cost needs (:class:`~kftune.errors.MissingChannelError`, e.g. ``beta_ref`` for
            the paper's cost), the model refuses its data (the single-track models: Vx ≤ 0),
            or it has fewer than 2 samples after the burn-in; the message names the
            manoeuvre, and the channel and sample where there is one.
        ConfigError: a model that needs a vehicle without one, an unknown cost channel, a
            model whose hooks fail on the first sample (:meth:`StateSpaceModel.probe`).

    ``problem(x)`` returns J for a point of ``problem.space`` (natural units).
    """

    def __init__(
        self,
        manoeuvres: Sequence[Manoeuvre],
        vehicle: VehicleParams | None,
        r0: Sequence[float] | np.ndarray,
        *,
        cost: CostSpec | None = None,
        parameterization: NoiseParameterization | None = None,
        workers: int = 1,
        burn_in: float = 0.0,
        model: str | StateSpaceModel = "single-track",
        filter: str = "ukf",
    ) -> None:
        self.manoeuvres = tuple(manoeuvres)
        self._fs = filter_spec(model, filter, vehicle)
        mod = self._fs.model
        if not self.manoeuvres:
            raise ConfigError("the tuning problem needs at least one manoeuvre")
        if not (
            isinstance(burn_in, (int, float))
            and not isinstance(burn_in, bool)
            and math.isfinite(burn_in)
            and burn_in >= 0
        ):
            raise ConfigError(f"burn_in must be a number of seconds >= 0, got {burn_in!r}")
        self.burn_in = float(burn_in)
        self.cost_spec = cost or CostSpec()
        check_cost_channels(self.cost_spec, mod)
        if self.cost_spec.kind == "msp" and not msp_channels(self.cost_spec, mod):
            raise ConfigError(
                "the multi-step prediction cost (msp) needs a positive weight on a measured "
                f"channel of model {mod.name!r} ({', '.join(mod.measurement_names)})"
            )
        for m in self.manoeuvres:
            self._check_channels(m)
            if m.n - first_scored(m, self.burn_in) < 2:
                raise ConfigError(
                    f"manoeuvre {m.name!r} ({m.duration:.2f} s) is shorter than the burn-in "
                    f"of {self.burn_in:g} s"
                )
        self.vehicle = vehicle
        self.r0 = np.asarray(r0, dtype=float)
        k = mod.n_measurements
        if self.r0.shape != (k,) or not np.all(np.isfinite(self.r0)) or np.any(self.r0 <= 0):
            raise ConfigError(
                f"r0 must be {k} positive finite variances {list(mod.measurement_names)}, "
                f"got {r0!r}"
            )
        self.parameterization = parameterization or NoiseParameterization(
            states=mod.state_names, measurements=mod.measurement_names
        )
        par = self.parameterization
        if par.states != mod.state_names or par.measurements != mod.measurement_names:
            raise ConfigError(
                f"the tuned parameters are for states {list(par.states)} and measurements "
                f"{list(par.measurements)}, but model {mod.name!r} has "
                f"{list(mod.state_names)} and {list(mod.measurement_names)}"
            )
        check_model_params(par, mod)
        recorded = dict(zip(mod.param_names, self._fs.params.tolist()))
        try:
            self.parameterization = par = par.with_start(recorded)
        except ValueError as exc:
            raise ConfigError(f"tune_model: {exc}") from None
        self._model_index = [mod.param_names.index(n) for n in par.model_names]
        #: c of :meth:`FilterSpec.run`: the runs use c·Q, c·R and c·P0 (1: as tuned).
        self.cov_scale = 1.0
        # before a budget is spent on the model; with the sigma points the tuning starts from
        self._fs.probe(self.manoeuvres, self.r0, settings=par.default_settings)
        if not (isinstance(workers, int) and workers >= 1):
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        self.workers = min(workers, len(self.manoeuvres))
        self._pool: ProcessPoolExecutor | None = None
        self._chunks = balanced_chunks([m.n for m in self.manoeuvres], self.workers)
        self._evaluated = False  # see compile_note

    @property
    def space(self) -> Space:
        """The search space of the optimiser."""
        return self.parameterization.space

    @property
    def model(self) -> StateSpaceModel:
        """The model the filter runs."""
        return self._fs.model

    @property
    def filter(self) -> str:
        """``"ukf"`` or ``"ekf"``."""
        return self._fs.filter

    @property
    def model_spec(self) -> str:
        """How the model was named (a registered name or a model file)."""
        return self._fs.spec

    def _outputs(self) -> tuple[str, ...]:
        return output_names(self._fs.model)

    def _check_channels(self, m: Manoeuvre) -> None:
        """Refuse a manoeuvre without the channels the model and the cost need, or data the
        model refuses (naming the manoeuvre, and the channel and row where it can)."""
        mod = self._fs.model
        who = f"model {mod.name!r}"
        m.require(mod.input_names, who, "input channel")
        m.require(mod.measurement_names, who, "measurement channel")
        if self.cost_spec.kind == "nrmse":
            refs = [f"{c}_ref" for c in self.cost_spec.channels if c not in mod.measurement_names]
            m.require(
                refs,
                "the nrmse cost (without a reference sensor, tune with --cost msp, the "
                "multi-step prediction of the measurements — README 'Tuning without a "
                "reference sensor' —, or weigh only measured channels: "
                f"--weights {','.join(f'{c}=1' for c in mod.measurement_names)})",
                "a reference channel",
            )
        elif self.cost_spec.kind in SCORING_RULES:
            m.require(
                [f"{c}_ref" for c in self.cost_spec.channels],
                f"the {self.cost_spec.kind} cost (it scores the reference under the filter's "
                "Gaussian; without a reference sensor use the nis, pem or msp cost)",
                "a reference channel",
            )
        if mod.validate_data is not None:
            u, z = self._fs.inputs(m)
            try:
                mod.validate_data(np.zeros((m.n, 0)) if u is None else u, z)
            except DataRefused as exc:
                raise DataError(
                    f"manoeuvre {m.name!r}, channel {exc.channel(mod)!r}, sample {exc.row} "
                    f"(t = {float(m.t[exc.row]):.4g} s): {who} refuses these data: {exc.reason}"
                ) from None
            except ValueError as exc:
                raise DataError(f"manoeuvre {m.name!r}: {who} refuses these data: {exc}") from None

    def decode(self, x: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray, UKFSettings]:
        """(q, r, settings) of a point."""
        return self.parameterization.decode(x, self.r0)

    def vehicle_at(self, x: Sequence[float] | np.ndarray) -> VehicleParams | None:
        """The vehicle of a point: the recorded one with the point's tuned model parameters
        (None for a model without a vehicle; unchanged for a model whose parameters do not
        come from the vehicle, which runs :meth:`params_at`).

        Raises:
            ValueError: a value the vehicle refuses (outside its plausible range).
        """
        values = self.parameterization.model_values(x)
        if self.vehicle is None or not values or not self._fs.model.needs_vehicle:
            return self.vehicle  # a model not of the vehicle: its parameters by params_at
        return self.vehicle.replace(**values)

    def params_at(self, x: Sequence[float] | np.ndarray) -> np.ndarray:
        """(n_p,) the model's parameter vector at a point: the recorded one with the point's
        tuned model parameters in their places (``param_names``)."""
        p = self._fs.params.copy()
        values = self.parameterization.model_values(x)
        for i, name in zip(self._model_index, self.parameterization.model_names):
            p[i] = values[name]
        return p

    def _point(
        self, x: Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, UKFSettings, np.ndarray | None]:
        """(q, r, settings, params) of a point; params None when no model parameter is
        tuned (the filter runs the recorded model)."""
        q, r, settings = self.decode(x)
        if not self.parameterization.model_names:
            return q, r, settings, None
        return q, r, settings, self.params_at(x)

    def __call__(self, x: Sequence[float] | np.ndarray) -> float:
        return self.evaluate(x).cost

    def compile_note(self) -> str | None:
        """What to say before the first evaluation: that it compiles the filter for the
        model, which takes seconds (a large model, minutes) that look like a hang and are
        not the time an evaluation takes; None once this problem has evaluated a point."""
        if self._evaluated:
            return None
        what = f"compiling the filter for model {self.model.name!r} ({self.filter})"
        return f"{what}, or loading it from an earlier run's cache…"

    def evaluate(self, x: Sequence[float] | np.ndarray) -> Evaluation:
        """Run the filter on every manoeuvre and compute the cost.

        Raises:
            FilterDivergedError: the filter diverged on a manoeuvre.
        """
        q, r, settings, params = self._point(x)
        spec, c = self.cost_spec, self.cov_scale
        self._evaluated = True  # the filter compiles now, also for a point that diverges
        if self.workers == 1:
            scores = [
                score_manoeuvre(m, self._fs, q, r, settings, spec, self.burn_in, params, c)
                for m in self.manoeuvres
            ]
        else:
            pool = self._get_pool()
            with sigint_blocked():  # workers started by a submit inherit it (see there)
                futures = [
                    pool.submit(score_chunk, chunk, q, r, settings, spec, self.burn_in, params, c)
                    for chunk in self._chunks
                ]
            by_index: dict[int, ManoeuvreScore] = {}
            for chunk, fut in zip(self._chunks, futures):
                by_index.update(zip(chunk, fut.result()))
            scores = [by_index[i] for i in range(len(self.manoeuvres))]
        return self._pool_scores(scores)

    def score_manoeuvres(
        self, x: Sequence[float] | np.ndarray, indices: Sequence[int]
    ) -> list[ManoeuvreScore]:
        """The scores of a point on the manoeuvres ``indices`` (a share of :meth:`evaluate`
        for a distributed engine; pooled by :meth:`_pool_scores` in manoeuvre order, they
        give :meth:`evaluate`'s cost bit for bit)."""
        q, r, settings, params = self._point(x)
        fs, spec, c = self._fs, self.cost_spec, self.cov_scale
        return [
            score_manoeuvre(self.manoeuvres[i], fs, q, r, settings, spec, self.burn_in, params, c)
            for i in indices
        ]

    def manoeuvre_chunks(self, k: int) -> list[list[int]]:
        """The manoeuvre indices in at most k groups of similar total length."""
        return balanced_chunks([m.n for m in self.manoeuvres], max(1, k))

    def _pool_scores(self, scores: Sequence[ManoeuvreScore]) -> Evaluation:
        """The cost J (paper Eq. 14–15, a scoring rule's, or a reference-free one) from
        every manoeuvre's score."""
        spec = self.cost_spec
        channels = spec.channels if spec.kind == "nrmse" else ()
        n_total = sum(s.n for s in scores)
        mean_nis = sum(s.nis_sum for s in scores) / n_total
        if spec.kind == "nis":
            cost = nis_cost([np.array([mean_nis])], n_z=self._fs.model.n_measurements)
            pooled: dict[str, float] = {}
        elif spec.kind == "msp":
            cost = multistep_cost([s.msp_sq for s in scores], [s.msp_n for s in scores])
            pooled = {}
        elif spec.kind == "pem":
            cost = innovation_nll(
                [np.array([sum(s.log_det_s_sum for s in scores) / n_total])],
                [np.array([mean_nis])],
                n_z=self._fs.model.n_measurements,
            )
            pooled = {}
        elif spec.kind in SCORING_RULES:
            cost, pooled = scoring_rule_cost(
                {c: [s.score_sum[c] for s in scores] for c in spec.channels},
                [s.n for s in scores],
                spec.weights,
                {c: [s.scale[c] for s in scores] for c in spec.channels}
                if spec.kind == "crps"
                else None,
            )
        else:
            cost, pooled = weighted_cost(
                {c: [s.nrmse[c] for s in scores] for c in channels},
                [s.n for s in scores],
                spec.weights,
                {c: [s.scale[c] for s in scores] for c in channels}
                if spec.normalise == "dataset"
                else None,
            )
        return Evaluation(cost=cost, pooled=pooled, mean_nis=mean_nis, scores=tuple(scores))

    def evaluate_batch(
        self, X: Sequence[Sequence[float]] | np.ndarray
    ) -> list[Evaluation | FilterDivergedError]:
        """Evaluate B points; a point whose filter diverged gets its error, not a raise.

        Where the model supplies vector lanes for its filter (the single-track UKF,
        :attr:`FilterSpec.has_lanes`) and in this process (``workers == 1``) every manoeuvre
        runs all points that share sigma-point settings and tuned model parameters in one
        call of the lanes (``UKF.run_batch(..., lanes=True)``, the sets across the CPU's
        vector lanes, one parameter vector for all); otherwise the points
        are evaluated one after another (a point whose model parameters no other point
        shares is a group of one, which runs the sequential kernel). Either way each result
        equals :meth:`evaluate`'s for that point exactly.

        Args:
            X: (B, d) points of ``self.space`` (natural units).

        Returns:
            B entries in the order of X: an :class:`Evaluation`, or the
            :class:`FilterDivergedError` that :meth:`evaluate` would have raised.

        Raises:
            DataError: a channel that cannot be scored (as :meth:`evaluate`).
        """
        points = [np.asarray(x, dtype=float) for x in X]
        # the vector lanes compute neither log det S (pem) nor predictions (msp)
        vector = self.cost_spec.kind in ("nrmse", "nis", *SCORING_RULES) and self.cov_scale == 1.0
        if not (vector and self._fs.has_lanes and self.workers == 1 and len(points) > 1):
            out: list[Evaluation | FilterDivergedError] = []
            for x in points:
                try:
                    out.append(self.evaluate(x))
                except FilterDivergedError as exc:
                    out.append(exc)
            return out
        decoded = [self.decode(x) for x in points]
        self._evaluated = True
        par = self.parameterization
        groups: dict[tuple[UKFSettings, tuple[float, ...]], list[int]] = {}
        for i, (x, (_, _, settings)) in enumerate(zip(points, decoded)):
            key = (settings, tuple(par.model_values(x).values()))
            groups.setdefault(key, []).append(i)
        # results[i][j]: point i's score on manoeuvre j, or its error (first manoeuvre first)
        results: list[list[ManoeuvreScore | FilterDivergedError]] = [[] for _ in points]
        for (settings, _), idx in groups.items():
            q = np.array([decoded[i][0] for i in idx])
            r = np.array([decoded[i][1] for i in idx])
            params = self._point(points[idx[0]])[3]  # shared by the group
            for m in self.manoeuvres:
                batch = self._fs.run_lanes(m, q, r, settings, params=params)
                for b, i in enumerate(idx):
                    try:
                        results[i].append(
                            score_result(
                                m,
                                batch[b],
                                self.cost_spec,
                                self.burn_in,
                                self._fs,
                                self._fs.params_or(params),
                            )
                        )
                    except FilterDivergedError as exc:
                        results[i].append(exc)
        out = []
        for per_m in results:
            err = next((e for e in per_m if isinstance(e, FilterDivergedError)), None)
            scores = [s for s in per_m if isinstance(s, ManoeuvreScore)]  # all, without err
            out.append(err if err is not None else self._pool_scores(scores))
        return out

    def fingerprint(self) -> dict[str, Any]:
        """What makes two problems the same objective, for a study to check on resume: a
        readable summary and a SHA-256 over the manoeuvre data, vehicle, R, cost,
        parameterisation and burn-in."""
        h = hashlib.sha256()
        for m in self.manoeuvres:
            h.update(m.name.encode())
            for a in self._fingerprinted(m):
                h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        spec = self.cost_spec
        described = {
            "vehicle": None if self.vehicle is None else self.vehicle.to_dict(),
            "r0": self.r0.tolist(),
            "cost": {"kind": spec.kind, "weights": dict(spec.weights), "estimate": spec.estimate},
            "parameterization": self.parameterization.to_dict(),
            "burn_in": self.burn_in,
        }
        if self.cov_scale != 1.0:  # a run as tuned keeps earlier fingerprints
            described["cov_scale"] = self.cov_scale
        if spec.normalise != "manoeuvre":  # the paper's Eq. 15 keeps earlier fingerprints
            described["cost"]["normalise"] = spec.normalise
        file_sha = model_file_sha256(self._fs.spec)
        if not self._fs.paper_pair:  # it keeps the fingerprints of earlier studies
            described["model"] = {"name": self._fs.model.name, "filter": self._fs.filter}
            if file_sha is not None:  # an edited model file is another objective
                described["model"]["file_sha256"] = file_sha
        h.update(json.dumps(described, sort_keys=True).encode())
        names = [m.name for m in self.manoeuvres]
        return {
            "summary": f"{len(names)} manoeuvres ({names[0]} … {names[-1]}), "
            f"{self.vehicle.name if self.vehicle is not None else 'no vehicle'}, "
            f"cost {spec.kind}"
            + (f" ({spec.normalise}-normalised)" if spec.normalise != "manoeuvre" else "")
            + (
                f", model parameters {', '.join(self.parameterization.model_names)} tuned"
                if self.parameterization.model_names
                else ""
            )
            + (f", model file sha256 {file_sha[:12]}" if file_sha else ""),
            "sha256": h.hexdigest(),
        }

    def _fingerprinted(self, m: Manoeuvre) -> list[np.ndarray]:
        """The arrays of ``m`` a fingerprint covers: for a model over the single-track
        channels with a reference sideslip, t, u, z and beta_ref, as studies have always
        been fingerprinted; otherwise t, then every channel the objective reads (the
        model's inputs and measurements, the cost's references), each after its name."""
        mod = self._fs.model
        if (
            mod.input_names == ("delta", "ax")
            and mod.measurement_names == SIDESLIP_MEASUREMENTS
            and m.has("beta_ref")
        ):
            return [m.t, m.u, m.z, m.beta_ref]
        names = [*mod.input_names, *mod.measurement_names]
        if self.cost_spec.kind in ("nrmse", *SCORING_RULES):
            names += [f"{c}_ref" for c in self.cost_spec.channels if c not in names]
        out = [m.t]
        for c in names:
            out += [np.frombuffer(c.encode(), dtype=np.uint8), m.channel(c)]
        return out

    def run(self, x: Sequence[float] | np.ndarray, manoeuvre: Manoeuvre) -> FilterResult:
        """The filter's full output on one manoeuvre for a point (its model parameters,
        with :attr:`cov_scale`)."""
        q, r, settings, params = self._point(x)
        return self._fs.run(manoeuvre, q, r, settings, params=params, cov_scale=self.cov_scale)

    def noise_only(self) -> TuningProblem:
        """This problem with no model parameter tuned: the same manoeuvres, recorded model,
        R, cost and burn-in, the noise (and sigma-point) parameters alone — the first stage
        of a joint tuning, and what ``kftune tune`` without ``--tune-model`` would tune (the
        same fingerprint). Shares nothing mutable: close it after use when ``workers`` > 1
        (it starts its own pool)."""
        other = copy.copy(self)
        other.parameterization = replace(
            self.parameterization, model_bounds={}, model_scales={}, model_start={}
        )
        other._model_index = []
        other._pool = None
        other.cov_scale = 1.0
        return other

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # spawn, not fork: numba's threading layer is not fork-safe once it has run
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=init_worker,
                initargs=(
                    self.manoeuvres,
                    self.vehicle,
                    self._fs.spec,
                    self._fs.filter,
                    os.getpid(),
                ),
            )
        return self._pool

    def close(self) -> None:
        """Stop the worker processes (no-op when serial)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def __enter__(self) -> TuningProblem:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_pool"] = None  # a pool does not travel; a copy in another process is serial
        state["workers"] = 1
        fs = state.pop("_fs")  # compiled model functions do not pickle: load them again
        state["_fs_spec"] = (fs.spec, fs.filter)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        spec, filt = state.pop("_fs_spec")
        self.__dict__.update(state)
        self._fs = filter_spec(spec, filt, self.vehicle)


def assess(
    problem: TuningProblem,
    x: Sequence[float] | np.ndarray,
    manoeuvres: Sequence[Manoeuvre],
    channels: Sequence[str] | None = None,
) -> tuple[dict[str, dict[str, float]], dict[str, FilterResult]]:
    """KPIs and channel errors of a tuned filter on manoeuvres (for tables and figures).

    Scored like the problem's cost: after its burn-in, with its measured-channel estimate
    (posterior or prior). A diverged manoeuvre gets NaN metrics and ``diverged = 1``.

    Returns:
        (metrics, results): manoeuvre name → metrics, and name → the filter's result.
        For a model with the sideslip output ``beta`` (the single-track models): ``rmse,
        mae, rmse_non, mae_non, n_non`` [deg] (sideslip KPIs, :mod:`kftune.tuning.kpi`)
        and ``rmse_beta`` [deg], NaN on a manoeuvre without the reference ``beta_ref``
        (:func:`missing_references` says which); ``rmse_r`` [deg/s], ``rmse_ay``
        [m/s²]. For any other model: ``rmse_<measurement>`` for each measurement, and
        ``rmse_<output>`` for each output whose reference ``<output>_ref`` the manoeuvre
        has (in the channel's unit). With ``channels`` (measurements or outputs of the
        model), for any model: only ``rmse_<channel>`` for each of them, in the channel's
        unit (:func:`channel_estimate`; a missing reference is an error). And
        ``diverged`` (0/1).
    """
    metrics: dict[str, dict[str, float]] = {}
    results: dict[str, FilterResult] = {}
    estimate = problem.cost_spec.estimate
    model = problem.model
    sideslip = (
        channels is None
        and "beta" in problem._outputs()
        and {"r", "ay"} <= set(model.measurement_names)
    )
    for m in manoeuvres:
        res = problem.run(x, m)
        results[m.name] = res
        k0 = first_scored(m, problem.burn_in)
        row: dict[str, float] = {}
        if sideslip:
            if m.has("beta_ref") and not res.diverged:
                beta = model_output(res, "beta")
                row.update(sideslip_kpis(beta[k0:], m.beta_ref[k0:], m.ay[k0:]))
            else:
                row.update({k: math.nan for k in ("rmse", "mae", "rmse_non", "mae_non")})
            row["rmse_beta"] = row["rmse"]
            scored: dict[str, Any] = {"r": np.degrees, "ay": float}  # r in deg/s
        elif channels is not None:
            scored = dict.fromkeys(channels, float)
        else:
            scored = dict.fromkeys(model.measurement_names, float)
            refs = [c for c in problem._outputs() if m.has(f"{c}_ref")]
            scored.update(dict.fromkeys(refs, float))
        for c, unit in scored.items():
            if res.diverged:
                row[f"rmse_{c}"] = math.nan
                continue
            est, ref = channel_estimate(m, res, c, estimate)
            row[f"rmse_{c}"] = float(unit(np.sqrt(np.mean((est[k0:] - ref[k0:]) ** 2))))
        row["diverged"] = float(res.diverged)
        metrics[m.name] = row
    return metrics, results


def missing_references(
    problem: TuningProblem, manoeuvres: Sequence[Manoeuvre]
) -> dict[str, list[str]]:
    """Reference channel → the manoeuvres that lack it, for the KPIs :func:`assess` gives
    (the sideslip KPIs' ``beta_ref``); empty when every reference is there."""
    out: dict[str, list[str]] = {}
    if "beta" in problem._outputs():
        lacking = [m.name for m in manoeuvres if not m.has("beta_ref")]
        if lacking:
            out["beta_ref"] = lacking
    return out
