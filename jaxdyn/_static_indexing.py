"""The trace-time check that the user's callbacks index their inputs within bounds.

JAX clamps out-of-range indices, so a callback written for more coordinates than it is given
(``qd[1]`` with one coordinate) would silently read the wrong entry. `checkify`'s index
checks find such reads. Called with values, the checked callbacks run as one small compiled
program. Under a trace (`simulate`'s program, a caller's `jax.jit` or `vmap`) the check is
decided from the checked callbacks' jaxpr, without compiling anything: the operations that
the check's result depends on are found, and where none of them depends on a traced value
(static indices, constant operands) they are evaluated in NumPy. Evaluating them with JAX
instead, under compile-time evaluation, ran every operation on constants in the callbacks
(a constant vector, a rotation matrix of constants) as a program of its own, compiled once
per shape: tens of programs at a first call.
"""

import equinox as eqx
import jax
import jax.core
import numpy as np
from jax.experimental import checkify
from jax.extend.core import ClosedJaxpr, Literal

from ._unroll_positions import dynamic_slice_positions


def check_static_indexing(fn, *args):
    """Raise if `fn(*args)` indexes an array out of bounds with a static index.

    On concrete arguments `fn` runs once under `checkify`'s index checks (a small compiled
    program, cached per system). Under an outer trace the check's result is evaluated from
    the jaxpr where it depends on constants alone; checkify merges the bounds checks into
    one result, so where any of them depends on traced values the check is skipped. `fn`
    should be cheap (the user callbacks alone, no derivatives).
    """
    leaves = jax.tree_util.tree_leaves((fn, args))
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        error = _error_from_constants(fn, args)
        if error is None:  # depends on traced values
            return
        message = error.get()
    else:
        message = _checked_jit(fn, args).get()
    if message is not None:
        raise ValueError(
            f"A callback indexes past the end of its input: {message.strip()} Check that the "
            "energies, forces and kinematics are written for the number of coordinates and "
            "speeds you pass (q of shape (n,), speeds of shape (m,))."
        )


def _checked(fn, args):
    return checkify.checkify(fn, errors=checkify.index_checks)(*args)[0]


_checked_jit = eqx.filter_jit(_checked)


def _error_from_constants(fn, args):
    """checkify's error of `fn(*args)`, evaluated in NumPy from the operations it depends on
    where none depends on the arguments or on a traced value closed over; else None."""
    closed, shapes, static = eqx.filter_make_jaxpr(lambda *a: _checked(fn, a))(*args)
    jaxpr = closed.jaxpr
    known = {v for v, c in zip(jaxpr.constvars, closed.consts)
             if not isinstance(c, jax.core.Tracer)}
    for eqn in jaxpr.eqns:
        if all(isinstance(v, Literal) or v in known for v in eqn.invars):
            known.update(eqn.outvars)
    if not all(isinstance(v, Literal) or v in known for v in jaxpr.outvars):
        return None
    values = _evaluate(jaxpr, closed.consts, [])
    arrays = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shapes), values)
    return eqx.combine(arrays, static)


