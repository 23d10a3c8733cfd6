"""The Gibbs kernel against an independent sampler of the same posterior and against the exact
posterior, and its conditionals against their exact distributions.

* The package's kernel (``sampler.sample_jit``) agrees with the exact posterior (all 2^K
  models enumerated, ``p0`` integrated analytically and ``v_s`` by quadrature) on PIPs, on the
  posterior mean and standard deviation of every ``theta * gamma`` and on the
  hyperparameters' posterior means, within 4 Monte Carlo standard errors (arviz's ESS-based
  MCSE), and so does the NumPy Algorithm 1 of benchmarks/algorithm1_numpy.py, the timing
  baseline (``pytest -m slow``: it checks a benchmark, not the package).
* The model of benchmarks/numpyro_model.py (discrete indicators, ``DiscreteHMCGibbs(NUTS)``)
  agrees with both the same way, within 4 combined MCSEs of the two samplers (``pytest -m
  slow``: NUTS takes most of this file's time).
* For a fixed indicator vector, the kernel's draws of ``sigma2``, ``theta``, ``v_s`` and ``p0``
  follow their exact conditionals (independent draws, so the standard errors are exact).
"""

import os
import sys
import time

import arviz as az
import jax
import numpy as np
import pytest
from scipy import stats as sps
from scipy.special import betaln, logsumexp

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import sampler as S

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import algorithm1_numpy  # noqa: E402
import numpyro_model  # noqa: E402

Z = 4.0  # allowed difference, in Monte Carlo standard errors
FLOOR = 1e-3  # absolute slack for quantities both samplers estimate with (near) zero error


