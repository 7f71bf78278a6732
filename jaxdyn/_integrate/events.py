"""The solve of a hybrid system: flows between events, each event located and the solve
restarted after its jump, in a loop of a fixed number of segments (so that `jax.jit`,
`jax.vmap`, `jax.grad` and `jax.jacfwd` all apply).

Each segment is one `diffrax.diffeqsolve` from the last event to t1 that stops at the first
zero crossing of a guard, located on the step's dense interpolant (`diffrax.Event`) by
bracketing the earliest zero without derivatives (`FirstCrossing`). Its derivative,
differentiated forward, is carried segment by segment: along the flow by the sensitivity
equations (only the vector field is differentiated, not the solver's loop), then across the
event by the implicit function theorem on the crossing c(t*, y(t*)) = 0 for the event's time
and forward mode through the jump, which together apply the saltation matrix of the event
(Aizerman and Gantmacher 1958). Where forward sensitivities do not apply (an implicit
solver, derivatives with respect to the times or tolerances), or in reverse mode through
checkpoints, the discrete solve is differentiated as it is.
"""

import copy
import dataclasses
import functools
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._sensitivities import forward_tangents
from .._solution import RESULTS, promoted
from .guards import Hybrid, Segment, Watch, can_rest, guard_counts, segment_field
from .solve import SensitivityEquations

#: Default budget of events per solve (`simulate(..., max_events=...)`).
MAX_EVENTS = 64


class EventRecord(eqx.Module):
    """The events of a hybrid solve, in the order they happened (`Solution.events`).

    **Fields** (E = `max_events`; rows past `count` are NaN, and -1 in `guard`):

    - `t`: the event times, shape (E,).
    - `guard`: which guard fired: its index among all guards of all events, in the order the
      events were given, each event's guards in order, shape (E,).
    - `q_minus`, `u_minus`: the state just before the event, shapes (E, n), (E, m).
    - `q_plus`, `u_plus`: the state just after its jump, shapes (E, n), (E, m).
    - `guard_rates`: ġ of every guard just before the event, shape (E, K): for an impact, the
      approach speeds. A crossing with ġ near zero (grazing) has an event time whose
      derivative is unbounded.
    - `impulses`: the impulses Λ of impacts, per guard (zero for other events), shape (E, K).
    - `resting`: which guards are held at rest after the event (a contact come to rest),
      shape (E, K).
    - `count`: the number of events that happened, a scalar.
    - `normal_forces`: the force each guard carries at rest, at the solution's save times:
      a resting contact's normal force λ (for a `RigidContact`'s friction guards, the
      friction force), zero where a guard does not rest, shape (k, K); None where no event
      can rest.
    """

    t: Float[Array, " E"]
    guard: Int[Array, " E"]
    q_minus: Float[Array, "E n"]
    u_minus: Float[Array, "E m"]
    q_plus: Float[Array, "E n"]
    u_plus: Float[Array, "E m"]
    guard_rates: Float[Array, "E K"]
    impulses: Float[Array, "E K"]
    resting: Bool[Array, "E K"]
    count: Int[Array, ""]
    normal_forces: Float[Array, "k K"] | None = None


class HybridSolution(eqx.Module):
    """What `simulate` reads of a solve (as of a `diffrax.Solution`), for a hybrid solve."""

    ts: tuple
    ys: tuple
    controller_state: tuple
    result: diffrax.RESULTS
    stats: dict
    events: EventRecord


def hybrid_solve(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint, max_steps,
                 events, max_events) -> "HybridSolution":
    """Segments of `diffrax.diffeqsolve` between events, at most `max_events` events.

    `args` is the vector field's (dynamics, p, factorisation, layout); `saveat` is
    `simulate`'s (the requested states, then the last state). Returns a `HybridSolution`:
    the scan over max_events + 1 segments (`_Segments.segment`), the last one to reach t1
    or to meet the event past the budget."""
    segments, t0, y0 = _segments(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint,
                                 max_steps, events, max_events)
    dynamics, p, _, layout = args
    q0, u0 = layout.split(y0)
    references0 = segments.watch.hybrid.references(dynamics, t0, q0, u0, p,
                                                   segments.no_guards)
    carry0 = segments.start(t0, y0, references0)
    carry, records = jax.lax.scan(segments.segment, carry0, jnp.arange(max_events + 1))
    return _hybrid_solution(carry, records, segments.requested.ts, max_events)


