"""Trees of joints (`RigidBodyTree`) and the articulated-body algorithm.

Oracles: Pinocchio (C++ rigid-body dynamics) on robot models of the `example-robot-data`
package — a 7-dof arm with a gripper (Panda), a quadruped on a free-floating base (Solo-12) and
a humanoid with 44 joints on a free-floating base (Talos), a quadruped with 65 fixed joints
(ANYmal-C); the N-link chain's equations written
by hand; Euler's equations for a free body; closed forms for springs, dampers and loads;
conservation of energy and momentum; finite differences for gradients.
"""

import os
from xml.etree import ElementTree

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
import jaxdyn._chunking
import jaxdyn._system.tree_levels

from helpers import (PENDULUM, assert_close, central_difference, central_difference_params,
                     compiles)

pin = pytest.importorskip("pinocchio")
yourdfpy = pytest.importorskip("yourdfpy")
from robots import Robot, robot_file  # noqa: E402  (needs Pinocchio)


def _formulations(tree, lagrange=True):
    out = {"articulated body": jaxdyn.ArticulatedBody(tree),
           "Kane": jaxdyn.Kane.from_system(tree),
           "Gibbs-Appell": jaxdyn.GibbsAppell.from_system(tree)}
    if lagrange:
        out["Lagrange"] = jaxdyn.Lagrangian.from_system(tree)
    return out


def _pinocchio_case(name, floating, num_states=3, seed=0):
    """The model in jaxdyn and Pinocchio, random states in both conventions, and Pinocchio's
    M (q), bias forces C(q, v) v + g(q), and accelerations for random joint forces."""
    robot = Robot.load(robot_file(name), floating)
    model, data = robot.model, robot.data
    (q_pin, v_pin, tau_pin), (q, u, tau) = robot.random_states(num_states, seed)
    masses, biases, accelerations = [], [], []
    for x, v, f in zip(q_pin, v_pin, tau_pin):
        m = pin.crba(model, data, x)
        masses.append(np.triu(m) + np.triu(m, 1).T)
        biases.append(pin.nonLinearEffects(model, data, x, v).copy())
        accelerations.append(pin.aba(model, data, x, v, f).copy())
    tree = robot.tree
    driven = jaxdyn.RigidBodyTree(tree.links, gravity=tree.gravity,
                                  forces=lambda q, u, p: p["tau"])
    return dict(tree=tree, driven=driven, p=robot.p, q=q, u=u, tau=tau, M=np.stack(masses),
                bias=np.stack(biases), accelerations=np.stack(accelerations),
                permutation=robot.permutation)


# The default run checks the Panda (a fixed base); the floating-base quadruped and the 50-joint
# humanoid compile for longer (40 s and more on two cores): `python -m pytest -m slow`. A
# floating base is checked by default too, against its closed form (planar joint in free fall).
ROBOTS = [("panda.urdf", False),
          pytest.param("solo12.urdf", True, marks=pytest.mark.slow),
          pytest.param("talos_full_v2.urdf", True, marks=pytest.mark.slow)]


@pytest.mark.parametrize("name, floating", ROBOTS)
def test_against_pinocchio(name, floating, monkeypatch):
    """M, the bias forces and the forward dynamics of every formulation against Pinocchio at
    random states, to 1e-10 relative. The recursions run as scans over the links in the
    general (buffered) form for trees, which compiles fastest; the next test runs the Panda
    arm's articulated-body algorithm in straight-line code (the default for its size)."""
    monkeypatch.setattr(jaxdyn._system.tree_levels, "LOOP_MAX", 0)
    case = _pinocchio_case(name, floating)
    perm, p = case["permutation"], case["p"]
    tree = case["tree"]
    m, f = jaxdyn.ArticulatedBody(tree).mass_matrix_and_forcing(0.0, case["q"], case["u"], p)
    m_pin = np.einsum("ij,sjk,lk->sil", perm, np.asarray(m), perm)
    assert_close(m_pin, case["M"], rtol=0, atol=1e-10 * np.max(np.abs(case["M"])))
    bias = -np.einsum("ij,sj->si", perm, np.asarray(f))
    assert_close(bias, case["bias"], rtol=0, atol=1e-10 * np.max(np.abs(case["bias"])))
    p_tau = jax.vmap(lambda tau: {**p, "tau": tau})(jnp.asarray(case["tau"]))
    scale = np.max(np.abs(case["accelerations"]))
    # Lagrange's equations need coordinates whose rates are the speeds: not for a floating
    # base's quaternion.
    formulations = _formulations(case["driven"], lagrange=not floating)
    if name.startswith("talos"):  # one formulation per route for the largest model
        formulations = {k: formulations[k] for k in ("articulated body", "Kane")}
    for label, dynamics in formulations.items():
        accelerations = jax.vmap(dynamics.accelerations)(
            jnp.zeros(len(case["q"])), case["q"], case["u"], p_tau)
        ours = np.einsum("ij,sj->si", perm, np.asarray(accelerations))
        assert_close(ours, case["accelerations"], rtol=0, atol=1e-10 * scale,
                     err_msg=f"{name}, {label}")


