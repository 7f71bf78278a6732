"""Trajectory optimisation (iLQR, DDP, multiple shooting, MPC) against the discrete Riccati
equation (SciPy), a quadratic program (SciPy), closed-loop simulation and finite differences
(float64). The comparison with Crocoddyl on the same problems is tests/test_crocoddyl.py."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

import jaxdyn
from helpers import assert_close, central_difference, compiles
from test_control import CART_POLE, cart_pole_T, cart_pole_V

# -- a chain of two masses and springs, pushed on each mass: linear ---------------------------

CHAIN = dict(m=np.array([1.0, 2.0]), k=np.array([3.0, 1.5]))


def chain_T(q, qd, p):
    return 0.5 * jnp.sum(p["m"] * qd**2)


def chain_V(q, p):
    stretch = jnp.array([q[0], q[1] - q[0]])
    return 0.5 * jnp.sum(p["k"] * stretch**2)


CHAIN_PLANT = jaxdyn.Controlled(jaxdyn.Lagrangian(chain_T, chain_V), input_map=[0, 1])
STATE_WEIGHTS = np.diag([2.0, 1.0, 0.5, 0.3])
INPUT_WEIGHTS = np.diag([0.2, 0.1])
DT = 0.05


def chain_matrices(discretisation="euler"):
    """ẋ = A x + B r of the chain, and its discretisation: Euler's, x + Δt (A x + B r), or
    the implicit midpoint rule's, x_{k+1} = x_k + Δt (A (x_k + x_{k+1})/2 + B r), which is
    the midpoint variational integrator of a quadratic Lagrangian with a force held over
    the step (Marsden and West 2001, §3.2)."""
    m, k = CHAIN["m"], CHAIN["k"]
    stiffness = np.array([[k[0] + k[1], -k[1]], [-k[1], k[1]]])
    a = np.block([[np.zeros((2, 2)), np.eye(2)], [-stiffness / m[:, None], np.zeros((2, 2))]])
    b = np.vstack([np.zeros((2, 2)), np.diag(1 / m)])
    if discretisation == "euler":
        return np.eye(4) + DT * a, DT * b
    implicit = np.eye(4) - DT / 2 * a
    return np.linalg.solve(implicit, np.eye(4) + DT / 2 * a), np.linalg.solve(implicit, DT * b)


def chain_running(q, u, r, p):
    x = jnp.concatenate([q, u])
    return 0.5 * (x @ STATE_WEIGHTS @ x + r @ INPUT_WEIGHTS @ r)


@pytest.mark.parametrize("discretisation", ["euler", "variational"])
def test_linear_quadratic_problem_is_the_discrete_riccati_solution(discretisation):
    """With the terminal cost ½ xᵀ P x, P the discrete algebraic Riccati equation's solution
    for the costs Δt Q, Δt R (SciPy), the finite-horizon problem is stationary: every gain is
    the infinite-horizon LQR gain, the optimal cost ½ x₀ᵀ P x₀, and iLQR solves it in one
    step (its model is the problem). With the variational integrator's step, whose Newton
    solve is differentiated by the implicit function theorem, the same against the implicit
    midpoint rule's matrices."""
    a, b = chain_matrices(discretisation)
    riccati = scipy.linalg.solve_discrete_are(a, b, DT * STATE_WEIGHTS, DT * INPUT_WEIGHTS)
    gain = np.linalg.solve(DT * INPUT_WEIGHTS + b.T @ riccati @ b, b.T @ riccati @ a)

    def terminal(q, u, p):
        x = jnp.concatenate([q, u])
        return 0.5 * x @ riccati @ x

    problem = jaxdyn.ShootingProblem(
        CHAIN_PLANT, chain_running, terminal, num_nodes=40, dt=DT,
        discretisation=jaxdyn.Euler() if discretisation == "euler" else jaxdyn.VariationalStep())
    q0, u0 = jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4])
    solution = jaxdyn.solve_optimal_control(problem, q0, u0, CHAIN)
    x0 = np.concatenate([q0, u0])
    assert int(solution.status) == 0 and int(solution.iterations) == 2  # a step, then the check
    np.testing.assert_allclose(solution.cost, 0.5 * x0 @ riccati @ x0, rtol=1e-12)
    np.testing.assert_allclose(solution.feedback, -np.broadcast_to(gain, (40, 2, 4)),
                               atol=1e-11)
    # The closed loop x_{k+1} = (A − B K) x_k, r_k = −K x_k.
    x, inputs = x0, []
    for _ in range(40):
        inputs.append(-gain @ x)
        x = (a - b @ gain) @ x
    np.testing.assert_allclose(solution.inputs, np.array(inputs), atol=1e-12)
    np.testing.assert_allclose(np.concatenate([solution.q[-1], solution.u[-1]]), x, atol=1e-12)


@pytest.mark.parametrize("bound", [0.8, 1.0, 2.0])
def test_bounded_inputs_solve_the_quadratic_program(bound):
    """Box-constrained inputs on the linear chain: the optimum is that of the convex quadratic
    program in the inputs (the states eliminated), solved by SciPy's L-BFGS-B; the active
    bounds hold exactly. (With the looser bounds the iterates once cycled between two
    trajectories, each step a rise of the cost that box-DDP's model had predicted.)"""
    a, b = chain_matrices()
    num = 30

    def terminal(q, u, p):
        x = jnp.concatenate([q, u])
        return 5.0 * x @ x

    problem = jaxdyn.ShootingProblem(CHAIN_PLANT, chain_running, terminal, num_nodes=num,
                                     dt=DT, discretisation=jaxdyn.Euler(),
                                     input_bounds=(-bound, bound))
    x0 = np.array([1.0, -0.5, 0.0, 0.8])
    solution = jaxdyn.solve_optimal_control(problem, x0[:2], x0[2:], CHAIN)

    def cost(flat):
        """The cost and its gradient in the inputs (the adjoint recursion backwards)."""
        r, xs, total = flat.reshape(num, 2), [x0], 0.0
        for k in range(num):
            total += DT * 0.5 * (xs[k] @ STATE_WEIGHTS @ xs[k] + r[k] @ INPUT_WEIGHTS @ r[k])
            xs.append(a @ xs[k] + b @ r[k])
        costate, gradient = 10.0 * xs[-1], np.zeros_like(r)
        for k in reversed(range(num)):
            gradient[k] = DT * INPUT_WEIGHTS @ r[k] + b.T @ costate
            costate = DT * STATE_WEIGHTS @ xs[k] + a.T @ costate
        return total + 5.0 * xs[-1] @ xs[-1], gradient.ravel()

    reference = scipy.optimize.minimize(
        cost, np.zeros(2 * num), jac=True, method="L-BFGS-B",
        bounds=[(-bound, bound)] * (2 * num), options=dict(ftol=1e-16, gtol=1e-12, maxiter=5000))
    assert int(solution.status) == 0
    assert np.sum(np.isclose(np.abs(solution.inputs), bound, rtol=0, atol=1e-12)) >= 2
    assert np.all(np.abs(solution.inputs) <= bound)
    np.testing.assert_allclose(solution.cost, reference.fun, rtol=1e-9)
    np.testing.assert_allclose(solution.inputs.ravel(), reference.x, atol=2e-5)


