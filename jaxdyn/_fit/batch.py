"""Many fits as one vmapped computation: `fit_batch` (independent systems of one model, each
to its own data) and the multi-start of `fit` (one problem from many starting points), one
compiled step for all members, each stopping at its own tolerance, sharded over devices."""

import functools
import sys
import time
import warnings
from typing import Callable, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import tqdm
from jax.sharding import Mesh, PartitionSpec

from .._dynamics import AbstractDynamics
from .._batch import place_on_mesh
from .adequacy import explained_loss
from .experiment import Experiment, HorizonContinuation, MultipleShooting
from .uncertainty import flatten_latent
from .problem import _setup_with
from .result import (
    FitResult,
    IdentifiabilityWarning,
    LackOfFitWarning,
    _result,
    _tolerance_of,
)
from .steps import INITIAL_FAILURE, _by_continuation, _init, _step, _warn_unconverged


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
