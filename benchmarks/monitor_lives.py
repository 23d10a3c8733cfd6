"""The monitor on simulated service lives of zoo members (issue 28's detection and false-alarm
targets): a zoo term that appears at window k, a 5% stiffness drop at window k, or nothing
(stationary lives). Each life's window 0 is the baseline update; windows 1.. are monitored
(`dtwin_jax.monitor.Monitor`, default settings), 5% noise on every signal.

    taskset -c 0 python benchmarks/monitor_lives.py --kind term --lives 50
    taskset -c 0 python benchmarks/monitor_lives.py --kind stiffness --lives 50
    taskset -c 0 python benchmarks/monitor_lives.py --kind stationary --lives 50 --windows 21
    taskset -c 0 python benchmarks/monitor_lives.py --kind weakening --lives 50 --windows 20

Prints one line per life and the summary; `--out` appends the summary (markdown) to a file.
"""

import argparse
import json
import time

import jax
import numpy as np

import dtwin_jax  # noqa: F401  (float64)
from dtwin_jax.models import zoo
from dtwin_jax.models.lives import simulate_life
from dtwin_jax.monitor import FALSE_ALARM, MONITOR_SETTINGS, Monitor
from dtwin_jax.monitor.degradation import TRENDS as DEGRADATION_TRENDS
from dtwin_jax.monitor.degradation import coefficient_track, remaining_life
from dtwin_jax.update.from_data import update_from_data


def _schedules(kind, W, k, failure=None):
    scale, stiffness = np.ones(W), np.ones(W)
    if kind == "term":
        scale[:k] = 0.0
    elif kind == "stiffness":
        stiffness[k:] = 0.95
    elif kind == "weakening":  # a straight loss that reaches CRITICAL_LOSS at the failure time
        stiffness = 1.0 - CRITICAL_LOSS * np.arange(W) / failure
    return scale, stiffness


# The weakening spring fails when it has lost this share of its stiffness.
CRITICAL_LOSS = 0.2


def _layout(window, layout):
    if layout == "accelerations":
        return window
    if layout == "states":
        return {k: v for k, v in window.items() if k != "xdot"}
    if layout == "accelerometers":
        return {k: v for k, v in window.items() if k != "x"}
    raise ValueError(layout)


