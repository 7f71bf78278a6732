"""jaxdyn example: a thin uniform disc rolling without slipping on a horizontal plane.

A nonholonomic system: five coordinates, three independent speeds.

    q = (x, y, ψ, θ, φ)   contact point (x, y) on the floor, yaw ψ, lean θ, spin φ
    u = (ψ̇, θ̇, φ̇)

The disc's orientation is R = R_z(ψ) R_x(θ) R_y(φ) (`euler_angles(..., "zxy")`): its symmetry
axis is the body y axis, ψ turns the heading a₁ = (cos ψ, sin ψ, 0) about the vertical, θ leans
the disc about the heading, and φ spins it about its own axis. The centre is
G = (x, y, 0) + r c₃ with c₃ = R_z(ψ) R_x(θ) e_z the in-plane direction from the contact point
up to the centre.

Rolling without slipping (the material point of the disc at the contact has zero velocity)
reduces, with this choice of coordinates, to

    ẋ = r φ̇ cos ψ,   ẏ = r φ̇ sin ψ

(a ψ̇ or θ̇ alone turns the disc about the contact point), so the kinematic map q̇ = K(q) u is

        ⎡0 0 r cos ψ⎤
        ⎢0 0 r sin ψ⎥
    K = ⎢1 0   0    ⎥
        ⎢0 1   0    ⎥
        ⎣0 0   1    ⎦

Gibbs–Appell and Kane are both formed from the same `MultibodySystem` with this map (Lagrange's
equations of the second kind do not apply: the constraint is not integrable). The script checks

1. the accelerations of the two formulations against each other at a generic state;
2. steady rolling in a circle: for lean θ₀ and yaw rate Ω the rolling rate ω₂ = φ̇ + Ω sin θ₀
   that makes the motion steady follows from Newton–Euler about the centre,

       A Ω² sin θ₀ cos θ₀ − (C + m r²) Ω ω₂ cos θ₀ = m g r sin θ₀,

   (A = m r²/4, C = m r²/2 the diametral and axial moments of inertia); there all accelerations
   must vanish, and a simulation must stay on the circle;
3. the stability of upright straight rolling at rolling rate ω₀: linearised, the lean obeys
   (A + m r²) θ̈ = −[(C + m r²) C ω₀²/A − m g r] θ, stable for ω₀² > m g r A / (C (C + m r²))
   = g / (3 r); the eigenvalues of the Jacobian of the jaxdyn dynamics are compared with it;
4. a simulated wobbling motion with both formulations: energy drift, the difference of the
   final states, and the slip velocity of the contact point along the trajectory.

Run:  python examples/rolling_disc.py
"""

import time

import jax

jax.config.update("jax_enable_x64", True)  # mechanics wants float64; jaxdyn never sets it

import jax.numpy as jnp
import numpy as np

import jaxdyn
from jaxdyn.rotations import euler_angles, rotation_x, rotation_z

P = {"m": 2.0, "r": 0.15, "g": 9.81}


def moments(p):
    """(A, C): diametral and axial moments of inertia of a thin uniform disc about its centre."""
    return 0.25 * p["m"] * p["r"] ** 2, 0.5 * p["m"] * p["r"] ** 2


def up_in_plane(q):
    """c₃: unit vector in the disc plane from the contact point to the centre (world axes)."""
    return rotation_z(q[2]) @ rotation_x(q[3]) @ jnp.array([0.0, 0.0, 1.0])


def centre(q, p):
    return jnp.array([q[0], q[1], 0.0]) + p["r"] * up_in_plane(q)


def orientation(q, p):
    return euler_angles(q[2:5], "zxy")


def inertia(p):
    a, c = moments(p)
    return jnp.diag(jnp.array([a, c, a]))  # symmetry axis = body y


def kinematic_map(q, p):
    """q̇ = K(q) u for u = (ψ̇, θ̇, φ̇), with the rolling constraint built in."""
    r, psi = p["r"], q[2]
    zero, one = jnp.zeros_like(psi), jnp.ones_like(psi)
    return jnp.array([
        [zero, zero, r * jnp.cos(psi)],
        [zero, zero, r * jnp.sin(psi)],
        [one, zero, zero],
        [zero, one, zero],
        [zero, zero, one],
    ])


disc = jaxdyn.RigidBody(mass=lambda p: p["m"], inertia=inertia, position=centre,
                        orientation=orientation)
system = jaxdyn.MultibodySystem([disc], gravity=lambda p: jnp.array([0.0, 0.0, -p["g"]]))
gibbs_appell = jaxdyn.GibbsAppell.from_system(system, kinematic_map)
kane = jaxdyn.Kane.from_system(system, kinematic_map)
FORMULATIONS = {"GibbsAppell": gibbs_appell, "Kane": kane}


