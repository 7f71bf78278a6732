"""Worked example 25.2: the elastic pendulum.

A ball of mass m on a massless spring (stiffness k, natural length l₀) swings in a vertical
plane. In polar coordinates (r, θ), θ from the downward vertical,
T = ½ m (ṙ² + r² θ̇²), V = −m g r cos θ + ½ k (r − l₀)², and the textbook equations are

    m r̈ − m r θ̇² − m g cos θ + k (r − l₀) = 0,     r θ̈ + 2 ṙ θ̇ + g sin θ = 0.

Run: python examples/worked_25_2_elastic_pendulum.py
"""

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402


def kinetic(q, qd, p):
    r, _ = q
    return 0.5 * p["m"] * (qd[0] ** 2 + r**2 * qd[1] ** 2)


def potential(q, p):
    r, theta = q
    return -p["m"] * p["g"] * r * jnp.cos(theta) + 0.5 * p["k"] * (r - p["l0"]) ** 2


def textbook(q, qd, p):
    """The accelerations solved from the textbook's two equations."""
    (r, theta), (rd, thetad) = q, qd
    rdd = r * thetad**2 + p["g"] * jnp.cos(theta) - p["k"] / p["m"] * (r - p["l0"])
    thetadd = -(2 * rd * thetad + p["g"] * jnp.sin(theta)) / r
    return jnp.array([rdd, thetadd])


def main():
    p = dict(m=0.5, k=40.0, l0=1.0, g=9.81)
    system = jaxdyn.Lagrangian(kinetic, potential)
    print("25.2 elastic pendulum: accelerations (r̈, θ̈)")
    states = [([1.1, 0.4], [0.3, -1.2]), ([0.8, -1.0], [-0.5, 2.0]), ([1.3, 2.5], [1.0, 0.1])]
    for q, qd in states:
        q, qd = jnp.array(q), jnp.array(qd)
        ours, theirs = system.accelerations(0.0, q, qd, p), textbook(q, qd, p)
        diff = float(jnp.max(jnp.abs(ours - theirs)) / jnp.max(jnp.abs(theirs)))
        print(f"  q = {q}, qd = {qd}\n    jaxdyn   {ours}\n    textbook {theirs}"
              f"   relative difference {diff:.1e}")
    q0, qd0 = jnp.array([1.2, 0.8]), jnp.array([0.0, 0.0])
    sol = jaxdyn.simulate(system, q0, qd0, p, t1=10.0, ts=jnp.linspace(0.0, 10.0, 1001))
    energy = system.energy(sol.ts, sol.q, sol.qd, p)
    drift = float(jnp.max(jnp.abs(energy - energy[0])) / jnp.abs(energy[0]))
    print(f"  10 s simulation: {int(sol.num_steps)} steps, relative energy drift {drift:.1e}")


if __name__ == "__main__":
    main()
