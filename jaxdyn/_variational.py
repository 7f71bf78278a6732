"""Structure-preserving steppers: a variational integrator built from the user's Lagrangian,
and Störmer–Verlet for separable systems. Both are diffrax solvers taking fixed steps, for
`jaxdyn.simulate` (which passes them the dynamics as the solve's arguments), so saving, dense
output, `vmap` and diffrax's adjoints work as with any other solver.

Why: a Runge–Kutta method's energy error grows secularly over long horizons; a symplectic
method's stays bounded (it exactly conserves a nearby "modified" energy), and a variational
integrator conserves the discrete momentum maps of the system's symmetries exactly (discrete
Noether theorem). References: J. E. Marsden and M. West, "Discrete mechanics and variational
integrators", Acta Numerica 10 (2001); E. Hairer, C. Lubich and G. Wanner, Geometric Numerical
Integration (2006), ch. VI; L. Verlet, Phys. Rev. 159 (1967).
"""

from typing import ClassVar, Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._linalg import spd_solve
from ._unroll import depends

_Y = tuple  # (q, u)


def _hermite(t0, t1, y0, y1, rates0, rates1):
    """dense_info for diffrax's cubic Hermite interpolation from (q, u) at both ends and
    their rates (q̇, u̇) there."""
    h = t1 - t0
    return dict(y0=y0, y1=y1, k0=jax.tree_util.tree_map(lambda r: h * r, rates0),
                k1=jax.tree_util.tree_map(lambda r: h * r, rates1))


class AbstractStructurePreserving(diffrax.AbstractSolver):
    """A fixed-step stepper of `jaxdyn.simulate` that reads the dynamics from the solve's
    arguments. `simulate` checks `check(dynamics, t, q, u, p)` at trace time."""

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation

    def order(self, terms):
        return 2

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def check(self, dynamics, t, q, u, p) -> None:
        """Raise a ValueError if this stepper cannot integrate `dynamics`."""


