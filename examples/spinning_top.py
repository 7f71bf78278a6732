"""jaxdyn example: a heavy symmetric top with its tip fixed at the origin.

Coordinates are the classical Euler angles q = (ψ, θ, φ) ("zxz": precession, nutation, spin);
the orientation is R = R_z(ψ) R_x(θ) R_z(φ) and the centre of mass sits at distance h along
the symmetry axis, r_G = R e_z h. The body is a `jaxdyn.RigidBody` (inertia about the centre of
mass: I₁ᶜ, I₁ᶜ, I₃), so about the tip I₁ = I₁ᶜ + m h².

The script

1. forms the equations three ways from one `MultibodySystem` — Lagrange (`Lagrangian.from_system`),
   Gibbs–Appell and Kane (speeds u = q̇) — and compares their accelerations with each other and
   with the closed-form equations of the heavy symmetric top,

       I₁ θ̈ = I₁ ψ̇² sin θ cos θ − I₃ ω₃ ψ̇ sin θ + m g h sin θ,   ω₃ = φ̇ + ψ̇ cos θ,
       ψ̈ sin θ = (I₃ ω₃ θ̇ − 2 I₁ ψ̇ θ̇ cos θ) / I₁,   φ̈ = −ψ̈ cos θ + ψ̇ θ̇ sin θ;

2. simulates a fast top with each formulation and reports the drift of the three first integrals,
   energy E, angular momentum about the vertical p_ψ = I₁ ψ̇ sin²θ + I₃ ω₃ cos θ and about the
   symmetry axis p_φ = I₃ ω₃;
3. compares the measured mean precession rate with the gyroscopic approximation
   Ω ≈ m g h / (I₃ ω₃) (and with the slow root of the steady-precession condition
   I₁ Ω² cos θ − I₃ ω₃ Ω + m g h = 0).

Run:  python examples/spinning_top.py       (writes spinning_top.png in the current directory)
"""

import time

import jax

jax.config.update("jax_enable_x64", True)  # mechanics wants float64; jaxdyn never sets it

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn
from jaxdyn.rotations import euler_angles

# A small top: 0.5 kg, centre of mass 4 cm above the tip, I₃ = ½ m R² for R = 5 cm.
P = {"m": 0.5, "h": 0.04, "I1c": 4.0e-4, "I3": 6.25e-4, "g": 9.81}


def orientation(q, p):
    return euler_angles(q, "zxz")


def position(q, p):
    return orientation(q, p) @ jnp.array([0.0, 0.0, p["h"]])


def inertia(p):
    return jnp.diag(jnp.stack([p["I1c"], p["I1c"], p["I3"]]))


top = jaxdyn.RigidBody(mass=lambda p: p["m"], inertia=inertia, position=position,
                       orientation=orientation)
system = jaxdyn.MultibodySystem([top], gravity=lambda p: jnp.array([0.0, 0.0, -p["g"]]))
FORMULATIONS = {
    "Lagrangian": jaxdyn.Lagrangian.from_system(system),
    "GibbsAppell": jaxdyn.GibbsAppell.from_system(system),
    "Kane": jaxdyn.Kane.from_system(system),
}


def tip_inertia(p):
    """(I₁, I₃) about the tip."""
    return p["I1c"] + p["m"] * p["h"] ** 2, p["I3"]


def closed_form_accelerations(q, qd, p):
    _, theta, _ = q
    psi_d, theta_d, phi_d = qd
    i1, i3 = tip_inertia(p)
    mgh = p["m"] * p["g"] * p["h"]
    s, c = jnp.sin(theta), jnp.cos(theta)
    omega3 = phi_d + psi_d * c
    theta_dd = (i1 * psi_d**2 * s * c - i3 * omega3 * psi_d * s + mgh * s) / i1
    psi_dd = (i3 * omega3 * theta_d - 2 * i1 * psi_d * theta_d * c) / (i1 * s)
    phi_dd = -psi_dd * c + psi_d * theta_d * s
    return jnp.stack([psi_dd, theta_dd, phi_dd])


