"""The links of a `RigidBodyTree`: each a rigid body and the joint that moves it in its parent
(`Link`), the loads applied to them (`LinkLoad`), and links welded together by fixed joints
into one body (`_Welded`, whose mass, centre of mass and inertia combine theirs by
Huygens–Steiner; Featherstone, Rigid Body Dynamics Algorithms, 2008, ch. 2). Their inertial
parameters are numbers or functions of the parameters p (`_value`), so that they can be fitted.
"""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._state import frozen_constant
from .joints import AbstractJoint


def _vector3(x, name):
    x = np.asarray(x, dtype=float)
    if x.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {x.shape}.")
    return tuple(float(a) for a in x)


def _rotation(x):
    x = np.eye(3) if x is None else np.asarray(x, dtype=float)
    if x.shape != (3, 3):
        raise ValueError(f"A link's rotation must be a 3×3 matrix, got shape {x.shape}.")
    if not np.allclose(x.T @ x, np.eye(3), atol=1e-9) or np.linalg.det(x) < 0:
        raise ValueError("A link's rotation must be a proper rotation matrix (RᵀR = I, det 1).")
    return tuple(tuple(float(a) for a in row) for row in x)


def _value(x, p):
    return jnp.asarray(x(p) if callable(x) else x)


class LinkParameter(eqx.Module):
    """Reads a link's inertial value from the parameters: p[link][key] (`from_urdf`'s links;
    the library's own lookup, which the trace-time check of the user's callables skips)."""

    link: str = eqx.field(static=True)
    key: str = eqx.field(static=True)

    def __call__(self, p):
        return p[self.link][self.key]


def users_callable(x) -> bool:
    """Whether a link's or tree's value is a function the user wrote (not a number, an array
    or the library's `LinkParameter`): what `check_static_indexing` needs to run."""
    return callable(x) and not isinstance(x, LinkParameter)


class Link(eqx.Module):
    """A rigid link of a `RigidBodyTree`, and the joint that moves it relative to its parent.

    **Arguments:**

    - `name`: unique within the tree.
    - `joint`: a `jaxdyn.Revolute`, `Prismatic`, `Spherical`, `Planar`, `Free` or `Fixed`.
    - `parent`: the parent link's name, or None for the world (a fixed base).
    - `translation`, `rotation`: the joint frame's placement in the parent's frame (origin,
      and axes as the columns of a rotation matrix); the link's frame coincides with the joint
      frame when the joint is at rest (q = 0, identity quaternion).
    - `mass`, `com` (centre of mass, link frame), `inertia` (3 × 3, about the centre of mass,
      link axes): numbers/arrays, or functions of the parameters p (to fit them).
    - `stiffness`, `damping`, `rest`: a joint spring ½ k (q − rest)² and damper −c q̇ (for
      revolute and prismatic joints); numbers or functions of p, or None.
    """

    name: str = eqx.field(static=True)
    joint: AbstractJoint
    parent: str | None = eqx.field(static=True, default=None)
    translation: tuple = eqx.field(static=True, default=(0.0, 0.0, 0.0),
                                   converter=lambda x: _vector3(x, "A link's translation"))
    rotation: tuple = eqx.field(static=True, default=None, converter=_rotation)
    mass: float | Callable = eqx.field(default=0.0, converter=frozen_constant)
    com: jax.Array | Callable = eqx.field(default=(0.0, 0.0, 0.0), converter=frozen_constant)
    inertia: jax.Array | Callable | None = eqx.field(default=None, converter=frozen_constant)
    stiffness: float | Callable | None = eqx.field(default=None, converter=frozen_constant)
    damping: float | Callable | None = eqx.field(default=None, converter=frozen_constant)
    rest: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if not isinstance(self.joint, AbstractJoint):
            raise ValueError(f"Link {self.name!r}: joint must be a jaxdyn joint (Revolute, "
                             f"Prismatic, Spherical, Planar, Free, Fixed), got "
                             f"{type(self.joint).__name__}.")
        if (self.stiffness is not None or self.damping is not None) and self.joint.nv != 1:
            raise ValueError(f"Link {self.name!r}: joint springs and dampers apply to "
                             "revolute and prismatic joints (one coordinate).")


class LinkLoad(eqx.Module):
    """A force (at a point of a link) and a torque applied to a link, in world axes.

    **Arguments:**

    - `link`: the link's name.
    - `force`: F(q, u, p) → (3,) in world axes, or None.
    - `torque`: τ(q, u, p) → (3,) in world axes, or None.
    - `point`: where the force acts, in the link's frame (default its origin).

    Both take t first in a time-dependent tree.
    """

    link: str = eqx.field(static=True)
    force: Callable | None = None
    torque: Callable | None = None
    point: tuple = eqx.field(static=True, default=(0.0, 0.0, 0.0),
                             converter=lambda x: _vector3(x, "A load's point"))


