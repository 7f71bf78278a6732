"""Linearisation about an operating point, and what a linear model tells: modes, stability,
controllability and observability."""

import functools
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._compile import filter_jit
from ._dynamics import AbstractDynamics, equations_of_motion
from ._errors import error_if, reports_state
from ._form.controlled import find_controlled
from ._state import check_vector, numbers_as_arrays, under_a_trace

_NONFINITE = ("The linearisation is not finite: the equations of motion fail at the "
              "operating point (a singular mass matrix or non-finite forcing there).")


class LinearModel(eqx.Module):
    """The linearised equations δẋ = A δx + B δr, δy = C δx + D δr about an operating point
    (x*, r*), x = [q; u] (coordinates, then speeds).

    For a constrained system the state δx is a set of independent coordinates of the states
    the constraints allow (their tangent space): `basis` maps it to the full perturbation,
    δ[q; u] = basis δx, and `independent` says which entries of [q; u] δx holds (or None
    for an orthonormal basis of that tangent space).

    **Fields:** `A` (s, s), `B` (s, k), `C` (o, s), `D` (o, k), `basis` (n + m, s),
    `num_coordinates`: how many of the s states are coordinates (they come first, then
    speeds), `num_q`: n, the system's coordinates, `independent`.
    """

    A: Float[Array, "s s"]
    B: Float[Array, "s k"]
    C: Float[Array, "o s"]
    D: Float[Array, "o k"]
    basis: Float[Array, "nm s"]
    num_coordinates: int = eqx.field(static=True)
    num_q: int = eqx.field(static=True)
    independent: tuple[int, ...] | None = eqx.field(static=True, default=None)

    def eigenvalues(self):
        """The eigenvalues λ of A (complex), sorted by real part, largest first."""
        values = jnp.linalg.eigvals(self.A)
        return values[jnp.argsort(-values.real)]

    def modes(self) -> "Modes":
        """Natural frequencies, damping ratios and shapes from the eigenvalues of A: for each
        eigenvalue λ (one of each complex pair), ω_n = |λ|, ζ = −Re λ / |λ|, damped
        frequency |Im λ|, and its mode shape, the coordinate part of the eigenvector mapped
        to all coordinates (`basis`). Sorted by ω_n."""
        values, vectors = jnp.linalg.eig(self.A)
        full = self.basis.astype(vectors.dtype) @ vectors
        shapes = full[: self.num_q]
        # One of each complex-conjugate pair (Im λ ≥ 0); real eigenvalues stay.
        order = jnp.lexsort((jnp.abs(values), values.imag < 0))
        values, shapes = values[order], shapes[:, order]
        frequency = jnp.abs(values)
        damping = jnp.where(frequency > 0, -values.real / jnp.where(frequency > 0, frequency,
                                                                     1), 1.0)
        return Modes(eigenvalues=values, natural_frequencies=frequency,
                     damping_ratios=damping, damped_frequencies=jnp.abs(values.imag),
                     shapes=shapes, conjugate=values.imag < 0)

    def stability(self, tol: float | None = None) -> str:
        """"asymptotically stable" (every Re λ < −tol), "unstable" (some Re λ > tol) or
        "marginally stable" (the largest Re λ within tol of 0: a conservative system, or
        a free coordinate). `tol` defaults to √ε · max(1, |λ|max). Concrete values only."""
        values = jnp.linalg.eigvals(self.A)
        scale = max(1.0, float(jnp.max(jnp.abs(values))))
        tol = float(jnp.sqrt(jnp.finfo(self.A.dtype).eps)) * scale if tol is None else tol
        largest = float(jnp.max(values.real))
        if largest < -tol:
            return "asymptotically stable"
        return "unstable" if largest > tol else "marginally stable"

    def controllability_matrix(self):
        """[B, AB, …, A^{s−1}B] (Kalman)."""
        return _krylov(self.A, self.B)

    def observability_matrix(self):
        """[C; CA; …; CA^{s−1}] (Kalman)."""
        return _krylov(self.A.T, self.C.T).T

    def is_controllable(self, tol: float = 1e-9) -> bool:
        """Whether the controllability matrix has full rank s: its smallest singular value
        above `tol` times its largest, after scaling A to unit norm (so that the powers of
        A stay comparable). Concrete values only."""
        scale = _scale(self.A)
        return _full_rank(_krylov(self.A / scale, self.B), self.A.shape[0], tol)

    def is_observable(self, tol: float = 1e-9) -> bool:
        """Whether the observability matrix has full rank s (as `is_controllable`)."""
        scale = _scale(self.A)
        return _full_rank(_krylov(self.A.T / scale, self.C.T), self.A.shape[0], tol)


