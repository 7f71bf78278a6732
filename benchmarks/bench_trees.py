"""Trees of joints: cost against the number of bodies, and real robot models.

Run: python benchmarks/bench_trees.py            (about 20 minutes)
     python benchmarks/bench_trees.py --quick    (chains up to 20, the Panda arm)
     python benchmarks/bench_trees.py --robots --record   (the robots alone; write
                                                 benchmarks/results/robots.csv)

Needs the test extras (Pinocchio, example-robot-data, yourdfpy) and, for the MJX columns,
`pip install mujoco-mjx==3.17.0 mujoco==3.17.0` (pinned together: pip pairs mujoco-mjx with an
incompatible mujoco otherwise); without MuJoCo those columns are left out.

- chain: N uniform rods hinged end to end (`RigidBodyTree` of revolute joints, relative
  angles) against the chain's closed-form equations written by hand in jax.numpy (absolute
  angles θ = cumsum(q), M_ij = a_ij cos(θ_i − θ_j) + δ_ij m l²/12, Cholesky solve, q̈ =
  first differences of θ̈), and against MuJoCo's MJX on the same chain (an MJCF of hinges);
- robots: the Panda and UR5 arms (fixed base), the ANYmal-C quadruped, the Unitree G1 and the
  Talos humanoid (floating base), from the URDFs of example-robot-data: forward dynamics
  (unchecked and the default checked call), mass matrix, inverse dynamics, a frame Jacobian
  and the torque regressor, each per state in a jitted vmap over 1024 states, against
  Pinocchio's aba, crba, rnea, computeFrameJacobian and computeJointTorqueRegressor called
  from Python, and MJX's forward dynamics (the same URDF without meshes, bodies on fixed
  joints fused into their parents) where installed;
- per formulation: `ArticulatedBody` (the default for trees), and Kane, Gibbs–Appell and
  Lagrange for chains up to N = 20 (their cost grows faster; compile and in-loop only).

Measured: compile time of a jitted `accelerations` (every cache cleared), one jitted call,
one evaluation inside a compiled loop (what a solver pays), per state of a vmap over 1024
states; compile and run time of a 1 s `simulate` (Tsit5, rtol = atol = 1e-8) against
`diffrax.diffeqsolve` on the hand-written right-hand side. jaxdyn's accelerations here are
`throw=False` (branch-free: what `simulate` integrates); the checked call costs one branch.
"""

import importlib.metadata
import os
import statistics
import sys
import time
import xml.etree.ElementTree as ET

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import CHAIN_PARAMS, chain_hand  # noqa: E402
from _results import Recorder  # noqa: E402
from _timing import compile_seconds, in_loop, interleaved  # noqa: E402

try:
    import mujoco
    from mujoco import mjx
except ImportError:
    mujoco = mjx = None

BATCH = 1024
# MJX on this CPU costs 40–60× the hand-written chain at N = 5 (below) and a vmapped batch
# of longer chains runs for many minutes: beyond this N it is left out.
MJX_CHAIN_MAX = 5
LOOP = 2000
# Each robot program is compiled this many times afresh and timed each time: the same program
# compiled afresh runs, now and then, 2–3× slower than usual (benchmarks/LOG.md, "Robots");
# the figure is the median over the compilations, the range beside it.
COMPILES = 3
TOL = 1e-8


# -- the chain ---------------------------------------------------------------------------------

def chain_tree(n):
    """The rods of `_systems.chain` as a tree: revolute about z, hanging along −y."""
    m, length, g = CHAIN_PARAMS["m"], CHAIN_PARAMS["l"], CHAIN_PARAMS["g"]
    inertia = np.diag([1.0, 0.0, 1.0]) * m * length**2 / 12
    links = [jaxdyn.Link(f"rod{i}", jaxdyn.Revolute((0, 0, 1)),
                         parent=None if i == 0 else f"rod{i - 1}",
                         translation=(0.0, 0.0 if i == 0 else -length, 0.0),
                         mass=m, com=(0.0, -length / 2, 0.0), inertia=inertia)
             for i in range(n)]
    return jaxdyn.RigidBodyTree(links, gravity=jnp.array([0.0, -g, 0.0]))


