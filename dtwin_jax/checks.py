"""Posterior-predictive residual checks of one regressed equation.

A discovered model that misses a term leaves structure in its residual `e = y - L theta`:
memory (not white), dependence on a state (a missing function of that state) or on the
direction of a velocity (a missing `sign(v)` friction term). `residual_checks` tests
for each, with a Bonferroni threshold over all its tests and a minimum effect size (the
fraction of residual variance the structure explains), so that very long records do not
flag negligible structure.

Samples of a time series are correlated, which makes the usual F and t tests far too
confident; the dependence tests count `n / tau` effective samples, `tau = 1 + 2 sum_k
rho_k` (lags `1..max_lag`, at least 1) the variance inflation of a mean of the residual.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg, stats

__all__ = ["residual_checks"]


def residual_checks(
    residual,
    states,
    velocity_index,
    state_names,
    *,
    max_lag: int = 20,
    alpha: float = 1e-3,
    min_effect: float = 0.01,
    bins: int = 10,
) -> dict:
    """Whiteness, state dependence and velocity-sign dependence of a residual.

    A check fails when its p-value is below `alpha / n_tests` (Bonferroni: `alpha` overall,
    over one whiteness test, one test per state and one per velocity) and its effect, the
    fraction of residual variance it explains beyond what noise alone gives, is at least
    `min_effect`.

    **Arguments:**

    - `residual`: the equation's residual, shape `(N,)` or `(R, N)` (`R` records), in the
      equation's units.
    - `states`: the states at the same samples, shape `(N, m)` or `(R, N, m)`.
    - `velocity_index`: the indices of the velocities among the `m` states; each gets a
      velocity-sign test.
    - `state_names`: the `m` state names, which key the results and name them in warnings.
    - `max_lag`: the number of lags of the whiteness test and of the variance inflation `tau`.
    - `alpha`: the overall significance level of all the tests together.
    - `min_effect`: the smallest fraction of residual variance a failed check must explain.
    - `bins`: the number of quantile bins of each state-dependence test.

    **Returns:** a JSON-ready dict: `ok`, `warnings` (one line per failed check, naming the
    check and the state), `threshold`, `min_effect`, `samples`, `variance_inflation`
    and the results `whiteness`, `state[name]` and `velocity_sign[name]`, each with
    `statistic`, `dof`, `p_value`, `effect` and `flag`.
    """
    e = np.atleast_2d(np.asarray(residual, dtype=float))
    x = np.asarray(states, dtype=float)
    x = x[None] if x.ndim == 2 else x
    if x.shape[:2] != e.shape or x.shape[2] != len(state_names):
        raise ValueError(f"residual {e.shape} and states {x.shape} do not match ({len(state_names)} names)")
    e = e - e.mean(axis=1, keepdims=True)
    z = (e / np.sqrt(np.mean(e**2))).ravel() if np.any(e) else e.ravel()
    flat = x.reshape(-1, x.shape[2])
    rho = pooled_autocorrelation(e, max_lag)
    tau = max(1.0, 1.0 + 2.0 * float(np.sum(rho)))
    n_tests = 1 + x.shape[2] + len(velocity_index)
    threshold = alpha / n_tests

    def judged(result):
        result["flag"] = bool(result["p_value"] < threshold and result["effect"] >= min_effect)
        return result

    white = judged(ljung_box(e, rho, max_lag))
    state = {name: judged(binned_means_test(z, flat[:, j], bins, tau)) for j, name in enumerate(state_names)}
    sign = {state_names[j]: judged(sign_test(z, flat[:, j], tau)) for j in velocity_index}
    warnings = []
    if white["flag"]:
        warnings.append(
            f"whiteness: residual is autocorrelated (Ljung-Box p={white['p_value']:.2g}; "
            f"{100 * white['effect']:.1f}% of its variance predictable from lags 1..{max_lag})"
        )
    warnings += [
        f"state {name}: residual depends on {name} (binned means p={r['p_value']:.2g}; "
        f"{100 * r['effect']:.1f}% of its variance): a missing function of {name}?"
        for name, r in state.items() if r["flag"]
    ]
    warnings += [
        f"sign of {name}: residual mean differs for {name} > 0 and {name} < 0 (Welch p={r['p_value']:.2g}; "
        f"{100 * r['effect']:.1f}% of its variance): a missing sign({name}) term?"
        for name, r in sign.items() if r["flag"]
    ]
    return {
        "ok": not warnings,
        "warnings": warnings,
        "threshold": threshold,
        "min_effect": min_effect,
        "samples": int(z.size),
        "variance_inflation": tau,
        "whiteness": white,
        "state": state,
        "velocity_sign": sign,
    }


def pooled_autocorrelation(e: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocorrelation at lags `1..max_lag` of demeaned records, pooled over records.

    **Arguments:**

    - `e`: demeaned residual records, shape `(R, N)`.
    - `max_lag`: the number of lags.

    **Returns:** the autocorrelations `rho`, shape `(max_lag,)`; zeros when `e` is all zero.
    """
    denom = np.sum(e**2)
    if denom == 0:
        return np.zeros(max_lag)
    return np.array([np.sum(e[:, k:] * e[:, :-k]) for k in range(1, max_lag + 1)]) / denom


