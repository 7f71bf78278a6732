"""A system of particles and rigid bodies: one description, three formulations."""

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
from .._form.euler_lagrange import Lagrangian
from .._form.gibbs_appell import GibbsAppell
from .._speeds import coordinate_motion, kinematic_matrix
from .bodies import Particle, RigidBody, _value
from .loads import BodyTorque, PointForce


class MultibodySystem(eqx.Module):
    """Particles and rigid bodies with potential energy, applied loads and dissipation.

    From this one description jaxdyn forms the equations of motion three ways:

    - `system.lagrangian()`: the kinetic energy T = Σ ½ m v·v + ½ ω·Iω for Lagrange's
      equations of the second kind;
    - `system.gibbs_appell(kinematic_map)`: the Gibbs function
      S = Σ ½ m a·a + ½ α·Iα + α·(ω × Iω) for the Gibbs–Appell equations ∂S/∂u̇ = Π;
    - `jaxdyn.Kane(system, kinematic_map)`: partial velocities and generalized active and
      inertia forces, F_r + F*_r = 0.

    **Arguments:**

    - `bodies`: a sequence of `Particle` and `RigidBody`.
    - `potential`: V(q, p) → scalar (springs, fields), or None.
    - `gravity`: the gravitational acceleration vector (3,) or a function g(p), or None; it adds
      Σ −m g·r_G to the potential.
    - `loads`: a sequence of `PointForce` and `BodyTorque`.
    - `forces`: further generalized forces Q(q, qd, p) → (n,), or None.
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

    # -- energies and forces on (t, q, q̇): everything Lagrange's equations need ---------------

    def kinetic_energy(self, t, q, qd, p):
        """T = Σ ½ m v·v + ½ ω·I ω."""
        t_dot = self._t_dot(t)
        return sum(b.kinetic_energy(self.time_dependent, t, q, t_dot, qd, p)
                   for b in self.bodies)

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

    def applied_forces(self, t, q, qd, p):
        """Generalized forces of the loads and of Q: Σ F·∂v/∂q̇ + Σ τ·∂ω/∂q̇ + Q."""
        t_dot = self._t_dot(t)
        total = jnp.zeros_like(qd)
        for load in self.loads:
            total = total + load.generalized_force(self.time_dependent, t, q, t_dot, qd, p)
        if self.forces is not None:
            total = total + vector(call(self.forces, "generalized forces Q",
                                        self.time_dependent, VELOCITY_ARGS, t, q, qd, p),
                                   "generalized forces Q", qd.shape)
        return total

    def dissipation_function(self, t, q, qd, p):
        """Rayleigh's D(q, q̇) (zero if none was given)."""
        if self.dissipation is None:
            return jnp.zeros((), q.dtype)
        return scalar(call(self.dissipation, "dissipation function D", self.time_dependent,
                           VELOCITY_ARGS, t, q, qd, p), "dissipation function D")

    def lagrangian(self) -> Lagrangian:
        """These bodies and loads as a `jaxdyn.Lagrangian` (coordinates q, speeds q̇)."""
        return Lagrangian(
            kinetic=_TimeFirst(self.kinetic_energy, self.time_dependent),
            potential=_TimeFirst(self.potential_energy, self.time_dependent),
            forces=_TimeFirst(self.applied_forces, self.time_dependent),
            dissipation=self.dissipation,
            time_dependent=self.time_dependent,
        )

    # -- in generalized speeds u, q̇ = K u: what Gibbs–Appell and Kane need -------------------

    def coordinate_rates(self, t, q, u, p, kinematic_map=None):
        """q̇ = K(t, q, p) u."""
        return kinematic_matrix(kinematic_map, self.time_dependent, t, q, u, p) @ u

    def generalized_active_forces(self, t, q, u, p, kinematic_map=None):
        """Π_r = F_r = Kᵀ (Q_applied − ∂V/∂q − ∂D/∂q̇): the active forces along each speed."""
        k = kinematic_matrix(kinematic_map, self.time_dependent, t, q, u, p)
        qd = k @ u
        potential_force = -jax.grad(self.potential_energy, argnums=1)(t, q, p)
        dissipative_force = -jax.grad(self.dissipation_function, argnums=2)(t, q, qd, p)
        return k.T @ (self.applied_forces(t, q, qd, p) + potential_force + dissipative_force)

    def gibbs_function(self, t, q, u, ud, p, kinematic_map=None):
        """S = Σ ½ m a·a + ½ α·I α + α·(ω × I ω), with q̇ = K u and q̈ = K̇ u + K u̇."""
        t_dot = self._t_dot(t)
        qd, qdd = coordinate_motion(kinematic_map, self.time_dependent, t, q, t_dot, u, ud, p)
        return sum(b.gibbs_function(self.time_dependent, t, q, t_dot, qd, qdd, p)
                   for b in self.bodies)

    def partial_velocities(self, t, q, u, p, kinematic_map=None):
        """Per body, v_r = ∂v/∂u_r (3, m), and for rigid bodies ω_r = ∂ω/∂u_r (3, m, body
        axes); Jacobians of the velocities in the speeds."""
        t_dot = self._t_dot(t)
        k = kinematic_matrix(kinematic_map, self.time_dependent, t, q, u, p)
        partials = []
        for body in self.bodies:
            def velocity(u, body=body):
                return body.velocity(self.time_dependent, t, q, t_dot, k @ u, p)

            def angular_velocity(u, body=body):
                return body.angular_velocity(self.time_dependent, t, q, t_dot, k @ u, p)

            v_r = jax.jacfwd(velocity)(u)
            w_r = jax.jacfwd(angular_velocity)(u) if isinstance(body, RigidBody) else None
            partials.append((v_r, w_r))
        return partials

    def generalized_inertia_forces(self, t, q, u, ud, p, kinematic_map=None, partials=None):
        """F*_r = −Σ m a·v_r − Σ (I α + ω × I ω)·ω_r (Kane)."""
        t_dot = self._t_dot(t)
        if partials is None:
            partials = self.partial_velocities(t, q, u, p, kinematic_map)
        qd, qdd = coordinate_motion(kinematic_map, self.time_dependent, t, q, t_dot, u, ud, p)
        total = jnp.zeros_like(u)
        for body, (v_r, w_r) in zip(self.bodies, partials):
            terms = body.inertia_terms(self.time_dependent, t, q, t_dot, qd, qdd, p)
            total = total - terms[0] * terms[1] @ v_r
            if w_r is not None:
                _, _, inertia, omega, alpha = terms
                total = total - (inertia @ alpha + jnp.cross(omega, inertia @ omega)) @ w_r
        return total

    def gibbs_appell(self, kinematic_map=None):
        """These bodies and loads as a `jaxdyn.GibbsAppell`, in speeds q̇ = K(q, p) u."""
        return GibbsAppell(
            gibbs=_TimeFirst(_WithMap(self.gibbs_function, kinematic_map), self.time_dependent),
            active_forces=_TimeFirst(_WithMap(self.generalized_active_forces, kinematic_map),
                                     self.time_dependent),
            kinematic_map=kinematic_map,
            time_dependent=self.time_dependent,
        )


class _TimeFirst(eqx.Module):
    """Adapts a system method (t first) to the calling convention of `time_dependent`."""

    method: Callable
    time_dependent: bool = eqx.field(static=True)

    def __call__(self, *args):
        if self.time_dependent:
            return self.method(*args)
        q = args[0]
        return self.method(jnp.zeros((), q.dtype), *args)


class _WithMap(eqx.Module):
    """A system method with its kinematic map bound."""

    method: Callable
    kinematic_map: Callable | None

    def __call__(self, *args):
        return self.method(*args, kinematic_map=self.kinematic_map)
