"""`simulate`: the single jit-compiled entry point that integrates any dynamics with diffrax."""

import contextlib
import functools

import diffrax
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core

from .. import _xla
from .._compile import filter_jit
from .._dynamics import (
    AbstractDynamics,
    constant_mass_matrix,
    mass_matrix_blocks,
    straight_line_size,
)
from .._errors import check_finite, library_checks_as_nan, reports_state
from .._linalg import factorise
from .._runge_kutta import UnrolledStages
from .._sensitivities import MAX_FORWARD, differentiable_size
from .._solution import RESULTS, Solution, promoted
from .._static_indexing import check_static_indexing
from .._state import check_parameter_dtypes, check_vector, numbers_as_arrays, state_dtype
from .._variational import AbstractStructurePreserving
from .failures import diagnose, guard, mass_matrix_condition, raise_failures
from .options import (
    check_tolerances,
    checked_save_times,
    checked_tolerances,
    fixed_steps,
    save_time_checks,
    step_budget,
    tolerance_checks,
)
from .events import MAX_EVENTS
from .guards import can_rest, check_events
from .solve import Layout, Projected, solve, vector_field


@reports_state(block=False)  # _simulate's results are ready when it returns
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
    save: tuple[str, ...] = ("q", "u", "qd"),
    solver: diffrax.AbstractSolver = diffrax.Dopri8(),
    rtol: float | None = None,
    atol: float | None = None,
    dt0=None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    max_steps: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
    inputs=None,
    events=None,
    max_events: int = MAX_EVENTS,
) -> Solution:
    r"""Integrate q̇ = K u, M u̇ = f (+ B r) from (t0, q0, u0) to t1:

    $$\dot q = K(t, q)\, u, \qquad M(t, q)\, \dot u = f(t, q, u) \;(+\, B(q)\, r),
      \qquad q(t_0) = q_0, \quad u(t_0) = u_0,$$

    with $K$ the kinematic map from speeds to coordinate rates (the identity for a
    `Lagrangian`, whose speeds are $\dot q$), $M$ the mass matrix, $f$ the forcing and $B r$
    the inputs of a `jaxdyn.Controlled` system.

    **Arguments:**

    - `dynamics`: any `jaxdyn.AbstractDynamics` (`Lagrangian`, `GibbsAppell`, `Kane`).
    - `q0`, `u0`: initial coordinates (n,) and speeds (m,) (for a `Lagrangian`, u0 = q̇0).
    - `p`: parameters, any pytree; differentiate the result with respect to it freely.
    - `t0`, `t1`: the interval; `t1 < t0` integrates backwards.
    - `ts`: times to save at; if None only t1 is saved.
    - `dense`: keep the dense interpolant (`Solution.evaluate`).
    - `save`: which of "q", "u", "qd" to save at `ts`; the others are None in the solution.
      Saving less interpolates and stores less in every step (and "qd" = K(q) u is only
      formed when asked for). For a `jaxdyn.Constrained` formulation, "constraints" also
      saves the multipliers, constraint forces and violations (`Solution.constraints`); for
      a `jaxdyn.Controlled` system, "inputs" saves the inputs r applied (`Solution.inputs`).
    - `solver`, `rtol`, `atol`, `dt0`, `stepsize_controller`: the diffrax solver and step-size
      control. Defaults: `Dopri8` (8th order) with a `PIDController` at rtol = atol = 1e-10 in
      float64 (1e-6 in float32, near what that precision can hold) and an automatically chosen
      first step. Mechanics is smooth, so a high order pays (see the solver guide in the
      README and benchmarks/bench_work_precision.py). Pass `solver=diffrax.Tsit5()` and
      looser tolerances for speed, or a fixed `dt0` with
      `stepsize_controller=diffrax.ConstantStepSize()` for fixed-step integration. For long
      horizons, `jaxdyn.VariationalIntegrator()` (any Lagrangian) or `jaxdyn.StormerVerlet()`
      (separable systems) with a fixed step `dt0` keep the energy error bounded; for stiff
      systems use an implicit solver such as `diffrax.Kvaerno5()` (see `jaxdyn.stiffness`).
    - `max_steps`: step budget; exhausting it is an error that estimates the steps the whole
      interval needs (or `RESULTS.max_steps_reached` with `throw=False`). Default: 16⁴ =
      65 536, or with fixed steps (concrete t0, t1, dt0) the number of steps the interval
      takes, if that is more (rounded up to a power of two, so that nearby intervals reuse
      the compiled solve). Called eagerly (not under `jax.jit` or `vmap`), an
      adaptive solve that exhausts the default budget is run again once with 8× the budget,
      so that a long interval is integrated whole; the error follows only if that runs out
      too.
    - `adjoint`: how to differentiate. The default (None), when q0, u0 and p hold at most
      16 floating-point entries and `dense` is False: forward sensitivities. The solve
      carries ∂y/∂x for the entries being differentiated (one tangent each, vectorised) and
      the derivative is applied as that matrix, so that `jax.grad`, `jax.jacrev`, `jax.jvp`
      and `jax.jacfwd` all work and cost a small multiple of one solve. Otherwise diffrax's
      `RecursiveCheckpointAdjoint`: reverse mode through the discrete solve with about
      √(2 max_steps) checkpoints, a memory bound that also holds under `vmap` (forward mode
      then needs `adjoint=diffrax.ForwardMode()`). Both differentiate the discrete solve
      (exactly what finite differences of the solve give). Any diffrax adjoint may be
      passed; for one long solve, `RecursiveCheckpointAdjoint(checkpoints=...)` with a
      checkpoint per step avoids recomputation. Measured costs: benchmarks/LOG.md.
    - `throw`: raise on failure; if False, inspect `Solution.result` (NaN or inf in the
      initial state or parameters then gives `RESULTS.nonfinite_state_or_parameters` and NaN
      states, so that one bad member does not stop a vmapped batch).
    - `inputs`: for a system with control inputs (`jaxdyn.Controlled`, also inside a
      `Constrained`): an array r, a signal r(t) (a function of t, or a diffrax path such as
      `diffrax.LinearInterpolation`) or a policy π(t, q, u, p); None keeps the system's own.
      Derivatives flow through the inputs' arrays (a policy's weights held as module fields).
    - `events`: a hybrid system's events, or a list of them: `jaxdyn.Event` (a guard
      g(q, u, p) and a reset, or a stop) and `jaxdyn.UnilateralContact` (gaps φ(q, p) ≥ 0
      with impacts by Newton's law). Each zero crossing of a guard is located to the last
      float by regula falsi on the step's interpolant, the state jumps, and the solve
      restarts from there; `Solution.events` records every event (`EventRecord`).
      Derivatives pass through the event times (implicit function theorem) and the jumps;
      by forward sensitivities (the default for few entries) they are carried along each
      segment by the sensitivity equations and mapped across each event by its saltation
      matrix, which agrees with the discrete solve's derivative to the solver's tolerance.
      Not with `dense=True`.
    - `max_events`: the most events handled (static: the solve is a loop of `max_events` + 1
      segments). The solve stops at the event past it, with `RESULTS.max_events_reached`.

    **Returns:** a `jaxdyn.Solution`.

    Numbers (t0, t1, ts, tolerances, dt0, and every float or int in `p`) are traced, so
    changing them reuses the compiled solve. The initial state and parameters are checked for
    NaN/inf. The right-hand side carries no checks: where the mass matrix is singular or the
    forcing not finite it returns NaN, the solver rejects the step and shrinks it, and when no
    step however small gets past a state the solve stops and names the state where the
    equations fail (`RESULTS.singular_mass_matrix`, `nonfinite_forcing`,
    `nonfinite_equations`).
    """
    if not _is_dynamics(type(dynamics)):
        raise ValueError(f"dynamics must be a jaxdyn.AbstractDynamics (e.g. "
                         f"jaxdyn.Lagrangian), got {type(dynamics).__name__}.")
    dtype = state_dtype(q0, u0)
    if inputs is not None:
        dynamics = dynamics.with_inputs(inputs)
    if _structure_preserving(type(solver)):
        stepsize_controller = fixed_steps(solver, rtol, atol, dt0, stepsize_controller)
    elif stepsize_controller is None:  # defaults filled in here, so that they are traced too
        default = 1e-10 if np.dtype(dtype).itemsize == 8 else 1e-6
        rtol = default if rtol is None else rtol
        atol = default if atol is None else atol
    elif rtol is not None or atol is not None:
        raise ValueError("Pass rtol/atol or a stepsize_controller, not both.")
    check_tolerances(rtol, atol)
    default_budget = max_steps is None
    max_steps = step_budget(max_steps, t0, t1, dt0, stepsize_controller)
    numbers = numbers_as_arrays((p, t0, t1, ts, rtol, atol, dt0), dtype)
    # Few arguments: binding them is part of the per-call cost.
    save = (save,) if isinstance(save, str) else tuple(save)
    _check_save(save, dynamics)
    # The entries a derivative can reach are the traced ones (of a caller's jax.grad, jit or
    # vmap), not concrete arrays closed over: a robot's hundreds of inertial parameters when
    # only q0 is differentiated. Counted with the inputs' arrays (a policy's weights).
    if events is not None:
        # Coefficients given as Python numbers (a restitution, a friction coefficient) are
        # traced, so that a new value reuses the compiled solve.
        events = jax.tree_util.tree_map(
            lambda x: numbers_as_arrays(x, dtype) if isinstance(x, float) else x,
            check_events(events, max_events))
        if dense:
            raise ValueError("dense=True is not available with events: the solution is "
                             "piecewise, one solve per segment between events.")
    # (Outside any trace nothing is traced: none to count, and the walk over the system's
    # formulations for its inputs, 30-70 µs of an eager call, is skipped.)
    reachable = 0 if jax_core.trace_state_clean() else differentiable_size([
        x for x in jax.tree_util.tree_leaves(
            (q0, u0, numbers[0], dynamics.applied_inputs(), events))
        if isinstance(x, jax.core.Tracer)])

    def run(budget, lean):
        # (The modules apart from the plain options, which the dispatch then reads as one
        # tree: `jaxdyn._compile.filter_jit`.)
        return _simulate(dynamics, solver, stepsize_controller, adjoint, events, q0, u0,
                         numbers, (dense, save, budget, throw, reachable, lean, max_events))

    # (Outside any trace every value is known: the walk over the leaves is skipped.)
    if not jax_core.trace_state_clean() and not all(
            _concrete_value(x) is not None
            for x in jax.tree_util.tree_leaves((dynamics, q0, u0, numbers))):
        return run(max_steps, lean=False)  # staged into a caller's program: diagnoses itself
    # Called eagerly (values known, also under an un-jitted jax.grad or jax.jvp, whose
    # tracers carry them): first a lean program, without the diagnosis of failures (which locates
    # a singular mass matrix, tells its cause and formats the message: as much to compile as
    # the equations again). Only when the solve fails is the full program compiled and run,
    # from the same inputs, to the same steps.
    solution = run(max_steps, lean=True)
    if _succeeded(solution):
        return solution
    if (default_budget and int(solution.num_steps) >= max_steps
            and (stepsize_controller is None
                 or isinstance(stepsize_controller, diffrax.AbstractAdaptiveStepSizeController))):
        # The default budget follows the interval: one more try with 8× as many steps.
        max_steps *= 8
        solution = run(max_steps, lean=True)
        if _succeeded(solution):
            return solution
    return run(max_steps, lean=False)


