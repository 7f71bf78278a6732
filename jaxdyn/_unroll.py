"""Straight-line scalar code for the equations of motion of small systems.

The equations of a system with a handful of coordinates, formed by automatic differentiation,
are a few hundred scalar operations spread over many tiny arrays: unit tangents built from an
identity matrix, stacks, pads, slices, dot products of 2-vectors. XLA compiles each tiny array
operation into a kernel of its own on the CPU, and on a double pendulum these kernels cost ten
times the arithmetic (the hand-written closed form compiles into one). Re-evaluating the traced
program (its jaxpr) one array element at a time turns it into a graph of scalar operations that
XLA fuses into a single kernel, and lets three things happen at trace time that XLA may not do
under IEEE semantics:

- constant folding: products with the zeros and ones of unit tangents and identity matrices
  vanish, as they would with JAX's own symbolic zeros (0·x is taken as 0);
- data movement (broadcasts, slices, gathers with static indices, transposes) becomes plain
  renaming of scalars;
- the structure of the result is visible: an entry that folds to a constant is known to be
  constant (used to skip work a system does not need);
- an operation already at hand is not written again, nor one that is a different expression
  of it, whatever way the user wrote T (cos²θ + sin²θ is 1, a sign meets a sum as a
  subtraction: `jaxdyn._unroll_numbering`).

Every scalar operation is the same JAX primitive as in the original program, so values are
unchanged (to rounding, where an identity replaced an expression) and JAX differentiates and
batches the result as usual. Primitives without an
element-wise rule (loops, linear solves, custom derivative rules) are evaluated on whole arrays
assembled from their elements, so every program can be unrolled; the budget below keeps the
unrolled program small, and larger programs run as they were written.

This is an interpreter over jaxprs in the sense of JAX's "Writing custom interpreters" guide.
This module holds its entry points: what is written out, within which budget, and how the
result is differentiated (`unrolled`, `structure`, `straight_line_size`, `depends`). The
interpreter itself, one equation at a time with a rule per primitive and the algebra that
folds constants, is `jaxdyn._unroll_rules`.
"""

import contextvars
import math
from typing import Literal, overload

import equinox as eqx
import jax
import numpy as np
from jax.extend import core as jex

from ._chunking import chunked_vmap
from ._custom_jvp import batch_axis_first
from ._unroll_numbering import _NUMBERING
from ._unroll_rules import (
    _ANALYSIS,
    _BUDGET,
    Symbol,
    _eval,
    _Fallback,
    _filled,
    _inline_jaxpr,
    _is_concrete,
    assemble,
    is_constant as is_constant,  # (re-exported: `jaxdyn._dynamics` names it from here)
    split,
)

# Programs whose unrolled form has more scalar operations than this (after constant folding)
# run as written. Up to it, straight-line code wins twice over: a program of 3-vectors and
# 3 × 3 rotations run as written launches a kernel per tiny operation (a heavy top by
# Gibbs–Appell, 2195 operations: 7.0 ms a simulation as arrays, 0.37 ms unrolled, and 18 → 9 s
# to compile; a chain of 5 rods by Lagrange, 3100: 11 → 0.85 ms, 23 → 12 s;
# benchmarks/bench_unroll_threshold.py). Beyond it XLA no longer keeps the scalar program in a
# few kernels and its compile time grows faster than the program: the Panda's articulated-body
# algorithm (6908 operations) had not compiled after 7 minutes unrolled (2.8 s as arrays, whose
# 6 × 6 operations are wide enough to amortise their launches).
MAX_ELEMENTS = 4000
# Programs whose arrays hold more elements than this in total (summed over every intermediate,
# before folding) are not tried: the interpreter's Python time (about 1 s per 100 000 elements).
# Spatial (6 × 6) algebra of small trees folds to a small fraction of its size.
MAX_TRIED = 40_000
# Programs analysed for their structure (`structure`), which emits nothing: Python time alone,
# 0.4–0.55 s for the mass matrix of a chain of 20 links by Kane's equations (111 000
# elements; analysed once per system and shapes, `jaxdyn._dynamics._mass_matrix_structure`).
MAX_ANALYSED = 200_000
# Programs differentiated (`jax.jvp`, `jax.grad`) as straight-line code up to this many scalar
# operations; larger ones are differentiated as arrays (see `_straight_line`).
MAX_DIFFERENTIATED = 2000


