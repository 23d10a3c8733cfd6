"""Program keys that do not depend on how an argument was built: a weakly typed array (one
made from a Python number, such as `jnp.asarray(0.0)`) keys a different program than the
same array strongly typed, though in float64 both compute the same numbers. The zoo's
systems mix both, so each member compiled its own simulation (`benchmarks/compile_log.py`
counts them)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax

__all__ = ["strong_jit", "strong_types"]


def strong_types(tree):
    """Every weakly typed array of a pytree made strongly typed, of the same dtype.

    **Arguments:**

    - `tree`: any pytree; its other leaves pass unchanged.

    **Returns:** the pytree with strongly typed arrays.
    """
    return jax.tree.map(lambda a: a.astype(a.dtype) if getattr(a, "weak_type", False) else a, tree)


def strong_jit(fun):
    """`equinox.filter_jit` of a function whose arguments are made strongly typed first
    (`strong_types`): one program for equal shapes, however they were built.

    **Arguments:**

    - `fun`: the function to compile.

    **Returns:** the jitted function, with `fun`'s signature and docstring.
    """
    jitted = eqx.filter_jit(fun)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        args, kwargs = strong_types((args, kwargs))
        return jitted(*args, **kwargs)

    return call
