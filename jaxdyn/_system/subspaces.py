"""Which speeds move which links of a `RigidBodyTree`, and how: the chain of links from the root
to a link with the indices of their coordinates and speeds (`ancestry`), and each speed's
joint motion subspace, in its link's axes (`speed_subspaces`) and turned and moved into the
world (`world_subspaces`): the columns of the Jacobian of any point the speed moves
(Featherstone, Rigid Body Dynamics Algorithms, 2008, §4.6). Frames, contacts and the
composite-body and Newton–Euler algorithms build on them.
"""

import jax
import jax.numpy as jnp
import numpy as np

from . import spatial


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
