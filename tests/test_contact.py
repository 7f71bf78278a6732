"""Compliant contact (`jaxdyn.Contact`, `jaxdyn.HuntCrossley`) against closed forms: a block
sliding to rest, held on a slope by static friction and sliding down a steeper one, a ball
rolling without slipping, resting forces against the weight, two balls colliding (Hertz's
impact, momentum), a capsule lying flat, and derivatives against finite differences.
ANYmal-C standing on its feet is checked on the contact guide's own solve (tests/test_docs.py,
whose program it shares); G1 stands in the slow set."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import assert_close, rotation_of

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


def test_two_particles_collide_by_lagrange_with_exact_derivatives():
    """The head-on elastic impact of two point masses (Lagrange's equations, the spheres given
    as functions of q): the exit speeds of an elastic impact, and the derivative of where the
    second ends up with respect to the stiffness k (which sets the contact time) against a
    central difference."""
    m1, m2, r, v = 1.0, 0.5, 0.05, 2.0
    particles = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * (m1 * qd[:3] @ qd[:3]
                                                          + m2 * qd[3:] @ qd[3:]),
                                  lambda q, p: 0.0 * q[0])
    pair = jaxdyn.ContactPair(jaxdyn.ContactPoint(lambda q, p: q[:3], radius=r),
                              jaxdyn.ContactPoint(lambda q, p: q[3:], radius=r))
    scene = jaxdyn.Contact(particles, [pair], model=jaxdyn.HuntCrossley(
        lambda p: p["k"], 0.0, friction=0.0))
    q0 = jnp.array([-0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    u0 = jnp.array([v, 0.0, 0.0, 0.0, 0.0, 0.0])

    def solve(k):
        return jaxdyn.simulate(scene, q0, u0, {"k": k}, t1=0.1, ts=jnp.array([0.1]),
                               save=("q", "u"), rtol=1e-11, atol=1e-11)

    sol = solve(K)
    assert_close(sol.u[-1, [0, 3]], [(m1 - m2) / (m1 + m2) * v, 2 * m1 / (m1 + m2) * v],
                 rtol=1e-8)
    position = lambda k: solve(k).q[-1, 3]  # noqa: E731
    gradient = jax.grad(position)(jnp.asarray(K))
    h = 1e-3 * K
    assert_close(gradient, (position(K + h) - position(K - h)) / (2 * h), rtol=1e-5)
    assert abs(float(gradient)) > 0  # (the contact time, and so the exit, depends on k)


def test_two_balls_collide_conserving_momentum_with_hertz_impact():
    """Two free balls (1 kg and 0.5 kg, r = 5 cm, no gravity) touch each other
    (`ContactPair`). Head on and elastic (α = μ = 0) their speeds leave as for a perfectly
    elastic impact, v₁' = (m₁ − m₂)/(m₁ + m₂) v, v₂' = 2 m₁/(m₁ + m₂) v, with Hertz's
    greatest penetration δ = (5 m* v²/(4 k))^{2/5} and contact time
    2 (δ/v) ∫₀¹ (1 − x^{5/2})^{−1/2} dx (m* the reduced mass). Glancing, spinning, dissipative
    and with friction, they keep their linear and angular momentum."""
    masses, r, v = (1.0, 0.5), 0.05, 2.0
    tree = jaxdyn.RigidBodyTree(
        [jaxdyn.Link(name, jaxdyn.Free(), mass=m, inertia=0.4 * m * r * r * jnp.eye(3))
         for name, m in zip("ab", masses)], gravity=jnp.zeros(3))
    pair = jaxdyn.ContactPair(jaxdyn.ContactPoint("a", radius=r),
                              jaxdyn.ContactPoint("b", radius=r))
    scene = jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), [pair], model=jaxdyn.HuntCrossley(
        K, lambda p: p["alpha"], friction=lambda p: p["mu"]))
    still = [1.0, 0.0, 0.0, 0.0]
    q0 = np.array([[-0.2, 0.0, 0.0, *still, 0.0, 0.0, 0.0, *still],
                   [-0.2, 0.03, 0.0, *still, 0.0, 0.0, 0.01, *still]])
    u0 = np.zeros((2, 12))
    u0[:, 0] = v
    u0[1, 2:6], u0[1, 9] = (0.3, 0.0, 5.0, 1.0), 2.0  # (speeds in the balls' axes: v, ω)
    p = {"alpha": jnp.array([0.0, 0.3]), "mu": jnp.array([0.0, 0.4])}
    ts = np.linspace(0.0, 0.2, 2001)
    sol = jaxdyn.simulate_batch(scene, q0, u0, p, batched_params=True, t1=ts[-1], ts=ts,
                                save=("q", "u", "contact"), **TOL)
    m1, m2 = masses
    assert_close(sol.u[0, -1, [0, 6]], [(m1 - m2) / (m1 + m2) * v, 2 * m1 / (m1 + m2) * v],
                 rtol=1e-7)
    reduced = m1 * m2 / (m1 + m2)
    deepest = (5 * reduced * v**2 / (4 * K)) ** 0.4
    assert_close(-np.min(sol.contact.gap[0]), deepest, rtol=1e-4)  # (sampled every 0.1 ms)
    gap = np.asarray(sol.contact.gap[0, :, 0])
    crossings = [ts[i] - gap[i] * (ts[i + 1] - ts[i]) / (gap[i + 1] - gap[i])
                 for i in np.flatnonzero(np.sign(gap[1:]) != np.sign(gap[:-1]))]
    integral = 0.4 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)
    assert_close(crossings[1] - crossings[0], 2 * deepest / v * integral, rtol=1e-4)

    def momenta(q, u):
        linear, angular = np.zeros(3), np.zeros(3)
        for i, m in enumerate(masses):
            turn = rotation_of(q[7 * i + 3:7 * i + 7])
            velocity, spin = turn @ u[6 * i:6 * i + 3], turn @ u[6 * i + 3:6 * i + 6]
            linear += m * velocity
            angular += np.cross(q[7 * i:7 * i + 3], m * velocity) + 0.4 * m * r * r * spin
        return linear, angular

    q, u = np.asarray(sol.q[1]), np.asarray(sol.u[1])
    before, after = momenta(q[0], u[0]), momenta(q[-1], u[-1])
    assert np.max(np.asarray(sol.contact.slip_speed[1])) > 0.5  # they rubbed
    assert np.max(np.asarray(sol.contact.normal_force[1])) > 100.0  # and hit
    # (to the solver's tolerance: momentum is conserved by the equations, but the balls'
    # speeds are in their own axes, so its sum is not a linear function of the state)
    assert_close(after[0], before[0], rtol=0, atol=1e-10)
    assert_close(after[1], before[1], rtol=0, atol=1e-10)


def test_a_capsule_from_urdf_falls_and_lies_flat_on_its_two_ends(tmp_path):
    """A rod with a capsule collision (URDF's `<capsule>` extension, as Drake writes it),
    dropped tilted, comes to lie flat: its two end spheres carry half its weight each, its
    axis level at the capsule's radius less the static penetration."""
    r, length, m = 0.02, 0.3, 0.5
    inertia = m * (3 * r * r + length**2) / 12
    (tmp_path / "rod.urdf").write_text(f"""<robot name="rod"><link name="rod">
      <inertial><mass value="{m}"/><inertia ixx="{inertia}" iyy="{inertia}" izz="1e-4"
        ixy="0" ixz="0" iyz="0"/></inertial>
      <collision><origin xyz="0 0 0" rpy="0 1.5707963267948966 0"/>
        <geometry><capsule radius="{r}" length="{length}"/></geometry></collision>
    </link></robot>""")
    tree, p = jaxdyn.from_urdf(tmp_path / "rod.urdf", floating=True)
    ends = jaxdyn.urdf_contact_points(tmp_path / "rod.urdf")
    assert len(ends) == 2 and all(c.radius == r for c in ends)
    assert_close(np.abs(ends[0].point), [length / 2, 0.0, 0.0], atol=1e-15, rtol=0)
    scene = jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), ends,
                           model=jaxdyn.HuntCrossley(K, 20.0, friction=MU))
    tilt = 0.3  # about y: one end 4.4 cm below the other
    q0 = np.array([0.0, 0.0, 0.1, np.cos(tilt / 2), 0.0, np.sin(tilt / 2), 0.0])
    sol = jaxdyn.simulate(scene, q0, np.zeros(6), p, t1=2.0, ts=np.array([2.0]),
                          save=("q", "contact"), **TOL)
    sink = (m * G / 2 / K) ** (2 / 3)
    assert_close(sol.contact.normal_force[-1], [m * G / 2] * 2, rtol=1e-6)
    assert_close(sol.q[-1, 2], r - sink, rtol=1e-6)


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
    with pytest.raises(ValueError, match="two different spheres"):
        jaxdyn.ContactPair(jaxdyn.ContactPoint("box"), jaxdyn.ContactPoint("box"))
    with pytest.raises(ValueError, match="no link named 'ball'"):
        jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), [jaxdyn.ContactPair(
            jaxdyn.ContactPoint("box"), jaxdyn.ContactPoint("ball"))], model=law)
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


