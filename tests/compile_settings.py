"""XLA's settings for the test run (the tests, and the notebooks' kernels, which inherit the
environment). The tests check results, not speed, and half of their time is XLA compiling
a few thousand distinct programs: JAX's `jax_disable_most_optimizations` has XLA generate
code at LLVM's optimisation level 0. Tests of properties that hold bit for bit in the
programs users run (batches laid out differently, sharded or not) compile at XLA's
defaults: the fixture `xla_defaults`, and `default_environment` for their subprocesses. The
benchmarks run at XLA's defaults."""

import os

SWITCH = "JAX_DISABLE_MOST_OPTIMIZATIONS"


def compile_fast():
    """Less optimisation by XLA in this process and its children, unless the user chose."""
    os.environ.setdefault(SWITCH, "1")


def default_environment(env=None):
    """The environment with `env` added, for a subprocess that compiles at XLA's defaults."""
    return {**os.environ, **(env or {}), SWITCH: "0"}
