"""Particles and rigid bodies described by their kinematics; velocities and accelerations by
JVPs of the user's position and orientation functions."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import CONFIGURATION_ARGS, call
from .._state import frozen_constant


def _value(x, p):
    """A mass or inertia given as a number/array or as a function of the parameters p."""
    return jnp.asarray(x(p) if callable(x) else x)


def mass(body, p):
    """The mass of a `Particle` or `RigidBody` for parameters p."""
    return _value(body.mass, p)


def vee(skew):
    """ω from its skew-symmetric matrix [ω]× (the antisymmetric part is used)."""
    return 0.5 * jnp.stack(
        [skew[2, 1] - skew[1, 2], skew[0, 2] - skew[2, 0], skew[1, 0] - skew[0, 1]]
    )


def along_motion(fn, t, q, t_dot, qd):
    """(fn(t, q), d/dt fn) along q̇ = qd: one JVP. `t_dot` is 1 for time-dependent kinematics
    and 0 otherwise (so time terms cost nothing when absent)."""
    return jax.jvp(fn, (t, q), (t_dot, qd))


class Particle(eqx.Module):
    """A point mass.

    **Arguments:**

    - `mass`: a number, or a function m(p) of the parameters (so that it can be fitted).
    - `position`: r(q, p) → (3,) in the world frame (r(t, q, p) in a time-dependent system).
    """

    mass: float | Callable = eqx.field(converter=frozen_constant)
    position: Callable

    def _position(self, time_dependent, t, q, p):
        r = jnp.asarray(call(self.position, "Particle position", time_dependent,
                             CONFIGURATION_ARGS, t, q, p))
        if r.shape != (3,):
            raise ValueError(
                f"Particle position must return a 3-vector, got shape {r.shape}; "
                "for planar motion return (x, y, 0)."
            )
        return r

    def velocity(self, time_dependent, t, q, t_dot, qd, p):
        """v = ∂r/∂q q̇ + ∂r/∂t."""
        return along_motion(lambda t, q: self._position(time_dependent, t, q, p),
                            t, q, t_dot, qd)[1]

    def kinetic_energy(self, time_dependent, t, q, t_dot, qd, p):
        """T = ½ m v·v."""
        v = self.velocity(time_dependent, t, q, t_dot, qd, p)
        return 0.5 * _value(self.mass, p) * jnp.dot(v, v)

    def inertia_terms(self, time_dependent, t, q, t_dot, qd, qdd, p):
        """(mass, acceleration a) with a = d/dt v along (q̇, q̈): a nested JVP."""
        def velocity(t, q, qd):
            return self.velocity(time_dependent, t, q, t_dot, qd, p)

        a = jax.jvp(velocity, (t, q, qd), (t_dot, qd, qdd))[1]
        return _value(self.mass, p), a

    def gibbs_function(self, time_dependent, t, q, t_dot, qd, qdd, p):
        """S = ½ m a·a."""
        m, a = self.inertia_terms(time_dependent, t, q, t_dot, qd, qdd, p)
        return 0.5 * m * jnp.dot(a, a)


class RigidBody(eqx.Module):
    """A rigid body.

    **Arguments:**

    - `mass`: a number, or a function m(p).
    - `inertia`: the 3×3 inertia tensor about the centre of mass in body axes, or a function
      I(p) returning it.
    - `position`: r_G(q, p) → (3,), the centre of mass in the world frame.
    - `orientation`: R(q, p) → (3, 3), body axes → world axes (see `jaxdyn.rotations`).

    Angular velocity comes from Ṙ: [ω_b]× = Rᵀ Ṙ (body axes), by one JVP of `orientation`.
    """

    mass: float | Callable = eqx.field(converter=frozen_constant)
    inertia: jax.Array | Callable = eqx.field(converter=frozen_constant)
    position: Callable
    orientation: Callable

    def _position(self, time_dependent, t, q, p):
        r = jnp.asarray(call(self.position, "RigidBody position", time_dependent,
                             CONFIGURATION_ARGS, t, q, p))
        if r.shape != (3,):
            raise ValueError(f"RigidBody position must return a 3-vector, got shape {r.shape}.")
        return r

    def _orientation(self, time_dependent, t, q, p):
        rotation = jnp.asarray(call(self.orientation, "RigidBody orientation", time_dependent,
                                    CONFIGURATION_ARGS, t, q, p))
        if rotation.shape != (3, 3):
            raise ValueError(
                f"RigidBody orientation must return a 3×3 rotation matrix, got shape "
                f"{rotation.shape}."
            )
        return rotation

    def _inertia(self, p):
        inertia = _value(self.inertia, p)
        if inertia.shape != (3, 3):
            raise ValueError(f"RigidBody inertia must be 3×3, got shape {inertia.shape}.")
        return inertia

    def velocity(self, time_dependent, t, q, t_dot, qd, p):
        """v_G, the velocity of the centre of mass."""
        return along_motion(lambda t, q: self._position(time_dependent, t, q, p),
                            t, q, t_dot, qd)[1]

    def angular_velocity(self, time_dependent, t, q, t_dot, qd, p):
        """ω in body axes, from [ω]× = Rᵀ Ṙ."""
        rotation, rotation_rate = along_motion(
            lambda t, q: self._orientation(time_dependent, t, q, p), t, q, t_dot, qd
        )
        return vee(rotation.T @ rotation_rate)

    def world_angular_velocity(self, time_dependent, t, q, t_dot, qd, p):
        """ω in world axes (R ω_b), the vector dotted with applied torques."""
        rotation = self._orientation(time_dependent, t, q, p)
        return rotation @ self.angular_velocity(time_dependent, t, q, t_dot, qd, p)

    def kinetic_energy(self, time_dependent, t, q, t_dot, qd, p):
        """T = ½ M v_G·v_G + ½ ω·I ω."""
        v = self.velocity(time_dependent, t, q, t_dot, qd, p)
        omega = self.angular_velocity(time_dependent, t, q, t_dot, qd, p)
        return 0.5 * (_value(self.mass, p) * jnp.dot(v, v)
                      + jnp.dot(omega, self._inertia(p) @ omega))

    def inertia_terms(self, time_dependent, t, q, t_dot, qd, qdd, p):
        """(M, a_G, I, ω, α), all in body axes for the rotational part; α = dω/dt."""
        def twist(t, q, qd):
            return (self.velocity(time_dependent, t, q, t_dot, qd, p),
                    self.angular_velocity(time_dependent, t, q, t_dot, qd, p))

        (_, omega), (a, alpha) = jax.jvp(twist, (t, q, qd), (t_dot, qd, qdd))
        return _value(self.mass, p), a, self._inertia(p), omega, alpha

    def gibbs_function(self, time_dependent, t, q, t_dot, qd, qdd, p):
        """S = ½ M a_G·a_G + ½ α·I α + α·(ω × I ω) (dropping terms free of α)."""
        m, a, inertia, omega, alpha = self.inertia_terms(time_dependent, t, q, t_dot, qd,
                                                         qdd, p)
        return (0.5 * m * jnp.dot(a, a) + 0.5 * jnp.dot(alpha, inertia @ alpha)
                + jnp.dot(alpha, jnp.cross(omega, inertia @ omega)))
