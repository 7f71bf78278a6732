"""Inputs, equilibria, linearisation and modes, against closed forms, sympy's Linearizer and
finite differences (float64)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
from helpers import compiles

CART_POLE = dict(M=1.0, m=0.1, l=0.5, g=9.81)


def cart_pole_T(q, qd, p):
    """Cart x, pole angle θ from the upward vertical, point mass m at distance l."""
    return (0.5 * (p["M"] + p["m"]) * qd[0] ** 2
            + p["m"] * p["l"] * qd[0] * qd[1] * jnp.cos(q[1])
            + 0.5 * p["m"] * p["l"] ** 2 * qd[1] ** 2)


def cart_pole_V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])


def cart_pole():
    return jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), input_map=[0])


def pendulum_T(q, qd, p):
    return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2


def pendulum_V(q, p):
    return -p["m"] * p["g"] * p["l"] * jnp.cos(q[0])


PENDULUM = dict(m=1.3, l=0.8, g=9.81)


def test_cart_pole_matrices_against_the_textbook():
    """About the upright pole: ẍ = (F − m g θ)/M, θ̈ = ((M + m) g θ − F)/(M l)."""
    M, m, l, g = (CART_POLE[k] for k in "Mmlg")
    model = jaxdyn.linearise(cart_pole(), 0.0, jnp.zeros(2), jnp.zeros(2), CART_POLE)
    a = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, -m * g / M, 0, 0],
                  [0, (M + m) * g / (M * l), 0, 0]])
    b = np.array([[0], [0], [1 / M], [-1 / (M * l)]])
    np.testing.assert_allclose(model.A, a, atol=1e-13)
    np.testing.assert_allclose(model.B, b, atol=1e-13)
    np.testing.assert_allclose(model.C, np.eye(4))
    assert model.stability() == "unstable"
    assert model.is_controllable()
    # The unstable eigenvalue √((M + m) g / (M l)), and a double zero (the cart's position).
    np.testing.assert_allclose(model.eigenvalues()[0].real, np.sqrt((M + m) * g / (M * l)),
                               rtol=1e-12)
    # Only the cart's position measured: observable; only the pole's angle: not (the cart's
    # position never shows in θ).
    cart = jaxdyn.linearise(cart_pole(), 0.0, jnp.zeros(2), jnp.zeros(2), CART_POLE,
                            output=lambda t, q, u, r, p: q[0])
    pole = jaxdyn.linearise(cart_pole(), 0.0, jnp.zeros(2), jnp.zeros(2), CART_POLE,
                            output=lambda t, q, u, r, p: q[1])
    np.testing.assert_allclose(cart.C, [[1, 0, 0, 0]])
    assert cart.is_observable() and not pole.is_observable()


def test_inverted_pendulum_eigenvalue_over_a_parameter_sweep():
    """λ = ±√(g/l) upright, ±i√(g/l) hanging, for every l of a vmapped sweep (a root locus)."""
    lengths = jnp.linspace(0.3, 2.0, 7)

    def eigenvalues(length, angle):
        p = dict(PENDULUM, l=length)
        model = jaxdyn.linearise(jaxdyn.Lagrangian(pendulum_T, pendulum_V), 0.0,
                                 jnp.array([angle]), jnp.zeros(1), p)
        return jnp.linalg.eigvals(model.A)

    upright = jax.vmap(eigenvalues, in_axes=(0, None))(lengths, jnp.pi)
    hanging = jax.vmap(eigenvalues, in_axes=(0, None))(lengths, 0.0)
    rate = np.sqrt(PENDULUM["g"] / np.asarray(lengths))
    np.testing.assert_allclose(np.sort(upright.real, axis=1), np.stack([-rate, rate], 1),
                               rtol=1e-12)
    np.testing.assert_allclose(np.sort(hanging.imag, axis=1), np.stack([-rate, rate], 1),
                               rtol=1e-12)
    np.testing.assert_allclose(hanging.real, 0, atol=1e-12)


def test_double_pendulum_small_oscillations():
    """det(K − ω² M) = 0 with M = [[(m₁+m₂)l₁², m₂l₁l₂], [m₂l₁l₂, m₂l₂²]],
    K = diag((m₁+m₂) g l₁, m₂ g l₂), solved as a quadratic in ω²."""
    p = dict(m1=1.0, m2=0.7, l1=1.2, l2=0.9, g=9.81)

    def T(q, qd, p):
        return (0.5 * (p["m1"] + p["m2"]) * (p["l1"] * qd[0]) ** 2
                + 0.5 * p["m2"] * (p["l2"] * qd[1]) ** 2
                + p["m2"] * p["l1"] * p["l2"] * qd[0] * qd[1] * jnp.cos(q[0] - q[1]))

    def V(q, p):
        return -(p["m1"] + p["m2"]) * p["g"] * p["l1"] * jnp.cos(q[0]) - (
            p["m2"] * p["g"] * p["l2"] * jnp.cos(q[1]))

    m1, m2, l1, l2, g = (p[k] for k in ("m1", "m2", "l1", "l2", "g"))
    mass = np.array([[(m1 + m2) * l1**2, m2 * l1 * l2], [m2 * l1 * l2, m2 * l2**2]])
    stiffness = np.diag([(m1 + m2) * g * l1, m2 * g * l2])
    # det(K − s M) = a s² + b s + c
    a = np.linalg.det(mass)
    b = -(stiffness[0, 0] * mass[1, 1] + stiffness[1, 1] * mass[0, 0])
    c = np.linalg.det(stiffness)
    squared = np.sort(np.roots([a, b, c]).real)
    system = jaxdyn.Lagrangian(T, V)
    modes = jaxdyn.normal_modes(system, 0.0, jnp.zeros(2), p)
    np.testing.assert_allclose(modes.natural_frequencies, np.sqrt(squared), rtol=1e-12)
    for k in range(2):  # (K − ω² M) φ = 0, φᵀ M φ = 1
        shape = np.asarray(modes.shapes[:, k])
        np.testing.assert_allclose((stiffness - squared[k] * mass) @ shape, 0, atol=1e-11)
        np.testing.assert_allclose(shape @ mass @ shape, 1, rtol=1e-12)
    # The same frequencies from the eigenvalues of A (conservative: ζ = 0).
    general = jaxdyn.linearise(system, 0.0, jnp.zeros(2), jnp.zeros(2), p).modes()
    carried = ~np.asarray(general.conjugate)
    np.testing.assert_allclose(np.sort(general.natural_frequencies[carried]),
                               np.sqrt(squared), rtol=1e-12)
    np.testing.assert_allclose(general.damping_ratios[carried], 0, atol=1e-12)
    assert jaxdyn.linearise(system, 0.0, jnp.zeros(2), jnp.zeros(2), p).stability() == (
        "marginally stable")


@pytest.mark.parametrize("n", [3, 6])
def test_spring_mass_chain_sine_modes(n):
    """n masses m between two walls, springs k: ω_j = 2 √(k/m) sin(jπ / (2(n+1))), shapes
    φ_j(i) ∝ sin(i j π / (n+1))."""
    p = dict(m=0.5, k=20.0)

    def T(q, qd, p):
        return 0.5 * p["m"] * jnp.sum(qd**2)

    def V(q, p):
        stretches = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * p["k"] * jnp.sum(stretches**2)

    system = jaxdyn.Lagrangian(T, V)
    modes = jaxdyn.normal_modes(system, 0.0, jnp.zeros(n), p)
    with compiles() as count:  # a new stiffness, given as a number, reuses the program
        stiffer = jaxdyn.normal_modes(system, 0.0, jnp.zeros(n), dict(m=0.5, k=80.0))
    assert count() == 0
    np.testing.assert_allclose(stiffer.natural_frequencies, 2 * modes.natural_frequencies,
                               rtol=1e-12)  # ω ∝ √k
    j = np.arange(1, n + 1)
    np.testing.assert_allclose(modes.natural_frequencies,
                               2 * np.sqrt(p["k"] / p["m"]) * np.sin(j * np.pi / (2 * (n + 1))),
                               rtol=1e-12)
    for jj in j:
        expected = np.sin(np.arange(1, n + 1) * jj * np.pi / (n + 1))
        shape = np.asarray(modes.shapes[:, jj - 1])
        cosine = abs(shape @ expected) / np.linalg.norm(shape) / np.linalg.norm(expected)
        np.testing.assert_allclose(cosine, 1, rtol=1e-12)


def test_eigenvalue_gradient_against_finite_differences():
    """d ω / d l of the upright cart-pole's unstable eigenvalue, and of a hanging pendulum's
    frequency √(g/l)."""
    def unstable(length):
        p = dict(CART_POLE, l=length)
        return jnp.max(jnp.linalg.eigvals(jaxdyn.linearise(
            cart_pole(), 0.0, jnp.zeros(2), jnp.zeros(2), p).A).real)

    def frequency(length):
        p = dict(PENDULUM, l=length)
        return jaxdyn.normal_modes(jaxdyn.Lagrangian(pendulum_T, pendulum_V), 0.0,
                                   jnp.zeros(1), p).natural_frequencies[0]

    for fn, x in ((unstable, 0.5), (frequency, 0.8)):
        h = 1e-6
        central = (fn(x + h) - fn(x - h)) / (2 * h)
        np.testing.assert_allclose(jax.grad(fn)(x), central, rtol=1e-7)
    M, m, g = CART_POLE["M"], CART_POLE["m"], CART_POLE["g"]
    np.testing.assert_allclose(jax.grad(unstable)(0.5),
                               -0.5 * np.sqrt((M + m) * g / M) * 0.5 ** -1.5, rtol=1e-10)


def test_equilibria_of_a_pendulum_under_a_constant_torque():
    """m g l sin θ = τ; with θ prescribed, the torque that holds it there."""
    m, l, g = (PENDULUM[k] for k in "mlg")
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(pendulum_T, pendulum_V), input_map=[0])
    torque = 4.0
    found = jaxdyn.equilibrium(plant, jnp.array([0.1]), PENDULUM, jnp.array([torque]))
    np.testing.assert_allclose(found.q, [np.arcsin(torque / (m * g * l))], rtol=1e-12)
    with compiles() as count:  # a new guess reuses the compiled solve
        upright = jaxdyn.equilibrium(plant, jnp.array([2.9]), PENDULUM, jnp.array([torque]))
    assert count() == 0
    np.testing.assert_allclose(upright.q, [np.pi - np.arcsin(torque / (m * g * l))],
                               rtol=1e-12)
    held = jaxdyn.equilibrium(plant, jnp.array([0.0]), PENDULUM, prescribed={0: 0.6})
    np.testing.assert_allclose(held.r, [m * g * l * np.sin(0.6)], rtol=1e-12)
    np.testing.assert_allclose(held.q, [0.6])
    # Newton's steps are solved without LAPACK (whose first call loads SciPy's, ~0.3 s)
    program = jax.jit(lambda q: jaxdyn.equilibrium(plant, q, PENDULUM, prescribed={0: 0.6}).r)
    assert "lapack" not in program.lower(jnp.array([0.0])).as_text().lower()
    with pytest.raises(RuntimeError, match="(?s)No equilibrium found.*last iterate q"):
        jaxdyn.equilibrium(plant, jnp.array([0.1]), PENDULUM, jnp.array([3 * m * g * l]))
    # Inside a caller's jit, a failure raises whichever output is read (here the inputs r).
    held_at = jax.jit(lambda angle: jaxdyn.equilibrium(
        plant, jnp.array([0.0]), {**PENDULUM, "g": 0.0 * angle + jnp.nan},
        prescribed={0: angle}).r)
    with pytest.raises(Exception, match="No equilibrium found"):
        jax.block_until_ready(held_at(0.6))


def test_constrained_pendulum_in_independent_coordinates():
    """A bob in Cartesian (x, y) on x² + y² = l²: about the bottom, in (x, ẋ),
    A = [[0, 1], [−g/l, 0]]; its equilibrium found on the constraint."""
    p = dict(m=1.0, g=9.81, l=2.0)
    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                          lambda q, p: p["m"] * p["g"] * q[1]),
        holonomic=lambda q, p: jnp.array([q @ q - p["l"] ** 2]))
    bottom = jnp.array([0.0, -2.0])
    model = jaxdyn.linearise(system, 0.0, bottom, jnp.zeros(2), p, independent=(0, 2))
    np.testing.assert_allclose(model.A, [[0, 1], [-p["g"] / p["l"], 0]], atol=1e-12)
    np.testing.assert_allclose(model.basis[:, 0], [1, 0, 0, 0], atol=1e-12)
    orthonormal = jaxdyn.linearise(system, 0.0, bottom, jnp.zeros(2), p).modes()
    np.testing.assert_allclose(orthonormal.natural_frequencies, np.sqrt(p["g"] / p["l"]),
                               rtol=1e-12)
    found = jaxdyn.equilibrium(system, jnp.array([0.4, -1.5]), p)
    np.testing.assert_allclose(found.q, bottom, atol=1e-10)


def test_linearise_reads_the_rank_of_redundant_constraints_and_compiles_once():
    """The rod stated twice (φ and 2φ: rank 1 of 2 rows) leaves one coordinate and one speed:
    about the bottom ω = √(g/l). A new operating point, or a new parameter given as a number,
    compiles nothing (the rank is read on the host, the program kept)."""
    def rod(q, p):
        row = q @ q - p["l"] ** 2
        return jnp.stack([row, 2 * row])

    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                          lambda q, p: p["m"] * p["g"] * q[1]),
        holonomic=rod, redundant="least_squares")
    p = dict(m=1.0, g=9.81, l=2.0)
    model = jaxdyn.linearise(system, 0.0, np.array([0.0, -2.0]), np.zeros(2), p)
    assert model.A.shape == (2, 2) and model.num_coordinates == 1
    np.testing.assert_allclose(model.modes().natural_frequencies, np.sqrt(p["g"] / p["l"]),
                               rtol=1e-12)
    with compiles() as count:
        for angle, g in ((0.2, 9.81), (0.4, 9.7)):
            at = 2.0 * np.array([np.sin(angle), -np.cos(angle)])
            jaxdyn.linearise(system, 0.0, at, np.zeros(2), dict(p, g=g))
    assert count() == 0


def test_sympy_linearizer_on_a_constrained_pendulum():
    """sympy.physics.mechanics' nonminimal-coordinates pendulum (Lagrange's method with the
    constraint q₁² + q₂² = L²), gravity tilted by β so that the equilibrium at angle β
    couples the coordinates (∂q₁/∂q₂ = −tan β), linearised by sympy's `Linearizer` in q₂,
    against `linearise(..., independent=(q₂, q̇₂))`."""
    sm = pytest.importorskip("sympy")
    me = pytest.importorskip("sympy.physics.mechanics")
    q1, q2 = me.dynamicsymbols("q1:3")
    q1d, q2d = me.dynamicsymbols("q1:3", 1)
    L, m, g, beta = sm.symbols("L, m, g, beta")
    N = me.ReferenceFrame("N")
    pN = me.Point("N*")
    pN.set_vel(N, 0)
    P = pN.locatenew("P1", q1 * N.x + q2 * N.y)
    P.set_vel(N, P.pos_from(pN).dt(N))
    particle = me.Particle("pP", P, m)
    lagrangian = me.Lagrangian(N, particle) + m * g * (q1 * sm.cos(beta) + q2 * sm.sin(beta))
    method = me.LagrangesMethod(lagrangian, [q1, q2], hol_coneqs=[q1**2 + q2**2 - L**2],
                                frame=N)
    method.form_lagranges_equations()
    values = {L: 1.5, m: 0.7, g: 9.81, beta: 0.6}
    x, y = 1.5 * np.cos(0.6), 1.5 * np.sin(0.6)
    qdd = me.dynamicsymbols("q1:3", 2)
    op_point = {q1: x, q2: y, q1d: 0, q2d: 0, qdd[0]: 0, qdd[1]: 0,
                method.lam_vec[0]: method.solve_multipliers(
                    op_point={q1: x, q2: y, q1d: 0, q2d: 0})[method.lam_vec[0]].subs(values)}
    linearizer = method.to_linearizer(q_ind=[q2], qd_ind=[q2d], q_dep=[q1], qd_dep=[q1d])
    a_sympy = np.array(linearizer.linearize(op_point=[op_point, values], A_and_B=True,
                                            simplify=False)[0], dtype=float)

    p = {"L": 1.5, "m": 0.7, "g": 9.81, "beta": 0.6}
    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                          lambda q, p: -p["m"] * p["g"] * (q[0] * jnp.cos(p["beta"])
                                                           + q[1] * jnp.sin(p["beta"]))),
        holonomic=lambda q, p: jnp.array([q @ q - p["L"] ** 2]))
    model = jaxdyn.linearise(system, 0.0, jnp.array([x, y]), jnp.zeros(2), p,
                             independent=(1, 3))
    np.testing.assert_allclose(model.A, a_sympy, rtol=1e-12, atol=1e-12)
    assert abs(a_sympy[1, 0]) > 1  # a real coupling, not a trivial zero


def test_constrained_linearisation_off_equilibrium():
    """The same pendulum (gravity along x) swinging, off equilibrium: in y = L sin θ the
    reduced equation is ÿ = −g (y/L) c − y ẏ² / (L c)², c = √(1 − y²/L²); A against its
    central differences."""
    length, g = 1.5, 9.81

    def reduced(y, yd):
        c = np.sqrt(1 - y * y / length**2)
        return -g * (y / length) * c - y * yd**2 / (length * c) ** 2

    angle, rate = 0.5, 0.8
    x, y = length * np.cos(angle), length * np.sin(angle)
    xd, yd = -length * np.sin(angle) * rate, length * np.cos(angle) * rate
    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: -g * q[0]),
        holonomic=lambda q, p: jnp.array([q @ q - length**2]))
    model = jaxdyn.linearise(system, 0.0, jnp.array([x, y]), jnp.array([xd, yd]),
                             independent=(1, 3))
    h = 1e-6
    expected = [(reduced(y + h, yd) - reduced(y - h, yd)) / (2 * h),
                (reduced(y, yd + h) - reduced(y, yd - h)) / (2 * h)]
    np.testing.assert_allclose(model.A[0], [0, 1], atol=1e-12)
    np.testing.assert_allclose(model.A[1], expected, rtol=1e-8)


@pytest.mark.parametrize("form", ["ArticulatedBody", "Kane", "GibbsAppell", "Lagrangian"])
def test_joint_torque_on_every_description(form):
    """A uniform rod on a hinge driven by a joint torque τ, described as a tree of links:
    θ̈ = (τ − m g (l/2) sin θ) / (m l²/3), and B = [0, 3/(m l²)] about the hanging rod."""
    m, l, g = 1.2, 0.9, 9.81
    inertia = jnp.diag(jnp.array([1.0, 0.0, 1.0])) * m * l**2 / 12
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("rod", jaxdyn.Revolute((0, 0, 1)), mass=m,
                                             com=(0.0, -l / 2, 0.0), inertia=inertia)],
                                gravity=jnp.array([0.0, -g, 0.0]))
    dynamics = getattr(jaxdyn, form).from_system(tree)
    plant = jaxdyn.Controlled(dynamics, input_map=[0])
    theta, torque = 0.7, 2.5
    accelerations = plant.with_inputs(jnp.array([torque])).accelerations(
        0.0, jnp.array([theta]), jnp.array([0.3]))
    expected = (torque - m * g * l / 2 * np.sin(theta)) / (m * l**2 / 3)
    np.testing.assert_allclose(accelerations, [expected], rtol=1e-12)
    model = jaxdyn.linearise(plant, 0.0, jnp.zeros(1), jnp.zeros(1))
    np.testing.assert_allclose(model.A, [[0, 1], [-1.5 * g / l, 0]], rtol=1e-12)
    np.testing.assert_allclose(model.B, [[0], [3 / (m * l**2)]], rtol=1e-12)


def test_inputs_as_constants_signals_and_policies():
    """A mass m pushed along a line: constant force F gives x = F t²/(2m); the signal
    F = sin t gives x = (t − sin t)/m; the same samples through diffrax's linear
    interpolation agree to the interpolation error; a policy F = −k x − c ẋ gives the
    damped oscillator's closed form; the saved inputs are those applied."""
    m = 2.0
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd),
                              input_map=lambda q, p: jnp.eye(1))
    ts = jnp.linspace(0.0, 3.0, 7)
    kw = dict(t1=3.0, ts=ts, save=("q", "inputs"), rtol=1e-12, atol=1e-12)
    constant = jaxdyn.simulate(plant, jnp.zeros(1), jnp.zeros(1), inputs=jnp.array([0.4]),
                               **kw)
    np.testing.assert_allclose(constant.q[:, 0], 0.4 * ts**2 / (2 * m), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(constant.inputs, np.full((7, 1), 0.4))
    signal = jaxdyn.simulate(plant, jnp.zeros(1), jnp.zeros(1),
                             inputs=lambda t: jnp.sin(t)[None], **kw)
    np.testing.assert_allclose(signal.q[:, 0], (ts - jnp.sin(ts)) / m, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(signal.inputs[:, 0], np.sin(ts), rtol=1e-12)
    samples = jnp.linspace(0.0, 3.0, 3001)
    path = diffrax.LinearInterpolation(samples, jnp.sin(samples)[:, None])
    interpolated = jaxdyn.simulate(plant, jnp.zeros(1), jnp.zeros(1), inputs=path, **kw)
    np.testing.assert_allclose(interpolated.q[:, 0], signal.q[:, 0], atol=1e-6)
    k, c = 8.0, 1.0

    def policy(t, q, u, p):
        return -k * q - c * u

    damped = jaxdyn.simulate(plant, jnp.array([1.0]), jnp.zeros(1), inputs=policy,
                             **dict(kw, save=("q", "u", "inputs")))
    wn, zeta = np.sqrt(k / m), c / (2 * np.sqrt(k * m))
    wd = wn * np.sqrt(1 - zeta**2)
    expected = np.exp(-zeta * wn * ts) * (np.cos(wd * ts) + zeta * wn / wd * np.sin(wd * ts))
    np.testing.assert_allclose(damped.q[:, 0], expected, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(damped.inputs[:, 0], -k * damped.q[:, 0] - c * damped.u[:, 0],
                               rtol=1e-12, atol=1e-12)


def test_gradients_through_inputs_against_finite_differences():
    """d x(T) / d(constant input) by `jax.grad` and d x(T) / d(policy gain) by `jax.jacfwd`,
    against central differences; the cart-pole, 2 s."""
    plant = cart_pole()
    q0, u0 = jnp.array([0.0, 0.2]), jnp.zeros(2)

    def final(r):
        return jaxdyn.simulate(plant, q0, u0, CART_POLE, t1=2.0, inputs=r, rtol=1e-11,
                               atol=1e-11).q[-1, 0]

    def with_gain(gain):
        policy = jax.tree_util.Partial(lambda g, t, q, u, p: g * q[1:], gain)
        return jaxdyn.simulate(plant, q0, u0, CART_POLE, t1=2.0, inputs=policy, rtol=1e-11,
                               atol=1e-11).q[-1, 0]

    for fn, x, derivative in ((final, jnp.array([0.3]), jax.grad),
                              (with_gain, jnp.array([5.0]), jax.jacfwd)):
        h = 1e-5
        central = (fn(x + h) - fn(x - h)) / (2 * h)
        np.testing.assert_allclose(derivative(fn)(x), [central], rtol=1e-6)


def test_input_errors_name_the_problem():
    plant = cart_pole()
    with pytest.raises(ValueError, match=r"inputs r must have shape \(1,\)"):
        jaxdyn.simulate(plant, jnp.zeros(2), jnp.zeros(2), CART_POLE, t1=0.1,
                        inputs=jnp.zeros(2))
    with pytest.raises(ValueError, match="declares no inputs"):
        jaxdyn.simulate(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), jnp.zeros(2),
                        jnp.zeros(2), CART_POLE, t1=0.1, inputs=jnp.zeros(1))
    with pytest.raises(ValueError, match="input map B must return an array of shape"):
        jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V),
                          lambda q, p: jnp.ones(2)).accelerations(0.0, jnp.zeros(2),
                                                                  jnp.zeros(2), CART_POLE)
    with pytest.raises(ValueError, match="input_map names speed 5"):
        jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), [5]).accelerations(
            0.0, jnp.zeros(2), jnp.zeros(2), CART_POLE)
    with pytest.raises(ValueError, match="B has 3 rows, but the system has 2 speeds"):
        jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V),
                          np.ones((3, 1))).accelerations(0.0, jnp.zeros(2), jnp.zeros(2),
                                                         CART_POLE)
    with pytest.raises(ValueError, match="a constant B as an array"):  # a column, not indices
        jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"directions must be an array \(2, k\)"):
        jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), jaxdyn.ForceInput(
            lambda q, p: q, directions=[1.0, 0.0])).input_matrix(0.0, jnp.zeros(2),
                                                                  jnp.zeros(2), CART_POLE)
    degenerate = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * q[0] ** 2 * qd[0] ** 2)
    with pytest.raises(RuntimeError, match="linearisation is not finite"):
        jaxdyn.linearise(degenerate, 0.0, jnp.zeros(1), jnp.zeros(1))
    # Inside a caller's jit, a failure raises whichever matrix is read (here B).
    driven = jaxdyn.Controlled(degenerate, input_map=[0])
    with pytest.raises(Exception, match="linearisation is not finite"):
        jax.block_until_ready(jax.jit(
            lambda q: jaxdyn.linearise(driven, 0.0, q, jnp.zeros(1), {}, jnp.zeros(1)).B)(
                jnp.zeros(1)))


