"""A twin folder's layout on disk (`dtwin_jax.io.store`): its lock, the names a save
writes (and may therefore remove), the check of a destination before any work, and reads
that follow no link and stop at 1 GiB."""

from __future__ import annotations

import fcntl
import json
import os
import re
import stat
import threading
from contextlib import contextmanager
from pathlib import Path

from dtwin_jax.errors import DataError

__all__ = ["FORMAT", "locked", "check_target"]

FORMAT = "dtwin-jax twin"
CONTENT = ("header.json", "nominal.toml", "posterior.nc", "statistics.npz", "result.json")
V1_FILES = ("twin.json", "nominal.toml", "posterior.nc", "statistics.npz", "result.json")
_LOCK = ".lock"
VERSION_DIR = re.compile(r"v(\d{6})")
_TMP_DIR = re.compile(r"\.v\d{6}\.tmp-[a-z0-9_]+")  # tempfile.mkdtemp's random part
_TMP_POINTER = re.compile(r"\.twin\.json\.tmp-[a-z0-9_]+")
_MAX_BYTES = 1 << 30  # a twin file larger than this is not one we wrote
_held = threading.local()  # this thread's held locks: realpath -> depth (re-entrant)


def umask() -> int:
    """The process's umask: written files get `0o666 & ~umask()` (tempfile makes 0600).
    Linux reports it in /proc; elsewhere it can only be read by setting it (to 022 for that
    instant, not 0, so that another thread's file is never made world-writable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def locked(path, *, create: bool = False, on_wait=None):
    """Hold the exclusive lock of the twin folder `path` (`fcntl.flock` on `path/.lock`)
    while the `with` block runs: other processes' saves and command-line updates wait.
    Re-entrant within a thread.

    **Arguments:**

    - `path`: the twin folder; it must hold a twin unless `create`.
    - `create`: make the folder (and its parents) if absent, and accept one that holds no
      twin yet (default False).
    - `on_wait`: called with no arguments once, before waiting for another holder; None
      (default) to wait silently.

    **Returns:** a context manager yielding `Path(path)`.
    """
    path = Path(path)
    key = os.path.realpath(path)
    held = _held.__dict__.setdefault("paths", {})
    if held.get(key):
        held[key] += 1
        try:
            yield path
        finally:
            held[key] -= 1
        return
    if create:
        path.mkdir(parents=True, exist_ok=True)
    elif not (path / "twin.json").is_file():
        what = "does not exist" if not path.exists() else "is not a twin folder (no twin.json)"
        raise DataError(f"twin '{path}' {what}")
    try:
        fd = os.open(path / _LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    except OSError as e:
        raise DataError(f"cannot lock twin '{path}': {e.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(fd, fcntl.LOCK_EX)
        held[key] = 1
        yield path
    finally:
        held.pop(key, None)
        os.close(fd)  # releases the lock


def check_target(path, *, force: bool = False) -> Path:
    """Refuse a twin destination before any work is done: `path` must be absent, an empty
    folder (or one holding only a killed save's leftovers), or a twin of ours when `force`
    (or, for a re-update, the twin it continues), inside a writable folder.

    **Arguments:**

    - `path`: the twin folder to be written.
    - `force`: accept an existing twin (`discover --save-twin --force`).

    **Returns:** `Path(path)`; raises a one-line `DataError`.
    """
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise DataError(f"twin folder '{path}' exists and is not a folder")
    if path.is_dir():
        if _is_twin(path):
            if not force:
                raise DataError(f"'{path}' already holds a twin; pass --force to replace it (its history is discarded)")
        else:
            foreign = sorted(e for e in os.listdir(path) if not _leftover(path, e))
            if foreign:
                raise DataError(f"'{path}' is not empty and not a dtwin-jax twin (it holds '{foreign[0]}'); "
                                "not writing a twin into it")
    parent = path
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK | os.X_OK):
        raise DataError(f"cannot write twin '{path}': '{parent}' is not a writable folder")
    return path


def _is_twin(path: Path) -> bool:
    """Whether `path` holds a `twin.json` of ours; one that is not is refused."""
    pointer = path / "twin.json"
    if not os.path.lexists(pointer):
        return False
    head = read_json(pointer)
    if not isinstance(head, dict) or head.get("format") != FORMAT or head.get("version") not in (1, 2):
        raise DataError(f"'{pointer}' is not a dtwin-jax twin; not writing over it")
    return True


def _leftover(path: Path, entry: str) -> bool:
    """Whether `path/entry` is ours to clean: the lock, a killed save's temporary pointer,
    or a version or temporary folder holding only our file names."""
    p = path / entry
    if entry == _LOCK or _TMP_POINTER.fullmatch(entry):
        return not p.is_symlink() and p.is_file()
    if _TMP_DIR.fullmatch(entry) or VERSION_DIR.fullmatch(entry):
        return not p.is_symlink() and p.is_dir() and all(_ours(e) for e in os.listdir(p))
    return False


def _ours(name: str) -> bool:
    """A file name a save writes into a version folder (or a writer's temporary beside one)."""
    return name in CONTENT or any(name.startswith(f".{c}.") for c in CONTENT)


def clean(path: Path, keep: str | None) -> None:
    """Remove a killed save's leftovers and version folders other than `keep`.

    Only our file names are removed, and a folder only when that leaves it empty; links are
    left alone.

    **Arguments:**

    - `path`: the twin folder.
    - `keep`: the name of the version folder to keep (e.g. `"v000003"`), or None to keep none.
    """
    for entry in os.listdir(path):
        p = path / entry
        if p.is_symlink():
            continue
        if _TMP_POINTER.fullmatch(entry) and p.is_file():
            os.unlink(p)
        elif (_TMP_DIR.fullmatch(entry) or (VERSION_DIR.fullmatch(entry) and entry != keep)) and p.is_dir():
            remove_ours(p, None, rmdir=True)


def remove_ours(folder: Path, names, *, rmdir: bool) -> None:
    """Remove our files from a folder, then the folder if asked and it is empty.

    Never removes a folder inside it: whatever else it holds stays.

    **Arguments:**

    - `folder`: the folder.
    - `names`: the file names to remove, or None for every name of `_ours` (a save's content
      files and their writers' temporaries).
    - `rmdir`: also remove `folder` when that leaves it empty.
    """
    for name in (names if names is not None else [e for e in os.listdir(folder) if _ours(e)]):
        p = folder / name
        if os.path.lexists(p) and not p.is_dir():
            os.unlink(p)
    if rmdir:
        try:
            os.rmdir(folder)
        except OSError:
            pass  # holds something we did not write


def sync_dir(path: Path) -> None:
    """Flush a folder's entries to disk (`fsync` of the folder), so that a rename survives a crash.

    **Arguments:**

    - `path`: the folder.
    """
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_bytes(path: Path) -> bytes:
    """A regular file's bytes (no link, FIFO or device; at most 1 GiB).

    Raises `FileNotFoundError` when it is absent, and a one-line `DataError` when it cannot be
    opened or is not a regular file of at most 1 GiB.

    **Arguments:**

    - `path`: the file.

    **Returns:** its content.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise
    except OSError as e:
        raise DataError(f"cannot read '{path}': {e.strerror}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_BYTES:
            raise DataError(f"'{path}' is not a regular file of at most 1 GiB")
        return f.read(_MAX_BYTES + 1)


def read_json(path: Path):
    """A JSON file's parsed content, read as `read_bytes` reads it.

    Raises a one-line `DataError` when it is absent, not a regular file or not valid JSON.

    **Arguments:**

    - `path`: the file.

    **Returns:** the parsed JSON value (any type: callers check it is an object).
    """
    try:
        data = read_bytes(path)
    except FileNotFoundError:
        raise DataError(f"'{path}' does not exist") from None
    try:
        return json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"'{path}' is not valid JSON: {e}") from None
