"""`solve_optimal_control`: the public entry point, its result and its derivatives."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._chunking import chunked_vmap
from .._compile import filter_jit
from .._state import check_vector, numbers_as_arrays, under_a_trace
from .problem import ShootingProblem
from .sensitivity import pull_back
from .augmented_lagrangian import (derivative_problem, iterate_with_constraints,
                                   unconstrained_multipliers)
from .solver import (CONSTRAINTS_UNMET, CONVERGED, DIVERGED, ILQR, MESSAGES,
                     AbstractTrajectorySolver, iterate_to_optimum)


class NotConvergedWarning(UserWarning):
    """An optimal control solve stopped at its iteration limit: the trajectory returned is the
    last iterate, not an optimum (raise `max_iterations`, or start nearer the optimum)."""


class OptimalTrajectory(eqx.Module):
    """The result of `jaxdyn.solve_optimal_control`.

    **Fields:**

    - `ts` (N+1,): the node times t_k.
    - `q` (N+1, n), `u` (N+1, m): the states at the nodes.
    - `inputs` (N, k): the inputs r_k, held over [t_k, t_{k+1}).
    - `cost`: J of the trajectory.
    - `feedforward` (N, k), `feedback` (N, k, n + m): the last backward pass's step
      δr = k + K δx, K the locally optimal feedback gains (Riccati gains) at the optimum,
      zero in the rows of inputs held at a bound. Not differentiated.
    - `iterations`: the backward passes run.
    - `status`: 0 converged, 1 stopped at the iteration limit, 2 diverged (`message`).
    - `gap`: the largest defect |F(x_k, r_k) − x_{k+1}| left (0 once feasible).
    - `regularisation`: the final Levenberg–Marquardt μ.
    - `predicted_decrease`: the decrease of the cost the last backward pass predicted for a
      full step, the measure of convergence (against `tol` (1 + |J|)).
    - `status` 3: with constraints, stopped with them violated beyond the solver's
      `constraint_tol`.
    - `constraint_violation`: the largest violation max(c, 0), |h| of the path and terminal
      constraints (0 without constraints).
    - `path_multipliers` (N, c), `terminal_multipliers` (e,): the constraints' Lagrange
      multipliers, λ ≥ 0 (zero where a path constraint is inactive) and ν, as the augmented
      Lagrangian estimates them; the derivative of the optimal cost with respect to a
      constraint's bound. Empty (shape (N, 0), (0,)) without constraints.
    """

    ts: jax.Array
    q: jax.Array
    u: jax.Array
    inputs: jax.Array
    cost: jax.Array
    feedforward: jax.Array
    feedback: jax.Array
    iterations: jax.Array
    status: jax.Array
    gap: jax.Array
    regularisation: jax.Array
    predicted_decrease: jax.Array
    constraint_violation: jax.Array
    path_multipliers: jax.Array
    terminal_multipliers: jax.Array

    @property
    def converged(self):
        """Whether the solve met its tolerance (an array under `vmap`)."""
        return self.status == CONVERGED

    @property
    def message(self) -> str:
        """The status in words (one solve, not under a trace)."""
        return MESSAGES[int(self.status)]

    def policy(self, input_bounds=None):
        """The time-varying affine feedback about the plan,

            r(t, x) = r_k + K_k (x − x̄(t)),   t ∈ [t_k, t_{k+1}),

        x̄(t) the plan's state interpolated linearly between its nodes (clamped to the
        horizon), clipped to `input_bounds` (r_lo, r_hi) where given (the problem's), as a
        policy π(t, q, u, p) for `jaxdyn.simulate(..., inputs=...)`: it tracks the optimal
        trajectory against disturbances and model errors. The gains are those of the last
        Riccati sweep (at the optimum when converged)."""
        bounds = None if input_bounds is None else tuple(
            jnp.broadcast_to(jnp.asarray(b, self.inputs.dtype), self.inputs.shape[-1:])
            for b in input_bounds)
        return TrackingPolicy(self.ts, jnp.concatenate([self.q, self.u], axis=-1),
                              self.inputs, jax.lax.stop_gradient(self.feedback), bounds)


class TrackingPolicy(eqx.Module):
    """r = r_k + K_k ([q; u] − x̄(t)) for t in [t_k, t_{k+1}), x̄ the plan's states
    interpolated linearly, clipped to the bounds where given: `OptimalTrajectory.policy()`."""

    ts: jax.Array
    xs: jax.Array
    inputs: jax.Array
    gains: jax.Array
    bounds: tuple | None = None

    def __call__(self, t, q, u, p=None):
        num = self.inputs.shape[0]
        dt = self.ts[1] - self.ts[0]
        position = jnp.clip((t - self.ts[0]) / dt, 0, num)
        k = jnp.minimum(jnp.floor(position).astype(int), num - 1)
        fraction = position - k.astype(position.dtype)
        reference = (1 - fraction) * self.xs[k] + fraction * self.xs[k + 1]
        r = self.inputs[k] + self.gains[k] @ (jnp.concatenate([q, u]) - reference)
        if self.bounds is not None:
            r = jnp.clip(r, *self.bounds)
        return r


def solve_optimal_control(problem: ShootingProblem, q0, u0, p=None, *, inputs=None,
                          states=None, solver: AbstractTrajectorySolver = ILQR(),
                          throw: bool = True) -> OptimalTrajectory:
    r"""Solve a `jaxdyn.ShootingProblem` from the state (q0, u0) by iLQR or DDP:

        min_r  Σ_{k<N} Δt ℓ(q_k, u_k, r_k, p) + Φ(q_N, u_N, p)
        s.t.   x_{k+1} = F_Δt(x_k, r_k, p),  x_0 = (q0, u0),  r_lo ≤ r_k ≤ r_hi.

    **Arguments:**

    - `problem`: the `jaxdyn.ShootingProblem`.
    - `q0`, `u0`: the initial state (for a `jaxdyn.Contact` scene, the system's q0: the
      ground's deformations start at zero, and the plan's q holds them appended).
    - `p`: the parameters, passed to the dynamics and the costs.
    - `inputs`: the initial guess of the inputs (N, k); None: zero (clipped to the bounds).
    - `states`: a guess of the states, a pair (q (N+1, n), u (N+1, m)): the solve starts
      from this possibly infeasible trajectory (multiple shooting, as FDDP: the defects
      F(x_k, r_k) − x_{k+1} close along the iterations); None: the rollout of `inputs`.
    - `solver`: `jaxdyn.ILQR()` (default, Gauss–Newton) or `jaxdyn.DDP()`; their
      `max_iterations` and `tol`.
    - `throw`: called with values (not inside your `jax.jit` or `vmap`), raise where the
      solve diverged and warn (`jaxdyn.NotConvergedWarning`) where it stopped at the
      iteration limit. Inside a trace, read `status`.

    **Returns:** a `jaxdyn.OptimalTrajectory`.

    Pure JAX: `jax.vmap` solves a batch of problems (initial states, targets or parameters
    in p) in one program, one problem after another, each with its own iterations;
    `jax.grad` of the optimal trajectory or cost with respect to q0, u0, p and the arrays the
    dynamics hold (a `jaxdyn.RigidBodyTree`'s masses, the places where `jaxdyn.HeldPoints`
    hold it) is exact at the optimum by the implicit function theorem (one more Riccati
    sweep, not the solver's iterations unrolled), and as accurate as the solve: the
    derivative of the optimal cost is insensitive to the tolerance (the cost is stationary),
    those of the inputs and states are not (tighten `tol`, or finish with `jaxdyn.DDP()`, whose
    convergence is quadratic). A solve that did not converge gives the gradient of the last
    iterate as if it were optimal.

    **Example** (the cart-pole of `jaxdyn.ShootingProblem`, from hanging):

        plan = jaxdyn.solve_optimal_control(problem, jnp.array([0.0, jnp.pi]), jnp.zeros(2), p)
        plan.q[-1], plan.cost, plan.converged, plan.policy()
    """
    if not isinstance(problem, ShootingProblem):
        raise ValueError(f"problem must be a jaxdyn.ShootingProblem, got "
                         f"{type(problem).__name__}.")
    if not isinstance(solver, AbstractTrajectorySolver):
        raise ValueError(f"solver must be jaxdyn.ILQR() or jaxdyn.DDP(), got "
                         f"{type(solver).__name__}.")
    q0, u0 = check_vector(q0, "q0"), check_vector(u0, "u0")
    dtype = jnp.result_type(q0, u0)
    q0, u0 = q0.astype(dtype), u0.astype(dtype)
    p = numbers_as_arrays(p, dtype)
    # A contact scene's coordinates carry the ground's deformations (zero at the start).
    q0 = check_vector(problem.dynamics.initial_coordinates(q0, u0, p), "q0")
    num_inputs = problem.num_inputs(q0, u0, p)
    shape = (problem.num_nodes, num_inputs)
    inputs = jnp.zeros(shape, dtype) if inputs is None else jnp.asarray(inputs, dtype)
    if inputs.shape != shape:
        raise ValueError(f"inputs (the guess) must have shape {shape} (N nodes, k inputs), "
                         f"got {inputs.shape}.")
    if states is not None:
        states = _checked_states(states, problem.num_nodes, q0.shape[0], u0.shape[0], dtype)
    result = _solve(problem, solver, q0, u0, p, inputs, states)
    if throw and not under_a_trace():
        _report(result)
    return result


def _checked_states(states, num_nodes, n, m, dtype):
    if not isinstance(states, (tuple, list)) or len(states) != 2:
        raise ValueError("states (the guess) must be a pair (q (N+1, n), u (N+1, m)).")
    qs, us = (jnp.asarray(s, dtype) for s in states)
    if qs.shape != (num_nodes + 1, n) or us.shape != (num_nodes + 1, m):
        raise ValueError(f"states (the guess) must be q of shape {(num_nodes + 1, n)} and u of "
                         f"shape {(num_nodes + 1, m)}, got {qs.shape} and {us.shape}.")
    return qs, us


def _report(result: OptimalTrajectory):
    # (NumPy on host copies: NumPy's reductions of JAX arrays would compile a program each)
    status = np.asarray(result.status)
    iterations = int(np.max(np.asarray(result.iterations)))
    if np.any(status == DIVERGED):
        raise ValueError(f"solve_optimal_control {MESSAGES[DIVERGED]} (after {iterations} "
                         "iterations, μ = "
                         f"{float(np.max(np.asarray(result.regularisation))):.1e}). Check that "
                         "the costs and dynamics are finite along the guess, scale the costs, "
                         "or start from a better guess (inputs=, states=).")
    if np.any(status == CONSTRAINTS_UNMET):
        violation = float(np.max(np.asarray(result.constraint_violation)))
        warnings.warn(f"solve_optimal_control {MESSAGES[CONSTRAINTS_UNMET]} (largest "
                      f"violation {violation:.1e}, after {iterations} iterations): the "
                      "trajectory is not an optimum of the constrained problem. The "
                      "constraints may be infeasible from this start; else raise the solver's "
                      "max_iterations or constraint_tol.", NotConvergedWarning, stacklevel=3)
    elif np.any(status != CONVERGED):
        decrease = float(np.max(np.asarray(result.predicted_decrease)))
        warnings.warn(f"solve_optimal_control {MESSAGES[int(status.max())]} ({iterations} "
                      f"iterations; the predicted decrease {decrease:.1e} is still above the "
                      "tolerance): the trajectory is not an optimum. Raise the solver's "
                      "max_iterations.", NotConvergedWarning, stacklevel=3)


@filter_jit
def _solve(problem, solver, q0, u0, p, inputs, states, duals=None):
    """The solve; `duals`: the constraints' multipliers to start from (λ, ν), or None."""
    num_q = q0.shape[0]
    x_init = jnp.concatenate([q0, u0])
    if states is None:
        xs = problem.rollout(x_init, inputs, p, num_q)
    else:
        xs = jnp.concatenate(states, axis=1)
    # The guess is where the iterations start, not a function of (q0, u0, p): the optimum's
    # derivatives come from the implicit function theorem alone.
    xs, inputs = jax.lax.stop_gradient((xs, inputs))
    if duals is not None:
        duals = jax.lax.stop_gradient(duals)
    # The problem's floating-point arrays (a tree's masses, a hold's positions, t0) are
    # differentiated with x̂_0 and p; the rest of it (functions, integers) is static.
    arrays, rest = eqx.partition(problem, eqx.is_inexact_array)
    iterate, multipliers = _optimum((x_init, p, arrays), rest, solver, xs, inputs, num_q,
                                    states is None, duals)
    multipliers = jax.lax.stop_gradient(multipliers)
    xs, rs = iterate.xs, iterate.rs
    gains = jax.lax.stop_gradient(iterate.gains)
    return OptimalTrajectory(
        ts=problem.times(xs.dtype), q=xs[:, :num_q], u=xs[:, num_q:], inputs=rs,
        cost=problem.cost(xs, rs, p, num_q), feedforward=gains.feedforward,
        feedback=gains.feedback, iterations=iterate.iterations, status=iterate.status,
        gap=jnp.max(jnp.abs(iterate.gaps)), regularisation=iterate.regularisation,
        predicted_decrease=iterate.decrease, constraint_violation=multipliers.violation,
        path_multipliers=multipliers.path_estimate,
        terminal_multipliers=multipliers.terminal_estimate)


@eqx.filter_custom_vjp
def _optimum(theta, rest, solver, xs, rs, num_q, feasible, duals):
    x_init, p, arrays = theta
    problem = eqx.combine(arrays, rest)

    def solve(problem, solver, x_init, p, xs, rs, duals):
        if problem.constrained:
            return iterate_with_constraints(problem, solver, x_init, p, xs, rs, num_q,
                                            feasible=feasible, duals=duals)
        return (iterate_to_optimum(problem, solver, x_init, p, xs, rs, num_q,
                                   feasible=feasible),
                unconstrained_multipliers(problem.num_nodes, xs.dtype))

    # Under `vmap`, one problem after another (`jaxdyn._chunking`): vmapped whole, every loop
    # of the solver (iterations, line search, box QP at each node) runs until its slowest
    # member stops, and a tree's recursions run as whole-batch array code. 64 Panda
    # problems: 404 ms per problem vmapped whole, 138 one after another (a single solve:
    # 133); 1024 double pendulums 1.64 and 1.15 ms.
    return chunked_vmap(solve)(problem, solver, x_init, p, xs, rs, duals)


@_optimum.def_fwd
def _optimum_fwd(perturbed, theta, rest, solver, xs, rs, num_q, feasible, duals):
    del perturbed
    optimum = _optimum.fn(theta, rest, solver, xs, rs, num_q, feasible, duals)
    return optimum, optimum


@_optimum.def_bwd
def _optimum_bwd(optimum, cotangent, perturbed, theta, rest, solver, xs, rs, num_q,
                 feasible, duals):
    del xs, rs, solver, feasible, duals
    iterate, multipliers = optimum
    cotangent = cotangent[0]
    x_init, p, arrays = theta
    xs_bar = jnp.zeros_like(iterate.xs) if cotangent.xs is None else cotangent.xs
    rs_bar = jnp.zeros_like(iterate.rs) if cotangent.rs is None else cotangent.rs
    # Only the problem's arrays that are differentiated: the others held as constants.
    differentiated = eqx.filter(arrays, perturbed[2])
    held = eqx.combine(eqx.filter(arrays, perturbed[2], inverse=True), rest)

    def problem_of(differentiated):
        problem = eqx.combine(differentiated, held)
        # With constraints, those of the problem whose Hessian holds the active constraints
        # stiffly (`derivative_problem`): the last augmented problem's own, whose penalty
        # may have stayed small, would let them move (by 2-4 % on the tests' linear problem).
        if problem.constrained:
            problem = derivative_problem(problem, multipliers, iterate.xs, iterate.rs, p,
                                         num_q)
        return problem

    return pull_back(problem_of, (x_init, p, differentiated), iterate.xs, iterate.rs,
                     iterate.gains.free, xs_bar, rs_bar, num_q)
