"""`jaxdyn.Lagrangian`: the equations of motion against independent oracles.

Oracles: closed forms, textbook equations of motion (solved with NumPy),
sympy.physics.mechanics, and NumPy linear algebra. All comparisons are in float64 to 1e-10
relative unless the test is about float32.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sm
import sympy.physics.mechanics as me

import jaxdyn
from jaxdyn._dynamics import straight_line_size

from helpers import (
    BEAD_ON_HOOP,
    BEAD_PARAMS,
    DOUBLE_PENDULUM,
    DRIVEN_SUPPORT,
    DRIVEN_SUPPORT_PARAMS,
    ELASTIC_PENDULUM,
    PENDULUM,
    SYSTEM_IDS,
    SYSTEMS,
    WHEELS_BAR,
    assert_close,
    driven_support_acceleration,
    sample_states,
    tree_allclose,
)

RTOL = 1e-10
NUM_STATES = 5


def _times(num, seed=1):
    return np.random.default_rng(seed).uniform(-3.0, 3.0, num)


# ---------------------------------------------------------------------------------------------
# Reference systems (harmonic oscillator, pendulum, double pendulum, 25.1, 25.2, 25.3)
# ---------------------------------------------------------------------------------------------


@functools.cache
def _quantities(name):
    """Every method of one reference system, evaluated once (jit-compiled, broadcast over
    NUM_STATES random states), together with the states and a random q̈ for the residual."""
    system = SYSTEMS[SYSTEM_IDS.index(name)]
    qs, qds = sample_states(system, NUM_STATES)
    ts = _times(NUM_STATES)
    qdds = np.random.default_rng(3).normal(size=qs.shape)
    true_qdds = np.stack([system.accelerations(q, qd, system.params) for q, qd in zip(qs, qds)])
    dynamics = system.dynamics

    @jax.jit
    def evaluate(ts, qs, qds, true_qdds, qdds, p):
        return dict(
            accelerations=dynamics.accelerations(ts, qs, qds, p),
            mass_matrix=dynamics.mass_matrix(ts, qs, qds, p),
            forcing=dynamics.forcing(ts, qs, qds, p),
            residual_true=dynamics.residual(ts, qs, qds, true_qdds, p),
            residual=dynamics.residual(ts, qs, qds, qdds, p),
            momentum=dynamics.momentum(ts, qs, qds, p),
            kinetic_energy=dynamics.kinetic_energy(ts, qs, qds, p),
            potential_energy=dynamics.potential_energy(ts, qs, qds, p),
            lagrangian=dynamics.lagrangian(ts, qs, qds, p),
            energy=dynamics.energy(ts, qs, qds, p),
            jacobi_integral=dynamics.jacobi_integral(ts, qs, qds, p),
        )

    values = evaluate(ts, qs, qds, true_qdds, qdds, system.params)
    values = {key: np.asarray(value) for key, value in values.items()}
    return system, qs, qds, true_qdds, qdds, values


@pytest.mark.parametrize("name", SYSTEM_IDS)
def test_accelerations_match_reference(name):
    system, qs, qds, true_qdds, _, values = _quantities(name)
    for q, qd, qdd, expected in zip(qs, qds, values["accelerations"], true_qdds):
        scale = np.max(np.abs(expected))
        assert_close(qdd, expected, rtol=RTOL, atol=RTOL * scale, err_msg=f"q={q}, qd={qd}")


@pytest.mark.parametrize("name", SYSTEM_IDS)
def test_mass_matrix_symmetric_positive_definite_and_matches_reference(name):
    system, qs, _, _, _, values = _quantities(name)
    for q, mass_matrix in zip(qs, values["mass_matrix"]):
        expected = system.mass_matrix(q, system.params)
        assert_close(mass_matrix, expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))
        # Symmetric up to round-off (the two triangles come from different derivative
        # passes, so exact bitwise symmetry is not expected).
        assert_close(mass_matrix, mass_matrix.T, rtol=0, atol=1e-14 * np.max(np.abs(expected)))
        assert np.all(np.linalg.eigvalsh(mass_matrix) > 0)


@pytest.mark.parametrize("name", SYSTEM_IDS)
def test_forcing_is_mass_matrix_times_reference_accelerations(name):
    system, qs, _, true_qdds, _, values = _quantities(name)
    for q, forcing, true_qdd in zip(qs, values["forcing"], true_qdds):
        expected = system.mass_matrix(q, system.params) @ true_qdd
        assert_close(forcing, expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))


@pytest.mark.parametrize("name", SYSTEM_IDS)
def test_residual(name):
    """Zero on the true motion; M (q̈ − q̈_true) on any other q̈ (the residual is linear in
    q̈ with the mass matrix as its coefficient)."""
    system, qs, _, true_qdds, qdds, values = _quantities(name)
    for i, q in enumerate(qs):
        mass_matrix = system.mass_matrix(q, system.params)
        # Scale of the terms that cancel in the residual, for an absolute tolerance.
        scale = np.max(np.abs(mass_matrix)) * max(1.0, np.max(np.abs(true_qdds[i])))
        assert_close(values["residual_true"][i], np.zeros(system.n), rtol=0, atol=RTOL * scale)
        assert_close(values["residual"][i], mass_matrix @ (qdds[i] - true_qdds[i]), rtol=1e-9,
                     atol=RTOL * scale)


@pytest.mark.parametrize("name", SYSTEM_IDS)
def test_momentum_and_energies(name):
    """For these natural systems T = ½ q̇ᵀ M q̇, so p = M q̇, and Jacobi's integral is T + V."""
    system, qs, qds, _, _, values = _quantities(name)
    p = system.params
    for i, (q, qd) in enumerate(zip(qs, qds)):
        mass_matrix = system.mass_matrix(q, p)
        kinetic = 0.5 * qd @ mass_matrix @ qd
        energy = system.energy(q, qd, p)
        potential = energy - kinetic
        scale = max(abs(kinetic), abs(potential), 1.0)
        assert_close(values["momentum"][i], mass_matrix @ qd, rtol=RTOL,
                     atol=RTOL * np.max(np.abs(mass_matrix)))
        for key, expected in [
            ("kinetic_energy", kinetic),
            ("potential_energy", potential),
            ("lagrangian", kinetic - potential),
            ("energy", energy),
            ("jacobi_integral", energy),
        ]:
            assert_close(values[key][i], expected, rtol=0, atol=RTOL * scale, err_msg=key)


