"""Structure-preserving steppers (`VariationalIntegrator`, `StormerVerlet`) against closed
forms, conservation laws and a hand-written leapfrog."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
from helpers import rod_chain

G = 9.81


def _double_pendulum():
    def kinetic(q, qd, p):
        m1, m2, l1, l2 = p["m1"], p["m2"], p["l1"], p["l2"]
        return (0.5 * (m1 + m2) * l1**2 * qd[0] ** 2 + 0.5 * m2 * l2**2 * qd[1] ** 2
                + m2 * l1 * l2 * qd[0] * qd[1] * jnp.cos(q[0] - q[1]))

    def potential(q, p):
        m1, m2, l1, l2 = p["m1"], p["m2"], p["l1"], p["l2"]
        return -(m1 + m2) * G * l1 * jnp.cos(q[0]) - m2 * G * l2 * jnp.cos(q[1])

    return jaxdyn.Lagrangian(kinetic, potential)


DOUBLE = _double_pendulum()
DOUBLE_P = {"m1": 1.0, "m2": 1.0, "l1": 1.0, "l2": 1.0}

# The symmetric heavy top in Euler angles (φ precession, θ nutation, ψ spin): φ and ψ are
# cyclic, so p_φ and p_ψ are momentum maps of its symmetries (Goldstein, Classical Mechanics,
# §5.7).
HEAVY_TOP = jaxdyn.Lagrangian(
    lambda q, qd, p: (0.5 * p["I1"] * (qd[1] ** 2 + qd[0] ** 2 * jnp.sin(q[1]) ** 2)
                      + 0.5 * p["I3"] * (qd[2] + qd[0] * jnp.cos(q[1])) ** 2),
    lambda q, p: p["mgl"] * jnp.cos(q[1]))
TOP_P = {"I1": 1.0, "I3": 0.5, "mgl": 1.0}
TOP_Q0, TOP_U0 = jnp.array([0.0, 0.5, 0.0]), jnp.array([0.3, 0.0, 8.0])

SPHERICAL = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * p["m"] * p["l"] ** 2 * (qd[0] ** 2 + jnp.sin(q[0]) ** 2 * qd[1] ** 2),
    lambda q, p: -p["m"] * G * p["l"] * jnp.cos(q[0]))
SPHERICAL_P = {"m": 1.3, "l": 0.7}

# m ẍ + c ẋ + k x = 0: the dissipation enters through the discrete Lagrange–d'Alembert
# principle.
OSCILLATOR = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
                               lambda q, p: 0.5 * p["k"] * q[0] ** 2,
                               dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)
OSCILLATOR_P = {"m": 1.0, "k": 4.0, "c": 0.4}

# Kepler's problem in Cartesian coordinates: constant M, so Störmer–Verlet applies.
KEPLER = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.dot(qd, qd),
                           lambda q, p: -p["mu"] / jnp.sqrt(jnp.dot(q, q)))
KEPLER_P = {"mu": 1.0}
KEPLER_Q0, KEPLER_U0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.2])


def _damped_closed_form(ts, p):
    """x(t) of the underdamped oscillator from x(0) = 1, ẋ(0) = 0."""
    w0 = np.sqrt(p["k"] / p["m"])
    zeta = p["c"] / (2 * np.sqrt(p["k"] * p["m"]))
    wd = w0 * np.sqrt(1 - zeta**2)
    ts = np.asarray(ts)
    return np.exp(-zeta * w0 * ts) * (np.cos(wd * ts) + zeta * w0 / wd * np.sin(wd * ts))


@pytest.mark.parametrize("rule", ["midpoint", pytest.param("trapezoidal",
                                                         marks=pytest.mark.slow)])
def test_forced_variational_integrator_converges_at_second_order(rule):
    ts = jnp.linspace(0.0, 10.0, 101)  # on the step grid of every h below
    exact = _damped_closed_form(ts, OSCILLATOR_P)
    steps = np.array([0.02, 0.01, 0.005])
    errors = []
    for h in steps:
        sol = jaxdyn.simulate(OSCILLATOR, jnp.array([1.0]), jnp.array([0.0]), OSCILLATOR_P,
                              t1=10.0, ts=ts, dt0=float(h),
                              solver=jaxdyn.VariationalIntegrator(rule=rule))
        errors.append(np.max(np.abs(np.asarray(sol.q[:, 0]) - exact)))
    slopes = np.diff(np.log(errors)) / np.diff(np.log(steps))
    np.testing.assert_allclose(slopes, 2.0, atol=0.02)
    assert errors[-1] < 1e-4


@pytest.mark.slow
def test_saved_values_between_steps_are_cubic_in_q():
    """Save times off the step grid: q from the cubic Hermite interpolant (third order between
    the second-order steps), so the error stays that of the steps."""
    h = 0.01
    ts = jnp.linspace(0.0, 10.0, 137)[1:]  # not on the grid
    exact = _damped_closed_form(ts, OSCILLATOR_P)
    on_grid = jaxdyn.simulate(OSCILLATOR, jnp.array([1.0]), jnp.array([0.0]), OSCILLATOR_P,
                              t1=10.0, ts=jnp.linspace(0.0, 10.0, 1001), dt0=h,
                              solver=jaxdyn.VariationalIntegrator())
    step_error = np.max(np.abs(np.asarray(on_grid.q[:, 0])
                               - _damped_closed_form(on_grid.ts, OSCILLATOR_P)))
    sol = jaxdyn.simulate(OSCILLATOR, jnp.array([1.0]), jnp.array([0.0]), OSCILLATOR_P,
                          t1=10.0, ts=ts, dt0=h, solver=jaxdyn.VariationalIntegrator())
    assert np.max(np.abs(np.asarray(sol.q[:, 0]) - exact)) < 1.5 * step_error


@pytest.mark.parametrize("rule", ["midpoint", pytest.param("trapezoidal",
                                                         marks=pytest.mark.slow)])
def test_momentum_maps_are_conserved_to_round_off(rule):
    """The spherical pendulum's p_φ and the heavy top's p_φ, p_ψ (cyclic coordinates): the
    discrete Noether theorem makes them exact invariants of a variational integrator, where an
    explicit Runge–Kutta method at a looser tolerance lets them wander."""
    solver = jaxdyn.VariationalIntegrator(rule=rule)
    ts = jnp.linspace(0.0, 100.0, 101)
    sol = jaxdyn.simulate(SPHERICAL, jnp.array([1.0, 0.0]), jnp.array([0.3, 2.0]),
                          SPHERICAL_P, t1=100.0, ts=ts, dt0=0.01, solver=solver)
    momenta = SPHERICAL.momentum(sol.ts, sol.q, sol.u, SPHERICAL_P)[:, 1]
    assert float(jnp.max(jnp.abs(momenta - momenta[0]))) < 1e-13
    top = jaxdyn.simulate(HEAVY_TOP, TOP_Q0, TOP_U0, TOP_P, t1=20.0,
                          ts=jnp.linspace(0.0, 20.0, 21), dt0=0.002, solver=solver)
    momenta = HEAVY_TOP.momentum(top.ts, top.q, top.u, TOP_P)[:, jnp.array([0, 2])]
    assert float(jnp.max(jnp.abs(momenta - momenta[None, 0]))) < 1e-12

    runge_kutta = jaxdyn.simulate(SPHERICAL, jnp.array([1.0, 0.0]), jnp.array([0.3, 2.0]),
                                  SPHERICAL_P, t1=100.0, ts=ts, solver=diffrax.Tsit5(),
                                  rtol=1e-6, atol=1e-6)
    momenta = SPHERICAL.momentum(runge_kutta.ts, runge_kutta.q, runge_kutta.u,
                                 SPHERICAL_P)[:, 1]
    assert float(jnp.max(jnp.abs(momenta - momenta[0]))) > 1e-7


def _energy_error(sol, system, p):
    energy = system.energy(sol.ts, sol.q, sol.u, p)
    return np.abs(np.asarray(energy - energy[0]))


def _drift_test(system, p, q0, u0, t1, h, runge_kutta_step):
    ts = jnp.linspace(0.0, t1, 4001)  # the energy error oscillates: sample it densely
    variational = jaxdyn.simulate(system, q0, u0, p, t1=t1, ts=ts, dt0=h,
                                  solver=jaxdyn.VariationalIntegrator())
    error = _energy_error(variational, system, p)
    # Bounded: the error over the last tenth of the run is no larger than over the first.
    assert error[-400:].max() < 1.5 * error[1:401].max()
    # An explicit Runge–Kutta method of the same order (Heun's) drifts: its error grows along
    # the run. (A high-order method with small steps drifts too, from a much smaller error:
    # benchmarks/bench_long_horizon.py compares them at equal run time.)
    explicit = jaxdyn.simulate(system, q0, u0, p, t1=t1, ts=ts, dt0=runge_kutta_step,
                               solver=diffrax.Heun(),
                               stepsize_controller=diffrax.ConstantStepSize())
    drift = _energy_error(explicit, system, p)
    assert drift[-400:].max() > 5 * drift[1:401].max()
    return error, drift


def test_energy_error_is_bounded_where_runge_kutta_drifts():
    """3 × 10⁴ steps of the double pendulum (chaotic); 10⁶ and the heavy top in the slow
    test."""
    _drift_test(DOUBLE, DOUBLE_P, jnp.array([1.0, 0.5]), jnp.zeros(2), t1=300.0, h=0.01,
                runge_kutta_step=0.01)


@pytest.mark.slow
def test_energy_error_is_bounded_over_a_million_steps():
    error, drift = _drift_test(DOUBLE, DOUBLE_P, jnp.array([1.0, 0.5]), jnp.zeros(2),
                               t1=10_000.0, h=0.01, runge_kutta_step=0.01)
    assert error.max() < 1e-2 < drift.max()
    _drift_test(HEAVY_TOP, TOP_P, TOP_Q0, TOP_U0, t1=2000.0, h=0.002, runge_kutta_step=0.01)


def _leapfrog(q, v, h, steps, mu):
    """Velocity Verlet for Kepler's problem, written out with NumPy."""
    def acceleration(q):
        return -mu * q / np.linalg.norm(q) ** 3

    a = acceleration(q)
    for _ in range(steps):
        half = v + h / 2 * a
        q = q + h * half
        a = acceleration(q)
        v = half + h / 2 * a
    return q, v


