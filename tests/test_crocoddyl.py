"""Trajectory optimisation against Crocoddyl: the same optimal control problems, written once in
jaxdyn (`ShootingProblem`, `solve_optimal_control`) and once in Crocoddyl (free forward
dynamics of a Pinocchio model, `IntegratedActionModelEuler`, residual costs), reach the same
optimum.

Each problem is first checked to be the same problem: Crocoddyl's step F(x, r) equals jaxdyn's
`SemiImplicitEuler` step, the rollouts of the same inputs agree, and Crocoddyl's total cost of
jaxdyn's optimal trajectory equals jaxdyn's cost to round-off. Then Crocoddyl's solver, run to
its round-off (th_stop = 1e-16), gives the reference optimum.

How close the optima must be follows from jaxdyn's stopping test: it stops once the full step's
predicted decrease is below tol (1 + |J|), so its cost lies above the optimum by about that much
(the decrease a Gauss–Newton step still had to make). The inputs then lie within
sqrt(2 ΔJ / λ) of the optimal ones, λ the least curvature of J in the inputs, which is at least
Δt w_r (the input weight of the running cost; the Gauss–Newton Hessian of the rest is positive
semidefinite, and at an optimum with active bounds the gradient only adds to J along feasible
directions). With tol = 1e-12 that bound is 3–5e-4; the solvers agree far better (1e-5 on the
Panda, whose input weight is small), and a different local optimum would be off by O(1).

Cases: (a) the Panda arm (fingers locked) reaching a point with its hand, gravity-compensating
torque regularisation and torque bounds, solved with SolverBoxFDDP; the bounds are tightened
from the Panda's own (87 / 12 N m, never reached by this motion) so that some are active at the
optimum; (b) a fully actuated double pendulum (a URDF written here, read by both) swung up to
upright, unbounded, solved with SolverFDDP, and by jaxdyn's DDP as well as iLQR; (c) the same
pendulum made to arrive exactly upright (a terminal constraint), against Crocoddyl's FDDP with
a terminal penalty whose weight grows.

Crocoddyl 3.2.1's wheels are built against Pinocchio 4.0.0's headers: with Pinocchio 4.1 it
reads the model's layout wrongly (no gravity in its dynamics, an allocation failure building a
gravity residual). The fixture `crocoddyl_reads_pinocchio` checks Crocoddyl's dynamics against
Pinocchio's `aba` first and names the mismatch.
"""

import importlib.metadata
import os

import jax
import jax.numpy as jnp
import numpy as np
import pinocchio as pin
import pytest

import crocoddyl
import jaxdyn

N, DT = 100, 0.01
TOL = 1e-12  # jaxdyn's stopping tolerance in these tests (the default is 1e-9)
ROUND_OFF = 1e-13

# -- the Panda reaching a point ----------------------------------------------------------------

FINGERS = ("panda_finger_joint1", "panda_finger_joint2")
HAND = "panda_hand"
TARGET = np.array([0.4, 0.2, 0.5])
Q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
# The Panda's torque limits are 87 N m (joints 1–4) and 12 N m (5–7); the optimal motion stays
# within 11, 21, 14, 24, 3, 4, 0.2 N m. Joints 1 and 3 are limited to 8 and 10 N m here, so
# that bounds are active at the optimum (at 3 nodes each, in both solvers).
LIMITS = np.array([8.0, 87.0, 10.0, 87.0, 12.0, 12.0, 12.0])
# Running: hand position, joint speeds, torques less gravity's; terminal: position, speeds.
W_X, W_U, W_R, W_XN, W_UN = 2e1, 2e-1, 2e-3, 2e3, 2e1

# -- the double pendulum -----------------------------------------------------------------------


def _rod(name, mass, length):
    i = mass * length**2 / 12
    return (f'<link name="{name}"><inertial><origin xyz="0 0 {-length / 2}"/>'
            f'<mass value="{mass}"/><inertia ixx="{i}" iyy="{i}" izz="1e-4" ixy="0" ixz="0" '
            'iyz="0"/></inertial></link>')


