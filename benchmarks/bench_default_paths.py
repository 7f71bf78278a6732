"""The paths users call, with default options, against the fastest hand-written floor.

Run: python benchmarks/bench_default_paths.py            (about 6 minutes on two cores)
     python benchmarks/bench_default_paths.py --quick    (fewer rounds, no 16384 batch)
     python benchmarks/bench_default_paths.py --check    (exit 1 when a ratio misses its target)
     python benchmarks/bench_default_paths.py --record   (write results/default_paths.csv)

Every row times what a user calls (un-jitted where the README calls it so, default `save` and
`throw`) side by side in one process with its floor, and prints the ratio and its target:

- the floor of the double pendulum is the fastest closed form known,
  `_systems.double_pendulum_fastest` (s = sin(θ₁ − θ₂), c = cos(θ₁ − θ₂), den = m₁ + m₂ s²);
  of the elastic pendulum its closed form; of the chain of 10 rods M = a cos(θᵢ − θⱼ) + …
  with a Cholesky solve (`_systems.py`);
- a trajectory's floor is `jax.jit` of `diffrax.diffeqsolve` on that closed form with the state
  as one vector y = [q; q̇] (the faster layout: a pair (q, q̇) costs 1.4–2.8× more per step), the
  same solver (Tsit5), tolerances (rtol = atol = 1e-8), PID controller and saving (the final
  state);
- jaxdyn is given T and V as a user writes them; for batches, T written three ways (scalar
  expressions, vectors and dot products, rotation matrices with a JVP).
"""

import argparse
import os
import statistics
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402
from jaxdyn._runge_kutta import UnrolledStages  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import (  # noqa: E402
    CHAIN_PARAMS,
    DOUBLE_PENDULUM_PARAMS,
    ELASTIC_PARAMS,
    chain_hand,
    chain_T,
    chain_V,
    double_pendulum_fastest,
    double_pendulum_T,
    double_pendulum_T_rotations,
    double_pendulum_T_scalar,
    double_pendulum_V,
    elastic_hand,
    elastic_T,
    elastic_V,
)
from _results import Recorder  # noqa: E402
from _timing import in_loop, interleaved  # noqa: E402

TOL = 1e-8
SOLVER = diffrax.Tsit5()
UNROLLED = UnrolledStages(SOLVER)
ROWS = []  # (row, system, ratio, target)


def report(row, system, ratio, target, detail=""):
    ROWS.append((row, system, ratio, target))
    mark = "ok " if ratio <= target else "MISS"
    print(f"  {mark} {row:<46s} {system:<18s} {ratio:6.2f}x  (target {target}x) {detail}",
          flush=True)


def systems():
    chain_accelerations, _ = chain_hand(10)
    return {
        "double pendulum": (jaxdyn.Lagrangian(double_pendulum_T_scalar, double_pendulum_V),
                            DOUBLE_PENDULUM_PARAMS, double_pendulum_fastest,
                            np.array([1.3, 0.4]), np.array([0.0, 0.0])),
        "elastic pendulum": (jaxdyn.Lagrangian(elastic_T, elastic_V), ELASTIC_PARAMS,
                             elastic_hand, np.array([1.4, 1.0]), np.array([0.0, 0.0])),
        "chain of 10": (jaxdyn.Lagrangian(chain_T, chain_V), CHAIN_PARAMS, chain_accelerations,
                        np.full(10, 0.9), np.zeros(10)),
    }


def floor_solve(hand, n, t1, ts=None, adjoint=diffrax.RecursiveCheckpointAdjoint(), jit=True,
                solver=SOLVER):
    """jax.jit of diffeqsolve on the hand-written equations, state y = [q; q̇]."""
    def field(t, y, p):
        return jnp.concatenate([y[n:], hand(t, y[:n], y[n:], p)])

    saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)

    def solve(y0, p):
        return diffrax.diffeqsolve(diffrax.ODETerm(field), solver, 0.0, t1, None, y0, args=p,
                                   saveat=saveat, max_steps=16**4, adjoint=adjoint,
                                   stepsize_controller=diffrax.PIDController(rtol=TOL,
                                                                             atol=TOL)).ys
    return jax.jit(solve) if jit else solve


