"""Straight-line scalar evaluation of traced programs (`jaxdyn._unroll`).

The reference for every unrolled program is JAX's own evaluation of the same function (an
independent code path: XLA on whole arrays). Checked under jit, vmap, grad and jvp, for the
primitives that equations of motion produce, for the fallback of primitives without an
element-wise rule, and for the structure analysis (structural zeros and dependencies)
against systems whose mass-matrix pattern is known by hand.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
from jaxdyn._dynamics import equations_of_motion
from jaxdyn._unroll import Symbol, _dead_code_eliminated, is_constant, structure, unrolled

from helpers import DOUBLE_PENDULUM, ELASTIC_PENDULUM, assert_close, compiles, rod_chain

RNG = np.random.default_rng(0)
X = jnp.asarray(RNG.normal(size=3))
Y = jnp.asarray(RNG.normal(size=3))
A = jnp.asarray(RNG.normal(size=(3, 3)))

PROGRAMS = {
    "cross product": (jnp.cross, (X, Y)),
    "norm": (jnp.linalg.norm, (X,)),
    "matrix-vector product": (lambda a, x: a @ x, (A, X)),
    "einsum": (lambda a, x: jnp.einsum("ij,j,i->", a, x, x), (A, X)),
    "static gather": (lambda x: x[jnp.array([0, 2])] * x[-1], (X,)),
    "scatter set and add": (lambda x: jnp.zeros(4).at[1].set(x[0]).at[2].add(x[1]), (X,)),
    "cumulative sum and product": (lambda x: jnp.cumsum(jnp.sin(x)) * jnp.cumprod(x), (X,)),
    "where": (lambda x: jnp.where(x > 0, x, -x**2), (X,)),
    "reductions": (lambda a: (a.max(axis=0), a.min(), a.prod(axis=1)), (A,)),
    "transcendental": (lambda x: jnp.exp(x) + jnp.arctan2(x, 1.5) + jnp.tanh(x) ** 3, (X,)),
    "hessian": (lambda x: jax.hessian(lambda y: jnp.sum(jnp.sin(y) * y[::-1]))(x), (X,)),
    "vmap over an identity (unit tangents)":
        (lambda x: jax.vmap(lambda v: jax.jvp(jnp.sin, (x,), (v,))[1])(jnp.eye(3)), (X,)),
    "reshape, transpose, concatenate": (lambda a: jnp.concatenate([a.T.reshape(-1), a[0]]), (A,)),
    # no element-wise rule: evaluated on whole arrays
    "linear solve (fallback)": (lambda a, x: jnp.linalg.solve(a @ a.T + jnp.eye(3), x), (A, X)),
    "scan (fallback)": (lambda x: jax.lax.scan(lambda c, y: (c * y + 1.0, c), 0.0, x), (X,)),
}


@pytest.mark.parametrize("name", PROGRAMS)
def test_unrolled_program_equals_jax(name):
    fn, args = PROGRAMS[name]
    expected = fn(*args)
    got = jax.jit(lambda *a: unrolled(fn, *a))(*args)
    jax.tree_util.tree_map(lambda g, e: assert_close(g, e, rtol=1e-14, atol=1e-15), got,
                           expected)


def test_unrolled_program_under_vmap_grad_and_jvp():
    def fn(x):
        return jnp.sum(jnp.cos(x) ** 2 * jnp.cumsum(x))

    xs = jnp.asarray(RNG.normal(size=(5, 3)))
    assert_close(jax.vmap(lambda x: unrolled(fn, x))(xs), jax.vmap(fn)(xs), rtol=1e-14)
    assert_close(jax.grad(lambda x: unrolled(fn, x))(X), jax.grad(fn)(X), rtol=1e-13)
    tangent_unrolled = jax.jvp(lambda x: unrolled(fn, x), (X,), (Y,))[1]
    assert_close(tangent_unrolled, jax.jvp(fn, (X,), (Y,))[1], rtol=1e-13)


def test_constant_folding_leaves_only_the_arithmetic_that_depends_on_inputs():
    # M e_j for unit tangents: the unrolled program multiplies by no zero or one.
    def mass_matrix(qd):
        return jax.jacfwd(jax.grad(lambda v: 0.5 * (2.0 * v[0] ** 2 + 3.0 * v[1] ** 2)))(qd)

    jaxpr = jax.make_jaxpr(lambda qd: unrolled(mass_matrix, qd))(jnp.ones(2))
    multiplications = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "mul"]
    assert not multiplications  # M = diag(2, 3) is known at trace time
    assert_close(jax.jit(lambda qd: unrolled(mass_matrix, qd))(jnp.ones(2)), np.diag([2., 3.]),
                 rtol=0)



@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_folded_divisions_and_square_roots_are_xlas_to_the_bit(dtype):
    """Constants folded at trace time by NumPy (division, square root: correctly rounded in
    IEEE arithmetic) equal what XLA computes for the same operands, zeros, infinities and
    NaN included; an integer division still truncates, as XLA's does. (Not subnormals: XLA's
    CPU kernels flush them to zero, and neither these folds nor the others do.)"""
    values = np.concatenate([RNG.normal(size=200) * 10.0 ** RNG.integers(-15, 15, 200),
                             [0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, np.nan, 3.0]])
    a = jnp.asarray(values.astype(dtype))
    b = jnp.roll(a, 7)
    # (`unrolled` folds operations on the constants it closes over; the reference is XLA's
    # kernels on the same operands)
    folded = jax.jit(lambda: unrolled(lambda: (a / b, jnp.sqrt(a))))()
    xla = jax.jit(lambda a, b: (a / b, jnp.sqrt(a)))(a, b)
    for f, x in zip(folded, xla):
        assert f.dtype == x.dtype == dtype
        assert np.asarray(f).tobytes() == np.asarray(x).tobytes()
    quotient = jax.jit(lambda: unrolled(lambda: jax.lax.div(jnp.asarray([-7, 7]), 2)))()
    assert quotient.tolist() == [-3, 3]


def _repeats(jaxpr):
    """Equations of a jaxpr (its outer level) that repeat an earlier one: the same primitive
    and parameters on the same operands (up to order, for additions and products)."""
    seen, repeats = set(), []
    for eqn in jaxpr.eqns:
        operands = [("literal", v.val.item()) if isinstance(v, jax.extend.core.Literal)
                    else id(v) for v in eqn.invars]
        if eqn.primitive.name in ("add", "add_any", "mul"):
            operands = sorted(operands, key=repr)
        key = (eqn.primitive.name, str(sorted(eqn.params.items())), tuple(operands))
        if key in seen:
            repeats.append(eqn)
        seen.add(key)
    return repeats


def test_written_out_code_holds_each_operation_once():
    """Lagrange's equations of a double pendulum from its T and V repeat the same products in
    every entry of M and f (the derivatives of T): written out, each operation on the same
    operands appears once (value numbering), and the accelerations are the closed form's."""
    dynamics = DOUBLE_PENDULUM.dynamics
    p = DOUBLE_PENDULUM.params
    q, u = jnp.array([0.3, -0.8]), jnp.array([1.1, 0.4])
    fn = lambda q, u: dynamics.form_equations(0.0, q, u, p)  # noqa: E731
    closed = jax.make_jaxpr(lambda q, u: unrolled(fn, q, u))(q, u)
    (straight_line,) = [e.params["call_jaxpr"] for e in closed.jaxpr.eqns
                        if e.primitive.name == "custom_jvp_call"]
    assert len(straight_line.eqns) > 50
    assert not _repeats(straight_line.jaxpr)
    mass_matrix, forcing = jax.jit(lambda q, u: unrolled(fn, q, u))(q, u)
    assert_close(mass_matrix, DOUBLE_PENDULUM.mass_matrix(np.asarray(q), p), rtol=1e-14)
    assert_close(jnp.linalg.solve(mass_matrix, forcing),
                 DOUBLE_PENDULUM.accelerations(np.asarray(q), np.asarray(u), p), rtol=1e-12)


