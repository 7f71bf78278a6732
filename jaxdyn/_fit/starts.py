"""Multi-start: a batch of starting points fitted at once, the best optimum kept."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class MultiStart(eqx.Module):
    """Fit from `count` starting points at once and keep the lowest loss.

    The starting points are the initial guess and `count − 1` others, each fitted parameter
    leaf multiplied by its own factor drawn log-uniformly from [1/`spread`, `spread`] (one
    factor per leaf, so that an inertia tensor or a vector keeps its shape and sign; initial
    states are not perturbed). Every start is a separate fit with the same optimiser and
    settings; they run as one vmapped computation (sharded over this process's devices), each start
    stopping where its own optimiser's tolerance is met, so that the result equals the best
    of the separate fits.

    **Arguments:**

    - `count`: the number of starting points, the initial guess among them.
    - `spread`: the largest factor between a starting point and the guess (default 2).
    - `seed`: of the factors.
    """

    count: int = eqx.field(default=16, static=True)
    spread: float = eqx.field(default=2.0, static=True)
    seed: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        if not isinstance(self.count, int) or self.count < 1:
            raise ValueError(f"count must be a positive integer, got {self.count!r}.")
        if not self.spread >= 1:
            raise ValueError(f"spread must be at least 1, got {self.spread!r}.")

    def starting_points(self, params, filter_spec=eqx.is_inexact_array) -> list:
        """The parameter pytrees the fit starts from: `params` first, then the others."""
        # Python numbers as arrays of JAX's default float, as `jaxdyn.fit` takes them.
        params = jax.tree_util.tree_map(
            lambda x: jnp.asarray(x) if isinstance(x, float) else x, params)
        trained, frozen = eqx.partition(params, filter_spec)
        leaves, treedef = jax.tree_util.tree_flatten(trained)
        rng = np.random.default_rng(self.seed)
        log_spread = np.log(self.spread)
        points = [params]
        for _ in range(self.count - 1):
            factors = np.exp(rng.uniform(-log_spread, log_spread, len(leaves)))
            scaled = [(leaf * factor).astype(leaf.dtype) for leaf, factor in zip(leaves, factors)]
            points.append(eqx.combine(jax.tree_util.tree_unflatten(treedef, scaled), frozen))
        return points
