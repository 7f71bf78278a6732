"""A tree of rigid links connected by joints, with recursive kinematics.

Each link's pose and velocity reuse its parent's (Featherstone, Rigid Body Dynamics
Algorithms, 2008, ch. 4): with the joint frame F placed in the parent P by (R_T, r_T) and the
link frame C moved in F by its joint, (R_J(q), r_J(q)), the link sits in its parent at

    R_PC = R_T R_J,   r_PC = r_T + R_T r_J,

in the world at R_WC = R_WP R_PC, r_WC = r_WP + R_WP r_PC, and moves with the spatial velocity

    ω_C = R_PCᵀ ω_P + ω_J,   v_C = R_PCᵀ (v_P + ω_P × r_PC) + v_J     (C's axes)

where (ω_J, v_J) = S u is the joint's own motion. The joints of one type are evaluated
together; the recursion itself runs as a Python loop for small trees (straight-line code, which
`jaxdyn._unroll` turns into a few kernels) and as a `lax.scan` for large ones, so that compile
time does not grow with the number of links: over the links of a chain (the carry is the
parent's state), and over the levels of a branched tree (the links of one depth together,
each gathering its parent's state from the level above, or summing what its children pass up
from the level below; consecutive levels of similar width in one scan, `_Levels`). A humanoid
of 30 bodies is ten levels of at most four links: ten steps of four links' arithmetic at once
rather than thirty steps of one, each of which would also read and write a buffer of every
link's state (per state in a batch, G1's forward dynamics 30.6 → 12.4 µs).
"""

import dataclasses
import functools
from typing import Any, Callable, overload

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._convention import call, scalar, vector
from .._state import check_vector, frozen_constant
from . import spatial
from .base import AbstractMultibody
from .joints import AbstractJoint, Fixed

# Trees with more links than this run their recursions as a `lax.scan` over links or levels
# (compile time independent of the number of links); smaller ones as a Python loop
# (straight-line code).
LOOP_MAX = 24

# The links' poses alone, a rotation and an offset composed per link, are straight-line code up
# to this many links: Talos's 45 cost 1.6 µs per state against 2.1 level by level, its mass
# matrix 6.2–6.9 against 7.3–7.8 µs, for 0.7 s more compile (which the articulated-body
# algorithm, compiling in 4.2 s on Talos, does not take: 5.0 s with them).
POSES_LOOP_MAX = 64

JOINT_ARGS = ("q", "u", "p")


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


# A band of levels costs its levels × its width in link-steps; a further band, about this many
# more (its scans' set-up and the hand-over between bands).
BAND_COST = 6


class _Band:
    """Consecutive levels of a tree taken together in one scan, each padded to the band's
    widest: `slots` (L, W) the link (counted from the head) in each slot, padding slots
    repeating the last link (a leaf, so that a padded slot computes what a real leaf would);
    `parent_slots` (L, W) each slot's parent in the level above, the identity for the band's
    first level, whose parents `entry` (W,) picks from the previous band's last level (in the
    first band: `roots_parents`, the links before the scan or the world); `children`
    (L, W, K) each slot's children in the level below, W where there is none (a row of
    zeros), and for the band's last level, unless it is the tree's, the identity: what its
    children in the next band passed up, `handoff` (W, K) picks and sums before the scan."""

    def __init__(self, levels, slot_of, parents, head, pad, following):
        self.width = width = max(len(level) for level in levels)
        self.slots = np.array([[i - head for i in level] + [pad] * (width - len(level))
                               for level in levels], dtype=np.int32)
        self.entry = np.array([slot_of[parents[i]] if parents[i] >= head else 0
                               for i in levels[0]] + [0] * (width - len(levels[0])),
                              dtype=np.int32)
        self.roots_parents = [parents[i] for i in levels[0]] + [-1] * (width - len(levels[0]))
        self.parent_slots = np.array(
            [list(range(width))] + [[slot_of[parents[i]] for i in level]
                                    + [0] * (width - len(level)) for level in levels[1:]],
            dtype=np.int32)
        below = levels[1:] + ([following] if following else [])
        kids = [[[slot_of[c] for c in level_below if parents[c] == i] for i in level]
                for level, level_below in zip(levels, below)]
        most = max([1] + [len(k) for level in kids for k in level])
        self.children = np.full((len(levels), width, most), width, dtype=np.int32)
        for d, level in enumerate(kids[:len(levels) - (1 if following else 0)]):
            for s, k in enumerate(level):
                self.children[d, s, :len(k)] = k
        self.handoff = np.full((width, most), -1, dtype=np.int32)  # −1: no child
        if following:
            self.children[-1, :, 0] = np.arange(width)
            for s, k in enumerate(kids[-1]):
                self.handoff[s, :len(k)] = k

    def by_slot(self, x):
        """Per-link data (N − head, …) → (L, W, …)."""
        return x[self.slots]


