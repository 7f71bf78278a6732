"""Chaos map of the double pendulum: the time until either arm first flips over, for every
pair of starting angles (θ₁, θ₂) on a grid, released from rest; one `jaxdyn.simulate_batch`
call on whatever devices are present, in chunks under a memory bound. Writes chaos_map.png.

Run: python examples/chaos_map.py [--size 200] [--t1 20]

Two equal point masses on equal massless rods. An arm can only flip over (pass through the
upward vertical, |θ| > π) if the energy allows it: for equal masses and lengths, starts with
2 cos θ₁ + cos θ₂ > 1 never flip, so they are not simulated at all (a third of the grid).
On a CPU, expose every core as a device to use them all, e.g.
XLA_FLAGS=--xla_force_host_platform_device_count=2 python examples/chaos_map.py
"""

import argparse
import time

import diffrax
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxdyn  # noqa: E402

G = 9.81


def kinetic(q, qd, p):
    # two unit masses on unit rods, absolute angles from the downward vertical
    v1 = qd[0] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
    v2 = v1 + qd[1] * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
    return 0.5 * (v1 @ v1 + v2 @ v2)


def potential(q, p):
    return -G * (2 * jnp.cos(q[0]) + jnp.cos(q[1]))


pendulum = jaxdyn.Lagrangian(kinetic, potential)


def flip_times(theta1, theta2, t1, samples_per_second=20, progress=True):
    """First time |θ₁| or |θ₂| exceeds π (NaN: no flip before t1), for starts at rest."""
    ts = np.linspace(0.0, t1, int(t1 * samples_per_second) + 1)
    q0 = np.stack([theta1, theta2], axis=1)
    solution = jaxdyn.simulate_batch(
        pendulum, q0, np.zeros_like(q0), None, t1=t1, ts=ts, save="q",
        solver=diffrax.Tsit5(), rtol=1e-8, atol=1e-8, max_steps=2**20,
        max_bytes=64 * 2**20, order="cost", progress=progress)
    flipped = np.any(np.abs(np.asarray(solution.q)) > np.pi, axis=2)
    first = np.argmax(flipped, axis=1)
    return np.where(flipped.any(axis=1), ts[first], np.nan)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=200, help="grid points per angle")
    parser.add_argument("--t1", type=float, default=20.0, help="seconds simulated")
    parser.add_argument("--out", default="chaos_map.png")
    args = parser.parse_args()

    angles = np.linspace(-np.pi, np.pi, args.size)
    theta1, theta2 = (x.ravel() for x in np.meshgrid(angles, angles, indexing="xy"))
    can_flip = 2 * np.cos(theta1) + np.cos(theta2) <= 1  # energy allows reaching |θ| = π
    times = np.full(theta1.shape, np.nan)
    start = time.perf_counter()
    times[can_flip] = flip_times(theta1[can_flip], theta2[can_flip], args.t1)
    seconds = time.perf_counter() - start
    count = int(can_flip.sum())
    print(f"{count} of {theta1.size} starts simulated ({theta1.size - count} cannot flip), "
          f"{args.t1} s each, on {len(jax.devices())} device(s): {seconds:.1f} s, "
          f"{count / seconds:.0f} trajectories/s; "
          f"{np.isfinite(times).sum()} flip within {args.t1} s")

    figure, axes = plt.subplots(figsize=(7, 6))
    image = axes.imshow(np.log10(times.reshape(args.size, args.size)), origin="lower",
                        extent=(-np.pi, np.pi, -np.pi, np.pi), cmap="magma_r",
                        interpolation="nearest")
    figure.colorbar(image, label="log₁₀ time to first flip [s] (blank: none)")
    axes.set_xlabel("θ₁(0) [rad]")
    axes.set_ylabel("θ₂(0) [rad]")
    axes.set_title(f"Double pendulum from rest: time to first flip ({args.size}² starts)")
    figure.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
