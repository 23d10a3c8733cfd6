"""A peer benchmark: dtwin-jax's default route against pysindy (STLSQ, ensemble STLSQ, SBR,
weak-form STLSQ) on the zoo members (`dtwin_jax.models.zoo`), same data, same candidate terms.

    pip install -e .[peers]        # pysindy>=2.1
    python benchmarks/peers.py --members 24 --seed 0 --duration 2 \\
        [--layouts accelerations states] [--chains 2 --draws 1000 --burn-in 500] \\
        [--sbr-warmup 500 --sbr-samples 1000] [--json out.json] [--md out.md]

Member `i` is `zoo.draw_member(seed + i)`, simulated and measured exactly as
`benchmarks/zoo.py` does (same keys, the member's own 2-5% noise on states, rates and
inputs), in two sensor layouts: `accelerations` (every state and rate measured) and
`states` (every state, no rates). Every method regresses the perturbation of each velocity
equation, `v' - f_nominal(x, u)`, on the member's library `ex.library` (19 columns for an
SDOF member, 61 for a chain) and is scored by `benchmarks/zoo.py`'s `score()`: exact
support, relative error `|coef / truth - 1|` of every true coefficient (a dropped true
term counts 100%), and 95% interval coverage where a method gives intervals.

**dtwin-jax**: `update_input_output(nominal, t, x, u, xdot, library=ex.library)` as
`benchmarks/zoo.py` runs it (accelerations: kinematic smoother with the measured rates;
states: its weak form, chosen automatically), `--chains x --draws, --burn-in`.

**pysindy** gets the same library columns as features (its optimizers on the design
matrix; its `WeakPDELibrary(IdentityLibrary())` for the weak form) and the nominal-removed
target. The nominal part is removed through `y = v - integral of f_nominal` (trapezoid for
the state part, the input held over each sample as the zoo simulates it), so that
`y' = v' - f_nominal` is the perturbation alone:

* target, `accelerations`: the measured rate minus `f_nominal` at the measured states and
  inputs, sample by sample; library on the measured states (what `SINDy.fit(x, x_dot=...)`
  would use);
* target, `states`: `SmoothedFiniteDifference()` (pysindy's default Savitzky-Golay, 11
  samples, order 3) of `y`; library on the states smoothed by the same smoother (what
  `SINDy` uses with `save_smooth=True`, its default);
* weak form (`states` only: it uses no rates, so the `accelerations` row would be the same
  numbers): target `WeakPDELibrary.convert_u_dot_integral(y)` (the test functions
  integrated by parts onto `y`: nothing differentiated), features the weak integrals of the
  library columns on the measured states; pysindy's defaults `K = 100` subdomains,
  `H_xt = T / 20`, `p = 4`, `np.random.seed(member seed)`.

**Fixed rule for the hyperparameters** (not tuned per member): each library column and
each target column is divided by its RMS before the fit (coefficients scaled back after),
so a coefficient is the share of the target's RMS a unit-RMS term carries, and pysindy's
defaults apply in those units: `STLSQ(threshold=0.1, alpha=0.05)` (a term carrying under 10%
of the target's RMS is cut); `EnsembleOptimizer(STLSQ(...), bagging=True, n_models=100)`
(bootstrap of the samples, median of the 100 models as pysindy aggregates them, 95%
interval = 2.5-97.5 percentiles of the 100 models); `SBR()` with its default priors
(`tau0 = 0.1`, slab `nu = 4, s = 2`, noise rate 1: suited to unit-RMS data), 1 NUTS chain,
`--sbr-warmup` / `--sbr-samples`; the coefficient is the posterior mean, the interval the
95% HDI of the draws, and a term is selected when that HDI excludes 0 (SBR sets no exact
zeros). STLSQ and weak STLSQ give no intervals: their coverage is not defined.

Prints one line per member, layout and method, then a markdown table by method and layout;
`--json` writes every row, `--md` the table with the command and the machine.
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/zoo.py

try:
    import pysindy as ps
except ImportError:
    sys.exit("benchmarks/peers.py needs pysindy: pip install -e .[peers]")

import jax
import numpy as np
import zoo as zoo_benchmark  # benchmarks/zoo.py: _layout, score

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax import SamplerSettings, update_input_output
from dtwin_jax.library import parse_library
from dtwin_jax.models import systems, zoo
from dtwin_jax.preprocess.measurement import measure

LAYOUTS = ("accelerations", "states")
METHODS = ("dtwin-jax", "STLSQ", "ensemble STLSQ", "SBR", "weak STLSQ")
INTERVALS = {"dtwin-jax": "95% HDI", "ensemble STLSQ": "2.5-97.5 percentiles", "SBR": "95% HDI"}
THRESHOLD = 0.1  # STLSQ threshold in units of the target's RMS (unit-RMS columns)
N_MODELS = 100  # ensemble size


class Equation(NamedTuple):
    """The fields of `dtwin_jax` posteriors that `benchmarks/zoo.py`'s `score()` reads."""

    kind: str
    state: str
    names: tuple
    selected: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    pip: np.ndarray
    hdi_95: np.ndarray


