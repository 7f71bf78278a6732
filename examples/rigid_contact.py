"""jaxdyn example: rigid contact with Coulomb friction, as events.

`jaxdyn.RigidContact` treats contact points as rigid unilateral contacts: impacts by Newton's
and Coulomb's laws (Glocker's frictional impact law), resting contacts that stick or slide,
and every switch (landing, lift-off, slip, stop) a located event. The motion between events
is smooth, so the closed forms hold to the solver's precision. The script

1. throws a solid ball down spinning onto the ground: with ample friction the first impact
   stops its contact point slipping, v_x⁺ = v_x − (2/7)(v_x − r ω_y); with little friction it
   slips, the tangential impulse μ Λ_N. Either way the ball bounces into rest and rolls off at
   (5 v_x + 2 r ω_y)/7, as its angular momentum about the contact point, kept by every
   impact, requires (μ is a parameter, so both runs share one compiled program);
2. pushes a box flat on its four lower corners across the floor: it stops after
   v₀²/(2 μ g) at t = v₀/(μ g) and sticks, its corners carrying its weight;
3. differentiates where a pushed block stops with respect to μ, through the event that stops
   it, against −v₀²/(2 μ² g).

Run:  python examples/rigid_contact.py
"""

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np

import jaxdyn

G = 9.81
SOLVE = dict(rtol=1e-10, atol=1e-10)


def free_body(name, mass, inertia):
    return jaxdyn.ArticulatedBody(jaxdyn.RigidBodyTree(
        [jaxdyn.Link(name, jaxdyn.Free(), mass=mass, inertia=inertia)],
        gravity=jnp.array([0.0, 0.0, -G])))


def world_speeds(q, u):
    """(v, ω) in the world from a free body's speeds in its own axes."""
    turn = jaxdyn.rotations.quaternion(q[3:7])
    return turn @ u[:3], turn @ u[3:]


# -- 1. a spinning ball struck onto the ground ------------------------------------------------
M, R, E = 0.5, 0.1, 0.5
ball = free_body("ball", M, 0.4 * M * R * R * jnp.eye(3))
q0 = jnp.array([0.0, 0.0, R + 0.05, 1.0, 0.0, 0.0, 0.0])
u0 = jnp.array([1.0, 0.0, -2.0, 0.0, 30.0, 0.0])  # forward, down, spinning backwards
ground = jaxdyn.RigidContact([jaxdyn.ContactPoint("ball", radius=R)], restitution=E,
                             friction=lambda p: p["mu"])
for mu in (1.0, 0.1):
    start = time.perf_counter()
    sol = jaxdyn.simulate(ball, q0, u0, {"mu": mu}, t1=1.0, events=[ground], max_events=32,
                          **SOLVE)
    count = int(sol.events.count)
    print(f"ball, μ = {mu}: {count} events in {time.perf_counter() - start:.1f} s (compiling "
          "included)")
    v, w = world_speeds(sol.events.q_minus[0], sol.events.u_minus[0])
    v_plus, w_plus = world_speeds(sol.events.q_plus[0], sol.events.u_plus[0])
    normal, tangential = np.asarray(sol.events.impulses[0])
    slip = v[0] - R * w[1]
    stick = 2 / 7 * M * abs(slip)  # the tangential impulse that stops the slip
    expected = (v[0] - 2 / 7 * slip if stick <= mu * normal
                else v[0] - mu * normal / M * np.sign(slip))
    print(f"  first impact: Λ_N = {normal:.6f} (m (1 + e)|v_z⁻| = {M * (1 + E) * -v[2]:.6f}), "
          f"‖Λ_T‖ = {tangential:.6f} ({'sticks' if stick <= mu * normal else 'slips'}: "
          f"{min(stick, mu * normal):.6f})")
    print(f"  v_x after it {v_plus[0]:.6f} (closed form {expected:.6f})")
    last = count - 1
    print(f"  at rest on the ground from t = {sol.events.t[last]:.4f} s, "
          f"{'rolling' if bool(sol.events.resting[last, 1]) else 'sliding'} at "
          f"{float(world_speeds(sol.q[-1], sol.u[-1])[0][0]):.6f} m/s "
          f"((5 v_x + 2 r ω_y)/7 = {(5 * u0[0] + 2 * R * u0[4]) / 7:.6f})")

# -- 2. a box pushed across the floor on four corners -----------------------------------------
MU, V0 = 0.5, 2.0
a, b, h = 0.2, 0.1, 0.05
box = free_body("box", 1.0, 1.0 / 12 * jnp.diag(jnp.array([b * b + h * h, a * a + h * h,
                                                           a * a + b * b])))
corners = jaxdyn.box_corners("box", (a, b, h))[::2]  # the four with z = −h/2
ts = np.linspace(0.0, 0.6, 7)
start = time.perf_counter()
sol = jaxdyn.simulate(box, jnp.array([0.0, 0.0, h / 2, 1.0, 0.0, 0.0, 0.0]),
                      jnp.array([V0, 0.0, 0.0, 0.0, 0.0, 0.0]), t1=ts[-1], ts=ts,
                      events=[jaxdyn.RigidContact(corners, friction=MU)], max_events=8,
                      **SOLVE)
count = int(sol.events.count)
print(f"box: {count} events in {time.perf_counter() - start:.1f} s (compiling included)")
print(f"  stops at t = {sol.events.t[count - 1]:.10f} s (v₀/(μ g) = {V0 / (MU * G):.10f}), "
      f"x = {sol.q[-1, 0]:.10f} m (v₀²/(2 μ g) = {V0**2 / (2 * MU * G):.10f})")
print(f"  all four corners stick: {bool(np.all(sol.events.resting[count - 1]))}; normal "
      f"forces {np.round(np.asarray(sol.events.normal_forces[-1, :4]), 4)} N, summing to "
      f"{float(np.sum(sol.events.normal_forces[-1, :4])):.10f} (m g = {G})")

# -- 3. the derivative of where a block stops ------------------------------------------------
particle = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: G * q[2])
floor = jaxdyn.RigidContact([jaxdyn.ContactPoint(lambda q, p: q)], friction=lambda p: p["mu"])


def stop(mu):
    sol = jaxdyn.simulate(particle, jnp.zeros(3), jnp.array([V0, 0.0, 0.0]), {"mu": mu},
                          t1=0.5, events=[floor], max_events=4, **SOLVE)
    return sol.q[-1, 0]


print(f"block: d(stop)/dμ = {float(jax.grad(stop)(MU)):.10f} "
      f"(−v₀²/(2 μ² g) = {-V0**2 / (2 * MU**2 * G):.10f})")
