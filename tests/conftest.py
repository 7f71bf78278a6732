"""Test configuration, set once for the whole suite.

Mechanics wants float64; strict dtype promotion and rank promotion set to "raise" make any
silent float32/float64 mixing or implicit broadcasting in the library (or the tests) an error.
Warnings are turned into errors by `filterwarnings = ["error"]` in pyproject.toml.
The suite runs in several worker processes (pytest-xdist): on a GPU each would otherwise
reserve most of its memory at start-up.
"""

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")
