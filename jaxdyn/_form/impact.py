"""Unilateral contacts and Newton's impact law, through any formulation's mass matrix."""

import itertools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._convention import CONFIGURATION_ARGS, call
from .._dynamics import formed_equations
from .._events import AbstractEvent, as_guards

#: The most contacts that may close at one instant: the impact law's complementarity problem
#: is solved by enumerating the 2^k sets of contacts that push (exact, and differentiable
#: within the set that holds).
MAX_SIMULTANEOUS = 10


class UnilateralContact(AbstractEvent):
    r"""Unilateral contacts φ(q) ≥ 0 with impacts by Newton's law of restitution.

    The motion is smooth while every gap φ_i(q, p) is open. When one closes (φ_i = 0 with
    approach, $\dot φ_i < 0$), the speeds jump by impulses Λ along the contacts' normals,

    $$M (u^+ - u^-) = J^\mathsf{T} Λ, \qquad J = \frac{\partial \dot φ}{\partial u},$$

    with the mass matrix M of the formulation simulated (in its own speeds: Lagrange's q̇,
    the speeds of Gibbs–Appell and Kane, a tree's joint speeds; a `Constrained` system's
    impulses also keep its velocity constraints, by the multipliers of the impact). On the
    contacts closed at the instant (φ_i within `closed_within` of zero), the impulses and the
    separation speeds obey Newton's law in the complementarity form of Moreau and Glocker,

    $$Λ \ge 0, \qquad \dot φ^+ + e\, \dot φ^- \ge 0,
      \qquad Λ^\mathsf{T}(\dot φ^+ + e\,\dot φ^-) = 0,$$

    which for one contact is $\dot φ^+ = -e\,\dot φ^-$ and for several simultaneous contacts a
    small linear complementarity problem, solved exactly (up to `MAX_SIMULTANEOUS` closed
    contacts).

    **Arguments:**

    - `gap`: φ(q, p) → a scalar or a vector of k gaps, positive while open (φ(t, q, p) with
      `time_dependent=True`, e.g. a moving wall).
    - `restitution`: the coefficient of restitution e ∈ [0, 1], a number, an array (k,), or
      a function e(p) of the parameters (so that it can be fitted or differentiated).
    - `closed_within`: gaps at most this are closed at an impact (simultaneous contacts).

    **Example:**

        ground = jaxdyn.UnilateralContact(lambda q, p: q[1], restitution=lambda p: p["e"])
        sol = jaxdyn.simulate(ball, q0, u0, p, t1=3.0, events=[ground], max_events=64)
        sol.events.t        # impact times
        sol.events.impulses # Λ at each impact

    Reference: I. Newton, Principia (1687), Cor. VI; J. J. Moreau, "Unilateral contact and dry
    friction in finite freedom dynamics" (1988); Ch. Glocker, Set-Valued Force Laws (2001);
    F. Pfeiffer, Ch. Glocker, Multibody Dynamics with Unilateral Contacts (1996).
    """

    gap: Callable
    restitution: float | jax.Array | Callable = 0.0
    closed_within: float = eqx.field(default=1e-9, static=True)
    time_dependent: bool = eqx.field(default=False, static=True)

    @property
    def direction(self) -> str:
        return "falling"

    @property
    def terminal(self) -> bool:
        return False

    def gaps(self, t, q, p):
        """φ(t, q, p), shape (k,)."""
        value = call(self.gap, "gap φ", self.time_dependent, CONFIGURATION_ARGS, t, q, p)
        return as_guards(value, "gap φ")

    def guards(self, dynamics, t, q, u, p):
        return self.gaps(t, q, p)

    def coefficients(self, p, k: int, dtype):
        """e, shape (k,)."""
        e = self.restitution(p) if callable(self.restitution) else self.restitution
        e = jnp.asarray(e, dtype)
        if e.ndim > 1 or (e.ndim == 1 and e.shape[0] != k):
            raise ValueError(f"The restitution must be a number or an array of {k} "
                             f"coefficients (one per gap), got shape {e.shape}.")
        return jnp.broadcast_to(e, (k,))

    def normal_speeds(self, dynamics, t, q, u, p):
        """(φ̇ = J u + ∂φ/∂t, J = ∂φ̇/∂u): the gaps' rates along the motion, linear in u."""
        def rates(u):
            q_dot = dynamics.coordinate_rates(t, q, u, p)
            dt = jnp.ones_like(t) if self.time_dependent else jnp.zeros_like(t)
            return jax.jvp(lambda t, q: self.gaps(t, q, p), (t, q), (dt, q_dot))[1]

        return rates(u), jax.jacfwd(rates)(u)

    def jump(self, dynamics, t, q, u, p, fired):
        k = fired.shape[0]
        if k > MAX_SIMULTANEOUS:
            raise ValueError(
                f"A UnilateralContact of {k} gaps: the impact law enumerates the sets of "
                f"contacts that push, up to {MAX_SIMULTANEOUS} gaps per contact. Split the "
                "gaps into several UnilateralContacts (contacts that cannot close at the "
                "same instant), or use a compliant contact.")
        closed = fired | (self.gaps(t, q, p) <= self.closed_within)
        speed, jacobian = self.normal_speeds(dynamics, t, q, u, p)
        restitution = self.coefficients(p, k, speed.dtype)
        response = impulse_response(dynamics, t, q, u, p, jacobian)
        delassus = jacobian @ response
        impulses = newton_impulses(delassus, (1 + restitution) * speed, closed)
        return q, u + response @ impulses, impulses


