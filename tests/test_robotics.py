"""The rigid-body algorithms of robotics: inverse dynamics (recursive Newton–Euler and
`residual` on every formulation), frame kinematics and Jacobians, centre of mass, centroidal
momentum, and the inertial-parameter regressors.

Oracles: Pinocchio on the Panda arm (fixed base, fixed and prismatic joints) and on a small
floating-base robot written here as URDF (the quadruped Solo-12 in the slow set); closed forms
for a planar two-link arm and a pendulum; finite differences for the gradients.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import assert_close, central_difference, compiles

pin = pytest.importorskip("pinocchio")
pytest.importorskip("yourdfpy")
from robots import Robot, robot_file  # noqa: E402  (needs Pinocchio)

TOL = 1e-10  # relative to the largest entry of Pinocchio's value


def _close(ours, theirs, err_msg=""):
    theirs = np.asarray(theirs)
    assert_close(ours, theirs, rtol=0, atol=TOL * max(1.0, np.max(np.abs(theirs))),
                 err_msg=err_msg)


def _angular_first(x):
    """Pinocchio's (v, ω) rows → jaxdyn's (ω, v)."""
    return np.concatenate([x[3:], x[:3]], axis=0)


def _no_root_mass(robot):
    """Pinocchio leaves the link fixed to the world out of the potential energy (it does not
    move); jaxdyn counts every link. Compared with the root's mass set to zero."""
    if robot.floating:
        return robot.p
    root = robot.tree.links[0].name
    return {**robot.p, root: {**robot.p[root], "mass": jnp.zeros(())}}


def _pinocchio_references(robot, frames, num_states=3, seed=0):
    model, data = robot.model, robot.data
    (q_pin, v_pin, a_pin), (q, u, ud) = robot.random_states(num_states, seed)
    out = {name: [] for name in ("tau", "com", "vcom", "Jcom", "Ag", "hg", "Y", "yT", "yV",
                                 "T", "V")}
    out["frames"] = {f: {k: [] for k in ("R", "r", "J", "J_local", "v_local", "a", "a_local")}
                     for f in frames}
    for x, v, a in zip(q_pin, v_pin, a_pin):
        out["tau"].append(pin.rnea(model, data, x, v, a).copy())
        pin.forwardKinematics(model, data, x, v, a)
        pin.updateFramePlacements(model, data)
        pin.computeJointJacobians(model, data, x)
        for f in frames:
            fid, record = model.getFrameId(f), out["frames"][f]
            record["R"].append(data.oMf[fid].rotation.copy())
            record["r"].append(data.oMf[fid].translation.copy())
            for key, axes in (("J", pin.LOCAL_WORLD_ALIGNED), ("J_local", pin.LOCAL)):
                record[key].append(_angular_first(pin.getFrameJacobian(model, data, fid, axes)))
            velocity = pin.getFrameVelocity(model, data, fid, pin.LOCAL)
            record["v_local"].append(np.concatenate([velocity.angular, velocity.linear]))
            for key, axes in (("a", pin.LOCAL_WORLD_ALIGNED), ("a_local", pin.LOCAL)):
                classical = pin.getFrameClassicalAcceleration(model, data, fid, axes)
                record[key].append(np.concatenate([classical.angular, classical.linear]))
        out["com"].append(pin.centerOfMass(model, data, x, v).copy())
        out["vcom"].append(data.vcom[0].copy())
        out["Jcom"].append(pin.jacobianCenterOfMass(model, data, x).copy())
        out["Ag"].append(_angular_first(pin.ccrba(model, data, x, v)))
        out["hg"].append(np.concatenate([data.hg.angular, data.hg.linear]))
        out["Y"].append(pin.computeJointTorqueRegressor(model, data, x, v, a).copy())
        out["yT"].append(np.ravel(pin.computeKineticEnergyRegressor(model, data, x, v)))
        out["yV"].append(np.ravel(pin.computePotentialEnergyRegressor(model, data, x)))
        out["T"].append(pin.computeKineticEnergy(model, data, x, v))
        out["V"].append(pin.computePotentialEnergy(model, data, x))
    stacked = {k: np.stack(v) for k, v in out.items() if k != "frames"}
    stacked["frames"] = {f: {k: np.stack(v) for k, v in d.items()}
                         for f, d in out["frames"].items()}
    return stacked, (q, u, ud)


def _ours(robot, frames, q, u, ud):
    """Everything jaxdyn computes, for stacked states: one compiled program."""
    tree, p = robot.tree, robot.p
    dynamics = jaxdyn.ArticulatedBody(tree)

    @jax.jit
    @jax.vmap
    def at(q, u, ud):
        out = {"tau": dynamics.residual(0.0, q, u, ud, p),
               # Pinocchio's convention: the links welded to the world left out.
               "com": jaxdyn.centre_of_mass(tree, q, p, include_fixed=False),
               "vcom": jaxdyn.centre_of_mass_velocity(tree, q, u, p, include_fixed=False),
               "Jcom": jaxdyn.centre_of_mass_jacobian(tree, q, p, include_fixed=False),
               "Ag": jaxdyn.centroidal_momentum_matrix(tree, q, p, include_fixed=False),
               "hg": jaxdyn.centroidal_momentum(tree, q, u, p, include_fixed=False),
               "Y": jaxdyn.inverse_dynamics_regressor(tree, q, u, ud, p),
               "frames": {}}
        out["yT"], out["yV"] = jaxdyn.energy_regressors(tree, q, u, p)
        for f in frames:
            rotation, origin = jaxdyn.frame_pose(tree, f, q, p)
            out["frames"][f] = dict(
                R=rotation, r=origin, J=jaxdyn.frame_jacobian(tree, f, q, p),
                J_local=jaxdyn.frame_jacobian(tree, f, q, p, axes="local"),
                v_local=jaxdyn.frame_velocity(tree, f, q, u, p, axes="local"),
                a=jaxdyn.frame_acceleration(tree, f, q, u, ud, p),
                a_local=jaxdyn.frame_acceleration(tree, f, q, u, ud, p, axes="local"))
        return out

    return at(q, u, ud)


