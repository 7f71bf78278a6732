"""Constraints (Lagrange's equations of the first kind) against closed forms, minimal-coordinate
models written independently, Euler's equations, conservation laws and finite differences."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_close

import jaxdyn

RNG = np.random.default_rng(3)
SIM = {"solver": diffrax.Tsit5(), "rtol": 1e-10, "atol": 1e-10}


# -- pendulum in Cartesian coordinates ----------------------------------------------------------

PENDULUM = {"m": 1.3, "l": 0.8, "g": 9.81}


def pendulum(stabilisation=jaxdyn.Projection(), redundant="error", twice=False):
    def kinetic(q, qd, p):
        return 0.5 * p["m"] * jnp.sum(qd**2)

    def potential(q, p):
        return p["m"] * p["g"] * q[1]

    def rod(q, p):
        row = q[0] ** 2 + q[1] ** 2 - p["l"] ** 2
        return jnp.stack([row, 2 * row]) if twice else jnp.stack([row])

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=rod,
                              stabilisation=stabilisation, redundant=redundant)


def pendulum_state(theta, omega, l=PENDULUM["l"]):
    """(q, q̇) on the circle for the angle θ from the downward vertical."""
    q = np.array([l * np.sin(theta), -l * np.cos(theta)])
    return q, l * omega * np.array([np.cos(theta), np.sin(theta)])


def test_pendulum_accelerations_and_tension_match_the_closed_form():
    system = pendulum()
    m, l, g = PENDULUM["m"], PENDULUM["l"], PENDULUM["g"]
    for theta, omega in RNG.uniform(-2, 2, (5, 2)):
        q, qd = pendulum_state(theta, omega)
        # θ̈ = −g/l sin θ; q̈ = l θ̈ (cos θ, sin θ) + l θ̇² (−sin θ, cos θ)
        theta_dd = -g / l * np.sin(theta)
        expected = l * theta_dd * np.array([np.cos(theta), np.sin(theta)]) + \
            l * omega**2 * np.array([-np.sin(theta), np.cos(theta)])
        assert_close(system.accelerations(0.0, q, qd, PENDULUM), expected, rtol=1e-12)
        # Cᵀλ = 2λ (x, y) is the rod's force on the bob; the tension is −2λl
        tension = m * l * omega**2 + m * g * np.cos(theta)
        lam = system.multipliers(0.0, q, qd, PENDULUM)
        assert_close(-2 * lam[0] * l, tension, rtol=1e-12)
        assert_close(system.constraint_forces(0.0, q, qd, PENDULUM), 2 * lam[0] * q,
                     rtol=1e-12)


def test_float32_is_an_explicit_option():
    """The same closed form in single precision, at single precision's tolerance."""
    system = pendulum()
    q, qd = (x.astype(np.float32) for x in pendulum_state(0.9, 1.3))
    g, l = PENDULUM["g"], PENDULUM["l"]
    accelerations = system.accelerations(np.float32(0.0), q, qd, PENDULUM)
    assert accelerations.dtype == np.float32
    theta_dd = -g / l * np.sin(0.9)
    expected = l * theta_dd * np.array([np.cos(0.9), np.sin(0.9)]) + \
        l * 1.3**2 * np.array([-np.sin(0.9), np.cos(0.9)])
    assert_close(np.asarray(accelerations, np.float64), expected, rtol=2e-5)


@pytest.mark.parametrize("stabilisation", [None, jaxdyn.Baumgarte(), jaxdyn.Projection()],
                         ids=["none", "baumgarte", "projection"])
