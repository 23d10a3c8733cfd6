"""Measurement noise, Savitzky-Golay smoothing, and rate estimation.

Signals are sampled on a uniform grid: `(N, c)` for one record or `(R, N, c)` for
`R` records, time along axis `-2`.
"""

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dtwin_jax.errors import DataError
from dtwin_jax.models.systems import LinearSecondOrder

__all__ = [
    "add_noise",
    "Measurements",
    "measure",
    "savgol_coefficients",
    "smooth",
    "smoothing_half_width",
    "highest_natural_frequency_hz",
    "estimate_rates",
]


def _concrete_float(value) -> float | None:
    """`value` as a float, or None when it is traced (validation then skipped)."""
    if isinstance(value, jax.core.Tracer):
        return None
    return float(np.asarray(value))


def add_noise(key: Array, signal: Float[Array, "... N c"], level, *, per_record: bool = True) -> Float[Array, "... N c"]:
    """Add Gaussian noise of std `level * std(signal)`.

    The std is taken over time, per column and per record, so `level` is a
    noise-to-signal ratio in `[0, 1]`.

    **Arguments:**

    - `key`: a JAX random key.
    - `signal`: the clean signal, `(N,)`, `(N, c)` or `(R, N, c)` (time along axis `-2`, or
      the only axis of `(N,)`).
    - `level`: the noise-to-signal ratio in `[0, 1]` (checked unless traced); 0 returns
      `signal` unchanged.
    - `per_record`: True (default): the std per record. False: an ensemble's std is taken over
      all records: one sensor per column, whose noise does not grow with a record's amplitude.

    **Returns:** the noisy signal, the shape and dtype of `signal`.
    """
    signal = jnp.asarray(signal)
    if signal.ndim not in (1, 2, 3):
        raise DataError(f"signal must have shape (N,), (N, c) or (R, N, c), got {signal.shape}")
    lv = _concrete_float(level)
    if lv is not None:
        if not 0.0 <= lv <= 1.0:
            raise DataError(f"noise level must be in [0, 1], got {lv}")
        if lv == 0.0:
            return signal
    time_axis = 0 if signal.ndim == 1 else signal.ndim - 2
    axis = (0, 1) if signal.ndim == 3 and not per_record else time_axis
    scale = level * jnp.std(signal, axis=axis, keepdims=True)
    return signal + scale * jax.random.normal(key, signal.shape, dtype=signal.dtype)


class Measurements(NamedTuple):
    """Sampled, possibly noisy, signals on the grid `t (N,)`.

    `x` is `(N, m)` or `(R, N, m)`; `xdot` has the shape of `x` or is None;
    `u` is `(N, n)` / `(R, N, n)` or None.
    """

    t: Float[Array, " N"]
    x: Float[Array, "... N m"]
    xdot: Float[Array, "... N m"] | None
    u: Float[Array, "... N n"] | None


def measure(key: Array, t, x, xdot=None, u=None, *, level) -> Measurements:
    """Corrupt each given signal with independent noise at `level` (see `add_noise`).

    **Arguments:**

    - `key`: a JAX random key (split into one per signal).
    - `t`: the sample times `(N,)`, s; kept noise-free.
    - `x`: states, `(N, m)` or `(R, N, m)`.
    - `xdot`: state rates, the shape of `x`, or None.
    - `u`: inputs, `(N, n)` or `(R, N, n)`, or None.
    - `level`: the noise-to-signal ratio in `[0, 1]`, per column and record.

    **Returns:** `Measurements` of `t` and the noisy `x`, `xdot`, `u` (None where not given).
    """
    kx, kxdot, ku = jax.random.split(key, 3)
    return Measurements(
        t=jnp.asarray(t),
        x=add_noise(kx, x, level),
        xdot=None if xdot is None else add_noise(kxdot, xdot, level),
        u=None if u is None else add_noise(ku, u, level),
    )


# ---------------------------------------------------------------------------
# Savitzky-Golay


