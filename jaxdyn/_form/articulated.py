"""Featherstone's articulated-body algorithm: forward dynamics of a tree in O(N)."""

import jax.numpy as jnp
import numpy as np

from .._dynamics import AbstractDynamics
from .._linalg import ldl, ldl_solve
from .._state import check_vector
from .._system import spatial
from .._system.tree import RigidBodyTree
from .composite import composite_mass_matrix
from .newton_euler import joint_forces as newton_euler_joint_forces, newton_euler


def _skew(v):
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                      jnp.stack([-y, x, zero], -1)], -2)


def _block(a, b, c, d):
    """[[a, b], [c, d]] from 3 × 3 blocks."""
    return jnp.concatenate([jnp.concatenate([a, b], -1), jnp.concatenate([c, d], -1)], -2)


def motion_transform(rotation, origin):
    """X (6 × 6) mapping motion vectors (ω, v) from the parent to the child frame:
    [[Rᵀ, 0], [−Rᵀ r×, Rᵀ]] (its transpose maps force vectors back)."""
    rt = jnp.swapaxes(rotation, -1, -2)
    zero = jnp.zeros_like(rt)
    return _block(rt, zero, -spatial.matmul(rt, _skew(origin)), rt)


def spatial_inertia(mass, com, inertia):
    """The 6 × 6 spatial inertia about a body frame's origin:
    [[I_c + m c× c×ᵀ, m c×], [m c×ᵀ, m 1]]."""
    c = _skew(com)
    m = mass[..., None, None]
    ct = jnp.swapaxes(c, -1, -2)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=inertia.dtype), inertia.shape)
    return _block(inertia + m * spatial.matmul(c, ct), m * c, m * ct, m * eye)


def _matvec6(m, v):
    return jnp.sum(m * v[..., None, :], axis=-1)


