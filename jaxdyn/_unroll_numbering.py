"""Value numbering for the straight-line evaluation (`jaxdyn._unroll_rules`): an operation whose
result is already at hand within one evaluation is not emitted again.

Two kinds of sameness are recognised.

- **Syntactic**: the same operation on the same elements (and, for +, ·, in either order).
  Autodiff forms the same products again and again (sin θ, cos θ and their products in every
  entry of Lagrange's M and f): of the operations a chain of two rods writes out, 46% by
  Lagrange's equations, 60% by Kane's and 33% by Gibbs–Appell's were repeats.
- **Semantic**: a different expression of the same function. How a user writes T decides
  the program autodiff forms: the double pendulum with T = ½(m₁|v₁|² + m₂|v₂|²) and
  vᵢ = lᵢθ̇ᵢ(cos θᵢ, sin θᵢ) forms cos²θ + sin²θ where T as the textbook writes it has 1, and
  cos θ₁ sin θ₂ − sin θ₁ cos θ₂ twice over. Each element that analytic operations form from
  the inputs is evaluated alongside at a few random points (NumPy, in float64), with a
  first-order bound on the rounding of each value. An element whose values are one constant
  at every point, within 16 times their rounding bounds, is that constant; one whose values
  are another element's (or their negatives) is that element; a sum whose values are a factor
  of its terms times a constant or another element is that product. This is randomised
  identity testing (Schwartz 1980, Zippel 1979): a non-constant analytic function agrees with
  a constant, or with another function, at a handful of random points with probability zero,
  and the tolerance is the values' rounding, not a relative threshold, so that an expression
  that varies by more than its rounding is never taken for another. Where the points cannot
  show a term (a sum with a term below the other's rounding at every point, values whose
  rounding is no longer small because a random pivot was tiny), the result is not followed.
  Only operations analytic wherever they are defined are followed (+, −, ·, ÷, integer
  powers, sin, cos, tan, exp, the hyperbolic functions): an identity they satisfy on an open
  set of points holds at every point where both sides are defined (the identity theorem).
  The result of any other
  operation (a comparison, a selection, √, log, a whole-array primitive) and every input is
  an independent variable, with values of its own: what holds for every value of an
  independent variable holds for its actual value.

Each operation emitted is a JAX primitive of the original program's kind; where an identity
replaces an expression, the value it gives differs from the original by rounding (1 − (cos²θ +
sin²θ) is 0 here and ±1 ulp there), and its derivatives are those of the same function.
"""

import contextvars
import math

import numpy as np

# The table of one evaluation: (operation, its elements) -> (elements, result), which keeps
# the elements alive, so that the identity of an element is not reused while the table holds
# it. Set by `jaxdyn._unroll.evaluate` around an evaluation that emits operations.
_NUMBERING: contextvars.ContextVar[dict | None] = contextvars.ContextVar(
    "jaxdyn_unroll_numbering", default=None)
_COMMUTATIVE = {"add", "add_any", "mul"}  # exactly, in IEEE arithmetic
_SAMPLES = "samples"  # (the key of the evaluation's `_Samples` in its table)
_NEGATIONS = "negations"  # (and of its negations: id(−x) -> (−x, x))
_PRODUCTS = "products"  # (and of its products: id(x·y) -> (x·y, (x, y)))


def _element_key(x):
    # a constant by its value, bit for bit (0.0 and -0.0 differ); an element by its identity
    return (x.dtype, x.tobytes()) if isinstance(x, np.generic) else id(x)


def numbered(operation, xs, extra, make, *, negate, multiply):
    """`make()`, the operation `operation` (a name or a function) on the elements `xs` with the
    hashable `extra`, or an element of this evaluation equal to it: the same operation on the
    same elements; a constant; another element or its negation (`negate(x)`); for a sum, the
    product (`multiply(x, y)`) of a factor of its terms and a constant or another element."""
    table = _NUMBERING.get()
    if table is None:
        return make()
    elements = tuple(_element_key(x) for x in xs)
    if operation in _COMMUTATIVE:
        elements = tuple(sorted(elements, key=repr))
    key = (operation, elements, extra)
    try:
        hit = table.get(key)
    except TypeError:  # parameters that cannot be hashed: not numbered
        return make()
    if hit is not None:
        return hit[1]
    samples = table.get(_SAMPLES)
    if samples is None:
        samples = table[_SAMPLES] = _Samples()
    values = samples.of_operation(operation, xs, extra)
    if values is not None:
        # (a negation is never answered by a negation: that would be itself)
        same = samples.equal(*values, negated=operation != "neg")
        if same is not None:
            element, negated = same
            return negate(element) if negated else element
        if operation in ("add", "add_any", "sub"):
            # A sum of products whose terms share a factor x and whose rest is an element
            # already at hand or a constant: (m₁ + m₂)l₁ · l₁ for (m₁ + m₂)l₁² (cos²θ + sin²θ)
            # written as four products.
            dtype, at_points, bounds = values
            factored = samples.factored(dtype, at_points, bounds, _factors(table, xs))
            if factored is not None:
                return multiply(*factored)
    out = make()
    if values is not None:
        samples.remember(out, *values)
    if operation == "neg":
        table.setdefault(_NEGATIONS, {})[id(out)] = (out, xs[0])
    elif operation == "mul":
        table.setdefault(_PRODUCTS, {})[id(out)] = (out, xs)
    table[key] = (xs, out)
    return out