class Modes(eqx.Module):
    """Modes of a linear model (`LinearModel.modes`, `normal_modes`).

    **Fields:** `eigenvalues` λ; `natural_frequencies` ω_n (rad/s); `damping_ratios` ζ;
    `damped_frequencies` ω_d = |Im λ|; `shapes` (n, modes), the coordinate perturbations
    (columns); `conjugate`: True for the second eigenvalue of a complex pair (the first has
    Im λ ≥ 0 and carries the mode).
    """

    eigenvalues: Array
    natural_frequencies: Array
    damping_ratios: Array
    damped_frequencies: Array
    shapes: Array
    conjugate: Array


def _krylov(a, b):
    blocks, block = [], b
    for _ in range(a.shape[0]):
        blocks.append(block)
        block = a @ block
    return jnp.concatenate(blocks, axis=1)


def _scale(a):
    norm = float(jnp.max(jnp.abs(a)))
    return norm if norm > 0 else 1.0


def _full_rank(matrix, size, tol):
    if matrix.shape[1] == 0:
        return size == 0
    singular = jnp.linalg.svd(matrix, compute_uv=False)
    return bool(singular.shape[0] >= size and singular[size - 1] > tol * singular[0])


@reports_state
def linearise(dynamics: AbstractDynamics, t, q, u, p=None, r=None, *,
              output: Callable | None = None, independent=None) -> LinearModel:
    """The linear model δẋ = A δx + B δr, δy = C δx + D δr of `dynamics` about the
    operating point (t, q, u, r), by forward-mode autodiff of the equations of motion

        ẋ = F(x, r) = [K(q) u; M⁻¹ (f + B_r r)],   A = ∂F/∂x,   B = ∂F/∂r.

    Works for every formulation: a `jaxdyn.Controlled` system supplies the inputs r (None:
    the system's own inputs, r = 0 by default; a system without inputs gives B of width 0);
    nonholonomic systems are linearised in their own speeds (`IndependentSpeeds`, Gibbs–Appell
    or Kane with independent speeds); constrained systems (`Constrained`) in the tangent space
    of their constraints c(q, u) = 0 (`AbstractDynamics.state_constraints`): with a basis T of
    that space and a left inverse S (S T = I), A = S ∂F/∂x T. With `independent` (indices of
    the entries of [q; u] to keep, e.g. a crank angle and its rate) S selects them and
    T = N (S N)⁻¹ for any basis N, as when dependent coordinates are eliminated (the
    "Linearizer" of sympy.physics.mechanics); without it T is orthonormal (Tᵀ = S).

    `output`: y = h(t, q, u, r, p) (C = ∂h/∂x T, D = ∂h/∂r); None for y = x (C = I, D = 0).
    Pure JAX: `jax.vmap` it over operating points or parameters, differentiate it with
    respect to p. A non-finite linearisation (M singular at the point) is an error.

    Reference: the linearisation of Lagrange's equations about a motion, e.g. L. Meirovitch,
    *Methods of Analytical Dynamics* (1970), ch. 6; for constrained systems D. L. Peterson,
    G. Gede, M. Hubbard, "Symbolic linearization of equations of motion of constrained
    multibody systems", Multibody Syst. Dyn. 33 (2015).
    """
    q, u = check_vector(q, "q"), check_vector(u, "u")
    t, p, r = numbers_as_arrays((t, p, r), q.dtype)
    independent = None if independent is None else tuple(int(i) for i in independent)
    # The constraints' ranks (redundant constraints) decide the shapes of the model, so they
    # are read on the host, from a small compiled program, when the values are at hand;
    # inside the caller's trace the constraints are taken as independent.
    ranks = None
    if not under_a_trace():
        ranks = tuple(_rank(values, matrix_shape) for values, matrix_shape in zip(
            *_constraint_singular_values(dynamics, t, q, u, p)))
    return _linearise(dynamics, t, q, u, p, r, output, independent, ranks)


