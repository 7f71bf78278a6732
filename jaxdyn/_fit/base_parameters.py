"""The base parameters of a linear identification problem: the combinations of the inertial
parameters that the data determine (Gautier and Khalil, 1990; Gautier, 1991).

The joint forces are τ = Y π; a column of the stacked regressor Y that is a combination of
others (a link whose mass only ever appears with its neighbour's, a moment about an axis that
never turns) leaves its parameter undetermined. QR factorisation with column pivoting,
Y P = Q R, orders the columns so that the first r (the numerical rank) are independent,
Y_b = Y P₁, and the others are combinations of them, Y_d = Y_b K with K = R₁₁⁻¹ R₁₂. Then

    Y π = Y_b β,    β = π_b + K π_d,

and β, the base parameters, are what least squares identifies: β̂ = argmin ‖Y_b β − τ‖,
with covariance s² (Y_bᵀ Y_b)⁻¹, s² = ‖Y_b β̂ − τ‖² / (rows − r).
"""

import equinox as eqx
import numpy as np
import scipy.linalg

# The ten inertial parameters of a link, in `jaxdyn.inertial_parameters`' order.
PARAMETER_NAMES = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


class BaseParameters(eqx.Module):
    """The identifiable combinations of the inertial parameters (Gautier and Khalil's base
    parameters), β = `combinations` π, from the stacked regressor of the data.

    **Fields:**

    - `names`: each base parameter as its combination, e.g. "rod0.Izz + 0.25 rod1.m"
      (parameters named `link.m`, `link.mx`, …, `link.Izz`: m, m c and the inertia about the
      link's origin, `jaxdyn.inertial_parameters`' order).
    - `combinations` (r, 10 L): the rows of β = C π over the fitted links' π (L links, ten
      each), one per base parameter: 1 at its own parameter, K at those it absorbs.
    - `values` (r,): β̂ from least squares on the independent columns.
    - `standard_errors` (r,): √diag(s² (Y_bᵀ Y_b)⁻¹), s² the residual variance per degree of
      freedom.
    - `identifiable` (L, 10): whether each single parameter is determined by the data (its
      unit vector lies in the row space of the regressor); the others only through the
      combinations.
    """

    names: tuple[str, ...]
    combinations: np.ndarray
    values: np.ndarray
    standard_errors: np.ndarray
    identifiable: np.ndarray

    def summary(self) -> str:
        """A table: each base parameter's value, standard error and combination."""
        lines = [f"{len(self.names)} base parameters (identifiable combinations):",
                 f"{'value':>12s}  {'std. error':>10s}  combination"]
        lines += [f"{v:12.6g}  {s:10.3g}  {name}" for v, s, name in
                  zip(self.values, self.standard_errors, self.names)]
        return "\n".join(lines)


def base_parameters(regressor, forces, rank: int, links, unseen) -> BaseParameters:
    """The base parameters of `regressor` (rows, 10 L) for the joint forces `forces` (rows,):
    `rank` independent columns found by QR with column pivoting; `unseen` (10 L − rank, 10 L)
    spans the combinations the regressor does not see (its null space)."""
    a, b = np.asarray(regressor, dtype=float), np.asarray(forces, dtype=float)
    # On the host (SciPy's LAPACK, as the rest of this report): eager, JAX's QR compiled
    # each of its operations apart.
    _, triangle, order = scipy.linalg.qr(a, mode="economic", pivoting=True)  # type: ignore[misc]
    independent, dependent = order[:rank], order[rank:]
    absorbed = np.linalg.solve(triangle[:rank, :rank], triangle[:rank, rank:])  # K
    combinations = np.zeros((rank, a.shape[1]))
    combinations[np.arange(rank), independent] = 1.0
    combinations[:, dependent] = absorbed
    # Coefficients below round-off of the factorisation are zero, not noise in the names.
    combinations[np.abs(combinations) < 1e-10 * max(1.0, np.max(np.abs(absorbed), initial=0))] = 0
    basis = a[:, independent]
    values, *_ = np.linalg.lstsq(basis, b, rcond=None)
    degrees = max(a.shape[0] - rank, 1)
    variance = float(np.sum((basis @ values - b) ** 2)) / degrees
    covariance = variance * np.linalg.inv(basis.T @ basis)
    names = [f"{link}.{name}" for link in links for name in PARAMETER_NAMES]
    seen = np.linalg.norm(np.asarray(unseen), axis=0) < 1e-6
    return BaseParameters(
        names=tuple(_combination(row, own, names) for row, own in zip(combinations, independent)),
        combinations=combinations,
        values=values,
        standard_errors=np.sqrt(np.maximum(np.diag(covariance), 0.0)),
        identifiable=seen.reshape(len(links), 10),
    )


def _combination(row, own, names) -> str:
    """'a + 0.25 b − 1.5 c': the base parameter (index `own`) first, then what it absorbs."""
    text = names[own]
    for j in np.flatnonzero(row):
        if j == own:
            continue
        coefficient = float(row[j])
        sign = "−" if coefficient < 0 else "+"
        magnitude = abs(coefficient)
        text += f" {sign} {names[j]}" if np.isclose(magnitude, 1.0) else \
            f" {sign} {magnitude:.4g} {names[j]}"
    return text
