"""Files of formats.md: measurement files (.npz, .csv), nominal models (.toml), results (.json).

Every reader raises a one-line `DataError` naming the problem; writers write to a
temporary file and rename it, so a failed run leaves nothing half-written.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import tomllib
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dtwin_jax.errors import DataError, dtype_word
from dtwin_jax.io.twin_folder import umask
from dtwin_jax.resources import check_file_arrays

if TYPE_CHECKING:
    from dtwin_jax.models.systems import LinearSecondOrder

__all__ = ["load_nominal", "load_measurements", "load_prediction_input", "write_json", "write_nominal", "atomic_path"]


def load_nominal(path) -> LinearSecondOrder:
    """Read a nominal model file (`.toml`).

    The file holds `M`, `C`, `K` (d x d), optional `B` (d x n), `extra_states` and `F0` (d);
    a missing key, a non-numeric entry or a wrong shape raises a one-line `DataError`.

    **Arguments:**

    - `path`: the `.toml` file.

    **Returns:** the nominal model, a `LinearSecondOrder`.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise DataError(f"nominal model file '{path}' does not exist") from None
    except tomllib.TOMLDecodeError as e:
        raise DataError(f"nominal model file '{path}' is not valid TOML: {e}") from None
    except UnicodeDecodeError:
        raise DataError(f"nominal model file '{path}' is not UTF-8 text") from None
    except OSError as e:
        raise DataError(f"nominal model file '{path}' cannot be read: {e.strerror}") from None
    for key in ("M", "C", "K"):
        if key not in doc:
            raise DataError(f"nominal model file '{path}' is missing key '{key}'")
    for key in ("M", "C", "K", "B", "F0"):
        if key in doc:
            _check_toml_numbers(path, key, doc[key])
    mats = {}
    for key in ("M", "C", "K", "B"):
        if key in doc:
            try:
                mats[key] = np.asarray(doc[key], dtype=np.float64)
            except (TypeError, ValueError):
                raise DataError(f"'{key}' in '{path}' is not a numeric matrix") from None
            if mats[key].ndim != 2:
                raise DataError(f"'{key}' in '{path}' must be a matrix (list of rows)")
    extra = doc.get("extra_states", 0)
    if not isinstance(extra, int) or isinstance(extra, bool) or extra < 0:
        raise DataError(f"'extra_states' in '{path}' must be a non-negative integer")
    F0 = doc.get("F0")
    if F0 is not None:
        try:
            F0 = np.asarray(F0, dtype=np.float64)
        except (TypeError, ValueError):
            raise DataError(f"'F0' in '{path}' is not a numeric vector") from None
        if F0.ndim != 1:
            raise DataError(f"'F0' in '{path}' must be a vector (one force per degree of freedom)")
    # Here, not at the top: the readers and their refusals stay free of diffrax's import.
    from dtwin_jax.models.systems import LinearSecondOrder

    return LinearSecondOrder.create(
        mats["M"], mats["C"], mats["K"], mats.get("B"), extra_states=extra, F0=F0
    )


def _check_toml_numbers(path: Path, key: str, value) -> None:
    """Refuse TOML values a float conversion would accept silently: booleans (`true` reads
    as 1.0) and numeric strings (`"1.0"`), anywhere in a nested array."""
    if isinstance(value, list):
        for v in value:
            _check_toml_numbers(path, key, v)
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        shown = str(value).lower() if isinstance(value, bool) else repr(value)  # as TOML spells it
        raise DataError(f"'{key}' in '{path}' has the entry {shown}, not a number")


