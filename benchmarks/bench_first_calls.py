"""First calls of jaxdyn's public entry points on small systems, each in a fresh process,
beside diffrax's first call on hand-written equations (issue "time to first result").

Rows, each measured in its own Python process (import excluded, float64, default options,
not jitted, as the README calls them); "later" is the slowest of two more calls with new
values of the same shapes (a new state, guess or parameter), which should compile nothing:

- floors: `jax.jit` of `diffrax.diffeqsolve` on the double pendulum's hand-written closed
  form (unit masses and lengths) with `simulate`'s default solver and tolerances (Dopri8,
  rtol = atol = 1e-10, 10 s), first call; and the first `jax.grad` of a loss on its final
  state through that solve (diffrax's default adjoint);
- the double pendulum from T and V (`jaxdyn.Lagrangian`, p = {"g": 9.81}): `accelerations`,
  `simulate` (t1 = 10 s, default options), `jax.grad` of the same loss through `simulate`,
  `linearise` and `normal_modes` about the bottom;
- `equilibrium` of the cart-pole with the cart held at x = 0 (the input is solved for);
- `fit` of a damped oscillator's stiffness and damping to 101 samples of its position
  (a result within 5 s is the issue's target for systems of up to three coordinates);
- with `--robots`: the Panda, UR5, ANYmal-C, G1 and Talos from example-robot-data, loaded by
  `from_urdf` (parameters traced), then the first call of forward dynamics
  (`ArticulatedBody.accelerations`), inverse dynamics (`residual`), a frame's pose and
  Jacobian, and the inverse-dynamics regressor, each timed (target: 3 s a call).

With `--cache`, each row runs again in two more processes sharing JAX's persistent
compilation cache (a fresh directory): the second process's first call is what a user who
enabled the cache waits for in every later session.

Run:  python benchmarks/bench_first_calls.py           (about 1 minute)
      python benchmarks/bench_first_calls.py --cache   (about 2 minutes)
      python benchmarks/bench_first_calls.py --robots  (adds the five robots: 2 minutes)
      python benchmarks/bench_first_calls.py --check   (exit 1 when a row misses its target)
      python benchmarks/bench_first_calls.py --record  (write benchmarks/results/first_calls.csv)
      python benchmarks/bench_first_calls.py --repeat 3  (three rounds, medians: on a noisy
                                                          machine one fresh process each can
                                                          be 30 % off)
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _results import Recorder  # noqa: E402

PRELUDE = """
import json, time
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import jaxdyn
"""

FLOOR = """
import diffrax
def field(t, y, args):
    q1, q2, w1, w2 = y
    d = q1 - q2
    s, c = jnp.sin(d), jnp.cos(d)
    den = 2.0 - c * c  # m1 + m2 s², unit masses and lengths
    a1 = (-9.81 * 2 * jnp.sin(q1) - s * (w2**2 + w1**2 * c) + 9.81 * jnp.sin(q2) * c) / den
    a2 = (2 * w1**2 * s - 9.81 * 2 * jnp.sin(q2) + 9.81 * 2 * jnp.sin(q1) * c
          + w2**2 * s * c) / den
    return jnp.stack([w1, w2, a1, a2])
solve = jax.jit(lambda y0: diffrax.diffeqsolve(
    diffrax.ODETerm(field), diffrax.Dopri8(), 0.0, 10.0, None, y0,
    stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10), max_steps=100000).ys)
start = time.perf_counter()
jax.block_until_ready(solve(jnp.array([1.0, 0.5, 0.0, 0.0])))
print(json.dumps({"first": time.perf_counter() - start}))
"""

GRADIENT_FLOOR = FLOOR.replace("solve = jax.jit(lambda y0:", "solve = jax.grad(lambda y0: jnp.sum(")
GRADIENT_FLOOR = GRADIENT_FLOOR.replace("max_steps=100000).ys)", "max_steps=100000).ys[-1] ** 2))")

PENDULUM = """
pendulum = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * (qd[0]**2 + (qd[0] * jnp.cos(q[0]) + qd[1] * jnp.cos(q[1]))**2
                            + (qd[0] * jnp.sin(q[0]) + qd[1] * jnp.sin(q[1]))**2),
    lambda q, p: -p["g"] * (2 * jnp.cos(q[0]) + jnp.cos(q[1])))
import numpy as np
def state(i):  # a new state of the same shapes at each call
    return np.array([1.0 + 0.1 * i, 0.5]), np.zeros(2)
def loss(q0):
    return jnp.sum(jaxdyn.simulate(pendulum, q0, jnp.zeros(2), {"g": 9.81}, t1=10.0).q[-1] ** 2)
