"""Joints: how a link moves relative to its parent.

A joint moves the link's frame C relative to the joint frame F fixed in the parent (see
`jaxdyn.Link`): C's pose in F is (R_J(q), r_J(q)). Its speeds u are chosen so that the motion
subspace S (the link's spatial velocity relative to F, in C's axes, is S u) is constant:

| joint | q | u | S u = (ω, v) in C's axes |
| --- | --- | --- | --- |
| `Revolute(axis)` | angle θ | θ̇ | (a θ̇, 0) |
| `Prismatic(axis)` | displacement s | ṡ | (0, a ṡ) |
| `Spherical()` | unit quaternion (w, x, y, z) | ω (C's axes) | (ω, 0) |
| `Planar()` | (x, y, θ) in F's xy plane | (v_x, v_y, ω) in C's axes | ((0, 0, ω), (v_x, v_y, 0)) |
| `Free()` | (r (3, in F), quaternion (4)) | (v, ω), both in C's axes | (ω, v) |
| `Fixed()` | — | — | — |

q̇ = K(q) u (`rate_matrix`): the identity for revolute and prismatic joints, quaternion
kinematics q̇ = ½ q ⊗ (0, ω) for spherical and free joints, a rotation for the planar joint's
translation. Every method broadcasts over leading axes, so that the joints of one type in a
tree are evaluated together (their parameters stacked).
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import spatial


class AbstractJoint(eqx.Module):
    """A joint type: its coordinates (nq), speeds (nv) and motion."""

    nq: eqx.AbstractClassVar[int]
    nv: eqx.AbstractClassVar[int]

    @abc.abstractmethod
    def transform(self, q) -> tuple[jax.Array, jax.Array]:
        """(R_J, r_J): the pose of the link frame in the joint frame, for coordinates q."""

    def placed_transform(self, rotation, translation, q) -> tuple[jax.Array, jax.Array]:
        """(R_PC, r_PC) = (R_F R_J, r_F + R_F r_J): the link frame's pose in its parent, the
        joint frame F sitting at (R_F, r_F) (constant, NumPy, stacked like q's leading axes)."""
        rotation_j, translation_j = self.transform(q)
        rotation = jnp.asarray(rotation, q.dtype)
        return (spatial.matmul(rotation, rotation_j),
                jnp.asarray(translation, q.dtype) + spatial.matvec(rotation, translation_j))

    @abc.abstractmethod
    def twist(self, u) -> tuple[jax.Array, jax.Array]:
        """(ω, v) = S u: the link's velocity relative to the joint frame, in its own axes."""

    @abc.abstractmethod
    def subspace(self) -> np.ndarray:
        """S (6 × nv), rows (ω, v): constant in the link's axes."""

    @abc.abstractmethod
    def rate_matrix(self, q) -> jax.Array:
        """K (nq × nv) with q̇ = K u."""

    @abc.abstractmethod
    def neutral(self) -> np.ndarray:
        """The coordinates of the joint at rest (angle 0, identity quaternion)."""

    def speeds(self, q, qd):
        """u from q̇, where K is invertible."""
        raise ValueError(
            f"A {type(self).__name__} joint's speeds are not the rates of its coordinates (its "
            "quaternion has one coordinate more than it has speeds), so Lagrange's equations in "
            "q̇ do not apply. Use the Gibbs–Appell, Kane or articulated-body formulation."
        )


def _along(axis, x):
    """x (…, 1) times a constant axis (3,): (…, 3)."""
    return x * jnp.broadcast_to(jnp.asarray(axis, x.dtype), x.shape[:-1] + (3,))


def _unit(axis) -> tuple[float, float, float]:
    """A unit axis as a tuple of floats: static, so that a joint's structure (say, rotation
    about z) is known at trace time and its zeros fold away."""
    axis = np.asarray(axis, dtype=float)
    norm = np.linalg.norm(axis) if axis.shape == (3,) else 0.0
    if norm == 0:
        raise ValueError(f"A joint axis must be a non-zero 3-vector, got {axis.tolist()}.")
    x, y, z = axis / norm
    return float(x), float(y), float(z)


class _AlongAxis(AbstractJoint):
    """A joint with one coordinate along or about a unit `axis`, its rate the speed."""

    axis: tuple[float, float, float] = eqx.field(static=True, converter=_unit,
                                                 default=(0.0, 0.0, 1.0))
    nq: ClassVar[int] = 1
    nv: ClassVar[int] = 1

    def rate_matrix(self, q):
        return jnp.ones(q.shape[:-1] + (1, 1), q.dtype)

    def neutral(self):
        return np.zeros(1)

    def speeds(self, q, qd):
        return qd


class Revolute(_AlongAxis):
    """Rotation by an angle θ about `axis` (a unit vector in the joint frame; normalised)."""

    def transform(self, q):
        axis = jnp.asarray(self.axis, q.dtype)
        return spatial.axis_rotation(axis, q[..., 0]), jnp.zeros(q.shape[:-1] + (3,), q.dtype)

    def placed_transform(self, rotation, translation, q):
        # R_F exp(θ [a]×) = R_F a aᵀ + cos θ R_F (1 − a aᵀ) + sin θ R_F [a]×: three constant
        # matrices, so that no 3 × 3 product is left to run time.
        a = np.asarray(self.axis)
        along = rotation @ np.outer(a, a)
        skew = np.cross(a, -np.eye(3))  # [a]×: row i is e_i × a, so that [a]× v = a × v
        c, s = jnp.cos(q[..., 0])[..., None, None], jnp.sin(q[..., 0])[..., None, None]
        rotation_pc = (jnp.asarray(along, q.dtype) + c * jnp.asarray(rotation - along, q.dtype)
                       + s * jnp.asarray(rotation @ skew, q.dtype))
        return rotation_pc, jnp.broadcast_to(jnp.asarray(translation, q.dtype),
                                             q.shape[:-1] + (3,))

    def twist(self, u):
        return _along(self.axis, u), jnp.zeros(u.shape[:-1] + (3,), u.dtype)

    def subspace(self):
        return np.concatenate([self.axis, np.zeros(3)])[:, None]


class Prismatic(_AlongAxis):
    """Translation by a distance s along `axis` (a unit vector in the joint frame)."""

    def transform(self, q):
        rotation = jnp.broadcast_to(jnp.eye(3, dtype=q.dtype), q.shape[:-1] + (3, 3))
        return rotation, _along(self.axis, q)

    def placed_transform(self, rotation, translation, q):
        # (R_F, r_F + (R_F a) s): the rotation is constant, the translation one product.
        turned = rotation @ np.asarray(self.axis)
        return (jnp.broadcast_to(jnp.asarray(rotation, q.dtype), q.shape[:-1] + (3, 3)),
                jnp.asarray(translation, q.dtype) + jnp.asarray(turned, q.dtype) * q)

    def twist(self, u):
        return jnp.zeros(u.shape[:-1] + (3,), u.dtype), _along(self.axis, u)

    def subspace(self):
        return np.concatenate([np.zeros(3), self.axis])[:, None]


class Spherical(AbstractJoint):
    """A ball joint: any rotation, as a unit quaternion (w, x, y, z); speeds are the angular
    velocity in the link's axes."""

    nq: ClassVar[int] = 4
    nv: ClassVar[int] = 3

    def transform(self, q):
        return spatial.quaternion_rotation(q), jnp.zeros_like(q[..., :3])

    def twist(self, u):
        return u, jnp.zeros_like(u)

    def subspace(self):
        return np.concatenate([np.eye(3), np.zeros((3, 3))])

    def rate_matrix(self, q):
        return spatial.quaternion_rate_matrix(q)

    def neutral(self):
        return np.array([1.0, 0.0, 0.0, 0.0])


class Planar(AbstractJoint):
    """Motion in the joint frame's xy plane: coordinates (x, y, θ), speeds the velocity
    (v_x, v_y) and rate of turn ω in the link's axes."""

    nq: ClassVar[int] = 3
    nv: ClassVar[int] = 3

    def transform(self, q):
        rotation = spatial.axis_rotation(jnp.array([0.0, 0.0, 1.0], dtype=q.dtype), q[..., 2])
        return rotation, jnp.stack([q[..., 0], q[..., 1], jnp.zeros_like(q[..., 0])], -1)

    def twist(self, u):
        zero = jnp.zeros_like(u[..., 0])
        return (jnp.stack([zero, zero, u[..., 2]], -1),
                jnp.stack([u[..., 0], u[..., 1], zero], -1))

    def subspace(self):
        s = np.zeros((6, 3))
        s[2, 2] = s[3, 0] = s[4, 1] = 1.0
        return s

    def rate_matrix(self, q):
        c, s = jnp.cos(q[..., 2]), jnp.sin(q[..., 2])
        zero, one = jnp.zeros_like(c), jnp.ones_like(c)
        return jnp.stack([jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1),
                          jnp.stack([zero, zero, one], -1)], -2)

    def neutral(self):
        return np.zeros(3)

    def speeds(self, q, qd):
        c, s = jnp.cos(q[..., 2]), jnp.sin(q[..., 2])
        return jnp.stack([c * qd[..., 0] + s * qd[..., 1], -s * qd[..., 0] + c * qd[..., 1],
                          qd[..., 2]], -1)


