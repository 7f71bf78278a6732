"""Custom JVPs whose function and rule agree on where a `jax.vmap` puts its batch axis.

JAX (0.10) batches a `jax.custom_jvp` met inside a `jax.jit` by tracing the function and the
rule separately: the outputs are labelled with the batch axes of the *function's* outputs,
while the rule's outputs are moved to the batch axes of the *rule's* own primal outputs. Where
the two differ, the derivative taken afterwards (`jax.jvp` or `jax.grad` of the vmapped, jitted
call) comes back with its axes exchanged, silently: a function that stacks scalars (its batch
axis last: jaxdyn's straight-line programs) with a rule that computes the same values as an
array program (batch axis first) returned the transpose of a square batch's tangent. Every
custom JVP of jaxdyn whose rule computes its values by another program than its function
therefore returns its outputs, from the function and from the rule, with the batch axis first
(`batch_axis_first`); without `vmap` XLA removes the added operation. (A rule that computes
its values by the function itself, as the accelerations of optimal control's dynamics do,
agrees with it by construction.)

`jvp_of_perturbed` serves rules defined with `symbolic_zeros=True`: it propagates only the
tangents that are not symbolic zeros, so that inputs a transformation does not perturb (a
system's arrays under a Jacobian in the state) cost nothing.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


def _first(x):
    if not eqx.is_inexact_array(x) or x.ndim == 0:
        return x
    # A concatenation's batching rule moves every operand's batch axis to the front; an empty
    # operand makes it one (JAX returns a lone operand unchanged) and XLA drops it.
    empty = jnp.zeros((0,) + x.shape[1:], x.dtype)
    return jax.lax.concatenate([x, empty], 0)


def batch_axis_first(tree):
    """`tree` with each inexact array's batch axis (under `jax.vmap`) first; the same values."""
    return jax.tree_util.tree_map(_first, tree)


def _perturbed(tangent) -> bool:
    return not isinstance(tangent, SymbolicZero) and \
        jnp.result_type(tangent) != jax.dtypes.float0


def jvp_of_perturbed(fn, primals, tangents, *, like):
    """`jax.jvp(fn, primals, tangents)` with the leaves whose tangent is a symbolic zero (or
    float0) held fixed rather than differentiated; `like`: a pytree of arrays shaped as
    `fn`'s output, whose zeros are the tangent where nothing is perturbed."""
    leaves, treedef = jax.tree_util.tree_flatten(primals)
    tangent_leaves = treedef.flatten_up_to(tangents)
    active = [i for i, dx in enumerate(tangent_leaves) if _perturbed(dx)]

    def of_active(*xs):
        filled = list(leaves)
        for i, x in zip(active, xs):
            filled[i] = x
        return fn(*jax.tree_util.tree_unflatten(treedef, filled))

    if not active:
        return of_active(), jax.tree_util.tree_map(jnp.zeros_like, like)
    return jax.jvp(of_active, tuple(leaves[i] for i in active),
                   tuple(tangent_leaves[i] for i in active))