class _Levels:
    """The links of a tree beyond its first `head` taken level by level (their depth below
    the links before them), the levels grouped into bands of consecutive levels (`_Band`) so
    that narrow levels are not padded to the width of the widest: the bands minimise the
    link-steps of the padded levels, plus `BAND_COST` per band (Talos: levels of 3, 3, 5, 5,
    4, 4, 2, 2, 2, 8, 6 links)."""

    def __init__(self, parents, head):
        n = len(parents)
        depth = {}
        for i in range(head, n):
            depth[i] = 0 if parents[i] < head else depth[parents[i]] + 1
        members = [[i for i in range(head, n) if depth[i] == d]
                   for d in range(max(depth.values()) + 1)]
        slot_of = {i: s for level in members for s, i in enumerate(level)}
        # cheapest split of the levels into bands (dynamic programming over the cut points)
        count = len(members)
        best = [0.0] + [np.inf] * count
        cut = [0] * (count + 1)
        for j in range(1, count + 1):
            for i in range(j):
                cost = best[i] + (j - i) * max(len(m) for m in members[i:j]) + BAND_COST
                if cost < best[j]:
                    best[j], cut[j] = cost, i
        edges, j = [], count
        while j:
            edges.append((cut[j], j))
            j = cut[j]
        edges.reverse()
        pad = n - 1 - head
        self.bands = [_Band(members[i:j], slot_of, parents, head, pad,
                            members[j] if j < count else None) for i, j in edges]
        offsets = np.cumsum([0] + [b.slots.size for b in self.bands])
        flat = {}
        for band, offset, (i, j) in zip(self.bands, offsets, edges):
            for d, level in enumerate(members[i:j]):
                for s, link in enumerate(level):
                    flat[link] = offset + d * band.width + s
        self.order = np.array([flat[i] for i in range(head, n)], dtype=np.int32)
        self.num_roots = len(members[0])

    def by_link(self, *per_band):
        """The bands' per-slot results (L_b, W_b, …) → (N − head, …) in link order."""
        return jnp.concatenate([x.reshape((-1,) + x.shape[2:]) for x in per_band])[self.order]


@functools.lru_cache(maxsize=64)
def _levels(parents: tuple[int, ...], head: int) -> _Levels:
    """The level structure of a tree (its parents' indices), built once per tree shape: every
    recursion of every trace asks for it."""
    return _Levels(parents, head)


def _stacked(first, rest) -> Any:
    """The states or outputs of a recursion, the head's (a list) and the rest's (stacked, or
    None), stacked over all links."""
    tree_map = jax.tree_util.tree_map
    if not first:
        return rest
    stacked = tree_map(lambda *xs: jnp.stack(xs), *first)
    if rest is None:
        return stacked
    return tree_map(lambda x, y: jnp.concatenate([x.astype(y.dtype), y]), stacked, rest)


def ancestry(tree, i) -> tuple[list[int], np.ndarray, np.ndarray]:
    """The links from the root to link i (root first, i last), and the indices of their
    coordinates and speeds in the whole tree's q and u: what moves link i."""
    chain = [i]
    while tree.parents[chain[-1]] >= 0:
        chain.append(tree.parents[chain[-1]])
    chain.reverse()
    q_index, u_index = (np.concatenate([np.arange(slices[tree.links[k].name].start,
                                                  slices[tree.links[k].name].stop, dtype=int)
                                        for k in chain])
                        for slices in (tree.coordinate_slices(), tree.speed_slices()))
    return chain, q_index, u_index


def speed_subspaces(tree) -> tuple[np.ndarray, np.ndarray]:
    """For each speed of `tree`, its link (m,) and its column of that link's joint motion
    subspace (m, 6), rows (ω, v) in the link's axes (constant for every joint type here)."""
    links, columns = [], []
    for i, link in enumerate(tree.links):
        subspace = np.asarray(link.joint.subspace(), dtype=float).reshape(6, -1)
        links += [i] * subspace.shape[1]
        columns += list(subspace.T)
    return np.array(links, dtype=np.int32), np.array(columns).reshape(-1, 6)


def world_subspaces(tree, rotation, origin, point=None) -> tuple[jax.Array, jax.Array]:
    """Every speed's motion subspace s_k = (ω_k, v_k) (m, 3) each, in the world's axes at a
    point P of the world (default its origin): the speed's joint S on link i, with the link
    at (R_i, r_i), turned and moved, ω_k = R_i S_ω, v_k = R_i S_v + ω_k × (P − r_i). It is
    the column of speed k in the Jacobian of any point moved by it (Featherstone, 2008, §4.6),
    from the links' world poses `rotation` (N, 3, 3) and `origin` (N, 3)."""
    link_of, subspace = speed_subspaces(tree)
    subspace = jnp.asarray(subspace, rotation.dtype)
    turn, at = rotation[link_of], origin[link_of]
    omega = spatial.matvec(turn, subspace[:, :3])
    offset = -at if point is None else point[None] - at
    return omega, spatial.matvec(turn, subspace[:, 3:]) + spatial.cross(omega, offset)


