"""What every description of bodies provides to the formulations.

A description (`MultibodySystem`: bodies given by their positions and orientations;
`RigidBodyTree`: links connected by joints) supplies the kinematics of its N bodies — the
velocity of each centre of mass (world axes) and each angular velocity (body axes) as
functions of (t, q, u) — their masses and inertias, its potential energy and its applied
forces. Everything the formulations need follows here, once, for every description:

    T = Σ ½ m v_G·v_G + ½ ω·I ω                     (Lagrange)
    S = Σ ½ m a_G·a_G + ½ α·I α + α·(ω × I ω)       (Gibbs–Appell)
    v_r = ∂v_G/∂u_r,  ω_r = ∂ω/∂u_r                 (Kane's partial velocities)
    F*_r = −Σ m a_G·v_r − Σ (I α + ω × I ω)·ω_r

with accelerations by one JVP of the velocities along the motion (ṫ, q̇ = K u, u̇).
Descriptions do not know the formulations; the formulations take a description.
"""

import abc
from typing import TYPE_CHECKING, Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import time_rate


class AbstractMultibody(eqx.Module):
    """A description of N bodies: their kinematics, inertia, potential energy and loads.

    Methods take ``(t, q, u, p)``, with speeds u related to the coordinates by q̇ = K(t, q, p) u
    (`kinematic_matrix`); `kinematic_map` is the description's own choice of speeds when None.
    """

    if TYPE_CHECKING:
        # An `eqx.AbstractVar` is no dataclass field at run time, but a type checker takes it
        # for one, first in `__init__`'s arguments: `RigidBodyTree(links, ...)` would not
        # check. Declared to it as what it is, a bool every description provides.
        @property
        def time_dependent(self) -> bool: ...
    else:
        time_dependent: eqx.AbstractVar[bool]

    # -- what a description provides ---------------------------------------------------------

    @abc.abstractmethod
    def kinematic_matrix(self, t, q, p, kinematic_map: Callable | None = None, u=None
                         ) -> jax.Array:
        """K (n × m) with q̇ = K u; with `u`, after checking that u has m entries."""

    @abc.abstractmethod
    def speeds_from_rates(self, t, q, qd, p) -> jax.Array:
        """u from q̇ (where the speeds are a re-parametrisation of q̇, K invertible); raises
        where they are not (quaternions, nonholonomic speeds)."""

    @abc.abstractmethod
    def inertias(self, p, dtype) -> tuple[jax.Array, jax.Array]:
        """(masses (N,), inertia tensors about the centres of mass, body axes (N, 3, 3)), in
        `dtype` (the state's: constants of a description never set the precision)."""

    @abc.abstractmethod
    def body_velocities(self, t, q, u, p, kinematic_map=None) -> tuple[jax.Array, jax.Array]:
        """(v_G (N, 3) in world axes, ω (N, 3) in body axes)."""

    @abc.abstractmethod
    def body_poses(self, t, q, p) -> tuple[jax.Array, jax.Array]:
        """(centres of mass (N, 3) in world axes, orientations R (N, 3, 3), body → world)."""

    @abc.abstractmethod
    def potential_energy(self, t, q, p) -> jax.Array:
        """V: gravity, springs and any user potential."""

    @abc.abstractmethod
    def applied_forces(self, t, q, u, p, kinematic_map=None) -> jax.Array:
        """The generalized non-conservative forces along the speeds (m,): loads, generalized
        forces and dissipation, Π with Π·δu the virtual work."""

    @abc.abstractmethod
    def user_functions(self, t, q, u, p, kinematic_map=None):
        """Every user callback evaluated once, without derivatives (for trace-time checks)."""

    # -- what follows for every description ---------------------------------------------------

    def check_speeds(self, t, q, u, p, kinematic_map=None) -> None:
        """Raise where q and u do not fit the description: by default, K formed (the
        user's `kinematic_map` called) and its shape checked against them. A description
        whose sizes are known without forming K compares q and u with them (a tree: its
        joints' sizes, rather than a block of K traced per joint at every check)."""
        self.kinematic_matrix(t, q, p, kinematic_map, u)

    def coordinate_rates(self, t, q, u, p, kinematic_map=None):
        """q̇ = K(t, q, p) u."""
        return self.kinematic_matrix(t, q, p, kinematic_map) @ u

    def kinetic_energy(self, t, q, u, p, kinematic_map=None):
        """T = Σ ½ m v_G·v_G + ½ ω·I ω."""
        masses, inertias = self.inertias(p, q.dtype)
        v, omega = self.body_velocities(t, q, u, p, kinematic_map)
        rotational = jnp.sum(omega * jnp.einsum("nij,nj->ni", inertias, omega))
        return 0.5 * (jnp.sum(masses * jnp.sum(v * v, axis=-1)) + rotational)

    def body_accelerations(self, t, q, u, ud, p, kinematic_map=None):
        """((v_G, ω), (a_G, α)): velocities and their rates along (ṫ, q̇ = K u, u̇), one JVP
        (α = dω/dt in body axes, since ω × ω = 0)."""
        qd = self.coordinate_rates(t, q, u, p, kinematic_map)

        def velocities(t, q, u):
            return self.body_velocities(t, q, u, p, kinematic_map)

        return jax.jvp(velocities, (t, q, u), (time_rate(t, self.time_dependent), qd, ud))

    def gibbs_function(self, t, q, u, ud, p, kinematic_map=None):
        """S = Σ ½ m a_G·a_G + ½ α·I α + α·(ω × I ω) (dropping terms free of u̇)."""
        masses, inertias = self.inertias(p, q.dtype)
        (_, omega), (a, alpha) = self.body_accelerations(t, q, u, ud, p, kinematic_map)
        i_alpha = jnp.einsum("nij,nj->ni", inertias, alpha)
        i_omega = jnp.einsum("nij,nj->ni", inertias, omega)
        return (0.5 * jnp.sum(masses * jnp.sum(a * a, axis=-1))
                + jnp.sum(0.5 * alpha * i_alpha + alpha * jnp.cross(omega, i_omega)))

    def generalized_active_forces(self, t, q, u, p, kinematic_map=None):
        """Π_r = Kᵀ(−∂V/∂q) + applied: every force along the speeds but the inertial ones
        (Kᵀ applied as the transpose of u ↦ K u, one VJP)."""
        potential_force = -jax.grad(self.potential_energy, argnums=1)(t, q, p)
        _, transpose = jax.vjp(lambda u: self.coordinate_rates(t, q, u, p, kinematic_map), u)
        return transpose(potential_force)[0] + self.applied_forces(t, q, u, p, kinematic_map)

    def partial_velocities(self, t, q, u, p, kinematic_map=None):
        """(v_r (N, 3, m), ω_r (N, 3, m)): the velocities' Jacobians in the speeds."""
        def velocities(u):
            return self.body_velocities(t, q, u, p, kinematic_map)

        return jax.jacfwd(velocities)(u)

    def generalized_inertia_forces(self, t, q, u, ud, p, kinematic_map=None, partials=None):
        """F*_r = −Σ m a_G·v_r − Σ (I α + ω × I ω)·ω_r (Kane)."""
        masses, inertias = self.inertias(p, q.dtype)
        if partials is None:
            partials = self.partial_velocities(t, q, u, p, kinematic_map)
        v_r, w_r = partials
        (_, omega), (a, alpha) = self.body_accelerations(t, q, u, ud, p, kinematic_map)
        torque = (jnp.einsum("nij,nj->ni", inertias, alpha)
                  + jnp.cross(omega, jnp.einsum("nij,nj->ni", inertias, omega)))
        return -(jnp.einsum("n,ni,nir->r", masses, a, v_r)
                 + jnp.einsum("ni,nir->r", torque, w_r))

    def kane_mass_matrix(self, p, partials):
        """M_rs = Σ m v_r·v_s + ω_r·I ω_s from the partial velocities."""
        masses, inertias = self.inertias(p, partials[0].dtype)
        v_r, w_r = partials
        return (jnp.einsum("n,nir,nis->rs", masses, v_r, v_r)
                + jnp.einsum("nir,nij,njs->rs", w_r, inertias, w_r))

    def linear_momentum(self, t, q, u, p, kinematic_map=None):
        """Σ m v_G (world axes)."""
        masses, _ = self.inertias(p, q.dtype)
        v, _ = self.body_velocities(t, q, u, p, kinematic_map)
        return jnp.sum(masses[:, None] * v, axis=0)

    def angular_momentum(self, t, q, u, p, kinematic_map=None):
        """Σ r_G × m v_G + R I ω: the angular momentum about the world origin (world axes)."""
        masses, inertias = self.inertias(p, q.dtype)
        v, omega = self.body_velocities(t, q, u, p, kinematic_map)
        positions, rotations = self.body_poses(t, q, p)
        spin = jnp.einsum("nij,njk,nk->ni", rotations, inertias, omega)
        return jnp.sum(jnp.cross(positions, masses[:, None] * v) + spin, axis=0)