def life(seed, kind, W, k, layout, framework, false_alarm, forget, seconds, stop_at_detection=False):
    member = zoo.draw_member(seed)
    ex = member.example._replace(duration=seconds)
    failure = float(np.random.default_rng(seed).uniform(1.5, 3.0) * W * seconds) if kind == "weakening" else None
    scale, stiffness = _schedules(kind, W, k, failure and failure / seconds)
    output_only = framework == "output-only"
    windows = simulate_life(ex, jax.random.key(seed), scale=scale, stiffness=stiffness, level=0.05,
                            output_only=output_only)
    mode = "output-only" if output_only else "input-output"
    library = ex.library_output_only if output_only else ex.library
    data = [_layout(w, layout) for w in windows] if not output_only else [
        {"t": w["t"], "x": w["x"]} if layout == "states" else {"t": w["t"], "xdot": w["xdot"],
                                                               "xdot_names": w["xdot_names"]} for w in windows]
    base = update_from_data(mode, ex.system.nominal, data[0], library=library, settings=MONITOR_SETTINGS)
    mon = Monitor(base, false_alarm=false_alarm, forget=forget)
    t0 = time.perf_counter()
    entries = []
    for i, d in enumerate(data[1:], start=1):
        entries.append(mon.step(d, source=f"w{i}"))
        # What follows the first alarm at or after the change cannot change the life's result.
        if stop_at_detection and kind in ("term", "stiffness") and i >= k and entries[-1]["alarm"]:
            break
    alarms = [i for i, e in enumerate(entries, start=1) if e["alarm"]]
    if kind == "weakening":  # the remaining life at the last window, from the stiffness's trend
        nominal = ex.system.nominal
        track = coefficient_track(mon.timeline, "x2:x1")
        critical = CRITICAL_LOSS * float(nominal.K[0, 0] / nominal.M[0, 0])
        out = {"seed": seed, "family": member.family, "failure": failure, "alarms": alarms,
               "seconds": time.perf_counter() - t0, "critical": critical,
               "track": {k: track[k].tolist() for k in ("t", "mean", "sd")}}  # to compare trends offline
        for trend in TRENDS:
            rul = remaining_life(track["t"], track["mean"], track["sd"], critical, trend=trend)
            out[trend] = {"lower": rul["lower"], "median": rul["median"], "upper": rul["upper"],
                          "covered": rul["lower"] <= failure <= rul["upper"], "scale": rul["scale"]}
        return out
    before = [i for i in alarms if kind == "stationary" or i < k]
    after = [i for i in alarms if kind != "stationary" and i >= k]
    return {"seed": seed, "family": member.family, "alarms": alarms, "false_alarms": len(before),
            "tested_before": (W - 1) if kind == "stationary" else k - 1,
            "delay": (after[0] - k) if after else None, "seconds": time.perf_counter() - t0,
            "window_seconds": sorted(e["seconds"] for e in entries)[len(entries) // 2],
            "reasons": entries[after[0] - 1]["new_terms"] + entries[after[0] - 1]["changed_terms"] if after else [],
            "p_min": min(e["p_value"] for e in entries)}


# The remaining-life trends compared: every one remaining_life knows.
TRENDS = tuple(DEGRADATION_TRENDS)


def trend_line(trend: str, found: list[tuple[dict, float]]) -> str:
    """One trend's coverage over lives: ``found`` holds each life's interval and true failure time."""
    widths = [(q["upper"] - q["lower"]) / failure if np.isfinite(q["upper"]) else np.inf for q, failure in found]
    return (f"- {trend} trend: true failure time inside the 90% interval **{sum(q['covered'] for q, _ in found)} / "
            f"{len(found)}**; median width {np.median(widths):.0%} of the failure time; median error of the median "
            f"{np.median([abs(q['median'] / failure - 1) for q, failure in found]):.1%}; intervals entirely before "
            f"the failure {sum(q['upper'] < failure for q, failure in found)}, after it "
            f"{sum(q['lower'] > failure for q, failure in found)}")


def report(lines: list[str], out: str | None) -> None:
    """Print the summary's markdown lines, and append them to ``out`` when given."""
    text = "\n".join(lines) + "\n"
    print(text)
    if out:
        with open(out, "a") as f:
            f.write(text + "\n")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kind", choices=("term", "stiffness", "stationary", "weakening"), default="term")
    ap.add_argument("--lives", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--windows", type=int, default=11)
    ap.add_argument("--change-at", type=int, default=5)
    ap.add_argument("--within", type=int, default=None, help="detection counts within this many windows "
                    "(default 3 for a term, 5 for the stiffness)")
    ap.add_argument("--layout", default="accelerations", choices=("accelerations", "states", "accelerometers"))
    ap.add_argument("--framework", default="input-output", choices=("input-output", "output-only"))
    ap.add_argument("--seconds", type=float, default=1.0, help="each window's length (s)")
    ap.add_argument("--false-alarm", type=float, default=None, help="default: the monitor's for the framework")
    ap.add_argument("--forget", type=float, default=0.9)
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--stop-at-detection", action="store_true", help="a term or stiffness life ends at its first "
                    "alarm at or after the change (the same result; the seconds per window then leave out the rest)")
    a = ap.parse_args()
    if a.false_alarm is None:  # an explicit 0 goes on to the monitor's one-line error
        a.false_alarm = FALSE_ALARM[a.framework]
    within = a.within or (3 if a.kind == "term" else 5)
    rows = []
    seeds = iter(range(a.first_seed, a.first_seed + 10 * a.lives))
    for seed in (s for s in seeds if a.kind != "weakening" or zoo.draw_member(s).example.system.nominal.d == 1):
        if len(rows) == a.lives:
            break
        r = life(seed, a.kind, a.windows, a.change_at, a.layout, a.framework, a.false_alarm, a.forget, a.seconds,
                 a.stop_at_detection)
        rows.append(r)
        print(json.dumps(r), flush=True)
    if a.kind == "weakening":
        lines = [f"## {a.framework}, {a.layout}, a weakening spring (SDOF members): {a.lives} lives (seeds "
                 f"{a.first_seed}..), {a.windows} windows of {a.seconds:g} s, failure at {CRITICAL_LOSS:.0%} stiffness "
                 "loss, 1.5-3x the monitored time", ""]
        lines += [trend_line(trend, [(r[trend], r["failure"]) for r in rows]) for trend in TRENDS]
        report(lines, a.out)
        if a.json:
            with open(a.json, "w") as f:
                json.dump(rows, f)
        return
    tested = sum(r["tested_before"] for r in rows)
    false = sum(r["false_alarms"] for r in rows)
    lines = [f"## {a.framework}, {a.layout}, {a.kind}: {a.lives} lives (seeds {a.first_seed}..), "
             f"{a.windows} windows of {a.seconds:g} s, change at {a.change_at}, false-alarm {a.false_alarm:g}, forget {a.forget:g}", ""]
    if a.kind != "stationary":
        found = [r for r in rows if r["delay"] is not None and r["delay"] < within]
        lines.append(f"- detected within {within} windows: **{len(found)} / {len(rows)}** "
                     f"(delays: {sorted(r['delay'] for r in rows if r['delay'] is not None)})")
        missed = [f"{r['seed']} {r['family']}" for r in rows if r not in found]
        lines.append(f"- missed: {', '.join(missed) or 'none'}")
    lines.append(f"- false alarms: **{false} in {tested} windows** that followed the twin")
    lines.append(f"- median seconds per window (tested and absorbed): "
                 f"{np.median([r['window_seconds'] for r in rows]):.3f}")
    report(lines, a.out)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f)


if __name__ == "__main__":
    main()
