"""Compiled entry points whose call costs what `jax.jit`'s own dispatch costs.

`eqx.filter_jit` traces the arrays among its arguments and treats everything else (the user's
callbacks, solvers, options) as static. Its dispatch re-partitions and re-hashes every argument
in Python at each call, about 100–200 µs for `simulate`'s arguments: more than a whole solve of
a small system over a few hundred steps. `filter_jit` here keeps those semantics but caches, per
argument structure, a `jax.jit` of the array leaves alone, so that a repeated call costs one
`tree_flatten`, a dictionary look-up and `jax.jit`'s C++ dispatch.
"""

import contextlib
import functools
import gc
import weakref
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core

from . import _xla
from ._errors import checks_as_nan_active, checks_read_on_host


def filter_jit(fn, compiler_options=None, *, checks_on_host=False):
    """`eqx.filter_jit(fn)` (arrays traced, other leaves static; non-array outputs allowed)
    with a cached dispatch; outside a trace the outputs are ready when it returns.
    `compiler_options`: XLA's options for the programs compiled here (`jax.jit`'s).
    `checks_on_host`: called with values, `fn`'s own checks (`jaxdyn._errors.error_if` at its
    top level) are flags the host reads after the program, which then holds no host callback
    (so that JAX's persistent compilation cache can keep it); only when one is up does the
    program with the checks run, to raise its message. Under a trace, the checks stay inside.

    The cache key is the arguments' tree structure, their non-array leaves (hashed: functions
    by identity, modules and numbers by value), the shapes and dtypes of their arrays, JAX's
    `jax_disable_most_optimizations` and whether checks are traced as NaN
    (`jaxdyn._errors.checks_as_nan`).
    Arguments with an unhashable non-array leaf take `eqx.filter_jit`'s own path. Under an
    outer trace (`jax.jit`, `vmap`, `grad`) both are the same inlined call.
    """
    if checks_on_host:
        checked = filter_jit(fn, compiler_options)

        def reading_checks(*args):
            with checks_read_on_host() as flags:
                out = fn(*args)
            return out, jnp.any(jnp.stack(flags)) if flags else np.False_

        lean = filter_jit(reading_checks, compiler_options)

        @functools.wraps(fn)
        def on_host(*args):
            if not jax_core.trace_state_clean():
                return checked(*args)
            out, failed = lean(*args)
            return checked(*args) if bool(failed) else out

        return on_host

    def under_setting(settings, *args):  # (the switches a static argument, for the cache)
        return fn(*args)

    under_setting.__name__ = under_setting.__qualname__ = getattr(fn, "__name__", "fn")
    by_setting = eqx.filter_jit(under_setting)

    def fallback(*args):
        return by_setting((jax.config.read("jax_disable_most_optimizations"),
                           checks_as_nan_active()), *args)

    cache: dict = {}

    @functools.wraps(fn)
    def wrapper(*args):
        leaves, treedef, parts = _flatten(args)
        if any(_TRACER in part.kinds for part in parts):
            return fallback(*args)
        kinds = [k for part in parts for k in part.kinds]
        dynamic = [i for i, k in enumerate(kinds) if k is _ARRAY]
        arrays = [leaves[i] for i in dynamic]
        # Typed, so that equal values of different types (1, 1.0, True) stay apart.
        static = tuple(item for part in parts for item in part.static)
        try:
            # (with JAX's switch for compile time over run time, under which jaxdyn also
            # traces other forms of some programs: `jaxdyn._integrate.simulate._stepper`)
            key = (treedef, static, tuple(part.avals for part in parts),
                   jax.config.read("jax_disable_most_optimizations"), checks_as_nan_active())
            entry = cache.get(key)
        except TypeError:  # an unhashable option
            return fallback(*args)
        if entry is None:
            entry = cache[key] = _Entry(fn, treedef, leaves, dynamic, compiler_options)
        if not jax_core.trace_state_clean():
            out = entry.nested(*arrays)
        elif not hasattr(entry, "out_treedef"):
            with gc_paused():  # the first call traces and compiles
                out = jax.block_until_ready(entry.compiled(*arrays))
        else:
            # Ready before returning (one batched wait on the arrays, not a walk of the output
            # pytree), so that an error raised by a check inside reaches the caller from here.
            out = jax.block_until_ready(entry.compiled(*arrays))
        return jax.tree_util.tree_unflatten(
            entry.out_treedef, _merge(entry.out_static, entry.out_dynamic, out))

    return wrapper


