"""Degradation over service time: a coefficient's trend across a monitor's windows,
extrapolated with its uncertainty to a critical level, gives the remaining useful life.

Each window's own estimate of the coefficient (`window_estimates` in the timeline:
least squares on that window alone, so independent from window to window) is one point
`c_w +- s_w` at service time `t_w`. A straight line `c(t) = a + b t` is fitted by
weighted least squares; the standard errors' common scale `phi` is unknown (a model that
fits worse than its noise), with a scaled-inverse-chi-square posterior that `PRIOR_DOF`
pseudo-windows pull towards 1, truncated at 1: a window's own standard error is a floor (its
residuals are taken as white), and a scatter smaller than it is chance, not precision. Draws of `(phi, a, b)` give
draws of the time the line reaches the critical level; the remaining life is that time less
now (zero once past it, infinite where the line heads away from the level).

A structure whose damage grows with a random loading (a crack) does not follow a line: its
loss is a drift plus a random walk, and the time it reaches the level depends on the loads
to come. `trend="wiener"` fits that walk to the track (a Wiener process with drift seen
through the windows' errors) and draws the failure time from its first passage (inverse
Gaussian), so the interval holds the future loads' spread as well as the fit's.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from dtwin_jax.errors import DataError

__all__ = ["PRIOR_DOF", "TRENDS", "coefficient_track", "remaining_life"]

# Pseudo-windows behind the prior "the windows' standard errors are right" (phi = 1).
PRIOR_DOF = 2.0


def coefficient_track(timeline: list[dict], term: str) -> dict:
    """One coefficient's window-alone estimates over a monitor's timeline.

    **Arguments:**

    - `timeline`: the monitor's window entries, `Monitor.timeline`
      (`dtwin_jax.monitor.Monitor.timeline`), or the `windows` of a `MONITOR.json`.
    - `term`: `"state:term"`, like `"x2:x1"` (the stiffness of an SDOF, in
      acceleration units: `-K / M` is the nominal's share, this the perturbation's); terms are
      named as in the library, states `x1 .. xm`.

    **Returns:** a dict: `t` (the windows' `t_start`, s), `mean` and `sd` (the estimates and
    their standard errors, the coefficient's units), each `(W,)` over the `W` windows that
    estimated it, and `index` `(W,)` int (their timeline indices). Raises `DataError` where
    `term` is not `"state:term"` or no window estimated it.
    """
    state, sep, expr = term.partition(":")
    if not sep:
        raise DataError(f"a tracked term is 'state:term', like 'x2:x1'; got {term!r}")
    rows = []
    for w in timeline:
        for e in w.get("window_estimates", []):
            if e.get("state") == state and expr in e.get("terms", {}):
                mean, sd = e["terms"][expr]
                if np.isfinite(mean) and np.isfinite(sd) and sd > 0:
                    rows.append((w["t_start"], mean, sd, w["index"]))
    if not rows:
        raise DataError(f"no window estimated {term!r} (terms are named as in the library, states x1..xm)")
    t, mean, sd, index = (np.array(c) for c in zip(*rows))
    return {"t": t.astype(float), "mean": mean.astype(float), "sd": sd.astype(float), "index": index.astype(int)}


TRENDS = {"linear": 1, "quadratic": 2, "wiener": 1}

# The Wiener trend's grids: phi (the standard errors' scale) and the random walk's variance
# accumulated over the track, in units of a window's mean variance.
_PHI_GRID = np.geomspace(1.0, 100.0, 25)
_WALK_GRID = np.geomspace(1e-3, 1e4, 36)


def _walk_log_prior(r):
    """Flat in the walk's standard deviation over the grid, on `log r`: a tail towards
    no walk would hide a walk that ~20 noisy windows cannot tell from white scatter."""
    return 0.5 * np.log(r)


def remaining_life(t, mean, sd, critical: float, *, now: float | None = None, level: float = 0.9,
                   trend: str = "linear", num_draws: int = 20000, seed: int = 0) -> dict:
    """When a coefficient's trend reaches `critical`, with its uncertainty.

    **Arguments:**

    - `t`: `(W,)` the windows' service times, s (`coefficient_track`'s `t`); at least 3
      windows (4 for a `"quadratic"` trend).
    - `mean`: `(W,)` the window-alone estimates of the coefficient (`coefficient_track`).
    - `sd`: `(W,)` their standard errors, positive (same units).
    - `critical`: the level at which the structure has failed (same units).
    - `now`: the service time, s, the remaining life counts from; None (default): the last
      window's.
    - `level`: the probability of the interval (default 0.9).
    - `trend`: `"linear"` (a straight line), `"quadratic"` (a loss that speeds up or
      slows down: wider intervals, from the curvature's uncertainty) or `"wiener"` (a
      straight drift plus a random walk, the degradation of a structure whose damage grows
      with a random loading, as a crack's does: the walk's variance is fitted to the track
      and the failure time is the walk's first passage, inverse Gaussian given the fit).
    - `num_draws`: the number of Monte Carlo draws of the trend (default 20000).
    - `seed`: the seed of the draws' random generator (default 0).

    **Returns:** a dict: `failure_time` (`(num_draws,)` draws, s; `inf` where the trend heads away),
    `median`, `lower`, `upper` (the failure time's quantiles at `(1 - level) / 2`, 0.5
    and `(1 + level) / 2`), `rul_median`, `rul_lower`, `rul_upper` (the same less `now`, at least
    0), `slope` and `slope_sd` (per s, now), `scale` (the posterior mean of `phi`, at least
    1) and the fitted `line` (its coefficients in powers of `t - now`: `(a, b)` or `(a, b, c)`),
    with `diffusion` (the walk's variance per s, posterior mean) for `"wiener"`, and `now`, `critical`
    and `trend` as given. Raises `DataError` on an unknown trend, too few windows, a level
    outside (0, 1) or non-finite data.
    """
    if trend not in TRENDS:
        raise DataError(f"unknown trend {trend!r}; expected one of {', '.join(TRENDS)}")
    degree = TRENDS[trend]
    t, mean, sd = (np.asarray(a, dtype=float) for a in (t, mean, sd))
    W = t.size
    if W < degree + 2 or mean.shape != t.shape or sd.shape != t.shape:
        raise DataError(f"a {trend} trend needs at least {degree + 2} windows' estimates of the same shape, got {W}")
    if not 0.0 < level < 1.0:
        raise DataError(f"the interval's level must be in (0, 1), got {level:g}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(mean)) and np.all((sd > 0) & np.isfinite(sd))):
        raise DataError("a trend needs finite times and estimates, and positive finite standard errors")
    now = float(t[-1]) if now is None else float(now)
    if trend == "wiener":
        return _wiener_life(t, mean, sd, float(critical), now, level, num_draws, np.random.default_rng(seed))
    X = np.stack([(t - now) ** p for p in range(degree + 1)], axis=1)  # centred at now: a is the level now
    w = 1.0 / sd**2
    A = X.T @ (w[:, None] * X)
    coef = np.linalg.solve(A, X.T @ (w * mean))
    rss = float(np.sum(w * (mean - X @ coef) ** 2))
    dof = PRIOR_DOF + W - (degree + 1)
    rng = np.random.default_rng(seed)
    # Scaled-inverse-chi-square draws given phi >= 1: chi2 = S / phi below S = PRIOR_DOF + rss.
    S = PRIOR_DOF + rss
    phi = S / chi2.ppf(rng.uniform(0.0, 1.0, num_draws) * chi2.cdf(S, dof), dof)
    L = np.linalg.cholesky(np.linalg.inv(A))
    line = coef + np.sqrt(phi)[:, None] * (rng.standard_normal((num_draws, degree + 1)) @ L.T)
    a = line[:, 0]
    healthy = np.sign(critical - mean[0])  # the side of the level the structure started on
    ahead = _first_crossing(line, critical)  # time from now to the crossing
    ahead = np.where(np.isfinite(ahead) & (ahead > 0), ahead, np.inf)  # heading away: never
    ahead = np.where((critical - a) * healthy <= 0, 0.0, ahead)  # past the level already: failed
    return _summary(now + ahead, now, level, critical, trend, slope=float(coef[1]),
                    slope_sd=float(np.sqrt(np.mean(phi) * np.linalg.inv(A)[1, 1])), scale=float(np.mean(phi)),
                    line=tuple(float(c) for c in coef))


def _summary(failure, now, level, critical, trend, **fit) -> dict:
    q = np.quantile(failure, [(1 - level) / 2, 0.5, (1 + level) / 2], method="inverted_cdf")  # no interpolation: inf stays inf
    return {"failure_time": failure, "lower": float(q[0]), "median": float(q[1]), "upper": float(q[2]),
            "rul_lower": float(max(q[0] - now, 0.0)), "rul_median": float(max(q[1] - now, 0.0)),
            "rul_upper": float(max(q[2] - now, 0.0)), **fit, "now": now, "critical": float(critical), "trend": trend}


def _wiener_life(t, mean, sd, critical, now, level, num_draws, rng) -> dict:
    """The `"wiener"` trend: `c(t) = a + b s + sigma B(s)` (`s = t - t_0`, `B` a standard
    Brownian motion) seen as `mean = c(t) + e`, `e ~ N(0, phi sd^2)` independent.

    `(a, b)` have a flat prior and are integrated out (restricted likelihood); `(sigma^2,
    phi)` are weighed on a grid (`sigma` flat over the walk's share of the track, from 1e-3
    to 1e4 windows' variances; `phi` as in the straight line). Each draw takes a grid point,
    `(a, b)` from their Gaussian posterior, the walk's value now given the windows, and the
    first passage from there to `critical`: inverse Gaussian, mean `D / b`, shape
    `D^2 / sigma^2` for the distance `D` (defective when the drift heads away).
    """
    s = t - t[0]
    s_now = now - t[0]
    nu = PRIOR_DOF
    log_prior_phi = -(nu / 2 + 1) * np.log(_PHI_GRID) - nu / (2 * _PHI_GRID) + np.log(_PHI_GRID)  # on log phi
    logw, s2, phi, A, beta, m_now, c_ab, spread = _wiener_grid(s, s_now, mean, sd, log_prior_phi)
    weights = np.exp(logw - logw.max())
    g = rng.choice(weights.size, size=num_draws, p=weights / weights.sum())  # each draw's grid point
    ab = beta[g] + np.einsum("nij,nj->ni", np.linalg.cholesky(np.linalg.inv(A))[g], rng.standard_normal((num_draws, 2)))
    c_now = (ab[:, 0] + ab[:, 1] * s_now + m_now[g] - np.einsum("ni,ni->n", ab, c_ab[g])
             + spread[g] * rng.standard_normal(num_draws))
    healthy = np.sign(critical - mean[0])  # the side of the level the structure started on
    failure = now + _first_passage((critical - c_now) * healthy, ab[:, 1] * healthy, s2[g], rng)
    return _summary(failure, now, level, critical, "wiener", slope=float(np.mean(ab[:, 1])),
                    slope_sd=float(np.std(ab[:, 1])), scale=float(np.mean(phi[g])), diffusion=float(np.mean(s2[g])),
                    line=(float(np.mean(c_now)), float(np.mean(ab[:, 1]))))


def _wiener_grid(s, s_now, mean, sd, log_prior_phi):
    """Every (walk, phi) grid point of the Wiener trend at times `s (W,)` from the first
    window: log prior + restricted likelihood, and what the draws need, batched over the grid."""
    X = np.stack([np.ones_like(s), s], axis=1)
    # Sigma = s2 min(s_i, s_j) + phi diag(sd^2) = D^1/2 U (s2 lam + phi) U^T D^1/2 for every grid
    # point at once (one eigendecomposition): each point's likelihood is then O(W).
    lam, U = np.linalg.eigh(np.minimum(s[:, None], s[None, :]) / np.outer(sd, sd))
    lam = np.maximum(lam, 0.0)
    rot = U.T / sd[None, :]  # U^T D^-1/2
    yt, Xt, kt = rot @ mean, rot @ X, rot @ np.minimum(s, s_now)
    walk = _WALK_GRID * np.mean(sd**2) / max(s[-1], 1e-300)  # sigma^2 per unit time
    s2 = np.repeat(walk, _PHI_GRID.size)
    phi = np.tile(_PHI_GRID, walk.size)
    log_prior = np.repeat(_walk_log_prior(_WALK_GRID), _PHI_GRID.size) + np.tile(log_prior_phi, walk.size)
    w = 1.0 / (s2[:, None] * lam[None, :] + phi[:, None])  # (G, W)
    A = np.einsum("wi,gw,wj->gij", Xt, w, Xt)
    beta = np.linalg.solve(A, np.einsum("wi,gw,w->gi", Xt, w, yt)[..., None])[..., 0]
    r = yt[None, :] - beta @ Xt.T
    reml = 0.5 * np.sum(np.log(w), axis=1) - 0.5 * np.linalg.slogdet(A)[1] - 0.5 * np.sum(w * r * r, axis=1)
    # The walk now, sigma B(s_now), given the windows and (a, b): Gaussian conditioning,
    # k^T Sigma^-1 (mean - X ab) with k = s2 min(s, s_now).
    wk = s2[:, None] * w * kt[None, :]
    spread = np.sqrt(np.maximum(s2 * s_now - s2 * (wk @ kt), 0.0))
    return log_prior + reml, s2, phi, A, beta, wk @ yt, wk @ Xt, spread


def _first_passage(distance, drift, s2, rng) -> np.ndarray:
    """Draws of the time a Brownian motion with `drift (n,)` and variance `s2 (n,) > 0` per
    unit time first covers `distance (n,)` (0 where already covered, `inf` where never)."""
    D = np.maximum(distance, 0.0)
    speed = np.abs(drift)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # Heading away, the walk still arrives with probability exp(-2 |b| D / sigma^2), and
        # then as fast as one heading towards it.
        arrives = (drift > 0) | (rng.uniform(size=D.shape) < np.exp(-2.0 * speed * D / s2))
        shape = np.maximum(D**2 / s2, 1e-300)
        walk = np.where(speed > 0, rng.wald(np.maximum(D / np.maximum(speed, 1e-300), 1e-300), shape),
                        D**2 / (s2 * rng.standard_normal(D.shape) ** 2))  # no drift: Levy
    return np.where(D > 0, np.where(arrives, walk, np.inf), 0.0)


def _first_crossing(line, critical: float) -> np.ndarray:
    """The first `tau > 0` where `sum_p line[:, p] tau^p` reaches `critical` (`inf`
    where it never does), for lines of degree 1 or 2 `(draws, 2 or 3)`."""
    a, b = line[:, 0] - critical, line[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        if line.shape[1] == 2:
            return -a / b
        c = line[:, 2]
        disc = b * b - 4.0 * a * c
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        roots = np.stack([(-b - root) / (2.0 * c), (-b + root) / (2.0 * c)])
        roots = np.where(np.isfinite(roots) & (roots > 0), roots, np.inf)
        return np.where(c == 0, np.where(-a / b > 0, -a / b, np.inf), roots.min(axis=0))
