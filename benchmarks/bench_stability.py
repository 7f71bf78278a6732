"""Numerical stability: long-horizon energy error against run time for every stepper, and
work–precision on a stiff system (explicit against implicit solvers).

Run: python benchmarks/bench_stability.py            (about 6 minutes on 2 cores; writes
     benchmarks/stability.csv and benchmarks/stability.png)
     python benchmarks/bench_stability.py --quick    (shorter horizons, a smoke test)
     python benchmarks/bench_stability.py --million  (10⁶ steps of h = 0.01 per stepper)

1. Long horizons. The double pendulum (θ = (1, 0.5) from rest, chaotic) over T = 1000 s and
   the symmetric heavy top in Euler angles over 200 s: for each stepper, the largest energy
   error |E − E₀| over the run relative to the energy scale, and its growth (the largest error
   over the last tenth of the run over that of the first tenth: ≈ 1 for a bounded error, ≈ 10
   or more for a secular drift), against the run time of one `simulate` call (median of
   interleaved rounds after compilation). Steppers: the variational integrator (midpoint and
   trapezoidal, fixed steps), Heun's method (explicit Runge–Kutta of the same order and step),
   Tsit5 and Dopri8 with error control at several tolerances.
2. Stiffness. A pendulum hung from a stiff, heavily damped spring (polar coordinates; spring k,
   damper c): with k = 10⁸, c = 10⁵ the stiffness ratio is 3 × 10⁴ (explicit solvers still
   finish); with k = 10¹², c = 10⁷ it is 4 × 10⁶ (only implicit ones do; the explicit
   solvers' step estimate comes from the max_steps error). Error: the swing angle over 5 s
   against a Kvaerno5 solve at rtol = atol = 1e-10 (ratio 3 × 10⁴), and against the rigid
   pendulum (ratio 4 × 10⁶, where the stretch g/k = 10⁻¹¹ is below every error and an
   implicit solve below 1e-8 runs into the rounding floor of its step, near ε h ‖J‖).
"""

import argparse
import csv
import os
import re
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _systems import DOUBLE_PENDULUM  # noqa: E402
from _timing import interleaved  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
G = 9.81

TOP = jaxdyn.Lagrangian(
    lambda q, qd, p: (0.5 * p["I1"] * (qd[1] ** 2 + qd[0] ** 2 * jnp.sin(q[1]) ** 2)
                      + 0.5 * p["I3"] * (qd[2] + qd[0] * jnp.cos(q[1])) ** 2),
    lambda q, p: p["mgl"] * jnp.cos(q[1]))
TOP_P = {"I1": 1.0, "I3": 0.5, "mgl": 1.0}