def test_stormer_verlet_is_the_leapfrog_and_conserves_angular_momentum():
    h, steps = 0.01, 2000
    sol = jaxdyn.simulate(KEPLER, KEPLER_Q0, KEPLER_U0, KEPLER_P, t1=h * steps,
                          ts=jnp.linspace(0.0, h * steps, 41), dt0=h,
                          solver=jaxdyn.StormerVerlet())
    q, v = _leapfrog(np.asarray(KEPLER_Q0), np.asarray(KEPLER_U0), h, steps, 1.0)
    np.testing.assert_allclose(sol.q[-1], q, rtol=0, atol=1e-11)
    np.testing.assert_allclose(sol.u[-1], v, rtol=0, atol=1e-11)
    angular = sol.q[:, 0] * sol.u[:, 1] - sol.q[:, 1] * sol.u[:, 0]
    assert float(jnp.max(jnp.abs(angular - angular[0]))) < 1e-13
    # The implicit trapezoidal variational integrator is the same method where M is constant.
    trapezoidal = jaxdyn.simulate(KEPLER, KEPLER_Q0, KEPLER_U0, KEPLER_P, t1=h * steps, dt0=h,
                                  solver=jaxdyn.VariationalIntegrator(rule="trapezoidal"))
    np.testing.assert_allclose(trapezoidal.q[-1], q, rtol=0, atol=1e-10)