# XLA's CPU backend has two code generators for fused element-wise work (benchmarks/LOG.md,
# "The straight-line program and XLA's CPU emitters"). `import jaxdyn` makes the elemental
# emitters the process's default: on straight-line programs of more than a few hundred scalar
# operations the newer fusion emitters generate code up to thousands of times slower. But a
# vmapped solve of equations smaller than this (scalar operations) runs faster with the fusion
# emitters, which vectorise the solver's loop over the batch better: 1024 double pendulums,
# T as 2-vectors (401 operations), 0.70x the time; as rotation matrices (597), 0.60x; a chain
# of 3 rods (829) the same; a chain of 5 (1528) 1.2x slower. Batched programs that jaxdyn
# compiles itself choose by this bound; a user's own `jax.jit` follows the process's choice.
FUSION_EMITTERS_MAX = 800
FUSION_EMITTERS = {"xla_cpu_use_fusion_emitters": True}


def batch_emitters(size, platform) -> dict | None:
    """XLA's compiler options for a vmapped solve on `platform` of equations of `size` scalar
    operations (None when they run as array programs): the fusion emitters for small ones on
    a CPU, else the process's default (None)."""
    if platform == "cpu" and size is not None and size <= FUSION_EMITTERS_MAX:
        return FUSION_EMITTERS
    return None


@contextlib.contextmanager
def gc_paused():
    """Python's cyclic garbage collector paused for a trace and compilation.

    Tracing allocates hundreds of thousands of short-lived objects, which trigger full
    collections that walk every object of the process (JAX, NumPy, SciPy and the user's):
    ~0.1 s of a 0.7 s first `simulate`. Garbage left in cycles is collected after."""
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


class _Entry:
    """One argument structure: its `jax.jit`, and the static part of its output (recorded
    when traced)."""

    # Set by the first call of `compiled`, which traces `arrays_only`.
    out_treedef: Any  # a jax.tree_util.PyTreeDef: an alias, which pyright refuses as a type
    out_dynamic: list[int]
    out_static: dict[int, Any]

    def __init__(self, fn, treedef, leaves, dynamic, compiler_options):
        template = list(leaves)

        def arrays_only(*arrays):
            filled = list(template)
            for i, x in zip(dynamic, arrays):
                filled[i] = x
            out = fn(*_unflatten(treedef, filled))
            out_leaves, self.out_treedef = jax.tree_util.tree_flatten(out)
            kinds = [_kind(type(x)) for x in out_leaves]
            self.out_dynamic = [i for i, k in enumerate(kinds) if k is not _STATIC]
            self.out_static = {i: x for i, (x, k) in enumerate(zip(out_leaves, kinds))
                               if k is _STATIC}
            return [out_leaves[i] for i in self.out_dynamic]

        # The template's arrays are replaced at every call: drop them, so that the first
        # call's inputs are not kept alive by the cache.
        for i in dynamic:
            template[i] = None
        # XLA's CPU switches that a program can carry itself (`jaxdyn._xla`): set whether or
        # not JAX started before jaxdyn was imported; the caller's own options win. Called
        # inside another trace (a derivative of values closed over), the same function
        # without options: JAX takes options on the outermost program only.
        self.compiled = jax.jit(arrays_only, compiler_options={
            **_xla.compiler_options(), **(compiler_options or {})} or None)
        self.nested = jax.jit(arrays_only)


def _merge(static, dynamic_positions, dynamic_values):
    leaves = [None] * (len(static) + len(dynamic_positions))
    for i, x in static.items():
        leaves[i] = x
    for i, x in zip(dynamic_positions, dynamic_values):
        leaves[i] = x
    return leaves


class _Part(NamedTuple):
    """What the dispatch reads of one argument's leaves: their kinds, the static ones (typed:
    equal values of different types, 1, 1.0 and True, stay apart) and the arrays' shapes and
    dtypes (for a large tree, a number that stands for them)."""

    kinds: tuple
    static: tuple
    avals: Any


def _part(leaves) -> _Part:
    kinds = tuple(_kind(type(x)) for x in leaves)
    return _Part(kinds, tuple((type(x), x) for x, k in zip(leaves, kinds) if k is _STATIC),
                 tuple((x.shape, x.dtype) for x, k in zip(leaves, kinds) if k is _ARRAY))


# Arguments seen recently, read once: modules (the user's system, solver, adjoint; immutable)
# by identity, the entry keeping the module alive so that its id is not reused; and large
# trees of JAX arrays (a robot's parameters: hundreds of arrays, whose shapes and dtypes alone
# cost ~0.3 ms to read in Python at every call) by the identities of their leaves, which JAX
# never changes in place. A tree's entry holds weak references only (a user's large arrays
# are not kept alive by it) and goes when one of its arrays does, before its id can be reused.
_MODULES: dict = {}
_TREES: dict = {}
_REMEMBERED_MAX = 256
_TREE_LEAVES_MIN = 16  # smaller trees are read at each call: cheaper than the look-up
# The shapes and dtypes of a large tree -> a number that stands for them in the cache's
# key (hashed at no cost, where a tuple of hundreds is hashed again at every call). Never
# cleared: a number is never reused for other shapes.
_AVALS: dict = {}