def floor_sensitivities(hand, n, t1, solver=SOLVER):
    """The floor of a gradient by forward sensitivities: the hand-written equations integrated
    with their sensitivity equations Ṡ = ∂f/∂y S + ∂f/∂p (one vectorised `jax.jvp` of the
    closed form per stage, z = [y; S], the error norm on y alone so that the steps are the
    forward solve's), the gradient of the loss on q(t₁) contracted from S by hand."""
    def field(t, y, p):
        return jnp.concatenate([y[n:], hand(t, y[:n], y[n:], p)])

    def loss_and_grad(y0, p):
        flat, unravel = ravel_pytree(p)
        k, m = flat.size, y0.size

        def augmented(t, z, flat):
            y, s = z[:m], z[m:].reshape(k, m)
            f, rates = jax.vmap(lambda s_k, e_k: jax.jvp(
                lambda y, x: field(t, y, unravel(x)), (y, flat), (s_k, e_k)),
                out_axes=(None, 0))(s, jnp.eye(k, dtype=flat.dtype))
            return jnp.concatenate([f, rates.reshape(-1)])

        norm = lambda error: optx.rms_norm(error[:m])  # diffrax's default norm, on y  # noqa: E731
        z = diffrax.diffeqsolve(
            diffrax.ODETerm(augmented), solver, 0.0, t1, None,
            jnp.concatenate([y0, jnp.zeros(k * m, y0.dtype)]), args=flat,
            saveat=diffrax.SaveAt(t1=True), max_steps=16**4,
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL, norm=norm)).ys[-1]
        q, s = z[:n], z[m:].reshape(k, m)[:, :n]
        return jnp.sum(q**2), s @ (2 * q)
    return loss_and_grad


def as_arrays(params):
    return {k: jnp.asarray(v) for k, v in params.items()}


def checks_in_loop(name, system, params, hand, q0, u0, rounds):
    """Deliverable 1: accelerations with their default check against throw=False."""
    p = as_arrays(params)
    t = jnp.asarray(0.0)
    n_loop = 20000
    loops = {
        "hand": in_loop(hand, n_loop),
        "throw=False": in_loop(lambda t, q, u, p: system.accelerations(t, q, u, p, throw=False),
                               n_loop),
        "default": in_loop(lambda t, q, u, p: system.accelerations(t, q, u, p), n_loop),
    }
    q, u = jnp.asarray(q0), jnp.asarray(u0)
    times = interleaved({k: (f, (t, q, u, p)) for k, f in loops.items()}, number=1,
                        rounds=rounds)
    report("accelerations default / throw=False, loop", name,
           times["default"] / times["throw=False"], 1.1,
           f"({times['default'] / n_loop * 1e9:.0f} / {times['throw=False'] / n_loop * 1e9:.0f}"
           f" ns; hand {times['hand'] / n_loop * 1e9:.0f} ns)")
    rng = np.random.default_rng(0)
    qs = jnp.asarray(q0 + 0.1 * rng.standard_normal((1024, len(q0))))
    us = jnp.asarray(u0 + 0.1 * rng.standard_normal((1024, len(u0))))
    vmapped = {
        "throw=False": jax.jit(jax.vmap(lambda q, u, p: system.accelerations(
            t, q, u, p, throw=False), in_axes=(0, 0, None))),
        "default": jax.jit(jax.vmap(lambda q, u, p: system.accelerations(t, q, u, p),
                                    in_axes=(0, 0, None))),
    }
    times = interleaved({k: (f, (qs, us, p)) for k, f in vmapped.items()}, number=20,
                        rounds=rounds)
    report("accelerations default / throw=False, vmap", name,
           times["default"] / times["throw=False"], 1.1)
    eager = {"throw=False": lambda t, q, u, p: system.accelerations(t, q, u, p, throw=False),
             "default": system.accelerations}
    times = interleaved({k: (f, (t, q, u, p)) for k, f in eager.items()}, number=200,
                        rounds=rounds)
    # No target: the host reads one flag after the program (the targets are the two
    # rows above); printed so that the price of a check with values is seen.
    print(f"       called with values, not jitted (no target): default "
          f"{times['default'] * 1e6:.1f} µs, throw=False {times['throw=False'] * 1e6:.1f} µs",
          flush=True)


