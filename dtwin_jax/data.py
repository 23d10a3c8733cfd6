"""Validation of measured signals: every check raises a one-line `DataError`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import LinearSecondOrder, real_array

__all__ = ["Records", "check_records", "state_range", "uniform_times"]

_MIN_SAMPLES = 16


class Records(NamedTuple):
    """Validated measurements with an explicit record axis.

    `t (N,)` seconds from 0 on an exact uniform grid; `x (R, N, m)`; `u (R, N, n)` or None;
    `xdot (R, N, m)` or None.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray | None
    xdot: np.ndarray | None

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])


def _as_records(name: str, a, N: int, width: int | None, what: str) -> np.ndarray:
    a = real_array(f"'{name}'", a)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise DataError(f"'{name}' must have shape (N, {what}) or (R, N, {what}), got {a.shape}")
    if a.shape[1] != N:
        raise DataError(f"'{name}' has {a.shape[1]} samples but 't' has {N}")
    if width is not None and a.shape[2] != width:
        raise DataError(f"'{name}' has {a.shape[2]} columns but the nominal model needs {width}")
    if not np.all(np.isfinite(a)):
        raise DataError(f"'{name}' contains NaN or infinite values")
    return a


def check_signal(name: str, a, num_samples: int, num_records: int) -> np.ndarray:
    """Check an extra measured signal (a closed loop's `reference`) and give it a record axis.

    The signal must be real and finite, `(N,)` (one channel), `(N, c)` or `(R, N, c)`, with
    the records and samples of `x`; every refusal is a one-line `DataError` naming it.

    **Arguments:**

    - `name`: the signal's name in error messages, e.g. `"reference"`.
    - `a`: the signal, shape `(N,)`, `(N, c)` or `(R, N, c)`, in its own units.
    - `num_samples`: the number of samples `N` of `t` (and `x`).
    - `num_records`: the number of records `R` of `x`.

    **Returns:** the signal as float64 `(R, N, c)`.
    """
    a = real_array(f"'{name}'", a)
    a = _as_records(name, a[:, None] if a.ndim == 1 else a, num_samples, None, "c")
    if a.shape[0] != num_records:
        raise DataError(f"'{name}' has {a.shape[0]} records but 'x' has {num_records}")
    return a


# A step may differ from the mean step by this fraction. Loggers with a hardware clock write
# times exact to their printed digits: 1024 Hz printed to 1 us is off by up to 1e-3 of a step.
# Timing errors of 1% of a step move a sample by 1% of its change over a step, far below
# sensor noise; a dropped or doubled sample (a 100% step change) is refused.
STEP_RTOL = 1e-2


def uniform_times(t) -> np.ndarray:
    """Check that `t` is uniformly sampled and rebase it to `arange(N) * dt`.

    The step is `dt = (t[-1] - t[0]) / (N - 1)`. Every step must be within `STEP_RTOL` of
    `dt`, plus 4 float64 spacings of `max|t|`: epoch timestamps (`t ~ 1.7e9` s) are stored to
    about 2.4e-7 s, which at 10 kHz is 0.24% of a step. Later code sees times from 0, so the
    size of `t[0]` costs no precision there. A refusal is a one-line `DataError`.

    **Arguments:**

    - `t`: `(N,)` real sample times in seconds, `N >= 16`.

    **Returns:** `(N,)` float64 times in seconds from 0, `arange(N) * dt` with `dt` rounded to
    the shortest decimal within that estimate's rounding error (`_shortest_step`).
    """
    t = real_array("'t'", t)
    if t.ndim != 1:
        raise DataError(f"'t' must be one-dimensional, got shape {t.shape}")
    if t.size < _MIN_SAMPLES:
        raise DataError(f"'t' has {t.size} samples; at least {_MIN_SAMPLES} are needed")
    if not np.all(np.isfinite(t)):
        raise DataError("'t' contains NaN or infinite values")
    dts = np.diff(t)
    dt = (t[-1] - t[0]) / (t.size - 1)
    stamp = 4 * np.spacing(np.max(np.abs(t)))  # a stored time's rounding error
    if not dt > 0 or np.any(dts <= 0) or np.max(np.abs(dts - dt)) > STEP_RTOL * dt + stamp:
        raise DataError(
            f"'t' is not uniformly spaced (steps from {dts.min():.6g} to {dts.max():.6g} s)"
        )
    return np.arange(t.size) * _shortest_step(dt, stamp / (t.size - 1))


