"""Failures of a solve: detected in the step-size controller where the equations of motion
fail, diagnosed after the solve from the last state reached, and raised with jaxdyn's account
of their cause (a singular mass matrix, a coordinate singularity, a step budget run out)."""

from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._chunking import chunked_vmap
from .._dynamics import AbstractDynamics, equations_of_motion, formed_mass_matrix
from .._errors import error_if
from .._solution import RESULTS


MAX_STEPS = (
    "The solver took the maximum number of steps (max_steps) before reaching t1: pass a "
    "larger `max_steps` (the estimate below scales the steps taken to the whole interval), "
    "loosen `rtol`/`atol`, or shorten the interval. If the steps are tiny, check the system: "
    "stiff motion (a huge stiffness; see `jaxdyn.stiffness` and an implicit solver such as "
    "diffrax.Kvaerno5) or a near-singular mass matrix (see `mass_matrix_condition`)."
)
MAX_STEPS_ILL_CONDITIONED = (
    "The solver took the maximum number of steps (max_steps) before reaching t1, and the mass "
    "matrix is ill-conditioned where it stopped (condition number below): the motion is "
    "approaching a singular configuration of the coordinates (a coordinate singularity: a "
    "polar angle near its pole, Euler angles near gimbal lock, r → 0 in polar coordinates), "
    "where some speeds grow without bound and the steps shrink. Remedy: coordinates without a "
    "singularity there (quaternions, as in jaxdyn.Spherical and jaxdyn.Free joints; other "
    "angles) or Cartesian coordinates with constraints (jaxdyn.Constrained). Follow "
    "`mass_matrix_condition` along the trajectory to see it coming."
)
COORDINATE_SINGULARITY = (
    "The mass matrix became singular along the motion, though it is positive definite at the "
    "initial state. Most often the motion reached a singular configuration of the coordinates "
    "(a coordinate singularity: a polar angle at its pole, Euler angles at gimbal lock, r = 0 "
    "in polar coordinates); remedy: coordinates without a singularity there (quaternions, as "
    "in jaxdyn.Spherical and jaxdyn.Free joints; other angles) or Cartesian coordinates with "
    "constraints (jaxdyn.Constrained). Otherwise the kinetic energy is not positive definite "
    "in the speeds everywhere (check its terms). Follow `mass_matrix_condition` along the "
    "trajectory to see it coming."
)
NEWTON = (
    "The implicit step's Newton iteration did not converge (the structure-preserving solver's "
    "`max_newton_steps`): the step is too long for the motion there. Take a smaller `dt0`."
)
DISTANT_ROOT = (
    "The variational integrator's implicit step converged to a solution far from the motion "
    "(the discrete Euler–Lagrange equations have other roots, which a step too long for the "
    "motion reaches): take a smaller `dt0`, about a tenth of the fastest period or less."
)


