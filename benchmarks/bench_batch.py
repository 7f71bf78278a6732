"""Batch simulation: `jaxdyn.simulate_batch` against a Python loop of single `simulate` calls,
a loop of SciPy's `solve_ivp`, and a vmapped diffrax solve of hand-written equations (the
floor), side by side in one process; then the cost of the slowest member, device scaling,
peak memory and compile time.

Run: python benchmarks/bench_batch.py            (about 8 minutes on two cores)
     python benchmarks/bench_batch.py --quick    (sizes up to 1024, fewer rounds)
     python benchmarks/bench_batch.py --floor    (only: the equations in and out of the solve)

The double pendulum over 10 s at rtol = atol = 1e-8 with Tsit5 (DOP853 for SciPy), final
state saved; starting angles θ₁ drawn from [0.5, 2.5] rad, θ₂ = θ₁/2 (regular to chaotic
motion: members take 120–700 steps), the same shuffled mix at every size. The loops are timed
on 64 (SciPy: 16) members and scaled. Device scaling and peak memory run in subprocesses
(`XLA_FLAGS=--xla_force_host_platform_device_count=N`; `ru_maxrss`).
"""

import argparse
import json
import os
import subprocess
import sys
import time

import diffrax
import jax
import numpy as np
import scipy.integrate

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM, as_arrays  # noqa: E402
from _timing import interleaved  # noqa: E402

T1, TOL = 10.0, 1e-8
OPTIONS = dict(t1=T1, solver=diffrax.Tsit5(), rtol=TOL, atol=TOL, save="q")


def starts(size, low=0.5, high=2.5, seed=0):
    angles = np.random.default_rng(seed).permutation(np.linspace(low, high, size))
    q0 = np.stack([angles, 0.5 * angles], axis=1)
    return q0, np.zeros_like(q0)


def numpy_rhs(p):
    m1, m2, l1, l2, g = (p[k] for k in ("m1", "m2", "l1", "l2", "g"))

    def rhs(t, y):
        q1, q2, w1, w2 = y
        d = q1 - q2
        den = 2 * m1 + m2 - m2 * np.cos(2 * d)
        a1 = (-g * (2 * m1 + m2) * np.sin(q1) - m2 * g * np.sin(q1 - 2 * q2)
              - 2 * np.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * np.cos(d))) / (l1 * den)
        a2 = (2 * np.sin(d) * (w1**2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(q1)
                               + w2**2 * l2 * m2 * np.cos(d))) / (l2 * den)
        return [w1, w2, a1, a2]

    return rhs


def hand_written_batch():
    """The floor: diffrax on the closed-form θ̈ written by hand, vmapped, same solver,
    tolerance and saving."""
    p = as_arrays(DOUBLE_PENDULUM.params)

    def field(t, y, args):
        q, qd = y
        return qd, DOUBLE_PENDULUM.hand_written(t, q, qd, p)

    def one(q0, u0):
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, T1, None, (q0, u0),
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
            saveat=diffrax.SaveAt(t1=True), max_steps=16**4)
        return solution.ys[0][-1], solution.stats["num_steps"]

    return jax.jit(jax.vmap(one))


def batch(q0, u0, **kwargs):
    solution = jaxdyn.simulate_batch(DOUBLE_PENDULUM.dynamics, q0, u0,
                                     as_arrays(DOUBLE_PENDULUM.params), **OPTIONS, **kwargs)
    return solution.q, solution.num_steps