def _compare_with_pinocchio(robot, frames):
    theirs, (q, u, ud) = _pinocchio_references(robot, frames)
    ours = _ours(robot, frames, q, u, ud)
    perm = robot.permutation  # jaxdyn's speeds → Pinocchio's

    def speeds_last(x):  # (…, m) in jaxdyn's speeds → Pinocchio's
        return np.einsum("...j,ij->...i", np.asarray(x), perm)

    _close(speeds_last(ours["tau"]), theirs["tau"], "inverse dynamics (rnea)")
    for f in frames:
        for key in ("R", "r", "v_local", "a", "a_local"):
            _close(ours["frames"][f][key], theirs["frames"][f][key], f"{f}: {key}")
        for key in ("J", "J_local"):
            _close(speeds_last(ours["frames"][f][key]), theirs["frames"][f][key], f"{f}: {key}")
    for key in ("com", "vcom", "hg"):
        _close(ours[key], theirs[key], key)
    for key in ("Jcom", "Ag"):
        _close(speeds_last(ours[key]), theirs[key], key)
    # The regressors: Pinocchio's columns are its joints' bodies (links attached by fixed
    # joints merged in, parameters in the joint's frame: the moving link's frame); each
    # equals jaxdyn's block of that link. Y π and the energies hold with jaxdyn's own π.
    names = [link.name for link in robot.tree.links]
    pi = np.asarray(jaxdyn.inertial_parameters(robot.tree, robot.p)).ravel()
    pi_moving = np.asarray(jaxdyn.inertial_parameters(robot.tree, _no_root_mass(robot))).ravel()
    for j, link in robot.joint_link.items():
        ours_block = slice(10 * names.index(link), 10 * names.index(link) + 10)
        theirs_block = slice(10 * (j - 1), 10 * j)
        _close(speeds_last(ours["Y"][:, :, ours_block].swapaxes(1, 2)).swapaxes(1, 2),
               theirs["Y"][:, :, theirs_block], f"regressor of {link}")
        _close(ours["yT"][:, ours_block], theirs["yT"][:, theirs_block], f"y_T of {link}")
        _close(ours["yV"][:, ours_block], theirs["yV"][:, theirs_block], f"y_V of {link}")
    _close(speeds_last(np.asarray(ours["Y"]) @ pi), theirs["tau"], "Y π")
    _close(np.asarray(ours["yT"]) @ pi, theirs["T"], "y_T π")
    _close(np.asarray(ours["yV"]) @ pi_moving, theirs["V"], "y_V π")


@pytest.fixture(scope="module")
def panda():
    return Robot.load(robot_file("panda.urdf"))


def test_panda_against_pinocchio(panda):
    """Inverse dynamics, frames (a revolute link, the hand on a fixed joint, a finger on a
    prismatic joint, the tool centre point), centre of mass, centroidal momentum and the
    regressors of the Panda arm at random states, against Pinocchio to 1e-10."""
    _compare_with_pinocchio(panda, ["panda_link3", "panda_hand", "panda_leftfinger",
                                    "panda_hand_tcp"])


FLOATING_URDF = """<robot name="hopper">
  <link name="base"><inertial><origin xyz="0.02 -0.01 0.03" rpy="0.1 0.2 0.3"/><mass value="3.0"/>
    <inertia ixx="0.05" ixy="0.002" ixz="-0.001" iyy="0.07" iyz="0.003" izz="0.09"/>
    </inertial></link>
  <link name="thigh"><inertial><origin xyz="0 0 -0.15" rpy="0 0 0"/><mass value="0.8"/>
    <inertia ixx="0.006" ixy="0" ixz="0" iyy="0.006" iyz="0" izz="0.001"/></inertial></link>
  <link name="shank"><inertial><origin xyz="0.01 0 -0.12" rpy="0 0.3 0"/><mass value="0.4"/>
    <inertia ixx="0.003" ixy="0.0001" ixz="0" iyy="0.002" iyz="0" izz="0.0005"/></inertial></link>
  <link name="foot"><inertial><origin xyz="0 0 -0.02" rpy="0 0 0"/><mass value="0.1"/>
    <inertia ixx="0.0001" ixy="0" ixz="0" iyy="0.0001" iyz="0" izz="0.0001"/></inertial></link>
  <link name="slider"><inertial><origin xyz="0 0.01 0" rpy="0 0 0"/><mass value="0.2"/>
    <inertia ixx="0.0002" ixy="0" ixz="0" iyy="0.0003" iyz="0" izz="0.0001"/></inertial></link>
  <joint name="hip" type="revolute"><parent link="base"/><child link="thigh"/>
    <origin xyz="0.1 0.05 -0.05" rpy="0.2 0 0.1"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="10"/></joint>
  <joint name="knee" type="revolute"><parent link="thigh"/><child link="shank"/>
    <origin xyz="0 0 -0.3" rpy="0 0 0"/><axis xyz="0.6 0.8 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="10"/></joint>
  <joint name="ankle" type="fixed"><parent link="shank"/><child link="foot"/>
    <origin xyz="0 0.02 -0.25" rpy="0 0.4 0"/></joint>
  <joint name="rail" type="prismatic"><parent link="base"/><child link="slider"/>
    <origin xyz="-0.1 0 0.05" rpy="0 0 0.5"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="10"/></joint>
</robot>"""


@pytest.fixture(scope="module")
def hopper(tmp_path_factory):
    """A small floating-base robot: a free base, a two-joint leg ending in a foot on a fixed
    joint, and a slider on a prismatic joint; off-diagonal inertias and rotated frames."""
    path = tmp_path_factory.mktemp("urdf") / "hopper.urdf"
    path.write_text(FLOATING_URDF)
    return Robot.load(str(path), floating=True)


def test_floating_base_against_pinocchio(hopper):
    _compare_with_pinocchio(hopper, ["base", "shank", "foot", "slider"])


