"""Example 3's crack followed over service time (issue 28): remaining life from the stiffness's trend.

    taskset -c 0 python benchmarks/monitor_crack.py --lives 20

The paper's crack (example 3: stiffness k lambda(D), lambda = 0.5 + 0.5 exp(-D), damage rate
D' = gamma (x1^2 + x2^2), gamma = 0.01) under white force runs on from an undamaged start; the
structure fails when it has lost `--critical` of its stiffness (default 10%: about 90 s). The
monitor sees 1 s windows of the displacement, velocity, acceleration and force (5% noise on
each; the damage is not measured) for the first `--monitored` windows, against the undamaged
SDOF as its nominal, and tracks `x2:x1` (the stiffness lost, in k/m units). Each life draws its
own force. Prints each life's true failure time and the 90% interval at the last window, then
the coverage.

Three trends (`remaining_life(..., trend=)`): a straight line, a parabola, and a drift plus a
random walk (`wiener`). The damage grows with the energy of a random force, so one structure's
failure time depends on the loads still to come (75-109 s over 50 lives): only the walk's
first passage holds that spread. The loss also grows as 1 - exp(-D), slower and slower, so a
line through the early windows runs ahead of the truth (its intervals err early).
"""

import argparse
import json
import time

import jax
import numpy as np
from monitor_lives import TRENDS, report, trend_line

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.models import systems
from dtwin_jax.models.systems import LinearSecondOrder
from dtwin_jax.monitor import MONITOR_SETTINGS, Monitor
from dtwin_jax.monitor.degradation import coefficient_track, remaining_life
from dtwin_jax.preprocess.measurement import add_noise
from dtwin_jax.update.from_data import update_from_data

LIBRARY = "poly:3"


def crack_life(seed: int, windows: int, critical: float, level: float = 0.05, max_windows: int = 400):
    """Simulate until the stiffness loss passes ``critical``; the first ``windows`` measured."""
    ex = systems.example3()
    N = int(round(1.0 / ex.dt))
    t = np.arange(N + 1) * ex.dt
    x0 = np.zeros(3)
    key = jax.random.key(seed)
    xs, xds, us, failure = [], [], [], None
    for i in range(max_windows):
        u = ex.input_std * jax.random.normal(jax.random.fold_in(key, i), (N + 1, 1))
        x, xd = (np.asarray(a) for a in systems.simulate(ex.system, x0, t, u))
        if i < windows:
            xs.append(x[:N]), xds.append(xd[:N]), us.append(np.asarray(u[:N]))
        loss = 0.5 * (1.0 - np.exp(-x[:N, 2]))
        if np.any(loss >= critical):
            failure = i + float(np.flatnonzero(loss >= critical)[0]) * ex.dt
            if i >= windows:
                break
        x0 = x[N]
    keys = jax.random.split(jax.random.fold_in(key, 10**6), 3)
    signals = {"x": np.concatenate(xs)[:, :2], "xdot": np.concatenate(xds)[:, :2], "u": np.concatenate(us)}
    noisy = {name: np.asarray(add_noise(k, a, level)) for k, (name, a) in zip(keys, signals.items())}
    times = np.arange(windows * N) * ex.dt
    data = [{"t": times[i * N:(i + 1) * N], **{k: a[i * N:(i + 1) * N] for k, a in noisy.items()}}
            for i in range(windows)]
    return data, failure


def life(seed: int, windows: int, critical: float, trends=TRENDS) -> dict:
    data, failure = crack_life(seed, windows, critical)
    nominal = LinearSecondOrder.create([[1.0]], [[2.0]], [[2000.0]], [[1.0]])
    base = update_from_data("input-output", nominal, data[0], library=LIBRARY, settings=MONITOR_SETTINGS)
    mon = Monitor(base)
    t0 = time.perf_counter()
    entries = [mon.step(d, source=f"w{i}") for i, d in enumerate(data[1:], start=1)]
    track = coefficient_track(mon.timeline, "x2:x1")
    out = {"seed": seed, "failure": failure, "alarms": [e["index"] for e in entries if e["alarm"]],
           "seconds": time.perf_counter() - t0,
           "track": {k: track[k].tolist() for k in ("t", "mean", "sd")}}  # to compare trends offline
    for trend in trends:
        rul = remaining_life(track["t"], track["mean"], track["sd"], critical * 2000.0, trend=trend)
        out[trend] = {"lower": rul["lower"], "median": rul["median"], "upper": rul["upper"],
                      "covered": bool(rul["lower"] <= failure <= rul["upper"])}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lives", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--monitored", type=int, default=40, help="windows of 1 s monitored (the first is the baseline)")
    ap.add_argument("--critical", type=float, default=0.1, help="the stiffness loss at failure")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None, help="write every life's row (with its track) here")
    a = ap.parse_args()
    rows = []
    for seed in range(a.first_seed, a.first_seed + a.lives):
        r = life(seed, a.monitored, a.critical)
        rows.append(r)
        print(json.dumps(r), flush=True)
    lines = [f"## example 3's crack: {a.lives} lives (seeds {a.first_seed}..), {a.monitored} windows of 1 s monitored, "
             f"failure at {a.critical:.0%} stiffness loss", "",
             f"- true failure times: {min(r['failure'] for r in rows):.0f}-{max(r['failure'] for r in rows):.0f} s"]
    lines += [trend_line(trend, [(r[trend], r["failure"]) for r in rows]) for trend in TRENDS]
    report(lines, a.out)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f)


if __name__ == "__main__":
    main()
