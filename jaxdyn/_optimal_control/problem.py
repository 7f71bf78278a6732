"""The optimal control problem in discrete time: a horizon of N nodes, the dynamics discretised
by a fixed-step one-step method, running and terminal costs.

    minimise   J = Σ_{k<N} Δt ℓ(t_k, q_k, u_k, r_k, p) + Φ(t_N, q_N, u_N, p)
    subject to x_{k+1} = F_Δt(t_k, x_k, r_k, p),   x_0 = (q0, u0),   r_lo ≤ r_k ≤ r_hi,

with x = (q, u) the state of a `jaxdyn` formulation driven by inputs r (`jaxdyn.Controlled`),
r held constant over each interval (a zero-order hold), t_k = t0 + k Δt.
"""

import abc
import functools
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._convention import call
from .._custom_jvp import jvp_of_perturbed
from .._dynamics import AbstractDynamics, equations_of_motion, formed_mass_matrix
from .._form.articulated import ArticulatedBody
from .._form.constraints import Constrained
from .._form.contact import Contact
from .._form.controlled import Controlled, find_controlled
from .._form.euler_lagrange import Lagrangian
from .._form.gibbs_appell import GibbsAppell
from .._form.kane import Kane
from .._linalg import spd_solve
from .._variational import (VariationalIntegrator, conjugate_momentum, discrete_forces,
                             newton_method, speeds_of_momentum)

_RUNNING_ARGS = ("q", "u", "r", "p")
_TERMINAL_ARGS = ("q", "u", "p")


class AbstractDiscretisation(eqx.Module):
    """A fixed-step one-step method x_{k+1} = F_Δt(t_k, x_k, r_k) for q̇ = K u, u̇ = a(q, u, r)
    with the inputs held over the step."""

    # The largest Δt |λ| for which the method damps ẋ = λx with λ < 0 (its stability interval
    # on the negative real axis), or None for a method that is not explicit: a relaxation of
    # time constant τ needs Δt < limit · τ.
    stability_limit: ClassVar[float | None] = None

    @abc.abstractmethod
    def step(self, field, rates, t, q, u, dt, system=None) -> tuple[jax.Array, jax.Array]:
        """(q_{k+1}, u_{k+1}) from (q_k, u_k); `field(t, q, u) → (q̇, u̇)`, `rates(t, q, u) → q̇`,
        `system`: (the formulation driven by the step's inputs, p), for methods built from the
        system itself rather than its equations of motion."""

    def check(self, dynamics) -> None:
        """Raise a ValueError if this method cannot discretise `dynamics`."""


class Euler(AbstractDiscretisation):
    """The explicit Euler method, x_{k+1} = x_k + Δt ẋ(t_k, x_k): first order."""

    stability_limit: ClassVar[float | None] = 2.0

    def step(self, field, rates, t, q, u, dt, system=None):
        qd, ud = field(t, q, u)
        return q + dt * qd, u + dt * ud


class SemiImplicitEuler(AbstractDiscretisation):
    """The symplectic (semi-implicit) Euler method, first order: the speeds first, then the
    coordinates with the new speeds,

        u_{k+1} = u_k + Δt u̇(t_k, q_k, u_k),   q_{k+1} = q_k + Δt K(q_k) u_{k+1},

    Crocoddyl's default integrated action model (`IntegratedActionModelEuler`), which keeps
    a pendulum's energy bounded where the explicit method lets it grow."""

    # (a contact scene's ground deformations ξ are coordinates whose rates depend on
    # themselves, ξ̇ = ξ̇(q, ξ, u): the method steps them explicitly in ξ)
    stability_limit: ClassVar[float | None] = 2.0

    def step(self, field, rates, t, q, u, dt, system=None):
        _, ud = field(t, q, u)
        u_next = u + dt * ud
        return q + dt * rates(t, q, u_next), u_next