class _Welded(eqx.Module):
    """The mass, centre of mass or central inertia of links welded together by fixed joints,
    in the axes of the first (the body): with link k placed at (R_k, r_k) in the body,

        m = Σ m_k,   c = Σ m_k c'_k / m  (c'_k = r_k + R_k c_k),
        I = Σ R_k I_k R_kᵀ + m_k (|d_k|² 1 − d_k d_kᵀ),   d_k = c'_k − c

    (Huygens–Steiner). A body of no mass has its centre at its origin."""

    links: tuple[Link, ...]
    rotations: tuple = eqx.field(static=True)
    translations: tuple = eqx.field(static=True)
    part: str = eqx.field(static=True)

    def __call__(self, p):
        combined = welded_inertias([(self.links, self.rotations, self.translations)], p)
        return combined[("mass", "com", "inertia").index(self.part)][0]


def welded_inertias(bodies, p, dtype=None):
    """(masses (B,), centres of mass (B, 3), central inertias (B, 3, 3)) of B bodies, each
    links welded together, given as (links, rotations R_k, translations r_k in the body's
    axes), by Huygens–Steiner as in `_Welded`; a body of no mass has its centre at its origin.

    All bodies at once, as arrays over all their links (each body's sums a product with a
    constant 0/1 matrix): written out per body, or per link, this work on the parameters
    alone was half of ANYmal-C's forward dynamics program (half its compile time and half
    its run, `benchmarks/LOG.md`)."""
    links = [link for body in bodies for link in body[0]]
    body_of = np.repeat(np.arange(len(bodies)), [len(body[0]) for body in bodies])
    masses = [jnp.asarray(_value(link.mass, p)) for link in links]
    dtype = jnp.result_type(*masses, float) if dtype is None else dtype
    masses = jnp.stack(masses).astype(dtype)
    summed = np.zeros((len(bodies), len(links)), dtype)
    summed[body_of, np.arange(len(links))] = 1.0
    rotations = np.asarray([r for body in bodies for r in body[1]], dtype)
    translations = np.asarray([r for body in bodies for r in body[2]], dtype)
    coms = [jnp.asarray(_value(link.com, p), dtype) for link in links]
    zero = np.zeros((3, 3), dtype)
    inertias = [zero if link.inertia is None else jnp.asarray(_value(link.inertia, p), dtype)
                for link in links]
    for name, values, shape in (("com", coms, (3,)), ("inertia", inertias, (3, 3))):
        if any(value.shape != shape for value in values):
            raise ValueError(f"Every link's {name} must have shape {shape}.")
    centres = translations + jnp.einsum("kij,kj->ki", rotations, jnp.stack(coms))
    mass = summed @ masses
    # Massless bodies (URDF's dummy links) have their centre at the origin: a safe divisor
    # keeps the derivative finite where the mass is zero.
    massless = (mass == 0)[:, None]
    centre = jnp.where(massless, 0.0, (summed @ (masses[:, None] * centres))
                       / jnp.where(massless, 1.0, mass[:, None]))
    d = centres - summed.T @ centre
    about_centre = (jnp.einsum("kij,kjl,kml->kim", rotations, jnp.stack(inertias), rotations)
                    + masses[:, None, None] * (jnp.sum(d * d, axis=1)[:, None, None]
                                               * np.eye(3, dtype=dtype)[None]
                                               - d[:, :, None] * d[:, None, :]))
    return mass, centre, jnp.einsum("bk,kij->bij", summed, about_centre)


def own_inertias(links, p, dtype=None):
    """(masses (N,), centres of mass (N, 3), central inertias (N, 3, 3)) of N links, each
    its own values (no link welded to another)."""
    masses = jnp.stack([jnp.asarray(_value(link.mass, p)) for link in links])
    dtype = masses.dtype if dtype is None else dtype
    coms = jnp.stack([jnp.asarray(_value(link.com, p), dtype) for link in links])
    zero = jnp.zeros((3, 3), dtype)
    inertias = jnp.stack([zero if link.inertia is None
                          else jnp.asarray(_value(link.inertia, p), dtype) for link in links])
    for name, value, shape in (("com", coms, (len(links), 3)),
                               ("inertia", inertias, (len(links), 3, 3))):
        if value.shape != shape:
            raise ValueError(f"Every link's {name} must have shape {shape[1:]}.")
    return masses.astype(dtype), coms, inertias
