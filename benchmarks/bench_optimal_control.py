"""Trajectory optimisation: jaxdyn's iLQR (`solve_optimal_control`) against Crocoddyl's FDDP,
on the same problems, side by side in one process.

Run: python benchmarks/bench_optimal_control.py            (about 5 minutes on 2 cores, 3 of
                                                            them compiling the Panda's solves)
     python benchmarks/bench_optimal_control.py --quick    (no batch of 1024)
     python benchmarks/bench_optimal_control.py --record   (write results/optimal_control.csv)
     python benchmarks/bench_optimal_control.py --only anymal  (one problem, not recorded)

Needs the test extras and Crocoddyl (`pip install crocoddyl`) built against the installed
Pinocchio: crocoddyl 3.2.1 needs pin 4.0.0 (with pin 4.1 its dynamics lose gravity; the
script checks and stops).

Problems (those of tests/test_crocoddyl.py, where they are shown to be the same problem in
both libraries and to reach the same optimum):

- Panda: the arm (fingers locked) brings its hand to a point, N = 100 nodes of Δt = 0.01 s,
  semi-implicit Euler (Crocoddyl's `IntegratedActionModelEuler`), running cost on the hand's
  position, the joint speeds and the torques less gravity's, terminal cost on the position
  and speeds, torques bounded by the Panda's limits (87 / 12 N m). Guess: the torques that
  hold the start against gravity. Crocoddyl: `SolverBoxFDDP`.
- double pendulum: fully actuated, swung up from hanging to upright, state tracking and input
  cost, unbounded, N = 100, Δt = 0.01 s, semi-implicit Euler. Guess: zero torques.
  Crocoddyl: `SolverFDDP`.
- ANYmal-C, feet held: the floating-base quadruped moves its base by (3, 2, −5) cm in 0.4 s
  with its four feet held where they stand (`jaxdyn.HeldPoints` with Baumgarte's terms;
  Crocoddyl's `ContactModel3D` and contact forward dynamics, the same equations to round-off
  in the test), N = 20, Δt = 0.02 s, semi-implicit Euler (the base's rotation stepped along
  the quaternion's rate in jaxdyn, along SE(3)'s exponential in Crocoddyl: the optima differ
  by that), costs on the base's position, the speeds and the torques. Guess: the quasi-static
  torques of the stance (Crocoddyl's `quasiStatic`). Crocoddyl: `SolverFDDP`. One solve
  only: jaxdyn's first call compiles for about 1.5 minutes.

Both solvers start from the rollout of the same guess, declared feasible to Crocoddyl
(`solve(xs, us, maxiter, isFeasible=True)`: from an infeasible start `SolverBoxFDDP` takes
its first steps without the bounds, clipping them in the rollout, a different iteration), and
stop by their own default tests: jaxdyn when the full step's predicted decrease is below
1e-9 (1 + |J|), Crocoddyl when Σ‖Q_u‖² < th_stop = 1e-9; the iterations and final costs of
both are printed. Crocoddyl runs with `nthreads = 1` (its OpenMP threads over the nodes, set
to the cores, are printed beside it; on a loaded 2-core machine they slow it down).

Each problem runs in a process of its own (with `--record`, one after another): a process that
has just freed a large batch's buffers runs later programs slower (ANYmal-C's solve after
the double pendulum's batch of 1024: 2.47× Crocoddyl's time against 1.65×, while with glibc's
malloc kept from returning memory to the system, `MALLOC_TRIM_THRESHOLD_` and
`MALLOC_MMAP_THRESHOLD_` at 1 GB, 1.61×), which would time the allocator's state, not the
solver.

Measured: one solve to convergence (jaxdyn compiled, median over interleaved rounds), time per
iteration (solve / iterations), jaxdyn's first call in this process (trace, compile, one run);
jaxdyn's model-predictive control, time a control step (ten warm-started iterations and the
plant's `simulate` over the interval; jaxdyn only);
a batch of perturbed starts (Panda: joint angles ± 0.1 rad, 64 of them; pendulum ± 0.3 rad,
64 and 1024) solved by `jax.jit(jax.vmap(...))` in one program against Crocoddyl solving them
one after another, per problem, with the median of the costs' relative differences. Under
`vmap` jaxdyn too solves the problems one after another, each with its own iterations.

The cart-pole is left out: Crocoddyl has no cart-pole action model in C++ (its examples write
one in Python, whose callbacks per node would time Python, not Crocoddyl).
"""

