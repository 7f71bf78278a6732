"""jaxdyn example: a ball bouncing into rest, identified from its measured heights.

A ball dropped on a floor (a `jaxdyn.UnilateralContact` with Newton's law of restitution e)
bounces at times that accumulate at t∞ = t₁ (1 + e)/(1 − e), where it comes to rest. The
script

1. simulates the drop and checks the impact times and apex heights e^{2k} h₀ against their
   closed forms, and the moment of rest against t∞;
2. differentiates the third impact time with respect to e and checks it against the closed
   form and a central difference;
3. fits e and the drop height to noisy heights with `jaxdyn.fit`;
4. plots the measured and fitted heights to bouncing_ball.png.

Run:  python examples/bouncing_ball.py
"""

import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn

G = 9.81
SOLVE = dict(solver=diffrax.Tsit5(), rtol=1e-10, atol=1e-10)

ball = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2), lambda q, p: G * q[0])
floor = jaxdyn.UnilateralContact(lambda q, p: q[0], restitution=lambda p: p["e"])


def drop(e, h0, ts):
    return jaxdyn.simulate(ball, jnp.stack([h0]), jnp.zeros(1), {"e": e}, t1=ts[-1], ts=ts,
                           events=[floor], max_events=64, **SOLVE)


def impact_times(e, h0, k):
    t1 = np.sqrt(2 * h0 / G)
    return t1 + np.concatenate([[0.0], np.cumsum(2 * t1 * e ** np.arange(1, k))])


e, h0 = 0.75, 1.2
ts = jnp.linspace(0.0, 5.0, 251)
start = time.perf_counter()
sol = drop(e, h0, ts)
print(f"1. simulated in {time.perf_counter() - start:.1f} s (first call, compiling included)")
count = int(sol.events.count)
closed = impact_times(e, h0, count)
print(f"   {count} events, the last the ball coming to rest: "
      f"{bool(sol.events.resting[count - 1, 0])}")
print(f"   impact times against the closed form, first 20: "
      f"{np.max(np.abs(np.asarray(sol.events.t[:20]) - closed[:20])):.1e} s")
apex = np.asarray(sol.events.u_plus[:20, 0]) ** 2 / (2 * G)
print(f"   apex heights against e^(2k) h0, first 20: "
      f"{np.max(np.abs(apex / (e ** (2 * np.arange(1, 21)) * h0) - 1)):.1e} (relative)")
t_inf = np.sqrt(2 * h0 / G) * (1 + e) / (1 - e)
print(f"   at rest from {float(sol.events.t[count - 1]):.6f} s; t∞ = {t_inf:.6f} s")


def third_impact(e):
    return drop(e, h0, jnp.array([0.0, 3.0])).events.t[2]


derivative = float(jax.grad(third_impact)(e))
step = 1e-6
central = float((third_impact(e + step) - third_impact(e - step)) / (2 * step))
print(f"2. d t3 / d e = {derivative:.10f}; closed form "
      f"{2 * np.sqrt(2 * h0 / G) * (1 + 2 * e):.10f}; central difference {central:.10f}")

rng = np.random.default_rng(1)
heights = np.asarray(sol.q[:, 0]) + 2e-3 * rng.standard_normal(ts.shape)
experiment = jaxdyn.Experiment(ts=ts, observations=jnp.asarray(heights), q0=jnp.array([1.0]),
                               u0=jnp.array([0.0]))
start = time.perf_counter()
result = jaxdyn.fit(ball, experiment, {"e": 0.6}, fit_initial_states=True,
                    simulate_options={"events": [floor], "max_events": 64, **SOLVE},
                    progress=False)
fitted_h0 = float(np.ravel(result.initial_states[0][0])[0])
print(f"3. fitted in {time.perf_counter() - start:.1f} s: e = {float(result.params['e']):.5f} "
      f"± {float(result.standard_errors['e']):.5f} (true {e}), h0 = {fitted_h0:.4f} m "
      f"(true {h0})")

fit = drop(result.params["e"], fitted_h0, ts)
plt.figure(figsize=(8, 3))
plt.plot(ts, heights, ".", ms=3, label="measured (2 mm noise)")
plt.plot(ts, fit.q[:, 0], lw=1, label="fitted model")
plt.axvline(t_inf, color="k", lw=0.8, ls="--", label="t∞")
plt.xlabel("t [s]")
plt.ylabel("height [m]")
plt.legend()
plt.tight_layout()
out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "figures",
                   "bouncing_ball.png")
plt.savefig(out, dpi=120)
print(f"4. figure written to {os.path.relpath(out)}")
