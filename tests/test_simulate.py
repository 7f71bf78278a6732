"""`jaxdyn.simulate` against exact solutions, an independent integrator (SciPy) and
conservation laws."""

import importlib
import json
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import scipy.special

import jaxdyn

from helpers import (
    BEAD_ON_HOOP,
    BEAD_PARAMS,
    DRIVEN_SUPPORT,
    DRIVEN_SUPPORT_PARAMS,
    ELASTIC_PENDULUM,
    HARMONIC_OSCILLATOR,
    PENDULUM,
    assert_close,
    driven_support_acceleration,
)

# ---------------------------------------------------------------------------------------------
# Harmonic oscillator: q = q0 cos ωt + (u0/ω) sin ωt
# ---------------------------------------------------------------------------------------------

HO = HARMONIC_OSCILLATOR.dynamics
HO_PARAMS = HARMONIC_OSCILLATOR.params
HO_T1 = 10.0
HO_TS = np.linspace(0.0, HO_T1, 21)
HO_Q0 = np.array([1.0])
HO_U0 = np.array([0.5])


def _ho_exact(t, q0, u0, p):
    w = np.sqrt(p["k"] / p["m"])
    t = np.asarray(t)[:, None]
    q = q0 * np.cos(w * t) + u0 / w * np.sin(w * t)
    u = -q0 * w * np.sin(w * t) + u0 * np.cos(w * t)
    return q, u


def test_harmonic_oscillator_matches_exact_solution():
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=HO_T1, ts=HO_TS)
    q, u = _ho_exact(HO_TS, HO_Q0, HO_U0, HO_PARAMS)
    assert sol.q.shape == (21, 1) and sol.u.shape == (21, 1) and sol.qd.shape == (21, 1)
    assert_close(sol.ts, HO_TS, rtol=0, atol=0)
    assert_close(sol.q, q, rtol=0, atol=1e-7)
    assert_close(sol.u, u, rtol=0, atol=1e-7)
    # For Lagrange's equations the speeds are the coordinate rates.
    assert_close(sol.qd, sol.u, rtol=0, atol=0)
    assert sol.result == jaxdyn.RESULTS.successful


def test_saving_only_t1_by_default():
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=HO_T1)
    q, u = _ho_exact([HO_T1], HO_Q0, HO_U0, HO_PARAMS)
    assert sol.ts.shape == (1,)
    assert_close(sol.ts, [HO_T1], rtol=0, atol=0)
    assert_close(sol.q, q, rtol=0, atol=1e-7)
    assert_close(sol.u, u, rtol=0, atol=1e-7)


def test_backwards_in_time():
    ts = np.linspace(0.0, -HO_T1, 11)
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=-HO_T1, ts=ts)
    q, u = _ho_exact(ts, HO_Q0, HO_U0, HO_PARAMS)
    assert_close(sol.q, q, rtol=0, atol=1e-7)
    assert_close(sol.u, u, rtol=0, atol=1e-7)