def _live_straight_line(jaxpr):
    """The equations of the straight-line code in a jaxpr (through the calls around it) that
    its outputs need."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "custom_jvp_call":
            return _dead_code_eliminated(eqn.params["call_jaxpr"].jaxpr).eqns
        inner = eqn.params.get("jaxpr")
        if inner is not None:
            found = _live_straight_line(getattr(inner, "jaxpr", inner))
            if found is not None:
                return found
    return None


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_identities_fold_to_their_constants(dtype):
    """Expressions that are constant as functions of the inputs, however written (cos² + sin²,
    a binomial expanded, sin 2θ against 2 sin θ cos θ, cosh² − sinh², a product of negations),
    are written out as their constants, and the same program is written at every trace."""
    def fn(x):
        a, b = x[0], x[1]
        return jnp.stack([jnp.cos(a) ** 2 + jnp.sin(a) ** 2,
                          (a + b) ** 2 - a ** 2 - 2 * a * b - b ** 2,
                          jnp.sin(2 * a) - 2 * jnp.sin(a) * jnp.cos(a),
                          jnp.cosh(b) ** 2 - jnp.sinh(b) ** 2,
                          (-a) * (-b) - a * b])

    x = jnp.asarray([0.7, -1.3], dtype)
    traced = jax.make_jaxpr(lambda x: unrolled(fn, x))(x)
    assert str(jax.make_jaxpr(lambda x: unrolled(fn, x))(x)) == str(traced)
    # nothing left to compute: the outputs are assembled from constants
    assert {e.primitive.name for e in _live_straight_line(traced.jaxpr)} <= {
        "stack", "broadcast_in_dim", "concatenate"}
    got = jax.jit(lambda x: unrolled(fn, x))(x)
    assert got.dtype == dtype
    assert got.tolist() == [1.0, 0.0, 0.0, 1.0, 0.0]
    # JAX's evaluation of the same expressions, rounding and all
    assert_close(got, fn(x), rtol=0, atol=8 * np.finfo(dtype).eps)


def test_nearly_constant_and_piecewise_expressions_are_not_taken_for_identities():
    """What holds only at the random points where identities are tested is not folded: a
    term below a constant's rounding at those points is still computed, a branch the points
    do not reach still taken, and square roots and angles (√x² = |x|, atan2(sin θ, cos θ) = θ
    on (−π, π] only) are never followed."""
    def fn(x):
        a, b = x[0], x[1]
        return jnp.stack([1.0 + 1e-12 * jnp.sin(a),
                          jnp.where(a > 3.0, a, 0.0),
                          jnp.sqrt(b) ** 2 - b,
                          jnp.arctan2(jnp.sin(a), jnp.cos(a)) - a])

    unrolled_fn = jax.jit(lambda x: unrolled(fn, x))
    for x in (jnp.array([5.0, -2.0]), jnp.array([0.3, 4.0])):
        np.testing.assert_allclose(unrolled_fn(x), fn(x), rtol=1e-15, atol=1e-15)
    assert np.isnan(unrolled_fn(jnp.array([5.0, -2.0]))[2])
    assert_close(unrolled_fn(jnp.array([5.0, -2.0]))[3], -2 * np.pi, rtol=1e-15)
    assert_close(jax.grad(lambda x: unrolled(fn, x)[0])(jnp.array([0.4, 1.0])),
                 [1e-12 * np.cos(0.4), 0.0], rtol=1e-12)


def test_the_ways_of_writing_T_write_out_about_as_much_code():
    """The double pendulum's T as the textbook writes it, with velocity vectors
    vᵢ = lᵢθ̇ᵢ(cos θᵢ, sin θᵢ), and with rotation matrices and a JVP for the velocities: the
    identities autodiff leaves in the last two (cos²θ + sin²θ, the sine of θ₁ − θ₂ written out
    twice, the signs of a rotation) fold away, so that their equations of motion write out at
    most twice the operations of the first (2.4× and 3.0× without), and all three give the
    closed form's accelerations."""
    def textbook(q, qd, p):
        return (0.5 * (p["m1"] + p["m2"]) * (p["l1"] * qd[0]) ** 2
                + 0.5 * p["m2"] * (p["l2"] * qd[1]) ** 2
                + p["m2"] * p["l1"] * p["l2"] * qd[0] * qd[1] * jnp.cos(q[0] - q[1]))

    def vectors(q, qd, p):
        v1 = p["l1"] * qd[0] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
        v2 = v1 + p["l2"] * qd[1] * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
        return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)

    def rotations(q, qd, p):
        def positions(q):
            def rotation(angle):
                c, s = jnp.cos(angle), jnp.sin(angle)
                return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])
            down = jnp.array([0.0, -1.0])
            r1 = p["l1"] * rotation(q[0]) @ down
            return r1, r1 + p["l2"] * rotation(q[1]) @ down
        v1, v2 = jax.jvp(positions, (q,), (qd,))[1]
        return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)

    def V(q, p):
        return -p["g"] * ((p["m1"] + p["m2"]) * p["l1"] * jnp.cos(q[0])
                          + p["m2"] * p["l2"] * jnp.cos(q[1]))

    p = {k: jnp.asarray(v) for k, v in dict(m1=1.0, m2=1.3, l1=0.9, l2=1.1, g=9.81).items()}
    q, u = jnp.array([0.7, -0.4]), jnp.array([0.3, -1.1])
    m1, m2, l1, l2, g = (float(p[k]) for k in ("m1", "m2", "l1", "l2", "g"))
    d = q[0] - q[1]
    den = 2 * m1 + m2 - m2 * np.cos(2 * d)
    closed_form = np.array([
        (-g * (2 * m1 + m2) * np.sin(q[0]) - m2 * g * np.sin(q[0] - 2 * q[1])
         - 2 * np.sin(d) * m2 * (u[1] ** 2 * l2 + u[0] ** 2 * l1 * np.cos(d))) / (l1 * den),
        (2 * np.sin(d) * (u[0] ** 2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(q[0])
                          + u[1] ** 2 * l2 * m2 * np.cos(d))) / (l2 * den)])
    sizes = {}
    for T in (textbook, vectors, rotations):
        system = jaxdyn.Lagrangian(T, V)
        fn = lambda q, u: equations_of_motion(system, jnp.zeros(()), q, u, p)[1]  # noqa: E731,B023
        sizes[T.__name__] = len(_live_straight_line(jax.make_jaxpr(fn)(q, u).jaxpr))
        assert_close(jax.jit(fn)(q, u), closed_form, rtol=1e-13)
    assert sizes["vectors"] <= 2 * sizes["textbook"], sizes
    assert sizes["rotations"] <= 2 * sizes["textbook"], sizes


