"""Impacts through every formulation (`jaxdyn.UnilateralContact`): Newton's law against the
same law written by hand, Pinocchio's `impulseDynamics` and the formulations against each
other; simultaneous impacts as the complementarity problem they are; a hybrid limit cycle (the
rimless wheel) and its stability.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
from helpers import DOUBLE_PENDULUM
from multibody_systems import _chain

TOL = dict(solver=diffrax.Tsit5(), rtol=1e-11, atol=1e-11)
G = 9.81


# -- formulations: the same impact through each one's mass matrix and speeds -----------------

def _tip_height(q, p):
    return -p["l"][0] * jnp.cos(q[0]) - p["l"][1] * jnp.cos(q[1])


def test_double_pendulum_tip_strikes_the_floor_newton_by_hand():
    """The tip of a double pendulum of point masses strikes a floor at depth h: the jump of
    the speeds is Newton's law with the textbook mass matrix and the tip's Jacobian,
    J = (l₁ sin θ₁, l₂ sin θ₂)."""
    p = dict(DOUBLE_PENDULUM.params, h=1.5, e=0.6)
    floor = jaxdyn.UnilateralContact(
        lambda q, p: p["h"] - p["l1"] * jnp.cos(q[0]) - p["l2"] * jnp.cos(q[1]),
        restitution=lambda p: p["e"])
    sol = jaxdyn.simulate(DOUBLE_PENDULUM.dynamics, jnp.array([1.4, 2.0]), jnp.zeros(2), p,
                          t1=2.0, events=[floor], max_events=3, **TOL)
    assert int(sol.events.count) >= 1
    q = np.asarray(sol.events.q_minus[0])
    u_minus = np.asarray(sol.events.u_minus[0])
    assert abs(p["h"] - p["l1"] * np.cos(q[0]) - p["l2"] * np.cos(q[1])) < 1e-10
    mass = DOUBLE_PENDULUM.mass_matrix(q, p)
    jacobian = np.array([p["l1"] * np.sin(q[0]), p["l2"] * np.sin(q[1])])
    approach = jacobian @ u_minus
    assert approach < 0
    impulse = -(1 + p["e"]) * approach / (jacobian @ np.linalg.solve(mass, jacobian))
    u_plus = u_minus + np.linalg.solve(mass, jacobian) * impulse
    np.testing.assert_allclose(sol.events.u_plus[0], u_plus, rtol=1e-10)
    np.testing.assert_allclose(sol.events.impulses[0, 0], impulse, rtol=1e-10)
    np.testing.assert_allclose(jacobian @ np.asarray(sol.events.u_plus[0]), -p["e"] * approach,
                               rtol=1e-10)


CHAIN = _chain(2)


@pytest.mark.parametrize("formulation", ["Kane", "Gibbs-Appell", "Kane, relative"])
def test_formulations_agree_across_impacts(formulation):
    """A chain of two rods whose tip strikes a floor, by Kane's equations (in the absolute
    angle rates, and in relative angle rates u = (θ̇₁, θ̇₂ − θ̇₁)) and Gibbs–Appell's against
    Lagrange's: the same impacts, and the same motion after them."""
    system, p = CHAIN.system, dict(CHAIN.params, h=0.6 * float(np.sum(CHAIN.params["l"])))
    floor = jaxdyn.UnilateralContact(lambda q, p: p["h"] + _tip_height(q, p), restitution=0.7)
    u0 = jnp.zeros(2)
    if formulation == "Kane":
        dynamics = jaxdyn.Kane(system)
    elif formulation == "Gibbs-Appell":
        dynamics = jaxdyn.GibbsAppell.from_system(system)
    else:
        dynamics = jaxdyn.Kane(system, kinematic_map=lambda q, p: jnp.array([[1.0, 0.0],
                                                                            [1.0, 1.0]]))
    sol = jaxdyn.simulate(dynamics, jnp.array([1.2, 2.2]), u0, p, t1=1.5, events=[floor],
                          max_events=4, ts=jnp.linspace(0.0, 1.5, 7), **TOL)
    reference = _chain_reference(p)
    count = int(reference.events.count)
    assert count >= 2 and int(sol.events.count) == count
    np.testing.assert_allclose(sol.events.t[:count], reference.events.t[:count], rtol=1e-9)
    np.testing.assert_allclose(sol.q, reference.q, atol=1e-8)
    np.testing.assert_allclose(sol.qd, reference.qd, atol=1e-7)


_CHAIN_CACHE = {}


