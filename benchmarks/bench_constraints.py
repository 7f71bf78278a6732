"""Constraints: cost and drift of each drift control, against the same motion in minimal
coordinates written by hand.

Run: python benchmarks/bench_constraints.py   (about 2 minutes)

The pendulum in Cartesian coordinates (x, y) with the rod x² + y² = l² as a holonomic
constraint (`jaxdyn.Constrained` of a `Lagrangian`), started at 2 rad, integrated over 100 s
(about 55 periods) with Tsit5 at rtol = atol = 1e-8, against θ̈ = −(g/l) sin θ written by hand in
jax.numpy and integrated by `diffrax.diffeqsolve` with the same solver and tolerances. For each
drift control (none, Baumgarte α = β = 10 s⁻¹, projection) and for the elimination into one
independent speed (`Constrained.eliminate`): the run time ratio to the hand-written solve, the
steps taken, the largest position violation |x² + y² − l²| and velocity violation at 1001 save
times, and the largest deviation of x from the hand-written solution's l sin θ.
"""

import os
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compile_seconds, interleaved

P = {"m": 1.0, "l": 1.0, "g": 9.81}
T1, TOL, THETA0 = 100.0, 1e-8, 2.0
TS = jnp.linspace(0.0, T1, 1001)


def kinetic(q, qd, p):
    return 0.5 * p["m"] * jnp.sum(qd**2)


def potential(q, p):
    return p["m"] * p["g"] * q[1]


def rod(q, p):
    return jnp.stack([q[0] ** 2 + q[1] ** 2 - p["l"] ** 2])


def by_hand(theta0):
    def field(t, y, args):
        return jnp.stack([y[1], -P["g"] / P["l"] * jnp.sin(y[0])])

    return diffrax.diffeqsolve(
        diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, T1, None, jnp.stack([theta0, 0.0]),
        saveat=diffrax.SaveAt(ts=TS), stepsize_controller=diffrax.PIDController(rtol=TOL,
                                                                                 atol=TOL),
        max_steps=100_000)


def main():
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64; pendulum in (x, y), "
          f"{T1:.0f} s, Tsit5 at {TOL:g}")
    l = P["l"]
    q0 = jnp.array([l * np.sin(THETA0), -l * np.cos(THETA0)])
    u0 = jnp.zeros(2)
    hand = jax.jit(by_hand)
    reference = hand(jnp.asarray(THETA0))
    x_reference = l * np.sin(np.asarray(reference.ys[:, 0]))
    variants = {
        "none": jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=rod,
                                   stabilisation=None),
        "Baumgarte": jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=rod,
                                        stabilisation=jaxdyn.Baumgarte()),
        "projection": jaxdyn.Constrained(jaxdyn.Lagrangian(kinetic, potential), holonomic=rod),
    }
    eliminated = variants["projection"].eliminate(0.0, q0, jnp.array([0.0, 0.1]), P,
                                                  independent=(0,))
    print(f"{'':>12s} {'time/hand':>9s} {'compile':>8s} {'steps':>6s} {'hand':>6s} "
          f"{'|φ| max':>8s} {'|φ̇| max':>8s} {'|x − x_hand|':>12s}")
    hand_steps = int(reference.stats["num_steps"])
    for name, system in [*variants.items(), ("eliminated", eliminated)]:
        v0 = u0[:1] if name == "eliminated" else u0

        def ours(q0, system=system, v0=v0):
            return jaxdyn.simulate(system, q0, v0, P, t1=T1, ts=TS, solver=diffrax.Tsit5(),
                                   rtol=TOL, atol=TOL, max_steps=100_000)

        compile_time = compile_seconds(ours, q0)
        times = interleaved({"hand": (hand, (jnp.asarray(THETA0),)),
                             "ours": (jax.jit(ours), (q0,))}, number=3)
        sol = jax.jit(ours)(q0)
        u = sol.u if name != "eliminated" else eliminated.speeds(sol.ts, sol.q, sol.u, P)
        constrained = variants["projection"]
        phi = np.max(np.abs(constrained.position_violation(sol.ts, sol.q, u, P)))
        phid = np.max(np.abs(constrained.velocity_violation(sol.ts, sol.q, u, P)))
        error = np.max(np.abs(np.asarray(sol.q[:, 0]) - x_reference))
        print(f"{name:>12s} {times['ours'] / times['hand']:8.2f}× {compile_time:7.1f}s "
              f"{int(sol.num_steps):6d} {hand_steps:6d} {phi:8.1e} {phid:8.1e} {error:12.1e}",
              flush=True)


if __name__ == "__main__":
    main()
