"""The interface every formulation implements, and the only thing `simulate` knows about."""

import abc

import equinox as eqx

from ._custom_types import Coordinates, MassMatrix, Params, RealScalarLike, Speeds
from ._errors import check_static_indexing, reports_state
from ._linalg import solve_mass_matrix
from ._state import over_states


class AbstractDynamics(eqx.Module):
    """Equations of motion in the form

        q̇ = K(t, q, p) u,        M(t, q, p) u̇ = f(t, q, u, p)

    with coordinates q (n,) and speeds u (m,). For Lagrange's equations u = q̇ and K = I; the
    Gibbs–Appell and Kane formulations may choose other speeds (and fewer of them than
    coordinates, for nonholonomic systems).

    Subclasses implement `coordinate_rates` and `mass_matrix_and_forcing`; the accelerations
    follow by a Cholesky solve. All public methods take ``(t, q, u, p=None)`` and also accept
    stacked states (leading axes broadcast).
    """

    @abc.abstractmethod
    def coordinate_rates(
        self, t: RealScalarLike, q: Coordinates, u: Speeds, p: Params = None
    ) -> Coordinates:
        """q̇ = K(t, q, p) u."""

    @abc.abstractmethod
    def mass_matrix_and_forcing(
        self, t: RealScalarLike, q: Coordinates, u: Speeds, p: Params = None
    ) -> tuple[MassMatrix, Speeds]:
        """(M, f) of M u̇ = f, formed together since they share their derivative passes."""

    @abc.abstractmethod
    def user_functions(self, t, q, u, p=None):
        """Every user callback evaluated once, without derivatives (for trace-time checks)."""

    def _checked_equations(self, t, q, u, p=None):
        """`mass_matrix_and_forcing`, after a trace-time check that no callback indexes past
        the end of q or u (which JAX would silently clamp)."""
        check_static_indexing(self.user_functions, t, q, u, p)
        return self.mass_matrix_and_forcing(t, q, u, p)

    @over_states("(),(n),(m)->(m,m)")
    def mass_matrix(self, t, q, u, p=None):
        """The mass matrix M of M u̇ = f (symmetric positive definite)."""
        return self._checked_equations(t, q, u, p)[0]

    @over_states("(),(n),(m)->(m)")
    def forcing(self, t, q, u, p=None):
        """The forcing f of M u̇ = f: every term of the equations except M u̇."""
        return self._checked_equations(t, q, u, p)[1]

    @reports_state
    @over_states("(),(n),(m)->(m)")
    def accelerations(self, t, q, u, p=None):
        """u̇ = M⁻¹ f by Cholesky; an error names the state if M is singular there."""
        mass_matrix, forcing = self._checked_equations(t, q, u, p)
        return solve_mass_matrix(mass_matrix, forcing, t, q, u)


def solve_equations(dynamics: AbstractDynamics, t, q, u, p):
    """u̇ = M⁻¹ f for one state, without the trace-time checks (for use inside solvers, where
    `simulate` has run them once)."""
    mass_matrix, forcing = dynamics.mass_matrix_and_forcing(t, q, u, p)
    return solve_mass_matrix(mass_matrix, forcing, t, q, u)