def write_nominal(path, nominal: LinearSecondOrder) -> None:
    """Write a nominal model as the TOML of formats.md, atomically.

    **Arguments:**

    - `path`: the `.toml` file to write (replaced if it exists).
    - `nominal`: the `LinearSecondOrder` to write.
    """

    def mat(a):
        return "[" + ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in np.asarray(a)) + "]"

    text = (
        f"M = {mat(nominal.M)}\nC = {mat(nominal.C)}\nK = {mat(nominal.K)}\n"
        f"B = {mat(nominal.B)}\nF0 = {mat(np.asarray(nominal.F0)[None])[1:-1]}\n"
        f"extra_states = {nominal.extra_states}\n"
    )
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def load_measurements(path) -> dict:
    """Read a measurement file (`.npz` or `.csv`).

    The file holds `t`, `x` and optional `u`, `xdot`, `x_names`, `xdot_names` and
    `u_interpolation` (absent: chosen from the input's spectrum). `x` may be absent when
    `xdot` is present (accelerometers alone). An extension of formats.md: `reference`
    (`.npz`, `(N, r)` or `(R, N, r)`), a closed loop's set-point, the instrument of
    `dtwin_jax.preprocess.instruments`.

    A CSV file holds one record with header `t,` then measured state names (all of
    `x1..xm` or a subset, which become `x_names`) `[,u1..un]`; columns `xdot1..`
    (all or a subset, which become `xdot_names`) carry measured rates.

    **Arguments:**

    - `path`: the `.npz` or `.csv` file.

    **Returns:** a dict of the keys present: `t (N,)` (s), `x (N, p)` or `(R, N, p)`, `u`,
    `xdot`, `reference` (real arrays, shapes as in the file), `x_names` and `xdot_names`
    (lists of state names) and `u_interpolation` (a string). The arrays are not yet checked
    for shape or sampling (`dtwin_jax.data.check_records` does that).
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"measurement file '{path}' does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        data = _read_npz(path, "measurement file")
    elif suffix == ".csv":
        data = _read_csv(path)
    else:
        raise DataError(f"measurement file '{path}' must be .npz or .csv")
    # 'x' may be left out when 'xdot' is there: accelerometers alone (formats.md).
    for key in ("t",) + (() if "xdot" in data else ("x",)):
        if key not in data:
            raise DataError(f"measurement file '{path}' is missing key '{key}'")
    out = {"t": data["t"]} | ({"x": data["x"]} if "x" in data else {})
    for key in ("u", "xdot", "reference"):
        if key in data:
            out[key] = data[key]
    for key, a in out.items():
        # Complex values would lose their imaginary part in the float conversion.
        if np.asarray(a).dtype.kind not in "iuf":
            raise DataError(f"'{key}' in '{path}' must hold real numbers, got {dtype_word(np.asarray(a).dtype)} values")
    for key in ("x_names", "xdot_names"):
        if key in data:
            names = np.atleast_1d(data[key])
            if names.ndim != 1 or not np.issubdtype(names.dtype, np.str_):
                raise DataError(f"'{key}' in '{path}' must be a vector of state names like ['x1']")
            out[key] = [str(n) for n in names]
    if "u_interpolation" in data:
        value = np.asarray(data["u_interpolation"])
        if value.shape != () or not np.issubdtype(value.dtype, np.str_):
            raise DataError(f"'u_interpolation' in '{path}' must be one string (held, linear, bandlimited or auto)")
        out["u_interpolation"] = str(value)
    return out


def _read_npz(path: Path, what: str) -> dict:
    """Every array of an `.npz` (no pickles), after the sizes its headers declare are
    checked against the memory available: a small file can declare a huge array."""
    unreadable = (OSError, ValueError, EOFError, zipfile.BadZipFile)
    try:
        nbytes = 0
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                        np.lib.format.read_array_header_2_0
                    shape, _, dtype = read(f)
                nbytes += math.prod(shape) * dtype.itemsize
    except unreadable as e:
        raise DataError(f"{what} '{path}' is not a readable .npz: {e}") from None
    check_file_arrays(nbytes, f"{what} '{path}'")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except unreadable as e:
        raise DataError(f"{what} '{path}' is not a readable .npz: {e}") from None


def load_prediction_input(path, nominal: LinearSecondOrder, *, needs_input: bool) -> dict:
    """Read `NEW.npz` of `dtwin-jax predict`: the times, initial state and inputs to predict from.

    The file holds `t (N,)` increasing (s), `x0 (m,)`, and `u (N, n)` when `needs_input`;
    a `u` of shape `(N,)` is read as one input.

    **Arguments:**

    - `path`: the `.npz` file.
    - `nominal`: the twin's nominal model, which gives `m` and `n`.
    - `needs_input`: whether `u` is required (an input-output twin); otherwise it is ignored.

    **Returns:** a dict of float arrays: `t (N,)`, `x0 (m,)` and, when `needs_input`,
    `u (N, n)`.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"input file '{path}' does not exist")
    data = _read_npz(path, "input file")
    keys = ("t", "x0", "u") if needs_input else ("t", "x0")
    for key in keys:
        if key not in data:
            raise DataError(f"input file '{path}' is missing key '{key}'")
        if data[key].dtype.kind not in "iuf" or not np.all(np.isfinite(data[key])):
            raise DataError(f"'{key}' in '{path}' must be finite numbers")
    t, x0 = data["t"].astype(float), data["x0"].astype(float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise DataError(f"'t' in '{path}' must be an increasing vector of at least 2 times")
    if x0.shape != (nominal.m,):
        raise DataError(f"'x0' in '{path}' has shape {x0.shape}; the twin has {nominal.m} states")
    out = {"t": t, "x0": x0}
    if needs_input:
        u = data["u"].astype(float)
        u = u[:, None] if u.ndim == 1 else u
        if u.shape != (t.size, nominal.n):
            raise DataError(f"'u' in '{path}' has shape {data['u'].shape}; expected ({t.size}, {nominal.n})")
        out["u"] = u
    return out


def _read_csv(path: Path) -> dict:
    try:
        # The text, its decoded copy and its lines each take about the file's size.
        check_file_arrays(path.stat().st_size, f"measurement file '{path}'")
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(f"measurement file '{path}' cannot be read: {e.strerror}") from None
    try:
        text = raw.decode("utf-8-sig")  # a BOM (spreadsheet exports) is not part of the header
    except UnicodeDecodeError:
        raise DataError(f"measurement file '{path}' is not UTF-8 text") from None
    lines = [(i, line) for i, line in enumerate(text.splitlines(), start=1) if line.strip()]
    if not lines:
        raise DataError(f"measurement file '{path}' is empty")
    header = [h.strip() for h in lines[0][1].split(",")]
    for h in header:
        if header.count(h) > 1:
            raise DataError(f"'{path}' names column '{h}' more than once")
    rows = lines[1:]
    if not rows:
        raise DataError(f"measurement file '{path}' has a header but no data rows")
    for i, line in rows:
        if line.count(",") != len(header) - 1:
            raise DataError(f"'{path}' line {i} has {line.count(',') + 1} values but its header names {len(header)}")
    try:
        table = np.loadtxt([line for _, line in rows], delimiter=",", ndmin=2)
    except ValueError:
        for i, line in rows:  # only on failure: name the file's line, not loadtxt's row
            for v in line.split(","):
                try:
                    float(v)
                except ValueError:
                    raise DataError(f"measurement file '{path}' line {i} has a non-numeric value {v.strip()!r}") from None
        raise DataError(f"measurement file '{path}' has a non-numeric value") from None
    cols = {name: table[:, i] for i, name in enumerate(header)}
    data = {}
    if "t" in cols:
        data["t"] = cols["t"]
    names = _numbered(header, "u")
    if names:
        data["u"] = np.stack([cols[n] for n in names], axis=1)
    rates = [h for h in header if h.startswith("xdot") and h[4:].isdigit()]  # a subset, like the states
    if rates:
        data["xdot"] = np.stack([cols[n] for n in rates], axis=1)
        data["xdot_names"] = np.asarray(["x" + h[4:] for h in rates])
    states = [h for h in header if h.startswith("x") and h[1:].isdigit()]  # a subset in any order
    if states:
        data["x"] = np.stack([cols[n] for n in states], axis=1)
        data["x_names"] = np.asarray(states)  # the header names them: all states or a subset
    unknown = [h for h in header if h != "t" and h not in states and h not in rates and h not in _numbered(header, "u")]
    if unknown:
        raise DataError(f"'{path}' has unknown column '{unknown[0]}' (expected t, x1.., u1.., xdot1..)")
    return data


def _numbered(header, prefix):
    """`prefix1, prefix2, ...` in order; a gap is an error."""
    found = sorted(
        (int(h[len(prefix):]), h) for h in header
        if h.startswith(prefix) and h[len(prefix):].isdigit()
    )
    for expect, (i, h) in enumerate(found, start=1):
        if i != expect:
            raise DataError(f"CSV columns '{prefix}1..' are not numbered consecutively (found '{h}')")
    return [h for _, h in found]


class atomic_path:
    """Context manager yielding a temporary path that replaces `path` on success only.

    The file gets the mode `open` would give it (`0o666` less the umask): `mkstemp`
    creates it `0o600`, which would hide results from the user's group."""

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self) -> str:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=self.path.suffix)
        os.close(fd)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            os.chmod(self.tmp, 0o666 & ~umask())
            os.replace(self.tmp, self.path)
        elif os.path.exists(self.tmp):
            os.remove(self.tmp)
        return False


def json_safe(obj):
    """A copy of `obj` with every non-finite float replaced by None.

    JSON has no NaN or Infinity, and strict parsers reject the bare tokens Python writes for
    them.

    **Arguments:**

    - `obj`: a JSON-ready object: dicts, lists, tuples and scalars, nested.

    **Returns:** the same structure (tuples become lists) with non-finite floats as None.
    """
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path, obj) -> None:
    """Write `obj` as strict JSON (non-finite numbers as null), atomically.

    **Arguments:**

    - `path`: the `.json` file to write (replaced if it exists).
    - `obj`: a JSON-ready object (see `json_safe`).
    """
    text = json.dumps(json_safe(obj), indent=2, allow_nan=False)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text + "\n")
