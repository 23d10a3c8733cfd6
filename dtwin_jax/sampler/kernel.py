"""Spike-and-slab Gibbs sampler for sparse Bayesian linear regression.

The model (the paper's Section 3, Fig. 1), for a target `y (N,)` and library `L (N, K)`:

    y | theta, sigma2        ~ N(L theta, sigma2 I)
    theta_k | gamma_k = 0    = 0                              (Dirac spike)
    theta_g | gamma, v_s     ~ N(0, sigma2 v_s I)             (slab, active set g)
    gamma_k | p0             ~ Bernoulli(p0)
    p0 ~ Beta(a_p, b_p),  sigma2 ~ IG(a_sigma, b_sigma),  v_s ~ IG(a_v, b_v)

One step is a partially collapsed Gibbs sweep:

1. each indicator `gamma_k` in random order from `p(gamma_k | gamma_-k, v_s, p0, y)`, with
   `theta` and `sigma2` integrated out (the paper's Appendix A);
2. `sigma2 ~ p(sigma2 | gamma, v_s, y)` (`theta` integrated out), then
   `theta ~ p(theta | gamma, sigma2, v_s, y)`;
3. `v_s ~ p(v_s | theta, sigma2, gamma)` and `p0 ~ p(p0 | gamma)`.

Everything works from the sufficient statistics `L^T L`, `L^T y`, `y^T y` and `N`:
nothing of size N x N is formed and a sweep's cost does not depend on N. The indicator
updates keep `P = A^-1` of the active block `A = L_g^T L_g + I / v_s` in `R = max_active`
slots (zeros off the active set), refactorised once per sweep (`v_s` has changed). An
indicator's conditional depends on the others only through `P`, so the sweep computes the
log-odds of all K indicators at once (`O(K R^2)`) and jumps to the next one in its order whose
uniform flips it; a flip is a rank-one Schur-complement update (`O(K R)`). A sweep costs
`O(K R^2 + flips K R)` instead of K sequential `O(R^2)` steps, with the same draws. A sweep that
flips nothing draws `sigma2` and `theta` from the factorisation it started with.

A column that is zero on every row (`gram[k, k] == 0`) is no term: its indicator stays 0 and
it does not count in `p0`'s update. The driver (`dtwin_jax.sampler.driver`) pads
libraries with such columns to a few sizes, so that one compiled program serves them all.

The kernel follows blackjax: `init(stats) -> GibbsState` and
`step(key, state, stats) -> (GibbsState, GibbsInfo)` are pure functions of NamedTuples,
jittable, vmappable over chains and over independent problems.

The chains' starting indicators are in `dtwin_jax.sampler.starts`; the drivers that run
them, in `dtwin_jax.sampler.driver`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular

__all__ = [
    "SpikeSlabPrior",
    "SuffStats",
    "GibbsState",
    "GibbsInfo",
    "GibbsTrace",
    "suff_stats",
    "weigh",
    "standardize",
    "log_marginal",
    "slots",
    "present_terms",
    "init",
    "step",
    "run_chain",
    "run_keys",
]


class SpikeSlabPrior(NamedTuple):
    """Hyperparameters (the paper's defaults; its authors' code uses `a_sigma = b_sigma = 1e-4`)."""

    a_p: float = 0.1
    b_p: float = 1.0
    a_v: float = 0.5
    b_v: float = 0.5
    a_sigma: float = 1e-4
    b_sigma: float = 1e-4


class SuffStats(NamedTuple):
    """Sufficient statistics of one regression `y = L theta + eps`."""

    gram: jax.Array  # (K, K)  L^T L
    xty: jax.Array  # (K,)    L^T y
    yty: jax.Array  # ()      y^T y
    n: jax.Array  # ()      number of rows N


class GibbsState(NamedTuple):
    gamma: jax.Array  # (K,) bool: slab membership
    theta: jax.Array  # (K,) coefficients, zero off the active set
    sigma2: jax.Array  # () residual variance
    v_s: jax.Array  # () slab variance (relative to sigma2)
    p0: jax.Array  # () prior inclusion probability


class GibbsInfo(NamedTuple):
    num_active: jax.Array  # () number of active terms after the sweep
    log_marginal: jax.Array  # () log p(y | gamma, v_s) after the sweep (up to a constant)


class GibbsTrace(NamedTuple):
    """Draws of one or more chains: leading axes `(..., num_draws)`."""

    gamma: jax.Array  # (..., D, K)
    theta: jax.Array  # (..., D, K)
    sigma2: jax.Array  # (..., D)
    v_s: jax.Array  # (..., D)
    p0: jax.Array  # (..., D)
    log_marginal: jax.Array  # (..., D)


def suff_stats(L: jax.Array, y: jax.Array) -> SuffStats:
    """Sufficient statistics of one regression.

    **Arguments:**

    - `L`: the library's columns, shape `(N, K)`.
    - `y`: the target, shape `(N,)`.

    **Returns:** `SuffStats` `(L^T L (K, K), L^T y (K,), y^T y (), N ())`, float64.
    """
    L = jnp.asarray(L, dtype=jnp.float64)
    y = jnp.asarray(y, dtype=jnp.float64)
    return SuffStats(L.T @ L, L.T @ y, y @ y, jnp.asarray(L.shape[0], dtype=jnp.float64))


def weigh(stats: SuffStats, factor) -> SuffStats:
    """Batched equations' statistics, each counted `factor` times: its rows' effective
    share (`n_eff / n`) keeps the estimates and widens the posterior to match.

    NumPy in, NumPy out (host-side steps); jax arrays too.

    **Arguments:**

    - `stats`: `SuffStats` batched over `q` equations (leading axis).
    - `factor`: the equations' factors, shape `(q,)`.

    **Returns:** `SuffStats`, every field times its equation's factor.
    """
    return SuffStats(*(a * factor[(slice(None),) + (None,) * (a.ndim - 1)] for a in stats))


def standardize(stats: SuffStats) -> tuple[SuffStats, jax.Array, jax.Array]:
    """Scale every column and the target to unit root-mean-square, so that the slab prior and
    the inverse-gamma prior on `sigma2` mean the same thing whatever the units of the data.

    **Arguments:**

    - `stats`: `SuffStats` (K terms; a zero column keeps scale 1).

    **Returns:** `(scaled_stats, column_scale, target_scale)`: the scaled `SuffStats`, the
    columns' RMS `(K,)` and the target's RMS `()`. A coefficient `beta` of the scaled problem
    is `theta = beta * target_scale / column_scale` in physical units and a scaled variance
    `s2` is `s2 * target_scale**2`.
    """
    col = jnp.sqrt(jnp.diagonal(stats.gram) / stats.n)
    col = jnp.where(col > 0, col, 1.0)
    ys = jnp.sqrt(stats.yty / stats.n)
    ys = jnp.where(ys > 0, ys, 1.0)
    scaled = SuffStats(
        stats.gram / jnp.outer(col, col), stats.xty / (col * ys), stats.yty / ys**2, stats.n
    )
    return scaled, col, ys


# --- the collapsed marginal likelihood -------------------------------------------------


def log_marginal(num_active, logdet, quad, v_s, stats: SuffStats, prior: SpikeSlabPrior):
    """`log p(y | gamma, v_s)` up to a constant, with `theta` and `sigma2` integrated out.

    **Arguments:**

    - `num_active`: the number of active terms `r`, `()`.
    - `logdet`: the log-determinant of the active block `A = L_g^T L_g + I / v_s`, `()`.
    - `quad`: the quadratic form `b_g^T A^-1 b_g` (`b = L^T y`), `()`.
    - `v_s`: the slab variance (relative to `sigma2`), `()`.
    - `stats`: the `SuffStats` (standardised).
    - `prior`: the `SpikeSlabPrior`.

    **Returns:** the log marginal likelihood, `()`, up to an additive constant.
    """
    resid = jnp.maximum(stats.yty - quad, 1e-300)
    shape = prior.a_sigma + 0.5 * stats.n
    return (
        -0.5 * num_active * jnp.log(v_s)
        - 0.5 * logdet
        - shape * jnp.log(prior.b_sigma + 0.5 * resid)
    )


def _factor(gram, xty, gamma, v_s):
    """Cholesky factor of the active block, padded with the identity off the active set."""
    m = gamma.astype(gram.dtype)
    mm = jnp.outer(m, m)
    A = (gram + jnp.eye(gram.shape[0]) / v_s) * mm + jnp.diag(1.0 - m)
    chol = jnp.linalg.cholesky(A)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
    mean = cho_solve((chol, True), xty * m) * m
    quad = jnp.dot(xty * m, mean)
    return chol, logdet, mean, quad, mm



def slots(K: int, max_active: int | None) -> int:
    """The number of active-set slots `R` (static): `max_active`, default 32, at most K.

    **Arguments:**

    - `K`: the number of library columns.
    - `max_active`: the largest model, or None for 32.

    **Returns:** `R`, a Python int.
    """
    return min(K, 32) if max_active is None else min(K, int(max_active))


def present_terms(stats: SuffStats) -> jax.Array:
    """The columns that are terms (not zero on every row).

    **Arguments:**

    - `stats`: `SuffStats` with `gram (K, K)`.

    **Returns:** `(K,)` bool, True for a term.
    """
    return jnp.diagonal(stats.gram) > 0


# --- initialisation --------------------------------------------------------------------


def init(
    stats: SuffStats,
    prior: SpikeSlabPrior = SpikeSlabPrior(),
    *,
    p0: float = 0.1,
    v_s: float = 10.0,
    gamma: jax.Array | None = None,
    max_active: int | None = None,
) -> GibbsState:
    """The blackjax-style initial state.

    **Arguments:**

    - `stats`: `SuffStats` (standardised: `standardize`).
    - `prior`: the `SpikeSlabPrior`.
    - `p0`: the starting inclusion probability (the paper's 0.1).
    - `v_s`: the starting slab variance, relative to `sigma2` (the paper's 10).
    - `gamma`: `(K,)` bool starting indicators; None: the greedy forward selection
      (`dtwin_jax.sampler.starts.greedy_indicators`).
    - `max_active`: the largest model for the greedy selection (default `min(K, 32)`); used
      only when `gamma` is None.

    **Returns:** `GibbsState` with `theta (K,)` the posterior mean given `gamma` and
    `sigma2` the residual variance.
    """
    p0 = jnp.asarray(p0, stats.gram.dtype)
    v_s = jnp.asarray(v_s, stats.gram.dtype)
    if gamma is None:  # starts builds on this module: imported here
        from dtwin_jax.sampler.starts import greedy_indicators

        R = slots(stats.gram.shape[0], max_active)
        gamma = greedy_indicators(stats, prior, p0, v_s, R)
    gamma = jnp.asarray(gamma, dtype=bool)
    _, _, mean, quad, _ = _factor(stats.gram, stats.xty, gamma, v_s)
    sigma2 = jnp.maximum(stats.yty - quad, 1e-300) / stats.n
    return GibbsState(gamma, mean, sigma2, v_s, p0)


# --- one sweep ---------------------------------------------------------------------------


def _active_slots(gamma, R):
    """The first `R` active indices in slots `(R,)` (`K` marks an empty slot), and the
    slot of every term `(K,)` (`R` when inactive)."""
    K = gamma.shape[0]
    slot_idx = jnp.nonzero(gamma, size=R, fill_value=K)[0].astype(jnp.int32)
    slot_of = jnp.full(K + 1, R, jnp.int32).at[slot_idx].set(jnp.arange(R, dtype=jnp.int32))
    return slot_idx, slot_of[:K]


def _factor_slots(stats: SuffStats, slot_idx, v_s):
    """Cholesky factor of the active block held in slots, identity on empty slots."""
    K = stats.gram.shape[0]
    R = slot_idx.shape[0]
    m = (slot_idx < K).astype(stats.gram.dtype)
    idx = jnp.minimum(slot_idx, K - 1)
    mm = jnp.outer(m, m)
    A = (stats.gram[idx][:, idx] + jnp.eye(R) / v_s) * mm + jnp.diag(1.0 - m)
    chol = jnp.linalg.cholesky(A)
    bs = stats.xty[idx] * m
    mean = cho_solve((chol, True), bs) * m
    return chol, 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol))), mean, jnp.dot(bs, mean), mm, bs


def _indicator_sweep(key, gamma, p0, v_s, stats: SuffStats, prior: SpikeSlabPrior, R: int):
    """Update every indicator once, in random order (the sweep of the module docstring)."""
    return _sweep(key, gamma, p0, v_s, stats, prior, R)[0]


def _sweep(key, gamma, p0, v_s, stats: SuffStats, prior: SpikeSlabPrior, R: int):
    """`_indicator_sweep`, also returning whether any indicator flipped and the active
    block's factorisation at the start, `(slot_idx, chol, logdet, mean, quad)`.

    The inverse `P (R, R)` of the active block lives in `R = max_active` slots. An
    indicator's conditional depends on the others only through `P`, which changes only when
    an indicator flips: so the log-odds of all K indicators are computed at once from
    `U = P G_act (R, K)`, the sweep jumps to the next indicator (in the random order) whose
    uniform flips it, flips it by rank-one updates of `P` and `U` (`O(R K)`) and
    recomputes. The same uniforms give the indicators of a one-at-a-time sweep, at a cost of
    (flips + 1) vectorised steps instead of K scalar ones.
    """
    K = stats.gram.shape[0]
    G, b = stats.gram, stats.xty
    dtype = G.dtype
    eye = jnp.eye(R, dtype=dtype)
    slot_idx, slot_of = _active_slots(gamma, R)
    chol, logdet, mean, quad, mm, _ = _factor_slots(stats, slot_idx, v_s)
    initial = (slot_idx, chol, logdet, mean, quad)
    P = cho_solve((chol, True), eye) * mm
    occupied = slot_idx < K
    G_act = G[jnp.minimum(slot_idx, K - 1)] * occupied[:, None]  # (R, K): slot j's row of G
    U = P @ G_act  # column k: P g_k, g_k the active part of G[:, k]
    logit_p0 = jnp.log(p0) - jnp.log1p(-p0)
    key_order, key_u = jax.random.split(key)
    order = jax.random.permutation(key_order, K)
    uniforms = jax.random.uniform(key_u, (K,), dtype=dtype)
    position = jnp.zeros(K, jnp.int32).at[order].set(jnp.arange(K, dtype=jnp.int32))
    u_k = uniforms[position]  # the uniform of each term's turn
    diag_G = jnp.diagonal(G)
    present = diag_G > 0

    def next_flip(P, U, G_act, slot_idx, slot_of, gamma, logdet, quad, r, start):
        """The first term at position >= start whose uniform flips it, and what the flip needs."""
        bs = b[jnp.minimum(slot_idx, K - 1)] * (slot_idx < K)
        s = jnp.maximum(diag_G + 1.0 / v_s - jnp.sum(G_act * U, axis=0), 1.0 / v_s)
        t = b - bs @ U
        j = jnp.minimum(slot_of, R - 1)
        pjj = jnp.where(gamma, jnp.diagonal(P)[j], 1.0)
        pb = (P @ bs)[j]
        r_out = r - gamma.astype(dtype)
        logdet_in = jnp.where(gamma, logdet, logdet + jnp.log(s))
        quad_in = jnp.where(gamma, quad, quad + t**2 / s)
        logdet_out = jnp.where(gamma, logdet + jnp.log(pjj), logdet)
        quad_out = jnp.where(gamma, quad - pb**2 / pjj, quad)
        log_odds = (
            logit_p0
            + log_marginal(r_out + 1, logdet_in, quad_in, v_s, stats, prior)
            - log_marginal(r_out, logdet_out, quad_out, v_s, stats, prior)
        )
        # The model size is capped at R (a truncated prior): a full model cannot grow.
        new = (u_k < jax.nn.sigmoid(log_odds)) & ~(~gamma & (r_out >= R)) & present
        k = jnp.argmin(jnp.where((new != gamma) & (position >= start), position, K)).astype(jnp.int32)
        found = (new[k] != gamma[k]) & (position[k] >= start)
        return found, k, (s[k], j[k], logdet_in[k], quad_in[k], logdet_out[k], quad_out[k])

    def flip(k, info, state):
        s, j, logdet_in, quad_in, logdet_out, quad_out = info
        P, U, G_act, slot_idx, slot_of, gamma, logdet, quad, r = state
        add = ~gamma[k]
        free = jnp.argmin(slot_idx < K).astype(jnp.int32)
        slot = jnp.where(add, free, j)
        # Adding k at an empty slot: P += vec vec^T / s with vec = P g_k - e_slot, and
        # U += vec w^T / s with w = G_act^T P g_k - G[k]. Removing k from slot j:
        # P -= p p^T / P_jj with p = P[:, j], and U -= p U[j] / P_jj.
        u = U[:, k]
        vec = jnp.where(add, u - eye[slot], P[:, slot])
        coef = jnp.where(add, 1.0 / s, -1.0 / P[slot, slot])
        w = jnp.where(add, u @ G_act - G[k], U[slot])
        slot_idx = slot_idx.at[slot].set(jnp.where(add, k, K))
        slot_of = slot_of.at[k].set(jnp.where(add, slot, R))
        m = (slot_idx < K).astype(dtype)
        P = (P + coef * jnp.outer(vec, vec)) * jnp.outer(m, m)
        U = (U + coef * jnp.outer(vec, w)) * m[:, None]
        G_act = G_act.at[slot].set(jnp.where(add, G[k], 0.0))
        gamma = gamma.at[k].set(add)
        logdet = jnp.where(add, logdet_in, logdet_out)
        quad = jnp.where(add, quad_in, quad_out)
        r = r + jnp.where(add, 1.0, -1.0)
        return P, U, G_act, slot_idx, slot_of, gamma, logdet, quad, r

    def body(carry):
        # Flip the indicator found last (none on the first pass), then look for the next:
        # one copy of each in the program (a search before the loop compiled a second).
        _, found, changed, k, info, state, start = carry
        state = jax.lax.cond(found, lambda: flip(k, info, state), lambda: state)
        start = jnp.where(found, position[k] + 1, start)
        found_next, k, info = next_flip(*state, start)
        return found_next, found_next, changed | found, k, info, state, start

    zero = jnp.zeros((), dtype)
    state = (P, U, G_act, slot_idx, slot_of, gamma, logdet, quad, jnp.sum(gamma).astype(dtype))
    info = (zero, jnp.zeros((), jnp.int32), zero, zero, zero, zero)
    carry = (True, False, False, jnp.zeros((), jnp.int32), info, state, jnp.zeros((), jnp.int32))
    # An indicator flips at most once per sweep, in the order of ``position``.
    _, _, changed, _, _, state, _ = jax.lax.while_loop(lambda c: c[0], body, carry)
    return state[5], changed, initial


def _pick(u, weights):
    """The index drawn with probability proportional to `weights (K,)` (non-negative) by
    the inverse CDF at the uniform `u`; `K - 1` when every weight is zero."""
    cdf = jnp.cumsum(weights)
    return jnp.minimum(jnp.sum(cdf <= u * cdf[-1]), weights.shape[0] - 1).astype(jnp.int32)


def _swap(key, gamma, current, v_s, stats: SuffStats, prior: SpikeSlabPrior):
    """One Metropolis-Hastings exchange move on the indicators at fixed `v_s`.

    Single-indicator Gibbs updates cross between two models that explain the data with
    different, nearly collinear terms (`x2*Abs(x2)` against `x2 + x2**3`) only through
    an intermediate model holding both or neither, which the marginal likelihood can make
    very improbable: the chain then stays in whichever it found first. The exchange goes
    straight across: an active term `j` (uniform) is proposed to be replaced by an
    inactive `k` drawn with probability proportional to `cos^2(L_j, L_k)` (the squared
    uncentred cosine of their columns, from the Gram), and the move is accepted on the
    collapsed `p(y | gamma, v_s)` (the model size, hence the prior of `gamma`, is
    unchanged). The proposal's reverse draws `k` among the active terms of the new model
    and `j` among its inactive ones with the same weights, so the Hastings ratio is
    `sum_{i inactive} w_ji / sum_{i inactive after} w_ki`. It leaves
    `p(gamma | y, v_s, p0)` invariant (`tests/test_ambiguity.py` checks it against
    enumeration).

    **Arguments:**

    - `key`: PRNG key.
    - `gamma`: `(K,)` bool, the indicators after the sweep.
    - `current`: the factorisation of `gamma`'s active block in `R` slots,
      `(slot_idx (R,), chol (R, R), logdet (), mean (R,), quad ())` as
      `_factor_slots` gives it.
    - `v_s`, `stats`, `prior`: as in `step`.

    **Returns:**

    `(gamma (K,), factorisation)`: the proposal's when accepted, else the inputs.
    """
    slot_idx, chol, logdet, mean, quad = current
    K = gamma.shape[0]
    R = slot_idx.shape[0]
    G, b = stats.gram, stats.xty
    dtype = G.dtype
    # One random call for the move's three variates, the two picks by inverse CDF: three
    # calls (a split, two categoricals, a uniform) cost twice as much (6 against 11 us a
    # sweep at K = 36, one pinned core), a fifth of the whole sweep.
    u_j, u_k, u_accept = jax.random.uniform(key, (3,), dtype=dtype)
    norm2 = jnp.maximum(jnp.diagonal(G), jnp.finfo(dtype).tiny)

    def weights(i):  # squared cosines of column i with every column, floored so every exchange has a reverse
        return G[i] ** 2 / (norm2[i] * norm2) + 1e-12

    r = jnp.sum(gamma)
    present = present_terms(stats)
    possible = (r >= 1) & (r < jnp.sum(present))
    j = _pick(u_j, gamma.astype(dtype))
    out = ~gamma & present
    w_j = weights(j)
    k = _pick(u_k, jnp.where(out, w_j, 0.0))
    w_k = weights(k)
    forward = jnp.sum(jnp.where(out, w_j, 0.0))
    backward = jnp.sum(jnp.where(out, w_k, 0.0)) - w_k[k] + w_k[j]
    # The exchanged model's log-determinant and quadratic form from the current factor:
    # remove j (P = A^-1: logdet + log P_jj, quad - mean_j^2 / P_jj), then add k with
    # P_-j = P - p p^T / P_jj (p = P e_j): O(R^2), no new factorisation unless accepted.
    occupied = slot_idx < K
    slot = jnp.argmax(slot_idx == j)
    g_k = G[k, jnp.minimum(slot_idx, K - 1)] * occupied
    solved = cho_solve((chol, True), jnp.stack([g_k, jnp.eye(R, dtype=dtype)[slot]], axis=1))
    u, p = solved[:, 0] * occupied, solved[:, 1] * occupied
    p_jj = p[slot]
    gp = g_k @ p
    s = G[k, k] + 1.0 / v_s - (g_k @ u - gp**2 / p_jj)
    t = b[k] - (g_k @ mean - gp * mean[slot] / p_jj)
    logdet_n = logdet + jnp.log(p_jj) + jnp.log(s)
    quad_n = quad - mean[slot] ** 2 / p_jj + t**2 / s
    rf = r.astype(dtype)
    log_ratio = (
        log_marginal(rf, logdet_n, quad_n, v_s, stats, prior)
        - log_marginal(rf, logdet, quad, v_s, stats, prior)
        + jnp.log(forward)
        - jnp.log(backward)
    )
    # A degenerate exchange (s <= 0 by rounding: NaN) compares False and is rejected.
    accept = possible & (s > 0) & (jnp.log(u_accept) < log_ratio)
    new_idx = jnp.where(slot_idx == j, k, slot_idx).astype(slot_idx.dtype)

    def exchanged(_):
        return (new_idx,) + _factor_slots(stats, new_idx, v_s)[:4]

    gamma = jnp.where(accept, gamma.at[j].set(False).at[k].set(True), gamma)
    return gamma, jax.lax.cond(accept, exchanged, lambda _: current, None)


def step(
    key: jax.Array,
    state: GibbsState,
    stats: SuffStats,
    prior: SpikeSlabPrior = SpikeSlabPrior(),
    max_active: int | None = None,
    swap: bool = True,
) -> tuple[GibbsState, GibbsInfo]:
    """One Gibbs sweep: the indicators in random order, then `sigma2`, `theta`, `v_s`
    and `p0`. Pure: the same key and state give the same result.

    **Arguments:**

    - `key`: PRNG key.
    - `state`: the `GibbsState` before the sweep.
    - `stats`: `SuffStats` (standardised: `standardize`).
    - `prior`: the `SpikeSlabPrior`.
    - `max_active`: static, default `min(K, 32)`: the largest model; the sampler then
      targets the prior truncated to models of at most that size.
    - `swap`: static; after the indicator sweep, one Metropolis-Hastings exchange of an
      active term for a correlated inactive one (`_swap`); False: the plain Gibbs sweep.

    **Returns:** `(state, info)`: the `GibbsState` after the sweep and its `GibbsInfo`
    (`num_active` and `log_marginal`, both `()`).
    """
    k_ind, k_gamma, k_theta = jax.random.split(key, 3)
    K = stats.gram.shape[0]
    R = slots(K, max_active)
    dtype = stats.gram.dtype
    gamma, changed, initial = _sweep(k_ind, state.gamma, state.p0, state.v_s, stats, prior, R)
    r = jnp.sum(gamma).astype(dtype)

    # Every gamma variate of the sweep in one call (sigma2, v_s and p0 = G_a / (G_a + G_b)),
    # in logs (p0's a_p = 0.1 underflows a plain gamma): one compiled rejection loop, not four.
    terms = jnp.sum(present_terms(stats)).astype(dtype)
    shapes = jnp.stack([prior.a_sigma + 0.5 * stats.n, prior.a_v + 0.5 * r, prior.a_p + r, prior.b_p + terms - r])
    log_g = jax.random.loggamma(k_gamma, shapes.astype(dtype), dtype=dtype)

    def refactor(_):
        slot_idx, _ = _active_slots(gamma, R)
        return (slot_idx,) + _factor_slots(stats, slot_idx, state.v_s)[:4]

    # Most sweeps flip nothing: then the sweep's own factorisation (same gamma, same v_s) serves.
    slot_idx, chol, logdet, mean, quad = jax.lax.cond(changed, refactor, lambda _: initial, None)
    if swap:
        # A key of its own (folded, not split), so the sweep's draws are those of swap=False.
        gamma, (slot_idx, chol, logdet, mean, quad) = _swap(
            jax.random.fold_in(key, 1), gamma, (slot_idx, chol, logdet, mean, quad), state.v_s, stats, prior
        )
    resid = jnp.maximum(stats.yty - quad, 1e-300)
    sigma2 = (prior.b_sigma + 0.5 * resid) * jnp.exp(-log_g[0])

    z = jax.random.normal(k_theta, (R,), dtype=dtype)
    m = (slot_idx < K).astype(dtype)
    theta_slots = (mean + jnp.sqrt(sigma2) * solve_triangular(chol.T, z, lower=False)) * m
    theta = jnp.zeros(K + 1, dtype).at[slot_idx].set(theta_slots)[:K]

    v_rate = prior.b_v + 0.5 * jnp.dot(theta, theta) / sigma2
    v_s = v_rate * jnp.exp(-log_g[1])
    p0 = jnp.exp(log_g[2] - jnp.logaddexp(log_g[2], log_g[3]))
    # Guard the log-odds against p0 rounding to exactly 0 or 1.
    p0 = jnp.clip(p0, 1e-300, 1.0 - 1e-16)

    log_ml = log_marginal(r, logdet, quad, state.v_s, stats, prior)
    return GibbsState(gamma, theta, sigma2, v_s, p0), GibbsInfo(r, log_ml)


def run_chain(
    key: jax.Array,
    state: GibbsState,
    stats: SuffStats,
    num_steps: int,
    prior: SpikeSlabPrior = SpikeSlabPrior(),
    max_active: int | None = None,
    swap: bool = True,
) -> tuple[GibbsState, GibbsTrace]:
    """`num_steps` sweeps of `step` under `lax.scan`.

    **Arguments:**

    - `key`: PRNG key, split into one key per sweep.
    - `state`: the starting `GibbsState`.
    - `stats`: `SuffStats` (standardised), as in `step`.
    - `num_steps`: static, the number of sweeps.
    - `prior`: the `SpikeSlabPrior`, as in `step`.
    - `max_active`: static, the largest model, as in `step`.
    - `swap`: static, the exchange move, as in `step`.

    **Returns:** `(state, trace)`: the last `GibbsState` and the `GibbsTrace` of every sweep,
    leading axis `num_steps`.
    """
    return run_keys(jax.random.split(key, num_steps), state, stats, prior, max_active, swap)


def run_keys(keys, state, stats, prior, max_active=None, swap=True):
    """Like `run_chain` but from explicit per-step keys.

    **Arguments:**

    - `keys`: one PRNG key per sweep, leading axis `num_steps` (as `jax.random.split` gives them).
    - `state`: the starting `GibbsState`.
    - `stats`: `SuffStats` (standardised), as in `step`.
    - `prior`: the `SpikeSlabPrior`, as in `step`.
    - `max_active`: static, the largest model (default None: `min(K, 32)`), as in `step`.
    - `swap`: static, the exchange move (default True), as in `step`.

    **Returns:** `(state, trace)`: the last `GibbsState` and the `GibbsTrace` of every sweep,
    leading axis `num_steps`.
    """

    def one(state, key):
        state, info = step(key, state, stats, prior, max_active, swap)
        return state, GibbsTrace(state.gamma, state.theta, state.sigma2, state.v_s, state.p0, info.log_marginal)

    return jax.lax.scan(one, state, keys)
