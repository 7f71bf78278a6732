"""jaxdyn: differentiable analytical dynamics on JAX."""

import importlib.metadata

from ._dynamics import AbstractDynamics as AbstractDynamics
from ._form.euler_lagrange import Lagrangian as Lagrangian
from ._integrate import simulate as simulate
from ._solution import RESULTS as RESULTS, Solution as Solution

try:
    __version__ = importlib.metadata.version("jaxdyn")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"
