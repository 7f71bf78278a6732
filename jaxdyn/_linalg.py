"""Solving M a = f for a symmetric positive definite mass matrix M."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import jax.scipy.linalg as jsl

SINGULAR_MASS_MATRIX = (
    "The mass matrix is singular or not positive definite, so the accelerations are not "
    "determined. Likely causes:\n"
    "  - a coordinate carries no inertia (a massless body, or a speed the kinetic energy does "
    "not depend on);\n"
    "  - the coordinates are redundant (two of them describe the same motion);\n"
    "  - the configuration is singular for this parametrisation (a coordinate singularity: "
    "gimbal lock of Euler angles, a spherical pendulum at the pole of its polar angle, r = 0 "
    "in polar coordinates); remedy: coordinates without a singularity there (quaternions, as "
    "in jaxdyn.Spherical and jaxdyn.Free joints; other angles), or Cartesian coordinates "
    "with constraints (jaxdyn.Constrained);\n"
    "  - a non-physical parameter (zero or negative mass or inertia);\n"
    "  - the kinetic energy is not convex in the speeds (wrong sign, or not quadratic)."
)

SINGULAR_CONSTRAINTS = (
    "The constraint Jacobian C (the rows of the holonomic constraints' velocity form and of the "
    "Pfaffian constraints, in the speeds) has lost rank here, so the multipliers are not "
    "determined. Likely causes:\n"
    "  - redundant constraints (one row a combination of others: a closed loop written twice, "
    "or a planar loop closed by more equations than it removes freedoms); pass "
    "redundant='least_squares' to take the minimum-norm multipliers;\n"
    "  - a singular configuration of the mechanism (a four-bar or slider-crank at a dead "
    "point, a linkage at a bifurcation), where the constraints stop fixing the motion: change "
    "the coordinates or the mechanism's dimensions, or stop short of that state."
)

NONFINITE_FORCING = (
    "The generalized forcing (the right-hand side of M a = f) contains NaN or inf. Likely "
    "causes: a NaN or inf in the state or parameters, or an energy, force or dissipation "
    "function that is not finite here (a division by zero, log or sqrt of a non-positive "
    "number)."
)

# Up to this size the factorisation is written out in scalar operations, which XLA fuses with
# the formation of M and f; a LAPACK call costs more than the whole arithmetic of a small
# system (benchmarks/bench_equations.py).
UNROLL_MAX = 8


class Factorisation(eqx.Module):
    """M = L D Lᵀ for a block-diagonal arrangement of M (one block when M is dense).

    Blocks of equal size are factored together, vectorised over the blocks. `groups`: per
    block size, the coordinates of each block (static, shape (blocks, size)); `factors`: per
    group either the unit lower-triangular L and the reciprocal pivots 1/D written out in
    scalar operations, or a LAPACK Cholesky factor C = L D^½ (blocks above `UNROLL_MAX`).
    `singular`: whether some pivot failed.
    """

    groups: tuple[tuple[tuple[int, ...], ...], ...] = eqx.field(static=True)
    factors: tuple
    written_out: tuple[bool, ...] = eqx.field(static=True)
    singular: jnp.ndarray


def factorise(mass_matrix, *, unrolled: bool, blocks=None) -> Factorisation:
    """Factor M, block by block if `blocks` (lists of coordinates) is given.

    With `unrolled` every block is written out in scalar operations (the caller evaluates the
    program as straight-line code); otherwise blocks up to `UNROLL_MAX` are, larger ones go to
    LAPACK. M counts as singular when a pivot D_j is not finite or
    min D_j ≤ m ε max_j |M_jj|, which also catches matrices that are positive definite only
    by round-off.
    """
    m = mass_matrix.shape[-1]
    blocks = [tuple(range(m))] if blocks is None else [tuple(b) for b in blocks]
    sizes = sorted({len(b) for b in blocks})
    groups = tuple(tuple(b for b in blocks if len(b) == size) for size in sizes)
    diagonal = jnp.stack([mass_matrix[i, i] for i in range(m)]) if unrolled \
        else jnp.diagonal(mass_matrix)
    threshold = m * jnp.finfo(mass_matrix.dtype).eps * jnp.max(jnp.abs(diagonal))
    factors, written_out, pivots = [], [], []
    for group in groups:
        index = np.asarray(group)
        sub = mass_matrix[None] if _whole(group, m) else \
            mass_matrix[index[:, :, None], index[:, None, :]]
        write_out = unrolled or index.shape[1] <= UNROLL_MAX
        if write_out:
            lower, group_pivots = ldl(sub)
            factors.append((lower, 1 / group_pivots))
        else:
            cholesky = jnp.linalg.cholesky(sub)
            group_pivots = jnp.diagonal(cholesky, axis1=-2, axis2=-1) ** 2
            factors.append(cholesky)
        written_out.append(write_out)
        pivots.append(group_pivots.reshape(-1))
    singular = ~jnp.all(jnp.concatenate(pivots) > threshold)  # also true for NaN pivots
    return Factorisation(groups, tuple(factors), tuple(written_out), singular)


def solve(factorisation: Factorisation, forcing):
    """a = M⁻¹ f from the factorisation; NaN where M is singular."""
    m = forcing.shape[-1]
    accelerations = None
    for group, factor, write_out in zip(factorisation.groups, factorisation.factors,
                                        factorisation.written_out):
        index = np.asarray(group)
        rhs = forcing[None] if _whole(group, m) else forcing[index]
        if write_out:
            x = ldl_solve(*factor, rhs)
        else:
            y = jsl.solve_triangular(factor, rhs[..., None], lower=True)
            x = jsl.solve_triangular(factor, y, lower=True, trans="T")[..., 0]
        if _whole(group, m):
            accelerations = x[0]
        else:
            if accelerations is None:
                accelerations = jnp.zeros_like(forcing)
            accelerations = accelerations.at[index].set(x)
    return jnp.where(factorisation.singular, jnp.nan, accelerations)


def _whole(group, m):
    return len(group) == 1 and group[0] == tuple(range(m))


def solve_mass_matrix(mass_matrix, forcing, *, unrolled: bool, blocks=None):
    """a = M⁻¹ f for symmetric positive definite M, with the failure flags.

    Returns (a, singular, nonfinite): a is NaN wherever M is singular or f not finite, so that
    a solver sees the failure without a branch; `singular` and `nonfinite` (boolean scalars)
    tell which, for error messages.
    """
    factorisation = factorise(mass_matrix, unrolled=unrolled, blocks=blocks)
    nonfinite = ~jnp.all(jnp.isfinite(forcing))
    accelerations = solve(factorisation, forcing)
    return jnp.where(nonfinite, jnp.nan, accelerations), factorisation.singular, nonfinite


def ldl(matrix):
    """M = L D Lᵀ written out entry by entry (no square roots), vectorised over leading axes.
    Returns (L as nested lists of entries, D stacked on the last axis)."""
    m = matrix.shape[-1]
    lower = [[None] * m for _ in range(m)]
    pivots, reciprocals = [], []
    for j in range(m):
        pivots.append(matrix[..., j, j]
                      - sum(lower[j][k] ** 2 * pivots[k] for k in range(j)))
        # One reciprocal per pivot, so that XLA does not split the computation at divisions.
        reciprocals.append(1 / pivots[j])
        for i in range(j + 1, m):
            dot = sum(lower[i][k] * lower[j][k] * pivots[k] for k in range(j))
            lower[i][j] = (matrix[..., i, j] - dot) * reciprocals[j]
    return tuple(tuple(row[:i]) for i, row in enumerate(lower)), jnp.stack(pivots, axis=-1)


def ldl_solve(lower, reciprocals, rhs):
    """x = L⁻ᵀ D⁻¹ L⁻¹ f entry by entry, vectorised over leading axes."""
    m = len(lower)
    y = []
    for i in range(m):  # L y = f
        y.append(rhs[..., i] - sum(lower[i][k] * y[k] for k in range(i)))
    x = [None] * m
    for i in reversed(range(m)):  # D Lᵀ x = y
        x[i] = (y[i] * reciprocals[..., i]
                - sum(lower[k][i] * x[k] for k in range(i + 1, m)))
    return jnp.stack(x, axis=-1)


def condition_number(mass_matrix):
    """κ(M) = λ_max / λ_min of a symmetric matrix, from its eigenvalues; ∞ where M is not
    positive definite."""
    eigenvalues = jnp.linalg.eigvalsh(mass_matrix)
    return jnp.where(eigenvalues[0] > 0, eigenvalues[-1] / eigenvalues[0], jnp.inf)
