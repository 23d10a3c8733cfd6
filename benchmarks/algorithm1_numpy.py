"""The paper's Algorithm 1 in plain NumPy, as written: the timing baseline of issue 10.

    from algorithm1_numpy import run, time_per_sweep

This is the sampler the package replaces, implemented the way the paper states it
(Section 3, Algorithm 1 and Appendix A, Eqs. 28-29), not the way dtwin_jax.sampler does it:

* every indicator ``psi_k`` (in order k = 1..K) evaluates both marginal likelihoods of
  Eq. (29b), ``p(Y | psi_k = 0, ...)`` and ``p(Y | psi_k = 1, ...)``, each through the N x N
  matrix ``I - L_r Sigma_theta L_r^T``: 2 K matrices of size N x N per sweep, O(K N^2 r);
* ``sigma2`` (step 8) and ``theta_r`` (steps 4 and 11) from ``Sigma_theta`` and ``L_r^T Y``,
  recomputed from ``L`` every sweep;
* ``v_s`` (step 9) and ``p0`` (step 10) from their inverse-gamma and beta conditionals.

Hierarchy and hyperparameters are those of ``dtwin_jax.sampler.SpikeSlabPrior`` (the prior
correlation ``R_0`` is the identity). The data are used as given: the package standardises
``L`` and ``y`` first, so pass standardised data to compare draws.

Three places where the paper's text cannot be followed literally, and what is done instead:

* Eq. (29b) prints ``h_z / vartheta_s^2`` in the denominator; the slab's normalising constant
  is ``vartheta_s^(h_z / 2)`` (the same ``|vartheta_s^-1 R_0^-1|^(1/2)`` as in its numerator).
* Step 4 writes ``mu_theta = Sigma_theta L_r^T Y`` with ``Sigma_theta`` including ``sigma2``;
  the conditional mean is ``(L_r^T L_r + I / vartheta_s)^-1 L_r^T Y`` (no ``sigma2``).
* Step 9 draws ``v_s`` from ``theta^(i)``, the previous sweep's coefficients, which were drawn
  under the previous indicators: after the indicators changed (a newly active term has
  ``theta_k = 0`` while ``h_z`` counts it) that is not a draw from a conditional of the
  posterior, and the chain would target something else. Here ``theta`` is drawn (step 11)
  before ``v_s``, the order of the package's kernel; the cost is the same.

Initialisation follows steps 2-3: every term active (least squares on the whole library is
the minimum-MSE model), ``p0 = 0.1`` and ``v_s = 10``. ``sigma2`` and ``theta`` need no initial
value: both are drawn after the indicators, with ``theta`` and ``sigma2`` integrated out of them.
"""

from __future__ import annotations

import ctypes
import time

import numpy as np
from scipy.special import expit, gammaln

from dtwin_jax.sampler import SpikeSlabPrior