def test_wheels_bar_closed_form_acceleration():
    """25.1: a = (2P + Q) g r² sin β / ((2P + Q) r² + 2 J g), for several parameter sets."""
    rng = np.random.default_rng(5)
    for _ in range(4):
        p = {
            "P": rng.uniform(5, 50), "Q": rng.uniform(5, 50), "J": rng.uniform(0.1, 2.0),
            "r": rng.uniform(0.1, 1.0), "g": 9.81, "beta": rng.uniform(0.05, 1.5),
        }
        P, Q, J, r, g, beta = (p[k] for k in ("P", "Q", "J", "r", "g", "beta"))
        expected = (2 * P + Q) * g * r**2 * np.sin(beta) / ((2 * P + Q) * r**2 + 2 * J * g)
        a = WHEELS_BAR.dynamics.accelerations(0.0, np.array([0.3]), np.array([1.1]), p)
        assert_close(a, np.array([expected]), rtol=RTOL)


def test_harmonic_oscillator_closed_form():
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
                               lambda q, p: 0.5 * p["k"] * q[0] ** 2)
    for m, k, q, qd in [(1.0, 1.0, 1.0, 0.0), (2.5, 7.0, -0.3, 4.0), (0.1, 30.0, 2.0, -1.0)]:
        a = system.accelerations(0.0, np.array([q]), np.array([qd]), {"m": m, "k": k})
        assert_close(a, np.array([-k / m * q]), rtol=RTOL)


# ---------------------------------------------------------------------------------------------
# Double pendulum against sympy.physics.mechanics
# ---------------------------------------------------------------------------------------------


