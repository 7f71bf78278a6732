"""The linear–quadratic subproblem of a shooting problem, solved by the Riccati recursion.

About a trajectory (x_k, r_k) with gaps g_{k+1} = F(x_k, r_k) − x_{k+1} (g_0 = x̂_0 − x_0 for
the initial state), the step (δx, δr) minimises the quadratic model

    Σ_k [ℓ_xᵀ δx_k + ℓ_rᵀ δr_k + ½ (δx_kᵀ ℓ_xx δx_k + 2 δr_kᵀ ℓ_rx δx_k + δr_kᵀ ℓ_rr δr_k)]
      + Φ_xᵀ δx_N + ½ δx_Nᵀ Φ_xx δx_N
    subject to δx_{k+1} = F_x δx_k + F_r δr_k + g_{k+1},   δx_0 = g_0,   r_lo ≤ r_k + δr_k ≤ r_hi.

Backwards from V_x = Φ_x, V_xx = Φ_xx, with the value expanded where the next state lands
(V'_x = V_x + V_xx g, the multiple-shooting form of Mastalli et al., "Crocoddyl", ICRA 2020):

    Q_x = ℓ_x + F_xᵀ V'_x,  Q_r = ℓ_r + F_rᵀ V'_x,  Q_xx = ℓ_xx + F_xᵀ V_xx F_x,
    Q_rr = ℓ_rr + F_rᵀ V_xx F_r,  Q_rx = ℓ_rx + F_rᵀ V_xx F_x   (+ V'_x · ∇²F for DDP),

and δr = k + K δx with k the minimiser of ½ δrᵀ (Q_rr + μI) δr + Q_rᵀ δr in the input box
(projected Newton, Tassa, Mansard and Todorov, "Control-limited differential dynamic
programming", ICRA 2014), K = −Q_rr,f⁻¹ Q_rx,f on the inputs left free (zero rows for those
at a bound), and

    V_x = Q_x + Kᵀ Q_rr k + Kᵀ Q_r + Q_rxᵀ k,   V_xx = Q_xx + Kᵀ Q_rr K + Kᵀ Q_rx + Q_rxᵀ K.

With input bounds (the box QP), as in box-DDP and Crocoddyl's box-FDDP, the value is
updated as for a minimiser on the free inputs alone, V_x = Q_x + Kᵀ Q_r,f and
V_xx = Q_xx + Q_rxᵀ K (Q_r,f: Q_r with the entries of inputs held at a bound zeroed): the
step the clamped inputs take to reach their bound (k's rows at a bound) is left out of the
value, and the model of the full step's change of cost is ΔJ(α) = α d₁ + ½ α² d₂ with
d₁ = Σ Q_r,f·k, d₂ = Σ kᵀ (Q_rr + μI) k. Where no bound is active, both updates are the same.
On the Panda reaching a point (torque limits active at 67 of 700 node inputs at the first
iteration) the exact expansion of the clamped policy took 137 iterations over six starts,
this update 108 (Crocoddyl's box-FDDP 89), to the same optima.

Reference: D. H. Jacobson and D. Q. Mayne, *Differential Dynamic Programming* (1970);
W. Li and E. Todorov, "Iterative linear quadratic regulator design", ICINCO 2004.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._linalg import spd_solve

_WRITTEN_OUT = 12  # inputs up to which the factorisation is straight-line code
_BOX_ITERATIONS = 30
_BOX_STEPS = 0.5 ** np.arange(12.0)  # NumPy: nothing computed with JAX at import


class Expansion(eqx.Module):
    """The derivatives of the discrete dynamics and costs at each node k < N (leading axis N),
    the terminal cost's at node N, and the gaps (N+1, n)."""

    fx: jax.Array
    fr: jax.Array
    lx: jax.Array
    lr: jax.Array
    lxx: jax.Array
    lrr: jax.Array
    lrx: jax.Array
    terminal_x: jax.Array
    terminal_xx: jax.Array
    gaps: jax.Array


