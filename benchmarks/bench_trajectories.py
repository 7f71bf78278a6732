"""Whole trajectories, per-call overhead, gradients and compile time: `jaxdyn.simulate` against
`diffrax.diffeqsolve` on the hand-written right-hand side, with the same solver, tolerances,
step-size controller and adjoint, side by side in one process.

Run: python benchmarks/bench_trajectories.py            (about 15 minutes)
     python benchmarks/bench_trajectories.py --quick    (double pendulum only)

- trajectory: Tsit5 at rtol = atol = 1e-8 over 10 s (the chain of 20: 2 s), called as a user
  calls each (both entry points are jit-compiled functions);
- per call: the same over 1 ms (one step): what is left is the cost of calling;
- gradient: of Σ q(t_k)² over 11 save times with respect to the parameters, `jax.grad` with
  diffrax's default `RecursiveCheckpointAdjoint`, as a multiple of one forward solve of the
  same code; for two systems also with a checkpoint per step and with `ForwardMode` +
  `jax.jacfwd` (the adjoints `simulate` documents);
- compile: first call with every cache cleared, of the solve and of its gradient.
"""

import os
import sys

import diffrax
import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM, ELASTIC_PENDULUM, as_arrays, chain  # noqa: E402
from _timing import compile_seconds, interleaved  # noqa: E402

SOLVER = diffrax.Tsit5()
TOL = 1e-8
MAX_STEPS = 16**4


def solvers(system, t1, adjoint=diffrax.RecursiveCheckpointAdjoint(), ts=None):
    """(hand-written diffeqsolve, jaxdyn.simulate), each p -> saved q."""
    q0 = jnp.full(system.n, 0.9) if system.n > 2 else jnp.array([1.3, 0.4])
    qd0 = jnp.zeros(system.n)
    saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)

    def field(t, y, p):
        return y[1], system.hand_written(t, y[0], y[1], p)

    term = diffrax.ODETerm(field)

    def hand(p):
        return diffrax.diffeqsolve(
            term, SOLVER, 0.0, t1, None, (q0, qd0), args=p, saveat=saveat,
            stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
            max_steps=MAX_STEPS, adjoint=adjoint).ys[0]

    def ours(p):
        return jaxdyn.simulate(system.dynamics, q0, qd0, p, t1=t1, ts=ts, solver=SOLVER,
                               rtol=TOL, atol=TOL, max_steps=MAX_STEPS, adjoint=adjoint,
                               save="q").q

    return hand, ours


def loss(solve):
    return lambda p: jnp.sum(solve(p) ** 2)


def trajectories(system, t1):
    p = as_arrays(system.params)
    hand, ours = solvers(system, t1)
    difference = float(jnp.max(jnp.abs(hand(p) - ours(p))))
    compile_hand, compile_ours = compile_seconds(hand, p), compile_seconds(ours, p)
    times = interleaved({"hand": (hand, (p,)), "jaxdyn": (ours, (p,))}, number=3, rounds=7)
    return times, (compile_hand, compile_ours), difference


def per_call(system):
    p = as_arrays(system.params)
    hand, ours = solvers(system, 1e-3)
    return interleaved({"hand": (hand, (p,)), "jaxdyn": (ours, (p,)),
                        "hand, in jit": (jax.jit(hand), (p,)),
                        "jaxdyn, in jit": (jax.jit(ours), (p,))}, number=200)


