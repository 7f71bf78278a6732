"""Batches: `jax.vmap` over `simulate`, and `jaxdyn.simulate_batch` (sharding, padding,
chunks, failing members, gradients).

References: the closed form of the harmonic oscillator, x(t) = x₀ cos ωt + (v₀/ω) sin ωt with
ω = √(k/m); single simulations one member at a time; central differences; and, on 4 simulated
CPU devices and in two processes joined by `jax.distributed`, the same batch computed
unsharded in one process.
"""

import json
import os
import socket
import subprocess
import sys
import textwrap

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn
from compile_settings import default_environment
from helpers import central_difference

OSCILLATOR = jaxdyn.Lagrangian(kinetic=lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                               potential=lambda q, p: 0.5 * p["k"] * q @ q)
TS = np.linspace(0.0, 2.0, 9)
# At 1e-9 the step-size controller's decisions (the number of steps) do not hinge on round-off,
# so that batches laid out differently (sharded, chunked, padded) take the same steps. The closed
# form is met to 5e-8 (measured: Dopri8's interpolant at the save times); a wrong batch layout
# would be wrong by O(1).
OPTIONS = dict(t1=2.0, ts=TS, rtol=1e-9, atol=1e-9)
CLOSED_FORM_ATOL = 2e-7


def closed_form(x0, v0, k, m=1.0):
    omega = np.sqrt(np.asarray(k) / m)[..., None]
    t = TS[None, :]
    return (np.asarray(x0)[..., None] * np.cos(omega * t)
            + np.asarray(v0)[..., None] / omega * np.sin(omega * t))


@pytest.fixture(scope="module")
def members():
    rng = np.random.default_rng(0)
    size = 21  # uneven: padded to whole chunks of 8 members per device, then stripped
    return dict(x0=rng.uniform(-1, 1, size), v0=rng.uniform(-1, 1, size),
                k=rng.uniform(1.0, 9.0, size))


def test_vmap_over_states_parameters_and_both(members):
    x0, v0, k = members["x0"], members["v0"], members["k"]

    def one(x, v, k):
        return jaxdyn.simulate(OSCILLATOR, x[None], v[None], {"m": 1.0, "k": k}, **OPTIONS).q[:, 0]

    both = jax.jit(jax.vmap(one))(x0, v0, k)
    states = jax.jit(jax.vmap(one, in_axes=(0, 0, None)))(x0, v0, 4.0)
    params = jax.jit(jax.vmap(one, in_axes=(None, None, 0)))(0.5, -0.2, k)
    np.testing.assert_allclose(both, closed_form(x0, v0, k), atol=CLOSED_FORM_ATOL)
    np.testing.assert_allclose(states, closed_form(x0, v0, 4.0), atol=CLOSED_FORM_ATOL)
    np.testing.assert_allclose(params, closed_form(0.5, -0.2, k), atol=CLOSED_FORM_ATOL)


def test_vmapped_simulate_with_a_nan_member_and_throw_false(members):
    """jax.vmap over simulate(throw=False): a member with a NaN parameter gets its own code
    and NaN states; the others are the closed form."""
    x0, v0, k = members["x0"], members["v0"], members["k"].copy()
    k[3] = np.nan
    solution = jax.jit(jax.vmap(lambda x, v, k: jaxdyn.simulate(
        OSCILLATOR, x[None], v[None], {"m": 1.0, "k": k}, throw=False, **OPTIONS)))(x0, v0, k)
    bad = np.asarray(solution.result == jaxdyn.RESULTS.nonfinite_state_or_parameters)
    assert bad.tolist() == [i == 3 for i in range(21)]
    assert bool(np.all(np.isnan(solution.q[3])))
    good = np.arange(21) != 3
    np.testing.assert_allclose(solution.q[good, :, 0], closed_form(x0[good], v0[good], k[good]),
                               atol=CLOSED_FORM_ATOL)