@functools.cache
def _is_dynamics(cls) -> bool:
    """Whether objects of this type are `AbstractDynamics` (by type: an abstract class's
    check costs ~1 µs of an eager call)."""
    return issubclass(cls, AbstractDynamics)


@functools.cache
def _structure_preserving(solver_type) -> bool:
    """Whether a solver of this type is a structure-preserving method (by type: an abstract
    class's check costs ~5 µs of an eager call)."""
    return issubclass(solver_type, AbstractStructurePreserving)


def _succeeded(solution) -> bool:
    """Whether every member of an eager solve succeeded (read on the host, no dispatch)."""
    result = _concrete_value(solution.result._value)
    assert result is not None  # (called with values)
    # (read as a NumPy array: a JAX array's own `item` costs ~5 µs more)
    result = np.asarray(result)
    if result.ndim == 0:  # (one solve: its code read as a number)
        return result.item() == _SUCCESSFUL
    return not np.any(result != _SUCCESSFUL)


_SUCCESSFUL = int(RESULTS.successful._value)


def _concrete_value(x):
    """`x`'s value where it is known while tracing: `x` itself, or the value a tracer of an
    un-jitted derivative carries (`jax.grad`, `jax.jvp`); None under `jax.jit` or `vmap`."""
    if isinstance(x, jax.core.Tracer):
        return x.to_concrete_value()
    return x