def hybrid_tangents(solver, t0, t1, dt0, y0, args, saveat, controller, max_steps, events,
                    max_events, tangents):
    """`hybrid_solve`'s arrays and their tangents along k directions: `tangents` are those of
    (y0, args, events), as `jaxdyn._sensitivities.forward_tangents` takes them. The
    sensitivity equations carry them along each segment and forward mode across its event
    (`_Segments.segment_with_tangents`)."""
    y0_tangents, args_tangents, events_tangents = tangents
    segments, t0, y0 = _segments(solver, t0, t1, dt0, y0, args, saveat, controller,
                                 diffrax.ForwardMode(), max_steps, events, max_events)
    hybrid = segments.watch.hybrid
    hybrid_tangents = Hybrid(events_tangents, hybrid.counts)
    segments = dataclasses.replace(segments, tangents=(args_tangents, hybrid_tangents))
    layout, k = args[3], y0_tangents.shape[0]

    def start(x):
        t0, y0, args, hybrid = x
        q0, u0 = layout.split(y0)
        references0 = hybrid.references(args[0], t0, q0, u0, args[1], segments.no_guards)
        return segments.with_system(args, hybrid).start(t0, y0, references0)

    state0 = forward_tangents(start, (t0, y0, args, hybrid),
                              (None, y0_tangents, args_tangents, hybrid_tangents), k)
    (carry, carry_tangents), (records, record_tangents) = jax.lax.scan(
        segments.segment_with_tangents, state0, jnp.arange(max_events + 1))
    record_tangents = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 1, 0), record_tangents)
    return forward_tangents(
        lambda x: eqx.filter(_hybrid_solution(x[0], x[1], segments.requested.ts, max_events),
                             eqx.is_array),
        (carry, records), (carry_tangents, record_tangents), k)


def _segments(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint, max_steps, events,
              max_events):
    """The `_Segments` of a hybrid solve, and its start (t0, y0)."""
    dynamics, p, _, layout = args
    q0, u0 = layout.split(y0)
    # Strongly typed times (a batch passes weakly typed ones): the event's root find is traced
    # once with the segment's times and must be called with the same types.
    t0, t1 = (jnp.asarray(t, y0.dtype) for t in (t0, t1))
    hybrid = Hybrid(events, tuple(guard_counts(events, dynamics, t0, q0, u0, p)))
    watch = Watch(hybrid, layout, y0.dtype)
    segments = _Segments(
        args=args, watch=watch, solver=solver, t1=t1, dt0=dt0, controller=controller,
        adjoint=adjoint, max_steps=max_steps, max_events=max_events,
        requested=saveat.subs[0], rests=can_rest(events, dynamics, t0, q0, u0, p),
        no_guards=jnp.zeros((watch.total,), bool), dtype=y0.dtype)
    return segments, t0, y0


