"""Inverse dynamics of a tree by the recursive Newton–Euler algorithm, and its regressor.

Featherstone, Rigid Body Dynamics Algorithms (2008), §5.3, in 3-vector algebra: outwards, each
link's spatial velocity and acceleration in its own axes,

    v_i = X_i v_λ(i) + S_i u_i,    a_i = X_i a_λ(i) + S_i u̇_i + v_i ×ₘ S_i u_i,

from the world's a_0 = (0, −g) (gravity as an acceleration of the base); the force each link
needs, f_i = I_i a_i + v_i ×* I_i v_i − f_i^ext; inwards, the force its joint transmits,
f_i + Σ_children X_cᵀ (…), whose components along the joint's motion are the joint forces
τ_i = S_iᵀ f_i. The result is M u̇ + c(q, u) − g(q) − Jᵀ f^ext: what the joints must supply.

A link's spatial inertia is written in its ten inertial parameters π = (m, m c, I_O), the mass,
first moments and the rotational inertia about the link's origin (the parallel-axis theorem
I_O = I_c + m (|c|² 1 − c cᵀ)), so that

    I (ω, v) = (I_O ω + h × v,  m v + ω × h),    h = m c,

and inverse dynamics is linear in π: τ = Y(q, u, u̇) π (Atkeson, An and Hollerbach, 1986),
the route to identifying a robot's inertial parameters from measured joint torques.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .._state import public_function
from .._system import spatial
from .._system.frames import point_motion
from .._system.subspaces import ancestry, world_subspaces
from .._system.tree import RigidBodyTree, checked_state as _checked

_SYMMETRIC = np.array([[4, 5, 7], [5, 6, 8], [7, 8, 9]])  # I_O's entries in π
UPPER = (np.array([0, 0, 1, 0, 1, 2]), np.array([0, 1, 1, 2, 2, 2]))  # π[4:] within I_O


def inertial_parameters(tree: RigidBodyTree, p=None, dtype=None) -> jax.Array:
    """π (N, 10): each link's ten inertial parameters, from the tree's masses, centres of mass
    and inertias about them (the parallel-axis theorem I_O = I_c + m (|c|² 1 − c cᵀ)), in
    Pinocchio's order: (m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz), the inertia
    about the link's origin in its axes. `.ravel()` gives the π of
    `jaxdyn.inverse_dynamics_regressor` and `jaxdyn.energy_regressors`."""
    masses, coms, inertias = tree.link_inertias(p, dtype)
    eye = jnp.eye(3, dtype=coms.dtype)[None]
    shift = masses[:, None, None] * (spatial.dot(coms, coms)[:, None, None] * eye
                                     - coms[:, :, None] * coms[:, None, :])
    origin = inertias + shift
    return jnp.concatenate([masses[:, None], masses[:, None] * coms,
                            origin[:, UPPER[0], UPPER[1]]], axis=-1)


def inertia_at_origin(parameters):
    """I_O (…, 3, 3), symmetric, from π (…, 10)."""
    return parameters[..., _SYMMETRIC]


def _split(parameters):
    """(m, h = m c, I_O) from π (…, 10): shapes (…), (…, 3), (…, 3, 3)."""
    return parameters[..., 0], parameters[..., 1:4], inertia_at_origin(parameters)


def _momentum(mass, first_moment, inertia, omega, velocity):
    """I (ω, v) = (I_O ω + h × v, m v + ω × h) about the link's origin."""
    return (spatial.matvec(inertia, omega) + spatial.cross(first_moment, velocity),
            mass[..., None] * velocity + spatial.cross(omega, first_moment))


