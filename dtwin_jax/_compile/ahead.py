"""Compilation ahead of need: the programs a later stage of an update runs, compiled in a
worker thread while the caller's earlier stages run.

A cold update is mostly XLA compilation, and much of the rest (tracing, the filters, the
chains) runs on one core; on a 2-core machine a second thread compiling the next stage's
programs fills the idle core. JAX's caches are shared across threads, so the stage's own
call then finds its programs compiled. A job that fails is ignored: the stage compiles
(and reports) for itself. JAX's thread-local settings (``with jax.default_device(...)`` and
the like) do not reach the worker; where they change a program, the worker's copy goes
unused and the stage compiles its own, as it would without the worker.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["Ahead"]


class Ahead:
    """A worker thread that runs named compile jobs in the order submitted.

    ``with Ahead() as ahead: ahead.submit("diffusion sampler", fn, *args); ...;
    ahead.wait("diffusion sampler")``: ``wait`` blocks until that job is done, so that the
    caller does not compile the same program a second time beside it. Leaving the block
    drops the jobs not started and waits for the running one. ``enabled=False``: no jobs
    (a process running :mod:`dtwin_jax._compile.aot`'s exported programs, whose stages would not use
    the programs compiled here)."""

    def __init__(self, enabled: bool = True) -> None:
        self._enabled = enabled
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dtwin-compile-ahead")
        self._jobs: dict[str, list[Future]] = {}

    def submit(self, name: str, fn: Callable, *args, **kwargs) -> None:
        """Queue ``fn(*args, **kwargs)`` under ``name`` (several jobs may share one); nothing
        when not ``enabled``."""
        if self._enabled:
            self._jobs.setdefault(name, []).append(self._pool.submit(fn, *args, **kwargs))

    def wait(self, name: str) -> None:
        """Block until the jobs named ``name`` are done; their errors are dropped (the
        stage's own call compiles the program and raises what is wrong)."""
        for job in self._jobs.pop(name, []):
            job.exception()

    def __enter__(self) -> "Ahead":
        return self

    def __exit__(self, *exc) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
