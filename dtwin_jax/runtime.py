"""Process set-up for fast runs on a small shared CPU: the command line's, and an opt-in for
Python (`dtwin_jax.configure_runtime()` first thing in a script or notebook).

The library itself changes no process state (only x64); this function does, on request.
"""

from __future__ import annotations

import os
from pathlib import Path

from dtwin_jax.errors import DataError

__all__ = ["configure_runtime"]


def configure_runtime(cores: str | None = None, cache: str | None = None, platform: str | None = None) -> dict:
    """Set up this process before its first JAX computation.

    * A persistent XLA compilation cache (`cache`). A new process then skips XLA compilation,
      and `dtwin_jax._compile.aot` keeps the traced sampler, smoothers, prediction and
      output-only programs beside it, so it skips their tracing too: the first output-only
      update in a new Python process takes a fraction of its cold time once the caches are filled.
    * Threading (`cores`). XLA sizes its CPU thread pool from the cores it may use when it
      starts and its threads spin while they wait: pinned, a sampler chain runs as fast as
      unpinned with the other cores idle, and much faster than unpinned with them busy
      (`benchmarks/thread_pinning.py`). Compilation uses every core it may. On a large machine
      or a GPU use `"all"`.
    * The device (`platform`). One window's update is a few thousand sequential sweeps of small
      matrices, which a GPU runs slower than one CPU core; a study of thousands of chains runs
      many times one core's rate there (`benchmarks/accelerator.py`). The command line picks
      `"cpu"` for its single updates and `"auto"` for `sweep`. On `"cpu"` the programs compile
      at LLVM's optimization level 2 instead of XLA's 3 (appended to `$XLA_FLAGS` unless it sets
      a level): a cold `discover` compiles sooner and every program measured runs as fast
      (docs/performance.md, "Compiling less").

    Pinning must come before JAX starts its CPU backend (the first computation): pinning
    every thread afterwards makes a chain far slower.

    **Arguments:**

    - `cores`: `"1"` pins the process to one core, `"all"` leaves the affinity alone; None
      (default) reads `$DTWIN_JAX_CORES`, else `"1"`.
    - `cache`: the compilation cache's directory, or `"off"` to disable it; None (default) reads
      `$DTWIN_JAX_CACHE`, else `~/.cache/dtwin-jax/jax`.
    - `platform`: `"cpu"` keeps JAX on the CPU even where an accelerator is present, `"auto"`
      lets JAX pick (a GPU when there is one); None (default) reads `$DTWIN_JAX_PLATFORM`, else
      `"auto"`.

    **Returns:** what was set, a dict with the keys among `"platform"`, `"xla_flags"`,
    `"compilation_cache"` and `"cores"` (the list of the one core pinned to).

    Bad values raise `DataError`.
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
