"""Programs that run once per call for microseconds to milliseconds (a sampler's set-up, its
per-sweep keys, the output-only first guesses) compile without LLVM's optimizations: about
half the compilation, the same bits out in the cases measured, and a longer run that at
their size nobody sees. Long-running programs (the sampler's chunks, the filters,
simulations) keep LLVM's optimizations: at level 0 they run several times longer. In a
process that `dtwin_jax.configure_runtime` sets up for the CPU they compile at level 2
instead of XLA's 3 (`prefer_level_2`): sooner, and every program measured runs as fast.
The measurements are in `docs/performance.md` ("Compiling less")."""

from __future__ import annotations

import functools
import os

import jax

__all__ = ["LEVEL_2", "QUICK_COMPILE", "prefer_level_2", "quick_jit"]

QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def quick_jit(static_argnums=()):
    """`jax.jit` with `QUICK_COMPILE` for a call from Python; inside another trace
    (an export by `dtwin_jax._compile.aot`, a caller's jit or vmap) the plain function, which
    that trace's program holds (JAX takes compiler options on top-level programs only).

    **Arguments:**

    - `static_argnums`: the positions of the static arguments, as for `jax.jit`.

    **Returns:** the decorator.
    """

    def wrap(fun):
        compiled = jax.jit(fun, static_argnums=static_argnums, compiler_options=QUICK_COMPILE)

        @functools.wraps(fun)
        def call(*args):
            traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(args))
            return (fun if traced else compiled)(*args)

        return call

    return wrap


LEVEL_2 = "--xla_backend_optimization_level=2"


def prefer_level_2() -> bool:
    """Append `LEVEL_2` to `$XLA_FLAGS` unless it sets a level already (the user's
    choice stands). XLA reads the variable at its first compilation, and JAX keys the
    persistent cache on it. Returns whether the flag was added."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {LEVEL_2}".strip()
    return True
