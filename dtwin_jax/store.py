"""A twin on disk: save, load, re-update (formats.md, "Saving a twin and predicting with it").

A twin folder ``TWIN_DIR`` holds, format version 2:

* ``twin.json``: the manifest and pointer, ``{"format": "dtwin-jax twin", "version": 2,
  "revision": 3, "current": "v000003", "files": {"header.json": "<sha256>", ...}}``;
* ``v000003/``: the content of that revision, never changed once written:

  * ``header.json``: ``format``, ``version``, ``mode``, state and input names, the library
    specs, each equation's state, kind and term names, sampler settings, PIP threshold,
    preprocessing, checks, the ``history`` of updates (time, data size, prior, discovered
    equations, the window's fingerprint, package version) and the output-error
    ``refinement`` (or null);
  * ``nominal.toml``: the nominal model (the nominal file of formats.md);
  * ``posterior.nc``: every equation's draws as an arviz DataTree (netCDF, group
    ``posterior``: ``theta_<state>_<kind>``, ``gamma_...``, ``sigma2_...``);
  * ``statistics.npz``: the sufficient statistics the sampler saw (``<kind>_gram``,
    ``_xty``, ``_yty``, ``_n``), so that a re-update can use the posterior as its prior;
  * ``result.json``: the result file of formats.md for the last update;

* ``.lock``: the lock file (never deleted).

Guarantees (a twin travels between users and is untrusted):

* Atomic: a save writes a new version folder in full (files synced), renames it into place,
  replaces ``twin.json`` (``os.replace``), then removes the previous version. At every
  instant the twin loads, with the old history or the new; leftovers of a killed save are
  removed by the next save.
* Nothing it did not write is deleted: only our file names are removed and a folder only
  when that leaves it empty; a folder that is neither empty nor a twin is refused, and a
  save over a twin must continue its history (or be asked to replace it).
* Locked: :func:`locked` holds ``fcntl.flock`` on ``.lock``; :func:`save_twin` takes it,
  and the command line holds it through read, update and write, so concurrent updates
  queue instead of losing one.
* Checksummed and checked: :func:`load_twin` verifies every file's SHA-256 against the
  manifest, then reads it defensively (:mod:`dtwin_jax.twin_files`: no netCDF reader, no
  pickles, every field, shape and dtype checked); any failure is one line naming the file.
* Files get the user's umask (0644 and 0755 under umask 022).

Version 1 (``twin.json`` the header, the other files beside it) is still read; the next
save migrates it, removing only the five file names version 1 wrote.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import stat
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dtwin_jax import sampler, twin_files
from dtwin_jax.errors import DataError
from dtwin_jax.io import json_safe, load_nominal, write_nominal
from dtwin_jax.library import parse_library
from dtwin_jax.posterior import EquationPosterior

__all__ = ["FORMAT", "VERSION", "save_twin", "load_twin", "locked", "check_target", "twin_revision"]

FORMAT = "dtwin-jax twin"
VERSION = 2
_CONTENT = ("header.json", "nominal.toml", "posterior.nc", "statistics.npz", "result.json")
_V1_FILES = ("twin.json", "nominal.toml", "posterior.nc", "statistics.npz", "result.json")
_LOCK = ".lock"
_VERSION_DIR = re.compile(r"v(\d{6})")
_TMP_DIR = re.compile(r"\.v\d{6}\.tmp-[a-z0-9_]+")  # tempfile.mkdtemp's random part
_TMP_POINTER = re.compile(r"\.twin\.json\.tmp-[a-z0-9_]+")
_MAX_BYTES = 1 << 30  # a twin file larger than this is not one we wrote
_LOAD_TRIES = 5

# Test hook: called with each step's name ("files", "folder", "pointer", "cleanup") of a save.
_AFTER_STEP = None
_held = threading.local()  # this thread's held locks: realpath -> depth (re-entrant)


def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old


@contextmanager
def locked(path, *, create: bool = False, on_wait=None):
    """Hold the exclusive lock of the twin folder ``path`` (``fcntl.flock`` on ``path/.lock``)
    while the ``with`` block runs: other processes' saves and command-line updates wait.
    Re-entrant within a thread.

    **Arguments:**

    - ``path``: the twin folder; it must hold a twin unless ``create`` (then it is made).
    - ``on_wait``: called with no arguments once, before waiting for another holder.

    **Returns:** a context manager yielding ``Path(path)``.
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
        raise DataError(f"twin '{path}' {'does not exist' if not path.exists() else 'is not a twin folder (no twin.json)'}")
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
    """Refuse a twin destination before any work is done: ``path`` must be absent, an empty
    folder (or one holding only a killed save's leftovers), or a twin of ours when ``force``
    (or, for a re-update, the twin it continues), inside a writable folder.

    **Arguments:**

    - ``path``: the twin folder to be written.
    - ``force``: accept an existing twin (``discover --save-twin --force``).

    **Returns:** ``Path(path)``; raises a one-line :class:`DataError`.
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
    """Whether ``path`` holds a ``twin.json`` of ours; one that is not is refused."""
    pointer = path / "twin.json"
    if not os.path.lexists(pointer):
        return False
    head = _read_json(pointer)
    if not isinstance(head, dict) or head.get("format") != FORMAT or head.get("version") not in (1, 2):
        raise DataError(f"'{pointer}' is not a dtwin-jax twin; not writing over it")
    return True


def _leftover(path: Path, entry: str) -> bool:
    """Whether ``path/entry`` is ours to clean: the lock, a killed save's temporary pointer,
    or a version or temporary folder holding only our file names."""
    p = path / entry
    if entry == _LOCK or _TMP_POINTER.fullmatch(entry):
        return not p.is_symlink() and p.is_file()
    if _TMP_DIR.fullmatch(entry) or _VERSION_DIR.fullmatch(entry):
        return not p.is_symlink() and p.is_dir() and all(_ours(e) for e in os.listdir(p))
    return False


def _ours(name: str) -> bool:
    """A file name a save writes into a version folder (or a writer's temporary beside one)."""
    return name in _CONTENT or any(name.startswith(f".{c}.") for c in _CONTENT)


def twin_revision(path) -> int:
    """The revision of the twin at ``path`` (0 for a version-1 twin); :func:`load_twin`
    records it on its result as ``twin_revision``."""
    head = _read_json(Path(path) / "twin.json")
    return int(head.get("revision", 0)) if isinstance(head, dict) else 0


def save_twin(result, path, *, expect_revision: int | None = None, replace: bool = False) -> Path:
    """Write the :class:`~dtwin_jax.update.UpdateResult` ``result`` as the twin folder ``path``.

    **Arguments:**

    - ``result``: the update to save.
    - ``path``: absent, an empty folder, or a twin. A twin is updated only if ``result``
      continues its history (a re-update of it, or the same twin), so an update saved
      meanwhile by someone else is never silently lost; ``replace=True`` replaces any twin.
      Files that are not the twin's are left alone.
    - ``expect_revision``: refuse unless the twin at ``path`` is still at this revision (the
      ``twin_revision`` of the result :func:`load_twin` returned).

    **Returns:** ``Path(path)``. Raises a one-line :class:`DataError`.
    """
    path = Path(path)
    lib = result.library
    if parse_library(lib.spec, lib.num_states, lib.num_inputs).names != lib.names:
        raise DataError(f"the library is not described by its spec '{lib.spec}' (a subset?); cannot save it")
    check_target(path, force=True)
    with locked(path, create=True):
        check_target(path, force=True)  # again under the lock
        version, revision, current = _current(path, replace)
        if version and expect_revision is not None and revision != expect_revision:
            raise DataError(f"twin '{path}' is at revision {revision}, not {expect_revision}: "
                            "it was saved meanwhile; load it again and re-update")
        history = [] if replace or not version else _history(path, current)
        if version and not replace and _normal(history) != _normal(result.history)[:len(history)]:
            raise DataError(f"twin '{path}' holds updates this result does not continue (saved meanwhile, or "
                            "another twin): load it again and re-update, or replace it (--force)")
        _clean(path, keep=current)
        used = [int(m.group(1)) for e in os.listdir(path) if (m := _VERSION_DIR.fullmatch(e))]
        new = f"v{max([revision] + used) + 1:06d}"
        mode = 0o666 & ~_umask()
        tmp = Path(tempfile.mkdtemp(dir=path, prefix=f".{new}.tmp-"))
        os.chmod(tmp, 0o777 & ~_umask())
        digests = _write_content(tmp, result, mode)
        _step("files")
        os.rename(tmp, path / new)
        _sync_dir(path)
        _step("folder")
        manifest = {"format": FORMAT, "version": VERSION, "revision": int(new[1:]), "current": new, "files": digests}
        fd, ptr = tempfile.mkstemp(dir=path, prefix=".twin.json.tmp-")
        with os.fdopen(fd, "w") as f:
            os.fchmod(f.fileno(), mode)
            f.write(json.dumps(manifest, indent=2) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(ptr, path / "twin.json")
        _sync_dir(path)
        _step("pointer")
        if version == 1:
            _remove_ours(path, _V1_FILES[1:], rmdir=False)
        _clean(path, keep=new)
        _step("cleanup")
    return path


def _step(name: str) -> None:
    if _AFTER_STEP is not None:
        _AFTER_STEP(name)


def _normal(history) -> list:
    """``history`` as it reads back from JSON, for comparison."""
    return json.loads(json.dumps(json_safe(list(history))))


def _write_content(folder: Path, result, mode: int) -> dict:
    """Write the five content files into ``folder``, synced, mode ``mode``; their SHA-256."""
    _write_text(folder / "header.json", json.dumps(json_safe(_header(result)), indent=2, allow_nan=False) + "\n")
    write_nominal(folder / "nominal.toml", result.nominal)
    result.to_arviz().to_netcdf(folder / "posterior.nc", engine="h5netcdf")
    arrays = {f"{kind}_{name}": np.asarray(a, dtype=np.float64) for kind, st in result.statistics.items()
              for name, a in zip(sampler.SuffStats._fields, st)}
    with open(folder / "statistics.npz", "wb") as f:
        np.savez(f, **arrays)
    _write_text(folder / "result.json", json.dumps(json_safe(result.to_json()), indent=2, allow_nan=False) + "\n")
    digests = {}
    for name in _CONTENT:
        with open(folder / name, "rb") as f:
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
            digests[name] = twin_files.sha256(f.read())
    return digests


def _write_text(path: Path, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)


def _sync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove_ours(folder: Path, names, *, rmdir: bool) -> None:
    """Remove the files ``names`` of ``folder`` (all of :func:`_ours` when None; never a
    folder), then the folder if ``rmdir`` and it is empty: whatever else it holds stays."""
    for name in (names if names is not None else [e for e in os.listdir(folder) if _ours(e)]):
        p = folder / name
        if os.path.lexists(p) and not p.is_dir():
            os.unlink(p)
    if rmdir:
        try:
            os.rmdir(folder)
        except OSError:
            pass  # holds something we did not write


def _clean(path: Path, keep: str | None) -> None:
    """Remove a killed save's leftovers and version folders other than ``keep``."""
    for entry in os.listdir(path):
        p = path / entry
        if p.is_symlink():
            continue
        if _TMP_POINTER.fullmatch(entry) and p.is_file():
            os.unlink(p)
        elif (_TMP_DIR.fullmatch(entry) or (_VERSION_DIR.fullmatch(entry) and entry != keep)) and p.is_dir():
            _remove_ours(p, None, rmdir=True)


def _current(path: Path, replace: bool):
    """``(version, revision, current folder name)`` of the twin at ``path``, ``(0, 0, None)``
    when it holds none; a damaged manifest counts as none when it is to be replaced."""
    if not os.path.lexists(path / "twin.json"):
        return 0, 0, None
    manifest = _read_json(path / "twin.json")
    if manifest.get("version") == 1:
        return 1, 0, None
    try:
        return 2, *_check_manifest(manifest, path / "twin.json")
    except DataError:
        if replace:
            return 2, 0, None
        raise


def _history(path: Path, current: str | None) -> list:
    head = _read_json(path / current / "header.json" if current else path / "twin.json")
    history = head.get("history") if isinstance(head, dict) else None
    if not isinstance(history, list):
        raise DataError(f"twin '{path}' has no readable history; replace it (--force) or remove it")
    return history


def _check_manifest(manifest: dict, name: Path) -> tuple[int, str]:
    revision, current, files = manifest.get("revision"), manifest.get("current"), manifest.get("files")
    if not isinstance(revision, int) or isinstance(revision, bool) or not 1 <= revision <= 999999 \
            or current != f"v{revision:06d}":
        raise DataError(f"'{name}' names no valid revision (revision {revision!r}, current {current!r})")
    if not isinstance(files, dict) or set(files) != set(_CONTENT) or not all(
            isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) for v in files.values()):
        raise DataError(f"'{name}': field 'files' must give the SHA-256 of {', '.join(_CONTENT)}")
    return revision, current


def _read_bytes(path: Path) -> bytes:
    """A regular file's bytes (no link, FIFO or device; at most 1 GiB)."""
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


def _read_json(path: Path):
    try:
        data = _read_bytes(path)
    except FileNotFoundError:
        raise DataError(f"'{path}' does not exist") from None
    try:
        return json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"'{path}' is not valid JSON: {e}") from None


