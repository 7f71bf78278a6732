"""Derivatives of a solve by forward sensitivities, usable in forward and reverse mode.

For a solve y(x) of few differentiated inputs x (k entries: parameters, initial state), the
sensitivities S = ∂y/∂x are carried with the solve by forward mode (k tangents of one solve,
vectorised; where the solver is an explicit Runge–Kutta method and the inputs are the initial
state and the parameters, as the sensitivity equations Ṡ = ∂f/∂y S + ∂f/∂x integrated with
the state, so that only the vector field is differentiated), and the derivative is applied as
the matrix it is:

    ẏ = S ẋ   (a JVP),      x̄ = Sᵀ ȳ   (a VJP: JAX transposes the product).

One function then supports `jax.jvp`, `jax.jacfwd`, `jax.grad` and `jax.jacrev`, whereas a
reverse-mode adjoint (a `custom_vjp`) refuses forward mode, and forward mode through a solve's
while loop cannot be transposed. With few inputs the k tangents cost less than the reverse
pass, which re-runs the solve from checkpoints and stores every step's linearisation.

Reference: Y. Cao, S. Li, L. Petzold, R. Serban, "Adjoint sensitivity analysis for
differential-algebraic equations", SIAM J. Sci. Comput. 24 (2003) (forward sensitivities
against adjoints).
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree

from ._custom_jvp import batch_axis_first

#: Up to this many differentiable entries (initial state and parameters) `simulate` carries
#: forward sensitivities by default; beyond, reverse mode through checkpoints is cheaper.
MAX_FORWARD = 16


def with_sensitivities(fn, dynamic, sensitivity_solve=None):
    """`fn(dynamic)`, differentiated by forward sensitivities: `dynamic` is a pytree of
    arrays, `fn` must be forward-mode differentiable (a diffrax solve with
    `adjoint=diffrax.ForwardMode()`).

    `sensitivity_solve(dynamic, basis)`, where given, computes the same solve with its
    sensitivities carried by the sensitivity equations, Ṡ = ∂f/∂y S + ∂f/∂x (so that only
    the vector field is differentiated, not the whole solve): `basis` lists, leaf by leaf
    of `dynamic`, the k tangent directions (an array with a leading axis k) or None for a
    leaf not differentiated. It returns `(fn(dynamic), S)`, S with the inexact arrays of
    the output, each with a leading axis k, or None where it does not apply (then the
    whole solve is differentiated in forward mode)."""
    return _call(fn, sensitivity_solve, dynamic)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _call(fn, sensitivity_solve, dynamic):
    return batch_axis_first(fn(dynamic))


def _rule(fn, sensitivity_solve, primals, tangents):
    (dynamic,), (tangent,) = primals, tangents
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    tangent_leaves = treedef.flatten_up_to(tangent)
    active = [i for i, (x, dx) in enumerate(zip(leaves, tangent_leaves))
              if eqx.is_inexact_array(x) and not isinstance(dx, SymbolicZero)]

    flat, unravel = ravel_pytree([leaves[i] for i in active])
    if flat.size == 0:
        out = fn(dynamic)
        return batch_axis_first((out, _tangents_like(out, None)))
    # One direction per differentiated entry: the identity, split leaf by leaf.
    leaf_basis = [None] * len(leaves)
    for i, directions in zip(active, jax.vmap(unravel)(jnp.eye(flat.size, dtype=flat.dtype))):
        leaf_basis[i] = directions
    solved = None if sensitivity_solve is None else sensitivity_solve(dynamic, leaf_basis)
    if solved is None:  # forward mode through the whole solve, one tangent per entry
        solved = forward_tangents(fn, dynamic, tangent_tree(dynamic, leaf_basis), flat.size)
    out, sensitivities = solved
    direction = ravel_pytree([tangent_leaves[i] for i in active])[0]
    # ẏ = S ẋ: linear in ẋ, so that reverse mode transposes it to x̄ = Sᵀ ȳ.
    applied = jax.tree_util.tree_map(lambda s: jnp.tensordot(direction, s, axes=1),
                                     sensitivities)
    return batch_axis_first((out, _tangents_like(out, applied)))


_call.defjvp(_rule, symbolic_zeros=True)


def forward_tangents(fn, primals, tangents, k):
    """(fn(primals), its tangents) along k directions at once, by forward mode: `tangents`
    has the structure of `eqx.filter(primals, eqx.is_inexact_array)`, with the k tangents of
    each inexact array along a leading axis, or None where it is not perturbed (held fixed,
    not differentiated). The result's tangents are those of `fn`'s inexact arrays
    (`eqx.filter(fn(primals), eqx.is_inexact_array)`, each with the leading axis k): one JVP
    vectorised over the k directions, the primal computed once."""
    leaves, treedef = jax.tree_util.tree_flatten(primals)
    directions = treedef.flatten_up_to(tangents)
    active = [i for i, (x, d) in enumerate(zip(leaves, directions))
              if d is not None and eqx.is_inexact_array(x)]

    def outputs(*chosen):
        filled = list(leaves)
        for i, x in zip(active, chosen):
            filled[i] = x
        return eqx.partition(fn(jax.tree_util.tree_unflatten(treedef, filled)),
                             eqx.is_inexact_array)

    if not active:
        out, rest = outputs()
        return eqx.combine(out, rest), jax.tree_util.tree_map(
            lambda x: jnp.zeros((k, *x.shape), x.dtype), out)
    out, derivative, rest = jax.vmap(
        lambda *v: jax.jvp(outputs, tuple(leaves[i] for i in active), v, has_aux=True),
        out_axes=(None, 0, None))(*(directions[i] for i in active))
    return eqx.combine(out, rest), derivative


def tangent_tree(part, leaf_basis):
    """The tangents of `part`'s inexact arrays as `forward_tangents` takes them, from
    `leaf_basis`: the k directions of each of its array leaves, None where not
    differentiated."""
    arrays = eqx.filter(part, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    return jax.tree_util.tree_unflatten(
        treedef, [b if eqx.is_inexact_array(x) else None for x, b in zip(leaves, leaf_basis)])


def _tangents_like(out, applied):
    """Tangents of `out`: `applied` for its inexact arrays (zeros if None), float0 zeros for
    the rest (integer results, step counts)."""
    applied_leaves = (None if applied is None
                      else iter(jax.tree_util.tree_leaves(applied)))

    def tangent(x):
        if eqx.is_inexact_array(x):
            return jnp.zeros_like(x) if applied_leaves is None else next(applied_leaves)
        return np.zeros(np.shape(x), jax.dtypes.float0)

    return jax.tree_util.tree_map(tangent, out)


def differentiable_size(tree) -> int:
    """The number of floating-point entries in `tree`."""
    return sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree)
               if eqx.is_inexact_array(x))