def make_problem(K: int, N: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The benchmark regression (as benchmarks/sampler_speed.py): ``L (N, K)`` standard
    normal, ``y (N,)`` from the first three columns with coefficients (1, -2, 0.5) and noise
    0.1 (fewer columns when K < 3)."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(N, K))
    coef = np.array([1.0, -2.0, 0.5])[: min(K, 3)]
    y = L[:, : coef.size] @ coef + 0.1 * rng.normal(size=N)
    return L, y


def log_marginal(L: np.ndarray, y: np.ndarray, psi: np.ndarray, v_s: float, prior: SpikeSlabPrior) -> float:
    """``log p(Y | psi, v_s)``, Eq. (29b) (Eq. (29a) when no term is active), with its constants.

    ``L (N, K)``, ``y (N,)``, ``psi (K,)`` bool. Forms the N x N matrix
    ``I - L_r Sigma_theta L_r^T`` of the paper, ``Sigma_theta (r, r)`` without ``sigma2``.
    """
    N = y.shape[0]
    Lr = L[:, psi]
    r = Lr.shape[1]
    sigma_theta = np.linalg.inv(Lr.T @ Lr + np.eye(r) / v_s)
    H = np.eye(N) - Lr @ sigma_theta @ Lr.T
    shape = prior.a_sigma + 0.5 * N
    const = gammaln(shape) + prior.a_sigma * np.log(prior.b_sigma) - gammaln(prior.a_sigma) - 0.5 * N * np.log(2 * np.pi)
    # (|R_0^-1| |Sigma_theta|)^(1/2) / vartheta_s^(h_z/2), with R_0 = I.
    log_det = 0.5 * np.linalg.slogdet(sigma_theta)[1] - 0.5 * r * np.log(v_s)
    return const + log_det - shape * np.log(prior.b_sigma + 0.5 * y @ H @ y)


def update_indicators(rng, L, y, psi, v_s, p0, prior: SpikeSlabPrior) -> np.ndarray:
    """Steps 6-7: each ``psi_k (K,)`` from ``Bern(p0 / (p0 + lambda (1 - p0)))``, in order."""
    psi = psi.copy()
    for k in range(psi.size):
        off, on = psi.copy(), psi.copy()
        off[k], on[k] = False, True
        log_lambda = log_marginal(L, y, off, v_s, prior) - log_marginal(L, y, on, v_s, prior)
        # p0 / (p0 + lambda (1 - p0)) in logs: lambda overflows for decisive data.
        u_k = expit(np.log(p0) - np.log1p(-p0) - log_lambda)
        psi[k] = rng.uniform() < u_k
    return psi


def init(K: int) -> dict:
    """Steps 2-3 and the initial hyperparameters: every term active, ``p0 = 0.1``, ``v_s = 10``."""
    return {"psi": np.ones(K, bool), "v_s": 10.0, "p0": 0.1}


def sweep(rng, L: np.ndarray, y: np.ndarray, state: dict, prior: SpikeSlabPrior) -> dict:
    """One iteration of Algorithm 1 (steps 6-11). ``state``: psi (K,) bool, v_s, p0.

    Returns the new state plus ``theta (K,)`` (zero off the active set) and ``sigma2``.
    """
    K = L.shape[1]
    N = y.shape[0]
    psi = update_indicators(rng, L, y, state["psi"], state["v_s"], state["p0"], prior)
    Lr = L[:, psi]
    r = Lr.shape[1]
    sigma_theta = np.linalg.inv(Lr.T @ Lr + np.eye(r) / state["v_s"])  # (r, r), without sigma2
    mu = sigma_theta @ (Lr.T @ y)
    # Step 8: Y^T Y - mu^T Sigma_theta^-1 mu, the residual sum of squares of the ridge fit.
    resid = y @ y - mu @ np.linalg.solve(sigma_theta, mu)
    sigma2 = (prior.b_sigma + 0.5 * resid) / rng.gamma(prior.a_sigma + 0.5 * N)
    # Step 11 (before step 9, see the module docstring).
    theta_r = rng.multivariate_normal(mu, sigma2 * sigma_theta) if r else np.zeros(0)
    # Step 9: R_0 = I.
    v_s = (prior.b_v + 0.5 * theta_r @ theta_r / sigma2) / rng.gamma(prior.a_v + 0.5 * r)
    # Step 10.
    p0 = rng.beta(prior.a_p + r, prior.b_p + K - r)
    theta = np.zeros(K)
    theta[psi] = theta_r
    return {"psi": psi, "v_s": v_s, "p0": p0, "theta": theta, "sigma2": sigma2}


def run(L, y, num_sweeps: int, seed: int = 0, prior: SpikeSlabPrior = SpikeSlabPrior()) -> dict:
    """``num_sweeps`` iterations of Algorithm 1 on ``L (N, K)``, ``y (N,)`` (no burn-in removed).

    Returns arrays with a leading ``(num_sweeps,)`` axis: ``gamma (S, K)`` bool,
    ``theta (S, K)``, ``sigma2 (S,)``, ``v_s (S,)``, ``p0 (S,)``.
    """
    L = np.asarray(L, float)
    y = np.asarray(y, float)
    rng = np.random.default_rng(seed)
    state = init(L.shape[1])
    draws = []
    for _ in range(num_sweeps):
        state = sweep(rng, L, y, state, prior)
        draws.append(state)
    out = {name: np.array([d[name] for d in draws]) for name in ("theta", "sigma2", "v_s", "p0")}
    out["gamma"] = np.array([d["psi"] for d in draws])
    return out


def reuse_freed_memory() -> None:
    """Let glibc's malloc serve the N x N matrices from memory it already holds.

    By default glibc maps every block above its mmap threshold (128 kB, raised only when a
    larger mapped block is freed) fresh from the kernel, and its first touch costs a page fault
    per 4 kB: a sweep at K = 36, N = 1e3 took 0.27 s in a fresh process and 0.045 s with these
    thresholds (or after any unrelated array of more than 8 MB had been freed). Fixing them
    makes the baseline's timing reproducible and as fast as this code gets. Process-wide; a
    no-op without glibc.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # mallopt parameter numbers (malloc.h)
    libc.mallopt(m_mmap_threshold, 32 * 2**20)  # the largest glibc accepts
    libc.mallopt(m_trim_threshold, 256 * 2**20)


def time_per_sweep(K: int, N: int, sweeps: int = 3, seed: int = 0) -> float:
    """Seconds per sweep on :func:`make_problem`'s ``(K, N)`` problem, averaged over ``sweeps``
    sweeps after one untimed sweep (the first starts from the full model, r = K, and costs
    more than the sweeps of a chain near its posterior, where r is the true support size).
    Calls :func:`reuse_freed_memory` first."""
    reuse_freed_memory()
    L, y = make_problem(K, N, seed)
    rng = np.random.default_rng(seed)
    prior = SpikeSlabPrior()
    state = sweep(rng, L, y, init(K), prior)
    start = time.perf_counter()
    for _ in range(sweeps):
        state = sweep(rng, L, y, state, prior)
    return (time.perf_counter() - start) / sweeps
