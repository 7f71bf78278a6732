"""diffrax's solve of the equations of motion: the state's layout, the vector field, and how
the solve is differentiated (forward sensitivities or reverse mode through checkpoints)."""

from typing import Any, cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._dynamics import equations_of_motion
from .._sensitivities import tangent_tree, with_sensitivities
from .._runge_kutta import UnrolledStages
from .._wrapped_solver import AbstractForwardingSolver
from .failures import GuardedAdaptive, solve_arguments


class Layout(eqx.Module):
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
    m: int = eqx.field(static=True, default=0)  # the speeds (read by step bounds)
    # diffrax's time s: t = origin + span s (`solve`); None: s = t.
    origin: Any = None
    span: Any = None

    def time(self, s):
        """The time t at diffrax's time s."""
        return s if self.origin is None else self.origin + self.span * s

    def duration(self, duration):
        """A duration in t (≥ 0) in diffrax's time."""
        return duration if self.span is None else duration / jnp.abs(self.span)

    def join(self, q, u):
        return jnp.concatenate([q, u], axis=-1) if self.flat else (q, u)

    def split(self, y):
        return (y[..., :self.n], y[..., self.n:]) if self.flat else y


def vector_field(t, y, args):
    dynamics, p, factorisation, layout = args[:4]  # (a hybrid solve's args carry a fifth)
    q, u = layout.split(y)
    rates, accelerations, _, _ = equations_of_motion(dynamics, layout.time(t), q, u, p,
                                                     factorisation)
    return layout.join(rates, accelerations)


def solve(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint, max_steps, *,
          forward, events=None, max_events=0):
    """diffrax's solve of the equations of motion, differentiated by forward sensitivities
    (`forward`: few inputs, `jaxdyn._sensitivities`) or by `adjoint` (default: reverse mode
    through checkpoints). Returns the `diffrax.Solution` (`throw=False`: jaxdyn raises its
    own errors after the solve). With `events`, the solve of a hybrid system
    (`jaxdyn._integrate.events`: a `HybridSolution`)."""
    times, requested = (t0, t1), saveat
    unit_interval = _on_unit_interval(y0, args, saveat, controller, events)
    if unit_interval:
        t0, t1, dt0, args, saveat = _unit_interval(t0, t1, dt0, args, saveat)

    def run(inputs, adjoint, vector_field=vector_field):
        t0, t1, dt0, y0, args, saveat, controller, events = inputs
        if events is not None:
            from .events import hybrid_solve  # (it builds on this module)
            return hybrid_solve(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint,
                                max_steps, events, max_events)
        term = diffrax.ODETerm(vector_field)
        if unit_interval:  # (the layout in args is the one `_unit_interval` set)
            term = _InScaledTime(vector_field, cast(Layout, solve_arguments(args)[3]).span)
        return diffrax.diffeqsolve(term, solver, t0, t1, dt0, y0,
                                   args=args, saveat=saveat, stepsize_controller=controller,
                                   adjoint=adjoint, max_steps=max_steps, throw=False)

    # The events' arrays (coefficients given as numbers) are inputs of the solve like the
    # parameters, not constants closed over by its derivative rule.
    inputs = (t0, t1, dt0, y0, args, saveat, controller, events)
    if not forward:
        solution = run(inputs,
                       diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint)
        return _times_back(solution, requested, *times) if unit_interval else solution
    dynamic, static = eqx.partition(inputs, eqx.is_array)

    def arrays_out(dynamic):  # what `simulate` reads of the solution, all arrays
        solution = run(eqx.combine(dynamic, static), diffrax.ForwardMode())
        return eqx.filter(solution, eqx.is_array)

    def sensitivity_solve(dynamic, basis):
        inputs = eqx.combine(dynamic, static)
        if events is None:
            return _sensitivity_equations(run, solver, inputs, basis)
        return _hybrid_sensitivities(solver, max_steps, max_events, inputs, dynamic, basis)

    solution = with_sensitivities(arrays_out, dynamic, sensitivity_solve)
    return _times_back(solution, requested, *times) if unit_interval else solution


