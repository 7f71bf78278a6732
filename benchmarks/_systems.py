"""The benchmark systems: each as a user gives it to jaxdyn (energies T and V) and as the
closed-form equations a user would write by hand in jax.numpy (the baseline).

- double pendulum: two point masses on massless rods, absolute angles from the downward
  vertical (the textbook closed form of θ̈₁, θ̈₂);
- elastic pendulum (reference worked example 25.2): polar coordinates (r, θ);
- N-link chain: N uniform rods (mass m, length l) hinged end to end, absolute angles, written
  by the user with cumulative sums of the link vectors; by hand, M_ij = a_ij cos(θ_i − θ_j)
  + δ_ij m l²/12 with a = m l² CᵀC (C_ki = 1 for i < k, ½ for i = k), the Coriolis and gravity
  vector, and a Cholesky solve.
"""

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

import jaxdyn


@dataclasses.dataclass(frozen=True)
class System:
    name: str
    n: int
    dynamics: jaxdyn.Lagrangian
    params: dict
    hand_written: Callable  # (t, q, qd, p) -> q̈
    hand_equations: Callable  # (t, q, qd, p) -> (M, f)
    sample: Callable  # rng -> (q, qd)


# -- double pendulum ---------------------------------------------------------------------------

DOUBLE_PENDULUM_PARAMS = dict(m1=1.0, m2=0.8, l1=1.0, l2=0.7, g=9.81)


def double_pendulum_T(q, qd, p):
    v1 = p["l1"] * qd[0] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
    v2 = v1 + p["l2"] * qd[1] * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
    return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)


def double_pendulum_V(q, p):
    return -p["g"] * ((p["m1"] + p["m2"]) * p["l1"] * jnp.cos(q[0])
                      + p["m2"] * p["l2"] * jnp.cos(q[1]))


def double_pendulum_hand(t, q, qd, p):
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    d = q[0] - q[1]
    den = 2 * m1 + m2 - m2 * jnp.cos(2 * d)
    a1 = (-g * (2 * m1 + m2) * jnp.sin(q[0]) - m2 * g * jnp.sin(q[0] - 2 * q[1])
          - 2 * jnp.sin(d) * m2 * (qd[1] ** 2 * l2 + qd[0] ** 2 * l1 * jnp.cos(d))) / (l1 * den)
    a2 = (2 * jnp.sin(d) * (qd[0] ** 2 * l1 * (m1 + m2) + g * (m1 + m2) * jnp.cos(q[0])
                            + qd[1] ** 2 * l2 * m2 * jnp.cos(d))) / (l2 * den)
    return jnp.stack([a1, a2])


def double_pendulum_fastest(t, q, qd, p):
    """The fastest closed form known (the floor of bench_default_paths.py): s = sin(θ₁ − θ₂),
    c = cos(θ₁ − θ₂), den = m₁ + m₂ s², four trigonometric calls and two divisions."""
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    d = q[0] - q[1]
    s, c = jnp.sin(d), jnp.cos(d)
    den = m1 + m2 * s * s
    s1, s2 = jnp.sin(q[0]), jnp.sin(q[1])
    a1 = (m2 * g * s2 * c - m2 * s * (l1 * qd[0] ** 2 * c + l2 * qd[1] ** 2)
          - (m1 + m2) * g * s1) / (l1 * den)
    a2 = ((m1 + m2) * (l1 * qd[0] ** 2 * s - g * s2 + g * s1 * c)
          + m2 * l2 * qd[1] ** 2 * s * c) / (l2 * den)
    return jnp.stack([a1, a2])


def double_pendulum_T_scalar(q, qd, p):
    """T as the textbook writes it: ½(m₁ + m₂)l₁²θ̇₁² + ½m₂l₂²θ̇₂² + m₂l₁l₂θ̇₁θ̇₂ cos(θ₁ − θ₂)."""
    return (0.5 * (p["m1"] + p["m2"]) * (p["l1"] * qd[0]) ** 2
            + 0.5 * p["m2"] * (p["l2"] * qd[1]) ** 2
            + p["m2"] * p["l1"] * p["l2"] * qd[0] * qd[1] * jnp.cos(q[0] - q[1]))


def _rotation(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def _double_pendulum_positions(q, p):
    down = jnp.array([0.0, -1.0])
    r1 = p["l1"] * _rotation(q[0]) @ down
    return r1, r1 + p["l2"] * _rotation(q[1]) @ down


def double_pendulum_T_rotations(q, qd, p):
    """T from positions built with rotation matrices, velocities by a JVP of the positions."""
    v1, v2 = jax.jvp(lambda q: _double_pendulum_positions(q, p), (q,), (qd,))[1]
    return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)


def double_pendulum_equations(t, q, qd, p):
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    d = q[0] - q[1]
    c = m2 * l1 * l2 * jnp.cos(d)
    s = m2 * l1 * l2 * jnp.sin(d)
    mass_matrix = jnp.stack([jnp.stack([(m1 + m2) * l1**2, c]), jnp.stack([c, m2 * l2**2])])
    forcing = jnp.stack([-s * qd[1] ** 2 - (m1 + m2) * g * l1 * jnp.sin(q[0]),
                         s * qd[0] ** 2 - m2 * g * l2 * jnp.sin(q[1])])
    return mass_matrix, forcing


