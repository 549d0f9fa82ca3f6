"""A tuned filter as a self-contained C99 program: ``kftune export --format c -o DIR``.

The export writes into DIR (:data:`C_FILES`):

* ``kftune_model.h``: the model's sizes, names and hook prototypes
  (:func:`kftune.models.c_contract.model_header`);
* ``kftune_model.c``: the model's C as it carries it (``StateSpaceModel.c_code``);
* ``kftune_filter.h``: the tuned constants (Q and R diagonals, the parameter vector p, dt,
  sigma-point weights, covariance scale c), the init/step API and the filter's conventions
  in comments, and the numbers-only macros of the older header export (``KFTUNE_*``);
* ``kftune_filter.c``: the UKF or the EKF step of kftune's generic kernels
  (:mod:`kftune.filters._generic_kernel`) operation by operation: the prior rule at step 0,
  Merwe weights, the Cholesky factorisation with the same jitter escalation, the
  predict/update in the same order of sums, the EKF's central differences where the model
  has no Jacobian, the finite checks, the model's check and its held conditions;
* ``kftune_demo.c``: reads a manoeuvre as CSV on standard input and writes the columns of
  ``kftune estimate`` (:func:`kftune.tuning.deploy.estimates_of`) on standard output;
* ``Makefile``: ``make`` builds ``kftune_demo`` (``cc -std=c99 -O2 -Wall -Wextra -Werror
  -pedantic``, ``CC`` and ``CFLAGS`` overridable), ``make asan`` the same with the address
  and undefined-behaviour sanitizers.

The filter allocates nothing (every array has a size fixed by the model's macros, and the
workspace lives in the caller's ``kf_filter``), and needs only libm. ``kf_real`` is
``double``, or ``float`` with ``precision="float"`` (the model header includes
``<tgmath.h>``, so that the same sources compute in float). The float build adds one step
that kftune's filters do not have: the UKF's prediction adds back the part of P that its
sigma points lose to float's rounding at the mean (``kf_spread_deficit``; without it tune's
default filter's Vx was 0.73 σ off the double filter's, with it 0.027 σ; BENCHMARKS.md).

:func:`check_export` builds the demo of an export with the system's C compiler and compares
every column it writes with kftune's own estimate on a dataset's manoeuvres (the relative
normwise deviation ‖c − k‖₂/‖k‖₂ per column, over the rows both filled).
"""

from __future__ import annotations

import math
import os
import re
import shlex
import shutil
import subprocess
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kftune.data.validate import TIME_NOISE_SPACINGS
from kftune.filters.sigma_points import UKFSettings, merwe_weights
from kftune.models.base import GENERIC_STOP_REASONS, STOP_NUMERICAL, StateSpaceModel
from kftune.models.jacobians import FD_REL_STEP
from kftune.models.kernel_io import JITTER_MAX, JITTER_START
from kftune.report.export import _c_comment, c_macros, provenance
from kftune.tuning.deploy import DT_TOLERANCE

__all__ = [
    "CFLAGS",
    "C_FILES",
    "FLOAT_BOUNDS",
    "FLOAT_MEASURES",
    "PRECISIONS",
    "TOLERANCE",
    "CheckRow",
    "DemoRun",
    "FloatColumn",
    "build_demo",
    "c_files",
    "check_manoeuvre",
    "column_deviations",
    "column_kind",
    "demo_columns",
    "find_compiler",
    "float_deviations",
    "float_summary",
    "manoeuvre_csv",
    "run_demo",
]

#: What ``kftune export --format c`` writes into its folder.
C_FILES = (
    "kftune_model.h",
    "kftune_model.c",
    "kftune_filter.h",
    "kftune_filter.c",
    "kftune_demo.c",
    "Makefile",
)
#: The C types a filter can compute in.
PRECISIONS = ("double", "float")
#: Largest relative normwise deviation of a double-precision export's column from kftune's
#: estimate that its check accepts.
TOLERANCE = 1e-9
#: The C compiler's flags of the demo (the Makefile's default CFLAGS).
CFLAGS = ("-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic")


# --------------------------------------------------------------------------------------
# The files
# --------------------------------------------------------------------------------------


def _check_document(doc: Mapping[str, Any], model: StateSpaceModel) -> None:
    """Refuse an export document that does not fit ``model`` (an edited tuned file, or the
    model file changed since): the C arrays take their sizes from the model, so a shorter
    list would run with zeros.

    Raises:
        ValueError: naming the key, what it holds and what the model needs.
    """
    if doc["filter"] not in ("ukf", "ekf"):
        raise ValueError(f"filter {doc['filter']!r}: the C export writes a UKF or an EKF")
    if doc["filter"] == "ukf" and "ukf_alpha" not in doc:
        raise ValueError("the deployment record of this UKF has no sigma_points")
    for key, names, what in (
        ("q_diag", model.state_names, "states"),
        ("r_diag", model.measurement_names, "measurements"),
        ("model_params", model.param_names, "parameters"),
    ):
        if len(doc[key]) != len(names):
            raise ValueError(
                f"{key} holds {len(doc[key])} values, model {model.name!r} has "
                f"{len(names)} {what} ({', '.join(names)})"
            )


def _float(v: float) -> str:
    """A C double literal of ``v`` that reads back as the same double."""
    text = repr(float(v))
    return text if any(c in text for c in ".en") else text + ".0"


def _init(values: Sequence[float], labels: Sequence[str]) -> str:
    """A brace initialiser, one value per line with its label, as a macro body."""
    if not values:
        return "{ 0 } /* none: a placeholder entry, never read */"
    lines = [f"    {_float(v)}, /* {_c_comment(label)} */ \\" for v, label in zip(values, labels)]
    return "{ \\\n" + "\n".join(lines) + "\n}"


def _ukf_weights(doc: Mapping[str, Any], n: int) -> tuple[float, float, float, float]:
    """(W_0^m, W_0^c, W_i, √(n + λ)) of the UKF's sigma points, as the filter computes them
    (:class:`kftune.filters.UKF`)."""
    settings = UKFSettings(doc["ukf_alpha"], doc["ukf_beta"], doc["ukf_kappa"])
    wm, wc = merwe_weights(n, settings)
    return float(wm[0]), float(wc[0]), float(wm[1]), math.sqrt(n + settings.lam(n))


def _stop_reasons(model: StateSpaceModel) -> dict[int, str]:
    """Every stop cause of the filter of ``model`` in words: the generic ones, the model's."""
    reasons = {k: v for k, v in GENERIC_STOP_REASONS.items() if k >= STOP_NUMERICAL}
    reasons.update(model.stop_reasons)
    for cause in model.held_causes:
        reasons.setdefault(cause, model.stop_reason(cause))
    return dict(sorted(reasons.items()))


