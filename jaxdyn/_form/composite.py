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
  over subtrees, I^c_i = π_i + Σ_{children k} I^c_k (one addition per link, leaves first);
- each speed's motion subspace s_i = (ω_i, v_i) at the world's origin is its joint's S turned
  by the link's rotation R and moved from the link's origin r, v_i = R S_v + r × ω_i;
- M_ij = s_i · I^c_link(j) s_j is formed only where link(i) is link(j) or an ancestor: with
  the speeds in depth-first order every subtree's speeds are consecutive, so each chain of
  the tree (links that are each their predecessor's only child) gives one product, its speeds
  against its own and its subtree's, and M is the symmetric closure of these rows.

Every step is a few 3-vector operations per link or per pair of speeds, with no recursion
beyond the links' poses: on robots the whole mass matrix costs less than forming it from the
partial velocities (Kane's Σ Jᵀ I J).
"""

import jax.numpy as jnp
import numpy as np

from .._system import spatial
from .._system.subspaces import speed_subspaces, world_subspaces
from .._system.tree import RigidBodyTree
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


def _chains(tree: RigidBodyTree) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """The speeds in depth-first order of their links, `order` (m,), so that every subtree's
    speeds are consecutive; and the tree cut into chains (runs of links each the only child
    of the one before), each as (first, last, end) in that order: the chain's own speeds are
    [first, last) and its subtree's [first, end). A speed of a chain moves the links of every
    speed after it up to `end`, and no other link of the chain."""
    n, parents = len(tree.links), tree.parents
    children = [[k for k in range(n) if parents[k] == i] for i in range(n)]
    slices = tree.speed_slices()
    own = [range(slices[link.name].start, slices[link.name].stop) for link in tree.links]
    order, chains = [], []

    def visit(i):
        first = len(order)
        while True:  # down the chain from i while each link has one child
            order.extend(own[i])
            if len(children[i]) != 1:
                break
            i = children[i][0]
        last = len(order)
        for child in children[i]:
            visit(child)
        chains.append((first, last, len(order)))

    for root in (i for i in range(n) if parents[i] < 0):
        visit(root)
    return np.asarray(order, dtype=int), chains


def composite_mass_matrix(tree: RigidBodyTree, t, q, p):
    """M (m, m) of a tree by the composite-rigid-body algorithm in world axes (module
    docstring): the same matrix as M_rs = Σ m v_r·v_s + ω_r·I ω_s of Kane's equations."""
    dtype = q.dtype
    rotation, origin = tree.link_poses(t, q, p)
    parameters = inertial_parameters(tree, p, dtype)
    mass, first_moment, inertia = placed(parameters[:, 0], parameters[:, 1:4],
                                         inertia_at_origin(parameters), rotation, origin)
    # The subtree sums as one add per link, leaves first: on robots a few hundred additions,
    # where a product with the subtree-membership matrix costs N² per parameter.
    n, parents = len(tree.links), tree.parents
    summed = list(jnp.concatenate([mass[:, None], first_moment, inertia.reshape(n, 9)], 1))
    for k in reversed(range(n)):
        if parents[k] >= 0:
            summed[parents[k]] = summed[parents[k]] + summed[k]
    composite = jnp.stack(summed)

    order, chains = _chains(tree)
    link_of = speed_subspaces(tree)[0][order]
    omega, velocity = (x[order] for x in world_subspaces(tree, rotation, origin))
    # F_j = I^c_link(j) s_j, the momentum about the world's origin (n, f) = (I ω + h × v,
    # m v + ω × h).
    mass_c, h = composite[link_of, 0], composite[link_of, 1:4]
    moment = (spatial.matvec(composite[link_of, 4:].reshape(-1, 3, 3), omega)
              + spatial.cross(h, velocity))
    force = mass_c[:, None] * velocity + spatial.cross(omega, h)
    motion, momentum = (jnp.concatenate([omega, velocity], 1),
                        jnp.concatenate([moment, force], 1))
    # s_i · F_j for i in a chain and j in the chain or its subtree, speeds in depth-first
    # order: each chain's rows are one product, zero outside [first, end). The rows hold
    # the upper triangle (and each chain's square block whole); M is its symmetric closure.
    m = len(order)
    if m == 0:
        return jnp.zeros((0, 0), dtype)
    rows = []
    for first, last, end in sorted(chains):
        if last == first:
            continue
        block = motion[first:last] @ momentum[first:end].T
        rows.append(jnp.pad(block, ((0, 0), (first, m - end))))
    upper = jnp.concatenate(rows)
    mass_matrix = jnp.where(np.triu(np.ones((m, m), dtype=bool)), upper, upper.T)
    if np.array_equal(order, np.arange(m)):
        return mass_matrix
    back = np.argsort(order)
    return mass_matrix[np.ix_(back, back)]
