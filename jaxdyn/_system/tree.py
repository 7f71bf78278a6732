"""A tree of rigid links connected by joints, with recursive kinematics.

Each link's pose and velocity reuse its parent's (Featherstone, Rigid Body Dynamics
Algorithms, 2008, ch. 4): with the joint frame F placed in the parent P by (R_T, r_T) and the
link frame C moved in F by its joint, (R_J(q), r_J(q)), the link sits in its parent at

    R_PC = R_T R_J,   r_PC = r_T + R_T r_J,

in the world at R_WC = R_WP R_PC, r_WC = r_WP + R_WP r_PC, and moves with the spatial velocity

    ω_C = R_PCᵀ ω_P + ω_J,   v_C = R_PCᵀ (v_P + ω_P × r_PC) + v_J     (C's axes)

where (ω_J, v_J) = S u is the joint's own motion. The joints of one type are evaluated
together; the recursion itself runs as a Python loop for small trees (straight-line code, which
`jaxdyn._unroll` turns into a few kernels), as a Python loop over the levels of a branched tree
of a dozen links or more (a quadruped's legs: three levels of four links), and as a `lax.scan`
for large ones, so that compile time does not grow with the number of links: over the links
of a chain (the carry is the parent's state), and over the levels of a branched tree (the
links of one depth together, each gathering its parent's state from the level above, or
summing what its children pass up from the level below; consecutive levels of similar width
in one scan: `tree_levels`). A humanoid of 30 bodies is ten levels of at most four links: ten
steps of four links' arithmetic at once rather than thirty steps of one, each of which would
also read and write a buffer of every link's state (per state in a batch, G1's forward
dynamics 30.6 → 12.4 µs). The links themselves (`Link`, `LinkLoad`) are in `links`.
"""

import dataclasses
from typing import TYPE_CHECKING, Callable, overload

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._convention import call, scalar, vector
from .._state import check_vector, frozen_constant
# `tree_levels` as a module: its `LOOP_MAX` and `POSES_LOOP_MAX` are read when a recursion is
# traced, so that setting them (as the tests do) takes effect.
from . import spatial, tree_levels
from .base import AbstractMultibody
from .joints import Fixed
from .links import (Link, LinkLoad, _rotation, _value, _vector3, _Welded, own_inertias,
                    users_callable, welded_inertias)
from .tree_levels import _stacked

JOINT_ARGS = ("q", "u", "p")


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

    if not TYPE_CHECKING:
        def __getattribute__(self, name):
            # A method looked up on a tree is Python's plain bound method. Equinox's own
            # (a module wrapping the method, so that it is a pytree) is built at every look-up
            # by walking the whole tree's pytree: about 2 ms for ANYmal-C's 78 links, and the
            # recursions look up the tree's structural methods hundreds of times while a
            # robot's program is traced.
            return object.__getattribute__(self, name)

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
        return jax.tree_util.tree_map(lambda x: tree_levels.take(x, inverse).astype(dtype),
                                      stacked)

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
                                        tree_levels.take(q, q_index))
                 for joint, members, q_index, _ in self._groups()]
        rotation, translation = self._by_link(poses, q.dtype)
        if u is None:
            return rotation, translation
        return rotation, translation, *self.joint_twists(u)

    def joint_twists(self, u):
        """(ω_J, v_J) = S u for every link (N, 3) each, in its own axes: linear in u, so that
        its transpose maps the links' spatial forces to forces along the speeds, Σ S_iᵀ f_i."""
        twists = [joint.twist(tree_levels.take(u, u_index))
                  for joint, _, _, u_index in self._groups()]
        return self._by_link(twists, u.dtype)

    def _is_chain(self):
        return tree_levels._is_chain(self.parents)

    def scan_head(self, loop_max: int | None = None) -> int:
        """How many leading links a recursion takes one by one before the rest, which it
        takes level by level (branched trees of `LEVELS_MIN` to `LOOP_MAX` links) or in a
        `lax.scan` (trees of more than `loop_max` links, default `LOOP_MAX`, and chains of
        `CHAIN_LOOP_MIN` links or more): all of them in shorter chains and small trees; else
        the roots on joints of more than one speed, such as a floating base, so that the
        other links carry the width of their own joints (one speed each in most robots), not
        the base's six."""
        n = len(self.links)
        chain = self._is_chain()
        if n <= (tree_levels.LOOP_MAX if loop_max is None else loop_max) and (
                n < tree_levels.LEVELS_MIN or n > tree_levels.LOOP_MAX or chain) and not (
                chain and n >= tree_levels.CHAIN_LOOP_MIN):
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
        return tree_levels.forward_split(self.parents, step, root, head_links, rest)

    def backward_split(self, step, zero, head_links, rest):
        """`backward` with the data split as in `forward_split`: returns the head's outputs (a
        list), the rest's (stacked, or None) and what the roots passed to the world."""
        return tree_levels.backward_split(self.parents, step, zero, head_links, rest)

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
                            loop_max=tree_levels.POSES_LOOP_MAX if alone else None)

    # -- inertia, energies and forces ---------------------------------------------------------

    def link_inertias(self, p, dtype=None):
        """(masses (N,), centres of mass (N, 3), inertias about them (N, 3, 3)). Where links
        are welded together (`merge_fixed`), every body's are combined at once
        (`welded_inertias`); a link alone keeps its own values (exactly: straight-line code
        folds what they fold)."""
        bodies = {i: link.mass for i, link in enumerate(self.links)
                  if isinstance(link.mass, _Welded)}
        if not bodies:
            return own_inertias(self.links, p, dtype)
        welded = list(bodies)
        combined = welded_inertias([(body.links, body.rotations, body.translations)
                                    for body in bodies.values()], p, dtype)
        alone = [i for i in range(len(self.links)) if i not in welded]
        if not alone:
            return combined
        own = own_inertias([self.links[i] for i in alone], p, combined[0].dtype)
        order = np.argsort(alone + welded)
        return tuple(jnp.concatenate([a, b])[order] for a, b in zip(own, combined))

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

    def check_speeds(self, t, q, u, p, kinematic_map=None) -> None:
        self._check_state(q, u, kinematic_map)

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
        """The user's callables alone (energies, forces, loads, gravity, the links' values
        given as functions of p): the recursive kinematics, and the parameters' lookups of
        a tree read from a URDF file (`LinkParameter`), are the library's and need no check
        (Talos: 78 links' inertial values, 0.24 of 2.1 s of the first forward dynamics'
        trace under cProfile)."""
        self._check_state(q, u, kinematic_map)
        args = (q, u, p) if not self.time_dependent else (t, q, u, p)
        names = JOINT_ARGS if not self.time_dependent else ("t", *JOINT_ARGS)
        loads = [(self._load_vector(load.force, "LinkLoad force", names, args, q.dtype),
                  self._load_vector(load.torque, "LinkLoad torque", names, args, q.dtype))
                 for load in self.loads]
        values = [_value(x, p) for link in self.links
                  for x in (link.mass, link.com, link.inertia, link.stiffness, link.damping)
                  if users_callable(x)]
        forces = self.joint_forces(t, q, u, p) if self.forces is not None else None
        return (self.elastic_energy(t, q, p) if self.potential is not None else None,
                forces, loads, _value(self.gravity, p) if users_callable(self.gravity)
                else None, values)

