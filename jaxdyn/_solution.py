"""The result of `simulate`."""

import diffrax
import equinox as eqx
from jaxtyping import Array, Float, Int

from ._linalg import NONFINITE_FORCING, SINGULAR_MASS_MATRIX


class RESULTS(diffrax.RESULTS):
    """diffrax's result codes, and the ways the equations of motion themselves can fail."""

    singular_mass_matrix = SINGULAR_MASS_MATRIX
    nonfinite_forcing = NONFINITE_FORCING
    nonfinite_equations = (
        "The equations of motion became NaN or inf where the mass matrix and the forcing "
        "are finite: the kinematic map q̇ = K(q) u, or an intermediate value of a callback, "
        "is not finite there."
    )


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
    - `dense`: the underlying `diffrax.Solution` when `dense=True` was asked for, else None;
      use `evaluate`.
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

    def evaluate(self, t):
        """(q(t), u(t)) from the solver's dense interpolant (needs `dense=True`)."""
        if self.dense is None:
            raise ValueError("evaluate needs a dense solution: call simulate(..., dense=True).")
        return self.dense.evaluate(t)