def structure(fn, *args, tags, max_elements: int | None = None):
    """What is known at trace time about each element of ``fn(*args)``, without evaluating
    it: a NumPy scalar where the element folds to a constant (a structural zero of a mass
    matrix, say), else a `Symbol` naming the inputs it depends on.

    `tags`: one hashable per positional argument (e.g. "t", "q", "u", "p"). Returns the
    output pytree with object arrays as leaves, or None when the program is over budget.
    """
    leaves, treedef = jax.tree_util.tree_flatten(args)
    closed, out_struct = jax.make_jaxpr(
        lambda *xs: fn(*jax.tree_util.tree_unflatten(treedef, xs)), return_shape=True
    )(*leaves)
    leaf_tags = [tag for arg, tag in zip(args, tags) for _ in jax.tree_util.tree_leaves(arg)]
    jaxpr = _dead_code_eliminated(closed.jaxpr)
    if _size(jaxpr) > (MAX_ANALYSED if max_elements is None else max_elements):
        return None
    inputs = [_symbols_like(leaf, tag) for leaf, tag in zip(leaves, leaf_tags)]
    consts = [c if _is_concrete(c) else _symbols_like(c, "const") for c in closed.consts]
    token = _ANALYSIS.set(True)
    try:
        outs = _eval(jaxpr, consts, inputs)
    finally:
        _ANALYSIS.reset(token)
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_struct), outs)


def _symbols_like(x, tag):
    return _filled(np.shape(x), Symbol(frozenset([tag])))


def unrolled(fn, *args, otherwise=None, max_elements: int | None = None,
             chunked: bool = False):
    """``fn(*args)`` evaluated as straight-line scalar code, or ``otherwise(*args)`` (by
    default ``fn(*args)`` as written) when the program is too large, or at once with
    `max_elements` 0; with `chunked`, that array program runs in chunks of a few states
    under `jax.vmap` (`jaxdyn._chunking`).

    Derivatives (`jax.jvp`, and so `jax.grad` through a solve) are those of ``fn``'s program
    written as straight-line code only while that is small (`MAX_DIFFERENTIATED`), else of
    the same program run on arrays: see `_straight_line`.

    `args` are pytrees of arrays; the result has the structure of ``fn(*args)``.
    """
    leaves, treedef = jax.tree_util.tree_flatten(args)
    limit = MAX_ELEMENTS if max_elements is None else max_elements
    array_program = fn if otherwise is None else otherwise
    if chunked:
        array_program = chunked_vmap(array_program)
    try:
        if limit <= 0:  # no attempt: not even the trace that would find it too large
            raise _Fallback
        closed, out_struct = _traced(fn, leaves, treedef, limit)
        out_leaves, out_treedef = jax.tree_util.tree_flatten(out_struct)
        outs = _straight_line(closed, leaves, limit, [s.dtype for s in out_leaves],
                              array_program if otherwise is not None else None, treedef)
    except _Fallback:
        return array_program(*args)
    return jax.tree_util.tree_unflatten(out_treedef, outs)