def test_frame_accelerations_are_the_rates_of_the_frame_velocities_for_every_joint():
    """The classical accelerations by the outward recursion (`frame_acceleration`, world and
    local axes, and the rows of `HeldPoints.velocities_and_accelerations`) against the time
    derivative of the frame's velocity along the motion, d/dt (ω, v_P) in world axes: the
    JVP of `frame_velocity` along (q̇ = K(q) u, u̇), by autodiff; on a tree with every joint
    type (a free base, spherical, planar, prismatic, revolute and fixed joints, rotated joint
    frames) and points off the links' origins. (All in one compiled program, which the test
    compiles sooner than each call's own.)"""
    turn = np.array([[0.0, -1.0, 0.0], [0.6, 0.0, 0.8], [-0.8, 0.0, 0.6]])
    tree = jaxdyn.RigidBodyTree([
        jaxdyn.Link("base", jaxdyn.Free(), mass=2.0),
        jaxdyn.Link("ball", jaxdyn.Spherical(), parent="base", translation=(0.1, -0.05, 0.2),
                    rotation=turn, mass=1.0),
        jaxdyn.Link("plate", jaxdyn.Planar(), parent="ball", translation=(0.0, 0.1, 0.3),
                    mass=1.0),
        jaxdyn.Link("slide", jaxdyn.Prismatic((0.3, 0.4, 1.2)), parent="plate",
                    rotation=turn.T, mass=1.0),
        jaxdyn.Link("arm", jaxdyn.Revolute((1.0, -2.0, 0.5)), parent="slide",
                    translation=(0.2, 0.0, -0.1), mass=1.0),
        jaxdyn.Link("tool", jaxdyn.Fixed(), parent="arm", translation=(0.05, 0.0, 0.1),
                    rotation=turn, mass=0.1)])
    rng = np.random.default_rng(11)
    q = np.asarray(tree.neutral_configuration()) + 0.3 * rng.standard_normal(tree.num_coordinates)
    u, ud = rng.standard_normal(tree.num_speeds), rng.standard_normal(tree.num_speeds)
    frames = {"base": (0.1, 0.2, -0.3), "ball": (0.0, 0.0, 0.0), "plate": (0.2, -0.1, 0.05),
              "slide": (-0.1, 0.3, 0.2), "tool": (0.02, 0.01, -0.04)}
    hold = jaxdyn.HeldPoints.at(tree, list(frames), q, points=list(frames.values()))

    @jax.jit  # (one program for all of it)
    def both(q, u, ud):
        qd = tree.coordinate_rates(0.0, q, u, None)
        out = {}
        for frame, point in frames.items():
            velocity, rates = jax.jvp(
                lambda q, u: jaxdyn.frame_velocity(tree, frame, q, u, point=point), (q, u),
                (qd, ud))
            rotation = jaxdyn.frame_pose(tree, frame, q)[0]
            out[frame] = dict(
                velocity=velocity, rates=rates,
                local=jnp.concatenate([rotation.T @ rates[:3], rotation.T @ rates[3:]]),
                world_recursion=jaxdyn.frame_acceleration(tree, frame, q, u, ud, point=point),
                local_recursion=jaxdyn.frame_acceleration(tree, frame, q, u, ud, point=point,
                                                          axes="local"))
        return out, hold.velocities_and_accelerations(q, u, ud)

    out, (velocities, accelerations) = both(jnp.asarray(q), u, ud)
    for k, frame in enumerate(frames):
        ours = out[frame]
        assert_close(ours["world_recursion"], ours["rates"], rtol=1e-12, atol=1e-12,
                     err_msg=frame)
        assert_close(ours["local_recursion"], ours["local"], rtol=1e-12, atol=1e-12,
                     err_msg=frame)
        assert_close(velocities[3 * k:3 * k + 3], ours["velocity"][3:], rtol=1e-12,
                     atol=1e-12, err_msg=frame)
        assert_close(accelerations[3 * k:3 * k + 3], ours["rates"][3:], rtol=1e-12,
                     atol=1e-12, err_msg=frame)


def test_a_points_jacobian_gives_its_velocity(hopper):
    """J(q) u of a point off a link's origin, in world and local axes, equals that point's
    velocity from the velocity recursion (`frame_velocity`, computed independently of the
    Jacobian's columns), on the floating hopper at random states."""
    tree, p = hopper.tree, hopper.p
    _, (qs, us, _) = hopper.random_states(3, seed=5)
    point = (0.02, -0.01, 0.05)
    for q, u in zip(qs, us):
        for frame in ("shank", "foot"):
            for axes in ("world", "local"):
                jacobian = jaxdyn.frame_jacobian(tree, frame, q, p, point=point, axes=axes)
                velocity = jaxdyn.frame_velocity(tree, frame, q, u, p, point=point, axes=axes)
                assert_close(np.asarray(jacobian) @ np.asarray(u), velocity, rtol=0,
                             atol=1e-12 * (1 + np.max(np.abs(velocity))))


def _held_point_terms(robot, q_pin, v_pin, frame, point):
    """Pinocchio's world position, linear Jacobian (3, nv) and classical acceleration at zero
    joint acceleration of a point fixed in a frame: the frame's own, carried to the point by
    rigid-body kinematics (d = R point: v_P = v + ω × d, a_P = a + ω̇ × d + ω × (ω × d))."""
    model, data = robot.model, robot.data
    fid = model.getFrameId(frame)
    pin.forwardKinematics(model, data, q_pin, v_pin, np.zeros(model.nv))
    pin.updateFramePlacements(model, data)
    pin.computeJointJacobians(model, data, q_pin)
    placement = data.oMf[fid]
    d = placement.rotation @ np.asarray(point)
    jacobian = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
    skew = np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
    omega = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).angular
    classical = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
    curvature = classical.linear + np.cross(classical.angular, d) + np.cross(
        omega, np.cross(omega, d))
    return placement.translation + d, jacobian[:3] - skew @ jacobian[3:], curvature