def slip_velocity(q, qd, p):
    """Velocity of the material point of the disc at the contact, v_G + ω × (P − G), computed
    from the body kinematics alone (independently of K)."""
    v_g = jax.jvp(lambda q: centre(q, p), (q,), (qd,))[1]
    rot, rot_dot = jax.jvp(lambda q: orientation(q, p), (q,), (qd,))
    omega_skew = rot_dot @ rot.T  # [ω]× in world axes
    omega = jnp.array([omega_skew[2, 1], omega_skew[0, 2], omega_skew[1, 0]])
    return v_g + jnp.cross(omega, -p["r"] * up_in_plane(q))


def energy(q, u, p):
    qd = kinematic_map(q, p) @ u
    t = jnp.zeros((), q.dtype)
    return system.kinetic_energy(t, q, qd, p) + system.potential_energy(t, q, p)


def max_rel(a, b):
    return float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))


def rule(title):
    print(f"\n== {title} " + "=" * max(3, 72 - len(title)))


np.set_printoptions(precision=10, suppress=False, linewidth=110)
m, r, g = P["m"], P["r"], P["g"]
A, C = moments(P)

# -- 0. The kinematic map embeds the rolling constraint ------------------------------------
rule("Rolling constraint: slip velocity of K u for random states (should be ~1e-17)")
key = jax.random.PRNGKey(0)
qs = jax.random.normal(key, (200, 5))
us = 3.0 * jax.random.normal(jax.random.PRNGKey(1), (200, 3))
slips = jax.vmap(lambda q, u: slip_velocity(q, kinematic_map(q, P) @ u, P))(qs, us)
print(f"max |v_contact| / (r max|u|) over 200 random states: "
      f"{float(jnp.max(jnp.abs(slips)) / (r * jnp.max(jnp.abs(us)))):.2e}")

# -- 1. Gibbs–Appell vs Kane at a generic state --------------------------------------------
rule("Accelerations u̇ = (ψ̈, θ̈, φ̈) at a generic state")
q = jnp.array([0.3, -0.2, 0.4, 0.25, 1.1])
u = jnp.array([0.7, -0.3, 5.0])
acc = {name: dyn.accelerations(0.0, q, u, P) for name, dyn in FORMULATIONS.items()}
for name, a in acc.items():
    print(f"{name:12s} {np.asarray(a)}")
print(f"max relative difference GibbsAppell vs Kane: "
      f"{max_rel(acc['GibbsAppell'], acc['Kane']):.2e}")
mass_ga, mass_kane = gibbs_appell.mass_matrix(0.0, q, u, P), kane.mass_matrix(0.0, q, u, P)
print(f"mass matrices: max relative difference {max_rel(mass_ga, mass_kane):.2e}")

# -- 2. Steady rolling in a circle ---------------------------------------------------------
rule("Steady rolling in a circle")
theta0, yaw_rate = 0.3, -1.5  # lean (rad), yaw rate Ω (rad/s); Ω < 0 turns toward the lean
s0, c0 = np.sin(theta0), np.cos(theta0)
omega2 = (A * yaw_rate**2 * s0 * c0 - m * g * r * s0) / ((C + m * r**2) * yaw_rate * c0)
spin_rate = omega2 - yaw_rate * s0
print(f"lean θ₀ = {theta0}, yaw rate Ω = {yaw_rate} rad/s  ->  steady spin φ̇ = "
      f"{spin_rate:.10f} rad/s (rolling rate ω₂ = {omega2:.6f})")
q_steady = jnp.array([0.0, 0.0, 0.0, theta0, 0.0])
u_steady = jnp.array([yaw_rate, 0.0, spin_rate])
for name, dyn in FORMULATIONS.items():
    a = dyn.accelerations(0.0, q_steady, u_steady, P)
    print(f"{name:12s} u̇ at the steady state: {np.asarray(a)}  "
          f"(scale Ω² = {yaw_rate**2:.2f})")
period = 2 * np.pi / abs(yaw_rate)
ts = jnp.linspace(0.0, 3 * period, 301)
sol = jaxdyn.simulate(gibbs_appell, q_steady, u_steady, P, t1=ts[-1], ts=ts,
                      rtol=1e-10, atol=1e-10)
