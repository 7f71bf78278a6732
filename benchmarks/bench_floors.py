"""The experiments behind the rows where jaxdyn misses its targets: what the floor is and why.

Run: python benchmarks/bench_floors.py      (about 3 minutes)

1. Chains of 10 and 20 rods given as one kinetic energy. The same chain with its rod velocities
   written as a product with a triangular matrix instead of `jnp.cumsum`, against the
   hand-written equations; per evaluation in a compiled loop and vmapped over 1024 states; and
   the number of kernels XLA runs per evaluation (fusions and library calls in the loop body).
2. The double pendulum's M and f: multiplications in the compiled program, autodiff-formed
   against the closed form (both compile to one kernel: the difference is arithmetic).
"""

import os
import re
import sys
from collections import Counter

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM, as_arrays, chain, states  # noqa: E402
from _timing import in_loop, interleaved  # noqa: E402

T = jnp.asarray(0.0)


def triangular_chain(n):
    """The chain of `_systems.chain`, its rod-centre velocities by a triangular product."""
    triangle = jnp.tril(jnp.ones((n, n))) - 0.5 * jnp.eye(n)

    def kinetic(q, qd, p):
        vx = triangle @ (p["l"] * jnp.cos(q) * qd)
        vy = triangle @ (p["l"] * jnp.sin(q) * qd)
        return 0.5 * p["m"] * (vx @ vx + vy @ vy) + 0.5 * p["m"] * p["l"] ** 2 / 12 * qd @ qd

    def potential(q, p):
        return p["m"] * p["g"] * jnp.sum(triangle @ (-p["l"] * jnp.cos(q)))

    return jaxdyn.Lagrangian(kinetic, potential)


def kernels(accelerations, args):
    """Kernels XLA runs per evaluation: fusions and library calls in the compiled loop body."""
    text = in_loop(accelerations, 10).lower(*args).compile().as_text()
    body = re.search(r"\n(%\S*region_0\S*) \(.*?\n}\n", text, re.S).group(0)
    counts = Counter(re.findall(r"= \S+ ([\w-]+)\(", body))
    return counts["fusion"] + counts["custom-call"] + counts["dot"]


def unchecked(dynamics):
    return lambda t, q, qd, p: dynamics.accelerations(t, q, qd, p, throw=False)


def chains():
    print("1. chain as one kinetic energy: per evaluation (ratio to hand-written) and kernels")
    for n in (10, 20):
        system = chain(n)
        p = as_arrays(system.params)
        qs, qds = states(system, 1024)
        args = (T, qs[0], qds[0], p)
        candidates = {"hand-written": system.hand_written,
                      "jaxdyn, cumsum": unchecked(system.dynamics),
                      "jaxdyn, triangular product": unchecked(triangular_chain(n))}
        reference = system.hand_written(*args)
        for name, fn in candidates.items():
            error = float(jnp.max(jnp.abs(fn(*args) - reference)) / jnp.max(jnp.abs(reference)))
            assert error < 1e-9, (name, error)
        iterations = 2000
        loop = interleaved({k: (in_loop(f, iterations), args) for k, f in candidates.items()},
                           number=1)
        batch = (T, qs, qds, p)
        vmapped = interleaved({k: (jax.jit(jax.vmap(f, in_axes=(None, 0, 0, None))), batch)
                               for k, f in candidates.items()}, number=10)
        for name, fn in candidates.items():
            print(f"   N = {n:2d} {name:28s} loop {1e6 * loop[name] / iterations:7.2f} µs "
                  f"({loop[name] / loop['hand-written']:4.2f}×)  "
                  f"vmap {1e3 * vmapped[name]:6.2f} ms "
                  f"({vmapped[name] / vmapped['hand-written']:4.2f}×)  kernels "
                  f"{kernels(fn, args):3d}", flush=True)


def multiplications():
    system = DOUBLE_PENDULUM
    p = as_arrays(system.params)
    qs, qds = states(system, 2)

    def count(equations):
        text = jax.jit(equations).lower(T, qs[0], qds[0], p).compile().as_text()
        return text.count(" multiply(")

    ours = count(system.dynamics.mass_matrix_and_forcing)
    closed = count(system.hand_equations)
    print(f"2. double pendulum M and f: {ours} multiplications formed by autodiff, {closed} in "
          "the closed form")


if __name__ == "__main__":
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64")
    chains()
    multiplications()