def test_held_points_against_pinocchio(hopper):
    """Points held in the world (`jaxdyn.HeldPoints`, the foot's sole and the slider):
    the accelerations and constraint forces of Lagrange's equations of the first kind, without
    and with Baumgarte's terms, against the KKT system [M −Jᵀ; J 0] formed in NumPy from
    Pinocchio's mass matrix, bias forces, frame Jacobians and classical accelerations, at
    random states (which violate the holds, so that Baumgarte's position and velocity terms
    count); and the multipliers, the holds' forces on the points, accelerate the centre of
    mass as Newton's second law says."""
    tree, p, model, data = hopper.tree, hopper.p, hopper.model, hopper.data
    frames, points = ["foot", "slider"], np.array([[0.01, 0.0, -0.03], [0.0, 0.02, 0.0]])
    holds = np.array([[0.1, -0.2, -0.5], [-0.1, 0.0, 0.05]])
    held = jaxdyn.HeldPoints(tree, frames, holds, points)
    (q_pin, v_pin, _), (q, u, _) = hopper.random_states(3, seed=11)
    perm = hopper.permutation
    for stabilisation in (None, jaxdyn.Baumgarte(3.0, 5.0)):
        constrained = jaxdyn.Constrained(jaxdyn.ArticulatedBody(tree), holonomic=held,
                                         stabilisation=stabilisation)
        ours = jax.jit(jax.vmap(lambda q, u: (constrained.accelerations(0.0, q, u, p),
                                              constrained.constraint_forces(0.0, q, u, p),
                                              constrained.position_violation(0.0, q, u, p),
                                              constrained.multipliers(0.0, q, u, p))))
        accelerations, forces, violation, ours_multipliers = ours(q, u)
        for k in range(3):
            terms = [_held_point_terms(hopper, q_pin[k], v_pin[k], f, x)
                     for f, x in zip(frames, points)]
            position = np.concatenate([t[0] for t in terms]) - holds.ravel()
            jacobian = np.concatenate([t[1] for t in terms])
            rhs = -np.concatenate([t[2] for t in terms])
            if stabilisation is not None:
                rhs -= 2 * 3.0 * jacobian @ v_pin[k] + 5.0**2 * position
            mass = pin.crba(model, data, q_pin[k])
            mass = np.triu(mass) + np.triu(mass, 1).T
            bias = pin.nonLinearEffects(model, data, q_pin[k], v_pin[k])
            m, c = model.nv, jacobian.shape[0]
            kkt = np.block([[mass, -jacobian.T], [jacobian, np.zeros((c, c))]])
            solution = np.linalg.solve(kkt, np.concatenate([-bias, rhs]))
            a_pin, multipliers = solution[:m], solution[m:]
            scale = 1 + np.max(np.abs(a_pin))
            assert_close(np.asarray(accelerations[k]) @ perm.T, a_pin, rtol=0,
                         atol=1e-10 * scale)
            assert_close(np.asarray(forces[k]) @ perm.T, jacobian.T @ multipliers, rtol=0,
                         atol=1e-10 * (1 + np.max(np.abs(jacobian.T @ multipliers))))
            assert_close(violation[k], position, rtol=0, atol=1e-12)
            # Newton's second law for the whole robot: the holds' forces and gravity
            # accelerate its centre of mass (Pinocchio's, at the accelerations found).
            pin.centerOfMass(model, data, q_pin[k], v_pin[k], a_pin)
            total = pin.computeTotalMass(model)
            assert_close(np.asarray(ours_multipliers[k]).reshape(-1, 3).sum(axis=0),
                         total * (data.acom[0] - model.gravity.linear), rtol=1e-10)


def test_first_kind_residuals_with_held_points_against_pinocchio(hopper):
    """The residuals of Lagrange's equations of the first kind at arbitrary accelerations
    and multipliers, M u̇ − f − Cᵀ λ and C u̇ − c with Baumgarte's terms, which the
    trajectory optimiser differentiates: formed in one pass of the recursive Newton–Euler
    algorithm with the holds' forces as loads (a point on the foot, welded to the shank by a
    fixed joint, and one on the slider), against Pinocchio's `rnea` less Jᵀ λ and its frame
    Jacobians and classical accelerations, at random states."""
    tree, p = hopper.tree, hopper.p
    frames, points = ["foot", "slider"], np.array([[0.01, 0.0, -0.03], [0.0, 0.02, 0.0]])
    holds = np.array([[0.1, -0.2, -0.5], [-0.1, 0.0, 0.05]])
    constrained = jaxdyn.Constrained(
        jaxdyn.ArticulatedBody(tree), holonomic=jaxdyn.HeldPoints(tree, frames, holds, points),
        stabilisation=jaxdyn.Baumgarte(3.0, 5.0))
    (q_pin, v_pin, a_pin), (q, u, ud) = hopper.random_states(3, seed=12)
    forces = np.random.default_rng(13).normal(size=(3, 6)) * 20.0
    first, second = jax.jit(jax.vmap(lambda q, u, ud, forces: constrained.first_kind_residuals(
        0.0, q, u, ud, forces, p)))(q, u, ud, forces)
    for k in range(3):
        terms = [_held_point_terms(hopper, q_pin[k], v_pin[k], f, x)
                 for f, x in zip(frames, points)]
        jacobian = np.concatenate([t[1] for t in terms])
        expected = (pin.rnea(hopper.model, hopper.data, q_pin[k], v_pin[k], a_pin[k])
                    - jacobian.T @ forces[k])
        assert_close(np.asarray(first[k]) @ hopper.permutation.T, expected, rtol=0,
                     atol=1e-11 * (1 + np.max(np.abs(expected))))
        position = np.concatenate([t[0] for t in terms]) - holds.ravel()
        expected = (jacobian @ a_pin[k] + np.concatenate([t[2] for t in terms])
                    + 2 * 3.0 * jacobian @ v_pin[k] + 5.0**2 * position)
        assert_close(second[k], expected, rtol=0, atol=1e-11 * (1 + np.max(np.abs(expected))))


def test_a_held_robots_step_differentiates_as_finite_differences(hopper):
    """The derivative of a shooting problem's step of the hopper with its foot held
    (`HeldPoints`, Baumgarte's terms), formed from the residuals of Lagrange's equations of
    the first kind (the recursive Newton–Euler algorithm and the points' accelerations),
    against central differences of the step, in the state and the inputs, and in where the
    foot is held (an array of the system)."""
    tree, p = hopper.tree, hopper.p
    held = jaxdyn.HeldPoints(tree, ["foot"], [[0.1, -0.2, -0.5]], [[0.01, 0.0, -0.03]])
    plant = jaxdyn.Constrained(jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=[6, 7, 8]),
                               holonomic=held, stabilisation=jaxdyn.Baumgarte(3.0, 5.0))
    problem = jaxdyn.ShootingProblem(plant, lambda q, u, r, p: r, num_nodes=1, dt=0.01,
                                     discretisation=jaxdyn.SemiImplicitEuler())
    _, (q, u, _) = hopper.random_states(1, seed=4)
    n = q.shape[1]
    z = np.concatenate([q[0], u[0], np.random.default_rng(5).normal(size=3)])
    size = z.shape[0] - 3

    def step(z):
        return problem.step(0.0, z[:size], z[size:], p, n)

    derivative = jax.jit(jax.jacfwd(step))(jnp.asarray(z))
    numeric = central_difference(jax.jit(step), z, step=1e-6)
    assert_close(derivative, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(numeric)))

    # The hold's position, an array of the system, as differentiable as the state.
    def moved(position):
        hold = jaxdyn.HeldPoints(tree, ["foot"], position[None], [[0.01, 0.0, -0.03]])
        return eqx.tree_at(lambda problem: problem.dynamics.holonomic, problem,
                           hold).step(0.0, z[:size], z[size:], p, n)

    position = np.array([0.1, -0.2, -0.5])
    derivative = jax.jit(jax.jacfwd(moved))(jnp.asarray(position))
    numeric = central_difference(jax.jit(moved), position, step=1e-6)
    assert_close(derivative, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(numeric)))


