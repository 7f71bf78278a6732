"""Parameter identification: `jaxdyn.fit` with Levenberg–Marquardt (the default) against
Gauss–Newton, BFGS and Adam on the same problems, and what one derivative of the trajectory
loss costs next to one simulation.

Run: python benchmarks/bench_fit.py            (3–5 minutes on the shared 2-core machine)
     python benchmarks/bench_fit.py --quick    (the oscillator's fits and the derivative costs,
                                                about 2 minutes)
     options: --learning-rate (Adam's, 0.05), --adam-steps (3000), --sweep (Adam's steps to
     1e-3 at other learning rates too: 10–15 minutes more), --rounds (of the derivative
     timings, 9)

Problems (data from SciPy's `solve_ivp`, DOP853 at 1e-12, on equations written by hand, never
from jaxdyn; seeded Gaussian noise σ = 0.01, weights 1/σ²):

- damped oscillator m ẍ + c ẋ + k x = 0 (m = 1, k = 4, c = 0.3 known to be fitted: k and c
  from the guess k = 3, c = 0.5), x from x0 = 1 at rest, 201 samples over 10 s;
- double pendulum of point masses (m1 = 1, m2 = 0.8, l1 = 1, l2 = 0.7) driven at the first
  joint by the known torque 2 sin(1.5 t) (which fixes the mass scale): m1, m2, l1, l2 from the
  guess (1.3, 0.6, 0.8, 0.9), both angles from (0.5, −0.3) at rest, 101 samples over 5 s.

Every fit runs with `jaxdyn.fit`'s defaults otherwise (optimiser tolerances rtol = atol = 1e-8;
simulations with Tsit5 at rtol = atol = 1e-8, the fit's default `simulate_options`, passed
explicitly so that every figure here uses the same), `uncertainty=False`. Each fit is run twice:
the first call's time includes tracing and compilation, the second's is reported as the run
time; "time to 1e-3" is read off the second run (a callback stamps every step). "Steps to
1e-3" is the first step whose loss is within 1e-3 (relative) of the Levenberg–Marquardt
optimum's loss; the steps of a least-squares solver include rejected trial steps. Adam
(optax.adam) runs on the fit's latent variables, the logarithms of the positive parameters.

Derivative costs, on the double pendulum's trajectory with the fit's settings: one jitted
`jaxdyn.simulate`; `jax.grad` of ½ Σ w (q − y)² through it (diffrax's default
`RecursiveCheckpointAdjoint`: what an Adam or BFGS step needs); `jax.jacfwd` of the 202
residuals √w (q − y) with respect to the 4 parameters through `diffrax.ForwardMode()` (what a
Levenberg–Marquardt step needs). Medians of interleaved rounds (`_timing.py`).
"""

import argparse
import os
import sys
import time
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from scipy.integrate import solve_ivp

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
# The torque-driven double pendulum and its hand-derived equations, shared with the tests.
sys.path.insert(0, os.path.join(os.path.dirname(__file__), os.pardir, "tests"))
from _timing import compile_seconds, interleaved  # noqa: E402
from fit_systems import PENDULUM, PENDULUM_TRUTH, pendulum_data  # noqa: E402

SIGMA, TARGET = 0.01, 1e-3
SIMULATE = {"solver": diffrax.Tsit5(), "rtol": 1e-8, "atol": 1e-8}  # jaxdyn.fit's default

# -- the damped oscillator ------------------------------------------------------------------

OSCILLATOR_TRUTH = {"m": 1.0, "k": 4.0, "c": 0.3}
OSCILLATOR_GUESS = {"m": 1.0, "k": 3.0, "c": 0.5}
OSCILLATOR = jaxdyn.Lagrangian(kinetic=lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
                               potential=lambda q, p: 0.5 * p["k"] * q[0] ** 2,
                               dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)


