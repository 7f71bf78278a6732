"""Path and terminal constraints by an augmented Lagrangian about iLQR and DDP.

For path constraints c_k = c(q_k, u_k, r_k) ≤ 0 (k < N) and terminal constraints
h(q_N, u_N) = 0, the solver (`jaxdyn.ILQR`, `jaxdyn.DDP`) minimises, for fixed multipliers
λ_k ≥ 0, ν and a penalty μ > 0, the augmented Lagrangian of Hestenes, Powell and Rockafellar

    J + Σ_{k<N} ½ μ ‖max(0, c_k + λ_k/μ)‖² + ½ μ ‖h + ν/μ‖²

(up to terms constant in the trajectory), and between its solves the multipliers take their
first-order update and the penalty grows where the violation fell too slowly:

    λ_k ← max(0, λ_k + μ c_k),   ν ← ν + μ h,   μ ← 10 μ unless the violation fell fourfold,

until the constraints hold and are complementary to their multipliers,
max(max_k |max(c_k, −λ_k/μ)|, |h|) below the solver's `constraint_tol` (the measure of the
bound-constrained augmented Lagrangian, zero only where each c_k = 0 or λ_k = 0), at a
converged inner solve (R. T. Rockafellar, "The multiplier method of
Hestenes and Powell applied to convex programming", JOTA 12, 1973; in trajectory
optimisation, the outer loop of ALTRO: T. A. Howell, B. E. Jackson and Z. Manchester,
"ALTRO: a fast solver for constrained trajectory optimization", IROS 2019). The penalty of
node k enters its running cost as Δt⁻¹ of it (the running cost is Δt ℓ); a running or
terminal cost given as a residual ρ keeps its Gauss–Newton form, the penalty's residual
√(μ/Δt) max(0, c + λ/μ) appended to it.

Each inner solve starts from the last one's trajectory (with its gaps), the early ones to a
loose tolerance (10⁻⁵, as ALTRO's intermediate tolerance) until the violation is within 100
times its own; the solver's `max_iterations` bounds the backward passes of all of them
together. Where a later inner solve diverges (a penalty stiffer than the solver's model of the
nonlinear dynamics follows), the last solve's trajectory is returned with status 3, the
constraints not met, and its violation.
"""

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .problem import ShootingProblem
from .solver import (CONSTRAINTS_UNMET, CONVERGED, DIVERGED, Iterate, initial_iterate,
                     iterate_to_optimum)

_FIRST_PENALTY = 100.0  # (ALTRO starts at 1; on the cart-pole on rails of ±0.3 m, 1 led
# to a worse local optimum the penalty then could not leave, 10-1000 all to the optimum)
_PENALTY_GROWTH = 10.0
_LARGEST_PENALTY = 1e8  # (ALTRO's largest)
_UPDATES = 30  # the outer iterations (updates of the multipliers) at most
_LOOSE_TOL = 1e-5  # the inner solves' tolerance until the violation is near its own
_NEAR = 100.0


class Augmented(ShootingProblem):
    """A constrained problem whose costs carry the augmented Lagrangian's penalties for fixed
    multipliers (λ (N, c), ν (e,)) and penalty μ: the problem the inner solver minimises.

    With `attained` (c*, h*), the values at an optimum, and `active` (N, c), the path
    constraints whose multiplier is positive: the problem whose stationary point is that
    optimum and whose Hessian holds the active constraints as the penalty's stiffness,
    ½ μ ‖c − c* + λ/μ‖² on the active ones alone (its gradient λ c' whatever μ), for the
    optimum's derivatives (`derivative_problem`)."""

    # (defaults only because ShootingProblem's last fields have them: __init__ sets all)
    multipliers: Any = None
    terminal_multipliers: Any = None
    penalty: Any = None
    attained: Any = None
    active: Any = None

    def __init__(self, problem: ShootingProblem, multipliers, terminal_multipliers, penalty,
                 attained=None, active=None):
        for field in dataclasses.fields(ShootingProblem):
            setattr(self, field.name, getattr(problem, field.name))
        self.multipliers = multipliers
        self.terminal_multipliers = terminal_multipliers
        self.penalty = penalty
        self.attained = attained
        self.active = active

    def _node(self, t):
        """k of the node at time t_k = t0 + k Δt."""
        k = jnp.round((t - self.t0) / self.dt)
        return jnp.clip(k, 0, self.num_nodes - 1).astype(jnp.int32)

    def running_value(self, t, q, u, r, p):
        value = super().running_value(t, q, u, r, p)
        if self.path_constraints is None:
            return value
        k = self._node(t)
        c = self.path_value(t, q, u, r, p)
        if self.attained is None:
            shifted = jnp.maximum(c + self.multipliers[k] / self.penalty, 0.0)
        else:
            shifted = jnp.where(self.active[k], c - self.attained[0][k]
                                + self.multipliers[k] / self.penalty, 0.0)
        return _with_penalty(value, self.penalty / self.dt, shifted)

    def final_value(self, t, q, u, p):
        value = super().final_value(t, q, u, p)
        if self.terminal_constraints is None:
            return value
        h = self.terminal_value(t, q, u, p)
        if self.attained is not None:
            h = h - self.attained[1]
        return _with_penalty(value, self.penalty, h + self.terminal_multipliers / self.penalty)


