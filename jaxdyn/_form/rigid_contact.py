r"""Rigid contact with Coulomb friction, as events: impacts by Newton's and Coulomb's laws in
the complementarity form of Moreau and Glocker, and resting contacts that stick or slide.

At each contact point the relative velocity of the touching material points is written in
the contact frame (n, t₁, t₂): γ = (γ_N, γ_T) = J u, with J (3, m) the rows of `rows`. The
contact forces are (λ_N, λ_T), the impulses of an impact (Λ_N, Λ_T).

**Impacts** (Glocker 2001, ch. 8): M (u⁺ − u⁻) = Σ Jᵀ Λ over the closed contacts, with

$$Λ_N \ge 0,\; ξ_N \ge 0,\; Λ_N ξ_N = 0,\qquad ξ_N = γ_N^+ + e\,γ_N^-,$$
$$\|Λ_T\| \le μ Λ_N,\qquad -ξ_T \in N_{\{\|Λ_T\| \le μΛ_N\}}(Λ_T),\qquad ξ_T = γ_T^+,$$

Newton's law normally and Coulomb's tangentially: the touching points stop slipping after the
impact (ξ_T = 0) unless that needs more than μ Λ_N, in which case Λ_T = −μ Λ_N ξ_T/‖ξ_T‖. The
impulses solve Λ = prox(Λ − r ξ(Λ)), the projection of Alart and Curnier onto
Λ_N ≥ 0 and the disc ‖Λ_T‖ ≤ μ Λ_N (Studer 2009): by the projected iteration to a few
digits, then by Newton's method on its semismooth equation, whose step at the solution also
gives the impulses' derivatives by the implicit function theorem.

**Resting contact**: a contact at rest holds γ̇_N = 0 with λ_N ≥ 0; it sticks (γ̇_T = 0,
‖λ_T‖ ≤ μ λ_N) or slides (λ_T = −μ λ_N γ_T/‖γ_T‖). The switches are events: a contact
lifts off when λ_N falls through zero; a sticking contact starts to slide when its margin
μ λ_N − ‖λ_T‖ falls through zero, in the direction −λ_T; a sliding contact stops when its slip
velocity along its direction at the segment's start, γ_T · d, falls through zero, and
then sticks if friction can hold it (μ λ_N ≥ ‖λ_T‖) or slides on.

References: Ch. Glocker, Set-Valued Force Laws (2001); F. Pfeiffer, Ch. Glocker, Multibody
Dynamics with Unilateral Contacts (1996), ch. 6–7; J. J. Moreau, "Unilateral contact and dry
friction in finite freedom dynamics" (1988); P. Alart, A. Curnier, "A mixed formulation for
frictional contact problems prone to Newton like solution methods", CMAME 92 (1991);
C. Studer, Numerics of Unilateral Contacts and Friction (2009).
"""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from .._dynamics import equations_of_motion
from .._events import constraint_response, hold
from .._linalg import small_solve
from .._system.contact import (AbstractTerrain, ContactPair, ContactPoint, Plane, check_points,
                               contact_kinematics, find_tree)
from .impact import MAX_SIMULTANEOUS, AbstractContactEvent, comes_to_rest


