"""Fast equations of motion: what jaxdyn's speed looks like from the user's side.

An elastic pendulum (worked example 25.2) given by its energies, against the same equations
written by hand:

1. direct calls compile once: a second call with new values (parameters as Python floats) is
   a dispatch, not a compilation;
2. `jax.jit` of a bound method, and `accelerations` inside a loop of your own (a hand-rolled
   symplectic Euler), against the closed form in the same loop: inside your trace the default
   check costs nothing (a failure is NaN), `throw=True` keeps a branch that raises;
3. a whole `simulate` against `diffrax.diffeqsolve` on the hand-written right-hand side;
4. what happens where the equations fail (r = 0: the mass matrix diag(m, m r²) is singular):
   an error naming the state when called with values, NaN inside your own `jax.jit`, and
   `diagnose` naming the cause of that NaN.

Run:  python examples/fast_equations.py
"""

import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxdyn  # noqa: E402


def kinetic(q, qd, p):
    return 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def potential(q, p):
    return -p["m"] * p["g"] * q[0] * jnp.cos(q[1]) + 0.5 * p["k"] * (q[0] - p["l0"]) ** 2


def by_hand(t, q, qd, p):  # the elastic pendulum's textbook equations, solved for (r̈, θ̈)
    m, g, k, l0 = p["m"], p["g"], p["k"], p["l0"]
    return jnp.stack([q[0] * qd[1] ** 2 + g * jnp.cos(q[1]) - k / m * (q[0] - l0),
                      -(2 * qd[0] * qd[1] + g * jnp.sin(q[1])) / q[0]])


pendulum = jaxdyn.Lagrangian(kinetic, potential)
p = {"m": 0.9, "g": 9.81, "k": 35.0, "l0": 1.2}
q, qd = jnp.array([1.3, 0.4]), jnp.array([0.2, -0.5])


def best_of(fn, repeat=7, number=1):
    samples = []
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(number):
            out = fn()
        jax.block_until_ready(out)
        samples.append((time.perf_counter() - start) / number)
    return statistics.median(samples)


print("1. direct calls compile once")
start = time.perf_counter()
jax.block_until_ready(pendulum.accelerations(0.0, q, qd, p))
print(f"   first call (traces and compiles):   {1e3 * (time.perf_counter() - start):7.1f} ms")
new_p = {"m": 1.1, "g": 9.81, "k": 20.0, "l0": 1.0}  # new values, same structure
later = best_of(lambda: pendulum.accelerations(0.5, q + 0.1, qd, new_p), number=100)
print(f"   later calls, new state and values: {1e6 * later:7.1f} µs")
gap = float(jnp.max(jnp.abs(pendulum.accelerations(0.0, q, qd, p) - by_hand(0.0, q, qd, p))))
print(f"   agree with the hand-written equations: {gap:.1e}")

print("\n2. inside your own compiled loop (symplectic Euler, 100 000 steps of 1 ms)")


def integrate(accelerations):
    @jax.jit
    def run(q, qd):
        def step(_, state):
            q, qd = state
            qd = qd + 1e-3 * accelerations(0.0, q, qd, p)
            return q + 1e-3 * qd, qd
        return jax.lax.fori_loop(0, 100_000, step, (q, qd))
    return run


loops = {"hand-written": integrate(by_hand),
         "jaxdyn": integrate(pendulum.accelerations),
         "jaxdyn, throw=True": integrate(lambda *a: pendulum.accelerations(*a, throw=True))}
for run in loops.values():
    jax.block_until_ready(run(q, qd))
times = {name: best_of(lambda run=run: run(q, qd)) for name, run in loops.items()}
for name, seconds in times.items():
    print(f"   {name:20s} {1e9 * seconds / 100_000:6.1f} ns per step   "
          f"({seconds / times['hand-written']:.2f}× hand-written)")
final = {name: run(q, qd)[0] for name, run in loops.items()}
print(f"   final states agree to "
      f"{float(jnp.max(jnp.abs(final['jaxdyn'] - final['hand-written']))):.1e}")
jitted = jax.jit(pendulum.accelerations)  # a bound method can be jitted directly
print(f"   jax.jit(pendulum.accelerations) → {jitted(0.0, q, qd, p)}")

print("\n3. a whole trajectory (Tsit5 at 1e-8, 10 s) against diffrax on the hand-written equations")


def field(t, y, p):  # defined once: a new function each call would recompile the solve
    return y[1], by_hand(t, y[0], y[1], p)


def hand_solve(p):
    return diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, 10.0, None, (q, qd),
                               args=p, stepsize_controller=diffrax.PIDController(rtol=1e-8,
                                                                                 atol=1e-8))


def jaxdyn_solve(p):
    return jaxdyn.simulate(pendulum, q, qd, p, t1=10.0, solver=diffrax.Tsit5(), rtol=1e-8,
                           atol=1e-8)


hand_time = best_of(lambda: hand_solve(p).ys)
ours_time = best_of(lambda: jaxdyn_solve(p).q)
print(f"   diffrax, hand-written: {1e3 * hand_time:6.2f} ms   jaxdyn.simulate: "
      f"{1e3 * ours_time:6.2f} ms   ({ours_time / hand_time:.2f}×)")

print("\n4. where the equations fail (r = 0)")
r0 = jnp.array([0.0, 0.4])
try:
    pendulum.accelerations(0.0, r0, qd, p)
except RuntimeError as error:
    print("   called with values: " + str(error).splitlines()[0])
    print("                       " + str(error).splitlines()[-1])
print(f"   inside jax.jit:     {jax.jit(pendulum.accelerations)(0.0, r0, qd, p)}")
print("   diagnose:           " + pendulum.diagnose(0.0, r0, qd, p).splitlines()[0])