def _header(result) -> dict:
    s = result.settings
    return {
        "format": FORMAT,
        "version": VERSION,
        "mode": result.mode,
        "state_names": list(result.state_names),
        "input_names": list(result.input_names),
        "library": result.library.spec,
        "num_inputs": int(result.library.num_inputs),
        "diffusion_library": result.preprocessing.get("diffusion_library"),
        "equations": [{"state": e.state, "kind": e.kind, "terms": list(e.names)} for e in result.equations],
        "pip_threshold": result.pip_threshold,
        "settings": {
            "num_chains": s.num_chains, "num_draws": s.num_draws, "num_burnin": s.num_burnin,
            "prior": s.prior._asdict(), "p0": s.p0, "v_s": s.v_s, "max_active": s.max_active,
        },
        "seconds": result.seconds,
        "preprocessing": result.preprocessing,
        "checks": result.checks,
        "history": result.history,
        "refinement": result.refinement,
    }


def _read_files(path: Path):
    """``(version, revision, folder, {name: bytes})`` of the twin at ``path``, checksums
    verified. Retried when a save replaces the twin while it is read (no lock needed)."""
    pointer = path / "twin.json"
    for _ in range(_LOAD_TRIES):
        manifest = _read_json(pointer)
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            got = manifest.get("format") if isinstance(manifest, dict) else None
            raise DataError(f"'{pointer}' is not a dtwin-jax twin (format {got!r})")
        if manifest.get("version") not in (1, VERSION):
            raise DataError(f"twin '{path}' has format version {manifest.get('version')!r}; "
                            f"this dtwin-jax reads 1 and {VERSION}")
        if manifest["version"] == 1:
            folder, names, revision = path, _V1_FILES, 0
        else:
            revision, current = _check_manifest(manifest, pointer)
            folder, names = path / current, _CONTENT
            if folder.is_symlink() or not folder.is_dir():
                raise DataError(f"twin '{path}': '{folder}' is not a folder")
        try:
            blobs = {name: _read_bytes(folder / name) for name in names}
        except FileNotFoundError as e:
            if _read_json(pointer) != manifest:
                continue  # a save moved the twin on meanwhile: read the new revision
            raise DataError(f"twin '{path}' is not complete (no {Path(e.filename).name})") from None
        if manifest["version"] == VERSION:
            for name in names:
                if twin_files.sha256(blobs[name]) != manifest["files"][name]:
                    raise DataError(f"'{folder / name}' does not match its checksum in '{pointer}' "
                                    "(edited or damaged); refusing the twin")
        return manifest["version"], revision, folder, blobs
    raise DataError(f"twin '{path}' kept changing while it was read; try again")