def _filter_header(doc: Mapping[str, Any], model: StateSpaceModel, source: str) -> str:
    """The text of ``kftune_filter.h``."""
    ukf = doc["filter"] == "ukf"
    n = model.n_states
    held = list(model.held_causes)
    rule = textwrap.fill(
        _c_comment(doc["initial_state"]), 88, initial_indent=" *    ", subsequent_indent=" *    "
    )
    q_init = _init(doc["q_diag"], [f"{s} [{u}]" for s, u in zip(doc["states"], doc["q_units"])])
    r_init = _init(
        doc["r_diag"], [f"{s} [{u}]" for s, u in zip(doc["measurements"], doc["r_units"])]
    )
    p_init = _init(
        doc["model_params"],
        [f"{s} [{u}]" for s, u in zip(doc["model_param_names"], doc["model_param_units"])],
    )
    repaired = "the prior, the UKF's predicted covariance" if ukf else "the prior"
    c = float(doc.get("covariance_scale", 1.0))
    intro = [f" * {_c_comment(line)}".rstrip() for line in provenance(doc, source).splitlines()]
    hold = (
        f"a held condition (of the model's check) that lasts KF_HOLD_TIME = "
        f"{model.hold_time:g} s, rounded to whole steps (at least 1), stops the run at the step "
        "where it began: kf_step returns its cause at the step where it has lasted that long, "
        "and sets stop_step to the first step of it; the outputs of the steps from stop_step "
        "on are invalid (kftune writes them as empty cells)"
        if held
        else "(this model has no held conditions)"
    )
    hold = textwrap.fill(
        _c_comment(hold) + ".", 90, initial_indent=" *  - ", subsequent_indent=" *    "
    )
    jac = (
        "the model's own Jacobians F and H"
        if model.F is not None and model.H is not None
        else "central differences of f and h (step KF_FD_REL_STEP * max(|x_j|, 1), the "
        "representable spacing (x_j + step) - (x_j - step) as divisor) where the model has no "
        "Jacobian"
    )
    text = f"""/*
{chr(10).join(intro)}
 *
 * kftune_filter.h: the tuned {doc["filter"].upper()} of model {_c_comment(repr(model.name))}
 * in C99, reproducing kftune's own estimates (kftune estimate) to rounding. Build it with
 * kftune_filter.c and the model's kftune_model.c; only libm is needed, nothing is allocated
 * (the workspace is the caller's kf_filter), sizes come from kftune_model.h.
 *
 * Use:
 *     static kf_filter kf;            (static: its workspace is O(n^2) numbers)
 *     kf_estimate est;
 *     kf_init(&kf, KF_DT);            (or the recording's own sample time, see below)
 *     for each sample k:              (u: KF_NU raw inputs, z: KF_M measurements, SI units)
 *         if (kf_step(&kf, u, z, &est) != KF_STOP_NONE) -> stopped: see "Stops";
 *         else use est.x, est.P_diag, est.outputs, ...
 *
 * Conventions (those of kftune's filters, kftune.filters.generic):
 *  - sample k carries u[k] and z[k]. Step 0 only updates the prior with z[0]: the prior
 *    (x0, P0) comes from the model's rule kf_model_prior(z[0], R, p):
{rule}
 *  - step k >= 1 predicts from k-1 to k with the PREVIOUS input u[k-1] held over the step,
 *    then updates with z[k] through the measurement model at the CURRENT input u[k].
 *  - Q = diag(KF_Q_INIT) is the process-noise variance per step of dt; R = diag(KF_R_INIT).
"""
    if ukf:
        text += """ *  - UKF: Merwe scaled sigma points x, x +- KF_UKF_SPREAD * L[:, i] (L the lower
 *    Cholesky factor of P; weights KF_UKF_WM0, KF_UKF_WC0, KF_UKF_WI from alpha, beta,
 *    kappa). The points of (x+, P+) go through f; the predicted mean and covariance (+Q)
 *    are factorised again and the sigma points are REDRAWN from (x_pred, P_pred) before
 *    they go through h for the update (not the propagated points).
"""
    else:
        text += f""" *  - EKF: x_pred = f(x+), P_pred = F P+ F' + Q with F at x+; H at x_pred; with
 *    {_c_comment(jac)}.
"""
    text += f""" *  - the update uses the Cholesky factor L_S of the innovation covariance S:
 *    x+ = x_pred + W'v, P+ = P_pred - W'W, NIS = v'v with W = inv(L_S) P_xz', v = inv(L_S) y.
 *  - covariance repair: P+ after each update, {repaired} and S
 *    are factorised with jitter when needed: KF_JITTER_START * max(diag), ten times more
 *    per try, up to KF_JITTER_MAX * max(diag), added to the diagonal (and kept in P).
 *  - covariance scale c = KF_COV_SCALE (the tuned file's calibration): the filter runs with
 *    Q and R as they are; the covariances it REPORTS are c times larger: est.P_diag is
 *    c * diag(P+), est.nis is NIS / c, est.log_det_s is log det S + m ln c. Do not run it
 *    with c*Q and c*R instead{": that moves a UKF's estimate" if ukf else ""}.
 *
 * Stops (kf_step returns a cause other than KF_STOP_NONE; every later call returns it too):
 *  - KF_STOP_NUMERICAL: a covariance that jitter cannot repair, or a non-finite state,
 *    NIS or estimated measurement;
 *  - the model's own causes (kf_stop_reason says them in words) from kf_model_check on
 *    each posterior estimate, at once;
{hold}
 *  kftune treats any stop as the filter diverging: the run ends; the outputs from
 *  kf->stop_step on are not estimates.
 *
 * Sample time: kftune estimate runs a recording at its own sample time (the median step)
 * and refuses one that differs from the tuned KF_DT by more than KF_DT_TOLERANCE (relative),
 * because Q is a variance per step; kftune_demo does the same.
 */
#ifndef KFTUNE_FILTER_H
#define KFTUNE_FILTER_H

#include "kftune_model.h"

#define KF_FILTER_UKF {int(ukf)} /* 1: unscented Kalman filter; 0: extended Kalman filter */
#define KF_DT {_float(doc["dt"])} /* [s] the sample time the filter was tuned at */
#define KF_DT_TOLERANCE {_float(DT_TOLERANCE)} /* [-] relative sample-time difference refused */
#define KF_COV_SCALE {_float(c)} /* [-] reported covariances are this many times P (calibration) */

/* process-noise variances per step of dt, diagonal of Q, in state order */
#define KF_Q_INIT {q_init}
/* measurement-noise variances, diagonal of R, in measurement order */
#define KF_R_INIT {r_init}
/* the model's parameter vector p (the tuned values where tuned with the noise) */
#define KF_P_INIT {p_init}
"""
    if ukf:
        wm0, wc0, wi, spread = _ukf_weights(doc, n)
        text += f"""
/* sigma points: {_c_comment(doc["sigma_points"])}; alpha {doc["ukf_alpha"]!r},
   beta {doc["ukf_beta"]!r}, kappa {doc["ukf_kappa"]!r}; lambda = alpha^2 (n + kappa) - n */
#define KF_UKF_WM0 {_float(wm0)} /* W_0^m = lambda / (n + lambda) */
#define KF_UKF_WC0 {_float(wc0)} /* W_0^c = W_0^m + 1 - alpha^2 + beta */
#define KF_UKF_WI {_float(wi)} /* W_i = 1 / (2 (n + lambda)), i = 1..2n */
#define KF_UKF_SPREAD {_float(spread)} /* sqrt(n + lambda) */
"""
    else:
        text += f"""
#define KF_FD_REL_STEP {_float(FD_REL_STEP)} /* central differences: eps^(1/3) */
"""
    reasons = _stop_reasons(model)
    text += f"""
#define KF_JITTER_START {_float(JITTER_START)} /* first jitter, times the largest variance */
#define KF_JITTER_MAX {_float(JITTER_MAX)} /* largest jitter, times the largest variance */
#define KF_HOLD_TIME {_float(model.hold_time)} /* [s] a held condition stops the run after it */
/* the stop cause of each held condition */
#define KF_HELD_CAUSES_INIT {{ {", ".join(str(c) for c in held) or "0"} }}

/* stop causes */
#define KF_STOP_NONE 0
"""
    for cause, why in reasons.items():
        name = "KF_STOP_NUMERICAL" if cause == STOP_NUMERICAL else f"KF_STOP_MODEL_{cause}"
        text += f"#define {name} {cause} /* {_c_comment(why)} */\n"
    text += f"""
/* the filter's state and workspace: fill with kf_init, then only kf_step changes it */
typedef struct kf_filter {{
    kf_real x[KF_N];           /* posterior mean of the last step (SI units of the states) */
    kf_real P[KF_N * KF_N];    /* its covariance, row-major, without the covariance scale */
    kf_real L[KF_N * KF_N];    /* lower Cholesky factor of P */
    kf_real w_prev[KF_NW_ARR]; /* the previous step's prepared input: the next prediction's */
    kf_real dt;                /* [s] the sample time it runs at */
    long k;                    /* the next step's index */
    int n_hold;                /* steps a held condition must last: KF_HOLD_TIME / dt */
    int held[KF_NHELD_ARR];    /* the conditions the model's check holds violated now */
    int count[KF_NHELD_ARR];   /* for how many steps in a row each has been */
    int cause;                 /* KF_STOP_NONE while it runs, else why it stopped */
    long stop_step;            /* -1 while it runs, else the first step not estimated */
    long n_repairs;            /* covariance factorisations that needed jitter */
    /* workspace */
    kf_real Pxz[KF_N * KF_M], S[KF_M * KF_M], Ls[KF_M * KF_M], A[KF_M * KF_M];
    kf_real W[KF_M * KF_N], zb[KF_M], zh[KF_M], y[KF_M], v[KF_M], w[KF_NW_ARR];
#if KF_FILTER_UKF
    kf_real X[(2 * KF_N + 1) * KF_N], D[(2 * KF_N + 1) * KF_N], Y[(2 * KF_N + 1) * KF_N];
    kf_real Z[(2 * KF_N + 1) * KF_M];
#else
    kf_real F[KF_N * KF_N], H[KF_M * KF_N], T[KF_N * KF_N], xw[KF_N], fp[KF_N], fm[KF_N];
    kf_real hp[KF_M], hm[KF_M];
#endif
}} kf_filter;

/* one step's estimate (what kftune estimate writes) */
typedef struct kf_estimate {{
    kf_real x[KF_N];              /* posterior mean x+ (state units) */
    kf_real P_diag[KF_N];         /* KF_COV_SCALE * diag(P+) (squared state units) */
    kf_real z_hat[KF_M];          /* h(x+, u_k) */
    kf_real innovation[KF_M];     /* z_k - h(x_pred, u_k) (UKF: the sigma points' mean) */
    kf_real nis;                  /* normalised innovation squared / KF_COV_SCALE */
    kf_real log_det_s;            /* log det S + m ln KF_COV_SCALE */
    kf_real outputs[KF_NOUT_ARR]; /* the model's outputs of x+ (kf_model_outputs) */
}} kf_estimate;

/* the tuned constants (kftune_filter.c) */
extern const kf_real kf_q[KF_N];
extern const kf_real kf_r[KF_M];
extern const kf_real kf_p[KF_NP_ARR];

/* Start a run at sample time dt [s] (KF_DT, or the recording's own; > 0). */
void kf_init(kf_filter *kf, double dt);
/* Step k: u the KF_NU raw inputs (may be NULL when KF_NU is 0), z the KF_M measurements of
   sample k. Returns KF_STOP_NONE and fills est, or the cause of a stop (est untouched). */
int kf_step(kf_filter *kf, const kf_real u[], const kf_real z[], kf_estimate *est);
/* A stop cause in words ("" for KF_STOP_NONE). */
const char *kf_stop_reason(int cause);

/* ---- the tuned values as the numbers-only export names them (KFTUNE_*) ---- */
{c_macros(doc, source)}
#endif /* KFTUNE_FILTER_H */
"""
    return text


