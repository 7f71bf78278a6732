"""Derivatives through jaxdyn against central finite differences.

Reverse-mode gradients of a trajectory loss (through `simulate` with its default
RecursiveCheckpointAdjoint) and Jacobians of the accelerations are compared with central
differences of the same functions. Finite differences are the independent reference here:
agreement between jax.grad and jax.jacfwd would only test JAX against itself.

The solves use rtol = atol = 1e-13 so that the finite-difference noise (the global solver
error, which varies non-smoothly as the adaptive step sequence changes, divided by the step
1e-5) stays far below the 1e-6 relative tolerance of the comparison. At 1e-12 the measured
discrepancy for the pendulum's parameter gradient was 8.6e-7, too close to the tolerance; at
1e-13 it is below 1e-7 for every case, while the AD gradient itself agrees across solver
tolerances to 1e-9.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import (
    DISC_SPRING_ROD,
    DOUBLE_PENDULUM,
    ELASTIC_PENDULUM,
    PENDULUM,
    central_difference,
    central_difference_params,
)

SOLVER_TOL = 1e-13
FD_STEP = 1e-5
GRAD_RTOL = 1e-6


def assert_gradient_close(actual, fd, *, rtol=GRAD_RTOL, what=""):
    """Relative agreement in the 2-norm over all components (components can be zero, e.g.
    the pendulum's motion does not depend on its mass)."""
    actual = np.asarray(actual, np.float64).ravel()
    fd = np.asarray(fd, np.float64).ravel()
    error = np.linalg.norm(actual - fd)
    assert error <= rtol * np.linalg.norm(fd), f"{what}: AD {actual}, FD {fd}, error {error}"


CASES = {
    # name: (system, q0, u0, t1, number of save times)
    "pendulum": (PENDULUM, np.array([1.2]), np.array([-0.4]), 3.0, 6),
    "double_pendulum": (DOUBLE_PENDULUM, np.array([0.9, -0.5]), np.array([0.3, 1.1]), 2.0, 5),
}


@functools.cache
def _trajectory_loss(name):
    """loss(p, q0, u0) = Σ_i |q(t_i)|², jit-compiled, with its jit-compiled gradient."""
    system, _, _, t1, num = CASES[name]
    ts = np.linspace(t1 / num, t1, num)

    @jax.jit
    def loss(p, q0, u0):
        sol = jaxdyn.simulate(system.dynamics, q0, u0, p, t1=t1, ts=ts, rtol=SOLVER_TOL,
                              atol=SOLVER_TOL)
        return jnp.sum(sol.q**2)

    return loss, jax.jit(jax.grad(loss, argnums=(0, 1, 2)))


@pytest.mark.parametrize("name", list(CASES))
def test_trajectory_loss_gradient_wrt_parameters(name):
    system, q0, u0, _, _ = CASES[name]
    loss, grad = _trajectory_loss(name)
    p = system.params
    grad_p, _, _ = grad(p, q0, u0)
    fd = central_difference_params(lambda p: float(loss(p, q0, u0)), p, FD_STEP)
    keys = sorted(p)
    assert_gradient_close([grad_p[k] for k in keys], [fd[k] for k in keys], what="dL/dp")
    # Sanity check of the setup: the loss does depend on the parameters.
    assert np.linalg.norm([fd[k] for k in keys]) > 1e-2


@pytest.mark.parametrize("name", list(CASES))
def test_trajectory_loss_gradient_wrt_initial_state(name):
    system, q0, u0, _, _ = CASES[name]
    loss, grad = _trajectory_loss(name)
    p = system.params
    _, grad_q0, grad_u0 = grad(p, q0, u0)
    fd_q0 = central_difference(lambda q0: float(loss(p, q0, u0)), q0, FD_STEP)
    fd_u0 = central_difference(lambda u0: float(loss(p, q0, u0)), u0, FD_STEP)
    assert_gradient_close(grad_q0, fd_q0, what="dL/dq0")
    assert_gradient_close(grad_u0, fd_u0, what="dL/du0")


def test_pendulum_gradient_wrt_mass_vanishes():
    """θ̈ = −(g/l) sin θ does not involve m: dL/dm = 0 (exactly, up to round-off)."""
    loss, grad = _trajectory_loss("pendulum")
    _, q0, u0, _, _ = CASES["pendulum"]
    grad_p, _, _ = grad(PENDULUM.params, q0, u0)
    assert abs(float(grad_p["m"])) < 1e-9 * abs(float(grad_p["l"]))


ACCELERATION_SYSTEMS = [DOUBLE_PENDULUM, ELASTIC_PENDULUM, DISC_SPRING_ROD]


@pytest.mark.parametrize("system", ACCELERATION_SYSTEMS, ids=lambda s: s.name)
def test_acceleration_jacobians_against_finite_differences(system):
    """∂q̈/∂p (reverse mode) and ∂q̈/∂q, ∂q̈/∂q̇ (forward mode) against central differences
    of the accelerations."""
    dynamics = system.dynamics
    keys = sorted(system.params)
    rng = np.random.default_rng(7)
    q, qd = system.sample(rng)
    t = 0.3

    def accelerations(vector):
        p = dict(zip(keys, vector))
        return dynamics.accelerations(t, q, qd, p)

    p_vector = np.array([system.params[k] for k in keys])
    jac_p = jax.jit(jax.jacrev(accelerations))(p_vector)
    fd_p = central_difference(lambda v: np.asarray(jax.jit(accelerations)(v)), p_vector, 1e-6)
    assert_gradient_close(jac_p, fd_p, what="dqdd/dp")

    state_accelerations = jax.jit(lambda q, qd: dynamics.accelerations(t, q, qd, system.params))
    jac_q, jac_qd = jax.jit(jax.jacfwd(lambda q, qd: dynamics.accelerations(
        t, q, qd, system.params), argnums=(0, 1)))(q, qd)
    fd_q = central_difference(lambda q: np.asarray(state_accelerations(q, qd)), q, 1e-6)
    fd_qd = central_difference(lambda qd: np.asarray(state_accelerations(q, qd)), qd, 1e-6)
    assert_gradient_close(jac_q, fd_q, what="dqdd/dq")
    assert_gradient_close(jac_qd, fd_qd, what="dqdd/dqd")


def test_acceleration_parameter_gradient_against_reference_derivative():
    """The derivative of the 25.1 closed form a = (2P+Q) g r² sin β / ((2P+Q) r² + 2 J g)
    with respect to J, by hand: ∂a/∂J = −2 g a / ((2P+Q) r² + 2 J g)."""
    from helpers import WHEELS_BAR

    p = WHEELS_BAR.params

    def acceleration(J):
        return WHEELS_BAR.dynamics.accelerations(0.0, jnp.array([0.1]), jnp.array([0.2]),
                                                 {**p, "J": J})[0]

    P, Q, J, r, g, beta = (p[k] for k in ("P", "Q", "J", "r", "g", "beta"))
    denominator = (2 * P + Q) * r**2 + 2 * J * g
    a = (2 * P + Q) * g * r**2 * np.sin(beta) / denominator
    expected = -2 * g * a / denominator
    actual = float(jax.grad(acceleration)(J))
    np.testing.assert_allclose(actual, expected, rtol=1e-10)
    fd = central_difference(lambda J: float(acceleration(float(J))), np.array(J), 1e-6)
    np.testing.assert_allclose(fd, expected, rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# Derivatives of simulate with its default adjoint, in both modes
# ---------------------------------------------------------------------------------------------


def _final_state(system, t1):
    def final(p, q0, u0):
        sol = jaxdyn.simulate(system.dynamics, q0, u0, p, t1=t1, rtol=SOLVER_TOL,
                              atol=SOLVER_TOL)
        return jnp.concatenate([sol.q[-1], sol.u[-1]])
    return final


def test_forward_mode_through_simulate_with_default_options():
    """jax.jacfwd through simulate as called by default (few parameters: forward
    sensitivities), with respect to the parameters and the initial angles, against central
    differences of the final state (jacfwd is JAX's vmapped jvp)."""
    system, q0, u0, t1, _ = CASES["double_pendulum"]
    final = _final_state(system, t1)
    keys = sorted(system.params)

    @jax.jit
    def of_vectors(v, q0):
        return final(dict(zip(keys, v)), q0, u0)

    v = np.array([system.params[k] for k in keys])
    jac_v, jac_q0 = jax.jit(jax.jacfwd(of_vectors, argnums=(0, 1)))(v, q0)
    fd_v = central_difference(lambda v: np.asarray(of_vectors(v, q0)), v, FD_STEP)
    fd_q0 = central_difference(lambda q0: np.asarray(of_vectors(v, q0)), q0, FD_STEP)
    assert_gradient_close(jac_v, fd_v, what="d(q, u)(t1)/dp")
    assert_gradient_close(jac_q0, fd_q0, what="d(q, u)(t1)/dq0")


def test_reverse_mode_for_many_inputs_through_checkpoints():
    """Beyond 16 differentiable entries simulate differentiates by reverse mode through
    checkpoints (a chain of 9 springs: 27 entries), against central differences."""
    n = 9
    chain = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * jnp.sum(qd**2),
        lambda q, p: 0.5 * jnp.sum(p["k"] * jnp.diff(q, prepend=0.0) ** 2))
    k = np.linspace(1.0, 3.0, n)
    q0 = np.linspace(0.1, 0.5, n)

    @jax.jit
    def loss(k, u0):
        sol = jaxdyn.simulate(chain, q0, u0, {"k": k}, t1=1.0, rtol=SOLVER_TOL,
                              atol=SOLVER_TOL)
        return jnp.sum(sol.q[-1] ** 2)

    u0 = np.zeros(n)
    grad_k = jax.jit(jax.grad(loss))(k, u0)
    fd = central_difference(lambda k: float(loss(k, u0)), k, FD_STEP)
    assert_gradient_close(grad_k, fd, what="dL/dk")
    with pytest.raises(TypeError, match="forward-mode"):  # JAX's refusal, documented
        jax.jvp(lambda k: loss(k, u0), (k,), (np.ones(n),))
