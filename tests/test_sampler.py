"""The spike-and-slab Gibbs kernel: correctness, purity, jit/vmap, sufficient statistics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import sampler as S
from dtwin_jax._compile.buckets import bucket, pad_stats
from dtwin_jax.sampler import driver, kernel


def _problem(seed=0, N=400, K=12, noise=0.3):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(N, K))
    L[:, 1] = L[:, 0] + 0.05 * rng.normal(size=N)  # a near-collinear pair
    theta = np.zeros(K)
    support = [k for k in (0, 4, 7) if k < K] or [0]
    theta[support] = [3.0, -2.0, 0.5][: len(support)]
    y = L @ theta + noise * rng.normal(size=N)
    return L, y, theta


def _dense_log_marginal(stats, gamma, v_s, prior):
    """log p(y | gamma, v_s) up to a constant, from the dense active block (Appendix A)."""
    G, b, yty, n = (np.asarray(a) for a in stats)
    A = G[np.ix_(gamma, gamma)] + np.eye(gamma.sum()) / v_s
    quad = b[gamma] @ np.linalg.solve(A, b[gamma]) if gamma.any() else 0.0
    logdet = np.linalg.slogdet(A)[1] if gamma.any() else 0.0
    shape = prior.a_sigma + 0.5 * n
    return -0.5 * gamma.sum() * np.log(v_s) - 0.5 * logdet - shape * np.log(prior.b_sigma + 0.5 * (yty - quad))


def test_recovers_support_and_coefficients():
    L, y, theta = _problem()
    # The chunked runner: sample_jit's draws, from the compiled chunk other tests here share.
    trace = S.sample_in_chunks(jax.random.key(0), S.suff_stats(L, y), num_draws=1000, num_burnin=300, num_chains=2)
    pip = np.asarray(trace.gamma).mean(axis=(0, 1))
    assert set(np.flatnonzero(pip > 0.5)) == {0, 4, 7}
    assert pip[[0, 4, 7]].min() > 0.95
    assert np.delete(pip, [0, 1, 4, 7]).max() < 0.1
    assert pip[1] < 0.5  # the near-duplicate of column 0 keeps some mass, honestly
    ols = np.linalg.lstsq(L[:, [0, 4, 7]], y, rcond=None)[0]
    gam = np.asarray(trace.gamma).reshape(-1, L.shape[1])
    model = (gam == np.isin(np.arange(L.shape[1]), [0, 4, 7])).all(axis=1)
    mean = np.asarray(trace.theta).reshape(-1, L.shape[1])[model].mean(axis=0)[[0, 4, 7]]
    np.testing.assert_allclose(mean, ols, rtol=0.02)  # the slab barely shrinks at this SNR
    assert abs(np.sqrt(np.asarray(trace.sigma2).mean()) - 0.3) < 0.03


def test_indicator_conditional_matches_exact_enumeration():
    """The rank-one indicator updates target the exact collapsed posterior of gamma."""
    L, y, _ = _problem(seed=1, N=60, K=4, noise=1.0)
    y = y + 0.15 * L[:, 2] * np.linalg.norm(y) / np.linalg.norm(L[:, 2])  # a weak, uncertain term
    stats = S.standardize(S.suff_stats(L, y))[0]
    prior = S.SpikeSlabPrior()
    p0, v_s = 0.3, 5.0
    # Exact p(gamma | y, p0, v_s) by enumeration over 2^K models, via the dense formula.
    K = 4
    logp = {}
    for bits in range(2**K):
        g = np.array([(bits >> k) & 1 for k in range(K)], dtype=bool)
        logp[bits] = _dense_log_marginal(stats, g, v_s, prior) + g.sum() * np.log(p0) + (K - g.sum()) * np.log1p(-p0)
    top = max(logp.values())
    exact = {b: np.exp(v - top) for b, v in logp.items()}
    z = sum(exact.values())
    exact_pip = np.array([sum(w for b, w in exact.items() if (b >> k) & 1) for k in range(K)]) / z

    # Run only the indicator sweeps at fixed p0, v_s (a Gibbs sampler for p(gamma | ...)).
    def sweep(gamma, key):
        gamma = kernel._indicator_sweep(key, gamma, jnp.asarray(p0), jnp.asarray(v_s), stats, prior, K)
        return gamma, gamma

    _, gammas = jax.jit(lambda k: jax.lax.scan(sweep, jnp.zeros(K, bool), jax.random.split(k, 20000)))(jax.random.key(3))
    est = np.asarray(gammas)[1000:].mean(axis=0)
    np.testing.assert_allclose(est, exact_pip, atol=0.02)


@pytest.mark.parametrize("R", [6, 3])
def test_sweep_jumping_between_flips_equals_one_at_a_time_sweep(R):
    """The sweep computes every indicator's log-odds at once and jumps to the next flip: its
    indicators are those of the plain sweep (one term at a time, in the same order, against the
    same uniforms, dense formulas), also when the model size cap R binds."""
    rng = np.random.default_rng(5)
    N, K = 30, 6
    L = rng.normal(size=(N, K))
    L[:, 1] = L[:, 0] + 0.3 * rng.normal(size=N)
    y = L[:, 0] - 0.5 * L[:, 2] + 0.2 * L[:, 3] + 1.5 * rng.normal(size=N)  # uncertain terms: many flips
    stats = S.standardize(S.suff_stats(L, y))[0]
    prior = S.SpikeSlabPrior()
    p0, v_s = 0.5, 3.0
    sweep = jax.jit(lambda k, g: kernel._indicator_sweep(k, g, jnp.asarray(p0), jnp.asarray(v_s), stats, prior, R))
    gamma, flips = np.zeros(K, bool), 0
    for key in jax.random.split(jax.random.key(11), 40):
        key_order, key_u = jax.random.split(key)
        order = np.asarray(jax.random.permutation(key_order, K))
        uniforms = np.asarray(jax.random.uniform(key_u, (K,), dtype=jnp.float64))
        expect = gamma.copy()
        for i, k in enumerate(order):
            on, off = expect.copy(), expect.copy()
            on[k], off[k] = True, False
            log_odds = (np.log(p0 / (1 - p0)) + _dense_log_marginal(stats, on, v_s, prior)
                        - _dense_log_marginal(stats, off, v_s, prior))
            full = not expect[k] and off.sum() >= R
            expect[k] = uniforms[i] < 1 / (1 + np.exp(-log_odds)) and not full
        got = np.asarray(sweep(key, jnp.asarray(gamma)))
        np.testing.assert_array_equal(got, expect)
        flips += int((got != gamma).sum())
        gamma = got
    assert flips >= 40  # the test exercises many flips per sweep, adds and removals
    assert gamma.sum() <= R


def test_step_is_pure_and_deterministic():
    L, y, _ = _problem()
    stats = S.standardize(S.suff_stats(L, y))[0]
    state = S.init(stats)
    a, _ = S.step(jax.random.key(5), state, stats)
    b, _ = S.step(jax.random.key(5), state, stats)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


def test_compiles_inside_jit_and_vmaps_over_chains_and_problems():
    L, y, _ = _problem()
    stats = S.standardize(S.suff_stats(L, y))[0]

    @jax.jit
    def user_code(key, stats):
        state = S.init(stats)
        keys = jax.random.split(key, 3)
        _, trace = jax.vmap(lambda k: S.run_chain(k, state, stats, 200))(keys)
        return trace.gamma.mean(axis=(0, 1)), trace.theta.shape

    pip, shape = user_code(jax.random.key(0), stats)
    assert shape == (3, 200, L.shape[1])
    assert set(np.flatnonzero(np.asarray(pip) > 0.5)) == {0, 4, 7}

    # vmap over independent regression problems (two targets sharing a library).
    y2 = L[:, 2] * 1.5 + 0.1 * np.random.default_rng(9).normal(size=L.shape[0])
    batch = jax.tree.map(lambda a, b: jnp.stack([a, b]), S.suff_stats(L, y), S.suff_stats(L, y2))
    traces = jax.jit(jax.vmap(lambda k, s: S.sample(k, s, num_draws=300, num_burnin=100, num_chains=2)))(
        jax.random.split(jax.random.key(1), 2), batch
    )
    pips = np.asarray(traces.gamma).mean(axis=(1, 2))
    assert set(np.flatnonzero(pips[0] > 0.5)) == {0, 4, 7}
    assert set(np.flatnonzero(pips[1] > 0.5)) == {2}


def test_depends_on_data_only_through_sufficient_statistics():
    """Two data sets with identical L^T L, L^T y, y^T y (and N) give identical chains."""
    L, y, _ = _problem(N=300)
    N, K = L.shape
    # Rotate [L y] by a random orthogonal N x N matrix: every inner product is unchanged.
    Q, _ = np.linalg.qr(np.random.default_rng(4).normal(size=(N, N)))
    L2, y2 = Q @ L, Q @ y
    s1, s2 = S.suff_stats(L, y), S.suff_stats(L2, y2)
    np.testing.assert_allclose(np.asarray(s1.gram), np.asarray(s2.gram), rtol=1e-11, atol=1e-9)
    assert not np.allclose(L, L2)
    t1 = S.sample_in_chunks(jax.random.key(7), s1, num_draws=400, num_burnin=100, num_chains=2)
    t2 = S.sample_in_chunks(jax.random.key(7), s2, num_draws=400, num_burnin=100, num_chains=2)
    np.testing.assert_array_equal(np.asarray(t1.gamma), np.asarray(t2.gamma))
    np.testing.assert_allclose(np.asarray(t1.theta), np.asarray(t2.theta), rtol=1e-7, atol=1e-9)
    # And a data set with 10x the rows but the same statistics costs the same sweep.
    assert S.suff_stats(np.vstack([L] * 10), np.concatenate([y] * 10)).gram.shape == (K, K)


def test_chunks_and_progress_give_identical_draws_count_every_sweep_and_reuse_one_program(monkeypatch):
    L, y, _ = _problem()
    st = S.suff_stats(L, y)
    a = S.sample(jax.random.key(2), st, num_draws=60, num_burnin=20, num_chains=2)
    b = S.sample(jax.random.key(2), st, num_draws=60, num_burnin=20, num_chains=2, progress=True)  # in chunks
    np.testing.assert_array_equal(np.asarray(a.gamma), np.asarray(b.gamma))
    for x, y in zip(a[1:], b[1:]):  # eager against compiled: rounding only
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-13)
    # Other lengths run the same compiled chunk: 400 + 350 sweeps are 3 chunks of 250 per chain.
    counted = []
    monkeypatch.setattr(driver, "tick", counted.append)
    compiled = driver._run_chains_jit._cache_size()
    c = S.sample_in_chunks(jax.random.key(3), st, num_draws=400, num_burnin=350, num_chains=2, progress=True)
    assert driver._run_chains_jit._cache_size() == compiled and counted == [2 * S.CHUNK] * 3
    assert c.theta.shape == (2, 400, 12) and isinstance(c.theta, np.ndarray)


def test_physical_units_are_restored():
    """Scaling a column by 1e4 scales its coefficient by 1e-4 and nothing else changes."""
    L, y, _ = _problem()
    L2 = L.copy()
    L2[:, 4] *= 1e4
    t1 = S.sample_jit(jax.random.key(0), S.suff_stats(L, y), num_draws=200, num_burnin=50, num_chains=1)
    t2 = S.sample_jit(jax.random.key(0), S.suff_stats(L2, y), num_draws=200, num_burnin=50, num_chains=1)
    np.testing.assert_array_equal(np.asarray(t1.gamma), np.asarray(t2.gamma))
    np.testing.assert_allclose(np.asarray(t2.theta)[..., 4] * 1e4, np.asarray(t1.theta)[..., 4], rtol=1e-8)


@pytest.mark.parametrize("K", [30, 200])
def test_sweep_cost_independent_of_N(K):
    """The kernel sees (K, K) statistics only: the compiled step has no N-sized buffer."""
    L, y, _ = _problem(N=50 * K if K < 100 else 2000, K=K)
    stats = S.standardize(S.suff_stats(L, y))[0]
    text = jax.jit(lambda k, s: S.step(k, s, stats)).lower(jax.random.key(0), S.init(stats)).as_text()
    assert f"{L.shape[0]}x" not in text and f"x{L.shape[0]}" not in text


def test_dispersed_starts_are_greedy_then_greedy_on_random_halves():
    L, y, _ = _problem(K=12)
    stats = S.standardize(S.suff_stats(L, y))[0]
    greedy = np.asarray(S.init(stats).gamma)
    starts = np.asarray(jax.jit(lambda k: S.initial_indicators(k, stats, 6))(jax.random.key(0)))
    assert starts.shape == (6, 12)
    np.testing.assert_array_equal(starts[0], greedy)
    assert len({row.tobytes() for row in starts}) > 2  # dispersed, not six copies
    assert (starts[1:].sum(axis=1) <= max(1, 12 // 4)).all()  # room left below the cap
    same = np.asarray(S.initial_indicators(jax.random.key(0), stats, 3, strategy="greedy"))
    assert (same == greedy).all()
    rand = np.asarray(S.initial_indicators(jax.random.key(0), stats, 5, strategy="random"))
    assert not rand[1].any() and (rand[2:].sum(axis=1) >= 1).all() and (rand[2:].sum(axis=1) <= 6).all()


def test_disagreeing_chains_are_visible_and_greedy_strategy_keeps_chain_keys():
    """A chain held away from the mode shows as PIP spread; "greedy" reproduces a sampler
    whose chains all start at the greedy state."""
    from dtwin_jax.posterior import EquationPosterior

    L, y, _ = _problem()
    st = S.suff_stats(L, y)
    g = S.sample_jit(jax.random.key(3), st, num_draws=300, num_burnin=100, num_chains=2, init_strategy="greedy")
    # The kernel's own chain, on the library padded as the driver pads it (12 -> 16 columns).
    scaled = pad_stats(S.standardize(st)[0], bucket(L.shape[1]))
    state = S.init(scaled)
    keys = jax.random.split(jax.random.key(3), 2)
    _, manual = S.run_chain(keys[0], state, scaled, 400)
    assert not np.asarray(manual.gamma)[:, L.shape[1]:].any()  # the padding is no term
    np.testing.assert_array_equal(np.asarray(g.gamma[0]), np.asarray(manual.gamma[100:, : L.shape[1]]))
    gam = np.array(g.gamma)
    gam[1, :, 4] = False  # chain 1 never includes the true term 4
    post = EquationPosterior("x2", "drift", tuple(map(str, range(L.shape[1]))), gam, np.asarray(g.theta), np.asarray(g.sigma2))
    assert post.pip_per_chain.shape == (2, L.shape[1])
    assert post.pip_chain_spread_max > 0.9 and np.argmax(post.pip_chain_spread) == 4
    assert np.nanmax(post.rhat_gamma()) > 1.5


@pytest.mark.parametrize("K", [19, 23])
def test_a_library_of_17_to_24_terms_samples_in_24_slots_with_the_draws_of_32(K):
    """Padded to 32 columns, a 19-term library took 32 active-set slots (0.170 s for the
    monitor's 2 x 1250 sweeps); its model cannot outgrow 19 terms, so 24 slots give the same
    draws (0.120 s, one pinned core: `taskset -c 0 python benchmarks/sampler_speed.py --slots`)."""
    from dtwin_jax._compile.buckets import active_slots

    assert [active_slots(k) for k in (1, 16, 17, 24, 25, 32, 33, 256)] == [16, 16, 24, 24, 32, 32, 32, 32]
    rng = np.random.default_rng(K)
    L = rng.normal(size=(400, K))
    y = L[:, :3] @ np.array([1.0, -0.5, 0.2]) + 0.5 * rng.normal(size=400)
    st = S.suff_stats(L, y)
    settings = S.SamplerSettings(num_chains=2, num_draws=300, num_burnin=100)
    default = S.sample_in_chunks(jax.random.key(1), st, settings)
    wide = S.sample_in_chunks(jax.random.key(1), st, settings, max_active=32)
    # The same draws; compiled with XLA's passes (JAX_DISABLE_MOST_OPTIMIZATIONS=0), the two
    # programs' sums may round differently (2e-16 seen), never enough to flip an inclusion.
    np.testing.assert_array_equal(default.gamma, wide.gamma)
    for name in ("theta", "sigma2"):
        np.testing.assert_allclose(getattr(default, name), getattr(wide, name), rtol=1e-12, atol=1e-15)
    assert default.gamma.mean(axis=(0, 1))[:2].min() == 1.0
