"""Physical parametrisations: unconstrained latent variables z that map onto parameters which
are physical by construction.

An optimiser moves z freely; the dynamics sees x = φ(z). A positive mass, length, stiffness or
damping is x = exp z. A rigid body's inertia tensor about its centre of mass, I, is physical when
it is the inertia of some mass distribution: positive definite with principal moments that obey
the triangle inequality I₁ ≤ I₂ + I₃. Both hold exactly when the second moment of the mass
distribution, Σ = ∫ r rᵀ dm = ½ tr(I) 1 − I, is positive definite (Wensing, Kim and Slotine,
"Linear matrix inequalities for physically consistent inertial parameter identification",
IEEE RA-L, 2017). So I = tr(Σ) 1 − Σ with Σ = L Lᵀ, L lower triangular with a positive
diagonal: six latent numbers, and every value of them is a physical inertia.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._state import transferred


class AbstractParametrisation(eqx.Module):
    """How a parameter leaf x is represented by unconstrained latent variables z."""

    @abc.abstractmethod
    def to_latent(self, x, name: str):
        """z with φ(z) = x; a `ValueError` naming `name` if x is not admissible."""

    @abc.abstractmethod
    def to_physical(self, z):
        """x = φ(z)."""


class Unconstrained(AbstractParametrisation):
    """x = z: any real value (offsets, angles, gravity, signed coefficients)."""

    def to_latent(self, x, name):
        return x

    def to_physical(self, z):
        return z


class Positive(AbstractParametrisation):
    """x = exp z > 0: masses, lengths, stiffnesses, damping, inertias of planar bodies.

    The logarithm also makes steps relative (a 10 % change is the same step for a mass of 1 g
    or 1 t), which suits parameters spanning orders of magnitude.
    """

    def to_latent(self, x, name):
        if not np.all(np.asarray(x) > 0):
            raise ValueError(f"{name} is parametrised as positive but its initial value is "
                             f"{np.asarray(x).tolist()}. Start it positive, or pass "
                             "jaxdyn.Unconstrained() for it in `parametrisation`.")
        # (x is a value here: NumPy's logarithm, where `jnp.log` would compile a program of
        # its own in a process's first fit)
        return transferred(np.log(np.asarray(x)))

    def to_physical(self, z):
        return jnp.exp(z)


class InertiaTensor(AbstractParametrisation):
    """A 3 × 3 inertia tensor about the centre of mass, physical for every latent value:
    I = tr(Σ) 1 − Σ, Σ = L Lᵀ, L lower triangular with diagonal exp(d) (six latent numbers).
    Positive definiteness and the triangle inequalities hold by construction."""

    def to_latent(self, x, name):
        x = np.asarray(x)
        if x.shape != (3, 3):
            raise ValueError(f"{name} is parametrised as an InertiaTensor but has shape "
                             f"{x.shape}; it must be 3 × 3.")
        if not np.allclose(x, x.T, rtol=1e-10, atol=0):
            raise ValueError(f"{name} must be symmetric to be an inertia tensor.")
        second_moment = 0.5 * np.trace(x) * np.eye(3) - x
        try:
            factor = np.linalg.cholesky(second_moment)
        except np.linalg.LinAlgError:
            moments = np.linalg.eigvalsh(x).tolist()
            raise ValueError(
                f"{name} (principal moments {moments}) is not the inertia of a rigid body: "
                "it must be positive definite with each principal moment strictly less than "
                "the sum of the other two.") from None
        rows, cols = np.tril_indices(3, -1)
        return jnp.concatenate([jnp.log(jnp.asarray(np.diag(factor), x.dtype)),
                                jnp.asarray(factor[rows, cols], x.dtype)])

    def to_physical(self, z):
        factor = jnp.diag(jnp.exp(z[:3]))
        rows, cols = np.tril_indices(3, -1)
        factor = factor.at[rows, cols].set(z[3:])
        second_moment = factor @ factor.T
        return jnp.trace(second_moment) * jnp.eye(3, dtype=z.dtype) - second_moment


def default_parametrisation(x) -> AbstractParametrisation:
    """`Positive` for a leaf whose initial values are all positive, else `Unconstrained`."""
    return Positive() if np.all(np.asarray(x) > 0) else Unconstrained()


def leaf_parametrisations(spec, params) -> list[AbstractParametrisation]:
    """One parametrisation per leaf of `params` (in flattening order), from `spec`: None (the
    default for every leaf), or a prefix tree of `params` whose leaves are parametrisations, or
    None for the default."""
    is_spec = lambda s: s is None or isinstance(s, AbstractParametrisation)  # noqa: E731
    leaves = jax.tree_util.tree_leaves(params)
    if spec is None:
        return [default_parametrisation(x) for x in leaves]
    specs = []

    def expand(s, subtree):
        specs.extend([s] * len(jax.tree_util.tree_leaves(subtree)))

    try:
        jax.tree_util.tree_map(expand, spec, params, is_leaf=is_spec)
    except ValueError as error:
        raise ValueError("`parametrisation` must be a prefix of the parameter tree, with "
                         "jaxdyn.Positive(), jaxdyn.Unconstrained(), jaxdyn.InertiaTensor() "
                         f"or None (the default) at its leaves: {error}") from None
    return [default_parametrisation(x) if s is None else s for s, x in zip(specs, leaves)]