def first_integrals(q, qd, p):
    """(E, p_ψ, p_φ) in closed form."""
    _, theta, _ = q
    psi_d, theta_d, phi_d = qd
    i1, i3 = tip_inertia(p)
    s, c = jnp.sin(theta), jnp.cos(theta)
    omega3 = phi_d + psi_d * c
    energy = (0.5 * i1 * (theta_d**2 + psi_d**2 * s**2) + 0.5 * i3 * omega3**2
              + p["m"] * p["g"] * p["h"] * c)
    return jnp.stack([energy, i1 * psi_d * s**2 + i3 * omega3 * c, i3 * omega3])


def max_rel(a, b):
    return float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))


def rule(title):
    print(f"\n== {title} " + "=" * max(3, 72 - len(title)))


np.set_printoptions(precision=10, linewidth=110)

# -- 1. Three formulations and the closed form at a generic state --------------------------
rule("Accelerations q̈ = (ψ̈, θ̈, φ̈) at a generic state")
q = jnp.array([0.3, 0.7, -0.4])
qd = jnp.array([1.3, -0.8, 40.0])
reference = closed_form_accelerations(q, qd, P)
acc = {name: dyn.accelerations(0.0, q, qd, P) for name, dyn in FORMULATIONS.items()}
print(f"{'closed form':12s} {np.asarray(reference)}")
for name, a in acc.items():
    print(f"{name:12s} {np.asarray(a)}   max rel. diff. to closed form {max_rel(a, reference):.1e}")
names = list(acc)
for i, a in enumerate(names):
    for b in names[i + 1:]:
        print(f"max relative difference {a} vs {b}: {max_rel(acc[a], acc[b]):.2e}")
integrals = first_integrals(q, qd, P)
lagrangian = FORMULATIONS["Lagrangian"]
print(f"energy: closed form {float(integrals[0]):.12f}, Lagrangian.energy "
      f"{float(lagrangian.energy(0.0, q, qd, P)):.12f}")
momenta = lagrangian.momentum(0.0, q, qd, P)
print(f"momenta ∂L/∂q̇ = {np.asarray(momenta)}; closed form p_ψ = {float(integrals[1]):.12f},"
      f" p_φ = {float(integrals[2]):.12f}")

# -- 2. A fast top: simulate with each formulation -----------------------------------------
i1, i3 = tip_inertia(P)
mgh = P["m"] * P["g"] * P["h"]
theta0, spin = 0.5, 150.0  # released with ψ̇ = θ̇ = 0, spinning at 150 rad/s
q0 = jnp.array([0.0, theta0, 0.0])
qd0 = jnp.array([0.0, 0.0, spin])
t1 = 6.0
ts = jnp.linspace(0.0, t1, 6001)
rule(f"Fast top, θ₀ = {theta0}, ω₃ = {spin} rad/s, {t1} s, Dopri8 rtol = atol = 1e-10")
sols = {}
for name, dyn in FORMULATIONS.items():
    start = time.perf_counter()
    sol = jaxdyn.simulate(dyn, q0, qd0, P, t1=t1, ts=ts, rtol=1e-10, atol=1e-10)
    sol.q.block_until_ready()
    elapsed = time.perf_counter() - start
    sols[name] = sol
    ints = jax.vmap(first_integrals, in_axes=(0, 0, None))(sol.q, sol.qd, P)
    drift = jnp.max(jnp.abs(ints - ints[0]), axis=0)
    scales = jnp.array([jnp.abs(ints[0, 0]), jnp.abs(ints[0, 2]), jnp.abs(ints[0, 2])])
    e_lib = lagrangian.energy(sol.ts, sol.q, sol.qd, P)
    print(f"{name:12s} {int(sol.num_steps)} steps, {elapsed:.2f} s (incl. compile); relative "
          f"drift: E {float(drift[0] / scales[0]):.1e}, p_ψ {float(drift[1] / scales[1]):.1e}, "
          f"p_φ {float(drift[2] / scales[2]):.1e}; "
          f"library energy vs closed form {float(jnp.max(jnp.abs(e_lib - ints[:, 0]))):.1e}")