@functools.cache
def _sympy_double_pendulum():
    """Mass matrix and forcing of the double pendulum of two particles, by LagrangesMethod,
    lambdified to NumPy as functions of (q1, q2, u1, u2, m1, m2, l1, l2, g)."""
    q1, q2 = me.dynamicsymbols("q1 q2")
    q1d, q2d = me.dynamicsymbols("q1 q2", 1)
    m1, m2, l1, l2, g = sm.symbols("m1 m2 l1 l2 g", positive=True)
    frame = me.ReferenceFrame("N")
    origin = me.Point("O")
    origin.set_vel(frame, 0)
    point1 = origin.locatenew("P1", l1 * sm.sin(q1) * frame.x - l1 * sm.cos(q1) * frame.y)
    point2 = point1.locatenew("P2", l2 * sm.sin(q2) * frame.x - l2 * sm.cos(q2) * frame.y)
    point1.set_vel(frame, point1.pos_from(origin).dt(frame))
    point2.set_vel(frame, point2.pos_from(origin).dt(frame))
    particle1 = me.Particle("pa1", point1, m1)
    particle2 = me.Particle("pa2", point2, m2)
    particle1.potential_energy = m1 * g * point1.pos_from(origin).dot(frame.y)
    particle2.potential_energy = m2 * g * point2.pos_from(origin).dot(frame.y)
    lagrangian = me.Lagrangian(frame, particle1, particle2)
    method = me.LagrangesMethod(lagrangian, [q1, q2])
    method.form_lagranges_equations()

    th1, th2, u1, u2 = sm.symbols("th1 th2 u1 u2")

    def to_symbols(expr):
        expr = me.msubs(expr, {q1d: u1, q2d: u2})  # speeds first, then coordinates
        return me.msubs(expr, {q1: th1, q2: th2})

    args = (th1, th2, u1, u2, m1, m2, l1, l2, g)
    mass_matrix = sm.lambdify(args, to_symbols(method.mass_matrix), "numpy")
    forcing = sm.lambdify(args, to_symbols(method.forcing), "numpy")

    def evaluate(q, qd, p):
        values = (*q, *qd, p["m1"], p["m2"], p["l1"], p["l2"], p["g"])
        return (np.asarray(mass_matrix(*values), np.float64),
                np.asarray(forcing(*values), np.float64).reshape(2))

    return evaluate


def test_double_pendulum_against_sympy():
    sympy_equations = _sympy_double_pendulum()
    dynamics = DOUBLE_PENDULUM.dynamics
    mass_matrix_and_forcing = jax.jit(
        lambda q, qd, p: (dynamics.mass_matrix(0.0, q, qd, p), dynamics.forcing(0.0, q, qd, p),
                          dynamics.accelerations(0.0, q, qd, p))
    )
    qs, qds = sample_states(DOUBLE_PENDULUM, 6, seed=11)
    rng = np.random.default_rng(12)
    for q, qd in zip(qs, qds):
        p = {"m1": rng.uniform(0.5, 2), "m2": rng.uniform(0.5, 2), "l1": rng.uniform(0.5, 2),
             "l2": rng.uniform(0.5, 2), "g": 9.81}
        expected_mass, expected_forcing = sympy_equations(q, qd, p)
        expected_qdd = np.linalg.solve(expected_mass, expected_forcing)
        mass_matrix, forcing, qdd = mass_matrix_and_forcing(q, qd, p)
        assert_close(mass_matrix, expected_mass, rtol=RTOL,
                     atol=RTOL * np.max(np.abs(expected_mass)))
        assert_close(forcing, expected_forcing, rtol=RTOL,
                     atol=RTOL * np.max(np.abs(expected_forcing)))
        assert_close(qdd, expected_qdd, rtol=RTOL, atol=RTOL * np.max(np.abs(expected_qdd)))
        # The registry's closed form agrees with sympy too (it is used as an oracle elsewhere).
        assert_close(DOUBLE_PENDULUM.accelerations(q, qd, p), expected_qdd, rtol=1e-11,
                     atol=1e-11 * np.max(np.abs(expected_qdd)))


# ---------------------------------------------------------------------------------------------
# Rheonomic systems, time-dependent forces, dissipation
# ---------------------------------------------------------------------------------------------

