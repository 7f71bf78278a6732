"""Errors: one test per failure mode, checking the type and the message.

Three tiers (DESIGN.md, habit 6): shapes and signatures → ValueError at trace time;
value-dependent problems (NaN input, singular mass matrix, non-finite forcing) → a runtime error
that names the state; solver failures → a RESULTS member, raised unless throw=False.
"""

import functools
import os
import re
import subprocess
import sys
import textwrap

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import jaxdyn

from helpers import PENDULUM, compiles

PEND = PENDULUM.dynamics
P = PENDULUM.params
Q0 = np.array([0.3])
U0 = np.array([0.0])

SINGULAR = r"^The mass matrix is singular or not positive definite"
BECAME_SINGULAR = (r"^The mass matrix became singular along the motion, though it is positive "
                   r"definite")
NONFINITE = r"^The generalized forcing \(the right-hand side of M a = f\) contains NaN or inf"


def _state_in_message(message):
    """(t, q, u) parsed from the '... It happened at t = ..., q = [...], u = [...].' ending."""
    match = re.search(r"It happened at t = (\S+), q = \[(.*)\], u = \[(.*)\]\.$", message)
    assert match is not None, message
    t = float(match.group(1))
    q = np.array([float(x) for x in match.group(2).split(",")])
    u = np.array([float(x) for x in match.group(3).split(",")])
    return t, q, u


def _kinetic(q, qd, p):
    return 0.5 * p["m"] * qd[0] ** 2


# ---------------------------------------------------------------------------------------------
# Shapes and structure: ValueError at trace time
# ---------------------------------------------------------------------------------------------


def test_q0_not_one_dimensional():
    with pytest.raises(ValueError, match=r"q0 must be a 1-D array of shape \(n,\), got shape "
                                         r"\(1, 1\)"):
        jaxdyn.simulate(PEND, np.array([[0.3]]), U0, P, t1=1.0)


def test_speeds_length_differs_from_coordinates():
    # Today the message comes from the per-state check and calls the speeds "qd"; naming
    # "u0" (as simulate's own shape check intends) would be clearer, so accept either.
    with pytest.raises(ValueError, match=r"(u0|qd).*\(2,\)"):
        jaxdyn.simulate(PEND, Q0, np.array([0.0, 1.0]), P, t1=1.0)


def test_state_length_mismatch_in_a_method():
    with pytest.raises(ValueError, match=r"qd must have shape \(2,\), got shape \(3,\)"):
        PEND.accelerations(0.0, np.zeros(2), np.zeros(3), P)


def test_non_scalar_kinetic_energy():
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd**2)
    with pytest.raises(ValueError, match=r"kinetic energy T must return a scalar, but returned "
                                         r"an array of shape \(1,\)"):
        jaxdyn.simulate(system, Q0, U0, P, t1=1.0)


def test_non_scalar_potential_energy():
    system = jaxdyn.Lagrangian(_kinetic, lambda q, p: 0.5 * q**2)
    with pytest.raises(ValueError, match=r"potential energy V must return a scalar, but "
                                         r"returned an array of shape \(1,\)"):
        jaxdyn.simulate(system, Q0, U0, P, t1=1.0)


def test_non_scalar_dissipation():
    system = jaxdyn.Lagrangian(_kinetic, dissipation=lambda q, qd, p: 0.5 * qd**2)
    with pytest.raises(ValueError, match=r"dissipation function D must return a scalar"):
        system.accelerations(0.0, Q0, U0, P)


def test_integer_energy_is_rejected():
    system = jaxdyn.Lagrangian(lambda q, qd, p: jnp.array(1))
    with pytest.raises(ValueError, match=r"kinetic energy T must return a floating-point "
                                         r"scalar, got dtype int"):
        system.mass_matrix(0.0, Q0, U0, P)


def test_wrong_shape_of_generalized_forces():
    system = jaxdyn.Lagrangian(_kinetic, forces=lambda q, qd, p: jnp.zeros(2))
    with pytest.raises(ValueError, match=r"generalized forces Q must return an array of shape "
                                         r"\(1,\), got shape \(2,\)"):
        jaxdyn.simulate(system, Q0, U0, P, t1=1.0)


def test_scalar_generalized_force_is_rejected():
    system = jaxdyn.Lagrangian(_kinetic, forces=lambda q, qd, p: -qd[0])
    with pytest.raises(ValueError, match=r"generalized forces Q must return an array of shape "
                                         r"\(1,\), got shape \(\)"):
        system.accelerations(0.0, Q0, U0, P)


def test_callback_without_t_but_declared_time_dependent():
    system = jaxdyn.Lagrangian(_kinetic, time_dependent=True)
    with pytest.raises(ValueError, match=r"kinetic energy T is called as T\(t, q, qd, p\) "
                                         r"\(time_dependent=True\).*pass time_dependent=False"):
        jaxdyn.simulate(system, Q0, U0, P, t1=1.0)


def test_callback_with_t_but_declared_autonomous():
    system = jaxdyn.Lagrangian(_kinetic, lambda t, q, p: 0.5 * q[0] ** 2)
    with pytest.raises(ValueError, match=r"potential energy V is called as V\(q, p\) "
                                         r"\(time_dependent=False\).*pass time_dependent=True"):
        jaxdyn.simulate(system, Q0, U0, P, t1=1.0)


def test_dynamics_of_the_wrong_type():
    with pytest.raises(ValueError, match=r"dynamics must be a jaxdyn.AbstractDynamics"):
        jaxdyn.simulate(lambda t, y, args: y, Q0, U0, P, t1=1.0)


def test_q0_and_u0_of_different_dtypes():
    with pytest.raises(ValueError, match=r"q0 and u0 must share a dtype, got float32 and "
                                         r"float64"):
        jaxdyn.simulate(PEND, Q0.astype(np.float32), U0, P, t1=1.0)


