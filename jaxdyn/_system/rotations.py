"""Rotation matrices R (body axes → world axes) for common parametrisations."""

import jax.numpy as jnp


def _axis_rotation(angle, i: int, j: int):
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    rows = [[one, zero, zero], [zero, one, zero], [zero, zero, one]]
    rows[i][i], rows[i][j], rows[j][i], rows[j][j] = c, -s, s, c
    return jnp.stack([jnp.stack(row) for row in rows])


def rotation_x(angle):
    """Rotation by `angle` about the x axis."""
    return _axis_rotation(angle, 1, 2)


def rotation_y(angle):
    """Rotation by `angle` about the y axis."""
    return _axis_rotation(angle, 2, 0)


def rotation_z(angle):
    """Rotation by `angle` about the z axis."""
    return _axis_rotation(angle, 0, 1)


def planar_rotation(angle):
    """Orientation of a body moving in the xy plane, turned by `angle` about z."""
    return rotation_z(angle)


_AXES = {"x": rotation_x, "y": rotation_y, "z": rotation_z}


def euler_angles(angles, sequence: str = "zxz"):
    """R = R_a(θ₁) R_b(θ₂) R_c(θ₃) for intrinsic (body-fixed) rotations in `sequence`.

    "zxz" gives the classical precession ψ, nutation θ, spin φ; "zyx" gives yaw, pitch, roll.
    Singular (gimbal lock) where the middle rotation aligns the first and third axes.
    """
    if len(sequence) != 3 or any(a not in _AXES for a in sequence):
        raise ValueError(f"sequence must be three of 'x', 'y', 'z', got {sequence!r}.")
    if jnp.shape(angles) != (3,):
        raise ValueError(f"euler_angles takes three angles, got shape {jnp.shape(angles)}.")
    a, b, c = (_AXES[axis] for axis in sequence)
    return a(angles[0]) @ b(angles[1]) @ c(angles[2])


def quaternion(quat):
    """R from a quaternion (w, x, y, z); it is normalised first, so any non-zero 4-vector
    gives a rotation (the scale is a gauge freedom: fix it with a constraint or stabilisation
    when the quaternion is a coordinate)."""
    if jnp.shape(quat) != (4,):
        raise ValueError(f"quaternion takes a 4-vector (w, x, y, z), got shape {jnp.shape(quat)}.")
    w, x, y, z = quat / jnp.linalg.norm(quat)
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