@pytest.mark.parametrize("t0, t1", [(0.7, 6.3), (6.3, 0.7), (3.0, -20.0)])
def test_a_solve_in_scaled_time_takes_the_steps_of_a_solve_in_time(t0, t1):
    """jaxdyn's default solve runs in s = (t − t₀)/(t₁ − t₀) (its compiled program then holds
    diffrax's t₀ and t₁ as constants). An affine change of time leaves the Runge–Kutta
    method and the PID control of its steps unchanged, and the first step is chosen in t:
    so the solve takes the steps of the same solve in t (a step bound in t, `dtmax`, which
    never binds here, keeps the time t), forward and backward, and both match diffrax on
    the hand-derived equations of the driven support (which depend on t)."""
    p = DRIVEN_SUPPORT_PARAMS
    ts = np.linspace(t0, t1, 9)

    def field(t, y, args):  # θ̈ = −(g + ÿ_s)/l sin θ, ÿ_s = −A ω² cos ωt
        ys_ddot = -p["A"] * p["w"] ** 2 * jnp.cos(p["w"] * t)
        return jnp.stack([y[1], -(p["g"] + ys_ddot) / p["l"] * jnp.sin(y[0])])

    def diffrax_solve(tolerance):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(field), diffrax.Dopri8(), t0, t1, None, jnp.array([1.2, -0.4]),
            saveat=diffrax.SaveAt(ts=ts), stepsize_controller=diffrax.PIDController(
                rtol=tolerance, atol=tolerance), max_steps=100_000).ys

    sol = jaxdyn.simulate(DRIVEN_SUPPORT, np.array([1.2]), np.array([-0.4]), p, t0=t0, t1=t1,
                          ts=ts)
    in_t = jaxdyn.simulate(DRIVEN_SUPPORT, np.array([1.2]), np.array([-0.4]), p, t0=t0, t1=t1,
                           ts=ts, stepsize_controller=diffrax.PIDController(
                               rtol=1e-10, atol=1e-10, dtmax=abs(t1 - t0)))
    assert int(sol.num_accepted_steps) == int(in_t.num_accepted_steps)
    assert int(sol.num_rejected_steps) == int(in_t.num_rejected_steps)
    assert_close(sol.ts, ts, rtol=0, atol=0)
    # As accurate as diffrax's solve at the same tolerance, both against a solve at 1e-14.
    # (Not their difference: the equations differ in form, so a step's acceptance can differ
    # by round-off, and the global error of a solve at 1e-10 along the driven motion, 12
    # turns over 23 s, reaches 4.5e-7.)
    exact = np.asarray(diffrax_solve(1e-14))
    theirs = np.max(np.abs(np.asarray(diffrax_solve(1e-10)) - exact), axis=0)
    for solution in (sol, in_t):
        ours = np.max(np.abs(np.stack([solution.q[:, 0], solution.u[:, 0]], axis=1) - exact),
                      axis=0)
        assert np.all(ours <= 2 * theirs + 1e-12), (ours, theirs)


def test_dense_evaluate_matches_exact_solution():
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=HO_T1, ts=HO_TS, dense=True)
    ts = np.random.default_rng(0).uniform(0.0, HO_T1, 9)
    evaluate = jax.jit(jax.vmap(lambda sol, t: sol.evaluate(t), in_axes=(None, 0)))
    q, u = evaluate(sol, ts)
    expected_q, expected_u = _ho_exact(ts, HO_Q0, HO_U0, HO_PARAMS)
    # The interpolant is less accurate than the step endpoints, but still close.
    assert_close(q, expected_q, rtol=0, atol=1e-6)
    assert_close(u, expected_u, rtol=0, atol=1e-6)


def test_vmap_over_parameters():
    ks = np.array([1.0, 2.5, 4.3, 9.0])

    @jax.jit
    def final_states(ks):
        def one(k):
            sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, {"m": HO_PARAMS["m"], "k": k}, t1=HO_T1,
                                  ts=HO_TS)
            return sol.q, sol.u
        return jax.vmap(one)(ks)

    q, u = final_states(ks)
    assert q.shape == (4, 21, 1)
    for i, k in enumerate(ks):
        expected_q, expected_u = _ho_exact(HO_TS, HO_Q0, HO_U0, {"m": HO_PARAMS["m"], "k": k})
        assert_close(q[i], expected_q, rtol=0, atol=1e-7)
        assert_close(u[i], expected_u, rtol=0, atol=1e-7)


def test_vmap_over_initial_states():
    q0s = np.array([[1.0], [-0.4], [2.0]])
    u0s = np.array([[0.5], [1.5], [0.0]])
    simulate = jax.jit(jax.vmap(
        lambda q0, u0: jaxdyn.simulate(HO, q0, u0, HO_PARAMS, t1=HO_T1, ts=HO_TS).q
    ))
    q = simulate(q0s, u0s)
    for i in range(3):
        expected_q, _ = _ho_exact(HO_TS, q0s[i], u0s[i], HO_PARAMS)
        assert_close(q[i], expected_q, rtol=0, atol=1e-7)