def branch_floor(rounds):
    """The floor of a check with a message inside a compiled loop: the hand-written double
    pendulum alone, with a `lax.cond` on its finiteness whose branch is pure (XLA turns it
    into a select), and with a host callback in that branch (what raising a message needs)."""
    p = as_arrays(DOUBLE_PENDULUM_PARAMS)
    n_loop = 20000

    def raise_(_):
        raise RuntimeError("not finite")

    def with_branch(callback):
        def checked(t, q, u, p):
            a = double_pendulum_fastest(t, q, u, p)
            failed = ~jnp.all(jnp.isfinite(a))
            if callback:
                flag = jax.lax.cond(failed, lambda: jax.pure_callback(
                    raise_, jax.ShapeDtypeStruct((), jnp.bool_), a), lambda: False)
            else:
                flag = jax.lax.cond(failed, lambda: jnp.sum(a) > 0, lambda: False)
            return a + 0.0 * flag  # tied to the result, as a check must be
        return checked

    loops = {"hand": in_loop(double_pendulum_fastest, n_loop),
             "pure branch": in_loop(with_branch(False), n_loop),
             "host-callback branch": in_loop(with_branch(True), n_loop)}
    args = (jnp.asarray(0.0), jnp.array([1.3, 0.4]), jnp.zeros(2), p)
    times = interleaved({k: (f, args) for k, f in loops.items()}, number=1, rounds=rounds)
    print("  floor of a check in a loop (double pendulum, hand-written): " + ", ".join(
        f"{k} {v / n_loop * 1e9:.0f} ns" for k, v in times.items()))


def trajectories(name, system, params, hand, q0, u0, rounds):
    """Deliverable 2: simulate as the README calls it, short and long trajectories."""
    n = len(q0)
    p_arrays = as_arrays(params)
    q0j, u0j = jnp.asarray(q0), jnp.asarray(u0)
    for label, t1 in (("short", 10.0 if n <= 2 else 2.0), ("long", 100.0 if n <= 2 else 20.0)):
        floor = floor_solve(hand, n, t1)
        y0 = jnp.concatenate([q0j, u0j])

        def called():  # as a user calls it: not jitted, default save and throw
            return jaxdyn.simulate(system, q0j, u0j, params, t1=t1, solver=diffrax.Tsit5(),
                                   rtol=TOL, atol=TOL)

        jitted = jax.jit(lambda q0, u0, p: jaxdyn.simulate(
            system, q0, u0, p, t1=t1, solver=SOLVER, rtol=TOL, atol=TOL, throw=False).q)
        steps = int(called().num_steps)
        times = interleaved({"floor": (floor, (y0, p_arrays)), "simulate": (called, ()),
                             "jit": (jitted, (q0j, u0j, p_arrays))},
                            number=3 if label == "long" else 10, rounds=rounds)
        report(f"simulate ({label}, {steps} steps) / floor", name,
               times["simulate"] / times["floor"], 1.3,
               f"({times['simulate'] * 1e3:.2f} / {times['floor'] * 1e3:.2f} ms)")
        report(f"jax.jit(simulate, throw=False) ({label}) / floor", name,
               times["jit"] / times["floor"], 1.3)