def load_twin(path):
    """Read a twin folder written by :func:`save_twin` (format version 1 or 2), checking
    every file (checksums, fields, shapes, dtypes) before use.

    **Arguments:**

    - ``path``: the twin folder.

    **Returns:** an :class:`~dtwin_jax.update.UpdateResult` whose twin predicts exactly as
    the saved one, with the attribute ``twin_revision`` (the revision loaded). Raises a
    one-line :class:`DataError` naming the file at fault.
    """
    from dtwin_jax.update import SamplerSettings, UpdateResult

    path = Path(path)
    if not path.is_dir() or not os.path.lexists(path / "twin.json"):
        what = "does not exist" if not path.exists() else "is not a twin folder (no twin.json)"
        raise DataError(f"twin '{path}' {what}")
    version, revision, folder, blobs = _read_files(path)
    head_name = folder / ("header.json" if version == VERSION else "twin.json")
    try:
        head = json.loads(blobs[head_name.name])
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"'{head_name}' is not valid JSON: {e}") from None
    twin_files.check_header(head, str(head_name), terms_required=version == VERSION)
    nominal = load_nominal(folder / "nominal.toml")
    if head["state_names"] != list(nominal.state_names) or head["num_inputs"] not in (0, nominal.n):
        raise DataError(f"twin header '{head_name}': its states and inputs do not match '{folder / 'nominal.toml'}'")
    lib = parse_library(head["library"], nominal.m, head["num_inputs"])
    dlib = parse_library(head["diffusion_library"], nominal.m, 0) if head["mode"] == "output-only" else None
    equations = _equations(head, blobs, folder, version, lib, dlib, nominal)
    statistics = _statistics(head, blobs, folder, equations)
    st = head["settings"]
    if set(st["prior"]) != set(sampler.SpikeSlabPrior._fields):
        raise DataError(f"twin header '{head_name}': settings.prior must hold {', '.join(sampler.SpikeSlabPrior._fields)}")
    settings = SamplerSettings(
        num_chains=st["num_chains"], num_draws=st["num_draws"], num_burnin=st["num_burnin"],
        prior=sampler.SpikeSlabPrior(**st["prior"]), p0=st["p0"], v_s=st["v_s"], max_active=st["max_active"],
    )
    _check_refinement_index(head, head_name, len([e for e in equations if e.kind == "drift"]) * lib.K)
    result = UpdateResult(
        mode=head["mode"], nominal=nominal, library=lib, equations=equations,
        pip_threshold=head["pip_threshold"], settings=settings, seconds=head["seconds"],
        preprocessing=head["preprocessing"], checks=head["checks"], statistics=statistics,
        history=head["history"], refinement=head.get("refinement"),
    )
    result.twin_revision = revision
    return result


