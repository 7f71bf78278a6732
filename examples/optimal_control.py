"""jaxdyn example: optimal control by iLQR — a cart-pole swung up with a bounded force, the
optimal cost differentiated, a batch of swing-ups, model-predictive control under model error,
and a Panda arm reaching a point with a payload its controller does not know.

The cart-pole of `examples/cart_pole_lqr.py` (cart x, pole angle θ from the upward vertical, a
force F on the cart) starts hanging at rest, θ = π, and is to stand upright at rest after
N = 100 intervals of Δt = 25 ms (2.5 s), the force held over each interval and bounded:

    minimise  Σ_k Δt (10⁻² F_k² + 0.1 x_k²) + 10³ (|q_N|² + |q̇_N|²),   |F_k| ≤ 6 N,
    subject to (q, q̇)_{k+1} = RK4 step of the equations of motion.

The script

1. solves it (`jaxdyn.solve_optimal_control`, iLQR with box-constrained inputs) and replays
   the plan in `jaxdyn.simulate` (adaptive Dopri8) open loop and with the locally optimal
   feedback r = r_k + K_k (x − x_k) of the last Riccati sweep (`OptimalTrajectory.policy`);
   then solves it again on a variational integrator's discrete dynamics
   (`jaxdyn.VariationalStep`);
2. differentiates the optimal cost J* with respect to the pole and cart masses (implicit
   function theorem at the optimum) and checks against central differences;
3. solves 32 swing-ups from hanging ± 29° in one compiled program (`jax.vmap`);
4. runs model-predictive control (`jaxdyn.model_predictive_control`: the problem solved again
   every 25 ms from the measured state, ten iLQR iterations warm-started) on a cart-pole whose
   pole is 20 % heavier than the model's, against the open-loop plan and the feedback policy;
   then on rails of ±0.4 m (path constraints |x| ≤ 0.4 m, an augmented Lagrangian about
   iLQR), planned and in MPC;
5. plans a reach of the Panda arm's hand to a point 0.27 m away (torques limited to 87 N·m on
   joints 1–4 and 12 N·m on 5–7, residual costs, semi-implicit Euler at 10 ms) and runs it in
   MPC on an arm carrying 1 kg in the hand that the controller's model does not know, timing
   each MPC step;
6. pushes a block across compliant ground against Coulomb friction (a `jaxdyn.Contact`
   scene as the shooting problem's dynamics) and compares the force with the rigid Coulomb
   block's closed form.

Run:  python examples/optimal_control.py      (plots to optimal_control.png with matplotlib;
several minutes, most of them compiling the Panda's MPC loop)
"""

import time

import jax

jax.config.update("jax_enable_x64", True)  # mechanics wants float64; jaxdyn never sets it

import jax.numpy as jnp
import numpy as np

import jaxdyn

P = dict(M=1.0, m=0.1, l=0.5, g=9.81)


def T(q, qd, p):
    return (0.5 * (p["M"] + p["m"]) * qd[0] ** 2
            + p["m"] * p["l"] * qd[0] * qd[1] * jnp.cos(q[1])
            + 0.5 * p["m"] * p["l"] ** 2 * qd[1] ** 2)


def V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])


plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])  # the force acts on x


def running_cost(q, u, r, p):  # ℓ(q, u, r, p): a small force, the cart near the origin
    return 1e-2 * r @ r + 0.1 * q[0] ** 2


def terminal_cost(q, u, p):  # Φ(q, u, p): upright (θ = 0) and at rest, the cart at x = 0
    return 1e3 * (q @ q + u @ u)


BOUND = 6.0  # N: the unbounded optimum pushes with 8.1 N
problem = jaxdyn.ShootingProblem(plant, running_cost, terminal_cost, num_nodes=100, dt=0.025,
                                 input_bounds=(-BOUND, BOUND))
hanging, rest = jnp.array([0.0, np.pi]), jnp.zeros(2)


def timed(fn, *args, **kwargs):
    """fn's result and its wall time, the result computed (jax.block_until_ready)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return out, time.perf_counter() - start


def held(inputs, dt):
    """The zero-order hold of a plan's inputs as a policy π(t, q, u, p) for simulate."""
    return lambda t, q, u, p: inputs[jnp.clip(jnp.floor(t / dt).astype(int), 0,
                                              inputs.shape[0] - 1)]


