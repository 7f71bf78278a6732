"""Small linear systems solved in the program's own operations: M a = f for a symmetric
positive definite mass matrix M (LDLᵀ), and square systems by Gaussian elimination with
partial pivoting (`PivotedLU`, for Newton's method)."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
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
# the formation of M and f; a library call, or a loop over columns, costs more than the whole
# arithmetic of a small system (benchmarks/bench_equations.py).
UNROLL_MAX = 8


class Factorisation(eqx.Module):
    """M = L D Lᵀ for a block-diagonal arrangement of M (one block when M is dense).

    Blocks of equal size are factored together, vectorised over the blocks. `groups`: per
    block size, the coordinates of each block (static, shape (blocks, size)); `factors`: per
    group the unit lower-triangular L and the reciprocal pivots 1/D, either written out in
    scalar operations (nested lists, `written_out`) or, for blocks above `UNROLL_MAX`, as
    arrays formed one column at a time (`ldl_by_columns`). `singular`: whether some pivot
    failed.
    """

    groups: tuple[tuple[tuple[int, ...], ...], ...] = eqx.field(static=True)
    factors: tuple
    written_out: tuple[bool, ...] = eqx.field(static=True)
    singular: jnp.ndarray


def factorise(mass_matrix, *, unrolled: bool, blocks=None) -> Factorisation:
    """Factor M, block by block if `blocks` (lists of coordinates) is given.

    With `unrolled` every block is written out in scalar operations (the caller evaluates the
    program as straight-line code); otherwise blocks up to `UNROLL_MAX` are, larger ones are
    factored column by column (`ldl_by_columns`). A pivot fails when D_j ≤ m ε max_k |M_kk|
    (over the block, of size m) or is not finite, which also catches matrices that are
    positive definite only by round-off (a coordinate singularity approached: M = diag(1,
    sin² θ) near the pole). `singular` says whether some pivot failed.
    """
    m = mass_matrix.shape[-1]
    blocks = [tuple(range(m))] if blocks is None else [tuple(b) for b in blocks]
    sizes = sorted({len(b) for b in blocks})
    groups = tuple(tuple(b for b in blocks if len(b) == size) for size in sizes)
    factors, written_out, failed = [], [], []
    for group in groups:
        index = np.asarray(group)
        sub = mass_matrix[None] if _whole(group, m) else \
            mass_matrix[index[:, :, None], index[:, None, :]]
        write_out = unrolled or index.shape[1] <= UNROLL_MAX
        if write_out:
            lower, reciprocals, group_failed = ldl(sub)
            factors.append((lower, reciprocals))
        else:
            lower, reciprocals, group_failed = ldl_by_columns(sub)
            factors.append((lower, reciprocals))
        written_out.append(write_out)
        failed.append(group_failed.reshape(-1))
    singular = jnp.any(jnp.concatenate(failed))
    return Factorisation(groups, tuple(factors), tuple(written_out), singular)


def _threshold(diagonal):
    """m ε max_j |M_jj|: a pivot at or below it has been cancelled to round-off of M's scale."""
    largest = jnp.abs(diagonal[0])
    for entry in diagonal[1:]:
        largest = jnp.maximum(largest, jnp.abs(entry))
    return len(diagonal) * jnp.finfo(largest.dtype).eps * largest


def solve(factorisation: Factorisation, forcing) -> jax.Array:
    """a = M⁻¹ f from the factorisation.

    Where a pivot failed, the entries of a that depend on it are NaN (written-out blocks:
    through the NaN reciprocal pivot, without coupling the other entries, so that XLA does
    not recompute every entry's inputs for every entry); blocks factored by columns are NaN
    whole."""
    m = forcing.shape[-1]
    accelerations: jax.Array | None = None
    for group, factor, write_out in zip(factorisation.groups, factorisation.factors,
                                        factorisation.written_out):
        index = np.asarray(group)
        rhs = forcing[None] if _whole(group, m) else forcing[index]
        lower, reciprocals = factor
        x = (ldl_solve if write_out else ldl_by_columns_solve)(lower, reciprocals, rhs)
        if _whole(group, m):
            accelerations = x[0]
        else:
            if accelerations is None:
                accelerations = jnp.zeros_like(forcing)
            accelerations = accelerations.at[index].set(x)
    assert accelerations is not None  # `factorise` makes at least one group (at trace time)
    if not all(factorisation.written_out):
        accelerations = jnp.where(factorisation.singular, jnp.nan, accelerations)
    return accelerations


