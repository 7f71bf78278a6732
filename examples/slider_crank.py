"""jaxdyn example: a slider-crank (a closed loop) in redundant coordinates with constraints.

A motor turns the crank (torque τ) against a damped piston. The mechanism is written as a new
user would: three bodies in their own coordinates q = (θ, φ, x) — crank angle, connecting-rod
angle below the axis, slider position — and the two equations that close the loop,

    r cos θ + L cos φ − x = 0,        r sin θ − L sin φ = 0,

given to `jaxdyn.Constrained`. The script

1. places the initial state on the constraints (`consistent_state`);
2. simulates 4 s with each drift control (none, Baumgarte, projection) and reports the largest
   violation of the loop closure and the run time;
3. plots the constraint forces and the crank speed to slider_crank.png. With the closure
   written as "rod end − slider pin = 0", Cᵀλ = Φᵀλ is the generalized force of a force λ
   applied at the rod's end and −λ at the slider: λ is the force of the slider pin on the
   rod, in x and y (newtons);
4. differentiates the crank's final angle with respect to the piston's mass through the
   constrained simulation, checked against a central difference.

Run:  python examples/slider_crank.py
"""

import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import jaxdyn

P = {"r": 0.1, "L": 0.35, "m_crank": 1.0, "m_rod": 0.6, "m_piston": 0.8, "g": 9.81,
     "torque": 2.0, "damping": 40.0}


def kinetic(q, qd, p):
    theta, phi, _ = q
    td, pd, xd = qd
    r, L = p["r"], p["L"]
    rod_x = -r * jnp.sin(theta) * td - L / 2 * jnp.sin(phi) * pd  # the rod's centre
    rod_y = r * jnp.cos(theta) * td - L / 2 * jnp.cos(phi) * pd
    return (p["m_crank"] * r**2 / 6 * td**2
            + 0.5 * p["m_rod"] * (rod_x**2 + rod_y**2) + p["m_rod"] * L**2 / 24 * pd**2
            + 0.5 * p["m_piston"] * xd**2)


def potential(q, p):
    theta, phi, _ = q
    return p["g"] * (p["m_crank"] * p["r"] / 2 * jnp.sin(theta)
                     + p["m_rod"] * (p["r"] * jnp.sin(theta) - p["L"] / 2 * jnp.sin(phi)))


def forces(q, qd, p):  # motor torque on θ, viscous piston on x
    return jnp.stack([p["torque"], 0.0 * qd[1], -p["damping"] * qd[2]])


def loop(q, p):
    theta, phi, x = q
    return jnp.stack([p["r"] * jnp.cos(theta) + p["L"] * jnp.cos(phi) - x,
                      p["r"] * jnp.sin(theta) - p["L"] * jnp.sin(phi)])


free = jaxdyn.Lagrangian(kinetic, potential, forces)
options = {"none": None, "Baumgarte": jaxdyn.Baumgarte(alpha=20.0, beta=20.0),
           "projection": jaxdyn.Projection()}
systems = {name: jaxdyn.Constrained(free, holonomic=loop, stabilisation=s)
           for name, s in options.items()}

# 1. a consistent initial state from a rough guess
q0, u0 = systems["projection"].consistent_state(0.0, np.array([0.0, 0.0, 0.4]),
                                                np.array([5.0, 0.0, 0.0]), P)
print(f"initial state on the loop: q0 = {np.round(q0, 6)}, u0 = {np.round(u0, 6)}")

# 2. drift with and without control
ts = jnp.linspace(0.0, 4.0, 801)
solutions = {}
for name, system in systems.items():
    run = lambda: jaxdyn.simulate(system, q0, u0, P, t1=4.0, ts=ts,  # noqa: E731
                                  save=("q", "u", "constraints"), solver=diffrax.Tsit5(),
                                  rtol=1e-7, atol=1e-7)
    run()
    start = time.perf_counter()
    solutions[name] = sol = run()
    seconds = time.perf_counter() - start
    print(f"{name:>10s}: max |loop violation| = "
          f"{float(jnp.max(jnp.abs(sol.constraints.position_violation))):.1e} m, "
          f"{int(sol.num_steps)} steps, {1e3 * seconds:.1f} ms")

sol = solutions["projection"]
power_in = P["torque"] * sol.u[:, 0]
print(f"crank speed after 4 s: {float(sol.u[-1, 0]):.3f} rad/s "
      f"(mean motor power {float(jnp.mean(power_in)):.2f} W)")

# 3. constraint forces: λ is the force of the slider pin on the rod (see the docstring)
lam = np.asarray(sol.constraints.multipliers)
figure, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
axes[0].plot(ts, lam[:, 0], label="λ₁: pin force on the rod, x")
axes[0].plot(ts, lam[:, 1], label="λ₂: pin force on the rod, y")
axes[0].set_ylabel("multiplier [N]")
axes[0].legend()
axes[1].plot(ts, sol.u[:, 0])
axes[1].set_ylabel("crank speed θ̇ [rad/s]")
axes[1].set_xlabel("t [s]")
figure.suptitle("slider-crank, constraint forces (projection)")
figure.tight_layout()
figure.savefig("slider_crank.png", dpi=120)
print("plot written to slider_crank.png")


# 4. d θ(4 s) / d m_piston through the constrained simulation
def final_angle(m_piston):
    p = dict(P, m_piston=m_piston)
    return jaxdyn.simulate(systems["projection"], q0, u0, p, t1=4.0, solver=diffrax.Tsit5(),
                           rtol=1e-9, atol=1e-9).q[-1, 0]


m = jnp.asarray(P["m_piston"])
gradient = jax.grad(final_angle)(m)
h = 1e-5
central = (final_angle(m + h) - final_angle(m - h)) / (2 * h)
print(f"dθ(4 s)/dm_piston = {float(gradient):.6f} rad/kg (central difference "
      f"{float(central):.6f})")
assert abs(gradient - central) < 1e-5 * max(1.0, abs(central))