def _straight_line(closed, leaves, limit, dtypes, array_program, treedef):
    """The outputs of the closed jaxpr on `leaves` as straight-line code (raising `_Fallback`
    when it emits more than `limit` operations), whose derivative (`jax.jvp`, and so
    `jax.grad` through a solve) is that of the straight-line code only up to
    `MAX_DIFFERENTIATED` operations, and beyond it that of `array_program` (a function of the
    arguments' pytree `treedef`), or of the jaxpr run on arrays where none is given.

    Why: JAX differentiates a program one operation at a time in Python, and XLA compiles the
    result; a program of thousands of scalar operations becomes tens of thousands once
    linearised and transposed. Reverse mode through a solve of a chain of 10 rods (2862
    operations) spent 18 s tracing and 37 s compiling that way; with its array program's
    derivative, 5 s and 8 s, and the gradient runs as fast (its backward pass is dominated by
    the checkpointed re-solve, not by the vector field). Small programs keep the
    straight-line derivative, which is what makes them fast inside a sensitivity solve.

    Everything a derivative may reach is an explicit input of a `jax.custom_jvp`: the traced
    leaves, the traced constants of the jaxpr (values closed over) and the arrays of
    `array_program`. Concrete leaves and constants stay closed over, so that they still fold
    at trace time. Where the jaxpr closes over traced values that `array_program` does not hold
    as arrays (a user's function closing over a traced value), the jaxpr itself is the array
    program.
    """
    traced = [i for i, c in enumerate(closed.consts) if not _is_concrete(c)]
    inputs = [i for i, x in enumerate(leaves) if not _is_concrete(x)]
    program_arrays, program_rest = eqx.partition(array_program, eqx.is_array)
    held = {id(x) for x in jax.tree_util.tree_leaves(program_arrays)}
    if any(id(closed.consts[i]) not in held for i in traced):
        array_program, program_arrays = None, None

    def complete(consts, xs):
        full_consts, full_leaves = list(closed.consts), list(leaves)
        for i, c in zip(traced, consts):
            full_consts[i] = c
        for i, x in zip(inputs, xs):
            full_leaves[i] = x
        return jex.ClosedJaxpr(closed.jaxpr, full_consts), full_leaves

    def evaluated(consts, xs, budget):
        program, full_leaves = complete(consts, xs)
        outs = evaluate(program, full_leaves, budget)
        return [assemble(o, d) for o, d in zip(outs, dtypes)]

    size = []  # the written-out program's operations, counted when first differentiated

    def operations():
        # (a count, emitting nothing: an attempt at writing out up to MAX_DIFFERENTIATED
        # operations would leave those it emitted before giving up in the derivative's trace)
        if not size:
            size.append(evaluate(closed, leaves, limit, emit=False))
        return size[0]

    # Where the derivative is the array program's, the values come from two programs, which
    # must agree on where a `vmap` puts its batch axis (`jaxdyn._custom_jvp`).
    # (the name marks it, for `_unroll_rules._is_straight_line`)
    @jax.custom_jvp
    def jaxdyn_straight_line(consts, xs, arrays):
        return batch_axis_first(evaluated(consts, xs, limit))

    @jaxdyn_straight_line.defjvp
    def derivative(primals, tangents):
        def differentiable(consts, xs, arrays):
            if operations() <= MAX_DIFFERENTIATED:
                return evaluated(consts, xs, limit)
            program, full_leaves = complete(consts, xs)
            if array_program is None:
                return jex.jaxpr_as_fun(program)(*full_leaves)
            fn = eqx.combine(arrays, program_rest)
            return jax.tree_util.tree_leaves(
                fn(*jax.tree_util.tree_unflatten(treedef, full_leaves)))

        return batch_axis_first(jax.jvp(differentiable, primals, tangents))

    return jaxdyn_straight_line([closed.consts[i] for i in traced],
                                [leaves[i] for i in inputs], program_arrays)


def straight_line_size(fn, *args, max_elements: int | None = None) -> int | None:
    """The number of scalar operations `unrolled(fn, *args)` would emit, or None when it
    would evaluate ``fn`` as written (too large for straight-line code)."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    limit = MAX_ELEMENTS if max_elements is None else max_elements
    try:
        closed, _ = _traced(fn, leaves, treedef, limit)
        return evaluate(closed, leaves, limit, emit=False)
    except _Fallback:
        return None


_ATTEMPT = contextvars.ContextVar("jaxdyn_unroll_attempt", default=None)


def give_up_beyond(count: int):
    """Inside the trace of an attempt at straight-line code (`unrolled`, `fits`): give up at
    once if the program will emit at least `count` operations, more than the attempt allows,
    rather than trace them (writing out an LDLᵀ factorisation of 50 speeds traces ~20 000
    operations in Python, seconds, to find that they do not fit). Outside an attempt: nothing.
    """
    limit = _ATTEMPT.get()
    if limit is not None and count > limit:
        raise _Fallback


def give_up_beyond_program(fn, *args):
    """Inside the trace of an attempt at straight-line code: give up at once if the program
    ``fn(*args)`` (a jitted function whose trace JAX caches, so that asking costs little)
    already holds more elements than an attempt tries (`MAX_TRIED`), before the rest of the
    attempt is traced (a chain of 20 links by Kane's equations: M and f alone hold 111 000,
    and writing out their LDLᵀ solve after them took 0.4 s of its first `simulate`).
    Outside an attempt: nothing."""
    limit = _ATTEMPT.get()
    if limit is None:
        return
    closed = eqx.filter_make_jaxpr(fn)(*args)[0]
    if _size(_dead_code_eliminated(closed.jaxpr)) > max(MAX_TRIED, limit):
        raise _Fallback


def _traced(fn, leaves, treedef, limit):
    """(closed jaxpr, output shapes) of ``fn`` on the leaves' structure. A program that is one
    call of a jitted function is its callee: `fn` can then be a `jax.jit` (or
    `eqx.filter_jit`) whose trace JAX caches, so that several analyses of the same equations
    (does it fit, evaluate it) trace the user's functions once."""
    token = _ATTEMPT.set(limit)
    try:
        closed, out_struct = jax.make_jaxpr(
            lambda *xs: fn(*jax.tree_util.tree_unflatten(treedef, xs)), return_shape=True
        )(*leaves)
    finally:
        _ATTEMPT.reset(token)
    jaxpr = closed.jaxpr
    if len(jaxpr.eqns) == 1:
        sub = _inline_jaxpr(jaxpr.eqns[0])
        if (sub is not None and list(jaxpr.eqns[0].invars) == list(jaxpr.invars)
                and list(jaxpr.eqns[0].outvars) == list(jaxpr.outvars)):
            closed = sub
    return closed, out_struct