# -- path and terminal constraints (augmented Lagrangian) --------------------------------------

CHAIN_START = np.array([1.0, -0.5, 0.0, 0.8])


def speed_limit(q, u, r, p):
    return u[1] - p["limit"]  # the second mass's speed at most `limit`


def reached(q, u, p):
    return jnp.concatenate([q, u]) - p["target"]  # the final state exactly `target`


CONSTRAINED_CHAIN = jaxdyn.ShootingProblem(
    CHAIN_PLANT, chain_running, num_nodes=30, dt=DT, discretisation=jaxdyn.Euler(),
    path_constraints=speed_limit, terminal_constraints=reached)
CONSTRAINED_PARAMETERS = dict(CHAIN, limit=jnp.array(0.82),
                              target=jnp.array([0.2, 0.3, 0.0, 0.0]))
TIGHT = jaxdyn.ILQR(tol=1e-14, constraint_tol=1e-11)


def constrained_chain_qp(limit, target):
    """The chain's constrained problem as a quadratic program in the inputs (Euler's matrices,
    the states eliminated): ½ rᵀ H r + gᵀ r subject to the speeds u₁ at nodes k < N at most
    `limit` and the final state at `target`; SciPy's SLSQP finds the active set, the KKT
    system on it gives the inputs and multipliers exactly."""
    a, b = chain_matrices()
    num = 30
    # x_k = Φ_k x0 + Σ_j Γ_kj r_j
    phi = [np.linalg.matrix_power(a, k) for k in range(num + 1)]
    gamma = np.zeros((num + 1, 4, 2 * num))
    for k in range(1, num + 1):
        for j in range(k):
            gamma[k, :, 2 * j:2 * j + 2] = phi[k - 1 - j] @ b
    free = np.array([phi[k] @ CHAIN_START for k in range(num + 1)])
    hessian = DT * sum(gamma[k].T @ STATE_WEIGHTS @ gamma[k] for k in range(num))
    hessian += DT * np.kron(np.eye(num), INPUT_WEIGHTS)
    gradient = DT * sum(gamma[k].T @ STATE_WEIGHTS @ free[k] for k in range(num))
    speeds, speeds_free = gamma[:num, 3], free[:num, 3]  # u₁ at nodes 0 … N−1
    final, final_free = gamma[num], free[num]

    def cost(r):
        return 0.5 * r @ hessian @ r + gradient @ r

    search = scipy.optimize.minimize(
        cost, np.zeros(2 * num), jac=lambda r: hessian @ r + gradient, method="SLSQP",
        constraints=[dict(type="ineq", fun=lambda r: limit - speeds_free - speeds @ r,
                          jac=lambda r: -speeds),
                     dict(type="eq", fun=lambda r: final_free + final @ r - target,
                          jac=lambda r: final)],
        options=dict(ftol=1e-15, maxiter=1000))
    active = np.flatnonzero(np.abs(speeds_free + speeds @ search.x - limit) < 1e-7)
    rows = np.vstack([speeds[active], final])
    kkt = np.block([[hessian, rows.T], [rows, np.zeros((len(rows), len(rows)))]])
    rhs = np.concatenate([-gradient, limit - speeds_free[active], target - final_free])
    solution = np.linalg.solve(kkt, rhs)
    inputs, multipliers = solution[:2 * num], solution[2 * num:]
    path = np.zeros(num)
    path[active] = multipliers[:len(active)]
    constant = DT * sum(0.5 * free[k] @ STATE_WEIGHTS @ free[k] for k in range(num))
    return inputs, path, multipliers[len(active):], cost(inputs) + constant, active


def test_path_and_terminal_constraints_solve_the_quadratic_program():
    """The linear chain with its second mass's speed limited at every node (active on a few)
    and its final state prescribed: the optimum, the constraints' multipliers λ ≥ 0 and ν
    are the KKT solution of the quadratic program on its active set (SciPy's SLSQP for the
    active set); without the limit the speed would exceed it."""
    solution = jaxdyn.solve_optimal_control(CONSTRAINED_CHAIN, CHAIN_START[:2], CHAIN_START[2:],
                                            CONSTRAINED_PARAMETERS, solver=TIGHT)
    inputs, path, terminal, cost, active = constrained_chain_qp(0.82, np.array([0.2, 0.3, 0, 0]))
    assert int(solution.status) == 0 and len(active) >= 2
    assert float(solution.constraint_violation) <= 1e-11
    np.testing.assert_allclose(solution.cost, cost, rtol=1e-10)
    np.testing.assert_allclose(solution.inputs.ravel(), inputs, atol=1e-6)
    np.testing.assert_allclose(solution.path_multipliers[:, 0], path, atol=1e-6)
    np.testing.assert_allclose(solution.terminal_multipliers, terminal, rtol=1e-6)
    np.testing.assert_allclose(solution.u[-1], 0.0, atol=1e-11)
    unlimited = jaxdyn.solve_optimal_control(CONSTRAINED_CHAIN, CHAIN_START[:2],
                                             CHAIN_START[2:], dict(CONSTRAINED_PARAMETERS,
                                                                   limit=jnp.array(9.0)))
    assert float(jnp.max(unlimited.u[:, 1])) > 0.83