def test_violation_over_a_long_horizon(stabilisation):
    """200 periods at a loose tolerance: without stabilisation the violation grows with the
    integration error; Baumgarte's keeps it at the local error, projection at round-off."""
    q0, u0 = pendulum_state(2.0, 0.0)
    sol = jaxdyn.simulate(pendulum(stabilisation), q0, u0, PENDULUM, t1=360.0,
                          ts=jnp.linspace(0, 360, 721), save=("q", "u", "constraints"),
                          solver=diffrax.Tsit5(), rtol=1e-6, atol=1e-6, max_steps=200_000)
    position = np.max(np.abs(sol.constraints.position_violation))
    velocity = np.max(np.abs(sol.constraints.velocity_violation))
    bound = {type(None): (1.0, 1.0), jaxdyn.Baumgarte: (1e-5, 1e-4),
             jaxdyn.Projection: (1e-14, 1e-13)}[type(stabilisation)]
    if stabilisation is None:
        assert position > 1e-3  # the drift these options are there to prevent
    else:
        assert position < bound[0] and velocity < bound[1], (position, velocity)


def test_gradient_through_a_constrained_simulation_matches_finite_differences():
    system = pendulum()

    def final_x(l):
        p = dict(PENDULUM, l=l)
        q0 = jnp.stack([l * jnp.sin(0.7), -l * jnp.cos(0.7)])
        sol = jaxdyn.simulate(system, q0, jnp.zeros(2), p, t1=1.5, **SIM)
        return sol.q[-1, 0]

    l = jnp.asarray(PENDULUM["l"])
    h = 1e-5
    fd = (final_x(l + h) - final_x(l - h)) / (2 * h)
    assert_close(jax.grad(final_x)(l), fd, rtol=1e-6)


def test_consistent_state_is_the_nearest_point_on_the_constraints():
    system = pendulum()
    q, u = system.consistent_state(0.0, np.array([0.3, -0.9]), np.array([0.4, 0.1]), PENDULUM)
    l = PENDULUM["l"]
    direction = np.array([0.3, -0.9]) / np.linalg.norm([0.3, -0.9])
    assert_close(q, l * direction, rtol=1e-12)  # radially onto the circle
    assert abs(np.dot(q, u)) < 1e-12  # tangent velocity
    tangent = np.array([-q[1], q[0]]) / l
    assert_close(u, np.dot([0.4, 0.1], tangent) * tangent, rtol=1e-12)


def test_consistent_state_that_cannot_be_reached_is_an_error():
    impossible = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2)),
        holonomic=lambda q, p: jnp.stack([jnp.sum(q**2) + 1.0]))
    with pytest.raises(RuntimeError, match="Could not place the state on the constraints"):
        impossible.consistent_state(0.0, np.array([0.3, 0.2]), np.zeros(2))


def test_redundant_constraints_error_or_least_squares():
    q, qd = pendulum_state(0.5, 1.0)
    with pytest.raises(RuntimeError, match=r"lost rank(.|\n)*redundant constraints"):
        pendulum(twice=True).accelerations(0.0, q, qd, PENDULUM)
    expected = pendulum().accelerations(0.0, q, qd, PENDULUM)
    relaxed = pendulum(twice=True, redundant="least_squares")
    assert_close(relaxed.accelerations(0.0, q, qd, PENDULUM), expected, rtol=1e-9)


def test_bad_constraint_functions_are_named():
    with pytest.raises(ValueError, match="holonomic constraint φ must return a 1-D array"):
        jaxdyn.Constrained(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2)),
                           holonomic=lambda q, p: jnp.sum(q**2)).accelerations(
            0.0, np.ones(2), np.zeros(2))
    with pytest.raises(ValueError, match=r"pfaffian constraint A must have shape \(m, n\)"):
        jaxdyn.Constrained(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2)),
                           pfaffian=lambda q, p: jnp.ones((1, 3))).accelerations(
            0.0, np.ones(2), np.zeros(2))
    with pytest.raises(ValueError, match="needs holonomic and/or pfaffian"):
        jaxdyn.Constrained(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2)))
    with pytest.raises(ValueError,
                       match="save names 'constraints', which Lagrangian does not record"):
        jaxdyn.simulate(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2)),
                        np.ones(2), np.zeros(2), t1=1.0, save=("q", "constraints"))


# -- four-bar linkage: a closed loop at a change point ---------------------------------------------

FOUR_BAR = {"l1": 1.0, "l2": 2.0, "l3": 1.5, "d": 1.5}