def _check_window(half_width: int, order: int, deriv: int) -> None:
    if int(half_width) != half_width or half_width < 0:
        raise DataError(f"half_width must be a non-negative integer, got {half_width}")
    if int(order) != order or order < 0:
        raise DataError(f"order must be a non-negative integer, got {order}")
    if int(deriv) != deriv or deriv < 0:
        raise DataError(f"deriv must be a non-negative integer, got {deriv}")
    if order >= 2 * half_width + 1:
        raise DataError(
            f"order {order} needs a window longer than 2*half_width+1 = {2 * half_width + 1}"
        )


def _fit_evaluate_matrix(half_width: int, order: int, deriv: int, s: np.ndarray) -> np.ndarray:
    """`(len(s), 2M+1)` map from window samples to the `deriv`-th derivative (unit
    spacing) of their least-squares polynomial, evaluated at offsets `s` from the
    window centre."""
    window = np.arange(-half_width, half_width + 1, dtype=np.float64)
    powers = np.arange(order + 1)
    # Centred abscissae keep the Vandermonde well conditioned.
    fit = np.linalg.pinv(window[:, None] ** powers)  # (order+1, W): samples -> coeffs
    falling = np.array([math.perm(int(p), deriv) for p in powers], dtype=np.float64)
    shifted = np.clip(powers - deriv, 0, None)
    evaluate = falling * np.asarray(s, dtype=np.float64)[:, None] ** shifted
    return evaluate @ fit


def savgol_coefficients(
    half_width: int, order: int, deriv: int = 0, dt: float = 1.0
) -> np.ndarray:
    """Savitzky-Golay filter taps `(2*half_width + 1,)`, in convolution order.

    Same convention as `scipy.signal.savgol_coeffs(..., use="conv")`: convolving a
    signal sampled every `dt` with them gives the `deriv`-th derivative of the local
    order-`order` least-squares polynomial, in units of signal / `time^deriv`.

    **Arguments:**

    - `half_width`: the window's half width `M` in samples (the window is `2 M + 1`).
    - `order`: the polynomial's order, less than `2 M + 1`.
    - `deriv`: the derivative to estimate (default 0: smoothing).
    - `dt`: the sample step (default 1), s.

    **Returns:** the taps `(2*half_width + 1,)`, float64; raises `DataError` for a bad window.
    """
    _check_window(half_width, order, deriv)
    correlation = _fit_evaluate_matrix(half_width, order, deriv, np.zeros(1))[0]
    return correlation[::-1] / dt**deriv


def _smooth_2d(x, half_width, order, deriv, dt):
    N = x.shape[0]
    width = 2 * half_width + 1
    taps = jnp.asarray(savgol_coefficients(half_width, order, deriv))
    interior = jax.vmap(lambda col: jnp.convolve(col, taps, mode="valid"), 1, 1)(x)
    # Edges as scipy's mode="interp": evaluate the fit of the first/last window.
    offsets = np.arange(1, half_width + 1)
    left = jnp.asarray(_fit_evaluate_matrix(half_width, order, deriv, offsets - half_width - 1))
    right = jnp.asarray(_fit_evaluate_matrix(half_width, order, deriv, offsets))
    out = jnp.concatenate([left @ x[:width], interior, right @ x[N - width :]], axis=0)
    return out / dt**deriv


def smooth(
    x: Float[Array, "... N c"], half_width: int, order: int = 4, deriv: int = 0, dt=1.0
) -> Float[Array, "... N c"]:
    """Savitzky-Golay filter along time; matches `scipy.signal.savgol_filter(mode="interp")`.

    The interior is a convolution; the first and last `half_width` samples come from the
    polynomial fitted to the first and last `2*half_width + 1` samples.

    **Arguments:**

    - `x`: the signal, `(N,)`, `(N, c)` or `(R, N, c)`, with `N >= 2*half_width + 1`.
    - `half_width`: the window's half width in samples, a static Python int.
    - `order`: the polynomial's order (default 4), a static Python int.
    - `deriv`: the derivative to estimate (default 0: smoothing), a static Python int.
    - `dt`: the sample step, s (default 1; only used when `deriv > 0`).

    **Returns:** the filtered signal (its `deriv`-th derivative, in signal units / `s^deriv`),
    the shape of `x`.
    """
    _check_window(half_width, order, deriv)
    x = jnp.asarray(x)
    if x.ndim not in (1, 2, 3):
        raise DataError(f"x must have shape (N,), (N, c) or (R, N, c), got {x.shape}")
    N, width = x.shape[0 if x.ndim == 1 else -2], 2 * half_width + 1
    if N < width:
        raise DataError(f"signal has {N} samples, fewer than the window 2*half_width+1 = {width}")
    return _smooth(x, dt, half_width, order, deriv)


