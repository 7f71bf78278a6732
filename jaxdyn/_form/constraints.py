"""Constraints on any formulation: Lagrange's equations of the first kind (multipliers), their
elimination into independent speeds, drift control and consistent states."""

from typing import Callable, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._convention import CONFIGURATION_ARGS, call, vector
from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._errors import error_if
from .._linalg import factorise, solve, spd_solve
from .._solution import ConstraintRecord
from .._state import check_vector, public_method
from .._system.frames import HeldPoints

NOT_ON_CONSTRAINTS = (
    "Could not place the state on the constraints: after the Gauss–Newton iterations the "
    "holonomic constraints are still violated (|φ| above the tolerance). Likely causes: the "
    "constraints have no solution near the given q (a loop that cannot close with these "
    "dimensions, or with the coordinates and speeds kept as given), a singular configuration "
    "where the constraint Jacobian loses rank, or a "
    "constraint function that is not differentiable there."
)


class Baumgarte(eqx.Module):
    r"""Baumgarte's stabilisation: the acceleration-level constraints are replaced by

        φ̈ + 2α φ̇ + β² φ = 0    (holonomic rows),     ġ + 2α g = 0    (Pfaffian rows g = A q̇ − b),

    so that a violation decays (critically damped for α = β) instead of growing like the
    integration error. α and β are rates (1/s): choose them a few times faster than the
    motion you simulate but slower than what the solver's step resolves, e.g. α = β = 2π/T for
    the shortest period T of interest; too large makes the system stiff (the solver's steps
    shrink), too small leaves drift. Defaults α = β = 10 s⁻¹ suit mechanisms with periods of
    about a second. Costs nothing per step beyond the constraint values.

    Reference: J. Baumgarte, Stabilization of constraints and integrals of motion in dynamical
    systems, Comput. Methods Appl. Mech. Eng. 1 (1972) 1–16.
    """

    alpha: float = 10.0
    beta: float = 10.0


class Projection(eqx.Module):
    """Projection of the state back onto the constraints after every step:

        q ← q − Φ⁺ φ(q)      (Gauss–Newton, `iterations` times; Φ = ∂φ/∂q, Φ⁺ the
                              minimum-norm pseudo-inverse),
        u ← u − C⁺ (C u − b) (the velocity constraints, exactly linear in u).

    Both corrections are the smallest changes (Euclidean) that satisfy the constraints. After a
    step the violation is of the order of the solver's local error ε, so one Gauss–Newton
    iteration leaves O(ε²) and two leave round-off; `iterations` is fixed so that gradients
    pass through it. The solver then restarts its first-same-as-last stage (one extra
    evaluation per step). The violation stays at round-off over any horizon.
    """

    iterations: int = eqx.field(default=2, static=True)


def _gauss_newton_step(residual, x):
    """x − J⁺ r(x), J = ∂r/∂x: the minimum-norm correction Jᵀ (J Jᵀ + δ I)⁻¹ r, δ = m ε
    tr J Jᵀ (redundant rows, where J Jᵀ is singular, add nothing to the step: Jᵀ annihilates
    what δ lets through). An LDLᵀ of the small m × m matrix, not a library's QR: a call to
    LAPACK inside `simulate`'s loop keeps XLA from compiling the loop as one function."""
    value, jacobian = residual(x), jax.jacfwd(residual)(x)
    if value.shape[0] == 0:
        return x, value
    gram = jacobian @ jacobian.T
    regularised = gram + (value.shape[0] * jnp.finfo(x.dtype).eps * jnp.trace(gram)
                          + jnp.finfo(x.dtype).tiny) * jnp.eye(value.shape[0], dtype=x.dtype)
    return x - jacobian.T @ spd_solve(regularised, value)[0], value


def _free(kept, size, name) -> np.ndarray:
    """The indices not in `kept` (entries that may move)."""
    kept = sorted({int(i) for i in kept})
    if any(not 0 <= i < size for i in kept):
        raise ValueError(f"{name} must hold indices in [0, {size}), got {kept}.")
    return np.array([i for i in range(size) if i not in kept], dtype=int)