def test_held_points_name_a_tree_of_another_size(hopper):
    """HeldPoints of one tree on a system of another size, a hold of the wrong shape and
    moving holds are named at trace time."""
    upright = np.zeros(hopper.tree.num_coordinates)
    upright[3] = 1.0  # the base's unit quaternion (w, x, y, z)
    held = jaxdyn.HeldPoints.at(hopper.tree, ["foot"], upright, hopper.p)
    other, other_p = jaxdyn.from_urdf(robot_file("panda.urdf"))
    with pytest.raises(ValueError, match="HeldPoints holds points of a tree with 10 coord"):
        jaxdyn.Constrained(jaxdyn.ArticulatedBody(other), holonomic=held).accelerations(
            0.0, jnp.zeros(other.num_coordinates), jnp.zeros(other.num_speeds), other_p)
    with pytest.raises(ValueError, match=r"positions must have shape \(2, 3\)"):
        jaxdyn.HeldPoints(hopper.tree, ["foot", "slider"], np.zeros(3))
    with pytest.raises(ValueError, match="scleronomic"):
        jaxdyn.Constrained(jaxdyn.ArticulatedBody(hopper.tree), holonomic=held,
                           time_dependent=True)
    with pytest.raises(ValueError, match="no link named 'fot'"):
        jaxdyn.HeldPoints(hopper.tree, ["fot"], np.zeros((1, 3)))


@pytest.mark.slow
def test_quadruped_against_pinocchio():
    _compare_with_pinocchio(Robot.load(robot_file("solo12.urdf"), floating=True),
                            ["base_link", "FL_FOOT", "HR_LOWER_LEG"])


def test_gradients_against_finite_differences(hopper):
    """∂/∂q of inverse dynamics, a frame's pose and Jacobian, the centre of mass, the
    centroidal momentum matrix and the regressor, forward mode against central differences;
    and ∂τ/∂(mass) by reverse mode."""
    tree, p = hopper.tree, hopper.p
    _, (q, u, ud) = hopper.random_states(1, seed=3)
    q, u, ud = q[0], u[0], ud[0]
    dynamics = jaxdyn.ArticulatedBody(tree)

    def everything(q, p):
        rotation, origin = jaxdyn.frame_pose(tree, "foot", q, p, point=(0.01, 0.0, -0.03))
        return jnp.concatenate([
            dynamics.residual(0.0, q, u, ud, p), rotation.ravel(), origin,
            jaxdyn.frame_jacobian(tree, "foot", q, p).ravel(),
            jaxdyn.frame_acceleration(tree, "slider", q, u, ud, p, axes="local"),
            jaxdyn.centre_of_mass(tree, q, p),
            jaxdyn.centroidal_momentum_matrix(tree, q, p).ravel(),
            jaxdyn.inverse_dynamics_regressor(tree, q, u, ud, p).ravel()])

    compiled = jax.jit(everything)
    derivative = jax.jit(jax.jacfwd(everything))(q, p)
    numeric = central_difference(lambda x: compiled(x, p), q, step=1e-6)
    assert_close(derivative, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(numeric)))

    def torque_norm(mass):
        masses = {**p, "shank": {**p["shank"], "mass": mass}}
        return jnp.sum(dynamics.residual(0.0, q, u, ud, masses) ** 2)

    gradient = jax.grad(torque_norm)(p["shank"]["mass"])
    numeric = central_difference(lambda m: torque_norm(jnp.asarray(m)),
                                 np.asarray(p["shank"]["mass"]))
    assert_close(gradient, numeric, rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# Closed forms
# ---------------------------------------------------------------------------------------------

ARM = {"m1": 1.2, "m2": 0.7, "l1": 0.9, "l2": 0.6, "g": 9.81}


def _planar_arm():
    """Two uniform rods in the xy plane, hinged about z, gravity along −y."""
    links = []
    for i, (m, l) in enumerate(((ARM["m1"], ARM["l1"]), (ARM["m2"], ARM["l2"]))):
        links.append(jaxdyn.Link(
            f"rod{i}", jaxdyn.Revolute((0, 0, 1)), parent=None if i == 0 else "rod0",
            translation=(0.0 if i == 0 else ARM["l1"], 0.0, 0.0), mass=m,
            com=(l / 2, 0.0, 0.0), inertia=jnp.diag(jnp.array([0.0, 1.0, 1.0]) * m * l**2 / 12)))
    links.append(jaxdyn.Link("tip", jaxdyn.Fixed(), parent="rod1",
                             translation=(ARM["l2"], 0.0, 0.0)))
    return jaxdyn.RigidBodyTree(links, gravity=jnp.array([0.0, -ARM["g"], 0.0]))


def _planar_arm_by_hand(q, qd, qdd):
    """The two-link arm's torques M q̈ + C q̇ + G (Spong, Hutchinson and Vidyasagar, Robot
    Modeling and Control, §7.3) and the tip's Jacobian, rows (ω_z, ẋ, ẏ)."""
    m1, m2, l1, l2, g = (ARM[k] for k in ("m1", "m2", "l1", "l2", "g"))
    lc1, lc2, i1, i2 = l1 / 2, l2 / 2, m1 * l1**2 / 12, m2 * l2**2 / 12
    c2, s2 = np.cos(q[1]), np.sin(q[1])
    m11 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * c2) + i1 + i2
    m12 = m2 * (lc2**2 + l1 * lc2 * c2) + i2
    m22 = m2 * lc2**2 + i2
    h = -m2 * l1 * lc2 * s2
    coriolis = np.array([h * qd[1] * (2 * qd[0] + qd[1]), -h * qd[0] ** 2])
    gravity = np.array([(m1 * lc1 + m2 * l1) * g * np.cos(q[0]) + m2 * lc2 * g * np.cos(q.sum()),
                        m2 * lc2 * g * np.cos(q.sum())])
    tau = np.array([[m11, m12], [m12, m22]]) @ qdd + coriolis + gravity
    s1, c1, s12, c12 = np.sin(q[0]), np.cos(q[0]), np.sin(q.sum()), np.cos(q.sum())
    jacobian = np.array([[1.0, 1.0], [-l1 * s1 - l2 * s12, -l2 * s12],
                         [l1 * c1 + l2 * c12, l2 * c12]])
    return tau, jacobian


