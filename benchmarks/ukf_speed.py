"""UKF speed: the single-track model's compiled 3×3 UKF loop against FilterPy on the same
manoeuvre and model.

Measures, side by side in one process (medians of interleaved repeats, after compilation):

* ``steps_per_s`` — filter steps per second of single ``UKF().run(SINGLE_TRACK, …)`` calls
  (:class:`kftune.filters.UKF`, which runs the model's own single-threaded 3×3 loop),
  input checks included, timed as 16 calls back to back (the 16 noise settings of the
  batch) so that single and batch timings span similar wall times — on a machine
  shared with other jobs a 1 ms call otherwise escapes the scheduler's sharing that a
  30 ms one sees;
* ``filterpy_steps_per_s`` — FilterPy's ``UnscentedKalmanFilter`` with
  ``MerweScaledSigmaPoints``, given the *compiled* scalar model as f and h, so that the
  ratio measures the filter machinery, not the model code (the faster, fairer of the two
  FilterPy variants); ``filterpy_numpy_model_steps_per_s`` gives FilterPy the readable
  numpy model instead;
* ``speedup`` = steps_per_s / filterpy_steps_per_s;
* ``batch16_steps_per_s`` — filter steps per second of ``UKF().run_batch`` with B = 16
  noise settings (16·N steps per call, numba threads over B), and the same with one thread;
* ``max_rel_diff`` — max over the three states of max_k |x_kernel − x_FilterPy| /
  max_k |x_FilterPy|, over both FilterPy variants;
* ``cost8_ms`` — wall time of eight single-run calls of 2,500 steps (20,000 steps, the
  size of one tuning-cost evaluation), input checks included.

The manoeuvre is the demo's 2,000-step sine steer (``kftune.cli.demo.demo_manoeuvre``),
which drives both axles into the Dugoff saturation.

Usage: ``.venv/bin/python benchmarks/ukf_speed.py [--repeats 31] [--filterpy-repeats 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import UKF, UKFSettings
from kftune.models import SINGLE_TRACK
from kftune.models.sideslip import single_track_prior
from kftune.vehicle import measure, step_rk4
from kftune.vehicle.single_track import measure_scalar, rk4_scalar, step_context_scalar


def filterpy_run(man, q, fx: Callable, hx: Callable) -> np.ndarray:
    """FilterPy with the time convention of kftune's filters (see tests/test_ukf.py)."""
    s = UKFSettings()
    points = MerweScaledSigmaPoints(3, alpha=s.alpha, beta=s.beta, kappa=s.kappa)
    ukf = UnscentedKalmanFilter(dim_x=3, dim_z=3, dt=man.dt, fx=fx, hx=hx, points=points)
    x0, P0 = single_track_prior(man.z[0], man.r_var, np.empty(0))  # the UKF's default prior
    ukf.x, ukf.P, ukf.Q, ukf.R = x0.copy(), P0.copy(), np.diag(q), np.diag(man.r_var)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
    xs = np.empty((man.u.shape[0], 3))
    for k in range(man.u.shape[0]):
        if k > 0:
            ukf.predict(u=man.u[k - 1])
        ukf.update(man.z[k], u=man.u[k])
        xs[k] = ukf.x
    return xs


def compiled_model(p: np.ndarray) -> tuple[Callable, Callable]:
    """f and h for FilterPy built on the kernel's compiled scalar model."""

    def fx(x, dt, u):
        tan_d, cos_d, fzf, fzr = step_context_scalar(u[0], u[1], p)
        return np.array(rk4_scalar(x[0], x[1], x[2], tan_d, cos_d, u[1], fzf, fzr, p, dt))

    def hx(x, u):
        return np.array(measure_scalar(x[0], x[1], x[2], *step_context_scalar(u[0], u[1], p), p))

    return fx, hx


def numpy_model(p: np.ndarray) -> tuple[Callable, Callable]:
    """f and h for FilterPy from the readable numpy model (as in tests/test_ukf.py)."""
    return (lambda x, dt, u: step_rk4(x, u, p, dt)), (lambda x, u: measure(x, u, p))


def max_rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.max(np.abs(a - b), axis=0) / np.max(np.abs(b), axis=0)))


def timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=31, help="kernel repeats (median)")
    ap.add_argument("--filterpy-repeats", type=int, default=3, help="FilterPy repeats (median)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the manoeuvre's noise")
    args = ap.parse_args()

    man = demo_manoeuvre(args.seed)
    n = man.u.shape[0]
    p = man.params.to_array()
    q = np.array(DEFAULT_Q)
    rng = np.random.default_rng(args.seed)
    q16 = q * 10.0 ** rng.uniform(-2, 2, size=(16, 3))
    cost_u = [np.tile(man.u, (2, 1))[:2500]] * 8  # 8 × 2,500 = 20,000 steps
    cost_z = [np.tile(man.z, (2, 1))[:2500]] * 8
    ukf = UKF()

    def run(u, z, q_b):  # one run of the model's 3×3 loop
        return ukf.run(SINGLE_TRACK, u, z, man.dt, q_b, man.r_var, params=man.params)

    def single():
        return run(man.u, man.z, q)

    def singles16():  # 16 single runs back to back: a block as long as the batch's
        for b in range(16):
            run(man.u, man.z, q16[b])

    def batch():  # the 3×3 loop in numba threads over the 16 settings
        return ukf.run_batch(SINGLE_TRACK, man.u, man.z, man.dt, q16, man.r_var, params=man.params)

    def cost8():
        for u, z in zip(cost_u, cost_z):
            run(u, z, q)

    # compile / load caches, and the accuracy check
    res = single()
    batch()
    fx_c, hx_c = compiled_model(p)
    fx_n, hx_n = numpy_model(p)
    rel = max(
        max_rel_diff(res.x, filterpy_run(man, q, fx_c, hx_c)),
        max_rel_diff(res.x, filterpy_run(man, q, fx_n, hx_n)),
    )

    threads = numba.get_num_threads()
    t_single, t_batch, t_batch1, t_cost, t_fp, t_fpn = [], [], [], [], [], []
    for i in range(args.repeats):
        t_single.append(timed(singles16))
        numba.set_num_threads(threads)
        t_batch.append(timed(batch))
        numba.set_num_threads(1)
        t_batch1.append(timed(batch))
        numba.set_num_threads(threads)
        t_cost.append(timed(cost8))
        if i < args.filterpy_repeats:  # interleaved with the kernel runs
            t_fp.append(timed(lambda: filterpy_run(man, q, fx_c, hx_c)))
            t_fpn.append(timed(lambda: filterpy_run(man, q, fx_n, hx_n)))

    med = statistics.median
    out = {
        "steps_per_s": 16 * n / med(t_single),
        "filterpy_steps_per_s": n / med(t_fp),
        "filterpy_numpy_model_steps_per_s": n / med(t_fpn),
        "speedup": 16 * med(t_fp) / med(t_single),
        "speedup_vs_filterpy_numpy_model": 16 * med(t_fpn) / med(t_single),
        "batch16_steps_per_s": 16 * n / med(t_batch),
        "batch16_1thread_steps_per_s": 16 * n / med(t_batch1),
        "batch_per_set_vs_single": med(t_single) / med(t_batch),
        "numba_threads": threads,
        "cost8_ms": 1e3 * med(t_cost),
        "max_rel_diff": rel,
        "steps": n,
        "repeats": args.repeats,
        "filterpy_repeats": args.filterpy_repeats,
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "cpus": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "python": platform.python_version(),
        "numba": numba.__version__,
    }
    print(f"manoeuvre: {n} steps (demo sine steer, seed {args.seed})")
    print(f"kernel, single run:         {out['steps_per_s']:>12,.0f} steps/s")
    print(f"FilterPy, compiled model:   {out['filterpy_steps_per_s']:>12,.0f} steps/s")
    print(f"FilterPy, numpy model:      {out['filterpy_numpy_model_steps_per_s']:>12,.0f} steps/s")
    print(f"speedup vs FilterPy:        {out['speedup']:>12,.0f} x")
    print(f"batch B=16, {threads} threads:     {out['batch16_steps_per_s']:>12,.0f} steps/s")
    print(f"batch B=16, 1 thread:       {out['batch16_1thread_steps_per_s']:>12,.0f} steps/s")
    print(f"cost-sized call (8 x 2500): {out['cost8_ms']:>12.2f} ms")
    print(f"max relative difference to FilterPy: {rel:.2e}")
    print(
        f"load average (1 min) at the end: {out['load_average_1min']:.2f} on {os.cpu_count()} CPUs"
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
