"""Work–precision: final-state error against run time for the solvers `jaxdyn.simulate` can use,
beside the same diffrax solvers on the fastest hand-written equations known (the floor) and
SciPy's `solve_ivp` (DOP853) on a NumPy right-hand side, over tolerances 1e-4 … 1e-12.

Run: python benchmarks/bench_work_precision.py      (about 5 minutes; writes
     benchmarks/work_precision.csv and benchmarks/work_precision.png)

Systems: a chaotic double pendulum (θ = (1.5, −1.0) from rest) and the elastic pendulum
(worked example 25.2), both over 10 s. The reference solution is jaxdyn with Dopri8 at
rtol = atol = 1e-13, cross-checked against SciPy's DOP853 at 1e-13 on the hand-written
equations; their difference (printed) bounds how far down the errors below mean anything.
Errors are max |q(t1) − q_ref(t1)|; times are medians of rounds after compilation, each call
a whole `simulate` (or `solve_ivp`) as a user makes it: `simulate` not jitted, with `save="q"`.
The floor ("diffrax, by hand") is `jax.jit(diffrax.diffeqsolve)` with the same solver,
tolerances, PID controller and final-state saving on the closed form with y = [q; q̇]: the
double pendulum's with s = sin(θ₁ − θ₂), c = cos(θ₁ − θ₂), den = m₁ + m₂ s²
(`_systems.double_pendulum_fastest`), the elastic pendulum's textbook form.
"""

import csv
import os
import sys
import time

import diffrax
import jax
import numpy as np
import scipy.integrate

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import (  # noqa: E402
    DOUBLE_PENDULUM,
    ELASTIC_PENDULUM,
    as_arrays,
    double_pendulum_fastest,
    elastic_hand,
)
from bench_batch import numpy_rhs as double_pendulum_rhs  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
T1 = 10.0
TOLERANCES = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
SOLVERS = {"Tsit5": diffrax.Tsit5(), "Dopri5": diffrax.Dopri5(), "Dopri8": diffrax.Dopri8()}


def elastic_rhs(p):
    m, g, k, l0 = (p[key] for key in ("m", "g", "k", "l0"))

    def rhs(t, y):
        r, theta, r_dot, theta_dot = y
        return [r_dot, theta_dot, r * theta_dot**2 + g * np.cos(theta) - k / m * (r - l0),
                -(2 * r_dot * theta_dot + g * np.sin(theta)) / r]

    return rhs


CASES = [
    ("double pendulum (chaotic)", DOUBLE_PENDULUM, np.array([1.5, -1.0]), double_pendulum_rhs,
     double_pendulum_fastest),
    ("elastic pendulum", ELASTIC_PENDULUM, np.array([1.5, 0.8]), elastic_rhs, elastic_hand),
]


def floor_solve(hand, n, solver, tol):
    """jax.jit of diffeqsolve on the hand-written equations, y = [q; q̇], final state saved."""
    def field(t, y, p):
        return jax.numpy.concatenate([y[n:], hand(t, y[:n], y[n:], p)])

    @jax.jit
    def solve(y0, p):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(field), solver, 0.0, T1, None, y0, args=p,
            saveat=diffrax.SaveAt(t1=True), max_steps=10**6,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol))
    return solve


def median_seconds(fn, rounds=5):
    fn()  # compile (and warm up)
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def study(name, system, q0, rhs_factory, hand):
    p = as_arrays(system.params)
    u0 = np.zeros_like(q0)
    rhs = rhs_factory(system.params)
    reference = np.asarray(jaxdyn.simulate(system.dynamics, q0, u0, p, t1=T1, rtol=1e-13,
                                           atol=1e-13, max_steps=10**6).q[-1])
    scipy_reference = scipy.integrate.solve_ivp(rhs, (0, T1), [*q0, *u0], method="DOP853",
                                                rtol=1e-13, atol=1e-13).y[:2, -1]
    spread = float(np.max(np.abs(reference - scipy_reference)))
    print(f"\n{name}: reference Dopri8 1e-13 vs SciPy DOP853 1e-13 differ by {spread:.1e}")
    print(f"{'solver':24s} {'tol':>7s} {'error':>9s} {'steps*':>7s} {'ms':>8s}"
          "   (*for SciPy: right-hand-side evaluations)")
    rows = []
    for solver_name, solver in SOLVERS.items():
        for tol in TOLERANCES:
            def run(solver=solver, tol=tol):
                return jaxdyn.simulate(system.dynamics, q0, u0, p, t1=T1, solver=solver,
                                       rtol=tol, atol=tol, max_steps=10**6, save="q")
            solution = run()
            seconds = median_seconds(run)
            error = float(np.max(np.abs(np.asarray(solution.q[-1]) - reference)))
            rows.append((name, f"jaxdyn {solver_name}", tol, error, int(solution.num_steps),
                         seconds))
            floor = floor_solve(hand, len(q0), solver, tol)
            y0 = jax.numpy.asarray(np.concatenate([q0, u0]))
            by_hand = floor(y0, p)
            seconds = median_seconds(lambda floor=floor, y0=y0: floor(y0, p).ys)
            error = float(np.max(np.abs(np.asarray(by_hand.ys[-1, :len(q0)]) - reference)))
            rows.append((name, f"diffrax {solver_name}, by hand", tol, error,
                         int(by_hand.stats["num_steps"]), seconds))
    for tol in TOLERANCES:
        def run_scipy(tol=tol):
            return scipy.integrate.solve_ivp(rhs, (0, T1), [*q0, *u0], method="DOP853",
                                             rtol=tol, atol=tol)
        solution = run_scipy()
        seconds = median_seconds(lambda: run_scipy().y)
        error = float(np.max(np.abs(solution.y[:2, -1] - reference)))
        rows.append((name, "SciPy DOP853", tol, error, int(solution.nfev), seconds))
    for _, solver_name, tol, error, steps, seconds in rows:
        print(f"{solver_name:24s} {tol:7.0e} {error:9.2e} {steps:7d} {1e3 * seconds:8.2f}")
    return rows, spread


def main():
    all_rows = []
    spreads = {}
    for case in CASES:
        rows, spread = study(*case)
        all_rows += rows
        spreads[case[0]] = spread
    with open(os.path.join(HERE, "work_precision.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["system", "solver", "tolerance", "error", "steps_or_nfev", "seconds"])
        writer.writerows(all_rows)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    fig, axes = plt.subplots(1, len(CASES), figsize=(12, 4.5))
    for ax, (name, *_rest) in zip(axes, CASES):
        for solver in sorted({r[1] for r in all_rows}):
            rows = [r for r in all_rows if r[0] == name and r[1] == solver]
            by_hand = solver.startswith("diffrax")
            color = ({"Tsit5": "C0", "Dopri5": "C1", "Dopri8": "C2"}.get(
                solver.split()[1].rstrip(","), "C3"))
            ax.loglog([r[5] * 1e3 for r in rows], [max(r[3], 1e-16) for r in rows],
                      "x--" if by_hand else "o-", color=color, label=solver)
        ax.axhline(max(spreads[name], 1e-16), color="grey", ls=":", label="reference spread")
        ax.set_xlabel("run time per solve (ms)")
        ax.set_ylabel("final-state error")
        ax.set_title(f"{name}, {T1:.0f} s")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "work_precision.png"), dpi=120)
    print("wrote benchmarks/work_precision.csv and benchmarks/work_precision.png")


if __name__ == "__main__":
    main()
