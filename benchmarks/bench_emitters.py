"""The straight-line programs of small systems under XLA's two CPU code generators.

jaxdyn evaluates the equations of small systems as straight-line scalar programs
(`jaxdyn._unroll`). XLA's CPU backend has two code generators for fused element-wise
computations: the newer fusion emitters (XLA's default) and the elemental emitters. On these
programs the fusion emitters produce code many times slower, so `import jaxdyn` selects the
elemental ones (`--xla_cpu_use_fusion_emitters=false`) unless XLA_FLAGS already names the
switch. This script measures both, each in a fresh process (the switch is read when JAX
starts its backend): forward dynamics of the UR5 arm (6 joints) and a chain of 6 rods
(articulated-body algorithm, unrolled) and of the double pendulum (Lagrange's equations), as
one jitted call, inside a compiled loop, and per state in a jitted vmap over 1024 states; and
the compile time of that vmap. A batch of double-pendulum simulations, the case the elemental
emitters make slower, is measured by `bench_default_paths.py --only batches` under
XLA_FLAGS=--xla_cpu_use_fusion_emitters=true and =false.

Run: python benchmarks/bench_emitters.py        (about 1 minute)
"""

import json
import os
import subprocess
import sys

MEASURE = r"""
import json, os, sys, time
sys.path.insert(0, os.path.join(os.getcwd(), "benchmarks"))
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import jaxdyn
from _systems import DOUBLE_PENDULUM_PARAMS, as_arrays, double_pendulum_T, double_pendulum_V
from _timing import in_loop, interleaved
from bench_trees import batch_of_states, chain_tree, robot_file

def cases():
    tree, _ = jaxdyn.from_urdf(robot_file("ur_description/urdf/ur5_robot.urdf"),
                               parameters=False, damping=False)
    ur5 = jaxdyn.ArticulatedBody(tree)
    qs, us = batch_of_states(6, 6, jnp.asarray(tree.neutral_configuration()), 0)
    yield "UR5, articulated body", ur5, qs, us, None
    rng = np.random.default_rng(0)
    yield ("chain of 6 rods, articulated body", jaxdyn.ArticulatedBody(chain_tree(6)),
           jnp.asarray(rng.normal(size=(1024, 6))), jnp.asarray(rng.normal(size=(1024, 6))), None)
    pendulum = jaxdyn.Lagrangian(double_pendulum_T, double_pendulum_V)
    yield ("double pendulum, Lagrange", pendulum, qs[:, :2], us[:, :2],
           as_arrays(DOUBLE_PENDULUM_PARAMS))

out = {}
for name, dynamics, qs, us, p in cases():
    t = jnp.asarray(0.0)
    f = lambda t, q, u, p: dynamics.accelerations(t, q, u, p, throw=False)
    batched = jax.jit(jax.vmap(f, (None, 0, 0, None)))
    start = time.perf_counter()
    jax.block_until_ready(batched(t, qs, us, p))
    compile_time = time.perf_counter() - start
    times = interleaved({"call": (jax.jit(f), (t, qs[0], us[0], p)),
                         "loop": (in_loop(f, 1000), (t, qs[0], us[0], p)),
                         "vmap": (batched, (t, qs, us, p))}, number=3, rounds=7)
    out[name] = {"call": times["call"], "loop": times["loop"] / 1000,
                 "vmap": times["vmap"] / qs.shape[0], "compile": compile_time}
print(json.dumps(out))
"""


def measure(flag):
    env = {**os.environ, "XLA_FLAGS": f"--xla_cpu_use_fusion_emitters={flag}"}
    done = subprocess.run([sys.executable, "-c", MEASURE], env=env, capture_output=True,
                          text=True, check=True, cwd=os.path.dirname(os.path.dirname(
                              os.path.abspath(__file__))))
    return json.loads(done.stdout.strip().splitlines()[-1])


def main():
    elemental, fusion = measure("false"), measure("true")
    print("µs per evaluation: elemental emitters (jaxdyn's choice) / fusion emitters (XLA's "
          "default) = ratio; compile of the vmap in s")
    for name in elemental:
        row = [f"{name:28s}"]
        for key in ("call", "loop", "vmap"):
            a, b = elemental[name][key] * 1e6, fusion[name][key] * 1e6
            row.append(f"{key} {a:8.2f} / {b:8.2f} = {a / b:6.3f}")
        row.append(f"compile {elemental[name]['compile']:.1f} / {fusion[name]['compile']:.1f}")
        print("  ".join(row))


if __name__ == "__main__":
    main()