def test_gradients_and_vmap_through_the_variational_integrator():
    solver = jaxdyn.VariationalIntegrator()

    def final_angle(length):
        p = dict(DOUBLE_P, l2=length)
        sol = jaxdyn.simulate(DOUBLE, jnp.array([1.0, 0.5]), jnp.zeros(2), p, t1=1.0,
                              dt0=0.01, solver=solver)
        return sol.q[-1, 1]

    gradient = jax.grad(final_angle)(1.0)
    eps = 1e-6
    central = (final_angle(1.0 + eps) - final_angle(1.0 - eps)) / (2 * eps)
    np.testing.assert_allclose(gradient, central, rtol=1e-6)

    starts = jnp.array([[1.0, 0.5], [0.2, -0.3], [2.0, 1.0]])
    batched = jax.vmap(lambda q0: jaxdyn.simulate(DOUBLE, q0, jnp.zeros(2), DOUBLE_P, t1=1.0,
                                                  dt0=0.01, solver=solver).q[-1])(starts)
    for q0, q1 in zip(starts, batched):
        single = jaxdyn.simulate(DOUBLE, q0, jnp.zeros(2), DOUBLE_P, t1=1.0, dt0=0.01,
                                 solver=solver)
        np.testing.assert_allclose(q1, single.q[-1], rtol=0, atol=1e-12)


