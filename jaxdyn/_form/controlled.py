"""Control inputs: generalized forces B(q, p) r added to a formulation's equations."""

import inspect
from typing import Any, Callable, TypeGuard

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._convention import CONFIGURATION_ARGS, call
from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._state import check_vector, public_method
from .._system.bodies import vee
from .articulated import ArticulatedBody, articulated_body_algorithm


class ForceInput(eqx.Module):
    r"""An input map for a force applied at a point P(q, p) of the system: the inputs are the
    force's components along `directions`, and they enter the equations as the generalized
    active forces (Kane and Levinson, *Dynamics: Theory and Applications*, 1985, §4.4)

        B = (∂v_P/∂u)ᵀ D,    v_P = (∂P/∂q) q̇ = (∂P/∂q) K(q) u,

    with ∂v_P/∂u the point's partial velocities along the formulation's speeds u (q̇ = K u) and
    D (3, k) the directions in world axes.

    **Arguments:**

    - `point`: P(q, p) → (3,) (or (2,) for a planar system), the point in world axes, e.g.
      a body's ``position`` or ``lambda q, p: x(q, p) + R(q, p) @ r`` for a point r fixed on
      it. (`jaxdyn.PointForce` is the same force as a load of a `MultibodySystem`, given as a
      function rather than as inputs.)
    - `directions`: D as an array (d, k) of fixed world directions, or a function D(q, p) →
      (d, k) (e.g. ``lambda q, p: R(q, p)[:, :1]``, a thrust along a body axis); None for the
      world axes (k = d).

    **Example** (a horizontal push on a cart-pole's bob):

        plant = jaxdyn.Controlled(system, jaxdyn.ForceInput(bob, directions=[[1.0], [0.0]]))
    """

    point: Callable
    directions: Any = None

    def matrix(self, controlled, t, q, p, num_speeds):
        """B (m, k) = (∂v_P/∂u)ᵀ D at (t, q) for the `Controlled` system `controlled`, whose
        dynamics has `num_speeds` speeds m (called by `Controlled`, not by users)."""
        rates = _speed_map(controlled.dynamics, t, q, p, num_speeds)  # K (n, m)
        point = lambda q: jnp.asarray(self.point(q, p))  # noqa: E731
        shape = jax.eval_shape(point, q).shape
        if len(shape) != 1:
            raise ValueError(f"ForceInput: point(q, p) must return a vector, got shape {shape}.")
        partial = _along_speeds(point, q, rates)  # ∂v_P/∂u (d, m)
        return partial.T @ _directions(self.directions, q, p, partial.shape[0])


class TorqueInput(eqx.Module):
    r"""An input map for a torque (a couple) applied to a body of orientation R(q, p): the
    inputs are the torque's components along `directions`, entering as

        B = (∂ω/∂u)ᵀ D,    ω̃ = Ṙ Rᵀ,   Ṙ = Σᵢ (∂R/∂qᵢ) q̇ᵢ,   q̇ = K(q) u,

    ∂ω/∂u the body's partial angular velocities (world axes; Kane and Levinson 1985, §4.4).
    A torque between two bodies (a motor) is two `TorqueInput`s of opposite sign, or the
    relative joint coordinate's column.

    **Arguments:**

    - `body`: a `RigidBody` (its orientation), or R(q, p) → (3, 3), body axes to world axes.
      (`jaxdyn.BodyTorque` is the same torque as a load of a `MultibodySystem`, given as a
      function rather than as inputs.)
    - `directions`: D (3, k) in world axes, or a function D(q, p) → (3, k) (body axes:
      ``lambda q, p: R(q, p)``); None for the world axes.
    """

    body: Any
    directions: Any = None

    def matrix(self, controlled, t, q, p, num_speeds):
        """B (m, k) = (∂ω/∂u)ᵀ D at (t, q) for the `Controlled` system `controlled`, whose
        dynamics has `num_speeds` speeds m (called by `Controlled`, not by users)."""
        rates = _speed_map(controlled.dynamics, t, q, p, num_speeds)
        orientation = getattr(self.body, "orientation", self.body)
        rotation = jnp.asarray(orientation(q, p))
        if rotation.shape != (3, 3):
            raise ValueError("TorqueInput: the orientation R(q, p) must be a (3, 3) rotation "
                             f"matrix, got shape {rotation.shape}.")
        rate = _along_speeds(lambda q: jnp.asarray(orientation(q, p)), q, rates)  # (3, 3, m)
        # ω̃ = Ṙ Rᵀ for each speed: the partial angular velocities, world axes (m, 3).
        partial = jax.vmap(lambda r: vee(r @ rotation.T), in_axes=2)(rate)
        return partial @ _directions(self.directions, q, p, 3)