def test_programs_over_budget_run_as_written():
    fn = lambda x: jnp.sin(x) @ jnp.cos(x)  # noqa: E731
    x = jnp.ones(50)
    jaxpr = jax.make_jaxpr(lambda x: unrolled(fn, x, max_elements=10))(x)
    # As written (inside the rule that batches array programs in chunks: a nested jaxpr).
    assert "dot_general" in str(jaxpr)
    assert_close(unrolled(fn, x, max_elements=10), fn(x), rtol=1e-15)
    called = []
    jax.make_jaxpr(lambda x: unrolled(fn, x, max_elements=10,
                                      otherwise=lambda x: called.append(True) or fn(x)))(x)
    assert called
    # The budget counts the operations left after constant folding: a constant input folds
    # the whole program, which then fits.
    called.clear()
    unrolled(fn, x, max_elements=10, otherwise=lambda x: called.append(True) or fn(x))
    assert not called


def test_equations_too_large_to_try_give_up_before_their_solve_is_written_out(monkeypatch):
    """An attempt at straight-line code whose M and f alone exceed what is tried gives up
    before writing out their LDLᵀ solve, and the structure of M is analysed once for a first
    `simulate`; the accelerations are the closed form's."""
    import jaxdyn._dynamics
    import jaxdyn._unroll

    # (functions of their own: traces that no earlier test cached)
    kinetic, potential = DOUBLE_PENDULUM.dynamics.kinetic, DOUBLE_PENDULUM.dynamics.potential
    system = jaxdyn.Lagrangian(lambda *a: kinetic(*a), lambda *a: potential(*a))
    p = DOUBLE_PENDULUM.params
    for budget in ("MAX_TRIED", "MAX_ELEMENTS"):  # below the double pendulum's M and f
        monkeypatch.setattr(jaxdyn._unroll, budget, 10)
    solves, analyses = [], []
    solve, structure = jaxdyn._dynamics.solve_mass_matrix, jaxdyn._dynamics.structure
    monkeypatch.setattr(jaxdyn._dynamics, "solve_mass_matrix",
                        lambda *a, **k: solves.append(k["unrolled"]) or solve(*a, **k))
    monkeypatch.setattr(jaxdyn._dynamics, "structure",
                        lambda *a, **k: analyses.append(True) or structure(*a, **k))
    q, qd = DOUBLE_PENDULUM.sample(np.random.default_rng(4))
    assert_close(system.accelerations(0.0, q, qd, p),
                 DOUBLE_PENDULUM.accelerations(q, qd, p), rtol=1e-12)
    assert solves and not any(solves)  # only the array program's solve was traced
    jaxdyn.simulate(system, q, qd, p, t1=0.1)
    assert len(analyses) == 1


