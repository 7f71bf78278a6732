"""`fit`: identify physical parameters from measured trajectories.

The loop is optimistix's own solver protocol (init, then step until terminate), driven from
Python one compiled step at a time, so that between steps a progress bar, a callback, a check
for non-finite values and a checkpoint cost nothing on the device.
"""

import functools
import os
import sys
import time
import warnings
from typing import Any, Callable, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import tqdm
from jax.sharding import Mesh, PartitionSpec

from .._dynamics import AbstractDynamics
from .._batch import place_on_mesh
from .._errors import _where
from .._state import numbers_as_arrays
from .adequacy import adequacy, explained_loss
from .experiment import Experiment, HorizonContinuation, MultipleShooting
from .parametrisation import leaf_parametrisations
from .starts import MultiStart
from .residuals import (
    TrajectoryMatching,
    group_experiments,
    least_squares_residuals,
    least_squares_residuals_forward,
    observe_coordinates,
    scalar_loss,
)
from .uncertainty import Uncertainty, analyse, flatten_latent, latent_names, parameter_names


# Integration error far below measurement noise; 5th order keeps every Jacobian column cheap.
# In float32 the tolerance is simulate's own float32 default, near what that precision holds.
SIMULATE_OPTIONS = {"solver": diffrax.Tsit5(), "rtol": 1e-8, "atol": 1e-8}
FLOAT32_SIMULATE_TOLERANCE = 1e-6


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


