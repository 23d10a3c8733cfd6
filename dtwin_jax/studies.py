"""Noise-sensitivity studies (the paper's Fig. 10): noise levels x replicate data sets x
chains in one compiled program.

For `L` noise levels and `Rp` replicate data sets, `noise_sweep` simulates the
replicates (diffrax, vmapped), corrupts every replicate at every level (vmapped over levels),
denoises, builds targets and sufficient statistics, runs the spike-and-slab Gibbs kernel
(`dtwin_jax.sampler.sample`) for every (level, replicate, equation) and summarises the
draws: PIPs, posterior mean/std of every coefficient given inclusion, a 95% interval from
quantiles, exact-support recovery and relative errors of the true terms. No Python loop over
levels: one `jit` per shape and setting.

Random numbers are common across levels: replicate `r` has one simulation, one unit noise
draw (scaled by the level) and one set of chain keys at every level, so the curves against
the level are not blurred by independent noise per level (see `study_keys`).

Framework 2 (output-only): the drift (simulation of `records` Brownian-forced records per
replicate, Kramers-Moyal statistics, sampling, summaries) is one compiled program; the
diffusion (likelihood maximum by `dtwin_jax.output_only.statespace.diffusion_mle`, its EM targets'
statistics) another, mapped over the (level, replicate) pairs, and its sampling a third. The
diffusion is the slow part on CPU.
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.errors import DataError
from dtwin_jax.input_output import targets
from dtwin_jax.library import Library, parse_library
from dtwin_jax.models import systems
from dtwin_jax.output_only import kramers_moyal, statespace
from dtwin_jax.output_only.stats import (
    diffusion_statistics,
    output_only_drift_stats,
)
from dtwin_jax.output_only.update import DIFFUSION_LIBRARY
from dtwin_jax.preprocess import measurement
from dtwin_jax.preprocess.denoise import auto_half_width
from dtwin_jax.progress import Bar, tick
from dtwin_jax.update.result import SamplerSettings

__all__ = [
    "DEFAULT_LEVELS",
    "FRAMEWORKS",
    "CoefficientSummary",
    "SweepResult",
    "noise_sweep",
    "study_keys",
    "summarise",
]

# The paper's Fig. 10: 14 levels from 0 to 60% of each signal's std.
DEFAULT_LEVELS = np.linspace(0.0, 0.6, 14)
FRAMEWORKS = ("input-output", "output-only")


class CoefficientSummary(NamedTuple):
    """Summary of one equation's draws, every array `(..., K)` (`(...)` for the last
    two). Coefficient statistics are given inclusion, as in `posterior.EquationPosterior`;
    `lower`/`upper` are the 2.5% and 97.5% quantiles (NaN for a never-included term)."""

    pip: jax.Array
    mean: jax.Array
    std: jax.Array
    lower: jax.Array
    upper: jax.Array
    rel_error: jax.Array  # |mean - truth| / |truth| on the true support, NaN elsewhere
    support_exact: jax.Array  # (...) selected terms == true support
    num_selected: jax.Array  # (...) number of terms with PIP above the threshold


def summarise(trace: sampler.GibbsTrace, truth, support, pip_threshold: float = 0.5) -> CoefficientSummary:
    """Summaries of one equation's trace (jittable).

    Coefficient statistics are given inclusion; `lower`/`upper` are the 2.5% and 97.5%
    quantiles of the included draws.

    **Arguments:**

    - `trace`: the equation's `sampler.GibbsTrace`, leading axes `(chains, draws)`.
    - `truth`: the true coefficients `(K,)`.
    - `support`: the terms that should be found, `(K,)` bool.
    - `pip_threshold`: the PIP above which a term counts as selected (default 0.5).

    **Returns:** a `CoefficientSummary`: `pip`, `mean`, `std`, `lower`, `upper`, `rel_error`
    each `(K,)`, `support_exact` (the selected terms are exactly `support`) and
    `num_selected`, scalars.
    """
    K = trace.theta.shape[-1]
    gamma = trace.gamma.reshape(-1, K)
    theta = trace.theta.reshape(-1, K)
    w = gamma.astype(theta.dtype)
    count = jnp.sum(w, axis=0)
    pip = count / gamma.shape[0]
    mean = jnp.sum(theta * w, axis=0) / jnp.maximum(count, 1.0)
    std = jnp.sqrt(jnp.sum(w * (theta - mean) ** 2, axis=0) / jnp.maximum(count, 1.0))
    included = jnp.where(gamma, theta, jnp.nan)
    lower, upper = jnp.nanquantile(included, jnp.array([0.025, 0.975]), axis=0)
    rel_error = jnp.where(support, jnp.abs(mean - truth) / jnp.where(support, jnp.abs(truth), 1.0), jnp.nan)
    selected = pip > pip_threshold
    return CoefficientSummary(
        pip, mean, std, lower, upper, rel_error, jnp.all(selected == support), jnp.sum(selected)
    )


def study_keys(seed: int, replicates: int, num_equations: int):
    """The random keys of a study, the same at every noise level.

    **Arguments:**

    - `seed`: the study's seed.
    - `replicates`: the number of replicate data sets `Rp`.
    - `num_equations`: the number of regressed equations `q`.

    **Returns:** `(simulation, noise, chains)`: keys `(Rp,)` for the replicates' simulations,
    `(Rp,)` for their unit noise draws, and `(Rp, q)` for the chains of every equation.
    """
    k_sim, k_noise, k_chain = jax.random.split(jax.random.key(seed), 3)
    chains = jax.random.split(k_chain, replicates * num_equations).reshape(replicates, num_equations)
    return jax.random.split(k_sim, replicates), jax.random.split(k_noise, replicates), chains


def _sample_and_summarise(keys, stats, truth, support, settings, method, pip_threshold):
    """Sample and summarise a batch of problems: `keys (B,)`, `stats` with leading `B`,
    `truth`/`support (B, K)`. Only the `(K,)` summaries leave the loop body, so a
    problem's draws never coexist with another's (memory stays at one trace)."""
    def one(key, st, tr, sup):
        trace = sampler.sample(key, st, settings, chain_method=method)
        out = summarise(trace, tr, sup, pip_threshold)
        jax.debug.callback(lambda _: tick(1), out.num_selected)  # one step per problem
        return out

    return sampler.batch_map(one, method, keys, stats, truth, support)


def _flatten(tree, lead: int):
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[lead:]), tree)


def _problems(stats, chain_keys, truth, support, levels):
    """Stats `(L, Rp, q, ...)` -> flat problems with their keys (common over levels)."""
    L = levels.shape[0]
    keys = jnp.broadcast_to(chain_keys, (L,) + chain_keys.shape)
    q, K = truth.shape
    shape = keys.shape
    flat_truth = jnp.broadcast_to(truth, shape + (K,)).reshape(-1, K)
    flat_support = jnp.broadcast_to(support, shape + (K,)).reshape(-1, K)
    return keys.reshape(-1), _flatten(stats, 3), flat_truth, flat_support


# --- framework 1 ----------------------------------------------------------------------------


def _io_stats(example: systems.Example, lib: Library, levels, sim_keys, noise_keys, half_width: int):
    """Statistics `(L, Rp, q, ...)`: replicates simulated (vmapped), each corrupted at every
    level (vmapped), kinematic smoothing, targets, library, input-noise correction."""
    nominal = example.system.nominal
    sims = jax.vmap(lambda k: systems.simulate_example(example, k))(sim_keys)
    t = sims["t"][0]

    def one(level, x, xdot, u, key):
        meas = measurement.measure(key, t, x, xdot, u, level=level)
        return targets.input_output_stats(nominal, lib, example.dt, meas.x, meas.u, meas.xdot, half_width)

    def per_level(level):
        return jax.vmap(one, (None, 0, 0, 0, 0))(level, sims["x"], sims["xdot"], sims["u"], noise_keys)

    return jax.vmap(per_level)(levels)


@eqx.filter_jit
def _io_program(example, lib, levels, keys, truth, support, half_width, settings, method, pip_threshold):
    sim_keys, noise_keys, chain_keys = keys
    stats = _io_stats(example, lib, levels, sim_keys, noise_keys, half_width)
    problems = _problems(stats, chain_keys, truth, support, levels)
    out = _sample_and_summarise(*problems, settings, method, pip_threshold)
    L, (Rp, q) = levels.shape[0], chain_keys.shape
    return jax.tree.map(lambda a: a.reshape((L, Rp, q) + a.shape[1:]), out)


# --- framework 2 ----------------------------------------------------------------------------


def _ensembles(example, sim_keys, records: int):
    """Brownian-forced ensembles `(Rp, records, N, m)`, one per replicate."""
    return jax.vmap(lambda k: systems.simulate_example_sde(example, k, num_records=records)["x"])(sim_keys)


def _drift_stats(example, lib, level, x, key, settings):
    nominal = example.system.nominal
    y = measurement.add_noise(key, x, level)
    return output_only_drift_stats(nominal, lib, y, example.dt, kramers_moyal.noise_variance(y),
                                   jax.random.fold_in(key, 1), settings)[0]


@eqx.filter_jit
def _oo_drift_program(example, lib, levels, keys, truth, support, records, settings, method,
                      pip_threshold, batch_size):
    sim_keys, noise_keys, chain_keys = keys
    x = _ensembles(example, sim_keys, records)
    L, (Rp, q) = levels.shape[0], chain_keys.shape
    # Over (level, replicate) pairs: lax.map in batches, because one pair's Kramers-Moyal
    # statistics hold (records * N, K) arrays (~40 MB at 100 records) and a full vmap would
    # hold all L * Rp of them at once.
    lv = jnp.repeat(levels, Rp)
    rep = jnp.tile(jnp.arange(Rp), L)
    stats = jax.lax.map(
        lambda a: _drift_stats(example, lib, a[0], x[a[1]], noise_keys[a[1]], settings),
        (lv, rep), batch_size=batch_size,
    )
    stats = jax.tree.map(lambda a: a.reshape((L, Rp) + a.shape[1:]), stats)
    out = _sample_and_summarise(*_problems(stats, chain_keys, truth, support, levels), settings, method, pip_threshold)
    return jax.tree.map(lambda a: a.reshape((L, Rp, q) + a.shape[1:]), out), x


@eqx.filter_jit
def _sample_program(keys, stats, truth, support, settings, method, pip_threshold):
    L, Rp, q = stats.n.shape
    problems = _problems(stats, keys, truth, support, jnp.zeros(L))
    out = _sample_and_summarise(*problems, settings, method, pip_threshold)
    return jax.tree.map(lambda a: a.reshape((L, Rp, q) + a.shape[1:]), out)


# Output-only (level, replicate) pairs vmapped together on an accelerator by default. With all
# 56 pairs of the 14 x 4 sweep at 100 records vmapped, the same program on the CPU held 21.6 GB
# (~0.4 GB per pair); 16 pairs, ~6 GB, fit a small GPU.
ACCELERATOR_BATCH = 16

# The pre-averaging window of the diffusion's first guess: static inside a compiled study
# (the data-driven rule needs concrete values); Newton steps from any such start converge.
PILOT_WINDOW = 16


def _diffusion_stats_one(example, lib, dlib, coef, x, level, key):
    """The diffusion's EM-target statistics of one noisy ensemble, by the same function as
    `update_output_only` (`dtwin_jax.output_only.stats.diffusion_statistics`), given the
    drift `coef (q, K)` (zero for unselected terms). Pure: mapped over a study's pairs."""
    nominal = example.system.nominal
    y = measurement.add_noise(key, x, level)  # the same noise as in the drift program
    regressed = tuple(int(i) for i in nominal.regressed_index)
    step = statespace.DriftStep(nominal, lib, jnp.asarray(coef), regressed, example.dt)
    fit = diffusion_statistics(step, dlib, y, kramers_moyal.noise_variance(y), window=PILOT_WINDOW)
    jax.debug.callback(lambda _: tick(1), fit.gamma)  # one step per data set
    return fit.stats


