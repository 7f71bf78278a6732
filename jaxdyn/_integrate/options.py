"""`simulate`'s options checked and completed: tolerances, save times, the step budget and the
step-size control of fixed-step solvers."""

import math

import diffrax
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._errors import error_if


def fixed_steps(solver, rtol, atol, dt0, stepsize_controller):
    """The step-size controller of a structure-preserving solver, which takes fixed steps."""
    name = type(solver).__name__
    if rtol is not None or atol is not None:
        raise ValueError(f"{name} takes fixed steps, without error control: pass the step as "
                         "dt0, not rtol/atol.")
    if dt0 is None:
        raise ValueError(f"{name} takes fixed steps: pass the step length as dt0.")
    if stepsize_controller is None:
        return diffrax.ConstantStepSize()
    if isinstance(stepsize_controller, diffrax.AbstractAdaptiveStepSizeController):
        raise ValueError(f"{name} takes fixed steps (an adaptive step destroys the "
                         "conservation it gives): use diffrax.ConstantStepSize() or "
                         "StepTo, or leave stepsize_controller unset.")
    return stepsize_controller


def _concrete(x):
    return x is None or not any(isinstance(leaf, jax.core.Tracer)
                                for leaf in jax.tree_util.tree_leaves(x))


def _tolerance_problem(rtol, atol):
    """None, or what is wrong with the tolerances (`rtol`, `atol` arrays)."""
    for name, value in (("rtol", rtol), ("atol", atol)):
        if value is not None and not np.all(np.isfinite(value) & (value >= 0)):
            return f"{name} must be finite and ≥ 0, got {value}."
    if rtol is not None and atol is not None and np.all(rtol + atol == 0):
        return "rtol and atol are both 0: no step could meet them. Pass positive tolerances."
    return None


def check_tolerances(rtol, atol):
    """Trace-time check of concrete tolerances (traced ones are checked in the solve)."""
    if all(x is None or type(x) is float for x in (rtol, atol)):  # the common case, cheaply
        if all(x is None or (math.isfinite(x) and x >= 0) for x in (rtol, atol)) and (
                rtol is None or atol is None or rtol + atol > 0):
            return
    if _concrete((rtol, atol)):
        as_array = lambda x: None if x is None else np.asarray(x)  # noqa: E731
        problem = _tolerance_problem(as_array(rtol), as_array(atol))
        if problem is not None:
            raise ValueError(problem)


def tolerance_checks(rtol, atol):
    """[(pred, message)]: the tolerances' value-dependent check (none when either is None)."""
    if rtol is None or atol is None:
        return []
    bad = (~jnp.isfinite(rtol) | ~jnp.isfinite(atol) | (rtol < 0) | (atol < 0)
           | (rtol + atol == 0))
    return [(bad, "rtol and atol must be finite and ≥ 0, and not both 0.")]


def checked_tolerances(rtol, atol):
    checks = tolerance_checks(rtol, atol)
    return error_if((rtol, atol), checks, {"rtol": rtol, "atol": atol}) if checks else (
        rtol, atol)


def save_time_checks(ts, t0, t1):
    """[(pred, message)]: whether the save times `ts` hold NaN or inf, leave [t0, t1], or run
    against the direction of integration; a `ValueError` at trace time if they are not a
    non-empty 1-D array."""
    if ts.ndim != 1:
        raise ValueError(f"ts must be a 1-D array of save times, got shape {ts.shape}.")
    if ts.shape[0] == 0:
        raise ValueError("ts is empty: pass at least one save time, or ts=None to save t1.")
    direction = jnp.where(t1 >= t0, 1, -1).astype(ts.dtype)
    outside = jnp.any((ts - t0) * direction < 0) | jnp.any((ts - t1) * direction > 0)
    against = jnp.any(jnp.diff(ts) * direction < 0)
    return [(~jnp.all(jnp.isfinite(ts)), "ts contains NaN or inf."),
            (outside, "ts must lie within the interval from t0 to t1."),
            (against, "ts must run in the direction of integration: increasing for t1 > t0, "
                      "decreasing for t1 < t0.")]


def checked_save_times(ts, t0, t1):
    """`ts`, or an error if they fail `save_time_checks` (a value-dependent check: one branch,
    taken on failure)."""
    return error_if(ts, save_time_checks(ts, t0, t1),
                    {"t0": t0, "t1": t1, "ts[0]": ts[0], "ts[-1]": ts[-1]})


def step_budget(max_steps, t0, t1, dt0, stepsize_controller):
    """`max_steps`, or its default: 16⁴, or the steps a fixed step takes over the interval."""
    if max_steps is not None:
        if not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}.")
        return max_steps
    budget = 16**4
    fixed = (stepsize_controller is not None and not isinstance(
        stepsize_controller, diffrax.AbstractAdaptiveStepSizeController))
    if fixed and dt0 is not None and _concrete((t0, t1, dt0)):
        span, step = abs(float(t1) - float(t0)), abs(float(dt0))
        if step > 0:
            needed = math.ceil(span / step * (1 + 1e-9)) + 1
            # Rounded up to a power of two: the budget is compiled in, and nearby intervals
            # then reuse the compiled solve.
            budget = max(budget, 2 ** math.ceil(math.log2(needed)))
    return budget
