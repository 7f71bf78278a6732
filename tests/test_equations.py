"""How the equations are evaluated: compile once, jit bound methods, branch-free evaluation,
work a system does not need skipped — each checked to leave the results unchanged against
independent oracles (closed forms, NumPy linear algebra)."""

import copy
import inspect

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import jaxdyn
import jaxdyn._unroll
from jaxdyn._dynamics import constant_mass_matrix, mass_matrix_blocks, straight_line_size
from jaxdyn.rotations import planar_rotation

from helpers import DOUBLE_PENDULUM, PENDULUM, assert_close, rod_chain

DP = DOUBLE_PENDULUM


# ---------------------------------------------------------------------------------------------
# Compiled once, reused; bound methods can be jitted
# ---------------------------------------------------------------------------------------------


def _counting_pendulum():
    """A pendulum whose kinetic energy counts how often it is traced."""
    traces = []

    def kinetic(q, qd, p):
        traces.append(None)
        return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2

    def potential(q, p):
        return -p["m"] * 9.81 * p["l"] * jnp.cos(q[0])

    return jaxdyn.Lagrangian(kinetic, potential), traces


def test_direct_calls_compile_once_per_shape():
    pendulum, traces = _counting_pendulum()
    p = {"m": 1.0, "l": 0.5}
    first = pendulum.accelerations(0.0, np.array([0.3]), np.array([0.0]), p)
    count = len(traces)
    assert count > 0
    # New state, new time, new Python-float parameter values: the compiled method is reused.
    second = pendulum.accelerations(1.0, np.array([0.7]), np.array([2.0]), {"m": 3.0, "l": 0.9})
    assert len(traces) == count
    assert_close(first, [-9.81 / 0.5 * np.sin(0.3)], rtol=1e-14)
    assert_close(second, [-9.81 / 0.9 * np.sin(0.7)], rtol=1e-14)


def test_simulate_does_not_recompile_for_new_numbers():
    pendulum, traces = _counting_pendulum()
    q0, u0 = np.array([0.3]), np.array([0.0])
    jaxdyn.simulate(pendulum, q0, u0, {"m": 1.0, "l": 0.5}, t1=1.0, ts=np.linspace(0, 1, 5),
                    rtol=1e-8)
    count = len(traces)
    sol = jaxdyn.simulate(pendulum, q0, u0, {"m": 2.0, "l": 0.7}, t1=2.0,
                          ts=np.linspace(0, 2, 5), rtol=1e-9, atol=1e-9)
    assert len(traces) == count
    # The new values were used: SciPy on θ̈ = −(g/l) sin θ with l = 0.7.
    reference = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], -9.81 / 0.7 * np.sin(y[0])], (0.0, 2.0), [0.3, 0.0],
        t_eval=np.linspace(0, 2, 5), rtol=1e-12, atol=1e-12)
    assert_close(sol.q[:, 0], reference.y[0], rtol=0, atol=1e-7)


def _sleigh():
    def orientation(q, p):
        return planar_rotation(q[2])

    def centre(q, p):
        return jnp.array([q[0], q[1], 0.0]) + orientation(q, p) @ jnp.array([p["a"], 0.0, 0.0])

    def kinematic_map(q, p):
        c, s = jnp.cos(q[2]), jnp.sin(q[2])
        return jnp.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])

    body = jaxdyn.RigidBody(2.0, jnp.diag(jnp.array([0.1, 0.1, 0.3])), centre, orientation)
    system = jaxdyn.MultibodySystem([body], gravity=jnp.array([0.0, 0.0, -9.81]))
    return system, kinematic_map


@pytest.mark.parametrize("formulation", ["Lagrange", "Gibbs-Appell", "Kane"])
def test_jit_of_a_bound_method_for_every_formulation(formulation):
    system, kinematic_map = _sleigh()
    dynamics = {"Lagrange": None,
                "Gibbs-Appell": jaxdyn.GibbsAppell.from_system(system, kinematic_map),
                "Kane": jaxdyn.Kane(system, kinematic_map)}[formulation]
    p = {"a": 0.3}
    if dynamics is None:  # holonomic version: the free planar body in (x, y, θ)
        dynamics = jaxdyn.Lagrangian.from_system(system)
        q, u = np.array([0.1, 0.2, 0.3]), np.array([1.0, -0.5, 0.4])
    else:
        q, u = np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.5])
    jitted = jax.jit(dynamics.accelerations)
    assert_close(jitted(0.0, q, u, p), dynamics.accelerations(0.0, q, u, p), rtol=1e-14)
    assert_close(jax.jit(dynamics.mass_matrix)(0.0, q, u, p), dynamics.mass_matrix(0.0, q, u, p),
                 rtol=1e-14)