def _shortest_step(dt: float, error: float) -> float:
    """The decimal with the fewest significant digits within `error` (s) of `dt` (and 4 of
    its own float64 spacings). Windows cut from one record at other offsets, or stamped with
    epoch times, then have the same `dt` bit for bit (1 ms, not 0.9999999999999953 ms for
    one and 1.0000000000000005 ms for another), and the programs keyed on it are reused."""
    error = float(error) + 4 * float(np.spacing(dt))
    for digits in range(1, 18):
        snapped = float(f"{dt:.{digits}g}")
        if abs(snapped - dt) <= error:
            return snapped
    return float(dt)


def check_records(
    t, x, u=None, xdot=None, nominal: LinearSecondOrder | None = None, *, x_columns=None, xdot_columns=None
) -> Records:
    """Check types, shapes, finiteness and uniform sampling.

    Complex, boolean and string arrays are refused; every refusal is a one-line `DataError`
    naming the key at fault.

    **Arguments:**

    - `t`: `(N,)` sample times in seconds, uniformly spaced (see `uniform_times`);
      any origin, epoch timestamps included.
    - `x`: measured states, `(N, w)` or `(R, N, w)` real, in the states' units.
    - `u`: inputs, `(N, n)` or `(R, N, n)` real, or None (default) for none.
    - `xdot`: measured state rates, `(N, w)` or `(R, N, w)` real (the states' units per
      second), or None (default) for none.
    - `nominal`: the nominal model, which gives the widths: `x` and `xdot` have `nominal.m`
      columns and `u` has `nominal.n`; None (default) checks no widths.
    - `x_columns`: the number of columns of `x` when only some states are measured; None
      (default) for `nominal.m` (no check without `nominal`).
    - `xdot_columns`: the number of columns of `xdot` when only some rates are measured; None
      (default) for as many as `x` has.

    **Returns:** `Records` with `t` rebased to the exact uniform grid `arange(N) * dt` from 0
    and every array float64 with a record axis: `x (R, N, w)`, `u (R, N, n)`, `xdot (R, N, w)`.
    """
    t = uniform_times(t)
    N = t.size
    m = nominal.m if nominal is not None else None
    n = nominal.n if nominal is not None else None
    x = _as_records("x", x, N, m if x_columns is None else x_columns, "m")
    R = x.shape[0]
    if u is not None:
        u = _as_records("u", u, N, n, "n")
        if u.shape[0] != R:
            raise DataError(f"'u' has {u.shape[0]} records but 'x' has {R}")
    if xdot is not None:
        xdot = _as_records("xdot", xdot, N, x.shape[2] if xdot_columns is None else xdot_columns, "m")
        if xdot.shape[0] != R:
            raise DataError(f"'xdot' has {xdot.shape[0]} records but 'x' has {R}")
    return Records(t, x, u, xdot)


def state_range(x, previous=None) -> list[list[float]]:
    """The range of each state the twin has seen, saved with it to bound its predictions.

    Used by `dtwin_jax.models.prediction.divergence_bounds`. NaN entries of `x` are ignored.

    **Arguments:**

    - `x`: states, shape `(..., m)`, in the states' units.
    - `previous`: the update this one continues (its `preprocessing["state_range"]` is
      merged in: a re-update's twin has seen both), or None (default).

    **Returns:** `[[lo, hi], ...]`, one pair per state: the smallest and largest value of `x`
    (and of `previous`'s range when given), as a list of `m` lists of floats.
    """
    x = np.asarray(x, dtype=float).reshape(-1, np.shape(x)[-1])
    lo, hi = np.nanmin(x, axis=0), np.nanmax(x, axis=0)
    old = None if previous is None else previous.preprocessing.get("state_range")
    if old is not None and np.shape(old) == (x.shape[1], 2):
        lo, hi = np.minimum(lo, np.asarray(old)[:, 0]), np.maximum(hi, np.asarray(old)[:, 1])
    return np.stack([lo, hi], axis=1).tolist()
