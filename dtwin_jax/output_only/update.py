"""Framework 2 (output-only, the paper's Section 4.2): measured states only. The drift
perturbation comes from Kramers-Moyal targets (`dtwin_jax.output_only.kramers_moyal`), then the
diffusion of every velocity from the Kalman likelihood given that drift
(`dtwin_jax.output_only.statespace`), whose EM targets are sampled by the same kernel. The
numerics are in `dtwin_jax.output_only.stats`; this module orchestrates them
and checks the result (whitened innovations, the noise correction's margin)."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax._compile import aot
from dtwin_jax.checks import residual_checks
from dtwin_jax.collinearity import collinearity_checks
from dtwin_jax.data import check_records, state_range
from dtwin_jax.errors import DataError
from dtwin_jax.library import DEFAULT_LIBRARY, Library, check_columns, parse_library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.output_only.stats import (
    brownian_variance,
    diffusion_statistics,
    drift_pass,
    first_pass_estimate,
    first_pass_rows,
    first_pass_settings,
)
from dtwin_jax.progress import Stages
from dtwin_jax.resources import check_sampler, check_update
from dtwin_jax.sampler import SuffStats
from dtwin_jax.update.lifecycle import (
    check_previous,
    check_repeat,
    updated_history,
    with_previous,
)
from dtwin_jax.update.result import SamplerSettings, UpdateResult
from dtwin_jax.update.sampling import (
    numpy_stats,
    posteriors,
    sample_equations,
)

__all__ = ["update_output_only", "OUTPUT_ONLY_LIBRARY", "DIFFUSION_LIBRARY", "MARGIN_WARN"]

# The paper's library without inputs (none are measured), and a small state-dependent
# diffusion library: constant, linear and quadratic.
OUTPUT_ONLY_LIBRARY = DEFAULT_LIBRARY.replace(",input", "")
DIFFUSION_LIBRARY = "poly:2"


def update_output_only(
    nominal: LinearSecondOrder,
    t,
    x,
    *,
    xdot=None,
    xdot_names=None,
    library: str | Library | None = None,
    diffusion_library: str | Library | None = None,
    pip_threshold: float = 0.5,
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    progress: bool = False,
    previous: UpdateResult | None = None,
    forget: float = 1.0,
    allow_repeat: bool = False,
) -> UpdateResult:
    """Discover the drift perturbation and the diffusion of `nominal` from its response
    alone (no force measured: an Ito diffusion driven by white force).

    **Arguments:**

    - `nominal`: the nominal model `dtwin_jax.models.systems.LinearSecondOrder`.
    - `t`: `(N,)` sample times, s, uniform.
    - `x`: `(N, m)` one record (a structure in service) or `(R, N, m)` an ensemble of
      independent records, every state measured; pooled into one regression. None with
      `xdot`: accelerometers alone (ambient vibration,
      `dtwin_jax.output_only.accelerometers.update_from_accelerometers`: a
      constant diffusion).
    - `xdot`: the accelerometers' samples, `(N, s)` or `(R, N, s)` for `s` measured rates (the
      rates of the velocity states, acceleration units), with `x=None`; beside `x` it is
      refused in one line.
    - `xdot_names`: the states of the columns of `xdot` (None: all `m`), with `xdot`.
    - `library`: the drift library, a spec (formats.md) or `Library`, or None (default) for
      `OUTPUT_ONLY_LIBRARY`; no `input` family.
    - `diffusion_library`: the diffusion's, likewise (None: `DIFFUSION_LIBRARY`); with
      accelerometers alone only the constant `"terms:1"`.
    - `pip_threshold`: inclusion probability above which a term is selected, as in
      `dtwin_jax.input_output.update.update_input_output`.
    - `settings`: the sampler's `SamplerSettings` (chains, draws, burn-in).
    - `seed`: the sampler's seed (the diffusion's equations take `seed + 1`).
    - `progress`: show the stages and a bar of the sweeps.
    - `previous`: for a re-update, as in `update_input_output`, an earlier output-only update
      of the same twin (same nominal model and libraries), whose drift and diffusion
      statistics, times `forget`, are added to this window's; None (default) for a first update.
    - `forget`: the previous statistics' weight, in [0, 1] (default 1).
    - `allow_repeat`: take a window already in the history (its data would count twice).

    **Returns:** an `UpdateResult` of mode `"output-only"`: one `drift` equation
    per regressed state (acceleration units) and one `diffusion` equation per velocity (the
    diagonal `Gamma_ii = (G G^T)_ii`, velocity^2 / s).
    """
    start = time.perf_counter()
    if x is None:  # accelerometers alone: ambient vibration
        from dtwin_jax.output_only.accelerometers import (
            update_from_accelerometers,
        )

        if diffusion_library is not None and str(getattr(diffusion_library, "spec", diffusion_library)) != "terms:1":
            raise DataError("accelerometers alone give a constant diffusion only: leave the diffusion library out")
        return update_from_accelerometers(
            nominal, t, xdot, xdot_names, output_only_library(library, nominal, OUTPUT_ONLY_LIBRARY),
            pip_threshold=pip_threshold, settings=settings, seed=seed, progress=progress, previous=previous,
            forget=forget, allow_repeat=allow_repeat)
    if xdot is not None:
        raise DataError("output-only takes the states 'x' or accelerometers alone ('xdot' without 'x'), not both yet")
    rec = check_records(t, x, None, None, nominal)
    if np.any(np.asarray(nominal.F0) != 0):
        raise DataError("output-only updates do not take a nominal F0 yet: set it to zero and keep the constant term '1' in the library")
    lib = output_only_library(library, nominal, OUTPUT_ONLY_LIBRARY)
    dlib = output_only_library(diffusion_library, nominal, DIFFUSION_LIBRARY)
    check_previous(previous, "output-only", nominal, lib, forget)
    check_repeat(previous, rec, allow_repeat)
    s, samples = settings, rec.x.shape[0] * rec.x.shape[1]
    check_update(samples, lib.K, len(nominal.regressed_index), s.num_chains, s.num_draws, s.num_burnin, library=lib.spec)
    check_sampler(nominal.d, dlib.K, s.num_chains, s.num_draws, s.num_burnin, library=dlib.spec)
    if previous is not None and previous.preprocessing.get("diffusion_library") != dlib.spec:
        raise DataError(f"re-update needs the previous diffusion library '{previous.preprocessing.get('diffusion_library')}'")
    stages = Stages(progress, 5, "output-only update")
    R, N, m = rec.x.shape
    dt = rec.dt
    with stages("drift statistics (Kramers-Moyal)"):
        noise_var = kramers_moyal.noise_variance(rec.x)
        check_columns(np.asarray(lib(rec.x.reshape(-1, m)[:: max(1, R * N // 20000)])), lib.names)
        drift_stats, margin = drift_statistics(nominal, lib, rec.x, dt, noise_var, settings, seed)
        drift_stats = jax.block_until_ready(with_previous(drift_stats, "drift", previous, forget))
    names = nominal.state_names
    regressed = [names[i] for i in nominal.regressed_index]
    with stages("drift sampling"):
        trace = jax.block_until_ready(sample_equations(drift_stats, settings, seed, progress))
        drift = posteriors(trace, regressed, "drift", lib.names, pip_threshold)
    with stages("diffusion likelihood (Kalman)"):
        # One step's mean drift: friction's sign averaged over half a step's Brownian increment.
        residual_var = np.array([e.sigma2.mean() for e in drift])
        gamma_drift = brownian_variance(nominal, dt, noise_var, residual_var)
        step_smoothing = np.zeros(m)  # on the host: each eager jnp operation compiles a program
        step_smoothing[np.asarray(nominal.velocity_index)] = 0.5 * dt * np.asarray(gamma_drift)
        step = statespace.DriftStep.from_coefficients(
            nominal, lib, np.stack([e.coefficients for e in drift]), dt, jnp.asarray(step_smoothing)
        )
        vel = tuple(int(v) for v in nominal.velocity_index)
        fit = diffusion_statistics(step, dlib, rec.x, noise_var)
        check_columns(np.asarray(fit.columns), dlib.names)
        gamma, fitted_noise, lin, y = fit.gamma, fit.noise, fit.lin, fit.segments
        gamma_var = np.diag(np.asarray(fit.gamma_cov))
        stats = jax.block_until_ready(with_previous(fit.stats, "diffusion", previous, forget))
    with stages("diffusion sampling"):
        trace = sample_equations(stats, settings, seed + 1, progress)
        velocities = [names[i] for i in nominal.velocity_index]
        diffusion = posteriors(trace, velocities, "diffusion", dlib.names, pip_threshold)
    # The drift's posterior-predictive check: one-step innovations of the velocities under
    # the fitted drift and diffusion, white and unpredictable from the past when it fits.
    with stages("residual checks"), stages:
        innov, predicted = statespace.standardized_innovations(lin, y, fitted_noise, gamma, vel)
        predicted = np.asarray(predicted)
        checks = {
            names[v]: residual_checks(np.asarray(innov[..., j]), predicted, vel, names)
            for j, v in enumerate(vel)
        }
    for state, mg in zip(regressed, np.asarray(margin)):
        checks[f"{state} noise correction"] = margin_check(float(mg))
    checks.update(collinearity_checks(drift_stats, drift))
    return UpdateResult(
        mode="output-only",
        nominal=nominal,
        library=lib,
        equations=drift + diffusion,
        pip_threshold=pip_threshold,
        settings=settings,
        seconds=time.perf_counter() - start,
        preprocessing={
            "noise_std": np.sqrt(np.asarray(fitted_noise)).tolist(),
            "drift_direction": "nominal model plus a first-pass sampled estimate",
            "diffusion_library": dlib.spec,
            "diffusion_estimator": "extended Kalman likelihood (iterated linearization)",
            "diffusion_pilot": np.asarray(fit.pilot).tolist(),
            "diffusion_pilot_window": int(fit.window),
            "diffusion_ml": np.asarray(gamma).tolist(),
            "diffusion_ml_std": np.sqrt(gamma_var).tolist(),
            "diffusion_effective_samples": np.asarray(stats.n).tolist(),
            "records": int(R),
            "samples": int(R * N),
            "state_range": state_range(rec.x, previous),
            "stage_seconds": dict(stages.seconds),
        },
        checks=checks,
        statistics={"drift": numpy_stats(drift_stats), "diffusion": numpy_stats(stats)},
        history=updated_history(previous, "output-only", rec, forget, drift + diffusion, time.perf_counter() - start),
    )


# A new process (the command line) reuses the traced program.
_drift_pass = aot.exported("drift_pass", static_argnums=(1, 3))(drift_pass)


def drift_statistics(nominal: LinearSecondOrder, lib: Library, x, dt: float, noise_var, settings: SamplerSettings,
                     seed: int) -> tuple[SuffStats, jax.Array]:
    """`output_only_drift_stats` of records with `key(seed)`, run as separate programs with
    the same result: both passes are one program, and the first pass's short run is the drift
    sampling's program (`sample_equations`), compiled once.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `lib`: the drift `Library` (no inputs).
    - `x`: measured states, shape `(R, N, m)`.
    - `dt`: the sample interval, s.
    - `noise_var`: the states' white-noise variances, shape `(m,)` (the states' units squared).
    - `settings`: the main run's `SamplerSettings` (the short run takes its
      `first_pass_settings`).
    - `seed`: the seed whose key's first split drives the short run.

    **Returns:** `(stats, margin)`: the `SuffStats` batched over the `q` regressed states, and
    `margin (q,)` the `correction_margin` of the corrected Gram matrices before their
    eigenvalues are floored."""
    R, N, m = x.shape

    def one_pass(coef, smoothing, rows):
        return _drift_pass(nominal, lib, x, float(dt), noise_var, coef, smoothing, jnp.asarray(rows))

    first, _ = one_pass(jnp.zeros((len(nominal.regressed_index), lib.K)), jnp.zeros(m), first_pass_rows(x))
    first_key = jax.random.split(jax.random.key(seed))[0]
    trace = sample_equations(first, first_pass_settings(settings), seed, False, key=first_key)
    return one_pass(*first_pass_estimate(nominal, dt, noise_var, trace), R * (N - 2))


def output_only_library(library, nominal: LinearSecondOrder, default: str) -> Library:
    """`library` resolved as in `resolve_library`, `default` for None; no inputs.

    A library with the `input` family raises `DataError` (output-only data has no inputs).

    **Arguments:**

    - `library`: a spec (formats.md), a `Library`, or None.
    - `nominal`: the nominal model `LinearSecondOrder` (its `m` states; no inputs).
    - `default`: the spec to use for None.

    **Returns:** the `Library` for the `m` states."""
    lib = library if isinstance(library, Library) else parse_library(library or default, nominal.m, 0)
    if lib.uses_inputs:
        raise DataError("library family 'input' needs measured inputs; output-only data has none")
    return lib


# Example 1 (100 records): -0.003 at 14% noise (support always right), -0.012 at 18% (3 of 4),
# -0.05 at 23% (1 of 4, the others select 16-28 terms with PIP 1).
MARGIN_WARN = -0.01


def margin_check(margin: float) -> dict:
    """The result's check of the noise correction: a warning below `MARGIN_WARN`.

    **Arguments:**

    - `margin`: one equation's smallest eigenvalue from
      `dtwin_jax.output_only.stats.correction_margin`.

    **Returns:** the check, a dict: `ok` (bool), `warnings` (a list of strings, empty when
    ok) and `min_eigenvalue` (`margin`)."""
    ok = margin >= MARGIN_WARN
    warning = (
        f"noise correction removed more than the data hold (smallest eigenvalue of the corrected "
        f"regressor correlation {margin:.3g} < {MARGIN_WARN}): noise too large for this library, PIPs "
        "and coefficients unreliable (use fewer terms, more records or less noisy sensors)"
    )
    return {"ok": bool(ok), "warnings": [] if ok else [warning], "min_eigenvalue": float(margin)}
