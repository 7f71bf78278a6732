"""Identification at scale: how the time and the memory of one `jaxdyn.fit` grow with the
number of experiments and with the length of the records.

Run: python benchmarks/bench_fit_scale.py           (about 3 minutes on two cores)

Problem: the damped oscillator m ẍ + c ẋ + k x = 0 (m = 1 known; k = 4, c = 0.3 fitted from
k = 3, c = 0.5), E experiments released from different x0 ∈ [0.5, 1.5] at rest, each sampled
at 20 Hz with noise σ = 0.01 (weights 1/σ²), data from SciPy's `solve_ivp` (DOP853 at
1e-12). Default options (Levenberg–Marquardt with the forward-mode Jacobian, uncertainties).
Each configuration runs in its own process: "peak MiB" is that process's peak resident memory
(`ru_maxrss`) less its peak before the fit (after importing JAX and building the data), so
it holds the compiled programs, the Jacobian and the simulations' buffers.
"""

import json
import resource
import subprocess
import sys
import time

CONFIGS = [(16, 10.0), (64, 10.0), (256, 10.0), (1, 100.0), (1, 1000.0), (4, 1000.0)]


def child(count, horizon):
    import jax
    import numpy as np
    from scipy.integrate import solve_ivp

    jax.config.update("jax_enable_x64", True)
    import jaxdyn

    oscillator = jaxdyn.Lagrangian(lambda q, qd, p: 0.5 * p["m"] * qd[0] ** 2,
                                   lambda q, p: 0.5 * p["k"] * q[0] ** 2,
                                   dissipation=lambda q, qd, p: 0.5 * p["c"] * qd[0] ** 2)
    rng = np.random.default_rng(0)
    ts = np.linspace(0.0, horizon, int(round(20 * horizon)) + 1)
    experiments = []
    for x0 in rng.uniform(0.5, 1.5, count):
        x = solve_ivp(lambda t, y: [y[1], -4.0 * y[0] - 0.3 * y[1]], (0.0, horizon),
                      [x0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853").y[0]
        experiments.append(jaxdyn.Experiment(ts, x + 0.01 * rng.standard_normal(ts.size),
                                             q0=[x0], u0=[0.0], weights=1e4))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    result = jaxdyn.fit(oscillator, experiments, {"m": 1.0, "k": 3.0, "c": 0.5},
                        filter_spec={"m": False, "k": True, "c": True}, progress=False,
                        simulate_options={"max_steps": 1_000_000})
    first = time.perf_counter() - start
    start = time.perf_counter()
    jaxdyn.fit(oscillator, experiments, {"m": 1.0, "k": 3.0, "c": 0.5},
               filter_spec={"m": False, "k": True, "c": True}, progress=False,
               simulate_options={"max_steps": 1_000_000})
    warm = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"first": first, "warm": warm, "peak_mib": (peak - before) / 1024,
                      "samples": count * ts.size, "steps": result.num_steps,
                      "k": float(result.params["k"]), "k_error": float(result.standard_errors["k"]),
                      "explains": bool(result.explains_data)}))


def main():
    print(f"{'experiments':>11s} {'horizon s':>9s} {'samples':>8s} {'first s':>8s} {'warm s':>7s} "
          f"{'peak MiB':>9s} {'steps':>5s} {'|k - 4| / σ_k':>13s} {'explained':>9s}")
    for count, horizon in CONFIGS:
        out = subprocess.run([sys.executable, __file__, "--child", str(count), str(horizon)],
                             capture_output=True, text=True, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        print(f"{count:11d} {horizon:9.0f} {r['samples']:8d} {r['first']:8.2f} {r['warm']:7.2f} "
              f"{r['peak_mib']:9.0f} {r['steps']:5d} {abs(r['k'] - 4.0) / r['k_error']:13.2f} "
              f"{str(r['explains']):>9s}", flush=True)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(int(sys.argv[2]), float(sys.argv[3]))
    else:
        main()