def link_motion(tree: RigidBodyTree, q, u, ud, gravity):
    """Each link's spatial velocity (ω, v) and acceleration (ω̇, a) in its own axes (N, 3) each,
    the acceleration measured from the world's (0, −g); and the poses of the links in their
    parents. (Featherstone's spatial acceleration: a is the rate of v at the link's origin
    as a point fixed in space, not the classical acceleration of the origin.)"""
    rotation, origin, omega_j, velocity_j = tree.joint_motion(q, u)
    alpha_j, accel_j = tree.joint_twists(ud)

    def step(parent, link):
        omega_p, velocity_p, alpha_p, accel_p = parent
        rotation_pc, origin_pc, w_j, v_j, dw_j, dv_j = link
        omega, velocity = spatial.motion_to_child(rotation_pc, origin_pc, omega_p, velocity_p)
        omega, velocity = omega + w_j, velocity + v_j
        alpha, accel = spatial.motion_to_child(rotation_pc, origin_pc, alpha_p, accel_p)
        c_omega, c_velocity = spatial.cross_motion(omega, velocity, w_j, v_j)
        return omega, velocity, alpha + dw_j + c_omega, accel + dv_j + c_velocity

    zero = jnp.zeros(3, q.dtype)
    states = tree.forward(step, (zero, zero, zero, -gravity),
                          (rotation, origin, omega_j, velocity_j, alpha_j, accel_j))
    return states, (rotation, origin)


def _link_forces(parameters, omega, velocity, alpha, accel):
    """(n, f): the spatial force each link needs for its motion, I a + v ×* I v, about its
    origin in its axes, from its inertial parameters π (…, 10); linear in π."""
    mass, first_moment, inertia = _split(parameters)
    moment_a, force_a = _momentum(mass, first_moment, inertia, alpha, accel)
    moment_v, force_v = _momentum(mass, first_moment, inertia, omega, velocity)
    moment_b, force_b = spatial.cross_force(omega, velocity, moment_v, force_v)
    return moment_a + moment_b, force_a + force_b


def newton_euler(tree: RigidBodyTree, t, q, u, ud, p):
    """τ = M u̇ + c(q, u) − g(q) − Jᵀ f^ext by the recursive Newton–Euler algorithm: the
    forces along the speeds that produce the accelerations u̇ at (q, u). Joint forces, springs
    and dampers are not included (they are what the joints supply)."""
    motion, poses = link_motion(tree, q, u, ud, tree.gravity_vector(p, q.dtype))
    return _joint_forces_needed(tree, t, q, u, p, motion, poses)


def _joint_forces_needed(tree, t, q, u, p, motion, poses, external=None):
    """The inward pass of `newton_euler` from the links' motion and poses in their parents;
    `external`: further forces on the links (moments, forces (N, 3) about their origins, in
    their axes), taken as loads."""
    dtype = q.dtype
    rotation, origin = poses
    moment, force = _link_forces(inertial_parameters(tree, p, dtype), *motion)
    if tree.loads:
        external_moment, external_force = tree.load_wrenches(t, q, u, p)
        moment, force = moment - external_moment, force - external_force
    if external is not None:
        moment, force = moment - external[0], force - external[1]

    def inwards(accumulated, link):
        rotation_pc, origin_pc, own_moment, own_force = link
        total = (own_moment + accumulated[0], own_force + accumulated[1])
        return total, spatial.force_to_parent(rotation_pc, origin_pc, *total)

    zero = jnp.zeros(3, dtype)
    transmitted, _ = tree.backward(inwards, (zero, zero), (rotation, origin, moment, force))
    # τ_i = S_iᵀ f_i for every joint at once: the transpose of u ↦ S u.
    _, transpose = jax.vjp(tree.joint_twists, u)
    return transpose(transmitted)[0]


