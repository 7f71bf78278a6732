"""Whether a fitted model explains its data: residuals against the noise in the data.

An optimiser's tolerance says that its steps stopped making progress, not that the fit found
the optimum: trajectory matching of an oscillating system has local minima (a frequency off
by whole periods over the horizon), and a model can lack a term (damping, friction). Either
way the residuals stay far above the measurement noise. The noise is estimated from the data
alone, by differences along each record: for samples y_j = s(t_j) + ε_j of a smooth signal s
with white noise ε of variance σ², the k-th differences Δᵏy of the noise have variance
C(2k, k) σ² while those of s are O(hᵏ s⁽ᵏ⁾), so

    σ̂² = min over k = 2, 3, 4 of  mean (Δᵏ √w y)² / C(2k, k)

(Rice 1984; Gasser, Sroka and Jennen-Steinmetz 1986; the smallest order rejects the signal
best at coarse sampling, where the estimate errs high and the test stays quiet). The fit
explains its data when the weighted residual variance

    σ² = Σ w (y − ŷ)² / (N − P)

is at most `RATIO_MAX` σ̂² (residuals at most twice the noise in RMS), or within integration
accuracy of the data where they hold no noise; with multiple shooting, the continuity
residuals must close to the same level.
"""

import math

import numpy as np

#: σ² / σ̂² above which the residuals are not noise: twice the noise in RMS.
RATIO_MAX = 4.0
#: Residuals within this multiple of the simulations' relative tolerance of the data's RMS
#: are integration error: noise-free data fitted exactly.
INTEGRATION_FLOOR = 100.0
_ORDERS = (2, 3, 4)


def noise_variance(observations, sqrt_weights) -> float:
    """σ̂², the variance of the weighted noise in a group's records (E, k, d) estimated by
    differences along each record (samples of weight 0, missing, break the differences)."""
    z = np.asarray(observations, np.float64) * np.asarray(sqrt_weights, np.float64)
    present = np.asarray(sqrt_weights) > 0
    estimates = []
    for order in _ORDERS:
        if z.shape[1] <= order:
            continue
        differences = np.diff(z, n=order, axis=1)
        # A difference is valid where all the samples it spans are present.
        valid = np.ones(differences.shape, bool)
        for shift in range(order + 1):
            valid &= present[:, shift:shift + differences.shape[1]]
        if valid.any():
            estimates.append(np.mean(differences[valid] ** 2) / math.comb(2 * order, order))
    return min(estimates) if estimates else float("nan")


def _noise_and_level(groups, tolerance):
    """(σ̂², the residual variance up to which the data count as explained, the number of
    weighted observations); σ̂² NaN where the records are too short."""
    counts = [int(np.sum(np.asarray(g.sqrt_weights) > 0)) for g in groups]
    estimates = [noise_variance(g.observations, g.sqrt_weights) for g in groups]
    known = [(e, c) for e, c in zip(estimates, counts) if np.isfinite(e)]
    if not known:
        return float("nan"), float("nan"), sum(counts)
    noise = float(np.average([e for e, _ in known], weights=[c for _, c in known]))
    weighted = np.concatenate([(np.asarray(g.observations) * np.asarray(g.sqrt_weights)).ravel()
                               for g in groups])
    floor = (INTEGRATION_FLOOR * tolerance) ** 2 * float(np.mean(weighted**2))
    return noise, max(RATIO_MAX * noise, floor), sum(counts)


def explained_loss(groups, num_unknowns, tolerance) -> float:
    """The largest loss ½ Σ w (y − ŷ)² whose residuals `adequacy` counts as explaining the
    data (∞ where the noise cannot be estimated)."""
    _, level, count = _noise_and_level(groups, tolerance)
    return float("inf") if np.isnan(level) else 0.5 * level * max(count - num_unknowns, 1)


def adequacy(groups, r_obs, r_continuity, num_unknowns, tolerance):
    """(σ², σ̂², explains the data, continuity closed) at the optimum; the last two are None
    where the records are too short to estimate the noise (fewer than four samples).

    `groups`: the problem's experiment groups (observations and weights); `r_obs`: the
    weighted observation residuals; `r_continuity`: the multiple-shooting continuity residuals
    (empty without); `num_unknowns`: fitted unknowns less the continuity conditions;
    `tolerance`: the simulations' relative tolerance."""
    noise, level, count = _noise_and_level(groups, tolerance)
    residual = float(np.sum(np.asarray(r_obs) ** 2) / max(count - num_unknowns, 1))
    if np.isnan(level):
        return residual, noise, None, None
    r_continuity = np.asarray(r_continuity)
    closed = bool(r_continuity.size == 0 or np.mean(r_continuity**2) <= level)
    return residual, noise, bool(residual <= level), closed
