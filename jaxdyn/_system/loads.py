"""Applied loads: forces at points and torques on rigid bodies."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import CONFIGURATION_ARGS, VELOCITY_ARGS, call
from .bodies import RigidBody, along_motion


def _load(fn, name, time_dependent, t, q, qd, p):
    value = jnp.asarray(call(fn, name, time_dependent, VELOCITY_ARGS, t, q, qd, p))
    if value.shape != (3,):
        raise ValueError(f"{name} must return a 3-vector in world axes, got shape {value.shape}.")
    return value


def _dot_partials(velocity, qd, load):
    """Q_j = load · ∂velocity/∂q̇_j for all j: one vector–Jacobian product."""
    return jax.vjp(velocity, qd)[1](load)[0]


class PointForce(eqx.Module):
    """A force F(q, qd, p) (world axes) applied at the point r(q, p).

    Its generalized force is Q_j = F·∂ṙ/∂q̇_j: the force dotted with the point's partial
    velocities.
    """

    point: Callable
    force: Callable

    def generalized_force(self, time_dependent, t, q, t_dot, qd, p):
        """Q (n,), Q_j = F·∂ṙ/∂q̇_j, at (t, q, q̇) (one vector–Jacobian product);
        `time_dependent` and `t_dot` as the `MultibodySystem` that holds the load passes them
        (called by it, not by users)."""
        def position(t, q):
            r = jnp.asarray(call(self.point, "PointForce point", time_dependent,
                                 CONFIGURATION_ARGS, t, q, p))
            if r.shape != (3,):
                raise ValueError(f"PointForce point must return a 3-vector, got {r.shape}.")
            return r

        def velocity(qd):
            return along_motion(position, t, q, t_dot, qd)[1]

        force = _load(self.force, "PointForce force", time_dependent, t, q, qd, p)
        return _dot_partials(velocity, qd, force)


class BodyTorque(eqx.Module):
    """A torque τ(q, qd, p) (world axes) applied to a rigid body.

    Its generalized force is Q_j = τ·∂ω/∂q̇_j (partial angular velocities).
    """

    body: RigidBody
    torque: Callable

    def generalized_force(self, time_dependent, t, q, t_dot, qd, p):
        """Q (n,), Q_j = τ·∂ω/∂q̇_j, at (t, q, q̇) (one vector–Jacobian product);
        `time_dependent` and `t_dot` as the `MultibodySystem` that holds the load passes them
        (called by it, not by users)."""
        def angular_velocity(qd):
            return self.body.world_angular_velocity(time_dependent, t, q, t_dot, qd, p)

        torque = _load(self.torque, "BodyTorque torque", time_dependent, t, q, qd, p)
        return _dot_partials(angular_velocity, qd, torque)