def _chain_reference(p):
    if "sol" not in _CHAIN_CACHE:
        floor = jaxdyn.UnilateralContact(lambda q, p: p["h"] + _tip_height(q, p),
                                         restitution=0.7)
        _CHAIN_CACHE["sol"] = jaxdyn.simulate(
            jaxdyn.Lagrangian.from_system(CHAIN.system), jnp.array([1.2, 2.2]), jnp.zeros(2),
            p, t1=1.5, events=[floor], max_events=4, ts=jnp.linspace(0.0, 1.5, 7), **TOL)
    return _CHAIN_CACHE["sol"]


def test_constrained_formulation_impacts_within_its_constraints():
    """A pendulum as a particle in Cartesian coordinates held by a rod (`Constrained`)
    strikes a wall: the impact keeps the rod's constraint and matches the pendulum in its
    angle (Lagrange's equations of one coordinate)."""
    length, e = 1.3, 0.75
    kinetic = lambda q, qd, p: 0.5 * jnp.sum(qd**2)
    potential = lambda q, p: G * q[1]
    rod = lambda q, p: jnp.array([q[0] ** 2 + q[1] ** 2 - length**2])
    cartesian = jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=rod)
    wall = jaxdyn.UnilateralContact(lambda q, p: q[0] + 0.3, restitution=e)  # x ≥ −0.3
    theta0 = 1.1
    q0 = jnp.array([length * np.sin(theta0), -length * np.cos(theta0)])
    sol = jaxdyn.simulate(cartesian, q0, jnp.zeros(2), t1=3.0, events=[wall], max_events=3,
                          **TOL)
    angle = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * length**2 * qd[0] ** 2,
                              lambda q, p: -G * length * jnp.cos(q[0]))
    wall_angle = jaxdyn.UnilateralContact(lambda q, p: length * jnp.sin(q[0]) + 0.3,
                                          restitution=e)
    reference = jaxdyn.simulate(angle, jnp.array([theta0]), jnp.zeros(1), t1=3.0,
                                events=[wall_angle], max_events=3, **TOL)
    count = int(reference.events.count)
    assert count >= 2 and int(sol.events.count) == count
    np.testing.assert_allclose(sol.events.t[:count], reference.events.t[:count], rtol=1e-8)
    u_plus = np.asarray(sol.events.u_plus[:count])
    q_minus = np.asarray(sol.events.q_minus[:count])
    np.testing.assert_allclose(np.sum(q_minus * u_plus, axis=1), 0.0, atol=1e-9)  # on the rod
    speed = np.linalg.norm(u_plus, axis=1)
    np.testing.assert_allclose(speed, length * np.abs(reference.events.u_plus[:count, 0]),
                               rtol=1e-8)


def test_panda_end_stop_against_pinocchio_impulse_dynamics():
    """The Panda arm (articulated-body formulation) strikes an end stop of its fourth joint:
    the post-impact speeds and the impulse equal Pinocchio's `impulseDynamics` (which solves
    the same impact law with its own CRBA)."""
    pin = pytest.importorskip("pinocchio")
    from robots import Robot, robot_file

    robot = Robot.load(robot_file("panda.urdf"))
    (q_pin, v_pin, _), (q, u, _) = robot.random_states(1, seed=3)
    u = u[0].copy()
    u[3] = abs(u[3]) + 0.5  # towards the stop
    e = 0.4
    stop = jaxdyn.UnilateralContact(lambda q, p: 2.5 - q[3], restitution=e)
    arm = jaxdyn.ArticulatedBody(robot.tree)
    # Compiled, as a solve calls it (eager, its operations would compile one by one).
    jump = eqx.filter_jit(stop.jump)
    _, u_plus, impulses, _ = jump(arm, 0.0, jnp.asarray(q[0]), jnp.asarray(u), robot.p,
                                  jnp.array([True]), jnp.array([False]))
    row = np.zeros(u.shape[0])
    row[3] = -1.0
    v_plus = pin.impulseDynamics(robot.model, robot.data, q_pin[0], robot.permutation @ u,
                                 (row @ robot.permutation.T)[None, :], e)
    np.testing.assert_allclose(robot.permutation @ np.asarray(u_plus), v_plus, rtol=1e-10,
                               atol=1e-12)
    np.testing.assert_allclose(impulses, np.abs(robot.data.impulse_c), rtol=1e-10)
    np.testing.assert_allclose(u_plus[3], -e * u[3], rtol=1e-12)


# -- simultaneous impacts: the complementarity problem ---------------------------------------

def _rod_T(q, qd, p):  # a planar rod (x, y, θ), mass 1, length 1
    return 0.5 * (qd[0] ** 2 + qd[1] ** 2) + 0.5 / 12 * qd[2] ** 2


def _rod_V(q, p):
    return G * q[1]


