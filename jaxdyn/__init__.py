"""jaxdyn: differentiable analytical dynamics on JAX."""

import importlib.metadata

from . import rotations as rotations
from ._dynamics import AbstractDynamics as AbstractDynamics
from ._form.euler_lagrange import Lagrangian as Lagrangian
from ._form.gibbs_appell import GibbsAppell as GibbsAppell
from ._form.kane import Kane as Kane
from ._integrate import simulate as simulate
from ._solution import RESULTS as RESULTS, Solution as Solution
from ._system.bodies import Particle as Particle, RigidBody as RigidBody
from ._system.loads import BodyTorque as BodyTorque, PointForce as PointForce
from ._system.multibody import MultibodySystem as MultibodySystem

try:
    __version__ = importlib.metadata.version("jaxdyn")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"
