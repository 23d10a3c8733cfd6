"""Traced programs kept on disk for new processes (the command line).

JAX's persistent compilation cache lets a new process skip XLA compilation, not tracing and
lowering: for a cold `dtwin-jax discover` of a 1 s window those are a large part of its
time (the kinematic smoother's Newton noise fit, the sampler; `docs/performance.md`).
`call` runs a jitted function through a serialized `jax.export` of it, kept in a folder
that `enable` names
(`dtwin_jax.configure_runtime` names one beside its compilation cache, so the command
line and the processes that opt in use it) and keyed by the function's name, the shapes and
dtypes of its arguments, its static arguments, the platform it runs on (a program exported
for the CPU fails on a GPU), the jax version and a digest of dtwin-jax's source. Otherwise,
or inside another trace, it is a plain call: within one process an export only costs a
second lowering, which is why it is off unless a process opts in (the command line does).
Programs with host callbacks (progress bars) cannot be exported, so equinox's run-time checks
(`eqx.error_if`, in diffrax's solves) are traced for an export as NaN outputs instead of
raised errors (callers of such programs already treat a non-finite result as a failure). A
program that still holds a callback (one whose inner programs this process traced before
with the checks on) runs as a plain call in this process.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import jax

__all__ = ["call", "enable", "enabled", "exported"]

# key -> jitted call of the exported program, so that a process traces each one once
_LOADED: dict[str, Callable] = {}
# _LOADED's value for a program that cannot be exported: a plain call.
_PLAIN = object()
# the folder of exported programs; None: plain calls (the library's default)
_folder: Path | None = None


def enable(folder: str | os.PathLike | None) -> None:
    """Keep exported programs in a folder. Process set-up, as the compilation cache is:
    `dtwin_jax.configure_runtime` calls it.

    **Arguments:**

    - `folder`: the folder of the exported programs, or None to stop using one.
    """
    global _folder
    _folder = None if folder is None else Path(folder)


def enabled() -> bool:
    """Whether `call` runs exported programs (a folder is set)."""
    return _folder is not None


def exported(name: str, static_argnums: tuple[int, ...] = ()) -> Callable:
    """Decorate a jitted function so that its calls run through `call` under a name.

    **Arguments:**

    - `name`: the program's name in the folder's keys.
    - `static_argnums`: the positions of the static arguments (hashable; their `repr` is
      part of the key).

    **Returns:** the decorator.
    """

    def wrap(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def run(*args):
            static = tuple(args[i] for i in static_argnums)
            dynamic = tuple(a for i, a in enumerate(args) if i not in static_argnums)

            def bound(*values):
                it = iter(values)
                return fn(*(args[i] if i in static_argnums else next(it) for i in range(len(args))))

            return call(name, bound, dynamic, static)

        return run

    return wrap


def call(name: str, fn: Callable, args: tuple, static: tuple = ()):
    """`fn(*args)` through a disk-cached export (a plain call when no folder is set or inside
    another trace).

    **Arguments:**

    - `name`: the program's name in the folder's keys.
    - `fn`: the function; it returns a pytree of arrays and of the package's NamedTuples
      (`_register`).
    - `args`: a tuple pytree of arrays (its structure is part of the key).
    - `static`: hashable values that change the program (their `repr` is part of the key).

    **Returns:** what `fn(*args)` returns.
    """
    leaves, tree = jax.tree.flatten(args)
    folder = _folder
    if folder is None or any(isinstance(a, jax.core.Tracer) for a in leaves):
        return fn(*args)  # inside another trace (vmap, jit) the caller's program holds it
    path = _path(folder, name, static, tree, leaves)
    key = path.stem
    run = _LOADED.get(key)
    if run is None:
        run = _load_or_export(path, fn, tree, leaves)
        _LOADED[key] = run
    return fn(*args) if run is _PLAIN else run(*leaves)


@functools.cache
def _register() -> None:
    """The NamedTuples that exported programs return, by name, so that an export holds its
    output's structure (called once, before the first export or load)."""
    from jax import export

    from dtwin_jax.output_only.statespace import Linearization
    from dtwin_jax.sampler.kernel import GibbsState, GibbsTrace, SuffStats

    for t in (SuffStats, GibbsState, GibbsTrace, Linearization):
        export.register_namedtuple_serialization(t, serialized_name=f"dtwin_jax.{t.__name__}")


def _path(folder: Path, name: str, static: tuple, tree, leaves) -> Path:
    from jax import export

    spec = "|".join([name, repr(static), str(tree), export.default_export_platform(), jax.__version__,
                     _source_digest()] + [f"{jax.typeof(a)}" for a in leaves])
    return folder / f"{name}-{hashlib.sha256(spec.encode()).hexdigest()[:32]}.bin"


@functools.cache
def _source_digest() -> str:
    """A digest of the package's own source: an edited dtwin-jax never runs a program
    exported from the code before the edit (a version number would not change with it)."""
    h = hashlib.sha256()
    package = Path(__file__).resolve().parents[1]  # dtwin_jax/, this module in dtwin_jax/_compile/
    for path in sorted(package.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()


@contextlib.contextmanager
def _checks_as_nan():
    """Equinox's run-time checks traced as NaN outputs instead of host callbacks, which
    `jax.export` cannot serialize. Inner programs traced meanwhile keep that form for the
    rest of the process (JAX's trace cache ignores the setting): a failed check there gives
    NaN, not an exception."""
    from equinox import _errors

    before, _errors.EQX_ON_ERROR = _errors.EQX_ON_ERROR, "nan"
    try:
        yield
    finally:
        _errors.EQX_ON_ERROR = before


def _load_or_export(path: Path, fn: Callable, tree, leaves) -> Callable:
    from jax import export

    _register()
    if path.is_file():
        try:
            loaded = export.deserialize(bytearray(path.read_bytes()))
            if export.default_export_platform() in loaded.platforms:
                return jax.jit(loaded.call)
        except Exception:  # a partial or foreign file: export it again
            pass

    def flat(*xs):
        return fn(*jax.tree.unflatten(tree, xs))

    try:
        with _checks_as_nan():
            exported = export.export(jax.jit(flat))(*leaves)
    except NotImplementedError:  # "serialization of host_callbacks is not yet implemented"
        return _PLAIN
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "wb") as f:
        f.write(exported.serialize())
    os.replace(tmp, path)  # whole or not at all: readers never see a partial file
    return jax.jit(exported.call)