def newton_euler_held(tree: RigidBodyTree, t, q, u, ud, p, links, points, forces):
    r"""Inverse dynamics with forces on held points, and the points' motion, in one pass:

        τ = M u̇ + c(q, u) − g(q) − Σ_P J_Pᵀ λ_P,

    with λ_P (world axes) acting at point P of link `links[k]` (`points[k]` in its axes) and
    J_P its velocity Jacobian in world axes, and each point's position r_P, velocity v_P and
    classical acceleration a_P = J_P u̇ + J̇_P u in world axes. The outward pass of the
    recursive Newton–Euler algorithm gives every link's spatial velocity (ω, v) and
    acceleration (ω̇, a) in its axes, from which

        v_P = v + ω × P,    a_P = a + ω̇ × P + ω × v_P

    (Featherstone, 2008, §5.3; a measured from the world's −g, which R a_P + g restores), and
    the inward pass takes the forces Rᵀ λ_P, with moments P × Rᵀ λ_P about the links'
    origins, as external forces: Lagrange's equations of the first kind with held points,
    M u̇ − f − Cᵀ λ and C u̇ + γ, from one pass of the recursions instead of the tree's and
    each point's chain apart.

    **Returns:** (τ (m,), r_P (k, 3), v_P (k, 3), a_P (k, 3)).
    """
    dtype = q.dtype
    gravity = tree.gravity_vector(p, dtype)
    motion, poses = link_motion(tree, q, u, ud, gravity)
    rotations, origins = tree.link_poses(t, q, p, alone=False)
    rotation = rotations[links]
    points = points.astype(dtype)
    velocity, _, accel = point_motion(points, *(x[links] for x in motion))
    force = spatial.tmatvec(rotation, forces)  # λ in each link's axes
    zero = jnp.zeros((len(tree.links), 3), dtype)
    external = (zero.at[links].add(spatial.cross(points, force)), zero.at[links].add(force))
    tau = _joint_forces_needed(tree, t, q, u, p, motion, poses, external)
    positions = origins[links] + spatial.matvec(rotation, points)
    return (tau, positions, spatial.matvec(rotation, velocity),
            spatial.matvec(rotation, accel) + gravity[None])


def joint_forces(tree: RigidBodyTree, t, q, u, p):
    """The forces along the speeds that the tree's joints already apply: `forces`, dampers,
    springs and any potential other than gravity (−Kᵀ ∂V/∂q)."""
    elastic = -jax.grad(tree.elastic_energy, argnums=1)(t, q, p)
    _, transpose = jax.vjp(lambda u: tree.coordinate_rates(t, q, u, p), u)
    return tree.joint_forces(t, q, u, p) + transpose(elastic)[0]


@public_function(chunked=False)
def inverse_dynamics_regressor(tree: RigidBodyTree, q, u, ud, p=None) -> jax.Array:
    r"""The joint-force regressor Y (m, 10 N) of a tree: inverse dynamics is linear in the
    links' inertial parameters,

        M(q) u̇ + c(q, u) − g(q) = Y(q, u, u̇) π,

    with π = `jaxdyn.inertial_parameters(tree, p).ravel()` (ten per link, links in the tree's
    order: m, m c, I_O about the link's origin). Joint forces, springs, dampers and link loads
    are not part of it (they do not scale with the inertial parameters). Stacking Y over
    measured states turns identification from joint torques into linear least squares
    (Atkeson, An and Hollerbach, 1986).

    **Arguments:** the tree, coordinates q (n,), speeds u (m,), accelerations u̇ (m,), and p
    (only gravity may depend on it). Formed link by link: the joint forces are the links'
    forces mapped back through their Jacobians, τ_i = Σ_j s_i · f_j over the links j that
    speed i moves, with s_i the speed's motion subspace in the world's axes at its origin
    and f_j = (n_O, f) the force link j needs, I_j a_j + v_j ×* I_j v_j (its spatial
    acceleration a_j measured from the world's (0, −g)), carried to the world's origin. That
    force is linear in the link's own π_j, f_j = X_j^* A_j π_j, so link j's columns are
    Y_ij = s_i · X_j^* A_j. `jax.vmap` it over states.
    """
    q, u, ud = _checked(tree, q, u, ud)
    if tree.num_speeds == 0:  # every link fixed: no joint force to explain
        return jnp.zeros((0, 10 * len(tree.links)), q.dtype)
    bodies = tree.merge_fixed()  # the links welded by fixed joints: one body each
    t = jnp.zeros((), q.dtype)
    motion, _ = link_motion(bodies, q, u, ud, bodies.gravity_vector(p, q.dtype))
    rotation, origin = bodies.link_poses(t, q, p)
    s_omega, s_velocity = world_subspaces(bodies, rotation, origin)
    moves = _moves(bodies)  # (m, bodies): speed i moves body j
    if bodies is not tree:
        # Every link of the tree on its body, placed at (R, r) in the body's axes: its pose
        # and its motion in its own axes follow by the rigid offset.
        body_index, placement_r, placement_t, attached = _welding(tree, bodies)
        turn, at = jnp.asarray(placement_r, q.dtype), jnp.asarray(placement_t, q.dtype)
        motion = [spatial.motion_to_child(turn, at, *(x[body_index] for x in pair))
                  for pair in (motion[:2], motion[2:])]
        motion = (*motion[0], *motion[1])
        rotation, origin = (spatial.matmul(rotation[body_index], turn),
                            origin[body_index] + spatial.matvec(rotation[body_index], at))
        moves = moves[:, body_index] & attached[None]

    def link_force(parameters, omega, velocity, alpha, accel):  # f_j (6,) of one link's π_j
        return jnp.concatenate(_link_forces(parameters, omega, velocity, alpha, accel))

    # A_j = ∂f_j/∂π_j (exact at π = 0: f_j is linear in π_j), (N, 6, 10), its ten columns
    # carried to the world's origin and axes (N, 10, 3) each
    body_regressors = jax.vmap(jax.jacfwd(link_force))(
        jnp.zeros((moves.shape[1], 10), q.dtype), *motion)
    moment, force = spatial.force_to_parent(
        rotation[:, None], origin[:, None], jnp.swapaxes(body_regressors[:, :3], 1, 2),
        jnp.swapaxes(body_regressors[:, 3:], 1, 2))
    # s_i · X_j^* A_j as six broadcast products (m, N, 10): a matrix product with an inner
    # dimension of six runs slower.
    columns = sum(subspace[:, k, None, None] * world[None, :, :, k]
                  for subspace, world in ((s_omega, moment), (s_velocity, force))
                  for k in range(3))
    return jnp.where(moves[:, :, None], columns, 0.0).reshape(len(moves), -1)