def four_bar():
    """Three uniform bars (unit mass per length) in absolute angles θ1, θ2, θ3, the loop closed
    by two holonomic constraints."""
    def kinetic(q, qd, p):
        l1, l2, l3 = p["l1"], p["l2"], p["l3"]
        t1, t2, _ = q
        crank = l1**3 / 6 * qd[0] ** 2
        rocker = l3**3 / 6 * qd[2] ** 2
        # coupler: centre velocity l1 θ̇1 e⊥(θ1) + l2/2 θ̇2 e⊥(θ2)
        v2 = (l1**2 * qd[0] ** 2 + l2**2 / 4 * qd[1] ** 2
              + l1 * l2 * qd[0] * qd[1] * jnp.cos(t1 - t2))
        return crank + rocker + 0.5 * l2 * v2 + l2**3 / 24 * qd[1] ** 2

    def loop(q, p):
        t1, t2, t3 = q
        return jnp.stack([
            p["l1"] * jnp.cos(t1) + p["l2"] * jnp.cos(t2) - p["d"] - p["l3"] * jnp.cos(t3),
            p["l1"] * jnp.sin(t1) + p["l2"] * jnp.sin(t2) - p["l3"] * jnp.sin(t3)])

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic), holonomic=loop)


def test_four_bar_at_its_change_point_is_an_error_naming_the_state():
    """l1 + l2 = d + l3: with all bars on the ground line C loses rank."""
    with pytest.raises(RuntimeError, match=r"lost rank(.|\n)*It happened at t = 0.0"):
        four_bar().accelerations(0.0, np.zeros(3), np.zeros(3), FOUR_BAR)
    # away from it, the loop closes and the mechanism moves with one degree of freedom
    q, u = four_bar().consistent_state(0.0, np.array([0.8, 0.3, 1.2]),
                                       np.array([1.0, 0.0, 0.0]), FOUR_BAR)
    assert np.all(np.isfinite(four_bar().accelerations(0.0, q, u, FOUR_BAR)))


# -- slider-crank against a minimal-coordinate model ---------------------------------------------

CRANK = {"r": 0.3, "L": 1.0, "m1": 0.5, "m2": 1.2, "m3": 2.0, "g": 9.81}


def slider_crank():
    """Crank (uniform, pivot at O, angle θ), connecting rod (uniform, angle φ below the axis),
    slider at x on the horizontal axis; coordinates (θ, φ, x) tied by the loop
    r cos θ + L cos φ − x = 0, r sin θ − L sin φ = 0."""
    def kinetic(q, qd, p):
        theta, phi, _ = q
        td, pd, xd = qd
        r, L = p["r"], p["L"]
        crank = p["m1"] * r**2 / 6 * td**2
        # rod centre: crank pin plus L/2 along the rod
        vx = -r * jnp.sin(theta) * td - L / 2 * jnp.sin(phi) * pd
        vy = r * jnp.cos(theta) * td - L / 2 * jnp.cos(phi) * pd
        rod = 0.5 * p["m2"] * (vx**2 + vy**2) + p["m2"] * L**2 / 24 * pd**2
        return crank + rod + 0.5 * p["m3"] * xd**2

    def potential(q, p):
        theta, phi, _ = q
        r, L = p["r"], p["L"]
        return p["g"] * (p["m1"] * r / 2 * jnp.sin(theta)
                         + p["m2"] * (r * jnp.sin(theta) - L / 2 * jnp.sin(phi)))

    def loop(q, p):
        theta, phi, x = q
        return jnp.stack([p["r"] * jnp.cos(theta) + p["L"] * jnp.cos(phi) - x,
                          p["r"] * jnp.sin(theta) - p["L"] * jnp.sin(phi)])

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=loop)


