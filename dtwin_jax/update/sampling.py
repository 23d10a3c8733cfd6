"""The step both frameworks share once their statistics are built: the library resolved from
its spec, the spike-and-slab sampler run on the sufficient statistics of every regressed
equation (`dtwin_jax.sampler.sample_in_chunks`), and the draws turned into one
`EquationPosterior` per equation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax import sampler
from dtwin_jax.library import DEFAULT_LIBRARY, Library, parse_library
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.posterior import EquationPosterior
from dtwin_jax.progress import Bar
from dtwin_jax.update.result import SamplerSettings

__all__ = ["resolve_library", "posteriors", "numpy_stats", "sample_equations"]


def resolve_library(library, nominal: LinearSecondOrder, num_inputs: int) -> Library:
    """The `Library` of a `library` argument.

    **Arguments:**

    - `library`: a `Library` (returned as is), a spec (formats.md) or None (`DEFAULT_LIBRARY`).
    - `nominal`: the nominal `LinearSecondOrder`, whose `m` states the library's terms use.
    - `num_inputs`: the number of inputs `n` the library's input terms use.

    **Returns:** the `Library`.
    """
    if isinstance(library, Library):
        return library
    return parse_library(library or DEFAULT_LIBRARY, nominal.m, num_inputs)


def posteriors(trace, state_names, kind: str, names, pip_threshold: float) -> list[EquationPosterior]:
    """One posterior per equation of a batched `trace`.

    **Arguments:**

    - `trace`: a `GibbsTrace` batched over the equations, `theta`/`gamma` `(q, chains, draws, K)`,
      `sigma2` `(q, chains, draws)`, physical units.
    - `state_names`: the `q` equations' states, in the order of `trace`'s leading axis.
    - `kind`: `"drift"` or `"diffusion"`.
    - `names`: the library's `K` term names.
    - `pip_threshold`: inclusion probability above which a term is selected.

    **Returns:** a list of `q` `EquationPosterior`s (host arrays).
    """
    trace = jax.tree.map(np.asarray, trace)
    return [
        EquationPosterior(state, kind, names, trace.gamma[j], trace.theta[j], trace.sigma2[j], pip_threshold)
        for j, state in enumerate(state_names)
    ]


def numpy_stats(stats: sampler.SuffStats) -> sampler.SuffStats:
    """Host copies, for the result's `statistics` (a re-update and the twin store).

    **Arguments:**

    - `stats`: `SuffStats` of any shapes (jax or numpy arrays).

    **Returns:** `SuffStats` of numpy arrays, same shapes.
    """
    return sampler.SuffStats(*(np.asarray(a) for a in stats))


def sample_equations(stats: sampler.SuffStats, settings: SamplerSettings, seed: int, progress: bool,
                      key: jax.Array | None = None) -> sampler.GibbsTrace:
    """Draws for the batched statistics of every equation, each by `sampler.sample_in_chunks`
    with its own key.

    Its programs depend on the library's size class and the chains only, so updates of other
    lengths and libraries, and the output-only first pass, reuse them.

    **Arguments:**

    - `stats`: `SuffStats` batched over `q` equations (leading axis), physical units.
    - `settings`: the `SamplerSettings`.
    - `seed`: the seed the equations' keys are split from (unused when `key` is given).
    - `progress`: a bar of every equation's sweeps.
    - `key`: a PRNG key to split instead of `seed`'s, or None (default).

    **Returns:** a `GibbsTrace` of host arrays, leading axes `(q, chains, draws)`: `gamma` and
    `theta` `(q, chains, draws, K)`, the others `(q, chains, draws)`.
    """
    # Strongly typed float64: a weakly typed count (from a Python scalar) and a re-update's
    # summed one would otherwise be two jit signatures, and the sampler would compile twice.
    stats = sampler.SuffStats(*(np.asarray(a, dtype=np.float64) for a in stats))  # sliced on the host
    q = stats.xty.shape[0]
    keys = jax.random.split(jax.random.key(seed) if key is None else key, q)
    total = settings.num_burnin + settings.num_draws
    sweeps = q * settings.num_chains * -(-total // sampler.CHUNK) * sampler.CHUNK
    with Bar(progress, sweeps, "Gibbs sweeps"):
        traces = [
            sampler.sample_in_chunks(keys[j], jax.tree.map(lambda a: a[j], stats), settings, progress=progress)
            for j in range(q)
        ]
    return sampler.GibbsTrace(*(np.stack(parts) for parts in zip(*traces)))
