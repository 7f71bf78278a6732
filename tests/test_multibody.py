"""Multibody systems: Particle/RigidBody descriptions through Lagrange, Gibbs–Appell and Kane.

Every check compares against something independent of the code under test: the other
formulations (different derivative paths: ∂²T/∂q̇², the Hessian of the Gibbs function, partial
velocities), closed forms and the textbook equations of worked examples 25.1–25.3, equations
derived by sympy.physics.mechanics.KanesMethod inside the tests, Euler's equations written by hand,
conservation laws along simulated trajectories, and finite differences.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sympy as sm
import sympy.physics.mechanics as me

import jaxdyn
from sympy_rolling_disc import sympy_rolling_disc
from multibody_systems import (
    HOLONOMIC,
    NONHOLONOMIC,
    SYSTEMS,
    cases,
    chain_joint,
    zxz_body_rates,
)

RTOL = 1e-10


def assert_rel(actual, desired, rtol=RTOL, what=""):
    """‖actual − desired‖ ≤ rtol ‖desired‖ (vector-relative, so that a component that happens
    to be near zero is judged on the scale of the whole vector)."""
    actual = np.asarray(actual, dtype=np.float64)
    desired = np.asarray(desired, dtype=np.float64)
    assert actual.shape == desired.shape, (what, actual.shape, desired.shape)
    error = np.linalg.norm(actual - desired)
    scale = np.linalg.norm(desired)
    assert error <= rtol * scale, f"{what}: |Δ| = {error:.3e}, |ref| = {scale:.3e}"


@eqx.filter_jit
def _accelerations(dynamics, q, u, p):
    return dynamics.accelerations(jnp.zeros((), q.dtype), q, u, p)


@eqx.filter_jit
def _mass_matrix(dynamics, q, u, p):
    return dynamics.mass_matrix(jnp.zeros((), q.dtype), q, u, p)


@functools.lru_cache(maxsize=None)
def formulations(name, with_map=True):
    """Built once per system (so that jit caches hit): {label: dynamics}."""
    ref = SYSTEMS[name]
    k = ref.kinematic_map if with_map else None
    out = {
        "gibbs_appell": jaxdyn.GibbsAppell.from_system(ref.system, k),
        "kane": jaxdyn.Kane(ref.system, k),
    }
    if k is None and ref.independent_coordinates:
        out["lagrangian"] = jaxdyn.Lagrangian.from_system(ref.system)
    return out


def ids(cases_):
    return [f"{name}-{i}" for name, i in cases_]


# ---------------------------------------------------------------------------------------------
# Three formulations agree on every holonomic system
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name,i", cases(HOLONOMIC), ids=ids(cases(HOLONOMIC)))
def test_formulations_agree(name, i):
    """Lagrange (Hessian of T), Gibbs–Appell (Hessian of S) and Kane (partial velocities) give
    the same accelerations, with speeds q̇ and, where the system has one, with the speeds of its
    kinematic map (q̈ = K u̇ + K̇ u)."""
    ref = SYSTEMS[name]
    q, u = ref.states[i]
    p = ref.params
    k = ref.kinematic_map
    results = {}
    if k is not None:
        by_speeds = {
            label: _accelerations(dyn, q, u, p) for label, dyn in formulations(name).items()
        }
        assert_rel(by_speeds["kane"], by_speeds["gibbs_appell"], what="Kane vs Gibbs–Appell")
        if ref.independent_coordinates:
            qd = k(q, p) @ u
            k_dot = jax.jvp(lambda q: k(q, p), (q,), (qd,))[1]
            for label, ud in by_speeds.items():
                results[f"{label} (map)"] = k(q, p) @ ud + k_dot @ u
    else:
        qd = u
    if ref.independent_coordinates:
        for label, dyn in formulations(name, with_map=False).items():
            results[label] = _accelerations(dyn, q, qd, p)
        assert len(results) >= 3
        for label, qdd in results.items():
            assert_rel(qdd, results["lagrangian"], what=f"{label} vs Lagrange")


@pytest.mark.parametrize("name", ["chain_3", "rolling_disc"])
def test_stacked_states_and_vmap(name):
    """Stacked states broadcast, and vmap over states matches one state at a time."""
    ref = SYSTEMS[name]
    kane = formulations(name)["kane"]
    qs = jnp.stack([q for q, _ in ref.states])
    us = jnp.stack([u for _, u in ref.states])
    one_by_one = jnp.stack([_accelerations(kane, q, u, ref.params) for q, u in ref.states])
    vmapped = eqx.filter_jit(jax.vmap(lambda q, u: kane.accelerations(0.0, q, u, ref.params)))
    assert_rel(vmapped(qs, us), one_by_one, rtol=1e-13, what="vmap")
    stacked = eqx.filter_jit(lambda q, u: kane.accelerations(jnp.zeros(3), q, u, ref.params))
    assert_rel(stacked(qs, us), one_by_one, rtol=1e-13, what="stacked states")


# ---------------------------------------------------------------------------------------------
# Worked textbook examples 25.1–25.3
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("i", range(3))
def test_example_25_1_wheels_and_bar(i):
    """a = (2P + Q) g r² sin β / ((2P + Q) r² + 2 J g), whatever the state (P, Q weights)."""
    ref = SYSTEMS["wheels_and_bar_25_1"]
    p = ref.params
    q, u = ref.states[i]
    w = 2 * p["P"] + p["Q"]
    expected = w * p["g"] * p["r"] ** 2 * np.sin(p["beta"]) / (
        w * p["r"] ** 2 + 2 * p["J"] * p["g"])
    for label, dyn in formulations(ref.name).items():
        assert_rel(_accelerations(dyn, q, u, p), [expected], what=label)
    # T = ½ (2P + Q)/g ṡ² + J ṡ²/r²
    lagrangian = formulations(ref.name)["lagrangian"]
    kinetic = 0.5 * w / p["g"] * u[0] ** 2 + p["J"] * u[0] ** 2 / p["r"] ** 2
    assert_rel(lagrangian.kinetic_energy(0.0, q, u, p), kinetic, what="T")


@pytest.mark.parametrize("i", range(3))
def test_example_25_2_elastic_pendulum(i):
    """m r̈ − m r θ̇² − m g cos θ + k (r − l₀) = 0,   r θ̈ + 2 ṙ θ̇ + g sin θ = 0."""
    ref = SYSTEMS["elastic_pendulum_25_2"]
    p = ref.params
    q, u = ref.states[i]
    (r, th), (rd, thd) = np.asarray(q), np.asarray(u)
    m, k, l0, g = p["m"], p["k"], p["l0"], p["g"]
    expected = [r * thd**2 + g * np.cos(th) - k / m * (r - l0),
                -(2 * rd * thd + g * np.sin(th)) / r]
    for label, dyn in formulations(ref.name).items():
        qdd = np.asarray(_accelerations(dyn, q, u, p))
        assert_rel(qdd, expected, what=label)
        # and the residuals of the textbook equations, term by term
        res1 = m * qdd[0] - m * r * thd**2 - m * g * np.cos(th) + k * (r - l0)
        res2 = r * qdd[1] + 2 * rd * thd + g * np.sin(th)
        assert abs(res1) <= RTOL * (abs(m * qdd[0]) + abs(m * r * thd**2)
                                    + abs(m * g * np.cos(th)) + abs(k * (r - l0)))
        assert abs(res2) <= RTOL * (abs(r * qdd[1]) + abs(2 * rd * thd) + abs(g * np.sin(th)))


@pytest.mark.parametrize("i", range(3))
def test_example_25_3_disc_spring_rod(i):
    """(3/2 M + m) ẍ + ½ m l (φ̈ cos φ − φ̇² sin φ) + k x = 0,
    ⅓ m l² φ̈ + ½ m l ẍ cos φ + ½ m g l sin φ = 0."""
    ref = SYSTEMS["disc_spring_rod_25_3"]
    p = ref.params
    q, u = ref.states[i]
    (x, ph), (xd, phd) = np.asarray(q), np.asarray(u)
    M, m, l, k, g = p["M"], p["m"], p["l"], p["k"], p["g"]
    a = np.array([[1.5 * M + m, 0.5 * m * l * np.cos(ph)],
                  [0.5 * m * l * np.cos(ph), m * l**2 / 3]])
    b = np.array([0.5 * m * l * phd**2 * np.sin(ph) - k * x, -0.5 * m * g * l * np.sin(ph)])
    expected = np.linalg.solve(a, b)
    for label, dyn in formulations(ref.name).items():
        assert_rel(_accelerations(dyn, q, u, p), expected, what=label)
    # the textbook kinetic energy T = ¾ M ẋ² + ½ m ẋ² + ⅙ m l² φ̇² + ½ m l ẋ φ̇ cos φ
    kinetic = (0.75 * M * xd**2 + 0.5 * m * xd**2 + m * l**2 * phd**2 / 6
               + 0.5 * m * l * xd * phd * np.cos(ph))
    assert_rel(formulations(ref.name)["lagrangian"].kinetic_energy(0.0, q, u, p), kinetic,
               what="T")


# ---------------------------------------------------------------------------------------------
# sympy.physics.mechanics as oracle
# ---------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def sympy_chain(n):
    """KanesMethod for the planar chain of rods (u = q̇): lambdified (M, f)."""
    q = me.dynamicsymbols(f"q0:{n}")
    u = me.dynamicsymbols(f"u0:{n}")
    m = sm.symbols(f"m0:{n}", positive=True)
    l = sm.symbols(f"l0:{n}", positive=True)
    g = sm.symbols("g")
    N = me.ReferenceFrame("N")
    joint = me.Point("O")
    joint.set_vel(N, 0)
    bodies, loads = [], []
    for i in range(n):
        A = N.orientnew(f"A{i}", "Axis", [q[i], N.z])
        centre = joint.locatenew(f"G{i}", -l[i] / 2 * A.y)
        centre.v2pt_theory(joint, N, A)
        inertia = me.inertia(A, m[i] * l[i] ** 2 / 12, m[i] * l[i] ** 2 / 400,
                             m[i] * l[i] ** 2 / 12)
        bodies.append(me.RigidBody(f"B{i}", centre, A, m[i], (inertia, centre)))
        loads.append((centre, -m[i] * g * N.y))
        next_joint = joint.locatenew(f"P{i + 1}", -l[i] * A.y)
        next_joint.v2pt_theory(joint, N, A)
        joint = next_joint
    kd = [q[i].diff(me.dynamicsymbols._t) - u[i] for i in range(n)]
    kane = me.KanesMethod(N, q_ind=q, u_ind=u, kd_eqs=kd)
    kane.kanes_equations(bodies, loads)
    args = (q, u, m, l, g)
    return (sm.lambdify(args, kane.mass_matrix, "numpy"),
            sm.lambdify(args, kane.forcing, "numpy"))


@pytest.mark.parametrize("i", range(3))
def test_chain_vs_sympy(i):
    ref = SYSTEMS["chain_3"]
    p = ref.params
    q, u = ref.states[i]
    mass_matrix, forcing = sympy_chain(3)
    args = (np.asarray(q), np.asarray(u), np.asarray(p["m"]), np.asarray(p["l"]), p["g"])
    m_sym = np.asarray(mass_matrix(*args), dtype=np.float64)
    f_sym = np.asarray(forcing(*args), dtype=np.float64).reshape(-1)
    expected = np.linalg.solve(m_sym, f_sym)
    for label, dyn in formulations(ref.name).items():
        assert_rel(_mass_matrix(dyn, q, u, p), m_sym, what=f"{label} mass matrix")
        assert_rel(_accelerations(dyn, q, u, p), expected, what=label)


@functools.lru_cache(maxsize=None)
def sympy_sleigh():
    """KanesMethod for the Chaplygin sleigh, speeds (v, ω), kinematic equations q̇ = K u."""
    x, y, th = me.dynamicsymbols("x y theta")
    v, w = me.dynamicsymbols("v omega")
    m, inertia_z, ixx, iyy, a, g_t = sm.symbols("m I Ixx Iyy a g_t")
    t = me.dynamicsymbols._t
    N = me.ReferenceFrame("N")
    A = N.orientnew("A", "Axis", [th, N.z])
    O = me.Point("O")
    O.set_vel(N, 0)
    G = O.locatenew("G", x * N.x + y * N.y + a * A.x)
    G.set_vel(N, G.pos_from(O).dt(N))  # in terms of q̇: KanesMethod substitutes q̇ = K u
    kd = [x.diff(t) - v * sm.cos(th), y.diff(t) - v * sm.sin(th), th.diff(t) - w]
    body = me.RigidBody("sleigh", G, A, m, (me.inertia(A, ixx, iyy, inertia_z), G))
    kane = me.KanesMethod(N, q_ind=[x, y, th], u_ind=[v, w], kd_eqs=kd)
    kane.kanes_equations([body], [(G, -m * g_t * N.y)])
    qdot = sm.Matrix([x.diff(t), y.diff(t), th.diff(t)]).subs(kane.kindiffdict())
    args = ([x, y, th], [v, w], [m, inertia_z, ixx, iyy, a, g_t])
    to_args = lambda q, u, p: (q, u, [p[k] for k in ("m", "I", "Ixx", "Iyy", "a", "g_t")])
    return (sm.lambdify(args, kane.mass_matrix, "numpy"),
            sm.lambdify(args, kane.forcing, "numpy"),
            sm.lambdify(args, qdot, "numpy"), to_args)


SYMPY_NONHOLONOMIC = {"chaplygin_sleigh": sympy_sleigh, "rolling_disc": sympy_rolling_disc}


@pytest.mark.parametrize("name,i", cases(NONHOLONOMIC), ids=ids(cases(NONHOLONOMIC)))
def test_nonholonomic_vs_sympy(name, i):
    """Gibbs–Appell and Kane with the same independent speeds both match sympy's KanesMethod."""
    ref = SYSTEMS[name]
    p = ref.params
    q, u = ref.states[i]
    mass_matrix, forcing, qdot, to_args = SYMPY_NONHOLONOMIC[name]()
    args = to_args(np.asarray(q), np.asarray(u), p)
    # sympy's kinematic differential equations reproduce q̇ = K u
    assert_rel(ref.kinematic_map(q, p) @ u,
               np.asarray(qdot(*args), dtype=np.float64).reshape(-1), what="q̇ = K u")
    m_sym = np.asarray(mass_matrix(*args), dtype=np.float64)
    f_sym = np.asarray(forcing(*args), dtype=np.float64).reshape(-1)
    expected = np.linalg.solve(m_sym, f_sym)
    for label, dyn in formulations(name).items():
        assert_rel(_mass_matrix(dyn, q, u, p), m_sym, what=f"{label} mass matrix")
        assert_rel(_accelerations(dyn, q, u, p), expected, what=label)