def _problem(seed=2, N=200, K=6, marginal=0.16):
    """``L (N, K)``, ``y (N,)``: two clear terms (1.0, -0.8), a marginal one (PIP about 0.6),
    three null columns, unit noise."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(N, K))
    theta = np.zeros(K)
    theta[:3] = [1.0, -0.8, marginal]
    return L, L @ theta + rng.normal(size=N)


def _exact_posterior(L, y, prior=S.SpikeSlabPrior(), num_grid=2001):
    """Exact posterior summaries of the model for ``L (N, K)``, ``y (N,)`` (scaled to unit RMS
    inside, as the samplers do), in physical
    units, for small K: every indicator vector enumerated, ``p0`` integrated analytically (a
    beta function), ``theta`` and ``sigma2`` analytically (Gaussian, inverse gamma) and ``v_s`` by
    quadrature on a uniform grid in ``log v_s``. NumPy only, independent of the package.

    Returns ``pip (K,)``, ``mean (K,)`` and ``sd (K,)`` of ``theta * gamma``, and the posterior
    means ``sigma2``, ``log_v_s``, ``p0``.
    """
    col, ys = numpyro_model.unit_rms_scales(L, y)
    Ls, yss = L / col, y / ys
    N, K = Ls.shape
    G, b, yty = Ls.T @ Ls, Ls.T @ yss, yss @ yss
    log_v = np.linspace(np.log(1e-6), np.log(1e8), num_grid)  # (V,)
    inv_v = np.exp(-log_v)
    log_prior_v = sps.invgamma.logpdf(np.exp(log_v), prior.a_v, scale=prior.b_v) + log_v  # density of log v_s
    shape = prior.a_sigma + 0.5 * N
    log_w, first, second, sigma2 = [], [], [], []
    gammas = (np.arange(2**K)[:, None] >> np.arange(K)) & 1 == 1  # (2^K, K)
    for g in gammas:
        # A = G_g + I / v_s = Q diag(lam + 1/v_s) Q^T: every v_s on the grid at once.
        lam, Q = np.linalg.eigh(G[np.ix_(g, g)])
        d = lam[None, :] + inv_v[:, None]  # (V, r)
        qb = Q.T @ b[g]
        rate = prior.b_sigma + 0.5 * (yty - np.sum(qb**2 / d, axis=1))  # (V,)
        log_w.append(
            -0.5 * g.sum() * log_v - 0.5 * np.log(d).sum(axis=1) - shape * np.log(rate)
            + log_prior_v + betaln(prior.a_p + g.sum(), prior.b_p + K - g.sum())
        )
        mean = np.zeros((log_v.size, K))
        mean[:, g] = (qb / d) @ Q.T  # E[theta_g | gamma, v_s, y]
        var = np.zeros((log_v.size, K))
        var[:, g] = (rate / (shape - 1))[:, None] * ((1.0 / d) @ (Q.T**2))  # E[sigma2] diag(A^-1)
        first.append(mean)
        second.append(mean**2 + var)
        sigma2.append(rate / (shape - 1))
    log_w = np.array(log_w)  # (2^K, V)
    w = np.exp(log_w - logsumexp(log_w))
    m1 = np.einsum("gv,gvk->k", w, np.array(first))
    m2 = np.einsum("gv,gvk->k", w, np.array(second))
    r = gammas.sum(axis=1)
    return {
        "pip": w.sum(axis=1) @ gammas,
        "mean": m1 * ys / col,
        "sd": np.sqrt(m2 - m1**2) * ys / col,
        "sigma2": np.sum(w * np.array(sigma2)) * ys**2,
        "log_v_s": np.sum(w * log_v),
        "p0": w.sum(axis=1) @ ((prior.a_p + r) / (prior.a_p + prior.b_p + K)),
    }


def _mcse(x, method="mean"):
    """arviz MCSE of ``x (chains, draws, ...)``; 0 where a quantity never moves (PIP of 1)."""
    return np.nan_to_num(np.asarray(az.mcse(np.asarray(x, float), method=method)), nan=0.0)


@pytest.fixture(scope="module")
def gibbs():
    """The kernel's draws (physical units, ``(chains, draws, ...)``) and the exact summaries."""
    L, y = _problem()
    start = time.perf_counter()
    trace = S.sample_jit(jax.random.key(0), S.suff_stats(L, y), num_draws=5000, num_burnin=500, num_chains=4)
    draws = {name: np.asarray(getattr(trace, name)) for name in ("gamma", "theta", "sigma2", "v_s", "p0")}
    print(f"\nwall time incl. compilation: Gibbs kernel {time.perf_counter() - start:.1f} s (4 x 5500 sweeps)")
    return draws, _exact_posterior(L, y)


@pytest.fixture(scope="module")
def nuts():
    """NumPyro's draws of the same posterior. 16 vmapped chains cost little more per
    iteration than 4 (the NUTS loop's overhead dominates at K = 6), and give 4x the effective
    draws."""
    L, y = _problem()
    start = time.perf_counter()
    draws = numpyro_model.fit(L, y, seed=1, num_warmup=500, num_samples=2000, num_chains=16)
    print(f"\nwall time incl. compilation: NumPyro DiscreteHMCGibbs {time.perf_counter() - start:.1f} s "
          f"(16 x 2500 iterations)")
    return draws


def _against_exact(label, name, x, exact, est, method="mean"):
    """Assert ``est`` of the draws ``x (chains, draws, ...)`` differs from ``exact`` by at most
    Z of their MCSEs (plus FLOOR); print the numbers."""
    a, se = est(x), _mcse(x, method)
    with np.printoptions(precision=4, suppress=True):
        print(f"{label}: exact {exact}\n  {name} {a} (mcse {se}, ESS {np.asarray(az.ess(np.asarray(x, float))).round(0)})"
              f"\n  |{name} - exact| / mcse {np.abs(a - exact) / np.maximum(se, 1e-12)}")
    assert np.all(np.abs(a - exact) <= Z * se + FLOOR), f"{label}: {name} vs exact"