SPRING_PENDULUM = jaxdyn.Lagrangian(
    lambda q, qd, p: 0.5 * p["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2),
    lambda q, p: 0.5 * p["k"] * (q[0] - p["l"]) ** 2 - p["m"] * G * q[0] * jnp.cos(q[1]),
    dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)


def long_horizon_cases(quick, million):
    p = {k: jnp.asarray(v) for k, v in DOUBLE_PENDULUM.params.items()}
    if million:
        return [("double pendulum", DOUBLE_PENDULUM.dynamics, p, jnp.array([1.0, 0.5]),
                 jnp.zeros(2), 10_000.0)]
    scale = 0.1 if quick else 1.0
    return [
        ("double pendulum", DOUBLE_PENDULUM.dynamics, p, jnp.array([1.0, 0.5]), jnp.zeros(2),
         1000.0 * scale),
        ("heavy top", TOP, TOP_P, jnp.array([0.0, 0.5, 0.0]), jnp.array([0.3, 0.0, 8.0]),
         200.0 * scale),
    ]


def steppers(h, million):
    """(label, simulate keywords); h is the fixed step."""
    fixed = [
        (f"variational midpoint h={h:g}", dict(solver=jaxdyn.VariationalIntegrator(),
                                               dt0=h)),
        (f"variational midpoint h={h / 2:g}", dict(solver=jaxdyn.VariationalIntegrator(),
                                                   dt0=h / 2)),
        (f"variational trapezoidal h={h:g}", dict(
            solver=jaxdyn.VariationalIntegrator(rule="trapezoidal"), dt0=h)),
        (f"Heun h={h:g}", dict(solver=diffrax.Heun(), dt0=h,
                               stepsize_controller=diffrax.ConstantStepSize())),
    ]
    adaptive = [(f"Tsit5 rtol={tol:g}", dict(solver=diffrax.Tsit5(), rtol=tol, atol=tol,
                                              max_steps=2_000_000))
                for tol in (1e-4, 1e-6, 1e-8)]
    adaptive += [(f"Dopri8 rtol={tol:g}", dict(solver=diffrax.Dopri8(), rtol=tol, atol=tol,
                                               max_steps=2_000_000))
                 for tol in (1e-8, 1e-10)]
    if million:
        return fixed[:1] + fixed[3:] + adaptive[:2]
    return fixed + adaptive


def run_long_horizons(args, rows):
    curves = {}
    for name, system, p, q0, u0, t1 in long_horizon_cases(args.quick, args.million):
        h = 0.01
        ts = jnp.linspace(0.0, t1, 2001)
        e0 = float(system.energy(0.0, q0, u0, p))
        scale = abs(e0) + float(system.kinetic_energy(0.0, q0, u0, p)) + 1.0
        print(f"\n{name}: T = {t1:g} s, E0 = {e0:.6g}")
        print(f"{'stepper':<34}{'steps':>10}{'run time':>12}{'max |ΔE|/E':>14}{'growth':>9}")
        candidates, outputs = {}, {}
        for label, options in steppers(h, args.million):
            run = jax.jit(lambda q0, u0, p, options=options: jaxdyn.simulate(
                system, q0, u0, p, t1=t1, ts=ts, **options))
            candidates[label] = (run, (q0, u0, p))
            outputs[label] = run(q0, u0, p)
        times = interleaved(candidates, number=1, rounds=1 if args.million else 3)
        for label, sol in outputs.items():
            error = np.abs(np.asarray(system.energy(sol.ts, sol.q, sol.u, p)) - e0) / scale
            tenth = len(error) // 10
            growth = error[-tenth:].max() / max(error[1:tenth + 1].max(), 1e-300)
            print(f"{label:<34}{int(sol.num_steps):>10}{times[label] * 1e3:>10.0f}ms"
                  f"{error.max():>14.2e}{growth:>9.1f}")
            rows.append(dict(case=f"long: {name}", method=label, steps=int(sol.num_steps),
                             seconds=times[label], error=error.max(), growth=growth))
            curves[(name, label)] = (np.asarray(sol.ts), error)
    return curves


def run_stiff(args, rows):
    q_start = 1.0
    cases = [("ratio 3e4", {"m": 1.0, "k": 1e8, "c": 1e5, "l": 1.0}),
             ("ratio 4e6", {"m": 1.0, "k": 1e12, "c": 1e7, "l": 1.0})]
    t1 = 1.0 if args.quick else 5.0
    ts = jnp.linspace(0.0, t1, 11)
    points = {}
    for name, p in cases:
        p = {k: jnp.asarray(v) for k, v in p.items()}
        q0 = jnp.array([1.0 + G * np.cos(q_start) / float(p["k"]), q_start])
        u0 = jnp.zeros(2)
        report = jaxdyn.stiffness(SPRING_PENDULUM, 0.0, q0, u0, p)
        if float(p["k"]) < 1e10:
            reference = jaxdyn.simulate(SPRING_PENDULUM, q0, u0, p, t1=t1, ts=ts,
                                        solver=diffrax.Kvaerno5(), rtol=1e-10, atol=1e-10,
                                        max_steps=2_000_000).q[:, 1]
        else:  # the rigid pendulum: the spring's stretch g/k = 10⁻¹¹ is below every error
            rigid = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * qd[0] ** 2,
                                      lambda q, p: -G * jnp.cos(q[0]))
            reference = jaxdyn.simulate(rigid, q0[1:], u0[1:], t1=t1, ts=ts, rtol=1e-13,
                                        atol=1e-13).q[:, 0]
        print(f"\nstiff spring pendulum, {name}: jaxdyn.stiffness ratio {report.ratio:.3g}, "
              f"recommends {type(report.solver).__name__}")
        print(f"{'solver':<12}{'rtol':>8}{'steps':>12}{'run time':>12}{'error':>11}")
        for solver in (diffrax.Tsit5(), diffrax.Dopri8(), diffrax.Kvaerno3(),
                       diffrax.Kvaerno5()):
            label = type(solver).__name__
            for tol in (1e-4, 1e-6, 1e-8):
                run = jax.jit(lambda q0, u0, p, solver=solver, tol=tol: jaxdyn.simulate(
                    SPRING_PENDULUM, q0, u0, p, t1=t1, ts=ts, solver=solver, rtol=tol,
                    atol=tol, max_steps=400_000))
                try:
                    sol = run(q0, u0, p)
                except Exception as e:  # noqa: BLE001 (the explicit solvers run out of steps)
                    needed = re.search(r"needs \(estimate\) = (\S+?),", str(e))
                    estimate = needed.group(1) if needed else "?"
                    print(f"{label:<12}{tol:>8.0e}   out of 400 000 steps; needs ~{estimate}")
                    rows.append(dict(case=f"stiff: {name}", method=f"{label} rtol={tol:g}",
                                     steps=float(estimate) if needed else np.nan,
                                     seconds=np.nan, error=np.nan, growth=np.nan))
                    continue
                seconds = interleaved({label: (run, (q0, u0, p))}, number=1, rounds=3)[label]
                error = float(jnp.max(jnp.abs(sol.q[:, 1] - reference)))
                print(f"{label:<12}{tol:>8.0e}{int(sol.num_steps):>12}"
                      f"{seconds * 1e3:>10.0f}ms{error:>11.2e}")
                rows.append(dict(case=f"stiff: {name}", method=f"{label} rtol={tol:g}",
                                 steps=int(sol.num_steps), seconds=seconds, error=error,
                                 growth=np.nan))
                points.setdefault((name, label), []).append((seconds, error))
    return points