# ---------------------------------------------------------------------------------------------
# Rigid bodies: Euler's equations, written by hand
# ---------------------------------------------------------------------------------------------


def _euler_residual(inertia, omega, omega_dot, torque):
    """(I ω̇ + ω × I ω − τ, its scale)."""
    terms = [inertia @ omega_dot, np.cross(omega, inertia @ omega), -torque]
    return sum(terms), sum(np.linalg.norm(t) for t in terms)


def _zxz_omega_and_rate(angles, rates, accelerations):
    """ω_body = E q̇ and ω̇_body = E q̈ + Ė q̇ from the hand-written E(θ, φ) of zxz angles."""
    e, e_dot = jax.jvp(zxz_body_rates, (angles,), (rates,))
    return np.asarray(e @ rates), np.asarray(e @ accelerations + e_dot @ rates)


@pytest.mark.parametrize("i", range(3))
def test_free_body_euler_angles_euler_equations(i):
    """Free body under gravity, zxz angles, speeds q̇: I ω̇ + ω × Iω = 0 in body axes and the
    centre of mass falls freely, for every formulation."""
    ref = SYSTEMS["free_body_euler"]
    p = ref.params
    q, u = ref.states[i]
    inertia = np.asarray(p["I"])
    for label, dyn in formulations(ref.name).items():
        qdd = _accelerations(dyn, q, u, p)
        assert_rel(qdd[:3], [0.0, 0.0, -p["g"]], what=f"{label} translation")
        omega, omega_dot = _zxz_omega_and_rate(q[3:], u[3:], qdd[3:])
        residual, scale = _euler_residual(inertia, omega, omega_dot, np.zeros(3))
        assert np.linalg.norm(residual) <= RTOL * scale, (label, residual, scale)