def gradients(system, t1, adjoints=False):
    p = as_arrays(system.params)
    ts = jnp.linspace(0.0, t1, 11)
    hand, ours = solvers(system, t1, ts=ts)
    grad_hand, grad_ours = jax.grad(loss(hand)), jax.grad(loss(ours))
    gh, go = jax.jit(grad_hand)(p), jax.jit(grad_ours)(p)
    # relative to the largest component (the chain's motion does not depend on its mass, so
    # that gradient is round-off on both sides)
    scale = max(float(jnp.abs(gh[k])) for k in gh)
    agreement = max(float(jnp.abs(gh[k] - go[k])) for k in gh) / scale
    candidates = {"forward hand": (jax.jit(loss(hand)), (p,)),
                  "forward jaxdyn": (jax.jit(loss(ours)), (p,)),
                  "grad hand": (jax.jit(grad_hand), (p,)),
                  "grad jaxdyn": (jax.jit(grad_ours), (p,))}
    if adjoints:
        steps = int(jaxdyn.simulate(system.dynamics, jnp.full(system.n, 0.9), jnp.zeros(system.n),
                                    p, t1=t1, solver=SOLVER, rtol=TOL, atol=TOL).num_steps)
        for name, adjoint, transform in (
                ("checkpoint per step", diffrax.RecursiveCheckpointAdjoint(checkpoints=steps),
                 jax.grad),
                ("ForwardMode + jacfwd", diffrax.ForwardMode(), jax.jacfwd)):
            for label, solve in zip(("hand", "jaxdyn"), solvers(system, t1, adjoint, ts)):
                candidates[f"{name} {label}"] = (jax.jit(transform(loss(solve))), (p,))
    times = interleaved(candidates, number=2, rounds=5)
    compiles = (compile_seconds(grad_hand, p), compile_seconds(grad_ours, p))
    return times, compiles, agreement


def main():
    quick = "--quick" in sys.argv
    systems = [(DOUBLE_PENDULUM, 10.0, True), (ELASTIC_PENDULUM, 10.0, False)]
    if not quick:
        systems += [(chain(2), 10.0, False), (chain(5), 10.0, False), (chain(10), 10.0, True),
                    (chain(20), 2.0, False)]
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64, Tsit5 at {TOL}")
    print("\n-- whole trajectory (eager calls) and compile time of the solve --")
    for system, t1, _ in systems:
        times, compiles, difference = trajectories(system, t1)
        print(f"{system.name:17s} t1 = {t1:4.1f}: hand {1e3 * times['hand']:8.2f} ms  jaxdyn "
              f"{1e3 * times['jaxdyn']:8.2f} ms  ratio {times['jaxdyn'] / times['hand']:5.2f}× | "
              f"compile hand {compiles[0]:5.2f} s  jaxdyn {compiles[1]:5.2f} s | final states "
              f"differ by {difference:.1e}", flush=True)
    print("\n-- per call (a 1 ms solve of the double pendulum) --")
    calls = per_call(DOUBLE_PENDULUM)
    for name, seconds in calls.items():
        print(f"{name:16s} {1e6 * seconds:7.1f} µs")
    print(f"ratios: eager {calls['jaxdyn'] / calls['hand']:.2f}×, inside jit "
          f"{calls['jaxdyn, in jit'] / calls['hand, in jit']:.2f}×")
    print("\n-- gradients (×: cost over one forward solve of the same code) --")
    for system, t1, adjoints in systems:
        times, compiles, agreement = gradients(system, t1, adjoints and not quick or
                                               system is DOUBLE_PENDULUM)
        fh, fo = times["forward hand"], times["forward jaxdyn"]
        line = (f"{system.name:17s} grad hand {times['grad hand'] / fh:5.2f}×  jaxdyn "
                f"{times['grad jaxdyn'] / fo:5.2f}× ({1e3 * times['grad jaxdyn']:7.1f} ms, "
                f"{times['grad jaxdyn'] / times['grad hand']:4.2f}× hand's gradient)")
        for name in ("checkpoint per step", "ForwardMode + jacfwd"):
            if f"{name} jaxdyn" in times:
                line += (f" | {name}: hand {times[f'{name} hand'] / fh:5.2f}×, jaxdyn "
                         f"{times[f'{name} jaxdyn'] / fo:5.2f}×")
        print(line + f" | compile hand {compiles[0]:5.2f} s, jaxdyn {compiles[1]:5.2f} s | "
              f"gradients agree to {agreement:.1e}", flush=True)


if __name__ == "__main__":
    main()