class RigidContact(AbstractContactEvent):
    r"""Contact points and spheres touching a terrain (or each other) as rigid unilateral
    contacts with Coulomb friction: impacts by Newton's law of restitution and Coulomb's law
    of friction (Glocker's frictional impact law), and resting contacts that stick or slide,
    their switches located as events (module `jaxdyn._form.rigid_contact`). For scenes of a
    few contacts: a block sliding to rest, a ball struck spinning onto the ground, a rod
    landing on its ends; compliant contact (`jaxdyn.Contact`) for robots' feet.

    Its guards are the k gaps g (in the order of `points`), then k friction guards: 1 in
    flight, the slip velocity along its direction γ_T · d while sliding, the margin
    μ λ_N − ‖λ_T‖ while sticking. `Solution.events` records impulses per guard (Λ_N, then
    ‖Λ_T‖), the guards at rest after each event (a gap at rest: the contact is closed; a
    friction guard at rest: it sticks), and the forces at the save times (λ_N, then the
    friction force ‖λ_T‖).

    **Arguments:**

    - `points`: `jaxdyn.ContactPoint`s (spheres on links or functions of q) and
      `jaxdyn.ContactPair`s, as for `jaxdyn.Contact`.
    - `terrain`: a `jaxdyn.Plane` (default: the ground z = 0) or `jaxdyn.HeightField`.
    - `restitution`: Newton's e ∈ [0, 1]: a number, an array (k,), or a function e(p).
    - `friction`: Coulomb's μ ≥ 0: a number, an array (k,), or a function μ(p).
    - `closed_within`: gaps at most this are closed at an impact (simultaneous contacts).
    - `rest_within`: a contact whose next flight would last less than this comes to rest
      (as for `jaxdyn.UnilateralContact`).
    - `stick_within`: a contact at rest slipping slower than this after an event sticks, if
      friction can hold it.

    **Example** (a box on the ground, pushed):

        scene = jaxdyn.RigidContact(jaxdyn.box_corners("box", (0.2, 0.1, 0.05))[:4],
                                    friction=0.5)
        sol = jaxdyn.simulate(jaxdyn.ArticulatedBody(tree), q0, u0, t1=1.0, events=[scene])
        sol.events.t[:sol.events.count]   # landing, then the box sticks
    """

    points: tuple[ContactPoint | ContactPair, ...]
    terrain: AbstractTerrain
    restitution: float | jax.Array | Callable
    friction: float | jax.Array | Callable
    closed_within: float = eqx.field(static=True)
    rest_within: float = eqx.field(static=True)
    stick_within: float = eqx.field(static=True)

    def __init__(self, points: Sequence[ContactPoint | ContactPair] | ContactPoint | ContactPair,
                 terrain: AbstractTerrain | None = None, restitution=0.0, friction=0.0, *,
                 closed_within: float = 1e-9, rest_within: float = 1e-5,
                 stick_within: float = 1e-8):
        terrain = Plane() if terrain is None else terrain
        if not isinstance(terrain, AbstractTerrain):
            raise ValueError("terrain must be a jaxdyn.Plane or jaxdyn.HeightField (an "
                             f"AbstractTerrain), got {type(terrain).__name__}.")
        points = (points,) if isinstance(points, (ContactPoint, ContactPair)) else tuple(points)
        if not points or not all(isinstance(c, (ContactPoint, ContactPair)) for c in points):
            raise ValueError("points must be a non-empty sequence of jaxdyn.ContactPoint or "
                             f"jaxdyn.ContactPair, got {points!r}.")
        if len(points) > MAX_SIMULTANEOUS:
            raise ValueError(f"A RigidContact of {len(points)} points: rigid contact is for "
                             f"scenes of a few contacts (at most {MAX_SIMULTANEOUS}); use "
                             "compliant contact (jaxdyn.Contact) for more.")
        for name, value in (("closed_within", closed_within), ("rest_within", rest_within),
                            ("stick_within", stick_within)):
            if not value >= 0:
                raise ValueError(f"{name} must be ≥ 0, got {value}.")
        self.points = points
        self.terrain = terrain
        self.restitution = restitution
        self.friction = friction
        self.closed_within = float(closed_within)
        self.rest_within = float(rest_within)
        self.stick_within = float(stick_within)

    # -- the contacts at one state ------------------------------------------------------------

    def contact_state(self, dynamics, t, q, u, p):
        """(g (k,), frame (k, 3, 3) of rows n, t₁, t₂, J (k, 3, m), γ = J u (k, 3), the bias
        γ̇ − J u̇ (k, 3)): the gaps, the contact frames, the relative velocities in them and
        their Jacobians along the speeds."""
        return _contact_state(self, dynamics, t, q, u, p)

    def coefficients(self, p, dtype):
        """(e (k,), μ (k,))."""
        k = len(self.points)
        out = []
        for name, value in (("restitution", self.restitution), ("friction", self.friction)):
            value = jnp.asarray(value(p) if callable(value) else value, dtype)
            if value.ndim > 1 or (value.ndim == 1 and value.shape[0] != k):
                raise ValueError(f"The {name} must be a number or an array of {k} "
                                 f"coefficients (one per contact), got shape {value.shape}.")
            out.append(jnp.broadcast_to(value, (k,)))
        return tuple(out)

    def guards(self, dynamics, t, q, u, p):
        """The gaps g, then the slip speeds ‖γ_T‖ (the friction guards as they are)."""
        gap, _, _, velocity, _ = self.contact_state(dynamics, t, q, u, p)
        return jnp.concatenate([gap, _norm(velocity[:, 1:])])

    def contact_rows(self, dynamics, t, q, u, p):
        return None  # (held_rows is this event's own)

    def _modes(self, resting):
        k = len(self.points)
        closed = resting[:k]
        return closed, resting[k:] & closed

    def _slip(self, velocity, reference, frame):
        """The direction of the friction force's opposite in the tangent plane (k, 2): the
        slip's direction, kept along the segment's direction d where the slip reverses (so
        that the field is smooth up to the event that stops it), and d itself while the slip
        is slower than `stick_within` (a slip starting from rest)."""
        tangential = velocity[:, 1:]
        along = jnp.einsum("kij,kj->ki", frame[:, 1:], reference)
        speed = _norm(tangential)
        sign = jnp.where(jnp.sum(tangential * along, axis=1) >= 0, 1.0, -1.0)
        return jnp.where((speed > self.stick_within)[:, None],
                         sign[:, None] * tangential / speed[:, None], along)

    def held_rows(self, dynamics, t, q, u, p, resting, reference):
        """The normal rows of the contacts at rest (their friction −μ λ_N along the slip
        folded into W for those sliding), and the tangential rows of those sticking."""
        closed, sticking = self._modes(resting)
        _, frame, rows, velocity, bias = self.contact_state(dynamics, t, q, u, p)
        _, mu = self.coefficients(p, q.dtype)
        slip = self._slip(velocity, reference, frame)
        sliding = closed & ~sticking
        normal = rows[:, 0] - jnp.where(sliding, mu, 0.0)[:, None] * (slip[:, :1] * rows[:, 1]
                                                         + slip[:, 1:] * rows[:, 2])
        m = u.shape[0]
        return (jnp.transpose(rows, (1, 0, 2)).reshape(-1, m),
                jnp.concatenate([normal, rows[:, 1], rows[:, 2]]),
                bias.T.reshape(-1), jnp.concatenate([closed, sticking, sticking]))

    def _split_forces(self, forces):
        k = len(self.points)
        return forces[:k], jnp.stack([forces[k:2 * k], forces[2 * k:]], axis=1)

    def held_values(self, dynamics, t, q, u, p, forces, resting, reference):
        """λ_N in place of the gaps at rest; the friction guards (class docstring)."""
        closed, sticking = self._modes(resting)
        gap, frame, _, velocity, _ = self.contact_state(dynamics, t, q, u, p)
        _, mu = self.coefficients(p, q.dtype)
        normal, tangential = self._split_forces(forces)
        along = jnp.einsum("kij,kj->ki", frame[:, 1:], reference)
        slip = jnp.sum(velocity[:, 1:] * along, axis=1)
        friction = jnp.where(sticking, mu * normal - _norm(tangential),
                             jnp.where(closed, slip, 1.0))
        return jnp.concatenate([jnp.where(closed, normal, gap), friction])

    def held_forces(self, forces, resting, p):
        """λ_N, then the friction force's magnitude: ‖λ_T‖ sticking, μ λ_N sliding."""
        closed, sticking = self._modes(resting)
        normal, tangential = self._split_forces(forces)
        _, mu = self.coefficients(p, forces.dtype)
        return jnp.concatenate([jnp.where(closed, normal, 0.0),
                                jnp.where(sticking, _norm(tangential),
                                          jnp.where(closed, mu * normal, 0.0))])

    def reference(self, dynamics, t, q, u, p, resting):
        """The slip directions d (k, 3) in the world at a segment's start: the slip's own
        where it slips, else −λ_T/‖λ_T‖ of the contact held sticking (where a slip starts)."""
        closed, _ = self._modes(resting)
        _, frame, _, velocity, _ = self.contact_state(dynamics, t, q, u, p)
        tangential = jnp.einsum("ki,kij->kj", velocity[:, 1:], frame[:, 1:])
        speed = _norm(velocity[:, 1:])
        _, free, _, _ = equations_of_motion(dynamics, t, q, u, p)
        zero = jnp.zeros(tangential.shape, q.dtype)
        stuck = self.held_rows(dynamics, t, q, u, p, jnp.concatenate([closed, closed]), zero)
        _, forces = hold(dynamics, t, q, u, p, free, stuck)
        load = jnp.einsum("ki,kij->kj", self._split_forces(forces)[1], frame[:, 1:])
        onset = jnp.where((_norm(load) > 0)[:, None], -load / _norm(load)[:, None],
                          frame[:, 1])
        return jnp.where((speed > self.stick_within)[:, None],
                         tangential / speed[:, None], onset)

    def _sustained(self, dynamics, t, q, u, p, closed, sticking, mu):
        """Of the contacts asked to stick, those friction can hold (‖λ_T‖ ≤ μ λ_N), found by
        holding them and releasing those that would need more (twice, for contacts whose
        release shifts the load onto others)."""
        _, free, _, _ = equations_of_motion(dynamics, t, q, u, p)
        zero = jnp.zeros((len(self.points), 3), q.dtype)
        for _ in range(2):
            rows = self.held_rows(dynamics, t, q, u, p, jnp.concatenate([closed, sticking]),
                                  zero)
            normal, tangential = self._split_forces(hold(dynamics, t, q, u, p, free, rows)[1])
            sticking = sticking & (_norm(tangential) <= mu * normal)
        return sticking

    def jump(self, dynamics, t, q, u, p, fired, resting):
        """An impact where a gap closed (frictional impact law; contacts whose next flight
        would be shorter than `rest_within` come to rest, plastically); a lift-off where a
        resting contact's λ_N fell through zero; a change of friction mode where a friction
        guard fired. Then the contacts at rest slipping slower than `stick_within` stick if
        friction holds them."""
        k = len(self.points)
        closed_before, sticking = self._modes(resting)
        fired_gap, fired_friction = fired[:k], fired[k:]
        gap, _, rows, velocity, _ = self.contact_state(dynamics, t, q, u, p)
        restitution, mu = self.coefficients(p, q.dtype)
        closed = fired_gap | closed_before | (gap <= self.closed_within)
        impact = jnp.any(fired_gap & ~closed_before)
        m = u.shape[0]
        jacobian = rows.reshape(-1, m)
        response = constraint_response(dynamics, t, q, u, p, jacobian)
        delassus = jacobian @ response
        approaching = velocity[:, 0] < 0

        def impulses(bouncing):
            free = velocity.at[:, 0].multiply(jnp.where(bouncing, 1 + restitution, 1.0))
            return coulomb_impulses(delassus, free, closed, mu)

        # which contacts would come to rest after bouncing (their next flight is short)
        bounced = u + response @ impulses(approaching).reshape(-1)
        _, accelerations, _, _ = equations_of_motion(dynamics, t, q, bounced, p)
        _, _, rows_b, velocity_b, bias_b = self.contact_state(dynamics, t, q, bounced, p)
        rest = comes_to_rest(closed, velocity_b[:, 0],
                             rows_b[:, 0] @ accelerations + bias_b[:, 0], self.rest_within)
        struck = impulses(approaching & ~rest)
        u_plus = jnp.where(impact, u + response @ struck.reshape(-1), u)
        struck = jnp.where(impact, struck, 0.0)
        closed_plus = jnp.where(impact, rest, closed_before & ~fired_gap)
        # friction modes: a contact released from sticking slides; one slipping slower
        # than stick_within sticks if friction holds it
        slip = _norm((rows @ u_plus)[:, 1:])
        asked = closed_plus & (slip <= self.stick_within) & ~(fired_friction & sticking)
        sticking_plus = self._sustained(dynamics, t, q, u_plus, p, closed_plus, asked, mu)
        return (q, u_plus, jnp.concatenate([struck[:, 0], _norm(struck[:, 1:])]),
                jnp.concatenate([closed_plus, sticking_plus]))