def test_rheonomic_driven_support_pendulum():
    p = DRIVEN_SUPPORT_PARAMS
    m, l, g, A, w = p["m"], p["l"], p["g"], p["A"], p["w"]
    rng = np.random.default_rng(21)
    for _ in range(NUM_STATES):
        t, theta, theta_d = rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3)
        q, qd = np.array([theta]), np.array([theta_d])
        qdd = DRIVEN_SUPPORT.accelerations(t, q, qd, p)
        expected = driven_support_acceleration(t, theta, p)
        assert_close(qdd, np.array([expected]), rtol=RTOL, atol=RTOL * (g + A * w**2) / l)
        # ∂L/∂θ̇ = m l² θ̇ + m l ẏ_s sin θ: depends on t explicitly.
        ys_dot = -A * w * np.sin(w * t)
        momentum = m * l**2 * theta_d + m * l * ys_dot * np.sin(theta)
        assert_close(DRIVEN_SUPPORT.momentum(t, q, qd, p), np.array([momentum]), rtol=RTOL,
                     atol=RTOL * m * l**2)
        # h = θ̇ ∂L/∂θ̇ − L = ½ m l² θ̇² − ½ m ẏ_s² + m g (y_s − l cos θ)  (≠ T + V here).
        ys = A * np.cos(w * t)
        jacobi = 0.5 * m * l**2 * theta_d**2 - 0.5 * m * ys_dot**2 + m * g * (
            ys - l * np.cos(theta)
        )
        assert_close(DRIVEN_SUPPORT.jacobi_integral(t, q, qd, p), jacobi, rtol=0,
                     atol=RTOL * 10 * m * g * l)
        # The residual vanishes on the hand-derived motion.
        assert_close(DRIVEN_SUPPORT.residual(t, q, qd, np.array([expected]), p), np.zeros(1),
                     rtol=0, atol=RTOL * m * l * (g + A * w**2))


def test_rheonomic_bead_on_rotating_hoop():
    """θ̈ = (Ω² cos θ − g/R) sin θ; h = ½ m R² (θ̇² − Ω² sin²θ) − m g R cos θ while
    T + V = ½ m R² (θ̇² + Ω² sin²θ) − m g R cos θ."""
    p = BEAD_PARAMS
    m, R, g, W = p["m"], p["R"], p["g"], p["Omega"]
    rng = np.random.default_rng(22)
    for _ in range(NUM_STATES):
        t, theta, theta_d = rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-3, 3)
        q, qd = np.array([theta]), np.array([theta_d])
        expected = (W**2 * np.cos(theta) - g / R) * np.sin(theta)
        scale = W**2 + g / R
        assert_close(BEAD_ON_HOOP.accelerations(t, q, qd, p), np.array([expected]), rtol=RTOL,
                     atol=RTOL * scale)
        assert_close(BEAD_ON_HOOP.mass_matrix(t, q, qd, p), np.array([[m * R**2]]), rtol=RTOL)
        energy_scale = m * R**2 * scale
        jacobi = 0.5 * m * R**2 * (theta_d**2 - W**2 * np.sin(theta) ** 2) - m * g * R * np.cos(
            theta
        )
        energy = 0.5 * m * R**2 * (theta_d**2 + W**2 * np.sin(theta) ** 2) - m * g * R * np.cos(
            theta
        )
        assert_close(BEAD_ON_HOOP.jacobi_integral(t, q, qd, p), jacobi, rtol=0,
                     atol=RTOL * energy_scale)
        assert_close(BEAD_ON_HOOP.energy(t, q, qd, p), energy, rtol=0, atol=RTOL * energy_scale)


def test_time_dependent_generalized_force():
    """Driven, damped oscillator m q̈ + c q̇ + k q = F cos ωt, with the force as Q(t, q, qd, p)
    and the damping from a Rayleigh function D(t, q, qd, p) = ½ c q̇²."""
    system = jaxdyn.Lagrangian(
        lambda t, q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
        lambda t, q, p: 0.5 * p["k"] * q[0] ** 2,
        forces=lambda t, q, qd, p: jnp.stack([p["F"] * jnp.cos(p["w"] * t)]),
        dissipation=lambda t, q, qd, p: 0.5 * p["c"] * qd[0] ** 2,
        time_dependent=True,
    )
    p = {"m": 1.5, "k": 6.0, "F": 2.0, "w": 1.7, "c": 0.3}
    rng = np.random.default_rng(23)
    for _ in range(NUM_STATES):
        t, q, qd = rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-2, 2)
        expected = (p["F"] * np.cos(p["w"] * t) - p["c"] * qd - p["k"] * q) / p["m"]
        qdd = system.accelerations(t, np.array([q]), np.array([qd]), p)
        assert_close(qdd, np.array([expected]), rtol=RTOL, atol=RTOL * 10)


