"""jaxdyn example: a six-axis robot arm loaded from URDF.

The arm (`examples/models/arm6.urdf`: six revolute joints with viscous damping, a gripper on a
fixed flange) becomes a `jaxdyn.RigidBodyTree` whose link masses, centres of mass, inertias and
joint damping are parameters. The script

1. lets the arm fall under gravity from a raised pose (motors off) and checks the power balance
   along the trajectory: the energy lost equals the work of the dampers, ∫ Σ c_i u_i² dt;
2. drives it to a target pose with a PD law plus gravity compensation, τ = K_p (q* − q) −
   K_d u − g(q), where g(q) is the forcing of the passive arm at rest (jaxdyn's own equations,
   called inside the controller);
3. differentiates the final gripper height of the falling arm with respect to the gripper's
   mass, and checks the derivative against a central difference;
4. plots the joint angles of both runs to robot_arm.png.

Run:  python examples/robot_arm.py
"""

import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import jaxdyn

HERE = os.path.dirname(os.path.abspath(__file__))
tree, p = jaxdyn.from_urdf(os.path.join(HERE, "models", "arm6.urdf"))
names = [link.name for link in tree.links if link.joint.nv == 1]
arm = jaxdyn.ArticulatedBody(tree)  # the articulated-body algorithm: the default for trees
print(f"arm6: {len(tree.links)} links, {tree.num_coordinates} joint angles ({', '.join(names)}), "
      f"total mass {sum(float(v['mass']) for v in p.values()):.2f} kg")

q0 = jnp.array([0.0, -1.2, 1.0, -0.5, 0.4, 0.0])  # rad
u0 = jnp.zeros(6)
t1 = 3.0
ts = jnp.linspace(0.0, t1, 301)

# -- 1. a passive fall, and the power balance ---------------------------------------------------
start = time.perf_counter()
fall = jaxdyn.simulate(arm, q0, u0, p, t1=t1, ts=ts, rtol=1e-10, atol=1e-10)
print(f"\n1. fall under gravity, motors off: {int(fall.num_steps)} steps, "
      f"{time.perf_counter() - start:.2f} s (compile included)")
energy = jax.vmap(arm.energy, (0, 0, 0, None))(fall.ts, fall.q, fall.u, p)
damping = jnp.array([p[link.name].get("damping", 0.0) for link in tree.links
                     if link.joint.nv == 1])
power = jnp.sum(damping * fall.u**2, axis=1)  # dissipated by the dampers
dissipated = jnp.sum(0.5 * (power[1:] + power[:-1]) * jnp.diff(fall.ts))  # trapezoid rule
print(f"   energy lost E(0) − E(t1) = {float(energy[0] - energy[-1]):.6f} J, "
      f"∫ Σ c u² dt = {float(dissipated):.6f} J (the trapezoid rule's error apart)")


# -- 2. PD control with gravity compensation ----------------------------------------------------
def controller(q, u, p):
    gravity_torque = arm.forcing(0.0, q, jnp.zeros_like(u), p)  # at rest: gravity alone
    return p["kp"] * (p["target"] - q) - p["kd"] * u - gravity_torque


driven = jaxdyn.ArticulatedBody(jaxdyn.RigidBodyTree(tree.links, gravity=tree.gravity,
                                                     forces=controller))
target = jnp.array([0.8, -0.6, 0.9, -0.3, -0.5, 0.2])
gains = {"kp": jnp.array([400.0, 400.0, 200.0, 50.0, 50.0, 20.0]),
         "kd": jnp.array([60.0, 60.0, 30.0, 5.0, 5.0, 1.0]), "target": target}
control = jaxdyn.simulate(driven, q0, u0, {**p, **gains}, t1=t1, ts=ts, rtol=1e-10, atol=1e-10)
print(f"\n2. PD + gravity compensation: |q(t1) − q*| = "
      f"{float(jnp.max(jnp.abs(control.q[-1] - target))):.2e} rad")


# -- 3. a derivative through the simulation -----------------------------------------------------
def gripper_height(gripper_mass):
    params = {**p, "gripper": {**p["gripper"], "mass": gripper_mass}}
    q_end = jaxdyn.simulate(arm, q0, u0, params, t1=1.0, rtol=1e-10, atol=1e-10).q[-1]
    rotations, origins = tree.link_poses(1.0, q_end, params)
    return origins[-1, 2]


mass = p["gripper"]["mass"]
derivative = jax.grad(gripper_height)(mass)
h = 1e-4
central = (gripper_height(mass + h) - gripper_height(mass - h)) / (2 * h)
print(f"\n3. d(gripper height at t = 1 s)/d(gripper mass) = {float(derivative):+.6f} m/kg "
      f"(central difference {float(central):+.6f})")

# -- 4. plot ------------------------------------------------------------------------------------
fig, axes = plt.subplots(1, 2, figsize=(11, 4))
for ax, solution, title in ((axes[0], fall, "motors off: falls under gravity, damped"),
                            (axes[1], control, "PD + gravity compensation to q*")):
    for i, name in enumerate(names):
        ax.plot(solution.ts, solution.q[:, i], label=name, color=f"C{i}")
        if solution is control:
            ax.axhline(float(target[i]), color=f"C{i}", lw=0.6, ls=":")
    ax.set_title(title)
    ax.set_xlabel("t [s]")
axes[0].set_ylabel("joint angle [rad]")
axes[1].legend(fontsize=8, loc="lower right")
fig.tight_layout()
fig.savefig("robot_arm.png", dpi=110)
print("\nwrote robot_arm.png")