def test_a_constant_input_map_given_as_an_array():
    """B as an array (m, k): a free particle of mass m in the plane pushed by two inputs along
    the columns of B accelerates by B r / m (Newton's second law)."""
    m = 2.5
    particle = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd)
    b = np.array([[1.0, 0.5], [0.0, 2.0]])
    r = jnp.array([3.0, -1.0])
    plant = jaxdyn.Controlled(particle, b, inputs=r)
    np.testing.assert_allclose(plant.accelerations(0.0, jnp.zeros(2), jnp.zeros(2)),
                               b @ np.asarray(r) / m, rtol=1e-14)
    assert plant.with_inputs(2 * r).input_matrix(0.0, jnp.zeros(2), jnp.zeros(2)).shape == (2, 2)


def test_rolling_disc_stability_boundary():
    """A rolling disc (nonholonomic, linearised in its independent speeds (ψ̇, θ̇, φ̇)) upright
    at rolling rate ω₀: the lean obeys (A + m r²) θ̈ = −[(C + m r²) C ω₀²/A − m g r] θ,
    stable above ω₀² = g / (3 r) (Gibbs–Appell and Kane)."""
    from jaxdyn.rotations import euler_angles, rotation_x, rotation_z

    p = {"m": 2.0, "r": 0.15, "g": 9.81}
    m, r, g = p["m"], p["r"], p["g"]
    a, c = m * r**2 / 4, m * r**2 / 2

    def centre(q, p):
        up = rotation_z(q[2]) @ rotation_x(q[3]) @ jnp.array([0.0, 0.0, 1.0])
        return jnp.array([q[0], q[1], 0.0]) + p["r"] * up

    def kinematic_map(q, p):  # rolling without slipping: ẋ = r φ̇ cos ψ, ẏ = r φ̇ sin ψ
        zero, one = jnp.zeros_like(q[2]), jnp.ones_like(q[2])
        return jnp.array([[zero, zero, p["r"] * jnp.cos(q[2])],
                          [zero, zero, p["r"] * jnp.sin(q[2])],
                          [one, zero, zero], [zero, one, zero], [zero, zero, one]])

    disc = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: jnp.diag(jnp.array([0.25, 0.5, 0.25])) * p["m"] * p["r"] ** 2,
        position=centre, orientation=lambda q, p: euler_angles(q[2:5], "zxy"))
    system = jaxdyn.MultibodySystem([disc], gravity=lambda p: jnp.array([0.0, 0.0, -p["g"]]))
    critical = np.sqrt(g / (3 * r))
    for form in (jaxdyn.GibbsAppell, jaxdyn.Kane):
        dynamics = form.from_system(system, kinematic_map)
        for factor, verdict in ((0.8, "unstable"), (1.25, "marginally stable")):
            omega0 = factor * critical
            model = jaxdyn.linearise(dynamics, 0.0, jnp.zeros(5),
                                     jnp.array([0.0, 0.0, omega0]), p)
            assert model.A.shape == (8, 8)
            assert model.stability() == verdict
            lean = ((c + m * r**2) * c * omega0**2 / a - m * g * r) / (a + m * r**2)
            values = np.asarray(model.eigenvalues())
            largest = values[np.argmax(np.abs(values))]
            np.testing.assert_allclose((largest**2).real, -lean, rtol=1e-10)