def _with_penalty(value, weight, shifted):
    """value + ½ w ‖s‖²: appended to a residual as √w s (Gauss–Newton), added to a scalar."""
    if value.ndim == 0:
        return value + 0.5 * weight * shifted @ shifted
    return jnp.concatenate([value, jnp.sqrt(weight) * shifted])


class Multipliers(eqx.Module):
    """The outer iteration's state: the multipliers and penalty of the last inner solve
    (those of its augmented problem, which the optimum's derivatives need), their updated
    estimates (the constraints' Lagrange multipliers), the violation and the updates made."""

    path: jax.Array
    terminal: jax.Array
    penalty: jax.Array
    path_estimate: jax.Array
    terminal_estimate: jax.Array
    violation: jax.Array
    residual: jax.Array
    updates: jax.Array

    def problem(self, problem: ShootingProblem) -> Augmented:
        return Augmented(problem, self.path, self.terminal, self.penalty)


# The stiffness with which the optimum's derivatives hold the active constraints: their
# error is of the order of the problem's curvature over it.
_STIFFNESS = 1e8


def derivative_problem(problem: ShootingProblem, multipliers: Multipliers, xs, rs, p, num_q):
    """The augmented problem whose implicit derivatives (`jaxdyn._optimal_control.
    sensitivity`) are those of the constrained optimum (xs, rs), its multipliers estimated:
    the active path constraints and the terminal ones held at their attained values with
    the stiffness `_STIFFNESS` (or the last penalty, if larger), the inactive ones left out.
    As exact as the penalty method's limit: to a relative 10⁻⁶ or better on the problems of
    the tests, against finite differences of the constrained optimum."""
    attained = jax.lax.stop_gradient(constraint_values(problem, xs, rs, p, num_q))
    stiffness = jnp.maximum(multipliers.penalty, _STIFFNESS)
    return Augmented(problem, multipliers.path_estimate, multipliers.terminal_estimate,
                     stiffness, attained=attained, active=multipliers.path_estimate > 0)


def constraint_values(problem: ShootingProblem, xs, rs, p, num_q):
    """(c (N, c), h (e,)) along a trajectory."""
    ts = problem.times(xs.dtype)
    path = jax.vmap(problem.path_value, in_axes=(0, 0, 0, 0, None))(
        ts[:-1], xs[:-1, :num_q], xs[:-1, num_q:], rs, p)
    return path, problem.terminal_value(ts[-1], xs[-1, :num_q], xs[-1, num_q:], p)


