"""Compliant contact (`jaxdyn.Contact`, `jaxdyn.HuntCrossley`) against closed forms: a block
sliding to rest, held on a slope by static friction and sliding down a steeper one, a ball
rolling without slipping, resting forces against the weight, and derivatives against finite
differences."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import assert_close

G, MU, K, C = 9.81, 0.5, 1e6, 3.0
MASS, SIZE = 1.0, (0.2, 0.1, 0.05)
TOL = dict(rtol=1e-8, atol=1e-8)


def _box_scene():
    """A box (free body) touching a slope of angle p["slope"] at its four lower corners."""
    a, b, h = SIZE
    inertia = MASS / 12 * jnp.diag(jnp.array([b * b + h * h, a * a + h * h, a * a + b * b]))
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("box", jaxdyn.Free(), mass=MASS, inertia=inertia)],
                                gravity=jnp.array([0.0, 0.0, -G]))
    corners = [jaxdyn.ContactPoint("box", (sx * a / 2, sy * b / 2, -h / 2))
               for sx in (-1, 1) for sy in (-1, 1)]
    return jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), corners,
                          jaxdyn.Plane.inclined(lambda p: p["slope"]),
                          jaxdyn.HuntCrossley(K, C, friction=lambda p: p["mu"]))


def _resting_on(slope):
    """The box's coordinates resting flat on the slope (sunk by its static penetration)."""
    sink = (MASS * G * np.cos(slope) / 4 / K) ** (2 / 3)
    normal = np.array([np.sin(slope), 0.0, np.cos(slope)])
    return np.array([*(normal * (SIZE[2] / 2 - sink)), np.cos(slope / 2), 0.0,
                     np.sin(slope / 2), 0.0])


SLOPES = np.radians([0.0, 20.0, 35.0])  # sliding to rest, held (tan γ < μ), sliding down
V0 = 2.0
TS = np.linspace(0.0, 0.6, 7)


@functools.cache
def _boxes():
    """One batch, one compiled solve: the box on flat ground pushed at V0 along x, and at rest
    on slopes of 20° and 35°."""
    q0 = np.stack([_resting_on(s) for s in SLOPES])
    u0 = np.zeros((3, 6))
    u0[0, 0] = V0  # (speeds in the box's axes: v then ω)
    p = {"slope": jnp.asarray(SLOPES), "mu": jnp.full(3, MU)}
    return jaxdyn.simulate_batch(_box_scene(), q0, u0, p, batched_params=True, t1=TS[-1],
                                 ts=TS, save=("q", "u", "contact"), **TOL)


def _downhill(slope):
    return np.array([np.cos(slope), 0.0, -np.sin(slope)])


def test_block_slides_to_rest_at_the_coulomb_stopping_distance():
    """Pushed at v₀ on flat ground, the box stops after v₀²/(2 μ g) (up to the tangential
    spring's travel μ W/(√δ k), where the ground holds it when it sticks) and stays put."""
    sol = _boxes()
    x = np.asarray(sol.q[0, :, 0])
    stop = V0**2 / (2 * MU * G)
    depth = (MASS * G / 4 / K) ** (2 / 3)
    travel = MU * MASS * G / 4 / (np.sqrt(depth) * K)
    assert abs(x[-1] - stop) < 2 * travel
    # decelerating at μ g while sliding (t = 0.1, 0.2 s), then at rest
    assert_close(sol.u[0, 1:3, 0], V0 - MU * G * TS[1:3], rtol=1e-3)
    # (it rocks on its corners' springs a while, at a thousandth of v₀ by 0.6 s)
    assert np.max(np.abs(sol.u[0, -1])) < 1e-3 * V0 and abs(x[-1] - x[-2]) < 1e-5


def test_static_friction_holds_the_block_below_the_friction_angle():
    """tan 20° < μ: the box stays where it was put (it settles by the spring's travel, a
    fraction of a millimetre, and then does not creep)."""
    sol = _boxes()
    travel = (np.asarray(sol.q[1, :, :3]) - _resting_on(SLOPES[1])[:3]) @ _downhill(SLOPES[1])
    assert np.all(np.abs(travel) < 2e-4)
    assert abs(travel[-1] - travel[-3]) < 1e-8  # held, not creeping
    assert np.max(np.abs(sol.u[1, -1])) < 1e-6


