"""Explicit Runge–Kutta steps with their stages written out.

diffrax runs the stages of a Runge–Kutta step as a loop (one iteration per stage, the tableau
row picked by index). XLA writes such a loop out when its body is small: the hand-written
equations of a double or elastic pendulum are small enough, equations formed by autodiff
usually are not, and a loop iteration costs about as much as the equations of a small system
(a Tsit5 step of the elastic pendulum: 0.6 µs written out, 1.2 µs as a loop run stage by
stage). Writing the stages out in Python gives every system the straight-line step, with the
same arithmetic: the same stages, tableau, error estimate and dense output as the wrapped
diffrax solver.
`simulate` uses it only where XLA runs the loop stage by stage: on the CPU with `import
jaxdyn`'s small-loop switch in effect, XLA compiles diffrax's whole loop, stages included, as
one function, which runs 10–15 % slower and compiles in half the time
(`jaxdyn._integrate.simulate.LOOPS_RUN_WHOLE`).

Reference: J. C. Butcher, Numerical Methods for Ordinary Differential Equations (2016), §23.
"""

from typing import cast

import diffrax
import jax
import jax.numpy as jnp

from ._wrapped_solver import AbstractForwardingSolver


class UnrolledStages(AbstractForwardingSolver):
    """A diffrax explicit Runge–Kutta solver (`diffrax.AbstractERK`: Tsit5, Dopri5, Dopri8,
    …) of an ODE, stepped with its stages written out.

        k_i = h f(t₀ + c_i h, y₀ + Σ_{j<i} a_ij k_j),   y₁ = y₀ + Σ b_i k_i,
        error = Σ (b_i − b̂_i) k_i

    (diffrax's `b_error` holds the differences). A first-same-as-last tableau reuses the last
    stage of a step as the first of the next, unless the state jumped (`made_jump`).
    """

    solver: diffrax.AbstractERK

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def init(self, terms, t0, t1, y0, args):
        if not _tableau(self.solver).fsal:
            return None
        # (first step, f at the end of the previous step): nothing to reuse yet.
        return jnp.array(True), jax.tree_util.tree_map(jnp.zeros_like, y0)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tableau = _tableau(self.solver)
        control = terms.contr(t0, t1)
        h = t1 - t0
        if tableau.fsal:
            first, f_last = solver_state
            f0 = jax.lax.cond(first | made_jump, lambda: terms.vf(t0, y0, args),
                              lambda: f_last)
        else:
            f0 = terms.vf(t0, y0, args)
        stages = [terms.prod(f0, control)]
        f = f0
        for c, row in zip(tableau.c, tableau.a_lower):
            y = _combine(y0, row, stages)
            f = terms.vf(t0 + float(c) * h, y, args)
            stages.append(terms.prod(f, control))
        y1 = _combine(y0, tableau.b_sol, stages)
        y_error = _combine(None, tableau.b_error, stages)
        k = jax.tree_util.tree_map(lambda *ks: jnp.stack(ks), *stages)
        dense_info = dict(y0=y0, y1=y1, k=k)
        # First same as last: the last stage was evaluated at (t1, y1).
        state = (jnp.array(False), f) if tableau.fsal else None
        return y1, y_error, dense_info, state, diffrax.RESULTS.successful


def _tableau(solver: diffrax.AbstractERK) -> diffrax.ButcherTableau:
    # An explicit Runge–Kutta solver's tableau is a `ButcherTableau` (diffrax's `AbstractERK`);
    # the annotation it inherits also admits the `MultiButcherTableau` of IMEX solvers.
    return cast(diffrax.ButcherTableau, solver.tableau)


def _combine(start, weights, stages):
    """start + Σ w_j k_j over the nonzero weights (start None: the sum alone)."""
    total = start
    for weight, stage in zip(weights, stages):
        if weight != 0:
            term = jax.tree_util.tree_map(lambda x, w=float(weight): w * x, stage)
            total = term if total is None else jax.tree_util.tree_map(jnp.add, total, term)
    return total
