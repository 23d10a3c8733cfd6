"""Updating a digital twin: measurements -> denoised states -> targets and library ->
sampler -> posterior -> updated twin.

Framework 1 (input-output, the paper's Section 4.1): measured states ``x``, inputs ``u`` and
rates ``xdot`` (or rates estimated from ``x``); every regressed equation is sampled by the
spike-and-slab Gibbs kernel, all equations in one vmapped call.

Framework 2 (output-only, Section 4.2): measured states only; the drift perturbation comes
from Kramers-Moyal targets (:mod:`dtwin_jax.kramers_moyal`), then the diffusion of every
velocity from the Kalman likelihood given that drift (:mod:`dtwin_jax.statespace`), whose EM
targets are sampled by the same kernel.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import kramers_moyal, statespace, sampler
from dtwin_jax.data import Records, check_records
from dtwin_jax.errors import DataError
from dtwin_jax.library import DEFAULT_LIBRARY, Library, check_columns, parse_library
from dtwin_jax.denoise import auto_half_width, kinematic_smoother, savgol_design_ok, savgol_states
from dtwin_jax.estimate import measured_index, state_smoother
from dtwin_jax.measurement import smooth
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.predict import UpdatedTwin, diffusion_terms
from dtwin_jax.systems import LinearSecondOrder, check_interpolation
from dtwin_jax.checks import residual_checks
from dtwin_jax.targets import equation_stats, input_output_targets, smoothed_input_output_stats

__all__ = [
    "SamplerSettings",
    "UpdateResult",
    "UpdatedTwin",
    "denoise_states",
    "update_input_output",
    "update_output_only",
    "OUTPUT_ONLY_LIBRARY",
    "DIFFUSION_LIBRARY",
]

# The paper's library without inputs (none are measured), and a small state-dependent
# diffusion library: constant, linear and quadratic.
OUTPUT_ONLY_LIBRARY = DEFAULT_LIBRARY.replace(",input", "")
DIFFUSION_LIBRARY = "poly:2"


@dataclass(frozen=True)
class SamplerSettings:
    """Chains, draws and prior of the Gibbs sampler (the paper uses 3000 sweeps)."""

    num_chains: int = 4
    num_draws: int = 2000
    num_burnin: int = 1000
    prior: sampler.SpikeSlabPrior = sampler.SpikeSlabPrior()
    p0: float = 0.1
    v_s: float = 10.0
    max_active: int | None = None


@dataclass
class UpdateResult:
    """Posteriors of every regressed equation, the updated twin and run diagnostics."""

    mode: str
    nominal: LinearSecondOrder
    library: Library
    equations: list[EquationPosterior]
    pip_threshold: float
    settings: SamplerSettings
    seconds: float
    preprocessing: dict = field(default_factory=dict)
    # Residual checks (dtwin_jax.checks.residual_checks) keyed by equation label; output-only
    # also "<state> noise correction" (the corrected Gram's definiteness, `correction_margin`).
    checks: dict = field(default_factory=dict)
    # The sufficient statistics the sampler saw, by kind ("drift", "diffusion"), batched over
    # equations, physical units: a re-update adds new data's to them (posterior as prior).
    statistics: dict = field(default_factory=dict)
    # One entry per update of this twin, oldest first (time, data size, prior, equations).
    history: list = field(default_factory=list)

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.nominal.state_names

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.nominal.input_names if self.library.uses_inputs else ()

    @property
    def twin(self) -> UpdatedTwin:
        """The updated model at the posterior means of the selected terms (with the
        discovered diffusion for an output-only update); :func:`predict.posterior_twins`
        gives posterior draws of it."""
        drift = [e for e in self.equations if e.kind == "drift"]
        index = tuple(self.state_names.index(e.state) for e in drift)
        coef = np.stack([e.coefficients for e in drift]) if drift else np.zeros((0, self.library.K))
        diffusion = [e for e in self.equations if e.kind == "diffusion"]
        interpolation = self.preprocessing.get("input_interpolation", "held")
        if not diffusion:
            return UpdatedTwin(self.nominal, self.library, index, jnp.asarray(coef), interpolation=interpolation)
        dcoef = np.stack([e.coefficients for e in diffusion])
        return UpdatedTwin(self.nominal, self.library, index, jnp.asarray(coef), *diffusion_terms(self, dcoef))

    def diagnostics(self) -> dict:
        rhat = np.concatenate([e.rhat() for e in self.equations] + [np.zeros(0)])
        ess = np.concatenate([e.ess_bulk() for e in self.equations] + [np.zeros(0)])
        rhat_g = np.concatenate([e.rhat_gamma() for e in self.equations] + [np.zeros(0)])
        rhat, ess = rhat[np.isfinite(rhat)], ess[np.isfinite(ess)]
        # inf (chains never overlap) must not vanish; clipped so that the JSON stays valid.
        rhat_g = np.minimum(rhat_g[~np.isnan(rhat_g)], 1e6)
        spread = {self._label(e): e.pip_chain_spread_max for e in self.equations}
        return {
            "chains": self.settings.num_chains,
            "draws": self.settings.num_draws,
            "burn_in": self.settings.num_burnin,
            "rhat_max": float(rhat.max()) if rhat.size else None,
            "rhat_gamma_max": float(rhat_g.max()) if rhat_g.size else None,
            "ess_bulk_min": float(ess.min()) if ess.size else None,
            "pip_chain_spread_max": max(spread.values(), default=0.0),
            "pip_chain_spread": spread,
            "seconds": round(self.seconds, 3),
        }

    @staticmethod
    def _label(e: EquationPosterior) -> str:
        return e.state if e.kind == "drift" else f"{e.state} [diffusion]"

    def warnings(self) -> list[str]:
        """One line per sign of an unreliable result: failed residual checks, chains that
        disagree on a PIP by more than 0.2, R-hat above 1.01."""
        out = [f"{label}: {w}" for label, c in self.checks.items() for w in c.get("warnings", [])]
        for e in self.equations:
            pips = e.pip_per_chain
            for k in np.flatnonzero(e.pip_chain_spread > 0.2):
                out.append(
                    f"chains disagree on PIP of {e.names[k]} in {self._label(e)} "
                    f"({pips[:, k].min():.2f}..{pips[:, k].max():.2f}): multimodal posterior, run longer"
                )
        diag = self.diagnostics()
        for key in ("rhat_max", "rhat_gamma_max"):
            if diag[key] is not None and diag[key] > 1.01:
                what = "coefficients" if key == "rhat_max" else "inclusion indicators"
                out.append(f"R-hat of the {what} {diag[key]:.3g} > 1.01: chains have not converged, run longer")
        return out

    def to_json(self) -> dict:
        """The result file of formats.md."""
        return {
            "mode": self.mode,
            "state_names": list(self.state_names),
            "input_names": list(self.input_names),
            "pip_threshold": self.pip_threshold,
            "library": self.library.spec,
            "equations": [e.to_json() for e in self.equations],
            "diagnostics": self.diagnostics(),
            "preprocessing": self.preprocessing,
            "checks": self.checks,
            "history": self.history,
        }

    def summary(self) -> str:
        """The discovered perturbation, one equation per line."""
        return "\n".join(e.equation() for e in self.equations)

    def to_arviz(self):
        """All equations' draws in one arviz DataTree (variables ``theta_<state>`` etc.)."""
        import arviz as az

        posterior, dims, coords = {}, {}, {}
        for e in self.equations:
            tag = f"{e.state}_{e.kind}"
            posterior[f"theta_{tag}"] = e.theta
            posterior[f"gamma_{tag}"] = e.gamma.astype(np.int8)
            posterior[f"sigma2_{tag}"] = e.sigma2
            dims[f"theta_{tag}"] = dims[f"gamma_{tag}"] = [f"term_{tag}"]
            coords[f"term_{tag}"] = list(e.names)
        return az.from_dict({"posterior": posterior}, dims=dims, coords=coords)


