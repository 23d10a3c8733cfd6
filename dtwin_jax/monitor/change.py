"""Is a new window consistent with the twin as it stood before it? A two-sample (Chow) score
test on sufficient statistics, with a false-alarm rate set in advance.

For one regressed equation, the twin's statistics `G0 = L0^T L0`, `b0 = L0^T y0` (its data,
older windows discounted) and the window's `G1`, `b1` give the window's score at the
coefficients that fit both, `g = b1 - G1 beta`, `beta = (G0 + G1)^+ (b0 + b1)`, over the whole
library. If the window follows the same linear model as the twin's data, `g ~ N(0, V)` with
`V = s2 (G1 - G1 (G0 + G1)^+ G1)`, and `T = g^T V^+ g / rank(V)` is Fisher's F with
`(rank(V), n0 + n1 - rank(G0) - rank(G1))` degrees of freedom, `s2` the two separate fits'
pooled residual variance. A new term, a lost one or a coefficient that moved adds
`G1 (G0 + G1)^+ G0 delta` to `g`: `T` grows with the window's information about the change.
Columns are scaled to the window's unit diagonal first, so ranks do not depend on units.

The test compares the window with the twin's *data*, not with its spike-and-slab posterior:
a posterior leaves out a small term that its data support only weakly, and its mean is shrunk
there; windows pooled over a minute then show that term against the posterior, though it was in
the twin's data all along, and a test against the posterior raises false alarms.

Where the states were estimated (accelerometers alone), each window's states carry their own
error, correlated over the whole window: it moves the window's score by an amount the rows'
noise does not account for. The update measures it, as the covariance `Omega` of the score
over draws of that error, and the test adds it to `V`.

Real windows' rows are not independent (smoothed states; a model that misses part of the
physics the same way in every window), so `V` can understate the score's spread by a factor
that each structure's own windows measure: `T` averages 1 over windows that follow the twin
when `V` is right. `overdispersion` estimates it (at least 1) and the tests use `V`
times it.

A change that one term carries (a new term) is seen with fewer windows by the score of each
term alone, `t_k = g_k / sqrt(V_kk)` (Student's t under the same hypothesis): the largest
`|t_k|` is tested with a Bonferroni factor `K`. A change of the nominal model's own physics (a
stiffness or a damping that moved) spreads over its linear terms, the displacements and the
velocities: the score on those columns alone, `g_L^T V_LL^+ g_L / rank(V_LL)`, is F with few
numerator degrees of freedom, so it sees such a change sooner than either test over the whole
library. The equation's p-value is the smallest of the tests' times their number (2, or 3 with
the linear terms).

Everything here is jittable and vmappable (a fleet tests every structure's window at once).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dtwin_jax.sampler import SuffStats

__all__ = ["PRIOR_WINDOWS", "ChangeTest", "linear_columns", "overdispersion", "window_test", "window_statistics"]

# Eigenvalues of a scaled Gram matrix (or of V) below this fraction of the largest are its null space.
_RANK_TOL = 1e-9
# Pseudo-windows behind "the rows are independent" (overdispersion 1).
PRIOR_WINDOWS = 5.0


class ChangeTest(NamedTuple):
    """The score tests of one window, per drift equation."""

    statistic: jax.Array  # (q,) T = g^T V^+ g / rank(V)
    df: jax.Array  # (q,) rank of V: the F's numerator degrees of freedom
    p_all: jax.Array  # (q,) P(F > T)
    term: jax.Array  # (q,) int: the term with the largest |t_k|
    z: jax.Array  # (q,) that t_k
    p_term: jax.Array  # (q,) min(1, K P(|t| > |t_k|))
    p_linear: jax.Array  # (q,) P(F > T_L) of the linear terms' score (1 where none is marked)
    p_value: jax.Array  # (q,) min(1, 3 min(p_all, p_term, p_linear)); min(1, 2 min(p_all, p_term)) with no linear column


def window_statistics(after, before, forget: float) -> SuffStats:
    """The drift statistics of the window alone, from a re-update.

    The re-update holds `after = window + forget * before`
    (`dtwin_jax.update.lifecycle.with_previous`), so `window = after - forget * before` (exact to
    rounding).

    **Arguments:**

    - `after`: the `UpdateResult` of the re-update with the window (the twin before it as `previous`).
    - `before`: the twin's `UpdateResult` before the window.
    - `forget`: the weight, in [0, 1], that the re-update gave the older data.

    **Returns:** the window's own drift statistics, a `SuffStats` of float64 NumPy arrays batched over
    the `q` drift equations: `gram (q, K, K)`, `xty (q, K)`, `yty (q,)`, `n (q,)`.
    """
    new, old = after.statistics["drift"], before.statistics["drift"]
    return SuffStats(*(np.asarray(a, dtype=float) - forget * np.asarray(b, dtype=float) for a, b in zip(new, old)))


def _eigen(A):
    """`(w, U, keep)`: the eigendecomposition of a symmetric positive semi-definite `A` and
    the eigenvalues outside its null space."""
    w, U = jnp.linalg.eigh(0.5 * (A + A.T))
    return w, U, w > _RANK_TOL * jnp.maximum(jnp.max(w), jnp.finfo(A.dtype).tiny)


def _pinv(A):
    """`(A^+, rank A)` of a symmetric positive semi-definite `A`."""
    w, U, keep = _eigen(A)
    return (U * jnp.where(keep, 1.0 / jnp.where(keep, w, 1.0), 0.0)) @ U.T, jnp.sum(keep)


def _f_test(V, g, dof):
    """`(T, rank V, P(F(rank V, dof) > T))` of `T = g^T V^+ g / rank V`."""
    w, U, keep = _eigen(V)
    z = jnp.where(keep, U.T @ g, 0.0) / jnp.sqrt(jnp.where(keep, w, 1.0))
    df = jnp.sum(keep)
    T = jnp.sum(z**2) / jnp.maximum(df, 1)
    # P(F(df, dof) > T) by the regularized incomplete beta function.
    p = jnp.where(df > 0, jax.scipy.special.betainc(dof / 2.0, jnp.maximum(df, 1) / 2.0, dof / (dof + df * T)), 1.0)
    return T, df, p


def _one(gram0, xty0, yty0, n0, gram1, xty1, yty1, n1, spread, dispersion, linear):
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(gram1), jnp.finfo(gram1.dtype).tiny))
    G0, G1 = (scale[:, None] * G * scale[None, :] for G in (gram0, gram1))
    b0, b1 = scale * xty0, scale * xty1
    P0, r0 = _pinv(G0)
    P1, r1 = _pinv(G1)
    Pp, _ = _pinv(G0 + G1)
    rss = jnp.maximum(yty0 - b0 @ P0 @ b0, 0.0) + jnp.maximum(yty1 - b1 @ P1 @ b1, 0.0)
    dof = jnp.maximum(n0 + n1 - r0 - r1, 1.0)
    g = b1 - G1 @ (Pp @ (b0 + b1))
    # The window's own states' error moves its score by Omega; through the joint fit `beta`
    # a share B = G1 (G0 + G1)^+ of it returns, and the twin's windows' (their sum taken as
    # n0 / n1 times this window's) enter through B alone.
    B = G1 @ Pp
    A = jnp.eye(g.size) - B
    O = scale[:, None] * spread * scale[None, :]
    V = dispersion * (rss / dof * (G1 - B @ G1) + A @ O @ A.T + n0 / jnp.maximum(n1, 1.0) * B @ O @ B.T)
    T, df, p_all = _f_test(V, g, dof)
    _, df_linear, p_linear = _f_test(V * linear[:, None] * linear[None, :], g * linear, dof)
    vd = jnp.diag(V)
    tk = jnp.where(vd > _RANK_TOL * jnp.max(vd), g / jnp.sqrt(jnp.where(vd > 0, vd, 1.0)), 0.0)
    k = jnp.argmax(jnp.abs(tk))
    p_one = jax.scipy.special.betainc(dof / 2.0, 0.5, dof / (dof + tk[k] ** 2))
    p_term = jnp.minimum(1.0, g.size * p_one)
    tests = jnp.where(df_linear > 0, 3.0, 2.0)
    p = jnp.minimum(1.0, tests * jnp.minimum(jnp.minimum(p_all, p_term), p_linear))
    return T, df, p_all, k, tk[k], p_term, p_linear, p


def overdispersion(ratio_sum, count):
    """The factor on `V` that a structure's own windows call for.

    The mean of `T` (unscaled) over its windows that followed the twin, with `PRIOR_WINDOWS`
    pseudo-windows at 1, and at least 1. Rows that are not independent (smoothed states, a model
    that misses part of the physics in the same way window after window) spread the score more
    than `V` says; `T` has mean about 1 where they do not.

    **Arguments:**

    - `ratio_sum`: `(q,)` sums of the unscaled `T` over those windows, per drift equation.
    - `count`: `(q,)` their number.

    **Returns:** the factor `(q,)` (a JAX array), at least 1.
    """
    return jnp.maximum(1.0, (PRIOR_WINDOWS + jnp.asarray(ratio_sum)) / (PRIOR_WINDOWS + jnp.asarray(count)))


@jax.jit
def window_test(twin: SuffStats, window: SuffStats, dispersion=1.0, spread=0.0, linear=False) -> ChangeTest:
    """The two-sample score test of a window's drift statistics against the twin's.

    **Arguments:**

    - `twin`: the twin's drift statistics before the window (`gram (q, K, K)`, `xty (q, K)`,
      `yty (q,)`, `n (q,)`; older windows discounted as the twin discounts them).
    - `window`: the window's own statistics, batched over the same `q` equations.
    - `dispersion`: `()` or `(q,)`, the factor on `V` (`overdispersion`); the returned
      `statistic` is `T` divided by it.
    - `spread`: `(q, K, K)` (or 0): the covariance `Omega` of the window's score `b1 - G1 c`
      over draws of its states' estimation error, when its states were estimated
      (`dtwin_jax.output_only.accelerometers.score_spread`); added to `V`.
    - `linear`: `(q, K)` or `(K,)` bool (or False): the columns of the nominal model's linear
      terms, every displacement and velocity (`linear_columns`), tested together as well.

    **Returns:** a `ChangeTest` of `(q,)` arrays; under "the window follows the twin's linear model"
    `p_all` is uniform on (0, 1), and `p_term` and `p_value` are at least as large as a
    uniform. A twin with no data (all zeros) gives `df = 0` and p-values of 1.
    """
    q, K = jnp.shape(twin.xty)
    dispersion = jnp.broadcast_to(jnp.asarray(dispersion, jnp.float64), (q,))
    spread = jnp.broadcast_to(jnp.asarray(spread, jnp.float64), (q, K, K))
    linear = jnp.broadcast_to(jnp.asarray(linear, jnp.float64), (q, K))
    args = [jnp.asarray(a, jnp.float64) for a in (*twin, *window)]
    return ChangeTest(*jax.vmap(_one)(*args, spread, dispersion, linear))


def linear_columns(names, nominal) -> np.ndarray:
    """Which of the library's terms are the nominal model's linear terms.

    The linear terms are `x1 .. x2d`, every displacement and velocity (the nominal's first `2 d`
    state names).

    **Arguments:**

    - `names`: the library's term names, `K` of them.
    - `nominal`: the nominal model (a `LinearSecondOrder`: its `state_names` and `d`).

    **Returns:** `(K,)` bool, True for the linear terms.
    """
    linear = set(nominal.state_names[:2 * nominal.d])
    return np.array([name in linear for name in names], dtype=bool)
