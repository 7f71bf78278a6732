"""Value-dependent errors that name what went wrong and where.

A check is one `lax.cond` on "did anything fail" (reduced over a vmapped batch, so it stays a
branch), whose failing side calls the host: there the message is formatted with the values
that matter (the time and state of a singular mass matrix, the parameter leaf holding a NaN)
and raised. Nothing runs on the host unless a check fails. `reports_state` turns such an error
into a plain `RuntimeError` with jaxdyn's message when it leaves a jaxdyn entry point; inside a
caller's own `jax.jit` the message (with the state) still appears in JAX's runtime error.
"""

import contextlib
import functools
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any, TypeVar, overload

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core

_where: list[str] = []  # host-side: the message of the first failed check of the current call


class _CheckFailed(RuntimeError):
    """Raised on the host by a failed check."""


class _QuietChecks(logging.Filter):
    """JAX logs every exception raised by a host callback, with its traceback, before passing
    it on as a runtime error. A failed check is such an exception on purpose, and its message
    reaches the caller as jaxdyn's own error: the log would print it a second time, with the
    paths of jaxdyn's files, even when the caller catches the error."""

    def filter(self, record):
        return not (record.exc_info and isinstance(record.exc_info[1], _CheckFailed))


logging.getLogger("jax._src.callback").addFilter(_QuietChecks())


# Programs being traced whose checks the host reads (`checks_read_on_host`): (trace, flags).
_read_on_host: list[tuple[Any, list]] = []


@contextlib.contextmanager
def checks_read_on_host():
    """Inside the trace of a program that is called with values: `error_if` at the program's
    own level (not inside its loops, branches or vmaps) records its failure flag in the list
    yielded, instead of a branch to the host, and passes its value through. The program then
    holds no host callback (JAX's persistent compilation cache keeps only such programs);
    whoever runs it reads the flags and, if one is up, runs the checked program for its
    message (`jaxdyn._compile.filter_jit`, `checks_on_host`)."""
    entry = (jax_core.unsafe_get_current_trace(), [])
    _read_on_host.append(entry)
    try:
        yield entry[1]
    finally:
        _read_on_host.pop()


@contextlib.contextmanager
def library_checks_as_nan():
    """Equinox's `error_if` (diffrax's checks of its arguments, such as save times in order)
    traced as NaN in the result instead of a host callback, for a program that holds no host
    callback so that JAX's persistent compilation cache can keep it. Only for programs whose
    arguments jaxdyn has checked itself and whose failures send the call to the checked
    program, where these checks raise as usual."""
    module: Any = sys.modules.get("equinox._errors")
    previous = getattr(module, "EQX_ON_ERROR", None)
    if previous != "raise":  # the user chose otherwise (or equinox moved it): leave it
        yield
        return
    module.EQX_ON_ERROR = "nan"
    try:
        yield
    finally:
        module.EQX_ON_ERROR = previous


# Whether `error_if` turns its value into NaN on failure instead of calling the host
# (`checks_as_nan`).
_as_nan: list[bool] = []


@contextlib.contextmanager
def checks_as_nan():
    """`error_if` traced as NaN in its value where a check fails, at any level of the trace,
    instead of a branch to the host (a value with no floating-point leaf keeps the branch);
    with `library_checks_as_nan` for equinox's. For a
    program called with values that holds no host callback (JAX's persistent compilation
    cache keeps only such programs), whose caller reads a non-finite result as a failure and
    then runs the checked program from the same inputs for the check's message."""
    _as_nan.append(True)
    try:
        with library_checks_as_nan():
            yield
    finally:
        _as_nan.pop()


def checks_as_nan_active() -> bool:
    """Whether `error_if` is traced as NaN here (`checks_as_nan`): part of the key of every
    jitted function whose trace holds checks, so that a trace cached under one setting is not
    reused under the other."""
    return bool(_as_nan)


UNEXPLAINED_FAILURE = (
    "The result is not finite (NaN or inf), and none of the causes checked for holds here:\n"
    "{}\nThis should not happen: please report it, with the state below, to jaxdyn's issue "
    "tracker."
)


