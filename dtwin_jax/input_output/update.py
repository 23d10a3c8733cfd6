"""Framework 1 (input-output, the paper's Section 4.1): measured states `x`, inputs `u`
and rates `xdot` (or rates estimated from `x`). The states are denoised (the kinematic
RTS smoother with measured rates, else Savitzky-Golay) or, with some states unmeasured,
estimated with their rates by the state-space smoother of `dtwin_jax.preprocess.estimate`; the
nominal rates are removed to give the targets `xdot - f(x, u)`, whose statistics on the
library go to the sampler, every regressed equation in one vmapped call."""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.checks import residual_checks
from dtwin_jax.collinearity import collinearity_checks, twin_coefficients
from dtwin_jax.data import Records, check_records, check_signal, state_range
from dtwin_jax.errors import DataError
from dtwin_jax.input_output.accelerometers import (
    accelerometer_regression,
    without_constant_columns,
)
from dtwin_jax.input_output.output_error import refine_output_error
from dtwin_jax.input_output.targets import (
    input_output_targets,
    smoothed_input_output_stats,
)
from dtwin_jax.library import Library, check_columns, without_degenerate_columns
from dtwin_jax.model_error import training_model_error
from dtwin_jax.models.systems import (
    LinearSecondOrder,
    check_interpolation,
    resolve_interpolation,
)
from dtwin_jax.preprocess.accelerometers import (
    accelerometer_layout,
    accelerometer_states,
    sampler_selection,
    widened_draws,
)
from dtwin_jax.preprocess.denoise import (
    auto_half_width,
    kinematic_smoother,
    savgol_design_ok,
    savgol_states,
)
from dtwin_jax.preprocess.estimate import measured_index, state_smoother
from dtwin_jax.preprocess.measurement import smooth
from dtwin_jax.preprocess.weak_form import (
    weak_input_output_stats,
    weak_layout_supported,
    weak_window_fits,
)
from dtwin_jax.progress import Stages
from dtwin_jax.resources import check_update
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
    resolve_library,
    sample_equations,
)

__all__ = ["update_input_output", "denoise_states"]

