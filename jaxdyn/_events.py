"""Discontinuities of the motion: what `simulate` sees of events, and events given by the user.

A hybrid system flows by its equations of motion until a guard g(t, q, u, p) crosses zero;
then its state jumps, (q⁻, u⁻) → (q⁺, u⁺), or the motion stops, and the flow restarts from the
new state. `simulate` locates the crossings and restarts the solve; it knows only this
protocol: the guards, their direction of crossing, and the jump. A user's own guard and reset
(`Event`) and the impacts of unilateral contacts (`jaxdyn.UnilateralContact`, whose jump is an
impact law) implement it.

Reference: R. Goebel, R. G. Sanfelice, A. R. Teel, Hybrid Dynamical Systems (2012); for the
derivative of a located event, the saltation matrix: M. A. Aizerman, F. R. Gantmacher, "On the
stability of periodic motions", J. Appl. Math. Mech. 22 (1958).
"""

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from ._convention import call, vector
from ._dynamics import formed_mass_matrix
from ._linalg import small_solve

#: The directions of a crossing that trigger an event: from positive to negative (a gap
#: closing), from negative to positive, or both.
DIRECTIONS = {"falling": False, "rising": True, "either": None}


class AbstractEvent(eqx.Module):
    """Guards whose zero crossings interrupt the motion, and what happens then.

    Subclasses give `guards` (k values, each one event), `direction` (which crossings count)
    and `jump`; `terminal` events stop the motion instead of jumping. A guard may also come
    to rest (a contact that stays closed): its `contact_rows` then hold it at zero as a
    constraint J u̇ + b = 0 with a multiplier λ ≥ 0, which takes the guard's place, so that
    the contact is released when λ falls through zero. Events whose resting guards hold
    other rows, or are held by other forces (Coulomb friction: `jaxdyn.RigidContact`),
    give `held_rows`, `held_values`, `held_forces` and `reference` instead.
    """

    direction: eqx.AbstractVar[str]
    terminal: eqx.AbstractVar[bool]

    @abc.abstractmethod
    def guards(self, dynamics, t, q, u, p) -> jax.Array:
        """The guard values g(t, q, u, p), shape (k,): an event where one crosses zero."""

    @abc.abstractmethod
    def jump(self, dynamics, t, q, u, p, fired, resting):
        """(q⁺, u⁺, impulses (k,), resting⁺ (k,)) from the state (q, u) at which the guards
        `fired` (k booleans) crossed zero, those `resting` being held as constraints."""

    @abc.abstractmethod
    def contact_rows(self, dynamics, t, q, u, p):
        """None, or (J (k, m), b (k,)) such that a guard at rest is held by J u̇ + b = 0."""

    def held_rows(self, dynamics, t, q, u, p, resting, reference):
        """None, or the rows (E (r, m), W (r, m), b (r,), active (r,)) held while the guards
        `resting` rest: E u̇ + b = 0 on the `active` rows, by the generalized forces Wᵀ λ.
        By default one row per guard, E = W = J of `contact_rows` (an ideal constraint);
        Coulomb friction in sliding makes W differ from E (the friction force follows the
        normal force). `reference` is what the event remembers of its segment's start."""
        rows = self.contact_rows(dynamics, t, q, u, p)
        if rows is None:
            return None
        return rows[0], rows[0], rows[1], resting

    def held_values(self, dynamics, t, q, u, p, forces, resting, reference):
        """The guards with the multipliers λ in place of those held at rest (a contact is
        released when its normal force falls through zero)."""
        return jnp.where(resting, forces, self.guards(dynamics, t, q, u, p))

    def held_forces(self, forces, resting, p):
        """The force each guard carries at rest (k,), from the multipliers of `held_rows`."""
        return forces

    def reference(self, dynamics, t, q, u, p, resting):
        """What the event remembers of a segment's start (None by default): a sliding
        contact's direction of slip."""
        return None


