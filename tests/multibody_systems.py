"""A registry of reference multibody systems, each built once, for the multibody tests.

Every entry is a `jaxdyn.MultibodySystem` together with a kinematic map (or None), its
parameters and a few random states. Every constant of a system (masses, inertias, lengths,
gravity) is read from the parameters `p`, so an entry can be evaluated in float32 by casting
`p`, `q` and `u`, and so that gradients with respect to masses flow.

Conventions: world z is up for the 3D systems; the planar systems move in the xy plane with
gravity along −y. Rotation matrices map body axes to world axes.

The worked examples 25.1–25.3 are those of a lecture chapter on the general equation of
dynamics and Lagrange's equations (two wheels and a bar on an incline, the elastic pendulum,
a rolling disc with a spring and a hinged rod), with their textbook equations of motion.
"""

import dataclasses
from typing import Callable

import jax.numpy as jnp
import numpy as np

import jaxdyn
from jaxdyn import rotations as rot


@dataclasses.dataclass(frozen=True)
class Reference:
    """One reference system.

    - `states`: ((q, u), ...) with u the speeds of `kinematic_map` (q̇ when it is None).
    - `holonomic`: False when `kinematic_map` embeds nonholonomic constraints (m < n).
    - `independent_coordinates`: True when q are independent coordinates, so that Lagrange's
      equations (speeds q̇) apply; False for redundant coordinates (a quaternion) and for
      nonholonomic systems.
    """

    name: str
    system: jaxdyn.MultibodySystem
    params: dict
    states: tuple
    kinematic_map: Callable | None = None
    holonomic: bool = True
    independent_coordinates: bool = True


def _rng(seed):
    return np.random.default_rng(seed)


def _arr(x):
    return jnp.asarray(np.asarray(x, dtype=np.float64))


def _down(p):
    """Gravity along −y (planar systems)."""
    return jnp.array([0.0, -p["g"], 0.0])


def _down_z(p):
    """Gravity along −z (3D systems)."""
    return jnp.array([0.0, 0.0, -p["g"]])


def _diag(a, b, c):
    zero = 0.0 * a
    return jnp.array([[a, zero, zero], [zero, b, zero], [zero, zero, c]])


# --- 25.1 Two wheels and a bar on an incline ------------------------------------------------
# s: distance travelled down the incline (angle β). The wheels (weight P, moment of inertia J
# about the axle, radius r) roll without slipping: wheel angle −s/r about z. The bar (weight Q)
# joins the axles and translates. P and Q are WEIGHTS: masses are P/g and Q/g.


def _incline_axes(p):
    beta = p["beta"]
    down_slope = jnp.array([jnp.cos(beta), -jnp.sin(beta), 0.0 * beta])
    normal = jnp.array([jnp.sin(beta), jnp.cos(beta), 0.0 * beta])
    return down_slope, normal


def _wheel_centre(offset):
    def position(q, p):
        e, n = _incline_axes(p)
        return (q[0] + offset(p)) * e + p["r"] * n

    return position


def _wheels_and_bar():
    wheel_mass = lambda p: p["P"] / p["g"]
    wheel_inertia = lambda p: _diag(0.5 * p["J"], 0.5 * p["J"], p["J"])
    wheel_orientation = lambda q, p: rot.rotation_z(-q[0] / p["r"])
    wheels = [
        jaxdyn.RigidBody(wheel_mass, wheel_inertia, _wheel_centre(lambda p: 0.0 * p["d"]),
                         wheel_orientation),
        jaxdyn.RigidBody(wheel_mass, wheel_inertia, _wheel_centre(lambda p: p["d"]),
                         wheel_orientation),
    ]
    bar = jaxdyn.RigidBody(
        mass=lambda p: p["Q"] / p["g"],
        inertia=lambda p: _diag(0.01 * p["Q"], 0.1 * p["Q"], 0.1 * p["Q"]) / p["g"],
        position=_wheel_centre(lambda p: 0.5 * p["d"]),
        orientation=lambda q, p: rot.rotation_z(-p["beta"] + 0.0 * q[0]),
    )
    system = jaxdyn.MultibodySystem((*wheels, bar), gravity=_down)
    p = {"P": 30.0, "Q": 50.0, "g": 9.81, "r": 0.3, "J": 0.2, "beta": 0.4, "d": 1.2}
    rng = _rng(251)
    states = tuple((_arr([rng.uniform(-2, 2)]), _arr([rng.uniform(-3, 3)])) for _ in range(3))
    return Reference("wheels_and_bar_25_1", system, p, states)