def test_gradients_of_a_constrained_optimum_against_finite_differences():
    """d J*/d p with active path and terminal constraints (implicit function theorem, the
    active constraints held) against central differences of solves: a mass, a stiffness,
    the limit (whose derivative is −Σ λ_k) and a target (−ν); under `vmap` one program."""
    def cost(p):
        return jaxdyn.solve_optimal_control(CONSTRAINED_CHAIN, CHAIN_START[:2],
                                            CHAIN_START[2:], p, solver=TIGHT).cost

    gradient = jax.grad(cost)(CONSTRAINED_PARAMETERS)
    h = 1e-5
    for name, index in (("m", 0), ("k", 1), ("limit", ()), ("target", 1)):
        value = jnp.asarray(CONSTRAINED_PARAMETERS[name])
        up, down = (cost(dict(CONSTRAINED_PARAMETERS, **{name: value.at[index].add(sign * h)}))
                    for sign in (1, -1))
        np.testing.assert_allclose(gradient[name][index], (up - down) / (2 * h), rtol=1e-6)
    solution = jaxdyn.solve_optimal_control(CONSTRAINED_CHAIN, CHAIN_START[:2],
                                            CHAIN_START[2:], CONSTRAINED_PARAMETERS,
                                            solver=TIGHT)
    np.testing.assert_allclose(gradient["limit"], -jnp.sum(solution.path_multipliers),
                               rtol=1e-6)
    np.testing.assert_allclose(gradient["target"], -solution.terminal_multipliers, rtol=1e-6)
    limits = jnp.array([0.82, 0.85])
    batched = jax.vmap(lambda limit: cost(dict(CONSTRAINED_PARAMETERS, limit=limit)))(limits)
    np.testing.assert_allclose(batched[0], solution.cost, rtol=1e-12)


class ChainEnergies(eqx.Module):
    """The chain's T and V with its masses and stiffnesses held as arrays of the system (a
    model whose parameters live in its own fields, as a tree's masses do), not in p."""

    m: jax.Array
    k: jax.Array

    def kinetic(self, q, qd, p):
        return chain_T(q, qd, dict(m=self.m))

    def potential(self, q, p):
        return chain_V(q, dict(k=self.k))


def test_the_optimum_differentiates_with_respect_to_the_systems_arrays():
    """Arrays held by the system itself (here the chain's masses and stiffnesses as fields of
    its energies) are differentiated as p is: the rollout of a plan through the implicit
    accelerations, and the optimal cost by the implicit function theorem, against central
    differences (before, the rollout's derivative with respect to them was zero, silently,
    and the optimum's refused)."""
    def problem_of(m, k):
        energies = ChainEnergies(m, k)
        plant = jaxdyn.Controlled(jaxdyn.Lagrangian(energies.kinetic, energies.potential),
                                  input_map=[0, 1])
        return jaxdyn.ShootingProblem(plant, chain_running, num_nodes=20, dt=DT,
                                      discretisation=jaxdyn.RungeKutta4())

    plan = 0.3 * jnp.sin(jnp.arange(40.0)).reshape(20, 2)

    def reached(mk):
        return problem_of(mk[:2], mk[2:]).rollout(jnp.asarray(CHAIN_START), plan, None, 2)[-1]

    def cost(mk):
        return jaxdyn.solve_optimal_control(problem_of(mk[:2], mk[2:]), CHAIN_START[:2],
                                            CHAIN_START[2:], solver=TIGHT).cost

    mk = np.concatenate([CHAIN["m"], CHAIN["k"]])
    rollout = jax.jacfwd(reached)(jnp.asarray(mk))
    assert_close(rollout, central_difference(reached, mk), rtol=1e-7, atol=1e-9)
    gradient = jax.grad(cost)(jnp.asarray(mk))
    assert_close(gradient, central_difference(cost, mk, step=1e-5), rtol=1e-6, atol=1e-9)


def test_infeasible_constraints_are_reported_not_hidden():
    """A speed limit below the initial speed (0.8) cannot hold at node 0: the solve stops
    with the constraints violated (status 3) and says so, rather than returning the
    penalised trajectory as an optimum (a new limit compiles nothing); constraints that are
    not functions or return matrices are refused by name."""
    jaxdyn.solve_optimal_control(CONSTRAINED_CHAIN, CHAIN_START[:2], CHAIN_START[2:],
                                 CONSTRAINED_PARAMETERS)
    with pytest.warns(jaxdyn.NotConvergedWarning, match="constraints violated"), \
            compiles() as count:
        solution = jaxdyn.solve_optimal_control(
            CONSTRAINED_CHAIN, CHAIN_START[:2], CHAIN_START[2:],
            dict(CONSTRAINED_PARAMETERS, limit=jnp.array(0.7)))
    assert count() == 0
    assert int(solution.status) == 3 and not bool(solution.converged)
    np.testing.assert_allclose(solution.constraint_violation, 0.1, rtol=1e-6)
    with pytest.raises(ValueError, match="path_constraints must be a function"):
        jaxdyn.ShootingProblem(CHAIN_PLANT, chain_running, num_nodes=5, dt=DT,
                               path_constraints=1.0)
    matrix = jaxdyn.ShootingProblem(CHAIN_PLANT, chain_running, num_nodes=5, dt=DT,
                                    terminal_constraints=lambda q, u, p: jnp.outer(q, u))
    with pytest.raises(ValueError, match="terminal constraints h must return a scalar or a "
                                         "vector"):
        jaxdyn.solve_optimal_control(matrix, CHAIN_START[:2], CHAIN_START[2:], CHAIN)


# -- the cart-pole, swung up -------------------------------------------------------------------

CART_PLANT = jaxdyn.Controlled(jaxdyn.Lagrangian(cart_pole_T, cart_pole_V), input_map=[0])
FORCE = 6.0  # active on about a fifth of the nodes


def swing_up_running(q, u, r, p):
    return 1e-2 * r @ r + 0.1 * q[0] ** 2


def swing_up_terminal(q, u, p):
    return 1e3 * (q @ q + u @ u)


SWING_UP = jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, swing_up_terminal,
                                  num_nodes=100, dt=0.025, input_bounds=(-FORCE, FORCE))
HANGING = jnp.array([0.0, np.pi])


@pytest.fixture(scope="module")
def swing_up():
    return jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE)