def crank_minimal():
    """The same mechanism in θ alone, φ(θ) = asin(r sin θ / L), x(θ) = r cos θ + L cos φ,
    its energies written from the bodies' positions (numpy-free closed form, differentiated by
    JAX only through the chain rule of these explicit positions)."""
    def positions(theta, p):
        r, L = p["r"], p["L"]
        phi = jnp.arcsin(r * jnp.sin(theta) / L)
        pin = jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)])
        rod = pin + L / 2 * jnp.stack([jnp.cos(phi), -jnp.sin(phi)])
        return phi, pin, rod, r * jnp.cos(theta) + L * jnp.cos(phi)

    def kinetic(q, qd, p):
        def tangent(f):
            return jax.jvp(lambda th: f(th), (q[0],), (qd[0],))[1]

        phid = tangent(lambda th: positions(th, p)[0])
        rodv = tangent(lambda th: positions(th, p)[2])
        xd = tangent(lambda th: positions(th, p)[3])
        return (p["m1"] * p["r"] ** 2 / 6 * qd[0] ** 2 + 0.5 * p["m2"] * jnp.sum(rodv**2)
                + p["m2"] * p["L"] ** 2 / 24 * phid**2 + 0.5 * p["m3"] * xd**2)

    def potential(q, p):
        _, pin, rod, _ = positions(q[0], p)
        return p["g"] * (p["m1"] * pin[1] / 2 + p["m2"] * rod[1])

    return jaxdyn.Lagrangian(kinetic, potential), positions


def test_slider_crank_matches_the_minimal_model_and_elimination():
    system = slider_crank()
    minimal, positions = crank_minimal()
    theta0, omega0 = 0.4, 2.0
    phi0, _, _, x0 = positions(theta0, CRANK)
    q0 = np.array([theta0, float(phi0), float(x0)])
    r, L = CRANK["r"], CRANK["L"]
    phid0 = r * np.cos(theta0) * omega0 / (L * np.cos(q0[1]))
    u0 = np.array([omega0, phid0, -r * np.sin(theta0) * omega0 - L * np.sin(q0[1]) * phid0])
    assert np.max(np.abs(system.velocity_violation(0.0, q0, u0, CRANK))) < 1e-14
    ts = jnp.linspace(0, 3.0, 31)
    constrained = jaxdyn.simulate(system, q0, u0, CRANK, t1=3.0, ts=ts, **SIM)
    reference = jaxdyn.simulate(minimal, q0[:1], np.array([omega0]), CRANK, t1=3.0, ts=ts,
                                **SIM)
    assert_close(constrained.q[:, 0], reference.q[:, 0], rtol=1e-7, atol=1e-8)
    assert_close(constrained.q[:, 2], positions(reference.q[:, 0], CRANK)[3], rtol=1e-7)
    # elimination: θ̇ independent, (φ̇, ẋ) dependent
    reduced = system.eliminate(0.0, q0, u0, CRANK)
    assert reduced.independent == (0,)
    for q, u in zip(constrained.q[::6], constrained.u[::6]):
        v = u[np.asarray(reduced.independent)]
        assert_close(reduced.speeds(0.0, q, v, CRANK), u, rtol=1e-9)
        full = system.accelerations(0.0, q, u, CRANK)
        assert_close(reduced.accelerations(0.0, q, v, CRANK), full[:1], rtol=1e-9)
    eliminated = jaxdyn.simulate(reduced, q0, u0[:1], CRANK, t1=3.0, ts=ts, **SIM)
    assert_close(eliminated.q, constrained.q, rtol=1e-7, atol=1e-8)


# -- bead on a rotating wire (rheonomic) -----------------------------------------------------------