def _along_speeds(fn, q, rates):
    """The rate of fn(q) along each speed (q̇ = K u with u a unit vector): one JVP per column
    of K, stacked last."""
    return jax.vmap(lambda k: jax.jvp(fn, (q,), (k,))[1], out_axes=-1)(rates.T)


def _speed_map(dynamics, t, q, p, num_speeds):
    """K(q) of q̇ = K u: the coordinate rates are linear in the speeds."""
    zero = jnp.zeros((num_speeds,), q.dtype)
    return jax.jacfwd(lambda u: dynamics.coordinate_rates(t, q, u, p))(zero)


def _directions(directions, q, p, dimension):
    if directions is None:
        return jnp.eye(dimension, dtype=q.dtype)
    value = jnp.asarray(directions(q, p) if callable(directions) else directions, q.dtype)
    if value.ndim != 2 or value.shape[0] != dimension:
        raise ValueError(f"directions must be an array ({dimension}, k) (one column per "
                         f"input), got shape {value.shape}.")
    return value


class Controlled(AbstractDynamics):
    r"""A formulation driven by control inputs r (k,) through an input map B:

        q̇ = K u,        M u̇ = f + B(t, q, p) r,

    B r being generalized forces along the wrapped formulation's speeds u (for Lagrange's
    equations, forces conjugate to q: δW = (B r)·δq). An actuated coordinate is a column of the
    identity; a force F on a point of a body is the column Jᵀ of that point's velocity Jacobian
    ∂v/∂u (Kane and Levinson, *Dynamics: Theory and Applications*, 1985, ch. 4: generalized
    active forces).

    The inputs are carried by the system (`with_inputs`, or `simulate(..., inputs=...)`):

    - an array r (k,): constant inputs (the default is r = 0);
    - a signal r(t): a function of t alone, or a `diffrax` path such as
      ``diffrax.LinearInterpolation(ts, rs)`` or ``diffrax.backward_hermite_coefficients``
      with ``diffrax.CubicInterpolation`` (samples of a measured or planned input);
    - a state-feedback policy r = π(t, q, u, p): any pure JAX function, e.g. an equinox
      module (a neural network); pass arrays it depends on as module fields (``eqx.Partial``),
      not as closed-over values, so that `jax.grad` reaches them.

    Every method of the wrapped formulation's protocol applies with the inputs in force. To
    constrain a controlled system, constrain this wrapper: ``Constrained(Controlled(...), ...)``
    (the multipliers then include the inputs' effect).

    **Arguments:**

    - `dynamics`: the formulation driven (`Lagrangian`, `GibbsAppell`, `Kane`,
      `ArticulatedBody`, `IndependentSpeeds`, …).
    - `input_map`: B(q, p) → (m, k) (B(t, q, p) with `time_dependent`); a constant B as an
      array (m, k); a sequence of the indices of the actuated speeds (B = columns of the
      identity: one input per index); a `ForceInput` or `TorqueInput`; or a tuple of these,
      whose columns are concatenated (the inputs in that order).
    - `inputs`: as above; None for r = 0.
    - `time_dependent`: if True, B takes t first.

    **Example** (a cart-pole pushed on the cart):

        plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])
        sol = jaxdyn.simulate(plant, q0, u0, p, t1=5.0, inputs=lambda t, q, u, p: -K @ x)
    """

    dynamics: AbstractDynamics
    input_map: "Callable | ForceInput | TorqueInput | _Actuated | _Constant | _Stacked | None"
    actuated: tuple[int, ...] | None = eqx.field(static=True)
    inputs: Any = None
    time_dependent: bool = eqx.field(default=False, static=True)

    def __init__(self, dynamics, input_map, inputs=None, *, time_dependent=False):
        if not isinstance(dynamics, AbstractDynamics):
            raise ValueError("Controlled needs a jaxdyn formulation (AbstractDynamics) to "
                             f"drive, got {type(dynamics).__name__}.")
        if isinstance(input_map, (tuple, list)) and any(
                _is_map(x) or isinstance(x, (list, tuple)) for x in input_map):
            self.input_map, self.actuated = _Stacked(tuple(
                x if _is_map(x) else _Actuated(_indices(x)) for x in input_map)), None
        elif _is_map(input_map):
            self.input_map, self.actuated = input_map, None
        elif isinstance(input_map, (np.ndarray, jax.Array)) and input_map.ndim == 2:
            self.input_map, self.actuated = _Constant(input_map), None
        else:
            self.input_map, self.actuated = None, _indices(input_map)
        self.dynamics = dynamics
        self.inputs = inputs
        self.time_dependent = time_dependent

    def with_inputs(self, inputs) -> "Controlled":
        """A copy driven by `inputs` (an array, a signal r(t) or path, or a policy
        π(t, q, u, p))."""
        return Controlled(self.dynamics, self.input_map if self.actuated is None
                          else self.actuated, inputs, time_dependent=self.time_dependent)

    def applied_inputs(self):
        """The inputs in force (`inputs`)."""
        return self.inputs

    # -- the inputs -----------------------------------------------------------------------------

    def _input_matrix(self, t, q, p, num_speeds):
        if self.actuated is not None:
            return _Actuated(self.actuated).matrix(self, t, q, p, num_speeds)
        if isinstance(self.input_map, _MAPS):
            return self.input_map.matrix(self, t, q, p, num_speeds)
        matrix = jnp.asarray(call(self.input_map, "input map B", self.time_dependent,
                                  CONFIGURATION_ARGS, t, q, p))
        if matrix.ndim != 2 or matrix.shape[0] != num_speeds:
            raise ValueError(f"input map B must return an array of shape (m, k) with m = "
                             f"{num_speeds} speeds, got shape {matrix.shape}.")
        return matrix.astype(q.dtype)

    def num_inputs(self, q, u, p=None) -> int:
        """k, the number of inputs (read from B's shape)."""
        if self.actuated is not None:
            return len(self.actuated)
        t = jnp.zeros((), jnp.asarray(q).dtype)
        return jax.eval_shape(lambda q, u: self._input_matrix(t, q, p, u.shape[0]),
                              jnp.asarray(q), jnp.asarray(u)).shape[1]

    def _inputs_at(self, t, q, u, p, k=None):
        """r at one state, checked against B's k columns (read from B when not given)."""
        k = self.num_inputs(q, u, p) if k is None else k
        inputs = self.inputs
        if inputs is None:
            return jnp.zeros((k,), q.dtype)
        if isinstance(inputs, diffrax.AbstractPath):
            value = inputs.evaluate(t)
        elif callable(inputs):
            value = inputs(t) if _takes_time_only(inputs) else inputs(t, q, u, p)
        else:
            value = inputs
        value = jnp.asarray(value)
        if value.shape != (k,):
            raise ValueError(f"the inputs r must have shape ({k},) (the input map B has {k} "
                             f"columns), got shape {value.shape}.")
        return value.astype(q.dtype)

    def applied(self, t, q, u, p):
        """B r at one state: the generalized forces of the inputs along the speeds."""
        matrix = self._input_matrix(t, q, p, u.shape[0])
        return matrix @ self._inputs_at(t, q, u, p, matrix.shape[1])

    @public_method("(),(n),(m)->(m,k)")
    def input_matrix(self, t, q, u, p=None):
        """B(t, q, p), the input map: generalized forces along the speeds per unit input."""
        q, u = check_vector(q, "q"), check_vector(u, "u")
        return self._input_matrix(jnp.asarray(t, q.dtype), q, p, u.shape[0])

    @public_method("(),(n),(m)->(k)")
    def input_values(self, t, q, u, p=None):
        """r(t, q, u): the inputs in force at a state."""
        q, u = check_vector(q, "q"), check_vector(u, "u")
        return self._inputs_at(jnp.asarray(t, q.dtype), q, u, p)

    # -- AbstractDynamics -----------------------------------------------------------------------

    @property
    def saved_records(self):
        return ("inputs", *self.dynamics.saved_records)

    def record(self, name, ts, q, u, p=None):
        if name == "inputs":
            return jax.vmap(self._inputs_at, in_axes=(0, 0, 0, None))(ts, q, u, p)
        return self.dynamics.record(name, ts, q, u, p)

    def coordinate_rates(self, t, q, u, p=None):
        return self.dynamics.coordinate_rates(t, q, u, p)

    def form_equations(self, t, q, u, p=None):
        """(M, f + B r)."""
        mass_matrix, forcing = self.dynamics.form_equations(t, q, u, p)
        return mass_matrix, forcing + self.applied(jnp.asarray(t, q.dtype), q, u, p)

    def form_residual(self, t, q, u, ud, p=None):
        """The wrapped formulation's M u̇ − f, less B r."""
        return (self.dynamics.form_residual(t, q, u, ud, p)
                - self.applied(jnp.asarray(t, q.dtype), q, u, p))

    def form_residual_held(self, t, q, u, ud, p, held, forces):
        """The wrapped formulation's, less B r."""
        inner = self.dynamics.form_residual_held(t, q, u, ud, p, held, forces)
        if inner is None:
            return None
        residual, *motion = inner
        return residual - self.applied(jnp.asarray(t, q.dtype), q, u, p), *motion

    def form_accelerations(self, t, q, u, p=None, *, small):
        if isinstance(self.dynamics, ArticulatedBody):  # B r joins the joint forces
            t = jnp.asarray(t, q.dtype)
            return articulated_body_algorithm(self.dynamics.tree.merge_fixed(), t, q, u, p,
                                              applied=self.applied(t, q, u, p))
        return accelerations_from_equations(self, t, q, u, p, small=small)

    def energy_terms(self, t, q, u, p=None):
        return self.dynamics.energy_terms(t, q, u, p)

    def user_functions(self, t, q, u, p=None):
        q, u = check_vector(q, "q"), check_vector(u, "u")
        return self.dynamics.user_functions(t, q, u, p), self.applied(
            jnp.asarray(t, q.dtype), q, u, p)

    def state_projection(self):
        return self.dynamics.state_projection()

    def singular_constraints(self, t, q, u, p=None):
        return self.dynamics.singular_constraints(t, q, u, p)

    def state_constraints(self, t, q, u, p=None):
        return self.dynamics.state_constraints(t, q, u, p)


