"""The solve of a hybrid system: flows between events, each event located and the solve
restarted after its jump, in a loop of a fixed number of segments (so that `jax.jit`,
`jax.vmap`, `jax.grad` and `jax.jacfwd` all apply).

Each segment is one `diffrax.diffeqsolve` from the last event to t1 that stops at the first
zero crossing of a guard, located by Newton's method on the step's dense interpolant
(`diffrax.Event`). Its derivative is that of the located crossing: the event time by the
implicit function theorem on g(t*, y(t*)) = 0, then the jump's Jacobian, which together give
the saltation matrix of the event (Aizerman and Gantmacher 1958) for the discrete solve.
"""

import dataclasses
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._dynamics import equations_of_motion
from .._events import DIRECTIONS, AbstractEvent, hold
from .._solution import RESULTS

#: Default budget of events per solve (`simulate(..., max_events=...)`).
MAX_EVENTS = 64
#: A guard within this of zero at the start of a segment is taken to be just before its
#: crossing (a contact closed at the start is met at once rather than passed through).
AT_ZERO = 1e-9


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


def check_events(events, max_events) -> tuple[AbstractEvent, ...]:
    """Trace-time check of `simulate`'s `events` and `max_events`."""
    if isinstance(events, AbstractEvent):
        events = (events,)
    events = tuple(events)
    for event in events:
        if not isinstance(event, AbstractEvent):
            raise ValueError("events must be jaxdyn events (jaxdyn.Event, "
                             f"jaxdyn.UnilateralContact), got {type(event).__name__}.")
    if not isinstance(max_events, int) or max_events < 1:
        raise ValueError(f"max_events must be a positive int, got {max_events!r}.")
    return events


def _guard_counts(events, dynamics, t, q, u, p):
    return [jax.eval_shape(lambda e=e: e.guards(dynamics, t, q, u, p)).shape[0]
            for e in events]


def can_rest(events, dynamics, t, q, u, p) -> bool:
    """Whether some guard of `events` can come to rest (its event has held rows): the vector
    field then carries the held-force solve (trace time)."""
    counts = _guard_counts(events, dynamics, t, q, u, p)
    hybrid = _Hybrid(tuple(events), tuple(counts))
    resting = jnp.zeros((sum(counts),), bool)
    references = hybrid.references(dynamics, t, q, u, p, resting)
    return jax.eval_shape(lambda: hybrid.rows(dynamics, t, q, u, p, resting,
                                              references)) is not None


def _guards(events, dynamics, t, q, u, p):
    return jnp.concatenate([e.guards(dynamics, t, q, u, p) for e in events])


