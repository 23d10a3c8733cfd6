"""The twin's model error: its free-run error on the data it was updated from.

A posterior over the library's coefficients carries the parameter uncertainty only; what
the library misses (and what the posterior mean gets wrong over a long free run) shows as a
free-run error on the training records themselves. Its standard deviation per measured
state is saved with the twin and added to every prediction's band
(`dtwin_jax.models.prediction.with_model_error`), unless `predict(..., model_error=False)`.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np

__all__ = ["training_model_error"]

# At most this many records and samples are simulated (the first ones).
_RECORDS = 4
_SAMPLES = 200_000
# The start transient left out: the initial velocity is an estimate.
_TRANSIENT = 0.05


def training_model_error(twin, t, x, u, x_index, x0) -> tuple[list[float] | None, str | None]:
    """Free-run RMS error of an unbatched updated twin on its training records.

    Simulates the first records (at most 4, and at most 200,000 samples in all) from their
    estimated initial states under their measured inputs, with the twin's posterior mean and
    no model error, and compares the measured states after the start transient (the first 5%
    of each simulated record: the initial velocity is an estimate).

    **Arguments:**

    - `twin`: the updated twin, a `dtwin_jax.models.prediction.UpdatedTwin`, unbatched.
    - `t`: sample times `(N,)`, s.
    - `x`: the measured states `(R, N, p)` of the `R` records, in the states' units.
    - `u`: the inputs `(R, N, n)`.
    - `x_index`: the indices `(p,)` of the measured states among the twin's `m` states.
    - `x0`: the estimated initial states `(R, m)` of the records.

    **Returns:** `(sd, None)`: `sd`, a list of `m` floats, the RMS error of each state in its
    units (0 for a state not measured); or `(None, why)`, a one-line reason, when the free run
    diverges or fails.
    """
    from dtwin_jax.models.prediction import PredictionWarning, predict

    R, N, _ = x.shape
    stacked = eqx.tree_at(lambda s: s.coefficients, twin, twin.coefficients[None])
    n = max(1, min(N, _SAMPLES // min(R, _RECORDS)))
    skip = int(_TRANSIENT * n)
    squares, count = np.zeros(len(x_index)), 0
    for r in range(min(R, _RECORDS)):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", PredictionWarning)
                path = predict(stacked, x0[r], t[:n], u[r, :n], model_error=False)["mean"]
        except Exception as e:  # noqa: BLE001 - the update stands; the band then lacks model error
            return None, f"the twin's free run on its training data failed ({(str(e).splitlines() or [''])[0][:200]})"
        err = np.asarray(path)[skip:, list(x_index)] - x[r, skip:n]
        if not np.all(np.isfinite(err)):
            return None, "the twin's free run on its training data is not finite"
        squares += np.sum(err**2, axis=0)
        count += err.shape[0]
    sd = np.zeros(twin.nominal.m)
    sd[list(x_index)] = np.sqrt(squares / max(count, 1))
    return sd.tolist(), None