def update_input_output(
    nominal: LinearSecondOrder,
    t,
    x,
    u,
    xdot=None,
    *,
    x_names=None,
    xdot_names=None,
    interpolation: str = "auto",
    library: str | Library | None = None,
    smoothing="auto",
    pip_threshold: float = 0.5,
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    progress: bool = False,
    previous: UpdateResult | None = None,
    forget: float = 1.0,
    allow_repeat: bool = False,
    refine: bool = False,
    reference=None,
) -> UpdateResult:
    """Discover the perturbation of `nominal` from input-output measurements.

    The route follows the sensors: with every state measured and no rates, the weak form
    (`dtwin_jax.preprocess.weak_form`: nothing differentiated); with rates measured, the kinematic
    smoother; with accelerometers alone, the anchored states and their weak form
    (`dtwin_jax.preprocess.accelerometers`); with some states unmeasured, or a few samples per
    period, the state-space smoother of `dtwin_jax.preprocess.estimate`. The layout and route are
    named in `preprocessing["layout"]` and `["smoothing"]`.

    **Arguments:**

    - `nominal`: the nominal model `dtwin_jax.models.systems.LinearSecondOrder`.
    - `t`: `(N,)` sample times, s, uniform.
    - `x`: `(N, p)` or `(R, N, p)` measured states (`R` records), or None with
      `xdot` (accelerometers alone).
    - `u`: `(N, n)` or `(R, N, n)` measured inputs (force units through `B`).
    - `xdot`: measured rates of the states `xdot_names` (accelerometers: the rates of the
      velocity states), same shapes as `x`, or None.
    - `x_names`: the states of the columns of `x`, like `["x1"]`, or None (default: all `m`
      in order).
    - `xdot_names`: the states whose rates are the columns of `xdot`, like `["x2"]`, or None
      (default: all `m` in order).
    - `interpolation`: the input between samples, `"held"`, `"linear"`,
      `"bandlimited"`, or `"auto"` (chosen from its spectrum by
      `dtwin_jax.models.systems.choose_interpolation`; reported as
      `preprocessing["input_interpolation"]` and `["input_interpolation_chosen_by"]`).
    - `library`: a spec (formats.md, like `"poly:3,sign,input"`) or a `Library`;
      None: the default library, adapted to the data (columns the data cannot tell apart
      dropped, with a warning).
    - `smoothing`: `"auto"` (the route above), `"weak"`, `"savgol"`,
      `"statespace"`, None (the states as measured) or an int Savitzky-Golay half width.
    - `pip_threshold`: inclusion probability above which a term is selected.
    - `settings`: `SamplerSettings` (chains, draws, burn-in).
    - `seed`: the sampler's seed.
    - `progress`: show the stages and a bar of the sweeps.
    - `previous`: an earlier update of the same twin (same nominal model and library),
      whose statistics, times `forget`, are added to this window's: its posterior is the
      prior; the history continues it.
    - `forget`: the previous statistics' weight, in [0, 1] (default 1).
    - `allow_repeat`: take a window already in the history (its data would count twice).
    - `refine`: refine the selected terms' coefficients by output error on the same data
      (`dtwin_jax.update.refine_output_error`): a sharper twin for long free runs.
    - `reference`: `(N,)`, `(N, r)` or `(R, N, r)` the set-point of a closed loop, or
      None. The estimator assumes the equation error white and independent of the columns;
      under feedback an unmeasured force reaches the input and that fails. Given, the
      reference is the instrument of a two-stage least squares (`dtwin_jax.preprocess.instruments`;
      the weak form's route only).

    **Returns:** an `UpdateResult` of mode `"input-output"`: one drift equation per
    regressed state, coefficients in acceleration units (`M^-1` applied), with the
    preprocessing, checks and statistics of the update.
    """
    start = time.perf_counter()
    if interpolation != "auto":
        check_interpolation(interpolation)  # refuse a bad name before the data checks
    accelerometers = x is None  # accelerometers alone (dtwin_jax.preprocess.accelerometers)
    if accelerometers:
        x, x_names = accelerometer_layout(nominal, xdot, xdot_names, u, refine)
    x_index = measured_index(x_names, nominal)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names") if xdot is not None else ()
    rec = check_records(t, x, u, xdot, nominal, x_columns=len(x_index), xdot_columns=len(xdot_index) or None)
    if rec.u is None:
        raise DataError("input-output update needs measured inputs 'u'")
    interpolation, interpolation_chosen_by = resolve_interpolation(interpolation, rec.u)
    # The default library adapts to the data (columns these data cannot identify dropped,
    # below); a re-update keeps the library of the update it continues.
    adapt = library is None and previous is None
    lib = previous.library if library is None and previous is not None else resolve_library(library, nominal, nominal.n)
    check_previous(previous, "input-output", nominal, lib, forget)
    check_repeat(previous, rec, allow_repeat)
    s = settings
    check_update(rec.x.shape[0] * rec.x.shape[1], lib.K, len(nominal.regressed_index), s.num_chains, s.num_draws,
                 s.num_burnin, library=lib.spec)
    hw = auto_half_width(nominal, rec.dt, rec.t.size)
    every = tuple(range(nominal.m))
    partial = x_index != every or (rec.xdot is not None and xdot_index != every)
    weak_ok = rec.xdot is None and weak_layout_supported(nominal, x_index)
    if smoothing == "weak" and not weak_ok:
        raise DataError("smoothing='weak' needs every displacement and extra state measured and no measured rates")
    if reference is not None:
        reference = check_signal("reference", reference, rec.t.size, rec.x.shape[0])
    # At a few samples per period the weak form's sums are exact for a band-limited input's
    # response only: a held input's steps alias (a 9-samples-per-period Duffing under held
    # white noise: free run 68% off, against 7% by the state-space smoother).
    sampled_well = savgol_design_ok(nominal, rec.dt) or interpolation == "bandlimited"
    if smoothing == "auto" and weak_ok and sampled_well and weak_window_fits(nominal, rec.dt, rec.t.size):
        # benchmarks/weak_form.py: 0.64% vs 3.15% median cubic error at 5% noise (states);
        # benchmarks/zoo.py --layout displacement: the state-space route found nothing.
        smoothing = "weak"
    if reference is not None and smoothing != "weak":  # the instrument enters the weak rows only
        why = ("every displacement measured, no rates, smoothing auto or weak" if not weak_ok or smoothing != "auto"
               else "these data cannot use it (too few samples per period or a record shorter than one window)")
        raise DataError(f"a 'reference' instrument needs the weak form: {why}")
    warnings = []
    if smoothing == "auto" and rec.xdot is None and not savgol_design_ok(nominal, rec.dt):
        warnings.append(
            "Savitzky-Golay filters cannot reach 8x the highest natural frequency below Nyquist "
            f"({1 / rec.dt:.4g} Hz sampling): rates from the state-space smoother instead"
        )
        smoothing = "statespace"
    elif smoothing == "savgol" and not savgol_design_ok(nominal, rec.dt):
        warnings.append("Savitzky-Golay filters cannot reach 8x the highest natural frequency below "
                        "Nyquist: rate estimates biased (smoothing='statespace' avoids this)")
    stages = Stages(progress, 4 + refine, "input-output update")
    with stages("states and rates"):
        if accelerometers:
            lib, dropped = without_constant_columns(lib, nominal, rec.u)
            if dropped:
                warnings.append("accelerometers do not see a constant force (a static displacement): "
                                + ", ".join(dropped) + " left out of the library")
            a = rec.xdot[..., [xdot_index.index(i) for i in nominal.velocity_index]]
            xs, rates, smoothing_info = accelerometer_states(
                nominal, rec.dt, rec.xdot, xdot_index, rec.u, lib,
                sampler_selection(nominal, rec.dt, a, lib, rec.u, settings, seed, interpolation),
                interpolation=interpolation, seed=seed)
            loop_names = list(lib.names)
            rate_source, correct, smoothing = "measured", True, "accelerometers"
        else:
            xs, rates, smoothing_info, rate_source, correct = _states_and_rates(
                rec, nominal, smoothing, partial, x_index, xdot_index, interpolation, hw)
    R, N, m = xs.shape
    with stages("library statistics"):
        L = np.asarray(lib(xs.reshape(R * N, m), rec.u.reshape(R * N, -1)))
        if adapt:
            lib, dropped = without_degenerate_columns(lib, L)
            if dropped:
                warnings.append(f"default library: {len(dropped)} terms these data cannot tell from others dropped: "
                                + ", ".join(dropped))
        else:
            check_columns(L, lib.names)
        del L
        # The same jitted chain as the batched studies (dtwin_jax.studies).
        # Rows where a sign(v) column may be wrong are left out (measured rates).
        if accelerometers:  # the weak rows below are the statistics
            noise_var = None
        else:
            keep = _clear_of_jumps(lib, nominal, xs, rec.x, x_index) if rate_source == "measured" else None
            stats, noise_var = smoothed_input_output_stats(nominal, lib, xs, rec.u, rates, hw, correct_inputs=correct,
                                                           keep=keep)
            if keep is not None:
                smoothing_info = {**(smoothing_info or {}),
                                  "rows_near_velocity_reversals_left_out": int((~keep).sum())}
        n_eff, feedback = None, None
        if smoothing == "weak":  # the Savitzky-Golay rates above serve the residual checks only
            stats, weak_info = weak_input_output_stats(nominal, lib, rec.t, rec.x, rec.u, x_index=x_index,
                                                       interpolation=interpolation, reference=reference)
            smoothing_info = {"states": smoothing_info, "regression": weak_info}
        if accelerometers:  # the weak form: the nominal part exact, whatever the states
            stats, weak_info, feedback, more = accelerometer_regression(nominal, lib, rec.dt, a, rec.u, xs, smoothing_info,
                                                                        loop_names, interpolation)
            warnings.extend(more)
            smoothing_info = {"states": smoothing_info, "regression": weak_info}
        elif rate_source == "state-space smoother":  # smoothed states: correlated rows
            stats, n_eff = _autocorrelation_corrected(stats, nominal, lib, xs, rec.u, rates)
        stats = jax.block_until_ready(with_previous(stats, "drift", previous, forget))
    with stages("sampling"):
        trace = jax.block_until_ready(sample_equations(stats, settings, seed, progress))
        if feedback is not None:  # what the anchor's loop and the states' error add
            trace = trace._replace(theta=widened_draws(trace.theta, trace.gamma, feedback, seed))
    names = nominal.state_names
    with stages("posterior and residual checks"):
        equations = posteriors(trace, [names[i] for i in nominal.regressed_index], "drift", lib.names, pip_threshold)
        collinear = collinearity_checks(stats, equations)
        # The residual of the twin's coefficients: a collinear group counted once.
        residual = _input_output_residuals(nominal, lib, xs, rec.u, rates, twin_coefficients(equations, collinear))
        checks = {
            e.state: residual_checks(residual[j], xs, nominal.velocity_index, names)
            for j, e in enumerate(equations)
        }
        checks.update(collinear)
    if warnings:
        checks["preprocessing"] = {"ok": False, "warnings": warnings}
    result = UpdateResult(
        mode="input-output",
        nominal=nominal,
        library=lib,
        equations=equations,
        pip_threshold=pip_threshold,
        settings=settings,
        seconds=time.perf_counter() - start,
        preprocessing={
            "state_smoothing": smoothing_info,
            "smoothing": smoothing,
            "rates": rate_source,
            "measured_states": [names[i] for i in x_index],
            "measured_rates": [names[i] for i in xdot_index],
            "layout": _layout_name(nominal, x_index, xdot_index),
            **({"states": "anchored kinematic RTS"} if accelerometers else {}),
            "input_interpolation": interpolation,
            "input_interpolation_chosen_by": interpolation_chosen_by,
            "input_noise_std": None if noise_var is None else np.sqrt(noise_var).tolist(),
            "samples": int(R * N),
            "state_range": state_range(xs, previous),
            "effective_samples": None if n_eff is None else n_eff.tolist(),
            "stage_seconds": dict(stages.seconds),
        },
        checks=checks,
        statistics={"drift": numpy_stats(stats)},
        history=updated_history(previous, "input-output", rec, forget, equations, time.perf_counter() - start),
    )
    if not refine:
        stages.close()
        return _with_model_error(result, rec, x_index, xs)
    noise = np.sqrt(np.mean((rec.x - xs[..., list(x_index)]) ** 2, axis=(0, 1)))
    try:
        with stages("output-error refinement"), stages:
            result = refine_output_error(result, rec.t, rec.x, rec.u, x_names=[names[i] for i in x_index],
                                     x0=xs[:, 0], noise_std=np.maximum(noise, 1e-9 * np.std(rec.x, axis=(0, 1))),
                                     input_noise_std=None if noise_var is None else np.sqrt(noise_var))
    except Exception as e:  # noqa: BLE001 - the Gibbs twin stands whatever failed; say why, in one line
        reason = (str(e).strip().splitlines() or [""])[0][:300]
        result = dataclasses.replace(result, checks={**checks, "refinement": {
            "ok": False, "warnings": [f"failed ({type(e).__name__}): {reason}; the twin is the Gibbs posterior's, "
                                      "unrefined"]}})
    preprocessing = {**result.preprocessing, "stage_seconds": dict(stages.seconds)}  # the refinement's too
    result = dataclasses.replace(result, preprocessing=preprocessing, seconds=time.perf_counter() - start)
    return _with_model_error(result, rec, x_index, xs)