def test_rayleigh_dissipation_two_dof():
    """Two masses in a chain, springs k1 (wall–1), k2 (1–2) and dampers c1, c2 alike:
    D = ½ c1 q̇1² + ½ c2 (q̇2 − q̇1)² gives the force −C q̇."""
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * p["m1"] * qd[0] ** 2 + 0.5 * p["m2"] * qd[1] ** 2,
        lambda q, p: 0.5 * p["k1"] * q[0] ** 2 + 0.5 * p["k2"] * (q[1] - q[0]) ** 2,
        dissipation=lambda q, qd, p: 0.5 * p["c1"] * qd[0] ** 2
        + 0.5 * p["c2"] * (qd[1] - qd[0]) ** 2,
    )
    p = {"m1": 1.0, "m2": 2.0, "k1": 3.0, "k2": 5.0, "c1": 0.4, "c2": 0.9}
    M = np.diag([p["m1"], p["m2"]])
    K = np.array([[p["k1"] + p["k2"], -p["k2"]], [-p["k2"], p["k2"]]])
    C = np.array([[p["c1"] + p["c2"], -p["c2"]], [-p["c2"], p["c2"]]])
    rng = np.random.default_rng(24)
    for _ in range(NUM_STATES):
        q, qd = rng.normal(size=2), rng.normal(size=2)
        expected = np.linalg.solve(M, -K @ q - C @ qd)
        assert_close(system.accelerations(0.0, q, qd, p), expected, rtol=RTOL, atol=1e-12)
        # Dissipation is not part of the energy or of Jacobi's integral.
        energy = 0.5 * qd @ M @ qd + 0.5 * q @ K @ q
        assert_close(system.energy(0.0, q, qd, p), energy, rtol=RTOL)
        assert_close(system.jacobi_integral(0.0, q, qd, p), energy, rtol=RTOL)


# ---------------------------------------------------------------------------------------------
# Sizes: n = 1 (above) and a chain of six nonlinear oscillators with a full mass matrix
# ---------------------------------------------------------------------------------------------


def _chain_params(n=6, seed=31):
    rng = np.random.default_rng(seed)
    factor = rng.normal(size=(n, n))
    return {
        "A": factor @ factor.T + n * np.eye(n),  # SPD inertia, fully coupled
        "k": rng.uniform(1, 5, n + 1),
        "beta": 0.7,
    }


def _chain_T(q, qd, p):
    return 0.5 * qd @ p["A"] @ qd


def _chain_V(q, p):
    """Fermi–Pasta–Ulam-β chain between two walls: springs on d_j = q_j − q_{j−1}."""
    zero = jnp.zeros((1,), q.dtype)
    d = jnp.diff(jnp.concatenate([zero, q, zero]))
    return jnp.sum(0.5 * p["k"] * d**2 + 0.25 * p["beta"] * d**4)


CHAIN = jaxdyn.Lagrangian(_chain_T, _chain_V)


def _chain_reference(q, qd, p):
    d = np.diff(np.concatenate([[0.0], q, [0.0]]))
    s = p["k"] * d + p["beta"] * d**3  # spring tensions
    grad_V = s[:-1] - s[1:]
    return np.linalg.solve(p["A"], -grad_V)