@overload
def checked_state(tree, q, u: None = None, ud: None = None) -> tuple[jax.Array, None, None]: ...


@overload
def checked_state(tree, q, u: ArrayLike, ud: None = None
                  ) -> tuple[jax.Array, jax.Array, None]: ...


@overload
def checked_state(tree, q, u: ArrayLike, ud: ArrayLike
                  ) -> tuple[jax.Array, jax.Array, jax.Array]: ...


def checked_state(tree, q, u=None, ud=None):
    """(q, u, u̇) checked against `tree` (a `RigidBodyTree`): 1-D, floating, of its sizes."""
    if not isinstance(tree, RigidBodyTree):
        raise ValueError(f"Expected a jaxdyn.RigidBodyTree, got {type(tree).__name__}.")
    q = check_vector(q, "q")
    u = None if u is None else check_vector(u, "u")
    tree._check_state(q, u)
    if ud is not None:
        ud = check_vector(ud, "u̇ (ud)", tree.num_speeds)
    return q, u, ud


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
        # As arrays over the welded links (stacked), not a Python sum per link: ANYmal-C's 65
        # welded links written out per link were 45 % of its forward dynamics' program.
        masses = [jnp.asarray(_value(link.mass, p)) for link in self.links]
        dtype = jnp.result_type(*masses, float)
        masses = jnp.stack(masses).astype(dtype)
        mass = jnp.sum(masses)
        if self.part == "mass":
            return mass
        rotations = np.stack(self.rotations).astype(dtype)
        centres = np.stack(self.translations).astype(dtype) + jnp.einsum(
            "kij,kj->ki", rotations,
            jnp.stack([jnp.asarray(_value(link.com, p), dtype) for link in self.links]))
        first = masses @ centres
        # Massless bodies (URDF's dummy links) have their centre at the origin: a safe divisor
        # keeps the derivative finite where the mass is zero.
        massless = mass == 0
        centre = jnp.where(massless, 0.0, first / jnp.where(massless, 1.0, mass))
        if self.part == "com":
            return centre
        with_inertia = [k for k, link in enumerate(self.links) if link.inertia is not None]
        total = jnp.zeros((3, 3), dtype)
        if with_inertia:
            inertias = jnp.stack([jnp.asarray(_value(self.links[k].inertia, p), dtype)
                                  for k in with_inertia])
            turned = rotations[np.asarray(with_inertia)]
            total = jnp.einsum("kij,kjl,kml->im", turned, inertias, turned)
        d = centres - centre[None, :]
        return total + (masses @ jnp.sum(d * d, axis=1)) * jnp.eye(3, dtype=dtype) - jnp.einsum(
            "k,ki,kj->ij", masses, d, d)