gradient = jax.grad(loss)
"""

CART_POLE = """
def T(q, qd, p):
    return (0.5 * (p["M"] + p["m"]) * qd[0]**2 + p["m"] * p["l"] * qd[0] * qd[1] * jnp.cos(q[1])
            + 0.5 * p["m"] * p["l"]**2 * qd[1]**2)
def V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])
plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])
p = dict(M=1.0, m=0.1, l=0.5, g=9.81)
"""

OSCILLATOR = """
import numpy as np
oscillator = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.5 * p["k"] * q @ q,
                               dissipation=lambda q, qd, p: 0.5 * p["c"] * qd @ qd)
ts = np.linspace(0.0, 10.0, 101)
truth = np.exp(-0.15 * ts) * np.cos(np.sqrt(4.0 - 0.15**2) * ts)  # k = 4, c = 0.3, x0 = 1
def guess(i):
    return {"k": 3.0 + 0.1 * i, "c": 0.5}
experiment = jaxdyn.Experiment(ts, truth[:, None], q0=np.ones(1), u0=np.array([-0.15]))
"""

TIMED = """
times = []
for i in range(3):
    start = time.perf_counter()
    jax.block_until_ready(CALL)
    times.append(time.perf_counter() - start)
print(json.dumps({"first": times[0], "later": max(times[1:])}))
"""

# name: (setup, the call with `i` the call's index, the target in floors, which floor)
ROWS = {
    "accelerations, double pendulum": (
        PENDULUM, "pendulum.accelerations(0.0, *state(i), {'g': 9.81})", 1.0, "forward"),
    "simulate, double pendulum, 10 s": (
        PENDULUM, "jaxdyn.simulate(pendulum, *state(i), {'g': 9.81}, t1=10.0).q", 1.0,
        "forward"),
    "jax.grad through simulate, double pendulum": (
        PENDULUM, "gradient(state(i)[0])", 1.0, "gradient"),
    "linearise, double pendulum": (
        PENDULUM, "jaxdyn.linearise(pendulum, 0.0, 0.01 * state(i)[0], np.zeros(2), "
                  "{'g': 9.81}).A", 1.0, "forward"),
    "normal_modes, double pendulum": (
        PENDULUM, "jaxdyn.normal_modes(pendulum, 0.0, np.zeros(2), {'g': 9.81 - 0.1 * i})"
                  ".natural_frequencies", 1.0, "forward"),
    "equilibrium, cart-pole held at x = 0": (
        CART_POLE, "jaxdyn.equilibrium(plant, np.array([0.0, 0.1 * (i + 1)]), p, "
                   "prescribed={0: 0.0}).q", 1.0, "forward"),
    "fit, damped oscillator (k, c), to the result": (
        OSCILLATOR, "jaxdyn.fit(oscillator, experiment, guess(i)).params['k']", None, None),
}
FIT_TARGET_SECONDS = 5.0

# The five robots of example-robot-data that the benchmarks use (`bench_trees.ROBOTS`): the
# URDF, whether the base floats, a frame.
ROBOTS = [("panda_description/urdf/panda.urdf", False, "panda_hand"),
          ("ur_description/urdf/ur5_robot.urdf", False, "tool0"),
          ("anymal_c_simple_description/urdf/anymal.urdf", True, "LF_FOOT"),
          ("g1_description/urdf/g1_29dof_rev_1_0.urdf", True, "left_rubber_hand"),
          ("talos_data/robots/talos_full_v2.urdf", True, "gripper_left_base_link")]
ROBOT_TARGET_SECONDS = 3.0

ROBOT = """
import numpy as np
start = time.perf_counter()
tree, p = jaxdyn.from_urdf(jaxdyn.example_robot_urdf({name!r}), floating={floating})
robot = jaxdyn.ArticulatedBody(tree)
times = {{"loading the URDF": time.perf_counter() - start}}
q = np.asarray(tree.neutral_configuration())
u, ud = np.full(tree.num_speeds, 0.1), np.full(tree.num_speeds, 0.2)
calls = {{
    "forward dynamics": lambda: robot.accelerations(0.0, q, u, p),
    "inverse dynamics": lambda: robot.residual(0.0, q, u, ud, p),
    "frame pose and Jacobian": lambda: (jaxdyn.frame_pose(tree, {frame!r}, q, p),
                                        jaxdyn.frame_jacobian(tree, {frame!r}, q, p)),
    "regressor": lambda: jaxdyn.inverse_dynamics_regressor(tree, q, u, ud, p),
}}
for what, call in calls.items():
    start = time.perf_counter()
    jax.block_until_ready(call())
    times[what] = time.perf_counter() - start
