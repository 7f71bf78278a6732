"""Contact geometry: points and spheres on a system, the terrain they may touch, and the
kinematics of each contact (signed distance, contact frame, velocity of the touching point).

A contact point is a sphere of radius r (r = 0: a point) whose centre c(q, p) moves with a link
of a `RigidBodyTree` (a point given in the link's axes) or is any function of the coordinates
(a particle, a body of a `MultibodySystem`, a point of a Lagrangian system). The terrain gives
at every point x of space a signed distance φ(x) (positive outside) and the unit normal n(x)
pointing out of it. For a sphere:

    gap g = φ(c) − r,     contact point x_C = c − r n(c),
    velocity of the body's material point at x_C:  v_C = v_c + ω × (x_C − c),

with ω the link's angular velocity (zero for a point of a system that is not a tree, whose
spheres then slide without rolling). g is differentiable everywhere: it is not clamped where
the bodies are apart, so that gradients see how far they are from touching (the force laws of
`jaxdyn._form.contact` are zero there, not the distance).

References: D. E. Stewart, Rigid-body dynamics with friction and impact, SIAM Review 42
(2000); F. Pfeiffer and C. Glocker, Multibody Dynamics with Unilateral Contacts (1996), ch. 3.
"""

import abc
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .tree import RigidBodyTree, _value, _vector3, ancestry, world_subspaces


class AbstractTerrain(eqx.Module):
    """What contact points may touch: a signed distance φ(x, p) and an outward unit normal."""

    @abc.abstractmethod
    def distance_and_normal(self, x, p) -> tuple[jax.Array, jax.Array]:
        """(φ, n) at a point x (3,) of the world: the signed distance (positive outside) and
        the unit normal pointing out of the terrain."""


class Plane(AbstractTerrain):
    """The half-space n·x ≤ h: the ground (default, z = 0) or a slope.

    **Arguments:**

    - `normal`: the outward normal (3,) (normalised here), or a function of p; default +z.
    - `height`: h, the plane's distance from the origin along the normal, or a function of p.

    `Plane.inclined(angle)`: the ground turned by `angle` about the y axis, so that "downhill"
    is +x: n = (sin γ, 0, cos γ).
    """

    normal: tuple | jax.Array | Callable = (0.0, 0.0, 1.0)
    height: float | Callable = 0.0

    @classmethod
    def inclined(cls, angle: float | Callable, height: float | Callable = 0.0) -> "Plane":
        """The plane through height·n with slope `angle` (radians, or a function of p)
        rising towards −x."""
        if callable(angle):
            def normal(p):
                gamma = jnp.asarray(angle(p))
                return jnp.stack([jnp.sin(gamma), jnp.zeros_like(gamma), jnp.cos(gamma)])

            return cls(normal, height)
        return cls((float(np.sin(angle)), 0.0, float(np.cos(angle))), height)

    def distance_and_normal(self, x, p):
        n = _value(self.normal, p).astype(x.dtype)
        if n.shape != (3,):
            raise ValueError(f"A plane's normal must be a 3-vector, got shape {n.shape}.")
        n = n / jnp.linalg.norm(n)
        return n @ x - _value(self.height, p).astype(x.dtype), n


class HeightField(AbstractTerrain):
    r"""Ground at the height z = h(x, y, p), any differentiable function (rolling hills,
    steps smoothed by the user, a fitted surface). To first order in the height above it,

        φ = (z − h) / √(1 + |∇h|²),     n = (−∂h/∂x, −∂h/∂y, 1) / √(1 + |∇h|²),

    exact for a plane and accurate to O(φ² |∇²h|) near the surface, where contact forces act.

    **Arguments:** `height`: h(x, y, p) → scalar.
    """

    height: Callable

    def distance_and_normal(self, x, p):
        h, (hx, hy) = jax.value_and_grad(lambda xy: self.height(xy[0], xy[1], p))(x[:2])
        scale = jnp.sqrt(1.0 + hx**2 + hy**2)
        return (x[2] - h) / scale, jnp.stack([-hx, -hy, jnp.ones_like(hx)]) / scale


class ContactPoint(eqx.Module):
    """A point or sphere that may touch the terrain.

    **Arguments:**

    - `body`: a link's name of the `RigidBodyTree` (the sphere's centre `point` is then in the
      link's axes; links attached by fixed joints count, as in `jaxdyn.frame_pose`), or a
      function c(q, p) → (3,) giving the centre in the world (any system).
    - `point`: the centre in the link's axes (default its origin); only with a link's name.
    - `radius`: r ≥ 0 (default 0: a point).
    - `name`: a label for records (default the link's name).

    Several points may share a link: a box's eight corners, a foot's sole.
    """

    body: str | Callable = eqx.field(static=True)
    point: tuple = eqx.field(static=True, default=(0.0, 0.0, 0.0),
                             converter=lambda x: _vector3(x, "A contact point's point"))
    radius: float = eqx.field(static=True, default=0.0, converter=float)
    name: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not (isinstance(self.body, str) or callable(self.body)):
            raise ValueError("A contact point's body is a link's name or a function c(q, p), "
                             f"got {self.body!r}.")
        if callable(self.body) and any(self.point):
            raise ValueError("A contact point given by a function c(q, p) takes no `point`: "
                             "put the offset in the function.")
        if not np.isfinite(self.radius) or self.radius < 0:
            raise ValueError(f"A contact sphere's radius must be finite and ≥ 0, got "
                             f"{self.radius}.")