def test_batch_under_a_policy():
    """simulate_batch with a state-feedback policy: each member the damped oscillator's
    closed form x(t) = x₀ e^{−ζω t}(cos ω_d t + ζω/ω_d sin ω_d t)."""
    m, k, c = 2.0, 8.0, 1.0
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd), [0])
    x0 = jnp.linspace(-1.0, 1.0, 5)[:, None]
    solution = jaxdyn.simulate_batch(plant, x0, jnp.zeros_like(x0), t1=2.0, rtol=1e-12,
                                     atol=1e-12, inputs=lambda t, q, u, p: -k * q - c * u)
    wn, zeta = np.sqrt(k / m), c / (2 * np.sqrt(k * m))
    wd = wn * np.sqrt(1 - zeta**2)
    expected = np.exp(-zeta * wn * 2.0) * (np.cos(wd * 2.0) + zeta * wn / wd * np.sin(wd * 2.0))
    np.testing.assert_allclose(solution.q[:, -1, 0], np.asarray(x0[:, 0]) * expected,
                               rtol=1e-9, atol=1e-12)


def test_heavy_top_steady_precession():
    """A heavy symmetric top on its tip, zxz Euler angles (ψ, θ, φ): steady precession at
    nutation θ₀ and spin ω₃ = φ̇ + ψ̇ cos θ₀ holds when I₁ Ω² cos θ₀ − I₃ ω₃ Ω + m g L = 0
    (Ω = ψ̇; a slow and a fast root). There the accelerations vanish, and the linearisation's
    non-zero eigenvalues are the nutation ±i √(U''(θ₀)/I₁) of Routh's reduced potential
    U(θ) = (b − a cos θ)² / (2 I₁ sin² θ) + m g L cos θ, a = I₃ ω₃, b = I₁ Ω sin² θ₀ + a cos θ₀
    (differentiated by sympy here); I₁ about the tip (I₁ + m L² with I₁ about the centre of
    mass)."""
    from multibody_systems import SYSTEMS

    sm = pytest.importorskip("sympy")
    reference = SYSTEMS["heavy_top"]
    p = reference.params
    m, length, i3, g = (p[k] for k in ("m", "L", "I3", "g"))
    i1 = p["I1"] + m * length**2
    system = jaxdyn.Lagrangian.from_system(reference.system)
    theta0, spin = 0.7, 50.0
    for precession in np.roots([i1 * np.cos(theta0), -i3 * spin, m * g * length]):
        rates = jnp.array([precession, 0.0, spin - precession * np.cos(theta0)])
        q0 = jnp.array([0.4, theta0, -1.1])
        np.testing.assert_allclose(system.accelerations(0.0, q0, rates, p), 0, atol=1e-10)
        theta = sm.symbols("theta")
        a = i3 * spin
        b = i1 * precession * np.sin(theta0) ** 2 + a * np.cos(theta0)
        potential = (b - a * sm.cos(theta)) ** 2 / (2 * i1 * sm.sin(theta) ** 2) + (
            m * g * length * sm.cos(theta))
        assert abs(float(sm.diff(potential, theta).subs(theta, theta0))) < 1e-9
        nutation = np.sqrt(float(sm.diff(potential, theta, 2).subs(theta, theta0)) / i1)
        values = np.asarray(jaxdyn.linearise(system, 0.0, q0, rates, p).eigenvalues())
        moving = values[np.abs(values) > 1e-6]
        np.testing.assert_allclose(np.sort(moving.imag), [-nutation, nutation], rtol=1e-10)
        np.testing.assert_allclose(moving.real, 0, atol=1e-8 * nutation)


