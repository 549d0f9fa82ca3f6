"""Filter speed over any model: the generic UKF and EKF against the 3×3 kernel and FilterPy.

Measures, side by side in one process (medians of interleaved repeats, after compilation),
filter steps per second on the demo's 2,000-step sine steer (``kftune.cli.demo``, deep in the
Dugoff saturation), input checks included:

* ``kernel3_steps_per_s`` — the single-track model's hand-written 3×3 UKF loop, which
  ``UKF().run(SINGLE_TRACK, …)`` runs (:class:`kftune.models.ModelKernels`);
* ``ukf_steps_per_s`` — the generic UKF loop on the same model (``UKF().run`` on
  ``dataclasses.replace(SINGLE_TRACK, ukf_kernels=None)``, a model that supplies no loop);
* ``ekf_steps_per_s`` — the EKF on the same model with its analytic Jacobians, and
  ``ekf_fd_steps_per_s`` with central differences instead;
* ``filterpy_steps_per_s`` — FilterPy's ``UnscentedKalmanFilter`` given the compiled scalar
  model (as in ``benchmarks/ukf_speed.py``: the ratio measures the filter machinery);
* ``ukf6_steps_per_s`` / ``ekf6_steps_per_s`` — the generic filters on the 6-state
  ``single-track-biases`` model (13 sigma points instead of 7; same manoeuvre, biased
  sensors);
* ``batch16_1thread_*`` — 16 noise settings per call on one thread, per set: the 3×3
  loop's and the generic loop's ``UKF().run_batch`` (in threads, not the vector lanes);
* ratios: ``ukf_slowdown_vs_kernel3`` (target ≤ 1.5), ``ekf_vs_ukf`` (target ≥ 1),
  ``ukf_vs_filterpy`` and ``ekf_vs_filterpy`` (targets ≥ 100);
* ``max_rel_diff_ukf_vs_kernel3`` — the generic UKF's states against the 3×3 kernel's;
* ``compile_s_*`` — first-call time of the generic filters on a model in this process
  (numba compiles the kernels once per model and process; the helpers come from numba's
  cache after the first run on a machine).

Single runs are timed as 16 calls back to back, so that single and batch timings span similar
wall times (see ``benchmarks/ukf_speed.py``). Timing is by wall clock; on a shared machine
compare the ratios within one run, and see ``load_average_1min``.

Usage: ``.venv/bin/python benchmarks/filter_speed.py [--repeats 21] [--filterpy-repeats 3]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np

from kftune.cli.demo import DEFAULT_Q, demo_manoeuvre
from kftune.filters import EKF, UKF
from kftune.models import SINGLE_TRACK, SINGLE_TRACK_BIASES
from ukf_speed import compiled_model, filterpy_run, max_rel_diff, timed

#: Sensor biases of the 6-state runs [m/s, m/s², rad/s] and their random-walk variances.
BIASES = np.array([0.1, 0.3, 0.005])
Q_BIASES = np.array([1e-7, 1e-6, 1e-9])

#: The single-track model without its own loops: the UKF runs the generic loop on it.
GENERIC_SINGLE_TRACK = dataclasses.replace(SINGLE_TRACK, ukf_kernels=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=21, help="kernel repeats (median)")
    ap.add_argument("--filterpy-repeats", type=int, default=3, help="FilterPy repeats (median)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the manoeuvre's noise")
    args = ap.parse_args()

    man = demo_manoeuvre(args.seed)
    n = man.u.shape[0]
    q = np.array(DEFAULT_Q)
    rng = np.random.default_rng(args.seed)
    q16 = q * 10.0 ** rng.uniform(-2, 2, size=(16, 3))
    z6 = man.z + BIASES
    q6 = np.r_[q, Q_BIASES]
    common = (man.u, man.z, man.dt)
    ukf, ekf, ekf_fd = UKF(), EKF(), EKF(numerical_jacobians=True)
    p = man.params  # the demo's vehicle (the model's default, given as the 3x3 runs always were)

    def block(run_one: Callable[[int], object]) -> Callable[[], None]:
        def run16() -> None:
            for b in range(16):
                run_one(b)

        return run16

    cases: dict[str, Callable[[], object]] = {
        "kernel3": block(lambda b: ukf.run(SINGLE_TRACK, *common, q16[b], man.r_var, params=p)),
        "ukf": block(lambda b: ukf.run(GENERIC_SINGLE_TRACK, *common, q16[b], man.r_var)),
        "ekf": block(lambda b: ekf.run(SINGLE_TRACK, *common, q16[b], man.r_var)),
        "ekf_fd": block(lambda b: ekf_fd.run(SINGLE_TRACK, *common, q16[b], man.r_var)),
        "ukf6": block(lambda b: ukf.run(SINGLE_TRACK_BIASES, man.u, z6, man.dt, q6, man.r_var)),
        "ekf6": block(lambda b: ekf.run(SINGLE_TRACK_BIASES, man.u, z6, man.dt, q6, man.r_var)),
        "batch16_1thread_kernel3": lambda: ukf.run_batch(
            SINGLE_TRACK, *common, q16, man.r_var, params=p
        ),
        "batch16_1thread_ukf": lambda: ukf.run_batch(GENERIC_SINGLE_TRACK, *common, q16, man.r_var),
    }
    compile_s = {
        "ukf": timed(lambda: ukf.run(GENERIC_SINGLE_TRACK, *common, q, man.r_var)),
        "ekf": timed(lambda: ekf.run(SINGLE_TRACK, *common, q, man.r_var)),
        "ukf6": timed(lambda: ukf.run(SINGLE_TRACK_BIASES, man.u, z6, man.dt, q6, man.r_var)),
    }
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # the batches on one thread: per-set cost, not parallelism
    for fn in cases.values():
        fn()
    res3 = ukf.run(SINGLE_TRACK, *common, q, man.r_var, params=p)
    res = ukf.run(GENERIC_SINGLE_TRACK, *common, q, man.r_var)
    rel = max_rel_diff(res.x, res3.x)
    fx, hx = compiled_model(man.params.to_array())

    times: dict[str, list[float]] = {k: [] for k in (*cases, "filterpy")}
    for i in range(args.repeats):
        for name, fn in cases.items():
            times[name].append(timed(fn))
        if i < args.filterpy_repeats:  # interleaved with the kernel runs
            times["filterpy"].append(timed(lambda: filterpy_run(man, q, fx, hx)))
    numba.set_num_threads(threads)

    med = {k: statistics.median(v) for k, v in times.items()}
    sps = {k: 16 * n / med[k] for k in cases}
    sps["filterpy"] = n / med["filterpy"]
    out = {
        "kernel3_steps_per_s": sps["kernel3"],
        "ukf_steps_per_s": sps["ukf"],
        "ekf_steps_per_s": sps["ekf"],
        "ekf_fd_steps_per_s": sps["ekf_fd"],
        "filterpy_steps_per_s": sps["filterpy"],
        "ukf6_steps_per_s": sps["ukf6"],
        "ekf6_steps_per_s": sps["ekf6"],
        "batch16_1thread_kernel3_steps_per_s": sps["batch16_1thread_kernel3"],
        "batch16_1thread_ukf_steps_per_s": sps["batch16_1thread_ukf"],
        "ukf_slowdown_vs_kernel3": sps["kernel3"] / sps["ukf"],
        "ekf_vs_ukf": sps["ekf"] / sps["ukf"],
        "ukf_vs_filterpy": sps["ukf"] / sps["filterpy"],
        "ekf_vs_filterpy": sps["ekf"] / sps["filterpy"],
        "ukf6_slowdown_vs_ukf3": sps["ukf"] / sps["ukf6"],
        "max_rel_diff_ukf_vs_kernel3": rel,
        "compile_s_ukf": compile_s["ukf"],
        "compile_s_ekf": compile_s["ekf"],
        "compile_s_ukf6": compile_s["ukf6"],
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
    print(f"manoeuvre: {n} steps (demo sine steer, seed {args.seed}); steps/s, one thread")
    rows = [
        ("3x3 loop (single-track's own)", "kernel3"),
        ("generic UKF, single-track", "ukf"),
        ("EKF, single-track (analytic J)", "ekf"),
        ("EKF, single-track (central diff.)", "ekf_fd"),
        ("FilterPy UKF (compiled model)", "filterpy"),
        ("generic UKF, n = 6", "ukf6"),
        ("EKF, n = 6", "ekf6"),
        ("batch B=16: 3x3 kernel, per set", "batch16_1thread_kernel3"),
        ("batch B=16: generic UKF, per set", "batch16_1thread_ukf"),
    ]
    for label, key in rows:
        print(f"{label:36s} {sps[key]:>12,.0f}")
    print(f"generic UKF slowdown vs 3x3: {out['ukf_slowdown_vs_kernel3']:.2f}x (target <= 1.5)")
    print(f"EKF / UKF speed:             {out['ekf_vs_ukf']:.2f}x (target >= 1)")
    print(f"UKF, EKF vs FilterPy:        {out['ukf_vs_filterpy']:.0f}x, "
          f"{out['ekf_vs_filterpy']:.0f}x (target >= 100)")  # fmt: skip
    print(f"max relative difference generic UKF vs 3x3: {rel:.1e}")
    print(
        "first call (compile) [s]: "
        + ", ".join(f"{k} {v:.1f}" for k, v in compile_s.items())
        + f"; load average (1 min) at the end: {out['load_average_1min']:.2f}"
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
