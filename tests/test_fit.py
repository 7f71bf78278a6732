"""`jaxdyn.fit`: parameter identification from measured trajectories.

The data come from SciPy's `solve_ivp` on equations derived by hand (the damped oscillator
m ẍ + c ẋ + k x = 0; the double pendulum of point masses with a torque at the first joint),
never from jaxdyn, with seeded Gaussian noise. Recovered parameters must lie within the noise's
justified tolerance of the truth and inside the reported confidence intervals.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from scipy.integrate import solve_ivp

import jaxdyn
from fit_systems import PENDULUM, PENDULUM_TRUTH, pendulum_data, positions
from helpers import central_difference

G = 9.81

# -- the damped oscillator ------------------------------------------------------------------

OSCILLATOR_TRUTH = {"m": 1.0, "k": 4.0, "c": 0.3}
OSCILLATOR_GUESS = {"m": 1.0, "k": 3.0, "c": 0.5}
SIGMA = 0.01


def _oscillator_T(q, qd, p):
    return 0.5 * p["m"] * qd[0] ** 2


def _oscillator_V(q, p):
    return 0.5 * p["k"] * q[0] ** 2


def _oscillator_D(q, qd, p):
    return 0.5 * p["c"] * qd[0] ** 2


OSCILLATOR = jaxdyn.Lagrangian(kinetic=_oscillator_T, potential=_oscillator_V,
                               dissipation=_oscillator_D)
OSCILLATOR_TRAINED = {"m": False, "k": True, "c": True}


def oscillator_experiment(x0=1.0, v0=0.0, num=201, seed=0):
    m, k, c = (OSCILLATOR_TRUTH[key] for key in ("m", "k", "c"))
    ts = np.linspace(0.0, 10.0, num)
    solution = solve_ivp(lambda t, y: [y[1], -(k * y[0] + c * y[1]) / m], (0.0, 10.0),
                         [x0, v0], t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853")
    noisy = solution.y[0] + SIGMA * np.random.default_rng(seed).standard_normal(num)
    return jaxdyn.Experiment(ts, noisy, q0=[x0], u0=[v0], weights=1 / SIGMA**2)


def fit_oscillator(experiment, **kwargs):
    return jaxdyn.fit(OSCILLATOR, experiment, OSCILLATOR_GUESS,
                      filter_spec=OSCILLATOR_TRAINED, **kwargs)


@pytest.fixture(scope="module")
def oscillator_fit():
    return fit_oscillator(oscillator_experiment())


def test_a_weakly_typed_guess_compiles_the_step_once(caplog):
    """A guess of weakly typed arrays (`jnp.asarray(3.0)`) comes back from the first step
    strongly typed, as does the optimiser's state: the fit's step is compiled once, not again
    for its own output (which cost a box's friction fit 13 of its 48 s)."""
    guess = {key: jnp.asarray(value) for key, value in OSCILLATOR_GUESS.items()}
    assert all(x.weak_type for x in guess.values())
    with jax.log_compiles(), caplog.at_level("WARNING"):
        result = jaxdyn.fit(OSCILLATOR, oscillator_experiment(num=51), guess,
                            filter_spec=OSCILLATOR_TRAINED, progress=False)
    assert result.converged
    steps = [r for r in caplog.records if "XLA compilation of jit(step)" in r.getMessage()]
    assert len(steps) == 1, [r.getMessage() for r in steps]


def test_oscillator_stiffness_and_damping_from_noisy_data(oscillator_fit):
    result = oscillator_fit
    assert result.converged
    errors = result.standard_errors
    for key in ("k", "c"):
        value = float(result.params[key])
        # Within three standard errors of the truth, and the truth inside the 95 % interval.
        assert abs(value - OSCILLATOR_TRUTH[key]) < 3 * float(errors[key]), key
        low, high = result.confidence_intervals(0.95)[f"p['{key}']"]
        assert low < OSCILLATOR_TRUTH[key] < high, key
        # 201 samples at 1 % noise pin k and c to well under 1 %.
        assert float(errors[key]) < 0.01 * OSCILLATOR_TRUTH[key]
    assert errors["m"] is None and float(result.params["m"]) == 1.0  # frozen
    # With weights 1/σ², the residual variance estimates 1 (χ² per degree of freedom).
    assert 0.8 < result.uncertainty.residual_variance < 1.2
    assert result.uncertainty.degrees_of_freedom == 201 - 2
    assert not result.uncertainty.unidentifiable
    correlation = result.uncertainty.correlation
    np.testing.assert_allclose(np.diag(correlation), 1.0, rtol=1e-12)
    assert result.loss_history[-1] <= result.loss_history[0]
    assert result.predictions[0].shape == (201, 1)
    # The noise estimated from the data alone (weighted: σ = 1) and the residuals agree.
    assert result.explains_data
    assert 0.8 < result.noise_variance < 1.2
    assert 0.8 < result.residual_variance / result.noise_variance < 1.25
    assert "explained by the model" in result.summary()


def test_a_model_missing_its_damping_reports_that_it_does_not_explain_the_data():
    """Data of the damped oscillator fitted with an undamped model: the optimiser converges,
    to the best undamped motion, and the fit says that its residuals are not noise."""
    undamped = jaxdyn.Lagrangian(kinetic=_oscillator_T, potential=_oscillator_V)
    with pytest.warns(jaxdyn.LackOfFitWarning, match="does not explain the data"):
        result = jaxdyn.fit(undamped, oscillator_experiment(), {"m": 1.0, "k": 3.0},
                            filter_spec={"m": False, "k": True})
    assert result.converged and result.explains_data is False
    assert result.residual_variance > 10 * result.noise_variance
    assert 0.8 < result.noise_variance < 1.2  # the noise estimate does not see the model
    assert "NOT explained" in result.summary()


ELASTIC_TRUTH = {"m": 0.9, "g": G, "k": 35.0, "l0": 1.1}


def _elastic_T(q, qd, p):
    r, _ = q
    return 0.5 * p["m"] * (qd[0] ** 2 + r**2 * qd[1] ** 2)


def _elastic_V(q, p):
    r, theta = q
    return -p["m"] * p["g"] * r * jnp.cos(theta) + 0.5 * p["k"] * (r - p["l0"]) ** 2


def _bob_x(t, q, u, p):
    """What the elastic pendulum's records observe: the bob's horizontal position r sin θ
    (one function for all tests, so that their fits share compiled programs)."""
    return q[:1] * jnp.sin(q[1:])


def elastic_experiments(sigma=1e-3):
    """Two experiments of 4 s of the elastic pendulum (polar coordinates r, θ from the
    downward vertical), only the bob's horizontal position r sin θ observed, from SciPy."""
    m, g, k, l0 = (ELASTIC_TRUTH[key] for key in ("m", "g", "k", "l0"))

    def rhs(t, y):
        r, theta, r_dot, theta_dot = y
        return [r_dot, theta_dot, r * theta_dot**2 + g * np.cos(theta) - k / m * (r - l0),
                -(2 * r_dot * theta_dot + g * np.sin(theta)) / r]

    rng = np.random.default_rng(5)
    experiments = []
    for q0 in ([1.3, 0.5], [1.0, -0.8]):
        ts = np.linspace(0.0, 4.0, 201)
        y = solve_ivp(rhs, (0.0, 4.0), [*q0, 0.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12,
                      method="DOP853").y
        x = y[0] * np.sin(y[1]) + sigma * rng.standard_normal(ts.size)
        experiments.append(jaxdyn.Experiment(ts, x[:, None], q0=q0, u0=[0.0, 0.0]))
    return experiments


def test_a_fit_stopped_in_a_local_minimum_says_so_and_continuation_finds_the_truth():
    """The elastic pendulum from k 2× and l₀ 0.8× the truth, initial states fitted too.
    Fitted directly (`globalisation=False`), the optimiser meets its tolerance in a local
    minimum (k ≈ 74, l₀ ≈ 1.5); the fit reports that the residuals are far above the noise
    estimated from the data (unweighted), and warns. By default the trapped fit is taken up
    again by horizon continuation, which ends at the truth (k, l₀ to the noise's accuracy)."""
    observe = _bob_x
    guess = {**ELASTIC_TRUTH, "k": 2.0 * ELASTIC_TRUTH["k"], "l0": 0.8 * ELASTIC_TRUTH["l0"]}
    trained = {"m": False, "g": False, "k": True, "l0": True}
    system, experiments = jaxdyn.Lagrangian(_elastic_T, _elastic_V), elastic_experiments()
    options = dict(filter_spec=trained, observe=observe, fit_initial_states=True,
                   uncertainty=False)
    with pytest.warns(jaxdyn.LackOfFitWarning, match="local minimum"):
        trapped = jaxdyn.fit(system, experiments, guess, globalisation=False, **options)
    assert trapped.converged and trapped.explains_data is False
    assert trapped.strategy == "direct"
    assert abs(float(trapped.params["k"]) - ELASTIC_TRUTH["k"]) > 1.0  # not at the truth
    # σ = 1e-3 estimated from the data alone, to 20 %.
    assert 0.8e-3 < np.sqrt(trapped.noise_variance) < 1.2e-3

    # No warning: the data are explained, also where the direct fit, replaced, ran out of
    # steps on its way down the valley.
    for max_steps in (200, trapped.num_steps - 1):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            found = jaxdyn.fit(system, experiments, guess, max_steps=max_steps, **options)
        assert found.strategy == "horizon continuation" and found.explains_data
        np.testing.assert_allclose(float(found.params["k"]), ELASTIC_TRUTH["k"], rtol=2e-3)
        np.testing.assert_allclose(float(found.params["l0"]), ELASTIC_TRUTH["l0"], rtol=2e-3)
        assert found.loss < 1e-3 * trapped.loss
    # A direct fit that runs out of steps and is returned still says so.
    with pytest.warns(RuntimeWarning, match="did not converge in max_steps = 3 steps"):
        jaxdyn.fit(system, experiments, guess, globalisation=False, max_steps=3, **options)


def test_multiple_shooting_with_partial_observations_from_a_short_horizon_fit():
    """Multiple shooting when the data observe only the bob's horizontal position (the state
    (r, θ, ṙ, θ̇) cannot be read from it): with horizon continuation the ten segments' nodes
    start on a simulation at the optimum of the short horizons, and the fit from the trapped
    guess (k 2×, l₀ 0.8×) ends at the truth with the segments joined into one solution."""
    observe = _bob_x
    guess = {**ELASTIC_TRUTH, "k": 2.0 * ELASTIC_TRUTH["k"], "l0": 0.8 * ELASTIC_TRUTH["l0"]}
    trained = {"m": False, "g": False, "k": True, "l0": True}
    system, experiments = jaxdyn.Lagrangian(_elastic_T, _elastic_V), elastic_experiments()
    found = jaxdyn.fit(system, experiments, guess, filter_spec=trained, observe=observe,
                       fit_initial_states=True, uncertainty=False,
                       shooting=jaxdyn.MultipleShooting(10),
                       globalisation=jaxdyn.HorizonContinuation())
    assert found.strategy == "horizon continuation"
    assert found.converged and found.explains_data and found.lack_of_fit is None
    np.testing.assert_allclose(float(found.params["k"]), ELASTIC_TRUTH["k"], rtol=2e-3)
    np.testing.assert_allclose(float(found.params["l0"]), ELASTIC_TRUTH["l0"], rtol=2e-3)
    # One solution: the fitted initial states, simulated whole, give the fitted predictions.
    for experiment, (q0, u0), predicted in zip(experiments, found.initial_states,
                                               found.predictions):
        whole = jaxdyn.simulate(system, q0, u0, found.params, t1=float(experiment.ts[-1]),
                                ts=experiment.ts, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(whole.q[:, :1] * jnp.sin(whole.q[:, 1:]), predicted,
                                   atol=1e-4)


def test_multi_start_equals_the_best_of_the_separate_fits():
    """Six starting points around the trapped guess of the elastic pendulum, fitted at once
    (one vmapped computation, `jaxdyn.MultiStart`) and one by one: the multi-start result is
    the best separate fit (the one that reaches the truth), to round-off."""
    observe = _bob_x
    guess = {**ELASTIC_TRUTH, "k": 2.0 * ELASTIC_TRUTH["k"], "l0": 0.8 * ELASTIC_TRUTH["l0"]}
    trained = {"m": False, "g": False, "k": True, "l0": True}
    system, experiments = jaxdyn.Lagrangian(_elastic_T, _elastic_V), elastic_experiments()
    options = dict(filter_spec=trained, observe=observe, fit_initial_states=True,
                   uncertainty=False, max_steps=60)
    starts = jaxdyn.MultiStart(6, spread=3.0, seed=1)
    points = starts.starting_points(guess, trained)
    assert len(points) == 6 and points[0] == guess
    with warnings.catch_warnings():  # the separate fits that end trapped or crawl warn
        warnings.simplefilter("ignore")
        separate = [jaxdyn.fit(system, experiments, point, globalisation=False, **options)
                    for point in points]
    best = min(separate, key=lambda result: result.loss)
    together = jaxdyn.fit(system, experiments, guess, globalisation=starts, **options)
    assert together.strategy == "multi-start (6)"
    assert together.converged and together.explains_data
    np.testing.assert_allclose(together.loss, best.loss, rtol=1e-9)
    for key in ("k", "l0"):
        np.testing.assert_allclose(float(together.params[key]), float(best.params[key]),
                                   rtol=1e-7)
    np.testing.assert_allclose(float(together.params["k"]), ELASTIC_TRUTH["k"], rtol=2e-3)
    assert sum(result.loss < 1.01 * best.loss for result in separate) == 1  # one start found it


def test_a_batch_of_systems_equals_their_separate_fits():
    """Four oscillators of one model, each with its own stiffness and damping (data from
    SciPy, its own noise), fitted at once by `fit_batch`: each result is the system's own
    `fit` to round-off and holds that system's truth within its confidence intervals; one
    system's guess whose simulation fails is named."""
    truths = [(4.0, 0.3), (2.0, 0.5), (6.0, 0.2), (3.0, 0.8)]
    systems, guesses = [], []
    for i, (k, c) in enumerate(truths):
        ts = np.linspace(0.0, 10.0, 101)
        y = solve_ivp(lambda t, y, k=k, c=c: [y[1], -k * y[0] - c * y[1]], (0.0, 10.0),
                      [1.0, 0.0], t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853").y[0]
        noisy = y + SIGMA * np.random.default_rng(10 + i).standard_normal(ts.size)
        systems.append(jaxdyn.Experiment(ts, noisy, q0=[1.0], u0=[0.0], weights=SIGMA**-2))
        guesses.append({"m": 1.0, "k": 0.8 * k, "c": 1.5 * c})
    options = dict(filter_spec=OSCILLATOR_TRAINED, progress=False)
    batch = jaxdyn.fit_batch(OSCILLATOR, systems, guesses, **options)
    for result, experiment, guess, (k, c) in zip(batch, systems, guesses, truths):
        alone = jaxdyn.fit(OSCILLATOR, experiment, guess, **options)
        assert result.converged and result.explains_data
        # Vectorised arithmetic rounds differently: at the optimum, trial steps whose
        # predicted reduction is round-off are rejected a different number of times before
        # the relative-change test is met; the steps that moved the iterate agree.
        assert abs(result.num_accepted_steps - alone.num_accepted_steps) <= 1
        for key, truth in (("k", k), ("c", c)):
            np.testing.assert_allclose(float(result.params[key]), float(alone.params[key]),
                                       rtol=1e-9)
            np.testing.assert_allclose(float(result.standard_errors[key]),
                                       float(alone.standard_errors[key]), rtol=1e-6)
            low, high = result.confidence_intervals(0.999)[f"p['{key}']"]
            assert low < truth < high, key
        np.testing.assert_allclose(result.loss, alone.loss, rtol=1e-9)

    with pytest.raises(ValueError, match="one entry per system: got 4 and 3"):
        jaxdyn.fit_batch(OSCILLATOR, systems, guesses[:3], **options)
    with pytest.raises(ValueError, match="System 1's experiments or parameters differ"):
        jaxdyn.fit_batch(OSCILLATOR, [systems[0], oscillator_experiment(num=51)],
                         guesses[:2], **options)
    failing = {"m": 0.0, "k": 3.0, "c": 0.5}  # a massless system: M singular, no motion
    with pytest.raises(ValueError, match=r"Systems \[1\]: The simulations at the initial"):
        jaxdyn.fit_batch(OSCILLATOR, systems[:2], [guesses[0], failing], **options)


def test_horizon_continuation_checks_its_fractions():
    with pytest.raises(ValueError, match="increasing numbers between 0 and 1"):
        jaxdyn.HorizonContinuation(fractions=(0.5, 0.25))
    with pytest.raises(ValueError, match="increasing numbers between 0 and 1"):
        jaxdyn.HorizonContinuation(fractions=(0.5, 1.0))
    experiment = oscillator_experiment()
    assert jaxdyn.HorizonContinuation(min_samples=16).samples(experiment, 0.125) == 26
    assert jaxdyn.HorizonContinuation().samples(experiment, 0.01) == 16
    assert jaxdyn.HorizonContinuation(min_samples=300).samples(experiment, 0.5) == 201
    with pytest.raises(ValueError, match="count must be a positive integer"):
        jaxdyn.MultiStart(0)
    with pytest.raises(ValueError, match="takes no callback or checkpoint"):
        jaxdyn.fit(OSCILLATOR, experiment, OSCILLATOR_GUESS, globalisation=jaxdyn.MultiStart(),
                   callback=lambda *args: False)
    with pytest.raises(ValueError, match="globalisation must be None, False, a"):
        jaxdyn.fit(OSCILLATOR, experiment, OSCILLATOR_GUESS, globalisation="multi-start")


def test_a_continuation_stage_fits_the_first_samples_alone():
    """A stage of a horizon continuation keeps the record's shapes (its later samples at its
    last time, weight 0, so that all stages share one compiled program): it must end where a
    fit of the record cut after those samples ends, with the residual count of the cut."""
    from jaxdyn._fit.steps import _fit_directly

    experiment = oscillator_experiment()
    cut = jaxdyn.Experiment(experiment.ts[:51], experiment.observations[:51], [1.0], [0.0],
                            weights=experiment.weights[:51])
    options = dict(filter_spec=OSCILLATOR_TRAINED, progress=False)
    alone = jaxdyn.fit(OSCILLATOR, cut, OSCILLATOR_GUESS, globalisation=False, **options)
    defaults = dict(parametrisation=None, observe=None, fit_initial_states=False,
                    shooting=None, optimiser=None, max_steps=200, rtol=1e-8, atol=1e-8,
                    adjoint=None, simulate_options=None, uncertainty=True,
                    identifiability_tolerance=None, callback=None, checkpoint=None,
                    checkpoint_every=1)
    stage = _fit_directly(OSCILLATOR, [experiment], OSCILLATOR_GUESS, horizons=[51],
                          **{**defaults, **options})
    for key in ("k", "c"):
        np.testing.assert_allclose(float(stage.params[key]), float(alone.params[key]),
                                   rtol=1e-10)
    np.testing.assert_allclose(stage.loss, alone.loss, rtol=1e-10)
    assert stage.uncertainty.degrees_of_freedom == alone.uncertainty.degrees_of_freedom == 49
    # The stage simulated only its horizon: its predictions stop at the cut's last time.
    np.testing.assert_allclose(stage.predictions[0][51:], stage.predictions[0][50:51].repeat(
        150, axis=0))


def test_standard_errors_match_the_spread_over_noise_realisations(oscillator_fit):
    """The Gauss–Newton standard error is the spread of the estimate over repeated noise:
    refit 12 noise realisations (same compiled fit) and compare."""
    estimates = np.array([
        [float(fit_oscillator(oscillator_experiment(seed=seed), uncertainty=False)
               .params[key]) for key in ("k", "c")] for seed in range(1, 13)])
    spread = estimates.std(axis=0, ddof=1)
    predicted = np.array([float(oscillator_fit.standard_errors[key]) for key in ("k", "c")])
    # 12 samples estimate a standard deviation to about ±20 % (1σ): allow a factor 1.8.
    assert np.all(spread < 1.8 * predicted) and np.all(spread > predicted / 1.8), (
        spread, predicted)


def test_simulate_options_reach_the_simulations(oscillator_fit):
    """Options for the simulations inside the fit, the step budget among them (a Python
    int that `simulate` needs when it compiles): the same tolerances give the same fit."""
    result = fit_oscillator(oscillator_experiment(), uncertainty=False, simulate_options={
        "max_steps": 10_000, "rtol": 1e-8, "atol": 1e-8})
    for key in ("k", "c"):
        np.testing.assert_allclose(float(result.params[key]),
                                   float(oscillator_fit.params[key]), rtol=1e-12)


def test_long_records_are_simulated_one_after_another(monkeypatch, oscillator_fit):
    """Records longer than `LONG_RECORD` samples are simulated by `lax.map` rather than
    `vmap` (whose saving cost grows as steps × samples): the same fit."""
    monkeypatch.setattr(jaxdyn._fit.residuals, "LONG_RECORD", 100)
    # Another observation function (the default's equal) makes a new program, traced with
    # the patched limit, rather than the fixture's compiled one.
    result = fit_oscillator(oscillator_experiment(), observe=lambda t, q, u, p: q)
    # The two programs round differently (XLA compiles the loop over records as one function,
    # the vmapped solves as kernels): equal to 1e-10, a hundredth of the fit's tolerance.
    for key in ("k", "c"):
        np.testing.assert_allclose(float(result.params[key]),
                                   float(oscillator_fit.params[key]), rtol=1e-10)
        np.testing.assert_allclose(float(result.standard_errors[key]),
                                   float(oscillator_fit.standard_errors[key]), rtol=1e-9)


def test_resumed_fit_ends_at_the_same_parameters(tmp_path, oscillator_fit):
    path = tmp_path / "fit.eqx"
    experiment = oscillator_experiment()

    def interrupt(step, params, loss):
        if step == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_oscillator(experiment, checkpoint=path, callback=interrupt)
    assert path.exists()
    seen = []
    resumed = fit_oscillator(experiment, checkpoint=path,
                             callback=lambda step, params, loss: seen.append(step))
    assert seen[0] == 6  # it went on from the checkpoint, not from the start
    for key in ("k", "c"):
        assert float(resumed.params[key]) == float(oscillator_fit.params[key])
    assert resumed.num_steps == oscillator_fit.num_steps
    np.testing.assert_array_equal(resumed.loss_history, oscillator_fit.loss_history)


@pytest.mark.slow
def test_multiple_shooting_nodes_started_on_a_simulation(oscillator_fit):
    """Four segments whose nodes start on a simulation at the initial guess: with a
    continuity weight of 1e4 (gaps of 1e-4 σ cost as much as one σ of observation error) the
    segments join at the optimum, which is then the single-shooting one."""
    shooting = jaxdyn.MultipleShooting(4, continuity_weight=1e4)
    result = fit_oscillator(oscillator_experiment(), shooting=shooting)
    assert result.converged
    for key in ("k", "c"):
        error = float(oscillator_fit.standard_errors[key])
        assert abs(float(result.params[key]) - float(oscillator_fit.params[key])) < 0.05 * error
    assert abs(result.loss - oscillator_fit.loss) < 1e-3 * oscillator_fit.loss


def test_callback_stops_the_fit():
    result = fit_oscillator(oscillator_experiment(), uncertainty=False,
                            callback=lambda step, params, loss: step == 3)
    assert result.num_steps == 3 and not result.converged


@pytest.mark.slow
def test_optax_optimiser_and_reverse_mode():
    """Any optax optimiser, through optimistix.OptaxMinimiser, with a reverse-mode gradient."""
    # optax's bias correction raises a Python float to an int32 power, which the suite's
    # strict dtype promotion refuses: optax is run under standard promotion, as users run it.
    with warnings.catch_warnings(), jax.numpy_dtype_promotion("standard"):
        warnings.simplefilter("ignore", RuntimeWarning)  # Adam stops at max_steps
        result = fit_oscillator(oscillator_experiment(), optimiser=optax.adam(0.05),
                                max_steps=300, uncertainty=False)
    assert result.loss_history[-1] < 1e-3 * result.loss_history[0]
    assert abs(float(result.params["k"]) - 4.0) < 0.02


@pytest.mark.slow
def test_minimiser_whose_trial_step_overflows_a_parameter():
    """BFGS's first trial step is the raw gradient (order 1e5 here): exp of it overflows the
    stiffness. That trial point must be rejected by the line search (infinite residuals), not
    stop the fit."""
    result = fit_oscillator(oscillator_experiment(), uncertainty=False,
                            optimiser=optx.BFGS(rtol=1e-8, atol=1e-8))
    assert result.converged
    for key in ("k", "c"):
        assert abs(float(result.params[key]) - OSCILLATOR_TRUTH[key]) < 0.01


@pytest.mark.slow
def test_fit_gradient_matches_finite_differences(oscillator_fit):
    """The derivatives the optimisers use — the forward-mode Jacobian (Gauss–Newton) and the
    reverse-mode gradient (optax) of ½‖r‖² through the parametrisation and the solve —
    against central differences in the latent variables."""
    from jaxdyn._fit.uncertainty import flatten_latent

    problem = oscillator_fit.problem
    latent = {**oscillator_fit.latent,
              "params": [jnp.log(jnp.array(3.5)), jnp.log(jnp.array(0.4))]}
    flat, unravel = flatten_latent(latent)

    def loss(problem, f):
        return 0.5 * jnp.sum(problem.residuals(unravel(f))[0] ** 2)

    reverse = eqx.tree_at(lambda p: p.adjoint, problem, diffrax.RecursiveCheckpointAdjoint())
    forward = eqx.tree_at(lambda p: p.adjoint, problem, diffrax.ForwardMode())
    gradient = jax.grad(lambda f: loss(reverse, f))(flat)
    residuals = lambda f: forward.residuals(unravel(f))[0]  # noqa: E731
    gauss_newton = jax.jacfwd(residuals)(flat).T @ residuals(flat)
    difference = central_difference(jax.jit(lambda f: loss(reverse, f)), np.asarray(flat),
                                    step=1e-6)
    np.testing.assert_allclose(gradient, difference, rtol=1e-5)
    np.testing.assert_allclose(gauss_newton, gradient, rtol=1e-9)


def test_what_the_optimiser_is_given_has_the_traced_shapes_and_derivatives():
    """The residual functions a fit hands the optimiser, on two groups of experiments with
    fitted initial states and multiple shooting: the shapes the optimiser's state is built
    from without tracing the simulations equal those JAX traces (and in a float32 fit); the
    forward-mode derivative of the residuals and of the predictions (the auxiliary output
    that the fit's result keeps) equals JAX's own differentiation of the simulations and a
    central difference along a direction."""
    from jax.flatten_util import ravel_pytree

    from jaxdyn._fit import residuals
    from jaxdyn._fit.problem import _setup_with

    options = dict(filter_spec=OSCILLATOR_TRAINED, parametrisation=None, observe=None,
                   fit_initial_states=True, shooting=jaxdyn.MultipleShooting(4),
                   optimiser=None, rtol=1e-8, atol=1e-8, adjoint=None,
                   simulate_options={"rtol": 1e-12, "atol": 1e-12},
                   identifiability_tolerance=None)
    experiments = [oscillator_experiment(num=41), oscillator_experiment(x0=0.5, num=61, seed=1)]
    float32 = {key: jnp.asarray(value, jnp.float32) for key, value in OSCILLATOR_GUESS.items()}
    for guess, shooting in ((OSCILLATOR_GUESS, options["shooting"]), (float32, None)):
        problem, latent, *_ = _setup_with(OSCILLATOR, experiments, guess,
                                          {**options, "shooting": shooting})
        for fn in (residuals.least_squares_residuals, residuals.least_squares_residuals_forward,
                   residuals.scalar_loss):
            assert residuals.output_structure(fn, problem, latent) == eqx.filter_eval_shape(
                fn, latent, problem), (fn.__name__, shooting)

    problem, latent, *_ = _setup_with(OSCILLATOR, experiments, OSCILLATOR_GUESS, options)
    flat, unravel = ravel_pytree(latent)
    direction = jnp.asarray(np.random.default_rng(2).standard_normal(flat.size))

    def forward(f):  # r and the predictions, through the residual function's own derivative
        r, (_, predictions) = residuals.least_squares_residuals_forward(unravel(f), problem)
        return jnp.concatenate([r, *[x.ravel() for x in predictions]])

    def by_jax(f):  # the same values, differentiated by JAX through the simulations
        predictions, r, _ = problem.evaluate(unravel(f))
        return jnp.concatenate([r, *[x.ravel() for x in predictions]])

    @jax.jit
    def both(f):
        return jax.jvp(forward, (f,), (direction,)), jax.jvp(by_jax, (f,), (direction,))

    (value, derivative), (value_by_jax, derivative_by_jax) = both(flat)
    np.testing.assert_allclose(value, value_by_jax, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(derivative, derivative_by_jax, rtol=1e-10, atol=1e-10)
    h = 1e-5
    difference = (both(flat + h * direction)[1][0] - both(flat - h * direction)[1][0]) / (2 * h)
    np.testing.assert_allclose(derivative, difference, rtol=1e-6, atol=1e-7)


def test_nan_gradient_stops_with_step_and_parameter():
    def V(q, p):
        # A stiffness correction √(c − 1) that vanishes at c = 1, where its derivative is
        # infinite: the Jacobian of the trajectory with respect to c is not finite.
        return 0.5 * (p["k"] + jnp.sqrt(p["offset"] - 1.0)) * q[0] ** 2

    system = jaxdyn.Lagrangian(kinetic=_oscillator_T, potential=V)
    experiment = oscillator_experiment(num=21)
    with pytest.raises(FloatingPointError, match=r"step 1 .*p\['offset'\]"):
        jaxdyn.fit(system, experiment, {"m": 1.0, "k": 3.0, "offset": 1.0},
                   filter_spec={"m": False, "k": True, "offset": True},
                   parametrisation={"m": None, "k": None, "offset": jaxdyn.Unconstrained()})


# -- the double pendulum --------------------------------------------------------------------


def test_double_pendulum_masses_and_lengths_from_several_experiments():
    """Three experiments (two of one length, simulated together under vmap, one longer),
    each driven by a known torque: the torque fixes the mass scale, so both masses and both
    lengths are identifiable from the noisy angles."""
    rng = np.random.default_rng(2)
    setups = [((0.5, -0.3), 41, 2.0, 1.5), ((-0.8, 0.4), 41, 1.0, 2.5), ((0.2, 0.9), 61, 3.0, 1.0)]
    experiments = []
    for q0, num, amplitude, frequency in setups:
        ts = np.linspace(0.0, 0.1 * (num - 1), num)
        states = pendulum_data(q0, ts, amplitude, frequency)
        noisy = states[:, :2] + SIGMA * rng.standard_normal((num, 2))
        experiments.append(jaxdyn.Experiment(ts, noisy, q0=q0, u0=[0.0, 0.0],
                                             inputs={"A": amplitude, "w": frequency},
                                             weights=1 / SIGMA**2))
    guess = {"m1": 1.3, "m2": 0.6, "l1": 0.8, "l2": 0.9}
    result = jaxdyn.fit(PENDULUM, experiments, guess)
    assert result.converged
    assert [p.shape for p in result.predictions] == [(41, 2), (41, 2), (61, 2)]
    intervals = result.confidence_intervals(0.99)
    for key, truth in PENDULUM_TRUTH.items():
        error = float(result.standard_errors[key])
        assert abs(float(result.params[key]) - truth) < 4 * error, key
        low, high = intervals[f"p['{key}']"]
        assert low < truth < high, key
        assert error < 0.05 * truth


def test_double_pendulum_from_a_guess_one_and_a_half_times_off():
    """Masses and lengths all 1.5× the truth, two torque-driven experiments of 8 s: the fit
    ends at the truth (within 1 % and four standard errors) and says the data are explained."""
    rng = np.random.default_rng(3)
    experiments = []
    for q0, amplitude, frequency in (((0.5, -0.3), 2.0, 1.5), ((-0.8, 0.4), 1.0, 2.5)):
        ts = np.linspace(0.0, 8.0, 161)
        noisy = (pendulum_data(q0, ts, amplitude, frequency)[:, :2]
                 + SIGMA * rng.standard_normal((ts.size, 2)))
        experiments.append(jaxdyn.Experiment(ts, noisy, q0=q0, u0=[0.0, 0.0],
                                             inputs={"A": amplitude, "w": frequency},
                                             weights=1 / SIGMA**2))
    guess = {key: 1.5 * value for key, value in PENDULUM_TRUTH.items()}
    result = jaxdyn.fit(PENDULUM, experiments, guess)
    assert result.converged and result.explains_data
    for key, truth in PENDULUM_TRUTH.items():
        value, error = float(result.params[key]), float(result.standard_errors[key])
        assert abs(value - truth) < min(4 * error, 0.01 * truth), key


def test_partial_observation_through_an_observation_function():
    """Only the horizontal position of the lower mass is measured (a marker seen by one
    camera axis), and the initial speeds are unknown: the lengths and initial speeds are
    fitted from it."""
    ts = np.linspace(0.0, 4.0, 81)
    states = pendulum_data((0.6, -0.4), ts)
    p_true = PENDULUM_TRUTH
    marker = (p_true["l1"] * np.sin(states[:, 0]) + p_true["l2"] * np.sin(states[:, 1]))
    noisy = marker + SIGMA * np.random.default_rng(3).standard_normal(ts.size)
    experiment = jaxdyn.Experiment(ts, noisy, q0=[0.6, -0.4], u0=[0.3, -0.2],
                                   inputs={"A": 0.0, "w": 1.0})

    def marker_x(t, q, u, p):
        return positions(q, p[0])[1][:1]

    guess = {**PENDULUM_TRUTH, "l1": 0.85, "l2": 0.8}
    result = jaxdyn.fit(PENDULUM, experiment, guess, observe=marker_x, fit_initial_states=True,
                        filter_spec={"m1": False, "m2": False, "l1": True, "l2": True})
    assert result.converged
    for key in ("l1", "l2"):
        error = float(result.standard_errors[key])
        assert abs(float(result.params[key]) - PENDULUM_TRUTH[key]) < 4 * error
        assert error < 0.01
    # The initial state is seen only through one noisy coordinate, the speeds least of all.
    q0, u0 = result.initial_states[0]
    np.testing.assert_allclose(q0, [0.6, -0.4], atol=0.02)
    np.testing.assert_allclose(u0, [0.0, 0.0], atol=0.15)


@pytest.mark.parametrize("dtype", [np.float64, pytest.param(np.float32, marks=pytest.mark.slow)])
def test_unidentifiable_combination_is_named(dtype):
    """Without an applied force, scaling both masses leaves the motion unchanged: only m₂/m₁
    is identifiable, and the report must say so by name — in float32 too, where round-off
    lifts the null singular value from 5e-16 to about 3e-7."""
    ts = np.linspace(0.0, 3.0, 61)
    states = pendulum_data((0.5, -0.3), ts)
    experiment = jaxdyn.Experiment(ts, states[:, :2], q0=[0.5, -0.3], u0=[0.0, 0.0],
                                   inputs={"A": 0.0, "w": 1.0})
    guess = {key: dtype(value) for key, value in
             {"m1": 1.2, "m2": 0.7, "l1": 1.0, "l2": 0.7}.items()}
    with pytest.warns(jaxdyn.IdentifiabilityWarning, match=r"p\[.m1.\] and p\[.m2.\] apart"):
        result = jaxdyn.fit(PENDULUM, experiment, guess,
                            filter_spec={"m1": True, "m2": True, "l1": False, "l2": False})
    report = result.uncertainty
    assert len(report.unidentifiable) == 1
    assert np.all(np.isinf(report.standard_errors))
    # The identifiable combination is recovered: the ratio.
    ratio = float(result.params["m2"] / result.params["m1"])
    assert abs(ratio - 0.8) < (1e-6 if dtype == np.float64 else 1e-5)


def test_float32_fit_keeps_its_precision_and_matches_float64(oscillator_fit):
    """float32 as an explicit option: float32 parameters make the whole fit float32 (data,
    simulations, optimiser). Its estimate must lie within 3σ of the truth, and agree with the
    float64 fit far inside the standard error, which the noise sets, not the precision
    (measured: 5e-7 relative)."""
    guess = {key: np.float32(value) for key, value in OSCILLATOR_GUESS.items()}
    result = jaxdyn.fit(OSCILLATOR, oscillator_experiment(), guess,
                        filter_spec=OSCILLATOR_TRAINED)
    assert result.converged
    for x in (*jax.tree_util.tree_leaves(result.params), *result.initial_states[0],
              result.predictions[0]):
        assert x.dtype == jnp.float32
    errors = oscillator_fit.standard_errors
    for key in ("k", "c"):
        assert abs(float(result.params[key]) - OSCILLATOR_TRUTH[key]) < 3 * errors[key]
        assert abs(float(result.params[key]) - float(oscillator_fit.params[key])) \
            < 0.01 * errors[key]
        assert abs(result.standard_errors[key] / errors[key] - 1) < 1e-3
    with pytest.raises(ValueError, match=r"mix precisions \(p\['c'\] is float32, "
                                         r"p\['k'\] is float64\)"):
        jaxdyn.fit(OSCILLATOR, oscillator_experiment(),
                   {**guess, "k": np.float64(3.0)}, filter_spec=OSCILLATOR_TRAINED)


@pytest.mark.slow
def test_parameter_without_effect_is_named():
    """A simple pendulum's mass cancels from θ̈ = −(g/l) sin θ: its Jacobian column is
    round-off, which must be reported rather than magnified by column scaling."""
    def T(q, qd, p):
        return 0.5 * p["m"] * p["l"] ** 2 * qd[0] ** 2

    def V(q, p):
        return -p["m"] * G * p["l"] * jnp.cos(q[0])

    ts = np.linspace(0.0, 3.0, 31)
    length, omega = 0.5, np.sqrt(G / 0.5)
    solution = solve_ivp(lambda t, y: [y[1], -omega**2 * np.sin(y[0])], (0.0, 3.0), [1.0, 0.0],
                         t_eval=ts, rtol=1e-12, atol=1e-12, method="DOP853")
    experiment = jaxdyn.Experiment(ts, solution.y[0], q0=[1.0], u0=[0.0])
    with pytest.warns(jaxdyn.IdentifiabilityWarning, match=r"cannot identify p\['m'\]: "):
        result = jaxdyn.fit(jaxdyn.Lagrangian(T, V), experiment, {"m": 2.0, "l": 0.6})
    assert np.isinf(result.standard_errors["m"])
    assert abs(float(result.params["l"]) - length) < 1e-6
    assert np.isfinite(result.standard_errors["l"])


@pytest.mark.slow  # a long fit (half a minute or more on two cores)
def test_chaotic_horizon_needs_multiple_shooting():
    """Eight seconds of a chaotic double pendulum: a single simulation from the initial state
    is so sensitive to the parameters that Levenberg–Marquardt, fitting it directly
    (`globalisation=False`), stalls in a local minimum far from the truth; sixteen shooting
    segments make the problem benign."""
    ts = np.linspace(0.0, 8.0, 401)
    states = pendulum_data((2.0, 2.4), ts)
    noisy = states + SIGMA * np.random.default_rng(1).standard_normal(states.shape)
    experiment = jaxdyn.Experiment(ts, noisy, q0=states[0, :2], u0=states[0, 2:],
                                   inputs={"A": 0.0, "w": 1.0}, weights=1 / SIGMA**2)

    def angles_and_rates(t, q, u, p):
        return jnp.concatenate([q, u])

    kwargs = dict(observe=angles_and_rates, simulate_options={"rtol": 1e-8, "atol": 1e-8},
                  filter_spec={"m1": False, "m2": True, "l1": True, "l2": True})
    guess = {"m1": 1.0, "m2": 1.0, "l1": 0.9, "l2": 0.8}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        single = jaxdyn.fit(PENDULUM, experiment, guess, max_steps=60, uncertainty=False,
                            globalisation=False, **kwargs)
    shooting = jaxdyn.MultipleShooting(16, initial_nodes=lambda ts, y: (y[:, :2], y[:, 2:]))
    multiple = jaxdyn.fit(PENDULUM, experiment, guess, shooting=shooting, **kwargs)
    assert multiple.converged
    # The noise floor: ½ χ² ≈ ½ N = 802; the single shot stays orders of magnitude above.
    assert multiple.loss < 1.2 * 0.5 * noisy.size
    assert single.loss > 1e3 * multiple.loss
    # Multiple shooting lands within 4 σ of the truth in every parameter; the single shot's
    # stationary point is more than 20 σ away in each (measured: 100–530 σ).
    single_misses = []
    for key in ("m2", "l1", "l2"):
        error = float(multiple.standard_errors[key])
        assert abs(float(multiple.params[key]) - PENDULUM_TRUTH[key]) < 4 * error, key
        single_misses.append(abs(float(single.params[key]) - PENDULUM_TRUTH[key]) / error)
    assert min(single_misses) > 20, single_misses


# -- a physical inertia -----------------------------------------------------------------------


def test_inertia_parametrisation_is_physical_for_every_latent_value():
    inertia = jaxdyn.InertiaTensor()
    rng = np.random.default_rng(4)
    for z in rng.normal(scale=2.0, size=(200, 6)):
        tensor = np.asarray(inertia.to_physical(jnp.asarray(z)))
        moments = np.linalg.eigvalsh(tensor)
        np.testing.assert_allclose(tensor, tensor.T, atol=1e-14)
        assert moments[0] > 0
        assert moments[2] <= moments[0] + moments[1] + 1e-12 * moments[2]
    box = np.diag([1.0 + 4.0, 4.0 + 9.0, 1.0 + 9.0]) / 12  # a 1 × 2 × 3 box of unit mass
    latent = inertia.to_latent(jnp.asarray(box), "I")
    np.testing.assert_allclose(inertia.to_physical(latent), box, rtol=1e-13, atol=1e-15)
    with pytest.raises(ValueError, match="principal moment"):
        inertia.to_latent(jnp.diag(jnp.array([1.0, 1.0, 3.0])), "p['I']")


@pytest.mark.slow  # a long fit (half a minute or more on two cores)
def test_inertia_tensor_fitted_from_gyro_data_stays_physical():
    """A heavy top on a ball joint (mass and centre of mass known) measured by a gyroscope
    (body angular velocity): the full inertia tensor is fitted, and every iterate is a
    physical inertia. Data: Euler's equations about the pivot, integrated by SciPy."""
    mass, com = 2.0, np.array([0.02, -0.01, 0.3])
    truth = np.array([[0.05, 0.004, -0.003], [0.004, 0.06, 0.002], [-0.003, 0.002, 0.02]])
    pivot = truth + mass * (com @ com * np.eye(3) - np.outer(com, com))

    def rhs(t, y):
        w, x, yq, z = y[:4]
        omega = y[4:]
        rotation = np.array([
            [1 - 2 * (yq**2 + z**2), 2 * (x * yq - w * z), 2 * (x * z + w * yq)],
            [2 * (x * yq + w * z), 1 - 2 * (x**2 + z**2), 2 * (yq * z - w * x)],
            [2 * (x * z - w * yq), 2 * (yq * z + w * x), 1 - 2 * (x**2 + yq**2)]])
        torque = np.cross(com, rotation.T @ np.array([0.0, 0.0, -G * mass]))
        quaternion_rate = 0.5 * np.array([
            -x * omega[0] - yq * omega[1] - z * omega[2],
            w * omega[0] + yq * omega[2] - z * omega[1],
            w * omega[1] + z * omega[0] - x * omega[2],
            w * omega[2] + x * omega[1] - yq * omega[0]])
        return np.concatenate([quaternion_rate,
                               np.linalg.solve(pivot, torque - np.cross(omega, pivot @ omega))])

    ts = np.linspace(0.0, 2.0, 81)
    q0 = np.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0])
    u0 = np.array([0.5, -0.3, 8.0])
    states = solve_ivp(rhs, (0.0, 2.0), [*q0, *u0], t_eval=ts, rtol=1e-12, atol=1e-12,
                       method="DOP853").y.T
    gyro_sigma = 0.01
    noisy = states[:, 4:] + gyro_sigma * np.random.default_rng(5).standard_normal((81, 3))
    top = jaxdyn.RigidBodyTree(
        [jaxdyn.Link("top", jaxdyn.Spherical(), mass=mass, com=tuple(com),
                     inertia=lambda p: p["I"])],
        gravity=jnp.array([0.0, 0.0, -G]))
    dynamics = jaxdyn.ArticulatedBody.from_system(top)
    experiment = jaxdyn.Experiment(ts, noisy, q0=q0, u0=u0, weights=1 / gyro_sigma**2)
    moments_seen = []

    def check_physical(step, params, loss):
        moments = np.linalg.eigvalsh(np.asarray(params["I"]))
        moments_seen.append(moments)
        assert moments[0] > 0 and moments[2] < moments[0] + moments[1]

    guess = {"I": np.diag([0.04, 0.04, 0.03])}
    result = jaxdyn.fit(dynamics, experiment, guess, observe=lambda t, q, u, p: u,
                        parametrisation={"I": jaxdyn.InertiaTensor()}, callback=check_physical)
    assert result.converged and len(moments_seen) == result.num_steps
    fitted = np.asarray(result.params["I"])
    errors = np.asarray(result.standard_errors["I"])
    assert np.all(np.abs(fitted - truth) < 4 * errors + 1e-12)
    np.testing.assert_allclose(fitted, truth, atol=2e-3)


# -- errors -----------------------------------------------------------------------------------


def test_errors_name_the_problem(tmp_path):
    ts = np.linspace(0.0, 1.0, 11)
    with pytest.raises(ValueError, match="rows \\[3\\]"):
        jaxdyn.Experiment(ts, np.where(np.arange(11) == 3, np.nan, 0.0), q0=[1.0], u0=[0.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        jaxdyn.Experiment(ts[::-1], np.zeros(11), q0=[1.0], u0=[0.0])
    with pytest.raises(ValueError, match=r"shape \(k, d\) with k = len\(ts\) = 11"):
        jaxdyn.Experiment(ts, np.zeros((10, 1)), q0=[1.0], u0=[0.0])
    with pytest.raises(ValueError, match="u0 must be a finite 1-D array"):
        jaxdyn.Experiment(ts, np.zeros(11), q0=[1.0], u0=[np.nan])
    experiment = jaxdyn.Experiment(ts, np.cos(2 * ts), q0=[1.0], u0=[0.0])
    with pytest.raises(ValueError, match="divisible by the 3 shooting segments"):
        fit_oscillator(experiment, shooting=jaxdyn.MultipleShooting(3))
    with pytest.raises(ValueError, match=r"p\['c'\] is parametrised as positive"):
        jaxdyn.fit(OSCILLATOR, experiment, {"m": 1.0, "k": 4.0, "c": -0.1},
                   parametrisation={"m": None, "k": None, "c": jaxdyn.Positive()})
    with pytest.raises(ValueError, match="selects no parameter"):
        jaxdyn.fit(OSCILLATOR, experiment, OSCILLATOR_GUESS, filter_spec=False)
    with pytest.raises(ValueError, match="observe returns 2 values per sample but the "
                                         "observations have 1"):
        fit_oscillator(experiment, observe=lambda t, q, u, p: jnp.concatenate([q, u]))
    # Checked inside the simulations (the tolerances are traced in a fit's step), named by
    # the step's checked program.
    with pytest.raises(RuntimeError, match="At step 1 of the fit: rtol and atol must be"):
        jaxdyn.fit(OSCILLATOR, experiment, OSCILLATOR_GUESS, simulate_options={"rtol": -1e-8})
    with pytest.raises(ValueError, match="optimiser must be"):
        fit_oscillator(experiment, optimiser="adam")
    path = tmp_path / "other.eqx"
    eqx.tree_serialise_leaves(path, (np.zeros(3),))
    with pytest.raises(ValueError, match="does not belong to this fit"):
        fit_oscillator(experiment, checkpoint=path)