def test_cart_pole_swings_up_and_its_gains_hold_it(swing_up):
    """From hanging to upright in 2.5 s with |F| ≤ 6 N (the bound active: the unbounded
    optimum pushes up to 8.1 N). The plan is the dynamics: its inputs, held over each
    interval and integrated by `simulate` (adaptive Dopri8, not the planner's RK4), retrace
    its states to RK4's error; and its Riccati gains, as feedback, bring the pole upright."""
    assert bool(swing_up.converged) and float(swing_up.gap) == 0.0
    assert np.all(np.abs(swing_up.inputs) <= FORCE)
    assert np.sum(np.abs(swing_up.inputs) == FORCE) >= 10
    np.testing.assert_allclose(swing_up.q[-1], 0.0, atol=2e-3)
    np.testing.assert_allclose(swing_up.u[-1], 0.0, atol=2e-3)

    def held(t):
        return swing_up.inputs[jnp.clip(jnp.floor(t / 0.025 + 1e-9).astype(int), 0, 99)]

    ts = swing_up.ts[:41]  # the first second: the hanging pole's motion, stable
    replay = jaxdyn.simulate(CART_PLANT, HANGING, jnp.zeros(2), CART_POLE, t1=1.0, ts=ts,
                             inputs=held, rtol=1e-11, atol=1e-11, max_steps=100_000)
    np.testing.assert_allclose(replay.q, swing_up.q[:41], atol=1e-5)  # RK4 at Δt = 0.025
    closed = jaxdyn.simulate(CART_PLANT, HANGING, jnp.zeros(2), CART_POLE, t1=2.5,
                             ts=swing_up.ts, inputs=swing_up.policy((-FORCE, FORCE)),
                             rtol=1e-10, atol=1e-10, save=("q", "u", "inputs"))
    # (the feedback acts continuously, the plan's inputs were held: 1.3e-3 apart)
    np.testing.assert_allclose(closed.q, swing_up.q, atol=3e-3)
    assert np.all(np.abs(closed.inputs) <= FORCE)


@pytest.mark.slow  # its own program (the constraints' outer loop): 10 s of compiling
def test_the_cart_pole_swings_up_within_its_rails(swing_up):
    """The swing-up with the cart's travel limited to |x| ≤ 0.4 m (path constraints; the
    unconstrained optimum runs to 0.6 m): the limit holds to the tolerance, touched where
    its multipliers are positive and nowhere else (complementarity), the pole still ends
    upright, at a higher cost than without rails."""
    travel = 0.4
    problem = jaxdyn.ShootingProblem(
        CART_PLANT, swing_up_running, swing_up_terminal, num_nodes=100, dt=0.025,
        input_bounds=(-FORCE, FORCE),
        path_constraints=lambda q, u, r, p: jnp.array([q[0] - travel, -q[0] - travel]))
    plan = jaxdyn.solve_optimal_control(problem, HANGING, jnp.zeros(2), CART_POLE)
    assert float(jnp.max(jnp.abs(swing_up.q[:, 0]))) > 0.6
    assert bool(plan.converged) and float(plan.constraint_violation) <= 1e-6
    assert float(jnp.max(jnp.abs(plan.q[:-1, 0]))) <= travel + 1e-6
    multipliers = np.asarray(plan.path_multipliers)
    margin = np.stack([travel - np.asarray(plan.q[:-1, 0]), travel + np.asarray(plan.q[:-1, 0])],
                      axis=1)
    assert np.all(multipliers >= 0) and np.any(multipliers > 0)
    assert np.all(margin[multipliers > 0] <= 1e-6)
    np.testing.assert_allclose(plan.q[-1], 0.0, atol=2e-3)
    assert float(plan.cost) > float(swing_up.cost)


RAILS = 0.3


def rails(q, u, r, p):
    return jnp.array([q[0] - RAILS, -q[0] - RAILS])


@pytest.mark.slow  # its own program: 10 s of compiling
def test_a_solve_whose_steps_the_cost_cannot_resolve_converges(monkeypatch):
    """Rails of ±0.3 m from ALTRO's first penalty of 1: at a penalty of 10⁷ the inner solve
    reaches steps whose predicted changes (10⁻⁹ to 10⁻¹³) lie below the round-off of its
    cost (2–6 × 10⁻¹² here, amplified by the penalty's stiffness of 4 × 10⁸), so no trial
    shows its decrease. Those below 10⁻¹² |J| are taken untested (the cost changing by less
    than the tolerance), the regularisation falls and the solve converges with the
    constraints met, rather than raising μ on trials it cannot tell apart until the
    iteration limit (or the largest μ, reported as diverged)."""
    import jaxdyn._optimal_control.augmented_lagrangian as augmented_lagrangian

    monkeypatch.setattr(augmented_lagrangian, "_FIRST_PENALTY", 1.0)
    problem = jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, swing_up_terminal,
                                     num_nodes=100, dt=0.025, input_bounds=(-FORCE, FORCE),
                                     path_constraints=rails)
    plan = jaxdyn.solve_optimal_control(problem, HANGING, jnp.zeros(2), CART_POLE,
                                        solver=jaxdyn.ILQR(max_iterations=2000))
    assert bool(plan.converged) and int(plan.iterations) < 2000
    assert float(plan.constraint_violation) <= 1e-6
    assert float(jnp.max(jnp.abs(plan.q[:-1, 0]))) <= RAILS + 1e-6
    assert abs(float(plan.predicted_decrease)) <= 1e-9 * (1 + float(plan.cost))


