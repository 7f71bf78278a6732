"""The benchmark systems derived symbolically with sympy.physics.mechanics (Kane's method) and
lambdified to jax.numpy: the route a user of sympy would take to the same equations.

Each function returns (accelerations(t, q, qd, p), derivation seconds), where the derivation
covers building the model, `kanes_equations` and `lambdify`; the accelerations solve the
lambdified M q̈ = f with `jnp.linalg.solve`.
"""

import time

import jax.numpy as jnp
import sympy as sm
import sympy.physics.mechanics as me


def _lambdified(kane, q, u, symbols, names):
    function = sm.lambdify((q, u, symbols), (kane.mass_matrix, kane.forcing), modules="jax")

    def accelerations(t, q_, qd_, p):
        mass_matrix, forcing = function(q_, qd_, [p[name] for name in names])
        return jnp.linalg.solve(mass_matrix, forcing[:, 0])

    return accelerations


def _kane(frame, q, u, bodies, loads):
    kane = me.KanesMethod(frame, q_ind=q, u_ind=u,
                          kd_eqs=[qi.diff() - ui for qi, ui in zip(q, u)])
    kane.kanes_equations(bodies, loads)
    return kane


def double_pendulum():
    start = time.perf_counter()
    q = me.dynamicsymbols("q1:3")
    u = me.dynamicsymbols("u1:3")
    m1, m2, l1, l2, g = symbols = sm.symbols("m1 m2 l1 l2 g")
    frame = me.ReferenceFrame("N")
    origin = me.Point("O")
    origin.set_vel(frame, 0)
    rates = {qi.diff(): ui for qi, ui in zip(q, u)}
    p1 = origin.locatenew("P1", l1 * (sm.sin(q[0]) * frame.x - sm.cos(q[0]) * frame.y))
    p2 = p1.locatenew("P2", l2 * (sm.sin(q[1]) * frame.x - sm.cos(q[1]) * frame.y))
    for point in (p1, p2):
        point.set_vel(frame, point.pos_from(origin).dt(frame).subs(rates))
    bodies = [me.Particle("A", p1, m1), me.Particle("B", p2, m2)]
    kane = _kane(frame, q, u, bodies, [(p1, -m1 * g * frame.y), (p2, -m2 * g * frame.y)])
    accelerations = _lambdified(kane, q, u, symbols, ["m1", "m2", "l1", "l2", "g"])
    return accelerations, time.perf_counter() - start


def elastic_pendulum():
    start = time.perf_counter()
    q = me.dynamicsymbols("r theta")
    u = me.dynamicsymbols("ur utheta")
    m, g, k, l0 = symbols = sm.symbols("m g k l0")
    frame = me.ReferenceFrame("N")
    origin = me.Point("O")
    origin.set_vel(frame, 0)
    rates = {qi.diff(): ui for qi, ui in zip(q, u)}
    ball = origin.locatenew("P", q[0] * (sm.sin(q[1]) * frame.x - sm.cos(q[1]) * frame.y))
    ball.set_vel(frame, ball.pos_from(origin).dt(frame).subs(rates))
    along = ball.pos_from(origin).normalize()
    spring = -k * (q[0] - l0) * along
    kane = _kane(frame, q, u, [me.Particle("B", ball, m)], [(ball, -m * g * frame.y + spring)])
    accelerations = _lambdified(kane, q, u, symbols, ["m", "g", "k", "l0"])
    return accelerations, time.perf_counter() - start


def chain(n):
    start = time.perf_counter()
    q = me.dynamicsymbols(f"q1:{n + 1}")
    u = me.dynamicsymbols(f"u1:{n + 1}")
    m, l, g = symbols = sm.symbols("m l g")
    frame = me.ReferenceFrame("N")
    origin = me.Point("O")
    origin.set_vel(frame, 0)
    rates = {qi.diff(): ui for qi, ui in zip(q, u)}
    bodies, loads, joint = [], [], origin
    for i in range(n):
        link = frame.orientnew(f"L{i}", "Axis", (q[i], frame.z))
        link.set_ang_vel(frame, u[i] * frame.z)
        direction = sm.sin(q[i]) * frame.x - sm.cos(q[i]) * frame.y
        centre = joint.locatenew(f"G{i}", l / 2 * direction)
        centre.set_vel(frame, centre.pos_from(origin).dt(frame).subs(rates))
        inertia = me.inertia(link, 0, 0, m * l**2 / 12)
        bodies.append(me.RigidBody(f"R{i}", centre, link, m, (inertia, centre)))
        loads.append((centre, -m * g * frame.y))
        joint = joint.locatenew(f"J{i}", l * direction)
    kane = _kane(frame, q, u, bodies, loads)
    accelerations = _lambdified(kane, q, u, symbols, ["m", "l", "g"])
    return accelerations, time.perf_counter() - start
