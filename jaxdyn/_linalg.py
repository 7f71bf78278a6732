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


def solve_mass_matrix(mass_matrix, forcing, t, q, u):
    """a = M⁻¹ f by Cholesky, M = L Lᵀ.

    We factor with `jax.scipy` rather than `lineax.Cholesky` because the check needs the
    pivots: M is treated as singular when min(diag L)² ≤ m ε max|diag M|, which also catches
    matrices that are positive definite only by round-off.
    """
    m = mass_matrix.shape[-1]
    factor, lower = jsl.cho_factor(mass_matrix, lower=True)
    pivots = jnp.diagonal(factor)
    eps = jnp.finfo(mass_matrix.dtype).eps
    scale = jnp.max(jnp.abs(jnp.diagonal(mass_matrix)))
    singular = ~jnp.all(jnp.isfinite(pivots)) | (jnp.min(pivots) ** 2 <= m * eps * scale)
    forcing = error_if_at_state(
        forcing, ~jnp.all(jnp.isfinite(forcing)), NONFINITE_FORCING, t, q, u
    )
    forcing = error_if_at_state(forcing, singular, SINGULAR_MASS_MATRIX, t, q, u)
    return jsl.cho_solve((factor, lower), forcing)
