"""Rigid contact with Coulomb friction (`jaxdyn.RigidContact`) against closed forms: a block
sliding to rest, held on a slope by static friction and sliding down a steeper one, the
derivative of the stopping distance in μ, a spinning ball struck onto the ground (sticking
and slipping impacts), a ball rolling down a slope, and a box on four corners."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import assert_close, rotation_of

G, MU, V0 = 9.81, 0.5, 2.0
TOL = dict(rtol=1e-10, atol=1e-10)
SLOPES = np.radians([0.0, 20.0, 35.0])  # sliding to rest, held (tan γ < μ), sliding down
TS = np.linspace(0.0, 1.0, 11)

# a point mass, its contact point its position
PARTICLE = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: G * q[2])
SLIDING = jaxdyn.RigidContact([jaxdyn.ContactPoint(lambda q, p: q)],
                              jaxdyn.Plane.inclined(lambda p: p["slope"]),
                              friction=lambda p: p["mu"])


def _downhill(slope):
    return np.array([np.cos(slope), 0.0, -np.sin(slope)])


H = 1e-6  # the step of the central differences in μ
DROP = 0.2  # the height the thrown block falls from


@functools.cache
def _particles():
    """One program for the particle tests: the trajectories and their derivatives in μ (one
    forward-mode pass), over a batch of the particle on flat ground pushed at V0 along x, at
    rest on slopes of 20° and 35°, pushed with μ ± H, and thrown along x from DROP onto
    flat ground with μ = MU and μ = 1.5."""
    q0 = np.zeros((7, 3))
    q0[5:, 2] = DROP
    u0 = np.zeros((7, 3))
    u0[[0, 3, 4, 5, 6], 0] = V0
    slopes = np.concatenate([SLOPES, np.zeros(4)])
    mus = np.array([MU, MU, MU, MU + H, MU - H, MU, 1.5])

    def solve(slope, mu, q0, u0):
        return jaxdyn.simulate(PARTICLE, q0, u0, {"slope": slope, "mu": mu}, t1=TS[-1],
                               ts=TS, events=[SLIDING], max_events=4, **TOL)

    def with_derivative(slope, mu, q0, u0):
        return jax.jvp(lambda mu: solve(slope, mu, q0, u0), (mu,), (jnp.ones_like(mu),))

    return jax.jit(jax.vmap(with_derivative))(jnp.asarray(slopes), jnp.asarray(mus),
                                              jnp.asarray(q0), jnp.asarray(u0))


def test_block_slides_to_rest_at_the_coulomb_stopping_distance_and_sticks():
    """Pushed at v₀ on the ground, the block decelerates at μ g, stops at t = v₀/(μ g) after
    v₀²/(2 μ g) (the event that ends its slip) and sticks there, its weight on the ground."""
    sol, _ = _particles()
    count = int(sol.events.count[0])
    assert count == 2  # met at rest at t = 0 (sliding), stopped
    stop = V0 / (MU * G)
    assert_close(sol.events.t[0, 1], stop, rtol=1e-10)
    np.testing.assert_array_equal(sol.events.resting[0, :2], [[True, False], [True, True]])
    x = np.where(TS < stop, V0 * TS - MU * G * TS**2 / 2, V0**2 / (2 * MU * G))
    assert_close(sol.q[0, :, 0], x, rtol=1e-10, atol=1e-12)
    assert_close(sol.q[0, :, 2], np.zeros(TS.size), rtol=0, atol=1e-12)
    # (the forces at the save times: λ_N = m g; friction μ m g while sliding, none stuck)
    assert_close(sol.events.normal_forces[0, 1:, 0], np.full(TS.size - 1, G), rtol=1e-10)
    assert_close(sol.events.normal_forces[0, 1:, 1], np.where(TS[1:] < stop, MU * G, 0.0),
                 rtol=1e-10, atol=1e-10)


def test_static_friction_holds_the_block_below_the_friction_angle():
    """tan 20° < μ: the block sticks where it was put, held by friction g sin γ ≤ μ g cos γ."""
    sol, _ = _particles()
    assert int(sol.events.count[1]) == 1
    np.testing.assert_array_equal(sol.events.resting[1, 0], [True, True])
    assert_close(sol.q[1], np.zeros((TS.size, 3)), rtol=0, atol=1e-12)
    slope = SLOPES[1]
    held = np.broadcast_to([G * np.cos(slope), G * np.sin(slope)], (TS.size - 1, 2))
    assert_close(sol.events.normal_forces[1, 1:], held, rtol=1e-10)


def test_block_slides_down_a_steep_slope_at_the_coulomb_acceleration():
    """tan 35° > μ: the block slides from rest with s̈ = g (sin γ − μ cos γ), exactly."""
    sol, _ = _particles()
    slope = SLOPES[2]
    assert int(sol.events.count[2]) == 1
    np.testing.assert_array_equal(sol.events.resting[2, 0], [True, False])
    s = np.asarray(sol.q[2]) @ _downhill(slope)
    assert_close(s, G * (np.sin(slope) - MU * np.cos(slope)) * TS**2 / 2, rtol=1e-10,
                 atol=1e-12)
    assert_close(np.asarray(sol.q[2]) @ [np.sin(slope), 0.0, np.cos(slope)], np.zeros(TS.size),
                 rtol=0, atol=1e-12)


def test_derivatives_in_mu_across_the_stop():
    """d/dμ of the trajectories, through the slides and the events that start and stop them:
    where the pushed block rests, −v₀²/(2 μ² g) (and a central difference); on the steep
    slope, −g cos γ t²/2; none where it sticks."""
    sol, tangent = _particles()
    rest = -V0**2 / (2 * MU**2 * G)
    assert_close(tangent.q[0, -1, 0], rest, rtol=1e-8)
    assert_close(tangent.q[0, -1, 0], (sol.q[3, -1, 0] - sol.q[4, -1, 0]) / (2 * H), rtol=1e-6)
    slope = SLOPES[2]
    assert_close(np.asarray(tangent.q[2]) @ _downhill(slope), -G * np.cos(slope) * TS**2 / 2,
                 rtol=1e-8, atol=1e-12)
    assert_close(tangent.q[1], np.zeros((TS.size, 3)), rtol=0, atol=1e-12)


@pytest.mark.parametrize("member, mu", [(5, MU), (6, 1.5)])
def test_thrown_block_lands_by_the_frictional_impact_law(member, mu):
    """Thrown along x at v₀ from h, the block lands at t = √(2h/g) with v_z⁻ = −√(2gh): a
    plastic impact, Λ_N = m |v_z⁻|, whose tangential impulse stops the slip if μ Λ_N ≥ m v₀
    (it sticks where it lands) and is μ Λ_N otherwise (v_x⁺ = v₀ − μ |v_z⁻|; it then slides
    v_x⁺²/(2 μ g) further and sticks)."""
    sol, _ = _particles()
    landing, fall = np.sqrt(2 * DROP / G), np.sqrt(2 * G * DROP)
    slip = max(V0 - mu * fall, 0.0)
    assert_close(sol.events.t[member, 0], landing, rtol=1e-10)
    assert_close(sol.events.impulses[member, 0], [fall, V0 - slip], rtol=1e-10)
    assert_close(sol.events.u_plus[member, 0], [slip, 0.0, 0.0], rtol=0, atol=1e-10)
    rest = V0 * landing + slip**2 / (2 * mu * G)
    assert_close(sol.q[member, -1], [rest, 0.0, 0.0], rtol=1e-10, atol=1e-12)
    assert bool(np.all(sol.events.resting[member, int(sol.events.count[member]) - 1]))
    assert (slip > 0) == (mu == MU)  # (the two regimes)


# -- a solid ball (I = 2/5 m r²), a free body of a tree ------------------------------------

M, R = 0.5, 0.1
BALL = jaxdyn.ArticulatedBody(jaxdyn.RigidBodyTree(
    [jaxdyn.Link("ball", jaxdyn.Free(), mass=M, inertia=0.4 * M * R * R * jnp.eye(3))],
    gravity=jnp.array([0.0, 0.0, -G])))
BALL_CONTACT = jaxdyn.RigidContact([jaxdyn.ContactPoint("ball", radius=R)],
                                   jaxdyn.Plane.inclined(lambda p: p["slope"]),
                                   restitution=lambda p: p["e"], friction=lambda p: p["mu"])


@functools.cache
def _balls():
    """One batch: the ball thrown down spinning backwards onto the ground with ample (μ = 1)
    and little (μ = 0.1) friction (it bounces on into rest), and at rest on a 20° slope
    (μ = 1)."""
    slope = np.radians(20.0)
    normal = np.array([np.sin(slope), 0.0, np.cos(slope)])
    q0 = np.array([[0.0, 0.0, R + 1e-3, 1.0, 0.0, 0.0, 0.0]] * 2
                  + [[*(normal * R), 1.0, 0.0, 0.0, 0.0]])
    u0 = np.array([[1.0, 0.0, -2.0, 0.0, 30.0, 0.0]] * 2 + [[0.0] * 6])
    p = {"slope": jnp.array([0.0, 0.0, slope]), "mu": jnp.array([1.0, 0.1, 1.0]),
         "e": jnp.array([0.5, 0.5, 0.0])}
    ts = np.linspace(0.0, 0.5, 6)
    return ts, jaxdyn.simulate_batch(BALL, q0, u0, p, batched_params=True, t1=ts[-1], ts=ts,
                                     events=[BALL_CONTACT], max_events=32, **TOL)


def _in_world(q, u):
    """(v, ω) in the world from a free body's speeds in its own axes."""
    turn = rotation_of(np.asarray(q[3:7]))
    return turn @ np.asarray(u[:3]), turn @ np.asarray(u[3:])