def fit(
    dynamics: AbstractDynamics,
    experiments: Experiment | Sequence[Experiment],
    params,
    *,
    filter_spec=eqx.is_inexact_array,
    parametrisation=None,
    observe: Callable | None = None,
    fit_initial_states: bool = False,
    shooting: MultipleShooting | None = None,
    optimiser=None,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    adjoint: diffrax.AbstractAdjoint | None = None,
    simulate_options: dict | None = None,
    uncertainty: bool = True,
    identifiability_tolerance: float | None = None,
    progress: bool | None = None,
    callback: Callable | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 1,
    globalisation: HorizonContinuation | bool | None = None,
) -> FitResult:
    """Fit parameters of `dynamics` to measured trajectories by trajectory matching:
    minimise ½ Σᵢⱼ wᵢⱼ ‖yᵢⱼ − h(tᵢⱼ, q(tᵢⱼ), u(tᵢⱼ), p)‖² over the parameters p (and, if
    asked, the initial states), where (q, u) solve the equations of motion from each
    experiment's initial state.

    **Arguments:**

    - `dynamics`: any `jaxdyn.AbstractDynamics`.
    - `experiments`: a `jaxdyn.Experiment` or a sequence of them; experiments of equal shapes
      are simulated together under `vmap`.
    - `params`: the parameter pytree at the initial guess (physical values). Its floating
      arrays set the fit's precision: float32 arrays make a float32 fit (data, states,
      simulations and optimiser in float32), Python numbers take JAX's default float.
    - `filter_spec`: which leaves are trained, as for `equinox.partition`: a function of a leaf
      or a pytree of bools (prefix of `params`); the rest stay fixed. Default: every floating
      leaf.
    - `parametrisation`: None, or a prefix tree of `params` with `jaxdyn.Positive()`,
      `jaxdyn.Unconstrained()`, `jaxdyn.InertiaTensor()` or None (the default) at its leaves.
      By default a leaf whose initial values are all positive stays positive (fitted as
      exp z), any other is unconstrained.
    - `observe`: h(t, q, u, p) → (d,), what was measured (a marker's position, some
      coordinates); default: q.
    - `fit_initial_states`: fit each experiment's (q0, u0) too, starting from the given ones.
    - `shooting`: `jaxdyn.MultipleShooting(segments)` for long horizons and chaotic motion
      (see its documentation); None integrates every experiment in one piece.
    - `optimiser`: None for Levenberg–Marquardt (`optimistix.LevenbergMarquardt(rtol, atol)`),
      any optimistix least-squares solver or minimiser, or any optax optimiser (run through
      `optimistix.OptaxMinimiser(optimiser, rtol, atol)`). Levenberg–Marquardt is the default
      because trajectory matching is a nonlinear least-squares problem: it uses the
      Jacobian's Gauss–Newton curvature, within 1e-3 of the optimum in 6–14 steps where
      Adam took 110–439 (benchmarks/bench_fit.py).
    - `max_steps`, `rtol`, `atol`: the step budget and tolerances of the optimiser.
    - `adjoint`: how derivatives pass through the simulations. Default: forward mode
      (`diffrax.ForwardMode()`, one Jacobian column per fitted unknown) for least-squares
      solvers, which need the whole Jacobian of many residuals with respect to few
      parameters; recursive checkpointing (`diffrax.RecursiveCheckpointAdjoint()`, one
      reverse pass) for minimisers, which need one gradient. Another adjoint for a
      least-squares solver forms the Jacobian in reverse mode, one row per residual.
    - `simulate_options`: keywords for `jaxdyn.simulate` (solver, rtol, atol, max_steps, ...).
      Default: `diffrax.Tsit5()` at rtol = atol = 1e-8, an integration error far below any
      measurement noise, at about a third of the cost of `simulate`'s own 1e-10 default in
      every residual and Jacobian evaluation; in a float32 fit 1e-6, as for `simulate`.
    - `uncertainty`: compute standard errors, correlations and identifiability at the optimum.
    - `identifiability_tolerance`: singular values of the column-scaled Jacobian below this
      fraction of the largest mark a direction the data cannot identify. Default: 1e-7 in
      float64, 1e-4 in float32 (an exactly unidentifiable direction shows there at a few
      float32 roundings, 3e-7 on a double pendulum's mass scale, against 5e-16 in float64).
    - `progress`: a tqdm progress bar; None shows it when running interactively (a terminal
      or a notebook).
    - `callback`: `callback(step, params, loss)` after every step (step counts from 1); return
      True to stop.
    - `checkpoint`: a file path. The optimiser's whole state is saved there (equinox
      serialisation) every `checkpoint_every` steps; a fit started with an existing file
      resumes from it and ends at the same parameters as an uninterrupted fit.
    - `globalisation`: how a fit escapes local minima. None (default): fit directly, and if
      the optimiser converges (or runs out of steps) where the model does not explain the
      data (`explains_data` False), fit again by `jaxdyn.HorizonContinuation()` from the
      initial guess and keep the lower loss. A `jaxdyn.HorizonContinuation`: fit by it from
      the start. A `jaxdyn.MultiStart`: fit from a batch of starting points at once (one
      vmapped computation) and keep the lowest loss. False: fit directly only.

    **Returns:** a `jaxdyn.FitResult`; a converged fit that still does not explain its data
    warns (`jaxdyn.LackOfFitWarning`).
    """
    start_time = time.perf_counter()
    experiments = [experiments] if isinstance(experiments, Experiment) else list(experiments)
    if not (globalisation is None or globalisation is False
            or isinstance(globalisation, (HorizonContinuation, MultiStart))):
        raise ValueError("globalisation must be None, False, a jaxdyn.HorizonContinuation or "
                         f"a jaxdyn.MultiStart, got {globalisation!r}.")
    if isinstance(globalisation, MultiStart) and (callback is not None or checkpoint):
        raise ValueError("A multi-start fit takes no callback or checkpoint (they follow one "
                         "fit's steps).")
    options = dict(filter_spec=filter_spec, parametrisation=parametrisation, observe=observe,
                   fit_initial_states=fit_initial_states, shooting=shooting,
                   optimiser=optimiser, max_steps=max_steps, rtol=rtol, atol=atol,
                   adjoint=adjoint, simulate_options=simulate_options, uncertainty=uncertainty,
                   identifiability_tolerance=identifiability_tolerance, progress=progress,
                   callback=callback, checkpoint=checkpoint,
                   checkpoint_every=checkpoint_every)
    if isinstance(globalisation, HorizonContinuation):
        result = _by_continuation(globalisation, dynamics, experiments, params, options)
    elif isinstance(globalisation, MultiStart):
        result = _multi_start(globalisation, dynamics, experiments, params, options)
    else:
        result = _fit_directly(dynamics, experiments, params, **options)
        # Trapped: converged where the data are not explained, or ran out of steps crawling
        # (not stopped by the callback, whose decision stands).
        trapped = result.explains_data is False and (result.converged
                                                     or result.num_steps >= max_steps)
        if globalisation is None and trapped and not checkpoint:
            retried = _by_continuation(HorizonContinuation(), dynamics, experiments, params,
                                       options)
            if retried.loss < result.loss:
                result = retried
    result = eqx.tree_at(lambda r: r.wall_time, result, time.perf_counter() - start_time)
    # Warned for the fit returned only (not for one that globalisation replaced).
    if result.uncertainty is not None and result.uncertainty.unidentifiable:
        warnings.warn("\n".join(result.uncertainty.unidentifiable), IdentifiabilityWarning,
                      stacklevel=2)
    if result.converged and result.lack_of_fit is not None:
        warnings.warn(result.lack_of_fit, LackOfFitWarning, stacklevel=2)
    return result


def _multi_start(starts, dynamics, experiments, params, options):
    """`starts.count` fits at once, one per starting point, as one vmapped computation; the
    lowest loss is kept (its uncertainty analysed as a single fit's)."""
    start_time = time.perf_counter()
    setups = [_setup_with(dynamics, experiments, point, options)
              for point in starts.starting_points(params, options["filter_spec"])]
    problem, latent = setups[0][:2]
    # A start that has converged where the data are explained has found the optimum (up to
    # the noise): the others need not run on.
    nodes = sum(np.size(x) for x in jax.tree_util.tree_leaves(latent["nodes"]))
    explained = explained_loss(problem.groups, flatten_latent(latent)[0].size - nodes,
                               _tolerance_of(problem))
    latents, states, losses, done, history, _ = _run_batched(
        setups, options, shared_problem=True, desc=f"fit ×{starts.count}",
        enough=lambda losses, done: np.any(done & (losses <= explained)),
        initial_failure=lambda failed: INITIAL_FAILURE if 0 in failed else None)
    best = int(np.argmin(np.where(done, losses, np.inf) if done.any() else losses))
    converged = bool(done[best] and np.isfinite(losses[best]))
    if not converged:
        _warn_unconverged(options["max_steps"], [h[best] for h in history])
    result = _result(problem, _member(latents, best), _member(states, best),
                     [h[best] for h in history], converged, len(history),
                     options["uncertainty"], setups[0][5], start_time)
    return eqx.tree_at(lambda r: r.strategy, result, f"multi-start ({starts.count})")


