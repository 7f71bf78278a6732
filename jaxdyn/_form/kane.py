"""Kane's equations: generalized active plus generalized inertia forces vanish."""

from typing import Callable

import jax.numpy as jnp

from .._dynamics import AbstractDynamics
from .._state import check_vector
from .._system.bodies import mass
from .._system.multibody import MultibodySystem


class Kane(AbstractDynamics):
    r"""Kane's method on a `MultibodySystem`:

        F_r + F*_r = 0,   r = 1 … m,
        F_r  = Σ F·v_r + Σ τ·ω_r (and −∂V/∂q, −∂D/∂q̇ along the speeds),
        F*_r = −Σ m a·v_r − Σ (I α + ω × I ω)·ω_r,

    with partial velocities v_r = ∂v/∂u_r, ω_r = ∂ω/∂u_r (Jacobians of the kinematics in the
    speeds). F*_r is affine in u̇ with coefficients given by the partial velocities, so

        M_rs = Σ m v_r·v_s + ω_r·I ω_s,   f = F + F*|_{u̇=0}.

    **Arguments:**

    - `system`: the `jaxdyn.MultibodySystem`.
    - `kinematic_map`: K(q, p) → (n, m) with q̇ = K u (the kinematic differential equations),
      or None for u = q̇. Independent speeds of a nonholonomic system: m < n.

    Reference: T. R. Kane and D. A. Levinson, Dynamics: Theory and Applications (1985);
    reference.md §2.
    """

    system: MultibodySystem
    kinematic_map: Callable | None = None

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = K(t, q, p) u."""
        return self.system.coordinate_rates(t, q, u, p, self.kinematic_map)

    def user_functions(self, t, q, u, p=None):
        """(T, V, applied forces, D, q̇) at one state."""
        q, u = check_vector(q, "q"), check_vector(u, "u")
        t = jnp.asarray(t, q.dtype)
        system = self.system
        qd = self.coordinate_rates(t, q, u, p)
        return (system.kinetic_energy(t, q, qd, p), system.potential_energy(t, q, p),
                system.applied_forces(t, q, qd, p), system.dissipation_function(t, q, qd, p), qd)

    def form_equations(self, t, q, u, p=None):
        """(M, f) with M_rs = Σ m v_r·v_s + ω_r·I ω_s and f = F + F*|u̇=0."""
        q = check_vector(q, "q")
        u = check_vector(u, "u")
        t = jnp.asarray(t, q.dtype)
        partials = self.system.partial_velocities(t, q, u, p, self.kinematic_map)
        mass_matrix = jnp.zeros((u.shape[0], u.shape[0]), u.dtype)
        for body, (v_r, w_r) in zip(self.system.bodies, partials):
            mass_matrix = mass_matrix + mass(body, p) * v_r.T @ v_r
            if w_r is not None:
                mass_matrix = mass_matrix + w_r.T @ body._inertia(p) @ w_r
        inertia_at_rest = self.system.generalized_inertia_forces(
            t, q, u, jnp.zeros_like(u), p, self.kinematic_map, partials
        )
        active = self.system.generalized_active_forces(t, q, u, p, self.kinematic_map)
        return mass_matrix, active + inertia_at_rest
