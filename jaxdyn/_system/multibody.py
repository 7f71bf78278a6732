"""A system of particles and rigid bodies, each described by its position and orientation."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import (
    CONFIGURATION_ARGS,
    VELOCITY_ARGS,
    call,
    scalar,
    time_rate,
    vector,
)
from .._speeds import kinematic_matrix
from .base import AbstractMultibody
from .bodies import Particle, RigidBody, _value
from .loads import BodyTorque, PointForce


class MultibodySystem(AbstractMultibody):
    """Particles and rigid bodies with potential energy, applied loads and dissipation.

    Each body is described by its position (and, for rigid bodies, its orientation) as a
    function of the coordinates; velocities, angular velocities, accelerations and partial
    velocities follow by automatic differentiation. Any formulation takes this description:
    `jaxdyn.Lagrangian.from_system(system)`, `jaxdyn.GibbsAppell.from_system(system, K)`,
    `jaxdyn.Kane.from_system(system, K)` (with generalized speeds q̇ = K(q, p) u, fewer of them
    than coordinates for nonholonomic systems).

    **Arguments:**

    - `bodies`: a sequence of `Particle` and `RigidBody`.
    - `potential`: V(q, p) → scalar (springs, fields), or None.
    - `gravity`: the gravitational acceleration vector (3,) or a function g(p), or None; it adds
      Σ −m g·r_G to the potential.
    - `loads`: a sequence of `PointForce` and `BodyTorque`.
    - `forces`: further generalized forces Q(q, qd, p) → (n,), along q̇, or None.
    - `dissipation`: Rayleigh dissipation function D(q, qd, p), or None.
    - `time_dependent`: if True every callback (positions, orientations, loads, energies,
      the kinematic map) takes t first.
    """

    bodies: tuple[Particle | RigidBody, ...] = eqx.field(converter=tuple)
    potential: Callable | None = None
    gravity: jax.Array | Callable | None = None
    loads: tuple[PointForce | BodyTorque, ...] = eqx.field(default=(), converter=tuple)
    forces: Callable | None = None
    dissipation: Callable | None = None
    time_dependent: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        if len(self.bodies) == 0:
            raise ValueError("MultibodySystem needs at least one body.")
        for body in self.bodies:
            if not isinstance(body, (Particle, RigidBody)):
                raise ValueError(
                    f"bodies must be jaxdyn.Particle or jaxdyn.RigidBody, got "
                    f"{type(body).__name__}."
                )
        for load in self.loads:
            if not isinstance(load, (PointForce, BodyTorque)):
                raise ValueError(
                    f"loads must be jaxdyn.PointForce or jaxdyn.BodyTorque, got "
                    f"{type(load).__name__}."
                )

    def _t_dot(self, t):
        return time_rate(t, self.time_dependent)

    def kinematic_matrix(self, t, q, p, kinematic_map=None, u=None):
        return kinematic_matrix(kinematic_map, self.time_dependent, t, q, p, u)

    def speeds_from_rates(self, t, q, qd, p):
        return qd

    def inertias(self, p, dtype):
        masses = jnp.stack([jnp.asarray(_value(b.mass, p), dtype) for b in self.bodies])
        zero = jnp.zeros((3, 3), dtype)
        inertias = jnp.stack([jnp.asarray(b._inertia(p), dtype) if isinstance(b, RigidBody)
                              else zero for b in self.bodies])
        return masses, inertias

    def body_velocities(self, t, q, u, p, kinematic_map=None):
        qd = self.coordinate_rates(t, q, u, p, kinematic_map)
        t_dot = self._t_dot(t)
        velocities, omegas = [], []
        for body in self.bodies:
            velocities.append(body.velocity(self.time_dependent, t, q, t_dot, qd, p))
            omegas.append(body.angular_velocity(self.time_dependent, t, q, t_dot, qd, p)
                          if isinstance(body, RigidBody) else jnp.zeros(3, q.dtype))
        return jnp.stack(velocities), jnp.stack(omegas)

    def body_poses(self, t, q, p):
        positions = jnp.stack([b._position(self.time_dependent, t, q, p) for b in self.bodies])
        eye = jnp.eye(3, dtype=q.dtype)
        rotations = jnp.stack([b._orientation(self.time_dependent, t, q, p)
                               if isinstance(b, RigidBody) else eye for b in self.bodies])
        return positions, rotations

    def potential_energy(self, t, q, p):
        """V(q) plus the gravitational energy Σ −m g·r_G."""
        total = jnp.zeros((), q.dtype)
        if self.potential is not None:
            total = total + scalar(call(self.potential, "potential energy V",
                                        self.time_dependent, CONFIGURATION_ARGS, t, q, p),
                                   "potential energy V")
        if self.gravity is not None:
            g = _value(self.gravity, p)
            for body in self.bodies:
                total = total - _value(body.mass, p) * jnp.dot(
                    g, body._position(self.time_dependent, t, q, p))
        return total

    def forces_along_rates(self, t, q, qd, p):
        """The generalized forces of the loads and of Q along q̇, and −∂D/∂q̇."""
        t_dot = self._t_dot(t)
        total = jnp.zeros_like(qd)
        for load in self.loads:
            total = total + load.generalized_force(self.time_dependent, t, q, t_dot, qd, p)
        if self.forces is not None:
            total = total + vector(call(self.forces, "generalized forces Q",
                                        self.time_dependent, VELOCITY_ARGS, t, q, qd, p),
                                   "generalized forces Q", qd.shape)
        if self.dissipation is not None:
            def dissipation(qd):
                return scalar(call(self.dissipation, "dissipation function D",
                                   self.time_dependent, VELOCITY_ARGS, t, q, qd, p),
                              "dissipation function D")
            total = total - jax.grad(dissipation)(qd)
        return total

    def applied_forces(self, t, q, u, p, kinematic_map=None):
        """Π = Kᵀ (Σ F·∂v/∂q̇ + Σ τ·∂ω/∂q̇ + Q − ∂D/∂q̇), at q̇ = K u."""
        k = self.kinematic_matrix(t, q, p, kinematic_map)
        return k.T @ self.forces_along_rates(t, q, k @ u, p)

    def user_functions(self, t, q, u, p, kinematic_map=None):
        qd = self.coordinate_rates(t, q, u, p, kinematic_map)
        return (self.body_velocities(t, q, u, p, kinematic_map), self.potential_energy(t, q, p),
                self.forces_along_rates(t, q, qd, p), qd)