def throughput(sizes, rounds):
    p = as_arrays(DOUBLE_PENDULUM.params)
    single = jax.jit(lambda q0, u0: jaxdyn.simulate(DOUBLE_PENDULUM.dynamics, q0, u0, p,
                                                    **OPTIONS).q)
    hand = hand_written_batch()
    rhs = numpy_rhs(DOUBLE_PENDULUM.params)
    q0s, u0s = starts(max(sizes))

    # agreement first: the batch against single solves, the floor and SciPy at 1e-12
    q_batch, _ = batch(q0s[:64], u0s[:64])
    q_single = np.stack([np.asarray(single(q0s[i], u0s[i])) for i in range(8)])
    q_hand, _ = hand(q0s[:64], u0s[:64])
    regular = int(np.argmin(q0s[:64, 0]))
    reference = scipy.integrate.solve_ivp(rhs, (0, T1), [*q0s[regular], 0, 0],
                                          method="DOP853", rtol=1e-12, atol=1e-12).y[:2, -1]
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, {len(jax.devices())} device(s), "
          f"float64; double pendulum, {T1} s, Tsit5 at {TOL}")
    print(f"agreement: batch vs single solves {np.max(np.abs(q_batch[:8] - q_single)):.1e}, "
          f"vs the hand-written floor {np.max(np.abs(q_batch - np.asarray(q_hand))):.1e} "
          f"(same steps, other round-off; chaotic members amplify it), regular member vs "
          f"SciPy at 1e-12 {np.max(np.abs(q_batch[regular, -1] - reference)):.1e}")

    def loop(count):
        return lambda: [single(q0s[i], u0s[i]).block_until_ready() for i in range(count)]

    def scipy_loop(count):
        return lambda: [scipy.integrate.solve_ivp(rhs, (0, T1), [*q0s[i], 0, 0],
                                                  method="DOP853", rtol=TOL, atol=TOL)
                        for i in range(count)]

    loops = interleaved({"loop": (loop(64), ()), "scipy": (scipy_loop(16), ())}, number=1,
                        rounds=3)
    loop_rate, scipy_rate = 64 / loops["loop"], 16 / loops["scipy"]
    print(f"\n{'batch':>6s} {'simulate_batch':>15s} {'hand floor':>11s} {'Python loop':>12s} "
          f"{'SciPy loop':>11s} {'vs floor':>9s} {'vs loop':>8s} {'vs SciPy':>9s}"
          "   (trajectories per second; vs floor = floor time / batch time)")
    rows = []
    for size in sizes:
        args = (q0s[:size], u0s[:size])
        batch(*args), hand(*args)  # compiled for this size
        candidates = {"batch": (lambda *a: batch(*a)[0], args)}
        if size <= 4096:
            candidates["hand"] = (lambda *a: hand(*a)[0].block_until_ready(), args)
        times = interleaved(candidates, number=1, rounds=rounds if size <= 4096 else 1)
        rate = size / times["batch"]
        hand_rate = size / times["hand"] if "hand" in times else float("nan")
        print(f"{size:6d} {rate:15.0f} {hand_rate:11.0f} {loop_rate:12.0f} {scipy_rate:11.0f} "
              f"{rate / hand_rate:8.2f}× {rate / loop_rate:7.1f}× {rate / scipy_rate:8.1f}×",
              flush=True)
        rows.append((size, rate, hand_rate))
    return rows


def slowest_member(rounds):
    """What the slowest member costs a vmapped adaptive solve, and what helps."""
    print("\nthe slowest member (batch of 1024 on one device; steps per member min/median/max;"
          " time; efficiency = mean steps / max steps):")
    p = as_arrays(DOUBLE_PENDULUM.params)
    hand = hand_written_batch()
    cases = {"regular (θ₁ ∈ [0.1, 0.5])": starts(1024, 0.1, 0.5),
             "chaotic (θ₁ ∈ [2.0, 2.5])": starts(1024, 2.0, 2.5),
             "mixed (θ₁ ∈ [0.5, 2.5])": starts(1024)}
    for name, (q0, u0) in cases.items():
        _, steps = hand(q0, u0)
        steps = np.asarray(steps)
        seconds = interleaved({"batch": (lambda: batch(q0, u0)[0], ())}, number=1,
                              rounds=rounds)["batch"]
        print(f"  {name:28s} steps {steps.min()}/{int(np.median(steps))}/{steps.max()}, "
              f"{seconds * 1e3:7.0f} ms, efficiency {steps.mean() / steps.max():.2f}")
    q0, u0 = cases["mixed (θ₁ ∈ [0.5, 2.5])"]
    variants = {
        "one chunk of 1024": dict(),
        "chunks of 64, given order": dict(chunk_size=64),
        "chunks of 64, order='cost'": dict(chunk_size=64, order="cost"),
    }
    for kwargs in variants.values():
        batch(q0, u0, **kwargs)
    times = interleaved({name: (lambda kw=kw: batch(q0, u0, **kw)[0], ())
                         for name, kw in variants.items()}, number=1, rounds=rounds)
    for name, seconds in times.items():
        print(f"  mixed, {name:30s} {seconds * 1e3:7.0f} ms")
    # fixed steps: every member takes the same steps (no waiting), at the error of the step
    reference = np.asarray(batch(q0[:64], u0[:64])[0])
    for dt in (0.01, 0.005):
        fixed = dict(stepsize_controller=diffrax.ConstantStepSize(), dt0=dt)

        def run(fixed=fixed):
            return jaxdyn.simulate_batch(DOUBLE_PENDULUM.dynamics, q0, u0, p, t1=T1,
                                         solver=diffrax.Tsit5(), save="q", **fixed).q

        run()
        seconds = interleaved({"fixed": (run, ())}, number=1, rounds=rounds)["fixed"]
        regular = np.argsort(q0[:64, 0])[:16]  # error on the regular members (chaos aside)
        error = np.max(np.abs(np.asarray(run())[:64][regular] - reference[regular]))
        print(f"  mixed, fixed step dt = {dt}:{'':14s} {seconds * 1e3:7.0f} ms, error on regular "
              f"members vs 1e-8 adaptive {error:.1e}")