# --- 25.2 Elastic pendulum ----------------------------------------------------------------
# q = (r, θ), θ from the downward vertical.


def _elastic_pendulum():
    ball = jaxdyn.Particle(
        mass=lambda p: p["m"],
        position=lambda q, p: jnp.array([q[0] * jnp.sin(q[1]), -q[0] * jnp.cos(q[1]),
                                         0.0 * q[0]]),
    )
    spring = lambda q, p: 0.5 * p["k"] * (q[0] - p["l0"]) ** 2
    system = jaxdyn.MultibodySystem((ball,), potential=spring, gravity=_down)
    p = {"m": 1.3, "k": 40.0, "l0": 1.0, "g": 9.81}
    rng = _rng(252)
    states = tuple(
        (_arr([rng.uniform(0.8, 1.5), rng.uniform(-1.0, 1.0)]), _arr(rng.uniform(-2, 2, 2)))
        for _ in range(3)
    )
    return Reference("elastic_pendulum_25_2", system, p, states)


# --- 25.3 Rolling disc, spring and hinged rod ---------------------------------------------
# q = (x, φ): x the displacement of the disc centre A from the spring's natural length, φ the
# rod's angle from the downward vertical. The disc (mass M, radius R) rolls: angle −x/R.


def _disc_spring_rod():
    disc = jaxdyn.RigidBody(
        mass=lambda p: p["M"],
        inertia=lambda p: _diag(0.25, 0.25, 0.5) * p["M"] * p["R"] ** 2,
        position=lambda q, p: jnp.array([q[0], p["R"] + 0.0 * q[0], 0.0 * q[0]]),
        orientation=lambda q, p: rot.rotation_z(-q[0] / p["R"]),
    )
    rod = jaxdyn.RigidBody(  # a thin rod along its body y axis
        mass=lambda p: p["m"],
        inertia=lambda p: _diag(1.0, 0.0, 1.0) * p["m"] * p["l"] ** 2 / 12.0,
        position=lambda q, p: jnp.array([q[0] + 0.5 * p["l"] * jnp.sin(q[1]),
                                         p["R"] - 0.5 * p["l"] * jnp.cos(q[1]), 0.0 * q[0]]),
        orientation=lambda q, p: rot.rotation_z(q[1]),
    )
    spring = lambda q, p: 0.5 * p["k"] * q[0] ** 2
    system = jaxdyn.MultibodySystem((disc, rod), potential=spring, gravity=_down)
    p = {"M": 2.0, "R": 0.25, "m": 0.7, "l": 0.9, "k": 15.0, "g": 9.81}
    rng = _rng(253)
    states = tuple(
        (_arr([rng.uniform(-0.3, 0.3), rng.uniform(-1.0, 1.0)]), _arr(rng.uniform(-2, 2, 2)))
        for _ in range(3)
    )
    return Reference("disc_spring_rod_25_3", system, p, states)


# --- Planar chain of N rigid rods ---------------------------------------------------------
# q_i: the absolute angle of rod i from the downward vertical; rod i (mass m_i, length l_i)
# lies along its body −y axis, hinged at the end of rod i−1 (rod 0 at the origin).


def chain_joint(q, p, i):
    """The hinge at the top of rod i (the tip of the chain for i = N)."""
    point = jnp.zeros(3, q.dtype)
    for j in range(i):
        point = point + p["l"][j] * jnp.array([jnp.sin(q[j]), -jnp.cos(q[j]), 0.0 * q[j]])
    return point


def rod_inertia(m, l):
    """A slender rod along body y: m l²/12 about the transverse axes, a little about y."""
    return _diag(m * l**2 / 12.0, m * l**2 / 400.0, m * l**2 / 12.0)


