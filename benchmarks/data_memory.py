"""Memory of loading a long recording: peak memory against the size of the arrays kept.

Writes, in a temporary folder, a kftune dataset with one long manoeuvre (a weaving drive at
100 Hz that passes every validation check; values with 2–7 decimals, as a logger writes
them) as ``.csv`` and as ``.csv.gz``, and loads each with :func:`kftune.data.load_dataset`
in a fresh child process, which reports:

* ``kept_mb`` — the float64 arrays of the loaded dataset (rows × 7 channels × 8 bytes);
* ``rss_peak_mb`` — the child's peak resident memory (``ru_maxrss``) above what it held
  after its imports, i.e. what loading added;
* ``traced_peak_mb`` — the peak of the memory Python and NumPy allocated during the load
  (``tracemalloc``; NumPy reports its array buffers to it);
* ``rss_ratio`` / ``traced_ratio`` — those peaks divided by ``kept_mb`` (target ≤ 3);
* ``load_s`` — wall time of the load (validation included); ``file_mb`` — size on disk.

Usage::

    .venv/bin/python benchmarks/data_memory.py                 # 1 M rows (~20 s a format)
    .venv/bin/python benchmarks/data_memory.py --rows 36000000 # 100 h at 100 Hz (minutes)
    .venv/bin/python benchmarks/data_memory.py --rows 200000 --formats csv

The last line of the output is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHANNELS = ("t", "delta", "ax", "ay", "r", "vx", "beta_ref")
#: printf formats of the columns (decimals of the bundled dataset's storage).
FORMATS = ("%.2f", "%.7f", "%.2f", "%.2f", "%.6f", "%.4f", "%.6f")
DT = 0.01

MANIFEST = """format = "kftune-dataset"
format_version = 1
name = "long"
dt = 0.01
vehicle = "bmw-320i"

[[manoeuvres]]
name = "long"
kind = "segment"
split = "train"
file = "{file}"
"""

CHILD = """
import json, resource, sys, time, tracemalloc
from kftune.data import load_dataset
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tracemalloc.start()
start = time.perf_counter()
ds = load_dataset(sys.argv[1])
elapsed = time.perf_counter() - start
_, traced = tracemalloc.get_traced_memory()
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
kept = sum(m.channel(c).nbytes for m in ds.manoeuvres for c in m.channel_names)
print(json.dumps({"kept": kept, "rss_kb": peak - base, "traced": traced, "load_s": elapsed,
                  "rows": sum(m.n for m in ds.manoeuvres)}))
"""


def write_rows(fh, rows: int, chunk: int = 1_000_000) -> None:
    """A weaving drive at 20 m/s: ay = vx·r, small β, a little noise (as the tests' data)."""
    fh.write((",".join(CHANNELS) + "\n").encode())
    rng = np.random.default_rng(0)
    for start in range(0, rows, chunk):
        k = np.arange(start, min(rows, start + chunk))
        t = k * DT
        vx = 20.0 + 0.5 * np.sin(0.3 * t)
        r = 0.3 * np.sin(1.5 * t)
        n = k.size
        cols = np.column_stack(
            [
                t,
                0.05 * np.sin(1.5 * t + 0.1),
                0.15 * np.cos(0.3 * t) + 0.05 * rng.standard_normal(n),
                vx * r + 0.05 * rng.standard_normal(n),
                r + 0.002 * rng.standard_normal(n),
                vx + 0.02 * rng.standard_normal(n),
                -0.02 * np.sin(1.5 * t - 0.2),
            ]
        )
        np.savetxt(fh, cols, fmt=FORMATS, delimiter=",")


def make_dataset(folder: Path, fmt: str, rows: int, csv: Path | None) -> Path:
    """A dataset folder with one manoeuvre file; the ``.csv.gz`` compresses ``csv`` when
    given (so its numbers are formatted once)."""
    folder.mkdir(parents=True)
    file = folder / f"long.{fmt}"
    if fmt == "csv.gz":
        with gzip.open(file, "wb", compresslevel=1) as fh:
            if csv is not None:
                with open(csv, "rb") as src:
                    shutil.copyfileobj(src, fh, 2**20)
            else:
                write_rows(fh, rows)
    else:
        with open(file, "wb") as fh:
            write_rows(fh, rows)
    (folder / "manifest.toml").write_text(MANIFEST.format(file=file.name))
    return file


def measure(folder: Path) -> dict:
    env = dict(os.environ)
    src = Path(__file__).resolve().parents[1] / "src"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(src), env.get("PYTHONPATH")]))
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(folder)],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if out.returncode != 0:
        raise SystemExit(f"loading {folder} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=1_000_000, help="samples (default 1 M)")
    parser.add_argument(
        "--formats", nargs="+", default=["csv", "csv.gz"], choices=["csv", "csv.gz"]
    )
    parser.add_argument(
        "--dir", type=Path, default=None, help="where to write (default: a temp dir)"
    )
    args = parser.parse_args()
    results: dict = {"rows": args.rows, "python": platform.python_version(), "formats": {}}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        csv = None
        for fmt in args.formats:
            start = time.perf_counter()
            path = make_dataset(Path(tmp) / fmt.replace(".", "_"), fmt, args.rows, csv)
            csv = path if fmt == "csv" else csv
            written = time.perf_counter() - start
            m = measure(path.parent)
            kept_mb = m["kept"] / 2**20
            row = {
                "file_mb": round(path.stat().st_size / 2**20, 1),
                "kept_mb": round(kept_mb, 1),
                "rss_peak_mb": round(m["rss_kb"] / 2**10, 1),
                "traced_peak_mb": round(m["traced"] / 2**20, 1),
                "rss_ratio": round(m["rss_kb"] / 2**10 / kept_mb, 2),
                "traced_ratio": round(m["traced"] / 2**20 / kept_mb, 2),
                "load_s": round(m["load_s"], 1),
                "write_s": round(written, 1),
            }
            assert m["rows"] == args.rows, m
            results["formats"][fmt] = row
            print(
                f"{fmt:7s} {args.rows:,} rows: file {row['file_mb']} MB, kept {row['kept_mb']} MB, "
                f"peak RSS +{row['rss_peak_mb']} MB ({row['rss_ratio']}×), traced peak "
                f"{row['traced_peak_mb']} MB ({row['traced_ratio']}×), load {row['load_s']} s",
                flush=True,
            )
            if fmt != "csv":
                path.unlink()
    print(json.dumps(results))


if __name__ == "__main__":
    main()