def _agree(label, g, n, est, method="mean"):
    """Assert ``est`` of the Gibbs draws ``g`` and of the NumPyro draws ``n`` (both
    ``(chains, draws, ...)``) differ by at most Z combined MCSEs (plus FLOOR)."""
    a, b = est(g), est(n)
    se = np.sqrt(_mcse(g, method) ** 2 + _mcse(n, method) ** 2)
    with np.printoptions(precision=4, suppress=True):
        print(f"{label}: |gibbs - numpyro| / combined mcse {np.abs(a - b) / np.maximum(se, 1e-12)}")
    assert np.all(np.abs(a - b) <= Z * se + FLOOR), label


def _mean(x):
    return x.mean(axis=(0, 1))


def _sd(x):
    return x.std(axis=(0, 1))


def _summaries(d, exact):
    """``(label, draws, exact value, estimator, MCSE method)`` of every compared quantity.
    ``v_s`` has a heavy right tail (IG with shape a_v + r/2 = 1.5 given two terms): its logs
    are compared."""
    return [("PIP", d["gamma"], exact["pip"], _mean, "mean"),
            ("theta*gamma mean", d["theta"], exact["mean"], _mean, "mean"),
            ("theta*gamma sd", d["theta"], exact["sd"], _sd, "sd"),
            ("sigma2 mean", d["sigma2"], exact["sigma2"], _mean, "mean"),
            ("log v_s mean", np.log(d["v_s"]), exact["log_v_s"], _mean, "mean"),
            ("p0 mean", d["p0"], exact["p0"], _mean, "mean")]


@pytest.mark.optimized
def test_the_kernel_samples_the_exact_posterior(gibbs):
    draws, exact = gibbs
    assert 0.2 < exact["pip"][2] < 0.8, "the marginal term must keep the PIP comparison non-trivial"
    for label, x, target, est, method in _summaries(draws, exact):
        _against_exact(label, "gibbs", x, target, est, method)


# NumPyro's NUTS-within-Gibbs takes about 40 s here, compilation included; the kernel's
# agreement with the exact posterior above is the default run's check.
@pytest.mark.slow
@pytest.mark.optimized
def test_numpyro_samples_the_same_posterior(gibbs, nuts):
    draws, exact = gibbs
    for (label, x, target, est, method), (_, n, *_) in zip(_summaries(draws, exact), _summaries(nuts, exact)):
        _against_exact(label, "numpyro", n, target, est, method)
        _agree(label, x, n, est, method)


@pytest.mark.slow  # the benchmarks' NumPy baseline, not the package: the kernel above runs by default
def test_algorithm1_baseline_matches_exact():
    """The NumPy Algorithm 1 that benchmarks/run.py times samples the same posterior."""
    L, y = _problem()
    col, ys = numpyro_model.unit_rms_scales(L, y)
    start = time.perf_counter()
    d = algorithm1_numpy.run(L / col, y / ys, 5500, seed=0)
    print(f"\nAlgorithm 1 (NumPy): 5500 sweeps in {time.perf_counter() - start:.1f} s")
    exact = _exact_posterior(L, y)
    gamma = d["gamma"][None, 500:].astype(float)  # (1 chain, draws, K)
    theta = d["theta"][None, 500:] * ys / col
    for label, x, target, est, method in [
        ("PIP", gamma, exact["pip"], _mean, "mean"),
        ("theta*gamma mean", theta, exact["mean"], _mean, "mean"),
        ("theta*gamma sd", theta, exact["sd"], _sd, "sd"),
        ("sigma2 mean", d["sigma2"][None, 500:] * ys**2, exact["sigma2"], _mean, "mean"),
    ]:
        se = _mcse(x, method)
        with np.printoptions(precision=4, suppress=True):
            print(f"{label}: Algorithm 1 {est(x)} exact {target} |diff| / mcse {np.abs(est(x) - target) / np.maximum(se, 1e-12)}")
        assert np.all(np.abs(est(x) - target) <= Z * se + FLOOR), label


# --- the continuous conditionals of one sweep ------------------------------------------------


