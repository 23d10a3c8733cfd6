"""The step both frameworks share once their statistics are built: the library resolved from
its spec, one spike-and-slab sampler call over the batched sufficient statistics of every
regressed equation (:mod:`dtwin_jax.sampler`), and the draws turned into one
:class:`EquationPosterior` per equation."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import aot, sampler
from dtwin_jax.library import DEFAULT_LIBRARY, Library, parse_library
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.progress import Bar
from dtwin_jax.systems import LinearSecondOrder
from dtwin_jax.update.result import SamplerSettings

__all__ = ["resolve_library", "posteriors", "numpy_stats"]


def resolve_library(library, nominal: LinearSecondOrder, num_inputs: int) -> Library:
    """``library``: a :class:`Library`, a spec (formats.md) or None (:data:`DEFAULT_LIBRARY`)."""
    if isinstance(library, Library):
        return library
    return parse_library(library or DEFAULT_LIBRARY, nominal.m, num_inputs)


def posteriors(trace, state_names, kind: str, names, pip_threshold: float) -> list[EquationPosterior]:
    """One posterior per equation of a batched ``trace`` (leading axis: the equations,
    in the order of ``state_names``); ``kind`` "drift" or "diffusion"."""
    trace = jax.tree.map(np.asarray, trace)
    return [
        EquationPosterior(state, kind, names, trace.gamma[j], trace.theta[j], trace.sigma2[j], pip_threshold)
        for j, state in enumerate(state_names)
    ]


def numpy_stats(stats: sampler.SuffStats) -> sampler.SuffStats:
    """Host copies, for the result's ``statistics`` (a re-update and the twin store)."""
    return sampler.SuffStats(*(np.asarray(a) for a in stats))


def _sample_equations(stats: sampler.SuffStats, settings: SamplerSettings, seed: int, progress: bool):
    """One sampler call over the batched statistics of every equation; ``progress``: a bar of
    the sweeps, advanced from inside the compiled program (the draws are the same)."""
    # Strongly typed float64: a weakly typed count (from a Python scalar) and a re-update's
    # summed one would otherwise be two jit signatures, and the sampler would compile twice.
    stats = sampler.SuffStats(*(jnp.asarray(a, dtype=jnp.float64) for a in stats))
    q = stats.xty.shape[0]
    keys = jax.random.split(jax.random.key(seed), q)
    method = sampler.default_batch_method()
    total = settings.num_burnin + settings.num_draws
    ticks = max(1, total // 100) if progress else 0
    if progress:  # host callbacks: not serializable, so traced in every process
        with Bar(True, q * settings.num_chains * (total // ticks) * ticks, "Gibbs sweeps"):
            return jax.block_until_ready(_sample_batch(keys, stats, settings, method, ticks))
    # A new process (the command line) reuses the traced program: see dtwin_jax.aot.
    return aot.call("sampler", lambda k, st: _sample_batch(k, st, settings, method), (keys, stats),
                    static=(settings, method), unflatten=lambda leaves: sampler.GibbsTrace(*leaves))


def _sampler_kwargs(settings: SamplerSettings) -> dict:
    """``settings`` as keyword arguments of :func:`sampler.sample`."""
    return dict(
        num_draws=settings.num_draws,
        num_burnin=settings.num_burnin,
        num_chains=settings.num_chains,
        prior=settings.prior,
        max_active=settings.max_active,
        p0=settings.p0,
        v_s=settings.v_s,
    )


@functools.partial(jax.jit, static_argnums=(2, 3, 4))
def _sample_batch(keys, stats, settings: SamplerSettings, method: str, ticks: int = 0):
    # One compiled program per settings and shapes: an eager lax.map over a fresh lambda
    # would compile again on every update.
    kwargs = _sampler_kwargs(settings)
    return sampler.batch_map(lambda k, s: sampler.sample(k, s, chain_method=method, ticks=ticks, **kwargs),
                             method, keys, stats)
