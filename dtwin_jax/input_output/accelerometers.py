"""The input-output regression on accelerometers alone: the weak rows at the anchored
states (`dtwin_jax.preprocess.weak_form_accelerometers`) and the widening of what the anchor's
loop feeds back into itself (`dtwin_jax.preprocess.accelerometers.state_feedback`)."""

from __future__ import annotations

import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.library import Library, parse_library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.accelerometers import state_feedback, unsettled_warnings
from dtwin_jax.preprocess.weak_form_accelerometers import (
    accelerometer_weak_stats,
    constant_columns,
)

__all__ = ["WIDENING_WARNING", "accelerometer_regression", "without_constant_columns"]

# A term whose interval the feedback widens more than this (the states follow whatever
# coefficients the anchor holds: zoo-0018's cubic coupling, 11% off) is named in a warning.
WIDENING_WARNING = 3.0


def without_constant_columns(lib: Library, nominal: LinearSecondOrder, u) -> tuple[Library, list[str]]:
    """The library without its columns that are constant whatever the states (`1`), and their names.

    The test functions of the accelerometers' weak form annihilate a constant column, so it is
    dropped rather than regressed.

    **Arguments:**

    - `lib`: the library.
    - `nominal`: the nominal model (its number of states `m`).
    - `u`: `(R, N, n)` measured inputs (the columns are probed at random states and these inputs).

    **Returns:** `(lib, dropped)`: the library without the constant columns (`lib` itself when
    there are none) and the dropped columns' names. Raises a `DataError` when no column is left."""
    R, N, _ = u.shape
    x = np.random.default_rng(0).standard_normal((1, min(N, 256), nominal.m))
    drop = constant_columns(lib, x, np.asarray(u)[:1, :x.shape[1]])
    if not drop:
        return lib, []
    kept = [name for k, name in enumerate(lib.names) if k not in drop]
    if not kept:
        raise DataError("accelerometers alone see no constant force, and the library has nothing else")
    return parse_library("terms:" + ";".join(kept), lib.num_states, lib.num_inputs), [lib.names[k] for k in drop]


def accelerometer_regression(nominal: LinearSecondOrder, lib: Library, dt: float, a, u, x, states_info: dict,
                             loop_names, interpolation: str) -> tuple:
    """The weak-form statistics at the anchored states and the feedback's widening.

    **Arguments:**

    - `nominal`: the nominal model.
    - `lib`: the (reduced) library.
    - `dt`: sample step, s.
    - `a`: `(R, N, d)` measured accelerations.
    - `u`: `(R, N, n)` inputs (zeros: output-only).
    - `x`: `(R, N, m)` the states of `dtwin_jax.preprocess.accelerometers.accelerometer_states`.
    - `states_info`: their info dict (`error_draws` and `coefficients` are popped from it).
    - `loop_names`: the term names of the library the loop ran with.
    - `interpolation`: the inputs' (`"held"` or `"bandlimited"`).

    **Returns:** `(stats, info, feedback, warnings)`: the `dtwin_jax.sampler.SuffStats` of the
    velocity equations, the weak form's description dict, the result of
    `dtwin_jax.preprocess.accelerometers.state_feedback` (None without coefficients or error draws),
    and a list of warning lines."""
    warnings = unsettled_warnings(states_info)
    draws, coef = states_info.pop("error_draws", None), states_info.pop("coefficients")
    if coef is not None:  # the loop's coefficients on the library as reduced since
        coef = coef[:, [list(loop_names).index(name) for name in lib.names]]
    stats, info = accelerometer_weak_stats(nominal, lib, dt, a, u, x, interpolation=interpolation,
                                           state_draws=draws, coef=coef)
    feedback = None
    if coef is not None and draws is not None:
        feedback = state_feedback(nominal, lib, dt, a, u, x, coef, draws, interpolation=interpolation)
        widening = float(np.max(np.linalg.svd(feedback["gain"], compute_uv=False), initial=1.0))
        info["state_feedback"] = {"eigenvalues": [round(v, 4) for v in feedback["eigenvalues"][:4]],
                                  "largest_widening": widening}
        if widening > WIDENING_WARNING:
            rows = np.linalg.norm(feedback["gain"], axis=1)  # each term's widening (isotropic spread)
            regressed = [nominal.state_names[i] for i in nominal.regressed_index]
            loose = [f"{lib.names[k]} ({regressed[e]})" for (e, k), g in zip(feedback["index"], rows)
                     if g >= rows.max() / 2]
            warnings.append(f"accelerometers alone leave {', '.join(loose)} poorly fixed (the states follow "
                            f"the coefficients the twin holds): intervals widened up to {widening:.1f}x; "
                            "a displacement sensor would pin them down")
    return stats, info, feedback, warnings