def _factors(table, xs, depth=3):
    """The factors of the products (through negations) that make up the elements `xs`, to
    `depth` levels."""
    products = table.get(_PRODUCTS, {})
    negations = table.get(_NEGATIONS, {})
    found: dict = {}
    frontier = list(xs)
    for _ in range(depth):
        deeper = []
        for x in frontier:
            if isinstance(x, np.generic):
                continue
            if id(x) in negations:
                deeper.append(negations[id(x)][1])
                continue
            product = products.get(id(x))
            if product is not None:
                for f in product[1]:
                    if not isinstance(f, np.generic):
                        found[id(f)] = f
                        deeper.append(f)
        frontier = deeper
    return list(found.values())


def negation_of(x):
    """x' where the element `x` is −x' emitted in this evaluation, else None."""
    table = _NUMBERING.get()
    if table is None or isinstance(x, np.generic):
        return None
    found = table.get(_NEGATIONS, {}).get(id(x))
    return None if found is None else found[1]


# The analytic operations followed: name -> (value, |derivative| of a unary one) on samples.
_UNARY = {
    "neg": (np.negative, lambda x, v: np.ones_like(x)),
    "sin": (np.sin, lambda x, v: np.abs(np.cos(x))),
    "cos": (np.cos, lambda x, v: np.abs(np.sin(x))),
    "tan": (np.tan, lambda x, v: 1 + v * v),
    "exp": (np.exp, lambda x, v: np.abs(v)),
    "expm1": (np.expm1, lambda x, v: np.abs(v + 1)),
    "sinh": (np.sinh, lambda x, v: np.cosh(x)),
    "cosh": (np.cosh, lambda x, v: np.abs(np.sinh(x))),
    "tanh": (np.tanh, lambda x, v: 1 - v * v),
    "square": (np.square, lambda x, v: 2 * np.abs(x)),
}
_BINARY = {"add", "add_any", "sub", "mul", "div"}
# Points per element: a false identity needs every one of them to agree within rounding.
_POINTS = 6
# Values agree within this many times their rounding bounds.
_SLACK = 16.0
_EPS = float(np.finfo(np.float64).eps)
# A term of a sum this small beside the sum's terms at every point is not seen in its values.
_SEEN = 1e-6
# Values are followed while their rounding bounds stay below this (inputs are drawn from
# [−2, 2]: the equations of a system stay far below it unless a random pivot is tiny).
_ROUNDED = 1e-8


