"""Uncertainty and identifiability at the optimum, from the Gauss–Newton approximation.

Near the optimum ẑ the residuals are r(z) ≈ r(ẑ) + J (z − ẑ), and with independent noise of
variance σ² (relative to the weights) the estimate is distributed approximately as

    cov(ẑ) = σ² (JᵀJ)⁻¹,   σ² = ‖r_obs‖² / (N − P),

N the number of weighted observations and P the number of fitted unknowns (less the continuity
conditions of multiple shooting, which remove as many as they add). With the columns of J
scaled to unit length, J D⁻¹ = U S Vᵀ: a relative singular value s_k/s_1 near zero is a
direction v_k in which the residuals do not change, a parameter or combination of parameters
the data cannot identify; it is reported by name and its parameters get infinite standard
errors. Parameters are reported in physical units: cov(x) = G cov(z) Gᵀ, G = ∂x/∂z.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax.flatten_util import ravel_pytree

from .residuals import TrajectoryMatching


class Uncertainty(eqx.Module):
    """Standard errors, correlations and identifiability of fitted parameters.

    **Fields:**

    - `names`: the fitted parameters' scalar entries, as `p['k']` or `p['I'][0, 1]`.
    - `standard_errors`: one per name (inf where the data cannot identify it).
    - `covariance`, `correlation`: over `names`.
    - `residual_variance`: σ², the weighted residual sum of squares per degree of freedom
      (about 1 when the weights are the inverse noise variances).
    - `degrees_of_freedom`: N − P.
    - `singular_values`: of the column-scaled Jacobian, relative to the largest (columns
      negligible next to the largest are left out and reported as unidentifiable).
    - `unidentifiable`: one sentence per direction the data cannot identify, naming the
      parameters (and initial states) involved; empty when all are identifiable.
    """

    names: tuple[str, ...]
    standard_errors: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    residual_variance: float
    degrees_of_freedom: int
    singular_values: np.ndarray
    unidentifiable: tuple[str, ...]


def latent_names(problem: TrajectoryMatching, z):
    """A name for every entry of the flattened latent vector (`flatten_latent`)."""
    params = problem.params(z["params"])
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    trained_paths = [path for (path, _), t in zip(leaves, problem.trained) if t]
    names = {"params": [], "states": [], "nodes": []}
    for path, latent in zip(trained_paths, z["params"]):
        base = "p" + jax.tree_util.keystr(path)
        names["params"].extend([base] if np.ndim(latent) == 0 else
                               [f"{base} (latent {i})" for i in range(np.size(latent))])
    for kind in ("states", "nodes"):
        if z[kind] is None:
            continue
        for group, (q, u) in zip(problem.groups, z[kind]):
            for label, x in (("q", q), ("u", u)):
                for index in np.ndindex(*np.shape(x)):
                    experiment = group.indices[index[0]]
                    if kind == "states":
                        what = f"initial {label}[{index[1]}]"
                    else:
                        what = f"shooting node {index[1] + 1} {label}[{index[2]}]"
                    names[kind].append(f"{what} of experiment {experiment}")
    return [name for key in LATENT_ORDER for name in names[key]]


LATENT_ORDER = ("params", "states", "nodes")


def flatten_latent(z):
    """(z as one vector, the inverse map): parameters first, then initial states, then
    shooting nodes."""
    flat, unravel = ravel_pytree(tuple(z[key] for key in LATENT_ORDER))
    return flat, lambda f: dict(zip(LATENT_ORDER, unravel(f)))


@eqx.filter_jit
def _linearisation(problem: TrajectoryMatching, z):
    """(J = ∂r/∂z, r, r_obs, G = ∂x/∂z_params, predictions) with z flattened, J in forward
    mode."""
    problem = eqx.tree_at(lambda p: p.adjoint, problem, diffrax.ForwardMode())
    flat, unravel = flatten_latent(z)
    physical = lambda f: ravel_pytree(problem.trained_leaves(  # noqa: E731
        problem.params(unravel(f)["params"])))[0]
    num_params = ravel_pytree(z["params"])[0].size
    def residuals(f):  # r, with the evaluation it came from (one pass for both)
        predictions, r_all, r_obs = problem.evaluate(unravel(f))
        return r_all, (r_all, r_obs, predictions)

    jacobian, (r_all, r_obs, predictions) = jax.jacfwd(residuals, has_aux=True)(flat)
    return (jacobian, r_all, r_obs, jax.jacfwd(physical)(flat)[:, :num_params], predictions)


@eqx.filter_jit
def _from_solver(problem: TrajectoryMatching, z, jac):
    """(J, G) of `_linearisation` from a least-squares solver's last linearisation at z: J
    materialised from the linear operator the solver formed (a matrix product: its Jacobian
    is already a residual of that linearisation, so it is not compiled a second time),
    columns in the order of `flatten_latent`."""
    matrix = jac.as_matrix()  # columns in the order of ravel_pytree(z)
    flat_z, unravel_z = ravel_pytree(z)
    position = jnp.arange(flat_z.size, dtype=flat_z.dtype)
    order = flatten_latent(unravel_z(position))[0].astype(int)
    flat, unravel = flatten_latent(z)
    physical = lambda f: ravel_pytree(problem.trained_leaves(  # noqa: E731
        problem.params(unravel(f)["params"])))[0]
    num_params = ravel_pytree(z["params"])[0].size
    return matrix[:, order], jax.jacfwd(physical)(flat)[:, :num_params]


def kept_evaluation(problem: TrajectoryMatching, state, z):
    """(J operator, r, r_obs, per group the predicted observations) at z, as a
    Gauss–Newton-type solver's state keeps them (optimistix keeps the linearisation and the
    residual function's auxiliary output of its accepted iterate, which is the iterate it
    returns), or None (another solver, or no step taken)."""
    f_info, aux = getattr(state, "f_info", None), getattr(state, "aux", None)
    if f_info is None or aux is None or bool(np.asarray(getattr(state, "first_step", True))):
        return None  # no step taken: the state holds a placeholder, not a linearisation
    jac, residual = getattr(f_info, "jac", None), getattr(f_info, "residual", None)
    if not isinstance(jac, lx.AbstractLinearOperator) or residual is None:
        return None
    if jax.tree_util.tree_structure(jac.in_structure()) != jax.tree_util.tree_structure(z):
        return None
    residual = np.asarray(residual)
    num_observations = sum(group.observations.size for group in problem.groups)
    # The observation residuals are r's leading block (`TrajectoryMatching.evaluate`).
    return jac, residual, residual[:num_observations], aux[1]


def analyse(problem: TrajectoryMatching, z, tolerance: float, state=None):
    """(the Gauss–Newton `Uncertainty` of the fit at z (forward-mode Jacobian), per group the
    predicted observations, ½‖r_obs‖², the residuals (r, r_obs)): one compiled evaluation,
    or none where `state` (a least-squares solver's final state) keeps the evaluation at z
    (`kept_evaluation`)."""
    kept = None if state is None else kept_evaluation(problem, state, z)
    if kept is None:
        *arrays, predictions = _linearisation(problem, z)
        jacobian, r_all, r_obs, g = (np.asarray(x) for x in arrays)
    else:
        jac, r_all, r_obs, predictions = kept
        jacobian, g = (np.asarray(x) for x in _from_solver(problem, z, jac))
    num_observations = int(sum(np.count_nonzero(np.asarray(group.sqrt_weights))
                               for group in problem.groups))
    num_continuity = r_all.size - r_obs.size
    dof = num_observations - (jacobian.shape[1] - num_continuity)
    variance = float(np.sum(r_obs**2) / dof) if dof > 0 else float("nan")

    # A column that is negligible next to the largest is an unknown the residuals do not see
    # (scaling it to unit length would only magnify round-off); the others are scaled to unit
    # length, so that the singular values do not depend on units.
    norms = np.linalg.norm(jacobian, axis=0)
    seen = norms > tolerance * np.max(norms)
    scale = np.where(seen, norms, 1.0)
    _, s, vt = np.linalg.svd(jacobian[:, seen] / scale[seen], full_matrices=False)
    relative = s / s[0]
    null = relative < tolerance
    inverse = np.where(null, 0.0, 1.0 / np.where(null, 1.0, s) ** 2)
    covariance_z = np.zeros((jacobian.shape[1],) * 2)
    covariance_z[np.ix_(seen, seen)] = (variance * (vt.T * inverse) @ vt
                                        / np.outer(scale[seen], scale[seen]))
    # The directions the data cannot identify, in all latent variables: each unseen unknown,
    # and each null right singular vector.
    directions = [(np.eye(jacobian.shape[1])[j], norms[j] / np.max(norms))
                  for j in np.nonzero(~seen)[0]]
    for k in np.nonzero(null)[0]:
        direction = np.zeros(jacobian.shape[1])
        direction[seen] = vt[k]
        directions.append((direction, relative[k]))

    num_params = g.shape[1]
    covariance = g @ covariance_z[:num_params, :num_params] @ g.T
    names = parameter_names(problem, z)
    names_z = latent_names(problem, z)
    unidentifiable = []
    undetermined = np.zeros(len(names), bool)
    for direction, size in directions:
        in_params = g @ (direction[:num_params] / scale[:num_params])
        if np.any(in_params):
            undetermined |= np.abs(in_params) > 1e-3 * np.max(np.abs(in_params))
        involved = np.nonzero(np.abs(direction) >= 0.1 * np.max(np.abs(direction)))[0]
        if len(involved) == 1:
            unidentifiable.append(
                f"The data cannot identify {names_z[involved[0]]}: the residuals do not "
                f"change with it (sensitivity {size:.1e} of the largest). Fix it, or add "
                "experiments that excite it.")
            continue
        terms = ", ".join(f"{names_z[i]} ({direction[i]:+.2f})" for i in involved)
        unidentifiable.append(
            f"The data cannot identify {_listing([names_z[i] for i in involved])} apart: the "
            f"residuals do not change along the combination {terms} of their scaled (for "
            f"positive parameters, relative) values (singular value {size:.1e} of the "
            "largest). Fix some of them, or add experiments that excite them differently.")
    errors = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    errors = np.where(undetermined, np.inf, errors)
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(errors, errors)
    correlation = np.where(undetermined[:, None] | undetermined[None, :]
                           | ~np.isfinite(correlation),
                           np.nan, correlation)
    report = Uncertainty(names=tuple(names), standard_errors=errors, covariance=covariance,
                         correlation=correlation, residual_variance=variance,
                         degrees_of_freedom=dof, singular_values=relative,
                         unidentifiable=tuple(unidentifiable))
    return report, predictions, 0.5 * float(np.sum(r_obs**2)), (r_all, r_obs)


def parameter_names(problem, z):
    """`p['k']`, `p['I'][0, 1]`, …: every scalar entry of the trained parameters, named by
    its path in the parameter tree."""
    params = problem.params(z["params"])
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    names = []
    for (path, leaf), trained in zip(leaves, problem.trained):
        if not trained:
            continue
        base = "p" + jax.tree_util.keystr(path)
        shape = np.shape(leaf)
        names.extend([base] if not shape else
                     [f"{base}[{', '.join(map(str, i))}]" for i in np.ndindex(*shape)])
    return names


def _listing(items):
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]
