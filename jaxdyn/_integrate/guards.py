"""The guards of a hybrid solve: the events as the vector field and the guards see them
between events (the resting contacts held, their multipliers in place of their guards), what
a segment's flow reads of them, and how a segment watches its guards for the first zero
crossing (`jaxdyn._integrate.events` solves segment by segment)."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._dynamics import equations_of_motion
from .._events import DIRECTIONS, AbstractEvent, hold
from .crossing import FirstCrossing

#: A guard within this of zero at the start of a segment is taken to be just before its
#: crossing (a contact closed at the start is met at once rather than passed through), or,
#: having just fired, at its crossing (float64; `at_zero` for other precisions).
AT_ZERO = 1e-9


def at_zero(dtype) -> float:
    """`AT_ZERO` in `dtype`: at least a hundred times its resolution, the round-off of a
    located crossing (in float32, a ball's height after its bounce is about 10⁻⁷ off zero)."""
    return max(AT_ZERO, 100 * float(jnp.finfo(dtype).eps))


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


def guard_counts(events, dynamics, t, q, u, p):
    return [jax.eval_shape(lambda e=e: e.guards(dynamics, t, q, u, p)).shape[0]
            for e in events]


def can_rest(events, dynamics, t, q, u, p) -> bool:
    """Whether some guard of `events` can come to rest (its event has held rows): the vector
    field then carries the held-force solve (trace time)."""
    counts = guard_counts(events, dynamics, t, q, u, p)
    hybrid = Hybrid(tuple(events), tuple(counts))
    resting = jnp.zeros((sum(counts),), bool)
    references = hybrid.references(dynamics, t, q, u, p, resting)
    return jax.eval_shape(lambda: hybrid.rows(dynamics, t, q, u, p, resting,
                                              references)) is not None


def _guards(events, dynamics, t, q, u, p):
    return jnp.concatenate([e.guards(dynamics, t, q, u, p) for e in events])


class Hybrid(eqx.Module):
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


class Segment(eqx.Module):
    """What the flow of a segment reads besides the system (the last of its args): where it
    started, the side each guard that just fired leaves zero towards, the guards held at
    rest, what each event remembers, which guards can fire, and the events themselves (an
    argument, not a constant of the flow, so that their coefficients are differentiated
    through the flow's own derivative rule); `orientation`, the sign that makes each guard fall
    through zero where it fires; `offset`, the values at the start of the guards that just
    fired (zero but for the round-off of the located crossing), which the segment measures
    them from."""

    t_start: Array
    leaving: Array
    resting: Array
    references: tuple
    armed: Array
    hybrid: Hybrid
    orientation: Array | None = None
    offset: Array | None = None


def segment_field(t, y, args):
    """The vector field of a segment: the equations of motion with the resting guards held."""
    dynamics, p, factorisation, layout, segment = args
    q, u = layout.split(y)
    rates, accelerations, _ = segment.hybrid.accelerations(
        dynamics, t, q, u, p, factorisation, segment.resting, segment.references)
    return layout.join(rates, accelerations)


class Watch:
    """The guards of a hybrid solve as its segments watch them for a crossing (built at trace
    time): which event each guard belongs to, each guard's value as the segment that starts
    at t_start sees it, which guards can fire from there, the `diffrax.Event` whose zero
    crossing ends a segment, and which guard that crossing was.

    All the guards are watched as one function, the least of them, each oriented so that it
    falls through zero where it fires: a falling guard as it is, a rising one negated, one
    that fires either way as the side it starts the segment on makes it. The first crossing
    of any guard is then the first zero of their least, located by one root find, and the
    guards are written into the program once (watched one by one, several guards crossing
    within one step would be told apart by the order they were listed in, not by time). A
    guard that cannot fire from where its segment starts (on the far side of zero, or at zero
    after firing and leaving it that way) enters as its absolute value, which touches zero
    where the guard crosses back without falling through it."""

    def __init__(self, hybrid, layout, dtype):
        self.hybrid, self.layout = hybrid, layout
        counts = hybrid.counts
        self.total = sum(counts)
        self.owner_list = [i for i, c in enumerate(counts) for _ in range(c)]  # each guard's event
        self.owner = jnp.asarray(self.owner_list, jnp.int32)
        self.tiny = jnp.finfo(dtype).tiny
        self.at_zero = at_zero(dtype)
        directions = [DIRECTIONS[event.direction] for event, c in zip(hybrid.events, counts)
                      for _ in range(c)]
        self.either = np.array([d is None for d in directions])
        # (falling +1, rising −1, either: set by each segment's start)
        self.towards = jnp.asarray([{False: 1.0, True: -1.0, None: 0.0}[d] for d in directions],
                                   dtype)
        self.event = diffrax.Event([self._least], FirstCrossing(), [False])

    def values(self, t, y, args, held=None):
        """The guards g (K,) at (t, y), those that just fired measured from where the segment
        restarted them. `held`: the held motion at (t, y), where the caller has it."""
        dynamics, p, factorisation, _, segment = args
        q, u = self.layout.split(y)
        g = segment.hybrid.values(dynamics, t, q, u, p, factorisation, segment.resting,
                                  segment.references, held)
        return g if segment.offset is None else g - segment.offset

    def _oriented(self, g, t, segment, orientation):
        """The guards g oriented to fall through zero where they fire; one at zero when a
        segment starts that did not just fire (a ball released on the floor) counts as just
        before its crossing, so that it cannot be passed unseen."""
        w = orientation * g
        fresh = (t == segment.t_start) & (segment.leaving == 0)
        return jnp.where(fresh & (w <= 0) & (w >= -self.at_zero), self.tiny, w)

    def watched(self, t, y, args, sided=False, held=None):
        """The guards as the segment watches them (K,): oriented, and as their absolute values
        where they cannot fire. With `sided`, those that just fired are put on the side the
        motion leaves them towards (the sign of ġ⁺), so that the crossing that was handled is
        not found again."""
        segment = args[-1]
        w = self._oriented(self.values(t, y, args, held), t, segment, segment.orientation)
        if sided:
            side = segment.orientation * segment.leaving * jnp.maximum(jnp.abs(w), self.tiny)
            w = jnp.where((t == segment.t_start) & (segment.leaving != 0), side, w)
        return jnp.where(segment.armed, w, jnp.abs(w))

    def _least(self, t, y, args, **kwargs):
        """The least of the watched guards: the `diffrax.Event`'s condition, whose zero
        crossing (falling) ends the segment, located on the step's dense interpolant by
        regula falsi (`FirstCrossing`). In JAX's default float (diffrax gives the crossing
        functions that did not fire a Python 0.0, which a float32 guard in 64-bit mode would
        not match)."""
        return jnp.min(self.watched(t, y, args, sided=True)).astype(jnp.result_type(float))

    def start(self, t, y, args):
        """The segment's `Segment` (the last of `args`) completed where it starts at (t, y):
        the guards' orientation, which can fire (on the side they fall from, or at zero just
        after firing and moving to that side), and the offset of those that just fired.

        A guard that fires either way is oriented by the side it starts on; one at zero that
        did not just fire, by the way the motion leaves zero (so that it fires at once, as a
        one-way guard at zero does when the motion takes it through).

        A guard that just fired restarts at its located crossing, a round-off away from zero
        and perhaps on the side it crossed to. Measured as it is, it would cross zero again
        an instant after the restart as the motion leaves it (a ball's height, −10⁻¹⁸ after
        its bounce, rising through zero 10⁻¹⁶ s later), a crossing that bracketing the first
        zero in the first step would find. So it is measured from where it restarted."""
        segment = args[-1]
        g = self.values(t, y, args)
        just_fired = (segment.leaving != 0) & (jnp.abs(g) <= self.at_zero)
        orientation = self.towards
        if self.either.any():
            dynamics, p, factorisation, layout, _ = args
            q, u = layout.split(y)
            rates = segment.hybrid.rates(dynamics, t, q, u, p, factorisation, segment.resting,
                                         segment.references)
            leaving_zero = jnp.where(rates > 0, -1.0, 1.0)
            side = jnp.where(just_fired, segment.leaving,
                             jnp.where(jnp.abs(g) > self.at_zero, jnp.sign(g), leaving_zero))
            orientation = jnp.where(self.either, side, orientation)
        w = self._oriented(g, t, segment, orientation)
        armed = jnp.where(just_fired, orientation * segment.leaving > 0, w > 0)
        offset = jnp.where(just_fired, g, 0.0)
        return dataclasses.replace(segment, armed=armed, orientation=orientation,
                                   offset=jax.lax.stop_gradient(offset))

    def fired(self, mask, t, y, args, held):
        """(K,) the guard whose crossing ended the segment (the least of the watched guards
        where the event's mask says a crossing did). `held`: the held motion at (t, y)."""
        first = jnp.argmin(self.watched(t, y, args, held=held))
        return jnp.zeros((self.total,), bool).at[first].set(mask[0])