@filter_jit
def _simulate(dynamics, solver, stepsize_controller, adjoint, events, q0, u0, numbers,
              options):
    # A lean program holds no host callback (JAX's persistent compilation cache keeps it):
    # its failures, diffrax's checks of arguments included, send the call on to the full
    # program. (Set while tracing, which is when the checks are written.)
    with library_checks_as_nan() if options[5] else contextlib.nullcontext():
        return _simulate_traced(dynamics, solver, stepsize_controller, adjoint, events, q0,
                                u0, numbers, options)


def _simulate_traced(dynamics, solver, stepsize_controller, adjoint, events, q0, u0, numbers,
                     options):
    p, t0, t1, ts, rtol, atol, dt0 = numbers
    dense, save, max_steps, throw, reachable, lean, max_events = options
    q0, u0, p, t0, t1 = _checked_start(dynamics, q0, u0, p, t0, t1, solver)
    # The lean program (called with values) carries no check that calls the host: its
    # invalid arguments only make it fail, and the full program, run then, names them. So it
    # holds no host callback, which also lets JAX's persistent compilation cache keep it.
    invalid = []
    if lean:
        invalid += [pred for pred, _ in tolerance_checks(rtol, atol)]
    else:
        rtol, atol = checked_tolerances(rtol, atol)
    if throw and not lean:
        q0, u0, p = check_finite(q0=q0, u0=u0, p=p)
        nonfinite_input = None
    else:  # its own result code, so that a vmapped batch is not stopped by one member
        q0, u0, p, nonfinite_input = _finite_stand_in(q0, u0, p)
    # A mass matrix of the parameters alone is factored once, here, not at every step (in
    # straight-line code it folds to a few operations per step anyway).
    factorisation = None
    size = straight_line_size(dynamics, t0, q0, u0, p)
    if size is None and constant_mass_matrix(dynamics, t0, q0, u0, p):
        factorisation = factorise(dynamics.mass_matrix(t0, q0, u0, p), unrolled=False,
                                  blocks=mass_matrix_blocks(dynamics, t0, q0, u0, p))
    layout = Layout(q0.shape[0], not isinstance(solver, AbstractStructurePreserving),
                    u0.shape[0])
    saveat, keep_q, keep_u = _save_at(save, layout, ts, t0, t1, dense, invalid if lean
                                      else None)
    if stepsize_controller is None:
        assert rtol is not None and atol is not None  # `simulate` filled in the defaults
        stepsize_controller = diffrax.PIDController(rtol=rtol, atol=atol)
    forward = adjoint is None and not dense and reachable <= MAX_FORWARD
    solver = _stepper(solver, dynamics, size, forward, events is not None and can_rest(
        events, dynamics, t0, q0, u0, p))
    solution = solve(solver, t0, t1, dt0, layout.join(q0, u0),
                     (dynamics, p, factorisation, layout), saveat,
                     guard(stepsize_controller), adjoint, max_steps, forward=forward,
                     events=events, max_events=max_events)
    # Saved (`saveat`): the states (requested, last), their times and the controller's state.
    assert solution.ys is not None and solution.ts is not None
    assert solution.controller_state is not None
    (q, u), last = solution.ys
    q_last, u_last = layout.split(last)
    projection = dynamics.state_projection()
    if projection is not None and keep_q and keep_u:
        # Saved states between steps are interpolated, off the constraints by the local
        # error: projected like the steps' ends.
        q, u = jax.vmap(projection, in_axes=(0, 0, 0, None))(solution.ts[0], q, u, p)
    t_last = solution.ts[1][0]
    stalled = solution.controller_state[-1]
    if lean:  # a failure is diagnosed by running the full program again
        result = RESULTS.where(stalled, RESULTS.nonfinite_equations,
                               promoted(solution.result))
    else:
        result, failure = diagnose(dynamics, p, factorisation, t_last, q_last[0], u_last[0],
                                    stalled, jnp.sign(t1 - t0), jnp.abs(t1 - t0))
        result = RESULTS.where(stalled, result, promoted(solution.result))
    if invalid:  # (lean only) the full program, run on failure, names the argument
        assert nonfinite_input is not None  # a lean program stands in for non-finite inputs
        nonfinite_input = nonfinite_input | jnp.any(jnp.stack(invalid))
    if nonfinite_input is not None:
        result = RESULTS.where(nonfinite_input, RESULTS.nonfinite_state_or_parameters, result)
        q, u = (None if x is None else jnp.where(nonfinite_input, jnp.nan, x) for x in (q, u))
    ts_out = solution.ts[0]
    event_record = getattr(solution, "events", None)  # a hybrid solve's (`HybridSolution`)
    if throw and not lean:
        condition = functools.partial(mass_matrix_condition, dynamics, p)
        # Every output a caller may read alone is tied to the check: the states and the
        # records formed from them, the times, the record of events, the dense solution
        # (under a caller's `jax.jit` XLA keeps only what the outputs read, and a check tied
        # to none of them would be dropped: a failed solve's last state returned silently).
        # (of the dense solution, its interpolant's times and states)
        arrays, rest = eqx.partition(solution, eqx.is_inexact_array) if dense else (None, None)
        ts_out, event_record, q, u, arrays = raise_failures(
            (ts_out, event_record, q, u, arrays), result, failure,
            (t0, q0, u0), t1, (t_last, q_last[0], u_last[0]), max_steps, condition,
            isinstance(solver, AbstractStructurePreserving))
        solution = eqx.combine(arrays, rest) if dense else solution
    return _solution(dynamics, p, save, solution, ts_out, q, u, result, layout, event_record,
                     dense)