@pytest.mark.parametrize("i", range(3))
def test_free_body_quaternion_euler_equations(i):
    """Free body in (position, quaternion) with speeds (v, ω_body): u̇ = (0, ω̇) where
    I ω̇ + ω × Iω = 0, including a quaternion that is not of unit norm."""
    ref = SYSTEMS["free_body_quaternion"]
    p = ref.params
    q, u = ref.states[i]
    inertia = np.asarray(p["I"])
    omega = np.asarray(u[3:])
    expected = np.linalg.solve(inertia, -np.cross(omega, inertia @ omega))
    for label, dyn in formulations(ref.name).items():
        ud = np.asarray(_accelerations(dyn, q, u, p))
        assert np.linalg.norm(ud[:3]) <= RTOL * np.linalg.norm(ud[3:]), label
        assert_rel(ud[3:], expected, what=label)
        residual, scale = _euler_residual(inertia, omega, ud[3:], np.zeros(3))
        assert np.linalg.norm(residual) <= RTOL * scale, (label, residual, scale)


def _top_inertia_about_tip(p):
    return np.diag([p["I1"] + p["m"] * p["L"] ** 2, p["I1"] + p["m"] * p["L"] ** 2, p["I3"]])


def _top_gravity_torque(q, p):
    """Body-axes torque of gravity about the tip: (0, 0, L) × (−m g Rᵀ e_z), with
    Rᵀ e_z = (sin θ sin φ, sin θ cos φ, cos θ) for zxz angles (hand-derived)."""
    _, th, ph = np.asarray(q)
    up_in_body = np.array([np.sin(th) * np.sin(ph), np.sin(th) * np.cos(ph), np.cos(th)])
    return np.cross([0.0, 0.0, p["L"]], -p["m"] * p["g"] * up_in_body)


