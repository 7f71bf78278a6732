"""Cost of one evaluation of the equations of motion, against the same equations written by
hand, derived with sympy, and formed by the naive Lagrangian-neural-network recipe.

Run: python benchmarks/bench_equations.py            (all systems, about 10 minutes)
     python benchmarks/bench_equations.py --quick    (double and elastic pendulum only)
     ... --record                                    (write benchmarks/results/equations.csv)

Systems (benchmarks/_systems.py): double pendulum, elastic pendulum (worked example 25.2), and
an N-link chain of rods for N = 2, 5, 10, 20, each a `jaxdyn.Lagrangian` from the T and V a
user writes. Every candidate is checked against the hand-written equations before timing.
Figures are seconds per evaluation, medians of interleaved rounds (`_timing.py`):

- loop: inside one compiled `fori_loop` (what a solver pays: no dispatch, a new state each
  iteration). "rhs" is `accelerations(..., throw=False)`, what `simulate` integrates (no
  checks, NaN where the equations fail); "accel." is `accelerations` with its default check,
  a branch that raises an error naming the state.
- vmap: one jitted call on a batch of 1024 states.
- call: one jitted call on one state (the per-call overhead included).
- M, f: `mass_matrix_and_forcing` inside the loop, against M and f written by hand.
- sympy: KanesMethod, lambdified to jax.numpy, `jnp.linalg.solve` (derivation time apart).
- LNN: full Hessians of L by `jax.hessian`/`jax.jacobian` and a pseudo-inverse, the recipe of
  Lagrangian neural networks (Cranmer et al., 2020).
"""

import os
import sys

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(__file__))
import _sympy_systems  # noqa: E402
from _systems import (  # noqa: E402
    DOUBLE_PENDULUM,
    ELASTIC_PENDULUM,
    as_arrays,
    chain,
    check_agreement,
    states,
)
from _results import Recorder  # noqa: E402
from _timing import compile_seconds, in_loop, interleaved  # noqa: E402

SYMPY = {"double pendulum": _sympy_systems.double_pendulum,
         "elastic pendulum": _sympy_systems.elastic_pendulum}


def lnn_recipe(system):
    """q̈ = (∂²L/∂q̇²)⁺ (∂L/∂q − (∂²L/∂q̇∂q) q̇) with every Hessian materialised."""
    lagrangian = system.dynamics.lagrangian

    def accelerations(t, q, qd, p):
        hessian = jax.hessian(lagrangian, argnums=2)(t, q, qd, p)
        mixed = jax.jacobian(jax.grad(lagrangian, argnums=2), argnums=1)(t, q, qd, p)
        gradient = jax.grad(lagrangian, argnums=1)(t, q, qd, p)
        return jnp.linalg.pinv(hessian) @ (gradient - mixed @ qd)

    return accelerations


def equations_as_vector(equations):
    """(M, f) as one vector f − M q̇ (the same extra work on both sides), for the loop. The
    product is written element-wise so that it fuses instead of calling a matrix kernel."""
    def vector(t, q, qd, p):
        mass_matrix, forcing = equations(t, q, qd, p)
        return forcing - jnp.sum(mass_matrix * qd[None, :], axis=1)

    return vector


def measure(system, sympy_model):
    p = as_arrays(system.params)
    t = jnp.asarray(0.0)
    qs, qds = states(system, 1024)
    q, qd = qs[0], qds[0]
    dynamics = system.dynamics
    check_agreement(system)
    sympy_accelerations, derivation = sympy_model()
    reference = system.hand_written(t, q, qd, p)
    for name, fn in (("sympy", sympy_accelerations), ("LNN", lnn_recipe(system))):
        error = float(jnp.max(jnp.abs(fn(t, q, qd, p) - reference)) / jnp.max(jnp.abs(reference)))
        assert error < 1e-8, (name, error)

    def unchecked(t, q, qd, p):
        return dynamics.accelerations(t, q, qd, p, throw=False)

    candidates = {"hand": system.hand_written, "rhs": unchecked,
                  "accelerations": dynamics.accelerations,
                  "sympy": sympy_accelerations, "LNN": lnn_recipe(system)}
    iterations = 20000 if system.n <= 5 else 2000
    args = (t, q, qd, p)
    loop = interleaved({k: (in_loop(fn, iterations), args) for k, fn in candidates.items()},
                       number=1)
    loop = {k: v / iterations for k, v in loop.items()}
    equations = interleaved({k: (in_loop(equations_as_vector(fn), iterations), args) for k, fn in
                             (("hand", system.hand_equations),
                              ("jaxdyn", dynamics.mass_matrix_and_forcing))}, number=1)
    equations = {k: v / iterations for k, v in equations.items()}
    batch = (t, qs, qds, p)
    vmapped = interleaved({k: (jax.jit(jax.vmap(candidates[k], in_axes=(None, 0, 0, None))), batch)
                           for k in ("hand", "rhs", "accelerations", "sympy", "LNN")}, number=20)
    call = interleaved({k: (jax.jit(candidates[k]), args) for k in ("hand", "rhs",
                                                                    "accelerations")},
                       number=2000)
    compiles = {k: compile_seconds(candidates[k], *args) for k in ("hand", "accelerations")}
    return dict(loop=loop, equations=equations, vmapped=vmapped, call=call, compiles=compiles,
                derivation=derivation)


