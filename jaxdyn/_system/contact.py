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
spheres then slide without rolling). Two spheres c₁, c₂ (`ContactPair`) touch each other
with g = |c₁ − c₂| − r₁ − r₂, n = (c₁ − c₂)/|c₁ − c₂|, x_C the midpoint of their surfaces'
nearest points and v_C the first's material point's velocity there relative to the second's.
g is differentiable everywhere: it is not clamped where
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

from .links import _value, _vector3
from .subspaces import ancestry, world_subspaces
from .tree import RigidBodyTree


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
    - `name`: a label for the user's bookkeeping (records list contacts in the order given,
      not by name).

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


class ContactPair(eqx.Module):
    """Two spheres that may touch each other: body–body contact (two links of a tree, a link
    and a function of q, or two points of any system).

    Their gap is g = |c₁ − c₂| − r₁ − r₂, the normal n = (c₁ − c₂)/|c₁ − c₂| points from the
    second towards the first, and the contact point is the midpoint of the surfaces' nearest
    points. The contact law's force F acts on the first sphere there and −F on the second
    (Newton's third law at one point): momentum and angular momentum pass between the bodies
    and are not created.

    **Arguments:** `first`, `second`: `jaxdyn.ContactPoint`s. Records list a pair where it
    stands in the scene's points.
    """

    first: ContactPoint
    second: ContactPoint

    def __check_init__(self):
        if not (isinstance(self.first, ContactPoint) and isinstance(self.second, ContactPoint)):
            raise ValueError("A ContactPair joins two jaxdyn.ContactPoint, got "
                             f"{type(self.first).__name__} and {type(self.second).__name__}.")
        key = [(c.body, c.point, c.radius) for c in (self.first, self.second)]
        if key[0] == key[1]:
            raise ValueError(f"A ContactPair joins two different spheres, got {self.first} "
                             "twice.")


def box_corners(link: str, size, centre=(0.0, 0.0, 0.0), rotation=None) -> list[ContactPoint]:
    """The eight corners of a box of edge lengths `size` (3,), centred at `centre` in the
    link's axes (turned by `rotation` (3, 3) if given), as contact points: a box on flat ground
    touches it at corners or along edges and faces, whose forces its corners carry."""
    size, centre = np.asarray(size, float), np.asarray(centre, float)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, float)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return [ContactPoint(link, centre + rotation @ (s * size / 2), name=f"{link}:corner{k}")
            for k, s in enumerate(signs)]


def capsule_ends(link: str, radius: float, length: float, centre=(0.0, 0.0, 0.0),
                 rotation=None) -> list[ContactPoint]:
    """A capsule of `radius` whose axis, of `length` between the centres of its two caps, runs
    along z of a frame at `centre` (turned by `rotation` (3, 3)) in the link's axes, as the
    two spheres at the ends of its axis. Against a plane the two spheres are the capsule
    exactly: the signed distance is linear along the axis, so its least value over the axis
    is at an end (a capsule lying flat touches at both, whose forces carry it). Against a
    curved terrain they miss the contact of the axis's middle with a crest."""
    centre = np.asarray(centre, float)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, float)
    if not (np.isfinite(length) and length >= 0):
        raise ValueError(f"A capsule's length must be finite and ≥ 0, got {length}.")
    axis = rotation @ np.array([0.0, 0.0, length / 2])
    return [ContactPoint(link, centre + sign * axis, radius, name=f"{link}:capsule{k}")
            for k, sign in enumerate((-1.0, 1.0))]


class ContactKinematics(eqx.Module):
    """Each contact's gap g (k,), normal n (k, 3), contact point x_C (k, 3), the velocity
    v_C (k, 3) of the body's material point there (of the first sphere's relative to the
    second's, for a pair) and its Jacobian J (k, 3, m) along the speeds, v_C = J u, all in
    world axes."""

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


def check_points(points: Sequence[ContactPoint | ContactPair] | ContactPoint | ContactPair,
                 tree: RigidBodyTree | None) -> tuple[ContactPoint | ContactPair, ...]:
    """Trace-time checks of the contact points against the system."""
    if isinstance(points, (ContactPoint, ContactPair)):
        points = (points,)
    points = tuple(points)
    if not points or not all(isinstance(c, (ContactPoint, ContactPair)) for c in points):
        raise ValueError("points must be a non-empty sequence of jaxdyn.ContactPoint or "
                         f"jaxdyn.ContactPair, got {points!r}.")
    names = None if tree is None else [link.name for link in tree.links]
    for c in _members(points):
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


def _members(points):
    """The spheres of `points`, pairs opened: what the kinematics moves."""
    for c in points:
        yield from ((c.first, c.second) if isinstance(c, ContactPair) else (c,))


