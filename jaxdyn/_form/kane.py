"""Kane's equations: generalized active plus generalized inertia forces vanish."""

from typing import Callable

import jax.numpy as jnp

from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._state import check_vector
from .._system.base import AbstractMultibody


class Kane(AbstractDynamics):
    r"""Kane's method on a description of bodies (`MultibodySystem`, `RigidBodyTree`):

    $$F_r + F^*_r = 0, \qquad r = 1, \dots, m,$$
    $$F_r = \sum F \cdot v_r + \sum \tau \cdot \omega_r \quad \text{(and } -\partial V/\partial q,
      \ -\partial D/\partial \dot q \text{ along the speeds)},$$
    $$F^*_r = -\sum m\, a \cdot v_r - \sum (I \alpha + \omega \times I \omega) \cdot \omega_r,$$

    with partial velocities v_r = ∂v/∂u_r, ω_r = ∂ω/∂u_r (Jacobians of the kinematics in the
    speeds). F*_r is affine in u̇ with coefficients given by the partial velocities, so

    $$M_{rs} = \sum m\, v_r \cdot v_s + \omega_r \cdot I \omega_s, \qquad
      f = F + F^*\big|_{\dot u = 0}.$$

    **Arguments:**

    - `system`: the description of the bodies.
    - `kinematic_map`: K(q, p) → (n, m) with q̇ = K u (the kinematic differential equations),
      or None for the description's own speeds (q̇ for a `MultibodySystem`, the joints'
      speeds for a `RigidBodyTree`). Independent speeds of a nonholonomic system: m < n.

    `Kane.from_system(system, kinematic_map)` is the same, named like the other formulations.

    Reference: T. R. Kane and D. A. Levinson, Dynamics: Theory and Applications (1985),
    ch. 6; R. L. Huston, Multibody Dynamics (1990), ch. 4.
    """

    system: AbstractMultibody
    kinematic_map: Callable | None = None

    def __check_init__(self):
        if not isinstance(self.system, AbstractMultibody):
            raise ValueError(
                "Kane's method needs a description of bodies (jaxdyn.MultibodySystem or "
                f"jaxdyn.RigidBodyTree), got {type(self.system).__name__}."
            )

    @classmethod
    def from_system(cls, system, kinematic_map=None) -> "Kane":
        """Kane's equations of `system`, in the speeds of `kinematic_map` (if given)."""
        return cls(system, kinematic_map)

    def _check(self, t, q, u, p):
        q, u = check_vector(q, "q"), check_vector(u, "u")
        t = jnp.asarray(t, q.dtype)
        self.system.check_speeds(t, q, u, p, self.kinematic_map)
        return t, q, u

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = K(t, q, p) u."""
        return self.system.coordinate_rates(t, q, u, p, self.kinematic_map)

    def user_functions(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u, p)
        return self.system.user_functions(t, q, u, p, self.kinematic_map)

    def energy_terms(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u, p)
        return (self.system.kinetic_energy(t, q, u, p, self.kinematic_map),
                self.system.potential_energy(t, q, p))

    def form_accelerations(self, t, q, u, p=None, *, small):
        return accelerations_from_equations(self, t, q, u, p, small=small)

    def form_equations(self, t, q, u, p=None):
        """(M, f) with M_rs = Σ m v_r·v_s + ω_r·I ω_s and f = F + F*|u̇=0."""
        t, q, u = self._check(t, q, u, p)
        return kane_equations(self.system, self.kinematic_map, t, q, u, p)


def kane_equations(system, kinematic_map, t, q, u, p):
    """Kane's (M, f) for a description of bodies: M from the partial velocities, f the
    generalized active forces plus the inertia forces at u̇ = 0."""
    partials = system.partial_velocities(t, q, u, p, kinematic_map)
    inertia_at_rest = system.generalized_inertia_forces(
        t, q, u, jnp.zeros_like(u), p, kinematic_map, partials)
    active = system.generalized_active_forces(t, q, u, p, kinematic_map)
    return system.kane_mass_matrix(p, partials), active + inertia_at_rest
