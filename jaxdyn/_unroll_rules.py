"""The element-wise interpreter behind `jaxdyn._unroll`: each equation of a jaxpr evaluated one
array element at a time, with the algebra that folds and simplifies it at trace time.

`jaxdyn._unroll` decides whether a program is written out as straight-line code, within which
budget, and how it is differentiated; this module is how one equation becomes scalars, kept
apart so that the rules per primitive can grow without the entry points. An element is a NumPy
scalar (a constant known at trace time), a 0-d JAX value (an emitted scalar operation) or, in a
structure analysis, a `Symbol`. Element-wise primitives fold and simplify (the symbolic-zero
identities of autodiff); data movement, contractions, reductions and static indexing have rules
that rename or combine elements (`_STRUCTURAL`); an operation is emitted once, and not at all
where it equals an element at hand (`jaxdyn._unroll_numbering`), and signs are carried
outwards to the sums they meet (`_signs_absorbed`); any other primitive runs on whole arrays
assembled from its elements (`_on_arrays`). The budget and the analysis switch are context
variables that `jaxdyn._unroll` sets around an evaluation. Nothing here imports
`jaxdyn._unroll`: the dependency runs one way.
"""

import contextvars
import math
from typing import TypeGuard, cast

import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex

from ._state import transferred
from ._unroll_numbering import negation_of
from ._unroll_numbering import numbered as _numbered
from ._unroll_positions import POSITIONS, scatter_targets

_EXACT = {  # element-wise primitives that NumPy evaluates exactly as XLA does (IEEE)
    "add": np.add, "add_any": np.add, "sub": np.subtract, "mul": np.multiply,
    "neg": np.negative, "max": np.maximum, "min": np.minimum, "abs": np.abs,
    "eq": np.equal, "ne": np.not_equal, "lt": np.less, "le": np.less_equal,
    "gt": np.greater, "ge": np.greater_equal, "and": np.bitwise_and, "or": np.bitwise_or,
    "not": np.invert, "xor": np.bitwise_xor, "square": np.square, "floor": np.floor,
    "ceil": np.ceil, "sign": np.sign, "copy": lambda x: x, "copy_p": lambda x: x,
}
# Correctly rounded in IEEE arithmetic on real floating-point operands, as XLA computes them
# (integer division truncates in XLA, not in NumPy).
_EXACT_INEXACT = {"div": np.divide, "sqrt": np.sqrt}
_ELEMENTWISE = set(_EXACT) | {
    "div", "sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh", "tanh",
    "asinh", "acosh", "atanh", "exp", "exp2", "log", "log1p", "expm1", "sqrt", "rsqrt", "cbrt",
    "pow", "integer_pow", "logistic", "erf", "erfc", "erf_inv", "lgamma", "digamma", "rem",
    "round", "is_finite", "nextafter", "select_n", "convert_element_type", "clamp",
    "stop_gradient", "reduce_precision", "imag", "real", "conj", "population_count",
    "shift_left", "shift_right_logical", "shift_right_arithmetic",
}
_INLINE = {"jit", "pjit", "closed_call", "core_call", "remat", "checkpoint"}


class _Fallback(Exception):
    """This program is not unrolled (too large, or with side effects)."""


class Symbol:
    """An element of a structure analysis: not a constant, depending on the inputs tagged
    `depends` (see `structure`)."""

    __slots__ = ("depends",)

    def __init__(self, depends: frozenset):
        self.depends = depends


_ANALYSIS = contextvars.ContextVar("jaxdyn_structure_analysis", default=False)


_BUDGET: contextvars.ContextVar[list[int] | None] = contextvars.ContextVar(
    "jaxdyn_unroll_budget", default=None)


def _spend(count):
    """Count `count` emitted scalar operations against the budget of `evaluate`."""
    budget = _BUDGET.get()
    if budget is not None:
        budget[0] -= count
        if budget[0] < 0:
            raise _Fallback


def numbered(operation, xs, extra, make):
    """`make()`, the operation `operation` (a name or a function) on the elements `xs` with the
    hashable `extra`, or an element of this evaluation equal to it (`jaxdyn._unroll_numbering`);
    counted against the budget either way, so that the bounds on what is written out
    (`jaxdyn._unroll.MAX_ELEMENTS`, `MAX_DIFFERENTIATED`, the emitters' choice) choose as they
    were measured to."""
    _spend(1)
    if _ANALYSIS.get():  # (a structure analysis emits nothing)
        return make()
    return _numbered(operation, xs, extra, make, negate=_negate, multiply=_mul)


