"""What skipping the work a system does not need saves, each measured against doing it anyway
in the same run.

Run: python benchmarks/bench_skips.py

1. No potential, forces or dissipation: not evaluated. Against the same system given V, Q and
   D that are identically zero but written as functions of the state (their derivatives are
   then formed at every evaluation).
2. A mass matrix independent of q (30 masses with a dense constant coupling of their kinetic
   energies, M = A Aᵀ + I): factored once per solve. Against forming and factoring M at every
   evaluation. (A small system evaluated as straight-line code needs no such step: its
   constant M folds to a few operations.)
3. A block-diagonal mass matrix (8 uncoupled double pendulums in one system, evaluated as
   arrays): solved block by block. Against one dense Cholesky factorisation.
4. Only the outputs asked for: a 2000-point trajectory saving q only, against q, u and q̇.
5. Nothing differentiated: the forward solve through diffrax's checkpointed loop (the default
   adjoint) against a plain `lax.while_loop` (diffrax with max_steps=None, not
   differentiable), both on jaxdyn's right-hand side.

A kinetic energy independent of q needs no velocity-coupling term: the JVP in q of ∂L/∂q̇ is
then a symbolic zero in JAX and no operation is formed (checked by counting the equations of
the traced program, printed last).
"""

import os
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402
from jaxdyn._dynamics import equations_of_motion, mass_matrix_blocks  # noqa: E402
from jaxdyn._linalg import factorise, solve_mass_matrix  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM, as_arrays, chain  # noqa: E402
from _timing import in_loop, interleaved  # noqa: E402

T = jnp.asarray(0.0)


def rhs(dynamics, factorisation=None):
    def accelerations(t, q, u, p):
        return equations_of_motion(dynamics, t, q, u, p, factorisation)[1]
    return accelerations


def row(name, skipped, done, unit="per evaluation"):
    print(f"{name:58s} skipped {_time(skipped):>9s}  done {_time(done):>9s}  saves "
          f"{100 * (1 - skipped / done):5.1f} % ({unit})", flush=True)


def _time(seconds):
    for unit, scale in (("s", 1), ("ms", 1e-3), ("µs", 1e-6), ("ns", 1e-9)):
        if seconds >= scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds / 1e-9:.3g} ns"


def absent_callbacks():
    system = chain(10)
    p = as_arrays(system.params)
    base = jaxdyn.Lagrangian(system.dynamics.kinetic)
    zeros = jaxdyn.Lagrangian(
        system.dynamics.kinetic,
        potential=lambda q, p: 0.0 * jnp.sum(jnp.cos(q)),
        forces=lambda q, qd, p: 0.0 * jnp.sin(q) * qd,
        dissipation=lambda q, qd, p: 0.0 * jnp.sum(qd**2 * jnp.cos(q)))
    q, u = jnp.full(10, 0.3), jnp.full(10, 0.1)
    iterations = 2000
    times = interleaved({"absent": (in_loop(rhs(base), iterations), (T, q, u, p)),
                         "zero": (in_loop(rhs(zeros), iterations), (T, q, u, p))}, number=1)
    row("1. no V, Q, D (chain of 10, arrays)", times["absent"] / iterations,
        times["zero"] / iterations)


def linear_chain(n=30):
    """T = ½ q̇ᵀ (A Aᵀ + I) q̇ with a dense A from the parameters (a coupled linear system in
    Cartesian coordinates), anharmonic springs: M is constant and dense."""
    def kinetic(q, qd, p):
        return 0.5 * (jnp.sum((p["A"].T @ qd) ** 2) + jnp.sum(qd**2))

    def potential(q, p):
        return p["k"] * jnp.sum(1 - jnp.cos(jnp.diff(jnp.concatenate([jnp.zeros(1), q]))))

    return jaxdyn.Lagrangian(kinetic, potential)