def batches(size, rounds):
    """Deliverable 3: simulate_batch and jax.vmap(simulate) against the vmapped floor."""
    angles = np.random.default_rng(0).permutation(np.linspace(0.5, 2.5, size))
    q0 = jnp.asarray(np.stack([angles, 0.5 * angles], axis=1))
    u0 = jnp.zeros_like(q0)
    p_arrays = as_arrays(DOUBLE_PENDULUM_PARAMS)
    floor = jax.jit(jax.vmap(floor_solve(double_pendulum_fastest, 2, 10.0), in_axes=(0, None)))
    candidates = {"floor": (floor, (jnp.concatenate([q0, u0], axis=1), p_arrays))}
    for label, T in (("scalar T", double_pendulum_T_scalar), ("vector T", double_pendulum_T),
                     ("rotation T", double_pendulum_T_rotations)):
        system = jaxdyn.Lagrangian(T, double_pendulum_V)
        candidates[f"simulate_batch, {label}"] = (
            lambda system=system: jaxdyn.simulate_batch(
                system, q0, u0, DOUBLE_PENDULUM_PARAMS, t1=10.0, solver=diffrax.Tsit5(),
                rtol=TOL, atol=TOL, save="q", progress=False).q, ())
        candidates[f"vmap(simulate), {label}"] = (
            jax.jit(jax.vmap(lambda q, u, p, system=system: jaxdyn.simulate(
                system, q, u, p, t1=10.0, solver=SOLVER, rtol=TOL, atol=TOL, save="q",
                throw=False).q, in_axes=(0, 0, None))), (q0, u0, p_arrays))
    times = interleaved(candidates, number=1, rounds=rounds)
    for key, value in times.items():
        if key != "floor":
            report(f"{key.split(',')[0]} ({size}) / vmapped floor", key.split(", ")[1],
                   value / times["floor"], 1.3)


