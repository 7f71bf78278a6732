"""One fit, step by step: optimistix's solver protocol (init, then step until terminate) driven
from Python one compiled step at a time, so that between steps a progress bar, a callback, a
check for non-finite values and a checkpoint cost nothing on the device; and horizon
continuation, a sequence of such fits over growing records."""

import contextlib
import functools
import os
import sys
import time
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import tqdm

from .._errors import _where, checks_as_nan
from .experiment import Experiment
from .residuals import output_structure, scalar_loss
from .uncertainty import flatten_latent, latent_names
from .problem import _setup, _strongly_typed
from .result import _result


INITIAL_FAILURE = ("The simulations at the initial parameters fail (the loss is not finite): "
                   "check the initial guess and states, e.g. with jaxdyn.simulate.")


def _warn_unconverged(max_steps, history, stacklevel=4):
    last = history[-1] if history else float("nan")
    warnings.warn(f"The fit did not converge in max_steps = {max_steps} steps (loss "
                  f"{last:.6g}); raise max_steps or start closer.", RuntimeWarning,
                  stacklevel=stacklevel)


def _in_precision(state, latent):
    """The optimiser's state in the fit's precision. Under float64-enabled JAX, optimistix
    starts some scalars (the trust region's step size) as float64 arrays; in a float32 fit
    they would promote the damped Gauss–Newton operator to float64, which lineax rejects."""
    dtype = jnp.result_type(*[x for x in jax.tree_util.tree_leaves(latent)
                              if eqx.is_inexact_array(x)])
    return _strongly_typed(jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) and x.dtype != dtype
        and jnp.issubdtype(x.dtype, jnp.floating) else x, state))


@eqx.filter_jit
def _init(solver, fn, latent, problem, options):
    f_struct, aux_struct = output_structure(fn, problem, latent)
    # (traced as the lean step is, `_compiled_step_for`, which then reuses what it traced)
    with checks_as_nan():
        return _in_precision(solver.init(fn, latent, problem, options, f_struct, aux_struct,
                                         frozenset()), latent)


def _step(solver, fn, latent, problem, options, state):
    latent, state, (loss, _) = solver.step(fn, latent, problem, options, state, frozenset())
    state = _in_precision(state, latent)
    done, _ = solver.terminate(fn, latent, problem, options, state, frozenset())
    # The accepted iterate and (least-squares solvers) the next trial point: a non-finite
    # Jacobian or gradient shows in them first.
    proposed = [x for x in jax.tree_util.tree_leaves((latent, getattr(state, "y_eval", None)))
                if eqx.is_inexact_array(x)]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in proposed]))
    return latent, state, loss, done, finite


@functools.lru_cache(maxsize=32)
def _compiled_step_for(solver_static, fn, lean):
    """`_step` compiled with the solver's static part closed over, found once per fit.

    A jitted function hashes its static arguments on every call; optimistix wraps an optax
    optimiser's closures in objects whose hash reads their source code (about 10 ms a step,
    more than a small problem's gradient). Keyed by that static part, the lookup is paid once
    per fit, and fits with equal solvers share the compiled step.

    `lean`: the checks inside the simulations (their tolerances, save times) give NaN on
    failure instead of calling the host, so that the program holds no host callback and
    JAX's persistent compilation cache keeps it; a step whose result is not finite is run
    again as the checked program (`lean` False), which names a failed check."""

    @eqx.filter_jit
    def step(solver_arrays, latent, problem, options, state):
        solver = eqx.combine(solver_arrays, solver_static)
        with checks_as_nan() if lean else contextlib.nullcontext():
            return _step(solver, fn, latent, problem, options, state)

    return step


def _compiled_step(solver, fn, lean=True):
    arrays, static = eqx.partition(solver, eqx.is_array)
    return functools.partial(_compiled_step_for(static, fn, lean), arrays)


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


def _fit_directly(dynamics, experiments, params, *, filter_spec, parametrisation, observe,
                  fit_initial_states, shooting, optimiser, max_steps, rtol, atol, adjoint,
                  simulate_options, uncertainty, identifiability_tolerance, progress,
                  callback, checkpoint, checkpoint_every, horizons=None, warn=True):
    """One fit from `params` (`fit` without globalisation); `horizons` as in
    `group_experiments`. `warn`: warn when the fit runs out of steps (False for a fit that
    globalisation may replace, whose caller warns for the fit it returns)."""
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
            previous, previous_state = latent, state
            try:
                latent, state, loss, done, finite = step(latent, problem, options, state)
                loss, done, finite = jax.device_get((loss, done, finite))  # one sync per step
                done = bool(done)
                if not (finite and np.isfinite(loss)):
                    # A failed check inside the simulations raises from the checked step.
                    _compiled_step(solver, fn, lean=False)(previous, problem, options,
                                                           previous_state)
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
    if warn and not done and not stopped:
        _warn_unconverged(max_steps, history)
    return _result(problem, latent, state, history, done, iteration, uncertainty,
                   identifiability_tolerance, start_time)


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