def test_a_vmapped_batch_in_chunks_against_pinocchio(monkeypatch):
    """`jax.vmap` of a tree's array programs runs in chunks of a few states
    (`jaxdyn._chunking`): a batch of 19 Panda states in chunks of 8 (two whole chunks and a
    padded one) gives Pinocchio's forward dynamics, mass matrix and the derivatives of the
    accelerations in q and u (`computeABADerivatives`), forward (`jacfwd`) and reverse
    (`grad`) through the batch, to 1e-10 relative."""
    robot = Robot.load(robot_file("panda.urdf"))
    model, data, perm = robot.model, robot.data, robot.permutation
    monkeypatch.setattr(jaxdyn._chunking, "CHUNK", 8)  # (the default may be one state)
    (q_pin, v_pin, tau_pin), (q, u, tau) = robot.random_states(19, seed=3)
    expected, d_dq, d_dv, masses = [], [], [], []
    for x, v, f in zip(q_pin, v_pin, tau_pin):
        expected.append(pin.aba(model, data, x, v, f).copy())
        derivatives = pin.computeABADerivatives(model, data, x, v, f)
        d_dq.append(derivatives[0].copy())
        d_dv.append(derivatives[1].copy())
        m = pin.crba(model, data, x)
        masses.append(np.triu(m) + np.triu(m, 1).T)
    expected, d_dq, d_dv = np.stack(expected), np.stack(d_dq), np.stack(d_dv)
    tree = jaxdyn.RigidBodyTree(robot.tree.links, gravity=robot.tree.gravity,
                                forces=lambda q, u, p: p["tau"])
    dynamics = jaxdyn.ArticulatedBody(tree)
    p_tau = jax.vmap(lambda tau: {**robot.p, "tau": tau})(jnp.asarray(tau))

    def accelerations(q, u, p):
        return dynamics.accelerations(0.0, q, u, p, throw=False)

    def to_pinocchio(x):  # speeds (and, for the Panda's one-coordinate joints, coordinates)
        return np.einsum("ij,...jk,lk->...il", perm, np.asarray(x), perm)

    # The batch runs as a loop over chunks (the rule's `lax.map`: a scan in the program).
    assert "scan" in str(jax.make_jaxpr(jax.vmap(accelerations))(q, u, p_tau))
    ours = np.einsum("ij,sj->si", perm, np.asarray(jax.vmap(accelerations)(q, u, p_tau)))
    scale = np.max(np.abs(expected))
    assert_close(ours, expected, rtol=0, atol=1e-10 * scale)
    m = jax.vmap(dynamics.mass_matrix)(jnp.zeros(19), q, u, p_tau)
    assert_close(to_pinocchio(m), np.stack(masses), rtol=0, atol=1e-10 * np.max(masses))
    jacobians = jax.vmap(jax.jacfwd(accelerations, argnums=(0, 1)))(q, u, p_tau)
    for ours, theirs in zip(jacobians, (d_dq, d_dv)):
        assert_close(to_pinocchio(ours), theirs, rtol=0, atol=1e-10 * np.max(np.abs(theirs)))
    # Reverse mode through the batch: ∂/∂q Σ |u̇|² = 2 (∂u̇/∂q)ᵀ u̇, state by state.
    gradient = jax.grad(lambda q: jnp.sum(jax.vmap(accelerations)(q, u, p_tau) ** 2))(q)
    chained = 2 * np.einsum("sij,si->sj", d_dq, expected)
    assert_close(np.einsum("ij,sj->si", perm, np.asarray(gradient)), chained, rtol=0,
                 atol=1e-10 * np.max(np.abs(chained)))


def test_urdf_parameters_are_the_files_inertial_values():
    case = _pinocchio_case("panda.urdf", False, num_states=2)
    p_tau = jax.vmap(lambda tau: {**case["p"], "tau": tau})(jnp.asarray(case["tau"]))
    accelerations = jax.vmap(jaxdyn.ArticulatedBody(case["driven"]).accelerations)(
        jnp.zeros(2), case["q"], case["u"], p_tau)
    assert_close(np.einsum("ij,sj->si", case["permutation"], np.asarray(accelerations)),
                 case["accelerations"], rtol=0,
                 atol=1e-10 * np.max(np.abs(case["accelerations"])))
    path = robot_file("panda.urdf")
    tree, p = jaxdyn.from_urdf(path)
    constant_tree, none = jaxdyn.from_urdf(path, parameters=False)
    assert none is None
    assert_close(p["panda_link1"]["mass"], 4.970684, rtol=1e-15)
    q, u = np.linspace(-0.5, 0.5, tree.num_coordinates), np.linspace(0.3, -0.3, tree.num_speeds)
    assert_close(jaxdyn.ArticulatedBody(tree).accelerations(0.0, q, u, p),
                 jaxdyn.ArticulatedBody(constant_tree).accelerations(0.0, q, u, None),
                 rtol=1e-13, atol=1e-13)
    # <dynamics damping="c"> is a damper −c q̇ on the joint: M (u̇ − u̇ without) = −c u
    undamped, p_undamped = jaxdyn.from_urdf(path, damping=False)
    damping = {j.find("child").get("link"): float(j.find("dynamics").get("damping", 0.0))
               for j in ElementTree.parse(path).getroot().iter("joint")
               if j.find("dynamics") is not None}
    assert damping and "damping" not in p_undamped["panda_link1"]
    c = np.zeros(tree.num_speeds)
    for link, rows in tree.speed_slices().items():
        c[rows] = damping.get(link, 0.0)
    dynamics = jaxdyn.ArticulatedBody(tree)
    difference = (dynamics.accelerations(0.0, q, u, p)
                  - jaxdyn.ArticulatedBody(undamped).accelerations(0.0, q, u, p_undamped))
    assert_close(dynamics.mass_matrix(0.0, q, u, p) @ difference, -c * u, rtol=1e-12,
                 atol=1e-13)


def test_urdf_closed_loop_is_refused(tmp_path):
    loop = """<robot name="loop">
      <link name="a"/><link name="b"/><link name="c"/>
      <joint name="ab" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
      <joint name="bc" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
      <joint name="ac" type="revolute"><parent link="a"/><child link="c"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
    </robot>"""
    path = tmp_path / "loop.urdf"
    path.write_text(loop)
    with pytest.raises(ValueError, match="closed loop"):
        jaxdyn.from_urdf(path)