import importlib.metadata
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import crocoddyl  # noqa: E402

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
# The problems are those of the Crocoddyl test, built by its functions.
sys.path.insert(0, os.path.join(os.path.dirname(__file__), os.pardir, "tests"))
from _results import Recorder  # noqa: E402
from _timing import interleaved  # noqa: E402
from test_crocoddyl import (  # noqa: E402
    N, anymal_problem, crocoddyl_mismatch, double_pendulum_problem, panda_problem)

MAX_ITERATIONS = 200
ROUNDS = 5
# Each batch is timed in up to ROUNDS rounds of both solvers, as many as fit in this many
# seconds (at least one).
BATCH_SECONDS = 60
# A single solve: SINGLE_ROUNDS rounds of both solvers, each of as many calls as take at least
# ROUND_SECONDS.
SINGLE_ROUNDS, ROUND_SECONDS = 9, 0.1
# jaxdyn per problem in a batch at or below Crocoddyl's sequential solves; one problem within
# 2× of Crocoddyl.
TARGET_BATCH, TARGET_SINGLE = 1.0, 2.0


# -- the problems ------------------------------------------------------------------------------

# The Panda's own torque limits (the test tightens two of them so that bounds are active).
PANDA_LIMITS = np.array([87.0] * 4 + [12.0] * 3)


def panda():
    case = panda_problem(limits=PANDA_LIMITS)
    hold = jax.jit(jax.vmap(case["hold"]))
    # A batch of 1024 would take about 10 minutes of each solver (0.1–0.6 s per problem).
    return dict(name="Panda", problem=case["problem"], p=case["p"], q0=case["q0"], spread=0.1,
                reference=case["reference"], bounded=True, batches=(64,),
                guesses=lambda q0s: np.asarray(hold(jnp.asarray(q0s))))


def double_pendulum():
    case = double_pendulum_problem(tempfile.mkdtemp())
    return dict(name="double pendulum", problem=case["problem"], p=case["p"], q0=case["q0"],
                spread=0.3, reference=case["reference"], bounded=False, batches=(64, 1024),
                guesses=lambda q0s: np.zeros((len(q0s), N, 2)))


def anymal():
    case = anymal_problem()
    joints = case["perm"][6:, 6:]  # Pinocchio's joint order from jaxdyn's
    return dict(name="ANYmal-C, feet held", problem=case["problem"], p=case["p"],
                q0=case["q0"], num_speeds=18, spread=0.0, reference=case["reference"],
                bounded=False, batches=(),
                guesses=lambda q0s: np.tile(case["guess"], (len(q0s), 1, 1)),
                crocoddyl_start=lambda q0, guess: (case["x0"], guess @ joints.T))


# -- the solvers -------------------------------------------------------------------------------

class CrocoddylSolves:
    """Crocoddyl's FDDP (BoxFDDP where bounded) from the rollout of a guess, one problem after
    another; its solver is built once (as in a loop of solves)."""

    def __init__(self, case, threads=1):
        self.problem = case["reference"]
        self.threads = threads
        kind = crocoddyl.SolverBoxFDDP if case["bounded"] else crocoddyl.SolverFDDP
        self.solver = kind(self.problem)
        self.nv = self.problem.runningModels[0].state.nv
        # jaxdyn's start and guess in Crocoddyl's state and input (the same but for a floating
        # base, whose quaternion Pinocchio stores last, and the joints' order).
        self.start = case.get("crocoddyl_start", lambda q0, guess: (
            np.concatenate([q0, np.zeros(self.nv)]), guess))

    def __call__(self, q0s, guesses):
        self.problem.nthreads = self.threads
        out = []
        for q0, guess in zip(q0s, guesses):
            self.problem.x0, guess = self.start(q0, guess)
            us = list(guess)
            self.solver.solve(self.problem.rollout(us), us, MAX_ITERATIONS, True)
            out.append((self.solver.cost, self.solver.iter))
        return np.array(out)


def jaxdyn_solve(case):
    """q0 (n,), guess (N, k) → (cost, iterations, status) of jaxdyn's iLQR, jitted."""
    problem, p = case["problem"], case["p"]
    num_speeds = case.get("num_speeds", case["q0"].shape[0])

    def solve(q0, guess):
        solution = jaxdyn.solve_optimal_control(problem, q0, jnp.zeros(num_speeds, q0.dtype), p,
                                                inputs=guess, solver=jaxdyn.ILQR(
                                                    max_iterations=MAX_ITERATIONS))
        return solution.cost, solution.iterations, solution.status

    return solve


