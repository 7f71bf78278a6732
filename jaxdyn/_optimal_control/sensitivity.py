"""Derivatives of an optimal trajectory by the implicit function theorem, not by unrolling the
solver's iterations.

At an optimum z* = (x_1 … x_N, r_0 … r_{N−1}) with costates λ, the Lagrangian

    ℒ(z, λ, θ) = J(z, θ) + Σ_k λ_{k+1}ᵀ (F(x_k, r_k, θ) − x_{k+1}) + λ_0ᵀ (x̂_0 − x_0),

θ = (x̂_0, p, s) (s the problem's arrays: a tree's masses, a hold's positions), is
stationary: R(z, λ, θ) = (∇_z ℒ, ∇_λ ℒ) = 0. Differentiating,
(dz/dθ, dλ/dθ) = −[∇²_{zλ} ℒ]⁻¹ ∂R/∂θ, so a cotangent z̄ of the trajectory pulls back to

    θ̄ = vᵀ ∂R/∂θ,   [H Aᵀ; A 0] v = −(z̄, 0),

H the Hessian of the Lagrangian in z and A the dynamics' Jacobian. That system is the
optimality condition of a linear–quadratic problem, min ½ δzᵀ H δz + z̄ᵀ δz subject to the
linearised dynamics with no gaps and δx_0 = 0, solved by the same Riccati recursion as a step of
DDP (the dynamics' curvature weighted by λ included), its costates v_λ = V_x + V_xx δx. Inputs
held at a bound stay there (a fixed active set, δr = 0 for them): exact where the bounds are
strictly active. The costates come from one backward sweep at the optimum over the exact
expansion's derivatives, λ_N = ∇Φ, λ_k = ∇_x(Δt ℓ_k) + F_xᵀ λ_{k+1}.

Reference: S. Gould et al., "On differentiating parameterized argmin and argmax problems",
2016; B. Amos et al., "Differentiable MPC for end-to-end planning and control", NeurIPS 2018.
"""

import jax
import jax.numpy as jnp

from .riccati import backward_pass, linear_rollout
from .solver import expand, step_curvature


def costates(expansion):
    """λ_0 … λ_N at a feasible trajectory, from its exact expansion: λ_N = ∇Φ,
    λ_k = ∇_x(Δt ℓ_k) + F_xᵀ λ_{k+1}."""
    def node(lam, data):
        lx, fx = data
        lam = lx + fx.T @ lam
        return lam, lam

    final = expansion.terminal_x
    _, lams = jax.lax.scan(node, final, (expansion.lx, expansion.fx), reverse=True)
    return jnp.concatenate([lams, final[None]])


def lagrangian(problem, xs, rs, lams, x_init, p, num_q):
    """ℒ(z, λ, θ) of the module's docstring."""
    ts = problem.times(xs.dtype)
    reached = jax.vmap(problem.step, in_axes=(0, 0, 0, None, None))(ts[:-1], xs[:-1], rs, p,
                                                                     num_q)
    return (problem.cost(xs, rs, p, num_q) + jnp.sum(lams[1:] * (reached - xs[1:]))
            + lams[0] @ (x_init - xs[0]))


def pull_back(problem_of, theta, xs, rs, free, xs_bar, rs_bar, num_q):
    """θ̄ = (x̂_0̄, p̄, s̄): the cotangents of θ = (x̂_0, p, s), the initial state, the
    parameters and the problem's differentiated arrays s (`problem_of(s)` the problem), given
    those of the optimal trajectory (xs_bar (N+1, n), rs_bar (N, k))."""
    x_init, p, arrays = theta
    problem = problem_of(arrays)
    expansion = expand(problem, xs, rs, jnp.zeros_like(xs), p, num_q, exact=True)
    lams = costates(expansion)
    # The linear–quadratic problem of the adjoint: linear terms z̄, the exact Hessian of ℒ.
    expansion = expansion.__class__(
        fx=expansion.fx, fr=expansion.fr, lx=xs_bar[:-1], lr=rs_bar, lxx=expansion.lxx,
        lrr=expansion.lrr, lrx=expansion.lrx, terminal_x=xs_bar[-1],
        terminal_xx=expansion.terminal_xx, gaps=jnp.zeros_like(xs))
    # The dynamics' curvature weighted by the costates, every node at once (vectorised, not
    # inside the Riccati recursion's loop, whose body XLA would otherwise compile as one
    # function with every step's second derivatives in it).
    curvatures = jax.vmap(step_curvature, in_axes=(None, 0, 0, 0, 0, None, None))(
        problem, problem.times(xs.dtype)[:-1], xs[:-1], rs, lams[1:], p, num_q)
    gains = backward_pass(
        expansion, rs, None, None, jnp.zeros((), xs.dtype),
        second_order=lambda k, _: jax.tree_util.tree_map(lambda h: h[k], curvatures),
        free=free)
    dxs, drs, _, _ = linear_rollout(expansion, gains)
    v_lams = gains.value_x + jnp.einsum("kij,kj->ki", gains.value_xx, dxs)

    # θ̄ = vᵀ ∂R/∂θ = d/dε ∇_θ ℒ(z + ε v_z, λ + ε v_λ, θ): forward over reverse, which
    # compiles to a smaller program than the reverse of a directional derivative.
    def parameter_gradient(xs, rs, lams):
        return jax.grad(lambda theta: lagrangian(problem_of(theta[2]), xs, rs, lams, theta[0],
                                                 theta[1], num_q))(theta)

    return jax.jvp(parameter_gradient, (xs, rs, lams), (dxs, drs, v_lams))[1]
