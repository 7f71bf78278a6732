"""`simulate`: the single jit-compiled entry point that integrates any dynamics with diffrax."""

import functools
import math
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from ._dynamics import (
    AbstractDynamics,
    constant_mass_matrix,
    equations_of_motion,
    formed_equations,
    mass_matrix_blocks,
    straight_line_size,
)
from ._linalg import factorise
from ._compile import filter_jit
from ._form.controlled import find_controlled, with_inputs
from ._errors import check_finite, check_static_indexing, error_if, reports_state
from ._runge_kutta import UnrolledStages
from ._sensitivities import MAX_FORWARD, differentiable_size, with_sensitivities
from ._solution import RESULTS, Solution
from ._state import check_parameter_dtypes, check_vector, numbers_as_arrays, state_dtype
from ._variational import AbstractStructurePreserving
from ._wrapped_solver import AbstractForwardingSolver

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


class _Layout(eqx.Module):
    """How the state (q, u) is held as diffrax's y.

    One vector y = [q; u] for diffrax's own solvers: every per-step operation of a solver
    (stage combinations, the error norm, interpolation, saving) is then one array operation
    rather than one per part, which on small systems is most of a step's cost (a two-part
    state costs 1.4–2.8× the one-vector state per step for the double and elastic pendulums,
    with the same equations). The pair (q, u) for the structure-preserving steppers, which
    update coordinates and speeds apart.
    """

    n: int = eqx.field(static=True)
    flat: bool = eqx.field(static=True)

    def join(self, q, u):
        return jnp.concatenate([q, u], axis=-1) if self.flat else (q, u)

    def split(self, y):
        return (y[..., :self.n], y[..., self.n:]) if self.flat else y