def ljung_box(e: np.ndarray, rho: np.ndarray, max_lag: int) -> dict:
    """Ljung-Box whiteness test summed over records (chi-square, `R * max_lag` dof).

    Effect: the fraction of variance the best linear predictor from lags `1..max_lag`
    explains (from the pooled autocorrelation `rho`), less its `max_lag / n` expected
    under white noise (`n` the number of samples).

    **Arguments:**

    - `e`: demeaned residual records, shape `(R, N)`.
    - `rho`: their pooled autocorrelation, shape `(max_lag,)` (`pooled_autocorrelation`).
    - `max_lag`: the number of lags.

    **Returns:** a dict with `statistic`, `dof`, `p_value` and `effect`.
    """
    R, N = e.shape
    lags = np.arange(1, max_lag + 1)
    q = 0.0
    for rec in e:
        d = np.sum(rec**2)
        if d > 0:
            r = np.array([np.sum(rec[k:] * rec[:-k]) for k in lags]) / d
            q += N * (N + 2) * np.sum(r**2 / (N - lags))
    dof = R * max_lag
    r2 = 0.0
    if np.any(rho):
        coef = linalg.solve_toeplitz(np.concatenate([[1.0], rho[:-1]]), rho)
        r2 = float(np.clip(coef @ rho, 0.0, 1.0))
    return {
        "statistic": float(q),
        "dof": dof,
        "p_value": float(stats.chi2.sf(q, dof)),
        "effect": max(0.0, r2 - max_lag / e.size),
    }


def binned_means_test(z: np.ndarray, x: np.ndarray, bins: int, tau: float) -> dict:
    """One-way ANOVA of the standardized residual over quantile bins of one state.

    Any function of `x` missing from the model shifts the bin means. The F statistic and its
    second dof count `n / tau` effective samples. Effect: `eta^2` (between-bin share of the
    variance) less its `(bins - 1) / n` expected under no dependence.

    **Arguments:**

    - `z`: the standardized residual, shape `(n,)`, all records flattened.
    - `x`: one state at the same samples, shape `(n,)`.
    - `bins`: the number of quantile bins (fewer when quantiles coincide).
    - `tau`: the variance inflation, at least 1: `n / tau` effective samples.

    **Returns:** a dict with `statistic` (F), `dof` (`[d1, d2]`), `p_value` and `effect`;
    p-value 1 and effect 0 when there is one bin only or `z` is constant.
    """
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)[1:-1]))
    group = np.searchsorted(edges, x, side="right")
    k = edges.size + 1
    n = z.size
    counts = np.bincount(group, minlength=k)
    means = np.bincount(group, weights=z, minlength=k) / np.maximum(counts, 1)
    total = np.sum((z - z.mean()) ** 2)
    if k < 2 or total == 0:
        return {"statistic": 0.0, "dof": [0, float(n)], "p_value": 1.0, "effect": 0.0}
    between = np.sum(counts * (means - z.mean()) ** 2)
    within = total - between
    n_eff = n / tau
    d1, d2 = k - 1, max(n_eff - k, 1.0)
    f = (between / d1) / max(within / (n - k), 1e-300) / tau
    return {
        "statistic": float(f),
        "dof": [int(d1), float(d2)],
        "p_value": float(stats.f.sf(f, d1, d2)),
        "effect": max(0.0, float(between / total) - d1 / n),
    }


def sign_test(z: np.ndarray, v: np.ndarray, tau: float) -> dict:
    """Welch t test of the standardized residual for `v > 0` against `v < 0`.

    A missing `sign(v)` term (e.g. Coulomb friction) shifts the two groups apart. The test
    counts `n / tau` effective samples. Effect: the share of variance the two group means
    explain, less its `1 / n` expected under no dependence.

    **Arguments:**

    - `z`: the standardized residual, shape `(n,)`, all records flattened.
    - `v`: one velocity at the same samples, shape `(n,)`.
    - `tau`: the variance inflation, at least 1.

    **Returns:** a dict with `statistic` (t), `dof`, `p_value`, `effect`, `mean_positive` and
    `mean_negative` (the mean of `z` where `v > 0` and where `v < 0`); p-value 1 and effect
    0 when either group has fewer than 2 samples.
    """
    pos, neg = z[v > 0], z[v < 0]
    if pos.size < 2 or neg.size < 2:
        return {"statistic": 0.0, "dof": 0.0, "p_value": 1.0, "effect": 0.0,
                "mean_positive": 0.0, "mean_negative": 0.0}
    va, vb = pos.var(ddof=1) / (pos.size / tau), neg.var(ddof=1) / (neg.size / tau)
    t = (pos.mean() - neg.mean()) / np.sqrt(max(va + vb, 1e-300))
    dof = (va + vb) ** 2 / (va**2 / max(pos.size / tau - 1, 1) + vb**2 / max(neg.size / tau - 1, 1))
    n = pos.size + neg.size
    share = pos.size * neg.size / n**2 * (pos.mean() - neg.mean()) ** 2 / max(np.var(z), 1e-300)
    return {
        "statistic": float(t),
        "dof": float(dof),
        "p_value": float(2 * stats.t.sf(abs(t), dof)),
        "effect": max(0.0, float(share) - 1.0 / n),
        "mean_positive": float(pos.mean()),
        "mean_negative": float(neg.mean()),
    }