def small_solve(matrix, rhs) -> jax.Array:
    """x = A⁻¹ b for a small square A (not necessarily symmetric) by Householder QR,
    A = Q R, x = R⁻¹ Qᵀ b: backward stable like LU with partial pivoting, and free of the
    loop that turns LU's pivots into a permutation, which XLA compiles separately at each
    of the dozens of places a hybrid solve inlines the contacts' small systems (Delassus
    matrices, impact and friction laws; a ball's unilateral contact: 2.1 → 1.6 s of XLA).
    Not `lu_factor` written out either: the hybrid tests took 8% longer with it."""
    q, r = jnp.linalg.qr(matrix)
    column = rhs.ndim == matrix.ndim - 1
    b = rhs[..., None] if column else rhs
    x = jsl.solve_triangular(r, jnp.swapaxes(q, -1, -2) @ b, lower=False)
    return x[..., 0] if column else x


def _whole(group, m):
    return len(group) == 1 and group[0] == tuple(range(m))


def solve_mass_matrix(mass_matrix, forcing, *, unrolled: bool, blocks=None):
    """a = M⁻¹ f for symmetric positive definite M, with the failure flags.

    Returns (a, singular, nonfinite): the entries of a that depend on a failed pivot of M or
    on a non-finite entry of f are NaN, so that a solver sees the failure without a branch;
    `singular` and `nonfinite` (boolean scalars) tell which, for error messages.
    """
    factorisation = factorise(mass_matrix, unrolled=unrolled, blocks=blocks)
    finite = jnp.isfinite(forcing)
    # Entry by entry (inf would not always reach the solution as NaN): no coupling.
    accelerations = solve(factorisation, jnp.where(finite, forcing, jnp.nan))
    return accelerations, factorisation.singular, ~jnp.all(finite)


def ldl(matrix):
    """M = L D Lᵀ written out entry by entry (no square roots), vectorised over leading axes.

    Returns (L as nested lists of entries, the reciprocal pivots 1/D_j, which pivots failed),
    the last two stacked on the last axis. A failed pivot (D_j ≤ m ε max_k |M_kk|, or not
    finite) has a NaN reciprocal, which reaches exactly the entries of L, and of a solution, that
    depend on it.
    """
    m = matrix.shape[-1]
    threshold = _threshold([matrix[..., j, j] for j in range(m)])
    lower = [[None] * m for _ in range(m)]
    pivots, reciprocals, failed = [], [], []
    for j in range(m):
        pivots.append(matrix[..., j, j]
                      - sum(lower[j][k] ** 2 * pivots[k] for k in range(j)))
        ok = pivots[j] > threshold  # False for NaN
        failed.append(~ok)
        # One reciprocal per pivot, so that XLA does not split the computation at divisions.
        reciprocals.append(jnp.where(ok, 1 / pivots[j], jnp.nan))
        for i in range(j + 1, m):
            dot = sum(lower[i][k] * lower[j][k] * pivots[k] for k in range(j))
            lower[i][j] = (matrix[..., i, j] - dot) * reciprocals[j]
    return (tuple(tuple(row[:i]) for i, row in enumerate(lower)),
            jnp.stack(reciprocals, axis=-1), jnp.stack(failed, axis=-1))


def ldl_solve(lower, reciprocals, rhs):
    """x = L⁻ᵀ D⁻¹ L⁻¹ f entry by entry, vectorised over leading axes."""
    m = len(lower)
    y = []
    for i in range(m):  # L y = f
        y.append(rhs[..., i] - sum(lower[i][k] * y[k] for k in range(i)))
    x: list[Any] = [None] * m
    for i in reversed(range(m)):  # D Lᵀ x = y
        x[i] = (y[i] * reciprocals[..., i]
                - sum(lower[k][i] * x[k] for k in range(i + 1, m)))
    return jnp.stack(x, axis=-1)