@pytest.mark.slow  # its own program: 10 s of compiling
def test_an_inner_solve_that_diverges_returns_the_last_trajectory(monkeypatch):
    """Where an inner solve after the first diverges (forced here: its trajectory made
    non-finite and its status diverged from the first update of the multipliers on, since
    whether a stiff penalty truly diverges hangs on round-off), the solve returns the last
    inner solve's trajectory, finite, as status 3 with its violation and a warning: not an
    error for a problem that came close, nor a trajectory passed off as converged."""
    import equinox as eqx

    import jaxdyn._optimal_control.augmented_lagrangian as augmented_lagrangian
    from jaxdyn._optimal_control.solver import DIVERGED

    inner_solve = augmented_lagrangian.iterate_to_optimum

    def diverging_once_pushed(augmented, *args, **kwargs):
        inner = inner_solve(augmented, *args, **kwargs)
        pushed = jnp.any(augmented.multipliers > 0)
        return eqx.tree_at(lambda it: (it.xs, it.status), inner,
                           (jnp.where(pushed, jnp.nan, inner.xs),
                            jnp.where(pushed, DIVERGED, inner.status)))

    monkeypatch.setattr(augmented_lagrangian, "iterate_to_optimum", diverging_once_pushed)
    problem = jaxdyn.ShootingProblem(  # (its own constraint function: its own program)
        CART_PLANT, swing_up_running, swing_up_terminal, num_nodes=100, dt=0.025,
        input_bounds=(-FORCE, FORCE),
        path_constraints=lambda q, u, r, p: jnp.array([q[0] - RAILS, -q[0] - RAILS]))
    with pytest.warns(jaxdyn.NotConvergedWarning, match="constraints violated"):
        plan = jaxdyn.solve_optimal_control(problem, HANGING, jnp.zeros(2), CART_POLE)
    assert int(plan.status) == 3
    # the first inner solve's: the penalty of 100 alone leaves the rails passed
    violation = float(jnp.max(jnp.abs(plan.q[:-1, 0]))) - RAILS
    assert 1e-4 < float(plan.constraint_violation) < 0.1
    np.testing.assert_allclose(plan.constraint_violation, violation, rtol=1e-12)
    assert np.all(np.isfinite(plan.q)) and np.all(np.isfinite(plan.inputs))
    assert np.all(np.abs(plan.inputs) <= FORCE)


# Solves converged to round-off, the references of the finite differences: DDP from the optimum
# converges quadratically (iLQR's linear convergence would leave the inputs ~10⁻⁶ off).
def test_a_variational_discretisation_swings_the_cart_pole_up():
    """The same swing-up with the variational integrator's step (midpoint rule, a Newton
    solve per node differentiated by the implicit function theorem): converged with the bound
    active, the pole upright; replayed by `simulate` (adaptive Dopri8), the plan's held inputs
    retrace its states to the midpoint rule's second-order error, the order below RK4's; a
    formulation other than a Lagrangian is refused by name."""
    problem = jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, swing_up_terminal,
                                     num_nodes=100, dt=0.025, input_bounds=(-FORCE, FORCE),
                                     discretisation=jaxdyn.VariationalStep())
    plan = jaxdyn.solve_optimal_control(problem, HANGING, jnp.zeros(2), CART_POLE)
    assert bool(plan.converged)
    assert np.all(np.abs(plan.inputs) <= FORCE) and np.sum(np.abs(plan.inputs) == FORCE) >= 10
    np.testing.assert_allclose(plan.q[-1], 0.0, atol=2e-3)

    def held(t):
        return plan.inputs[jnp.clip(jnp.floor(t / 0.025 + 1e-9).astype(int), 0, 99)]

    replay = jaxdyn.simulate(CART_PLANT, HANGING, jnp.zeros(2), CART_POLE, t1=1.0,
                             ts=plan.ts[:41], inputs=held, rtol=1e-11, atol=1e-11,
                             max_steps=100_000)
    error = float(jnp.max(jnp.abs(replay.q - plan.q[:41])))
    assert 1e-4 < error < 1e-2, error  # (2.2e-3; RK4's plan: below 1e-5)
    with pytest.raises(ValueError, match="VariationalStep is built from a Lagrangian"):
        jaxdyn.ShootingProblem(  # the cart held by a constraint: a constrained formulation
            jaxdyn.Constrained(CART_PLANT, holonomic=lambda q, p: q[:1]), swing_up_running,
            num_nodes=10, dt=0.025, discretisation=jaxdyn.VariationalStep())


TO_ROUND_OFF = jaxdyn.DDP(tol=1e-15)


# Slow (30 s): the default run checks the implicit-function-theorem derivatives of a
# constrained optimum against central differences (above); this one, the input bound active
# and the inputs' derivatives in the start included, runs with -m slow.
@pytest.mark.slow
def test_gradients_of_the_optimum_against_finite_differences(swing_up):
    """d J*/d p and d r*/d x₀ by the implicit function theorem (the bound active on 18
    nodes) against central differences of solves converged to round-off. (The derivatives of
    the inputs are as accurate as the solve they start from: at iLQR's default tolerance
    they are 2·10⁻⁴ off, the cost's derivative is not, being stationary.)"""
    def optimum(m, l, angle, solver=jaxdyn.ILQR(tol=1e-15, max_iterations=1000)):
        p = dict(CART_POLE, m=m, l=l)
        solution = jaxdyn.solve_optimal_control(SWING_UP, jnp.array([0.0, angle]), jnp.zeros(2),
                                                p, solver=solver, inputs=swing_up.inputs)
        return solution.cost, solution.inputs[10, 0]

    point = (0.1, 0.5, np.pi)
    gradients = jax.jacobian(optimum, argnums=(0, 1, 2))(*point)
    h = 1e-5
    for i in range(3):
        up = [v + h * (j == i) for j, v in enumerate(point)]
        down = [v - h * (j == i) for j, v in enumerate(point)]
        (cost_up, input_up), (cost_down, input_down) = (optimum(*up, TO_ROUND_OFF),
                                                        optimum(*down, TO_ROUND_OFF))
        np.testing.assert_allclose(gradients[0][i], (cost_up - cost_down) / (2 * h), rtol=1e-7)
        # (the inputs' round-off, ~10⁻¹², over h: a few 10⁻⁷ of the difference quotient)
        np.testing.assert_allclose(gradients[1][i], (input_up - input_down) / (2 * h),
                                   rtol=1e-5)
    # Under `vmap` (each problem solved apart, `jaxdyn._chunking`) the same derivatives.
    masses = jnp.array([0.1, 0.12])
    batched = jax.vmap(jax.grad(lambda m: optimum(m, 0.5, np.pi)[0]))(masses)
    np.testing.assert_allclose(batched[0], gradients[0][0], rtol=1e-10)
    cost_up, cost_down = (optimum(0.12 + sign * h, 0.5, np.pi, TO_ROUND_OFF)[0]
                          for sign in (1, -1))
    np.testing.assert_allclose(batched[1], (cost_up - cost_down) / (2 * h), rtol=1e-7)


