"""How often `jaxdyn.fit` reaches the global optimum from starting points far from the truth,
with and without globalisation, and how long it takes.

Run: python benchmarks/bench_globalisation.py              (about 5 minutes on two cores)
     python benchmarks/bench_globalisation.py --starts 100 (the issue's 100 starting points)
     python benchmarks/bench_globalisation.py --problem double-pendulum --starts 100
     ... --record                                (write results/globalisation_<problem>.csv)

Problem: the elastic pendulum (polar coordinates r, θ; m = 0.9, g = 9.81 known; k = 35 and
l₀ = 1.2 fitted, with both experiments' initial states), two experiments of 4 s from rest at
(r, θ) = (1.3, 0.5) and (1.0, −0.8), 201 samples each, only the bob's horizontal position
r sin θ observed, data from SciPy's `solve_ivp` (DOP853 at 1e-12) on the hand-written
equations with Gaussian noise σ = 1e-3 (unweighted). Starting points: k and l₀ each a
log-uniform factor in [0.5, 2] of the truth (seeded), the initial states at their true values
(and fitted).

Strategies: `globalisation=False` (one Levenberg–Marquardt fit from the guess), the default
(that fit, then horizon continuation when it ended trapped where the data are not explained),
`jaxdyn.HorizonContinuation()` from the start, and `jaxdyn.MultiStart(8)` (the guess and seven
points at 0.5–2× it, fitted at once); and multiple shooting in 10 segments (the state is not
observed, so the nodes start on a simulation: at the guess, or with continuation at the
short horizons' optimum) directly, by default and with continuation. A fit succeeds when k and
l₀ are within 1 % of the truth (the noise allows ~0.1 %). "Honest" counts the failures that report
`explains_data=False`.

`--problem double-pendulum`: the torque-driven double pendulum of `bench_fit.py` (both angles
observed with σ = 0.01, 101 samples over 5 s, data from SciPy): m1, m2, l1, l2 each from a
log-uniform factor in [0.5, 2] of the truth; success: all four within 1 % (their standard
errors are 0.1–0.5 %); the first three strategies (`MultiStart(8)` takes 15 s per fit
here, 92 s where its starts crawl to `max_steps`: 4 starting points measured, all found).
Times are wall times per fit after the first one; "first s" is the first fit of each strategy,
in the order of the table in one process (its compilation, less what the strategies before it
compiled: a continuation's stages keep the records' shapes and share the whole fit's compiled
program).
"""

import argparse
import os
import statistics
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _results import Recorder  # noqa: E402
from _systems import ELASTIC_PARAMS, elastic_T, elastic_V  # noqa: E402
from bench_work_precision import elastic_rhs  # noqa: E402

TRUTH = ELASTIC_PARAMS
TRAINED = {"m": False, "g": False, "k": True, "l0": True}
SIGMA = 1e-3


def observe(t, q, u, p):
    return q[:1] * jnp.sin(q[1:])


def experiments():
    rhs = elastic_rhs(TRUTH)
    rng = np.random.default_rng(5)
    out = []
    for q0 in ([1.3, 0.5], [1.0, -0.8]):
        ts = np.linspace(0.0, 4.0, 201)
        y = solve_ivp(rhs, (0.0, 4.0), [*q0, 0.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12,
                      method="DOP853").y
        x = y[0] * np.sin(y[1]) + SIGMA * rng.standard_normal(ts.size)
        out.append(jaxdyn.Experiment(ts, x[:, None], q0=q0, u0=[0.0, 0.0]))
    return out


SHOOTING = jaxdyn.MultipleShooting(10)
STRATEGIES = {  # name: (globalisation, shooting)
    "direct (globalisation=False)": (False, None),
    "default (continuation if trapped)": (None, None),
    "HorizonContinuation() from the start": (jaxdyn.HorizonContinuation(), None),
    "MultiStart(8) around the guess": (jaxdyn.MultiStart(8), None),
    "MultipleShooting(10), direct": (False, SHOOTING),
    "MultipleShooting(10), default": (None, SHOOTING),
    "MultipleShooting(10), HorizonContinuation()": (jaxdyn.HorizonContinuation(), SHOOTING)}


def elastic_problem():
    return dict(system=jaxdyn.Lagrangian(elastic_T, elastic_V), data=experiments(),
                truth=TRUTH, trained=TRAINED, strategies=STRATEGIES,
                options=dict(observe=observe, fit_initial_states=True))


def pendulum_problem():
    """The torque-driven double pendulum of `bench_fit.py` (both angles observed, σ = 0.01,
    101 samples over 5 s): m1, m2, l1, l2 fitted."""
    from bench_fit import pendulum_problem as problem

    problem = problem()
    return dict(system=problem["dynamics"], data=[problem["experiment"]],
                truth=problem["truth"], trained={key: True for key in problem["truth"]},
                strategies={name: STRATEGIES[name] for name in list(STRATEGIES)[:3]},
                options={})


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--starts", type=int, default=40)
    parser.add_argument("--problem", choices=("elastic", "double-pendulum"), default="elastic")
    parser.add_argument("--record", action="store_true",
                        help="write benchmarks/results/globalisation_<problem>.csv")
    args = parser.parse_args()
    recorder = Recorder(f"globalisation_{args.problem.replace('-', '_')}")
    problem = (elastic_problem if args.problem == "elastic" else pendulum_problem)()
    system, data, truth = problem["system"], problem["data"], problem["truth"]
    fitted = [key for key, trained in problem["trained"].items() if trained]
    factors = np.exp(np.random.default_rng(0).uniform(np.log(0.5), np.log(2.0),
                                                      (args.starts, len(fitted))))

    def run(point, globalisation, shooting):
        guess = {**truth, **{key: f * truth[key] for key, f in zip(fitted, point)}}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return jaxdyn.fit(system, data, guess, filter_spec=problem["trained"],
                              uncertainty=False, progress=False, globalisation=globalisation,
                              shooting=shooting, **problem["options"])

    print(f"{args.problem}: {args.starts} starting points, {', '.join(fitted)} each at "
          "0.5–2x the truth")
    print(f"{'strategy':44s} {'success':>8s} {'honest':>7s} {'median s':>9s} {'max s':>7s} "
          f"{'first s':>8s}")
    for name, (globalisation, shooting) in problem["strategies"].items():
        successes, honest, times = 0, 0, []
        start = time.perf_counter()
        run(factors[0], globalisation, shooting)  # compile
        first = time.perf_counter() - start
        for point in factors:
            start = time.perf_counter()
            result = run(point, globalisation, shooting)
            times.append(time.perf_counter() - start)
            found = all(abs(float(result.params[key]) / truth[key] - 1) < 1e-2
                        for key in fitted)
            successes += found
            honest += (not found) and result.explains_data is False
        failures = args.starts - successes
        print(f"{name:44s} {successes / args.starts:8.0%} {honest:>3d}/{failures:<3d} "
              f"{statistics.median(times):9.2f} {max(times):7.2f} {first:8.2f}", flush=True)
        recorder.add(f"{name}: starts that reach the truth (of {args.starts})", "",
                     100 * successes / args.starts, "%")
        if failures:  # (none to report where every start reached the truth)
            recorder.add(f"{name}: failures that report themselves (data not explained)", "",
                         100 * honest / failures, "%")
        recorder.add(f"{name}: median seconds a fit", "", statistics.median(times), "s")
    if args.record:
        recorder.write()


if __name__ == "__main__":
    main()
