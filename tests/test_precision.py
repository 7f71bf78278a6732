"""float32 as an explicit option: every result keeps the state's dtype (no dtype is
hard-coded), and the error against float64 stays at a stated tolerance."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

from helpers import DOUBLE_PENDULUM, PENDULUM
from test_tree import ROD, chain_tree

F32 = jnp.float32


def _cast(tree, dtype):
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if isinstance(x, float | np.ndarray | jax.Array)
        else x, tree)


CASES = [
    ("pendulum", PENDULUM.dynamics, PENDULUM.params, [0.8], [0.0]),
    ("double_pendulum", DOUBLE_PENDULUM.dynamics, DOUBLE_PENDULUM.params, [0.6, -0.4],
     [0.0, 0.5]),
    ("chain_tree_3", jaxdyn.ArticulatedBody(chain_tree(3)), ROD, [0.5, -0.3, 0.2],
     [0.0, 0.4, -0.2]),
]


# The tree's float32 simulation compiles for longer: in the slow set; its public methods are
# checked in float32 by default (below).
SIMULATION_CASES = [*CASES[:2], pytest.param(*CASES[2], id=CASES[2][0], marks=pytest.mark.slow)]


@pytest.mark.parametrize("name, dynamics, p, q0, u0", SIMULATION_CASES,
                         ids=[c[0] for c in CASES])
def test_float32_simulation_keeps_its_dtype_and_tracks_float64(name, dynamics, p, q0, u0):
    """Over 5 s of regular motion at the float32 default tolerance (1e-6): within 1e-3 of the
    float64 solution (measured 1e-5 to 1e-4: benchmarks/LOG.md has the growth over time),
    with the energy error within 1e-4 of the energy scale."""
    ts = np.linspace(0.0, 5.0, 51)
    sol64 = jaxdyn.simulate(dynamics, np.array(q0), np.array(u0), p, t1=5.0, ts=ts)
    sol32 = jaxdyn.simulate(dynamics, np.array(q0, np.float32), np.array(u0, np.float32),
                            _cast(p, F32), t1=5.0, ts=ts.astype(np.float32))
    for x in (sol32.ts, sol32.q, sol32.u, sol32.qd):
        assert x.dtype == F32, name
    np.testing.assert_allclose(sol32.q, sol64.q, atol=1e-3)
    p32 = _cast(p, F32)
    energy = dynamics.energy(sol32.ts, sol32.q, sol32.u, p32)
    scale = float(jnp.max(jnp.abs(dynamics.kinetic_energy(sol64.ts, sol64.q, sol64.u, p)))) + 1
    assert energy.dtype == F32
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-4 * scale


@pytest.mark.parametrize("name, dynamics, p, q0, u0", CASES, ids=[c[0] for c in CASES])
def test_public_methods_compute_in_the_states_dtype(name, dynamics, p, q0, u0):
    p32 = _cast(p, F32)
    t, q, u = np.float32(0.1), np.array(q0, np.float32), np.array(u0, np.float32)
    for method in ("mass_matrix", "forcing", "accelerations", "energy", "momentum",
                   "mass_matrix_condition", "kinetic_energy", "potential_energy"):
        value = getattr(dynamics, method)(t, q, u, p32)
        assert value.dtype == F32, method
        reference = getattr(dynamics, method)(0.1, np.array(q0), np.array(u0), p)
        np.testing.assert_allclose(value, reference, rtol=1e-4, atol=1e-4, err_msg=method)


@pytest.mark.slow
def test_float32_structure_preserving_steppers():
    """The variational integrator's Newton tolerance follows the dtype (√ε): in float32 the
    energy error stays bounded over 10⁴ steps, at the size the step gives in float64."""
    dynamics, p = DOUBLE_PENDULUM.dynamics, DOUBLE_PENDULUM.params
    q0, u0 = np.array([0.6, -0.4]), np.array([0.0, 0.5])
    errors = {}
    for dtype in (np.float64, np.float32):
        pd = _cast(p, dtype) if dtype == np.float32 else p
        sol = jaxdyn.simulate(dynamics, q0.astype(dtype), u0.astype(dtype), pd, t1=100.0,
                              ts=np.linspace(0.0, 100.0, 401).astype(dtype), dt0=0.01,
                              solver=jaxdyn.VariationalIntegrator())
        assert sol.q.dtype == dtype
        energy = dynamics.energy(sol.ts, sol.q, sol.u, pd)
        errors[dtype] = np.abs(np.asarray(energy - energy[0], np.float64))
    assert errors[np.float32].max() < 2 * errors[np.float64].max() + 1e-4
    assert errors[np.float32][-100:].max() < 2 * errors[np.float32][1:101].max() + 1e-4

    kepler = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.dot(qd, qd),
                               lambda q, p: -1.0 / jnp.sqrt(jnp.dot(q, q)))
    sol = jaxdyn.simulate(kepler, np.array([1.0, 0.0], np.float32),
                          np.array([0.0, 1.2], np.float32), t1=np.float32(50.0), dt0=0.01,
                          solver=jaxdyn.StormerVerlet(), ts=np.linspace(0, 50, 11, dtype=F32))
    assert sol.q.dtype == F32
    angular = sol.q[:, 0] * sol.u[:, 1] - sol.q[:, 1] * sol.u[:, 0]
    np.testing.assert_allclose(angular, 1.2, rtol=1e-5)


def test_float32_stiff_solve_and_stiffness_report():
    spring = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2,
                               lambda q, p: 0.5 * p["k"] * q[0] ** 2,
                               dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)
    p = {"k": np.float32(1e6), "c": np.float32(1e5)}
    q0, u0 = np.array([1.0], np.float32), np.array([0.0], np.float32)
    report = jaxdyn.stiffness(spring, 0.0, q0, u0, p)
    assert report.stiff
    # In float32 an implicit solver's error estimate has a rounding floor near ε₃₂ h ‖J‖:
    # at this stiffness ratio (10⁴) rtol = 1e-4 already fails, 1e-3 works (benchmarks/LOG.md).
    sol = jaxdyn.simulate(spring, q0, u0, p, t1=1.0, solver=diffrax.Kvaerno5(), rtol=1e-3,
                          atol=1e-3)
    assert sol.q.dtype == F32 and int(sol.num_steps) < 100
    # Overdamped: x(t) from x(0) = 1, ẋ(0) = 0 with the roots of λ² + c λ + k = 0.
    slow, fast = np.sort(np.roots([1.0, 1e5, 1e6]).real)[::-1]
    exact = (fast * np.exp(slow * 1.0) - slow * np.exp(fast * 1.0)) / (fast - slow)
    np.testing.assert_allclose(sol.q[-1, 0], exact, atol=2e-5)


def test_float32_ball_bounces_and_comes_to_rest():
    """A ball (e = 0.5) bouncing in float32: its impacts at t₁ (1 + 2e + … + 2e^{k−1}), then
    at rest on the floor from their accumulation time t₁ (1 + e)/(1 − e), where float64 has
    it. A restart after each impact lies a float32 round-off (10⁻⁷) from the floor: taken
    for one (not a contact passed through), so the ball neither falls through nor bounces
    on at the floor."""
    ball = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2), lambda q, p: 9.81 * q[1])
    floor = jaxdyn.UnilateralContact(lambda q, p: q[1], restitution=lambda p: p["e"])
    ts = np.linspace(0.0, 2.0, 5, dtype=np.float32)
    sol = jaxdyn.simulate(ball, np.array([0.0, 1.0], np.float32), np.array([0.3, 0.0], np.float32),
                          {"e": np.float32(0.5)}, t1=np.float32(2.0), ts=ts, events=[floor],
                          max_events=40, solver=diffrax.Tsit5(), rtol=1e-5, atol=1e-5)
    assert sol.q.dtype == F32
    first = np.sqrt(2 / 9.81)
    impacts = first * (1 + np.concatenate([[0.0], np.cumsum(2 * 0.5 ** np.arange(1, 6))]))
    np.testing.assert_allclose(sol.events.t[:6], impacts, rtol=1e-4)
    count = int(sol.events.count)
    assert bool(sol.events.resting[count - 1, 0])
    np.testing.assert_allclose(sol.events.t[count - 1], first * 3, rtol=1e-3)
    after = ts > first * 3
    np.testing.assert_allclose(sol.q[after, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(sol.q[after, 0], 0.3 * ts[after], rtol=1e-5)