class VariationalIntegrator(AbstractStructurePreserving):
    r"""A variational integrator of a `jaxdyn.Lagrangian`: the discrete Euler–Lagrange
    equations of a discrete Lagrangian L_d(q_k, q_{k+1}) ≈ ∫ L dt over one step h,

        midpoint:      L_d = h L(t_k + h/2, (q_k + q_{k+1})/2, (q_{k+1} − q_k)/h)
        trapezoidal:   L_d = h/2 [L(t_k, q_k, v) + L(t_{k+1}, q_{k+1}, v)],  v = (q_{k+1} − q_k)/h,

    in position–momentum form, with non-conservative forces Q − ∂D/∂q̇ through the discrete
    Lagrange–d'Alembert principle (forces F_d^± of the same quadrature):

        p_k = −D₁L_d(q_k, q_{k+1}) − F_d^−,        p_{k+1} = D₂L_d(q_k, q_{k+1}) + F_d^+.

    The first equation is solved for q_{k+1} by Newton's method (optimistix, differentiated
    through by the implicit function theorem); the speeds follow from the Legendre transform
    ∂L/∂q̇(q_{k+1}, q̇_{k+1}) = p_{k+1}: one Newton step, exact when T is quadratic in q̇, and
    Newton's method otherwise. Both rules are second order, symplectic and symmetric: over
    long horizons the energy error of a conservative system oscillates without drift, and the
    momentum map of every symmetry of L (a cyclic coordinate's momentum, an angular momentum)
    is conserved to round-off. The trapezoidal rule is Störmer–Verlet where M is constant.

    Use it through `jaxdyn.simulate(lagrangian, ..., solver=VariationalIntegrator(), dt0=h)`:
    the steps are fixed (an error-controlled step would destroy the conservation). Saved values
    between steps are cubic Hermite in q (from q̇ at both ends) and quadratic in q̇ (from u̇ at
    the start). A step too long for the motion stops the solve with an error (Newton's method
    did not converge, or converged to a root far from the motion) rather than continuing on a
    wrong root.

    **Arguments:**

    - `rule`: "midpoint" (default; also symplectic for every L) or "trapezoidal".
    - `rtol`, `atol`: Newton's tolerances on the mean velocity (q_{k+1} − q_k)/h (default √ε
      of the state's dtype: Newton converges quadratically, so the solution is then exact to
      round-off).
    - `max_newton_steps`: Newton iterations per step before the solve stops with an error
      (the step is too long for the motion: take a smaller `dt0`).

    Reference: Marsden & West, Acta Numerica 10 (2001), §1.6 and §3.2 (forced systems).
    """

    rule: Literal["midpoint", "trapezoidal"] = eqx.field(default="midpoint", static=True)
    rtol: float | None = eqx.field(default=None, static=True)
    atol: float | None = eqx.field(default=None, static=True)
    max_newton_steps: int = eqx.field(default=32, static=True)

    def __check_init__(self):
        if self.rule not in ("midpoint", "trapezoidal"):
            raise ValueError(f"rule must be 'midpoint' or 'trapezoidal', got {self.rule!r}.")
        if self.max_newton_steps < 1:
            raise ValueError(f"max_newton_steps must be ≥ 1, got {self.max_newton_steps}.")
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive, got {value}.")

    def check(self, dynamics, t, q, u, p):
        from ._form.euler_lagrange import Lagrangian

        if not isinstance(dynamics, Lagrangian):
            raise ValueError(
                "VariationalIntegrator is built from a Lagrangian L(t, q, q̇): it needs a "
                f"jaxdyn.Lagrangian (or Lagrangian.from_system(...)), got "
                f"{type(dynamics).__name__}. Other formulations: use StormerVerlet (separable "
                "systems) or a diffrax solver.")

    def _newton(self, dtype):
        return newton_method(dtype, self.rtol, self.atol)

    def init(self, terms, t0, t1, y0, args):
        dynamics, p, _, _ = args
        q0, u0 = y0
        return conjugate_momentum(dynamics, t0, q0, u0, p)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        from ._dynamics import equations_of_motion

        dynamics, p, factorisation, _ = args
        q0, u0 = y0
        h = t1 - t0
        # The momentum p_k: carried from the last step (exact there), unless the state jumped.
        momentum0 = jax.lax.cond(made_jump, lambda: conjugate_momentum(dynamics, t0, q0, u0, p),
                                 lambda: solver_state)
        newton = self._newton(q0.dtype)

        forced = discrete_forces(dynamics, p, t0, t1, q0, self.rule)

        # p_k + D₁L_d + F_d^− = 0, solved for the mean velocity v = (q_{k+1} − q_k)/h rather
        # than q_{k+1}: v then carries its full precision, where (q_{k+1} − q_k)/h would
        # lose digits to cancellation (amplified by 1/h into the momenta) once |q| ≫ h |v|.
        # Initial guess: the speeds at the middle of the step, u_k + h/2 u̇_k, within O(h²)
        # of v. It also guards the root: the discrete equations have other roots far from the
        # motion, which Newton's method can reach from a step too long for the motion; a root
        # further from the guess than the guess is from u_k is not the motion's.
        accelerations = equations_of_motion(dynamics, t0, q0, u0, p, factorisation)[1]
        guess = u0 + h / 2 * accelerations
        position = optx.root_find(lambda v, _: momentum0 + forced(v)[0], newton, guess,
                                  max_steps=self.max_newton_steps, throw=False)
        v = position.value
        slack = newton.atol + newton.rtol * jnp.max(jnp.abs(v))
        nearby = (jnp.max(jnp.abs(v - guess))
                  <= 0.5 * jnp.max(jnp.abs(guess - u0)) + 0.1 * jnp.max(jnp.abs(u0)) + slack)
        q1 = q0 + h * v
        momentum1 = forced(v)[1]
        u1, speeds_converged = self._speeds(dynamics, t1, q1, v, p, momentum1, newton)
        y1 = (q1, u1)
        finite = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(u1))
        # Non-finite equations (a singular mass matrix) are diagnosed by `simulate` from the
        # last regular state; a Newton iteration that merely did not converge is reported here.
        converged = (position.result == optx.RESULTS.successful) & speeds_converged
        result = diffrax.RESULTS.where(converged | ~finite, diffrax.RESULTS.successful,
                                       diffrax.RESULTS.nonlinear_max_steps_reached)
        result = diffrax.RESULTS.where(nearby | ~finite, result,
                                       diffrax.RESULTS.nonlinear_divergence)
        dense_info = _hermite(t0, t1, y0, y1, (u0, accelerations),
                              (u1, 2 * (u1 - u0) / h - accelerations))
        return y1, None, dense_info, momentum1, result

    def _speeds(self, dynamics, t, q, guess, p, momentum, newton):
        return speeds_of_momentum(dynamics, t, q, guess, p, momentum, newton,
                                  self.max_newton_steps)