class Gains(eqx.Module):
    """δr_k = k_k + K_k δx_k, the value's expansion V_x, V_xx at each node (N+1), which inputs
    were free (not at a bound), the dynamics' curvature V'_x · ∇²F in the model (DDP; zero
    for iLQR) and whether every Q_rr + μI was positive definite."""

    feedforward: jax.Array
    feedback: jax.Array
    value_x: jax.Array
    value_xx: jax.Array
    free: jax.Array
    curvature: tuple[jax.Array, jax.Array, jax.Array]
    ok: jax.Array
    expected: tuple[jax.Array, jax.Array] | None = None  # (d₁, d₂) of box-DDP's model


def _masked(matrix, free):
    """The Hessian restricted to the free inputs, the identity on the others: its solve
    leaves the inputs at a bound where they are."""
    both = free[:, None] & free[None, :]
    return jnp.where(both, matrix, jnp.eye(matrix.shape[0], dtype=matrix.dtype))


def _cholesky_solve(matrix, rhs):
    """(H⁻¹ b, whether H is positive definite) for a symmetric H by LDLᵀ (`spd_solve`):
    written out entry by entry for the few inputs of most problems (a LAPACK call costs more
    than the arithmetic of a 7 × 7 factorisation, at every node of every sweep), by columns
    above."""
    return spd_solve(matrix, rhs, written_out=_WRITTEN_OUT)


def box_qp(hessian, gradient, lo, hi, start):
    """argmin ½ δᵀ H δ + gᵀ δ over lo ≤ δ ≤ hi, by projected Newton (Bertsekas, "Projected
    Newton methods for optimization problems with simple constraints", SIAM J. Control
    Optim. 20, 1982): Newton steps on the inputs not held at a bound by their gradient, a
    projected backtracking search along them. Returns (δ, free, ok)."""
    def value(x):
        return 0.5 * x @ hessian @ x + gradient @ x

    def held(x):
        slope = hessian @ x + gradient
        return ((x <= lo) & (slope > 0)) | ((x >= hi) & (slope < 0))

    def body(state):
        x, _, it, _ = state
        slope = hessian @ x + gradient
        free = ~held(x)
        direction, ok = _cholesky_solve(_masked(hessian, free), -jnp.where(free, slope, 0))
        trials = jnp.clip(x[None] + jnp.asarray(_BOX_STEPS[:, None], x.dtype) * direction[None],
                          lo[None], hi[None])
        values = jax.vmap(value)(trials)
        decrease = values - value(x) <= 1e-4 * (trials - x[None]) @ slope  # Armijo, projected
        pick = jnp.argmax(decrease)
        moved = jnp.any(decrease) & ok
        new = jnp.where(moved, trials[pick], x)
        small = jnp.max(jnp.abs(jnp.where(free, slope, 0))) <= 1e-13 * (
            1 + jnp.max(jnp.abs(gradient)))
        return new, ok, it + 1, small | ~moved

    x0 = jnp.clip(start, lo, hi)
    x, ok, _, _ = jax.lax.while_loop(
        lambda s: (s[2] < _BOX_ITERATIONS) & ~s[3], body, (x0, jnp.array(True), 0,
                                                           jnp.array(False)))
    return x, ~held(x), ok