# Revolute joints about y, hanging along −z at q = 0 (Pinocchio reads a "revolute" joint about
# a coordinate axis as one angle; a "continuous" one would be (cos, sin)).
DOUBLE_PENDULUM = f"""<?xml version="1.0"?>
<robot name="double_pendulum">
  <link name="base"/>
  {_rod("upper", 1.0, 1.0)}
  {_rod("lower", 0.5, 0.8)}
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <axis xyz="0 1 0"/><limit lower="-10" upper="10" effort="100" velocity="100"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="lower"/>
    <origin xyz="0 0 -1.0"/><axis xyz="0 1 0"/>
    <limit lower="-10" upper="10" effort="100" velocity="100"/></joint>
</robot>
"""
UPRIGHT = np.array([np.pi, 0.0, 0.0, 0.0])
W_STATE, W_INPUT, W_FINAL = 1.0, 1e-2, 1e3


def crocoddyl_mismatch():
    """None where Crocoddyl's forward dynamics are Pinocchio's `aba` (with gravity) on a sample
    arm, else what differs and why (a Crocoddyl built against another Pinocchio than the
    installed one reads its model wrongly)."""
    model = pin.buildSampleModelManipulator()
    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFull(state)
    dynamics = crocoddyl.DifferentialActionModelFreeFwdDynamics(
        state, actuation, crocoddyl.CostModelSum(state, actuation.nu))
    data = dynamics.createData()
    rng = np.random.default_rng(0)
    q = pin.randomConfiguration(model)
    v, tau = rng.normal(size=model.nv), rng.normal(size=model.nv)
    dynamics.calc(data, np.concatenate([q, v]), tau)
    expected = pin.aba(model, model.createData(), q, v, tau)
    if np.allclose(data.xout, expected, rtol=0, atol=1e-10):
        return None
    return ("Crocoddyl's forward dynamics differ from Pinocchio's aba (by "
            f"{np.max(np.abs(data.xout - expected)):.3g}): crocoddyl "
            f"{importlib.metadata.version('crocoddyl')} was built against another Pinocchio "
            f"than the installed pin {importlib.metadata.version('pin')} (crocoddyl 3.2.1 "
            "needs pin 4.0.0).")


@pytest.fixture(scope="module", autouse=True)
def crocoddyl_reads_pinocchio():
    """Crocoddyl's forward dynamics are Pinocchio's `aba` (with gravity) on a sample arm."""
    mismatch = crocoddyl_mismatch()
    if mismatch is not None:
        pytest.fail(mismatch)


def _crocoddyl_problem(model, x0, running_costs, terminal_costs, bounds=None):
    """Crocoddyl's shooting problem: free forward dynamics, the Euler integrated action model
    (semi-implicit: v⁺ = v + Δt a, q⁺ = q + Δt v⁺; running cost Δt ℓ; terminal Δt = 0)."""
    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFull(state)

    def costs(terms):
        total = crocoddyl.CostModelSum(state, actuation.nu)
        for name, (activation, residual, weight) in terms(state, actuation.nu).items():
            total.addCost(name, crocoddyl.CostModelResidual(state, activation, residual), weight)
        return total

    def action(terms, dt):
        return crocoddyl.IntegratedActionModelEuler(
            crocoddyl.DifferentialActionModelFreeFwdDynamics(state, actuation, costs(terms)),
            dt)

    running, terminal = action(running_costs, DT), action(terminal_costs, 0.0)
    if bounds is not None:
        running.u_lb, running.u_ub = -bounds, bounds
    problem = crocoddyl.ShootingProblem(x0, [running] * N, terminal)
    problem.nthreads = 1
    return problem