class RungeKutta4(AbstractDiscretisation):
    """The classical fourth-order Runge–Kutta method (Kutta, 1901) with the inputs held over
    the step:

        k₁ = ẋ(t, x),  k₂ = ẋ(t + Δt/2, x + Δt k₁/2),  k₃ = ẋ(t + Δt/2, x + Δt k₂/2),
        k₄ = ẋ(t + Δt, x + Δt k₃),   x_{k+1} = x + Δt (k₁ + 2k₂ + 2k₃ + k₄)/6."""

    # (|1 + z + z²/2 + z³/6 + z⁴/24| ≤ 1 for −2.785 ≤ z ≤ 0)
    stability_limit: ClassVar[float | None] = 2.785

    def step(self, field, rates, t, q, u, dt, system=None):
        def stage(c, dq, du):
            return field(t + c * dt, q + c * dt * dq, u + c * dt * du)

        k1 = field(t, q, u)
        k2 = stage(0.5, *k1)
        k3 = stage(0.5, *k2)
        k4 = stage(1.0, *k3)
        dq, du = (a + 2 * b + 2 * c + d for a, b, c, d in zip(k1, k2, k3, k4))
        return q + dt / 6 * dq, u + dt / 6 * du


class VariationalStep(AbstractDiscretisation):
    r"""A step of a variational integrator (`jaxdyn.VariationalIntegrator`, Marsden and West,
    Acta Numerica 10, 2001) of a `jaxdyn.Lagrangian` driven by inputs: the discrete
    Lagrange–d'Alembert principle with the discrete Lagrangian of `rule`,

        p_k = −D₁L_d(q_k, q_{k+1}) − F_d^−,   p_{k+1} = D₂L_d(q_k, q_{k+1}) + F_d^+,

    the forces F (the Lagrangian's non-conservative forces and the inputs' B r, held over the
    step) in the same quadrature; the first equation solved for q_{k+1} by Newton's method
    (differentiated by the implicit function theorem), the speeds from p_{k+1} = ∂L/∂q̇. Second
    order, symplectic: the discrete dynamics of an optimal control problem whose horizon is
    long against the motion's periods, where an explicit method's energy drifts (Junge, Marsden
    and Ober-Blöbaum, "Discrete mechanics and optimal control", IFAC 2005). A step whose Newton
    iteration does not converge gives NaN (the line search then refuses it).

    **Arguments:**

    - `rule`: "midpoint" (default) or "trapezoidal", as `jaxdyn.VariationalIntegrator`.
    - `max_newton_steps`: Newton iterations per step.
    """

    rule: Literal["midpoint", "trapezoidal"] = eqx.field(default="midpoint", static=True)
    max_newton_steps: int = eqx.field(default=32, static=True)

    def __check_init__(self):
        VariationalIntegrator(rule=self.rule, max_newton_steps=self.max_newton_steps)

    def check(self, dynamics):
        if not (isinstance(dynamics, Controlled) and isinstance(dynamics.dynamics, Lagrangian)):
            raise ValueError(
                "VariationalStep is built from a Lagrangian L(t, q, q̇): it needs "
                "jaxdyn.Controlled(jaxdyn.Lagrangian(...), input_map), got "
                f"{type(dynamics).__name__}"
                + (f"({type(dynamics.dynamics).__name__})" if isinstance(dynamics, Controlled)
                   else "") + ". Other formulations: RungeKutta4, SemiImplicitEuler or Euler.")

    def step(self, field, rates, t, q, u, dt, system=None):
        if system is None:
            raise ValueError("VariationalStep needs the system (ShootingProblem passes it).")
        driven, p = system
        lagrangian = driven.dynamics
        newton = newton_method(q.dtype)
        forced = discrete_forces(lagrangian, p, t, t + dt, q, self.rule,
                                 lambda t, q, v: driven.applied(t, q, v, p))
        momentum = conjugate_momentum(lagrangian, t, q, u, p)
        # Solved for the mean velocity v = (q_{k+1} − q_k)/Δt, from the speeds at the middle
        # of the step (within O(Δt²) of it), as `VariationalIntegrator` does.
        guess = u + dt / 2 * field(t, q, u)[1]
        root = optx.root_find(lambda v, _: momentum + forced(v)[0], newton, guess,
                              max_steps=self.max_newton_steps, throw=False)
        q_next = q + dt * root.value
        u_next, speeds_found = speeds_of_momentum(lagrangian, t + dt, q_next, root.value, p,
                                                  forced(root.value)[1], newton,
                                                  self.max_newton_steps)
        found = (root.result == optx.RESULTS.successful) & speeds_found
        return jnp.where(found, q_next, jnp.nan), jnp.where(found, u_next, jnp.nan)