@pytest.mark.parametrize("i", range(3))
def test_heavy_top_euler_equations(i):
    """Heavy top about its fixed tip: I_O ω̇ + ω × I_O ω = τ_gravity in body axes, with speeds
    u = ω_body (Gibbs–Appell, Kane) and with speeds q̇ (all three formulations)."""
    ref = SYSTEMS["heavy_top"]
    p = ref.params
    q, u = ref.states[i]
    inertia = _top_inertia_about_tip(p)
    torque = _top_gravity_torque(q, p)
    for label, dyn in formulations(ref.name).items():  # u = ω_body
        ud = np.asarray(_accelerations(dyn, q, u, p))
        residual, scale = _euler_residual(inertia, np.asarray(u), ud, torque)
        assert np.linalg.norm(residual) <= RTOL * scale, (label, residual, scale)
    qd = ref.kinematic_map(q, p) @ u
    for label, dyn in formulations(ref.name, with_map=False).items():  # u = q̇
        qdd = _accelerations(dyn, q, qd, p)
        omega, omega_dot = _zxz_omega_and_rate(q, qd, qdd)
        assert_rel(omega, u, rtol=1e-13, what="ω from the hand-written E")
        residual, scale = _euler_residual(inertia, omega, omega_dot, torque)
        assert np.linalg.norm(residual) <= RTOL * scale, (label, residual, scale)


# ---------------------------------------------------------------------------------------------
# Conservation along simulated trajectories
# ---------------------------------------------------------------------------------------------

SIM = dict(rtol=1e-10, atol=1e-10)
# Relative drift allowed over these short runs. The tolerances bound the LOCAL error per step;
# the global error of an invariant after ~10²–10³ steps is 10–1000 times that (measured here:
# 1e-9–1e-8, scaling down with the tolerance). A wrong inertia or Coriolis term drifts by O(1).
CONSERVED = 1e3 * SIM["rtol"]


def assert_conserved(values, what, scale=None):
    values = np.asarray(values)
    scale = np.max(np.abs(values)) if scale is None else scale
    drift = np.max(np.abs(values - values[0]))
    assert drift <= CONSERVED * scale, f"{what}: drift {drift:.3e} on a scale of {scale:.3e}"


def _rotate_by_quaternion(quat, v):
    """R v = v + 2 w (e × v) + 2 e × (e × v) for the unit quaternion (w, e)."""
    quat = quat / np.linalg.norm(quat)
    w, e = quat[0], quat[1:]
    return v + 2 * w * np.cross(e, v) + 2 * np.cross(e, np.cross(e, v))


