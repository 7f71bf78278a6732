"""Trajectory matching: the residuals between measured and simulated observations, as a function
of unconstrained latent variables (parameters, initial states, shooting nodes).

    r = [ √w (y_ij − h(t_ij, q(t_ij), u(t_ij), p)) ;  w_c (x_s(end) − x_{s+1}) ],

where the first block runs over the experiments i and their samples j, and the second (multiple
shooting only) over the joints between consecutive segments.
"""

from typing import Any, Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .._custom_jvp import batch_axis_first
from .._errors import checks_as_nan_active
from .._dynamics import AbstractDynamics
from .._integrate import simulate
from .experiment import Experiment, MultipleShooting
from .parametrisation import AbstractParametrisation


# Experiments of a group are simulated together (vmap) up to this many samples each, one
# after another (lax.map) beyond. Under vmap the solves' loops run in step, and saving at the
# sample times selects over every member's whole record at each step, which grows as the
# steps times the samples: 4 oscillator records of 20 001 samples fit in 28.5 s vmapped, 6.2 s
# mapped; records of 5001 samples in 0.64 s vmapped, 1.4 s mapped (benchmarks/bench_fit_scale.py).
LONG_RECORD = 10_000


def observe_coordinates(t, q, u, p):
    """The default observation: the coordinates q."""
    return q


class ExperimentGroup(eqx.Module):
    """Experiments of identical shapes, stacked along a leading axis (simulated with vmap)."""

    indices: tuple[int, ...] = eqx.field(static=True)
    ts: Any  # (E, k)
    observations: Any  # (E, k, d)
    sqrt_weights: Any  # (E, k, d)
    q0: Any  # (E, n)
    u0: Any  # (E, m)
    inputs: Any  # stacked pytree, or None


def _shape_key(experiment: Experiment):
    leaves, treedef = jax.tree_util.tree_flatten(experiment.inputs)
    return (experiment.ts.shape, experiment.observations.shape, experiment.q0.shape,
            experiment.u0.shape, treedef, tuple(np.shape(x) for x in leaves))


def _as_data(x, dtype):
    return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x


def group_experiments(experiments, dtype, horizons=None) -> tuple[ExperimentGroup, ...]:
    """Group experiments by shape, in order of first appearance.

    `horizons`: None, or per experiment the number of leading samples fitted (a stage of a
    horizon continuation). The later samples keep their places, at the last fitted time and
    with weight 0: the simulation ends at that time, their residuals are 0, and the problem
    has the whole records' shapes, so that it shares their compiled programs."""
    horizons = [None] * len(experiments) if horizons is None else horizons
    keys = {}
    for i, experiment in enumerate(experiments):
        keys.setdefault(_shape_key(experiment), []).append(i)
    groups = []
    for indices in keys.values():
        members = [experiments[i] for i in indices]
        sampled = [_sampled(experiments[i], horizons[i]) for i in indices]

        def stack(get):
            return jnp.asarray(np.stack([get(e) for e in members]), dtype)

        inputs = None
        if members[0].inputs is not None:
            # Measured inputs are data: floating ones take the fit's precision, as the
            # observations do.
            inputs = jax.tree_util.tree_map(
                lambda *xs: _as_data(jnp.stack([jnp.asarray(x) for x in xs]), dtype),
                *[e.inputs for e in members])
        groups.append(ExperimentGroup(
            indices=tuple(indices),
            ts=jnp.asarray(np.stack([ts for ts, _ in sampled]), dtype),
            observations=stack(lambda e: e.observations),
            sqrt_weights=jnp.asarray(np.stack([np.sqrt(w) for _, w in sampled]), dtype),
            q0=stack(lambda e: e.q0),
            u0=stack(lambda e: e.u0),
            inputs=inputs))
    return tuple(groups)


def _sampled(experiment: Experiment, horizon: int | None):
    """(ts, weights) of `experiment` fitted over its first `horizon` samples (all if None)."""
    weights = (np.ones_like(experiment.observations) if experiment.weights is None
               else np.array(experiment.weights))
    if horizon is None:
        return experiment.ts, weights
    weights[horizon:] = 0.0
    return np.minimum(experiment.ts, experiment.ts[horizon - 1]), weights


