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
from .._system.tree import (RigidBodyTree, ancestry, checked_state as _checked,
                            speed_subspaces)

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
    dtype = q.dtype
    (omega, velocity, alpha, accel), (rotation, origin) = link_motion(
        tree, q, u, ud, tree.gravity_vector(p, dtype))
    moment, force = _link_forces(inertial_parameters(tree, p, dtype), omega, velocity, alpha,
                                 accel)
    if tree.loads:
        external_moment, external_force = tree.load_wrenches(t, q, u, p)
        moment, force = moment - external_moment, force - external_force

    def inwards(accumulated, link):
        rotation_pc, origin_pc, own_moment, own_force = link
        total = (own_moment + accumulated[0], own_force + accumulated[1])
        return total, spatial.force_to_parent(rotation_pc, origin_pc, *total)

    zero = jnp.zeros(3, dtype)
    transmitted, _ = tree.backward(inwards, (zero, zero), (rotation, origin, moment, force))
    # τ_i = S_iᵀ f_i for every joint at once: the transpose of u ↦ S u.
    _, transpose = jax.vjp(tree.joint_twists, u)
    return transpose(transmitted)[0]


def joint_forces(tree: RigidBodyTree, t, q, u, p):
    """The forces along the speeds that the tree's joints already apply: `forces`, dampers,
    springs and any potential other than gravity (−Kᵀ ∂V/∂q)."""
    elastic = -jax.grad(tree.elastic_energy, argnums=1)(t, q, p)
    _, transpose = jax.vjp(lambda u: tree.coordinate_rates(t, q, u, p), u)
    return tree.joint_forces(t, q, u, p) + transpose(elastic)[0]


@public_function()
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
    forces mapped back through their Jacobians, τ = Σ_j J_jᵀ f_j, and each link's force
    f_j = I_j a_j + v_j ×* I_j v_j (its spatial acceleration a_j measured from the world's
    (0, −g)) is linear in its own π_j, f_j = A_j π_j, so the columns of link j are J_jᵀ A_j,
    with J_j (6, m) the Jacobian of the link's velocity in its own axes. `jax.vmap` it over
    states.
    """
    q, u, ud = _checked(tree, q, u, ud)
    bodies = tree.merge_fixed()  # the links welded by fixed joints: one body each
    n = len(bodies.links)
    t = jnp.zeros((), q.dtype)
    (omega, velocity, alpha, accel), _ = link_motion(bodies, q, u, ud,
                                                     bodies.gravity_vector(p, q.dtype))

    def link_force(parameters, omega, velocity, alpha, accel):  # f_j (6,) of one link's π_j
        return jnp.concatenate(_link_forces(parameters, omega, velocity, alpha, accel))

    # A_j = ∂f_j/∂π_j (exact at π = 0: f_j is linear in π_j), (n, 6, 10)
    body_regressors = jax.vmap(jax.jacfwd(link_force))(
        jnp.zeros((n, 10), q.dtype), omega, velocity, alpha, accel)

    # J_j's columns for the speeds that move link j (those of its ancestors and its own; the
    # others are zero), each speed's motion subspace S of its link i carried to link j's
    # origin and axes: ω = R_jᵀ R_i S_ω, v = R_jᵀ (R_i S_v + R_i S_ω × (r_j − r_i)).
    speeds, moving, position = _speeds_moving(bodies)
    link_of, subspace = speed_subspaces(bodies)
    rotation, origin = bodies.link_poses(t, q, p)
    subspace = jnp.asarray(subspace[speeds], q.dtype)  # (n, K, 6)
    turn, at = rotation[link_of[speeds]], origin[link_of[speeds]]
    omega = spatial.matvec(turn, subspace[..., :3])
    velocity = spatial.matvec(turn, subspace[..., 3:]) + spatial.cross(omega,
                                                                       origin[:, None] - at)
    columns = jnp.concatenate([jnp.einsum("jab,jka->jkb", rotation, omega),
                               jnp.einsum("jab,jka->jkb", rotation, velocity)], axis=-1)
    blocks = jnp.einsum("jkc,jce->jke", columns * jnp.asarray(moving, q.dtype)[..., None],
                        body_regressors)  # (n, K, 10): J_jᵀ A_j on link j's moving speeds
    blocks = jnp.concatenate([blocks, jnp.zeros((n, 1, 10), q.dtype)], axis=1)
    regressor = blocks[np.arange(n)[None, :], position]  # (m, n, 10)
    if bodies is tree:
        return regressor.reshape(-1, 10 * n)
    # A welded link's π enters its body's π linearly (`_transport`): Y_k = Y_body(k) T_k.
    body_index, transport = _welding(tree, bodies)
    columns = jnp.einsum("mkj,kje->mke", regressor[:, body_index],
                         jnp.asarray(transport, q.dtype))
    return columns.reshape(-1, 10 * len(tree.links))


def _speeds_moving(tree: RigidBodyTree):
    """For each link j, the speeds that move it (its ancestors' and its own), padded to the
    longest such list: their indices (N, K), whether each slot is one (N, K), and for each
    speed and link the slot that holds it, K where the speed does not move the link (m, N)."""
    lists = [ancestry(tree, j)[2] for j in range(len(tree.links))]
    width = max(1, max(len(speeds) for speeds in lists))
    speeds = np.zeros((len(lists), width), dtype=int)
    moving = np.zeros((len(lists), width), dtype=bool)
    position = np.full((tree.num_speeds, len(lists)), width, dtype=int)
    for j, listed in enumerate(lists):
        speeds[j, :len(listed)], moving[j, :len(listed)] = listed, True
        position[listed, j] = np.arange(len(listed))
    return speeds, moving, position


def _transport(parameters, rotation, translation):
    """π of a link seen from a body it is welded to, placed at (R, r) in the body's axes:
    m, R h + m r, and about the body's origin I = R I_O Rᵀ + m (|r|² 1 − r rᵀ) + 2 (r·R h) 1
    − r (R h)ᵀ − (R h) rᵀ (the parallel-axis theorem with the first moment). Linear in π."""
    mass, first_moment = parameters[0], rotation @ parameters[1:4]
    inertia = (rotation @ inertia_at_origin(parameters) @ rotation.T
               + mass * (translation @ translation * np.eye(3) - np.outer(translation,
                                                                          translation))
               + 2 * (translation @ first_moment) * np.eye(3)
               - np.outer(translation, first_moment) - np.outer(first_moment, translation))
    return np.concatenate([[mass], first_moment + mass * translation,
                           inertia[UPPER]])


def _welding(tree, bodies):
    """For each link of `tree`, the index of its body in `bodies` (`merge_fixed`) and the
    10 × 10 matrix T_k with π_body = Σ_k T_k π_k (zero for links fixed to the world)."""
    names = [link.name for link in bodies.links]
    placements = tree.welded_bodies()
    body_index = np.zeros(len(tree.links), dtype=int)
    transport = np.zeros((len(tree.links), 10, 10))
    for k, link in enumerate(tree.links):
        body, rotation, translation = placements[link.name]
        if body is None:
            continue
        body_index[k] = names.index(body)
        transport[k] = np.stack([_transport(unit, rotation, translation)
                                 for unit in np.eye(10)], axis=1)
    return body_index, transport


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
