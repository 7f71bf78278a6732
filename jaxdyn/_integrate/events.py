"""The solve of a hybrid system: flows between events, each event located and the solve
restarted after its jump, in a loop of a fixed number of segments (so that `jax.jit`,
`jax.vmap`, `jax.grad` and `jax.jacfwd` all apply).

Each segment is one `diffrax.diffeqsolve` from the last event to t1 that stops at the first
zero crossing of a guard, located by Newton's method on the step's dense interpolant
(`diffrax.Event`). Its derivative is that of the located crossing: the event time by the
implicit function theorem on g(t*, y(t*)) = 0, then the jump's Jacobian, which together give
the saltation matrix of the event (Aizerman and Gantmacher 1958) for the discrete solve.
"""

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

    def values(self, dynamics, t, q, u, p, factorisation, resting, references):
        """The guards, with the multiplier λ_i in place of each guard held at rest."""
        rows = self.rows(dynamics, t, q, u, p, resting, references)
        if rows is None:
            return _guards(self.events, dynamics, t, q, u, p)
        # the equations are formed only while some guard rests (a real branch unless vmapped)
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

    def rates(self, dynamics, t, q, u, p, factorisation, resting, references):
        """ġ of the guards (as they are, not their multipliers) along the motion at (t, q, u):
        one JVP along (1, q̇, u̇)."""
        rates, accelerations, _ = self.accelerations(dynamics, t, q, u, p, factorisation,
                                                     resting, references)
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
    `simulate`'s (the requested states, then the last state). Returns a `HybridSolution`."""
    dynamics, p, factorisation, layout = args
    q0, u0 = layout.split(y0)
    # Strongly typed times (a batch passes weakly typed ones): the event's root find is traced
    # once with the segment's times and must be called with the same types.
    t0, t1 = (jnp.asarray(t, y0.dtype) for t in (t0, t1))
    counts = _guard_counts(events, dynamics, t0, q0, u0, p)
    hybrid = _Hybrid(events, tuple(counts))
    total = sum(counts)
    owner_list = [i for i, c in enumerate(counts) for _ in range(c)]  # each guard's event
    owner = jnp.asarray(owner_list, jnp.int32)
    requested = saveat.subs[0]
    dtype = y0.dtype
    tiny = jnp.finfo(dtype).tiny

    directions = [DIRECTIONS[event.direction] for event, c in zip(events, counts)
                  for _ in range(c)]
    falling = np.array([d is False for d in directions])
    rising = np.array([d is True for d in directions])

    def guard_values(t, y, args, sided=False):
        """The guards (K,), as the segment that starts at t_start sees them."""
        dynamics, p, factorisation, _, (t_start, leaving, resting, references, _) = args
        q, u = layout.split(y)
        g = hybrid.values(dynamics, t, q, u, p, factorisation, resting, references)
        at_start = (t == t_start) & (leaving == 0)
        # A guard at zero when a segment starts that did not just fire (a ball released on
        # the floor) counts as just before its crossing, so that it cannot be passed unseen.
        g = jnp.where(at_start & falling & (g <= 0) & (g >= -AT_ZERO), tiny, g)
        g = jnp.where(at_start & rising & (g >= 0) & (g <= AT_ZERO), -tiny, g)
        if not sided:
            return g
        # At a restart the guards that just fired sit at zero: their side is the one the
        # motion leaves them towards (the sign of ġ⁺), so that the crossing that was
        # handled is not found again.
        side = leaving * jnp.maximum(jnp.abs(g), tiny)
        return jnp.where((t == t_start) & (leaving != 0), side, g)

    # The guards that cross one way are watched as one function, the least of them (each
    # taken so that it falls through zero): the first crossing of any is the first zero of
    # their least, located by one root find, and the field is written into the program once
    # rather than once per guard. A guard that cannot fire from where its segment starts
    # (on the far side of zero, or at zero after firing and leaving it that way) enters as
    # its absolute value, which touches zero where the guard crosses back without falling
    # through it. Guards that fire both ways are watched one by one.
    groups = [(np.flatnonzero(falling), 1.0), (np.flatnonzero(rising), -1.0)]
    groups = [(index, sign) for index, sign in groups if index.size]
    either = [i for i, d in enumerate(directions) if d is None]
    towards = jnp.asarray(np.where(rising, -1.0, 1.0), dtype)  # (falling taken as +)

    def watched(index, sign, g, armed):
        value = sign * g[index]
        return jnp.where(armed[index], value, jnp.abs(value))

    def least(index, sign):
        def cond_fn(t, y, args, **kwargs):
            armed = args[-1][-1]
            return jnp.min(watched(index, sign, guard_values(t, y, args, sided=True),
                                   armed))
        return cond_fn

    def single(index):
        def cond_fn(t, y, args, **kwargs):
            return guard_values(t, y, args, sided=True)[index]
        return cond_fn

    def armed_at(t, y, args):
        """Which guards start a segment where they can fire: on the side they fall from, or
        at zero just after firing and moving to that side."""
        leaving = args[-1][1]
        g = guard_values(t, y, args)
        just_fired = (leaving != 0) & (jnp.abs(g) <= AT_ZERO)
        return jnp.where(just_fired, towards * leaving > 0, towards * g > 0)

    def which_fired(mask, t, y, args):
        """(K,) the guards whose crossing ended the segment, from the event's mask."""
        g = guard_values(t, y, args)
        armed = args[-1][-1]
        fired = jnp.zeros((total,), bool)
        for (index, sign), hit in zip(groups, mask[:len(groups)]):
            first = jnp.asarray(index)[jnp.argmin(watched(index, sign, g, armed))]
            fired = fired.at[first].set(hit)
        for i, hit in zip(either, mask[len(groups):]):
            fired = fired.at[i].set(hit)
        return fired

    root_finder = optx.Newton(rtol=1e-12 if dtype == jnp.float64 else 1e-6,
                              atol=1e-12 if dtype == jnp.float64 else 1e-6)
    event = diffrax.Event([least(index, sign) for index, sign in groups]
                          + [single(i) for i in either], root_finder,
                          [False] * len(groups) + [None] * len(either))
    ts_requested = requested.ts
    no_guards = jnp.zeros((total,), bool)
    references0 = hybrid.references(dynamics, t0, q0, u0, p, no_guards)
    rests = can_rest(events, dynamics, t0, q0, u0, p)

    def observe(t, y, args):
        """The requested quantities, and the normal forces λ of the contacts held at rest."""
        seen = requested.fn(t, y, args)
        if not rests:
            return seen, None
        dynamics, p, factorisation, _, (_, _, resting, references, _) = args
        q, u = layout.split(y)
        return seen, hybrid.held_forces(dynamics, t, q, u, p, factorisation, resting,
                                        references)

    def segment(carry, index):
        (t_start, y_start, leaving, resting, references, done, saved, last, result, steps,
         count) = carry
        t_from = jnp.where(done, t1, t_start)
        if ts_requested is None:
            sub = diffrax.SubSaveAt(t1=True, fn=observe)
        else:
            sub = diffrax.SubSaveAt(ts=jnp.clip(ts_requested, t_from, t1), fn=observe)
        segment_args = (*args, (t_from, leaving, resting, references, no_guards))
        segment_args = (*args, (t_from, leaving, resting, references,
                                armed_at(t_from, y_start, segment_args)))
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(hybrid.field), solver, t_from, t1, dt0, y_start,
            args=segment_args,
            saveat=diffrax.SaveAt(subs=[sub, diffrax.SubSaveAt(t1=True)],
                                  controller_state=True),
            stepsize_controller=controller, adjoint=adjoint, max_steps=max_steps,
            event=event, throw=False)
        # (saved as asked: the states and times, the controller's state, the event mask)
        assert solution.ys is not None and solution.ts is not None
        assert solution.event_mask is not None and solution.controller_state is not None
        ran = ~done
        (requested_ys, last_y) = solution.ys
        t_end = solution.ts[1][0]
        y_end = last_y[0]
        fired = which_fired(solution.event_mask, t_end, y_end, segment_args) & ran
        happened = jnp.any(fired)
        # The requested states this segment covers: (t_start, t_end], and t0 itself.
        if ts_requested is None:
            saved = jax.tree_util.tree_map(lambda new, old: jnp.where(ran, new, old),
                                           requested_ys, saved)
        else:
            covered = ((ts_requested > t_from) | ((index == 0) & (ts_requested >= t_from))) & (
                ts_requested <= t_end) & ran
            saved = jax.tree_util.tree_map(
                lambda new, old: jnp.where(covered.reshape((-1,) + (1,) * (new.ndim - 1)),
                                           new, old), requested_ys, saved)
        # The jump of the event whose guard fired (one event object fires at a time).
        q, u = layout.split(y_end)
        which = jnp.argmax(fired)
        fired_owner = owner[which]
        guard_rates = hybrid.rates(dynamics, t_end, q, u, p, factorisation, resting,
                                   references)

        def jump(i):
            mine = np.array([k for k, o in enumerate(owner_list) if o == i])

            def apply():
                q_plus, u_plus, impulses, resting_plus = events[i].jump(
                    dynamics, t_end, q, u, p, fired[mine], resting[mine])
                return (q_plus, u_plus, jnp.zeros((total,), dtype).at[mine].set(impulses),
                        resting.at[mine].set(resting_plus))
            return apply

        terminal = jnp.asarray([e.terminal for e in events])[fired_owner]
        q_plus, u_plus, impulses, resting_plus = jax.lax.switch(
            fired_owner, [jump(i) for i in range(len(events))])
        apply_jump = happened & ~terminal & (index < max_events)
        q_plus = jnp.where(apply_jump, q_plus, q)
        u_plus = jnp.where(apply_jump, u_plus, u)
        impulses = jnp.where(apply_jump, impulses, 0.0)
        resting_plus = jnp.where(apply_jump, resting_plus, resting)
        y_next = layout.join(q_plus, u_plus)
        # ġ just after the jump: which side each fired guard leaves towards (none for a guard
        # that came to rest or was released: it changes meaning there).
        references_next = hybrid.references(dynamics, t_end, q_plus, u_plus, p, resting_plus)
        rates_after = hybrid.rates(dynamics, t_end, q_plus, u_plus, p, factorisation,
                                   resting_plus, references_next)
        same = resting_plus == resting
        leaving_next = jnp.where(fired & same, jnp.sign(rates_after), 0.0).astype(dtype)

        segment_result = diffrax.RESULTS.where(
            solution.result == diffrax.RESULTS.event_occurred, diffrax.RESULTS.successful,
            solution.result)
        failed = ran & (segment_result != diffrax.RESULTS.successful)
        exhausted = ran & happened & ~terminal & (index >= max_events)
        new_result = RESULTS.where(failed, RESULTS.promote(segment_result), result)
        new_result = RESULTS.where(exhausted, RESULTS.max_events_reached, new_result)
        stalled = solution.controller_state[-1]
        last = jax.tree_util.tree_map(
            lambda new, old: jnp.where(ran, new, old),
            (t_end, y_end, stalled), last)
        steps = jax.tree_util.tree_map(
            lambda total, s: total + jnp.where(ran, s, 0), steps,
            (solution.stats["num_steps"], solution.stats["num_accepted_steps"],
             solution.stats["num_rejected_steps"]))
        record = (jnp.where(happened, t_end, jnp.nan),
                  jnp.where(happened, which, -1),
                  jnp.where(happened, q, jnp.nan), jnp.where(happened, u, jnp.nan),
                  jnp.where(apply_jump, q_plus, jnp.nan),
                  jnp.where(apply_jump, u_plus, jnp.nan),
                  jnp.where(happened, guard_rates, jnp.nan),
                  jnp.where(happened, impulses, jnp.nan),
                  happened & resting_plus)
        count = count + (happened & (index < max_events)).astype(count.dtype)
        done = done | ~happened | terminal | failed | exhausted
        carry = (t_end, y_next, leaving_next, resting_plus, references_next, done, saved, last,
                 new_result, steps, count)
        return carry, record

    start_args = (*args, (t0, jnp.zeros((total,), dtype), no_guards, references0, no_guards))
    if ts_requested is None:
        saved0 = jax.eval_shape(lambda: observe(t0, y0, start_args))
    else:
        saved0 = jax.eval_shape(lambda: jax.vmap(lambda t: observe(t, y0, start_args))(
            ts_requested))
    saved0 = jax.tree_util.tree_map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), saved0)
    if ts_requested is None:
        saved0 = jax.tree_util.tree_map(lambda x: x[None], saved0)
    zero = jnp.zeros((), jnp.int32)
    carry0 = (t0, y0, jnp.zeros((total,), dtype), no_guards, references0, jnp.array(False),
              saved0,
              (t0, y0, jnp.array(False)), RESULTS.successful, (zero, zero, zero), zero)
    carry, records = jax.lax.scan(segment, carry0, jnp.arange(max_events + 1))
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