def test_ddp_converges_quadratically_where_ilqr_converges_linearly(swing_up):
    """From near the optimum, DDP (the dynamics' second derivatives in its model) meets a
    tolerance of 10⁻¹⁵ in a few iterations; iLQR (Gauss–Newton, linear convergence) needs
    many times as many (4 against 32 with box-DDP's value update at the bounds, over 40 with
    the exact expansion of the clamped policy); both reach the same optimum."""
    start = swing_up.inputs + 0.01 * jnp.sin(jnp.arange(100.0))[:, None]
    ddp = jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE,
                                       solver=TO_ROUND_OFF, inputs=start)
    ilqr = jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE,
                                        solver=jaxdyn.ILQR(tol=1e-15, max_iterations=1000),
                                        inputs=start)
    assert bool(ddp.converged) and int(ddp.iterations) <= 5
    assert bool(ilqr.converged) and int(ilqr.iterations) >= 6 * int(ddp.iterations)
    np.testing.assert_allclose(ddp.cost, ilqr.cost, rtol=1e-13)
    np.testing.assert_allclose(ddp.inputs, ilqr.inputs, atol=1e-6)


def test_new_values_reuse_the_compiled_solve(swing_up):
    """A second solve with new values of the same shapes (start, parameters, guess, the
    problem's t0) compiles nothing."""
    problem = jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, swing_up_terminal,
                                     num_nodes=100, dt=0.025, input_bounds=(-FORCE, FORCE),
                                     t0=1.5)
    start, rest = jnp.array([0.0, np.pi - 0.1]), jnp.zeros(2)
    with compiles() as count:
        again = jaxdyn.solve_optimal_control(problem, start, rest, dict(CART_POLE, m=0.11),
                                             inputs=swing_up.inputs)
    assert count() == 0 and bool(again.converged)
    np.testing.assert_allclose(again.ts[0], 1.5)


def test_a_batch_of_swing_ups_is_one_program(swing_up):
    """`jax.vmap` over initial angles: one compiled program, each member its own solve."""
    angles = jnp.array([np.pi, np.pi - 0.2, np.pi + 0.3])

    def cost(angle):
        return jaxdyn.solve_optimal_control(SWING_UP, jnp.array([0.0, angle]), jnp.zeros(2),
                                            CART_POLE).cost

    batched = jax.jit(jax.vmap(cost))
    with compiles() as count:
        costs = batched(angles)
    assert count() == 1
    np.testing.assert_allclose(costs[0], swing_up.cost, rtol=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(costs[1], cost(angles[1]), rtol=1e-10)


def test_an_infeasible_start_closes_its_gaps():
    """Multiple shooting from states on a straight line from hanging to upright (far from any
    trajectory) with zero inputs: the defects close and the pole swings up."""
    line = jnp.linspace(0.0, 1.0, 101)[:, None]
    states = (HANGING[None] * (1 - line), jnp.zeros((101, 2)))
    solution = jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE,
                                            states=states)
    assert bool(solution.converged) and float(solution.gap) == 0.0
    np.testing.assert_allclose(solution.q[-1], 0.0, atol=2e-3)
    assert np.all(np.abs(solution.inputs) <= FORCE)


# -- a block pushed against Coulomb friction, in compliant contact with the ground -----------

BLOCK = dict(m=2.0, g=9.81, mu=0.5, k=1e6)


def block_scene(relaxation):
    """A block (a point mass) on compliant ground (Hunt–Crossley, Coulomb friction μ), pushed
    along x by a force r; the ground's tangential deformation relaxes in `relaxation` s."""
    m, g, mu, k = (BLOCK[name] for name in ("m", "g", "mu", "k"))
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * m * qd @ qd,
                                                lambda q, p: m * g * q[2]), input_map=[0])
    return jaxdyn.Contact(plant, [jaxdyn.ContactPoint(lambda q, p: q)],
                          model=jaxdyn.HuntCrossley(k, 1.0, friction=mu,
                                                    tangential_damping=relaxation * k,
                                                    smoothing=1e-5))