def _setup_with(dynamics, experiments, params, options):
    return _setup(dynamics, experiments, params, options["filter_spec"],
                  options["parametrisation"], options["observe"],
                  options["fit_initial_states"], options["shooting"], options["optimiser"],
                  options["rtol"], options["atol"], options["adjoint"],
                  options["simulate_options"], options["identifiability_tolerance"])


def _member(tree, i):
    """Member i of a tree stacked along a leading axis (non-array leaves shared)."""
    return jax.tree_util.tree_map(lambda x: x[i] if eqx.is_array(x) else x, tree)


def _stacked(trees):
    """Trees of one structure stacked along a new leading axis (non-array leaves, equal in
    all, kept once)."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs) if eqx.is_array(xs[0]) else xs[0],
                                  *trees)


def _run_batched(setups, options, *, shared_problem, desc, initial_failure, enough=None,
                 devices=None):
    """Fits from every setup at once, one vmapped step for all, each member stopping where
    its own optimiser's tolerance is met or its iterate stops being finite (it keeps its last
    finite iterate, its loss infinite). `shared_problem`: every member fits the first setup's
    problem (a multi-start), else each its own (problems of equal shapes). `enough(losses,
    done)` may stop all early; `initial_failure(members)`, given the members whose loss at
    the initial guess is not finite, returns the message of the ValueError to raise, or
    None. Returns the stacked latents and optimiser states, the final
    losses, which members converged, the loss of every member at every step, and each
    member's number of steps. The members are sharded over `devices` (default: this
    process's, whose results it can read), padded to a multiple of their number with copies
    of the first, which start stopped."""
    problem, _, solver, fn, solver_options, _ = setups[0]
    count = len(setups)
    mesh = Mesh(np.asarray(jax.local_devices() if devices is None else list(devices)),
                ("batch",))
    width = mesh.devices.size
    setups = setups + [setups[0]] * (-count % width)
    problems = problem if shared_problem else _stacked([s[0] for s in setups])
    latents = _stacked([s[1] for s in setups])
    if width > 1:
        latents = _on_mesh(latents, mesh, PartitionSpec("batch"))
        problems = _on_mesh(problems, mesh, PartitionSpec(
            *(() if shared_problem else ("batch",))))
        solver_options = _on_mesh(solver_options, mesh, PartitionSpec())
    mapped = eqx.if_array(0)
    states = eqx.filter_vmap(lambda z, problem: _init(solver, fn, z, problem, solver_options),
                             in_axes=(mapped, None if shared_problem else mapped))(
        latents, problems)
    solver_arrays, solver_static = eqx.partition(solver, eqx.is_array)
    step = functools.partial(_compiled_batched_step_for(solver_static, fn, shared_problem),
                             solver_arrays)
    max_steps = options["max_steps"]
    done, finite = np.arange(len(setups)) >= count, np.ones(len(setups), bool)
    losses, steps, history = np.full(len(setups), np.inf), np.zeros(len(setups), int), []
    progress = options["progress"]
    if progress is None:
        progress = sys.stderr.isatty() or "ipykernel" in sys.modules
    with tqdm.tqdm(total=max_steps, disable=not progress, desc=desc, unit="step",
                   file=sys.stderr, mininterval=0.5) as bar:
        while not done.all() and len(history) < max_steps:
            latents, states, loss, now_done, now_finite = step(
                latents, problems, solver_options, states, jnp.asarray(done))
            loss, now_done, now_finite = (np.asarray(x) for x in jax.device_get(
                (loss, now_done, now_finite)))
            if not history and (message := initial_failure(
                    [i for i in range(count) if not np.isfinite(loss[i])])):
                raise ValueError(message)
            steps += ~done
            # A member whose iterate stopped being finite is dropped (its loss infinite).
            losses = np.where(done, losses, np.where(now_finite, loss, np.inf))
            finite &= now_finite | done
            done = done | now_done | ~now_finite
            history.append(losses.copy())
            bar.update(1)
            bar.set_postfix(loss=f"{np.min(losses):.4g}", done=f"{int(done.sum())}")
            if enough is not None and enough(losses, done):
                break
    real = lambda x: x[:count] if eqx.is_array(x) else x  # noqa: E731
    latents, states = jax.tree_util.tree_map(real, (latents, states))
    return (latents, states, losses[:count], (done & finite)[:count],
            [h[:count] for h in history], steps[:count])


def _on_mesh(tree, mesh, spec):
    """The arrays of `tree` laid out on the mesh; its other leaves unchanged."""
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(place_on_mesh(arrays, mesh, spec), rest)


@functools.lru_cache(maxsize=32)
def _compiled_batched_step_for(solver_static, fn, shared_problem):
    """`_step` of every member at once (vmapped); a member that has stopped, or whose new
    iterate is not finite, keeps its iterate."""

    @eqx.filter_jit
    def step(solver_arrays, latents, problems, options, states, done):
        solver = eqx.combine(solver_arrays, solver_static)

        def one(latent, problem, state, done):
            new_latent, new_state, loss, now_done, finite = _step(solver, fn, latent, problem,
                                                                  options, state)
            stay = done | ~finite
            keep = lambda new, old: jnp.where(stay, old, new) if eqx.is_array(new) else new  # noqa: E731
            return (jax.tree_util.tree_map(keep, new_latent, latent),
                    jax.tree_util.tree_map(keep, new_state, state), loss, done | now_done,
                    finite)

        mapped = eqx.if_array(0)
        return eqx.filter_vmap(one, in_axes=(mapped, None if shared_problem else mapped,
                                             mapped, mapped))(latents, problems, states, done)

    return step


def fit_batch(
    dynamics: AbstractDynamics,
    experiments: Sequence[Experiment | Sequence[Experiment]],
    params: Sequence,
    *,
    filter_spec=eqx.is_inexact_array,
    parametrisation=None,
    observe: Callable | None = None,
    fit_initial_states: bool = False,
    shooting: MultipleShooting | None = None,
    optimiser=None,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    adjoint: diffrax.AbstractAdjoint | None = None,
    simulate_options: dict | None = None,
    uncertainty: bool = True,
    identifiability_tolerance: float | None = None,
    progress: bool | None = None,
    globalisation: bool | None = None,
    devices=None,
) -> list[FitResult]:
    """Fit B independent systems of one model at once, each to its own experiments with its
    own parameters: B separate `jaxdyn.fit`s run as one vmapped computation (one compiled
    step for all, each system stopping where its own optimiser's tolerance is met), e.g. one
    robot joint, motor or specimen per system, or a fleet of identical machines measured one
    by one.

    **Arguments:**

    - `dynamics`: the model, shared by the systems.
    - `experiments`: per system, a `jaxdyn.Experiment` or a sequence of them; the systems'
      experiments must have equal shapes (numbers of samples, observations, coordinates),
      their times, data, weights and initial states may differ.
    - `params`: per system, the parameter pytree at its initial guess (one structure for
      all; the frozen leaves may differ between systems).
    - `globalisation`: None (default): as `jaxdyn.fit`, a system whose fit converges (or
      runs out of steps) where the model does not explain its data is fitted again by
      `jaxdyn.HorizonContinuation()` (one system after another, one compiled program for
      all), the lower loss kept. False: the batched fits only.
    - `devices`: the devices the systems are sharded over (`jax.sharding`; the batch padded
      to a multiple of their number), all of this process; default `jax.local_devices()`.
    - The other arguments are those of `jaxdyn.fit`, the same for every system.

    **Returns:** a list of B `jaxdyn.FitResult`s, each what `jaxdyn.fit` would return for that
    system alone (to round-off). Systems that do not converge, or whose data the model does
    not explain, are named in one warning each (`RuntimeWarning`,
    `jaxdyn.LackOfFitWarning`); a system whose iterate stops being finite ends there,
    unconverged, without stopping the others.
    """
    start_time = time.perf_counter()
    systems = [[e] if isinstance(e, Experiment) else list(e) for e in experiments]
    params = list(params)
    if not systems or len(systems) != len(params):
        raise ValueError(f"experiments and params must give one entry per system: got "
                         f"{len(systems)} and {len(params)}.")
    if globalisation not in (None, False):
        raise ValueError("fit_batch's globalisation must be None (horizon continuation for "
                         f"the systems left trapped) or False, got {globalisation!r}.")
    options = dict(filter_spec=filter_spec, parametrisation=parametrisation, observe=observe,
                   fit_initial_states=fit_initial_states, shooting=shooting,
                   optimiser=optimiser, max_steps=max_steps, rtol=rtol, atol=atol,
                   adjoint=adjoint, simulate_options=simulate_options, uncertainty=uncertainty,
                   identifiability_tolerance=identifiability_tolerance, progress=progress,
                   callback=None, checkpoint=None, checkpoint_every=1)
    setups = [_setup_with(dynamics, e, p, options) for e, p in zip(systems, params)]
    first = jax.tree_util.tree_structure(setups[0][:2])
    for i, setup in enumerate(setups[1:], 1):
        shapes = [np.shape(x) for x in jax.tree_util.tree_leaves(setup[:2])]
        if (jax.tree_util.tree_structure(setup[:2]) != first or shapes != [
                np.shape(x) for x in jax.tree_util.tree_leaves(setups[0][:2])]):
            raise ValueError(f"System {i}'s experiments or parameters differ in structure or "
                             "shape from system 0's: fit_batch stacks the systems, which "
                             "must have equal numbers of experiments and samples and one "
                             "parameter structure.")
    latents, states, _, done, history, steps = _run_batched(
        setups, options, shared_problem=False, desc=f"fit batch ×{len(setups)}",
        devices=devices,
        initial_failure=lambda failed: f"Systems {failed}: {INITIAL_FAILURE}" if failed
        else None)
    latents, states = jax.device_get((latents, states))  # members read on the host
    results = []
    for i, setup in enumerate(setups):
        results.append(_result(setup[0], _member(latents, i), _member(states, i),
                               [h[i] for h in history[:steps[i]]], bool(done[i]), int(steps[i]),
                               uncertainty, setup[5], start_time))
    if globalisation is None:
        for i, result in enumerate(results):
            if result.explains_data is False and (result.converged
                                                  or result.num_steps >= max_steps):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    retried = _by_continuation(HorizonContinuation(), dynamics, systems[i],
                                               params[i], options)
                if retried.loss < result.loss:
                    results[i] = retried
    wall_time = time.perf_counter() - start_time
    results = [eqx.tree_at(lambda r: r.wall_time, r, wall_time) for r in results]
    for condition, message, category in (
            (lambda r: not r.converged, f"did not converge in max_steps = {max_steps} steps "
             "(or their iterates stopped being finite)", RuntimeWarning),
            (lambda r: r.converged and r.lack_of_fit is not None, "do not explain their data "
             "(residuals far above the noise: see each result's lack_of_fit)",
             LackOfFitWarning),
            (lambda r: r.uncertainty is not None and r.uncertainty.unidentifiable,
             "have parameters their data cannot identify (see each result's uncertainty)",
             IdentifiabilityWarning)):
        named = [i for i, r in enumerate(results) if condition(r)]
        if named:
            warnings.warn(f"Systems {named} of the batch {message}.", category, stacklevel=2)
    return results


def _by_continuation(continuation, dynamics, experiments, params, options):
    """`continuation`'s stages, then the whole records, each from the last optimum (and,
    with fitted initial states, from its initial states)."""
    stage_options = {**options, "uncertainty": False, "callback": None, "checkpoint": None,
                     "shooting": None}
    guess = params
    for fraction in continuation.fractions:
        horizons = [continuation.samples(e, fraction) for e in experiments]
        with warnings.catch_warnings():  # a stage is a starting point, converged or not
            warnings.simplefilter("ignore", RuntimeWarning)
            result = _fit_directly(dynamics, experiments, guess, horizons=horizons,
                                   **stage_options)
        guess = result.params
        if options["fit_initial_states"]:
            experiments = [Experiment(e.ts, e.observations, np.asarray(q0), np.asarray(u0),
                                      e.inputs, e.weights)
                           for e, (q0, u0) in zip(experiments, result.initial_states)]
    result = _fit_directly(dynamics, experiments, guess, **options)
    return eqx.tree_at(lambda r: r.strategy, result, "horizon continuation")


def _fit_directly(dynamics, experiments, params, *, filter_spec, parametrisation, observe,
                  fit_initial_states, shooting, optimiser, max_steps, rtol, atol, adjoint,
                  simulate_options, uncertainty, identifiability_tolerance, progress,
                  callback, checkpoint, checkpoint_every, horizons=None):
    """One fit from `params` (`fit` without globalisation); `horizons` as in
    `group_experiments`."""
    start_time = time.perf_counter()
    problem, latent, solver, fn, options, identifiability_tolerance = _setup(
        dynamics, experiments, params, filter_spec, parametrisation, observe,
        fit_initial_states, shooting, optimiser, rtol, atol, adjoint, simulate_options,
        identifiability_tolerance, horizons)
    state = _init(solver, fn, latent, problem, options)
    iteration, history = 0, []
    step = _compiled_step(solver, fn)
    if checkpoint is not None and os.path.exists(checkpoint):
        iteration, latent, state, history = _load(checkpoint, latent, state, max_steps)

    if progress is None:
        progress = sys.stderr.isatty() or "ipykernel" in sys.modules
    bar = tqdm.tqdm(total=max_steps, initial=iteration, disable=not progress, desc="fit",
                    unit="step", file=sys.stderr, mininterval=0.5)
    done = bool(iteration) and _terminated(solver, fn, latent, problem, options, state)
    stopped = False
    try:
        while not done and iteration < max_steps:
            previous = latent
            try:
                latent, state, loss, done, finite = step(latent, problem, options, state)
                loss, done, finite = jax.device_get((loss, done, finite))  # one sync per step
                done = bool(done)
            except Exception as error:
                if not _where:
                    raise
                raise RuntimeError(f"At step {iteration + 1} of the fit: {_where.pop()}") \
                    from error
            iteration += 1
            loss = float(loss)
            if iteration == 1 and not np.isfinite(loss):  # the loss at the initial guess
                raise ValueError(INITIAL_FAILURE)
            if not finite:
                raise FloatingPointError(_nonfinite_message(problem, previous, iteration))
            history.append(loss)
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4g}")
            if checkpoint is not None and (done or iteration % checkpoint_every == 0):
                _save(checkpoint, iteration, latent, state, history, max_steps)
            if callback is not None and callback(iteration, problem.params(latent["params"]),
                                                 loss):
                stopped = True
                break
    finally:
        bar.close()
    if not done and not stopped:
        _warn_unconverged(max_steps, history)
    return _result(problem, latent, state, history, done, iteration, uncertainty,
                   identifiability_tolerance, start_time)


INITIAL_FAILURE = ("The simulations at the initial parameters fail (the loss is not finite): "
                   "check the initial guess and states, e.g. with jaxdyn.simulate.")


def _warn_unconverged(max_steps, history):
    last = history[-1] if history else float("nan")
    warnings.warn(f"The fit did not converge in max_steps = {max_steps} steps (loss "
                  f"{last:.6g}); raise max_steps or start closer.", RuntimeWarning,
                  stacklevel=4)


def _setup(dynamics, experiments, params, filter_spec, parametrisation, observe,
           fit_initial_states, shooting, optimiser, rtol, atol, adjoint, simulate_options,
           identifiability_tolerance, horizons=None):
    """(the problem, the latent starting point, the optimistix solver, the function it
    minimises, its options, the identifiability tolerance), after checking the arguments."""
    if not experiments or not all(isinstance(e, Experiment) for e in experiments):
        raise ValueError("experiments must be a jaxdyn.Experiment or a non-empty sequence of "
                         "them.")
    if not isinstance(dynamics, AbstractDynamics):
        raise ValueError(f"dynamics must be a jaxdyn.AbstractDynamics, got "
                         f"{type(dynamics).__name__}.")
    shooting = MultipleShooting(1) if shooting is None else shooting
    for i, e in enumerate(experiments):
        if (e.ts.shape[0] - 1) % shooting.segments:
            raise ValueError(f"Experiment {i} has {e.ts.shape[0]} samples: len(ts) − 1 = "
                             f"{e.ts.shape[0] - 1} must be divisible by the "
                             f"{shooting.segments} shooting segments.")
    least_squares, solver = _solver(optimiser, rtol, atol)
    dtype = fit_dtype(params)
    if identifiability_tolerance is None:
        identifiability_tolerance = 1e-7 if jnp.finfo(dtype).bits == 64 else 1e-4
    if adjoint is None:
        adjoint = (diffrax.ForwardMode() if least_squares
                   else diffrax.RecursiveCheckpointAdjoint())
    options = {"jac": "fwd" if isinstance(adjoint, diffrax.ForwardMode) else "bwd"}
    problem, latent = _problem(dynamics, experiments, params, dtype, filter_spec,
                               parametrisation, observe, fit_initial_states, shooting,
                               simulate_options, adjoint, horizons)
    # Weakly typed guesses (`jnp.asarray(0.3)`, Python numbers) come back from the first step
    # strongly typed, and the step would compile a second time for them (13 s for a box's
    # friction): the iterate is strongly typed from the start.
    latent = _strongly_typed(latent)
    fn = scalar_loss
    if least_squares:
        fn = (least_squares_residuals_forward if options["jac"] == "fwd"
              else least_squares_residuals)
    return problem, latent, solver, fn, options, identifiability_tolerance


def _solver(optimiser, rtol, atol):
    """(is a least-squares solver, the optimistix solver)."""
    if optimiser is None:
        return True, optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    if isinstance(optimiser, optx.AbstractLeastSquaresSolver) and not isinstance(
            optimiser, optx.AbstractMinimiser):
        return True, optimiser
    if isinstance(optimiser, optx.AbstractMinimiser):
        return False, optimiser
    if isinstance(optimiser, optax.GradientTransformation):
        return False, optx.OptaxMinimiser(optimiser, rtol=rtol, atol=atol)
    raise ValueError("optimiser must be None (Levenberg–Marquardt), an optimistix "
                     "least-squares solver or minimiser, or an optax optimiser; got "
                     f"{type(optimiser).__name__}.")


def _problem(dynamics, experiments, params, dtype, filter_spec, parametrisation, observe,
             fit_initial_states, shooting, simulate_options, adjoint, horizons=None):
    """The `TrajectoryMatching` problem (in precision `dtype`) and the latent starting
    point."""
    params = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype)
                                    if isinstance(x, float) else x, params)
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        if eqx.is_inexact_array(leaf) and not np.all(np.isfinite(np.asarray(leaf))):
            raise ValueError(f"p{jax.tree_util.keystr(path)} holds NaN or inf.")
    trained_tree, frozen = eqx.partition(params, filter_spec)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    trained_flags = tuple(jax.tree_util.tree_leaves(
        jax.tree_util.tree_map(lambda x: x is not None, trained_tree, is_leaf=lambda x: x is None)))
    if len(trained_flags) != len(leaves) or not any(trained_flags):
        raise ValueError("filter_spec selects no parameter to fit.")
    all_specs = leaf_parametrisations(parametrisation, params)
    names = [f"p{jax.tree_util.keystr(path)}"
             for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
    specs, z_params = [], []
    for spec, leaf, name, trained in zip(all_specs, leaves, names, trained_flags):
        if trained:
            if not eqx.is_inexact_array(leaf):
                raise ValueError(f"{name} is selected for fitting but is not a floating-point "
                                 "array.")
            specs.append(spec)
            z_params.append(spec.to_latent(leaf, name))
    groups = group_experiments(experiments, dtype, horizons)
    problem = TrajectoryMatching(
        dynamics=dynamics, groups=groups, frozen=frozen, treedef=treedef,
        trained=trained_flags, parametrisations=tuple(specs),
        observe=observe_coordinates if observe is None else observe,
        shooting=shooting, fit_initial_states=fit_initial_states,
        simulate_options=_simulate_options(simulate_options, dtype),
        adjoint=adjoint)
    states = tuple((g.q0, g.u0) for g in groups) if fit_initial_states else None
    latent = {"params": z_params, "states": states, "nodes": None}
    if shooting.segments > 1:
        latent["nodes"] = _initial_nodes(problem, latent, experiments)
    return problem, latent


def fit_dtype(params):
    """The precision of the fit: that of the parameters' floating arrays (all of one dtype),
    or JAX's default float where they are Python numbers. Data, initial states and
    simulations follow it, so that float32 is a choice made by the parameters alone."""
    dtypes = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        if isinstance(leaf, (np.ndarray, np.generic, jax.Array)) and jnp.issubdtype(
                leaf.dtype, jnp.inexact):
            if jnp.issubdtype(leaf.dtype, jnp.complexfloating):
                raise ValueError(f"p{jax.tree_util.keystr(path)} is complex ({leaf.dtype}): "
                                 "parameters must be real.")
            dtypes.setdefault(jnp.dtype(leaf.dtype), f"p{jax.tree_util.keystr(path)}")
    if len(dtypes) > 1:
        listing = ", ".join(f"{where} is {dtype}" for dtype, where in dtypes.items())
        raise ValueError(f"The parameters mix precisions ({listing}): give every floating "
                         "leaf one dtype (float64, or float32 for a float32 fit).")
    return next(iter(dtypes)) if dtypes else jnp.dtype(jnp.result_type(float))


def _simulate_options(given, dtype):
    options = dict(SIMULATE_OPTIONS)
    if jnp.finfo(dtype).bits < 64:
        options["rtol"] = options["atol"] = FLOAT32_SIMULATE_TOLERANCE
    given = dict(given or {})
    if "stepsize_controller" in given:  # it carries its own tolerances
        del options["rtol"], options["atol"]
    # Tolerances and step sizes as traced arrays (another value reuses the compiled
    # program); integers (the step budget) stay Python numbers, fixed when compiling.
    return {key: numbers_as_arrays(value, dtype) if isinstance(value, float) else value
            for key, value in {**options, **given}.items()}


def _initial_nodes(problem, latent, experiments):
    """Shooting nodes at the start of every segment but the first: from the data (the
    user's `initial_nodes`) or from a simulation at the initial parameters."""
    segments = problem.shooting.segments
    nodes = []
    for group, (q0, u0) in zip(problem.groups, problem.initial_states(latent)):
        length = (group.ts.shape[1] - 1) // segments
        at = np.arange(1, segments) * length
        if problem.shooting.initial_nodes is not None:
            states = [problem.shooting.initial_nodes(experiments[i].ts,
                                                     experiments[i].observations)
                      for i in group.indices]
            q = jnp.stack([jnp.asarray(s[0])[at] for s in states]).astype(q0.dtype)
            u = jnp.stack([jnp.asarray(s[1])[at] for s in states]).astype(u0.dtype)
        else:
            p = problem.params(latent["params"])
            q, u = _simulated_states(problem, group, p, q0, u0, at)
        nodes.append((q, u))
    return tuple(nodes)


@eqx.filter_jit
def _simulated_states(problem, group, p, q0, u0, at):
    q, u = jax.vmap(problem.solve, in_axes=(None, 0, 0, 0, 0))(p, group.inputs, q0, u0,
                                                               group.ts)
    return q[:, at], u[:, at]


@eqx.filter_jit
def _evaluate(problem, latent):
    """(per group the predicted observations, ½‖r_obs‖², r, r_obs)."""
    predictions, residuals, observation = problem.evaluate(latent)
    return predictions, 0.5 * jnp.sum(observation**2), residuals, observation


def _in_precision(state, latent):
    """The optimiser's state in the fit's precision. Under float64-enabled JAX, optimistix
    starts some scalars (the trust region's step size) as float64 arrays; in a float32 fit
    they would promote the damped Gauss–Newton operator to float64, which lineax rejects."""
    dtype = jnp.result_type(*[x for x in jax.tree_util.tree_leaves(latent)
                              if eqx.is_inexact_array(x)])
    return _strongly_typed(jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) and x.dtype != dtype
        and jnp.issubdtype(x.dtype, jnp.floating) else x, state))