def _crocoddyl_optimum(problem, guess, bounded):
    """Crocoddyl's optimum from the rollout of the inputs `guess` (a feasible start), to
    round-off."""
    solver = (crocoddyl.SolverBoxFDDP if bounded else crocoddyl.SolverFDDP)(problem)
    solver.th_stop = 1e-16
    us = list(np.asarray(guess))
    assert solver.solve(problem.rollout(us), us, 500, True)
    return solver


# -- the problems (benchmarks/bench_optimal_control.py builds its own with these) -------------


def panda_problem(limits=LIMITS):
    """The Panda reaching TARGET from Q0 at rest, torques bounded by ±`limits` (those of this
    test by default; the Panda's own are 87 / 12 N m): jaxdyn's problem `problem`, its
    parameters `p`, the start `q0`, `hold` (a start q → the N torques that hold it against
    gravity: the guess) and Crocoddyl's problem `reference`."""
    tree, p = jaxdyn.from_urdf(jaxdyn.example_robot_urdf("panda"), locked=FINGERS,
                               damping=False)  # Pinocchio's aba has no joint damping
    body = jaxdyn.ArticulatedBody(tree)
    arm = jaxdyn.Controlled(body, input_map=list(range(7)))
    target = jnp.asarray(TARGET)

    def gravity(q, p):
        return -body.forcing(0.0, q, jnp.zeros_like(q), p)

    def running(q, u, r, p):
        _, x = jaxdyn.frame_pose(tree, HAND, q, p)
        return jnp.concatenate([np.sqrt(W_X) * (x - target), np.sqrt(W_U) * u,
                                np.sqrt(W_R) * (r - gravity(q, p))])

    def terminal(q, u, p):
        _, x = jaxdyn.frame_pose(tree, HAND, q, p)
        return jnp.concatenate([np.sqrt(W_XN) * (x - target), np.sqrt(W_UN) * u])

    problem = jaxdyn.ShootingProblem(arm, running, terminal, num_nodes=N, dt=DT,
                                     discretisation=jaxdyn.SemiImplicitEuler(),
                                     input_bounds=(-limits, limits))

    def hold(q):
        return jnp.tile(gravity(q, p), (N, 1))

    path = jaxdyn.example_robot_urdf("panda")
    full = pin.buildModelFromUrdf(path)
    model = pin.buildReducedModel(full, [full.getJointId(name) for name in FINGERS],
                                  pin.neutral(full))
    hand = model.getFrameId(HAND)
    speeds = np.concatenate([np.zeros(7), np.ones(7)])  # the state residual's v part alone

    def position(state, nu):
        return (crocoddyl.ActivationModelQuad(3),
                crocoddyl.ResidualModelFrameTranslation(state, hand, TARGET, nu))

    def speed(state, nu):
        return (crocoddyl.ActivationModelWeightedQuad(speeds),
                crocoddyl.ResidualModelState(state, np.zeros(14), nu))

    def running_costs(state, nu):
        return {"hand": (*position(state, nu), W_X), "speed": (*speed(state, nu), W_U),
                "torque": (crocoddyl.ActivationModelQuad(nu),
                           crocoddyl.ResidualModelControlGrav(state, nu), W_R)}

    def terminal_costs(state, nu):
        return {"hand": (*position(state, nu), W_XN), "speed": (*speed(state, nu), W_UN)}

    reference = _crocoddyl_problem(model, np.concatenate([Q0, np.zeros(7)]), running_costs,
                                   terminal_costs, limits)
    return dict(problem=problem, p=p, q0=Q0, hold=hold, reference=reference)


