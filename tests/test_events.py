"""Events, resets and impacts (`simulate(..., events=...)`): the bouncing ball, resting
contact, a pendulum against a wall, resets and stops, against closed forms, an event-located
SciPy solve and finite differences (impacts through each formulation: test_impacts.py).

One system is compiled per family of tests (module-level functions), so that the file's
tests share their compiled programs.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.special

import jaxdyn
from helpers import central_difference, compiles

TOL = dict(solver=diffrax.Tsit5(), rtol=1e-11, atol=1e-11)
G = 9.81


# -- a ball bouncing on the ground: impact times and apex heights in closed form -------------

def _ball_T(q, qd, p):
    return 0.5 * p["m"] * jnp.sum(qd**2)


def _ball_V(q, p):
    return p["m"] * p["g"] * q[1]


BALL = jaxdyn.Lagrangian(_ball_T, _ball_V)
GROUND = jaxdyn.UnilateralContact(lambda q, p: q[1], restitution=lambda p: p["e"])


TS = jnp.linspace(0.0, 3.0, 61)


def _bounces(e, h0, *, max_events=40, adjoint=None, t1=3.0, ts=TS):
    """The ball dropped from h₀ with horizontal speed 0.4: the tests that call it with the
    defaults share one compiled program."""
    p = {"m": 0.7, "g": G, "e": e}
    return jaxdyn.simulate(BALL, jnp.stack([0.0, h0]), jnp.array([0.4, 0.0]), p, t1=t1,
                           ts=ts, events=[GROUND], max_events=max_events, adjoint=adjoint,
                           **TOL)


def _impact_times(e, h0, k):
    """t_1 = √(2h₀/g), each flight after it 2 e^j v₁ / g."""
    first = np.sqrt(2 * h0 / G)
    flights = 2 * first * e ** np.arange(1, k)
    return first + np.concatenate([[0.0], np.cumsum(flights)])


def test_ball_impact_times_apexes_and_impulses_closed_form():
    e, h0 = 0.8, 1.0
    sol = _bounces(e, h0)
    count = int(sol.events.count)
    assert count == 6  # the seventh impact falls after t1 = 3
    np.testing.assert_allclose(sol.events.t[:count], _impact_times(e, h0, count), rtol=1e-9)
    assert np.all(np.isnan(sol.events.t[count:])) and np.all(sol.events.guard[count:] == -1)
    # the vertical speed reverses with factor e; the horizontal one is untouched
    v_in = np.asarray(sol.events.u_minus[:count, 1])
    np.testing.assert_allclose(sol.events.u_plus[:count, 1], -e * v_in, rtol=1e-12)
    np.testing.assert_allclose(sol.events.u_plus[:count, 0], 0.4, rtol=1e-12)
    # apex k: e^{2k} h₀; impulse m (1 + e) |v|
    apexes = np.asarray(sol.events.u_plus[:count, 1]) ** 2 / (2 * G)
    np.testing.assert_allclose(apexes, e ** (2 * np.arange(1, count + 1)) * h0, rtol=1e-9)
    np.testing.assert_allclose(sol.events.impulses[:count, 0], -0.7 * (1 + e) * v_in,
                               rtol=1e-12)
    np.testing.assert_allclose(sol.events.guard_rates[:count, 0], v_in, rtol=1e-12)
    assert float(sol.q[-1, 1]) > 0  # never below the ground


def test_ball_saved_states_follow_the_bounces():
    """States saved at ts between impacts: the parabola of each flight."""
    e, h0 = 0.8, 1.0
    ts = TS
    sol = _bounces(e, h0)
    impacts = _impact_times(e, h0, 7)
    v = G * impacts[0] * e ** np.arange(0, 7)  # launch speed after impact k (k ≥ 1)
    expected = []
    for t in np.asarray(ts):
        k = np.searchsorted(impacts, t)  # flights before t
        if k == 0:
            expected.append(h0 - 0.5 * G * t**2)
        else:
            s = t - impacts[k - 1]
            expected.append(v[k] * s - 0.5 * G * s**2)
    np.testing.assert_allclose(sol.q[:, 1], expected, atol=1e-9)
    np.testing.assert_allclose(sol.q[:, 0], 0.4 * np.asarray(ts), rtol=1e-12)


def _third_impact(e, h0, adjoint=None):
    return _bounces(e, h0, adjoint=adjoint, max_events=4, t1=2.0, ts=None).events.t[2]


def _third_impact_closed(e, h0):
    first = jnp.sqrt(2 * h0 / G)
    return first * (1 + 2 * e + 2 * e * e)


@pytest.mark.parametrize("adjoint", [None, diffrax.RecursiveCheckpointAdjoint()],
                         ids=["forward sensitivities", "reverse"])
def test_ball_gradient_of_impact_time_in_e_and_h0(adjoint):
    gradient = jax.grad(_third_impact, argnums=(0, 1))(0.8, 1.0, adjoint)
    expected = jax.grad(_third_impact_closed, argnums=(0, 1))(0.8, 1.0)
    np.testing.assert_allclose(gradient, expected, rtol=1e-8)


def test_ball_forward_mode_across_impacts():
    jacobian = jax.jacfwd(_third_impact, argnums=(0, 1))(0.8, 1.0)
    expected = jax.grad(_third_impact_closed, argnums=(0, 1))(0.8, 1.0)
    np.testing.assert_allclose(jacobian, expected, rtol=1e-8)


def test_batch_members_with_different_event_counts():
    """One compiled program; each member stops at its own number of events."""
    def count(h0):
        sol = jaxdyn.simulate(BALL, jnp.array([0.0, h0]), jnp.array([0.0, 0.0]),
                              {"m": 1.0, "g": G, "e": 0.9}, t1=1.2, events=GROUND,
                              max_events=12, **TOL)
        return sol.events.count, sol.q[-1, 1]
    h0s = np.array([0.1, 0.6, 3.0])
    counts, heights = jax.jit(jax.vmap(count))(jnp.asarray(h0s))
    expected = [int(np.sum(_impact_times(0.9, h, 40) <= 1.2)) for h in h0s]
    np.testing.assert_array_equal(counts, expected)
    assert np.all(np.asarray(heights) >= 0)


def test_event_budget_is_reported():
    """Out of events: the error names the budget and the time and state where the solve
    stopped (the third impact, at t₁ (1 + 2e + 2e²))."""
    with pytest.raises(Exception, match="max_events") as error:
        _bounces(0.8, 1.0, max_events=2)
    stopped = float(error.value.args[0].split("It happened at t = ")[1].split(",")[0])
    np.testing.assert_allclose(stopped, _impact_times(0.8, 1.0, 3)[2], rtol=1e-9)
    # throw=False: the result says so (one compiled program shared with the check below)
    def record(h0, throw):
        sol = jaxdyn.simulate(BALL, jnp.stack([0.0, h0]), jnp.array([0.4, 0.0]),
                              {"m": 0.7, "g": G, "e": 0.8}, t1=3.0, events=[GROUND],
                              max_events=2, throw=throw, **TOL)
        return sol.result, sol.events.count

    result, count = jax.jit(record, static_argnums=1)(1.0, False)
    assert result == jaxdyn.RESULTS.max_events_reached and int(count) == 2
    # inside a caller's jit, reading only the record of events still raises
    with pytest.raises(Exception, match="max_events"):
        jax.jit(lambda h0: record(h0, True)[1])(1.0)


def test_zeno_ball_comes_to_rest_at_the_accumulation_time():
    """Impacts with e < 1 accumulate at t∞ = t₁ (1 + e)/(1 − e); the contact then rests
    (held by its normal force m g) and the ball slides on at its horizontal speed."""
    e = 0.5
    sol = _bounces(e, 1.0)
    count = int(sol.events.count)
    t_inf = np.sqrt(2 / G) * (1 + e) / (1 - e)
    assert bool(sol.events.resting[count - 1, 0]) and not np.any(sol.events.resting[:count - 1])
    # the rest begins within rest_within / (1 − e) of the accumulation time
    assert t_inf - 3e-5 < float(sol.events.t[count - 1]) <= t_inf
    after = np.asarray(TS) > t_inf
    np.testing.assert_allclose(sol.q[after, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(sol.u[after, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(sol.q[after, 0], 0.4 * np.asarray(TS)[after], rtol=1e-10)
    # the floor carries the ball's weight m g from then on
    np.testing.assert_allclose(sol.events.normal_forces[after, 0], 0.7 * G, rtol=1e-10)


def test_resting_contact_released_when_its_normal_force_vanishes():
    """A body at rest on the floor, pulled up by a force k t growing in time: the normal force
    m g − k t falls through zero at t_r = m g / k, where the contact is released; then
    y = k (t − t_r)³ / (6 m)."""
    k = 4.0
    lifted = jaxdyn.Lagrangian(lambda t, q, qd, p: 0.5 * jnp.sum(qd**2),
                               lambda t, q, p: G * q[0] - k * t * q[0], time_dependent=True)
    floor = jaxdyn.UnilateralContact(lambda t, q, p: q[0], time_dependent=True)
    ts = jnp.linspace(0.0, 3.5, 8)
    sol = jaxdyn.simulate(lifted, jnp.array([0.0]), jnp.array([0.0]), t1=3.5, ts=ts,
                          events=[floor], max_events=4, **TOL)
    t_release = G / k
    assert int(sol.events.count) == 2  # met at rest at t = 0, released at t_r
    np.testing.assert_array_equal(sol.events.resting[:2, 0], [True, False])
    np.testing.assert_allclose(sol.events.t[:2], [0.0, t_release], atol=1e-10)
    expected = np.where(ts > t_release, k / 6 * (ts - t_release) ** 3, 0.0)
    np.testing.assert_allclose(sol.q[:, 0], expected, atol=1e-9)
    # the floor's normal force while the body rests, m g − k t (from the event at t = 0+ on)
    np.testing.assert_allclose(sol.events.normal_forces[1:, 0],
                               np.where(ts < t_release, G - k * ts, 0.0)[1:], atol=1e-9)


def test_fit_recovers_restitution_and_drop_height():
    """`jaxdyn.fit` with events: e and h₀ from noisy heights of a ball bouncing into rest
    (the data from the closed form)."""
    e, h0 = 0.75, 1.2
    ts = np.linspace(0.0, 2.5, 126)
    impacts = _impact_times(e, h0, 40)
    launch = G * impacts[0] * e ** np.arange(0, 40)
    heights = []
    for t in ts:
        k = np.searchsorted(impacts, t)
        s = t - (impacts[k - 1] if k else 0.0)
        heights.append(h0 - 0.5 * G * t**2 if k == 0 else max(launch[k] * s - 0.5 * G * s**2,
                                                                0.0))
    noisy = np.array(heights) + 1e-3 * np.random.default_rng(0).standard_normal(ts.shape)
    vertical = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2),
                                 lambda q, p: G * q[0])
    floor = jaxdyn.UnilateralContact(lambda q, p: q[0], restitution=lambda p: p["e"])
    experiment = jaxdyn.Experiment(ts=jnp.asarray(ts), observations=jnp.asarray(noisy),
                                   q0=jnp.array([1.0]), u0=jnp.array([0.0]))
    result = jaxdyn.fit(vertical, experiment, {"e": 0.6}, fit_initial_states=True,
                        simulate_options={"events": [floor], "max_events": 40, **TOL},
                        progress=False)
    assert result.converged
    np.testing.assert_allclose(result.params["e"], e, atol=5 * result.standard_errors["e"])
    np.testing.assert_allclose(np.ravel(result.initial_states[0][0])[0], h0, atol=2e-3)


# -- a pendulum swinging into a wall: complete elliptic integrals ----------------------------

def _pendulum_T(q, qd, p):
    return 0.5 * p["l"] ** 2 * qd[0] ** 2


def _pendulum_V(q, p):
    return -G * p["l"] * jnp.cos(q[0])


PENDULUM = jaxdyn.Lagrangian(_pendulum_T, _pendulum_V)
WALL = jaxdyn.UnilateralContact(lambda q, p: -q[0], restitution=lambda p: p["e"])  # θ ≤ 0


def test_pendulum_into_a_wall_elliptic_integrals():
    """Released from θ₀ < 0, the pendulum reaches the wall at the vertical after a quarter
    period K(sin²(θ₀/2))/ω; it rebounds with e times the speed to an amplitude θ₁ and returns
    after half a period of that amplitude, 2K(sin²(θ₁/2))/ω."""
    l, e, theta0 = 0.9, 0.7, -2.0
    omega = np.sqrt(G / l)
    sol = jaxdyn.simulate(PENDULUM, jnp.array([theta0]), jnp.zeros(1), {"l": l, "e": e},
                          t1=2.5, events=[WALL], max_events=3, **TOL)
    t1 = scipy.special.ellipk(np.sin(theta0 / 2) ** 2) / omega
    speed = 2 * omega * np.sin(-theta0 / 2)  # θ̇ at the bottom
    theta1 = 2 * np.arcsin(e * speed / (2 * omega))
    t2 = t1 + 2 * scipy.special.ellipk(np.sin(theta1 / 2) ** 2) / omega
    np.testing.assert_allclose(sol.events.t[:2], [t1, t2], rtol=1e-9)
    np.testing.assert_allclose(sol.events.u_minus[0, 0], speed, rtol=1e-9)


def _scipy_wall(e, theta0, l, t_end):
    """An independent reference: SciPy's `solve_ivp` with a terminal event, restarted by hand
    after each impact (θ̇ → −e θ̇)."""
    def f(t, y):
        return [y[1], -G / l * np.sin(y[0])]

    def hit(t, y):
        return -y[0]
    hit.terminal, hit.direction = True, -1
    t, y = 0.0, np.array([theta0, 0.0])
    while True:
        out = scipy.integrate.solve_ivp(f, (t, t_end), y, method="DOP853", rtol=1e-13,
                                        atol=1e-13, events=hit)
        if out.status != 1:
            return out.y[:, -1]
        t, y = out.t_events[0][0], out.y_events[0][0].copy()
        y[0], y[1] = 0.0, -e * y[1]
        t += 1e-14  # leave the wall (the event is located at θ = 0)


@pytest.mark.parametrize("adjoint", [diffrax.RecursiveCheckpointAdjoint(), None],
                         ids=["reverse mode through the solve", "sensitivities and saltation"])
def test_gradient_through_impacts_against_scipy_finite_differences(adjoint):
    """d(θ, θ̇)(t_end)/d(e, θ₀, l) after two impacts, by `jax.jacrev`, against central
    differences of SciPy's event-located solve: reverse mode through the restarted solve,
    and the default forward sensitivities (the sensitivity equations along each segment, the
    saltation across each impact)."""
    t_end = 2.6

    def final(x):
        e, theta0, l = x
        sol = jaxdyn.simulate(PENDULUM, jnp.stack([theta0]), jnp.zeros(1), {"l": l, "e": e},
                              t1=t_end, events=[WALL], max_events=4, adjoint=adjoint, **TOL)
        return jnp.concatenate([sol.q[-1], sol.u[-1]]), sol.events.count

    x = np.array([0.7, -2.0, 0.9])
    jacobian, count = jax.jacrev(final, has_aux=True)(jnp.asarray(x))
    assert int(count) == 2
    reference = central_difference(lambda x: _scipy_wall(*x, t_end), x, step=1e-5)
    np.testing.assert_allclose(jacobian, reference, rtol=1e-5, atol=1e-6)
    # and the values: the same as SciPy's, through the same compiled program
    value = jax.vjp(lambda x: final(x)[0], jnp.asarray(x))[0]
    np.testing.assert_allclose(value, _scipy_wall(*x, t_end), rtol=1e-8)


# -- events with a reset, and events that stop ----------------------------------------------

def test_reset_wraps_the_angle_of_a_rotating_pendulum():
    """θ is wrapped back by 2π each time it passes π: the motion is the unwrapped motion
    modulo 2π, and the events fall where the unwrapped angle passes π + 2πk."""
    wrap = jaxdyn.Event(lambda q, u, p: q[0] - np.pi, lambda q, u, p: (q - 2 * np.pi, u),
                        direction="rising")
    ts = jnp.linspace(0.0, 4.0, 41)
    args = (PENDULUM, jnp.array([0.0]), jnp.array([8.0]), {"l": 1.0})
    wrapped = jaxdyn.simulate(*args, t1=4.0, ts=ts, events=[wrap], max_events=8, **TOL)
    free = jaxdyn.simulate(*args, t1=4.0, ts=ts, **TOL)
    count = int(wrapped.events.count)
    assert count >= 3
    unwrapped = np.asarray(free.q[:, 0])
    np.testing.assert_allclose(np.asarray(wrapped.q[:, 0]),
                               np.mod(unwrapped + np.pi, 2 * np.pi) - np.pi, atol=1e-8)
    dense = jaxdyn.simulate(*args, t1=4.0, dense=True, **TOL)
    crossing = [dense.evaluate(t)[0][0] for t in np.asarray(wrapped.events.t[:count])]
    np.testing.assert_allclose(crossing, np.pi + 2 * np.pi * np.arange(count), atol=1e-8)


def test_stop_event_ends_the_motion():
    """A ball thrown up stops when it first falls back through its launch height: at
    t = 2 v₀ / g, and nothing is saved after it."""
    stop = jaxdyn.Event(lambda q, u, p: q[1] - 1.0)
    ts = jnp.linspace(0.0, 2.0, 21)
    sol = jaxdyn.simulate(BALL, jnp.array([0.0, 1.0]), jnp.array([0.0, 3.0]),
                          {"m": 1.0, "g": G}, t1=2.0, ts=ts, events=[stop], **TOL)
    t_stop = 2 * 3.0 / G
    assert int(sol.events.count) == 1
    np.testing.assert_allclose(sol.events.t[0], t_stop, rtol=1e-11)
    before = np.asarray(ts) <= t_stop
    np.testing.assert_allclose(sol.q[before, 1], 1.0 + 3.0 * ts[before] - 0.5 * G * ts[before]
                               ** 2, atol=1e-10)
    assert np.all(np.isnan(np.asarray(sol.q[~before])))


def test_the_earliest_of_guards_crossing_in_one_step_fires_whatever_their_order():
    """A particle at constant speed, x = t, stopped at x = 0.4 or x = 0.7 by guards that fire
    either way: the motion is polynomial, so the solver's steps are long and one step crosses
    both. The stop is at t = 0.4 by the guard at 0.4, whatever the order the guards are
    listed in, whichever side of zero each starts on, and as one vector guard."""
    free = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd @ qd, lambda q, p: 0.0 * q[0])
    far = jaxdyn.Event(lambda q, u, p: 0.7 - q[0], direction="either")  # starts positive
    near = jaxdyn.Event(lambda q, u, p: q[0] - 0.4, direction="either")  # starts negative
    both = jaxdyn.Event(lambda q, u, p: jnp.stack([0.7 - q[0], q[0] - 0.4]), direction="either")
    for events, guard in (([far, near], 1), ([near, far], 0), ([both], 1)):
        sol = jaxdyn.simulate(free, jnp.array([0.0]), jnp.array([1.0]), t1=2.0,
                              events=events, max_events=2, **TOL)
        assert int(sol.events.count) == 1
        np.testing.assert_allclose(sol.events.t[0], 0.4, rtol=1e-14)
        assert int(sol.events.guard[0]) == guard


# -- bad input -------------------------------------------------------------------------------

def _ball_floor(q, p):
    return q[1]


def test_a_restitution_given_as_a_number_is_not_compiled_in():
    """A coefficient given as a Python number is traced like the parameters: a new value
    gives its own impact times and compiles nothing (JAX's compile events counted)."""
    for e in (0.8, 0.9):
        with compiles() as count:
            floor = jaxdyn.UnilateralContact(_ball_floor, restitution=e)
            sol = jaxdyn.simulate(BALL, jnp.array([0.0, 1.0]), jnp.array([0.4, 0.0]),
                                  {"m": 0.7, "g": G}, t1=1.9, events=[floor], max_events=4,
                                  **TOL)
        assert count() == 0 or e == 0.8, "a new restitution compiled again"
        expected = _impact_times(e, 1.0, 4)
        expected = expected[expected < 1.9]  # three impacts, then two
        assert int(sol.events.count) == expected.size
        np.testing.assert_allclose(np.asarray(sol.events.t)[:expected.size], expected,
                                   rtol=1e-9)


def test_bad_events_are_named():
    args = (BALL, jnp.array([0.0, 1.0]), jnp.zeros(2), {"m": 1.0, "g": G, "e": 0.5})
    with pytest.raises(ValueError, match="direction"):
        jaxdyn.Event(lambda q, u, p: q[1], direction="down")
    with pytest.raises(ValueError, match="events must be jaxdyn events"):
        jaxdyn.simulate(*args, t1=1.0, events=[lambda q, u, p: q[1]])
    with pytest.raises(ValueError, match="max_events"):
        jaxdyn.simulate(*args, t1=1.0, events=[GROUND], max_events=0)
    with pytest.raises(ValueError, match="dense"):
        jaxdyn.simulate(*args, t1=1.0, events=[GROUND], dense=True)
    matrix = jaxdyn.UnilateralContact(lambda q, p: jnp.outer(q, q))
    with pytest.raises(ValueError, match="scalar or a vector"):
        jaxdyn.simulate(*args, t1=1.0, events=[matrix])
    with pytest.raises(ValueError, match="restitution"):
        jaxdyn.simulate(*args, t1=1.0, events=[jaxdyn.UnilateralContact(
            lambda q, p: q[1], restitution=jnp.array([0.5, 0.5]))])


def test_simulate_batch_with_events():
    """`simulate_batch` passes events through: balls dropped from several heights, each with
    its own impacts (the closed form), as single solves give them."""
    heights = np.array([0.3, 1.0, 2.0])
    q0 = jnp.stack([jnp.zeros(3), jnp.asarray(heights)], axis=1)
    batch = jaxdyn.simulate_batch(BALL, q0, jnp.zeros((3, 2)), {"m": 1.0, "g": G, "e": 0.9},
                                  t1=2.0, events=[GROUND], max_events=12, **TOL)
    for i, h in enumerate(heights):
        expected = _impact_times(0.9, h, 40)
        expected = expected[expected <= 2.0]
        count = int(batch.events.count[i])
        assert count == len(expected)
        np.testing.assert_allclose(batch.events.t[i, :count], expected, rtol=1e-9)