print(json.dumps(times))
"""


CACHE = """
jax.config.update("jax_compilation_cache_dir", {directory!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
"""


def fresh(code, prelude=""):
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(prelude + PRELUDE + code)],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _median(runs):
    """Each figure's median over runs (dicts of the same keys)."""
    return {key: statistics.median(run[key] for run in runs) for key in runs[0]}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--check", action="store_true")
    parser.add_argument("--cache", action="store_true")
    parser.add_argument("--robots", action="store_true")
    parser.add_argument("--record", action="store_true",
                        help="write the figures to benchmarks/results/first_calls.csv")
    parser.add_argument("--repeat", type=int, default=1,
                        help="rounds of fresh processes (floors and rows in turn); the "
                             "median of each figure is reported")
    args = parser.parse_args()
    recorder = Recorder("first_calls")
    rounds = []
    for _ in range(args.repeat):  # the floors and the rows in turn, against the day's drift
        floors = {"forward": fresh(FLOOR)["first"], "gradient": fresh(GRADIENT_FLOOR)["first"]}
        rounds.append((floors, {name: fresh("import numpy as np\n" + setup
                                            + TIMED.replace("CALL", call))
                                for name, (setup, call, _, _) in ROWS.items()}))
    floors = _median([floors for floors, _ in rounds])
    print(f"{'call':46s} {'first':>8s} {'/ floor':>8s} {'later':>9s}  target")
    print(f"{'floor: diffrax, hand-written double pendulum':46s} {floors['forward']:7.2f}s")
    print(f"{'floor: jax.grad through it':46s} {floors['gradient']:7.2f}s")
    missed = 0
    for name, (setup, call, target, floor) in ROWS.items():
        row = _median([rows[name] for _, rows in rounds])
        if floor is None:
            ratio, met = "", row["first"] <= FIT_TARGET_SECONDS
            goal = f"{FIT_TARGET_SECONDS:.0f} s"
        else:
            ratio = f"{row['first'] / floors[floor]:7.2f}x"
            met, goal = row["first"] <= target * floors[floor], f"{target}x {floor} floor"
        missed += not met
        if floor is None:
            recorder.add(f"{name}: first call, seconds", "", row["first"], "s",
                         FIT_TARGET_SECONDS)
        else:
            recorder.add(f"{name}: first call / the {floor} floor's", "",
                         row["first"] / floors[floor], "×", target)
        print(f"{name:46s} {row['first']:7.2f}s {ratio:>8s} {1e3 * row['later']:7.1f}ms  "
              f"{'ok' if met else 'MISS'} ({goal})", flush=True)
    print(f"\n{len(ROWS) - missed} of {len(ROWS)} rows meet their targets.")
    if args.cache:
        print("\nWith JAX's persistent compilation cache (jax_compilation_cache_dir): the "
              "first call of a second process")
        for name, (setup, call, _, _) in ROWS.items():
            with tempfile.TemporaryDirectory() as directory:
                code = "import numpy as np\n" + setup + TIMED.replace("CALL", call)
                prelude = "import jax\n" + CACHE.format(directory=directory)
                fresh(code, prelude)
                row = fresh(code, prelude)
            recorder.add(f"{name}: first call of a second process, persistent cache", "",
                         row["first"], "s")
            print(f"{name:46s} {row['first']:7.2f}s", flush=True)
    if args.robots:
        print(f"\nRobots (example-robot-data), first calls in a fresh process each; target "
              f"{ROBOT_TARGET_SECONDS:.0f} s a call")
        for name, floating, frame in ROBOTS:
            times = _median([fresh(ROBOT.format(name=name, floating=floating, frame=frame))
                             for _ in range(args.repeat)])
            late = [what for what, seconds in times.items()
                    if what != "loading the URDF" and seconds > ROBOT_TARGET_SECONDS]
            missed += bool(late)
            for what, seconds in times.items():
                if what != "loading the URDF":
                    recorder.add(f"first {what}, seconds", name.split("/")[-1].split(".")[0],
                                 seconds, "s", ROBOT_TARGET_SECONDS)
            print(f"{name.split('/')[-1]:24s} " + ", ".join(
                f"{what} {seconds:.2f} s" for what, seconds in times.items())
                + ("" if not late else "  MISS"), flush=True)
    if args.record:
        recorder.write()
    if args.check and missed:
        sys.exit(1)


if __name__ == "__main__":
    main()
