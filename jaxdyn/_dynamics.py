"""The interface every formulation implements, and the only thing `simulate` knows about."""

import abc
import dataclasses
import functools
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Coordinates, MassMatrix, Params, RealScalarLike, Speeds
from ._errors import error_if
from ._static_indexing import check_static_indexing
from ._linalg import (
    NONFINITE_FORCING,
    SINGULAR_CONSTRAINTS,
    SINGULAR_MASS_MATRIX,
    condition_number,
    solve,
    solve_mass_matrix,
)
from ._state import public_method, under_a_trace
from ._unroll import (Symbol, give_up_beyond, give_up_beyond_program, is_constant, structure,
                      unrolled)
from ._unroll import straight_line_size as straight_line_program_size


class _NoInputs(ValueError):
    """A formulation that declares no inputs was given some."""


class AbstractDynamics(eqx.Module):
    """Equations of motion in the form

        q̇ = K(t, q, p) u,        M(t, q, p) u̇ = f(t, q, u, p)

    with coordinates q (n,) and speeds u (m,). For Lagrange's equations u = q̇ and K = I; the
    Gibbs–Appell and Kane formulations may choose other speeds (and fewer of them than
    coordinates, for nonholonomic systems).

    Subclasses implement `coordinate_rates`, `form_equations` (their own way of forming M and
    f), `form_accelerations` (usually `accelerations_from_equations`: an LDLᵀ solve of M u̇ =
    f; the articulated-body algorithm has its own), `energy_terms` and `user_functions`.
    Everything else follows here: small systems evaluated as straight-line scalar code
    (`jaxdyn._unroll`), and the public methods, which take ``(t, q, u, p=None)``, accept
    stacked states (leading axes broadcast), compile once per system and shape, and can be
    passed to `jax.jit` as bound methods.
    """

    #: The quantities beyond q, u and q̇ that `simulate(..., save=...)` can record along a
    #: trajectory of this formulation, by name (`Constrained`: "constraints"); see `record`.
    #: A class attribute: read without binding a method, which for a module costs ~50 µs.
    saved_records: ClassVar[tuple[str, ...]] = ()

    @property
    def batch_in_chunks(self) -> bool:
        """Whether `jax.vmap` runs this system's array programs in chunks of a few states
        (`jaxdyn._chunking`): true for the recursions over trees of 6 × 6 spatial algebra
        (many small kernels, memory-bound when a thousand states stream through each), false
        for equations formed as whole matrices (LAPACK's batched factorisations prefer the
        whole batch). A system wrapping another (`Controlled`, `Constrained`) follows it."""
        inner = getattr(self, "dynamics", None)
        return isinstance(inner, AbstractDynamics) and inner.batch_in_chunks

    @property
    def mass_matrix_in_straight_line(self) -> bool:
        """Whether `mass_matrix` tries straight-line scalar code (`jaxdyn._unroll`) before the
        array program: true but for the composite-rigid-body algorithm on trees, whose array
        program runs faster in a batch and compiles sooner. A system wrapping another follows
        it."""
        inner = getattr(self, "dynamics", None)
        return not isinstance(inner, AbstractDynamics) or inner.mass_matrix_in_straight_line

    @property
    def equations_in_straight_line(self) -> bool:
        """Whether the equations of motion (`accelerations`, `simulate`) try straight-line
        scalar code (`jaxdyn._unroll`) before the array program: true but where they cannot fit
        its budget, so that the attempt, a whole trace of the equations, is not spent (trees of
        more than `ArticulatedBody.STRAIGHT_LINE_SPEEDS` speeds). A system wrapping another
        follows it."""
        inner = getattr(self, "dynamics", None)
        return not isinstance(inner, AbstractDynamics) or inner.equations_in_straight_line

    @abc.abstractmethod
    def coordinate_rates(
        self, t: RealScalarLike, q: Coordinates, u: Speeds, p: Params = None
    ) -> Coordinates:
        """q̇ = K(t, q, p) u."""

    @abc.abstractmethod
    def form_equations(
        self, t: RealScalarLike, q: Coordinates, u: Speeds, p: Params = None
    ) -> tuple[MassMatrix, Speeds]:
        """(M, f) of M u̇ = f for one state, as this formulation forms them."""

    @abc.abstractmethod
    def form_accelerations(self, t, q, u, p=None, *, small: bool
                           ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(u̇, singular, nonfinite) for one state, u̇ NaN where the equations fail; `small`:
        the program will run as straight-line scalar code (see `equations_of_motion`)."""

    @abc.abstractmethod
    def energy_terms(self, t, q, u, p=None) -> tuple[jax.Array, jax.Array]:
        """(T, V), the kinetic and potential energy, for the diagnostics."""

    @abc.abstractmethod
    def user_functions(self, t, q, u, p=None):
        """Every user callback evaluated once, without derivatives (for trace-time checks)."""

    def form_rates_and_accelerations(self, t, q, u, p=None, *, small: bool):
        """(q̇, u̇, singular, nonfinite): `coordinate_rates` and `form_accelerations` at one
        state; a formulation whose two share work (`jaxdyn.Contact`: the contact forces)
        forms them together."""
        return (self.coordinate_rates(t, q, u, p),
                *self.form_accelerations(t, q, u, p, small=small))

    def form_residual(self, t, q, u, ud, p=None):
        """M u̇ − f for one state, from this formulation's (M, f); a formulation with a cheaper
        route (the articulated-body formulation: the recursive Newton–Euler algorithm)
        overrides it."""
        mass_matrix, forcing = self.form_equations(t, q, u, p)
        return mass_matrix @ ud - forcing

    def form_residual_held(self, t, q, u, ud, p, held, forces
                           ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array] | None:
        """(M u̇ − f − Cᵀ λ, r_P, v_P, a_P): the residual of Lagrange's equations of the first
        kind with the points of `held` (a `jaxdyn.HeldPoints`) pushed by `forces` λ (k, 3)
        in world axes, and the points' positions, velocities and classical accelerations
        (k, 3) each in world axes, from one pass over the formulation's recursions; None
        where the formulation has no such pass (the articulated-body formulation has it:
        `jaxdyn._form.newton_euler.newton_euler_held`)."""
        return None

    def state_projection(self) -> Callable | None:
        """None, or a function (t, q, u, p) → (q, u) that `simulate` applies after every step
        (drift control of constrained systems, `jaxdyn.Projection`)."""
        return None

    def state_constraints(self, t, q, u, p=None):
        """(φ(t, q), g(t, q, u)): the constraints on the states the system can take, position
        constraints and velocity constraints (including φ̇), each zero on admissible states;
        shapes (0,) when the coordinates and speeds are independent. Linearisation works in
        the tangent space of these constraints."""
        empty = jnp.zeros((0,), q.dtype)
        return empty, empty

    def singular_constraints(self, t, q, u, p=None):
        """Whether, where the equations fail as singular, the constraints are the cause rather
        than the mass matrix (only constrained formulations have constraints)."""
        return jnp.zeros((), bool)

    def initial_coordinates(self, q0, u0, p=None):
        """The coordinates a solve starts from, given `q0` as the caller wrote it: `q0` itself,
        but for a system whose state holds more than its bodies' coordinates (a
        `jaxdyn.Contact` scene appends the ground's deformations, zero at the start)."""
        inner = getattr(self, "dynamics", None)
        if isinstance(inner, AbstractDynamics):
            return inner.initial_coordinates(q0, u0, p)
        return q0

    @property
    def bounds_steps(self) -> bool:
        """Whether an adaptive solve must limit its steps by `step_bound` (a `jaxdyn.Contact`
        scene); a system wrapping another follows it."""
        inner = getattr(self, "dynamics", None)
        return isinstance(inner, AbstractDynamics) and inner.bounds_steps

    def step_bound(self, t, q, u, p=None):
        """The longest step an adaptive solve may take next from (t, q, u): unbounded, but for
        a system whose vector field switches on within a step too fast for the error
        estimate to see (a contact stepped over: `jaxdyn.Contact`)."""
        inner = getattr(self, "dynamics", None)
        if isinstance(inner, AbstractDynamics):
            return inner.step_bound(t, q, u, p)
        return jnp.asarray(jnp.inf, q.dtype)

    def record(self, name: str, ts, q, u, p=None):
        """The quantity `name` (one of `saved_records`) at stacked states (ts, q, u), for
        the field of `jaxdyn.Solution` of that name."""
        raise ValueError(f"{type(self).__name__} records nothing named {name!r}.")

    def with_inputs(self, inputs) -> "AbstractDynamics":
        """This system driven by `inputs` (an array r, a signal r(t) or a diffrax path, or a
        policy π(t, q, u, p)): the formulation that declares inputs (`jaxdyn.Controlled`)
        takes them, wherever it sits in this one (a `Constrained` or `Contact` system wraps
        it); an error if none declares inputs. `simulate(..., inputs=...)` calls this."""
        driven, found = self, False
        for name, inner in self._formulations_inside():
            try:
                replaced = inner.with_inputs(inputs)
            except _NoInputs:
                continue
            driven = eqx.tree_at(lambda s, name=name: getattr(s, name), driven, replaced)
            found = True
        if not found:
            raise _NoInputs(f"{type(self).__name__} declares no inputs: wrap the formulation "
                            "as jaxdyn.Controlled(dynamics, input_map) to drive it.")
        return driven

    def applied_inputs(self):
        """The inputs driving this system (as `with_inputs` gave them), or None where it
        declares none: what a derivative through `simulate` can reach beyond q0, u0 and p."""
        for _, inner in self._formulations_inside():
            inputs = inner.applied_inputs()
            if inputs is not None:
                return inputs
        return None

    def _formulations_inside(self) -> list[tuple[str, "AbstractDynamics"]]:
        """(field name, formulation) of the formulations this one wraps."""
        return [(f.name, x) for f in dataclasses.fields(self)
                if isinstance(x := getattr(self, f.name), AbstractDynamics)]

    def __hash__(self):
        # By structure (callbacks, static fields, array shapes), so that a bound method such
        # as `jax.jit(system.accelerations)` can be hashed although the system holds arrays;
        # equal systems have equal hashes, and `==` (Equinox's, by value) settles collisions.
        leaves, treedef = jax.tree_util.tree_flatten(self)
        return hash((treedef, tuple(
            (x.shape, str(x.dtype)) if eqx.is_array(x) else x for x in leaves)))

    @public_method("(),(n),(m)->(m,m),(m)")
    def mass_matrix_and_forcing(self, t, q, u, p=None):
        """(M, f) of M u̇ = f, formed together (they share their derivative passes)."""
        check_static_indexing(self.user_functions, t, q, u, p)
        return unrolled(self.form_equations, t, q, u, p, chunked=self.batch_in_chunks)

    @public_method("(),(n),(m)->(m,m)")
    def mass_matrix(self, t, q, u, p=None):
        """The mass matrix M of M u̇ = f (symmetric positive definite)."""
        check_static_indexing(self.user_functions, t, q, u, p)
        return unrolled(lambda *args: self.form_equations(*args)[0], t, q, u, p,
                        chunked=self.batch_in_chunks,
                        max_elements=None if self.mass_matrix_in_straight_line else 0)

    @public_method("(),(n),(m)->()")
    def mass_matrix_condition(self, t, q, u, p=None):
        """κ(M) = λ_max / λ_min, the 2-norm condition number of the mass matrix (symmetric):
        near 1/ε it is numerically singular, and a growing κ along a trajectory announces a
        coordinate singularity (Euler angles near gimbal lock, polar angles near the pole).
        Infinite where M has a zero or negative eigenvalue."""
        return condition_number(self.mass_matrix(t, q, u, p))

    @public_method("(),(n),(m)->(m)")
    def forcing(self, t, q, u, p=None):
        """The forcing f of M u̇ = f: every term of the equations except M u̇."""
        check_static_indexing(self.user_functions, t, q, u, p)
        return unrolled(lambda *args: self.form_equations(*args)[1], t, q, u, p,
                        chunked=self.batch_in_chunks)

    @public_method("(),(n),(m)->(m)", checked=True)
    def accelerations(self, t, q, u, p=None, *, throw: bool | None = None):
        """u̇ = M⁻¹ f (an LDLᵀ factorisation of M).

        Where M is singular or f not finite, the default raises an error that names the cause
        and the state (t, q, u) when called with values, and returns NaN there inside your own
        `jax.jit`, `vmap` or `grad`, where it costs nothing (`diagnose` then names the cause
        of a NaN). `throw=True` raises inside your trace too (a branch that calls the host,
        which in a scalar loop of your own costs a few evaluations of a small system's
        equations); `throw=False` returns NaN everywhere, with no branch (what `simulate`
        integrates).
        """
        check_static_indexing(self.user_functions, t, q, u, p)
        _, accelerations, singular, nonfinite = equations_of_motion(self, t, q, u, p)
        if not throw:
            return accelerations

        # The flags come with the accelerations (a few reductions); the cause that costs
        # something (which constraints are singular) is sought only where u̇ is NaN. Forming
        # the equations again in the failing branch would compile them twice.
        def causes():
            constraints = singular & self.singular_constraints(t, q, u, p)
            return [(nonfinite, NONFINITE_FORCING), (constraints, SINGULAR_CONSTRAINTS),
                    (singular, SINGULAR_MASS_MATRIX)]

        return error_if(accelerations, causes, (t, q, u),
                        failed=~jnp.all(jnp.isfinite(accelerations)))

    def diagnose(self, t, q, u, p=None) -> str | None:
        """Why M u̇ = f has no finite solution u̇ at a state, or None where it has one.

        The message `accelerations` raises by default when called with values: the cause (a
        non-finite forcing, singular constraints, a singular or indefinite mass matrix) with
        its likely reasons, ending with the state, "It happened at t = …, q = […], u = […]."
        (the first failing one of stacked states). For a NaN that came out of your own
        `jax.jit`, `vmap` or `grad`, where failures are carried as values: pass the state
        that gave it. Reads values, so it is called outside a trace.
        """
        if under_a_trace():
            raise ValueError("diagnose reads the values of the state: call it outside "
                             "jax.jit, vmap and grad, with the state that gave a NaN.")
        try:
            self.accelerations(t, q, u, p, throw=True)
        except RuntimeError as failure:
            return str(failure)
        return None

    @public_method("(),(n),(m),(m)->(m)")
    def residual(self, t, q, u, ud, p=None):
        """Inverse dynamics: r = M(t, q) u̇ − f(t, q, u), the generalized forces along the
        speeds that the motion (q, u, u̇) needs beyond those the system already applies (zero
        along its own motion; for a robot, the joint torques of a planned trajectory). For a
        `Constrained` system f holds no constraint forces: r is what the constraints and any
        actuators must supply together. Leading axes broadcast (a whole trajectory at once)."""
        check_static_indexing(self.user_functions, t, q, u, p)
        return unrolled(self.form_residual, t, q, u, ud, p, chunked=self.batch_in_chunks)

    @public_method("(),(n),(m)->()")
    def kinetic_energy(self, t, q, u, p=None):
        """T."""
        return self.energy_terms(t, q, u, p)[0]

    @public_method("(),(n),(m)->()")
    def potential_energy(self, t, q, u, p=None):
        """V (u is accepted for a uniform signature and ignored)."""
        return self.energy_terms(t, q, u, p)[1]

    @public_method("(),(n),(m)->()")
    def energy(self, t, q, u, p=None):
        """Mechanical energy E = T + V: conserved by a conservative, scleronomic system."""
        kinetic, potential = self.energy_terms(t, q, u, p)
        return kinetic + potential

    @public_method("(),(n),(m)->(m)")
    def momentum(self, t, q, u, p=None):
        """The generalized momenta ∂T/∂u conjugate to the speeds (∂L/∂q̇ for Lagrange's
        equations): conserved along a cyclic coordinate."""
        return jax.grad(lambda u: self.energy_terms(t, q, u, p)[0])(u)


@eqx.filter_jit  # traced once per system and shapes; inlined into every caller's program
def equations_of_motion(dynamics: AbstractDynamics, t, q, u, p, factorisation=None):
    """(q̇, u̇, singular, nonfinite) for one state, with no checks and no branches.

    u̇ is NaN where M is singular or f not finite (the flags say which), so that a solver
    rejects the step instead of stopping: `simulate` diagnoses the failure after the solve.
    Small systems are evaluated as straight-line scalar code with the LDLᵀ factorisation
    written out (structural zeros of M fold away, so independent subsystems are solved apart
    for free); larger ones as array programs, M factored block by block when it is
    block-diagonal. With `factorisation` (of a mass matrix that does not depend on the state,
    see `constant_mass_matrix`) only f is formed.
    """
    if factorisation is not None:  # given for systems evaluated as arrays only
        return _equations(dynamics, t, q, u, p, factorisation=factorisation, small=False)
    return unrolled(functools.partial(_straight_line_equations, dynamics), t, q, u, p,
                    otherwise=functools.partial(_array_equations, dynamics),
                    chunked=dynamics.batch_in_chunks,
                    max_elements=None if dynamics.equations_in_straight_line else 0)


def straight_line_size(dynamics, t, q, u, p) -> int | None:
    """The scalar operations of `equations_of_motion` as straight-line code, or None when it
    evaluates this system as array operations (too large for straight-line code, or never
    tried: `equations_in_straight_line`, whose count would cost a whole trace of the
    equations, 1.1 s for ANYmal in contact)."""
    if not dynamics.equations_in_straight_line:
        return None
    return straight_line_program_size(functools.partial(_straight_line_equations, dynamics),
                                      t, q, u, p)


@eqx.filter_jit  # its trace is cached: `fits` and `unrolled` then trace the user's functions once
def _straight_line_equations(dynamics, t, q, u, p):
    return _equations(dynamics, t, q, u, p, factorisation=None, small=True)


@eqx.filter_jit  # its trace is cached: every stage of a step, the step-size controller's first
# step and the failure checks ask for the equations (ANYmal in contact traced them 5 times)
def _array_equations(dynamics, t, q, u, p):
    return _equations(dynamics, t, q, u, p, factorisation=None, small=False)


def _equations(dynamics, t, q, u, p, *, factorisation, small):
    if factorisation is None:
        return dynamics.form_rates_and_accelerations(t, q, u, p, small=small)
    rates = dynamics.coordinate_rates(t, q, u, p)
    forcing = dynamics.form_equations(t, q, u, p)[1]
    nonfinite = ~jnp.all(jnp.isfinite(forcing))
    accelerations = jnp.where(nonfinite, jnp.nan, solve(factorisation, forcing))
    return rates, accelerations, factorisation.singular, nonfinite


def accelerations_from_equations(dynamics, t, q, u, p, *, small):
    """(u̇, singular, nonfinite) by an LDLᵀ solve of the formulation's M u̇ = f: written out in
    straight-line code when `small`, else block by block (`mass_matrix_blocks`)."""
    if small:  # the LDLᵀ factorisation written out emits about m³/6 multiply–adds
        give_up_beyond(u.shape[-1] ** 3 // 6)
    mass_matrix, forcing = formed_equations(dynamics, t, q, u, p)
    if small:
        give_up_beyond_program(formed_equations, dynamics, t, q, u, p)
    blocks = None if small else mass_matrix_blocks(dynamics, t, q, u, p)
    return solve_mass_matrix(mass_matrix, forcing, unrolled=small, blocks=blocks)


@eqx.filter_jit  # its trace is cached: the failure diagnosis reuses the solve's trace
def formed_equations(dynamics, t, q, u, p):
    """(M, f) of M u̇ = f, as `AbstractDynamics.form_equations` forms them, traced once per
    system and shapes."""
    return dynamics.form_equations(t, q, u, p)


@eqx.filter_jit  # traced once per system and shapes; inlined into every caller's program
def formed_mass_matrix(dynamics, t, q, u, p):
    """M of M u̇ = f alone, for the programs that need it beside the equations of motion (the
    forces that hold events' rows, the condition number of a failure's message): written out
    in straight-line scalar code where the system's M is (`unrolled`), else as
    `form_equations` forms it on arrays. The array program of a small system is the larger
    one (Appell's M as the Hessian of the Gibbs function: 1192 operations for a chain of two
    rods, where the written-out form folds the constants and emits each product once), and a
    hybrid solve holds it at every place its vector field is asked for."""
    # (M from `formed_equations`, whose trace the equations of motion have cached: the
    # user's functions are not traced again; the straight-line code keeps M's part alone)
    return unrolled(lambda *args: formed_equations(dynamics, *args)[0], t, q, u, p,
                    max_elements=None if dynamics.mass_matrix_in_straight_line else 0)


# What `structure` found of M, by system and argument shapes: the analysis sees the arguments
# as symbols (their values never matter), and a first `simulate` asks twice (is M constant,
# what are its blocks), at up to a second each for a chain of 20 links by Kane's equations.
_STRUCTURES: dict = {}


def _mass_matrix_structure(dynamics, t, q, u, p):
    leaves, treedef = jax.tree_util.tree_flatten((t, q, u, p))
    key = (dynamics, treedef, tuple((jnp.shape(x), jnp.result_type(x), _weak(x))
                                     for x in leaves))
    try:
        found = _STRUCTURES.get(key)
    except TypeError:  # a system that holds traced or unhashable values: analysed each time
        key, found = None, None
    if found is None:
        found = (structure(lambda *args: dynamics.form_equations(*args)[0], t, q, u, p,
                           tags=("t", "q", "u", "p")),)
        if key is not None:
            if len(_STRUCTURES) >= 64:
                _STRUCTURES.clear()
            _STRUCTURES[key] = found
    return found[0]


def _weak(x) -> bool:
    return bool(getattr(getattr(x, "aval", None), "weak_type", False)) or isinstance(
        x, (int, float))


def mass_matrix_blocks(dynamics, t, q, u, p):
    """The diagonal blocks of M after a permutation (its structural zeros found at trace
    time), or None when M is one block or too large to analyse."""
    elements = _mass_matrix_structure(dynamics, t, q, u, p)
    if elements is None:
        return None
    coupled = np.array([[not (is_constant(e) and e == 0) for e in row] for row in elements])
    blocks = _connected_components(coupled | coupled.T)
    return None if len(blocks) == 1 else blocks


def constant_mass_matrix(dynamics, t, q, u, p) -> bool:
    """True if M provably depends on the parameters alone (Cartesian coordinates, linear
    systems): it can then be factored once per solve instead of at every step. Not analysed
    where M is formed as an array program (`mass_matrix_in_straight_line` false: trees'
    composite-rigid-body algorithm, whose M turns with the links): the analysis would cost a
    whole trace of the equations (2 s for ANYmal in contact) to find what the joints say."""
    if not dynamics.mass_matrix_in_straight_line:
        return False
    elements = _mass_matrix_structure(dynamics, t, q, u, p)
    if elements is None:
        return False
    return not any(isinstance(e, Symbol) and e.depends & {"t", "q", "u"}
                   for e in elements.ravel())


def _connected_components(adjacency):
    """Groups of indices connected through the nonzero pattern (each sorted)."""
    m = adjacency.shape[0]
    group = list(range(m))

    def find(i):
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    for i, j in zip(*np.nonzero(adjacency)):
        group[find(i)] = find(j)
    components = {}
    for i in range(m):
        components.setdefault(find(i), []).append(i)
    return sorted(tuple(c) for c in components.values())