@pytest.mark.slow
def test_g1_humanoid_stands_on_its_feet():
    """The G1 humanoid (29 joints, example-robot-data), every joint held at zero by PD control,
    set down 1 cm above the ground on the four collision spheres of each sole: it stands, its
    feet's vertical forces summing to its weight, upright and not sliding. (Slow: the stiff
    PD control of its light wrists takes some 16 000 adaptive steps a second.)"""
    path = jaxdyn.example_robot_urdf("g1_29dof_rev_1_0")
    tree, p = jaxdyn.from_urdf(path, floating=True)
    soles = jaxdyn.urdf_contact_points(path, links=["left_ankle_roll_link",
                                                    "right_ankle_roll_link"])
    assert len(soles) == 8
    joints = tree.num_speeds - 6

    def hold(t, q, u, p):
        return -500.0 * q[7:] - 20.0 * u[6:]

    robot = jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 6 + joints)),
                              inputs=hold)
    scene = jaxdyn.Contact(robot, soles, model=jaxdyn.HuntCrossley(1e6, 1.0, friction=0.8))
    q = jnp.concatenate([jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), jnp.zeros(joints)])
    lowest = min(float(jaxdyn.frame_pose(tree, c.body, q, p, point=c.point)[1][2]) - c.radius
                 for c in soles)
    sol = jaxdyn.simulate(scene, q.at[2].set(0.01 - lowest), jnp.zeros(6 + joints), p, t1=1.0,
                          ts=jnp.array([0.8, 1.0]), save=("q", "contact"), rtol=1e-6, atol=1e-6)
    weight = 9.81 * sum(float(link["mass"]) for link in p.values())
    assert_close(np.sum(np.asarray(sol.contact.force[-1, :, 2])), weight, rtol=2e-3)
    assert float(sol.q[-1, 3]) > 0.999  # upright: the base's quaternion near the identity
    moved = np.asarray(sol.contact.position[1, :, :2] - sol.contact.position[0, :, :2])
    assert np.max(np.abs(moved)) < 1e-3