def test_a_nonfinite_array_deep_in_the_parameters_gets_its_own_code():
    """The finite stand-in of simulate(throw=False) checks the parameters an entry of the
    dict at a time, the entry's arrays flattened into one vector: each array is put back in
    its shape and place (the oscillator reads a nested element), and an inf in any of them,
    used or not, gives its own code and NaN states."""
    nested = jaxdyn.Lagrangian(kinetic=lambda q, qd, p: 0.5 * p["body"]["m"] * qd @ qd,
                               potential=lambda q, p: 0.5 * p["spring"]["k"][1, 0] * q @ q)
    p = {"body": {"m": 1.0, "com": np.array([0.0, 0.1, 0.2])},
         "spring": {"k": np.array([[9.0], [4.0]]), "rest": 0.3}}
    solution = jaxdyn.simulate(nested, [0.5], [-0.2], p, throw=False, **OPTIONS)
    assert solution.result == jaxdyn.RESULTS.successful
    np.testing.assert_allclose(solution.q[:, 0], closed_form(0.5, -0.2, 4.0)[0],
                               atol=CLOSED_FORM_ATOL)
    p["body"]["com"] = np.array([0.0, np.inf, 0.2])
    solution = jaxdyn.simulate(nested, [0.5], [-0.2], p, throw=False, **OPTIONS)
    assert solution.result == jaxdyn.RESULTS.nonfinite_state_or_parameters
    assert bool(np.all(np.isnan(solution.q)))


@pytest.mark.usefixtures("xla_defaults")  # bit for bit in the programs users run
def test_simulate_batch_matches_the_closed_form_and_single_simulations(members):
    x0, v0, k = members["x0"][:, None], members["v0"][:, None], members["k"]
    p = {"m": 1.0, "k": k}
    solution = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params={"m": False,
                                                                            "k": True},
                                     **OPTIONS)
    assert solution.q.shape == (21, len(TS), 1) and solution.ts.shape == (21, len(TS))
    assert bool(jnp.all(solution.result == jaxdyn.RESULTS.successful))
    np.testing.assert_allclose(solution.q[..., 0], closed_form(x0[:, 0], v0[:, 0], k),
                               atol=CLOSED_FORM_ATOL)
    # Each device runs the program of jax.vmap(simulate): equal bit for bit on this system.
    vmapped = jax.jit(jax.vmap(lambda x, v, k: jaxdyn.simulate(
        OSCILLATOR, x, v, {"m": 1.0, "k": k}, **OPTIONS)))(x0, v0, k)
    single = jax.jit(lambda x, v, k: jaxdyn.simulate(OSCILLATOR, x, v, {"m": 1.0, "k": k},
                                                     **OPTIONS))
    for i in range(21):
        alone = single(x0[i], v0[i], k[i])
        for field in ("q", "u", "qd", "num_steps"):
            np.testing.assert_array_equal(getattr(solution, field)[i],
                                          getattr(vmapped, field)[i], err_msg=f"{field} {i}")
            # A single solve is another program (scalar rather than vector code, so other
            # round-off in the error estimate, which for this smooth motion is near round-off
            # itself): the same steps, and trajectories apart by the order of the tolerance
            # (measured up to 2e-9), where the closed form is 2e-7 away.
            np.testing.assert_allclose(getattr(solution, field)[i], getattr(alone, field),
                                       rtol=0, atol=1e-8, err_msg=f"{field}, member {i}")


def test_chunks_order_and_shared_parameters_agree(members, capsys):
    x0, v0 = members["x0"][:, None], members["v0"][:, None]
    whole = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": 4.0}, progress=True,
                                  **OPTIONS)
    assert "1/1" in capsys.readouterr().err  # one chunk: the bar completes too
    # shared parameters against the same values given per member
    per_member = {"m": np.ones(21), "k": np.full(21, 4.0)}
    batched = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, per_member, batched_params=True,
                                    **OPTIONS)
    np.testing.assert_allclose(batched.q, whole.q, rtol=0, atol=1e-12)
    # three chunks of 8 (the last padded), in host memory; the progress bar counts them
    chunked = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": 4.0}, chunk_size=8,
                                    progress=True, **OPTIONS)
    assert "3/3" in capsys.readouterr().err
    assert isinstance(chunked.q, np.ndarray) and chunked.q.shape == whole.q.shape
    np.testing.assert_allclose(chunked.q, whole.q, rtol=0, atol=1e-12)
    # a byte bound: one member's results are 9 save times × (q, u, qd, ts) + the statistics;
    # room for 17 members is rounded down to 16 (whole vectors of 8): two chunks
    per_member = chunked.q[0].nbytes * 3 + chunked.ts[0].nbytes + 4 * 8 + 2 * 8
    by_bytes = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": 4.0},
                                     max_bytes=17 * per_member, progress=True, **OPTIONS)
    assert "2/2" in capsys.readouterr().err
    np.testing.assert_allclose(by_bytes.q, whole.q, rtol=0, atol=1e-12)
    # members run in order of their cost, returned in the order given
    ordered = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": 4.0}, chunk_size=8,
                                    order="cost", **OPTIONS)
    np.testing.assert_allclose(ordered.q, whole.q, rtol=0, atol=1e-12)
    # one shared initial state, batched parameters
    sweep = jaxdyn.simulate_batch(OSCILLATOR, [0.5], [-0.2], {"m": 1.0, "k": members["k"]},
                                  batched_params={"m": False, "k": True}, **OPTIONS)
    np.testing.assert_allclose(sweep.q[..., 0], closed_form(0.5, -0.2, members["k"]),
                               atol=CLOSED_FORM_ATOL)