def backward_pass(expansion: Expansion, rs, lo, hi, regularisation, *, second_order=None,
                  free=None, start=None):
    """The Riccati recursion of the module's docstring. `second_order(k, V'_x)`:
    (h_xx, h_rr, h_rx) = ∇²(V'_x · F_k) for DDP, None for Gauss–Newton (iLQR). `free`: which
    inputs are free, fixed (N, k) (the sensitivity of an optimum, whose active bounds stay
    active); None: found by the box QP from the bounds (lo, hi) about the inputs rs.
    `start`: the previous feedforward, a warm start for the box QP."""
    m = expansion.fr.shape[2]
    bounded = free is None and lo is not None
    eye = jnp.eye(m, dtype=rs.dtype)
    num_nodes = rs.shape[0]
    start = jnp.zeros_like(rs) if start is None else start
    fixed_free = jnp.ones_like(rs, bool) if free is None else free

    def node(carry, data):
        vx, vxx = carry
        k, fx, fr, lx, lr, lxx, lrr, lrx, gap, r, warm, node_free = data
        vx_next = vx + vxx @ gap
        qx, qr = lx + fx.T @ vx_next, lr + fr.T @ vx_next
        qxx, qrr, qrx = lxx + fx.T @ vxx @ fx, lrr + fr.T @ vxx @ fr, lrx + fr.T @ vxx @ fx
        if second_order is None:
            hxx, hrr, hrx = jnp.zeros_like(qxx), jnp.zeros_like(qrr), jnp.zeros_like(qrx)
        else:
            hxx, hrr, hrx = second_order(k, vx_next)
            qxx, qrr, qrx = qxx + hxx, qrr + hrr, qrx + hrx
        regularised = qrr + regularisation * eye
        if bounded:
            ff, node_free, ok = box_qp(regularised, qr, lo - r, hi - r, warm)
            fb, ok_fb = _cholesky_solve(_masked(regularised, node_free),
                                        -jnp.where(node_free[:, None], qrx, 0))
        else:  # one factorisation for both
            both, ok = _cholesky_solve(_masked(regularised, node_free), -jnp.where(
                node_free[:, None], jnp.concatenate([qr[:, None], qrx], axis=1), 0))
            ff, fb, ok_fb = both[:, 0], both[:, 1:], ok
        if bounded:  # box-DDP's update, on the free inputs (the module's docstring)
            free_qr = jnp.where(node_free, qr, 0)
            vx, vxx = qx + fb.T @ free_qr, qxx + qrx.T @ fb
            expected = (free_qr @ ff, ff @ regularised @ ff)
        else:
            vx = qx + fb.T @ qrr @ ff + fb.T @ qr + qrx.T @ ff
            vxx = qxx + fb.T @ qrr @ fb + fb.T @ qrx + qrx.T @ fb
            expected = None
        vxx = 0.5 * (vxx + vxx.T)
        return (vx, vxx), (ff, fb, vx, vxx, node_free, (hxx, hrr, hrx), ok & ok_fb, expected)

    e = expansion
    data = (jnp.arange(num_nodes), e.fx, e.fr, e.lx, e.lr, e.lxx, e.lrr, e.lrx, e.gaps[1:], rs,
            start, fixed_free)
    _, (ff, fb, vx, vxx, node_free, curvature, ok, expected) = jax.lax.scan(
        node, (e.terminal_x, e.terminal_xx), data, reverse=True)
    return Gains(feedforward=ff, feedback=fb,
                 value_x=jnp.concatenate([vx, e.terminal_x[None]]),
                 value_xx=jnp.concatenate([vxx, e.terminal_xx[None]]),
                 free=node_free, curvature=curvature,
                 ok=jnp.all(ok) & jnp.all(jnp.isfinite(vxx)),
                 expected=None if expected is None else (jnp.sum(expected[0]),
                                                         jnp.sum(expected[1])))


def linear_rollout(expansion: Expansion, gains: Gains):
    """The step (δx (N+1, n), δr (N, k)) of the linear model under δr = k + K δx, from
    δx_0 = g_0, and its predicted change of cost ΔJ(α) = α d₁ + ½ α² d₂ for the step scaled
    by α (every term of the step is linear in α, the gaps included), in the model the
    gains minimise (with the dynamics' curvature for DDP)."""
    e = expansion
    hxx, hrr, hrx = gains.curvature

    def node(dx, data):
        fx, fr, ff, fb, gap = data
        dr = ff + fb @ dx
        return fx @ dx + fr @ dr + gap, (dx, dr)

    last, (dxs, drs) = jax.lax.scan(node, e.gaps[0], (e.fx, e.fr, gains.feedforward,
                                                      gains.feedback, e.gaps[1:]))
    d1 = (jnp.sum(e.lx * dxs) + jnp.sum(e.lr * drs) + e.terminal_x @ last)
    d2 = (jnp.einsum("ki,kij,kj->", dxs, e.lxx + hxx, dxs)
          + 2 * jnp.einsum("ki,kij,kj->", drs, e.lrx + hrx, dxs)
          + jnp.einsum("ki,kij,kj->", drs, e.lrr + hrr, drs) + last @ e.terminal_xx @ last)
    return jnp.concatenate([dxs, last[None]]), drs, d1, d2