def test_point_forces_and_body_torques_as_generalized_active_forces():
    """Kane's generalized active forces of a force at a point and of a torque on a body,
    against their closed forms: a horizontal force F at the cart-pole's bob (x + l sin θ,
    l cos θ) gives Q = F (1, l cos θ); a torque τ about the world vertical on the heavy top
    gives, in zxz Euler angle rates, Q = τ (1, 0, cos θ), and in body angular velocities
    (Gibbs–Appell, u = ω), Q = τ Rᵀ e_z. A tuple of maps stacks their columns."""
    from multibody_systems import SYSTEMS, zxz_angle_rates
    from jaxdyn.rotations import euler_angles

    bob = jaxdyn.ForceInput(
        lambda q, p: jnp.stack([q[0] + p["l"] * jnp.sin(q[1]), p["l"] * jnp.cos(q[1])]),
        directions=[[1.0], [0.0]])
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), (bob, [0]))
    q, u = jnp.array([0.3, 0.4]), jnp.array([0.5, -1.0])
    np.testing.assert_allclose(
        plant.input_matrix(0.0, q, u, CART_POLE),
        [[1.0, 1.0], [CART_POLE["l"] * np.cos(0.4), 0.0]], rtol=1e-14)
    # The pushed bob accelerates the equations by M⁻¹ B r, as an explicit force in T, V would.
    pushed = jaxdyn.Lagrangian(
        cart_pole_T, cart_pole_V,
        forces=lambda q, qd, p: 2.0 * jnp.stack([jnp.ones_like(q[0]), p["l"] * jnp.cos(q[1])]))
    np.testing.assert_allclose(
        plant.with_inputs(jnp.array([2.0, 0.0])).accelerations(0.0, q, u, CART_POLE),
        pushed.accelerations(0.0, q, u, CART_POLE), rtol=1e-13)

    reference = SYSTEMS["heavy_top"]
    about_z = jaxdyn.TorqueInput(lambda q, p: euler_angles(q, "zxz"), directions=[[0.0], [0.0],
                                                                                 [1.0]])
    angles, rates = jnp.array([0.4, 0.7, -1.1]), jnp.array([0.2, 0.1, 20.0])
    lagrange = jaxdyn.Controlled(jaxdyn.Lagrangian.from_system(reference.system), about_z)
    np.testing.assert_allclose(lagrange.input_matrix(0.0, angles, rates, reference.params),
                               [[1.0], [0.0], [np.cos(0.7)]], atol=1e-14)
    appell = jaxdyn.Controlled(jaxdyn.GibbsAppell.from_system(
        reference.system, lambda q, p: zxz_angle_rates(q)), about_z)
    np.testing.assert_allclose(appell.input_matrix(0.0, angles, rates, reference.params),
                               np.asarray(euler_angles(angles, "zxz"))[2][:, None],
                               atol=1e-14)


