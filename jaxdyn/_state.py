"""What a state is: time t, coordinates q (n,), speeds u (m,). Validation, broadcasting, and
the public methods that take states."""

import functools
import math
import os
import sys
import warnings
from typing import Any, Callable, Concatenate, Generic, ParamSpec, TypeVar, overload

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core

from ._chunking import chunked_vmap
from ._compile import filter_jit, remembered_arrays
from ._errors import reports_state


def as_float_array(x, name: str) -> jax.Array:
    """`x` as a floating-point array; integers are promoted to the default float dtype."""
    # (A NumPy array or a list, outside any trace: `transferred`)
    at_hand = isinstance(x, (np.ndarray, list, tuple)) and jax_core.trace_state_clean()
    x = np.asarray(x) if at_hand else jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.integer) or jnp.issubdtype(x.dtype, jnp.bool_):
        x = x.astype(jnp.result_type(float))
    elif not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"{name} must be a real floating-point array, got dtype {x.dtype}.")
    return transferred(x) if at_hand else jnp.asarray(x)


def transferred(x, dtype=None) -> jax.Array:
    """`jnp.asarray(x, dtype)` for a value at hand (NumPy, Python numbers, concrete arrays):
    converted by NumPy and transferred, with JAX's dtype canonicalisation. A conversion by
    JAX compiles a program of its own for each shape and dtype, 10-40 ms of a process's first
    call (`linearise`, `equilibrium`, `fit`, loading a URDF)."""
    return jax.device_put(np.asarray(x, dtype))


def check_vector(x, name: str, size: int | None = None) -> jax.Array:
    """Trace-time check that `x` is 1-D (of length `size` if given)."""
    x = as_float_array(x, name)
    if x.ndim != 1:
        raise ValueError(
            f"{name} must be a 1-D array of shape (n,), got shape {x.shape}. "
            "A system with one coordinate takes q of shape (1,)."
        )
    if size is not None and x.shape[0] != size:
        raise ValueError(f"{name} must have shape ({size},), got shape {x.shape}.")
    return x


def over_states(signature: str):
    """Make a method written for one state also accept stacked states (a trajectory).

    The method is ``method(self, *arrays, p=None)`` on one state; `signature` is its core
    signature in `jnp.vectorize` notation, e.g. ``"(),(n),(n)->()"`` for ``(t, q, qd) -> E``.
    Leading axes broadcast, so ``system.energy(sol.ts, sol.q, sol.qd, p)`` gives the energy
    along a whole trajectory.
    """
    inputs = signature.split("->")[0]
    names = _state_names(signature)
    num_arrays = len(names)
    core_ndims = [part.count(",") + (0 if part == "()" else 1) for part in _split(inputs)]

    def decorator(method):
        def broadcast(self, *args, **kwargs):
            options = {k: v for k, v in kwargs.items() if k != "p"}
            args = _positional(method.__name__, names, args, kwargs)
            arrays = [as_float_array(a, n) for a, n in zip(args[:num_arrays], names)]
            p = args[num_arrays] if len(args) > num_arrays else None
            for a, n, k in zip(arrays, names, core_ndims):
                if a.ndim < k:
                    raise ValueError(
                        f"{n} must have at least {k} dimension(s), got shape {a.shape}."
                    )
            if all(a.ndim == k for a, k in zip(arrays, core_ndims)):
                return method(self, *arrays, p, **options)
            fn = jnp.vectorize(lambda *xs: method(self, *xs, p, **options), signature=signature)
            return fn(*arrays)

        return functools.wraps(method)(broadcast)

    return decorator


def _state_names(signature: str) -> tuple[str, ...]:
    """The names of the arrays a method on states takes, by its core signature (`over_states`):
    ``("t", "q", "qd")`` for ``"(),(n),(n)->()"``."""
    return ("t", "q", "qd", "qdd")[:signature.split("->")[0].count("(")]


def _positional(name, names, args, kwargs):
    """The arguments (*arrays, p) of a method on states, with p possibly given by keyword
    (other keywords are the method's own options)."""
    if "p" in kwargs and len(args) != len(names):
        raise TypeError(
            f"{name} takes ({', '.join(names)}, p=None), got keyword arguments "
            f"{sorted(kwargs)} after {len(args)} positional arguments."
        )
    args = (*args, kwargs["p"]) if "p" in kwargs else args
    if len(args) not in (len(names), len(names) + 1):
        raise TypeError(
            f"{name} takes ({', '.join(names)}, p=None), got {len(args)} positional arguments."
        )
    return args


