"""Events and impacts: cost per impact, accuracy of event times and the cost of a gradient,
against the same work written by hand.

Run: python benchmarks/bench_events.py   (about 2 minutes)

A ball (x, y) dropped from 1 m with horizontal speed 0.3 m/s onto a floor with restitution
e = 0.9, simulated over 5 s (8 impacts), Tsit5 at rtol = atol = 1e-10:

- **jaxdyn**: `simulate(ball, ..., events=[UnilateralContact(...)], max_events=16)` from
  T and V, under `jax.jit`, and as the README calls it (not jitted, default `throw`);
- **hand-written diffrax (the floor)**: the closed-form vector field (ẋ, ẏ, 0, −g) in
  jax.numpy, a `diffrax.Event` on y located by optimistix's Newton, and the restart loop
  written by hand as a `lax.scan` over 17 segments with the reset v_y → −e v_y, under
  `jax.jit`: the fastest form of the same work in JAX that we know (no equations formed, no
  impact law solved, no resting-contact logic);
- **SciPy**: `solve_ivp` (DOP853, rtol = atol = 1e-10) with a terminal event, restarted in a
  Python loop (no derivatives).

Printed: run time per call and per impact against the floor, compile times, the largest
error of the 8 impact times against the closed form t_k = t₁ (1 + 2e + … + 2e^{k−1}), and the
cost of d(final state)/d(e, h₀) (jax.grad through each JAX candidate) against its forward
solve.
"""

import os
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.integrate

jax.config.update("jax_enable_x64", True)

import jaxdyn

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved

G, E, H0, VX, T1, TOL, SEGMENTS = 9.81, 0.9, 1.0, 0.3, 5.0, 1e-10, 16

ball = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * jnp.sum(qd**2), lambda q, p: G * q[1])
floor = jaxdyn.UnilateralContact(lambda q, p: q[1], restitution=lambda p: p["e"])


def jaxdyn_solve(e, h0):
    sol = jaxdyn.simulate(ball, jnp.stack([0.0, h0]), jnp.array([VX, 0.0]), {"e": e}, t1=T1,
                          events=[floor], max_events=SEGMENTS, solver=diffrax.Tsit5(),
                          rtol=TOL, atol=TOL)
    return sol.events.t, jnp.concatenate([sol.q[-1], sol.u[-1]])


def hand_solve(e, h0):
    """The restart loop written by hand: one diffeqsolve per flight in a scan."""
    term = diffrax.ODETerm(lambda t, y, args: jnp.stack([y[2], y[3], 0.0 * y[2], -G + 0.0 * y[3]]))
    event = diffrax.Event(lambda t, y, args, **kwargs: jnp.where(t == args, 1e-300, y[1]),
                          optx.Newton(rtol=1e-12, atol=1e-12), direction=False)
    controller = diffrax.PIDController(rtol=TOL, atol=TOL)

    def segment(carry, _):
        t, y = carry
        sol = diffrax.diffeqsolve(term, diffrax.Tsit5(), t, T1, None, y, args=t, event=event,
                                  stepsize_controller=controller, max_steps=4096, throw=False)
        t_end, y_end = sol.ts[-1], sol.ys[-1]
        hit = sol.event_mask
        y_next = jnp.where(hit, y_end * jnp.array([1.0, 1.0, 1.0, -e]), y_end)
        return (t_end, y_next), jnp.where(hit, t_end, jnp.nan)

    (_, y), times = jax.lax.scan(segment, (jnp.zeros(()), jnp.stack([0.0, h0, VX, 0.0])),
                                 None, length=SEGMENTS + 1)
    return times[:SEGMENTS], y