def _pattern(elements):
    """'0' for a structural zero, 'c' for another constant, else the dependencies."""
    def one(e):
        if is_constant(e):
            return "0" if e == 0 else "c"
        return "".join(sorted(e.depends))

    return np.vectorize(one, otypes=[object])(elements)


def test_structure_of_the_elastic_pendulum_mass_matrix():
    """M = diag(m, m r²): the off-diagonal entries are structural zeros, M₀₀ depends on the
    parameters alone and M₁₁ on q and the parameters."""
    system = ELASTIC_PENDULUM
    q, qd = np.array([1.2, 0.3]), np.array([0.1, 0.2])
    mass_matrix, forcing = structure(system.dynamics.form_equations, jnp.asarray(0.0), q, qd,
                                     system.params, tags=("t", "q", "u", "p"))
    assert _pattern(mass_matrix).tolist() == [["p", "0"], ["0", "pq"]]
    assert all(isinstance(e, Symbol) and e.depends == {"p", "q", "u"} for e in forcing)


def test_structure_of_a_constant_and_block_diagonal_mass_matrix():
    """Two independent subsystems in Cartesian coordinates: a particle (x, z) and an
    oscillator y; M = diag(2, 3, 2) is constant and has three 1×1 blocks."""
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: qd[0] ** 2 + 1.5 * qd[1] ** 2 + qd[2] ** 2,
        lambda q, p: p["k"] * q[1] ** 2 + jnp.sin(q[0]) * q[2])
    mass_matrix, _ = structure(system.form_equations, 0.0, np.ones(3), np.ones(3), {"k": 1.0},
                               tags=("t", "q", "u", "p"))
    assert _pattern(mass_matrix).tolist() == [["c", "0", "0"], ["0", "c", "0"], ["0", "0", "c"]]