@pytest.mark.parametrize("n", [6, 40])
def test_chains_of_nonlinear_oscillators(n):
    """Six coordinates run as straight-line code; forty as arrays, the straight-line attempt
    abandoned before its LDLᵀ factorisation (~40³/6 operations) is traced."""
    p = _chain_params(n)
    assert (straight_line_size(CHAIN, jnp.asarray(0.0), jnp.zeros(n), jnp.zeros(n), p)
            is None) == (n == 40)
    rng = np.random.default_rng(32)
    qs, qds = rng.normal(size=(NUM_STATES, n)), rng.normal(size=(NUM_STATES, n))

    @jax.jit
    def evaluate(q, qd, p):
        return (CHAIN.accelerations(0.0, q, qd, p), CHAIN.mass_matrix(0.0, q, qd, p),
                CHAIN.momentum(0.0, q, qd, p))

    qdd, mass_matrix, momentum = evaluate(qs, qds, p)
    for i, (q, qd) in enumerate(zip(qs, qds)):
        expected = _chain_reference(q, qd, p)
        assert_close(qdd[i], expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))
        assert_close(mass_matrix[i], p["A"], rtol=RTOL)
        assert_close(momentum[i], p["A"] @ qd, rtol=RTOL, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Broadcasting and JAX transformations
# ---------------------------------------------------------------------------------------------


def test_broadcasting_over_a_trajectory():
    """Methods accept stacked states: (k,) times with (k, n) coordinates, a scalar time with
    stacked states, and several leading axes. (Jit-compiled to keep the test fast; the
    broadcasting happens at trace time, identically to an eager call.)"""
    system = DOUBLE_PENDULUM
    dynamics = system.dynamics
    num = 7
    qs, qds = sample_states(system, num, seed=41)
    ts = _times(num)
    p = system.params
    expected_qdd = np.stack([system.accelerations(q, qd, p) for q, qd in zip(qs, qds)])
    expected_mass = np.stack([system.mass_matrix(q, p) for q in qs])
    expected_energy = np.array([system.energy(q, qd, p) for q, qd in zip(qs, qds)])

    @jax.jit
    def evaluate(ts, qs, qds, qdds, p):
        grid_qs = jnp.stack([qs, qs])
        grid_qds = jnp.stack([qds, qds])
        return dict(
            accelerations=dynamics.accelerations(ts, qs, qds, p),
            mass_matrix=dynamics.mass_matrix(ts, qs, qds, p),
            energy=dynamics.energy(ts, qs, qds, p),
            residual=dynamics.residual(ts, qs, qds, qdds, p),
            scalar_t=dynamics.accelerations(0.0, qs, qds, p),
            grid=dynamics.accelerations(jnp.zeros((1, num)), grid_qs, grid_qds, p),
        )

    values = evaluate(ts, qs, qds, expected_qdd, p)
    qdd_atol = RTOL * np.max(np.abs(expected_qdd))
    assert values["accelerations"].shape == (num, 2)
    assert_close(values["accelerations"], expected_qdd, rtol=RTOL, atol=qdd_atol)
    assert values["mass_matrix"].shape == (num, 2, 2)
    assert_close(values["mass_matrix"], expected_mass, rtol=RTOL, atol=1e-12)
    assert values["energy"].shape == (num,)
    assert_close(values["energy"], expected_energy, rtol=RTOL,
                 atol=RTOL * np.max(np.abs(expected_energy)))
    assert values["residual"].shape == (num, 2)
    assert_close(values["residual"], np.zeros_like(expected_qdd), rtol=0, atol=1e-9)
    assert_close(values["scalar_t"], expected_qdd, rtol=RTOL, atol=qdd_atol)
    assert values["grid"].shape == (2, num, 2)
    assert_close(values["grid"][1], expected_qdd, rtol=RTOL, atol=qdd_atol)


def test_broadcasting_eager_trajectory():
    """The plain (un-jitted) call on a stacked trajectory, as after a simulation."""
    system = PENDULUM
    qs, qds = sample_states(system, 4, seed=42)
    ts = _times(4)
    expected = np.stack([system.accelerations(q, qd, system.params) for q, qd in zip(qs, qds)])
    qdd = system.dynamics.accelerations(ts, qs, qds, system.params)
    assert_close(qdd, expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))
    energy = system.dynamics.energy(ts, qs, qds, system.params)
    assert_close(energy, [system.energy(q, qd, system.params) for q, qd in zip(qs, qds)],
                 rtol=RTOL)


def test_plain_and_jit_calls_match_reference():
    system = DOUBLE_PENDULUM
    accelerations = jax.jit(system.dynamics.accelerations)
    qs, qds = sample_states(system, 3, seed=51)
    for q, qd in zip(qs, qds):
        expected = system.accelerations(q, qd, system.params)
        atol = RTOL * np.max(np.abs(expected))
        assert_close(system.dynamics.accelerations(0.0, q, qd, system.params), expected,
                     rtol=RTOL, atol=atol)
        assert_close(accelerations(0.0, q, qd, system.params), expected, rtol=RTOL, atol=atol)