def _strongly_typed(tree):
    """`tree` with its weakly typed arrays made strong (the same dtype): a jitted step whose
    output types differ from its input's only in weak types compiles again for its output."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype=x.dtype) if getattr(x, "weak_type", False) else x,
        tree)


@eqx.filter_jit
def _init(solver, fn, latent, problem, options):
    f_struct, aux_struct = jax.eval_shape(lambda z: fn(z, problem), latent)
    return _in_precision(solver.init(fn, latent, problem, options, f_struct, aux_struct,
                                     frozenset()), latent)


def _step(solver, fn, latent, problem, options, state):
    latent, state, loss = solver.step(fn, latent, problem, options, state, frozenset())
    state = _in_precision(state, latent)
    done, _ = solver.terminate(fn, latent, problem, options, state, frozenset())
    # The accepted iterate and (least-squares solvers) the next trial point: a non-finite
    # Jacobian or gradient shows in them first.
    proposed = [x for x in jax.tree_util.tree_leaves((latent, getattr(state, "y_eval", None)))
                if eqx.is_inexact_array(x)]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in proposed]))
    return latent, state, loss, done, finite


@functools.lru_cache(maxsize=32)
def _compiled_step_for(solver_static, fn):
    """`_step` compiled with the solver's static part closed over, found once per fit.

    A jitted function hashes its static arguments on every call; optimistix wraps an optax
    optimiser's closures in objects whose hash reads their source code (about 10 ms a step,
    more than a small problem's gradient). Keyed by that static part, the lookup is paid once
    per fit, and fits with equal solvers share the compiled step."""

    @eqx.filter_jit
    def step(solver_arrays, latent, problem, options, state):
        solver = eqx.combine(solver_arrays, solver_static)
        return _step(solver, fn, latent, problem, options, state)

    return step


def _compiled_step(solver, fn):
    arrays, static = eqx.partition(solver, eqx.is_array)
    return functools.partial(_compiled_step_for(static, fn), arrays)


def _terminated(solver, fn, latent, problem, options, state):
    return bool(solver.terminate(fn, latent, problem, options, state, frozenset())[0])


def _nonfinite_message(problem, latent, iteration):
    """Why the iterate became non-finite: the entries of the gradient at the last finite
    iterate that are NaN or inf, by name."""
    reverse = eqx.tree_at(lambda p: p.adjoint, problem, diffrax.RecursiveCheckpointAdjoint())
    flat, unravel = flatten_latent(latent)
    gradient = np.asarray(jax.grad(lambda f: scalar_loss(unravel(f), reverse)[0])(flat))
    bad = [name for name, g in zip(latent_names(problem, latent), gradient)
           if not np.isfinite(g)]
    if bad:
        return (f"The gradient of the loss is NaN or inf at step {iteration} of the fit, in "
                f"{', '.join(bad)}. A parameter enters the equations where their derivative "
                "is not finite (sqrt or log at 0, a division by a parameter that reaches 0).")
    return (f"The fit produced non-finite values at step {iteration} although the gradient "
            "is finite there: the residuals overflow; scale the data or the weights.")


def _save(path, iteration, latent, state, history, max_steps):
    padded = np.full(max_steps, np.nan)
    padded[:len(history)] = history
    temporary = f"{path}.partial"
    eqx.tree_serialise_leaves(temporary, (np.asarray(iteration), latent, state, padded))
    os.replace(temporary, path)  # atomic: an interruption never leaves half a checkpoint


def _load(path, latent, state, max_steps):
    like = (np.asarray(0), latent, state, np.full(max_steps, np.nan))
    try:
        iteration, latent, state, padded = eqx.tree_deserialise_leaves(path, like)
    except Exception as error:
        raise ValueError(f"The checkpoint {os.fspath(path)!r} does not belong to this fit "
                         f"(another system, data or optimiser): {error}") from None
    iteration = int(iteration)
    return iteration, latent, state, [float(x) for x in padded[:iteration]]


def _result(problem, latent, state, history, converged, iteration, uncertainty, tolerance,
            start_time):
    params = problem.params(latent["params"])
    states = problem.initial_states(latent)
    initial_states, predictions = {}, {}
    if uncertainty:
        report, predicted_groups, loss, (r_all, r_obs) = analyse(problem, latent, tolerance,
                                                                 state)
    else:
        report = None
        predicted_groups, loss, r_all, r_obs = _evaluate(problem, latent)
    for group, (q0, u0), predicted in zip(problem.groups, states, predicted_groups):
        for k, i in enumerate(group.indices):
            initial_states[i] = (q0[k], u0[k])
            predictions[i] = predicted[k]
    r_obs = np.asarray(r_obs)
    r_continuity = np.asarray(r_all)[r_obs.size:]
    residual, noise, explains, closed = adequacy(
        problem.groups, r_obs, r_continuity,
        flatten_latent(latent)[0].size - r_continuity.size,
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