def box_corners(link: str, size, centre=(0.0, 0.0, 0.0), rotation=None) -> list[ContactPoint]:
    """The eight corners of a box of edge lengths `size` (3,), centred at `centre` in the
    link's axes (turned by `rotation` (3, 3) if given), as contact points: a box on flat ground
    touches it at corners or along edges and faces, whose forces its corners carry."""
    size, centre = np.asarray(size, float), np.asarray(centre, float)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, float)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return [ContactPoint(link, centre + rotation @ (s * size / 2), name=f"{link}:corner{k}")
            for k, s in enumerate(signs)]


class ContactKinematics(eqx.Module):
    """Each contact's gap g (k,), normal n (k, 3), contact point x_C (k, 3), the velocity
    v_C (k, 3) of the body's material point there and its Jacobian J (k, 3, m) along the
    speeds, v_C = J u, all in world axes."""

    gap: jax.Array
    normal: jax.Array
    position: jax.Array
    velocity: jax.Array
    jacobian: jax.Array


def find_tree(dynamics) -> RigidBodyTree | None:
    """The `RigidBodyTree` a formulation was made from, looking through wrappers."""
    while dynamics is not None:
        tree = getattr(dynamics, "tree", None)
        if isinstance(tree, RigidBodyTree):
            return tree
        if isinstance(getattr(dynamics, "system", None), RigidBodyTree):
            return dynamics.system
        dynamics = getattr(dynamics, "dynamics", None)
    return None


def check_points(points: Sequence[ContactPoint], tree: RigidBodyTree | None):
    """Trace-time checks of the contact points against the system."""
    if isinstance(points, ContactPoint):
        points = (points,)
    points = tuple(points)
    if not points or not all(isinstance(c, ContactPoint) for c in points):
        raise ValueError("points must be a non-empty sequence of jaxdyn.ContactPoint, got "
                         f"{points!r}.")
    names = None if tree is None else [link.name for link in tree.links]
    for c in points:
        if isinstance(c.body, str):
            if names is None:
                raise ValueError(f"The contact point on {c.body!r} names a link, but the system "
                                 "is not made from a jaxdyn.RigidBodyTree: give its centre as a "
                                 "function c(q, p).")
            if c.body not in names:
                close = [n for n in names if c.body.lower() in n.lower()]
                hint = f" Did you mean one of {close}?" if close else ""
                raise ValueError(f"The tree has no link named {c.body!r}.{hint}")
    return points


def contact_kinematics(points, terrain: AbstractTerrain, tree, kinematics, t, q, u, p
                       ) -> ContactKinematics:
    """Gaps, normals, contact points, their velocities and Jacobians (module docstring) at one
    state.

    A point on a link moves with the speeds of the joints from the root to its link: its
    Jacobian's columns are those speeds' motion subspaces carried to the point (Featherstone,
    2008, §4.6; `world_subspaces`), from one pass of the tree's link poses, and zero for
    the other speeds; no derivative is taken. A point given as a function c(q, p) has the
    Jacobian (∂c/∂q) K (`kinematics` gives q̇ = K(t, q, p) u, linear in u)."""
    dtype = q.dtype
    m = u.shape[0]
    centres, jacobians, turning = [], [], []
    if any(isinstance(c.body, str) for c in points):
        index = {link.name: i for i, link in enumerate(tree.links)}
        rotations, origins = tree.link_poses(t, q, p)
    for c in points:
        if isinstance(c.body, str):
            chain, _, u_index = ancestry(tree, index[c.body])
            links = RigidBodyTree([tree.links[k] for k in chain])
            rotation, origin = rotations[np.array(chain)], origins[np.array(chain)]
            centre = origin[-1] + rotation[-1] @ jnp.asarray(c.point, dtype)
            omega, velocity = world_subspaces(links, rotation, origin, centre)
            full = jnp.zeros((2, 3, m), dtype).at[:, :, u_index].set(
                jnp.stack([omega.T, velocity.T]))
            centres.append(centre)
            turning.append(full[0])
            jacobians.append(full[1])
        else:
            centre = jnp.asarray(c.body(q, p), dtype)
            if centre.shape != (3,):
                raise ValueError(f"A contact point's function c(q, p) must return a 3-vector "
                                 f"in the world, got shape {centre.shape}.")
            # (∂c/∂q) K column by column: K is linear in u
            jacobian = jax.jacfwd(lambda u: jax.jvp(
                lambda q: jnp.asarray(c.body(q, p), dtype), (q,),
                (kinematics(t, q, u, p),))[1])(u)
            centres.append(centre)
            turning.append(jnp.zeros((3, m), dtype))  # (a point: no turning)
            jacobians.append(jacobian)
    centre, omega, jacobian = jnp.stack(centres), jnp.stack(turning), jnp.stack(jacobians)
    distance, normal = jax.vmap(lambda x: terrain.distance_and_normal(x, p))(centre)
    radius = jnp.asarray(np.array([c.radius for c in points]), dtype)
    arm = -radius[:, None] * normal  # from the centre to the contact point
    # v_C = v_c + ω × arm, column by column: J_C = J_c − [arm]× J_ω
    jacobian = jacobian + jnp.cross(omega, arm[:, :, None], axisa=1, axisb=1, axisc=1)
    return ContactKinematics(gap=distance - radius, normal=normal, position=centre + arm,
                             velocity=jacobian @ u, jacobian=jacobian)
