"""Unilateral contacts and Newton's impact law, through any formulation's mass matrix."""

import itertools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._convention import CONFIGURATION_ARGS, call
from .._dynamics import equations_of_motion
from .._events import AbstractEvent, as_guards, constraint_response
from .._linalg import small_solve

#: The most contacts that may close at one instant: the impact law's complementarity problem
#: is solved by enumerating the 2^k sets of contacts that push (exact, and differentiable
#: within the set that holds).
MAX_SIMULTANEOUS = 10


class AbstractContactEvent(AbstractEvent):
    """Unilateral contacts as events: gaps that fire as they close, and never stop the motion."""

    @property
    def direction(self) -> str:
        return "falling"

    @property
    def terminal(self) -> bool:
        return False


def comes_to_rest(closed, separation, normal_acceleration, rest_within):
    """The closed contacts whose next flight, 2 φ̇⁺/|φ̈| under the free motion, would last at
    most `rest_within`: a Zeno sequence of impacts ends there in resting contact."""
    flight = 2 * jnp.maximum(separation, 0.0) / jnp.maximum(
        -normal_acceleration, jnp.finfo(separation.dtype).tiny)
    return closed & (normal_acceleration < 0) & (flight <= rest_within)


class UnilateralContact(AbstractContactEvent):
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
    contacts); a closed contact that is not approaching takes e = 0 ($\dot φ^+ \ge 0$).

    **Arguments:**

    - `gap`: φ(q, p) → a scalar or a vector of k gaps, positive while open (φ(t, q, p) with
      `time_dependent=True`, e.g. a moving wall).
    - `restitution`: the coefficient of restitution e ∈ [0, 1], a number, an array (k,), or
      a function e(p) of the parameters (so that it can be fitted or differentiated).
    - `closed_within`: gaps at most this are closed at an impact (simultaneous contacts).
    - `rest_within`: a contact whose next flight would last less than this (in time units)
      comes to rest: a Zeno sequence of impacts, whose flights shrink geometrically, ends in
      resting contact. The contact is then held closed by its normal force λ ≥ 0 (recorded
      in place of the guard), and released by another event when λ falls through zero.

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
    rest_within: float = eqx.field(default=1e-5, static=True)
    time_dependent: bool = eqx.field(default=False, static=True)

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

    def contact_rows(self, dynamics, t, q, u, p):
        """(J, b) with φ̈ = J u̇ + b: a resting contact is held by φ̈ = 0."""
        def rates(t, q, u):
            return self.normal_speeds(dynamics, t, q, u, p)[0]

        q_dot = dynamics.coordinate_rates(t, q, u, p)
        dt = jnp.ones_like(t) if self.time_dependent else jnp.zeros_like(t)
        bias = jax.jvp(rates, (t, q, u), (dt, q_dot, jnp.zeros_like(u)))[1]
        return self.normal_speeds(dynamics, t, q, u, p)[1], bias

    def jump(self, dynamics, t, q, u, p, fired, resting):
        """Newton's law on the contacts closed at the instant; a fired contact that was
        resting is released instead (its normal force fell through zero). Contacts whose
        next flight would last less than `rest_within` come to rest: their impact is
        perfectly plastic (e = 0) and they are held closed from then on, so that a Zeno
        sequence of impacts (a ball bouncing with e < 1, whose impacts accumulate at a finite
        time) ends in resting contact after finitely many events."""
        k = fired.shape[0]
        if k > MAX_SIMULTANEOUS:
            raise ValueError(
                f"A UnilateralContact of {k} gaps: the impact law enumerates the sets of "
                f"contacts that push, up to {MAX_SIMULTANEOUS} gaps per contact. Split the "
                "gaps into several UnilateralContacts (contacts that cannot close at the "
                "same instant), or use a compliant contact.")
        closed = fired | resting | (self.gaps(t, q, p) <= self.closed_within)
        speed, jacobian = self.normal_speeds(dynamics, t, q, u, p)
        restitution = self.coefficients(p, k, speed.dtype)
        response = constraint_response(dynamics, t, q, u, p, jacobian)
        delassus = jacobian @ response
        # Newton's law on the approaching contacts; contacts closed but separating or at
        # rest only may not penetrate (e = 0: φ̇⁺ ≥ 0), as Glocker's law applied to them
        # would let them move into the obstacle at −e φ̇⁻.
        approaching = speed < 0
        bounced = u + response @ newton_impulses(
            delassus, jnp.where(approaching, 1 + restitution, 1.0) * speed, closed)
        _, accelerations, _, _ = equations_of_motion(dynamics, t, q, bounced, p)
        rows, bias = self.contact_rows(dynamics, t, q, bounced, p)
        normal_acceleration = rows @ accelerations + bias
        separation = jacobian @ (bounced - u) + speed
        rest = comes_to_rest(closed, separation, normal_acceleration, self.rest_within)
        impulses = newton_impulses(
            delassus, jnp.where(approaching & ~rest, 1 + restitution, 1.0) * speed, closed)
        impact = jnp.any(fired & ~resting)
        u_plus = jnp.where(impact, u + response @ impulses, u)
        impulses = jnp.where(impact, impulses, 0.0)
        return q, u_plus, impulses, jnp.where(impact, rest, resting & ~fired)


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
        impulses = jnp.where(s, small_solve(matrix, jnp.where(s, -free, 0.0)), 0.0)
        w = delassus @ impulses + free
        # sign violations as speeds (G Λ is one), relative to the approach speeds
        violation = (jnp.sum(jnp.maximum(-impulses, 0.0)) * scale
                     + jnp.sum(jnp.where(closed & ~s, jnp.maximum(-w, 0.0), 0.0))
                     ) / jnp.maximum(jnp.max(jnp.abs(free)), jnp.finfo(free.dtype).tiny)
        allowed = ~jnp.any(s & ~closed)
        return impulses, jnp.where(allowed, violation, jnp.inf)

    impulses, violation = jax.vmap(candidate)(sets)
    return impulses[jnp.argmin(violation)]