def _chain(n):
    bodies = []
    for i in range(n):
        bodies.append(jaxdyn.RigidBody(
            mass=lambda p, i=i: p["m"][i],
            inertia=lambda p, i=i: rod_inertia(p["m"][i], p["l"][i]),
            position=lambda q, p, i=i: chain_joint(q, p, i) + 0.5 * p["l"][i] * jnp.array(
                [jnp.sin(q[i]), -jnp.cos(q[i]), 0.0 * q[i]]),
            orientation=lambda q, p, i=i: rot.planar_rotation(q[i]),
        ))
    system = jaxdyn.MultibodySystem(tuple(bodies), gravity=_down)
    rng = _rng(300 + n)
    p = {"m": _arr(rng.uniform(0.5, 2.0, n)), "l": _arr(rng.uniform(0.4, 1.2, n)), "g": 9.81}
    states = tuple((_arr(rng.uniform(-2, 2, n)), _arr(rng.uniform(-2, 2, n)))
                   for _ in range(3))
    return Reference(f"chain_{n}", system, p, states)


# --- Spherical pendulum --------------------------------------------------------------------
# q = (θ, φ): polar angle from the downward vertical and azimuth.


def _spherical_pendulum():
    bob = jaxdyn.Particle(
        mass=lambda p: p["m"],
        position=lambda q, p: p["l"] * jnp.array([jnp.sin(q[0]) * jnp.cos(q[1]),
                                                  jnp.sin(q[0]) * jnp.sin(q[1]),
                                                  -jnp.cos(q[0])]),
    )
    system = jaxdyn.MultibodySystem((bob,), gravity=_down_z)
    p = {"m": 0.8, "l": 1.1, "g": 9.81}
    rng = _rng(305)
    states = tuple(
        (_arr([rng.uniform(0.4, 1.4), rng.uniform(-3, 3)]), _arr(rng.uniform(-2, 2, 2)))
        for _ in range(3)
    )
    return Reference("spherical_pendulum", system, p, states)


# --- Euler angles zxz: body angular velocity ------------------------------------------------


def zxz_body_rates(angles):
    """E(θ, φ) with ω_body = E (ψ̇, θ̇, φ̇) for R = R_z(ψ) R_x(θ) R_z(φ) (hand-derived)."""
    _, th, ph = angles
    zero = 0.0 * th
    return jnp.array([
        [jnp.sin(th) * jnp.sin(ph), jnp.cos(ph), zero],
        [jnp.sin(th) * jnp.cos(ph), -jnp.sin(ph), zero],
        [jnp.cos(th), zero, 1.0 + zero],
    ])


def zxz_angle_rates(angles):
    """E⁻¹: (ψ̇, θ̇, φ̇) = E⁻¹ ω_body, written out (singular at θ = 0, π)."""
    _, th, ph = angles
    s, c = jnp.sin(th), jnp.cos(th)
    zero = 0.0 * th
    return jnp.array([
        [jnp.sin(ph) / s, jnp.cos(ph) / s, zero],
        [jnp.cos(ph), -jnp.sin(ph), zero],
        [-c * jnp.sin(ph) / s, -c * jnp.cos(ph) / s, 1.0 + zero],
    ])


# --- Heavy symmetric top ----------------------------------------------------------------
# q = (ψ, θ, φ) zxz Euler angles (precession, nutation, spin) about the fixed tip O; the centre
# of mass sits at distance L along the body symmetry axis z. Speeds: u = ω in body axes.


def _heavy_top():
    top = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: _diag(p["I1"], p["I1"], p["I3"]),
        position=lambda q, p: rot.euler_angles(q, "zxz") @ jnp.array([0.0, 0.0, p["L"]]),
        orientation=lambda q, p: rot.euler_angles(q, "zxz"),
    )
    system = jaxdyn.MultibodySystem((top,), gravity=_down_z)
    p = {"m": 1.5, "L": 0.3, "I1": 0.02, "I3": 0.035, "g": 9.81}
    kinematic_map = lambda q, p: zxz_angle_rates(q)
    rng = _rng(306)
    states = tuple(
        (_arr([rng.uniform(-3, 3), rng.uniform(0.4, 1.2), rng.uniform(-3, 3)]),
         _arr([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(10, 30)]))
        for _ in range(3)
    )
    return Reference("heavy_top", system, p, states, kinematic_map=kinematic_map)


# --- Free rigid body, full inertia tensor ---------------------------------------------------

FULL_INERTIA = [[0.30, 0.04, -0.02], [0.04, 0.45, 0.03], [-0.02, 0.03, 0.52]]