def plot(curves, points, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    systems = sorted({name for name, _ in curves})
    fig, axes = plt.subplots(1, len(systems) + 1, figsize=(5.5 * (len(systems) + 1), 4.2))
    for ax, system in zip(axes, systems):
        for (name, label), (ts, error) in curves.items():
            if name == system and ("h=" in label or "rtol=1e-06" in label
                                   or "rtol=1e-08" in label):
                ax.loglog(ts[1:], np.maximum(error[1:], 1e-17), label=label, lw=0.8)
        ax.set(title=f"{system}: energy error", xlabel="t (s)", ylabel="|E − E₀| / scale")
        ax.legend(fontsize=6)
    ax = axes[-1]
    for (name, label), values in points.items():
        seconds, errors = zip(*values)
        ax.loglog(seconds, errors, "o-" if "Kvaerno" in label else "s--",
                  label=f"{label} ({name})")
    ax.set(title="stiff spring pendulum: work–precision", xlabel="run time (s)",
           ylabel="max |θ − θ_ref|")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--million", action="store_true")
    args = parser.parse_args()
    rows = []
    curves = run_long_horizons(args, rows)
    if args.million:
        return
    points = run_stiff(args, rows)
    if args.quick:
        return
    with open(os.path.join(HERE, "stability.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(curves, points, os.path.join(HERE, "stability.png"))
    print("\nwrote benchmarks/stability.csv and benchmarks/stability.png")


if __name__ == "__main__":
    main()