def test_bead_on_a_rotating_wire():
    """A bead on a straight wire spinning at Ω about a vertical axis through it, in the
    horizontal plane: r̈ = Ω² r, and the wire pushes with N = 2 m Ω ṙ (Coriolis)."""
    m, omega = 0.7, 1.9
    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * jnp.sum(qd**2)),
        holonomic=lambda t, q, p: jnp.stack([-jnp.sin(omega * t) * q[0]
                                             + jnp.cos(omega * t) * q[1]]),
        time_dependent=True)
    for t, r, rd in RNG.uniform(0.1, 2.0, (4, 3)):
        e = np.array([np.cos(omega * t), np.sin(omega * t)])
        n = np.array([-np.sin(omega * t), np.cos(omega * t)])
        q, qd = r * e, rd * e + r * omega * n
        # (r̈ − rΩ²) e + 2ṙΩ n with r̈ = Ω² r
        expected = 2 * rd * omega * n
        assert_close(system.accelerations(t, q, qd), expected, rtol=1e-12, atol=1e-12)
        assert_close(system.multipliers(t, q, qd)[0], 2 * m * omega * rd, rtol=1e-12)
    sol = jaxdyn.simulate(system, np.array([0.5, 0.0]), np.array([0.0, 0.5 * omega]), t1=1.0,
                          **SIM)
    r_final = np.linalg.norm(sol.q[-1])
    assert_close(r_final, 0.5 * np.cosh(omega * 1.0), rtol=1e-8)


# -- a free rigid body in unit-quaternion coordinates (M alone singular) -------------------------

J = np.array([1.0, 2.0, 3.5])


def _e_matrix(quaternion):
    w, x, y, z = quaternion
    return jnp.array([[-x, -y, -z], [w, -z, y], [z, w, -x], [-y, x, w]])


def quaternion_body():
    def kinetic(q, qd, p):
        omega = 2 * _e_matrix(q).T @ qd  # body angular velocity, exact for |q| = 1
        return 0.5 * jnp.sum(J * omega**2)

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic),
                              holonomic=lambda q, p: jnp.stack([jnp.sum(q**2) - 1.0]))


def test_free_body_in_quaternions_follows_eulers_equations():
    system = quaternion_body()
    q = RNG.normal(size=4)
    q /= np.linalg.norm(q)
    omega = RNG.normal(size=3)
    qd = 0.5 * np.asarray(_e_matrix(q)) @ omega
    # M = 4 E J Eᵀ is singular (rank 3): the constraint makes the system regular
    m = jaxdyn.Lagrangian(system.dynamics.kinetic).mass_matrix(0.0, q, qd)
    assert np.linalg.matrix_rank(np.asarray(m)) == 3
    omega_dot = (np.cross(J * omega, omega)) / J  # Euler: J ω̇ = (Jω) × ω
    expected = 0.5 * np.asarray(_e_matrix(qd)) @ omega + 0.5 * np.asarray(_e_matrix(q)) @ \
        omega_dot
    assert_close(system.accelerations(0.0, q, qd), expected, rtol=1e-11, atol=1e-12)
    sol = jaxdyn.simulate(system, q, qd, t1=5.0, ts=jnp.linspace(0, 5, 11), **SIM)
    energy = system.energy(sol.ts, sol.q, sol.u)
    assert_close(energy, np.full(energy.shape, energy[0]), rtol=1e-9)
    # the angular momentum in space, R (J ω), is conserved
    from jaxdyn.rotations import quaternion as rotation_of
    momenta = [np.asarray(rotation_of(qk)) @ (J * (2 * np.asarray(_e_matrix(qk)).T @ qdk))
               for qk, qdk in zip(sol.q, sol.u)]
    assert_close(np.array(momenta), np.tile(momenta[0], (len(momenta), 1)), rtol=1e-8)


# -- Chaplygin sleigh (Pfaffian) -----------------------------------------------------------------

SLEIGH = {"m": 2.0, "I": 0.3, "a": 0.4}


def sleigh():
    """q = (x, y, θ) of the centre of mass; the knife edge at a behind it along the body axis
    cannot slide sideways: −sin θ ẋ + cos θ ẏ − a θ̇ = 0."""
    def kinetic(q, qd, p):
        return 0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * p["I"] * qd[2] ** 2

    def knife(q, p):
        return jnp.stack([jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), -p["a"]])])

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic), pfaffian=knife)