def test_free_body_conserves_momentum_and_energy():
    ref = SYSTEMS["free_body_quaternion"]
    p = ref.params
    q0, u0 = ref.states[2]  # the non-unit quaternion
    sol = jaxdyn.simulate(formulations(ref.name)["kane"], q0, u0, p, t1=2.0,
                          ts=jnp.linspace(0.0, 2.0, 21), **SIM)
    inertia = np.asarray(p["I"])
    q, u = np.asarray(sol.q), np.asarray(sol.u)
    spin = [_rotate_by_quaternion(qq[3:], inertia @ uu[3:]) for qq, uu in zip(q, u)]
    energy = [0.5 * p["m"] * uu[:3] @ uu[:3] + 0.5 * uu[3:] @ inertia @ uu[3:] for uu in u]
    spin = np.asarray(spin)
    scale = np.linalg.norm(spin[0])
    for axis in range(3):
        assert_conserved(spin[:, axis], f"angular momentum {axis}", scale)
    assert_conserved(energy, "energy")
    assert_conserved(np.linalg.norm(q[:, 3:], axis=1), "quaternion norm")
    assert_rel(q[:, :3], np.asarray(q0[:3]) + np.outer(sol.ts, u0[:3]), rtol=1e-12,
               what="translation")
    # the body really tumbles (the check is not vacuous)
    assert np.max(np.abs(u[:, 3:] - u[0, 3:])) > 0.1


def test_heavy_top_conserves_energy_and_momenta():
    """Energy, and the momenta of the cyclic angles ψ (about the vertical) and φ (about the
    symmetry axis), from `Lagrangian.momentum`, along a Gibbs–Appell run in speeds ω_body."""
    ref = SYSTEMS["heavy_top"]
    p = ref.params
    q0, u0 = ref.states[0]
    sol = jaxdyn.simulate(formulations(ref.name)["gibbs_appell"], q0, u0, p, t1=1.0,
                          ts=jnp.linspace(0.0, 1.0, 21), **SIM)
    inertia = _top_inertia_about_tip(p)
    q, omega = np.asarray(sol.q), np.asarray(sol.u)
    energy = [0.5 * w @ inertia @ w + p["m"] * p["g"] * p["L"] * np.cos(qq[1])
              for qq, w in zip(q, omega)]
    assert_conserved(energy, "energy")
    momenta = np.asarray(formulations(ref.name, with_map=False)["lagrangian"].momentum(
        sol.ts, sol.q, sol.qd, p))
    # independent values at t = 0: the vertical component of I_O ω, and I₃ ω₃
    _, th, ph = np.asarray(q0)
    up_in_body = np.array([np.sin(th) * np.sin(ph), np.sin(th) * np.cos(ph), np.cos(th)])
    assert_rel(momenta[0, 0], up_in_body @ inertia @ np.asarray(u0), what="p_ψ")
    assert_rel(momenta[0, 2], p["I3"] * u0[2], what="p_φ")
    assert_conserved(momenta[:, 0], "p_ψ", np.max(np.abs(momenta)))
    assert_conserved(momenta[:, 2], "p_φ", np.max(np.abs(momenta)))
    assert np.ptp(q[:, 1]) > 1e-3  # it nutates


def test_spherical_pendulum_conserves_energy_and_vertical_momentum():
    ref = SYSTEMS["spherical_pendulum"]
    p = ref.params
    q0, u0 = ref.states[0]
    sol = jaxdyn.simulate(formulations(ref.name)["lagrangian"], q0, u0, p, t1=2.0,
                          ts=jnp.linspace(0.0, 2.0, 21), **SIM)
    th, ph = np.asarray(sol.q).T
    thd, phd = np.asarray(sol.qd).T
    m, l, g = p["m"], p["l"], p["g"]
    energy = 0.5 * m * l**2 * (thd**2 + np.sin(th) ** 2 * phd**2) - m * g * l * np.cos(th)
    assert_conserved(energy, "energy", np.max(np.abs(energy)) + m * g * l)
    assert_conserved(m * l**2 * np.sin(th) ** 2 * phd, "L_z")
    assert np.ptp(th) > 0.1


def test_compound_pendulum_3d_conserves_energy_and_vertical_momentum():
    """Full inertia tensor, offset centre of mass, zyx angles: energy and the vertical angular
    momentum about the pivot, L_z = e_z · (m r × v + R I ω_body) with ω_world from Ṙ Rᵀ by
    finite differences of R (independent of the library's angular velocity)."""
    ref = SYSTEMS["compound_pendulum_3d"]
    p = ref.params
    q0, u0 = ref.states[0]
    sol = jaxdyn.simulate(formulations(ref.name)["kane"], q0, u0, p, t1=1.0,
                          ts=jnp.linspace(0.0, 1.0, 11), **SIM)
    inertia, c = np.asarray(p["I"]), np.asarray(p["c"])

    def rotation(a):  # zyx: R_z(yaw) R_y(pitch) R_x(roll), written out with numpy
        cz, sz, cy, sy, cx, sx = (np.cos(a[0]), np.sin(a[0]), np.cos(a[1]), np.sin(a[1]),
                                  np.cos(a[2]), np.sin(a[2]))
        rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        return rz @ ry @ rx

    energies, momenta = [], []
    for q, qd in zip(np.asarray(sol.q), np.asarray(sol.qd)):
        h = 1e-6
        r_mat = rotation(q)
        r_dot = (rotation(q + h * qd) - rotation(q - h * qd)) / (2 * h)
        skew = r_dot @ r_mat.T
        omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        r_g = r_mat @ c
        v_g = np.cross(omega, r_g)
        inertia_world = r_mat @ inertia @ r_mat.T
        energies.append(0.5 * p["m"] * v_g @ v_g + 0.5 * omega @ inertia_world @ omega
                        + p["m"] * p["g"] * r_g[2])
        momenta.append((p["m"] * np.cross(r_g, v_g) + inertia_world @ omega)[2])
    scale = np.max(np.abs(energies))
    # the finite differences of R carry ~1e-10 relative error, well inside CONSERVED
    assert_conserved(energies, "energy", scale)
    assert_conserved(momenta, "L_z", np.max(np.abs(momenta)))