# A sample is left out when a velocity inside sign() is within this many of its noise std of 0.
_JUMP_SIGMAS = 3.0


def _clear_of_jumps(lib, nominal, xs, x, x_index):
    """`(R, N)` True where every velocity that enters a `sign` term of `lib` is at least
    `_JUMP_SIGMAS` noise standard deviations from 0, or None (no such term, or no measured
    velocity to size its noise). Near a reversal the denoised velocity's sign is a coin flip,
    and those rows alone made `x2 + x2**3` beat `x2*Abs(x2)` with the friction low
    (`benchmarks/ambiguity.py`)."""
    names = nominal.state_names
    joined = " ".join(lib.names)
    velocities = [v for v in nominal.velocity_index if f"sign({names[v]})" in joined and v in x_index]
    if not velocities:
        return None
    keep = np.ones(xs.shape[:2], dtype=bool)
    for v in velocities:
        raw = x[..., list(x_index).index(v)]
        sigma = float(np.std(raw - xs[..., v]))
        keep &= np.abs(xs[..., v]) > _JUMP_SIGMAS * sigma
    return keep if keep.mean() > 0.5 else None


def _layout_name(nominal, x_index, xdot_index) -> str:
    """The sensor layout, in the words of the README's sensors table."""
    every, positions = set(range(nominal.m)), set(range(nominal.m)) - set(nominal.velocity_index)
    if not x_index:
        return "accelerometers"
    if set(x_index) == every:
        return "states and rates" if set(xdot_index) >= set(nominal.velocity_index) else (
            "states and some rates" if xdot_index else "states")
    if set(x_index) == positions and not xdot_index:
        return "displacement"
    return "partial states"