ROD = jaxdyn.Lagrangian(_rod_T, _rod_V)
ROD_ENDS = jaxdyn.UnilateralContact(
    lambda q, p: jnp.stack([q[1] - 0.5 * jnp.sin(q[2]), q[1] + 0.5 * jnp.sin(q[2])]),
    restitution=0.5)


def test_rod_landing_flat_hits_with_both_ends():
    """Both ends strike at once: equal impulses, the centre's speed reverses with e, no spin
    (a single-contact law applied to either end would set the rod spinning)."""
    sol = jaxdyn.simulate(ROD, jnp.array([0.0, 1.0, 0.0]), jnp.array([0.2, 0.0, 0.0]),
                          t1=0.6, events=[ROD_ENDS], max_events=2, **TOL)
    v = -np.sqrt(2 * G * 1.0)
    np.testing.assert_allclose(sol.events.t[0], np.sqrt(2 / G), rtol=1e-10)
    np.testing.assert_allclose(sol.events.u_plus[0], [0.2, -0.5 * v, 0.0], atol=1e-9)
    np.testing.assert_allclose(sol.events.impulses[0], [-0.75 * v, -0.75 * v], rtol=1e-8)


def test_spinning_rod_both_ends_push_though_one_separates():
    """A flat rod at the floor, falling (ẏ = −1) and spinning (θ̇ = 4): its left end approaches
    at −3, its right end separates at +1. Newton's law at the left end alone would drive the
    right end into the floor (at −1.25), so both ends push: G Λ = −c with the Delassus matrix
    G = [[4, −2], [−2, 4]] and c = ((1 + e)(−3), +1), Λ = (4/3, 5/12) ≥ 0."""
    q0, u0 = jnp.array([0.0, 0.0, 0.0]), jnp.array([0.0, -1.0, 4.0])
    fired, resting = jnp.array([True, False]), jnp.array([False, False])
    jump = eqx.filter_jit(ROD_ENDS.jump)  # compiled, as a solve calls it
    _, u_plus, impulses, rest = jump(ROD, 0.0, q0, u0, None, fired, resting)
    np.testing.assert_allclose(impulses, [4 / 3, 5 / 12], rtol=1e-12)
    ends = np.array([[0.0, 1.0, -0.5], [0.0, 1.0, 0.5]])
    expected = np.asarray(u0) + np.diag([1.0, 1.0, 12.0]) @ ends.T @ np.array([4 / 3, 5 / 12])
    np.testing.assert_allclose(u_plus, expected, rtol=1e-12)
    np.testing.assert_allclose(ends @ np.asarray(u_plus), [1.5, 0.0], atol=1e-12)
    # the right end, now still and pulled down, rests
    np.testing.assert_array_equal(rest, [False, True])


# -- a hybrid limit cycle: the rimless wheel --------------------------------------------------

def _rimless_wheel_step(omega, alpha, gamma):
    """The rimless wheel's return map on its post-collision speed: the stance spoke (angle θ
    from the vertical, an inverted pendulum of length 1) starts at θ = γ − α with θ̇ = ω and
    swings until the next spoke strikes (θ = γ + α); the collision keeps the angular momentum
    about the new contact: θ⁺ = θ − 2α, θ̇⁺ = cos(2α) θ̇."""
    stance = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2,
                               lambda q, p: G * jnp.cos(q[0]))
    strike = jaxdyn.Event(lambda q, u, p: p["gamma"] + p["alpha"] - q[0],
                          lambda q, u, p: (q - 2 * p["alpha"], jnp.cos(2 * p["alpha"]) * u))
    sol = jaxdyn.simulate(stance, jnp.stack([gamma - alpha]), jnp.stack([omega]),
                          {"alpha": alpha, "gamma": gamma}, t1=3.0, events=[strike],
                          max_events=1, throw=False, **TOL)
    return sol.events.u_plus[0, 0]


def test_rimless_wheel_limit_cycle_and_its_stability():
    """Newton's method on the return map finds the limit cycle's speed
    ω* = cot 2α √(4 g sin α sin γ) (McGeer 1990; Coleman 1998), and `jax.grad` of the map
    there gives its Floquet multiplier cos² 2α."""
    alpha, gamma = np.pi / 8, 0.08
    step = lambda w: _rimless_wheel_step(w, alpha, gamma)
    residual = jax.jit(jax.value_and_grad(lambda w: step(w) - w))
    omega = 1.5
    for _ in range(8):
        value, slope = residual(omega)
        omega = omega - float(value) / float(slope)
    expected = np.sqrt(4 * G * np.sin(alpha) * np.sin(gamma)) / np.tan(2 * alpha)
    np.testing.assert_allclose(omega, expected, rtol=1e-9)
    multiplier = jax.grad(step)(omega)
    np.testing.assert_allclose(multiplier, np.cos(2 * alpha) ** 2, rtol=1e-7)
