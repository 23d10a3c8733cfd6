"""Running chains: the sampler's settings, `sample` (jittable, vmappable) and
`sample_in_chunks` (the same draws, run from Python in calls of `CHUNK` sweeps).

Both standardise the statistics, start the chains (`dtwin_jax.sampler.starts`), run
the kernel's sweeps (`dtwin_jax.sampler.kernel`) and return the draws in physical
units. Libraries are run padded with zero columns to 16, 32, 64, 128 or 256 terms, so that
one compiled program serves every library of a size class; the padding is no term (the
kernel's zero columns) and is cut from the draws.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax._compile import aot
from dtwin_jax._compile.buckets import active_slots, bucket, pad_stats, unpad_trace
from dtwin_jax._compile.quick_compile import quick_jit
from dtwin_jax.progress import Bar, tick
from dtwin_jax.sampler.kernel import (
    GibbsState,
    GibbsTrace,
    SpikeSlabPrior,
    SuffStats,
    run_keys,
    standardize,
)
from dtwin_jax.sampler.starts import starting_states

__all__ = [
    "SamplerSettings",
    "sample",
    "sample_jit",
    "sample_in_chunks",
    "CHUNK",
    "default_batch_method",
    "batch_map",
]


@dataclasses.dataclass(frozen=True)
class SamplerSettings:
    """Chains, draws, prior and starts of the Gibbs sampler (the paper runs 3000 sweeps).

    **Arguments:**

    - `num_chains`: the number of chains (default 4).
    - `num_draws`: the draws kept per chain (default 2000).
    - `num_burnin`: the sweeps dropped before them (default 1000).
    - `prior`: the `dtwin_jax.sampler.kernel.SpikeSlabPrior` hyperparameters.
    - `p0`: the prior inclusion probability the chains start at (default 0.1).
    - `v_s`: the slab variance (relative to `sigma2`) the chains start at (default 10).
    - `max_active`: the largest model; None (default): the first of 16, 24 or 32 that holds
      the library's real K, else 32 (`dtwin_jax._compile.buckets.active_slots`). The prior is
      truncated there.
    - `swap`: each sweep ends with an exchange move between correlated terms (default True).
    - `chain_method`: `"vectorized"` (vmap over chains) or `"sequential"` (`lax.map`);
      None picks vectorized on accelerators and sequential on CPU, where XLA runs the vmapped
      indicator loop slower per chain (`benchmarks/sampler_speed.py`).
    - `init_strategy`: the chains' starts, `"dispersed"` (default), `"random"` or `"greedy"`
      (`dtwin_jax.sampler.starts.initial_indicators`).
    """

    num_chains: int = 4
    num_draws: int = 2000
    num_burnin: int = 1000
    prior: SpikeSlabPrior = SpikeSlabPrior()
    p0: float = 0.1
    v_s: float = 10.0
    max_active: int | None = None
    swap: bool = True
    chain_method: str | None = None
    init_strategy: str = "dispersed"


def _settings(settings: SamplerSettings | None, overrides: dict) -> SamplerSettings:
    return dataclasses.replace(settings or SamplerSettings(), **overrides)


def sample(key: jax.Array, stats: SuffStats, settings: SamplerSettings | None = None, *, progress: bool = False,
           **overrides) -> GibbsTrace:
    """Standardise, run the chains and return the draws in physical units.

    Jittable and vmappable over `key` and `stats` (with `progress` False).

    **Arguments:**

    - `key`: PRNG key.
    - `stats`: `dtwin_jax.sampler.kernel.SuffStats` of one regression (K terms), physical units.
    - `settings`: `SamplerSettings`, or None (default) for its defaults.
    - `progress`: a bar of the sweeps (runs `sample_in_chunks`, whose draws are the same;
      not under `jit`).
    - `**overrides`: fields of `settings` to replace, e.g. `sample(key, stats, num_draws=500)`.

    **Returns:** a `dtwin_jax.sampler.kernel.GibbsTrace`, leading axes `(num_chains, num_draws)`:
    `gamma (C, D, K)` bool, `theta (C, D, K)` in the units of `y` per unit of each library
    column, `sigma2 (C, D)` in units of `y**2`, `v_s`, `p0` and `log_marginal` `(C, D)`.
    """
    s = _settings(settings, overrides)
    if progress:
        return jax.tree.map(jnp.asarray, sample_in_chunks(key, stats, s, progress=True))
    K = stats.gram.shape[-1]
    s = _with_slots(s, K)
    scaled, col, ys = standardize(pad_stats(stats, bucket(K)))
    total = s.num_burnin + s.num_draws
    states = starting_states(key, scaled, s.prior, s.p0, s.v_s, s.max_active, s.num_chains, s.init_strategy)
    keys = jax.vmap(lambda k: jax.random.split(k, total))(jax.random.split(key, s.num_chains))
    _, trace = _run_chains(keys, states, scaled, s.prior, s.max_active, s.chain_method or default_batch_method(),
                           s.swap)
    trace = unpad_trace(jax.tree.map(lambda a: a[:, s.num_burnin:], trace), K)
    return trace._replace(theta=trace.theta * (ys / col[:K]), sigma2=trace.sigma2 * ys**2)


sample_jit = jax.jit(sample, static_argnames=("settings", "progress", *(f.name for f in dataclasses.fields(SamplerSettings))))
sample_jit.__doc__ = "`jax.jit` of `sample` (`progress` must be False)."

# Sweeps per call of :func:`sample_in_chunks`' compiled program: ~11 ms of work at K = 36,
# against ~0.1 ms to dispatch a call.
CHUNK = 250


def sample_in_chunks(key: jax.Array, stats: SuffStats, settings: SamplerSettings | None = None, *,
                     progress: bool = False, **overrides) -> GibbsTrace:
    """`sample` run from Python in calls of `CHUNK` sweeps, with the same draws.

    Its compiled programs depend on the library's size class, the chains and the prior, not
    on `num_draws`, `num_burnin` or K within a class, so updates of other lengths and
    other libraries reuse them (compiling one takes far longer than running a chunk). The
    last chunk is padded; its extra sweeps are dropped. Not jittable (use `sample` inside
    `jit`).

    **Arguments:**

    - `key`: PRNG key, as in `sample`.
    - `stats`: `dtwin_jax.sampler.kernel.SuffStats` of one regression (K terms), physical units.
    - `settings`: `SamplerSettings`, or None (default) for its defaults.
    - `progress`: a bar of the sweeps, advanced after each chunk (an enclosing bar, if one
      is open, counts them instead).
    - `**overrides`: fields of `settings` to replace, as in `sample`.

    **Returns:** a `dtwin_jax.sampler.kernel.GibbsTrace` of host (numpy) arrays, leading axes
    `(num_chains, num_draws)`, in physical units as `sample`'s.
    """
    s = _settings(settings, overrides)
    K = stats.gram.shape[-1]
    s = _with_slots(s, K)
    padded = pad_stats(SuffStats(*(np.asarray(a, np.float64) for a in stats)), bucket(K), np)
    scaled, col, ys, keys, states = _chunk_setup(key, jax.device_put(padded), s)
    total = s.num_burnin + s.num_draws
    parts = []
    with Bar(progress, s.num_chains * keys.shape[1], "Gibbs sweeps"):
        for i in range(keys.shape[1] // CHUNK):
            states, trace = _chunk(keys[:, i * CHUNK : (i + 1) * CHUNK], states, scaled, s)
            parts.append(trace)
            if progress:
                jax.block_until_ready(trace)
                tick(s.num_chains * CHUNK)
    trace = GibbsTrace(*(np.concatenate([np.asarray(p[i]) for p in parts], axis=1)[:, s.num_burnin:total]
                         for i in range(len(GibbsTrace._fields))))
    trace = unpad_trace(trace, K)
    return trace._replace(theta=trace.theta * (np.asarray(ys) / np.asarray(col)[:K]),
                          sigma2=trace.sigma2 * float(ys) ** 2)


def _with_slots(s: SamplerSettings, K: int) -> SamplerSettings:
    """`s` with the default `max_active` resolved on the real `K` (`active_slots`),
    before the library is padded."""
    return s if s.max_active is not None else dataclasses.replace(s, max_active=active_slots(K))


def _chunk_setup(key, stats: SuffStats, s: SamplerSettings):
    """Scaled statistics, scales, per-sweep keys `(C, chunks * CHUNK)` and starting states."""
    setup = (s.prior, float(s.p0), float(s.v_s), s.max_active, s.num_chains, s.init_strategy)
    scaled, col, ys, chain_keys, states = _setup_program(key, stats, *setup)
    total = s.num_burnin + s.num_draws
    return scaled, col, ys, _step_keys(chain_keys, total, -(-total // CHUNK) * CHUNK), states


def _chunk_static(s: SamplerSettings) -> tuple:
    return s.prior, s.max_active, s.chain_method or default_batch_method(), s.swap


def _chunk(keys, states, scaled, s: SamplerSettings):
    return _chunk_program(keys, states, scaled, *_chunk_static(s))


@aot.exported("sampler_setup", static_argnums=(2, 3, 4, 5, 6, 7))
@quick_jit(static_argnums=(2, 3, 4, 5, 6, 7))
def _setup_program(key, stats, prior, p0, v_s, max_active, num_chains, init_strategy):
    """`sample`'s set-up but for the per-sweep keys: scaled statistics, scales, one
    key per chain and the starting states."""
    scaled, col, ys = standardize(stats)
    states = starting_states(key, scaled, prior, p0, v_s, max_active, num_chains, init_strategy)
    return scaled, col, ys, jax.random.split(key, num_chains), states


@quick_jit(static_argnums=(1, 2))
def _step_keys(chain_keys, total: int, padded: int):
    """`(C, padded)` per-sweep keys: `sample`'s `total` keys per chain, then the
    last one repeated (sweeps that are run and dropped)."""
    keys = jax.vmap(lambda k: jax.random.split(k, total))(chain_keys)
    return jnp.concatenate([keys, jnp.repeat(keys[:, -1:], padded - total, axis=1)], axis=1)


def default_batch_method() -> str:
    """`"vectorized"` on GPU/TPU, `"sequential"` on CPU."""
    return "sequential" if jax.default_backend() == "cpu" else "vectorized"


def batch_map(fn, method: str, *args):
    """`fn` over the leading axis of `args`: `jax.vmap` or `lax.map` by `method`.

    **Arguments:**

    - `fn`: the function of one element, called as `fn(*slices)`; returns a pytree of arrays.
    - `method`: `"vectorized"` (`jax.vmap`) or `"sequential"` (`lax.map`); any other raises
      `ValueError`.
    - `*args`: pytrees of arrays with a common leading axis, mapped over together.

    **Returns:** `fn`'s outputs stacked along a new leading axis.
    """
    if method == "vectorized":
        return jax.vmap(fn)(*args)
    if method == "sequential":
        return jax.lax.map(lambda a: fn(*a), args)
    raise ValueError(f"unknown batch method {method!r} (vectorized or sequential)")


def _run_chains(keys, states, stats, prior, max_active, method, swap=True) -> tuple[GibbsState, GibbsTrace]:
    return batch_map(lambda k, s: run_keys(k, s, stats, prior, max_active, swap), method, keys, states)


_run_chains_jit = jax.jit(_run_chains, static_argnums=(3, 4, 5, 6))
_chunk_program = aot.exported("sampler_chunk", static_argnums=(3, 4, 5, 6))(_run_chains_jit)
