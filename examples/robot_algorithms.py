"""Rigid-body algorithms on a six-axis arm from URDF.

1. Inverse dynamics along a planned motion (recursive Newton–Euler, `residual`).
2. Identification of the arm's inertial parameters from noisy joint torques through the
   regressor: M u̇ + c − g = Y(q, u, u̇) π is linear in π (ten parameters per link), so the
   identifiable combinations follow from linear least squares; physically consistent
   parameters (each link a rigid body: pseudo-inertia positive definite) from the convex fit
   of `jaxdyn.fit_inertial_parameters`.
3. Computed-torque control of the gripper's tool point along a circle: the task-space
   acceleration from frame Jacobians (ẍ = J u̇ + J̇ u), the joint torques from inverse
   dynamics.

Run: python examples/robot_algorithms.py (writes robot_algorithms.png).
"""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

import jaxdyn

jax.config.update("jax_enable_x64", True)

URDF = pathlib.Path(__file__).parent / "models" / "arm6.urdf"
robot, p_true = jaxdyn.from_urdf(URDF, damping=False)
arm = jaxdyn.ArticulatedBody(robot)
m = robot.num_speeds
links = [link.name for link in robot.links]

# -- 1. Inverse dynamics along an exciting motion ------------------------------------------------
# A finite Fourier series per joint (Swevers et al., 1997): smooth, periodic, rich in frequency.
rng = np.random.default_rng(0)
amplitudes = rng.uniform(-0.4, 0.4, size=(2, 3, m))
base_frequency = 2 * np.pi / 10.0


def excitation(t):
    """(q, u, u̇) of the planned motion at time t."""
    def position(t):
        k = jnp.arange(1, 4)[:, None]
        return jnp.sum(amplitudes[0] * jnp.sin(k * base_frequency * t)
                       + amplitudes[1] * jnp.cos(k * base_frequency * t), axis=0)

    q, u = jax.jvp(position, (t,), (jnp.ones_like(t),))
    _, ud = jax.jvp(lambda t: jax.jvp(position, (t,), (jnp.ones_like(t),))[1], (t,),
                    (jnp.ones_like(t),))
    return q, u, ud


def torques_and_regressor(ts):
    q, u, ud = jax.vmap(excitation)(ts)
    tau = arm.residual(ts, q, u, ud, p_true)  # stacked states broadcast
    regressor = jax.vmap(lambda q, u, ud: jaxdyn.inverse_dynamics_regressor(robot, q, u, ud))(
        q, u, ud)
    return q, u, ud, tau, regressor


ts = jnp.linspace(0.0, 10.0, 401)
q, u, ud, tau, Y = torques_and_regressor(ts)
print(f"1. inverse dynamics along the planned motion: peak joint torques "
      f"{np.round(np.max(np.abs(tau), axis=0), 1)} N·m")

# -- 2. Identification from noisy torques --------------------------------------------------------
sigma = 0.05 * np.std(np.asarray(tau), axis=0)  # torque-sensor noise, 5 % of each joint's spread
measured = tau + sigma * rng.normal(size=tau.shape)
prior = jax.tree_util.tree_map(lambda x: 1.3 * x, p_true)  # CAD values 30 % off
result = jaxdyn.fit_inertial_parameters(robot, q, u, ud, measured, prior, weights=sigma**-2)
singular = result.singular_values
print(f"2. regressor: {10 * len(result.links)} inertial parameters of {len(result.links)} moving "
      f"links, {result.rank} identifiable combinations (what the joint axes cannot see is not); "
      f"condition number of the identifiable part {singular[0] / singular[result.rank - 1]:.1e}")

# Gautier and Khalil's base parameters: the combinations of π the torques determine.
base = result.base_parameters
relative = base.standard_errors / np.maximum(np.abs(base.values), 1e-12)
print(f"   {np.sum(relative < 0.1)} of {len(base.names)} base parameters determined to 10 %, "
      "e.g.:")
for i in np.argsort(-np.abs(base.values))[:2]:
    print(f"   {base.names[i]} = {base.values[i]:.4g} ± {base.standard_errors[i]:.2g}")

# A validation motion not used in the fit: torques predicted from each estimate.
ts_check = jnp.linspace(0.0, 10.0, 201) + 0.37
q_c, u_c, ud_c, tau_c, Y_c = torques_and_regressor(ts_check * 0.8)
for label, pi in (("least squares", result.least_squares),
                  ("physically consistent", result.inertial_parameters)):
    predicted = np.asarray(Y_c) @ np.asarray(pi).ravel()
    print(f"   {label:21s}: validation RMS error "
          f"{np.sqrt(np.mean((predicted - np.asarray(tau_c)) ** 2)):.3f} N·m "
          f"(noise RMS {np.sqrt(np.mean(sigma ** 2)):.3f}), weighted residual RMS "
          f"{result.least_squares_rms if label == 'least squares' else result.residual_rms:.3f}")
print(f"   consistent fit: {result.num_steps} Newton steps "
      f"({'converged' if result.converged else 'NOT converged'}), every link a rigid body")
for k in result.links:
    print(f"   {k:10s} mass {float(result.params[k]['mass']):6.3f} kg "
          f"(true {float(p_true[k]['mass']):6.3f}, prior {float(prior[k]['mass']):6.3f})")