def _emit(primitive, xs, dtypes, params):
    """Bind `primitive` on elements, or (in a structure analysis) the symbol it would give."""
    def make():
        if _ANALYSIS.get():
            return Symbol(frozenset().union(*(x.depends for x in xs
                                              if isinstance(x, Symbol))))
        return primitive.bind(*[_lift(x, d) for x, d in zip(xs, dtypes)], **params)
    return numbered(primitive.name, xs, (tuple(dtypes), tuple(sorted(params.items()))), make)


def split(x) -> np.ndarray:
    """An array as an object array of its elements (NumPy scalars if x is a constant)."""
    if isinstance(x, np.ndarray) and x.dtype == object:
        return x
    if not isinstance(x, jax.Array) or _is_concrete(x):
        x = np.asarray(x)
        out = np.empty(x.shape, dtype=object)
        for index in np.ndindex(x.shape):
            out[index] = x[index]
        return out
    out = np.empty(x.shape, dtype=object)
    if x.ndim == 0:
        out[()] = x
    else:
        flat = x.reshape(-1)
        for k, index in enumerate(np.ndindex(x.shape)):
            out[index] = flat[k]
    return out


def assemble(elements: np.ndarray, dtype) -> jax.Array:
    """The array whose elements are `elements` (constants and 0-d JAX values)."""
    if elements.size == 0:
        return jnp.zeros(elements.shape, dtype)
    flat = [_lift(e, dtype) for e in elements.ravel()]
    if elements.ndim == 0:
        return flat[0]
    return jnp.stack(flat).reshape(elements.shape)


def is_constant(element) -> TypeGuard[np.generic]:
    """True if an element is known at trace time."""
    return isinstance(element, np.generic)


# -- the interpreter ----------------------------------------------------------------------------


def _is_concrete(x):
    return not isinstance(x, jax.core.Tracer)


def _lift(element, dtype):
    if is_constant(element):
        return jnp.asarray(element, dtype)
    return element


def _constant(value, dtype):
    return np.asarray(value, dtype)[()]


def _inline_jaxpr(eqn):
    if eqn.primitive.name == "custom_jvp_call" and _is_straight_line(eqn.params["call_jaxpr"]):
        # straight-line code of `unrolled` within a program written out again: its
        # elements, whose derivative the outer program's rule then gives
        return eqn.params["call_jaxpr"]
    if eqn.primitive.name in _INLINE:
        sub = eqn.params.get("jaxpr")
        if isinstance(sub, jex.ClosedJaxpr):
            return sub
        if isinstance(sub, jex.Jaxpr):
            return jex.ClosedJaxpr(sub, ())
    return None


def _is_straight_line(closed) -> bool:
    """Whether a custom_jvp_call's function is `jaxdyn._unroll._straight_line`'s (which
    names it so)."""
    info = getattr(closed.jaxpr, "debug_info", None)
    return "jaxdyn_straight_line" in str(getattr(info, "func_src_info", ""))


def _eval(jaxpr, consts, args) -> list[np.ndarray]:
    env = {}

    def read(v):
        if isinstance(v, jex.Literal):
            # A literal's abstract value is a ShapedArray (declared as any AbstractValue); the
            # cast names its type as a string, which costs no attribute look-up here.
            return split(np.asarray(v.val, cast("jax.core.ShapedArray", v.aval).dtype))
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = split(c)
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        outs = _apply(eqn, ins)
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _apply(eqn, ins):
    name = eqn.primitive.name
    params = eqn.params
    sub = _inline_jaxpr(eqn)
    if sub is not None:
        return _eval(sub.jaxpr, sub.consts, ins)
    if name in _ELEMENTWISE:
        return [_elementwise(eqn, ins)]
    rule = _STRUCTURAL.get(name)
    if rule is not None:
        result = rule(eqn, ins)
        if result is not None:
            return [result] if not eqn.primitive.multiple_results else list(result)
    if name == "cond" and all(is_constant(e) for e in ins[0].ravel()):
        branch = params["branches"][int(ins[0][()])]
        return _eval(branch.jaxpr, branch.consts, ins[1:])
    return _on_arrays(eqn, ins)