# ---------------------------------------------------------------------------------------------
# The N-link chain against its equations written by hand
# ---------------------------------------------------------------------------------------------

ROD = {"m": 1.3, "l": 0.7, "g": 9.81}


def chain_tree(n):
    """N uniform rods hinged end to end, swinging about z; at rest they hang along −y."""
    inertia = jnp.diag(jnp.array([1.0, 0.0, 1.0])) * ROD["m"] * ROD["l"] ** 2 / 12
    links = [jaxdyn.Link(f"rod{i}", jaxdyn.Revolute((0, 0, 1)),
                         parent=None if i == 0 else f"rod{i - 1}",
                         translation=(0.0, 0.0 if i == 0 else -ROD["l"], 0.0),
                         mass=ROD["m"], com=(0.0, -ROD["l"] / 2, 0.0), inertia=inertia)
             for i in range(n)]
    return jaxdyn.RigidBodyTree(links, gravity=jnp.array([0.0, -ROD["g"], 0.0]))


def chain_by_hand(theta, omega):
    """Absolute angles θ from the downward vertical: M_ij = a_ij cos(θ_i − θ_j) + δ_ij m l²/12,
    a = m l² CᵀC with C_ki = 1 (i < k), ½ (i = k); θ̈ = M⁻¹ f."""
    n = len(theta)
    m, l, g = ROD["m"], ROD["l"], ROD["g"]
    index = np.arange(n)
    c = np.where(index[None, :] < index[:, None], 1.0, 0.0) + 0.5 * np.eye(n)
    a = m * l**2 * c.T @ c
    diff = theta[:, None] - theta[None, :]
    mass = a * np.cos(diff) + np.eye(n) * m * l**2 / 12
    forcing = -(a * np.sin(diff)) @ omega**2 - m * g * l * c.sum(axis=0) * np.sin(theta)
    return np.linalg.solve(mass, forcing)


@pytest.mark.parametrize("n", [3, pytest.param(20, marks=pytest.mark.slow)])
def test_chain_against_hand_written_equations(n, monkeypatch):
    """Relative joint angles q: θ = cumsum(q), θ̈ = cumsum(q̈). N = 3 runs the recursions as a
    Python loop, N = 20 as a scan (the form of chains of `CHAIN_LOOP_MIN` links or more: the
    carry is the parent's state); and the scan once more for N = 3 (LOOP_MAX lowered)."""
    rng = np.random.default_rng(n)
    q, u = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    absolute = chain_by_hand(np.cumsum(q), np.cumsum(u))
    expected_relative = np.diff(np.concatenate([[0.0], absolute]))
    tree = chain_tree(n)
    assert tree.scan_head() == (n if n < jaxdyn._system.tree_levels.CHAIN_LOOP_MIN else 0)
    for label, dynamics in _formulations(tree).items():
        assert_close(dynamics.accelerations(0.0, q, u, None), expected_relative, rtol=0,
                     atol=1e-10 * np.max(np.abs(expected_relative)), err_msg=label)
    if n == 3:
        monkeypatch.setattr(jaxdyn._system.tree_levels, "LOOP_MAX", 1)
        tree = chain_tree(n)  # a new tree: nothing compiled for it yet
        assert_close(jaxdyn.ArticulatedBody(tree).accelerations(0.0, q, u, None),
                     expected_relative, rtol=0, atol=1e-10 * np.max(np.abs(expected_relative)))


# ---------------------------------------------------------------------------------------------
# Free, spherical and planar joints
# ---------------------------------------------------------------------------------------------

INERTIA = np.diag([0.3, 0.5, 0.8]) + 0.05 * np.ones((3, 3))


def test_free_body_follows_eulers_equations():
    """A torque-free body with its centre of mass at its origin: I ω̇ = −ω × I ω, and the body-
    axes velocity of its centre rotates against ω: v̇ = −ω × v (constant in the world)."""
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("body", jaxdyn.Free(), mass=2.0,
                                             inertia=jnp.asarray(INERTIA))])
    quaternion = np.array([0.9, 0.1, -0.3, 0.2])
    q = np.concatenate([[0.1, 0.2, 0.3], quaternion / np.linalg.norm(quaternion)])
    v, omega = np.array([0.4, -0.1, 0.7]), np.array([1.1, -0.6, 2.3])
    expected = np.concatenate([-np.cross(omega, v),
                               np.linalg.solve(INERTIA, -np.cross(omega, INERTIA @ omega))])
    for label, dynamics in _formulations(tree, lagrange=False).items():
        assert_close(dynamics.accelerations(0.0, q, np.concatenate([v, omega]), None),
                     expected, rtol=1e-12, err_msg=label)


