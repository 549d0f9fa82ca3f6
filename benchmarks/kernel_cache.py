"""How long a new process takes to run a model's generic filter, with and without the kernel
cache (:mod:`kftune.filters._compiled`).

For each model and filter, three fresh Python processes run the filter once over the
bundled set's first training manoeuvre: the first with an empty cache folder (it compiles
and writes the cache), the second and third with that folder (they load it). Each process
reports its own time from the model's loading to the end of the run, so Python's and
numba's start-up are not in it. Prints a table; the last line is one JSON object.

    python benchmarks/kernel_cache.py [--models single-track ctrv examples/linear_bicycle.py]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = """
import json, sys, time
import numpy as np
from kftune.data import default_dataset
from kftune.filters import get_filter
from kftune.models import resolve_model
from kftune.models.user import is_model_file, load_model

ds = default_dataset()
m = ds.train[0]
t0 = time.perf_counter()
model = load_model(sys.argv[1]) if is_model_file(sys.argv[1]) else resolve_model(sys.argv[1])
if not all(m.has(c) for c in (*model.input_names, *model.measurement_names)):
    rng = np.random.default_rng(0)
    u = rng.standard_normal((m.n, model.n_inputs)) if model.n_inputs else None
    z = np.cumsum(rng.standard_normal((m.n, model.n_measurements)), axis=0)
else:
    u = np.column_stack([m.channel(c) for c in model.input_names]) if model.input_names else None
    z = np.column_stack([m.channel(c) for c in model.measurement_names])
q, r = np.full(model.n_states, 1e-4), np.full(model.n_measurements, 1e-2)
params = model.params_vector(ds.vehicle) if model.needs_vehicle else None
get_filter(sys.argv[2]).run(model, u, z, m.dt, q, r, params=params)
print(json.dumps({"seconds": time.perf_counter() - t0}))
"""


def run(model: str, filt: str, cache: str) -> float:
    env = {**os.environ, "KFTUNE_CACHE_DIR": cache}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, model, filt], capture_output=True, text=True, env=env
    )
    if out.returncode != 0:
        raise SystemExit(f"{model} {filt}: {out.stderr[-1000:]}")
    return float(json.loads(out.stdout.strip().splitlines()[-1])["seconds"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--models",
        nargs="+",
        default=["single-track-ay-bias", "ctrv", str(Path("examples") / "linear_bicycle.py")],
    )
    ap.add_argument("--filters", nargs="+", default=["ukf", "ekf"])
    args = ap.parse_args()
    rows = []
    print(f"{'model':<28} {'filter':<6} {'cold [s]':>9} {'warm [s]':>9} {'ratio':>7}")
    for model in args.models:
        for filt in args.filters:
            with tempfile.TemporaryDirectory() as cache:
                cold = run(model, filt, cache)
                warm = sorted(run(model, filt, cache) for _ in range(2))[0]
            rows.append({"model": model, "filter": filt, "cold_s": cold, "warm_s": warm})
            print(f"{model:<28} {filt:<6} {cold:9.2f} {warm:9.2f} {cold / warm:7.1f}")
    print(json.dumps({"benchmark": "kernel_cache", "rows": rows}))


if __name__ == "__main__":
    main()