def _filter_source(model: StateSpaceModel) -> str:
    """The text of ``kftune_filter.c``: :data:`_ENGINE` with the stop reasons."""
    cases = "\n".join(
        f'    case {cause}: return "{_c_comment(why)}";'
        for cause, why in _stop_reasons(model).items()
    )
    return _ENGINE.replace("@STOP_REASONS@", cases)


#: The filter engine (kftune_filter.c). Each routine names the kernel function of
#: :mod:`kftune.filters._generic_kernel` it follows; the sums run in the same order.
_ENGINE = r"""/*
 * kftune_filter.c: the UKF and EKF steps of kftune's generic kernels
 * (kftune/filters/_generic_kernel.py), operation by operation. See kftune_filter.h.
 * Matrices are row-major: A[i * ncols + j].
 */
#include <stddef.h>

#include "kftune_filter.h"

#define KF_NS (2 * KF_N + 1)
/* 1 when kf_real is float: the float build's compensation (kf_spread_deficit) runs; the
   double build computes exactly as kftune does */
#define KF_REAL_IS_FLOAT (sizeof(kf_real) < sizeof(double))

const kf_real kf_q[KF_N] = KF_Q_INIT;
const kf_real kf_r[KF_M] = KF_R_INIT;
const kf_real kf_p[KF_NP_ARR] = KF_P_INIT;
static const int kf_held_causes[KF_NHELD_ARR] = KF_HELD_CAUSES_INIT;

const char *kf_stop_reason(int cause)
{
    switch (cause) {
    case KF_STOP_NONE: return "";
@STOP_REASONS@
    default: return "a stop cause of the model";
    }
}

/* chol: lower Cholesky factor L of P + jitter I from P's upper triangle;
   0 when a pivot is not > 0 and finite */
static int kf_chol(const kf_real *P, kf_real *L, kf_real jitter, int n)
{
    int i, j, k;
    kf_real s;
    for (i = 0; i < n; i++) {
        for (j = 0; j <= i; j++) {
            if (i == j) {
                s = P[i * n + i] + jitter;
                for (k = 0; k < j; k++)
                    s -= L[i * n + k] * L[i * n + k];
                if (!(s > 0 && s < INFINITY))
                    return 0;
                L[i * n + i] = sqrt(s);
            } else {
                s = P[j * n + i];
                for (k = 0; k < j; k++)
                    s -= L[i * n + k] * L[j * n + k];
                L[i * n + j] = s / L[j * n + j];
            }
        }
    }
    return 1;
}

/* chol_repair: 0 factorised as is, 1 after adding *jitter to the diagonal, 2 not repairable */
static int kf_chol_repair(const kf_real *P, kf_real *L, int n, kf_real *jitter)
{
    kf_real jit = 0, limit = 0, scale;
    int status = 0, i, j, finite;
    *jitter = 0;
    for (;;) {
        if (kf_chol(P, L, jit, n)) {
            *jitter = jit;
            return status;
        }
        if (status == 0) {
            status = 1;
            scale = P[0];
            finite = 1;
            for (i = 0; i < n; i++) {
                if (P[i * n + i] > scale)
                    scale = P[i * n + i];
                for (j = i; j < n; j++)
                    if (!isfinite(P[i * n + j]))
                        finite = 0;
            }
            jit = (kf_real)KF_JITTER_START * scale;
            limit = (kf_real)KF_JITTER_MAX * scale * (kf_real)1.0000001;
            if (!(finite && jit > 0))
                return 2;
        } else {
            jit *= 10;
        }
        if (!(jit <= limit))
            return 2;
    }
}

/* kalman_update: (x, P) updated in place from zb, S (with R), Pxz and z; returns the status
   of S's factorisation (x, P untouched on 2) and the NIS in *nis */
static int kf_kalman_update(kf_filter *kf, const kf_real z[], kf_real *nis)
{
    const int n = KF_N, m = KF_M;
    int i, j, k, a, b, st;
    kf_real s, jit;
    st = kf_chol_repair(kf->S, kf->Ls, m, &jit);
    if (st == 2) {
        *nis = NAN;
        return st;
    }
    /* A = inverse of L_S by forward substitution */
    for (i = 0; i < m; i++)
        kf->A[i * m + i] = 1 / kf->Ls[i * m + i];
    for (i = 1; i < m; i++) {
        for (j = 0; j < i; j++) {
            s = kf->Ls[i * m + j] * kf->A[j * m + j];
            for (k = j + 1; k < i; k++)
                s += kf->Ls[i * m + k] * kf->A[k * m + j];
            kf->A[i * m + j] = -s * kf->A[i * m + i];
        }
    }
    /* W = A Pxz',  v = A y */
    for (i = 0; i < m; i++) {
        for (j = 0; j < n; j++) {
            s = kf->A[i * m] * kf->Pxz[j * m];
            for (k = 1; k <= i; k++)
                s += kf->A[i * m + k] * kf->Pxz[j * m + k];
            kf->W[i * n + j] = s;
        }
    }
    for (i = 0; i < m; i++)
        kf->y[i] = z[i] - kf->zb[i];
    *nis = 0;
    for (i = 0; i < m; i++) {
        s = kf->A[i * m] * kf->y[0];
        for (k = 1; k <= i; k++)
            s += kf->A[i * m + k] * kf->y[k];
        kf->v[i] = s;
        *nis = i == 0 ? s * s : *nis + s * s;
    }
    /* x+ = x_pred + W' v,  P+ = P_pred - W' W */
    for (j = 0; j < n; j++) {
        s = kf->W[j] * kf->v[0];
        for (i = 1; i < m; i++)
            s += kf->W[i * n + j] * kf->v[i];
        kf->x[j] += s;
    }
    for (a = 0; a < n; a++) {
        for (b = a; b < n; b++) {
            s = kf->W[a] * kf->W[b];
            for (i = 1; i < m; i++)
                s += kf->W[i * n + a] * kf->W[i * n + b];
            kf->P[a * n + b] -= s;
            kf->P[b * n + a] = kf->P[a * n + b];
        }
    }
    return st;
}

#if KF_FILTER_UKF
/* sigma_points: X = x + D with D = 0, +-c L[:, i] (update), or x itself where D is 0
   (prediction): the two differ only for a state -0.0, as in kftune's kernels */
static void kf_sigma_points(kf_filter *kf, int update)
{
    const int n = KF_N;
    int i, j;
    kf_real d, c = (kf_real)KF_UKF_SPREAD;
    for (j = 0; j < n; j++) {
        kf->X[j] = update ? kf->x[j] + 0 : kf->x[j];
        kf->D[j] = 0;
    }
    for (i = 0; i < n; i++) {
        for (j = 0; j < n; j++) {
            d = j >= i ? c * kf->L[j * n + i] : 0;
            kf->D[(1 + i) * n + j] = d;
            kf->D[(1 + n + i) * n + j] = -d;
            if (update) {
                kf->X[(1 + i) * n + j] = kf->x[j] + d;
                kf->X[(1 + n + i) * n + j] = kf->x[j] + -d;
            } else {
                kf->X[(1 + i) * n + j] = j >= i ? kf->x[j] + d : kf->x[j];
                kf->X[(1 + n + i) * n + j] = j >= i ? kf->x[j] - d : kf->x[j];
            }
        }
    }
}

/* Float only (kftune's filters have no such step): the sigma points X_i = x + D_i are
   rounded to float's grid at x, which is coarse against D_i where a state's sigma is a
   small fraction of its value (Vx: ulp(33 m/s) = 3.8e-6 m/s against a spread of 3e-3), so
   the points carry the covariance sum W_i (X_i - x)(X_i - x)' instead of P, off by about
   1e-3 with the same sign step after step. kf_spread_deficit writes the difference
   P - sum W_i (X_i - x)(X_i - x)' (each X_i - x exact in float) into L, no longer needed
   once the points are drawn; kf_step adds it to the predicted covariance (as if f moved it
   as the identity does, which over one step of dt is the leading term). */
static void kf_spread_deficit(kf_filter *kf)
{
    const int n = KF_N;
    int i, a, b;
    kf_real s;
    for (a = 0; a < n; a++) {
        for (b = 0; b < n; b++) {
            s = 0;
            for (i = 1; i < KF_NS; i++)
                s += (kf->X[i * n + a] - kf->x[a]) * (kf->X[i * n + b] - kf->x[b]);
            kf->L[a * n + b] = kf->P[a * n + b] - (kf_real)KF_UKF_WI * s;
        }
    }
}

/* unscented_moments: mean = sum W^m Y_i; Y_i -= mean; cov = sum W^c d d' + diag(noise);
   Y: (2n+1, k) */
static void kf_unscented_moments(kf_real *Y, kf_real *mean, kf_real *cov, const kf_real *noise,
                                 int k)
{
    int i, j, a, b;
    kf_real s;
    const kf_real wm0 = (kf_real)KF_UKF_WM0, wc0 = (kf_real)KF_UKF_WC0, wi = (kf_real)KF_UKF_WI;
    for (j = 0; j < k; j++) {
        s = wm0 * Y[j];
        for (i = 1; i < KF_NS; i++)
            s += wi * Y[i * k + j];
        mean[j] = s;
    }
    for (i = 0; i < KF_NS; i++)
        for (j = 0; j < k; j++)
            Y[i * k + j] -= mean[j];
    for (a = 0; a < k; a++) {
        for (b = a; b < k; b++) {
            s = wc0 * Y[a] * Y[b];
            for (i = 1; i < KF_NS; i++)
                s += wi * Y[i * k + a] * Y[i * k + b];
            cov[a * k + b] = s;
        }
        cov[a * k + a] += noise[a];
        for (b = a + 1; b < k; b++)
            cov[b * k + a] = cov[a * k + b];
    }
}
#elif !KF_HAS_F_JACOBIAN || !KF_HAS_H_JACOBIAN
/* numerical_process_jacobian / numerical_measurement_jacobian: central differences
   (kftune/models/jacobians.py); which = 0 for f into F, 1 for h into H */
static void kf_central_differences(kf_filter *kf, int which, const kf_real w[])
{
    const int n = KF_N, rows = which == 0 ? KF_N : KF_M;
    int i, j;
    kf_real ax, step, hi, lo, inv;
    kf_real *out = which == 0 ? kf->F : kf->H;
    kf_real *gp = which == 0 ? kf->fp : kf->hp, *gm = which == 0 ? kf->fm : kf->hm;
    for (j = 0; j < n; j++)
        kf->xw[j] = kf->x[j];
    for (j = 0; j < n; j++) {
        ax = fabs(kf->x[j]);
        step = (kf_real)KF_FD_REL_STEP * ((kf_real)1 > ax ? (kf_real)1 : ax);
        hi = kf->x[j] + step;
        lo = kf->x[j] - step;
        kf->xw[j] = hi;
        if (which == 0)
            kf_model_f(kf->xw, w, kf_p, kf->dt, gp);
        else
            kf_model_h(kf->xw, w, kf_p, gp);
        kf->xw[j] = lo;
        if (which == 0)
            kf_model_f(kf->xw, w, kf_p, kf->dt, gm);
        else
            kf_model_h(kf->xw, w, kf_p, gm);
        kf->xw[j] = kf->x[j];
        inv = 1 / (hi - lo);
        for (i = 0; i < rows; i++)
            out[i * n + j] = (gp[i] - gm[i]) * inv;
    }
}
#endif

#if !KF_FILTER_UKF
/* linearised_prediction / linearised_moments: out = A B (rows x cols, sums over inner),
   A row-major with rows of length inner, B[i][b] at B[i * bi + b * bb] (B' is bi = 1,
   bb = inner). With noise: only the upper triangle summed, noise added on the diagonal,
   mirrored (a covariance); without: every entry. */
static void kf_product(const kf_real *A, const kf_real *B, int bi, int bb, kf_real *out,
                       int rows, int cols, int inner, const kf_real *noise)
{
    int a, b, i;
    kf_real s;
    for (a = 0; a < rows; a++) {
        for (b = noise != NULL ? a : 0; b < cols; b++) {
            s = 0;
            for (i = 0; i < inner; i++)
                s += A[a * inner + i] * B[i * bi + b * bb];
            if (noise == NULL) {
                out[a * cols + b] = s;
            } else {
                out[a * cols + b] = a == b ? s + noise[a] : s;
                out[b * cols + a] = out[a * cols + b];
            }
        }
    }
}
#endif

void kf_init(kf_filter *kf, double dt)
{
    int j;
    for (j = 0; j < KF_N * KF_N; j++) {
        kf->P[j] = 0;
        kf->L[j] = 0;
    }
    for (j = 0; j < KF_M * KF_M; j++) {
        kf->A[j] = 0;
        kf->Ls[j] = 0;
    }
    for (j = 0; j < KF_NHELD_ARR; j++) {
        kf->held[j] = 0;
        kf->count[j] = 0;
    }
    kf->dt = (kf_real)dt;
    kf->n_hold = 1;
    if (KF_NHELD > 0) {
        int steps = (int)(KF_HOLD_TIME / dt + 0.5);
        kf->n_hold = steps > 1 ? steps : 1;
    }
    kf->k = 0;
    kf->cause = KF_STOP_NONE;
    kf->stop_step = -1;
    kf->n_repairs = 0;
}

static int kf_stop(kf_filter *kf, long step, int cause)
{
    kf->stop_step = step;
    kf->cause = cause;
    return cause;
}

/* the prepared input row of u (kf_model_prepare, or u itself) into w */
static void kf_prepare(const kf_real u[], kf_real w[])
{
#if KF_HAS_PREPARE
    kf_model_prepare(u, kf_p, w);
#else
    int j;
    for (j = 0; j < KF_NU; j++)
        w[j] = u[j];
    (void)u;
    (void)w;
#endif
}

int kf_step(kf_filter *kf, const kf_real u[], const kf_real z[], kf_estimate *est)
{
    const int n = KF_N, m = KF_M;
    const long k = kf->k;
    int i, j, st, st_s, cause;
    kf_real jit, nis, ldet;
    if (kf->cause != KF_STOP_NONE)
        return kf->cause;
    kf_prepare(u, kf->w);
    if (k == 0) {
        /* prior: x = x0; P = P0 symmetrised, factorised and repaired (P0 is written into
           L, the factor's place, which the factorisation then fills: no stack array) */
        const kf_real *P0 = kf->L;
        kf_model_prior(z, kf_r, kf_p, kf->x, kf->L);
        for (i = 0; i < n; i++) {
            kf->P[i * n + i] = P0[i * n + i];
            for (j = i + 1; j < n; j++) {
                kf->P[i * n + j] = (kf_real)0.5 * (P0[i * n + j] + P0[j * n + i]);
                kf->P[j * n + i] = kf->P[i * n + j];
            }
        }
        for (i = 0; i < n * n; i++)
            kf->L[i] = 0;
        st = kf_chol_repair(kf->P, kf->L, n, &jit);
        if (st == 2)
            return kf_stop(kf, 0, KF_STOP_NUMERICAL);
        if (st == 1)
            for (i = 0; i < n; i++)
                kf->P[i * n + i] += jit;
        kf->n_repairs += st;
    }
#if KF_FILTER_UKF
    if (k > 0) {
        /* predict k-1 -> k with u[k-1]: the points of (x+, P+) through f */
        kf_sigma_points(kf, 0);
        if (KF_REAL_IS_FLOAT)
            kf_spread_deficit(kf);
        for (i = 0; i < KF_NS; i++)
            kf_model_f(&kf->X[i * n], kf->w_prev, kf_p, kf->dt, &kf->Y[i * n]);
        kf_unscented_moments(kf->Y, kf->x, kf->P, kf_q, n);
        if (KF_REAL_IS_FLOAT)
            for (i = 0; i < n * n; i++)
                kf->P[i] += kf->L[i];
        st = kf_chol_repair(kf->P, kf->L, n, &jit);
        if (st == 2)
            return kf_stop(kf, k, KF_STOP_NUMERICAL);
        if (st == 1)
            for (j = 0; j < n; j++)
                kf->P[j * n + j] += jit;
        kf->n_repairs += st;
    }
    /* update with z[k] and h(., u[k]): the sigma points redrawn from (x_pred, P_pred) */
    kf_sigma_points(kf, 1);
    for (i = 0; i < KF_NS; i++)
        kf_model_h(&kf->X[i * n], kf->w, kf_p, &kf->Z[i * m]);
    kf_unscented_moments(kf->Z, kf->zb, kf->S, kf_r, m);
    {
        /* cross_covariance: Pxz = sum_{i >= 1} W_i D_i dZ_i' */
        int a, b;
        kf_real s;
        for (a = 0; a < n; a++) {
            for (b = 0; b < m; b++) {
                s = 0;
                for (i = 1; i < KF_NS; i++)
                    s += (kf_real)KF_UKF_WI * kf->D[i * n + a] * kf->Z[i * m + b];
                kf->Pxz[a * m + b] = s;
            }
        }
    }
#else
    if (k > 0) {
        /* predict: F at x+; x_pred = f(x+, u[k-1]); P_pred = F P F' + Q */
#if KF_HAS_F_JACOBIAN
        kf_model_F(kf->x, kf->w_prev, kf_p, kf->dt, kf->F);
#else
        kf_central_differences(kf, 0, kf->w_prev);
#endif
        kf_model_f(kf->x, kf->w_prev, kf_p, kf->dt, kf->xw);
        for (j = 0; j < n; j++)
            kf->x[j] = kf->xw[j];
        kf_product(kf->F, kf->P, n, 1, kf->T, n, n, n, NULL); /* T = F P */
        kf_product(kf->T, kf->F, 1, n, kf->P, n, n, n, kf_q); /* P = T F' + Q */
    }
    /* update: H at x_pred; zb = h(x_pred, u[k]); Pxz = P H'; S = H Pxz + R */
#if KF_HAS_H_JACOBIAN
    kf_model_H(kf->x, kf->w, kf_p, kf->H);
#else
    kf_central_differences(kf, 1, kf->w);
#endif
    kf_model_h(kf->x, kf->w, kf_p, kf->zb);
    kf_product(kf->P, kf->H, 1, n, kf->Pxz, n, m, n, NULL);   /* Pxz = P H' */
    kf_product(kf->H, kf->Pxz, m, 1, kf->S, m, m, n, kf_r);  /* S = H Pxz + R */
#endif
    st_s = kf_kalman_update(kf, z, &nis);
    /* conclude_step: the numerical checks, the model's check, the held conditions */
    if (st_s == 2)
        return kf_stop(kf, k, KF_STOP_NUMERICAL);
    st = kf_chol_repair(kf->P, kf->L, n, &jit);
    kf_model_h(kf->x, kf->w, kf_p, kf->zh);
    {
        int finite = isfinite(nis);
        for (j = 0; j < n; j++)
            finite = finite && isfinite(kf->x[j]);
        for (j = 0; j < m; j++)
            finite = finite && isfinite(kf->zh[j]);
        if (st == 2 || !finite)
            return kf_stop(kf, k, KF_STOP_NUMERICAL);
    }
#if KF_HAS_CHECK
    cause = kf_model_check(kf->x, z, kf->w, kf_p, kf->held);
#else
    cause = KF_STOP_NONE;
#endif
    if (cause != KF_STOP_NONE)
        return kf_stop(kf, k, cause);
    ldet = 0;
    for (i = 0; i < m; i++)
        ldet += 2 * log(kf->Ls[i * m + i]);
    for (j = 0; j < KF_NHELD; j++)
        kf->count[j] = kf->held[j] ? kf->count[j] + 1 : 0;
    for (j = 0; j < KF_NHELD; j++)
        if (kf->count[j] >= kf->n_hold)
            return kf_stop(kf, k + 1 - kf->n_hold, kf_held_causes[j]);
    if (st == 1)
        for (j = 0; j < n; j++)
            kf->P[j * n + j] += jit;
    kf->n_repairs += st_s + st;
    for (j = 0; j < n; j++) {
        est->x[j] = kf->x[j];
        est->P_diag[j] = kf->P[j * n + j] * (kf_real)KF_COV_SCALE;
    }
    for (j = 0; j < m; j++) {
        est->innovation[j] = kf->y[j];
        est->z_hat[j] = kf->zh[j];
    }
    est->nis = nis / (kf_real)KF_COV_SCALE;
    est->log_det_s = ldet + (kf_real)m * log((kf_real)KF_COV_SCALE);
    kf_model_outputs(kf->x, est->outputs);
    for (j = 0; j < KF_NW; j++)
        kf->w_prev[j] = kf->w[j];
    kf->k = k + 1;
    return KF_STOP_NONE;
}
"""