# (hashed by identity: its bound `observe` is a static part of each segment's diffeqsolve)
@dataclasses.dataclass(frozen=True, eq=False)
class _Segments:
    """The segments of a hybrid solve (trace time): each the flow from the last event to the
    first zero crossing of a guard, the jump of the event that fired and the restart after
    it (`segment`, the body of the solve's scan)."""

    args: tuple  # the vector field's (dynamics, p, factorisation, layout)
    watch: Watch
    solver: diffrax.AbstractSolver
    t1: Array
    dt0: Any  # None or the first step
    controller: diffrax.AbstractStepSizeController
    adjoint: diffrax.AbstractAdjoint
    max_steps: int | None
    max_events: int
    requested: diffrax.SubSaveAt  # simulate's requested states
    rests: bool  # whether some guard can come to rest (the normal forces are then saved)
    no_guards: Bool[Array, " K"]
    dtype: np.dtype
    # the k tangents of the system's args and events, where the solve carries its tangents
    # (`segment_with_tangents`)
    tangents: Any = None

    def with_system(self, args, hybrid):
        """These segments, of the system's `args` and events `hybrid` (those differentiated)."""
        watch = copy.copy(self.watch)
        watch.hybrid = hybrid
        return dataclasses.replace(self, args=args, watch=watch)

    def observe(self, t, y, args):
        """The requested quantities, and the normal forces λ of the contacts held at rest."""
        seen = self.requested.fn(t, y, args)
        if not self.rests:
            return seen, None
        dynamics, p, factorisation, _, segment = args
        q, u = self.watch.layout.split(y)
        return seen, segment.hybrid.held_forces(dynamics, t, q, u, p, factorisation,
                                                segment.resting, segment.references)

    def start(self, t0, y0, references0):
        """The scan's carry before the first segment: the solve at (t0, y0), no guard resting
        or just fired, the saves NaN and no steps taken."""
        ts_requested = self.requested.ts
        total = self.watch.total
        start_args = (*self.args, Segment(t0, jnp.zeros((total,), self.dtype),
                                           self.no_guards, references0, self.no_guards,
                                           self.watch.hybrid))
        if ts_requested is None:
            saved0 = jax.eval_shape(lambda: self.observe(t0, y0, start_args))
        else:
            saved0 = jax.eval_shape(lambda: jax.vmap(
                lambda t: self.observe(t, y0, start_args))(ts_requested))
        saved0 = jax.tree_util.tree_map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), saved0)
        if ts_requested is None:
            saved0 = jax.tree_util.tree_map(lambda x: x[None], saved0)
        zero = jnp.zeros((), jnp.int32)
        return (t0, y0, jnp.zeros((total,), self.dtype), self.no_guards, references0,
                jnp.array(False), saved0,
                (t0, y0, jnp.array(False)), RESULTS.successful, (zero, zero, zero), zero)

    def segment(self, carry, index):
        """Segment `index` (the scan's body): the flow to the first crossing, the event's
        jump and the restart after it; the event's row of the `EventRecord`. Once the solve is
        done (no event before t1, a stop, a failure, the budget spent) a segment changes
        nothing."""
        t_from, segment_args, solution = self.flow(*carry[:6])
        return self.after_flow(carry, index, t_from, segment_args, solution)

    def segment_with_tangents(self, state, index):
        """`segment` with the k tangents of its carry (the scan's body where the solve
        carries its tangents): the flow by its sensitivity equations (`_flow_tangents`),
        the rest (the crossing, the jump, the restart) by forward mode."""
        carry, carry_tangents = state
        t_start, y_start, leaving, resting, references, done = carry[:6]
        d_t_start, d_y_start, d_leaving, _, d_references = carry_tangents[:5]
        d_args, d_hybrid = self.tangents
        t_from = jnp.where(done, self.t1, t_start)
        d_t_from = jnp.where(done, 0.0, d_t_start)
        segment_args = self.segment_args(t_from, y_start, leaving, resting, references)
        d_segment = dataclasses.replace(
            eqx.filter(segment_args[-1], eqx.is_inexact_array), t_start=d_t_from,
            leaving=d_leaving, references=d_references, hybrid=d_hybrid,
            orientation=jnp.zeros((d_y_start.shape[0], self.watch.total), self.dtype),
            offset=jnp.zeros((d_y_start.shape[0], self.watch.total), self.dtype))
        d_segment_args = (*d_args, d_segment)
        solution, d_solution = self._flow_tangents(t_from, d_t_from, y_start, d_y_start,
                                                   segment_args, d_segment_args)

        def rest(x):
            carry, t_from, segment_args, solution, args, hybrid = x
            return self.with_system(args, hybrid).after_flow(carry, index, t_from,
                                                             segment_args, solution)

        (carry, record), (carry_tangents, record_tangents) = forward_tangents(
            rest, (carry, t_from, segment_args, solution, self.args, self.watch.hybrid),
            (carry_tangents, d_t_from, d_segment_args, d_solution, d_args, d_hybrid),
            d_y_start.shape[0])
        return (carry, carry_tangents), (record, record_tangents)

    def after_flow(self, carry, index, t_from, segment_args, solution):
        """The rest of `segment` after its flow: the crossing, the jump, the restart."""
        (t_start, y_start, leaving, resting, references, done, saved, last, result, steps,
         count) = carry
        # (saved as asked: the states and times, the controller's state, the event mask)
        assert solution.ys is not None and solution.ts is not None
        assert solution.event_mask is not None and solution.controller_state is not None
        ran = ~done
        (requested_ys, last_y) = solution.ys
        t_end = solution.ts[1][0]
        y_end = last_y[0]
        # The held motion where the segment ends, formed once for the guards that fired and
        # for their rates before the jump (each use would otherwise write it into the program).
        dynamics, p, factorisation, layout = self.args
        q_end, u_end = layout.split(y_end)
        held = self.watch.hybrid.accelerations(dynamics, t_end, q_end, u_end, p, factorisation,
                                               resting, references)
        fired = self.watch.fired(solution.event_mask, t_end, y_end, segment_args, held) & ran
        happened = jnp.any(fired)
        saved = _keep_covered(saved, requested_ys, self.requested.ts, t_from, t_end, index,
                              ran)
        before, after = self.jump(t_end, y_end, fired, happened, resting, references, index,
                                  held)
        q_plus, u_plus, _, resting_plus, _, terminal = after
        y_next = self.watch.layout.join(q_plus, u_plus)
        references_next, leaving_next = self.restart(t_end, q_plus, u_plus, fired, resting,
                                                     resting_plus)
        failed, exhausted, new_result = _outcome(solution, result, ran, happened, terminal,
                                                 index, self.max_events)
        stalled = solution.controller_state[-1]
        last, steps = _tally(last, steps, ran, (t_end, y_end, stalled), solution.stats)
        record = _record(happened, t_end, before, after)
        count = count + (happened & (index < self.max_events)).astype(count.dtype)
        done = done | ~happened | terminal | failed | exhausted
        carry = (t_end, y_next, leaving_next, resting_plus, references_next, done, saved, last,
                 new_result, steps, count)
        return carry, record

    def flow(self, t_start, y_start, leaving, resting, references, done):
        """The flow of a segment: `diffrax.diffeqsolve` from the last event to t1 (from t1
        itself, an empty solve, once the solve is done), stopped at the first zero crossing of
        a guard armed at its start. Returns the segment's start, its args and its solution."""
        t_from = jnp.where(done, self.t1, t_start)
        segment_args = self.segment_args(t_from, y_start, leaving, resting, references)
        return t_from, segment_args, self._solve(t_from, y_start, segment_args,
                                                 self._save_times(t_from))

    def segment_args(self, t_from, y_start, leaving, resting, references):
        """The args of a segment's flow: the system's, and the segment's (`Segment`)."""
        segment = Segment(t_from, leaving, resting, references, self.no_guards,
                           self.watch.hybrid)
        return (*self.args, self.watch.start(t_from, y_start, (*self.args, segment)))

    def _save_times(self, t_from):
        """The requested save times, those before the segment's start clipped to it."""
        ts = self.requested.ts
        return None if ts is None else jnp.clip(ts, t_from, self.t1)

    def _saveat(self, ts):
        sub = diffrax.SubSaveAt(t1=True, fn=self.observe) if ts is None else \
            diffrax.SubSaveAt(ts=ts, fn=self.observe)
        return diffrax.SaveAt(subs=[sub, diffrax.SubSaveAt(t1=True)], controller_state=True)

    def _solve(self, t_from, y_start, segment_args, ts, field=segment_field, saveat=None,
               controller=None, event=None):
        """The segment's `diffrax.diffeqsolve` from (t_from, y_start) to t1, saving at `ts`
        (or t1) and where it ends; `field`, `saveat`, `controller` and `event` replace the
        plain solve's (those of the sensitivity solve)."""
        return diffrax.diffeqsolve(
            diffrax.ODETerm(field), self.solver, t_from, self.t1, self.dt0, y_start,
            args=segment_args, saveat=self._saveat(ts) if saveat is None else saveat,
            stepsize_controller=self.controller if controller is None else controller,
            adjoint=self.adjoint, max_steps=self.max_steps,
            event=self.watch.event if event is None else event, throw=False)

    def _flow_tangents(self, t_from, d_t_from, y_start, d_y_start, segment_args,
                       d_segment_args):
        """The flow of a segment with its k tangents (`SensitivityEquations`), given those of
        its start time t₀ (an event's time), its initial state and its args (the system's
        parameters, the events' coefficients, what the events remember). The sensitivities
        start at S_k(t₀) = ẏ₀ − f(t₀, y₀) ṫ₀ (the flow is met at fixed times, and starts
        later by ṫ₀); where a guard's crossing c(t*, y(t*)) = 0 ends the segment, its time
        moves by

            ṫ* = −(∂c/∂y S_k + ∂c/∂x ẋ_k) / (∂c/∂t + ∂c/∂y f),

        and the state there by S_k + f ṫ*. With the jump's derivative (forward mode through
        the event's map) and the next segment's start, this maps the sensitivities across
        the event by its saltation matrix (Aizerman and Gantmacher 1958). The derivative is
        that of the flow, the located crossing and the jump, which the discrete solve
        approximates to its tolerance. Returns the solution's arrays and their tangents."""
        ts = self._save_times(t_from)
        saveat = self._saveat(ts)
        controller = SensitivityEquations.controller_of(self.solver, y_start, saveat,
                                                        self.controller)
        n, k = y_start.shape[0], d_y_start.shape[0]
        leaves, treedef = jax.tree_util.tree_flatten(segment_args)
        directions = treedef.flatten_up_to(d_segment_args)
        equations = SensitivityEquations(
            segment_field, n, k, [d for x, d in zip(leaves, directions) if eqx.is_inexact_array(x)])
        start_rate = segment_field(t_from, y_start, segment_args)
        s0 = d_y_start - d_t_from[:, None] * start_rate[None]
        arguments = equations.arguments(segment_args)
        crossing = self.watch.event
        event = diffrax.Event(
            [functools.partial(_of_state, cond, equations) for cond in crossing.cond_fn],
            crossing.root_finder, crossing.direction)
        solution = self._solve(t_from, equations.state(y_start, s0), arguments, ts,
                               equations.field, equations.saveat(saveat), controller, event)
        assert solution.event_mask is not None
        out, sensitivities = equations.results(solution)
        # The crossing that ended the segment (none: it reached t1, ∂t* = 0).
        mask = jnp.stack([jnp.asarray(m) for m in solution.event_mask])
        t_end, y_end = out.ts[1][0], out.ys[1][0]
        s_end = sensitivities.ys[1][:, 0]

        def crossing_value(t, y, args):
            values = jnp.stack([cond(t, y, args) for cond in crossing.cond_fn])
            return jnp.sum(jnp.where(mask, values, 0.0))

        rate_end = segment_field(t_end, y_end, segment_args)
        _, along = jax.jvp(lambda t, y: crossing_value(t, y, segment_args), (t_end, y_end),
                           (jnp.ones_like(t_end), rate_end))
        _, across = equations.jvps(crossing_value, t_end, y_end, s_end, arguments)
        fired = jnp.any(mask)
        moved = jnp.where(fired, -across / jnp.where(fired, along, 1.0), 0.0)  # ∂t*/∂x (k,)
        sensitivities = eqx.tree_at(
            lambda s: (s.ts[1], s.ys[1]), sensitivities,
            (moved[:, None], (s_end + moved[:, None] * rate_end[None])[:, None]))
        if ts is None:  # the requested quantities are saved at t* too
            _, observed_rate = jax.jvp(lambda t, y: self.observe(t, y, segment_args),
                                       (t_end, y_end), (jnp.ones_like(t_end), rate_end))
            sensitivities = eqx.tree_at(
                lambda s: s.ys[0], sensitivities, jax.tree_util.tree_map(
                    lambda s, rate: s + moved.reshape((k,) + (1,) * (s.ndim - 1))
                    * rate.reshape(s.shape[1:])[None],
                    sensitivities.ys[0], observed_rate))
        return out, sensitivities

    def jump(self, t_end, y_end, fired, happened, resting, references, index, held):
        """The event that ended a segment: the state (q⁻, u⁻) just before it, the guard that
        fired and all guards' rates ġ⁻ there; then the jump (q⁺, u⁺) = Δ(q⁻, u⁻) of the event
        that guard belongs to (one event object fires at a time), its impulses Λ, the guards
        resting after it, whether it applies and whether the event stops the motion. No jump
        applies without an event, at a stop, or past the budget: the state stays. `held`:
        the held motion (q̇, u̇, λ) at the segment's end, which gives ġ⁻."""
        dynamics, p, factorisation, layout = self.args
        q, u = layout.split(y_end)
        which = jnp.argmax(fired)
        fired_owner = self.watch.owner[which]
        guard_rates = self.watch.hybrid.rates(dynamics, t_end, q, u, p, factorisation,
                                              resting, references, held)
        events = self.watch.hybrid.events
        terminal = jnp.asarray([e.terminal for e in events])[fired_owner]
        q_plus, u_plus, impulses, resting_plus = jax.lax.switch(
            fired_owner, [self._jump_branch(i, t_end, q, u, fired, resting)
                          for i in range(len(events))])
        apply_jump = happened & ~terminal & (index < self.max_events)
        q_plus = jnp.where(apply_jump, q_plus, q)
        u_plus = jnp.where(apply_jump, u_plus, u)
        impulses = jnp.where(apply_jump, impulses, 0.0)
        resting_plus = jnp.where(apply_jump, resting_plus, resting)
        return ((q, u, which, guard_rates),
                (q_plus, u_plus, impulses, resting_plus, apply_jump, terminal))

    def _jump_branch(self, i, t, q, u, fired, resting):
        """Event i's jump, a branch of the switch over the event that fired: its guards' rows
        of `fired` and `resting` in; (q⁺, u⁺), its impulses and its resting guards set in
        place among all the guards out."""
        mine = np.array([k for k, o in enumerate(self.watch.owner_list) if o == i])
        dynamics, p, _, _ = self.args

        def apply():
            q_plus, u_plus, impulses, resting_plus = self.watch.hybrid.events[i].jump(
                dynamics, t, q, u, p, fired[mine], resting[mine])
            return (q_plus, u_plus,
                    jnp.zeros((self.watch.total,), self.dtype).at[mine].set(impulses),
                    resting.at[mine].set(resting_plus))
        return apply

    def restart(self, t_end, q_plus, u_plus, fired, resting, resting_plus):
        """What the next segment starts from after the jump: what each event remembers of
        (t, q⁺, u⁺), and the side each fired guard leaves zero towards."""
        dynamics, p, factorisation, _ = self.args
        hybrid = self.watch.hybrid
        # ġ just after the jump: which side each fired guard leaves towards (none for a guard
        # that came to rest or was released: it changes meaning there).
        references_next = hybrid.references(dynamics, t_end, q_plus, u_plus, p, resting_plus)
        rates_after = hybrid.rates(dynamics, t_end, q_plus, u_plus, p, factorisation,
                                   resting_plus, references_next)
        same = resting_plus == resting
        leaving_next = jnp.where(fired & same, jnp.sign(rates_after), 0.0).astype(self.dtype)
        return references_next, leaving_next