class ShootingProblem(eqx.Module):
    r"""An optimal control problem over N intervals of Δt of a system with inputs:

        minimise   Σ_{k<N} Δt ℓ(q_k, u_k, r_k, p) + Φ(q_N, u_N, p)
        subject to (q, u)_{k+1} = F_Δt((q, u)_k, r_k),   (q, u)_0 = (q0, u0),
                   r_lo ≤ r_k ≤ r_hi,   c(q_k, u_k, r_k, p) ≤ 0 (k < N),
                   h(q_N, u_N, p) = 0,

    F_Δt one step of `discretisation` of the equations of motion q̇ = K u,
    M u̇ = f + B r with r held over the step. The running cost is integrated by the
    rectangle rule (Δt ℓ at each node), as Crocoddyl does with its Euler models.

    **Arguments:**

    - `dynamics`: any jaxdyn formulation driven by inputs (`jaxdyn.Controlled`, possibly
      inside `Constrained` or a compliant `Contact` scene): `Lagrangian`, `GibbsAppell`,
      `Kane`, `ArticulatedBody` (robots). A `Contact` scene's coordinates are (q, ξ), the
      ground's deformations appended; an explicit step must be shorter than twice their
      relaxation time c_t/k_t (2.785 times for `RungeKutta4`), else a `ValueError`.
    - `running_cost`: ℓ(q, u, r, p) → a scalar, or a residual vector ρ for ℓ = ½‖ρ‖²
      (ℓ(t, q, u, r, p) with `time_dependent`). Write least-squares costs (tracking,
      reaching, regularisation, weights folded into ρ) as residuals: iLQR then uses the
      Gauss–Newton Hessian ρ'ᵀρ', positive semidefinite wherever the trajectory is, as
      Crocoddyl's residual costs do; a scalar's Hessian is exact, and where it is indefinite
      (a squared distance through nonlinear kinematics, far from the target) the
      regularisation has to make up for it.
    - `terminal_cost`: Φ(q, u, p) → a scalar or a residual vector (Φ(t, q, u, p) with
      `time_dependent`); None: 0.
    - `num_nodes`: N, the number of intervals.
    - `dt`: Δt, the interval.
    - `discretisation`: `jaxdyn.RungeKutta4()` (default), `jaxdyn.SemiImplicitEuler()`,
      `jaxdyn.Euler()` or, for a `Lagrangian`, `jaxdyn.VariationalStep()` (a variational
      integrator's step).
    - `input_bounds`: (r_lo, r_hi), arrays of shape (k,) or scalars (±inf where unbounded);
      None for unbounded inputs.
    - `path_constraints`: c(q, u, r, p) → a vector, kept c ≤ 0 at every node k < N (limits
      of a state: a cart's travel, a joint's range; of an input's combination: a friction
      cone, a power limit; c(t, q, u, r, p) with `time_dependent`); None: none.
    - `terminal_constraints`: h(q, u, p) → a vector, made h = 0 at node N (reach a state
      exactly rather than by a terminal cost's weight); None: none.
    - `t0`: the time of node 0.
    - `time_dependent`: whether the costs and constraints take t first.

    With constraints, `jaxdyn.solve_optimal_control` solves by an augmented Lagrangian about
    the solver (Hestenes–Powell–Rockafellar; ALTRO's outer loop, Howell, Jackson and
    Manchester, IROS 2019): the solver minimises the costs with Δt⁻¹ ½ μ ‖max(0, c + λ/μ)‖²
    added at each node and ½ μ ‖h + ν/μ‖² at node N, then λ ← max(0, λ + μ c), ν ← ν + μ h,
    μ grown tenfold where the violation did not fall fourfold, until the constraints hold,
    and are complementary to their multipliers (λ_k = 0 where c_k < 0), to the solver's
    `constraint_tol`.

    Targets and weights that you want to differentiate the optimum with respect to belong in
    p, with the physical parameters: `jaxdyn.solve_optimal_control` differentiates with respect
    to q0, u0, p and the floating-point arrays the dynamics hold (a tree's masses, inertias and
    gravity; the places where `HeldPoints` hold a robot), not with respect to the costs' own
    constants.

    **Example** (a cart-pole swung up):

        problem = jaxdyn.ShootingProblem(
            plant, running_cost=lambda q, u, r, p: 1e-2 * r @ r,
            terminal_cost=lambda q, u, p: 1e3 * ((q - target) @ (q - target) + u @ u),
            num_nodes=100, dt=0.02, input_bounds=(-20.0, 20.0))
    """

    dynamics: AbstractDynamics
    running_cost: object = eqx.field(static=True)
    terminal_cost: object = eqx.field(static=True)
    num_nodes: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    discretisation: AbstractDiscretisation = RungeKutta4()
    input_bounds: tuple | None = eqx.field(default=None, static=True)
    t0: float | jax.Array | np.ndarray = 0.0
    time_dependent: bool = eqx.field(default=False, static=True)
    path_constraints: object = eqx.field(default=None, static=True)
    terminal_constraints: object = eqx.field(default=None, static=True)

    def __check_init__(self):
        if not isinstance(self.dynamics, AbstractDynamics):
            raise ValueError("ShootingProblem needs a jaxdyn formulation (AbstractDynamics), "
                             f"got {type(self.dynamics).__name__}.")
        if find_controlled(self.dynamics) is None:
            raise ValueError(f"{type(self.dynamics).__name__} declares no inputs to optimise: "
                             "wrap the formulation as jaxdyn.Controlled(dynamics, input_map).")
        if not callable(self.running_cost):
            raise ValueError("running_cost must be a function ℓ(q, u, r, p) → scalar.")
        if self.terminal_cost is not None and not callable(self.terminal_cost):
            raise ValueError("terminal_cost must be a function Φ(q, u, p) → scalar, or None.")
        if int(self.num_nodes) != self.num_nodes or self.num_nodes < 1:
            raise ValueError(f"num_nodes must be a positive integer, got {self.num_nodes!r}.")
        if not float(self.dt) > 0:
            raise ValueError(f"dt must be positive, got {self.dt!r}.")
        if not isinstance(self.discretisation, AbstractDiscretisation):
            raise ValueError("discretisation must be jaxdyn.RungeKutta4(), "
                             "jaxdyn.SemiImplicitEuler(), jaxdyn.Euler() or "
                             "jaxdyn.VariationalStep(), got "
                             f"{type(self.discretisation).__name__}.")
        self.discretisation.check(self.dynamics)
        _check_contact_steps(self.dynamics, self.discretisation, float(self.dt))
        if self.input_bounds is not None and len(self.input_bounds) != 2:
            raise ValueError("input_bounds must be a pair (r_lo, r_hi).")
        for name, value, form in (("path_constraints", self.path_constraints,
                                   "c(q, u, r, p) → vector (c ≤ 0)"),
                                  ("terminal_constraints", self.terminal_constraints,
                                   "h(q, u, p) → vector (h = 0)")):
            if value is not None and not callable(value):
                raise ValueError(f"{name} must be a function {form}, or None.")

    def __init__(self, dynamics, running_cost, terminal_cost=None, *, num_nodes, dt,
                 discretisation=RungeKutta4(), input_bounds=None, t0=0.0,
                 time_dependent=False, path_constraints=None, terminal_constraints=None):
        self.dynamics = dynamics
        self.running_cost = running_cost
        self.terminal_cost = terminal_cost
        self.num_nodes = int(num_nodes)
        self.dt = float(dt)
        self.discretisation = discretisation
        # Static Python floats, so that a problem is hashed by value and a new problem with
        # the same bounds reuses the compiled solver.
        self.input_bounds = None if input_bounds is None else tuple(
            tuple(float(v) for v in jnp.ravel(jnp.asarray(b, float))) for b in input_bounds)
        # A number becomes a NumPy scalar, which the compiled solver takes as an input: a new
        # t0 (a receding horizon's) then reuses the program instead of compiling another.
        self.t0 = np.asarray(t0, dtype=float) if isinstance(t0, (int, float)) else t0
        self.time_dependent = time_dependent
        self.path_constraints = path_constraints
        self.terminal_constraints = terminal_constraints

    # -- the discrete dynamics ------------------------------------------------------------------

    def times(self, dtype=float):
        """t_k = t0 + k Δt, k = 0 … N."""
        return self.t0 + self.dt * jnp.arange(self.num_nodes + 1, dtype=dtype)

    def num_inputs(self, q, u, p=None) -> int:
        """k, the number of inputs."""
        controlled = find_controlled(self.dynamics)
        assert controlled is not None
        return controlled.num_inputs(q, u, p)

    def step(self, t, x, r, p, num_q):
        """x_{k+1} = F_Δt(t_k, x_k, r_k): one step of the discretisation, r held."""
        return jnp.concatenate(_split_step(self, t, x[:num_q], x[num_q:], r, p))

    def split_step(self, t, q, u, r, p):
        """(q_{k+1}, u_{k+1}) = F_Δt(t_k, (q_k, u_k), r_k): `step` with the coordinates and
        speeds apart, whose Jacobians in each are formed without perturbing the other."""
        return _split_step(self, t, q, u, r, p)

    def _split_step(self, t, q, u, r, p):
        driven = self.dynamics.with_inputs(r)
        implicit = (_accelerations if _residual_is_equations(self.dynamics) else
                    first_kind_accelerations if _first_kind_residuals(self.dynamics) else None)

        def field(t, q, u):
            if implicit is not None:
                return (driven.coordinate_rates(t, q, u, p),
                        implicit(self.dynamics, t, q, u, r, p))
            rates, accelerations_, _, _ = equations_of_motion(driven, t, q, u, p)
            return rates, accelerations_

        def rates(t, q, u):
            return driven.coordinate_rates(t, q, u, p)

        return self.discretisation.step(field, rates, t, q, u, jnp.asarray(self.dt, q.dtype),
                                        system=(driven, p))

    def bounds(self, num_inputs, dtype):
        """(r_lo, r_hi) as arrays of shape (k,) (±inf where unbounded), (None, None) for a
        problem without bounds."""
        if self.input_bounds is None:
            return None, None
        lo, hi = (jnp.broadcast_to(jnp.asarray(b, dtype), (num_inputs,))
                  for b in self.input_bounds)
        return lo, hi

    # -- the costs ------------------------------------------------------------------------------

    def running_value(self, t, q, u, r, p):
        """ℓ as the user's function returns it: a scalar, or a residual vector ρ."""
        return _cost_value(call(self.running_cost, "running cost ℓ", self.time_dependent,
                                _RUNNING_ARGS, t, q, u, r, p), "running cost ℓ")

    def final_value(self, t, q, u, p):
        """Φ as the user's function returns it: a scalar, or a residual vector ρ."""
        if self.terminal_cost is None:
            return jnp.zeros((), q.dtype)
        return _cost_value(call(self.terminal_cost, "terminal cost Φ", self.time_dependent,
                                _TERMINAL_ARGS, t, q, u, p), "terminal cost Φ")

    # -- the constraints ------------------------------------------------------------------------

    @property
    def constrained(self) -> bool:
        """Whether the problem has path or terminal constraints."""
        return self.path_constraints is not None or self.terminal_constraints is not None

    def path_value(self, t, q, u, r, p):
        """c(t_k, q_k, u_k, r_k, p) (c ≤ 0), shape (c,); (0,) without path constraints."""
        if self.path_constraints is None:
            return jnp.zeros((0,), q.dtype)
        return _constraint_value(call(self.path_constraints, "path constraints c",
                                      self.time_dependent, _RUNNING_ARGS, t, q, u, r, p),
                                 "path constraints c")

    def terminal_value(self, t, q, u, p):
        """h(t_N, q_N, u_N, p) (h = 0), shape (e,); (0,) without terminal constraints."""
        if self.terminal_constraints is None:
            return jnp.zeros((0,), q.dtype)
        return _constraint_value(call(self.terminal_constraints, "terminal constraints h",
                                      self.time_dependent, _TERMINAL_ARGS, t, q, u, p),
                                 "terminal constraints h")

    def node_cost(self, t, q, u, r, p):
        """Δt ℓ(t_k, q_k, u_k, r_k, p), the running cost of node k (ℓ = ½‖ρ‖² for a
        residual)."""
        return self.dt * _as_cost(self.running_value(t, q, u, r, p))

    def final_cost(self, t, q, u, p):
        """Φ(t_N, q_N, u_N, p), the terminal cost (0 when None; ½‖ρ‖² for a residual)."""
        return _as_cost(self.final_value(t, q, u, p))

    def cost(self, xs, rs, p, num_q):
        """J = Σ_{k<N} Δt ℓ_k + Φ_N of a trajectory (xs (N+1, n), rs (N, k))."""
        ts = self.times(xs.dtype)
        running = jax.vmap(self.node_cost, in_axes=(0, 0, 0, 0, None))(
            ts[:-1], xs[:-1, :num_q], xs[:-1, num_q:], rs, p)
        return jnp.sum(running) + self.final_cost(ts[-1], xs[-1, :num_q], xs[-1, num_q:], p)

    def rollout(self, x0, rs, p, num_q):
        """The states x_0 … x_N reached from x0 under the inputs rs (a single shooting)."""
        ts = self.times(x0.dtype)

        def one(x, step):
            t, r = step
            x_next = self.step(t, x, r, p, num_q)
            return x_next, x_next

        _, xs = jax.lax.scan(one, x0, (ts[:-1], rs))
        return jnp.concatenate([x0[None], xs])