def _moves(tree: RigidBodyTree) -> np.ndarray:
    """(m, N): whether speed i moves link j (its link is j or one of j's ancestors)."""
    moves = np.zeros((tree.num_speeds, len(tree.links)), dtype=bool)
    for j in range(len(tree.links)):
        moves[ancestry(tree, j)[2], j] = True
    return moves


def _welding(tree, bodies):
    """For each link of `tree`: the index of its body in `bodies` (`merge_fixed`), its
    placement (R, r) in the body's axes, and whether it is on a body at all (links fixed to
    the world are not)."""
    names = [link.name for link in bodies.links]
    welded = tree.welded_bodies()
    placements = [welded[link.name] for link in tree.links]
    return (np.array([0 if body is None else names.index(body) for body, _, _ in placements]),
            np.array([rotation for _, rotation, _ in placements]),
            np.array([translation for _, _, translation in placements]),
            np.array([body is not None for body, _, _ in placements]))


@public_function()
def energy_regressors(tree: RigidBodyTree, q, u, p=None) -> tuple[jax.Array, jax.Array]:
    r"""(y_T, y_V), each (10 N,): the kinetic energy and the gravitational potential energy
    are linear in the links' inertial parameters π (see `jaxdyn.inertial_parameters`),

        T = y_T(q, u)·π,   T = Σ ½ (ω·I_O ω + 2 ω·(h × v) + m v·v),
        V = y_V(q)·π,      V = −Σ g·(m r_O + R h),

    with (ω, v) each link's spatial velocity at its origin in its axes, (R, r_O) its pose and
    h = m c. The energy balance dE/dt = u·τ turns them into identification from energy
    (Gautier and Khalil, 1988). Joint springs and user potentials are not included.
    """
    q, u, _ = _checked(tree, q, u)
    n = len(tree.links)
    t = jnp.zeros((), q.dtype)
    rotation, origin, omega, velocity = tree.link_states(t, q, u, p)
    gravity = tree.gravity_vector(p, q.dtype)

    def kinetic(parameters):
        mass, first_moment, inertia = _split(parameters.reshape(n, 10))
        moment, force = _momentum(mass, first_moment, inertia, omega, velocity)
        return 0.5 * jnp.sum(spatial.dot(omega, moment) + spatial.dot(velocity, force))

    def potential(parameters):
        mass, first_moment, _ = _split(parameters.reshape(n, 10))
        centres = mass[:, None] * origin + spatial.matvec(rotation, first_moment)
        return -jnp.sum(spatial.dot(centres, gravity))

    zero = jnp.zeros(10 * n, q.dtype)
    return jax.grad(kinetic)(zero), jax.grad(potential)(zero)