def test_save_times_not_one_dimensional():
    with pytest.raises(ValueError, match=r"ts must be a 1-D array of save times, got shape "
                                         r"\(2, 2\)"):
        jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, ts=np.zeros((2, 2)))


def test_complex_state_is_rejected():
    with pytest.raises(ValueError, match=r"q must be a real floating-point array, got dtype "
                                         r"complex128"):
        PEND.accelerations(0.0, np.array([0.3 + 0.0j]), U0, P)


def test_evaluate_needs_dense_output():
    sol = jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0)
    with pytest.raises(ValueError, match=r"evaluate needs a dense solution: call "
                                         r"simulate\(\.\.\., dense=True\)"):
        sol.evaluate(0.5)


def test_method_called_with_too_many_arguments():
    with pytest.raises(TypeError, match=r"accelerations takes \(t, q, qd, p=None\), got 5 "
                                        r"positional arguments"):
        PEND.accelerations(0.0, Q0, U0, P, P)


# ---------------------------------------------------------------------------------------------
# Non-finite inputs
# ---------------------------------------------------------------------------------------------


def test_nan_in_q0():
    with pytest.raises(RuntimeError, match=r"q0 contains NaN or inf"):
        jaxdyn.simulate(PEND, np.array([np.nan]), U0, P, t1=1.0)


def test_inf_in_u0():
    with pytest.raises(RuntimeError, match=r"u0 contains NaN or inf"):
        jaxdyn.simulate(PEND, Q0, np.array([np.inf]), P, t1=1.0)


def test_under_a_callers_vmap_the_checked_parameters_stay_shared_and_a_nan_still_raises():
    """`simulate` checks its inputs inside a caller's `jax.jit(jax.vmap(...))`: values shared
    by the batch come back shared (tied to the check's batched flag, a robot's parameters
    became one copy per member, streamed through every step of the solve: twice the run and
    compile time of ANYmal's vmapped drop in contact), and a member starting at NaN still
    raises, naming it."""
    from jaxdyn._errors import check_finite

    qs = jnp.array([[0.3], [0.4]])
    p = {name: jnp.asarray(value) for name, value in P.items()}
    shared = jax.vmap(lambda q: check_finite(q0=q, p=p)[1], out_axes=None)(qs)  # (unbatched)
    assert all(float(shared[name]) == float(p[name]) for name in p)
    batch = jax.jit(jax.vmap(lambda q: jaxdyn.simulate(PEND, q, U0, P, t1=0.2).q[-1]))
    np.testing.assert_allclose(batch(qs)[:, 0], [jaxdyn.simulate(PEND, q, U0, P, t1=0.2).q[-1, 0]
                                                 for q in qs], rtol=1e-12)
    with pytest.raises(Exception, match=r"q0 contains NaN or inf"):
        jax.block_until_ready(batch(jnp.array([[0.3], [jnp.nan]])))


def test_nan_in_a_parameter_names_the_leaf():
    system = jaxdyn.Lagrangian(_kinetic, lambda q, p: 0.5 * p["k"] * q[0] ** 2)
    with pytest.raises(RuntimeError, match=r"p\['k'\] contains NaN or inf"):
        jaxdyn.simulate(system, Q0, U0, {"m": 1.0, "k": np.nan}, t1=1.0)


def test_nan_in_a_nested_parameter_names_the_path():
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * p["body"]["m"] * qd[0] ** 2,
        lambda q, p: 0.5 * p["spring"]["k"] * q[0] ** 2,
    )
    p = {"body": {"m": 1.0}, "spring": {"k": np.array(np.inf)}}
    with pytest.raises(RuntimeError, match=r"p\['spring'\]\['k'\] contains NaN or inf"):
        jaxdyn.simulate(system, Q0, U0, p, t1=1.0)


# ---------------------------------------------------------------------------------------------
# Singular or indefinite mass matrix, non-finite forcing: errors naming the state
# ---------------------------------------------------------------------------------------------


def test_singular_mass_matrix_at_the_initial_state():
    with pytest.raises(RuntimeError, match=SINGULAR) as info:
        jaxdyn.simulate(PEND, Q0, U0, {**P, "m": 0.0}, t1=1.0)
    message = str(info.value)
    assert message.endswith("It happened at t = 0.0, q = [0.3], u = [0.0].")
    assert "a coordinate carries no inertia" in message  # a troubleshooting paragraph


def test_mass_matrix_not_positive_definite():
    with pytest.raises(RuntimeError, match=SINGULAR) as info:
        jaxdyn.simulate(PEND, Q0, U0, {**P, "m": -1.0}, t1=1.0)
    assert str(info.value).endswith("It happened at t = 0.0, q = [0.3], u = [0.0].")


