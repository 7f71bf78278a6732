"""The result of `simulate`."""

import diffrax
import equinox as eqx
from jaxtyping import Array, Float, Int

RESULTS = diffrax.RESULTS


class Solution(eqx.Module):
    """A simulated trajectory.

    **Fields:**

    - `ts`: the save times, shape (k,).
    - `q`: coordinates at `ts`, shape (k, n).
    - `u`: speeds at `ts`, shape (k, m); for a `Lagrangian` these are q̇.
    - `qd`: coordinate rates q̇ = K u at `ts`, shape (k, n).
    - `result`: a `jaxdyn.RESULTS` member (`RESULTS.successful` unless `throw=False` and the
      solve failed).
    - `num_steps`, `num_accepted_steps`, `num_rejected_steps`: solver statistics.
    - `dense`: the underlying `diffrax.Solution` when `dense=True` was asked for, else None;
      use `evaluate`.
    """

    ts: Float[Array, " k"]
    q: Float[Array, "k n"]
    u: Float[Array, "k m"]
    qd: Float[Array, "k n"]
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