def test_centre_of_mass_counts_the_links_welded_to_the_world_unless_told_not_to():
    """UR5 (example-robot-data) has three links welded to the world (world, base_link, base).
    `include_fixed=False` is Pinocchio's `centerOfMass`; the default, the whole robot's, is
    Pinocchio's centre of the moving links and its universe body's inertia (the welded links,
    merged) averaged by mass."""
    path = jaxdyn.example_robot_urdf("ur5")
    tree, p = jaxdyn.from_urdf(path)
    model = pin.buildModelFromUrdf(path)
    data = model.createData()
    q = np.random.default_rng(0).uniform(-1.0, 1.0, model.nq)
    moving = pin.centerOfMass(model, data, q)
    base = model.inertias[0]  # the universe's body: what is welded to the world
    whole = ((data.mass[0] * moving + base.mass * base.lever) / (data.mass[0] + base.mass))
    assert base.mass > 1.0
    _close(jaxdyn.centre_of_mass(tree, q, p, include_fixed=False), moving)
    _close(jaxdyn.centre_of_mass(tree, q, p), whole)
    assert np.linalg.norm(whole - moving) > 0.03
    # A floating base has nothing welded to the world: the option changes nothing.
    floating, pf = jaxdyn.from_urdf(path, floating=True)
    qf = np.concatenate([np.zeros(3), [1.0, 0, 0, 0], q])
    np.testing.assert_array_equal(jaxdyn.centre_of_mass(floating, qf, pf),
                                  jaxdyn.centre_of_mass(floating, qf, pf, include_fixed=False))


def test_the_regressor_per_joint_is_pinocchios_on_anymal():
    """ANYmal-C (example-robot-data) has 78 URDF links, 13 moving bodies: the regressor of
    `tree.merge_fixed()` has Pinocchio's 130 columns (ten per joint's body, the links welded
    to it merged in, in the joint's frame) and equals `computeJointTorqueRegressor` at random
    states, floating base included."""
    robot = Robot.load(jaxdyn.example_robot_urdf("anymal_c"), floating=True)
    (q_pin, v_pin, a_pin), (q, u, ud) = robot.random_states(2, 0)
    bodies = robot.tree.merge_fixed()
    names = [link.name for link in bodies.links]
    assert len(robot.tree.links) == 78 and len(names) == 13
    regressors = jax.vmap(lambda q, u, ud: jaxdyn.inverse_dynamics_regressor(
        bodies, q, u, ud, robot.p))(q, u, ud)
    for k in range(2):
        theirs = pin.computeJointTorqueRegressor(robot.model, robot.data, q_pin[k], v_pin[k],
                                                 a_pin[k])
        ours = robot.permutation @ np.asarray(regressors[k])  # rows in Pinocchio's order
        ours = np.concatenate([ours[:, 10 * names.index(link):10 * names.index(link) + 10]
                               for link in robot.joint_link.values()], axis=1)
        assert ours.shape == theirs.shape == (18, 130)
        _close(ours, theirs)


def test_identification_of_ur5_per_joint_keeps_every_link_plausible():
    """UR5 (example-robot-data) from 2 % noisy torques at 200 random states, the prior 30 %
    heavy: one body per joint (60 parameters, rank 36 as in Pinocchio's regressor), the
    residual at the noise's level, and every mass within 10× of the truth (the wrist's last
    link, whose mass alone the torques do not see, stays near its prior rather than falling
    to zero); then the same robot carrying 20× its wrist's mass: the estimate warns, naming
    the link."""
    tree, truth = jaxdyn.from_urdf(jaxdyn.example_robot_urdf("ur5"), damping=False)
    rng = np.random.default_rng(0)
    q, u = rng.uniform(-2.0, 2.0, (200, 6)), rng.normal(size=(200, 6))
    ud = 3.0 * rng.normal(size=(200, 6))
    arm = jaxdyn.ArticulatedBody(tree)
    torques = jax.vmap(arm.residual, (None, 0, 0, 0, None))
    prior = jax.tree_util.tree_map(lambda x: 1.3 * x, truth)
    for scale, warns in ((1.0, False), (20.0, True)):
        payload = {**truth, "wrist_3_link": {**truth["wrist_3_link"],
                                             "mass": scale * truth["wrist_3_link"]["mass"]}}
        tau = np.asarray(torques(0.0, q, u, ud, payload))
        sigma = 0.02 * np.std(tau, axis=0)
        measured = tau + sigma * rng.normal(size=tau.shape)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = jaxdyn.fit_inertial_parameters(tree, q, u, ud, measured, prior,
                                                    weights=sigma**-2)
        names = [w for w in caught if issubclass(w.category, jaxdyn.ImplausibleEstimateWarning)]
        assert result.links == ("shoulder_link", "upper_arm_link", "forearm_link",
                                "wrist_1_link", "wrist_2_link", "wrist_3_link")
        assert result.rank == 36 and result.converged
        assert result.residual_rms < 1.1
        if not warns:
            assert not names and not result.implausible
            for link in result.links:
                ratio = float(result.params[link]["mass"]) / float(truth[link]["mass"])
                assert 0.1 < ratio < 10, link
        else:
            assert list(result.implausible) == ["wrist_3_link"]
            assert len(names) == 1 and "wrist_3_link: mass" in str(names[0].message)


def test_planar_arm_against_its_textbook_equations():
    tree = _planar_arm()
    rng = np.random.default_rng(1)
    for q, qd, qdd in rng.normal(size=(3, 3, 2)):
        tau, jacobian = _planar_arm_by_hand(q, qd, qdd)
        assert_close(jaxdyn.ArticulatedBody(tree).residual(0.0, q, qd, qdd), tau, rtol=1e-12)
        ours = jaxdyn.frame_jacobian(tree, "tip", q)
        assert_close(ours[np.array([2, 3, 4])], jacobian, rtol=1e-12, atol=1e-14)
        assert_close(ours[np.array([0, 1, 5])], np.zeros((3, 2)), rtol=0, atol=1e-15)
        _, origin = jaxdyn.frame_pose(tree, "tip", q)
        assert_close(origin[:2], [ARM["l1"] * np.cos(q[0]) + ARM["l2"] * np.cos(q.sum()),
                                  ARM["l1"] * np.sin(q[0]) + ARM["l2"] * np.sin(q.sum())],
                     rtol=1e-13)


