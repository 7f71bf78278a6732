"""The mass matrix of a tree by the composite-rigid-body algorithm, in world axes.

Featherstone, Rigid Body Dynamics Algorithms (2008), §6.2: the joint-space inertia matrix of
a tree is

    M_ij = S_iᵀ I^c_j S_j   for link(i) an ancestor of link(j) or link(j) itself (and M_ji),
    M_ij = 0                 for links on different branches,

where I^c_j is the composite inertia of the subtree rooted at link(j) (the links beyond j
welded into one rigid body) and S_i, S_j the joints' motion subspaces. Featherstone carries
these quantities in each link's own axes and transforms them link by link; written in the
world's axes and about the world's origin instead, no transform is needed between links:

- a link's ten inertial parameters π = (m, h = m c, I_O) are carried to the world by the
  parallel-axis theorem with a first moment (`placed`), and composite inertias are plain sums
  over subtrees, I^c = D π_world with D the constant subtree-membership matrix;
- each speed's motion subspace s_i = (ω_i, v_i) at the world's origin is its joint's S turned
  by the link's rotation R and moved from the link's origin r, v_i = R S_v + r × ω_i;
- M is then A = [s_i · I^c_link(j) s_j], kept where link(i) and link(j) lie on one branch.

Every step is a few 3-vector operations per link or per pair of speeds, with no recursion
beyond the links' poses: on robots the whole mass matrix costs less than forming it from the
partial velocities (Kane's Σ Jᵀ I J).
"""

import jax.numpy as jnp
import numpy as np

from .._system import spatial
from .._system.tree import RigidBodyTree, ancestry, speed_subspaces
from .newton_euler import inertia_at_origin, inertial_parameters


def placed(mass, first_moment, inertia, rotation, translation):
    """The inertial parameters (m, h, I_O) of a body, given in its own axes about its origin,
    seen from a frame in which the body's axes are turned by R and its origin sits at r:

        m,   R h + m r,   R I_O Rᵀ + m (|r|² 1 − r rᵀ) + 2 (r·R h) 1 − r (R h)ᵀ − (R h) rᵀ

    (the parallel-axis theorem with the first moment; linear in π). Batched on leading axes."""
    turned = spatial.matvec(rotation, first_moment)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=inertia.dtype), inertia.shape)

    def outer(a, b):
        return a[..., :, None] * b[..., None, :]

    scale = (mass * spatial.dot(translation, translation)
             + 2 * spatial.dot(translation, turned))[..., None, None]
    about = (spatial.matmul(spatial.matmul(rotation, inertia), jnp.swapaxes(rotation, -1, -2))
             + scale * eye - mass[..., None, None] * outer(translation, translation)
             - outer(translation, turned) - outer(turned, translation))
    return mass, turned + mass[..., None] * translation, about


def _subtrees(tree: RigidBodyTree) -> np.ndarray:
    """D (N, N): D[i, k] = 1 where link k lies in the subtree rooted at link i (i itself
    included)."""
    n = len(tree.links)
    membership = np.zeros((n, n), dtype=bool)
    for k in range(n):
        membership[ancestry(tree, k)[0], k] = True
    return membership


def composite_mass_matrix(tree: RigidBodyTree, t, q, p):
    """M (m, m) of a tree by the composite-rigid-body algorithm in world axes (module
    docstring): the same matrix as M_rs = Σ m v_r·v_s + ω_r·I ω_s of Kane's equations."""
    dtype = q.dtype
    rotation, origin = tree.link_poses(t, q, p)
    parameters = inertial_parameters(tree, p, dtype)
    mass, first_moment, inertia = placed(parameters[:, 0], parameters[:, 1:4],
                                         inertia_at_origin(parameters), rotation, origin)
    subtrees = _subtrees(tree)
    membership = jnp.asarray(subtrees, dtype)
    mass_c = membership @ mass
    first_c = membership @ first_moment
    inertia_c = jnp.einsum("ik,kab->iab", membership, inertia)

    link_of, subspace = speed_subspaces(tree)
    turn, at = rotation[link_of], origin[link_of]
    omega = spatial.matvec(turn, jnp.asarray(subspace[:, :3], dtype))
    velocity = spatial.matvec(turn, jnp.asarray(subspace[:, 3:], dtype)) + spatial.cross(at,
                                                                                      omega)
    # F_j = I^c_link(j) s_j, the momentum about the world's origin (n, f) = (I ω + h × v,
    # m v + ω × h).
    h = first_c[link_of]
    moment = spatial.matvec(inertia_c[link_of], omega) + spatial.cross(h, velocity)
    force = mass_c[link_of][:, None] * velocity + spatial.cross(omega, h)
    products = omega @ moment.T + velocity @ force.T  # s_i · F_j
    branch = subtrees[np.ix_(link_of, link_of)]  # link(i) is link(j) or one of its ancestors
    return jnp.where(branch, products, jnp.where(branch.T, products.T, 0.0))