# -- 1. the swing-up ----------------------------------------------------------------------------
plan, first = timed(jaxdyn.solve_optimal_control, problem, hanging, rest, P)
plan, again = timed(jaxdyn.solve_optimal_control, problem, hanging, rest, P)
saturated = np.mean(np.abs(np.asarray(plan.inputs)) >= BOUND - 1e-9)
print(f"1. swing-up: {plan.message}\n   {int(plan.iterations)} iterations, J* = "
      f"{float(plan.cost):.6f}; {first:.1f} s the first call (compiling), {1e3 * again:.0f} ms "
      "the second")
print(f"   q(2.5 s) = {np.asarray(plan.q[-1])}, q̇(2.5 s) = {np.asarray(plan.u[-1])}")
print(f"   peak |F| = {float(jnp.max(jnp.abs(plan.inputs))):.3f} N (bound {BOUND} N), at the "
      f"bound over {100 * saturated:.0f} % of the horizon")
ts = plan.ts
replay = jaxdyn.simulate(plant, hanging, rest, P, t1=2.5, ts=ts,
                         inputs=held(plan.inputs, problem.dt), save=("q", "u", "inputs"))
tracked = jaxdyn.simulate(plant, hanging, rest, P, t1=2.5, ts=ts,
                          inputs=plan.policy((-BOUND, BOUND)), save=("q", "u", "inputs"))
print("   replayed in simulate (Dopri8, adaptive): max |q(t_k) − q_k| open loop "
      f"{float(jnp.max(jnp.abs(replay.q - plan.q))):.1e} (the RK4 discretisation's error), "
      f"with the feedback policy {float(jnp.max(jnp.abs(tracked.q - plan.q))):.1e}; the "
      f"policy's peak force {float(jnp.max(jnp.abs(tracked.inputs))):.2f} N (clipped to the "
      "bound; the policy acts continuously where the plan held each force)")
# The same problem on a variational integrator's discrete dynamics (second order, symplectic).
variational = jaxdyn.ShootingProblem(plant, running_cost, terminal_cost, num_nodes=100,
                                     dt=0.025, input_bounds=(-BOUND, BOUND),
                                     discretisation=jaxdyn.VariationalStep())
plan_v = jaxdyn.solve_optimal_control(variational, hanging, rest, P)
replay_v = jaxdyn.simulate(plant, hanging, rest, P, t1=2.5, ts=ts,
                           inputs=held(plan_v.inputs, problem.dt))
print(f"   with jaxdyn.VariationalStep(): {int(plan_v.iterations)} iterations, J* = "
      f"{float(plan_v.cost):.6f}; replayed open loop "
      f"{float(jnp.max(jnp.abs(replay_v.q - plan_v.q))):.1e} (second order against RK4's "
      "fourth, the difference amplified open loop near the unstable upright)")

# -- 2. the optimal cost's derivatives ----------------------------------------------------------


def optimal_cost(m, M):
    return jaxdyn.solve_optimal_control(problem, hanging, rest, dict(P, m=m, M=M)).cost


(dm, dM), seconds = timed(jax.grad(optimal_cost, argnums=(0, 1)), P["m"], P["M"])
h = 1e-4
fd_m = (optimal_cost(P["m"] + h, P["M"]) - optimal_cost(P["m"] - h, P["M"])) / (2 * h)
fd_M = (optimal_cost(P["m"], P["M"] + h) - optimal_cost(P["m"], P["M"] - h)) / (2 * h)
print(f"\n2. dJ*/dm = {float(dm):.6f} (central difference {float(fd_m):.6f}), dJ*/dM = "
      f"{float(dM):.6f} (central difference {float(fd_M):.6f}) per kg; {seconds:.1f} s "
      "(compiling the solve and its adjoint)")

# -- 3. a batch of swing-ups, one program -------------------------------------------------------
angles = np.pi + jnp.linspace(-0.5, 0.5, 32)
swing_ups = jax.jit(jax.vmap(lambda theta: jaxdyn.solve_optimal_control(
    problem, jnp.array([0.0, theta]), rest, P)))
batch, first = timed(swing_ups, angles)
batch, again = timed(swing_ups, angles + 0.0)
converged = np.asarray(batch.converged)
print(f"\n3. 32 swing-ups from θ0 = π ± 0.5 rad: {converged.sum()} of 32 converged "
      f"({np.asarray(batch.iterations).min()}–{np.asarray(batch.iterations).max()} iterations),"
      f" J* from {float(batch.cost.min()):.3f} to {float(batch.cost.max()):.3f}, max |θ_N| = "
      f"{float(jnp.max(jnp.abs(batch.q[:, -1, 1]))):.1e} rad; {first:.1f} s the first call, "
      f"{again:.2f} s the second")

