"""Worked example 25.1: two wheels and a bar rolling down an incline.

Two equal wheels (radius r, weight P, moment of inertia J about the centre) roll without
slipping down an incline of angle β; a uniform bar of weight Q joins their centres. With s the
distance travelled, T = ½ (2P + Q)/g ṡ² + J ṡ²/r² and V = −(2P + Q) s sin β, and the textbook
answer is a = (2P + Q) g r² sin β / ((2P + Q) r² + 2 J g).

Run: python examples/worked_25_1_wheels_bar.py
"""

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402


def kinetic(q, qd, p):
    return 0.5 * (2 * p["P"] + p["Q"]) / p["g"] * qd[0] ** 2 + p["J"] * qd[0] ** 2 / p["r"] ** 2


def potential(q, p):
    return -(2 * p["P"] + p["Q"]) * q[0] * jnp.sin(p["beta"])


def main():
    p = dict(P=30.0, Q=50.0, J=0.4, r=0.25, beta=jnp.pi / 6, g=9.81)
    system = jaxdyn.Lagrangian(kinetic, potential)
    computed = system.accelerations(0.0, jnp.array([0.0]), jnp.array([0.0]), p)[0]
    W = 2 * p["P"] + p["Q"]
    textbook = W * p["g"] * p["r"] ** 2 * jnp.sin(p["beta"]) / (
        W * p["r"] ** 2 + 2 * p["J"] * p["g"]
    )
    print("25.1 two wheels and a bar on an incline")
    print(f"  jaxdyn   a = {float(computed):.15f} m/s²")
    print(f"  textbook a = {float(textbook):.15f} m/s²")
    print(f"  relative difference {float(abs(computed - textbook) / textbook):.1e}")

    # Uniform acceleration from rest: s(t) = ½ a t².
    sol = jaxdyn.simulate(system, jnp.array([0.0]), jnp.array([0.0]), p, t1=2.0)
    print(f"  simulated s(2 s) = {float(sol.q[-1, 0]):.12f} m, ½ a t² = "
          f"{float(0.5 * textbook * 4.0):.12f} m")


if __name__ == "__main__":
    main()