def raise_failures(ts, result, failure, start, t1, last, max_steps, condition,
                    structure_preserving):
    """`ts`, or an error whose first line is jaxdyn's account of why the solve failed.

    Where the mass matrix is singular at the failure but regular at the start, or the solve
    ran out of steps where it is ill-conditioned, the cause named is the configuration (a
    coordinate singularity). `condition(t, q, u)`, the mass matrix's condition number, is
    evaluated only on failure."""
    t0 = start[0]
    t_last = last[0]

    def checks():  # evaluated only in the branch taken on failure
        # Both states in one batched call, formed once for every message that names them
        # (ANYmal-C in contact under a caller's jit: 2 800 fewer lines of LLVM IR).
        conditions = jax.vmap(condition)(*jax.tree_util.tree_map(
            lambda a, b: jnp.stack([jnp.asarray(a), jnp.asarray(b)]), start, last))
        singular = result == RESULTS.singular_mass_matrix
        regular_at_start = conditions[0] < _ILL_CONDITIONED
        out_of_steps = result == RESULTS.max_steps_reached
        ill = conditions[1] >= _ILL_CONDITIONED
        covered = jnp.abs(t_last - t0)
        budget = {"t reached": t_last, "max_steps": jnp.asarray(max_steps),
                  "steps the whole interval needs (estimate)": jnp.ceil(
                      max_steps * jnp.abs(t1 - t0) / jnp.where(covered > 0, covered, 1)),
                  "mass matrix condition number (start, last)": conditions}
        listed = [(singular & regular_at_start, COORDINATE_SINGULARITY, failure)]
        listed += [(result == code, RESULTS[code], failure) for code in _EQUATION_FAILURES]
        listed += [(out_of_steps & ill, MAX_STEPS_ILL_CONDITIONED, budget),
                   (out_of_steps, MAX_STEPS, budget)]
        if structure_preserving:  # the codes of its implicit step (`VariationalIntegrator`)
            listed += [(result == RESULTS.nonlinear_max_steps_reached, NEWTON, {"t": t_last}),
                       (result == RESULTS.nonlinear_divergence, DISTANT_ROOT, {"t": t_last})]
        # a hybrid solve out of events: where it stopped (the event past the budget)
        listed += [(result == RESULTS.max_events_reached, RESULTS[RESULTS.max_events_reached],
                    last)]
        listed += [(result == RESULTS._name_to_item[name], RESULTS[RESULTS._name_to_item[name]],
                    None) for name in RESULTS._name_to_item if name not in handled]
        return listed

    handled = _HANDLED | ({"nonlinear_max_steps_reached", "nonlinear_divergence"}
                          if structure_preserving else set())
    # One branch for every failure: its messages share the mass matrix's condition numbers.
    return error_if(ts, checks, failed=result != RESULTS.successful)


@eqx.filter_jit  # traced once per solve's compilation, though the messages ask for it 4 times
def mass_matrix_condition(dynamics, p, t, q, u):
    """κ(M) at one state (∞ where M is not positive definite), for failure messages only.

    M is formed in the program and its eigenvalues found on the host (NumPy): only a failed
    solve asks for them, and an eigensolver in the program would cost every solve its
    compilation (and the first one in a process LAPACK's set-up, ~0.1 s)."""
    mass_matrix = jax.lax.stop_gradient(formed_mass_matrix(dynamics, t, q, u, p))
    return jax.pure_callback(_host_condition, jax.ShapeDtypeStruct((), mass_matrix.dtype),
                             mass_matrix, vmap_method="expand_dims")


def _host_condition(mass_matrix):
    mass_matrix = np.asarray(mass_matrix)
    out = np.full(mass_matrix.shape[:-2], np.inf, mass_matrix.dtype)
    for index in np.ndindex(out.shape):
        matrix = mass_matrix[index]
        if np.all(np.isfinite(matrix)):
            eigenvalues = np.linalg.eigvalsh(matrix)
            if eigenvalues[0] > 0:
                out[index] = eigenvalues[-1] / eigenvalues[0]
    return out


# A mass matrix this ill-conditioned loses half the digits of the accelerations.
_ILL_CONDITIONED = 1e8

_EQUATION_FAILURES = (RESULTS.singular_mass_matrix, RESULTS.singular_constraints,
                      RESULTS.nonfinite_forcing, RESULTS.nonfinite_equations)
_HANDLED = {"successful", "max_steps_reached", "max_events_reached",
            "singular_mass_matrix", "singular_constraints", "nonfinite_forcing",
            "nonfinite_equations"}


# -- failures of the equations of motion: detected in the step-size controller, diagnosed after
# the solve -------------------------------------------------------------------------------------


def guard(controller):
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return GuardedAdaptive(controller)
    return _GuardedFixed(controller)