def _step_on(residual, x, free):
    """A Gauss–Newton step of `residual` that moves only the entries `free` of x."""
    if free.size == x.shape[-1]:
        return _gauss_newton_step(residual, x)[0]
    return x.at[free].set(_gauss_newton_step(lambda y: residual(x.at[free].set(y)), x[free])[0])


def _minimum_norm_solve(matrix, rhs):
    """S⁺ r for symmetric positive semi-definite S, by its eigendecomposition: directions with
    eigenvalues below m ε max|eigenvalue| (the redundant constraints) are left out."""
    values, vectors = jnp.linalg.eigh(matrix)
    keep = values > matrix.shape[-1] * jnp.finfo(matrix.dtype).eps * jnp.max(jnp.abs(values))
    inverse = jnp.where(keep, 1 / jnp.where(keep, values, 1), 0)
    return vectors @ (inverse * (vectors.T @ rhs))


class FirstKind:
    r"""The linear system of Lagrange's equations of the first kind at one state, factored
    once: M x − Cᵀ y = a, C x = b for any right-hand sides (a, b). With ρ = tr M / tr CᵀC,
    M̃ = M + ρ CᵀC (positive definite wherever M is on the motions C allows) and the Schur
    complement S = C M̃⁻¹ Cᵀ:

        S y = b − C M̃⁻¹ (a + ρ Cᵀ b),      x = M̃⁻¹ (a + ρ Cᵀ b + Cᵀ y).

    (x, y) = (u̇, λ) for (a, b) = (f, c); the same factors give their derivatives."""

    def __init__(self, mass_matrix, jacobian, *, small, least_squares=False):
        gram = jacobian.T @ jacobian
        self.jacobian = jacobian
        self.rho = jnp.trace(mass_matrix) / (jnp.trace(gram) + jnp.finfo(mass_matrix.dtype).tiny)
        self.factors = factorise(mass_matrix + self.rho * gram, unrolled=small)
        self.inverse_ct = jax.vmap(lambda b: solve(self.factors, b))(jacobian)  # M̃⁻¹ Cᵀ, rows
        self.schur = jacobian @ self.inverse_ct.T
        self.schur_factors = None if least_squares else factorise(self.schur, unrolled=small)
        self.mass_singular = self.factors.singular
        self.constraints_singular = (jnp.zeros((), bool) if self.schur_factors is None
                                     else self.schur_factors.singular)

    def solve(self, a, b):
        """(x, y) with M x − Cᵀ y = a, C x = b (y of least norm for redundant constraints)."""
        free = solve(self.factors, a + self.rho * self.jacobian.T @ b)
        residual = b - self.jacobian @ free
        y = (_minimum_norm_solve(self.schur, residual) if self.schur_factors is None
             else solve(self.schur_factors, residual))
        return free + self.inverse_ct.T @ y, y