def oscillator_problem():
    m, k, c = (OSCILLATOR_TRUTH[key] for key in ("m", "k", "c"))
    ts = np.linspace(0.0, 10.0, 201)
    x = solve_ivp(lambda t, y: [y[1], -(k * y[0] + c * y[1]) / m], (0.0, 10.0), [1.0, 0.0],
                  t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853").y[:1].T
    noisy = x + SIGMA * np.random.default_rng(0).standard_normal(x.shape)
    experiment = jaxdyn.Experiment(ts, noisy, q0=[1.0], u0=[0.0], weights=1 / SIGMA**2)
    return dict(name="damped oscillator", dynamics=OSCILLATOR, experiment=experiment,
                clean=x, truth=OSCILLATOR_TRUTH, guess=OSCILLATOR_GUESS,
                p_model=OSCILLATOR_TRUTH, filter_spec={"m": False, "k": True, "c": True})


# -- the double pendulum, driven at the first joint -----------------------------------------

PENDULUM_GUESS = {"m1": 1.3, "m2": 0.6, "l1": 0.8, "l2": 0.9}
TORQUE = {"A": 2.0, "w": 1.5}
PENDULUM_Q0 = (0.5, -0.3)


def pendulum_problem():
    ts = np.linspace(0.0, 5.0, 101)
    angles = pendulum_data(PENDULUM_Q0, ts, TORQUE["A"], TORQUE["w"])[:, :2]
    noisy = angles + SIGMA * np.random.default_rng(2).standard_normal(angles.shape)
    experiment = jaxdyn.Experiment(ts, noisy, q0=PENDULUM_Q0, u0=[0.0, 0.0], inputs=TORQUE,
                                   weights=1 / SIGMA**2)
    return dict(name="double pendulum", dynamics=PENDULUM, experiment=experiment, clean=angles,
                truth=PENDULUM_TRUTH, guess=PENDULUM_GUESS, p_model=(PENDULUM_TRUTH, TORQUE),
                filter_spec={key: True for key in PENDULUM_TRUTH})


def model_check(problem):
    """jaxdyn's model at the true parameters against SciPy's solution of the hand-written
    equations (the data before noise), with the fit's simulation settings."""
    e = problem["experiment"]
    p = jax.tree_util.tree_map(jnp.asarray, problem["p_model"])
    q = jaxdyn.simulate(problem["dynamics"], jnp.asarray(e.q0), jnp.asarray(e.u0), p,
                        t1=e.ts[-1], ts=jnp.asarray(e.ts), save="q", **SIMULATE).q
    return float(np.max(np.abs(np.asarray(q) - problem["clean"])))


# -- the fits -------------------------------------------------------------------------------


def optimisers(learning_rate, adam_steps):
    """name -> (optimiser for `jaxdyn.fit`, max_steps)."""
    return {
        "Levenberg–Marquardt": (None, 200),
        "Gauss–Newton": (optx.GaussNewton(rtol=1e-8, atol=1e-8), 200),
        "BFGS": (optx.BFGS(rtol=1e-8, atol=1e-8), 1000),
        f"Adam ({learning_rate:g})": (optax.adam(learning_rate), adam_steps),
    }


def run_fit(problem, optimiser, max_steps):
    """(result, seconds from the call to the end of every step), or the error."""
    stamps = []
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # max_steps reached: reported
        try:
            result = jaxdyn.fit(problem["dynamics"], problem["experiment"], problem["guess"],
                                filter_spec=problem["filter_spec"], optimiser=optimiser,
                                max_steps=max_steps, simulate_options=SIMULATE,
                                uncertainty=False,
                                callback=lambda *_: stamps.append(time.perf_counter()))
        except Exception as error:  # reported in the table
            return error, None, time.perf_counter() - start
    return result, np.asarray(stamps) - start, time.perf_counter() - start


def compare_optimisers(problem, candidates):
    print(f"\n-- {problem['name']}: model at the truth vs SciPy's data before noise: "
          f"{model_check(problem):.1e} --")
    rows, reference = [], None
    for name, (optimiser, max_steps) in candidates.items():
        jax.clear_caches()  # every first call compiles everything it needs
        first = run_fit(problem, optimiser, max_steps)
        if isinstance(first[0], Exception):
            rows.append((name, first, None))
            print(f"{name}: fails ({first[0]})", flush=True)
            continue
        second = run_fit(problem, optimiser, max_steps)
        rows.append((name, first, second))
        if reference is None:  # Levenberg–Marquardt, first in the list
            reference = second[0]
        print(f"{name}: done ({second[0].num_steps} steps, {second[2]:.2f} s)", flush=True)
    target = reference.loss * (1 + TARGET)
    truth = problem["truth"]
    keys = [k for k, trained in problem["filter_spec"].items() if trained]
    floor = 0.5 * problem["experiment"].observations.size
    print(f"\n{problem['name']}: optimum ½χ² = {reference.loss:.6g} (Levenberg–Marquardt; "
          f"noise floor ½N = {floor:g}); target ≤ {target:.6g}")
    print(f"{'optimiser':22s} {'steps to 1e-3':>13s} {'steps':>6s} {'stop':>9s} "
          f"{'1st call':>9s} {'run':>8s} {'per step':>9s} {'to 1e-3':>8s} {'final ½χ²':>11s} "
          f"{'max |Δp|/p truth':>16s} {'vs LM':>8s}")
    for name, first, second in rows:
        if second is None:
            print(f"{name:22s} fails at the first call: {first[0]}")
            continue
        result, stamps, seconds = second
        hit = np.nonzero(result.loss_history <= target)[0]
        steps_to, time_to = ((f"{hit[0] + 1}", f"{stamps[hit[0]]:7.2f}s") if hit.size
                             else ("—", "—"))
        error = max(abs(float(result.params[k]) - truth[k]) / truth[k] for k in keys)
        versus = max(abs(float(result.params[k]) - float(reference.params[k]))
                     / abs(float(reference.params[k])) for k in keys)
        stop = "converged" if result.converged else "max_steps"
        print(f"{name:22s} {steps_to:>13s} {result.num_steps:6d} {stop:>9s} "
              f"{first[2]:8.2f}s {seconds:7.2f}s {1e3 * seconds / result.num_steps:7.1f}ms "
              f"{time_to:>8s} {result.loss:11.6g} {error:16.2e} {versus:8.1e}")
    print("parameters: " + "; ".join(
        f"{name}: " + ", ".join(f"{k} = {float(second[0].params[k]):.6g}" for k in keys)
        for name, _, second in rows if second is not None))
    # What a diagonal scaling (Adam's) cannot undo: correlations, and the spread of the
    # singular values of the Jacobian with unit columns.
    report = jaxdyn.fit(problem["dynamics"], problem["experiment"], problem["guess"],
                        filter_spec=problem["filter_spec"], simulate_options=SIMULATE).uncertainty
    correlation = np.abs(report.correlation - np.eye(len(report.names)))
    i, j = np.unravel_index(np.argmax(correlation), correlation.shape)
    print(f"at the optimum: largest correlation {report.correlation[i, j]:+.3f} "
          f"({report.names[i]}, {report.names[j]}); column-scaled Jacobian's condition number "
          f"{1 / np.min(report.singular_values):.1f}")
    return rows, target


def learning_rates(problem, target, rates, max_steps):
    """Adam's steps to the target at other learning rates (each fit stopped there by its
    callback): that the comparison does not hinge on one learning rate."""
    print(f"{problem['name']}, Adam's steps to 1e-3 by learning rate:", end="", flush=True)
    for rate in rates:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            result = jaxdyn.fit(problem["dynamics"], problem["experiment"], problem["guess"],
                                filter_spec=problem["filter_spec"], optimiser=optax.adam(rate),
                                max_steps=max_steps, simulate_options=SIMULATE,
                                uncertainty=False,
                                callback=lambda step, params, loss: loss <= target)
        reached = result.loss_history[-1] <= target
        print(f"  {rate:g}: {result.num_steps if reached else f'> {max_steps}'}", end="",
              flush=True)
    print()


# -- the cost of one derivative -------------------------------------------------------------


def derivative_costs(problem, rounds):
    e = problem["experiment"]
    ts, y = jnp.asarray(e.ts), jnp.asarray(e.observations)
    q0, u0 = jnp.asarray(e.q0), jnp.asarray(e.u0)
    sqrt_w = jnp.asarray(np.sqrt(e.weights))
    params = {k: jnp.asarray(v) for k, v in problem["guess"].items()}
    inputs = {k: jnp.asarray(v) for k, v in TORQUE.items()}

    reverse = diffrax.RecursiveCheckpointAdjoint()  # simulate's default

    def angles(params, adjoint=reverse):
        return jaxdyn.simulate(PENDULUM, q0, u0, (params, inputs), t1=ts[-1], ts=ts, save="q",
                               adjoint=adjoint, throw=False, **SIMULATE).q

    def residuals(params, adjoint=reverse):
        return (sqrt_w * (angles(params, adjoint) - y)).ravel()

    def loss(params):
        return 0.5 * jnp.sum(residuals(params) ** 2)

    def jacobian(params):
        return jax.jacfwd(lambda p: residuals(p, diffrax.ForwardMode()))(params)

    forward, gradient, jac = jax.jit(angles), jax.jit(jax.grad(loss)), jax.jit(jacobian)
    # The two derivatives agree: Jᵀ r is the gradient of ½‖r‖².
    g, J, r = gradient(params), jac(params), jax.jit(residuals)(params)
    agreement = max(abs(float(J[k] @ r - g[k])) / abs(float(g[k])) for k in params)
    steps = int(jaxdyn.simulate(PENDULUM, q0, u0, (params, inputs), t1=ts[-1], ts=ts,
                                save="q", **SIMULATE).num_steps)
    times = interleaved({"forward": (forward, (params,)), "gradient": (gradient, (params,)),
                         "jacobian": (jac, (params,))}, number=3, rounds=rounds)
    compiles = {name: compile_seconds(fn, params)
                for name, fn in (("forward", angles), ("gradient", jax.grad(loss)),
                                 ("jacobian", jacobian))}
    return times, compiles, agreement, steps


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="the oscillator's fits only (and the derivative costs)")
    parser.add_argument("--learning-rate", type=float, default=0.05,
                        help="Adam's learning rate on the latent (log) parameters")
    parser.add_argument("--adam-steps", type=int, default=3000, help="Adam's max_steps")
    parser.add_argument("--rounds", type=int, default=9,
                        help="interleaved rounds for the derivative costs")
    parser.add_argument("--sweep", action="store_true",
                        help="also Adam's steps to 1e-3 at learning rates 0.01 … 0.5 (about 5 "
                             "more minutes)")
    args = parser.parse_args()
    print(f"jax {jax.__version__}, diffrax {diffrax.__version__}, optimistix "
          f"{optx.__version__}, optax {optax.__version__}, {jax.devices()[0].platform}, "
          f"float64, {os.cpu_count()} cores")
    problems = [oscillator_problem()] + ([] if args.quick else [pendulum_problem()])
    candidates = optimisers(args.learning_rate, args.adam_steps)
    for problem in problems:
        _, target = compare_optimisers(problem, candidates)
        if args.sweep:
            learning_rates(problem, target, (0.01, 0.02, 0.1, 0.2, 0.5), args.adam_steps)

    print("\n-- one derivative of the double pendulum's trajectory loss, against one simulation "
          "(Tsit5 at 1e-8, 101 save times, 4 parameters, at the guess) --")
    times, compiles, agreement, steps = derivative_costs(pendulum_problem(), args.rounds)
    forward = times["forward"]
    print(f"solver steps: {steps}; Jᵀr agrees with the gradient to {agreement:.1e} (relative)")
    for name, label in (("forward", "forward `simulate`"),
                        ("gradient", "jax.grad, RecursiveCheckpointAdjoint"),
                        ("jacobian", "jax.jacfwd, ForwardMode (202 × 4)")):
        print(f"{label:38s} {1e3 * times[name]:8.2f} ms  {times[name] / forward:6.2f}× forward "
              f"| compile {compiles[name]:5.2f} s")


if __name__ == "__main__":
    main()