def iterate_with_constraints(problem: ShootingProblem, solver, x_init, p, xs, rs, num_q, *,
                             feasible: bool = False, duals=None) -> tuple[Iterate, Multipliers]:
    """The augmented Lagrangian's outer iterations about `iterate_to_optimum`, from the guess
    (xs, rs), with the first penalty and the multipliers `duals` (λ (N, c), ν (e,)), zero
    where None (a receding horizon passes its last plan's, shifted)."""
    dtype = xs.dtype
    if duals is None:
        path, terminal = jax.eval_shape(lambda: constraint_values(problem, xs, rs, p, num_q))
        duals = jnp.zeros(path.shape, dtype), jnp.zeros(terminal.shape, dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    first = Multipliers(path=duals[0], terminal=duals[1],
                        penalty=jnp.asarray(_FIRST_PENALTY, dtype), path_estimate=duals[0],
                        terminal_estimate=duals[1], violation=inf, residual=inf,
                        updates=jnp.array(0))
    # Every inner solve inside the loop, the first too, so that the solver is compiled once.
    start = initial_iterate(problem, x_init, p, xs, rs, num_q, feasible=feasible)

    def outer(state):
        iterate, multipliers, last_used, _ = state
        augmented = multipliers.problem(problem)
        # Early solves to a loose tolerance, while the multipliers are far from their values
        # (as ALTRO's intermediate tolerance): the solver's own once the violation nears its.
        loose = multipliers.residual > _NEAR * solver.constraint_tol
        tol = jnp.where(loose, jnp.maximum(_LOOSE_TOL, solver.tol), solver.tol)
        inner = iterate_to_optimum(augmented, solver, x_init, p, iterate.xs, iterate.rs,
                                   num_q, iterations=iterate.iterations, tol=tol)
        c, h = constraint_values(problem, inner.xs, inner.rs, p, num_q)
        violation = jnp.maximum(jnp.max(jnp.maximum(c, 0.0), initial=0.0),
                                jnp.max(jnp.abs(h), initial=0.0))
        mu = multipliers.penalty
        estimates = jnp.maximum(multipliers.path + mu * c, 0.0), multipliers.terminal + mu * h
        # Feasibility and complementarity together: max(c, −λ/μ) is zero only where c = 0 or
        # λ = 0 (a constraint that still pushes, λ > 0, from inside its bound is not met).
        residual = jnp.maximum(
            jnp.max(jnp.abs(jnp.maximum(c, -multipliers.path / mu)), initial=0.0),
            jnp.max(jnp.abs(h), initial=0.0))
        met = (inner.status == CONVERGED) & (residual <= solver.constraint_tol) & ~loose
        updates = multipliers.updates + 1
        stop = met | (inner.status != CONVERGED) | (updates >= _UPDATES)
        status = jnp.where(met | (inner.status != CONVERGED), inner.status, CONSTRAINTS_UNMET)
        inner = eqx.tree_at(lambda it: (it.status, it.done), inner,
                            (status, stop))
        used = eqx.tree_at(lambda m: (m.path_estimate, m.terminal_estimate, m.violation,
                                      m.residual, m.updates),
                           multipliers, (*estimates, violation, residual, updates))
        # A later solve that diverges (a penalty stiffer than the solver's model of the
        # nonlinear dynamics can follow): the last solve's trajectory is returned, reported
        # as not meeting the constraints, rather than an error for a problem that came close.
        fell = (inner.status == DIVERGED) & (multipliers.updates > 0)
        last = eqx.tree_at(lambda it: (it.status, it.done), iterate,
                           (jnp.full_like(iterate.status, CONSTRAINTS_UNMET), stop))
        inner, used = jax.tree_util.tree_map(lambda a, b: jnp.where(fell, a, b),
                                             (last, last_used), (inner, used))
        slow = residual > 0.25 * multipliers.residual
        following = Multipliers(
            path=estimates[0], terminal=estimates[1],
            penalty=jnp.where(slow, jnp.minimum(_PENALTY_GROWTH * mu, _LARGEST_PENALTY), mu),
            path_estimate=estimates[0], terminal_estimate=estimates[1], violation=violation,
            residual=residual, updates=updates)
        return inner, following, used, stop

    # (the last multipliers used are returned with the iterate: its augmented problem). The
    # condition reads two loop-carried values, the count beside the flag that already holds
    # it: where it reads one, XLA's trip-count analysis copies the computation of its update,
    # here every inner solve, at each pass (`solver.iterate_to_optimum`).
    iterate, _, used, _ = jax.lax.while_loop(
        lambda state: ~state[3] & (state[1].updates < _UPDATES), outer,
        (start, first, first, jnp.array(False)))
    return iterate, used


def unconstrained_multipliers(num_nodes, dtype) -> Multipliers:
    """The state of a problem without constraints (nothing to report: no multipliers)."""
    path, empty = jnp.zeros((num_nodes, 0), dtype), jnp.zeros((0,), dtype)
    return Multipliers(path=path, terminal=empty, penalty=jnp.zeros((), dtype),
                       path_estimate=path, terminal_estimate=empty,
                       violation=jnp.zeros((), dtype), residual=jnp.zeros((), dtype),
                       updates=jnp.array(0))
