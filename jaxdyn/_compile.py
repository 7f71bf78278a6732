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
import operator
import weakref
from typing import Any, Callable, NamedTuple

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
        if any(part.tracer for part in parts):
            return fallback(*args)
        try:
            # (with JAX's switch for compile time over run time, under which jaxdyn also
            # traces other forms of some programs: `jaxdyn._integrate.simulate._stepper`)
            key = (treedef, tuple(part.static for part in parts),
                   tuple(part.avals for part in parts),
                   jax.config.read("jax_disable_most_optimizations"), checks_as_nan_active())
            entry = cache.get(key)
        except TypeError:  # an unhashable option
            return fallback(*args)
        if entry is None:
            kinds = [k for part in parts for k in part.kinds]
            entry = cache[key] = _Entry(fn, treedef, leaves,
                                        [i for i, k in enumerate(kinds) if k is _ARRAY],
                                        compiler_options)
        arrays = entry.arrays_of(leaves)
        if not jax_core.trace_state_clean():
            out = entry.nested(*arrays)
        elif not hasattr(entry, "out_treedef"):
            with gc_paused():  # the first call traces and compiles
                out = jax.block_until_ready(entry.compiled(*arrays))
        else:
            out = entry.compiled(*arrays)
            # Ready before returning, so that an error raised by a check inside reaches the
            # caller from here. The outputs of one program are ready together: one wait,
            # after the output is assembled while the program runs.
            result = _assembled(entry, out)
            if out:
                out[0].block_until_ready()
            return result
        return _assembled(entry, out)

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
    # The output's leaves with its static ones in place (None when all are arrays).
    out_template: list | None
    # Where the program returns an array once for several outputs, the gather of its outputs
    # into them (else None).
    out_repeated: Callable | None

    def __init__(self, fn, treedef, leaves, dynamic, compiler_options):
        template = list(leaves)
        self.arrays_of = _getter(dynamic)

        def arrays_only(*arrays):
            filled = list(template)
            for i, x in zip(dynamic, arrays):
                filled[i] = x
            out = fn(*_unflatten(treedef, filled))
            out_leaves, self.out_treedef = jax.tree_util.tree_flatten(out)
            kinds = [_kind(type(x)) for x in out_leaves]
            self.out_dynamic = [i for i, k in enumerate(kinds) if k is not _STATIC]
            self.out_template = None if _STATIC not in kinds else [
                x if k is _STATIC else None for x, k in zip(out_leaves, kinds)]
            # An array returned twice (a `Lagrangian`'s q̇, which is its u) leaves the program
            # once: each output costs its dispatch ~2 µs.
            unique, positions = [], []
            for i in self.out_dynamic:
                positions.append(next((j for j, x in enumerate(unique)
                                       if x is out_leaves[i]), len(unique)))
                if positions[-1] == len(unique):
                    unique.append(out_leaves[i])
            self.out_repeated = (None if len(unique) == len(self.out_dynamic)
                                 else _getter(positions))
            return unique

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


def _assembled(entry, out):
    """The output of `entry`'s function from the arrays its program returned."""
    if entry.out_repeated is not None:
        out = entry.out_repeated(out)
    if entry.out_template is not None:
        out = _merge(entry.out_template, entry.out_dynamic, out)
    return jax.tree_util.tree_unflatten(entry.out_treedef, out)


def _merge(template, dynamic_positions, dynamic_values):
    leaves = list(template)
    for i, x in zip(dynamic_positions, dynamic_values):
        leaves[i] = x
    return leaves


def _getter(positions):
    """A function of a list giving its items at `positions`, as a tuple (`itemgetter`,
    which returns a bare item for one position)."""
    if len(positions) == 1:
        position = positions[0]
        return lambda items: (items[position],)
    return operator.itemgetter(*positions) if positions else (lambda items: ())


class _Part(NamedTuple):
    """What the dispatch reads of one argument's leaves: their kinds, whether one is a
    tracer, the static ones with the types of all (typed: equal values of different types,
    1, 1.0 and True, stay apart) and the arrays' shapes and dtypes (for a large tree, a
    number that stands for them)."""

    kinds: tuple
    tracer: bool
    static: tuple
    avals: Any


# The leaves' types -> (their kinds, whether one is a tracer, the static leaves' types, and
# getters of the static leaves and of the arrays): read once per pattern of types, so that
# a call's leaves are sorted by two C-level gathers rather than a walk in Python.
_PATTERNS: dict = {}
_SHAPE_AND_DTYPE = operator.attrgetter("shape", "dtype")


def _part(leaves) -> _Part:
    types = tuple(map(type, leaves))
    pattern = _PATTERNS.get(types)
    if pattern is None:
        if len(_PATTERNS) >= _REMEMBERED_MAX:
            _PATTERNS.clear()
        kinds = tuple(_kind(t) for t in types)
        static = [i for i, k in enumerate(kinds) if k is _STATIC]
        pattern = _PATTERNS[types] = (
            kinds, _TRACER in kinds, tuple(types[i] for i in static), _getter(static),
            _getter([i for i, k in enumerate(kinds) if k is _ARRAY]))
    kinds, tracer, static_types, static, arrays = pattern
    # (the types of the static leaves alone: arrays of NumPy and of JAX share a program)
    return _Part(kinds, tracer, (static_types, static(leaves)),
                 tuple(map(_SHAPE_AND_DTYPE, arrays(leaves))))