def test_a_constrained_controlled_system_holds_and_saves_its_inputs():
    """A bob on a rod (Cartesian (x, y), x² + y² = l²) pushed sideways by a constant force F
    (input along x) rests at tan θ = F / (m g): started there it stays, and the saved inputs
    are F at every time; `equilibrium` finds the same angle."""
    p = dict(m=0.8, g=9.81, l=1.5)
    force = 3.0
    angle = np.arctan2(force, p["m"] * p["g"])
    system = jaxdyn.Constrained(
        jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                                            lambda q, p: p["m"] * p["g"] * q[1]), [0]),
        holonomic=lambda q, p: jnp.array([q @ q - p["l"] ** 2]))
    rest = jnp.array([p["l"] * np.sin(angle), -p["l"] * np.cos(angle)])
    ts = jnp.linspace(0.0, 2.0, 5)
    solution = jaxdyn.simulate(system, rest, jnp.zeros(2), p, t1=2.0, ts=ts,
                               inputs=jnp.array([force]), save=("q", "inputs"), rtol=1e-10,
                               atol=1e-10)
    np.testing.assert_allclose(solution.q, np.broadcast_to(rest, (5, 2)), atol=1e-9)
    np.testing.assert_allclose(solution.inputs, np.full((5, 1), force))
    found = jaxdyn.equilibrium(system, jnp.array([0.3, -1.4]), p, jnp.array([force]))
    np.testing.assert_allclose(found.q, rest, atol=1e-10)
