"""Recognising stiffness: the eigenvalues of the linearised equations of motion, and the
solver they call for."""

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._dynamics import AbstractDynamics
from ._linearisation import state_jacobians
from ._state import check_vector, numbers_as_arrays, state_dtype

# Eigenvalues below this fraction of the largest are taken as zero (rigid-body and cyclic
# modes, whose rate is zero: they do not make a system stiff).
_ZERO_MODE = 1e-9


class Stiffness(eqx.Module):
    """The local time scales of a system at one state (`jaxdyn.stiffness`).

    **Fields:**

    - `eigenvalues`: λ of the Jacobian J = ∂(q̇, u̇)/∂(q, u) (complex, n + m of them).
    - `fastest`, `slowest`: the largest and smallest nonzero |λ| (rates in 1/s; 1/|λ| is a
      time scale).
    - `ratio`: the stiffness ratio `fastest / slowest`.
    - `stiff`: whether `ratio` ≥ `threshold` (by default 10³): an explicit solver's step is
      then bounded by stability at 1/fastest rather than by the accuracy the slow motion needs.
    """

    eigenvalues: np.ndarray
    fastest: float
    slowest: float
    ratio: float
    stiff: bool
    damped: bool

    @property
    def solver(self) -> diffrax.AbstractSolver:
        """The recommended solver: `diffrax.Kvaerno5()` (L-stable, implicit) when stiff, else
        jaxdyn's default `diffrax.Dopri8()`."""
        return diffrax.Kvaerno5() if self.stiff else diffrax.Dopri8()

    @property
    def recommendation(self) -> str:
        """The advice, in words."""
        if not self.stiff:
            return (f"Not stiff (ratio {self.ratio:.3g}): an explicit solver (the default "
                    "Dopri8, or Tsit5 at loose tolerances) is the efficient choice.")
        advice = (f"Stiff (ratio {self.ratio:.3g}; fastest time scale {1 / self.fastest:.3g} "
                  f"s, slowest {1 / self.slowest:.3g} s): an explicit solver needs steps of "
                  "about the fastest time scale however smooth the motion. Use an implicit "
                  "solver, simulate(..., solver=diffrax.Kvaerno5()), whose step follows the "
                  "accuracy of the slow motion.")
        if not self.damped:
            advice += (" The fast modes are undamped oscillations: an L-stable implicit solver "
                       "damps them out (right when they are a nuisance, such as a stiff spring "
                       "standing in for a rigid link; then also consider a constraint "
                       "instead), while resolving them needs steps shorter than the fastest "
                       "time scale (e.g. VariationalIntegrator with such a dt0, which keeps "
                       "their energy).")
        return advice

    def __str__(self):
        return self.recommendation


def stiffness(dynamics: AbstractDynamics, t, q, u, p=None, *,
              threshold: float = 1e3) -> Stiffness:
    """The stiffness of `dynamics` at the state (t, q, u), from the eigenvalues λ of the
    linearised equations of motion, d/dt (δq, δu) = J (δq, δu) with

        J = [[∂q̇/∂q, ∂q̇/∂u], [∂u̇/∂q, ∂u̇/∂u]].

    A stiff spring of stiffness k on a mass m gives λ = ±i √(k/m); with damping c, real λ
    near −c/m and −k/c. The stiffness ratio is max |λ| / min |λ| over the nonzero λ.
    Stiffness is local: evaluate it at a few states of the motion (it is cheap). J is formed
    by forward-mode differentiation and its eigenvalues are computed with NumPy.

    **Returns:** a `jaxdyn.Stiffness`, with `.recommendation` (advice in words) and `.solver`
    (the recommended diffrax solver).

    **Example:**

        report = jaxdyn.stiffness(system, 0.0, q0, u0, p)
        sol = jaxdyn.simulate(system, q0, u0, p, t1=10.0, solver=report.solver)
    """
    if not isinstance(dynamics, AbstractDynamics):
        raise ValueError(f"dynamics must be a jaxdyn.AbstractDynamics, got "
                         f"{type(dynamics).__name__}.")
    dtype = state_dtype(q, u)
    q, u = check_vector(q, "q"), check_vector(u, "u")
    t, p = numbers_as_arrays((t, p), dtype)
    jacobian = np.asarray(state_jacobians(dynamics, jnp.asarray(t, dtype), q, u, p,
                                          jnp.zeros((0,), dtype))[0])
    if not np.all(np.isfinite(jacobian)):
        raise ValueError("The linearised equations of motion are not finite at this state (a "
                         "singular mass matrix, or a non-finite force): no stiffness to "
                         "report. Check the state with dynamics.accelerations(t, q, u, p).")
    eigenvalues = np.linalg.eigvals(jacobian)
    magnitudes = np.abs(eigenvalues)
    fastest = float(magnitudes.max())
    nonzero = magnitudes[magnitudes > _ZERO_MODE * max(fastest, np.finfo(dtype).tiny)]
    slowest = float(nonzero.min()) if nonzero.size else 0.0
    ratio = fastest / slowest if slowest > 0 else 1.0
    fast = magnitudes >= fastest / 10
    # Damped fast modes: their real parts are a sizeable fraction of their magnitude.
    damped = bool(np.all(-eigenvalues[fast].real > 0.1 * magnitudes[fast]))
    return Stiffness(eigenvalues=eigenvalues, fastest=fastest, slowest=slowest, ratio=ratio,
                     stiff=bool(ratio >= threshold), damped=damped)