class _Hybrid(eqx.Module):
    """The events of a solve and how their guards are laid out: the vector field with the
    resting contacts held, and the guards with their multipliers in place of those held."""

    events: tuple
    counts: tuple[int, ...] = eqx.field(static=True)

    def split(self, values):
        """`values` over all guards, as one array per event."""
        return jnp.split(values, np.cumsum(self.counts)[:-1])

    def rows(self, dynamics, t, q, u, p, resting, references):
        """Each event's held rows (E, W, b, active) (None for an event that cannot rest), or
        None if no event can rest."""
        return _rows(self, dynamics, t, q, u, p, resting, references)

    def accelerations(self, dynamics, t, q, u, p, factorisation, resting, references):
        """(q̇, u̇, λ): the equations of motion with the rows of the `resting` guards held and
        their multipliers λ (zero for the others; None if no event can rest)."""
        return _accelerations(self, dynamics, t, q, u, p, factorisation, resting, references)

    def _accelerations(self, dynamics, t, q, u, p, factorisation, resting, references):
        rates, free, _, _ = equations_of_motion(dynamics, t, q, u, p, factorisation)
        rows = self.rows(dynamics, t, q, u, p, resting, references)
        if rows is None:
            return rates, free, None
        rows = [r for r in rows if r is not None]
        rows = tuple(jnp.concatenate(parts) for parts in zip(*rows))
        active = rows[3]
        accelerations, forces = jax.lax.cond(
            jnp.any(active), lambda: hold(dynamics, t, q, u, p, free, rows),
            lambda: (free, jnp.zeros(active.shape, u.dtype)))
        return rates, accelerations, forces

    def _per_event(self, rows, forces):
        """The multipliers λ of all held rows, as one array per event (None where it has no
        rows)."""
        sizes = [0 if r is None else r[3].shape[0] for r in rows]
        parts = jnp.split(forces, np.cumsum(sizes)[:-1])
        return [None if r is None else f for r, f in zip(rows, parts)]

    def values(self, dynamics, t, q, u, p, factorisation, resting, references, held=None):
        """The guards, with the multiplier λ_i in place of each guard held at rest. `held`:
        the held motion (q̇, u̇, λ) at this state where the caller has it already."""
        rows = self.rows(dynamics, t, q, u, p, resting, references)
        if rows is None:
            return _guards(self.events, dynamics, t, q, u, p)
        if held is not None:
            forces = held[2]
        else:
            # the equations are formed only while some guard rests (a real branch unless
            # vmapped)
            size = sum(r[3].shape[0] for r in rows if r is not None)
            forces = jax.lax.cond(
                jnp.any(resting),
                lambda: self.accelerations(dynamics, t, q, u, p, factorisation, resting,
                                           references)[2],
                lambda: jnp.zeros((size,), u.dtype))
        return jnp.concatenate([
            e.guards(dynamics, t, q, u, p) if f is None else
            e.held_values(dynamics, t, q, u, p, f, r, ref)
            for e, f, r, ref in zip(self.events, self._per_event(rows, forces),
                                    self.split(resting), references)])

    def held_forces(self, dynamics, t, q, u, p, factorisation, resting, references):
        """The force each guard carries at rest (zero for the others), shape (K,)."""
        rows = self.rows(dynamics, t, q, u, p, resting, references)
        forces = self.accelerations(dynamics, t, q, u, p, factorisation, resting,
                                    references)[2]
        return jnp.concatenate([
            jnp.zeros((c,), u.dtype) if f is None else e.held_forces(f, r, p)
            for e, c, f, r in zip(self.events, self.counts, self._per_event(rows, forces),
                                  self.split(resting))])

    def references(self, dynamics, t, q, u, p, resting):
        """What each event remembers of a segment that starts at (t, q, u)."""
        return tuple(e.reference(dynamics, t, q, u, p, r)
                     for e, r in zip(self.events, self.split(resting)))

    def field(self, t, y, args):
        dynamics, p, factorisation, layout, (_, _, resting, references, _) = args
        q, u = layout.split(y)
        rates, accelerations, _ = self.accelerations(dynamics, t, q, u, p, factorisation,
                                                     resting, references)
        return layout.join(rates, accelerations)

    def rates(self, dynamics, t, q, u, p, factorisation, resting, references, held=None):
        """ġ of the guards (as they are, not their multipliers) along the motion at (t, q, u):
        one JVP along (1, q̇, u̇). `held`: the held motion there, where the caller has it."""
        if held is None:
            held = self.accelerations(dynamics, t, q, u, p, factorisation, resting,
                                      references)
        rates, accelerations, _ = held
        rates, accelerations = jax.lax.stop_gradient((rates, accelerations))
        return jax.jvp(lambda t, q, u: _guards(self.events, dynamics, t, q, u, p),
                       (t, q, u), (jnp.ones_like(t), rates, accelerations))[1]


# The guards' rows and the held accelerations are asked for at every stage of a step, by the
# guards' rates and by the jump: each is traced once per solve (a nested jit, inlined by XLA)
# rather than once per use. A chain of two rods striking a floor traced its guards' rows 48
# times and spent 2.5 of its 8 s of tracing on them.
@eqx.filter_jit
def _rows(hybrid, dynamics, t, q, u, p, resting, references):
    rows = [e.held_rows(dynamics, t, q, u, p, r, ref)
            for e, r, ref in zip(hybrid.events, hybrid.split(resting), references)]
    return None if all(r is None for r in rows) else rows


@eqx.filter_jit
def _accelerations(hybrid, dynamics, t, q, u, p, factorisation, resting, references):
    return hybrid._accelerations(dynamics, t, q, u, p, factorisation, resting, references)