def _equations(head, blobs, folder, version, lib, dlib, nominal) -> list[EquationPosterior]:
    name = str(folder / "posterior.nc")
    expected = []
    for eq in head["equations"]:
        tag = f"{eq['state']}_{eq['kind']}"
        names = tuple(eq["terms"]) if version == VERSION else twin_files.read_term_names(blobs["posterior.nc"], name, tag)
        want = lib.names if eq["kind"] == "drift" else dlib.names
        if names != want:
            raise DataError(f"twin '{folder}': the terms of {tag} do not match its library "
                            f"'{head['library'] if eq['kind'] == 'drift' else head['diffusion_library']}'")
        expected.append((eq["state"], eq["kind"], names))
    diffusion = [s for s, k, _ in expected if k == "diffusion"]
    if diffusion and diffusion != [nominal.state_names[v] for v in nominal.velocity_index]:
        raise DataError(f"twin '{folder}': the diffusion equations must be those of the velocities, in order")
    interpolation = head["preprocessing"].get("input_interpolation", "held")
    if interpolation not in ("held", "linear", "bandlimited"):
        raise DataError(f"twin '{folder}': unknown input interpolation {interpolation!r}")
    st = head["settings"]
    draws = twin_files.read_posterior(blobs["posterior.nc"], name, [(s, k, len(n)) for s, k, n in expected],
                                      st["num_chains"], st["num_draws"])
    return [EquationPosterior(s, k, n, *draws[f"{s}_{k}"], head["pip_threshold"]) for s, k, n in expected]


def _statistics(head, blobs, folder, equations) -> dict:
    shapes = {}
    for kind in ("drift", "diffusion"):
        eqs = [e for e in equations if e.kind == kind]
        if eqs:
            shapes[kind] = (len(eqs), len(eqs[0].names))
    stats = twin_files.read_statistics(blobs["statistics.npz"], str(folder / "statistics.npz"), shapes)
    return {kind: sampler.SuffStats(*(s[f] for f in sampler.SuffStats._fields)) for kind, s in stats.items()}


def _check_refinement_index(head, head_name, size: int) -> None:
    ref = head.get("refinement")
    if ref is not None and any(i >= size for i in ref["index"]):
        raise DataError(f"twin header '{head_name}', refinement: field 'index' points past the {size} coefficients")