def _sphere_motion(c, tree, poses, kinematics, t, q, u, p):
    """(centre c (3,), J_ω (3, m), J_c (3, m)) of one sphere: its centre and the Jacobians of
    its body's angular velocity and of its centre's velocity along the speeds."""
    dtype, m = q.dtype, u.shape[0]
    if isinstance(c.body, str):
        # the point on the moving body its link is welded to (`merge_fixed`): the poses are
        # those of the moving bodies only (ANYmal-C: 13, not 78 links)
        merged, rotations, origins, index, welded = poses
        body, offset_rotation, offset = welded[c.body]
        point = offset + offset_rotation @ np.asarray(c.point)
        if body is None:  # welded to the world: it does not move
            zero = jnp.zeros((3, m), dtype)
            return jnp.asarray(point, dtype), zero, zero
        chain, _, u_index = ancestry(merged, index[body])
        links = RigidBodyTree([merged.links[k] for k in chain])
        rotation, origin = rotations[np.array(chain)], origins[np.array(chain)]
        centre = origin[-1] + rotation[-1] @ jnp.asarray(point, dtype)
        omega, velocity = world_subspaces(links, rotation, origin, centre)
        full = jnp.zeros((2, 3, m), dtype).at[:, :, u_index].set(
            jnp.stack([omega.T, velocity.T]))
        return centre, full[0], full[1]
    centre = jnp.asarray(c.body(q, p), dtype)
    if centre.shape != (3,):
        raise ValueError(f"A contact point's function c(q, p) must return a 3-vector in the "
                         f"world, got shape {centre.shape}.")
    # (∂c/∂q) K column by column: K is linear in u
    jacobian = jax.jacfwd(lambda u: jax.jvp(
        lambda q: jnp.asarray(c.body(q, p), dtype), (q,), (kinematics(t, q, u, p),))[1])(u)
    return centre, jnp.zeros((3, m), dtype), jacobian  # (a point: no turning)


def _at(motion, x):
    """The Jacobian of the velocity of the body's material point at x: v_x = v_c + ω × (x − c),
    column by column J_x = J_c − [x − c]× J_ω."""
    centre, omega, jacobian = motion
    return jacobian + jnp.cross(omega, (x - centre)[:, None], axisa=0, axisb=0, axisc=0)


def contact_kinematics(points, terrain: AbstractTerrain, tree, kinematics, t, q, u, p
                       ) -> ContactKinematics:
    """Gaps, normals, contact points, their velocities and Jacobians (module docstring) at one
    state, a pair's relative to its second sphere.

    A point on a link moves with the speeds of the joints from the root to its link: its
    Jacobian's columns are those speeds' motion subspaces carried to the point (Featherstone,
    2008, §4.6; `world_subspaces`), from one pass of the poses of the tree's moving bodies
    (links on fixed joints welded to them, `RigidBodyTree.merge_fixed`), and zero for the other
    speeds; no derivative is taken. A point given as a function c(q, p) has the
    Jacobian (∂c/∂q) K (`kinematics` gives q̇ = K(t, q, p) u, linear in u)."""
    dtype = q.dtype
    poses = None
    if any(isinstance(c.body, str) for c in _members(points)):
        merged = tree.merge_fixed()
        poses = (merged, *merged.link_poses(t, q, p),
                 {link.name: i for i, link in enumerate(merged.links)}, tree.welded_bodies())
    gaps, normals, positions, jacobians = [], [], [], []
    for c in points:
        if isinstance(c, ContactPair):
            a, b = (_sphere_motion(s, tree, poses, kinematics, t, q, u, p)
                    for s in (c.first, c.second))
            d = a[0] - b[0]
            square = d @ d
            # (a safe norm: concentric spheres have no normal, and take +z)
            dist = jnp.sqrt(jnp.where(square > 0, square, 1.0))
            n = jnp.where(square > 0, d / dist, jnp.array([0.0, 0.0, 1.0], dtype))
            dist = jnp.where(square > 0, dist, 0.0)
            # the midpoint of the two surfaces' nearest points, where the forces act
            x = 0.5 * (a[0] - c.first.radius * n + b[0] + c.second.radius * n)
            gaps.append(dist - c.first.radius - c.second.radius)
            jacobians.append(_at(a, x) - _at(b, x))
        else:
            motion = _sphere_motion(c, tree, poses, kinematics, t, q, u, p)
            distance, n = terrain.distance_and_normal(motion[0], p)
            x = motion[0] - c.radius * n
            gaps.append(distance - c.radius)
            jacobians.append(_at(motion, x))
        normals.append(n)
        positions.append(x)
    jacobian = jnp.stack(jacobians)
    return ContactKinematics(gap=jnp.stack(gaps), normal=jnp.stack(normals),
                             position=jnp.stack(positions), velocity=jacobian @ u,
                             jacobian=jacobian)
