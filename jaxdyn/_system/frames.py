"""Kinematics of named frames of a tree, its centre of mass and its centroidal momentum.

A frame is a link of a `RigidBodyTree`, found by name (a URDF file's every link, those attached
by fixed joints included), optionally with its origin moved to a `point` given in the link's
axes (a tool tip); its axes are the link's. Velocities are spatial motion vectors in jaxdyn's
order (ω, v), v the velocity of the frame's origin, expressed

- `axes="world"`: in the world's axes (Pinocchio's LOCAL_WORLD_ALIGNED), or
- `axes="local"`: in the frame's own axes (Pinocchio's LOCAL),

and the frame Jacobian J (6, m) maps the speeds to them, (ω, v) = J(q) u (Featherstone, Rigid
Body Dynamics Algorithms, 2008, §4.6; Pinocchio lists v before ω). Accelerations are classical:
ω̇ and the second derivative of the origin's position, (ω̇, v̇) = J u̇ + J̇ u, formed by the
outward recursion of the links' accelerations (§5.3).

The centroidal momentum (Orin, Goswami and Lee, 2013) is h_G = (k_G, l), the angular momentum
about the centre of mass and the linear momentum, in world axes; h_G = A_G(q) u with A_G the
centroidal momentum matrix.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._state import public_function
from . import spatial
from .tree_levels import take
from .subspaces import ancestry, world_subspaces
from .tree import RigidBodyTree, checked_state as _checked

_AXES = ("world", "local")


def _index(tree, frame):
    names = [link.name for link in tree.links]
    if isinstance(frame, str):
        if frame not in names:
            close = [n for n in names if frame.lower() in n.lower()]
            hint = f" Did you mean one of {close}?" if close else f" Its links: {names}."
            raise ValueError(f"The tree has no link named {frame!r}.{hint}")
        return names.index(frame)
    if isinstance(frame, (int, np.integer)) and -len(names) <= frame < len(names):
        return int(frame) % len(names)
    raise ValueError(f"A frame is a link's name (or index), got {frame!r}.")


def _ancestors(tree, i):
    """The links from the root to link i, as a tree of its own (a chain), and the indices of
    its coordinates and speeds in the whole tree's q and u: a frame's pose and motion depend on
    nothing else, so a foot of a 78-link quadruped costs a chain of eight links."""
    chain, q_index, u_index = ancestry(tree, i)
    return RigidBodyTree([tree.links[k] for k in chain], gravity=tree.gravity), q_index, u_index


def _point(point, dtype):
    point = jnp.zeros(3, dtype) if point is None else jnp.asarray(point, dtype)
    if point.shape != (3,):
        raise ValueError(f"point must be a 3-vector in the link's axes, got shape {point.shape}.")
    return point


def _check_axes(axes):
    if axes not in _AXES:
        raise ValueError(f"axes must be 'world' or 'local', got {axes!r}.")


@public_function(num_static=2)
def frame_pose(tree: RigidBodyTree, frame, q, p=None, *, point=None):
    """(R, r): the frame's orientation (its axes as the columns of R, (3, 3)) and its origin
    (3,) in the world, at coordinates q.

    **Arguments:** the tree, the frame (a link's name or index), q (n,); `point`: the origin in
    the link's axes (default the link's own origin).
    """
    q, _, _ = _checked(tree, q)
    chain, q_index, _ = _ancestors(tree, _index(tree, frame))
    rotations, origins = chain.link_poses(jnp.zeros((), q.dtype), take(q, q_index), p)
    return rotations[-1], origins[-1] + rotations[-1] @ _point(point, q.dtype)


def _velocity(chain, point, axes, q, u, p):
    """(ω, v) of the last link of `chain` (see `_ancestors`), at its coordinates and speeds."""
    rotations, _, omega, velocity = chain.link_states(jnp.zeros((), q.dtype), q, u, p)
    omega, velocity = omega[-1], velocity[-1] + spatial.cross(omega[-1], point)
    if axes == "world":
        omega, velocity = rotations[-1] @ omega, rotations[-1] @ velocity
    return jnp.concatenate([omega, velocity])


@public_function(num_static=2)
def frame_velocity(tree: RigidBodyTree, frame, q, u, p=None, *, point=None, axes="world"):
    """(ω, v) (6,): the frame's angular velocity and its origin's velocity, in world or local
    axes (module docstring)."""
    _check_axes(axes)
    q, u, _ = _checked(tree, q, u)
    chain, q_index, u_index = _ancestors(tree, _index(tree, frame))
    return _velocity(chain, _point(point, q.dtype), axes, take(q, q_index), take(u, u_index), p)


@public_function(num_static=2)
def frame_jacobian(tree: RigidBodyTree, frame, q, p=None, *, point=None, axes="world"):
    """J (6, m) with (ω, v) = J(q) u: rows ω then v, in world or local axes (module
    docstring). Column k is speed k's motion subspace S (of its joint, on link i with pose
    (R_i, r_i)) carried to the frame's point P: ω_k = R_i S_ω, v_k = R_i S_v + ω_k × (P − r_i);
    zero for speeds that do not move the frame."""
    _check_axes(axes)
    q, _, _ = _checked(tree, q)
    chain, q_index, u_index = _ancestors(tree, _index(tree, frame))
    # Column by column (`world_subspaces`): a direct formula, cheaper than differentiating
    # the velocity recursion.
    rotations, origins = chain.link_poses(jnp.zeros((), q.dtype), take(q, q_index), p)
    where = origins[-1] + rotations[-1] @ _point(point, q.dtype)
    omega, velocity = world_subspaces(chain, rotations, origins, where)
    if axes == "local":
        omega, velocity = omega @ rotations[-1], velocity @ rotations[-1]  # Rᵀ x, row-wise
    columns = jnp.concatenate([omega, velocity], axis=1).T
    return jnp.zeros((6, tree.num_speeds), q.dtype).at[:, u_index].set(columns)


def _accelerations(chain, q, u, ud):
    """(R_WC, ω, v, ω̇, v̇) (N, …) of every link of a tree (a chain, `_ancestors`): its orientation,
    angular velocity and origin's velocity, and the rates of their components in its own
    (moving) axes, by the outward recursion of Featherstone (Rigid Body Dynamics Algorithms,
    2008, §5.3) in each link's axes. With the joint's pose (R_PC, r_PC) in its parent and its
    twist (ω_J, v_J) = S u (S constant in the link's axes, so that its rate is S u̇), the
    parent's motion seen in the child's axes, ω̃ = R_PCᵀ ω_P and ṽ = R_PCᵀ (v_P + ω_P × r_PC),
    and Ṙ_PC = R_PC [ω_J]×, ṙ_PC = R_PC v_J:

        ω̇_C = R_PCᵀ ω̇_P − ω_J × ω̃ + S_ω u̇,
        v̇_C = R_PCᵀ (v̇_P + ω̇_P × r_PC) + ω̃ × v_J − ω_J × ṽ + S_v u̇,

    from the world at rest. (One pass carrying six 3-vectors, where differentiating the
    velocity recursion carries the tangents of every pose as well.)"""
    rotation, translation, omega_j, velocity_j = chain.joint_motion(q, u)
    alpha_j, accel_j = chain.joint_twists(ud)

    def step(parent, link):
        rotation_wp, omega_p, velocity_p, alpha_p, accel_p = parent
        rotation_pc, origin_pc, omega_jc, velocity_jc, alpha_jc, accel_jc = link
        omega, velocity = spatial.motion_to_child(rotation_pc, origin_pc, omega_p, velocity_p)
        alpha = (spatial.tmatvec(rotation_pc, alpha_p) - spatial.cross(omega_jc, omega)
                 + alpha_jc)
        accel = (spatial.tmatvec(rotation_pc, accel_p + spatial.cross(alpha_p, origin_pc))
                 + spatial.cross(omega, velocity_jc) - spatial.cross(omega_jc, velocity)
                 + accel_jc)
        return (spatial.matmul(rotation_wp, rotation_pc), omega + omega_jc,
                velocity + velocity_jc, alpha, accel)

    zero = jnp.zeros(3, q.dtype)
    root = (jnp.eye(3, dtype=q.dtype), zero, zero, zero, zero)
    return chain.forward(step, root, (rotation, translation, omega_j, velocity_j, alpha_j,
                                      accel_j))


def _point_accelerations(chain, point, q, u, ud, links: int | np.ndarray = -1):
    """(R_WC, v_P, ω̇, a_P): the orientation of the chain's last link (or of the tree's
    `links`, with a point (k, 3) on each), the velocity of `point` (in the link's axes), the
    link's angular acceleration and the point's classical acceleration, all in the link's
    axes: v_P = v + ω × P, a_P = v̇ + ω̇ × P + ω × v_P (the rate of v_P's components in the
    moving axes, plus the axes' own turning)."""
    rotation, omega, velocity, alpha, accel = (x[links] for x in
                                               _accelerations(chain, q, u, ud))
    return rotation, *point_motion(point, omega, velocity, alpha, accel)


def point_motion(point, omega, velocity, alpha, accel):
    """(v_P, ω̇, a_P) of a point P fixed in a link, from the link's spatial motion (ω, v, ω̇,
    v̇) about its origin, all in the link's axes: v_P = v + ω × P, a_P = v̇ + ω̇ × P + ω × v_P
    (the rate of v_P's components in the moving axes, plus the axes' own turning)."""
    velocity = velocity + spatial.cross(omega, point)
    return velocity, alpha, accel + spatial.cross(alpha, point) + spatial.cross(omega, velocity)


@public_function(num_static=2)
def frame_acceleration(tree: RigidBodyTree, frame, q, u, ud, p=None, *, point=None,
                       axes="world"):
    """(ω̇, v̇) (6,): the classical accelerations of the frame, J u̇ + J̇ u: the rate of its
    angular velocity and the second derivative of its origin's position, in world or local
    axes (for local axes, the world-axes rates expressed in the frame's axes). Formed by the
    outward recursion of link accelerations (Featherstone, 2008, §5.3)."""
    _check_axes(axes)
    q, u, ud = _checked(tree, q, u, ud)
    chain, q_index, u_index = _ancestors(tree, _index(tree, frame))
    rotation, _, alpha, accel = _point_accelerations(
        chain, _point(point, q.dtype), take(q, q_index), take(u, u_index), take(ud, u_index))
    if axes == "world":
        alpha, accel = rotation @ alpha, rotation @ accel
    return jnp.concatenate([alpha, accel])


def _counted(tree, p, dtype, include_fixed):
    """The links' masses (N,) and inertias (N, 3, 3), zero for the links welded to the world
    unless `include_fixed`."""
    masses, inertias = tree.inertias(p, dtype)
    if include_fixed:
        return masses, inertias
    welded = tree.welded_bodies()
    moving = np.array([welded[link.name][0] is not None for link in tree.links])
    if not moving.any():
        raise ValueError("include_fixed=False leaves no link: every link of this tree is "
                         "welded to the world.")
    return jnp.where(moving, masses, 0.0), jnp.where(moving[:, None, None], inertias, 0.0)


@public_function()
def centre_of_mass(tree: RigidBodyTree, q, p=None, *, include_fixed=True):
    """c = Σ m_i r_Gi / Σ m_i (3,), in the world.

    `include_fixed`: count the links welded to the world (a fixed base and what is bolted to
    it), which do not move. True (the default) gives the whole robot's centre of mass; False
    leaves them out, Pinocchio's convention (`pinocchio.centerOfMass`, `data.vcom`,
    `jacobianCenterOfMass`, `ccrba`). On a floating base no link is welded to the world and
    both agree. The same option in `centre_of_mass_velocity`, `centre_of_mass_jacobian`,
    `centroidal_momentum` and `centroidal_momentum_matrix`.
    """
    q, _, _ = _checked(tree, q)
    masses, _ = _counted(tree, p, q.dtype, include_fixed)
    centres, _ = tree.body_poses(jnp.zeros((), q.dtype), q, p)
    return masses @ centres / jnp.sum(masses)


def _centre_of_mass_velocity(tree, q, u, p, include_fixed):
    masses, _ = _counted(tree, p, q.dtype, include_fixed)
    velocities, _ = tree.body_velocities(jnp.zeros((), q.dtype), q, u, p)
    return masses @ velocities / jnp.sum(masses)


@public_function()
def centre_of_mass_velocity(tree: RigidBodyTree, q, u, p=None, *, include_fixed=True):
    """ċ = Σ m_i v_Gi / Σ m_i (3,), world axes. `include_fixed` as in `centre_of_mass`."""
    q, u, _ = _checked(tree, q, u)
    return _centre_of_mass_velocity(tree, q, u, p, include_fixed)


@public_function()
def centre_of_mass_jacobian(tree: RigidBodyTree, q, p=None, *, include_fixed=True):
    """J_c (3, m) with ċ = J_c(q) u (world axes). `include_fixed` as in `centre_of_mass`."""
    q, _, _ = _checked(tree, q)
    zero = jnp.zeros(tree.num_speeds, q.dtype)
    return jax.jacfwd(lambda u: _centre_of_mass_velocity(tree, q, u, p, include_fixed))(zero)


def _centroidal_momentum(tree, q, u, p, include_fixed):
    masses, inertias = _counted(tree, p, q.dtype, include_fixed)
    t = jnp.zeros((), q.dtype)
    velocities, omega = tree.body_velocities(t, q, u, p)
    centres, rotations = tree.body_poses(t, q, p)
    centre = masses @ centres / jnp.sum(masses)
    linear = masses[:, None] * velocities
    spin = spatial.matvec(rotations, spatial.matvec(inertias, omega))
    angular = jnp.sum(spatial.cross(centres - centre[None], linear) + spin, axis=0)
    return jnp.concatenate([angular, jnp.sum(linear, axis=0)])


@public_function()
def centroidal_momentum(tree: RigidBodyTree, q, u, p=None, *, include_fixed=True):
    """h_G = (k_G, l) (6,): the angular momentum about the centre of mass,
    Σ (r_Gi − c) × m_i v_Gi + R_i I_i ω_i, and the linear momentum Σ m_i v_Gi, in world axes.
    `include_fixed` as in `centre_of_mass` (links welded to the world carry no momentum, but
    they move the centre c)."""
    q, u, _ = _checked(tree, q, u)
    return _centroidal_momentum(tree, q, u, p, include_fixed)


@public_function()
def centroidal_momentum_matrix(tree: RigidBodyTree, q, p=None, *, include_fixed=True):
    """A_G (6, m) with h_G = A_G(q) u: rows the angular momentum about the centre of mass, then
    the linear momentum, world axes. `include_fixed` as in `centre_of_mass`."""
    q, _, _ = _checked(tree, q)
    zero = jnp.zeros(tree.num_speeds, q.dtype)
    return jax.jacfwd(lambda u: _centroidal_momentum(tree, q, u, p, include_fixed))(zero)


class HeldPoints(eqx.Module):
    r"""Points of a tree's links held at fixed places in the world, as holonomic constraints
    for `jaxdyn.Constrained` (feet on the ground, a hand on a handle):

        φ(q) = r_P(q) − r_P* = 0        (three rows per point, in world axes),

    with the velocity terms that Lagrange's equations of the first kind need taken from the
    tree's recursions instead of by differentiating φ:

        C = J_v(q)    (rows v of each point's `frame_jacobian`, φ̇ = C u),
        γ = J̇_v u    (each point's classical acceleration at u̇ = 0, `frame_acceleration`),

    as Pinocchio's and Crocoddyl's 3-D contact models take them (Featherstone, Rigid Body
    Dynamics Algorithms, 2008, §8.3). A function of `frame_pose` given as `holonomic` defines
    the same constraints, but `Constrained` then forms C and γ by differentiating it once and
    twice, and a trajectory optimiser's expansion (`jaxdyn.solve_optimal_control`)
    differentiates those again: here the expansion differentiates first-order kinematics.

    **Arguments:**

    - `tree`: the `jaxdyn.RigidBodyTree` whose coordinates and speeds the constrained
      formulation has (`ArticulatedBody(tree)`, `Kane(tree)`, …, possibly `Controlled`).
    - `frames`: the links (names or indices), one per point.
    - `positions` (k, 3): where the points are held, in world axes.
    - `points` (k, 3): each point in its link's axes (default the links' origins).

    `HeldPoints.at(tree, frames, q, p)` holds the points where they are at coordinates q.
    """

    tree: RigidBodyTree
    frames: tuple[int, ...] = eqx.field(static=True)
    positions: jax.Array
    points: jax.Array

    def __init__(self, tree: RigidBodyTree, frames, positions, points=None):
        if not isinstance(tree, RigidBodyTree):
            raise ValueError(f"HeldPoints needs a jaxdyn.RigidBodyTree, got "
                             f"{type(tree).__name__}.")
        if isinstance(frames, (str, int, np.integer)):
            frames = [frames]
        self.tree = tree
        self.frames = tuple(_index(tree, frame) for frame in frames)
        k = len(self.frames)
        positions = jnp.asarray(positions)
        if not jnp.issubdtype(positions.dtype, jnp.floating):
            positions = positions.astype(float)
        if positions.shape != (k, 3):
            raise ValueError(f"positions must have shape ({k}, 3), one world point per frame, "
                             f"got {positions.shape}.")
        self.positions = positions
        points = jnp.zeros((k, 3), positions.dtype) if points is None else \
            jnp.asarray(points, positions.dtype)
        if points.shape != (k, 3):
            raise ValueError(f"points must have shape ({k}, 3), one point in its link's axes "
                             f"per frame, got {points.shape}.")
        self.points = points

    @classmethod
    def at(cls, tree: RigidBodyTree, frames, q, p=None, *, points=None) -> "HeldPoints":
        """The points held where they are at coordinates q."""
        if isinstance(frames, (str, int, np.integer)):
            frames = [frames]
        frames = [_index(tree, frame) for frame in frames]  # a misspelt name, named first
        q = jnp.asarray(q)
        points = jnp.zeros((len(frames), 3), q.dtype) if points is None else \
            jnp.asarray(points, q.dtype)
        if points.shape != (len(frames), 3):
            raise ValueError(f"points must have shape ({len(frames)}, 3), got {points.shape}.")
        positions = jnp.stack([frame_pose(tree, frame, q, p, point=point)[1]
                               for frame, point in zip(frames, points)])
        return cls(tree, frames, positions, points)

    def _checked(self, q, u=None):
        if q.shape != (self.tree.num_coordinates,) or (
                u is not None and u.shape != (self.tree.num_speeds,)):
            raise ValueError(
                f"HeldPoints holds points of a tree with {self.tree.num_coordinates} coordinates "
                f"and {self.tree.num_speeds} speeds; the constrained system has q of shape "
                f"{q.shape}" + ("" if u is None else f" and u of shape {u.shape}") + ". Give "
                "Constrained the formulation of this tree (ArticulatedBody(tree), Kane(tree), "
                "…, possibly Controlled).")

    def on_bodies(self):
        """(the links of `tree.merge_fixed()` that carry the points (k,), the points in their
        axes (k, 3)), or None where a point is welded to the world."""
        bodies = self.tree.merge_fixed()
        index = {link.name: i for i, link in enumerate(bodies.links)}
        welded = self.tree.welded_bodies()
        links, points = [], []
        for frame, point in zip(self.frames, self.points):
            body, rotation, translation = welded[self.tree.links[frame].name]
            if body is None:  # nothing moves it: the chains' route below
                return None
            links.append(index[body])
            points.append(jnp.asarray(rotation, point.dtype) @ point
                          + jnp.asarray(translation, point.dtype))
        return np.asarray(links), jnp.stack(points)

    def __call__(self, q, p=None):
        """φ(q) (3k,): each point's position less where it is held."""
        self._checked(q)
        t = jnp.zeros((), q.dtype)
        on_bodies = self.on_bodies()
        if on_bodies is not None:  # one pass over the welded tree's links
            links, points = on_bodies
            rotations, origins = self.tree.merge_fixed().link_poses(t, q, p)
            return (origins[links] + spatial.matvec(rotations[links], points.astype(q.dtype))
                    - self.positions).reshape(-1)
        rows = []
        for frame, point, position in zip(self.frames, self.points, self.positions):
            chain, q_index, _ = _ancestors(self.tree, frame)
            rotations, origins = chain.link_poses(t, take(q, q_index), p)
            rows.append(origins[-1] + rotations[-1] @ point.astype(q.dtype) - position)
        return jnp.concatenate(rows)

    def velocities_and_accelerations(self, q, u, ud, p=None):
        """(φ̇ = C u, φ̈ = C u̇ + γ) (3k,): each point's velocity and classical acceleration
        in world axes, by the outward recursion of link accelerations (`frame_acceleration`)."""
        self._checked(q, u)
        on_bodies = self.on_bodies()
        if on_bodies is not None:  # one pass over the welded tree's links, not one per chain
            links, points = on_bodies
            rotation, velocity, _, accel = _point_accelerations(
                self.tree.merge_fixed(), points.astype(q.dtype), q, u, ud, links)
            return (spatial.matvec(rotation, velocity).reshape(-1),
                    spatial.matvec(rotation, accel).reshape(-1))
        velocities, accelerations = [], []
        for frame, point in zip(self.frames, self.points):
            chain, q_index, u_index = _ancestors(self.tree, frame)
            rotation, velocity, _, accel = _point_accelerations(
                chain, point.astype(q.dtype), take(q, q_index), take(u, u_index),
                take(ud, u_index))
            velocities.append(rotation @ velocity)
            accelerations.append(rotation @ accel)
        return jnp.concatenate(velocities), jnp.concatenate(accelerations)

    def velocity_terms(self, q, u, p=None):
        """(C (3k, m), γ (3k,)): the rows of φ̇ = C u and the curvature γ = J̇ u (the points'
        classical accelerations at u̇ = 0), so that φ̈ = C u̇ + γ."""
        self._checked(q, u)
        t = jnp.zeros((), q.dtype)
        curvature = self.velocities_and_accelerations(q, u, jnp.zeros_like(u), p)[1]
        on_bodies = self.on_bodies()
        if on_bodies is not None:  # the welded tree's poses once for every point
            links, points = on_bodies
            bodies = self.tree.merge_fixed()
            rotations, origins = bodies.link_poses(t, q, p)
            where = origins[links] + spatial.matvec(rotations[links], points.astype(q.dtype))
            moved = np.zeros((len(links), self.tree.num_speeds), bool)
            for k, link in enumerate(links):
                moved[k, ancestry(bodies, int(link))[2]] = True
            # Every speed's subspace at the world's origin, once; at each point P its linear
            # part is v_k + ω_k × P, for the speeds that move P's body.
            omega, velocity = world_subspaces(bodies, rotations, origins)
            columns = velocity[None] + spatial.cross(omega[None], where[:, None])
            jacobians = jnp.where(moved[:, :, None], columns, 0.0)  # (k, m, 3)
            return jnp.swapaxes(jacobians, 1, 2).reshape(-1, self.tree.num_speeds), curvature
        jacobians = []
        for frame, point in zip(self.frames, self.points):
            chain, q_index, u_index = _ancestors(self.tree, frame)
            rotations, origins = chain.link_poses(t, take(q, q_index), p)
            where = origins[-1] + rotations[-1] @ point.astype(q.dtype)
            _, velocity = world_subspaces(chain, rotations, origins, where)
            jacobians.append(jnp.zeros((3, self.tree.num_speeds), q.dtype)
                             .at[:, u_index].set(velocity.T))
        return jnp.concatenate(jacobians), curvature