def _on_arrays(eqn, ins):
    """Evaluate one equation on whole arrays (no element-wise rule)."""
    _spend(sum(math.prod(v.aval.shape) for v in eqn.outvars))
    if _ANALYSIS.get():  # every output element may depend on every input element
        depends = frozenset().union(*(e.depends for x in ins for e in x.ravel()
                                      if isinstance(e, Symbol)))
        return [_filled(v.aval.shape, Symbol(depends)) for v in eqn.outvars]
    arrays = [assemble(x, v.aval.dtype) for x, v in zip(ins, eqn.invars)]
    # (bind parameters, not the equation's: a custom_jvp_call binds its functions, for one)
    outs = eqn.primitive.bind(*arrays, **eqn.primitive.get_bind_params(eqn.params))
    outs = outs if eqn.primitive.multiple_results else [outs]
    return [split(o) for o in outs]


def _filled(shape, element):
    out = np.empty(shape, dtype=object)
    for index in np.ndindex(shape):
        out[index] = element
    return out


def _elementwise(eqn, ins):
    dtypes = [v.aval.dtype for v in eqn.invars]
    out_dtype = eqn.outvars[0].aval.dtype
    name = eqn.primitive.name
    shape = eqn.outvars[0].aval.shape
    ins = [np.broadcast_to(x, shape) for x in ins]
    out = np.empty(shape, dtype=object)
    for index in np.ndindex(shape):
        out[index] = _scalar(eqn.primitive, name, eqn.params, [x[index] for x in ins], dtypes,
                             out_dtype)
    return out


def _scalar(primitive, name, params, xs, dtypes, out_dtype):
    if all(is_constant(x) for x in xs):
        return _fold(primitive, name, params, xs, dtypes, out_dtype)
    simpler = _simplify(name, params, xs, out_dtype)
    if simpler is not None:
        return simpler
    if name in _SIGNED and not _ANALYSIS.get():
        unsigned = [negation_of(x) for x in xs]
        if any(x is not None for x in unsigned):
            return _signs_absorbed(
                name, params, xs, unsigned,
                # (the same operation keeps its parameters, such as `mul`'s out_dtype; the
                # sums it becomes, add and sub, have none)
                lambda other, ys: _scalar(_SIGNED[other], other,
                                          params if other == name else {}, ys, dtypes,
                                          out_dtype))
    return _emit(primitive, xs, dtypes, params)


# Operations through which a sign passes: exactly in IEEE arithmetic for +, −, ·, ÷ and powers;
# for the odd and even functions, to the rounding of their implementations at worst.
_SIGNED = {"neg": jax.lax.neg_p, "add": jax.lax.add_p, "add_any": jax.lax.add_p,
           "sub": jax.lax.sub_p, "mul": jax.lax.mul_p, "div": jax.lax.div_p,
           "sin": jax.lax.sin_p, "tan": jax.lax.tan_p, "sinh": jax.lax.sinh_p,
           "tanh": jax.lax.tanh_p, "cos": jax.lax.cos_p, "cosh": jax.lax.cosh_p,
           "integer_pow": jax.lax.integer_pow_p, "square": jax.lax.square_p}
_ODD = {"sin", "tan", "sinh", "tanh"}


def _signs_absorbed(name, params, xs, unsigned, apply):
    """`name` on `xs`, where some of them are negations −x' (`unsigned` holds x' there, else
    None), with the signs carried outwards: (−a)·b = −(a·b), a + (−b) = a − b, sin(−a) =
    −sin a, cos(−a) = cos a, …, so that a sign written by a rotation matrix or a derivative
    costs no operation of its own where it meets a sum, and two signs cancel. `apply(name,
    operands)` applies an operation."""
    plain = [x if u is None else u for x, u in zip(xs, unsigned)]
    negated = [u is not None for u in unsigned]
    if name == "neg":
        return plain[0]
    if name in ("mul", "div"):
        result = apply(name, plain)
        return _negate(result) if negated[0] != negated[1] else result
    if name in ("add", "add_any", "sub"):
        # ±a ± b with a, b the unsigned operands
        (a, b), a_negated = plain, negated[0]
        b_negated = negated[1] != (name == "sub")
        if a_negated and b_negated:
            return _negate(apply("add", [a, b]))
        if a_negated:
            return apply("sub", [b, a])
        return apply("sub" if b_negated else "add", [a, b])
    if name in _ODD:
        return _negate(apply(name, plain))
    if name == "integer_pow" and params["y"] % 2:
        return _negate(apply(name, plain))
    return apply(name, plain)  # even: cos, cosh, squares and even powers