def test_mass_matrix_becomes_singular_during_the_solve_polar_coordinates():
    """A free particle in polar coordinates aimed at the origin: M = diag(m, m r²) is singular
    at r = 0, reached at t = 1 (fixed steps of 0.25 land exactly there)."""
    polar = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2))
    with pytest.raises(RuntimeError, match=BECAME_SINGULAR) as info:
        jaxdyn.simulate(polar, np.array([1.0, 0.0]), np.array([-1.0, 0.0]), {"m": 1.0}, t1=2.0,
                        dt0=0.25, stepsize_controller=diffrax.ConstantStepSize())
    t, q, u = _state_in_message(str(info.value))
    assert t == 1.0
    np.testing.assert_allclose(q, [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(u, [-1.0, 0.0])


def test_mass_matrix_loses_definiteness_during_an_adaptive_solve():
    """T = ½ q̇1² + ½ (a − q1) q̇2² with q̇1 = 1, q̇2 = 0: the motion is q1 = t exactly, and M22
    = a − q1 turns negative once t > a. The error names a time just past a and that state."""
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * qd[0] ** 2 + 0.5 * (p["a"] - q[0]) * qd[1] ** 2
    )
    with pytest.raises(RuntimeError, match=BECAME_SINGULAR) as info:
        jaxdyn.simulate(system, np.array([0.0, 0.0]), np.array([1.0, 0.0]), {"a": 1.0}, t1=3.0)
    t, q, u = _state_in_message(str(info.value))
    assert 1.0 - 1e-12 <= t < 3.0
    np.testing.assert_allclose(q, [t, 0.0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(u, [1.0, 0.0], rtol=1e-12, atol=1e-12)


def test_a_failure_under_an_uncompiled_gradient_is_diagnosed():
    """Under an un-jitted `jax.grad` the solve runs its lean program (the values are known);
    a failure then runs the full program, whose message names the state as in a plain call."""
    polar = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2))

    def loss(r0):
        return jaxdyn.simulate(polar, jnp.stack([r0, 0.0]), np.array([-1.0, 0.0]), {"m": 1.0},
                               t1=2.0, dt0=0.25,
                               stepsize_controller=diffrax.ConstantStepSize()).q[-1, 0]

    with pytest.raises(RuntimeError, match=BECAME_SINGULAR) as info:
        jax.grad(loss)(1.0)
    assert _state_in_message(str(info.value))[0] == 1.0


def test_singular_mass_matrix_plain_call_names_the_state():
    with pytest.raises(RuntimeError, match=SINGULAR) as info:
        PEND.accelerations(0.5, Q0, np.array([2.0]), {**P, "m": 0.0})
    assert str(info.value).endswith("It happened at t = 0.5, q = [0.3], u = [2.0].")


def test_singular_mass_matrix_in_a_batch_names_the_failing_state():
    polar = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2))
    ts = np.array([0.0, 1.0, 2.0])
    qs = np.array([[1.0, 0.0], [0.0, 0.5], [2.0, 1.0]])  # the second is at r = 0
    with pytest.raises(RuntimeError, match=SINGULAR) as info:
        polar.accelerations(ts, qs, np.ones((3, 2)), {"m": 1.0})
    assert str(info.value).endswith("It happened at t = 1.0, q = [0.0, 0.5], u = [1.0, 1.0].")


def test_inside_a_callers_jit_a_singular_state_is_nan_without_a_branch_and_diagnosed_after(
        capfd):
    """The default check costs nothing inside the caller's own trace: no host callback in
    the program (so XLA may compile a loop around it as one function), NaN where M is
    singular; `diagnose` then names the cause and the state. `throw=True` keeps the check
    inside the trace. A failure raised on purpose leaves no traceback on stderr."""
    def call(m, **options):
        return PEND.accelerations(0.5, jnp.array([0.3]), jnp.array([2.0]), {**P, "m": m},
                                  **options)

    assert "callback" not in str(jax.make_jaxpr(call)(1.0))
    assert "callback" in str(jax.make_jaxpr(functools.partial(call, throw=True))(1.0))
    in_loop = jax.jit(call)
    np.testing.assert_allclose(in_loop(1.0), [-P["g"] / P["l"] * np.sin(0.3)], rtol=1e-14)
    assert np.isnan(in_loop(0.0)).all()
    message = PEND.diagnose(0.5, np.array([0.3]), np.array([2.0]), {**P, "m": 0.0})
    assert re.match(SINGULAR, message)
    assert message.endswith("It happened at t = 0.5, q = [0.3], u = [2.0].")
    assert PEND.diagnose(0.5, np.array([0.3]), np.array([2.0]), P) is None
    with pytest.raises(Exception, match="The mass matrix is singular"):
        jax.block_until_ready(jax.jit(functools.partial(call, throw=True))(0.0))
    with pytest.raises(ValueError, match="diagnose reads the values"):
        jax.jit(lambda m: PEND.diagnose(0.5, Q0, U0, {**P, "m": m}))(1.0)
    assert "Traceback" not in capfd.readouterr().err


def test_a_checked_call_with_values_compiles_once_and_again_only_on_failure():
    """Called with values, `accelerations` reads one finite flag on the host; a new state of
    the same shapes compiles nothing, and only a failure compiles the checked program that
    names it."""
    state = (np.array([0.3]), np.array([0.0]))
    PEND.accelerations(0.0, *state, P)
    with compiles() as count:
        for q in (0.1, 0.2, 0.4):
            PEND.accelerations(0.0, np.array([q]), state[1], P)
    assert count() == 0
    with pytest.raises(RuntimeError, match=SINGULAR):
        PEND.accelerations(0.0, *state, {**P, "m": 0.0})


def test_nonfinite_forcing_plain_call():
    """An inverse-square force Q = k / q² evaluated at q = 0."""
    system = jaxdyn.Lagrangian(_kinetic, forces=lambda q, qd, p: p["k"] / q**2)
    with pytest.raises(RuntimeError, match=NONFINITE) as info:
        system.accelerations(0.0, np.array([0.0]), np.array([1.0]), {"m": 1.0, "k": 1.0})
    assert str(info.value).endswith("It happened at t = 0.0, q = [0.0], u = [1.0].")


