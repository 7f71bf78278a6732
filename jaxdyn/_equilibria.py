"""Equilibria: states at rest, u = 0 and u̇ = 0, found by optimistix."""

import functools

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ._compile import filter_jit
from ._dynamics import AbstractDynamics, equations_of_motion
from ._errors import error_if, reports_state
from ._linalg import PIVOTED_LU_MAX, PivotedLU
from ._form.controlled import find_controlled
from ._state import check_vector, numbers_as_arrays, transferred

_NOT_FOUND = ("No equilibrium found: the solver stopped with the residual |u̇| (and |φ| for "
              "constraints) above the tolerance. Try another initial guess q, or check that "
              "an equilibrium exists (the inputs may not be able to hold the prescribed "
              "coordinates).")


class Equilibrium(eqx.Module):
    """An equilibrium found by `equilibrium`.

    **Fields:** `q` (n,): the coordinates at rest; `r` (k,): the inputs that hold them (given,
    or solved for with `prescribed`; shape (0,) without inputs); `residual`: max |u̇| (and
    |φ|) there; `num_steps`: the solver's iterations.
    """

    q: Float[Array, " n"]
    r: Float[Array, " k"]
    residual: Float[Array, ""]
    num_steps: Array


@reports_state
def equilibrium(dynamics: AbstractDynamics, q, p=None, r=None, *, t=0.0, prescribed=None,
                num_speeds: int | None = None, rtol: float | None = None,
                atol: float | None = None, max_steps: int = 256) -> Equilibrium:
    """An equilibrium of `dynamics` near the guess `q`: coordinates where the system stays at
    rest, u = 0 and

        u̇(t, q, 0, r) = 0    (M u̇ = f + B r: the forces balance, f(q, 0) + B r = 0),

    with the holonomic constraints φ(q) = 0 for a constrained system.

    - `r`: the inputs of a `jaxdyn.Controlled` system (default: its own, r = 0 unless set).
    - `prescribed`: {coordinate index: value} held fixed; the inputs are then unknowns too
      (the inputs that hold the system there, e.g. the torque that holds a pendulum at 30°),
      with `r` as their initial guess.
    - `num_speeds`: the number of speeds u (default: one per coordinate, u = q̇; give it
      for speeds of another number, e.g. quaternion coordinates or independent speeds).

    Square systems (as many equations as unknowns) are solved by optimistix's Newton root
    finder (its linear systems, up to 16 unknowns, by Gaussian elimination with partial
    pivoting), others (constraints, more inputs than prescribed coordinates) by
    Levenberg–Marquardt in the least-squares sense (the minimum-norm correction at each
    step). Tolerances default to √ε (about 1e-8 in float64). When no equilibrium is found,
    the error names the last iterate.
    """
    q = check_vector(q, "q")
    t, p = numbers_as_arrays((t, p), q.dtype)
    t = jnp.asarray(t, q.dtype)
    n = q.shape[0]
    if find_controlled(dynamics) is None and (r is not None or prescribed):
        raise ValueError(f"{type(dynamics).__name__} declares no inputs: r and "
                         "prescribed coordinates need jaxdyn.Controlled(dynamics, "
                         "input_map).")
    prescribed = dict(prescribed or {})
    fixed = np.array(sorted(int(i) for i in prescribed), dtype=np.int32)
    if np.any((fixed < 0) | (fixed >= n)):
        raise ValueError(f"prescribed names coordinates {fixed.tolist()}, but there are {n}.")
    values = [prescribed[int(i)] for i in fixed]
    values = (jnp.asarray(values, q.dtype) if any(isinstance(v, jax.core.Tracer) for v in values)
              else transferred(values, q.dtype))
    r = None if r is None else jnp.atleast_1d(jnp.asarray(r, q.dtype))
    eps = float(jnp.finfo(q.dtype).eps)
    rtol = float(np.sqrt(eps)) if rtol is None else rtol
    atol = float(np.sqrt(eps)) if atol is None else atol
    # One compiled program per system and shapes: a new guess, parameter or input reuses it.
    q_out, r_out, size, steps = _equilibrium(
        dynamics, t, q, p, r, values,
        (tuple(fixed.tolist()), num_speeds, float(rtol), float(atol), int(max_steps)))
    return Equilibrium(q=q_out, r=r_out, residual=size, num_steps=steps)


@functools.partial(filter_jit, checks_on_host=True)
def _equilibrium(dynamics, t, q, p, r, values, options):
    fixed, num_speeds, rtol, atol, max_steps = options
    n = q.shape[0]
    controlled = find_controlled(dynamics)
    zeros_u = jnp.zeros((n if num_speeds is None else num_speeds,), q.dtype)
    if controlled is None:
        r = jnp.zeros((0,), q.dtype)
    elif r is None:
        r = jnp.atleast_1d(controlled.input_values(t, q, zeros_u, p))
    fixed = np.array(fixed, dtype=np.int32)
    free = np.setdiff1d(np.arange(n), fixed).astype(np.int32)
    solve_inputs = fixed.size > 0

    def state(z):
        q_full = q.at[free].set(z[:free.size]).at[fixed].set(values)
        return q_full, (z[free.size:] if solve_inputs else r)

    def residual(z, _):
        q_full, inputs = state(z)
        driven = dynamics if controlled is None else dynamics.with_inputs(inputs)
        _, accelerations, _, _ = equations_of_motion(driven, t, q_full, zeros_u, p)
        phi = dynamics.state_constraints(t, q_full, zeros_u, p)[0]
        return jnp.concatenate([accelerations, phi])

    z0 = jnp.concatenate([q[free], r if solve_inputs else r[:0]])
    # (M u̇ = f has a row per speed; the constraints' rows are counted without tracing the
    # equations of motion once more)
    equations = zeros_u.shape[0] + jax.eval_shape(
        lambda z: dynamics.state_constraints(t, state(z)[0], zeros_u, p)[0], z0).shape[0]
    if equations == z0.shape[0]:
        # Newton's linear systems of a small model solved in the program's own operations
        # (`PivotedLU`): LAPACK's LU would load SciPy's LAPACK at the first call, ~0.3 s.
        solver = (optx.Newton(rtol=rtol, atol=atol, linear_solver=PivotedLU())
                  if z0.shape[0] <= PIVOTED_LU_MAX else optx.Newton(rtol=rtol, atol=atol))
        solution = optx.root_find(residual, solver, z0, max_steps=max_steps, throw=False)
    else:
        solution = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=rtol, atol=atol),
                                      z0, max_steps=max_steps, throw=False)
    q_out, r_out = state(solution.value)
    size = jnp.max(jnp.abs(residual(solution.value, None)), initial=0.0)
    scale = 1 + jnp.max(jnp.abs(q_out))
    failed = ~(size <= 100 * atol * scale) | ~jnp.all(jnp.isfinite(q_out))
    # (both tied to the check: inside a caller's `jax.jit`, r read alone keeps it)
    q_out, r_out = error_if((q_out, r_out), [(failed, _NOT_FOUND)],
                            {"the last iterate q": q_out, "r": r_out, "residual": size})
    return q_out, r_out, size, solution.stats["num_steps"]