def _columns(model: StateSpaceModel) -> tuple[list[str], list[str]]:
    """(names, C expressions of ``e``, a kf_estimate) of the columns the demo computes, in
    the order of :func:`kftune.tuning.deploy.estimates_of` after ``t``."""
    names: list[str] = []
    exprs: list[str] = []
    states = model.state_names
    for i, s in enumerate(states):
        names.append(s)
        exprs.append(f"e->x[{i}]")
    for i, s in enumerate(states):
        names.append(f"{s}_std")
        exprs.append(f"sqrt(e->P_diag[{i}])")
    outputs = list(model.outputs)
    if "beta" in outputs:
        names.append("beta")
        exprs.append(f"e->outputs[{outputs.index('beta')}]")
        if states[:2] == ("vx", "vy"):  # tuning.runs.beta_std: the delta method
            names.append("beta_std")
            exprs.append(
                "sqrt(e->x[1] * e->x[1] * e->P_diag[0] + e->x[0] * e->x[0] * e->P_diag[1]) / "
                "(e->x[0] * e->x[0] + e->x[1] * e->x[1])"
            )
    for i, name in enumerate(outputs):
        if name not in names:
            names.append(name)
            exprs.append(f"e->outputs[{i}]")
    for i, z in enumerate(model.measurement_names):
        names.append(f"innovation_{z}")
        exprs.append(f"e->innovation[{i}]")
    names.append("nis")
    exprs.append("e->nis")
    return names, exprs


