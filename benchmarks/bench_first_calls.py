"""First calls of `equilibrium` and `normal_modes`, each in a fresh process, beside diffrax's
first call on hand-written equations (issue "time to first result").

Rows, each measured in its own Python process (import excluded, float64, default options,
not jitted, as the README calls them):

- floor: `jax.jit` of `diffrax.diffeqsolve` (Tsit5, rtol = atol = 1e-8, 10 s) on the double
  pendulum's hand-written closed form (unit masses and lengths), first call;
- `normal_modes` of the double pendulum from T and V about the bottom: first call, then a
  call with a new g (a Python float);
- `equilibrium` of the cart-pole with the cart held at x = 0 (the input is solved for): first
  call, then calls from new guesses.

Run:  python benchmarks/bench_first_calls.py
"""

import json
import subprocess
import sys
import textwrap

PRELUDE = """
import json, time
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import jaxdyn
"""

FLOOR = """
import diffrax
def field(t, y, args):
    q1, q2, w1, w2 = y
    d = q1 - q2
    s, c = jnp.sin(d), jnp.cos(d)
    den = 2.0 - c * c  # m1 + m2 s², unit masses and lengths
    a1 = (-9.81 * 2 * jnp.sin(q1) - s * (w2**2 + w1**2 * c) + 9.81 * jnp.sin(q2) * c) / den
    a2 = (2 * w1**2 * s - 9.81 * 2 * jnp.sin(q2) + 9.81 * 2 * jnp.sin(q1) * c
          + w2**2 * s * c) / den
    return jnp.stack([w1, w2, a1, a2])
solve = jax.jit(lambda y0: diffrax.diffeqsolve(
    diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, 10.0, None, y0,
    stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8), max_steps=100000).ys)
start = time.perf_counter()
jax.block_until_ready(solve(jnp.array([1.0, 0.5, 0.0, 0.0])))
print(json.dumps({"first": time.perf_counter() - start}))
"""

MODES = """
pendulum = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * (qd[0]**2 + (qd[0] * jnp.cos(q[0]) + qd[1] * jnp.cos(q[1]))**2
                            + (qd[0] * jnp.sin(q[0]) + qd[1] * jnp.sin(q[1]))**2),
    lambda q, p: -p["g"] * (2 * jnp.cos(q[0]) + jnp.cos(q[1])))
times = []
for g in (9.81, 9.7, 9.6):
    start = time.perf_counter()
    jax.block_until_ready(jaxdyn.normal_modes(pendulum, 0.0, jnp.zeros(2), {"g": g}))
    times.append(time.perf_counter() - start)
print(json.dumps({"first": times[0], "later": max(times[1:])}))
"""

EQUILIBRIUM = """
def T(q, qd, p):
    return (0.5 * (p["M"] + p["m"]) * qd[0]**2 + p["m"] * p["l"] * qd[0] * qd[1] * jnp.cos(q[1])
            + 0.5 * p["m"] * p["l"]**2 * qd[1]**2)
def V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])
plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])
p = dict(M=1.0, m=0.1, l=0.5, g=9.81)
times = []
for guess in (0.1, 0.2, 0.3):
    start = time.perf_counter()
    jax.block_until_ready(jaxdyn.equilibrium(plant, jnp.array([0.0, guess]), p,
                                             prescribed={0: 0.0}).q)
    times.append(time.perf_counter() - start)
print(json.dumps({"first": times[0], "later": max(times[1:])}))
"""


def fresh(code):
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(PRELUDE + code)],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    floor = fresh(FLOOR)["first"]
    print(f"{'call':46s} {'first':>8s} {'/ floor':>8s} {'later':>9s}")
    print(f"{'diffrax on the hand-written double pendulum':46s} {floor:7.2f}s {1.0:7.2f}x")
    for name, code in (("normal_modes, double pendulum", MODES),
                       ("equilibrium, cart-pole held at x = 0", EQUILIBRIUM)):
        row = fresh(code)
        print(f"{name:46s} {row['first']:7.2f}s {row['first'] / floor:7.2f}x "
              f"{1e3 * row['later']:7.1f}ms")


if __name__ == "__main__":
    main()