# -- 3. Computed-torque control of the tool point along a circle ---------------------------------
tool = (0.0, 0.1, 0.0)  # in the gripper's axes
q_start = jnp.array([0.0, -0.6, 1.2, -0.6, 0.0, 0.0])
_, start = jaxdyn.frame_pose(robot, "gripper", q_start, p_true, point=tool)
radius, period = 0.1, 2.0


def target(t):
    """x_d(t): a circle in a vertical plane through the start, and its two rates."""
    def x(t):
        angle = 2 * jnp.pi * t / period
        return start + radius * jnp.stack([jnp.cos(angle) - 1.0, jnp.sin(angle),
                                           jnp.zeros_like(angle)])

    x_d, v_d = jax.jvp(x, (t,), (jnp.ones_like(t),))
    a_d = jax.jvp(lambda t: jax.jvp(x, (t,), (jnp.ones_like(t),))[1], (t,),
                  (jnp.ones_like(t),))[1]
    return x_d, v_d, a_d


def computed_torque(t, q, u, p):
    """τ = ID(q, u, u̇*): u̇* puts the task acceleration J u̇ + J̇ u at ẍ_d + K_d ė + K_p e (a
    damped pseudo-inverse, and joint damping in the null space of the three task rows)."""
    x_d, v_d, a_d = target(t)
    _, x = jaxdyn.frame_pose(robot, "gripper", q, p, point=tool)
    jacobian = jaxdyn.frame_jacobian(robot, "gripper", q, p, point=tool)[3:]
    bias = jaxdyn.frame_acceleration(robot, "gripper", q, u, jnp.zeros_like(u), p,
                                     point=tool)[3:]  # J̇ u
    command = a_d + 40.0 * (v_d - jacobian @ u) + 400.0 * (x_d - x) - bias
    pseudo_inverse = jacobian.T @ jnp.linalg.inv(jacobian @ jacobian.T + 1e-6 * jnp.eye(3))
    null = jnp.eye(m) - pseudo_inverse @ jacobian
    ud = pseudo_inverse @ command - null @ (5.0 * u)
    return arm.residual(t, q, u, ud, p)


plant = jaxdyn.Controlled(arm, list(range(m)), computed_torque)
ts_control = jnp.linspace(0.0, 2 * period, 201)
sol = jaxdyn.simulate(plant, q_start, jnp.zeros(m), p_true, t1=float(ts_control[-1]), ts=ts_control,
                      save=("q", "u", "inputs"))
tip = jax.vmap(lambda q: jaxdyn.frame_pose(robot, "gripper", q, p_true, point=tool)[1])(sol.q)
goal = jax.vmap(lambda t: target(t)[0])(ts_control)
tracking = np.linalg.norm(np.asarray(tip - goal), axis=1)
print(f"3. computed-torque tracking of a {radius} m circle: error {1e3 * tracking[-1]:.2e} mm "
      f"after {2 * period:.0f} s (starting at rest on the circle; "
      f"peak {1e3 * np.max(tracking):.2e} mm), "
      f"peak torque {np.max(np.abs(np.asarray(sol.inputs))):.1f} N·m")

# -- 4. The tool point held in the world, the joints free ---------------------------------------
# Lagrange's equations of the first kind with the tool point as three holonomic constraints
# (`HeldPoints`: C and γ from the tree's recursions); the arm sags about its held tip under
# gravity, and the multipliers are the hold's force on the tip.
hold = jaxdyn.HeldPoints.at(robot, ["gripper"], q_start, p_true, points=[tool])
held_arm = jaxdyn.Constrained(arm, holonomic=hold)
sol_held = jaxdyn.simulate(held_arm, q_start, jnp.zeros(m), p_true, t1=2.0,
                           ts=jnp.linspace(0.0, 2.0, 101), save=("q", "constraints"))
force = np.asarray(sol_held.constraints.multipliers)
off_hold = np.max(np.abs(np.asarray(sol_held.constraints.position_violation)))
moved = np.max(np.abs(np.asarray(sol_held.q[-1] - q_start)))
print(f"4. tool point held, joints free for 2 s: the tip {off_hold:.1e} m from its hold, "
      f"joints moved by up to {moved:.2f} rad, the hold's force on the tip "
      f"{np.round(force[-1], 2)} N")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].plot(np.asarray(tau_c)[:, 1], label="true")
    for (label, pi), style in zip((("least squares", result.least_squares),
                                   ("physically consistent", result.inertial_parameters)),
                                  ("--", ":")):
        axes[0].plot((np.asarray(Y_c) @ np.asarray(pi).ravel())[:, 1], style, label=label)
    axes[0].set(title="shoulder-lift torque, validation motion", xlabel="sample", ylabel="N·m")
    axes[0].legend()
    axes[1].plot(*np.asarray(goal)[:, :2].T, "k", label="target")
    axes[1].plot(*np.asarray(tip)[:, :2].T, "r--", label="tool point")
    axes[1].set(title="tool point (world x, y)", xlabel="x [m]", ylabel="y [m]", aspect="equal")
    axes[1].legend()
    axes[2].semilogy(ts_control, np.maximum(tracking, 1e-16))
    axes[2].set(title="tracking error", xlabel="t [s]", ylabel="m")
    fig.tight_layout()
    fig.savefig("robot_algorithms.png", dpi=100)
    print("wrote robot_algorithms.png")
except ImportError:
    pass
