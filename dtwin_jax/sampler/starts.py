"""Where the chains start: the greedy forward selection and the dispersed starts.

Chains that all start in one mode cannot reveal a second one. `initial_indicators`
starts chain 0 from a greedy forward selection (`greedy_indicators`) and the others from
greedy selections among random halves of the library: a posterior with several modes then
shows up as chains that disagree (per-chain PIPs, R-hat).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dtwin_jax.sampler.kernel import (
    GibbsState,
    SpikeSlabPrior,
    SuffStats,
    init,
    log_marginal,
    present_terms,
    slots,
)

__all__ = ["greedy_indicators", "initial_indicators", "starting_states"]


def greedy_indicators(stats: SuffStats, prior: SpikeSlabPrior, p0, v_s, R, allowed=None):
    """Forward selection on the collapsed posterior of `gamma` at fixed `p0` and `v_s`.

    Starting from the empty model, add the term whose inclusion most increases
    `log p(y | gamma, v_s) + log p(gamma | p0)` until no addition helps. This replaces the
    paper's least-squares initialisation (Algorithm 1, steps 2-3), which breaks down when the
    library is nearly collinear (K close to N, or exp/sin next to polynomials).

    **Arguments:**

    - `stats`: `SuffStats` (standardised).
    - `prior`: the `SpikeSlabPrior`.
    - `p0`: the inclusion probability, held fixed, `()`.
    - `v_s`: the slab variance (relative to `sigma2`), held fixed, `()`.
    - `R`: the largest model (may be traced).
    - `allowed`: `(K,)` bool, the candidates, or None (default) for every term; zero columns
      never.

    **Returns:** `(K,)` bool indicators.
    """
    K = stats.gram.shape[0]
    G, b = stats.gram, stats.xty
    logit_p0 = jnp.log(p0) - jnp.log1p(-p0)
    allowed = present_terms(stats) & (True if allowed is None else jnp.asarray(allowed, bool))

    def gains(P, gamma, logdet, quad, r):
        m = gamma.astype(G.dtype)
        U = P @ (G * m[:, None])  # column k: P g_k, g_k the active part of G[:, k]
        s = jnp.maximum(jnp.diagonal(G) + 1.0 / v_s - jnp.sum(G * m[:, None] * U, axis=0), 1.0 / v_s)
        t = b - U.T @ b
        new = log_marginal(r + 1, logdet + jnp.log(s), quad + t**2 / s, v_s, stats, prior)
        old = log_marginal(r, logdet, quad, v_s, stats, prior)
        gain = jnp.where(gamma | ~allowed, -jnp.inf, new - old + logit_p0)
        return gain, U, s, t

    def cond(carry):
        _, gamma, _, _, r, best = carry
        return (best > 0) & (r < R)

    def body(carry):
        P, gamma, logdet, quad, r, _ = carry
        gain, U, s, t = gains(P, gamma, logdet, quad, r)
        k = jnp.argmax(gain)
        best = gain[k]
        w = U[:, k] - jnp.eye(K, dtype=G.dtype)[k]
        add = best > 0
        P = jnp.where(add, P + jnp.outer(w, w) / s[k], P)
        gamma = jnp.where(add, gamma.at[k].set(True), gamma)
        logdet = jnp.where(add, logdet + jnp.log(s[k]), logdet)
        quad = jnp.where(add, quad + t[k] ** 2 / s[k], quad)
        r = jnp.where(add, r + 1, r)
        return P, gamma, logdet, quad, r, best

    carry = (
        jnp.zeros_like(G),
        jnp.zeros(K, dtype=bool),
        jnp.zeros((), G.dtype),
        jnp.zeros((), G.dtype),
        jnp.zeros((), jnp.int32),
        jnp.asarray(jnp.inf, G.dtype),
    )
    return jax.lax.while_loop(cond, body, carry)[1]


def initial_indicators(
    key: jax.Array,
    stats: SuffStats,
    num_chains: int,
    prior: SpikeSlabPrior = SpikeSlabPrior(),
    *,
    p0: float = 0.1,
    v_s: float = 10.0,
    max_active: int | None = None,
    strategy: str = "dispersed",
) -> jax.Array:
    """Starting indicators of `num_chains` chains.

    Every strategy starts chain 0 from the greedy forward selection (as `init`).
    Chains c >= 1:

    - `"dispersed"`: the greedy selection, of at most `max(1, R // 4)` terms
      (`R = max_active`), among a random half of the library (each term kept with
      probability 1/2). Where the best model's terms are left out, the chain starts at the
      best model made of the others: a locally good alternative, the kind of second mode a
      single greedy start hides.
    - `"random"`: chain 1 the empty model, chains c >= 2 a uniformly random subset of size
      uniform on `1..min(R, K // 2)`. On large collinear libraries the first sweeps from
      such a start can fill the model up to the cap `R` with poor terms, where it stays
      (the sweep only adds below the cap): on example 2's 258-term library some chains from
      the empty model and from random subsets were still there after many sweeps.
    - `"greedy"`: the greedy selection for every chain.

    Pure and jittable. The caps count terms, not the zero columns a driver pads with.

    **Arguments:**

    - `key`: PRNG key for the random choices.
    - `stats`: standardised `SuffStats`.
    - `num_chains`: static, the number of chains.
    - `prior`: the `SpikeSlabPrior`.
    - `p0`: the inclusion probability held fixed in the greedy selections (default 0.1), as in
      `dtwin_jax.sampler.kernel.init`.
    - `v_s`: the slab variance held fixed there (default 10), as in `init`.
    - `max_active`: the largest model `R` (default None: `min(K, 32)`), as in `init`.
    - `strategy`: `"dispersed"` (default), `"random"` or `"greedy"` (above); any other raises
      `ValueError`.

    **Returns:** `(num_chains, K)` bool starting indicators.
    """
    if strategy not in ("dispersed", "random", "greedy"):
        raise ValueError(f"unknown init_strategy {strategy!r} (dispersed, random or greedy)")
    K = stats.gram.shape[0]
    R = slots(K, max_active)
    dtype = stats.gram.dtype
    p0, v_s = jnp.asarray(p0, dtype), jnp.asarray(v_s, dtype)
    if strategy == "greedy" or num_chains == 1:
        return jnp.broadcast_to(greedy_indicators(stats, prior, p0, v_s, R), (num_chains, K))
    # The caps count terms, not the zero columns a driver pads with: static R where there are none.
    terms = jnp.sum(present_terms(stats))
    R_terms = jnp.minimum(terms, R)
    if strategy == "dispersed":
        # Chains c >= 1: the greedy selection among a random half, stopped at R // 4 terms: a
        # start at the cap R cannot take in a better term (the sweep only adds below the cap);
        # on example 2's 258-term library 1 in 36 uncapped starts stayed at the cap,
        # log p(y | gamma) 320 below the mode, and none of 72 capped. All chains' selections
        # run as one vmapped loop (one compiled program).
        halves = jax.vmap(lambda k: jax.random.bernoulli(k, 0.5, (K,)))(jax.random.split(key, num_chains - 1))
        allowed = jnp.concatenate([jnp.ones((1, K), bool), halves])
        caps = jnp.concatenate([R_terms[None], jnp.full(num_chains - 1, jnp.maximum(1, R_terms // 4))])
        return jax.vmap(lambda a, c: greedy_indicators(stats, prior, p0, v_s, c, allowed=a))(allowed, caps)
    largest = jnp.minimum(R_terms, terms // 2)
    present = present_terms(stats)

    def random_subset(k):
        k_size, k_perm = jax.random.split(k)
        size = jnp.where(largest > 0, jax.random.randint(k_size, (), 1, jnp.maximum(largest, 1) + 1), 0)
        # The first ``size`` terms of a random permutation: every subset of that size equally likely.
        perm = jax.random.permutation(k_perm, K)
        rank = jnp.cumsum(present[perm]) - 1
        return jnp.zeros(K, bool).at[perm].set(present[perm] & (rank < size))

    greedy = greedy_indicators(stats, prior, p0, v_s, R)
    others = jax.vmap(random_subset)(jax.random.split(key, num_chains - 2))
    return jnp.concatenate([greedy[None], jnp.zeros((1, K), bool), others])


def starting_states(key, scaled, prior, p0, v_s, max_active, num_chains, init_strategy) -> GibbsState:
    """The chains' starting states: `initial_indicators`, then
    `dtwin_jax.sampler.kernel.init` for each.

    **Arguments:**

    - `key`: PRNG key; the starts draw from a key folded off it.
    - `scaled`: the standardised `SuffStats`.
    - `prior`: the `SpikeSlabPrior`.
    - `p0`: the starting inclusion probability, as in `initial_indicators`.
    - `v_s`: the starting slab variance, as in `initial_indicators`.
    - `max_active`: the largest model, or None, as in `initial_indicators`.
    - `num_chains`: static, the number of chains.
    - `init_strategy`: `initial_indicators`' `strategy`.

    **Returns:** `GibbsState` with leading axis `num_chains`.
    """
    # The starting states draw from a key folded off ``key``, so the chains' own keys (and
    # with ``init_strategy="greedy"`` the draws) are those of a greedy-only sampler.
    gammas = initial_indicators(
        jax.random.fold_in(key, 1), scaled, num_chains, prior,
        p0=p0, v_s=v_s, max_active=max_active, strategy=init_strategy,
    )
    return jax.vmap(lambda g: init(scaled, prior, p0=p0, v_s=v_s, gamma=g))(gammas)