def test_nonfinite_forcing_during_the_solve():
    """Q2 = −sqrt(a − q1) with q1 = t: NaN once the solver evaluates past t = a."""
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * qd[0] ** 2 + 0.5 * qd[1] ** 2,
        forces=lambda q, qd, p: jnp.stack([jnp.zeros_like(q[0]), -jnp.sqrt(p["a"] - q[0])]),
    )
    with pytest.raises(RuntimeError, match=NONFINITE) as info:
        jaxdyn.simulate(system, np.array([0.0, 0.0]), np.array([1.0, 0.0]), {"a": 1.0}, t1=3.0)
    t, q, _ = _state_in_message(str(info.value))
    assert 1.0 - 1e-12 < t < 3.0
    np.testing.assert_allclose(q[0], t, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Solver failures
# ---------------------------------------------------------------------------------------------


def test_max_steps_reached_raises():
    with pytest.raises(RuntimeError, match=r"The solver took the maximum number of steps "
                                           r"\(max_steps\) before reaching t1"):
        jaxdyn.simulate(PEND, Q0, U0, P, t1=10.0, max_steps=5)


@pytest.mark.parametrize("read", ["q", "u", "qd", "ts", "dense"])
def test_a_failed_solve_raises_in_a_callers_jit_whichever_output_is_read(read):
    """Inside a caller's `jax.jit`, XLA keeps only what the outputs read: each output the
    caller may read alone (here the states, their rates, the times, the dense solution) is
    tied to the failure check, so a solve that ran out of steps raises rather than returning
    the last state it reached as if it were t1's."""
    save = ("q", "u", "qd")

    def run(q0):
        sol = jaxdyn.simulate(PEND, q0, U0, P, t1=10.0, max_steps=5, save=save,
                              dense=read == "dense")
        return sol.evaluate(np.float64(10.0))[0] if read == "dense" else getattr(sol, read)[-1]

    with pytest.raises(Exception, match=r"The solver took the maximum number of steps"):
        jax.block_until_ready(jax.jit(run)(Q0))


def test_max_steps_reached_without_throw_returns_the_result():
    sol = jaxdyn.simulate(PEND, Q0, U0, P, t1=10.0, max_steps=5, throw=False)
    assert sol.result != jaxdyn.RESULTS.successful
    assert sol.result == jaxdyn.RESULTS.max_steps_reached
    assert int(sol.num_steps) == 5


# ---------------------------------------------------------------------------------------------
# Out-of-bounds indexing in a callback
# ---------------------------------------------------------------------------------------------


def test_callback_indexing_past_the_coordinates_is_an_error():
    """T reads qd[1] but the system is simulated with one coordinate (a typo or a wrong q0).

    JAX clamps out-of-range static indices, so qd[1] silently reads qd[0]: T becomes q̇0²,
    `mass_matrix` returns [[2.]] instead of raising, and `simulate` returns a wrong motion
    with `result == RESULTS.successful`.
    Shape problems in callbacks should be a ValueError at trace time (DESIGN.md, habit 6),
    like the non-scalar-energy and wrong-Q-shape errors above.
    """
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2 + 0.5 * qd[1] ** 2)
    with pytest.raises((ValueError, IndexError), match=r"(?i)index|bounds|shape"):
        jaxdyn.simulate(system, Q0, np.array([1.0]), None, t1=1.0)



@pytest.mark.parametrize("callback", ["forces", "dissipation"])
def test_forces_or_dissipation_indexing_past_the_speeds_is_an_error(callback):
    """Q or D reading qd[1] of a system of one coordinate: the clamped read would damp or
    drive the motion with q̇0 and return a plausible, wrong motion. The check evaluates the
    user's Q and D themselves (no derivative of D is formed for it)."""
    bad = {"forces": dict(forces=lambda q, qd, p: -0.1 * qd[1] * qd),
           "dissipation": dict(dissipation=lambda q, qd, p: 0.05 * qd[1] ** 2)}[callback]
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.5 * q @ q, **bad)
    with pytest.raises(ValueError, match="indexes past the end"):
        jaxdyn.simulate(system, Q0, np.array([1.0]), None, t1=1.0)
    with pytest.raises(ValueError, match="indexes past the end"):
        system.accelerations(0.0, Q0, np.array([1.0]))


def test_an_eliminated_systems_callbacks_are_checked_without_solving_for_its_speeds():
    """A system reduced to its independent speeds (`Constrained.eliminate`) whose force reads
    qd[2] of two speeds is named. The check evaluates the user's callbacks at speeds of the
    right shape, without the Jacobian and solve that give the dependent speeds: through them,
    the solve's own indexing depended on traced values, which turned the whole check off
    (the read went unnoticed), and compile-time evaluation compiled each of their operations
    apart (2.5 s at the slider-crank's first call)."""
    system = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.5 * q @ q,
                          forces=lambda q, qd, p: -0.1 * qd[2] * qd),
        holonomic=lambda q, p: jnp.stack([q[0] - 2.0 * q[1]]))
    q0, u0 = np.array([0.2, 0.1]), np.array([0.2, 0.1])
    reduced = system.eliminate(0.0, q0, u0)
    with pytest.raises(ValueError, match="indexes past the end"):
        reduced.accelerations(0.0, q0, u0[:1])
    program = str(jax.make_jaxpr(reduced.user_functions)(0.0, q0, u0[:1]))
    assert "= mul" in program  # the force's product, evaluated
    solves = re.findall(r"= (lu|triangular_solve|custom_linear_solve|cholesky)\b", program)
    assert not solves, solves


def test_a_links_value_indexing_past_its_parameter_is_an_error():
    """A tree's link whose mass is a function of p reading p["m"][2] of a 2-vector: the
    clamped read would give the second mass to this link; the tree's checks of the user's
    callables name it, while the library's own lookups of a URDF tree's parameters are not
    evaluated for the check."""
    tree = jaxdyn.RigidBodyTree([jaxdyn.Link("arm", jaxdyn.Revolute((0, 0, 1)),
                                             mass=lambda p: p["m"][2], com=(0.3, 0.0, 0.0),
                                             inertia=0.01 * jnp.eye(3))],
                                gravity=jnp.array([0.0, -9.81, 0.0]))
    p = {"m": jnp.array([1.0, 2.0])}
    with pytest.raises(ValueError, match="indexes past the end"):
        jaxdyn.ArticulatedBody(tree).accelerations(0.0, jnp.zeros(1), jnp.zeros(1), p)
    with pytest.raises(ValueError, match="indexes past the end"):
        jaxdyn.simulate(jaxdyn.ArticulatedBody(tree), jnp.zeros(1), jnp.zeros(1), p, t1=0.1)


