"""Framework 2's statistics: the jittable steps from measured states to the sampler's
sufficient statistics, shared by `update_output_only` and the noise studies
(`dtwin_jax.studies`).

Drift: Kramers-Moyal targets (`dtwin_jax.output_only.kramers_moyal`) in two passes, the second
moving the regressors along a first sampled estimate (`output_only_drift_stats`).
Diffusion, given that drift: the Kalman likelihood's maximum and its EM targets
(`dtwin_jax.output_only.statespace`), weighted to carry the likelihood's information
(`diffusion_statistics`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from dtwin_jax import sampler
from dtwin_jax._compile import aot
from dtwin_jax._compile.quick_compile import quick_jit
from dtwin_jax.input_output.targets import equation_stats
from dtwin_jax.library import Library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.update.result import SamplerSettings

__all__ = [
    "FIRST_PASS_ROWS",
    "DiffusionFit",
    "brownian_variance",
    "correction_margin",
    "diffusion_regression",
    "diffusion_statistics",
    "drift_pass",
    "first_pass_estimate",
    "first_pass_rows",
    "first_pass_settings",
    "output_only_drift_stats",
]


FIRST_PASS_ROWS = 20000


def first_pass_settings(settings: SamplerSettings) -> SamplerSettings:
    """The first pass's short run: `settings`' chains, one chunk of burn-in and one of
    draws (`sampler.CHUNK` sweeps each), so that it runs the main run's compiled
    chunk program (`sampler.sample_in_chunks`).

    **Arguments:**

    - `settings`: the main run's `SamplerSettings`.

    **Returns:** `SamplerSettings`, `settings` with `num_burnin` and `num_draws` both
    `sampler.CHUNK`."""
    return dataclasses.replace(settings, num_draws=sampler.CHUNK, num_burnin=sampler.CHUNK)


def first_pass_rows(x) -> int:
    """Samples of records the first pass uses: whole records up to `FIRST_PASS_ROWS` samples.

    **Arguments:**

    - `x`: the records, shape `(R, N, m)` (only the shape is used).

    **Returns:** the number of drift rows (an int): `N - 2` per record for as many whole
    records as fit in `FIRST_PASS_ROWS` (at least one), or `FIRST_PASS_ROWS` for a single
    record."""
    R, N, _ = x.shape
    return max(1, FIRST_PASS_ROWS // N) * (N - 2) if R > 1 else FIRST_PASS_ROWS


@functools.partial(jax.jit, static_argnums=(1,))
def drift_pass(nominal: LinearSecondOrder, lib: Library, x, dt, noise_var, coef, smoothing, rows) -> tuple:
    """One pass of `output_only_drift_stats`: the Kramers-Moyal statistics of the first
    `rows` samples with the regressors moved along the nominal model plus `coef`.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `lib`: the drift `Library` (no inputs; static).
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `coef`: `(q, K)` the drift perturbation's current estimate (zeros for the nominal model
      alone).
    - `smoothing`: variances `(m,)` over which the library's non-smooth families are averaged
      (zeros: exact terms).
    - `rows`: how many samples to use, from the start in record order (may be traced).

    **Returns:** `(stats, margin)`: the `SuffStats` batched over the `q` regressed states,
    the Gram matrices' eigenvalues floored (`_nearest_pd`), and the `correction_margin`
    `(q,)` of the corrected Gram matrices before the floor."""
    st = kramers_moyal.drift_statistics(nominal, lib, x, dt, noise_var, coef, smoothing=smoothing, rows=rows)
    return st._replace(gram=_nearest_pd(st.gram)), correction_margin(st.gram)


@quick_jit()
def first_pass_estimate(nominal: LinearSecondOrder, dt, noise_var, trace: sampler.GibbsTrace) -> tuple:
    """The drift of the first pass's draws: the means of the terms with PIP > 0.5 and the
    library's smoothing for the second pass.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `trace`: the first pass's `GibbsTrace`, leading axes `(q, chains, draws, ...)`.

    **Returns:** `(coef, smoothing)`: `coef (q, K)` the means of the selected terms (others
    0), and `smoothing (m,)` the variances `1.5 dt Gamma - s^2` (floored at 0) at the
    velocities, zero elsewhere (`Gamma` from `brownian_variance`)."""
    vel = jnp.asarray(nominal.velocity_index)
    gamma_draws, theta = jnp.asarray(trace.gamma), jnp.asarray(trace.theta)
    included = gamma_draws.sum(axis=(1, 2))  # (q, K)
    chosen = included > 0.5 * gamma_draws.shape[1] * gamma_draws.shape[2]
    coef = jnp.where(chosen, theta.sum(axis=(1, 2)) / jnp.maximum(included, 1), 0.0)
    gamma = brownian_variance(nominal, dt, noise_var, jnp.asarray(trace.sigma2).mean(axis=(1, 2)))
    # Gamma 1.5 dt: the step k+1 -> k+2 seen from sample k; the noise's own smoothing is s^2.
    c = jnp.maximum(1.5 * dt * gamma - jnp.asarray(noise_var)[vel], 0.0)
    return coef, jnp.zeros(nominal.m).at[vel].set(c)


@functools.partial(jax.jit, static_argnums=(1, 6))
def output_only_drift_stats(nominal: LinearSecondOrder, lib: Library, x, dt, noise_var, key,
                            settings: SamplerSettings = SamplerSettings()) -> tuple:
    """Kramers-Moyal drift statistics of records (batched over the regressed states), with
    the regressors moved along the model's drift (two passes).

    The first pass moves them along the nominal model only, on the first ~20000 samples
    (`first_pass_rows`); a short sampler run (`first_pass_settings`) gives the
    selected terms (PIP > 0.5) and their means, and the second pass moves the regressors
    along the nominal model plus that estimate (its error enters only the O(dt) shift). A
    greedy first estimate is not enough: on example 2's 256 terms it adds fifth-degree terms
    whose rough flow spoils the shift. The second pass uses all samples. Both passes are one
    compiled loop body (statistics, then the short run; the second pass's run goes unused).
    Pure and jittable (`dt` static through the shapes).
    `update_output_only` runs the same steps as separate programs, with the same draws.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `lib`: the drift `Library` (no inputs; static).
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `key`: a JAX random key for the short runs: pass `k` uses `jax.random.split(key, 2)[k]`,
      its equation `j` the `j`-th of `split` of that into `q`.
    - `settings`: the main run's `SamplerSettings` (static), of which the short run takes
      `first_pass_settings`.

    **Returns:** `(stats, margin)`: the `SuffStats` batched over the `q` regressed states, and
    `margin (q,)` the `correction_margin` of the corrected Gram matrices before their
    eigenvalues are floored.
    """
    q = len(nominal.regressed_index)
    R, N, _ = x.shape
    first_settings = first_pass_settings(settings)  # the update's first pass, as one call

    def one_pass(carry, inputs):
        key, rows = inputs
        coef, smoothing, _, _ = carry
        st, margin = drift_pass(nominal, lib, x, dt, noise_var, coef, smoothing, rows)
        trace = jax.vmap(lambda k, s: sampler.sample(k, s, first_settings))(jax.random.split(key, q), st)
        coef, smoothing = first_pass_estimate(nominal, dt, noise_var, trace)
        return (coef, smoothing, st, margin), None

    K = lib.K
    blank = sampler.SuffStats(jnp.zeros((q, K, K)), jnp.zeros((q, K)), jnp.zeros(q), jnp.zeros(q))
    carry = (jnp.zeros((q, K)), jnp.zeros(nominal.m), blank, jnp.zeros(q))
    passes = (jax.random.split(key, 2), jnp.asarray([first_pass_rows(x), R * (N - 2)]))
    (_, _, st, margin), _ = jax.lax.scan(one_pass, carry, passes)
    return st, margin


def correction_margin(gram) -> jax.Array:
    """Smallest eigenvalue of the correlation matrices of noise-corrected Gram matrices:
    near zero (collinear terms) or slightly below from sampling error; well below zero where
    the noise correction removes more than the data hold, and the regression then amplifies
    noise in those directions without bound.

    **Arguments:**

    - `gram`: the noise-corrected Gram matrices, shape `(q, K, K)`.

    **Returns:** the smallest eigenvalues, shape `(q,)` (dimensionless)."""
    scale = jnp.sqrt(jnp.maximum(jnp.diagonal(gram, axis1=-2, axis2=-1), 1e-300))
    return jnp.linalg.eigvalsh(gram / (scale[..., :, None] * scale[..., None, :]))[..., 0]


@quick_jit()
def brownian_variance(nominal: LinearSecondOrder, dt, noise_var, residual_var) -> jax.Array:
    """The velocities' diffusion seen in the drift regression's residual variance, less the
    measurement noise's share.

    A rough estimate (it holds the drift's misfit too) for smoothing the non-smooth library
    families: over a step the velocity moves by a Brownian increment of variance
    `Gamma * time`, and `E[sign(v)]` over it is a smoothed sign (`Library.__call__`).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `residual_var`: the drift regression's residual variances, shape `(r,)` (target units
      squared), the velocities' first.

    **Returns:** `Gamma`, shape `(d,)` (velocity^2 / s), floored at zero.
    """
    Phi, Psi = kramers_moyal.propagators(nominal, dt)
    noise = jnp.diag(jnp.asarray(noise_var))
    back = jnp.linalg.inv(Psi)
    noise_in_targets = jnp.diagonal(back @ (noise + Phi @ noise @ Phi.T) @ back.T)
    vel = jnp.asarray(nominal.velocity_index)
    return dt * jnp.maximum(jnp.asarray(residual_var)[: nominal.d] - noise_in_targets[vel], 0.0)


def _nearest_pd(gram):
    """Noise-corrected Gram matrices `(q, K, K)` can lose definiteness in directions the data
    barely sees; floor the eigenvalues of the correlation matrix at `1e-9`."""
    scale = jnp.sqrt(jnp.maximum(jnp.diagonal(gram, axis1=-2, axis2=-1), 1e-300))
    corr = gram / (scale[..., :, None] * scale[..., None, :])
    w, v = jnp.linalg.eigh(corr)
    corr = jnp.einsum("...ij,...j,...kj->...ik", v, jnp.maximum(w, 1e-9), v)
    return corr * (scale[..., :, None] * scale[..., None, :])


class DiffusionFit(NamedTuple):
    """`diffusion_statistics`' output for records cut into `P` segments of `L` samples."""

    stats: sampler.SuffStats  # weighted EM-target statistics, gram (d, Kd, Kd) .. n (d,)
    gamma: jax.Array  # (d,) maximum-likelihood diffusion, velocity^2 / s
    gamma_cov: jax.Array  # (d, d) its covariance, the noise profiled out
    noise: jax.Array  # (P, m) fitted measurement noise variances per segment
    lin: statespace.Linearization  # batched over segments, at the maximum
    segments: jax.Array  # (P, L, m) the records' segments
    columns: jax.Array  # (P (L-1), Kd) diffusion library at the smoothed states
    pilot: jax.Array  # (d,) pre-averaged first guess of gamma
    window: int  # its pre-averaging window in samples


# A new process (the command line) reuses the traced program.
_diffusion_mle = aot.exported("diffusion_mle")(statespace.diffusion_mle)


def diffusion_statistics(
    step: statespace.DriftStep, dlib: Library, x, noise_var, *, window: int | None = None
) -> DiffusionFit:
    """The diffusion library's statistics, given the drift `step`, from measured records.

    Pre-averaged first guess (`kramers_moyal.preaveraged_diffusion`), likelihood
    maximum (`statespace.diffusion_mle`), EM targets at it and their statistics on
    `dlib` weighted by `_diffusion_stats`.

    **Arguments:**

    - `step`: the updated drift's `statespace.DriftStep`.
    - `dlib`: the diffusion `Library` (no inputs).
    - `x`: measured states, shape `(R, N, m)`.
    - `noise_var`: the measurement noise variances, shape `(m,)` (the states' units squared):
      first guesses, refitted with the diffusion.
    - `window`: the pre-averaging window in samples; None (default) picks it from the data,
      which needs concrete values, so pass an int under `jit`.

    **Returns:** a `DiffusionFit` (statistics, the likelihood's maximum and its covariance,
    fitted noise, linearization, segments, columns, first guess and window).
    """
    nominal = step.nominal
    pilot, window = kramers_moyal.preaveraged_diffusion(
        nominal, x, step.dt, noise_var, step.perturbation, window=window
    )
    y = statespace.segments(x)
    gamma, gamma_cov, noise, lin = _diffusion_mle(step, y, noise_var, pilot)
    vel = tuple(int(v) for v in nominal.velocity_index)
    stats, L = diffusion_regression(dlib, lin, y, noise, gamma, gamma_cov, vel)
    return DiffusionFit(stats, gamma, gamma_cov, noise, lin, y, L, pilot, window)


@functools.partial(jax.jit, static_argnums=(0, 6))
def diffusion_regression(dlib: Library, lin: statespace.Linearization, y, noise, gamma, gamma_cov,
                         velocity_index: tuple[int, ...]) -> tuple[sampler.SuffStats, jax.Array]:
    """The EM targets of `statespace.diffusion_targets` at the likelihood's maximum regressed
    on `dlib` at the smoothed states, one program.

    **Arguments:**

    - `dlib`: the diffusion `Library` (no inputs; static).
    - `lin`: the segments' `statespace.Linearization` at the maximum (batched over segments).
    - `y`: the records' segments, shape `(P, L, m)`.
    - `noise`: the fitted measurement noise variances, shape `(P, m)` (the states' units
      squared).
    - `gamma`: the likelihood's maximum, shape `(d,)` (velocity^2 / s).
    - `gamma_cov`: its covariance, shape `(d, d)`.
    - `velocity_index`: the `d` velocities' positions in the state, a tuple of ints (static).

    **Returns:** `(stats, columns)`: the weighted `SuffStats` batched over the `d` velocities
    (`_diffusion_stats`), and the diffusion library's columns `(P (L-1), Kd)` at the smoothed
    states."""
    Y, X = statespace.diffusion_targets(lin, y, noise, gamma, velocity_index)
    Y = Y.reshape(-1, Y.shape[-1])
    L = dlib(X.reshape(-1, X.shape[-1]))
    return _diffusion_stats(equation_stats(L, Y), Y, gamma, jnp.diagonal(gamma_cov)), L


def _diffusion_stats(stats: sampler.SuffStats, Y, gamma, gamma_var) -> sampler.SuffStats:
    """Statistics of the EM diffusion targets `Y (n, d)`, weighted to carry the likelihood's
    information about `gamma (d,)`, whose variance is `gamma_var (d,)`.

    A target is the conditional expectation of a squared one-step residual, `Gamma chi^2_1`,
    whose scatter `2 Gamma^2` around it the expectation removes; that scatter is added back
    to the residual sum of squares, so the sampler's noise level is a squared increment's.
    The targets then count as `n_eff = 2 Gamma^2 / Var(Gamma)` independent squared
    increments, so a constant diffusion's posterior variance is `1 / information`.
    """
    n = Y.shape[0]
    missing = jnp.maximum(2.0 * gamma**2 - jnp.var(Y, axis=0), 0.0)
    scale = 2.0 * gamma**2 / gamma_var / n  # n_eff / n
    return sampler.weigh(stats._replace(yty=stats.yty + n * missing), scale)
