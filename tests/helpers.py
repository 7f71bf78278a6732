"""Shared test utilities: comparisons, finite differences and reference systems.

Every reference system pairs a `jaxdyn.Lagrangian` (the energies, written the way a user would)
with oracles that are independent of jaxdyn: the mass matrix, the accelerations and the energy,
derived by hand (or taken from the standard literature) and evaluated with
NumPy. Tests cross them with `pytest.mark.parametrize("system", SYSTEMS, ids=SYSTEM_IDS)`.
"""

import contextlib
import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxdyn


def tree_allclose(x, y, *, rtol=1e-10, atol=1e-12) -> bool:
    """True if two pytrees have the same structure, and leaves of equal shape and dtype whose
    values agree to `|x - y| <= atol + rtol |y|`."""
    x_leaves, x_tree = jax.tree_util.tree_flatten(x)
    y_leaves, y_tree = jax.tree_util.tree_flatten(y)
    if x_tree != y_tree:
        return False
    for a, b in zip(x_leaves, y_leaves):
        a = np.asarray(a)
        b = np.asarray(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return False
        if not np.allclose(a, b, rtol=rtol, atol=atol):
            return False
    return True


def assert_close(actual, desired, *, rtol, atol=0.0, err_msg=""):
    """`np.testing.assert_allclose` after moving JAX arrays to NumPy (shapes must match)."""
    actual = np.asarray(actual)
    desired = np.asarray(desired)
    assert actual.shape == desired.shape, (actual.shape, desired.shape)
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=atol, err_msg=err_msg)


_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiled: list = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kwargs: _compiled.append(event) if event == _COMPILE_EVENT
    else None)


@contextlib.contextmanager
def compiles():
    """Counts the programs XLA compiles inside the block: `with compiles() as count: ...`,
    then `count()`."""
    start = len(_compiled)
    yield lambda: len(_compiled) - start


