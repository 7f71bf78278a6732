"""Cost of `accelerations` for each formulation on a planar N-link chain described body by
body (`MultibodySystem`), against the hand-written equations of the same chain, measured side
by side in one process: per evaluation inside a compiled loop (`throw=False`, what a solver
pays) and compile time (first call, caches cleared).

Run: python benchmarks/bench_formulations.py

The chain: N uniform rods (mass m, length l) hinged end to end, absolute angles θ_i from the
downward vertical, gravity. Hand-written equations (derived on paper):

    Σ_j a_ij [cos(θ_i − θ_j) θ̈_j + sin(θ_i − θ_j) θ̇_j²] + (m l²/12) θ̈_i + m g l b_i sin θ_i = 0

with a = m l² CᵀC, C_ki = 1 (i < k), ½ (i = k), 0 (i > k), and b_i = Σ_k C_ki, solved by a
Cholesky factorisation (`jax.scipy.linalg.cho_factor`).
"""

import os
import sys

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402
from jaxdyn.rotations import planar_rotation  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, in_loop, interleaved  # noqa: E402

M_ROD, L_ROD, G = 1.0, 0.5, 9.81


def chain_system(n):
    def rod_position(i):
        def position(q, p):
            joints = sum((L_ROD * jnp.array([jnp.sin(q[k]), -jnp.cos(q[k]), 0.0])
                          for k in range(i)), jnp.zeros(3))
            return joints + 0.5 * L_ROD * jnp.array([jnp.sin(q[i]), -jnp.cos(q[i]), 0.0])
        return position

    def rod_orientation(i):
        return lambda q, p: planar_rotation(q[i])

    inertia = jnp.diag(jnp.array([1.0, 0.0, 1.0])) * M_ROD * L_ROD**2 / 12
    rods = [jaxdyn.RigidBody(M_ROD, inertia, rod_position(i), rod_orientation(i))
            for i in range(n)]
    return jaxdyn.MultibodySystem(rods, gravity=jnp.array([0.0, -G, 0.0]))


def hand_written(n):
    idx = jnp.arange(n)
    c = jnp.where(idx[None, :] < idx[:, None], 1.0, 0.0) + 0.5 * jnp.eye(n)  # C[k, i]
    a = M_ROD * L_ROD**2 * c.T @ c
    b = jnp.sum(c, axis=0)

    def accelerations(t, q, qd, p):
        diff = q[:, None] - q[None, :]
        mass_matrix = a * jnp.cos(diff) + jnp.eye(n) * M_ROD * L_ROD**2 / 12
        forcing = -(a * jnp.sin(diff)) @ qd**2 - M_ROD * G * L_ROD * b * jnp.sin(q)
        return jsl.cho_solve(jsl.cho_factor(mass_matrix), forcing)

    return accelerations


def main(sizes=(2, 5, 10, 20)):
    t = jnp.asarray(0.0)
    names = ("Lagrange", "Gibbs–Appell", "Kane")
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64, per evaluation inside "
          "a compiled loop")
    print(f"{'N':>3s} {'hand-written':>13s} " + " ".join(f"{name:>20s}" for name in names))
    for n in sizes:
        system = chain_system(n)
        key_q, key_u = jax.random.split(jax.random.PRNGKey(n))
        q, qd = jax.random.normal(key_q, (n,)), jax.random.normal(key_u, (n,))
        baseline = hand_written(n)
        formulations = [jaxdyn.Lagrangian.from_system(system),
                        jaxdyn.GibbsAppell.from_system(system),
                        jaxdyn.Kane.from_system(system)]
        reference = baseline(t, q, qd, None)
        for dynamics in formulations:  # all must solve the same equations before timing
            ours = dynamics.accelerations(t, q, qd, None)
            error = float(jnp.max(jnp.abs(ours - reference)) / jnp.max(jnp.abs(reference)))
            assert error < 1e-9, (type(dynamics).__name__, n, error)

        def unchecked(dynamics):
            return lambda t, q, qd, p: dynamics.accelerations(t, q, qd, p, throw=False)

        candidates = {"hand": baseline, **{name: unchecked(d)
                                           for name, d in zip(names, formulations)}}
        compiles = {k: compile_seconds(fn, t, q, qd, None) for k, fn in candidates.items()}
        iterations = 2000 if n <= 5 else 200
        times = interleaved({k: (in_loop(fn, iterations), (t, q, qd, None))
                             for k, fn in candidates.items()}, number=1, rounds=5)
        base = times["hand"] / iterations
        cells = [f"{1e6 * times[k] / iterations:8.1f} µs ({times[k] / times['hand']:5.1f}×)"
                 for k in names]
        print(f"{n:3d} {1e6 * base:10.2f} µs " + " ".join(f"{c:>20s}" for c in cells))
        print(f"{'':3s} {compiles['hand']:11.2f} s " + " ".join(
            f"{compiles[k]:18.2f} s" for k in names) + "   (compile)", flush=True)


if __name__ == "__main__":
    main()
