"""Generalized speeds u and the kinematic map q̇ = K(t, q, p) u.

With m speeds for n coordinates, m < n embeds nonholonomic (Pfaffian) constraints: the motion
allowed by A(q) q̇ = 0 is spanned by the columns of K (A K = 0). K = I (u = q̇) by default.
"""

import jax
import jax.numpy as jnp

from ._convention import CONFIGURATION_ARGS, call


def kinematic_matrix(kinematic_map, time_dependent, t, q, u, p):
    """K(t, q, p), shape (n, m); the identity when `kinematic_map` is None."""
    n, m = q.shape[0], u.shape[0]
    if kinematic_map is None:
        if n != m:
            raise ValueError(
                f"Without a kinematic_map the speeds are q̇, so u must have the shape of q "
                f"({n},), got {u.shape}. Pass kinematic_map=K with q̇ = K(q, p) u to use other "
                "speeds."
            )
        return jnp.eye(n, dtype=q.dtype)
    matrix = jnp.asarray(call(kinematic_map, "kinematic_map K", time_dependent,
                              CONFIGURATION_ARGS, t, q, p))
    if matrix.shape != (n, m):
        raise ValueError(
            f"kinematic_map must return K of shape (n, m) = ({n}, {m}) for q of shape ({n},) "
            f"and u of shape ({m},), got {matrix.shape}."
        )
    return matrix


def coordinate_motion(kinematic_map, time_dependent, t, q, t_dot, u, ud, p):
    """(q̇, q̈) = (K u, K̇ u + K u̇), with K̇ = dK/dt along the motion by one JVP."""
    def matrix(t, q):
        return kinematic_matrix(kinematic_map, time_dependent, t, q, u, p)

    if kinematic_map is None:  # K = I: skip the JVP
        return u, ud
    k = matrix(t, q)
    qd = k @ u
    k_dot = jax.jvp(matrix, (t, q), (t_dot, qd))[1]
    return qd, k_dot @ u + k @ ud
