"""`simulate`: the single jit-compiled entry point that integrates any dynamics with diffrax."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._dynamics import AbstractDynamics, solve_equations
from ._errors import check_static_indexing, nonfinite_tree_check, reports_state
from ._solution import RESULTS, Solution
from ._state import check_vector

MAX_STEPS = (
    "The solver took the maximum number of steps (max_steps) before reaching t1. Increase "
    "`max_steps`, loosen `rtol`/`atol`, shorten the interval, or check the system: very fast "
    "or stiff motion (a huge stiffness, a near-singular mass matrix) forces tiny steps."
)


def _vector_field(t, y, args):
    dynamics, p = args
    q, u = y
    return dynamics.coordinate_rates(t, q, u, p), solve_equations(dynamics, t, q, u, p)


@reports_state
def simulate(
    dynamics: AbstractDynamics,
    q0,
    u0,
    p=None,
    *,
    t0=0.0,
    t1,
    ts=None,
    dense: bool = False,
    solver: diffrax.AbstractSolver = diffrax.Dopri8(),
    rtol: float | None = None,
    atol: float | None = None,
    dt0=None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    max_steps: int = 16**4,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    throw: bool = True,
) -> Solution:
    """Integrate q̇ = K u, M u̇ = f from (t0, q0, u0) to t1.

    **Arguments:**

    - `dynamics`: any `jaxdyn.AbstractDynamics` (`Lagrangian`, and later formulations).
    - `q0`, `u0`: initial coordinates (n,) and speeds (m,) (for a `Lagrangian`, u0 = q̇0).
    - `p`: parameters, any pytree; differentiate the result with respect to it freely.
    - `t0`, `t1`: the interval; `t1 < t0` integrates backwards.
    - `ts`: times to save at; if None only t1 is saved.
    - `dense`: keep the dense interpolant (`Solution.evaluate`).
    - `solver`, `rtol`, `atol`, `dt0`, `stepsize_controller`: the diffrax solver and step-size
      control. Defaults: `Dopri8` (8th order) with a `PIDController` at rtol = atol = 1e-10 in
      float64 (1e-6 in float32, near what that precision can hold) and an automatically chosen
      first step. Mechanics is smooth, so a high order pays: on a chaotic double pendulum over
      10 s Dopri8 at 1e-10 is 20 times more accurate than Tsit5 at 1e-10 for 1.25 times the
      run time (benchmarks/bench_work_precision.py). Pass `solver=diffrax.Tsit5()` and looser
      tolerances for speed, or a fixed `dt0` with `stepsize_controller=
      diffrax.ConstantStepSize()` for fixed-step integration.
    - `max_steps`: step budget; exhausting it is an error (or `RESULTS.max_steps_reached` with
      `throw=False`).
    - `adjoint`: how to differentiate; the default `RecursiveCheckpointAdjoint` differentiates
      the discrete solve exactly, which is what matches finite differences.
    - `throw`: raise on solver failure; if False, inspect `Solution.result`.

    **Returns:** a `jaxdyn.Solution`.

    Initial state and parameters are checked for NaN/inf; a singular mass matrix met during
    the solve stops it with an error naming the time and state.
    """
    # Python floats in p become arrays: traced, not baked into the compiled solve (and so no
    # recompilation when a parameter value changes).
    p = jax.tree_util.tree_map(lambda x: jnp.asarray(x) if isinstance(x, float) else x, p)
    return _simulate(dynamics, q0, u0, p, t0=t0, t1=t1, ts=ts, dense=dense, solver=solver,
                     rtol=rtol, atol=atol, dt0=dt0, stepsize_controller=stepsize_controller,
                     max_steps=max_steps, adjoint=adjoint, throw=throw)


@eqx.filter_jit
def _simulate(dynamics, q0, u0, p, *, t0, t1, ts, dense, solver, rtol, atol, dt0,
              stepsize_controller, max_steps, adjoint, throw):
    q0 = check_vector(q0, "q0")
    u0 = check_vector(u0, "u0")
    if q0.dtype != u0.dtype:
        raise ValueError(
            f"q0 and u0 must share a dtype, got {q0.dtype} and {u0.dtype}. Use float64 "
            "(jax.config.update('jax_enable_x64', True)) for accurate mechanics."
        )
    if not isinstance(dynamics, AbstractDynamics):
        raise ValueError(
            f"dynamics must be a jaxdyn.AbstractDynamics (e.g. jaxdyn.Lagrangian), got "
            f"{type(dynamics).__name__}."
        )
    dtype = q0.dtype
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    _check_shapes(dynamics, t0, q0, u0, p)
    q0 = nonfinite_tree_check(q0, "q0")
    u0 = nonfinite_tree_check(u0, "u0")
    p = nonfinite_tree_check(p, "p")

    if ts is None:
        saveat = diffrax.SaveAt(t1=True, dense=dense)
    else:
        ts = jnp.asarray(ts, dtype)
        if ts.ndim != 1:
            raise ValueError(f"ts must be a 1-D array of save times, got shape {ts.shape}.")
        saveat = diffrax.SaveAt(ts=ts, dense=dense)
    if stepsize_controller is None:
        default = 1e-10 if jnp.finfo(dtype).bits == 64 else 1e-6
        stepsize_controller = diffrax.PIDController(
            rtol=default if rtol is None else rtol, atol=default if atol is None else atol
        )
    elif rtol is not None or atol is not None:
        raise ValueError("Pass rtol/atol or a stepsize_controller, not both.")
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        solver,
        t0,
        t1,
        dt0,
        (q0, u0),
        args=(dynamics, p),
        saveat=saveat,
        stepsize_controller=stepsize_controller,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=False,  # raised below, with jaxdyn's own messages
    )
    q, u = solution.ys
    if throw:
        q = eqx.error_if(q, solution.result == RESULTS.max_steps_reached, MAX_STEPS)
        q = solution.result.error_if(q, solution.result != RESULTS.successful)
    qd = jax.vmap(dynamics.coordinate_rates, in_axes=(0, 0, 0, None))(solution.ts, q, u, p)
    return Solution(
        ts=solution.ts,
        q=q,
        u=u,
        qd=qd,
        result=solution.result,
        num_steps=solution.stats["num_steps"],
        num_accepted_steps=solution.stats["num_accepted_steps"],
        num_rejected_steps=solution.stats["num_rejected_steps"],
        dense=solution if dense else None,
    )


def _check_shapes(dynamics, t0, q0, u0, p):
    """Trace the dynamics once on the initial state, so that shape errors in user callbacks
    are reported before the solve with the shapes involved."""
    check_static_indexing(dynamics.user_functions, t0, q0, u0, p)
    rates, accelerations = eqx.filter_eval_shape(_vector_field, t0, (q0, u0), (dynamics, p))
    if rates.shape != q0.shape:
        raise ValueError(
            f"coordinate_rates returned shape {rates.shape} for q0 of shape {q0.shape}."
        )
    if accelerations.shape != u0.shape:
        raise ValueError(
            f"The dynamics expects {accelerations.shape[0]} speeds but u0 has shape "
            f"{u0.shape}."
        )