def double_pendulum_problem(directory):
    """The double pendulum swung up from hanging at rest to UPRIGHT, unbounded, its URDF
    written to `directory`: jaxdyn's problem `problem`, its parameters `p`, the start `q0`,
    the guess `guess` (zero torques) and Crocoddyl's problem `reference`."""
    path = os.path.join(directory, "double_pendulum.urdf")
    with open(path, "w") as out:
        out.write(DOUBLE_PENDULUM)
    tree, p = jaxdyn.from_urdf(path)
    plant = jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=[0, 1])
    upright = jnp.asarray(UPRIGHT)

    def running(q, u, r, p):
        return jnp.concatenate([np.sqrt(W_STATE) * (jnp.concatenate([q, u]) - upright),
                                np.sqrt(W_INPUT) * r])

    def terminal(q, u, p):
        return np.sqrt(W_FINAL) * (jnp.concatenate([q, u]) - upright)

    problem = jaxdyn.ShootingProblem(plant, running, terminal, num_nodes=N, dt=DT,
                                     discretisation=jaxdyn.SemiImplicitEuler())

    def state_cost(state, nu):
        return (crocoddyl.ActivationModelQuad(4),
                crocoddyl.ResidualModelState(state, UPRIGHT, nu))

    def running_costs(state, nu):
        return {"state": (*state_cost(state, nu), W_STATE),
                "input": (crocoddyl.ActivationModelQuad(nu),
                          crocoddyl.ResidualModelControl(state, nu), W_INPUT)}

    def terminal_costs(state, nu):
        return {"state": (*state_cost(state, nu), W_FINAL)}

    reference = _crocoddyl_problem(pin.buildModelFromUrdf(path), np.zeros(4), running_costs,
                                   terminal_costs)
    return dict(problem=problem, p=p, q0=np.zeros(2), guess=np.zeros((N, 2)),
                reference=reference)


# -- ANYmal-C shifting its base, its four feet held ------------------------------------------

ANYMAL = "anymal_c_simple_description/urdf/anymal.urdf"
FEET = ["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"]
STANCE = np.array([-0.1, 0.7, -1.0, 0.1, 0.7, -1.0, -0.1, -0.7, 1.0, 0.1, -0.7, 1.0])
BASE_SHIFT = np.array([0.03, 0.02, -0.05])
ANYMAL_N, ANYMAL_DT = 20, 0.02
ALPHA, BETA = 10.0, 10.0  # Baumgarte's rates; Crocoddyl's gains are (β², 2α)
# Running: the base's position, every speed, the joint torques; terminal: position, speeds.
W_BASE, W_SPEED, W_TORQUE, W_BASE_N, W_SPEED_N = 1e2, 1.0, 1e-4, 1e4, 1e2


