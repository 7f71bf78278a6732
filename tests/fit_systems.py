"""The torque-driven double pendulum of the fit tests and benchmarks: the model as a user
writes it for jaxdyn (energies of point masses on massless rods) and, independently, its
hand-derived equations integrated by SciPy to make the "measured" data."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import jaxdyn

G = 9.81

PENDULUM_TRUTH = {"m1": 1.0, "m2": 0.8, "l1": 1.0, "l2": 0.7}


def pendulum_rhs(amplitude, frequency):
    """Hand-derived: M(θ) θ̈ = f for point masses on massless rods, angles from the
    downward vertical, torque τ = A sin(ω t) at the first joint."""
    m1, m2, l1, l2 = (PENDULUM_TRUTH[k] for k in ("m1", "m2", "l1", "l2"))

    def rhs(t, y):
        a, b, ad, bd = y
        c, s = np.cos(a - b), np.sin(a - b)
        mass = np.array([[(m1 + m2) * l1**2, m2 * l1 * l2 * c],
                         [m2 * l1 * l2 * c, m2 * l2**2]])
        force = np.array([
            -m2 * l1 * l2 * bd**2 * s - (m1 + m2) * G * l1 * np.sin(a)
            + amplitude * np.sin(frequency * t),
            m2 * l1 * l2 * ad**2 * s - m2 * G * l2 * np.sin(b)])
        return np.concatenate([[ad, bd], np.linalg.solve(mass, force)])

    return rhs


def positions(q, p):
    """Cartesian positions of the two masses."""
    first = p["l1"] * jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])
    return first, first + p["l2"] * jnp.stack([jnp.sin(q[1]), -jnp.cos(q[1])])


def _pendulum_T(t, q, qd, p):
    v1, v2 = jax.jvp(lambda q: positions(q, p[0]), (q,), (qd,))[1]
    return 0.5 * p[0]["m1"] * v1 @ v1 + 0.5 * p[0]["m2"] * v2 @ v2


def _pendulum_V(t, q, p):
    first, second = positions(q, p[0])
    return G * (p[0]["m1"] * first[1] + p[0]["m2"] * second[1])


def _pendulum_Q(t, q, qd, p):
    inputs = p[1]
    return jnp.stack([inputs["A"] * jnp.sin(inputs["w"] * t), jnp.zeros_like(t)])


PENDULUM = jaxdyn.Lagrangian(kinetic=_pendulum_T, potential=_pendulum_V, forces=_pendulum_Q,
                             time_dependent=True)


def pendulum_data(q0, ts, amplitude=0.0, frequency=1.0):
    """States (k, 4) = (θ₁, θ₂, θ̇₁, θ̇₂) at ts from rest at q0."""
    solution = solve_ivp(pendulum_rhs(amplitude, frequency), (ts[0], ts[-1]),
                         [*q0, 0.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853")
    return solution.y.T