def denoise_states(records: Records, nominal: LinearSecondOrder, smoothing="auto") -> tuple:
    """Denoise the measured states before they enter the library and the nominal rates.

    ``smoothing``: ``"auto"`` (the kinematic RTS smoother when rates are measured, else a
    Savitzky-Golay filter matched to the sampling rate), ``"savgol"``, an int Savitzky-Golay
    half width, or None (raw states). Returns ``(x (R, N, m), description dict or None)``.
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


def _with_previous(stats: sampler.SuffStats, kind: str, previous, forget: float) -> sampler.SuffStats:
    """``stats`` plus ``forget`` times the previous update's of the same ``kind``: for the
    conjugate part of the model the posterior after both data windows, so the previous
    posterior serves as the prior (``forget < 1`` discounts old data, for a system that drifts)."""
    if previous is None:
        return stats
    old = previous.statistics.get(kind)
    if old is None:
        raise DataError(f"the previous update holds no {kind} statistics to combine with")
    # Same shapes: _check_previous has matched the libraries.
    return sampler.SuffStats(*(jnp.asarray(a) + forget * np.asarray(b) for a, b in zip(stats, old)))


def _check_previous(previous, mode: str, nominal: LinearSecondOrder, lib: Library, forget: float) -> None:
    if previous is None:
        return
    if not 0.0 <= forget <= 1.0:
        raise DataError(f"forget must be in [0, 1], got {forget}")
    if previous.mode != mode:
        raise DataError(f"cannot re-update a {previous.mode} twin with {mode} data")
    if previous.library.names != lib.names:
        raise DataError(f"re-update needs the previous library '{previous.library.spec}', got '{lib.spec}'")
    same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(
        (previous.nominal.M, previous.nominal.C, previous.nominal.K, previous.nominal.B, previous.nominal.F0),
        (nominal.M, nominal.C, nominal.K, nominal.B, nominal.F0)))
    if not same or previous.nominal.extra_states != nominal.extra_states:
        raise DataError("re-update needs the previous update's nominal model")


def _history(previous, mode: str, rec: Records, forget: float, equations, seconds: float) -> list[dict]:
    """The previous update's history plus an entry for this one."""
    from datetime import datetime, timezone

    from dtwin_jax import __version__

    past = [] if previous is None else list(previous.history)
    prior = "spike-and-slab" if previous is None else f"posterior of update {len(past)} (forget {forget:g})"
    R, N, _ = rec.x.shape
    return past + [{
        "update": len(past) + 1,
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mode": mode,
        "records": int(R),
        "samples": int(R * N),
        "window_s": float((N - 1) * rec.dt),
        "prior": prior,
        "seconds": round(seconds, 3),
        "equations": [e.equation() for e in equations],
        "dtwin_jax": __version__,
    }]


