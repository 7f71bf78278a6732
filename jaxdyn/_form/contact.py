r"""Compliant contact: a system touching a terrain at contact points, with a Hunt–Crossley
normal force and Coulomb friction through a tangential deformation carried in the state.

For each contact (`jaxdyn._system.contact`: gap g, normal n, velocity v_C of the touching
material point), the penetration δ = max(−g, 0) and its rate δ̇ = −n·v_C give the normal force
of Hunt and Crossley's law with Hertz's exponent (a sphere on a half-space),

    f_n = max(0, k δ^{3/2} (1 + α δ̇)),

whose damping vanishes with the penetration as the stiffness does: the force, and with it the
vector field, is Lipschitz through a touchdown, so that sensitivities (and gradients) through
it are those of the solution. (A damping c √δ δ̇, as in Azad and Featherstone's normal law,
has an unbounded derivative ∂f/∂δ = c δ̇ / (2√δ) at touchdown: derivatives through a solve then
depend on where the steps fall, and missed finite differences by a factor 2 on a trotting
quadruped.)

and the ground's tangential deformation ξ (a 3-vector in the tangent plane, part of the state)
the friction force

    h = −(k_t ξ_t + c_t v_t),     F_t = s √δ h,     s = min(1, μ f_n / (√δ |h|)),
    ξ̇ = −(s h + k_t ξ_t) / c_t,

with v_t, ξ_t the tangential parts of v_C and ξ. While the contact sticks (s = 1), ξ̇ = v_t: the
ground deforms with the point and a tangential spring–damper holds it, so static friction holds
a body at rest on a slope below tan γ = μ (no creep). When the stick force would leave the
friction cone, F_t lies on it (|F_t| = μ f_n) and ξ relaxes so that the spring–damper carries
exactly F_t. Off contact (f_n = 0) ξ relaxes to 0. The force acts on the body at the contact
point; it enters the equations as generalized active forces Q = Σ (∂v_C/∂u)ᵀ F (Kane and
Levinson, 1985, ch. 4), with J_C the contact point's Jacobian, v_C = J_C u.

References: K. H. Hunt and F. R. E. Crossley, Coefficient of restitution interpreted as damping
in vibroimpact, J. Appl. Mech. 42 (1975); M. Azad and R. Featherstone, Modeling the contact
between a rolling sphere and a compliant ground plane, ACRA 2010 and 2014 (the tangential
deformation as a state); the model jaxsim builds on (Ferigo et al., 2024).
"""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._dynamics import AbstractDynamics, accelerations_from_equations
from .._state import check_vector
from .._system.contact import (
    AbstractTerrain,
    ContactPair,
    ContactPoint,
    Plane,
    _members,
    check_points,
    contact_kinematics,
    find_tree,
)
from .._system.links import _value
from .._system.tree import RigidBodyTree
from .articulated import ArticulatedBody, articulated_body_algorithm
from .controlled import Controlled


# How far past the terrain's surface one step may carry a contact point (m): about the
# penetration at which compliant ground holds a body, so that the step's stages meet the force.
APPROACH_DEPTH = 1e-3

# The ground's tangential relaxation time c_t / k_t (s) when no damping is given.
DEFAULT_RELAXATION = 2e-3