def main():
    quick = "--quick" in sys.argv
    recorder = Recorder("equations")
    systems = [(DOUBLE_PENDULUM, SYMPY["double pendulum"]),
               (ELASTIC_PENDULUM, SYMPY["elastic pendulum"])]
    if not quick:
        for n in (2, 5, 10, 20):
            systems.append((chain(n), lambda n=n: _sympy_systems.chain(n)))
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64; ratios = jaxdyn / hand")
    header = (f"{'system':17s} {'loop: hand':>11s} {'rhs':>7s} {'accel.':>7s} {'sympy':>7s} "
              f"{'LNN':>7s} | {'M,f':>6s} | {'vmap: hand':>11s} {'rhs':>7s} {'accel.':>7s} "
              f"{'sympy':>7s} {'LNN':>7s} | {'call: hand':>11s} {'rhs':>7s} {'accel.':>7s}")
    print(header)
    rows = []
    for system, sympy_model in systems:
        r = measure(system, sympy_model)
        rows.append((system, r))
        loop, vm, call = r["loop"], r["vmapped"], r["call"]
        ratio = lambda d, k: d[k] / d["hand"]  # noqa: E731
        print(f"{system.name:17s} {_time(loop['hand']):>11s} {ratio(loop, 'rhs'):6.2f}× "
              f"{ratio(loop, 'accelerations'):6.2f}× {ratio(loop, 'sympy'):6.2f}× "
              f"{ratio(loop, 'LNN'):6.2f}× | {ratio(r['equations'], 'jaxdyn'):5.2f}× | "
              f"{_time(vm['hand']):>11s} {ratio(vm, 'rhs'):6.2f}× "
              f"{ratio(vm, 'accelerations'):6.2f}× "
              f"{ratio(vm, 'sympy'):6.2f}× {ratio(vm, 'LNN'):6.2f}× | "
              f"{_time(call['hand']):>11s} {ratio(call, 'rhs'):6.2f}× "
              f"{ratio(call, 'accelerations'):6.2f}×", flush=True)
        for label, d, key in (
                ("in a compiled loop: accelerations(throw=False) / hand-written", loop, "rhs"),
                ("in a compiled loop: accelerations (default) / hand-written", loop,
                 "accelerations"),
                ("in a compiled loop: sympy (KanesMethod) / hand-written", loop, "sympy"),
                ("in a compiled loop: the LNN recipe / hand-written", loop, "LNN"),
                ("vmap of 1024: accelerations(throw=False) / hand-written", vm, "rhs"),
                ("one jitted call: accelerations(throw=False) / hand-written", call, "rhs")):
            recorder.add(label, system.name, ratio(d, key))
        recorder.add("in a compiled loop: mass_matrix_and_forcing / M, f by hand",
                     system.name, ratio(r["equations"], "jaxdyn"))
    print("\ncompile (first call of a fresh jax.jit of one evaluation) and sympy derivation:")
    for system, r in rows:
        c = r["compiles"]
        print(f"{system.name:17s} hand {c['hand']:6.2f} s   jaxdyn accelerations "
              f"{c['accelerations']:6.2f} s   sympy derivation + lambdify {r['derivation']:6.2f} s")
        recorder.add("compile: accelerations / hand-written (a fresh jax.jit)", system.name,
                     c["accelerations"] / c["hand"])
    if "--record" in sys.argv:
        recorder.write()


def _time(seconds):
    for unit, scale in (("s", 1), ("ms", 1e-3), ("µs", 1e-6), ("ns", 1e-9)):
        if seconds >= scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds / 1e-9:.3g} ns"


if __name__ == "__main__":
    main()
