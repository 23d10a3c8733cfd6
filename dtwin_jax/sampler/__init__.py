"""Spike-and-slab Gibbs sampler for sparse Bayesian linear regression, from sufficient
statistics: the kernel (:mod:`~dtwin_jax.sampler.kernel`, blackjax-style ``init`` / ``step``),
the chains' starts (:mod:`~dtwin_jax.sampler.starts`) and the drivers that run them
(:mod:`~dtwin_jax.sampler.driver`)."""

from dtwin_jax.sampler.driver import (
    CHUNK,
    SamplerSettings,
    batch_map,
    default_batch_method,
    sample,
    sample_in_chunks,
    sample_jit,
)
from dtwin_jax.sampler.kernel import (
    GibbsInfo,
    GibbsState,
    GibbsTrace,
    SpikeSlabPrior,
    SuffStats,
    init,
    run_chain,
    standardize,
    step,
    suff_stats,
)
from dtwin_jax.sampler.starts import initial_indicators

__all__ = [
    "SpikeSlabPrior",
    "SuffStats",
    "GibbsState",
    "GibbsInfo",
    "GibbsTrace",
    "SamplerSettings",
    "suff_stats",
    "standardize",
    "init",
    "step",
    "run_chain",
    "initial_indicators",
    "sample",
    "sample_jit",
    "sample_in_chunks",
    "CHUNK",
    "default_batch_method",
    "batch_map",
]
