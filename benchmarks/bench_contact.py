"""Contact: ANYmal-C standing and trotting on flat ground, jaxdyn against MJX on the same model.

Both simulators load the same URDF (example-robot-data's anymal_c_simple_description) with the
same contact geometry: the four feet, spheres of 3 cm, against a ground plane, friction 0.8;
both drive the twelve joints by the same PD law, τ = 400 (q* − q) − 10 q̇, towards the file's
standing posture (standing) or an open-loop 2 Hz trot (trotting). They differ in the contact
model and the integration, as the two libraries do:

- jaxdyn: `jaxdyn.Contact` with `HuntCrossley(1e6, 1.0, friction=0.8)` (compliant, the
  ground's tangential deformation in the state), the articulated-body algorithm, diffrax's
  adaptive Tsit5 at rtol = atol = 1e-4 and 1e-6 (the default, Dopri8 at 1e-10, is the
  reference of the errors);
- MJX: MuJoCo's soft convex contact (default solref/solimp), its default Euler integrator at
  MuJoCo's default step of 2 ms (`mujoco-mjx`, in the benchmarks' extras).

Printed, per simulated second: one robot (jitted, warm), and per state in a vmapped batch of
`--batch` robots (default 1024) dropped from different heights, standing and trotting; the
first call's time (trace, compile, run): jaxdyn's in a fresh process each, with `simulate` not
jitted as the contact guide calls it and inside the caller's `jax.jit`, MJX's (always jitted)
in this process; the standing robot's settled vertical force against its weight in each, as a
check that both simulate the same scene.

Also the error of each after 1 s of the trot, against its own library's converged solution
(the models differ): MJX's default step trades accuracy for speed, so a comparison per state
says at which accuracy it holds.

Run:  python benchmarks/bench_contact.py [--batch 1024] [--seconds 1.0] [--record]
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

# A large vmapped batch wedges on jaxlib 0.10: its batched LAPACK kernels (MJX's Cholesky
# factorisations) split their batch into tasks on XLA's intra-op thread pool and wait for
# them, and two such kernels running at once hold every thread of a 2-core machine's pool
# (benchmarks/LOG.md, "Why the 1024 runs stall"). The kernels split nothing when the pool has
# one thread, which PJRT_NPROC sets (read when JAX starts its CPU client); both libraries run
# under it. MJX at a batch of 64, 1 s standing: 37.8 ms/s per state with two threads, 33.8
# with one (within the shared machine's noise).
# (Not for a first call timed in a fresh process, `--first-call`: it runs no batch, and a
# user's process has XLA's default pool.)
if "--first-call" not in sys.argv:
    os.environ.setdefault("PJRT_NPROC", "1")

import jax

# Dispatching synchronously keeps each row printed as soon as it is measured.
jax.config.update("jax_cpu_enable_async_dispatch", False)

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import numpy as np

import jaxdyn

def _positive_hatch(path):
    """The URDF with the 142 g hatch's inertia made positive definite (its off-diagonal terms
    equal its diagonal, a singular tensor MuJoCo refuses): the diagonal kept, for both."""
    text = open(path).read()
    text = text.replace('<inertia ixx="0.001" ixy="0.001" ixz="0.001" iyy="0.001" iyz="0.001" '
                        'izz="0.001"/>', '<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" '
                        'iyz="0" izz="0.001"/>')
    out = tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False)
    out.write(text)
    out.close()
    return out.name


PATH = _positive_hatch(
    jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf"))
FEET = ["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"]
STANCE = np.array([-0.1, 0.7, -1.0, 0.1, 0.7, -1.0, -0.1, -0.7, 1.0, 0.1, -0.7, 1.0])
KP, KD, MU = 400.0, 10.0, 0.8


def targets(t, swing):
    """The PD law's joint targets: the stance, plus (swing > 0) an open-loop trot."""
    angle = 2 * jnp.pi * 2.0 * t + jnp.array([0.0, jnp.pi, jnp.pi, 0.0])
    lifted, side = jnp.maximum(jnp.sin(angle), 0.0), jnp.array([1.0, 1.0, -1.0, -1.0])
    lift = jnp.where(swing > 0, 0.3, 0.0)
    hip = swing * jnp.cos(angle) + 0.5 * lift * lifted * side
    knee = -lift * lifted * side
    offset = jnp.stack([jnp.zeros(4), hip, knee], axis=1).reshape(-1)
    return STANCE + jnp.minimum(t / 0.5, 1.0) * offset


