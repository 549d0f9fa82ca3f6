"""Per-set throughput of the single-track model's vector-lane UKF loop against its single run.

    NUMBA_NUM_THREADS=1 taskset -c 0 python benchmarks/batch_kernel.py [--repeats 15]

For B = 1, 2, 4, 8, 16 noise settings (Q diagonals drawn log-uniformly around the demo's
Q, all stable) over one bundled manoeuvre, side by side in one run: B sequential calls of
``UKF().run(SINGLE_TRACK, …)`` (the model's 3×3 loop,
:mod:`kftune.models._sideslip_ukf`) against one call of
``UKF().run_batch(SINGLE_TRACK, …, lanes=True)`` (the sets across the vector lanes of one
core, :mod:`kftune.models._sideslip_lanes`). Interleaved repeats, medians. Throughput =
filter steps per second per parameter set; speed-up = single time / batch time for the
same B sets. B = 1 in ``run_batch`` dispatches to the single loop, so its row measures only
the wrapper; the raw lane loop at B = 1 (padded to 8 lanes) is printed as ``simd_b1_raw``.
Prints figures and, as the last line, one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np

from kftune.cli.demo import DEFAULT_Q
from kftune.data import default_dataset
from kftune.filters import UKF, UKFSettings, merwe_weights
from kftune.models import SINGLE_TRACK
from kftune.models import _sideslip_lanes as soa
from kftune.models.kernel_io import KernelData, KernelOutputs, SigmaWeights
from kftune.models.sideslip import single_track_prior
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
    ukf = UKF()

    def single(q_b: np.ndarray) -> None:  # the model's 3×3 loop
        ukf.run(SINGLE_TRACK, m.u, m.z, m.dt, q_b, r, params=ds.vehicle)

    def lanes(q: np.ndarray) -> None:  # the vector lanes (B = 1: the 3×3 loop)
        ukf.run_batch(SINGLE_TRACK, m.u, m.z, m.dt, q, r, params=ds.vehicle, lanes=True)

    single(q_all[0])  # compile / load the single loop
    # the raw lane loop at B = 1 (run_batch would dispatch to the 3×3 loop), on the data
    # the UKF would give it: prepared inputs, default prior, 0.5 s runaway hold; writable
    # C-ordered copies, the argument types ensure_compiled compiled the loop for (other
    # types would compile another specialisation, inside the timing)
    p = np.array(SINGLE_TRACK.params_vector(ds.vehicle))
    r1 = np.array([r], dtype=float)
    x1, p1 = single_track_prior(m.z[0], r1[0], p)
    data = KernelData(
        np.array(SINGLE_TRACK.prepared_inputs(m.u, p)), np.array(m.z), p, float(m.dt),
        np.array(q_all[:1]), r1, np.array([x1]), np.array([p1]), max(1, int(0.5 / m.dt + 0.5)),
        np.array(SINGLE_TRACK.held_causes, dtype=np.int64),
    )  # fmt: skip
    wm, wc = merwe_weights(3, UKFSettings())
    w = SigmaWeights(float(wm[0]), float(wc[0]), float(wm[1]), math.sqrt(3 + UKFSettings().lam(3)))

    def raw_b1() -> None:
        outs = KernelOutputs.empty(m.n, 3, 3, batch=1)
        ints = [np.zeros(1, dtype=np.int64) for _ in range(3)]
        soa.run_kernel_soa(data, w, outs, *ints)

    rows = []
    print(f"manoeuvre {m.name}: {m.n} steps; {args.repeats} repeats, medians")
    print(f"{'B':>3} {'single [ms]':>12} {'batch [ms]':>11} {'steps/s/set single':>19} "
          f"{'steps/s/set batch':>18} {'speed-up':>9}")  # fmt: skip
    for b in SIZES:
        q = q_all[:b]
        lanes(q)
        ts, tb = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            for i in range(b):
                single(q[i])
            ts.append(time.perf_counter() - t)
            t = time.perf_counter()
            lanes(q)
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
    raw_b1()  # (loaded with the loop: no compilation in the timing)
    raw = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        raw_b1()
        raw.append(time.perf_counter() - t)
    raw_s = float(np.median(raw))
    print(f"raw lane loop at B = 1 (8 lanes, 7 idle): {raw_s * 1e3:.2f} ms "
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