def anymal_problem():
    """ANYmal-C (example-robot-data) moving its base by `BASE_SHIFT` in 0.4 s with its four feet
    held where they stand (`jaxdyn.HeldPoints` with Baumgarte's terms; Crocoddyl's
    `ContactModel3D` in world-aligned axes with gains (β², 2α)), semi-implicit Euler at 20 ms:
    jaxdyn's `problem`, `p`, `q0` and `guess` (the quasi-static torques that hold the stance,
    Crocoddyl's `quasiStatic`), Crocoddyl's problem `reference`, its `x0` and `their_guess`
    (Pinocchio's joint order), the speed permutation `perm` (v_pin = perm u) and Crocoddyl's
    continuous contact dynamics `contact_dynamics`.

    The discrete steps differ in the base's rotation: Crocoddyl moves it along SE(3)'s
    exponential, jaxdyn's semi-implicit Euler along q̇ = K(q) u (the quaternion's rate), which
    differ by O(Δt²) per step."""
    from robots import Robot  # needs Pinocchio, as this module does

    robot = Robot.load(jaxdyn.example_robot_urdf(ANYMAL), floating=True)
    tree, p, model = robot.tree, robot.p, robot.model
    joints = robot.permutation[6:, 6:]  # Pinocchio's joint order from jaxdyn's
    q0 = np.concatenate([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], STANCE])
    held = jaxdyn.HeldPoints.at(tree, FEET, q0, p)
    plant = jaxdyn.Constrained(
        jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 18))),
        holonomic=held, stabilisation=jaxdyn.Baumgarte(ALPHA, BETA))
    target = jnp.asarray(BASE_SHIFT)

    def running(q, u, r, p):
        return jnp.concatenate([np.sqrt(W_BASE) * (q[:3] - target), np.sqrt(W_SPEED) * u,
                                np.sqrt(W_TORQUE) * r])

    def terminal(q, u, p):
        return jnp.concatenate([np.sqrt(W_BASE_N) * (q[:3] - target), np.sqrt(W_SPEED_N) * u])

    problem = jaxdyn.ShootingProblem(plant, running, terminal, num_nodes=ANYMAL_N,
                                     dt=ANYMAL_DT, discretisation=jaxdyn.SemiImplicitEuler())

    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFloatingBase(state)
    nu, base = actuation.nu, model.getFrameId("base")
    x0 = np.concatenate([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], joints @ STANCE,
                         np.zeros(model.nv)])
    data = model.createData()
    pin.framesForwardKinematics(model, data, x0[:model.nq])
    speeds = np.concatenate([np.zeros(model.nv), np.ones(model.nv)])

    def action(weights, dt):
        contacts = crocoddyl.ContactModelMultiple(state, nu)
        for foot in FEET:
            frame = model.getFrameId(foot)
            contacts.addContact(foot, crocoddyl.ContactModel3D(
                state, frame, data.oMf[frame].translation.copy(), pin.LOCAL_WORLD_ALIGNED, nu,
                np.array([BETA**2, 2 * ALPHA])))
        costs = crocoddyl.CostModelSum(state, nu)
        w_base, w_speed, w_torque = weights
        costs.addCost("base", crocoddyl.CostModelResidual(
            state, crocoddyl.ActivationModelQuad(3),
            crocoddyl.ResidualModelFrameTranslation(state, base, BASE_SHIFT, nu)), w_base)
        costs.addCost("speed", crocoddyl.CostModelResidual(
            state, crocoddyl.ActivationModelWeightedQuad(speeds),
            crocoddyl.ResidualModelState(state, x0, nu)), w_speed)
        if w_torque:
            costs.addCost("torque", crocoddyl.CostModelResidual(
                state, crocoddyl.ActivationModelQuad(nu),
                crocoddyl.ResidualModelControl(state, nu)), w_torque)
        dynamics = crocoddyl.DifferentialActionModelContactFwdDynamics(
            state, actuation, contacts, costs, 0.0, True)
        return crocoddyl.IntegratedActionModelEuler(dynamics, dt), dynamics

    (running_model, contact_dynamics), (terminal_model, _) = (
        action((W_BASE, W_SPEED, W_TORQUE), ANYMAL_DT), action((W_BASE_N, W_SPEED_N, 0.0), 0.0))
    reference = crocoddyl.ShootingProblem(x0, [running_model] * ANYMAL_N, terminal_model)
    reference.nthreads = 1
    their_guess = np.array(reference.quasiStatic([x0] * ANYMAL_N))
    return dict(problem=problem, p=p, q0=q0, guess=their_guess @ joints, reference=reference,
                x0=x0, their_guess=their_guess, perm=robot.permutation, robot=robot,
                contact_dynamics=contact_dynamics, plant=plant)


