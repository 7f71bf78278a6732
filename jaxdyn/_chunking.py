"""`jax.vmap` of array programs in chunks of a few states.

A tree's recursions (the articulated-body, composite-rigid-body and Newton–Euler algorithms,
frame kinematics) as array programs are tens of small kernels of 6 × 6 and 3 × 3 algebra per
link. Batched over a thousand states by `jax.vmap`, every kernel streams arrays of a thousand
blocks through memory and the program runs at the speed of memory, not of arithmetic; over a
few states at a time the same kernels work in cache. So these programs define their own
batching rule (`jax.custom_batching.custom_vmap`): under `jax.vmap` they run as `jax.lax.map`
over chunks of `CHUNK` states, each chunk vmapped. Measured on the Panda arm's forward
dynamics, per state in a batch of 1024 (2-core CPU, float64): 13.8 µs vmapped, 2.2 µs in
chunks of 8, 9.9 µs one state at a time as XLA's runtime runs a loop, 1.6 µs one state at a
time with the loop compiled as one function (jaxdyn's default, `jaxdyn._xla`;
`benchmarks/LOG.md`). Equations formed as whole
matrices do not use it: LAPACK's batched factorisations prefer the whole batch. Derivatives
are those of the function itself, batched by plain `vmap` (a custom_vmap's own JVP cannot be
linearised by JAX, see `chunked_vmap`), and nested `vmap`s batch the map.
"""

import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from ._custom_jvp import batch_axis_first
from ._xla import SMALL_LOOPS_ONE_FUNCTION

# States per chunk. Where XLA compiles small loops as one function (`jaxdyn._xla`), one: the
# loop over states runs as compiled code, without the runtime's launch of every kernel per
# iteration (per state in a batch of 1024, the G1 humanoid's mass matrix 7.8 µs in chunks of
# 8, 5.8 one at a time; its forward dynamics 8.9 and 8.7; Talos's compiles in 4.7 s against
# 5.8). Else 8: a chunk's kernels then carry the launches, and 8–16 states keep a robot's
# arrays in cache (the UR5: 1.2 µs per state at 16, 6.1 µs at 32; the Panda one state at a
# time 9.9 µs, in chunks of 8 2.2).
CHUNK = 1 if SMALL_LOOPS_ONE_FUNCTION else 8


def chunked_vmap(fn: Callable[..., Any]) -> Callable[..., Any]:
    """`fn`, whose `jax.vmap` runs in chunks of `CHUNK` states. Non-array leaves of the
    arguments (static options, Python callables) are passed through unchanged."""

    # The arguments bound in a partial (a formulation: `functools.partial(equations, dynamics)`)
    # join the arguments: an array among them may be batched (the inputs r a system carries,
    # under a `vmap` over nodes of a trajectory), which a custom_vmap cannot close over.
    bound = fn.args if isinstance(fn, functools.partial) else ()
    if bound:
        fn = functools.partial(fn.func, **fn.keywords)

    def call(*args):
        args = (*bound, *args)
        leaves, treedef = jax.tree_util.tree_flatten(args)
        where = [i for i, leaf in enumerate(leaves) if eqx.is_array(leaf)]

        def evaluate(arrays):
            full = list(leaves)
            for i, array in zip(where, arrays):
                full[i] = array
            return fn(*jax.tree_util.tree_unflatten(treedef, full))

        # A flat list of arrays (no None placeholders: JAX's JVP of a custom batching rule
        # compares the trees of primals and tangents, which None leaves would make differ).
        @custom_vmap
        def inner(arrays):
            return evaluate(arrays)

        @inner.def_vmap
        def rule(axis_size, in_batched, arrays):
            (in_batched,) = in_batched
            batched = [a for a, b in zip(arrays, in_batched) if b]

            def one(batched):
                members = iter(batched)
                return evaluate([next(members) if b else a for a, b in zip(arrays, in_batched)])

            if not batched:  # (the JVP's rule may see no primal batched with its tangent)
                out = evaluate(arrays)
                return out, jax.tree_util.tree_map(lambda _: False, out)
            if axis_size <= CHUNK:
                out = jax.vmap(one)(batched)
                return out, jax.tree_util.tree_map(lambda _: True, out)
            # Padded to whole chunks with copies of the first state (a remainder would be a
            # second copy of the program to compile), the padding cut from the result.
            chunks = -(-axis_size // CHUNK)
            padding = chunks * CHUNK - axis_size
            padded = [jnp.concatenate([x, jnp.repeat(x[:1], padding, axis=0)]) if padding
                      else x for x in batched]
            split = [x.reshape((chunks, CHUNK) + x.shape[1:]) for x in padded]
            out = jax.lax.map(jax.vmap(one), split)
            out = jax.tree_util.tree_map(
                lambda y: y.reshape((chunks * CHUNK,) + y.shape[2:])[:axis_size], out)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        # JAX linearises a custom_vmap function through its JVP and cannot split that into a
        # known primal and a linear tangent ("Linearization failed to produce known values"):
        # `jax.linearize`, and so reverse mode and Newton's method, failed on every tree's
        # equations. The JVP is therefore that of the function itself
        # (linearisable, batched by plain `vmap`); the primal keeps its chunked batching.
        @jax.custom_jvp
        def differentiable(arrays):
            return inner(arrays)  # (batched by `rule`: its batch axis first)

        @differentiable.defjvp
        def derivative(primals, tangents):
            return batch_axis_first(jax.jvp(evaluate, primals, tangents))

        return differentiable([leaves[i] for i in where])

    return call
