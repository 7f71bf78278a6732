"""Rigid-body motion in 3D: rotations, quaternions and the spatial (6D) algebra of motion and
force vectors, vectorised over leading axes.

Conventions (Featherstone, Rigid Body Dynamics Algorithms, 2008, ch. 2): a spatial motion
vector is m = (ω, v), the angular velocity and the velocity of the frame's origin, both in the
frame's axes; a spatial force is f = (n, f), the moment about the origin and the force. A frame
C placed in a frame P by a rotation R (columns: C's axes in P) and an origin r (in P) maps
motion vectors from P to C by

    ω_C = Rᵀ ω_P,    v_C = Rᵀ (v_P + ω_P × r)

and force vectors from C back to P by n_P = R n_C + r × R f_C, f_P = R f_C. Quaternions are
(w, x, y, z), scalar first, as in `jaxdyn.rotations.quaternion`.
"""

import jax.numpy as jnp


def cross(a, b):
    """a × b for 3-vectors on the last axis (written out, so that it fuses)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def dot(a, b):
    a, b = jnp.broadcast_arrays(a, b)
    return jnp.sum(a * b, axis=-1)


def matvec(m, v):
    """m v for 3×3 matrices and 3-vectors on the last axes."""
    return jnp.sum(m * v[..., None, :], axis=-1)


def tmatvec(m, v):
    """mᵀ v."""
    return jnp.sum(m * v[..., :, None], axis=-2)


def matmul(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def axis_rotation(axis, angle):
    """R = exp(angle [axis]×) for a unit axis (Rodrigues' formula); `axis` (3,) or batched
    like `angle`."""
    axis = jnp.broadcast_to(axis, jnp.shape(angle) + (3,))
    c, s = jnp.cos(angle)[..., None, None], jnp.sin(angle)[..., None, None]
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = jnp.zeros_like(x)
    skew = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                      jnp.stack([-y, x, zero], -1)], -2)
    outer = axis[..., :, None] * axis[..., None, :]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=skew.dtype), skew.shape)
    return c * eye + s * skew + (1 - c) * outer


def quaternion_rotation(quaternion):
    """R from a quaternion (w, x, y, z), normalised first: its kinematics q̇ = ½ q ⊗ (0, ω)
    keep it unit only up to the solver's tolerance, and every formulation then sees the same
    exact rotation (the scale is a direction the dynamics does not depend on)."""
    quaternion = quaternion / jnp.sqrt(jnp.sum(quaternion**2, axis=-1, keepdims=True))
    w, x, y, z = (quaternion[..., i] for i in range(4))
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def quaternion_rate_matrix(quaternion):
    """G with q̇ = G ω for a body angular velocity ω (body axes): q̇ = ½ q ⊗ (0, ω)."""
    w, x, y, z = (quaternion[..., i] for i in range(4))
    return 0.5 * jnp.stack([
        jnp.stack([-x, -y, -z], -1),
        jnp.stack([w, -z, y], -1),
        jnp.stack([z, w, -x], -1),
        jnp.stack([-y, x, w], -1),
    ], -2)


def motion_to_child(rotation, origin, omega, velocity):
    """A motion vector (ω, v) of the parent frame in the child's axes (see module docstring)."""
    return tmatvec(rotation, omega), tmatvec(rotation, velocity + cross(omega, origin))


def force_to_parent(rotation, origin, moment, force):
    """A force vector (n, f) given in the child frame, in the parent frame."""
    force_parent = matvec(rotation, force)
    return matvec(rotation, moment) + cross(origin, force_parent), force_parent


def cross_motion(omega, velocity, m_omega, m_velocity):
    """(ω, v) ×ₘ (m_ω, m_v): the rate of a motion vector fixed in a moving frame."""
    return cross(omega, m_omega), cross(omega, m_velocity) + cross(velocity, m_omega)


def cross_force(omega, velocity, moment, force):
    """(ω, v) ×* (n, f): the rate of a force vector fixed in a moving frame."""
    return cross(omega, moment) + cross(velocity, force), cross(omega, force)


def inertia_times(mass, com, inertia, omega, velocity):
    """The spatial inertia of a body (mass, centre of mass `com` and rotational inertia about
    it, in the body frame) applied to a motion vector: the momentum (n, f) about the origin,

        f = m (v + ω × c),    n = I_c ω + c × f.
    """
    force = mass[..., None] * (velocity + cross(omega, com))
    return matvec(inertia, omega) + cross(com, force), force