# -- 4. MPC with a heavier pole -----------------------------------------------------------------
heavy = dict(P, m=1.2 * P["m"])
open_loop = jaxdyn.simulate(plant, hanging, rest, heavy, t1=2.5, ts=ts,
                            inputs=held(plan.inputs, problem.dt))
feedback = jaxdyn.simulate(plant, hanging, rest, heavy, t1=2.5, ts=ts,
                           inputs=plan.policy((-BOUND, BOUND)))
mpc_steps = 200
mpc, first = timed(jaxdyn.model_predictive_control, problem, hanging, rest, P,
                   num_steps=mpc_steps, plant_parameters=heavy)
mpc, again = timed(jaxdyn.model_predictive_control, problem, hanging, rest, P,
                   num_steps=mpc_steps, plant_parameters=heavy)
print(f"\n4. the pole 20 % heavier than the model (m = {heavy['m']:.2f} kg): θ(2.5 s) open loop "
      f"{float(open_loop.q[-1, 1]):+.3f} rad, with the feedback policy "
      f"{float(feedback.q[-1, 1]):+.1e} rad")
print(f"   MPC over {mpc_steps} steps (5 s): θ(2.5 s) = {float(mpc.q[100, 1]):+.1e} rad, "
      f"θ(5 s) = {float(mpc.q[-1, 1]):+.1e} rad, x(5 s) = {float(mpc.q[-1, 0]):+.1e} m, peak "
      f"|F| {float(jnp.max(jnp.abs(mpc.inputs))):.2f} N; {int(mpc.iterations.sum())} iterations"
      f" in all, {int(np.sum(np.asarray(mpc.status) != 0))} steps stopped at their 10")
print(f"   {first:.1f} s the first call (compiling), {1e3 * again / mpc_steps:.1f} ms per step "
      "the second")

# The cart on rails of ±0.4 m (the unconstrained plan runs it 0.6 m out): path constraints.
on_rails = jaxdyn.ShootingProblem(
    plant, running_cost, terminal_cost, num_nodes=100, dt=0.025, input_bounds=(-BOUND, BOUND),
    path_constraints=lambda q, u, r, p: jnp.array([q[0] - 0.4, -q[0] - 0.4]))
plan_r = jaxdyn.solve_optimal_control(on_rails, hanging, rest, P)
mpc_r = jaxdyn.model_predictive_control(on_rails, hanging, rest, P, num_steps=mpc_steps,
                                        plant_parameters=heavy)
print(f"   on rails of ±0.4 m: plan {plan_r.message.split(':')[0]}, J* = "
      f"{float(plan_r.cost):.5f} (without rails {float(plan.cost):.5f}), max |x| "
      f"{float(jnp.max(jnp.abs(plan_r.q[:, 0]))):.6f} m (without "
      f"{float(jnp.max(jnp.abs(plan.q[:, 0]))):.3f}), "
      f"multipliers Σλ = {float(plan_r.path_multipliers.sum()):.4f} = −dJ*/dL; MPC with the "
      f"heavier pole: max |x| {float(jnp.max(jnp.abs(mpc_r.q[:, 0]))):.4f} m, θ(5 s) = "
      f"{float(mpc_r.q[-1, 1]):+.1e} rad")

# -- 5. the Panda reaching with an unknown payload ----------------------------------------------
tree, p = jaxdyn.from_urdf(jaxdyn.example_robot_urdf("panda"),
                           locked=("panda_finger_joint1", "panda_finger_joint2"))
body = jaxdyn.ArticulatedBody(tree)
arm = jaxdyn.Controlled(body, input_map=list(range(7)))
q_start = jnp.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
limits = jnp.array([87.0] * 4 + [12.0] * 3)  # N·m


def gravity_torque(q, p):  # the torque that holds the arm at rest at q
    return -body.forcing(0.0, q, jnp.zeros_like(q), p)


def hand(q, p):
    return jaxdyn.frame_pose(tree, "panda_hand", q, p)[1]


target = jnp.array([0.4, 0.25, 0.6])


