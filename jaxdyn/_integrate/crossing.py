"""Locating the first zero crossing of a set of guards within one step, without derivatives.

When a step of the solver ends with some guard cᵢ on the other side of zero, the crossing lies
between the step's start a and end b, and the step's dense interpolant gives each cᵢ(t) there.
The crossing that ends the segment is the earliest one. It is located by regula falsi with the
Illinois modification (Dowell and Jarratt 1971): the bracket [a, b] always has every guard on
its starting side at a and at least one past zero at b; the next point is the earliest of the
guards' secant roots,

    tᵢ = a − cᵢ(a) (b − a) / (cᵢ(b) − cᵢ(a)),

and when one end of the bracket is kept twice in a row its values are halved, so that both
ends close in at a superlinear rate. Unlike Newton's method, this needs no derivative of the
guards: compiling a hybrid solve traces them, and the solver's interpolant, once rather than
with their Jacobian, and the root cannot leave the step.
"""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree, Scalar


class _BracketState(eqx.Module):
    lower: Scalar
    upper: Scalar
    at_lower: Float[Array, " m"]  # the guards at the bracket's ends (halved where kept)
    at_upper: Float[Array, " m"]
    # Which side of zero each function starts the step on. Kept, not read off `at_lower`'s
    # signs: the Illinois halvings can underflow a tiny value there (a guard that just fired
    # is put a smallest float to its side at the restart) to zero.
    side: Bool[Array, " m"]
    tolerance: Scalar  # the bracket's width at which the crossing counts as located
    kept: Int[Array, ""]  # the end the last point left in place (-1 lower, 1 upper, 0 none)
    done: Bool[Array, ""]


def _values(fn, t, args) -> Float[Array, " m"]:
    out, _ = fn(t, args)
    return jnp.stack([jnp.asarray(v) for v in jax.tree_util.tree_leaves(out)])


class FirstCrossing(optx.AbstractRootFinder):
    """The earliest zero crossing in [lower, upper] of the guards `fn(t, args)` (a pytree of
    scalars, as `diffrax.Event` hands them to its root finder: the guards that did not cross
    in the step are zero throughout). Terminates when the bracket is narrower than
    atol + rtol |t| + 2 ε max(|t|, the step) (by default: to the last float, or the step's
    own resolution where it starts at t = 0), or a point lands on a zero;
    returns the bracket's upper end, the earliest time found past the crossing (where the
    event's guard has crossed, as the solver's step found it)."""

    rtol: float = 0.0
    atol: float = 0.0
    norm: ClassVar[Callable[[PyTree], Scalar]] = optx.max_norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del y, f_struct, aux_struct, tags
        dtype = jnp.result_type(options["upper"], float)
        ends = jnp.stack([jnp.asarray(options["lower"], dtype), jnp.asarray(options["upper"],
                                                                         dtype)])
        at_lower, at_upper = jax.vmap(lambda t: _values(fn, t, args))(ends)
        crossing = jnp.sign(at_lower) != jnp.sign(at_upper)
        # A guard at zero at an end of the step is already located there (the earlier end
        # first, as the earliest crossing is the one sought).
        lower_zero = jnp.any(crossing & (at_lower == 0))
        upper_zero = jnp.any(crossing & (at_upper == 0))
        lower = jnp.where(upper_zero & ~lower_zero, ends[1], ends[0])
        upper = jnp.where(lower_zero, ends[0], ends[1])
        # To the last float of the step's span: a crossing at t = 0 is located to the step's
        # scale, not to the smallest float.
        span = jnp.max(jnp.abs(ends)).clip(min=ends[1] - ends[0])
        tolerance = self.atol + self.rtol * jnp.abs(ends[1]) + 2 * jnp.finfo(dtype).eps * span
        return _BracketState(lower, upper, at_lower, at_upper, at_lower > 0, tolerance,
                             jnp.array(0, jnp.int8), lower_zero | upper_zero)

    def _next(self, state: _BracketState) -> Scalar:
        """The earliest of the guards' secant roots in the bracket (its midpoint where
        rounding leaves a secant root on an end)."""
        a, b, fa, fb = state.lower, state.upper, state.at_lower, state.at_upper
        crossing = (fa > 0) != (fb > 0)
        denominator = jnp.where(crossing, fb - fa, 1.0)
        roots = jnp.where(crossing, a - fa * (b - a) / denominator, b)
        t = jnp.min(roots)
        return jnp.where((t > a) & (t < b), t, a + 0.5 * (b - a))

    def step(self, fn, y, args, options, state: _BracketState, tags):
        del y, options, tags
        t = self._next(state)
        values = _values(fn, t, args)
        past = jnp.any((values > 0) != state.side)
        hit = jnp.any((values == 0) & (state.side != (state.at_upper > 0)))
        # Illinois: the end kept for a second time in a row has its values halved.
        at_lower = jnp.where(past, jnp.where(state.kept == -1, 0.5, 1.0) * state.at_lower,
                             values)
        at_upper = jnp.where(past, values,
                             jnp.where(state.kept == 1, 0.5, 1.0) * state.at_upper)
        kept = jnp.where(past, -1, 1).astype(jnp.int8)
        lower = jnp.where(past & ~hit, state.lower, t)
        upper = jnp.where(past | hit, t, state.upper)
        done = state.done | hit
        new = _BracketState(jnp.where(state.done, state.lower, lower),
                            jnp.where(state.done, state.upper, upper), at_lower, at_upper,
                            state.side, state.tolerance, kept, done)
        return new.upper, new, None

    def terminate(self, fn, y, args, options, state: _BracketState, tags):
        del fn, y, args, options, tags
        return state.done | (state.upper - state.lower <= state.tolerance), \
            optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, y, aux, args, options, tags, result
        return state.upper, None, {}


FirstCrossing.__init__.__doc__ = """rtol, atol: the bracket's width at which the crossing is
taken as located (by default, to the last float)."""