class TrajectoryMatching(eqx.Module):
    """The least-squares problem that `jaxdyn.fit` solves.

    Latent variables z = {"params": latent leaves of the trained parameters, "states": per
    group (q0, u0) when initial states are fitted, else None, "nodes": per group the shooting
    nodes (q, u) of shape (E, segments − 1, ·), else None}.
    """

    dynamics: AbstractDynamics
    groups: tuple[ExperimentGroup, ...]
    frozen: Any  # the parameter tree with trained leaves replaced by None
    treedef: Any = eqx.field(static=True)  # of the full parameter tree
    trained: tuple[bool, ...] = eqx.field(static=True)  # per leaf of the parameter tree
    parametrisations: tuple[AbstractParametrisation, ...]  # per trained leaf
    observe: Callable = eqx.field(static=True)
    shooting: MultipleShooting
    fit_initial_states: bool = eqx.field(static=True)
    simulate_options: dict
    adjoint: diffrax.AbstractAdjoint

    # -- latent ↔ physical --------------------------------------------------------------------

    def params(self, z_params):
        """The full parameter tree (physical values) from the trained leaves' latent values."""
        physical = iter([s.to_physical(x) for s, x in zip(self.parametrisations, z_params)])
        frozen = iter(jax.tree_util.tree_leaves(self.frozen))
        leaves = [next(physical) if trained else next(frozen) for trained in self.trained]
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def trained_leaves(self, params):
        leaves = jax.tree_util.tree_leaves(params)
        return [x for x, trained in zip(leaves, self.trained) if trained]

    def initial_states(self, z):
        """Per group, (q0, u0) stacked over its experiments."""
        if z["states"] is not None:
            return z["states"]
        return tuple((g.q0, g.u0) for g in self.groups)

    # -- predictions and residuals ------------------------------------------------------------

    def solve(self, params, inputs, q0, u0, ts):
        """(q, u) at the times ts from (q0, u0) at ts[0]: one simulation (failures give
        infinite states, so that an optimiser rejects the trial point)."""
        p = params if inputs is None else (params, inputs)
        solution = simulate(self.dynamics, q0, u0, p, t0=ts[0], t1=ts[-1], ts=ts,
                            save=("q", "u"), adjoint=self.adjoint, throw=False,
                            **self.simulate_options)
        assert solution.q is not None and solution.u is not None  # saved: save=("q", "u")
        return solution.q, solution.u

    def _segments(self, ts, params, q0, u0, inputs, nodes):
        """Observations predicted along one experiment, and the continuity gaps."""
        p = params if inputs is None else (params, inputs)
        segments = self.shooting.segments
        length = (ts.shape[0] - 1) // segments
        index = np.arange(segments)[:, None] * length + np.arange(length + 1)
        t_segments = ts[index]
        if nodes is None:
            starts = (q0[None], u0[None])
        else:
            starts = (jnp.concatenate([q0[None], nodes[0]]),
                      jnp.concatenate([u0[None], nodes[1]]))

        def segment(t, q_start, u_start):
            q, u = self.solve(params, inputs, q_start, u_start, t)
            observed = jax.vmap(self.observe, in_axes=(0, 0, 0, None))(t, q, u, p)
            return observed, q[-1], u[-1]

        if segments == 1:  # no vmap of one: it would batch the whole simulation once more
            observed, q_end, u_end = jax.tree_util.tree_map(
                lambda x: x[None], segment(t_segments[0], starts[0][0], starts[1][0]))
        else:
            observed, q_end, u_end = jax.vmap(segment)(t_segments, *starts)
        predicted = jnp.concatenate([
            observed[:, :length].reshape(segments * length, -1), observed[-1, length:]])
        gaps = None
        if nodes is not None:
            gaps = jnp.concatenate([(q_end[:-1] - nodes[0]).ravel(),
                                    (u_end[:-1] - nodes[1]).ravel()])
        return predicted, gaps

    def predictions(self, z):
        """Per group, the predicted observations (E, k, d) and continuity gaps (or None)."""
        params = self.params(z["params"])
        # A trial point of an optimiser may overflow a parameter (exp of a long step): its
        # residuals are then infinite, for the step to be rejected, rather than an error.
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in
                                    jax.tree_util.tree_leaves(params) if eqx.is_inexact_array(x)]))
        params = jax.tree_util.tree_map(
            lambda x: jnp.where(finite, x, jnp.ones_like(x)) if eqx.is_inexact_array(x) else x,
            params)
        states = self.initial_states(z)
        out = []
        for i, group in enumerate(self.groups):
            nodes = None if z["nodes"] is None else z["nodes"][i]
            q0, u0 = states[i]
            per_experiment = (group.ts, q0, u0, group.inputs, nodes)
            if group.ts.shape[1] > LONG_RECORD:
                predicted, gaps = jax.lax.map(
                    lambda x: self._segments(x[0], params, *x[1:]), per_experiment)
            elif group.ts.shape[0] == 1:  # no vmap of one: it would batch the simulation again
                ts, q0, u0, inputs, nodes = jax.tree_util.tree_map(lambda x: x[0],
                                                                   per_experiment)
                predicted, gaps = jax.tree_util.tree_map(
                    lambda x: x[None], self._segments(ts, params, q0, u0, inputs, nodes))
            else:
                predicted, gaps = jax.vmap(self._segments, in_axes=(0, None, 0, 0, 0, 0))(
                    group.ts, params, q0, u0, group.inputs, nodes)
            out.append((jnp.where(finite, predicted, jnp.inf), gaps))
        return out

    def evaluate(self, z):
        """(per group the predicted observations (E, k, d), r as one vector, the observation
        residuals alone)."""
        observation, continuity, predictions = [], [], []
        for group, (predicted, gaps) in zip(self.groups, self.predictions(z)):
            if predicted.shape != group.observations.shape:
                raise ValueError(
                    f"observe returns {predicted.shape[-1]} values per sample but the "
                    f"observations have {group.observations.shape[-1]} (experiments "
                    f"{list(group.indices)}).")
            predicted = predicted.astype(group.observations.dtype)  # (evaluation_structure)
            predictions.append(predicted)
            observation.append((group.sqrt_weights * (predicted - group.observations)).ravel())
            if gaps is not None:
                continuity.append(self.shooting.continuity_weight * gaps.ravel())
        observation = jnp.concatenate(observation)
        return predictions, jnp.concatenate([observation, *continuity]), observation

    def evaluation_structure(self, z):
        """(per group the predicted observations, r) as `jax.ShapeDtypeStruct`s, as `evaluate`
        returns them, from the shapes of the data and of z: tracing `evaluate` for its
        shapes would trace every simulation once more."""
        predictions = [jax.ShapeDtypeStruct(g.observations.shape, g.observations.dtype)
                       for g in self.groups]
        # r: the observation residuals, then the continuity gaps, one per node coordinate.
        size = sum(g.observations.size for g in self.groups) + sum(
            x.size for x in jax.tree_util.tree_leaves(z["nodes"]))
        dtype = jnp.result_type(*[g.observations.dtype for g in self.groups])
        return predictions, jax.ShapeDtypeStruct((size,), dtype)

    def residuals(self, z):
        """(r, observation residuals alone): r as one vector."""
        return self.evaluate(z)[1:]