def test_a_block_pushed_against_coulomb_friction_in_compliant_contact():
    """Contact in a shooting problem: the block moved from rest to rest 1 m away in 1 s with
    the least Σ Δt r² (semi-implicit Euler, Δt = 2.5 ms, the final state a constraint). While
    it slides forward, friction is μ m g against the motion, so the optimal force is the rigid
    Coulomb block's: m a_k + μ m g, with a_k the discrete double integrator's least-norm
    accelerations (NumPy). The compliant model departs from it where the block sticks: at the
    start, while the ground's deformation loads (τ = 20 ms), and as it comes to rest."""
    m, g, mu, k = (BLOCK[name] for name in ("m", "g", "mu", "k"))
    num_nodes, dt = 400, 0.0025
    problem = jaxdyn.ShootingProblem(
        block_scene(0.02), lambda q, u, r, p: r, num_nodes=num_nodes, dt=dt,
        discretisation=jaxdyn.SemiImplicitEuler(),
        terminal_constraints=lambda q, u, p: jnp.array([q[0] - 1.0, u[0]]))
    resting = (m * g / k) ** (2 / 3)  # the block's sinking under its weight
    plan = jaxdyn.solve_optimal_control(
        problem, jnp.array([0.0, 0.0, -resting]), jnp.zeros(3), {},
        inputs=jnp.full((num_nodes, 1), 1.2 * mu * m * g))  # (a guess that slides it)
    assert bool(plan.converged)
    assert plan.q.shape == (num_nodes + 1, 6)  # (q, ξ): the ground's deformation appended
    np.testing.assert_allclose([plan.q[-1, 0], plan.u[-1, 0]], [1.0, 0.0], atol=1e-6)
    # x_N = Δt² Σ (N − k) a_k, v_N = Δt Σ a_k (semi-implicit Euler from rest)
    steps = np.arange(num_nodes)
    a = np.stack([dt**2 * (num_nodes - steps), dt * np.ones(num_nodes)])
    least_norm = a.T @ np.linalg.solve(a @ a.T, np.array([1.0, 0.0]))
    sliding = slice(num_nodes // 10, num_nodes - num_nodes // 50)
    np.testing.assert_allclose(plan.inputs[sliding, 0],
                               m * least_norm[sliding] + mu * m * g, atol=0.05)


def test_mpc_pushes_the_block_in_compliant_contact():
    """MPC on the contact scene: the closed loop carries the ground's deformation with the
    block's state, and its states are the plant's own motion under the inputs it applied
    (`simulate` of the scene with those inputs held over each interval)."""
    m, g, mu = BLOCK["m"], BLOCK["g"], BLOCK["mu"]
    scene, dt, steps = block_scene(0.02), 0.01, 5
    problem = jaxdyn.ShootingProblem(
        scene, lambda q, u, r, p: jnp.concatenate([0.1 * r, 10 * (q[:1] - 1.0), u[:1]]),
        num_nodes=20, dt=dt, discretisation=jaxdyn.SemiImplicitEuler())
    q0 = jnp.array([0.0, 0.0, -(m * g / BLOCK["k"]) ** (2 / 3)])
    loop = jaxdyn.model_predictive_control(problem, q0, jnp.zeros(3), {}, num_steps=steps,
                                           inputs=jnp.full((20, 1), 1.2 * mu * m * g))
    assert loop.q.shape == (steps + 1, 6)  # (q, ξ)
    assert float(loop.q[-1, 0]) > 0.01  # pushed forward, past sticking
    applied = loop.inputs[:, 0]
    replay = jaxdyn.simulate(scene.with_inputs(lambda t: applied[jnp.minimum(
        jnp.floor(t / dt + 1e-9).astype(int), steps - 1)][None]), q0, jnp.zeros(3), {},
        t1=steps * dt, ts=loop.ts, rtol=1e-10, atol=1e-10, max_steps=100_000)
    np.testing.assert_allclose(replay.q, loop.q, atol=1e-6)


def test_a_contact_step_too_long_for_the_ground_is_named():
    """The ground's deformation relaxes in τ = 2 ms by default: an explicit step of 5 ms would
    let it grow without bound (and lose friction)."""
    running = lambda q, u, r, p: r  # noqa: E731
    with pytest.raises(ValueError, match=r"relaxes in τ = c_t/k_t = 2 ms.*below 2τ = 4 ms"):
        jaxdyn.ShootingProblem(block_scene(2e-3), running, num_nodes=10, dt=0.005,
                               discretisation=jaxdyn.SemiImplicitEuler())
    with pytest.raises(ValueError, match=r"below 2.785τ"):
        jaxdyn.ShootingProblem(block_scene(2e-3), running, num_nodes=10, dt=0.006)
    jaxdyn.ShootingProblem(block_scene(2e-3), running, num_nodes=10, dt=0.005)  # RK4: stable


def test_mpc_swings_up_and_holds_the_pole_of_a_heavier_plant():
    """Receding-horizon control (a 1.5 s horizon, at most 10 iterations a step, warm-started)
    from hanging, of a plant whose pole is 20 % heavier than the model's: the pole comes up
    and stays, within the force bound."""
    problem = jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, swing_up_terminal,
                                     num_nodes=60, dt=0.025, input_bounds=(-10.0, 10.0))
    closed = jaxdyn.model_predictive_control(
        problem, HANGING, jnp.zeros(2), CART_POLE, num_steps=200,
        plant_parameters=dict(CART_POLE, m=0.12))
    assert closed.q.shape == (201, 2) and closed.inputs.shape == (200, 1)
    np.testing.assert_allclose(closed.q[-20:], 0.0, atol=2e-3)
    np.testing.assert_allclose(closed.u[-20:], 0.0, atol=2e-3)
    assert np.all(np.abs(closed.inputs) <= 10.0)
    assert np.all(np.asarray(closed.status) != 2)


# -- the double pendulum: DDP against iLQR -----------------------------------------------------

PENDULUM = dict(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=9.81)


def double_pendulum_T(q, qd, p):
    """Point masses; angles from the upward vertical."""
    v1 = p["l1"] * qd[0] * jnp.array([jnp.cos(q[0]), -jnp.sin(q[0])])
    v2 = v1 + p["l2"] * qd[1] * jnp.array([jnp.cos(q[1]), -jnp.sin(q[1])])
    return 0.5 * p["m1"] * v1 @ v1 + 0.5 * p["m2"] * v2 @ v2


def double_pendulum_V(q, p):
    h1 = p["l1"] * jnp.cos(q[0])
    return p["g"] * (p["m1"] * h1 + p["m2"] * (h1 + p["l2"] * jnp.cos(q[1])))


@pytest.mark.slow  # its own program (a second system): 10 s of compiling
def test_double_pendulum_swings_up_and_is_held():
    """Both joints driven (|τ| ≤ 15 N m) from hanging: the plan ends upright, its Riccati gains
    as feedback in `simulate` follow it there, and an LQR designed on `jaxdyn.linearise` at the
    upright (SciPy's Riccati solver) holds it for a second after the horizon."""
    plant = jaxdyn.Controlled(jaxdyn.Lagrangian(double_pendulum_T, double_pendulum_V),
                              input_map=[0, 1])

    def running(q, u, r, p):
        return 1e-2 * r @ r

    def terminal(q, u, p):
        return 1e3 * (q @ q + u @ u)

    problem = jaxdyn.ShootingProblem(plant, running, terminal, num_nodes=60, dt=0.04,
                                     input_bounds=(-15.0, 15.0))
    q0 = jnp.array([np.pi, np.pi])
    plan = jaxdyn.solve_optimal_control(problem, q0, jnp.zeros(2), PENDULUM)
    assert bool(plan.converged) and np.all(np.abs(plan.inputs) <= 15.0)
    np.testing.assert_allclose(np.cos(plan.q[-1]), 1.0, atol=1e-5)  # upright, whichever turn
    upright = jnp.round(plan.q[-1] / (2 * np.pi)) * 2 * np.pi
    model = jaxdyn.linearise(plant, 0.0, upright, jnp.zeros(2), PENDULUM, jnp.zeros(2))
    a, b = np.asarray(model.A), np.asarray(model.B)
    gain = np.linalg.solve(np.eye(2), b.T @ scipy.linalg.solve_continuous_are(
        a, b, np.eye(4), np.eye(2)))
    follow = plan.policy((-15.0, 15.0))

    def swing_then_hold(t, q, u, p):
        held = -jnp.asarray(gain) @ jnp.concatenate([q - upright, u])
        return jnp.where(t < plan.ts[-1], follow(t, q, u, p), held)

    run = jaxdyn.simulate(plant, q0, jnp.zeros(2), PENDULUM, t1=3.4, inputs=swing_then_hold,
                          rtol=1e-10, atol=1e-10, ts=jnp.linspace(0.0, 3.4, 86))
    np.testing.assert_allclose(run.q[:61], plan.q, atol=2e-2)  # the continuous feedback
    np.testing.assert_allclose(run.q[-10:], jnp.broadcast_to(upright, (10, 2)), atol=1e-3)


