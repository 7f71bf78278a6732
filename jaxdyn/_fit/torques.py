"""`fit_inertial_parameters`: a robot's inertial parameters from measured joint torques.

Inverse dynamics is linear in the links' inertial parameters, τ = Y(q, u, u̇) π (Atkeson, An
and Hollerbach, 1986), so identification from torque data is linear least squares over the
stacked regressor. Its unconstrained solution is often not a rigid body (a negative mass, an
inertia that breaks the triangle inequality) and fixes only the identifiable combinations of π
(the base parameters, `jaxdyn._fit.base_parameters`). Physical consistency holds exactly when
each link's pseudo-inertia

    J = [[Σ, h], [hᵀ, m]],   Σ = ½ tr(I_O) 1 − I_O,  h = m c

is positive definite (Wensing, Kim and Slotine, 2017). The consistent estimate adds to the
torque residual a small multiple of the log-det (Burg) divergence of each J from the prior's,
D(J ‖ J₀) = tr(J₀⁻¹ J) − log det(J₀⁻¹ J) − 4 (Lee, Wensing and Park, 2020): convex, infinite
on the boundary of the consistent set, so the optimum is a rigid body strictly inside it, and
what the torques do not determine is settled by the body closest to the prior in this
geometry, not pushed onto the edge of the set (a link's mass to zero).
"""

import warnings
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
from .._system.links import LinkParameter
from .base_parameters import PARAMETER_NAMES, BaseParameters, base_parameters