def test_gradient_through_a_batch_matches_finite_differences(members):
    x0, v0 = members["x0"][:, None], members["v0"][:, None]

    def loss(k):
        solution = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": k}, **OPTIONS)
        return jnp.sum(solution.q[:, -1, 0] ** 2)

    gradient = jax.grad(loss)(4.0)
    np.testing.assert_allclose(gradient, central_difference(loss, 4.0, 1e-5), rtol=1e-6)
    # and the closed form's own derivative: d/dk Σ x(T)²
    exact = central_difference(lambda k: np.sum(closed_form(x0[:, 0], v0[:, 0], k)[:, -1] ** 2),
                               4.0, 1e-6)
    np.testing.assert_allclose(gradient, exact, rtol=1e-6)


def test_one_failing_member_does_not_sink_the_batch(members):
    x0, v0 = members["x0"][:, None], members["v0"][:, None]
    k = members["k"].copy()
    m = np.ones(21)
    k[4] = np.nan  # a non-finite parameter
    m[9] = 0.0  # a singular mass matrix
    p = {"m": m, "k": k}
    solution = jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params=True, throw=False,
                                     **OPTIONS)
    assert (solution.result == jaxdyn.RESULTS.nonfinite_state_or_parameters)[4]
    assert (solution.result == jaxdyn.RESULTS.singular_mass_matrix)[9]
    assert bool(np.all(np.isnan(solution.q[4])))
    good = np.setdiff1d(np.arange(21), [4, 9])
    assert bool(jnp.all((solution.result == jaxdyn.RESULTS.successful)[good]))
    np.testing.assert_allclose(solution.q[good, :, 0], closed_form(x0[good, 0], v0[good, 0],
                                                                    k[good]), atol=CLOSED_FORM_ATOL)
    with pytest.raises(RuntimeError, match=r"(?s)Member 4 of the batch of 21 failed.*"
                       r"p\['k'\] = nan.*p\['k'\] contains NaN or inf"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params=True, **OPTIONS)
    # members run in order of cost: the error still gives the index as given
    with pytest.raises(RuntimeError, match=r"Member 4 of the batch of 21 failed"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params=True, order="cost",
                              **OPTIONS)
    p["k"][4] = 4.0
    with pytest.raises(RuntimeError, match=r"(?s)Member 9 of the batch of 21 failed.*"
                       r"p\['m'\] = 0.0.*mass matrix is singular.*It happened at t = "):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params=True, **OPTIONS)
    # inside a jit: the first failing member's index and initial state
    staged = jax.jit(lambda p: jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p,
                                                     batched_params=True, **OPTIONS).q)
    with pytest.raises(Exception, match=r"(?s)mass matrix is singular.*member = 9, q0 = "):
        jax.block_until_ready(staged(p))