def _split(inputs: str) -> list[str]:
    return ["(" + part.strip("(),") + ")" for part in inputs.split(")") if part.strip(",")]


def check_parameter_dtypes(p, dtype):
    """Parameters share the state's real floating dtype: mixed precision would either be
    promoted silently (float32 work done in float64, or the reverse) or fail deep inside."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(p):
        if not eqx.is_inexact_array(leaf) or leaf.dtype == dtype:
            continue
        where = f"p{jax.tree_util.keystr(path)}"
        if jnp.issubdtype(leaf.dtype, jnp.complexfloating):
            raise ValueError(f"{where} is complex ({leaf.dtype}): parameters must be real.")
        raise ValueError(
            f"{where} has dtype {leaf.dtype} but the state is {dtype}: mixed "
            "precision is not accepted. Cast the parameters to the state's dtype, e.g. "
            f"jax.tree.map(lambda x: x.astype(jnp.{dtype}), p), or the state to theirs.")


def numbers_as_arrays(tree, dtype=None) -> Any:
    """Python floats and ints in `tree` as arrays, so that they are traced rather than
    compiled in: a new parameter value, time or tolerance then reuses the compiled program.

    Floats take `dtype` (that of the state; by default JAX's default float), so that a Python
    number never changes the precision of a computation. A float becomes a device array kept
    for the next call with the same number (`_device_scalar`): a host value would be copied
    to the device at every call, ~2 µs each, about as much as the rest of a call's dispatch.
    """
    dtype = np.dtype(jnp.result_type(float) if dtype is None else dtype)

    def convert(x):
        if type(x) is float:  # (the common case first: a walk over a call's numbers)
            return _device_scalar(x, math.copysign(1.0, x), dtype)
        if isinstance(x, bool):
            return x
        if isinstance(x, float):
            return _device_scalar(x, math.copysign(1.0, x), dtype)
        if isinstance(x, int):
            return np.asarray(x, jnp.result_type(int))
        return x

    def converted(tree):
        # (A robot's parameters are hundreds of arrays and no number: a walk that finds
        # none returns the tree as it is instead of rebuilding it, 0.2-0.5 ms of each eager
        # call; the arguments of a call, a tuple, are walked one by one.)
        kind = type(tree)
        if kind is tuple:
            return tuple(map(converted, tree))
        if tree is None or kind is bool:
            return tree
        if kind is float or kind is int:  # (a time, a tolerance)
            return convert(tree)
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        if remembered_arrays(leaves, treedef) or not any(map(_is_number, map(type, leaves))):
            return tree
        return jax.tree_util.tree_unflatten(treedef, list(map(convert, leaves)))

    return converted(tree)


@functools.cache
def _is_number(cls) -> bool:
    return issubclass(cls, (float, int))


@functools.lru_cache(maxsize=1024)
def _device_scalar(value, sign, dtype):
    # `sign` keeps 0.0 and -0.0 apart (they are equal as keys). Made concrete even when
    # called under a trace, so that no tracer is kept.
    # A transfer of the NumPy value, not `jnp.asarray` (a conversion XLA compiles, ~5 ms in a
    # new process).
    with jax.ensure_compile_time_eval():
        return transferred(value, dtype)


FLOAT32_BY_DEFAULT = (
    "jaxdyn is computing in float32 because JAX's 64-bit mode is off: mass matrices, long "
    "integrations and fits lose most of their accuracy (float64 inputs are cast to float32, "
    "and jnp.array(1.0) is float32). Turn it on before any JAX computation: "
    "jax.config.update('jax_enable_x64', True). To compute in float32 on purpose, call "
    "jaxdyn.allow_float32() (this warning is then not given).")
_warned_float32 = []
# A precision no default gives: a state in float16 or bfloat16 was chosen. A float32 array
# was not, necessarily: with 64-bit mode off every array JAX makes is float32.
_CHOSEN_PRECISION = (np.dtype(np.float16), np.dtype(jnp.bfloat16))
_FLOAT32_ALLOWED = [False]


def allow_float32(allowed: bool = True) -> None:
    """Declare that computing in float32 is intended, for this process.

    jaxdyn computes in the precision of the state, and JAX makes float32 arrays (and casts
    float64 inputs to float32) unless its 64-bit mode is on. Mechanics loses most of its
    accuracy there (a mass matrix's condition number times ε₃₂ ≈ 1.2e-7; the default
    tolerance becomes 1e-6), so the first computation with 64-bit mode off warns once,
    naming the switch, unless this was called. For float64, call
    `jax.config.update("jax_enable_x64", True)` before any JAX computation instead.

    **Arguments:**

    - `allowed`: True (float32 on purpose: no warning) or False (warn again, once, at the
      next computation in float32).
    """
    _FLOAT32_ALLOWED[0] = bool(allowed)
    if not allowed:
        _warned_float32.clear()


# JAX's flags are attributes that `Config` adds at run time, unknown to a type checker.
_CONFIG: Any = jax.config


def _caller_outside_jaxdyn() -> int:
    """The `stacklevel` of the first caller outside the jaxdyn package (the user's line)."""
    frame, level = sys._getframe(2), 2  # 1: the function that warns; 2: its caller
    package = os.path.dirname(os.path.abspath(__file__))
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


def state_dtype(*candidates):
    """The floating dtype of the first array among `candidates` (the state), else the
    default float. Warns once per process when JAX's 64-bit mode is off, unless float32 was
    declared intended (`allow_float32`) or the state is in float16 or bfloat16."""
    if (not _CONFIG.jax_enable_x64 and not _warned_float32 and not _FLOAT32_ALLOWED[0]
            and not any(getattr(x, "dtype", None) in _CHOSEN_PRECISION for x in candidates)):
        _warned_float32.append(True)
        warnings.warn(FLOAT32_BY_DEFAULT, UserWarning, stacklevel=_caller_outside_jaxdyn())
    for x in candidates:
        dtype = getattr(x, "dtype", None)
        if dtype is not None and jnp.issubdtype(dtype, jnp.floating):
            return dtype
    return jnp.result_type(float)


def under_a_trace() -> bool:
    """Whether a JAX transformation (`jax.jit`, `vmap`, `grad`) is tracing the caller, so that
    values are not at hand."""
    return not jax_core.trace_state_clean()


def public_method(signature: str, *, checked: bool = False):
    """A public method on states: `over_states` broadcasting, compiled once per system and
    argument shapes (and reused on every later call, also when called outside `jax.jit`),
    with errors that name the failing state (`reports_state`).

    Inside a caller's `jax.jit`, `vmap` or `grad` it is traced once and inlined.

    `checked`: the method takes `throw` (True: a value-dependent check inside the program,
    whose failing branch raises from the host; False: NaN where the result fails, no branch).
    Its default, None, costs nothing in either place a method is called from. Called eagerly
    the program carries no branch and the host reads one flag, "all finite", from the result
    (its values are on the host's doorstep anyway); only when that flag is down does the
    checked program run, to name the cause and the state. Inside a caller's trace (their
    `jax.jit`, `vmap`, `grad`) a failure is carried as a value, NaN, as with `throw=False`: a
    check's host callback there would keep XLA from compiling a small loop as one function
    and cost several evaluations of the equations per iteration.
    """
    names = _state_names(signature)

    def decorator(method):
        broadcast = over_states(signature)(method)

        def evaluate(self, args, options):
            if len(args) > len(names):  # dtypes are static: checked when traced
                check_parameter_dtypes(args[-1], state_dtype(*args[1:]))
            return broadcast(self, *args, **dict(options))

        compiled = filter_jit(evaluate)

        @filter_jit
        def flagged(self, args, options):
            out = evaluate(self, args, options)
            return out, jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf))
                                           for leaf in jax.tree_util.tree_leaves(out)]))

        @functools.wraps(method)
        def wrapper(self, *args, **kwargs):
            throw = kwargs.pop("throw", None) if checked else False
            options = tuple((k, v) for k, v in kwargs.items() if k != "p")
            args = _positional(method.__name__, names, args, kwargs)
            args = numbers_as_arrays(args, state_dtype(*args[1:]))
            if throw is not None or not checked:
                return compiled(self, args, options + ((("throw", throw),) if checked else ()))
            unchecked = options + (("throw", False),)
            if under_a_trace():  # inside the caller's trace: NaN on failure
                return compiled(self, args, unchecked)
            out, finite = flagged(self, args, unchecked)
            if bool(finite):
                return out
            # Only now, with the failure in hand: the checked program names cause and state.
            return compiled(self, args, options + (("throw", True),))

        return BoundOnce(reports_state(wrapper, block=False))  # `compiled`: ready results

    return decorator