def test_chaplygin_sleigh_matches_its_closed_form():
    """In the body's speeds v (forward) and ω: v̇ = a ω², ω̇ = −m a v ω / (I + m a²), and the
    knife's sideways force is λ = m (a ω̇ + v ω)."""
    system = sleigh()
    m, inertia, a = SLEIGH["m"], SLEIGH["I"], SLEIGH["a"]
    for theta, v, omega in RNG.uniform(-1.5, 1.5, (4, 3)):
        e, n = np.array([np.cos(theta), np.sin(theta)]), np.array([-np.sin(theta),
                                                                   np.cos(theta)])
        q = np.array([0.2, -0.1, theta])
        qd = np.concatenate([v * e + a * omega * n, [omega]])
        v_dot, omega_dot = a * omega**2, -m * a * v * omega / (inertia + m * a**2)
        # d/dt (v e + a ω n) = v̇ e + v ω n + a ω̇ n − a ω² e
        expected = np.concatenate([(v_dot - a * omega**2) * e + (v * omega + a * omega_dot) * n,
                                   [omega_dot]])
        assert_close(system.accelerations(0.0, q, qd, SLEIGH), expected, rtol=1e-12,
                     atol=1e-12)
        assert_close(system.multipliers(0.0, q, qd, SLEIGH)[0], m * (a * omega_dot + v * omega),
                     rtol=1e-12, atol=1e-12)
    # elimination gives the same motion in two independent speeds; energy is conserved
    q0, u0 = np.array([0.0, 0.0, 0.3]), np.array([np.cos(0.3), np.sin(0.3), 0.0])
    u0 = np.asarray(system.consistent_state(0.0, q0, u0 + np.array([0, 0, 0.8]), SLEIGH)[1])
    reduced = system.eliminate(0.0, q0, u0, SLEIGH)
    full = jaxdyn.simulate(system, q0, u0, SLEIGH, t1=4.0, ts=jnp.linspace(0, 4, 9), **SIM)
    short = jaxdyn.simulate(reduced, q0, u0[np.asarray(reduced.independent)], SLEIGH, t1=4.0,
                            ts=jnp.linspace(0, 4, 9), **SIM)
    assert_close(short.q, full.q, rtol=1e-8, atol=1e-9)
    energy = system.energy(full.ts, full.q, full.u, SLEIGH)
    assert_close(energy, np.full(energy.shape, energy[0]), rtol=1e-9)


def test_a_closed_loop_of_joints_matches_the_four_bar_in_absolute_angles():
    """The four-bar as a chain of three revolute links whose tip is pinned to the ground point D
    (`Constrained(ArticulatedBody(tree), holonomic=...)`, relative angles) against the
    Lagrangian four-bar above (absolute angles): the same accelerations."""
    l1, l2, l3, d = (FOUR_BAR[k] for k in ("l1", "l2", "l3", "d"))

    def bar(name, length, parent=None, offset=0.0):
        return jaxdyn.Link(name, jaxdyn.Revolute((0, 0, 1)), parent=parent,
                           translation=(offset, 0.0, 0.0), mass=length,
                           com=(length / 2, 0.0, 0.0),
                           inertia=np.diag([0.0, 1.0, 1.0]) * length**3 / 12)

    tree = jaxdyn.RigidBodyTree([bar("crank", l1), bar("coupler", l2, "crank", l1),
                                 bar("rocker", l3, "coupler", l2)], gravity=np.zeros(3))

    def pinned(q, p):
        rotation, origin = tree.link_poses(0.0, q, p)
        tip = origin[2] + rotation[2] @ jnp.array([l3, 0.0, 0.0])
        return tip[:2] - jnp.array([d, 0.0])

    loop = jaxdyn.Constrained(jaxdyn.ArticulatedBody(tree), holonomic=pinned)
    reference = four_bar()
    q_abs, u_abs = reference.consistent_state(0.0, np.array([0.8, 0.3, 1.2]),
                                              np.array([1.0, 0.0, 0.0]), FOUR_BAR)
    to_relative = np.array([[1, 0, 0], [-1, 1, 0], [0, -1, 1]])  # θ3 + π − θ2 for the rocker
    q_rel = to_relative @ np.asarray(q_abs) + np.array([0.0, 0.0, np.pi])
    u_rel = to_relative @ np.asarray(u_abs)
    assert np.max(np.abs(loop.position_violation(0.0, q_rel, u_rel))) < 1e-12
    expected = to_relative @ np.asarray(reference.accelerations(0.0, q_abs, u_abs, FOUR_BAR))
    assert_close(loop.accelerations(0.0, q_rel, u_rel), expected, rtol=1e-10, atol=1e-12)