def constant_mass_matrix():
    n = 30
    system = linear_chain(n)
    p = {"A": jnp.asarray(np.random.default_rng(0).normal(size=(n, n)) / n),
         "k": jnp.asarray(40.0)}
    q, u = jnp.linspace(0.0, 0.2, n), jnp.zeros(n)
    factorisation = factorise(system.mass_matrix(T, q, u, p), unrolled=False,
                              blocks=mass_matrix_blocks(system, T, q, u, p))
    iterations = 2000
    times = interleaved({"once": (in_loop(rhs(system, factorisation), iterations), (T, q, u, p)),
                         "every": (in_loop(rhs(system), iterations), (T, q, u, p))}, number=1)
    row("2. constant dense M factored once (30 coupled masses)", times["once"] / iterations,
        times["every"] / iterations)


def blocks():
    count = 8
    dp = DOUBLE_PENDULUM.dynamics

    def kinetic(q, qd, p):
        return sum(dp.kinetic(q[2 * i: 2 * i + 2], qd[2 * i: 2 * i + 2], p)
                   for i in range(count))

    def potential(q, p):
        return sum(dp.potential(q[2 * i: 2 * i + 2], p) for i in range(count))

    system = jaxdyn.Lagrangian(kinetic, potential)
    p = as_arrays(DOUBLE_PENDULUM.params)
    q, u = jnp.linspace(-1, 1, 2 * count), jnp.linspace(0.5, -0.5, 2 * count)
    block_list = [(2 * i, 2 * i + 1) for i in range(count)]

    def solver(blocks):
        def accelerations(t, q, u, p):
            mass_matrix, forcing = system.form_equations(t, q, u, p)
            return solve_mass_matrix(mass_matrix, forcing, unrolled=False, blocks=blocks)[0]
        return accelerations

    iterations = 2000
    times = interleaved({"blocks": (in_loop(solver(block_list), iterations), (T, q, u, p)),
                         "dense": (in_loop(solver(None), iterations), (T, q, u, p))}, number=1)
    row("3. block-diagonal M solved by blocks (8 double pendulums)",
        times["blocks"] / iterations, times["dense"] / iterations)


def outputs():
    system = DOUBLE_PENDULUM
    p = as_arrays(system.params)
    ts = jnp.linspace(0.0, 10.0, 2000)

    def run(save):
        return lambda: jaxdyn.simulate(system.dynamics, jnp.array([1.3, 0.4]), jnp.zeros(2), p,
                                       t1=10.0, ts=ts, save=save, solver=diffrax.Tsit5(),
                                       rtol=1e-8, atol=1e-8)

    times = interleaved({"q": (run("q"), ()), "all": (run(("q", "u", "qd")), ())}, number=3)
    row("4. save q only (2000 points, double pendulum)", times["q"], times["all"], "per solve")


def bookkeeping():
    system = DOUBLE_PENDULUM
    p = as_arrays(system.params)

    def field(t, y, p):
        return equations_of_motion(system.dynamics, t, y[0], y[1], p)[:2]

    def run(max_steps):
        return jax.jit(lambda p: diffrax.diffeqsolve(
            diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, 10.0, None,
            (jnp.array([1.3, 0.4]), jnp.zeros(2)), args=p,
            stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
            max_steps=max_steps).ys)

    times = interleaved({"plain": (run(None), (p,)), "checkpointed": (run(16**4), (p,))},
                        number=5)
    row("5. forward solve: plain loop vs checkpointed loop", times["plain"],
        times["checkpointed"], "per solve")


def coupling():
    def count(kinetic):
        system = jaxdyn.Lagrangian(kinetic, lambda q, p: -jnp.sum(jnp.cos(q)))
        jaxpr = jax.make_jaxpr(system.form_equations)(T, jnp.ones(3), jnp.ones(3), None)
        return len(jaxpr.jaxpr.eqns)

    independent = count(lambda q, qd, p: 0.5 * jnp.sum(jnp.arange(1.0, 4.0) * qd**2))
    dependent = count(lambda q, qd, p: 0.5 * jnp.sum((jnp.arange(1.0, 4.0) + q**2) * qd**2))
    print(f"T independent of q: {independent} traced equations for M and f, against "
          f"{dependent} when T depends on q (the coupling JVP is a symbolic zero)")


def main():
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64")
    absent_callbacks()
    constant_mass_matrix()
    blocks()
    outputs()
    bookkeeping()
    coupling()


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
