"""Generalized speeds u and the kinematic map q̇ = K(t, q, p) u.

With m speeds for n coordinates, m < n embeds nonholonomic (Pfaffian) constraints: the motion
allowed by A(q) q̇ = 0 is spanned by the columns of K (A K = 0). K = I (u = q̇) by default.
"""

import jax.numpy as jnp

from ._convention import CONFIGURATION_ARGS, call


def kinematic_matrix(kinematic_map, time_dependent, t, q, p, u=None):
    """K(t, q, p), shape (n, m); the identity when `kinematic_map` is None. With `u`, checks
    that K has one column per speed."""
    n = q.shape[0]
    if kinematic_map is None:
        if u is not None and u.shape[0] != n:
            raise ValueError(
                f"Without a kinematic_map the speeds are q̇, so u must have the shape of q "
                f"({n},), got {u.shape}. Pass kinematic_map=K with q̇ = K(q, p) u to use other "
                "speeds."
            )
        return jnp.eye(n, dtype=q.dtype)
    matrix = jnp.asarray(call(kinematic_map, "kinematic_map K", time_dependent,
                              CONFIGURATION_ARGS, t, q, p))
    return check_kinematic_matrix(matrix, q, u)


def check_kinematic_matrix(matrix, q, u=None):
    """K, after checking it has a row per coordinate (and a column per speed)."""
    n = q.shape[0]
    m = matrix.shape[-1] if u is None else u.shape[0]
    if matrix.shape != (n, m):
        raise ValueError(
            f"kinematic_map must return K of shape (n, m) = ({n}, {m}) for q of shape ({n},) "
            f"and u of shape ({m},), got {matrix.shape}."
        )
    return matrix
