"""jaxtyping aliases shared by the whole library, for signatures (not checked at run time)."""

from typing import Any

from jaxtyping import Array, ArrayLike, Float, PyTree

RealScalarLike = float | int | Float[ArrayLike, ""]
Coordinates = Float[Array, "n"]  # q
Speeds = Float[Array, "m"]  # u (q̇ for Lagrangian dynamics)
MassMatrix = Float[Array, "m m"]
Params = PyTree[Any]  # p: any pytree, passed to every callback, never closed over