def _fold(primitive, name, params, xs, dtypes, out_dtype):
    """A constant operation, evaluated at trace time."""
    if name in _EXACT:
        # IEEE semantics as XLA would compute them (0·inf = NaN is a result, not a warning).
        with np.errstate(all="ignore"):
            return _constant(_EXACT[name](*xs), out_dtype)
    if name == "convert_element_type":
        return _constant(xs[0], out_dtype)
    if name == "select_n":
        return _constant(xs[1 + int(xs[0])], out_dtype)
    if name == "integer_pow":
        with np.errstate(all="ignore"):
            return _constant(xs[0] ** params["y"], out_dtype)
    if name in _EXACT_INEXACT and np.issubdtype(out_dtype, np.floating):  # (not complex)
        with np.errstate(all="ignore"):
            return _constant(_EXACT_INEXACT[name](*xs), out_dtype)
    with jax.ensure_compile_time_eval():  # (`transferred`: no program to convert operands)
        value = primitive.bind(*[transferred(x, d) for x, d in zip(xs, dtypes)], **params)
    return _constant(np.asarray(value), out_dtype)


def _simplify(name, params, xs, out_dtype):
    """Identities with the constants 0, 1 and −1 (the symbolic-zero rules of autodiff)."""
    def const(x, value):
        return is_constant(x) and x == value

    zero = _constant(0, out_dtype)
    if name in ("add", "add_any"):
        if const(xs[0], 0):
            return xs[1]
        if const(xs[1], 0):
            return xs[0]
    elif name == "sub":
        if const(xs[1], 0):
            return xs[0]
        if const(xs[0], 0):
            return _negate(xs[1])
    elif name == "mul":
        if const(xs[0], 0) or const(xs[1], 0):
            return zero
        if const(xs[0], 1):
            return xs[1]
        if const(xs[1], 1):
            return xs[0]
        if const(xs[0], -1):
            return _negate(xs[1])
        if const(xs[1], -1):
            return _negate(xs[0])
    elif name == "div":
        if const(xs[0], 0):
            return zero
        if const(xs[1], 1):
            return xs[0]
    elif name == "integer_pow":
        if params["y"] == 1:
            return xs[0]
        if params["y"] == 0:
            return _constant(1, out_dtype)
    elif name == "select_n":
        if is_constant(xs[0]):
            return xs[1 + int(xs[0])]
        if all(x is xs[1] for x in xs[2:]):
            return xs[1]
    elif name in ("convert_element_type", "copy", "copy_p"):
        if name != "convert_element_type" or getattr(xs[0], "dtype", None) == out_dtype:
            return xs[0]
    return None


def _negate(x):
    if isinstance(x, Symbol):
        return x
    # (numbered, but not counted: the budgets were measured without it)
    return _numbered("neg", (x,), ((x.dtype,), ()), lambda: jax.lax.neg(x), negate=_negate,
                     multiply=_mul)


# -- data movement and reductions --------------------------------------------------------------
# Each rule takes the equation and its inputs as object arrays; None means "no element-wise
# rule for these inputs", and the equation is evaluated on whole arrays instead.


def _combine(primitive, fold):
    """A binary operation on two elements, folded when both are constants."""
    name = {jax.lax.add: "add", jax.lax.mul: "mul"}.get(primitive, primitive)

    def combine(a, b):
        if is_constant(a) and is_constant(b):
            return _constant(fold(a, b), np.result_type(a, b))

        def make():
            if _ANALYSIS.get():
                return Symbol(frozenset().union(*(x.depends for x in (a, b)
                                                  if isinstance(x, Symbol))))
            dtype = b.dtype if is_constant(a) else a.dtype
            return primitive(_lift(a, dtype), _lift(b, dtype))
        return numbered(name, (a, b), None, make)

    return combine


def _add(a, b):
    if is_constant(a) and a == 0:
        return b
    if is_constant(b) and b == 0:
        return a
    return _combine(jax.lax.add, np.add)(a, b)


def _mul(a, b):
    for x, y in ((a, b), (b, a)):
        if is_constant(x) and x == 0:
            return _constant(0, x.dtype if isinstance(y, Symbol) else np.result_type(x, y.dtype))
        if is_constant(x) and x == 1:
            return y
    return _combine(jax.lax.mul, np.multiply)(a, b)