def where_the_time_goes(rounds):
    """The equations alone against the same equations inside the vmapped solve: which part
    of the gap to the floor is the equations and which is the solver's loop around them."""
    p = as_arrays(DOUBLE_PENDULUM.params)
    q0, u0 = starts(1024)
    jaxdyn_rhs = jax.tree_util.Partial(lambda t, q, qd, p: DOUBLE_PENDULUM.dynamics.accelerations(
        t, q, qd, p, throw=False))

    def in_loop(rhs, iterations=2000):  # semi-implicit Euler: a new state every evaluation
        def run(q, qd):
            def body(_, state):
                q, qd = state
                a = jax.vmap(lambda q, qd: rhs(0.0, q, qd, p))(q, qd)
                return q + 1e-4 * qd, qd + 1e-4 * a
            return jax.lax.fori_loop(0, iterations, body, (q, qd))
        return jax.jit(run)

    def in_solve(rhs, scan_kind=None):
        def field(t, y, args):
            return y[1], rhs(t, y[0], y[1], p)

        def one(q0, u0):
            return diffrax.diffeqsolve(
                diffrax.ODETerm(field), diffrax.Tsit5(scan_kind=scan_kind), 0.0, T1, None,
                (q0, u0),
                stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
                saveat=diffrax.SaveAt(t1=True), max_steps=16**4).ys[0]
        return jax.jit(jax.vmap(one))

    loops = {"hand": in_loop(DOUBLE_PENDULUM.hand_written), "jaxdyn": in_loop(jaxdyn_rhs)}
    solves = {"hand": in_solve(DOUBLE_PENDULUM.hand_written), "jaxdyn": in_solve(jaxdyn_rhs),
              "hand, bounded": in_solve(DOUBLE_PENDULUM.hand_written, "bounded"),
              "jaxdyn, bounded": in_solve(jaxdyn_rhs, "bounded"),
              "simulate": lambda q0, u0: batch(q0, u0)[0]}
    for f in (*loops.values(), *solves.values()):
        jax.block_until_ready(f(q0, u0 + 0.1))
    loop = interleaved({k: (lambda f=f: jax.block_until_ready(f(q0, u0 + 0.1)), ())
                        for k, f in loops.items()}, number=1, rounds=rounds)
    solve = interleaved({k: (lambda f=f: jax.block_until_ready(f(q0, u0)), ())
                         for k, f in solves.items()}, number=1, rounds=rounds)
    print("\nwhere the time goes (batch of 1024, mixed starts, one device):")
    print(f"  equations alone in a compiled loop: hand {loop['hand'] / 2048e3 * 1e9:.1f} ns per "
          f"member and evaluation, jaxdyn {loop['jaxdyn'] / loop['hand']:.2f}× hand")
    print(f"  inside diffrax's vmapped Tsit5 solve: hand {solve['hand'] * 1e3:.0f} ms, jaxdyn's "
          f"equations {solve['jaxdyn'] / solve['hand']:.2f}×; stages in a bounded loop: hand "
          f"{solve['hand, bounded'] / solve['hand']:.2f}×, jaxdyn's equations "
          f"{solve['jaxdyn, bounded'] / solve['hand']:.2f}×; simulate_batch (bounded) "
          f"{solve['simulate'] / solve['hand']:.2f}×")


