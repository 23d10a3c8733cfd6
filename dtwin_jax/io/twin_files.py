"""Defensive readers of a twin's files (`dtwin_jax.io.store`).

A twin folder travels between users and is untrusted: every file is checked against the
header before use, and every failure is a one-line `DataError` naming the file.

* the header (`header.json`; `twin.json` of a version-1 twin): a schema check of every
  field (presence, type, known states, modes and kinds);
* `posterior.nc`: read with h5py from bytes already checksummed, only the datasets the
  header names, refusing external storage, links, virtual datasets, filters other than
  HDF5's built-in ones and unexpected shapes or dtypes (a netCDF reader would follow what
  the file says: external storage reads any local file);
* `statistics.npz`: no pickles; exactly the expected keys, shapes and float dtypes.
"""

from __future__ import annotations

import hashlib
import io
import math
import re

import numpy as np

from dtwin_jax.errors import DataError

__all__ = ["MAX_RECENT", "RECENT_KINDS", "sha256", "check_header", "read_posterior", "read_statistics", "read_term_names"]

MODES = ("input-output", "output-only")
KINDS = ("drift", "diffusion")
_PRIOR_FIELDS = ("a_p", "b_p", "a_v", "b_v", "a_sigma", "b_sigma")
# HDF5's built-in filters (deflate, shuffle, fletcher32): no plugin is loaded for a twin.
_FILTERS = {1, 2, 3}
_STATS_FIELDS = ("gram", "xty", "yty", "n")


def sha256(data: bytes) -> str:
    """Hex SHA-256 of `data`.

    **Arguments:**

    - `data`: the bytes to hash.

    **Returns:** the digest, 64 lowercase hex digits.
    """
    return hashlib.sha256(data).hexdigest()


def _int(lo):
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _strs(v) -> bool:
    return isinstance(v, list) and all(isinstance(s, str) for s in v)


def _opt(check):
    return lambda v: v is None or check(v)


_HEADER = {
    "mode": (lambda v: v in MODES, "input-output or output-only"),
    "state_names": (lambda v: _strs(v) and len(v) > 0, "a list of state names"),
    "input_names": (_strs, "a list of input names"),
    "library": (lambda v: isinstance(v, str), "a library spec (string)"),
    "num_inputs": (_int(0), "a non-negative integer"),
    "diffusion_library": (_opt(lambda v: isinstance(v, str)), "a library spec or null"),
    "equations": (lambda v: isinstance(v, list) and len(v) > 0 and all(isinstance(e, dict) for e in v),
                  "a non-empty list of equations"),
    "pip_threshold": (lambda v: _num(v) and 0 <= v < 1, "a number in [0, 1)"),
    "settings": (lambda v: isinstance(v, dict), "an object"),
    "seconds": (_num, "a number"),
    "preprocessing": (lambda v: isinstance(v, dict), "an object"),
    "checks": (lambda v: isinstance(v, dict), "an object"),
    "history": (lambda v: isinstance(v, list) and all(isinstance(h, dict) for h in v), "a list of objects"),
    "refinement": (_opt(lambda v: isinstance(v, dict)), "an object or null"),
}
_SETTINGS = {
    "num_chains": (_int(1), "a positive integer"),
    "num_draws": (_int(1), "a positive integer"),
    "num_burnin": (_int(0), "a non-negative integer"),
    "prior": (lambda v: isinstance(v, dict), "an object"),
    "p0": (lambda v: _num(v) and 0 < v < 1, "a number in (0, 1)"),
    "v_s": (lambda v: _num(v) and v > 0, "a positive number"),
    "max_active": (_opt(_int(1)), "a positive integer or null"),
}
_EQUATION = {
    "state": (lambda v: isinstance(v, str), "a state name"),
    "kind": (lambda v: v in KINDS, "drift or diffusion"),
    "terms": (_strs, "a list of term names"),
}


