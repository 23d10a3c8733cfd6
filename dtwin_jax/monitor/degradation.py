"""Degradation over service time: a coefficient's trend across a monitor's windows,
extrapolated with its uncertainty to a critical level, gives the remaining useful life.

Each window's own estimate of the coefficient (``window_estimates`` in the timeline:
least squares on that window alone, so independent from window to window) is one point
``c_w +- s_w`` at service time ``t_w``. A straight line ``c(t) = a + b t`` is fitted by
weighted least squares; the standard errors' common scale ``phi`` is unknown (a model that
fits worse than its noise), with a scaled-inverse-chi-square posterior that ``PRIOR_DOF``
pseudo-windows pull towards 1, truncated at 1: a window's own standard error is a floor (its
residuals are taken as white), and a scatter smaller than it is chance, not precision. Draws of ``(phi, a, b)`` give
draws of the time the line reaches the critical level; the remaining life is that time less
now (zero once past it, infinite where the line heads away from the level).
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

    - ``timeline``: :attr:`Monitor.timeline <dtwin_jax.monitor.Monitor.timeline>` (or the
      ``windows`` of a ``MONITOR.json``).
    - ``term``: ``"state:term"``, like ``"x2:x1"`` (the stiffness of an SDOF, in
      acceleration units: ``-K / M`` is the nominal's share, this the perturbation's).

    **Returns:** ``t`` (the windows' ``t_start``, s), ``mean`` and ``sd`` ``(W,)`` over the
    windows that estimated it, and ``index`` (their timeline indices).
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


TRENDS = {"linear": 1, "quadratic": 2}


def remaining_life(t, mean, sd, critical: float, *, now: float | None = None, level: float = 0.9,
                   trend: str = "linear", num_draws: int = 20000, seed: int = 0) -> dict:
    """When a coefficient's trend reaches ``critical``, with its uncertainty.

    **Arguments:**

    - ``t``, ``mean``, ``sd``: ``(W,)`` service times (s) and the window-alone estimates
      with their standard errors (:func:`coefficient_track`); at least 3 windows.
    - ``critical``: the level at which the structure has failed (same units).
    - ``now``: the service time the remaining life counts from (default the last window's).
    - ``level``: the probability of the interval (default 0.9).
    - ``trend``: ``"linear"`` (a straight line) or ``"quadratic"`` (a loss that speeds up or
      slows down, as a crack's does: wider intervals, from the curvature's uncertainty).
    - ``num_draws``, ``seed``: Monte Carlo draws of the trend.

    **Returns:** ``failure_time`` (the draws, s; ``inf`` where the trend heads away),
    ``median``, ``lower``, ``upper`` (the failure time's quantiles at ``(1 - level) / 2``, 0.5
    and ``(1 + level) / 2``), ``rul_median``, ``rul_lower``, ``rul_upper`` (the same less ``now``, at least
    0), ``slope`` and ``slope_sd`` (per s, now), ``scale`` (the posterior mean of ``phi``, at least
    1) and the fitted ``line`` (its coefficients in powers of ``t - now``: ``(a, b)`` or ``(a, b, c)``).
    """
    if trend not in TRENDS:
        raise DataError(f"unknown trend {trend!r}; expected one of {', '.join(TRENDS)}")
    degree = TRENDS[trend]
    t, mean, sd = (np.asarray(a, dtype=float) for a in (t, mean, sd))
    W = t.size
    if W < degree + 2 or mean.shape != t.shape or sd.shape != t.shape:
        raise DataError(f"a {trend} trend needs at least {degree + 2} windows' estimates of the same shape, got {W}")
    now = float(t[-1]) if now is None else float(now)
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
    failure = now + ahead
    if not 0.0 < level < 1.0:
        raise DataError(f"the interval's level must be in (0, 1), got {level:g}")
    q = np.quantile(failure, [(1 - level) / 2, 0.5, (1 + level) / 2], method="inverted_cdf")  # no interpolation: inf stays inf
    return {"failure_time": failure, "lower": float(q[0]), "median": float(q[1]), "upper": float(q[2]),
            "rul_lower": float(max(q[0] - now, 0.0)), "rul_median": float(max(q[1] - now, 0.0)),
            "rul_upper": float(max(q[2] - now, 0.0)), "slope": float(coef[1]),
            "slope_sd": float(np.sqrt(np.mean(phi) * np.linalg.inv(A)[1, 1])), "scale": float(np.mean(phi)),
            "line": tuple(float(c) for c in coef), "now": now, "critical": float(critical), "trend": trend}


def _first_crossing(line, critical: float) -> np.ndarray:
    """The first ``tau > 0`` where ``sum_p line[:, p] tau^p`` reaches ``critical`` (``inf``
    where it never does), for lines of degree 1 or 2 ``(draws, 2 or 3)``."""
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
