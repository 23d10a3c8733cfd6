"""Regression targets and their sufficient statistics.

Framework 1 (input-output): the nominal model is removed from the measured rates (the paper's
Eq. 14), `y_i = xdot_i - f_i(x, u)` for every regressed state `i` (velocities and extra
states; the kinematic rows are exact), and each `y_i` is regressed on one library `L(x, u)`.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from dtwin_jax import sampler
from dtwin_jax.library import Library
from dtwin_jax.linalg import mass_solve
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.preprocess.denoise import input_noise_variance, kinematic_smoother

__all__ = [
    "input_output_targets",
    "equation_stats",
    "correct_input_noise",
    "smoothed_input_output_stats",
    "input_output_stats",
]


@eqx.filter_jit  # one program: called eagerly, each operation was one (a warm call loads each)
def input_output_targets(nominal: LinearSecondOrder, x, u, xdot) -> jax.Array:
    """Eq. 14: measured rates minus the nominal rates of the regressed states.

    **Arguments:**

    - `nominal`: the nominal model.
    - `x`: `(N, m)` states (denoised or estimated).
    - `u`: `(N, n)` inputs.
    - `xdot`: `(N, m)` measured (or estimated) rates.

    **Returns:** the targets `xdot - f(x, u)` of the regressed states, `(N, len(nominal.regressed_index))`,
    in the rates' units.
    """
    idx = jnp.asarray(nominal.regressed_index)
    return (jnp.asarray(xdot) - nominal.rate_batch(jnp.asarray(x), jnp.asarray(u)))[:, idx]


def equation_stats(L, Y) -> sampler.SuffStats:
    """Sufficient statistics of every target column on one library, batched over the equations.

    **Arguments:**

    - `L`: `(N, K)` the library's columns.
    - `Y`: `(N, q)` the targets, one column per equation.

    **Returns:** `sampler.SuffStats` batched over the `q` equations: `gram (q, K, K)`,
    `xty (q, K)`, `yty (q,)` and `n (q,)` (the number of rows `N`).
    """
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

    The noise `n` on `u_j` sits in the library column `u_j` (adding `N var_j` to its
    squared norm) and, through the removed nominal `M^-1 B u`, in every velocity target with
    the opposite sign (adding `-N (M^-1 B)_ij var_j` to `L^T y`). Unremoved, it shows up as
    a spurious `u_j` term at high noise.

    **Arguments:**

    - `stats`: `sampler.SuffStats` batched over the regressed equations.
    - `lib`: the library (only its input columns, named as the nominal's inputs, are corrected).
    - `nominal`: the nominal model (`M`, `B`, the input names and the regressed states).
    - `noise_var`: `(n,)` variance of the noise on each input (input units squared); may be traced.

    **Returns:** the corrected `sampler.SuffStats` (`gram` and `xty` changed).
    """
    gain = mass_solve(nominal.M, nominal.B)  # (d, n)
    noise_var = jnp.asarray(noise_var)
    gram, xty = jnp.asarray(stats.gram), jnp.asarray(stats.xty)
    n_rows = jnp.asarray(stats.n)[..., 0]
    for j, name in enumerate(nominal.input_names):  # static: names and indices
        if name not in lib.names:
            continue
        k = lib.names.index(name)
        gram = gram.at[..., k, k].add(-n_rows[..., None] * noise_var[..., j, None])
        for e, i in enumerate(nominal.regressed_index):
            if i in nominal.velocity_index:
                shift = n_rows * gain[i - nominal.d, j] * noise_var[..., j]
                xty = xty.at[..., e, k].add(shift)
    return stats._replace(gram=gram, xty=xty)


@functools.partial(jax.jit, static_argnames=("half_width", "correct_inputs"))
def smoothed_input_output_stats(
    nominal: LinearSecondOrder, lib: Library, xs, u, xdot, half_width: int, *, correct_inputs: bool = True, keep=None
) -> tuple[sampler.SuffStats, jax.Array | None]:
    """Statistics of every regressed equation from denoised states, pooled over records.

    With `correct_inputs` (and an `input` family in `lib`) the input noise is estimated
    (`denoise.input_noise_variance`) and removed (`correct_input_noise`). Jitted
    (`half_width` and `correct_inputs` static; `lib` holds no arrays).

    **Arguments:**

    - `nominal`: the nominal model.
    - `lib`: the library.
    - `xs`: `(R, N, m)` denoised states.
    - `u`: `(R, N, n)` measured inputs.
    - `xdot`: `(R, N, m)` measured (or estimated) rates.
    - `half_width`: half width of the noise filters, samples (static).
    - `correct_inputs`: estimate and remove the input noise.
    - `keep`: `(R, N)` bool, only those rows enter the statistics (the input noise is still
      estimated from whole records), or None (every row); a mask, not a subset, so one
      compiled program serves every count.

    **Returns:** `(stats, noise_var)`: `sampler.SuffStats` batched over the regressed
    equations, and the input noise variance `(n,)`, or None when not corrected.
    """
    xs, u, xdot = (jnp.asarray(a) for a in (xs, u, xdot))
    m, n = xs.shape[-1], u.shape[-1]
    xs_flat, u_flat = xs.reshape(-1, m), u.reshape(-1, n)
    Y = input_output_targets(nominal, xs_flat, u_flat, xdot.reshape(-1, m))
    L = lib(xs_flat, u_flat)
    if keep is None:
        stats = equation_stats(L, Y)
    else:
        w = jnp.asarray(keep, L.dtype).reshape(-1, 1)
        stats = equation_stats(L * w, Y * w)
        stats = stats._replace(n=jnp.full_like(stats.n, jnp.sum(w)))
    if not (correct_inputs and lib.uses_inputs):
        return stats, None
    noise_var = input_noise_variance(nominal, xs, u, xdot, half_width)
    return correct_input_noise(stats, lib, nominal, noise_var), noise_var


@functools.partial(jax.jit, static_argnames=("dt", "half_width"))
def input_output_stats(
    nominal: LinearSecondOrder, lib: Library, dt: float, x, u, xdot, half_width: int
) -> sampler.SuffStats:
    """The whole framework-1 chain for measured records, from the raw states to the statistics.

    Kinematic RTS smoothing of the states (records smoothed one by one and pooled), targets
    (Eq. 14), library, statistics and the input-noise correction. Jitted (`dt` and
    `half_width` static), vmappable over data.

    **Arguments:**

    - `nominal`: the nominal model.
    - `lib`: the library.
    - `dt`: sample step, s (static).
    - `x`: `(N, m)` or `(R, N, m)` measured states.
    - `u`: `(N, n)` or `(R, N, n)` measured inputs.
    - `xdot`: measured rates, shaped like `x`.
    - `half_width`: half width of the noise filters, samples (static, see `denoise.auto_half_width`).

    **Returns:** `sampler.SuffStats` batched over the regressed equations.
    """
    x, u, xdot = (jnp.asarray(a) for a in (x, u, xdot))
    if x.ndim == 2:
        x, u, xdot = x[None], u[None], xdot[None]
    xs = jax.vmap(lambda a, b, c: kinematic_smoother(nominal, dt, a, b, c, half_width))(x, xdot, u)
    return smoothed_input_output_stats(nominal, lib, xs, u, xdot, half_width)[0]