def chain_by_hand(n):
    """The hand-written chain in relative angles: θ = cumsum(q), q̈ = Δθ̈."""
    absolute, _ = chain_hand(n)
    p = {k: jnp.asarray(v) for k, v in CHAIN_PARAMS.items()}

    def accelerations(t, q, u, _):
        theta_dd = absolute(t, jnp.cumsum(q), jnp.cumsum(u), p)
        return jnp.concatenate([theta_dd[:1], jnp.diff(theta_dd)])

    return accelerations


def chain_mjcf(n):
    m, length, g = CHAIN_PARAMS["m"], CHAIN_PARAMS["l"], CHAIN_PARAMS["g"]
    i_rod = m * length**2 / 12
    body = ""
    for i in reversed(range(n)):
        pos = "0 0 0" if i == 0 else f"0 {-length} 0"
        body = (f'<body name="rod{i}" pos="{pos}"><joint type="hinge" axis="0 0 1"/>'
                f'<inertial pos="0 {-length / 2} 0" mass="{m}" '
                f'diaginertia="{i_rod} {1e-12} {i_rod}"/>{body}</body>')
    return (f'<mujoco><option gravity="0 {-g} 0"><flag constraint="disable" contact="disable"/>'
            f'</option><worldbody>{body}</worldbody></mujoco>')


# -- robots ------------------------------------------------------------------------------------

def robot_file(name):
    for f in importlib.metadata.files("example-robot-data"):
        if str(f).endswith("robots/" + name):
            return str(f.locate())
    raise FileNotFoundError(name)


