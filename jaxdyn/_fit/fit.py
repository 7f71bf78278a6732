"""`fit`: identify physical parameters from measured trajectories, directly or with a
globalisation (horizon continuation, multi-start) that escapes local minima."""

import os
import time
import warnings
from typing import Callable, Sequence

import diffrax
import equinox as eqx

from .._dynamics import AbstractDynamics
from .experiment import Experiment, HorizonContinuation, MultipleShooting
from .starts import MultiStart
from .batch import _multi_start
from .result import FitResult, IdentifiabilityWarning, LackOfFitWarning
from .steps import _by_continuation, _fit_directly, _warn_unconverged


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
    warns (`jaxdyn.LackOfFitWarning`), one that ran out of steps warns too (`RuntimeWarning`;
    not for a direct attempt that globalisation replaced).
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
        may_retry = globalisation is None and not checkpoint
        result = _fit_directly(dynamics, experiments, params, warn=not may_retry, **options)
        # Trapped: converged where the data are not explained, or ran out of steps crawling
        # (not stopped by the callback, whose decision stands).
        ran_out = not result.converged and result.num_steps >= max_steps
        trapped = result.explains_data is False and (result.converged or ran_out)
        if may_retry and trapped:
            retried = _by_continuation(HorizonContinuation(), dynamics, experiments, params,
                                       options)
            if retried.loss < result.loss:
                result = retried
        if may_retry and result.strategy == "direct" and ran_out:
            # (the direct fit's warning, only where it is the fit returned)
            _warn_unconverged(max_steps, list(result.loss_history), stacklevel=3)
    result = eqx.tree_at(lambda r: r.wall_time, result, time.perf_counter() - start_time)
    # Warned for the fit returned only (not for one that globalisation replaced).
    if result.uncertainty is not None and result.uncertainty.unidentifiable:
        warnings.warn("\n".join(result.uncertainty.unidentifiable), IdentifiabilityWarning,
                      stacklevel=2)
    if result.converged and result.lack_of_fit is not None:
        warnings.warn(result.lack_of_fit, LackOfFitWarning, stacklevel=2)
    return result
