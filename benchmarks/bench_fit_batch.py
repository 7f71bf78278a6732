"""A batch of independent systems fitted at once (`jaxdyn.fit_batch`) against the same fits
one after another (`jaxdyn.fit` in a loop), with default options.

Run: python benchmarks/bench_fit_batch.py            (about 3 minutes on two cores)
     python benchmarks/bench_fit_batch.py --sizes 8 32

Problem: B damped oscillators m ẍ + c ẋ + k x = 0 of one model (m = 1 known), each with its
own stiffness k ∈ [2, 6] and damping c ∈ [0.2, 0.8] (seeded), x measured from x0 = 1 at rest,
101 samples over 10 s, data from SciPy's `solve_ivp` (DOP853 at 1e-12) on the hand-written
equation with noise σ = 0.01 (weights 1/σ²); each fit starts at k 0.8× and c 1.5× its truth.
Default options (Levenberg–Marquardt, uncertainties computed). Times: the first call of
each route in this process (compilation included; the loop's first fit compiles once for all
its members), then medians of 3 calls. "max rel. diff." compares every system's fitted k and
c between the two routes.
"""

import argparse
import statistics
import time
import warnings

import jax
import numpy as np
from scipy.integrate import solve_ivp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

SIGMA = 0.01
TRAINED = {"m": False, "k": True, "c": True}


def oscillator():
    return jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
                             lambda q, p: 0.5 * p["k"] * q[0] ** 2,
                             dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)


def systems(count, seed=0):
    rng = np.random.default_rng(seed)
    ts = np.linspace(0.0, 10.0, 101)
    experiments, guesses, truths = [], [], []
    for _ in range(count):
        k, c = rng.uniform(2.0, 6.0), rng.uniform(0.2, 0.8)
        x = solve_ivp(lambda t, y, k=k, c=c: [y[1], -k * y[0] - c * y[1]], (0.0, 10.0),
                      [1.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853").y[0]
        noisy = x + SIGMA * rng.standard_normal(ts.size)
        experiments.append(jaxdyn.Experiment(ts, noisy, q0=[1.0], u0=[0.0], weights=SIGMA**-2))
        guesses.append({"m": 1.0, "k": 0.8 * k, "c": 1.5 * c})
        truths.append((k, c))
    return experiments, guesses, truths


def timed(fn, repeats=3):
    start = time.perf_counter()
    out = fn()
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return out, first, statistics.median(times)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 32, 128])
    args = parser.parse_args()
    system = oscillator()
    print(f"{'B':>5s} {'loop first s':>13s} {'loop s':>8s} {'batch first s':>14s} "
          f"{'batch s':>8s} {'loop / batch':>13s} {'max rel. diff.':>15s} {'converged':>10s}")
    for count in args.sizes:
        experiments, guesses, _ = systems(count)
        options = dict(filter_spec=TRAINED, progress=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loop, loop_first, loop_time = timed(lambda: [
                jaxdyn.fit(system, e, g, **options) for e, g in zip(experiments, guesses)])
            batch, batch_first, batch_time = timed(
                lambda: jaxdyn.fit_batch(system, experiments, guesses, **options))
        difference = max(abs(float(a.params[key]) / float(b.params[key]) - 1)
                         for a, b in zip(batch, loop) for key in ("k", "c"))
        converged = sum(r.converged and bool(r.explains_data) for r in batch)
        print(f"{count:5d} {loop_first:13.2f} {loop_time:8.2f} {batch_first:14.2f} "
              f"{batch_time:8.2f} {loop_time / batch_time:12.1f}x {difference:15.1e} "
              f"{converged:>5d}/{count}", flush=True)


if __name__ == "__main__":
    main()