def _evaluate(jaxpr, consts, args):
    """The outputs of `jaxpr` at `consts` and `args` (NumPy values), evaluating only the
    equations they need, in NumPy (`_NUMPY`; any other primitive by JAX)."""
    needed = {v for v in jaxpr.outvars if not isinstance(v, Literal)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        if any(v in needed for v in eqn.outvars):
            kept.append(eqn)
            needed.update(v for v in eqn.invars if not isinstance(v, Literal))
    env = {**dict(zip(jaxpr.constvars, consts)), **dict(zip(jaxpr.invars, args))}

    def read(v):
        return np.asarray(v.val if isinstance(v, Literal) else env[v])

    for eqn in reversed(kept):
        inputs = [read(v) for v in eqn.invars]
        outputs = _apply(eqn, inputs)
        for v, x in zip(eqn.outvars, outputs if eqn.primitive.multiple_results else [outputs]):
            env[v] = x
    return [read(v) for v in jaxpr.outvars]


def _apply(eqn, inputs):
    params = eqn.params
    rule = _NUMPY.get(eqn.primitive.name)
    out = None if rule is None else rule(*inputs, **params)
    # (a nested jit, as `jnp.where` and `clip` make, or a function with custom derivatives)
    inner = params.get("jaxpr", params.get("call_jaxpr"))
    if out is None and isinstance(inner, ClosedJaxpr):
        out = _evaluate(inner.jaxpr, [np.asarray(c) for c in inner.consts], inputs)
    elif out is None:  # a primitive without a NumPy rule: JAX's own, on constants
        with jax.ensure_compile_time_eval():
            out = eqn.primitive.bind(*inputs, **params)
        out = [np.asarray(x) for x in out] if eqn.primitive.multiple_results else out
    if eqn.primitive.multiple_results:
        return [np.asarray(x, v.aval.dtype) for x, v in zip(out, eqn.outvars)]
    return np.asarray(out, eqn.outvars[0].aval.dtype)


def _broadcast_in_dim(x, shape, broadcast_dimensions, **_):
    expanded = np.expand_dims(x, [d for d in range(len(shape))
                                  if d not in broadcast_dimensions])
    return np.broadcast_to(expanded, shape)


def _select_n(which, *cases):
    return np.choose(which.astype(np.int64), np.broadcast_arrays(*cases))


def _iota(*, dtype, shape, dimension, **_):
    return np.broadcast_to(np.expand_dims(np.arange(shape[dimension], dtype=dtype), [
        d for d in range(len(shape)) if d != dimension]), shape)


def _div(a, b):
    """XLA's division: integers rounded toward zero (None, for JAX's own, at a zero divisor
    or an overflow)."""
    if np.issubdtype(a.dtype, np.inexact):
        with np.errstate(all="ignore"):
            return np.divide(a, b)
    if (b == 0).any() or (np.issubdtype(a.dtype, np.signedinteger) and (b == -1).any()):
        return None
    quotient = np.abs(a) // np.abs(b)
    return np.where((a < 0) != (b < 0), -quotient, quotient)


def _rem(a, b):
    """XLA's remainder: the dividend's sign (C's `fmod`)."""
    if not np.issubdtype(a.dtype, np.inexact) and ((b == 0).any() or (b == -1).any()):
        return None
    with np.errstate(all="ignore"):
        return np.fmod(a, b)


def _reduction(fn):
    return lambda x, *, axes, **_: fn(x, axis=tuple(axes))


# The operations of checkify's bounds checks and of index arithmetic, in NumPy (whose integer
# arithmetic wraps as XLA's does). A rule returns None where it leaves the case to JAX.
_NUMPY = {
    "div": _div, "rem": _rem,
    "lt": np.less, "le": np.less_equal, "gt": np.greater, "ge": np.greater_equal,
    "eq": np.equal, "ne": np.not_equal,
    "add": np.add, "sub": np.subtract, "mul": np.multiply, "neg": np.negative,
    "max": np.maximum, "min": np.minimum, "abs": np.abs, "sign": np.sign,
    "and": np.bitwise_and, "or": np.bitwise_or, "xor": np.bitwise_xor,
    "not": lambda x: np.logical_not(x) if x.dtype == bool else np.invert(x),
    "select_n": _select_n,
    "clamp": lambda lo, x, hi: np.clip(x, lo, hi),
    "convert_element_type": lambda x, *, new_dtype, **_: x.astype(new_dtype),
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": lambda x, *, new_sizes, **_: np.reshape(x, new_sizes),
    "squeeze": lambda x, *, dimensions: np.squeeze(x, axis=tuple(dimensions)),
    "concatenate": lambda *xs, dimension: np.concatenate(xs, axis=dimension),
    # (XLA's clamping of the starts, as the straight-line evaluation locates slices)
    "dynamic_slice": lambda x, *starts, slice_sizes: dynamic_slice_positions(
        {"slice_sizes": slice_sizes}, x, *starts),
    "iota": _iota,
    "argmin": lambda x, *, axes, index_dtype: np.argmin(x, axis=axes[0]).astype(index_dtype),
    "argmax": lambda x, *, axes, index_dtype: np.argmax(x, axis=axes[0]).astype(index_dtype),
    "reduce_or": _reduction(np.any), "reduce_and": _reduction(np.all),
    "reduce_max": _reduction(np.max), "reduce_min": _reduction(np.min),
    "reduce_sum": _reduction(np.sum),
    "copy": np.copy, "copy_p": np.copy,
}
