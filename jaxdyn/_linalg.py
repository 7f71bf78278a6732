"""Solving M a = f for a symmetric positive definite mass matrix M."""

import jax.numpy as jnp
import jax.scipy.linalg as jsl

from ._errors import error_if_at_state

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

# Up to this size the Cholesky factorisation and substitutions are unrolled into scalar
# operations that XLA fuses; a LAPACK call per matrix costs more than the arithmetic for the
# small mass matrices of most mechanisms (benchmarks/bench_accelerations.py, vmap case).
UNROLL_MAX = 8


def _cholesky_unrolled(matrix):
    m = matrix.shape[0]
    factor = [[None] * m for _ in range(m)]
    for j in range(m):
        pivot = matrix[j, j] - sum(factor[j][k] ** 2 for k in range(j))
        factor[j][j] = jnp.sqrt(pivot)  # NaN when not positive definite
        for i in range(j + 1, m):
            dot = sum(factor[i][k] * factor[j][k] for k in range(j))
            factor[i][j] = (matrix[i, j] - dot) / factor[j][j]
    return factor


def _solve_unrolled(factor, rhs):
    m = len(factor)
    y = []
    for i in range(m):  # L y = f
        y.append((rhs[i] - sum(factor[i][k] * y[k] for k in range(i))) / factor[i][i])
    x = [None] * m
    for i in reversed(range(m)):  # Lᵀ x = y
        x[i] = (y[i] - sum(factor[k][i] * x[k] for k in range(i + 1, m))) / factor[i][i]
    return jnp.stack(x)


def solve_mass_matrix(mass_matrix, forcing, t, q, u):
    """a = M⁻¹ f by Cholesky, M = L Lᵀ.

    M is treated as singular when min(diag L)² ≤ m ε max|diag M| (or a pivot is NaN), which
    also catches matrices that are positive definite only by round-off. We factor ourselves
    (unrolled for small M, `jax.scipy` otherwise) rather than through `lineax.Cholesky`
    because the check needs the pivots.
    """
    m = mass_matrix.shape[-1]
    if m <= UNROLL_MAX:
        factor = _cholesky_unrolled(mass_matrix)
        pivots = jnp.stack([factor[i][i] for i in range(m)])
    else:
        factor, lower = jsl.cho_factor(mass_matrix, lower=True)
        pivots = jnp.diagonal(factor)
    eps = jnp.finfo(mass_matrix.dtype).eps
    scale = jnp.max(jnp.abs(jnp.diagonal(mass_matrix)))
    singular = ~jnp.all(jnp.isfinite(pivots)) | (jnp.min(pivots) ** 2 <= m * eps * scale)
    forcing = error_if_at_state(
        forcing, ~jnp.all(jnp.isfinite(forcing)), NONFINITE_FORCING, t, q, u
    )
    forcing = error_if_at_state(forcing, singular, SINGULAR_MASS_MATRIX, t, q, u)
    if m <= UNROLL_MAX:
        return _solve_unrolled(factor, forcing)
    return jsl.cho_solve((factor, lower), forcing)