def ldl_by_columns(matrix):
    """M = L D Lᵀ one column at a time, vectorised over leading axes:

        D_j = M_jj − Σ_{k<j} L_jk² D_k,   L_ij = (M_ij − Σ_{k<j} L_ik L_jk D_k) / D_j   (i > j),

    a loop of m steps of vector work (Golub and Van Loan, Matrix Computations, § 4.1), whose
    program does not grow with m: for blocks too large to write out entry by entry (a chain
    of 20 rods from T and V, 5 s simulated: first call 3.4 s, then 311 ms, against 3.1 s and
    330 ms by LAPACK; the columns written out as straight-line code 5 s and 324 ms; a tree
    chain of 20 by Kane's equations compiles longer, 9 s against 5.5). Not
    LAPACK's Cholesky: jaxlib 0.10's batched LAPACK kernels split a large batch over XLA's
    intra-op thread pool and block until it is done, so that two such kernels running at once
    in one program (a solve and its derivative's, under `jax.vmap`) can each hold a thread
    the other waits for, and the program never returns (`lapack_dtrsm_ffi` in
    `jax::ParallelBatchMap`, seen on a 2-core machine). Returns (L (…, m, m) unit lower
    triangular, 1/D (…, m), which pivots failed (…, m)); a failed pivot, as in `ldl`, has a
    NaN reciprocal, which here spreads to every later column."""
    m = matrix.shape[-1]
    threshold = _threshold([matrix[..., j, j] for j in range(m)])
    rows = jnp.arange(m)

    def column(j, carry):  # Lᵀ's row j (L's column j), D_j and 1/D_j
        upper, pivots, reciprocals = carry  # upper = Lᵀ, rows filled in turn
        weighted = jnp.take(upper, j, axis=-1) * pivots  # L_jk D_k, zero for k ≥ j
        pivot = jnp.take(jnp.take(matrix, j, axis=-1), j, axis=-1) - jnp.sum(
            jnp.take(upper, j, axis=-1) * weighted, axis=-1)
        reciprocal = jnp.where(pivot > threshold, 1 / pivot, jnp.nan)  # NaN: failed
        entries = (jnp.take(matrix, j, axis=-1)
                   - jnp.sum(upper * weighted[..., :, None], axis=-2)) * reciprocal[..., None]
        entries = jnp.where(jnp.broadcast_to(rows > j, entries.shape), entries,
                            jnp.broadcast_to(rows == j, entries.shape).astype(matrix.dtype))
        upper = jax.lax.dynamic_update_index_in_dim(upper, entries[..., None, :], j, -2)
        pivots = jax.lax.dynamic_update_index_in_dim(pivots, pivot[..., None], j, -1)
        reciprocals = jax.lax.dynamic_update_index_in_dim(reciprocals, reciprocal[..., None],
                                                          j, -1)
        return upper, pivots, reciprocals

    zeros = jnp.zeros(matrix.shape[:-1], matrix.dtype)
    upper, _, reciprocals = jax.lax.fori_loop(0, m, column,
                                              (jnp.zeros_like(matrix), zeros, zeros))
    return jnp.swapaxes(upper, -1, -2), reciprocals, jnp.isnan(reciprocals)  # NaN: failed


def ldl_by_columns_solve(lower, reciprocals, rhs):
    """x = L⁻ᵀ D⁻¹ L⁻¹ f from `ldl_by_columns`, by column-oriented substitution (m vector
    updates each way, straight-line code: one fused operation each), vectorised over leading
    axes."""
    m = rhs.shape[-1]
    strict = lower - jnp.broadcast_to(jnp.eye(m, dtype=lower.dtype), lower.shape)

    y = rhs
    for j in range(m):  # L y = f: y_j is final, remove it from the rows below
        y = y - strict[..., :, j] * y[..., j, None]
    x = y * reciprocals
    for j in reversed(range(m)):  # Lᵀ x = D⁻¹ y: x_j is final, remove it from the rows above
        x = x - strict[..., j, :] * x[..., j, None]
    return x