@eqx.filter_jit
def _diffusion_program(example, lib, dlib, levels, coef, x, noise_keys, batch_size):
    """Diffusion statistics of every (level, replicate) pair, `coef (L, Rp, q, K)`, ensembles
    `x (Rp, records, N, m)`: one compiled program, lax.map over the pairs in batches."""
    L, Rp = coef.shape[:2]
    lv = jnp.repeat(levels, Rp)
    rep = jnp.tile(jnp.arange(Rp), L)
    stats = jax.lax.map(
        lambda a: _diffusion_stats_one(example, lib, dlib, coef[a[0] // Rp, a[1]], x[a[1]], a[2], noise_keys[a[1]]),
        (jnp.arange(L * Rp), rep, lv), batch_size=batch_size,
    )
    return jax.tree.map(lambda a: a.reshape((L, Rp) + a.shape[1:]), stats)


# --- results --------------------------------------------------------------------------------


@dataclass
class SweepResult:
    """A noise sweep: summaries `(L, Rp, q, K)` of every equation at every level and
    replicate (`summary`), and for framework 2 the diffusion's in `diffusion`.

    `names (K,)` library terms, `states (q,)` regressed states, `truth (q, K)` true
    coefficients and `support (q, K)` the terms that should be found."""

    example: str
    framework: str
    kind: str  # "drift" or "diffusion"
    levels: np.ndarray
    names: tuple[str, ...]
    states: tuple[str, ...]
    truth: np.ndarray
    support: np.ndarray
    summary: CoefficientSummary
    settings: SamplerSettings
    seconds: float
    records: int = 1
    diffusion: SweepResult | None = None
    timings: dict = field(default_factory=dict)

    @property
    def replicates(self) -> int:
        return int(self.summary.pip.shape[1])

    @property
    def support_recovery(self) -> np.ndarray:
        """`(L,)` fraction of replicates whose every equation has the exact support."""
        return np.mean(np.all(self.summary.support_exact, axis=2), axis=1)

    def true_terms(self) -> list[tuple[int, int]]:
        """`(equation, term)` indices of the true support."""
        return [tuple(int(i) for i in ij) for ij in np.argwhere(self.support)]

    def term_errors(self) -> dict[str, np.ndarray]:
        """`{"x2: x1**3": (L, Rp) relative errors}` for every true term."""
        return {f"{self.states[e]}: {self.names[k]}": np.asarray(self.summary.rel_error[:, :, e, k])
                for e, k in self.true_terms()}

    def table(self) -> list[dict]:
        """Per level: support recovery and the median (over replicates) error of every true
        term, in percent (diffusion terms prefixed `diffusion`)."""
        rows = []
        for i, level in enumerate(self.levels):
            row = {"level": float(level), "support_recovery_pct": 100 * float(self.support_recovery[i])}
            for name, err in self.term_errors().items():
                row[f"median_error_pct[{name}]"] = 100 * float(np.median(err[i]))
            if self.diffusion is not None:
                row["diffusion_support_recovery_pct"] = 100 * float(self.diffusion.support_recovery[i])
                for name, err in self.diffusion.term_errors().items():
                    row[f"median_error_pct[diffusion {name}]"] = 100 * float(np.median(err[i]))
            rows.append(row)
        return rows

    def to_rows(self) -> list[dict]:
        """One row per level, replicate and true term (then the diffusion's)."""
        s = jax.tree.map(np.asarray, self.summary)
        rows = []
        for i, level in enumerate(self.levels):
            for r in range(self.replicates):
                for e, k in self.true_terms():
                    rows.append({
                        "example": self.example, "framework": self.framework, "kind": self.kind,
                        "level": float(level), "replicate": r, "state": self.states[e],
                        "term": self.names[k], "truth": float(self.truth[e, k]),
                        "pip": float(s.pip[i, r, e, k]), "mean": float(s.mean[i, r, e, k]),
                        "std": float(s.std[i, r, e, k]), "lower": float(s.lower[i, r, e, k]),
                        "upper": float(s.upper[i, r, e, k]), "rel_error": float(s.rel_error[i, r, e, k]),
                        "support_exact": bool(s.support_exact[i, r, e]),
                        "num_selected": int(s.num_selected[i, r, e]),
                    })
        return rows + (self.diffusion.to_rows() if self.diffusion is not None else [])

    def to_json(self) -> dict:
        def clean(v):  # NaN is not JSON
            return None if isinstance(v, float) and not np.isfinite(v) else v

        return {
            "example": self.example,
            "framework": self.framework,
            "levels": [float(v) for v in self.levels],
            "replicates": self.replicates,
            "records": self.records,
            "chains": self.settings.num_chains,
            "draws": self.settings.num_draws,
            "burn_in": self.settings.num_burnin,
            "seconds": round(self.seconds, 3),
            "timings": {k: round(v, 3) for k, v in self.timings.items()},
            "table": self.table(),
            "rows": [{k: clean(v) for k, v in row.items()} for row in self.to_rows()],
        }

    def to_csv(self, path) -> None:
        """Write `to_rows` as a CSV file (atomically): one row per level, replicate and true term.

        **Arguments:**

        - `path`: the CSV file to write.
        """
        from dtwin_jax.io import atomic_path

        rows = self.to_rows()
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


# --- the sweep ------------------------------------------------------------------------------


def _check(levels, replicates: int, records: int, framework: str) -> np.ndarray:
    levels = np.atleast_1d(np.asarray(levels, dtype=np.float64))
    if levels.ndim != 1 or levels.size == 0:
        raise DataError("noise levels must be a non-empty list of numbers")
    if not np.all(np.isfinite(levels)) or levels.min() < 0 or levels.max() > 1:
        bad = levels[~(np.isfinite(levels) & (levels >= 0) & (levels <= 1))][0]
        raise DataError(f"noise levels must be in [0, 1], got {bad:g}")
    if int(replicates) != replicates or replicates < 1:
        raise DataError(f"replicates must be a positive integer, got {replicates}")
    if int(records) != records or records < 1:
        raise DataError(f"records must be a positive integer, got {records}")
    if framework not in FRAMEWORKS:
        raise DataError(f"framework must be one of {', '.join(FRAMEWORKS)}, got {framework!r}")
    return levels


def _truth(example: systems.Example, names, states) -> tuple[np.ndarray, np.ndarray]:
    """True coefficients `(q, K)` and the identifiable support `(q, K)`."""
    truth = example.true_coefficients(names)
    ident = example.identifiable()
    support = np.array([[n in ident.get(s, {}) for n in names] for s in states])
    return truth, support


def noise_sweep(
    example: systems.Example | str,
    levels=DEFAULT_LEVELS,
    *,
    replicates: int = 4,
    framework: str = "input-output",
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    records: int = 100,
    pip_threshold: float = 0.5,
    diffusion: bool = True,
    progress: bool = True,
    batch_size: int | None = None,
) -> SweepResult:
    """Discover the perturbation of `example` at every noise level for independent data sets.

    `progress` shows one bar step per sampled (level, replicate, equation) problem, advanced
    from inside the compiled program by a host callback; compilation, simulation and the
    statistics come before its first step, and the output-only diffusion loop has its own bar.

    **Arguments:**

    - `example`: a `systems.Example`, or the name of one in `systems.EXAMPLES` (`"example1"`,
      say).
    - `levels`: the noise levels `(L,)`, fractions of each signal's std in [0, 1] (default
      `DEFAULT_LEVELS`, 14 levels from 0 to 0.6).
    - `replicates`: the number of independent data sets `Rp` per level (default 4).
    - `framework`: `"input-output"` (default; one measured record of states, inputs and rates
      per data set, as the paper) or `"output-only"` (an ensemble of `records` Brownian-forced
      records of the states per data set).
    - `settings`: the sampler's `SamplerSettings` (chains, draws, burn-in; default `SamplerSettings()`).
    - `seed`: the seed of `study_keys` (default 0).
    - `records`: Brownian-forced records per data set, output-only only (default 100).
    - `pip_threshold`: the PIP above which a term counts as selected (default 0.5).
    - `diffusion`: output-only only: discover the diffusion too (default True; see the module
      docstring).
    - `progress`: show progress bars on standard error (default True).
    - `batch_size`: (level, replicate) pairs whose output-only statistics are vmapped
      together; None (default): one at a time on CPU (bounded memory) and up to
      `ACCELERATOR_BATCH` (16) at once on an accelerator. A large GPU takes more (an H200 holds
      all 56 pairs of the 14 x 4 sweep with 100 records, drift and diffusion, at once).

    **Returns:** a `SweepResult` with summaries `(L, replicates, q, K)` (and, output-only with
    `diffusion`, the diffusion's in its `diffusion`).
    """
    ex = systems.EXAMPLES[example]() if isinstance(example, str) else example
    levels = _check(levels, replicates, records, framework)
    if batch_size is None:
        batch_size = 1 if jax.default_backend() == "cpu" else min(levels.size * replicates, ACCELERATOR_BATCH)
    if not isinstance(batch_size, int) or batch_size < 1:
        raise DataError(f"batch_size must be a positive integer, got {batch_size!r}")
    if framework == "output-only":
        ex = ex.for_output_only()
    nominal = ex.system.nominal
    N = int(round(ex.duration / ex.dt)) + (framework == "output-only")  # samples per record
    hw = auto_half_width(nominal, ex.dt, N)
    spec = ex.library if framework == "input-output" else ex.library_output_only
    lib = parse_library(spec, nominal.m, nominal.n if framework == "input-output" else 0)
    states = tuple(nominal.state_names[i] for i in nominal.regressed_index)
    truth, support = _truth(ex, lib.names, states)
    keys = study_keys(seed, replicates, len(states))
    method = sampler.default_batch_method()
    L = levels.size
    start = time.perf_counter()
    with Bar(progress, L * replicates * len(states), "sampled problems"):
        if framework == "input-output":
            out = _io_program(ex, lib, jnp.asarray(levels), keys, jnp.asarray(truth), jnp.asarray(support),
                              hw, settings, method, pip_threshold)
        else:
            out, x = _oo_drift_program(ex, lib, jnp.asarray(levels), keys, jnp.asarray(truth),
                                       jnp.asarray(support), records, settings,
                                       method, pip_threshold, batch_size)
        out = jax.tree.map(np.asarray, out)
    seconds = time.perf_counter() - start
    result = SweepResult(ex.name, framework, "drift", levels, lib.names, states, truth, support, out,
                         settings, seconds, records if framework == "output-only" else 1,
                         timings={"drift_seconds": seconds})
    if framework == "output-only" and diffusion:
        result.diffusion = _diffusion_sweep(ex, lib, levels, keys, x, out, settings, method, pip_threshold,
                                            progress, records, batch_size)
        result.timings["diffusion_seconds"] = result.diffusion.seconds
        result.seconds = time.perf_counter() - start
    return result


def _diffusion_sweep(ex, lib, levels, keys, x, drift, settings, method, pip_threshold, progress, records,
                     batch_size):
    """Framework 2's diffusion at every level and replicate: the likelihood maxima and EM
    statistics of all pairs in one compiled program, then one compiled sampler call."""
    start = time.perf_counter()
    nominal = ex.system.nominal
    dlib = parse_library(DIFFUSION_LIBRARY, nominal.m, 0)
    _, noise_keys, _ = keys
    L, Rp = levels.size, x.shape[0]
    coef = np.where(drift.pip > pip_threshold, drift.mean, 0.0)  # (L, Rp, q, K)
    with Bar(progress, L * Rp, "diffusion likelihoods"):
        stats = _diffusion_program(ex, lib, dlib, jnp.asarray(levels), jnp.asarray(coef), x, noise_keys, batch_size)
        stats = jax.tree.map(jnp.asarray, jax.block_until_ready(stats))
    states = tuple(nominal.state_names[i] for i in nominal.velocity_index)
    true_gamma = ex.true_diffusion()
    truth = np.array([[true_gamma[s] if n == "1" else 0.0 for n in dlib.names] for s in states])
    support = truth != 0
    d = len(states)
    chain_keys = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, 1), d))(keys[2][:, 0])
    with Bar(progress, L * Rp * d, "sampled diffusion problems"):
        out = _sample_program(chain_keys, stats, jnp.asarray(truth), jnp.asarray(support), settings, method,
                              pip_threshold)
        out = jax.tree.map(np.asarray, out)
    return SweepResult(ex.name, "output-only", "diffusion", levels, dlib.names, states, truth, support, out,
                       settings, time.perf_counter() - start, records)

