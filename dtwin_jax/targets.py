"""Regression targets and their sufficient statistics.

Framework 1 (input-output): the nominal model is removed from the measured rates (the paper's
Eq. 14), ``y_i = xdot_i - f_i(x, u)`` for every regressed state ``i`` (velocities and extra
states; the kinematic rows are exact), and each ``y_i`` is regressed on one library ``L(x, u)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.library import Library
from dtwin_jax.systems import LinearSecondOrder

__all__ = ["input_output_targets", "equation_stats", "correct_input_noise"]


def input_output_targets(nominal: LinearSecondOrder, x, u, xdot) -> jax.Array:
    """Eq. 14: measured rates minus the nominal rates of the regressed states.

    ``x (N, m)``, ``u (N, n)``, ``xdot (N, m)`` -> ``(N, len(nominal.regressed_index))``.
    """
    idx = jnp.asarray(nominal.regressed_index)
    return (jnp.asarray(xdot) - nominal.rate_batch(jnp.asarray(x), jnp.asarray(u)))[:, idx]


def equation_stats(L, Y) -> sampler.SuffStats:
    """Sufficient statistics of every target column of ``Y (N, q)`` on one library ``L (N, K)``,
    batched over the ``q`` equations."""
    L = jnp.asarray(L)
    Y = jnp.asarray(Y)
    gram = L.T @ L
    return sampler.SuffStats(
        jnp.broadcast_to(gram, (Y.shape[1],) + gram.shape),
        (L.T @ Y).T,
        jnp.sum(Y * Y, axis=0),
        jnp.full(Y.shape[1], float(L.shape[0])),
    )


def correct_input_noise(stats: sampler.SuffStats, lib: Library, nominal: LinearSecondOrder, noise_var) -> sampler.SuffStats:
    """Remove the input noise's contribution to the statistics (errors in variables).

    The noise ``n`` on ``u_j`` sits in the library column ``u_j`` (adding ``N var_j`` to its
    squared norm) and, through the removed nominal ``M^-1 B u``, in every velocity target with
    the opposite sign (adding ``-N (M^-1 B)_ij var_j`` to ``L^T y``). Unremoved, it shows up as
    a spurious ``u_j`` term at high noise.
    """
    gain = np.linalg.solve(np.asarray(nominal.M), np.asarray(nominal.B))  # (d, n)
    gram, xty = np.array(stats.gram), np.array(stats.xty)
    n_rows = float(np.asarray(stats.n)[0])
    regressed = nominal.regressed_index
    for j, name in enumerate(nominal.input_names):
        if name not in lib.names:
            continue
        k = lib.names.index(name)
        gram[:, k, k] -= n_rows * noise_var[j]
        for e, i in enumerate(regressed):
            if i in nominal.velocity_index:
                xty[e, k] += n_rows * gain[i - nominal.d, j] * noise_var[j]
    return stats._replace(gram=jnp.asarray(gram), xty=jnp.asarray(xty))