def test_vmap_over_states_matches_reference():
    system = ELASTIC_PENDULUM
    qs, qds = sample_states(system, 8, seed=52)
    ts = _times(8)
    accelerations = jax.jit(jax.vmap(system.dynamics.accelerations, in_axes=(0, 0, 0, None)))
    qdd = accelerations(ts, qs, qds, system.params)
    expected = np.stack([system.accelerations(q, qd, system.params) for q, qd in zip(qs, qds)])
    assert_close(qdd, expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))


def test_vmap_over_parameters_matches_reference():
    system = DOUBLE_PENDULUM
    rng = np.random.default_rng(53)
    num = 6
    batch = {
        "m1": rng.uniform(0.5, 2, num), "m2": rng.uniform(0.5, 2, num),
        "l1": rng.uniform(0.5, 2, num), "l2": rng.uniform(0.5, 2, num),
        "g": np.full(num, 9.81),
    }
    q, qd = np.array([0.4, -1.2]), np.array([0.9, 2.1])
    accelerations = jax.jit(jax.vmap(system.dynamics.accelerations, in_axes=(None, None, None, 0)))
    qdd = accelerations(0.0, q, qd, batch)
    assert qdd.shape == (num, 2)
    for i in range(num):
        p = {key: value[i] for key, value in batch.items()}
        expected = system.accelerations(q, qd, p)
        assert_close(qdd[i], expected, rtol=RTOL, atol=RTOL * np.max(np.abs(expected)))


def test_float32_is_an_explicit_option():
    """Float32 arrays in give float32 out (no silent promotion), accurate to float32 level."""
    system = DOUBLE_PENDULUM
    dynamics = system.dynamics
    qs, qds = sample_states(system, NUM_STATES, seed=61)
    p32 = {key: np.float32(value) for key, value in system.params.items()}
    q32, qd32 = qs.astype(np.float32), qds.astype(np.float32)
    t32 = np.zeros(NUM_STATES, np.float32)

    @jax.jit
    def evaluate(t, q, qd, p):
        return (dynamics.accelerations(t, q, qd, p), dynamics.mass_matrix(t, q, qd, p),
                dynamics.energy(t, q, qd, p))

    qdd, mass_matrix, energy = evaluate(t32, q32, qd32, p32)
    assert qdd.dtype == jnp.float32
    assert mass_matrix.dtype == jnp.float32
    assert energy.dtype == jnp.float32
    # One plain call as well, with a Python-float time.
    assert dynamics.accelerations(0.0, q32[0], qd32[0], p32).dtype == jnp.float32
    # Reference in float64 at the float32-rounded state and parameters.
    p64 = {key: float(value) for key, value in p32.items()}
    for i in range(NUM_STATES):
        q64, qd64 = q32[i].astype(np.float64), qd32[i].astype(np.float64)
        expected = system.accelerations(q64, qd64, p64)
        assert_close(qdd[i], expected, rtol=1e-5, atol=1e-5 * np.max(np.abs(expected)))
        assert_close(mass_matrix[i], system.mass_matrix(q64, p64), rtol=1e-5, atol=1e-6)
        expected_energy = system.energy(q64, qd64, p64)
        assert_close(energy[i], expected_energy, rtol=1e-5, atol=1e-5 * abs(expected_energy))


def test_tree_allclose_helper():
    """The comparison helper itself: structure, dtype and tolerance all count."""
    a = {"x": np.array([1.0, 2.0]), "y": np.array(3.0)}
    assert tree_allclose(a, {"x": np.array([1.0, 2.0 + 1e-13]), "y": np.array(3.0)})
    assert not tree_allclose(a, {"x": np.array([1.0, 2.1]), "y": np.array(3.0)})
    assert not tree_allclose(a, {"x": np.array([1.0, 2.0], np.float32), "y": np.array(3.0)})
    assert not tree_allclose(a, {"x": np.array([1.0, 2.0])})
