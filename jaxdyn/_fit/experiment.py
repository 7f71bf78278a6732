"""Measured data: experiments, and how a long horizon is cut: into shooting segments, or into
the growing horizons of a continuation."""

import math
from typing import Any, Callable

import equinox as eqx
import numpy as np


class Experiment(eqx.Module):
    """One measured trajectory.

    **Arguments:**

    - `ts`: the measurement times (k,), increasing; the motion starts at `ts[0]`.
    - `observations`: the measurements (k, d) at `ts` (or (k,) for one observed quantity),
      what `observe(t, q, u, p)` predicts; by default the coordinates q (d = n).
    - `q0`, `u0`: the initial state at `ts[0]`: known, or a first guess when `jaxdyn.fit` fits
      initial states too (`fit_initial_states=True`).
    - `inputs`: what differs between experiments apart from the initial state (a torque
      profile, a commanded trajectory): any pytree, or None. With inputs, the dynamics and
      `observe` receive p = (params, inputs).
    - `weights`: None (all 1) or non-negative weights broadcastable to (k, d), ideally the
      inverse noise variances 1/σ²; a weight 0 drops a missing sample. Residuals are
      √w (y − ŷ).
    """

    ts: Any
    observations: Any
    q0: Any
    u0: Any
    inputs: Any = None
    weights: Any = None

    def __init__(self, ts, observations, q0, u0, inputs=None, weights=None):
        ts = np.asarray(ts, dtype=float)
        observations = np.asarray(observations, dtype=float)
        if observations.ndim == 1:
            observations = observations[:, None]
        if ts.ndim != 1 or ts.shape[0] < 2:
            raise ValueError(f"ts must be 1-D with at least two times, got shape {ts.shape}.")
        if not np.all(np.diff(ts) > 0):
            raise ValueError("ts must be strictly increasing.")
        if observations.ndim != 2 or observations.shape[0] != ts.shape[0]:
            raise ValueError(f"observations must have shape (k, d) with k = len(ts) = "
                             f"{ts.shape[0]}, got {observations.shape}.")
        bad = np.nonzero(~np.all(np.isfinite(observations), axis=1))[0]
        if bad.size:
            raise ValueError(f"observations hold NaN or inf at rows {bad[:10].tolist()}; give "
                             "a missing sample any finite value and weight 0.")
        if weights is not None:
            weights = np.broadcast_to(np.asarray(weights, dtype=float), observations.shape)
            if not np.all(np.isfinite(weights)) or np.any(weights < 0):
                raise ValueError("weights must be finite and non-negative.")
        self.ts = ts
        self.observations = observations
        self.q0 = np.atleast_1d(np.asarray(q0, dtype=float))
        self.u0 = np.atleast_1d(np.asarray(u0, dtype=float))
        for name, x in (("q0", self.q0), ("u0", self.u0)):
            if x.ndim != 1 or not np.all(np.isfinite(x)):
                raise ValueError(f"{name} must be a finite 1-D array, got {x.tolist()}.")
        self.inputs = inputs
        self.weights = weights


class MultipleShooting(eqx.Module):
    """Cut every experiment into `segments` shooting segments of equal numbers of samples.

    Each segment starts from its own state (a *shooting node*, fitted with the parameters) and
    integrates only to the next node; a continuity residual w·(x(end of segment) − next node)
    ties the pieces together, and at the optimum they join into one trajectory (Bock and
    Plitt, 1984). Over a long horizon, and above all for chaotic motion, a single simulation
    from the initial state depends so sensitively on the parameters that the loss is a
    landscape of narrow local minima; short segments keep it close to quadratic.

    **Arguments:**

    - `segments`: the number of segments; len(ts) − 1 must be divisible by it.
    - `continuity_weight`: w; a continuity residual w·gap is in the units of the weighted
      observation residuals √w_obs·error, so with weights 1/σ² a gap costs as much as an
      observation error w σ times larger. Too small a w lets the segments part at the
      optimum and biases it (choose w well above 1/σ); too large a one makes the problem
      ill-conditioned for Levenberg–Marquardt. The default suits σ ≈ 0.01.
    - `initial_nodes`: None, or a function (ts, observations) → (q (k, n), u (k, m)) giving a
      state at every sample from the data (e.g. measured angles and rates), from which the
      nodes start. With None, the nodes start on a simulation at the initial parameters.

    Where the data do not observe the state (a marker's position, some coordinates), the
    nodes cannot be read from them: fit with `globalisation=jaxdyn.HorizonContinuation()`,
    and the nodes start on a simulation at the optimum of the short horizons (the
    continuation's stages, single-shooting fits of the first parts of every record, whose
    single basin contains the truth), not at the initial guess. The default globalisation
    takes that route when a fit by multiple shooting ends trapped.
    """

    segments: int = eqx.field(static=True)
    continuity_weight: float = 100.0
    initial_nodes: Callable | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        if not isinstance(self.segments, int) or self.segments < 1:
            raise ValueError(f"segments must be a positive integer, got {self.segments!r}.")


class HorizonContinuation(eqx.Module):
    """Fit the first part of every record, then longer parts, each from the optimum of the
    last, and the whole records last.

    A trajectory over many periods depends on a frequency so sensitively that the loss has a
    local minimum wherever the simulated and measured oscillations are a whole number of
    periods apart; over the first period or two it has one basin, whose optimum is close to
    the global one of the longer horizon (Bock 1983; Voss, Timmer and Kurths 2004). Each stage
    lengthens the horizon while the fit stays in that basin. A stage keeps the records' shapes
    (its later samples stay in place, at its last time and with weight 0, and are not
    simulated), so that the stages and the whole fit share one compiled program.

    **Arguments:**

    - `fractions`: the parts of each record fitted before the whole, increasing (default: an
      eighth, a quarter, a half).
    - `min_samples`: the fewest samples a stage fits (records shorter than this are fitted
      whole at every stage).
    """

    fractions: tuple[float, ...] = eqx.field(default=(0.125, 0.25, 0.5), static=True)
    min_samples: int = eqx.field(default=16, static=True)

    def __check_init__(self):
        if (not self.fractions or any(not 0 < f < 1 for f in self.fractions)
                or list(self.fractions) != sorted(self.fractions)):
            raise ValueError("fractions must be increasing numbers between 0 and 1, got "
                             f"{self.fractions!r}.")

    def samples(self, experiment: Experiment, fraction: float) -> int:
        """How many leading samples of `experiment` the stage `fraction` fits (at least
        `min_samples`, at most the whole record)."""
        count = experiment.ts.shape[0]
        return min(count, max(self.min_samples, math.ceil(fraction * (count - 1)) + 1))
