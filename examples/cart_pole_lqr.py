"""jaxdyn example: a cart-pole balanced by an LQR designed on jaxdyn's linearisation.

The cart-pole (cart x, pole angle θ from the upward vertical, a point mass m on a massless
pole of length l) is written as energies; a force F on the cart is its one input:

    T = ½ (M + m) ẋ² + m l ẋ θ̇ cos θ + ½ m l² θ̇²,    V = m g l cos θ,    B = [1, 0]ᵀ.

The script finds the upright equilibrium, linearises about it (A and B checked against the
textbook matrices), reads off the modes, designs a linear-quadratic regulator (the Riccati
equation solved by SciPy), simulates the nonlinear closed loop from a 30° tilt with the applied
force saved, and sweeps the pole length in one vmapped batch of linearisations (a root locus).

Run:  python examples/cart_pole_lqr.py      (plots to cart_pole_lqr.png with matplotlib)
"""

import jax

jax.config.update("jax_enable_x64", True)  # mechanics wants float64; jaxdyn never sets it

import jax.numpy as jnp
import numpy as np
import scipy.linalg

import jaxdyn

P = dict(M=1.0, m=0.1, l=0.5, g=9.81)


def T(q, qd, p):
    return (0.5 * (p["M"] + p["m"]) * qd[0] ** 2
            + p["m"] * p["l"] * qd[0] * qd[1] * jnp.cos(q[1])
            + 0.5 * p["m"] * p["l"] ** 2 * qd[1] ** 2)


def V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])


plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])  # the force acts on x

# 1. The upright equilibrium (cart held at x = 0: the force that holds it there is solved for).
upright = jaxdyn.equilibrium(plant, jnp.array([0.0, 0.1]), P, prescribed={0: 0.0})
print(f"equilibrium q = {np.asarray(upright.q)}, holding force {float(upright.r[0]):.2e} N")

# 2. Linearisation: δẋ = A δx + B δF with x = (x, θ, ẋ, θ̇).
model = jaxdyn.linearise(plant, 0.0, upright.q, jnp.zeros(2), P, upright.r)
M, m, l, g = P["M"], P["m"], P["l"], P["g"]
textbook_A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, -m * g / M, 0, 0],
                       [0, (M + m) * g / (M * l), 0, 0]])
textbook_B = np.array([[0], [0], [1 / M], [-1 / (M * l)]])
print(f"A, B against the textbook: {np.abs(model.A - textbook_A).max():.1e}, "
      f"{np.abs(model.B - textbook_B).max():.1e}")
print(f"open loop: {model.stability()}, eigenvalues {np.round(np.asarray(model.eigenvalues()), 4)}"
      f", controllable: {model.is_controllable()}")

# 3. LQR: minimise ∫ xᵀQx + Rr² dt; P from the continuous algebraic Riccati equation.
Q, R = np.diag([10.0, 100.0, 1.0, 1.0]), np.array([[0.1]])
riccati = scipy.linalg.solve_continuous_are(np.asarray(model.A), np.asarray(model.B), Q, R)
gain = np.linalg.solve(R, np.asarray(model.B).T @ riccati)
closed = model.A - model.B @ gain
print(f"LQR gain K = {np.round(gain, 3)}; closed-loop eigenvalues "
      f"{np.round(np.linalg.eigvals(np.asarray(closed)), 3)}")


def policy(t, q, u, p):
    """F = −K (x − x*), the LQR state feedback."""
    return -jnp.asarray(gain) @ jnp.concatenate([q - upright.q, u])


# 4. The nonlinear closed loop from a 30° tilt, the applied force saved.
ts = jnp.linspace(0.0, 6.0, 301)
solution = jaxdyn.simulate(plant, jnp.array([0.0, np.radians(30.0)]), jnp.zeros(2), P,
                           t1=6.0, ts=ts, inputs=policy, save=("q", "u", "inputs"))
print(f"closed loop: |θ(6 s)| = {abs(float(solution.q[-1, 1])):.2e} rad, "
      f"|x(6 s)| = {abs(float(solution.q[-1, 0])):.2e} m, peak force "
      f"{float(jnp.max(jnp.abs(solution.inputs))):.2f} N")

# 5. Root locus over the pole length: one vmapped batch of linearisations.
lengths = jnp.linspace(0.2, 2.0, 40)
eigenvalues = jax.vmap(lambda length: jnp.linalg.eigvals(jaxdyn.linearise(
    plant, 0.0, jnp.zeros(2), jnp.zeros(2), dict(P, l=length)).A))(lengths)
rate = jnp.max(eigenvalues.real, axis=1)
print(f"unstable eigenvalue from l = 0.2 m to 2 m: {float(rate[0]):.3f} → {float(rate[-1]):.3f}"
      f" 1/s (closed form √((M+m)g/(Ml)): {np.sqrt((M + m) * g / (M * 0.2)):.3f} → "
      f"{np.sqrt((M + m) * g / (M * 2.0)):.3f})")

# 6. Its gradient: how the growth rate changes with the pole length, by autodiff.
growth = lambda length: jnp.max(jnp.linalg.eigvals(jaxdyn.linearise(  # noqa: E731
    plant, 0.0, jnp.zeros(2), jnp.zeros(2), dict(P, l=length)).A).real)
print(f"d(growth rate)/dl at l = 0.5 m: {float(jax.grad(growth)(0.5)):.4f} 1/(s m) "
      f"(closed form {-0.5 * np.sqrt((M + m) * g / M) * 0.5 ** -1.5:.4f})")

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    plt = None
if plt is not None:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    axes[0].plot(ts, np.degrees(solution.q[:, 1]), label="θ (deg)")
    axes[0].plot(ts, solution.q[:, 0] * 100, label="x (cm)")
    axes[0].set_xlabel("t (s)")
    axes[0].legend()
    axes[0].set_title("closed loop from 30°")
    axes[1].plot(ts, solution.inputs[:, 0])
    axes[1].set_xlabel("t (s)")
    axes[1].set_title("applied force F (N)")
    for k in range(4):
        axes[2].scatter(eigenvalues[:, k].real, eigenvalues[:, k].imag, c=lengths, s=8)
    axes[2].set_xlabel("Re λ")
    axes[2].set_ylabel("Im λ")
    axes[2].set_title("open-loop eigenvalues, l = 0.2…2 m")
    fig.tight_layout()
    fig.savefig("cart_pole_lqr.png", dpi=110)
    print("plots: cart_pole_lqr.png")