def reach(q, u, r, p):  # residuals ρ, ℓ = ½|ρ|²: Gauss–Newton Hessians for iLQR
    return jnp.concatenate([jnp.sqrt(2e1) * (hand(q, p) - target), jnp.sqrt(2e-1) * u,
                            jnp.sqrt(2e-3) * (r - gravity_torque(q, p))])


def arrive(q, u, p):
    return jnp.concatenate([jnp.sqrt(2e3) * (hand(q, p) - target), jnp.sqrt(2e1) * u])


panda = jaxdyn.ShootingProblem(arm, reach, arrive, num_nodes=100, dt=0.01,
                               discretisation=jaxdyn.SemiImplicitEuler(),
                               input_bounds=(-limits, limits))
payload = {name: dict(values) for name, values in p.items()}
payload["panda_hand"]["mass"] = p["panda_hand"]["mass"] + 1.0
hold = gravity_torque(q_start, p)
guess = jnp.tile(hold, (panda.num_nodes, 1))  # zero torque: the arm falls and the guess diverges
print(f"\n5. Panda: hand from {np.round(np.asarray(hand(q_start, p)), 3)} to "
      f"{np.asarray(target)} m; holding torques at the start {np.round(np.asarray(hold), 2)} "
      f"N·m, with the 1 kg payload {np.round(np.asarray(gravity_torque(q_start, payload)), 2)}"
      " (limits 87 and 12)")
reach_plan, first = timed(jaxdyn.solve_optimal_control, panda, q_start, jnp.zeros(7), p,
                          inputs=guess)
reach_plan, again = timed(jaxdyn.solve_optimal_control, panda, q_start, jnp.zeros(7), p,
                          inputs=guess)
print(f"   plan: {reach_plan.message}; {int(reach_plan.iterations)} iterations, hand error at "
      f"1 s {1e3 * float(jnp.linalg.norm(hand(reach_plan.q[-1], p) - target)):.2f} mm, peak "
      f"torques {np.round(np.asarray(jnp.max(jnp.abs(reach_plan.inputs), 0)), 1)} N·m; "
      f"{first:.1f} s the first call, {again:.2f} s the second")
sagging = jaxdyn.simulate(arm, q_start, jnp.zeros(7), payload, t1=1.0, ts=reach_plan.ts,
                          inputs=held(reach_plan.inputs, panda.dt))
hand_steps = 150
arm_mpc = {}
for name, parameters in (("model", p), ("payload", payload)):
    arm_mpc[name], arm_mpc[name + " time"] = timed(
        jaxdyn.model_predictive_control, panda, q_start, jnp.zeros(7), p,
        num_steps=hand_steps, inputs=guess, plant_parameters=parameters)


def hand_errors(qs):
    return 1e3 * jnp.linalg.norm(jax.vmap(hand, (0, None))(qs, p) - target, axis=1)  # mm


informed = jaxdyn.model_predictive_control(panda, q_start, jnp.zeros(7), payload,
                                           num_steps=hand_steps, inputs=jnp.tile(
                                               gravity_torque(q_start, payload), (100, 1)),
                                           plant_parameters=payload)
print(f"   with the payload, the plan open loop: hand error at 1 s "
      f"{float(hand_errors(sagging.q)[-1]):.1f} mm")
for name, result in (("MPC, no payload", arm_mpc["model"]),
                     ("MPC, 1 kg unknown to it", arm_mpc["payload"]),
                     ("MPC whose model knows the 1 kg", informed)):
    print(f"   {name}: hand error at 1 s {float(hand_errors(result.q)[100]):.1f} mm, at 1.5 s "
          f"{float(hand_errors(result.q)[-1]):.1f} mm; peak torques "
          f"{np.round(np.asarray(jnp.max(jnp.abs(result.inputs), 0)), 1)} N·m")
print(f"   MPC of {hand_steps} steps (each: 10 iLQR iterations on 100 nodes and Dopri8 over "
      f"10 ms): {arm_mpc['model time']:.0f} s the first call (compiling), "
      f"{1e3 * arm_mpc['payload time'] / hand_steps:.0f} ms per step the second")

# -- 6. compliant contact: a block pushed against Coulomb friction ---------------------------
print("\n6. a 2 kg block on compliant ground (Coulomb friction 0.5) pushed 1 m, rest to rest, "
      "in 1 s")
MASS, MU, STIFFNESS = 2.0, 0.5, 1e6
block = jaxdyn.Controlled(jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * MASS * qd @ qd,
                                            lambda q, p: MASS * 9.81 * q[2]), input_map=[0])