def demo_columns(model: StateSpaceModel) -> list[str]:
    """The columns the demo of a filter of ``model`` writes before the references: ``t``
    and those of :func:`kftune.tuning.deploy.estimates_of`."""
    return ["t", *_columns(model)[0]]


def _reference_candidates(model: StateSpaceModel, computed: Sequence[str]) -> list[str]:
    """The reference columns estimate copies from a recording that has them, in order."""
    out = ["beta_ref"]
    for name in (*model.state_names, *model.outputs):
        ref = f"{name}_ref"
        if name != "beta" and ref not in out and ref not in computed:
            out.append(ref)
    return out


def _c_string(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _demo_source(model: StateSpaceModel) -> str:
    """The text of ``kftune_demo.c``."""
    names, exprs = _columns(model)
    refs = _reference_candidates(model, names)
    assign = "\n".join(f"    col[{i}] = {e};" for i, e in enumerate(exprs))
    inputs = ", ".join(_c_string(s) for s in model.input_names) or '""'
    meas = ", ".join(_c_string(s) for s in model.measurement_names)
    return (
        _DEMO.replace("@NCOL@", str(len(names)))
        .replace("@HEADER@", _c_string(",".join(names)))
        .replace("@NREF@", str(len(refs)))
        .replace("@REFS@", ", ".join(_c_string(s) for s in refs))
        .replace("@INPUTS@", inputs)
        .replace("@MEASUREMENTS@", meas)
        .replace("@COLUMNS@", assign)
        .replace("@SPACINGS@", repr(TIME_NOISE_SPACINGS))
    )


#: kftune_demo.c: the CSV in and out around the filter (it may allocate: the filter does not).
_DEMO = r"""/*
 * kftune_demo.c: run the exported filter on a manoeuvre.
 *
 *     ./kftune_demo < manoeuvre.csv > estimates.csv
 *     gzip -dc manoeuvre.csv.gz | ./kftune_demo > estimates.csv
 *
 * Input: a manoeuvre of a kftune dataset as uncompressed CSV on standard input. A dataset's
 * manoeuvre files are gzipped (.csv.gz: the bundled set's, and those kftune dataset import
 * and kftune dataset generate write): decompress them on the way in, as above. The CSV is a
 * header row naming the columns, among them t [s], the model's inputs and measurements (in
 * any order; other columns are ignored, except the references kftune estimate copies, such
 * as beta_ref), then one row of numbers per sample.
 * Output: the columns of kftune estimate, same names and order: t, the states, <state>_std,
 * the model's outputs (beta, beta_std), innovation_<measurement>, nis and the references,
 * every number with %.17g, empty cells where kftune has none (after a stop).
 * The manoeuvre runs at its own sample time (the median step, as kftune's); one that differs
 * from the tuned KF_DT by more than KF_DT_TOLERANCE is refused, as kftune estimate does.
 * Exit status: 0 done; 1 the filter stopped (diverged; the rows from its stop step are
 * empty, the reason on standard error); 2 unusable input (the reason on standard error).
 * The model's own data checks are not repeated here (kftune refuses, for example, a
 * single-track manoeuvre whose measured Vx is not > 0 before it filters): check with
 * kftune dataset info or kftune estimate first.
 */
#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kftune_filter.h"

#define NCOL @NCOL@
#define NREF @NREF@
static const char *const col_header = @HEADER@;
static const char *const ref_names[NREF] = { @REFS@ };
static const char *const input_names[KF_NU_ARR] = { @INPUTS@ };
static const char *const meas_names[KF_M] = { @MEASUREMENTS@ };
/* kftune's TIME_NOISE_SPACINGS (kftune/data/validate.py sample_time) */
#define TIME_NOISE_SPACINGS @SPACINGS@

/* the columns of one estimate, in the order of col_header */
static void columns(const kf_estimate *e, double col[])
{
@COLUMNS@
}

static void fail(const char *fmt, ...)
{
    va_list ap;
    fputs("kftune_demo: ", stderr);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    exit(2);
}

static void *grow(void *p, size_t n)
{
    void *q = realloc(p, n);
    if (q == NULL)
        fail("out of memory");
    return q;
}

/* one line of stdin without its end of line (malloc'ed), NULL at the end */
static char *read_line(void)
{
    size_t n = 0, cap = 256;
    int ch;
    char *s = grow(NULL, cap);
    while ((ch = getchar()) != EOF && ch != '\n') {
        if (n + 2 > cap)
            s = grow(s, cap *= 2);
        s[n++] = (char)ch;
    }
    if (ch == EOF && n == 0) {
        free(s);
        return NULL;
    }
    if (n > 0 && s[n - 1] == '\r')
        n--;
    s[n] = '\0';
    return s;
}

/* the number of cells of a row */
static int count_cells(const char *s)
{
    int n = 1;
    for (; *s; s++)
        n += *s == ',';
    return n;
}

/* split s in place at commas into its cells; 0 when it has not exactly n */
static int split(char *s, char **cells, int n)
{
    int i;
    if (count_cells(s) != n)
        return 0;
    for (i = 0; i < n; i++) {
        char *end = strchr(s, ',');
        cells[i] = s;
        if (end != NULL) {
            *end = '\0';
            s = end + 1;
        }
    }
    return 1;
}

static char *trim(char *s)
{
    char *end;
    while (*s == ' ' || *s == '\t' || *s == '"')
        s++;
    end = s + strlen(s);
    while (end > s && (end[-1] == ' ' || end[-1] == '\t' || end[-1] == '"'))
        *--end = '\0';
    return s;
}

/* a number of a cell: 1 parsed into *v, 0 empty (NaN), -1 not a number */
static int number(char *cell, double *v)
{
    char *s = trim(cell), *end;
    if (*s == '\0') {
        *v = NAN;
        return 0;
    }
    errno = 0;
    *v = strtod(s, &end);
    if (end == s || *trim(end) != '\0')
        return -1;
    return 1;
}

static int column_of(char **names, int n, const char *name)
{
    int i, found = -1;
    for (i = 0; i < n; i++) {
        if (strcmp(names[i], name) == 0) {
            if (found >= 0)
                fail("line 1: the column %s is named twice in the header", name);
            found = i;
        }
    }
    return found;
}

static int by_value(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return x < y ? -1 : x > y;
}

/* kftune's sample_time: the median step, rounded to the shortest decimal within the
   timestamps' own resolution (TIME_NOISE_SPACINGS float spacings of the largest |t|) */
static double sample_time(const double *t, long n)
{
    double *d = grow(NULL, (size_t)(n - 1) * sizeof *d), dt, big = 0, spacing, quantum;
    long i;
    int dec, first, last;
    char text[64];
    for (i = 0; i + 1 < n; i++)
        d[i] = t[i + 1] - t[i];
    qsort(d, (size_t)(n - 1), sizeof *d, by_value);
    dt = (n - 1) % 2 ? d[(n - 1) / 2] : (d[(n - 1) / 2 - 1] + d[(n - 1) / 2]) / 2;
    free(d);
    for (i = 0; i < n; i++)
        if (fabs(t[i]) > big)
            big = fabs(t[i]);
    if (!(isfinite(dt) && dt > 0))
        return dt;
    spacing = nextafter(big, INFINITY) - big;
    quantum = TIME_NOISE_SPACINGS * spacing > dt * 1e-12 ? TIME_NOISE_SPACINGS * spacing
                                                         : dt * 1e-12;
    if (quantum >= dt)
        return dt;
    first = -(int)floor(log10(dt));
    last = -(int)floor(log10(quantum));
    for (dec = first; dec <= last; dec++) {
        /* Python's round(dt, dec): the decimal rounding of the exact double, read back */
        double rounded;
        int digits = (int)floor(log10(dt)) + 1 + dec; /* significant digits kept */
        if (dec > 40 || digits < 1)
            continue;
        if (dec >= 0)
            sprintf(text, "%.*f", dec, dt);
        else
            sprintf(text, "%.*e", digits - 1, dt);
        rounded = strtod(text, NULL);
        if (fabs(rounded - dt) <= quantum)
            return rounded;
    }
    return dt;
}

int main(void)
{
    static kf_filter kf;
    kf_estimate est;
    char *line, *header, **cells;
    int ncell, i, j, t_col, in_col[KF_NU_ARR], z_col[KF_M], ref_col[NREF], ref_any[NREF];
    long n = 0, cap = 1024, k, lineno = 1, stop = -1;
    double *data = NULL, *out = NULL, dt;
    const int width = 1 + KF_NU + KF_M + NREF; /* t, u, z, references */
    kf_real u[KF_NU_ARR], z[KF_M];
    int cause = KF_STOP_NONE;

    line = read_line();
    if (line == NULL)
        fail("no header row on standard input: expected a manoeuvre's CSV whose header names "
             "t, the inputs and the measurements");
    ncell = count_cells(line);
    cells = grow(NULL, (size_t)ncell * sizeof *cells);
    split(line, cells, ncell);
    header = line;
    for (i = 0; i < ncell; i++)
        cells[i] = trim(cells[i]);
    t_col = column_of(cells, ncell, "t");
    if (t_col < 0)
        fail("line 1: the header names no column t (time [s]); it names %d columns", ncell);
    for (j = 0; j < KF_NU; j++)
        if ((in_col[j] = column_of(cells, ncell, input_names[j])) < 0)
            fail("line 1: the header names no column %s, an input of the model", input_names[j]);
    for (j = 0; j < KF_M; j++)
        if ((z_col[j] = column_of(cells, ncell, meas_names[j])) < 0)
            fail("line 1: the header names no column %s, a measurement of the model",
                 meas_names[j]);
    for (j = 0; j < NREF; j++) {
        ref_col[j] = column_of(cells, ncell, ref_names[j]);
        ref_any[j] = 0;
    }
    data = grow(NULL, (size_t)cap * width * sizeof *data);
    while ((line = read_line()) != NULL) {
        double *row;
        lineno++;
        if (*trim(line) == '\0') {
            free(line);
            continue;
        }
        if (!split(line, cells, ncell))
            fail("line %ld has %d cells; the header has %d", lineno, count_cells(line), ncell);
        if (n == cap)
            data = grow(data, (size_t)(cap *= 2) * width * sizeof *data);
        row = data + n * width;
        for (j = 0; j < 1 + KF_NU + KF_M; j++) {
            int c = j == 0 ? t_col : j <= KF_NU ? in_col[j - 1] : z_col[j - 1 - KF_NU];
            const char *name = j == 0 ? "t" : j <= KF_NU ? input_names[j - 1]
                                                        : meas_names[j - 1 - KF_NU];
            int got = number(cells[c], &row[j]);
            if (got <= 0)
                fail("line %ld, column %s: '%s' is not a number", lineno, name, trim(cells[c]));
            if (!isfinite(row[j]))
                fail("line %ld, column %s: %s is not finite; the filter needs finite values",
                     lineno, name, trim(cells[c]));
        }
        for (j = 0; j < NREF; j++) {
            double *v = &row[1 + KF_NU + KF_M + j];
            *v = NAN;
            if (ref_col[j] >= 0 && number(cells[ref_col[j]], v) < 0)
                fail("line %ld, column %s: '%s' is not a number", lineno, ref_names[j],
                     trim(cells[ref_col[j]]));
            if (isfinite(*v))
                ref_any[j] = 1;
        }
        n++;
        free(line);
    }
    free(cells);
    free(header);
    if (n < 2)
        fail("%ld rows of samples; at least 2 are needed (the sample time is the median step)",
             n);
    {
        double *t = grow(NULL, (size_t)n * sizeof *t);
        for (k = 0; k < n; k++)
            t[k] = data[k * width];
        dt = sample_time(t, n);
        free(t);
    }
    if (!(dt > 0))
        fail("the time column t does not increase (median step %.6g s)", dt);
    if (fabs(dt - KF_DT) > KF_DT_TOLERANCE * KF_DT)
        fail("the manoeuvre is sampled every %.6g s, the filter was tuned at dt = %.6g s (Q is "
             "a variance per step): kftune estimate refuses it too", dt, KF_DT);

    out = grow(NULL, (size_t)n * NCOL * sizeof *out);
    kf_init(&kf, dt);
    for (k = 0; k < n; k++) {
        const double *row = data + k * width;
        for (j = 0; j < KF_NU; j++)
            u[j] = (kf_real)row[1 + j];
        for (j = 0; j < KF_M; j++)
            z[j] = (kf_real)row[1 + KF_NU + j];
        cause = kf_step(&kf, u, z, &est);
        if (cause != KF_STOP_NONE) {
            stop = kf.stop_step;
            break;
        }
        columns(&est, out + k * NCOL);
    }

    printf("t,%s", col_header);
    for (j = 0; j < NREF; j++)
        if (ref_any[j])
            printf(",%s", ref_names[j]);
    putchar('\n');
    for (k = 0; k < n; k++) {
        const double *row = data + k * width;
        printf("%.17g", row[0]);
        for (j = 0; j < NCOL; j++) {
            double v = out[k * NCOL + j];
            if ((stop >= 0 && k >= stop) || isnan(v))
                putchar(',');
            else
                printf(",%.17g", v);
        }
        for (j = 0; j < NREF; j++) {
            double v = row[1 + KF_NU + KF_M + j];
            if (!ref_any[j])
                continue;
            if (isnan(v))
                putchar(',');
            else
                printf(",%.17g", v);
        }
        putchar('\n');
    }
    if (fflush(stdout) != 0 || ferror(stdout))
        fail("cannot write the estimates to standard output");
    if (stop >= 0)
        fprintf(stderr,
                "kftune_demo: the filter stopped at step %ld (t = %.17g s), cause %d: %s\n",
                stop, data[stop * width], cause, kf_stop_reason(cause));
    free(data);
    free(out);
    return stop >= 0 ? 1 : 0;
}
"""

#: The Makefile (recipes start with a tab).
_MAKEFILE = """\
# Build the exported kftune filter's demo: make (or make CC=clang CFLAGS=...).
# make asan: the same with the address and undefined-behaviour sanitizers.
# Run it on a manoeuvre's uncompressed CSV; a dataset's files are gzipped (.csv.gz):
#     gzip -dc manoeuvre.csv.gz | ./kftune_demo > estimates.csv
CC ?= cc
CFLAGS ?= -std=c99 -O2 -Wall -Wextra -Werror -pedantic
LDLIBS ?= -lm
SOURCES = kftune_demo.c kftune_filter.c kftune_model.c
HEADERS = kftune_filter.h kftune_model.h

kftune_demo: $(SOURCES) $(HEADERS)
\t$(CC) $(CFLAGS) -o $@ $(SOURCES) $(LDLIBS)

asan: $(SOURCES) $(HEADERS)
\t$(CC) $(CFLAGS) -g -fsanitize=address,undefined -fno-sanitize-recover=all \\
\t\t-o kftune_demo_asan $(SOURCES) $(LDLIBS)

clean:
\trm -f kftune_demo kftune_demo_asan

.PHONY: asan clean
"""


def c_files(
    doc: Mapping[str, Any],
    model: StateSpaceModel,
    *,
    precision: str = "double",
    source: str = "tuned.json",
) -> dict[str, str]:
    """The files of a C export, name → text (:data:`C_FILES`).

    Args:
        doc: the export document of the tuned file (:func:`kftune.report.export.export_document`).
        model: the model it was tuned with (its ``c_code`` is the model's C).
        precision: ``kf_real``, ``"double"`` or ``"float"``.
        source: the tuned file's name, for the provenance comment.

    Raises:
        ValueError: ``model`` cannot be exported
            (:func:`kftune.models.c_contract.export_refusal`), or an unknown precision.
    """
    from kftune.models.c_contract import export_refusal, model_header

    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {list(PRECISIONS)}, got {precision!r}")
    why = export_refusal(model)
    if why is not None:
        raise ValueError(why)
    _check_document(doc, model)
    assert model.c_code is not None  # refusal says so
    code = model.c_code if model.c_code.endswith("\n") else model.c_code + "\n"
    return {
        "kftune_model.h": model_header(model, precision),
        "kftune_model.c": code,
        "kftune_filter.h": _filter_header(doc, model, source),
        "kftune_filter.c": _filter_source(model),
        "kftune_demo.c": _demo_source(model),
        "Makefile": _MAKEFILE,
    }


# --------------------------------------------------------------------------------------
# Building and running the demo, and comparing it with kftune
# --------------------------------------------------------------------------------------


def find_compiler() -> list[str] | None:
    """The C compiler command: ``$CC`` (split as a shell would) if set, else ``cc``, ``gcc``
    or ``clang`` on the PATH; None when there is none."""
    env = os.environ.get("CC", "").strip()
    if env:
        parts = shlex.split(env)
        return parts if shutil.which(parts[0]) else None
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path is not None:
            return [path]
    return None


def build_demo(
    folder: Path,
    work: Path,
    cc: Sequence[str],
    flags: Sequence[str] = CFLAGS,
    name: str = "kftune_demo",
) -> Path:
    """Compile the demo of the export in ``folder`` into ``work``/``name``.

    Raises:
        RuntimeError: the compiler failed (its messages, first 2,000 characters).
    """
    exe = work / name
    sources = [str(folder / f) for f in ("kftune_demo.c", "kftune_filter.c", "kftune_model.c")]
    res = subprocess.run(
        [*cc, *flags, "-I", str(folder), "-o", str(exe), *sources, "-lm"],
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        raise RuntimeError(
            f"{' '.join(cc)} failed to build the demo of {folder}:\n{res.stderr.strip()[:2000]}"
        )
    return exe


def manoeuvre_csv(m: Any) -> str:
    """A manoeuvre as the CSV of a kftune dataset's file: ``t`` and every channel, each
    number with %.17g (the same double read back), NaN as an empty cell."""
    names = ["t", *m.channel_names] if "t" not in m.channel_names else list(m.channel_names)
    data = np.column_stack(
        [np.asarray(m.t if c == "t" else m.channel(c), dtype=float) for c in names]
    )
    lines = [",".join(names)]
    for row in data.tolist():
        lines.append(",".join("" if math.isnan(v) else f"{v:.17g}" for v in row))
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class DemoRun:
    """One run of a demo over a manoeuvre.

    Attributes:
        columns: name → (N,) values (NaN for an empty cell), in the demo's column order.
        stop: (step, cause) where the filter stopped, or None.
        returncode: the demo's exit status; stderr: what it said.
    """

    columns: dict[str, np.ndarray]
    stop: tuple[int, int] | None
    returncode: int
    stderr: str


_STOPPED = re.compile(r"stopped at step (\d+) \(t = [^)]*\), cause (\d+)")


def run_demo(exe: Path, csv_text: str, timeout: float = 600.0) -> DemoRun:
    """Run the demo ``exe`` with ``csv_text`` on standard input and read what it writes.

    Raises:
        RuntimeError: it exited with another status than 0 (done) or 1 (stopped), or wrote
            no table (its message in the error).
    """
    res = subprocess.run(
        [str(exe)], input=csv_text, capture_output=True, text=True, timeout=timeout
    )
    if res.returncode not in (0, 1) or not res.stdout:
        raise RuntimeError(f"{exe.name} exited with {res.returncode}: {res.stderr.strip()[:500]}")
    lines = res.stdout.splitlines()
    names = lines[0].split(",")
    values = np.array(
        [[float(c) if c else math.nan for c in row.split(",")] for row in lines[1:]], dtype=float
    ).reshape(len(lines) - 1, len(names))
    found = _STOPPED.search(res.stderr)
    stop = (int(found.group(1)), int(found.group(2))) if found else None
    return DemoRun({n: values[:, i] for i, n in enumerate(names)}, stop, res.returncode, res.stderr)


def column_deviations(
    got: Mapping[str, np.ndarray], want: Mapping[str, np.ndarray]
) -> dict[str, float]:
    """The relative normwise deviation ‖got − want‖₂ / ‖want‖₂ of each column of ``want``
    (0 where both are zero): over the rows where both are finite, and ∞ where one is
    finite and the other is not (a stop at another step) or ``got`` lacks the column."""
    out: dict[str, float] = {}
    for name, w in want.items():
        g = got.get(name)
        w = np.asarray(w, dtype=float)
        if g is None or g.shape != w.shape:
            out[name] = math.inf
            continue
        fg, fw = np.isfinite(g), np.isfinite(w)
        if np.any(fg != fw):
            out[name] = math.inf
            continue
        diff = float(np.linalg.norm(g[fw] - w[fw]))
        norm = float(np.linalg.norm(w[fw]))
        out[name] = 0.0 if diff == 0.0 else (diff / norm if norm > 0 else math.inf)
    return out


#: How a float export's check measures each kind of column against the double filter
#: (:func:`float_deviations`), sample by sample.
FLOAT_MEASURES = {
    "state": "|f - d| / sigma_d (in units of the column's own standard deviation)",
    "std": "|sigma_f - sigma_d| / sigma_d (relative)",
    "innovation": "|y_f - y_d| / sqrt(R) (in units of the measurement noise)",
    "nis": "|NIS_f - NIS_d| (absolute)",
    "other": "|f - d| / rms(d) (relative to the column's size)",
}
#: The largest deviation of a float export's column from the double filter that its check
#: accepts, per kind of column (:data:`FLOAT_MEASURES`): a tenth of the column's own σ for
#: a state or β, 10 % of a σ, a tenth of √R for an innovation, 0.5 for the NIS (a χ² gate
#: moved by less than that). Chosen for what an estimate is used for, and checked against
#: the eleven float filters measured in BENCHMARKS.md ("--precision float"): nine are
#: inside, the nearest 1.7 times (σ of r where the gyro is followed tightly); the two UKFs
#: whose Vx is known to about 1e-5 of itself (q_vx at tune's lower bound 1e-10) are not,
#: and their check says so. "other" (an output without a σ column; no built-in model has one) is not
#: measured: 1e-3 of the column's RMS.
FLOAT_BOUNDS = {"state": 0.1, "std": 0.1, "innovation": 0.1, "nis": 0.5, "other": 1e-3}


def column_kind(name: str, columns: Sequence[str]) -> str:
    """The kind of the estimate column ``name`` among ``columns`` (:data:`FLOAT_MEASURES`):
    a state or output with a ``<name>_std`` column, a standard deviation, an innovation, the
    NIS, or another (an output without σ, a copied reference)."""
    if name == "nis":
        return "nis"
    if name.startswith("innovation_"):
        return "innovation"
    if name.endswith("_std") and name[: -len("_std")] in columns:
        return "std"
    if f"{name}_std" in columns:
        return "state"
    return "other"


def float_deviations(
    got: Mapping[str, np.ndarray], want: Mapping[str, np.ndarray], r_diag: Mapping[str, float]
) -> dict[str, np.ndarray]:
    """Sample by sample, how far each column of a float filter's run ``got`` is from the
    double filter's (or kftune's) ``want``, in the terms of its kind (:func:`column_kind`,
    :data:`FLOAT_MEASURES`): a state or output in units of its own standard deviation
    σ_d (the ``<name>_std`` column of ``want``), a σ relative to σ_d, an innovation in units
    of √R of its measurement (``r_diag``: measurement name → variance; √S ≥ √R, so this is
    the stricter measure), the NIS absolutely, any other column relative to its RMS.

    Returns:
        column name → (N,) deviations over the rows where both are finite (the rows where
        only one is finite are a stop at another step, which the check reports apart).
    """
    out: dict[str, np.ndarray] = {}
    names = list(want)
    for name, w in want.items():
        if name == "t" or name not in got:
            continue
        g, w = np.asarray(got[name], dtype=float), np.asarray(w, dtype=float)
        ok = np.isfinite(g) & np.isfinite(w)
        diff = np.abs(g - w)
        kind = column_kind(name, names)
        if kind == "state":
            scale = np.asarray(want[f"{name}_std"], dtype=float)
            ok &= np.isfinite(scale) & (scale > 0)
        elif kind == "std":
            scale = np.abs(w)
            ok &= scale > 0
        elif kind == "innovation":
            scale = np.full(w.shape, math.sqrt(r_diag[name[len("innovation_") :]]))
        elif kind == "nis":
            scale = np.ones(w.shape)
        else:
            rms = float(np.sqrt(np.mean(w[ok] ** 2))) if ok.any() else 0.0
            scale = np.full(w.shape, rms if rms > 0 else 1.0)
        out[name] = diff[ok] / scale[ok]
    return out


@dataclass(frozen=True)
class CheckRow:
    """How an exported filter's demo agreed with kftune on one manoeuvre.

    Attributes:
        manoeuvre: its name.
        deviation: the largest relative normwise deviation of a column from kftune's
            estimate (:func:`column_deviations`); ∞ where the two stopped at other steps.
        column: the column where it is largest.
        stop: (step, cause) where the C filter stopped, or None.
        kftune_stop: (step, cause) where kftune's stopped, or None.
        vs_double: for a float export, the largest deviation from the double export's
            demo (None otherwise).
        float_deviation: for a float export, each column's deviations from kftune's
            estimate sample by sample, in the terms of its kind (:func:`float_deviations`);
            None otherwise.
    """

    manoeuvre: str
    deviation: float
    column: str
    stop: tuple[int, int] | None
    kftune_stop: tuple[int, int] | None
    vs_double: float | None = None
    float_deviation: Mapping[str, np.ndarray] | None = None


def check_manoeuvre(
    exe: Path,
    tuned: Any,
    m: Any,
    vehicle: Any,
    double_exe: Path | None = None,
    r_diag: Mapping[str, float] | None = None,
) -> CheckRow:
    """Run the demo ``exe`` and kftune's estimate (:func:`kftune.tuning.deploy.estimate`)
    of the tuned filter ``tuned`` on the manoeuvre ``m`` and compare every column; with
    ``double_exe`` (the double export's demo of a float export) compare with it too, and
    measure each column in its own terms (:func:`float_deviations`, with ``r_diag``, the
    measurement name → R variance)."""
    from kftune.tuning.deploy import estimate

    est = estimate(tuned, m, vehicle, probe=False)
    text = manoeuvre_csv(m)
    run = run_demo(exe, text)
    dev = column_deviations(run.columns, est.columns)
    column = max(dev, key=lambda c: dev[c])
    res = est.result
    kftune_stop = (int(res.diverged_step), int(res.diverged_cause)) if res.diverged else None
    vs_double = None
    per_sample = None
    if double_exe is not None:
        other = run_demo(double_exe, text)
        vs_double = max(column_deviations(run.columns, other.columns).values())
        per_sample = float_deviations(run.columns, est.columns, r_diag or {})
    deviation = dev[column] if run.stop == kftune_stop else math.inf
    return CheckRow(m.name, deviation, column, run.stop, kftune_stop, vs_double, per_sample)


@dataclass(frozen=True)
class FloatColumn:
    """How far one column of a float export is from kftune's estimate over a check's
    manoeuvres (:func:`float_summary`).

    Attributes:
        kind: its kind (:data:`FLOAT_MEASURES`); largest, p99: the largest deviation and
            its 99th percentile over every sample, in the kind's terms; bound: the bound of
            its kind (:data:`FLOAT_BOUNDS`).
    """

    kind: str
    largest: float
    p99: float
    bound: float

    @property
    def within(self) -> bool:
        """Whether the largest deviation is within the bound."""
        return self.largest <= self.bound


def float_summary(rows: Sequence[CheckRow], columns: Sequence[str]) -> dict[str, FloatColumn]:
    """Pool the float deviations of a check's ``rows`` column by column (the estimate's
    ``columns``, to tell each column's kind); references copied from the input are left
    out (they are the input's numbers)."""
    pooled: dict[str, list[np.ndarray]] = {}
    for row in rows:
        for name, values in (row.float_deviation or {}).items():
            if not name.endswith("_ref"):
                pooled.setdefault(name, []).append(values)
    out: dict[str, FloatColumn] = {}
    for name, parts in pooled.items():
        v = np.concatenate(parts)
        kind = column_kind(name, columns)
        largest, p99 = (float(v.max()), float(np.percentile(v, 99))) if v.size else (0.0, 0.0)
        out[name] = FloatColumn(kind, largest, p99, FLOAT_BOUNDS[kind])
    return out