def test_solver_statistics_fixed_step():
    """With a constant step the number of steps is known: (t1 − t0)/dt0, none rejected."""
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=2.0, dt0=0.02,
                          stepsize_controller=diffrax.ConstantStepSize())
    assert int(sol.num_steps) == 100
    assert int(sol.num_accepted_steps) == 100
    assert int(sol.num_rejected_steps) == 0
    q, _ = _ho_exact([2.0], HO_Q0, HO_U0, HO_PARAMS)
    assert_close(sol.q, q, rtol=0, atol=1e-8)  # Tsit5 at h = 0.02: error ~ h⁵


def test_solver_statistics_adaptive():
    sol = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=HO_T1, ts=HO_TS)
    num_steps = int(sol.num_steps)
    assert num_steps > 0
    assert int(sol.num_accepted_steps) + int(sol.num_rejected_steps) == num_steps
    assert int(sol.num_accepted_steps) > 0
    # Tighter tolerances need more steps.
    tight = jaxdyn.simulate(HO, HO_Q0, HO_U0, HO_PARAMS, t1=HO_T1, ts=HO_TS, rtol=1e-11,
                            atol=1e-11)
    assert int(tight.num_accepted_steps) > int(sol.num_accepted_steps)


def test_float32_simulation():
    sol = jaxdyn.simulate(HO, HO_Q0.astype(np.float32), HO_U0.astype(np.float32),
                          {"m": np.float32(HO_PARAMS["m"]), "k": np.float32(HO_PARAMS["k"])},
                          t1=HO_T1, ts=HO_TS.astype(np.float32), rtol=1e-6, atol=1e-6)
    for leaf in (sol.ts, sol.q, sol.u, sol.qd):
        assert leaf.dtype == jnp.float32
    q, u = _ho_exact(HO_TS, HO_Q0, HO_U0, HO_PARAMS)
    assert_close(sol.q, q.astype(np.float32), rtol=0, atol=1e-4)
    assert_close(sol.u, u.astype(np.float32), rtol=0, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# Pendulum: energy and period
# ---------------------------------------------------------------------------------------------


def test_pendulum_conserves_energy():
    p = PENDULUM.params
    ts = np.linspace(0.0, 10.0, 101)
    sol = jaxdyn.simulate(PENDULUM.dynamics, np.array([2.5]), np.array([0.0]), p, t1=10.0,
                          ts=ts)
    energy = np.array([PENDULUM.energy(q, u, p) for q, u in zip(np.asarray(sol.q),
                                                                np.asarray(sol.u))])
    scale = p["m"] * p["g"] * p["l"]
    assert np.max(np.abs(energy - energy[0])) < 1e-7 * scale
    # The motion is not trivial: it swings through large angles.
    assert np.max(np.abs(np.asarray(sol.q))) > 2.0 and np.min(np.asarray(sol.q)) < -2.0


def _zero_crossings(sol, t0, t1, num=400):
    """Times where q[0](t) changes sign, located by root finding on the dense interpolant."""
    theta = jax.jit(lambda sol, t: sol.evaluate(t)[0][0])
    grid = np.linspace(t0, t1, num)
    values = np.asarray(jax.jit(jax.vmap(lambda sol, t: sol.evaluate(t)[0][0],
                                         in_axes=(None, 0)))(sol, grid))
    crossings = []
    for i in np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:])):
        crossings.append(scipy.optimize.brentq(lambda t: float(theta(sol, t)), grid[i],
                                               grid[i + 1], xtol=1e-14, rtol=1e-15))
    return np.array(crossings)