def _numpy_stats(stats: sampler.SuffStats) -> sampler.SuffStats:
    return sampler.SuffStats(*(np.asarray(a) for a in stats))


def _library(library, nominal: LinearSecondOrder, num_inputs: int) -> Library:
    if isinstance(library, Library):
        return library
    return parse_library(library or DEFAULT_LIBRARY, nominal.m, num_inputs)


def _sample_equations(stats: sampler.SuffStats, settings: SamplerSettings, seed: int, progress: bool):
    """One sampler call over the batched statistics of every equation."""
    q = stats.xty.shape[0]
    keys = jax.random.split(jax.random.key(seed), q)
    if progress:
        traces = [
            sampler.sample(keys[i], jax.tree.map(lambda a: a[i], stats), progress=True, **_sampler_kwargs(settings))
            for i in range(q)
        ]
        return jax.tree.map(lambda *a: jnp.stack(a), *traces)
    return _sample_batch(keys, stats, settings, sampler.default_batch_method())


def _sampler_kwargs(settings: SamplerSettings) -> dict:
    return dict(
        num_draws=settings.num_draws,
        num_burnin=settings.num_burnin,
        num_chains=settings.num_chains,
        prior=settings.prior,
        max_active=settings.max_active,
        p0=settings.p0,
        v_s=settings.v_s,
    )


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample_batch(keys, stats, settings: SamplerSettings, method: str):
    # One compiled program per settings and shapes: an eager lax.map over a fresh lambda
    # would compile again on every update.
    kwargs = _sampler_kwargs(settings)
    return sampler.batch_map(lambda k, s: sampler.sample(k, s, chain_method=method, **kwargs), method, keys, stats)


