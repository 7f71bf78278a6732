"""Value-dependent errors that name the state where they happened.

`eqx.error_if` stops a computation with a fixed message. For a singular mass matrix the user
also needs to know *where*: the time and state. Traced values cannot be formatted into an
`eqx.error_if` message, so the failing branch first hands the state to the host (a
`pure_callback` that only runs once the error is certain), and `reports_state` appends it when
the error crosses a jaxdyn entry point such as `simulate`.
"""

import functools

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify

_where: list[str] = []  # host-side; the first failing state of the current call


def _record(msg, pred, t, q, u):
    pred = np.asarray(pred)
    if pred.any() and not _where:
        state = ", ".join(f"{k} = {np.asarray(v).tolist()}" for k, v in zip("tqu", (t, q, u)))
        _where.append(f"{msg}\n\nIt happened at {state}.")
    return pred


def error_if_at_state(x, pred, msg: str, t, q, u):
    """`eqx.error_if(x, pred, msg)`, remembering the state (t, q, u) where `pred` held."""
    t, q, u = jax.lax.stop_gradient((t, q, u))  # the record is diagnostics only

    def record():
        struct = jax.ShapeDtypeStruct(jnp.shape(pred), jnp.bool_)
        callback = functools.partial(_record, msg)
        return jax.pure_callback(callback, struct, pred, t, q, u, vmap_method="sequential")

    # `unvmap_any` keeps the `cond` a real branch under vmap, so the host is only
    # called when some batch member has failed.
    pred = jax.lax.cond(eqxi.unvmap_any(pred), record, lambda: pred)
    return eqx.error_if(x, pred, msg)


def reports_state(fn):
    """Decorate an entry point so that errors raised by `error_if_at_state` name the state."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        _where.clear()
        try:
            return _block(fn(*args, **kwargs))
        except Exception:
            if not _where:
                raise
            message = _where.pop()
            # The error was ours: replace Equinox's generic runtime-error text by the message
            # and the state.
            raise RuntimeError(message) from None

    return wrapper


def nonfinite_tree_check(tree, what: str):
    """Error (naming the leaf) if any floating-point leaf of `tree` holds NaN or inf."""
    leaves = jax.tree_util.tree_leaves_with_path(tree)
    checked = []
    for path, leaf in leaves:
        if eqx.is_inexact_array(leaf):
            name = f"{what}{jax.tree_util.keystr(path)}"
            leaf = eqx.error_if(
                leaf,
                ~jnp.all(jnp.isfinite(leaf)),
                f"{name} contains NaN or inf. Check the initial state and parameters you "
                "passed (a division by zero or a failed earlier computation upstream).",
            )
        checked.append(leaf)
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(tree), checked)


def _block(tree):
    # Callback errors surface when results are ready: wait here so they pass through `wrapper`.
    # Under an outer trace there is nothing to wait for.
    def block(x):
        if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
            x.block_until_ready()
        return x

    return jax.tree_util.tree_map(block, tree)


def check_static_indexing(fn, *args):
    """Raise if `fn(*args)` indexes an array out of bounds with a static index.

    JAX clamps out-of-range indices, so a callback written for more coordinates than it is
    given (``qd[1]`` with one coordinate) would silently read the wrong entry. Tracing `fn`
    under `checkify` with compile-time evaluation computes the bounds checks of static indices
    at trace time (their operands are constants); checks that depend on traced values stay
    symbolic and are skipped. `fn` should be cheap (the user callbacks alone, no derivatives):
    what it stages is unused and dropped by XLA.
    """
    leaves = jax.tree_util.tree_leaves((fn, args))
    with jax.ensure_compile_time_eval():
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            error = _checked(fn, args)
        else:  # an eager call: trace it (cached per system) so that the checks are formed
            error = _checked_jit(fn, args)
        try:
            message = error.get()
        except jax.errors.ConcretizationTypeError:  # depends on traced values
            return
    if message is not None:
        raise ValueError(
            f"A callback indexes past the end of its input: {message.strip()} Check that the "
            "energies, forces and kinematics are written for the number of coordinates and "
            "speeds you pass (q of shape (n,), speeds of shape (m,))."
        )


def _checked(fn, args):
    return checkify.checkify(fn, errors=checkify.index_checks)(*args)[0]


_checked_jit = eqx.filter_jit(_checked)