class RigidBodyTree(AbstractMultibody):
    """Rigid links connected in a tree by joints: robots, linkages, chains, ropes.

    Coordinates and speeds are those of the joints, in the order of the links; q̇ = K(q) u with
    K block-diagonal (the identity for revolute and prismatic joints, quaternion kinematics for
    spherical and free joints). Every formulation takes this description:
    `jaxdyn.ArticulatedBody(tree)` (the articulated-body algorithm, O(N): the fast default),
    `jaxdyn.Kane.from_system(tree)`, `jaxdyn.GibbsAppell.from_system(tree)`,
    `jaxdyn.Lagrangian.from_system(tree)` (not for quaternion joints).

    **Arguments:**

    - `links`: a sequence of `jaxdyn.Link`, each listed after its parent.
    - `gravity`: the gravitational acceleration (3,) in world axes, or a function g(p), or None.
    - `forces`: τ(q, u, p) → (m,), generalized forces along the speeds (motor torques, any
      joint-space law), or None.
    - `loads`: a sequence of `jaxdyn.LinkLoad`.
    - `potential`: a further potential energy V(q, p), or None.
    - `time_dependent`: if True `forces`, the loads and `potential` take t first.

    **Example:** a double pendulum of two rods swinging about z.

        rod = dict(mass=1.0, com=(0.5, 0.0, 0.0), inertia=jnp.diag(jnp.array([0., 1., 1.]) / 12))
        tree = jaxdyn.RigidBodyTree([
            jaxdyn.Link("upper", jaxdyn.Revolute((0, 0, 1)), **rod),
            jaxdyn.Link("lower", jaxdyn.Revolute((0, 0, 1)), parent="upper",
                        translation=(1.0, 0.0, 0.0), **rod),
        ], gravity=jnp.array([0.0, -9.81, 0.0]))
    """

    links: tuple[Link, ...] = eqx.field(converter=tuple)
    gravity: jax.Array | Callable | None = eqx.field(default=None, converter=frozen_constant)
    forces: Callable | None = None
    loads: tuple[LinkLoad, ...] = eqx.field(default=(), converter=tuple)
    potential: Callable | None = None
    time_dependent: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        if len(self.links) == 0:
            raise ValueError("A RigidBodyTree needs at least one link.")
        seen = {}
        for i, link in enumerate(self.links):
            if not isinstance(link, Link):
                raise ValueError(f"links must be jaxdyn.Link, got {type(link).__name__}.")
            if link.name in seen:
                raise ValueError(f"Two links are named {link.name!r}: names must be unique.")
            if link.parent is not None and link.parent not in seen:
                later = [lk.name for lk in self.links[i + 1:]]
                if link.parent in later:
                    raise ValueError(f"Link {link.name!r} is listed before its parent "
                                     f"{link.parent!r}: list every link after its parent.")
                raise ValueError(f"Link {link.name!r} has the parent {link.parent!r}, which is "
                                 "not a link of the tree.")
            seen[link.name] = i
        for load in self.loads:
            if not isinstance(load, LinkLoad) or load.link not in seen:
                raise ValueError(f"loads must be jaxdyn.LinkLoad on links of the tree, got "
                                 f"{load!r}.")

    # -- structure -----------------------------------------------------------------------------

    @property
    def parents(self) -> tuple[int, ...]:
        """The index of each link's parent (−1 for the world)."""
        index = {link.name: i for i, link in enumerate(self.links)}
        return tuple(-1 if link.parent is None else index[link.parent] for link in self.links)

    @property
    def num_coordinates(self) -> int:
        return sum(link.joint.nq for link in self.links)

    @property
    def num_speeds(self) -> int:
        return sum(link.joint.nv for link in self.links)

    def _offsets(self, size):
        offsets, start = [], 0
        for link in self.links:
            offsets.append(start)
            start += size(link.joint)
        return offsets

    def coordinate_slices(self) -> dict[str, slice]:
        """Where each link's joint coordinates sit in q."""
        starts = self._offsets(lambda j: j.nq)
        return {link.name: slice(s, s + link.joint.nq) for link, s in zip(self.links, starts)}

    def speed_slices(self) -> dict[str, slice]:
        """Where each link's joint speeds sit in u."""
        starts = self._offsets(lambda j: j.nv)
        return {link.name: slice(s, s + link.joint.nv) for link, s in zip(self.links, starts)}

    def neutral_configuration(self) -> np.ndarray:
        """q with every joint at rest (angles 0, identity quaternions)."""
        return np.concatenate([link.joint.neutral() for link in self.links])

    def _groups(self):
        """Links whose joints are identical, evaluated together: (joint, link indices,
        coordinate indices (k, nq), speed indices (k, nv))."""
        q_starts, u_starts = self._offsets(lambda j: j.nq), self._offsets(lambda j: j.nv)
        groups = {}
        for i, link in enumerate(self.links):
            groups.setdefault(link.joint, []).append(i)
        out = []
        for joint, members in groups.items():
            q_index = np.array([[q_starts[i] + k for k in range(joint.nq)] for i in members],
                               dtype=np.int32).reshape(len(members), joint.nq)
            u_index = np.array([[u_starts[i] + k for k in range(joint.nv)] for i in members],
                               dtype=np.int32).reshape(len(members), joint.nv)
            out.append((joint, members, q_index, u_index))
        return out

    def _placements(self):
        rotations = np.array([np.asarray(link.rotation) for link in self.links])
        translations = np.array([np.asarray(link.translation) for link in self.links])
        return rotations, translations

    def merge_fixed(self) -> "RigidBodyTree":
        """The same dynamics on fewer links: every link on a `Fixed` joint is welded to its
        parent (masses, centres of mass and inertias combined, loads moved onto it), and links
        fixed to the world are dropped (with the links that hang from them re-placed in the
        world). Coordinates, speeds, gravity, forces and springs are unchanged, so forward and
        inverse dynamics and the mass matrix are the same, on fewer links: URDF models hang
        sensors, feet and tool frames on fixed joints (ANYmal-C's 78 links weld into 13).
        `ArticulatedBody` computes on this tree; frames and energies keep every link.
        """
        if not any(isinstance(link.joint, Fixed) for link in self.links):
            return self
        body_of, members, links = self.welded_bodies(), {}, []
        for link in self.links:
            body, rotation, translation = body_of[link.name]
            if isinstance(link.joint, Fixed):
                if body is not None:
                    members[body].append((link, rotation, translation))
            else:
                members[link.name] = [(link, rotation, translation)]
                placement = (None, np.eye(3), np.zeros(3)) if link.parent is None \
                    else body_of[link.parent]
                links.append(dataclasses.replace(
                    link, parent=placement[0], rotation=placement[1] @ np.asarray(link.rotation),
                    translation=placement[2] + placement[1] @ np.asarray(link.translation)))
        if not links:  # nothing moves: keep the tree as it is
            return self
        for i, link in enumerate(links):
            welded = members[link.name]
            if len(welded) > 1:
                parts = {part: _Welded(tuple(w[0] for w in welded),
                                       tuple(_rotation(w[1]) for w in welded),
                                       tuple(_vector3(w[2], "translation") for w in welded),
                                       part)
                         for part in ("mass", "com", "inertia")}
                links[i] = dataclasses.replace(link, **parts)
        loads = []
        for load in self.loads:
            body, rotation, translation = body_of[load.link]
            if body is not None:  # loads on links fixed to the world do no work
                loads.append(LinkLoad(body, load.force, load.torque,
                                      translation + rotation @ np.asarray(load.point)))
        return RigidBodyTree(links, gravity=self.gravity, forces=self.forces, loads=loads,
                             potential=self.potential, time_dependent=self.time_dependent)

    def welded_bodies(self) -> dict:
        """{link: (body, R, r)}: the moving link each link is welded to by fixed joints (itself
        for a link on a moving joint; None for links fixed to the world) and the link's
        placement in that body's axes (R, r), NumPy: the bodies of `merge_fixed`."""
        body_of = {}
        for link in self.links:
            if not isinstance(link.joint, Fixed):
                body_of[link.name] = (link.name, np.eye(3), np.zeros(3))
                continue
            body, base_r, base_t = ((None, np.eye(3), np.zeros(3)) if link.parent is None
                                    else body_of[link.parent])
            body_of[link.name] = (body, base_r @ np.asarray(link.rotation),
                                  base_t + base_r @ np.asarray(link.translation))
        return body_of

    # -- joint motion and the recursion ---------------------------------------------------------

    def _by_link(self, pieces, dtype):
        """Per-group results → arrays in link order."""
        order = np.concatenate([np.asarray(members) for _, members, _, _ in self._groups()])
        inverse = np.argsort(order)
        stacked = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *pieces)
        return jax.tree_util.tree_map(lambda x: x[inverse].astype(dtype), stacked)

    @overload
    def joint_motion(self, q, u: None = None) -> tuple[jax.Array, jax.Array]: ...

    @overload
    def joint_motion(self, q, u: jax.Array
                     ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]: ...

    def joint_motion(self, q, u=None):
        """For every link (in order): its pose in its parent (R_PC (N, 3, 3), r_PC (N, 3)), and
        with `u` its joint velocity (ω_J, v_J) (N, 3) each, in its own axes."""
        rotations_t, translations_t = self._placements()
        poses = [joint.placed_transform(rotations_t[members], translations_t[members],
                                        q[q_index])
                 for joint, members, q_index, _ in self._groups()]
        rotation, translation = self._by_link(poses, q.dtype)
        if u is None:
            return rotation, translation
        return rotation, translation, *self.joint_twists(u)

    def joint_twists(self, u):
        """(ω_J, v_J) = S u for every link (N, 3) each, in its own axes: linear in u, so that
        its transpose maps the links' spatial forces to forces along the speeds, Σ S_iᵀ f_i."""
        twists = [joint.twist(u[u_index]) for joint, _, _, u_index in self._groups()]
        return self._by_link(twists, u.dtype)

    def _is_chain(self):
        return all(parent == i - 1 for i, parent in enumerate(self.parents))

    def scan_head(self, loop_max: int | None = None) -> int:
        """How many leading links a recursion takes one by one before its `lax.scan` (trees of
        more than `loop_max` links, default `LOOP_MAX`; all of them below): the roots on
        joints of more than one speed, such as a floating base, so that the links in the scan
        carry the width of their own joints (one speed each in most robots), not the base's
        six."""
        n = len(self.links)
        if n <= (LOOP_MAX if loop_max is None else loop_max):
            return n
        head = 0
        while head < n and self.parents[head] < 0 and self.links[head].joint.nv > 1:
            head += 1
        return head

    def forward(self, step, root, per_link, *, loop_max=None):
        """The parent-to-child recursion: state_i = step(state of parent(i), per_link[i]), with
        `root` the world's state; returns the stacked states of the links. Straight-line code
        up to `loop_max` links (`scan_head`)."""
        head = self.scan_head(loop_max)
        tree_map = jax.tree_util.tree_map

        def passed_on(parent, data):
            state = step(parent, data)
            return state, state

        first, rest = self.forward_split(passed_on, root, [tree_map(lambda x: x[i], per_link)
                                                           for i in range(head)],
                                         tree_map(lambda x: x[head:], per_link))
        return _stacked(first, rest)

    def backward(self, step, zero, per_link):
        """The child-to-parent recursion, links in reverse order: (out_i, to_parent_i) =
        step(acc_i, per_link[i]), where acc_i is `zero` plus what the children of i passed up.
        Returns the stacked outputs and what the roots passed to the world."""
        head = self.scan_head()
        tree_map = jax.tree_util.tree_map
        first, rest, world = self.backward_split(
            step, zero, [tree_map(lambda x: x[i], per_link) for i in range(head)],
            tree_map(lambda x: x[head:], per_link))
        return _stacked(first, rest), world

    def forward_split(self, step, root, head_links, rest):
        """The parent-to-child recursion with the data of the first `scan_head()` links given
        one by one (a list: each may have its own shapes, such as a floating base's six
        columns) and the rest's stacked (or None when there is no rest): (state_i, out_i) =
        step(state of parent(i), data_i), the state passed to the children (of the same shape
        for every link of the scan and for the roots it hangs from). Returns the outputs the
        same way, a list and stacked."""
        parents, tree_map = self.parents, jax.tree_util.tree_map
        n, head = len(parents), len(head_links)
        states, outputs = [], []
        for i in range(head):
            state, out = step(root if parents[i] < 0 else states[parents[i]], head_links[i])
            states.append(state)
            outputs.append(out)
        if head == n:
            return outputs, None
        if self._is_chain():  # the carry is the parent's state: no level to gather from
            return outputs, jax.lax.scan(step, states[-1] if states else root, rest)[1]
        # Level by level (links of one depth below the head together, `_Levels`): the carry
        # is the previous level's states, each link's parent gathered from it.
        levels = _levels(parents, head)

        def body(previous, xs):
            parent_slot, data = xs
            return jax.vmap(step)(tree_map(lambda x: x[parent_slot], previous), data)

        scanned, last = [], None
        for band in levels.bands:
            if last is None:
                start = tree_map(lambda *xs: jnp.stack(xs), *[
                    root if parent < 0 else states[parent] for parent in band.roots_parents])
            else:
                start = tree_map(lambda x: x[band.entry], last)
            last, out = jax.lax.scan(body, start, (band.parent_slots,
                                                   tree_map(band.by_slot, rest)))
            scanned.append(out)
        return outputs, tree_map(levels.by_link, *scanned)

    def backward_split(self, step, zero, head_links, rest):
        """`backward` with the data split as in `forward_split`: returns the head's outputs (a
        list), the rest's (stacked, or None) and what the roots passed to the world."""
        parents, tree_map = self.parents, jax.tree_util.tree_map
        n, head = len(parents), len(head_links)
        accumulated = [zero] * (n + 1)  # the last for the world
        scanned = None
        if head < n:
            if self._is_chain():  # the carry is what the child passes up
                def chain_body(carry, data):
                    out, up = step(carry, data)
                    return tree_map(jnp.add, zero, up), out

                up, scanned = jax.lax.scan(chain_body, zero, rest, reverse=True)
                accumulated[head - 1 if head else n] = up
            else:  # level by level, leaves first: the carry is what the level below passes up
                levels = _levels(parents, head)

                def summed(below, children):  # each slot's children's (W: a row of zeros)
                    return tree_map(lambda b: jnp.sum(jnp.concatenate(
                        [b, jnp.zeros_like(b[:1])])[children], axis=1), below)

                def body(below, xs):
                    children, data = xs
                    total = tree_map(lambda z, s: z[None] + s, zero, summed(below, children))
                    out, up = jax.vmap(step)(total, data)
                    return up, out

                per_band, up = [None] * len(levels.bands), None
                for b in reversed(range(len(levels.bands))):
                    band = levels.bands[b]
                    if up is None:  # the tree's last level: nothing below
                        start = tree_map(lambda z: jnp.zeros((band.width,) + jnp.shape(z),
                                                             jnp.result_type(z)), zero)
                    else:  # what the next band's first level passed up, summed per parent
                        width_below = jax.tree_util.tree_leaves(up)[0].shape[0]
                        start = summed(up, np.where(band.handoff < 0, width_below,
                                                    band.handoff))
                    up, per_band[b] = jax.lax.scan(body, start, (band.children,
                                                                 tree_map(band.by_slot, rest)),
                                                   reverse=True)
                scanned = tree_map(levels.by_link, *per_band)
                for slot, parent in enumerate(levels.bands[0].roots_parents[:levels.num_roots]):
                    target = n if parent < 0 else parent
                    accumulated[target] = tree_map(lambda a, x: a + x[slot],
                                                   accumulated[target], up)
        outputs = [None] * head
        for i in reversed(range(head)):
            outputs[i], up = step(accumulated[i], head_links[i])
            target = n if parents[i] < 0 else parents[i]
            accumulated[target] = tree_map(jnp.add, accumulated[target], up)
        return outputs, scanned, accumulated[n]

    def link_states(self, t, q, u, p):
        """World poses and velocities of the links: (R_WC (N, 3, 3), r_WC (N, 3), ω (N, 3),
        v (N, 3)), the angular velocity and the velocity of each link's origin in its own
        axes."""
        rotation, translation, omega_j, velocity_j = self.joint_motion(q, u)
        dtype = q.dtype

        def step(parent, link):
            rotation_wp, origin_wp, omega_p, velocity_p = parent
            rotation_pc, origin_pc, omega_jc, velocity_jc = link
            omega, velocity = spatial.motion_to_child(rotation_pc, origin_pc, omega_p,
                                                      velocity_p)
            return (spatial.matmul(rotation_wp, rotation_pc),
                    origin_wp + spatial.matvec(rotation_wp, origin_pc),
                    omega + omega_jc, velocity + velocity_jc)

        root = (jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype), jnp.zeros(3, dtype),
                jnp.zeros(3, dtype))
        return self.forward(step, root, (rotation, translation, omega_j, velocity_j))

    def link_poses(self, t, q, p, *, alone=True):
        """(R_WC (N, 3, 3), r_WC (N, 3)): the links' frames in the world. `alone`: the poses
        are all the caller's recursion over links, and are straight-line code up to
        `POSES_LOOP_MAX` links; else they run as the tree's recursions do (`LOOP_MAX`)."""
        rotation, translation = self.joint_motion(q)

        def step(parent, link):
            rotation_wp, origin_wp = parent
            rotation_pc, origin_pc = link
            return (spatial.matmul(rotation_wp, rotation_pc),
                    origin_wp + spatial.matvec(rotation_wp, origin_pc))

        root = (jnp.eye(3, dtype=q.dtype), jnp.zeros(3, q.dtype))
        return self.forward(step, root, (rotation, translation),
                            loop_max=POSES_LOOP_MAX if alone else None)

    # -- inertia, energies and forces ---------------------------------------------------------

    def link_inertias(self, p, dtype=None):
        """(masses (N,), centres of mass (N, 3), inertias about them (N, 3, 3))."""
        masses = jnp.stack([jnp.asarray(_value(link.mass, p)) for link in self.links])
        dtype = masses.dtype if dtype is None else dtype
        coms = jnp.stack([jnp.asarray(_value(link.com, p), dtype) for link in self.links])
        zero = jnp.zeros((3, 3), dtype)
        inertias = jnp.stack([zero if link.inertia is None
                              else jnp.asarray(_value(link.inertia, p), dtype)
                              for link in self.links])
        for name, value, shape in (("com", coms, (len(self.links), 3)),
                                   ("inertia", inertias, (len(self.links), 3, 3))):
            if value.shape != shape:
                raise ValueError(f"Every link's {name} must have shape {shape[1:]}.")
        return masses.astype(dtype), coms, inertias

    def kinematic_matrix(self, t, q, p, kinematic_map=None, u=None):
        self._check_state(q, u, kinematic_map)
        m = self.num_speeds
        q_slices, u_slices = self.coordinate_slices(), self.speed_slices()
        rows = []  # block-diagonal: each joint's K in its rows and columns
        for link in self.links:
            if link.joint.nq:
                qs, us = q_slices[link.name], u_slices[link.name]
                block = link.joint.rate_matrix(q[qs])
                rows.append(jnp.concatenate([  # NumPy zeros: constants, nothing to evaluate
                    np.zeros((link.joint.nq, us.start), q.dtype), block,
                    np.zeros((link.joint.nq, m - us.stop), q.dtype)], axis=1))
        return jnp.concatenate(rows) if rows else jnp.zeros((0, m), q.dtype)

    def coordinate_rates(self, t, q, u, p, kinematic_map=None):
        """q̇ = K(q) u, joint by joint."""
        self._check_state(q, u, kinematic_map)
        q_slices, u_slices = self.coordinate_slices(), self.speed_slices()
        pieces = []
        for link in self.links:
            if link.joint.nq:
                qs, us = q_slices[link.name], u_slices[link.name]
                pieces.append(link.joint.rate_matrix(q[qs]) @ u[us])
        return jnp.concatenate(pieces) if pieces else jnp.zeros(0, q.dtype)

    def _check_state(self, q, u, kinematic_map=None):
        if kinematic_map is not None:
            raise ValueError("A RigidBodyTree's speeds are its joints' own: pass no "
                             "kinematic_map.")
        if q.shape != (self.num_coordinates,):
            raise ValueError(f"This tree has {self.num_coordinates} coordinates (its joints'), "
                             f"but q has shape {q.shape}.")
        if u is not None and u.shape != (self.num_speeds,):
            raise ValueError(f"This tree has {self.num_speeds} speeds (its joints'), but u has "
                             f"shape {u.shape}.")

    def speeds_from_rates(self, t, q, qd, p):
        self._check_state(q, None)
        q_slices = self.coordinate_slices()
        pieces = [link.joint.speeds(q[q_slices[link.name]], qd[q_slices[link.name]])
                  for link in self.links if link.joint.nq]
        return jnp.concatenate(pieces) if pieces else jnp.zeros(0, qd.dtype)

    def inertias(self, p, dtype):
        masses, _, inertias = self.link_inertias(p, dtype)
        return masses, inertias

    def body_velocities(self, t, q, u, p, kinematic_map=None):
        self._check_state(q, u, kinematic_map)
        rotations, _, omega, velocity = self.link_states(t, q, u, p)
        _, coms, _ = self.link_inertias(p, q.dtype)
        return spatial.matvec(rotations, velocity + spatial.cross(omega, coms)), omega

    def body_poses(self, t, q, p):
        rotations, origins = self.link_poses(t, q, p)
        _, coms, _ = self.link_inertias(p, q.dtype)
        return origins + spatial.matvec(rotations, coms), rotations

    def gravity_vector(self, p, dtype):
        """g in world axes (zero without gravity)."""
        if self.gravity is None:
            return jnp.zeros(3, dtype)
        g = jnp.asarray(_value(self.gravity, p), dtype)
        if g.shape != (3,):
            raise ValueError(f"gravity must be a 3-vector, got shape {g.shape}.")
        return g

    def potential_energy(self, t, q, p):
        """Gravity Σ −m g·r_G, the joint springs ½ k (q − rest)², and `potential`."""
        total = self.elastic_energy(t, q, p)
        if self.gravity is not None:
            masses, _, _ = self.link_inertias(p, q.dtype)
            centres, _ = self.body_poses(t, q, p)
            total = total - jnp.sum(masses * spatial.dot(centres, self.gravity_vector(p, q.dtype)))
        return total

    def elastic_energy(self, t, q, p):
        """The joint springs ½ k (q − rest)² and `potential`: V without gravity."""
        total = jnp.zeros((), q.dtype)
        q_slices = self.coordinate_slices()
        for link in self.links:
            if link.stiffness is not None:
                stretch = q[q_slices[link.name]][0] - link.rest
                total = total + 0.5 * _value(link.stiffness, p) * stretch**2
        if self.potential is not None:
            args = (q, p) if not self.time_dependent else (t, q, p)
            total = total + scalar(call(self.potential, "potential energy V", False,
                                        ("q", "p") if not self.time_dependent else
                                        ("t", "q", "p"), None, *args), "potential energy V")
        return total

    def joint_forces(self, t, q, u, p):
        """Generalized forces along the speeds from `forces` and the joint dampers."""
        total = jnp.zeros_like(u)
        if self.forces is not None:
            args = (q, u, p) if not self.time_dependent else (t, q, u, p)
            names = JOINT_ARGS if not self.time_dependent else ("t", *JOINT_ARGS)
            total = total + vector(call(self.forces, "generalized forces", False, names, None,
                                        *args), "generalized forces", u.shape)
        if any(link.damping is not None for link in self.links):
            u_slices = self.speed_slices()
            total = total + jnp.concatenate([
                -_value(link.damping, p) * u[u_slices[link.name]] if link.damping is not None
                else jnp.zeros(link.joint.nv, u.dtype) for link in self.links])
        return total

    def load_wrenches(self, t, q, u, p):
        """The loads as spatial forces (n, f) on each link, about its origin in its own axes
        (N, 3) each: what the articulated-body algorithm takes."""
        n = len(self.links)
        moments = jnp.zeros((n, 3), q.dtype)
        forces = jnp.zeros((n, 3), q.dtype)
        if not self.loads:
            return moments, forces
        rotations, _ = self.link_poses(t, q, p)
        index = {link.name: i for i, link in enumerate(self.links)}
        args = (q, u, p) if not self.time_dependent else (t, q, u, p)
        names = JOINT_ARGS if not self.time_dependent else ("t", *JOINT_ARGS)
        for load in self.loads:
            i = index[load.link]
            force = self._load_vector(load.force, "LinkLoad force", names, args, q.dtype)
            torque = self._load_vector(load.torque, "LinkLoad torque", names, args, q.dtype)
            force_link = spatial.tmatvec(rotations[i], force)
            moment_link = spatial.tmatvec(rotations[i], torque) + spatial.cross(
                jnp.asarray(load.point, q.dtype), force_link)
            moments = moments.at[i].add(moment_link)
            forces = forces.at[i].add(force_link)
        return moments, forces

    @staticmethod
    def _load_vector(fn, name, names, args, dtype):
        if fn is None:
            return jnp.zeros(3, dtype)
        return vector(call(fn, name, False, names, None, *args), name, (3,))

    def applied_forces(self, t, q, u, p, kinematic_map=None):
        """Π: joint forces and dampers, and the loads' virtual work Σ J_iᵀ (n_i, f_i) (one VJP
        of the links' velocities)."""
        self._check_state(q, u, kinematic_map)
        total = self.joint_forces(t, q, u, p)
        if self.loads:
            moments, forces = self.load_wrenches(t, q, u, p)

            def twists(u):
                _, _, omega, velocity = self.link_states(t, q, u, p)
                return omega, velocity

            total = total + jax.vjp(twists, u)[1]((moments, forces))[0]
        return total

    def user_functions(self, t, q, u, p, kinematic_map=None):
        """The user's callables alone (energies, forces, loads, gravity, inertial parameters):
        the recursive kinematics is the library's and needs no check."""
        self._check_state(q, u, kinematic_map)
        args = (q, u, p) if not self.time_dependent else (t, q, u, p)
        names = JOINT_ARGS if not self.time_dependent else ("t", *JOINT_ARGS)
        loads = [(self._load_vector(load.force, "LinkLoad force", names, args, q.dtype),
                  self._load_vector(load.torque, "LinkLoad torque", names, args, q.dtype))
                 for load in self.loads]
        return (self.elastic_energy(t, q, p), self.joint_forces(t, q, u, p), loads,
                self.gravity_vector(p, q.dtype), self.link_inertias(p, q.dtype))
