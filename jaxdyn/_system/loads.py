"""Applied loads: forces at points and torques on rigid bodies."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import CONFIGURATION_ARGS, VELOCITY_ARGS, call
from .bodies import RigidBody, along_motion


def _load_vector(value, name):
    value = jnp.asarray(value)
    if value.shape != (3,):
        raise ValueError(f"{name} must return a 3-vector in world axes, got shape {value.shape}.")
    return value


class PointForce(eqx.Module):
    """A force F(q, qd, p) (world axes) applied at the point r(q, p).

    Its generalized force is Q_j = F·∂ṙ/∂q̇_j, the force dotted with the point's partial
    velocities: a vector–Jacobian product of the point's velocity in q̇.
    """

    point: Callable
    force: Callable

    def generalized_force(self, time_dependent, t, q, t_dot, qd, p):
        force = _load_vector(call(self.force, "PointForce force", time_dependent,
                                  VELOCITY_ARGS, t, q, qd, p), "PointForce force")

        def velocity(qd):
            position = lambda t, q: _load_vector(
                call(self.point, "PointForce point", time_dependent, CONFIGURATION_ARGS,
                     t, q, p), "PointForce point")
            return along_motion(position, t, q, t_dot, qd)[1]

        return jax.vjp(velocity, qd)[1](force)[0]


class BodyTorque(eqx.Module):
    """A torque τ(q, qd, p) (world axes) applied to a rigid body.

    Its generalized force is Q_j = τ·∂ω/∂q̇_j (partial angular velocities).
    """

    body: RigidBody
    torque: Callable

    def generalized_force(self, time_dependent, t, q, t_dot, qd, p):
        torque = _load_vector(call(self.torque, "BodyTorque torque", time_dependent,
                                   VELOCITY_ARGS, t, q, qd, p), "BodyTorque torque")

        def angular_velocity(qd):
            return self.body.world_angular_velocity(time_dependent, t, q, t_dot, qd, p)

        return jax.vjp(angular_velocity, qd)[1](torque)[0]
