"""`fit_inertial_parameters`: a robot's inertial parameters from measured joint torques.

Inverse dynamics is linear in the links' inertial parameters, τ = Y(q, u, u̇) π (Atkeson, An
and Hollerbach, 1986), so identification from torque data is linear least squares over the
stacked regressor. Its unconstrained solution is often not a rigid body (a negative mass, an
inertia that breaks the triangle inequality) and fixes only the identifiable combinations of π.
Physical consistency holds exactly when each link's pseudo-inertia

    J = [[Σ, h], [hᵀ, m]],   Σ = ½ tr(I_O) 1 − I_O,  h = m c

is positive definite (Wensing, Kim and Slotine, 2017): a convex set in π, and the torque
residual is a convex quadratic, so the consistent estimate is the unique optimum of a convex
problem, found by the barrier method (−log det J keeps every iterate a rigid body) rather than
by a local search over a parametrisation of the set. A small pull towards the prior (CAD
values), acting only on the combinations of π that the torques do not see, settles those.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._form.newton_euler import (
    UPPER,
    inertia_at_origin,
    inertial_parameters,
    inverse_dynamics_regressor,
)
from .._system.tree import RigidBodyTree
from .._system.urdf import LinkParameter


class InertialFit(eqx.Module):
    """What `jaxdyn.fit_inertial_parameters` returns.

    **Fields:**

    - `params`: the prior parameters with each fitted link's `mass`, `com` and `inertia`
      (about the centre of mass) replaced by the physically consistent estimate.
    - `inertial_parameters`: π (N, 10) of the consistent estimate, every link of the tree
      (links not fitted keep the prior's), in `jaxdyn.inertial_parameters`' order.
    - `least_squares`: the unconstrained minimum-norm least-squares π (N, 10) (zero for links
      not fitted): the best torque fit, not necessarily a rigid body.
    - `links`: the names of the fitted links.
    - `rank`: the number of identifiable combinations of the fitted parameters (the numerical
      rank of the weighted regressor); `singular_values` its singular values.
    - `residual_rms`, `least_squares_rms`: the root mean square of the weighted torque
      residual √w (τ − Y π) of each estimate (≈ 1 when the weights are 1/σ² and the model
      explains the data).
    - `converged`, `num_steps`: the consistent fit's barrier method (Newton steps).
    """

    params: Any
    inertial_parameters: jax.Array
    least_squares: jax.Array
    links: tuple[str, ...]
    rank: int
    singular_values: np.ndarray
    residual_rms: float
    least_squares_rms: float
    converged: bool
    num_steps: int


def _pseudo_inertia(pi):
    """J (4, 4) from π (10,)."""
    inertia = inertia_at_origin(pi)
    second_moment = 0.5 * jnp.trace(inertia) * jnp.eye(3, dtype=pi.dtype) - inertia
    return jnp.block([[second_moment, pi[1:4, None]], [pi[None, 1:4], pi[None, :1]]])


def _from_pseudo_inertia(j):
    """π (10,) from J (4, 4)."""
    second_moment = j[:3, :3]
    inertia = jnp.trace(second_moment) * jnp.eye(3, dtype=j.dtype) - second_moment
    return jnp.concatenate([j[3:, 3], j[:3, 3], inertia[UPPER]])


def _physical(pi):
    """(mass, centre of mass, inertia about it) from one link's π."""
    mass, first_moment = pi[0], pi[1:4]
    com = first_moment / mass
    shift = mass * (jnp.dot(com, com) * jnp.eye(3, dtype=pi.dtype) - jnp.outer(com, com))
    inertia = inertia_at_origin(pi) - shift  # the parallel-axis theorem, backwards
    return mass, com, inertia


def _regressors(tree, q, u, ud, p, chunk):
    """Y over the samples, (k, m, 10 N), `chunk` states at a time (memory bounded by it)."""
    def one(state):
        q, u, ud = state
        return inverse_dynamics_regressor(tree, q, u, ud, p)

    return jax.lax.map(one, (q, u, ud), batch_size=min(chunk, q.shape[0]))


def _log_det(pi):
    """log det J(π) of one link."""
    return jnp.linalg.slogdet(_pseudo_inertia(pi))[1]


def _barrier_objective(pi, mu, problem):
    """½ ‖S Vᵀ π − c‖² + ½ w² ‖Vₙᵀ(π − π_prior)‖² − μ Σ log det J(πᵢ): convex in π, finite
    exactly inside the consistent set."""
    r_matrix, c, unseen, prior, pull, _ = problem
    residual, prior_residual = r_matrix @ pi - c, pull * (unseen @ (pi - prior))
    log_det = jax.vmap(_log_det)(pi.reshape(-1, 10))
    return 0.5 * (residual @ residual + prior_residual @ prior_residual) - mu * jnp.sum(log_det)


@jax.jit
def _newton_step(pi, mu, problem):
    """One damped Newton step on the barrier problem, halved until every link's pseudo-inertia
    stays positive definite and the objective falls (Armijo); returns the Newton decrement.
    The Hessian is the quadratic part's constant one plus the barrier's, block-diagonal by
    link (10 × 10 blocks)."""
    value, gradient = jax.value_and_grad(_barrier_objective)(pi, mu, problem)
    blocks = jax.vmap(jax.hessian(_log_det))(pi.reshape(-1, 10))
    hessian = problem[-1] - mu * jax.scipy.linalg.block_diag(*blocks)
    step = -jnp.linalg.solve(hessian, gradient)
    decrement = -gradient @ step

    def acceptable(alpha):
        trial = pi + alpha * step
        feasible = jnp.all(jnp.linalg.eigvalsh(jax.vmap(_pseudo_inertia)(
            trial.reshape(-1, 10)))[:, 0] > 0)
        sufficient = _barrier_objective(trial, mu, problem) <= value - 0.25 * alpha * decrement
        return feasible & sufficient

    alpha = jax.lax.while_loop(lambda a: (a > 1e-12) & ~acceptable(a), lambda a: 0.5 * a,
                               jnp.ones((), pi.dtype))
    return jnp.where(alpha > 1e-12, pi + alpha * step, pi), decrement


def _interior_point(problem, pi, tolerance, max_steps):
    """The barrier method (Boyd and Vandenberghe, Convex Optimization, §11.3): Newton's method
    on the barrier problem for μ falling tenfold per stage; the last stage's optimum is within
    4 N μ (the barrier's parameter) of the constrained optimum. Stops when that bound is
    below `tolerance` relative to the objective's scale."""
    scale = _barrier_objective(pi, 0.0, problem) + 1e-300
    links = pi.shape[0] // 10
    mu, steps = float(scale) / (4 * links), 0
    while True:
        for _ in range(50):
            pi, decrement = _newton_step(pi, jnp.asarray(mu, pi.dtype), problem)
            steps += 1
            if float(decrement) < 1e-3 * tolerance * float(scale) or steps >= max_steps:
                break
        if steps >= max_steps:
            return pi, False, steps
        if 4 * links * mu < tolerance * float(scale):
            return pi, True, steps
        mu /= 10.0


def fit_inertial_parameters(
    tree: RigidBodyTree,
    q,
    u,
    ud,
    tau,
    p,
    *,
    weights=None,
    links=None,
    prior_weight: float = 1e-8,
    tolerance: float = 1e-12,
    max_steps: int = 500,
    chunk: int = 256,
) -> InertialFit:
    r"""Identify a robot's inertial parameters from measured joint torques.

    Minimises the weighted torque residual over the links' inertial parameters π,

        ½ Σₖ ‖W^½ (τₖ − Y(qₖ, uₖ, u̇ₖ) π)‖² + ½ λ s² ‖Vₙᵀ(π − π_prior)‖²,

    once without constraints (the minimum-norm linear least squares, `least_squares`) and once
    over physically consistent bodies only: each link's pseudo-inertia J(πᵢ) = [[½ tr(I_O) 1 −
    I_O, m c], [m cᵀ, m]] positive definite (Wensing, Kim and Slotine, 2017), a convex problem
    solved by the barrier method from the prior (Newton steps on the objective − μ Σ log det
    J(πᵢ), μ falling tenfold per stage) on the reduced problem: with the SVD W^½ Y = U S Vᵀ of
    the stacked regressor, ‖W^½(τ − Y π)‖² = ‖S Vᵀ π − Uᵀ W^½ τ‖² + const, so a step costs
    (10 N)³ whatever the number of samples. Vₙ spans the combinations of π the regressor does
    not see (its null space),
    λ = `prior_weight` and s, the regressor's largest singular value: the pull settles what the
    data do not determine and, where the prior's unseen part cannot be completed into rigid
    bodies that fit the data, biases the fit by about λ relative.

    **Arguments:**

    - `tree`: the robot (e.g. from `jaxdyn.from_urdf(path)`); its joint forces, springs,
      dampers and loads are not part of the regressor, so give τ without them (or subtract
      them first).
    - `q` (k, n), `u` (k, m), `ud` (k, m): the measured (or filtered) states and
      accelerations; `tau` (k, m): the measured joint forces, in the tree's speed order.
    - `p`: the prior parameters (CAD values; gravity too where it is a parameter). The
      fitted links' mass, com and inertia must be read from p, as `from_urdf` does by default
      (`parameters=True`).
    - `weights`: None (all 1), or the inverse noise variances 1/σ², broadcastable to (k, m).
    - `links`: the names of the links to fit; by default every link the torques can see (a
      nonzero column of the regressor: links welded to a fixed base are left out).
    - `prior_weight`: λ above. `tolerance`: the barrier method stops when its bound on the
      distance to the optimum falls below this, relative to the objective at the prior;
      `max_steps`: at most that many Newton steps.
    - `chunk`: states per batch of regressors (bounds memory on long records).

    **Returns:** an `InertialFit`.
    """
    q, u, ud, tau = (jnp.asarray(x, dtype=float) for x in (q, u, ud, tau))
    if tau.ndim != 2 or tau.shape[1] != tree.num_speeds:
        raise ValueError(f"tau must have shape (k, {tree.num_speeds}) (one row of joint forces "
                         f"per sample), got {tau.shape}.")
    k, m = tau.shape
    for name, x, width in (("q", q, tree.num_coordinates), ("u", u, m), ("ud", ud, m)):
        if x.shape != (k, width):
            raise ValueError(f"{name} must have shape ({k}, {width}) to match tau, got "
                             f"{x.shape}.")
        if not bool(jnp.all(jnp.isfinite(x))):
            raise ValueError(f"{name} holds NaN or inf.")
    if not bool(jnp.all(jnp.isfinite(tau))):
        raise ValueError("tau holds NaN or inf.")
    root_weights = jnp.sqrt(jnp.broadcast_to(
        jnp.asarray(1.0 if weights is None else weights, dtype=float), (k, m)))
    if not bool(jnp.all(jnp.isfinite(root_weights))):
        raise ValueError("weights must be finite and non-negative.")

    names = [link.name for link in tree.links]
    unknown = sorted(set(links or ()) - set(names))
    if unknown:
        raise ValueError(f"links {unknown} are not in the tree (its links: {names}).")
    regressor = _regressors(tree, q, u, ud, p, chunk) * root_weights[:, :, None]
    regressor = regressor.reshape(k * m, len(names), 10)
    if links is None:
        seen = np.asarray(jnp.any(regressor != 0, axis=(0, 2)))
        links = [name for name, s in zip(names, seen) if s]
    fitted = np.array([names.index(name) for name in links])
    for index in fitted:
        link = tree.links[index]
        if not all(isinstance(getattr(link, key), LinkParameter)
                   for key in ("mass", "com", "inertia")):
            raise ValueError(f"link {link.name!r}'s mass, com and inertia must be read from p "
                             "to be fitted: load the robot with jaxdyn.from_urdf(path) "
                             "(parameters=True, the default).")

    prior = inertial_parameters(tree, p, dtype=q.dtype)
    a = regressor[:, fitted].reshape(k * m, 10 * len(fitted))
    b = (tau * root_weights).ravel() - regressor.reshape(k * m, -1) @ prior.ravel() \
        + a @ prior[fitted].ravel()  # the links not fitted keep the prior's torques
    # One SVD a = U S Vᵀ gives the rank, the minimum-norm least squares and the reduced
    # problem: ‖a π − b‖² = ‖S Vᵀ π − Uᵀ b‖² + const.
    left, singular, directions = jnp.linalg.svd(a, full_matrices=False)
    rank = int(np.sum(np.asarray(singular) > 1e-10 * float(singular[0])))
    c = left.T @ b
    least_squares = directions[:rank].T @ (c[:rank] / singular[:rank])
    r_matrix = singular[:, None] * directions
    unseen = directions[rank:]  # the combinations of π the torques do not see
    # A prior whose pseudo-inertia is singular (a massless link) is nudged inside the cone.
    pseudo = jax.vmap(_pseudo_inertia)(prior[fitted])
    nudge = 1e-9 * jnp.max(jnp.trace(pseudo, axis1=1, axis2=2)) * jnp.eye(4, dtype=q.dtype)[None]
    inside = np.linalg.eigvalsh(np.asarray(pseudo + nudge))[:, 0] > 0
    if not np.all(inside):
        raise ValueError(f"the prior of links {[links[i] for i in np.nonzero(~inside)[0]]} is "
                         "not a rigid body (its pseudo-inertia is not positive semi-definite): "
                         "give physically consistent prior masses, centres of mass and "
                         "inertias.")
    start = jax.vmap(_from_pseudo_inertia)(pseudo + nudge).ravel()
    pull = np.sqrt(prior_weight) * singular[0]
    quadratic = r_matrix.T @ r_matrix + pull**2 * unseen.T @ unseen  # its constant Hessian
    problem = (r_matrix, c, unseen, prior[fitted].ravel(), pull, quadratic)
    consistent, converged, num_steps = _interior_point(problem, start, tolerance, max_steps)
    consistent = consistent.reshape(-1, 10)

    estimate = prior.at[fitted].set(consistent)
    params = jax.tree_util.tree_map(lambda x: x, p)  # a copy: p itself stays the prior
    for index, pi in zip(fitted, consistent):
        link = tree.links[index]
        for key, value in zip(("mass", "com", "inertia"), _physical(pi)):
            parameter = getattr(link, key)
            params[parameter.link] = {**params[parameter.link], parameter.key: value}
    rms = lambda x: float(jnp.sqrt(jnp.mean((a @ x - b) ** 2)))  # noqa: E731
    return InertialFit(
        params=params,
        inertial_parameters=estimate,
        least_squares=jnp.zeros_like(prior).at[fitted].set(least_squares.reshape(-1, 10)),
        links=tuple(links),
        rank=rank,
        singular_values=np.asarray(singular),
        residual_rms=rms(consistent.ravel()),
        least_squares_rms=rms(least_squares),
        converged=converged,
        num_steps=num_steps,
    )