def test_pendulum_regressor_closed_form():
    """A link swinging about z under gravity along −y: τ = I_O,zz θ̈ + g (m c_x cos θ −
    m c_y sin θ), so the regressor row is (0, g cos θ, −g sin θ, 0, 0, 0, 0, 0, 0, θ̈) whatever
    the link's parameters; and the energies' rows (½ θ̇² in I_zz; g (sin θ, cos θ) in m c)."""
    g = 9.81
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("bob", jaxdyn.Revolute((0, 0, 1)), mass=2.0,
                                             com=(0.3, -0.1, 0.05),
                                             inertia=jnp.diag(jnp.array([0.1, 0.2, 0.3])))],
                                gravity=jnp.array([0.0, -g, 0.0]))
    theta, rate, acceleration = 0.7, -1.3, 2.1
    q, u, ud = jnp.array([theta]), jnp.array([rate]), jnp.array([acceleration])
    row = np.zeros(10)
    row[[1, 2, 9]] = g * np.cos(theta), -g * np.sin(theta), acceleration
    assert_close(jaxdyn.inverse_dynamics_regressor(tree, q, u, ud), row[None], rtol=1e-14,
                 atol=1e-14)
    y_t, y_v = jaxdyn.energy_regressors(tree, q, u)
    expected_t, expected_v = np.zeros(10), np.zeros(10)
    expected_t[9] = 0.5 * rate**2
    expected_v[[1, 2]] = g * np.sin(theta), g * np.cos(theta)
    assert_close(y_t, expected_t, rtol=1e-14, atol=1e-15)
    assert_close(y_v, expected_v, rtol=1e-14, atol=1e-15)
    pi = np.asarray(jaxdyn.inertial_parameters(tree))[0]  # I_O = I_c + m (|c|² 1 − c cᵀ)
    assert_close(pi[[0, 1, 2, 3]], [2.0, 0.6, -0.2, 0.1], rtol=1e-14)
    assert_close(pi[9], 0.3 + 2.0 * (0.3**2 + 0.1**2), rtol=1e-14)
    assert_close(pi[5], -2.0 * 0.3 * -0.1, rtol=1e-14)  # I_xy = −m c_x c_y


# ---------------------------------------------------------------------------------------------
# `residual` on every formulation
# ---------------------------------------------------------------------------------------------


def _loaded_arm():
    """A spatial three-link arm with a spring, dampers, joint forces and a force on its tip."""
    inertia = jnp.diag(jnp.array([0.02, 0.03, 0.04]))
    links = [
        jaxdyn.Link("a", jaxdyn.Revolute((0, 0, 1)), mass=1.0, com=(0.1, 0.0, 0.2),
                    inertia=inertia, damping=0.3),
        jaxdyn.Link("b", jaxdyn.Revolute((0, 1, 0)), parent="a", translation=(0.0, 0.0, 0.4),
                    mass=0.8, com=(0.2, 0.0, 0.0), inertia=inertia, stiffness=2.0),
        jaxdyn.Link("c", jaxdyn.Prismatic((1, 0, 0)), parent="b", translation=(0.4, 0.0, 0.0),
                    mass=0.5, com=(0.1, 0.05, 0.0), inertia=inertia),
    ]
    load = jaxdyn.LinkLoad("c", force=lambda q, u, p: jnp.array([0.3, -0.2, 0.5]) * q[0],
                           point=(0.1, 0.0, 0.0))
    return jaxdyn.RigidBodyTree(links, gravity=jnp.array([0.0, 0.0, -9.81]),
                                forces=lambda q, u, p: jnp.sin(q) - 0.1 * u, loads=[load])


def test_residual_on_every_formulation():
    """M u̇ − f from each formulation: zero along its own accelerations, equal across the
    formulations (the articulated body's by Newton–Euler, the others from M and f), equal to
    M (u̇ − u̇₀) for any u̇; and a controlled system's less B r."""
    tree = _loaded_arm()
    formulations = {"articulated body": jaxdyn.ArticulatedBody(tree),
                    "Kane": jaxdyn.Kane.from_system(tree),
                    "Gibbs-Appell": jaxdyn.GibbsAppell.from_system(tree),
                    "Lagrange": jaxdyn.Lagrangian.from_system(tree)}
    rng = np.random.default_rng(2)
    q, u, ud = rng.normal(size=(3, 4, 3))
    t = np.zeros(4)
    reference = formulations["Kane"]
    mass_matrix = reference.mass_matrix(t, q, u)
    own = reference.accelerations(t, q, u)
    expected = np.einsum("sij,sj->si", mass_matrix, ud - own)
    for label, dynamics in formulations.items():
        assert_close(dynamics.residual(t, q, u, ud), expected, rtol=1e-11, atol=1e-12,
                     err_msg=label)
        assert_close(dynamics.residual(t, q, u, dynamics.accelerations(t, q, u)),
                     np.zeros_like(u), rtol=0, atol=1e-12, err_msg=label)
    inputs = np.array([0.4, -0.7])
    for label in ("articulated body", "Kane"):
        controlled = jaxdyn.Controlled(formulations[label], [0, 2], inputs)
        assert_close(controlled.residual(t, q, u, ud),
                     expected - np.array([0.4, 0.0, -0.7]), rtol=1e-11, atol=1e-12,
                     err_msg=label)


def test_errors_name_the_problem(panda):
    tree, q = panda.tree, panda.tree.neutral_configuration()
    with pytest.raises(ValueError, match="no link named 'hand'.*panda_hand"):
        jaxdyn.frame_pose(tree, "hand", q)
    with pytest.raises(ValueError, match="axes must be 'world' or 'local'"):
        jaxdyn.frame_jacobian(tree, "panda_hand", q, axes="LOCAL_WORLD_ALIGNED")
    with pytest.raises(ValueError, match="point must be a 3-vector"):
        jaxdyn.frame_pose(tree, "panda_hand", q, point=(0.0, 0.1))
    with pytest.raises(ValueError, match="q has shape"):
        jaxdyn.centre_of_mass(tree, q[:-1])
    u = np.zeros(tree.num_speeds)
    with pytest.raises(ValueError, match=r"u̇ \(ud\) must have shape \(9,\)"):
        jaxdyn.inverse_dynamics_regressor(tree, q, u, u[:-1])
    with pytest.raises(ValueError, match="RigidBodyTree"):
        jaxdyn.centre_of_mass(jaxdyn.ArticulatedBody(tree), q)


def _planar_arm_urdf(path, scale_inertia=1.0, com_shift=1.0):
    """The planar arm of `_planar_arm` as a URDF (its rods given a small x moment, so that
    each is a rigid body strictly inside the consistent set), with a massless tip frame."""
    links, joints = [], []
    for i, (m, l) in enumerate(((ARM["m1"], ARM["l1"]), (ARM["m2"], ARM["l2"]))):
        izz = scale_inertia * m * l**2 / 12
        links.append(
            f'<link name="rod{i}"><inertial><origin xyz="{com_shift * l / 2} 0 0"/>'
            f'<mass value="{scale_inertia * m}"/><inertia ixx="{scale_inertia * 1e-3}" ixy="0" '
            f'ixz="0" iyy="{izz}" iyz="0" izz="{izz}"/></inertial></link>')
        joints.append(
            f'<joint name="j{i}" type="continuous"><parent link="{"base" if i == 0 else "rod0"}"/>'
            f'<child link="rod{i}"/><origin xyz="{0.0 if i == 0 else ARM["l1"]} 0 0"/>'
            '<axis xyz="0 0 1"/></joint>')
    text = ('<robot name="arm"><link name="base"/>' + "".join(links) + '<link name="tip"/>'
            + "".join(joints) + f'<joint name="tool" type="fixed"><parent link="rod1"/>'
            f'<child link="tip"/><origin xyz="{ARM["l2"]} 0 0"/></joint></robot>')
    path.write_text(text)
    return jaxdyn.from_urdf(str(path), gravity=(0.0, -ARM["g"], 0.0), damping=False)