class Constrained(AbstractDynamics):
    r"""A formulation (any `jaxdyn.AbstractDynamics`) under constraints, by Lagrange's equations
    of the first kind:

        M u̇ = f + Cᵀ λ,        C u̇ = −γ,

    where the velocity constraints are written in the formulation's speeds,

        g(t, q, u) = C(t, q) u − b(t, q) = 0:   the rows  Φ K u + ∂φ/∂t  of holonomic
        constraints φ(t, q) = 0 (Φ = ∂φ/∂q, q̇ = K u), and  A K u − b  of Pfaffian constraints
        A(t, q) q̇ = b(t, q);

    γ = ∂g/∂t + (∂g/∂q) q̇ is the curvature term (d/dt of the rows times u, and the time
    terms), formed by one JVP; C = ∂g/∂u by forward mode. With a `Baumgarte` stabilisation
    −γ becomes −γ − 2α g − β² φ.

    **Signs**: Cᵀλ is the generalized constraint force acting on the system, along the speeds
    (`constraint_forces`); λ_i is the multiplier of row i. For a pendulum in Cartesian
    coordinates with φ = x² + y² − l², the force on the bob is 2λ (x, y): the rod's tension
    is −2λl.

    **Solution**: M may be singular where the constrained system is regular (a free body in
    unit-quaternion coordinates, whose T does not depend on the quaternion's scale). The first
    equation plus ρ Cᵀ (C u̇ + γ) = 0 gives (M + ρ CᵀC) u̇ = f − ρ Cᵀγ + Cᵀλ with the same u̇
    and λ, and M + ρ CᵀC is positive definite whenever M is positive definite on the motions
    the constraints allow; ρ = tr M / tr CᵀC balances the two. Then, with an LDLᵀ
    factorisation of that matrix M̃, λ from the Schur complement

        (C M̃⁻¹ Cᵀ) λ = −γ − C M̃⁻¹ f̃,      u̇ = M̃⁻¹ (f̃ + Cᵀ λ).

    A rank-deficient C (redundant constraints, a dead point) makes C M̃⁻¹ Cᵀ singular: an error
    that names the state, or with ``redundant="least_squares"`` the minimum-norm multipliers
    (u̇ is still unique when the redundant rows are consistent).

    **Arguments:**

    - `dynamics`: the unconstrained formulation (`Lagrangian`, `Kane`, `GibbsAppell`,
      `ArticulatedBody`, …); its coordinates may be redundant (Cartesian, closed loops).
    - `holonomic`: φ(q, p) → (m₁,), or `jaxdyn.HeldPoints` (points of a tree's links held
      in the world, whose C and γ come from the tree's recursions), or None.
    - `pfaffian`: (q, p) → A (m₂, n), or (A, b) with b (m₂,), for A q̇ = b; or None.
    - `time_dependent`: if True both take t first: φ(t, q, p), (t, q, p) → (A, b)
      (rheonomic constraints, a bead on a driven wire).
    - `stabilisation`: `Baumgarte(α, β)`, `Projection()` (the default: violation at
      round-off, one extra evaluation and a few small solves per step) or None (the
      index-reduced equations alone: the violation grows with the integration error).
    - `redundant`: "error" (default) or "least_squares" (see above).
    """

    dynamics: AbstractDynamics
    holonomic: Callable | None = None
    pfaffian: Callable | None = None
    time_dependent: bool = eqx.field(default=False, static=True)
    stabilisation: Baumgarte | Projection | None = Projection()
    redundant: str = eqx.field(default="error", static=True)

    def __check_init__(self):
        if not isinstance(self.dynamics, AbstractDynamics):
            raise ValueError("Constrained needs a jaxdyn formulation (AbstractDynamics) to "
                             f"constrain, got {type(self.dynamics).__name__}.")
        if self.holonomic is None and self.pfaffian is None:
            raise ValueError("Constrained needs holonomic and/or pfaffian constraints.")
        if isinstance(self.holonomic, HeldPoints) and self.time_dependent:
            raise ValueError("HeldPoints are held at fixed places (scleronomic): give "
                             "time_dependent=False, or a function φ(t, q, p) for moving holds.")
        if self.redundant not in ("error", "least_squares"):
            raise ValueError(f"redundant must be 'error' or 'least_squares', got "
                             f"{self.redundant!r}.")
        if not isinstance(self.stabilisation, (Baumgarte, Projection, type(None))):
            raise ValueError("stabilisation must be jaxdyn.Baumgarte(...), "
                             f"jaxdyn.Projection(...) or None, got {self.stabilisation!r}.")

    # -- the constraints in the user's convention ---------------------------------------------

    def _phi(self, t, q, p):
        if self.holonomic is None:
            return jnp.zeros((0,), q.dtype)
        value = jnp.asarray(call(self.holonomic, "holonomic constraint φ", self.time_dependent,
                                 CONFIGURATION_ARGS, t, q, p))
        if value.ndim != 1:
            raise ValueError("holonomic constraint φ must return a 1-D array of shape (m,), "
                             f"got shape {value.shape}.")
        return value

    def _pfaffian(self, t, q, p):
        value = call(self.pfaffian, "pfaffian constraint (A, b)", self.time_dependent,
                     CONFIGURATION_ARGS, t, q, p)
        if isinstance(value, (tuple, list)):
            matrix, rhs = (jnp.asarray(v) for v in value)
        else:
            matrix = jnp.asarray(value)
            rhs = jnp.zeros(matrix.shape[:1], q.dtype)
        if matrix.ndim != 2 or matrix.shape[1] != q.shape[0]:
            raise ValueError("pfaffian constraint A must have shape (m, n) with n = "
                             f"{q.shape[0]} coordinates, got {matrix.shape}.")
        return matrix, vector(rhs, "pfaffian constraint b", matrix.shape[:1])

    def _velocity_residual(self, t, q, u, p, *, held=True):
        """g(t, q, u) = C u − b: φ̇ along q̇ = K u, then A q̇ − b (without the rows of
        `HeldPoints` unless `held`)."""
        qd = self.dynamics.coordinate_rates(t, q, u, p)
        rows = []
        if isinstance(self.holonomic, HeldPoints):
            if held:  # φ̇: the points' velocities, without forming C
                rows.append(self.holonomic.velocities_and_accelerations(
                    q, u, jnp.zeros_like(u), p)[0])
        elif self.holonomic is not None:
            rows.append(jax.jvp(lambda t, q: self._phi(t, q, p), (t, q),
                                (jnp.ones_like(t), qd))[1])
        if self.pfaffian is not None:
            matrix, rhs = self._pfaffian(t, q, p)
            rows.append(matrix @ qd - rhs)
        return jnp.concatenate(rows) if rows else jnp.zeros((0,), q.dtype)

    def _check(self, t, q, u):
        q, u = check_vector(q, "q"), check_vector(u, "u")
        return jnp.asarray(t, q.dtype), q, u

    def constraint_terms(self, t, q, u, p):
        """(C, g, γ, φ): the constraint Jacobian in the speeds, the velocity residual, the
        curvature term and the holonomic residual, at one state."""
        def residual(t, q, u):  # the rows differentiated here: all but those of HeldPoints
            return self._velocity_residual(t, q, u, p, held=False)

        g, curvature = jax.jvp(lambda t, q: residual(t, q, u), (t, q),
                               (jnp.ones_like(t), self.dynamics.coordinate_rates(t, q, u, p)))
        jacobian = jax.jacfwd(lambda u: residual(t, q, u))(u)
        if isinstance(self.holonomic, HeldPoints):  # first-order kinematics of the tree
            held, held_curvature = self.holonomic.velocity_terms(q, u, p)
            jacobian = jnp.concatenate([held, jacobian])
            g = jnp.concatenate([held @ u, g])
            curvature = jnp.concatenate([held_curvature, curvature])
        return jacobian, g, curvature, self._phi(t, q, p)

    def acceleration_residual(self, t, q, u, ud, p=None):
        """C u̇ − c at one state (zero on the constrained motion): for `HeldPoints` alone,
        the points' classical accelerations plus the stabilisation's terms, one JVP of the
        tree's velocity recursion, without forming C."""
        if not isinstance(self.holonomic, HeldPoints) or self.pfaffian is not None:
            jacobian, rhs = self.constraint_rows(t, q, u, p)
            return jacobian @ ud - rhs
        velocity, acceleration = self.holonomic.velocities_and_accelerations(q, u, ud, p)
        if isinstance(self.stabilisation, Baumgarte):
            alpha = jnp.asarray(self.stabilisation.alpha, q.dtype)
            beta = jnp.asarray(self.stabilisation.beta, q.dtype)
            acceleration = (acceleration + 2 * alpha * velocity
                            + beta**2 * self.holonomic(q, p))
        return acceleration

    def first_kind_residuals(self, t, q, u, ud, multipliers, p=None):
        """(M u̇ − f − Cᵀ λ, C u̇ − c) at one state: the residuals of Lagrange's equations of
        the first kind at accelerations u̇ and multipliers λ, zero at their solution. For
        `HeldPoints` alone on a formulation that forms both in one pass of its recursions
        (`form_residual_held`: the articulated-body formulation's recursive Newton–Euler
        algorithm, the points' forces λ taken as loads), that pass; else the formulation's
        residual less Cᵀ λ, the transpose of u̇ ↦ C u̇ − c applied to λ."""
        if isinstance(self.holonomic, HeldPoints) and self.pfaffian is None:
            held = self.holonomic
            fused = self.dynamics.form_residual_held(t, q, u, ud, p, held,
                                                     multipliers.reshape(-1, 3))
            if fused is not None:
                residual, positions, velocities, accelerations = fused
                second = accelerations.reshape(-1)
                if isinstance(self.stabilisation, Baumgarte):
                    alpha = jnp.asarray(self.stabilisation.alpha, q.dtype)
                    beta = jnp.asarray(self.stabilisation.beta, q.dtype)
                    second = (second + 2 * alpha * velocities.reshape(-1)
                              + beta**2 * (positions - held.positions).reshape(-1))
                return residual, second
        # (C u̇ − c is affine in u̇ with the coefficient C: Cᵀ λ is its VJP in u̇)
        second, transpose = jax.vjp(lambda ud: self.acceleration_residual(t, q, u, ud, p), ud)
        return self.dynamics.form_residual(t, q, u, ud, p) - transpose(multipliers)[0], second

    def constraint_rows(self, t, q, u, p=None):
        """(C, c) of C u̇ = c at one state, with the stabilisation's terms."""
        jacobian, g, curvature, phi = self.constraint_terms(t, q, u, p)
        rhs = -curvature
        if isinstance(self.stabilisation, Baumgarte):
            alpha = jnp.asarray(self.stabilisation.alpha, q.dtype)
            beta = jnp.asarray(self.stabilisation.beta, q.dtype)
            position = jnp.concatenate([phi, jnp.zeros(g.shape[0] - phi.shape[0], q.dtype)])
            rhs = rhs - 2 * alpha * g - beta**2 * position
        return jacobian, rhs

    def _first_kind(self, t, q, u, p, *, small=False):
        """(u̇, λ, the factored system, whether it failed, whether f or c is not finite)."""
        mass_matrix, forcing = self.dynamics.form_equations(t, q, u, p)
        jacobian, rhs = self.constraint_rows(t, q, u, p)
        kkt = FirstKind(mass_matrix, jacobian, small=small,
                        least_squares=self.redundant == "least_squares")
        accelerations, multipliers = kkt.solve(forcing, rhs)
        nonfinite = ~jnp.all(jnp.isfinite(forcing)) | ~jnp.all(jnp.isfinite(rhs))
        failed = kkt.mass_singular | kkt.constraints_singular | nonfinite
        return accelerations, multipliers, kkt, failed, nonfinite

    def _solve(self, t, q, u, p, *, small):
        """(u̇, λ, C, mass_singular, constraints_singular, nonfinite)."""
        accelerations, multipliers, kkt, failed, nonfinite = self._first_kind(
            t, q, u, p, small=small)
        accelerations = jnp.where(failed, jnp.nan, accelerations)
        return (accelerations, multipliers, kkt.jacobian, kkt.mass_singular,
                kkt.constraints_singular, nonfinite)

    def first_kind(self, t, q, u, p=None):
        """(u̇, λ, the factored system `FirstKind`) at one state, for callers that solve
        Lagrange's equations of the first kind again with other right-hand sides (their
        derivatives); u̇ is NaN where the equations fail."""
        accelerations, multipliers, kkt, failed, _ = self._first_kind(t, q, u, p)
        return jnp.where(failed, jnp.nan, accelerations), multipliers, kkt

    # -- AbstractDynamics ---------------------------------------------------------------------

    def coordinate_rates(self, t, q, u, p=None):
        """q̇ = K u, the constrained formulation's."""
        return self.dynamics.coordinate_rates(t, q, u, p)

    def form_equations(self, t, q, u, p=None):
        """(M, f) of the unconstrained formulation (the constraint forces are not in f)."""
        return self.dynamics.form_equations(t, q, u, p)

    def form_accelerations(self, t, q, u, p=None, *, small):
        t, q, u = self._check(t, q, u)
        accelerations, _, _, mass_singular, constraints_singular, nonfinite = self._solve(
            t, q, u, p, small=small)
        return accelerations, mass_singular | constraints_singular, nonfinite

    def state_constraints(self, t, q, u, p=None):
        """(φ(t, q), g(t, q, u)): the holonomic constraints and every velocity constraint."""
        return self._phi(t, q, p), self._velocity_residual(t, q, u, p)

    def singular_constraints(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u)
        _, _, _, mass_singular, constraints_singular, _ = self._solve(t, q, u, p, small=False)
        return constraints_singular & ~mass_singular

    def energy_terms(self, t, q, u, p=None):
        return self.dynamics.energy_terms(t, q, u, p)

    def user_functions(self, t, q, u, p=None):
        t, q, u = self._check(t, q, u)
        values = [self.dynamics.user_functions(t, q, u, p), self._phi(t, q, p)]
        if self.pfaffian is not None:
            values.append(self._pfaffian(t, q, p))
        return values

    def state_projection(self):
        return self.project if isinstance(self.stabilisation, Projection) else None

    @property
    def saved_records(self):
        return ("constraints", *self.dynamics.saved_records)

    def record(self, name, ts, q, u, p=None):
        if name != "constraints":  # the constrained formulation's own (a Controlled's inputs)
            return self.dynamics.record(name, ts, q, u, p)
        return ConstraintRecord(multipliers=self.multipliers(ts, q, u, p),
                                constraint_forces=self.constraint_forces(ts, q, u, p),
                                position_violation=self.position_violation(ts, q, u, p),
                                velocity_violation=self.velocity_violation(ts, q, u, p))

    # -- constraint quantities ------------------------------------------------------------------

    @public_method("(),(n),(m)->(k)")
    def multipliers(self, t, q, u, p=None):
        """λ, one per constraint row (holonomic rows first, then Pfaffian)."""
        t, q, u = self._check(t, q, u)
        return self._solve(t, q, u, p, small=False)[1]

    @public_method("(),(n),(m)->(m)")
    def constraint_forces(self, t, q, u, p=None):
        """Cᵀλ: the generalized constraint forces along the speeds."""
        t, q, u = self._check(t, q, u)
        _, multipliers, jacobian, *_ = self._solve(t, q, u, p, small=False)
        return jacobian.T @ multipliers

    @public_method("(),(n),(m)->(k,m)")
    def constraint_jacobian(self, t, q, u, p=None):
        """C = ∂g/∂u, the velocity constraints' rows in the speeds."""
        t, q, u = self._check(t, q, u)
        return self.constraint_terms(t, q, u, p)[0]

    @public_method("(),(n),(m)->(k)")
    def position_violation(self, t, q, u, p=None):
        """φ(t, q), the holonomic constraints' residual (u is ignored)."""
        t, q, u = self._check(t, q, u)
        return self._phi(t, q, p)

    @public_method("(),(n),(m)->(k)")
    def velocity_violation(self, t, q, u, p=None):
        """g = C u − b, every constraint's velocity residual (φ̇ for holonomic rows)."""
        t, q, u = self._check(t, q, u)
        return self._velocity_residual(t, q, u, p)

    def project(self, t, q, u, p=None, iterations=None):
        """(q, u) moved onto the constraints by the smallest corrections (`Projection`); no
        checks and no branches (used after every step of `simulate`)."""
        if iterations is None:
            if not isinstance(self.stabilisation, Projection):
                raise ValueError("project needs `iterations` when the stabilisation is not a "
                                 f"jaxdyn.Projection (it is {self.stabilisation!r}).")
            iterations = self.stabilisation.iterations
        for _ in range(iterations):
            q, _ = _gauss_newton_step(lambda q: self._phi(t, q, p), q)
        u, _ = _gauss_newton_step(lambda u: self._velocity_residual(t, q, u, p), u)
        return q, u

    @public_method("(),(n),(m)->(n),(m)")
    def consistent_state(self, t, q, u, p=None, *, keep_q: tuple[int, ...] = (),
                         keep_u: tuple[int, ...] = (), tol=None, iterations: int = 20):
        """(q, u) on the constraints, nearest to the given ones: Gauss–Newton with
        minimum-norm steps for φ(t, q) = 0, then the minimum-norm correction of u for
        C u = b. Use it for initial conditions.

        `keep_q`, `keep_u`: indices of coordinates and speeds that must stay as given (a
        crank's angle and speed prescribed); only the others move. Without them every entry
        may move (a crank speed of 3 can come back as 2.64): compare the result with the
        input to see what moved. Raises an error naming the state when |φ| or |C u − b| >
        `tol` (default √ε·(1 + |q|)) after `iterations`, e.g. when the kept entries admit no
        consistent state."""
        t, q, u = self._check(t, q, u)
        start = (t, q, u)
        free_q = _free(keep_q, q.shape[-1], "keep_q")
        free_u = _free(keep_u, u.shape[-1], "keep_u")
        q_new = q
        for _ in range(iterations):
            q_new = _step_on(lambda q: self._phi(t, q, p), q_new, free_q)
        u_new = _step_on(lambda u: self._velocity_residual(t, q_new, u, p), u, free_u)
        if tol is None:
            tol = jnp.sqrt(jnp.finfo(q.dtype).eps) * (1 + jnp.max(jnp.abs(q)))
        residual = jnp.concatenate([jnp.abs(self._phi(t, q_new, p)),
                                    jnp.abs(self._velocity_residual(t, q_new, u_new, p))])
        bad = ~jnp.all(residual <= tol) | ~jnp.all(jnp.isfinite(q_new))
        q_new = error_if(q_new, [(bad, NOT_ON_CONSTRAINTS)], start)
        return q_new, u_new

    def eliminate(self, t, q, u, p=None, independent=None) -> "IndependentSpeeds":
        """The same system in independent speeds (`IndependentSpeeds`), chosen at the state
        (t, q, u) unless `independent` (indices among the speeds) is given: the speeds left
        after a column-pivoted QR of C takes the best-conditioned dependent ones."""
        u = np.asarray(u)
        if independent is None:
            import scipy.linalg  # eager, once per model

            jacobian = np.asarray(self.constraint_jacobian(t, q, u, p))
            # scipy's qr is unannotated: with pivoting=True it returns (Q, R, pivots).
            _, r, pivots = cast(tuple[np.ndarray, np.ndarray, np.ndarray],
                                scipy.linalg.qr(jacobian, pivoting=True))
            rank = int(np.sum(np.abs(np.diag(r)) > 1e-10 * np.abs(r[0, 0])))
            independent = sorted(int(i) for i in pivots[rank:])
        return IndependentSpeeds(self, tuple(independent), u.shape[0])