def _hybrid_sensitivities(solver, max_steps, max_events, inputs, dynamic, basis):
    """A hybrid solve with its forward sensitivities (`jaxdyn._integrate.events`: the
    sensitivity equations along each segment, mapped across each event), for the k
    directions of `basis` (per leaf of `dynamic`, the solve's array inputs); None (forward
    mode through the whole solve instead) where the times, tolerances or save times are
    differentiated, or the sensitivity equations do not apply."""
    t0, t1, dt0, y0, args, saveat, controller, events = inputs
    counts = [len(jax.tree_util.tree_leaves(part)) for part in dynamic]
    ends = np.cumsum(counts)
    if any(b is not None for b in basis[:ends[2]] + basis[ends[4]:ends[6]]):
        return None
    if SensitivityEquations.controller_of(solver, y0, saveat, controller) is None:
        return None
    k = next(b for b in basis if b is not None).shape[0]
    y0_basis = basis[ends[2]]
    tangents = (jnp.zeros((k, *y0.shape), y0.dtype) if y0_basis is None else y0_basis,
                tangent_tree(args, basis[ends[3]:ends[4]]),
                tangent_tree(events, basis[ends[6]:]))
    from .events import hybrid_tangents  # (it builds on this module)
    return hybrid_tangents(solver, t0, t1, dt0, y0, args, saveat, controller, max_steps,
                           events, max_events, tangents)


def _on_unit_interval(y0, args, saveat, controller, events):
    """Whether the solve runs in the time s = (t − t₀)/(t₁ − t₀) (`_unit_interval`).

    diffrax rounds a step that ends within 100 ulps of its t₁ to t₁, and finds that threshold
    by 100 successive `nextafter`s of t₁ times the direction of integration. Unless t₀ and t₁
    are both constants of the program, XLA compiles that chain of about 2200 operations:
    0.45-0.6 s, a third of a small system's compilation. jaxdyn keeps the times inputs of its
    programs (a new end time compiles nothing), and diffrax's constants are 0 and 1 in s.

    The solve in s is the solve in t: explicit and implicit Runge–Kutta methods are
    invariant under an affine change of time, and so is the PID controller, whose first step
    (a heuristic that is not) is chosen in t (`jaxdyn._integrate.failures`). So for diffrax's
    solvers on the flat state with a `PIDController` without step bounds in t (dtmin,
    dtmax), saving at requested times or the end, in the default floating-point type (that of
    diffrax's times 0 and 1). The structure-preserving steppers, fixed steps (whose round-off
    near t₁ diffrax's 100 ulps absorb in t), dense output (read at times t), hybrid solves
    and float32 under x64 keep the time t."""
    subs = saveat.subs if isinstance(saveat.subs, (list, tuple)) else [saveat.subs]
    layout = args[3] if isinstance(args, tuple) and len(args) == 4 else None
    return (events is None and not saveat.dense and isinstance(layout, Layout) and layout.flat
            and isinstance(y0, jax.Array) and y0.dtype == jnp.asarray(0.0).dtype
            and isinstance(controller, GuardedAdaptive)
            and type(controller.controller) is diffrax.PIDController
            and controller.controller.dtmin is None and controller.controller.dtmax is None
            and all(not (sub.t0 or sub.steps) for sub in subs))


def _unit_interval(t0, t1, dt0, args, saveat):
    """(s₀ = 0, s₁ = 1, the first step, args, saveat) of the solve in s = (t − t₀)/(t₁ − t₀):
    the layout maps s to t (`Layout.time`), the save times and a first step given in t are
    mapped to s. (t₁ = t₀: a step over s ∈ [0, 1] of length zero in t.)"""
    dynamics, p, factorisation, layout = args
    span = t1 - t0
    layout = eqx.tree_at(lambda l: (l.origin, l.span), layout, (t0, span),
                         is_leaf=lambda x: x is None)

    def in_s(t, at_zero_span):
        return jnp.where(span == 0, at_zero_span, (t - t0) / jnp.where(span == 0, 1, span))

    saveat = eqx.tree_at(
        lambda s: [sub.ts for sub in s.subs if sub.ts is not None], saveat,
        [in_s(sub.ts, 1.0) for sub in saveat.subs if sub.ts is not None])
    if dt0 is not None:
        dt0 = jnp.where(span == 0, 1.0, dt0 / jnp.where(span == 0, 1, span))
    # Python numbers: constants of the program, as diffrax's t₀ and t₁.
    return 0.0, 1.0, dt0, (dynamics, p, factorisation, layout), saveat


class _InScaledTime(diffrax.ODETerm):
    """dy/dt = f(t, y) in diffrax's time s = (t − t₀)/(t₁ − t₀): `vf` is f at t (the
    layout's `time`), the control of a step is its length in t, h = (t₁ − t₀) Δs, so that
    each stage h f is formed as in t."""

    span: Any = None

    def contr(self, t0, t1, **kwargs):
        return self.span * (t1 - t0)


