"""The exported C filter's speed against kftune's compiled kernels, on the same model and
manoeuvres, in one run.

For each of the single-track UKF (kftune runs it on the model's own hand-written 3×3 loop)
and EKF (the generic kernel with the model's Jacobians), tuned by the manual rule of thumb
(``kftune tune -m manual``) and exported with ``kftune export --format c``, it measures
filter steps per second over the bundled set's 23 test manoeuvres:

* ``c_steps_per_s`` — the exported ``kf_init``/``kf_step`` compiled with ``cc -std=c99 -O2``
  (a small timing program beside the export: the manoeuvres read once, then only the steps
  are timed; no CSV in the loop);
* ``kftune_steps_per_s`` — kftune's own run of the tuned filter on the same manoeuvres
  (:meth:`kftune.tuning.runs.FilterSpec.run`, what ``kftune estimate`` calls: the input
  checks and the prepared inputs included, after compilation);
* for the UKF also ``kftune_generic_steps_per_s``, kftune's generic UKF kernel on the same
  model (the algorithm the export writes out, for any n; the model without its own loops,
  ``dataclasses.replace(model, ukf_kernels=None)``), and ``c_vs_kftune_generic``;
* ``c_vs_kftune`` — the ratio; ``max_rel_dev`` — the largest relative normwise deviation
  of the C filter's states from kftune's on these manoeuvres (a run that measured a wrong
  filter would say so).

Medians of ``--repeats`` interleaved repetitions (each repetition: all 23 manoeuvres). Wall
clock; on a shared machine compare the ratio within one run. The last line of output is one
JSON object.

Usage: ``.venv/bin/python benchmarks/c_export_speed.py [--repeats 7]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from kftune.cli import main as kftune
from kftune.data import default_dataset
from kftune.report.c_export import CFLAGS, find_compiler
from kftune.tuning.deploy import TunedFilter
from kftune.tuning.runs import filter_spec

#: The timing program: reads N, then N rows of u (KF_NU) and z (KF_M) as raw doubles per
#: manoeuvre from a file, runs every manoeuvre REPS times and prints each repetition's
#: seconds and the last run's states (for the check against kftune).
BENCH_C = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "kftune_filter.h"

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

int main(int argc, char **argv)
{
    static kf_filter kf;
    kf_estimate est;
    FILE *in = fopen(argv[1], "rb"), *states = fopen(argv[3], "wb");
    int reps = atoi(argv[2]), r, k, j;
    long total = 0, n_m = 0, n[64];
    double *data[64], dt = KF_DT, sink = 0;
    kf_real u[KF_NU_ARR], z[KF_M];
    (void)argc;
    while (n_m < 64 && fread(&n[n_m], sizeof n[0], 1, in) == 1) {
        size_t size = (size_t)n[n_m] * (KF_NU + KF_M);
        data[n_m] = malloc(size * sizeof(double));
        if (fread(data[n_m], sizeof(double), size, in) != size)
            return 2;
        total += n[n_m++];
    }
    for (r = 0; r < reps; r++) {
        double t0 = now();
        long m;
        for (m = 0; m < n_m; m++) {
            kf_init(&kf, dt);
            for (k = 0; k < n[m]; k++) {
                const double *row = data[m] + (size_t)k * (KF_NU + KF_M);
                for (j = 0; j < KF_NU; j++)
                    u[j] = row[j];
                for (j = 0; j < KF_M; j++)
                    z[j] = row[KF_NU + j];
                if (kf_step(&kf, u, z, &est) != KF_STOP_NONE)
                    return 3;
                sink += est.x[0];
                if (r == reps - 1)
                    for (j = 0; j < KF_N; j++) {
                        double v = est.x[j];
                        fwrite(&v, sizeof v, 1, states);
                    }
            }
        }
        printf("%.9f\n", now() - t0);
    }
    fclose(states);
    fprintf(stderr, "%ld steps per repetition (checksum %g)\n", total, sink);
    return 0;
}
"""