def _norm(x):
    """‖x‖ along the last axis, with a derivative at zero (zero)."""
    square = jnp.sum(x * x, axis=-1)
    safe = jnp.sqrt(jnp.where(square > 0, square, 1.0))
    return jnp.where(square > 0, safe, 0.0)


def contact_frame(normal):
    """(k, 3, 3): rows n, t₁, t₂, an orthonormal frame smooth in n (t₁ ⟂ n from the world's x
    axis, or y where n is nearly along x)."""
    axis = jnp.where((jnp.abs(normal[:, :1]) < 0.9), jnp.array([1.0, 0.0, 0.0], normal.dtype),
                     jnp.array([0.0, 1.0, 0.0], normal.dtype))
    first = jnp.cross(normal, axis)
    first = first / jnp.linalg.norm(first, axis=1, keepdims=True)
    return jnp.stack([normal, first, jnp.cross(normal, first)], axis=1)


# Asked for at every stage by the guards, the held rows and the jump: traced once per solve
# (a nested jit, inlined by XLA).
@eqx.filter_jit
def _contact_state(event, dynamics, t, q, u, p):
    points = check_points(event.points, find_tree(dynamics))

    def velocity(q):
        kin = contact_kinematics(points, event.terrain, find_tree(dynamics),
                                 dynamics.coordinate_rates, t, q, u, p)
        frame = contact_frame(kin.normal)
        rows = jnp.einsum("kij,kjm->kim", frame, kin.jacobian)
        return rows @ u, (kin.gap, frame, rows)

    q_dot = dynamics.coordinate_rates(t, q, u, p)
    speed, bias, (gap, frame, rows) = jax.jvp(velocity, (q,), (q_dot,), has_aux=True)
    return gap, frame, rows, speed, bias