class _Samples:
    """The values of an evaluation's elements at `_POINTS` random points, each with a bound
    on its rounding error; elements never seen are independent variables."""

    def __init__(self):
        # a fixed seed: the same program is written out the same way at every trace
        self.random = np.random.default_rng(0)
        self.values: dict = {}  # id(element) -> (element, values, bounds)
        self.by_value: dict = {}  # (dtype, the first values, rounded) -> [element]

    def of(self, x):
        """(values, rounding bounds) of an element, or None when it is not a real float."""
        if isinstance(x, np.generic):
            if not np.issubdtype(x.dtype, np.floating):
                return None
            return np.full(_POINTS, float(x)), np.zeros(_POINTS)
        known = self.values.get(id(x))
        if known is not None:
            return known[1], known[2]
        dtype = getattr(x, "dtype", None)
        if dtype is None or not np.issubdtype(dtype, np.floating) or np.ndim(x) != 0:
            return None
        # an input, or an operation not followed: an independent variable
        values = self.random.uniform(-2.0, 2.0, _POINTS)
        self.values[id(x)] = (x, values, np.zeros(_POINTS))
        return values, self.values[id(x)][2]

    def of_operation(self, operation, xs, extra):
        """(dtype, values, bounds) of the operation's result, or None when it is not followed
        (not analytic, not on real floats, or not finite at the points)."""
        if not isinstance(operation, str) or not (operation in _BINARY or operation in _UNARY
                                                  or operation == "integer_pow"):
            return None
        dtypes = {x.dtype for x in xs if not isinstance(x, np.generic)}
        if len(dtypes) != 1:
            return None
        (dtype,) = dtypes
        operands = []
        for x in xs:
            known = self.of(x)
            if known is None:
                return None
            operands.append(known)
        with np.errstate(all="ignore"):
            if operation in _BINARY:
                (a, da), (b, db) = operands
                if operation in ("add", "add_any", "sub"):
                    v = a + b if operation != "sub" else a - b
                    bound = da + db
                    # A term below the other's rounding at every point is not seen in the
                    # sum's values there (2·10¹³ + x at points where a random pivot was
                    # tiny), though it may not be at the actual point: such a sum is not
                    # followed, nor is what is formed from it.
                    scale = np.abs(a) + np.abs(b)
                    if any(not isinstance(x, np.generic) and np.all(np.abs(o) <= _SEEN * scale)
                           for x, o in zip(xs, (a, b))):
                        return None
                elif operation == "mul":
                    v = a * b
                    bound = np.abs(b) * da + np.abs(a) * db
                else:
                    v = a / b
                    bound = (da + np.abs(v) * db) / np.abs(b)
            elif operation == "integer_pow":
                (a, da), = operands
                y = dict(extra[1])["y"]
                v = a ** y
                bound = np.abs(y * a ** (y - 1)) * da
            else:
                (a, da), = operands
                value, slope = _UNARY[operation]
                v = value(a)
                bound = slope(a, v) * da
            bound = bound + 2 * _EPS * np.abs(v)  # the operation's own rounding, ≤ 1 ulp
        # (and values whose rounding is no longer small at the points, where the relation
        # between their terms says little about the relation at other points)
        if not (np.all(np.isfinite(v)) and np.all(bound <= _ROUNDED)):
            return None
        return dtype, v, bound

    def equal(self, dtype, values, bounds, negated=True):
        """(an element, whether negated) or (a constant, False) equal to the values, or
        None; an element's negative only if `negated`."""
        tolerance = _SLACK * bounds
        # A constant: the value with the least rounding, an integer where it is within it.
        best = values[np.argmin(bounds)]
        if np.all(np.abs(values - best) <= tolerance + _SLACK * bounds.min()):
            whole = float(np.round(best))
            constant = whole if np.all(np.abs(values - whole) <= tolerance) else best
            return np.asarray(constant, dtype)[()], False
        for sign in (1.0, -1.0) if negated else (1.0,):
            for element in self.by_value.get(self._key(dtype, sign * values), ()):
                _, other, other_bounds = self.values[id(element)]
                if np.all(np.abs(sign * values - other) <= tolerance + _SLACK * other_bounds):
                    return element, sign < 0
        return None

    def factored(self, dtype, values, bounds, factors):
        """(x, y): one of `factors` and an element or a constant whose product has these
        values, or None."""
        for x in factors:
            known = self.values.get(id(x))
            if known is None or getattr(x, "dtype", None) != dtype:
                continue
            _, xv, xb = known
            if np.any(np.abs(xv) < 1e-3):  # (a quotient's rounding bound would be loose)
                continue
            with np.errstate(all="ignore"):
                ratio = values / xv
                rb = (bounds + np.abs(ratio) * xb) / np.abs(xv)
            same = self.equal(dtype, ratio, rb, negated=False)
            if same is not None and same[0] is not x:
                return x, same[0]
        return None

    def remember(self, element, dtype, values, bounds):
        if np.ndim(element) != 0 or getattr(element, "dtype", None) != dtype:
            return
        self.values[id(element)] = (element, values, bounds)
        self.by_value.setdefault(self._key(dtype, values), []).append(element)

    @staticmethod
    def _key(dtype, values):
        # the first two values to 8 significant digits: elements that agree to rounding share
        # the key unless a value sits on a rounding boundary (an identity then missed)
        return (dtype, *(_significant(v) for v in values[:2]))


def _significant(value: float) -> float:
    if value == 0 or not math.isfinite(value):
        return value
    return round(value, 7 - int(math.floor(math.log10(abs(value)))))