def test_pendulum_period():
    """Small swings: 2π √(l/g). Any amplitude θ0: 4 √(l/g) K(sin²(θ0/2)) (complete elliptic
    integral of the first kind, parameter m = k²). Tight solver tolerances: the absolute
    tolerance must be small against the 1e-2 amplitude of the small swing."""
    p = PENDULUM.params
    root = np.sqrt(p["l"] / p["g"])
    t1 = 8.0
    for theta0 in (1e-2, 2.0):
        sol = jaxdyn.simulate(PENDULUM.dynamics, np.array([theta0]), np.array([0.0]), p, t1=t1,
                              dense=True, rtol=1e-12, atol=1e-12)
        crossings = _zero_crossings(sol, 0.0, t1)
        assert len(crossings) >= 4
        # Crossings alternate direction every half period.
        half_periods = np.diff(crossings)
        period = 2 * np.mean(half_periods)
        exact = 4 * root * scipy.special.ellipk(np.sin(theta0 / 2) ** 2)
        assert_close(2 * half_periods, np.full_like(half_periods, exact), rtol=1e-8)
        assert_close(crossings[0], exact / 4, rtol=1e-8)
        if theta0 < 0.1:
            # 2π√(l/g) is the period to O(θ0²): relative correction θ0²/16 ≈ 6e-6.
            assert_close(period, 2 * np.pi * root, rtol=1e-5)
            assert abs(period / (2 * np.pi * root) - 1 - theta0**2 / 16) < 1e-8


# ---------------------------------------------------------------------------------------------
# Dissipation and forcing
# ---------------------------------------------------------------------------------------------


def test_damped_oscillator_rayleigh_dissipation():
    """m q̈ + c q̇ + k q = 0 from D = ½ c q̇², underdamped:
    q = e^{−ζω₀t} (q0 cos ω_d t + (u0 + ζω₀ q0)/ω_d sin ω_d t)."""
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
        lambda q, p: 0.5 * p["k"] * q[0] ** 2,
        dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2,
    )
    p = {"m": 1.5, "k": 20.0, "c": 1.2}
    q0, u0 = 0.8, -0.3
    ts = np.linspace(0.0, 6.0, 31)
    sol = jaxdyn.simulate(system, np.array([q0]), np.array([u0]), p, t1=6.0, ts=ts)
    w0 = np.sqrt(p["k"] / p["m"])
    zeta = p["c"] / (2 * np.sqrt(p["k"] * p["m"]))
    assert zeta < 1
    wd = w0 * np.sqrt(1 - zeta**2)
    b = (u0 + zeta * w0 * q0) / wd
    decay = np.exp(-zeta * w0 * ts)
    q = decay * (q0 * np.cos(wd * ts) + b * np.sin(wd * ts))
    u = -zeta * w0 * q + decay * wd * (-q0 * np.sin(wd * ts) + b * np.cos(wd * ts))
    assert_close(sol.q[:, 0], q, rtol=0, atol=1e-7)
    assert_close(sol.u[:, 0], u, rtol=0, atol=1e-6)
    # The energy dissipated matches the power of the damping force: E decreases.
    energy = np.asarray(system.energy(sol.ts, sol.q, sol.qd, p))
    assert np.all(np.diff(energy) < 0)


DRIVEN_OSCILLATOR = jaxdyn.Lagrangian(
    lambda t, q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
    lambda t, q, p: 0.5 * p["k"] * q[0] ** 2,
    forces=lambda t, q, qd, p: jnp.stack([p["F"] * jnp.cos(p["w"] * t)]),
    time_dependent=True,
)