def _free_body_euler():
    """q = (x, y, z, ψ, θ, φ), zxz Euler angles; speeds q̇; under gravity."""
    body = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: p["I"],
        position=lambda q, p: q[:3],
        orientation=lambda q, p: rot.euler_angles(q[3:], "zxz"),
    )
    system = jaxdyn.MultibodySystem((body,), gravity=_down_z)
    p = {"m": 2.0, "I": _arr(FULL_INERTIA), "g": 9.81}
    rng = _rng(307)
    states = tuple(
        (_arr([*rng.uniform(-1, 1, 3), rng.uniform(-3, 3), rng.uniform(0.5, 1.2),
               rng.uniform(-3, 3)]), _arr(rng.uniform(-3, 3, 6)))
        for _ in range(3)
    )
    return Reference("free_body_euler", system, p, states)


def quaternion_rates(quat):
    """G with q̇_quat = G ω_body, i.e. q̇ = ½ q ⊗ (0, ω) for (w, x, y, z) (hand-written). Its
    columns are orthogonal to the quaternion, so its norm is conserved."""
    w, x, y, z = quat
    return 0.5 * jnp.array([[-x, -y, -z], [w, -z, y], [z, w, -x], [-y, x, w]])


def free_body_quaternion_map(q, p):
    """q̇ = K u for q = (r, quaternion), u = (v_world, ω_body)."""
    k = jnp.zeros((7, 6), q.dtype)
    k = k.at[:3, :3].set(jnp.eye(3, dtype=q.dtype))
    return k.at[3:, 3:].set(quaternion_rates(q[3:]))


def _free_body_quaternion():
    """q = (x, y, z, quaternion) (7), u = (v, ω_body) (6): redundant coordinates."""
    body = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: p["I"],
        position=lambda q, p: q[:3],
        orientation=lambda q, p: rot.quaternion(q[3:]),
    )
    system = jaxdyn.MultibodySystem((body,))
    p = {"m": 2.0, "I": _arr(FULL_INERTIA)}
    rng = _rng(308)
    states = []
    for scale in (1.0, 1.0, 1.3):  # the quaternion's scale is a gauge freedom
        quat = rng.normal(size=4)
        quat = scale * quat / np.linalg.norm(quat)
        states.append((_arr([*rng.uniform(-1, 1, 3), *quat]), _arr(rng.uniform(-3, 3, 6))))
    return Reference("free_body_quaternion", system, p, tuple(states),
                     kinematic_map=free_body_quaternion_map, independent_coordinates=False)


# --- 3D compound pendulum on a spherical joint -----------------------------------------------
# q = zyx Euler angles (yaw, pitch, roll); the pivot is the origin, the centre of mass is at
# the body-frame offset c (off every principal axis), full inertia tensor about the COM.


def _compound_pendulum_3d():
    body = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: p["I"],
        position=lambda q, p: rot.euler_angles(q, "zyx") @ p["c"],
        orientation=lambda q, p: rot.euler_angles(q, "zyx"),
    )
    system = jaxdyn.MultibodySystem((body,), gravity=_down_z)
    p = {"m": 1.7, "I": _arr(FULL_INERTIA), "c": _arr([0.05, -0.03, -0.5]), "g": 9.81}
    rng = _rng(309)
    states = tuple(
        (_arr([rng.uniform(-3, 3), rng.uniform(-1, 1), rng.uniform(-1.5, 1.5)]),
         _arr(rng.uniform(-3, 3, 3)))
        for _ in range(3)
    )
    return Reference("compound_pendulum_3d", system, p, states)


# --- Chaplygin sleigh (nonholonomic) --------------------------------------------------------
# q = (x, y, θ): the knife edge P at (x, y), heading θ; the centre of mass G is a distance a
# ahead of P along the heading. No lateral slip at P: −ẋ sin θ + ẏ cos θ = 0. Speeds u = (v, ω):
# forward speed of P and yaw rate. The plane is tilted: in-plane gravity g_t along −y.


def sleigh_map(q, p):
    th = q[2]
    zero = 0.0 * th
    return jnp.array([[jnp.cos(th), zero], [jnp.sin(th), zero], [zero, 1.0 + zero]])


