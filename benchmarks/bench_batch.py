"""Batch throughput: trajectories per second for `jax.vmap(jaxdyn.simulate)` over initial
states, against a Python loop of single `simulate` calls and a loop of SciPy's `solve_ivp`
(DOP853 on a NumPy right-hand side), side by side in one process.

Run: python benchmarks/bench_batch.py

The double pendulum over 10 s at rtol = atol = 1e-8 (Tsit5 for jaxdyn, DOP853 for SciPy: each
at its usual choice), starting angles drawn from [0.5, 2.5] rad (regular to chaotic motion, so
members take different numbers of steps; every batch, and the loops, see the same mix). Batch sizes 1, 64 and 1024; the Python loops are
timed on 64 members and scaled. Compile time of the vmapped solve is reported apart.
"""

import os
import sys
import time

import diffrax
import jax
import numpy as np
import scipy.integrate

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM, as_arrays  # noqa: E402
from _timing import interleaved  # noqa: E402

T1, TOL = 10.0, 1e-8


def numpy_rhs(p):
    m1, m2, l1, l2, g = (p[k] for k in ("m1", "m2", "l1", "l2", "g"))

    def rhs(t, y):
        q1, q2, w1, w2 = y
        d = q1 - q2
        den = 2 * m1 + m2 - m2 * np.cos(2 * d)
        a1 = (-g * (2 * m1 + m2) * np.sin(q1) - m2 * g * np.sin(q1 - 2 * q2)
              - 2 * np.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * np.cos(d))) / (l1 * den)
        a2 = (2 * np.sin(d) * (w1**2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(q1)
                               + w2**2 * l2 * m2 * np.cos(d))) / (l2 * den)
        return [w1, w2, a1, a2]

    return rhs


def main():
    system = DOUBLE_PENDULUM
    p = as_arrays(system.params)
    # The same mix of regular and chaotic members in every batch size: shuffled angles.
    angles = np.random.default_rng(0).permutation(np.linspace(0.5, 2.5, 1024))
    q0s = np.stack([angles, 0.5 * angles], axis=1)
    u0s = np.zeros_like(q0s)

    def one(q0, u0):
        return jaxdyn.simulate(system.dynamics, q0, u0, p, t1=T1, solver=diffrax.Tsit5(),
                               rtol=TOL, atol=TOL, save="q").q[-1]

    batched = jax.jit(jax.vmap(one))
    start = time.perf_counter()
    jax.block_until_ready(batched(q0s[:64], u0s[:64]))
    compile_seconds = time.perf_counter() - start

    # agreement: the batch against single solves and against SciPy
    rhs = numpy_rhs(system.params)
    single = np.asarray(one(q0s[10], u0s[10]))
    reference = scipy.integrate.solve_ivp(rhs, (0, T1), [*q0s[10], 0, 0], method="DOP853",
                                          rtol=1e-12, atol=1e-12).y[:2, -1]
    batch_value = np.asarray(batched(q0s[:64], u0s[:64]))[10]
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64; double pendulum, "
          f"{T1} s, tol {TOL}")
    print(f"member 10: batch vs single {np.max(np.abs(batch_value - single)):.1e}, vs SciPy "
          f"DOP853 at 1e-12 {np.max(np.abs(single - reference)):.1e}; compile of the vmapped "
          f"solve {compile_seconds:.2f} s")

    def python_loop(count):
        def run():
            return [one(q0s[i], u0s[i]) for i in range(count)]
        return run

    def scipy_loop(count):
        def run():
            return [scipy.integrate.solve_ivp(rhs, (0, T1), [*q0s[i], 0, 0], method="DOP853",
                                              rtol=TOL, atol=TOL).y[:2, -1]
                    for i in range(count)]
        return run

    loops = interleaved({"python loop of simulate": (python_loop(64), ()),
                         "scipy solve_ivp loop": (scipy_loop(64), ())}, number=1, rounds=3)
    per_trajectory = {k: v / 64 for k, v in loops.items()}
    print(f"{'batch':>6s} {'jaxdyn vmap':>14s} {'Python loop':>14s} {'SciPy loop':>14s} "
          f"{'vs loop':>8s} {'vs SciPy':>9s}   (trajectories per second)")
    for size in (1, 64, 1024):
        times = interleaved({"vmap": (batched, (q0s[:size], u0s[:size]))}, number=1, rounds=5)
        rate = size / times["vmap"]
        loop_rate = 1 / per_trajectory["python loop of simulate"]
        scipy_rate = 1 / per_trajectory["scipy solve_ivp loop"]
        print(f"{size:6d} {rate:14.0f} {loop_rate:14.0f} {scipy_rate:14.0f} "
              f"{rate / loop_rate:7.1f}× {rate / scipy_rate:8.1f}×", flush=True)


if __name__ == "__main__":
    main()