def test_a_bound_method_is_built_once_per_instance():
    """Equinox builds a bound method (a pytree walking the whole module) at every attribute
    access; jaxdyn's public methods keep theirs on the instance: the same object each time,
    and another instance's own."""
    system, _ = _sleigh()
    dynamics = jaxdyn.Lagrangian.from_system(system)
    assert dynamics.accelerations is dynamics.accelerations
    assert dynamics.mass_matrix is not dynamics.accelerations
    other = jaxdyn.Lagrangian.from_system(system)
    assert other.accelerations is not dynamics.accelerations
    copied = copy.copy(dynamics)  # shares the original's attributes, the cache among them
    assert copied.accelerations is not dynamics.accelerations
    assert copied.accelerations is copied.accelerations
    assert dynamics.accelerations is dynamics.accelerations
    rebuilt = jax.tree_util.tree_map(lambda x: x, dynamics)
    assert rebuilt.accelerations is not dynamics.accelerations
    # What `help` and `inspect` show, as for any bound method
    assert dynamics.accelerations.__doc__ == type(dynamics).accelerations.__doc__
    assert list(inspect.signature(dynamics.accelerations).parameters)[:4] == ["t", "q", "u", "p"]
    q, u, p = np.array([0.1, 0.2, 0.3]), np.array([1.0, -0.5, 0.4]), {"a": 0.3}
    assert_close(other.accelerations(0.0, q, u, p), dynamics.accelerations(0.0, q, u, p),
                 rtol=0)


# ---------------------------------------------------------------------------------------------
# Branch-free evaluation: NaN where the equations fail, with throw=False
# ---------------------------------------------------------------------------------------------


def test_accelerations_without_check_return_nan_where_the_mass_matrix_is_singular():
    pendulum = PENDULUM.dynamics
    singular = {**PENDULUM.params, "m": 0.0}
    a = pendulum.accelerations(0.0, np.array([0.3]), np.array([0.0]), singular, throw=False)
    assert np.isnan(np.asarray(a)).all()
    with pytest.raises(RuntimeError, match="The mass matrix is singular"):
        pendulum.accelerations(0.0, np.array([0.3]), np.array([0.0]), singular)
    regular = pendulum.accelerations(0.0, np.array([0.3]), np.array([0.0]), PENDULUM.params,
                                     throw=False)
    assert_close(regular, PENDULUM.accelerations(np.array([0.3]), None, PENDULUM.params),
                 rtol=1e-14)


def test_a_failed_solve_reports_its_cause_without_throwing():
    polar = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2))
    sol = jaxdyn.simulate(polar, np.array([1.0, 0.0]), np.array([-1.0, 0.0]), None, t1=2.0,
                          dt0=0.25, stepsize_controller=diffrax.ConstantStepSize(), throw=False)
    assert sol.result == jaxdyn.RESULTS.singular_mass_matrix
    # Dopri8's last stage of the step from 0.75 to 1 meets r = 0: that step is not accepted.
    assert int(sol.num_accepted_steps) == 3


def test_an_adaptive_solve_stops_where_the_equations_fail_and_not_at_max_steps():
    """q1 = t exactly and M22 = 1 − q1: the solver creeps up to t = 1 with ever smaller steps
    and stops there (a few hundred steps), instead of spending its whole step budget."""
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2 + 0.5 * (1 - q[0]) * qd[1] ** 2)
    sol = jaxdyn.simulate(system, np.zeros(2), np.array([1.0, 0.0]), None, t1=3.0, throw=False)
    assert sol.result == jaxdyn.RESULTS.singular_mass_matrix
    assert int(sol.num_steps) < 1000


# ---------------------------------------------------------------------------------------------
# Work a system does not need is skipped; results unchanged
# ---------------------------------------------------------------------------------------------


def _oscillators(n):
    """n unit masses in a row joined by unit springs, Cartesian coordinates: M = I."""
    def kinetic(q, qd, p):
        return 0.5 * p["m"] * jnp.sum(qd**2)

    def potential(q, p):
        stretch = jnp.diff(jnp.concatenate([jnp.zeros(1), q, jnp.zeros(1)]))
        return 0.5 * p["k"] * jnp.sum(stretch**2)

    return jaxdyn.Lagrangian(kinetic, potential)


def _normal_modes(n, q0, t, m, k):
    """Exact solution of the fixed–fixed spring chain from rest: normal modes."""
    stiffness = k * (2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1))
    w2, modes = np.linalg.eigh(stiffness / m)
    amplitudes = modes.T @ q0
    return np.stack([modes @ (amplitudes * np.cos(np.sqrt(w2) * ti)) for ti in t])