def _gathers(q, qd, p):  # reads with static indices of every form, all within bounds
    table = jnp.arange(12.0).reshape(3, 4)
    # (integer division and remainder as jnp forms them from XLA's: −7 // 2 = −4, which
    # reads the first of 4; −7 % 4 = 1)
    rounded = jnp.arange(4)[jnp.array(-7) // 2] + jnp.arange(4)[jnp.array(-7) % 4]
    return (q[-1], qd[1:3], table[2, q.shape[0]], table[jnp.array([0, 2])], rounded,
            jax.lax.dynamic_slice(table, (1, 2), (2, 2)), table.at[1, 5].get(mode="clip"))


@pytest.mark.parametrize("index", [0, 1, 2, -1, -2, -3])
def test_the_index_check_under_a_trace_agrees_with_checkify_run_on_values(index):
    """Under a trace the index check is decided in NumPy from the checked callbacks' jaxpr;
    called with values, JAX runs the same checks (`checkify`) as a program. Both give the
    same verdict and message for static reads in and out of bounds, negative, gathered and
    sliced (the reference: JAX's own evaluation)."""
    from jaxdyn._static_indexing import _checked_jit, _error_from_constants

    def fn(q, qd, p):
        return q[index], _gathers(q, qd, p)

    q, qd = jnp.array([0.3, 0.4]), jnp.array([0.1, -0.2])
    expected = _checked_jit(fn, (q, qd, None)).get()
    messages = []
    jax.jit(lambda q, qd: messages.append(
        _error_from_constants(fn, (q, qd, None)).get()))(q, qd)
    assert messages == [expected]
    assert (expected is None) == (-2 <= index <= 1)


def test_constants_in_the_callbacks_are_not_compiled_one_by_one_at_a_first_call(monkeypatch):
    """A Lagrangian whose T and V build constant arrays (a rotation of constants, an offset
    vector), as users write them: the index check, traced with the first solve, compiled
    each constant operation as a program of its own (20 programs here, 51 for a free body
    in quaternions); now the first `simulate` compiles its solve alone."""
    def system():  # new functions at each call: a system traced and compiled anew
        def kinetic(q, qd, p):
            axes = jnp.array([[0.0, -1.0], [1.0, 0.0]]) @ jnp.diag(jnp.array([2.0, 3.0]))
            return 0.5 * qd @ (axes.T @ axes + jnp.eye(2)) @ qd

        def potential(q, p):
            offset = jnp.linspace(0.0, 1.0, 2) * jnp.array([1.5, -0.5]) + 0.25
            return 0.5 * jnp.sum((q - offset) ** 2) + jnp.cos(jnp.array([0.1, 0.2])) @ q

        return jaxdyn.Lagrangian(kinetic, potential)

    simulate_module = sys.modules["jaxdyn._integrate.simulate"]
    # The process's own first programs (diffrax's result code, a cosine of constants folded
    # by XLA's kernel) compiled by a first solve of the same equations without the check:
    monkeypatch.setattr(simulate_module, "check_static_indexing", lambda *args: None)
    q0, u0 = np.array([0.3, -0.2]), np.zeros(2)
    jaxdyn.simulate(system(), q0, u0, None, t1=0.2)
    monkeypatch.undo()
    with compiles() as count:
        jaxdyn.simulate(system(), q0, u0, None, t1=0.2)
    assert count() == 1, count()


# ---------------------------------------------------------------------------------------------
# Hostile arguments of simulate: tolerances, save times, step budget, parameters, callbacks
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rtol, atol, message", [
    (0.0, 0.0, r"^rtol and atol are both 0"),
    (-1e-6, 1e-6, r"^rtol must be finite and ≥ 0, got -1e-06"),
    (1e-6, float("nan"), r"^atol must be finite and ≥ 0, got nan"),
    (float("inf"), 1e-6, r"^rtol must be finite and ≥ 0"),
])
def test_bad_tolerances_are_named(rtol, atol, message):
    with pytest.raises(ValueError, match=message):
        jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, rtol=rtol, atol=atol)


def test_traced_bad_tolerances_are_named_before_the_solve():
    """Under jit the tolerances are values: the check runs in the compiled solve."""
    run = jax.jit(lambda tol: jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, rtol=tol, atol=tol).q)
    with pytest.raises(Exception, match="rtol and atol must be finite and ≥ 0, and not both 0"):
        jax.block_until_ready(run(0.0))
    np.testing.assert_allclose(run(1e-8), jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0).q, atol=1e-7)


@pytest.mark.parametrize("t1, ts, message", [
    (1.0, [0.5, 1.5], r"^ts must lie within the interval from t0 to t1"),
    (1.0, [-0.1, 0.5], r"^ts must lie within the interval from t0 to t1"),
    (-1.0, [-0.2, -0.5, -2.0], r"^ts must lie within the interval from t0 to t1"),
    (-1.0, [-1.0, -0.5], r"^ts must run in the direction of integration"),
    (1.0, [0.5, 0.2], r"^ts must run in the direction of integration"),
    (1.0, [0.5, float("nan")], r"^ts contains NaN or inf"),
])
def test_bad_save_times_are_named(t1, ts, message):
    with pytest.raises(RuntimeError, match=message) as info:
        jaxdyn.simulate(PEND, Q0, U0, P, t1=t1, ts=np.array(ts))
    assert "It happened at t0 = 0.0, t1 = " in str(info.value)