def rotation_of(quaternion):
    """R from a unit quaternion (w, x, y, z), written out (the numbers a reader checks)."""
    w, x, y, z = quaternion
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def central_difference(f: Callable, x, step: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian of `f` at `x` (NumPy arrays in and out).

    Component i is perturbed by h_i = step * max(1, |x_i|); the result has shape
    f(x).shape + x.shape. Truncation error is O(h²), round-off O(ε |f| / h).
    """
    x = np.asarray(x, dtype=np.float64)
    f0 = np.asarray(f(x))
    jac = np.zeros(f0.shape + x.shape)
    for index in np.ndindex(*x.shape):
        h = step * max(1.0, abs(float(x[index])))
        xp = x.copy()
        xm = x.copy()
        xp[index] += h
        xm[index] -= h
        jac[(...,) + index] = (np.asarray(f(xp)) - np.asarray(f(xm))) / (2 * h)
    return jac


def central_difference_params(f: Callable, p: dict, step: float = 1e-6) -> dict:
    """Central finite-difference gradient of a scalar `f(p)` for a flat dict of float leaves."""
    grads = {}
    for key, value in p.items():
        def along(x, key=key):
            return f({**p, key: float(np.asarray(x).reshape(()))})
        grads[key] = central_difference(along, np.asarray(value, np.float64), step)
    return grads


# ---------------------------------------------------------------------------------------------
# Reference systems
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ReferenceSystem:
    """A Lagrangian system with independent NumPy oracles.

    - `dynamics`: the jaxdyn system under test.
    - `params`: a dict of float parameters.
    - `sample(rng)`: a random state (q, qd), NumPy float64, inside the system's valid region.
    - `mass_matrix(q, p)`, `accelerations(q, qd, p)`, `energy(q, qd, p)` (T + V): oracles.
    """

    name: str
    n: int
    dynamics: jaxdyn.Lagrangian
    params: dict
    sample: Callable
    mass_matrix: Callable
    accelerations: Callable
    energy: Callable


# Harmonic oscillator: T = ½ m q̇², V = ½ k q², q̈ = −(k/m) q.
def _ho_T(q, qd, p):
    return 0.5 * p["m"] * qd[0] ** 2


def _ho_V(q, p):
    return 0.5 * p["k"] * q[0] ** 2


HARMONIC_OSCILLATOR = ReferenceSystem(
    name="harmonic_oscillator",
    n=1,
    dynamics=jaxdyn.Lagrangian(_ho_T, _ho_V),
    params={"m": 1.7, "k": 4.3},
    sample=lambda rng: (rng.uniform(-2, 2, 1), rng.uniform(-2, 2, 1)),
    mass_matrix=lambda q, p: np.array([[p["m"]]]),
    accelerations=lambda q, qd, p: -p["k"] / p["m"] * q,
    energy=lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2 + 0.5 * p["k"] * q[0] ** 2,
)


# Simple pendulum (point mass, massless rod), θ from the downward vertical:
# T = ½ m l² θ̇², V = −m g l cos θ, θ̈ = −(g/l) sin θ.
def _pendulum_T(q, qd, p):
    return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2


def _pendulum_V(q, p):
    return -p["m"] * p["g"] * p["l"] * jnp.cos(q[0])


PENDULUM = ReferenceSystem(
    name="pendulum",
    n=1,
    dynamics=jaxdyn.Lagrangian(_pendulum_T, _pendulum_V),
    params={"m": 1.3, "l": 0.8, "g": 9.81},
    sample=lambda rng: (rng.uniform(-3, 3, 1), rng.uniform(-3, 3, 1)),
    mass_matrix=lambda q, p: np.array([[p["m"] * p["l"] ** 2]]),
    accelerations=lambda q, qd, p: -p["g"] / p["l"] * np.sin(q),
    energy=lambda q, qd, p: 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2
    - p["m"] * p["g"] * p["l"] * np.cos(q[0]),
)


# Double pendulum of two point masses, angles from the downward vertical. The energies are
# written from the Cartesian velocities of the two particles; the oracle is the textbook closed
# form of the accelerations (e.g. myphysicslab "double pendulum"), checked against
# sympy.physics.mechanics in test_lagrangian.py.
def _double_pendulum_T(q, qd, p):
    l1, l2 = p["l1"], p["l2"]
    v1 = jnp.stack([l1 * jnp.cos(q[0]) * qd[0], l1 * jnp.sin(q[0]) * qd[0]])
    v2 = v1 + jnp.stack([l2 * jnp.cos(q[1]) * qd[1], l2 * jnp.sin(q[1]) * qd[1]])
    return 0.5 * p["m1"] * jnp.dot(v1, v1) + 0.5 * p["m2"] * jnp.dot(v2, v2)


def _double_pendulum_V(q, p):
    y1 = -p["l1"] * jnp.cos(q[0])
    y2 = y1 - p["l2"] * jnp.cos(q[1])
    return p["g"] * (p["m1"] * y1 + p["m2"] * y2)


def _double_pendulum_mass_matrix(q, p):
    m1, m2, l1, l2 = p["m1"], p["m2"], p["l1"], p["l2"]
    c = m2 * l1 * l2 * np.cos(q[0] - q[1])
    return np.array([[(m1 + m2) * l1**2, c], [c, m2 * l2**2]])


def _double_pendulum_accelerations(q, qd, p):
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    t1, t2 = q
    w1, w2 = qd
    d = t1 - t2
    den = 2 * m1 + m2 - m2 * np.cos(2 * t1 - 2 * t2)
    a1 = (
        -g * (2 * m1 + m2) * np.sin(t1)
        - m2 * g * np.sin(t1 - 2 * t2)
        - 2 * np.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * np.cos(d))
    ) / (l1 * den)
    a2 = (
        2
        * np.sin(d)
        * (w1**2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(t1) + w2**2 * l2 * m2 * np.cos(d))
    ) / (l2 * den)
    return np.array([a1, a2])


def _double_pendulum_energy(q, qd, p):
    m1, m2, l1, l2, g = p["m1"], p["m2"], p["l1"], p["l2"], p["g"]
    T = (
        0.5 * (m1 + m2) * l1**2 * qd[0] ** 2
        + 0.5 * m2 * l2**2 * qd[1] ** 2
        + m2 * l1 * l2 * qd[0] * qd[1] * np.cos(q[0] - q[1])
    )
    V = -(m1 + m2) * g * l1 * np.cos(q[0]) - m2 * g * l2 * np.cos(q[1])
    return T + V


DOUBLE_PENDULUM = ReferenceSystem(
    name="double_pendulum",
    n=2,
    dynamics=jaxdyn.Lagrangian(_double_pendulum_T, _double_pendulum_V),
    params={"m1": 1.2, "m2": 0.7, "l1": 1.1, "l2": 0.6, "g": 9.81},
    sample=lambda rng: (rng.uniform(-3, 3, 2), rng.uniform(-3, 3, 2)),
    mass_matrix=_double_pendulum_mass_matrix,
    accelerations=_double_pendulum_accelerations,
    energy=_double_pendulum_energy,
)


# 25.2 Elastic pendulum, q = (r, θ): T = ½ m (ṙ² + r² θ̇²), V = −m g r cos θ + ½ k (r − l₀)².
#   m r̈ − m r θ̇² − m g cos θ + k (r − l₀) = 0,   r θ̈ + 2 ṙ θ̇ + g sin θ = 0.
def _elastic_T(q, qd, p):
    return 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def _elastic_V(q, p):
    return -p["m"] * p["g"] * q[0] * jnp.cos(q[1]) + 0.5 * p["k"] * (q[0] - p["l0"]) ** 2


def _elastic_accelerations(q, qd, p):
    m, g, k, l0 = p["m"], p["g"], p["k"], p["l0"]
    r, th = q
    rd, thd = qd
    rdd = (m * r * thd**2 + m * g * np.cos(th) - k * (r - l0)) / m
    thdd = -(2 * rd * thd + g * np.sin(th)) / r
    return np.array([rdd, thdd])


ELASTIC_PENDULUM = ReferenceSystem(
    name="elastic_pendulum_25_2",
    n=2,
    dynamics=jaxdyn.Lagrangian(_elastic_T, _elastic_V),
    params={"m": 0.9, "g": 9.81, "k": 35.0, "l0": 1.2},
    sample=lambda rng: (
        np.array([rng.uniform(0.5, 2.0), rng.uniform(-3, 3)]),
        rng.uniform(-2, 2, 2),
    ),
    mass_matrix=lambda q, p: np.diag([p["m"], p["m"] * q[0] ** 2]),
    accelerations=_elastic_accelerations,
    energy=lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)
    - p["m"] * p["g"] * q[0] * np.cos(q[1])
    + 0.5 * p["k"] * (q[0] - p["l0"]) ** 2,
)


# 25.3 Rolling disc (M, R) tied to a wall by a spring k, uniform rod (m, l) hinged at its
# centre, q = (x, φ):
#   T = ¾ M ẋ² + ½ m ẋ² + ⅙ m l² φ̇² + ½ m l ẋ φ̇ cos φ,  V = ½ k x² − ½ m g l cos φ
#   (3/2 M + m) ẍ + ½ m l (φ̈ cos φ − φ̇² sin φ) + k x = 0
#   ⅓ m l² φ̈ + ½ m l ẍ cos φ + ½ m g l sin φ = 0
def _disc_rod_T(q, qd, p):
    M, m, l = p["M"], p["m"], p["l"]
    x_d, phi_d = qd
    return (
        0.75 * M * x_d**2
        + 0.5 * m * x_d**2
        + m * l**2 * phi_d**2 / 6
        + 0.5 * m * l * x_d * phi_d * jnp.cos(q[1])
    )


def _disc_rod_V(q, p):
    return 0.5 * p["k"] * q[0] ** 2 - 0.5 * p["m"] * p["g"] * p["l"] * jnp.cos(q[1])


def _disc_rod_mass_matrix(q, p):
    M, m, l = p["M"], p["m"], p["l"]
    c = 0.5 * m * l * np.cos(q[1])
    return np.array([[1.5 * M + m, c], [c, m * l**2 / 3]])


def _disc_rod_accelerations(q, qd, p):
    m, l, g, k = p["m"], p["l"], p["g"], p["k"]
    x, phi = q
    phi_d = qd[1]
    rhs = np.array(
        [-k * x + 0.5 * m * l * phi_d**2 * np.sin(phi), -0.5 * m * g * l * np.sin(phi)]
    )
    return np.linalg.solve(_disc_rod_mass_matrix(q, p), rhs)


DISC_SPRING_ROD = ReferenceSystem(
    name="disc_spring_rod_25_3",
    n=2,
    dynamics=jaxdyn.Lagrangian(_disc_rod_T, _disc_rod_V),
    params={"M": 2.5, "m": 0.8, "l": 1.4, "k": 12.0, "g": 9.81},
    sample=lambda rng: (rng.uniform(-2, 2, 2), rng.uniform(-2, 2, 2)),
    mass_matrix=_disc_rod_mass_matrix,
    accelerations=_disc_rod_accelerations,
    energy=lambda q, qd, p: 0.75 * p["M"] * qd[0] ** 2
    + 0.5 * p["m"] * qd[0] ** 2
    + p["m"] * p["l"] ** 2 * qd[1] ** 2 / 6
    + 0.5 * p["m"] * p["l"] * qd[0] * qd[1] * np.cos(q[1])
    + 0.5 * p["k"] * q[0] ** 2
    - 0.5 * p["m"] * p["g"] * p["l"] * np.cos(q[1]),
)


# 25.1 Two wheels (weight P each, radius r, moment of inertia J) and a bar (weight Q) rolling
# down an incline of angle β; s is the distance travelled. Weights, so masses are P/g, Q/g:
#   T = ½ (2P + Q)/g ṡ² + J ṡ²/r²,  V = −(2P + Q) s sin β,
#   a = (2P + Q) g r² sin β / ((2P + Q) r² + 2 J g).
def _wheels_T(q, qd, p):
    return 0.5 * (2 * p["P"] + p["Q"]) / p["g"] * qd[0] ** 2 + p["J"] * qd[0] ** 2 / p["r"] ** 2


def _wheels_V(q, p):
    return -(2 * p["P"] + p["Q"]) * q[0] * jnp.sin(p["beta"])


def _wheels_acceleration(p):
    P, Q, J, r, g, beta = p["P"], p["Q"], p["J"], p["r"], p["g"], p["beta"]
    return (2 * P + Q) * g * r**2 * np.sin(beta) / ((2 * P + Q) * r**2 + 2 * J * g)


WHEELS_BAR = ReferenceSystem(
    name="wheels_bar_25_1",
    n=1,
    dynamics=jaxdyn.Lagrangian(_wheels_T, _wheels_V),
    params={"P": 30.0, "Q": 50.0, "J": 0.4, "r": 0.35, "g": 9.81, "beta": 0.4},
    sample=lambda rng: (rng.uniform(-5, 5, 1), rng.uniform(-3, 3, 1)),
    mass_matrix=lambda q, p: np.array(
        [[(2 * p["P"] + p["Q"]) / p["g"] + 2 * p["J"] / p["r"] ** 2]]
    ),
    accelerations=lambda q, qd, p: np.array([_wheels_acceleration(p)]),
    energy=lambda q, qd, p: 0.5 * (2 * p["P"] + p["Q"]) / p["g"] * qd[0] ** 2
    + p["J"] * qd[0] ** 2 / p["r"] ** 2
    - (2 * p["P"] + p["Q"]) * q[0] * np.sin(p["beta"]),
)


# ---------------------------------------------------------------------------------------------
# Rheonomic (time-dependent) systems
# ---------------------------------------------------------------------------------------------

DRIVEN_SUPPORT_PARAMS = {"m": 0.7, "l": 1.3, "g": 9.81, "A": 0.2, "w": 5.0}


def _driven_support_T(t, q, qd, p):
    """Pendulum whose support moves vertically, y_s = A cos ωt: bob at
    (l sin θ, y_s − l cos θ), velocity (l cos θ θ̇, ẏ_s + l sin θ θ̇)."""
    ys_dot = -p["A"] * p["w"] * jnp.sin(p["w"] * t)
    vx = p["l"] * jnp.cos(q[0]) * qd[0]
    vy = ys_dot + p["l"] * jnp.sin(q[0]) * qd[0]
    return 0.5 * p["m"] * (vx**2 + vy**2)


def _driven_support_V(t, q, p):
    ys = p["A"] * jnp.cos(p["w"] * t)
    return p["m"] * p["g"] * (ys - p["l"] * jnp.cos(q[0]))


DRIVEN_SUPPORT = jaxdyn.Lagrangian(_driven_support_T, _driven_support_V, time_dependent=True)


def driven_support_acceleration(t, theta, p):
    """Hand-derived: θ̈ = −(g + ÿ_s)/l sin θ, ÿ_s = −A ω² cos ωt."""
    ys_ddot = -p["A"] * p["w"] ** 2 * np.cos(p["w"] * t)
    return -(p["g"] + ys_ddot) / p["l"] * np.sin(theta)


BEAD_PARAMS = {"m": 0.3, "R": 0.8, "g": 9.81, "Omega": 4.5}


def _bead_position(t, q, p):
    """Bead on a hoop of radius R spinning about the vertical axis at rate Ω; θ from the
    bottom of the hoop."""
    s = p["R"] * jnp.sin(q[0])
    angle = p["Omega"] * t
    return jnp.stack([s * jnp.cos(angle), s * jnp.sin(angle), -p["R"] * jnp.cos(q[0])])


def _bead_T(t, q, qd, p):
    # Velocity of the bead by a JVP of its position along (ṫ, q̇) = (1, q̇).
    _, velocity = jax.jvp(lambda t, q: _bead_position(t, q, p), (t, q), (jnp.ones_like(t), qd))
    return 0.5 * p["m"] * jnp.dot(velocity, velocity)


def _bead_V(t, q, p):
    return p["m"] * p["g"] * _bead_position(t, q, p)[2]


BEAD_ON_HOOP = jaxdyn.Lagrangian(_bead_T, _bead_V, time_dependent=True)



SYSTEMS = [
    HARMONIC_OSCILLATOR,
    PENDULUM,
    DOUBLE_PENDULUM,
    ELASTIC_PENDULUM,
    DISC_SPRING_ROD,
    WHEELS_BAR,
]
SYSTEM_IDS = [system.name for system in SYSTEMS]


def sample_states(system: ReferenceSystem, num: int, seed: int = 0):
    """`num` random states (q, qd) of `system`, each NumPy float64 of shape (num, n)."""
    rng = np.random.default_rng(seed)
    states = [system.sample(rng) for _ in range(num)]
    q = np.stack([np.asarray(s[0], np.float64) for s in states])
    qd = np.stack([np.asarray(s[1], np.float64) for s in states])
    return q, qd


def rod_chain():
    """A planar chain of rods (absolute angles q, point masses m at lengths l) from T and V,
    as a user writes it: any number of rods, by the sizes of p["m"] and p["l"]."""
    def kinetic(q, qd, p):
        vx = jnp.cumsum(p["l"] * jnp.cos(q) * qd)
        vy = jnp.cumsum(p["l"] * jnp.sin(q) * qd)
        return 0.5 * jnp.sum(p["m"] * (vx**2 + vy**2))

    def potential(q, p):
        return p["g"] * jnp.sum(p["m"] * -jnp.cumsum(p["l"] * jnp.cos(q)))

    return jaxdyn.Lagrangian(kinetic, potential)
