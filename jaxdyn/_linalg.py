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
    "  - the configuration is singular for this parametrisation (e.g. gimbal lock of Euler "
    "angles, r = 0 in polar coordinates);\n"
    "  - a non-physical parameter (zero or negative mass or inertia);\n"
    "  - the kinetic energy is not convex in the speeds (wrong sign, or not quadratic)."
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

    `blocks`: the coordinates of each diagonal block (static); per block either the unit
    lower-triangular L and the reciprocal pivots 1/D written out as scalars (`unrolled`), or a
    LAPACK Cholesky factor C = L D^½. `singular`: whether some pivot failed.
    """

    blocks: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    factors: tuple
    unrolled: bool = eqx.field(static=True)
    singular: jnp.ndarray


def factorise(mass_matrix, *, unrolled: bool, blocks=None) -> Factorisation:
    """Factor M (block by block if `blocks` is given).

    M counts as singular when a pivot D_j is not finite or min D_j ≤ m ε max_j |M_jj|, which
    also catches matrices that are positive definite only by round-off.
    """
    m = mass_matrix.shape[-1]
    blocks = (tuple(range(m)),) if blocks is None else tuple(tuple(b) for b in blocks)
    diagonal = jnp.stack([mass_matrix[i, i] for i in range(m)]) if unrolled or m <= UNROLL_MAX \
        else jnp.diagonal(mass_matrix)
    threshold = m * jnp.finfo(mass_matrix.dtype).eps * jnp.max(jnp.abs(diagonal))
    factors, pivots = [], []
    write_out = unrolled or max(len(b) for b in blocks) <= UNROLL_MAX
    for block in blocks:
        sub = mass_matrix[np.ix_(block, block)] if len(blocks) > 1 else mass_matrix
        if write_out:
            lower, block_pivots = _ldl(sub)
            factors.append((lower, 1 / block_pivots))
        else:
            cholesky = jnp.linalg.cholesky(sub)
            block_pivots = jnp.diagonal(cholesky) ** 2
            factors.append(cholesky)
        pivots.append(block_pivots)
    pivots = jnp.concatenate(pivots)
    singular = ~jnp.all(pivots > threshold)  # also true for NaN pivots
    return Factorisation(blocks, tuple(factors), write_out, singular)


def solve(factorisation: Factorisation, forcing):
    """a = M⁻¹ f from the factorisation; NaN where M is singular."""
    single = len(factorisation.blocks) == 1
    accelerations = jnp.zeros_like(forcing) if not single else None
    for block, factor in zip(factorisation.blocks, factorisation.factors):
        rhs = forcing if single else forcing[np.asarray(block)]
        if factorisation.unrolled:
            x = _ldl_solve(*factor, rhs)
        else:
            x = jsl.cho_solve((factor, True), rhs)
        accelerations = x if single else accelerations.at[np.asarray(block)].set(x)
    return jnp.where(factorisation.singular, jnp.nan, accelerations)


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


def _ldl(matrix):
    """M = L D Lᵀ in scalar operations (no square roots). Returns (L as nested lists, D)."""
    m = matrix.shape[0]
    lower = [[None] * m for _ in range(m)]
    pivots, reciprocals = [], []
    for j in range(m):
        pivots.append(matrix[j, j] - sum(lower[j][k] ** 2 * pivots[k] for k in range(j)))
        # One reciprocal per pivot, so that XLA does not split the computation at divisions.
        reciprocals.append(1 / pivots[j])
        for i in range(j + 1, m):
            dot = sum(lower[i][k] * lower[j][k] * pivots[k] for k in range(j))
            lower[i][j] = (matrix[i, j] - dot) * reciprocals[j]
    return tuple(tuple(row[:i]) for i, row in enumerate(lower)), jnp.stack(pivots)


def _ldl_solve(lower, reciprocals, rhs):
    """x = L⁻ᵀ D⁻¹ L⁻¹ f in scalar operations."""
    m = len(lower)
    y = []
    for i in range(m):  # L y = f
        y.append(rhs[i] - sum(lower[i][k] * y[k] for k in range(i)))
    x = [None] * m
    for i in reversed(range(m)):  # D Lᵀ x = y
        x[i] = y[i] * reciprocals[i] - sum(lower[k][i] * x[k] for k in range(i + 1, m))
    return jnp.stack(x)