def _data(member: zoo.Member, duration: float | None):
    """The member's simulation and measurements, with `benchmarks/zoo.py`'s keys."""
    ex = member.example
    sim = systems.simulate_example(ex, jax.random.fold_in(jax.random.key(member.seed), 1), duration=duration)
    return measure(jax.random.fold_in(jax.random.key(member.seed), 2), sim["t"], sim["x"], sim["xdot"], sim["u"],
                   level=member.noise_level)


def _dtwin(member, meas, layout, settings):
    nominal = member.example.system.nominal
    x, x_names, xdot, xdot_names = zoo_benchmark._layout(nominal, layout, meas)
    return update_input_output(nominal, meas.t, x, meas.u, xdot, x_names=x_names, xdot_names=xdot_names,
                               library=member.example.library, settings=settings, seed=member.seed).equations


def _nominal_removed(nominal, t, x, u):
    """`y = v - integral of f_nominal (N, r)` of the regressed states, `y(0) = v(0)`.

    The state part of `f_nominal` by the trapezoid rule, the input part held over each
    sample (`u_k` on `[t_k, t_k+1)`, as `systems.simulate_example` drives the system)."""
    idx = list(nominal.regressed_index)
    zero_x, zero_u = np.zeros_like(x), np.zeros_like(u)
    f_const = np.asarray(nominal.rate_batch(zero_x, zero_u))[:, idx]
    f_x = np.asarray(nominal.rate_batch(x, zero_u))[:, idx] - f_const
    f_u = np.asarray(nominal.rate_batch(zero_x, u))[:, idx]  # input and constant force
    dt = np.diff(t)[:, None]
    steps = 0.5 * (f_x[1:] + f_x[:-1]) * dt + f_u[:-1] * dt
    integral = np.concatenate([np.zeros((1, len(idx))), np.cumsum(steps, axis=0)])
    return x[:, idx] - integral


def _rms(a):
    r = np.sqrt(np.mean(a**2, axis=0))
    return np.where(r > 0, r, 1.0)


def _hdi(draws, prob=0.95):
    """Shortest interval holding `prob` of the draws `(S, ...)`: `(..., 2)`."""
    s = np.sort(draws, axis=0)
    n = s.shape[0]
    k = int(np.ceil(prob * n))
    widths = s[k - 1:] - s[: n - k + 1]
    lo_index = np.argmin(widths, axis=0)
    lo = np.take_along_axis(s, lo_index[None], axis=0)[0]
    hi = np.take_along_axis(s, (lo_index + k - 1)[None], axis=0)[0]
    return np.stack([lo, hi], axis=-1)