def robot_mjcf(path, floating):
    """The URDF for MuJoCo: no meshes, no joint limits or damping (jaxdyn and Pinocchio see
    none of them here either), a floating joint above the root for a free base."""
    root = ET.parse(path).getroot()
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for element in link.findall(tag):
                link.remove(element)
    for joint in root.findall("joint"):  # not a transmission's
        for tag in ("dynamics", "mimic", "safety_controller", "calibration"):
            for element in joint.findall(tag):
                joint.remove(element)
        for limit in joint.findall("limit"):
            limit.attrib.pop("lower", None)
            limit.attrib.pop("upper", None)
    if floating:
        children = {j.find("child").get("link") for j in root.findall("joint")}
        base = next(link.get("name") for link in root.iter("link")
                    if link.get("name") not in children)
        ET.SubElement(root, "link", name="mjx_world")
        joint = ET.SubElement(root, "joint", name="mjx_free", type="floating")
        ET.SubElement(joint, "parent", link="mjx_world")
        ET.SubElement(joint, "child", link=base)
    # MuJoCo refuses principal moments that break the triangle inequality (A + B < C), which
    # ANYmal-C's four depth cameras and its hatch (moments 0, 0, 3e-3) carry: raised just
    # enough to meet it for MuJoCo. Jaxdyn and Pinocchio take the file's values; the
    # computation costs the same.
    balanced = False
    for inertia in root.iter("inertia"):
        keys = ("ixx", "ixy", "ixz", "ixy", "iyy", "iyz", "ixz", "iyz", "izz")
        matrix = np.array([float(inertia.get(k, 0.0)) for k in keys]).reshape(3, 3)
        moments, axes = np.linalg.eigh(matrix)
        if moments[2] <= 0 or (moments[0] + moments[1] >= moments[2] and moments[0] > 0):
            continue  # massless, or a valid inertia
        balanced = True
        middle = max(moments[1], moments[2] / 2)
        matrix = axes @ np.diag([max(moments[0], moments[2] - middle), middle, moments[2]]) @ axes.T
        for k, (i, j) in zip(("ixx", "ixy", "ixz", "iyy", "iyz", "izz"),
                             ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            inertia.set(k, repr(float(matrix[i, j])))
    extension = ET.SubElement(root, "mujoco")
    # Bodies on fixed joints fused into their parents, as jaxdyn's `merge_fixed` welds them.
    ET.SubElement(extension, "compiler", discardvisual="true", fusestatic="true",
                  balanceinertia="false", inertiafromgeom="false")
    model = mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
    model.opt.disableflags |= (mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
                               | mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return model, balanced


# -- measurements ------------------------------------------------------------------------------

def batch_of_states(n_q, n_u, neutral, seed):
    rng = np.random.default_rng(seed)
    q = np.asarray(neutral) + rng.uniform(-0.5, 0.5, (BATCH, n_q))
    if n_q != n_u:  # a free base: normalise its quaternion (coordinates 3:7)
        q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    return jnp.asarray(q), jnp.asarray(rng.uniform(-1, 1, (BATCH, n_u)))


def evaluation_costs(candidates, qs, us, number):
    """{name: (accelerations(t, q, u, p), p)} → per-call, in-loop and per-state-in-vmap seconds.
    The in-loop driver integrates q by the speeds, so it is run for equal numbers of q and u."""
    t = jnp.asarray(0.0)
    single = interleaved({name: (jax.jit(fn), (t, qs[0], us[0], p))
                          for name, (fn, p) in candidates.items()}, number=number)
    batched = interleaved({name: (jax.jit(jax.vmap(fn, (None, 0, 0, None))), (t, qs, us, p))
                           for name, (fn, p) in candidates.items()}, number=3)
    out = {name: {"call": single[name], "vmap": batched[name] / BATCH} for name in candidates}
    if qs.shape[1] == us.shape[1]:
        loop = interleaved({name: (in_loop(fn, LOOP), (t, qs[0], us[0], p))
                            for name, (fn, p) in candidates.items()}, number=1, rounds=5)
        for name in candidates:
            out[name]["loop"] = loop[name] / LOOP
    return out


def unchecked(dynamics):
    return lambda t, q, u, p: dynamics.accelerations(t, q, u, p, throw=False)


def mjx_accelerations(model):
    """MJX's forward dynamics (qacc) as accelerations(t, q, u, p)."""
    device_model = mjx.put_model(model)
    data = mjx.make_data(device_model)

    def accelerations(t, q, u, _):
        return mjx.forward(device_model, data.replace(qpos=q, qvel=u)).qacc

    return accelerations


def simulate_pair(dynamics, hand, q0, u0):
    term = diffrax.ODETerm(lambda t, y, p: (y[1], hand(t, y[0], y[1], p)))

    def by_hand(q0):
        return diffrax.diffeqsolve(
            term, diffrax.Tsit5(), 0.0, 1.0, None, (q0, u0), saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
            max_steps=16**4).ys[0][-1]

    def ours(q0):
        return jaxdyn.simulate(dynamics, q0, u0, None, t1=1.0, rtol=TOL, atol=TOL,
                               save="q").q[-1]

    difference = float(jnp.max(jnp.abs(by_hand(q0) - ours(q0))))
    compiles = compile_seconds(by_hand, q0), compile_seconds(ours, q0)
    times = interleaved({"hand": (jax.jit(by_hand), (q0,)), "jaxdyn": (jax.jit(ours), (q0,))},
                        number=1, rounds=5)
    return times, compiles, difference


def fmt(seconds):
    return f"{seconds * 1e6:9.2f}" if seconds < 1e-1 else f"{seconds * 1e6:9.0f}"


def chains(sizes, formulation_sizes):
    print("\n-- chain of N rods: µs per evaluation (ratio to the hand-written chain) --")
    print(f"{'N':>4s} {'what':>12s} {'hand':>9s} {'ABA':>9s} {'ratio':>6s}"
          + (f" {'MJX':>9s} {'ratio':>6s}" if mjx else "") + "   compile ABA / hand")
    for n in sizes:
        tree = chain_tree(n)
        aba = jaxdyn.ArticulatedBody(tree)
        hand = chain_by_hand(n)
        qs, us = batch_of_states(n, n, np.zeros(n), n)
        reference = jax.vmap(hand, (None, 0, 0, None))(0.0, qs[:8], us[:8], None)
        ours = jax.vmap(unchecked(aba), (None, 0, 0, None))(0.0, qs[:8], us[:8], None)
        error = float(jnp.max(jnp.abs(ours - reference)) / jnp.max(jnp.abs(reference)))
        assert error < 1e-9, (n, error)
        candidates = {"hand": (hand, None), "ABA": (unchecked(aba), None)}
        if mjx and n <= MJX_CHAIN_MAX:
            model = mujoco.MjModel.from_xml_string(chain_mjcf(n))
            candidates["MJX"] = (mjx_accelerations(model), None)
            theirs = jax.vmap(candidates["MJX"][0], (None, 0, 0, None))(0.0, qs[:8], us[:8], None)
            assert float(jnp.max(jnp.abs(theirs - reference))) < 1e-6 * float(
                jnp.max(jnp.abs(reference))), n
        costs = evaluation_costs(candidates, qs, us, number=200)
        compiles = (compile_seconds(unchecked(aba), 0.0, qs[0], us[0], None),
                    compile_seconds(hand, 0.0, qs[0], us[0], None))
        for what in ("call", "loop", "vmap"):
            row = (f"{n:4d} {what:>12s} {fmt(costs['hand'][what])} {fmt(costs['ABA'][what])} "
                   f"{costs['ABA'][what] / costs['hand'][what]:5.2f}×")
            if "MJX" in costs:
                row += (f" {fmt(costs['MJX'][what])} "
                        f"{costs['MJX'][what] / costs['hand'][what]:5.2f}×")
            if what == "call":
                row += f"   {compiles[0]:.2f} s / {compiles[1]:.2f} s"
            print(row, flush=True)
        times, sim_compiles, difference = simulate_pair(aba, hand, qs[0], us[0])
        print(f"{n:4d} {'1 s simulate':>12s} {fmt(times['hand'])} {fmt(times['jaxdyn'])} "
              f"{times['jaxdyn'] / times['hand']:5.2f}×   compile {sim_compiles[1]:.2f} s / "
              f"{sim_compiles[0]:.2f} s   (|Δq(1)| = {difference:.1e})", flush=True)
        if n in formulation_sizes:
            others = {"Kane": jaxdyn.Kane.from_system(tree),
                      "Gibbs–Appell": jaxdyn.GibbsAppell.from_system(tree),
                      "Lagrange": jaxdyn.Lagrangian.from_system(tree)}
            args = (jnp.asarray(0.0), qs[0], us[0], None)
            loop = interleaved({"hand": (in_loop(hand, LOOP), args)}
                               | {name: (in_loop(unchecked(d), LOOP), args)
                                  for name, d in others.items()}, number=1, rounds=5)
            for name, dynamics in others.items():
                error = float(jnp.max(jnp.abs(unchecked(dynamics)(0.0, qs[0], us[0], None)
                                              - reference[0])))
                seconds = compile_seconds(unchecked(dynamics), 0.0, qs[0], us[0], None)
                print(f"{n:4d} {name:>12s} in loop {fmt(loop[name] / LOOP)} µs "
                      f"({loop[name] / loop['hand']:.2f}× hand), compile {seconds:.2f} s, "
                      f"|Δq̈| = {error:.1e}", flush=True)


ROBOTS = [("panda_description/urdf/panda.urdf", False, "panda_hand"),
          ("ur_description/urdf/ur5_robot.urdf", False, "tool0"),
          ("anymal_c_simple_description/urdf/anymal.urdf", True, "LF_FOOT"),
          ("g1_description/urdf/g1_29dof_rev_1_0.urdf", True, "left_rubber_hand"),
          ("talos_data/robots/talos_full_v2.urdf", True, "gripper_left_base_link")]


def pinocchio_per_call(fn, states, repeats=20):
    """Seconds per call of a Pinocchio function called from Python over the given states."""
    start = time.perf_counter()
    for _ in range(repeats):
        for state in states:
            fn(*state)
    return (time.perf_counter() - start) / (repeats * len(states))


def robots(names):
    """Per algorithm and robot: jaxdyn per state in a jitted vmap over 1024 states (and its
    compile time) against Pinocchio per call from Python (64 random states)."""
    import pinocchio as pin

    print("\n-- robot models: per state in a vmap of 1024 (compile) against Pinocchio per call --")
    for name, floating, frame in names:
        path = robot_file(name)
        tree, p = jaxdyn.from_urdf(path, floating=floating, parameters=False,
                                   damping=False)  # none in Pinocchio's or MJX's model
        aba = jaxdyn.ArticulatedBody(tree)
        bodies = tree.merge_fixed()
        model = (pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer()) if floating
                 else pin.buildModelFromUrdf(path))
        data = model.createData()
        # the same model: the mass matrices' eigenvalues at the neutral configuration agree
        m_pin = pin.crba(model, data, pin.neutral(model))
        m_pin = np.triu(m_pin) + np.triu(m_pin, 1).T
        neutral = jnp.asarray(tree.neutral_configuration())
        m_ours = aba.mass_matrix(0.0, neutral, jnp.zeros(tree.num_speeds), None)
        assert np.allclose(np.linalg.eigvalsh(m_ours), np.linalg.eigvalsh(m_pin),
                           rtol=1e-10, atol=1e-12), name
        qs, us = batch_of_states(tree.num_coordinates, tree.num_speeds, neutral, 0)
        uds = us[::-1]
        t = jnp.asarray(0.0)
        frame_id = model.getFrameId(frame)
        world = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        rng = np.random.default_rng(1)
        states = [(pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq)),
                   rng.uniform(-1, 1, model.nv), rng.uniform(-1, 1, model.nv))
                  for _ in range(64)]
        algorithms = {  # name: (jaxdyn per state (q, u, u̇), Pinocchio (q, v, a))
            "forward dynamics, throw=False": (
                lambda q, u, ud: aba.accelerations(t, q, u, None, throw=False),
                lambda q, v, a: pin.aba(model, data, q, v, a)),
            "forward dynamics, default (checked)": (
                lambda q, u, ud: aba.accelerations(t, q, u, None),
                lambda q, v, a: pin.aba(model, data, q, v, a)),
            "mass matrix (CRBA)": (
                lambda q, u, ud: aba.mass_matrix(t, q, u, None),
                lambda q, v, a: pin.crba(model, data, q)),
            "inverse dynamics (RNEA)": (
                lambda q, u, ud: aba.residual(t, q, u, ud, None),
                lambda q, v, a: pin.rnea(model, data, q, v, a)),
            f"Jacobian of {frame}": (
                lambda q, u, ud: jaxdyn.frame_jacobian(tree, frame, q),
                lambda q, v, a: pin.computeFrameJacobian(model, data, q, frame_id, world)),
            "torque regressor, every URDF link": (
                lambda q, u, ud: jaxdyn.inverse_dynamics_regressor(tree, q, u, ud),
                lambda q, v, a: pin.computeJointTorqueRegressor(model, data, q, v, a)),
            # Pinocchio's columns: one body per joint, fixed links welded in (merge_fixed)
            "torque regressor, welded bodies": (
                lambda q, u, ud: jaxdyn.inverse_dynamics_regressor(bodies, q, u, ud),
                lambda q, v, a: pin.computeJointTorqueRegressor(model, data, q, v, a)),
        }
        print(f"{name.split('/')[-1]} (nq {tree.num_coordinates}, nv {tree.num_speeds}, "
              f"{len(tree.links)} links, {len(tree.merge_fixed().links)} after merging fixed "
              "joints)", flush=True)
        for label, (ours, theirs) in algorithms.items():
            batched = jax.vmap(ours)
            times, compile_times = [], []
            for _ in range(COMPILES):  # each time afresh (`compile_seconds` clears the caches)
                compile_times.append(compile_seconds(batched, qs, us, uds))
                times.append(interleaved({label: (jax.jit(batched), (qs, us, uds))},
                                         number=3)[label] / BATCH)
            vmapped, compile_time = statistics.median(times), statistics.median(compile_times)
            pinocchio = pinocchio_per_call(theirs, states)
            spread = f" [{min(times) * 1e6:.2f}–{max(times) * 1e6:.2f}]" if COMPILES > 1 else ""
            print(f"  {label:36s} {fmt(vmapped)} per state{spread} (compile "
                  f"{compile_time:4.1f} s); Pinocchio {fmt(pinocchio)}; ratio "
                  f"{vmapped / pinocchio:5.2f}×", flush=True)
            robot = name.split("/")[-1].split(".")[0]
            RECORDER.add(f"{label}: per state in a vmap of {BATCH} / Pinocchio per call",
                         robot, vmapped / pinocchio)
            if label.startswith("forward dynamics, default"):
                ours_fd = vmapped
            if label.startswith("torque regressor, welded"):
                regressor_pinocchio = pinocchio
        # The regressor's output is m × 10 N numbers a state (Talos's 180 kB): a batch of 1024
        # writes a fresh buffer of that size, and its first touch of every page (a page
        # fault each 4 kB) sets a floor. Beside it, zeros of that shape written alone, and the
        # same regressor over 128 states, whose output malloc reuses from call to call.
        shape = (tree.num_speeds, 10 * len(bodies.links))
        write = jax.jit(jax.vmap(lambda q: jnp.zeros(shape, q.dtype) + q[0]))
        welded = jax.jit(jax.vmap(lambda q, u, ud: jaxdyn.inverse_dynamics_regressor(
            bodies, q, u, ud)))
        small = (qs[:128], us[:128], uds[:128])
        floor = interleaved({"zeros": (write, (qs,))}, number=3)["zeros"] / BATCH
        small_batch = interleaved({"128": (welded, small)}, number=3)["128"] / 128
        print(f"  {'   the output alone, zeros written':36s} {fmt(floor)} per state; the "
              f"welded regressor over 128 states {fmt(small_batch)} per state, ratio "
              f"{small_batch / regressor_pinocchio:5.2f}×", flush=True)
        if mjx:
            mj, balanced = robot_mjcf(path, floating)
            m_mj = np.zeros((mj.nv, mj.nv))
            mj_data = mujoco.MjData(mj)
            mujoco.mj_forward(mj, mj_data)
            mujoco.mj_fullM(mj, mj_data, m_mj)
            eigenvalues, expected = np.linalg.eigvalsh(m_mj), np.linalg.eigvalsh(m_pin)
            agreement = float(np.max(np.abs(eigenvalues - expected) / expected))
            assert agreement <= (1e-2 if balanced else 1e-8), (name, agreement)
            # MuJoCo's coordinates differ in order and, for the base, in convention: its own
            # random states, of the same spread
            mj_q = np.tile(mj.qpos0, (BATCH, 1))
            mj_q[:, -(mj.nq - (7 if floating else 0)):] += np.random.default_rng(0).uniform(
                -0.5, 0.5, (BATCH, mj.nq - (7 if floating else 0)))
            fn = mjx_accelerations(mj)
            mj_qs = jnp.asarray(mj_q)
            mjx_compile = compile_seconds(fn, t, mj_qs[0], us[0], None)
            mjx_vmapped = interleaved({"MJX": (jax.jit(jax.vmap(fn, (None, 0, 0, None))),
                                               (t, mj_qs, us, None))}, number=3)["MJX"] / BATCH
            print(f"  {'MJX forward dynamics':36s} {fmt(mjx_vmapped)} per state (compile "
                  f"{mjx_compile:4.1f} s); ratio to jaxdyn's {mjx_vmapped / ours_fd:5.2f}×; "
                  f"M's eigenvalues within {agreement:.0e}"
                  + (" (inertias balanced by MuJoCo)" if balanced else ""), flush=True)


RECORDER = Recorder("robots")


def main():
    quick = "--quick" in sys.argv
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64"
          + (f", mujoco {mujoco.__version__}" if mujoco else ", MJX not installed"))
    if "--robots" not in sys.argv:
        sizes = (2, 5, 10, 20) if quick else (2, 5, 10, 20, 50, 100)
        chains(sizes, formulation_sizes=(5, 20) if quick else (5, 10, 20))
    robots(ROBOTS[:1] if quick else ROBOTS)
    if "--record" in sys.argv:
        RECORDER.write()


if __name__ == "__main__":
    main()
