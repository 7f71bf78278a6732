"""`Lagrangian.accelerations` against a hand-written double-pendulum right-hand side.

Run: python benchmarks/bench_accelerations.py

Both are jit-compiled and timed after compilation, side by side in one process; the figure
that matters is the ratio jaxdyn / hand-written. Also times a batch of 1024 states (vmap) and a
whole `jaxdyn.simulate` against `diffrax.diffeqsolve` on the hand-written right-hand side with
the same solver and tolerances.
"""

import os
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _timing import timed  # noqa: E402

P = dict(m1=1.0, m2=0.8, l1=1.0, l2=0.7, g=9.81)


def kinetic(q, qd, p):
    v1 = p["l1"] * qd[0] * jnp.array([jnp.cos(q[0]), jnp.sin(q[0])])
    v2 = v1 + p["l2"] * qd[1] * jnp.array([jnp.cos(q[1]), jnp.sin(q[1])])
    return 0.5 * (p["m1"] * v1 @ v1 + p["m2"] * v2 @ v2)


def potential(q, p):
    return -p["g"] * ((p["m1"] + p["m2"]) * p["l1"] * jnp.cos(q[0])
                      + p["m2"] * p["l2"] * jnp.cos(q[1]))


def hand_written(t, q, qd, p):
    """The textbook closed form of the double pendulum (absolute angles)."""
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    d = q[0] - q[1]
    den = 2 * m1 + m2 - m2 * jnp.cos(2 * d)
    a1 = (-g * (2 * m1 + m2) * jnp.sin(q[0]) - m2 * g * jnp.sin(q[0] - 2 * q[1])
          - 2 * jnp.sin(d) * m2 * (qd[1] ** 2 * l2 + qd[0] ** 2 * l1 * jnp.cos(d))) / (l1 * den)
    a2 = (2 * jnp.sin(d) * (qd[0] ** 2 * l1 * (m1 + m2) + g * (m1 + m2) * jnp.cos(q[0])
                            + qd[1] ** 2 * l2 * m2 * jnp.cos(d))) / (l2 * den)
    return jnp.stack([a1, a2])


def main():
    p = {k: jnp.asarray(v) for k, v in P.items()}
    system = jaxdyn.Lagrangian(kinetic, potential)
    t = jnp.asarray(0.0)
    q, qd = jnp.array([0.7, -0.4]), jnp.array([1.1, 0.3])

    ours = jax.jit(system.accelerations)
    theirs = jax.jit(hand_written)
    batched_ours = jax.vmap(system.accelerations, in_axes=(None, 0, 0, None))
    batched_theirs = jax.vmap(hand_written, in_axes=(None, 0, 0, None))
    agreement = float(jnp.max(jnp.abs(ours(t, q, qd, p) - theirs(t, q, qd, p))))
    assert agreement < 1e-12, agreement

    key = jax.random.PRNGKey(0)
    qs, qds = jax.random.normal(key, (2, 1024, 2))

    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64; agreement {agreement:.1e}")
    print(f"{'case':34s} {'hand-written':>13s} {'jaxdyn':>11s} {'ratio':>6s}")
    for name, (a, b, args) in {
        "accelerations, one state": (hand_written, system.accelerations, (t, q, qd, p)),
        "accelerations, vmap over 1024": (batched_theirs, batched_ours, (t, qs, qds, p)),
    }.items():
        (base_compile, base), (mine_compile, mine) = timed(a, *args), timed(b, *args)
        print(f"{name:34s} {1e6 * base:10.2f} µs {1e6 * mine:8.2f} µs {mine / base:6.2f}")
        print(f"{'  compile':34s} {base_compile:10.3f} s  {mine_compile:8.3f} s  "
              f"{mine_compile / base_compile:6.2f}")

    solver, tol, t1 = diffrax.Dopri8(), 1e-10, 10.0

    def baseline_solve(p):
        def field(t, y, p):
            return y[1], hand_written(t, y[0], y[1], p)
        sol = diffrax.diffeqsolve(diffrax.ODETerm(field), solver, 0.0, t1, None, (q, qd), args=p,
                                  stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
                                  max_steps=100_000)
        return sol.ys[0][-1]

    def jaxdyn_solve(p):
        return jaxdyn.simulate(system, q, qd, p, t1=t1, solver=solver, rtol=tol, atol=tol,
                               max_steps=100_000).q[-1]

    difference = float(jnp.max(jnp.abs(jax.jit(baseline_solve)(p) - jaxdyn_solve(p))))
    (base_compile, base), (mine_compile, mine) = (timed(baseline_solve, p, number=5),
                                                  timed(jaxdyn_solve, p, number=5))
    print(f"{'simulate 10 s (Dopri8, tol 1e-10)':34s} {1e3 * base:10.2f} ms {1e3 * mine:8.2f} ms "
          f"{mine / base:6.2f}   (final states differ by {difference:.1e})")
    print(f"{'  compile':34s} {base_compile:10.3f} s  {mine_compile:8.3f} s  "
          f"{mine_compile / base_compile:6.2f}")
    grad_base = jax.grad(lambda p: jnp.sum(baseline_solve(p) ** 2))
    grad_mine = jax.grad(lambda p: jnp.sum(jaxdyn_solve(p) ** 2))
    gb, gm = jax.jit(grad_base)(p), jax.jit(grad_mine)(p)
    gdiff = max(float(np.abs(gb[k] - gm[k])) for k in gb)
    (base_compile, base), (mine_compile, mine) = (timed(grad_base, p, number=3),
                                                  timed(grad_mine, p, number=3))
    print(f"{'grad of simulate w.r.t. p':34s} {1e3 * base:10.2f} ms {1e3 * mine:8.2f} ms "
          f"{mine / base:6.2f}   (gradients differ by {gdiff:.1e})")
    print(f"{'  compile':34s} {base_compile:10.3f} s  {mine_compile:8.3f} s  "
          f"{mine_compile / base_compile:6.2f}")


if __name__ == "__main__":
    main()