_CHILD = """
import json, os, resource, sys, time
sys.path.insert(0, {here!r})
import numpy as np, jax, diffrax
jax.config.update("jax_enable_x64", True)
import jaxdyn, bench_batch as b
from _systems import DOUBLE_PENDULUM, as_arrays
task = {task!r}
q0, u0 = b.starts(task["size"])
p = as_arrays(DOUBLE_PENDULUM.params)
options = dict(b.OPTIONS, **task.get("options", {{}}))
if "ts" in options:
    options["ts"] = np.linspace(0.0, b.T1, options["ts"])
def run():
    return jaxdyn.simulate_batch(DOUBLE_PENDULUM.dynamics, q0, u0, p, **options,
                                 **task.get("kwargs", {{}}))
start = time.perf_counter(); jax.block_until_ready(run()); first = time.perf_counter() - start
times = []
for _ in range(task.get("rounds", 1)):
    start = time.perf_counter()
    jax.block_until_ready(run())
    times.append(time.perf_counter() - start)
print(json.dumps(dict(first=first, seconds=min(times), devices=len(jax.devices()),
                      rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)))
"""


def child(task, devices=1):
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "")
               + f" --xla_force_host_platform_device_count={devices}")
    script = _CHILD.format(here=os.path.dirname(os.path.abspath(__file__)), task=task)
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def scaling(rounds):
    print("\ndevice scaling (batch of 1024, simulated CPU devices on this machine's "
          f"{os.cpu_count()} cores; each in its own process):")
    base = None
    for devices in (1, 2, 4):
        result = child(dict(size=1024, rounds=rounds), devices)
        base = base or result["seconds"]
        print(f"  {devices} device(s): {1024 / result['seconds']:6.0f} trajectories/s, "
              f"{base / result['seconds']:.2f}× one device; first call (compile + run) "
              f"{result['first']:.1f} s")


def memory():
    saves = 1001
    print(f"\npeak memory (resident set of a fresh process; batch of 16384, q and u saved at "
          f"{saves} times: {16384 * saves * 4 * 8 / 2**20:.0f} MiB of results):")
    for name, kwargs in {"one chunk": {}, "chunks of 1024": dict(chunk_size=1024),
                         "max_bytes = 64 MiB": dict(max_bytes=64 * 2**20)}.items():
        result = child(dict(size=16384, options=dict(ts=saves, save=("q", "u")),
                            kwargs=kwargs))
        print(f"  {name:20s} peak {result['rss'] / 2**20:6.0f} MiB, {result['seconds']:.1f} s")


def compile_time():
    q0s, u0s = starts(1024)
    p = as_arrays(DOUBLE_PENDULUM.params)
    start = time.perf_counter()
    batch(q0s, u0s)[0].block_until_ready()
    first = time.perf_counter() - start
    vmapped = jax.jit(jax.vmap(lambda q0, u0: jaxdyn.simulate(DOUBLE_PENDULUM.dynamics, q0, u0,
                                                              p, **OPTIONS).q))
    start = time.perf_counter()
    vmapped(q0s, u0s).block_until_ready()
    print(f"\ncompile (first call, batch 1024, including the run): simulate_batch {first:.1f} s,"
          f" jax.jit(jax.vmap(simulate)) {time.perf_counter() - start:.1f} s")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--floor", action="store_true", help="only where the time goes")
    args = parser.parse_args()
    rounds = 2 if args.quick else 3
    if args.floor:
        return where_the_time_goes(rounds)
    compile_time()
    throughput((1, 64, 1024) if args.quick else (1, 64, 1024, 16384), rounds)
    where_the_time_goes(rounds)
    slowest_member(rounds)
    scaling(rounds)
    if not args.quick:
        memory()


if __name__ == "__main__":
    main()