def _prox(impulses, velocity, closed, mu, r):
    """prox(Λ − r ξ): the normal impulses onto Λ_N ≥ 0, the tangential onto the disc
    ‖Λ_T‖ ≤ μ Λ_N; zero on the open contacts."""
    trial = impulses - r * velocity
    normal = jnp.maximum(trial[:, 0], 0.0)
    tangential = trial[:, 1:]
    size = _norm(tangential)
    scale = jnp.where(size > mu * normal, mu * normal / jnp.where(size > 0, size, 1.0), 1.0)
    out = jnp.concatenate([normal[:, None], tangential * scale[:, None]], axis=1)
    return jnp.where(closed[:, None], out, 0.0)


def coulomb_impulses(delassus, free, closed, mu):
    """Λ (k, 3) of the frictional impact law on the `closed` contacts, ξ = free + G Λ with G
    the Delassus matrix (3k, 3k) in the contacts' frames (contact by contact: N, T₁, T₂) and
    `free` (k, 3) the velocities ξ at Λ = 0: ((1 + e) γ_N⁻, γ_T⁻).

    The fixed point Λ = prox(Λ − r ξ(Λ)) (module docstring) is found by the projected
    iteration with r = 1/tr G (convergent: r ‖G‖ < 1), to 1e-3 of round-off or 4000 sweeps,
    then refined by two Newton steps on Λ − prox(Λ − r ξ(Λ)) = 0, each accepted if it lowers
    the residual. The Newton steps are taken from the iterate with its derivative cut, so
    that the derivative of Λ is that of the implicit function theorem at the solution."""
    k = closed.shape[0]
    dtype = free.dtype
    active = jnp.repeat(closed, 3)
    r = 1.0 / jnp.maximum(jnp.sum(jnp.where(active, jnp.abs(jnp.diagonal(delassus)), 0.0)),
                          jnp.finfo(dtype).tiny)

    def step(impulses, delassus, free, mu):
        velocity = free + (delassus @ impulses.reshape(-1)).reshape(k, 3)
        return _prox(impulses, velocity, closed, mu, r)

    scale = jnp.maximum(jnp.max(jnp.abs(free)) * r, jnp.finfo(dtype).tiny)
    tolerance = 1e3 * jnp.finfo(dtype).eps * scale

    def unfinished(carry):
        _, change, count = carry
        return (change > tolerance) & (count < 4000)

    def sweep(carry):
        impulses, _, count = carry
        new = step(impulses, *jax.lax.stop_gradient((delassus, free, mu)))
        return new, jnp.max(jnp.abs(new - impulses)), count + 1

    start = jnp.zeros((k, 3), dtype)
    impulses, _, _ = jax.lax.while_loop(unfinished, sweep,
                                        (start, jnp.asarray(jnp.inf, dtype), 0))
    impulses = jax.lax.stop_gradient(impulses)

    def residual(x):
        x = x.reshape(k, 3)
        return (x - step(x, delassus, free, mu)).reshape(-1)

    eye = jnp.eye(3 * k, dtype=dtype)
    for _ in range(2):
        x = impulses.reshape(-1)
        value = residual(x)
        matrix = jax.jacfwd(residual)(x)
        # (a regularisation at round-off: redundant contacts leave it singular)
        newton = x - small_solve(matrix + 16 * jnp.finfo(dtype).eps * eye, value)
        better = jnp.sum(residual(newton) ** 2) <= jnp.sum(value ** 2)
        impulses = jnp.where(better, newton, x).reshape(k, 3)
    return impulses