def starts(case, size, seed=0):
    rng = np.random.default_rng(seed)
    q0s = case["q0"] + case["spread"] * rng.uniform(-1, 1, (size, case["q0"].shape[0]))
    return q0s, case["guesses"](q0s)


# -- the measurements --------------------------------------------------------------------------

def single(case, recorder):
    """One solve, both solvers: iterations, costs, time to convergence and per iteration."""
    name = case["name"]
    q0s = case["q0"][None]  # the nominal start
    guesses = case["guesses"](q0s)
    q0, guess = jnp.asarray(q0s[0]), jnp.asarray(guesses[0])
    ours = jax.jit(jaxdyn_solve(case))
    start = time.perf_counter()
    cost, iterations, status = (np.asarray(v) for v in ours(q0, guess))
    first = time.perf_counter() - start
    theirs = CrocoddylSolves(case)
    (their_cost, their_iterations), = theirs(q0s, guesses)
    threaded = CrocoddylSolves(case, threads=os.cpu_count() or 1)
    # Rounds of at least ROUND_SECONDS (a solve takes 1–100 ms): a round of a single call of
    # a short solve times the machine's hiccups as much as the solve.
    start = time.perf_counter()
    theirs(q0s, guesses)
    number = max(1, math.ceil(ROUND_SECONDS / (time.perf_counter() - start)))
    times = interleaved({"jaxdyn": (ours, (q0, guess)), "crocoddyl": (theirs, (q0s, guesses)),
                         "threaded": (threaded, (q0s, guesses))}, number=number,
                        rounds=SINGLE_ROUNDS)
    ours_t, theirs_t = times["jaxdyn"], times["crocoddyl"]
    per_ours, per_theirs = ours_t / iterations, theirs_t / their_iterations
    print(f"\n{name}: one solve from the nominal start")
    print(f"  jaxdyn    {int(iterations):3d} iterations, cost {float(cost):.12g} (status "
          f"{int(status)}), {ours_t * 1e3:8.2f} ms, {per_ours * 1e3:6.3f} ms/iteration; "
          f"first call {first:.1f} s")
    print(f"  Crocoddyl {int(their_iterations):3d} iterations, cost {their_cost:.12g}, "
          f"{theirs_t * 1e3:8.2f} ms, {per_theirs * 1e3:6.3f} ms/iteration "
          f"({os.cpu_count()} threads: {times['threaded'] * 1e3:.2f} ms)")
    print(f"  cost jaxdyn / Crocoddyl − 1 = {float(cost) / their_cost - 1:.2e}; "
          f"solve {ours_t / theirs_t:.2f}×, per iteration {per_ours / per_theirs:.2f}×")
    recorder.add("iterations, jaxdyn", name, float(iterations), "")
    recorder.add("iterations, Crocoddyl", name, float(their_iterations), "")
    recorder.add("jaxdyn one solve", name, ours_t * 1e3, "ms")
    recorder.add("Crocoddyl one solve", name, theirs_t * 1e3, "ms")
    recorder.add("one solve, jaxdyn / Crocoddyl", name, ours_t / theirs_t, "×", TARGET_SINGLE)
    recorder.add("per iteration, jaxdyn / Crocoddyl", name, per_ours / per_theirs, "×")
    recorder.add("jaxdyn first call (trace, compile, run)", name, first, "s")