def _fit(method, theta, target, seed, sbr_warmup, sbr_samples):
    """`coef (r, K)`, `interval (r, K, 2)` (NaN: none) and `selected (r, K)` of one pysindy
    optimizer on unit-RMS columns and targets, scaled back to the data's units."""
    col, tgt = _rms(theta), _rms(target)
    a, b = theta / col, target / tgt
    r, K = target.shape[1], theta.shape[1]
    interval = np.full((r, K, 2), np.nan)
    np.random.seed(seed)
    if method in ("STLSQ", "weak STLSQ"):
        opt = ps.STLSQ(threshold=THRESHOLD).fit(a, b)
        coef = np.atleast_2d(opt.coef_)
        selected = coef != 0
    elif method == "ensemble STLSQ":
        opt = ps.EnsembleOptimizer(ps.STLSQ(threshold=THRESHOLD), bagging=True, n_models=N_MODELS).fit(a, b)
        coef = np.atleast_2d(opt.coef_)
        models = np.stack([np.atleast_2d(c) for c in opt.coef_list])  # (n_models, r, K)
        interval = np.stack([np.percentile(models, 2.5, axis=0), np.percentile(models, 97.5, axis=0)], axis=-1)
        selected = coef != 0
    elif method == "SBR":
        opt = ps.SBR(num_warmup=sbr_warmup, num_samples=sbr_samples,
                     mcmc_kwargs={"seed": seed, "progress_bar": False}).fit(a, b)
        coef = np.atleast_2d(opt.coef_)
        draws = np.asarray(opt.mcmc_.get_samples()["beta"]).reshape(-1, r, K)
        interval = _hdi(draws)
        selected = (interval[..., 0] > 0) | (interval[..., 1] < 0)
    else:
        raise ValueError(method)
    scale = tgt[:, None] / col[None, :]
    return coef * scale, interval * scale[..., None], selected


def _pysindy(method, member, meas, layout, sbr_warmup, sbr_samples):
    """The equations of one pysindy method on one member and layout."""
    ex = member.example
    nominal = ex.system.nominal
    lib = parse_library(ex.library, nominal.m, nominal.n)
    idx = list(nominal.regressed_index)
    t, x, u = np.asarray(meas.t), np.asarray(meas.x), np.asarray(meas.u)
    if method == "weak STLSQ":
        y = _nominal_removed(nominal, t, x, u)
        weak = ps.WeakPDELibrary(function_library=ps.IdentityLibrary(), spatiotemporal_grid=t)  # draws subdomains
        theta = np.asarray(weak.fit_transform(np.asarray(lib(x, u))))
        target = np.asarray(weak.convert_u_dot_integral(ps.AxesArray(y, {"ax_time": 0, "ax_coord": 1})))
    elif layout == "accelerations":
        theta = np.asarray(lib(x, u))
        target = np.asarray(meas.xdot)[:, idx] - np.asarray(nominal.rate_batch(x, u))[:, idx]
    else:
        target = ps.SmoothedFiniteDifference()._differentiate(_nominal_removed(nominal, t, x, u), t)
        smoother = ps.SmoothedFiniteDifference()
        smoother._differentiate(x, t)
        theta = np.asarray(lib(np.asarray(smoother.smoothed_x_), u))
    coef, interval, selected = _fit(method, theta, np.asarray(target), member.seed, sbr_warmup, sbr_samples)
    names = nominal.state_names
    nan = np.full(lib.K, np.nan)
    return [Equation("drift", names[i], lib.names, selected[j], coef[j], nan, selected[j].astype(float), interval[j])
            for j, i in enumerate(idx)]


def _failed(member, error):
    return {"support_exact": False, "support": {}, "failure": f"{type(error).__name__}: {error}",
            "terms": [{"state": s, "term": t, "truth": c, "covered": False, "error": 1.0}
                      for s, terms in member.example.true_terms.items() for t, c in terms.items()]}


def stats(rows, method) -> tuple:
    """`(members, exact %, median error %, p90 error %, coverage % or NaN, seconds/member)`."""
    errors = np.array([t["error"] for r in rows for t in r["terms"]])
    covered = [t["covered"] for r in rows for t in r["terms"]]
    coverage = 100 * np.mean(covered) if method in INTERVALS and covered else float("nan")
    return (len(rows), 100 * np.mean([r["support_exact"] for r in rows]), 100 * np.median(errors),
            100 * np.percentile(errors, 90), coverage, np.mean([r["seconds"] for r in rows]))


def table(rows) -> str:
    lines = ["| method | layout | members | exact support % | median error % | p90 error % | 95% interval coverage % | s / member |",
             "|---|---|---|---|---|---|---|---|"]
    for method in METHODS:
        for layout in LAYOUTS:
            group = [r for r in rows if r["method"] == method and r["layout"] == layout]
            if group:
                n, exact, med, p90, cover, sec = stats(group, method)
                cov = "n/a" if np.isnan(cover) else f"{cover:.0f}"
                lines.append(f"| {method} | {layout} | {n} | {exact:.0f} | {med:.2f} | {p90:.1f} | {cov} | {sec:.2f} |")
    return "\n".join(lines)