def impulse_response(dynamics, t, q, u, p, jacobian):
    """X = ∂u⁺/∂Λ, shape (m, k): the change of the speeds per unit impulse along each row of
    `jacobian`, M X = Jᵀ, within the velocity constraints A u = b of a constrained
    formulation (their impulsive multipliers solved together: [M Aᵀ; A 0])."""
    mass_matrix = formed_equations(dynamics, t, q, u, p)[0]
    _, velocity_constraints = dynamics.state_constraints(t, q, u, p)
    m, k = u.shape[0], jacobian.shape[0]
    if velocity_constraints.shape[0] == 0:
        return jnp.linalg.solve(mass_matrix, jacobian.T)
    a = jax.jacfwd(lambda u: dynamics.state_constraints(t, q, u, p)[1])(u)
    c = a.shape[0]
    kkt = jnp.block([[mass_matrix, a.T], [a, jnp.zeros((c, c), a.dtype)]])
    rhs = jnp.concatenate([jacobian.T, jnp.zeros((c, k), a.dtype)])
    return jnp.linalg.solve(kkt, rhs)[:m]


def newton_impulses(delassus, free, closed):
    """Λ of the linear complementarity problem

        w = G Λ + c,   Λ ≥ 0,   w ≥ 0,   Λᵀ w = 0   on the closed contacts (Λ = 0 elsewhere),

    with G the Delassus matrix J X and c = (1 + e) φ̇⁻, by enumerating the sets of contacts
    that push: each set S gives Λ_S = −G_SS⁻¹ c_S, and the set whose Λ and w have the least
    violation of their signs is the solution (unique for G positive definite; for redundant
    contacts, one of the impulses that give the unique post-impact speeds). Within that set Λ
    is a smooth function of G and c, so derivatives pass through it."""
    k = free.shape[0]
    sets = jnp.asarray(np.array(list(itertools.product([False, True], repeat=k)), bool))
    scale = jnp.maximum(jnp.max(jnp.abs(jnp.diagonal(delassus))), jnp.finfo(free.dtype).tiny)
    # A regularisation at round-off keeps G_SS invertible for redundant contacts (J of
    # deficient rank); it changes Λ by a few ulps relative.
    regularised = delassus + 16 * jnp.finfo(free.dtype).eps * scale * jnp.eye(k,
                                                                              dtype=free.dtype)

    def candidate(s):
        both = s[:, None] & s[None, :]
        matrix = jnp.where(both, regularised, jnp.eye(k, dtype=free.dtype))
        impulses = jnp.where(s, jnp.linalg.solve(matrix, jnp.where(s, -free, 0.0)), 0.0)
        w = delassus @ impulses + free
        # sign violations as speeds (G Λ is one), relative to the approach speeds
        violation = (jnp.sum(jnp.maximum(-impulses, 0.0)) * scale
                     + jnp.sum(jnp.where(closed & ~s, jnp.maximum(-w, 0.0), 0.0))
                     ) / jnp.maximum(jnp.max(jnp.abs(free)), jnp.finfo(free.dtype).tiny)
        allowed = ~jnp.any(s & ~closed)
        return impulses, jnp.where(allowed, violation, jnp.inf)

    impulses, violation = jax.vmap(candidate)(sets)
    return impulses[jnp.argmin(violation)]