class HuntCrossley(eqx.Module):
    r"""The compliant contact law of the module docstring: a Hunt–Crossley normal force
    f_n = max(0, k δ^{3/2} (1 + α δ̇)) and Coulomb friction μ through a tangential
    spring–damper (k_t, c_t) on the ground's deformation.

    **Arguments** (each a number or a function of the parameters p, so that `jaxdyn.fit` can
    identify it):

    - `stiffness`: k (N/m^{3/2}); a body of weight W resting on N contacts sinks by
      δ = (W / (N k))^{2/3}: e.g. k = 10⁶ with W/N = 100 N sinks 2.2 mm.
    - `dissipation`: α (s/m), Hunt and Crossley's damping factor; an impact at speed v₀ has
      a coefficient of restitution e with α ≈ 3 (1 − e²) / (4 v₀)
      (`HuntCrossley.restitution_dissipation`).
    - `friction`: μ, Coulomb's coefficient (static and kinetic).
    - `tangential_stiffness`: k_t (N/m^{3/2}); default k.
    - `tangential_damping`: c_t (N s/m^{3/2}) > 0; default k_t × 2 ms, so that off contact the
      deformation relaxes in 2 ms. The tangential response of a contact carrying a mass m is
      then lightly damped (damping ratio ≈ δ^{1/4} c_t / (2 √(k_t m)): 0.06 for a quadruped's
      foot), so that a light body landing while sliding springs back a little, as a rubber
      ball does; a larger c_t damps that, at the cost of shorter steps (ANYmal's drop: 506
      steps with k_t × 2 ms, 1370 with k_t × 10 ms).
    - `smoothing`: ε (m) ≥ 0. With ε > 0 the penetration is ε·softplus(−g/ε), the normal force
      a softplus of the law at the force scale k ε^{3/2}, and the friction cone's saturation
      s = μ f_n / √((μ f_n)² + δ|h|² + (μ k ε^{3/2})²): forces smooth in the state, for useful
      rather than exact gradients of contact-rich trajectories (Suh et al., Do differentiable
      simulators give better policy gradients?, ICML 2022). The default 0 is the exact model.
    """

    stiffness: float | Callable
    dissipation: float | Callable
    friction: float | Callable
    tangential_stiffness: float | Callable | None = None
    tangential_damping: float | Callable | None = None
    smoothing: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        for name in ("stiffness", "dissipation", "friction", "tangential_stiffness",
                     "tangential_damping"):
            value = getattr(self, name)
            if value is not None and not callable(value):
                if not jnp.all(jnp.isfinite(jnp.asarray(value))) or jnp.any(
                        jnp.asarray(value) < 0):
                    raise ValueError(f"HuntCrossley's {name} must be finite and ≥ 0, got "
                                     f"{value}.")
        if self.smoothing < 0:
            raise ValueError(f"smoothing must be ≥ 0, got {self.smoothing}.")

    def relaxation_time(self) -> float | None:
        """τ = c_t / k_t (s): off contact the ground's deformation relaxes as ξ̇ = −ξ / τ, the
        fastest rate of the tangential model, which a fixed explicit step must resolve. None
        where c_t or k_t is a function of the parameters (or traced)."""
        if self.tangential_damping is None:
            return DEFAULT_RELAXATION
        k_t = self.stiffness if self.tangential_stiffness is None else self.tangential_stiffness
        if any(callable(x) or isinstance(x, jax.core.Tracer)
               for x in (self.tangential_damping, k_t)):
            return None
        return float(np.asarray(self.tangential_damping) / np.asarray(k_t))

    @staticmethod
    def restitution_dissipation(restitution, speed):
        """α for a coefficient of restitution e at impact speed v₀, by Lankarani and
        Nikravesh's estimate (J. Mech. Des. 112, 1990) for Hunt–Crossley's law:
        α = 3 (1 − e²) / (4 v₀)."""
        return 3.0 * (1.0 - restitution**2) / (4.0 * speed)

    def forces(self, kinematics, deformation, p):
        """(F (k, 3), ξ̇ (k, 3), f_n (k,), F_t (k, 3)) at every contact: the force on the body
        at the contact point (world axes), the deformation's rate, the normal and the friction
        force."""
        dtype = deformation.dtype
        k, alpha, mu = (_value(x, p).astype(dtype) for x in (self.stiffness, self.dissipation,
                                                              self.friction))
        k_t = k if self.tangential_stiffness is None else _value(
            self.tangential_stiffness, p).astype(dtype)
        c_t = DEFAULT_RELAXATION * k_t if self.tangential_damping is None else _value(
            self.tangential_damping, p).astype(dtype)
        n, v = kinematics.normal, kinematics.velocity
        v_n = jnp.sum(n * v, axis=-1)
        v_t = v - v_n[:, None] * n
        xi_t = deformation - jnp.sum(n * deformation, axis=-1)[:, None] * n
        eps = self.smoothing
        if eps > 0:
            depth = eps * jax.nn.softplus(-kinematics.gap / eps)
        else:
            depth = jnp.maximum(-kinematics.gap, 0.0)
        root = jnp.sqrt(jnp.where(depth > 0, depth, 1.0))  # (a safe √ at δ = 0)
        root = jnp.where(depth > 0, root, 0.0)
        raw = k * depth * root * (1.0 - alpha * v_n)
        if eps > 0:
            scale = k * eps**1.5
            normal = scale * jax.nn.softplus(raw / scale)
        else:
            normal = jnp.maximum(raw, 0.0)
        h = -(k_t * xi_t + c_t * v_t)
        square = jnp.sum(h * h, axis=-1)
        # |h| with every derivative finite at h = 0 (a contact at rest with no load along the
        # ground): the second derivative of √(|h|² + tiny) overflows there
        size = jnp.where(square > 0, jnp.sqrt(jnp.where(square > 0, square, 1.0)), 0.0)
        cone = mu * normal
        # s: the share of the stick force h that the cone lets through. Without normal force
        # (off contact, or separating faster than the damping allows) there is no friction,
        # s = 0, and ξ relaxes: with s = 1 there, ξ̇ = v_t would wind the deformation up in
        # flight and fling the body back at touchdown.
        if eps > 0:  # a smooth cone, closing smoothly below the force scale k ε^{3/2} μ
            both = cone**2 + (root * size) ** 2 + (mu * k * eps**1.5) ** 2
            s = cone / jnp.sqrt(both)
        else:
            over = root * size > cone
            s = jnp.where(cone > 0, jnp.where(over, cone / jnp.where(over, root * size, 1.0),
                                              1.0), 0.0)
        friction = (s * root)[:, None] * h
        rate = -(s[:, None] * h + k_t * xi_t) / c_t
        return normal[:, None] * n + friction, rate, normal, friction