def test_backward_save_times_are_accepted():
    ts = np.array([0.0, -0.5, -1.0])
    sol = jaxdyn.simulate(PEND, Q0, U0, P, t1=-1.0, ts=ts)
    forward = jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, ts=-ts)  # the pendulum is reversible
    np.testing.assert_allclose(sol.q, forward.q, atol=1e-9)


def test_empty_save_times_and_bad_step_budgets():
    with pytest.raises(ValueError, match="ts is empty"):
        jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, ts=np.array([]))
    for bad in (0, -5, 10.5):
        with pytest.raises(ValueError, match="max_steps must be a positive int"):
            jaxdyn.simulate(PEND, Q0, U0, P, t1=1.0, max_steps=bad)


def test_max_steps_error_estimates_the_steps_needed():
    """The estimate scales the steps taken to the whole interval: within a factor of two of
    what the solve then takes (the pendulum's steps are uniform over its periods)."""
    with pytest.raises(RuntimeError, match=r"^The solver took the maximum number of steps") as e:
        jaxdyn.simulate(PEND, Q0, U0, P, t1=100.0, max_steps=50)
    estimate = float(re.search(r"steps the whole interval needs \(estimate\) = (\S+?),",
                               str(e.value)).group(1))
    taken = int(jaxdyn.simulate(PEND, Q0, U0, P, t1=100.0, max_steps=10_000).num_steps)
    assert taken / 2 < estimate < 2 * taken


def test_mixed_precision_and_complex_parameters_are_rejected():
    mixed = r"^p\['m'\] has dtype float64 but the state is float32: mixed precision"
    q32, u32 = Q0.astype(np.float32), U0.astype(np.float32)
    with pytest.raises(ValueError, match=mixed):
        jaxdyn.simulate(PEND, q32, u32, {**P, "m": np.array(1.0, np.float64)}, t1=1.0)
    with pytest.raises(ValueError, match=mixed):  # the methods on states too
        PEND.accelerations(0.0, q32, u32, {**P, "m": np.array(1.0, np.float64)})
    with pytest.raises(ValueError, match=r"p\['m'\] is complex"):
        jaxdyn.simulate(PEND, Q0, U0, {**P, "m": np.array(1.0, np.complex128)}, t1=1.0)


def test_a_missing_parameter_is_named():
    with pytest.raises(ValueError, match=r"raised KeyError: 'm'(.|\n)*Is a parameter missing "
                                         r"from p\? It has keys \['g', 'l'\]"):
        jaxdyn.simulate(PEND, Q0, U0, {"g": 9.81, "l": 1.0}, t1=1.0)


def test_a_callback_that_raises_is_named():
    def potential(q, p):
        raise ZeroDivisionError("division by zero")

    system = jaxdyn.Lagrangian(_kinetic, potential)
    with pytest.raises(ValueError, match=r"^Potential energy V, called as V\(q, p\) with q of "
                                         r"shape \(1,\), raised ZeroDivisionError"):
        jaxdyn.simulate(system, Q0, U0, {"m": 1.0}, t1=1.0)


def test_a_python_branch_on_traced_values_gets_a_hint():
    system = jaxdyn.Lagrangian(_kinetic, lambda q, p: q[0] if q[0] > 0 else -q[0])
    with pytest.raises(ValueError, match=r"jnp.where or jax.lax.cond"):
        jaxdyn.simulate(system, Q0, U0, {"m": 1.0}, t1=1.0)


# Property-based: whatever tolerances or save times a user passes, simulate either solves or
# answers with jaxdyn's own message, never a crash inside JAX or a silent NaN.

_NUMBERS = st.one_of(st.floats(-1.0, 1.0), st.sampled_from([0.0, -0.0, 1e-300, float("nan"),
                                                              float("inf"), -float("inf")]))


@settings(max_examples=25, deadline=None, derandomize=True)
@given(rtol=_NUMBERS, atol=_NUMBERS)
def test_any_tolerances_solve_or_are_named(rtol, atol):
    valid = (np.isfinite(rtol) and np.isfinite(atol) and rtol >= 0 and atol >= 0
             and rtol + atol > 0)
    if valid:
        rtol, atol = max(rtol, 1e-12), max(atol, 1e-12)  # far below this is a budget question
        sol = jaxdyn.simulate(PEND, Q0, U0, P, t1=0.5, rtol=rtol, atol=atol, max_steps=100_000)
        assert np.all(np.isfinite(sol.q))
    else:
        with pytest.raises(ValueError, match=r"^(rtol|atol)"):
            jaxdyn.simulate(PEND, Q0, U0, P, t1=0.5, rtol=rtol, atol=atol)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(ts=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3), backwards=st.booleans())
def test_any_save_times_solve_or_are_named(ts, backwards):
    t1 = -1.0 if backwards else 1.0
    ts = np.array(ts)
    direction = np.sign(t1)
    inside = np.all(ts * direction >= 0) and np.all(ts * direction <= 1.0)
    ordered = np.all(np.diff(ts) * direction >= 0)
    if inside and ordered:
        sol = jaxdyn.simulate(PEND, Q0, U0, P, t1=t1, ts=ts)
        reference = PENDULUM_BY_SCIPY(ts)
        np.testing.assert_allclose(sol.q[:, 0], reference, atol=1e-8)
    else:
        with pytest.raises(RuntimeError, match=r"^ts must"):
            jaxdyn.simulate(PEND, Q0, U0, P, t1=t1, ts=ts)


def PENDULUM_BY_SCIPY(ts):
    """θ(t) of the pendulum from (Q0, U0), by SciPy's DOP853 on θ̈ = −(g/l) sin θ."""
    import scipy.integrate

    g, length = P["g"], P["l"]
    order = np.argsort(np.abs(ts))
    end = ts[order][-1]
    if end == 0.0:
        return np.full(len(ts), Q0[0])
    solution = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], -g / length * np.sin(y[0])], (0.0, end), [Q0[0], U0[0]],
        method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True)
    return solution.sol(ts)[0]


