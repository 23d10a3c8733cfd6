"""Programs that run once per call for microseconds to milliseconds (a sampler's set-up, its
per-sweep keys, the output-only first guesses) compile without LLVM's optimizations: about
half the compilation, the same bits out in the cases measured, and runs 1.5x longer, which
at their size nobody sees (docs/performance.md, compiling less). Long-running programs (the
sampler's chunks, the filters, simulations) keep XLA's defaults: at level 0 they run 2-10x
longer."""

from __future__ import annotations

import functools

import jax

__all__ = ["QUICK_COMPILE", "quick_jit"]

QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def quick_jit(static_argnums=()):
    """``jax.jit`` with :data:`QUICK_COMPILE` for a call from Python; inside another trace
    (an export by :mod:`dtwin_jax._compile.aot`, a caller's jit or vmap) the plain function, which
    that trace's program holds (JAX takes compiler options on top-level programs only)."""

    def wrap(fun):
        compiled = jax.jit(fun, static_argnums=static_argnums, compiler_options=QUICK_COMPILE)

        @functools.wraps(fun)
        def call(*args):
            traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(args))
            return (fun if traced else compiled)(*args)

        return call

    return wrap