@overload
def evaluate(closed: jex.ClosedJaxpr, leaves, max_elements: int,
             emit: Literal[True] = True) -> list[np.ndarray]: ...


@overload
def evaluate(closed: jex.ClosedJaxpr, leaves, max_elements: int,
             emit: Literal[False]) -> int: ...


def evaluate(closed: jex.ClosedJaxpr, leaves, max_elements: int, emit: bool = True):
    """Evaluate a closed jaxpr element by element; returns object arrays of scalars, or with
    `emit=False` only the number of operations it would emit.

    Each element is a NumPy scalar (a constant known at trace time) or a 0-d JAX value. Raises
    `_Fallback` when the program has side effects, is too large to try, or emits more than
    `max_elements` operations.
    """
    jaxpr = _dead_code_eliminated(closed.jaxpr)
    if jaxpr.effects or _size(jaxpr) > max(MAX_TRIED, max_elements):
        raise _Fallback
    remaining = [max_elements]
    budget = _BUDGET.set(remaining)
    numbering = _NUMBERING.set({})
    analysis = _ANALYSIS.set(True) if not emit else None
    try:
        if not emit:  # only the count is wanted: inputs and traced constants as symbols
            leaves = [_symbols_like(x, "input") for x in leaves]  # as if traced
            # (a traced constant may belong to a trace that has ended, or to an outer one,
            # such as an input closed over under `jax.jacfwd`: nothing may touch it)
            consts = [c if _is_concrete(c) else _symbols_like(c, "const")
                      for c in closed.consts]
            _eval(jaxpr, consts, [split(x) for x in leaves])
            return max_elements - remaining[0]
        return _eval(jaxpr, closed.consts, [split(x) for x in leaves])
    finally:
        _BUDGET.reset(budget)
        _NUMBERING.reset(numbering)
        if analysis is not None:
            _ANALYSIS.reset(analysis)


def _dead_code_eliminated(jaxpr):
    """Drop equations whose outputs are never used (linearisations compute unused primals)."""
    live = {v for v in jaxpr.outvars if isinstance(v, jex.Var)}
    kept = []
    for eqn in reversed(jaxpr.eqns):
        if eqn.effects or any(v in live for v in eqn.outvars):
            kept.append(eqn)
            live.update(v for v in eqn.invars if isinstance(v, jex.Var))
    return jaxpr.replace(eqns=list(reversed(kept)))


def _size(jaxpr) -> int:
    """Elements produced by the program: the unrolled program's size, and its Python cost."""
    total = 0
    for eqn in jaxpr.eqns:
        sub = _inline_jaxpr(eqn)
        if sub is not None:
            total += _size(sub.jaxpr)
            continue
        for v in eqn.outvars:
            total += math.prod(v.aval.shape) if hasattr(v.aval, "shape") else 1
        if eqn.primitive.name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += math.prod(v.aval.shape) * math.prod(lhs[d] for d in contract)
    return total


def depends(fn, *args, tags) -> frozenset:
    """The tags of the positional arguments that ``fn(*args)`` depends on, from the data flow
    of its program (whole arrays, not elements: cheap for programs of any size). Calls are
    followed into; other structured primitives (loops, custom derivatives) are taken to make
    every output depend on every input. `tags` as for `structure`."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    closed = jax.make_jaxpr(lambda *xs: fn(*jax.tree_util.tree_unflatten(treedef, xs)))(*leaves)
    leaf_tags = [frozenset([tag]) for arg, tag in zip(args, tags)
                 for _ in jax.tree_util.tree_leaves(arg)]
    return frozenset().union(*_flow(closed.jaxpr, leaf_tags))


def _flow(jaxpr, inputs):
    env = dict(zip(jaxpr.invars, inputs))

    def read(v):
        return env.get(v, frozenset()) if isinstance(v, jex.Var) else frozenset()

    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        sub = _inline_jaxpr(eqn)
        if sub is not None:
            outs = _flow(sub.jaxpr, ins)
        else:
            outs = [frozenset().union(*ins)] * len(eqn.outvars)
        env.update(zip(eqn.outvars, outs))
    return [read(v) for v in jaxpr.outvars]