def _fields(obj: dict, spec: dict, where: str, optional=()) -> None:
    for key, (ok, what) in spec.items():
        if key not in obj:
            if key in optional:
                continue
            raise DataError(f"{where}: field '{key}' is missing")
        if not ok(obj[key]):
            raise DataError(f"{where}: field '{key}' must be {what}, got {_short(obj[key])}")


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def check_header(head, name: str, *, terms_required: bool) -> dict:
    """Check a twin header: every field present with its type, equations of known states and kinds.

    Also checks that the settings and the refinement are usable. Raises a one-line
    `DataError` naming the file and the field.

    **Arguments:**

    - `head`: the header, parsed JSON.
    - `name`: the file it was read from, for error messages.
    - `terms_required`: whether each equation must list its term names in `terms` (format
      version 2).

    **Returns:** `head`, unchanged.
    """
    where = f"twin header '{name}'"
    if not isinstance(head, dict):
        raise DataError(f"{where} is not a JSON object")
    _fields(head, _HEADER, where, optional=("refinement",))
    _fields(head["settings"], _SETTINGS, f"{where}, settings")
    _fields(head["settings"]["prior"], {k: (lambda v: _num(v) and v > 0, "a positive number") for k in _PRIOR_FIELDS},
            f"{where}, settings.prior")
    if len(set(head["state_names"])) != len(head["state_names"]):
        raise DataError(f"{where}: field 'state_names' repeats a name")
    seen = set()
    for i, eq in enumerate(head["equations"]):
        _fields(eq, _EQUATION, f"{where}, equation {i}", optional=() if terms_required else ("terms",))
        if eq["state"] not in head["state_names"]:
            raise DataError(f"{where}, equation {i}: unknown state {_short(eq['state'])}")
        if (eq["state"], eq["kind"]) in seen:
            raise DataError(f"{where}, equation {i}: {eq['state']} {eq['kind']} appears twice")
        seen.add((eq["state"], eq["kind"]))
    kinds = {eq["kind"] for eq in head["equations"]}
    if head["mode"] == "input-output" and kinds != {"drift"}:
        raise DataError(f"{where}: an input-output twin has drift equations only")
    if head["mode"] == "output-only" and (
            kinds != set(KINDS) or not isinstance(head["diffusion_library"], str)
            or head["preprocessing"].get("diffusion_library") != head["diffusion_library"]):
        raise DataError(f"{where}: an output-only twin needs drift and diffusion equations and its diffusion library")
    if head.get("refinement") is not None:
        _check_refinement(head["refinement"], where)
    return head


def _check_refinement(ref: dict, where: str) -> None:
    where = f"{where}, refinement"
    for key in ("method", "terms", "index", "mean", "cov", "noise_std", "residual_scale", "hac_lags",
                "iterations", "samples"):
        if key not in ref:
            raise DataError(f"{where}: field '{key}' is missing")
    index, mean, cov, terms = ref["index"], ref["mean"], ref["cov"], ref["terms"]
    if not (isinstance(index, list) and all(_int(0)(i) for i in index) and len(set(index)) == len(index)):
        raise DataError(f"{where}: field 'index' must be a list of distinct non-negative integers")
    P = len(index)
    if not (isinstance(mean, list) and len(mean) == P and all(_num(v) for v in mean)):
        raise DataError(f"{where}: field 'mean' must be {P} numbers")
    if not (isinstance(cov, list) and len(cov) == P
            and all(isinstance(r, list) and len(r) == P and all(_num(v) for v in r) for r in cov)):
        raise DataError(f"{where}: field 'cov' must be a {P} x {P} matrix")
    if not (isinstance(terms, list) and len(terms) == P and all(
            isinstance(t, dict) and isinstance(t.get("state"), str) and isinstance(t.get("expr"), str) for t in terms)):
        raise DataError(f"{where}: field 'terms' must be {P} objects with 'state' and 'expr'")


def _h5(data: bytes, name: str):
    import h5py

    try:
        return h5py.File(io.BytesIO(data), "r")
    except Exception as e:  # h5py raises OSError, ValueError... for a damaged file
        raise DataError(f"'{name}' is not a readable HDF5/netCDF file ({_first_line(e)})") from None