def test_errors_name_the_problem(members):
    x0, v0 = members["x0"][:, None], members["v0"][:, None]
    p = {"m": 1.0, "k": 4.0}
    with pytest.raises(ValueError, match=r"leading axes disagree: q0 has 21, u0 has 12"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0[:12], p, **OPTIONS)
    with pytest.raises(ValueError, match=r"q0 has 21, u0 has 21, p\['k'\] has 5"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, {"m": 1.0, "k": np.ones(5)},
                              batched_params={"m": False, "k": True}, **OPTIONS)
    with pytest.raises(ValueError, match="Nothing is batched"):
        jaxdyn.simulate_batch(OSCILLATOR, [0.1], [0.0], p, **OPTIONS)
    with pytest.raises(ValueError, match=r"p\['k'\] is batched but is a scalar"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, batched_params=True, **OPTIONS)
    with pytest.raises(ValueError, match=r"q0 must have shape \(B, n\)"):
        jaxdyn.simulate_batch(OSCILLATOR, x0[None], v0, p, **OPTIONS)
    with pytest.raises(ValueError, match="unknown keyword.*'rtl'"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, t1=1.0, rtl=1e-6)
    with pytest.raises(ValueError, match="holds less than 8 member"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, max_bytes=10, **OPTIONS)
    with pytest.raises(ValueError, match="order must be"):
        jaxdyn.simulate_batch(OSCILLATOR, x0, v0, p, order="fastest", **OPTIONS)


# -- several devices, several processes ------------------------------------------------------

_SETUP = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
{extra}
import numpy as np, jaxdyn
oscillator = jaxdyn.Lagrangian(kinetic=lambda q, qd, p: 0.5 * p["m"] * qd @ qd,
                               potential=lambda q, p: 0.5 * p["k"] * q @ q)
rng = np.random.default_rng(0)
x0, v0, k = rng.uniform(-1, 1, (37, 1)), rng.uniform(-1, 1, (37, 1)), rng.uniform(1, 9, 37)
# The reference: one vmap on one device over the members padded to 40 (whole SIMD vectors).
pad = np.arange(40) % 37
p, spec = {{"m": 1.0, "k": k}}, {{"m": False, "k": True}}
options = dict(t1=2.0, ts=np.linspace(0.0, 2.0, 9), rtol=1e-9, atol=1e-9)
def run(**kwargs):
    return np.asarray(jaxdyn.simulate_batch(oscillator, x0, v0, p, batched_params=spec,
                                            **options, **kwargs).q)
unsharded = np.asarray(jax.jit(jax.vmap(lambda x, v, k: jaxdyn.simulate(
    oscillator, x, v, {{"m": 1.0, "k": k}}, **options).q))(x0[pad], v0[pad], k[pad]))[:37]