def test_structure_of_the_double_pendulum_is_dense():
    system = DOUBLE_PENDULUM
    mass_matrix, _ = structure(system.dynamics.form_equations, 0.0, np.ones(2), np.ones(2),
                               system.params, tags=("t", "q", "u", "p"))
    assert all(isinstance(e, Symbol) and "q" in e.depends for e in mass_matrix.ravel())


@pytest.mark.parametrize("index", [
    lambda x: x[jnp.array([0, 2])],
    lambda x: x[:, jnp.array([3, 1, 1])],
    lambda x: x[jnp.array([2, 0]), jnp.array([1, 3])],
    lambda x: x.at[jnp.array([5, 0])].get(mode="clip"),
    lambda x: jnp.take_along_axis(x, jnp.array([[0], [2], [1]]), axis=1),
    lambda x: jax.lax.dynamic_slice(x, (jnp.int32(2), jnp.int32(1)), (2, 2)),
    lambda x: jax.lax.dynamic_update_slice(x, -x[:2, :2], (jnp.int32(-1), jnp.int32(3))),
    lambda x: x.at[1, 2].set(-x[0, 0]),
    lambda x: x.at[:, 1].set(2.0 * x[:, 3]),
    lambda x: x.at[-1, jnp.array([0, 3])].set(x[0, :2]),
    lambda x: x.at[jnp.array([1, 5])].set(x[:2] + 1.0, mode="drop"),
    lambda x: x.at[jnp.array([1, 5])].set(x[:2] + 1.0, mode="clip"),
    lambda x: x.at[jnp.array([2, 0])].add(x[:2]),
    lambda x: x.at[jnp.array([1, 1]), 2].add(x[:2, 0]),
    lambda x: x.at[1:3, 2].set(0.5),
])
def test_static_indexing_unrolls_to_what_xla_computes(index):
    """Gathers, dynamic slices and scatters (`.at[...].set`, `.add`) with indices known at
    trace time, located element by element in NumPy (XLA's clamping and dropping included),
    against XLA running the same program; no program is compiled to locate them."""
    x = jnp.arange(1.0, 13.0).reshape(3, 4)
    with compiles() as count:  # traced, not run: a program compiled would be a location's
        jax.make_jaxpr(lambda x: unrolled(index, x))(x)
    assert count() == 0, count()
    assert_close(unrolled(index, x), index(x), rtol=0)