class ArticulatedBody(AbstractDynamics):
    r"""Forward dynamics of a `RigidBodyTree` by the articulated-body algorithm (Featherstone,
    Rigid Body Dynamics Algorithms, 2008, §7.3), in O(N) for N links:

    1. outwards, the links' spatial velocities v_i = X_i v_λ(i) + S_i u_i, velocity-product
       accelerations c_i = v_i ×ₘ S_i u_i and bias forces p_i = v_i ×* I_i v_i − f_i;
    2. inwards, articulated inertias and bias forces: U_i = I^A_i S_i, D_i = S_iᵀ U_i,
       τ'_i = τ_i − S_iᵀ p^A_i, and the parent receives X_iᵀ (I^A_i − U_i D_i⁻¹ U_iᵀ) X_i and
       X_iᵀ (p^A_i + I^a_i c_i + U_i D_i⁻¹ τ'_i);
    3. outwards, a'_i = X_i a_λ(i) + c_i, u̇_i = D_i⁻¹ (τ'_i − U_iᵀ a'_i), a_i = a'_i + S_i u̇_i,
       from the world's acceleration (0, −g) (gravity as an acceleration of the base).

    Joint forces τ gather `forces`, the dampers, the springs and any potential other than
    gravity (−Kᵀ ∂V/∂q); loads enter as the links' external forces f_i. `mass_matrix` is
    formed by the composite-rigid-body algorithm (§6.2) and `forcing` by the recursive
    Newton–Euler algorithm at u̇ = 0 (§5.3).
    All three run on the tree with its fixed joints welded (`RigidBodyTree.merge_fixed`).
    This is the fast formulation for trees; the others agree with it to round-off.

    **Arguments:**

    - `tree`: the `jaxdyn.RigidBodyTree`.
    """

    tree: RigidBodyTree

    @property
    def batch_in_chunks(self) -> bool:
        """True: under `jax.vmap` the recursions run in chunks of a few states (per state in a
        batch of 1024, the Panda's forward dynamics 13.8 → 2.2 µs)."""
        return True

    def __check_init__(self):
        if not isinstance(self.tree, RigidBodyTree):
            raise ValueError("The articulated-body algorithm needs a jaxdyn.RigidBodyTree, got "
                             f"{type(self.tree).__name__}.")

    @classmethod
    def from_system(cls, tree: RigidBodyTree) -> "ArticulatedBody":
        """The articulated-body algorithm on `tree`."""
        return cls(tree)

    def _check(self, t, q, u):
        q, u = check_vector(q, "q"), check_vector(u, "u")
        self.tree._check_state(q, u)
        return jnp.asarray(t, q.dtype), q, u

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = K(q) u, joint by joint."""
        return self.tree.coordinate_rates(t, q, u, p)

    def user_functions(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u)
        return self.tree.user_functions(t, q, u, p)

    def energy_terms(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u)
        return self.tree.kinetic_energy(t, q, u, p), self.tree.potential_energy(t, q, p)

    def form_equations(self, t, q, u, p=None):
        """(M, f): M by the composite-rigid-body algorithm, f = τ − c(q, u) + g(q) + Jᵀ f^ext
        by the recursive Newton–Euler algorithm at u̇ = 0."""
        t, q, u = self._check(t, q, u)
        bodies = self.tree.merge_fixed()
        forcing = (newton_euler_joint_forces(bodies, t, q, u, p)
                   - newton_euler(bodies, t, q, u, jnp.zeros_like(u), p))
        return composite_mass_matrix(bodies, t, q, p), forcing

    def form_accelerations(self, t, q, u, p=None, *, small):
        t, q, u = self._check(t, q, u)
        return articulated_body_algorithm(self.tree.merge_fixed(), t, q, u, p)

    def form_residual(self, t, q, u, ud, p=None):
        """M u̇ − f by the recursive Newton–Euler algorithm (Featherstone §5.3), O(N): the
        links' inertial and gravitational forces and loads, less the joints' own forces."""
        t, q, u = self._check(t, q, u)
        ud = check_vector(ud, "u̇ (ud)", self.tree.num_speeds)
        bodies = self.tree.merge_fixed()
        return (newton_euler(bodies, t, q, u, ud, p)
                - newton_euler_joint_forces(bodies, t, q, u, p))


def _subspaces(tree):
    """Per link the motion subspace padded to the tree's largest joint, S (N, 6, k), the mask
    of padded columns (N, k), and for each speed its (link, column)."""
    width = max(1, max(link.joint.nv for link in tree.links))
    subspaces = np.zeros((len(tree.links), 6, width))
    padded = np.ones((len(tree.links), width))
    columns = []
    for i, link in enumerate(tree.links):
        nv = link.joint.nv
        subspaces[i, :, :nv] = link.joint.subspace()
        padded[i, :nv] = 0.0
        columns += [(i, k) for k in range(nv)]
    return subspaces, padded, columns


def articulated_body_algorithm(tree, t, q, u, p, applied=None):
    """(u̇, singular, nonfinite): the accelerations of `tree`, NaN where some D_i is singular
    (a link whose joint moves nothing with inertia) or the forces are not finite. `applied`:
    further generalized forces along the speeds (control inputs B r), added to the joint
    forces."""
    dtype = q.dtype
    subspaces_np, padded_np, columns = _subspaces(tree)
    n, width = padded_np.shape
    subspaces = jnp.asarray(subspaces_np, dtype)
    # Links taken one by one see their own joint's width (see `inwards`); those in the scan
    # the widest of theirs (a floating base is taken before the scan: `scan_head`).
    head = tree.scan_head()
    scan_width = max([1] + [link.joint.nv for link in tree.links[head:]])
    link_of, column_of = (np.array(x, dtype=np.int32) for x in zip(*columns)) if columns else \
        (np.zeros(0, np.int32), np.zeros(0, np.int32))

    # Joint forces along the speeds: forces, dampers, and every potential but gravity.
    tau = newton_euler_joint_forces(tree, t, q, u, p)
    if applied is not None:
        tau = tau + applied
    tau_links = jnp.zeros((n, width), dtype).at[link_of, column_of].set(tau)

    rotation, origin, omega_j, velocity_j = tree.joint_motion(q, u)
    transforms = motion_transform(rotation, origin)
    masses, coms, inertias = tree.link_inertias(p, dtype)
    inertia6 = spatial_inertia(masses, coms, inertias)
    moments, forces = tree.load_wrenches(t, q, u, p)
    joint_velocity = jnp.concatenate([omega_j, velocity_j], -1)

    # 1. velocities outwards
    def outwards(parent, link):
        x, vj = link
        return _matvec6(x, parent) + vj

    velocity = tree.forward(outwards, jnp.zeros(6, dtype), (transforms, joint_velocity))
    omega, linear = velocity[:, :3], velocity[:, 3:]
    c_omega, c_linear = spatial.cross_motion(omega, linear, omega_j, velocity_j)
    bias_acceleration = jnp.concatenate([c_omega, c_linear], -1)
    momentum = _matvec6(inertia6, velocity)
    b_moment, b_force = spatial.cross_force(omega, linear, momentum[:, :3], momentum[:, 3:])
    bias = jnp.concatenate([b_moment - moments, b_force - forces], -1)

    # 2. articulated inertias inwards
    def inwards(accumulated, link):
        inertia_c, bias_c = accumulated
        x, own_inertia, own_bias, s, pad, torque, c = link
        # Links taken one by one (a Python loop) see their own joint's width k (`pad` is a
        # NumPy constant): a floating base's six columns do not widen every other link's
        # algebra. In a scan every link has the scan's widest joint, padded columns pinned.
        k = max(1, int(np.sum(pad == 0))) if isinstance(pad, np.ndarray) else scan_width
        s, pad, torque = s[:, :k], pad[:k], torque[:k]
        pinned = jnp.asarray(pad, dtype)  # a NumPy constant: in the state's dtype
        articulated = own_inertia + inertia_c
        articulated_bias = own_bias + bias_c
        u_matrix = spatial.matmul(articulated, s)  # U = I^A S
        st = jnp.swapaxes(s, -1, -2)
        d = spatial.matmul(st, u_matrix) + jnp.diag(pinned)
        lower, reciprocals, failed_pivots = ldl(d)
        residual = torque - _matvec6(st, articulated_bias)
        d_inv_ut = ldl_solve(lower, reciprocals, u_matrix)  # U D⁻¹ (D symmetric), row-wise
        d_inv_residual = ldl_solve(lower, reciprocals, residual)
        reduced = articulated - spatial.matmul(d_inv_ut, jnp.swapaxes(u_matrix, -1, -2))
        reduced_bias = (articulated_bias + _matvec6(reduced, c)
                        + _matvec6(u_matrix, d_inv_residual))
        xt = jnp.swapaxes(x, -1, -2)
        up = (spatial.matmul(xt, spatial.matmul(reduced, x)), _matvec6(xt, reduced_bias))
        failed = jnp.any(failed_pivots & (pad == 0))  # padded columns are pinned, never fail
        widen = ((0, 0),) * (u_matrix.ndim - 1) + ((0, width - k),)
        return (jnp.pad(u_matrix, widen), jnp.pad(d_inv_ut, widen),
                jnp.pad(d_inv_residual, widen[-1:]), failed), up

    zero = (jnp.zeros((6, 6), dtype), jnp.zeros(6, dtype))
    (u_matrices, u_d_inv, d_inv_residuals, failures), _ = tree.backward(
        inwards, zero, (transforms, inertia6, bias, subspaces, padded_np, tau_links,
                        bias_acceleration))

    # 3. accelerations outwards, from the world's (0, −g)
    def accelerations_out(parent, link):
        parent_acceleration, _ = parent
        x, c, s, u_matrix, ud_inv, d_inv_residual = link
        acceleration = _matvec6(x, parent_acceleration) + c
        udot = d_inv_residual - _matvec6(jnp.swapaxes(ud_inv, -1, -2), acceleration)
        return acceleration + _matvec6(s, udot), udot

    gravity = tree.gravity_vector(p, dtype)
    world = (jnp.concatenate([jnp.zeros(3, dtype), -gravity]), jnp.zeros(width, dtype))
    _, udots = tree.forward(accelerations_out, world,
                            (transforms, bias_acceleration, subspaces, u_matrices, u_d_inv,
                             d_inv_residuals))
    accelerations = udots[link_of, column_of]
    singular = jnp.any(failures)
    nonfinite = ~jnp.all(jnp.isfinite(tau)) | ~jnp.all(jnp.isfinite(bias))
    return jnp.where(singular | nonfinite, jnp.nan, accelerations), singular, nonfinite
