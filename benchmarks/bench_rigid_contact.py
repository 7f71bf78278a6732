"""Rigid contact with Coulomb friction (`jaxdyn.RigidContact`): a block pushed along the
ground slides to rest and sticks, against the same work written by hand in diffrax.

The block: a point mass released on the ground at 2 m/s, μ = 0.5, 1 s (it stops at
t = v₀/(μ g) = 0.408 s, after v₀²/(2 μ g) = 0.4077 m). jaxdyn: `simulate` with the particle's
T and V and a `RigidContact` at its position (events: met at rest at t = 0, the stop).
The floor: the sliding motion written by hand, ẋ = v, v̇ = −μ g, solved by
`diffrax.diffeqsolve` with a `diffrax.Event` on v (the same Newton root finder at 1e-12)
up to the stop, the block then still; Tsit5 at rtol = atol = 1e-10 both, under `jax.jit`.
Also the first calls of a free ball struck spinning onto the ground (16 events) and of a
box on four corners pushed to rest, each in a fresh process.

Run:  python benchmarks/bench_rigid_contact.py
"""

import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import optimistix as optx

import jaxdyn

G, MU, V0, T1 = 9.81, 0.5, 2.0, 1.0
TOL = dict(rtol=1e-10, atol=1e-10)
STOP = V0**2 / (2 * MU * G)


PARTICLE = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: G * q[2])
GROUND = jaxdyn.RigidContact([jaxdyn.ContactPoint(lambda q, p: q)], friction=lambda p: p["mu"])


def jaxdyn_block(mu):
    particle, ground = PARTICLE, GROUND
    sol = jaxdyn.simulate(particle, jnp.zeros(3), jnp.array([V0, 0.0, 0.0]), {"mu": mu},
                          t1=T1, events=[ground], max_events=4, solver=diffrax.Tsit5(), **TOL)
    return sol.q[-1, 0]


def hand_block(mu):
    def field(t, y, args):
        return jnp.stack([y[1], -mu * G])

    event = diffrax.Event(lambda t, y, args, **kwargs: y[1],
                          optx.Newton(rtol=1e-12, atol=1e-12))
    sol = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, T1, None,
                              jnp.array([0.0, V0]), event=event,
                              stepsize_controller=diffrax.PIDController(**TOL))
    return sol.ys[-1, 0]


def timed(fn, *args, repeats=200):
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - start
    compiled(*args).block_until_ready()
    start = time.perf_counter()
    for _ in range(repeats):
        value = compiled(*args)
    value.block_until_ready()
    return (time.perf_counter() - start) / repeats, compile_s, float(value)


def first_call(scene):
    """The first and a warm `simulate` of a scene, in a fresh process (the child's lines)."""
    code = f"""
import time, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import jaxdyn
G = 9.81
if "{scene}" == "ball":
    m, r = 0.5, 0.1
    body = jaxdyn.Link("ball", jaxdyn.Free(), mass=m, inertia=0.4 * m * r * r * jnp.eye(3))
    points, q0 = [jaxdyn.ContactPoint("ball", radius=r)], [0, 0, r + 0.05, 1.0, 0, 0, 0]
    u0, e, t1, n = [1.0, 0, -2.0, 0, 30.0, 0], 0.5, 1.0, 32
else:
    a, b, h = 0.2, 0.1, 0.05
    body = jaxdyn.Link("box", jaxdyn.Free(), mass=1.0, inertia=jnp.diag(jnp.array(
        [b * b + h * h, a * a + h * h, a * a + b * b])) / 12)
    points, q0 = jaxdyn.box_corners("box", (a, b, h))[::2], [0, 0, h / 2, 1.0, 0, 0, 0]
    u0, e, t1, n = [2.0, 0, 0, 0, 0, 0], 0.0, 0.6, 8
dynamics = jaxdyn.ArticulatedBody(jaxdyn.RigidBodyTree([body], gravity=jnp.array([0, 0, -G])))
contact = jaxdyn.RigidContact(points, restitution=e, friction=lambda p: p["mu"])
def run(mu):
    sol = jaxdyn.simulate(dynamics, jnp.array(q0), jnp.array(u0), {{"mu": mu}}, t1=t1,
                          events=[contact], max_events=n, rtol=1e-10, atol=1e-10)
    return jax.block_until_ready(sol)
start = time.perf_counter(); sol = run(0.5); first = time.perf_counter() - start
start = time.perf_counter(); run(0.6); warm = time.perf_counter() - start
print(f"{scene}", first, warm, int(sol.events.count))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[1]), float(out[2]), int(out[3])


def main():
    print(__doc__.split("\n\n")[1].replace("\n", " "))
    rows = {"jaxdyn, jax.jit(simulate)": timed(jaxdyn_block, MU),
            "hand-written diffrax with an Event (floor)": timed(hand_block, MU)}
    floor = rows["hand-written diffrax with an Event (floor)"][0]
    start = time.perf_counter()
    jaxdyn_block(MU).block_until_ready()
    first = time.perf_counter() - start
    start = time.perf_counter()
    moved = float(jaxdyn_block(MU * 1.001))
    plain = time.perf_counter() - start
    print(f"\n{'candidate':44s} {'run':>9s} {'/ floor':>8s} {'compile':>8s} {'stop error':>11s}")
    for name, (run, compile_s, value) in rows.items():
        print(f"{name:44s} {run * 1e3:7.3f}ms {run / floor:7.1f}× {compile_s:7.1f}s "
              f"{abs(value - STOP):11.1e}")
    print(f"{'jaxdyn as the README calls it (not jitted)':44s} {plain * 1e3:7.3f}ms "
          f"{plain / floor:7.1f}× {first:7.1f}s (first call) {abs(moved - STOP / 1.001):.1e}")
    print("\nfirst calls in fresh processes (simulate, not jitted):")
    for scene in ("ball", "box"):
        first, warm, events = first_call(scene)
        print(f"  {scene}: first call {first:.1f} s, then {warm * 1e3:.1f} ms ({events} events)")


if __name__ == "__main__":
    main()
