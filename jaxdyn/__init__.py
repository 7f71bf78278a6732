"""jaxdyn: differentiable analytical dynamics on JAX."""

from importlib.metadata import PackageNotFoundError as _NotInstalled, version as _version
from . import _xla as _xla
from ._xla import compiler_options as compiler_options

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
from ._fit.batch import fit_batch as fit_batch
from ._fit.fit import fit as fit
from ._fit.result import (
    FitResult as FitResult,
    IdentifiabilityWarning as IdentifiabilityWarning,
    LackOfFitWarning as LackOfFitWarning,
)
from ._fit.base_parameters import BaseParameters as BaseParameters
from ._fit.torques import (
    ImplausibleEstimateWarning as ImplausibleEstimateWarning,
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
from ._integrate.events import EventRecord as EventRecord
from ._events import AbstractEvent as AbstractEvent, Event as Event
from ._form.impact import UnilateralContact as UnilateralContact
from ._form.rigid_contact import RigidContact as RigidContact
from ._form.contact import (
    Contact as Contact,
    ContactRecord as ContactRecord,
    HuntCrossley as HuntCrossley,
)
from ._system.contact import (
    AbstractTerrain as AbstractTerrain,
    ContactPair as ContactPair,
    ContactPoint as ContactPoint,
    HeightField as HeightField,
    Plane as Plane,
    box_corners as box_corners,
    capsule_ends as capsule_ends,
)
from ._system.urdf import urdf_contact_points as urdf_contact_points
from ._linearisation import (
    LinearModel as LinearModel,
    Modes as Modes,
    linearise as linearise,
    normal_modes as normal_modes,
)
from ._batch import simulate_batch as simulate_batch
from ._optimal_control.problem import (
    AbstractDiscretisation as AbstractDiscretisation,
    Euler as Euler,
    RungeKutta4 as RungeKutta4,
    SemiImplicitEuler as SemiImplicitEuler,
    ShootingProblem as ShootingProblem,
    VariationalStep as VariationalStep,
)
from ._optimal_control.solver import (
    DDP as DDP,
    ILQR as ILQR,
    AbstractTrajectorySolver as AbstractTrajectorySolver,
)
from ._optimal_control.optimum import (
    NotConvergedWarning as NotConvergedWarning,
    OptimalTrajectory as OptimalTrajectory,
    TrackingPolicy as TrackingPolicy,
    solve_optimal_control as solve_optimal_control,
)
from ._optimal_control.mpc import (
    ClosedLoop as ClosedLoop,
    model_predictive_control as model_predictive_control,
)
from ._state import allow_float32 as allow_float32
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
    HeldPoints as HeldPoints,
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
from ._system.links import Link as Link, LinkLoad as LinkLoad
from ._system.tree import RigidBodyTree as RigidBodyTree
from ._system.urdf import example_robot_urdf as example_robot_urdf, from_urdf as from_urdf

try:
    __version__ = _version("jaxdyn")
except _NotInstalled:  # running from a source tree
    __version__ = "0.0.0+unknown"