def test_block_slides_down_a_steep_slope_at_the_coulomb_acceleration():
    """tan 35° > μ: the box slides with s̈ = g (sin γ − μ cos γ), measured as the rate of its
    speed once it slides."""
    sol = _boxes()
    slope = SLOPES[2]
    velocity = np.asarray(sol.q[2, :, :3])
    speed = np.gradient(velocity @ _downhill(slope), TS)
    rate = (speed[-2] - speed[2]) / (TS[-2] - TS[2])
    assert_close(rate, G * (np.sin(slope) - MU * np.cos(slope)), rtol=2e-3)


def test_resting_forces_carry_the_weight():
    """At rest the contact forces carry the weight: normal forces summing to W cos γ,
    friction forces to W sin γ up the slope, W straight up in all."""
    sol = _boxes()
    weight = MASS * G
    for i, settled in ((0, 1e-4), (1, 1e-6)):  # (the pushed box still rocks a little)
        slope = SLOPES[i]
        assert_close(np.sum(sol.contact.normal_force[i, -1]), weight * np.cos(slope),
                     rtol=settled)
        force = np.sum(np.asarray(sol.contact.force[i, -1]), axis=0)
        assert_close(force, [0.0, 0.0, weight], atol=settled * weight, rtol=0)
    assert np.all(np.asarray(sol.contact.gap) < 0)  # every corner touches throughout


def test_ball_rolls_without_slipping_at_five_sevenths_g_sin_slope():
    """A solid ball (I = 2/5 m r²) on a 20° slope with ample friction rolls: its centre
    accelerates at 5/7 g sin γ and its contact point does not slip."""
    m, r, slope = 0.5, 0.1, np.radians(20.0)
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link(
        "ball", jaxdyn.Free(), mass=m, inertia=0.4 * m * r * r * jnp.eye(3))],
        gravity=jnp.array([0.0, 0.0, -G]))
    scene = jaxdyn.Contact(jaxdyn.ArticulatedBody(tree),
                           [jaxdyn.ContactPoint("ball", radius=r)], jaxdyn.Plane.inclined(slope),
                           jaxdyn.HuntCrossley(K, C, friction=1.0))
    normal = np.array([np.sin(slope), 0.0, np.cos(slope)])
    sink = (m * G * np.cos(slope) / K) ** (2 / 3)
    q0 = jnp.array([*(normal * (r - sink)), 1.0, 0.0, 0.0, 0.0])
    ts = np.linspace(0.0, 0.5, 6)
    sol = jaxdyn.simulate(scene, q0, jnp.zeros(6), t1=0.5, ts=ts, save=("q", "contact"), **TOL)
    s = (np.asarray(sol.q[:, :3]) - np.asarray(q0[:3])) @ _downhill(slope)
    speed = np.gradient(s, ts)
    rate = (speed[-2] - speed[1]) / (ts[-2] - ts[1])
    assert_close(rate, 5 / 7 * G * np.sin(slope), rtol=2e-3)
    assert np.max(np.asarray(sol.contact.slip_speed[1:])) < 1e-3


def test_gradient_through_sliding_against_finite_differences():
    """∂x(t)/∂μ of a block sliding on a point contact, by reverse mode through the solve, equals
    central differences (the solve is smooth while it slides), and ≈ −g t²/2 (Coulomb)."""
    m = 1.0
    particle = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd, lambda q, p: m * G * q[2])
    scene = jaxdyn.Contact(particle, [jaxdyn.ContactPoint(lambda q, p: q)],
                           model=jaxdyn.HuntCrossley(K, C, friction=lambda p: p["mu"]))
    q0 = jnp.array([0.0, 0.0, -(m * G / K) ** (2 / 3)])
    u0 = jnp.array([V0, 0.0, 0.0])

    def position(mu):
        sol = jaxdyn.simulate(scene, q0, u0, {"mu": mu}, t1=0.2, save=("q",), **TOL)
        return sol.q[-1, 0]

    gradient = jax.grad(position)(MU)
    h = 1e-5
    central = (position(MU + h) - position(MU - h)) / (2 * h)
    assert_close(gradient, central, rtol=1e-5)
    assert_close(gradient, -G * 0.2**2 / 2, rtol=2e-2)