def scipy_solve(e, h0):
    def f(t, y):
        return [y[2], y[3], 0.0, -G]

    def hit(t, y):
        return y[1]
    hit.terminal, hit.direction = True, -1
    t, y, times = 0.0, np.array([0.0, h0, VX, 0.0]), []
    while True:
        out = scipy.integrate.solve_ivp(f, (t, T1), y, method="DOP853", rtol=TOL, atol=TOL,
                                        events=hit)
        if out.status != 1:
            return np.array(times), out.y[:, -1]
        t, y = out.t_events[0][0], out.y_events[0][0].copy()
        times.append(t)
        y[1], y[3] = 0.0, -e * y[3]
        t += 1e-15


def closed_form_times():
    t1 = np.sqrt(2 * H0 / G)
    times = t1 + np.concatenate([[0.0], np.cumsum(2 * t1 * E ** np.arange(1, 40))])
    return times[times < T1]


def main():
    expected = closed_form_times()
    impacts = len(expected)
    e, h0 = jnp.asarray(E), jnp.asarray(H0)
    candidates = {"jaxdyn (jit)": jax.jit(jaxdyn_solve), "hand-written diffrax (jit)":
                  jax.jit(hand_solve)}
    compiles = {name: compile_seconds(fn, e, h0) for name, fn in candidates.items()}
    start = time.perf_counter()
    jax.block_until_ready(jaxdyn_solve(e, h0))
    compiles["jaxdyn (as the README calls it)"] = time.perf_counter() - start
    errors = {}
    for name, fn in candidates.items():
        times, _ = fn(e, h0)
        errors[name] = np.max(np.abs(np.asarray(times[:impacts]) - expected))
    scipy_times, _ = scipy_solve(E, H0)
    errors["SciPy solve_ivp"] = np.max(np.abs(scipy_times[:impacts] - expected))

    timing = {name: (fn, (e, h0)) for name, fn in candidates.items()}
    timing["jaxdyn (as the README calls it)"] = (jaxdyn_solve, (e, h0))
    grads = {name + ", jax.grad": (jax.jit(jax.grad(lambda e, h, fn=fn: jnp.sum(fn(e, h)[1]),
                                                    argnums=(0, 1))), (e, h0))
             for name, fn in (("jaxdyn", jaxdyn_solve), ("hand-written diffrax", hand_solve))}
    for name, (fn, args) in grads.items():
        compiles[name] = compile_seconds(fn, *args)
    seconds = interleaved({**timing, **grads}, number=3, rounds=7)
    start = time.perf_counter()
    for _ in range(5):
        scipy_solve(E, H0)
    seconds["SciPy solve_ivp"] = (time.perf_counter() - start) / 5

    floor_time = seconds["hand-written diffrax (jit)"]
    print(f"Bouncing ball, {impacts} impacts in {T1} s, Tsit5 at {TOL:g} "
          f"(SciPy: DOP853 at {TOL:g})\n")
    print(f"{'candidate':38s} {'run':>9s} {'per impact':>11s} {'/ floor':>8s} {'compile':>8s}"
          f" {'event-time error':>17s}")
    for name, value in seconds.items():
        if "grad" in name:
            continue
        print(f"{name:38s} {value * 1e3:7.2f} ms {value / impacts * 1e6:8.1f} µs "
              f"{value / floor_time:7.2f}x {compiles.get(name, float('nan')):7.1f} s "
              f"{errors.get(name.replace(' (as the README calls it)', ' (jit)'), np.nan):17.1e}")
    print("\nGradient d(final state)/d(e, h0), jax.grad under jax.jit:")
    for name in ("jaxdyn", "hand-written diffrax"):
        forward = seconds["jaxdyn (jit)" if name == "jaxdyn" else "hand-written diffrax (jit)"]
        value = seconds[name + ", jax.grad"]
        print(f"{name:38s} {value * 1e3:7.2f} ms  {value / forward:5.1f}x its forward solve, "
              f"{value / seconds['hand-written diffrax, jax.grad']:5.2f}x the floor's gradient;"
              f" compile {compiles[name + ', jax.grad']:.1f} s")


if __name__ == "__main__":
    main()
