"""jaxtyping aliases shared by the whole library (checked at run time in tests only)."""

from typing import Any, Callable

from jaxtyping import Array, ArrayLike, Float, PyTree

Scalar = Float[Array, ""]
RealScalarLike = float | int | Float[ArrayLike, ""]
Coordinates = Float[Array, "n"]  # q
Speeds = Float[Array, "m"]  # u (q̇ for Lagrangian dynamics)
MassMatrix = Float[Array, "m m"]
Params = PyTree[Any]  # p: any pytree, passed to every callback, never closed over
Callback = Callable[..., Any]