def test_a_constrained_step_differentiates_as_finite_differences():
    """The derivative of a shooting problem's step of a constrained system (a pendulum as a
    particle on its rod, φ a function, Baumgarte's terms; RK4's four stages), formed from the
    residuals of Lagrange's equations of the first kind, against central differences."""
    p = dict(m=1.3, g=9.81, l=0.8)
    particle = jaxdyn.Constrained(
        jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                                            lambda q, p: p["m"] * p["g"] * q[1]),
                          input_map=[0]),
        holonomic=lambda q, p: jnp.array([q @ q - p["l"] ** 2]),
        stabilisation=jaxdyn.Baumgarte(2.0, 3.0))
    problem = jaxdyn.ShootingProblem(particle, lambda q, u, r, p: r, num_nodes=1, dt=0.05)
    z = np.array([0.5, -0.7, 0.3, 0.1, 0.4])  # q, u off the rod, and the force

    def step(z):
        return problem.step(0.0, z[:4], z[4:], p, 2)

    derivative = jax.jit(jax.jacfwd(step))(jnp.asarray(z))
    numeric = central_difference(jax.jit(step), z, step=1e-6)
    np.testing.assert_allclose(derivative, numeric, rtol=1e-6,
                               atol=1e-6 * np.max(np.abs(numeric)))


@pytest.mark.slow  # its own program (a constrained system): 10 s of compiling
def test_a_constrained_pendulum_reaches_the_optimum_of_its_angle():
    """A pendulum as a particle (x, y) held on its rod by a holonomic constraint
    (`Constrained`, multipliers) and as one angle (`Lagrangian`): pushed by a horizontal force
    from hanging to 0.5 rad at rest, both reach the same optimum (to the constrained
    integration's drift off the rod, 10⁻⁶)."""
    def cartesian_T(q, qd, p):
        return 0.5 * p["m"] * qd @ qd

    def cartesian_V(q, p):
        return p["m"] * p["g"] * q[1]

    def rod(q, p):
        return jnp.array([q @ q - p["l"] ** 2])

    def angle_T(q, qd, p):
        return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2

    def angle_V(q, p):
        return -p["m"] * p["g"] * p["l"] * jnp.cos(q[0])

    def effort(q, u, r, p):
        return 1e-2 * r @ r

    def at_rest_at(position, velocity):
        goal = jnp.array([np.sin(0.5), -np.cos(0.5)])
        return 1e2 * ((position - goal) @ (position - goal) + velocity @ velocity)

    def cartesian_terminal(q, u, p):
        return at_rest_at(q, u)

    def angle_terminal(q, u, p):
        direction = jnp.array([jnp.cos(q[0]), jnp.sin(q[0])])
        return at_rest_at(p["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])]),
                          p["l"] * u[0] * direction)

    p = dict(m=1.0, g=9.81, l=1.0)
    particle = jaxdyn.Constrained(
        jaxdyn.Controlled(jaxdyn.Lagrangian(cartesian_T, cartesian_V), input_map=[0]),
        holonomic=rod)
    # The horizontal force F does the work F l cos θ δθ: B = [l cos θ].
    angle = jaxdyn.Controlled(jaxdyn.Lagrangian(angle_T, angle_V),
                              input_map=lambda q, p: jnp.array([[p["l"] * jnp.cos(q[0])]]))
    cartesian = jaxdyn.solve_optimal_control(
        jaxdyn.ShootingProblem(particle, effort, cartesian_terminal, num_nodes=50, dt=0.04),
        jnp.array([0.0, -1.0]), jnp.zeros(2), p)
    minimal = jaxdyn.solve_optimal_control(
        jaxdyn.ShootingProblem(angle, effort, angle_terminal, num_nodes=50, dt=0.04),
        jnp.zeros(1), jnp.zeros(1), p)
    assert bool(cartesian.converged) and bool(minimal.converged)
    np.testing.assert_allclose(cartesian.cost, minimal.cost, rtol=1e-5)
    np.testing.assert_allclose(cartesian.inputs, minimal.inputs, atol=1e-4)
    np.testing.assert_allclose(jnp.arctan2(cartesian.q[:, 0], -cartesian.q[:, 1]),
                               minimal.q[:, 0], atol=1e-5)


# -- errors --------------------------------------------------------------------------------------

def test_problems_and_failures_are_named():
    uncontrolled = jaxdyn.Lagrangian(cart_pole_T, cart_pole_V)
    with pytest.raises(ValueError, match="declares no inputs"):
        jaxdyn.ShootingProblem(uncontrolled, swing_up_running, num_nodes=10, dt=0.1)
    with pytest.raises(ValueError, match="num_nodes"):
        jaxdyn.ShootingProblem(CART_PLANT, swing_up_running, num_nodes=0, dt=0.1)
    with pytest.raises(ValueError, match=r"shape \(100, 1\)"):
        jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE,
                                     inputs=jnp.zeros((99, 1)))
    matrix = jaxdyn.ShootingProblem(CART_PLANT, lambda q, u, r, p: jnp.outer(q, q),
                                    num_nodes=10, dt=0.1)
    with pytest.raises(ValueError, match="scalar or a residual vector"):
        jaxdyn.solve_optimal_control(matrix, HANGING, jnp.zeros(2), CART_POLE)
    nan = jaxdyn.ShootingProblem(CART_PLANT, lambda q, u, r, p: jnp.log(q[0] - 1.0),
                                 num_nodes=10, dt=0.1)
    with pytest.raises(ValueError, match="not finite"):
        jaxdyn.solve_optimal_control(nan, HANGING, jnp.zeros(2), CART_POLE)
    with pytest.warns(jaxdyn.NotConvergedWarning, match="iteration limit"):
        short = jaxdyn.solve_optimal_control(SWING_UP, HANGING, jnp.zeros(2), CART_POLE,
                                             solver=jaxdyn.ILQR(max_iterations=3))
    assert int(short.status) == 1 and not bool(short.converged)