def spd_solve(matrix, rhs, *, written_out=UNROLL_MAX):
    """(H⁻¹ b, whether H is positive definite) for a symmetric H, b a vector (…, m) or
    columns (…, m, k): LDLᵀ written out entry by entry up to `written_out`, by columns above
    (`ldl_by_columns`)."""
    if matrix.shape[-1] <= written_out:
        lower, reciprocals, failed = ldl(matrix)
        solve_with = ldl_solve
    else:
        lower, reciprocals, failed = ldl_by_columns(matrix)
        solve_with = ldl_by_columns_solve
    if rhs.ndim == matrix.ndim:  # columns
        solution = jax.vmap(lambda b: solve_with(lower, reciprocals, b), -1, -1)(rhs)
    else:
        solution = solve_with(lower, reciprocals, rhs)
    return solution, ~jnp.any(failed, axis=-1)


def condition_number(mass_matrix):
    """κ(M) = λ_max / λ_min of a symmetric matrix, from its eigenvalues; ∞ where M is not
    positive definite."""
    eigenvalues = jnp.linalg.eigvalsh(mass_matrix)
    return jnp.where(eigenvalues[0] > 0, eigenvalues[-1] / eigenvalues[0], jnp.inf)


def lu_factor(matrix):
    """P A = L U by Gaussian elimination with partial pivoting (Golub and Van Loan, Matrix
    Computations, Algorithm 3.4.1), in n − 1 steps of array operations, vectorised over
    leading axes: at step k the row of largest |a_ik| (i ≥ k) is exchanged with row k and
    eliminated below it. No library call (LAPACK's getrf: the first in a process loads
    SciPy's LAPACK, about 0.3 s, and its pivots become a permutation through a loop that
    XLA compiles apart).

    Returns (L and U packed in one matrix, L unit lower triangular below the diagonal; the
    rows' order, P A = A[order]; whether A is singular to working precision: a pivot
    |U_kk| ≤ n ε max |A_ij|, or not finite)."""
    n = matrix.shape[-1]
    rows = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), matrix.shape[:-1])
    a = matrix
    order = rows
    for k in range(n - 1):
        chosen = k + jnp.argmax(jnp.abs(a[..., k:, k]), axis=-1).astype(jnp.int32)
        is_chosen = rows == chosen[..., None]
        exchanged = (rows == k) | is_chosen  # rows k and the pivot's trade places
        pivot_row = jnp.sum(jnp.where(is_chosen[..., None], a, 0), axis=-2)
        source = jnp.where((rows == k)[..., None], pivot_row[..., None, :], a[..., k, None, :])
        a = jnp.where(exchanged[..., None], source, a)
        pivot_order = jnp.sum(jnp.where(is_chosen, order, 0), axis=-1, dtype=jnp.int32)
        order = jnp.where(exchanged, jnp.where(rows == k, pivot_order[..., None],
                                               order[..., k, None]), order)
        multipliers = a[..., k + 1:, k] / a[..., k, k, None]
        a = a.at[..., k + 1:, k].set(multipliers)
        a = a.at[..., k + 1:, k + 1:].add(-multipliers[..., :, None] * a[..., k, None, k + 1:])
    diagonal = jnp.abs(jnp.diagonal(a, axis1=-2, axis2=-1))
    scale = jnp.max(jnp.abs(matrix), axis=(-2, -1))
    singular = ~jnp.all(diagonal > n * jnp.finfo(matrix.dtype).eps * scale[..., None], axis=-1)
    return a, order, singular