def batch(case, size, recorder):
    """A batch of perturbed starts: jaxdyn's vmap against Crocoddyl's solves in turn."""
    name = case["name"]
    q0s, guesses = starts(case, size, seed=1)
    ours = jax.jit(jax.vmap(jaxdyn_solve(case)))
    args = (jnp.asarray(q0s), jnp.asarray(guesses))
    start = time.perf_counter()
    cost, iterations, status = (np.asarray(v) for v in ours(*args))
    first = time.perf_counter() - start
    theirs = CrocoddylSolves(case)
    # Rounds of both in turn, as many as fit in BATCH_SECONDS (a Panda batch takes tens of
    # seconds): the first round's Crocoddyl solves give its costs.
    samples, reference = {"jaxdyn": [], "crocoddyl": []}, None
    while not samples["jaxdyn"] or (
            len(samples["jaxdyn"]) < ROUNDS
            and (len(samples["jaxdyn"]) + 1) * sum(map(statistics.mean, samples.values()))
            <= BATCH_SECONDS):
        start = time.perf_counter()
        jax.block_until_ready(ours(*args))
        samples["jaxdyn"].append(time.perf_counter() - start)
        start = time.perf_counter()
        reference = theirs(q0s, guesses)
        samples["crocoddyl"].append(time.perf_counter() - start)
    ours_t, theirs_t = (statistics.median(samples[k]) / size for k in ("jaxdyn", "crocoddyl"))
    gap = np.abs(cost / reference[:, 0] - 1)
    print(f"\n{name}: batch of {size} (first call {first:.1f} s; {len(samples['jaxdyn'])} "
          "rounds)")
    print(f"  jaxdyn    converged {np.sum(status == 0)}/{size}, iterations median "
          f"{statistics.median(iterations):.0f}, max {iterations.max()}, "
          f"{ours_t * 1e3:8.3f} ms per problem")
    print(f"  Crocoddyl iterations median {statistics.median(reference[:, 1]):.0f}, max "
          f"{reference[:, 1].max():.0f}, {theirs_t * 1e3:8.3f} ms per problem")
    print(f"  costs: |jaxdyn / Crocoddyl − 1| median {np.median(gap):.1e}, max "
          f"{gap.max():.1e}; per problem {ours_t / theirs_t:.2f}×")
    recorder.add(f"per problem, batch of {size}, jaxdyn / Crocoddyl", name, ours_t / theirs_t,
                 "×", TARGET_BATCH)
    recorder.add(f"jaxdyn per problem, batch of {size}", name, ours_t * 1e3, "ms")
    recorder.add(f"Crocoddyl per problem, {size} in turn", name, theirs_t * 1e3, "ms")


def mpc(case, recorder, steps=100):
    """jaxdyn's model-predictive control (`model_predictive_control`: ten warm-started iLQR
    iterations a step, the plant integrated by `simulate` over each interval) from the
    nominal start: time per control step, the first call beside it. jaxdyn only (Crocoddyl
    has no closed-loop driver of its own)."""
    name = case["name"]
    q0 = jnp.asarray(case["q0"])
    guess = jnp.asarray(case["guesses"](case["q0"][None])[0])

    def run():
        return jaxdyn.model_predictive_control(case["problem"], q0, jnp.zeros_like(q0),
                                               case["p"], num_steps=steps, inputs=guess)

    start = time.perf_counter()
    jax.block_until_ready(run())
    first = time.perf_counter() - start
    laps = []
    for _ in range(ROUNDS):
        start = time.perf_counter()
        loop = jax.block_until_ready(run())
        laps.append(time.perf_counter() - start)
    per_step = statistics.median(laps) / steps
    print(f"\n{name}: MPC, {steps} steps: {per_step * 1e3:.2f} ms a step (iterations a step: "
          f"median {statistics.median(np.asarray(loop.iterations)):.0f}); first call "
          f"{first:.1f} s")
    recorder.add("jaxdyn MPC, time a step", name, per_step * 1e3, "ms")


def main():
    mismatch = crocoddyl_mismatch()
    if mismatch is not None:
        sys.exit(mismatch)
    quick = "--quick" in sys.argv
    recorder = Recorder("optimal_control")
    makes = {make.__name__: make for make in (double_pendulum, panda, anymal)}
    if "--only" not in sys.argv:  # each problem in a process of its own (the module docstring)
        print(f"jax {jax.__version__}, crocoddyl {importlib.metadata.version('crocoddyl')}, "
              f"pin {importlib.metadata.version('pin')}, {os.cpu_count()} cores")
        for name in makes:
            with tempfile.TemporaryDirectory() as directory:
                rows = os.path.join(directory, "rows.json")
                subprocess.run([sys.executable, __file__, "--only", name, "--rows", rows,
                                *(["--quick"] if quick else [])], check=True)
                with open(rows) as file:
                    recorder.rows.extend(json.load(file))
        if "--record" in sys.argv:
            recorder.write()
        return
    wanted = sys.argv[sys.argv.index("--only") + 1]
    if wanted not in makes or "--record" in sys.argv:
        sys.exit("--only takes double_pendulum, panda or anymal, without --record")
    case = makes[wanted]()
    single(case, recorder)
    if case["name"] == "double pendulum":  # the Panda's MPC: examples/optimal_control.py
        mpc(case, recorder)
    for size in case["batches"][:1] if quick else case["batches"]:
        batch(case, size, recorder)
    if "--rows" in sys.argv:  # (a process of `--record`'s)
        with open(sys.argv[sys.argv.index("--rows") + 1], "w") as file:
            json.dump(recorder.rows, file)


if __name__ == "__main__":
    main()