# -- rolling disc as Pfaffian constraints, against sympy's KanesMethod ----------------------------

DISC = {"m": 1.5, "r": 0.4, "g": 9.81}


def _disc_frames(q):
    """R_N←D = Rz(ψ) Rx(θ) Ry(φ) (heading, lean, spin), and the lean frame's z axis."""
    from jaxdyn.rotations import rotation_x, rotation_y, rotation_z

    lean = rotation_z(q[2]) @ rotation_x(q[3])
    return lean @ rotation_y(q[4]), lean[:, 2]


def rolling_disc_pfaffian():
    """q = (x, y, ψ, θ, φ) with (x, y) the contact point, q̇ as speeds (a `Lagrangian` of the
    disc's energies); the disc's material point at the contact has no horizontal velocity:
    two Pfaffian rows A(q) q̇ = 0, A = ∂v_P/∂q̇."""
    def centre(q, p):
        return jnp.concatenate([q[:2], jnp.zeros(1)]) + p["r"] * _disc_frames(q)[1]

    def omega_body(q, qd):
        rotation, rate = jax.jvp(lambda q: _disc_frames(q)[0], (q,), (qd,))
        skew = rotation.T @ rate
        return jnp.stack([skew[2, 1], skew[0, 2], skew[1, 0]])

    def kinetic(q, qd, p):
        v = jax.jvp(lambda q: centre(q, p), (q,), (qd,))[1]
        w = omega_body(q, qd)
        inertia = p["m"] * p["r"] ** 2 * jnp.array([0.25, 0.5, 0.25])
        return 0.5 * p["m"] * jnp.sum(v**2) + 0.5 * jnp.sum(inertia * w**2)

    def potential(q, p):
        return p["m"] * p["g"] * centre(q, p)[2]

    def contact_velocity(q, qd, p):
        v = jax.jvp(lambda q: centre(q, p), (q,), (qd,))[1]
        rotation = _disc_frames(q)[0]
        w = rotation @ omega_body(q, qd)  # in the ground's axes
        return v + jnp.cross(w, -p["r"] * _disc_frames(q)[1])

    def no_slip(q, p):
        return jax.jacfwd(lambda qd: contact_velocity(q, qd, p)[:2])(jnp.zeros_like(q))

    return jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), pfaffian=no_slip), centre


def test_rolling_disc_as_pfaffian_constraints_matches_sympy_kanes_method():
    """q̈ of the multiplier form, mapped to the speeds of sympy's model (u1 = θ̇, u3 = ψ̇ cos θ,
    u2 = φ̇ + u3 tan θ, differentiated by hand), against KanesMethod's u̇ = M⁻¹ f."""
    from sympy_rolling_disc import sympy_rolling_disc

    mass, forcing, rates, to_args = sympy_rolling_disc()
    system, centre = rolling_disc_pfaffian()
    for _ in range(3):
        q = np.concatenate([RNG.uniform(-1, 1, 3), RNG.uniform(-0.6, 0.6, 1),
                            RNG.uniform(-1, 1, 1)])
        u = RNG.uniform(-2, 2, 3)
        args = to_args(q, u, DISC)
        qd = np.asarray(rates(*args), float).ravel()
        udot = np.linalg.solve(np.asarray(mass(*args), float),
                               np.asarray(forcing(*args), float).ravel())
        assert np.max(np.abs(system.velocity_violation(0.0, q, qd, DISC))) < 1e-12
        qdd = np.asarray(system.accelerations(0.0, q, qd, DISC))
        theta, theta_d, psi_d = q[3], qd[3], qd[2]
        u3_dot = qdd[2] * np.cos(theta) - psi_d * theta_d * np.sin(theta)
        u2_dot = qdd[4] + u3_dot * np.tan(theta) + u[2] * theta_d / np.cos(theta) ** 2
        assert_close(np.array([qdd[3], u2_dot, u3_dot]), udot, rtol=1e-10, atol=1e-10)
        # the multipliers are the friction force at the contact: m a_G (horizontal part)
        a_centre = jax.jvp(lambda q, qd: jax.jvp(lambda q: centre(q, DISC), (q,), (qd,))[1],
                           (jnp.asarray(q), jnp.asarray(qd)),
                           (jnp.asarray(qd), jnp.asarray(qdd)))[1]
        assert_close(system.multipliers(0.0, q, qd, DISC), DISC["m"] * a_centre[:2],
                     rtol=1e-10, atol=1e-10)