def lu_solve(lu, order, rhs, *, transposed: bool = False):
    """x = A⁻¹ b (or A⁻ᵀ b) from `lu_factor`'s P A = L U, b a vector (…, n) or columns
    (…, n, k): L y = P b, U x = y; transposed Uᵀ w = b, Lᵀ v = w, x = Pᵀ v."""
    n = lu.shape[-1]
    column = rhs.ndim == lu.ndim - 1
    b = rhs[..., None] if column else rhs
    entry = lambda i, j: lu[..., i, j, None]  # noqa: E731  (broadcast against b's columns)
    if not transposed:
        b = jnp.take_along_axis(b, jnp.broadcast_to(order[..., None], b.shape), axis=-2)
        y: list[Any] = []
        for i in range(n):  # L y = P b, L unit lower triangular
            y.append(b[..., i, :] - sum((entry(i, k) * y[k] for k in range(i)), 0))
        x: list[Any] = [None] * n
        for i in reversed(range(n)):  # U x = y
            x[i] = (y[i] - sum((entry(i, k) * x[k] for k in range(i + 1, n)), 0)) / entry(i, i)
        solution = jnp.stack(x, axis=-2)
    else:
        w: list[Any] = []
        for i in range(n):  # Uᵀ w = b
            w.append((b[..., i, :] - sum((entry(k, i) * w[k] for k in range(i)), 0))
                     / entry(i, i))
        v: list[Any] = [None] * n
        for i in reversed(range(n)):  # Lᵀ v = w
            v[i] = w[i] - sum((entry(k, i) * v[k] for k in range(i + 1, n)), 0)
        stacked = jnp.stack(v, axis=-2)  # P x = v: x[order[i]] = v[i]
        inverse = jnp.argsort(order, axis=-1)
        solution = jnp.take_along_axis(stacked, jnp.broadcast_to(inverse[..., None],
                                                                 stacked.shape), axis=-2)
    return solution[..., 0] if column else solution


# Up to this size `equilibrium` uses `PivotedLU` for Newton's steps: its program grows with n
# (n − 1 elimination steps, 2n substitution rows), LAPACK's does not. Measured only on small
# systems (the cart-pole's three unknowns); the bound itself is a judgement, not a measurement.
PIVOTED_LU_MAX = 16


class PivotedLU(lx.AbstractLinearSolver):
    """A lineax solver for small square systems by `lu_factor` and `lu_solve`: what
    optimistix's Newton method solves at each step (the equilibria of `equilibrium`),
    without LAPACK, whose first call in a process costs about 0.3 s of loading SciPy's
    LAPACK, more than such a whole solve compiles in. A singular matrix (to working
    precision) is reported as lineax's `singular` result."""

    def init(self, operator, options):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("PivotedLU solves square systems only, got an operator from "
                             f"{operator.in_size()} to {operator.out_size()} entries.")
        lu, order, singular = lu_factor(operator.as_matrix())
        return _LUState(lu, order, singular, _Layout.of(operator.in_structure()),
                        _Layout.of(operator.out_structure()), False)

    def compute(self, state, vector, options):
        del options
        b = jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(vector)])
        x = lu_solve(state.lu, state.order, b, transposed=state.transposed)
        result = lx.RESULTS.where(state.singular, lx.RESULTS.singular, lx.RESULTS.successful)
        return state.inputs.unravel(x), result, {}

    def transpose(self, state, options):
        del options
        return _LUState(state.lu, state.order, state.singular, state.outputs, state.inputs,
                        not state.transposed), {}

    def conj(self, state, options):
        del options
        return eqx.tree_at(lambda s: s.lu, state, jnp.conj(state.lu)), {}

    def assume_full_rank(self):
        return True


class _Layout(eqx.Module):
    """A pytree of arrays' structure, shapes and dtypes (static): how a flat vector splits."""

    treedef: Any = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)
    dtypes: tuple = eqx.field(static=True)

    @classmethod
    def of(cls, structure):
        leaves, treedef = jax.tree_util.tree_flatten(structure)
        return cls(treedef, tuple(tuple(x.shape) for x in leaves),
                   tuple(x.dtype for x in leaves))

    def unravel(self, flat):
        sizes = np.cumsum([int(np.prod(s)) for s in self.shapes])[:-1]
        parts = jnp.split(flat, sizes)
        return jax.tree_util.tree_unflatten(self.treedef, [
            part.reshape(shape).astype(dtype)
            for part, shape, dtype in zip(parts, self.shapes, self.dtypes)])


class _LUState(eqx.Module):
    lu: jax.Array
    order: jax.Array
    singular: jax.Array
    inputs: _Layout  # the operator's input structure: the solution's
    outputs: _Layout
    transposed: bool = eqx.field(static=True)