class ImplausibleEstimateWarning(UserWarning):
    """A fitted inertial parameter that is physically implausible (a mass far from the prior,
    a body at the edge of physical consistency) and what the data could not determine."""


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
    - `converged`, `num_steps`: whether Newton's method for the consistent estimate met its
      tolerance, and its steps.
    - `base_parameters`: the identifiable combinations of the fitted links' parameters
      (Gautier and Khalil's base parameters, `BaseParameters`): their combinations, values
      from least squares and standard errors, and which single parameters are identifiable.
    - `implausible`: the fitted links whose consistent estimate is physically implausible (a
      mass more than 10× from the prior's, or a body at the edge of consistency: its
      pseudo-inertia nearly singular), each with the reason; `fit_inertial_parameters` warns
      about them (`ImplausibleEstimateWarning`).

    `summary()` prints the fit, the base parameters and the implausible links.
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
    base_parameters: BaseParameters
    implausible: dict

    def summary(self) -> str:
        """The fit in a few lines: residuals, rank, the base parameters, the doubts."""
        lines = [f"{len(self.links)} links fitted ({', '.join(self.links)}): rank {self.rank} "
                 f"of {10 * len(self.links)}",
                 f"weighted residual RMS {self.residual_rms:.4g} (consistent), "
                 f"{self.least_squares_rms:.4g} (least squares); Newton "
                 f"{'converged' if self.converged else 'NOT converged'} in {self.num_steps} "
                 "steps",
                 self.base_parameters.summary()]
        lines += [f"implausible: {link}: {why}" for link, why in self.implausible.items()]
        return "\n".join(lines)


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


@eqx.filter_jit
def _regressors(tree, q, u, ud, root_weights, p, chunk):
    """The weighted regressors √w Y over the samples, (k m, N, 10), `chunk` states at a time
    (memory bounded by it), and which of the N links they see (a nonzero column). Compiled as
    one program, kept per tree and shapes: eager, the map over a new closure compiled its loop
    again at every call."""
    def one(state):
        q, u, ud = state
        return inverse_dynamics_regressor(tree, q, u, ud, p)

    regressor = jax.lax.map(one, (q, u, ud), batch_size=min(chunk, q.shape[0]))
    regressor = (regressor * root_weights[:, :, None]).reshape(q.shape[0] * u.shape[1],
                                                               len(tree.links), 10)
    return regressor, jnp.any(regressor != 0, axis=(0, 2))


@eqx.filter_jit
def _least_squares(tree, regressor, tau, root_weights, p, fitted):
    """The prior's π, and A π = b over the fitted links (`fitted`, a tuple of link indices)
    with the others at the prior's values, with A's thin SVD U S Vᵀ: one program (eager, each
    of its operations compiled apart)."""
    k, m = tau.shape
    fitted = np.asarray(fitted)
    prior = inertial_parameters(tree, p, dtype=tau.dtype)
    a = regressor[:, fitted].reshape(k * m, 10 * len(fitted))
    b = (tau * root_weights).ravel() - regressor.reshape(k * m, -1) @ prior.ravel() \
        + a @ prior[fitted].ravel()  # the links not fitted keep the prior's torques
    return prior, a, b, *jnp.linalg.svd(a, full_matrices=False)


# Compiled once for the module (eager, each of their operations compiled apart).
_pseudo_inertias = jax.jit(jax.vmap(_pseudo_inertia))
_physical_all = jax.jit(jax.vmap(_physical))


def _log_det(pi):
    """log det J(π) of one link."""
    return jnp.linalg.slogdet(_pseudo_inertia(pi))[1]


def _objective(pi, problem):
    """½ ‖S Vᵀ π − c‖² + Σᵢ wᵢ [tr(J₀ᵢ⁻¹ J(πᵢ)) − log det J(πᵢ)]: the torque residual and the
    log-det divergence from the prior (up to constants); convex in π, finite exactly inside
    the consistent set."""
    r_matrix, c, prior_inverse, weight, _ = problem
    residual = r_matrix @ pi - c
    pseudo = jax.vmap(_pseudo_inertia)(pi.reshape(-1, 10))
    divergence = (jnp.sum(prior_inverse * pseudo, axis=(1, 2))  # tr(J₀⁻¹ J), J₀⁻¹ symmetric
                  - jax.vmap(_log_det)(pi.reshape(-1, 10)))
    return 0.5 * residual @ residual + weight @ divergence


_objective_value = jax.jit(_objective)


@jax.jit
def _newton_step(pi, problem):
    """One damped Newton step, halved until every link's pseudo-inertia stays positive
    definite and the objective falls (Armijo); returns the Newton decrement and the value.
    The Hessian is the residual's constant one plus the divergence's, block-diagonal by link
    (10 × 10 blocks)."""
    value, gradient = jax.value_and_grad(_objective)(pi, problem)
    blocks = jax.vmap(jax.hessian(_log_det))(pi.reshape(-1, 10))
    hessian = problem[-1] - jax.scipy.linalg.block_diag(*(problem[3][:, None, None] * blocks))
    step = -jnp.linalg.solve(hessian, gradient)
    decrement = -gradient @ step

    def acceptable(alpha):
        trial = pi + alpha * step
        feasible = jnp.all(jnp.linalg.eigvalsh(jax.vmap(_pseudo_inertia)(
            trial.reshape(-1, 10)))[:, 0] > 0)
        sufficient = _objective(trial, problem) <= value - 0.25 * alpha * decrement
        return feasible & sufficient

    alpha = jax.lax.while_loop(lambda a: (a > 1e-12) & ~acceptable(a), lambda a: 0.5 * a,
                               jnp.ones((), pi.dtype))
    return jnp.where(alpha > 1e-12, pi + alpha * step, pi), decrement, value


def _newton(problem, pi, tolerance, max_steps):
    """Damped Newton's method from the prior (Boyd and Vandenberghe, Convex Optimization,
    §9.5): stops when half the squared Newton decrement, which bounds the distance to the
    optimum near it, falls below `tolerance` relative to the objective's scale."""
    scale = abs(float(_objective_value(pi, problem))) + 1e-300
    for steps in range(1, max_steps + 1):
        pi, decrement, _ = _newton_step(pi, problem)
        if 0.5 * float(decrement) < tolerance * scale:
            return pi, True, steps
    return pi, False, max_steps


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
    prior_weight: float = 1e-10,
    tolerance: float = 1e-12,
    max_steps: int = 500,
    chunk: int = 256,
) -> InertialFit:
    r"""Identify a robot's inertial parameters from measured joint torques.

    Minimises the weighted torque residual over the links' inertial parameters π,

        ½ Σₖ ‖W^½ (τₖ − Y(qₖ, uₖ, u̇ₖ) π)‖² + Σᵢ wᵢ D(J(πᵢ) ‖ J₀ᵢ),

    once without the second term (the minimum-norm linear least squares, `least_squares`)
    and once with it: D(J ‖ J₀) = tr(J₀⁻¹ J) − log det(J₀⁻¹ J) − 4 is the log-det divergence
    of link i's pseudo-inertia J(πᵢ) = [[½ tr(I_O) 1 − I_O, m c], [m cᵀ, m]] from the prior's
    J₀ᵢ (Lee, Wensing and Park, 2020). It is finite exactly for rigid bodies (J positive
    definite; Wensing, Kim and Slotine, 2017) and convex, so the estimate is the unique
    optimum of a convex problem, found by damped Newton steps from the prior, always a rigid
    body, and what the torques do not determine is taken from the closest body to the prior
    rather than from the edge of the consistent set. The weights wᵢ = λ s² ‖J₀ᵢ‖²_F (λ =
    `prior_weight`, s the largest singular value of the weighted regressor) make the pull λ
    relative to the best-determined combination: negligible where the torques see π, decisive
    where they do not. Steps run on the reduced problem: with the SVD W^½ Y = U S Vᵀ of the
    stacked regressor, ‖W^½(τ − Y π)‖² = ‖S Vᵀ π − Uᵀ W^½ τ‖² + const, so a step costs
    (10 N)³ whatever the number of samples.

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
    - `links`: the names of the links to fit; by default every link on a moving joint that
      the torques can see (a nonzero column of the regressor), one per joint as in Pinocchio's
      regressor: the links welded to them by fixed joints (sensors, tool frames, covers) keep
      the prior's parameters, and the moving link takes up what the welded body as a whole
      needs. Name welded links to fit them too (their split with the moving link is then
      not identifiable: see `InertialFit.base_parameters`).
    - `prior_weight`: λ above. `tolerance`: Newton's method stops when half its squared
      decrement (≈ the distance to the optimum in objective) falls below this, relative to
      the objective at the prior; `max_steps`: at most that many Newton steps.
    - `chunk`: states per batch of regressors (bounds memory on long records).

    **Returns:** an `InertialFit`.
    """
    q, u, ud, tau, root_weights = _checked_records(tree, q, u, ud, tau, weights)
    k, m = tau.shape
    names = [link.name for link in tree.links]
    unknown = sorted(set(links or ()) - set(names))
    if unknown:
        raise ValueError(f"links {unknown} are not in the tree (its links: {names}).")
    regressor, seen = _regressors(tree, q, u, ud, root_weights, p, chunk)
    if links is None:
        seen = np.asarray(seen)
        links = [link.name for link, s in zip(tree.links, seen) if s and link.joint.nv]
    fitted = np.array([names.index(name) for name in links])
    for index in fitted:
        link = tree.links[index]
        if not all(isinstance(getattr(link, key), LinkParameter)
                   for key in ("mass", "com", "inertia")):
            raise ValueError(f"link {link.name!r}'s mass, com and inertia must be read from p "
                             "to be fitted: load the robot with jaxdyn.from_urdf(path) "
                             "(parameters=True, the default).")

    # One SVD a = U S Vᵀ gives the rank, the minimum-norm least squares and the reduced
    # problem: ‖a π − b‖² = ‖S Vᵀ π − Uᵀ b‖² + const.
    prior, a, b, left, singular, directions = _least_squares(
        tree, regressor, tau, root_weights, p, tuple(int(i) for i in fitted))
    rank = int(np.sum(np.asarray(singular) > 1e-10 * float(singular[0])))
    c = left.T @ b
    least_squares = directions[:rank].T @ (c[:rank] / singular[:rank])
    base = base_parameters(a, b, rank, links, directions[rank:])
    consistent, converged, num_steps = _consistent(
        singular[:, None] * directions, c, singular[0], prior[fitted], links, prior_weight,
        tolerance, max_steps)
    implausible = _implausible(consistent, prior[fitted], links, base.identifiable)
    if implausible:
        warnings.warn("physically implausible estimates: " + "; ".join(
            f"{link}: {why}" for link, why in implausible.items()) + ". Fix what the data "
            "cannot determine (leave the link out with links=[...], or excite the joints that "
            "move it) or give a closer prior.", ImplausibleEstimateWarning, stacklevel=2)
    rms = lambda x: float(jnp.sqrt(jnp.mean((a @ x - b) ** 2)))  # noqa: E731
    return InertialFit(
        params=_with_estimates(tree, p, fitted, consistent),
        inertial_parameters=prior.at[fitted].set(consistent),
        least_squares=jnp.zeros_like(prior).at[fitted].set(least_squares.reshape(-1, 10)),
        links=tuple(links),
        rank=rank,
        singular_values=np.asarray(singular),
        residual_rms=rms(consistent.ravel()),
        least_squares_rms=rms(least_squares),
        converged=converged,
        num_steps=num_steps,
        base_parameters=base,
        implausible=implausible,
    )