def update_input_output(
    nominal: LinearSecondOrder,
    t,
    x,
    u,
    xdot=None,
    *,
    x_names=None,
    xdot_names=None,
    interpolation: str = "held",
    library: str | Library | None = None,
    smoothing="auto",
    pip_threshold: float = 0.5,
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    progress: bool = False,
    previous: UpdateResult | None = None,
    forget: float = 1.0,
) -> UpdateResult:
    """Discover the perturbation of ``nominal`` from input-output measurements.

    ``t (N,)`` s; ``x (N, p)`` or ``(R, N, p)`` measured states, named ``x_names`` (default
    all ``m`` in order); ``u (N, n)`` or ``(R, N, n)`` measured inputs, held over each step
    or interpolated linearly (``interpolation``); ``xdot`` measured rates of the states
    ``xdot_names`` (accelerometers), or None. With every state measured the rates come from
    the kinematic smoother (rates measured) or a Savitzky-Golay derivative; with some states
    unmeasured, or when the Savitzky-Golay design cannot be met (a few samples per period), or
    with ``smoothing="statespace"``, every state and rate comes from the state-space smoother
    of :mod:`dtwin_jax.estimate`. ``library`` is a spec (formats.md) or a :class:`Library`.
    ``previous``: an earlier update of the same twin (same nominal model and library) whose
    posterior is the prior of this one (its statistics, times ``forget``, are added to the
    new window's); the result's history continues the previous one.
    """
    start = time.perf_counter()
    check_interpolation(interpolation)
    x_index = measured_index(x_names, nominal)
    xdot_index = measured_index(xdot_names, nominal, "xdot_names") if xdot is not None else ()
    rec = check_records(t, x, u, xdot, nominal, x_columns=len(x_index), xdot_columns=len(xdot_index) or None)
    if rec.u is None:
        raise DataError("input-output update needs measured inputs 'u'")
    lib = _library(library, nominal, nominal.n)
    _check_previous(previous, "input-output", nominal, lib, forget)
    hw = auto_half_width(nominal, rec.dt, rec.t.size)
    every = tuple(range(nominal.m))
    partial = x_index != every or (rec.xdot is not None and xdot_index != every)
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
    if partial or smoothing == "statespace":
        xs, rates, smoothing_info = state_smoother(
            nominal, rec.dt, rec.x, x_index, rec.u, rec.xdot, xdot_index, interpolation=interpolation
        )
        rate_source = "state-space smoother"
        correct = False
    else:
        xs, smoothing_info = denoise_states(rec, nominal, smoothing)
        if rec.xdot is not None:
            rates = rec.xdot
            rate_source = "measured"
        else:
            rates = np.asarray(smooth(rec.x, hw, order=4, deriv=1, dt=rec.dt))
            rate_source = f"savitzky-golay derivative (order 4, half width {hw})"
        correct = rec.xdot is not None and smoothing is not None
    R, N, m = xs.shape
    check_columns(np.asarray(lib(xs.reshape(R * N, m), rec.u.reshape(R * N, -1))), lib.names)
    # The same jitted chain as the batched studies (dtwin_jax.studies).
    stats, noise_var = smoothed_input_output_stats(nominal, lib, xs, rec.u, rates, hw, correct_inputs=correct)
    n_eff = None
    if rate_source == "state-space smoother":
        stats, n_eff = _autocorrelation_corrected(stats, nominal, lib, xs, rec.u, rates)
    stats = _with_previous(stats, "drift", previous, forget)
    trace = _sample_equations(stats, settings, seed, progress)
    trace = jax.tree.map(np.asarray, trace)
    names = nominal.state_names
    equations = [
        EquationPosterior(
            names[i], "drift", lib.names, trace.gamma[j], trace.theta[j], trace.sigma2[j],
            pip_threshold,
        )
        for j, i in enumerate(nominal.regressed_index)
    ]
    residual = _input_output_residuals(nominal, lib, xs, rec.u, rates, equations)
    checks = {
        e.state: residual_checks(residual[j], xs, nominal.velocity_index, names)
        for j, e in enumerate(equations)
    }
    if warnings:
        checks["preprocessing"] = {"ok": False, "warnings": warnings}
    return UpdateResult(
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
            "input_interpolation": interpolation,
            "input_noise_std": None if noise_var is None else np.sqrt(noise_var).tolist(),
            "samples": int(R * N),
            "effective_samples": None if n_eff is None else n_eff.tolist(),
        },
        checks=checks,
        statistics={"drift": _numpy_stats(stats)},
        history=_history(previous, "input-output", rec, forget, equations, time.perf_counter() - start),
    )