def _checked_start(dynamics, q0, u0, p, t0, t1, solver):
    """(q0, u0, p, t0, t1) checked (vectors of one dtype, the system's shapes, parameters of
    that dtype) and strongly typed in the state's dtype."""
    q0 = check_vector(q0, "q0")
    u0 = check_vector(u0, "u0")
    if q0.dtype != u0.dtype:
        raise ValueError(
            f"q0 and u0 must share a dtype, got {q0.dtype} and {u0.dtype}. Use float64 "
            "(jax.config.update('jax_enable_x64', True)) for accurate mechanics."
        )
    q0 = check_vector(dynamics.initial_coordinates(q0, u0, p), "q0")
    dtype = q0.dtype
    # Strongly typed (`jnp.full(n, 0.3)` is weakly typed): as the solve's state is, so that
    # the equations traced for the shape check are the solve's (a weak type retraces them).
    q0, u0 = jnp.asarray(q0, dtype), jnp.asarray(u0, dtype)
    check_parameter_dtypes(p, dtype)
    # The parameters too: the checks after this one return them strongly typed, and a
    # weakly typed leaf (a Python float passed through a caller's `jax.jit`) would retrace
    # the equations for the solve (ANYmal in contact: 0.6-0.9 s of a first call).
    p = jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, x.dtype) if eqx.is_inexact_array(x) else x, p)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    _check_shapes(dynamics, t0, q0, u0, p)
    if isinstance(solver, AbstractStructurePreserving):
        solver.check(dynamics, t0, q0, u0, p)
    return q0, u0, p, t0, t1


