"""jaxdyn example: a box sliding, a box tumbling, friction identified from data, two balls
colliding.

A box (a free rigid body, 20 × 10 × 5 cm, 1 kg) touches compliant ground at its eight corners
(`jaxdyn.box_corners`) through `jaxdyn.Contact` with a Hunt–Crossley normal force and Coulomb
friction (`jaxdyn.HuntCrossley`). The script

1. pushes it across the floor at 2 m/s and checks its stopping distance against Coulomb's
   v₀²/(2 μ g);
2. throws it spinning onto the floor, where it bounces, tumbles and comes to rest on a face,
   its energy only ever falling;
3. identifies the friction coefficient μ from noisy "measurements" of the push (`jaxdyn.fit`,
   with its standard error);
4. collides two balls (`jaxdyn.ContactPair`) and checks that their momentum is kept;
5. plots the three boxes to docs/figures/sliding_box.png.

Run:  python examples/sliding_box.py
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

G, K, C, MU = 9.81, 1e6, 3.0, 0.5
SIZE, MASS = (0.2, 0.1, 0.05), 1.0
SOLVE = dict(rtol=1e-8, atol=1e-8)


def box_tree():
    a, b, h = SIZE
    inertia = MASS / 12 * jnp.diag(jnp.array([b * b + h * h, a * a + h * h, a * a + b * b]))
    return jaxdyn.RigidBodyTree([jaxdyn.Link("box", jaxdyn.Free(), mass=MASS, inertia=inertia)],
                                gravity=jnp.array([0.0, 0.0, -G]))


# The friction coefficient is a parameter, so that it can be identified.
box = jaxdyn.Contact(jaxdyn.ArticulatedBody(box_tree()), jaxdyn.box_corners("box", SIZE),
                     model=jaxdyn.HuntCrossley(K, C, friction=lambda p: p["mu"]))
sink = (MASS * G / 4 / K) ** (2 / 3)  # four corners carry the weight
flat = jnp.array([0.0, 0.0, SIZE[2] / 2 - sink, 1.0, 0.0, 0.0, 0.0])

# -- 1. sliding to rest ------------------------------------------------------------------------
V0 = 2.0
ts = np.linspace(0.0, 0.6, 61)
push = jnp.zeros(6).at[0].set(V0)  # (a free body's speeds are in its axes: v then ω)
start = time.perf_counter()
slid = jaxdyn.simulate(box, flat, push, {"mu": MU}, t1=ts[-1], ts=ts, save=("q", "contact"),
                       **SOLVE)
stop = V0**2 / (2 * MU * G)
print(f"sliding: stopped after {float(slid.q[-1, 0]):.4f} m, Coulomb v0²/(2 μ g) = {stop:.4f} m "
      f"({slid.num_steps} steps; {time.perf_counter() - start:.1f} s with compiling)")
assert abs(float(slid.q[-1, 0]) - stop) < 1e-3

# -- 2. tumbling -------------------------------------------------------------------------------
tilted = jnp.array([0.0, 0.0, 0.3, np.cos(0.3), np.sin(0.3) * 0.6, np.sin(0.3) * 0.8, 0.0])
spin = jnp.array([1.5, 0.0, 0.0, 8.0, -5.0, 3.0])
tt = np.linspace(0.0, 2.0, 401)
tumbled = jaxdyn.simulate(box, tilted, spin, {"mu": MU}, t1=tt[-1], ts=tt,
                          save=("q", "u", "contact"), **SOLVE)
# The box's energy T + V (the ground's elastic energy not counted: it dips while a corner
# presses in); in flight, between touches, it can only have fallen.
energy = np.asarray(box.energy(tt, tumbled.q, tumbled.u, {"mu": MU}))
flying = np.all(np.asarray(tumbled.contact.gap) > 0, axis=1)
touching = np.sum(np.asarray(tumbled.contact.gap[-1]) < 0)
print(f"tumbling: energy {energy[0]:.3f} J → {energy[-1]:.3f} J over {int(np.sum(~flying))} "
      f"samples in contact, never rising from one flight to the next (by at most "
      f"{max(np.max(np.diff(energy[flying])), 0.0):.1e} J); at rest on {touching} corners, "
      f"speed {float(jnp.max(jnp.abs(tumbled.u[-1]))):.1e}")
assert touching == 4 and np.max(np.diff(energy[flying])) < 1e-6

# -- 3. friction identified from a noisy push --------------------------------------------------
rng = np.random.default_rng(0)
measured = np.asarray(slid.q[:, :2]) + 1e-3 * rng.standard_normal((len(ts), 2))
experiment = jaxdyn.Experiment(ts, measured, flat, push, weights=1e6)  # σ = 1 mm
start = time.perf_counter()
result = jaxdyn.fit(box, [experiment], {"mu": jnp.asarray(0.3)},
                    observe=lambda t, q, u, p: q[:2])
print(f"identified μ = {float(result.params['mu']):.4f} ± {float(result.standard_errors['mu']):.4f}"
      f" (true {MU}) in {time.perf_counter() - start:.1f} s; converged: {result.converged}")
assert result.converged and abs(float(result.params["mu"]) - MU) < 5 * float(
    result.standard_errors["mu"])

# -- 4. two balls colliding ---------------------------------------------------------------------
r = 0.05
balls = jaxdyn.RigidBodyTree(
    [jaxdyn.Link(name, jaxdyn.Free(), mass=m, inertia=0.4 * m * r * r * jnp.eye(3))
     for name, m in (("a", 1.0), ("b", 0.5))], gravity=jnp.zeros(3))
pair = jaxdyn.Contact(jaxdyn.ArticulatedBody(balls), [jaxdyn.ContactPair(
    jaxdyn.ContactPoint("a", radius=r), jaxdyn.ContactPoint("b", radius=r))],
    model=jaxdyn.HuntCrossley(K, 0.3, friction=0.4))
q0 = jnp.array([-0.2, 0.03, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
u0 = jnp.array([2.0, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
hit = jaxdyn.simulate(pair, q0, u0, t1=0.2, ts=jnp.array([0.0, 0.2]), save=("q", "u"), **SOLVE)


def momentum(q, u):  # (a free body's speeds are in its own axes: turned to the world's)
    return sum(m * jaxdyn.rotations.quaternion(q[7 * i + 3:7 * i + 7]) @ u[6 * i:6 * i + 3]
               for i, m in enumerate((1.0, 0.5)))


before, after = momentum(hit.q[0], hit.u[0]), momentum(hit.q[-1], hit.u[-1])
print(f"two balls: momentum {np.asarray(before)} → {np.asarray(after).round(10)} kg m/s; "
      f"ball b leaves at {np.asarray(hit.u[-1, 6:9]).round(3)} m/s (in its axes)")
assert np.max(np.abs(after - before)) < 1e-8

# -- 5. figure ---------------------------------------------------------------------------------
figure, (left, middle, right) = plt.subplots(1, 3, figsize=(13, 3.6))
left.plot(ts, slid.q[:, 0], label="box")
left.axhline(stop, color="k", ls="--", label="v₀²/(2 μ g)")
left.set(xlabel="t (s)", ylabel="x (m)", title="pushed at 2 m/s, μ = 0.5")
left.legend()
middle.plot(tt, energy, label="energy T + V (J)")
middle.plot(tt, np.sum(np.asarray(tumbled.contact.normal_force), axis=1) / 100,
            label="normal force / 100 N", alpha=0.6)
middle.set(xlabel="t (s)", xlim=(0.0, 0.6), title="thrown spinning: lands, tumbles, rests")
middle.legend()
for mu, style, label in ((0.3, "--", "first guess μ = 0.3"),
                         (float(result.params["mu"]), "-", "fitted")):
    model = jaxdyn.simulate(box, flat, push, {"mu": mu}, t1=ts[-1], ts=ts, **SOLVE)
    right.plot(ts, model.q[:, 0], style, label=label)
right.plot(ts, measured[:, 0], ".", ms=3, color="k", label="measured (σ = 1 mm)")
right.set(xlabel="t (s)", ylabel="x (m)",
          title=f"μ fitted: {float(result.params['mu']):.4f} ± "
                f"{float(result.standard_errors['mu']):.4f}")
right.legend()
figure.tight_layout()
out = os.path.join(os.path.dirname(__file__), os.pardir, "docs", "figures", "sliding_box.png")
figure.savefig(out, dpi=110)
print("wrote", os.path.normpath(out))