@pytest.mark.slow  # (the free ball's hybrid program compiles for 30–40 s)
@pytest.mark.parametrize("member, mu", [(0, 1.0), (1, 0.1)])
def test_spinning_ball_struck_onto_the_ground_sticks_or_slips(member, mu):
    """The oblique impact of a spinning ball (Glocker's law, e = 0.5): the slip of the
    contact point s⁻ = v_x − r ω_y needs the impulse Λ_T = −(2/7) m s⁻ to stop; with ample
    friction (|Λ_T| ≤ μ Λ_N) it stops, v_x⁺ = v_x − (2/7) s⁻, ω_y⁺ = ω_y + 5 s⁻/(7 r); with
    little it slips on, Λ_T = −μ Λ_N sign s⁻. Normally v_z⁺ = −e v_z⁻, Λ_N = m (1 + e)|v_z⁻|."""
    _, sol = _balls()
    events = sol.events  # (the first impact)
    v, w = _in_world(events.q_minus[member, 0], events.u_minus[member, 0])
    v_plus, w_plus = _in_world(events.q_plus[member, 0], events.u_plus[member, 0])
    e = 0.5
    normal = M * (1 + e) * -v[2]
    slip = v[0] - R * w[1]
    tangential = -2 / 7 * M * slip
    if abs(tangential) > mu * normal:
        tangential = -mu * normal * np.sign(slip)
    assert_close(events.impulses[member, 0], [normal, abs(tangential)], rtol=1e-10)
    assert_close(v_plus, [v[0] + tangential / M, 0.0, -e * v[2]], rtol=1e-10, atol=1e-12)
    assert_close(w_plus, [0.0, w[1] - 5 * tangential / (2 * M * R), 0.0], rtol=1e-10,
                 atol=1e-10)
    assert (abs(tangential) < mu * normal) == (mu == 1.0)  # (the two regimes)