@pytest.mark.parametrize("straight_line", [True, False])
def test_a_constant_mass_matrix_is_detected_and_factored_once(straight_line, monkeypatch):
    """Evaluated as arrays (the budget for straight-line code set to zero), M = m I is
    factored once before the solve; either way the motion is the exact normal-mode one."""
    n, p = 6, {"m": 1.3, "k": 7.0}
    system = _oscillators(n)
    q0 = np.random.default_rng(1).normal(size=n)
    assert constant_mass_matrix(system, 0.0, q0, np.zeros(n), p)
    assert not constant_mass_matrix(DP.dynamics, 0.0, np.ones(2), np.ones(2), DP.params)
    if not straight_line:
        monkeypatch.setattr(jaxdyn._unroll, "MAX_ELEMENTS", 0)
        assert straight_line_size(system, 0.0, q0, np.zeros(n), p) is None
    ts = np.linspace(0.0, 5.0, 11)
    sol = jaxdyn.simulate(system, q0, np.zeros(n), p, t1=5.0, ts=ts)
    assert_close(sol.q, _normal_modes(n, q0, ts, p["m"], p["k"]), rtol=0, atol=1e-8)


def test_independent_subsystems_are_solved_block_by_block(monkeypatch):
    """Eight uncoupled double pendulums in one system. Evaluated as arrays (the budget for
    straight-line code set to zero), M is found to be eight 2×2 blocks; the accelerations
    equal those of the single double pendulum's closed form."""
    count = 8

    def kinetic(q, qd, p):
        return sum(DP.dynamics.kinetic(q[2 * i: 2 * i + 2], qd[2 * i: 2 * i + 2], p)
                   for i in range(count))

    def potential(q, p):
        return sum(DP.dynamics.potential(q[2 * i: 2 * i + 2], p) for i in range(count))

    system = jaxdyn.Lagrangian(kinetic, potential)
    rng = np.random.default_rng(2)
    q, qd = rng.uniform(-2, 2, 2 * count), rng.uniform(-2, 2, 2 * count)
    blocks = mass_matrix_blocks(system, 0.0, q, qd, DP.params)
    assert blocks == [(2 * i, 2 * i + 1) for i in range(count)]
    monkeypatch.setattr(jaxdyn._unroll, "MAX_ELEMENTS", 0)
    accelerations = system.accelerations(0.0, q, qd, DP.params)
    expected = np.concatenate([DP.accelerations(q[2 * i: 2 * i + 2], qd[2 * i: 2 * i + 2],
                                                DP.params) for i in range(count)])
    assert_close(accelerations, expected, rtol=1e-10)


def test_kinetic_energy_independent_of_q_and_no_potential():
    """T = ½ Σ m_i q̇_i² with forces only: no velocity coupling, nothing from V; q̈ = Q/m."""
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(p["m"] * qd**2),
                               forces=lambda q, qd, p: -p["c"] * qd)
    p = {"m": jnp.array([1.0, 2.0, 4.0]), "c": 0.5}
    qd = np.array([1.0, -2.0, 3.0])
    assert_close(system.accelerations(0.0, np.ones(3), qd, p), -0.5 * qd / np.array([1, 2, 4.]),
                 rtol=1e-15)


def test_only_the_outputs_asked_for_are_saved():
    ts = np.linspace(0.0, 1.0, 5)
    args = (DP.dynamics, np.array([0.4, 0.2]), np.zeros(2), DP.params)
    full = jaxdyn.simulate(*args, t1=1.0, ts=ts)
    only_q = jaxdyn.simulate(*args, t1=1.0, ts=ts, save="q")
    assert only_q.u is None and only_q.qd is None
    assert_close(only_q.q, full.q, rtol=0, atol=0)
    with pytest.raises(ValueError, match="save must name some of 'q', 'u', 'qd'"):
        jaxdyn.simulate(*args, t1=1.0, save=("q", "energy"))


def test_python_numbers_keep_the_precision_of_the_state():
    q0, u0 = np.array([0.3], np.float32), np.array([0.0], np.float32)
    sol = jaxdyn.simulate(PENDULUM.dynamics, q0, u0, {"m": 1.0, "l": 0.5, "g": 9.81}, t1=0.5)
    assert sol.q.dtype == np.float32 and sol.ts.dtype == np.float32


