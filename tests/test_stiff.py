"""Stiff systems (recognised by the linearisation's eigenvalues, solved implicitly) and
singular or ill-conditioned configurations."""

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn

G = 9.81

# A pendulum on a stiff, heavily damped spring, in polar coordinates (r, θ): the radial
# spring k and damper c give real eigenvalues near −c/m and −k/c, the swing ±i √(g/l).
SPRING_PENDULUM = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2),
    lambda q, p: 0.5 * p["k"] * (q[0] - p["l"]) ** 2 - p["m"] * G * q[0] * jnp.cos(q[1]),
    dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)
STIFF_P = {"m": 1.0, "k": 1e12, "c": 1e7, "l": 1.0}
# Released at rest at 1 rad, with the spring at its static stretch.
STIFF_Q0 = jnp.array([1.0 + G * np.cos(1.0) / 1e12, 1.0])


def test_stiffness_is_recognised_from_the_eigenvalues():
    report = jaxdyn.stiffness(SPRING_PENDULUM, 0.0, STIFF_Q0, jnp.zeros(2), STIFF_P)
    # The linearisation's eigenvalues, by hand: radial m λ² + c λ + k = 0, and the swing's
    # λ² = −g cos θ / l (the radial mode decouples at rest).
    m, c, k = STIFF_P["m"], STIFF_P["c"], STIFF_P["k"]
    radial = np.roots([m, c, k])
    swing = np.sqrt(G * np.cos(1.0) / STIFF_P["l"])
    expected = np.sort(np.abs(np.concatenate([radial, [swing, swing]])))
    np.testing.assert_allclose(np.sort(np.abs(report.eigenvalues)), expected, rtol=1e-6)
    assert report.ratio == pytest.approx(np.abs(radial).max() / swing, rel=1e-6)
    assert report.ratio > 1e6 and report.stiff and report.damped
    assert isinstance(report.solver, diffrax.Kvaerno5)
    assert "implicit solver" in report.recommendation

    pendulum = jaxdyn.stiffness(SPRING_PENDULUM, 0.0, STIFF_Q0, jnp.zeros(2),
                                {**STIFF_P, "k": 40.0, "c": 0.0})
    assert not pendulum.stiff and isinstance(pendulum.solver, diffrax.Dopri8)
    assert "Not stiff" in str(pendulum)


def test_a_stiff_system_solved_implicitly_matches_its_rigid_limit():
    """Stiffness ratio 4 × 10⁶: Kvaerno5 follows the slow swing in a few thousand steps, and
    the swing is that of the rigid pendulum (the spring's stretch is 10⁻¹¹); an explicit
    solver runs out of steps, and the error says how many it would need."""
    ts = jnp.linspace(0.0, 5.0, 11)
    sol = jaxdyn.simulate(SPRING_PENDULUM, STIFF_Q0, jnp.zeros(2), STIFF_P, t1=5.0, ts=ts,
                          solver=diffrax.Kvaerno5(), rtol=1e-8, atol=1e-8)
    rigid = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2,
                              lambda q, p: -G * jnp.cos(q[0]))
    reference = jaxdyn.simulate(rigid, STIFF_Q0[1:], jnp.zeros(1), t1=5.0, ts=ts)
    np.testing.assert_allclose(sol.q[:, 1], reference.q[:, 0], atol=1e-6)
    np.testing.assert_allclose(sol.q[:, 0], 1.0, atol=1e-10)
    assert int(sol.num_steps) < 5000
    with pytest.raises(RuntimeError, match=r"(?s)^The solver took the maximum number of steps.*"
                                           r"jaxdyn.stiffness"):
        jaxdyn.simulate(SPRING_PENDULUM, STIFF_Q0, jnp.zeros(2), STIFF_P, t1=5.0,
                        solver=diffrax.Tsit5(), rtol=1e-8, atol=1e-8, max_steps=2000)


# The spherical pendulum in polar and azimuthal angles (θ from the downward vertical): M =
# m l² diag(1, sin² θ) is singular at the pole θ = 0.
SPHERICAL = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * (qd[0] ** 2 + jnp.sin(q[0]) ** 2 * qd[1] ** 2),
    lambda q, p: -G * jnp.cos(q[0]))
# The symmetric top in Euler angles (φ, θ, ψ): gimbal lock at θ = 0, where φ and ψ turn
# about the same axis.
TOP = jaxdyn.Lagrangian(
    lambda q, qd, p: (0.5 * (qd[1] ** 2 + qd[0] ** 2 * jnp.sin(q[1]) ** 2)
                      + 0.25 * (qd[2] + qd[0] * jnp.cos(q[1])) ** 2),
    lambda q, p: jnp.cos(q[1]))


def test_the_condition_number_along_a_trajectory_announces_the_pole():
    qs = jnp.array([[1.0, 0.0], [1e-2, 0.0], [1e-4, 0.3], [0.0, 0.0]])
    condition = SPHERICAL.mass_matrix_condition(0.0, qs, jnp.zeros((4, 2)))
    np.testing.assert_allclose(condition[:3], 1 / np.sin(qs[:3, 0]) ** 2, rtol=1e-9)
    assert condition[3] == np.inf


@pytest.mark.parametrize("system, q0, u0", [
    (SPHERICAL, [0.3, 0.0], [-3.0, 1e-8]),            # through the pole
    (TOP, [0.0, 0.3, 0.0], [1e-8, -3.0, 0.0]),       # into gimbal lock
])
def test_a_coordinate_singularity_is_named_with_its_remedy(system, q0, u0):
    """Aimed (almost) through the singular configuration: the speed of the azimuth grows as
    1/sin² θ. Either a step lands where M is singular, or the steps shrink until the budget
    runs out; both errors name the coordinate singularity and the remedy."""
    with pytest.raises(RuntimeError, match=r"(?s)^The (mass matrix became singular along the "
                                           r"motion|solver took the maximum number of steps "
                                           r"\(max_steps\) before reaching t1, and the mass "
                                           r"matrix is ill-conditioned).*coordinate "
                                           r"singularity.*quaternions") as info:
        jaxdyn.simulate(system, jnp.array(q0), jnp.array(u0), t1=2.0)
    message = str(info.value)
    if "ill-conditioned" in message:  # the condition numbers at the start and where it stopped
        start, last = (float(x) for x in message.rsplit("[", 1)[1].rstrip("].").split(","))
        assert start < 100 and last > 1e8


def test_the_same_motion_in_cartesian_coordinates_passes_the_pole():
    """The remedy works: the spherical pendulum as a particle on a sphere (a constraint)."""
    constrained = jaxdyn.Constrained(
        jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.dot(qd, qd), lambda q, p: G * q[2]),
        holonomic=lambda q, p: jnp.array([jnp.dot(q, q) - 1.0]))
    theta = 0.3
    q0 = jnp.array([np.sin(theta), 0.0, -np.cos(theta)])
    u0 = 3.0 * jnp.array([-np.cos(theta), 1e-8, -np.sin(theta)])
    sol = jaxdyn.simulate(constrained, q0, u0, t1=2.0, ts=jnp.linspace(0.0, 2.0, 21))
    radius = jnp.linalg.norm(sol.q, axis=1)
    np.testing.assert_allclose(radius, 1.0, atol=1e-8)
    assert float(jnp.min(jnp.abs(sol.q[:, 0]))) < 0.2  # it went over the bottom
