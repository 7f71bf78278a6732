"""Model-predictive control: the shooting problem solved again at every control interval from
the measured state, its first input applied to the plant, warm-started from the previous
solution shifted by one node (the receding horizon; Mayne et al., "Constrained model
predictive control: stability and optimality", Automatica 36, 2000)."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._dynamics import AbstractDynamics
from .._integrate import simulate
from .._state import check_vector, numbers_as_arrays
from .optimum import OptimalTrajectory, _report, _solve
from .problem import ShootingProblem
from .solver import ILQR, AbstractTrajectorySolver


class ClosedLoop(eqx.Module):
    """The result of `jaxdyn.model_predictive_control`.

    **Fields:**

    - `ts` (S+1,): the control instants t_j = t0 + j Δt.
    - `q` (S+1, n), `u` (S+1, m): the plant's state at t_j.
    - `inputs` (S, k): the input applied over [t_j, t_{j+1}).
    - `predicted_cost` (S,): the optimal cost of each solve.
    - `iterations` (S,), `status` (S,): each solve's iterations and status (as
      `jaxdyn.OptimalTrajectory`; a solve stopped at its limit is normal in real-time MPC).
    - `last`: the last solve's `jaxdyn.OptimalTrajectory` (the plan from the final state).
    """

    ts: jax.Array
    q: jax.Array
    u: jax.Array
    inputs: jax.Array
    predicted_cost: jax.Array
    iterations: jax.Array
    status: jax.Array
    last: OptimalTrajectory


def model_predictive_control(problem: ShootingProblem, q0, u0, p=None, *, num_steps: int,
                             plant: AbstractDynamics | None = None, plant_parameters=None,
                             solver: AbstractTrajectorySolver = ILQR(max_iterations=10),
                             first_solver: AbstractTrajectorySolver | None = ILQR(),
                             inputs=None, rtol: float = 1e-8, atol: float = 1e-8
                             ) -> ClosedLoop:
    r"""Receding-horizon control of a plant by `problem`: at each t_j = t0 + j Δt, solve

        min Σ_{k<N} Δt ℓ + Φ  from the measured state x(t_j)

    warm-started from the previous solution shifted by one node (its inputs, and with path or
    terminal constraints their multipliers), apply its first input r_0
    over [t_j, t_j + Δt) (a zero-order hold) and integrate the plant over the interval with
    `jaxdyn.simulate` (adaptive Dopri8 at `rtol`, `atol`). The whole loop is one compiled
    program (`jax.lax.scan`): `jax.vmap` it over initial states or parameters.

    **Arguments:**

    - `problem`: the `jaxdyn.ShootingProblem` (its `dt` is the control interval).
    - `q0`, `u0`: the plant's initial state.
    - `p`: the parameters of the model the controller plans with.
    - `num_steps`: S, the control intervals simulated.
    - `plant`: the system driven (`problem.dynamics` when None); with `plant_parameters`
      (p when None): a different or perturbed model — model mismatch, an unknown payload.
    - `solver`: the solver of each step, usually a few iterations (real-time iterations).
    - `first_solver`: the solver of the first plan, from `inputs`; None: `solver`.
    - `inputs`: the first plan's guess (N, k); None: zero.

    **Returns:** a `jaxdyn.ClosedLoop`.

    With values (not under your own trace), a first plan that does not converge warns and
    one that diverges raises, as `jaxdyn.solve_optimal_control` does.
    """
    if not isinstance(problem, ShootingProblem):
        raise ValueError(f"problem must be a jaxdyn.ShootingProblem, got "
                         f"{type(problem).__name__}.")
    if int(num_steps) != num_steps or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}.")
    q0, u0 = check_vector(q0, "q0"), check_vector(u0, "u0")
    dtype = jnp.result_type(q0, u0)
    q0, u0 = q0.astype(dtype), u0.astype(dtype)
    p = numbers_as_arrays(p, dtype)
    # A contact scene's coordinates carry the ground's deformations (zero at the start).
    q0 = check_vector(problem.dynamics.initial_coordinates(q0, u0, p), "q0")
    plant = problem.dynamics if plant is None else plant
    plant_parameters = p if plant_parameters is None else numbers_as_arrays(plant_parameters,
                                                                            dtype)
    shape = (problem.num_nodes, problem.num_inputs(q0, u0, p))
    inputs = jnp.zeros(shape, dtype) if inputs is None else jnp.asarray(inputs, dtype)
    if inputs.shape != shape:
        raise ValueError(f"inputs (the first plan's guess) must have shape {shape}, got "
                         f"{inputs.shape}.")
    first = _solve(problem, first_solver or solver, q0, u0, p, inputs, None)
    _report(first)
    return _closed_loop(problem, plant, solver, first, q0, u0, p, plant_parameters,
                        int(num_steps), float(rtol), float(atol))


def _shifted(values):
    """The plan moved on by one node, its last value repeated."""
    return jnp.concatenate([values[1:], values[-1:]])


def _warm_start(problem, plan, t, q, u, p):
    """The inputs of the previous plan, moved on by one node and rolled out from the measured
    state under the plan's own feedback, r_k = r̄_k + K_k (x_k − x̄_k) (clipped to the bounds):
    a feasible guess that stays near the plan where the plant has strayed from it (the
    shifted inputs alone, replayed open loop, let an unstable plant fall away from it)."""
    num_q = q.shape[0]
    xs = _shifted(jnp.concatenate([plan.q, plan.u], axis=1))
    inputs, gains = _shifted(plan.inputs), _shifted(plan.feedback)
    lo, hi = problem.bounds(inputs.shape[1], inputs.dtype)
    ts = t + problem.dt * jnp.arange(problem.num_nodes, dtype=q.dtype)

    def node(x, data):
        time, x_ref, r_ref, gain = data
        r = r_ref + gain @ (x - x_ref)
        if lo is not None and hi is not None:
            r = jnp.clip(r, lo, hi)
        return problem.step(time, x, r, p, num_q), r

    _, guess = jax.lax.scan(node, jnp.concatenate([q, u]), (ts, xs[:-1], inputs, gains))
    return guess


@eqx.filter_jit
def _closed_loop(problem, plant, solver, first, q0, u0, p, plant_parameters, num_steps,
                 rtol, atol):
    def control_step(carry, j):
        q, u, plan = carry
        t = problem.t0 + j.astype(q.dtype) * problem.dt
        current = eqx.tree_at(lambda pr: pr.t0, problem, t)
        guess = _warm_start(problem, plan, t, q, u, p)
        # (the constraints' multipliers warm-started too, moved on by one node)
        duals = (_shifted(plan.path_multipliers), plan.terminal_multipliers)
        plan = jax.lax.cond(j == 0, lambda: plan, lambda: _solve(
            current, solver, q, u, p, guess, None, duals if problem.constrained else None))
        applied = plan.inputs[0]
        reached = simulate(plant.with_inputs(applied), q, u, plant_parameters, t0=t,
                           t1=t + problem.dt, rtol=rtol, atol=atol, save=("q", "u"),
                           throw=False)
        assert reached.q is not None and reached.u is not None  # saved
        q_next, u_next = reached.q[-1], reached.u[-1]
        return (q_next, u_next, plan), (q_next, u_next, applied, plan.cost, plan.iterations,
                                        plan.status)

    (_, _, last), (qs, us, applied, costs, iterations, status) = jax.lax.scan(
        control_step, (q0, u0, first), jnp.arange(num_steps))
    ts = problem.t0 + problem.dt * jnp.arange(num_steps + 1, dtype=q0.dtype)
    return ClosedLoop(ts=ts, q=jnp.concatenate([q0[None], qs]),
                      u=jnp.concatenate([u0[None], us]), inputs=applied,
                      predicted_cost=costs, iterations=iterations, status=status, last=last)
