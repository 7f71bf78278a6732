"""jaxdyn example: ANYmal-C standing and trotting on compliant ground.

The quadruped (example-robot-data's URDF, its feet the file's 3 cm collision spheres) touches
the ground through `jaxdyn.Contact` with a Hunt–Crossley normal force and Coulomb friction
(`jaxdyn.HuntCrossley`); its twelve joints are driven by PD control towards a target posture
(`jaxdyn.Controlled` with a policy). The script

1. drops it from 0.1 m above its standing height and checks that it settles: the feet's
   vertical forces sum to its weight and the feet do not slide;
2. drops a batch of 64 robots from different heights and tilts (`jaxdyn.simulate_batch`, one
   compiled, vmapped solve) and reports the spread of their settled heights;
3. trots it open loop (diagonal legs swinging in phase) for 3 s and reports how far it went;
4. differentiates the distance trotted in 1 s with respect to the swing amplitude (`jax.grad`
   through the contact-rich solve) and checks it against a central difference;
5. plots the drop's forces and the trot's path to quadruped.png.

Run:  python -m pip install -e ".[robots]" && python examples/quadruped.py
"""

import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn

PATH = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf")
FEET = ["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"]
# The standing posture of the file's SRDF (HAA, HFE, KFE of LF, RF, LH, RH).
STANCE = jnp.array([-0.1, 0.7, -1.0, 0.1, 0.7, -1.0, -0.1, -0.7, 1.0, 0.1, -0.7, 1.0])
SOLVE = dict(rtol=1e-6, atol=1e-6)

tree, p = jaxdyn.from_urdf(PATH, floating=True)
feet = jaxdyn.urdf_contact_points(PATH, links=FEET)
weight = 9.81 * sum(float(link["mass"]) for link in p.values())


def trot(t, p):
    """Joint targets of an open-loop trot at 2 Hz: LF with RH, RF with LH; each leg swings its
    hip (HFE) fore and aft and lifts its knee (KFE) while swinging forward; the gait fades in
    over the first half second."""
    angle = 2 * jnp.pi * 2.0 * t + jnp.array([0.0, jnp.pi, jnp.pi, 0.0])
    lifted = jnp.maximum(jnp.sin(angle), 0.0)
    side = jnp.array([1.0, 1.0, -1.0, -1.0])  # the hind knees bend the other way
    hip = p["gait"]["swing"] * jnp.cos(angle) + 0.15 * lifted * side
    knee = -0.3 * lifted * side
    offset = jnp.stack([jnp.zeros(4), hip, knee], axis=1).reshape(-1)
    return STANCE + jnp.minimum(t / 0.5, 1.0) * offset


def pd(target):
    def policy(t, q, u, p):  # joint torques, 400 N m/rad and 10 N m s/rad
        return 400.0 * (target(t, p) - q[7:]) - 10.0 * u[6:]
    return policy


def scene(target):
    robot = jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 18)),
                              inputs=pd(target))
    return jaxdyn.Contact(robot, feet, model=jaxdyn.HuntCrossley(1e6, 1.0, friction=0.8))


standing_scene = scene(lambda t, p: STANCE)
trotting_scene = scene(trot)
p = {**p, "gait": {"swing": jnp.asarray(0.2)}}

upright = jnp.concatenate([jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), STANCE])
soles = [jaxdyn.frame_pose(tree, f.body, upright, p, point=f.point)[1][2] - f.radius
         for f in feet]
standing_height = -float(min(soles))
q_stand = upright.at[2].set(standing_height)
u_rest = jnp.zeros(18)

# 1. The drop.
ts = jnp.linspace(0.0, 1.5, 151)
start = time.perf_counter()
drop = jaxdyn.simulate(standing_scene, q_stand.at[2].add(0.1), u_rest, p, t1=1.5, ts=ts,
                       save=("q", "contact"), **SOLVE)
print(f"drop: first call {time.perf_counter() - start:.1f} s (compiling), "
      f"{int(drop.num_steps)} steps")
start = time.perf_counter()
jax.block_until_ready(jaxdyn.simulate(standing_scene, q_stand.at[2].add(0.1), u_rest, p,
                                      t1=1.5, ts=ts, save=("q", "contact"), **SOLVE).q)