def family_table(rows) -> str:
    """Exact support % by family (columns) and method / layout (rows)."""
    families = [f for f in zoo.FAMILIES if any(r["family"] == f for r in rows)]
    lines = ["| method | layout | " + " | ".join(families) + " |", "|---|---|" + "---|" * len(families)]
    for method in METHODS:
        for layout in LAYOUTS:
            group = [r for r in rows if r["method"] == method and r["layout"] == layout]
            if group:
                cells = []
                for f in families:
                    g = [r["support_exact"] for r in group if r["family"] == f]
                    cells.append(f"{sum(g)}/{len(g)}")
                lines.append(f"| {method} | {layout} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--members", type=int, default=24)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=2.0, help="window length in s")
    p.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=list(LAYOUTS))
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument("--chains", type=int, default=2)
    p.add_argument("--draws", type=int, default=1000)
    p.add_argument("--burn-in", type=int, default=500)
    p.add_argument("--sbr-warmup", type=int, default=500)
    p.add_argument("--sbr-samples", type=int, default=1000)
    p.add_argument("--json", default=None)
    p.add_argument("--md", default=None)
    a = p.parse_args()
    settings = SamplerSettings(num_chains=a.chains, num_draws=a.draws, num_burnin=a.burn_in)
    print(f"{a.members} members from seed {a.seed}, {a.duration} s; layouts {a.layouts}; dtwin-jax {a.chains} chains x "
          f"{a.draws} draws, {a.burn_in} burn-in; SBR {a.sbr_warmup} warmup, {a.sbr_samples} samples; pysindy "
          f"{ps.__version__}", flush=True)
    rows = []
    for i in range(a.members):
        member = zoo.draw_member(a.seed + i)
        meas = _data(member, a.duration)
        for layout in a.layouts:
            for method in a.methods:
                if method == "weak STLSQ" and layout != "states":
                    continue  # no rates used: the same numbers as in the states layout
                start = time.perf_counter()
                try:
                    if method == "dtwin-jax":
                        eqs = _dtwin(member, meas, layout, settings)
                    else:
                        eqs = _pysindy(method, member, meas, layout, a.sbr_warmup, a.sbr_samples)
                    row = zoo_benchmark.score(member, eqs) | {"failure": None}
                except Exception as e:  # a failed fit is a result too: scored as wrong
                    row = _failed(member, e)
                seconds = time.perf_counter() - start
                row = {"method": method, "layout": layout, "name": member.example.name, "family": member.family,
                       "seed": member.seed, "noise_level": member.noise_level, "seconds": seconds} | row
                rows.append(row)
                errors = ", ".join(f"{t['term']} {100 * t['error']:.1f}%" for t in row["terms"])
                extra = {s: v["selected"] for s, v in row["support"].items() if not v["exact"]}
                print(f"{member.example.name} {layout} {method}: support "
                      f"{'ok' if row['support_exact'] else 'WRONG ' + str(extra)}; {errors}; {seconds:.1f} s"
                      + (f"; FAILED {row['failure']}" if row["failure"] else ""), flush=True)
    out = table(rows)
    print()
    print(out)
    print()
    print(family_table(rows), flush=True)
    config = {"members": a.members, "seed": a.seed, "duration": a.duration, "layouts": a.layouts,
              "methods": a.methods, "settings": {"chains": a.chains, "draws": a.draws, "burn_in": a.burn_in},
              "sbr": {"warmup": a.sbr_warmup, "samples": a.sbr_samples}, "stlsq_threshold": THRESHOLD,
              "ensemble_models": N_MODELS, "pysindy": ps.__version__,
              "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores, CPU"}
    if a.json:
        with open(a.json, "w") as f:
            json.dump(config | {"rows": rows}, f, indent=1, default=float)
    if a.md:
        with open(a.md, "w") as f:
            f.write("# Peer benchmark: dtwin-jax against pysindy on the zoo\n\n"
                    f"    python benchmarks/peers.py {' '.join(sys.argv[1:])}\n\n"
                    f"pysindy {ps.__version__}; {config['machine']}. Set-up and the fixed hyperparameter rules: "
                    "the docstring of `benchmarks/peers.py`. `s / member`: wall seconds per fit, compilation "
                    f"included, on a machine shared with other jobs.\n\n{out}\n\n"
                    f"Exact support by family (members with exactly the true terms):\n\n{family_table(rows)}\n")


if __name__ == "__main__":
    main()
