"""The result of `simulate`."""

from typing import Any

import diffrax
import equinox as eqx
from jaxtyping import Array, Float, Int

from ._linalg import NONFINITE_FORCING, SINGULAR_CONSTRAINTS, SINGULAR_MASS_MATRIX


# equinox's enumerations look final to a type checker (an Enum with members), but are made to be
# extended; diffrax's own RESULTS carries the same ignore.
class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """diffrax's result codes, and the ways the equations of motion themselves can fail."""

    singular_mass_matrix = SINGULAR_MASS_MATRIX
    nonfinite_forcing = NONFINITE_FORCING
    singular_constraints = SINGULAR_CONSTRAINTS
    nonfinite_equations = (
        "The equations of motion became NaN or inf where the mass matrix and the forcing "
        "are finite: the kinematic map q̇ = K(q) u, or an intermediate value of a callback, "
        "is not finite there."
    )
    max_events_reached = (
        "The solve met more events than its budget (simulate's max_events) before t1; it "
        "stopped at the event past the budget, whose time and state are the solution's last. "
        "Pass a larger max_events; if the events crowd towards one instant (impacts whose "
        "approach speeds shrink geometrically, a Zeno sequence), the contact is coming to "
        "rest there."
    )
    nonfinite_state_or_parameters = (
        "The initial state or the parameters contain NaN or inf (simulate or simulate_batch "
        "with throw=False): the results are NaN."
    )


def promoted(result) -> RESULTS:
    """A solve's result code (diffrax's `RESULTS`, or already jaxdyn's) as a jaxdyn
    `RESULTS` member.

    An equinox enumeration stores its parent's items first and in their order, so each of
    diffrax's codes keeps its value in jaxdyn's enumeration: promoting one relabels the value.
    (`RESULTS.promote` looks the value up in a table under `jax.ensure_compile_time_eval`,
    which compiles two tiny programs in a process's first solve: 40-90 ms of it.)
    """
    if isinstance(result, RESULTS):
        return result
    member: Any = type(RESULTS.successful)  # equinox's EnumerationItem (an enum to a type checker)
    return member(result._value, RESULTS)


class ConstraintRecord(eqx.Module):
    """Constraint quantities along a trajectory of a `jaxdyn.Constrained` formulation
    (`simulate(..., save=(..., "constraints"))`).

    **Fields:**

    - `multipliers`: λ at the save times, shape (k, m) (holonomic rows, then Pfaffian).
    - `constraint_forces`: Cᵀλ, the generalized constraint forces along the speeds (k, n_u).
    - `position_violation`: φ(t, q), shape (k, m₁).
    - `velocity_violation`: C u − b, shape (k, m).
    """

    multipliers: Float[Array, "k m"]
    constraint_forces: Float[Array, "k nu"]
    position_violation: Float[Array, "k m1"]
    velocity_violation: Float[Array, "k m"]


class Solution(eqx.Module):
    """A simulated trajectory.

    **Fields:**

    - `ts`: the save times, shape (k,).
    - `q`: coordinates at `ts`, shape (k, n).
    - `u`: speeds at `ts`, shape (k, m); for a `Lagrangian` these are q̇.
    - `qd`: coordinate rates q̇ = K u at `ts`, shape (k, n).
      (Each of `q`, `u`, `qd` is None when `simulate(..., save=...)` left it out.)
    - `result`: a `jaxdyn.RESULTS` member (`RESULTS.successful` unless `throw=False` and the
      solve failed).
    - `num_steps`, `num_accepted_steps`, `num_rejected_steps`: solver statistics.
    - `constraints`: a `ConstraintRecord` when `save` included "constraints", else None.
    - `inputs`: the inputs r applied at `ts`, shape (k, number of inputs), when `save`
      included "inputs" (a `jaxdyn.Controlled` system), else None.
    - `contact`: a `jaxdyn.ContactRecord` (forces, gaps, slip at `ts`) when `save` included
      "contact" (a `jaxdyn.Contact` scene), else None.
    - `dense`: the underlying `diffrax.Solution` when `dense=True` was asked for, else None;
      use `evaluate`.
    - `events`: a `jaxdyn.EventRecord` of the events met when `simulate` was given events
      (times, guards, states before and after, impulses), else None.
    """

    ts: Float[Array, " k"]
    q: Float[Array, "k n"] | None
    u: Float[Array, "k m"] | None
    qd: Float[Array, "k n"] | None
    result: RESULTS
    num_steps: Int[Array, ""]
    num_accepted_steps: Int[Array, ""]
    num_rejected_steps: Int[Array, ""]
    dense: diffrax.Solution | None = None
    constraints: ConstraintRecord | None = None
    inputs: Float[Array, "k r"] | None = None
    contact: Any = None  # a `ContactRecord` when save included "contact"
    layout: Any = None  # how `dense` holds (q, u): `layout.split(y)` gives them
    events: Any = None  # an `EventRecord` when simulate was given events

    def evaluate(self, t):
        """(q(t), u(t)) from the solver's dense interpolant (needs `dense=True`)."""
        if self.dense is None:
            raise ValueError("evaluate needs a dense solution: call simulate(..., dense=True).")
        return self.layout.split(self.dense.evaluate(t))
