"""jaxdyn example: trajectory optimisation of a floating-base robot, ANYmal-C shifting its base
with its four feet held on the ground.

The quadruped (example-robot-data's URDF, a free base and twelve joints) keeps its feet where
they stand: `jaxdyn.HeldPoints` makes them holonomic constraints of `jaxdyn.Constrained`
(Lagrange's equations of the first kind, with Baumgarte's stabilisation), the twelve joint
torques the inputs (`jaxdyn.Controlled`). Over N = 20 intervals of 20 ms (semi-implicit
Euler, Crocoddyl's integrated action model) it moves its base by (3, 2, −5) cm:

    minimise  Σ_k Δt ½ (10² |p_k − p*|² + |u_k|² + 10⁻⁴ |τ_k|²) + ½ (10⁴ |p_N − p*|² + 10² |u_N|²)

with p the base's position, as residual costs (Gauss–Newton Hessians for iLQR). The script

1. finds the torques that hold the stance (the least-norm joint torques and foot forces that
   balance gravity at rest: the quasi-static guess, as Crocoddyl's `quasiStatic`);
2. solves the problem (`jaxdyn.solve_optimal_control`, iLQR), reports the base's motion, the
   feet's drift from their holds and the time of the first (compiling) and second solve;
3. replays the plan in `jaxdyn.simulate` (adaptive Dopri8 on the continuous equations) open
   loop and under the plan's feedback policy (`OptimalTrajectory.policy`), and compares
   where the base ends;
4. plots the base's path and the torques to quadruped_base_shift.png.

The same problem is solved by Crocoddyl in tests/test_crocoddyl.py (the same optimum to
6.6·10⁻⁵, the difference of the two discretisations of the base's rotation) and timed
against it in benchmarks/bench_optimal_control.py.

Run:  python -m pip install -e ".[robots]" && python examples/quadruped_base_shift.py
      (about a minute: the first solve compiles for half a minute on a 2-core CPU)
"""

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np

import jaxdyn

PATH = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf")
FEET = ["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"]
# The standing posture of the file's SRDF (HAA, HFE, KFE of LF, RF, LH, RH).
STANCE = np.array([-0.1, 0.7, -1.0, 0.1, 0.7, -1.0, -0.1, -0.7, 1.0, 0.1, -0.7, 1.0])
SHIFT = jnp.array([0.03, 0.02, -0.05])
N, DT = 20, 0.02

tree, p = jaxdyn.from_urdf(PATH, floating=True)
q0 = jnp.asarray(np.concatenate([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], STANCE]))
u0 = jnp.zeros(tree.num_speeds)
held = jaxdyn.HeldPoints.at(tree, FEET, q0, p)
plant = jaxdyn.Constrained(
    jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 18))),
    holonomic=held, stabilisation=jaxdyn.Baumgarte(10.0, 10.0))


def running(q, u, r, p):  # residuals ρ, ℓ = ½|ρ|²
    return jnp.concatenate([10.0 * (q[:3] - SHIFT), u, 1e-2 * r])


def terminal(q, u, p):
    return jnp.concatenate([100.0 * (q[:3] - SHIFT), 10.0 * u])


problem = jaxdyn.ShootingProblem(plant, running, terminal, num_nodes=N, dt=DT,
                                 discretisation=jaxdyn.SemiImplicitEuler())

# -- 1. the torques that hold the stance --------------------------------------------------------
# At rest, M·0 = f + B τ + Jᵀ λ: the joint torques τ and the feet's forces λ that balance
# gravity, the least-norm pair (18 equations, 24 unknowns). The gravity forces f are minus
# the inverse dynamics at rest; J stacks the feet's linear rows in world axes.
gravity = -np.asarray(jaxdyn.ArticulatedBody(tree).residual(0.0, q0, u0, u0, p))
jacobian = np.concatenate([np.asarray(jaxdyn.frame_jacobian(tree, foot, q0, p))[3:]
                           for foot in FEET])
actuation = np.eye(tree.num_speeds)[:, 6:]
solution = np.linalg.lstsq(np.hstack([actuation, jacobian.T]), -gravity, rcond=None)[0]
holding = solution[:12]
print(f"1. holding torques {np.round(holding, 1)} N·m; the feet carry "
      f"{np.round(solution[12:].reshape(4, 3)[:, 2], 1)} N")

# -- 2. the solve ----------------------------------------------------------------------------
guess = jnp.tile(jnp.asarray(holding), (N, 1))
start = time.perf_counter()
plan = jaxdyn.solve_optimal_control(problem, q0, u0, p, inputs=guess)
first = time.perf_counter() - start
start = time.perf_counter()
jax.block_until_ready(jaxdyn.solve_optimal_control(problem, q0, u0, p, inputs=guess))
second = time.perf_counter() - start
feet = np.stack([np.stack([np.asarray(jaxdyn.frame_pose(tree, foot, q, p)[1]) for foot in FEET])
                 for q in plan.q])
drift = 1e3 * np.max(np.linalg.norm(feet - feet[0], axis=-1))
print(f"2. {plan.message} in {int(plan.iterations)} iterations, cost {float(plan.cost):.6f}\n"
      f"   base moved by {np.round(1e2 * np.asarray(plan.q[-1, :3]), 2)} cm (target "
      f"{np.round(1e2 * np.asarray(SHIFT), 2)}); the feet drift at most {drift:.1f} mm from "
      f"their holds (semi-implicit Euler with Baumgarte's terms)\n"
      f"   first solve {first:.0f} s (compiling), second {1e3 * second:.0f} ms")

# -- 3. the plan replayed in continuous time ------------------------------------------------------
horizon = N * DT
replays = {}
for name, inputs in (("open loop", lambda t: plan.inputs[jnp.minimum(
        jnp.floor(t / DT).astype(int), N - 1)]), ("feedback policy", plan.policy())):
    replays[name] = jaxdyn.simulate(plant, q0, u0, p, t1=horizon, inputs=inputs,
                                    ts=plan.ts, rtol=1e-8, atol=1e-8, save=("q", "u"))
    end = np.round(1e2 * np.asarray(replays[name].q[-1, :3]), 2)
    apart = 1e3 * float(jnp.max(jnp.abs(replays[name].q[:, :3] - plan.q[:, :3])))
    print(f"3. {name} in simulate (Dopri8): base at {end} cm, {apart:.2f} mm from the plan at "
          "most")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    plt = None
if plt is not None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.5))
    for i, axis in enumerate("xyz"):
        axes[0].plot(plan.ts, 1e2 * plan.q[:, i], color=f"C{i}", label=f"{axis}, plan")
        axes[0].plot(plan.ts, 1e2 * replays["feedback policy"].q[:, i], "--", color=f"C{i}",
                     label=f"{axis}, simulate with the policy")
    axes[0].set_xlabel("t (s)")
    axes[0].set_title("base position (cm)")
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].step(plan.ts[:-1], plan.inputs, where="post", lw=0.8)
    axes[1].set_xlabel("t (s)")
    axes[1].set_title("joint torques (N·m)")
    fig.tight_layout()
    fig.savefig("quadruped_base_shift.png", dpi=110)
    print("\nplots: quadruped_base_shift.png")
