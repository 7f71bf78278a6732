"""jaxdyn demo: a double pendulum, from its energies to a gradient through the simulation.

Two point masses m1, m2 on massless rods of lengths l1, l2, angles θ1, θ2 measured from the
downward vertical. jaxdyn is given only the kinetic and potential energies; it forms Lagrange's
equations by automatic differentiation, integrates them with diffrax, and differentiates the
whole simulation with respect to the parameters.

Run:  python examples/demo.py        (writes double_pendulum.png in the current directory)
"""

import time

import jax

jax.config.update("jax_enable_x64", True)  # mechanics wants float64; jaxdyn never sets it

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import jaxdyn


# --- The system: energies only. Parameters p are a pytree (here a dict) passed to every ---
# --- callback, never closed over, so that jax.grad / jax.vmap / optax see them.          ---
def kinetic(q, qd, p):
    th1, th2 = q
    w1, w2 = qd
    m1, m2, l1, l2 = p["m1"], p["m2"], p["l1"], p["l2"]
    return (
        0.5 * (m1 + m2) * l1**2 * w1**2
        + 0.5 * m2 * l2**2 * w2**2
        + m2 * l1 * l2 * w1 * w2 * jnp.cos(th1 - th2)
    )


def potential(q, p):
    th1, th2 = q
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    return -(m1 + m2) * g * l1 * jnp.cos(th1) - m2 * g * l2 * jnp.cos(th2)


pendulum = jaxdyn.Lagrangian(kinetic, potential)
p = {"m1": 1.0, "m2": 1.0, "l1": 1.0, "l2": 1.0, "g": 9.81}
q0 = jnp.array([2.0, 2.5])  # rad: high-energy, chaotic motion
qd0 = jnp.array([0.0, 0.0])  # rad/s
t1 = 20.0
ts = jnp.linspace(0.0, t1, 2001)


def rule(title):
    print(f"\n== {title} " + "=" * max(3, 72 - len(title)))


rule("Double pendulum, 20 s, default solver (Dopri8, rtol = atol = 1e-10), float64")

# The first call traces and compiles; later calls with the same shapes reuse the compiled solve
# (parameter values are traced, so changing them does not recompile).
start = time.perf_counter()
sol = jaxdyn.simulate(pendulum, q0, qd0, p, t1=t1, ts=ts)
jax.block_until_ready(sol)
compile_and_run = time.perf_counter() - start

runs = []
for _ in range(5):
    start = time.perf_counter()
    sol = jaxdyn.simulate(pendulum, q0, qd0, p, t1=t1, ts=ts)
    jax.block_until_ready(sol)
    runs.append(time.perf_counter() - start)
run = sorted(runs)[len(runs) // 2]

energy = pendulum.energy(sol.ts, sol.q, sol.qd, p)  # broadcasts over the whole trajectory
rel_energy_error = jnp.max(jnp.abs(energy - energy[0])) / jnp.abs(energy[0])

print(f"  steps taken             : {int(sol.num_steps)} "
      f"({int(sol.num_accepted_steps)} accepted, {int(sol.num_rejected_steps)} rejected)")
print(f"  energy E(0)             : {float(energy[0]):.6f} J")
print(f"  max|E(t)-E(0)|/|E(0)|   : {float(rel_energy_error):.2e}")
print(f"  first call (compile+run): {compile_and_run:8.3f} s")
print(f"  later calls (run only)  : {run * 1e3:8.2f} ms  (median of {len(runs)})")
print(f"  final angles            : θ1 = {float(sol.q[-1, 0]):+.6f}, "
      f"θ2 = {float(sol.q[-1, 1]):+.6f} rad")


# --- A gradient through the simulation --------------------------------------------------
# Loss: mean squared horizontal position of the lower mass over the first 2 s. (Over 20 s
# this chaotic system's sensitivities grow by many orders of magnitude; a short horizon keeps
# the finite-difference comparison meaningful.)
rule("Gradient of a trajectory loss w.r.t. l2: autodiff vs finite difference")
ts_loss = jnp.linspace(0.0, 2.0, 201)


def loss(l2):
    params = dict(p, l2=l2)
    s = jaxdyn.simulate(pendulum, q0, qd0, params, t1=2.0, ts=ts_loss)
    x2 = params["l1"] * jnp.sin(s.q[:, 0]) + l2 * jnp.sin(s.q[:, 1])
    return jnp.mean(x2**2)


l2 = jnp.asarray(p["l2"])
grad_loss = jax.jit(jax.grad(loss))
start = time.perf_counter()
g_ad = float(grad_loss(l2))
grad_compile = time.perf_counter() - start
start = time.perf_counter()
g_ad = float(grad_loss(l2))
grad_run = time.perf_counter() - start

h = 1e-5
loss_jit = jax.jit(loss)
g_fd = float((loss_jit(l2 + h) - loss_jit(l2 - h)) / (2 * h))

print(f"  {f'loss at l2 = {float(l2)} m':24s}: {float(loss_jit(l2)):+.10f}")
print(f"  dloss/dl2, autodiff     : {g_ad:+.10f}")
print(f"  dloss/dl2, central FD   : {g_fd:+.10f}   (h = {h:g})")
print(f"  relative difference     : {abs(g_ad - g_fd) / abs(g_fd):.1e}")
print(f"  grad: first call {grad_compile:.2f} s (compile+run), then {grad_run * 1e3:.1f} ms")


# --- Plot ----------------------------------------------------------------------------------
x1 = p["l1"] * jnp.sin(sol.q[:, 0])
y1 = -p["l1"] * jnp.cos(sol.q[:, 0])
x2 = x1 + p["l2"] * jnp.sin(sol.q[:, 1])
y2 = y1 - p["l2"] * jnp.cos(sol.q[:, 1])

fig, (ax_path, ax_energy) = plt.subplots(1, 2, figsize=(11, 4.5))
ax_path.plot(x2, y2, lw=0.6, color="tab:blue", label="mass 2")
ax_path.plot(x1, y1, lw=0.8, color="tab:orange", label="mass 1")
ax_path.plot([0.0, x1[0], x2[0]], [0.0, y1[0], y2[0]], "k-o", ms=4, label="t = 0")
ax_path.set_aspect("equal")
ax_path.set_xlabel("x [m]")
ax_path.set_ylabel("y [m]")
ax_path.set_title("Double pendulum, 0–20 s", pad=16)
ax_path.legend(loc="lower left", fontsize=8)

ax_energy.plot(sol.ts, (energy - energy[0]) / jnp.abs(energy[0]), lw=0.8)
ax_energy.set_xlabel("t [s]")
ax_energy.set_ylabel("(E(t) − E(0)) / |E(0)|")
ax_energy.set_title("Relative energy error (Dopri8, rtol = atol = 1e-10)", pad=16)
ax_energy.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
fig.tight_layout()
fig.savefig("double_pendulum.png", dpi=120)
rule("Plot")
print("  wrote double_pendulum.png")