def test_import_chooses_xla_cpu_code_generators_or_says_it_could_not():
    """`import jaxdyn` turns XLA's CPU fusion emitters off (on the straight-line programs of
    small systems they generate code up to thousands of times slower) and YNNPACK fusions (on
    the small batched block products of a tree's recursions several times slower), lets XLA
    compile loops of up to a megabyte per iteration as one function, keeps a user's own
    choice of any of them, and warns, naming the switches, when JAX started before jaxdyn was
    imported. The import itself computes nothing: JAX's backend is not started, and no
    program compiled, until the user's first computation."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    loops = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000"
    ours = f"--xla_cpu_use_fusion_emitters=false --xla_cpu_experimental_ynn_fusion_type= {loops}"
    scripts = {
        "first": ("import os, jaxdyn, jax.numpy as jnp; jnp.ones(1); "
                  "print(os.environ['XLA_FLAGS'])", {}),
        "chosen": ("import os, jaxdyn, jax._src.xla_bridge as xb; "
                   "print(os.environ['XLA_FLAGS']); print(xb.backends_are_initialized())",
                   {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}),
        "both chosen": ("import os, jaxdyn; print(os.environ['XLA_FLAGS'])",
                        {"XLA_FLAGS": "--xla_cpu_experimental_ynn_fusion_type=dot "
                                      "--xla_cpu_use_fusion_emitters=true"}),
        "late": ("import jax.numpy as jnp; jnp.ones(1); import jaxdyn", {}),
    }
    running = {name: subprocess.Popen([sys.executable, "-W", "error", "-c", code],
                                      env={**env, **extra}, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True)
               for name, (code, extra) in scripts.items()}
    done = {name: (process.wait(), *process.communicate()) for name, process in running.items()}
    assert done["first"][0] == 0, done["first"][2]
    assert done["first"][1].strip() == ours
    flags, started = done["chosen"][1].strip().splitlines()
    assert flags == ("--xla_cpu_use_fusion_emitters=true "
                     f"--xla_cpu_experimental_ynn_fusion_type= {loops}")
    assert started == "False", "import jaxdyn started JAX's backend"
    assert done["both chosen"][1].strip() == ("--xla_cpu_experimental_ynn_fusion_type=dot "
                                              f"--xla_cpu_use_fusion_emitters=true {loops}")
    assert done["late"][0] != 0
    assert f'XLA_FLAGS="{ours}"' in done["late"][2]


def test_imported_after_jax_started_jaxdyns_programs_still_turn_ynnpack_fusions_off(tmp_path):
    """Imported after JAX started, jaxdyn cannot set the process's XLA switches, but the
    programs it compiles itself carry the one a program can (YNNPACK fusions off, which slow
    a tree's small batched products), and `jaxdyn.compiler_options()` gives it to the
    caller's own `jax.jit`; without it, XLA fuses the Panda's mass matrix into YNNPACK calls
    (read in XLA's optimised programs)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["XLA_FLAGS"] = (f"--xla_dump_to={tmp_path} "
                        "--xla_dump_hlo_module_re=.*(arrays_only|plain_jit|with_options).*")
    code = textwrap.dedent("""
        import warnings
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        jnp.ones(1)  # JAX starts before jaxdyn is imported
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import jaxdyn
        assert any("compiler_options=jaxdyn.compiler_options()" in str(w.message)
                   for w in caught)
        tree, p = jaxdyn.from_urdf(jaxdyn.example_robot_urdf(
            "panda_description/urdf/panda.urdf"))
        robot = jaxdyn.ArticulatedBody(tree)
        q = np.tile(np.asarray(tree.neutral_configuration()), (64, 1))
        u = np.full_like(q, 0.1)
        robot.mass_matrix(0.0, q, u, p)  # compiled by jaxdyn
        def plain_jit(q, u):
            return robot.mass_matrix(0.0, q, u, p)
        def with_options(q, u):
            return robot.mass_matrix(0.0, q, u, p)
        jax.jit(plain_jit)(q, u)
        jax.jit(with_options, compiler_options=jaxdyn.compiler_options())(q, u)
    """)
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True)
    assert run.returncode == 0, run.stderr

    def fused(name):
        (program,) = tmp_path.glob(f"*jit_{name}.cpu_after_optimizations.txt")
        return program.read_text().count("ynn_fusion")

    assert fused("plain_jit") > 0
    assert fused("arrays_only") == fused("with_options") == 0