# The step is traced once per problem and shapes: the rollout, the line search's trials, the
# expansion's Jacobians, DDP's curvature, the sensitivities of an optimum and MPC all call
# it, each under its own transformations (vmap, jacfwd, hessian, grad), which JAX then applies
# to the one trace (and caches) instead of running the user's energies through them again in
# Python. The cart-pole from T and V (RK4, 100 nodes, the optimal-control guide): the first
# jax.grad of the optimal cost 27 → 19 s, the first solve with the variational step 10.8 →
# 9.5 s (benchmarks/LOG.md, "A step traced once").
@eqx.filter_jit
def _split_step(problem, t, q, u, r, p):
    return problem._split_step(t, q, u, r, p)


def _residual_is_equations(dynamics) -> bool:
    """Whether the system's residual R(q, u, u̇, r) = M u̇ − f − B r is the equations its
    accelerations solve: a formulation driven directly, not constrained or in contact."""
    return isinstance(dynamics, Controlled) and isinstance(
        dynamics.dynamics, (Lagrangian, GibbsAppell, Kane, ArticulatedBody))


# The implicit accelerations below are custom JVPs of the system's arrays as well as of the
# state, inputs and parameters: a tree's masses, inertias and gravity, a hold's positions are
# as differentiable as p (were the system a non-differentiated argument, their derivatives
# would be dropped silently, and a transformation outside a jit would close over its tracers).
# Tangents that are symbolic zeros (the arrays, under the expansion's Jacobians in the state)
# are not propagated: `jvp_of_perturbed`.