def _save_at(save, layout, ts, t0, t1, dense, invalid):
    """(diffrax's `SaveAt`, whether q and u are kept): the requested saves (`ts`, or t1) of
    what `save` needs, and the last state reached, from which a failure is diagnosed. The
    save times are checked, or (a lean program: `invalid` a list) their checks appended to
    `invalid`."""
    records = [name for name in save if name not in _STATE_QUANTITIES]
    keep_q = bool(records) or "q" in save or "qd" in save
    keep_u = bool(records) or "u" in save or "qd" in save

    def observe(t, y, args):
        q, u = layout.split(y)
        return q if keep_q else None, u if keep_u else None

    if ts is None:
        requested = diffrax.SubSaveAt(t1=True, fn=observe)
    else:
        ts = jnp.asarray(ts, t0.dtype)
        if invalid is not None:
            invalid += [pred for pred, _ in save_time_checks(ts, t0, t1)]
        else:
            ts = checked_save_times(ts, t0, t1)
        requested = diffrax.SubSaveAt(ts=ts, fn=observe)
    saveat = diffrax.SaveAt(subs=[requested, diffrax.SubSaveAt(t1=True)], dense=dense,
                            controller_state=True)
    return saveat, keep_q, keep_u


def _stepper(solver, dynamics, size, forward, resting_field):
    """The solver as it steps: an explicit Runge–Kutta method's stages written out for small
    equations differentiated forward (`UnrolledStages`) where XLA would run diffrax's loop
    over them kernel by kernel (`LOOPS_RUN_WHOLE` false: off the CPU, or JAX started before
    `import jaxdyn`), unless XLA is asked to compile fast (`jax_disable_most_optimizations`);
    the step projected onto the constraints where the system has a projection
    (`Projected`)."""
    # Events whose contacts can rest put the held-force solve into the vector field, and a
    # hybrid solve also evaluates the field in its root find, its guards' rates and its
    # saves: written out, the stages multiply that program (a particle under rigid contact
    # with friction, Dopri8: 12 → 6 s of XLA, run time 1.3 → 1.1 ms as a loop).
    if (isinstance(solver, diffrax.AbstractERK) and solver.scan_kind is None
            and size is not None and size <= WRITTEN_OUT_STAGES_MAX and forward
            and not resting_field
            and not (LOOPS_RUN_WHOLE and jax.default_backend() == "cpu")
            and not jax.config.read("jax_disable_most_optimizations")):
        # The same steps, without a loop over the stages. Not for reverse mode, whose pass
        # through written-out stages costs 3× diffrax's loop, nor for large equations
        # (`WRITTEN_OUT_STAGES_MAX`), nor under diffrax's `ForwardMode` (chosen to be
        # differentiated: jvp and vmap of written-out stages put the equations into the
        # program once per stage and tangent), nor where the user has asked XLA for compile
        # time over run time (`jax_disable_most_optimizations`).
        solver = UnrolledStages(solver)
    if dynamics.state_projection() is not None:
        solver = Projected(solver)
    return solver


