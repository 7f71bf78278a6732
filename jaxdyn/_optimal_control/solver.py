"""iLQR and DDP on a shooting problem, in the multiple-shooting (feasibility-driven) form.

Each iteration expands the problem about the current trajectory (the dynamics' Jacobians and
the costs' gradients and Hessians, by autodiff), solves the linear–quadratic subproblem by the
Riccati recursion (`jaxdyn._optimal_control.riccati`), and takes the step along the
nonlinear dynamics with a backtracking line search:

    r̂_k = clip(r_k + α k_k + K_k (x̂_k − x_k), r_lo, r_hi),
    x̂_{k+1} = F(x̂_k, r̂_k) − (1 − α) g_{k+1},   x̂_0 = x_0 + α g_0,

so that a step of length α closes the fraction α of every gap g (Mastalli et al.,
"Crocoddyl: an efficient and versatile framework for multi-contact optimal control",
ICRA 2020); from a feasible guess the gaps are zero and this is the classical method. A step
is taken when the cost falls by at least a tenth of the model's prediction (or, where the
model predicts a rise while gaps are being closed, rises by at most twice the prediction; on
a feasible trajectory, where box-DDP's model predicts a rise while inputs move onto their
bounds, when the cost does not rise), or, where the model predicts a change
below 10⁻¹² |J| and the tolerance, when the cost changes by less than the tolerance: such
steps are taken as Crocoddyl takes those whose expected improvement is below its
`th_grad`, since the cost's round-off, amplified along the rollout and by stiff penalties,
can exceed the predicted change and would otherwise reject every trial, raise μ and stall
the solve at its iteration limit short of the convergence test. The
Levenberg–Marquardt regularisation μ of Q_rr starts at 0, grows tenfold (from 10⁻⁹) where
Q_rr + μI is not positive definite or no step is taken, and shrinks tenfold (to 0 below 10⁻⁹)
where a step of at least ½ is taken (Tassa, Erez
and Todorov, "Synthesis and stabilization of complex behaviors through online trajectory
optimization", IROS 2012).
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .problem import ShootingProblem
from .riccati import Expansion, Gains, backward_pass, linear_rollout

CONVERGED, ITERATION_LIMIT, DIVERGED, CONSTRAINTS_UNMET = 0, 1, 2, 3
MESSAGES = {CONVERGED: "converged: the predicted decrease fell below the tolerance on a "
                       "feasible trajectory",
            CONSTRAINTS_UNMET: "stopped with the constraints violated beyond their tolerance "
                               "after the augmented Lagrangian's last update",
            ITERATION_LIMIT: "stopped at the iteration limit before converging",
            DIVERGED: "diverged: no step decreased the cost even at the largest "
                      "regularisation, or the cost is not finite"}
_STEPS = 0.5 ** np.arange(10.0)  # NumPy: nothing computed with JAX at import
_REGULARISATION = (1e-9, 1e9)  # the least nonzero and the largest μ (Crocoddyl's bounds)
_UNRESOLVED = 1e-12  # relative: predicted changes of the cost taken untested below it (the
# cost's round-off, 10⁻¹⁶ |J|, grows by orders of magnitude in a stiff penalty and a rollout)


class AbstractTrajectorySolver(eqx.Module):
    """A solver of `jaxdyn.ShootingProblem`s: iLQR (`jaxdyn.ILQR`) or DDP (`jaxdyn.DDP`)."""

    max_iterations: eqx.AbstractVar[int]
    tol: eqx.AbstractVar[float]
    constraint_tol: eqx.AbstractVar[float]
    second_order: ClassVar[bool]


class ILQR(AbstractTrajectorySolver):
    """The iterative linear–quadratic regulator: Gauss–Newton on the dynamics (their first
    derivatives only; the costs' Hessians exact), with box-constrained inputs, multiple
    shooting from an infeasible guess (FDDP), line search and self-tuned regularisation.

    Reference: W. Li and E. Todorov, "Iterative linear quadratic regulator design for
    nonlinear biological movement systems", ICINCO 2004; C. Mastalli et al., ICRA 2020.

    **Arguments:**

    - `max_iterations`: the iteration limit (each backward pass counts one; with
      constraints, those of all the augmented Lagrangian's inner solves together).
    - `tol`: converged when the trajectory is feasible and the full step's predicted change
      of the cost is below `tol` (1 + |J|) in absolute value.
    - `constraint_tol`: with path or terminal constraints (`jaxdyn.ShootingProblem`), the
      largest violation (max(c, 0), |h|) and departure from complementarity (min(−c, λ/μ))
      accepted at convergence.
    """

    max_iterations: int = eqx.field(default=200, static=True)
    tol: float = eqx.field(default=1e-9, static=True)
    constraint_tol: float = eqx.field(default=1e-6, static=True)
    second_order: ClassVar[bool] = False


class DDP(AbstractTrajectorySolver):
    """Differential dynamic programming: as `jaxdyn.ILQR`, with the dynamics' second
    derivatives (V'_x · ∇²F by autodiff, one Hessian of a scalar per node) in the expansion
    of Q: quadratic convergence near the optimum, at a higher cost per iteration.

    Reference: D. H. Jacobson and D. Q. Mayne, *Differential Dynamic Programming* (1970).

    **Arguments:** as `jaxdyn.ILQR`.
    """

    max_iterations: int = eqx.field(default=200, static=True)
    tol: float = eqx.field(default=1e-9, static=True)
    constraint_tol: float = eqx.field(default=1e-6, static=True)
    second_order: ClassVar[bool] = True


class Iterate(eqx.Module):
    """The state of the iteration."""

    xs: jax.Array
    rs: jax.Array
    gaps: jax.Array
    cost: jax.Array
    regularisation: jax.Array
    iterations: jax.Array
    status: jax.Array
    done: jax.Array
    gains: Gains
    decrease: jax.Array


def _jacobians(f, parts):
    """(f(*parts), [∂f/∂part for each part]): f linearised once about `parts`, then its linear
    map differentiated in each part with the others held at zero. Taken apart, a part that f
    does not depend on through some operation (the speeds, in a hand's position; the inputs,
    in everything but B r) carries no directions through it, where one Jacobian in all the
    parts together would carry every direction through every operation; linearised once,
    the point's own computation (for a robot, its whole dynamics) is traced and compiled
    once, not once per part."""
    value, linear = jax.linearize(f, *parts)
    zeros = tuple(jnp.zeros_like(x) for x in parts)

    def wrt(i):
        return jax.jacfwd(lambda d: linear(*zeros[:i], d, *zeros[i + 1:]))(zeros[i])

    return value, [wrt(i) for i in range(len(parts))]


def _derivatives(value, parts):
    """(gradient, Hessian) of ½‖ρ‖² in the Gauss–Newton form (ρ'ᵀρ, ρ'ᵀρ') when `value`
    returns a residual ρ, else of the scalar exactly; in the `parts` (q, u, r) concatenated,
    each differentiated apart (`_jacobians`)."""
    if jax.eval_shape(value, *parts).ndim == 0:
        def gradient(*parts):
            return jnp.concatenate(jax.grad(value, argnums=tuple(range(len(parts))))(*parts))

        gradient_value, hessian = _jacobians(gradient, parts)
        return gradient_value, jnp.concatenate(hessian, axis=1)
    residual, jacobian = _jacobians(value, parts)
    jacobian = jnp.concatenate(jacobian, axis=1)
    return jacobian.T @ residual, jacobian.T @ jacobian


def expand(problem: ShootingProblem, xs, rs, gaps, p, num_q, *, exact=False) -> Expansion:
    """The dynamics' Jacobians and the costs' derivatives at every node (the Gauss–Newton
    Hessians of residual costs unless `exact`), each in the coordinates, the speeds and the
    inputs apart (`_jacobians`)."""
    ts = problem.times(xs.dtype)
    n = xs.shape[1]

    def step(t, x, r):
        _, ((qq, uq), (qu, uu), (qr, ur)) = _jacobians(
            lambda q, u, r: problem.split_step(t, q, u, r, p), (x[:num_q], x[num_q:], r))
        return jnp.block([[qq, qu], [uq, uu]]), jnp.concatenate([qr, ur])

    def running(t, x, r):
        value = problem.node_cost if exact else problem.running_value
        gradient, hessian = _derivatives(lambda q, u, r: value(t, q, u, r, p),
                                         (x[:num_q], x[num_q:], r))
        return (gradient, hessian) if exact else (problem.dt * gradient, problem.dt * hessian)

    def final(x):
        value = problem.final_cost if exact else problem.final_value
        return _derivatives(lambda q, u: value(ts[-1], q, u, p), (x[:num_q], x[num_q:]))

    fx, fr = jax.vmap(step)(ts[:-1], xs[:-1], rs)
    gradient, hessian = jax.vmap(running)(ts[:-1], xs[:-1], rs)
    terminal_x, terminal_xx = final(xs[-1])
    return Expansion(fx=fx, fr=fr, lx=gradient[:, :n], lr=gradient[:, n:],
                     lxx=hessian[:, :n, :n], lrr=hessian[:, n:, n:], lrx=hessian[:, n:, :n],
                     terminal_x=terminal_x, terminal_xx=terminal_xx, gaps=gaps)


def step_curvature(problem: ShootingProblem, t, x, r, weights, p, num_q):
    """∇²(w · F(t, x, r)) of one step, split as (h_xx, h_rr, h_rx); in the coordinates, the
    speeds and the inputs apart (`_jacobians`)."""
    def contracted(q, u, r):
        q_next, u_next = problem.split_step(t, q, u, r, p)
        return weights[:num_q] @ q_next + weights[num_q:] @ u_next

    n = x.shape[0]
    _, hessian = _derivatives(contracted, (x[:num_q], x[num_q:], r))
    return hessian[:n, :n], hessian[n:, n:], hessian[n:, :n]


def dynamics_curvature(problem: ShootingProblem, xs, rs, p, num_q):
    """second_order(k, λ) = ∇²(λ · F_k) at node k, split as (h_xx, h_rr, h_rx)."""
    ts = problem.times(xs.dtype)
    return lambda k, weights: step_curvature(problem, ts[k], xs[k], rs[k], weights, p, num_q)


def gaps_of(problem: ShootingProblem, x0, xs, rs, p, num_q):
    """g_0 = x̂_0 − x_0, g_{k+1} = F(x_k, r_k) − x_{k+1}: the defects of a trajectory."""
    ts = problem.times(xs.dtype)
    reached = jax.vmap(problem.step, in_axes=(0, 0, 0, None, None))(ts[:-1], xs[:-1], rs, p,
                                                                     num_q)
    return jnp.concatenate([(x0 - xs[0])[None], reached - xs[1:]])


def _forward(problem, iterate, gains, alpha, lo, hi, p, num_q):
    """The trajectory of a step of length α along the nonlinear dynamics, and its cost."""
    ts = problem.times(iterate.xs.dtype)
    gaps = iterate.gaps

    def node(x, data):
        t, x_ref, r_ref, ff, fb, gap = data
        r = r_ref + alpha * ff + fb @ (x - x_ref)
        r = r if lo is None else jnp.clip(r, lo, hi)
        x_next = problem.step(t, x, r, p, num_q) - (1 - alpha) * gap
        return x_next, (x_next, r)

    start = iterate.xs[0] + alpha * gaps[0]
    _, (xs, rs) = jax.lax.scan(node, start, (ts[:-1], iterate.xs[:-1], iterate.rs,
                                             gains.feedforward, gains.feedback, gaps[1:]))
    xs = jnp.concatenate([start[None], xs])
    return xs, rs, problem.cost(xs, rs, p, num_q)


def _line_search(problem, iterate, gains, d1, d2, lo, hi, p, num_q, tolerance, feasible):
    """The first α in 1, ½, … ¼⁵¹² whose step the acceptance test takes, or none;
    `tolerance`: the change of the cost below which the solve has converged; `feasible`:
    whether the trajectory has no gaps (a rise of the cost is then never taken)."""
    def trial(i):
        alpha = jnp.asarray(_STEPS, iterate.xs.dtype)[i]
        xs, rs, cost = _forward(problem, iterate, gains, alpha, lo, hi, p, num_q)
        predicted = alpha * d1 + 0.5 * alpha ** 2 * d2  # the model's change of cost
        change = cost - iterate.cost
        # (with the round-off of the cost as slack: the last steps predict changes below it)
        slack = 1e-14 * jnp.abs(iterate.cost)
        # A rise the model predicts is taken only while gaps are being closed. On a feasible
        # trajectory box-DDP's model predicts one where inputs have yet to reach a bound (its
        # d₁ leaves their gradient out, its d₂ keeps their step), though every step of a
        # descent lowers the cost: taking such rises let a convex problem's iterates cycle
        # between two trajectories, the cost rising in turn along each.
        rise = jnp.where(feasible, slack, 2 * predicted + slack)
        decreased = jnp.where(predicted < 0, change <= 0.1 * predicted + slack, change <= rise)
        # A change the model puts below what the cost resolves is held to the tolerance, not
        # to the model: the cost's round-off (a stiff penalty's, an unstable rollout's) may
        # exceed the predicted change.
        unmeasured = ((jnp.abs(predicted) <= jnp.minimum(tolerance, _UNRESOLVED * jnp.abs(
            iterate.cost))) & (change <= tolerance))
        accepted = jnp.isfinite(cost) & (decreased | unmeasured)
        return xs, rs, cost, alpha, accepted

    def body(state):
        i, _ = state
        return i + 1, trial(i)

    # The first trial inside the loop, so that the rollout is traced (and compiled) once.
    nothing = (iterate.xs, iterate.rs, iterate.cost, jnp.zeros((), iterate.xs.dtype),
               jnp.array(False))
    _, (xs, rs, cost, alpha, accepted) = jax.lax.while_loop(
        lambda s: (s[0] < _STEPS.shape[0]) & ~s[1][4], body, (0, nothing))
    return xs, rs, cost, alpha, accepted


def _raised(mu):
    return jnp.maximum(10 * mu, _REGULARISATION[0])


def _lowered(mu):
    """μ / 10, and none below the least: a Newton step unbiased where Q_rr is positive
    definite (the linear–quadratic problem then solves in one step, to round-off)."""
    return jnp.where(mu / 10 < _REGULARISATION[0], 0.0, mu / 10)


def _iteration(problem, solver, lo, hi, p, num_q, tol, iterate: Iterate) -> Iterate:
    xs, rs = iterate.xs, iterate.rs
    expansion = expand(problem, xs, rs, iterate.gaps, p, num_q, exact=solver.second_order)
    second = dynamics_curvature(problem, xs, rs, p, num_q) if solver.second_order else None

    def riccati(mu):
        return backward_pass(expansion, rs, lo, hi, mu, second_order=second,
                             start=iterate.gains.feedforward)

    # Where Q_rr + μI is not positive definite, μ grows and the Riccati sweep runs again on
    # the same expansion (the derivatives, the expensive part, are not formed again). The
    # first sweep runs inside the loop, so that the sweep is compiled once.
    def sweep(state):
        mu, _, first = state
        mu = jnp.where(first, mu, _raised(mu))
        return mu, riccati(mu), jnp.array(False)

    mu, gains, _ = jax.lax.while_loop(
        lambda s: s[2] | (~s[1].ok & (s[0] <= _REGULARISATION[1])), sweep,
        (iterate.regularisation, iterate.gains, jnp.array(True)))
    iterate = eqx.tree_at(lambda it: it.regularisation, iterate, mu)
    _, _, d1, d2 = linear_rollout(expansion, gains)
    feasible = jnp.max(jnp.abs(iterate.gaps)) <= 1e-12 * (1 + jnp.max(jnp.abs(xs)))
    if gains.expected is not None:  # input bounds: box-DDP's model of the step, once the
        # trajectory is feasible (`riccati`); while gaps remain, the linear rollout's, which
        # accounts for closing them
        d1 = jnp.where(feasible, gains.expected[0], d1)
        d2 = jnp.where(feasible, gains.expected[1], d2)
    decrease = -(d1 + 0.5 * d2)
    # The predicted decrease measures stationarity only for the Newton step itself: a large μ
    # shortens the step, and with it the prediction, far from an optimum. (In absolute value:
    # box-DDP's model predicts a rise where an input has yet to reach its bound.)
    tolerance = tol * (1 + jnp.abs(iterate.cost))
    converged = (gains.ok & feasible & (iterate.regularisation <= _REGULARISATION[0])
                 & (jnp.abs(decrease) <= tolerance))

    def step(_):
        new_xs, new_rs, cost, alpha, accepted = _line_search(problem, iterate, gains, d1, d2,
                                                             lo, hi, p, num_q, tolerance,
                                                             feasible)
        mu = iterate.regularisation
        mu = jnp.where(~accepted | (alpha <= 0.01), _raised(mu),
                       jnp.where(alpha >= 0.5, _lowered(mu), mu))
        return (jnp.where(accepted, new_xs, xs), jnp.where(accepted, new_rs, rs),
                jnp.where(accepted, (1 - alpha) * iterate.gaps, iterate.gaps),
                jnp.where(accepted, cost, iterate.cost), mu)

    def refuse(_):
        return xs, rs, iterate.gaps, iterate.cost, _raised(iterate.regularisation)

    # A converged iteration still takes its (Newton) step: it costs one rollout, and it is
    # what makes the returned inputs accurate to the square of the last error (DDP), not to
    # the square root of the tolerance on the cost.
    new_xs, new_rs, gaps, cost, mu = jax.lax.cond(gains.ok, step, refuse, None)
    mu = jnp.where(converged, iterate.regularisation, mu)
    iterations = iterate.iterations + 1
    diverged = (mu > _REGULARISATION[1]) | ~jnp.isfinite(cost)
    limit = iterations >= solver.max_iterations
    status = jnp.where(converged, CONVERGED, jnp.where(diverged, DIVERGED, ITERATION_LIMIT))
    return Iterate(xs=new_xs, rs=new_rs, gaps=gaps, cost=cost, regularisation=mu,
                   iterations=iterations, status=status, done=converged | diverged | limit,
                   gains=gains, decrease=decrease)


def initial_iterate(problem: ShootingProblem, x_init, p, xs, rs, num_q, *,
                    feasible: bool = False, iterations=0) -> Iterate:
    """The iteration's state at the guess (xs, rs): inputs clipped to their bounds, gaps and
    cost formed, no gains yet. `feasible`: xs is the rollout of rs from x_init (no gaps to
    form); `iterations`: those already counted (by earlier solves)."""
    lo, hi = problem.bounds(rs.shape[1], rs.dtype)
    if lo is not None and hi is not None:
        rs = jnp.clip(rs, lo[None], hi[None])
    gaps = jnp.zeros_like(xs) if feasible else gaps_of(problem, x_init, xs, rs, p, num_q)
    cost = problem.cost(xs, rs, p, num_q)
    n, m, big_n = xs.shape[1], rs.shape[1], rs.shape[0]
    empty = Gains(feedforward=jnp.zeros_like(rs), feedback=jnp.zeros((big_n, m, n), rs.dtype),
                  value_x=jnp.zeros_like(xs), value_xx=jnp.zeros((big_n + 1, n, n), rs.dtype),
                  free=jnp.ones_like(rs, bool), ok=jnp.array(False),
                  curvature=(jnp.zeros((big_n, n, n), rs.dtype), jnp.zeros((big_n, m, m), rs.dtype),
                             jnp.zeros((big_n, m, n), rs.dtype)),
                  expected=None if lo is None else (jnp.zeros((), rs.dtype),
                                                      jnp.zeros((), rs.dtype)))
    finite = jnp.isfinite(cost)
    return Iterate(xs=xs, rs=rs, gaps=gaps, cost=cost,
                   regularisation=jnp.zeros((), rs.dtype),
                   iterations=jnp.asarray(iterations, jnp.int32),
                   status=jnp.where(finite, ITERATION_LIMIT, DIVERGED), done=~finite,
                   gains=empty, decrease=jnp.asarray(jnp.inf, rs.dtype))


def iterate_to_optimum(problem: ShootingProblem, solver: AbstractTrajectorySolver, x_init, p,
                       xs, rs, num_q, *, feasible: bool = False, iterations=0,
                       tol=None) -> Iterate:
    """The solver's iterations from the guess (xs, rs) until converged, diverged or at the
    iteration limit. The returned gains are those of the last backward pass (at the optimum
    when converged). `feasible`: xs is the rollout of rs from x_init (no gaps to form);
    `iterations`: those already spent (the limit counts them); `tol`: the solver's, unless
    given (a looser one, as an array, for the augmented Lagrangian's early solves)."""
    tol = solver.tol if tol is None else tol
    lo, hi = problem.bounds(rs.shape[1], rs.dtype)
    start = initial_iterate(problem, x_init, p, xs, rs, num_q, feasible=feasible,
                            iterations=iterations)
    # The limit is tested again beside `done`, which already holds it: XLA's while-loop passes
    # look for a trip count wherever a loop's condition reads a single loop-carried value, and
    # for that copy the whole computation of its update, here the whole iteration, at every
    # pass (the Panda reaching a point: 33 s of compilation against 10 s reading two values).
    return jax.lax.while_loop(
        lambda it: ~it.done & (it.iterations < solver.max_iterations),
        lambda it: _iteration(problem, solver, lo, hi, p, num_q, tol, it), start)
