"""Timing helpers shared by the benchmarks: compile and run timed separately."""

import statistics
import time

import jax


def compile_time(fn, *args):
    """Seconds to trace and compile `fn` for `args` (a fresh jit, so nothing is cached)."""
    start = time.perf_counter()
    jax.jit(lambda *a: fn(*a)).lower(*args).compile()
    return time.perf_counter() - start


def run_time(fn, *args, number=200, rounds=7):
    """Median over `rounds` of the mean seconds per call, after compilation."""
    jax.block_until_ready(fn(*args))
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(number):
            out = fn(*args)
        jax.block_until_ready(out)
        samples.append((time.perf_counter() - start) / number)
    return statistics.median(samples)