def _solution(dynamics, p, save, solution, ts, q, u, result, layout, events, dense):
    """The `Solution`: what `save` asks for (q̇ = K u and the formulation's records formed
    from the saved states), the result code and the solver's statistics."""
    qd = None
    if "qd" in save:
        assert q is not None and u is not None  # kept (`keep_q`, `keep_u`)
        qd = jax.vmap(dynamics.coordinate_rates, in_axes=(0, 0, 0, None))(ts, q, u, p)
    recorded = {name: dynamics.record(name, ts, q, u, p)
                for name in save if name not in _STATE_QUANTITIES}
    return Solution(
        ts=ts,
        q=q if "q" in save else None,
        u=u if "u" in save else None,
        qd=qd,
        result=result,
        num_steps=solution.stats["num_steps"],
        num_accepted_steps=solution.stats["num_accepted_steps"],
        num_rejected_steps=solution.stats["num_rejected_steps"],
        dense=solution if dense else None,
        constraints=recorded.get("constraints"),
        inputs=recorded.get("inputs"),
        contact=recorded.get("contact"),
        layout=layout,
        events=events,
    )


_STATE_QUANTITIES = ("q", "u", "qd")


def _check_save(save, dynamics):
    """Trace-time check of `save`: state quantities, and the records the formulation offers
    (`AbstractDynamics.saved_records`)."""
    if save and all(name in _STATE_QUANTITIES for name in save):  # (the default, cheaply)
        return
    offered = dynamics.saved_records if isinstance(dynamics, AbstractDynamics) else ()
    if save and all(name in _STATE_QUANTITIES or name in offered for name in save):
        return
    names = ", ".join(repr(name) for name in (*_STATE_QUANTITIES, *offered))
    if not save:
        raise ValueError(f"save must name some of {names}, got {save!r}.")
    for name in save:
        if name not in _STATE_QUANTITIES and name not in offered:
            raise ValueError(
                f"save names {name!r}, which {type(dynamics).__name__} does not record: save "
                f"must name some of {names} (a jaxdyn.Constrained formulation also records "
                "'constraints', a jaxdyn.Controlled one 'inputs', a jaxdyn.Contact scene "
                "'contact').")