def _checked_records(tree, q, u, ud, tau, weights):
    """(q, u, u̇, τ, √w) as float arrays of matching shapes, finite, the weights broadcast to
    τ's shape (k, m)."""
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
    return q, u, ud, tau, root_weights


def _consistent(r_matrix, c, largest, prior, links, prior_weight, tolerance, max_steps):
    """The consistent estimate π (L, 10) of the fitted links, minimising ½ ‖R π − c‖² plus
    the weighted log-det divergences from the prior's pseudo-inertias (`_objective`), by
    Newton's method from the prior; with whether it converged and its steps."""
    start = _nudged_pseudo_inertias(prior)
    inside = np.linalg.eigvalsh(np.asarray(start))[:, 0] > 0
    if not np.all(inside):
        raise ValueError(f"the prior of links {[links[i] for i in np.nonzero(~inside)[0]]} is "
                         "not a rigid body (its pseudo-inertia is not positive semi-definite): "
                         "give physically consistent prior masses, centres of mass and "
                         "inertias.")
    problem, pi = _problem(r_matrix, c, largest, start, prior_weight)
    consistent, converged, num_steps = _newton(problem, pi, tolerance, max_steps)
    return consistent.reshape(-1, 10), converged, num_steps


@jax.jit
def _nudged_pseudo_inertias(prior):
    """The prior's pseudo-inertias J₀ (L, 4, 4); one that is singular (a massless link) is
    nudged inside the cone."""
    pseudo = _pseudo_inertias(prior)
    scale = jnp.max(jnp.trace(pseudo, axis1=1, axis2=2))
    return pseudo + 1e-9 * scale * jnp.eye(4, dtype=prior.dtype)[None]


