"""sympy's KanesMethod for the rolling disc: the independent reference shared by the tests of
the independent-speed formulations and of the Pfaffian (multiplier) form."""

import functools

import sympy as sm
import sympy.physics.mechanics as me


@functools.lru_cache(maxsize=None)
def sympy_rolling_disc():
    """KanesMethod for the rolling disc, q = (x, y, ψ, θ, φ), speeds u = ω in lean axes, the
    rolling constraint embedded in the kinematic equations q̇ = K u. The velocity of the centre
    is the time derivative of its position (not the rolling formula), so sympy's partial
    velocities come from its own differentiation."""
    x, y, psi, th, ph = me.dynamicsymbols("x y psi theta phi")
    u1, u2, u3 = me.dynamicsymbols("u1 u2 u3")
    m, r, g = sm.symbols("m r g", positive=True)
    t = me.dynamicsymbols._t
    N = me.ReferenceFrame("N")
    Y = N.orientnew("Y", "Axis", [psi, N.z])
    L = Y.orientnew("L", "Axis", [th, Y.x])
    D = L.orientnew("D", "Axis", [ph, L.y])
    O = me.Point("O")
    O.set_vel(N, 0)
    G = O.locatenew("G", x * N.x + y * N.y + r * L.z)
    G.set_vel(N, G.pos_from(O).dt(N))
    spin = u2 - u3 * sm.tan(th)
    kd = [x.diff(t) - r * sm.cos(psi) * spin, y.diff(t) - r * sm.sin(psi) * spin,
          psi.diff(t) - u3 / sm.cos(th), th.diff(t) - u1, ph.diff(t) - spin]
    inertia = me.inertia(D, m * r**2 / 4, m * r**2 / 2, m * r**2 / 4)
    disc = me.RigidBody("disc", G, D, m, (inertia, G))
    coords = [x, y, psi, th, ph]
    kane = me.KanesMethod(N, q_ind=coords, u_ind=[u1, u2, u3], kd_eqs=kd)
    kane.kanes_equations([disc], [(G, -m * g * N.z)])
    qdot = sm.Matrix([c.diff(t) for c in coords]).subs(kane.kindiffdict())
    # sympy's own angular velocity of the disc in L axes: must be (u1, u2, u3) after q̇ = K u
    omega = sm.Matrix([D.ang_vel_in(N).dot(e) for e in (L.x, L.y, L.z)])
    omega = sm.simplify(omega.subs(kane.kindiffdict()))
    assert omega == sm.Matrix([u1, u2, u3]), omega
    # and the contact point of the disc is at rest: v_G + ω × (−r L_z) = 0
    contact_velocity = (G.vel(N) + D.ang_vel_in(N).cross(-r * L.z)).to_matrix(N)
    assert sm.simplify(contact_velocity.subs(kane.kindiffdict())) == sm.zeros(3, 1)
    args = (coords, [u1, u2, u3], [m, r, g])
    to_args = lambda q, u, p: (q, u, [p["m"], p["r"], p["g"]])
    return (sm.lambdify(args, kane.mass_matrix, "numpy"),
            sm.lambdify(args, kane.forcing, "numpy"),
            sm.lambdify(args, qdot, "numpy"), to_args)