class ContactRecord(eqx.Module):
    """Contact quantities at the save times of a `jaxdyn.Contact` scene
    (`simulate(..., save=(..., "contact"))`), per contact point in the order given.

    **Fields** (k save times, c contacts; world axes):

    - `gap`: signed distances (k, c), negative in penetration (not clamped).
    - `normal_force`: f_n ≥ 0 (k, c).
    - `friction_force`: F_t (k, c, 3).
    - `force`: the whole force on the body, f_n n + F_t (k, c, 3).
    - `position`: the contact points (k, c, 3).
    - `slip_speed`: |v_t| of the touching material point (k, c).
    - `deformation`: the ground's tangential deformation ξ (k, c, 3).
    """

    gap: Float[Array, "k c"]
    normal_force: Float[Array, "k c"]
    friction_force: Float[Array, "k c 3"]
    force: Float[Array, "k c 3"]
    position: Float[Array, "k c 3"]
    slip_speed: Float[Array, "k c"]
    deformation: Float[Array, "k c 3"]


class Contact(AbstractDynamics):
    r"""A formulation in compliant contact with a terrain at contact points:

        q̇ = K u,   ξ̇ = ξ̇(q, ξ, u),   M u̇ = f + Σ_c (∂v_C/∂u)ᵀ F_c(q, ξ, u),

    with F_c the contact law's force (`HuntCrossley`) at contact c and ξ the ground's
    tangential deformations, three per contact, appended to the coordinates: the scene's
    coordinates are (q, ξ), and `simulate` accepts the system's q0 alone (ξ = 0). Save
    "contact" to record forces, gaps and slip (`ContactRecord`).

    **Arguments:**

    - `dynamics`: the formulation in contact (`ArticulatedBody(tree)` for robots, also
      driven: `Controlled(ArticulatedBody(tree), ...)`; any formulation, with contact points
      given as functions c(q, p)).
    - `points`: a sequence of `jaxdyn.ContactPoint` (spheres on links, or functions of q)
      touching the terrain, and of `jaxdyn.ContactPair` (two spheres touching each other);
      `jaxdyn.urdf_contact_points` reads a URDF's collision spheres, capsules and boxes.
    - `terrain`: a `jaxdyn.Plane` (default: the ground z = 0) or `jaxdyn.HeightField`.
    - `model`: the contact law, a `jaxdyn.HuntCrossley`.

    **Example** (ANYmal's feet on flat ground):

        path = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/anymal.urdf")
        tree, p = jaxdyn.from_urdf(path, floating=True)
        feet = jaxdyn.urdf_contact_points(path, links=[f"{leg}_FOOT" for leg in
                                                       ("LF", "RF", "LH", "RH")])
        scene = jaxdyn.Contact(jaxdyn.ArticulatedBody(tree), feet,
                               model=jaxdyn.HuntCrossley(1e6, 2e3, friction=0.8))
        sol = jaxdyn.simulate(scene, q0, u0, p, t1=1.0, save=("q", "u", "contact"))
    """

    dynamics: AbstractDynamics
    points: tuple[ContactPoint | ContactPair, ...]
    model: HuntCrossley
    terrain: AbstractTerrain = Plane()

    def __init__(self, dynamics, points: Sequence[ContactPoint | ContactPair], terrain=None,
                 model=None):
        if not isinstance(dynamics, AbstractDynamics):
            raise ValueError("Contact needs a jaxdyn formulation (AbstractDynamics), got "
                             f"{type(dynamics).__name__}.")
        if model is None or not isinstance(model, HuntCrossley):
            raise ValueError("Contact needs a contact law: model=jaxdyn.HuntCrossley(stiffness, "
                             f"dissipation, friction), got {model!r}.")
        terrain = Plane() if terrain is None else terrain
        if not isinstance(terrain, AbstractTerrain):
            raise ValueError("terrain must be a jaxdyn.Plane or jaxdyn.HeightField (an "
                             f"AbstractTerrain), got {type(terrain).__name__}.")
        self.dynamics = dynamics
        self.points = check_points(points, find_tree(dynamics))
        self.terrain = terrain
        self.model = model

    # -- the scene's state --------------------------------------------------------------------

    @property
    def num_contact_states(self) -> int:
        """3 per contact point: the deformations ξ appended to the coordinates."""
        return 3 * len(self.points)

    def split_coordinates(self, q):
        """(the system's q, ξ (…, c, 3)) from the scene's coordinates."""
        k = self.num_contact_states
        return q[..., :-k], q[..., -k:].reshape(*q.shape[:-1], len(self.points), 3)

    def coordinates(self, q, deformation=None):
        """The scene's coordinates (q, ξ) from the system's q (ξ = 0 unless given)."""
        q = jnp.asarray(q)
        if deformation is None:
            deformation = jnp.zeros((*q.shape[:-1], self.num_contact_states), q.dtype)
        return jnp.concatenate([q, jnp.reshape(deformation, (*q.shape[:-1], -1))], axis=-1)

    def initial_coordinates(self, q0, u0, p=None):
        """`q0` with ξ = 0 appended when it holds the system's coordinates alone."""
        q0, u0 = jnp.asarray(q0), jnp.asarray(u0)
        if q0.ndim == 0 or u0.ndim == 0:
            return q0
        first = q0[(0,) * (q0.ndim - 1)], u0[(0,) * (u0.ndim - 1)]  # (stacked states)
        try:
            rates = jax.eval_shape(
                lambda q, u: self.dynamics.coordinate_rates(jnp.zeros((), q.dtype), q, u, p),
                *first)
        except (ValueError, TypeError, IndexError):
            return q0
        if rates.shape == first[0].shape:
            return self.coordinates(q0)
        return q0

    def _contacts(self, t, q, u, p):
        """(kinematics, F, ξ̇, f_n, F_t, Q): every contact at one state, and the generalized
        active forces Q = Σ J_Cᵀ F along the speeds (v_C = J_C u)."""
        q, deformation = self.split_coordinates(q)
        kin = _kinematics(self, t, q, u, p)
        force, rate, normal, friction = self.model.forces(kin, deformation, p)
        generalized = jnp.einsum("kim,ki->m", kin.jacobian, force)
        return kin, force, rate, normal, friction, generalized

    @property
    def bounds_steps(self) -> bool:
        return True

    def step_bound(self, t, q, u, p=None):
        """The time for the nearest approaching contact point to reach the terrain and
        `APPROACH_DEPTH` into it: min over contacts of (max(g, 0) + d) / max(−n·v_C, 0). In
        flight (free fall integrated exactly, with an error estimate of zero) an adaptive
        solver's steps grow until one would carry a point through the ground, or deep into it,
        between two stages; so bounded, a stage meets the contact force and the error
        estimate takes over."""
        system_q, _ = self.split_coordinates(q)
        kin = _kinematics(self, t, system_q, u, p)
        approach = -jnp.sum(kin.normal * kin.velocity, axis=-1)
        reach = jnp.maximum(kin.gap, 0.0) + APPROACH_DEPTH
        return jnp.min(jnp.where(approach > 0, reach / jnp.where(approach > 0, approach, 1.0),
                                 jnp.inf))

    def contact_forces(self, t, q, u, p=None):
        """Q (m,): the contacts' generalized active forces along the speeds at one state."""
        q, u = check_vector(q, "q"), check_vector(u, "u")
        return self._contacts(jnp.asarray(t, q.dtype), q, u, p)[-1]

    # -- AbstractDynamics ----------------------------------------------------------------------

    @property
    def saved_records(self):
        return ("contact", *self.dynamics.saved_records)

    def record(self, name, ts, q, u, p=None):
        if name != "contact":
            return self.dynamics.record(name, ts, self.split_coordinates(q)[0], u, p)

        def one(t, q, u):
            kin, force, _, normal, friction, _ = self._contacts(t, q, u, p)
            v = kin.velocity
            v_t = v - jnp.sum(kin.normal * v, axis=-1)[:, None] * kin.normal
            return ContactRecord(gap=kin.gap, normal_force=normal, friction_force=friction,
                                 force=force, position=kin.position,
                                 slip_speed=jnp.linalg.norm(v_t, axis=-1),
                                 deformation=self.split_coordinates(q)[1])

        return jax.vmap(one)(ts, q, u)

    def coordinate_rates(self, t, q, u, p=None):
        system_q, _ = self.split_coordinates(q)
        rate = self._contacts(jnp.asarray(t, q.dtype), q, u, p)[2]
        return jnp.concatenate([self.dynamics.coordinate_rates(t, system_q, u, p),
                                rate.reshape(-1)])

    def form_equations(self, t, q, u, p=None):
        """(M, f + Q)."""
        mass_matrix, forcing = self.dynamics.form_equations(t, self.split_coordinates(q)[0],
                                                            u, p)
        return mass_matrix, forcing + self._contacts(jnp.asarray(t, q.dtype), q, u, p)[-1]

    def form_residual(self, t, q, u, ud, p=None):
        """The system's M u̇ − f, less the contact forces Q."""
        return (self.dynamics.form_residual(t, self.split_coordinates(q)[0], u, ud, p)
                - self._contacts(jnp.asarray(t, q.dtype), q, u, p)[-1])

    def form_accelerations(self, t, q, u, p=None, *, small):
        return self.form_rates_and_accelerations(t, q, u, p, small=small)[1:]

    @property
    def _articulated(self) -> RigidBodyTree | None:
        """The tree whose articulated-body algorithm takes the contact forces, when the system
        in contact is one (also driven), else None."""
        inner = self.dynamics
        if isinstance(inner, Controlled):
            inner = inner.dynamics
        return inner.tree if isinstance(inner, ArticulatedBody) else None

    @property
    def equations_in_straight_line(self) -> bool:
        """False for a tree, whose contact forces join the articulated-body algorithm as
        array operations (not straight-line code): a solver's stages then run in a loop, not
        written out 13 times over (two balls on the ground: 47 s to compile written out, 5 s
        as a loop)."""
        return self._articulated is None and self.dynamics.equations_in_straight_line

    def form_rates_and_accelerations(self, t, q, u, p=None, *, small):
        """(q̇ with ξ̇, u̇, singular, nonfinite), the contacts formed once for both."""
        t = jnp.asarray(t, q.dtype)
        system_q, _ = self.split_coordinates(q)
        _, _, rate, _, _, forces = self._contacts(t, q, u, p)
        rates = jnp.concatenate([self.dynamics.coordinate_rates(t, system_q, u, p),
                                 rate.reshape(-1)])
        tree = self._articulated
        if tree is None:
            return rates, *accelerations_from_equations(self, t, q, u, p, small=small)
        if isinstance(self.dynamics, Controlled):
            forces = forces + self.dynamics.applied(t, system_q, u, p)
        # The articulated-body algorithm with the contact forces joining the joint forces.
        return rates, *articulated_body_algorithm(tree.merge_fixed(), t, system_q, u, p,
                                                  applied=forces)

    def energy_terms(self, t, q, u, p=None):
        return self.dynamics.energy_terms(t, self.split_coordinates(q)[0], u, p)

    def user_functions(self, t, q, u, p=None):
        """The system's callbacks, the contact points given as functions, the terrain at the
        first point and the law's constants: the user's code alone, which `simulate` checks
        with constants folded at trace time (not the tree's kinematics, whose constant
        operations would then each run and compile on their own)."""
        q, u = check_vector(q, "q"), check_vector(u, "u")
        system_q, _ = self.split_coordinates(q)
        points = [c.body(system_q, p) for c in _members(self.points) if callable(c.body)]
        where = points[0] if points else jnp.zeros(3, q.dtype)
        law = [_value(x, p) for x in (self.model.stiffness, self.model.dissipation,
                                      self.model.friction)]
        return (self.dynamics.user_functions(t, system_q, u, p), points,
                self.terrain.distance_and_normal(jnp.asarray(where, q.dtype), p), law)

    def state_projection(self):
        inner = self.dynamics.state_projection()
        if inner is None:
            return None

        def projection(t, q, u, p):
            system_q, deformation = self.split_coordinates(q)
            system_q, u = inner(t, system_q, u, p)
            return self.coordinates(system_q, deformation), u

        return projection

    def singular_constraints(self, t, q, u, p=None):
        return self.dynamics.singular_constraints(t, self.split_coordinates(q)[0], u, p)

    def state_constraints(self, t, q, u, p=None):
        return self.dynamics.state_constraints(t, self.split_coordinates(q)[0], u, p)


# The contacts' kinematics are asked for at every stage of a step, by the step bound and by the
# records: traced once per solve (a nested jit, inlined by XLA) rather than once per use.
@eqx.filter_jit
def _kinematics(scene, t, q, u, p):
    return contact_kinematics(scene.points, scene.terrain, find_tree(scene.dynamics),
                              scene.dynamics.coordinate_rates, t, q, u, p)