def test_spherical_pendulum_matches_a_description_by_positions():
    """A body on a ball joint under gravity, against the same body described by its position
    and orientation (quaternion coordinates, speeds the body angular velocity) — Kane on a
    `MultibodySystem`, an independent route to the same equations."""
    com = np.array([0.1, -0.2, -0.6])
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("bob", jaxdyn.Spherical(), mass=1.5,
                                             com=tuple(com), inertia=jnp.asarray(INERTIA))],
                                gravity=jnp.array([0.0, 0.0, -9.81]))

    def orientation(q, p):
        return jaxdyn.rotations.quaternion(q)

    body = jaxdyn.RigidBody(1.5, jnp.asarray(INERTIA),
                            lambda q, p: orientation(q, p) @ jnp.asarray(com), orientation)
    system = jaxdyn.MultibodySystem([body], gravity=jnp.array([0.0, 0.0, -9.81]))

    def kinematic_map(q, p):  # q̇ = ½ q ⊗ (0, ω)
        w, x, y, z = q / jnp.linalg.norm(q)
        return 0.5 * jnp.array([[-x, -y, -z], [w, -z, y], [z, w, -x], [-y, x, w]])

    reference = jaxdyn.Kane(system, kinematic_map)
    quaternion = np.array([0.8, 0.3, -0.4, 0.2])
    q, u = quaternion / np.linalg.norm(quaternion), np.array([0.7, -1.2, 0.5])
    expected = reference.accelerations(0.0, q, u, None)
    for label, dynamics in _formulations(tree, lagrange=False).items():
        assert_close(dynamics.accelerations(0.0, q, u, None), expected, rtol=1e-12, atol=1e-12,
                     err_msg=label)
        assert_close(dynamics.energy(0.0, q, u, None), reference.energy(0.0, q, u, None),
                     rtol=1e-13)


def test_planar_joint_free_fall_and_spin():
    """A planar body (plane normal to z) under gravity −y in the plane: its centre falls with
    g, and with no torque about its centre its rate of turn is constant — checked through the
    world motion of the centre after a short simulation, its origin a distance c from the
    centre."""
    c = 0.3
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("plate", jaxdyn.Planar(), mass=2.0,
                                             com=(c, 0.0, 0.0),
                                             inertia=jnp.diag(jnp.array([0.1, 0.2, 0.25])))],
                                gravity=jnp.array([0.0, -9.81, 0.0]))
    q0, u0 = np.array([0.0, 0.0, 0.4]), np.array([0.0, 0.0, 1.5])
    # body-axes velocity of the origin when the centre is at rest: v = −ω × c = (0, −ω c, 0)
    u0[1] = -u0[2] * c
    t1 = 0.8
    for label, dynamics in _formulations(tree).items():
        # Lagrange's speeds are q̇ = K(q) u
        speeds = tree.coordinate_rates(0.0, q0, u0, None) if label == "Lagrange" else u0
        sol = jaxdyn.simulate(dynamics, q0, speeds, None, t1=t1)
        x, y, theta = np.asarray(sol.q[-1])
        centre = np.array([x + c * np.cos(theta), y + c * np.sin(theta)])
        start = np.array([c * np.cos(0.4), c * np.sin(0.4)])
        assert_close(centre, start + np.array([0.0, -0.5 * 9.81 * t1**2]), rtol=0, atol=1e-9,
                     err_msg=label)
        assert_close(theta, 0.4 + 1.5 * t1, rtol=1e-10, err_msg=label)


# ---------------------------------------------------------------------------------------------
# Springs, dampers, loads; conservation; gradients
# ---------------------------------------------------------------------------------------------


def test_pendulum_with_spring_damper_motor_and_tip_force():
    """One rod about z, hanging along −y: I_O θ̈ = −k (θ − θ₀) − c θ̇ + τ − m g (l/2) sin θ
    + F_x l cos θ for a horizontal force F_x at the tip (world x)."""
    m, l, g, k, c, rest, tau, fx = 1.3, 0.7, 9.81, 4.0, 0.3, 0.2, 0.5, 1.7
    link = jaxdyn.Link("rod", jaxdyn.Revolute((0, 0, 1)), mass=lambda p: p["m"],
                       com=(0.0, -l / 2, 0.0),
                       inertia=jnp.diag(jnp.array([1.0, 0.0, 1.0])) * m * l**2 / 12,
                       stiffness=lambda p: p["k"], damping=c, rest=rest)
    tree = jaxdyn.RigidBodyTree(
        [link], gravity=jnp.array([0.0, -g, 0.0]),
        forces=lambda q, u, p: jnp.full(1, tau),
        loads=[jaxdyn.LinkLoad("rod", force=lambda q, u, p: jnp.array([fx, 0.0, 0.0]),
                               point=(0.0, -l, 0.0))])
    theta, omega = 0.6, -0.8
    inertia_o = m * l**2 / 3
    expected = (-k * (theta - rest) - c * omega + tau - m * g * l / 2 * np.sin(theta)
                + fx * l * np.cos(theta)) / inertia_o
    for label, dynamics in _formulations(tree).items():
        assert_close(dynamics.accelerations(0.0, np.array([theta]), np.array([omega]),
                                            {"m": m, "k": k}), [expected], rtol=1e-12,
                     err_msg=label)