def error_if(x, checks: Sequence[tuple] | Callable[[], Sequence[tuple]], state=None, *,
             failed=None):
    """`x`, or an error if one of `checks` fails.

    `checks`: a sequence of (pred, message) with boolean scalar preds, or a function returning
    one; the first true pred is reported. An entry (pred, message, state) ends its message with
    its own state instead of the shared one. `failed`: a cheap boolean saying whether any check
    fails (by default, the checks themselves). Given `failed` and a function, the checks are
    only evaluated in the branch taken on failure: detecting a failure then costs as little as
    computing `failed` (say, a NaN in `x`), and finding its cause costs nothing until it
    happens. `state`: None, or (t, q, u) to end the message with "It happened at t = …, q =
    […], u = […]." (under vmap, the state of the first failing batch member), or a dict of
    labelled values to end it with "It happened at label = …, …", or a function returning
    one of these (evaluated only on failure: for values that cost something to compute).

    Values and derivatives of `x` pass through unchanged: the branch sees its inputs through
    `stop_gradient`, and only a boolean (False) comes back from it.
    """
    if not callable(checks):
        listed = list(checks)
        checks = lambda: listed  # noqa: E731
    messages = tuple(check[1] for check in checks())
    if failed is None:
        failed = jnp.any(_preds(checks()))
    if _read_on_host and _read_on_host[-1][0] is jax_core.unsafe_get_current_trace():
        _read_on_host[-1][1].append(jnp.asarray(failed))
        return x
    if _as_nan and any(eqx.is_inexact_array(a) for a in jax.tree_util.tree_leaves(x)):
        # (any member's failure under vmap: x stays unbatched, as below; a value without a
        # floating-point leaf could not show the failure, and keeps the branch to the host)
        failed = eqxi.unvmap_any(failed)
        return jax.tree_util.tree_map(
            lambda a: jnp.where(failed, jnp.nan, a) if jnp.issubdtype(a.dtype, jnp.inexact)
            else a, x)
    described = state if callable(state) else lambda: state

    def fail():
        listed = checks()
        shared = described() if any(len(check) == 2 for check in listed) else None
        labels, values = [], []
        for check in listed:
            labelled = _labelled(check[2] if len(check) == 3 else shared)
            labels.append(tuple(labelled))
            values.append(tuple(labelled.values()))
        preds = jax.lax.stop_gradient(_preds(listed))
        raise_ = functools.partial(_raise, messages, tuple(labels))
        return jax.pure_callback(raise_, jax.ShapeDtypeStruct((), jnp.bool_), preds,
                                 jax.lax.stop_gradient(tuple(values)),
                                 jax.lax.stop_gradient(jnp.asarray(failed)),
                                 vmap_method="sequential")

    # `unvmap_any` keeps the `cond` a real branch under vmap: the host is only called when some
    # batch member has failed.
    flag = jax.lax.cond(eqxi.unvmap_any(failed), fail, lambda: jnp.zeros((), jnp.bool_))
    # The branch's result is batched under vmap (its operands are), and tying x to it would
    # batch x: a robot's parameters checked once, then one copy per member of the batch,
    # folded into nothing and streamed through every step of a vmapped `simulate` (ANYmal
    # in contact at a batch of 1024: 70 µs a step against 37, twice the compile). Unbatched
    # (any member's flag: each is False unless the call raises).
    flag = eqxi.unvmap_any(flag)
    # Tie x to the check, so that it is not removed as unused: adding 0 (XLA keeps 0·flag).
    # Integer and boolean leaves through a floating-point zero (XLA folds 0·n for integers).
    zero = jnp.zeros((), jnp.float32) * flag.astype(jnp.float32)
    return jax.tree_util.tree_map(
        lambda a: a + jnp.zeros((), a.dtype) * flag.astype(a.dtype)
        if jnp.issubdtype(a.dtype, jnp.inexact) else
        (a | zero.astype(a.dtype)) if a.dtype == jnp.bool_ else a + zero.astype(a.dtype), x)


def _labelled(state):
    if state is None:
        return {}
    return state if isinstance(state, dict) else dict(zip("tqu", state))


def _preds(listed):
    return jnp.stack([jnp.asarray(check[0]) for check in listed])


def _raise(messages, labels, preds, values, failed):
    preds = np.asarray(preds)
    if not preds.any():
        if not np.asarray(failed):  # another batch member failed
            return np.zeros((), np.bool_)
        # This one failed, and none of the causes it checks holds: say so rather than return
        # the NaN silently, with the state of the first check that has one.
        first = next((i for i, label in enumerate(labels) if label), 0)
        message = UNEXPLAINED_FAILURE.format("\n".join(
            "  - " + m.split(". ")[0].split(":")[0].rstrip(".") + "." for m in messages))
    else:
        first = int(np.argmax(preds))
        message = messages[first]
    if labels[first]:
        described = ", ".join(f"{k} = {np.asarray(v).tolist()}"
                              for k, v in zip(labels[first], values[first]))
        message = f"{message}\n\nIt happened at {described}."
    if not _where:
        _where.append(message)
    raise _CheckFailed(message)


_F = TypeVar("_F", bound=Callable[..., Any])


@overload
def reports_state(fn: None = None, *, block: bool = True) -> Callable[[_F], _F]: ...


@overload
def reports_state(fn: _F, *, block: bool = True) -> _F: ...


def reports_state(fn: Callable | None = None, *, block: bool = True) -> Any:
    """Decorate an entry point so that a failed `error_if` leaves it as a `RuntimeError`
    carrying jaxdyn's message alone (not the runtime's wrapping of it). `block=False` for an
    entry point whose results are ready when it returns (`jaxdyn._compile.filter_jit`)."""
    if fn is None:
        return functools.partial(reports_state, block=block)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        _where.clear()
        try:
            out = fn(*args, **kwargs)
            return _block(out) if block else out
        except Exception:
            if not _where:
                raise
            raise RuntimeError(_where.pop()) from None

    return wrapper


def check_finite(**trees):
    """The keyword arguments (pytrees) as a tuple, or an error naming the first floating-point
    leaf that holds NaN or inf, as in ``p['spring']['k']``."""
    values, checks, positions = [], [], []
    flat = []
    for what, tree in trees.items():
        leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
        flat.append((treedef, len(leaves)))
        for path, leaf in leaves:
            if eqx.is_inexact_array(leaf):
                positions.append(len(values))
                checks.append((~jnp.all(jnp.isfinite(leaf)),
                               f"{what}{jax.tree_util.keystr(path)} contains NaN or inf. Check "
                               "the initial state and parameters you passed (a division by zero "
                               "or a failed earlier computation upstream)."))
            values.append(leaf)
    if checks:
        checked = error_if([values[i] for i in positions], checks)
        for i, leaf in zip(positions, checked):
            values[i] = leaf
    out, start = [], 0
    for treedef, count in flat:
        out.append(jax.tree_util.tree_unflatten(treedef, values[start:start + count]))
        start += count
    return tuple(out)


def _block(tree):
    # Callback errors surface when results are ready: wait here so they pass through `wrapper`.
    # Under an outer trace there is nothing to wait for.
    leaves = jax.tree_util.tree_leaves(tree)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return tree
    jax.block_until_ready(leaves)
    return tree