def _guard_init(controller, terms, t0, t1, y0, dt0, args, func, error_order):
    layout = solve_arguments(args)[3]
    if dt0 is None and layout is not None and layout.span is not None:
        # A solve in s = (t − t₀)/(t₁ − t₀) (`jaxdyn._integrate.solve`): diffrax's first step
        # (E. Hairer, S. P. Nørsett, G. Wanner, Solving Ordinary Differential Equations I,
        # §II.4) is not invariant under a scaling of time, so it is chosen in the time
        # τ = |t₁ − t₀| s, as diffrax chooses it in t (a backward solve: in −t).
        length = jnp.abs(layout.span)
        zero = length == 0
        inverse = jnp.where(zero, 0, 1 / jnp.where(zero, 1, length))
        direction = jnp.sign(layout.span)

        def func_in_t(terms, tau, y, args):  # (`func` gives dy/dt: the term's `vf`)
            return jax.tree_util.tree_map(lambda rate: direction * rate,
                                          func(terms, tau * inverse, y, args))

        tau_next, state = controller.init(terms, t0, length, y0, None, args, func_in_t,
                                          error_order)
        t_next = t0 + jnp.where(zero, 1, (tau_next - t0) * inverse)
    else:
        t_next, state = controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        t_next = jnp.minimum(t_next, t0 + _step_bound(args, t0, y0))
    return t_next, (state, jnp.abs(t1 - t0), jnp.array(False))


def solve_arguments(args):
    """(dynamics, p, factorisation, layout) of the solve's arguments (those of the plain
    solve, or of the forward-sensitivity solve, whose state is y then the sensitivities);
    Nones where they are not a jaxdyn solve's."""
    if isinstance(args, tuple) and args and isinstance(args[0], tuple) and args[0] \
            and isinstance(args[0][0], AbstractDynamics):
        args = args[0]  # (the sensitivity solve's: ((dynamics, p, ...), directions))
    if not (isinstance(args, tuple) and len(args) >= 4
            and isinstance(args[0], AbstractDynamics)):
        return None, None, None, None
    return args[:4]


def _step_bound(args, t, y):
    """The longest next step, in diffrax's time, the dynamics allow from (t, y)
    (`AbstractDynamics.step_bound`: contacts not yet touching must not be stepped over)."""
    dynamics, p, _, layout = solve_arguments(args)
    if dynamics is None or layout is None or not dynamics.bounds_steps:
        return jnp.inf
    if layout.flat:  # (y, or y then the sensitivities: y's q and u come first)
        q, u = y[:layout.n], y[layout.n:layout.n + layout.m]
    else:
        q, u = y
    # A tree's kinematics, like its other recursions, batch in chunks under `vmap`
    # (`jaxdyn._chunking`): ANYmal-C's bound over 256 states, 1.4-2.2 µs per state against
    # 1.9-3.2 vmapped whole.
    return layout.duration(chunked_vmap(dynamics.step_bound)(layout.time(t), q, u, p)).astype(
        jnp.result_type(t))


def _guard_adapt(controller, can_shrink, t0, t1, y0, y1_candidate, args, y_error,
                 error_order, guard_state):
    """The wrapped controller's decision, unless the step met non-finite equations and cannot
    shrink further (the step is within round-off of zero, or the steps are fixed): then the
    step is rejected and the solve stops (`stalled`), keeping the last state it reached."""
    state, span, _ = guard_state
    keep, next_t0, next_t1, made_jump, state, result = controller.adapt_step_size(
        t0, t1, y0, y1_candidate, args, y_error, error_order, state)
    if can_shrink:  # the next step stops short of contacts it could otherwise step over
        bound = _step_bound(args, next_t0, jax.tree_util.tree_map(
            lambda a, b: jnp.where(keep, a, b), y1_candidate, y0))
        next_t1 = jnp.minimum(next_t1, next_t0 + bound)
    nonfinite = ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(x))
                                    for x in jax.tree_util.tree_leaves(y1_candidate)]))
    if can_shrink:
        eps = jnp.finfo(jnp.result_type(t0)).eps
        scale = jnp.maximum(jnp.maximum(jnp.abs(t0), jnp.abs(t1)), span)
        stalled = nonfinite & (jnp.abs(t1 - t0) <= 64 * eps * scale)
    else:
        stalled = nonfinite
    # diffrax's own code for "the step size went to zero"; `simulate` replaces it by the cause.
    result = diffrax.RESULTS.where(stalled, diffrax.RESULTS.dt_min_reached, result)
    next_t0 = jnp.where(stalled, t0, next_t0)  # time stays with the state that is kept
    next_t1 = jnp.where(stalled, t1, next_t1)
    return keep & ~stalled, next_t0, next_t1, made_jump, (state, span, stalled), result