class StormerVerlet(AbstractStructurePreserving):
    r"""The Störmer–Verlet (leapfrog, velocity Verlet) method for separable systems, whose
    accelerations u̇ = a(t, q) do not depend on the speeds and whose kinematics q̇ = K u have a
    constant K (T = ½ uᵀ M u with constant M; V(q) and position-dependent forces):

        u_{k+½} = u_k + h/2 a(t_k, q_k),   q_{k+1} = q_k + h K u_{k+½},
        u_{k+1} = u_{k+½} + h/2 a(t_{k+1}, q_{k+1}).

    Explicit, second order, symplectic and time-reversible: one evaluation of the
    accelerations per step (the last one is reused by the next step). `simulate` checks at
    trace time that the system is separable (from the data flow of its equations) and names
    the dependence that is not; for a mass matrix M(q) or velocity-dependent forces use
    `VariationalIntegrator` (which, with rule="trapezoidal", is the implicit generalisation
    of this method).

    Reference: Hairer, Lubich & Wanner, Acta Numerica 12 (2003) 399–450.
    """

    def check(self, dynamics, t, q, u, p):
        from ._dynamics import equations_of_motion

        def equations(t, q, u, p):
            rates, accelerations, _, _ = equations_of_motion(dynamics, t, q, u, p)
            return rates, accelerations

        kinematics = depends(lambda *a: equations(*a)[0], t, q, u, p, tags="tqup")
        dynamic = depends(lambda *a: equations(*a)[1], t, q, u, p, tags="tqup")
        if kinematics & {"t", "q"}:
            raise ValueError(
                "StormerVerlet needs constant kinematics q̇ = K u, but this system's coordinate "
                "rates depend on the coordinates (e.g. angular velocities with quaternions or "
                "Euler angles). Use VariationalIntegrator on a Lagrangian, or a diffrax solver.")
        if "u" in dynamic:
            raise ValueError(
                "StormerVerlet is explicit only for separable systems, but this system's "
                "accelerations depend on the speeds (a mass matrix that depends on q, which "
                "brings Coriolis and centrifugal terms, or velocity-dependent forces such as "
                "damping). Use VariationalIntegrator (symplectic for any Lagrangian, with "
                "forces through the discrete Lagrange–d'Alembert principle).")

    def init(self, terms, t0, t1, y0, args):
        return self._accelerations(t0, y0, args)

    @staticmethod
    def _accelerations(t, y, args):
        from ._dynamics import equations_of_motion

        dynamics, p, factorisation, _ = args
        q, u = y
        return equations_of_motion(dynamics, t, q, u, p, factorisation)[1]

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        dynamics, p, _, _ = args
        q0, u0 = y0
        h = t1 - t0
        a0 = jax.lax.cond(made_jump, lambda: self._accelerations(t0, y0, args),
                          lambda: solver_state)
        half = u0 + h / 2 * a0
        q1 = q0 + h * dynamics.coordinate_rates(t0, q0, half, p)
        a1 = self._accelerations(t1, (q1, half), args)
        u1 = half + h / 2 * a1
        y1 = (q1, u1)
        rates0 = dynamics.coordinate_rates(t0, q0, u0, p)
        rates1 = dynamics.coordinate_rates(t1, q1, u1, p)
        dense_info = _hermite(t0, t1, y0, y1, (rates0, a0), (rates1, a1))
        return y1, None, dense_info, a1, diffrax.RESULTS.successful