# Arguments seen recently, read once: modules (the user's system, solver, adjoint; immutable)
# by identity, the entry keeping the module alive so that its id is not reused; and large
# trees of JAX arrays (a robot's parameters: hundreds of arrays, whose shapes and dtypes alone
# cost ~0.3 ms to read in Python at every call) by the identities of their leaves, which JAX
# never changes in place. A tree's entry holds weak references only (a user's large arrays
# are not kept alive by it) and goes when one of its arrays does, before its id can be reused.
_MODULES: dict = {}
_MODULES_BY_VALUE: dict = {}
_TREES: dict = {}
_REMEMBERED_MAX = 256
_TREE_LEAVES_MIN = 16  # smaller trees are read at each call: cheaper than the look-up
# Arguments of fewer leaves than this, together, are read at each call as one; more, and the
# large trees among them are looked up.
_TOGETHER_LEAVES_MAX = 64
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
    element. The other arguments (arrays, numbers, options) are flattened together and read
    as one `_Part` (one walk instead of one per argument: ~40 µs of an eager `simulate`),
    unless they hold a large tree, which is read apart so that a tree of JAX arrays is
    remembered; their leaves come last. `treedef`: a tuple of (position, leaf count or
    "tuple", treedef) in the leaves' order, the other arguments' as (positions, "together",
    treedef of their tuple) or one entry each."""
    leaves, treedefs, parts = [], [], []
    plain, positions = [], []  # (the other arguments)
    for i, x in enumerate(args):
        if _is_module(type(x)):
            hit = _MODULES.get(id(x))
            if hit is None or hit[0] is not x:
                hit = _read_module(x)
            leaves.extend(hit[1])
            parts.append(hit[3])
            treedefs.append((i, len(hit[1]), hit[2]))
        elif type(x) is tuple and any(map(_is_module, map(type, x))):
            sub_leaves, sub_treedef, sub_parts = _flatten(x)
            leaves.extend(sub_leaves)
            parts.extend(sub_parts)
            treedefs.append((i, "tuple", sub_treedef))
        else:
            plain.append(x)
            positions.append(i)
    plain_leaves, plain_treedef = jax.tree_util.tree_flatten(plain)
    if len(plain_leaves) < _TOGETHER_LEAVES_MAX:
        parts.append(_part(plain_leaves))
        treedefs.append((tuple(positions), "together", plain_treedef))
    else:
        plain_leaves = []
        for i, x in zip(positions, plain):
            sub_leaves, sub_treedef = jax.tree_util.tree_flatten(x)
            parts.append(_tree_part(sub_leaves, sub_treedef))
            plain_leaves.extend(sub_leaves)
            treedefs.append((i, len(sub_leaves), sub_treedef))
    leaves.extend(plain_leaves)
    return leaves, tuple(treedefs), parts


def _read_module(x):
    """(x, leaves, treedef, `_Part`) of a module not seen before, remembered by identity; one
    whose fields are hashable values (a solver made at each call, `diffrax.Tsit5()`) is also
    remembered by them, typed, so that an equal module reuses the reading."""
    try:
        fields = vars(x)
        by_value = (type(x), tuple(fields.items()), tuple(map(type, fields.values())))
        hit = _MODULES_BY_VALUE.get(by_value)
    except TypeError:  # (a field holds an array)
        by_value = hit = None
    if hit is None:
        leaves, treedef = jax.tree_util.tree_flatten(x)
        hit = (x, leaves, treedef, _part(leaves))
        if hit[3].tracer:
            return hit
        if by_value is not None:
            if len(_MODULES_BY_VALUE) >= _REMEMBERED_MAX:
                _MODULES_BY_VALUE.clear()
            _MODULES_BY_VALUE[by_value] = hit
    if len(_MODULES) >= _REMEMBERED_MAX:
        _MODULES.clear()
    _MODULES[id(x)] = hit = (x, *hit[1:])
    return hit


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
    out, start = [None] * _count_arguments(treedefs), 0
    for position, kind, treedef in treedefs:
        if kind == "tuple":
            count = _count(treedef)
            out[position] = tuple(_unflatten(treedef, leaves[start:start + count]))
        elif kind == "together":
            count = treedef.num_leaves
            for i, x in zip(position, jax.tree_util.tree_unflatten(
                    treedef, leaves[start:start + count])):
                out[i] = x
        else:
            count = kind
            out[position] = jax.tree_util.tree_unflatten(treedef, leaves[start:start + count])
        start += count
    return out


def _count_arguments(treedefs):
    return sum(len(position) if kind == "together" else 1 for position, kind, _ in treedefs)


def _count(treedefs):
    return sum(_count(t) if k == "tuple" else t.num_leaves if k == "together" else k
               for _, k, t in treedefs)