def _moments_match(label, x, mean, var):
    """Sample mean and variance of independent draws ``x (M,)`` against exact ones, within Z
    standard errors (of the variance: from the sample's fourth central moment)."""
    M = x.size
    c = x - x.mean()
    se_mean = np.sqrt(var / M)
    se_var = np.sqrt(max(np.mean(c**4) - c.var() ** 2, 0.0) / M)
    print(f"{label:10s} mean {x.mean():.6g} (exact {mean:.6g}, se {se_mean:.2g})  "
          f"var {c.var():.6g} (exact {var:.6g}, se {se_var:.2g})")
    assert abs(x.mean() - mean) <= Z * se_mean, label
    assert abs(c.var() - var) <= Z * se_var, label


def test_continuous_conditionals_are_exact():
    """Given the indicators a sweep draws, ``sigma2 | gamma, v_s, y`` is IG (theta integrated
    out), ``theta | gamma, sigma2, v_s, y`` Gaussian, ``v_s | theta, sigma2, gamma`` IG and
    ``p0 | gamma`` Beta. ``step`` draws the indicators first and everything else given them, so
    the draws of many steps from one state, kept where the indicators came out as ``g``, are
    independent draws from these conditionals. Decisive data and a small ``p0`` keep almost
    every draw."""
    L, y = _problem(seed=5, marginal=0.5)
    stats = S.standardize(S.suff_stats(L, y))[0]
    prior = S.SpikeSlabPrior()
    K = L.shape[1]
    g = np.arange(K) < 3
    v_s = 2.0
    state = S.init(stats, prior, p0=0.02, v_s=v_s, gamma=g)
    keys = jax.random.split(jax.random.key(3), 40_000)
    new = jax.jit(jax.vmap(lambda k: S.step(k, state, stats, prior)[0]))(keys)
    keep = np.all(np.asarray(new.gamma) == g, axis=1)
    assert keep.mean() > 0.9
    sigma2, v_new, p0 = (np.asarray(a)[keep] for a in (new.sigma2, new.v_s, new.p0))
    theta = np.asarray(new.theta)[keep][:, g]
    M, r = theta.shape
    print(f"\n{M} of {keys.shape[0]} draws kept (indicators = {g.astype(int)})")

    # Exact conditional parameters, in NumPy.
    G = np.asarray(stats.gram)[np.ix_(g, g)]
    b = np.asarray(stats.xty)[g]
    A = G + np.eye(r) / v_s
    mean = np.linalg.solve(A, b)
    shape = prior.a_sigma + 0.5 * float(stats.n)
    rate = prior.b_sigma + 0.5 * (float(stats.yty) - b @ mean)
    ig = sps.invgamma(shape, scale=rate)
    _moments_match("sigma2", sigma2, ig.mean(), ig.var())

    # theta = mean + sqrt(sigma2) C^-T z with A = C C^T: z must be independent standard normals.
    C = np.linalg.cholesky(A)
    z = (theta - mean) @ C / np.sqrt(sigma2)[:, None]
    for j in range(r):
        _moments_match(f"theta z[{j}]", z[:, j], 0.0, 1.0)
    cov = np.cov(z.T)
    print(f"theta z covariance off-diagonal max |.| {np.abs(cov - np.diag(np.diag(cov))).max():.3g}")
    assert np.abs(cov - np.diag(np.diag(cov))).max() <= Z / np.sqrt(M)

    # v_s: parameters change with every draw of (theta, sigma2), so test its PIT for U(0, 1).
    v_rate = prior.b_v + 0.5 * np.sum(theta**2, axis=1) / sigma2
    u = sps.invgamma.cdf(v_new, prior.a_v + 0.5 * r, scale=v_rate)
    _moments_match("v_s PIT", u, 0.5, 1.0 / 12.0)

    beta = sps.beta(prior.a_p + r, prior.b_p + K - r)
    _moments_match("p0", p0, beta.mean(), beta.var())
