"""Figures: posterior inclusion probabilities as stem plots; noise sweeps (Fig. 10);
predictions with their 95% band (Figs. 7-9); degradation forecasts."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_pip", "plot_noise_sweep", "plot_prediction", "plot_degradation", "plot_monitor"]


def _figure(size):
    """A figure outside pyplot: no backend is selected or changed (an interactive session
    keeps its own), and Jupyter still displays the returned figure."""
    from matplotlib.figure import Figure

    return Figure(figsize=size)


def _save(fig, path):
    if path is not None:
        from dtwin_jax.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")  # legends sit outside the axes
    return fig


# Terms whose inclusion probability reaches this are named on PIP plots.
PIP_LABEL = 0.1


def plot_pip(result, path=None):
    """Stem plot of every equation's PIPs with the selection threshold.

    One panel per equation; every term with PIP of at least `PIP_LABEL` is named (the
    selected ones in bold).

    **Arguments:**

    - `result`: an `UpdateResult`.
    - `path`: where to write the figure (PNG), or None (default) to write nothing.

    **Returns:** the matplotlib `Figure`.
    """
    eqs = result.equations
    fig = _figure((10, 2.6 * len(eqs)))
    axes = fig.subplots(len(eqs), 1, squeeze=False)
    for ax, eq in zip(axes[:, 0], eqs):
        pip = eq.pip
        k = np.arange(pip.size)
        ax.stem(k, pip, basefmt="k-")
        ax.axhline(result.pip_threshold, color="r", ls="-.", lw=1)
        for i in np.flatnonzero(pip >= PIP_LABEL):
            ax.annotate(eq.names[i], (i, pip[i]), textcoords="offset points", xytext=(4, 2), fontsize=8,
                        rotation=30, fontweight="bold" if eq.selected[i] else "normal")
        ax.set_ylim(0, 1.25)
        ax.set_xlim(-1, pip.size)
        ax.set_ylabel("PIP (-)")
        ax.set_title(f"{eq.state} ({eq.kind}): {int(eq.selected.sum())} of {pip.size} terms selected", fontsize=10)
    axes[-1, 0].set_xlabel("library term (index)")
    fig.tight_layout()
    return _save(fig, path)


def plot_noise_sweep(sweep, path=None):
    """The paper's Fig. 10 for a `SweepResult`.

    Against the noise level (% of each signal's std): (a) the relative error (%) of every true
    term's posterior mean, median over replicates with the min-max band, and (b) the support
    recovery rate (% of replicates whose every equation has exactly the true support).
    Framework 2's diffusion terms are drawn dashed.

    **Arguments:**

    - `sweep`: the `SweepResult` of `noise_sweep`.
    - `path`: where to write the figure (PNG), or None (default) to write nothing.

    **Returns:** the matplotlib `Figure`.
    """
    level = 100 * np.asarray(sweep.levels)
    fig = _figure((11, 4))
    ax_err, ax_sup = fig.subplots(1, 2)
    parts = [(sweep, "-", "")] + ([(sweep.diffusion, "--", "diffusion ")] if sweep.diffusion is not None else [])
    for part, ls, prefix in parts:
        for name, err in part.term_errors().items():
            err = 100 * err  # (L, Rp)
            line, = ax_err.plot(level, np.median(err, axis=1), ls, marker="o", ms=3, label=prefix + name)
            ax_err.fill_between(level, err.min(axis=1), err.max(axis=1), color=line.get_color(), alpha=0.2)
        ax_sup.plot(level, 100 * part.support_recovery, ls, marker="o", ms=3, label=prefix + "support" if prefix else "drift")
    ax_err.set_yscale("symlog", linthresh=0.1)
    ax_err.set_xlabel("noise level (% of signal std)")
    ax_err.set_ylabel("relative error of posterior mean (%)")
    ax_err.set_title(f"(a) {sweep.example}, {sweep.framework}: coefficient error "
                     f"(median, min-max of {sweep.replicates})", fontsize=9)
    ax_err.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.18), ncol=3, frameon=False)
    ax_sup.set_ylim(-3, 103)
    ax_sup.set_xlabel("noise level (% of signal std)")
    ax_sup.set_ylabel("exact support recovered (% of replicates)")
    ax_sup.set_title("(b) support recovery", fontsize=9)
    ax_sup.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.18), ncol=2, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def plot_prediction(prediction, truth=None, *, states=None, names=None, units=None, path=None, label="truth"):
    """Predicted mean and 95% band of each state against a measurement (the paper's Figs. 7-9).

    The measurement is black, the twin red with its band, and the legend sits above the plots;
    time is in s.

    **Arguments:**

    - `prediction`: the dict of `dtwin_jax.models.prediction.predict` (`t (N,)` s, and
      `mean`, `lower`, `upper`, each `(N, m)`).
    - `truth`: the measured or true states `(N, m)` at the same times, or None (default) to
      draw the twin alone.
    - `states`: the indices of the states to show, or None (default) for all.
    - `names`: one name per state of the model, or None (default) for `x1, x2, ...`.
    - `units`: one unit per state of the model, or None (default) for "state units".
    - `path`: where to write the figure (PNG), or None (default) to write nothing.
    - `label`: the legend's name for `truth` (default `"truth"`).

    **Returns:** the matplotlib `Figure`.
    """
    t = np.asarray(prediction["t"])
    mean, lower, upper = (np.asarray(prediction[k]) for k in ("mean", "lower", "upper"))
    states = range(mean.shape[1]) if states is None else states
    states = list(states)
    fig = _figure((10, 2.4 * len(states)))
    axes = fig.subplots(len(states), 1, squeeze=False, sharex=True)[:, 0]
    for ax, i in zip(axes, states):
        ax.fill_between(t, lower[:, i], upper[:, i], color="tab:red", alpha=0.3, lw=0, label="twin 95% band")
        if truth is not None:
            ax.plot(t, np.asarray(truth)[:, i], color="k", lw=0.9, label=label)
        ax.plot(t, mean[:, i], color="tab:red", lw=0.9, label="twin (mean)")
        unit = units[i] if units else "state units"
        ax.set_ylabel(f"{names[i] if names else f'x{i + 1}'} ({unit})")
    axes[0].legend(loc="lower left", bbox_to_anchor=(0.0, 1.02), fontsize=8, ncol=3, frameon=False)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    return _save(fig, path)


def plot_degradation(forecast, truth=None, path=None):
    """Damage forecast (mean, 95% band, truth) and the failure-probability curve with its 95% interval.

    **Arguments:**

    - `forecast`: the dict of `dtwin_jax.models.prediction.degradation_forecast` (`t (N,)` s,
      the damage's mean and band, `critical`, the failure probability and its interval).
    - `truth`: the true damage `(N,)` in state units at the same times, or None (default); when
      given, its first crossing of the critical level is marked.
    - `path`: where to write the figure (PNG), or None (default) to write nothing.

    **Returns:** the matplotlib `Figure`.
    """
    t = np.asarray(forecast["t"])
    fig = _figure((11, 4))
    ax_d, ax_p = fig.subplots(1, 2)
    ax_d.fill_between(t, forecast["damage_lower"], forecast["damage_upper"], color="tab:red", alpha=0.3, lw=0,
                      label="twin 95% band")
    if truth is not None:
        ax_d.plot(t, truth, color="k", lw=1, label="truth")
    ax_d.plot(t, forecast["damage_mean"], color="tab:red", lw=1, label="twin (mean)")
    ax_d.axhline(forecast["critical"], color="gray", ls=":", lw=1, label="critical level")
    ax_d.set_xlabel("time (s)")
    ax_d.set_ylabel("damage (state units)")
    ax_d.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.02), ncol=2, frameon=False)
    p = np.asarray(forecast["probability"])
    ax_p.fill_between(t, forecast["probability_lower"], forecast["probability_upper"], color="tab:orange",
                      alpha=0.3, lw=0, label="95% interval")
    ax_p.plot(t, p, color="tab:orange", lw=1.2, label="P(damage > critical by t)")
    if truth is not None:
        crossed = np.flatnonzero(np.asarray(truth) > forecast["critical"])
        if crossed.size:
            ax_p.axvline(t[crossed[0]], color="k", lw=1, label="true crossing")
    ax_p.set_ylim(-0.02, 1.02)
    ax_p.set_xlabel("time (s)")
    ax_p.set_ylabel("failure probability (-)")
    ax_p.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.02), ncol=2, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


# At most this many coefficient panels on a monitor plot (the terms selected longest).
MONITOR_PANELS = 6


def plot_monitor(timeline, path=None, *, false_alarm=None, remaining=None):
    """A monitor's timeline (`Monitor`) over service time.

    Panels: each window's p-value against the false-alarm rate, the PIPs of every term ever
    selected, and the coefficients (acceleration units) of the terms selected longest (at most
    `MONITOR_PANELS`), with their 95% interval; alarms are red vertical lines. The x-axis is
    the windows' `t_start` in s, or the window index where those do not increase.

    **Arguments:**

    - `timeline`: the monitor's windows, one dict each (`Monitor.timeline`).
    - `path`: where to write the figure (PNG), or None (default) to write nothing.
    - `false_alarm`: the false-alarm rate, drawn as a line on the p-value panel, or None
      (default) for no line.
    - `remaining`: `(term, track, rul)`, the tracked term's name, its `coefficient_track` and
      its `remaining_life` (`dtwin_jax.monitor.degradation`), which adds a last panel: the
      coefficient's window estimates, its trend and the failure time's interval; None
      (default) for no such panel.

    **Returns:** the matplotlib `Figure`.
    """
    from dtwin_jax.monitor.timeline import ever_selected

    ts = np.array([w["t_start"] for w in timeline], dtype=float)
    if ts.size < 2 or np.any(np.diff(ts) <= 0):  # windows from files that each start at 0
        ts, xlabel = np.array([w["index"] for w in timeline], dtype=float), "window"
    else:
        xlabel = "service time (s)"
    terms = ever_selected(timeline)
    rows = {term: _monitor_rows(timeline, term) for term in terms}
    longest = sorted(terms, key=lambda term: -np.sum(np.isfinite(rows[term][1])))[:MONITOR_PANELS]
    extra = remaining is not None
    fig = _figure((10, 2.2 * (2 + len(longest) + extra)))
    axes = fig.subplots(2 + len(longest) + extra, 1, squeeze=False, sharex=True)[:, 0]
    if extra:
        _remaining_panel(axes[-1], *remaining)
    p = np.array([w["p_value"] for w in timeline], dtype=float)
    axes[0].semilogy(ts, np.maximum(p, 1e-300), "o-", color="k", ms=3, lw=0.8, label="window p-value")
    if false_alarm is not None:
        axes[0].axhline(false_alarm, color="tab:red", ls="--", lw=1, label=f"false-alarm rate {false_alarm:g}")
    axes[0].set_ylabel("p-value (-)")
    axes[0].legend(loc="lower left", bbox_to_anchor=(0.0, 1.02), fontsize=8, ncol=3, frameon=False)
    for term in terms:
        axes[1].plot(ts, rows[term][0], lw=1, label=_term_label(term))
    axes[1].set_ylim(-0.02, 1.02)
    axes[1].set_ylabel("PIP (-)")
    if terms:
        axes[1].legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7, frameon=False)
    for ax, term in zip(axes[2:2 + len(longest)], longest):
        _, mean, lower, upper = rows[term]
        ax.fill_between(ts, lower, upper, color="tab:blue", alpha=0.3, lw=0, label="95% interval")
        ax.plot(ts, mean, "o-", color="tab:blue", ms=2.5, lw=0.8, label="posterior mean")
        ax.set_ylabel(f"{_term_label(term)}\n(acceleration units)", fontsize=8)
    for ax in axes[:2 + len(longest)]:
        for t_alarm in ts[[bool(w["alarm"]) for w in timeline]]:
            ax.axvline(t_alarm, color="tab:red", lw=0.8, alpha=0.7)
    axes[-1].set_xlabel(xlabel)
    fig.tight_layout()
    return _save(fig, path)


def _remaining_panel(ax, term, track, rul):
    """The tracked coefficient's window estimates (+-2 sd), its fitted line to the critical
    level and the failure time's interval."""
    t = np.asarray(track["t"])
    ax.errorbar(t, track["mean"], yerr=2 * np.asarray(track["sd"]), fmt="o", ms=3, color="k", lw=0.8,
                label="window estimate (+-2 sd)")
    end = rul["upper"] if np.isfinite(rul["upper"]) else t[-1] + 2 * (t[-1] - t[0])
    tt = np.linspace(t[0], max(end, t[-1]), 200)
    ax.plot(tt, np.polynomial.polynomial.polyval(tt - rul["now"], rul["line"]), color="tab:blue", lw=1, label="trend")
    ax.axhline(rul["critical"], color="tab:red", ls="--", lw=1, label="critical level")
    if np.isfinite(rul["lower"]):
        ax.axvspan(rul["lower"], end, color="tab:orange", alpha=0.25, lw=0, label="failure time (90% interval)")
    ax.axvline(rul["median"], color="tab:orange", lw=1)
    ax.set_ylabel(f"{term}\n(acceleration units)", fontsize=8)
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.02), fontsize=8, ncol=4, frameon=False)


def _term_label(term) -> str:
    state, kind, expr = term
    return f"{state}:{expr}" if kind == "drift" else f"{state} {kind}:{expr}"


def _monitor_rows(timeline, term):
    """`(pip, mean, lower, upper)` of `term` over the windows (NaN where not selected)."""
    state, kind, expr = term
    out = np.full((4, len(timeline)), np.nan)
    for i, w in enumerate(timeline):
        eq = next((e for e in w["equations"] if (e["state"], e["kind"]) == (state, kind)), None)
        if eq is None:
            continue
        out[0, i] = eq["pip"].get(expr, np.nan)
        hit = next((t for t in eq["terms"] if t["expr"] == expr), None)
        if hit:
            out[1:, i] = hit["mean"], *hit["hdi_95"]
    return out