def timed(fn, *args):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


# -- jaxdyn --------------------------------------------------------------------------------

tree, params = jaxdyn.from_urdf(PATH, floating=True)
feet = jaxdyn.urdf_contact_points(PATH, links=FEET)
weight = 9.81 * sum(float(link["mass"]) for link in params.values())


def pd(t, q, u, p):
    return KP * (targets(t, p["swing"]) - q[7:]) - KD * u[6:]


robot = jaxdyn.Controlled(jaxdyn.ArticulatedBody(tree), input_map=list(range(6, 18)), inputs=pd)
scene = jaxdyn.Contact(robot, feet, model=jaxdyn.HuntCrossley(1e6, 1.0, friction=MU))
upright = jnp.concatenate([jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), STANCE])
standing_height = -min(float(jaxdyn.frame_pose(tree, f.body, upright, params, point=f.point)[1][2])
                       - f.radius for f in feet)


def jaxdyn_run(seconds, solver, tol):
    def run(q0, swing):
        sol = jaxdyn.simulate(scene, q0, jnp.zeros(18), {**params, "swing": swing}, t1=seconds,
                              save=("q", "contact"), solver=solver, rtol=tol, atol=tol)
        return sol.q[-1], jnp.sum(sol.contact.force[-1, :, 2]), sol.num_steps
    return run


# -- MJX -----------------------------------------------------------------------------------

def mujoco_model():
    """The URDF as MuJoCo compiles it (visual and non-sphere collision geometry dropped; bodies
    fixed to their parents fused into them, as jaxdyn welds them; the inertias of a few camera
    links of a few grams, which break the triangle inequality, balanced), with a free joint on
    the base, a ground plane, friction μ on the feet and position actuators
    τ = KP (ctrl − q) − KD q̇."""
    import mujoco

    text = open(PATH).read()
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)
    text = re.sub(r"<collision>((?!</collision>).)*?<(cylinder|mesh|box)\b.*?</collision>", "",
                  text, flags=re.S)
    text = re.sub(r"(<robot[^>]*>)", r'\1<mujoco><compiler discardvisual="true" '
                  r'fusestatic="true" balanceinertia="true"/></mujoco>'
                  r'<link name="world"/><joint name="root" type="floating"><parent link="world"/>'
                  r'<child link="base"/></joint>', text, count=1)
    model = mujoco.MjModel.from_xml_string(text)
    with tempfile.NamedTemporaryFile(suffix=".xml") as f:
        mujoco.mj_saveLastXML(f.name, model)
        root = ET.parse(f.name).getroot()
    world = root.find("worldbody")
    for joint in root.iter("joint"):  # jaxdyn's tree has neither joint limits nor torque limits
        for limit in ("range", "actuatorfrcrange", "limited"):
            joint.attrib.pop(limit, None)
    world.insert(0, ET.Element("geom", name="floor", type="plane", size="0 0 1",
                               friction=f"{MU} 0.005 0.0001"))
    for geom in root.iter("geom"):
        if geom.get("type") == "sphere":
            geom.set("friction", f"{MU} 0.005 0.0001")
    actuators = ET.SubElement(root, "actuator")
    joints = [j.get("name") for j in root.iter("joint") if j.get("type", "hinge") == "hinge"]
    # (the floating root becomes a free joint)
    for name in joints:
        ET.SubElement(actuators, "position", joint=name, kp=str(KP), kv=str(KD))
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode")), joints


