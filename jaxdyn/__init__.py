"""jaxdyn: differentiable analytical dynamics on JAX."""

from importlib.metadata import PackageNotFoundError as _NotInstalled, version as _version
import os as _os

# Two of XLA's CPU code generators are turned off, each for programs that jaxdyn forms
# (benchmarks/README.md, "XLA's CPU code generators"):
# - the fusion emitters compile the straight-line scalar programs of small systems
#   (`jaxdyn._unroll`) into code that runs 50–2500× slower than XLA's elemental emitters: a
#   UR5 arm's forward dynamics costs 1 ms per state in a vmapped batch with them, 0.4 µs
#   without;
# - YNNPACK fusions take over the small batched products of 6 × 6 and 3 × 3 blocks in a
#   tree's recursions and run them several times slower than XLA's own loops: a humanoid's
#   forward dynamics (G1) costs 49 µs per state in a batch with them, 15 µs without.
# The switches are read when JAX first starts its CPU backend, so they are set here, before
# jaxdyn creates any array, unless the user chose values of their own.
_XLA_SWITCHES = {"xla_cpu_use_fusion_emitters": "false",
                 "xla_cpu_experimental_ynn_fusion_type": ""}
_unset = [name for name in _XLA_SWITCHES if name not in _os.environ.get("XLA_FLAGS", "")]
if _unset:
    _os.environ["XLA_FLAGS"] = " ".join(
        [_os.environ.get("XLA_FLAGS", "")] + [f"--{name}={_XLA_SWITCHES[name]}"
                                              for name in _unset]).strip()
    import jax._src.xla_bridge as _xla_bridge

    if _xla_bridge.backends_are_initialized() and _xla_bridge.default_backend() == "cpu":
        import warnings as _warnings

        _warnings.warn(
            "JAX started its backends before jaxdyn was imported, so jaxdyn could not turn "
            "off XLA's CPU fusion emitters and YNNPACK fusions, which run the programs of "
            "small systems and of robots' recursions several to thousands of times slower on "
            "the CPU (a vmapped batch above all). Import jaxdyn before the first JAX "
            "computation, or start Python with XLA_FLAGS=\"" + " ".join(
                f"--{name}={value}" for name, value in _XLA_SWITCHES.items()) + "\".",
            stacklevel=2)
    del _xla_bridge
del _os, _unset

from . import rotations as rotations
from ._system.base import AbstractMultibody as AbstractMultibody
from ._dynamics import AbstractDynamics as AbstractDynamics
from ._form.articulated import ArticulatedBody as ArticulatedBody
from ._form.constraints import (
    Baumgarte as Baumgarte,
    Constrained as Constrained,
    IndependentSpeeds as IndependentSpeeds,
    Projection as Projection,
)
from ._form.controlled import Controlled as Controlled
from ._form.controlled import ForceInput as ForceInput
from ._form.controlled import TorqueInput as TorqueInput
from ._form.euler_lagrange import Lagrangian as Lagrangian
from ._form.gibbs_appell import GibbsAppell as GibbsAppell
from ._form.kane import Kane as Kane
from ._form.newton_euler import (
    energy_regressors as energy_regressors,
    inertial_parameters as inertial_parameters,
    inverse_dynamics_regressor as inverse_dynamics_regressor,
)
from ._fit.experiment import (
    Experiment as Experiment,
    HorizonContinuation as HorizonContinuation,
    MultipleShooting as MultipleShooting,
)
from ._fit.starts import MultiStart as MultiStart
from ._fit.fit import (
    FitResult as FitResult,
    IdentifiabilityWarning as IdentifiabilityWarning,
    LackOfFitWarning as LackOfFitWarning,
    fit as fit,
    fit_batch as fit_batch,
)
from ._fit.torques import (
    InertialFit as InertialFit,
    fit_inertial_parameters as fit_inertial_parameters,
)
from ._fit.parametrisation import (
    AbstractParametrisation as AbstractParametrisation,
    InertiaTensor as InertiaTensor,
    Positive as Positive,
    Unconstrained as Unconstrained,
)
from ._fit.uncertainty import Uncertainty as Uncertainty
from ._equilibria import Equilibrium as Equilibrium, equilibrium as equilibrium
from ._integrate import simulate as simulate
from ._linearisation import (
    LinearModel as LinearModel,
    Modes as Modes,
    linearise as linearise,
    normal_modes as normal_modes,
)
from ._batch import simulate_batch as simulate_batch
from ._stiffness import Stiffness as Stiffness, stiffness as stiffness
from ._variational import (
    AbstractStructurePreserving as AbstractStructurePreserving,
    StormerVerlet as StormerVerlet,
    VariationalIntegrator as VariationalIntegrator,
)
from ._solution import (
    RESULTS as RESULTS,
    ConstraintRecord as ConstraintRecord,
    Solution as Solution,
)
from ._system.bodies import Particle as Particle, RigidBody as RigidBody
from ._system.loads import BodyTorque as BodyTorque, PointForce as PointForce
from ._system.frames import (
    centre_of_mass as centre_of_mass,
    centre_of_mass_jacobian as centre_of_mass_jacobian,
    centre_of_mass_velocity as centre_of_mass_velocity,
    centroidal_momentum as centroidal_momentum,
    centroidal_momentum_matrix as centroidal_momentum_matrix,
    frame_acceleration as frame_acceleration,
    frame_jacobian as frame_jacobian,
    frame_pose as frame_pose,
    frame_velocity as frame_velocity,
)
from ._system.joints import (
    AbstractJoint as AbstractJoint,
    Fixed as Fixed,
    Free as Free,
    Planar as Planar,
    Prismatic as Prismatic,
    Revolute as Revolute,
    Spherical as Spherical,
)
from ._system.multibody import MultibodySystem as MultibodySystem
from ._system.tree import Link as Link, LinkLoad as LinkLoad, RigidBodyTree as RigidBodyTree
from ._system.urdf import example_robot_urdf as example_robot_urdf, from_urdf as from_urdf

try:
    __version__ = _version("jaxdyn")
except _NotInstalled:  # running from a source tree
    __version__ = "0.0.0+unknown"