def test_contact_errors():
    """Bad scenes are refused at construction, naming the problem."""
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("box", jaxdyn.Free(), mass=1.0,
                                             inertia=jnp.eye(3))])
    law = jaxdyn.HuntCrossley(K, C, friction=MU)
    with pytest.raises(ValueError, match="no link named 'foot'"):
        jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), [jaxdyn.ContactPoint("foot")], model=law)
    with pytest.raises(ValueError, match="contact law"):
        jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), [jaxdyn.ContactPoint("box")])
    with pytest.raises(ValueError, match="radius"):
        jaxdyn.ContactPoint("box", radius=-1.0)
    with pytest.raises(ValueError, match="friction must be finite"):
        jaxdyn.HuntCrossley(K, C, friction=-0.1)
    particle = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.0 * q[0])
    with pytest.raises(ValueError, match="not made from a jaxdyn.RigidBodyTree"):
        jaxdyn.Contact(particle, [jaxdyn.ContactPoint("box")], model=law)


def test_friction_and_stiffness_identified_from_sliding_and_bouncing():
    """`jaxdyn.fit` recovers μ and k from two trajectories of one ball (a point mass with a
    point contact): sliding to rest (its stopping distance v₀²/(2 μ g) sets μ) and bouncing on
    the compliant floor (its rebounds set k at a given dissipation α)."""
    m, c = 1.0, 0.2
    ball = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd, lambda q, p: m * G * q[2])
    scene = jaxdyn.Contact(ball, [jaxdyn.ContactPoint(lambda q, p: q)], model=jaxdyn.HuntCrossley(
        lambda p: p["k"], c, friction=lambda p: p["mu"]))
    true = {"mu": jnp.asarray(0.4), "k": jnp.asarray(2e5)}
    ts = np.linspace(0.0, 0.8, 41)
    starts = [(jnp.array([0.0, 0.0, -(m * G / 2e5) ** (2 / 3)]), jnp.array([V0, 0.0, 0.0])),
              (jnp.array([0.0, 0.0, 0.2]), jnp.zeros(3))]
    experiments = []
    for q0, u0 in starts:
        sol = jaxdyn.simulate(scene, q0, u0, true, t1=ts[-1], ts=ts, save=("q",), rtol=1e-10,
                              atol=1e-10)
        experiments.append(jaxdyn.Experiment(ts, sol.q[:, :3], q0, u0))
    assert np.ptp(np.asarray(experiments[1].observations[:, 2])) > 0.15  # it bounced
    result = jaxdyn.fit(scene, experiments, {"mu": jnp.asarray(0.6), "k": jnp.asarray(5e5)},
                        observe=lambda t, q, u, p: q[:3])
    assert result.converged
    assert_close(result.params["mu"], 0.4, rtol=1e-5)
    assert_close(result.params["k"], 2e5, rtol=1e-3)


ANYMAL_STANCE = np.array([-0.1, 0.7, -1.0, 0.1, 0.7, -1.0, -0.1, -0.7, 1.0, 0.1, -0.7, 1.0])


def test_anymal_dropped_on_the_ground_settles_on_its_feet():
    """ANYmal-C (example-robot-data), its joints held at a standing posture by PD control, is
    dropped from 0.1 and 0.05 m above its standing height: after a second the feet's vertical
    forces sum to its weight and its feet do not slide."""
    path = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf")
    tree, p = jaxdyn.from_urdf(path, floating=True)
    feet = jaxdyn.urdf_contact_points(path, links=["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"])
    assert [f.radius for f in feet] == [0.03] * 4  # the URDF's foot spheres
    stance = jnp.asarray(ANYMAL_STANCE)

    def hold(t, q, u, p):
        return 400.0 * (stance - q[7:]) - 10.0 * u[6:]

    robot = jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 18)),
                              inputs=hold)
    scene = jaxdyn.Contact(robot, feet, model=jaxdyn.HuntCrossley(1e6, 1.0, friction=0.8))
    q = jnp.concatenate([jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), stance])
    soles = [jaxdyn.frame_pose(tree, f.body, q, p, point=f.point)[1][2] - f.radius
             for f in feet]
    standing = -float(min(soles))
    q0 = np.stack([np.asarray(q.at[2].set(standing + drop)) for drop in (0.1, 0.05)])
    sol = jaxdyn.simulate_batch(scene, q0, np.zeros((2, 18)), p, t1=1.2,
                                ts=np.array([0.0, 0.4, 1.0, 1.2]), save=("q", "contact"),
                                rtol=1e-6, atol=1e-6)
    weight = 9.81 * sum(float(link["mass"]) for link in p.values())
    vertical = np.sum(np.asarray(sol.contact.force[:, -1, :, 2]), axis=-1)
    assert_close(vertical, [weight, weight], rtol=1e-3)
    assert np.all(np.asarray(sol.contact.normal_force[:, 0]) == 0)  # dropped from the air
    moved = np.asarray(sol.contact.position[:, -1, :, :2] - sol.contact.position[:, -2, :, :2])
    assert np.max(np.abs(moved)) < 1e-4  # feet planted, not sliding
    assert np.all(np.abs(np.asarray(sol.q[:, -1, 2]) - standing) < 0.02)  # stands at its height


