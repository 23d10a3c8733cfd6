"""The weak form of framework 1 from accelerometers: the nominal part exact, whatever the states.

With only the accelerations `a` of the degrees of freedom measured (and the force), the
displacement and velocity are unknown, and any estimate of them drifts below the first mode.
Multiplying each velocity equation `a_i = f_i(q, v, u) + Theta(q, v, u) theta` by test
functions `chi_k''` (the second derivative of `chi_k = (s (1 - s))^p` on a window of the
record) and integrating by parts twice moves both time derivatives of the unknown states onto
the test function:

    int chi'' q dt = int chi a dt,        int chi'' v dt = -int chi' a dt,

so the nominal model's part of every row is the measured acceleration through three known
filters, exactly, and a constant force (nothing an accelerometer sees) drops out. Only the
library terms see the estimated states (`dtwin_jax.preprocess.accelerometers`), through `chi''`,
which weighs a frequency `w` by `w^2`: the integrated noise of the states (`1 / w^2`)
comes out flat.

The rows' covariance (one per equation) has three parts: the accelerometers' white noise
through the three filters; a white equation error of unknown size (the force sensor's noise,
process noise, what the library misses), by restricted maximum likelihood as in
`dtwin_jax.preprocess.weak_form`; and, when draws of the states' estimation error are given, the
error it puts into the selected terms (errors in variables), so that a coefficient of a term
of poorly known states gets the wider interval it should.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.library import Library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.denoise import auto_half_width, noise_std
from dtwin_jax.preprocess.weak_form import (
    TEST_POWER,
    bump_functions,
    cut_segments,
    check_window,
    effective_share,
    reml_weight,
    weak_stats,
    weak_windows,
    window_filter,
    window_grams,
)

__all__ = ["accelerometer_kernels", "accelerometer_weak_stats", "constant_columns", "equivalent_linear",
           "segment_samples"]

# A record is cut into segments, each a record of its own, so that the rows' dense (W, W)
# matrices (the filters' nine Gram matrices and about five per equation) stay under this: they
# grow as the square of the record's length: zoo-0005's update (an 11 Hz SDOF) peaked at 2.4 GB
# at 40 s, 7.1 GB at 80 s, and was killed for memory at 160 s (2.4 GB at 80 s with segments).
# Every 40 s window of zoo members 0-49 stays whole (2.6 GiB at most).
_SEGMENT_BYTES = 3 << 30


def accelerometer_kernels(dt: float, width: int, held: bool,
                          power: int = TEST_POWER) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """The quadrature weights of `chi`, `chi'`, `chi''` on one window, for smooth signals
    (trapezoid) and for a held input (exact over each held step); `window_filter` places
    them on every window of a record.

    **Arguments:**

    - `dt`: the sample step, s.
    - `width`: the window in samples.
    - `held`: inputs held over each step (else band-limited: the trapezoid, and the second
      triple equals the first).
    - `power`: p of `chi = (s (1 - s))^p` (default `TEST_POWER`).

    **Returns:** `((phi, dphi, ddphi), (phi_h, dphi_h, ddphi_h))`, each `(width,)`: the smooth
    signals' weights and the held input's."""
    phi, dphi, ddphi, held_w = bump_functions(width, dt, power)
    if not held:
        return (phi, dphi, ddphi), (phi, dphi, ddphi)
    # The integral of chi' (chi'') over a held step is the step's change of chi (chi').
    steps = [np.append(np.diff(g / dt), 0.0) for g in (phi, dphi)]
    return (phi, dphi, ddphi), (held_w, steps[0], steps[1])


def constant_columns(lib: Library, x, u) -> list[int]:
    """Library columns constant on the data: a constant force shifts the static displacement
    only, which accelerometers do not see.

    **Arguments:**

    - `lib`: the library of `K` candidate terms.
    - `x`: states `(R, N, m)`.
    - `u`: inputs `(R, N, n)`.

    **Returns:** the indices of the columns whose spread is at most `1e-12` of their largest
    magnitude."""
    m = x.shape[-1]
    L = np.asarray(lib(jnp.asarray(np.reshape(x, (-1, m))), jnp.asarray(np.reshape(u, (-1, u.shape[-1])))))
    spread = np.max(L, axis=0) - np.min(L, axis=0)
    return [k for k in range(L.shape[1]) if spread[k] <= 1e-12 * max(np.max(np.abs(L[:, k])), 1e-300)]


def segment_samples(num_samples: int, width: int, d: int) -> int:
    """The longest segment (at most `num_samples`, at least 4 windows; halving) whose rows'
    dense matrices fit `_SEGMENT_BYTES`: `W` windows of `width` samples every
    `width // 8`, `(9 + 5 d) W^2` doubles for `d` equations.

    **Arguments:**

    - `num_samples`: the samples per record.
    - `width`: the window in samples.
    - `d`: the number of equations (degrees of freedom).

    **Returns:** the segment length in samples."""
    stride = max(1, width // 8)
    n = num_samples
    while n > 4 * width and 8 * (9 + 5 * d) * ((n - width) // stride + 1) ** 2 > _SEGMENT_BYTES:
        n = max(4 * width, n // 2)
    return n


def _rows(nominal: LinearSecondOrder, dt: float, a, u, interpolation: str, width, power: int) -> dict:
    """The weak targets `Y (R, W, d)` and what builds them: the filtered accelerations
    `int chi a`, `int chi' a` (`(R, W, d)` each), the smooth filters, the weights
    `ops (d, d, 3)` of the three filtered accelerations in each equation, and the
    accelerometers' noise variances `(d,)`."""
    R, N, d = a.shape
    m = nominal.m
    w0, _ = weak_windows(nominal, dt, N)
    width = w0 if width is None else int(width)
    stride = max(1, width // 8)
    check_window(N, width, stride, power)
    kernels, held = accelerometer_kernels(dt, width, interpolation == "held", power)
    M, B = np.asarray(nominal.M), np.asarray(nominal.B)
    J = np.asarray(jax.jacfwd(nominal.rate)(jnp.zeros(m), jnp.zeros(nominal.n)))
    idx = list(nominal.regressed_index)
    # The acceleration's held part (the input through M^-1 B) and its smooth rest.
    h = np.einsum("ij,rnj->rni", np.linalg.solve(M, B), u)
    rest = a - h
    Ia, Da, DDa = (window_filter(k, stride, rest) + window_filter(kh, stride, h) for k, kh in zip(kernels, held))
    # ops[i, j] weighs (int chi a_j, int chi' a_j, int chi'' a_j) in equation i's target.
    ops = np.zeros((d, d, 3))
    for ii, i in enumerate(idx):
        ops[ii, ii, 2] = 1.0
        ops[ii, :, 0] = -J[i, :d]
        ops[ii, :, 1] = J[i, d:2 * d]
    f_u = np.asarray(jax.vmap(nominal.rate_batch)(jnp.zeros((R, N, m)), jnp.asarray(u)))
    f_u = f_u - np.asarray(nominal.rate(jnp.zeros(m), jnp.zeros(nominal.n)))
    Y = (np.einsum("rwj,ij->rwi", Ia, ops[..., 0]) + np.einsum("rwj,ij->rwi", Da, ops[..., 1])
         + np.einsum("rwj,ij->rwi", DDa, ops[..., 2]) - window_filter(held[2], stride, f_u[..., idx]))
    # Sensor noise: the SG residual of the smooth rest (the force sensor's noise is in it too).
    noise_var = np.mean(np.asarray(noise_std(jnp.asarray(rest), auto_half_width(nominal, dt, N))) ** 2, axis=0)
    return {"Y": Y, "Ia": Ia, "Da": Da, "kernels": kernels, "ops": ops, "noise_var": noise_var,
            "width": width, "stride": stride}


def equivalent_linear(nominal: LinearSecondOrder, dt: float, a, u, interpolation: str = "held") -> np.ndarray:
    """The linear correction `(d, 2d)` (acceleration units) that best fits the accelerations,
    `a = f(q, v, u) + Delta [q; v]`: its columns `int chi'' q = int chi a` and
    `int chi'' v = -int chi' a` need no state estimate. A start for the states of a strongly
    nonlinear structure, whose nominal model is far from its equivalent linearization.

    Least squares over every window (the default of `weak_windows`) and record.

    **Arguments:**

    - `nominal`: the nominal model.
    - `dt`: the sample step, s.
    - `a`: measured accelerations of the degrees of freedom `(R, N, d)`.
    - `u`: measured inputs `(R, N, n)`.
    - `interpolation`: the inputs between samples: `"held"` (default, integrated exactly
      over each held step) or `"bandlimited"`.

    **Returns:** `Delta`, `(d, 2d)`: the correction's displacement then velocity columns, in
    acceleration units per state unit."""
    rows = _rows(nominal, dt, np.asarray(a, dtype=np.float64), np.asarray(u, dtype=np.float64), interpolation,
                 None, TEST_POWER)
    d = rows["Y"].shape[-1]
    X = np.concatenate([rows["Ia"], -rows["Da"]], axis=-1).reshape(-1, 2 * d)
    scale = np.maximum(np.linalg.norm(X, axis=0), 1e-300)
    delta, *_ = np.linalg.lstsq(X / scale, rows["Y"].reshape(-1, d), rcond=1e-10)
    return (delta / scale[:, None]).T


def accelerometer_weak_stats(nominal: LinearSecondOrder, lib: Library, dt: float, a, u, x, *,
                             interpolation: str = "held", state_draws=None, coef=None,
                             equation_error: bool = True, width: int | None = None,
                             power: int = TEST_POWER) -> tuple[sampler.SuffStats, dict]:
    """Weak-form statistics of the velocity equations from accelerations and force.

    **Arguments:**

    - `nominal`: the nominal model (no extra states).
    - `lib`: the library of `K` candidate terms.
    - `dt`: sample step, s.
    - `a`: `(R, N, d)` measured accelerations of the degrees of freedom (state units / s^2).
    - `u`: `(R, N, n)` measured inputs.
    - `x`: `(R, N, m)` estimated states, where the library is evaluated.
    - `interpolation`: `"held"` (default: inputs integrated exactly over each held step) or
      `"bandlimited"`.
    - `state_draws`: `(S, R, N, m)` draws of the states' estimation error, or None; with
      `coef`, the error they put into those terms enters the rows' covariance.
    - `coef`: `(q, K)` coefficients of the terms, one row per velocity equation, or None;
      used only with `state_draws`.
    - `equation_error`: add a white equation error sized by REML, and weigh the rows by their
      effective share (default True).
    - `width`: window in samples (default: one period of the fastest nominal mode); the
      stride is `width // 8`.
    - `power`: p of `chi = (s (1 - s))^p` (default `TEST_POWER`).

    **Returns:** `(stats, info)`: `SuffStats` batched over the velocity equations (all `K`
    columns; columns constant on the data are zero), and a description dict."""

    a, u, x = (np.asarray(v, dtype=np.float64) for v in (a, u, x))
    d = a.shape[-1]
    width = weak_windows(nominal, dt, a.shape[1])[0] if width is None else int(width)
    length = segment_samples(a.shape[1], width, d)
    if length < a.shape[1]:  # a long record: segments, each a record of its own
        a, u, x = (cut_segments(v, length) for v in (a, u, x))
        if state_draws is not None:
            state_draws = np.stack([cut_segments(np.asarray(s), length) for s in state_draws])
    R, N, d = a.shape
    m = nominal.m
    rows = _rows(nominal, dt, a, u, interpolation, width, power)
    Y, ops, kernels, stride = rows["Y"], rows["ops"], rows["kernels"], rows["stride"]
    flat_u = jnp.asarray(u.reshape(R * N, -1))

    def columns(states):
        raw = np.asarray(lib(jnp.asarray(states.reshape(R * N, m)), flat_u)).reshape(R, N, -1)
        return window_filter(kernels[2], stride, raw)

    L = columns(x)
    for k in constant_columns(lib, x, u):
        L[..., k] = 0.0
    noise_var = rows["noise_var"]
    grams = window_grams(kernels, Y.shape[1], stride)
    S_x = np.einsum("p,ipa,ipb,abvw->ivw", noise_var, ops, ops, grams)
    S_w = grams[2, 2]
    S_e = np.zeros_like(S_x)
    if state_draws is not None and coef is not None:
        coef = np.asarray(coef)
        for draw in np.asarray(state_draws):
            err = np.einsum("rwk,ik->irw", columns(x + draw) - L, coef)
            S_e += np.einsum("irv,irw->ivw", err, err) / (R * len(state_draws))
    weights, scale = np.zeros(d), np.ones(d)
    norms = np.linalg.norm(L.reshape(-1, L.shape[-1]), axis=0)
    live = np.flatnonzero(norms > 0)
    Ls = L[..., live] / norms[live]
    base = S_x + S_e
    if equation_error:
        for i in range(d):
            weights[i] = reml_weight(Ls, Y[..., i], base[i], S_w)
    cov = base + weights[:, None, None] * S_w[None]
    stats = weak_stats(jnp.asarray(Y), jnp.asarray(L), jnp.asarray(cov))
    if equation_error:
        for i in range(d):
            scale[i] = effective_share(Ls, Y[..., i], cov[i])
        stats = sampler.weigh(stats, jnp.asarray(scale))
    info = {
        "method": "weak-form (accelerometers): test functions chi'', the nominal part from the "
                  "accelerations by parts",
        "width": rows["width"], "stride": rows["stride"], "power": power, "windows": int(Y.shape[1]),
        "segments": int(R), "segment_samples": int(N),
        "acceleration_noise_std": np.sqrt(noise_var).tolist(),
        "effective_share": scale.tolist(),
        "equation_error_share": [float(w * np.trace(S_w) / (w * np.trace(S_w) + np.trace(base[i])))
                                 for i, w in enumerate(weights)],
        "equation_error_weight": weights.tolist(),
        "state_error_share": [float(np.trace(S_e[i]) / max(np.trace(cov[i]), 1e-300)) for i in range(d)],
    }
    return stats, info