# Slow (18 s): the held points' dynamics are checked against Pinocchio in the default run
# (tests/test_robotics.py::test_held_points_against_pinocchio).
@pytest.mark.slow
def test_held_feet_are_crocoddyls_contact_dynamics():
    """Lagrange's equations of the first kind with ANYmal-C's feet held (`HeldPoints`,
    Baumgarte's terms) are Crocoddyl's contact dynamics (`ContactModel3D` with gains (β², 2α),
    `DifferentialActionModelContactFwdDynamics`): the accelerations at random states and
    torques, away from the holds, to round-off."""
    case = anymal_problem()
    robot, plant, p, perm = case["robot"], case["plant"], case["p"], case["perm"]
    dynamics = case["contact_dynamics"]
    data = dynamics.createData()
    (q_pin, v_pin, _), (q, u, _) = robot.random_states(3, seed=2)
    torques = np.random.default_rng(3).normal(size=(3, 12)) * 20
    ours = jax.jit(jax.vmap(lambda q, u, r: plant.with_inputs(r).accelerations(0.0, q, u, p)))(
        q, u, torques)
    for k in range(3):
        dynamics.calc(data, np.concatenate([q_pin[k], v_pin[k]]), perm[6:, 6:] @ torques[k])
        theirs = data.xout.copy()
        np.testing.assert_allclose(np.asarray(ours[k]) @ perm.T, theirs, rtol=0,
                                   atol=1e-9 * (1 + np.max(np.abs(theirs))))


@pytest.fixture(scope="module")
def panda():
    case = panda_problem()
    problem, p, reference = case["problem"], case["p"], case["reference"]
    q0 = jnp.asarray(case["q0"])
    guess = case["hold"](q0)
    solution = jaxdyn.solve_optimal_control(problem, q0, jnp.zeros(7), p, inputs=guess,
                                            solver=jaxdyn.ILQR(tol=TOL))
    return dict(problem=problem, p=p, q0=q0, guess=guess, solution=solution,
                reference=reference, weight=W_R, bounds=LIMITS,
                optimum=_crocoddyl_optimum(reference, guess, bounded=True))


@pytest.fixture(scope="module")
def double_pendulum(tmp_path_factory):
    case = double_pendulum_problem(str(tmp_path_factory.mktemp("urdf")))
    problem, p, reference = case["problem"], case["p"], case["reference"]
    q0, guess = jnp.asarray(case["q0"]), jnp.asarray(case["guess"])
    solution = jaxdyn.solve_optimal_control(problem, q0, jnp.zeros(2), p, inputs=guess,
                                            solver=jaxdyn.ILQR(tol=TOL))
    return dict(problem=problem, p=p, q0=q0, guess=guess, solution=solution,
                reference=reference, weight=W_INPUT, bounds=None,
                optimum=_crocoddyl_optimum(reference, guess, bounded=False))


# The Panda compiles for 40 s to 2 min on two cores: a slow test (python -m pytest -m slow).
CASES = [pytest.param("panda", marks=pytest.mark.slow), "double_pendulum"]


def _states(solution):
    return np.concatenate([solution.q, solution.u], axis=1)


@pytest.mark.parametrize("case", CASES)
def test_same_discrete_dynamics(case, request):
    """One step of Crocoddyl's Euler model is jaxdyn's semi-implicit Euler step, at nodes of
    the optimal trajectory and at random states and inputs; the rollouts of Crocoddyl's
    optimal inputs agree over the horizon."""
    c = request.getfixturevalue(case)
    problem, p, reference = c["problem"], c["p"], c["reference"]
    model, data = reference.runningModels[0], reference.runningDatas[0]
    n = model.state.nq
    rng = np.random.default_rng(1)
    solution = c["solution"]
    nodes = [(x, r) for x, r in zip(_states(solution)[::17], np.asarray(solution.inputs)[::17])]
    nodes += [(np.concatenate([rng.uniform(-2, 2, n), rng.normal(size=n)]),
               rng.normal(size=n) * 5) for _ in range(3)]
    step = jax.jit(lambda x, r: problem.step(0.0, x, r, p, n))
    for x, r in nodes:
        model.calc(data, x, r)
        theirs = np.array(data.xnext)
        np.testing.assert_allclose(step(jnp.asarray(x), jnp.asarray(r)), theirs, rtol=0,
                                   atol=ROUND_OFF * max(1.0, np.max(np.abs(theirs))))
    inputs = np.array(c["optimum"].us)
    theirs = np.array(reference.rollout(list(inputs)))
    ours = problem.rollout(jnp.asarray(theirs[0]), jnp.asarray(inputs), p, n)
    # N steps carry the round-off of each along.
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-11 * np.max(np.abs(theirs)))