def _of_state(cond, equations, t, y, args, **kwargs):
    """The guard crossing `cond` of the sensitivity solve's state [y; S], read on y."""
    return cond(t, equations.split(y)[0], args[0], **kwargs)


def _keep_covered(saved, requested_ys, ts_requested, t_from, t_end, index, ran):
    """The requested states, those this segment covers taken from its solve."""
    # The requested states this segment covers: (t_start, t_end], and t0 itself.
    if ts_requested is None:
        return jax.tree_util.tree_map(lambda new, old: jnp.where(ran, new, old),
                                      requested_ys, saved)
    covered = ((ts_requested > t_from) | ((index == 0) & (ts_requested >= t_from))) & (
        ts_requested <= t_end) & ran
    return jax.tree_util.tree_map(
        lambda new, old: jnp.where(covered.reshape((-1,) + (1,) * (new.ndim - 1)),
                                   new, old), requested_ys, saved)


def _outcome(solution, result, ran, happened, terminal, index, max_events):
    """The solve's result after a segment: whether it failed (a located event is a success
    here), whether it met an event past the budget, and the result so far."""
    segment_result = diffrax.RESULTS.where(
        solution.result == diffrax.RESULTS.event_occurred, diffrax.RESULTS.successful,
        solution.result)
    failed = ran & (segment_result != diffrax.RESULTS.successful)
    exhausted = ran & happened & ~terminal & (index >= max_events)
    new_result = RESULTS.where(failed, promoted(segment_result), result)
    new_result = RESULTS.where(exhausted, RESULTS.max_events_reached, new_result)
    return failed, exhausted, new_result


