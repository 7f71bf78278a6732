"""Rotation matrices for `RigidBody.orientation`: planar angle, axis rotations, Euler angles,
quaternions."""

from ._system.rotations import (
    euler_angles as euler_angles,
    planar_rotation as planar_rotation,
    quaternion as quaternion,
    rotation_x as rotation_x,
    rotation_y as rotation_y,
    rotation_z as rotation_z,
)
