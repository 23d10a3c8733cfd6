"""A twin on disk: save, load, re-update (formats.md, "Saving a twin and predicting with it").

A twin folder `TWIN_DIR` holds, format version 2:

* `twin.json`: the manifest and pointer, `{"format": "dtwin-jax twin", "version": 2,
  "revision": 3, "current": "v000003", "files": {"header.json": "<sha256>", ...}}`;
* `v000003/`: the content of that revision, never changed once written:

  * `header.json`: `format`, `version`, `mode`, state and input names, the library
    specs, each equation's state, kind and term names, sampler settings, PIP threshold,
    preprocessing, checks, the `history` of updates (time, data size, prior, discovered
    equations, the window's fingerprint, package version) and the output-error
    `refinement` (or null);
  * `nominal.toml`: the nominal model (the nominal file of formats.md);
  * `posterior.nc`: every equation's draws as an arviz DataTree (netCDF, group
    `posterior`: `theta_<state>_<kind>`, `gamma_...`, `sigma2_...`);
  * `statistics.npz`: the sufficient statistics the sampler saw (`<kind>_gram`,
    `_xty`, `_yty`, `_n`), so that a re-update can use the posterior as its prior;
    a monitored twin (`dtwin_jax.monitor`) also its last windows' statistics and its
    drift statistics before each and their score spreads (`recent_windows_*`,
    `recent_twins_*`, `recent_spreads_*`, a leading axis of 1-4); an update from
    accelerometers alone its window's score spread (`drift_spread_*`);
  * `result.json`: the result file of formats.md for the last update;

* `.lock`: the lock file (never deleted).

Guarantees (a twin travels between users and is untrusted):

* Atomic: a save writes a new version folder in full (files synced), renames it into place,
  replaces `twin.json` (`os.replace`), then removes the previous version. At every
  instant the twin loads, with the old history or the new; leftovers of a killed save are
  removed by the next save.
* Nothing it did not write is deleted: only our file names are removed and a folder only
  when that leaves it empty; a folder that is neither empty nor a twin is refused, and a
  save over a twin must continue its history (or be asked to replace it).
* Locked: `locked` holds `fcntl.flock` on `.lock`; `save_twin` takes it,
  and the command line holds it through read, update and write, so concurrent updates
  queue instead of losing one.
* Checksummed and checked: `load_twin` verifies every file's SHA-256 against the
  manifest, then reads it defensively (`dtwin_jax.io.twin_files`: no netCDF reader, no
  pickles, every field, shape and dtype checked); any failure is one line naming the file.
  (`dtwin_jax.io.twin_folder` holds the lock, the names a save may remove and the
  destination check.)
* Files get the user's umask (0644 and 0755 under umask 022).

Version 1 (`twin.json` the header, the other files beside it) is still read; the next
save migrates it, removing only the five file names version 1 wrote.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from dtwin_jax import sampler
from dtwin_jax.errors import DataError
from dtwin_jax.io import json_safe, load_nominal, twin_files, twin_folder, write_nominal
from dtwin_jax.io.twin_folder import CONTENT, FORMAT, V1_FILES, check_target, locked
from dtwin_jax.library import parse_library
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.resources import check_num_inputs

__all__ = ["FORMAT", "VERSION", "save_twin", "load_twin", "locked", "check_target", "twin_revision"]

VERSION = 2
_LOAD_TRIES = 5

# Test hook: called with each step's name ("files", "folder", "pointer", "cleanup") of a save.
_AFTER_STEP = None


def twin_revision(path) -> int:
    """The revision of the twin at `path`; `load_twin` records it on its result as `twin_revision`.

    **Arguments:**

    - `path`: the twin folder.

    **Returns:** the revision, an int: 0 for a version-1 twin (or a `twin.json` that is not
    a JSON object).
    """
    head = twin_folder.read_json(Path(path) / "twin.json")
    return int(head.get("revision", 0)) if isinstance(head, dict) else 0


def save_twin(result, path, *, expect_revision: int | None = None, replace: bool = False) -> Path:
    """Write the `update.UpdateResult` `result` as the twin folder `path`.

    **Arguments:**

    - `result`: the update to save.
    - `path`: absent, an empty folder, or a twin. A twin is updated only if `result`
      continues its history (a re-update of it, or the same twin), so an update saved
      meanwhile by someone else is never silently lost. Files that are not the twin's are
      left alone.
    - `expect_revision`: refuse unless the twin at `path` is still at this revision (the
      `twin_revision` of the result `load_twin` returned); None (default) checks no revision.
    - `replace`: replace any twin at `path`, its history discarded, even one `result` does
      not continue or one whose manifest is damaged (default False).

    **Returns:** `Path(path)`. Raises a one-line `DataError`.
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
        twin_folder.clean(path, keep=current)
        used = [int(m.group(1)) for e in os.listdir(path) if (m := twin_folder.VERSION_DIR.fullmatch(e))]
        new = f"v{max([revision] + used) + 1:06d}"
        mode = 0o666 & ~twin_folder.umask()
        tmp = Path(tempfile.mkdtemp(dir=path, prefix=f".{new}.tmp-"))
        os.chmod(tmp, 0o777 & ~twin_folder.umask())
        digests = _write_content(tmp, result, mode)
        _step("files")
        os.rename(tmp, path / new)
        twin_folder.sync_dir(path)
        _step("folder")
        manifest = {"format": FORMAT, "version": VERSION, "revision": int(new[1:]), "current": new, "files": digests}
        fd, ptr = tempfile.mkstemp(dir=path, prefix=".twin.json.tmp-")
        with os.fdopen(fd, "w") as f:
            os.fchmod(f.fileno(), mode)
            f.write(json.dumps(manifest, indent=2) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(ptr, path / "twin.json")
        twin_folder.sync_dir(path)
        _step("pointer")
        if version == 1:
            twin_folder.remove_ours(path, V1_FILES[1:], rmdir=False)
        twin_folder.clean(path, keep=new)
        _step("cleanup")
    return path


def _step(name: str) -> None:
    if _AFTER_STEP is not None:
        _AFTER_STEP(name)


def _normal(history) -> list:
    """`history` as it reads back from JSON, for comparison."""
    return json.loads(json.dumps(json_safe(list(history))))


def _write_content(folder: Path, result, mode: int) -> dict:
    """Write the five content files into `folder`, synced, mode `mode`; their SHA-256."""
    _write_text(folder / "header.json", json.dumps(json_safe(_header(result)), indent=2, allow_nan=False) + "\n")
    write_nominal(folder / "nominal.toml", result.nominal)
    result.to_arviz().to_netcdf(folder / "posterior.nc", engine="h5netcdf")
    arrays = {f"{kind}_{name}": np.asarray(a, dtype=np.float64) for kind, st in result.statistics.items()
              for name, a in zip(sampler.SuffStats._fields, st)}
    with open(folder / "statistics.npz", "wb") as f:
        np.savez(f, **arrays)
    _write_text(folder / "result.json", json.dumps(json_safe(result.to_json()), indent=2, allow_nan=False) + "\n")
    digests = {}
    for name in CONTENT:
        with open(folder / name, "rb") as f:
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
            digests[name] = twin_files.sha256(f.read())
    return digests


def _write_text(path: Path, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)


def _current(path: Path, replace: bool):
    """`(version, revision, current folder name)` of the twin at `path`, `(0, 0, None)`
    when it holds none; a damaged manifest counts as none when it is to be replaced."""
    if not os.path.lexists(path / "twin.json"):
        return 0, 0, None
    manifest = twin_folder.read_json(path / "twin.json")
    if not isinstance(manifest, dict):
        if replace:
            return 2, 0, None
        raise DataError(f"'{path / 'twin.json'}' is not a dtwin-jax twin (not a JSON object)")
    if manifest.get("version") == 1:
        return 1, 0, None
    try:
        return 2, *_check_manifest(manifest, path / "twin.json")
    except DataError:
        if replace:
            return 2, 0, None
        raise


def _history(path: Path, current: str | None) -> list:
    head = twin_folder.read_json(path / current / "header.json" if current else path / "twin.json")
    history = head.get("history") if isinstance(head, dict) else None
    if not isinstance(history, list):
        raise DataError(f"twin '{path}' has no readable history; replace it (--force) or remove it")
    return history


def _check_manifest(manifest: dict, name: Path) -> tuple[int, str]:
    revision, current, files = manifest.get("revision"), manifest.get("current"), manifest.get("files")
    if not isinstance(revision, int) or isinstance(revision, bool) or not 1 <= revision <= 999999 \
            or current != f"v{revision:06d}":
        raise DataError(f"'{name}' names no valid revision (revision {revision!r}, current {current!r})")
    if not isinstance(files, dict) or set(files) != set(CONTENT) or not all(
            isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) for v in files.values()):
        raise DataError(f"'{name}': field 'files' must give the SHA-256 of {', '.join(CONTENT)}")
    return revision, current


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
    """`(version, revision, folder, {name: bytes})` of the twin at `path`, checksums
    verified. Retried when a save replaces the twin while it is read (no lock needed)."""
    pointer = path / "twin.json"
    for _ in range(_LOAD_TRIES):
        manifest = twin_folder.read_json(pointer)
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            got = manifest.get("format") if isinstance(manifest, dict) else None
            raise DataError(f"'{pointer}' is not a dtwin-jax twin (format {got!r})")
        if manifest.get("version") not in (1, VERSION):
            raise DataError(f"twin '{path}' has format version {manifest.get('version')!r}; "
                            f"this dtwin-jax reads 1 and {VERSION}")
        if manifest["version"] == 1:
            folder, names, revision = path, V1_FILES, 0
        else:
            revision, current = _check_manifest(manifest, pointer)
            folder, names = path / current, CONTENT
            if folder.is_symlink() or not folder.is_dir():
                raise DataError(f"twin '{path}': '{folder}' is not a folder")
        try:
            blobs = {name: twin_folder.read_bytes(folder / name) for name in names}
        except FileNotFoundError as e:
            if twin_folder.read_json(pointer) != manifest:
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
    """Read a twin folder written by `save_twin` (format version 1 or 2), checking
    every file (checksums, fields, shapes, dtypes) before use.

    **Arguments:**

    - `path`: the twin folder.

    **Returns:** an `update.UpdateResult` whose twin predicts exactly as
    the saved one, with the attribute `twin_revision` (the revision loaded). Raises a
    one-line `DataError` naming the file at fault.
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
    check_num_inputs(head["num_inputs"], nominal.n, f"'{head_name}'")
    if head["state_names"] != list(nominal.state_names):
        raise DataError(f"twin header '{head_name}': its states do not match '{folder / 'nominal.toml'}'")
    lib = parse_library(head["library"], nominal.m, head["num_inputs"])
    dlib = parse_library(head["diffusion_library"], nominal.m, 0) if head["mode"] == "output-only" else None
    equations = _equations(head, blobs, folder, version, lib, dlib, nominal)
    statistics = _statistics(head, blobs, folder, equations)
    st = head["settings"]
    fields = sampler.SpikeSlabPrior._fields
    if set(st["prior"]) != set(fields):
        raise DataError(f"twin header '{head_name}': settings.prior must hold {', '.join(fields)}")
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
        names = (tuple(eq["terms"]) if version == VERSION
                 else twin_files.read_term_names(blobs["posterior.nc"], name, tag))
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
    sd = head["preprocessing"].get("model_error_sd")
    if sd is not None and not (isinstance(sd, list) and len(sd) == nominal.m and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0 for v in sd)):
        raise DataError(f"twin '{folder}': model_error_sd must be {nominal.m} finite non-negative numbers")
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
    optional = {kind: shapes["drift"] for kind in twin_files.RECENT_KINDS} if "drift" in shapes else {}
    maybe = {twin_files.SPREAD_KIND: shapes["drift"]} if "drift" in shapes else {}
    stats = twin_files.read_statistics(blobs["statistics.npz"], str(folder / "statistics.npz"), shapes, optional,
                                       twin_files.MAX_RECENT, maybe)
    return {kind: sampler.SuffStats(*(s[f] for f in sampler.SuffStats._fields)) for kind, s in stats.items()}


def _check_refinement_index(head, head_name, size: int) -> None:
    ref = head.get("refinement")
    if ref is not None and any(i >= size for i in ref["index"]):
        raise DataError(f"twin header '{head_name}', refinement: field 'index' points past the {size} coefficients")
