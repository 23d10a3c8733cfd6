"""Process set-up for fast runs on a small shared CPU: the command line's, and an opt-in for
Python (``dtwin_jax.configure_runtime()`` first thing in a script or notebook).

The library itself changes no process state (only x64); this function does, on request.
"""

from __future__ import annotations

import os
from pathlib import Path

from dtwin_jax.errors import DataError

__all__ = ["configure_runtime"]


def configure_runtime(cores: str | None = None, cache: str | None = None, platform: str | None = None) -> dict:
    """Set up this process before its first JAX computation.

    * A persistent XLA compilation cache (``cache``, else ``$DTWIN_JAX_CACHE``, default
      ``~/.cache/dtwin-jax/jax``; ``"off"`` disables it). A new process then skips XLA
      compilation, and :mod:`dtwin_jax._compile.aot` keeps the traced sampler, smoothers,
      prediction and output-only programs beside it, so it skips their tracing too: the output-only update
      of 300 records x 1 s, the first call in a new Python process, took 24 s with nothing
      cached and 5.8 s with the caches filled (one core; 16.8 and 5.5-5.7 s on both).
    * Threading (``cores``, else ``$DTWIN_JAX_CORES``): ``"1"`` (the default) pins the
      process to one core, ``"all"`` leaves the affinity alone. XLA sizes its CPU thread pool
      from the cores it may use when it starts and its threads spin while they wait: on this
      2-core machine a sampler chain took 0.19 s pinned against 0.20 s unpinned with the
      other core idle, and 0.38 s unpinned with it busy (``benchmarks/thread_pinning.py``).
      Compilation uses every core it may (1.8x faster on two). On a large machine or a GPU
      use ``"all"``.
    * The device (``platform``, else ``$DTWIN_JAX_PLATFORM``, default ``"auto"``): ``"cpu"``
      keeps JAX on the CPU even where an accelerator is present; ``"auto"`` lets JAX pick (a
      GPU when there is one). One window's update is a few thousand sequential sweeps of
      small matrices, which a GPU runs slower than one CPU core (example 1's warm
      input-output update: 3.4 s on an H200 against 0.94 s on one core of the same machine,
      0.34 s here); a study of thousands of chains runs ~57x one core's rate there
      (``benchmarks/accelerator.py``). The command line picks
      ``"cpu"`` for its single updates and ``"auto"`` for ``sweep``. On ``"cpu"`` the
      programs compile at LLVM's optimization level 2 instead of XLA's 3 (appended to
      ``$XLA_FLAGS`` unless it sets a level): a cold ``discover`` compiles sooner and every
      program measured runs as fast (docs/performance.md, "Compiling less").

    Pinning must come before JAX starts its CPU backend (the first computation): pinning
    every thread afterwards made a chain take 81 s. Returns what was set. Bad values raise
    :class:`~dtwin_jax.errors.DataError`.
    """
    import jax

    done = {}
    platform = platform or os.environ.get("DTWIN_JAX_PLATFORM", "auto")
    if platform not in ("cpu", "auto"):
        raise DataError(f"DTWIN_JAX_PLATFORM must be cpu or auto, got {platform!r}")
    if platform == "cpu":
        from dtwin_jax._compile.quick_compile import prefer_level_2

        jax.config.update("jax_platforms", "cpu")
        done["platform"] = "cpu"
        if prefer_level_2():
            done["xla_flags"] = os.environ["XLA_FLAGS"]
    cache = cache or os.environ.get("DTWIN_JAX_CACHE", os.path.join(Path.home(), ".cache", "dtwin-jax", "jax"))
    if cache != "off":
        from dtwin_jax._compile import aot

        jax.config.update("jax_compilation_cache_dir", cache)
        aot.enable(os.path.join(cache, "dtwin-export"))
        # Every program: a discover compiles ~40 small ones (0.6 s together) besides the big ones.
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        done["compilation_cache"] = cache
    cores = cores or os.environ.get("DTWIN_JAX_CORES", "1")
    if cores not in ("1", "all"):
        raise DataError(f"DTWIN_JAX_CORES must be 1 or all, got {cores!r}")
    if cores == "1" and hasattr(os, "sched_setaffinity"):
        allowed = sorted(os.sched_getaffinity(0))
        if len(allowed) > 1:
            os.sched_setaffinity(0, {allowed[0]})
        done["cores"] = [allowed[0]]
    return done