def _first_line(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return (text[0] if text else type(e).__name__)[:120]


def _dataset(group, key: str, name: str):
    """The plain dataset `key` of `group`: no link, external storage, virtual layout or
    filter plugin (each could make HDF5 read what the file names, not what it holds)."""
    import h5py

    link = group.get(key, getlink=True)
    if link is None:
        raise DataError(f"'{name}' has no dataset '{group.name.strip('/')}/{key}'")
    if not isinstance(link, h5py.HardLink):
        raise DataError(f"'{name}': '{key}' is a {type(link).__name__}; a twin holds plain datasets only")
    ds = group[key]
    if not isinstance(ds, h5py.Dataset):
        raise DataError(f"'{name}': '{key}' is not a dataset")
    if ds.external:
        raise DataError(f"'{name}': dataset '{key}' uses external storage; refusing to read it")
    if ds.is_virtual:
        raise DataError(f"'{name}': dataset '{key}' is virtual; refusing to read it")
    plist = ds.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        if plist.get_filter(i)[0] not in _FILTERS:
            raise DataError(f"'{name}': dataset '{key}' uses HDF5 filter {plist.get_filter(i)[0]}; refusing it")
    return ds


def _array(group, key: str, name: str, shape: tuple, kinds: str) -> np.ndarray:
    ds = _dataset(group, key, name)
    if ds.shape != shape:
        raise DataError(f"'{name}': dataset '{key}' has shape {ds.shape}; the twin header says {shape}")
    if ds.dtype.kind not in kinds or ds.dtype.itemsize > 8:
        want = "float" if kinds == "f" else "integer"
        raise DataError(f"'{name}': dataset '{key}' has dtype {ds.dtype}; expected {want}")
    try:
        a = np.asarray(ds[()])
    except Exception as e:
        raise DataError(f"'{name}': dataset '{key}' cannot be read ({_first_line(e)})") from None
    if kinds == "f" and not np.all(np.isfinite(a)):
        raise DataError(f"'{name}': dataset '{key}' holds NaN or infinite values")
    return a


def _posterior_group(f, name: str):
    import h5py

    link = f.get("posterior", getlink=True)
    if not isinstance(link, h5py.HardLink) or not isinstance(f["posterior"], h5py.Group):
        raise DataError(f"'{name}' has no group 'posterior'")
    return f["posterior"]


def read_term_names(data: bytes, name: str, tag: str) -> tuple[str, ...]:
    """A version-1 twin's term names of one equation, from `posterior.nc`.

    They are the string coordinate `posterior/term_<tag>` (version 2 keeps them in the header).

    **Arguments:**

    - `data`: the bytes of `posterior.nc`, already checksummed.
    - `name`: the file's path, for error messages.
    - `tag`: the equation, `<state>_<kind>`.

    **Returns:** the term names, a tuple of strings.
    """
    with _h5(data, name) as f:
        ds = _dataset(_posterior_group(f, name), f"term_{tag}", name)
        if ds.ndim != 1 or ds.dtype.kind not in "OSU":
            raise DataError(f"'{name}': dataset 'term_{tag}' is not a list of term names")
        try:
            names = tuple(str(v) for v in ds.asstr()[()])
        except Exception as e:
            raise DataError(f"'{name}': dataset 'term_{tag}' is not a list of term names ({_first_line(e)})") from None
    return names


def read_posterior(data: bytes, name: str, equations: list[tuple[str, str, int]], chains: int, draws: int) -> dict:
    """Draws of every equation from `posterior.nc`, each checked against the header's shapes.

    **Arguments:**

    - `data`: the bytes of `posterior.nc`, already checksummed.
    - `name`: the file's path, for error messages.
    - `equations`: one `(state, kind, K)` per equation, `K` its number of terms.
    - `chains`: the number of chains the header gives.
    - `draws`: the number of draws per chain the header gives.

    **Returns:** a dict `"<state>_<kind>" -> (gamma, theta, sigma2)`: inclusion indicators
    `(chains, draws, K)` bool, coefficients `(chains, draws, K)` float64 and noise variances
    `(chains, draws)` float64.
    """
    out = {}
    with _h5(data, name) as f:
        post = _posterior_group(f, name)
        for state, kind, K in equations:
            tag = f"{state}_{kind}"
            if not re.fullmatch(r"[A-Za-z0-9]+_(drift|diffusion)", tag):
                raise DataError(f"'{name}': unexpected equation name '{tag}'")
            gamma = _array(post, f"gamma_{tag}", name, (chains, draws, K), "iub")
            if not np.all((gamma == 0) | (gamma == 1)):
                raise DataError(f"'{name}': dataset 'gamma_{tag}' holds values other than 0 and 1")
            theta = _array(post, f"theta_{tag}", name, (chains, draws, K), "f").astype(np.float64)
            sigma2 = _array(post, f"sigma2_{tag}", name, (chains, draws), "f").astype(np.float64)
            out[tag] = (gamma.astype(bool), theta, sigma2)
    return out


# A monitored twin also keeps its last windows (dtwin_jax.monitor): their drift statistics and
# the twin's before each, newest first, at most MAX_RECENT.
RECENT_KINDS = ("recent_windows", "recent_twins", "recent_spreads")
MAX_RECENT = 4
# An update from accelerometers alone also keeps the covariance of its window's drift score
# over draws of the states' estimation error (gram; dtwin_jax.monitor.change.window_test).
SPREAD_KIND = "drift_spread"


def read_statistics(data: bytes, name: str, expected: dict[str, tuple[int, int]],
                    optional: dict[str, tuple[int, int]] | None = None, max_lead: int = 0,
                    maybe: dict[str, tuple[int, int]] | None = None) -> dict:
    """The sufficient statistics of `statistics.npz`: exactly the expected keys, no pickled objects.

    **Arguments:**

    - `data`: the bytes of `statistics.npz`, already checksummed.
    - `name`: the file's path, for error messages.
    - `expected`: the kinds that must be there, each mapped to `(q equations, K terms)`.
    - `optional`: kinds (a monitor's recent windows) that may be there or not, all together,
      each with a leading axis of the same length `P <= max_lead`; None (default) for none.
    - `max_lead`: the largest length `P` of the optional kinds' leading axis.
    - `maybe`: kinds that may be there or not, each alone, mapped like `expected`; None
      (default) for none.

    **Returns:** `kind -> {gram (q, K, K), xty (q, K), yty (q,), n (q,)}` as float64 (with a
    leading axis `(P,)` for the optional kinds), one entry per kind present.
    """
    optional = optional or {}
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            files = set(z.files)
            expected = {**expected, **{k: v for k, v in (maybe or {}).items() if f"{k}_n" in files}}
            lead = {k: z[f"{k}_n"].shape[:1] for k in optional if f"{k}_n" in files}
            present = {k: v for k, v in optional.items() if k in lead} if lead else {}
            if lead and len(present) < len(optional):
                missing = sorted(set(optional) - set(present))[0]
                raise DataError(f"'{name}' is missing key '{missing}_n'")
            kinds = {**{k: ((), v) for k, v in expected.items()}, **{k: (lead[k], v) for k, v in present.items()}}
            want = {f"{kind}_{field}" for kind in kinds for field in _STATS_FIELDS}
            if files != want:
                extra, missing = sorted(files - want), sorted(want - files)
                what = f"is missing key '{missing[0]}'" if missing else f"has unexpected key '{extra[0]}'"
                raise DataError(f"'{name}' {what}")
            leads = {shape for shape, _ in kinds.values() if shape}
            if len(leads) > 1 or any(not 1 <= P <= max_lead for (P,) in leads):
                raise DataError(f"'{name}': the recent windows' statistics have lengths {sorted(leads)}; expected one "
                                f"length from 1 to {max_lead}")
            out = {}
            for kind, (P, (q, K)) in kinds.items():
                shapes = {"gram": P + (q, K, K), "xty": P + (q, K), "yty": P + (q,), "n": P + (q,)}
                out[kind] = {}
                for field in _STATS_FIELDS:
                    a = z[f"{kind}_{field}"]
                    if a.dtype.kind != "f" or a.shape != shapes[field]:
                        raise DataError(f"'{name}': '{kind}_{field}' has shape {a.shape} and dtype {a.dtype}; "
                                        f"expected {shapes[field]} float")
                    if not np.all(np.isfinite(a)):
                        raise DataError(f"'{name}': '{kind}_{field}' holds NaN or infinite values")
                    out[kind][field] = a.astype(np.float64)
    except DataError:
        raise
    except Exception as e:  # zipfile, numpy format and pickle refusals
        raise DataError(f"'{name}' is not a readable .npz of statistics ({_first_line(e)})") from None
    return out