class GuardedAdaptive(diffrax.AbstractAdaptiveStepSizeController):
    """An adaptive step-size controller that stops the solve where the equations fail."""

    controller: diffrax.AbstractAdaptiveStepSizeController

    def __init__(self, controller: diffrax.AbstractAdaptiveStepSizeController):
        # Written out because diffrax declares rtol, atol and norm as `eqx.AbstractVar`s, which
        # a type checker takes for arguments of the generated `__init__` (they are properties
        # here: the wrapped controller's).
        self.controller = controller

    @property
    def rtol(self):
        return self.controller.rtol

    @property
    def atol(self):
        return self.controller.atol

    @property
    def norm(self):
        return self.controller.norm

    def wrap(self, direction):
        # diffrax declares `wrap` to return the base class; an adaptive controller's returns
        # its own type.
        return GuardedAdaptive(cast(diffrax.AbstractAdaptiveStepSizeController,
                                     self.controller.wrap(direction)))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return _guard_init(self.controller, terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        return _guard_adapt(self.controller, True, t0, t1, y0, y1_candidate, args, y_error,
                            error_order, controller_state)


class _GuardedFixed(diffrax.AbstractStepSizeController):
    """A fixed-step controller that stops the solve where the equations fail."""

    controller: diffrax.AbstractStepSizeController

    def wrap(self, direction):
        return _GuardedFixed(self.controller.wrap(direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return _guard_init(self.controller, terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        return _guard_adapt(self.controller, False, t0, t1, y0, y1_candidate, args, y_error,
                            error_order, controller_state)


def diagnose(dynamics, p, factorisation, t, q, u, stalled, direction, span):
    """Why and where the equations failed, from the last state the solve reached.

    That state is regular or (with fixed steps) the failing one itself. Otherwise the failure
    lies within round-off of it along the motion: probe explicit-Euler states at steps that
    double from a few ulps until the equations fail. Runs only when the solve stalled; it
    costs one evaluation per solve otherwise.

    Returns (the RESULTS code, (t, q, u) where the equations fail).
    """
    t, q, u = jax.lax.stop_gradient((t, q, u))
    base = 4 * jnp.finfo(t.dtype).eps * jnp.maximum(jnp.abs(t), span)

    # One evaluation in the loop: the first at the last state itself (h = 0), whose rates
    # and accelerations (made finite) direct the probes after it.
    def searching(carry):
        k, _, _, singular, nonfinite, finite = carry
        return (k == 0) | (stalled & ~(singular | nonfinite | ~finite) & (k <= 64))

    def probe(carry):
        k, _, direction_of_motion, *_ = carry
        h = jnp.where(k == 0, 0, direction * base * 2.0 ** (k - 1)).astype(t.dtype)
        rates, accelerations = direction_of_motion
        state = (t + h, q + h * rates, u + h * accelerations)
        rates_k, accelerations_k, singular, nonfinite = equations_of_motion(dynamics, *state, p,
                                                                            factorisation)
        finite = jnp.all(jnp.isfinite(rates_k)) & jnp.all(jnp.isfinite(accelerations_k))
        direction_of_motion = jax.tree_util.tree_map(
            lambda new, old: jnp.where(k == 0, jnp.where(jnp.isfinite(new), new, 0), old),
            (rates_k, accelerations_k), direction_of_motion)
        return k + 1, state, direction_of_motion, singular, nonfinite, finite

    start = (jnp.array(0), (t, q, u), (jnp.zeros_like(q), jnp.zeros_like(u)),
             jnp.array(False), jnp.array(False), jnp.array(True))
    _, (t_fail, q_fail, u_fail), _, singular, nonfinite, _ = jax.lax.while_loop(
        searching, probe, start)
    by_constraints = singular & dynamics.singular_constraints(t_fail, q_fail, u_fail, p)
    code = RESULTS.where(singular, RESULTS.singular_mass_matrix,
                         RESULTS.where(nonfinite, RESULTS.nonfinite_forcing,
                                       RESULTS.nonfinite_equations))
    code = RESULTS.where(by_constraints, RESULTS.singular_constraints, code)
    return code, (t_fail, q_fail, u_fail)