DOUBLE_PENDULUM = System(
    "double pendulum", 2, jaxdyn.Lagrangian(double_pendulum_T, double_pendulum_V),
    DOUBLE_PENDULUM_PARAMS, double_pendulum_hand, double_pendulum_equations,
    lambda rng: (rng.uniform(-3, 3, 2), rng.uniform(-2, 2, 2)))


# -- elastic pendulum (25.2) -------------------------------------------------------------------

ELASTIC_PARAMS = dict(m=0.9, g=9.81, k=35.0, l0=1.2)


def elastic_T(q, qd, p):
    return 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def elastic_V(q, p):
    return -p["m"] * p["g"] * q[0] * jnp.cos(q[1]) + 0.5 * p["k"] * (q[0] - p["l0"]) ** 2


def elastic_hand(t, q, qd, p):
    m, g, k, l0 = p["m"], p["g"], p["k"], p["l0"]
    r, theta, r_dot, theta_dot = q[0], q[1], qd[0], qd[1]
    return jnp.stack([r * theta_dot**2 + g * jnp.cos(theta) - k / m * (r - l0),
                      -(2 * r_dot * theta_dot + g * jnp.sin(theta)) / r])


def elastic_equations(t, q, qd, p):
    m, g, k, l0 = p["m"], p["g"], p["k"], p["l0"]
    r, theta, r_dot, theta_dot = q[0], q[1], qd[0], qd[1]
    zero = jnp.zeros_like(r)
    mass_matrix = jnp.stack([jnp.stack([m + zero, zero]), jnp.stack([zero, m * r**2])])
    forcing = jnp.stack([m * r * theta_dot**2 + m * g * jnp.cos(theta) - k * (r - l0),
                         -2 * m * r * r_dot * theta_dot - m * g * r * jnp.sin(theta)])
    return mass_matrix, forcing


ELASTIC_PENDULUM = System(
    "elastic pendulum", 2, jaxdyn.Lagrangian(elastic_T, elastic_V), ELASTIC_PARAMS,
    elastic_hand, elastic_equations,
    lambda rng: (np.array([rng.uniform(0.8, 1.6), rng.uniform(-2, 2)]), rng.uniform(-2, 2, 2)))


# -- N-link chain --------------------------------------------------------------------------------

CHAIN_PARAMS = dict(m=1.0, l=0.5, g=9.81)


def chain_T(q, qd, p):
    """Rod centres from cumulative sums of the link vectors l (sin θ, −cos θ)."""
    vx = p["l"] * jnp.cos(q) * qd
    vy = p["l"] * jnp.sin(q) * qd
    centre_vx = jnp.cumsum(vx) - 0.5 * vx
    centre_vy = jnp.cumsum(vy) - 0.5 * vy
    return (0.5 * p["m"] * jnp.sum(centre_vx**2 + centre_vy**2)
            + 0.5 * p["m"] * p["l"] ** 2 / 12 * jnp.sum(qd**2))


def chain_V(q, p):
    y = -p["l"] * jnp.cos(q)
    return p["m"] * p["g"] * jnp.sum(jnp.cumsum(y) - 0.5 * y)


def chain_hand(n):
    index = np.arange(n)
    c = np.where(index[None, :] < index[:, None], 1.0, 0.0) + 0.5 * np.eye(n)  # C[k, i]
    coupling = c.T @ c
    heights = c.sum(axis=0)

    def equations(t, q, qd, p):
        m, l, g = p["m"], p["l"], p["g"]
        a = m * l**2 * coupling
        diff = q[:, None] - q[None, :]
        mass_matrix = a * jnp.cos(diff) + jnp.eye(n) * m * l**2 / 12
        forcing = -(a * jnp.sin(diff)) @ qd**2 - m * g * l * heights * jnp.sin(q)
        return mass_matrix, forcing

    def accelerations(t, q, qd, p):
        mass_matrix, forcing = equations(t, q, qd, p)
        return jsl.cho_solve(jsl.cho_factor(mass_matrix), forcing)

    return accelerations, equations


def chain(n):
    accelerations, equations = chain_hand(n)
    return System(f"chain N={n}", n, jaxdyn.Lagrangian(chain_T, chain_V), CHAIN_PARAMS,
                  accelerations, equations,
                  lambda rng: (rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)))


SYSTEMS = [DOUBLE_PENDULUM, ELASTIC_PENDULUM] + [chain(n) for n in (2, 5, 10, 20)]


def as_arrays(params):
    return {k: jnp.asarray(v) for k, v in params.items()}


def states(system, count, seed=0):
    """`count` random states (q, qd) as arrays of shape (count, n)."""
    rng = np.random.default_rng(seed)
    pairs = [system.sample(rng) for _ in range(count)]
    return (jnp.asarray(np.stack([a for a, _ in pairs])),
            jnp.asarray(np.stack([b for _, b in pairs])))


def check_agreement(system, tol=1e-9):
    """jaxdyn and the hand-written equations agree before anything is timed."""
    p = as_arrays(system.params)
    qs, qds = states(system, 8)
    t = jnp.asarray(0.0)
    ours = jax.vmap(system.dynamics.accelerations, in_axes=(None, 0, 0, None))(t, qs, qds, p)
    theirs = jax.vmap(system.hand_written, in_axes=(None, 0, 0, None))(t, qs, qds, p)
    error = float(jnp.max(jnp.abs(ours - theirs)) / jnp.max(jnp.abs(theirs)))
    assert error < tol, (system.name, error)
    return error
