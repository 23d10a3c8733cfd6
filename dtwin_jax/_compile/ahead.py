"""Compilation ahead of need: the programs a later stage of an update runs, compiled in a
worker thread while the caller's earlier stages run.

A cold update is mostly XLA compilation, and much of the rest (tracing, the filters, the
chains) runs on one core; on a 2-core machine a second thread compiling the next stage's
programs fills the idle core. JAX's caches are shared across threads, and a call of a
program that the worker is compiling waits for it instead of compiling it again, so the
stage's own call finds its program compiled. A job that fails is ignored: the stage compiles
(and reports) for itself. JAX's thread-local settings (``with jax.default_device(...)`` and
the like) do not reach the worker; where they change a program, the worker's copy goes
unused and the stage compiles its own, as it would without the worker.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from dtwin_jax._compile import aot

__all__ = ["Ahead"]


class Ahead:
    """A worker thread that runs compile jobs in the order submitted:
    ``with Ahead() as ahead: ahead.submit(fn, *args); ...``. Leaving the block drops the
    jobs not started and waits for the running one. A process that runs exported programs
    (:mod:`dtwin_jax._compile.aot`, the command line) runs no jobs: its stages would not use
    the programs compiled here."""

    def __init__(self) -> None:
        self._enabled = not aot.enabled()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dtwin-compile-ahead")

    def submit(self, fn: Callable, *args, **kwargs) -> None:
        """Queue ``fn(*args, **kwargs)``; its errors are dropped (the stage's own call
        compiles the program and raises what is wrong)."""
        if self._enabled:
            self._pool.submit(fn, *args, **kwargs)

    def __enter__(self) -> "Ahead":
        return self

    def __exit__(self, *exc) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