def _autocorrelation_corrected(stats, nominal, lib, xs, u, rates) -> tuple[sampler.SuffStats, np.ndarray]:
    """Statistics scaled to the residuals' effective sample size `(q,)`.

    A smoother's rate estimates are smooth in time, so the regression residuals (model
    mismatch, estimation error) are autocorrelated, and counting every sample as independent
    makes the posterior too narrow and every small systematic term "certain" (on the
    Silverbox: 0.8% posterior std of the cubic stiffness where windows differ by 4%, and
    velocity cross-terms at PIP 1). The residuals of a least-squares fit on the whole
    library give the effective size (arviz's ESS, summed over records); scaling the
    statistics by `n_eff / n` keeps their estimates and widens the posterior to match."""
    import arviz as az

    R, N, m = xs.shape
    x, uu = jnp.asarray(xs).reshape(R * N, m), jnp.asarray(u).reshape(R * N, -1)
    Y = np.asarray(input_output_targets(nominal, x, uu, jnp.asarray(rates).reshape(R * N, m)))
    L = np.asarray(lib(x, uu))
    coef, *_ = np.linalg.lstsq(L / np.linalg.norm(L, axis=0), Y, rcond=None)
    residual = (Y - (L / np.linalg.norm(L, axis=0)) @ coef).T.reshape(-1, R, N)
    n_eff = np.array([sum(float(az.ess(r[None], method="mean")) for r in eq) for eq in residual])
    scale = jnp.asarray(np.minimum(n_eff / (R * N), 1.0))
    scaled = sampler.SuffStats(stats.gram * scale[:, None, None], stats.xty * scale[:, None], stats.yty * scale,
                               stats.n * scale)
    return scaled, n_eff


def _input_output_residuals(nominal, lib, xs, u, rates, equations) -> np.ndarray:
    """Residuals ``(q, R, N)`` of every regressed equation under its selected terms."""
    R, N, m = xs.shape
    x, uu = jnp.asarray(xs).reshape(R * N, m), jnp.asarray(u).reshape(R * N, -1)
    Y = input_output_targets(nominal, x, uu, jnp.asarray(rates).reshape(R * N, m))
    coef = jnp.asarray(np.stack([e.coefficients for e in equations]))
    return np.asarray((Y - lib(x, uu) @ coef.T).T).reshape(-1, R, N)


def _output_only_library(library, nominal: LinearSecondOrder, default: str) -> Library:
    lib = library if isinstance(library, Library) else parse_library(library or default, nominal.m, 0)
    if lib.uses_inputs:
        raise DataError("library family 'input' needs measured inputs; output-only data has none")
    return lib


def _posteriors(trace, state_names, kind, names, pip_threshold):
    trace = jax.tree.map(np.asarray, trace)
    return [
        EquationPosterior(state, kind, names, trace.gamma[j], trace.theta[j], trace.sigma2[j], pip_threshold)
        for j, state in enumerate(state_names)
    ]