def _with_model_error(result: UpdateResult, rec, x_index, xs) -> UpdateResult:
    """The result with the twin's free-run error on its training data
    (`preprocessing["model_error_sd"]`, `dtwin_jax.model_error`), which predictions
    add to their band; a warning instead when that free run fails."""
    if not x_index:  # nothing measured to compare a free run with (accelerometers alone)
        return result
    start = time.perf_counter()
    sd, why = training_model_error(result.twin, rec.t, rec.x, rec.u, x_index, xs[:, 0])
    preprocessing = {**result.preprocessing, "model_error_sd": sd}
    checks = result.checks
    if why is not None:
        checks = {**checks, "model_error": {"ok": False, "warnings": [why + "; predictions carry the parameter "
                                                                      "uncertainty only"]}}
    return dataclasses.replace(result, preprocessing=preprocessing, checks=checks,
                               seconds=result.seconds + time.perf_counter() - start)


def _states_and_rates(rec, nominal, smoothing, partial, x_index, xdot_index, interpolation, hw):
    """Denoised or estimated states `(R, N, m)` and their rates, a description of the
    smoothing, where the rates came from, and whether the input-noise correction applies."""
    if smoothing == "weak" and partial:  # residual checks on Savitzky-Golay derivatives of the displacements
        xs, rates = _savgol_from_displacements(rec, nominal, x_index, hw)
        info = {"method": "savitzky-golay", "order": 4, "half_width": hw}
        return xs, rates, info, "none: weak form (residual checks on Savitzky-Golay derivatives)", False
    if partial or smoothing == "statespace":
        xs, rates, info = state_smoother(
            nominal, rec.dt, rec.x, x_index, rec.u, rec.xdot, xdot_index, interpolation=interpolation
        )
        return xs, rates, info, "state-space smoother", False
    if smoothing == "weak":  # raw states regress; these smoothed ones feed the residual checks
        xs, info = denoise_states(rec, nominal, "savgol")
        rates = np.asarray(smooth(rec.x, hw, order=4, deriv=1, dt=rec.dt))
        return xs, rates, info, "none: weak form (residual checks on Savitzky-Golay rates)", False
    xs, info = denoise_states(rec, nominal, smoothing)
    if rec.xdot is not None:
        return xs, rec.xdot, info, "measured", smoothing is not None
    rates = np.asarray(smooth(rec.x, hw, order=4, deriv=1, dt=rec.dt))
    return xs, rates, info, f"savitzky-golay derivative (order 4, half width {hw})", False


