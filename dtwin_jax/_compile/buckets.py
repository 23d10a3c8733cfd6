"""Libraries padded to a few sizes, so that one compiled sampler serves every library of a
size class instead of one program per K (compiling one takes seconds; running it, often
less). The padding columns are zero: the kernel treats a zero column as no term
(`dtwin_jax.sampler.kernel`), so the posterior of the real columns is unchanged; the
random stream, and so the draws, depend on the padded size."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["BUCKETS", "SLOT_CLASSES", "TABLE_BUCKETS", "active_slots", "bucket", "pad_stats", "unpad_trace"]

# Above the largest bucket a library keeps its size: padding it would cost more sweeps'
# time than its one compilation.
BUCKETS = (16, 32, 64, 128, 256)
# The sampler's active-set slots R (its cost grows with R, and the prior is truncated there)
# by default: the class of the real K, not the padded one's min(K, 32). A library of 17-24
# terms padded to 32 gets 24 (the zoo's 19-term library: 0.170 -> 0.120 s for the monitor's
# 2 x 1250 sweeps, one pinned core); a model cannot outgrow its real K, so the draws are
# the same.
SLOT_CLASSES = (16, 24, 32)
# A simulated twin's term table (dtwin_jax.library.term_table): most twins use a handful of
# terms, each row evaluated at every solver stage, so the classes start smaller.
TABLE_BUCKETS = (4, 8) + BUCKETS


def bucket(K: int, sizes: tuple[int, ...] = BUCKETS) -> int:
    """The padded size of a `K`-term library: the first of `sizes` that holds it, else `K`.

    **Arguments:**

    - `K`: the library's number of terms.
    - `sizes`: the size classes, increasing (default `BUCKETS`).

    **Returns:** the padded size, an int.
    """
    return next((b for b in sizes if K <= b), K)


def active_slots(K: int) -> int:
    """The default number of active-set slots for a library (before padding): the first of
    `SLOT_CLASSES` that holds it, at most 32.

    **Arguments:**

    - `K`: the library's real number of terms.

    **Returns:** the number of slots, an int.
    """
    return min(bucket(K, SLOT_CLASSES), SLOT_CLASSES[-1])


def pad_stats(stats, size: int, xp=jnp):
    """Sufficient statistics with zero columns appended up to `size`.

    **Arguments:**

    - `stats`: a `SuffStats` of `K` columns (`gram (..., K, K)`, `xty (..., K)`).
    - `size`: the padded number of columns, at least `K`.
    - `xp`: the array module, `jax.numpy` (default) or `numpy` on the host.

    **Returns:** the `SuffStats` with `size - K` zero columns (`stats` itself when `size == K`).
    """
    extra = size - stats.gram.shape[-1]
    if extra == 0:
        return stats
    gram = xp.pad(stats.gram, [(0, 0)] * (stats.gram.ndim - 2) + [(0, extra), (0, extra)])
    xty = xp.pad(stats.xty, [(0, 0)] * (stats.xty.ndim - 1) + [(0, extra)])
    return type(stats)(gram, xty, stats.yty, stats.n)


def unpad_trace(trace, K: int):
    """A trace cut back to the library's columns.

    **Arguments:**

    - `trace`: a `GibbsTrace` of a padded library (`gamma`, `theta` with the padded size last).
    - `K`: the library's real number of terms.

    **Returns:** the trace with `gamma` and `theta` cut to their first `K` columns.
    """
    return trace._replace(gamma=trace.gamma[..., :K], theta=trace.theta[..., :K])

