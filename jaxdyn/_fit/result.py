"""What a fit returns (`FitResult`): the fitted parameters and predictions, whether the model
explains the data (residuals against the noise estimated from the data), standard errors and
intervals; and the warnings a fit gives."""

import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._state import numbers_as_arrays, transferred
from .adequacy import adequacy
from .residuals import (
    TrajectoryMatching,
)
from .uncertainty import Uncertainty, analyse, kept_evaluation, parameter_names
from .problem import _evaluate, fit_dtype


class LackOfFitWarning(UserWarning):
    """Issued by `jaxdyn.fit` when the fitted model does not explain the data: its residuals
    stay far above the noise estimated from the data (a local minimum, or a term missing
    from the model), or multiple-shooting segments were left apart."""


class IdentifiabilityWarning(UserWarning):
    """The data cannot identify some parameters (`FitResult.uncertainty.unidentifiable`)."""


class FitResult(eqx.Module):
    """What `jaxdyn.fit` returns.

    **Fields:**

    - `params`: the fitted parameters (the whole tree: trained and frozen leaves).
    - `initial_states`: per experiment, the initial state (q0, u0) (fitted or as given).
    - `loss`: ½ Σ w (y − ŷ)² over all observations at the fitted values.
    - `loss_history`: that loss at the iterate of every step.
    - `predictions`: per experiment, the fitted model's observations at the data's times.
    - `converged`: whether the optimiser's tolerance was met (else `max_steps` ran out or the
      callback stopped the fit). It does not say that the optimum was found: see
      `explains_data`.
    - `explains_data`: whether the residuals are at the level of the noise in the data (σ² at
      most 4 σ̂²) and multiple-shooting segments join; False means a local minimum or a
      model that lacks a term, and `fit` warns (`jaxdyn.LackOfFitWarning`). None where the
      records are too short to estimate the noise.
    - `lack_of_fit`: why the data are not explained (the message of the warning), or None.
    - `strategy`: "direct", or "horizon continuation" (`jaxdyn.HorizonContinuation`).
    - `residual_variance`: σ² = Σ w (y − ŷ)² / (N − P), the weighted residual variance.
    - `noise_variance`: σ̂², the weighted noise variance estimated from the data alone by
      differences along each record (Rice 1984), whatever the weights.
    - `num_steps`, `num_accepted_steps` (least-squares solvers: steps that lowered the loss),
      `wall_time` (seconds, compilation included).
    - `uncertainty`: a `jaxdyn.Uncertainty` (standard errors, correlations, identifiability),
      or None with `uncertainty=False`.
    - `problem`, `latent`: the least-squares problem and the optimiser's unconstrained
      variables (for `loss_at` and further analysis).
    """

    params: Any
    initial_states: tuple
    loss: float
    loss_history: np.ndarray
    predictions: tuple
    converged: bool
    explains_data: bool | None
    lack_of_fit: str | None
    strategy: str
    residual_variance: float
    noise_variance: float
    num_steps: int
    num_accepted_steps: int | None
    wall_time: float
    uncertainty: Uncertainty | None
    problem: TrajectoryMatching
    latent: Any

    @property
    def standard_errors(self):
        """Standard errors shaped like the parameter tree (None for frozen leaves)."""
        errors = iter(self._uncertainty().standard_errors)
        leaves = jax.tree_util.tree_leaves(self.params)
        out = [np.reshape([next(errors) for _ in range(np.size(x))], np.shape(x))
               if trained else None for x, trained in zip(leaves, self.problem.trained)]
        return jax.tree_util.tree_unflatten(self.problem.treedef, out)

    def confidence_intervals(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """Per parameter entry, the interval x̂ ± z σ̂ of the normal approximation at the
        optimum (z = 1.96 for 95 %)."""
        z = float(jax.scipy.special.ndtri(0.5 + level / 2))
        values = np.concatenate([np.ravel(x) for x in self.problem.trained_leaves(self.params)])
        uncertainty = self._uncertainty()
        errors = uncertainty.standard_errors
        return {name: (float(v - z * e), float(v + z * e))
                for name, v, e in zip(uncertainty.names, values, errors)}

    def _uncertainty(self) -> Uncertainty:
        """`uncertainty`, which the standard errors and intervals need."""
        if self.uncertainty is None:  # an AttributeError, as before, that says why
            raise AttributeError("This fit has no standard errors: it ran with "
                                 "uncertainty=False.")
        return self.uncertainty

    def summary(self) -> str:
        """The loss and convergence, whether the model explains the data (residuals against
        the noise estimated from the data), and a table of the fitted parameters with
        standard errors and 95 % intervals."""
        lines = [f"loss {self.loss:.6g} after {self.num_steps} steps "
                 f"({'converged' if self.converged else 'not converged'}, "
                 f"{self.wall_time:.1f} s)"]
        if self.explains_data is not None:
            verdict = ("explained by the model" if self.explains_data else
                       "NOT explained by the model (a local minimum, or a term missing)")
            lines.append(f"residual RMS {np.sqrt(self.residual_variance):.3g} against noise "
                         f"{np.sqrt(self.noise_variance):.3g} estimated from the data "
                         f"(weighted): data {verdict}")
        if self.uncertainty is None:
            return "\n".join(lines)
        intervals = self.confidence_intervals()
        values = np.concatenate([np.ravel(x) for x in self.problem.trained_leaves(self.params)])
        width = max(len(n) for n in self.uncertainty.names)
        lines.append(f"{'parameter':<{width}}  {'value':>12}  {'std. error':>11}  95 % interval")
        for name, v, e in zip(self.uncertainty.names, values,
                              self.uncertainty.standard_errors):
            low, high = intervals[name]
            lines.append(f"{name:<{width}}  {v:12.6g}  {e:11.3g}  [{low:.6g}, {high:.6g}]")
        lines.extend(self.uncertainty.unidentifiable)
        return "\n".join(lines)

    def loss_at(self, params):
        """½ Σ w (y − ŷ)² at other parameter values, the fitted initial states and shooting
        nodes kept: to draw the loss landscape around the optimum."""
        latent = eqx.tree_at(lambda z: z["params"], self.latent,
                             [s.to_latent(x, n) for s, x, n in zip(
                                 self.problem.parametrisations,
                                 self.problem.trained_leaves(
                                     numbers_as_arrays(params, fit_dtype(self.params))),
                                 parameter_names(self.problem, self.latent))])
        return float(_evaluate(self.problem, latent)[1])


def _result(problem, latent, state, history, converged, iteration, uncertainty, tolerance,
            start_time):
    params = problem.params(latent["params"])
    states = problem.initial_states(latent)
    initial_states, predictions = {}, {}
    if uncertainty:
        report, predicted_groups, loss, (r_all, r_obs) = analyse(problem, latent, tolerance,
                                                                 state)
    elif (kept := kept_evaluation(problem, state, latent)) is not None:
        report = None
        _, r_all, r_obs, predicted_groups = kept
        loss = 0.5 * np.sum(r_obs**2)
    else:
        report = None
        predicted_groups, loss, r_all, r_obs = _evaluate(problem, latent)
    for group, (q0, u0), predicted in zip(problem.groups, states, predicted_groups):
        for k, i in enumerate(group.indices):
            initial_states[i] = (_row(q0, k), _row(u0, k))
            predictions[i] = _row(predicted, k)
    r_obs = np.asarray(r_obs)
    r_continuity = np.asarray(r_all)[r_obs.size:]
    residual, noise, explains, closed = adequacy(
        problem.groups, r_obs, r_continuity,
        sum(np.size(x) for x in jax.tree_util.tree_leaves(latent)) - r_continuity.size,
        _tolerance_of(problem))
    lack_of_fit = None
    if explains is False or closed is False:
        lack_of_fit = _lack_of_fit_message(residual, noise, explains, closed, r_continuity)
    accepted = getattr(state, "num_accepted_steps", None)
    return FitResult(
        params=params,
        initial_states=tuple(initial_states[i] for i in range(len(initial_states))),
        loss=float(loss),
        loss_history=np.asarray(history),
        predictions=tuple(predictions[i] for i in range(len(predictions))),
        converged=bool(converged),
        explains_data=None if explains is None else bool(explains and closed),
        lack_of_fit=lack_of_fit, strategy="direct",
        residual_variance=residual, noise_variance=noise, num_steps=iteration,
        num_accepted_steps=None if accepted is None else int(accepted),
        wall_time=time.perf_counter() - start_time, uncertainty=report, problem=problem,
        latent=latent)


def _tolerance_of(problem):
    """The simulations' relative tolerance (√ε where a step-size controller sets it)."""
    dtype = jnp.result_type(*[g.observations for g in problem.groups])
    return float(problem.simulate_options.get("rtol", np.finfo(dtype).eps ** 0.5))


def _lack_of_fit_message(residual, noise, explains, closed, r_continuity):
    lines = []
    if not explains:
        lines.append(
            f"The fitted model does not explain the data: its residual variance is "
            f"{residual / noise:.3g} times the noise variance estimated from the data "
            f"(residual RMS {np.sqrt(residual):.3g} against noise {np.sqrt(noise):.3g}, "
            "weighted), although the optimiser stopped. Either the fit stopped in a local "
            "minimum (trajectories of oscillations have many: start from other values, fit "
            "by jaxdyn.HorizonContinuation, or use jaxdyn.MultipleShooting) or the model "
            "lacks a term (damping, friction, an input).")
    if not closed:
        lines.append(
            f"The multiple-shooting segments do not join (continuity residuals of RMS "
            f"{np.sqrt(np.mean(r_continuity**2)):.3g}): the fitted trajectory is not one "
            "solution of the equations. Raise max_steps, or the continuity_weight.")
    return "\n".join(lines)


def _row(x, k):
    """Row k of a stacked result (indexing the JAX array would compile a program of its own
    in a process's first fit)."""
    return transferred(np.asarray(x)[k])
