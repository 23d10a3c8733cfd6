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


# XLA's optimizing passes off: most of the suite's time is compiling programs that run once
# or twice (the default run in 531 s with them off against 610 s with them on, 2026-11-28).
# Benchmarks, the documentation's numbers and users keep them. Set before JAX starts, so
# that subprocesses (the command line, the notebooks' kernels, the fleet's processes) inherit
# it; JAX_DISABLE_MOST_OPTIMIZATIONS=0 runs the suite optimized. Tests marked `optimized`
# keep the passes (pytest_runtest_protocol below).
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
# The tests marked `optimized` compile as the command line does, at LLVM's level 2 (XLA's 3
# otherwise; dtwin_jax.configure_runtime): those 12 tests in 132.7 s against 145.4 s, one core.
from dtwin_jax._compile.quick_compile import prefer_level_2  # noqa: E402

prefer_level_2()

# One persistent XLA compilation cache for the whole session, shared by the workers: tests
# build the same programs (sampler, simulators, smoothers) in many places.
import jax  # noqa: E402

PASSES_OFF = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] not in ("0", "false")
# DTWIN_TEST_IGNORE_OPTIMIZED=1: the marker `optimized` changes nothing (to measure what it saves).
IGNORE_OPTIMIZED = os.environ.get("DTWIN_TEST_IGNORE_OPTIMIZED") == "1"
jax.config.update("jax_disable_most_optimizations", PASSES_OFF)

_cache = os.environ.get("DTWIN_TEST_JAX_CACHE", os.path.join(os.path.dirname(__file__), "..", ".pytest_cache", "jax"))
os.environ["DTWIN_JAX_CACHE"] = _cache  # the command line run in-process uses the same
jax.config.update("jax_compilation_cache_dir", _cache)
# Every program, the ~2300 small op-by-op ones too: the other worker reuses them.
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


import logging  # noqa: E402

import pytest  # noqa: E402


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """A test marked ``optimized`` (its time goes into running programs, not compiling them)
    compiles with XLA's passes on, setup and teardown included (a module's fixtures are set up
    by its first test); its subprocesses too. JAX's in-memory caches ignore the flag, so a
    program compiled before keeps the passes it was compiled with."""
    if item.get_closest_marker("optimized") is None or IGNORE_OPTIMIZED:
        return (yield)
    os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "0"
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        return (yield)
    finally:
        os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1" if PASSES_OFF else "0"
        jax.config.update("jax_disable_most_optimizations", PASSES_OFF)


@pytest.fixture
def suite_passes_off() -> bool:
    """Whether the suite compiles without XLA's optimizing passes (unmarked tests)."""
    return PASSES_OFF


@pytest.fixture
def lowered_programs():
    """A list that collects ``(thread name, program name, shapes)`` for every program JAX
    lowers while the test runs, in any thread (``jax.log_compiles`` is per thread; JAX
    logs lowering at DEBUG level otherwise). A program found in JAX's caches is not lowered."""
    found = []

    class Keep(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Compiling "):
                head, shapes = message.split(" with ", 1)
                found.append((record.threadName, head.split(" ")[1], shapes))

    logger, handler, level = logging.getLogger("jax"), Keep(), logging.getLogger("jax").level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield found
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