def test_fixed_joints_are_welded_into_their_parents():
    """A rod about z on a stand welded to the world (placed at (0.1, 0.2, 0), turned by φ about
    z), with a tool on a fixed joint at its tip (turned 90° about x: its inertia diag(a, b, c)
    contributes b about z; centre of mass d beyond the tip; a horizontal force F_x at e beyond
    the tip): (m l²/3 + m_t (l + d)² + b) θ̈ = −g (m l/2 + m_t (l + d)) sin(θ + φ)
    + F_x (l + e) cos(θ + φ). The articulated-body algorithm runs on one link
    (`merge_fixed`); Kane's equations on all three."""
    m, l, g, m_t, d, e, fx, phi = 1.3, 0.7, 9.81, 0.4, 0.15, 0.25, 1.7, 0.3
    a, b, c = 0.02, 0.05, 0.03
    turn = np.array([[np.cos(phi), -np.sin(phi), 0.0], [np.sin(phi), np.cos(phi), 0.0],
                     [0.0, 0.0, 1.0]])
    tree = jaxdyn.RigidBodyTree([
        jaxdyn.Link("stand", jaxdyn.Fixed(), translation=(0.1, 0.2, 0.0), rotation=turn,
                    mass=5.0, com=(0.0, 0.3, 0.0), inertia=jnp.eye(3)),
        jaxdyn.Link("rod", jaxdyn.Revolute((0, 0, 1)), parent="stand", mass=m,
                    com=(0.0, -l / 2, 0.0),
                    inertia=jnp.diag(jnp.array([1.0, 0.0, 1.0])) * m * l**2 / 12),
        jaxdyn.Link("tool", jaxdyn.Fixed(), parent="rod", translation=(0.0, -l, 0.0),
                    rotation=[[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
                    mass=lambda p: p["m_t"], com=(0.0, 0.0, d),
                    inertia=jnp.diag(jnp.array([a, b, c]))),
    ], gravity=jnp.array([0.0, -g, 0.0]),
        loads=[jaxdyn.LinkLoad("tool", force=lambda q, u, p: jnp.array([fx, 0.0, 0.0]),
                               point=(0.0, 0.0, e)),
               jaxdyn.LinkLoad("stand", force=lambda q, u, p: jnp.array([0.0, 1.0, 0.0]))])
    assert [link.name for link in tree.merge_fixed().links] == ["rod"]
    theta, omega = 0.6, -0.8
    angle = theta + phi
    expected = ((-g * (m * l / 2 + m_t * (l + d)) * np.sin(angle) + fx * (l + e) * np.cos(angle))
                / (m * l**2 / 3 + m_t * (l + d)**2 + b))
    for dynamics in (jaxdyn.ArticulatedBody(tree), jaxdyn.Kane.from_system(tree)):
        assert_close(dynamics.accelerations(0.0, np.array([theta]), np.array([omega]),
                                             {"m_t": m_t}), [expected], rtol=1e-12)


@pytest.mark.parametrize("form", ["levels", pytest.param("scan", marks=pytest.mark.slow),
                                  pytest.param("straight", marks=pytest.mark.slow)])
def test_a_robot_with_many_fixed_joints_against_pinocchio(form, monkeypatch):
    """ANYmal-C hangs 65 of its 78 links (feet, sensors, covers) on fixed joints: the
    articulated-body algorithm welds them into 13 moving links, as Pinocchio does. Forward
    dynamics and M against Pinocchio, with the floating base taken before the other links
    (`scan_head`) and the legs level by level in straight-line code (the default for 13
    branched links), and (slow set) in a scan over the levels and link by link."""
    if form == "scan":
        monkeypatch.setattr(jaxdyn._system.tree_levels, "LOOP_MAX", 0)
    if form == "straight":
        monkeypatch.setattr(jaxdyn._system.tree_levels, "LEVELS_MIN", 14)
    case = _pinocchio_case("anymal_c_simple_description/urdf/anymal.urdf", True, num_states=2)
    perm, p = case["permutation"], case["p"]
    assert len(case["tree"].links) == 78 and len(case["tree"].merge_fixed().links) == 13
    assert case["tree"].merge_fixed().scan_head() == (13 if form == "straight" else 1)
    dynamics = jaxdyn.ArticulatedBody(case["driven"])
    p_tau = jax.vmap(lambda tau: {**p, "tau": tau})(jnp.asarray(case["tau"]))
    accelerations = jax.vmap(dynamics.accelerations)(jnp.zeros(2), case["q"], case["u"], p_tau)
    assert_close(np.einsum("ij,sj->si", perm, np.asarray(accelerations)),
                 case["accelerations"], rtol=0,
                 atol=1e-10 * np.max(np.abs(case["accelerations"])))
    m = jax.vmap(dynamics.mass_matrix)(jnp.zeros(2), case["q"], case["u"], p_tau)
    assert_close(np.einsum("ij,sjk,lk->sil", perm, np.asarray(m), perm), case["M"], rtol=0,
                 atol=1e-10 * np.max(np.abs(case["M"])))


def _floating_arm():
    """A free-floating base with a two-link arm (revolute about y and x) and a ball joint."""
    inertia = jnp.asarray(INERTIA)
    return jaxdyn.RigidBodyTree([
        jaxdyn.Link("base", jaxdyn.Free(), mass=3.0, com=(0.05, 0.0, 0.1), inertia=inertia),
        jaxdyn.Link("upper", jaxdyn.Revolute((0, 1, 0)), parent="base",
                    translation=(0.2, 0.0, 0.1), mass=1.0, com=(0.0, 0.0, 0.3),
                    inertia=0.2 * inertia),
        jaxdyn.Link("lower", jaxdyn.Revolute((1, 0, 0)), parent="upper",
                    translation=(0.0, 0.0, 0.6), mass=0.5, com=(0.0, 0.1, 0.2),
                    inertia=0.1 * inertia),
        jaxdyn.Link("hand", jaxdyn.Spherical(), parent="lower", translation=(0.0, 0.0, 0.4),
                    mass=0.3, com=(0.0, 0.0, 0.05), inertia=0.05 * inertia),
    ])


@pytest.mark.parametrize("form", ["scan", "levels"])
def test_levels_in_ground_axes_against_kane_and_finite_differences(form, monkeypatch):
    """Branched trees beyond straight-line code run their recursions level by level (links of
    one depth together: in a scan, or in straight-line code up to `LOOP_MAX` links) and the
    articulated-body algorithm in ground axes: a floating base taken before the levels, two
    branches of different depths, a ball joint widening the other links to three columns
    (revolute links padded), and a force on a link. Forward dynamics and the mass matrix
    against Kane's equations of the same tree (`LOOP_MAX` or `LEVELS_MIN` lowered so that
    this tree of 7 links takes that form), and the derivatives in q, u against central
    differences."""
    if form == "scan":
        monkeypatch.setattr(jaxdyn._system.tree_levels, "LOOP_MAX", 1)
        monkeypatch.setattr(jaxdyn._system.tree_levels, "POSES_LOOP_MAX", 1)  # poses too
    else:
        monkeypatch.setattr(jaxdyn._system.tree_levels, "LEVELS_MIN", 1)
    inertia = jnp.asarray(INERTIA)
    arm = _floating_arm()
    tree = jaxdyn.RigidBodyTree(list(arm.links) + [
        jaxdyn.Link("leg", jaxdyn.Revolute((0, 0, 1)), parent="base",
                    translation=(-0.2, 0.1, 0.0), mass=0.8, com=(0.0, -0.2, 0.0),
                    inertia=0.3 * inertia),
        jaxdyn.Link("foot", jaxdyn.Prismatic((0, 1, 0)), parent="leg",
                    translation=(0.0, -0.4, 0.0), mass=0.2, com=(0.05, 0.0, 0.0),
                    inertia=0.02 * inertia),
        jaxdyn.Link("finger", jaxdyn.Revolute((0, 1, 0)), parent="lower",
                    translation=(0.1, 0.0, 0.4), mass=0.1, com=(0.0, 0.0, 0.05),
                    inertia=0.01 * inertia),
    ], gravity=jnp.array([0.0, 0.0, -9.81]), loads=[jaxdyn.LinkLoad(
        "hand", force=lambda q, u, p: jnp.array([0.3, -0.2, 0.5]) * (1 + q[0]),
        torque=lambda q, u, p: jnp.array([0.1, 0.0, -0.05]) * u[2], point=(0.0, 0.05, 0.1))])
    assert tree.scan_head() == 1 and not tree._is_chain()
    q = np.asarray(tree.neutral_configuration())
    rng = np.random.default_rng(5)
    q = q + rng.uniform(-0.4, 0.4, q.shape)
    q[3:7] /= np.linalg.norm(q[3:7])
    q[9:13] /= np.linalg.norm(q[9:13])
    q[:3] += [3.0, -2.0, 1.0]  # away from the world's origin
    u = rng.uniform(-1, 1, tree.num_speeds)
    aba = jaxdyn.ArticulatedBody(tree)
    kane = jaxdyn.Kane.from_system(tree)
    expected = kane.accelerations(0.0, q, u, None)
    assert_close(aba.accelerations(0.0, q, u, None), expected, rtol=0,
                 atol=1e-10 * np.max(np.abs(expected)))
    # The links are not in depth-first order (leg and finger come after the hand), so the
    # composite-rigid-body mass matrix reorders its speeds and back.
    assert_close(aba.mass_matrix(0.0, q, u, None), kane.mass_matrix(0.0, q, u, None),
                 rtol=1e-12, atol=1e-14)

    def accelerations(q, u):
        return aba.accelerations(0.0, q, u, None, throw=False)

    d_dq, d_du = jax.jacfwd(accelerations, argnums=(0, 1))(q, u)
    assert_close(d_dq, central_difference(lambda x: accelerations(x, u), q), rtol=0,
                 atol=1e-6 * np.max(np.abs(d_dq)))
    assert_close(d_du, central_difference(lambda x: accelerations(q, x), u), rtol=0,
                 atol=1e-6 * np.max(np.abs(d_du)))


@pytest.mark.slow
def test_free_floating_tree_conserves_energy_and_momentum():
    tree = _floating_arm()
    dynamics = jaxdyn.ArticulatedBody(tree)
    q0 = tree.neutral_configuration()
    q0[7:9] = [0.4, -0.7]
    u0 = np.array([0.1, -0.2, 0.3, 0.5, -0.4, 0.2, 1.0, -1.5, 0.3, 0.8, -0.6])
    ts = np.linspace(0.0, 2.0, 21)
    sol = jaxdyn.simulate(dynamics, q0, u0, None, t1=2.0, ts=ts)
    energy = dynamics.energy(sol.ts, sol.q, sol.u, None)
    assert np.max(np.abs(energy - energy[:1])) < 1e-8 * abs(float(energy[0]))
    linear = jax.vmap(lambda q, u: tree.linear_momentum(0.0, q, u, None))(sol.q, sol.u)
    angular = jax.vmap(lambda q, u: tree.angular_momentum(0.0, q, u, None))(sol.q, sol.u)
    assert np.max(np.abs(linear - linear[:1])) < 1e-9
    assert np.max(np.abs(angular - angular[:1])) < 1e-8
    # the other formulations on the same states
    for label, other in _formulations(tree, lagrange=False).items():
        assert_close(other.accelerations(0.0, sol.q[5], sol.u[5], None),
                     dynamics.accelerations(0.0, sol.q[5], sol.u[5], None), rtol=1e-10,
                     atol=1e-10, err_msg=label)


def test_gradients_with_respect_to_masses_and_inertias():
    """d/dp of a short simulation's final state against central finite differences."""
    def link(name, parent, p_key):
        return jaxdyn.Link(name, jaxdyn.Revolute((0, 0, 1)), parent=parent,
                           translation=(0.0, 0.0 if parent is None else -0.7, 0.0),
                           mass=lambda p, k=p_key: p[k], com=(0.0, -0.35, 0.0),
                           inertia=lambda p, k=p_key: jnp.diag(
                               jnp.array([1.0, 0.0, 1.0])) * p[k + "_I"])

    tree = jaxdyn.RigidBodyTree([link("a", None, "m1"), link("b", "a", "m2")],
                                gravity=jnp.array([0.0, -9.81, 0.0]))
    dynamics = jaxdyn.ArticulatedBody(tree)
    q0, u0 = np.array([0.8, -0.3]), np.array([0.0, 0.5])
    p = {"m1": 1.2, "m1_I": 0.05, "m2": 0.7, "m2_I": 0.03}

    def loss(p):
        sol = jaxdyn.simulate(dynamics, q0, u0, p, t1=1.0, rtol=1e-12, atol=1e-12)
        return jnp.sum(sol.q[-1] ** 2 + 0.1 * sol.u[-1] ** 2)

    grads = jax.grad(loss)(p)
    numeric = central_difference_params(loss, p, step=1e-5)
    for key in p:
        assert_close(grads[key], numeric[key], rtol=1e-6, atol=1e-8, err_msg=key)


def test_tree_errors():
    with pytest.raises(ValueError, match="listed before its parent"):
        jaxdyn.RigidBodyTree([jaxdyn.Link("b", jaxdyn.Revolute(), parent="a"),
                              jaxdyn.Link("a", jaxdyn.Revolute())])
    with pytest.raises(ValueError, match="names must be unique"):
        jaxdyn.RigidBodyTree([jaxdyn.Link("a", jaxdyn.Revolute()),
                              jaxdyn.Link("a", jaxdyn.Revolute(), parent="a")])
    with pytest.raises(ValueError, match="springs and dampers apply to revolute"):
        jaxdyn.Link("a", jaxdyn.Spherical(), stiffness=1.0)
    tree = _floating_arm()
    with pytest.raises(ValueError, match="Lagrange's equations in q̇ do not apply"):
        jaxdyn.Lagrangian.from_system(tree).accelerations(
            0.0, tree.neutral_configuration(), np.zeros(13), None)
    with pytest.raises(ValueError, match="This tree has 13 coordinates"):
        jaxdyn.ArticulatedBody(tree).accelerations(0.0, np.zeros(3), np.zeros(11), None)
    # Kane's and Gibbs–Appell's equations of a tree compare q and u with its sizes
    q = tree.neutral_configuration()
    for dynamics in (jaxdyn.Kane.from_system(tree), jaxdyn.GibbsAppell.from_system(tree)):
        with pytest.raises(ValueError, match="This tree has 11 speeds"):
            dynamics.accelerations(0.0, q, np.zeros(12), None)
        with pytest.raises(ValueError, match="This tree has 11 speeds"):
            jaxdyn.simulate(dynamics, q, np.zeros(12), None, t1=0.1)
    with pytest.raises(ValueError, match="a non-zero 3-vector"):
        jaxdyn.Revolute((0.0, 0.0, 0.0))
    massless = jaxdyn.RigidBodyTree([jaxdyn.Link("a", jaxdyn.Revolute())])
    with pytest.raises(RuntimeError, match="mass matrix is singular"):
        jaxdyn.ArticulatedBody(massless).accelerations(0.0, np.zeros(1), np.zeros(1), None)


def test_example_robots_are_found_by_name():
    """`jaxdyn.example_robot_urdf` finds example-robot-data's files by name, robot, unique
    prefix or path ending, and names the candidates when a name is ambiguous or unknown, by
    names that each find one file."""
    panda = jaxdyn.example_robot_urdf("panda")
    assert panda.endswith("panda_description/urdf/panda.urdf") and os.path.isfile(panda)
    assert jaxdyn.example_robot_urdf("ur5").endswith("ur_description/urdf/ur5_robot.urdf")
    tree, _ = jaxdyn.from_urdf(panda)
    assert tree.num_speeds == 9  # seven arm joints and two fingers
    with pytest.raises(ValueError, match="anymal_b_simple_description.*anymal_c_simple"):
        jaxdyn.example_robot_urdf("anymal")
    anymal_c = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf")
    assert jaxdyn.example_robot_urdf("anymal_c") == anymal_c  # its robot's one file
    with pytest.raises(ValueError, match="No example robot is named 'hal9000'.*panda") as info:
        jaxdyn.example_robot_urdf("hal9000")
    # Every name the error offers finds one file, a different one each.
    offered = str(info.value).split("the collection has: ")[1].rstrip(".").split(", ")
    found = {jaxdyn.example_robot_urdf(name) for name in offered}
    assert len(found) == len(offered) > 60 and anymal_c in found


def test_reverse_mode_through_the_articulated_body_algorithm():
    """`jax.linearize` and `jax.grad` of the Panda's forward dynamics (reverse mode; its
    batched array program is chunked) against a central difference: a custom_vmap's own JVP
    could not be linearised by JAX."""
    robot = Robot.load(robot_file("panda.urdf"))
    arm = jaxdyn.ArticulatedBody(robot.tree)
    (_, _, _), (q, u, _) = robot.random_states(1, seed=5)
    q, u = jnp.asarray(q[0]), jnp.asarray(u[0])
    direction = jnp.linspace(-1.0, 1.0, q.shape[0])

    def accelerations(q):
        return arm.accelerations(0.0, q, u, robot.p)

    _, linear = jax.linearize(accelerations, q)
    h = 1e-6
    central = (accelerations(q + h * direction) - accelerations(q - h * direction)) / (2 * h)
    assert_close(linear(direction), central, rtol=1e-6, atol=1e-6)
    gradient = jax.grad(lambda q: jnp.sum(accelerations(q)))(q)
    assert_close(gradient @ direction, jnp.sum(central), rtol=1e-6, atol=1e-6)


def test_later_calls_of_the_robotics_functions_and_a_gradient_compile_nothing():
    """Called again with a new state of the same shapes, the articulated-body algorithm,
    inverse dynamics, a frame's pose and Jacobian, the regressor and a gradient through
    `simulate` reuse their programs (XLA's compile events counted)."""
    tree = chain_tree(3)
    robot = jaxdyn.ArticulatedBody(tree)

    def loss(q0):  # a pendulum's: the same path through `simulate`, less to compile
        return jnp.sum(jaxdyn.simulate(PENDULUM.dynamics, q0[:1], np.zeros(1), PENDULUM.params,
                                       t1=0.5).q[-1] ** 2)

    gradient = jax.grad(loss)

    def calls(q):
        u, ud = np.full(3, 0.2), np.full(3, -0.1)
        return (robot.accelerations(0.0, q, u), robot.residual(0.0, q, u, ud),
                jaxdyn.frame_pose(tree, "rod2", q), jaxdyn.frame_jacobian(tree, "rod2", q),
                jaxdyn.inverse_dynamics_regressor(tree, q, u, ud), gradient(q))

    first = calls(np.array([0.1, 0.2, 0.3]))
    with compiles() as count:
        second = calls(np.array([0.4, -0.2, 0.1]))
    assert count() == 0
    # The new state was used: inverse dynamics of the forward dynamics' accelerations is zero.
    np.testing.assert_allclose(robot.residual(0.0, np.array([0.4, -0.2, 0.1]), np.full(3, 0.2),
                                              second[0]), 0.0, atol=1e-12)
    assert not np.allclose(first[1], second[1])


def test_kanes_and_gibbs_appells_first_simulate_of_a_tree_compiles_the_solve_alone():
    """The check of the callbacks' indexing, traced with the solve, evaluates the user's
    callbacks only: not the kinematic matrix, whose blocks of constants (a revolute joint's
    1) it would evaluate one operation at a time, a program each (two per joint). Kane's
    and Gibbs–Appell's equations of the same chain then agree."""
    tree = chain_tree(4)
    q0, u0 = np.array([0.4, -0.3, 0.2, 0.1]), np.array([0.5, 0.0, -0.4, 0.3])
    finals = []
    for dynamics in (jaxdyn.Kane.from_system(tree), jaxdyn.GibbsAppell.from_system(tree)):
        with compiles() as count:
            sol = jaxdyn.simulate(dynamics, q0, u0, None, t1=0.3, rtol=1e-11, atol=1e-11)
        # the solve's program, and at most one small program of diffrax's own (its result
        # code's first `bitwise_or` in a process)
        assert count() <= 2, count()
        finals.append(np.concatenate([sol.q[-1], sol.u[-1]]))
    assert_close(finals[0], finals[1], rtol=0, atol=1e-9)


def test_parameters_changed_in_place_are_read_again_and_not_kept_alive():
    """The dispatch remembers a robot's parameters by the identities of their arrays (not
    read again at each call): a dict changed in place, an array replaced by a Python float,
    gives Pinocchio's forward dynamics of the changed model, the same values as NumPy arrays
    compile nothing, and no call keeps the arrays alive."""
    import gc
    import weakref

    path = jaxdyn.example_robot_urdf("panda")
    tree, p = jaxdyn.from_urdf(path, damping=False)
    body = jaxdyn.ArticulatedBody(tree)
    model = pin.buildModelFromUrdf(path)
    rng = np.random.default_rng(11)
    q, u = rng.uniform(-1, 1, 9), rng.normal(size=9)
    for doubled in (False, True, True):  # the last: the changed parameters again
        if doubled and model.inertias[4].mass < 3.5:
            p["panda_link4"]["mass"] = 2 * float(p["panda_link4"]["mass"])
            model.inertias[4].mass = 2 * model.inertias[4].mass
        expected = pin.aba(model, model.createData(), q, u, np.zeros(9))
        assert_close(body.accelerations(0.0, q, u, p), expected, rtol=0, atol=1e-10)
        assert_close(body.residual(0.0, q, u, expected, p), np.zeros(9), rtol=0, atol=1e-10)
    with compiles() as count:  # the same shapes as NumPy arrays: the same program
        assert_close(body.accelerations(0.0, q, u, jax.tree.map(np.asarray, p)), expected,
                     rtol=0, atol=1e-10)
    assert count() == 0
    com = weakref.ref(p["panda_link4"]["com"])
    del p
    gc.collect()
    assert com() is None


def test_locked_joints_are_pinocchios_reduced_model():
    """`from_urdf(..., locked=...)` welds the Panda's fingers at zero: its mass matrix and
    forward dynamics are those of Pinocchio's `buildReducedModel` at the zero reference, and
    an unknown joint name is an error."""
    path = jaxdyn.example_robot_urdf("panda")
    fingers = ("panda_finger_joint1", "panda_finger_joint2")
    tree, p = jaxdyn.from_urdf(path, locked=fingers, damping=False)
    model = pin.buildModelFromUrdf(path)
    reduced = pin.buildReducedModel(model, [model.getJointId(f) for f in fingers],
                                    pin.neutral(model))
    data = reduced.createData()
    rng = np.random.default_rng(3)
    q, u, tau = rng.uniform(-1, 1, 7), rng.normal(size=7), rng.normal(size=7)
    assert tree.num_coordinates == reduced.nq == 7
    body = jaxdyn.ArticulatedBody(tree)
    assert_close(body.mass_matrix(0.0, q, u, p), pin.crba(reduced, data, q), rtol=0, atol=1e-12)
    driven = jaxdyn.Controlled(body, input_map=list(range(7)), inputs=jnp.asarray(tau))
    assert_close(driven.accelerations(0.0, q, u, p), pin.aba(reduced, data, q, u, tau),
                 rtol=0, atol=1e-11)
    with pytest.raises(ValueError, match="not in the file"):
        jaxdyn.from_urdf(path, locked=("panda_joint8_typo",))