def mjx_run(model, seconds):
    from mujoco import mjx

    mx = mjx.put_model(model)
    steps = int(round(seconds / model.opt.timestep))

    def run(qpos0, swing):
        data = mjx.make_data(mx).replace(qpos=qpos0)

        def step(data, k):
            data = data.replace(ctrl=targets(k * model.opt.timestep, swing))
            return mjx.step(mx, data), None

        data, _ = jax.lax.scan(step, data, jnp.arange(steps))
        # vertical contact forces on the feet: the constraint forces along +z of each contact
        force = jnp.sum(data.qfrc_constraint[2])  # the base's z row: total vertical support
        return data.qpos, force, jnp.asarray(steps)
    return run


def errors_after_a_trot(seconds):
    """Each setting's error after `seconds` of the trot from standing height, against its own
    library's converged solution of its own model (the two contact models differ, so each is
    measured against itself): jaxdyn's default solver (Dopri8 at rtol = atol = 1e-10), MJX's
    Euler at 0.1 ms. The base's position error (m)."""
    start = upright.at[2].set(standing_height)
    out = {}
    reference = jax.jit(jaxdyn_run(seconds, diffrax.Dopri8(), 1e-10))(start, 0.2)[0]
    for name, tol in JAXDYN.items():
        q = jax.jit(jaxdyn_run(seconds, diffrax.Tsit5(), tol))(start, 0.2)[0]
        out[name] = float(jnp.linalg.norm(q[:3] - reference[:3]))
    try:
        model, _ = mujoco_model()
    except ImportError:
        return out
    finest = model.opt.timestep
    model.opt.timestep = 1e-4
    reference = jax.jit(mjx_run(model, seconds))(start, 0.2)[0]
    model.opt.timestep = finest
    q = jax.jit(mjx_run(model, seconds))(start, 0.2)[0]
    out[MJX] = float(jnp.linalg.norm(q[:3] - reference[:3]))
    return out


def fresh_first_call(tol, way, seconds):
    """The first call of jaxdyn's run (`way`: "eager", simulate not jitted; "staged", inside
    `jax.jit`) in a new process, in seconds."""
    out = subprocess.run([sys.executable, __file__, "--first-call", way, "--tol", str(tol),
                          "--seconds", str(seconds)], capture_output=True, text=True,
                         check=True, env={k: v for k, v in os.environ.items()
                                          if k != "PJRT_NPROC"}).stdout
    return float(out.strip().splitlines()[-1])


def first_call(tol, way, seconds):
    run = jaxdyn_run(seconds, diffrax.Tsit5(), tol)
    call = run if way == "eager" else jax.jit(run)
    print(timed(call, upright.at[2].set(standing_height + 0.02), 0.0))


# jaxdyn's settings: Tsit5 at two tolerances (the default, Dopri8 at 1e-10, is the reference
# of the errors); MJX's own default integrator and step.
JAXDYN = {"jaxdyn Tsit5 1e-4": 1e-4, "jaxdyn Tsit5 1e-6": 1e-6}
MJX = "MJX Euler 2 ms"