def _vector_field(t, y, args):
    dynamics, p, factorisation, layout = args
    q, u = layout.split(y)
    rates, accelerations, _, _ = equations_of_motion(dynamics, t, q, u, p, factorisation)
    return layout.join(rates, accelerations)


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
      checkpoint per step avoids recomputation. Measured costs: benchmarks/README.md.
    - `throw`: raise on failure; if False, inspect `Solution.result` (NaN or inf in the
      initial state or parameters then gives `RESULTS.nonfinite_state_or_parameters` and NaN
      states, so that one bad member does not stop a vmapped batch).
    - `inputs`: for a system with control inputs (`jaxdyn.Controlled`, also inside a
      `Constrained`): an array r, a signal r(t) (a function of t, or a diffrax path such as
      `diffrax.LinearInterpolation`) or a policy π(t, q, u, p); None keeps the system's own.
      Derivatives flow through the inputs' arrays (a policy's weights held as module fields).

    **Returns:** a `jaxdyn.Solution`.

    Numbers (t0, t1, ts, tolerances, dt0, and every float or int in `p`) are traced, so
    changing them reuses the compiled solve. The initial state and parameters are checked for
    NaN/inf. The right-hand side carries no checks: where the mass matrix is singular or the
    forcing not finite it returns NaN, the solver rejects the step and shrinks it, and when no
    step however small gets past a state the solve stops and names the state where the
    equations fail (`RESULTS.singular_mass_matrix`, `nonfinite_forcing`,
    `nonfinite_equations`).
    """
    dtype = state_dtype(q0, u0)
    if inputs is not None:
        dynamics = with_inputs(dynamics, inputs)
    if isinstance(solver, AbstractStructurePreserving):
        stepsize_controller = _fixed_steps(solver, rtol, atol, dt0, stepsize_controller)
    elif stepsize_controller is None:  # defaults filled in here, so that they are traced too
        default = 1e-10 if jnp.finfo(dtype).bits == 64 else 1e-6
        rtol = default if rtol is None else rtol
        atol = default if atol is None else atol
    elif rtol is not None or atol is not None:
        raise ValueError("Pass rtol/atol or a stepsize_controller, not both.")
    _check_tolerances(rtol, atol)
    default_budget = max_steps is None
    max_steps = _step_budget(max_steps, t0, t1, dt0, stepsize_controller)
    numbers = numbers_as_arrays((p, t0, t1, ts, rtol, atol, dt0), dtype)
    # Few arguments: binding them is part of the per-call cost.
    save = (save,) if isinstance(save, str) else tuple(save)
    _check_save(save, dynamics)
    # The entries a derivative can reach are the traced ones (of a caller's jax.grad, jit or
    # vmap), not concrete arrays closed over: a robot's hundreds of inertial parameters when
    # only q0 is differentiated. Counted with the inputs' arrays (a policy's weights).
    reachable = differentiable_size([x for x in jax.tree_util.tree_leaves(
        (q0, u0, numbers[0], _inputs_of(dynamics))) if isinstance(x, jax.core.Tracer)])

    def run(budget, lean):
        return _simulate(dynamics, q0, u0, numbers, (dense, save, solver, stepsize_controller,
                                                     budget, adjoint, throw, reachable, lean))

    if not all(_concrete_value(x) is not None
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


def _succeeded(solution) -> bool:
    """Whether every member of an eager solve succeeded (read on the host, no dispatch)."""
    result = _concrete_value(solution.result._value)
    return not np.any(np.asarray(result) != RESULTS.successful._value)


def _concrete_value(x):
    """`x`'s value where it is known while tracing: `x` itself, or the value a tracer of an
    un-jitted derivative carries (`jax.grad`, `jax.jvp`); None under `jax.jit` or `vmap`."""
    if isinstance(x, jax.core.Tracer):
        return x.to_concrete_value()
    return x


@filter_jit
def _simulate(dynamics, q0, u0, numbers, options):
    p, t0, t1, ts, rtol, atol, dt0 = numbers
    dense, save, solver, stepsize_controller, max_steps, adjoint, throw, reachable, lean = options
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
    # Strongly typed (`jnp.full(n, 0.3)` is weakly typed): as the solve's state is, so that
    # the equations traced for the shape check are the solve's (a weak type retraces them).
    q0, u0 = jnp.asarray(q0, dtype), jnp.asarray(u0, dtype)
    check_parameter_dtypes(p, dtype)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    _check_shapes(dynamics, t0, q0, u0, p)
    if isinstance(solver, AbstractStructurePreserving):
        solver.check(dynamics, t0, q0, u0, p)
    rtol, atol = _checked_tolerances(rtol, atol)
    if throw:
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

    records = tuple(name for name in save if name not in _STATE_QUANTITIES)
    keep_q = bool(records) or "q" in save or "qd" in save
    keep_u = bool(records) or "u" in save or "qd" in save

    layout = _Layout(q0.shape[0], not isinstance(solver, AbstractStructurePreserving))

    def observe(t, y, args):
        q, u = layout.split(y)
        return q if keep_q else None, u if keep_u else None

    if ts is None:
        requested = diffrax.SubSaveAt(t1=True, fn=observe)
    else:
        ts = _checked_save_times(jnp.asarray(ts, dtype), t0, t1)
        requested = diffrax.SubSaveAt(ts=ts, fn=observe)
    # The last state reached is saved too: where the solve stops early, it is the state from
    # which the failure is diagnosed.
    saveat = diffrax.SaveAt(subs=[requested, diffrax.SubSaveAt(t1=True)], dense=dense,
                            controller_state=True)
    if stepsize_controller is None:
        assert rtol is not None and atol is not None  # `simulate` filled in the defaults
        stepsize_controller = diffrax.PIDController(rtol=rtol, atol=atol)
    forward = adjoint is None and not dense and reachable <= MAX_FORWARD
    if (isinstance(solver, diffrax.AbstractERK) and solver.scan_kind is None
            and size is not None and size <= WRITTEN_OUT_STAGES_MAX and forward):
        # The same steps, without a loop over the stages (2–3× faster on small systems).
        # Not for reverse mode, whose pass through written-out stages costs 3× diffrax's
        # loop, nor for large equations (`WRITTEN_OUT_STAGES_MAX`), nor under diffrax's
        # `ForwardMode` (chosen to be differentiated: jvp and vmap of written-out stages
        # put the equations into the program once per stage and tangent; a fit of the
        # torque-driven double pendulum, three experiments, compiled in 44.5 s written out
        # and 23.8 s as a loop; a later fit took 0.89 and 1.28 s). Forward sensitivities
        # (`forward`) keep them written out, primal and sensitivity equations alike: as a
        # loop, the double pendulum's gradient compiled 2–3× faster but ran 4× slower.
        solver = UnrolledStages(solver)
    if dynamics.state_projection() is not None:
        solver = _Projected(solver)
    solution = _solve(solver, t0, t1, dt0, layout.join(q0, u0),
                      (dynamics, p, factorisation, layout), saveat,
                      _guard(stepsize_controller), adjoint, max_steps, forward=forward)
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
                               RESULTS.promote(solution.result))
    else:
        result, failure = _diagnose(dynamics, p, factorisation, t_last, q_last[0], u_last[0],
                                    stalled, jnp.sign(t1 - t0), jnp.abs(t1 - t0))
        result = RESULTS.where(stalled, result, RESULTS.promote(solution.result))
    if nonfinite_input is not None:
        result = RESULTS.where(nonfinite_input, RESULTS.nonfinite_state_or_parameters, result)
        q, u = (None if x is None else jnp.where(nonfinite_input, jnp.nan, x) for x in (q, u))
    ts_out = solution.ts[0]
    if throw and not lean:
        condition = functools.partial(_condition, dynamics, p)
        ts_out = _raise_failures(ts_out, result, failure, (t0, q0, u0), t1,
                                 (t_last, q_last[0], u_last[0]), max_steps, condition,
                                 isinstance(solver, AbstractStructurePreserving))
    qd = None
    if "qd" in save:
        assert q is not None and u is not None  # kept (`keep_q`, `keep_u`)
        qd = jax.vmap(dynamics.coordinate_rates, in_axes=(0, 0, 0, None))(ts_out, q, u, p)
    recorded = {name: dynamics.record(name, ts_out, q, u, p) for name in records}
    return Solution(
        ts=ts_out,
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
        layout=layout,
    )


_STATE_QUANTITIES = ("q", "u", "qd")


def _inputs_of(dynamics):
    controlled = find_controlled(dynamics)
    return None if controlled is None else controlled.inputs


def _check_save(save, dynamics):
    """Trace-time check of `save`: state quantities, and the records the formulation offers
    (`AbstractDynamics.saved_records`)."""
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
                "'constraints', a jaxdyn.Controlled one 'inputs').")


def _solve(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint, max_steps, *,
           forward):
    """diffrax's solve of the equations of motion, differentiated by forward sensitivities
    (`forward`: few inputs, `jaxdyn._sensitivities`) or by `adjoint` (default: reverse mode
    through checkpoints). Returns the `diffrax.Solution` (`throw=False`: jaxdyn raises its
    own errors after the solve)."""
    def run(inputs, adjoint, vector_field=_vector_field):
        t0, t1, dt0, y0, args, saveat, controller = inputs
        return diffrax.diffeqsolve(diffrax.ODETerm(vector_field), solver, t0, t1, dt0, y0,
                                   args=args, saveat=saveat, stepsize_controller=controller,
                                   adjoint=adjoint, max_steps=max_steps, throw=False)

    inputs = (t0, t1, dt0, y0, args, saveat, controller)
    if not forward:
        return run(inputs, diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint)
    dynamic, static = eqx.partition(inputs, eqx.is_array)

    def arrays_out(dynamic):  # what `simulate` reads of the solution, all arrays
        solution = run(eqx.combine(dynamic, static), diffrax.ForwardMode())
        return eqx.filter(solution, eqx.is_array)

    def sensitivity_solve(dynamic, basis):
        return _sensitivity_equations(run, solver, eqx.combine(dynamic, static), basis)

    return with_sensitivities(arrays_out, dynamic, sensitivity_solve)


def _sensitivity_equations(run, solver, inputs, basis):
    """The solve of y' = f(t, y, x) together with its forward sensitivity equations

        Ṡ_k = ∂f/∂y S_k + ∂f/∂x e_k,   S_k(t₀) = ∂y₀/∂x e_k,

    for the k directions e_k of `basis` (per leaf of the solve's array inputs, None where
    not differentiated), as one state z = [y; S₁; …; S_k]: only the vector field is
    differentiated (one vectorised JVP), not the solver's loop. The error norm reads y
    alone, so that the steps are the plain solve's, and an explicit Runge–Kutta method
    applied to the sensitivity equations on those steps is exactly the derivative of its
    solution at fixed steps (the steps do not depend on x: diffrax's controller stops their
    gradient), so that S equals what forward mode through the solve gives. Returns the
    solution's arrays and their sensitivities (`jaxdyn._sensitivities.with_sensitivities`),
    or None where this does not apply: derivatives with respect to times, tolerances or
    save times, a state that is not one vector, or a solver other than an explicit
    Runge–Kutta method.

    Reference: E. Hairer, S. P. Nørsett, G. Wanner, Solving Ordinary Differential Equations
    I (1993), §I.14 and §II.6 (internal differentiation)."""
    t0, t1, dt0, y0, args, saveat, controller = inputs
    counts = [len(jax.tree_util.tree_leaves(eqx.filter(part, eqx.is_array)))
              for part in inputs]
    first_y0 = sum(counts[:3])
    first_args = first_y0 + counts[3]
    if any(b is not None for b in basis[:first_y0] + basis[first_args + counts[4]:]):
        return None
    # By type, not isinstance: diffrax counts a wrapped solver (`_Projected`, whose projection
    # the sensitivities would have to follow) as an instance of the solver it wraps.
    inner = solver.solver if type(solver) is UnrolledStages else solver
    if not (issubclass(type(inner), diffrax.AbstractERK) and isinstance(y0, jax.Array)
            and y0.ndim == 1):
        return None
    if saveat.dense:
        return None
    n = y0.shape[0]
    if isinstance(controller, _GuardedAdaptive):
        if not hasattr(controller.controller, "norm"):
            return None
        plain_norm = controller.controller.norm
        controller = eqx.tree_at(lambda c: c.controller.norm, controller,
                                 lambda error: plain_norm(error[:n]))
    k = next(b for b in basis if b is not None).shape[0]
    s0 = basis[first_y0]
    s0 = jnp.zeros((k, n), y0.dtype) if s0 is None else s0
    arg_basis = basis[first_args:first_args + counts[4]]
    differentiated = [i for i, b in enumerate(arg_basis) if b is not None]
    directions = [arg_basis[i] for i in differentiated]

    def split(z):
        return z[:n], z[n:].reshape(k, n)

    @eqx.filter_jit  # traced and differentiated once, for every place the solver calls it
    def field(t, z, augmented):
        args, directions = augmented
        y, s = split(z)
        dynamic, static = eqx.partition(args, eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)

        def rate(y, chosen):  # f(t, y, x) with x the differentiated leaves of args
            given = list(leaves)
            for i, x in zip(differentiated, chosen):
                given[i] = x
            return _vector_field(
                t, y, eqx.combine(jax.tree_util.tree_unflatten(treedef, given), static))

        chosen = [leaves[i] for i in differentiated]
        f, rates = jax.vmap(lambda s_k, e_k: jax.jvp(rate, (y, chosen), (s_k, e_k)),
                            out_axes=(None, 0))(s, directions)
        return jnp.concatenate([f, rates.reshape(-1)])

    def observed(fn):  # a saved quantity and its sensitivities: (g(y), ∂g/∂y S)
        def save(t, z, augmented):
            y, s = split(z)
            return jax.vmap(lambda s_k: jax.jvp(lambda y: fn(t, y, augmented[0]), (y,), (s_k,)),
                            out_axes=(None, 0))(s)
        return save

    subs = saveat.subs if isinstance(saveat.subs, (list, tuple)) else [saveat.subs]
    saveat = diffrax.SaveAt(subs=[eqx.tree_at(lambda sub: sub.fn, sub, observed(sub.fn))
                                  for sub in subs],
                            solver_state=saveat.solver_state,
                            controller_state=saveat.controller_state,
                            made_jump=saveat.made_jump)
    z0 = jnp.concatenate([y0, s0.reshape(-1)])
    solution = run((t0, t1, dt0, z0, (args, directions), saveat, controller),
                   diffrax.ForwardMode(), field)
    out = eqx.filter(eqx.tree_at(lambda s: s.ys, solution, [y for y, _ in solution.ys],
                                 is_leaf=lambda x: x is None), eqx.is_array)
    # S for the saved quantities (saved with the time axis first; k moved to the front),
    # zero for the rest (times, step counts, the controller's state: independent of x).
    saved = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 1, 0),
                                   [s for _, s in solution.ys])
    zeros = jax.tree_util.tree_map(lambda x: jnp.zeros((k, *x.shape), x.dtype),
                                   eqx.filter(out, eqx.is_inexact_array))
    return out, eqx.tree_at(lambda s: s.ys, zeros, saved, is_leaf=lambda x: x is None)


def _fixed_steps(solver, rtol, atol, dt0, stepsize_controller):
    """The step-size controller of a structure-preserving solver, which takes fixed steps."""
    name = type(solver).__name__
    if rtol is not None or atol is not None:
        raise ValueError(f"{name} takes fixed steps, without error control: pass the step as "
                         "dt0, not rtol/atol.")
    if dt0 is None:
        raise ValueError(f"{name} takes fixed steps: pass the step length as dt0.")
    if stepsize_controller is None:
        return diffrax.ConstantStepSize()
    if isinstance(stepsize_controller, diffrax.AbstractAdaptiveStepSizeController):
        raise ValueError(f"{name} takes fixed steps (an adaptive step destroys the "
                         "conservation it gives): use diffrax.ConstantStepSize() or "
                         "StepTo, or leave stepsize_controller unset.")
    return stepsize_controller


def _concrete(x):
    return x is None or not any(isinstance(leaf, jax.core.Tracer)
                                for leaf in jax.tree_util.tree_leaves(x))


def _tolerance_problem(rtol, atol):
    """None, or what is wrong with the tolerances (`rtol`, `atol` arrays)."""
    for name, value in (("rtol", rtol), ("atol", atol)):
        if value is not None and not np.all(np.isfinite(value) & (value >= 0)):
            return f"{name} must be finite and ≥ 0, got {value}."
    if rtol is not None and atol is not None and np.all(rtol + atol == 0):
        return "rtol and atol are both 0: no step could meet them. Pass positive tolerances."
    return None


def _check_tolerances(rtol, atol):
    """Trace-time check of concrete tolerances (traced ones are checked in the solve)."""
    if all(x is None or type(x) is float for x in (rtol, atol)):  # the common case, cheaply
        if all(x is None or (math.isfinite(x) and x >= 0) for x in (rtol, atol)) and (
                rtol is None or atol is None or rtol + atol > 0):
            return
    if _concrete((rtol, atol)):
        as_array = lambda x: None if x is None else np.asarray(x)  # noqa: E731
        problem = _tolerance_problem(as_array(rtol), as_array(atol))
        if problem is not None:
            raise ValueError(problem)


def _checked_tolerances(rtol, atol):
    if rtol is None or atol is None:
        return rtol, atol
    bad = (~jnp.isfinite(rtol) | ~jnp.isfinite(atol) | (rtol < 0) | (atol < 0)
           | (rtol + atol == 0))
    return error_if((rtol, atol), [(bad, "rtol and atol must be finite and ≥ 0, and not both "
                                         "0.")], {"rtol": rtol, "atol": atol})


def _checked_save_times(ts, t0, t1):
    """`ts`, or an error if they are not 1-D, leave [t0, t1], or run against the direction of
    integration (a value-dependent check: one branch, taken on failure)."""
    if ts.ndim != 1:
        raise ValueError(f"ts must be a 1-D array of save times, got shape {ts.shape}.")
    if ts.shape[0] == 0:
        raise ValueError("ts is empty: pass at least one save time, or ts=None to save t1.")
    direction = jnp.where(t1 >= t0, 1, -1).astype(ts.dtype)
    outside = jnp.any((ts - t0) * direction < 0) | jnp.any((ts - t1) * direction > 0)
    against = jnp.any(jnp.diff(ts) * direction < 0)
    return error_if(ts, [
        (~jnp.all(jnp.isfinite(ts)), "ts contains NaN or inf."),
        (outside, "ts must lie within the interval from t0 to t1."),
        (against, "ts must run in the direction of integration: increasing for t1 > t0, "
                  "decreasing for t1 < t0.")],
        {"t0": t0, "t1": t1, "ts[0]": ts[0], "ts[-1]": ts[-1]})


def _step_budget(max_steps, t0, t1, dt0, stepsize_controller):
    """`max_steps`, or its default: 16⁴, or the steps a fixed step takes over the interval."""
    if max_steps is not None:
        if not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
        return max_steps
    budget = 16**4
    fixed = (stepsize_controller is not None and not isinstance(
        stepsize_controller, diffrax.AbstractAdaptiveStepSizeController))
    if fixed and dt0 is not None and _concrete((t0, t1, dt0)):
        span, step = abs(float(t1) - float(t0)), abs(float(dt0))
        if step > 0:
            needed = math.ceil(span / step * (1 + 1e-9)) + 1
            # Rounded up to a power of two: the budget is compiled in, and nearby intervals
            # then reuse the compiled solve.
            budget = max(budget, 2 ** math.ceil(math.log2(needed)))
    return budget


def _raise_failures(ts, result, failure, start, t1, last, max_steps, condition,
                    structure_preserving):
    """`ts`, or an error whose first line is jaxdyn's account of why the solve failed.

    Where the mass matrix is singular at the failure but regular at the start, or the solve
    ran out of steps where it is ill-conditioned, the cause named is the configuration (a
    coordinate singularity). `condition(t, q, u)`, the mass matrix's condition number, is
    evaluated only on failure."""
    t0 = start[0]
    t_last = last[0]

    def checks():  # evaluated only in the branch taken on failure
        singular = result == RESULTS.singular_mass_matrix
        regular_at_start = condition(*start) < _ILL_CONDITIONED
        out_of_steps = result == RESULTS.max_steps_reached
        ill = condition(*last) >= _ILL_CONDITIONED
        covered = jnp.abs(t_last - t0)
        budget = {"t reached": t_last, "max_steps": jnp.asarray(max_steps),
                  "steps the whole interval needs (estimate)": jnp.ceil(
                      max_steps * jnp.abs(t1 - t0) / jnp.where(covered > 0, covered, 1)),
                  "mass matrix condition number (start, last)": jnp.stack(
                      [condition(*start), condition(*last)])}
        listed = [(singular & regular_at_start, COORDINATE_SINGULARITY, failure)]
        listed += [(result == code, RESULTS[code], failure) for code in _EQUATION_FAILURES]
        listed += [(out_of_steps & ill, MAX_STEPS_ILL_CONDITIONED, budget),
                   (out_of_steps, MAX_STEPS, budget)]
        if structure_preserving:  # the codes of its implicit step (`VariationalIntegrator`)
            listed += [(result == RESULTS.nonlinear_max_steps_reached, NEWTON, {"t": t_last}),
                       (result == RESULTS.nonlinear_divergence, DISTANT_ROOT, {"t": t_last})]
        listed += [(result == RESULTS._name_to_item[name], RESULTS[RESULTS._name_to_item[name]],
                    None) for name in RESULTS._name_to_item if name not in handled]
        return listed

    handled = _HANDLED | ({"nonlinear_max_steps_reached", "nonlinear_divergence"}
                          if structure_preserving else set())
    # One branch for every failure: its messages share the mass matrix's condition numbers.
    return error_if(ts, checks, failed=result != RESULTS.successful)


@eqx.filter_jit  # traced once per solve's compilation, though the messages ask for it 4 times
def _condition(dynamics, p, t, q, u):
    """κ(M) at one state (∞ where M is not positive definite), for failure messages only.

    M is formed in the program and its eigenvalues found on the host (NumPy): only a failed
    solve asks for them, and an eigensolver in the program would cost every solve its
    compilation (and the first one in a process LAPACK's set-up, ~0.1 s)."""
    mass_matrix = jax.lax.stop_gradient(formed_equations(dynamics, t, q, u, p)[0])
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


# Runge–Kutta stages are written out (`UnrolledStages`) for equations of at most this many
# scalar operations in straight-line code. Measured with Dopri8 (first simulate / run time,
# written out against diffrax's stage loop): double pendulum (183 operations) 0.88 / 0.74 s,
# 0.11 / 0.34 ms; articulated chain of 6 (1302) 4.3 / 2.0 s, 0.78 / 1.69 ms; chain of 6 rods
# (1782) 4.0 / 1.4 s, 1.35 / 1.94 ms; articulated chain of 8 (1812) 18 / 3.1 s, 16.9 / 11.8 ms;
# chain of 10 rods (3746) 41 / 5.3 s, 17.0 / 10.3 ms. Equations evaluated as arrays keep the
# loop too (UR5 arm: 7.8 / 2.8 s, 10.8 / 5.0 ms): written out, a step's program is the
# equations' times the stages, which XLA compiles slowly and runs from a cold cache.
WRITTEN_OUT_STAGES_MAX = 1500

# A mass matrix this ill-conditioned loses half the digits of the accelerations.
_ILL_CONDITIONED = 1e8

_EQUATION_FAILURES = (RESULTS.singular_mass_matrix, RESULTS.singular_constraints,
                      RESULTS.nonfinite_forcing, RESULTS.nonfinite_equations)
_HANDLED = {"successful", "max_steps_reached",
            "singular_mass_matrix", "singular_constraints", "nonfinite_forcing",
            "nonfinite_equations"}


def _finite_stand_in(q0, u0, p):
    """(q0, u0, p) with NaN and inf replaced by zeros, and whether there were any: the solve
    then runs on finite numbers (and stops soon if they make no sense, e.g. a zero mass) and
    its result is discarded."""
    leaves = [x for x in jax.tree_util.tree_leaves((q0, u0, p)) if eqx.is_inexact_array(x)]
    nonfinite = ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    q0, u0, p = jax.tree_util.tree_map(
        lambda x: jnp.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
        if eqx.is_inexact_array(x) else x, (q0, u0, p))
    return q0, u0, p, nonfinite


def _check_shapes(dynamics, t0, q0, u0, p):
    """Trace the dynamics once on the initial state, so that shape errors in user callbacks
    are reported before the solve with the shapes involved."""
    check_static_indexing(dynamics.user_functions, t0, q0, u0, p)
    rates, accelerations = eqx.filter_eval_shape(
        _vector_field, t0, (q0, u0), (dynamics, p, None, _Layout(q0.shape[0], False)))
    if rates.shape != q0.shape:
        raise ValueError(
            f"coordinate_rates returned shape {rates.shape} for q0 of shape {q0.shape}."
        )
    if accelerations.shape != u0.shape:
        raise ValueError(
            f"The dynamics expects {accelerations.shape[0]} speeds but u0 has shape "
            f"{u0.shape}."
        )


# -- failures of the equations of motion: detected in the step-size controller, diagnosed after
# the solve -------------------------------------------------------------------------------------


def _guard(controller):
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return _GuardedAdaptive(controller)
    return _GuardedFixed(controller)


def _guard_init(controller, terms, t0, t1, y0, dt0, args, func, error_order):
    t_next, state = controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
    return t_next, (state, jnp.abs(t1 - t0), jnp.array(False))


def _guard_adapt(controller, can_shrink, t0, t1, y0, y1_candidate, args, y_error,
                 error_order, guard_state):
    """The wrapped controller's decision, unless the step met non-finite equations and cannot
    shrink further (the step is within round-off of zero, or the steps are fixed): then the
    step is rejected and the solve stops (`stalled`), keeping the last state it reached."""
    state, span, _ = guard_state
    keep, next_t0, next_t1, made_jump, state, result = controller.adapt_step_size(
        t0, t1, y0, y1_candidate, args, y_error, error_order, state)
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


class _GuardedAdaptive(diffrax.AbstractAdaptiveStepSizeController):
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
        return _GuardedAdaptive(cast(diffrax.AbstractAdaptiveStepSizeController,
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


def _diagnose(dynamics, p, factorisation, t, q, u, stalled, direction, span):
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


class _Projected(AbstractForwardingSolver):
    """A diffrax solver whose every step ends with the dynamics' `state_projection` (drift
    control of constraints). The step's error estimate is the wrapped solver's, before the
    projection; the next step re-evaluates its first stage at the projected state
    (`made_jump`), as first-same-as-last solvers would otherwise reuse the unprojected one."""

    solver: diffrax.AbstractSolver

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True)
        dynamics, p, _, layout = args
        y1 = layout.join(*dynamics.state_projection()(t1, *layout.split(y1), p))
        if "y1" in dense_info:
            dense_info = dict(dense_info, y1=y1)
        return y1, y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