def gradients(name, system, params, hand, q0, u0, rounds):
    """Deliverable 4: jax.grad of a loss on the final state against one forward simulate."""
    p_arrays = as_arrays(params)
    q0j, u0j = jnp.asarray(q0), jnp.asarray(u0)

    def forward(p):
        return jaxdyn.simulate(system, q0j, u0j, p, t1=10.0, solver=SOLVER, rtol=TOL,
                               atol=TOL).q[-1]

    loss = lambda p: jnp.sum(forward(p) ** 2)  # noqa: E731
    # The floor experiment: diffrax's adjoints on the hand-written equations, same solve.
    y0 = jnp.concatenate([q0j, u0j])

    def hand_forward(p, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        return floor_solve(hand, len(q0), 10.0, adjoint=adjoint, jit=False)(y0, p)[-1, :len(q0)]

    hand_reverse = lambda p: jnp.sum(hand_forward(p) ** 2)  # noqa: E731
    hand_tangents = lambda p: jnp.sum(hand_forward(p, diffrax.ForwardMode()) ** 2)  # noqa: E731
    times = interleaved({"forward": (jax.jit(forward), (p_arrays,)),
                         "grad": (jax.jit(jax.grad(loss)), (p_arrays,)),
                         "hand": (jax.jit(hand_forward), (p_arrays,)),
                         "hand reverse": (jax.jit(jax.grad(hand_reverse)), (p_arrays,)),
                         "hand forward": (jax.jit(jax.jacfwd(hand_tangents)), (p_arrays,)),
                         "hand sensitivities": (jax.jit(floor_sensitivities(hand, len(q0), 10.0)),
                                                (y0, p_arrays)),
                         # The same two solves with the stages written out, as jaxdyn steps.
                         "hand unrolled": (floor_solve(hand, len(q0), 10.0, solver=UNROLLED),
                                           (y0, p_arrays)),
                         "hand sensitivities unrolled": (jax.jit(floor_sensitivities(
                             hand, len(q0), 10.0, UNROLLED)), (y0, p_arrays))},
                        number=3, rounds=rounds)
    report("jax.grad(simulate) / forward simulate", name, times["grad"] / times["forward"],
           4.0)
    print(f"       floor experiment, / the hand-written forward solve: jaxdyn's gradient "
          f"{times['grad'] / times['hand']:.2f}x, diffrax on the hand-written equations: "
          f"ForwardMode (jacfwd) {times['hand forward'] / times['hand']:.2f}x, checkpointed "
          f"reverse {times['hand reverse'] / times['hand']:.2f}x, its sensitivity equations "
          f"(vectorised jvp, error on y) {times['hand sensitivities'] / times['hand']:.2f}x; "
          f"jaxdyn's forward solve {times['forward'] / times['hand']:.2f}x; with the stages "
          f"written out (jaxdyn's UnrolledStages), the hand-written sensitivity equations / "
          f"forward solve {times['hand sensitivities unrolled'] / times['hand unrolled']:.2f}x")
    try:
        jax.jacfwd(forward)(p_arrays)
        works = "works"
    except Exception as error:  # noqa: BLE001 -- reported, the row is the point
        works = f"fails: {type(error).__name__}"
    print(f"       jax.jacfwd through simulate with default options: {works}")


FIRST_CALL = r"""
import os, sys, time
sys.path.insert(0, os.path.join(os.getcwd(), "benchmarks"))
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import diffrax, jaxdyn
import bench_default_paths as b
system, params, hand, q0, u0 = b.systems()[sys.argv[1]]
q0, u0 = jnp.asarray(q0), jnp.asarray(u0)
jnp.zeros(1).block_until_ready()  # JAX's backend started, as in any session
start = time.perf_counter()
if sys.argv[2] == "floor":
    jax.block_until_ready(b.floor_solve(hand, len(q0), 10.0)(jnp.concatenate([q0, u0]),
                                                              b.as_arrays(params)))
else:  # as the README calls it
    jaxdyn.simulate(system, q0, u0, params, t1=10.0, solver=diffrax.Tsit5(), rtol=b.TOL,
                    atol=b.TOL)
print(time.perf_counter() - start)
"""


def compile_times(name, rounds=3):
    """Deliverable 5: the first call of simulate against the first call of the floor, each in
    a fresh Python process (what a user waits for in a new session: tracing, compiling and
    every first use of a library's machinery), alternated, medians of `rounds`."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    times = {"floor": [], "simulate": []}
    for _ in range(rounds):
        for kind, measured in times.items():
            done = subprocess.run([sys.executable, "-c", FIRST_CALL, name, kind], cwd=root,
                                  capture_output=True, text=True, check=True)
            measured.append(float(done.stdout.strip().splitlines()[-1]))
    ours, floor = (statistics.median(times[k]) for k in ("simulate", "floor"))
    report("first simulate / first floor call", name, ours / floor, 1.5,
           f"({ours:.2f} / {floor:.2f} s, fresh processes)")


LARGE_FIRST_CALL = r"""
import os, sys, time
sys.path.insert(0, os.path.join(os.getcwd(), "benchmarks"))
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import diffrax, jaxdyn
from _systems import CHAIN_PARAMS, chain_T, chain_V
from bench_trees import chain_tree, robot_file
kind, n = sys.argv[1], int(sys.argv[2])
jnp.zeros(1).block_until_ready()
if kind == "energies":
    system, p = jaxdyn.Lagrangian(chain_T, chain_V), CHAIN_PARAMS
elif kind == "panda":
    tree, p = jaxdyn.from_urdf(robot_file("panda_description/urdf/panda.urdf"))
    system = jaxdyn.ArticulatedBody(tree)
    n = tree.num_speeds
else:
    system, p = getattr(jaxdyn, kind)(chain_tree(n)), None
q0, u0 = jnp.full(n, 0.3), jnp.zeros(n)
start = time.perf_counter()
jaxdyn.simulate(system, q0, u0, p, t1=1.0)
forward = time.perf_counter() - start
if kind == "panda":  # the first gradient of a loss on the final state, by default
    loss = lambda q0: jnp.sum(jaxdyn.simulate(system, q0, u0, p, t1=1.0, save="q").q[-1] ** 2)
    start = time.perf_counter()
    jax.block_until_ready(jax.grad(loss)(q0))
    print(forward, time.perf_counter() - start)
else:
    print(forward)
"""


def large_first_calls():
    """Deliverable 5: the first `simulate` (default options, 1 s) of large systems, each in a
    fresh process: a chain of 50 rods given as T and V, `RigidBodyTree` chains of 20, 50 and
    100 links (articulated-body algorithm) and of 20 (Kane's equations); and on the Panda arm
    from URDF the first forward call against the first `jax.grad` through it."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def first(kind, n):
        done = subprocess.run([sys.executable, "-c", LARGE_FIRST_CALL, kind, str(n)], cwd=root,
                              capture_output=True, text=True, check=True)
        return [float(x) for x in done.stdout.strip().splitlines()[-1].split()]

    for kind, n, label in (("energies", 50, "chain of 50 rods, T and V (Lagrange)"),
                           ("ArticulatedBody", 20, "tree chain of 20, articulated body"),
                           ("ArticulatedBody", 50, "tree chain of 50, articulated body"),
                           ("ArticulatedBody", 100, "tree chain of 100, articulated body"),
                           ("Kane", 20, "tree chain of 20, Kane")):
        seconds = first(kind, n)[0]
        report(f"first simulate, s (target 5 s): {label}", "", seconds / 5.0, 1.0,
               f"({seconds:.1f} s)")
    forward, gradient = first("panda", 0)
    report("first jax.grad / first simulate (2x)", "Panda arm (URDF)", gradient / forward, 2.0,
           f"({gradient:.1f} / {forward:.1f} s)")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--check", action="store_true")
    parser.add_argument("--only", default="checks,trajectories,batches,gradients,compile")
    parser.add_argument("--record", action="store_true",
                        help="write the figures to benchmarks/results/default_paths.csv")
    args = parser.parse_args()
    rounds = 5 if args.quick else 9
    only = set(args.only.split(","))
    cases = systems()
    print(f"jax {jax.__version__}, diffrax {diffrax.__version__}, {jax.devices()[0].platform}, "
          f"{len(jax.devices())} device(s), float64")
    if "checks" in only:
        print("1. default checks (medians of interleaved rounds)")
        for name, case in cases.items():
            checks_in_loop(name, *case, rounds)
        branch_floor(rounds)
    if "trajectories" in only:
        print("2. simulate as the README calls it (Tsit5, rtol = atol = 1e-8)")
        for name, case in cases.items():
            trajectories(name, *case, rounds)
    if "batches" in only:
        print("3. batches of double pendulums (10 s, final state)")
        for size in (1024,) if args.quick else (1024, 16384):
            batches(size, 3 if size > 1024 else rounds)
    if "gradients" in only:
        print("4. gradients")
        for name in ("double pendulum", "elastic pendulum"):
            gradients(name, *cases[name], rounds)
    if "compile" in only:
        print("5. compile time (fresh processes)")
        for name in ("double pendulum", "elastic pendulum"):
            compile_times(name)
        large_first_calls()
    missed = [row for row in ROWS if row[2] > row[3]]
    print(f"\n{len(ROWS) - len(missed)} of {len(ROWS)} rows meet their targets.")
    if args.record:
        recorder = Recorder("default_paths")
        for row, system, ratio, target in ROWS:
            recorder.add(row, system, ratio, "×", target)
        recorder.write()
    if args.check and missed:
        sys.exit(1)


if __name__ == "__main__":
    main()