def least_squares_residuals(z, problem: TrajectoryMatching):
    """r(z) for a least-squares solver, with (½‖r_observations‖², the predicted observations
    per group) as auxiliary output. A Gauss–Newton-type solver keeps the auxiliary output of
    its accepted iterate in its state, so the fit's predictions need no simulation of their
    own afterwards."""
    predictions, residuals, observation = problem.evaluate(z)
    return residuals, (0.5 * jnp.sum(observation**2), predictions)


def least_squares_residuals_forward(z, problem: TrajectoryMatching):
    """`least_squares_residuals` whose derivative is the Jacobian J = ∂r/∂z, formed once
    by forward mode (one batched pass with a column per unknown) and then applied as a
    matrix. A least-squares solver linearises r once per step and applies the linear map
    several times (to form and solve the damped Gauss–Newton system, for the predicted
    reduction, transposed for Jᵀr); each application of the lazily linearised simulation
    would cost about a pass of the tangent simulation, each application of J a matrix
    product."""
    flat, unravel = ravel_pytree(z)
    residuals, observation, predictions = _materialised(problem, flat, unravel)
    return residuals, (0.5 * jnp.sum(observation**2), predictions)


def _materialised(problem, flat, unravel):
    """(r, r_obs, the predictions per group) at the flat latent vector, differentiated
    through the whole Jacobian."""

    @jax.custom_jvp
    def evaluated(f):
        predictions, r, observation = problem.evaluate(unravel(f))
        return batch_axis_first((r, observation, predictions))

    @evaluated.defjvp
    def evaluated_jvp(primals, tangents):
        (f,), (df,) = primals, tangents
        (jacobian, jacobian_predictions), values = _jacobian(problem, unravel(f),
                                                             checks_as_nan_active())
        dr = jacobian @ df
        # r_obs is the leading block of r: its tangent is the leading block of dr.
        return batch_axis_first((values, (dr, dr[:values[1].size],
                                          [j @ df for j in jacobian_predictions])))

    return evaluated(flat)


@eqx.filter_jit
def _jacobian(problem: TrajectoryMatching, z, checks_as_nan: bool):
    """((∂r/∂f, ∂predictions/∂f), (r, r_obs, predictions)) at z, f = z raveled, by forward
    mode. Jitted, so that JAX traces it once per problem: an optimiser traces the
    linearisation of the residuals when it starts (for its state's shapes) and again in its
    step. `checks_as_nan`: the setting it is traced under (`jaxdyn._errors.checks_as_nan`),
    a static argument so that the two forms are cached apart."""
    f, unravel = ravel_pytree(z)

    def differentiated(f):  # what is differentiated, and every value, from the same pass
        predictions, r, observation = problem.evaluate(unravel(f))
        return (r, predictions), (r, observation, predictions)

    return jax.jacfwd(differentiated, has_aux=True)(f)


def output_structure(fn, problem: TrajectoryMatching, z):
    """(output, auxiliary output) of `fn(z, problem)`, one of the functions of this module,
    as `jax.ShapeDtypeStruct`s (`TrajectoryMatching.evaluation_structure`)."""
    predictions, r = problem.evaluation_structure(z)
    loss = jax.ShapeDtypeStruct((), r.dtype)
    return (loss if fn is scalar_loss else r), (loss, predictions)


def scalar_loss(z, problem: TrajectoryMatching):
    """½‖r(z)‖² for a minimiser (optax, BFGS), with auxiliary output as
    `least_squares_residuals`'."""
    predictions, residuals, observation = problem.evaluate(z)
    return 0.5 * jnp.sum(residuals**2), (0.5 * jnp.sum(observation**2), predictions)