def test_a_singular_block_leaves_the_independent_accelerations_finite():
    """Two uncoupled oscillators, one without mass: with throw=False only the massless one's
    acceleration is NaN (the failed pivot reaches the entries that depend on it alone); the
    other is the closed form −(k/m) x. The default check still names the singular M."""
    pair = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * (p["m"][0] * qd[0] ** 2
                                                     + p["m"][1] * qd[1] ** 2),
                             lambda q, p: 0.5 * p["k"] * q @ q)
    p = {"m": np.array([0.0, 2.0]), "k": 3.0}
    q = np.array([0.4, 0.5])
    a = pair.accelerations(0.0, q, np.zeros(2), p, throw=False)
    assert np.isnan(a[0])
    np.testing.assert_allclose(a[1], -3.0 / 2.0 * 0.5, rtol=1e-15)
    with pytest.raises(RuntimeError, match="The mass matrix is singular"):
        pair.accelerations(0.0, q, np.zeros(2), p)


# ---------------------------------------------------------------------------------------------
# Large systems: factored column by column, in the program itself
# ---------------------------------------------------------------------------------------------


def test_a_large_system_matches_numpy_and_its_batched_derivative_calls_no_lapack_kernel():
    """A chain of 20 rods from T and V (its mass matrix factored column by column, above the
    size written out entry by entry): the accelerations of a batch of states equal
    NumPy's solve of Lagrange's equations, M = ∂²T/∂q̇², f = ∂L/∂q − (∂²L/∂q̇∂q) q̇, formed
    here by autodiff; a massless last rod is named singular. The vmapped Jacobian's program
    calls no LAPACK kernel: jaxlib 0.10's batched kernels can deadlock when two run at once
    (a solve and its derivative's), which left a shooting problem's solve hanging."""
    n = 20
    chain = rod_chain()
    p = {"m": np.linspace(1.0, 2.0, n) / n, "l": np.linspace(1.0, 0.5, n) / n, "g": 9.81}
    rng = np.random.default_rng(3)
    qs, qds = rng.uniform(-1.0, 1.0, (3, n)), rng.uniform(-1.0, 1.0, (3, n))

    def accelerations(q, qd):
        return chain.accelerations(0.0, q, qd, p, throw=False)

    got = jax.jit(jax.vmap(accelerations))(qs, qds)

    def lagrangian(q, qd):
        return chain.kinetic(q, qd, p) - chain.potential(q, p)

    @jax.jit
    def lagrange(q, qd):  # M and f of Lagrange's equations, M u̇ = f
        mixed = jax.jacfwd(jax.grad(lagrangian, argnums=1), argnums=0)(q, qd)
        return (jax.hessian(lagrangian, argnums=1)(q, qd),
                jax.grad(lagrangian, argnums=0)(q, qd) - mixed @ qd)

    for q, qd, a in zip(qs, qds, np.asarray(got)):
        mass, forcing = (np.asarray(x) for x in lagrange(q, qd))
        assert_close(a, np.linalg.solve(mass, forcing), rtol=1e-11, atol=1e-11)

    program = jax.jit(jax.vmap(jax.jacfwd(accelerations))).lower(qs, qds).as_text()
    assert "lapack" not in program.lower()
    massless = {**p, "m": np.concatenate([p["m"][:-1], [0.0]])}
    assert np.isnan(np.asarray(chain.accelerations(0.0, qs[0], qds[0], massless,
                                                   throw=False))).all()
    with pytest.raises(RuntimeError, match="The mass matrix is singular"):
        chain.accelerations(0.0, qs[0], qds[0], massless)


