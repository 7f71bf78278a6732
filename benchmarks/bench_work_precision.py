"""Work–precision of the solvers `jaxdyn.simulate` can use, on a chaotic double pendulum.

Run: python benchmarks/bench_work_precision.py

For each solver and tolerance: the final-state error against a Dopri8 reference at
rtol = atol = 1e-13, the number of steps, and the run time after compilation (median of
rounds). All runs happen side by side in one process, so their ratios are comparable.
"""

import statistics
import time

import diffrax
import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402


def kinetic(q, qd, p):
    v1 = p["l1"] * qd[0] * jnp.array([jnp.cos(q[0]), jnp.sin(q[0])])
    v2 = v1 + p["l2"] * qd[1] * jnp.array([jnp.cos(q[1]), jnp.sin(q[1])])
    return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)


def potential(q, p):
    y1 = -p["l1"] * jnp.cos(q[0])
    y2 = y1 - p["l2"] * jnp.cos(q[1])
    return p["g"] * (p["m1"] * y1 + p["m2"] * y2)


def main(t1=10.0, rounds=7):
    system = jaxdyn.Lagrangian(kinetic, potential)
    p = {k: jnp.asarray(v) for k, v in dict(l1=1.0, l2=1.0, m1=1.0, m2=1.0, g=9.81).items()}
    q0, u0 = jnp.array([1.5, -1.0]), jnp.zeros(2)
    reference = jaxdyn.simulate(system, q0, u0, p, t1=t1, solver=diffrax.Dopri8(),
                                rtol=1e-13, atol=1e-13, max_steps=10**6).q[-1]
    print(f"double pendulum, t1 = {t1}, error = max |q(t1) - q_ref(t1)|")
    print(f"{'solver':8s} {'tol':>7s} {'error':>9s} {'steps':>6s} {'ms':>7s}")
    for name, solver in [("Tsit5", diffrax.Tsit5()), ("Dopri5", diffrax.Dopri5()),
                         ("Dopri8", diffrax.Dopri8())]:
        for tol in (1e-6, 1e-8, 1e-10, 1e-12):
            def run():
                return jaxdyn.simulate(system, q0, u0, p, t1=t1, solver=solver, rtol=tol,
                                       atol=tol, max_steps=10**6)
            solution = run()  # compile
            times = []
            for _ in range(rounds):
                start = time.perf_counter()
                jax.block_until_ready(run())
                times.append(time.perf_counter() - start)
            error = float(jnp.max(jnp.abs(solution.q[-1] - reference)))
            print(f"{name:8s} {tol:7.0e} {error:9.2e} {int(solution.num_steps):6d} "
                  f"{1e3 * statistics.median(times):7.2f}")


if __name__ == "__main__":
    main()