def remembered_arrays(leaves, treedef) -> bool:
    """Whether `leaves` (of a tree of `treedef`) are a large tree of JAX arrays seen before,
    unchanged (the same arrays): nothing in them then needs reading again."""
    if len(leaves) < _TREE_LEAVES_MIN:
        return False
    return (treedef, tuple(map(id, leaves))) in _TREES


def _flatten(args):
    """(leaves, treedef, parts) of a tuple of arguments. Modules are read once and remembered,
    each with its own `_Part`; so is a tuple holding a module at its top level, element by
    element. The other arguments (arrays, numbers, options) are read as one `_Part` (one
    walk instead of one per argument: ~40 µs of an eager `simulate`), unless one of them is
    a large tree, which is read apart so that a tree of JAX arrays is remembered; their
    leaves come last. `treedef`: a tuple of (position, leaf count or "tuple", treedef) in
    the leaves' order."""
    leaves, treedefs, parts = [], [], []
    plain_leaves, plain, plain_treedefs = [], [], []  # (the other arguments)
    for i, x in enumerate(args):
        if _is_module(type(x)):
            hit = _MODULES.get(id(x))
            if hit is None or hit[0] is not x:
                hit = (x, *jax.tree_util.tree_flatten(x))
                if not any(_kind(type(leaf)) is _TRACER for leaf in hit[1]):
                    if len(_MODULES) >= _REMEMBERED_MAX:
                        _MODULES.clear()
                    _MODULES[id(x)] = hit = (*hit, _part(hit[1]))
            leaves.extend(hit[1])
            parts.append(hit[3] if len(hit) > 3 else _part(hit[1]))
            treedefs.append((i, len(hit[1]), hit[2]))
        elif type(x) is tuple and any(_is_module(type(e)) for e in x):
            sub_leaves, sub_treedef, sub_parts = _flatten(x)
            leaves.extend(sub_leaves)
            parts.extend(sub_parts)
            treedefs.append((i, "tuple", sub_treedef))
        else:
            sub_leaves, sub_treedef = jax.tree_util.tree_flatten(x)
            plain_leaves.extend(sub_leaves)
            plain.append(sub_leaves)
            plain_treedefs.append((i, len(sub_leaves), sub_treedef))
    if all(len(sub_leaves) < _TREE_LEAVES_MIN for sub_leaves in plain):
        parts.append(_part(plain_leaves))
    else:
        parts.extend(_tree_part(sub_leaves, t[2]) for sub_leaves, t in zip(plain,
                                                                             plain_treedefs))
    leaves.extend(plain_leaves)
    return leaves, (*treedefs, *plain_treedefs), parts


def _tree_part(leaves, treedef) -> _Part:
    if len(leaves) < _TREE_LEAVES_MIN:
        return _part(leaves)
    key = (treedef, tuple(map(id, leaves)))
    hit = _TREES.get(key)
    if hit is not None:
        return hit[1]
    part = _part(leaves)
    # (a number for the shapes whether or not the tree is remembered: the same shapes given
    # as NumPy arrays must find the program compiled for JAX arrays)
    part = part._replace(avals=_AVALS.setdefault(part.avals, len(_AVALS)))
    if all(isinstance(x, jax.Array) and _kind(type(x)) is _ARRAY for x in leaves):
        if len(_TREES) >= _REMEMBERED_MAX:
            _TREES.clear()

        def forget(_, key=key):
            _TREES.pop(key, None)

        _TREES[key] = ([weakref.ref(x, forget) for x in leaves], part)
    return part


# What a leaf is, by its type (cached: `isinstance` against JAX's abstract array classes costs
# more than the rest of the dispatch).
_ARRAY, _TRACER, _STATIC = "array", "tracer", "static"


@functools.cache
def _kind(cls):
    if issubclass(cls, jax.core.Tracer):
        return _TRACER
    return _ARRAY if issubclass(cls, (jax.Array, np.ndarray, np.generic)) else _STATIC


@functools.cache
def _is_module(cls):
    return issubclass(cls, eqx.Module)


def _unflatten(treedefs, leaves):
    """The arguments from their leaves and `_flatten`'s treedef."""
    out, start = [None] * len(treedefs), 0
    for position, kind, treedef in treedefs:
        if kind == "tuple":
            count = _count(treedef)
            out[position] = tuple(_unflatten(treedef, leaves[start:start + count]))
        else:
            count = kind
            out[position] = jax.tree_util.tree_unflatten(treedef, leaves[start:start + count])
        start += count
    return out


def _count(treedefs):
    return sum(_count(t) if k == "tuple" else k for _, k, t in treedefs)