# One program per system, shapes, output function and ranks.
@functools.partial(filter_jit, checks_on_host=True)
def _linearise(dynamics, t, q, u, p, r, output, independent, ranks):
    t = jnp.asarray(t, q.dtype)
    n = q.shape[0]
    controlled = find_controlled(dynamics)
    if controlled is None:
        if r is not None:
            raise ValueError(f"r was given, but {type(dynamics).__name__} declares no inputs: "
                             "wrap it as jaxdyn.Controlled(dynamics, input_map).")
        r = jnp.zeros((0,), q.dtype)
    elif r is None:
        r = controlled.input_values(t, q, u, p)
    r = check_vector(jnp.asarray(r, q.dtype), "r") if jnp.ndim(r) else jnp.reshape(r, (1,))
    if controlled is not None and r.shape != (controlled.num_inputs(q, u, p),):
        raise ValueError(f"r must have shape ({controlled.num_inputs(q, u, p)},) (the input "
                         f"map's columns), got {r.shape}.")

    x = jnp.concatenate([q, u])
    a_full, b_full = state_jacobians(dynamics, t, q, u, p, r)
    basis, selection, num_coordinates = _tangent_space(dynamics, t, q, u, p, independent, ranks)
    a, b = selection @ a_full @ basis, selection @ b_full
    if output is None:
        c, d = jnp.eye(a.shape[0], dtype=q.dtype), jnp.zeros((a.shape[0], r.shape[0]), q.dtype)
    else:
        h = lambda x, r: jnp.atleast_1d(output(t, x[:n], x[n:], r, p))  # noqa: E731
        c_full, d = jax.jacfwd(h, argnums=(0, 1))(x, r)
        c = c_full @ basis
    # (both tied to the check: inside a caller's `jax.jit`, B read alone keeps it)
    a, b = error_if((a, b), [(~jnp.all(jnp.isfinite(a)) | ~jnp.all(jnp.isfinite(b)),
                              _NONFINITE)], (t, q, u))
    return LinearModel(A=a, B=b, C=c, D=d, basis=basis, num_coordinates=num_coordinates,
                       num_q=n, independent=independent)


@eqx.filter_jit  # traced once per system and shapes
def state_jacobians(dynamics, t, q, u, p, r):
    """(∂F/∂x, ∂F/∂r) of ẋ = F(x, r) = [q̇; u̇], x = [q; u], by forward mode; `r` of shape
    (0,) for a system without inputs."""
    n = q.shape[0]

    def field(x, r):
        driven = dynamics if r.shape[0] == 0 else dynamics.with_inputs(r)
        rates, accelerations, _, _ = equations_of_motion(driven, t, x[:n], x[n:], p)
        return jnp.concatenate([rates, accelerations])

    return jax.jacfwd(field, argnums=(0, 1))(jnp.concatenate([q, u]), r)


def _constraint_jacobians(dynamics, t, q, u, p):
    """(Φ, G_q, G_u): Φ = ∂φ/∂q of the position constraints, G_q = ∂g/∂q and G_u = ∂g/∂u of
    the velocity constraints; None for a system without constraints."""
    phi, g = jax.eval_shape(lambda: dynamics.state_constraints(t, q, u, p))
    if phi.shape[0] + g.shape[0] == 0:
        return None
    position = jax.jacfwd(lambda q: dynamics.state_constraints(t, q, u, p)[0])(q)
    g_q, g_u = jax.jacfwd(lambda q, u: dynamics.state_constraints(t, q, u, p)[1],
                          argnums=(0, 1))(q, u)
    return position, g_q, g_u


@filter_jit
def _constraint_singular_values(dynamics, t, q, u, p):
    """((σ(Φ), σ(G_u)), their matrices' shapes), or ((), ()) without constraints."""
    jacobians = _constraint_jacobians(dynamics, t, q, u, p)
    if jacobians is None:
        return (), ()
    position, _, g_u = jacobians
    return (tuple(jnp.linalg.svd(a, compute_uv=False) if a.shape[0] else jnp.zeros(0, a.dtype)
                  for a in (position, g_u)),
            (position.shape, g_u.shape))


def _rank(values, shape):
    """The numerical rank of a matrix of `shape` from its singular values (descending), at
    the relative tolerance max(shape) ε σ₁ (NumPy's `matrix_rank`)."""
    values = np.asarray(values)
    if values.size == 0:
        return 0
    tol = max(shape) * np.finfo(values.dtype).eps * max(float(values[0]), 1e-300)
    return int(np.sum(values > tol))


def _tangent_space(dynamics, t, q, u, p, independent, ranks):
    """(T, S, coordinates kept): a basis T of the perturbations δ[q; u] that the constraints
    allow, a left inverse S, and how many of the reduced states are coordinates; identities
    for a system without constraints. `ranks`: those of Φ and G_u, or None to take them as
    full (independent constraints).

    With Φ = ∂φ/∂q and the velocity constraints' G_q = ∂g/∂q, G_u = ∂g/∂u, the admissible
    perturbations are δq = N_q a (N_q spanning null Φ) and δu = −G_u⁺ G_q N_q a + N_u b
    (N_u spanning null G_u): T = [[N_q, 0], [−G_u⁺ G_q N_q, N_u]], coordinates first."""
    n, m = q.shape[0], u.shape[0]
    jacobians = _constraint_jacobians(dynamics, t, q, u, p)
    if jacobians is None:
        if independent is not None:
            raise ValueError("independent selects coordinates of a constrained system; "
                             f"{type(dynamics).__name__} has no constraints.")
        eye = jnp.eye(n + m, dtype=q.dtype)
        return eye, eye, n
    position, g_q, g_u = jacobians
    rank_q, rank_u = ranks if ranks is not None else (None, None)
    null_q, null_u = _null_space(position, rank_q), _null_space(g_u, rank_u)
    coupling = (-jnp.linalg.pinv(g_u) @ g_q @ null_q if g_u.shape[0]
                else jnp.zeros((m, null_q.shape[1]), q.dtype))
    basis = jnp.block([[null_q, jnp.zeros((n, null_u.shape[1]), q.dtype)],
                       [coupling, null_u]])
    if independent is None:
        return basis, basis.T, null_q.shape[1]
    kept = sum(i < n for i in independent)
    if len(independent) != basis.shape[1] or kept != null_q.shape[1]:
        raise ValueError(
            f"independent must name {null_q.shape[1]} coordinates (indices 0…{n - 1}) and "
            f"{null_u.shape[1]} speeds (indices {n}…{n + m - 1}) of [q; u], the states the "
            f"constraints leave free; got {list(independent)}.")
    selection = jnp.eye(n + m, dtype=q.dtype)[jnp.asarray(independent)]
    return basis @ jnp.linalg.inv(selection @ basis), selection, kept


