"""The first gradient through a solve of a chain of 10 rods given as T and V, as a user writes
it, against diffrax on the closed form of the same chain; each in a fresh process.

Run: python benchmarks/bench_chain_gradient.py          (jaxdyn)
     python benchmarks/bench_chain_gradient.py hand     (diffrax on the closed form)

The loss is Σ (q(5), q̇(5))² after 5 s of Tsit5 at rtol = atol = 1e-8; `jax.grad` with respect
to p (the 10 masses, 10 lengths and g: reverse mode through diffrax's checkpoints). The closed
form: M_ij = l_i l_j cos(q_i − q_j) μ_max(i,j) (μ_k the mass below joint k) and a linear solve.
Printed: the seconds of the first gradient (tracing, compiling and one run) and d/dg, which
the two must share.
"""

import sys
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402

import jaxdyn  # noqa: E402

N = 10
P = {"m": jnp.full(N, 1.0 / N), "l": jnp.full(N, 1.0 / N), "g": 9.81}
Q0 = 0.3 + 0.5 * jnp.sin(jnp.pi * jnp.arange(1, N + 1) / (N + 1))
U0 = jnp.zeros(N)


def T(q, qd, p):
    vx = jnp.cumsum(p["l"] * jnp.cos(q) * qd)
    vy = jnp.cumsum(p["l"] * jnp.sin(q) * qd)
    return 0.5 * jnp.sum(p["m"] * (vx**2 + vy**2))


def V(q, p):
    return p["g"] * jnp.sum(p["m"] * -jnp.cumsum(p["l"] * jnp.cos(q)))


def final_state_jaxdyn(p):
    sol = jaxdyn.simulate(jaxdyn.Lagrangian(T, V), Q0, U0, p, t1=5.0, solver=diffrax.Tsit5(),
                          rtol=1e-8, atol=1e-8, max_steps=100_000)
    return jnp.concatenate([sol.q[-1], sol.u[-1]])


def final_state_hand(p):
    l, m, g = p["l"], p["m"], p["g"]
    mu = jnp.cumsum(m[::-1])[::-1]
    idx = jnp.arange(N)
    ll = l[:, None] * l[None, :] * mu[jnp.maximum(idx[:, None], idx[None, :])]

    def f(t, y, args):
        q, qd = y[:N], y[N:]
        dq = q[:, None] - q[None, :]
        rhs = -(ll * jnp.sin(dq)) @ (qd * qd) - g * l * mu * jnp.sin(q)
        return jnp.concatenate([qd, jnp.linalg.solve(ll * jnp.cos(dq), rhs)])

    sol = diffrax.diffeqsolve(diffrax.ODETerm(f), diffrax.Tsit5(), 0.0, 5.0, None,
                              jnp.concatenate([Q0, U0]),
                              stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
                              max_steps=100_000)
    return sol.ys[-1]


if __name__ == "__main__":
    final = final_state_hand if "hand" in sys.argv else final_state_jaxdyn
    grad = jax.grad(lambda p: jnp.sum(final(p) ** 2))
    start = time.perf_counter()
    g = grad(P)
    jax.block_until_ready(g)
    print(f"first gradient: {time.perf_counter() - start:.1f} s; d/dg = {float(g['g']):.6e}")
