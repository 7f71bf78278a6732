"""The single calling convention for user callbacks.

Every user function receives its arguments in the order ``(t, q, qd, p)``, dropping those it
cannot depend on: ``T(q, qd, p)``, ``V(q, p)``, ``D(q, qd, p)``, ``Q(q, qd, p)`` for an
autonomous system, and the same with ``t`` first when the system is declared
``time_dependent=True`` (rheonomic kinematics, a driven support, a time-varying force).
Parameters ``p`` are always an argument, never closed over, so that `jax.grad`, `jax.vmap` and
optax see them.
"""

import inspect

import jax
import jax.numpy as jnp

VELOCITY_ARGS = ("q", "qd", "p")
CONFIGURATION_ARGS = ("q", "p")


def call(fn, name: str, time_dependent: bool, argnames: tuple[str, ...], t, *args):
    """Call a user callback following the convention, with a clear error if its signature
    cannot accept the arguments."""
    full = (t, *args) if time_dependent else args
    names = ("t", *argnames) if time_dependent else argnames
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):  # builtins, some C callables: nothing to check
        signature = None
    if signature is not None:
        try:
            signature.bind(*full)
        except TypeError as e:
            hint = (
                "If it does not depend on time, pass time_dependent=False."
                if time_dependent
                else "If it depends on time, pass time_dependent=True and take t first."
            )
            raise ValueError(
                f"{name} is called as {name.split()[-1]}({', '.join(names)}) "
                f"(time_dependent={time_dependent}), but its signature is "
                f"{signature}: {e}. {hint}"
            ) from None
    try:
        return fn(*full)
    except CallbackError:
        raise
    except Exception as e:  # noqa: BLE001 (re-raised with the callback named)
        raise CallbackError(_explain(e, name, names, full)) from e


class CallbackError(ValueError):
    """A user callback raised while jaxdyn traced it: the message names the callback."""


def _explain(error, name, names, args):
    shapes = ", ".join(f"{n} of shape {tuple(a.shape)}" for n, a in zip(names, args)
                       if hasattr(a, "shape"))
    message = (f"{name[:1].upper() + name[1:]}, called as {name.split()[-1]}({', '.join(names)})"
               f"{' with ' + shapes if shapes else ''}, raised {type(error).__name__}: {error}")
    traced = isinstance(error, jax.errors.ConcretizationTypeError
                        | jax.errors.TracerBoolConversionError
                        | jax.errors.TracerIntegerConversionError
                        | jax.errors.TracerArrayConversionError)
    # JAX's errors for a Python branch on a traced value are TypeErrors too: not a parameter.
    if isinstance(error, KeyError | IndexError | TypeError) and "p" in names and not traced:
        parameters = args[names.index("p")]
        keys = sorted(map(str, parameters)) if isinstance(parameters, dict) else None
        message += (f"\n\nIs a parameter missing from p? It has keys {keys}." if keys
                    is not None else f"\n\nCheck the parameters p passed: got "
                    f"{type(parameters).__name__}.")
    if traced:
        message += ("\n\nCallbacks are traced by JAX: branch with jnp.where or jax.lax.cond, "
                    "not Python `if` on values of q, qd or p.")
    return message


def scalar(value, name: str):
    """Check that an energy-like callback returned a scalar."""
    value = jnp.asarray(value)
    if value.shape != ():
        raise ValueError(
            f"{name} must return a scalar, but returned an array of shape {value.shape}. "
            "Sum the contributions (e.g. jnp.sum) so that it returns one number."
        )
    if not jnp.issubdtype(value.dtype, jnp.inexact):
        raise ValueError(f"{name} must return a floating-point scalar, got dtype {value.dtype}.")
    return value


def vector(value, name: str, shape: tuple[int, ...]):
    """Check that a vector-valued callback returned an array of the expected shape."""
    value = jnp.asarray(value)
    if value.shape != shape:
        raise ValueError(f"{name} must return an array of shape {shape}, got shape {value.shape}.")
    return value


def time_rate(t, time_dependent: bool):
    """dt/dt along the motion, as the time tangent of the JVPs: 1 brings in the explicit ∂/∂t
    terms of a time-dependent system; 0 skips them for an autonomous one."""
    return jnp.ones_like(t) if time_dependent else jnp.zeros_like(t)