ground = jaxdyn.Contact(block, [jaxdyn.ContactPoint(lambda q, p: q)],
                        model=jaxdyn.HuntCrossley(STIFFNESS, 1.0, friction=MU,
                                                  tangential_damping=0.02 * STIFFNESS,
                                                  smoothing=1e-5))
PUSH_NODES, PUSH_DT = 400, 0.0025  # an explicit step must resolve the ground's τ = 20 ms
push = jaxdyn.ShootingProblem(
    ground, lambda q, u, r, p: r, num_nodes=PUSH_NODES, dt=PUSH_DT,
    discretisation=jaxdyn.SemiImplicitEuler(),
    terminal_constraints=lambda q, u, p: jnp.array([q[0] - 1.0, u[0]]))
pushed = jaxdyn.solve_optimal_control(
    push, jnp.array([0.0, 0.0, -(MASS * 9.81 / STIFFNESS) ** (2 / 3)]), jnp.zeros(3), {},
    inputs=jnp.full((PUSH_NODES, 1), 1.2 * MU * MASS * 9.81))  # a guess that slides it
# The rigid Coulomb block: m a + μ m g, a the least-norm accelerations with x_N = 1, v_N = 0.
nodes = np.arange(PUSH_NODES)
conditions = np.stack([PUSH_DT**2 * (PUSH_NODES - nodes), PUSH_DT * np.ones(PUSH_NODES)])
coulomb = (MASS * conditions.T @ np.linalg.solve(conditions @ conditions.T, [1.0, 0.0])
           + MU * MASS * 9.81)
sliding = slice(PUSH_NODES // 10, PUSH_NODES - PUSH_NODES // 50)
print(f"   {pushed.message} ({int(pushed.iterations)} iterations); while it slides the force "
      f"is the rigid Coulomb block's to "
      f"{float(np.max(np.abs(pushed.inputs[sliding, 0] - coulomb[sliding]))):.3f} N")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    plt = None
if plt is not None:
    fig, axes = plt.subplots(2, 3, figsize=(14, 7))
    ax = axes[0, 0]
    ax.plot(ts, np.degrees(plan.q[:, 1]), label="θ plan (deg)")
    ax.plot(ts, np.degrees(tracked.q[:, 1]), "--", label="θ simulated, feedback")
    ax.plot(ts, 100 * plan.q[:, 0], label="x plan (cm)")
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=8)
    ax.set_title("1. swing-up from hanging")
    ax = axes[0, 1]
    ax.step(ts[:-1], plan.inputs[:, 0], where="post", label="plan")
    ax.axhline(BOUND, color="k", lw=0.6, ls=":")
    ax.axhline(-BOUND, color="k", lw=0.6, ls=":")
    ax.set_xlabel("t (s)")
    ax.set_title("force on the cart (N), bound ±6 N")
    ax = axes[0, 2]
    for k in range(angles.shape[0]):
        ax.plot(ts, np.degrees(batch.q[k, :, 1]), color="C0" if converged[k] else "C3",
                lw=0.7)
    ax.set_xlabel("t (s)")
    ax.set_title("3. 32 swing-ups, one program: θ (deg)")
    ax = axes[1, 0]
    ax.plot(ts, np.degrees(open_loop.q[:, 1]), label="plan, open loop")
    ax.plot(ts, np.degrees(feedback.q[:, 1]), label="plan + feedback policy")
    ax.plot(mpc.ts, np.degrees(mpc.q[:, 1]), label="MPC")
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=8)
    ax.set_title("4. θ (deg), pole 20 % heavier than the model")
    ax = axes[1, 1]
    ax.step(mpc.ts[:-1], mpc.inputs[:, 0], where="post")
    ax.set_xlabel("t (s)")
    ax.set_title("MPC's force (N)")
    ax = axes[1, 2]
    ax.semilogy(reach_plan.ts, hand_errors(sagging.q), label="plan, open loop, payload")
    for name, result in (("MPC, no payload", arm_mpc["model"]),
                         ("MPC, unknown payload", arm_mpc["payload"]),
                         ("MPC, payload known", informed)):
        ax.semilogy(result.ts, hand_errors(result.q), label=name)
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=8)
    ax.set_title("5. Panda: hand's distance to the target (mm)")
    fig.tight_layout()
    fig.savefig("optimal_control.png", dpi=110)
    print("\nplots: optimal_control.png")
