"""Lagrange's equations of the second kind, formed by automatic differentiation."""

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .._convention import (
    CONFIGURATION_ARGS,
    VELOCITY_ARGS,
    call,
    scalar,
    time_rate,
    vector,
)
from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._state import check_vector, public_method
from .._system.base import AbstractMultibody


class Lagrangian(AbstractDynamics):
    r"""A holonomic system in independent coordinates, from its energies.

    Lagrange's equations of the second kind, with $L = T - V$,

    $$\frac{d}{dt}\frac{\partial L}{\partial \dot q} - \frac{\partial L}{\partial q}
      = Q - \frac{\partial D}{\partial \dot q},$$

    are expanded as $M \ddot q = f$ with

    $$M = \frac{\partial^2 L}{\partial \dot q^2}, \qquad
      f = Q - \frac{\partial D}{\partial \dot q} + \frac{\partial L}{\partial q}
      - \frac{\partial^2 L}{\partial \dot q\, \partial q}\, \dot q
      - \frac{\partial^2 L}{\partial \dot q\, \partial t}.$$

    One forward pass linearises (∂L/∂q̇, ∂L/∂q) (reverse-mode gradients); M is that linear map
    applied to the unit speeds (forward-over-reverse), and the velocity coupling and time terms
    are ONE more application along (1, q̇, 0). The mixed Hessian ∂²L/∂q̇∂q is never formed.

    **Arguments:**

    - `kinetic`: T(q, qd, p) → scalar.
    - `potential`: V(q, p) → scalar, or None.
    - `forces`: generalized non-conservative forces Q(q, qd, p) → (n,), defined by the virtual
      work δW = Σ Q_j δq_j (inputs, friction), or None.
    - `dissipation`: Rayleigh dissipation function D(q, qd, p) → scalar, or None; it adds the
      force −∂D/∂q̇.
    - `time_dependent`: if True every callback takes `t` first: T(t, q, qd, p), V(t, q, p),
      Q(t, q, qd, p), D(t, q, qd, p) (rheonomic constraints, a driven support, a forcing that
      varies in time).

    The speeds of this formulation are u = q̇. Every method takes ``(t, q, qd, p=None)``, and
    leading axes broadcast, so methods apply to whole trajectories.

    **Example:**

        def T(q, qd, p):
            return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2
        def V(q, p):
            return -p["m"] * 9.81 * p["l"] * jnp.cos(q[0])
        pendulum = jaxdyn.Lagrangian(T, V)
        qdd = pendulum.accelerations(0.0, jnp.array([0.3]), jnp.array([0.0]), p)

    Reference: J. L. Lagrange, Mécanique analytique (1788); H. Goldstein, Classical
    Mechanics (3rd ed., 2002), §1.4–1.6.
    """

    kinetic: Callable
    potential: Callable | None = None
    forces: Callable | None = None
    dissipation: Callable | None = None
    time_dependent: bool = eqx.field(default=False, static=True)

    @classmethod
    def from_system(cls, system: AbstractMultibody) -> "Lagrangian":
        """Lagrange's equations of a description of bodies (`MultibodySystem`,
        `RigidBodyTree`): T = Σ ½ m v_G·v_G + ½ ω·I ω, its V, and the generalized forces of
        its loads, dissipation and joint forces along q̇ (Q = (∂u/∂q̇)ᵀ Π). Needs coordinates
        whose rates determine the speeds: not quaternions (use Gibbs–Appell, Kane or the
        articulated-body algorithm for those)."""
        if not isinstance(system, AbstractMultibody):
            raise ValueError(
                "Lagrangian.from_system needs a description of bodies (jaxdyn.MultibodySystem "
                f"or jaxdyn.RigidBodyTree), got {type(system).__name__}."
            )
        return cls(kinetic=_SystemQuantity(system, "kinetic"),
                   potential=_SystemQuantity(system, "potential"),
                   forces=_SystemQuantity(system, "forces"),
                   time_dependent=system.time_dependent)

    def _kinetic(self, t, q, qd, p):
        value = call(self.kinetic, "kinetic energy T", self.time_dependent, VELOCITY_ARGS,
                     t, q, qd, p)
        return scalar(value, "kinetic energy T")

    def _potential(self, t, q, p):
        if self.potential is None:
            return jnp.zeros((), q.dtype)
        value = call(self.potential, "potential energy V", self.time_dependent,
                     CONFIGURATION_ARGS, t, q, p)
        return scalar(value, "potential energy V")

    def _lagrangian(self, t, q, qd, p):
        return self._kinetic(t, q, qd, p) - self._potential(t, q, p)

    def _forces(self, t, q, qd, p):
        """Q, the generalized forces the user gave."""
        value = call(self.forces, "generalized forces Q", self.time_dependent, VELOCITY_ARGS,
                     t, q, qd, p)
        return vector(value, "generalized forces Q", qd.shape)

    def _dissipation(self, t, q, qd, p):
        """D, Rayleigh's dissipation function the user gave."""
        value = call(self.dissipation, "dissipation function D", self.time_dependent,
                     VELOCITY_ARGS, t, q, qd, p)
        return scalar(value, "dissipation function D")

    def _nonconservative(self, t, q, qd, p):
        """Q − ∂D/∂q̇."""
        total = jnp.zeros_like(qd)
        if self.forces is not None:
            total = total + self._forces(t, q, qd, p)
        if self.dissipation is not None:
            total = total - jax.grad(lambda qd: self._dissipation(t, q, qd, p))(qd)
        return total

    def _check(self, t, q, qd):
        q = check_vector(q, "q")
        qd = check_vector(qd, "qd", q.shape[0])
        return jnp.asarray(t, q.dtype), q, qd

    def _linearised_momentum(self, t, q, qd, p):
        """((∂L/∂q̇, ∂L/∂q), their linearisation in (t, q, q̇))."""
        def gradients(t, q, qd):
            dL_dq, dL_dqd = jax.grad(self._lagrangian, argnums=(1, 2))(t, q, qd, p)
            return dL_dqd, dL_dq

        return jax.linearize(gradients, t, q, qd)

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = u: the speeds of Lagrange's equations are the coordinate rates."""
        return u

    def user_functions(self, t, q, qd, p=None):
        """(L, Q, D) at one state, Q and D where the user gave them; from a description, the
        description's callbacks."""
        t, q, qd = self._check(t, q, qd)
        if isinstance(self.kinetic, _SystemQuantity):
            system = self.kinetic.system
            return system.user_functions(t, q, system.speeds_from_rates(t, q, qd, p), p)
        # (The callbacks alone, no derivative and no zeros: the check evaluates what is
        # constant at trace time, and each constant it forms compiles a program of its own.)
        return (self._lagrangian(t, q, qd, p),
                None if self.forces is None else self._forces(t, q, qd, p),
                None if self.dissipation is None else self._dissipation(t, q, qd, p))

    def form_accelerations(self, t, q, qd, p=None, *, small):
        return accelerations_from_equations(self, t, q, qd, p, small=small)

    def energy_terms(self, t, q, qd, p=None):
        """(T(t, q, q̇), V(t, q)). For a time-dependent (rheonomic) system T + V is evaluated
        with the energies at time t and is in general not conserved; see `jacobi_integral`."""
        t, q, qd = self._check(t, q, qd)
        return self._kinetic(t, q, qd, p), self._potential(t, q, p)

    def form_equations(self, t, q, qd, p=None):
        """(M, f) with M = ∂²L/∂q̇² and f = Q − ∂D/∂q̇ + ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t."""
        t, q, qd = self._check(t, q, qd)

        def momentum(t, q, qd):
            return jax.grad(self._lagrangian, argnums=2)(t, q, qd, p)

        # M: the momentum's Jacobian in the speeds, forward-over-reverse along unit speeds.
        _, along_speeds = jax.linearize(lambda qd: momentum(t, q, qd), qd)
        mass_matrix = jax.vmap(along_speeds)(jnp.eye(q.shape[0], dtype=qd.dtype))
        # The momentum's rate at q̈ = 0, (∂²L/∂q̇∂q) q̇ + ∂²L/∂q̇∂t: one JVP along (ṫ, q̇), in
        # its own pass so that no work is spent on zero tangents.
        coupling = jax.jvp(lambda t, q: momentum(t, q, qd), (t, q),
                           (time_rate(t, self.time_dependent), qd))[1]
        dL_dq = jax.grad(self._lagrangian, argnums=1)(t, q, qd, p)
        return mass_matrix, self._nonconservative(t, q, qd, p) + dL_dq - coupling

    @public_method("(),(n),(n),(n)->(n)")
    def residual(self, t, q, qd, qdd, p=None):
        """The Euler–Lagrange residual d/dt ∂L/∂q̇ − ∂L/∂q − Q + ∂D/∂q̇ of a given motion.

        Zero (to measurement accuracy) when (q, q̇, q̈) satisfies the equations of motion. The
        total derivative d/dt ∂L/∂q̇ is one JVP along (1, q̇, q̈); no solve is involved, so
        this also checks measured motion where M is ill-conditioned.
        """
        t, q, qd = self._check(t, q, qd)
        qdd = check_vector(qdd, "qdd", q.shape[0])
        (_, dL_dq), linear = self._linearised_momentum(t, q, qd, p)
        momentum_rate, _ = linear(time_rate(t, self.time_dependent), qd, qdd)
        return momentum_rate - dL_dq - self._nonconservative(t, q, qd, p)

    @public_method("(),(n),(n)->()")
    def lagrangian(self, t, q, qd, p=None):
        """L = T − V."""
        t, q, qd = self._check(t, q, qd)
        return self._lagrangian(t, q, qd, p)

    @public_method("(),(n),(n)->()")
    def jacobi_integral(self, t, q, qd, p=None):
        """Jacobi's integral h = q̇·∂L/∂q̇ − L (the Hamiltonian in terms of q̇).

        Equal to T + V when T is quadratic in q̇. Conserved whenever L has no explicit t and
        Q = 0, D = 0, also for rheonomic coordinates such as a uniformly rotating frame, where
        T + V is not conserved.
        """
        t, q, qd = self._check(t, q, qd)
        lagrangian, momentum = jax.value_and_grad(self._lagrangian, argnums=2)(t, q, qd, p)
        return jnp.dot(qd, momentum) - lagrangian


class _SystemQuantity(eqx.Module):
    """A description's kinetic energy, potential energy or generalized forces as a callback
    in Lagrange's calling convention (t first when the description is time-dependent)."""

    system: AbstractMultibody
    quantity: str = eqx.field(static=True)

    def __call__(self, *args):
        system = self.system
        if system.time_dependent:
            t, *args = args
        else:
            t = jnp.zeros((), args[0].dtype)
        if self.quantity == "potential":
            q, p = args
            return system.potential_energy(t, q, p)
        q, qd, p = args
        u, transpose = jax.vjp(lambda qd: system.speeds_from_rates(t, q, qd, p), qd)
        if self.quantity == "kinetic":
            return system.kinetic_energy(t, q, u, p)
        # Q·δq̇ = Π·δu with u linear in q̇: Q = (∂u/∂q̇)ᵀ Π.
        return transpose(system.applied_forces(t, q, u, p))[0]