def _indices(input_map) -> tuple[int, ...]:
    try:
        values = np.atleast_1d(np.asarray(input_map))
    except ValueError:  # (ragged)
        values = np.zeros((0,))
    indices = (tuple(int(i) for i in values)
               if values.ndim == 1 and np.issubdtype(values.dtype, np.integer) else ())
    if not indices or len(set(indices)) != len(indices) or min(indices) < 0:
        raise ValueError("input_map must be B(q, p) → (m, k), a constant B as an array "
                         "(m, k), or distinct non-negative indices of actuated speeds, got "
                         f"{input_map!r}.")
    return indices


class _Actuated(eqx.Module):
    """Actuated speeds: B = the identity's columns at `indices`."""

    indices: tuple[int, ...] = eqx.field(static=True)

    def matrix(self, controlled, t, q, p, num_speeds):
        if max(self.indices) >= num_speeds:
            raise ValueError(f"input_map names speed {max(self.indices)}, but the system "
                             f"has {num_speeds} speeds.")
        # A NumPy constant: no indexing operation staged (or run eagerly) per call.
        return jnp.asarray(np.eye(num_speeds, dtype=q.dtype)[:, list(self.indices)])


class _Constant(eqx.Module):
    """A constant input map, B given as an array (m, k)."""

    value: Any

    def matrix(self, controlled, t, q, p, num_speeds):
        if self.value.shape[0] != num_speeds:
            raise ValueError(f"input_map B has {self.value.shape[0]} rows, but the system has "
                             f"{num_speeds} speeds: B must be (m, k) with m = {num_speeds}.")
        return jnp.asarray(self.value, q.dtype)


