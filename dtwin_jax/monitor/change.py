"""Is a new window consistent with the twin as it stood before it? A posterior-predictive
score test on the window's sufficient statistics, with a false-alarm rate set in advance.

For one regressed equation, the twin's posterior gives the coefficients' mean `mu` and
covariance `Sigma` (model-averaged over the spike-and-slab draws) and the residual variance
`s2`. The window's statistics `G = L^T L`, `b = L^T y` give its score at the twin's mean,
`g = b - G mu`. If the window follows the twin, `g ~ N(0, V)` with
`V = s2 G + G Sigma G` (the window's noise, and the twin's own uncertainty seen through the
window's columns), so `T = g^T V^+ g` is chi-square with `rank(V)` degrees of freedom. A new
term, a lost one or a coefficient that moved adds `G delta` to `g`: `T` grows with the
window's information about the change. Columns are scaled to unit diagonal first, so the
rank does not depend on their units.

Real windows' rows are not independent (smoothed states; a model that misses part of the
physics the same way in every window), so `V` understates the score's spread by a factor
that each structure's own windows measure: `T / df` averages 1 over windows that follow the
twin when `V` is right. :func:`overdispersion` estimates it (at least 1) and the tests use
`V` times it.

A change that one term carries (a new term, a stiffness that moved) is seen with fewer
windows by the score of each term alone, `z_k = g_k / sqrt(V_kk)`, standard normal under
the same hypothesis: the largest `|z_k|` is tested with a Bonferroni factor `K`. The
equation's p-value is the smaller of the two tests' times 2.

Everything here is jittable and vmappable (a fleet tests every structure's window at once).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.sampler import SuffStats

__all__ = ["PRIOR_WINDOWS", "Belief", "ChangeTest", "belief", "overdispersion", "window_test", "window_statistics"]

# Eigenvalues of the scaled V below this fraction of the largest are its null space.
_RANK_TOL = 1e-9
# Pseudo-windows behind "the rows are independent" (overdispersion 1).
PRIOR_WINDOWS = 5.0


class Belief(NamedTuple):
    """What the twin believes about its `q` drift equations, over a library of `K` terms."""

    mean: jax.Array  # (q, K) posterior mean of the coefficients (zero where excluded), acceleration units
    cov: jax.Array  # (q, K, K) their posterior covariance
    sigma2: jax.Array  # (q,) posterior mean of the residual variance


class ChangeTest(NamedTuple):
    """The score tests of one window, per drift equation."""

    statistic: jax.Array  # (q,) T
    df: jax.Array  # (q,) rank of V: the chi-square's degrees of freedom
    p_all: jax.Array  # (q,) P(chi2_df > T)
    term: jax.Array  # (q,) int: the term with the largest |z_k|
    z: jax.Array  # (q,) that z_k
    p_term: jax.Array  # (q,) min(1, K P(|N(0, 1)| > |z|))
    p_value: jax.Array  # (q,) min(1, 2 min(p_all, p_term))


def belief(result) -> Belief:
    """The drift equations' :class:`Belief` from an :class:`~dtwin_jax.update.UpdateResult`'s
    posterior draws (every chain and draw pooled).

    **Arguments:**

    - `result`: an update (either framework).

    **Returns:** a :class:`Belief` with `q` = the number of drift equations.
    """
    means, covs, s2 = [], [], []
    for e in result.equations:
        if e.kind != "drift":
            continue
        theta = np.asarray(e.theta, dtype=float).reshape(-1, e.theta.shape[-1])
        means.append(theta.mean(axis=0))
        covs.append(np.atleast_2d(np.cov(theta, rowvar=False)) if theta.shape[0] > 1 else np.zeros((theta.shape[1],) * 2))
        s2.append(float(np.mean(e.sigma2)))
    return Belief(jnp.asarray(np.stack(means)), jnp.asarray(np.stack(covs)), jnp.asarray(s2))


def window_statistics(after, before, forget: float) -> SuffStats:
    """The drift statistics of the window alone, from a re-update: `after = window + forget
    * before` (:func:`dtwin_jax.update.lifecycle.with_previous`), so `window = after - forget
    * before` (exact to rounding)."""
    new, old = after.statistics["drift"], before.statistics["drift"]
    return SuffStats(*(np.asarray(a, dtype=float) - forget * np.asarray(b, dtype=float) for a, b in zip(new, old)))


def _one(mean, cov, sigma2, gram, xty, dispersion):
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(gram), jnp.finfo(gram.dtype).tiny))
    G = scale[:, None] * gram * scale[None, :]
    g = scale * (xty - gram @ mean)
    S = cov / (scale[:, None] * scale[None, :])
    V = dispersion * (sigma2 * G + G @ S @ G)
    w, U = jnp.linalg.eigh(0.5 * (V + V.T))
    keep = w > _RANK_TOL * jnp.max(w)
    z = jnp.where(keep, U.T @ g, 0.0) / jnp.sqrt(jnp.where(keep, w, 1.0))
    T = jnp.sum(z**2)
    df = jnp.sum(keep)
    p_all = jax.scipy.special.gammaincc(jnp.maximum(df, 1) / 2.0, T / 2.0)
    vd = jnp.diag(V)
    zk = jnp.where(vd > _RANK_TOL * jnp.max(vd), g / jnp.sqrt(jnp.where(vd > 0, vd, 1.0)), 0.0)
    k = jnp.argmax(jnp.abs(zk))
    p_term = jnp.minimum(1.0, g.size * jax.scipy.special.erfc(jnp.abs(zk[k]) / jnp.sqrt(2.0)))
    return T, df, p_all, k, zk[k], p_term, jnp.minimum(1.0, 2.0 * jnp.minimum(p_all, p_term))


def overdispersion(ratio_sum, count):
    """The factor on `V` that a structure's own windows call for: the mean of `T / df` over
    its windows that followed the twin, with :data:`PRIOR_WINDOWS` pseudo-windows at 1, and at
    least 1. Rows that are not independent (smoothed states, a model that misses part of
    the physics in the same way window after window) spread the score more than `V` says;
    `T / df` has mean 1 where they do not. `ratio_sum`, `count`: `(q,)` sums of `T / df`
    (unscaled) and their number."""
    return jnp.maximum(1.0, (PRIOR_WINDOWS + jnp.asarray(ratio_sum)) / (PRIOR_WINDOWS + jnp.asarray(count)))


@jax.jit
def window_test(prior: Belief, window: SuffStats, dispersion=1.0) -> ChangeTest:
    """The score test of a window's drift statistics against the twin before it.

    **Arguments:**

    - `prior`: the twin's :class:`Belief` before the window.
    - `window`: the window's own statistics, batched over the same `q` equations
      (`gram (q, K, K)`, `xty (q, K)`; `yty`, `n` unused).
    - `dispersion`: `()` or `(q,)`, the factor on `V` (:func:`overdispersion`); the returned
      `statistic` is `T` divided by it.

    **Returns:** a :class:`ChangeTest`; under "the window follows the twin" `p_all` is
    uniform on (0, 1), and `p_term` and `p_value` are at least as large as a uniform.
    """
    q = prior.sigma2.shape[0]
    dispersion = jnp.broadcast_to(jnp.asarray(dispersion, jnp.float64), (q,))
    return ChangeTest(*jax.vmap(_one)(prior.mean, prior.cov, prior.sigma2, jnp.asarray(window.gram),
                                      jnp.asarray(window.xty), dispersion))