def accelerations(dynamics, t, q, u, r, p):
    """u̇(q, u, r) of M u̇ = f + B r, differentiated through the residual: from
    R(q, u, u̇(q, u, r), r) = 0,

        δu̇ = −M⁻¹ (∂R/∂t δt + ∂R/∂q δq + ∂R/∂u δu + ∂R/∂r δr + ∂R/∂p δp + ∂R/∂s δs),

    s the system's arrays; one forward-mode pass of the residual (for a tree, the recursive
    Newton–Euler algorithm) per direction and one factorisation of M, instead of the
    derivative of the solve itself (for a tree, of the articulated-body algorithm): the route
    of Carpentier and Mansard's analytical derivatives of rigid-body dynamics (RSS 2018), here
    by autodiff."""
    arrays, rest = eqx.partition(dynamics, eqx.is_array)
    return _driven_accelerations(rest, arrays, t, q, u, r, p)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _driven_accelerations(rest, arrays, t, q, u, r, p):
    dynamics = eqx.combine(arrays, rest)
    return equations_of_motion(dynamics.with_inputs(r), t, q, u, p)[1]


def _driven_accelerations_jvp(rest, primals, tangents):
    arrays, t, q, u, r, p = primals
    dynamics = eqx.combine(arrays, rest)
    driven = dynamics.with_inputs(r)
    ud = equations_of_motion(driven, t, q, u, p)[1]
    mass_matrix = formed_mass_matrix(driven, t, q, u, p)
    _, d_residual = jvp_of_perturbed(
        lambda arrays, t, q, u, r, p: _residual(eqx.combine(arrays, rest), t, ud, q, u, r, p),
        primals, tangents, like=ud)
    return ud, -spd_solve(mass_matrix, d_residual)[0]