def _operations(jaxpr):
    """Equations of a jaxpr, those of the programs it calls included."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for value in eqn.params.values():
            if hasattr(value, "jaxpr") and hasattr(value.jaxpr, "eqns"):  # a ClosedJaxpr
                total += _operations(value.jaxpr)
            elif hasattr(value, "eqns"):
                total += _operations(value)
    return total


def test_large_straight_line_programs_are_differentiated_as_arrays():
    """Equations written out as thousands of scalar operations (a chain of 10 rods) are
    differentiated as the array program: its JVP holds fewer operations than the equations
    written out (2372 against 2862), where the written-out JVP held 8987, which took 73 s to
    compile through a solve; and the derivative equals central differences."""
    from jaxdyn._dynamics import equations_of_motion, straight_line_size

    n = 10
    chain = rod_chain()
    p = {"m": jnp.full(n, 0.1), "l": jnp.full(n, 0.1), "g": jnp.asarray(9.81)}
    q = 0.3 + 0.5 * jnp.sin(jnp.arange(n, dtype=jnp.float64) / 3.0)
    u = jnp.linspace(-1.0, 1.0, n)
    size = straight_line_size(chain, jnp.zeros(()), q, u, p)
    assert size is not None and size > 2000  # written out when evaluated

    def accelerations(g):
        return equations_of_motion(chain, jnp.zeros(()), q, u, {**p, "g": g})[1]

    linear = jax.make_jaxpr(lambda g: jax.jvp(accelerations, (g,), (jnp.ones(()),))[1])(
        p["g"])
    assert _operations(linear.jaxpr) < 1.5 * size  # (written out: 8987 for 2862)
    slope = jax.jvp(accelerations, (p["g"],), (jnp.ones(()),))[1]
    h = 1e-5
    central = (accelerations(p["g"] + h) - accelerations(p["g"] - h)) / (2 * h)
    assert_close(slope, central, rtol=1e-7, atol=1e-9)


def test_derivative_reaches_values_the_callbacks_close_over():
    """A callback closing over a traced value (a stiffness k under `jax.grad`): the written-out
    program's derivative must reach it, also where the derivative is the array program's."""
    def accelerations_for(k, n):
        spring = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2),
                                   lambda q, p: 0.5 * k * jnp.sum(jnp.sin(q) ** 2))
        q = jnp.linspace(0.1, 0.9, n)
        return spring.accelerations(0.0, q, jnp.zeros(n))

    for n in (2, 12):
        derivative = jax.jacfwd(lambda k: accelerations_for(k, n))(2.0)
        q = np.linspace(0.1, 0.9, n)
        assert_close(derivative, -np.sin(q) * np.cos(q), rtol=1e-12)
        gradient = jax.grad(lambda k: jnp.sum(accelerations_for(k, n)))(2.0)
        assert_close(gradient, -np.sum(np.sin(q) * np.cos(q)), rtol=1e-12)


def test_derivative_of_a_program_closing_over_an_outer_traced_value():
    """The written-out program closes over r, traced by an outer `jax.jacfwd` (as `linearise`
    differentiates in the inputs): counting the program's operations for its derivative must
    not touch that tracer, with and without `jax.jit` around."""
    q = jnp.array([0.3, 0.4])

    def f(r):
        return unrolled(lambda q: jnp.sin(q) * r[0] + q**2 * r[1], q)

    expected = np.stack([np.sin(q), np.asarray(q) ** 2], axis=1)
    for transform in (lambda g: g, jax.jit):
        assert_close(transform(jax.jacfwd(f))(jnp.array([1.0, 2.0])), expected, rtol=1e-15)


def test_callbacks_with_custom_derivatives_are_written_out():
    """A callback using a function with a custom JVP (jax.nn.softplus's log-sum-exp, a custom
    rule) in written-out code: values and derivatives equal JAX's evaluation."""
    def V(q, p):
        return jnp.sum(jax.nn.relu(q) ** 2) + jnp.sum(jax.nn.softplus(q))

    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2), V)
    q, u = jnp.array([0.4, -0.2]), jnp.zeros(2)
    expected = -jax.grad(V)(q, None)
    assert_close(system.accelerations(0.0, q, u), expected, rtol=1e-14)
    jacobian = jax.jacfwd(lambda q: system.accelerations(0.0, q, u))(q)
    assert_close(jacobian, -jax.hessian(V)(q, None), rtol=1e-12)


