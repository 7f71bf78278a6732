"""What a state is: time t, coordinates q (n,), speeds u (m,). Validation and broadcasting."""

import functools

import jax.numpy as jnp


def as_float_array(x, name: str):
    """`x` as a floating-point array; integers are promoted to the default float dtype."""
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.integer) or jnp.issubdtype(x.dtype, jnp.bool_):
        x = x.astype(jnp.result_type(float))
    elif not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"{name} must be a real floating-point array, got dtype {x.dtype}.")
    return x


def check_vector(x, name: str, size: int | None = None):
    """Trace-time check that `x` is 1-D (of length `size` if given)."""
    x = as_float_array(x, name)
    if x.ndim != 1:
        raise ValueError(
            f"{name} must be a 1-D array of shape (n,), got shape {x.shape}. "
            "A system with one coordinate takes q of shape (1,)."
        )
    if size is not None and x.shape[0] != size:
        raise ValueError(f"{name} must have shape ({size},), got shape {x.shape}.")
    return x


def over_states(signature: str):
    """Make a method written for one state also accept stacked states (a trajectory).

    The method is ``method(self, *arrays, p=None)`` on one state; `signature` is its core
    signature in `jnp.vectorize` notation, e.g. ``"(),(n),(n)->()"`` for ``(t, q, qd) -> E``.
    Leading axes broadcast, so ``system.energy(sol.ts, sol.q, sol.qd, p)`` gives the energy
    along a whole trajectory.
    """
    inputs = signature.split("->")[0]
    num_arrays = inputs.count("(")
    core_ndims = [part.count(",") + (0 if part == "()" else 1) for part in _split(inputs)]
    names = ("t", "q", "qd", "qdd")[:num_arrays]

    def decorator(method):
        @functools.wraps(method)
        def wrapper(self, *args):
            if len(args) not in (num_arrays, num_arrays + 1):
                raise TypeError(
                    f"{method.__name__} takes ({', '.join(names)}, p=None), "
                    f"got {len(args)} positional arguments."
                )
            arrays = [as_float_array(a, n) for a, n in zip(args[:num_arrays], names)]
            p = args[num_arrays] if len(args) > num_arrays else None
            for a, n, k in zip(arrays, names, core_ndims):
                if a.ndim < k:
                    raise ValueError(
                        f"{n} must have at least {k} dimension(s), got shape {a.shape}."
                    )
            if all(a.ndim == k for a, k in zip(arrays, core_ndims)):
                return method(self, *arrays, p)
            fn = jnp.vectorize(lambda *xs: method(self, *xs, p), signature=signature)
            return fn(*arrays)

        return wrapper

    return decorator


def _split(inputs: str) -> list[str]:
    return ["(" + part.strip("(),") + ")" for part in inputs.split(")") if part.strip(",")]