def _chaplygin_sleigh():
    body = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: _diag(p["Ixx"], p["Iyy"], p["I"]),
        position=lambda q, p: jnp.array([q[0] + p["a"] * jnp.cos(q[2]),
                                         q[1] + p["a"] * jnp.sin(q[2]), 0.0 * q[0]]),
        orientation=lambda q, p: rot.planar_rotation(q[2]),
    )
    system = jaxdyn.MultibodySystem((body,), gravity=lambda p: jnp.array([0.0, -p["g_t"], 0.0]))
    p = {"m": 1.2, "I": 0.08, "Ixx": 0.05, "Iyy": 0.06, "a": 0.3, "g_t": 2.0}
    rng = _rng(310)
    states = tuple((_arr(rng.uniform(-2, 2, 3)), _arr(rng.uniform(-2, 2, 2)))
                   for _ in range(3))
    return Reference("chaplygin_sleigh", system, p, states, kinematic_map=sleigh_map,
                     holonomic=False, independent_coordinates=False)


# --- Rolling disc on a plane (nonholonomic) ----------------------------------------------
# q = (x, y, ψ, θ, φ): contact point (x, y), yaw ψ, lean θ (0 = upright), spin φ;
# R = R_z(ψ) R_x(θ) R_y(φ), the disc's symmetry axis is body y. The lean frame L = R_z(ψ) R_x(θ)
# gives the centre at (x, y, 0) + r L_z. Speeds: the disc's angular velocity in L axes,
# ω = u1 L_x + u2 L_y + u3 L_z, so θ̇ = u1, ψ̇ = u3 / cos θ, φ̇ = u2 − u3 tan θ; rolling without
# slipping (the contact material point at rest) then gives (ẋ, ẏ) = r φ̇ (cos ψ, sin ψ).


def disc_map(q, p):
    _, _, psi, th, _ = q
    r = p["r"]
    zero = 0.0 * th
    tan = jnp.tan(th)
    return jnp.array([
        [zero, r * jnp.cos(psi), -r * jnp.cos(psi) * tan],
        [zero, r * jnp.sin(psi), -r * jnp.sin(psi) * tan],
        [zero, zero, 1.0 / jnp.cos(th)],
        [1.0 + zero, zero, zero],
        [zero, 1.0 + zero, -tan],
    ])


def _lean_frame(q):
    return rot.rotation_z(q[2]) @ rot.rotation_x(q[3])


def _rolling_disc():
    disc = jaxdyn.RigidBody(
        mass=lambda p: p["m"],
        inertia=lambda p: _diag(0.25, 0.5, 0.25) * p["m"] * p["r"] ** 2,
        position=lambda q, p: jnp.array([q[0], q[1], 0.0 * q[0]])
        + p["r"] * _lean_frame(q)[:, 2],
        orientation=lambda q, p: _lean_frame(q) @ rot.rotation_y(q[4]),
    )
    system = jaxdyn.MultibodySystem((disc,), gravity=_down_z)
    p = {"m": 0.9, "r": 0.35, "g": 9.81}
    rng = _rng(311)
    states = []
    for lean in (0.0, rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6)):  # upright included
        q = [*rng.uniform(-1, 1, 2), rng.uniform(-3, 3), lean, rng.uniform(-3, 3)]
        states.append((_arr(q), _arr([rng.uniform(-1, 1), rng.uniform(4, 8),
                                      rng.uniform(-2, 2)])))
    return Reference("rolling_disc", system, p, tuple(states), kinematic_map=disc_map,
                     holonomic=False, independent_coordinates=False)


SYSTEMS = {
    ref.name: ref
    for ref in (
        _wheels_and_bar(),
        _elastic_pendulum(),
        _disc_spring_rod(),
        _chain(3),
        _chain(5),
        _spherical_pendulum(),
        _heavy_top(),
        _free_body_euler(),
        _free_body_quaternion(),
        _compound_pendulum_3d(),
        _chaplygin_sleigh(),
        _rolling_disc(),
    )
}

HOLONOMIC = [name for name, ref in SYSTEMS.items() if ref.holonomic]
INDEPENDENT = [name for name, ref in SYSTEMS.items() if ref.independent_coordinates]
NONHOLONOMIC = [name for name, ref in SYSTEMS.items() if not ref.holonomic]


def cases(names):
    """(name, state index) pairs for pytest.parametrize."""
    return [(name, i) for name in names for i in range(len(SYSTEMS[name].states))]