def main():
    from _results import Recorder

    parser = argparse.ArgumentParser()
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--record", action="store_true")
    parser.add_argument("--first-call", choices=("eager", "staged"))  # (`fresh_first_call`)
    parser.add_argument("--tol", type=float)
    args = parser.parse_args()
    if args.first_call:
        return first_call(args.tol, args.first_call, args.seconds)
    seconds, batch = args.seconds, args.batch
    heights = standing_height + 0.02 + 0.08 * jnp.linspace(0.0, 1.0, batch)
    q0s = jnp.tile(upright, (batch, 1)).at[:, 2].set(heights)
    print(f"ANYmal-C, {seconds} s simulated, batch of {batch}; CPU: {jax.devices()[0]}")
    print(f"weight {weight:.2f} N, standing height {standing_height:.4f} m\n")

    runs = {name: jaxdyn_run(seconds, diffrax.Tsit5(), tol) for name, tol in JAXDYN.items()}
    try:
        model, joints = mujoco_model()
        assert len(joints) == 12
        # MuJoCo's qpos: base position, quaternion (w, x, y, z), joints: jaxdyn's order.
        runs[MJX] = mjx_run(model, seconds)
    except ImportError as error:
        print(f"(MJX not installed: {error}; pip install -e '.[benchmarks]')")
    print(f"{'':22s} {'first':>7s} {'first':>7s} {'standing':>9s} {'trotting':>9s} "
          f"{'batch':>10s} {'batch trot':>10s}  settled vertical force")
    print(f"{'':22s} {'one':>7s} {'batch':>7s} {'ms/s':>9s} {'ms/s':>9s} {'ms/s/state':>10s}"
          f" {'ms/s/state':>10s}  one, batch median (N)    steps", flush=True)
    rows = {}
    for name, run in runs.items():  # (each row printed as soon as it is measured)
        one = jax.jit(run)
        many = jax.jit(jax.vmap(run, in_axes=(0, None)))
        # jaxdyn's first calls each in a fresh process (in this one, the traces of the row
        # before would be reused): as the contact guide and the quadruped example call it,
        # `simulate` not jitted (its program without the diagnosis of failures, which only
        # a failed solve compiles), and inside the caller's own `jax.jit` (the diagnosis
        # then part of the program). MJX's run is always jitted.
        if name == MJX:
            first = first_staged = timed(one, q0s[0], 0.0)
        else:
            first, first_staged = (fresh_first_call(JAXDYN[name], way, seconds)
                                   for way in ("eager", "staged"))
        (q, force, steps) = one(q0s[0], 0.0)
        single = min(timed(one, q0s[0], 0.0) for _ in range(3))
        trot = min(timed(one, upright.at[2].set(standing_height), 0.2) for _ in range(2))
        first_batch = timed(many, q0s, 0.0)
        start = time.perf_counter()
        qs, forces, _ = jax.block_until_ready(many(q0s, 0.0))
        per_state = (time.perf_counter() - start) / batch
        trot_state = timed(many, q0s, 0.2) / batch
        rows[name] = dict(first=first, first_staged=first_staged, first_batch=first_batch,
                          single=single / seconds,
                          trot=trot / seconds, batch=per_state / seconds,
                          batch_trot=trot_state / seconds)
        print(f"{name:22s} {first:6.1f}s {first_batch:6.1f}s {1e3 * single / seconds:9.2f} "
              f"{1e3 * trot / seconds:9.2f} {1e3 * per_state / seconds:10.3f} "
              f"{1e3 * trot_state / seconds:10.3f}  {float(force):8.2f} "
              f"{float(jnp.median(forces)):8.2f}     {int(steps)}", flush=True)
    errors = errors_after_a_trot(seconds)
    print("\nbase position error after the trot, each against its own converged solution: "
          + ", ".join(f"{name} {error:.1e} m" for name, error in errors.items()))

    recorder = Recorder("contact")
    for name, row in rows.items():
        recorder.add("first call, one robot, simulate not jitted (trace, compile, 1 s "
                     "simulated)", name, row["first"], "s", 10.0 if name != MJX else None)
        recorder.add("first call, one robot, inside the caller's jax.jit", name,
                     row["first_staged"], "s")
        recorder.add(f"first call, batch of {batch} (trace, compile, run)", name,
                     row["first_batch"], "s")
        recorder.add("one robot standing, ms per simulated s", name, 1e3 * row["single"], "ms")
        recorder.add("one robot trotting, ms per simulated s", name, 1e3 * row["trot"], "ms")
        recorder.add(f"standing, batch of {batch}: ms per simulated s per state", name,
                     1e3 * row["batch"], "ms")
        recorder.add(f"trotting, batch of {batch}: ms per simulated s per state", name,
                     1e3 * row["batch_trot"], "ms")
        if name in errors:
            recorder.add("base position error after 1 s of trot, against its own converged "
                         "solution", name, errors[name], "m")
        if MJX in rows and name != MJX:
            for key, what in (("batch", "standing"), ("batch_trot", "trotting")):
                ratio = row[key] / rows[MJX][key]
                recorder.add(f"{what}, batch of {batch}: per state / MJX's", name, ratio, "×",
                             1.0)
                print(f"{name}: {what} per state in the batch / MJX's: {ratio:.2f}")
    if args.record:
        recorder.write()


if __name__ == "__main__":
    main()
