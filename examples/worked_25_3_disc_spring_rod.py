"""Worked example 25.3: a rolling disc tied to a wall by a spring, with a hinged rod.

A uniform disc (mass M, radius R) rolls without slipping; its centre A is tied to a wall by a
horizontal spring (stiffness k); a uniform rod AB (mass m, length l) swings from a hinge at A.
With x the displacement of A and φ the rod's angle from the downward vertical,

    T = ¾ M ẋ² + ½ m ẋ² + ⅙ m l² φ̇² + ½ m l ẋ φ̇ cos φ,   V = ½ k x² − ½ m g l cos φ,

and the textbook equations are

    (3/2 M + m) ẍ + ½ m l (φ̈ cos φ − φ̇² sin φ) + k x = 0,
    ⅓ m l² φ̈ + ½ m l ẍ cos φ + ½ m g l sin φ = 0.

The system is built twice: once as `jaxdyn.Lagrangian` from the textbook's T and V as written,
and once from its bodies (a rolling disc and a rod) with all three formulations; every one is
compared with the accelerations solved from the textbook's equations.

Run: python examples/worked_25_3_disc_spring_rod.py
"""

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402
from jaxdyn.rotations import planar_rotation  # noqa: E402


def kinetic(q, qd, p):
    """The textbook's T, as written."""
    (_, phi), (xd, phid) = q, qd
    M, m, l = p["M"], p["m"], p["l"]
    return (0.75 * M * xd**2 + 0.5 * m * xd**2 + m * l**2 * phid**2 / 6
            + 0.5 * m * l * xd * phid * jnp.cos(phi))


def potential(q, p):
    """The textbook's V, as written (g = 9.81 m/s²)."""
    x, phi = q
    return 0.5 * p["k"] * x**2 - 0.5 * p["m"] * 9.81 * p["l"] * jnp.cos(phi)


def disc_centre(q, p):
    return jnp.array([q[0], 0.0, 0.0])


def disc_orientation(q, p):
    return planar_rotation(-q[0] / p["R"])  # rolling without slipping: angle = −x / R


def rod_orientation(q, p):
    return planar_rotation(q[1])


def rod_centre(q, p):
    return disc_centre(q, p) + rod_orientation(q, p) @ jnp.array([0.0, -p["l"] / 2, 0.0])


def build():
    def disc_inertia(p):
        return jnp.diag(jnp.array([0.25, 0.25, 0.5])) * p["M"] * p["R"] ** 2

    def rod_inertia(p):
        return jnp.diag(jnp.array([1.0, 0.0, 1.0])) * p["m"] * p["l"] ** 2 / 12

    disc = jaxdyn.RigidBody(lambda p: p["M"], disc_inertia, disc_centre, disc_orientation)
    rod = jaxdyn.RigidBody(lambda p: p["m"], rod_inertia, rod_centre, rod_orientation)
    spring = lambda q, p: 0.5 * p["k"] * q[0] ** 2  # noqa: E731
    return jaxdyn.MultibodySystem(
        [disc, rod], potential=spring, gravity=jnp.array([0.0, -9.81, 0.0])
    )


def textbook(q, qd, p):
    """Solve the textbook's two linear equations for (ẍ, φ̈)."""
    (x, phi), (_, phid) = q, qd
    M, m, l, k, g = p["M"], p["m"], p["l"], p["k"], 9.81
    a = np.array([[1.5 * M + m, 0.5 * m * l * np.cos(phi)],
                  [0.5 * m * l * np.cos(phi), m * l**2 / 3]])
    b = np.array([0.5 * m * l * phid**2 * np.sin(phi) - k * x,
                  -0.5 * m * g * l * np.sin(phi)])
    return np.linalg.solve(a, b)


def main():
    p = dict(M=2.0, R=0.3, m=0.7, l=0.9, k=25.0)
    system = build()
    formulations = {"Lagrangian(T, V)": jaxdyn.Lagrangian(kinetic, potential),
                    "bodies: Lagrange": jaxdyn.Lagrangian.from_system(system),
                    "bodies: Gibbs–Appell": jaxdyn.GibbsAppell.from_system(system),
                    "bodies: Kane": jaxdyn.Kane.from_system(system)}
    print("25.3 rolling disc, spring and hinged rod: accelerations (ẍ, φ̈)")
    for q, qd in [([0.1, 0.5], [0.2, -1.0]), ([-0.3, 2.0], [1.5, 3.0])]:
        q, qd = jnp.array(q), jnp.array(qd)
        reference = textbook(np.asarray(q), np.asarray(qd), p)
        print(f"  q = {q}, qd = {qd}\n    {'textbook':21s} {reference}")
        for name, dynamics in formulations.items():
            ours = np.asarray(dynamics.accelerations(0.0, q, qd, p))
            diff = np.max(np.abs(ours - reference)) / np.max(np.abs(reference))
            print(f"    {name:21s} {ours}   relative difference {diff:.1e}")
    lagrangian = formulations["Lagrangian(T, V)"]
    sol = jaxdyn.simulate(lagrangian, jnp.array([0.1, 1.0]), jnp.zeros(2), p, t1=10.0,
                          ts=jnp.linspace(0.0, 10.0, 501))
    energy = lagrangian.energy(sol.ts, sol.q, sol.qd, p)
    drift = float(jnp.max(jnp.abs(energy - energy[0])) / jnp.abs(energy[0]))
    print(f"  10 s simulation: {int(sol.num_steps)} steps, relative energy drift {drift:.1e}")


if __name__ == "__main__":
    main()