def _times_back(solution, saveat, t0, t1):
    """The solution's save times in t: the requested times themselves where saved (as a
    solve in t returns them), diffrax's inf where not reached (a failed solve), and the time
    reached where the end is saved (t₁, or where a failed solve stopped)."""
    def back(sub, saved):
        if sub.ts is not None:
            requested = jnp.where(jnp.isfinite(saved[:len(sub.ts)]), sub.ts,
                                  saved[:len(sub.ts)])
            return jnp.concatenate([requested, back(eqx.tree_at(lambda s: s.ts, sub, None),
                                                    saved[len(sub.ts):])])
        return jnp.where(saved == 1, t1, t0 + (t1 - t0) * saved)

    return eqx.tree_at(lambda s: s.ts, solution,
                       [back(sub, saved) for sub, saved in zip(saveat.subs, solution.ts)])


def _sensitivity_equations(run, solver, inputs, basis):
    """The solve of y' = f(t, y, x) together with its forward sensitivity equations
    (`SensitivityEquations`), for the k directions of `basis` (per leaf of the solve's array
    inputs, None where not differentiated). Returns the solution's arrays and their
    sensitivities (`jaxdyn._sensitivities.with_sensitivities`), or None where this does not
    apply: derivatives with respect to times, tolerances or save times, a state that is not
    one vector, or a solver other than an explicit Runge–Kutta method."""
    t0, t1, dt0, y0, args, saveat, controller, _ = inputs
    counts = [len(jax.tree_util.tree_leaves(eqx.filter(part, eqx.is_array)))
              for part in inputs]
    first_y0 = sum(counts[:3])
    first_args = first_y0 + counts[3]
    # The solve's times, in t or (the layout's origin and span, its last leaves of args) in
    # s, enter through the steps, which the sensitivity equations hold fixed.
    times_in_args = len(jax.tree_util.tree_leaves(eqx.filter(args[3], eqx.is_array)))
    if any(b is not None for b in basis[:first_y0] + basis[first_args + counts[4]:]
           + basis[first_args + counts[4] - times_in_args:first_args + counts[4]]):
        return None
    controller = SensitivityEquations.controller_of(solver, y0, saveat, controller)
    if controller is None:
        return None
    n = y0.shape[0]
    k = next(b for b in basis if b is not None).shape[0]
    s0 = basis[first_y0]
    arg_leaves = jax.tree_util.tree_leaves(eqx.filter(args, eqx.is_array))
    equations = SensitivityEquations(
        vector_field, n, k, [b for x, b in zip(arg_leaves, basis[first_args:])
                             if eqx.is_inexact_array(x)])
    z0 = equations.state(y0, jnp.zeros((k, n), y0.dtype) if s0 is None else s0)
    solution = run((t0, t1, dt0, z0, equations.arguments(args), equations.saveat(saveat),
                    controller, None), diffrax.ForwardMode(), equations.field)
    return equations.results(solution)