def hybrid_solve(solver, t0, t1, dt0, y0, args, saveat, controller, adjoint, max_steps,
                 events, max_events):
    """Segments of `diffrax.diffeqsolve` between events, at most `max_events` events.

    `args` is the vector field's (dynamics, p, factorisation, layout); `saveat` is
    `simulate`'s (the requested states, then the last state). Returns a `HybridSolution`:
    the scan over max_events + 1 segments (`_Segments.segment`), the last one to reach t1
    or to meet the event past the budget."""
    dynamics, p, _, layout = args
    q0, u0 = layout.split(y0)
    # Strongly typed times (a batch passes weakly typed ones): the event's root find is traced
    # once with the segment's times and must be called with the same types.
    t0, t1 = (jnp.asarray(t, y0.dtype) for t in (t0, t1))
    counts = _guard_counts(events, dynamics, t0, q0, u0, p)
    hybrid = _Hybrid(events, tuple(counts))
    watch = _Watch(hybrid, layout, y0.dtype)
    no_guards = jnp.zeros((watch.total,), bool)
    references0 = hybrid.references(dynamics, t0, q0, u0, p, no_guards)
    segments = _Segments(
        args=args, watch=watch, solver=solver, t1=t1, dt0=dt0, controller=controller,
        adjoint=adjoint, max_steps=max_steps, max_events=max_events,
        requested=saveat.subs[0], rests=can_rest(events, dynamics, t0, q0, u0, p),
        no_guards=no_guards, dtype=y0.dtype)
    carry0 = segments.start(t0, y0, references0)
    carry, records = jax.lax.scan(segments.segment, carry0, jnp.arange(max_events + 1))
    return _hybrid_solution(carry, records, segments.requested.ts, max_events)


class _Watch:
    """The guards of a hybrid solve as its segments watch them for a crossing (built at trace
    time): which event each guard belongs to, each guard's value as the segment that starts
    at t_start sees it, which guards can fire from there, the `diffrax.Event` whose zero
    crossing ends a segment, and which guard that crossing was."""

    def __init__(self, hybrid, layout, dtype):
        self.hybrid, self.layout = hybrid, layout
        counts = hybrid.counts
        self.total = sum(counts)
        self.owner_list = [i for i, c in enumerate(counts) for _ in range(c)]  # each guard's event
        self.owner = jnp.asarray(self.owner_list, jnp.int32)
        self.tiny = jnp.finfo(dtype).tiny
        directions = [DIRECTIONS[event.direction] for event, c in zip(hybrid.events, counts)
                      for _ in range(c)]
        self.falling = np.array([d is False for d in directions])
        self.rising = np.array([d is True for d in directions])
        # The guards that cross one way are watched as one function, the least of them (each
        # taken so that it falls through zero): the first crossing of any is the first zero of
        # their least, located by one root find, and the field is written into the program once
        # rather than once per guard. A guard that cannot fire from where its segment starts
        # (on the far side of zero, or at zero after firing and leaving it that way) enters as
        # its absolute value, which touches zero where the guard crosses back without falling
        # through it. Guards that fire both ways are watched one by one.
        groups = [(np.flatnonzero(self.falling), 1.0), (np.flatnonzero(self.rising), -1.0)]
        self.groups = [(index, sign) for index, sign in groups if index.size]
        self.either = [i for i, d in enumerate(directions) if d is None]
        self.towards = jnp.asarray(np.where(self.rising, -1.0, 1.0), dtype)  # (falling taken as +)
        self.event = self._crossing_event(dtype)

    def values(self, t, y, args, sided=False, held=None):
        """The guards g (K,) at (t, y), as the segment that starts at t_start sees them: with
        `sided`, those that just fired are put on the side the motion leaves them towards.
        `held`: the held motion at (t, y), where the caller has it."""
        dynamics, p, factorisation, _, (t_start, leaving, resting, references, _) = args
        q, u = self.layout.split(y)
        g = self.hybrid.values(dynamics, t, q, u, p, factorisation, resting, references,
                               held)
        at_start = (t == t_start) & (leaving == 0)
        # A guard at zero when a segment starts that did not just fire (a ball released on
        # the floor) counts as just before its crossing, so that it cannot be passed unseen.
        g = jnp.where(at_start & self.falling & (g <= 0) & (g >= -AT_ZERO), self.tiny, g)
        g = jnp.where(at_start & self.rising & (g >= 0) & (g <= AT_ZERO), -self.tiny, g)
        if not sided:
            return g
        # At a restart the guards that just fired sit at zero: their side is the one the
        # motion leaves them towards (the sign of ġ⁺), so that the crossing that was
        # handled is not found again.
        side = leaving * jnp.maximum(jnp.abs(g), self.tiny)
        return jnp.where((t == t_start) & (leaving != 0), side, g)

    def _crossing_event(self, dtype):
        """The `diffrax.Event` that stops a segment at the first zero crossing of a guard: the
        least of each one-way group, each guard of either direction alone, its crossing
        located by Newton's method on the step's dense interpolant."""

        def least(index, sign):
            """The least of the one-way guards `index`, each falling through zero as it fires."""
            def cond_fn(t, y, args, **kwargs):
                armed = args[-1][-1]
                return jnp.min(_watched(index, sign, self.values(t, y, args, sided=True),
                                        armed))
            return cond_fn

        def single(index):
            """Guard `index` alone (it fires either way)."""
            def cond_fn(t, y, args, **kwargs):
                return self.values(t, y, args, sided=True)[index]
            return cond_fn

        root_finder = optx.Newton(rtol=1e-12 if dtype == jnp.float64 else 1e-6,
                                  atol=1e-12 if dtype == jnp.float64 else 1e-6)
        return diffrax.Event([least(index, sign) for index, sign in self.groups]
                             + [single(i) for i in self.either], root_finder,
                             [False] * len(self.groups) + [None] * len(self.either))

    def armed(self, t, y, args):
        """Which guards start a segment where they can fire: on the side they fall from, or
        at zero just after firing and moving to that side."""
        leaving = args[-1][1]
        g = self.values(t, y, args)
        just_fired = (leaving != 0) & (jnp.abs(g) <= AT_ZERO)
        return jnp.where(just_fired, self.towards * leaving > 0, self.towards * g > 0)

    def fired(self, mask, t, y, args, held):
        """(K,) the guards whose crossing ended the segment, from the event's mask: in a
        one-way group, the least of its guards. `held`: the held motion at (t, y)."""
        g = self.values(t, y, args, held=held)
        armed = args[-1][-1]
        fired = jnp.zeros((self.total,), bool)
        for (index, sign), hit in zip(self.groups, mask[:len(self.groups)]):
            first = jnp.asarray(index)[jnp.argmin(_watched(index, sign, g, armed))]
            fired = fired.at[first].set(hit)
        for i, hit in zip(self.either, mask[len(self.groups):]):
            fired = fired.at[i].set(hit)
        return fired