print(f"      again {1e3 * (time.perf_counter() - start):.0f} ms for 1.5 s simulated")
vertical = np.asarray(drop.contact.force[:, :, 2].sum(axis=1))
slide = np.abs(np.asarray(drop.contact.position[-1, :, :2] - drop.contact.position[-51, :, :2]))
print(f"      settled: vertical forces {vertical[-1]:.2f} N, weight {weight:.2f} N; "
      f"feet moved {slide.max():.1e} m in the last 0.5 s; base at "
      f"{float(drop.q[-1, 2]):.4f} m (standing height {standing_height:.4f} m)")
assert abs(vertical[-1] / weight - 1) < 1e-3 and slide.max() < 1e-4

# 2. A batch of drops: heights 0-0.15 m above standing, tilted up to 0.1 rad about x.
key_heights, key_tilts = jax.random.split(jax.random.PRNGKey(0))
count = 64
heights = jax.random.uniform(key_heights, (count,), maxval=0.15)
tilts = jax.random.uniform(key_tilts, (count,), minval=-0.1, maxval=0.1)
q0s = jnp.tile(q_stand, (count, 1))
q0s = q0s.at[:, 2].add(heights).at[:, 3].set(jnp.cos(tilts / 2)).at[:, 4].set(jnp.sin(tilts / 2))
start = time.perf_counter()
batch = jaxdyn.simulate_batch(standing_scene, q0s, jnp.zeros((count, 18)), p, t1=1.5,
                              save=("q",), **SOLVE)
print(f"batch of {count} drops: {time.perf_counter() - start:.1f} s; settled heights "
      f"{float(batch.q[:, -1, 2].min()):.4f}–{float(batch.q[:, -1, 2].max()):.4f} m")

# 3. The trot.
ts_trot = jnp.linspace(0.0, 3.0, 301)
walk = jaxdyn.simulate(trotting_scene, q_stand, u_rest, p, t1=3.0, ts=ts_trot,
                       save=("q", "contact"), **SOLVE)
distance = float(walk.q[-1, 0] - walk.q[0, 0])
print(f"trot: {distance:.2f} m forward in 3 s ({distance / 2.5:.2f} m/s once under way), "
      f"{float(walk.q[-1, 1]):+.2f} m sideways, {int(walk.num_steps)} steps")
assert distance > 1.0


# 4. The gradient of the distance trotted in 1 s with respect to the swing amplitude.
def trotted(swing):
    gait = {**p, "gait": {"swing": swing}}
    return jaxdyn.simulate(trotting_scene, q_stand, u_rest, gait, t1=1.0, save=("q",),
                           **SOLVE).q[-1, 0]


swing = jnp.asarray(0.2)
gradient = jax.grad(trotted)(swing)
h = 1e-4
central = (trotted(swing + h) - trotted(swing - h)) / (2 * h)
print(f"d(distance in 1 s)/d(swing) = {float(gradient):.4f} m/rad (reverse mode), "
      f"{float(central):.4f} (central difference, h = {h})")
assert abs(gradient / central - 1) < 1e-2  # (the derivative is as accurate as the solve)

# 5. The figure.
figure, (forces, path) = plt.subplots(1, 2, figsize=(11, 4))
for k, name in enumerate(FEET):
    forces.plot(ts, drop.contact.force[:, k, 2], label=name.replace("_FOOT", ""))
forces.plot(ts, vertical, "k", label="sum")
forces.axhline(weight, color="grey", ls="--", label="weight")
forces.set(xlabel="t (s)", ylabel="vertical contact force (N)",
           title="ANYmal dropped from 0.1 m, PD-held stance")
forces.legend()
path.plot(walk.q[:, 0], walk.q[:, 1], label="base")
for k, name in enumerate(FEET):
    down = np.asarray(walk.contact.normal_force[:, k]) > 0
    path.plot(np.asarray(walk.contact.position[down, k, 0]),
              np.asarray(walk.contact.position[down, k, 1]), ".", ms=2,
              label=f"{name.replace('_FOOT', '')} on the ground")
path.set(xlabel="x (m)", ylabel="y (m)", title="open-loop trot, 3 s", aspect="equal")
path.legend(fontsize=7)
figure.tight_layout()
out = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "figures", "quadruped.png")
figure.savefig(out, dpi=110)
print("wrote", os.path.normpath(out))
