"""Program keys that do not depend on how an argument was built: a weakly typed array (one
made from a Python number, such as `jnp.asarray(0.0)`) keys a different program than the
same array strongly typed, though in float64 both compute the same numbers. The zoo's
systems mix both, so each member compiled its own simulation (19 of the test suite's 66
`simulate` compilations, `benchmarks/compile_log.py`)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax

__all__ = ["strong_jit", "strong_types"]


def strong_types(tree):
    """`tree` with every weakly typed array converted to the same dtype, strongly typed."""
    return jax.tree.map(lambda a: a.astype(a.dtype) if getattr(a, "weak_type", False) else a, tree)


def strong_jit(fun):
    """`equinox.filter_jit` of `fun` whose arguments are made strongly typed first
    (`strong_types`): one program for equal shapes, however they were built."""
    jitted = eqx.filter_jit(fun)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        args, kwargs = strong_types((args, kwargs))
        return jitted(*args, **kwargs)

    return call