@jax.jit
def _problem(r_matrix, c, largest, start, prior_weight):
    """`_objective`'s data (R, c, J₀⁻¹, the weights, RᵀR) and Newton's starting π."""
    weight = prior_weight * largest ** 2 * jnp.sum(start**2, axis=(1, 2))
    problem = (r_matrix, c, jnp.linalg.inv(start), weight, r_matrix.T @ r_matrix)
    return problem, jax.vmap(_from_pseudo_inertia)(start).ravel()


def _with_estimates(tree, p, fitted, estimates):
    """A copy of `p` with each fitted link's mass, centre of mass and central inertia taken
    from its estimate π."""
    params = jax.tree_util.tree_map(lambda x: x, p)  # a copy: p itself stays the prior
    physical = _physical_all(estimates)
    for i, index in enumerate(fitted):
        link = tree.links[index]
        for key, value in zip(("mass", "com", "inertia"), (x[i] for x in physical)):
            parameter = getattr(link, key)
            params[parameter.link] = {**params[parameter.link], parameter.key: value}
    return params


def _implausible(estimate, prior, links, identifiable) -> dict:
    """{link: why} for estimates a long way from the prior's mass or at the edge of physical
    consistency (the smallest eigenvalue of the pseudo-inertia below 10⁻⁶ of its trace),
    naming the link's parameters the data do not determine."""
    estimate, prior = np.asarray(estimate), np.asarray(prior)
    pseudo = np.asarray(_pseudo_inertias(jnp.asarray(estimate)))
    eigenvalues = np.linalg.eigvalsh(pseudo)
    found = {}
    for i, link in enumerate(links):
        reasons = []
        mass, prior_mass = estimate[i, 0], prior[i, 0]
        if prior_mass > 0 and not 0.1 < mass / prior_mass < 10:
            reasons.append(f"mass {mass:.3g} against the prior's {prior_mass:.3g}")
        if eigenvalues[i, 0] < 1e-6 * np.sum(eigenvalues[i]):
            reasons.append("at the edge of physical consistency (its mass lies on a plane, "
                           "a line or a point)")
        if reasons:
            unseen = [name for name, seen in zip(PARAMETER_NAMES, identifiable[i]) if not seen]
            if unseen:
                reasons.append("not identifiable alone: " + ", ".join(unseen))
            found[link] = ", ".join(reasons)
    return found