def _chain_tree(n):
    """N uniform rods (1.3 kg, 0.7 m) hinged end to end about z, gravity along −y."""
    inertia = jnp.diag(jnp.array([1.0, 0.0, 1.0])) * 1.3 * 0.7**2 / 12
    links = [jaxdyn.Link(f"rod{i}", jaxdyn.Revolute((0, 0, 1)),
                         parent=None if i == 0 else f"rod{i - 1}",
                         translation=(0.0, 0.0 if i == 0 else -0.7, 0.0),
                         mass=1.3, com=(0.0, -0.35, 0.0), inertia=inertia)
             for i in range(n)]
    return jaxdyn.RigidBodyTree(links, gravity=jnp.array([0.0, -9.81, 0.0]))


@pytest.mark.parametrize("path", ["written-out derivative", "array derivative",
                                  "array program in chunks"])
def test_a_vmapped_program_differentiated_afterwards_keeps_its_batch_axis(path, monkeypatch):
    """The forcing of a square batch of states (as many states as coordinates), vmapped,
    differentiated with respect to a value shared by the batch: equal to central differences
    state by state, through each of the three ways equations are differentiated. Inside a
    `jit` JAX labels a custom JVP's outputs by the function's batch axes and moves the rule's
    to the rule's own: straight-line code stacks scalars (batch axis last) and its array
    derivative computes the values batch axis first, so the tangent came back transposed."""
    import jaxdyn._unroll as unroll

    n = 5
    if path == "array program in chunks":
        monkeypatch.setattr(unroll, "MAX_ELEMENTS", 0)
        system = jaxdyn.ArticulatedBody(_chain_tree(n))
        p, u0 = None, jnp.linspace(0.5, -0.4, n)

        def forcing(s, q):  # s scales the speeds: the centripetal terms, quadratic in s
            return system.forcing(0.0, q, s * u0, p)
    else:
        if path == "array derivative":
            monkeypatch.setattr(unroll, "MAX_DIFFERENTIATED", 0)
        system = rod_chain()
        p = {"m": jnp.linspace(0.1, 0.3, n), "l": jnp.full(n, 0.2)}
        u0 = jnp.linspace(0.5, -0.4, n)

        def forcing(s, q):  # s is gravity here
            return system.forcing(0.0, q, u0, {**p, "g": s})

    qs = jnp.asarray(RNG.uniform(-1.0, 1.0, (n, n)))
    s = jnp.asarray(1.7)

    def batch(s):
        return jax.vmap(forcing, (None, 0))(s, qs)

    h = 1e-6
    central = (batch(s + h) - batch(s - h)) / (2 * h)
    for transform in (lambda g: g, jax.jit):
        tangent = transform(lambda s: jax.jvp(batch, (s,), (jnp.ones(()),))[1])(s)
        assert_close(tangent, central, rtol=1e-7, atol=1e-8)