def _sleigh_energy(q, u, p):
    """(T, V) of the sleigh: v_G = v A_x + a ω A_y."""
    v, w = u.T
    kinetic = 0.5 * p["m"] * (v**2 + p["a"] ** 2 * w**2) + 0.5 * p["I"] * w**2
    return kinetic, p["m"] * p["g_t"] * (q[:, 1] + p["a"] * np.sin(q[:, 2]))


def _disc_energy(q, u, p):
    """(T, V) of the disc: v_G = r (u2 L_x − u1 L_y), ω = (u1, u2, u3) in L axes, where the
    inertia is diag(¼, ½, ¼) m r² as in body axes (symmetric about y)."""
    m, r, g = p["m"], p["r"], p["g"]
    u1, u2, u3 = u.T
    kinetic = (0.5 * m * r**2 * (u1**2 + u2**2)
               + 0.5 * m * r**2 * (0.25 * u1**2 + 0.5 * u2**2 + 0.25 * u3**2))
    return kinetic, m * g * r * np.cos(q[:, 3])


def _sleigh_slip(q, qd, p):
    """Lateral velocity of the knife edge."""
    th = q[:, 2]
    return [-qd[:, 0] * np.sin(th) + qd[:, 1] * np.cos(th)]


def _disc_slip(q, qd, p):
    """Velocity of the contact point of the disc: lateral, and longitudinal minus r φ̇."""
    psi = q[:, 2]
    lateral = -qd[:, 0] * np.sin(psi) + qd[:, 1] * np.cos(psi)
    longitudinal = qd[:, 0] * np.cos(psi) + qd[:, 1] * np.sin(psi) - p["r"] * qd[:, 4]
    return [lateral, longitudinal]


@pytest.mark.parametrize(
    "name,formulation,energy,slip",
    [("chaplygin_sleigh", "kane", _sleigh_energy, _sleigh_slip),
     ("rolling_disc", "gibbs_appell", _disc_energy, _disc_slip)],
    ids=["chaplygin_sleigh", "rolling_disc"],
)
def test_nonholonomic_conserves_energy_and_constraint(name, formulation, energy, slip):
    ref = SYSTEMS[name]
    p = ref.params
    q0, u0 = ref.states[1]
    sol = jaxdyn.simulate(formulations(name)[formulation], q0, u0, p, t1=1.0,
                          ts=jnp.linspace(0.0, 1.0, 21), **SIM)
    q, u, qd = np.asarray(sol.q), np.asarray(sol.u), np.asarray(sol.qd)
    kinetic, potential = energy(q, u, p)
    scale = np.max(np.abs(kinetic)) + np.max(np.abs(potential))
    assert_conserved(kinetic + potential, "energy", scale)
    speed = np.max(np.linalg.norm(qd[:, :2], axis=1))
    for component in slip(q, qd, p):
        assert np.max(np.abs(component)) <= 1e-13 * speed
    assert np.ptp(q[:, 2]) > 0.1  # it turns


# ---------------------------------------------------------------------------------------------
# A Gibbs function written by hand
# ---------------------------------------------------------------------------------------------


def test_user_gibbs_appell_polar_particle():
    """S = ½ m [(r̈ − r θ̇²)² + (r θ̈ + 2 ṙ θ̇)²], Π = −∇V for the elastic pendulum's
    V = ½ k (r − l₀)² − m g r cos θ, vs the closed-form polar equations of motion."""
    def gibbs(q, u, ud, p):
        r, rd, thd = q[0], u[0], u[1]
        radial = ud[0] - r * thd**2
        transverse = r * ud[1] + 2 * rd * thd
        return 0.5 * p["m"] * (radial**2 + transverse**2)

    def potential(q, p):
        return 0.5 * p["k"] * (q[0] - p["l0"]) ** 2 - p["m"] * p["g"] * q[0] * jnp.cos(q[1])

    def active_forces(q, u, p):
        return -jax.grad(potential)(q, p)

    dyn = jaxdyn.GibbsAppell(gibbs=gibbs, active_forces=active_forces)
    p = {"m": 1.3, "k": 40.0, "l0": 1.0, "g": 9.81}
    rng = np.random.default_rng(7)
    for _ in range(3):
        q = jnp.asarray([rng.uniform(0.5, 1.5), rng.uniform(-2, 2)])
        u = jnp.asarray(rng.uniform(-2, 2, 2))
        (r, th), (rd, thd) = np.asarray(q), np.asarray(u)
        m, k, l0, g = p["m"], p["k"], p["l0"], p["g"]
        # m (r̈ − r θ̇²) = −∂V/∂r,  m r (r θ̈ + 2 ṙ θ̇) = −∂V/∂θ
        expected = [r * thd**2 + (-k * (r - l0) + m * g * np.cos(th)) / m,
                    (-m * g * r * np.sin(th) / (m * r) - 2 * rd * thd) / r]
        assert_rel(_accelerations(dyn, q, u, p), expected, what="polar")
        assert_rel(_mass_matrix(dyn, q, u, p), np.diag([m, m * r**2]), what="M")


