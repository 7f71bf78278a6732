"""jaxdyn example: fits that find the global optimum, or say that they did not.

An elastic pendulum (polar coordinates r, θ; spring stiffness k and natural length l₀ unknown,
mass and gravity known) is observed through the bob's horizontal position alone, two records
of 4 s with noise σ = 1e-3, the data from SciPy. Trajectory matching of an oscillation has a
local minimum wherever the simulated and measured motions are a whole number of periods
apart. From k 2× and l₀ 0.8× the truth:

1. one Levenberg–Marquardt fit (`globalisation=False`) meets its tolerance in a local minimum;
   the result says so (`explains_data=False`: residuals far above the noise estimated from
   the data) and warns;
2. by default `jaxdyn.fit` then fits again by horizon continuation (the first eighth, quarter
   and half of every record, then the whole, each from the last optimum) and ends at the
   truth;
3. `jaxdyn.fit_batch` fits three pendulums with different springs at once, each with its own
   parameters, continuing the ones left trapped.

(`globalisation=jaxdyn.MultiStart(8)` fits eight starting points around the guess at once and
keeps the best; from 100 random guesses at 0.5–2× the truth it found the optimum in 88 % of
them, continuation in 100 %: benchmarks/bench_globalisation.py. From this guess all eight of
its starts end trapped, and it says so.)

Run:  python examples/fit_globalisation.py
"""

import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import jaxdyn


def kinetic(q, qd, p):
    return 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2)


def potential(q, p):
    r, theta = q
    return -p["m"] * p["g"] * r * jnp.cos(theta) + 0.5 * p["k"] * (r - p["l0"]) ** 2


def bob_x(t, q, u, p):  # what was measured: the bob's horizontal position r sin θ
    return q[:1] * jnp.sin(q[1:])


def records(truth, seed, sigma=1e-3):
    """Two records of 4 s from rest, from the hand-written equations (SciPy, DOP853)."""
    m, g, k, l0 = (truth[key] for key in ("m", "g", "k", "l0"))

    def rhs(t, y):
        r, theta, r_dot, theta_dot = y
        return [r_dot, theta_dot, r * theta_dot**2 + g * np.cos(theta) - k / m * (r - l0),
                -(2 * r_dot * theta_dot + g * np.sin(theta)) / r]

    rng, out = np.random.default_rng(seed), []
    for q0 in ([1.3, 0.5], [1.0, -0.8]):
        ts = np.linspace(0.0, 4.0, 201)
        y = solve_ivp(rhs, (0.0, 4.0), [*q0, 0.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12,
                      method="DOP853").y
        x = y[0] * np.sin(y[1]) + sigma * rng.standard_normal(ts.size)
        out.append(jaxdyn.Experiment(ts, x[:, None], q0=q0, u0=[0.0, 0.0]))
    return out


def main():
    pendulum = jaxdyn.Lagrangian(kinetic, potential)
    truth = {"m": 0.9, "g": 9.81, "k": 35.0, "l0": 1.2}
    options = dict(filter_spec={"m": False, "g": False, "k": True, "l0": True},
                   observe=bob_x, fit_initial_states=True, uncertainty=False, progress=False)
    guess = {**truth, "k": 2.0 * truth["k"], "l0": 0.8 * truth["l0"]}
    data = records(truth, seed=5)

    def show(label, result):
        print(f"{label:34s} k = {float(result.params['k']):6.2f}, "
              f"l0 = {float(result.params['l0']):.3f}, loss {result.loss:9.3g}, "
              f"explains the data: {result.explains_data} ({result.strategy}, "
              f"{result.wall_time:.1f} s)")

    print(f"truth: k = {truth['k']}, l0 = {truth['l0']}; guess: k = {guess['k']}, "
          f"l0 = {guess['l0']:.2f}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        direct = jaxdyn.fit(pendulum, data, guess, globalisation=False, **options)
    show("1. one Levenberg–Marquardt fit", direct)
    for warning in caught:
        print("   warned:", type(warning.message).__name__, "—",
              str(warning.message).split(":")[0])
    show("2. default (continuation if trapped)", jaxdyn.fit(pendulum, data, guess, **options))

    springs = [{**truth, "k": k, "l0": l0} for k, l0 in ((35.0, 1.2), (20.0, 1.0), (50.0, 1.4))]
    start = time.perf_counter()
    fleet = jaxdyn.fit_batch(pendulum, [records(t, seed=i) for i, t in enumerate(springs)],
                             [{**t, "k": 2.0 * t["k"], "l0": 0.8 * t["l0"]} for t in springs],
                             **options)
    print(f"3. fit_batch, three pendulums ({time.perf_counter() - start:.1f} s):")
    for spring, result in zip(springs, fleet):
        show(f"   truth k = {spring['k']}, l0 = {spring['l0']}", result)


if __name__ == "__main__":
    main()