"""


def _python(script, env=None, timeout=300):
    return subprocess.Popen([sys.executable, "-c", script], env=default_environment(env),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(process, timeout=300):
    out, err = process.communicate(timeout=timeout)
    assert process.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


# Slow (31 s at XLA's defaults): the default run shards over two processes
# (test_two_processes_with_jax_distributed_equal_one).
@pytest.mark.slow
def test_sharded_over_four_cpu_devices_equals_unsharded():
    """On 4 simulated CPU devices (in a subprocess, so the rest of the suite keeps one): 37
    members padded to 64 (16 per device), ordered by cost, and on two of the four devices in
    three chunks of 16, each equal to the unsharded vmap; a chaotic double pendulum, where
    a difference in round-off grows with the motion, equal to round-off so amplified; and
    `fit_batch` of three systems sharded over the four devices, each at its own truth."""
    script = _SETUP.format(extra="") + textwrap.dedent("""
        assert len(jax.devices()) == 4
        out = {"devices": len(jax.devices())}
        for name, kwargs in {"whole": {}, "by cost": {"order": "cost"}}.items():
            out[name] = float(np.max(np.abs(run(**kwargs) - unsharded)))
        two = jaxdyn.simulate_batch(oscillator, x0, v0, p, batched_params=spec,
                                    devices=jax.devices()[:2], chunk_size=16, **options)
        out["two of four"] = float(np.max(np.abs(np.asarray(two.q) - unsharded)))
        import jax.numpy as jnp
        def kinetic(q, qd, p):
            v1 = qd[0] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
            v2 = v1 + qd[1] * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
            return 0.5 * (v1 @ v1 + v2 @ v2)
        pendulum = jaxdyn.Lagrangian(
            kinetic, lambda q, p: -9.81 * (2 * jnp.cos(q[0]) + jnp.cos(q[1])))
        angles = np.linspace(0.5, 2.5, 37)
        q0 = np.stack([angles, angles / 2], axis=1)
        chaotic = dict(t1=5.0, rtol=1e-8, atol=1e-8)
        q = jaxdyn.simulate_batch(pendulum, q0, 0 * q0, **chaotic).q
        reference = jax.jit(jax.vmap(lambda q0: jaxdyn.simulate(
            pendulum, q0, 0 * q0, **chaotic).q))(q0[pad])[:37]
        out["chaotic double pendulum"] = float(np.max(np.abs(np.asarray(q - reference))))
        # Fits of independent systems sharded the same way (3 padded to 4): each system's
        # stiffness from its own data (x = cos(√k t), noise 1e-3), within a few standard
        # errors (~2e-5 relative) of its truth — a member mixed up with another would not be.
        fit_ts = np.linspace(0.0, 5.0, 51)
        systems, guesses, stiffnesses = [], [], (2.0, 5.0, 8.0)
        for i, stiffness in enumerate(stiffnesses):
            x = np.cos(np.sqrt(stiffness) * fit_ts)
            x = x + 1e-3 * np.random.default_rng(i).standard_normal(51)
            systems.append(jaxdyn.Experiment(fit_ts, x, q0=[1.0], u0=[0.0], weights=1e6))
            guesses.append({"m": 1.0, "k": 0.8 * stiffness})
        fits = jaxdyn.fit_batch(oscillator, systems, guesses, filter_spec={"m": False, "k": True},
                                progress=False)
        out["fit_batch"] = max(abs(float(r.params["k"]) - k) / float(r.standard_errors["k"])
                               for r, k in zip(fits, stiffnesses))
        out["fit_batch converged"] = all(r.converged and r.explains_data for r in fits)
        print(json.dumps(out))
    """)
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    result = _result(_python(script, {"XLA_FLAGS": flags}))
    assert result.pop("devices") == 4
    assert result.pop("fit_batch converged")
    assert result.pop("fit_batch") < 5.0  # standard errors from the truth, at most
    # The chaotic member: the written-out Runge–Kutta stages are vectorised by XLA according
    # to the batch's shape, so an ulp of difference can appear and the motion amplifies it
    # (measured 2.2e-12 after 5 s); every other layout agrees bit for bit.
    chaotic = result.pop("chaotic double pendulum")
    assert chaotic <= 1e-9, chaotic
    for name, difference in result.items():
        assert difference <= 1e-12, (name, difference)


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_two_processes_with_jax_distributed_equal_one():
    """Two processes on this machine joined by `jax.distributed.initialize` (CPU, loopback,
    Gloo collectives), one device each: the batch is sharded over both, and each process
    receives the whole result, equal to the single-process unsharded vmap."""
    port = _free_port()
    processes = []
    for rank in range(2):
        extra = textwrap.dedent(f"""
            jax.config.update("jax_cpu_collectives_implementation", "gloo")
            jax.distributed.initialize(coordinator_address="localhost:{port}",
                                       num_processes=2, process_id={rank})
        """)
        script = _SETUP.format(extra=extra) + textwrap.dedent("""
            assert jax.process_count() == 2 and len(jax.devices()) == 2
            q = run()
            print(json.dumps({"difference": float(np.max(np.abs(q - unsharded))),
                              "shape": list(q.shape)}))
        """)
        processes.append(_python(script))
    for process in processes:
        result = _result(process)
        assert result["shape"] == [37, 9, 1]
        assert result["difference"] <= 1e-12


def test_float32_batch():
    """float32 as an explicit option: states in float32 give float32 results near the closed
    form (to what float32 and its default tolerance hold)."""
    x0 = np.linspace(-1, 1, 5, dtype=np.float32)[:, None]
    solution = jaxdyn.simulate_batch(OSCILLATOR, x0, np.zeros_like(x0),
                                     {"m": np.float32(1.0), "k": np.float32(4.0)}, t1=2.0,
                                     ts=TS.astype(np.float32), solver=diffrax.Tsit5())
    assert solution.q.dtype == jnp.float32
    np.testing.assert_allclose(solution.q[..., 0], closed_form(x0[:, 0], 0 * x0[:, 0], 4.0),
                               atol=1e-4)