# ---------------------------------------------------------------------------------------------
# Loads and dissipation
# ---------------------------------------------------------------------------------------------


def _chain_with(**extra):
    ref = SYSTEMS["chain_3"]
    return jaxdyn.MultibodySystem(ref.system.bodies, gravity=ref.system.gravity, **extra)


@functools.lru_cache(maxsize=None)
def _loaded_chains():
    """The 3-rod chain with a horizontal force at its tip and a motor between rods 0 and 1
    (torque +τ on rod 1, −τ on rod 0), as loads; and the same with the generalized force
    written by hand: Q_j = F l_j cos q_j + τ (−1, 1, 0)_j."""
    bodies = SYSTEMS["chain_3"].system.bodies
    force = lambda q, qd, p: jnp.array([p["F"], 0.0, 0.0])
    motor = lambda q, qd, p: p["tau"] - p["c"] * (qd[1] - qd[0])
    torque = lambda q, qd, p: jnp.array([0.0, 0.0, motor(q, qd, p)])
    reaction = lambda q, qd, p: -torque(q, qd, p)
    loaded = _chain_with(loads=(
        jaxdyn.PointForce(point=lambda q, p: chain_joint(q, p, 3), force=force),
        jaxdyn.BodyTorque(bodies[1], torque),
        jaxdyn.BodyTorque(bodies[0], reaction),
    ))

    def by_hand(q, qd, p):
        tip = p["F"] * p["l"] * jnp.cos(q)
        return tip + motor(q, qd, p) * jnp.array([-1.0, 1.0, 0.0])

    return loaded, jaxdyn.Lagrangian.from_system(_chain_with(forces=by_hand))


@functools.lru_cache(maxsize=None)
def _three(system):
    return {"lagrangian": jaxdyn.Lagrangian.from_system(system),
            "gibbs_appell": jaxdyn.GibbsAppell.from_system(system),
            "kane": jaxdyn.Kane(system)}


@pytest.mark.parametrize("i", range(3))
def test_point_force_and_body_torque(i):
    ref = SYSTEMS["chain_3"]
    p = {**ref.params, "F": 3.0, "tau": 1.7, "c": 0.4}
    q, u = ref.states[i]
    loaded, by_hand = _loaded_chains()
    expected = _accelerations(by_hand, q, u, p)
    free = _accelerations(formulations("chain_3")["lagrangian"], q, u, ref.params)
    assert np.linalg.norm(expected - free) > 0.1 * np.linalg.norm(free)  # the loads matter
    for label, dyn in _three(loaded).items():
        assert_rel(_accelerations(dyn, q, u, p), expected, what=f"loads, {label}")


@pytest.mark.parametrize("i", range(3))
def test_loads_on_chaplygin_sleigh(i):
    """A push F along the heading at the knife edge and a yaw torque τ, with the sleigh's
    closed-form equations in speeds (v, ω):
        m v̇ − m a ω² = F − m g_t sin θ,   (I + m a²) ω̇ + m a v ω = τ − m g_t a cos θ."""
    ref = SYSTEMS["chaplygin_sleigh"]
    body = ref.system.bodies[0]
    push = jaxdyn.PointForce(
        point=lambda q, p: jnp.array([q[0], q[1], 0.0 * q[0]]),
        force=lambda q, qd, p: p["F"] * jnp.array([jnp.cos(q[2]), jnp.sin(q[2]), 0.0 * q[2]]),
    )
    turn = jaxdyn.BodyTorque(body, lambda q, qd, p: jnp.array([0.0, 0.0, p["tau"]]))
    system = jaxdyn.MultibodySystem((body,), gravity=ref.system.gravity, loads=(push, turn))
    p = {**ref.params, "F": 0.8, "tau": -0.3}
    q, u = ref.states[i]
    th, (v, w) = float(q[2]), np.asarray(u)
    m, a, inertia, g_t = p["m"], p["a"], p["I"], p["g_t"]
    expected = [(p["F"] - m * g_t * np.sin(th)) / m + a * w**2,
                (p["tau"] - m * g_t * a * np.cos(th) - m * a * v * w) / (inertia + m * a**2)]
    for dyn in (jaxdyn.GibbsAppell.from_system(system, ref.kinematic_map),
                jaxdyn.Kane(system, ref.kinematic_map)):
        assert_rel(_accelerations(dyn, q, u, p), expected, what=type(dyn).__name__)


def _relative_rates(qd):
    return qd - jnp.concatenate([jnp.zeros(1, qd.dtype), qd[:-1]])


def _joint_damping(q, qd, p):
    """D = ½ Σ c_j (q̇_j − q̇_{j−1})² (q̇_{−1} = 0)."""
    return 0.5 * jnp.sum(p["c"] * _relative_rates(qd) ** 2)


def _joint_damping_by_hand(q, qd, p):
    """−∂D/∂q̇_j = −c_j (q̇_j − q̇_{j−1}) + c_{j+1} (q̇_{j+1} − q̇_j)."""
    joint = p["c"] * _relative_rates(qd)
    return -joint + jnp.concatenate([joint[1:], jnp.zeros(1, qd.dtype)])