def discrete_forces(dynamics, p, t0, t1, q0, rule, force=None):
    """v ↦ (D₁L_d + F_d^−, D₂L_d + F_d^+) at (q_k, q_{k+1} = q_k + h v), h = t1 − t0, for a
    `Lagrangian` with its non-conservative forces plus `force(t, q, q̇)` (further
    generalized forces, such as inputs B r) in the rule's quadrature."""
    h = t1 - t0

    def forces(t, q, v):
        total = dynamics._nonconservative(t, q, v, p)
        return total if force is None else total + force(t, q, v)

    def forced(v):
        q1 = q0 + h * v
        if rule == "midpoint":
            tm, qm = t0 + h / 2, (q0 + q1) / 2
            dL_dq, dL_dv = _gradients(dynamics, tm, qm, v, p)
            half = h / 2 * (dL_dq + forces(tm, qm, v))
            return half - dL_dv, half + dL_dv
        dL_dq0, dL_dv0 = _gradients(dynamics, t0, q0, v, p)
        dL_dq1, dL_dv1 = _gradients(dynamics, t1, q1, v, p)
        mean_dv = (dL_dv0 + dL_dv1) / 2
        return (h / 2 * (dL_dq0 + forces(t0, q0, v)) - mean_dv,
                h / 2 * (dL_dq1 + forces(t1, q1, v)) + mean_dv)

    return forced


def newton_method(dtype, rtol=None, atol=None):
    """Newton's method at tolerances √ε of `dtype` unless given: it converges quadratically,
    so the solution is then exact to round-off."""
    tol = float(np.sqrt(np.finfo(dtype).eps))
    return optx.Newton(rtol=tol if rtol is None else rtol, atol=tol if atol is None else atol)


def speeds_of_momentum(dynamics, t, q, guess, p, momentum, newton, max_steps):
    """(q̇ with ∂L/∂q̇(t, q, q̇) = p, whether found): one Newton step from `guess` (exact when
    T is quadratic in q̇, as for every mechanical system: ∂L/∂q̇ is then affine in q̇ with the
    mass matrix as its slope), then Newton's method only where that left a residual."""
    def residual(speeds):
        return conjugate_momentum(dynamics, t, q, speeds, p) - momentum

    value, slope = jax.linearize(residual, guess)
    mass_matrix = jax.vmap(slope)(jnp.eye(guess.shape[0], dtype=guess.dtype))
    speeds = guess - spd_solve(mass_matrix, value)[0]
    left = residual(speeds)
    scale = newton.atol + newton.rtol * jnp.max(jnp.abs(momentum))
    solved = jnp.max(jnp.abs(left)) <= scale

    def iterate():
        # The root's derivative solved in the least-squares sense: a branch not taken is
        # differentiated too wherever `cond` runs as a select (under vmap), and the
        # linearisation (`jax.linearize`, reverse mode) gives it zeros for its values, so that
        # its Jacobian is zero there; solved by LU, that is NaN, which lineax raises as an
        # error although the select discards it.
        sol = optx.root_find(lambda x, _: residual(x), newton, speeds, max_steps=max_steps,
                             throw=False, adjoint=optx.ImplicitAdjoint(
                                 linear_solver=lx.AutoLinearSolver(well_posed=False)))
        return sol.value, sol.result == optx.RESULTS.successful

    return jax.lax.cond(solved, lambda: (speeds, jnp.array(True)), iterate)


def _gradients(dynamics, t, q, v, p):
    """(∂L/∂q, ∂L/∂q̇) of a `Lagrangian`."""
    return jax.grad(dynamics._lagrangian, argnums=(1, 2))(t, q, v, p)


def conjugate_momentum(dynamics, t, q, v, p):
    """The momentum ∂L/∂q̇ (Legendre transform) of a `Lagrangian`."""
    return jax.grad(dynamics._lagrangian, argnums=2)(t, q, v, p)
