"""Timing helpers shared by the benchmarks.

Machines are shared and noisy, so candidates are always timed side by side: compiled first
(compile time recorded apart), then run in interleaved rounds (every candidate once per round,
in turn) and summarised by the median over rounds. Ratios are formed from those medians.
"""

import statistics
import time

import jax
import jax.numpy as jnp


def compile_seconds(fn, *args):
    """Seconds for the first call of a fresh `jax.jit(fn)` with every cache cleared first
    (JAX's and so jaxdyn's compiled methods): trace, compile and one run."""
    jax.clear_caches()
    start = time.perf_counter()
    jax.block_until_ready(jax.jit(lambda *a: fn(*a))(*args))
    return time.perf_counter() - start


def interleaved(candidates, *, number, rounds=9):
    """Median seconds per call of each candidate.

    `candidates`: {name: (callable, args)}; each callable is called as given (wrap it in
    `jax.jit` yourself), first once to compile, then `number` times per round.
    """
    for fn, args in candidates.values():
        jax.block_until_ready(fn(*args))
    samples = {name: [] for name in candidates}
    for _ in range(rounds):
        for name, (fn, args) in candidates.items():
            start = time.perf_counter()
            for _ in range(number):
                out = fn(*args)
            jax.block_until_ready(out)
            samples[name].append((time.perf_counter() - start) / number)
    return {name: statistics.median(values) for name, values in samples.items()}


def in_loop(accelerations, iterations):
    """A jitted function timing `accelerations(t, q, qd, p)` inside a compiled loop, as a solver
    calls it: `iterations` steps of semi-implicit Euler with a tiny step, so that every
    evaluation sees a new state (nothing can be hoisted out of the loop) and no dispatch or
    transfer is counted. Divide its run time by `iterations`."""
    def run(t, q, qd, p):
        h = jnp.asarray(1e-9, q.dtype)

        def step(_, state):
            q, qd = state
            qd = qd + h * accelerations(t, q, qd, p)
            return q + h * qd, qd

        return jax.lax.fori_loop(0, iterations, step, (q, qd))

    return jax.jit(run)