@functools.lru_cache(maxsize=None)
def _damped_chains():
    return (_three(_chain_with(dissipation=_joint_damping)),
            jaxdyn.Lagrangian.from_system(_chain_with(forces=_joint_damping_by_hand)))


@pytest.mark.parametrize("i", range(3))
def test_rayleigh_dissipation(i):
    """Joint damping through a Rayleigh function gives the hand-written generalized force in
    every formulation."""
    ref = SYSTEMS["chain_3"]
    p = {**ref.params, "c": jnp.array([0.3, 0.5, 0.2])}
    q, u = ref.states[i]
    damped, by_hand = _damped_chains()
    expected = _accelerations(by_hand, q, u, p)
    free = _accelerations(formulations("chain_3")["lagrangian"], q, u, ref.params)
    assert np.linalg.norm(expected - free) > 0.01 * np.linalg.norm(free)
    for label, dyn in damped.items():
        assert_rel(_accelerations(dyn, q, u, p), expected, what=label)


# ---------------------------------------------------------------------------------------------
# Differentiating with respect to a mass; float32
# ---------------------------------------------------------------------------------------------


def test_grad_through_kane_wrt_body_mass():
    """d/dM of a trajectory loss (25.3: the rolling disc's mass M) through Kane and simulate,
    vs central finite differences. Fixed steps, so that the loss is a smooth function of the
    mass and the two agree to the finite-difference error."""
    ref = SYSTEMS["disc_spring_rod_25_3"]
    kane = formulations(ref.name)["kane"]
    q0, u0 = ref.states[0]
    ts = jnp.linspace(0.0, 1.0, 11)

    @jax.jit
    def loss(mass):
        p = {**ref.params, "M": mass}
        sol = jaxdyn.simulate(kane, q0, u0, p, t1=1.0, ts=ts, dt0=0.01,
                              stepsize_controller=diffrax.ConstantStepSize())
        # the rod's tip, x + l sin φ
        return jnp.mean((sol.q[:, 0] + p["l"] * jnp.sin(sol.q[:, 1])) ** 2)

    mass = jnp.asarray(ref.params["M"])
    grad = float(jax.jit(jax.grad(loss))(mass))
    h = 1e-4
    fd = float((loss(mass + h) - loss(mass - h)) / (2 * h))
    assert abs(grad) > 1e-3
    assert abs(grad - fd) <= 1e-6 * abs(fd), (grad, fd)


def test_float32_explicit():
    """With q, u and p in float32 every formulation computes in float32 and agrees with float64
    to ~1e-4; a short float32 simulation agrees with the float64 one."""
    ref = SYSTEMS["spherical_pendulum"]
    p64 = ref.params
    p32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), p64)
    for q, u in ref.states:
        q32, u32 = q.astype(jnp.float32), u.astype(jnp.float32)
        for label, dyn in formulations(ref.name).items():
            a32 = _accelerations(dyn, q32, u32, p32)
            assert a32.dtype == jnp.float32, label
            assert_rel(a32, _accelerations(dyn, q, u, p64), rtol=1e-4, what=label)
    q, u = ref.states[0]
    dyn = formulations(ref.name)["kane"]
    ts = jnp.linspace(0.0, 0.5, 6)
    sol32 = jaxdyn.simulate(dyn, q.astype(jnp.float32), u.astype(jnp.float32), p32, t1=0.5,
                            ts=ts.astype(jnp.float32), rtol=1e-6, atol=1e-6)
    sol64 = jaxdyn.simulate(dyn, q, u, p64, t1=0.5, ts=ts, rtol=1e-6, atol=1e-6)
    assert sol32.q.dtype == jnp.float32 and sol32.u.dtype == jnp.float32
    assert_rel(sol32.q, sol64.q, rtol=1e-4, what="float32 trajectory")


# ---------------------------------------------------------------------------------------------
# Clear errors
# ---------------------------------------------------------------------------------------------


def test_error_particle_position_shape():
    bad = jaxdyn.Particle(1.0, lambda q, p: q[:2])
    system = jaxdyn.MultibodySystem((bad,))
    q = jnp.array([0.1, 0.2])
    for dyn in _three(system).values():
        with pytest.raises(ValueError, match="Particle position must return a 3-vector"):
            dyn.accelerations(0.0, q, q, None)


def test_error_kinematic_map_shape():
    ref = SYSTEMS["chaplygin_sleigh"]
    q, u = ref.states[0]
    wrong = lambda q, p: jnp.zeros((3, 3))
    for dyn in (jaxdyn.GibbsAppell.from_system(ref.system, wrong), jaxdyn.Kane(ref.system, wrong)):
        with pytest.raises(ValueError, match=r"kinematic_map must return K of shape \(n, m\)"):
            dyn.accelerations(0.0, q, u, ref.params)


def test_error_speeds_without_map():
    ref = SYSTEMS["chaplygin_sleigh"]
    q, u = ref.states[0]  # 3 coordinates, 2 speeds, and no map given
    for dyn in (jaxdyn.GibbsAppell.from_system(ref.system), jaxdyn.Kane(ref.system)):
        with pytest.raises(ValueError, match="Without a kinematic_map the speeds are q̇"):
            dyn.accelerations(0.0, q, u, ref.params)
    with pytest.raises(ValueError, match="qd must have shape"):
        jaxdyn.Lagrangian.from_system(ref.system).accelerations(0.0, q, u, ref.params)
