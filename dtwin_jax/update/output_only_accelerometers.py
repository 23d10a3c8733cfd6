"""Framework 2 from accelerometers alone: the ambient vibration of a structure in service.

Nothing but the accelerations ``a`` of the degrees of freedom is measured; the force is white
and unknown (the Ito diffusion of framework 2). The states come from the anchored smoother
(:mod:`dtwin_jax.accelerometers`) with no input: the kinematic chains integrate the measured
accelerations, and the equation of motion anchors them below the first mode, its force being
the white one. The drift perturbation is the weak form of the velocity equations
(:mod:`dtwin_jax.weak_form_accelerometers`), whose rows need no state estimate for the nominal
part, and the diffusion is their white equation error.

The accelerations' white floor ``T`` (their Savitzky-Golay residual) is the sensor's noise
plus the force's ``Gamma / dt``; the two enter the weak rows through different filters (the
sensor's through ``chi''``, ``chi'`` and ``chi`` weighted by the nominal ``K`` and ``C``, the
force's through ``chi''`` only), so the rows' restricted likelihood splits them. The smoother
needs the split (the sensor's share is its kinematic chains' noise, the force's its anchor's), so
the split and the states are iterated: measured on zoo-0000 (2 s x 10 records, 3% sensor
noise), the first pass with the whole floor as sensor noise gave ``Gamma / dt`` 67 (truth
105.6), the second 103.5, the third 103.9.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from dtwin_jax.accelerometers import ERROR_DRAWS, accelerometer_layout, accelerometer_states, sampler_selection, widened_draws
from dtwin_jax.collinearity import collinearity_checks
from dtwin_jax.data import check_records, state_range
from dtwin_jax.errors import DataError
from dtwin_jax.estimate import measured_index
from dtwin_jax.library import Library
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.progress import Stages
from dtwin_jax.resources import check_update
from dtwin_jax.sampler import SuffStats
from dtwin_jax.systems import LinearSecondOrder
from dtwin_jax.update.accelerometer_regression import accelerometer_regression, without_constant_columns
from dtwin_jax.update.lifecycle import check_repeat, updated_history
from dtwin_jax.update.result import SamplerSettings, UpdateResult
from dtwin_jax.update.sampling import _sample_equations, numpy_stats, posteriors

__all__ = ["CONSTANT_DIFFUSION", "SPLIT_PASSES", "update_from_accelerometers"]

# The diffusion of each velocity is one constant (its equation error): formats.md's
# "constant-only diffusion is the term 1".
CONSTANT_DIFFUSION = "terms:1"
# Passes of the states with the sensor / force split re-estimated (the module's note).
SPLIT_PASSES = 3
# The smoother's inputs are integrated as band-limited signals (the force is broadband).
_INTERPOLATION = "bandlimited"


def update_from_accelerometers(nominal: LinearSecondOrder, t, xdot, xdot_names, lib: Library, *,
                               pip_threshold: float, settings: SamplerSettings, seed: int, progress: bool,
                               previous, forget: float, allow_repeat: bool) -> UpdateResult:
    """Discover the drift perturbation and the constant diffusion of ``nominal`` from
    accelerometers alone (called by :func:`~dtwin_jax.update.output_only.update_output_only`).

    **Arguments:**

    - ``nominal``: the nominal model (every degree of freedom with an accelerometer, ``K``
      positive definite, no extra states).
    - ``t``: ``(N,)`` sample times, s, uniform.
    - ``xdot``: ``(N, s)`` or ``(R, N, s)`` measured rates; those of the velocity states are the
      accelerations (state units / s^2).
    - ``xdot_names``: the states of its columns (None: all ``m``).
    - ``lib``: the drift library (no inputs); a constant column is left out with a warning.
    - ``pip_threshold``, ``settings``, ``seed``, ``progress``, ``allow_repeat``: as
      :func:`~dtwin_jax.update.output_only.update_output_only`.
    - ``previous``, ``forget``: a re-update; not taken yet (refused in one line).

    **Returns:** an :class:`UpdateResult` of mode ``"output-only"``: one ``drift`` equation per
    velocity and one ``diffusion`` equation (the constant ``Gamma_ii``, velocity^2 / s)."""
    start = time.perf_counter()
    if previous is not None:
        raise DataError("re-updates from accelerometers alone are not supported yet: update from the records together")
    x, _ = accelerometer_layout(nominal, xdot, xdot_names, None)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names")
    rec = check_records(t, x, None, xdot, nominal, x_columns=0, xdot_columns=len(xdot_index))
    if np.any(np.asarray(nominal.F0) != 0):
        raise DataError("output-only updates do not take a nominal F0 yet: set it to zero")
    check_repeat(previous, rec, allow_repeat)
    R, N = rec.xdot.shape[:2]
    s = settings
    check_update(R * N, lib.K, len(nominal.regressed_index), s.num_chains, s.num_draws, s.num_burnin, library=lib.spec)
    u = np.zeros((R, N, nominal.n))
    warnings = []
    lib, dropped = without_constant_columns(lib, nominal, u)
    if dropped:
        warnings.append("accelerometers do not see a constant force (a static displacement): "
                        + ", ".join(dropped) + " left out of the library")
    vel = list(nominal.velocity_index)
    a = rec.xdot[..., [xdot_index.index(i) for i in vel]]
    dt, M2 = rec.dt, np.diag(np.asarray(nominal.M)) ** 2
    regressed = [nominal.state_names[i] for i in nominal.regressed_index]
    stages = Stages(progress, 3, "output-only update (accelerometers)")
    with stages("states and the sensor / force split"):
        sensor = force = None
        for p in range(SPLIT_PASSES):
            final = p == SPLIT_PASSES - 1
            select = sampler_selection(nominal, dt, a, lib, u, settings, seed, _INTERPOLATION, force)
            xs, _, states_info = accelerometer_states(
                nominal, dt, rec.xdot, xdot_index, u, lib, select, interpolation=_INTERPOLATION, seed=seed,
                error_draws=ERROR_DRAWS if final else 0, white_force=force,
                force_variance=None if force is None else M2 * force,
                acceleration_noise_std=None if sensor is None else np.sqrt(sensor))
            if final:
                break
            stats, info, _, _ = accelerometer_regression(nominal, lib, dt, a, u, xs, states_info, lib.names,
                                                         _INTERPOLATION, force)
            sensor, force = _split(info)
    with stages("drift sampling"):
        stats, info, feedback, more = accelerometer_regression(nominal, lib, dt, a, u, xs, states_info, lib.names,
                                                               _INTERPOLATION, force)
        warnings.extend(more)
        trace = jax.block_until_ready(_sample_equations(stats, settings, seed, progress))
        if feedback is not None:
            trace = trace._replace(theta=widened_draws(trace.theta, trace.gamma, feedback, seed))
        drift = posteriors(trace, regressed, "drift", lib.names, pip_threshold)
    with stages("diffusion"), stages:
        sensor, force = _split(info)
        # The rows' noise scale carries the estimate's spread (its mean is not used, above).
        sigma2 = np.asarray(trace.sigma2)  # (d, chains, draws)
        gamma_draws = (force * dt)[:, None, None] * sigma2 / sigma2.mean(axis=(1, 2), keepdims=True)
        velocities = [nominal.state_names[i] for i in vel]
        diffusion = [EquationPosterior(v, "diffusion", ("1",), np.ones(g.shape + (1,), dtype=bool), g[..., None], sigma2[j],
                                       pip_threshold) for j, (v, g) in enumerate(zip(velocities, gamma_draws))]
        diffusion_stats = _constant_stats(gamma_draws, np.asarray(stats.n))
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
            "state_smoothing": {"states": states_info, "regression": info},
            "acceleration_noise_std": np.sqrt(sensor).tolist(),
            "diffusion_library": CONSTANT_DIFFUSION,
            "diffusion_estimator": "the weak rows' white equation error, split from the accelerometers' noise by "
                                   "restricted likelihood",
            "diffusion_ml": (force * dt).tolist(),
            "records": int(R),
            "samples": int(R * N),
            "state_range": state_range(xs, None),
            "stage_seconds": dict(stages.seconds),
        },
        checks=checks,
        statistics={"drift": numpy_stats(stats), "diffusion": diffusion_stats},
        history=updated_history(None, "output-only", rec, forget, equations, time.perf_counter() - start),
    )


def _split(info: dict) -> tuple[np.ndarray, np.ndarray]:
    """The accelerations' white floor ``T (d,)`` split ``(sensor variance (d,), force Gamma / dt
    (d,))``: the weak rows' covariance ``S_x(T) + lambda S_w`` is that of a sensor variance ``s``
    and a force variance ``f`` with ``f / s = lambda / T``, and ``s + f = T``. The floor is
    measured well (it is nearly all of the accelerations' variance in ambient vibration); the
    noise scale of the rows is not (zoo-0006, 40 records: ``sigma2 lambda dt`` was 43% off with
    the Ito correction's residual shift, 20% without; the split of the floor 0.3%)."""
    floor = np.asarray(info["acceleration_noise_std"]) ** 2
    lam = np.asarray(info["equation_error_weight"])
    return floor * floor / (floor + lam), floor * lam / (floor + lam)


def _constant_stats(gamma_draws, n) -> SuffStats:
    """The constant diffusion's statistics for the twin store, ``n`` pseudo-observations per
    velocity whose mean and spread are the draws' (``gamma_draws (d, chains, draws)``)."""
    g = np.asarray(gamma_draws).reshape(gamma_draws.shape[0], -1)
    mean, var = g.mean(axis=1), g.var(axis=1)
    n = np.asarray(n, dtype=np.float64)
    return SuffStats(n[:, None, None], (n * mean)[:, None], n * (mean**2 + var), n)