def test_forward_mode_through_a_projected_solve():
    """diffrax's ForwardMode adjoint through the projection-wrapped solver: the derivative of
    a bead's position on a circle of radius l with respect to l, against a central difference
    (reverse mode through the projection: test_gradient_through_a_constrained_simulation_…)."""
    def kinetic(q, qd, p):
        return 0.5 * qd @ qd

    def potential(q, p):
        return 9.81 * q[1]

    def circle(q, p):
        return jnp.stack([q @ q - p["l"] ** 2])

    bead = jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=circle)

    def end(l, adjoint):
        return jaxdyn.simulate(bead, jnp.stack([l, 0.0]), jnp.zeros(2), {"l": l}, t1=0.5,
                               adjoint=adjoint).q[-1]

    forward = jax.jacfwd(lambda l: end(l, diffrax.ForwardMode()))(1.0)
    h = 1e-6
    central = (end(1.0 + h, diffrax.ForwardMode()) - end(1.0 - h, diffrax.ForwardMode())) / (2 * h)
    np.testing.assert_allclose(forward, central, rtol=1e-6, atol=1e-8)


def test_consistent_state_keeps_the_prescribed_coordinates_and_speeds():
    """Slider-crank with the crank's angle θ = 0.7 and speed θ̇ = 3 prescribed (`keep_q`,
    `keep_u`): they stay exactly as given, and the rest is the closed-form kinematics
    φ = asin(r sin θ / L), x = r cos θ + L cos φ, φ̇ = r cos θ θ̇ / (L cos φ),
    ẋ = −r sin θ θ̇ − L sin φ φ̇. Without them the crank speed moves too."""
    system, (r, length) = slider_crank(), (CRANK["r"], CRANK["L"])
    theta, theta_dot = 0.7, 3.0
    q, u = system.consistent_state(0.0, np.array([theta, 0.1, 1.5]),
                                   np.array([theta_dot, 0.0, 0.0]), CRANK, keep_q=(0,),
                                   keep_u=(0,))
    phi = np.arcsin(r * np.sin(theta) / length)
    phi_dot = r * np.cos(theta) * theta_dot / (length * np.cos(phi))
    assert float(q[0]) == theta and float(u[0]) == theta_dot
    np.testing.assert_allclose(q, [theta, phi, r * np.cos(theta) + length * np.cos(phi)],
                               rtol=1e-12)
    np.testing.assert_allclose(
        u, [theta_dot, phi_dot, -r * np.sin(theta) * theta_dot - length * np.sin(phi) * phi_dot],
        rtol=1e-12)
    _, moved = system.consistent_state(0.0, np.array([theta, 0.1, 1.5]),
                                       np.array([theta_dot, 0.0, 0.0]), CRANK)
    assert abs(float(moved[0]) - theta_dot) > 1e-3
    with pytest.raises(ValueError, match=r"keep_u must hold indices in \[0, 3\)"):
        system.consistent_state(0.0, q, u, CRANK, keep_u=(3,))