_max = _combine(jax.lax.max, np.maximum)
_min = _combine(jax.lax.min, np.minimum)


def _sum(values, dtype):
    total = _constant(0, dtype)
    for v in values:
        total = _add(total, v)
    return total


def _dot_general(eqn, ins):
    x, y = ins
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lf = [d for d in range(x.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(y.ndim) if d not in rc and d not in rb]
    xt = np.transpose(x, list(lb) + lf + list(lc))
    yt = np.transpose(y, list(rb) + list(rc) + rf)
    batch = xt.shape[: len(lb)]
    free_x = xt.shape[len(lb): len(lb) + len(lf)]
    free_y = yt.shape[len(rb) + len(rc):]
    k = math.prod(xt.shape[len(lb) + len(lf):])
    xs = xt.reshape(math.prod(batch), math.prod(free_x), k)
    ys = yt.reshape(math.prod(batch), k, math.prod(free_y))
    dtype = eqn.outvars[0].aval.dtype
    out = np.empty((xs.shape[0], xs.shape[1], ys.shape[2]), dtype=object)
    for b, i, j in np.ndindex(out.shape):
        terms = (_mul(_cast(xs[b, i, c], dtype), _cast(ys[b, c, j], dtype)) for c in range(k))
        out[b, i, j] = _sum(terms, dtype)
    return out.reshape(batch + free_x + free_y)


def _cast(element, dtype):
    """An element in `dtype` (dot_general may accumulate in a wider type)."""
    if is_constant(element):
        return _constant(element, dtype)
    if isinstance(element, Symbol):
        return element
    if element.dtype != dtype:
        return jax.lax.convert_element_type(element, dtype)
    return element


def _reduce(combine):
    def rule(eqn, ins):
        (x,) = ins
        axes = eqn.params["axes"]
        kept = [d for d in range(x.ndim) if d not in axes]
        moved = np.transpose(x, kept + list(axes)).reshape([x.shape[d] for d in kept] + [-1])
        out = np.empty(moved.shape[:-1], dtype=object)
        for index in np.ndindex(out.shape):
            values = list(moved[index])
            total = values[0]
            for v in values[1:]:
                total = combine(total, v)
            out[index] = total
        return out

    return rule


def _cumulative(combine):
    def rule(eqn, ins):
        (x,) = ins
        axis, reverse = eqn.params["axis"], eqn.params["reverse"]
        source = np.moveaxis(np.flip(x, axis) if reverse else x, axis, 0)
        out = np.empty(source.shape, dtype=object)
        out[0] = source[0]
        for i in range(1, source.shape[0]):
            for index in np.ndindex(source.shape[1:]):
                out[(i, *index)] = combine(out[(i - 1, *index)], source[(i, *index)])
        out = np.moveaxis(out, 0, axis)
        return np.flip(out, axis) if reverse else out

    return rule


def _broadcast_in_dim(eqn, ins):
    (x,) = ins[:1]
    shape = eqn.params["shape"]
    expanded = [1] * len(shape)
    for i, d in enumerate(eqn.params["broadcast_dimensions"]):
        expanded[d] = x.shape[i]
    return np.broadcast_to(x.reshape(expanded), shape).copy()


def _slice(eqn, ins):
    (x,) = ins
    p = eqn.params
    strides = p["strides"] or (1,) * x.ndim
    return x[tuple(slice(a, b, s) for a, b, s in zip(p["start_indices"], p["limit_indices"],
                                                     strides))]


def _pad(eqn, ins):
    x, value = ins
    config = eqn.params["padding_config"]
    if any(lo < 0 or hi < 0 or inner != 0 for lo, hi, inner in config):
        return None
    out = np.empty(eqn.outvars[0].aval.shape, dtype=object)
    out[...] = value[()]
    out[tuple(slice(lo, lo + s) for s, (lo, _, _) in zip(x.shape, config))] = x
    return out


def _iota(eqn, ins):
    p = eqn.params
    shape, dimension = p["shape"], p["dimension"]
    line = np.arange(shape[dimension], dtype=p["dtype"])
    line = line.reshape([-1 if d == dimension else 1 for d in range(len(shape))])
    return split(np.broadcast_to(line, shape))


def _constant_array(x):
    """An object array of constants as a NumPy array, or None if one element is not known."""
    if not all(is_constant(e) for e in x.ravel()):
        return None
    dtype = x.ravel()[0].dtype if x.size else np.int32
    return np.asarray(x.tolist(), dtype=dtype).reshape(x.shape)


# Data movement with indices known at trace time (static indexing): find where each element
# goes by applying the primitive to the elements' positions, in NumPy for the gathers, slices
# and scatters that indexing produces (`jaxdyn._unroll_positions`: no XLA program compiled
# per indexing pattern), by the primitive itself in the cases left to it.
_MOVED = {"gather": (0,), "dynamic_slice": (0,), "scatter": (0, 2), "dynamic_update_slice": (0, 1)}


def _by_position(eqn, ins):
    moved = _MOVED[eqn.primitive.name]
    pool, arrays = [], []
    for i, x in enumerate(ins):
        if i in moved:
            first = len(pool) + 1  # 0 marks an element filled in (out of bounds)
            pool.extend(x.ravel())
            arrays.append(np.arange(first, first + x.size, dtype=np.int32).reshape(x.shape))
        else:
            constant = _constant_array(x)
            if constant is None:
                return None
            arrays.append(constant)
    rule = POSITIONS.get(eqn.primitive.name)
    target = NotImplemented if rule is None else rule(eqn.params, *arrays)
    if target is NotImplemented:  # a case left to the primitive, run on the positions
        with jax.ensure_compile_time_eval():
            target = np.asarray(eqn.primitive.bind(*map(jnp.asarray, arrays), **eqn.params))
    if target is None or (np.asarray(target) == 0).any():  # out of bounds: the primitive's
        return None  # own semantics
    out = np.empty(target.shape, dtype=object)
    for index in np.ndindex(target.shape):
        out[index] = pool[target[index] - 1]
    return out


def _scatter_add(eqn, ins):
    """operand + Σ updates at their static destinations (`scatter_targets`; the primitive
    on arrays where it leaves the case to XLA)."""
    operand, indices, updates = ins
    index_array = _constant_array(indices)
    if index_array is None:
        return None
    targets = scatter_targets(eqn.params, operand.shape, index_array, updates.shape)
    if targets is None:
        return None
    out = operand.copy()
    for index, target in targets.items():
        if target is not None:
            out[target] = _add(out[target], updates[index])
    return out


_STRUCTURAL = {
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": lambda eqn, ins: ins[0].reshape(eqn.params["new_sizes"]),
    "squeeze": lambda eqn, ins: np.squeeze(ins[0], tuple(eqn.params["dimensions"])),
    "expand_dims": lambda eqn, ins: np.expand_dims(ins[0], eqn.params["dimensions"]),
    "transpose": lambda eqn, ins: np.transpose(ins[0], eqn.params["permutation"]),
    "rev": lambda eqn, ins: np.flip(ins[0], eqn.params["dimensions"]),
    "slice": _slice,
    "pad": _pad,
    "concatenate": lambda eqn, ins: np.concatenate(ins, axis=eqn.params["dimension"]),
    "stack": lambda eqn, ins: np.stack(ins, axis=eqn.params["axis"]),
    "unstack": lambda eqn, ins: [x[i:i + 1].reshape(x.shape[1:]) for x in
                                 [np.moveaxis(ins[0], eqn.params["axis"], 0)]
                                 for i in range(x.shape[0])],
    "split": lambda eqn, ins: np.split(ins[0], np.cumsum(eqn.params["sizes"])[:-1],
                                       axis=eqn.params["axis"]),
    "iota": _iota,
    "dot_general": _dot_general,
    "reduce_sum": _reduce(_add),
    "reduce_max": _reduce(_max),
    "reduce_min": _reduce(_min),
    "reduce_prod": _reduce(_mul),
    "reduce_or": _reduce(_combine(jax.lax.bitwise_or, np.bitwise_or)),
    "reduce_and": _reduce(_combine(jax.lax.bitwise_and, np.bitwise_and)),
    "cumsum": _cumulative(_add),
    "cumprod": _cumulative(_mul),
    "cummax": _cumulative(_max),
    "cummin": _cumulative(_min),
    "gather": _by_position,
    "dynamic_slice": _by_position,
    "scatter": _by_position,
    "dynamic_update_slice": _by_position,
    "scatter_add": _scatter_add,
    "scatter-add": _scatter_add,
}
