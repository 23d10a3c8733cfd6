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


# One persistent XLA compilation cache for the whole session, shared by the workers: tests
# build the same programs (sampler, simulators, smoothers) in many places.
import jax  # noqa: E402

_cache = os.environ.get("DTWIN_TEST_JAX_CACHE", os.path.join(os.path.dirname(__file__), "..", ".pytest_cache", "jax"))
os.environ["DTWIN_JAX_CACHE"] = _cache  # the command line run in-process uses the same
jax.config.update("jax_compilation_cache_dir", _cache)
# Every program, the ~2300 small op-by-op ones too: the other worker reuses them.
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