class Event(AbstractEvent):
    r"""An event given by its guard and its reset map.

    When the guard $g(t, q, u, p)$ crosses zero in `direction`, the state jumps by the reset
    $(q^+, u^+) = \Delta(t, q^-, u^-, p)$ (a walker's stance-leg swap, a switch of mode), or,
    with no reset, the motion stops there (`simulate` then saves NaN after that time).

    **Arguments:**

    - `guard`: g(q, u, p) → a scalar or a vector of k guards (each an event of its own);
      g(t, q, u, p) with `time_dependent=True`.
    - `reset`: Δ(q, u, p) → (q⁺, u⁺), or Δ(t, q, u, p) with `time_dependent=True`; None stops
      the motion at the event.
    - `direction`: "falling" (g from positive to negative, the default), "rising", or
      "either". Of all the guards of all the events, the first to cross fires, even where
      several cross within one step of the solver; its time is located to the last float.
    - `time_dependent`: the callbacks take t first.

    **Example:**

        # stop when the pendulum first passes the vertical, moving to the left
        stop = jaxdyn.Event(lambda q, u, p: q[0], direction="falling")
        sol = jaxdyn.simulate(pendulum, q0, u0, p, t1=10.0, events=[stop])
        sol.events.t[0]   # the time of the crossing
    """

    guard: Callable
    reset: Callable | None = None
    direction: str = eqx.field(default="falling", static=True)
    time_dependent: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        check_direction(self.direction)

    @property
    def terminal(self) -> bool:
        return self.reset is None

    def guards(self, dynamics, t, q, u, p):
        value = call(self.guard, "guard g", self.time_dependent, ("q", "u", "p"), t, q, u, p)
        return as_guards(value, "guard g")

    def contact_rows(self, dynamics, t, q, u, p):
        return None

    def jump(self, dynamics, t, q, u, p, fired, resting):
        k = fired.shape[0]
        if self.reset is None:
            return q, u, jnp.zeros((k,), q.dtype), resting
        value = call(self.reset, "reset Δ", self.time_dependent, ("q", "u", "p"), t, q, u, p)
        if not (isinstance(value, tuple | list) and len(value) == 2):
            raise ValueError("The reset Δ must return a pair (q⁺, u⁺), got "
                             f"{type(value).__name__}.")
        q_plus = vector(value[0], "reset Δ's q⁺", q.shape)
        u_plus = vector(value[1], "reset Δ's u⁺", u.shape)
        return (q_plus.astype(q.dtype), u_plus.astype(u.dtype), jnp.zeros((k,), q.dtype),
                resting)


def constraint_response(dynamics, t, q, u, p, jacobian):
    """X, shape (m, k): the change of the speeds per unit impulse (or of the accelerations
    per unit force) along each row of `jacobian`, M X = Jᵀ, within the velocity constraints
    A u = b of a constrained formulation (their multipliers solved with it: [M Aᵀ; A 0]),
    with M the formulation's own mass matrix in its own speeds."""
    mass_matrix = formed_mass_matrix(dynamics, t, q, u, p)
    _, velocity_constraints = dynamics.state_constraints(t, q, u, p)
    m, k = u.shape[0], jacobian.shape[0]
    if velocity_constraints.shape[0] == 0:
        return small_solve(mass_matrix, jacobian.T)
    a = jax.jacfwd(lambda u: dynamics.state_constraints(t, q, u, p)[1])(u)
    c = a.shape[0]
    kkt = jnp.block([[mass_matrix, a.T], [a, jnp.zeros((c, c), a.dtype)]])
    rhs = jnp.concatenate([jacobian.T, jnp.zeros((c, k), a.dtype)])
    return small_solve(kkt, rhs)[:m]


def hold(dynamics, t, q, u, p, free, rows):
    """(u̇, λ): the accelerations `free` corrected by the forces Wᵀ λ that hold the active
    rows E u̇ + b = 0 of `rows` = (E, W, b, active) (λ = 0 on the others),

        (E X) λ = −(E u̇_free + b),   u̇ = u̇_free + X λ,   M X = Wᵀ,

    with X from `constraint_response` (within a constrained formulation's own constraints).
    E X is the Delassus matrix (not symmetric where W ≠ E); a regularisation at round-off keeps
    it invertible for redundant contacts (a box flat on four corners), whose λ is then the
    one of least norm and u̇ unique."""
    rows_e, rows_w, bias, active = rows
    response = constraint_response(dynamics, t, q, u, p, rows_w)
    delassus = rows_e @ response
    r = active.shape[0]
    scale = jnp.maximum(jnp.max(jnp.abs(jnp.diagonal(delassus))), jnp.finfo(u.dtype).tiny)
    eye = jnp.eye(r, dtype=u.dtype)
    both = active[:, None] & active[None, :]
    delassus = jnp.where(both, delassus + 16 * jnp.finfo(u.dtype).eps * scale * eye, eye)
    forces = jnp.where(active, small_solve(
        delassus, jnp.where(active, -(rows_e @ free + bias), 0.0)), 0.0)
    return free + response @ forces, forces


def check_direction(direction):
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {', '.join(map(repr, DIRECTIONS))}, got "
                         f"{direction!r}.")


def as_guards(value, name: str) -> jax.Array:
    """A guard function's value as a vector of guards (a scalar is one guard)."""
    value = jnp.asarray(value)
    if value.ndim > 1:
        raise ValueError(f"The {name} must return a scalar or a vector, got shape "
                         f"{value.shape}.")
    if not jnp.issubdtype(value.dtype, jnp.floating):
        raise ValueError(f"The {name} must return real values (a zero crossing is located), "
                         f"got dtype {value.dtype}.")
    return jnp.atleast_1d(value)