def test_structure_preserving_solvers_reject_what_they_cannot_do():
    q0, u0 = jnp.array([1.0, 0.5]), jnp.zeros(2)
    with pytest.raises(ValueError, match="accelerations depend on the speeds"):
        jaxdyn.simulate(DOUBLE, q0, u0, DOUBLE_P, t1=1.0, dt0=0.01,
                        solver=jaxdyn.StormerVerlet())
    with pytest.raises(ValueError, match="pass the step length as dt0"):
        jaxdyn.simulate(DOUBLE, q0, u0, DOUBLE_P, t1=1.0, solver=jaxdyn.VariationalIntegrator())
    with pytest.raises(ValueError, match="not rtol/atol"):
        jaxdyn.simulate(DOUBLE, q0, u0, DOUBLE_P, t1=1.0, dt0=0.01, rtol=1e-8,
                        solver=jaxdyn.VariationalIntegrator())
    with pytest.raises(ValueError, match="takes fixed steps"):
        jaxdyn.simulate(DOUBLE, q0, u0, DOUBLE_P, t1=1.0, dt0=0.01,
                        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
                        solver=jaxdyn.VariationalIntegrator())
    with pytest.raises(ValueError, match="rule must be"):
        jaxdyn.VariationalIntegrator(rule="simpson")
    particle = jaxdyn.Particle(mass=1.0, position=lambda q, p: jnp.append(q, 0.0))
    kane = jaxdyn.Kane(jaxdyn.MultibodySystem((particle,)))
    with pytest.raises(ValueError, match="needs a jaxdyn.Lagrangian"):
        jaxdyn.simulate(kane, q0, u0, None, t1=1.0, dt0=0.01,
                        solver=jaxdyn.VariationalIntegrator())


def test_a_step_too_long_for_newton_is_reported():
    with pytest.raises(RuntimeError, match="^The implicit step's Newton iteration did not "
                                           "converge"):
        jaxdyn.simulate(DOUBLE, jnp.array([2.5, 2.0]), jnp.array([5.0, -5.0]), DOUBLE_P,
                        t1=2.0, dt0=0.05, solver=jaxdyn.VariationalIntegrator(max_newton_steps=1))


def test_a_root_far_from_the_motion_is_refused():
    """A step too long for a fast, light link: Newton's method converges (residual 5e-14) to
    another root of the discrete equations, with speeds five times the motion's, where the
    energy would jump from −56 to 4561. The step is refused and the error says why; half the
    step follows the motion (energy conserved to the step's O(h²))."""
    chain = rod_chain()
    p = {"m": np.array([0.41, 1.15, 1.92]), "l": np.array([0.38, 0.58, 0.86]), "g": 13.8}
    q0, u0 = jnp.array([0.25, -0.19, 0.02]), jnp.array([10.5, -7.9, 0.7])
    h = 0.0207
    with pytest.raises(RuntimeError, match="^The variational integrator's implicit step "
                                           "converged to a solution far from the motion"):
        jaxdyn.simulate(chain, q0, u0, p, t1=19 * h, dt0=h,
                        solver=jaxdyn.VariationalIntegrator())
    sol = jaxdyn.simulate(chain, q0, u0, p, t1=19 * h, dt0=h / 2,
                          ts=jnp.linspace(0.0, 19 * h, 20),
                          solver=jaxdyn.VariationalIntegrator())
    energy = chain.energy(sol.ts, sol.q, sol.u, p)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 0.05 * abs(float(energy[0]))


def test_long_fixed_step_runs_get_the_steps_they_need():
    """The default step budget follows the interval for fixed steps (10⁵ steps > 16⁴)."""
    sol = jaxdyn.simulate(KEPLER, KEPLER_Q0, KEPLER_U0, KEPLER_P, t1=1000.0, dt0=0.01,
                          solver=jaxdyn.StormerVerlet())
    assert int(sol.num_steps) == 100_000