def _savgol_from_displacements(rec, nominal, x_index, hw) -> tuple[np.ndarray, np.ndarray]:
    """States `(R, N, m)` and rates with every unmeasured velocity the Savitzky-Golay
    derivative of its displacement (the weak form's layouts: displacements measured)."""
    R, N, _ = rec.x.shape
    xs, rates = np.zeros((R, N, nominal.m)), np.zeros((R, N, nominal.m))
    measured = np.asarray(savgol_states(rec.x, hw))
    slope = np.asarray(smooth(rec.x, hw, order=4, deriv=1, dt=rec.dt))
    curve = np.asarray(smooth(rec.x, hw, order=4, deriv=2, dt=rec.dt))
    for r, i in enumerate(x_index):
        xs[..., i], rates[..., i] = measured[..., r], slope[..., r]
        if i < nominal.d and i + nominal.d not in x_index:  # its velocity from it
            xs[..., i + nominal.d], rates[..., i + nominal.d] = slope[..., r], curve[..., r]
    return xs, rates


def denoise_states(records: Records, nominal: LinearSecondOrder, smoothing="auto") -> tuple:
    """Denoise the measured states before they enter the library and the nominal rates.

    **Arguments:**

    - `records`: the checked `Records` (`x (R, N, m)`, the rates `xdot` or None, the inputs
      `u` or None, `dt` s).
    - `nominal`: the nominal model (it sets the filters' width, `auto_half_width`).
    - `smoothing`: `"auto"` (the kinematic RTS smoother when rates are measured, else a
      Savitzky-Golay filter matched to the sampling rate), `"savgol"`, an int Savitzky-Golay
      half width (samples), or None (raw states).

    **Returns:** `(x, info)`: the denoised states `(R, N, m)` and a dict describing the
    smoothing, or None for raw states.
    """
    if smoothing is None:
        return records.x, None
    hw = auto_half_width(nominal, records.dt, records.t.size)
    if smoothing == "auto" and records.xdot is not None:
        u = records.u if records.u is not None else [None] * records.x.shape[0]
        xs = np.stack([
            np.asarray(kinematic_smoother(nominal, records.dt, x, xd, uu, hw))
            for x, xd, uu in zip(records.x, records.xdot, u)
        ])
        return xs, {"method": "kinematic-rts", "noise_half_width": hw}
    if smoothing not in ("auto", "savgol"):
        hw = min(int(smoothing), (records.t.size - 1) // 2)
    return np.asarray(savgol_states(records.x, hw)), {"method": "savitzky-golay", "order": 4, "half_width": hw}


def _autocorrelation_corrected(stats, nominal, lib, xs, u, rates) -> tuple[sampler.SuffStats, np.ndarray]:
    """Statistics scaled to the residuals' effective sample size `(q,)`.

    A smoother's rate estimates are smooth in time, so the regression residuals (model
    mismatch, estimation error) are autocorrelated, and counting every sample as independent
    makes the posterior too narrow and every small systematic term "certain" (on the
    Silverbox: a posterior std of the cubic stiffness far below the spread between windows,
    and velocity cross-terms at PIP 1). The residuals of a least-squares fit on the whole
    library give the effective size (arviz's ESS, summed over records); scaling the
    statistics by `n_eff / n` keeps their estimates and widens the posterior to match."""
    import arviz_stats as az

    R, N, m = xs.shape
    x, uu = jnp.asarray(np.reshape(xs, (R * N, m))), jnp.asarray(np.reshape(u, (R * N, -1)))
    Y = np.asarray(input_output_targets(nominal, x, uu, jnp.asarray(np.reshape(rates, (R * N, m)))))
    L = np.asarray(lib(x, uu))
    coef, *_ = np.linalg.lstsq(L / np.linalg.norm(L, axis=0), Y, rcond=None)
    residual = (Y - (L / np.linalg.norm(L, axis=0)) @ coef).T.reshape(-1, R, N)
    n_eff = np.array([sum(float(az.ess(r[None], method="mean")) for r in eq) for eq in residual])
    scale = np.minimum(n_eff / (R * N), 1.0)
    scaled = sampler.weigh(sampler.SuffStats(*(np.asarray(a) for a in stats)), scale)
    return scaled, n_eff


def _input_output_residuals(nominal, lib, xs, u, rates, coef) -> np.ndarray:
    """Residuals `(q, R, N)` of every regressed equation under coefficients `coef (q, K)`."""
    R, N, m = xs.shape
    x, uu = jnp.asarray(np.reshape(xs, (R * N, m))), jnp.asarray(np.reshape(u, (R * N, -1)))
    Y = np.asarray(input_output_targets(nominal, x, uu, jnp.asarray(np.reshape(rates, (R * N, m)))))
    return (Y - np.asarray(lib(x, uu)) @ np.asarray(coef).T).T.reshape(-1, R, N)
