"""The Gibbs–Appell equations: the mass matrix is the Hessian of the Gibbs function."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import call, scalar, vector
from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._speeds import kinematic_matrix
from .._state import check_vector
from .._system.base import AbstractMultibody

GIBBS_ARGS = ("q", "u", "ud", "p")
ACTIVE_ARGS = ("q", "u", "p")


class GibbsAppell(AbstractDynamics):
    r"""Equations of motion from a Gibbs function ("energy of accelerations").

    $$\frac{\partial S}{\partial \dot u_r} = \Pi_r, \qquad r = 1, \dots, m,$$

    with $S(q, u, \dot u) = \tfrac12 \sum m\, a \cdot a$ ($+ \tfrac12 \alpha \cdot I \alpha
    + \alpha \cdot (\omega \times I \omega)$ for rigid bodies) quadratic in $\dot u$, so

    $$M = \frac{\partial^2 S}{\partial \dot u^2} \;\text{(its Hessian in the accelerations)},
      \qquad f = \Pi - \left.\frac{\partial S}{\partial \dot u}\right|_{\dot u = 0}.$$

    M is formed forward-over-reverse at u̇ = 0, where the gradient is also the bias.

    **Arguments:**

    - `gibbs`: S(q, u, ud, p) → scalar.
    - `active_forces`: Π(q, u, p) → (m,), the generalized active forces along the speeds, or
      None for a free system.
    - `kinematic_map`: K(q, p) → (n, m) with q̇ = K u, or None for u = q̇. With m < n the
      speeds are independent quasi-velocities of a nonholonomic system.
    - `time_dependent`: if True every callback takes t first.

    Build one from a description of bodies with `GibbsAppell.from_system(system, K)`: S is
    then Σ ½ m a_G·a_G + ½ α·I α + α·(ω × I ω) over the bodies (Khang's matrix form: with the
    body accelerations affine in u̇, a = J u̇ + J̇ u, its Hessian is Σ Jᵀ M_body J).

    Reference: P. Appell (1899); N. V. Khang, Vietnam J. Mech. 28(4) (2006).
    """

    gibbs: Callable
    active_forces: Callable | None = None
    kinematic_map: Callable | None = None
    time_dependent: bool = eqx.field(default=False, static=True)
    system: AbstractMultibody | None = None

    @classmethod
    def from_system(cls, system: AbstractMultibody, kinematic_map=None) -> "GibbsAppell":
        """The Gibbs–Appell equations of a description of bodies (`MultibodySystem`,
        `RigidBodyTree`), in the speeds of `kinematic_map` (if given; else the description's
        own)."""
        if not isinstance(system, AbstractMultibody):
            raise ValueError(
                "GibbsAppell.from_system needs a description of bodies (jaxdyn.MultibodySystem "
                f"or jaxdyn.RigidBodyTree), got {type(system).__name__}."
            )
        return cls(gibbs=_SystemQuantity(system, "gibbs", kinematic_map),
                   active_forces=_SystemQuantity(system, "active", kinematic_map),
                   kinematic_map=kinematic_map, time_dependent=system.time_dependent,
                   system=system)

    def _kinematic_matrix(self, t, q, u, p):
        if self.system is not None:
            return self.system.kinematic_matrix(t, q, p, self.kinematic_map, u)
        return kinematic_matrix(self.kinematic_map, self.time_dependent, t, q, p, u)

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = K(t, q, p) u."""
        return self._kinematic_matrix(t, q, u, p) @ u

    def _check(self, t, q, u, p):
        q = check_vector(q, "q")
        u = check_vector(u, "u")
        t = jnp.asarray(t, q.dtype)
        if self.system is not None:
            self.system.check_speeds(t, q, u, p, self.kinematic_map)
        else:  # (K of the user's kinematic map, its shape checked)
            kinematic_matrix(self.kinematic_map, self.time_dependent, t, q, p, u)
        return t, q, u

    def energy_terms(self, t, q, u, p=None):
        if self.system is None:
            raise ValueError(
                "A GibbsAppell built from a Gibbs function has no kinetic or potential energy. "
                "Build it from a description of bodies (GibbsAppell.from_system) for the "
                "energies and momenta."
            )
        t, q, u = self._check(t, q, u, p)
        return (self.system.kinetic_energy(t, q, u, p, self.kinematic_map),
                self.system.potential_energy(t, q, p))

    def form_accelerations(self, t, q, u, p=None, *, small):
        return accelerations_from_equations(self, t, q, u, p, small=small)

    def _gibbs(self, t, q, u, ud, p):
        value = call(self.gibbs, "Gibbs function S", self.time_dependent, GIBBS_ARGS,
                     t, q, u, ud, p)
        return scalar(value, "Gibbs function S")

    def _active_forces(self, t, q, u, p):
        if self.active_forces is None:
            return jnp.zeros_like(u)
        return vector(call(self.active_forces, "active forces Π", self.time_dependent,
                           ACTIVE_ARGS, t, q, u, p), "active forces Π", u.shape)

    def user_functions(self, t, q, u, p=None):
        """(S at u̇ = 0, Π, q̇) at one state; from a description, the description's callbacks."""
        t, q, u = self._check(t, q, u, p)
        if self.system is not None:
            return self.system.user_functions(t, q, u, p, self.kinematic_map)
        return (self._gibbs(t, q, u, jnp.zeros_like(u), p), self._active_forces(t, q, u, p),
                self.coordinate_rates(t, q, u, p))

    def form_equations(self, t, q, u, p=None):
        """(M, f) with M = ∂²S/∂u̇² and f = Π − ∂S/∂u̇ at u̇ = 0."""
        t, q, u = self._check(t, q, u, p)

        def gibbs(ud):
            return self._gibbs(t, q, u, ud, p)

        # One linearisation of ∇_u̇ S at u̇ = 0 gives the bias (its value) and M (its tangent
        # map, applied to the unit accelerations): forward-over-reverse.
        bias, hessian_times = jax.linearize(jax.grad(gibbs), jnp.zeros_like(u))
        mass_matrix = jax.vmap(hessian_times)(jnp.eye(u.shape[0], dtype=u.dtype))
        return mass_matrix, self._active_forces(t, q, u, p) - bias


class _SystemQuantity(eqx.Module):
    """A description's Gibbs function or active forces, as a callback in the calling
    convention (t first when the description is time-dependent)."""

    system: AbstractMultibody
    quantity: str = eqx.field(static=True)
    kinematic_map: Callable | None

    def __call__(self, *args):
        if self.system.time_dependent:
            t, *args = args
        else:
            t = jnp.zeros((), args[0].dtype)
        if self.quantity == "gibbs":
            q, u, ud, p = args
            return self.system.gibbs_function(t, q, u, ud, p, self.kinematic_map)
        q, u, p = args
        return self.system.generalized_active_forces(t, q, u, p, self.kinematic_map)