@pytest.mark.slow
def test_ball_rolls_without_slipping_at_five_sevenths_g_sin_slope():
    """Released on a 20° slope with ample friction, the ball's contact sticks and it rolls:
    its centre travels 5/14 g sin γ t² (Routh), to the solver's tolerance (the turning
    body's quaternion is not integrated exactly, unlike the particles' parabolas)."""
    ts, sol = _balls()
    slope = np.radians(20.0)
    np.testing.assert_array_equal(sol.events.resting[2, 0], [True, True])
    s = (np.asarray(sol.q[2, :, :3]) - np.asarray(sol.q[2, 0, :3])) @ _downhill(slope)
    assert_close(s, 5 / 14 * G * np.sin(slope) * ts**2, rtol=1e-8, atol=1e-12)


@pytest.mark.slow  # (its hybrid program compiles for about a minute)
def test_box_on_four_corners_slides_to_rest_carrying_its_weight():
    """A box flat on its four lower corners (redundant contacts), pushed: it stops after
    v₀²/(2 μ g), its corners' normal forces summing to its weight."""
    a, b, h = 0.2, 0.1, 0.05
    inertia = 1.0 / 12 * jnp.diag(jnp.array([b * b + h * h, a * a + h * h, a * a + b * b]))
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("box", jaxdyn.Free(), mass=1.0,
                                             inertia=inertia)],
                                gravity=jnp.array([0.0, 0.0, -G]))
    corners = jaxdyn.box_corners("box", (a, b, h))[::2]  # (the four with z = −h/2)
    ts = np.linspace(0.0, 0.6, 7)
    sol = jaxdyn.simulate(jaxdyn.ArticulatedBody(tree), jnp.array([0, 0, h / 2, 1.0, 0, 0, 0]),
                          jnp.array([V0, 0, 0, 0, 0, 0]), t1=ts[-1], ts=ts,
                          events=[jaxdyn.RigidContact(corners, friction=MU)], max_events=8,
                          **TOL)
    stop = V0 / (MU * G)
    x = np.where(ts < stop, V0 * ts - MU * G * ts**2 / 2, V0**2 / (2 * MU * G))
    assert_close(sol.q[:, 0], x, rtol=1e-10, atol=1e-12)
    assert_close(np.sum(sol.events.normal_forces[1:, :4], axis=1), np.full(ts.size - 1, G),
                 rtol=1e-10)
    assert np.all(sol.events.resting[int(sol.events.count) - 1])  # all four stick


def test_rigid_contact_errors():
    with pytest.raises(ValueError, match="non-empty sequence"):
        jaxdyn.RigidContact([])
    with pytest.raises(ValueError, match="terrain"):
        jaxdyn.RigidContact([jaxdyn.ContactPoint("ball")], terrain="ground")
    with pytest.raises(ValueError, match="at most"):
        jaxdyn.RigidContact([jaxdyn.ContactPoint("ball", (0.0, 0.0, float(z)))
                             for z in range(11)])
    with pytest.raises(ValueError, match="no link named"):
        jaxdyn.simulate(BALL, jnp.array([0, 0, 1.0, 1, 0, 0, 0]), jnp.zeros(6), t1=0.1,
                        events=[jaxdyn.RigidContact([jaxdyn.ContactPoint("bal")])])
    with pytest.raises(ValueError, match="friction must be a number or an array of 1"):
        jaxdyn.simulate(BALL, jnp.array([0, 0, 1.0, 1, 0, 0, 0]), jnp.zeros(6), t1=0.1,
                        events=[jaxdyn.RigidContact([jaxdyn.ContactPoint("ball")],
                                                    friction=jnp.ones(2))])
