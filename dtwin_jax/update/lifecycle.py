"""A twin's lifecycle across updates: a re-update checks that it continues the previous one
(same mode, nominal model and library), adds the previous update's sufficient statistics
to the new data's (the previous posterior as the prior, old data discounted by `forget`)
and appends an entry to the history that the result carries. Each entry keeps the window's
fingerprint (`window_fingerprint`), so a window already in the history is refused
(`check_repeat`): its data would count twice."""

from __future__ import annotations

import hashlib

import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.data import Records
from dtwin_jax.errors import DataError
from dtwin_jax.library import Library
from dtwin_jax.models.systems import LinearSecondOrder

__all__ = ["arrays_sha256", "check_previous", "check_repeat", "window_fingerprint", "with_previous", "updated_history"]


def with_previous(stats: sampler.SuffStats, kind: str, previous, forget: float) -> sampler.SuffStats:
    """`stats` plus `forget` times the previous update's of the same `kind`.

    For the conjugate part of the model this is the posterior after both data windows, so the
    previous posterior serves as the prior (`forget < 1` discounts old data, for a system that
    drifts).

    **Arguments:**

    - `stats`: this window's `SuffStats`, batched over the equations, physical units.
    - `kind`: `"drift"` or `"diffusion"`, the statistics of `previous` to add.
    - `previous`: the previous `UpdateResult`, or None (then `stats` is returned as is); one
      without statistics of that `kind` raises `DataError`.
    - `forget`: the previous statistics' weight, in `[0, 1]`.

    **Returns:** the combined `SuffStats`, same shapes as `stats`.
    """
    if previous is None:
        return stats
    old = previous.statistics.get(kind)
    if old is None:
        raise DataError(f"the previous update holds no {kind} statistics to combine with")
    # Same shapes: check_previous has matched the libraries.
    return sampler.SuffStats(*(jnp.asarray(a) + forget * np.asarray(b) for a, b in zip(stats, old)))


def check_previous(previous, mode: str, nominal: LinearSecondOrder, lib: Library, forget: float) -> None:
    """Raise `DataError` unless `previous` can be continued by a `mode` update of `nominal`
    with library `lib`.

    **Arguments:**

    - `previous`: the previous `UpdateResult`, or None (nothing to check).
    - `mode`: `"input-output"` or `"output-only"`; must be the previous update's.
    - `nominal`: the nominal `LinearSecondOrder`; must equal the previous one.
    - `lib`: the `Library`; its term names must be the previous one's.
    - `forget`: the previous statistics' weight; must be in `[0, 1]`.
    """
    if previous is None:
        return
    if not 0.0 <= forget <= 1.0:
        raise DataError(f"forget must be in [0, 1], got {forget}")
    if previous.mode != mode:
        raise DataError(f"cannot re-update a {previous.mode} twin with {mode} data")
    if previous.library.names != lib.names:
        raise DataError(f"re-update needs the previous library '{previous.library.spec}', got '{lib.spec}'")
    same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(
        (previous.nominal.M, previous.nominal.C, previous.nominal.K, previous.nominal.B, previous.nominal.F0),
        (nominal.M, nominal.C, nominal.K, nominal.B, nominal.F0)))
    if not same or previous.nominal.extra_states != nominal.extra_states:
        raise DataError("re-update needs the previous update's nominal model")


def arrays_sha256(arrays: dict, extra: str = "") -> str:
    """SHA-256 (hex) of named arrays as float64 bytes with their shapes, then `extra`: equal
    for the same data read again.

    **Arguments:**

    - `arrays`: name -> array (any shape) or None (counts as absent), hashed in order.
    - `extra`: a string hashed after them (default empty).

    **Returns:** the hex digest, a 64-character string.
    """
    h = hashlib.sha256()
    for name, a in arrays.items():
        if a is None:
            h.update(f"{name}:none;".encode())
            continue
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(f"{name}:{a.shape};".encode())
        h.update(a.tobytes())
    h.update(extra.encode())
    return h.hexdigest()


def window_fingerprint(rec: Records) -> str:
    """SHA-256 (hex) of a window's `t`, `x`, `u` and `xdot` (`arrays_sha256`).

    **Arguments:**

    - `rec`: the window's `Records`.

    **Returns:** the hex digest, a 64-character string.
    """
    return arrays_sha256({name: getattr(rec, name) for name in ("t", "x", "u", "xdot")})


def check_repeat(previous, rec: Records, allow_repeat: bool = False) -> None:
    """Raise `DataError` when the window `rec` is already in `previous`'s history (its
    data would count twice in the prior), unless `allow_repeat`.

    **Arguments:**

    - `previous`: the previous `UpdateResult`, or None (nothing to check).
    - `rec`: this window's `Records`.
    - `allow_repeat`: take the window even if it is in the history (default False).
    """
    if previous is None or allow_repeat:
        return
    fp = window_fingerprint(rec)
    for entry in previous.history:
        if isinstance(entry, dict) and entry.get("window_sha256") == fp:
            raise DataError(f"this window is already in the twin's history (update {entry.get('update')}, "
                            f"fingerprint {fp[:12]}): its data would count twice; "
                            "allow it with --allow-repeat (allow_repeat=True)")


def updated_history(previous, mode: str, rec: Records, forget: float, equations, seconds: float) -> list[dict]:
    """The previous update's history plus an entry for this one.

    **Arguments:**

    - `previous`: the previous `UpdateResult`, or None (a first update, prior spike-and-slab).
    - `mode`: `"input-output"` or `"output-only"`.
    - `rec`: this window's `Records`, `x (R, N, m)`.
    - `forget`: the previous statistics' weight, recorded in the entry's prior.
    - `equations`: this update's `EquationPosterior`s, recorded as equations.
    - `seconds`: the update's wall time, s.

    **Returns:** the history, a list of dicts oldest first; the new entry has `update`, `time`,
    `mode`, `records`, `samples`, `window_s`, `prior`, `seconds`, `equations`, `dtwin_jax`
    (the version) and `window_sha256`.
    """
    from datetime import datetime, timezone

    from dtwin_jax import __version__

    past = [] if previous is None else list(previous.history)
    prior = "spike-and-slab" if previous is None else f"posterior of update {len(past)} (forget {forget:g})"
    R, N, _ = rec.x.shape
    return past + [{
        "update": len(past) + 1,
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mode": mode,
        "records": int(R),
        "samples": int(R * N),
        "window_s": float((N - 1) * rec.dt),
        "prior": prior,
        "seconds": round(seconds, 3),
        "equations": [e.equation() for e in equations],
        "dtwin_jax": __version__,
        "window_sha256": window_fingerprint(rec),
    }]