class SensitivityEquations:
    """A solve of y' = f(t, y, x) together with its forward sensitivity equations

        Ṡ_k = ∂f/∂y S_k + ∂f/∂x e_k,   S_k(t₀) given,

    for k directions e_k of the inexact arrays x of the vector field's args (`arg_basis`: per
    such leaf, the k directions or None where not differentiated), as one state
    z = [y; S₁; …; S_k]: only the vector field is differentiated (one vectorised JVP), not the
    solver's loop. The error norm reads y alone, so that the steps are the plain solve's, and
    an explicit Runge–Kutta method applied to the sensitivity equations on those steps is
    exactly the derivative of its solution at fixed steps (the steps do not depend on x:
    diffrax's controller stops their gradient), so that S equals what forward mode through
    the solve gives. Built at trace time.

    Reference: E. Hairer, S. P. Nørsett, G. Wanner, Solving Ordinary Differential Equations
    I (1993), §I.14 and §II.6 (internal differentiation)."""

    def __init__(self, vector_field, n, k, arg_basis):
        self.n, self.k = n, k
        self.differentiated = [i for i, b in enumerate(arg_basis) if b is not None]
        self.directions = [arg_basis[i] for i in self.differentiated]

        @eqx.filter_jit  # traced and differentiated once, for every place the solver calls it
        def field(t, z, augmented):
            y, s = self.split(z)
            f, rates = self.jvps(vector_field, t, y, s, augmented)
            return jnp.concatenate([f, rates.reshape(-1)])

        self.field = field

    @staticmethod
    def controller_of(solver, y0, saveat, controller):
        """The step-size controller of the sensitivity solve (its error norm reads y, the
        first n entries), or None where the sensitivity equations do not apply: a solver
        other than an explicit Runge–Kutta method, a state that is not one vector, dense
        output, a controller without a norm."""
        # By type, not isinstance: diffrax counts a wrapped solver (`Projected`, whose
        # projection the sensitivities would have to follow) as an instance of the solver it
        # wraps.
        inner = solver.solver if type(solver) is UnrolledStages else solver
        if not (issubclass(type(inner), diffrax.AbstractERK) and isinstance(y0, jax.Array)
                and y0.ndim == 1) or saveat.dense:
            return None
        n = y0.shape[0]
        if isinstance(controller, GuardedAdaptive):
            if not hasattr(controller.controller, "norm"):
                return None
            plain_norm = controller.controller.norm
            controller = eqx.tree_at(lambda c: c.controller.norm, controller,
                                     lambda error: plain_norm(error[:n]))
        return controller

    def split(self, z):
        """(y, S) of the state z: S with one row per direction."""
        return z[:self.n], z[self.n:].reshape(self.k, self.n)

    def state(self, y, s):
        """z of (y, S)."""
        return jnp.concatenate([y, s.reshape(-1)])

    def arguments(self, args):
        """The sensitivity solve's args: the vector field's, and the directions e_k."""
        return args, self.directions

    def chosen(self, args):
        """The differentiated leaves x of `args`."""
        leaves = jax.tree_util.tree_leaves(eqx.filter(args, eqx.is_inexact_array))
        return [leaves[i] for i in self.differentiated]

    def substituted(self, args, chosen):
        """`args` with its differentiated leaves replaced by `chosen`."""
        dynamic, static = eqx.partition(args, eqx.is_inexact_array)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        for i, x in zip(self.differentiated, chosen):
            leaves[i] = x
        return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)

    def jvps(self, fn, t, y, s, augmented):
        """(g, [dg/dx e_k]_k) of g = fn(t, y, args) along the k directions (S_k, e_k), where
        `augmented` is (args, the directions e)."""
        args, directions = augmented
        return jax.vmap(
            lambda s_k, e_k: jax.jvp(lambda y, x: fn(t, y, self.substituted(args, x)),
                                     (y, self.chosen(args)), (s_k, e_k)),
            out_axes=(None, 0))(s, directions)

    def observed(self, fn):
        """A saved quantity g(t, y, args) of z, with its sensitivities: (g, ∂g/∂y S + ∂g/∂x e)."""
        def save(t, z, augmented):
            y, s = self.split(z)
            return self.jvps(fn, t, y, s, augmented)
        return save

    def saveat(self, saveat):
        """diffrax's `SaveAt` of the sensitivity solve: each save's quantities observed with
        their sensitivities."""
        subs = saveat.subs if isinstance(saveat.subs, (list, tuple)) else [saveat.subs]
        return diffrax.SaveAt(subs=[eqx.tree_at(lambda sub: sub.fn, sub, self.observed(sub.fn))
                                    for sub in subs],
                              solver_state=saveat.solver_state,
                              controller_state=saveat.controller_state,
                              made_jump=saveat.made_jump)

    def results(self, solution):
        """The plain solution's arrays, and their sensitivities: those of the saved
        quantities (saved with the time axis first; k moved to the front), zero for the rest
        (times, step counts, the controller's state: independent of x)."""
        out = eqx.filter(eqx.tree_at(lambda s: s.ys, solution, [y for y, _ in solution.ys],
                                     is_leaf=lambda x: x is None), eqx.is_array)
        saved = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 1, 0),
                                       [s for _, s in solution.ys])
        zeros = jax.tree_util.tree_map(lambda x: jnp.zeros((self.k, *x.shape), x.dtype),
                                       eqx.filter(out, eqx.is_inexact_array))
        return out, eqx.tree_at(lambda s: s.ys, zeros, saved, is_leaf=lambda x: x is None)


class Projected(AbstractForwardingSolver):
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
        dynamics, p, _, layout = args[:4]
        y1 = layout.join(*dynamics.state_projection()(layout.time(t1), *layout.split(y1), p))
        if "y1" in dense_info:
            dense_info = dict(dense_info, y1=y1)
        return y1, y_error, dense_info, solver_state, result

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