_driven_accelerations.defjvp(_driven_accelerations_jvp, symbolic_zeros=True)


# traced once per system and shapes, however often its JVP is asked for
@eqx.filter_jit
def _residual(dynamics, t, ud, q, u, r, p):
    return dynamics.with_inputs(r).form_residual(t, q, u, ud, p)


# Called through `jax.jit`, the stages of a step share one trace of the accelerations and JAX
# caches the derivatives of that trace (its JVP rule is traced once, not once per stage and
# per transformation); see `_split_step`.
_accelerations = eqx.filter_jit(accelerations)


def _first_kind_residuals(dynamics) -> bool:
    """Whether the system is Lagrange's equations of the first kind on a formulation driven
    directly (`Constrained` about one that `_residual_is_equations` accepts)."""
    return isinstance(dynamics, Constrained) and _residual_is_equations(dynamics.dynamics)


def first_kind_accelerations(dynamics, t, q, u, r, p):
    """u̇(q, u, r) of Lagrange's equations of the first kind, M u̇ = f + B r + Cᵀλ,
    C u̇ = c, differentiated through their residuals R₁ = M u̇ − f − B r − Cᵀλ and
    R₂ = C u̇ − c at the solution: with ∂R the derivatives at fixed (u̇, λ),

        M δu̇ − Cᵀ δλ = −∂R₁ · δx,      C δu̇ = −∂R₂ · δx,

    x the time, state, inputs, parameters and the system's arrays; one forward-mode pass of the
    residuals (for a tree, the recursive Newton–Euler algorithm and the constraints'
    kinematics) per direction, solved with the factors of the accelerations' own system
    (`FirstKind`), instead of the derivative of the solve itself: the route of Carpentier and
    Mansard's analytical derivatives, here by autodiff."""
    arrays, rest = eqx.partition(dynamics, eqx.is_array)
    return _first_kind_accelerations(rest, arrays, t, q, u, r, p)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _first_kind_accelerations(rest, arrays, t, q, u, r, p):
    dynamics = eqx.combine(arrays, rest)
    return equations_of_motion(dynamics.with_inputs(r), t, q, u, p)[1]