def _tally(last, steps, ran, now, stats):
    """The solve's last (time, state, stall flag), `now` where the segment ran, and its step
    counts with the segment's `stats` added."""
    last = jax.tree_util.tree_map(
        lambda new, old: jnp.where(ran, new, old),
        now, last)
    steps = jax.tree_util.tree_map(
        lambda total, s: total + jnp.where(ran, s, 0), steps,
        (stats["num_steps"], stats["num_accepted_steps"], stats["num_rejected_steps"]))
    return last, steps


def _record(happened, t_end, before, after):
    """A segment's row of the `EventRecord`, of `_Segments.jump`'s `before` and `after`: the
    event's time, its guard, the states before and after its jump, ġ⁻, Λ and the resting
    guards (NaN, and -1 in the guard, where no event happened; the state after NaN where no
    jump applied)."""
    q, u, which, guard_rates = before
    q_plus, u_plus, impulses, resting_plus, apply_jump, _ = after
    return (jnp.where(happened, t_end, jnp.nan),
            jnp.where(happened, which, -1),
            jnp.where(happened, q, jnp.nan), jnp.where(happened, u, jnp.nan),
            jnp.where(apply_jump, q_plus, jnp.nan),
            jnp.where(apply_jump, u_plus, jnp.nan),
            jnp.where(happened, guard_rates, jnp.nan),
            jnp.where(happened, impulses, jnp.nan),
            happened & resting_plus)


def _hybrid_solution(carry, records, ts_requested, max_events):
    """The `HybridSolution` of the scan's last carry and its rows of events (the row of the
    segment past the budget left out)."""
    (*_, (saved, forces), (t_last, y_last, stalled), result, steps, count) = carry
    records = jax.tree_util.tree_map(lambda x: x[:max_events], records)
    (t_events, guard, q_minus, u_minus, q_plus, u_plus, rates, impulses, resting) = records
    ts_out = t_last[None] if ts_requested is None else ts_requested
    return HybridSolution(
        ts=(ts_out, t_last[None]),
        ys=(saved, y_last[None]),
        controller_state=(None, None, stalled),
        result=result,
        stats={"num_steps": steps[0], "num_accepted_steps": steps[1],
               "num_rejected_steps": steps[2]},
        events=EventRecord(t=t_events, guard=guard, q_minus=q_minus, u_minus=u_minus,
                           q_plus=q_plus, u_plus=u_plus, guard_rates=rates,
                           impulses=impulses, resting=resting, count=count,
                           normal_forces=forces))