@pytest.mark.parametrize("case", CASES)
def test_same_cost(case, request):
    """Crocoddyl's total cost Σ Δt ℓ + Φ of jaxdyn's optimal trajectory is jaxdyn's."""
    c = request.getfixturevalue(case)
    solution = c["solution"]
    assert solution.status == 0 and solution.gap == 0
    theirs = c["reference"].calc(list(_states(solution)), list(np.asarray(solution.inputs)))
    np.testing.assert_allclose(float(solution.cost), theirs, rtol=ROUND_OFF)


@pytest.mark.parametrize("case", CASES)
def test_same_optimum(case, request):
    """jaxdyn's iLQR reaches Crocoddyl's optimum: the cost to within jaxdyn's stopping
    tolerance, the inputs to within what that tolerance allows (the module docstring), the
    same bounds active, the same states, and the same Riccati feedback gains."""
    c = request.getfixturevalue(case)
    solution, optimum = c["solution"], c["optimum"]
    cost = float(solution.cost)
    excess = TOL * (1 + cost)  # what jaxdyn's stopping test leaves
    assert optimum.cost - ROUND_OFF * cost <= cost <= optimum.cost + 2 * excess
    ours, theirs = np.asarray(solution.inputs), np.array(optimum.us)
    bound = np.sqrt(2 * 2 * excess / (DT * c["weight"]))
    assert np.linalg.norm(ours - theirs) <= bound
    # Measured: up to 6e-6 (Panda) and 1e-5 (pendulum), against inputs of 20 and 50 N m.
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-4)
    np.testing.assert_allclose(_states(solution), np.array(optimum.xs), rtol=0, atol=1e-5)
    if c["bounds"] is not None:
        active = np.abs(ours) >= c["bounds"] * (1 - 1e-12)
        assert active.any()
        np.testing.assert_array_equal(active, np.abs(theirs) >= c["bounds"] * (1 - 1e-12))
    # δr = k + K δx in jaxdyn, δr = −k − K δx in Crocoddyl; rows of active inputs are zero in
    # both. The gains follow the trajectories (1e-6 apart): measured 3e-5 (Panda) and 7e-6
    # (pendulum) of the largest gain.
    gains = -np.array(optimum.K)
    np.testing.assert_allclose(solution.feedback, gains, rtol=0,
                               atol=1e-3 * np.max(np.abs(gains)))


@pytest.mark.slow  # DDP's program (the dynamics' second derivatives) compiles for 30 s
def test_ddp_same_optimum(double_pendulum):
    """jaxdyn's DDP (the dynamics' second derivatives in the model) reaches the same optimum
    as Crocoddyl's FDDP (Gauss–Newton), its cost Hessians exact instead of Gauss–Newton: the
    same stationary point."""
    c = double_pendulum
    solution = jaxdyn.solve_optimal_control(c["problem"], c["q0"], jnp.zeros(2), c["p"],
                                            inputs=c["guess"], solver=jaxdyn.DDP(tol=TOL))
    assert solution.status == 0
    cost, optimum = float(solution.cost), c["optimum"]
    assert optimum.cost - ROUND_OFF * cost <= cost <= optimum.cost + 2 * TOL * (1 + cost)
    np.testing.assert_allclose(solution.inputs, np.array(optimum.us), rtol=0, atol=1e-4)