def _watched(index, sign, g, armed):
    """The guards `index` of one group, each taken so that it falls through zero where it
    fires (sign g), and as |sign g| where it cannot fire from where its segment starts."""
    value = sign * g[index]
    return jnp.where(armed[index], value, jnp.abs(value))


# (hashed by identity: its bound `observe` is a static part of each segment's diffeqsolve)
@dataclasses.dataclass(frozen=True, eq=False)
class _Segments:
    """The segments of a hybrid solve (trace time): each the flow from the last event to the
    first zero crossing of a guard, the jump of the event that fired and the restart after
    it (`segment`, the body of the solve's scan)."""

    args: tuple  # the vector field's (dynamics, p, factorisation, layout)
    watch: _Watch
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

    def observe(self, t, y, args):
        """The requested quantities, and the normal forces λ of the contacts held at rest."""
        seen = self.requested.fn(t, y, args)
        if not self.rests:
            return seen, None
        dynamics, p, factorisation, _, (_, _, resting, references, _) = args
        q, u = self.watch.layout.split(y)
        return seen, self.watch.hybrid.held_forces(dynamics, t, q, u, p, factorisation,
                                                   resting, references)

    def start(self, t0, y0, references0):
        """The scan's carry before the first segment: the solve at (t0, y0), no guard resting
        or just fired, the saves NaN and no steps taken."""
        ts_requested = self.requested.ts
        total = self.watch.total
        start_args = (*self.args, (t0, jnp.zeros((total,), self.dtype), self.no_guards,
                                   references0, self.no_guards))
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
        (t_start, y_start, leaving, resting, references, done, saved, last, result, steps,
         count) = carry
        t_from, segment_args, solution = self.flow(t_start, y_start, leaving, resting,
                                                   references, done)
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
        ts_requested = self.requested.ts
        if ts_requested is None:
            sub = diffrax.SubSaveAt(t1=True, fn=self.observe)
        else:
            sub = diffrax.SubSaveAt(ts=jnp.clip(ts_requested, t_from, self.t1),
                                    fn=self.observe)
        segment_args = (*self.args, (t_from, leaving, resting, references, self.no_guards))
        segment_args = (*self.args, (t_from, leaving, resting, references,
                                     self.watch.armed(t_from, y_start, segment_args)))
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(self.watch.hybrid.field), self.solver, t_from, self.t1, self.dt0,
            y_start, args=segment_args,
            saveat=diffrax.SaveAt(subs=[sub, diffrax.SubSaveAt(t1=True)],
                                  controller_state=True),
            stepsize_controller=self.controller, adjoint=self.adjoint,
            max_steps=self.max_steps, event=self.watch.event, throw=False)
        return t_from, segment_args, solution

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
    new_result = RESULTS.where(failed, RESULTS.promote(segment_result), result)
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
