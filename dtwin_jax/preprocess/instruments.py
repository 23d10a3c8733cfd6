"""The reference signal of a closed loop as an instrument.

Under feedback the input reacts to everything that moves the states, an unmeasured force
included, so the library columns (the input's among them) are correlated with the equation
error, and least squares is biased however long the record. A reference (set-point) signal
is chosen by the operator, independent of the plant's disturbances and of the sensors' noise:
the part of the states and input that it explains is an instrument. Two-stage least squares:
the states and inputs are first regressed on the reference's lags (both ways in time: the
reference is exogenous at every lag), the library at those fitted values gives the
instruments `Z`, and the regression uses the columns' projection on `Z`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.errors import DataError

__all__ = ["REFERENCE_SPAN", "REFERENCE_TAPS", "reference_fit", "instrumented_stats"]

# The first stage's lags: this many on each side of the sample, over at most this span (s)
# (an eighth of the record when shorter): a closed loop settles within a few time constants.
REFERENCE_TAPS = 32
REFERENCE_SPAN = 0.5


def reference_fit(signals, reference, dt: float) -> np.ndarray:
    """The part of `signals (R, N, c)` explained by the lags of `reference (R, N, r)`.

    The lags span `+-REFERENCE_SPAN` s, or an eighth of the record when that is shorter.

    **Arguments:**

    - `signals`: the states and inputs to instrument, `(R, N, c)` (R records of N samples).
    - `reference`: the closed loop's set-point, `(R, N, r)`, same records and samples;
      raises `DataError` otherwise.
    - `dt`: the sample step, s.

    **Returns:** the fitted values `(R, N, c)`, float64: least squares on a constant and
    `2 REFERENCE_TAPS + 1` lags of every reference channel spread over `+-REFERENCE_SPAN`
    (pooled over records; edges padded with the edge value)."""
    signals, reference = np.asarray(signals, np.float64), np.asarray(reference, np.float64)
    R, N, c = signals.shape
    if reference.shape[:2] != (R, N):
        raise DataError(f"'reference' must have the records and samples of 'x', got {reference.shape[:2]} and {(R, N)}")
    span = max(1, int(round(min(REFERENCE_SPAN, N * dt / 8) / dt)))
    lags = np.unique(np.round(np.linspace(-span, span, 2 * REFERENCE_TAPS + 1)).astype(int))
    padded = np.pad(reference, ((0, 0), (span, span), (0, 0)), mode="edge")
    feats = np.concatenate([padded[:, span + k:span + k + N] for k in lags] + [np.ones((R, N, 1))], axis=-1)
    F, S = feats.reshape(R * N, -1), signals.reshape(R * N, c)
    scale = np.maximum(np.linalg.norm(F, axis=0), 1e-300)
    beta, *_ = np.linalg.lstsq(F / scale, S, rcond=None)
    return ((F / scale) @ beta).reshape(R, N, c)


def instrumented_stats(Y, L, Z, cov) -> sampler.SuffStats:
    """Two-stage least-squares statistics of every regressed equation, pooled over records.

    **Arguments:**

    - `Y`: targets, `(R, W, q)` (R records, W rows, q regressed equations).
    - `L`: library columns, `(R, W, K)`.
    - `Z`: instruments, `(R, W, J)`, `J >= K`.
    - `cov`: the rows' noise covariance per equation, `(q, W, W)` (the same in every record).

    **Returns:** `SuffStats` batched over the `q` equations, of the whitened columns projected
    on the whitened instruments: `gram = L' P L`, `xty = L' P y` (`P` the projection); `yty`,
    `n` as `weak_form.weak_stats`. The sampler's residual `y - P L theta` then holds what the
    instruments do not explain: wider intervals, not narrower."""


    from scipy.linalg import solve_triangular

    Y, L, Z, cov = (np.asarray(v, np.float64) for v in (Y, L, Z, cov))
    out = []
    for i in range(Y.shape[-1]):
        c = cov[i] + 1e-10 * np.trace(cov[i]) / cov.shape[-1] * np.eye(cov.shape[-1])
        chol = np.linalg.cholesky(c)
        Lw, Zw = (np.concatenate([solve_triangular(chol, A[r], lower=True) for r in range(A.shape[0])]) for A in (L, Z))
        yw = np.concatenate([solve_triangular(chol, Y[r, :, i], lower=True) for r in range(Y.shape[0])])
        U, sv, _ = np.linalg.svd(Zw / np.maximum(np.linalg.norm(Zw, axis=0), 1e-300), full_matrices=False)
        U = U[:, sv > 1e-10 * sv[0]]  # dependent instruments (a constant twice) add no direction
        PL = U @ (U.T @ Lw)
        out.append((PL.T @ PL, PL.T @ yw, yw @ yw, float(Lw.shape[0])))
    return sampler.SuffStats(*(jnp.asarray(np.stack(v)) for v in zip(*out)))