# Whether XLA compiles the solver's loop, stages and all, as one function (on the CPU, with
# `import jaxdyn`'s small-loop switch in effect, `jaxdyn._xla`): diffrax's loop over the
# stages then costs about what written-out stages cost to run, and far less to compile. The
# double pendulum from T and V, Dopri8 at 1e-10 over 10 s, written out against the loop (one
# process; benchmarks/LOG.md, "Written-out stages, measured again"): the forward solve's
# first call 2.15 / 0.98 s, its run 0.446 / 0.504 ms; `jax.grad` through it (forward
# sensitivities) 4.3 / 1.4 s and 1.63 / 0.97 ms. Without the switch the loop runs stage by
# stage, kernel by kernel: the same solve 0.41 ms written out, 3.56 ms as a loop.
LOOPS_RUN_WHOLE = _xla.SMALL_LOOPS_ONE_FUNCTION

# Where they are written out (`_stepper`), for equations of at most this many scalar
# operations in straight-line code. Measured with Dopri8 before `LOOPS_RUN_WHOLE` (first
# simulate / run time, written out against diffrax's stage loop run stage by stage): double
# pendulum (183 operations) 0.88 / 0.74 s, 0.11 / 0.34 ms; articulated chain of 6 (1302) 4.3 /
# 2.0 s, 0.78 / 1.69 ms; chain of 6 rods (1782) 4.0 / 1.4 s, 1.35 / 1.94 ms; articulated chain
# of 8 (1812) 18 / 3.1 s, 16.9 / 11.8 ms; chain of 10 rods (3746) 41 / 5.3 s, 17.0 / 10.3 ms.
# Equations evaluated as arrays keep the loop too (UR5 arm: 7.8 / 2.8 s, 10.8 / 5.0 ms):
# written out, a step's program is the equations' times the stages, which XLA compiles slowly
# and runs from a cold cache.
WRITTEN_OUT_STAGES_MAX = 1500


def _finite_stand_in(q0, u0, p):
    """(q0, u0, p) with NaN and inf replaced by zeros, and whether there were any: the solve
    then runs on finite numbers (and stops soon if they make no sense, e.g. a zero mass) and
    its result is discarded.

    The arrays are checked and replaced a group at a time, q0, u0 and each entry of `p` (of a
    dict: a robot's link, its mass, centre of mass and inertia), flattened into one vector: a
    few operations per group rather than per array (ANYmal-C's 78 links, 234 arrays, in
    contact: the solve's optimised HLO 38 540 → 29 725 lines, XLA's passes over it 2.2–2.5 →
    1.7–2.2 s).
    Not all of `p` in one vector: a `jax.vmap` over one parameter would then batch them all."""
    entries, structure = jax.tree_util.tree_flatten(p, is_leaf=lambda x: x is not p)
    replaced, flags = zip(*map(_finite_group, [q0, u0, *entries]))
    q0, u0, *entries = replaced
    return q0, u0, jax.tree_util.tree_unflatten(structure, entries), jnp.any(jnp.stack(flags))


def _finite_group(tree):
    """(`tree` with its non-finite floating-point entries zeroed, whether it had any), its
    arrays of one dtype checked as one flattened vector."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    nonfinite = [jnp.zeros((), bool)]
    by_dtype: dict = {}
    for i, x in enumerate(leaves):
        if eqx.is_inexact_array(x):
            by_dtype.setdefault(x.dtype, []).append(i)
    for members in by_dtype.values():
        flat = jnp.concatenate([jnp.ravel(leaves[i]) for i in members])
        finite = jnp.isfinite(flat)
        nonfinite.append(~jnp.all(finite))
        flat = jnp.where(finite, flat, 0)
        offset = 0
        for i in members:
            size = leaves[i].size
            leaves[i] = flat[offset:offset + size].reshape(leaves[i].shape)
            offset += size
    return jax.tree_util.tree_unflatten(treedef, leaves), jnp.any(jnp.stack(nonfinite))


def _check_shapes(dynamics, t0, q0, u0, p):
    """Trace the dynamics once on the initial state, so that shape errors in user callbacks
    are reported before the solve with the shapes involved."""
    check_static_indexing(dynamics.user_functions, t0, q0, u0, p)
    rates, accelerations = eqx.filter_eval_shape(
        vector_field, t0, (q0, u0), (dynamics, p, None, Layout(q0.shape[0], False)))
    if rates.shape != q0.shape:
        raise ValueError(
            f"coordinate_rates returned shape {rates.shape} for q0 of shape {q0.shape}."
        )
    if accelerations.shape != u0.shape:
        raise ValueError(
            f"The dynamics expects {accelerations.shape[0]} speeds but u0 has shape "
            f"{u0.shape}."
        )