class IndependentSpeeds(AbstractDynamics):
    r"""The constraints of a `Constrained` formulation eliminated: the state is (q, v) with v
    the independent speeds, u = u(t, q, v) solving C u = b for the dependent ones,

        u = B v + w,    B = ∂u/∂v,    Bᵀ M B v̇ = Bᵀ (f − M (∂u/∂t + (∂u/∂q) q̇)),

    (Kane's equations in independent speeds: the constraint forces Cᵀλ do no work on the
    allowed motions, CB = 0, and drop out). Agrees with the multiplier form; fewer speeds,
    no multipliers, the velocity constraints hold exactly; holonomic drift of q is controlled
    by the same `Projection` (position level) if the `Constrained` has one.

    **Arguments:**

    - `constrained`: a `jaxdyn.Constrained`.
    - `independent`: indices of the independent speeds among the formulation's speeds.
    - `num_speeds`: how many speeds the formulation has.

    `Constrained.eliminate(t, q, u, p)` builds one, choosing the independent speeds at a state.
    The dependent block of C must stay invertible along the motion; where it does not, the
    equations become non-finite and the error names the state.
    """

    constrained: Constrained
    independent: tuple[int, ...] = eqx.field(static=True)
    num_speeds: int = eqx.field(static=True)

    def __check_init__(self):
        if not isinstance(self.constrained, Constrained):
            raise ValueError("IndependentSpeeds needs a jaxdyn.Constrained, got "
                             f"{type(self.constrained).__name__}.")
        if any(not 0 <= i < self.num_speeds for i in self.independent) or len(
                set(self.independent)) != len(self.independent):
            raise ValueError(f"independent must be distinct indices below num_speeds = "
                             f"{self.num_speeds}, got {self.independent}.")

    def _placed(self, q, v):
        """The speeds with v at the independent places and zeros elsewhere."""
        if v.shape != (len(self.independent),):
            raise ValueError(f"v must have shape ({len(self.independent)},) (the independent "
                             f"speeds {self.independent}), got {v.shape}.")
        independent = np.asarray(self.independent, dtype=np.int32)
        return jnp.zeros(self.num_speeds, q.dtype).at[independent].set(v)

    def _speeds(self, t, q, v, p):
        """u(t, q, v): C_d u_d = b − C_i v (g(u) = C u − b is affine in u)."""
        base = self._placed(q, v)
        dependent = np.setdiff1d(np.arange(self.num_speeds), self.independent).astype(np.int32)
        residual = lambda u: self.constrained._velocity_residual(t, q, u, p)  # noqa: E731
        jacobian = jax.jacfwd(residual)(base)
        if jacobian.shape[0] != dependent.shape[0]:
            raise ValueError(
                f"{jacobian.shape[0]} constraint rows need as many dependent speeds, got "
                f"{dependent.shape[0]} ({self.num_speeds} speeds, {len(self.independent)} "
                "independent).")
        u_dependent = jnp.linalg.solve(jacobian[:, dependent], -residual(base))
        return base.at[dependent].set(u_dependent)

    def coordinate_rates(self, t, q, v, p=None):
        return self.constrained.coordinate_rates(t, q, self._speeds(t, q, v, p), p)

    def form_equations(self, t, q, v, p=None):
        """(Bᵀ M B, Bᵀ (f − M ẇ))."""
        q, v = check_vector(q, "q"), check_vector(v, "v")
        t = jnp.asarray(t, q.dtype)
        u = self._speeds(t, q, v, p)
        basis = jax.jacfwd(lambda v: self._speeds(t, q, v, p))(v)
        drift = jax.jvp(lambda t, q: self._speeds(t, q, v, p), (t, q),
                        (jnp.ones_like(t), self.constrained.coordinate_rates(t, q, u, p)))[1]
        mass_matrix, forcing = self.constrained.dynamics.form_equations(t, q, u, p)
        return basis.T @ mass_matrix @ basis, basis.T @ (forcing - mass_matrix @ drift)

    def form_accelerations(self, t, q, v, p=None, *, small):
        return accelerations_from_equations(self, t, q, v, p, small=small)

    def energy_terms(self, t, q, v, p=None):
        return self.constrained.energy_terms(t, q, self._speeds(t, q, v, p), p)

    def user_functions(self, t, q, v, p=None):
        # The callbacks at speeds of the right shape: their indexing does not depend on the
        # values, so the dependent speeds' solve (a Jacobian and a factorisation) is not
        # needed to check it.
        return self.constrained.user_functions(t, q, self._placed(q, v), p)

    def state_constraints(self, t, q, v, p=None):
        """(φ(t, q), none): the velocity constraints hold by construction of the speeds."""
        return self.constrained._phi(t, q, p), jnp.zeros((0,), q.dtype)

    def state_projection(self):
        stabilisation = self.constrained.stabilisation
        if not isinstance(stabilisation, Projection):
            return None

        def project(t, q, v, p):
            for _ in range(stabilisation.iterations):
                q, _ = _gauss_newton_step(lambda q: self.constrained._phi(t, q, p), q)
            return q, v

        return project

    @property
    def saved_records(self):
        return self.constrained.saved_records

    def record(self, name, ts, q, v, p=None):
        u = jax.vmap(self._speeds, in_axes=(0, 0, 0, None))(ts, q, v, p)
        return self.constrained.record(name, ts, q, u, p)

    @public_method("(),(n),(k)->(m)")
    def speeds(self, t, q, v, p=None):
        """All the formulation's speeds u(t, q, v)."""
        return self._speeds(jnp.asarray(t, q.dtype), q, v, p)
