"""Framework 2 from accelerometers alone: the ambient vibration of a structure in service.

Nothing but the accelerations `a` of the degrees of freedom is measured; the force is white
and unknown (the Ito diffusion of framework 2). An accelerometer's sample is the velocity's
increment over its interval over `dt`: the Kramers-Moyal target of framework 2, measured
rather than differenced. The states come from the anchored smoother
(`dtwin_jax.preprocess.accelerometers`) with no input: the kinematic chains integrate the measured
accelerations, and the equation of motion anchors them below the first mode, its force the
white one. Each row regresses a sample on the library at the state the drift predicts for it
from the sample before (non-anticipating, as Ito's calculus needs; the increment's O(dt) term
cancels, as in framework 2's moved regressors).

The weak form of `dtwin_jax.preprocess.weak_form_accelerometers` is not used for the drift here: its
windows hold the white force both in the rows' error and in the states that the columns see
(with the true states of a zoo member, least squares took a spurious damping), and its
`chi''` weighting leaves little of a damping force. On the zoo these rows find the exact
support far more often than the weak form with an Ito correction, and on every damping member
(`benchmarks/results/zoo_output_only_accelerometers.md`).

Its restricted likelihood serves the diffusion: the accelerations' white floor `T` (their
Savitzky-Golay residual) is the sensors' noise plus the force's `Gamma / dt`, and the two
enter the weak rows through different filters, which splits them. The smoother needs the split
(the sensors' share is its kinematic chains' noise, the force's its anchor's), so states and
split are iterated.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.collinearity import collinearity_checks
from dtwin_jax.data import check_records, state_range
from dtwin_jax.errors import DataError
from dtwin_jax.input_output.accelerometers import without_constant_columns
from dtwin_jax.io.twin_files import SPREAD_KIND
from dtwin_jax.library import Library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.output_only.stats import first_pass_settings
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.preprocess.accelerometers import (
    ERROR_DRAWS,
    accelerometer_layout,
    accelerometer_states,
    selected_least_squares,
    unsettled_warnings,
    widened_draws,
)
from dtwin_jax.preprocess.estimate import measured_index
from dtwin_jax.preprocess.weak_form_accelerometers import accelerometer_weak_stats
from dtwin_jax.progress import Stages
from dtwin_jax.resources import check_update
from dtwin_jax.sampler import SuffStats
from dtwin_jax.update.lifecycle import (
    check_previous,
    check_repeat,
    updated_history,
    with_previous,
)
from dtwin_jax.update.result import SamplerSettings, UpdateResult
from dtwin_jax.update.sampling import numpy_stats, posteriors, sample_equations

__all__ = ["CONSTANT_DIFFUSION", "SPLIT_PASSES", "update_from_accelerometers", "increment_stats", "score_spread"]

# The diffusion of each velocity is one constant: formats.md's "constant-only diffusion is the
# term 1".
CONSTANT_DIFFUSION = "terms:1"
# Passes of the states, the sensor / force split re-estimated after each but the last.
SPLIT_PASSES = 3
# The smoother's and the weak rows' inputs are integrated as band-limited (the force is broadband).
_INTERPOLATION = "bandlimited"


def update_from_accelerometers(nominal: LinearSecondOrder, t, xdot, xdot_names, lib: Library, *,
                               pip_threshold: float, settings: SamplerSettings, seed: int, progress: bool,
                               previous, forget: float, allow_repeat: bool = False) -> UpdateResult:
    """Discover the drift perturbation and the constant diffusion of `nominal` from
    accelerometers alone (called by `dtwin_jax.output_only.update.update_output_only`).

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder` (every degree of freedom with an
      accelerometer, `K` positive definite, no extra states).
    - `t`: `(N,)` sample times, s, uniform.
    - `xdot`: `(N, s)` or `(R, N, s)` measured rates (`s` of them); those of the velocity states are the
      accelerometers' averages over each sample's interval (state units / s^2).
    - `xdot_names`: the states of the columns of `xdot` (None: all `m`).
    - `lib`: the drift `Library` (no inputs); a constant column is left out with a warning.
    - `pip_threshold`: inclusion probability above which a term is selected, as in
      `dtwin_jax.output_only.update.update_output_only`.
    - `settings`: the sampler's `SamplerSettings` (chains, draws, burn-in); the anchor's short
      selection runs use `dtwin_jax.output_only.stats.first_pass_settings` of it.
    - `seed`: the sampler's seed (also that of the states' error draws).
    - `progress`: show the stages and a bar of the sweeps.
    - `previous`: for a re-update, an earlier output-only update from accelerometers alone (a
      constant diffusion), whose drift statistics and constant diffusion's pseudo-observations,
      times `forget`, are added to this window's (`dtwin_jax.update.lifecycle.with_previous`);
      None for a first update. The states are this window's own (its anchor selects from this
      window alone).
    - `forget`: the previous statistics' weight, in [0, 1].
    - `allow_repeat`: take a window already in the history (its data would count twice).

    **Returns:** an `UpdateResult` of mode `"output-only"`: one `drift` equation per
    velocity and one `diffusion` equation (the constant `Gamma_ii`, velocity^2 / s)."""
    start = time.perf_counter()
    x, _ = accelerometer_layout(nominal, xdot, xdot_names, None)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names")
    rec = check_records(t, x, None, xdot, nominal, x_columns=0, xdot_columns=len(xdot_index))
    if previous is not None and previous.preprocessing.get("diffusion_library") != CONSTANT_DIFFUSION:
        raise DataError("a re-update from accelerometers alone needs a twin updated from accelerometers alone "
                        "(a constant diffusion)")
    if np.any(np.asarray(nominal.F0) != 0):
        raise DataError("output-only updates do not take a nominal F0 yet: set it to zero")
    R, N = rec.xdot.shape[:2]
    s = settings
    check_update(R * N, lib.K, len(nominal.regressed_index), s.num_chains, s.num_draws, s.num_burnin, library=lib.spec)
    u = np.zeros((R, N, nominal.n))
    warnings = []
    lib, dropped = without_constant_columns(lib, nominal, u)
    if dropped:
        warnings.append("accelerometers do not see a constant force (a static displacement): "
                        + ", ".join(dropped) + " left out of the library")
    check_previous(previous, "output-only", nominal, lib, forget)
    check_repeat(previous, rec, allow_repeat)
    vel = list(nominal.velocity_index)
    a = rec.xdot[..., [xdot_index.index(i) for i in vel]]
    dt, M2 = rec.dt, np.diag(np.asarray(nominal.M)) ** 2
    regressed = [nominal.state_names[i] for i in nominal.regressed_index]

    def select(xs):  # the anchor's terms: PIP > 1/2 in a short run on the increments
        trace = sample_equations(increment_stats(nominal, lib, dt, a, xs), first_pass_settings(settings), seed, False)
        return np.stack([e.coefficients for e in posteriors(trace, regressed, "drift", lib.names, 0.5)])

    def refit(xs, index):  # the settled support's least squares on the increments
        return selected_least_squares(increment_stats(nominal, lib, dt, a, xs), index)

    stages = Stages(progress, 3, "output-only update (accelerometers)")
    with stages("states and the sensor / force split"):
        sensor = force = None
        for p in range(SPLIT_PASSES):
            final = p == SPLIT_PASSES - 1
            xs, _, states_info = accelerometer_states(
                nominal, dt, rec.xdot, xdot_index, u, lib, select, interpolation=_INTERPOLATION, seed=seed,
                error_draws=ERROR_DRAWS if final else 0, refit=refit,
                force_variance=None if force is None else M2 * force,
                acceleration_noise_std=None if sensor is None else np.sqrt(sensor))
            _, weak = accelerometer_weak_stats(nominal, lib, dt, a, u, xs, interpolation=_INTERPOLATION)
            sensor, force = _split(weak)
        warnings += unsettled_warnings(states_info)
    with stages("drift sampling"):
        draws, coef = states_info.pop("error_draws", None), states_info.pop("coefficients")
        stats = with_previous(increment_stats(nominal, lib, dt, a, xs), "drift", previous, forget)
        trace = jax.block_until_ready(sample_equations(stats, settings, seed, progress))
        perturbed = None if draws is None else [increment_stats(nominal, lib, dt, a, xs + draw) for draw in draws]
        errors = _errors_in_variables(coef, perturbed)
        if errors is not None:  # the states' estimation error, in the selected terms' draws
            trace = trace._replace(theta=widened_draws(trace.theta, trace.gamma, errors, seed))
        drift = posteriors(trace, regressed, "drift", lib.names, pip_threshold)
    with stages("diffusion"), stages:
        # The increments' noise scale carries the estimate's spread (its level is the split's).
        sigma2 = np.asarray(trace.sigma2)  # (d, chains, draws)
        spread = sigma2 / sigma2.mean(axis=(1, 2), keepdims=True)
        gamma_draws = (force * dt)[:, None, None] * spread
        window_n = np.asarray(stats.n) if previous is None else np.asarray(stats.n) - forget * np.asarray(
            previous.statistics["drift"].n)
        diffusion_stats = with_previous(_constant_stats(gamma_draws, window_n), "diffusion", previous, forget)
        if previous is not None:  # the pooled level, this window's relative spread
            gamma_draws = (np.asarray(diffusion_stats.xty)[:, 0] / np.asarray(diffusion_stats.n))[:, None, None] * spread
        velocities = [nominal.state_names[i] for i in vel]
        diffusion = [EquationPosterior(v, "diffusion", ("1",), np.ones(g.shape + (1,), dtype=bool), g[..., None],
                                       sigma2[j], pip_threshold) for j, (v, g) in enumerate(zip(velocities, gamma_draws))]
    checks = collinearity_checks(stats, drift)
    if warnings:
        checks["preprocessing"] = {"ok": False, "warnings": warnings}
    equations = drift + diffusion
    return UpdateResult(
        mode="output-only",
        nominal=nominal,
        library=lib,
        equations=equations,
        pip_threshold=pip_threshold,
        settings=settings,
        seconds=time.perf_counter() - start,
        preprocessing={
            "layout": "accelerometers",
            "measured_rates": [nominal.state_names[i] for i in xdot_index],
            "states": "anchored kinematic RTS",
            "state_smoothing": states_info,
            "drift_rows": "accelerometer samples as Kramers-Moyal increments, regressors at the drift's prediction",
            "errors_in_variables": None if errors is None else np.sqrt(np.diag(errors["extra"])).tolist(),
            "acceleration_noise_std": np.sqrt(sensor).tolist(),
            "diffusion_library": CONSTANT_DIFFUSION,
            "diffusion_estimator": "the accelerations' white floor less the sensors' share (restricted likelihood "
                                   "of the weak rows)",
            "diffusion_ml": (force * dt).tolist(),
            "records": int(R),
            "samples": int(R * N),
            "state_range": state_range(xs, previous),
            "stage_seconds": dict(stages.seconds),
        },
        checks=checks,
        statistics={"drift": numpy_stats(stats), "diffusion": numpy_stats(diffusion_stats),
                    **({} if perturbed is None else {SPREAD_KIND: score_spread(coef, perturbed)})},
        history=updated_history(previous, "output-only", rec, forget, equations, time.perf_counter() - start),
    )


def increment_stats(nominal: LinearSecondOrder, lib: Library, dt: float, a, x) -> SuffStats:
    """Kramers-Moyal statistics of accelerometer samples.

    **Arguments:**

    - `nominal`: the nominal model `LinearSecondOrder`.
    - `lib`: the drift `Library` (no inputs).
    - `dt`: the sample interval, s.
    - `a`: `(R, N, d)` the accelerometers' averages over each sample's interval (acceleration
      units).
    - `x`: `(R, N, m)` the states.

    **Returns:** `SuffStats` batched over the `d` velocity equations (`gram (d, K, K)`, `xty
    (d, K)`, `yty (d,)`, `n (d,)` = `R (N - 1)`): sample `k` less the nominal drift, regressed
    on the library, both at the state one Euler step of the nominal drift predicts from sample
    `k - 1` (the regressors see no force of the interval's own)."""
    d, m = nominal.d, nominal.m
    vel = list(nominal.velocity_index)
    R, N, _ = x.shape
    zero = jnp.zeros((R, N - 1, nominal.n))
    before = jnp.asarray(x[:, :-1])
    pred = before + dt * jax.vmap(nominal.rate_batch)(before, zero)
    y = (a[:, 1:] - np.asarray(jax.vmap(nominal.rate_batch)(pred, zero))[..., vel]).reshape(-1, d)
    L = np.asarray(lib(pred.reshape(-1, m), zero.reshape(-1, nominal.n)))
    return SuffStats(np.stack([L.T @ L] * d), (L.T @ y).T, (y * y).sum(axis=0), np.full(d, float(L.shape[0])))


def _errors_in_variables(coef, perturbed) -> dict | None:
    """The spread of the selected terms' fit over the statistics `perturbed` at draws of the
    states' estimation error, for `dtwin_jax.preprocess.accelerometers.widened_draws`
    (no feedback gain): None when nothing is selected or no draws."""
    if coef is None or perturbed is None:
        return None
    index = [(e, int(k)) for e in range(coef.shape[0]) for k in np.flatnonzero(coef[e])]
    if not index:
        return None
    fits = np.array([selected_least_squares(st, index) for st in perturbed])
    return {"index": index, "gain": np.eye(len(index)), "extra": np.atleast_2d(np.cov(fits.T))}


def score_spread(coef, perturbed) -> SuffStats:
    """The covariance of each equation's score `b - G c` over draws of the states' estimation
    error: the part of a window's score that its own states' error puts there
    (`dtwin_jax.monitor.change.window_test`).

    **Arguments:**

    - `coef`: `(q, K)` the window's coefficients `c`, or None for zero.
    - `perturbed`: the statistics (`SuffStats`, `G = gram (q, K, K)`, `b = xty (q, K)`) at each
      of `S` draws of the states' estimation error, a sequence.

    **Returns:** `SuffStats`: `gram (q, K, K)` the scores' covariance, `xty` and `yty` zeros,
    `n (q,)` the number of draws `S`."""
    scores = np.array([np.asarray(st.xty) - np.einsum("jkl,jl->jk", np.asarray(st.gram),
                                                        0.0 if coef is None else np.asarray(coef, dtype=float))
                       for st in perturbed])  # (S, q, K)
    S, q, K = scores.shape
    d = scores - scores.mean(axis=0)
    return SuffStats(np.einsum("sjk,sjl->jkl", d, d) / max(S - 1, 1), np.zeros((q, K)), np.zeros(q), np.full(q, float(S)))


def _split(info: dict) -> tuple[np.ndarray, np.ndarray]:
    """The accelerations' white floor `T (d,)` split `(sensor variance (d,), force Gamma / dt
    (d,))`: the weak rows' covariance `S_x(T) + lambda S_w` is that of a sensor variance `s`
    and a force variance `f` with `f / s = lambda / T`, and `s + f = T`. The floor is
    measured well (it is nearly all of the accelerations' variance in ambient vibration); the
    rows' noise scale is not (on a zoo member `sigma2 lambda dt` was far off where the split of
    the floor was close)."""
    floor = np.asarray(info["acceleration_noise_std"]) ** 2
    lam = np.asarray(info["equation_error_weight"])
    return floor * floor / (floor + lam), floor * lam / (floor + lam)


def _constant_stats(gamma_draws, n) -> SuffStats:
    """The constant diffusion's statistics for the twin store, `n` pseudo-observations per
    velocity whose mean and spread are the draws' (`gamma_draws (d, chains, draws)`)."""
    g = np.asarray(gamma_draws).reshape(gamma_draws.shape[0], -1)
    mean, var = g.mean(axis=1), g.var(axis=1)
    n = np.asarray(n, dtype=np.float64)
    return SuffStats(n[:, None, None], (n * mean)[:, None], n * (mean**2 + var), n)