def _null_space(matrix, rank=None):
    """An orthonormal basis (columns) of the null space of `matrix` (k, d) of rank `rank`
    (None: min(k, d)), by the SVD."""
    d = matrix.shape[1]
    if matrix.shape[0] == 0:
        return jnp.eye(d, dtype=matrix.dtype)
    _, _, vt = jnp.linalg.svd(matrix, full_matrices=True)
    return vt[min(matrix.shape) if rank is None else rank:].T


@reports_state
def normal_modes(dynamics: AbstractDynamics, t, q, p=None, r=None) -> Modes:
    """Undamped normal modes about an equilibrium q (speeds u = 0): the generalized symmetric
    eigenproblem

        K φ = ω² M φ,    K = −∂f/∂q (symmetrised),   M the mass matrix,

    solved as the symmetric eigenproblem of L⁻¹ K L⁻ᵀ with M = L Lᵀ. Frequencies ω = √(ω²);
    an unstable direction (ω² < 0) reports ω = −√(−ω²) (negative: the growth rate). Shapes
    are M-orthonormal (φᵀ M φ = I), sorted by ω². For systems whose speeds are the coordinate
    rates (Lagrange's equations, and Gibbs–Appell or Kane with u = q̇); a constrained or
    damped system: `linearise(...).modes()`.

    Reference: Lord Rayleigh, *The Theory of Sound* (1877), ch. 4; L. Meirovitch,
    *Fundamentals of Vibrations* (2001), §7.
    """
    q = check_vector(q, "q")
    t, p = numbers_as_arrays((t, p), q.dtype)
    return _normal_modes(dynamics, jnp.asarray(t, q.dtype), q, p, r)


# One program per system and shapes: new points and parameters reuse it.
@functools.partial(filter_jit, checks_on_host=True)
def _normal_modes(dynamics, t, q, p, r) -> Modes:
    u = jnp.zeros_like(q)
    if sum(x.shape[0] for x in jax.eval_shape(lambda: dynamics.state_constraints(t, q, u, p))):
        raise ValueError("normal_modes needs independent coordinates; for a constrained "
                         "system use jaxdyn.linearise(...).modes().")
    driven = dynamics if find_controlled(dynamics) is None or r is None else \
        dynamics.with_inputs(r)
    mass_matrix = driven.form_equations(t, q, u, p)[0]
    if mass_matrix.shape != (q.shape[0], q.shape[0]):
        raise ValueError("normal_modes needs as many speeds as coordinates (u = q̇).")
    stiffness = -jax.jacfwd(lambda q: driven.form_equations(t, q, u, p)[1])(q)
    stiffness = 0.5 * (stiffness + stiffness.T)
    lower = jnp.linalg.cholesky(mass_matrix)
    inverse = jax.scipy.linalg.solve_triangular(lower, jnp.eye(q.shape[0], dtype=q.dtype),
                                                lower=True)
    squared, vectors = jnp.linalg.eigh(inverse @ stiffness @ inverse.T)
    shapes = inverse.T @ vectors
    squared = error_if(squared, [(~jnp.all(jnp.isfinite(squared)), _NONFINITE)], (t, q, u))
    # √|ω²|, with a finite derivative at a zero frequency (a free coordinate).
    zero = squared == 0
    root = jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, jnp.abs(squared))))
    frequency = jnp.sign(squared) * root
    zeros = jnp.zeros_like(root)
    values = jnp.where(squared >= 0, jax.lax.complex(zeros, root), jax.lax.complex(root, zeros))
    return Modes(eigenvalues=values, natural_frequencies=frequency,
                 damping_ratios=jnp.zeros_like(frequency), damped_frequencies=frequency,
                 shapes=shapes, conjugate=jnp.zeros(frequency.shape, bool))