@pytest.mark.parametrize("size", [5, 13, 20])
def test_symmetric_solves_match_numpy_and_flag_what_is_not_positive_definite(size):
    """`spd_solve` (written out up to 8, by columns above) against NumPy on a batch of random
    positive definite matrices, with one and several right-hand sides; an indefinite matrix
    and a singular one are flagged; the derivative against a central difference."""
    from jaxdyn._linalg import spd_solve as solve
    spd_solve = jax.jit(solve)  # compiled, as the library calls it (eager, op by op)
    rng = np.random.default_rng(size)
    a = rng.normal(size=(4, size, size))
    h = a @ np.swapaxes(a, 1, 2) + size * np.eye(size)
    b, columns = rng.normal(size=(4, size)), rng.normal(size=(4, size, 3))
    x, positive = spd_solve(jnp.asarray(h), jnp.asarray(b))
    assert_close(x, np.linalg.solve(h, b[..., None])[..., 0], rtol=1e-12, atol=1e-13)
    assert_close(spd_solve(jnp.asarray(h), jnp.asarray(columns))[0],
                 np.linalg.solve(h, columns), rtol=1e-12, atol=1e-13)
    assert np.asarray(positive).all()
    indefinite = np.diag(np.r_[np.ones(size - 1), -1.0])
    singular = np.diag(np.r_[np.ones(size // 2), 0.0, np.ones(size - size // 2 - 1)])
    for bad in (indefinite, singular):
        x, positive = spd_solve(jnp.asarray(bad), jnp.ones(size))
        assert not bool(positive) and np.isnan(np.asarray(x)).any()

    def total(m):
        return jnp.sum(spd_solve(m @ m.T + size * jnp.eye(size), jnp.asarray(b[0]))[0])

    total = jax.jit(total)
    direction = rng.normal(size=(size, size))
    step = 1e-6
    difference = (total(a[0] + step * direction) - total(a[0] - step * direction)) / (2 * step)
    assert_close(jnp.sum(jax.jit(jax.grad(total))(jnp.asarray(a[0])) * direction), difference,
                 rtol=1e-7)


def test_pivoted_lu_solves_match_numpy_and_exchange_rows_where_a_pivot_vanishes():
    """`lu_factor` and `lu_solve` (Gaussian elimination with partial pivoting) against NumPy
    on random square matrices of sizes 1 to 16, A x = b and Aᵀ x = b, one and several
    right-hand sides; a matrix whose leading entry is zero (no LU without an exchange of
    rows); a singular matrix flagged; `PivotedLU` through lineax with its derivative against
    a central difference, and as Newton's solver in optimistix."""
    import lineax as lx
    import optimistix as optx
    from jaxdyn._linalg import PivotedLU
    from jaxdyn._linalg import lu_factor as factor
    from jaxdyn._linalg import lu_solve as solve
    # Compiled, as the library calls them: eager, each step's operations compile apart.
    lu_factor = jax.jit(factor)
    lu_solve = jax.jit(solve, static_argnames="transposed")
    rng = np.random.default_rng(7)
    for size in (1, 2, 3, 8, 16):
        a = rng.normal(size=(3, size, size))
        b, columns = rng.normal(size=(3, size)), rng.normal(size=(3, size, 2))
        lu, order, singular = lu_factor(jnp.asarray(a))
        assert not np.asarray(singular).any()
        assert_close(lu_solve(lu, order, jnp.asarray(b)),
                     np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-10, atol=1e-11)
        assert_close(lu_solve(lu, order, jnp.asarray(b), transposed=True),
                     np.linalg.solve(np.swapaxes(a, 1, 2), b[..., None])[..., 0],
                     rtol=1e-10, atol=1e-11)
        assert_close(lu_solve(lu, order, jnp.asarray(columns)), np.linalg.solve(a, columns),
                     rtol=1e-10, atol=1e-11)
    exchange = np.array([[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]])
    lu, order, singular = lu_factor(jnp.asarray(exchange))
    assert not bool(singular)
    assert_close(lu_solve(lu, order, jnp.array([1.0, 2.0, 3.0])),
                 np.linalg.solve(exchange, [1.0, 2.0, 3.0]), rtol=1e-14, atol=1e-15)
    assert bool(lu_factor(jnp.array([[1.0, 2.0], [2.0, 4.0]]))[2])

    matrix, rhs = rng.normal(size=(4, 4)), rng.normal(size=4)
    solution = lx.linear_solve(lx.MatrixLinearOperator(jnp.asarray(matrix)), jnp.asarray(rhs),
                               PivotedLU())
    assert_close(solution.value, np.linalg.solve(matrix, rhs), rtol=1e-12, atol=1e-13)
    singular_solve = lx.linear_solve(lx.MatrixLinearOperator(jnp.array([[1.0, 2.0], [2.0, 4.0]])),
                                     jnp.ones(2), PivotedLU(), throw=False)
    assert singular_solve.result == lx.RESULTS.singular

    def total(m):
        return jnp.sum(lx.linear_solve(lx.MatrixLinearOperator(m), jnp.asarray(rhs),
                                       PivotedLU()).value)

    direction, step = rng.normal(size=(4, 4)), 1e-6
    difference = (total(matrix + step * direction) - total(matrix - step * direction)) / (2 * step)
    assert_close(jnp.sum(jax.grad(total)(jnp.asarray(matrix)) * direction), difference,
                 rtol=1e-7)

    def circle_and_line(z, _):  # x² + y² = 4 and x = y: (√2, √2) from (1, 0.5)
        return jnp.stack([z[0] ** 2 + z[1] ** 2 - 4.0, z[0] - z[1]])

    found = optx.root_find(circle_and_line,
                           optx.Newton(1e-12, 1e-12, linear_solver=PivotedLU()),
                           jnp.array([1.0, 0.5]))
    assert_close(found.value, [np.sqrt(2.0), np.sqrt(2.0)], rtol=1e-12, atol=1e-12)