print("(p_ψ drift relative to p_φ = I₃ω₃, the angular momentum scale)")
for name in names[1:]:
    dq = jnp.max(jnp.abs(sols[name].q[-1] - sols["Lagrangian"].q[-1]))
    print(f"final state {name} vs Lagrangian: max |Δq| = {float(dq):.2e} rad")

# -- 3. Mean precession vs the gyroscopic approximation ------------------------------------
rule("Precession rate of the fast top")
sol = sols["Lagrangian"]
omega3 = float(first_integrals(sol.q[0], sol.qd[0], P)[2] / i3)
gyroscopic = mgh / (i3 * omega3)
slow_root = (i3 * omega3 - np.sqrt((i3 * omega3) ** 2 - 4 * i1 * np.cos(theta0) * mgh)) / (
    2 * i1 * np.cos(theta0))
# Mean over a whole number of nutation periods: from the first to the last minimum of ψ̇.
psi_d = np.asarray(sol.qd[:, 0])
minima = np.where((psi_d[1:-1] <= psi_d[:-2]) & (psi_d[1:-1] < psi_d[2:]))[0] + 1
first, last = minima[0], minima[-1]
measured = float((sol.q[last, 0] - sol.q[first, 0]) / (sol.ts[last] - sol.ts[first]))
nutation_freq = 2 * np.pi * (len(minima) - 1) / float(sol.ts[last] - sol.ts[first])
print(f"nutation: {len(minima) - 1} periods, measured frequency {nutation_freq:.3f} rad/s "
      f"(leading-order fast-top estimate I₃ω₃/I₁ = {i3 * omega3 / i1:.3f})")
print(f"nutation amplitude: θ ∈ [{float(sol.q[:, 1].min()):.6f}, {float(sol.q[:, 1].max()):.6f}]"
      f" rad (estimate θ₀ + 2 I₁ m g h sin θ₀/(I₃ω₃)² = "
      f"{theta0 + 2 * i1 * mgh * np.sin(theta0) / (i3 * omega3) ** 2:.6f})")
print(f"measured mean precession rate      Ω = {measured:.6f} rad/s")
print(f"gyroscopic approximation m g h/(I₃ω₃) = {gyroscopic:.6f} rad/s  "
      f"(relative difference {abs(measured - gyroscopic) / gyroscopic:.2e})")
print(f"steady slow-precession root            = {slow_root:.6f} rad/s  "
      f"(relative difference {abs(measured - slow_root) / slow_root:.2e})")

# -- Plot ----------------------------------------------------------------------------------
axis = jax.vmap(lambda q: orientation(q, P)[:, 2])(sol.q)  # symmetry axis in world axes
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5))
ax0.plot(axis[:, 0], axis[:, 1], lw=0.6)
ax0.set_aspect("equal")
ax0.set_title("symmetry axis seen from above (unit sphere)")
ax0.set_xlabel("x")
ax0.set_ylabel("y")
window = sol.ts <= 0.5
ax1.plot(sol.ts[window], sol.q[window, 1], label="θ (nutation)")
ax1.set_xlabel("t [s]")
ax1.set_ylabel("θ [rad]")
ax1b = ax1.twinx()
ax1b.plot(sol.ts[window], sol.qd[window, 0], color="C1", lw=0.8, label="dψ/dt (precession rate)")
ax1b.axhline(gyroscopic, color="C2", ls="--", lw=0.8, label="m g h / (I3 ω3)")
ax1b.set_ylabel("dψ/dt [rad/s]")
ax1.legend(loc="upper left")
ax1b.legend(loc="upper right")
ax1.set_title("first 0.5 s")
fig.tight_layout()
fig.savefig("spinning_top.png", dpi=110)
print("\nwrote spinning_top.png")