def test_inertial_parameters_from_torques(tmp_path):
    """Torques of the textbook two-link arm (Spong et al.), the prior 30 % off: the planar arm
    has six identifiable combinations (Khalil and Dombre: ZZ₁ + m₂l₁², MX₁ + m₂l₁, MY₁, ZZ₂,
    MX₂, MY₂); the consistent estimate is a rigid body for every link and predicts torques at
    new states as the textbook does; the base parameters span the same combinations as the
    textbook's and take their values; with noise, the weighted residual is the noise's (χ²)."""
    tree, truth = _planar_arm_urdf(tmp_path / "arm.urdf")
    _, prior = _planar_arm_urdf(tmp_path / "prior.urdf", scale_inertia=1.3, com_shift=0.8)
    rng = np.random.default_rng(3)
    states = rng.normal(size=(2, 3, 60, 2))
    (q, u, ud), (q_new, u_new, ud_new) = states
    tau = np.stack([_planar_arm_by_hand(*x)[0] for x in zip(q, u, ud)])
    tau_new = np.stack([_planar_arm_by_hand(*x)[0] for x in zip(q_new, u_new, ud_new)])

    result = jaxdyn.fit_inertial_parameters(tree, q, u, ud, tau, prior)
    with compiles() as count:  # new torques of the same shapes reuse the programs
        jaxdyn.fit_inertial_parameters(tree, q, u, ud, 1.01 * tau, prior)
    assert count() == 0
    # The fixed base is invisible to torques; the massless tip, welded to rod1, keeps its prior.
    assert result.links == ("rod0", "rod1")
    assert result.rank == 6
    assert result.converged
    predicted = jax.vmap(jaxdyn.ArticulatedBody(tree).residual, (None, 0, 0, 0, None))(
        0.0, q_new, u_new, ud_new, result.params)
    assert_close(predicted, tau_new, rtol=0, atol=1e-7 * np.max(np.abs(tau_new)))
    for name in result.links:
        mass, inertia = result.params[name]["mass"], np.asarray(result.params[name]["inertia"])
        moments = np.linalg.eigvalsh(inertia)
        assert mass > 0 and moments[0] > 0 and moments[2] <= moments[0] + moments[1], name
    # The six combinations themselves (π of rod0 and rod1: m, mx, my, mz, Ixx, …, Izz).
    _, rod0, rod1, _ = np.asarray(result.inertial_parameters)
    m2 = rod1[0]
    l1, l2 = ARM["l1"], ARM["l2"]
    identified = [rod0[9] + m2 * l1**2, rod0[1] + m2 * l1, rod0[2], rod1[9], rod1[1], rod1[2]]
    textbook = [ARM["m1"] * l1**2 / 3 + ARM["m2"] * l1**2, ARM["m1"] * l1 / 2 + ARM["m2"] * l1,
                0.0, ARM["m2"] * l2**2 / 3, ARM["m2"] * l2 / 2, 0.0]
    assert_close(identified, textbook, rtol=1e-6, atol=1e-7)  # the prior's pull: ~1e-8
    # Gautier and Khalil's base parameters: six, spanning the textbook's combinations (rows
    # over the 20 parameters of rod0 and rod1), each valued as the textbook's π gives it.
    base = result.base_parameters
    textbook_rows = np.zeros((6, 20))
    for row, entries in enumerate(([(9, 1), (10, l1**2)], [(1, 1), (10, l1)], [(2, 1)],
                                   [(19, 1)], [(11, 1)], [(12, 1)])):
        for column, value in entries:
            textbook_rows[row, column] = value
    assert base.combinations.shape == (6, 20) and len(base.names) == 6
    assert np.linalg.matrix_rank(np.vstack([base.combinations, textbook_rows]), tol=1e-8) == 6
    true_pi = np.asarray(jaxdyn.inertial_parameters(tree, truth))[1:3].ravel()  # rod0, rod1
    assert_close(base.values, base.combinations @ true_pi, rtol=1e-9, atol=1e-9)
    assert np.all(base.standard_errors < 1e-9)  # noise-free torques
    # One name per base parameter, its own parameter first; mz, Ixx, … are invisible.
    assert any(name.startswith("rod0.Izz") or "rod0.Izz" in name for name in base.names)
    assert not base.identifiable[:, [3, 4, 5, 6, 7, 8]].any()
    assert base.identifiable[1, 9]  # ZZ₂ alone is identifiable
    assert "base parameters" in result.summary()

    sigma = 0.01 * np.std(tau, axis=0)
    noisy = tau + sigma * rng.normal(size=tau.shape)
    result = jaxdyn.fit_inertial_parameters(tree, q, u, ud, noisy, prior, weights=sigma**-2,
                                            links=["rod0", "rod1"])
    assert 0.7 < result.least_squares_rms < 1.1  # χ² per degree of freedom ≈ 1 (120 − 6 dof)
    assert result.residual_rms < 1.1 * result.least_squares_rms + 0.05
    predicted = jax.vmap(jaxdyn.ArticulatedBody(tree).residual, (None, 0, 0, 0, None))(
        0.0, q_new, u_new, ud_new, result.params)
    assert np.sqrt(np.mean((np.asarray(predicted) - tau_new) ** 2 / sigma**2)) < 1.0

    with pytest.raises(ValueError, match=r"tau must have shape \(k, 2\)"):
        jaxdyn.fit_inertial_parameters(tree, q, u, ud, tau[:, :1], prior)
    with pytest.raises(ValueError, match="ud holds NaN"):
        jaxdyn.fit_inertial_parameters(tree, q, u, np.full_like(ud, np.nan), tau, prior)
    with pytest.raises(ValueError, match=r"links \['elbow'\] are not in the tree"):
        jaxdyn.fit_inertial_parameters(tree, q, u, ud, tau, prior, links=["elbow"])