def update_output_only(
    nominal: LinearSecondOrder,
    t,
    x,
    *,
    library: str | Library | None = None,
    diffusion_library: str | Library | None = None,
    pip_threshold: float = 0.5,
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    progress: bool = False,
    previous: UpdateResult | None = None,
    forget: float = 1.0,
) -> UpdateResult:
    """Discover drift perturbation and diffusion of ``nominal`` from measured states only.

    ``t (N,)`` s, uniform; ``x (N, m)`` one record (a structure in service) or ``(R, N, m)``
    an ensemble of independent records; both are pooled into one regression. ``library``
    (drift, default :data:`OUTPUT_ONLY_LIBRARY`) and ``diffusion_library`` (default
    :data:`DIFFUSION_LIBRARY`) are specs (formats.md) or :class:`Library`. The result holds
    one ``drift`` equation per regressed state and one ``diffusion`` equation (the diagonal
    ``Gamma_ii = (G G^T)_ii``, units of velocity^2 / s) per velocity. ``previous`` and
    ``forget``: a re-update, as in :func:`update_input_output` (drift and diffusion).
    """
    start = time.perf_counter()
    rec = check_records(t, x, None, None, nominal)
    if np.any(np.asarray(nominal.F0) != 0):
        raise DataError("output-only updates do not take a nominal F0 yet: set it to zero and keep the constant term '1' in the library")
    lib = _output_only_library(library, nominal, OUTPUT_ONLY_LIBRARY)
    dlib = _output_only_library(diffusion_library, nominal, DIFFUSION_LIBRARY)
    _check_previous(previous, "output-only", nominal, lib, forget)
    if previous is not None and previous.preprocessing.get("diffusion_library") != dlib.spec:
        raise DataError(f"re-update needs the previous diffusion library '{previous.preprocessing.get('diffusion_library')}'")
    R, N, m = rec.x.shape
    dt = rec.dt
    noise_var = kramers_moyal.noise_variance(rec.x)
    check_columns(np.asarray(lib(rec.x.reshape(-1, m)[:: max(1, R * N // 20000)])), lib.names)
    drift_stats, margin = output_only_drift_stats(nominal, lib, rec.x, dt, noise_var, jax.random.key(seed))
    names = nominal.state_names
    regressed = [names[i] for i in nominal.regressed_index]
    drift_stats = _with_previous(drift_stats, "drift", previous, forget)
    trace = _sample_equations(drift_stats, settings, seed, progress)
    drift = _posteriors(trace, regressed, "drift", lib.names, pip_threshold)
    # One step's mean drift: friction's sign averaged over half a step's Brownian increment.
    residual_var = np.array([e.sigma2.mean() for e in drift])
    gamma_drift = brownian_variance(nominal, dt, noise_var, residual_var)
    step_smoothing = jnp.zeros(m).at[jnp.asarray(nominal.velocity_index)].set(0.5 * dt * gamma_drift)
    step = statespace.DriftStep.from_coefficients(
        nominal, lib, np.stack([e.coefficients for e in drift]), dt, step_smoothing
    )
    pilot, window = kramers_moyal.preaveraged_diffusion(nominal, rec.x, dt, noise_var, step.perturbation)
    y = statespace.segments(rec.x)
    gamma, gamma_cov, fitted_noise, lin = statespace.diffusion_mle(step, y, noise_var, pilot)
    vel = tuple(int(v) for v in nominal.velocity_index)
    Yg, Xg = statespace.diffusion_targets(lin, y, fitted_noise, gamma, vel)
    Yg = np.asarray(Yg).reshape(-1, nominal.d)
    Lg = np.asarray(dlib(np.asarray(Xg).reshape(-1, m)))
    check_columns(Lg, dlib.names)
    gamma_var = np.diag(np.asarray(gamma_cov))
    stats = _diffusion_stats(equation_stats(Lg, Yg), Yg, np.asarray(gamma), gamma_var)
    stats = _with_previous(stats, "diffusion", previous, forget)
    trace = _sample_equations(stats, settings, seed + 1, progress)
    velocities = [names[i] for i in nominal.velocity_index]
    diffusion = _posteriors(trace, velocities, "diffusion", dlib.names, pip_threshold)
    # The drift's posterior-predictive check: one-step innovations of the velocities under
    # the fitted drift and diffusion, white and unpredictable from the past when it fits.
    innov, predicted = statespace.standardized_innovations(lin, y, fitted_noise, gamma, vel)
    predicted = np.asarray(predicted)
    checks = {
        names[v]: residual_checks(np.asarray(innov[..., j]), predicted, vel, names)
        for j, v in enumerate(vel)
    }
    for state, mg in zip(regressed, np.asarray(margin)):
        checks[f"{state} noise correction"] = _margin_check(float(mg))
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
            "diffusion_pilot": np.asarray(pilot).tolist(),
            "diffusion_pilot_window": int(window),
            "diffusion_ml": np.asarray(gamma).tolist(),
            "diffusion_ml_std": np.sqrt(gamma_var).tolist(),
            "diffusion_effective_samples": np.asarray(stats.n).tolist(),
            "records": int(R),
            "samples": int(R * N),
        },
        checks=checks,
        statistics={"drift": _numpy_stats(drift_stats), "diffusion": _numpy_stats(stats)},
        history=_history(previous, "output-only", rec, forget, drift + diffusion, time.perf_counter() - start),
    )


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
    return sampler.SuffStats(
        stats.gram * scale[:, None, None],
        stats.xty * scale[:, None],
        (stats.yty + n * missing) * scale,
        stats.n * scale,
    )


_FIRST_PASS = dict(num_chains=1, num_draws=300, num_burnin=300)
FIRST_PASS_ROWS = 20000


@functools.partial(jax.jit, static_argnums=(1,))
def output_only_drift_stats(nominal: LinearSecondOrder, lib: Library, x, dt, noise_var, key) -> tuple:
    """Kramers-Moyal drift statistics of records ``x (R, N, m)`` (batched over the regressed
    states), with the regressors moved along the model's drift (two passes).

    The first pass moves them along the nominal model only, on the first ~20000 samples
    (:data:`FIRST_PASS_ROWS`); a short sampler run gives the
    selected terms (PIP > 0.5) and their means, and the second pass moves the regressors
    along the nominal model plus that estimate (its error enters only the O(dt) shift). A
    greedy first estimate is not enough: on example 2's 256 terms it adds fifth-degree terms
    whose rough flow spoils the shift. The second pass uses all samples. Both passes are one
    compiled loop body (statistics, then the short run; the second pass's run goes unused).
    Pure and jittable (``dt`` static through the shapes; ``key`` for the short runs).
    Returns ``(stats, margin (q,))``, ``margin`` the :func:`correction_margin` of the
    corrected Gram matrices before their eigenvalues are floored.
    """
    regressed = jnp.asarray(nominal.regressed_index)
    vel = jnp.asarray(nominal.velocity_index)
    q = regressed.size

    R, N, _ = x.shape
    leading = max(1, FIRST_PASS_ROWS // N) * (N - 2) if R > 1 else FIRST_PASS_ROWS  # whole records

    def one_pass(carry, inputs):
        key, rows = inputs
        coef, smoothing, _, _ = carry

        def perturbation(z):
            return jnp.zeros(z.shape[-1], z.dtype).at[regressed].set(coef @ lib.eval_single(z, None, smoothing))

        st = kramers_moyal.drift_statistics(
            nominal, lib, x, dt, noise_var, perturbation, smoothing=smoothing, rows=rows
        )
        margin = correction_margin(st.gram)
        st = st._replace(gram=_nearest_pd(st.gram))
        trace = jax.vmap(lambda k, s: sampler.sample(k, s, **_FIRST_PASS))(jax.random.split(key, q), st)
        included = trace.gamma.sum(axis=(1, 2))  # (q, K)
        chosen = included > 0.5 * trace.gamma.shape[1] * trace.gamma.shape[2]
        coef = jnp.where(chosen, trace.theta.sum(axis=(1, 2)) / jnp.maximum(included, 1), 0.0)
        gamma = brownian_variance(nominal, dt, noise_var, trace.sigma2.mean(axis=(1, 2)))
        # Gamma 1.5 dt: the step k+1 -> k+2 seen from sample k; the noise's own smoothing is s^2.
        c = jnp.maximum(1.5 * dt * gamma - jnp.asarray(noise_var)[vel], 0.0)
        return (coef, jnp.zeros(nominal.m).at[vel].set(c), st, margin), None

    K = lib.K
    blank = sampler.SuffStats(jnp.zeros((q, K, K)), jnp.zeros((q, K)), jnp.zeros(q), jnp.zeros(q))
    carry = (jnp.zeros((q, K)), jnp.zeros(nominal.m), blank, jnp.zeros(q))
    passes = (jax.random.split(key, 2), jnp.asarray([leading, R * (N - 2)]))
    (_, _, st, margin), _ = jax.lax.scan(one_pass, carry, passes)
    return st, margin


# Example 1 (100 records): -0.003 at 14% noise (support always right), -0.012 at 18% (3 of 4),
# -0.05 at 23% (1 of 4, the others select 16-28 terms with PIP 1).
MARGIN_WARN = -0.01


def correction_margin(gram) -> jax.Array:
    """Smallest eigenvalue ``(q,)`` of the correlation matrices of noise-corrected Gram
    matrices ``(q, K, K)``: near zero (collinear terms) or slightly below from sampling error;
    well below zero where the noise correction removes more than the data hold, and the
    regression then amplifies noise in those directions without bound."""
    scale = jnp.sqrt(jnp.maximum(jnp.diagonal(gram, axis1=-2, axis2=-1), 1e-300))
    return jnp.linalg.eigvalsh(gram / (scale[..., :, None] * scale[..., None, :]))[..., 0]


def _margin_check(margin: float) -> dict:
    ok = margin >= MARGIN_WARN
    warning = (
        f"noise correction removed more than the data hold (smallest eigenvalue of the corrected "
        f"regressor correlation {margin:.3g} < {MARGIN_WARN}): noise too large for this library, PIPs "
        "and coefficients unreliable (use fewer terms, more records or less noisy sensors)"
    )
    return {"ok": bool(ok), "warnings": [] if ok else [warning], "min_eigenvalue": float(margin)}


def brownian_variance(nominal: LinearSecondOrder, dt, noise_var, residual_var) -> jax.Array:
    """The velocities' diffusion ``Gamma (d,)`` seen in the drift regression's residual
    variance ``residual_var (r,)`` (target units), less the measurement noise's share.

    A rough estimate (it holds the drift's misfit too) for smoothing the non-smooth library
    families: over a step the velocity moves by a Brownian increment of variance
    ``Gamma * time``, and ``E[sign(v)]`` over it is a smoothed sign (:meth:`Library.__call__`).
    """
    Phi, Psi = kramers_moyal.propagators(nominal, dt)
    noise = jnp.diag(jnp.asarray(noise_var))
    back = jnp.linalg.inv(Psi)
    noise_in_targets = jnp.diagonal(back @ (noise + Phi @ noise @ Phi.T) @ back.T)
    vel = jnp.asarray(nominal.velocity_index)
    return dt * jnp.maximum(jnp.asarray(residual_var)[: nominal.d] - noise_in_targets[vel], 0.0)


def _nearest_pd(gram):
    """Noise-corrected Gram matrices ``(q, K, K)`` can lose definiteness in directions the data
    barely sees; floor the eigenvalues of the correlation matrix at ``1e-9``."""
    scale = jnp.sqrt(jnp.maximum(jnp.diagonal(gram, axis1=-2, axis2=-1), 1e-300))
    corr = gram / (scale[..., :, None] * scale[..., None, :])
    w, v = jnp.linalg.eigh(corr)
    corr = jnp.einsum("...ij,...j,...kj->...ik", v, jnp.maximum(w, 1e-9), v)
    return corr * (scale[..., :, None] * scale[..., None, :])