print(f"simulated 3 turns (GibbsAppell): max |θ − θ₀| = "
      f"{float(jnp.max(jnp.abs(sol.q[:, 3] - theta0))):.2e} rad, max |ψ̇ − Ω| = "
      f"{float(jnp.max(jnp.abs(sol.u[:, 0] - yaw_rate))):.2e}, max |φ̇ − φ̇₀| = "
      f"{float(jnp.max(jnp.abs(sol.u[:, 2] - spin_rate))):.2e}")
# The contact point runs on a circle of radius r φ̇/|Ω| (it moves at r φ̇ along the heading),
# the centre G on a concentric one of radius r ω₂/|Ω|, closer in by r sin θ₀.
circle_centre = jnp.array([0.0, r * spin_rate / yaw_rate])  # to the side the disc turns
contact_dist = jnp.linalg.norm(sol.q[:, :2] - circle_centre, axis=1)
g_dist = jnp.linalg.norm(jax.vmap(centre, in_axes=(0, None))(sol.q, P)[:, :2] - circle_centre,
                         axis=1)
for label, dist, expected in (("contact point", contact_dist, r * spin_rate / abs(yaw_rate)),
                              ("centre G     ", g_dist, r * omega2 / abs(yaw_rate))):
    print(f"{label} distance from the circle's centre: {float(dist.min()):.12f} .. "
          f"{float(dist.max()):.12f} m (expected {expected:.12f})")

# -- 3. Stability of upright straight rolling ----------------------------------------------
rule("Upright straight rolling: linear stability")
critical = np.sqrt(m * g * r * A / (C * (C + m * r**2)))
print(f"analytic critical rolling rate ω_c = sqrt(g / 3r) = {critical:.6f} rad/s "
      f"(speed {r * critical:.4f} m/s)")


def linearised(dyn, omega0):
    """The linear model about upright straight rolling with φ̇ = ω₀ (jaxdyn.linearise)."""
    return jaxdyn.linearise(dyn, 0.0, jnp.zeros(5), jnp.array([0.0, 0.0, omega0]), P)


for factor in (0.8, 1.25, 2.0):
    omega0 = factor * critical
    k_lean = ((C + m * r**2) * C * omega0**2 / A - m * g * r) / (A + m * r**2)
    line = f"ω₀ = {factor:4.2f} ω_c: analytic λ² = {-k_lean:+.8f};"
    for name, dyn in FORMULATIONS.items():
        model = linearised(dyn, omega0)
        eig = np.asarray(model.eigenvalues())
        lam = eig[np.argmax(np.abs(eig))]
        line += f" {name} λ² = {complex(lam**2).real:+.8f} ({model.stability()})"
    print(line)

# -- 4. A wobbling motion, both formulations -----------------------------------------------
rule("Wobbling motion, 10 s, Dopri8 rtol = atol = 1e-10, both formulations")
q0 = jnp.array([0.0, 0.0, 0.0, 0.2, 0.0])
u0 = jnp.array([0.5, 0.4, 9.0])
ts = jnp.linspace(0.0, 10.0, 2001)
sols = {}
for name, dyn in FORMULATIONS.items():
    start = time.perf_counter()
    sol = jaxdyn.simulate(dyn, q0, u0, P, t1=10.0, ts=ts, rtol=1e-10, atol=1e-10)
    sol.q.block_until_ready()
    elapsed = time.perf_counter() - start
    sols[name] = sol
    e = jax.vmap(energy, in_axes=(0, 0, None))(sol.q, sol.u, P)
    slip = jax.vmap(slip_velocity, in_axes=(0, 0, None))(sol.q, sol.qd, P)
    speed = r * jnp.max(jnp.abs(sol.u))
    print(f"{name:12s} {int(sol.num_steps)} steps, {elapsed:.2f} s (incl. compile); "
          f"energy drift max|E − E₀|/E₀ = {float(jnp.max(jnp.abs(e - e[0])) / e[0]):.2e}; "
          f"max slip |v_contact| = {float(jnp.max(jnp.linalg.norm(slip, axis=1))):.2e} m/s "
          f"(speed scale {float(speed):.2f} m/s)")
    print(f"{'':12s} lean θ ∈ [{float(sol.q[:, 3].min()):.4f}, {float(sol.q[:, 3].max()):.4f}]"
          f" rad, final q = {np.asarray(sol.q[-1])}")
dq = jnp.max(jnp.abs(sols["GibbsAppell"].q[-1] - sols["Kane"].q[-1]))
du = jnp.max(jnp.abs(sols["GibbsAppell"].u[-1] - sols["Kane"].u[-1]))
print(f"final state GibbsAppell vs Kane: max |Δq| = {float(dq):.2e}, max |Δu| = {float(du):.2e}")
