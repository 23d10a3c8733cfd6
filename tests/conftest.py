"""Test-session set-up: each pytest-xdist worker runs on a core of its own.

XLA's CPU thread pool spins while it waits; two processes sharing both cores slow each
other down (one sampler chain ran 2.7x faster pinned to one core). With ``-n 2`` on a
2-core machine, worker ``gwN`` is pinned to core ``N mod cores`` before JAX starts.
"""

import os

_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if _worker.startswith("gw") and hasattr(os, "sched_setaffinity"):
    _cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {_cores[int(_worker[2:]) % len(_cores)]})

# The two workers compile many of the same programs (the sampler at each problem shape, the
# zoo's pilot simulations, example 1's updates); a compilation cache shared on disk for the
# session lets the second compile of a program be a load.
import tempfile  # noqa: E402

import jax  # noqa: E402

# PYTEST_XDIST_TESTRUNUID: one id shared by the workers of this run.
_run = os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid()))
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), f"dtwin-jax-cache-{_run}"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
