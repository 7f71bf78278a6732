"""Accuracy where simulations usually go wrong: a long horizon, a stiff spring, and a coordinate
singularity. Writes long_horizon.png.

Run: python examples/long_horizon.py [--t1 2000]

1. The double pendulum over t1 seconds: the variational integrator built from its Lagrangian
   (fixed step 0.01) keeps the energy error bounded, while Heun's method (explicit
   Runge–Kutta, same order and step) drifts and Tsit5 at rtol = 1e-6 creeps.
2. A pendulum on a stiff, heavily damped spring: `jaxdyn.stiffness` reads the stiffness ratio
   off the linearised equations and recommends an implicit solver, which then takes a few
   thousand steps where an explicit one would need tens of millions.
3. A spherical pendulum in polar angles aimed at the pole: the mass matrix's condition number
   grows along the way, and simulate stops with an error naming the coordinate singularity.
"""

import argparse
import time

import diffrax
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

G = 9.81


def double_pendulum():
    def kinetic(q, qd, p):
        return (0.5 * (p["m1"] + p["m2"]) * p["l1"] ** 2 * qd[0] ** 2
                + 0.5 * p["m2"] * p["l2"] ** 2 * qd[1] ** 2
                + p["m2"] * p["l1"] * p["l2"] * qd[0] * qd[1] * jnp.cos(q[0] - q[1]))

    def potential(q, p):
        return (-(p["m1"] + p["m2"]) * G * p["l1"] * jnp.cos(q[0])
                - p["m2"] * G * p["l2"] * jnp.cos(q[1]))

    return jaxdyn.Lagrangian(kinetic, potential), {"m1": 1.0, "m2": 1.0, "l1": 1.0, "l2": 1.0}


def long_horizon(ax, t1):
    system, p = double_pendulum()
    q0, u0 = jnp.array([1.0, 0.5]), jnp.zeros(2)
    ts = jnp.linspace(0.0, t1, 4001)
    e0 = system.energy(0.0, q0, u0, p)
    runs = {
        "variational midpoint, h = 0.01": dict(solver=jaxdyn.VariationalIntegrator(),
                                               dt0=0.01),
        "Heun (explicit RK2), h = 0.01": dict(solver=diffrax.Heun(), dt0=0.01,
                                              stepsize_controller=diffrax.ConstantStepSize()),
        "Tsit5, rtol = atol = 1e-6": dict(solver=diffrax.Tsit5(), rtol=1e-6, atol=1e-6,
                                          max_steps=1_000_000),
    }
    print(f"1. double pendulum over {t1:g} s (energy E0 = {float(e0):.4f})")
    for label, options in runs.items():
        start = time.perf_counter()
        sol = jaxdyn.simulate(system, q0, u0, p, t1=t1, ts=ts, **options)
        seconds = time.perf_counter() - start
        error = np.abs(np.asarray(system.energy(sol.ts, sol.q, sol.u, p) - e0))
        tenth = len(error) // 10
        print(f"   {label:<34} max |E − E0| = {error.max():.2e}, last tenth / first tenth = "
              f"{error[-tenth:].max() / error[1:tenth + 1].max():5.1f}, "
              f"{int(sol.num_steps)} steps, {seconds:.1f} s (with compilation)")
        ax.loglog(np.asarray(sol.ts)[1:], np.maximum(error[1:], 1e-16), lw=0.7, label=label)
    ax.set(xlabel="t (s)", ylabel="|E − E₀|", title="double pendulum: energy error")
    ax.legend(fontsize=7)


def stiff(ax):
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2),
        lambda q, p: 0.5 * p["k"] * (q[0] - p["l"]) ** 2 - p["m"] * G * q[0] * jnp.cos(q[1]),
        dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)
    p = {"m": 1.0, "k": 1e12, "c": 1e7, "l": 1.0}
    q0 = jnp.array([1.0 + G * np.cos(1.0) / p["k"], 1.0])
    report = jaxdyn.stiffness(system, 0.0, q0, jnp.zeros(2), p)
    print("\n2. pendulum on a stiff damped spring:", report.recommendation)
    ts = jnp.linspace(0.0, 5.0, 201)
    sol = jaxdyn.simulate(system, q0, jnp.zeros(2), p, t1=5.0, ts=ts, solver=report.solver,
                          rtol=1e-8, atol=1e-8)
    print(f"   {type(report.solver).__name__}: {int(sol.num_steps)} steps; spring stretch "
          f"{float(jnp.max(jnp.abs(sol.q[:, 0] - 1.0))):.1e} m")
    try:
        jaxdyn.simulate(system, q0, jnp.zeros(2), p, t1=5.0, solver=diffrax.Tsit5(),
                        rtol=1e-8, atol=1e-8, max_steps=4096)
    except RuntimeError as error:
        print("   Tsit5:", str(error).splitlines()[-1])
    ax.plot(sol.ts, sol.q[:, 1], label="θ (Kvaerno5)")
    ax.set(xlabel="t (s)", ylabel="θ (rad)", title=f"stiffness ratio {report.ratio:.1e}")
    ax.legend(fontsize=7)


def singular(ax):
    system = jaxdyn.Lagrangian(
        lambda q, qd, p: 0.5 * (qd[0] ** 2 + jnp.sin(q[0]) ** 2 * qd[1] ** 2),
        lambda q, p: -G * jnp.cos(q[0]))
    q0, u0 = jnp.array([0.3, 0.0]), jnp.array([-3.0, 1e-6])
    ts = jnp.linspace(0.0, 0.0969, 200)
    sol = jaxdyn.simulate(system, q0, u0, t1=0.0969, ts=ts, max_steps=100_000)
    condition = system.mass_matrix_condition(sol.ts, sol.q, sol.u)
    print("\n3. spherical pendulum aimed at the pole: condition number of M from "
          f"{float(condition[0]):.1f} to {float(condition[-1]):.1e}")
    try:  # closer still to the pole: the solve stops, and says why
        jaxdyn.simulate(system, q0, jnp.array([-3.0, 1e-8]), t1=1.0)
    except RuntimeError as error:
        print("  ", str(error).splitlines()[0][:160], "...")
        print("  ", str(error).splitlines()[-1])
    ax.semilogy(sol.ts, condition)
    ax.set(xlabel="t (s)", ylabel="κ(M)", title="spherical pendulum near the pole")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--t1", type=float, default=2000.0)
    args = parser.parse_args()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    long_horizon(axes[0], args.t1)
    stiff(axes[1])
    singular(axes[2])
    fig.tight_layout()
    fig.savefig("long_horizon.png", dpi=110)
    print("\nwrote long_horizon.png")


if __name__ == "__main__":
    main()
