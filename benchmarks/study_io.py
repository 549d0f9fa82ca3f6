"""What a study costs per evaluation, against the evaluation itself.

Runs ``kftune.minimize`` with random search (whose proposals cost microseconds) on the
paper's cost over the bundled training set, ``--n`` evaluations without a study and
``--n`` with one, alternately ``--repeats`` times, and reports per evaluation: the median
evaluation time, and the extra wall time a study adds (its two commits, and the checkpoint
after each result that keeps the ``.db`` file self-contained). The disk's ``fsync``
latency is measured too: a checkpoint is two or three of them, so it sets the cost.

Run it with ``PYTHONPATH`` pointing at another checkout to measure that one's studies.

Usage: python benchmarks/study_io.py [--n 100] [--repeats 3] [--dir DIR]
Last line: one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from kftune.data import default_dataset
from kftune.optim import minimize
from kftune.tuning.problem import TuningProblem


def fsync_latency(folder: Path, n: int = 30) -> float:
    """Median time [s] of writing 4 KiB and ``fsync``-ing it, in ``folder``."""
    times = []
    path = folder / "fsync-probe.bin"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        for _ in range(n):
            os.pwrite(fd, b"x" * 4096, 0)
            t0 = time.perf_counter()
            os.fsync(fd)
            times.append(time.perf_counter() - t0)
    finally:
        os.close(fd)
        path.unlink()
    return statistics.median(times)


def run(problem: TuningProblem, n: int, storage: Path | None) -> tuple[float, float]:
    """(wall time [s], median evaluation time [s]) of one random-search run."""
    t0 = time.perf_counter()
    res = minimize(problem, problem.space, "random", budget=n, seed=0, storage=storage)
    wall = time.perf_counter() - t0
    return wall, statistics.median(r.t_eval for r in res.history)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100, help="evaluations per run (default 100)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each kind (default 3)")
    ap.add_argument("--dir", type=Path, default=None, help="folder of the study files")
    args = ap.parse_args()

    ds = default_dataset()
    problem = TuningProblem(ds.train, ds.vehicle, ds.r_default)
    problem(problem.space.from_unit([0.5] * problem.space.dim))  # load the compiled kernel
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        folder = Path(tmp)
        plain, stored, evals = [], [], []
        for k in range(args.repeats):
            wall, t_eval = run(problem, args.n, None)
            plain.append(wall / args.n)
            evals.append(t_eval)
            wall, t_eval = run(problem, args.n, folder / f"s{k}.db")
            stored.append(wall / args.n)
            evals.append(t_eval)
        fsync = fsync_latency(folder)
    t_eval = statistics.median(evals)
    overhead = statistics.median(stored) - statistics.median(plain)
    print(f"evaluation (bundled training set, 8 manoeuvres): {t_eval * 1e3:.2f} ms (median)")
    print(f"wall per evaluation without a study: {statistics.median(plain) * 1e3:.2f} ms")
    print(f"wall per evaluation with a study:    {statistics.median(stored) * 1e3:.2f} ms")
    print(
        f"study overhead per evaluation: {overhead * 1e3:.2f} ms "
        f"({100 * overhead / t_eval:.0f} % of an evaluation)"
    )
    print(f"fsync of 4 KiB on this disk: {fsync * 1e3:.2f} ms (median)")
    summary = {
        "n": args.n,
        "repeats": args.repeats,
        "t_eval_ms": round(t_eval * 1e3, 3),
        "wall_plain_ms": round(statistics.median(plain) * 1e3, 3),
        "wall_study_ms": round(statistics.median(stored) * 1e3, 3),
        "overhead_ms": round(overhead * 1e3, 3),
        "overhead_share": round(overhead / t_eval, 4),
        "fsync_ms": round(fsync * 1e3, 3),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