@pytest.mark.slow  # the Panda's solve and its implicit-function derivative compile for 2 min
def test_the_pandas_optimal_cost_differentiated_by_a_links_mass():
    """dJ*/dm of the Panda's reach with respect to its last link's mass, through the solve's
    implicit-function derivative, equals central differences of J*: its torque cost holds
    the gravity torques `forcing(q, p)` at every node, vmapped over the nodes (whose tangent
    with respect to p once came back with the nodes' and joints' axes exchanged)."""
    case = panda_problem()
    problem, p, q0 = case["problem"], case["p"], jnp.asarray(case["q0"])
    guess = case["hold"](q0)

    def optimal_cost(mass):
        link = dict(p["panda_link7"], mass=mass)
        return jaxdyn.solve_optimal_control(problem, q0, jnp.zeros(7),
                                            {**p, "panda_link7": link}, inputs=guess).cost

    mass, h = jnp.asarray(p["panda_link7"]["mass"]), 1e-4
    central = (optimal_cost(mass + h) - optimal_cost(mass - h)) / (2 * h)
    # measured: 0.00976597 against 0.00976596
    np.testing.assert_allclose(jax.grad(optimal_cost)(mass), central, rtol=1e-5)


@pytest.mark.slow  # its own program (the constraints' outer loop about the solver): 15 s
def test_a_terminal_constraint_is_the_limit_of_crocoddyls_terminal_penalty(double_pendulum):
    """The double pendulum made to arrive exactly upright at rest (`terminal_constraints`,
    jaxdyn's augmented Lagrangian) in place of its terminal cost: Crocoddyl's FDDP with the
    terminal cost ½ W |x_N − upright|² converges to the constrained optimum as W grows, its
    inputs off by O(1/W) — 1e-4, 1e-6, 1e-8 at W = 1e6, 1e8, 1e10 — and its running cost
    to jaxdyn's constrained optimal cost. (Crocoddyl 3.2.1's SolverIntro does not enforce a
    constraint on the terminal node: it ended 0.8 rad from upright, so the penalty is the
    reference.)"""
    c = double_pendulum
    reference = c["reference"]
    state = reference.terminalModel.differential.state
    problem = jaxdyn.ShootingProblem(
        c["problem"].dynamics, c["problem"].running_cost, num_nodes=N, dt=DT,
        discretisation=jaxdyn.SemiImplicitEuler(),
        terminal_constraints=lambda q, u, p: jnp.concatenate([q, u]) - jnp.asarray(UPRIGHT))
    solution = jaxdyn.solve_optimal_control(
        problem, c["q0"], jnp.zeros(2), c["p"],
        solver=jaxdyn.ILQR(tol=TOL, constraint_tol=1e-10, max_iterations=500))
    assert int(solution.status) == 0 and float(solution.constraint_violation) <= 1e-10
    ours = np.asarray(solution.inputs)
    errors = []
    for weight in (1e6, 1e8, 1e10):
        costs = crocoddyl.CostModelSum(state, 2)
        costs.addCost("state", crocoddyl.CostModelResidual(
            state, crocoddyl.ActivationModelQuad(4),
            crocoddyl.ResidualModelState(state, UPRIGHT, 2)), weight)
        terminal = crocoddyl.IntegratedActionModelEuler(
            crocoddyl.DifferentialActionModelFreeFwdDynamics(
                state, crocoddyl.ActuationModelFull(state), costs), 0.0)
        penalised = crocoddyl.ShootingProblem(np.zeros(4), list(reference.runningModels),
                                              terminal)
        solver = crocoddyl.SolverFDDP(penalised)
        solver.th_stop = 1e-18
        assert solver.solve(penalised.rollout(list(ours)), list(ours), 1000, True)
        errors.append(np.max(np.abs(np.array(solver.us) - ours)))
        running = solver.cost - penalised.terminalData.cost
        np.testing.assert_allclose(running, float(solution.cost), rtol=10 / weight)
    # (measured 1.4e-4, 1.4e-6, 1.1e-8: each 100-fold W a 100-fold smaller difference)
    assert errors[0] < 1e-3 and errors[1] < errors[0] / 30 and errors[2] < errors[1] / 30
    assert errors[2] < 1e-7