class _Stacked(eqx.Module):
    """The columns of several input maps side by side (a tuple given as `input_map`)."""

    maps: tuple

    def matrix(self, controlled, t, q, p, num_speeds):
        return jnp.concatenate([
            x.matrix(controlled, t, q, p, num_speeds) if isinstance(x, _MAPS)
            else Controlled(controlled.dynamics, x, time_dependent=controlled.time_dependent)
            ._input_matrix(t, q, p, num_speeds) for x in self.maps], axis=1)


_MAPS = (ForceInput, TorqueInput, _Actuated, _Constant, _Stacked)


def _is_map(x) -> TypeGuard[Callable | ForceInput | TorqueInput | _Actuated | _Constant
                             | _Stacked]:
    return callable(x) or isinstance(x, _MAPS)


def _takes_time_only(fn) -> bool:
    """Whether `fn` is a signal r(t) (one positional argument) rather than π(t, q, u, p)."""
    try:
        parameters = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    positional = [x for x in parameters
                  if x.kind in (x.POSITIONAL_ONLY, x.POSITIONAL_OR_KEYWORD)]
    variadic = any(x.kind == x.VAR_POSITIONAL for x in parameters)
    return len(positional) == 1 and not variadic


def find_controlled(dynamics) -> Controlled | None:
    """The `Controlled` inside `dynamics` (itself, or the one a constraint wraps), or None."""
    found = [x for x in jax.tree_util.tree_leaves(
        dynamics, is_leaf=lambda x: isinstance(x, Controlled)) if isinstance(x, Controlled)]
    return found[0] if found else None