def test_bouncing_with_friction_never_gains_energy_and_frictionless_bounces_differentiate():
    """A ball thrown onto a compliant floor with friction: its energy in flight never grows
    from one flight to the next (the ground's deformation relaxes off contact rather than
    storing the sliding speed), and friction stops its sliding. Without friction, the
    derivative of its height at t through three bounces with respect to the drop height
    equals central differences (the normal law is Lipschitz through touchdown, and no step
    passes over a touchdown)."""
    m = 1.0
    ball = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd, lambda q, p: m * G * q[2])

    def scene(mu):
        # (the tangential response well damped, k_t × 10 ms: a light ball landing while it
        # slides would otherwise spring back and forth on the ground's deformation a while)
        return jaxdyn.Contact(ball, [jaxdyn.ContactPoint(lambda q, p: q)],
                              model=jaxdyn.HuntCrossley(1e5, 0.2, friction=mu,
                                                        tangential_damping=1e3))

    ts = np.linspace(0.0, 1.5, 301)
    sol = jaxdyn.simulate(scene(0.3), jnp.array([0.0, 0.0, 0.1]), jnp.array([1.0, 0.5, 0.0]),
                          t1=ts[-1], ts=ts, save=("q", "u", "contact"), **TOL)
    energy = 0.5 * m * np.sum(np.asarray(sol.u) ** 2, axis=1) + m * G * np.asarray(sol.q[:, 2])
    flying = np.asarray(sol.contact.gap[:, 0]) > 1e-4
    assert flying.sum() > 50 and (~flying).sum() > 20
    assert np.all(np.diff(energy[flying]) <= 1e-9)
    assert np.max(np.abs(np.asarray(sol.u[-1, :2]))) < 1e-3  # no longer sliding (it still
    # bounces: Hunt and Crossley's restitution tends to 1 at low impact speeds)

    def height(h0):  # (three bounces by t = 0.8)
        return jaxdyn.simulate(scene(0.0), jnp.stack([0.0, 0.0, h0]), jnp.zeros(3), t1=0.8,
                               save=("q",), rtol=1e-12, atol=1e-12).q[-1, 2]

    # The derivative of the discrete solve carries no error control of its own: across the
    # stiff touchdowns it is as accurate as the solve's tolerance allows (5e-3 at 1e-8,
    # 3e-5 at 1e-12), and agrees with differences of solves that tight.
    h0, step = jnp.asarray(0.1), 1e-5
    central = (height(h0 + step) - height(h0 - step)) / (2 * step)
    assert_close(jax.grad(height)(h0), central, rtol=1e-4)


def test_height_field_of_a_slope_is_the_inclined_plane():
    """A height field z = −x tan γ is the plane `Plane.inclined(γ)`: the same signed distance
    (exact for a plane, not clamped above or below it) and normal at any point; and a
    curved one, z = a cos(x), has the normal (a sin x, 0, 1)/√(1 + a² sin² x)."""
    slope = np.radians(25.0)
    field = jaxdyn.HeightField(lambda x, y, p: -x * jnp.tan(slope))
    plane = jaxdyn.Plane.inclined(slope)
    points = jnp.array([[0.3, -0.2, 0.5], [-1.0, 2.0, -0.3], [0.0, 0.0, 0.0]])
    for x in points:
        (d_field, n_field), (d_plane, n_plane) = (terrain.distance_and_normal(x, None)
                                                  for terrain in (field, plane))
        assert_close(d_field, d_plane, rtol=1e-14, atol=1e-15)
        assert_close(n_field, n_plane, rtol=1e-14, atol=1e-15)
    a, x = 0.2, 0.7
    hills = jaxdyn.HeightField(lambda x, y, p: a * jnp.cos(x))
    _, normal = hills.distance_and_normal(jnp.array([x, 0.0, 1.0]), None)
    assert_close(normal, np.array([a * np.sin(x), 0.0, 1.0]) / np.hypot(1.0, a * np.sin(x)),
                 rtol=1e-14)