def c_rate(folder: Path, manoeuvres: list, spec, reps: int, cc: list[str]) -> tuple:
    """(seconds of each repetition, (N_total, n) states of the last) of the C filter."""
    model = spec.model
    raw, exe = folder / "inputs.bin", folder / "bench"
    if not exe.exists():  # the inputs and the program once per export
        with raw.open("wb") as fh:
            for m in manoeuvres:
                u, z = spec.inputs(m)
                rows = np.column_stack([a for a in (u, z) if a is not None]).astype(np.float64)
                fh.write(np.int64(len(rows)).tobytes())
                fh.write(np.ascontiguousarray(rows).tobytes())
        (folder / "bench.c").write_text(BENCH_C)
        sources = [str(folder / f) for f in ("bench.c", "kftune_filter.c", "kftune_model.c")]
        subprocess.run([*cc, *CFLAGS, "-o", str(exe), *sources, "-lm"], check=True)
    res = subprocess.run(
        [str(exe), str(raw), str(reps), str(folder / "states.bin")],
        capture_output=True,
        text=True,
        check=True,
    )
    seconds = [float(v) for v in res.stdout.split()]
    states = np.fromfile(folder / "states.bin").reshape(-1, model.n_states)
    return seconds, states


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7, help="repetitions (median)")
    args = ap.parse_args()
    cc = find_compiler()
    if cc is None:
        raise SystemExit("no C compiler (CC, cc, gcc or clang): nothing to measure")
    cc_version = subprocess.run([*cc, "--version"], capture_output=True, text=True).stdout
    ds = default_dataset()
    manoeuvres = list(ds.test)
    steps = sum(m.n for m in manoeuvres)
    out: dict = {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "cc": cc_version.splitlines()[0] if cc_version else " ".join(cc),
        "cflags": " ".join(CFLAGS),
        "manoeuvres": len(manoeuvres),
        "steps": steps,
        "repeats": args.repeats,
    }
    with tempfile.TemporaryDirectory(prefix="kftune-c-speed-") as tmp:
        work = Path(tmp)
        ukf = work / "tuned-ukf.json"
        assert kftune(["tune", "-m", "manual", "-q", "-o", str(ukf)]) == 0
        doc = json.loads(ukf.read_text())
        doc["filter"] = doc["deployment"]["filter"] = "ekf"
        doc["deployment"]["sigma_points"] = None
        (work / "tuned-ekf.json").write_text(json.dumps(doc))
        for filt in ("ukf", "ekf"):
            params = work / f"tuned-{filt}.json"
            folder = work / f"c-{filt}"
            assert kftune(["export", str(params), "-f", "c", "-o", str(folder)]) == 0
            tuned = TunedFilter.from_document(json.loads(params.read_text()), str(params))
            spec = filter_spec(tuned.model, tuned.filter, ds.vehicle)
            p = tuned.params_of(spec.model, spec.params)

            def kftune_run(spec=spec, tuned=tuned, p=p) -> list:
                return [
                    spec.run(m, tuned.q, tuned.r, tuned.settings, params=p).x for m in manoeuvres
                ]

            # the model's own 3×3 loop (the single-track UKF's) against the generic kernel
            own_loop = filt == "ukf" and spec.model.ukf_kernels is not None
            generic_model = dataclasses.replace(spec.model, ukf_kernels=None)

            def generic_run(spec=spec, tuned=tuned, p=p, model=generic_model) -> list:
                """The generic kernel (the single-track UKF's other way in kftune)."""
                runner = spec.filter_object(tuned.settings)
                return [
                    runner.run(model, *spec.inputs(m), m.dt, tuned.q, tuned.r, params=p).x
                    for m in manoeuvres
                ]

            want = np.vstack(kftune_run())  # compiles the kernels
            also_generic = own_loop
            if also_generic:
                generic_run()
            c_times, k_times, g_times = [], [], []
            states = None
            for _ in range(args.repeats):  # interleaved: one C batch, one kftune repetition
                secs, states = c_rate(folder, manoeuvres, spec, 1, cc)
                c_times += secs
                t0 = time.perf_counter()
                kftune_run()
                k_times.append(time.perf_counter() - t0)
                if also_generic:
                    t0 = time.perf_counter()
                    generic_run()
                    g_times.append(time.perf_counter() - t0)
            dev = max(
                float(np.linalg.norm(states[:, j] - want[:, j]) / np.linalg.norm(want[:, j]))
                for j in range(want.shape[1])
            )
            c_rate_ = steps / statistics.median(c_times)
            k_rate = steps / statistics.median(k_times)
            out[filt] = {
                "kftune_kernel": "3x3 (the model's own)" if own_loop else "generic",
                "c_steps_per_s": round(c_rate_),
                "kftune_steps_per_s": round(k_rate),
                "c_vs_kftune": round(c_rate_ / k_rate, 3),
                "max_rel_dev": dev,
            }
            if also_generic:
                g_rate = steps / statistics.median(g_times)
                out[filt]["kftune_generic_steps_per_s"] = round(g_rate)
                out[filt]["c_vs_kftune_generic"] = round(c_rate_ / g_rate, 3)
            print(
                f"{filt}: C {c_rate_:,.0f} steps/s, kftune ({out[filt]['kftune_kernel']}) "
                f"{k_rate:,.0f} steps/s, ratio {c_rate_ / k_rate:.2f}, states within {dev:.1e}"
            )
    out["load_average_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
