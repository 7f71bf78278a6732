"""Timing helpers shared by the benchmarks: compilation and run time measured separately."""

import statistics
import time

import jax


def timed(fn, *args, number=200, rounds=7):
    """(compile seconds, run seconds per call) for `fn` jit-compiled on `args`.

    Compilation is the first call of a fresh `jax.jit` (trace, compile, one run); the run time
    is the median over `rounds` of the mean over `number` later calls, through `jax.jit`'s
    dispatch as a user calls it (an AOT-compiled executable dispatches more slowly when the
    program holds host callbacks, as jaxdyn's error checks do).
    """
    compiled = jax.jit(lambda *a: fn(*a))
    start = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    compile_seconds = time.perf_counter() - start
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(number):
            out = compiled(*args)
        jax.block_until_ready(out)
        samples.append((time.perf_counter() - start) / number)
    return compile_seconds, statistics.median(samples)
