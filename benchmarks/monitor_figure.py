"""The documentation's monitoring figures (docs/monitoring.md):

- `docs/monitor-timeline.png`: zoo member 4 (an SDOF) followed over 15 windows of 1 s, 5%
  noise on every signal: its stiffness drops 5% at window 5 and Coulomb friction appears at
  window 10;
- `docs/monitor-remaining-life.png`: zoo member 2 losing 1% of its stiffness per 1 s
  window, followed over 20 windows: its remaining life to a 20% loss (the truth: 20 s).

    taskset -c 0 python benchmarks/monitor_figure.py
"""

import jax
import numpy as np

import dtwin_jax  # noqa: F401
from dtwin_jax.models import zoo
from dtwin_jax.models.lives import simulate_life
from dtwin_jax.monitor import MONITOR_SETTINGS, Monitor
from dtwin_jax.monitor.degradation import coefficient_track, remaining_life
from dtwin_jax.plots import plot_monitor
from dtwin_jax.update.from_data import update_from_data


def follow(seed, scale, stiffness):
    ex = zoo.draw_member(seed).example
    windows = simulate_life(ex, jax.random.key(seed), scale=scale, stiffness=stiffness)
    mon = Monitor(update_from_data("input-output", ex.system.nominal, windows[0], library=ex.library,
                                   settings=MONITOR_SETTINGS))
    for i, w in enumerate(windows[1:], start=1):
        e = mon.step(w, source=f"w{i:03d}")
        print(f"member {seed} window {i}: alarm {e['alarm']}, p = {e['p_value']:.3g}, new {e['new_terms']}, "
              f"changed {e['changed_terms']}, {e['seconds']:.2f} s")
    return ex, mon


def main():
    W = 15
    ex, mon = follow(4, np.r_[np.zeros(10), np.ones(W - 10)], np.r_[np.ones(5), np.full(W - 5, 0.95)])
    plot_monitor(mon.timeline, "docs/monitor-timeline.png", false_alarm=mon.false_alarm)
    W = 20
    ex, mon = follow(2, np.ones(W), 1.0 - 0.01 * np.arange(W))
    k_over_m = float(ex.system.nominal.K[0, 0] / ex.system.nominal.M[0, 0])
    track = coefficient_track(mon.timeline, "x2:x1")
    rul = remaining_life(track["t"], track["mean"], track["sd"], 0.2 * k_over_m)
    print(f"true failure 20 s; median {rul['median']:.2f} s, 90% interval [{rul['lower']:.2f}, {rul['upper']:.2f}] s")
    plot_monitor(mon.timeline, "docs/monitor-remaining-life.png", false_alarm=mon.false_alarm,
                 remaining=("x2:x1", track, rul))


if __name__ == "__main__":
    main()
