"""XLA's settings for the test run (the tests, and the notebooks' kernels, which inherit the
environment). The tests check results, not speed, and half of their time is XLA compiling
a few thousand distinct programs: JAX's `jax_disable_most_optimizations` has XLA generate
code at LLVM's optimisation level 0. Tests of properties that hold bit for bit in the
programs users run (batches laid out differently, sharded or not) compile at XLA's
defaults: the fixture `xla_defaults`, and `default_environment` for their subprocesses. The
benchmarks run at XLA's defaults."""

import atexit
import os
import shutil
import tempfile

SWITCH = "JAX_DISABLE_MOST_OPTIMIZATIONS"


def compile_fast():
    """Less optimisation by XLA in this process and its children, unless the user chose; and
    one persistent compilation cache for the run, shared by its processes (the xdist workers,
    the notebooks' kernels, the guides' and examples' subprocesses inherit it): a program that
    several of them compile (a robot's solve in a test and in a guide, the quickstart's
    pendulum in the README and a notebook) compiles once. A fresh directory per run, so that a
    run's time is that of a clean machine."""
    os.environ.setdefault(SWITCH, "1")
    if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
        cache = tempfile.mkdtemp(prefix="jaxdyn-test-xla-")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = cache
        atexit.register(shutil.rmtree, cache, True)  # (by the process that made it)
        # (programs that compile in under a second are not worth a disk write and read)
        os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")


def default_environment(env=None):
    """The environment with `env` added, for a subprocess that compiles at XLA's defaults."""
    return {**os.environ, **(env or {}), SWITCH: "0"}