def test_float32_by_default_warns_once_naming_the_switch_unless_chosen():
    """With JAX's 64-bit mode off, every array is float32 (`jnp.array(1.0)` too) and float64
    inputs are cast: jaxdyn warns once, at the user's line, naming both switches, whether the
    state came as float64 or as the float32 arrays JAX makes by default; after
    `jaxdyn.allow_float32()` (the choice made explicit) no warning."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    system = ("import numpy as np, jax.numpy as jnp, jaxdyn; "
              "s = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.5 * q @ q); ")
    scripts = {
        "float64 given": system + ("x = jaxdyn.simulate(s, np.ones(1), np.zeros(1), t1=1.0); "
                                   "y = s.accelerations(0.0, np.ones(1), np.zeros(1)); "
                                   "print(x.q.dtype, y.dtype)"),
        "jnp default": system + ("x = jaxdyn.simulate(s, jnp.array([1.0]), jnp.array([0.0]), "
                                 "t1=1.0); print(x.q.dtype)"),
        "float32 chosen": system + ("jaxdyn.allow_float32(); x = jaxdyn.simulate(s, "
                                    "jnp.array([1.0]), jnp.array([0.0]), t1=1.0); "
                                    "print(x.q.dtype)"),
    }
    running = {name: subprocess.Popen([sys.executable, "-W", "always", "-c", code], env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for name, code in scripts.items()}
    done = {name: (process.wait(), *process.communicate()) for name, process in running.items()}
    for name in ("float64 given", "jnp default"):
        code, out, err = done[name]
        assert code == 0, err
        assert set(out.split()) == {"float32"}
        assert err.count("jaxdyn is computing in float32") == 1, name
        assert "jax.config.update('jax_enable_x64', True)" in err
        assert "jaxdyn.allow_float32()" in err
        assert err.startswith("<string>:1: UserWarning")  # the user's line, not jaxdyn's
    code, out, err = done["float32 chosen"]
    assert code == 0 and out.split() == ["float32"], err
    assert "jaxdyn is computing in float32" not in err


def test_a_python_branch_on_a_traced_value_is_named_without_a_parameter_hint():
    """A Python `if` on q inside T raises JAX's TracerBoolConversionError (a TypeError): the
    message names the callback and says to branch with jnp.where, and does not suggest a
    missing parameter."""
    def kinetic(q, qd, p):
        if q[0] > 0:  # a Python branch on a traced value
            return 0.5 * p["m"] * qd @ qd
        return qd @ qd

    system = jaxdyn.Lagrangian(kinetic, lambda q, p: 0.0 * q[0])
    with pytest.raises(ValueError) as caught:
        system.accelerations(0.0, np.ones(1), np.zeros(1), {"m": 1.0})
    message = str(caught.value)
    assert "kinetic" in message.lower() and "jnp.where" in message
    assert "missing from p" not in message


def test_public_names_are_documented_and_no_stray_module_is_exported():
    """Every public name of `jaxdyn` has a docstring (the documentation renders them), and the
    only module among them is `jaxdyn.rotations`."""
    import types

    public = {name: getattr(jaxdyn, name) for name in dir(jaxdyn) if not name.startswith("_")}
    modules = sorted(name for name, value in public.items()
                     if isinstance(value, types.ModuleType))
    assert modules == ["rotations"]
    undocumented = sorted(name for name, value in public.items()
                          if not isinstance(value, types.ModuleType)
                          and not (getattr(value, "__doc__", None) or "").strip())
    assert not undocumented, undocumented


def test_the_default_step_budget_follows_a_long_interval_when_called_eagerly():
    """An oscillator over 40 000 s (about 6400 periods) needs ~100 000 steps at the default
    tolerance, more than the default budget of 65 536: called eagerly, `simulate` runs it
    again with 8× the budget and integrates the whole interval (the closed form cos t to
    1e-5 after 6400 periods); staged in a caller's jit, the budget stays and the result says
    it ran out."""
    system = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.5 * q @ q)
    solution = jaxdyn.simulate(system, np.ones(1), np.zeros(1), t1=40_000.0, save="q")
    assert int(solution.num_steps) > 16**4
    np.testing.assert_allclose(solution.q[-1, 0], np.cos(40_000.0), atol=1e-5)
    staged = jax.jit(lambda q0: jaxdyn.simulate(system, q0, jnp.zeros(1), t1=40_000.0,
                                                save="q", throw=False).result)(jnp.ones(1))
    assert staged == jaxdyn.RESULTS.max_steps_reached


def test_a_nan_whose_cause_no_check_finds_still_raises_and_says_what_was_checked():
    """The guard of `accelerations` and `simulate`: a failure (here a NaN in the result) for
    which none of the listed causes holds raises, with the causes it ruled out and the state,
    rather than returning the NaN silently; eager, compiled, and for the failing member of a
    vmapped batch (the others pass)."""
    from jaxdyn._errors import error_if, reports_state
    from jaxdyn._linalg import NONFINITE_FORCING, SINGULAR_MASS_MATRIX

    def check(x):
        return error_if(x, lambda: [(jnp.zeros((), bool), SINGULAR_MASS_MATRIX),
                                    (jnp.zeros((), bool), NONFINITE_FORCING)],
                        (0.5, x, x), failed=~jnp.all(jnp.isfinite(x)))

    bad = np.array([np.nan, 1.0])
    expected = (r"^The result is not finite \(NaN or inf\), and none of the causes checked "
                r"for holds here:\n  - The mass matrix is singular(.|\n)*contains NaN or "
                r"inf\.(.|\n)*It happened at t = 0.5, q = \[nan, 1.0\]")
    for guarded in (reports_state(check), reports_state(jax.jit(check))):
        with pytest.raises(RuntimeError, match=expected):
            guarded(bad)
    batched = reports_state(jax.jit(jax.vmap(check)))
    np.testing.assert_array_equal(batched(np.ones((3, 2))), np.ones((3, 2)))
    with pytest.raises(RuntimeError, match=r"It happened at t = 0.5, q = \[nan, 1.0\]"):
        batched(np.stack([np.ones(2), bad]))


def test_checks_traced_as_nan_show_in_floating_point_values_and_keep_the_rest():
    """Under `checks_as_nan` (a fit's step, which must hold no host callback), a failed check
    makes its floating-point value NaN and a passed one leaves it alone; a value with no
    floating-point leaf, which NaN cannot mark, keeps the check's branch to the host and
    still raises its message."""
    from jaxdyn._errors import checks_as_nan, error_if

    def checked(x, message):
        return error_if(x, [(x.sum() > 3, message)])

    with checks_as_nan():
        floats = jax.jit(functools.partial(checked, message="too large"))
        np.testing.assert_array_equal(floats(jnp.array([1.0, 2.0])), [1.0, 2.0])
        assert np.all(np.isnan(floats(jnp.array([1.0, 5.0]))))
        integers = jax.jit(functools.partial(checked, message="integers too large"))
        np.testing.assert_array_equal(integers(jnp.array([1, 2])), [1, 2])
        with pytest.raises(Exception, match="integers too large"):
            jax.block_until_ready(integers(jnp.array([1, 5])))
