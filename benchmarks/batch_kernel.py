"""Throughput per parameter set of the vectorised batch UKF kernel against the single run.

    NUMBA_NUM_THREADS=1 taskset -c 0 python benchmarks/batch_kernel.py [--repeats 15]

For B = 1, 2, 4, 8, 16 noise settings (Q diagonals drawn log-uniformly around the demo's
Q, all stable) over one bundled manoeuvre, side by side in one run: B sequential calls of
``run_ukf`` (the 3×3 kernel) against one call of ``run_ukf_simd`` (the sets across the
vector lanes, one core). Interleaved repeats, medians. Throughput = filter steps per second
per parameter set; speed-up = single time / batch time for the same B sets. B = 1 in
``run_ukf_simd`` dispatches to the single kernel, so its row measures only the wrapper;
the raw SIMD kernel at B = 1 (padded to 8 lanes) is printed as ``simd_b1_raw``. Prints
figures and, as the last line, one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from kftune.cli.demo import DEFAULT_Q
from kftune.data import default_dataset
from kftune.filters import _soa_kernel as soa
from kftune.filters import run_ukf, run_ukf_simd
from kftune.filters.ukf import UKFSettings, _check_batch, _weights
from kftune.report.provenance import machine

SIZES = (1, 2, 4, 8, 16)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    ds = default_dataset()
    m = max(ds.train, key=lambda m: m.n)
    rng = np.random.default_rng(args.seed)
    q_all = np.array(DEFAULT_Q) * 10.0 ** rng.uniform(-2, 1, size=(max(SIZES), 3))
    r = ds.r_default
    t0 = time.perf_counter()
    soa.ensure_compiled()
    compile_s = time.perf_counter() - t0
    run_ukf(m.u, m.z, m.dt, ds.vehicle, q_all[0], r)  # compile / load the single kernel
    # raw SIMD kernel at B = 1 (the wrapper would dispatch to run_ukf)
    mp, u, z, dt, q1, r1, x1, p1 = _check_batch(
        m.u, m.z, m.dt, ds.vehicle, q_all[:1], r, None, None
    )
    w = _weights(UKFSettings())

    def raw_b1() -> None:
        outs = [np.empty((1, m.n, 3)) for _ in range(4)] + [np.empty((1, m.n))]
        ints = [np.zeros(1, dtype=np.int64) for _ in range(3)]
        soa.run_kernel_soa(mp, u, z, dt, q1, r1, x1, p1, *w, *outs, *ints)

    rows = []
    print(f"manoeuvre {m.name}: {m.n} steps; {args.repeats} repeats, medians")
    print(f"{'B':>3} {'single [ms]':>12} {'batch [ms]':>11} {'steps/s/set single':>19} "
          f"{'steps/s/set batch':>18} {'speed-up':>9}")  # fmt: skip
    for b in SIZES:
        q = q_all[:b]
        run_ukf_simd(m.u, m.z, m.dt, ds.vehicle, q, r)
        ts, tb = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            for i in range(b):
                run_ukf(m.u, m.z, m.dt, ds.vehicle, q[i], r)
            ts.append(time.perf_counter() - t)
            t = time.perf_counter()
            run_ukf_simd(m.u, m.z, m.dt, ds.vehicle, q, r)
            tb.append(time.perf_counter() - t)
        s, bt = float(np.median(ts)), float(np.median(tb))
        row = {
            "B": b,
            "single_s": s,
            "batch_s": bt,
            "steps_per_s_per_set_single": m.n * b / s,
            "steps_per_s_per_set_batch": m.n * b / bt,
            "speedup": s / bt,
        }
        rows.append(row)
        single_rate = row["steps_per_s_per_set_single"]
        batch_rate = row["steps_per_s_per_set_batch"]
        print(f"{b:>3} {s * 1e3:>12.2f} {bt * 1e3:>11.2f} {single_rate:>19.3g} "
              f"{batch_rate:>18.3g} {row['speedup']:>9.2f}")  # fmt: skip
    raw = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        raw_b1()
        raw.append(time.perf_counter() - t)
    raw_s = float(np.median(raw))
    print(f"raw SIMD kernel at B = 1 (8 lanes, 7 idle): {raw_s * 1e3:.2f} ms "
          f"({rows[0]['single_s'] / raw_s:.2f}x the single run)")  # fmt: skip
    print(f"first use: kernel compiled or loaded from cache in {compile_s:.1f} s")
    out = {
        "benchmark": "batch_kernel",
        "manoeuvre": m.name,
        "steps": m.n,
        "repeats": args.repeats,
        "numba_num_threads": os.environ.get("NUMBA_NUM_THREADS"),
        "machine": machine(),
        "rows": rows,
        "simd_b1_raw_s": raw_s,
        "speedup_at_8": next(r["speedup"] for r in rows if r["B"] == 8),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
