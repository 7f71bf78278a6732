"""Test configuration, set once for the whole suite.

Mechanics wants float64; strict dtype promotion and rank promotion set to "raise" make any
silent float32/float64 mixing or implicit broadcasting in the library (or the tests) an error.
Warnings are turned into errors by `filterwarnings = ["error"]` in pyproject.toml.
The suite runs in several worker processes (pytest-xdist): on a GPU each would otherwise
reserve most of its memory at start-up.

The tests check results, not speed, and half of their time is XLA compiling a few thousand
distinct programs: XLA generates code at LLVM's optimisation level 0 (`compile_settings`;
the fixture `xla_defaults` for tests of bit-for-bit properties) and Python's garbage
collector leaves the imported modules alone (benchmarks/LOG.md, "The default test run":
the heaviest test files 344 → 247 s of CPU).
"""

import gc
import os

import pytest

from compile_settings import compile_fast

compile_fast()
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_collection_finish(session):
    """Every module the tests import is loaded: a full collection no longer walks them."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(10_000, 50, 100)


@pytest.fixture
def xla_defaults():
    """Programs compiled within the test at XLA's default optimisation, as users run them."""
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    yield
    jax.config.update("jax_disable_most_optimizations", before)