def _first_kind_accelerations_jvp(rest, primals, tangents):
    arrays, t, q, u, r, p = primals
    ud, multipliers, kkt = eqx.combine(arrays, rest).with_inputs(r).first_kind(t, q, u, p)

    def residuals(arrays, t, q, u, r, p):
        driven = eqx.combine(arrays, rest).with_inputs(r)
        return driven.first_kind_residuals(t, q, u, ud, multipliers, p)

    like = (ud, jnp.zeros(kkt.jacobian.shape[0], ud.dtype))
    _, (d_first, d_second) = jvp_of_perturbed(residuals, primals, tangents, like=like)
    return ud, kkt.solve(-d_first, -d_second)[0]


_first_kind_accelerations.defjvp(_first_kind_accelerations_jvp, symbolic_zeros=True)


def _check_contact_steps(dynamics, discretisation, dt):
    """A ValueError where a compliant contact scene's ground deformation relaxes faster than
    the fixed explicit step can follow: ξ would grow without bound (off contact ξ̇ = −ξ/τ),
    and with it friction would be lost, while the solver still converges on the wrong
    physics."""
    limit = discretisation.stability_limit
    if limit is None:
        return
    scenes = [x for x in jax.tree_util.tree_leaves(
        dynamics, is_leaf=lambda x: isinstance(x, Contact)) if isinstance(x, Contact)]
    for scene in scenes:
        tau = scene.model.relaxation_time()
        if tau is not None and dt >= limit * tau:
            raise ValueError(
                f"The contact scene's ground deformation relaxes in τ = c_t/k_t = "
                f"{tau * 1e3:.3g} ms, faster than {type(discretisation).__name__}'s fixed step "
                f"of {dt * 1e3:.3g} ms can follow (stable below {limit:g}τ = "
                f"{limit * tau * 1e3:.3g} ms): the deformation would grow without bound and "
                "friction be lost. Take a shorter dt, or a slower relaxation: "
                f"HuntCrossley(..., tangential_damping=k_t × τ) with τ > {dt / limit * 1e3:.3g} "
                "ms.")


def _cost_value(value, name):
    value = jnp.asarray(value)
    if value.ndim > 1:
        raise ValueError(f"the {name} must return a scalar or a residual vector ρ (ℓ = ½‖ρ‖²),"
                         f" got shape {value.shape}.")
    return value


def _constraint_value(value, name):
    value = jnp.asarray(value)
    if value.ndim > 1:
        raise ValueError(f"the {name} must return a scalar or a vector, got shape "
                         f"{value.shape}.")
    return jnp.atleast_1d(value)


def _as_cost(value):
    return value if value.ndim == 0 else 0.5 * value @ value