# One program per shape and window: called eagerly (the update's host-side steps), each of
# its operations was a program of its own, which a new process traces and loads one by one.
@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _smooth(x, dt, half_width: int, order: int, deriv: int):
    if x.ndim == 1:
        return _smooth_2d(x[:, None], half_width, order, deriv, dt)[:, 0]
    if x.ndim == 2:
        return _smooth_2d(x, half_width, order, deriv, dt)
    return jax.vmap(lambda r: _smooth_2d(r, half_width, order, deriv, dt))(x)


def smoothing_half_width(
    dt: float,
    f_signal_hz: float,
    order: int = 4,
    factor: float = 8.0,
    max_half_width: int = 500,
) -> int:
    """Half width `M` whose Savitzky-Golay -3 dB cutoff is about `factor * f_signal_hz`.

    Matches the filter to both the sampling rate `1/dt` and the signal band, via
    Schafer's approximation `f_c / (f_s / 2) ~ (order + 1) / (3.2 M - 4.6)`.

    **Arguments:**

    - `dt`: the sample step, s (positive).
    - `f_signal_hz`: the signal's band, Hz (positive); usually the highest nominal natural
      frequency (see `highest_natural_frequency_hz`).
    - `order`: the filter's polynomial order (default 4).
    - `factor`: the cutoff over `f_signal_hz` (default 8): room for harmonics created by the
      nonlinearity.
    - `max_half_width`: the largest half width returned (default 500).

    **Returns:** the half width `M` in samples, clamped to `[order // 2 + 1, max_half_width]`.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise DataError(f"sampling interval dt must be positive, got {dt}")
    if not (np.isfinite(f_signal_hz) and f_signal_hz > 0):
        raise DataError(f"signal frequency must be positive, got {f_signal_hz} Hz")
    ratio = factor * f_signal_hz / (0.5 / dt)  # cutoff as a fraction of Nyquist
    half_width = round(((order + 1) / ratio + 4.6) / 3.2)
    return int(min(max(half_width, order // 2 + 1), max_half_width))


def highest_natural_frequency_hz(nominal: LinearSecondOrder) -> float:
    """Largest undamped natural frequency of the nominal model, `max sqrt(eig(M^-1 K)) / 2 pi`, Hz.

    **Arguments:**

    - `nominal`: the nominal model, with mass `M` and stiffness `K`.

    **Returns:** the frequency in Hz, a float (0 without stiffness).
    """
    M = np.asarray(nominal.M, dtype=np.float64)
    K = np.asarray(nominal.K, dtype=np.float64)
    omega2 = np.real(np.linalg.eigvals(np.linalg.solve(M, K)))
    return float(np.sqrt(np.clip(omega2, 0.0, None)).max() / (2 * np.pi))


def estimate_rates(
    x: Float[Array, "... N m"], dt, half_width: int, order: int = 4
) -> Float[Array, "... N m"]:
    """Time derivative of each state by the Savitzky-Golay derivative filter.

    For when rates are not measured. The filter differentiates exactly any
    polynomial of degree <= `order` over the window, so for a smooth signal the
    bias in the interior is `O((half_width * dt)^order)`, while the least-squares fit
    suppresses noise above the cutoff (see `smoothing_half_width`). The first and
    last `half_width` samples use one-sided fits and are less accurate.

    **Arguments:**

    - `x`: the states, `(N, m)` or `(R, N, m)` (also `(N,)`).
    - `dt`: the sample step, s.
    - `half_width`: the window's half width in samples.
    - `order`: the polynomial's order (default 4).

    **Returns:** the rates, the shape of `x`, in the states' units per second.
    """

    return smooth(x, half_width, order, deriv=1, dt=dt)