_Self = TypeVar("_Self")
_Params = ParamSpec("_Params")
_Return = TypeVar("_Return")


class _Bound(eqx.Module):
    """`instance.method`, a pytree of the instance (what equinox's bound methods are), with
    the method's name, docstring and signature (`__wrapped__`, for `help` and `inspect`)."""

    method: Callable = eqx.field(static=True)
    instance: Any

    def __post_init__(self):
        for name in ("__module__", "__name__", "__qualname__", "__doc__"):
            if hasattr(self.method, name):
                object.__setattr__(self, name, getattr(self.method, name))

    def __call__(self, *args, **kwargs):
        return self.method(self.instance, *args, **kwargs)

    @property
    def __wrapped__(self):
        return self.method.__get__(self.instance, type(self.instance))


class BoundOnce(Generic[_Self, _Params, _Return]):
    """A method whose bound form (`_Bound`, a pytree of the instance as equinox's own bound
    methods are) is built once per instance and kept on it. Equinox builds its bound method
    at every attribute access, which walks the whole module in Python: 0.1–0.5 ms for a robot
    of 13–78 links, more than the call it precedes. (The instance and its cache refer to each
    other: Python's cyclic collector frees them.)"""

    def __init__(self, method: Callable[Concatenate[_Self, _Params], _Return]):
        self.method = method
        self.__doc__, self.__wrapped__ = method.__doc__, method  # for help() and inspect

    @overload
    def __get__(self, instance: None, owner: Any = None
                ) -> Callable[Concatenate[_Self, _Params], _Return]: ...

    @overload
    def __get__(self, instance: _Self, owner: Any = None) -> Callable[_Params, _Return]: ...

    def __get__(self, instance, owner=None):
        if instance is None:
            return self.method
        # The module is frozen: a cache beside its fields, not one of them, with its owner
        # (a `copy.copy` of the module shares its attributes, and gets a cache of its own).
        # Keyed by the descriptor: a subclass's override and the method it overrides differ.
        cache = instance.__dict__.get("_bound_methods")
        if cache is None or cache[0] is not instance:
            cache = (instance, {})
            object.__setattr__(instance, "_bound_methods", cache)
        method = cache[1].get(self)
        if method is None:
            method = cache[1][self] = _Bound(self.method, instance)
        return method


