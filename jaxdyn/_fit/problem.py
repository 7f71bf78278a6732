"""The least-squares problem of a fit: its arguments checked, the optimiser chosen, the
parameters mapped to the optimiser's unconstrained variables, the simulations' options, the
multiple-shooting nodes, and the loss evaluated at a point."""


import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx

from .._dynamics import AbstractDynamics
from .._state import numbers_as_arrays, transferred
from .experiment import Experiment, MultipleShooting
from .parametrisation import leaf_parametrisations
from .residuals import (
    TrajectoryMatching,
    group_experiments,
    least_squares_residuals,
    least_squares_residuals_forward,
    observe_coordinates,
    scalar_loss,
)


# Integration error far below measurement noise; 5th order keeps every Jacobian column cheap.
# In float32 the tolerance is simulate's own float32 default, near what that precision holds.
SIMULATE_OPTIONS = {"solver": diffrax.Tsit5(), "rtol": 1e-8, "atol": 1e-8}


FLOAT32_SIMULATE_TOLERANCE = 1e-6


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


def _setup_with(dynamics, experiments, params, options):
    return _setup(dynamics, experiments, params, options["filter_spec"],
                  options["parametrisation"], options["observe"],
                  options["fit_initial_states"], options["shooting"], options["optimiser"],
                  options["rtol"], options["atol"], options["adjoint"],
                  options["simulate_options"], options["identifiability_tolerance"])


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
    params = jax.tree_util.tree_map(lambda x: transferred(x, dtype)
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


def _strongly_typed(tree):
    """`tree` with its weakly typed arrays made strong (the same dtype): a jitted step whose
    output types differ from its input's only in weak types compiles again for its output."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype=x.dtype) if getattr(x, "weak_type", False) else x,
        tree)