@pytest.mark.parametrize("t0", [0.0, 2.0])
def test_driven_oscillator_time_dependent_force(t0):
    """m q̈ + k q = F cos ωt (ω ≠ ω₀) from (t0, q0, u0):
    q = a cos ω₀(t − t0) + b sin ω₀(t − t0) + A cos ωt,  A = F / (m (ω₀² − ω²)),
    a = q0 − A cos ωt0,  b = (u0 + A ω sin ωt0) / ω₀. A start at t0 ≠ 0 checks that the
    callbacks see the absolute time."""
    p = {"m": 0.8, "k": 5.0, "F": 1.3, "w": 1.1}
    q0, u0 = 0.2, 0.7
    t1 = t0 + 8.0
    ts = np.linspace(t0, t1, 33)
    sol = jaxdyn.simulate(DRIVEN_OSCILLATOR, np.array([q0]), np.array([u0]), p, t0=t0, t1=t1,
                          ts=ts)
    w0, w = np.sqrt(p["k"] / p["m"]), p["w"]
    A = p["F"] / (p["m"] * (w0**2 - w**2))
    a = q0 - A * np.cos(w * t0)
    b = (u0 + A * w * np.sin(w * t0)) / w0
    s = ts - t0
    q = a * np.cos(w0 * s) + b * np.sin(w0 * s) + A * np.cos(w * ts)
    u = -a * w0 * np.sin(w0 * s) + b * w0 * np.cos(w0 * s) - A * w * np.sin(w * ts)
    assert_close(sol.ts, ts, rtol=0, atol=0)
    assert_close(sol.q[:, 0], q, rtol=0, atol=1e-7)
    assert_close(sol.u[:, 0], u, rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Rheonomic systems
# ---------------------------------------------------------------------------------------------


def test_driven_support_pendulum_matches_scipy():
    """The pendulum on a vertically oscillating support against SciPy's DOP853 on the
    hand-derived θ̈ = −(g + ÿ_s)/l sin θ."""
    p = DRIVEN_SUPPORT_PARAMS
    t1 = 5.0
    ts = np.linspace(0.0, t1, 26)
    theta0, omega0 = 1.0, -0.5

    def rhs(t, y):
        return [y[1], driven_support_acceleration(t, y[0], p)]

    reference = scipy.integrate.solve_ivp(rhs, (0.0, t1), [theta0, omega0], method="DOP853",
                                          t_eval=ts, rtol=1e-11, atol=1e-12)
    assert reference.success
    sol = jaxdyn.simulate(DRIVEN_SUPPORT, np.array([theta0]), np.array([omega0]), p, t1=t1,
                          ts=ts, rtol=1e-10, atol=1e-10)
    assert_close(sol.q[:, 0], reference.y[0], rtol=0, atol=1e-7)
    assert_close(sol.u[:, 0], reference.y[1], rtol=0, atol=1e-7)


def test_bead_on_rotating_hoop_conserves_jacobi_integral():
    """Uniform rotation: h = ½ m R² (θ̇² − Ω² sin²θ) − m g R cos θ is conserved while T + V is
    not (the motor driving the hoop does work)."""
    p = BEAD_PARAMS
    m, R, g, W = p["m"], p["R"], p["g"], p["Omega"]
    ts = np.linspace(0.0, 5.0, 51)
    sol = jaxdyn.simulate(BEAD_ON_HOOP, np.array([0.3]), np.array([1.0]), p, t1=5.0, ts=ts)
    theta, theta_d = np.asarray(sol.q[:, 0]), np.asarray(sol.u[:, 0])
    jacobi = 0.5 * m * R**2 * (theta_d**2 - W**2 * np.sin(theta) ** 2) - m * g * R * np.cos(
        theta
    )
    energy = 0.5 * m * R**2 * (theta_d**2 + W**2 * np.sin(theta) ** 2) - m * g * R * np.cos(
        theta
    )
    scale = m * R**2 * W**2
    assert np.max(np.abs(jacobi - jacobi[0])) < 1e-7 * scale
    assert np.max(np.abs(energy - energy[0])) > 1e-2 * scale


# ---------------------------------------------------------------------------------------------
# Elastic pendulum (25.2)
# ---------------------------------------------------------------------------------------------


def test_elastic_pendulum_conserves_energy():
    p = ELASTIC_PENDULUM.params
    ts = np.linspace(0.0, 6.0, 61)
    q0, u0 = np.array([1.5, 1.0]), np.array([0.3, -0.8])
    sol = jaxdyn.simulate(ELASTIC_PENDULUM.dynamics, q0, u0, p, t1=6.0, ts=ts)
    energy = np.array([ELASTIC_PENDULUM.energy(q, u, p) for q, u in zip(np.asarray(sol.q),
                                                                         np.asarray(sol.u))])
    scale = p["m"] * p["g"] * p["l0"]
    assert np.max(np.abs(energy - energy[0])) < 1e-7 * scale
    # Both degrees of freedom move appreciably (the spring and the swing exchange energy).
    assert np.ptp(np.asarray(sol.q[:, 0])) > 0.1 and np.ptp(np.asarray(sol.q[:, 1])) > 0.5


def test_solution_is_a_pytree_that_can_be_returned_from_jit():
    """`simulate` composes with an outer filter_jit; the result equals the exact solution."""
    run = eqx.filter_jit(lambda q0: jaxdyn.simulate(HO, q0, HO_U0, HO_PARAMS, t1=HO_T1,
                                                    ts=HO_TS))
    sol = run(np.array([-0.7]))
    q, _ = _ho_exact(HO_TS, np.array([-0.7]), HO_U0, HO_PARAMS)
    assert_close(sol.q, q, rtol=0, atol=1e-7)


@pytest.mark.usefixtures("xla_defaults")  # (the stages can be written out there)
@pytest.mark.parametrize("solver", [diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8()],
                         ids=lambda s: type(s).__name__)
def test_written_out_stages_take_diffrax_steps(solver, monkeypatch):
    """simulate writes the Runge–Kutta stages out (no loop over them) at XLA's default
    optimisation where XLA would run diffrax's loop over the stages kernel by kernel (JAX
    started before `import jaxdyn`, or off the CPU), not where it compiles the loop whole
    nor where XLA is asked to compile fast: the steps, their number and the states are
    those of diffrax's own stage loop (`scan_kind="lax"`, which simulate leaves as it is)
    on the same equations, to round-off; and both follow the closed form of the double
    pendulum to the tolerance."""
    from helpers import DOUBLE_PENDULUM
    from jaxdyn._runge_kutta import UnrolledStages

    module = importlib.import_module("jaxdyn._integrate.simulate")  # (the package's name
    # `simulate` is the function)

    # (both settings patched: the process's own depends on XLA_FLAGS and the import order)
    monkeypatch.setattr(module, "LOOPS_RUN_WHOLE", True)
    assert module._stepper(solver, DOUBLE_PENDULUM.dynamics, 183, True, False) is solver
    monkeypatch.setattr(module, "LOOPS_RUN_WHOLE", False)
    assert type(module._stepper(solver, DOUBLE_PENDULUM.dynamics, 183, True, False)) \
        is UnrolledStages
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        assert module._stepper(solver, DOUBLE_PENDULUM.dynamics, 183, True, False) is solver
    finally:
        jax.config.update("jax_disable_most_optimizations", False)
    p = DOUBLE_PENDULUM.params
    q0, u0 = np.array([1.3, -0.4]), np.array([0.2, 0.7])
    ts = np.linspace(0.0, 3.0, 7)
    # At 1e-8 no step's acceptance hinges on round-off of the error estimate (which the two
    # sum in other orders: at 1e-9 Dopri8 takes 124 steps one way, 125 the other).
    options = dict(t1=3.0, ts=ts, rtol=1e-8, atol=1e-8)
    ours = jaxdyn.simulate(DOUBLE_PENDULUM.dynamics, q0, u0, p, solver=solver, **options)
    looped = eqx.tree_at(lambda s: s.scan_kind, solver, "lax", is_leaf=lambda x: x is None)
    theirs = jaxdyn.simulate(DOUBLE_PENDULUM.dynamics, q0, u0, p, solver=looped, **options)
    assert int(ours.num_steps) == int(theirs.num_steps)
    assert int(ours.num_rejected_steps) == int(theirs.num_rejected_steps)
    np.testing.assert_allclose(ours.q, theirs.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours.u, theirs.u, rtol=0, atol=1e-12)
    reference = scipy.integrate.solve_ivp(
        lambda t, y: np.concatenate([y[2:], DOUBLE_PENDULUM.accelerations(y[:2], y[2:], p)]),
        (0.0, 3.0), np.concatenate([q0, u0]), method="DOP853", t_eval=ts, rtol=1e-12,
        atol=1e-12)
    np.testing.assert_allclose(ours.q, reference.y[:2].T, rtol=0, atol=1e-5)


def test_a_repeated_call_reuses_the_compiled_solve():
    """New parameter values, times and tolerances (Python floats), a solver made anew at each
    call and the same shapes as JAX arrays reuse the compiled program: the user's energy is
    traced once; a new `save` or another solver compiles anew."""
    traced = []

    def kinetic(q, qd, p):
        traced.append(1)  # runs only while JAX traces
        return 0.5 * p["m"] * qd @ qd

    oscillator = jaxdyn.Lagrangian(kinetic, lambda q, p: 0.5 * p["k"] * q @ q)
    first = jaxdyn.simulate(oscillator, np.ones(1), np.zeros(1), {"m": 1.0, "k": 4.0}, t1=1.0,
                            solver=diffrax.Tsit5())
    count = len(traced)
    second = jaxdyn.simulate(oscillator, np.ones(1), np.zeros(1), {"m": 1.0, "k": 9.0},
                             t1=0.5, rtol=1e-9, atol=1e-9, solver=diffrax.Tsit5())
    third = jaxdyn.simulate(oscillator, jnp.ones(1), jnp.zeros(1), {"m": 1.0, "k": 1.0},
                            t1=0.5, rtol=1e-9, atol=1e-9, solver=diffrax.Tsit5())
    assert len(traced) == count
    np.testing.assert_allclose(first.q[-1], np.cos(2.0), atol=1e-8)
    np.testing.assert_allclose(second.q[-1], np.cos(1.5), atol=1e-7)
    np.testing.assert_allclose(third.q[-1], np.cos(0.5), atol=1e-7)
    # (q̇ of a Lagrangian is u: the same values, whichever output carries them)
    np.testing.assert_array_equal(third.qd, third.u)
    np.testing.assert_allclose(third.u[-1], -np.sin(0.5), atol=1e-7)
    jaxdyn.simulate(oscillator, np.ones(1), np.zeros(1), {"m": 1.0, "k": 9.0}, t1=0.5,
                    save="q", solver=diffrax.Tsit5())
    assert len(traced) > count
    count = len(traced)
    jaxdyn.simulate(oscillator, np.ones(1), np.zeros(1), {"m": 1.0, "k": 9.0}, t1=0.5,
                    solver=diffrax.Dopri5())
    assert len(traced) > count



def test_a_weakly_typed_parameter_in_a_callers_jit_traces_the_equations_once():
    """A parameter that reaches `simulate` weakly typed (a Python float passed through the
    caller's `jax.jit`) traces the user's energy as often as a strongly typed one: the
    shape check and the solve share one trace of the equations."""
    def counted(m):  # a new system each time: nothing traced before
        traced = []

        def kinetic(q, qd, p):
            traced.append(1)  # runs only while JAX traces
            return 0.5 * p["m"] * qd @ qd

        oscillator = jaxdyn.Lagrangian(kinetic, lambda q, p: 0.5 * q @ q)
        run = jax.jit(lambda m: jaxdyn.simulate(oscillator, np.ones(1), np.zeros(1),
                                                {"m": m}, t1=1.0).q)
        np.testing.assert_allclose(run(m)[-1], np.cos(1.0), atol=1e-8)
        return len(traced)

    assert counted(1.0) == counted(np.float64(1.0)) > 0

def test_programs_called_with_values_are_kept_by_the_persistent_compilation_cache(tmp_path):
    """Called with values, `simulate`, `accelerations`, `linearise`, `normal_modes`,
    `equilibrium` and `fit` compile programs without host callbacks (their checks are read
    on the host, or in a fit's step traced as NaN, which sends the step to its checked
    program), which JAX's persistent compilation cache keeps: a second process compiles
    none of them again. And the first process compiles no tiny program of jaxdyn's own besides them
    (an eager JAX operation on a value at hand, 10-40 ms each: a conversion, a look-up in a
    table); those of diffrax and optimistix are theirs."""
    script = textwrap.dedent(f"""
        import collections, json
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        jax.config.update("jax_compilation_cache_dir", {str(tmp_path)!r})
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        import jaxdyn
        events = collections.Counter()
        jax.monitoring.register_event_listener(lambda e, **k: events.update([e]))
        import logging, traceback
        own = []  # programs compiled for jaxdyn's own code, other than its entry points
        class Compiles(logging.Handler):
            def emit(self, record):
                message = record.getMessage()
                if not message.startswith("Compiling "):
                    return
                name = message.split(" with")[0][len("Compiling "):]
                for frame in reversed(traceback.extract_stack()):
                    if any(f"/{{lib}}/" in frame.filename
                           for lib in ("diffrax", "optimistix", "lineax")):
                        return  # an operation of a library jaxdyn calls
                    if "/jaxdyn/" in frame.filename:
                        if name != "jit(arrays_only)":
                            own.append(f"{{name}} at {{frame.filename}}:{{frame.lineno}}")
                        return
        for logger in ("jax._src.dispatch", "jax._src.interpreters.pxla"):
            logging.getLogger(logger).addHandler(Compiles())
            logging.getLogger(logger).setLevel(logging.DEBUG)
        jax.config.update("jax_log_compiles", True)
        pendulum = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd,
                                     lambda q, p: -p["g"] * jnp.cos(q[0]))
        plant = jaxdyn.Controlled(pendulum, input_map=[0])
        q, u, p = np.array([0.3]), np.zeros(1), {{"g": 9.81}}
        jaxdyn.simulate(pendulum, q, u, p, t1=1.0, ts=np.linspace(0.0, 1.0, 3))
        pendulum.accelerations(0.0, q, u, p)
        jaxdyn.linearise(plant, 0.0, q, u, p)
        jaxdyn.normal_modes(pendulum, 0.0, np.zeros(1), p)
        jaxdyn.equilibrium(plant, q, p, prescribed={{0: 0.3}})
        own_before_fit = list(own)
        ts = np.linspace(0.0, 2.0, 21)
        jaxdyn.fit(pendulum, jaxdyn.Experiment(ts, 0.3 * np.cos(3.1 * ts), q, u), {{"g": 9.0}},
                   progress=False)
        print(json.dumps({{
            "requests": events["/jax/compilation_cache/compile_requests_use_cache"],
            "hits": events["/jax/compilation_cache/cache_hits"],
            "misses": events["/jax/compilation_cache/cache_misses"], "own": own_before_fit}}))
    """)

    def run():
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    first = run()
    assert first["requests"] >= 5 and first["hits"] + first["misses"] == first["requests"], first
    assert first["own"] == [], first["own"]
    second = run()  # (a program with a host callback is asked for, but neither hit nor kept)
    assert second["hits"] == second["requests"] == first["requests"], second
    assert second["misses"] == 0, second


def test_every_diffrax_result_keeps_its_meaning_as_a_jaxdyn_result():
    """A solve's result code, relabelled as jaxdyn's (`promoted`), is the member equinox's own
    promotion gives, for every code diffrax has, also as a traced value."""
    from jaxdyn._solution import promoted

    # (equinox keeps an enumeration's members by name; the test may read that table)
    for name, item in diffrax.RESULTS._name_to_item.items():
        ours, equinox = promoted(item), jaxdyn.RESULTS.promote(item)
        assert ours == equinox and ours == getattr(jaxdyn.RESULTS, name), name
        traced = jax.jit(lambda flag: promoted(diffrax.RESULTS.where(
            flag, item, diffrax.RESULTS.successful))._value)(True)
        assert int(traced) == int(equinox._value), name
        assert jaxdyn.RESULTS[ours] == diffrax.RESULTS[item], name  # the same message