class Free(AbstractJoint):
    """A free-floating link (6 degrees of freedom): position r of its origin in the joint
    frame and orientation as a unit quaternion (w, x, y, z), q = (r, quaternion); speeds
    u = (v, ω), the velocity of its origin and its angular velocity, both in its own axes."""

    nq: ClassVar[int] = 7
    nv: ClassVar[int] = 6

    def transform(self, q):
        return spatial.quaternion_rotation(q[..., 3:]), q[..., :3]

    def twist(self, u):
        return u[..., 3:], u[..., :3]

    def subspace(self):
        s = np.zeros((6, 6))
        s[:3, 3:] = np.eye(3)
        s[3:, :3] = np.eye(3)
        return s

    def rate_matrix(self, q):
        rotation = spatial.quaternion_rotation(q[..., 3:])  # ṙ = R v
        rates = spatial.quaternion_rate_matrix(q[..., 3:])
        zeros = jnp.zeros(q.shape[:-1] + (3, 3), q.dtype)
        return jnp.concatenate([jnp.concatenate([rotation, zeros], -1),
                                jnp.concatenate([zeros[..., :1, :].repeat(4, -2), rates], -1)],
                               -2)

    def neutral(self):
        return np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])


class Fixed(AbstractJoint):
    """A rigid attachment: the link moves with its parent."""

    nq: ClassVar[int] = 0
    nv: ClassVar[int] = 0

    def transform(self, q):
        return jnp.broadcast_to(jnp.eye(3, dtype=q.dtype), q.shape[:-1] + (3, 3)), \
            jnp.zeros(q.shape[:-1] + (3,), q.dtype)

    def twist(self, u):
        zero = jnp.zeros(u.shape[:-1] + (3,), u.dtype)
        return zero, zero

    def subspace(self):
        return np.zeros((6, 0))

    def rate_matrix(self, q):
        return jnp.zeros(q.shape[:-1] + (0, 0), q.dtype)

    def neutral(self):
        return np.zeros(0)

    def speeds(self, q, qd):
        return qd