def public_function(num_static: int = 1, chunked: bool = True):
    """A public function ``fn(system, *args, **options)`` of a system and states, compiled once
    per system, argument shapes and options (keyword options and the first `num_static`
    positional arguments — the system, a frame's name — are static; Python floats among the
    rest are traced, so that a new value reuses the program). Inside a caller's `jax.jit`,
    `vmap` or `grad` it is traced once and inlined; under `vmap` it runs in chunks of a few
    states (`jaxdyn._chunking`) where `chunked`, else batched whole."""
    def decorator(fn):
        @filter_jit
        def compiled(static, args, options):
            # Under `jax.vmap` in chunks of a few states (`jaxdyn._chunking`): a tree's
            # recursions are array programs of many small kernels.
            partial = functools.partial(fn, **dict(options))
            return (chunked_vmap(partial) if chunked else partial)(*static, *args)

        @functools.wraps(fn)
        def wrapper(*args, **options):
            static, arrays = args[:num_static], args[num_static:]
            arrays = numbers_as_arrays(arrays, state_dtype(*arrays))
            return compiled(static, arrays, tuple(sorted(options.items())))

        return wrapper

    return decorator


def frozen_constant(x: Any) -> Any:
    """A numeric constant as (nested tuples of) Python floats, not an array: a compiled
    program then sees it as a constant, folded into straight-line code, rather than as one
    more input (`eqx.filter_jit` traces every array of a module). Functions of p, None and
    traced values are kept as they are."""
    if x is None or callable(x) or isinstance(x, jax.core.Tracer):
        return x

    def frozen(value):
        return tuple(frozen(v) for v in value) if isinstance(value, list) else value

    return frozen(np.asarray(x, dtype=float).tolist())
